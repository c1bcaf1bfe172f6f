//! GPU ray-tracing figures for docs/performance.md ("GPU BVH and `path` on the GPU"):
//! 1. rays per second of the BVH traversal alone (`engine::gpu::bvh`, closest hit), for
//!    coherent primary-like rays (a pinhole camera's pixel grid) and incoherent
//!    diffuse-bounce rays (cosine-distributed about the normal from random surface points),
//!    GPU against the CPU tracer on all cores (the same rays);
//! 2. milliseconds a step of `path` on the GPU against the CPU `path`, with both bakes'
//!    estimated error, on the bundled Cornell box and `scenes/occlusion_room.glb`.
//!
//! Usage: cargo run --release --example gpu_trace_bench [-- RAYS=1048576 STEPS=8 RES=128]
//! (`LIGHTMAPD_ADAPTER` picks the adapter as for a bake.)

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use lightmapd::engine::atlas::Atlas;
use lightmapd::engine::atlas::unwrap::{UvUnwrap, generate_lightmap_uvs};
use lightmapd::engine::gpu::bvh::{BVH_MISS, QueryRay, QueryRunner};
use lightmapd::engine::gpu::scene_lights::{GpuSceneLights, LightSources};
use lightmapd::engine::gpu::scene_rays::SceneRays;
use lightmapd::engine::gpu::{GpuContext, Requirements};
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::raytrace::{Tracer, cosine_sample};
use lightmapd::engine::rng::Rng;
use lightmapd::engine::scene::build::cornell_box;
use lightmapd::engine::scene::library::procedural_blocks;
use lightmapd::engine::scene::{Hemisphere, Lighting, Scene, Sky, import_file, import_slice};
use lightmapd::engine::technique::{self, BakeInputs};
use rayon::prelude::*;
use serde_json::json;

fn arg(name: &str, default: usize) -> usize {
    std::env::args()
        .skip(1)
        .find_map(|a| a.strip_prefix(&format!("{name}=")).and_then(|v| v.parse().ok()))
        .unwrap_or(default)
}

fn scenes() -> Vec<(&'static str, Scene)> {
    let room = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/occlusion_room.glb");
    vec![
        ("cornell-box", import_slice(&cornell_box().to_glb(), None).unwrap().0),
        (
            "blocks-25k",
            import_slice(&procedural_blocks().to_glb(), None).unwrap().0,
        ),
        ("occlusion_room", import_file(std::path::Path::new(room)).unwrap().0),
    ]
}

fn coherent(scene: &Scene, n: usize) -> Vec<QueryRay> {
    // A camera outside the bounds looking at the centre, one ray per pixel of a square grid.
    let c = scene.bounds.center();
    let r = 0.5 * scene.bounds.diagonal();
    let eye = c + Vec3::new(0.3, 0.4, 1.0).normalize() * (1.6 * r);
    let fwd = (c - eye).normalize();
    let right = fwd.cross(Vec3::Y).normalize();
    let up = right.cross(fwd);
    let side = (n as f32).sqrt() as usize;
    let mut rays = Vec::with_capacity(side * side);
    for j in 0..side {
        for i in 0..side {
            let x = (i as f32 + 0.5) / side as f32 * 2.0 - 1.0;
            let y = (j as f32 + 0.5) / side as f32 * 2.0 - 1.0;
            let d = (fwd + right * (0.6 * x) + up * (0.6 * y)).normalize();
            rays.push(QueryRay {
                origin: eye.to_array(),
                tmax: f32::MAX,
                dir: d.to_array(),
                mode: 0,
            });
        }
    }
    rays
}

fn incoherent(scene: &Scene, n: usize) -> Vec<QueryRay> {
    let eps = 2e-5 * scene.bounds.diagonal();
    (0..n)
        .map(|i| {
            let mut rng = Rng::new(9, 0, i as u64, 0);
            let k = ((rng.next_f32() * scene.triangles.len() as f32) as usize).min(scene.triangles.len() - 1);
            let t = &scene.triangles[k];
            let (mut a, mut b) = (rng.next_f32(), rng.next_f32());
            if a + b > 1.0 {
                a = 1.0 - a;
                b = 1.0 - b;
            }
            let ng = t.geometric_normal();
            let p = t.point(Vec3::new(1.0 - a - b, a, b)) + ng * eps;
            let d = cosine_sample(ng, rng.next_f32(), rng.next_f32());
            QueryRay {
                origin: p.to_array(),
                tmax: f32::MAX,
                dir: d.to_array(),
                mode: 0,
            }
        })
        .collect()
}

fn traversal(ctx: &Arc<GpuContext>, rays_n: usize) {
    println!(
        "| scene | triangles | BVH nodes / depth | rays | kind | hit % | GPU Mrays/s | CPU Mrays/s ({} threads) |",
        rayon::current_num_threads()
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- |");
    for (name, scene) in scenes() {
        let tracer = Tracer::new(&scene);
        let shared = SceneRays::new(Arc::new(scene.clone()));
        let emitters = shared.emitters();
        let bvh = GpuSceneLights::new(
            ctx,
            "bvh query",
            &shared,
            &Lighting::default(),
            &emitters,
            LightSources::NONE,
        )
        .unwrap();
        for (kind, rays) in [
            ("coherent", coherent(&scene, rays_n)),
            ("incoherent", incoherent(&scene, rays_n)),
        ] {
            let runner = QueryRunner::new(ctx, &bvh, rays.len()).unwrap();
            runner.load(ctx, &rays);
            runner.dispatch(ctx, rays.len()).unwrap(); // compile, warm up
            let reps = 3;
            let t0 = Instant::now();
            for _ in 0..reps {
                runner.dispatch(ctx, rays.len()).unwrap();
            }
            let gpu_s = t0.elapsed().as_secs_f64() / reps as f64;
            let hits = runner.run(ctx, &rays).unwrap();
            let hit = hits.iter().filter(|h| h.slot != BVH_MISS).count() as f64 / rays.len() as f64;
            let t0 = Instant::now();
            let cpu_hits: usize = rays
                .par_iter()
                .map(|r| {
                    tracer
                        .trace(&scene, r.origin.into(), r.dir.into(), f32::INFINITY)
                        .is_some() as usize
                })
                .sum();
            let cpu_s = t0.elapsed().as_secs_f64();
            assert!(
                (cpu_hits as f64 / rays.len() as f64 - hit).abs() < 0.01,
                "CPU and GPU hit rates differ"
            );
            println!(
                "| {name} | {} | {} / {} | {} | {kind} | {:.1} | {:.2} | {:.2} |",
                scene.triangles.len(),
                bvh.bvh.data.nodes.len(),
                bvh.bvh.data.depth,
                rays.len(),
                100.0 * hit,
                rays.len() as f64 / gpu_s / 1e6,
                rays.len() as f64 / cpu_s / 1e6
            );
        }
    }
}

fn path_steps(steps: u64, res: u32) {
    println!();
    println!(
        "| scene | triangles | lightmap | texels | device | ms / step (4 paths a texel) | estimated error after {steps} steps |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    let lighting = Lighting {
        sky: Some(Sky {
            radiance: Vec3::new(0.2, 0.3, 0.5),
            hemisphere: Hemisphere::Upper,
        }),
        sun: None,
    };
    for (name, mut scene) in scenes().into_iter().filter(|(n, _)| *n != "blocks-25k") {
        if scene.needs_lightmap_uvs {
            generate_lightmap_uvs(&mut scene, res, &UvUnwrap).unwrap();
        }
        let scene = Arc::new(scene);
        let atlas = Arc::new(Atlas::build(&scene, res, res).unwrap());
        let request = BakeRequest {
            technique: "path".into(),
            lighting,
            ..Default::default()
        };
        let plan = lightmapd::engine::job::plan_for(&scene, &request).unwrap();
        for device in ["gpu", "cpu"] {
            let inputs = BakeInputs::new(scene.clone(), atlas.clone(), lighting, 1, plan.clone());
            let mut tech =
                technique::create("path", inputs, &json!({"samples_per_step": 4, "device": device})).unwrap();
            tech.step().unwrap();
            tech.snapshot().unwrap(); // waits for the first step (pipeline compilation)
            let t0 = Instant::now();
            for _ in 0..steps {
                tech.step().unwrap();
            }
            let snap = tech.snapshot().unwrap(); // waits for the GPU
            let ms = t0.elapsed().as_secs_f64() * 1e3 / steps as f64;
            let err = snap.estimate().error.relative.unwrap_or(f32::NAN);
            println!(
                "| {name} | {} | {res}^2 | {} | {device} | {ms:.1} | {:.2} % |",
                scene.triangles.len(),
                atlas.texels.len(),
                100.0 * err
            );
        }
    }
}

fn main() {
    tracing_subscriber::fmt().with_writer(std::io::stderr).init();
    let ctx = Arc::new(GpuContext::new(&Requirements::default()).expect("a GPU adapter (lavapipe will do)"));
    println!(
        "adapter: {} ({:?}, {:?})",
        ctx.info.name, ctx.info.device_type, ctx.info.backend
    );
    traversal(&ctx, arg("RAYS", 1 << 20));
    path_steps(arg("STEPS", 8) as u64, arg("RES", 128) as u32);
}
