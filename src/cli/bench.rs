//! `lightmapd bench`: true error against bake time for the techniques on the benchmark
//! scenes (`lightmapd::bench` does the work; this is its options).

use std::path::PathBuf;

use super::{Failure, bad_input, engine_failure};

#[derive(clap::Args)]
pub(crate) struct BenchArgs {
    /// Scenes to run (comma separated; default: the seven small scenes; `real` adds every
    /// real-size scene: occlusion-room, living-room, kenney-fps-level, level-256k).
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// Techniques to compare (comma separated; default: all).
    #[arg(long, value_delimiter = ',')]
    techniques: Vec<String>,
    /// A run sized for CI: 1 s a scene and technique and 10-s references unless the two
    /// flags below say otherwise (about a minute and a half for the small scenes on two
    /// cores; the figures are coarse).
    #[arg(long)]
    quick: bool,
    /// Bake time per scene and technique [default: 20, or 1 with --quick]; with --steps,
    /// the most a scene and technique may take.
    #[arg(long)]
    budget_seconds: Option<f64>,
    /// A sweep by steps instead of by time: a snapshot at 4, 16, 64, … steps up to this
    /// many (powers of 4, at least 4), each scene and technique stopping there or at its
    /// budget, whichever comes first.
    #[arg(long)]
    steps: Option<u64>,
    /// Bake time of a path reference for scenes with no closed form (cached) [default: 90,
    /// or 10 with --quick].
    #[arg(long)]
    reference_seconds: Option<f64>,
    /// Where results.csv, summary.md and the plots go.
    #[arg(long, default_value = "bench-results")]
    out: PathBuf,
    /// Where converged references are cached.
    #[arg(long, default_value = "bench-results/cache")]
    cache: PathBuf,
    /// Leave out the light probes' measurements (three closed-form scenes, the budget each).
    #[arg(long)]
    no_probes: bool,
}

pub(crate) fn bench(args: BenchArgs) -> Result<(), Failure> {
    let budget_seconds = args.budget_seconds.unwrap_or(if args.quick { 1.0 } else { 20.0 });
    let reference_seconds = args.reference_seconds.unwrap_or(if args.quick { 10.0 } else { 90.0 });
    for (what, v) in [
        ("--budget-seconds", budget_seconds),
        ("--reference-seconds", reference_seconds),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(bad_input(format!("{what} must be a positive number, got {v}")));
        }
    }
    if let Some(n) = args.steps
        && n < 4
    {
        return Err(bad_input(format!(
            "--steps must be at least 4 (the first snapshot), got {n}"
        )));
    }
    let cfg = lightmapd::bench::BenchConfig {
        steps: args.steps,
        scenes: args.scenes,
        techniques: if args.techniques.is_empty() {
            lightmapd::engine::technique::TECHNIQUES
                .iter()
                .map(|t| t.to_string())
                .collect()
        } else {
            args.techniques
        },
        budget: std::time::Duration::from_secs_f64(budget_seconds),
        reference_budget: std::time::Duration::from_secs_f64(reference_seconds),
        out_dir: args.out.clone(),
        cache_dir: args.cache,
        probes: !args.no_probes,
    };
    let samples = lightmapd::bench::run(&cfg, &mut |line| eprintln!("bench: {line}")).map_err(engine_failure)?;
    eprintln!(
        "bench: {} measurements written to {}",
        samples.len(),
        args.out.display()
    );
    Ok(())
}
