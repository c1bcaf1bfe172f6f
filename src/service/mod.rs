//! The bake service (DESIGN §7, §8): an HTTP API over a durable job queue, an artifact
//! store, and a pool of workers that run `engine::job::bake`.
//!
//! Shape: [`routes`] parse and validate, then call the [`queue`] or the [`store`]; a
//! [`worker`] claims a job, runs the bake on a blocking thread, and reports progress and
//! snapshots back through the queue and the store; [`events`] turns a job's row into
//! server-sent events. Nothing here knows how a lightmap is computed, and the engine knows
//! nothing of this module.
//!
//! Processes: `lightmapd serve` runs the API and N workers in one process ([`start`]);
//! `lightmapd worker` runs workers only ([`run_workers`]), sharing the database and the
//! store with a `serve`. In-process notifications (a new job, a cancel, a change to a
//! job) make one process react at once; across processes PostgreSQL's LISTEN/NOTIFY
//! feeds the same [`Hub`] signals ([`queue::Queue::listen`]), and with SQLite the same
//! things are found by polling the database, a little later.
//!
//! Hostile clients (issue 12): every size and budget a request can ask for is capped by
//! [`Limits`] (413 for bodies, 422 naming the field, 429 with `Retry-After` for a full
//! per-client queue, 503 for too many event streams); [`auth`] adds optional bearer
//! tokens; every request has a time limit (a scene upload, an idle limit per chunk: [`upload`]); artifacts are written to a temporary file,
//! synced, then renamed, before the job that made them is marked succeeded.
//!
//! Deployed (issue 24): [`check_exposure`] refuses to serve a non-loopback address
//! without tokens unless told the network is trusted; tokens may come from a secret file
//! ([`auth::sync_tokens_file`]); snapshot retention ([`store::snapshot_kept`]) and the
//! retention sweeper ([`retention_loop`]) bound the store; leases are short (5 s by
//! default, renewed until the job's end is recorded) and measured on the database's clock
//! ([`queue::Queue::clock`]). Uploads are spooled to disk ([`upload`]), imports run at
//! most `--max-concurrent-imports` at once, and large bodies in flight are capped
//! (`--max-large-bodies`, 503 beyond).
//!
//! Limits: API and worker processes on several machines need PostgreSQL and an artifact
//! store they all reach (an S3 bucket, [`store`], or a shared filesystem).

pub mod auth;
pub mod client;
pub mod console;
pub mod events;
pub mod farm;
pub mod metrics;
pub mod model;
pub mod problem;
pub mod queue;
pub mod routes;
pub mod store;
pub mod upload;
pub mod worker;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicI64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::{Notify, broadcast, watch};
use tokio::task::JoinHandle;

use crate::service::metrics::Metrics;
use crate::service::queue::Queue;
use crate::service::store::{Artifacts, StoreUrl};

/// Everything `serve` and `worker` are configured with.
#[derive(Clone, Debug)]
pub struct Config {
    pub listen: SocketAddr,
    /// Holds `lightmapd.db` and `objects/` unless `database_url` / `store` say otherwise.
    pub data_dir: PathBuf,
    pub workers: usize,
    /// `sqlite://FILE` or `postgres://USER:PASSWORD@HOST/DB` ([`queue::open`]).
    pub database_url: Option<String>,
    /// Where artifacts go: a directory or an S3 bucket (default: `data_dir/objects`).
    pub store: Option<StoreUrl>,
    /// What one client may ask of the server.
    pub limits: Limits,
    /// Require a bearer token on every route but `/healthz` (`lightmapd token create`).
    pub auth: bool,
    /// How long a worker's claim on a job lasts without renewal.
    pub lease: Duration,
    /// Longest time between stored snapshot EXRs of a running bake.
    pub snapshot_interval: Duration,
    /// Snapshot EXR+PNG pairs kept per job: the latest and a thinned history
    /// ([`store::snapshot_kept`]).
    pub snapshot_keep: u32,
    /// Finished jobs (and their artifacts) older than this are removed by the sweeper;
    /// `None` keeps them until deleted.
    pub job_retention: Option<Duration>,
    /// How often the sweeper runs and the store's usage is measured.
    pub sweep_interval: Duration,
    /// Tokens from a secret file (`--tokens-file`), synced into the database at start-up;
    /// `None`: no file.
    pub tokens_file: Option<Vec<auth::FileToken>>,
    /// A worker process exits (code 1) after this long without reaching its database.
    pub database_timeout: Duration,
}

/// Default lease: short, so a dead worker's job is queued again within
/// [`DEFAULT_LEASE`] plus one recovery period (at most 1 s) of its last renewal.
pub const DEFAULT_LEASE: Duration = Duration::from_secs(5);
/// Default retention of finished jobs: 7 days.
pub const DEFAULT_JOB_RETENTION: Duration = Duration::from_secs(7 * 24 * 3600);

/// Refuses to serve `listen` without tokens when it is not a loopback address, unless
/// `insecure` says the network is trusted: without tokens every caller may list,
/// download, cancel and delete every job.
/// Installs aws-lc-rs as rustls' process-wide crypto provider, once (later calls do
/// nothing). Why: the service's dependencies compile rustls with two providers (ring for
/// sqlx, aws-lc-rs for reqwest and object_store), and rustls then has no default, so the
/// certificate verifier sqlx builds for `sslmode=verify-ca` / `verify-full` panicked. The
/// PostgreSQL queue calls this before it connects, and so does `main`.
pub fn install_crypto_provider() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // Err only when some provider is installed already, which is all this wants.
        let _ = rustls::crypto::aws_lc_rs::default_provider().install_default();
    });
}

pub fn check_exposure(listen: SocketAddr, auth: bool, insecure: bool) -> Result<(), String> {
    if auth || insecure || listen.ip().is_loopback() {
        return Ok(());
    }
    Err(format!(
        "refusing to serve {listen} without authentication: anyone who can reach it could list, download, \
         cancel and delete every job. Add --auth (tokens from `lightmapd token create` or --tokens-file), \
         or --insecure-no-auth on a network you trust, or listen on 127.0.0.1"
    ))
}

impl Default for Config {
    fn default() -> Self {
        Config {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            data_dir: PathBuf::from("lightmapd-data"),
            workers: 1,
            database_url: None,
            store: None,
            limits: Limits::default(),
            auth: false,
            lease: DEFAULT_LEASE,
            snapshot_interval: Duration::from_secs(2),
            snapshot_keep: 8,
            job_retention: Some(DEFAULT_JOB_RETENTION),
            sweep_interval: Duration::from_secs(60),
            tokens_file: None,
            database_timeout: Duration::from_secs(60),
        }
    }
}

/// Caps on what a request may ask for; each is a `serve` flag (docs/service.md).
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// Largest scene upload, in bytes (413 beyond).
    pub max_scene_bytes: usize,
    /// Largest other request body (a job), in bytes (413 beyond).
    pub max_body_bytes: usize,
    /// Triangles of an uploaded scene after flattening its node tree (422 `triangles`).
    pub max_triangles: usize,
    /// Width and height of each texture (422 `textures`).
    pub max_texture_side: u32,
    /// Lightmap side (422 `resolution`).
    pub max_resolution: u32,
    /// A job's `stop.seconds`; a job without one gets this (422 `stop.seconds` beyond).
    pub max_job_seconds: f64,
    /// A job's `stop.steps` (422 `stop.steps` beyond).
    pub max_job_steps: u64,
    /// Queued jobs one client may have (429 beyond).
    pub max_queued_per_client: u64,
    /// Event streams open at once on this server (503 beyond).
    pub max_event_streams: usize,
    /// A job's estimated peak memory (`engine::footprint`); more is refused at submission
    /// (422 `resolution`) and by a worker whose own limit is lower.
    pub max_job_memory_bytes: u64,
    /// Time to answer a request (the headers; an event stream's body is not limited).
    /// A scene upload is not under it: its body only has to keep arriving
    /// ([`Limits::upload_idle_timeout`]).
    pub request_timeout: Duration,
    /// Longest wait for the next chunk of an upload's body (408 beyond), instead of a
    /// time for the whole upload, so a large scene on a slow link succeeds.
    pub upload_idle_timeout: Duration,
    /// Large bodies (uploads without a `Content-Length` or above `large_body_bytes`,
    /// downloads above it) in flight at once; past it, 503 with `Retry-After`.
    pub max_large_bodies: usize,
    /// What counts as a large body ([`LARGE_BODY_BYTES`] unless a test says otherwise).
    pub large_body_bytes: u64,
    /// Scene imports at once (an import holds the scene in memory); more wait.
    pub max_concurrent_imports: usize,
    /// Highest job priority an editor token (or any caller without tokens) may set; an
    /// admin token may set any (403 beyond).
    pub max_priority: i32,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_scene_bytes: 256 << 20,
            max_body_bytes: 1 << 20,
            max_triangles: 5_000_000,
            max_texture_side: 8192,
            max_resolution: model::MAX_SERVICE_RESOLUTION,
            max_job_seconds: 3600.0,
            max_job_steps: 1 << 20,
            max_queued_per_client: 100,
            max_event_streams: 256,
            max_job_memory_bytes: 8 << 30,
            request_timeout: Duration::from_secs(60),
            upload_idle_timeout: Duration::from_secs(30),
            max_large_bodies: 8,
            large_body_bytes: LARGE_BODY_BYTES,
            max_concurrent_imports: 2,
            max_priority: 10,
        }
    }
}

/// A body larger than this counts against [`Limits::max_large_bodies`].
pub const LARGE_BODY_BYTES: u64 = 16 << 20;

/// Why a local bake is being stopped early.
#[repr(u8)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopSignal {
    None = 0,
    /// The user cancelled the job.
    Cancel = 1,
    /// The process is shutting down: hand the job back.
    Shutdown = 2,
    /// The lease was lost: someone else owns the job now; write nothing.
    LeaseLost = 3,
}

/// A running bake's stop flag, set from the async side and read by the bake thread
/// after every step. The first reason set wins.
#[derive(Default)]
pub struct StopFlag(AtomicU8);

impl StopFlag {
    pub fn set(&self, s: StopSignal) {
        let _ = self
            .0
            .compare_exchange(StopSignal::None as u8, s as u8, Ordering::SeqCst, Ordering::SeqCst);
    }

    pub fn get(&self) -> StopSignal {
        match self.0.load(Ordering::SeqCst) {
            1 => StopSignal::Cancel,
            2 => StopSignal::Shutdown,
            3 => StopSignal::LeaseLost,
            _ => StopSignal::None,
        }
    }
}

/// In-process signals between routes, workers and event streams.
pub struct Hub {
    /// The id of a job whose row just changed (event streams re-read it).
    pub changed: broadcast::Sender<String>,
    /// A job was queued (idle workers try a claim).
    pub work: Notify,
    /// Stop flags of the bakes this process runs, by job id.
    running: Mutex<HashMap<String, Arc<StopFlag>>>,
}

impl Default for Hub {
    fn default() -> Self {
        Hub {
            changed: broadcast::channel(1024).0,
            work: Notify::new(),
            running: Mutex::new(HashMap::new()),
        }
    }
}

impl Hub {
    pub fn job_changed(&self, id: &str) {
        let _ = self.changed.send(id.to_string());
    }

    fn register(&self, id: &str) -> Arc<StopFlag> {
        let flag = Arc::new(StopFlag::default());
        if let Ok(mut m) = self.running.lock() {
            m.insert(id.to_string(), flag.clone());
        }
        flag
    }

    fn unregister(&self, id: &str) {
        if let Ok(mut m) = self.running.lock() {
            m.remove(id);
        }
    }

    /// Stops a bake this process runs, if it runs it (the cancel route calls this so the
    /// bake stops within one step rather than at the next heartbeat).
    pub fn stop_local(&self, id: &str, why: StopSignal) {
        if let Ok(m) = self.running.lock()
            && let Some(f) = m.get(id)
        {
            f.set(why);
        }
    }
}

/// What routes, workers and event streams share.
#[derive(Clone)]
pub struct AppState {
    pub queue: Arc<dyn Queue>,
    pub artifacts: Artifacts,
    pub metrics: Arc<Metrics>,
    pub hub: Arc<Hub>,
    pub config: Arc<Config>,
    /// Becomes `true` when the process is shutting down.
    pub shutdown: watch::Receiver<bool>,
    /// One permit per open event stream (`Limits::max_event_streams`).
    pub streams: Arc<tokio::sync::Semaphore>,
    /// One permit per large body in flight (`Limits::max_large_bodies`).
    pub large_bodies: Arc<tokio::sync::Semaphore>,
    /// One permit per scene import running (`Limits::max_concurrent_imports`).
    pub imports: Arc<tokio::sync::Semaphore>,
    /// The database's clock minus this process's, in ms ([`AppState::db_now`]).
    clock_offset: Arc<AtomicI64>,
}

impl AppState {
    fn new(queue: Arc<dyn Queue>, artifacts: Artifacts, config: &Config, shutdown: watch::Receiver<bool>) -> AppState {
        AppState {
            queue,
            artifacts,
            metrics: Arc::new(Metrics::default()),
            hub: Arc::new(Hub::default()),
            streams: Arc::new(tokio::sync::Semaphore::new(config.limits.max_event_streams)),
            large_bodies: Arc::new(tokio::sync::Semaphore::new(config.limits.max_large_bodies)),
            imports: Arc::new(tokio::sync::Semaphore::new(config.limits.max_concurrent_imports.max(1))),
            config: Arc::new(config.clone()),
            shutdown,
            clock_offset: Arc::new(AtomicI64::new(0)),
        }
    }

    /// A state over an SQLite queue and a local store in `config.data_dir`, for unit tests
    /// of routes.
    #[cfg(test)]
    pub(crate) async fn for_tests(config: &Config) -> AppState {
        let queue = queue::sqlite::SqliteQueue::open(&config.data_dir.join("lightmapd.db"))
            .await
            .unwrap();
        let artifacts = Artifacts::local(&config.data_dir.join("objects")).unwrap();
        let (_tx, rx) = watch::channel(false);
        AppState::new(Arc::new(queue), artifacts, config, rx)
    }

    /// Now on the database's clock (Unix ms): this process's clock plus the offset last
    /// measured by [`AppState::sync_clock`] (every recovery period).
    pub fn db_now(&self) -> i64 {
        queue::now_ms() + self.clock_offset.load(Ordering::Relaxed)
    }

    /// Reads the database's clock, remembers its offset from ours, and returns it.
    pub async fn sync_clock(&self) -> Result<i64, sqlx::Error> {
        let before = queue::now_ms();
        let db = self.queue.clock().await?;
        let after = queue::now_ms();
        // The database read its clock somewhere in the round trip: assume the middle.
        self.clock_offset.store(db - (before + after) / 2, Ordering::Relaxed);
        Ok(db)
    }
}

/// Removes a finished job: its artifacts first, then its row (so a failure in between
/// leaves a job whose deletion can be retried, never artifacts nobody can find).
pub async fn remove_job(state: &AppState, id: &str) -> Result<queue::JobDeletion, problem::Problem> {
    match state.queue.job(id).await? {
        None => return Ok(queue::JobDeletion::NotFound),
        Some(j) if !j.status.is_terminal() => return Ok(queue::JobDeletion::Unfinished(j.status)),
        Some(_) => {}
    }
    state.artifacts.delete_prefix(&store::job_prefix(id)).await?;
    let r = state.queue.delete_job(id).await?;
    if r == queue::JobDeletion::Deleted {
        state.hub.job_changed(id);
    }
    Ok(r)
}

/// The retention sweeper: every `sweep_interval`, removes finished jobs older than
/// `job_retention` (artifacts and row) and measures the store's usage for `/metrics`.
/// Several API processes may sweep at once: a job removed twice is removed once.
pub async fn retention_loop(state: AppState) {
    let mut shutdown = state.shutdown.clone();
    loop {
        if let Some(keep) = state.config.job_retention {
            let before = state.db_now() - keep.as_millis() as i64;
            loop {
                let ids = match state.queue.finished_before(before, 100).await {
                    Ok(ids) => ids,
                    Err(e) => {
                        tracing::warn!(error = %e, "retention sweep: cannot list finished jobs");
                        break;
                    }
                };
                let mut removed = 0;
                for id in &ids {
                    match remove_job(&state, id).await {
                        Ok(queue::JobDeletion::Deleted) => {
                            removed += 1;
                            state.metrics.jobs_expired.fetch_add(1, Ordering::Relaxed);
                            tracing::info!(job = %id, "retention: finished job removed");
                        }
                        Ok(_) => {}
                        Err(e) => tracing::warn!(job = %id, error = %e.detail, "retention: cannot remove job"),
                    }
                }
                if ids.len() < 100 || removed == 0 {
                    break;
                }
            }
        }
        match state
            .queue
            .forget_workers(state.db_now() - queue::WORKER_FORGET_MS)
            .await
        {
            Ok(0) => {}
            Ok(n) => tracing::info!(workers = n, "retention: workers not seen for a day removed"),
            Err(e) => tracing::warn!(error = %e, "retention sweep: cannot remove old workers"),
        }
        match state.artifacts.usage().await {
            Ok(u) => state.metrics.set_store_usage(u),
            Err(e) => tracing::warn!(error = %e, "cannot measure the artifact store's usage"),
        }
        tokio::select! {
            _ = tokio::time::sleep(state.config.sweep_interval) => {}
            _ = shutting_down(&mut shutdown) => break,
        }
    }
}

/// Opens the queue and the store the configuration names.
pub async fn open_backends(config: &Config) -> anyhow::Result<(Arc<dyn Queue>, Artifacts)> {
    if config.database_url.is_none() {
        // The data folder is made only when something goes in it: a worker with a
        // database URL and an S3 store has none.
        std::fs::create_dir_all(&config.data_dir)?;
    }
    let queue = queue::open(config.database_url.as_deref(), &config.data_dir.join("lightmapd.db")).await?;
    let store = config
        .store
        .clone()
        .unwrap_or_else(|| StoreUrl::Local(config.data_dir.join("objects")));
    let artifacts = Artifacts::open(&store, &[]).await?;
    Ok((queue, artifacts))
}

/// A started service: its address, and a way to stop it and wait for it.
pub struct Running {
    pub addr: SocketAddr,
    shutdown: watch::Sender<bool>,
    tasks: Vec<JoinHandle<()>>,
}

impl Running {
    /// Starts a graceful shutdown: no new requests, running bakes handed back to the queue.
    pub fn begin_shutdown(&self) {
        let _ = self.shutdown.send(true);
    }

    /// Waits until the server and every worker have stopped.
    pub async fn wait(self) {
        for t in self.tasks {
            let _ = t.await;
        }
    }

    pub async fn shutdown(self) {
        self.begin_shutdown();
        self.wait().await;
    }
}

/// Starts the API and `config.workers` workers; returns once the socket is bound.
pub async fn start(config: Config) -> anyhow::Result<Running> {
    let (queue, artifacts) = open_backends(&config).await?;
    start_with(config, queue, artifacts).await
}

/// [`start`] over a queue and store made by the caller (fault-injection tests wrap them).
pub async fn start_with(config: Config, queue: Arc<dyn Queue>, artifacts: Artifacts) -> anyhow::Result<Running> {
    let (tx, rx) = watch::channel(false);
    let state = AppState::new(queue, artifacts, &config, rx.clone());
    if let Some(tokens) = &config.tokens_file {
        let sync = auth::sync_tokens_file(&*state.queue, tokens).await?;
        tracing::info!(added = ?sync.added, revoked = ?sync.revoked, kept = ?sync.kept, "tokens file applied");
    }
    if let Err(e) = state.sync_clock().await {
        tracing::warn!(error = %e, "cannot read the database's clock; using this machine's until it answers");
    }
    // Uploads a killed process was receiving are of no use to anyone.
    upload::clear_spool(&config.data_dir.join("spool"));
    let mut tasks = vec![tokio::spawn(worker::recovery_loop(state.clone()))];
    tasks.push(tokio::spawn(retention_loop(state.clone())));
    tasks.extend(state.queue.listen(state.hub.clone(), rx.clone()));
    tasks.extend(worker::spawn_pool(
        &state,
        config.workers,
        Arc::new(worker::EngineShared::default()),
    ));
    let listener = tokio::net::TcpListener::bind(config.listen).await?;
    let addr = listener.local_addr()?;
    let app = routes::router(state.clone());
    let mut stop = rx.clone();
    tasks.push(tokio::spawn(async move {
        // The peer address feeds the per-client queue limit when tokens are off.
        let served = axum::serve(listener, app.into_make_service_with_connect_info::<SocketAddr>())
            .with_graceful_shutdown(async move { shutting_down(&mut stop).await })
            .await;
        if let Err(e) = served {
            tracing::error!(error = %e, "HTTP server stopped");
        }
    }));
    tracing::info!(%addr, workers = config.workers, "lightmapd serving");
    Ok(Running {
        addr,
        shutdown: tx,
        tasks,
    })
}

/// Runs workers only (no API) until `shutdown` resolves, or until the database has not
/// answered for `config.database_timeout` (then an error: the process exits 1 and its
/// supervisor restarts it, which is what the compose and Kubernetes files rely on).
pub async fn run_workers(config: Config, shutdown: impl std::future::Future<Output = ()>) -> anyhow::Result<()> {
    let (queue, artifacts) = open_backends(&config).await?;
    run_workers_with(config, queue, artifacts, shutdown).await
}

/// [`run_workers`] over a queue and store made by the caller.
pub async fn run_workers_with(
    config: Config,
    queue: Arc<dyn Queue>,
    artifacts: Artifacts,
    shutdown: impl std::future::Future<Output = ()>,
) -> anyhow::Result<()> {
    let (tx, rx) = watch::channel(false);
    let state = AppState::new(queue, artifacts, &config, rx.clone());
    let _ = state.sync_clock().await;
    let mut tasks = vec![tokio::spawn(worker::recovery_loop(state.clone()))];
    tasks.extend(state.queue.listen(state.hub.clone(), rx));
    tasks.extend(worker::spawn_pool(
        &state,
        config.workers,
        Arc::new(worker::EngineShared::default()),
    ));
    let outcome = tokio::select! {
        _ = shutdown => Ok(()),
        lost = database_watchdog(&state, config.database_timeout) => Err(lost),
    };
    let _ = tx.send(true);
    for t in tasks {
        let _ = t.await;
    }
    outcome
}

/// Resolves with an error once the database has failed every check for `timeout`
/// (checked every second, or every `timeout / 4` when that is shorter).
async fn database_watchdog(state: &AppState, timeout: Duration) -> anyhow::Error {
    let period = (timeout / 4).clamp(Duration::from_millis(50), Duration::from_secs(1));
    let mut last_ok = std::time::Instant::now();
    loop {
        tokio::time::sleep(period).await;
        match state.queue.clock().await {
            Ok(_) => last_ok = std::time::Instant::now(),
            Err(e) if last_ok.elapsed() >= timeout => {
                tracing::error!(error = %e, seconds = timeout.as_secs_f64(), "the database has not answered: exiting so the supervisor restarts this worker");
                return anyhow::anyhow!(
                    "the database has not answered for {} s (--database-timeout-s): {e}",
                    timeout.as_secs_f64()
                );
            }
            Err(e) => tracing::warn!(error = %e, "database check failed"),
        }
    }
}

/// Resolves once `rx` says the process is shutting down (or its sender is gone).
pub async fn shutting_down(rx: &mut watch::Receiver<bool>) {
    // The guard `wait_for` returns is not `Send`; dropping it here keeps callers' futures
    // spawnable.
    let _ = rx.wait_for(|s| *s).await.map(|_| ());
}

/// Resolves on SIGTERM or Ctrl-C.
pub async fn termination() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}
