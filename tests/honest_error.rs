//! The error a bake reports covers its bias (issue 21 point 2): for every biased
//! technique, on two scenes with closed forms at every texel, the reported relative error
//! at the end of a short bake (measured at control texels against `path`,
//! `engine::control`) lies within a factor 2 of the true one, computed here from the
//! closed form. On lavapipe, 4-second bakes (the docs' table uses 20 s).
//!
//! Scenes: the closed box of albedo 0.9 (answer 1 everywhere: stiff, where the biased
//! techniques lose or gain light) and the parallel plates (the receiver reads the form
//! factor, every other texel 0).

mod common;

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use common::have_adapter;
use glam::Vec3;
use lightmapd::bench::{self, BenchConfig};
use lightmapd::engine::accumulate::LUMINANCE;
use lightmapd::engine::bake::StopCriteria;
use lightmapd::engine::job::{self, BakeRequest};
use lightmapd::engine::post::denoised::Denoiser;
use lightmapd::engine::scene::import_slice;
use lightmapd::engine::scene::library::benchmark_scenes;
use lightmapd::engine::technique::TABLE;

/// The answer a bake is measured against: the closed form at every texel, or a cached
/// long `path` bake (`lightmapd::bench::reference`) with its own relative error.
enum Answer {
    Closed,
    Path { budget: f64 },
}

/// The bench's `path` reference of `scene` baked for `budget` seconds, cached under the
/// test target's temporary directory.
fn path_reference(
    scene: &lightmapd::engine::scene::library::LibraryScene,
    prepared: &bench::PreparedScene,
    budget: f64,
) -> bench::Reference {
    let cfg = BenchConfig {
        scenes: Vec::new(),
        techniques: Vec::new(),
        budget: Duration::ZERO,
        steps: None,
        reference_budget: Duration::from_secs_f64(budget),
        out_dir: PathBuf::new(),
        cache_dir: PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("honest-error-references"),
        probes: false,
    };
    bench::reference(scene, prepared, &cfg).expect("the path reference")
}

/// (reported, true) relative error of a bake of `technique` on the library scene `name`
/// at `resolution`, stopped by `stop`. Against a `path` reference, the reference's own
/// noise is taken out of the measured error (independent errors add in squares).
fn measure(
    technique: &str,
    name: &str,
    resolution: u32,
    stop: StopCriteria,
    params: serde_json::Value,
    answer: Answer,
    denoise: Denoiser,
) -> (f32, f64, Unresolved) {
    let s = benchmark_scenes()
        .into_iter()
        .find(|s| s.name == name)
        .expect("library scene");
    let scene = Arc::new(import_slice(&(s.glb)(), None).expect("imports").0);
    let offset = scene.origin_offset;
    let request = BakeRequest {
        technique: technique.into(),
        resolution,
        lighting: s.lighting,
        stop,
        params,
        denoise,
        seed: 7,
        ..Default::default()
    };
    let r = job::bake_unobserved(scene, &request).expect("the bake");
    let l = |v: Vec3| v.dot(LUMINANCE) as f64;
    let truth = match answer {
        Answer::Closed => {
            let analytic = s.analytic.expect("a closed form");
            let (mut err2, mut ref2) = (0.0f64, 0.0f64);
            // Where the closed form is defined (sphere-over-plane: on the plane only).
            for (k, t) in r.atlas.texels.iter().enumerate() {
                let Some(want) = analytic(t.position.as_dvec3() + offset, t.geo_normal) else {
                    continue;
                };
                err2 += (l(r.estimate.total[k]) - l(want)).powi(2);
                ref2 += l(want).powi(2);
            }
            (err2 / ref2).sqrt()
        }
        Answer::Path { budget } => {
            assert_eq!(
                s.resolution, resolution,
                "the cached reference is at the scene's own resolution"
            );
            let prepared = bench::prepare(&s).expect("prepares");
            let reference = path_reference(&s, &prepared, budget);
            // The bench's atlas is the unvalidated one (texels inside geometry kept); the
            // bake's lost those. The same pixel is the same texel.
            let by_pixel: std::collections::HashMap<u32, (Vec3, Option<Vec3>)> = prepared
                .atlas
                .texels
                .iter()
                .zip(&reference.values)
                .map(|(t, v)| (t.pixel, (t.position, *v)))
                .collect();
            let values: Vec<Option<Vec3>> = r
                .atlas
                .texels
                .iter()
                .map(|t| {
                    let (at, v) = by_pixel
                        .get(&t.pixel)
                        .expect("every baked texel is in the reference's atlas");
                    assert_eq!(*at, t.position, "the same texel at pixel {}", t.pixel);
                    *v
                })
                .collect();
            let measured = bench::true_error(&r.estimate.total, &values);
            eprintln!(
                "{name}: reference {} with relative error {:.4}; measured {measured:.4}",
                reference.kind, reference.error
            );
            (measured * measured - reference.error * reference.error)
                .max(0.0)
                .sqrt()
        }
    };
    let e = r.estimate.error;
    let reported = e.relative.expect("an error estimate");
    eprintln!(
        "{technique} on {name}: reported {reported:.4} (noise {:?}, bias {:?}, 90 % interval {:?}, {:?} control texels), true {truth:.4}, ratio {:.2}, {} steps",
        e.noise,
        e.bias,
        e.interval,
        e.control_texels,
        reported as f64 / truth,
        r.estimate.steps
    );
    // A biased technique's figure is measured at control texels; path's is its noise.
    let unbiased = TABLE.iter().any(|t| t.id == technique && t.unbiased);
    assert_eq!(e.control_texels.is_some(), !unbiased, "{technique}: control texels");
    if !unbiased {
        assert!(e.noise.is_some() && e.bias.is_some() && e.interval.is_some());
    }
    (reported, truth, Unresolved::of(&e, truth))
}

/// Whether a biased technique's bake ended below its control's resolution: the control's
/// 90 % interval starts at the noise floor (the control told no bias from zero: its mean
/// minus 1.645 standard errors is under the calibrated noise), and the true error lies
/// inside that interval. There the reported figure is the noise floor and the ratio to a
/// true error the control cannot see says nothing; what the job states, the interval,
/// holds. (The closed box of albedo 0.9 with sdb at 400 steps, true 0.19 %, read 0.24 %
/// on 2026-12-04 and 0.03 % with an interval of [0.03 %, 0.23 %] on 2026-12-05, after
/// `path`'s sampler, which the control runs, changed: a true error at the edge of what
/// 256 control texels resolve lands on either side of it.)
#[derive(Debug, Clone, Copy)]
struct Unresolved(bool);

impl Unresolved {
    fn of(e: &lightmapd::engine::accumulate::ErrorSummary, truth: f64) -> Unresolved {
        let (Some([lo, hi]), Some(noise)) = (e.interval, e.noise) else {
            return Unresolved(false);
        };
        let at_floor = lo as f64 <= noise as f64 * (1.0 + 1e-6);
        Unresolved(at_floor && truth <= hi as f64)
    }
}

fn params_for(technique: &str) -> serde_json::Value {
    match technique {
        "obscurance" => serde_json::json!({"map_size": 256}),
        // A quarter of the default map's raster (lavapipe's cost per direction): the
        // claim is that the reported error covers the true one whatever the settings.
        "sdb" => serde_json::json!({"map_size": 256}),
        "sdf" => serde_json::json!({"resolution": 48}),
        _ => serde_json::json!({}),
    }
}

/// Steps of a few seconds each on lavapipe (fixed steps, so the test is deterministic
/// up to the control's time-sliced sample count).
fn steps_for(technique: &str) -> u64 {
    match technique {
        "sdf" => 3000,
        "hemicube" => 150,
        _ => 400,
    }
}

/// Bakes every biased technique on the two closed-form scenes at each of `steps(id)`
/// with `denoise`, and lists the bakes whose reported error is not within a factor 2 of
/// the true one (unless the truth is below the control's resolution and inside the
/// stated interval, [`Unresolved`]); `what` names the figure in the messages.
fn factor_two_failures(what: &str, denoise: Denoiser, steps: impl Fn(&str) -> Vec<u64>) -> Vec<String> {
    let mut failures = Vec::new();
    for e in TABLE.iter().filter(|e| !e.unbiased) {
        for n in steps(e.id) {
            for (scene, resolution) in [("closed-box-0.9", 24), ("parallel-plates", 32)] {
                let stop = StopCriteria {
                    steps: Some(n),
                    seconds: None,
                    target_error: None,
                };
                let (reported, truth, unresolved) =
                    measure(e.id, scene, resolution, stop, params_for(e.id), Answer::Closed, denoise);
                let ratio = reported as f64 / truth;
                if unresolved.0 {
                    eprintln!(
                        "{} on {scene}, {n} steps, {what}: true {truth:.4} below the control's resolution, inside its 90 % interval",
                        e.id
                    );
                } else if !(0.5..=2.0).contains(&ratio) {
                    failures.push(format!(
                        "{} on {scene}, {n} steps, {what}: reported {reported:.4}, true {truth:.4}, ratio {ratio:.2} outside [0.5, 2]",
                        e.id
                    ));
                }
            }
        }
    }
    failures
}

#[test]
fn reported_error_is_within_a_factor_two_of_the_true_error() {
    if !have_adapter() {
        return;
    }
    let failures = factor_two_failures("raw", Denoiser::None, |id| vec![steps_for(id)]);
    assert!(failures.is_empty(), "reported / true error:\n{}", failures.join("\n"));
}

/// The same for what is delivered: a biased technique's denoised lightmap is measured at
/// its control texels (`ControlValues::assess_delivered`), so its reported error is within a
/// factor 2 of its true one too: on the two closed forms early in a bake, where the
/// filters move the most (4 steps; `sdf`, whose steps are cheap, 50), and at the end of
/// the bake above; and for `obscurance` on the Cornell box at 4 steps as `lightmapd
/// bench` bakes it (its seed, its atlas, a 10-s `path` reference), where the filters
/// change the map's bias most. There the figure this replaced, the raw map's measured
/// bias in quadrature with the filters' noise bound, stated 0.36 of the truth
/// (2026-12-06). On the closed forms the two figures agree within the control's
/// resolution. (At 16 `sdb` steps on the 0.9 box the true error, 0.1-1.3 % over seeds,
/// sits at the control's resolution, and whether it fell inside the stated 90 % interval
/// depended on the control's time-sliced samples: not a case this test can hold either
/// figure to.)
#[test]
fn delivered_error_is_within_a_factor_two_of_the_true_error() {
    if !have_adapter() {
        return;
    }
    let early = |id: &str| if id == "sdf" { 50 } else { 4 };
    let mut failures = factor_two_failures("delivered", Denoiser::Auto, |id| vec![early(id), steps_for(id)]);
    let cornell = benchmark_scenes()
        .into_iter()
        .find(|s| s.name == "cornell-box")
        .expect("library scene");
    let prepared = bench::prepare(&cornell).expect("prepares");
    let reference = path_reference(&cornell, &prepared, 10.0);
    let samples = bench::measure(
        &cornell,
        &prepared,
        &reference,
        "obscurance",
        Duration::from_secs(300),
        Some(4),
    )
    .expect("the bench's bake");
    let at4 = samples.iter().find(|s| s.steps == 4).expect("a snapshot at 4 steps");
    // Less the reference's own error, in quadrature, as above.
    let truth = (at4.denoised_error.powi(2) - reference.error.powi(2)).max(0.0).sqrt();
    let reported = at4.denoised_estimate.expect("a delivered estimate") as f64;
    let ratio = reported / truth;
    eprintln!(
        "obscurance on the Cornell box, 4 steps, bench: delivered reported {reported:.4}, true {truth:.4}, ratio {ratio:.2}"
    );
    if !(0.5..=2.0).contains(&ratio) {
        failures.push(format!(
            "obscurance on the Cornell box, 4 steps, delivered: reported {reported:.4}, true {truth:.4}, ratio {ratio:.2} outside [0.5, 2]"
        ));
    }
    assert!(
        failures.is_empty(),
        "delivered reported / true error:\n{}",
        failures.join("\n")
    );
}

/// The table of docs/accuracy.md: 20-second bakes of every technique on every
/// benchmark scene, against the closed form where the scene has one and a cached
/// `path` reference (env `HONEST_REFERENCE_SECONDS`, default 600 s on the CPU) where it
/// has not. Env `HONEST_SCENES` / `HONEST_TECHNIQUES` (comma-separated) narrow it.
/// Slow (about 20 minutes, plus the references once): run with `--ignored`.
#[test]
#[ignore]
fn table_of_reported_and_true_error_after_20_seconds() {
    if !have_adapter() {
        return;
    }
    let pick = |var: &str, name: &str| std::env::var(var).map_or(true, |v| v.split(',').any(|x| x == name));
    let budget = std::env::var("HONEST_REFERENCE_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(600.0);
    let mut rows = vec![
        "| technique | scene | reported | true | reported / true |".to_string(),
        "| --- | --- | --- | --- | --- |".to_string(),
    ];
    // Every technique: the biased ones report noise and bias (the control texels), the
    // unbiased `path` its halves' noise, which is its whole error.
    for e in TABLE.iter().filter(|e| pick("HONEST_TECHNIQUES", e.id)) {
        for s in benchmark_scenes().into_iter().filter(|s| pick("HONEST_SCENES", s.name)) {
            let stop = StopCriteria {
                steps: None,
                seconds: Some(20.0),
                target_error: None,
            };
            let answer = if s.analytic.is_some() {
                Answer::Closed
            } else {
                Answer::Path { budget }
            };
            let (reported, truth, _) = measure(
                e.id,
                s.name,
                s.resolution,
                stop,
                params_for(e.id),
                answer,
                Denoiser::None,
            );
            rows.push(format!(
                "| {} | {} | {:.2} % | {:.2} % | {:.2} |",
                e.id,
                s.name,
                100.0 * reported,
                100.0 * truth,
                reported as f64 / truth
            ));
            println!("{}", rows.last().expect("a row"));
        }
    }
    println!("{}", rows.join("\n"));
}
