//! The stiff and extreme cases of DESIGN §5, for every technique (issue 6). The suite is
//! table-driven: `stability_suite!` generates one test per case for a technique row, so
//! a new technique adds one line at the bottom with the bias it is allowed.
//!
//! Every case asserts a value; the figures each prints (run with `--nocapture`) are the
//! ones in `docs/stability.md`.

mod common;

use std::sync::Arc;

use common::{assert_unbiased, bake, import, lum};
use glam::Vec3;
use lightmapd::engine::atlas::Texel;
use lightmapd::engine::bake::StopCriteria;
use lightmapd::engine::job::{self, BakeRequest};
use lightmapd::engine::output::OutputLayer;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder, cornell_box, write_glb};
use lightmapd::engine::scene::library::{closed_box as closed_box_builder, rect_form_factor, upper_sky};
use lightmapd::engine::scene::{Lighting, Scene, import_slice};
use lightmapd::engine::technique::{self, LightSource};
use serde_json::{Value, json};

/// A technique under test: its parameters, the relative bias it is allowed on top of its
/// noise (0 for an unbiased technique), and the cases it is known to fail, each documented
/// with its measured value in `docs/stability.md`. A known failure still runs and still
/// asserts what must hold whatever the technique (finite values, the light's ordering),
/// and its mean relative deviation from the closed form must stay within the bound the
/// row states for it (measured, with a margin): a regression fails, an open failure
/// stays visible.
#[derive(Clone)]
pub struct Row {
    pub technique: &'static str,
    pub params: Value,
    pub bias: f64,
    /// (case, largest |mean relative deviation| allowed).
    pub open_failures: &'static [(&'static str, f64)],
    /// Seeds the connected rooms are baked with, their room means averaged: more than one
    /// where one 32-step bake's room means are noise-dominated ([`connected_rooms`]).
    pub room_seeds: u64,
}

impl Row {
    /// The bound of an open failure, or None when the case must pass.
    fn fails(&self, case: &str) -> Option<f64> {
        self.open_failures.iter().find(|(c, _)| *c == case).map(|(_, b)| *b)
    }
}

/// The case names `Row::open_failures` may list.
pub const TINY_EMITTER: &str = "tiny bright emitter";
/// The closed boxes, lit by their own emission only.
pub const STIFF_BOX: &str = "stiff closed box";
/// Coincident back-to-back single-sided sheets.
pub const BACK_TO_BACK: &str = "back-to-back sheets";

/// Whether `row`'s technique transports emitted light (its technique-table row says).
fn bakes_emitters(row: &Row) -> bool {
    technique::entry(row.technique)
        .unwrap()
        .lights
        .contains(&LightSource::Emitters)
}

/// For a technique that does not transport emitted light, an emitter-lit case is refused
/// before baking (issue 21): checks the refusal names the emitters and says so. For every
/// other technique checks the job is accepted, and returns false (the case bakes).
fn refused_for_emitters(row: &Row, scene: &Scene, lighting: Lighting) -> bool {
    let request = BakeRequest {
        technique: row.technique.into(),
        lighting,
        ..Default::default()
    };
    match job::plan_for(scene, &request) {
        Ok(_) => {
            assert!(
                bakes_emitters(row),
                "{}: an emitter-lit job should be refused",
                row.technique
            );
            false
        }
        Err(e) => {
            let msg = e.to_string();
            assert!(
                !bakes_emitters(row) && e.is_bad_input() && msg.contains("emissive triangle(s)"),
                "{}: {msg}",
                row.technique
            );
            eprintln!("{} refuses the case before baking: {msg}", row.technique);
            true
        }
    }
}

fn closed_box(rho: f32) -> Scene {
    import(&closed_box_builder(rho))
}

/// Closed box, Le = 1 − ρ so the answer is 1 whatever ρ: the stiff case where hundreds
/// or thousands of bounces matter.
pub fn stiff_closed_box(row: &Row, rho: f32) {
    let scene = closed_box(rho);
    if refused_for_emitters(row, &scene, Lighting::default()) {
        return;
    }
    let baked = common::try_bake(scene, 16, Lighting::default(), row.technique, row.params.clone(), 8);
    let (atlas, est) = match baked {
        Ok(b) => b,
        // A bake the adapter cannot finish (llvmpipe's loop budget cuts `path`'s longest
        // paths on the GPU) must be refused with that reason, never delivered dark.
        Err(e) if row.fails(STIFF_BOX).is_some() && e.to_string().contains("loop budget") => {
            eprintln!("{} closed box rho={rho} (open failure): refused: {e}", row.technique);
            return;
        }
        Err(e) => panic!("{} closed box rho={rho}: {e}", row.technique),
    };
    assert!(est.total.iter().all(|v| v.is_finite()), "non-finite texel");
    if let Some(bound) = row.fails(STIFF_BOX) {
        // Whatever the technique: finite and never negative; the deviation from the
        // closed form (1) within the row's stated bound.
        assert!(est.total.iter().all(|v| v.min_element() >= 0.0), "negative texel");
        let (dev, se) = common::mean_deviation(&atlas, &est, |_| true, |_| Vec3::ONE);
        eprintln!(
            "{} closed box rho={rho} (open failure): mean relative deviation {dev:+.4}, standard error {se:.4}",
            row.technique
        );
        assert!(
            dev.abs() <= bound,
            "closed box rho={rho}: deviation {dev:+.4} beyond the stated {bound}"
        );
        return;
    }
    let (dev, se, _) = assert_unbiased(
        &atlas,
        &est,
        |_| true,
        |_| Vec3::ONE,
        row.bias,
        &format!("{} closed box rho={rho}", row.technique),
    );
    // The bound: within 2 % (and the data must be able to show it).
    assert!(
        dev.abs() < 0.02 && 5.0 * se < 0.02,
        "deviation {dev}, standard error {se}"
    );
}

/// An emitter of radiance 1e6 on 1 cm² (area 1e-4) 1 m above a black plane, beside a sky
/// of 1e-3: no NaN or infinity, and the plane reads the small source's form factor.
pub fn tiny_bright_emitter(row: &Row) {
    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.0; 3], [1e6; 3]));
    b.square("ground", Vec3::ZERO, 4.0, Vec3::Y, black);
    b.square("lamp", Vec3::new(0.0, 1.0, 0.0), 0.01, Vec3::NEG_Y, lamp);
    let scene = import(&b);
    let offset = scene.origin_offset.as_vec3();
    let sky = 1e-3f32;
    if refused_for_emitters(row, &scene, upper_sky(sky)) {
        return;
    }
    // The ground chart is centred at u = v = 0.25: a texel centre for W = 62.
    let (atlas, est) = bake(scene, 62, upper_sky(sky), row.technique, row.params.clone(), 8);
    assert!(est.total.iter().all(|v| v.is_finite()), "non-finite texel");
    let on_ground = |t: &Texel| t.geo_normal.y > 0.99 && (t.position.y + offset.y).abs() < 0.01;
    let expected = |t: &Texel| {
        let p = t.position + offset;
        let f = rect_form_factor(p.x as f64, p.z as f64, -0.005, 0.005, -0.005, 0.005, 1.0 - p.y as f64);
        // The lamp's own square hides that much sky.
        Vec3::splat((1e6 * f + sky as f64 * (1.0 - f)) as f32)
    };
    if let Some(bound) = row.fails(TINY_EMITTER) {
        // Whatever the technique: finite (checked above) and never below the sky's own
        // light; the deviation from the closed form within the row's stated bound.
        let ground: Vec<f64> = atlas
            .texels
            .iter()
            .zip(&est.total)
            .filter(|(t, _)| on_ground(t))
            .map(|(_, v)| lum(*v))
            .collect();
        assert!(ground.iter().all(|&g| g >= 0.99e-3), "ground below the sky's own light");
        let (dev, _) = common::mean_deviation(&atlas, &est, on_ground, expected);
        let peak = ground.iter().copied().fold(0.0, f64::max);
        eprintln!(
            "{} tiny bright emitter (open failure): mean relative deviation {dev:+.3}, brightest ground texel {peak:.1} (exact 31.8)",
            row.technique
        );
        assert!(
            dev.abs() <= bound,
            "tiny emitter: deviation {dev:+.4} beyond the stated {bound}"
        );
        return;
    }
    assert_unbiased(
        &atlas,
        &est,
        on_ground,
        expected,
        row.bias,
        &format!("{} tiny bright emitter", row.technique),
    );
    // Directly below: about Le·A/(π h²) = 31.8.
    let centre = atlas
        .texels
        .iter()
        .position(|t| on_ground(t) && (t.position + offset).x.abs() < 1e-4 && (t.position + offset).z.abs() < 1e-4);
    let k = centre.expect("a texel near the axis");
    assert!(
        (lum(est.total[k]) - 31.83).abs() < 0.05 * 31.83,
        "below the lamp: {}",
        est.total[k]
    );
}

/// The Cornell box baked as given, scaled by 1e-3 and 1e4, and translated by 1e5: the
/// lightmap may differ by at most 1 % RMS (irradiance does not depend on scale or place).
pub fn scale_and_translation_invariance(row: &Row) {
    // A technique that does not transport emitted light is checked under a sky instead,
    // with the emitter turned off (the box is open at the front): invariance must hold
    // for the light it bakes.
    let mut cornell = cornell_box();
    if !bakes_emitters(row) {
        cornell.materials.iter_mut().for_each(|m| m.emission = [0.0; 3]);
    }
    let (json, bin) = cornell.to_gltf();
    let bake_with = |transform: Option<Value>| {
        let mut json = json.clone();
        if let Some(t) = transform {
            let n = json["nodes"].as_array().unwrap().len();
            let mut parent = t;
            parent["children"] = json!((0..n).collect::<Vec<_>>());
            json["nodes"].as_array_mut().unwrap().push(parent);
            json["scenes"][0]["nodes"] = json!([n]);
        }
        let scene = import_slice(&write_glb(&json, &bin), None).unwrap().0;
        let lighting = if !bakes_emitters(row) {
            upper_sky(1.0)
        } else {
            Lighting::default()
        };
        bake(scene, 32, lighting, row.technique, row.params.clone(), 4).1
    };
    let base = bake_with(None);
    let rms = |v: &[Vec3]| (v.iter().map(|x| lum(*x).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
    for (name, t) in [
        ("scaled 1e-3", json!({"scale": [1e-3, 1e-3, 1e-3]})),
        ("scaled 1e4", json!({"scale": [1e4, 1e4, 1e4]})),
        ("translated 1e5", json!({"translation": [1e5, 1e5, -1e5]})),
    ] {
        let other = bake_with(Some(t));
        let diff: Vec<Vec3> = base.total.iter().zip(&other.total).map(|(a, b)| *a - *b).collect();
        let rel = rms(&diff) / rms(&base.total);
        eprintln!("{} {name}: RMS difference {rel:.2e}", row.technique);
        assert!(rel <= 0.01, "{name}: RMS difference {rel}");
    }
}

/// Zero-area, sliver and coplanar duplicate triangles on a plane under the sky: import
/// drops what has no area, nothing is NaN, and the plane still reads the sky.
pub fn degenerate_and_coplanar_geometry(row: &Row) {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("ground", Vec3::ZERO, 4.0, Vec3::Y, m);
    b.square("ground copy", Vec3::ZERO, 4.0, Vec3::Y, m); // coplanar, its own chart
    // A sliver 1e-7 m wide and a triangle with two equal vertices, floating above.
    let sliver = b.quad(
        "sliver",
        Vec3::new(-1.0, 1.0, 0.0),
        Vec3::new(2.0, 0.0, 0.0),
        Vec3::new(0.0, 0.0, 1e-7),
        m,
    );
    b.meshes[sliver].indices.extend([0, 0, 1]);
    let (json, bin) = b.to_gltf();
    let (scene, report) = import_slice(&write_glb(&json, &bin), None).unwrap();
    assert!(report.degenerate_triangles >= 1, "the zero-area triangle is dropped");
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) = bake(scene, 48, upper_sky(1.0), row.technique, row.params.clone(), 4);
    assert!(est.total.iter().all(|v| v.is_finite()));
    // Ground texels away from the sliver's shadow (|z| > 0.5) see the whole sky.
    let open = |t: &Texel| {
        let p = t.position + offset;
        t.geo_normal.y > 0.99 && p.y.abs() < 0.01 && p.z.abs() > 0.5
    };
    assert_unbiased(
        &atlas,
        &est,
        open,
        |_| Vec3::ONE,
        row.bias,
        &format!("{} coplanar ground", row.technique),
    );
}

/// Two closed rooms sharing a wall 1 mm thick (a tenth of a texel here): one lit by an
/// emissive ceiling, one dark. Whatever the dark room reads is leaked light.
pub fn thin_wall_leak(row: &Row) -> f64 {
    let mut b = SceneBuilder::new();
    let wall = b.material(MaterialDesc::diffuse("wall", [0.5; 3]));
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.5; 3], [1.0; 3]));
    let room = |b: &mut SceneBuilder, centre: Vec3, name: &str, ceiling: usize| {
        for n in [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z] {
            let mat = if n == Vec3::NEG_Y { ceiling } else { wall };
            b.square(&format!("{name} {n}"), centre - n, 2.0, n, mat);
        }
    };
    room(&mut b, Vec3::new(-1.0, 0.0, 0.0), "lit", lamp);
    room(&mut b, Vec3::new(1.001, 0.0, 0.0), "dark", wall);
    let scene = import(&b);
    if refused_for_emitters(row, &scene, Lighting::default()) {
        return 0.0;
    }
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) = bake(scene, 64, Lighting::default(), row.technique, row.params.clone(), 4);
    let (mut lit, mut dark, mut nl, mut nd) = (0.0, 0.0, 0, 0);
    for (k, t) in atlas.texels.iter().enumerate() {
        if (t.position + offset).x < 0.0 {
            lit += lum(est.total[k]);
            nl += 1;
        } else {
            dark += lum(est.total[k]);
            nd += 1;
        }
    }
    let leak = (dark / nd as f64) / (lit / nl as f64);
    eprintln!(
        "{} thin wall: dark room / lit room = {leak:.2e} ({nd} and {nl} texels)",
        row.technique
    );
    leak
}

/// Values far beyond half-float range survive to the EXR unclamped.
pub fn beyond_half_float(row: &Row) {
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.0; 3], [1e6; 3]));
    b.square("ground", Vec3::ZERO, 1.0, Vec3::Y, grey);
    // A technique that cannot bake the emitter gets the same radiance from a sky over
    // the open ground instead, which still reads far beyond half-float range: what this
    // case checks is that such values reach the EXR unclamped.
    if bakes_emitters(row) {
        b.square("lamp", Vec3::new(0.0, 0.05, 0.0), 1.0, Vec3::NEG_Y, lamp);
    }
    let scene = Arc::new(import(&b));
    let lighting = if !bakes_emitters(row) {
        upper_sky(1e6)
    } else {
        Lighting::default()
    };
    let request = BakeRequest {
        technique: row.technique.into(),
        lighting,
        resolution: 32,
        stop: StopCriteria {
            steps: Some(4),
            ..Default::default()
        },
        params: row.params.clone(),
        outputs: vec![OutputLayer::Validity],
        // The raw estimate: this case is about float range, and a denoised peak texel
        // may be the one seam stitching moves (then the EXR and the estimate differ there).
        denoise: lightmapd::engine::post::denoised::Denoiser::None,
        ..Default::default()
    };
    let result = job::bake_unobserved(scene, &request).unwrap();
    let peak = result
        .estimate
        .total
        .iter()
        .map(|v| v.max_element())
        .fold(0.0f32, f32::max);
    assert!(
        peak > 1e5,
        "the ground under a 1e6 lamp 5 cm away reads about 1e6 × 0.9, got {peak}"
    );
    use exr::prelude::{ReadChannels, ReadLayers};
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(result.first_page().to_vec()))
        .unwrap();
    let r = image.layer_data[0]
        .channel_data
        .list
        .iter()
        .find(|c| c.name.to_string() == "R")
        .unwrap();
    let exr_peak = r.sample_data.values_as_f32().fold(0.0f32, f32::max);
    assert_eq!(
        exr_peak, peak,
        "the EXR holds the float32 value, not a half-float 65504"
    );
}

/// No light anywhere: exact zeros, an error of 0 (not NaN), and a plan that says so.
pub fn no_light_at_all(row: &Row) {
    let scene = import(&cornell_box().materials.iter().fold(cornell_box(), |mut b, _| {
        for m in &mut b.materials {
            m.emission = [0.0; 3];
        }
        b
    }));
    let (_, est) = bake(
        scene.clone(),
        24,
        Lighting::default(),
        row.technique,
        row.params.clone(),
        4,
    );
    assert!(est.total.iter().all(|v| *v == Vec3::ZERO));
    assert_eq!(est.error.relative, Some(0.0));
    let request = BakeRequest {
        technique: row.technique.into(),
        ..Default::default()
    };
    let plan = lightmapd::engine::job::plan_for(&scene, &request).unwrap();
    assert!(plan.left_out.iter().any(|p| p.name == "light"), "{plan:?}");
}

// Measured at 32 steps, resolution 32, lavapipe (deviation of the lit / dark room mean
// from the 1024-sample `path` reference; docs/stability.md): path −0.3 % / −0.6 %, path on
// the GPU +1.7 % / +0.6 %, vpl +1.3 % / −4.2 % (+48 % / +45 % while crease sample points
// sat within its plane test's tolerance of the next wall), obscurance +46 % / +54 % (light
// through the creases, open), sdf −52 % / −61 % (sky visibility without
// interreflection), hemicube over seeds 1-4 +3.1 % / −16.5 % (one seed's dark room reads
// −33 % to +7 % over seeds 1-6: a 32-step bake's dark room is noise-dominated, so the
// row averages four; −7 % / −65 % on one seed before its near-field split and the
// whole-offset crease inset; the rest is light beyond 32 bounces) and sdb −20 % / −71 %
// (open: the stiff room). Each row's `rooms` bound is above its measured value, so a
// regression fails and the open failures stay visible.

/// Two rooms 2 m × 2 m × 2 m side by side, connected by a doorway in the wall they share
/// (two single-sided faces back to back), one of albedo 0.3 open to an upper sky of
/// radiance 1 on its far side, one of albedo 0.95 lit only through the doorway (issue
/// 21): the dark room's light has bounced many times. The mean of each room against the
/// `path` reference of the same scene: returns the relative deviations (lit, dark).
pub fn connected_rooms(row: &Row) -> (f64, f64) {
    const RESOLUTION: u32 = 32;
    let (ref_lit, ref_dark) = reference_rooms();
    let dev = |got: f64, want: (f64, f64)| (got - want.0) / want.0;
    let (mut lit, mut dark) = (0.0, 0.0);
    for seed in 1..=row.room_seeds {
        let (l, d) = room_means(row.technique, row.params.clone(), 32, seed);
        eprintln!(
            "{} connected rooms, seed {seed}: lit room {:.4} (path {:.4} ± {:.4}, {:+.4}), dark room {:.4} (path {:.4} ± {:.4}, {:+.4}) at {RESOLUTION}²",
            row.technique,
            l.0,
            ref_lit.0,
            ref_lit.1,
            dev(l.0, ref_lit),
            d.0,
            ref_dark.0,
            ref_dark.1,
            dev(d.0, ref_dark)
        );
        assert!(
            l.0.is_finite() && d.0.is_finite() && d.0 > 0.0,
            "the dark room must receive light"
        );
        lit += l.0 / row.room_seeds as f64;
        dark += d.0 / row.room_seeds as f64;
    }
    (dev(lit, ref_lit), dev(dark, ref_dark))
}

/// The connected rooms' scene (see [`connected_rooms`]).
fn connected_rooms_scene() -> Scene {
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("lit room", [0.3; 3]));
    let white = b.material(MaterialDesc::diffuse("dark room", [0.95; 3]));
    // A rectangle from `corner` along `u` and `v`, facing `normal` (single-sided).
    let mut rect = |name: &str, corner: Vec3, u: Vec3, v: Vec3, normal: Vec3, m: usize| {
        if u.cross(v).dot(normal) > 0.0 {
            b.quad(name, corner, u, v, m);
        } else {
            b.quad(name, corner, v, u, m);
        }
    };
    for (room, x0, m) in [("lit", -2.0f32, grey), ("dark", 0.0, white)] {
        let c = Vec3::new(x0, -1.0, -1.0);
        rect(&format!("{room} floor"), c, Vec3::X * 2.0, Vec3::Z * 2.0, Vec3::Y, m);
        rect(
            &format!("{room} ceiling"),
            c + Vec3::Y * 2.0,
            Vec3::X * 2.0,
            Vec3::Z * 2.0,
            Vec3::NEG_Y,
            m,
        );
        rect(&format!("{room} back"), c, Vec3::X * 2.0, Vec3::Y * 2.0, Vec3::Z, m);
        rect(
            &format!("{room} front"),
            c + Vec3::Z * 2.0,
            Vec3::X * 2.0,
            Vec3::Y * 2.0,
            Vec3::NEG_Z,
            m,
        );
    }
    // The dark room's far wall; the lit room's far side (x = -2) is open to the sky.
    rect(
        "dark end",
        Vec3::new(2.0, -1.0, -1.0),
        Vec3::Y * 2.0,
        Vec3::Z * 2.0,
        Vec3::NEG_X,
        white,
    );
    // The shared wall at x = 0 around a doorway 0.8 m wide and 1.6 m high, one face per room.
    let pieces = [
        (Vec3::new(0.0, -1.0, -1.0), Vec3::Y * 2.0, Vec3::Z * 0.6),
        (Vec3::new(0.0, -1.0, 0.4), Vec3::Y * 2.0, Vec3::Z * 0.6),
        (Vec3::new(0.0, 0.6, -0.4), Vec3::Y * 0.4, Vec3::Z * 0.8),
    ];
    for (k, (corner, u, v)) in pieces.into_iter().enumerate() {
        rect(&format!("wall {k} lit side"), corner, u, v, Vec3::NEG_X, grey);
        rect(&format!("wall {k} dark side"), corner, u, v, Vec3::X, white);
    }
    import(&b)
}

/// Each room's mean texel luminance and its standard error, baked by `technique`.
fn room_means(technique: &str, params: Value, steps: u64, seed: u64) -> ((f64, f64), (f64, f64)) {
    let scene = connected_rooms_scene();
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) =
        common::try_bake_seeded(scene, 32, upper_sky(1.0), technique, params, steps, seed).expect("the bake");
    let se = est.texel_error.clone().unwrap_or_else(|| vec![0.0; est.total.len()]);
    let mean = |dark: bool| {
        let (mut sum, mut var, mut n) = (0.0f64, 0.0f64, 0usize);
        for (k, t) in atlas.texels.iter().enumerate() {
            // A texel belongs to the room its surface faces into.
            let p = t.position + offset + t.geo_normal * 1e-3;
            if (p.x > 0.0) == dark {
                sum += lum(est.total[k]);
                var += (se[k] as f64).powi(2);
                n += 1;
            }
        }
        (sum / n as f64, var.sqrt() / n as f64)
    };
    (mean(false), mean(true))
}

/// The `path` reference of the connected rooms, baked once per test process.
fn reference_rooms() -> ((f64, f64), (f64, f64)) {
    static REFERENCE: std::sync::OnceLock<((f64, f64), (f64, f64))> = std::sync::OnceLock::new();
    *REFERENCE.get_or_init(|| room_means("path", json!({"samples_per_step": 32, "device": "cpu"}), 32, 1))
}

/// Coincident back-to-back single-sided sheets (issue 21): a 1 m² emitter facing down
/// (radiance 1) with a black twin facing up at the same place, 1 m above a black floor,
/// under an upper sky of radiance 1. Each side must read as if it were alone: the floor
/// sees sky or emitter, radiance 1 either way, so it reads exactly 1, and the twin's top
/// sees only sky, 1.
///
/// Measured (48², 8 steps, lavapipe), floor / twin's top: path −0.4 % / 0, the GPU path
/// +0.1 % / 0, sdb 0 / 0, vpl +0.2 % / −1.8 %, hemicube +1.3 % / 0; obscurance's floor
/// −30.2 % (open failure: its depth layers see the twin's black back where the emitter
/// is); sdf's floor +18 % (open failure: its sky visibility under the thin sheet).
pub fn back_to_back_sheets(row: &Row) {
    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.0; 3], [1.0; 3]));
    let top = Vec3::new(0.0, 1.0, 0.0);
    b.square("floor", Vec3::ZERO, 1.0, Vec3::Y, black);
    b.square("emitter", top, 1.0, Vec3::NEG_Y, lamp);
    b.square("twin", top, 1.0, Vec3::Y, black);
    let scene = import(&b);
    if refused_for_emitters(row, &scene, upper_sky(1.0)) {
        return;
    }
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) = bake(scene, 48, upper_sky(1.0), row.technique, row.params.clone(), 8);
    assert!(est.total.iter().all(|v| v.is_finite() && v.min_element() >= 0.0));
    let up = |high: bool| move |t: &Texel| t.geo_normal.y > 0.99 && ((t.position + offset).y > 0.5) == high;
    for (name, select) in [("floor", up(false)), ("twin's top", up(true))] {
        let what = format!("{} back-to-back sheets, {name}", row.technique);
        if let Some(bound) = row.fails(BACK_TO_BACK) {
            let (dev, se) = common::mean_deviation(&atlas, &est, select, |_| Vec3::ONE);
            eprintln!("{what} (open failure): mean relative deviation {dev:+.4}, standard error {se:.4}");
            assert!(
                dev.abs() <= bound,
                "{what}: deviation {dev:+.4} beyond the stated {bound}"
            );
        } else {
            // 1e-4: f32 rounding of sums of ones (the twin's top has no noise in `path`).
            assert_unbiased(&atlas, &est, select, |_| Vec3::ONE, row.bias + 1e-4, &what);
        }
    }
}

/// One test per case for technique row `$row` in module `$name`; `$leak` is the largest
/// thin-wall leak the technique is allowed.
macro_rules! stability_suite {
    ($name:ident, $row:expr, leak <= $leak:expr, rooms <= $rooms:expr) => {
        mod $name {
            use super::*;
            fn row() -> Row {
                $row
            }
            #[test]
            fn closed_box_rho_0_99() {
                stiff_closed_box(&row(), 0.99);
            }
            #[test]
            fn closed_box_rho_0_999() {
                stiff_closed_box(&row(), 0.999);
            }
            #[test]
            fn tiny_bright_emitter_beside_dim_sky() {
                tiny_bright_emitter(&row());
            }
            #[test]
            fn scale_and_translation() {
                scale_and_translation_invariance(&row());
            }
            #[test]
            fn degenerate_and_coplanar() {
                degenerate_and_coplanar_geometry(&row());
            }
            #[test]
            fn thin_wall() {
                let leak = thin_wall_leak(&row());
                assert!(leak <= $leak, "leak {leak} above {}", $leak);
            }
            #[test]
            fn values_beyond_half_float() {
                beyond_half_float(&row());
            }
            #[test]
            fn no_light() {
                no_light_at_all(&row());
            }
            #[test]
            fn back_to_back_sheets_each_lit_as_if_alone() {
                back_to_back_sheets(&row());
            }
            #[test]
            fn connected_rooms_against_path() {
                let (lit, dark) = connected_rooms(&row());
                assert!(
                    lit.abs() <= $rooms && dark.abs() <= $rooms,
                    "room means off the path reference by {lit:+.4} (lit) and {dark:+.4} (dark), bound {}",
                    $rooms
                );
            }
        }
    };
}

// The reference is unbiased: no bias allowance, and a closed wall must not leak at all
// beyond rays slipping through the cracks of non-watertight triangle tests (< 1e-4).
stability_suite!(
    path,
    Row {
        technique: "path",
        params: json!({"samples_per_step": 4}),
        bias: 0.0,
        open_failures: &[],
        room_seeds: 1,
    },
    leak <= 1e-4,
    rooms <= 0.05
);

// `path` on the GPU (technique::path::gpu, a megakernel over the GPU BVH): the CPU's
// estimator with other random streams, so the CPU row's bounds. Open failure on lavapipe
// only: llvmpipe ends an invocation's loops after 65535 iterations in all, which cut the
// stiff boxes' paths (measured -30.4 % at rho 0.99 and -81.7 % at 0.999 with 4 samples a
// step; 0.73, 0.37, 0.18 at rho 0.999 with 1, 2, 4 samples: the budget, not the
// estimator). The cut is now detected and the bake refused with that reason, which is
// what the case asserts there; elsewhere the 0.85 bound holds it.
stability_suite!(
    path_gpu,
    Row {
        technique: "path",
        params: json!({"samples_per_step": 4, "device": "gpu"}),
        bias: 0.0,
        open_failures: &[(STIFF_BOX, 0.85)],
        room_seeds: 1,
    },
    leak <= 1e-4,
    rooms <= 0.05
);

// `sdb` (average mode, 64 directions a step, default 5 x 5 neighbourhood): biased by
// design (dilation of the neighbourhood, overdraw), so cases that compare with a closed
// form allow 2 %. The thin wall leaks through overdraw, measured 0.7 %.
stability_suite!(
    sdb,
    Row {
        technique: "sdb",
        params: json!({"map_size": 128, "directions_per_step": 64}),
        bias: 0.02,
        open_failures: &[],
        room_seeds: 1,
    },
    leak <= 1e-2,
    rooms <= 0.8
);

// vpl: unbiased but for the clamp of its VPLs' 1/d^2 (light lost within 0.02 of the scene
// radius of a VPL, in corners) and shadow-map silhouettes. 256 VPLs a step, smaller VPL
// maps (32) to keep the suite fast. The stiff boxes are open failures at this case's 8
// steps: not a bias but noise (measured: rho 0.99 +1.2 % and rho 0.999 -3.0 %, standard
// errors 0.99 % and 0.91 %, where the case needs 5 standard errors under 2 %); see
// docs/vpl.md. Thin wall: measured 1.9e-4 (plane-side shadow test).
stability_suite!(
    vpl,
    Row {
        technique: "vpl",
        params: json!({"vpls_per_step": 256, "vpl_map_size": 32}),
        bias: 0.02,
        open_failures: &[(STIFF_BOX, 0.06)],
        room_seeds: 1,
    },
    leak <= 1e-3,
    rooms <= 0.1
);

// Obscurance is not a radiosity solver: one scene-wide ambient term I_A (seed Eq. 5)
// stands in for the bounces. Measured (docs/obscurance.md): the stiff closed boxes read
// 9.7 % low (corners and edges within dmax); the 1 cm^2 emitter, smaller than a map
// pixel, is light-sampled by the shared direct-light module (`emitters = auto`) and its
// brightest ground texel reads the closed form (it was missed before, -99.98 %); the dark room of the thin-wall case reads 0.30 of the lit one
// through the scene-wide I_A W, by design (its direct light, which is what would pass the
// wall, is checked to be below 1e-3 in tests/obscurance.rs), hence the leak bound. The
// bias allowance is the lateral map-pixel error of the open cases.
stability_suite!(
    obscurance,
    Row {
        technique: "obscurance",
        params: json!({"map_size": 256}),
        bias: 0.02,
        open_failures: &[(STIFF_BOX, 0.12), (BACK_TO_BACK, 0.35)],
        room_seeds: 1,
    },
    leak <= 0.35,
    rooms <= 0.65
);

// `sdf`: sky light from its distance volume, every other light from the shared
// direct-light module (GPU rays), bounced by one scene-wide ambient. Measured (lavapipe):
// - the stiff closed boxes -8.2 % at both albedos: the noise of the emitters' light
//   sampling (8 steps x 4 samples a texel here), which the scene-wide ambient shares by
//   all texels, so the texels' mean does not average it away (the furnace at 32 steps x
//   16 samples reads -0.4 %, tests/direct_light.rs). One draw of a heavy-tailed mean:
//   seeds 1-8 read -8.8 % to +3.8 % at albedo 0.99 (2026-12-06, streams keyed by pixel;
//   -5.4 % with the earlier keying by texel index); bound 0.12;
// - the back-to-back sheets' floor +18 %: the distance field's sky visibility under a
//   thin sheet (a sign the two faces disagree on, docs/sdf.md) on top of the exact
//   emitter; bound 0.25;
// - the thin wall's dark room 0.33 of the lit one: the scene-wide ambient reaches it, as
//   obscurance's does (by design; its direct light is 0, tests/direct_light.rs);
// - the open coplanar ground -3e-5 and the tiny emitter exact; the 1 % allowance is the
//   model's error on open geometry far from borders (docs/sdf.md).
stability_suite!(
    sdf,
    Row {
        technique: "sdf",
        params: json!({"resolution": 32}),
        bias: 0.01,
        open_failures: &[(STIFF_BOX, 0.12), (BACK_TO_BACK, 0.25)],
        room_seeds: 1,
    },
    leak <= 0.35,
    rooms <= 0.7
);

// hemicube: stochastic iteration, one bounce deeper per step, so the stiff closed boxes
// (albedo 0.99 and 0.999, 8 steps) cannot converge by the method's nature: an open
// failure, measured in docs/stability.md (−94.7 % and −99.5 %). Its transfer has no
// corner bias left (texel cells, the near-field split: docs/hemicube.md); the bias
// allowance covers the light level's noise, which the iteration carries from step to step.
stability_suite!(
    hemicube,
    Row {
        technique: "hemicube",
        params: json!({"shooters_per_step": 16}),
        bias: 0.05,
        open_failures: &[(STIFF_BOX, 1.0)],
        room_seeds: 4,
    },
    leak <= 1e-2,
    rooms <= 0.3
);
