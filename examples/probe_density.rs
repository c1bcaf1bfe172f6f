//! Does adaptive probe density pay (issue 26 point 1: "denser near geometry if you measure
//! it pays")? The figures of docs/probes.md, *Adaptive density*.
//!
//! `cargo run --release --example probe_density [SCENE] [SPACING] [SUBDIVIDE] [STEPS] [POINTS]`
//! (defaults: kenney-fps-level, 4 m, 2 levels, 32 steps, 2000 points). SCENE is one of the
//! real-size library scenes (`library::real_size_scenes`), with its lighting.
//!
//! What a dynamic object gets is the probes *interpolated* where it stands, so that is what
//! is measured: POINTS random points in the scene's bounds, each baked as a probe itself
//! (the truth, 4 x STEPS steps; points inside geometry, by the baker's own test, are
//! dropped), against three probe sets baked with STEPS steps each:
//! - `grid`: the uniform grid at SPACING;
//! - `adaptive`: the same grid split SUBDIVIDE levels where geometry passes;
//! - `grid, as many`: a uniform grid whose spacing gives about as many probes as `adaptive`
//!   (the fair comparison: more probes anywhere also help).
//!
//! At each point: the valid probes among its 16 nearest that it sees (an unoccluded
//! segment; a probe behind a wall must not light it), at most 8, weighted by inverse squared
//! distance (the nearest probe alone when it sees none). The error is E/π of the
//! interpolated SH against the truth's along the six axis normals, luminance, RMS over
//! points and normals over the RMS truth; also over the points within NEAR = SPACING / 4
//! of a surface (the distance: the shortest of 64 rays), where the adaptive set puts its
//! probes. The truth's own noise is printed beside (its estimated relative error).
//!
//! IDW over visible neighbours stands in for what engines do (Unity and Godot
//! tetrahedralize the probes and interpolate barycentrically); it is the same rule for all
//! three sets, so it compares placements, not interpolators.

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use lightmapd::engine::gpu::scene_rays::SceneRays;
use lightmapd::engine::scene::import_slice;
use lightmapd::engine::scene::library::real_size_scenes;
use lightmapd::engine::technique::path::probes::{
    MAX_PROBES, ProbeBaker, ProbeSet, SH9, adaptive_positions, grid_positions, irradiance_over_pi,
};
use serde_json::json;

const LUMINANCE: Vec3 = Vec3::new(0.2126, 0.7152, 0.0722);
const NORMALS: [Vec3; 6] = [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z];

fn bake(rays: &SceneRays, lighting: lightmapd::engine::scene::Lighting, at: Vec<Vec3>, steps: u32) -> ProbeSet {
    let mut b = ProbeBaker::sharing(rays, lighting, at, &json!({"samples_per_step": 64, "device": "cpu"}), 5)
        .expect("probe baker");
    for _ in 0..steps {
        b.step().expect("step");
    }
    b.result().expect("probes")
}

fn sh(p: &lightmapd::engine::technique::path::probes::Probe) -> [Vec3; SH9] {
    p.sh.map(Vec3::from_array)
}

fn main() {
    let arg = |k: usize| std::env::args().nth(k);
    let name = arg(1).unwrap_or_else(|| "kenney-fps-level".into());
    let spacing: f32 = arg(2).and_then(|s| s.parse().ok()).unwrap_or(4.0);
    let subdivide: u32 = arg(3).and_then(|s| s.parse().ok()).unwrap_or(2);
    let steps: u32 = arg(4).and_then(|s| s.parse().ok()).unwrap_or(32);
    let points: usize = arg(5).and_then(|s| s.parse().ok()).unwrap_or(2000);
    let case = real_size_scenes()
        .into_iter()
        .find(|s| s.name == name)
        .unwrap_or_else(|| panic!("no real-size scene {name}"));
    let scene = Arc::new(import_slice(&(case.glb)(), None).expect("scene imports").0);
    let rays = SceneRays::new(scene.clone());
    let tracer = rays.tracer();
    let (lo, hi) = scene
        .triangles
        .iter()
        .flat_map(|t| t.p)
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p), hi.max(p))
        });
    // Random points in the bounds (a fixed LCG: the same points every run).
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut unit = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let test: Vec<Vec3> = (0..points)
        .map(|_| lo + (hi - lo) * Vec3::new(unit(), unit(), unit()))
        .collect();
    let t = Instant::now();
    let truth = bake(&rays, case.lighting, test.clone(), 4 * steps);
    let keep: Vec<usize> = (0..test.len()).filter(|&i| truth.probes[i].valid).collect();
    println!(
        "{name}: bounds {:.1} x {:.1} x {:.1} m, {} test points ({} inside geometry dropped), truth {} steps in {:.1} s, its error {:.2} %",
        (hi - lo).x,
        (hi - lo).y,
        (hi - lo).z,
        keep.len(),
        test.len() - keep.len(),
        4 * steps,
        t.elapsed().as_secs_f64(),
        100.0 * truth.error.unwrap_or(f32::NAN)
    );
    // Distance to the nearest surface: the shortest of 64 stratified rays.
    let near = spacing / 4.0;
    let distance = |x: Vec3| -> f32 {
        let mut best = f32::INFINITY;
        for i in 0..8 {
            for j in 0..8 {
                let z = 1.0 - 2.0 * (i as f32 + 0.5) / 8.0;
                let r = (1.0 - z * z).max(0.0).sqrt();
                let phi = std::f32::consts::TAU * (j as f32 + 0.5) / 8.0;
                let w = Vec3::new(r * phi.cos(), r * phi.sin(), z);
                if let Some(h) = tracer.trace(&scene, x, w, best) {
                    best = best.min(h.t);
                }
            }
        }
        best
    };
    let close: Vec<bool> = keep.iter().map(|&i| distance(test[i]) < near).collect();

    let grid = grid_positions(&scene, spacing, MAX_PROBES).expect("grid");
    let adaptive = adaptive_positions(&scene, spacing, subdivide, MAX_PROBES).expect("adaptive");
    let fair = spacing * (grid.len() as f32 / adaptive.len() as f32).cbrt();
    let as_many = grid_positions(&scene, fair, MAX_PROBES).expect("grid as many");
    println!(
        "| set | spacing | probes | valid | bake s | error, all points | error, within {near} m of a surface ({} points) |\n| --- | --- | --- | --- | --- | --- | --- |",
        close.iter().filter(|c| **c).count()
    );
    for (label, s, at) in [
        ("grid", format!("{spacing} m"), grid),
        (
            "adaptive",
            format!(
                "{spacing} m, {subdivide} levels (to {} m)",
                spacing / (1 << subdivide) as f32
            ),
            adaptive,
        ),
        ("grid, as many", format!("{fair:.2} m"), as_many),
    ] {
        let t = Instant::now();
        let set = bake(&rays, case.lighting, at.clone(), steps);
        let seconds = t.elapsed().as_secs_f64();
        let valid: Vec<(Vec3, [Vec3; SH9])> = set
            .probes
            .iter()
            .zip(&at)
            .filter(|(p, _)| p.valid)
            .map(|(p, x)| (*x, sh(p)))
            .collect();
        let (mut err2, mut ref2, mut near_err2, mut near_ref2) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for (k, &i) in keep.iter().enumerate() {
            let x = test[i];
            let mut by_distance: Vec<(f32, usize)> = valid
                .iter()
                .enumerate()
                .map(|(j, (p, _))| ((*p - x).length_squared(), j))
                .collect();
            let nearest = by_distance.len().min(16);
            by_distance.select_nth_unstable_by(nearest.saturating_sub(1), |a, b| a.0.total_cmp(&b.0));
            by_distance.truncate(nearest);
            by_distance.sort_by(|a, b| a.0.total_cmp(&b.0));
            let seen: Vec<(f32, usize)> = by_distance
                .iter()
                .filter(|(d2, j)| {
                    let d = d2.sqrt();
                    d == 0.0 || tracer.unoccluded(&scene, x, (valid[*j].0 - x) / d, d)
                })
                .take(8)
                .copied()
                .collect();
            let used = if seen.is_empty() { &by_distance[..1] } else { &seen[..] };
            let mut c = [Vec3::ZERO; SH9];
            let mut wsum = 0.0;
            for (d2, j) in used {
                let w = 1.0 / d2.max(1e-6);
                for (a, b) in c.iter_mut().zip(&valid[*j].1) {
                    *a += *b * w;
                }
                wsum += w;
            }
            let c = c.map(|v| v / wsum);
            let want = sh(&truth.probes[i]);
            for n in NORMALS {
                let e = irradiance_over_pi(&c, n).dot(LUMINANCE) as f64;
                let r = irradiance_over_pi(&want, n).dot(LUMINANCE) as f64;
                err2 += (e - r).powi(2);
                ref2 += r * r;
                if close[k] {
                    near_err2 += (e - r).powi(2);
                    near_ref2 += r * r;
                }
            }
        }
        println!(
            "| {label} | {s} | {} | {} | {seconds:.1} | {:.2} % | {:.2} % |",
            at.len(),
            valid.len(),
            100.0 * (err2 / ref2).sqrt(),
            100.0 * (near_err2 / near_ref2.max(1e-30)).sqrt()
        );
    }
}
