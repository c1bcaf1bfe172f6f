//! `lightmapd bench`: true error against run time for every technique on the benchmark
//! scenes (DESIGN §4, issue 5).
//!
//! How: for each scene of `engine::scene::library` and each technique, bake with a
//! snapshot at geometric time points (budget/128, budget/64, …, budget), or with
//! `--steps N` at 4, 16, 64, … N steps (issue 22's sweep of the denoiser by step count,
//! the budget then a cap), and measure the true error of each snapshot against the
//! reference: the closed-form answer where the scene has one, else a long `path` bake
//! cached on disk, keyed by a hash of the scene file, resolution, lighting and reference
//! budget (so a changed scene is never compared with a stale reference). The error metric is the one of `docs/accuracy.md`:
//! RMS over reference texels of the luminance difference, over the RMS reference
//! luminance. The estimated error is the one a job reports: for a biased technique its
//! noise and its bias measured at control texels (`engine::control`), whose `path` steps
//! run inside the clock as in a bake. Outputs: `results.csv`, one log-log SVG plot per scene (written by hand:
//! a few polylines need no plotting crate), and `summary.md` with the time each
//! technique needs to reach 10 %, 5 %, 2 % and 1 %. Light probes ([`probes`]): three
//! closed-form scenes, the same time points, `probes.csv` and a table in `summary.md`.
//!
//! Scenes: the seven small ones of `library::benchmark_scenes` by default (five with a
//! closed form); the real-size ones of `library::real_size_scenes` (three bundled
//! third-party levels at their default density, a 256k-triangle generated level on a 1024²
//! page) when asked for, since their `path` references take minutes on a CPU (seconds on
//! a GPU). `lightmapd bench --quick` is the CI-sized run: 1 s a bake, 10-s references.
//!
//! Limits: times are wall-clock on whatever machine runs it; a reference bake's own
//! noise (reported in `summary.md`) is a floor under every measured error.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::Vec3;
use serde_json::json;

use crate::engine::accumulate::Estimate;
use crate::engine::atlas::{Atlas, unwrap};
use crate::engine::control::ControlTexels;
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::job::BakeRequest;
use crate::engine::scene::library::{LibraryScene, benchmark_scenes, real_size_scenes};
use crate::engine::scene::{Scene, import_slice};

use crate::engine::technique::{self, BakeInputs, EngineError};

pub mod probes;

#[derive(Clone, Debug)]
pub struct BenchConfig {
    /// Scene names to run ([`select_scenes`]: the small scenes when empty, `real` for every
    /// real-size one).
    pub scenes: Vec<String>,
    pub techniques: Vec<String>,
    /// Bake time per scene and technique (with `steps`, the most it may take).
    pub budget: Duration,
    /// A sweep by steps: snapshots at 4, 16, 64, … up to this many steps (each scene and
    /// technique stops there or at `budget`), instead of at geometric time points.
    pub steps: Option<u64>,
    /// Bake time of a `path` reference where a scene has no closed form.
    pub reference_budget: Duration,
    pub out_dir: PathBuf,
    pub cache_dir: PathBuf,
    /// Also measure light probes (`probes`): three closed-form scenes, each with both
    /// samplings, `budget` each.
    pub probes: bool,
}

#[derive(Clone, Debug)]
pub struct Sample {
    pub scene: String,
    pub technique: String,
    pub seconds: f64,
    pub steps: u64,
    pub true_error: f64,
    pub estimated_error: Option<f32>,
    /// True error of the same snapshot as delivered: after the default denoiser
    /// (OIDN when installed, else the own filter), blended by the error estimate.
    pub denoised_error: f64,
    /// The delivered lightmap's own error estimate (what the header reports).
    pub denoised_estimate: Option<f32>,
    /// True error after the own filter (blended), and after OIDN (blended) where
    /// installed.
    pub own_error: f64,
    pub oidn_error: Option<f64>,
}

/// Per valid texel, the reference value (None where it has none), and how it was made.
pub struct Reference {
    pub values: Vec<Option<Vec3>>,
    pub kind: String,
    /// The reference's own estimated relative error (0 for a closed form).
    pub error: f64,
}

/// True relative error of `estimate` against `reference` (`docs/accuracy.md`): the
/// engine's metric, which a job with a reference reports too.
pub use crate::engine::reference::relative_error as true_error;

fn fnv1a(bytes: &[u8], mut h: u64) -> u64 {
    for b in bytes {
        h ^= *b as u64;
        h = h.wrapping_mul(0x100_0000_01b3);
    }
    h
}

pub struct PreparedScene {
    pub scene: Arc<Scene>,
    /// The scene's rays, shared by every bake of the scene in the benchmark.
    pub rays: Arc<SceneRays>,
    pub atlas: Arc<Atlas>,
    pub glb: Vec<u8>,
}

/// Imports `lib`, generates lightmap UVs for meshes without (at its density, on pages of
/// its resolution) and builds the texel set (not validated: texels inside geometry stay,
/// in the reference and in every bake alike).
pub fn prepare(lib: &LibraryScene) -> Result<PreparedScene, EngineError> {
    let glb = (lib.glb)();
    let internal = |e: String| EngineError::Internal(format!("bench scene {}: {e}", lib.name));
    let mut scene = import_slice(&glb, None).map_err(|e| internal(e.to_string()))?.0;
    if scene.needs_lightmap_uvs {
        unwrap::generate_lightmap_uvs_with(
            &mut scene,
            lib.resolution,
            unwrap::LightmapUvs::GenerateMissing,
            lib.texels_per_metre,
            &unwrap::UvUnwrap,
        )
        .map_err(internal)?;
    }
    let (w, h) = scene
        .layout
        .as_ref()
        .map_or((lib.resolution, lib.resolution), |l| (l.width, l.height));
    let scene = Arc::new(scene);
    let atlas = Arc::new(Atlas::build(&scene, w, h).map_err(|e| internal(e.to_string()))?);
    Ok(PreparedScene {
        rays: SceneRays::new(scene.clone()),
        scene,
        atlas,
        glb,
    })
}

fn inputs(p: &PreparedScene, lib: &LibraryScene, technique: &str, seed: u64) -> Result<BakeInputs, EngineError> {
    let request = BakeRequest {
        technique: technique.into(),
        lighting: lib.lighting,
        seed,
        ..Default::default()
    };
    let plan = crate::engine::job::plan_for(&p.scene, &request)?;
    Ok(BakeInputs::sharing(
        p.rays.clone(),
        p.atlas.clone(),
        lib.lighting,
        seed,
        plan,
    ))
}

/// `lib`'s closed form at every texel of `p` (at the texel's sample point in the scene's
/// own coordinates, before the import's recentring), or `None` for a scene without one.
pub fn analytic_reference(lib: &LibraryScene, p: &PreparedScene) -> Option<Vec<Option<Vec3>>> {
    let f = lib.analytic?;
    let offset = p.scene.origin_offset;
    Some(
        p.atlas
            .texels
            .iter()
            .map(|t| f(t.position.as_dvec3() + offset, t.geo_normal))
            .collect(),
    )
}

/// The reference for `lib`: its closed form, or a cached long `path` bake.
pub fn reference(lib: &LibraryScene, p: &PreparedScene, cfg: &BenchConfig) -> Result<Reference, EngineError> {
    if let Some(values) = analytic_reference(lib, p) {
        return Ok(Reference {
            values,
            kind: "analytic".into(),
            error: 0.0,
        });
    }
    let key = {
        let mut h = fnv1a(&p.glb, 0xcbf2_9ce4_8422_2325);
        h = fnv1a(&lib.resolution.to_le_bytes(), h);
        h = fnv1a(json!(lib.lighting).to_string().as_bytes(), h);
        fnv1a(&cfg.reference_budget.as_millis().to_le_bytes(), h)
    };
    let path = cfg.cache_dir.join(format!("{}-{key:016x}.ref", lib.name));
    if let Some(r) = read_cached(&path, p.atlas.texels.len()) {
        return Ok(r);
    }
    let mut tech = technique::create("path", inputs(p, lib, "path", 0xbe9c)?, &json!({"samples_per_step": 8}))?;
    let start = Instant::now();
    while start.elapsed() < cfg.reference_budget || tech.steps_done() < 2 {
        tech.step()?;
    }
    let est = tech.snapshot()?.estimate();
    let error = est.error.relative.unwrap_or(1.0) as f64;
    write_cached(&path, &est.total, error)
        .map_err(|e| EngineError::Internal(format!("writing {}: {e}", path.display())))?;
    Ok(Reference {
        values: est.total.into_iter().map(Some).collect(),
        kind: "path".into(),
        error,
    })
}

/// A cached reference of `texels` texels at `path` (its own error, then f32 RGB per
/// texel, little-endian), or `None` when it is missing or of another size.
pub fn read_cached(path: &Path, texels: usize) -> Option<Reference> {
    let bytes = std::fs::read(path).ok()?;
    if bytes.len() != 8 + texels * 12 {
        return None;
    }
    let error = f64::from_le_bytes(bytes[..8].try_into().ok()?);
    let floats: Vec<f32> = bytes[8..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    let values = floats
        .chunks_exact(3)
        .map(|c| Some(Vec3::new(c[0], c[1], c[2])))
        .collect();
    Some(Reference {
        values,
        kind: "path (cached)".into(),
        error,
    })
}

/// Writes a reference for [`read_cached`], atomically.
pub fn write_cached(path: &Path, values: &[Vec3], error: f64) -> std::io::Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let mut bytes = error.to_le_bytes().to_vec();
    for v in values {
        for c in v.to_array() {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    crate::engine::output::write_atomically(path, &bytes)
}

/// Bakes `technique` on a prepared scene, measuring at geometric time points (budget/128,
/// budget/64, …, budget), or with `steps` at 4, 16, 64, … steps up to it, stopping at the
/// budget if that comes first (a last snapshot then at the steps reached).
pub fn measure(
    lib: &LibraryScene,
    p: &PreparedScene,
    reference: &Reference,
    technique: &str,
    budget: Duration,
    steps: Option<u64>,
) -> Result<Vec<Sample>, EngineError> {
    let mut tech = technique::create(technique, inputs(p, lib, technique, 1)?, &serde_json::Value::Null)?;
    // A biased technique's estimate is what a job reports: its noise and, through the
    // control texels, its bias (issue 21), with the control's time in the clock as in a
    // bake; without it the "estimated" column showed noise alone (sdf on the Cornell box
    // 0.08 % against a true 13 %).
    let mut control = if technique::entry(technique)?.unbiased || p.atlas.texels.is_empty() {
        None
    } else {
        Some(ControlTexels::new(&p.rays, &p.atlas, lib.lighting, 1, 1)?)
    };
    let mut technique_time = Duration::ZERO;
    let mut samples = Vec::new();
    let start = Instant::now();
    // Never 0: the doubling below would not move it past the clock (a zero budget hung).
    let mut next = (budget.as_secs_f64() / 128.0).max(1e-6);
    let (mut next_step, mut recorded) = (4u64, 0u64);
    let request = BakeRequest {
        technique: technique.into(),
        lighting: lib.lighting,
        ..Default::default()
    };
    let oidn = crate::engine::post::oidn::Oidn::available();
    let mut record = |est: &Estimate, seconds: f64| {
        use crate::engine::post::denoised::{Used, apply};
        let denoised = crate::engine::job::finish(&p.atlas, est, &request);
        let own = apply(&p.atlas, est, Used::Own);
        let oidn_error = oidn.then(|| true_error(&apply(&p.atlas, est, Used::Oidn).total, &reference.values));
        samples.push(Sample {
            denoised_error: true_error(&denoised.total, &reference.values),
            denoised_estimate: denoised.error.relative,
            own_error: true_error(&own.total, &reference.values),
            oidn_error,
            scene: lib.name.into(),
            technique: technique.into(),
            seconds,
            steps: est.steps,
            true_error: true_error(&est.total, &reference.values),
            estimated_error: est.error.relative,
        })
    };
    loop {
        let t0 = Instant::now();
        tech.step()?;
        technique_time += t0.elapsed();
        if let Some(c) = &mut control {
            c.keep_up(technique_time)?;
        }
        let t = start.elapsed().as_secs_f64();
        let done = tech.steps_done();
        let over = t >= budget.as_secs_f64() && done >= 2;
        let due = match steps {
            // The sweep's snapshot, the last one, or the budget's end between two.
            Some(last) => done >= next_step || done >= last || (over && done > recorded),
            None => done >= 2 && (t >= next || t >= budget.as_secs_f64()),
        };
        if due {
            let mut est = tech.snapshot()?.estimate();
            if let Some(c) = &mut control {
                c.assess(&mut est)?;
            }
            record(&est, t);
            recorded = done;
            while next <= t {
                next *= 2.0;
            }
            while next_step <= done {
                next_step *= 4;
            }
        }
        if over || steps.is_some_and(|last| done >= last) {
            break;
        }
    }
    Ok(samples)
}

/// Runs the whole benchmark and writes its outputs; `log` receives one line per stage.
/// The scenes `names` asks for, in the library's order: the small scenes when empty,
/// `real` for every real-size one, else each by name.
pub fn select_scenes(names: &[String]) -> Result<Vec<LibraryScene>, EngineError> {
    let small = benchmark_scenes();
    let real = real_size_scenes();
    if names.is_empty() {
        return Ok(small);
    }
    for s in names {
        if s != "real" && !small.iter().chain(&real).any(|l| l.name == s) {
            let names: Vec<&str> = small.iter().chain(&real).map(|l| l.name).collect();
            return Err(EngineError::BadInput(format!(
                "unknown bench scene {s:?}; available: {}, or real (every real-size scene)",
                names.join(", ")
            )));
        }
    }
    let all_real = names.iter().any(|s| s == "real");
    Ok(small
        .into_iter()
        .filter(|l| names.iter().any(|s| s == l.name))
        .chain(
            real.into_iter()
                .filter(|l| all_real || names.iter().any(|s| s == l.name)),
        )
        .collect())
}

pub fn run(cfg: &BenchConfig, log: &mut dyn FnMut(&str)) -> Result<Vec<Sample>, EngineError> {
    let chosen = select_scenes(&cfg.scenes)?;
    for t in &cfg.techniques {
        technique::entry(t)?;
    }
    let io = |e: std::io::Error| EngineError::Internal(format!("writing bench results: {e}"));
    std::fs::create_dir_all(&cfg.out_dir).map_err(io)?;
    let mut all_samples = Vec::new();
    let mut refs = Vec::new();
    let mut probe_count = 0;
    for lib in &chosen {
        let p = prepare(lib)?;
        log(&format!(
            "{}: {} triangles, {} texels; reference…",
            lib.name,
            p.scene.triangles.len(),
            p.atlas.texels.len()
        ));
        let r = reference(lib, &p, cfg)?;
        refs.push((
            lib.name,
            r.kind.clone(),
            r.error,
            p.scene.triangles.len(),
            p.atlas.texels.len(),
        ));
        let mut scene_samples = Vec::new();
        for t in &cfg.techniques {
            match cfg.steps {
                Some(n) => log(&format!(
                    "{}: {t} to {n} steps, at most {:.0} s",
                    lib.name,
                    cfg.budget.as_secs_f64()
                )),
                None => log(&format!("{}: {t} for {:.0} s", lib.name, cfg.budget.as_secs_f64())),
            }
            scene_samples.extend(measure(lib, &p, &r, t, cfg.budget, cfg.steps)?);
        }
        std::fs::write(
            cfg.out_dir.join(format!("{}.svg", lib.name)),
            plot_svg(lib.name, &scene_samples),
        )
        .map_err(io)?;
        all_samples.extend(scene_samples);
    }
    let mut csv = String::from(
        "scene,technique,seconds,steps,true_error,estimated_error,denoised_error,denoised_estimate,own_error,oidn_error\n",
    );
    for s in &all_samples {
        let est = s.estimated_error.map(|e| format!("{e:.6}")).unwrap_or_default();
        let den_est = s.denoised_estimate.map(|e| format!("{e:.6}")).unwrap_or_default();
        let oidn = s.oidn_error.map(|e| format!("{e:.6}")).unwrap_or_default();
        let _ = writeln!(
            csv,
            "{},{},{:.4},{},{:.6},{},{:.6},{},{:.6},{}",
            s.scene, s.technique, s.seconds, s.steps, s.true_error, est, s.denoised_error, den_est, s.own_error, oidn
        );
    }
    std::fs::write(cfg.out_dir.join("results.csv"), csv).map_err(io)?;
    let mut md = summary_md(&all_samples, &refs, cfg);
    if cfg.probes {
        let mut probe_samples = Vec::new();
        for case in probes::probe_cases(PROBE_SIDE)? {
            for sampling in ["sobol", "independent"] {
                log(&format!(
                    "light probes, {}, {sampling}: {:.0} s",
                    case.name,
                    cfg.budget.as_secs_f64()
                ));
                probe_samples.extend(probes::measure(&case, cfg.budget, sampling)?);
            }
        }
        let mut csv = String::from("scene,device,sampling,probes,seconds,steps,true_error,estimated_error\n");
        for s in &probe_samples {
            let est = s.estimated_error.map(|e| format!("{e:.6}")).unwrap_or_default();
            let _ = writeln!(
                csv,
                "{},{},{},{},{:.4},{},{:.6},{}",
                s.scene, s.device, s.sampling, s.probes, s.seconds, s.steps, s.true_error, est
            );
        }
        std::fs::write(cfg.out_dir.join("probes.csv"), csv).map_err(io)?;
        md.push_str(&probes_md(&probe_samples));
        probe_count = probe_samples.len();
    }
    std::fs::write(cfg.out_dir.join("summary.md"), md).map_err(io)?;
    if cfg.probes {
        log(&format!("light probes: {probe_count} measurements in probes.csv"));
    }
    Ok(all_samples)
}

/// The first time in `run` (seconds, true error), in order, at which the error is at most
/// `target`, as a table cell ("—" when never).
fn time_to(run: impl IntoIterator<Item = (f64, f64)>, target: f64, digits: usize) -> String {
    run.into_iter()
        .find(|(_, e)| *e <= target)
        .map(|(t, _)| format!("{t:.digits$} s"))
        .unwrap_or_else(|| "—".into())
}

/// Probes a side of each probe scene's grid: 4³ = 64 probes.
const PROBE_SIDE: usize = 4;

/// The probes' table in summary.md: time to each true error, and the last measurement.
fn probes_md(samples: &[probes::ProbeSample]) -> String {
    let mut md = String::from(
        "\nLight probes (closed-form c00, 64 samples a probe a step; `probes.csv`): time to reach a true relative error of L0.\n\n\
         | scene | device | sampling | probes | 10 % | 5 % | 2 % | 1 % | final error (estimated) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    );
    let mut runs: Vec<(&str, &str)> = samples
        .iter()
        .map(|s| (s.scene.as_str(), s.sampling.as_str()))
        .collect();
    runs.dedup();
    for (name, sampling) in runs {
        let run: Vec<&probes::ProbeSample> = samples
            .iter()
            .filter(|s| s.scene == name && s.sampling == sampling)
            .collect();
        let reach = |target: f64| time_to(run.iter().map(|s| (s.seconds, s.true_error)), target, 3);
        let Some(last) = run.last() else { continue };
        let est = last
            .estimated_error
            .map(|e| format!("{:.2} %", e * 100.0))
            .unwrap_or_else(|| "n/a".into());
        let _ = writeln!(
            md,
            "| {name} | {} | {sampling} | {} | {} | {} | {} | {} | {:.2} % ({est}) |",
            last.device,
            last.probes,
            reach(0.10),
            reach(0.05),
            reach(0.02),
            reach(0.01),
            last.true_error * 100.0
        );
    }
    md
}

fn summary_md(samples: &[Sample], refs: &[(&str, String, f64, usize, usize)], cfg: &BenchConfig) -> String {
    let mut md = String::new();
    let _ = match cfg.steps {
        Some(n) => writeln!(
            md,
            "Snapshots at 4, 16, 64, … up to {n} steps, at most {:.0} s per scene and technique (a row that stops at the budget ends at the steps it reached).\n",
            cfg.budget.as_secs_f64()
        ),
        None => writeln!(
            md,
            "Budget {:.0} s per scene and technique.\n",
            cfg.budget.as_secs_f64()
        ),
    };
    let _ = writeln!(
        md,
        "| scene | triangles | texels | reference | reference error |\n| --- | --- | --- | --- | --- |"
    );
    for (name, kind, err, tris, texels) in refs {
        let _ = writeln!(md, "| {name} | {tris} | {texels} | {kind} | {:.2} % |", err * 100.0);
    }
    let _ = writeln!(
        md,
        "\nTime to reach a true relative error (— = not within the budget); last column: error at the end.\n"
    );
    let _ = writeln!(
        md,
        "| scene | technique | steps | 10 % | 5 % | 2 % | 1 % | 2 % denoised | final error (estimated) | final denoised (estimated) | snapshots denoised worse than raw | worst denoised / raw (at steps) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"
    );
    let mut keys: Vec<(&str, &str)> = samples
        .iter()
        .map(|s| (s.scene.as_str(), s.technique.as_str()))
        .collect();
    keys.dedup();
    for (scene, tech) in keys {
        let run: Vec<&Sample> = samples
            .iter()
            .filter(|s| s.scene == scene && s.technique == tech)
            .collect();
        let reach_denoised = time_to(run.iter().map(|s| (s.seconds, s.denoised_error)), 0.02, 2);
        let last_denoised = run
            .last()
            .map(|s| {
                let est = s
                    .denoised_estimate
                    .map(|e| format!("{:.2} %", e * 100.0))
                    .unwrap_or_else(|| "n/a".into());
                format!("{:.2} % ({est})", s.denoised_error * 100.0)
            })
            .unwrap_or_default();
        let worse = run.iter().filter(|s| s.denoised_error > s.true_error).count();
        // The largest ratio, where raw has an error to compare with (a closed form met
        // to rounding is no test of the denoiser).
        let worst = run
            .iter()
            .filter(|s| s.true_error > 1e-5)
            .map(|s| (s.denoised_error / s.true_error, s.steps))
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map_or_else(|| "n/a".into(), |(r, steps)| format!("{r:.4} ({steps})"));
        let steps = match (run.first(), run.last()) {
            (Some(a), Some(b)) => format!("{}-{}", a.steps, b.steps),
            _ => String::new(),
        };
        let reach = |target: f64| time_to(run.iter().map(|s| (s.seconds, s.true_error)), target, 2);
        let last = run.last().map(|s| {
            let est = s
                .estimated_error
                .map(|e| format!("{:.2} %", e * 100.0))
                .unwrap_or_else(|| "n/a".into());
            format!("{:.2} % ({est})", s.true_error * 100.0)
        });
        let _ = writeln!(
            md,
            "| {scene} | {tech} | {steps} | {} | {} | {} | {} | {reach_denoised} | {} | {last_denoised} | {worse} of {} | {worst} |",
            reach(0.10),
            reach(0.05),
            reach(0.02),
            reach(0.01),
            last.unwrap_or_default(),
            run.len()
        );
    }
    md
}

/// A log-log plot of true error (solid) and estimated error (dashed) against time.
pub fn plot_svg(title: &str, samples: &[Sample]) -> String {
    let (w, h, left, right, top, bottom) = (640.0, 420.0, 70.0, 150.0, 40.0, 50.0);
    let pts: Vec<&Sample> = samples
        .iter()
        .filter(|s| s.seconds > 0.0 && s.true_error > 0.0)
        .collect();
    let (mut t0, mut t1, mut e0, mut e1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for s in &pts {
        t0 = t0.min(s.seconds.log10());
        t1 = t1.max(s.seconds.log10());
        for e in [
            Some(s.true_error),
            s.estimated_error.map(|e| e as f64).filter(|e| *e > 0.0),
        ]
        .into_iter()
        .flatten()
        {
            e0 = e0.min(e.log10());
            e1 = e1.max(e.log10());
        }
    }
    if pts.is_empty() {
        (t0, t1, e0, e1) = (-1.0, 1.0, -3.0, 0.0);
    }
    let (t0, t1, e0, e1) = (
        t0.floor(),
        t1.ceil().max(t0.floor() + 1.0),
        e0.floor(),
        e1.ceil().max(e0.floor() + 1.0),
    );
    let x = |t: f64| left + (t.log10() - t0) / (t1 - t0) * (w - left - right);
    let y = |e: f64| top + (e1 - e.log10()) / (e1 - e0) * (h - top - bottom);
    let mut svg = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"12\">\n\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n\
         <text x=\"{}\" y=\"22\" text-anchor=\"middle\" font-size=\"15\">{title}: relative error against time</text>\n",
        (left + w - right) / 2.0
    );
    for d in t0 as i32..=t1 as i32 {
        let px = x(10f64.powi(d));
        let _ = writeln!(
            svg,
            "<line x1=\"{px}\" y1=\"{top}\" x2=\"{px}\" y2=\"{}\" stroke=\"#ddd\"/><text x=\"{px}\" y=\"{}\" text-anchor=\"middle\">1e{d} s</text>",
            h - bottom,
            h - bottom + 18.0
        );
    }
    for d in e0 as i32..=e1 as i32 {
        let py = y(10f64.powi(d));
        let _ = writeln!(
            svg,
            "<line x1=\"{left}\" y1=\"{py}\" x2=\"{}\" y2=\"{py}\" stroke=\"#ddd\"/><text x=\"{}\" y=\"{}\" text-anchor=\"end\">1e{d}</text>",
            w - right,
            left - 6.0,
            py + 4.0
        );
    }
    let colours = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"];
    let mut techniques: Vec<&str> = pts.iter().map(|s| s.technique.as_str()).collect();
    techniques.dedup();
    for (k, tech) in techniques.iter().enumerate() {
        let colour = colours[k % colours.len()];
        let run: Vec<&&Sample> = pts.iter().filter(|s| s.technique == *tech).collect();
        let line: Vec<String> = run
            .iter()
            .map(|s| format!("{:.1},{:.1}", x(s.seconds), y(s.true_error)))
            .collect();
        let est: Vec<String> = run
            .iter()
            .filter_map(|s| {
                s.estimated_error
                    .filter(|e| *e > 0.0)
                    .map(|e| format!("{:.1},{:.1}", x(s.seconds), y(e as f64)))
            })
            .collect();
        let _ = writeln!(
            svg,
            "<polyline fill=\"none\" stroke=\"{colour}\" stroke-width=\"2\" points=\"{}\"/>",
            line.join(" ")
        );
        let _ = writeln!(
            svg,
            "<polyline fill=\"none\" stroke=\"{colour}\" stroke-dasharray=\"5,4\" points=\"{}\"/>",
            est.join(" ")
        );
        let ly = top + 20.0 * k as f64;
        let _ = writeln!(
            svg,
            "<line x1=\"{}\" y1=\"{ly}\" x2=\"{}\" y2=\"{ly}\" stroke=\"{colour}\" stroke-width=\"2\"/><text x=\"{}\" y=\"{}\">{tech}</text>",
            w - right + 10.0,
            w - right + 34.0,
            w - right + 40.0,
            ly + 4.0
        );
    }
    let _ = writeln!(
        svg,
        "<text x=\"{}\" y=\"{}\" fill=\"#555\">solid: true error</text><text x=\"{}\" y=\"{}\" fill=\"#555\">dashed: estimated</text>\n</svg>",
        w - right + 10.0,
        h - bottom - 20.0,
        w - right + 10.0,
        h - bottom - 4.0
    );
    svg
}
