//! glTF alpha (issue 19 point 5): MASK and BLEND materials in every ray query, on the CPU
//! tracer and on the GPU BVH, against closed forms.
//!
//! The canopy: a black 2 m square canopy 1 m over a black ground under a uniform upper
//! sky of radiance 1. Where the canopy lets a fraction of the light through, a ground
//! point reads E/π = 1 − Σ F over what stops light, F the form factor to that part of
//! the canopy:
//! - opaque: 1 − F (the whole rectangle);
//! - MASK with an alpha texture of stripes, a quarter of them cut away
//!   ([`TextureDesc::alpha_stripes`], cutoff 0.5): the stripes that stay are exact
//!   rectangles (bilinear alpha crosses the cutoff on texel edges), so the closed form
//!   is 1 − Σ F(stripe), which is 1 − (1 − c)·F up to the stripes' placement;
//! - BLEND with alpha a: each ray stops with probability a, so E/π = 1 − a·F;
//! - MASK with alpha 0 everywhere: the canopy is gone, E/π = 1.
//!
//! `path` must hold these within its noise on the CPU and on the GPU; the GPU BVH's
//! alpha decisions must be the CPU's ray for ray; the shared direct-light pass (`sdf`'s
//! sun) must pass the sun through a BLEND canopy in proportion to 1 − a. GPU tests fail,
//! not skip, without an adapter under `LIGHTMAPD_REQUIRE_GPU=1`.

mod common;

use std::sync::Arc;

use common::{assert_unbiased, bake, have_adapter, import};
use glam::Vec3;
use lightmapd::engine::atlas::Texel;
use lightmapd::engine::gpu::bvh::{BVH_MISS, QueryRay, QueryRunner};
use lightmapd::engine::gpu::scene_lights::{GpuSceneLights, LightSources};
use lightmapd::engine::gpu::scene_rays::SceneRays;
use lightmapd::engine::gpu::{GpuContext, Requirements};
use lightmapd::engine::job::{BakeRequest, plan_for};
use lightmapd::engine::raytrace::Tracer;
use lightmapd::engine::rng::Rng;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder, TextureDesc, write_glb};
use lightmapd::engine::scene::library::rect_form_factor;
use lightmapd::engine::scene::{AlphaMode, Hemisphere, Lighting, Scene, Sky, Sun, import_slice};
use serde_json::json;

/// Stripes: period 4 texels, 1 cut, 64 periods across the canopy (3.1 cm each).
const PERIOD: u32 = 4;
const CUT: u32 = 1;
const REPEATS: u32 = 64;

#[derive(Clone, Copy, Debug)]
enum Canopy {
    Opaque,
    Stripes,
    Blend(f32),
    AllCut,
}

/// A black ground (4 m square at y = 0) under a black canopy (2 m square at y = 1,
/// facing down) made of `canopy`.
fn canopy_scene(canopy: Canopy) -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("ground", [0.0; 3]));
    b.square("ground", Vec3::ZERO, 4.0, Vec3::Y, black);
    let leaves = MaterialDesc::diffuse("leaves", [0.0; 3]);
    let leaves = match canopy {
        Canopy::Opaque => leaves,
        Canopy::Stripes => leaves
            .alpha(AlphaMode::Mask { cutoff: 0.5 })
            .textured(TextureDesc::alpha_stripes(PERIOD, CUT, REPEATS)),
        Canopy::Blend(a) => {
            let mut m = leaves.alpha(AlphaMode::Blend);
            m.base_color[3] = a;
            m
        }
        Canopy::AllCut => {
            let mut m = leaves.alpha(AlphaMode::Mask { cutoff: 0.5 });
            m.base_color[3] = 0.0;
            m
        }
    };
    let m = b.material(leaves);
    // u along +x (TEXCOORD_0's u, across the stripes), v along +z: u × v = −y, facing down.
    b.quad(
        "canopy",
        Vec3::new(-1.0, 1.0, -1.0),
        Vec3::new(2.0, 0.0, 0.0),
        Vec3::new(0.0, 0.0, 2.0),
        m,
    );
    b
}

/// E/π at ground point (x, 0, z) under `canopy` (module doc).
fn closed_form(canopy: Canopy, x: f64, z: f64) -> f64 {
    let f = |x0: f64, x1: f64| rect_form_factor(x, z, x0, x1, -1.0, 1.0, 1.0);
    match canopy {
        Canopy::Opaque => 1.0 - f(-1.0, 1.0),
        Canopy::AllCut => 1.0,
        Canopy::Blend(a) => 1.0 - a as f64 * f(-1.0, 1.0),
        Canopy::Stripes => {
            // Texels [PERIOD·j, PERIOD·j + PERIOD − CUT) of REPEATS·PERIOD stay, over x in [−1, 1].
            let texel = 2.0 / (REPEATS * PERIOD) as f64;
            let kept: f64 = (0..REPEATS)
                .map(|j| {
                    let x0 = -1.0 + (j * PERIOD) as f64 * texel;
                    f(x0, x0 + (PERIOD - CUT) as f64 * texel)
                })
                .sum();
            1.0 - kept
        }
    }
}

fn upper_sky() -> Lighting {
    Lighting {
        sky: Some(Sky {
            radiance: Vec3::ONE,
            hemisphere: Hemisphere::Upper,
        }),
        sun: None,
    }
}

const CANOPIES: [(Canopy, &str); 4] = [
    (Canopy::Opaque, "opaque canopy"),
    (Canopy::Stripes, "MASK stripes, a quarter cut"),
    (Canopy::Blend(0.4), "BLEND alpha 0.4"),
    (Canopy::AllCut, "MASK, all cut away"),
];

fn canopy_closed_form_holds(params: serde_json::Value, device: &str) {
    for (canopy, label) in CANOPIES {
        let scene = import(&canopy_scene(canopy));
        let offset = scene.origin_offset.as_vec3();
        let (atlas, est) = bake(scene, 48, upper_sky(), "path", params.clone(), 16);
        let ground = |t: &Texel| t.geo_normal.y > 0.99 && (t.position + offset).y.abs() < 1e-3;
        let expected = |t: &Texel| {
            let p = t.position + offset;
            Vec3::splat(closed_form(canopy, p.x as f64, p.z as f64) as f32)
        };
        let (_, _, n) = assert_unbiased(&atlas, &est, ground, expected, 0.0, &format!("{device} path, {label}"));
        assert!(n > 300, "{label}: {n} ground texels");
    }
    // The stripes' closed form is the 1 − (1 − c)·F to within their placement.
    let (c, f) = (
        CUT as f64 / PERIOD as f64,
        rect_form_factor(0.3, 0.2, -1.0, 1.0, -1.0, 1.0, 1.0),
    );
    let stripes = closed_form(Canopy::Stripes, 0.3, 0.2);
    assert!(
        (stripes - (1.0 - (1.0 - c) * f)).abs() < 2e-3,
        "{stripes} vs {}",
        1.0 - (1.0 - c) * f
    );
}

#[test]
fn canopy_closed_form_holds_for_path_on_the_cpu() {
    canopy_closed_form_holds(json!({"samples_per_step": 16, "device": "cpu"}), "CPU");
}

#[test]
fn canopy_closed_form_holds_for_path_on_the_gpu() {
    let _gpu = common::gpu_serial();
    if !have_adapter() {
        return;
    }
    canopy_closed_form_holds(json!({"samples_per_step": 16, "device": "gpu"}), "GPU");
}

#[test]
fn import_reads_alpha_modes_and_the_texture_alpha() {
    let (scene, report) = import_slice(&canopy_scene(Canopy::Stripes).to_glb(), None).expect("imports");
    let leaves = scene.materials.iter().find(|m| m.name == "leaves").unwrap();
    assert_eq!(leaves.alpha_mode, AlphaMode::Mask { cutoff: 0.5 });
    assert_eq!(report.alpha_materials, vec!["leaves (MASK 0.5)".to_string()]);
    assert!(
        !report.warnings.iter().any(|w| w.contains("alphaMode")),
        "alpha is read, not listed as unread: {:?}",
        report.warnings
    );
    // Coverage along the canopy at texel centres: 1, 1, 1, 0 per period.
    let (id, tri) = scene
        .triangles
        .iter()
        .enumerate()
        .find(|(_, t)| scene.material(t).name == "leaves")
        .unwrap();
    let texels = (PERIOD * REPEATS) as f32;
    let mut checked = 0;
    for k in 0..(PERIOD * REPEATS) {
        // The point whose TEXCOORD_0 u is texel k's centre, v = 0.5.
        let uv = glam::Vec2::new((k as f32 + 0.5) / texels, 0.5);
        let b = barycentric_of_uv(tri.uv, uv).expect("inside the triangle or its twin");
        let a = scene.coverage(tri, b);
        let want = if k % PERIOD < PERIOD - CUT { 1.0 } else { 0.0 };
        // Points outside this triangle (the quad's other half) are skipped.
        if b.min_element() >= 0.0 {
            assert!((a - want).abs() < 1e-6, "texel {k}: coverage {a}, want {want}");
            let origin = tri.point(b) - Vec3::Y;
            assert_eq!(scene.stops_ray(id as u32, b, origin, Vec3::Y), want == 1.0, "texel {k}");
            checked += 1;
        }
    }
    assert!(checked > 64, "{checked} texel centres on the triangle");
    let (blend, report) = import_slice(&canopy_scene(Canopy::Blend(0.4)).to_glb(), None).expect("imports");
    assert!(blend.materials.iter().any(|m| m.alpha_mode == AlphaMode::Blend));
    assert_eq!(report.alpha_materials, vec!["leaves (BLEND)".to_string()]);
}

/// Barycentrics of `uv` in the triangle with those UVs (may be negative outside it).
fn barycentric_of_uv(t: [glam::Vec2; 3], uv: glam::Vec2) -> Option<Vec3> {
    let (a, b, c) = (t[0], t[1], t[2]);
    let det = (b - a).perp_dot(c - a);
    if det == 0.0 {
        return None;
    }
    let l1 = (uv - a).perp_dot(c - a) / det;
    let l2 = (b - a).perp_dot(uv - a) / det;
    Some(Vec3::new(1.0 - l1 - l2, l1, l2))
}

#[test]
fn a_bad_alpha_cutoff_names_the_material() {
    let (mut json, bin) = canopy_scene(Canopy::Stripes).to_gltf();
    json["materials"][1]["alphaCutoff"] = json!(-0.5);
    let err = import_slice(&write_glb(&json, &bin), None).expect_err("a negative cutoff is refused");
    let text = err.to_string();
    assert!(text.contains("leaves") && text.contains("alphaCutoff"), "{text}");
}

#[test]
fn cpu_rays_pass_cut_away_stripes_and_blend_in_proportion() {
    let scene = import(&canopy_scene(Canopy::Stripes));
    let offset = scene.origin_offset.as_vec3();
    let tracer = Tracer::new(&scene);
    let texel = 2.0 / (PERIOD * REPEATS) as f32;
    // Straight up through each texel's centre of the first periods.
    for k in 0..(4 * PERIOD) {
        let x = -1.0 + (k as f32 + 0.5) * texel;
        let o = Vec3::new(x, 0.5, 0.31) - offset;
        let free = tracer.unoccluded(&scene, o, Vec3::Y, 2.0);
        assert_eq!(free, k % PERIOD >= PERIOD - CUT, "texel {k} at x = {x}");
        let hit = tracer.trace(&scene, o, Vec3::Y, 2.0);
        assert_eq!(hit.is_none(), free, "closest hit agrees with occlusion at texel {k}");
    }
    // BLEND 0.4: 40 % of rays stop (binomial, 20000 rays: 5 sd = 1.7 %).
    let scene = import(&canopy_scene(Canopy::Blend(0.4)));
    let offset = scene.origin_offset.as_vec3();
    let tracer = Tracer::new(&scene);
    let mut rng = Rng::new(3, 0, 0, 0);
    let n = 20000;
    let stopped = (0..n)
        .filter(|_| {
            let o = Vec3::new(rng.next_f32() * 1.6 - 0.8, 0.5, rng.next_f32() * 1.6 - 0.8) - offset;
            !tracer.unoccluded(&scene, o, Vec3::Y, 2.0)
        })
        .count();
    let frac = stopped as f64 / n as f64;
    assert!((frac - 0.4).abs() < 0.017, "BLEND 0.4 stopped {frac} of the rays");
}

#[test]
fn gpu_alpha_decisions_are_the_cpus() {
    let _gpu = common::gpu_serial();
    if !have_adapter() {
        return;
    }
    let ctx = Arc::new(GpuContext::new(&Requirements::default()).expect("adapter"));
    for canopy in [Canopy::Stripes, Canopy::Blend(0.4), Canopy::AllCut] {
        let scene: Scene = import(&canopy_scene(canopy));
        let rays_of = SceneRays::new(Arc::new(scene.clone()));
        let gpu = GpuSceneLights::new(
            &ctx,
            "alpha query",
            &rays_of,
            &Lighting::default(),
            &rays_of.emitters(),
            LightSources::NONE,
        )
        .unwrap();
        let tracer = rays_of.tracer();
        let offset = scene.origin_offset.as_vec3();
        let mut rng = Rng::new(9, 0, 0, 0);
        let mut rays = Vec::new();
        for i in 0..8000u32 {
            let o = Vec3::new(rng.next_f32() * 1.8 - 0.9, 0.2, rng.next_f32() * 1.8 - 0.9) - offset;
            let d = Vec3::new(rng.next_f32() - 0.5, 2.0, rng.next_f32() - 0.5).normalize();
            rays.push(QueryRay {
                origin: o.to_array(),
                tmax: 10.0,
                dir: d.to_array(),
                mode: i % 2,
            });
        }
        let runner = QueryRunner::new(&ctx, &gpu, rays.len()).unwrap();
        let hits = runner.run(&ctx, &rays).unwrap();
        let mut differ = 0;
        let mut stopped = 0;
        for (r, h) in rays.iter().zip(&hits) {
            let (o, d) = (Vec3::from(r.origin), Vec3::from(r.dir));
            let cpu_stops = if r.mode == 1 {
                !tracer.unoccluded(&scene, o, d, r.tmax)
            } else {
                tracer.trace(&scene, o, d, r.tmax).is_some()
            };
            let gpu_stops = if r.mode == 1 { h.slot == 1 } else { h.slot != BVH_MISS };
            differ += usize::from(cpu_stops != gpu_stops);
            stopped += usize::from(gpu_stops);
        }
        eprintln!(
            "{canopy:?}: {stopped} of {} rays stopped, {differ} decided otherwise than the CPU",
            rays.len()
        );
        // MASK: only rays within an ulp of a stripe edge may differ; BLEND: the same hash
        // on both sides, only a draw within rounding of the coverage may differ.
        assert!(differ <= rays.len() / 1000, "{canopy:?}: {differ} rays differ");
        match canopy {
            Canopy::AllCut => assert_eq!(stopped, 0),
            _ => assert!(stopped > rays.len() / 5, "{canopy:?}: {stopped} stopped"),
        }
    }
}

/// The shared direct-light pass (through `sdf`, whose sun it bakes): a sun straight
/// down through a BLEND canopy of alpha 0.4 leaves 60 % of its irradiance under it.
#[test]
fn the_direct_light_pass_passes_the_sun_through_blend_in_proportion() {
    let _gpu = common::gpu_serial();
    if !have_adapter() {
        return;
    }
    let sun = Sun {
        direction: Vec3::NEG_Y,
        radiance: Vec3::splat(1.0),
        angular_diameter: 0.53f32.to_radians(),
    };
    let lighting = Lighting {
        sky: None,
        sun: Some(sun),
    };
    let scene = import(&canopy_scene(Canopy::Blend(0.4)));
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) = bake(scene, 96, lighting, "sdf", json!({}), 16);
    let e = (sun.radiance * sun.solid_angle()).x / std::f32::consts::PI;
    let under = |t: &Texel| {
        let p = t.position + offset;
        t.geo_normal.y > 0.99 && p.y.abs() < 1e-3 && p.x.abs() < 0.8 && p.z.abs() < 0.8
    };
    let (_, se, n) = assert_unbiased(
        &atlas,
        &est,
        under,
        |_| Vec3::splat(0.6 * e),
        1e-3,
        "sun through BLEND 0.4",
    );
    assert!(
        n > 200 && se < 0.01,
        "{n} texels, standard error {se}: too few to tell 0.6 from 0.55"
    );
}

#[test]
fn plans_say_where_alpha_is_tested() {
    let scene = import(&canopy_scene(Canopy::Stripes));
    let plan = |technique: &str| {
        plan_for(
            &scene,
            &BakeRequest {
                technique: technique.into(),
                lighting: upper_sky(),
                ..Default::default()
            },
        )
        .expect("plan")
    };
    for technique in ["path", "vpl", "hemicube", "obscurance"] {
        let p = plan(technique);
        assert!(p.runs("alpha test"), "{technique}");
        assert!(!p.left_out.iter().any(|i| i.name.contains("alpha")), "{technique}");
    }
    // sdf's distance field holds occupancy, sdb's k x k lookup closes fine cut-outs: their
    // plans say so.
    for (technique, what) in [("sdf", "signed distance field"), ("sdb", "k x k map lookup")] {
        let p = plan(technique);
        assert!(p.runs("alpha test"), "{technique}");
        let item = p
            .left_out
            .iter()
            .find(|i| i.name == "alpha test elsewhere")
            .unwrap_or_else(|| panic!("{technique} says what sees alpha as opaque"));
        assert!(
            item.why.contains(what) && item.why.contains("opaque"),
            "{technique}: {}",
            item.why
        );
    }
    // No alpha material, no alpha line.
    let opaque = import(&canopy_scene(Canopy::Opaque));
    let p = plan_for(
        &opaque,
        &BakeRequest {
            technique: "sdb".into(),
            lighting: upper_sky(),
            ..Default::default()
        },
    )
    .unwrap();
    assert!(!p.runs("alpha test") && !p.left_out.iter().any(|i| i.name.contains("alpha")));
}

/// Mean E/π over the ground texels under and around the canopy, and the closed form's
/// mean over the same texels.
fn ground_means(technique: &str, params: serde_json::Value, steps: u64, canopy: Canopy) -> (f64, f64) {
    let scene = import(&canopy_scene(canopy));
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) = bake(scene, 48, upper_sky(), technique, params, steps);
    let (mut got, mut want, mut n) = (0.0, 0.0, 0);
    for (k, t) in atlas.texels.iter().enumerate() {
        let p = t.position + offset;
        if t.geo_normal.y > 0.99 && p.y.abs() < 1e-3 && p.x.abs() < 1.5 && p.z.abs() < 1.5 {
            got += common::lum(est.total[k]);
            want += closed_form(canopy, p.x as f64, p.z as f64);
            n += 1;
        }
    }
    assert!(n > 100, "{technique}: {n} ground texels");
    (got / n as f64, want / n as f64)
}

/// The map techniques alpha-test in their depth maps, layers and shadow atlases. Under a
/// stripes or BLEND canopy:
/// - `vpl`, `obscurance`, `hemicube`: the ground reads the closed form to within the
///   technique's own bias on the same scene with an opaque canopy (measured here) plus 2 %,
///   and the canopy's effect (what the cut-outs add over the opaque canopy) is the closed
///   form's to within 25 %;
/// - `sdb`: its k x k lookup takes the nearest sample in front among k² map pixels, which
///   closes cut-outs finer than k pixels: at the default k = 5 almost none of the light
///   through them arrives, at k = 1 about half (its overdraw bias, the same that lets
///   +20 % through the opaque canopy). Its plan says so; this checks those figures.
///
/// (`sdf` is not here: its distance field holds occupancy; its k and α, fitted to
/// alpha-tested CPU rays, absorb cut-outs only on average over the scene, which on this
/// one-object scene happens to give 80 % of the effect; its plan says so.)
#[test]
fn canopy_closed_form_holds_for_the_map_techniques() {
    let _gpu = common::gpu_serial();
    if !have_adapter() {
        return;
    }
    // (technique, params, steps, allowed range of the effect ratio)
    let runs = [
        ("vpl", json!({"vpls_per_step": 256, "vpl_map_size": 32}), 8, (0.8, 1.25)),
        ("obscurance", json!({"map_size": 256}), 8, (0.8, 1.25)),
        ("hemicube", json!({"shooters_per_step": 16}), 8, (0.8, 1.25)),
        (
            "sdb",
            json!({"map_size": 128, "directions_per_step": 64}),
            4,
            (0.0, 0.25),
        ),
        (
            "sdb",
            json!({"map_size": 128, "directions_per_step": 64, "neighbourhood": 1}),
            4,
            (0.35, 0.7),
        ),
    ];
    for (technique, params, steps, (lo, hi)) in runs {
        let means: Vec<(f64, f64)> = CANOPIES
            .iter()
            .map(|(canopy, _)| ground_means(technique, params.clone(), steps, *canopy))
            .collect();
        let line: Vec<String> = CANOPIES
            .iter()
            .zip(&means)
            .map(|((_, label), (got, want))| {
                format!("{label}: {got:.4} vs {want:.4} ({:+.2} %)", 100.0 * (got / want - 1.0))
            })
            .collect();
        eprintln!("{technique} {params}: {}", line.join("; "));
        let (opaque, opaque_want) = means[0];
        let bias = (opaque / opaque_want - 1.0).abs();
        for (k, (canopy, label)) in CANOPIES.iter().enumerate().skip(1) {
            let (got, want) = means[k];
            if !matches!(canopy, Canopy::AllCut) {
                let ratio = (got - opaque) / (want - opaque_want);
                assert!(
                    (lo..=hi).contains(&ratio),
                    "{technique} {params}, {label}: the cut-outs add {:.4}, the closed form {:.4} (ratio {ratio:.2}, expected {lo}..{hi})",
                    got - opaque,
                    want - opaque_want
                );
            }
            if lo > 0.5 || matches!(canopy, Canopy::AllCut) {
                assert!(
                    (got / want - 1.0).abs() <= bias.max(0.02) + 0.02,
                    "{technique} {params}, {label}: {got:.4} vs {want:.4}, beyond its opaque-canopy bias {bias:.4} + 2 %"
                );
            }
        }
    }
}

/// An alpha texture that cannot be decoded is refused at import, naming the image (a
/// MASK material would otherwise have no coverage to test).
#[test]
fn an_unreadable_alpha_texture_names_the_image() {
    let (json, mut bin) = canopy_scene(Canopy::Stripes).to_gltf();
    let view = &json["bufferViews"][json["images"][0]["bufferView"].as_u64().unwrap() as usize];
    let (at, len) = (
        view["byteOffset"].as_u64().unwrap() as usize,
        view["byteLength"].as_u64().unwrap() as usize,
    );
    bin[at..at + len].fill(0);
    let err = import_slice(&write_glb(&json, &bin), None).expect_err("an undecodable image is refused");
    let text = err.to_string();
    assert!(text.contains("image 0") && text.contains("cannot decode"), "{text}");
}
