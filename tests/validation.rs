//! The validation report flags a crafted scene with overlapping charts and texels inside
//! a closed box, in the bake summary and as debug EXR layers (issue 13).

use std::sync::Arc;

use exr::prelude::{ReadChannels, ReadLayers};
use glam::Vec3;
use lightmapd::engine::bake::StopCriteria;
use lightmapd::engine::job::{self, BakeRequest};
use lightmapd::engine::output::OutputLayer;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder, write_glb};
use lightmapd::engine::scene::{Hemisphere, Lighting, Sky, import_slice};
use serde_json::json;

#[test]
fn overlap_and_inside_texels_are_reported_and_shown() {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("floor", Vec3::ZERO, 4.0, Vec3::Y, m);
    b.block("crate", Vec3::ZERO, Vec3::splat(0.5), 0.0, m);
    let (mut json, bin) = b.to_gltf();
    // A second instance of the floor on the same chart: overlapping lightmap UVs.
    json["nodes"]
        .as_array_mut()
        .unwrap()
        .push(json!({"mesh": 0, "translation": [0.0, -3.0, 0.0]}));
    let n = json["nodes"].as_array().unwrap().len();
    json["scenes"][0]["nodes"] = json!((0..n).collect::<Vec<_>>());
    let scene = Arc::new(import_slice(&write_glb(&json, &bin), None).unwrap().0);
    let request = BakeRequest {
        resolution: 64,
        lighting: Lighting {
            sky: Some(Sky {
                radiance: Vec3::ONE,
                hemisphere: Hemisphere::Upper,
            }),
            sun: None,
        },
        stop: StopCriteria {
            steps: Some(2),
            ..Default::default()
        },
        outputs: vec![OutputLayer::Debug, OutputLayer::Validity],
        ..Default::default()
    };
    let result = job::bake_unobserved(scene, &request).unwrap();
    let v = &result.summary.validation;
    eprintln!("{v:?}");
    assert!(v.inside_geometry_texels > 0, "texels under the crate are inside it");
    assert!(v.overlapping_texels > 0, "the floor's two instances share texels");
    assert!(v.warnings.iter().any(|w| w.contains("overlap")));
    assert!(v.warnings.iter().any(|w| w.contains("inside closed geometry")));

    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(result.first_page().to_vec()))
        .unwrap();
    let count = |name: &str| {
        let c = image.layer_data[0]
            .channel_data
            .list
            .iter()
            .find(|c| c.name.to_string() == name)
            .unwrap();
        c.sample_data.values_as_f32().filter(|v| *v > 0.0).count()
    };
    assert_eq!(count("debug.inside.Y"), v.inside_geometry_texels);
    assert_eq!(count("debug.overlap.Y"), v.overlapping_texels as usize);
    assert_eq!(count("debug.density.Y"), v.valid_texels);
    // Inside texels are not valid.
    assert_eq!(count("validity.Y"), v.valid_texels);
}

/// Issue 20 point 3: texel validation's rays traced by the GPU's BVH query pass
/// (`gpu::validate`, used on hardware GPUs) decide every texel as the CPU's do. Both
/// routes cast the same rays from the same streams, and on lavapipe the GPU's closest hit
/// is the CPU's (`tests/gpu_bvh.rs`), so the fractions must agree exactly. The atlas has
/// more texels than one chunk of the GPU route, so the chunking is checked too.
#[test]
fn the_gpu_route_decides_every_texel_as_the_cpu_does() {
    use lightmapd::engine::atlas::{Atlas, validate};
    use lightmapd::engine::gpu::scene_rays::SceneRays;
    use lightmapd::engine::gpu::{self, Requirements};

    let ctx = match gpu::shared(&Requirements::default()) {
        Ok(c) => c,
        Err(e) if std::env::var("LIGHTMAPD_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("SKIPPED: no GPU adapter ({e})");
            return;
        }
        Err(e) => panic!("no GPU adapter: {e}"),
    };
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("floor", Vec3::ZERO, 6.0, Vec3::Y, m);
    for (i, x) in [-2.0f32, -0.5, 1.0, 2.2].into_iter().enumerate() {
        b.block(
            &format!("crate {i}"),
            Vec3::new(x, 0.0, 0.3 * x),
            Vec3::splat(0.4),
            0.3 * i as f32,
            m,
        );
    }
    let scene = Arc::new(import_slice(&b.to_glb(), None).unwrap().0);
    let atlas = Atlas::build(&scene, 384, 384).unwrap();
    assert!(
        atlas.texels.len() > gpu::validate::CHUNK_TEXELS,
        "{} texels: more than a chunk",
        atlas.texels.len()
    );
    let rays = SceneRays::new(scene.clone());
    let started = std::time::Instant::now();
    let cpu = validate::backface_fractions(&scene, &rays.tracer(), &atlas.texels);
    let cpu_s = started.elapsed().as_secs_f64();
    let started = std::time::Instant::now();
    let on_gpu = gpu::validate::backface_fractions(&ctx, &rays, &atlas.texels).expect("the GPU route");
    let gpu_s = started.elapsed().as_secs_f64();
    let inside = |f: &[f32]| f.iter().filter(|x| **x > validate::BACKFACE_TOLERANCE).count();
    let differ = cpu.iter().zip(&on_gpu).filter(|(a, b)| a != b).count();
    eprintln!(
        "{} texels on {}: CPU {cpu_s:.2} s, GPU route {gpu_s:.2} s; inside {} (CPU) {} (GPU); fractions differ at {differ}",
        atlas.texels.len(),
        ctx.info.name,
        inside(&cpu),
        inside(&on_gpu)
    );
    assert_eq!(on_gpu.len(), cpu.len());
    assert!(
        inside(&cpu) > 100,
        "the crates stand on the floor: texels under them are inside"
    );
    assert_eq!(differ, 0, "texels whose back-face fraction differs between the routes");
}
