//! `lightmapd bake` and `lightmapd merge`: the engine on one scene with no server. A
//! bake writes its lightmap pages (and, on request, the scene with its lightmap UVs,
//! light probes, a preview and a saved state), with a progress bar; with `--task K/N` it
//! bakes one task of a split bake (a step range, a chain, a region, or one region's task
//! of a round), and `merge` puts the tasks' results back together (docs/scaling.md).

use std::io::IsTerminal;
use std::ops::ControlFlow;
use std::path::PathBuf;
use std::sync::Arc;

use clap::ValueEnum;
use indicatif::{ProgressBar, ProgressStyle};
use lightmapd::engine::bake::{BakeEvent, StopCriteria};
use lightmapd::engine::job::{self, BakeRequest};
use lightmapd::engine::output::{OutputLayer, write_atomically};
use lightmapd::engine::scene;
use lightmapd::engine::tasks;
use lightmapd::engine::technique::obscurance::{ObscuranceState, UpdateReach};

use super::{Failure, LightingArgs, bad_input, engine_failure, error_text, log_format};

#[derive(clap::Args)]
pub(crate) struct BakeArgs {
    /// The scene: .glb, or .gltf with its buffers and images beside it.
    scene: PathBuf,
    /// Where to write the lightmap: a folder (created if missing) gets one OpenEXR per
    /// page, `lightmap-P.exr`, and `lightmaps.json`; a path ending in `.exr` gets the
    /// lightmap of a one-page bake (a bake that needs several pages then stops before
    /// baking, exit 2). With `--task K/N`: the task's result file.
    #[arg(short, long)]
    output: PathBuf,
    #[arg(long, default_value = "path")]
    technique: String,
    /// Lightmap width and height in texels.
    #[arg(long, default_value_t = 256)]
    resolution: u32,
    #[command(flatten)]
    lighting: LightingArgs,
    /// Stop after this many steps.
    #[arg(long)]
    steps: Option<u64>,
    /// Stop after this many seconds.
    #[arg(long)]
    seconds: Option<f64>,
    /// Stop when the estimated relative error falls to this.
    #[arg(long)]
    target_error: Option<f32>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Extra layers: validity, direct, indirect, sh, ao, debug, shadowmask (comma separated).
    #[arg(long, value_delimiter = ',', value_parser = OutputLayer::parse)]
    outputs: Vec<OutputLayer>,
    /// The shadowmask's lights, one per channel: sun, a light's name or #index (comma
    /// separated; default: the sun and the scene's lights, at most four). Their direct
    /// light is left out of the lightmap and direct.* (a renderer adds it times the mask).
    #[arg(long, value_delimiter = ',')]
    shadowmask_lights: Vec<String>,
    /// Write the raw estimate, without a denoiser (same as `--denoiser none`).
    #[arg(long)]
    no_denoise: bool,
    /// Denoiser: auto (OIDN when installed, else own), oidn, own, none.
    #[arg(long, value_parser = lightmapd::engine::post::denoised::Denoiser::parse)]
    denoiser: Option<lightmapd::engine::post::denoised::Denoiser>,
    /// Lightmap UVs: keep (authored only), generate-missing (default), regenerate-all,
    /// repack-instances (authored UVs of a mesh several nodes place get a rectangle per
    /// node, the UVs kept).
    #[arg(long, default_value = "generate-missing")]
    lightmap_uvs: lightmapd::engine::atlas::unwrap::LightmapUvs,
    /// Texel density of generated lightmap UVs (texels per metre); default: the highest
    /// at which they fit one --resolution-wide page.
    #[arg(long)]
    texels_per_unit: Option<f32>,
    /// At a --texels-per-unit, the widest a page grows (from --resolution, doubling) while
    /// the charts need more than one page; beyond it they take several pages of this size
    /// (default 4096, or --resolution if larger).
    #[arg(long)]
    max_page_size: Option<u32>,
    /// Also write the scene as .glb with its lightmap UVs (TEXCOORD_1), e.g. after they
    /// were generated for a scene that had none.
    #[arg(long)]
    write_gltf: Option<PathBuf>,
    /// Also write a tone-mapped PNG preview here.
    #[arg(long)]
    preview: Option<PathBuf>,
    /// Technique parameters as a JSON object, e.g. '{"samples_per_step": 8}'.
    #[arg(long)]
    params: Option<String>,
    /// obscurance: also save the bake's state (accumulators and influence masks, JSON)
    /// here, for a later `--update-from`.
    #[arg(long)]
    save_state: Option<PathBuf>,
    /// obscurance: update the bake saved in this state file for the scene given, where
    /// the meshes named by --changed-meshes moved or were added: only the texels they
    /// influence are recomputed (the same step count as the saved bake).
    #[arg(long, requires = "changed_meshes")]
    update_from: Option<PathBuf>,
    /// obscurance: names of the meshes that moved or were added (comma separated).
    #[arg(long, value_delimiter = ',')]
    changed_meshes: Vec<String>,
    /// obscurance --update-from: recompute texels that saw a changed mesh at any
    /// distance (`all`: obscurance and direct light) or within dmax only (`dmax`: the
    /// paper's set, faster, misses far sky occlusion).
    #[arg(long, value_enum, default_value = "all")]
    update_reach: ReachArg,
    /// Also bake light probes (radiance SH to L2 by `path` on the CPU, docs/probes.md)
    /// on a grid of --probe-spacing over the scene's bounds and at the glTF nodes whose
    /// extras.light_probe is true, written here as JSON.
    #[arg(long)]
    probes: Option<PathBuf>,
    /// Probe grid spacing in metres.
    #[arg(long)]
    probe_spacing: Option<f32>,
    /// Split the probe grid's cells that geometry passes through into 8, this many levels
    /// down (0 to 4): denser probes near surfaces.
    #[arg(long, default_value_t = 0)]
    probe_subdivide: u32,
    /// Steps of the probe bake (64 samples a probe each).
    #[arg(long, default_value_t = 16)]
    probe_steps: u32,
    /// Where the probes bake: auto (the GPU when a hardware adapter is there), cpu or gpu.
    #[arg(long, value_enum, default_value_t = ProbeDevice::Auto)]
    probe_device: ProbeDevice,
    /// Bake only task K of N (0-based) of a bake split across processes or machines:
    /// its share of `--steps`, written to -o as a task result for `lightmapd merge`
    /// (docs/scaling.md). Every task takes the same options. A `path` task is a range of
    /// the job's steps; any other technique's is an independent chain (the whole grid
    /// from step 0 with its own seed), which the merge averages.
    #[arg(long, value_parser = parse_task)]
    task: Option<(u32, u32)>,
    /// With --task: the N tasks are R regions of the grid (its pages when R is at most the
    /// page count, else bands of rows with equal texel counts), each baked as N / R step
    /// ranges (`path`) or chains (`vpl`, `sdf`, `obscurance`); task K bakes region
    /// K / (N / R). `sdb` and `hemicube` do not split tasks by regions (each step moves
    /// light over the whole grid); with --rounds, `hemicube` and `sdb` bake regions in rounds.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    regions: Option<u32>,
    /// Bake in this many rounds, the grid cut into --regions regions, each region baked
    /// with the others' light held at what the round before estimated (block Jacobi,
    /// `hemicube` and `sdb`; docs/scaling.md, "Pages in rounds"); --steps is every region's,
    /// over all rounds. Alone: every round in this process, one region after another.
    /// With --task K/R and --round: one region's task of one round, written for
    /// `lightmapd merge` (the last round's) and for the next round's --previous.
    #[arg(long, requires = "regions", value_parser = clap::value_parser!(u32).range(1..=64))]
    rounds: Option<u32>,
    /// With --rounds and --task: the round (0-based) this task bakes.
    #[arg(long, requires = "rounds", requires = "task")]
    round: Option<u32>,
    /// With --round above 0: every region's task result of the round before (the light
    /// this task holds, and its own region's accumulators).
    #[arg(long, num_args = 1.., requires = "round")]
    previous: Vec<PathBuf>,
}

/// `--probe-device`.
#[derive(Clone, Copy, ValueEnum)]
enum ProbeDevice {
    Auto,
    Cpu,
    Gpu,
}

impl From<ProbeDevice> for lightmapd::engine::gpu::RayDevice {
    fn from(d: ProbeDevice) -> Self {
        match d {
            ProbeDevice::Auto => Self::Auto,
            ProbeDevice::Cpu => Self::Cpu,
            ProbeDevice::Gpu => Self::Gpu,
        }
    }
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum ReachArg {
    All,
    Dmax,
}

fn parse_task(s: &str) -> Result<(u32, u32), String> {
    let bad = || format!("--task takes K/N with 0 <= K < N (task K of N), got {s:?}");
    let (k, n) = s.split_once('/').ok_or_else(bad)?;
    let (k, n) = (
        k.trim().parse::<u32>().map_err(|_| bad())?,
        n.trim().parse::<u32>().map_err(|_| bad())?,
    );
    if k >= n {
        return Err(bad());
    }
    Ok((k, n))
}

/// The bake the options ask for, checked as far as the options alone allow (the
/// technique's name, `--params` as JSON); the engine checks the rest before baking.
fn request(args: &BakeArgs) -> Result<BakeRequest, Failure> {
    lightmapd::engine::technique::entry(&args.technique).map_err(|e| bad_input(e.to_string()))?;
    let params = match &args.params {
        Some(p) => serde_json::from_str(p).map_err(|e| bad_input(format!("--params is not JSON: {e}")))?,
        None => serde_json::Value::Null,
    };
    let stop = if args.steps.is_none() && args.seconds.is_none() && args.target_error.is_none() {
        BakeRequest::default().stop
    } else {
        StopCriteria {
            steps: args.steps,
            seconds: args.seconds,
            target_error: args.target_error,
        }
    };
    Ok(BakeRequest {
        technique: args.technique.clone(),
        resolution: args.resolution,
        lighting: args.lighting.lighting(),
        stop,
        params,
        outputs: args.outputs.clone(),
        seed: args.seed,
        denoise: if args.no_denoise {
            lightmapd::engine::post::denoised::Denoiser::None
        } else {
            args.denoiser.unwrap_or_default()
        },
        lightmap_uvs: args.lightmap_uvs,
        texels_per_unit: args.texels_per_unit,
        max_page_size: args.max_page_size,
        shadowmask_lights: args.shadowmask_lights.clone(),
        // Checked with the rest of the request before the bake (exit 2 naming the field).
        probes: args.probes.as_ref().map(|_| lightmapd::engine::job::ProbeRequest {
            spacing: args.probe_spacing,
            subdivide: args.probe_subdivide,
            positions: Vec::new(),
            steps: args.probe_steps,
            device: args.probe_device.into(),
        }),
    })
}

pub(crate) fn bake(args: BakeArgs) -> Result<(), Failure> {
    let request = request(&args)?;
    let stop = request.stop;
    let (scene, report) =
        scene::import_file(&args.scene).map_err(|e| bad_input(format!("{}: {e}", args.scene.display())))?;
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    tracing::info!(triangles = report.triangles, lights = report.lights, "scene imported");
    // Before the bake, not only in the plan line after it: a level exported without its
    // lights bakes an exactly black lightmap, which a user should not wait for to learn.
    if !lightmapd::engine::plan::SceneFeatures::of(&scene, &request.lighting, &request.outputs).has_light() {
        eprintln!(
            "warning: the scene has no emissive surface or punctual light and the bake no --sky or --sun: the lightmap will be exactly zero (give --sky R,G,B for a uniform sky)"
        );
    }

    if let Some(w) = request.lighting.faint_sun() {
        eprintln!("warning: {w}");
    }

    let bar = progress_bar(stop.steps);
    // A one-file output for a bake that needs several pages stops the bake as soon as
    // the texel grid (and so its pages) is known, before any sampling.
    let pages_over = std::cell::Cell::new(None::<usize>);
    let mut observer = |e: BakeEvent<'_>| {
        if pages_over.get().is_some() {
            return ControlFlow::Break(());
        }
        match e {
            BakeEvent::Progress { steps, .. } => bar.set_position(steps),
            BakeEvent::Snapshot { estimate, .. } => {
                if let Some(err) = estimate.error.relative {
                    bar.set_message(format!("error {:.2}%", err * 100.0));
                }
            }
            // Written with the lightmap (`--write-gltf`).
            BakeEvent::GeneratedUvs { .. } => {}
            BakeEvent::Probes { steps, of, probes } => {
                bar.set_message(format!("light probes: {probes} probes, step {steps} of {of}"));
            }
        }
        ControlFlow::Continue(())
    };
    let single_file = is_exr_path(&args.output);
    let mut on_atlas = |atlas: &Arc<lightmapd::engine::atlas::Atlas>| {
        let a = atlas.report();
        tracing::info!(
            texels = a.valid_texels,
            overlapping = a.overlapping_texels,
            pages = a.pages,
            "texel set built"
        );
        if single_file && atlas.pages.len() > 1 {
            pages_over.set(Some(atlas.pages.len()));
        }
    };
    if args.regions.is_some() && args.task.is_none() && args.rounds.is_none() {
        return Err(bad_input(
            "--regions cuts the grid for --task or --rounds; give one of them",
        ));
    }
    if let Some((k, n)) = args.task {
        return bake_task(
            &args,
            Arc::new(scene),
            &request,
            k,
            n,
            &mut observer,
            &mut on_atlas,
            &bar,
        );
    }
    let result = if args.save_state.is_some() || args.update_from.is_some() {
        let previous: Option<ObscuranceState> = match &args.update_from {
            Some(p) => {
                let bytes = std::fs::read(p).map_err(|e| bad_input(format!("{}: {e}", p.display())))?;
                Some(
                    serde_json::from_slice(&bytes)
                        .map_err(|e| bad_input(format!("{}: not an obscurance state file: {e}", p.display())))?,
                )
            }
            None => None,
        };
        let reach = match args.update_reach {
            ReachArg::All => UpdateReach::All,
            ReachArg::Dmax => UpdateReach::Dmax,
        };
        let update = previous.as_ref().map(|s| (s, args.changed_meshes.as_slice(), reach));
        let (result, state) = job::bake_obscurance(
            Arc::new(scene),
            &request,
            &job::BakeOptions::default(),
            &mut observer,
            update,
        )
        .map_err(engine_failure)?;
        if let Some(p) = &args.save_state {
            let bytes = serde_json::to_vec(&state).map_err(|e| Failure {
                code: 1,
                message: format!("encoding the bake state: {e}"),
            })?;
            write_atomically(p, &bytes).map_err(|e| Failure {
                code: 1,
                message: format!("cannot write {}: {e}", p.display()),
            })?;
        }
        result
    } else if let (Some(rounds), None) = (args.rounds, args.task) {
        let shape = lightmapd::engine::rounds::RoundsShape {
            regions: args.regions.unwrap_or(1),
            rounds,
        };
        if let Some(n) = stop.steps {
            bar.set_length(n * u64::from(shape.regions));
        }
        let baked = lightmapd::engine::rounds::bake_in_rounds(
            Arc::new(scene),
            &request,
            shape,
            &job::BakeOptions::default(),
            &mut observer,
            &mut on_atlas,
        );
        if let Some(n) = pages_over.get() {
            bar.finish_and_clear();
            return Err(several_pages(&args.output, n));
        }
        let baked = baked.map_err(engine_failure)?;
        for (k, r) in baked.rounds.iter().enumerate() {
            eprintln!(
                "round {k}: {} steps a region in {:.2} s, the held light moved {:.2} % of its RMS",
                r.steps,
                r.seconds,
                r.change * 100.0
            );
        }
        baked.result
    } else {
        // How far the step in progress is, shown beside the step count while a long step
        // runs (`bake::StepProgress`; CPU `path` reports it).
        let progress = lightmapd::engine::bake::StepProgress::new();
        let options = job::BakeOptions {
            step_progress: Some(progress.clone()),
            ..Default::default()
        };
        let done = std::sync::atomic::AtomicBool::new(false);
        std::thread::scope(|scope| {
            scope.spawn(|| {
                while !done.load(std::sync::atomic::Ordering::Relaxed) {
                    let p = progress.permille();
                    bar.set_prefix(if p > 0 && p < 1000 {
                        format!(" (+{} %)", p / 10)
                    } else {
                        String::new()
                    });
                    std::thread::sleep(std::time::Duration::from_millis(200));
                }
            });
            let result = job::bake(
                Arc::new(scene),
                &request,
                &options,
                &mut observer,
                &mut on_atlas,
                &mut |plan| tracing::info!(plan = %plan.summary_line(), "plan"),
            );
            done.store(true, std::sync::atomic::Ordering::Relaxed);
            result
        })
        .map_err(engine_failure)?
    };
    bar.finish_and_clear();
    if let Some(n) = pages_over.get() {
        return Err(several_pages(&args.output, n));
    }
    let written = write_lightmaps(&args.output, &result)?;
    if let Some(p) = &args.write_gltf {
        let glb = lightmapd::engine::scene::export::to_glb(&result.scene).map_err(|e| Failure {
            code: 1,
            message: format!("writing {}: {e}", p.display()),
        })?;
        write_atomically(p, &glb).map_err(|e| Failure {
            code: 1,
            message: format!("cannot write {}: {e}", p.display()),
        })?;
    }
    if let Some(p) = &args.preview {
        write_atomically(p, &result.preview_png).map_err(|e| Failure {
            code: 1,
            message: format!("cannot write {}: {e}", p.display()),
        })?;
    }
    if let (Some(path), Some(set)) = (&args.probes, &result.probes) {
        write_probes(set, path)?;
    }
    print_summary(&args.scene, &result.summary, &written);
    Ok(())
}

/// The bake's progress bar on a terminal (hidden otherwise), `steps` long when the bake
/// stops at a step count; log lines are written above it (`log_format::show_above`).
fn progress_bar(steps: Option<u64>) -> ProgressBar {
    let bar = if std::io::stderr().is_terminal() {
        ProgressBar::new(0)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} {elapsed_precise} [{wide_bar}] step {pos}{prefix} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    log_format::show_above(&bar);
    if let Some(n) = steps {
        bar.set_length(n);
    }
    // The bar's clock and spinner move on their own, so a long step (a large level's pass
    // over every texel) never looks like a hang.
    bar.enable_steady_tick(std::time::Duration::from_millis(250));
    bar
}

/// The lines a finished bake prints: its plan, the generated UVs, the validation's
/// warnings and the one-line result.
fn print_summary(scene: &std::path::Path, s: &job::BakeSummary, written: &str) {
    eprintln!("plan: {}", s.plan.summary_line());
    if let Some(u) = &s.generated_uvs {
        eprintln!(
            "generated lightmap UVs: {} charts, {:.0} % of the lightmap used, {:.1} texels per metre",
            u.charts,
            u.utilisation * 100.0,
            u.texels_per_metre
        );
        if u.repacked_instances > 0 {
            eprintln!(
                "repacked instances: {} nodes of meshes with authored UVs, each its own rectangle, on {} page(s)",
                u.repacked_instances, u.repacked_pages
            );
        }
    }
    for w in &s.validation.warnings {
        eprintln!("warning: {w}");
    }
    let err = error_text(s.error.relative);
    eprintln!(
        "baked {} ({}x{}, {} texels) with {}: {} steps in {:.2} s ({:.2} ms a step), estimated error {} (stopped by {:?}) -> {}",
        scene.display(),
        s.atlas.width,
        s.atlas.height,
        s.atlas.valid_texels,
        s.technique,
        s.steps,
        s.seconds,
        1e3 * s.seconds / s.steps.max(1) as f64,
        err,
        s.stopped_by,
        written
    );
}

/// Whether `-o` names one EXR file rather than a folder of pages.
fn is_exr_path(path: &std::path::Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"))
}

fn several_pages(path: &std::path::Path, pages: usize) -> Failure {
    bad_input(format!(
        "the bake needs {pages} lightmap pages and -o {} names one EXR file: give -o a folder for lightmap-P.exr and lightmaps.json",
        path.display()
    ))
}

/// Writes a bake's pages to `-o`: a folder gets every `lightmap-P.exr` and
/// `lightmaps.json` (the manifest last, so it names only pages on disk); an `.exr` path
/// gets the one page. Returns what was written, for the summary line.
fn write_lightmaps(output: &std::path::Path, result: &job::BakeResult) -> Result<String, Failure> {
    let cannot = |p: &std::path::Path, e: std::io::Error| Failure {
        code: 1,
        message: format!("cannot write {}: {e}", p.display()),
    };
    if is_exr_path(output) {
        if result.pages.len() > 1 {
            return Err(several_pages(output, result.pages.len()));
        }
        write_atomically(output, result.first_page()).map_err(|e| cannot(output, e))?;
        return Ok(output.display().to_string());
    }
    std::fs::create_dir_all(output).map_err(|e| cannot(output, e))?;
    for page in &result.pages {
        let p = output.join(&page.entry.file);
        write_atomically(&p, &page.exr).map_err(|e| cannot(&p, e))?;
    }
    let manifest = serde_json::to_vec_pretty(&result.manifest).map_err(|e| Failure {
        code: 1,
        message: format!("encoding lightmaps.json: {e}"),
    })?;
    let p = output.join(lightmapd::engine::output::pages::MANIFEST_FILE);
    write_atomically(&p, &manifest).map_err(|e| cannot(&p, e))?;
    Ok(format!(
        "{} ({} page{} and {})",
        output.display(),
        result.pages.len(),
        if result.pages.len() == 1 { "" } else { "s" },
        lightmapd::engine::output::pages::MANIFEST_FILE
    ))
}

/// `bake --task K/N`: one task's result to `args.output` (`engine::tasks`).
#[allow(clippy::too_many_arguments)]
fn bake_task(
    args: &BakeArgs,
    scene: Arc<scene::Scene>,
    request: &BakeRequest,
    k: u32,
    n: u32,
    observer: &mut dyn lightmapd::engine::bake::BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<lightmapd::engine::atlas::Atlas>),
    bar: &ProgressBar,
) -> Result<(), Failure> {
    let elsewhere = [
        (
            args.save_state.is_some() || args.update_from.is_some(),
            "--save-state/--update-from",
        ),
        (args.probes.is_some(), "--probes"),
        (args.write_gltf.is_some(), "--write-gltf"),
        (args.preview.is_some(), "--preview (give it to `lightmapd merge`)"),
    ];
    if let Some((_, flag)) = elsewhere.iter().find(|(given, _)| *given) {
        return Err(bad_input(format!("--task: {flag} is not for a task of a split bake")));
    }
    let (task, partial) = if let Some(rounds) = args.rounds {
        let regions = args.regions.unwrap_or(1);
        if n != regions {
            return Err(bad_input(format!(
                "--rounds: --task K/N takes N = --regions ({regions}), one task a region each round; got N = {n}"
            )));
        }
        let Some(round) = args.round else {
            return Err(bad_input(
                "--task with --rounds needs --round (the round this task bakes)",
            ));
        };
        let all = tasks::split_rounds(request, regions, rounds).map_err(engine_failure)?;
        let task = all
            .get(round as usize)
            .map(|r| r[k as usize])
            .ok_or_else(|| bad_input(format!("--round {round}: the bake has rounds 0..{rounds}")))?;
        let mut previous = Vec::with_capacity(args.previous.len());
        for p in &args.previous {
            previous.push(read_round_before(p, task.region)?);
        }
        bar.set_length(task.steps);
        let partial = lightmapd::engine::rounds::bake_round_task(
            scene,
            request,
            task,
            &previous,
            &job::BakeOptions::default(),
            observer,
            on_atlas,
        )
        .map_err(engine_failure)?;
        (task, partial)
    } else {
        let shape = tasks::TaskShape {
            tasks: n,
            regions: args.regions.unwrap_or(1),
        };
        let tasks = tasks::split(request, shape).map_err(engine_failure)?;
        let task = tasks[k as usize];
        bar.set_length(task.steps);
        let partial = tasks::bake_task(
            scene,
            request,
            task,
            &job::BakeOptions::default(),
            observer,
            on_atlas,
            &mut |plan| tracing::info!(plan = %plan.summary_line(), "plan"),
        )
        .map_err(engine_failure)?;
        (task, partial)
    };
    bar.finish_and_clear();
    let bytes = partial.encode().map_err(engine_failure)?;
    write_atomically(&args.output, &bytes).map_err(|e| Failure {
        code: 1,
        message: format!("cannot write {}: {e}", args.output.display()),
    })?;
    let h = &partial.header;
    let mut region = if task.regions > 1 {
        format!(", region {}/{} ({} texels)", task.region, task.regions, h.texels)
    } else {
        String::new()
    };
    // A round task's halves go on from the rounds before it: its own steps are the
    // round's.
    let baked = if task.rounds > 0 {
        region += &format!(", round {}/{}", task.round, task.rounds);
        task.steps
    } else {
        h.half_steps[0] + h.half_steps[1]
    };
    eprintln!(
        "baked task {k}/{n} of {}{region}: steps {}..{} ({} steps in {:.2} s, stopped by {:?}) -> {}",
        args.scene.display(),
        task.first_step,
        task.first_step + baked,
        baked,
        h.seconds,
        h.stopped_by,
        args.output.display()
    );
    Ok(())
}

/// One `--previous` file of a round task: read whole when it is the task's own region's
/// (the halves it resumes), not a round result or not the size its header describes
/// (whose errors `decode` names), or not a plain file (a pipe cannot seek); else only its
/// header, pixels and held light, seeking past its halves (`Partial::decode_held`: 16
/// bytes a texel of a round result's 40, or 64 with the `direct` layer).
fn read_round_before(path: &std::path::Path, region: u32) -> Result<tasks::Partial, Failure> {
    use std::io::{Read, Seek, SeekFrom};
    let what = path.display().to_string();
    let io = |e: std::io::Error| bad_input(format!("{what}: {e}"));
    let bad = |e: lightmapd::engine::technique::EngineError| bad_input(e.to_string());
    let whole = || -> Result<tasks::Partial, Failure> {
        let bytes = std::fs::read(path).map_err(io)?;
        tasks::Partial::decode(&bytes, &what).map_err(bad)
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let meta = file.metadata().map_err(io)?;
    if !meta.is_file() {
        return whole();
    }
    let size = meta.len();
    let mut start = vec![0u8; tasks::PartialLayout::LEAD.min(size as usize)];
    file.read_exact(&mut start).map_err(io)?;
    let len = tasks::PartialLayout::header_len(&start, &what).map_err(bad)?;
    if len > size - start.len() as u64 {
        return Err(bad_input(format!(
            "{what}: header of {len} bytes runs past the end of the file"
        )));
    }
    start.resize(start.len() + len as usize, 0);
    file.read_exact(&mut start[tasks::PartialLayout::LEAD..]).map_err(io)?;
    let layout = tasks::PartialLayout::parse(&start, &what).map_err(bad)?;
    if layout.header.task.region == region || !layout.header.held || layout.file_len() != size {
        return whole();
    }
    let mut read = |r: &std::ops::Range<u64>| -> Result<Vec<u8>, Failure> {
        let mut b = vec![0u8; (r.end - r.start) as usize];
        file.seek(SeekFrom::Start(r.start)).map_err(io)?;
        file.read_exact(&mut b).map_err(io)?;
        Ok(b)
    };
    let (pixels, held) = (read(&layout.pixels)?, read(&layout.held)?);
    tasks::Partial::decode_held(layout, &pixels, &held, &what).map_err(bad)
}

/// Writes the baked probes as JSON to `path`.
fn write_probes(
    set: &lightmapd::engine::technique::path::probes::ProbeSet,
    path: &std::path::Path,
) -> Result<(), Failure> {
    let json = serde_json::to_vec_pretty(set).map_err(|e| Failure {
        code: 1,
        message: format!("encoding the probes: {e}"),
    })?;
    write_atomically(path, &json).map_err(|e| Failure {
        code: 1,
        message: format!("cannot write {}: {e}", path.display()),
    })?;
    let invalid = set.probes.iter().filter(|p| !p.valid).count();
    eprintln!(
        "baked {} probes ({invalid} inside geometry, not baked), error {} -> {}",
        set.probes.len(),
        set.error
            .map_or("n/a (one step)".into(), |e| format!("{:.2} %", 100.0 * e)),
        path.display()
    );
    Ok(())
}

#[derive(clap::Args)]
pub(crate) struct MergeArgs {
    /// The scene the tasks baked.
    #[arg(long)]
    scene: PathBuf,
    /// Every task's result (`bake --task K/N -o FILE`), in any order.
    #[arg(required = true)]
    parts: Vec<PathBuf>,
    /// Where to write the lightmap: a folder (`lightmap-P.exr` per page and
    /// `lightmaps.json`) or, for one page, a path ending in `.exr`.
    #[arg(short, long)]
    output: PathBuf,
    /// Also write a tone-mapped PNG preview of the lightmap here.
    #[arg(long)]
    preview: Option<PathBuf>,
}

/// `lightmapd merge`: every task's result into the job's lightmap, checked to be all
/// the tasks of one request on this scene (`engine::tasks::merge`).
pub(crate) fn merge(args: MergeArgs) -> Result<(), Failure> {
    let mut parts = Vec::with_capacity(args.parts.len());
    for p in &args.parts {
        let bytes = std::fs::read(p).map_err(|e| bad_input(format!("{}: {e}", p.display())))?;
        let what = p.display().to_string();
        parts.push(tasks::Partial::decode(&bytes, &what).map_err(|e| bad_input(e.to_string()))?);
    }
    let (scene, report) =
        scene::import_file(&args.scene).map_err(|e| bad_input(format!("{}: {e}", args.scene.display())))?;
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    let result =
        tasks::merge(Arc::new(scene), &parts, &job::BakeOptions::default(), &mut |_| {}).map_err(engine_failure)?;
    let written = write_lightmaps(&args.output, &result)?;
    if let Some(p) = &args.preview {
        write_atomically(p, &result.preview_png).map_err(|e| Failure {
            code: 1,
            message: format!("cannot write {}: {e}", p.display()),
        })?;
    }
    let s = &result.summary;
    let err = error_text(s.error.relative);
    eprintln!(
        "merged {} tasks of {} ({} texels) with {}: {} steps, {:.2} s of task time, estimated error {} -> {}",
        parts.len(),
        args.scene.display(),
        s.atlas.valid_texels,
        s.technique,
        s.steps,
        s.seconds,
        err,
        written
    );
    Ok(())
}
