//! Is the live error estimate honest? For the unbiased `path`, the half-difference
//! estimate must track the true error (against the closed-form answer) within a factor
//! of 2 at every snapshot of a run (issue 5).

use lightmapd::bench::{BenchConfig, prepare, reference, true_error};
use lightmapd::engine::accumulate::Snapshot;
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::scene::library::benchmark_scenes;
use lightmapd::engine::technique::{self, BakeInputs};
use std::time::Duration;

/// A bench configuration for scenes whose reference is a closed form (no bake, no cache).
fn analytic_only() -> BenchConfig {
    BenchConfig {
        scenes: vec![],
        techniques: vec![],
        budget: Duration::ZERO,
        steps: None,
        reference_budget: Duration::ZERO,
        out_dir: std::env::temp_dir(),
        cache_dir: std::env::temp_dir(),
        probes: false,
    }
}

fn track(scene_name: &str) {
    let lib = benchmark_scenes().into_iter().find(|s| s.name == scene_name).unwrap();
    let p = prepare(&lib).unwrap();
    let cfg = analytic_only();
    let r = reference(&lib, &p, &cfg).unwrap();
    assert_eq!(r.kind, "analytic");
    let request = BakeRequest {
        lighting: lib.lighting,
        ..Default::default()
    };
    let plan = lightmapd::engine::job::plan_for(&p.scene, &request).unwrap();
    let inputs = BakeInputs::new(p.scene.clone(), p.atlas.clone(), lib.lighting, 3, plan);
    let mut tech = technique::create("path", inputs, &serde_json::json!({"samples_per_step": 1})).unwrap();
    let mut checkpoints = vec![2u64, 4, 8, 16, 32, 64];
    while let Some(&next) = checkpoints.first() {
        tech.step().unwrap();
        if tech.steps_done() < next {
            continue;
        }
        checkpoints.remove(0);
        let snap: Snapshot = tech.snapshot().unwrap();
        let est = snap.estimate();
        let truth = true_error(&est.total, &r.values);
        let estimated = est.error.relative.unwrap() as f64;
        let ratio = estimated / truth;
        eprintln!("{scene_name}: {next} steps: true {truth:.4}, estimated {estimated:.4}, ratio {ratio:.2}");
        assert!(
            (0.5..=2.0).contains(&ratio),
            "{scene_name} at {next} steps: estimated {estimated}, true {truth}"
        );
    }
}

#[test]
fn estimate_tracks_true_error_closed_box() {
    track("closed-box-0.9");
}

#[test]
fn estimate_tracks_true_error_parallel_plates() {
    track("parallel-plates");
}

/// The denoiser lowers the true error of a noisy bake (4 paths per texel) on scenes with
/// closed-form answers, including the sphere's soft shadow, where blurring would show.
#[test]
fn denoising_lowers_true_error() {
    for name in ["sphere-over-plane", "parallel-plates", "closed-box-0.9"] {
        let lib = benchmark_scenes().into_iter().find(|s| s.name == name).unwrap();
        let p = prepare(&lib).unwrap();
        let cfg = analytic_only();
        let r = reference(&lib, &p, &cfg).unwrap();
        let request = BakeRequest {
            lighting: lib.lighting,
            ..Default::default()
        };
        let plan = lightmapd::engine::job::plan_for(&p.scene, &request).unwrap();
        let inputs = BakeInputs::new(p.scene.clone(), p.atlas.clone(), lib.lighting, 9, plan);
        let mut tech = technique::create("path", inputs, &serde_json::json!({"samples_per_step": 2})).unwrap();
        tech.step().unwrap();
        tech.step().unwrap();
        let est = tech.snapshot().unwrap().estimate();
        let raw = true_error(&est.total, &r.values);
        let den = true_error(
            &lightmapd::engine::job::finish(&p.atlas, &est, &request).total,
            &r.values,
        );
        eprintln!("{name}: true error raw {raw:.4}, denoised {den:.4}");
        assert!(den < 0.6 * raw, "{name}: denoising took the error from {raw} to {den}");
    }
}
