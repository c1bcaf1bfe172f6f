//! `path` on a level of real size (issue 20 point 4 and its goal "a 1024² page of a
//! 250k-triangle level to 2 % in ≤ 10 s"): the generated level of
//! `engine::scene::library::generated_level` (400 boxes of 640 triangles on a 100 m
//! ground: 256,128 triangles, no `TEXCOORD_1`), its UVs generated at DENSITY texels a
//! metre on PAGE-wide pages, lit by `library::outdoor_lighting` (sky and sun), baked
//! by `path` on the device asked for. Prints, for docs/performance.md:
//! 1. the preparation (import, UVs, texel set, BVH, validation) in seconds;
//! 2. the bake's error against its own time at doubling checkpoints: the estimated error
//!    (the halves' noise) and the true error against a longer reference bake of another
//!    seed on the same device, with the reference's own noise taken out in squares
//!    (E|a − r|² = e_a² + e_r² for independent bakes);
//! 3. the CPU `path` on all cores for CPU_SECONDS, and the time it would need to reach
//!    the device bake's final error (path's noise falls as 1/√t, so t_cpu · (e_cpu /
//!    e)²), which gives the speed-up at equal error.
//!
//! Usage: `cargo run --release --example level_bench -- [BOXES=400] [CELLS=8]
//! [DENSITY=4.5] [PAGE=1024] [SECONDS=10] [REF_SECONDS=40] [CPU_SECONDS=10] [SPP=4]
//! [DEVICE=gpu]`; `LIGHTMAPD_ADAPTER` picks the adapter as for a bake.
//!
//! Limits: the bake's clock stops while the error is computed on the host; each
//! checkpoint's snapshot (a read-back) is in the clock, as in a real bake. The true error
//! is only as good as the reference: its noise is printed and taken out, so when it is
//! not well under the bake's error the corrected figure is itself noisy.

use std::sync::Arc;
use std::time::{Duration, Instant};

use lightmapd::bench::true_error;
use lightmapd::engine::atlas::{Atlas, unwrap, validate};
use lightmapd::engine::gpu::scene_rays::SceneRays;
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::scene::library::{generated_level, outdoor_lighting};
use lightmapd::engine::scene::{Lighting, import_slice};
use lightmapd::engine::technique::{self, BakeInputs};
use serde_json::json;

fn arg<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::args()
        .skip(1)
        .find_map(|a| a.strip_prefix(&format!("{name}=")).and_then(|v| v.parse().ok()))
        .unwrap_or(default)
}

/// What every bake of the run shares.
struct Setup {
    rays: Arc<SceneRays>,
    atlas: Arc<Atlas>,
    lighting: Lighting,
    spp: u32,
}

/// One bake of `path` on `device` with `seed`, stepped for `seconds` of its own clock,
/// calling `at` with (seconds, steps, estimate) at each doubling checkpoint from
/// `first` seconds and at the end.
fn bake(
    setup: &Setup,
    device: &str,
    seed: u64,
    seconds: f64,
    first: f64,
    mut at: impl FnMut(f64, u64, &lightmapd::engine::accumulate::Estimate),
) {
    let Setup {
        rays,
        atlas,
        lighting,
        spp,
    } = setup;
    let lighting = *lighting;
    let request = BakeRequest {
        technique: "path".into(),
        lighting,
        seed,
        ..Default::default()
    };
    let plan = lightmapd::engine::job::plan_for(rays.scene(), &request).expect("a plan");
    let inputs = BakeInputs::sharing(rays.clone(), atlas.clone(), lighting, seed, plan);
    let t = Instant::now();
    let mut tech = technique::create("path", inputs, &json!({"samples_per_step": spp, "device": device}))
        .expect("path on the device asked for");
    println!(
        "{device} path (seed {seed}): set up in {:.2} s",
        t.elapsed().as_secs_f64()
    );
    let mut clock = Duration::ZERO;
    let mut next = first;
    loop {
        let t = Instant::now();
        tech.step().expect("a step");
        clock += t.elapsed();
        let s = clock.as_secs_f64();
        if s >= next || s >= seconds {
            let t = Instant::now();
            let snap = tech.snapshot().expect("a snapshot");
            clock += t.elapsed(); // the read-back waits for the queued steps: their time
            let estimate = snap.estimate();
            at(clock.as_secs_f64(), tech.steps_done(), &estimate);
            if clock.as_secs_f64() >= seconds {
                return;
            }
            while next <= clock.as_secs_f64() {
                next *= 2.0;
            }
        }
    }
}

fn main() {
    tracing_subscriber::fmt().with_writer(std::io::stderr).init();
    let boxes: u32 = arg("BOXES", 400);
    let cells: u32 = arg("CELLS", 8);
    let density: f32 = arg("DENSITY", 4.5);
    let page: u32 = arg("PAGE", 1024);
    let seconds: f64 = arg("SECONDS", 10.0);
    let ref_seconds: f64 = arg("REF_SECONDS", 40.0);
    let cpu_seconds: f64 = arg("CPU_SECONDS", 10.0);
    let spp: u32 = arg("SPP", 4);
    let device: String = arg("DEVICE", "gpu".to_string());
    let lighting = outdoor_lighting();

    println!("## Preparation ({} threads)", rayon::current_num_threads());
    let t = Instant::now();
    let glb = generated_level(boxes, cells);
    let (mut scene, report) = import_slice(&glb, None).expect("the generated level imports");
    println!(
        "import: {} triangles, {:.2} s",
        report.triangles,
        t.elapsed().as_secs_f64()
    );
    let t = Instant::now();
    let u = unwrap::generate_lightmap_uvs_with(
        &mut scene,
        page,
        unwrap::LightmapUvs::GenerateMissing,
        Some(density),
        &unwrap::UvUnwrap,
    )
    .expect("UVs");
    let (w, h) = scene.layout.as_ref().map_or((page, page), |l| (l.width, l.height));
    println!(
        "UVs: {} charts, {} pages of {page}^2, {:.1} texels/m, {:.2} s",
        u.charts,
        u.generated_pages,
        u.texels_per_metre,
        t.elapsed().as_secs_f64()
    );
    let t = Instant::now();
    let scene = Arc::new(scene);
    let mut atlas = Atlas::build(&scene, w, h).expect("the texel set");
    let rays = SceneRays::new(scene.clone());
    let tracer = rays.tracer();
    let v = validate::validate_with(&scene, &tracer, &mut atlas);
    println!(
        "texel set, BVH and validation: {} valid texels ({} inside geometry removed), {:.2} s",
        v.valid_texels,
        v.inside_geometry_texels,
        t.elapsed().as_secs_f64()
    );
    let setup = Setup {
        rays,
        atlas: Arc::new(atlas),
        lighting,
        spp,
    };

    println!("## Reference: {device} path, {ref_seconds} s, seed 9");
    let mut reference = Vec::new();
    let mut ref_error = 0.0f64;
    bake(&setup, &device, 9, ref_seconds, ref_seconds, |s, steps, e| {
        ref_error = e.error.relative.unwrap_or(1.0) as f64;
        println!(
            "reference: {steps} steps in {s:.2} s, estimated error {:.3} %",
            100.0 * ref_error
        );
        reference = e.total.iter().copied().map(Some).collect();
    });

    println!("## {device} path, {seconds} s, seed 1");
    println!(
        "| seconds | steps | paths / texel | estimated error | true error (raw) | true error (reference noise out) |"
    );
    println!("| --- | --- | --- | --- | --- | --- |");
    let mut last = (0.0, 0.0);
    let mut to = [None::<f64>; 2];
    bake(&setup, &device, 1, seconds, 0.25, |s, steps, e| {
        let raw = true_error(&e.total, &reference);
        let corrected = (raw * raw - ref_error * ref_error).max(0.0).sqrt();
        let est = e.error.relative.unwrap_or(f32::NAN) as f64;
        println!(
            "| {s:.2} | {steps} | {} | {:.2} % | {:.2} % | {:.2} % |",
            steps * spp as u64,
            100.0 * est,
            100.0 * raw,
            100.0 * corrected
        );
        for (slot, goal) in to.iter_mut().zip([0.02, 0.01]) {
            if slot.is_none() && corrected <= goal {
                *slot = Some(s);
            }
        }
        last = (s, est);
    });
    let show = |t: Option<f64>| t.map_or("not within the run".to_string(), |t| format!("{t:.2} s"));
    println!(
        "time to 2 % true error: {}; to 1 %: {} (at doubling checkpoints)",
        show(to[0]),
        show(to[1])
    );

    if cpu_seconds > 0.0 {
        println!(
            "## cpu path, {cpu_seconds} s, seed 1, {} threads",
            rayon::current_num_threads()
        );
        let mut cpu = (0.0, 0.0);
        bake(&setup, "cpu", 1, cpu_seconds, cpu_seconds, |s, steps, e| {
            let est = e.error.relative.unwrap_or(f32::NAN) as f64;
            println!("cpu: {steps} steps in {s:.2} s, estimated error {:.2} %", 100.0 * est);
            cpu = (s, est);
        });
        let (t_dev, e_dev) = last;
        let t_cpu_equal = cpu.0 * (cpu.1 / e_dev).powi(2);
        println!(
            "equal error {:.2} %: {device} {t_dev:.2} s, cpu {t_cpu_equal:.1} s (extrapolated as 1/sqrt(t)): {:.1}x",
            100.0 * e_dev,
            t_cpu_equal / t_dev
        );
    }
}
