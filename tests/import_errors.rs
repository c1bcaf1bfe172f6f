//! Every import error, from a deliberately broken file: each must be a specific error
//! that names the place (mesh, primitive, accessor, buffer), never a panic.

use glam::Vec3;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder, remove_lightmap_uvs, write_glb};
use lightmapd::engine::scene::{ImportError, import_file, import_slice};
use serde_json::{Value, json};

fn quad_scene() -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("Floor", Vec3::ZERO, 2.0, Vec3::Y, m);
    b
}

fn err_of(json: &Value, bin: &[u8]) -> String {
    match import_slice(&write_glb(json, bin), None) {
        Ok(_) => panic!("import should fail"),
        Err(e) => e.to_string(),
    }
}

/// Accessor index of `attribute` in mesh 0, primitive 0.
fn accessor(json: &Value, attribute: &str) -> usize {
    json["meshes"][0]["primitives"][0]["attributes"][attribute]
        .as_u64()
        .unwrap() as usize
}

/// Byte offset of accessor `a`'s data in the binary buffer.
fn data_offset(json: &Value, a: usize) -> usize {
    let view = json["accessors"][a]["bufferView"].as_u64().unwrap() as usize;
    json["bufferViews"][view]["byteOffset"].as_u64().unwrap() as usize
}

#[test]
fn not_gltf() {
    let e = import_slice(b"\x89PNG\r\n\x1a\n not a scene", None).unwrap_err();
    assert!(matches!(e, ImportError::NotGltf(_)), "{e}");
    assert!(e.to_string().contains("neither a GLB header"), "{e}");
    let e = import_slice(b"", None).unwrap_err();
    assert_eq!(e.to_string(), "not a glTF 2.0 file: the file is empty");
    let e = import_slice(b"{\"asset\": ", None).unwrap_err();
    assert!(matches!(e, ImportError::NotGltf(_)), "{e}");
}

#[test]
fn truncated_glb() {
    let glb = quad_scene().to_glb();
    let e = import_slice(&glb[..glb.len() - 40], None).unwrap_err();
    assert!(matches!(e, ImportError::NotGltf(_)), "{e}");
    assert!(e.to_string().contains("GLB"), "{e}");
}

#[test]
fn truncated_data_uri_buffer() {
    use base64::Engine as _;
    let (mut json, bin) = quad_scene().to_gltf();
    let short = base64::engine::general_purpose::STANDARD.encode(&bin[..bin.len() / 2]);
    json["buffers"][0]["uri"] = json!(format!("data:application/octet-stream;base64,{short}"));
    let text = serde_json::to_vec(&json).unwrap();
    let e = import_slice(&text, None).unwrap_err().to_string();
    assert!(e.starts_with("buffer 0: truncated: byteLength is"), "{e}");
}

#[test]
fn missing_external_buffer() {
    let dir = std::env::temp_dir().join(format!("lightmapd-missing-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (mut json, _) = quad_scene().to_gltf();
    json["buffers"][0]["uri"] = json!("scene.bin");
    let path = dir.join("scene.gltf");
    std::fs::write(&path, serde_json::to_vec(&json).unwrap()).unwrap();
    let e = import_file(&path).unwrap_err().to_string();
    assert!(
        e.starts_with("buffer 0: uri: cannot read external file \"scene.bin\""),
        "{e}"
    );
    // The same file sent without a folder (as the service receives it) says so.
    let e = import_slice(&std::fs::read(&path).unwrap(), None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("cannot be resolved here"), "{e}");
    // Paths must stay inside the scene's folder.
    json["buffers"][0]["uri"] = json!("../../etc/passwd");
    std::fs::write(&path, serde_json::to_vec(&json).unwrap()).unwrap();
    let e = import_file(&path).unwrap_err().to_string();
    assert!(e.contains("must be a relative path inside the scene's folder"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn external_buffer_is_read() {
    let dir = std::env::temp_dir().join(format!("lightmapd-external-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (mut json, bin) = quad_scene().to_gltf();
    json["buffers"][0]["uri"] = json!("quad%20data.bin");
    std::fs::write(dir.join("quad data.bin"), &bin).unwrap();
    std::fs::write(dir.join("quad.gltf"), serde_json::to_vec(&json).unwrap()).unwrap();
    let (scene, report) = import_file(&dir.join("quad.gltf")).unwrap();
    assert_eq!(scene.triangles.len(), 2);
    assert_eq!(report.triangles, 2);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn accessor_out_of_bounds() {
    let (mut json, bin) = quad_scene().to_gltf();
    let a = accessor(&json, "POSITION");
    json["accessors"][a]["count"] = json!(1000);
    let e = err_of(&json, &bin);
    assert!(
        e.starts_with(&format!(
            "mesh 0 \"Floor\", primitive 0: accessor {a} (POSITION): out of bounds: 1000 elements"
        )),
        "{e}"
    );
}

#[test]
fn buffer_view_outside_buffer() {
    let (mut json, bin) = quad_scene().to_gltf();
    let a = accessor(&json, "NORMAL");
    let view = json["accessors"][a]["bufferView"].as_u64().unwrap() as usize;
    json["bufferViews"][view]["byteOffset"] = json!(bin.len() - 8);
    let e = err_of(&json, &bin);
    assert!(
        e.contains(&format!("accessor {a} (NORMAL)")) && e.contains("lies outside buffer 0"),
        "{e}"
    );
}

#[test]
fn nan_and_infinite_positions() {
    for bad in [f32::NAN, f32::INFINITY] {
        let (json, mut bin) = quad_scene().to_gltf();
        let a = accessor(&json, "POSITION");
        let off = data_offset(&json, a) + 12 * 2 + 4; // vertex 2, y
        bin[off..off + 4].copy_from_slice(&bad.to_le_bytes());
        let e = err_of(&json, &bin);
        assert!(
            e.starts_with(&format!(
                "mesh 0 \"Floor\", primitive 0: accessor {a} (POSITION): element 2 is not finite"
            )),
            "{e}"
        );
    }
}

#[test]
fn nan_lightmap_uv() {
    let (json, mut bin) = quad_scene().to_gltf();
    let a = accessor(&json, "TEXCOORD_1");
    let off = data_offset(&json, a) + 8; // vertex 1, u
    bin[off..off + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = err_of(&json, &bin);
    assert!(
        e.contains(&format!("accessor {a} (TEXCOORD_1): element 1 is not finite")),
        "{e}"
    );
}

#[test]
fn lightmap_uv_outside_unit_square() {
    let (json, mut bin) = quad_scene().to_gltf();
    let a = accessor(&json, "TEXCOORD_1");
    let off = data_offset(&json, a) + 8 * 3 + 4; // vertex 3, v
    bin[off..off + 4].copy_from_slice(&1.25f32.to_le_bytes());
    let e = err_of(&json, &bin);
    assert!(
        e.contains(&format!("accessor {a} (TEXCOORD_1): lightmap UV")) && e.contains("of vertex 3 is outside [0, 1]"),
        "{e}"
    );
}

#[test]
fn no_lightmap_uvs_is_reported_not_refused() {
    let (mut json, bin) = quad_scene().to_gltf();
    remove_lightmap_uvs(&mut json, Some(&[0]));
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert!(!report.has_lightmap_uvs);
    assert!(scene.needs_lightmap_uvs);
    assert_eq!(
        report.warnings,
        vec![
            "mesh 0 \"Floor\", primitive 0 has no TEXCOORD_1: lightmap UVs will be generated for the meshes without \
             them, authored ones are kept (bake --write-gltf saves them)"
                .to_string()
        ]
    );
}

/// `n` unit squares in a row, mesh k named "{name} k": all of one grey material, or with
/// `own`, each of a material of its own named as its mesh, of albedo `own`.
fn row_of_squares(n: usize, name: &str, own: Option<[f32; 3]>) -> (Value, Vec<u8>) {
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    for k in 0..n {
        let label = format!("{name} {k}");
        let m = own.map_or(grey, |albedo| b.material(MaterialDesc::diffuse(&label, albedo)));
        b.square(&label, Vec3::new(k as f32 * 2.0, 0.0, 0.0), 1.0, Vec3::Y, m);
    }
    b.to_gltf()
}

/// A level of many meshes without lightmap UVs gets one warning that names the first eight
/// and counts the rest, not one name a mesh.
#[test]
fn many_meshes_without_lightmap_uvs_are_counted_not_listed() {
    let (mut json, bin) = row_of_squares(20, "tile", None);
    remove_lightmap_uvs(&mut json, None);
    let (_, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    let warning = report
        .warnings
        .iter()
        .find(|w| w.contains("TEXCOORD_1"))
        .expect("a warning about the missing lightmap UVs");
    assert!(
        warning.starts_with("20 primitives (mesh 0 \"tile 0\", primitive 0; mesh 1 \"tile 1\", primitive 0; "),
        "{warning}"
    );
    assert!(
        warning.contains(
            "mesh 7 \"tile 7\", primitive 0; and 12 more) have no TEXCOORD_1: lightmap UVs will be generated"
        ),
        "{warning}"
    );
    assert!(!warning.contains("tile 8"), "{warning}");
}

/// A few meshes without lightmap UVs are all named ("have"); many materials bounded are
/// counted past the eighth.
#[test]
fn short_lists_are_named_and_long_ones_counted() {
    let (mut json, bin) = row_of_squares(10, "white", Some([1.0; 3]));
    remove_lightmap_uvs(&mut json, Some(&[2, 5]));
    let (_, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    let find = |what: &str| {
        report
            .warnings
            .iter()
            .find(|w| w.contains(what))
            .unwrap_or_else(|| panic!("no warning about {what}: {:?}", report.warnings))
            .clone()
    };
    assert!(
        find("TEXCOORD_1").starts_with(
            "mesh 2 \"white 2\", primitive 0; mesh 5 \"white 5\", primitive 0 have no TEXCOORD_1: lightmap UVs"
        ),
        "{:?}",
        report.warnings
    );
    let albedo = find("albedo bounded");
    assert!(albedo.contains("white 0 to "), "{albedo}");
    assert!(
        albedo.contains("white 7 to ") && albedo.ends_with(", and 2 more"),
        "{albedo}"
    );
    assert!(!albedo.contains("white 8"), "{albedo}");
}

/// Malformed fields repeated on every node, mesh or primitive of a level (an exporter's
/// mistake) make one warning a kind that names the first eight items and counts the rest;
/// two items of a kind keep a line each, and every bad value is still replaced.
#[test]
fn malformed_items_make_one_warning_a_kind() {
    let (mut json, bin) = row_of_squares(10, "tile", None);
    for k in 0..10 {
        json["nodes"][k]["extras"] = json!({"lightmap_scale": -1, "lightmap": {"page": "one"}});
        json["meshes"][k]["extras"] = json!({"lightmap_scale": 0});
        let triangles = json["meshes"][k]["primitives"][0].clone();
        let mut lines = triangles.clone();
        lines["mode"] = json!(1);
        json["meshes"][k]["primitives"] = json!([triangles, lines]);
    }
    json["nodes"][3]["extras"]["lightmap"]["scale_offset"] = json!([0, 1, 0, 0]);
    json["nodes"][4]["extras"]["lightmap"]["scale_offset"] = json!([1, 1]);
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    let eight = |each: &dyn Fn(usize) -> String| (0..8).map(each).collect::<Vec<_>>().join("; ") + "; and 2 more";
    assert_eq!(
        report.warnings,
        [
            format!(
                "10 meshes' extras.lightmap_scale are not numbers in (0, 1000]; using 1 ({})",
                eight(&|k| format!("mesh {k} \"tile {k}\" (0)"))
            ),
            format!(
                "10 nodes' extras.lightmap_scale are not numbers in (0, 1000]; using 1 ({})",
                eight(&|k| format!("node {k} \"tile {k}\" (-1)"))
            ),
            format!(
                "10 nodes' extras.lightmap.page are not page numbers below 256; page 0 used ({})",
                eight(&|k| format!("node {k} \"tile {k}\" (\"one\")"))
            ),
            format!(
                "10 primitives are not TRIANGLES and are skipped ({})",
                eight(&|k| format!("mesh {k} \"tile {k}\", primitive 1 (Lines)"))
            ),
            "node 3 \"tile 3\": extras.lightmap.scale_offset is not four finite numbers with positive scales; ignored"
                .to_string(),
            "node 4 \"tile 4\": extras.lightmap.scale_offset is not four finite numbers with positive scales; ignored"
                .to_string(),
        ]
    );
    assert!(scene.meshes.iter().all(|m| m.lightmap_scale == 1.0));
    assert_eq!(scene.triangles.len(), 20, "the lines are skipped, the squares kept");
}

/// Many instanced meshes with authored lightmap UVs: one warning, the first eight named
/// with their node counts, the rest counted.
#[test]
fn many_shared_authored_meshes_make_one_warning() {
    let (mut doc, bin) = row_of_squares(10, "prop", None);
    let nodes = doc["nodes"].as_array_mut().unwrap();
    let placed = nodes.len();
    for k in 0..10 {
        nodes.push(json!({"mesh": k, "translation": [k as f32 * 2.0, 0.0, 5.0]}));
    }
    doc["scenes"][0]["nodes"] = json!((0..placed + 10).collect::<Vec<_>>());
    let (_, report) = import_slice(&write_glb(&doc, &bin), None).unwrap();
    let shared: Vec<&String> = report.warnings.iter().filter(|w| w.contains("share texels")).collect();
    assert_eq!(shared.len(), 1, "{:?}", report.warnings);
    assert!(
        shared[0].starts_with(
            "10 meshes with authored TEXCOORD_1 are placed by several nodes (mesh 0 \"prop 0\" by 2; mesh 1 \"prop 1\" by 2; "
        ) && shared[0].contains("mesh 7 \"prop 7\" by 2; and 2 more): unless their extras.lightmap.scale_offset differ"),
        "{}",
        shared[0]
    );
}

#[test]
fn no_triangles() {
    let (mut json, bin) = quad_scene().to_gltf();
    json["meshes"][0]["primitives"][0]["mode"] = json!(0); // POINTS
    let e = err_of(&json, &bin);
    assert_eq!(e, "the scene has no triangles to bake");

    // All triangles degenerate: said so.
    let (json, mut bin) = quad_scene().to_gltf();
    let a = accessor(&json, "POSITION");
    let off = data_offset(&json, a);
    for v in 0..4 {
        bin[off + 12 * v..off + 12 * v + 12].copy_from_slice(bytemuck::cast_slice(&[1.0f32, 2.0, 3.0]));
    }
    let e = err_of(&json, &bin);
    assert_eq!(e, "the scene has no triangles to bake (all 2 triangles are degenerate)");
}

#[test]
fn degenerate_triangles_are_dropped_and_counted() {
    let (mut json, mut bin) = quad_scene().to_gltf();
    // Append a third triangle (0, 0, 1): zero area.
    let idx = json["meshes"][0]["primitives"][0]["indices"].as_u64().unwrap() as usize;
    let view = json["accessors"][idx]["bufferView"].as_u64().unwrap() as usize;
    assert_eq!(
        json["bufferViews"][view]["byteOffset"].as_u64().unwrap() as usize + 24,
        bin.len(),
        "indices are last"
    );
    bin.extend_from_slice(bytemuck::cast_slice(&[0u32, 0, 1]));
    json["bufferViews"][view]["byteLength"] = json!(36);
    json["accessors"][idx]["count"] = json!(9);
    json["buffers"][0]["byteLength"] = json!(bin.len());
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert_eq!(scene.triangles.len(), 2);
    assert_eq!(report.degenerate_triangles, 1);
    assert_eq!(report.triangles, 2);
}

#[test]
fn index_past_the_vertices() {
    let (json, mut bin) = quad_scene().to_gltf();
    let n = bin.len();
    bin[n - 4..].copy_from_slice(&7u32.to_le_bytes());
    let e = err_of(&json, &bin);
    assert!(
        e.contains("(indices): index 7 at position 5 is past the 4 vertices"),
        "{e}"
    );
}

#[test]
fn non_triangle_modes_are_named_in_a_warning() {
    let (mut json, bin) = quad_scene().to_gltf();
    let prim = json["meshes"][0]["primitives"][0].clone();
    let mut lines = prim.clone();
    lines["mode"] = json!(1);
    json["meshes"][0]["primitives"] = json!([prim, lines]);
    let (_, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert_eq!(
        report.warnings,
        vec!["mesh 0 \"Floor\", primitive 1: mode Lines is not TRIANGLES and is skipped".to_string()]
    );
}

#[test]
fn mirrored_node_keeps_front_faces_in_front() {
    let (mut json, bin) = quad_scene().to_gltf();
    json["nodes"][0]["scale"] = json!([-1.0, 1.0, 1.0]);
    let (scene, _) = import_slice(&write_glb(&json, &bin), None).unwrap();
    for t in &scene.triangles {
        assert!(
            (t.geometric_normal() - Vec3::Y).length() < 1e-6,
            "{}",
            t.geometric_normal()
        );
        assert!((t.n[0] - Vec3::Y).length() < 1e-6);
    }
}

#[test]
fn node_hierarchy_transforms_compose() {
    let (mut json, bin) = quad_scene().to_gltf();
    // Parent translates by (10, 0, 0) and scales by 2; child is the quad, moved up 1.
    json["nodes"][0]["translation"] = json!([0.0, 1.0, 0.0]);
    json["nodes"]
        .as_array_mut()
        .unwrap()
        .push(json!({"children": [0], "translation": [10.0, 0.0, 0.0], "scale": [2.0, 2.0, 2.0]}));
    json["scenes"][0]["nodes"] = json!([1]);
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    // World y = 2 * 1 = 2, x in 10 + 2 * [-1, 1].
    assert_eq!(report.bounds_min, [8.0, 2.0, -2.0]);
    assert_eq!(report.bounds_max, [12.0, 2.0, 2.0]);
    assert!((scene.origin_offset.x - 10.0).abs() < 1e-12);
}

#[test]
fn emissive_strength_and_lights_are_read() {
    let mut b = quad_scene();
    let lamp = b.material(MaterialDesc::emissive("lamp", [1.0; 3], [40.0, 20.0, 10.0]));
    b.square("panel", Vec3::new(0.0, 2.0, 0.0), 0.5, Vec3::NEG_Y, lamp);
    b.light(lightmapd::engine::scene::build::LightDesc::Spot {
        position: Vec3::new(0.0, 3.0, 0.0),
        direction: Vec3::NEG_Y,
        color: [1.0, 0.5, 0.25],
        intensity: 8.0,
        inner: 0.2,
        outer: 0.5,
    });
    let (scene, report) = import_slice(&b.to_glb(), None).unwrap();
    assert_eq!(report.lights, 1);
    assert_eq!(report.emissive_triangles, 2);
    let l = &scene.lights[0];
    assert!((l.intensity - Vec3::new(8.0, 4.0, 2.0)).length() < 1e-5);
    assert!((l.direction - Vec3::NEG_Y).length() < 1e-5);
    let m = scene.materials.iter().find(|m| m.name == "lamp").unwrap();
    assert!(
        (m.emissive - Vec3::new(40.0, 20.0, 10.0)).length() < 1e-4,
        "{}",
        m.emissive
    );
}
