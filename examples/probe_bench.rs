//! Error against time for light probes (issue 26 point 5), the figures of docs/probes.md.
//!
//! `cargo run --release --example probe_bench [MAX_STEPS] [cpu|gpu] [SIDE] [sobol|independent]`: bakes a grid of
//! SIDE³ probes (default 4) with `path`'s probe estimator (64 samples a probe a step, on all
//! cores or on the GPU, lavapipe counting) in scenes whose probe
//! coefficients have closed forms, and prints after 1, 2, 4, … MAX_STEPS (default 256)
//! steps the wall time, the set's reported error (`ProbeSet::error`, the RMS of the L0
//! standard errors over the RMS L0; none after one step) and the true error (RMS over the valid probes of
//! |c00 − exact| over the exact c00, luminance). The scenes and the error are `lightmapd::bench::probes`' (its module doc), which
//! `lightmapd bench` also measures against time.

use std::sync::Arc;
use std::time::Instant;

use lightmapd::bench::probes::{baker, probe_cases, true_error};
use lightmapd::engine::gpu::scene_rays::SceneRays;

fn main() {
    let arg = |k: usize| std::env::args().nth(k);
    let max_steps: u64 = arg(1).and_then(|s| s.parse().ok()).unwrap_or(256);
    let device = arg(2).unwrap_or_else(|| "cpu".into());
    let side: usize = arg(3).and_then(|s| s.parse().ok()).unwrap_or(4);
    let sampling = arg(4).unwrap_or_else(|| "sobol".into());
    println!(
        "| scene | device | probes | steps | samples a probe | seconds | reported error | true error (L0, RMS) |\n| --- | --- | --- | --- | --- | --- | --- | --- |"
    );
    for case in probe_cases(side).expect("probe scenes") {
        // The job's route: the baker shares the bake's rays (and, on the GPU, its uploads).
        let rays = SceneRays::new(Arc::new(case.scene.clone()));
        let mut baker = baker(&case, &rays, &device, &sampling).expect("probe baker");
        let adapter = baker.device();
        let t = Instant::now();
        let mut next = 1;
        for step in 1..=max_steps {
            baker.step().expect("probe step");
            if step != next {
                continue;
            }
            next *= 2;
            // After the read-back: on the GPU the steps run asynchronously until then.
            let set = baker.result().expect("probes");
            let seconds = t.elapsed().as_secs_f64();
            let (error, n) = true_error(&case, &set);
            println!(
                "| {} | {adapter} | {} | {step} | {} | {seconds:.3} | {} | {:.3} % |",
                case.name,
                n,
                step * 64,
                set.error
                    .map_or("n/a (one half)".into(), |e| format!("{:.3} %", 100.0 * e)),
                100.0 * error
            );
        }
    }
}
