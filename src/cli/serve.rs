//! `lightmapd serve` and `lightmapd worker`: the bake service's process (HTTP API and a
//! pool of workers) and a workers-only process, their options turned into the service's
//! limits and tunings, each checked with an error that names the option.

use std::path::PathBuf;
use std::time::Duration;

use lightmapd::service;
use lightmapd::service::store::StoreUrl;

use super::{Failure, bad_input, runtime};

#[derive(clap::Args)]
pub(crate) struct ServeArgs {
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
pub(crate) struct WorkerArgs {
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
pub(crate) fn database_url(flag: Option<String>) -> Result<Option<String>, Failure> {
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

fn snapshot_keep(t: &Tuning) -> Result<u32, Failure> {
    if t.snapshot_keep == 0 {
        return Err(bad_input("--snapshot-keep must be at least 1 (the latest snapshot)"));
    }
    Ok(t.snapshot_keep)
}

pub(crate) fn serve(args: ServeArgs) -> Result<(), Failure> {
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

pub(crate) fn worker(args: WorkerArgs) -> Result<(), Failure> {
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
