//! `lightmapd submit`: the service's client on the command line. It uploads a scene,
//! submits a bake, prints the job's warnings and, when asked to wait, follows its progress
//! and downloads the lightmap (`service::client` does the HTTP).

use std::path::PathBuf;

use lightmapd::engine::scene::{Hemisphere, Lighting};
use lightmapd::service;

use super::{Failure, LightingArgs, bad_input, runtime};

#[derive(clap::Args)]
pub(crate) struct SubmitArgs {
    /// The scene: .glb, or .gltf with its buffers and images beside it.
    scene: PathBuf,
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    server: String,
    /// Follow the job with a progress bar until it ends.
    #[arg(long)]
    wait: bool,
    /// Download the final lightmap here (implies --wait): a folder gets every page and
    /// lightmaps.json, a path ending in .exr the one page of a one-page job.
    #[arg(short, long)]
    output: Option<PathBuf>,
    #[arg(long)]
    technique: Option<String>,
    #[arg(long)]
    resolution: Option<u32>,
    #[command(flatten)]
    lighting: LightingArgs,
    #[arg(long)]
    steps: Option<u64>,
    #[arg(long)]
    seconds: Option<f64>,
    #[arg(long)]
    target_error: Option<f32>,
    #[arg(long)]
    seed: Option<u64>,
    /// Extra layers: validity, direct, indirect, sh, ao, debug, shadowmask (comma separated).
    #[arg(long, value_delimiter = ',')]
    outputs: Vec<String>,
    /// The shadowmask's lights, one per channel: sun, a light's name or #index (comma
    /// separated; default: the sun and the scene's lights, at most four).
    #[arg(long, value_delimiter = ',')]
    shadowmask_lights: Vec<String>,
    /// Technique parameters as a JSON object.
    #[arg(long)]
    params: Option<String>,
    /// Denoiser: auto (OIDN when installed, else own), oidn, own, none (the job's `denoise`).
    #[arg(long)]
    denoiser: Option<String>,
    /// Lightmap UVs: keep (authored only), generate-missing (the server's default),
    /// regenerate-all, repack-instances (authored UVs of a mesh several nodes place get a
    /// rectangle per node).
    #[arg(long)]
    lightmap_uvs: Option<String>,
    /// Texel density of generated lightmap UVs (texels per metre).
    #[arg(long)]
    texels_per_unit: Option<f32>,
    /// At a --texels-per-unit, the widest a page grows before more pages are added.
    #[arg(long)]
    max_page_size: Option<u32>,
    /// A succeeded job of the same scene, grid and light to measure this job's error
    /// against (each history point's `true_error`).
    #[arg(long)]
    reference: Option<String>,
    /// Higher runs first.
    #[arg(long)]
    priority: Option<i32>,
    /// Split the job into this many tasks that several workers bake at once (the job's
    /// `tasks`; docs/scaling.md).
    #[arg(long)]
    tasks: Option<u32>,
    /// With --tasks or --rounds: cut the lightmap grid into this many regions (whole
    /// pages, or bands of rows; the job's `regions`).
    #[arg(long)]
    regions: Option<u32>,
    /// Bake the --regions in this many rounds, each region with the others' light held
    /// (`hemicube`, `sdb`; the job's `rounds`).
    #[arg(long)]
    rounds: Option<u32>,
    /// What a worker must have to take the job: gpu (a hardware adapter), oidn (comma
    /// separated; the job's `requires`).
    #[arg(long, value_delimiter = ',')]
    requires: Vec<String>,
    /// Bearer token for a server run with --auth (default: $LIGHTMAPD_TOKEN, which keeps
    /// it out of the process list).
    #[arg(long)]
    token: Option<String>,
    /// When the server is busy (429: too many of your jobs queued; 503), wait as its
    /// `Retry-After` says and try again, for at most this many seconds (0: fail at once).
    #[arg(long, default_value_t = 600.0)]
    retry_for: f64,
}

pub(crate) fn submit(args: SubmitArgs) -> Result<(), Failure> {
    let mut job = serde_json::Map::new();
    if let Some(t) = args.technique {
        job.insert("technique".into(), t.into());
    }
    if let Some(r) = args.resolution {
        job.insert("resolution".into(), r.into());
    }
    let mut lighting = serde_json::Map::new();
    let Lighting { sky, sun } = args.lighting.lighting();
    if let Some(sky) = sky {
        let hemisphere = match sky.hemisphere {
            Hemisphere::Upper => "upper",
            Hemisphere::Full => "full",
        };
        lighting.insert(
            "sky".into(),
            serde_json::json!({"radiance": sky.radiance.to_array(), "hemisphere": hemisphere}),
        );
    }
    if let Some(sun) = sun {
        lighting.insert(
            "sun".into(),
            serde_json::json!({
                "direction": sun.direction.to_array(),
                "angular_diameter_deg": sun.angular_diameter.to_degrees(),
                "radiance": sun.radiance.to_array(),
            }),
        );
    }
    if !lighting.is_empty() {
        job.insert("lighting".into(), lighting.into());
    }
    if args.steps.is_some() || args.seconds.is_some() || args.target_error.is_some() {
        let mut stop = serde_json::Map::new();
        if let Some(v) = args.steps {
            stop.insert("steps".into(), v.into());
        }
        if let Some(v) = args.seconds {
            stop.insert("seconds".into(), v.into());
        }
        if let Some(v) = args.target_error {
            stop.insert("target_error".into(), v.into());
        }
        job.insert("stop".into(), stop.into());
    }
    if let Some(p) = &args.params {
        let v: serde_json::Value =
            serde_json::from_str(p).map_err(|e| bad_input(format!("--params is not JSON: {e}")))?;
        job.insert("params".into(), v);
    }
    if !args.outputs.is_empty() {
        job.insert("outputs".into(), args.outputs.clone().into());
    }
    if !args.shadowmask_lights.is_empty() {
        job.insert("shadowmask_lights".into(), args.shadowmask_lights.clone().into());
    }
    // Checked by the server (422 naming the field), like every other job field.
    if let Some(d) = &args.denoiser {
        job.insert("denoise".into(), d.clone().into());
    }
    if let Some(m) = &args.lightmap_uvs {
        job.insert("lightmap_uvs".into(), m.clone().into());
    }
    if let Some(t) = args.texels_per_unit {
        job.insert("texels_per_unit".into(), t.into());
    }
    if let Some(m) = args.max_page_size {
        job.insert("max_page_size".into(), m.into());
    }
    if let Some(r) = &args.reference {
        job.insert("reference".into(), r.clone().into());
    }
    if let Some(v) = args.seed {
        job.insert("seed".into(), v.into());
    }
    if let Some(v) = args.priority {
        job.insert("priority".into(), v.into());
    }
    for (field, v) in [
        ("tasks", args.tasks),
        ("regions", args.regions),
        ("rounds", args.rounds),
    ] {
        if let Some(v) = v {
            job.insert(field.into(), v.into());
        }
    }
    if !args.requires.is_empty() {
        let mut requires = serde_json::Map::new();
        for r in &args.requires {
            match r.as_str() {
                "gpu" | "oidn" => requires.insert(r.clone(), true.into()),
                other => {
                    return Err(bad_input(format!(
                        "--requires: unknown capability {other:?}; one of gpu, oidn"
                    )));
                }
            };
        }
        job.insert("requires".into(), requires.into());
    }
    let request = service::client::Submit {
        server: args.server,
        scene: args.scene,
        job: job.into(),
        wait: args.wait,
        output: args.output,
        token: args
            .token
            .or_else(|| std::env::var("LIGHTMAPD_TOKEN").ok().filter(|t| !t.is_empty())),
        retry_for: std::time::Duration::try_from_secs_f64(args.retry_for).map_err(|_| Failure {
            code: 2,
            message: format!(
                "--retry-for must be a non-negative number of seconds, not {}",
                args.retry_for
            ),
        })?,
    };
    let job = runtime()?
        .block_on(service::client::submit(request))
        .map_err(|e| Failure {
            code: e.code,
            message: e.message,
        })?;
    // The job document on stdout, for scripts.
    println!("{}", serde_json::to_string(&job).unwrap_or_default());
    Ok(())
}
