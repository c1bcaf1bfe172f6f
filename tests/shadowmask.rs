//! The shadowmask layer (`engine::shadowmask`, issue 26 points 3 and 4) on lavapipe in CI.
//!
//! - A sun-lit ground with a wall: at every ground texel the mask equals the fraction of
//!   the sun's disc that the wall leaves visible, computed here independently by a
//!   quadrature over the disc with an exact ray-rectangle test, and the penumbra's width
//!   is the closed form h/tan(e − r) − h/tan(e + r) of the disc's angular radius r.
//! - Consistency, for an unbiased technique (`path`) and one that bakes its direct light
//!   through the shared module (`sdf`): with the sun masked, the lightmap plus
//!   mask × the sun's unshadowed E/pi is the lightmap baked without a mask, `direct.*`
//!   keeps only the unmasked point light (its closed form), and the bounce is unchanged.
//! - The EXR carries `shadowmask.R`/`.G` and the header names the lights.
//!
//! The tests fail, not skip, without an adapter under `LIGHTMAPD_REQUIRE_GPU=1`.

mod common;

use std::f32::consts::PI;
use std::sync::Arc;

use common::{have_adapter, import, lum};
use exr::prelude::{ReadChannels, ReadLayers};
use glam::Vec3;
use lightmapd::engine::bake::StopCriteria;
use lightmapd::engine::job::{BakeRequest, BakeResult, bake_unobserved};
use lightmapd::engine::output::OutputLayer;
use lightmapd::engine::post::denoised::Denoiser;
use lightmapd::engine::scene::build::{LightDesc, MaterialDesc, SceneBuilder};
use lightmapd::engine::scene::{Lighting, Scene, Sun};

/// The sun 45 degrees up, its light travelling toward +x, with a large disc (8 degrees)
/// so the penumbra spans several texels.
fn sun() -> Sun {
    Sun {
        direction: Vec3::new(1.0, -1.0, 0.0).normalize(),
        radiance: Vec3::splat(20.0),
        angular_diameter: 8f32.to_radians(),
    }
}

const WALL_HEIGHT: f32 = 2.0;

/// A 5 m ground from x = -1 to 4 and a 2 m x 2 m wall in the plane x = 0 standing on it
/// (z from -1 to 1); `ground` is the ground's albedo. With `lamp`, a point light over the
/// ground in front of the wall.
fn scene(ground: f32, lamp: bool) -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let g = b.material(MaterialDesc::diffuse("ground", [ground; 3]));
    let w = b.material(MaterialDesc::diffuse("wall", [0.0; 3]).two_sided());
    b.square("ground", Vec3::new(1.5, 0.0, 0.0), 5.0, Vec3::Y, g);
    b.square(
        "wall",
        Vec3::new(0.0, WALL_HEIGHT / 2.0, 0.0),
        WALL_HEIGHT,
        Vec3::NEG_X,
        w,
    );
    if lamp {
        b.light(LightDesc::Point {
            position: Vec3::new(-0.6, 1.2, 0.3),
            color: [1.0, 0.8, 0.6],
            intensity: 2.0,
        });
    }
    b
}

fn request(technique: &str, outputs: &[OutputLayer], masked: &[&str], steps: u64) -> BakeRequest {
    BakeRequest {
        technique: technique.into(),
        resolution: 64,
        lighting: Lighting {
            sky: None,
            sun: Some(sun()),
        },
        stop: StopCriteria {
            steps: Some(steps),
            seconds: None,
            target_error: None,
        },
        outputs: outputs.to_vec(),
        shadowmask_lights: masked.iter().map(|s| s.to_string()).collect(),
        denoise: Denoiser::None,
        seed: 3,
        ..Default::default()
    }
}

fn run(scene: &Scene, r: &BakeRequest) -> BakeResult {
    bake_unobserved(Arc::new(scene.clone()), r).unwrap_or_else(|e| panic!("{} bake: {e}", r.technique))
}

/// The fraction of the sun's disc seen from ground point `p` past the wall (x = 0,
/// 0 <= y <= WALL_HEIGHT, |z| <= 1), by a 256 x 256 quadrature uniform in solid angle over
/// the disc (cos theta uniform, phi uniform: midpoints), each direction tested against the
/// wall's rectangle exactly.
fn visible_fraction(p: Vec3, s: &Sun) -> f32 {
    let axis = -s.direction;
    let cos_max = (0.5 * s.angular_diameter).cos();
    let t = axis.cross(Vec3::Z).normalize();
    let b = axis.cross(t);
    let n = 256;
    let mut seen = 0u32;
    for i in 0..n {
        let cos_t = 1.0 - (i as f32 + 0.5) / n as f32 * (1.0 - cos_max);
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        for j in 0..n {
            let phi = 2.0 * PI * (j as f32 + 0.5) / n as f32;
            let w = t * (sin_t * phi.cos()) + b * (sin_t * phi.sin()) + axis * cos_t;
            // The ray p + k w meets the plane x = 0 at k = -p.x / w.x (toward -x only).
            let blocked = w.x < 0.0 && p.x > 0.0 && {
                let k = -p.x / w.x;
                let hit = p + w * k;
                hit.y >= 0.0 && hit.y <= WALL_HEIGHT && hit.z.abs() <= 1.0
            };
            if !blocked && w.y > 0.0 {
                seen += 1;
            }
        }
    }
    seen as f32 / (n * n) as f32
}

#[test]
fn sun_shadowmask_is_the_visible_fraction_of_the_disc() {
    if !have_adapter() {
        return;
    }
    let scene = import(&scene(0.0, false));
    let offset = scene.origin_offset.as_vec3();
    let r = run(&scene, &request("path", &[OutputLayer::Shadowmask], &[], 40));
    let mask = r.estimate.shadowmask.as_ref().expect("a shadowmask was asked for");
    assert_eq!(mask.lights, vec!["sun".to_string()]);
    let s = sun();
    let (mut checked, mut sum_abs, mut worst) = (0usize, 0.0f64, (0.0f32, Vec3::ZERO));
    // (x, mask) of ground texels near z = 0, to measure the penumbra's width.
    let mut profile: Vec<(f32, f32)> = Vec::new();
    let mut texel = 0.0f32;
    for (k, t) in r.atlas.texels.iter().enumerate() {
        let p = t.position + offset;
        if t.geo_normal.y < 0.99 || p.y.abs() > 1e-3 {
            continue;
        }
        let want = visible_fraction(p, &s);
        let got = mask.values[k][0];
        assert!(
            (got - want).abs() < 0.1,
            "ground {p}: mask {got}, the disc's visible fraction {want}"
        );
        let d = (got - want).abs();
        sum_abs += d as f64;
        if d > worst.0 {
            worst = (d, p);
        }
        checked += 1;
        texel = texel.max(t.size);
        if p.z.abs() < 0.3 {
            profile.push((p.x, got));
        }
        for c in 1..4 {
            assert_eq!(mask.values[k][c], 0.0, "unused channel {c}");
        }
    }
    let mean_abs = sum_abs / checked as f64;
    eprintln!("{checked} ground texels: mean |mask - quadrature| {mean_abs:.4}, worst {worst:?}");
    assert!(checked > 400, "{checked} ground texels");
    // (16 + 40) x 8 = 448 disc samples a texel: a binary fraction's standard error <= 0.024.
    assert!(mean_abs < 0.01, "mean |mask - quadrature| {mean_abs}, worst {worst:?}");

    // The penumbra's width at z near 0, where the wall is as good as infinite: from the
    // last texel with mask < 0.02 to the first with mask > 0.98, against
    // h / tan(e - r) - h / tan(e + r), within a texel or so.
    let e = 45f32.to_radians();
    let rad = 0.5 * s.angular_diameter;
    let (x_umbra, x_lit) = (WALL_HEIGHT / (e + rad).tan(), WALL_HEIGHT / (e - rad).tan());
    profile.sort_by(|a, b| a.0.total_cmp(&b.0));
    let dark_end = profile
        .iter()
        .filter(|(x, m)| *x > 0.05 && *m < 0.02)
        .map(|(x, _)| *x)
        .fold(f32::MIN, f32::max);
    let lit_start = profile
        .iter()
        .filter(|(x, m)| *x > 0.05 && *m > 0.98)
        .map(|(x, _)| *x)
        .fold(f32::MAX, f32::min);
    eprintln!(
        "penumbra {dark_end:.3} to {lit_start:.3} m, closed form {x_umbra:.3} to {x_lit:.3} (texel {texel:.3} m)"
    );
    assert!(
        (dark_end - x_umbra).abs() < 1.5 * texel && (lit_start - x_lit).abs() < 1.5 * texel,
        "penumbra from {dark_end} to {lit_start}, closed form {x_umbra} to {x_lit}"
    );
    assert!(
        ((lit_start - dark_end) - (x_lit - x_umbra)).abs() < 2.5 * texel,
        "penumbra width {} vs {}",
        lit_start - dark_end,
        x_lit - x_umbra
    );
    // In front of the wall: the whole disc.
    for (x, m) in &profile {
        if *x < -0.05 {
            assert!((*m - 1.0).abs() < 1e-6, "open ground x = {x}: {m}");
        }
    }
}

/// The sun's E/pi at a texel with normal `n` and no shadow.
fn sun_unshadowed(n: Vec3) -> Vec3 {
    let s = sun();
    s.radiance * s.solid_angle() * (-s.direction).dot(n).max(0.0) / PI
}

#[test]
fn masked_sun_leaves_the_lightmap_and_direct_layer_consistently() {
    if !have_adapter() {
        return;
    }
    let scene = import(&scene(0.5, true));
    let offset = scene.origin_offset.as_vec3();
    let lamp = scene.lights[0].clone();
    for (technique, steps) in [("path", 24), ("sdf", 24)] {
        let full = run(
            &scene,
            &request(technique, &[OutputLayer::Direct, OutputLayer::Indirect], &[], steps),
        );
        let masked = run(
            &scene,
            &request(
                technique,
                &[OutputLayer::Direct, OutputLayer::Indirect, OutputLayer::Shadowmask],
                &["sun"],
                steps,
            ),
        );
        assert!(
            masked.summary.plan.passes.iter().any(|p| p.name == "shadowmask"),
            "the plan lists the shadowmask"
        );
        let mask = masked.estimate.shadowmask.as_ref().unwrap();
        let (fd, md) = (
            full.estimate.direct.as_ref().unwrap(),
            masked.estimate.direct.as_ref().unwrap(),
        );
        let (mut sum_full, mut sum_rebuilt, mut sum_ind_full, mut sum_ind_masked) = (0.0, 0.0, 0.0, 0.0);
        let mut lamp_checked = 0;
        for (k, t) in masked.atlas.texels.iter().enumerate() {
            let sun_e = sun_unshadowed(t.normal) * mask.values[k][0];
            sum_full += lum(full.estimate.total[k]);
            sum_rebuilt += lum(masked.estimate.total[k] + sun_e);
            sum_ind_full += lum(full.estimate.total[k] - fd[k]);
            sum_ind_masked += lum(masked.estimate.total[k] - md[k]);
            // Where the sun's disc is wholly visible or wholly hidden, direct.* is the
            // point light alone, exactly (a delta light: one shadow ray, no noise).
            let p = t.position + offset;
            let m = mask.values[k][0];
            if t.geo_normal.y > 0.99 && p.y.abs() < 1e-3 && (m == 0.0 || m == 1.0) && p.x < -0.05 {
                // The scene's lights and texels share the import's frame (offset removed).
                let to = lamp.position - t.position;
                let d = to.length();
                let want = lamp.intensity * (to / d).dot(t.normal).max(0.0) / (PI * d * d);
                // What is left of the sun is the two estimators' noise: the cosine over
                // the 8-degree disc varies by +-5 %, a few per cent of its E/pi a sample.
                let sun_left = 0.02 * sun_unshadowed(t.normal).x;
                assert!(
                    (md[k] - want).abs().max_element() < sun_left + 1e-3 * want.max_element(),
                    "{technique}: direct at {p} (mask {m}) is {}, the lamp alone {want}",
                    md[k]
                );
                lamp_checked += 1;
            }
        }
        assert!(
            lamp_checked > 50,
            "{technique}: {lamp_checked} texels checked for the lamp"
        );
        let rel = |a: f64, b: f64| (a - b).abs() / b;
        eprintln!(
            "{technique}: rebuilt/full {:.5}, bounce masked/unmasked {:.5}, {lamp_checked} lamp texels, error {:?}",
            sum_rebuilt / sum_full,
            sum_ind_masked / sum_ind_full,
            masked.estimate.error.relative
        );
        assert!(
            rel(sum_rebuilt, sum_full) < 0.01,
            "{technique}: lightmap + mask x sun {sum_rebuilt} vs the unmasked lightmap {sum_full}"
        );
        assert!(
            rel(sum_ind_masked, sum_ind_full) < 0.03,
            "{technique}: the bounce with the sun masked {sum_ind_masked} vs unmasked {sum_ind_full}"
        );
        // The reported error covers the darker lightmap: it is relative to its own RMS.
        let e = masked.estimate.error;
        assert!(
            e.relative.is_some_and(|r| r.is_finite() && r > 0.0),
            "{technique}: {e:?}"
        );
    }
}

#[test]
fn the_exr_names_each_channels_light() {
    if !have_adapter() {
        return;
    }
    let scene = import(&scene(0.5, true));
    let r = run(
        &scene,
        &request("sdf", &[OutputLayer::Shadowmask], &["light 0", "sun"], 4),
    );
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(r.first_page().to_vec()))
        .unwrap();
    let layer = &image.layer_data[0];
    let names: Vec<String> = layer.channel_data.list.iter().map(|c| c.name.to_string()).collect();
    assert!(names.contains(&"shadowmask.R".to_string()) && names.contains(&"shadowmask.G".to_string()));
    assert!(
        !names.contains(&"shadowmask.B".to_string()),
        "two lights, two channels: {names:?}"
    );
    let attr = layer
        .attributes
        .other
        .get(&exr::prelude::Text::from("lightmapd:shadowmask"))
        .expect("the header names the lights");
    match attr {
        exr::meta::attribute::AttributeValue::Text(t) => assert_eq!(t.to_string(), r#"["light 0","sun"]"#),
        other => panic!("lightmapd:shadowmask is {other:?}"),
    }
    // The point light's channel is hard: every texel reads 0 or 1.
    let mask = r.estimate.shadowmask.as_ref().unwrap();
    assert!(mask.values.iter().all(|v| v[0] == 0.0 || v[0] == 1.0));
    assert!(mask.values.iter().any(|v| v[0] == 0.0) && mask.values.iter().any(|v| v[0] == 1.0));
}

#[test]
fn bad_shadowmask_requests_are_refused_before_baking() {
    let scene = import(&scene(0.5, true));
    let plan = |r: &BakeRequest| {
        lightmapd::engine::job::plan_for(&scene, r)
            .map(|_| ())
            .unwrap_err()
            .to_string()
    };
    let mut r = request("path", &[OutputLayer::Shadowmask], &["Lamp"], 1);
    assert!(plan(&r).contains("shadowmask_lights[0]: no light is called \"Lamp\"; the job has: sun, \"light 0\" (#0)"));
    r.outputs = vec![];
    r.shadowmask_lights = vec!["sun".into()];
    assert!(plan(&r).contains("shadowmask_lights names lights but outputs has no \"shadowmask\""));
    r.outputs = vec![OutputLayer::Shadowmask, OutputLayer::Sh];
    assert!(plan(&r).contains("outputs: \"shadowmask\" and \"sh\" cannot be baked together"));
}
