//! Real levels (issue 19): the third-party scenes in `scenes/third-party` (attribution in
//! its SOURCES.md) get lightmap UVs with every placed instance on its own texels, and the
//! import limits that bite real files: only the default scene is baked, per-node opt-out
//! and density, `KHR_mesh_quantization`, `KHR_texture_transform`, missing normals, a
//! texel density in texels per metre with as many pages as it needs, the albedo bound.

mod common;

use std::path::Path;

use glam::{Vec2, Vec3};
use lightmapd::engine::atlas::Atlas;
use lightmapd::engine::atlas::unwrap::{
    LightmapUvs, UvUnwrap, generate_lightmap_uvs, generate_lightmap_uvs_paged, generate_lightmap_uvs_with,
};
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder, remove_lightmap_uvs, write_glb};
use lightmapd::engine::scene::{ALBEDO_BOUND, DEFAULT_MATERIAL_ALBEDO, Scene, export, import_slice};
use serde_json::json;

fn level(name: &str) -> Scene {
    let bytes = std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scenes/third-party")
            .join(name),
    )
    .unwrap();
    import_slice(&bytes, None).unwrap().0
}

/// Texels per instance of `scene` in `atlas`.
fn texels_per_instance(scene: &Scene, atlas: &Atlas) -> Vec<usize> {
    let source = scene.source.as_ref().unwrap();
    let mut owner = vec![usize::MAX; scene.triangles.len()];
    for (k, inst) in source.instances.iter().enumerate() {
        for t in inst.triangles.clone() {
            owner[t] = k;
        }
    }
    let mut count = vec![0; source.instances.len()];
    for t in &atlas.texels {
        count[owner[t.triangle as usize]] += 1;
    }
    count
}

/// The FPS kit level: 7 meshes placed by 39 nodes. Each node gets its own rectangle, so
/// every instance owns texels and none overlaps another. Its 7 materials are all named
/// "colormap": the albedo warning tells them apart by index.
#[test]
fn kenney_instances_each_get_their_own_texels() {
    let bytes =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/third-party/kenney_fps_level.glb")).unwrap();
    let (_, report) = import_slice(&bytes, None).unwrap();
    let albedo: Vec<&String> = report.warnings.iter().filter(|w| w.starts_with("albedo")).collect();
    let each: Vec<String> = (0..7).map(|k| format!("colormap (material {k}) to 0.999")).collect();
    assert_eq!(
        albedo,
        [&format!(
            "albedo bounded for bounced light (so paths in closed rooms end): {}",
            each.join(", ")
        )]
    );
    let mut scene = level("kenney_fps_level.glb");
    let source = scene.source.clone().unwrap();
    assert_eq!(source.instances.len(), 39);
    let r = generate_lightmap_uvs(&mut scene, 512, &UvUnwrap).unwrap();
    assert_eq!((r.generated_meshes, r.kept_meshes, r.instances), (7, 0, 39), "{r:?}");
    let atlas = Atlas::build(&scene, 512, 512).unwrap();
    assert_eq!(atlas.overlapping_texels, 0);
    let per = texels_per_instance(&scene, &atlas);
    assert!(per.iter().all(|n| *n > 0), "an instance has no texel: {per:?}");
    // One layout per mesh: the 39 rectangles are all distinct.
    let layout = scene.layout.as_ref().unwrap();
    let rects: std::collections::HashSet<String> = layout
        .scale_offset
        .iter()
        .map(|s| format!("{:?}", s.unwrap()))
        .collect();
    assert_eq!(rects.len(), 39);
    eprintln!(
        "kenney: {r:?}, {} texels, per instance min {}",
        atlas.texels.len(),
        per.iter().min().unwrap()
    );
}

/// Many small charts in many instances fill a small page with padding, and the automatic
/// density collapses: the Kenney level at 256² is warned about, the grass named first;
/// opting the grass out, as the warning advises, gives the level several times the
/// density; the living room at 256² (23 % covered) is not warned about.
#[test]
fn a_page_filled_with_padding_is_warned_about() {
    let padding = |r: &lightmapd::engine::atlas::unwrap::UnwrapReport| -> Vec<String> {
        r.warnings
            .iter()
            .filter(|w| w.contains("the rest is padding"))
            .cloned()
            .collect()
    };
    let mut kenney = level("kenney_fps_level.glb");
    let r = generate_lightmap_uvs(&mut kenney, 256, &UvUnwrap).unwrap();
    let warned = padding(&r);
    assert_eq!(warned.len(), 1, "{:?}", r.warnings);
    assert!(
        warned[0].starts_with(&format!(
            "the generated charts cover 1 % of their 256x256 page at {:.2} texels/m: the rest is padding (3 texels around each of 221 charts",
            r.texels_per_metre
        )),
        "{}",
        warned[0]
    );
    assert!(
        warned[0].contains(
            "the meshes taking the most page for their surface: mesh 5 \"grass-small\" (5 instances: 21 % of the page for 0.2 % of the surface), mesh 4 \"grass\" (10 instances:"
        ),
        "{}",
        warned[0]
    );
    assert!(warned[0].ends_with("opt such detail meshes out with extras.lightmap: false (they still cast shadows)"));

    let bytes =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/third-party/kenney_fps_level.glb")).unwrap();
    let glb = gltf::binary::Glb::from_slice(&bytes).unwrap();
    let mut doc: serde_json::Value = serde_json::from_slice(&glb.json).unwrap();
    let grass: Vec<usize> = (0..doc["meshes"].as_array().unwrap().len())
        .filter(|&m| {
            doc["meshes"][m]["name"]
                .as_str()
                .is_some_and(|n| n.starts_with("grass"))
        })
        .collect();
    for node in doc["nodes"].as_array_mut().unwrap() {
        if node["mesh"].as_u64().is_some_and(|m| grass.contains(&(m as usize))) {
            node["extras"] = json!({"lightmap": false});
        }
    }
    let mut opted = import_slice(&write_glb(&doc, glb.bin.as_deref().unwrap()), None)
        .unwrap()
        .0;
    let o = generate_lightmap_uvs(&mut opted, 256, &UvUnwrap).unwrap();
    assert!(
        o.texels_per_metre > 2.5 * r.texels_per_metre,
        "grass opted out: {} texels/m against {}",
        o.texels_per_metre,
        r.texels_per_metre
    );

    let mut room = level("living_room.glb");
    let r = generate_lightmap_uvs(&mut room, 256, &UvUnwrap).unwrap();
    assert!(r.utilisation > 0.2, "{}", r.utilisation);
    assert!(padding(&r).is_empty(), "{:?}", r.warnings);
}

/// A texel density in texels per metre: a 4 m square at 8 texels/m spans 32 texels
/// (padding aside); a density too high for one page gives several pages stacked in one
/// taller page instead of an error.
/// Two upward grey squares, `a` of side `a` and `b` of side `b` beside it, as a .glb
/// without lightmap UVs.
fn two_squares_without_uvs(names: [&str; 2], a: f32, b: f32) -> Vec<u8> {
    let mut builder = SceneBuilder::new();
    let m = builder.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    builder.square(names[0], Vec3::ZERO, a, Vec3::Y, m);
    builder.square(names[1], Vec3::new(10.0, 0.0, 0.0), b, Vec3::Y, m);
    let (mut json, bin) = builder.to_gltf();
    remove_lightmap_uvs(&mut json, None);
    write_glb(&json, &bin)
}

/// Ten meshes scaled down to fit their pages make one warning, naming eight with the
/// density each got and counting the rest; two make one warning each (above).
#[test]
fn many_meshes_scaled_down_make_one_warning() {
    let mut builder = SceneBuilder::new();
    let m = builder.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    for k in 0..10 {
        builder.square(
            &format!("slab {k}"),
            Vec3::new(10.0 * k as f32, 0.0, 0.0),
            4.0,
            Vec3::Y,
            m,
        );
    }
    let (mut json, bin) = builder.to_gltf();
    remove_lightmap_uvs(&mut json, None);
    let (mut scene, _) = import_slice(&write_glb(&json, &bin), None).unwrap();
    let r = generate_lightmap_uvs_with(&mut scene, 256, LightmapUvs::GenerateMissing, Some(100.0), &UvUnwrap).unwrap();
    let scaled: Vec<&String> = r.warnings.iter().filter(|w| w.contains("scaled down")).collect();
    assert_eq!(scaled.len(), 1, "{:?}", r.warnings);
    let w = scaled[0];
    assert!(
        w.starts_with("10 meshes' charts were scaled down to fit a 256x") && w.contains("(mesh 0 \"slab 0\" at "),
        "{w}"
    );
    assert!(
        w.contains(" texels/m instead of 100.00; ") && w.contains("; and 2 more) (raise max_page_size"),
        "{w}"
    );
    assert!(!w.contains("slab 8"), "{w}");
}

#[test]
fn texels_per_unit_sets_the_density_and_adds_pages() {
    let glb = two_squares_without_uvs(["a", "b"], 4.0, 4.0);
    let (mut scene, _) = import_slice(&glb, None).unwrap();
    let r = generate_lightmap_uvs_with(&mut scene, 256, LightmapUvs::GenerateMissing, Some(8.0), &UvUnwrap).unwrap();
    assert_eq!(r.texels_per_metre, 8.0);
    assert!(
        r.warnings.iter().all(|w| !w.contains("scaled down")),
        "{:?}",
        r.warnings
    );
    let atlas = Atlas::build(&scene, r.width, r.height).unwrap();
    // Two 32 x 32 texel charts.
    let n = atlas.texels.len() as f32;
    assert!((n - 2.0 * 32.0 * 32.0).abs() <= 2.0 * 4.0 * 32.0, "{n} texels");
    assert_eq!(r.generated_pages, 1);

    // 100 texels/m: each square is 400 texels wide, more than a 256 page: each chart is
    // scaled down to fit a page, and the two take a page each.
    let (mut scene, _) = import_slice(&glb, None).unwrap();
    let r = generate_lightmap_uvs_with(&mut scene, 256, LightmapUvs::GenerateMissing, Some(100.0), &UvUnwrap).unwrap();
    eprintln!("{r:?}");
    assert_eq!((r.width, r.generated_pages), (256, 2), "{r:?}");
    assert_eq!(r.height, 512);
    let atlas = Atlas::build(&scene, r.width, r.height).unwrap();
    assert_eq!(atlas.overlapping_texels, 0);
    let per = texels_per_instance(&scene, &atlas);
    assert!(per.iter().all(|n| *n > 200 * 200), "{per:?}");
    // Both are named as scaled down, with the density they got.
    let scaled: Vec<&String> = r.warnings.iter().filter(|w| w.contains("scaled down")).collect();
    assert_eq!(scaled.len(), 2, "{:?}", r.warnings);
    assert!(
        scaled[0].starts_with("mesh 0 \"a\": its charts were scaled down to fit a 256x256 page, ")
            && scaled[0].contains(" texels/m instead of 100.00"),
        "{scaled:?}"
    );
    assert!(scaled[1].starts_with("mesh 1 \"b\": "), "{scaled:?}");

    // A small mesh beside a large one at that density: only the large one is named.
    let (mut scene, _) = import_slice(&two_squares_without_uvs(["large", "small"], 4.0, 0.5), None).unwrap();
    let r = generate_lightmap_uvs_with(&mut scene, 256, LightmapUvs::GenerateMissing, Some(100.0), &UvUnwrap).unwrap();
    let scaled: Vec<&String> = r.warnings.iter().filter(|w| w.contains("scaled down")).collect();
    assert_eq!(scaled.len(), 1, "{:?}", r.warnings);
    assert!(scaled[0].starts_with("mesh 0 \"large\": "), "{scaled:?}");

    // The Kenney level at 40 texels/m: an instanced mesh's charts make a layout taller
    // than a 256 page, which the unwrapper does not scale down; the density is lowered
    // until it fits, with a warning, instead of the bake failing.
    let mut kenney = level("kenney_fps_level.glb");
    let r = generate_lightmap_uvs_with(&mut kenney, 256, LightmapUvs::GenerateMissing, Some(40.0), &UvUnwrap).unwrap();
    let lowered: Vec<&String> = r.warnings.iter().filter(|w| w.contains("baked at")).collect();
    assert_eq!(lowered.len(), 1, "{:?}", r.warnings);
    assert!(
        lowered[0].starts_with("texels_per_unit 40: chart of ") && lowered[0].contains("doesn't fit a 256x256 page"),
        "{lowered:?}"
    );
    assert!(
        r.texels_per_metre < 40.0 && r.texels_per_metre >= 40.0 * 0.75f32.powi(8),
        "{r:?}"
    );
    assert!(
        lowered[0].contains(&format!("baked at {:.2} texels/m", r.texels_per_metre)),
        "{lowered:?}"
    );
    let atlas = Atlas::build(&kenney, r.width, r.height).unwrap();
    assert_eq!(atlas.overlapping_texels, 0);

    let (mut scene, _) = import_slice(&glb, None).unwrap();
    let e =
        generate_lightmap_uvs_with(&mut scene, 256, LightmapUvs::GenerateMissing, Some(-1.0), &UvUnwrap).unwrap_err();
    assert_eq!(e, "texels_per_unit must be a positive number, got -1");
}

/// `max_page_size` (issue 19 point 2): at a fixed density the page grows from
/// `resolution` (doubling) until the charts fit one page at the density asked, and only at
/// `max_page_size` do they take several pages.
#[test]
fn a_fixed_density_grows_the_page_before_adding_pages() {
    let glb = two_squares_without_uvs(["a", "b"], 4.0, 4.0);
    let squares = |max: u32| {
        let (mut scene, _) = import_slice(&glb, None).unwrap();
        let r = generate_lightmap_uvs_paged(
            &mut scene,
            256,
            max,
            LightmapUvs::GenerateMissing,
            Some(100.0),
            &UvUnwrap,
        )
        .unwrap();
        let atlas = Atlas::build(&scene, r.width, r.height).unwrap();
        assert_eq!(atlas.overlapping_texels, 0, "{r:?}");
        (r, texels_per_instance(&scene, &atlas))
    };
    // 100 texels/m: each 4 m square is a 400 x 400 chart. Up to 1024 wide, both fit one
    // page at the density asked: no chart is scaled down.
    let (r, per) = squares(4096);
    assert_eq!((r.width, r.height, r.generated_pages), (1024, 1024, 1), "{r:?}");
    assert_eq!(r.texels_per_metre, 100.0);
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    // Each square holds its 400 x 400 texels (a texel row more or less at each edge).
    assert!(per.iter().all(|n| n.abs_diff(400 * 400) <= 4 * 401), "{per:?}");
    // A 512 page holds one chart, not two: two 512 pages, still at 100 texels/m.
    let (r, per) = squares(512);
    assert_eq!((r.width, r.height, r.generated_pages), (512, 1024, 2), "{r:?}");
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    assert!(per.iter().all(|n| n.abs_diff(400 * 400) <= 4 * 401), "{per:?}");
    // At most 256: the old pages of `resolution`, each chart scaled down with a warning
    // (as texels_per_unit_sets_the_density_and_adds_pages measures).
    let (r, _) = squares(256);
    assert_eq!((r.width, r.generated_pages), (256, 2), "{r:?}");
    assert_eq!(r.warnings.iter().filter(|w| w.contains("scaled down")).count(), 2);
    // The automatic density keeps the page `resolution` wide, whatever the maximum.
    let (mut scene, _) = import_slice(&glb, None).unwrap();
    let r = generate_lightmap_uvs_paged(&mut scene, 256, 4096, LightmapUvs::GenerateMissing, None, &UvUnwrap).unwrap();
    assert_eq!((r.width, r.height), (256, 256), "{r:?}");

    // The Kenney level at 40 texels/m, which on 256-wide pages had its density lowered to
    // fit (texels_per_unit_sets_the_density_and_adds_pages): by default the page grows
    // and the density asked is the density baked.
    let mut kenney = level("kenney_fps_level.glb");
    let r = generate_lightmap_uvs_paged(
        &mut kenney,
        256,
        4096,
        LightmapUvs::GenerateMissing,
        Some(40.0),
        &UvUnwrap,
    )
    .unwrap();
    eprintln!("kenney at 40 texels/m: {r:?}");
    assert_eq!(r.texels_per_metre, 40.0, "{r:?}");
    assert!(r.warnings.iter().all(|w| !w.contains("baked at")), "{:?}", r.warnings);
    assert_eq!(r.generated_pages, 1, "{r:?}");
    assert!(r.width > 256 && r.width <= 4096, "{r:?}");
    let atlas = Atlas::build(&kenney, r.width, r.height).unwrap();
    assert_eq!(atlas.overlapping_texels, 0);

    // A maximum below the resolution names both.
    let (mut scene, _) = import_slice(&glb, None).unwrap();
    let e = generate_lightmap_uvs_paged(&mut scene, 256, 128, LightmapUvs::GenerateMissing, Some(8.0), &UvUnwrap)
        .unwrap_err();
    assert_eq!(
        e,
        "max_page_size 128 is below resolution 256: pages start resolution wide and grow up to max_page_size"
    );
}

/// Only the default scene is baked: a mesh no node uses, and a node in another scene,
/// add no triangle; `extras.lightmap: false` keeps a node's shadow but gives it no texel;
/// a node's `extras.lightmap_scale` scales its density.
#[test]
fn only_the_scene_is_baked_and_nodes_opt_out() {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("floor", Vec3::ZERO, 2.0, Vec3::Y, m);
    b.square("wall", Vec3::new(0.0, 1.0, -1.0), 2.0, Vec3::Z, m);
    b.square("dense", Vec3::new(4.0, 0.0, 0.0), 2.0, Vec3::Y, m);
    b.square("collider", Vec3::new(0.0, 5.0, 0.0), 2.0, Vec3::Y, m);
    let (mut json, bin) = b.to_gltf();
    remove_lightmap_uvs(&mut json, None);
    // Node 3 (collider) is in a second scene only; node 1 (wall) opts out; node 2 is dense.
    json["scenes"] = json!([{"nodes": [0, 1, 2]}, {"nodes": [3]}]);
    json["nodes"][1]["extras"] = json!({"lightmap": false, "editor": "keep me"});
    json["nodes"][2]["extras"] = json!({"lightmap_scale": 2.0});
    let glb = write_glb(&json, &bin);
    let (mut scene, _) = import_slice(&glb, None).unwrap();
    assert_eq!(scene.triangles.len(), 6, "the collider is not in the default scene");
    assert!(scene.triangles.iter().all(|t| t.mesh != 3));
    generate_lightmap_uvs(&mut scene, 128, &UvUnwrap).unwrap();
    let atlas = Atlas::build(&scene, 128, 128).unwrap();
    let per = texels_per_instance(&scene, &atlas);
    assert_eq!(per[1], 0, "the opted-out wall owns texels: {per:?}");
    let ratio = per[2] as f32 / per[0] as f32;
    assert!((ratio - 4.0).abs() < 0.5, "dense / plain texels {ratio}");
    // The wall still casts: it is in the triangle list, with no lightmap footprint.
    assert_eq!(scene.triangles.iter().filter(|t| t.mesh == 1).count(), 2);

    let out = export::to_glb(&scene).unwrap();
    let doc: serde_json::Value = serde_json::from_slice(&gltf::binary::Glb::from_slice(&out).unwrap().json).unwrap();
    assert_eq!(
        doc["nodes"][1]["extras"],
        json!({"lightmap": false, "editor": "keep me"})
    );
    assert!(
        doc["nodes"][3].get("extras").is_none(),
        "a node outside the scene got a lightmap"
    );
    assert_eq!(doc["nodes"][2]["extras"]["lightmap_scale"], 2.0);
    assert!(doc["nodes"][2]["extras"]["lightmap"]["scale_offset"].is_array());
}

/// `KHR_mesh_quantization`: u16 positions under a scaling node, i8 normalised normals;
/// no normals at all gives flat ones; a base colour `KHR_texture_transform` moves
/// TEXCOORD_0.
#[test]
fn quantized_positions_missing_normals_and_texture_transform() {
    let positions: [[u16; 4]; 4] = [[0, 0, 0, 0], [2, 0, 0, 0], [2, 0, 2, 0], [0, 0, 2, 0]];
    let normals: [[i8; 4]; 4] = [[0, 127, 0, 0]; 4];
    let uv0: [[f32; 2]; 4] = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    let indices: [u16; 6] = [0, 2, 1, 0, 3, 2];
    let mut bin = Vec::new();
    bin.extend(positions.iter().flatten().flat_map(|v| v.to_le_bytes()));
    bin.extend(normals.iter().flatten().map(|v| *v as u8));
    bin.extend(uv0.iter().flatten().flat_map(|v| v.to_le_bytes()));
    bin.extend(indices.iter().flat_map(|v| v.to_le_bytes()));
    let doc = |with_normals: bool| {
        let mut attributes = json!({"POSITION": 0, "TEXCOORD_0": 2});
        if with_normals {
            attributes["NORMAL"] = json!(1);
        }
        json!({
            "asset": {"version": "2.0"},
            "extensionsUsed": ["KHR_mesh_quantization", "KHR_texture_transform"],
            "extensionsRequired": ["KHR_mesh_quantization"],
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, "scale": [0.5, 0.5, 0.5]}],
            "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0,
                "extensions": {"KHR_texture_transform": {"offset": [0.5, 0.0], "scale": [0.5, 0.5]}}}}}],
            "meshes": [{"primitives": [{"attributes": attributes, "indices": 3, "material": 0}]}],
            "accessors": [
                {"bufferView": 0, "componentType": 5123, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [2, 0, 2]},
                {"bufferView": 1, "componentType": 5120, "normalized": true, "count": 4, "type": "VEC3"},
                {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"},
                {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}
            ],
            "bufferViews": [
                {"buffer": 0, "byteOffset": 0, "byteLength": 32, "byteStride": 8},
                {"buffer": 0, "byteOffset": 32, "byteLength": 16, "byteStride": 4},
                {"buffer": 0, "byteOffset": 48, "byteLength": 32},
                {"buffer": 0, "byteOffset": 80, "byteLength": 12}
            ],
            "buffers": [{"byteLength": 92}],
            "textures": [{"source": 0}],
            "images": [{"uri": "data:image/png;base64,iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8/5+hHgAHggJ/PchI7wAAAABJRU5ErkJggg=="}]
        })
    };
    for with_normals in [true, false] {
        let (scene, report) = import_slice(&write_glb(&doc(with_normals), &bin), None).unwrap();
        assert_eq!(scene.triangles.len(), 2);
        let world = |p: Vec3| p + scene.origin_offset.as_vec3();
        let (lo, hi) = scene.triangles.iter().flat_map(|t| t.p).fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(world(p)), hi.max(world(p))),
        );
        assert_eq!((lo, hi), (Vec3::ZERO, Vec3::new(1.0, 0.0, 1.0)), "u16 positions x 0.5");
        for t in &scene.triangles {
            assert!(t.n.iter().all(|n| (*n - Vec3::Y).length() < 1e-6), "{:?}", t.n);
            // uv' = 0.5 uv + (0.5, 0).
            for uv in t.uv {
                assert!(uv.x >= 0.5 && uv.x <= 1.0 && uv.y <= 0.5, "{uv}");
            }
        }
        let uvs: Vec<Vec2> = scene.triangles.iter().flat_map(|t| t.uv).collect();
        assert!(uvs.contains(&Vec2::new(1.0, 0.5)));
        // Both extensions are read: the report lists neither as unread or unsupported.
        assert!(
            !report
                .warnings
                .iter()
                .any(|w| w.contains("KHR_mesh_quantization") || w.contains("KHR_texture_transform")),
            "{:?}",
            report.warnings
        );
    }
}

/// glTF's default material (white) is bounded for bounced light, a file's albedo above
/// 0.999 too, and the report says so.
#[test]
fn albedo_is_bounded_and_reported() {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("snow", [1.0, 0.5, 0.99]));
    b.square("floor", Vec3::ZERO, 2.0, Vec3::Y, m);
    let (mut json, bin) = b.to_gltf();
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert_eq!(
        scene.materials[0].base_color.truncate(),
        Vec3::new(ALBEDO_BOUND, 0.5, 0.99)
    );
    assert_eq!((report.albedo_bound, report.default_material_albedo), (0.999, 0.8));
    assert_eq!(
        report
            .warnings
            .iter()
            .filter(|w| w.starts_with("albedo"))
            .collect::<Vec<_>>(),
        ["albedo bounded for bounced light (so paths in closed rooms end): snow to 0.999"]
    );
    json["meshes"][0]["primitives"][0]
        .as_object_mut()
        .unwrap()
        .remove("material");
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert!(report.default_material_used);
    assert_eq!(scene.triangles[0].material as usize, scene.materials.len() - 1);
    assert_eq!(
        scene.albedo(&scene.triangles[0], Vec3::splat(1.0 / 3.0)),
        Vec3::splat(DEFAULT_MATERIAL_ALBEDO)
    );
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.ends_with(": snow to 0.999, default to 0.8")),
        "{:?}",
        report.warnings
    );
}

/// `lightmap_uvs: repack-instances` (issue 19 point 3): one square mesh with authored
/// `TEXCOORD_1`, placed by three nodes (one of them scaled 2x). As authored, all three
/// address the same texels; repacked, each gets a rectangle of its own at one density (the
/// scaled one four times the texels), the mesh's `TEXCOORD_1` comes back byte for byte, and
/// the written file, read back with `keep`, addresses the same texels.
#[test]
fn repack_instances_gives_shared_authored_uvs_a_rectangle_each() {
    use std::sync::Arc;

    use lightmapd::engine::bake::StopCriteria;
    use lightmapd::engine::job::{self, BakeRequest};
    use lightmapd::engine::scene::library::upper_sky;

    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.5, 0.5, 0.5]));
    b.square("tile", Vec3::ZERO, 1.0, Vec3::Y, grey);
    let (mut doc, bin) = b.to_gltf();
    let nodes = doc["nodes"].as_array_mut().unwrap();
    nodes.push(json!({"name": "right", "mesh": 0, "translation": [3.0, 0.0, 0.0]}));
    nodes.push(json!({"name": "big", "mesh": 0, "translation": [-4.0, 0.0, 0.0], "scale": [2.0, 2.0, 2.0]}));
    doc["scenes"][0]["nodes"] = json!([0, 1, 2]);
    let input = write_glb(&doc, &bin);
    let (scene, report) = import_slice(&input, None).unwrap();
    assert!(
        report.warnings.iter().any(|w| w.contains("is placed by 3 nodes")
            && w.contains("lightmap_uvs: repack-instances gives each its own rectangle")),
        "{:?}",
        report.warnings
    );
    let request = |uvs: LightmapUvs| BakeRequest {
        resolution: 64,
        lightmap_uvs: uvs,
        lighting: upper_sky(1.0),
        stop: StopCriteria {
            steps: Some(2),
            ..Default::default()
        },
        params: json!({"samples_per_step": 4, "device": "cpu"}),
        ..Default::default()
    };
    // As authored: the three share one set of texels.
    let shared = job::bake_unobserved(Arc::new(scene.clone()), &request(LightmapUvs::GenerateMissing)).unwrap();
    assert!(shared.atlas.overlapping_texels > 0);

    let result = job::bake_unobserved(Arc::new(scene), &request(LightmapUvs::RepackInstances)).unwrap();
    let u = result.summary.generated_uvs.clone().expect("a layout was made");
    eprintln!("{u:?}");
    assert_eq!(
        (
            u.generated_meshes,
            u.kept_meshes,
            u.repacked_instances,
            u.repacked_pages
        ),
        (0, 1, 3, 1),
        "{u:?}"
    );
    assert_eq!((result.atlas.width, result.atlas.height), (64, 64));
    // The density is the same for all three: the 1 m square's rectangle is its UV box
    // (0.875 of the UV square) at S = density texels per unit of UV.
    assert!(u.texels_per_metre > 10.0 && u.utilisation > 0.25, "{u:?}");
    assert_eq!(result.atlas.overlapping_texels, 0);
    let per = texels_per_instance(&result.scene, &result.atlas);
    eprintln!("texels per instance: {per:?}");
    assert_eq!(per[0], per[1], "two instances of one size get the same rectangle");
    let ratio = per[2] as f64 / per[0] as f64;
    assert!((3.4..=4.6).contains(&ratio), "the 2x node has {ratio} times the texels");
    // The highest density that fits one page: the three rectangles use a fair share of it.
    assert!(per.iter().sum::<usize>() > 64 * 64 / 4, "{per:?}");
    // An open upward square under a uniform upper sky: E/π = 1 at every texel.
    for (k, v) in result.estimate.total.iter().enumerate() {
        assert!((*v - Vec3::ONE).abs().max_element() < 1e-3, "texel {k}: {v}");
    }

    // The written file: the mesh and its TEXCOORD_1 as they were, a rectangle per node.
    let glb = export::to_glb(&result.scene).unwrap();
    let out = gltf::binary::Glb::from_slice(&glb).unwrap();
    let written: serde_json::Value = serde_json::from_slice(&out.json).unwrap();
    let uv_bytes = |doc: &serde_json::Value, bin: &[u8]| -> Vec<u8> {
        let a = doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_1"]
            .as_u64()
            .unwrap() as usize;
        let acc = &doc["accessors"][a];
        let view = &doc["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
        let start =
            view["byteOffset"].as_u64().unwrap_or(0) as usize + acc["byteOffset"].as_u64().unwrap_or(0) as usize;
        bin[start..start + 8 * acc["count"].as_u64().unwrap() as usize].to_vec()
    };
    assert_eq!(uv_bytes(&doc, &bin), uv_bytes(&written, out.bin.as_ref().unwrap()));
    assert_eq!(written["meshes"].as_array().unwrap().len(), 1);
    let rects: std::collections::HashSet<String> = (0..3)
        .map(|n| {
            let l = &written["nodes"][n]["extras"]["lightmap"];
            assert_eq!(
                (l["page"].clone(), l["file"].clone()),
                (json!(0), json!("lightmap-0.exr"))
            );
            l["scale_offset"].to_string()
        })
        .collect();
    assert_eq!(rects.len(), 3, "{rects:?}");
    // Read back with `keep`: the same texels, none shared.
    let (back, _) = import_slice(&glb, None).unwrap();
    let again = job::bake_unobserved(
        Arc::new(back),
        &BakeRequest {
            stop: StopCriteria {
                steps: Some(1),
                ..Default::default()
            },
            ..request(LightmapUvs::Keep)
        },
    )
    .unwrap();
    assert_eq!(again.atlas.overlapping_texels, 0);
    assert_eq!(again.atlas.texels.len(), result.atlas.texels.len());
    for (a, b) in again.scene.triangles.iter().zip(&result.scene.triangles) {
        for k in 0..3 {
            assert!(
                (a.lm[k] - b.lm[k]).abs().max_element() < 1e-6,
                "{:?} vs {:?}",
                a.lm,
                b.lm
            );
        }
    }
}

/// Texel anisotropy of instance `k`: the area-weighted mean, over its triangles, of the
/// ratio of the largest to the smallest stretch from lightmap texels to world metres.
fn texel_anisotropy(scene: &Scene, width: u32, height: u32, k: usize) -> f64 {
    let inst = &scene.source.as_ref().unwrap().instances[k];
    let (mut sum, mut weight) = (0.0f64, 0.0f64);
    for t in &scene.triangles[inst.triangles.clone()] {
        let e = [(t.p[1] - t.p[0]).as_dvec3(), (t.p[2] - t.p[0]).as_dvec3()];
        let px = |v: Vec2| glam::DVec2::new(f64::from(v.x) * f64::from(width), f64::from(v.y) * f64::from(height));
        let d = glam::DMat2::from_cols(px(t.lm[1] - t.lm[0]), px(t.lm[2] - t.lm[0]));
        let area = 0.5 * e[0].cross(e[1]).length();
        if d.determinant().abs() < 1e-9 || area <= 0.0 {
            continue;
        }
        // J maps texel offsets to world offsets: J · d = e, J = E · D⁻¹ (3 x 2); its
        // singular values are the square roots of JᵀJ's eigenvalues.
        let inv = d.inverse();
        let j0 = e[0] * inv.x_axis.x + e[1] * inv.x_axis.y;
        let j1 = e[0] * inv.y_axis.x + e[1] * inv.y_axis.y;
        let (a, b, c) = (j0.dot(j0), j0.dot(j1), j1.dot(j1));
        let mid = 0.5 * (a + c);
        let r = (0.25 * (a - c) * (a - c) + b * b).sqrt();
        let ratio = ((mid + r) / (mid - r).max(1e-30)).sqrt();
        sum += ratio * area;
        weight += area;
    }
    sum / weight
}

/// An instance stretched past `OWN_LAYOUT_RATIO` gets a layout of its own (issue 19 point
/// 3): a sphere placed as it is, stretched 6x along x, and stretched the same way but
/// turned 90°. The two stretched nodes share one own layout (their shapes differ by a
/// rotation), unwrapped in the stretched shape, so their texels are about as square as the
/// plain sphere's; the written glTF carries a copy of the mesh for them.
#[test]
fn a_stretched_instance_gets_its_own_layout() {
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.5, 0.5, 0.5]));
    b.sphere("ball", Vec3::ZERO, 1.0, 24, 12, grey);
    let (mut doc, bin) = b.to_gltf();
    remove_lightmap_uvs(&mut doc, None);
    let nodes = doc["nodes"].as_array_mut().unwrap();
    nodes.push(json!({"name": "long", "mesh": 0, "translation": [0.0, 4.0, 0.0], "scale": [6.0, 1.0, 1.0]}));
    // Turned 90° about y: the same stretch, along z.
    let h = std::f32::consts::FRAC_1_SQRT_2;
    nodes.push(json!({"name": "long turned", "mesh": 0, "translation": [0.0, 8.0, 0.0], "rotation": [0.0, h, 0.0, h], "scale": [6.0, 1.0, 1.0]}));
    doc["scenes"][0]["nodes"] = json!([0, 1, 2]);
    let input = write_glb(&doc, &bin);
    let (mut scene, _) = import_slice(&input, None).unwrap();
    let r = generate_lightmap_uvs(&mut scene, 512, &UvUnwrap).unwrap();
    eprintln!("{r:?}");
    assert_eq!((r.generated_meshes, r.own_layouts, r.instances), (1, 1, 3), "{r:?}");
    assert_eq!(r.warnings.len(), 1, "{:?}", r.warnings);
    assert!(
        r.warnings[0].starts_with(
            "node 1 scales mesh 0 \"ball\" 6.0x more along one axis than another: it gets a lightmap layout of its own"
        ),
        "{:?}",
        r.warnings
    );
    let atlas = Atlas::build(&scene, r.width, r.height).unwrap();
    assert_eq!(atlas.overlapping_texels, 0);
    let aniso: Vec<f64> = (0..3).map(|k| texel_anisotropy(&scene, r.width, r.height, k)).collect();
    eprintln!("texel anisotropy per node: {aniso:?}");
    // Stretched nodes: about as square as the plain one (a shared layout would be ~6).
    assert!(aniso[1] < 1.6 * aniso[0] && aniso[2] < 1.6 * aniso[0], "{aniso:?}");
    // The density holds on all three: texels over world area within 25 % of each other.
    let per = texels_per_instance(&scene, &atlas);
    let area = |k: usize| -> f64 {
        let inst = &scene.source.as_ref().unwrap().instances[k];
        scene.triangles[inst.triangles.clone()]
            .iter()
            .map(|t| 0.5 * f64::from((t.p[1] - t.p[0]).cross(t.p[2] - t.p[0]).length()))
            .sum()
    };
    let density: Vec<f64> = (0..3).map(|k| per[k] as f64 / area(k)).collect();
    eprintln!("texels per m² per node: {density:?}");
    let (lo, hi) = density
        .iter()
        .fold((f64::MAX, 0.0f64), |(l, h), d| (l.min(*d), h.max(*d)));
    assert!(hi < 1.25 * lo, "{density:?}");

    // The written glTF: a copy of the mesh for the two stretched nodes.
    let glb = export::to_glb(&scene).unwrap();
    let out = gltf::binary::Glb::from_slice(&glb).unwrap();
    let written: serde_json::Value = serde_json::from_slice(&out.json).unwrap();
    assert_eq!(written["meshes"].as_array().unwrap().len(), 2);
    assert_eq!(written["meshes"][1]["name"], "ball (own lightmap layout 0)");
    let mesh_of = |n: usize| written["nodes"][n]["mesh"].as_u64().unwrap();
    assert_eq!((mesh_of(0), mesh_of(1), mesh_of(2)), (0, 1, 1));
    // lightmaps.json names the mesh the written file's node uses.
    let placed: Vec<usize> = scene.placements().iter().map(|p| p.mesh).collect();
    assert_eq!(placed, vec![0, 1, 1]);
    let path = std::env::temp_dir().join(format!("lightmapd-stretched-{}.glb", std::process::id()));
    std::fs::write(&path, &glb).unwrap();
    let v = common::validate_gltf(&path);
    std::fs::remove_file(&path).ok();
    assert_eq!(
        (v["errors"].as_u64(), v["warnings"].as_u64()),
        (Some(0), Some(0)),
        "{v}"
    );
    // Read back (now authored), it addresses the same texels.
    let (mut back, report) = import_slice(&glb, None).unwrap();
    assert!(report.has_lightmap_uvs);
    let again = generate_lightmap_uvs_with(&mut back, 512, LightmapUvs::Keep, None, &UvUnwrap).unwrap();
    assert_eq!((again.width, again.height), (r.width, r.height));
    for (a, b) in back.triangles.iter().zip(&scene.triangles) {
        for k in 0..3 {
            assert!(
                (a.lm[k] - b.lm[k]).abs().max_element() < 1e-6,
                "{:?} vs {:?}",
                a.lm,
                b.lm
            );
        }
    }
}
