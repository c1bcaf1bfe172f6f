//! `sdb` throughput: milliseconds per direction (illumination map + gather, and the
//! per-step resolve) for scenes of about 1k, 25k and 100k triangles, illumination map
//! 512^2, lightmaps 256^2 and 1024^2 (issue 3, item 5). Prints a Markdown table; the
//! figures go to docs/performance.md with the machine named.
//!
//! Scenes: a 20 m ground plane with a grid of UV spheres (each its own chart), sized so
//! the triangle counts land near the targets; a white sky, so the gather does real work.
//! Timing: 4 warm-up directions (pipeline compilation happens at the first draw), then
//! N directions timed up to GPU completion (a device poll, no readback).
//!
//! Usage: cargo bench --bench sdb_direction [-- DIRECTIONS=64]

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use lightmapd::engine::atlas::Atlas;
use lightmapd::engine::gpu::{GpuContext, Requirements};
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder};
use lightmapd::engine::scene::{Hemisphere, Lighting, Sky, import_slice};
use lightmapd::engine::technique::BakeInputs;
use lightmapd::engine::technique::sdb::{SdbEngine, SdbParams, sdb_input};

/// Ground plane plus `n x n` spheres of `segments x segments/2` quads (2 triangles each).
fn spheres(n: usize, segments: u32) -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.6; 3]));
    b.square("ground", Vec3::ZERO, 20.0, Vec3::Y, grey);
    let step = 16.0 / n as f32;
    for i in 0..n {
        for j in 0..n {
            let c = Vec3::new(
                -8.0 + (i as f32 + 0.5) * step,
                0.5 * step,
                -8.0 + (j as f32 + 0.5) * step,
            );
            b.sphere(&format!("ball {i} {j}"), c, 0.4 * step, segments, segments / 2, grey);
        }
    }
    b
}

fn main() {
    let directions: u32 = std::env::args()
        .skip(1)
        .find_map(|a| a.strip_prefix("DIRECTIONS=").and_then(|v| v.parse().ok()))
        .unwrap_or(64);
    let ctx = match GpuContext::new(&Requirements::default()) {
        Ok(c) => Arc::new(c),
        Err(e) => {
            eprintln!("no GPU context, nothing to measure: {e}");
            return;
        }
    };
    println!(
        "adapter: {} ({:?}, {:?})",
        ctx.info.name, ctx.info.device_type, ctx.info.backend
    );
    println!("| scene | triangles | lightmap | valid texels | map | k | ms / direction |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    let lighting = Lighting {
        sky: Some(Sky {
            radiance: Vec3::ONE,
            hemisphere: Hemisphere::Upper,
        }),
        sun: None,
    };
    // 1k: 1 sphere of 32 x 16 quads (1024 triangles); 25k: 25 spheres of 32 x 16; 100k:
    // 25 spheres of 64 x 32 (4096 triangles each).
    for (name, n, segments) in [("1 sphere", 1, 32), ("25 spheres", 5, 32), ("25 fine spheres", 5, 64)] {
        let scene = Arc::new(import_slice(&spheres(n, segments).to_glb(), None).expect("scene").0);
        for res in [256u32, 1024] {
            let atlas = Arc::new(Atlas::build(&scene, res, res).expect("atlas"));
            let request = BakeRequest {
                technique: "sdb".into(),
                lighting,
                ..Default::default()
            };
            let plan = lightmapd::engine::job::plan_for(&scene, &request).expect("plan");
            let inputs = BakeInputs::new(scene.clone(), atlas.clone(), lighting, 1, plan);
            for k in [3u32, 5] {
                let params = SdbParams {
                    map_size: Some(512),
                    neighbourhood: k,
                    ..SdbParams::default()
                };
                let mut engine = SdbEngine::new(
                    ctx.clone(),
                    sdb_input(&ctx, &inputs, &params).expect("sdb input").0,
                    params,
                )
                .expect("engine");
                for _ in 0..4 {
                    engine.step().expect("step");
                }
                engine.finish().expect("finish");
                let t0 = Instant::now();
                for _ in 0..directions {
                    engine.step().expect("step");
                }
                engine.finish().expect("finish");
                let ms = t0.elapsed().as_secs_f64() * 1e3 / directions as f64;
                println!(
                    "| {name} | {} | {res}^2 | {} | 512^2 | {k} | {ms:.2} |",
                    scene.triangles.len(),
                    atlas.texels.len()
                );
            }
        }
    }
}
