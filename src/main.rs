//! `lightmapd`: the command line (DESIGN §9). `bake` runs the engine on one scene with no
//! server; `example` writes the bundled example scenes; `serve` runs the bake service (API
//! and workers), `worker` runs workers only, `submit` sends a scene to a server, `token`
//! manages the bearer tokens of a server run with `--auth`. Exit
//! codes: 0 success, 2 bad input (unreadable scene, bad option, a 4xx answer), 1 anything
//! else.

mod log_format;

use std::io::IsTerminal;
use std::ops::ControlFlow;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use clap::{Parser, Subcommand, ValueEnum};
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use lightmapd::engine::bake::{BakeEvent, StopCriteria};
use lightmapd::engine::job::{self, BakeRequest};
use lightmapd::engine::output::{OutputLayer, write_atomically};
use lightmapd::engine::scene::{self, Hemisphere, Lighting, Sky, Sun};
use lightmapd::engine::tasks;
use lightmapd::engine::technique::obscurance::{ObscuranceState, UpdateReach};
use lightmapd::service;
use lightmapd::service::store::StoreUrl;

#[derive(Parser)]
#[command(name = "lightmapd", version, about = "Bakes lightmaps from glTF scenes")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Bake a lightmap from a .glb or .gltf scene into an EXR file.
    Bake(Box<BakeArgs>),
    /// Measure true error against run time for techniques on the benchmark scenes.
    Bench(BenchArgs),
    /// Write a bundled example scene as .glb.
    Example {
        #[arg(value_enum, default_value = "cornell-box")]
        name: Example,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Run the bake service: HTTP API and a pool of workers, SQLite and a local folder or S3.
    Serve(ServeArgs),
    /// Run workers only, against the database and store of a `serve`.
    Worker(WorkerArgs),
    /// Upload a scene to a server, submit a bake, optionally wait and download the EXR.
    Submit(Box<SubmitArgs>),
    /// Create, list or revoke the bearer tokens of a server run with `--auth`.
    Token(TokenArgs),
    /// Merge the task results of a bake split with `bake --task K/N` into its lightmap.
    Merge(MergeArgs),
}

#[derive(clap::Args)]
struct MergeArgs {
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

#[derive(clap::Args)]
struct TokenArgs {
    #[command(subcommand)]
    action: TokenAction,
    /// The server's data folder (its database is DATA_DIR/lightmapd.db).
    #[arg(long, default_value = "lightmapd-data", global = true)]
    data_dir: PathBuf,
    /// postgres://… or sqlite://FILE, when the server was given --database-url (default:
    /// $LIGHTMAPD_DATABASE_URL, or the contents of $LIGHTMAPD_DATABASE_URL_FILE).
    #[arg(long, global = true)]
    database_url: Option<String>,
}

#[derive(Subcommand)]
enum TokenAction {
    /// Make a token; its secret is printed once, on stdout.
    Create {
        /// A name for people (who or what uses it); unique among live tokens.
        #[arg(long)]
        name: String,
        /// editor: its own scenes and jobs, priority up to --max-priority; admin: every
        /// client's jobs, any priority.
        #[arg(long, value_enum, default_value = "editor")]
        role: RoleArg,
    },
    /// Every token: id, name, role, created, active/revoked, source.
    List,
    /// Revoke a token by id, or by name when one live token has it.
    Revoke { token: String },
    /// Print a fresh random secret for a --tokens-file line (touches no database).
    Secret,
}

#[derive(Clone, Copy, ValueEnum)]
enum RoleArg {
    Editor,
    Admin,
}

#[derive(clap::Args)]
struct ServeArgs {
    #[arg(long, default_value = "127.0.0.1:8080")]
    listen: std::net::SocketAddr,
    /// Holds the SQLite database and the artifact folder.
    #[arg(long, default_value = "lightmapd-data")]
    data_dir: PathBuf,
    /// Bakes run at once in this process (0: API only).
    #[arg(long, default_value_t = 1)]
    workers: usize,
    /// postgres://USER:PASSWORD@HOST/DB or sqlite://FILE (default: DATA_DIR/lightmapd.db).
    #[arg(long)]
    database_url: Option<String>,
    /// Artifact store: s3://BUCKET/PREFIX (endpoint, region and keys from AWS_* variables),
    /// file://DIR or a directory (default: DATA_DIR/objects).
    #[arg(long, value_parser = StoreUrl::parse)]
    store: Option<StoreUrl>,
    /// Require a bearer token (`lightmapd token create`) on every route but /healthz.
    #[arg(long)]
    auth: bool,
    /// Serve a non-loopback address without --auth (a network you trust); refused otherwise.
    #[arg(long)]
    insecure_no_auth: bool,
    /// `NAME ROLE SECRET` lines (a mounted secret), applied at start-up: new lines become
    /// tokens, removed lines' tokens are revoked (default: $LIGHTMAPD_TOKENS_FILE).
    #[arg(long)]
    tokens_file: Option<PathBuf>,
    /// Finished jobs and their artifacts are removed this many hours after they end (0:
    /// kept until deleted).
    #[arg(long, default_value_t = 168.0)]
    job_retention_hours: f64,
    #[command(flatten)]
    tuning: Tuning,
}

#[derive(clap::Args)]
struct WorkerArgs {
    /// The database of the `serve` this worker helps: postgres://USER:PASSWORD@HOST/DB
    /// (workers on other machines) or sqlite://FILE (the same machine); default
    /// $LIGHTMAPD_DATABASE_URL or the contents of $LIGHTMAPD_DATABASE_URL_FILE.
    #[arg(long)]
    database_url: Option<String>,
    /// The artifact store of that `serve`: s3://BUCKET/PREFIX, file://DIR or a directory.
    #[arg(long, value_parser = StoreUrl::parse)]
    store: StoreUrl,
    #[arg(long, default_value_t = 1)]
    workers: usize,
    /// Exit with code 1 after this many seconds without reaching the database (the
    /// supervisor restarts the worker).
    #[arg(long, default_value_t = 60.0)]
    database_timeout_s: f64,
    #[command(flatten)]
    tuning: Tuning,
}

#[derive(clap::Args)]
struct Tuning {
    /// Largest scene upload in bytes (413 beyond).
    #[arg(long, default_value_t = 256 << 20)]
    max_scene_bytes: usize,
    /// Largest other request body (a job) in bytes (413 beyond).
    #[arg(long, default_value_t = 1 << 20)]
    max_body_bytes: usize,
    /// Most triangles in a scene, instances counted once each (422 beyond).
    #[arg(long, default_value_t = 5_000_000)]
    max_triangles: usize,
    /// Largest texture width or height in pixels (422 beyond).
    #[arg(long, default_value_t = 8192)]
    max_texture_size: u32,
    /// Largest lightmap side in texels (422 beyond).
    #[arg(long, default_value_t = 4096)]
    max_resolution: u32,
    /// Longest bake; a job without stop.seconds gets this (422 beyond).
    #[arg(long, default_value_t = 3600.0)]
    max_job_seconds: f64,
    /// Most steps of a bake (422 beyond).
    #[arg(long, default_value_t = 1 << 20)]
    max_job_steps: u64,
    /// Queued jobs one client (token, or IP address without --auth) may have (429 beyond).
    #[arg(long, default_value_t = 100)]
    max_queued_per_client: u64,
    /// Event streams open at once (503 beyond).
    #[arg(long, default_value_t = 256)]
    max_event_streams: usize,
    /// A job's estimated peak memory in MiB; a bigger job is refused at submission, and
    /// not taken by a worker whose own limit is lower (it waits for one that covers it).
    #[arg(long, default_value_t = 8192)]
    max_job_memory_mb: u64,
    /// Time to answer a request, in seconds (an event stream's body is not limited; a
    /// scene upload has --upload-idle-timeout-s instead).
    #[arg(long, default_value_t = 60.0)]
    request_timeout_s: f64,
    /// Longest wait in seconds for the next chunk of a scene upload (408 beyond): uploads
    /// have no total time, so a large scene on a slow link succeeds.
    #[arg(long, default_value_t = 30.0)]
    upload_idle_timeout_s: f64,
    /// Large bodies in flight at once: uploads above 16 MiB or of unknown length, and
    /// downloads above 16 MiB (503 with Retry-After beyond).
    #[arg(long, default_value_t = 8)]
    max_large_bodies: usize,
    /// Scene imports at once (each holds its scene in memory); more wait their turn.
    #[arg(long, default_value_t = 2)]
    max_concurrent_imports: usize,
    /// A worker's claim on a job lasts this long without renewal; a job whose worker
    /// died is taken up again after it (within it plus 1 s).
    #[arg(long, default_value_t = 5.0)]
    lease_seconds: f64,
    /// Longest time between stored snapshot EXRs of a running bake.
    #[arg(long, default_value_t = 2.0)]
    snapshot_interval_s: f64,
    /// Snapshots kept per job: the latest and an evenly thinned history (at least 1).
    #[arg(long, default_value_t = 8)]
    snapshot_keep: u32,
    /// Highest priority an editor token (or any caller without --auth) may give a job;
    /// admin tokens may set any (403 beyond).
    #[arg(long, default_value_t = 10)]
    max_priority: i32,
}

#[derive(clap::Args)]
struct SubmitArgs {
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
    /// Uniform sky radiance R,G,B.
    #[arg(long, value_parser = parse_vec3)]
    sky: Option<Vec3>,
    #[arg(long, value_enum, default_value = "upper")]
    sky_hemisphere: HemisphereArg,
    /// Sun: DX,DY,DZ (from the sun toward the scene),DIAMETER_DEG,R,G,B (radiance, per steradian: a 0.53° disc is 6.7e-5 sr, so an irradiance E needs a radiance of E / 6.7e-5).
    #[arg(long, value_parser = parse_sun)]
    sun: Option<Sun>,
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

#[derive(clap::Args)]
struct BenchArgs {
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

#[derive(Clone, Copy, ValueEnum)]
enum Example {
    CornellBox,
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

#[derive(Clone, Copy, ValueEnum)]
enum HemisphereArg {
    Upper,
    Full,
}

#[derive(clap::Args)]
struct BakeArgs {
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
    /// Uniform sky radiance R,G,B.
    #[arg(long, value_parser = parse_vec3)]
    sky: Option<Vec3>,
    #[arg(long, value_enum, default_value = "upper")]
    sky_hemisphere: HemisphereArg,
    /// Sun: DX,DY,DZ (from the sun toward the scene),DIAMETER_DEG,R,G,B (radiance, per steradian: a 0.53° disc is 6.7e-5 sr, so an irradiance E needs a radiance of E / 6.7e-5).
    #[arg(long, value_parser = parse_sun)]
    sun: Option<Sun>,
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

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum ReachArg {
    All,
    Dmax,
}

fn parse_floats(s: &str, n: usize, what: &str) -> Result<Vec<f32>, String> {
    let v: Result<Vec<f32>, _> = s.split(',').map(|x| x.trim().parse::<f32>()).collect();
    match v {
        Ok(v) if v.len() == n && v.iter().all(|x| x.is_finite()) => Ok(v),
        _ => Err(format!(
            "expected {what} as {n} comma-separated finite numbers, got {s:?}"
        )),
    }
}

fn parse_vec3(s: &str) -> Result<Vec3, String> {
    parse_floats(s, 3, "R,G,B").map(|v| Vec3::new(v[0], v[1], v[2]))
}

fn parse_sun(s: &str) -> Result<Sun, String> {
    let v = parse_floats(s, 7, "DX,DY,DZ,DIAMETER_DEG,R,G,B")?;
    let direction = Vec3::new(v[0], v[1], v[2]);
    if direction.length() < 1e-6 {
        return Err("sun direction must not be zero".into());
    }
    Ok(Sun {
        direction: direction.normalize(),
        angular_diameter: v[3].to_radians(),
        radiance: Vec3::new(v[4], v[5], v[6]),
    })
}

/// A failure and the exit code it earns.
struct Failure {
    code: u8,
    message: String,
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

/// On a machine without a display session (no `XDG_RUNTIME_DIR`: a server, a container, CI)
/// Mesa's Vulkan device-select layer prints "error: XDG_RUNTIME_DIR is invalid or not set
/// in the environment" up to four times a bake while it looks for a display to order the
/// GPUs by; nothing is wrong, but it reads as a failure. lightmapd picks its adapter itself
/// (`LIGHTMAPD_ADAPTER`, `engine::gpu`), so there the layer is switched off
/// (`NODEVICE_SELECT=1`, Mesa's own switch) unless the user has set it or chosen a device
/// through it (`MESA_VK_DEVICE_SELECT`). Called first thing in `main`, before any thread
/// exists.
fn quiet_device_select() {
    // Empty counts as unset, as it does for Mesa.
    let unset = |name: &str| std::env::var_os(name).is_none_or(|v| v.is_empty());
    if unset("XDG_RUNTIME_DIR") && unset("NODEVICE_SELECT") && unset("MESA_VK_DEVICE_SELECT") {
        // SAFETY: no other thread exists yet (this runs first in `main`), so nothing reads
        // the environment while it is written.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

/// An engine error as the process's failure: exit code 2 for bad input, else 1.
fn engine_failure(e: lightmapd::engine::technique::EngineError) -> Failure {
    Failure {
        code: if e.is_bad_input() { 2 } else { 1 },
        message: e.to_string(),
    }
}

/// A relative error estimate as printed: "1.23%", or "n/a" without one.
fn error_text(relative: Option<f32>) -> String {
    relative.map_or_else(|| "n/a".into(), |e| format!("{:.2}%", e * 100.0))
}

fn bad_input(message: impl Into<String>) -> Failure {
    Failure {
        code: 2,
        message: message.into(),
    }
}

fn main() -> ExitCode {
    quiet_device_select();
    lightmapd::service::install_crypto_provider();
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if e.use_stderr() => {
            // Bad options get one line, like every other bad input; clap's usage hints
            // and the "--help" tip are left out.
            let text = e.to_string();
            let line: Vec<&str> = text
                .lines()
                .map(str::trim)
                .take_while(|l| !l.starts_with("Usage:") && !l.starts_with("For more information"))
                .filter(|l| !l.is_empty())
                .collect();
            eprintln!("{}", line.join(" "));
            return ExitCode::from(2);
        }
        Err(e) => e.exit(), // --help and --version
    };
    // The service logs what it does by default; the one-shot commands only warn.
    let default_filter = match cli.command {
        Command::Serve(_) | Command::Worker(_) => "info",
        _ => "warn",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| default_filter.into());
    // Colour codes only for a person; log files and journald get plain text.
    let ansi = std::io::stderr().is_terminal();
    let logs = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(|| log_format::Stderr)
        .with_ansi(ansi);
    if matches!(cli.command, Command::Serve(_) | Command::Worker(_)) {
        logs.init();
    } else {
        logs.event_format(log_format::CommandLine::new(ansi)).init();
    }
    let result = match cli.command {
        Command::Serve(args) => serve(args),
        Command::Worker(args) => worker(args),
        Command::Submit(args) => submit(*args),
        Command::Token(args) => token(args),
        Command::Bake(args) => bake(*args),
        Command::Merge(args) => merge(args),
        Command::Bench(args) => bench(args),
        Command::Example {
            name: Example::CornellBox,
            output,
        } => write_atomically(&output, &scene::build::cornell_box().to_glb()).map_err(|e| Failure {
            code: 1,
            message: format!("cannot write {}: {e}", output.display()),
        }),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(f) => {
            eprintln!("error: {}", f.message);
            ExitCode::from(f.code)
        }
    }
}

fn runtime() -> Result<tokio::runtime::Runtime, Failure> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| Failure {
            code: 1,
            message: format!("cannot start the async runtime: {e}"),
        })
}

fn limits(t: &Tuning) -> Result<service::Limits, Failure> {
    if !(t.max_job_seconds.is_finite() && t.max_job_seconds > 0.0) {
        return Err(bad_input(format!(
            "--max-job-seconds must be a positive number, got {}",
            t.max_job_seconds
        )));
    }
    if !(t.request_timeout_s.is_finite() && t.request_timeout_s > 0.0) {
        return Err(bad_input(format!(
            "--request-timeout-s must be a positive number, got {}",
            t.request_timeout_s
        )));
    }
    if !(t.upload_idle_timeout_s.is_finite() && t.upload_idle_timeout_s > 0.0) {
        return Err(bad_input(format!(
            "--upload-idle-timeout-s must be a positive number, got {}",
            t.upload_idle_timeout_s
        )));
    }
    if t.max_large_bodies == 0 || t.max_concurrent_imports == 0 {
        return Err(bad_input(
            "--max-large-bodies and --max-concurrent-imports must be at least 1".to_string(),
        ));
    }
    Ok(service::Limits {
        max_scene_bytes: t.max_scene_bytes,
        max_body_bytes: t.max_body_bytes,
        max_triangles: t.max_triangles,
        max_texture_side: t.max_texture_size,
        max_resolution: t.max_resolution,
        max_job_seconds: t.max_job_seconds,
        max_job_steps: t.max_job_steps,
        max_queued_per_client: t.max_queued_per_client,
        max_event_streams: t.max_event_streams,
        max_job_memory_bytes: t.max_job_memory_mb.saturating_mul(1 << 20),
        request_timeout: Duration::from_secs_f64(t.request_timeout_s),
        upload_idle_timeout: Duration::from_secs_f64(t.upload_idle_timeout_s),
        max_large_bodies: t.max_large_bodies,
        large_body_bytes: service::LARGE_BODY_BYTES,
        max_concurrent_imports: t.max_concurrent_imports,
        max_priority: t.max_priority,
    })
}

/// `--database-url`, else `$LIGHTMAPD_DATABASE_URL`, else the contents of the file
/// `$LIGHTMAPD_DATABASE_URL_FILE` names (a mounted secret), so the password need not be
/// in argv.
fn database_url(flag: Option<String>) -> Result<Option<String>, Failure> {
    if flag.is_some() {
        return Ok(flag);
    }
    if let Ok(url) = std::env::var("LIGHTMAPD_DATABASE_URL")
        && !url.trim().is_empty()
    {
        return Ok(Some(url.trim().to_string()));
    }
    match std::env::var_os("LIGHTMAPD_DATABASE_URL_FILE") {
        Some(path) if !path.is_empty() => {
            let text = std::fs::read_to_string(&path).map_err(|e| {
                bad_input(format!(
                    "LIGHTMAPD_DATABASE_URL_FILE={}: cannot read it: {e}",
                    std::path::Path::new(&path).display()
                ))
            })?;
            let url = text.trim();
            if url.is_empty() {
                return Err(bad_input(format!(
                    "LIGHTMAPD_DATABASE_URL_FILE={} is empty",
                    std::path::Path::new(&path).display()
                )));
            }
            Ok(Some(url.to_string()))
        }
        _ => Ok(None),
    }
}

/// Reads and checks a tokens file (`--tokens-file`, else `$LIGHTMAPD_TOKENS_FILE`).
fn tokens_file(flag: Option<PathBuf>) -> Result<Option<Vec<service::auth::FileToken>>, Failure> {
    let path = flag.or_else(|| {
        std::env::var_os("LIGHTMAPD_TOKENS_FILE")
            .filter(|p| !p.is_empty())
            .map(PathBuf::from)
    });
    let Some(path) = path else { return Ok(None) };
    let text = std::fs::read_to_string(&path)
        .map_err(|e| bad_input(format!("tokens file {}: cannot read it: {e}", path.display())))?;
    let tokens = service::auth::parse_tokens_file(&text)
        .map_err(|e| bad_input(format!("tokens file {}: {e}", path.display())))?;
    Ok(Some(tokens))
}

fn tuning(t: &Tuning) -> Result<(Duration, Duration), Failure> {
    let positive = |v: f64, name: &str| {
        if v.is_finite() && v > 0.0 {
            Ok(Duration::from_secs_f64(v))
        } else {
            Err(bad_input(format!(
                "--{name} must be a positive number of seconds, got {v}"
            )))
        }
    };
    Ok((
        positive(t.lease_seconds, "lease-seconds")?,
        positive(t.snapshot_interval_s, "snapshot-interval-s")?,
    ))
}

fn serve(args: ServeArgs) -> Result<(), Failure> {
    let (lease, snapshot_interval) = tuning(&args.tuning)?;
    service::check_exposure(args.listen, args.auth, args.insecure_no_auth).map_err(bad_input)?;
    if args.insecure_no_auth && !args.listen.ip().is_loopback() && !args.auth {
        tracing::warn!(listen = %args.listen, "serving without authentication (--insecure-no-auth): every caller owns every job");
    }
    let tokens = tokens_file(args.tokens_file)?;
    if tokens.is_some() && !args.auth {
        return Err(bad_input(
            "--tokens-file needs --auth (without it tokens are not checked)",
        ));
    }
    if !(args.job_retention_hours.is_finite() && args.job_retention_hours >= 0.0) {
        return Err(bad_input(format!(
            "--job-retention-hours must be a number >= 0, got {}",
            args.job_retention_hours
        )));
    }
    let config = service::Config {
        listen: args.listen,
        data_dir: args.data_dir,
        workers: args.workers,
        database_url: database_url(args.database_url)?,
        store: args.store,
        limits: limits(&args.tuning)?,
        auth: args.auth,
        lease,
        snapshot_interval,
        snapshot_keep: snapshot_keep(&args.tuning)?,
        job_retention: (args.job_retention_hours > 0.0)
            .then(|| Duration::from_secs_f64(args.job_retention_hours * 3600.0)),
        tokens_file: tokens,
        ..service::Config::default()
    };
    runtime()?.block_on(async move {
        let running = service::start(config).await.map_err(|e| Failure {
            code: 1,
            message: format!("cannot start the service: {e:#}"),
        })?;
        // Tests and scripts read the address from this line (`--listen 127.0.0.1:0`).
        println!("lightmapd listening on http://{}", running.addr);
        use std::io::Write;
        let _ = std::io::stdout().flush();
        service::termination().await;
        tracing::info!("shutting down: running jobs go back to the queue");
        running.shutdown().await;
        Ok(())
    })
}

fn snapshot_keep(t: &Tuning) -> Result<u32, Failure> {
    if t.snapshot_keep == 0 {
        return Err(bad_input("--snapshot-keep must be at least 1 (the latest snapshot)"));
    }
    Ok(t.snapshot_keep)
}

fn worker(args: WorkerArgs) -> Result<(), Failure> {
    let (lease, snapshot_interval) = tuning(&args.tuning)?;
    let Some(url) = database_url(args.database_url)? else {
        return Err(bad_input(
            "worker needs its database: --database-url, LIGHTMAPD_DATABASE_URL or LIGHTMAPD_DATABASE_URL_FILE",
        ));
    };
    if !service::queue::supported_url(&url) {
        return Err(bad_input(service::queue::unsupported_url(&url)));
    }
    if !(args.database_timeout_s.is_finite() && args.database_timeout_s > 0.0) {
        return Err(bad_input(format!(
            "--database-timeout-s must be a positive number of seconds, got {}",
            args.database_timeout_s
        )));
    }
    let config = service::Config {
        workers: args.workers,
        database_url: Some(url),
        store: Some(args.store),
        limits: limits(&args.tuning)?,
        lease,
        snapshot_interval,
        snapshot_keep: snapshot_keep(&args.tuning)?,
        database_timeout: Duration::from_secs_f64(args.database_timeout_s),
        ..service::Config::default()
    };
    runtime()?
        .block_on(service::run_workers(config, service::termination()))
        .map_err(|e| Failure {
            code: 1,
            message: format!("worker: {e:#}"),
        })
}

fn submit(args: SubmitArgs) -> Result<(), Failure> {
    let mut job = serde_json::Map::new();
    if let Some(t) = args.technique {
        job.insert("technique".into(), t.into());
    }
    if let Some(r) = args.resolution {
        job.insert("resolution".into(), r.into());
    }
    let mut lighting = serde_json::Map::new();
    if let Some(sky) = args.sky {
        let hemisphere = match args.sky_hemisphere {
            HemisphereArg::Upper => "upper",
            HemisphereArg::Full => "full",
        };
        lighting.insert(
            "sky".into(),
            serde_json::json!({"radiance": sky.to_array(), "hemisphere": hemisphere}),
        );
    }
    if let Some(sun) = args.sun {
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

fn token(args: TokenArgs) -> Result<(), Failure> {
    if let TokenAction::Secret = args.action {
        println!("{}", service::auth::new_secret());
        return Ok(());
    }
    let config = service::Config {
        data_dir: args.data_dir,
        database_url: database_url(args.database_url)?,
        ..service::Config::default()
    };
    let fail = |e: &dyn std::fmt::Display| Failure {
        code: 1,
        message: format!("token: {e}"),
    };
    runtime()?.block_on(async move {
        let (queue, _) = service::open_backends(&config).await.map_err(|e| fail(&e))?;
        match args.action {
            TokenAction::Create { name, role } => {
                if name.trim().is_empty() || name.chars().any(char::is_whitespace) {
                    return Err(bad_input("--name must be one word (no spaces)"));
                }
                let role = match role {
                    RoleArg::Editor => service::queue::Role::Editor,
                    RoleArg::Admin => service::queue::Role::Admin,
                };
                let (record, secret) = service::auth::create_token(&*queue, &name, role)
                    .await
                    .map_err(|e| token_failure(&e))?;
                eprintln!(
                    "token {} ({name}, {}) created; its secret is shown only now:",
                    record.id,
                    role.as_str()
                );
                println!("{secret}");
            }
            TokenAction::List => {
                for t in queue.tokens().await.map_err(|e| fail(&e))? {
                    let revoked = t
                        .revoked_at
                        .map(|ms| format!("revoked {}", service::model::rfc3339(ms)))
                        .unwrap_or_else(|| "active".into());
                    println!(
                        "{}\t{}\t{}\tcreated {}\t{revoked}\t{}",
                        t.id,
                        t.name,
                        t.role.as_str(),
                        service::model::rfc3339(t.created_at),
                        t.source
                    );
                }
            }
            TokenAction::Revoke { token } => {
                let t = service::auth::resolve_token(&*queue, &token)
                    .await
                    .map_err(|e| token_failure(&e))?;
                if !queue
                    .revoke_token(&t.id, service::queue::now_ms())
                    .await
                    .map_err(|e| fail(&e))?
                {
                    return Err(bad_input(format!("no active token with id or name {token:?}")));
                }
                eprintln!("token {} ({}) revoked", t.id, t.name);
            }
            TokenAction::Secret => {}
        }
        Ok(())
    })
}

fn token_failure(e: &service::auth::TokenError) -> Failure {
    match e {
        service::auth::TokenError::Invalid(m) => bad_input(m.clone()),
        service::auth::TokenError::Database(e) => Failure {
            code: 1,
            message: format!("token: {e}"),
        },
    }
}

fn bake(args: BakeArgs) -> Result<(), Failure> {
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
    let request = BakeRequest {
        technique: args.technique.clone(),
        resolution: args.resolution,
        lighting: Lighting {
            sky: args.sky.map(|radiance| Sky {
                radiance,
                hemisphere: match args.sky_hemisphere {
                    HemisphereArg::Upper => Hemisphere::Upper,
                    HemisphereArg::Full => Hemisphere::Full,
                },
            }),
            sun: args.sun,
        },
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
    };

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
    if let Some(n) = stop.steps {
        bar.set_length(n);
    }
    // The bar's clock and spinner move on their own, so a long step (a large level's pass
    // over every texel) never looks like a hang.
    bar.enable_steady_tick(std::time::Duration::from_millis(250));
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
    let s = &result.summary;
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
        args.scene.display(),
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
    Ok(())
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

/// `lightmapd merge`: every task's result into the job's lightmap, checked to be all
/// the tasks of one request on this scene (`engine::tasks::merge`).
fn merge(args: MergeArgs) -> Result<(), Failure> {
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

fn bench(args: BenchArgs) -> Result<(), Failure> {
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
