//! The written glTF is the input level with lightmap UVs added (issue 19, point 6), on
//! the three third-party levels in `scenes/third-party` (attribution in its SOURCES.md):
//! same nodes (names, hierarchy, transforms), meshes shared as before, primitives with
//! their materials, samplers, textures and images byte for byte, extensions kept; every
//! node of the scene with a mesh carries `extras.lightmap`; re-importing the file gives
//! the baked triangles and lightmap UVs back; the Khronos validator finds no error.

mod common;

use std::path::{Path, PathBuf};

use lightmapd::engine::atlas::Atlas;
use lightmapd::engine::atlas::unwrap::{UvUnwrap, generate_lightmap_uvs};
use lightmapd::engine::scene::{export, import_slice};
use serde_json::Value;

fn level(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes/third-party")
        .join(name)
}

/// JSON and binary chunk of a GLB.
fn parse(bytes: &[u8]) -> (Value, Vec<u8>) {
    let glb = gltf::binary::Glb::from_slice(bytes).expect("a GLB");
    (
        serde_json::from_slice(&glb.json).expect("JSON chunk"),
        glb.bin.map(|b| b.into_owned()).unwrap_or_default(),
    )
}

fn len(v: &Value, key: &str) -> usize {
    v[key].as_array().map_or(0, Vec::len)
}

/// The bytes of accessor `a` element by element (stride removed).
fn accessor_bytes(doc: &Value, bin: &[u8], a: usize) -> Vec<u8> {
    let acc = &doc["accessors"][a];
    let view = &doc["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
    let size = match acc["componentType"].as_u64().unwrap() {
        5120 | 5121 => 1,
        5122 | 5123 => 2,
        _ => 4,
    } * match acc["type"].as_str().unwrap() {
        "SCALAR" => 1,
        "VEC2" => 2,
        "VEC3" => 3,
        _ => 4,
    };
    let stride = view["byteStride"].as_u64().map_or(size, |s| s as usize);
    let start = view["byteOffset"].as_u64().unwrap_or(0) as usize + acc["byteOffset"].as_u64().unwrap_or(0) as usize;
    (0..acc["count"].as_u64().unwrap() as usize)
        .flat_map(|i| bin[start + i * stride..start + i * stride + size].to_vec())
        .collect()
}

fn image_bytes(doc: &Value, bin: &[u8], i: usize) -> Vec<u8> {
    let view = &doc["bufferViews"][doc["images"][i]["bufferView"].as_u64().unwrap() as usize];
    let start = view["byteOffset"].as_u64().unwrap_or(0) as usize;
    bin[start..start + view["byteLength"].as_u64().unwrap() as usize].to_vec()
}

fn roundtrip(name: &str, resolution: u32) {
    let input = std::fs::read(level(name)).unwrap();
    let (mut scene, report) = import_slice(&input, None).unwrap();
    assert!(!report.has_lightmap_uvs, "{name} has no TEXCOORD_1");
    let unwrap = generate_lightmap_uvs(&mut scene, resolution, &UvUnwrap).unwrap();
    eprintln!("{name}: {unwrap:?}");
    let layout = scene.layout.clone().unwrap();
    let atlas = Atlas::build(&scene, layout.width, layout.height).unwrap();
    assert_eq!(atlas.overlapping_texels, 0, "{name}: generated charts overlap");

    let glb = export::to_glb(&scene).unwrap();
    let (a, abin) = parse(&input);
    let (b, bbin) = parse(&glb);

    // The same document, only with lightmap UVs added.
    for key in [
        "nodes",
        "meshes",
        "materials",
        "textures",
        "samplers",
        "images",
        "scenes",
    ] {
        assert_eq!(len(&a, key), len(&b, key), "{name}: number of {key}");
    }
    for key in [
        "materials",
        "textures",
        "samplers",
        "scenes",
        "extensionsUsed",
        "extensionsRequired",
        "asset",
    ] {
        assert_eq!(a[key], b[key], "{name}: {key} differ");
    }
    assert_eq!(a["scene"], b["scene"]);
    for (i, (na, nb)) in a["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .zip(b["nodes"].as_array().unwrap())
        .enumerate()
    {
        for key in [
            "name",
            "mesh",
            "children",
            "translation",
            "rotation",
            "scale",
            "matrix",
            "extensions",
            "camera",
        ] {
            assert_eq!(na[key], nb[key], "{name}: node {i} {key}");
        }
    }
    for i in 0..len(&a, "images") {
        assert_eq!(
            image_bytes(&a, &abin, i),
            image_bytes(&b, &bbin, i),
            "{name}: image {i} re-encoded"
        );
    }
    let mut placed = std::collections::HashSet::new();
    for inst in &scene.source.as_ref().unwrap().instances {
        placed.insert(inst.node);
    }
    for (m, (ma, mb)) in a["meshes"]
        .as_array()
        .unwrap()
        .iter()
        .zip(b["meshes"].as_array().unwrap())
        .enumerate()
    {
        assert_eq!(ma["name"], mb["name"]);
        let (pa, pb) = (
            ma["primitives"].as_array().unwrap(),
            mb["primitives"].as_array().unwrap(),
        );
        assert_eq!(pa.len(), pb.len(), "{name}: mesh {m} primitives");
        for (p, (x, y)) in pa.iter().zip(pb).enumerate() {
            assert_eq!(x["material"], y["material"], "{name}: mesh {m} primitive {p} material");
            assert_eq!(x["mode"], y["mode"]);
            for semantic in x["attributes"].as_object().unwrap().keys() {
                assert!(
                    y["attributes"].get(semantic).is_some(),
                    "{name}: mesh {m} lost {semantic}"
                );
            }
            assert!(
                y["attributes"].get("TEXCOORD_1").is_some(),
                "{name}: mesh {m} has no TEXCOORD_1"
            );
        }
    }
    for (i, node) in b["nodes"].as_array().unwrap().iter().enumerate() {
        let lm = &node["extras"]["lightmap"];
        if !placed.contains(&i) {
            assert!(lm.is_null(), "{name}: node {i} is not in the scene but has a lightmap");
            continue;
        }
        assert_eq!(lm["page"], 0);
        assert_eq!(lm["file"], "lightmap-0.exr");
        let so: Vec<f64> = lm["scale_offset"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(so.len(), 4);
        assert!(
            so[0] > 0.0 && so[1] > 0.0 && so[0] + so[2] <= 1.0 + 1e-6 && so[1] + so[3] <= 1.0 + 1e-6,
            "{so:?}"
        );
        // Other extras stay.
        for (k, v) in a["nodes"][i]["extras"].as_object().into_iter().flatten() {
            assert_eq!(&node["extras"][k], v);
        }
    }

    // Re-imported: the same triangles at the same places with the same lightmap UVs.
    let (back, back_report) = import_slice(&glb, None).unwrap();
    assert!(back_report.has_lightmap_uvs);
    assert_eq!(back_report.meshes, report.meshes);
    assert_eq!(back_report.materials, report.materials);
    assert_eq!(back.triangles.len(), scene.triangles.len(), "{name}");
    for (x, y) in back.triangles.iter().zip(&scene.triangles) {
        assert_eq!(x.material, y.material);
        for k in 0..3 {
            assert!(
                (x.lm[k] - y.lm[k]).abs().max_element() < 1e-6,
                "{name}: {} vs {}",
                x.lm[k],
                y.lm[k]
            );
            let (pa, pb) = (
                x.p[k].as_dvec3() + back.origin_offset,
                y.p[k].as_dvec3() + scene.origin_offset,
            );
            assert!((pa - pb).abs().max_element() < 1e-4, "{name}: {pa} vs {pb}");
        }
    }
    // Once more: a file whose UVs are all authored is written with them unchanged.
    let again = export::to_glb(&back).unwrap();
    let (c, cbin) = parse(&again);
    for (m, mesh) in b["meshes"].as_array().unwrap().iter().enumerate() {
        for (p, prim) in mesh["primitives"].as_array().unwrap().iter().enumerate() {
            let (ua, ub) = (
                prim["attributes"]["TEXCOORD_1"].as_u64().unwrap() as usize,
                c["meshes"][m]["primitives"][p]["attributes"]["TEXCOORD_1"]
                    .as_u64()
                    .unwrap() as usize,
            );
            assert_eq!(
                accessor_bytes(&b, &bbin, ua),
                accessor_bytes(&c, &cbin, ub),
                "authored UVs changed"
            );
        }
    }
    for (i, node) in b["nodes"].as_array().unwrap().iter().enumerate() {
        assert_eq!(node["extras"], c["nodes"][i]["extras"], "{name}: node {i} extras");
    }

    let dir = std::env::temp_dir().join(format!("lightmapd-roundtrip-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, &glb).unwrap();
    let v = common::validate_gltf(&path);
    eprintln!("validator: {v}");
    assert_eq!(v["errors"], 0, "{name}: {v}");
    assert_eq!(v["warnings"], 0, "{name}: {v}");
    // No unused object the input did not have, but the lightmap UVs themselves (no
    // material samples TEXCOORD_1, so the validator calls each "possibly unused"): the
    // accessors and views the split primitives left behind are removed
    // (`scene::export::prune_orphans`; before, 35, 42 and 70 more infos than the input).
    let before = common::validate_gltf(&level(name));
    let had: Vec<&str> = before["unused"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect();
    let new: Vec<&str> = v["unused"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .filter(|p| !had.contains(p) && !p.ends_with("/attributes/TEXCOORD_1"))
        .collect();
    assert!(new.is_empty(), "{name}: unused objects the input did not have: {new:?}");
}

#[test]
fn living_room_comes_back_whole() {
    roundtrip("living_room.glb", 512);
}

#[test]
fn kenney_fps_level_comes_back_whole() {
    roundtrip("kenney_fps_level.glb", 512);
}

#[test]
fn occlusion_room_comes_back_whole() {
    roundtrip("occlusion_room.glb", 512);
}
