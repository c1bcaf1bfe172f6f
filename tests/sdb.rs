//! `sdb` against analytic answers, on whatever adapter there is (lavapipe in CI).
//!
//! These tests skip, with a printed message, only when there is no adapter at all (and fail
//! instead under `LIGHTMAPD_REQUIRE_GPU=1`, set in `.ci/run`); any
//! other GPU error fails them.
//!
//! Tolerances follow from the technique's known bias (see the module doc of
//! `lightmapd::engine::technique::sdb`):
//! - scenes whose overdraw is 1 along every ray (an open plane, a closed box seen from
//!   inside with back faces culled) have no stochastic-depth bias at all, so what is left
//!   is Monte Carlo noise (small with stratified directions) and, with bounces, the
//!   feedback transient, which decays like n^-(1+ramp)(1-albedo);
//! - the direct pass has shadow-map bias only at shadow boundaries, which the tests stay
//!   away from by two map pixels.

mod common;

use std::f64::consts::PI;
use std::sync::Arc;

use common::{bake, import, lum};
use glam::{Vec2, Vec3};
use lightmapd::engine::gpu::{GpuContext, GpuError, Requirements};
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder, cornell_box};
use lightmapd::engine::scene::library::upper_sky;
use lightmapd::engine::scene::{Lighting, Sun};
use lightmapd::engine::technique::sdb::{
    AccumulationMode, DirectionSequence, DirectionalLight, SdbEngine, SdbInput, SdbParams, SdbTexel, SdbTriangle,
};
use serde_json::json;

/// The test context, or None (with a message) when the machine has no adapter at all.
fn context() -> Option<Arc<GpuContext>> {
    match GpuContext::new(&Requirements::default()) {
        Ok(c) => Some(Arc::new(c)),
        Err(GpuError::NoAdapter) if std::env::var("LIGHTMAPD_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("SKIPPED: no GPU adapter on this machine (install mesa-vulkan-drivers for lavapipe)");
            None
        }
        Err(e) => panic!("GPU context (LIGHTMAPD_REQUIRE_GPU=1 makes a missing adapter fatal): {e}"),
    }
}

/// A planar quad: centre, unit normal, half-size, with (t, b, n) right-handed so that
/// corners (-t-b, +t-b, +t+b, -t+b) are counter-clockwise seen from the normal's side.
struct Quad {
    centre: Vec3,
    normal: Vec3,
    t: Vec3,
    b: Vec3,
    half: f32,
    /// Lightmap rectangle [u0, v0, u1, v1].
    rect: [f32; 4],
    albedo: Vec3,
    emission: Vec3,
    double_sided: bool,
    mesh: u32,
}

impl Quad {
    fn new(centre: Vec3, normal: Vec3, half: f32, rect: [f32; 4]) -> Self {
        let n = normal.normalize();
        let (t, _) = n.any_orthonormal_pair();
        let b = n.cross(t);
        Quad {
            centre,
            normal: n,
            t,
            b,
            half,
            rect,
            albedo: Vec3::splat(0.5),
            emission: Vec3::ZERO,
            double_sided: false,
            mesh: 0,
        }
    }

    fn point(&self, alpha: f32, beta: f32) -> Vec3 {
        self.centre + self.t * ((2.0 * alpha - 1.0) * self.half) + self.b * ((2.0 * beta - 1.0) * self.half)
    }

    fn triangles(&self) -> [SdbTriangle; 2] {
        let [u0, v0, u1, v1] = self.rect;
        let p = [
            self.point(0.0, 0.0),
            self.point(1.0, 0.0),
            self.point(1.0, 1.0),
            self.point(0.0, 1.0),
        ];
        let uv = [
            Vec2::new(u0, v0),
            Vec2::new(u1, v0),
            Vec2::new(u1, v1),
            Vec2::new(u0, v1),
        ];
        let tri = |a: usize, b: usize, c: usize| SdbTriangle {
            p: [p[a], p[b], p[c]],
            lm: [uv[a], uv[b], uv[c]],
            emission: self.emission,
            emission_textured: false,
            double_sided: self.double_sided,
            mesh: self.mesh,
            material: 0,
            alpha_uv: [Vec2::ZERO; 3],
        };
        [tri(0, 1, 2), tri(0, 2, 3)]
    }
}

/// Triangles and texels of a set of quads on a W x H lightmap: a texel is valid when its
/// centre lies inside a quad's rectangle; its point is offset off the surface by 1e-4 of
/// the quad size, as the atlas does.
fn build(quads: &[Quad], width: u32, height: u32) -> (Vec<SdbTriangle>, Vec<SdbTexel>, Vec<usize>) {
    let mut tris = Vec::new();
    let mut texels = Vec::new();
    let mut owner = Vec::new();
    for q in quads {
        tris.extend(q.triangles());
    }
    for j in 0..height {
        for i in 0..width {
            let u = (i as f32 + 0.5) / width as f32;
            let v = (j as f32 + 0.5) / height as f32;
            for (k, q) in quads.iter().enumerate() {
                let [u0, v0, u1, v1] = q.rect;
                if u > u0 && u < u1 && v > v0 && v < v1 {
                    let p = q.point((u - u0) / (u1 - u0), (v - v0) / (v1 - v0));
                    texels.push(SdbTexel {
                        pixel: j * width + i,
                        position: p + q.normal * (2e-4 * q.half),
                        normal: q.normal,
                        geo_normal: q.normal,
                        albedo: q.albedo,
                        emission: q.emission,
                    });
                    owner.push(k);
                    break;
                }
            }
        }
    }
    (tris, texels, owner)
}

fn run(engine: &mut SdbEngine, steps: u32) -> Vec<Vec3> {
    let start = std::time::Instant::now();
    for _ in 0..steps {
        engine.step().expect("sdb step");
    }
    let [even, odd] = engine.read_halves().expect("read back");
    eprintln!("{steps} steps in {:.2} s", start.elapsed().as_secs_f64());
    even.total
        .iter()
        .zip(&odd.total)
        .map(|(a, b)| (*a + *b) * 0.5)
        .collect()
}

fn params(map: u32, k: u32) -> SdbParams {
    SdbParams {
        map_size: Some(map),
        neighbourhood: k,
        ..SdbParams::default()
    }
}

fn mean(v: &[Vec3]) -> Vec3 {
    v.iter().copied().sum::<Vec3>() / v.len() as f32
}

#[test]
fn open_plane_under_uniform_sky_sees_the_sky() {
    let _gpu = common::gpu_serial();
    // Single-sided quad facing +Y under a uniform sky of radiance 1 over the full sphere:
    // E/pi = 1 exactly (the upper hemisphere is unoccluded; the plane's own back face, a
    // black blocker, lies in the texels' normal plane and must be rejected).
    let Some(ctx) = context() else { return };
    let quad = Quad::new(Vec3::ZERO, Vec3::Y, 0.5, [0.0, 0.0, 1.0, 1.0]);
    let (triangles, texels, _) = build(&[quad], 16, 16);
    let input = SdbInput {
        triangles,
        texels,
        width: 16,
        height: 16,
        environment: Some(Arc::new(|_| Vec3::ONE)),
        lights: vec![],
        seed: 7,
        want_direct: false,
        ambient: None,
        small_lights: None,
        tables: None,
    };
    let mut engine = SdbEngine::new(ctx, input, params(128, 3)).unwrap();
    let e = run(&mut engine, 512);
    let m = mean(&e);
    eprintln!("mean {m}");
    // Stratified directions: the texel-average error of 512 directions is far below 1%;
    // per texel the same estimate (every texel sees the same unoccluded sky).
    assert!((m - Vec3::ONE).abs().max_element() < 0.01, "mean {m}");
    for v in &e {
        assert!((*v - Vec3::ONE).abs().max_element() < 0.02, "texel {v}");
    }
}

/// Six inward-facing quads forming a closed unit cube, each on its own lightmap block
/// with a one-texel gutter.
fn inward_cube(albedo: f32, emission: f32) -> Vec<Quad> {
    let faces = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z];
    faces
        .iter()
        .enumerate()
        .map(|(k, &axis)| {
            let (bx, by) = ((k % 3) as f32, (k / 3) as f32);
            // 3 x 2 blocks of 16 texels on a 48 x 32 map, gutter of 1 texel.
            let rect = [
                (bx * 16.0 + 1.0) / 48.0,
                (by * 16.0 + 1.0) / 32.0,
                (bx * 16.0 + 15.0) / 48.0,
                (by * 16.0 + 15.0) / 32.0,
            ];
            let mut q = Quad::new(axis * 0.5, -axis, 0.5, rect);
            q.albedo = Vec3::splat(albedo);
            q.emission = Vec3::splat(emission);
            q
        })
        .collect()
}

#[test]
fn closed_emissive_box_converges_to_the_furnace_solution() {
    let _gpu = common::gpu_serial();
    // Inside a closed box whose walls all emit L_e and reflect with albedo a, radiance is
    // L_e / (1 - a) in every direction, so E/pi = L_e / (1 - a) = 2 for a = 0.5. The
    // box is closed and single-sided: back faces are culled, overdraw is 1, and the only
    // errors are noise and the feedback transient (about n^-2(1-a) = 1/n with ramp 1).
    let Some(ctx) = context() else { return };
    let (triangles, texels, _) = build(&inward_cube(0.5, 1.0), 48, 32);
    let input = SdbInput {
        triangles,
        texels,
        width: 48,
        height: 32,
        environment: None,
        lights: vec![],
        seed: 3,
        want_direct: false,
        ambient: None,
        small_lights: None,
        tables: None,
    };
    let mut engine = SdbEngine::new(ctx, input, params(128, 3)).unwrap();
    let e = run(&mut engine, 1024);
    let m = mean(&e);
    eprintln!("mean {m}");
    assert!((m - Vec3::splat(2.0)).abs().max_element() < 0.03, "mean {m}");
    let worst = e
        .iter()
        .map(|v| (*v - Vec3::splat(2.0)).abs().max_element())
        .fold(0.0, f32::max);
    eprintln!("worst texel error {worst}");
    assert!(worst < 0.15, "worst texel error {worst}");
}

#[test]
fn leaky_mode_reaches_the_same_solution() {
    let _gpu = common::gpu_serial();
    // The seed's leaky integration, with the start-up correction, must agree with the
    // furnace answer once its memory (1/b = 50 directions) is short against the run;
    // its noise is larger (it averages only about 2/b directions), hence the tolerance.
    let Some(ctx) = context() else { return };
    let (triangles, texels, _) = build(&inward_cube(0.5, 1.0), 48, 32);
    let input = SdbInput {
        triangles,
        texels,
        width: 48,
        height: 32,
        environment: None,
        lights: vec![],
        seed: 5,
        want_direct: false,
        ambient: None,
        small_lights: None,
        tables: None,
    };
    let p = SdbParams {
        mode: AccumulationMode::Leaky,
        blend: 0.02,
        ..params(128, 3)
    };
    let mut engine = SdbEngine::new(ctx, input, p).unwrap();
    let e = run(&mut engine, 600);
    let m = mean(&e);
    eprintln!("mean {m}");
    assert!((m - Vec3::splat(2.0)).abs().max_element() < 0.1, "mean {m}");
}

#[test]
fn sun_direct_light_and_shadow() {
    let _gpu = common::gpu_serial();
    // A floor quad lit by a directional light from 60 degrees off vertical, with a
    // single-sided blocker above half of it. Unshadowed: E/pi = E_perp/pi * cos 60 = 0.5;
    // shadowed: 0 (no sky, black blocker back face... and its reflected light is zero
    // because the blocker's top is not lit from below).
    let Some(ctx) = context() else { return };
    let floor = Quad::new(Vec3::ZERO, Vec3::Y, 1.0, [0.0, 0.0, 1.0, 0.5]);
    // Blocker: facing up, above x < 0 part; the light comes straight down the y-z plane.
    let mut blocker = Quad::new(Vec3::new(-0.6, 0.3, 0.0), Vec3::Y, 0.4, [0.0, 0.5, 1.0, 1.0]);
    blocker.albedo = Vec3::ZERO;
    let mut floor = floor;
    floor.albedo = Vec3::ZERO; // no bounce: pure direct light
    let (triangles, texels, owner) = build(&[floor, blocker], 32, 32);
    let positions: Vec<Vec3> = texels.iter().map(|t| t.position).collect();
    let theta = 60f32.to_radians();
    let light = DirectionalLight {
        direction: Vec3::new(0.0, -theta.cos(), -theta.sin()),
        irradiance_over_pi: Vec3::ONE,
        cone_half_angle: 0.0,
    };
    let input = SdbInput {
        triangles,
        texels,
        width: 32,
        height: 32,
        environment: None,
        lights: vec![light],
        seed: 1,
        want_direct: true,
        ambient: None,
        small_lights: None,
        tables: None,
    };
    let mut engine = SdbEngine::new(ctx, input, params(256, 3)).unwrap();
    let e = run(&mut engine, 8);
    let [even, _] = engine.read_halves().unwrap();
    let direct = even.direct.expect("direct layer with a light");
    // Shadow of the blocker on the floor: x in [-1, -0.2], z shifted by 0.3 * tan 60 toward -z.
    let shift = 0.3 * theta.tan();
    let mut lit = 0;
    let mut shadowed = 0;
    for (k, p) in positions.iter().enumerate() {
        if owner[k] != 0 {
            continue;
        }
        let inside = p.x > -1.0 + 0.1 && p.x < -0.2 - 0.1 && p.z > -0.4 - shift + 0.1 && p.z < 0.4 - shift - 0.1;
        let outside = p.x > -0.2 + 0.1 || p.z > 0.4 - shift + 0.1 || p.z < -0.4 - shift - 0.1;
        if inside {
            assert!(e[k].max_element() < 0.01, "shadowed texel at {p}: {}", e[k]);
            shadowed += 1;
        } else if outside {
            assert!(
                (e[k] - Vec3::splat(0.5)).abs().max_element() < 0.01,
                "lit texel at {p}: {}",
                e[k]
            );
            assert!(
                (direct[k] - Vec3::splat(0.5)).abs().max_element() < 0.01,
                "direct layer at {p}: {}",
                direct[k]
            );
            lit += 1;
        }
    }
    assert!(lit > 50 && shadowed > 20, "lit {lit}, shadowed {shadowed}");
}

#[test]
fn random_and_stratified_directions_agree() {
    let _gpu = common::gpu_serial();
    let Some(ctx) = context() else { return };
    let quad = Quad::new(Vec3::ZERO, Vec3::Y, 0.5, [0.0, 0.0, 1.0, 1.0]);
    let (triangles, texels, _) = build(&[quad], 8, 8);
    let input = SdbInput {
        triangles,
        texels,
        width: 8,
        height: 8,
        environment: Some(Arc::new(|w: Vec3| Vec3::splat(w.y.max(0.0) * 3.0))),
        lights: vec![],
        seed: 11,
        want_direct: false,
        ambient: None,
        small_lights: None,
        tables: None,
    };
    // Sky radiance 3 cos(theta) over the upper hemisphere: E/pi = (1/pi) int 3 cos^2 = 2.
    let p = SdbParams {
        directions: DirectionSequence::Random,
        ..params(64, 1)
    };
    let mut engine = SdbEngine::new(ctx, input, p).unwrap();
    let e = run(&mut engine, 2048);
    // i.i.d. directions: relative standard deviation of 4 * 3 cos^2 max(.,0) estimator
    // over 2048 samples is about 3.5%; all texels see the same directions, so test the
    // mean at 4 sigma.
    let m = mean(&e);
    eprintln!("mean {m}");
    assert!((m - Vec3::splat(2.0)).abs().max_element() < 0.3, "mean {m}");
}

// ---------------------------------------------------------------------------------------
// The foundation's analytic scenes, built in code and imported through the real glTF path
// ---------------------------------------------------------------------------------------

/// Whether the machine has an adapter; prints why a test is skipped otherwise.
fn have_adapter() -> bool {
    context().is_some()
}

#[test]
fn imported_closed_cube_furnace() {
    let _gpu = common::gpu_serial();
    // Six separate square meshes, inward, albedo 0.5, emission 1: E/pi = 2 everywhere.
    // Known bias: the feedback transient (about 2 / n for ramp 1, i.e. 0.2% after 1024
    // directions) and, where welding does not close the box, overdraw 2 (a wall's back
    // face behind the texel): the far wall is missed by all 9 samples with probability
    // 2^-9 = 0.2%. Tolerance: 2% on the mean, 10% per texel (edges and corners, where
    // neighbourhood samples come from the adjacent wall, still see the same radiance).
    if !have_adapter() {
        return;
    }
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::emissive("wall", [0.5; 3], [1.0; 3]));
    for n in [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z] {
        b.square(&format!("face {n}"), -n, 2.0, n, m);
    }
    let (atlas, est) = bake(
        import(&b),
        48,
        Lighting::default(),
        "sdb",
        json!({"map_size": 128}),
        1024,
    );
    assert!(atlas.texels.len() > 1000);
    let mean = est.total.iter().map(|v| lum(*v)).sum::<f64>() / est.total.len() as f64;
    let worst = est.total.iter().map(|v| (lum(*v) - 2.0).abs()).fold(0.0, f64::max);
    eprintln!("imported furnace: mean {mean:.4} (expected 2), worst texel deviation {worst:.4}");
    assert!((mean - 2.0).abs() < 0.04, "mean {mean}");
    assert!(worst < 0.2, "worst texel deviation {worst}");
}

/// Unset, `map_size` is chosen at prepare and reported in the job's parameters: the
/// smallest multiple of 256 (from 512) whose pixel over the triangles' diagonal is at
/// most half the median texel side; a room keeps 512, and a size the job gives is kept.
#[test]
fn the_map_size_is_chosen_from_the_scene_and_its_texels() {
    use lightmapd::engine::atlas::Atlas;
    use lightmapd::engine::technique::{self, BakeInputs};
    let _gpu = common::gpu_serial();
    if !have_adapter() {
        return;
    }
    // Two 1 m squares 12 m apart: a 12 m scene with texels of a few centimetres.
    let far = common::two_squares(12.0);
    let mut room = SceneBuilder::new();
    let m = room.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    room.square("floor", Vec3::ZERO, 1.0, Vec3::Y, m);
    for (name, builder, params, auto) in [
        ("two squares", &far, json!({}), true),
        ("two squares, map_size 256", &far, json!({"map_size": 256}), false),
        ("one square", &room, json!({}), true),
    ] {
        let scene = Arc::new(import(builder));
        let atlas = Arc::new(Atlas::build(&scene, 64, 64).expect("atlas"));
        let request = lightmapd::engine::job::BakeRequest {
            technique: "sdb".into(),
            lighting: upper_sky(1.0),
            ..Default::default()
        };
        let plan = lightmapd::engine::job::plan_for(&scene, &request).expect("plan");
        let inputs = BakeInputs::new(scene.clone(), atlas.clone(), upper_sky(1.0), 1, plan);
        let tech = technique::create("sdb", inputs, &params).expect("sdb prepares");
        let n = tech.params()["map_size"]
            .as_u64()
            .expect("map_size reported as a number") as f32;
        if !auto {
            assert_eq!(n, 256.0, "{name}");
            continue;
        }
        let mut sizes: Vec<f32> = atlas.texels.iter().map(|t| t.size).collect();
        sizes.sort_by(f32::total_cmp);
        let texel = sizes[sizes.len() / 2];
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for p in scene.triangles.iter().flat_map(|t| t.p) {
            lo = lo.min(p);
            hi = hi.max(p);
        }
        let diagonal = (hi - lo).length();
        assert!(
            diagonal / n <= texel / 2.0 * 1.0001,
            "{name}: {n} pixels over {diagonal} m, texel {texel} m"
        );
        if n > 512.0 {
            assert!(
                diagonal / (n - 256.0) > texel / 2.0,
                "{name}: {n} is not the smallest size"
            );
        }
        let want_large = name == "two squares";
        assert_eq!(
            n > 512.0,
            want_large,
            "{name}: {n} pixels over {diagonal} m, texel {texel} m"
        );
    }
}

#[test]
fn imported_plane_under_upper_sky() {
    let _gpu = common::gpu_serial();
    // An upward 10 m square under an upper-hemisphere sky: nothing but the plane itself,
    // so E/pi = L exactly; stratified directions leave well under 1% after 256.
    if !have_adapter() {
        return;
    }
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("ground", Vec3::ZERO, 10.0, Vec3::Y, m);
    let l = 1.7f32;
    let (atlas, est) = bake(import(&b), 32, upper_sky(l), "sdb", json!({"map_size": 128}), 256);
    assert!(atlas.texels.len() > 500);
    for v in &est.total {
        assert!((*v - Vec3::splat(l)).abs().max_element() < 0.01 * l, "{v}");
    }
    // Everything is direct light from the sky.
    let direct = est.direct.as_ref().expect("direct layer");
    for (t, d) in est.total.iter().zip(direct) {
        assert!((*t - *d).abs().max_element() < 1e-4, "total {t} direct {d}");
    }
}

fn corner_form_factor(a: f64, b: f64, c: f64) -> f64 {
    let (x, y) = (a / c, b / c);
    let (sx, sy) = ((1.0 + x * x).sqrt(), (1.0 + y * y).sqrt());
    (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / (2.0 * PI)
}

fn rect_form_factor(px: f64, pz: f64, x0: f64, x1: f64, z0: f64, z1: f64, c: f64) -> f64 {
    let s = |a: f64, b: f64| a.signum() * b.signum() * corner_form_factor(a.abs(), b.abs(), c);
    s(x1 - px, z1 - pz) - s(x0 - px, z1 - pz) - s(x1 - px, z0 - pz) + s(x0 - px, z0 - pz)
}

#[test]
fn imported_parallel_squares_form_factor() {
    let _gpu = common::gpu_serial();
    // A black receiver under a unit emitter one unit up: E/pi = the point-to-rectangle
    // form factor (0.23946 at the centre). Tolerances: see the bias note below for the
    // mean over the receiver, and the noise note for the RMS per texel.
    if !have_adapter() {
        return;
    }
    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.0; 3], [1.0; 3]));
    b.square("receiver", Vec3::ZERO, 1.0, Vec3::Y, black);
    b.square("emitter", Vec3::new(0.0, 1.0, 0.0), 1.0, Vec3::NEG_Y, lamp);
    let scene = import(&b);
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) = bake(scene, 62, Lighting::default(), "sdb", json!({"map_size": 512}), 1024);
    let (mut got, mut want, mut sq, mut count) = (0.0, 0.0, 0.0f64, 0usize);
    for (k, t) in atlas.texels.iter().enumerate() {
        if t.geo_normal.y < 0.99 {
            continue;
        }
        let p = t.position + offset;
        let f = rect_form_factor(p.x as f64, p.z as f64, -0.5, 0.5, -0.5, 0.5, 1.0 - p.y as f64);
        got += lum(est.total[k]);
        want += f;
        sq += ((lum(est.total[k]) - f) / f).powi(2);
        count += 1;
    }
    let rel = got / want - 1.0;
    let rms = (sq / count as f64).sqrt();
    eprintln!(
        "parallel squares: mean relative deviation {rel:+.4}, RMS relative deviation {rms:.4} over {count} texels"
    );
    // Known bias: "nearest wins" dilates every surface by (k - 1)/2 map pixels, since a
    // ray passing just outside the emitter still finds emitter samples in its
    // neighbourhood while one just inside always does. With k = 5 and a 512 map over this
    // scene (projected span at most its 1.73 m diagonal: pixel <= 3.4 mm) the 1 m emitter
    // grows by at most 2 x 6.8 mm per side: +0% to +2.7% in area. Measured +4.0% with a
    // 256 map and +1.1% with k = 3 at 256, as this predicts. Allowed: that range plus
    // 1.5% for the noise of the mean.
    assert!((-0.015..0.042).contains(&rel), "mean relative deviation {rel}");
    // Per texel the estimator is noisy: only about 7% of uniform directions hit the
    // emitter (solid angle about 0.9 sr of 4 pi), so a texel's estimate is a Bernoulli
    // count with relative standard deviation about sqrt(0.93 / 0.07 / n) = 11% at n = 1024
    // for i.i.d. directions; stratification brings it below that but the even/odd
    // halves of one R2 sequence are too correlated to estimate it per texel. So the RMS
    // over texels is tested against 10% (most of the i.i.d. noise bound; stratification
    // measured 2.5% at n = 2048) + 2.7% (dilation).
    assert!(rms < 0.127, "RMS relative deviation {rms}");
    // The emitter faces the black receiver only: zero.
    for (k, t) in atlas.texels.iter().enumerate() {
        if t.geo_normal.y < -0.99 {
            assert!(est.total[k].max_element() < 1e-6, "{}", est.total[k]);
        }
    }
}

#[test]
fn imported_sun_on_a_plane() {
    let _gpu = common::gpu_serial();
    // A sun 60 degrees off vertical on an open plane: E/pi = L Omega cos(60) / pi at every
    // texel (no occluder, no bounce), all of it direct.
    if !have_adapter() {
        return;
    }
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("ground", Vec3::ZERO, 4.0, Vec3::Y, m);
    let theta = 60f32.to_radians();
    let sun = Sun {
        direction: Vec3::new(theta.sin(), -theta.cos(), 0.0),
        angular_diameter: 0.53f32.to_radians(),
        radiance: Vec3::splat(1e4),
    };
    let expected = 1e4 * sun.solid_angle() * theta.cos() / std::f32::consts::PI;
    let lighting = Lighting {
        sky: None,
        sun: Some(sun),
    };
    let (_, est) = bake(import(&b), 16, lighting, "sdb", json!({"map_size": 128}), 16);
    let direct = est.direct.as_ref().expect("direct layer");
    for (t, d) in est.total.iter().zip(direct) {
        // The disc is sampled per direction: cos varies by +-0.23 degrees * tan(60), 0.7%.
        assert!((t.x - expected).abs() < 0.01 * expected, "{t} vs {expected}");
        assert!((t.x - d.x).abs() < 1e-3 * expected);
    }
}

#[test]
fn plan_reports_point_lights_and_the_sh_layer() {
    let _gpu = common::gpu_serial();
    use lightmapd::engine::plan::SceneFeatures;
    let f = SceneFeatures {
        punctual_lights: 3,
        directional_lights: 1,
        emissive_triangles: 0,
        sky: false,
        sun: false,
        glossy_materials: 0,
        textured_materials: 0,
        double_sided_triangles: 0,
        alpha_materials: 0,
        want_direct: false,
        want_validity: false,
        want_sh: true,
    };
    let plan = lightmapd::engine::technique::plan("sdb", &f).unwrap();
    assert!(plan.runs("shadow maps + direct pass"));
    assert!(plan.runs("point and spot lights (GPU rays)"));
    let item = plan
        .passes
        .iter()
        .find(|i| i.name == "point and spot lights (GPU rays)")
        .unwrap();
    assert!(item.why.starts_with("2 point/spot"), "{}", item.why);
    // Asking sdb for the sh layer is reported, not silently dropped.
    assert!(
        plan.left_out
            .iter()
            .any(|i| i.name == "directional (sh) layer" && i.why.starts_with("asked for"))
    );
}

#[test]
fn point_and_spot_lights_with_a_hard_shadow() {
    let _gpu = common::gpu_serial();
    // A black floor (no bounce anywhere) under a point light and a spot, with a black
    // 0.6 m square 0.5 m up casting the point light's shadow. Per texel, in closed form:
    // point: I h / (pi d^3), and no light where the segment to the light crosses the
    // square; spot: I cos / (pi d^2) times glTF's cone falloff (clamp((cos a - cos outer)
    // / (cos inner - cos outer))^2). One shadow ray per texel at its centre, so the answer
    // is exact up to float rounding (tolerance 1e-4 relative) away from the shadow's edge
    // (texels whose segment passes within 2 cm of it are skipped: a texel's centre is not
    // the same point as the texel in the map).
    use lightmapd::engine::scene::build::LightDesc;
    if !have_adapter() {
        return;
    }
    let mut b = SceneBuilder::new();
    let black = b.material(MaterialDesc::diffuse("black", [0.0; 3]));
    b.square("floor", Vec3::ZERO, 4.0, Vec3::Y, black);
    b.square("blocker", Vec3::new(-0.7, 0.5, 0.0), 0.6, Vec3::Y, black);
    let point = Vec3::new(-0.7, 1.0, 0.1);
    b.light(LightDesc::Point {
        position: point,
        color: [1.0, 0.8, 0.6],
        intensity: 5.0,
    });
    let spot = Vec3::new(1.0, 1.5, 0.0);
    let (inner, outer) = (0.3f32, 0.6f32);
    b.light(LightDesc::Spot {
        position: spot,
        direction: Vec3::NEG_Y,
        color: [0.5, 0.5, 1.0],
        intensity: 20.0,
        inner,
        outer,
    });
    let scene = import(&b);
    let offset = scene.origin_offset.as_vec3();
    let (atlas, est) = bake(scene, 64, Lighting::default(), "sdb", json!({"map_size": 64}), 4);
    let (mut checked, mut shadowed) = (0, 0);
    for (k, texel) in atlas.texels.iter().enumerate() {
        // The importer re-centres the scene (`origin_offset`); the closed forms are in
        // the file's frame.
        let p = texel.position + offset;
        if p.y > 0.25 {
            continue; // the blocker's own texels
        }
        // Where the segment to the point light crosses y = 0.5, against the square.
        let q = p + (point - p) * ((0.5 - p.y) / (point.y - p.y));
        let inside = (q.x + 0.7).abs().max(q.z.abs());
        if (inside - 0.3).abs() < 0.02 {
            continue;
        }
        let mut want = Vec3::ZERO;
        if inside > 0.3 {
            let d = point.distance(p);
            want += Vec3::new(1.0, 0.8, 0.6) * (5.0 * (point.y - p.y) / (PI as f32 * d * d * d));
        } else {
            shadowed += 1;
        }
        let to = spot - p;
        let d = to.length();
        let cos_axis = (-to / d).dot(Vec3::NEG_Y);
        let cone = ((cos_axis - outer.cos()) / (inner.cos() - outer.cos())).clamp(0.0, 1.0);
        want += Vec3::new(0.5, 0.5, 1.0) * (20.0 * cone * cone * (to.y / d) / (PI as f32 * d * d));
        let got = est.total[k];
        assert!(
            (got - want).abs().max_element() <= 1e-4 * want.max_element().max(1e-3),
            "texel at {p}: {got} vs {want}"
        );
        let direct = est.direct.as_ref().expect("direct layer")[k];
        assert!(
            (got - direct).abs().max_element() <= 1e-5,
            "all of it is direct: {got} vs {direct}"
        );
        checked += 1;
    }
    assert!(
        checked > 600 && shadowed > 40,
        "{checked} texels checked, {shadowed} in shadow"
    );
}

#[test]
fn cornell_box_against_path() {
    let _gpu = common::gpu_serial();
    // The bundled Cornell box: sdb against a path-traced reference of the same atlas.
    // Relative RMSE (luminance) = sqrt(mean (sdb - path)^2) / sqrt(mean path^2).
    // Budget, justified by the numbers printed: the reference's own noise (its halves'
    // standard error), sdb's noise (its halves), and sdb's bias: the light is a small
    // 0.5 x 0.4 m emitter hit by few directions (variance, not bias), the box is open at
    // the front, so no surface is closed and back faces stay as black blockers: overdraw
    // reaches 4 to 5 along vertical rays, and the layers behind the receiver win the
    // depth lottery and are rejected, so the nearest surface in front is missed with
    // probability about (1 - 1/K)^(k^2): 0.4% at K = 5 with the default k = 5 (but 13%
    // with k = 3, which measured 23% dark here). Contact shadows blur over about 3 map
    // pixels (0.6 cm at 512). Measured per surface (docs/sdb.md): within 5% except the
    // short block's side in its contact shadow (12% dark). Bound: the measured noise
    // floor plus 10% for that bias. The mean over the box is tested within 10%: 5% bias
    // plus its noise, which is large because the light subtends about 0.4% of the sphere
    // from the floor (about 8 of 2048 directions hit it) and all texels share the same
    // directions, so their errors are correlated. With k = 3 the mean is 20-26% dark,
    // which this catches.
    if !have_adapter() {
        return;
    }
    let res = 24;
    let (_, reference) = bake(
        import(&cornell_box()),
        res,
        Lighting::default(),
        "path",
        json!({"samples_per_step": 64}),
        16,
    );
    // 1024 directions in 64 steps of 16 (measured 117 s on lavapipe, 2 cores; 2048 took
    // 234 s and read RMSE 0.075, mean -2.6 %; 1024 read 0.112 and -3.8 %, well inside the
    // bounds, which a 3 x 3 neighbourhood's 20 % darkening still breaks).
    let (_, est) = bake(
        import(&cornell_box()),
        res,
        Lighting::default(),
        "sdb",
        json!({"directions_per_step": 16}),
        64,
    );
    let n = reference.total.len() as f64;
    let ms = |a: &[Vec3], b: &[Vec3]| a.iter().zip(b).map(|(x, y)| (lum(*x) - lum(*y)).powi(2)).sum::<f64>() / n;
    let zeros = vec![Vec3::ZERO; reference.total.len()];
    let norm = ms(&reference.total, &zeros).sqrt();
    let rmse = ms(&est.total, &reference.total).sqrt() / norm;
    let se = |e: &lightmapd::engine::accumulate::Estimate| {
        (e.texel_error
            .as_ref()
            .unwrap()
            .iter()
            .map(|x| (*x as f64).powi(2))
            .sum::<f64>()
            / n)
            .sqrt()
            / norm
    };
    let (se_ref, se_sdb) = (se(&reference), se(&est));
    let noise = (se_ref * se_ref + se_sdb * se_sdb).sqrt();
    let mean_rel =
        est.total.iter().map(|v| lum(*v)).sum::<f64>() / reference.total.iter().map(|v| lum(*v)).sum::<f64>() - 1.0;
    eprintln!(
        "cornell: relative RMSE {rmse:.4}, noise floor {noise:.4} (path {se_ref:.4}, sdb {se_sdb:.4}), mean deviation {mean_rel:+.4}"
    );
    assert!(rmse < 2.0 * noise + 0.10, "relative RMSE {rmse} (noise {noise})");
    assert!(mean_rel.abs() < 0.10, "mean deviation {mean_rel}");
}

#[test]
#[ignore = "diagnostic: per-surface sdb / path ratios on the Cornell box"]
fn cornell_per_surface() {
    let _gpu = common::gpu_serial();
    if !have_adapter() {
        return;
    }
    let res = 24;
    let scene = import(&cornell_box());
    let names: Vec<String> = scene.meshes.iter().map(|m| m.name.clone()).collect();
    let tri_mesh: Vec<u32> = scene.triangles.iter().map(|t| t.mesh).collect();
    let (atlas, reference) = bake(
        import(&cornell_box()),
        res,
        Lighting::default(),
        "path",
        json!({"samples_per_step": 64}),
        8,
    );
    let params: serde_json::Value = std::env::var("SDB_PARAMS")
        .ok()
        .map(|s| serde_json::from_str(&s).unwrap())
        .unwrap_or(json!({}));
    let (_, est) = bake(import(&cornell_box()), res, Lighting::default(), "sdb", params, 1024);
    let mut sums = vec![(0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize); names.len()];
    for (k, t) in atlas.texels.iter().enumerate() {
        let m = tri_mesh[t.triangle as usize] as usize;
        sums[m].0 += lum(est.total[k]);
        sums[m].1 += lum(reference.total[k]);
        sums[m].2 += lum(est.direct.as_ref().unwrap()[k]);
        sums[m].3 += lum(reference.direct.as_ref().unwrap()[k]);
        sums[m].4 += 1;
    }
    for (name, s) in names.iter().zip(&sums) {
        eprintln!(
            "{name:>14}: {:4} texels  total sdb/path {:.3}  direct sdb/path {:.3}  (path total {:.3})",
            s.4,
            s.0 / s.1,
            s.2 / s.3,
            s.1 / s.4 as f64
        );
    }
}

#[test]
fn depth_layers_recover_surfaces_lost_to_overdraw() {
    let _gpu = common::gpu_serial();
    // A receiver under a 1 m emitter (as in the form-factor test), with four double-sided
    // black planes below the receiver: along every vertical map ray there are then 6
    // layers (4 blockers x 1 + the receiver's black back face + the emitter), of which
    // only the emitter is in front of the receiver. The gather finds it with probability
    // 1 - (5/6)^(layers k^2): 81% for one layer of 3 x 3, 99.9% for four. Both estimates
    // are compared with the same bake's no-blocker twin, so dilation and noise cancel.
    let Some(ctx) = context() else { return };
    let run_with = |blockers: bool, layers: u32| {
        let mut quads = vec![Quad::new(Vec3::ZERO, Vec3::Y, 0.5, [0.0, 0.0, 0.5, 0.5])];
        let mut emitter = Quad::new(Vec3::new(0.0, 1.0, 0.0), -Vec3::Y, 0.5, [0.5, 0.0, 1.0, 0.5]);
        emitter.emission = Vec3::ONE;
        emitter.albedo = Vec3::ZERO;
        quads[0].albedo = Vec3::ZERO;
        quads.push(emitter);
        if blockers {
            for i in 0..4 {
                let mut b = Quad::new(
                    Vec3::new(0.0, -0.1 * (i + 1) as f32, 0.0),
                    Vec3::Y,
                    0.6,
                    [0.0, 0.5, 0.01, 0.51],
                );
                b.albedo = Vec3::ZERO;
                b.double_sided = true;
                b.mesh = 2 + i;
                quads.push(b);
            }
        }
        let (triangles, texels, owner) = build(&quads, 32, 32);
        let input = SdbInput {
            triangles,
            texels,
            width: 32,
            height: 32,
            environment: None,
            lights: vec![],
            seed: 9,
            want_direct: false,
            ambient: None,
            small_lights: None,
            tables: None,
        };
        let p = SdbParams {
            depth_layers: layers,
            ..params(128, 3)
        };
        let mut engine = SdbEngine::new(ctx.clone(), input, p).unwrap();
        let e = run(&mut engine, 256);
        let receiver: Vec<Vec3> = e
            .iter()
            .zip(&owner)
            .filter(|(_, o)| **o == 0)
            .map(|(v, _)| *v)
            .collect();
        mean(&receiver).x
    };
    let clear = run_with(false, 1);
    let one = run_with(true, 1) / clear;
    let four = run_with(true, 4) / clear;
    eprintln!("overdraw 6: one layer {one:.3}, four layers {four:.3} of the unobstructed value");
    assert!((0.7..0.92).contains(&one), "one layer: {one}");
    assert!((four - 1.0).abs() < 0.02, "four layers: {four}");
}

#[test]
#[ignore = "measurement for docs/sdb.md: stratified vs random directions at equal steps"]
fn measure_stratified_vs_random() {
    let _gpu = common::gpu_serial();
    // RMS relative error over the receiver of the parallel-squares scene (closed form),
    // for both sequences at equal direction counts, averaged over 4 seeds. Map 256, k = 3.
    let Some(ctx) = context() else { return };
    let emitter_half = 0.5f32;
    println!("| directions | stratified RMS error | random RMS error |");
    println!("| --- | --- | --- |");
    for n in [64u32, 256, 1024, 4096] {
        let mut err = [0.0f64; 2];
        for (s, seq) in [DirectionSequence::Stratified, DirectionSequence::Random]
            .into_iter()
            .enumerate()
        {
            for seed in 0..4u64 {
                let receiver = Quad::new(Vec3::ZERO, Vec3::Y, 0.5, [0.0, 0.0, 0.5, 1.0]);
                let mut emitter = Quad::new(Vec3::new(0.0, 1.0, 0.0), -Vec3::Y, emitter_half, [0.5, 0.0, 1.0, 1.0]);
                emitter.emission = Vec3::ONE;
                emitter.albedo = Vec3::ZERO;
                let mut receiver = receiver;
                receiver.albedo = Vec3::ZERO;
                let (triangles, texels, owner) = build(&[receiver, emitter], 32, 16);
                let positions: Vec<Vec3> = texels.iter().map(|t| t.position).collect();
                let input = SdbInput {
                    triangles,
                    texels,
                    width: 32,
                    height: 16,
                    environment: None,
                    lights: vec![],
                    seed,
                    want_direct: false,
                    ambient: None,
                    small_lights: None,
                    tables: None,
                };
                let p = SdbParams {
                    directions: seq,
                    ..params(256, 3)
                };
                let mut engine = SdbEngine::new(ctx.clone(), input, p).unwrap();
                for _ in 0..n {
                    engine.step().unwrap();
                }
                let [a, b] = engine.read_halves().unwrap();
                let (mut sq, mut count) = (0.0, 0);
                for (k, p) in positions.iter().enumerate() {
                    if owner[k] != 0 {
                        continue;
                    }
                    let f = rect_form_factor(p.x as f64, p.z as f64, -0.5, 0.5, -0.5, 0.5, 1.0 - p.y as f64);
                    let v = ((a.total[k] + b.total[k]) * 0.5).x as f64;
                    sq += ((v - f) / f).powi(2);
                    count += 1;
                }
                err[s] += (sq / count as f64).sqrt() / 4.0;
            }
        }
        println!("| {n} | {:.4} | {:.4} |", err[0], err[1]);
    }
}

/// A step of `sdb` in a bake with a time limit or a watcher (issue 19 point 10) runs its
/// directions in slices of whole directions and then its small lights' pass in slices of
/// texels: sliced steps equal whole ones bit for bit, and a step stopped between two
/// slices adds nothing and leaves its directions and random stream as they were, so the
/// bake goes on as if it had not been started. Two cases: the Cornell box with a point
/// light, the ambient-mode correction's antipodal pairs and several directions a step
/// (the stop comes between two directions); and one direction a step (`leaky` mode, no
/// pairs), where the directions finish and the stop comes in the small lights' pass, so
/// the directions' halves are put back.
#[test]
fn sliced_steps_equal_whole_ones_and_an_abandoned_step_adds_nothing() {
    use lightmapd::engine::atlas::Atlas;
    use lightmapd::engine::scene::build::LightDesc;
    use lightmapd::engine::technique::{self, BakeInputs, Technique};
    if !have_adapter() {
        return;
    }
    let _gpu = common::gpu_serial();
    let mut b = cornell_box();
    b.light(LightDesc::Point {
        position: Vec3::new(0.1, 0.3, 0.2),
        color: [1.0, 0.8, 0.6],
        intensity: 2.0,
    });
    // A 2 cm lamp on the back wall: a small emitter, sampled anew every step (point
    // lights alone are computed once a half).
    let lamp = b.material(MaterialDesc::emissive("lamp", [0.5; 3], [400.0; 3]));
    b.square("lamp", Vec3::new(0.0, 1.0, -0.99), 0.02, Vec3::Z, lamp);
    let scene = Arc::new(import(&b));
    let atlas = Arc::new(Atlas::build(&scene, 144, 144).unwrap());
    assert!(atlas.texels.len() > 8192, "{} texels", atlas.texels.len());
    for params in [
        json!({"map_size": 128, "directions_per_step": 4}),
        json!({"map_size": 128, "directions_per_step": 1, "mode": "leaky"}),
    ] {
        let make = || -> Box<dyn Technique> {
            let request = lightmapd::engine::job::BakeRequest {
                technique: "sdb".into(),
                ..Default::default()
            };
            let plan = lightmapd::engine::job::plan_for(&scene, &request).unwrap();
            let inputs = BakeInputs::new(scene.clone(), atlas.clone(), Lighting::default(), 7, plan);
            technique::create("sdb", inputs, &params).unwrap()
        };
        common::assert_sliced_steps_match_whole(&make);
        // Half resolve and directions, half small lights: a stop just past half lands in the
        // small lights after the directions finished.
        common::assert_stopped_step_adds_nothing(&make, 501);
    }
}
