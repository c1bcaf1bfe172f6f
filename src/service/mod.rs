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
//! tokens; every request has a time limit; artifacts are written to a temporary file,
//! synced, then renamed, before the job that made them is marked succeeded.
//!
//! Limits: API and worker processes on several machines need PostgreSQL and an artifact
//! store they all reach (an S3 bucket, [`store`], or a shared filesystem).

pub mod auth;
pub mod client;
pub mod console;
pub mod events;
pub mod metrics;
pub mod model;
pub mod problem;
pub mod queue;
pub mod routes;
pub mod store;
pub mod worker;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU8, Ordering};
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
            lease: Duration::from_secs(30),
            snapshot_interval: Duration::from_secs(2),
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
    pub request_timeout: Duration,
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
        }
    }
}

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
}

impl AppState {
    fn new(queue: Arc<dyn Queue>, artifacts: Artifacts, config: &Config, shutdown: watch::Receiver<bool>) -> AppState {
        AppState {
            queue,
            artifacts,
            metrics: Arc::new(Metrics::default()),
            hub: Arc::new(Hub::default()),
            streams: Arc::new(tokio::sync::Semaphore::new(config.limits.max_event_streams)),
            config: Arc::new(config.clone()),
            shutdown,
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
    let mut tasks = vec![tokio::spawn(worker::recovery_loop(state.clone()))];
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

/// Runs workers only (no API) until `shutdown` resolves.
pub async fn run_workers(config: Config, shutdown: impl std::future::Future<Output = ()>) -> anyhow::Result<()> {
    let (queue, artifacts) = open_backends(&config).await?;
    let (tx, rx) = watch::channel(false);
    let state = AppState::new(queue, artifacts, &config, rx.clone());
    let mut tasks = vec![tokio::spawn(worker::recovery_loop(state.clone()))];
    tasks.extend(state.queue.listen(state.hub.clone(), rx));
    tasks.extend(worker::spawn_pool(
        &state,
        config.workers,
        Arc::new(worker::EngineShared::default()),
    ));
    shutdown.await;
    let _ = tx.send(true);
    for t in tasks {
        let _ = t.await;
    }
    Ok(())
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
