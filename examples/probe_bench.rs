//! Error against time for light probes (issue 26 point 5), the figures of docs/probes.md.
//!
//! `cargo run --release --example probe_bench [MAX_STEPS] [cpu|gpu] [SIDE]`: bakes a grid of
//! SIDE³ probes (default 4) with `path`'s probe estimator (64 samples a probe a step, on all
//! cores or on the GPU, lavapipe counting) in scenes whose probe
//! coefficients have closed forms, and prints after 1, 2, 4, … MAX_STEPS (default 256)
//! steps the wall time, the set's reported error (`ProbeSet::error`, the RMS of the L0
//! standard errors over the RMS L0; none after one step) and the true error (RMS over the valid probes of
//! |c00 − exact| over the exact c00, luminance):
//! - the furnace: inside a closed box of albedo ρ emitting 1 − ρ, the radiance is 1 in
//!   every direction, so c00 = √(4π) at every probe (multi-bounce paths);
//! - the open sky: over a black 10 m plane under an upper sky of 1, c00 = 2π Y00 at every
//!   probe above it (one bounce: the black ground ends the paths);
//! - the small lamp: a 0.2 m square of radiance 10 facing down 1.5 m over a black ground,
//!   c00 = Le Y00 Ω at each probe with Ω the lamp's solid angle from it (light sampling
//!   of emitters, MIS with the uniform directions).

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use lightmapd::engine::gpu::scene_rays::SceneRays;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder};
use lightmapd::engine::scene::library::closed_box;
use lightmapd::engine::scene::{Hemisphere, Lighting, Scene, Sky, import_slice};
use lightmapd::engine::technique::path::probes::ProbeBaker;
use serde_json::json;

const Y00: f64 = 0.282_094_791_773_878;

/// Solid angle of the axis-aligned rectangle [x0, x1] × [z0, z1] a height h above the
/// point (0, 0): the sum of four corner rectangles with signs, each
/// atan(a b / (h √(h² + a² + b²))).
fn rect_solid_angle(x0: f64, x1: f64, z0: f64, z1: f64, h: f64) -> f64 {
    let corner =
        |a: f64, b: f64| a.signum() * b.signum() * (a.abs() * b.abs() / (h * (h * h + a * a + b * b).sqrt())).atan();
    corner(x1, z1) - corner(x0, z1) - corner(x1, z0) + corner(x0, z0)
}

struct Case {
    name: &'static str,
    scene: Scene,
    lighting: Lighting,
    /// Probe positions in the scene's frame, with the exact c00 at each.
    probes: Vec<(Vec3, f64)>,
}

fn import(b: &SceneBuilder) -> Scene {
    import_slice(&b.to_glb(), None).expect("scene imports").0
}

fn cases(side: usize) -> Vec<Case> {
    let grid = |lo: Vec3, hi: Vec3, n: usize| -> Vec<Vec3> {
        let mut v = Vec::new();
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let f = |c: usize| (c as f32 + 0.5) / n as f32;
                    v.push(lo + (hi - lo) * Vec3::new(f(i), f(j), f(k)));
                }
            }
        }
        v
    };
    let furnace = import(&closed_box(0.5));
    let offset = furnace.origin_offset.as_vec3();
    let furnace_probes = grid(Vec3::splat(-0.8), Vec3::splat(0.8), side)
        .into_iter()
        .map(|p| (p - offset, (4.0 * std::f64::consts::PI).sqrt()))
        .collect();

    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    b.square("ground", Vec3::ZERO, 10.0, Vec3::Y, black);
    let sky = import(&b);
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
    let lamp_scene = import(&b);
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
    vec![
        Case {
            name: "furnace (closed box, rho 0.5)",
            scene: furnace,
            lighting: Lighting::default(),
            probes: furnace_probes,
        },
        Case {
            name: "open sky over a black plane",
            scene: sky,
            lighting: upper,
            probes: sky_probes,
        },
        Case {
            name: "0.2 m lamp over a black plane",
            scene: lamp_scene,
            lighting: Lighting::default(),
            probes: lamp_probes,
        },
    ]
}

fn main() {
    let arg = |k: usize| std::env::args().nth(k);
    let max_steps: u64 = arg(1).and_then(|s| s.parse().ok()).unwrap_or(256);
    let device = arg(2).unwrap_or_else(|| "cpu".into());
    let side: usize = arg(3).and_then(|s| s.parse().ok()).unwrap_or(4);
    println!(
        "| scene | device | probes | steps | samples a probe | seconds | reported error | true error (L0, RMS) |\n| --- | --- | --- | --- | --- | --- | --- | --- |"
    );
    for case in cases(side) {
        let positions: Vec<Vec3> = case.probes.iter().map(|(p, _)| *p).collect();
        // The job's route: the baker shares the bake's rays (and, on the GPU, its uploads).
        let rays = SceneRays::new(Arc::new(case.scene.clone()));
        let mut baker = ProbeBaker::sharing(
            &rays,
            case.lighting,
            positions,
            &json!({"samples_per_step": 64, "device": device}),
            7,
        )
        .expect("probe baker");
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
            let (mut sq, mut n) = (0.0, 0);
            for (p, (_, exact)) in set.probes.iter().zip(&case.probes) {
                if !p.valid {
                    continue;
                }
                let c00 = 0.2126 * p.sh[0][0] as f64 + 0.7152 * p.sh[0][1] as f64 + 0.0722 * p.sh[0][2] as f64;
                sq += ((c00 - exact) / exact).powi(2);
                n += 1;
            }
            println!(
                "| {} | {adapter} | {} | {step} | {} | {seconds:.3} | {} | {:.3} % |",
                case.name,
                n,
                step * 64,
                set.error
                    .map_or("n/a (one half)".into(), |e| format!("{:.3} %", 100.0 * e)),
                100.0 * (sq / n.max(1) as f64).sqrt()
            );
        }
    }
}
