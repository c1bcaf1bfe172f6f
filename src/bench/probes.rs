//! Light probes in `lightmapd bench` (issue 26 point 5: error against time for probes):
//! three scenes whose probe coefficients have closed forms, baked by the job's probe baker
//! on the device `auto` picks, measured at geometric time points as the texels are.
//!
//! - the furnace: inside a closed box of albedo ρ emitting 1 − ρ the radiance is 1 in every
//!   direction, so c00 = √(4π) at every probe (multi-bounce paths);
//! - the open sky: over a black 10 m plane under an upper sky of 1, c00 = 2π Y00 at every
//!   probe above it (one bounce: the black ground ends the paths);
//! - the small lamp: a 0.2 m square of radiance 10 facing down 1.5 m over a black ground,
//!   c00 = Le Y00 Ω at each probe, Ω the lamp's solid angle from it (emitter sampling,
//!   MIS with the uniform directions).
//!
//! Each with both samplings: `sobol` (the default) and `independent`. Under the open sky
//! `sobol` is exact: the sky is seen where the uniform direction's y = r sin 2πu2 > 0, a
//! function of one coordinate that every block of a half's stratified points splits
//! exactly in two; the lamp, sampled on its square by stratified points, comes close.
//!
//! The true error is the RMS over the valid probes of |c00 − exact| / exact (luminance);
//! the reported one is the set's `error` (the L0 standard error from the two halves). The
//! probes are a SIDE³ grid in each scene (`examples/probe_bench.rs` prints the same cases
//! step by step, on a chosen device).

use std::time::{Duration, Instant};

use glam::Vec3;
use serde_json::json;

use crate::engine::error::EngineError;
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::scene::build::{MaterialDesc, SceneBuilder};
use crate::engine::scene::library::closed_box;
use crate::engine::scene::{Hemisphere, Lighting, Scene, Sky, import_slice};
use crate::engine::technique::path::probes::{ProbeBaker, ProbeSet};

const Y00: f64 = 0.282_094_791_773_878;

/// One scene of probes with their exact c00.
pub struct ProbeCase {
    pub name: &'static str,
    pub scene: Scene,
    pub lighting: Lighting,
    /// Probe positions in the scene's frame, with the exact c00 at each.
    pub probes: Vec<(Vec3, f64)>,
}

/// One measurement of a probe bake.
#[derive(Clone, Debug)]
pub struct ProbeSample {
    pub scene: String,
    /// Where the probes baked: `cpu` or the adapter's name.
    pub device: String,
    /// `sobol` or `independent` (`path`'s `sampling`).
    pub sampling: String,
    pub probes: usize,
    pub seconds: f64,
    pub steps: u64,
    pub true_error: f64,
    pub estimated_error: Option<f32>,
}

/// Solid angle of the axis-aligned rectangle [x0, x1] × [z0, z1] a height h above the
/// point (0, 0): the sum of four corner rectangles with signs, each
/// atan(a b / (h √(h² + a² + b²))).
fn rect_solid_angle(x0: f64, x1: f64, z0: f64, z1: f64, h: f64) -> f64 {
    let corner =
        |a: f64, b: f64| a.signum() * b.signum() * (a.abs() * b.abs() / (h * (h * h + a * a + b * b).sqrt())).atan();
    corner(x1, z1) - corner(x0, z1) - corner(x1, z0) + corner(x0, z0)
}

fn import(b: &SceneBuilder) -> Result<Scene, EngineError> {
    import_slice(&b.to_glb(), None)
        .map(|(scene, _)| scene)
        .map_err(|e| EngineError::Internal(format!("probe bench scene: {e}")))
}

/// A `side`³ grid of points over [lo, hi] (cell centres).
fn grid(lo: Vec3, hi: Vec3, side: usize) -> Vec<Vec3> {
    let f = |c: usize| (c as f32 + 0.5) / side as f32;
    (0..side)
        .flat_map(|i| (0..side).flat_map(move |j| (0..side).map(move |k| lo + (hi - lo) * Vec3::new(f(i), f(j), f(k)))))
        .collect()
}

/// The three scenes (module doc) with `side`³ probes each.
pub fn probe_cases(side: usize) -> Result<Vec<ProbeCase>, EngineError> {
    let furnace = import(&closed_box(0.5))?;
    let offset = furnace.origin_offset.as_vec3();
    let furnace_probes = grid(Vec3::splat(-0.8), Vec3::splat(0.8), side)
        .into_iter()
        .map(|p| (p - offset, (4.0 * std::f64::consts::PI).sqrt()))
        .collect();

    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    b.square("ground", Vec3::ZERO, 10.0, Vec3::Y, black);
    let sky = import(&b)?;
    let offset = sky.origin_offset.as_vec3();
    let sky_probes = grid(Vec3::new(-1.0, 0.2, -1.0), Vec3::new(1.0, 2.0, 1.0), side)
        .into_iter()
        .map(|p| (p - offset, 2.0 * std::f64::consts::PI * Y00))
        .collect();

    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.0; 3], [10.0; 3]));
    b.square("ground", Vec3::ZERO, 10.0, Vec3::Y, black);
    b.square("lamp", Vec3::new(0.0, 1.5, 0.0), 0.2, Vec3::NEG_Y, lamp);
    let lamp_scene = import(&b)?;
    let offset = lamp_scene.origin_offset.as_vec3();
    let lamp_probes = grid(Vec3::new(-1.0, 0.2, -1.0), Vec3::new(1.0, 1.2, 1.0), side)
        .into_iter()
        .map(|p| {
            let h = 1.5 - p.y as f64;
            let (x, z) = (p.x as f64, p.z as f64);
            let omega = rect_solid_angle(-0.1 - x, 0.1 - x, -0.1 - z, 0.1 - z, h);
            (p - offset, 10.0 * Y00 * omega)
        })
        .collect();

    let upper = Lighting {
        sky: Some(Sky {
            radiance: Vec3::ONE,
            hemisphere: Hemisphere::Upper,
        }),
        sun: None,
    };
    Ok(vec![
        ProbeCase {
            name: "furnace (closed box of albedo 0.5)",
            scene: furnace,
            lighting: Lighting::default(),
            probes: furnace_probes,
        },
        ProbeCase {
            name: "open sky over a black plane",
            scene: sky,
            lighting: upper,
            probes: sky_probes,
        },
        ProbeCase {
            name: "0.2 m lamp over a black plane",
            scene: lamp_scene,
            lighting: Lighting::default(),
            probes: lamp_probes,
        },
    ])
}

/// The RMS over the valid probes of |c00 − exact| / exact (luminance), and how many.
pub fn true_error(case: &ProbeCase, set: &ProbeSet) -> (f64, usize) {
    let (mut sq, mut n) = (0.0, 0);
    for (p, (_, exact)) in set.probes.iter().zip(&case.probes) {
        if p.valid {
            let c00 = 0.2126 * p.sh[0][0] as f64 + 0.7152 * p.sh[0][1] as f64 + 0.0722 * p.sh[0][2] as f64;
            sq += ((c00 - exact) / exact).powi(2);
            n += 1;
        }
    }
    ((sq / n.max(1) as f64).sqrt(), n)
}

/// A probe baker for `case` on `device` (`auto`, `cpu` or `gpu`) with `sampling` (`sobol`
/// or `independent`), sharing `rays`.
pub fn baker<'a>(
    case: &ProbeCase,
    rays: &'a SceneRays,
    device: &str,
    sampling: &str,
) -> Result<ProbeBaker<'a>, EngineError> {
    let positions: Vec<Vec3> = case.probes.iter().map(|(p, _)| *p).collect();
    ProbeBaker::sharing(
        rays,
        case.lighting,
        positions,
        &json!({"samples_per_step": 64, "device": device, "sampling": sampling}),
        7,
    )
}

/// Bakes `case`'s probes on the `auto` device with `sampling` for `budget`, measuring
/// after 2 steps and then at budget/128, budget/64, …, budget (the texels' time points).
pub fn measure(case: &ProbeCase, budget: Duration, sampling: &str) -> Result<Vec<ProbeSample>, EngineError> {
    let rays = SceneRays::new(std::sync::Arc::new(case.scene.clone()));
    let mut baker = baker(case, &rays, "auto", sampling)?;
    let device = baker.device();
    let mut samples = Vec::new();
    let start = Instant::now();
    let mut next = budget.as_secs_f64() / 128.0;
    let mut steps = 0u64;
    loop {
        baker.step()?;
        steps += 1;
        let t = start.elapsed().as_secs_f64();
        if steps >= 2 && (t >= next || t >= budget.as_secs_f64()) {
            // The read-back waits for a GPU's queued steps: inside the clock.
            let set = baker.result()?;
            let (error, probes) = true_error(case, &set);
            samples.push(ProbeSample {
                scene: case.name.into(),
                device: device.clone(),
                sampling: sampling.into(),
                probes,
                seconds: start.elapsed().as_secs_f64(),
                steps,
                true_error: error,
                estimated_error: set.error,
            });
            while next <= t {
                next *= 2.0;
            }
        }
        if t >= budget.as_secs_f64() && steps >= 2 {
            return Ok(samples);
        }
    }
}
