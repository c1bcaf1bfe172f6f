//! Shared helpers for the engine's integration tests: build a scene in code, import it
//! through the real glTF path, bake it, and compare against analytic answers with
//! tolerances that follow from the sample count.
#![allow(dead_code)]

use std::sync::Arc;

use glam::Vec3;
use lightmapd::engine::accumulate::{Estimate, LUMINANCE};
use lightmapd::engine::atlas::{Atlas, Texel};
use lightmapd::engine::scene::build::SceneBuilder;
use lightmapd::engine::scene::{Lighting, Scene, import_slice};
use lightmapd::engine::technique::{self, BakeInputs};

/// Two 1 m grey squares facing up, `apart` metres apart along x: a scene many texels
/// wide, whose scene-wide maps the techniques size from it (`gpu::view::auto_map_size`).
pub fn two_squares(apart: f32) -> SceneBuilder {
    use lightmapd::engine::scene::build::MaterialDesc;
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("near", Vec3::ZERO, 1.0, Vec3::Y, m);
    b.square("far", Vec3::new(apart, 0.0, 0.0), 1.0, Vec3::Y, m);
    b
}

pub fn import(builder: &SceneBuilder) -> Scene {
    import_slice(&builder.to_glb(), None).expect("test scene imports").0
}

/// Bakes `steps` steps of `technique` and returns the atlas and the estimate.
pub fn bake(
    scene: Scene,
    resolution: u32,
    lighting: Lighting,
    technique: &str,
    params: serde_json::Value,
    steps: u64,
) -> (Arc<Atlas>, Estimate) {
    try_bake(scene, resolution, lighting, technique, params, steps).expect("the bake")
}

/// [`bake`], returning the engine's error instead of panicking on it.
pub fn try_bake(
    scene: Scene,
    resolution: u32,
    lighting: Lighting,
    technique: &str,
    params: serde_json::Value,
    steps: u64,
) -> Result<(Arc<Atlas>, Estimate), lightmapd::engine::technique::EngineError> {
    try_bake_seeded(scene, resolution, lighting, technique, params, steps, 1)
}

/// [`try_bake`] with the bake's random seed.
pub fn try_bake_seeded(
    scene: Scene,
    resolution: u32,
    lighting: Lighting,
    technique: &str,
    params: serde_json::Value,
    steps: u64,
    seed: u64,
) -> Result<(Arc<Atlas>, Estimate), lightmapd::engine::technique::EngineError> {
    let scene = Arc::new(scene);
    let atlas = Arc::new(Atlas::build(&scene, resolution, resolution).expect("atlas"));
    let request = lightmapd::engine::job::BakeRequest {
        technique: technique.into(),
        lighting,
        // The direct layer, and the directional moments from a technique that keeps them
        // (asking one that does not is refused before baking).
        outputs: [
            lightmapd::engine::output::OutputLayer::Direct,
            lightmapd::engine::output::OutputLayer::Sh,
        ]
        .into_iter()
        .filter(|l| technique::entry(technique).unwrap().layers.contains(l))
        .collect(),
        ..Default::default()
    };
    let plan = lightmapd::engine::job::plan_for(&scene, &request)?;
    let inputs = BakeInputs {
        want_direct: true,
        ..BakeInputs::new(scene, atlas.clone(), lighting, seed, plan)
    };
    let mut tech = technique::create(technique, inputs, &params)?;
    for _ in 0..steps {
        tech.step()?;
    }
    Ok((atlas, tech.snapshot()?.estimate()))
}

/// Runs the GPU-heavy tests of one test binary one at a time: lavapipe already spreads
/// each dispatch over every core, and two bakes at once on CI's two cores took longer
/// together than one after the other (`tests/sdb.rs`: 256 s with two test threads,
/// 157 s with one). Hold the guard for the whole test.
pub fn gpu_serial() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// True when a GPU adapter (lavapipe counts) is there; without one the calling test
/// skips with a message, or fails under `LIGHTMAPD_REQUIRE_GPU=1` (set in `.ci/run`).
pub fn have_adapter() -> bool {
    use lightmapd::engine::gpu::{self, GpuError, Requirements};
    match gpu::shared(&Requirements::default()) {
        Ok(_) => true,
        Err(GpuError::NoAdapter) if std::env::var("LIGHTMAPD_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("SKIPPED: no GPU adapter on this machine (install mesa-vulkan-drivers for lavapipe)");
            false
        }
        Err(e) => panic!("GPU context (LIGHTMAPD_REQUIRE_GPU=1 makes a missing adapter fatal): {e}"),
    }
}

pub fn lum(v: Vec3) -> f64 {
    v.dot(LUMINANCE) as f64
}

/// Compares an unbiased estimate with `expected` over the texels `select` keeps.
///
/// The texels are independent (separate random streams), so the mean deviation over n
/// texels has standard error sqrt(Σ se_t²) / n, with se_t each texel's standard error
/// from the two half-accumulators. A mean deviation beyond 5 of those (probability
/// below 1e-6 for an unbiased estimator) or beyond the stated `model_bias` is a failure.
/// Returns (mean relative deviation, its standard error, texel count).
pub fn assert_unbiased(
    atlas: &Atlas,
    est: &Estimate,
    select: impl Fn(&Texel) -> bool,
    expected: impl Fn(&Texel) -> Vec3,
    model_bias: f64,
    what: &str,
) -> (f64, f64, usize) {
    let n = atlas.texels.iter().filter(|t| select(t)).count();
    assert!(n > 0, "{what}: no texel selected");
    let (mean_dev, mean_se) = mean_deviation(atlas, est, select, expected);
    eprintln!(
        "{what}: {n} texels, mean relative deviation {mean_dev:+.5} (standard error {mean_se:.5}, model bias allowance {model_bias})"
    );
    assert!(
        mean_dev.abs() <= 5.0 * mean_se + model_bias,
        "{what}: mean relative deviation {mean_dev:+.5} exceeds 5 standard errors ({mean_se:.5}) + {model_bias}"
    );
    (mean_dev, mean_se, n)
}

/// Mean relative luminance deviation from `expected` over the selected texels, and its
/// standard error (see [`assert_unbiased`]).
pub fn mean_deviation(
    atlas: &Atlas,
    est: &Estimate,
    select: impl Fn(&Texel) -> bool,
    expected: impl Fn(&Texel) -> Vec3,
) -> (f64, f64) {
    let se = est.texel_error.as_ref().expect("both halves have steps");
    let (mut dev, mut var, mut norm) = (0.0f64, 0.0f64, 0.0f64);
    for (k, t) in atlas.texels.iter().enumerate() {
        if !select(t) {
            continue;
        }
        let e = lum(expected(t));
        dev += lum(est.total[k]) - e;
        var += (se[k] as f64).powi(2);
        norm += e;
    }
    (dev / norm, var.sqrt() / norm)
}

/// Runs scripts/validate-gltf.sh (the Khronos validator) on a written file; returns its
/// JSON line (`errors`, `warnings`, `infos`, `codes`, `unused`).
pub fn validate_gltf(path: &std::path::Path) -> serde_json::Value {
    let out = std::process::Command::new("bash")
        .arg(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/validate-gltf.sh"))
        .arg(path)
        .output()
        .expect("bash runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout
        .lines()
        .last()
        .unwrap_or_else(|| panic!("validator printed nothing: {}", String::from_utf8_lossy(&out.stderr)));
    serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}"))
}

/// A technique's halves as a snapshot reads them: steps and totals, compared bit for bit.
type Halves = (u64, u64, Vec<glam::Vec3>, Vec<glam::Vec3>);

fn halves_of(t: &mut Box<dyn lightmapd::engine::technique::Technique>) -> Halves {
    let s = t.snapshot().unwrap();
    (s.even.steps, s.odd.steps, s.even.total, s.odd.total)
}

/// A technique's GPU steps in slices (issue 19 point 10) against whole ones: with a far
/// deadline and a watcher, three steps (the first sliced) equal three whole ones bit for
/// bit and the watcher hears the last slice; two whole steps, then a third stopped after
/// its first slice by a deadline already past (it does not count), then the third again
/// whole, equal the three whole ones too: a stopped step leaves every half as it was.
/// `make` builds a fresh technique over a grid of more texels than the first slices.
pub fn assert_sliced_steps_match_whole(make: &dyn Fn() -> Box<dyn lightmapd::engine::technique::Technique>) {
    use lightmapd::engine::technique::api::StepProgress;
    use std::time::{Duration, Instant};
    let mut whole = make();
    for _ in 0..3 {
        whole.step().unwrap();
    }
    let mut sliced = make();
    let progress = StepProgress::new();
    sliced.set_step_progress(progress.clone());
    sliced.set_deadline(Some(Instant::now() + Duration::from_secs(3600)));
    sliced.step().unwrap();
    assert_eq!(progress.permille(), 1000, "the watcher heard the last slice");
    for _ in 0..2 {
        sliced.step().unwrap();
    }
    assert_eq!(sliced.steps_done(), 3);
    assert!(
        halves_of(&mut whole) == halves_of(&mut sliced),
        "a sliced step differs from a whole one"
    );

    let mut cut = make();
    for _ in 0..2 {
        cut.step().unwrap();
    }
    cut.set_deadline(Some(Instant::now()));
    cut.step().unwrap();
    assert_eq!(cut.steps_done(), 2, "a step stopped between slices does not count");
    cut.set_deadline(None);
    cut.step().unwrap();
    assert!(
        halves_of(&mut cut) == halves_of(&mut whole),
        "after an abandoned step a half is not as it was"
    );
}

/// As [`assert_sliced_steps_match_whole`]'s second half, with the stop put at a chosen
/// point of the step instead of its first check: two whole steps, then a third watched
/// and asked to stop once `permille` thousandths of it are done
/// (`StepProgress::stop_at_permille`), which must not count, then the third again
/// (watched, no stop point) equal three whole steps bit for bit. For a technique whose
/// step has several sliced parts, a point in a later part checks that part's put-back.
pub fn assert_stopped_step_adds_nothing(
    make: &dyn Fn() -> Box<dyn lightmapd::engine::technique::Technique>,
    permille: u32,
) {
    use lightmapd::engine::technique::api::StepProgress;
    let mut whole = make();
    for _ in 0..3 {
        whole.step().unwrap();
    }
    let mut cut = make();
    for _ in 0..2 {
        cut.step().unwrap();
    }
    let progress = StepProgress::new();
    progress.stop_at_permille(permille);
    cut.set_step_progress(progress.clone());
    cut.step().unwrap();
    assert_eq!(
        cut.steps_done(),
        2,
        "a step stopped at {permille} permille does not count"
    );
    assert!(
        progress.permille() >= permille && progress.permille() < 1000,
        "the step stopped at {} permille, not in the part asked for ({permille})",
        progress.permille()
    );
    progress.stop_at_permille(0);
    cut.step().unwrap();
    assert!(
        halves_of(&mut cut) == halves_of(&mut whole),
        "after a step stopped at {permille} permille a half is not as it was"
    );
}

/// Every channel of an EXR's first layer, by name, as f32.
pub fn exr_channels(path: &std::path::Path) -> Vec<(String, Vec<f32>)> {
    use exr::prelude::{ReadChannels, ReadLayers};
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_file(path)
        .unwrap_or_else(|e| panic!("{}: not a readable EXR: {e}", path.display()));
    image.layer_data[0]
        .channel_data
        .list
        .iter()
        .map(|c| (c.name.to_string(), c.sample_data.values_as_f32().collect()))
        .collect()
}
