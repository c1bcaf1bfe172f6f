//! Workers: claim a job, run the bake on a blocking thread, report back, finish.
//!
//! How: each worker is an async task that loops over [`Queue::claim`](crate::service::queue::Queue::claim). A claimed job's
//! bake runs under `spawn_blocking` (the engine is CPU- or GPU-bound and must never
//! stall the runtime's threads) with an observer that only touches shared memory: the
//! latest progress, the history of (seconds, steps, error) points, and, every
//! `snapshot_interval`, the raw estimate handed to an encoder thread, which denoises and
//! encodes the snapshot EXR and PNG beside the bake and hands them over a channel. The async
//! side ticks 4 times a second: it writes progress if it changed (so the database sees
//! at most ~4 writes a second per job), renews the lease with the same statement, reads
//! back the cancel flag, and uploads snapshots. While a step that reports how far it is
//! runs (CPU `path`: one step can be minutes on a large level), the ticker moves the
//! progress on with it (`step_fraction`, and `elapsed_s` and `fraction` live). The bake thread checks the job's
//! [`StopFlag`] after every step, and the ticker passes a raised flag into the step in
//! progress (`StepProgress::request_stop`), so a cancel stops even a long CPU `path` step
//! within a chunk of it (a quarter second for the ticker, plus the chunk).
//!
//! Snapshots: after storing snapshot `n` (and recording the count), the worker deletes
//! the ones snapshot retention no longer keeps ([`store::snapshots_to_drop`]), so a job
//! holds at most `snapshot_keep` snapshot pairs however long it bakes.
//!
//! Leases (issue 24): the lease is renewed for as long as the job is ours, not only while
//! the bake runs: storing the final EXR, preview and scene, and recording the end, run
//! under `while_holding`, which keeps renewing it, so a slow upload never lets the lease
//! lapse and the job run twice. Every lease time is on the database's clock
//! ([`AppState::db_now`]).
//!
//! Endings: finished → final EXR and preview stored, then `succeeded`; engine error →
//! `failed` with its message; cancel → `cancelled`; shutdown → the job is released to
//! `queued` (attempt not counted); lease lost → nothing is written, the job is someone
//! else's now. [`recovery_loop`] re-queues the jobs of workers that died.
//!
//! Limits: a bake restarts from step 0 when it is taken up again. The scene is imported
//! again for each job (no cache); for the small scenes a lightmap bake takes that is
//! milliseconds.

use std::ops::ControlFlow;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use bytes::Bytes;
use glam::Vec3;
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tracing::Instrument;

use crate::engine::atlas::Atlas;
use crate::engine::bake::{BakeEvent, StopReason};
use crate::engine::job::{self, BakeOptions, BakeResult};
use crate::engine::plan::Plan;
use crate::engine::reference::{ReferenceLightmap, relative_error};
use crate::engine::scene::{self, Scene};
use crate::engine::technique::EngineError;
use crate::service::model::{HistoryPoint, JobStatus, ProbeProgress, Progress};
use crate::service::queue::{Capabilities, JobRecord, JobUpdate, Lease, Outcome, QueueResult, WORKER_REFRESH};
use crate::service::{AppState, StopFlag, StopSignal, shutting_down, store};

/// How often a running job's progress is written and its lease checked.
pub(crate) const TICK: Duration = Duration::from_millis(250);
/// How long an idle worker waits for a wake-up (`Hub::work`: a job queued in this
/// process, or a PostgreSQL `lightmapd_work` NOTIFY from any) before asking again.
const IDLE_POLL: Duration = Duration::from_millis(500);
/// The most history points kept per job (one per snapshot; the schedule makes few).
const MAX_HISTORY: usize = 2000;

/// Engine resources every worker of a process shares, created once.
///
/// Empty: the one wgpu device the GPU techniques share lives in the engine
/// (`engine::gpu::shared`), created by the first GPU job and reused by every later one
/// in this process; a `path` job never creates it.
#[derive(Default)]
pub struct EngineShared {}

/// What this process's workers can run: the default adapter (and whether it is
/// hardware), OIDN, and the per-job memory limit. Probed once, off the runtime's threads
/// (adapter enumeration loads the Vulkan drivers).
pub async fn capabilities(state: &AppState) -> Capabilities {
    let memory_bytes = state.config.limits.max_job_memory_bytes;
    let probe = tokio::task::spawn_blocking(|| {
        let adapter = crate::engine::gpu::default_adapter();
        let oidn = crate::engine::post::oidn::Oidn::available();
        (adapter, oidn)
    });
    let (adapter, oidn) = probe.await.unwrap_or((None, false));
    let software = crate::engine::gpu::AdapterPreference::from_env() == crate::engine::gpu::AdapterPreference::Cpu;
    Capabilities {
        gpu: !software && matches!(adapter, Some((_, "discrete" | "integrated" | "virtual"))),
        adapter_kind: adapter.as_ref().map(|a| a.1.to_string()),
        adapter: adapter.map(|a| a.0),
        oidn,
        memory_bytes,
    }
}

/// Starts `n` workers named after this process, and the loop that keeps them
/// registered (`workers.last_seen`) while the process runs.
pub fn spawn_pool(state: &AppState, n: usize, engine: Arc<EngineShared>) -> Vec<JoinHandle<()>> {
    let host = std::env::var("HOSTNAME").unwrap_or_else(|_| "local".into());
    let instance = &uuid::Uuid::new_v4().simple().to_string()[..8];
    state.metrics.workers.fetch_add(n, Ordering::Relaxed);
    let ids: Vec<String> = (0..n)
        .map(|i| format!("{host}-{}-{instance}-{i}", std::process::id()))
        .collect();
    let caps = Arc::new(tokio::sync::OnceCell::new());
    let mut handles: Vec<JoinHandle<()>> = ids
        .iter()
        .map(|id| tokio::spawn(worker_loop(state.clone(), id.clone(), engine.clone(), caps.clone())))
        .collect();
    if n > 0 {
        handles.push(tokio::spawn(presence_loop(state.clone(), ids, caps)));
    }
    handles
}

/// Re-registers this process's workers every [`WORKER_REFRESH`] (a busy worker does not
/// pass through its claim loop for as long as a bake runs), so the API counts them alive.
async fn presence_loop(state: AppState, ids: Vec<String>, caps: Arc<tokio::sync::OnceCell<Capabilities>>) {
    let mut shutdown = state.shutdown.clone();
    let caps = caps.get_or_init(|| capabilities(&state)).await.clone();
    loop {
        for id in &ids {
            if let Err(e) = state.queue.register_worker(id, &caps, state.db_now()).await {
                tracing::warn!(worker = %id, error = %e, "cannot register the worker");
            }
        }
        tokio::select! {
            _ = tokio::time::sleep(WORKER_REFRESH) => {}
            _ = shutting_down(&mut shutdown) => break,
        }
    }
}

async fn worker_loop(
    state: AppState,
    worker: String,
    engine: Arc<EngineShared>,
    caps: Arc<tokio::sync::OnceCell<Capabilities>>,
) {
    let mut shutdown = state.shutdown.clone();
    let caps = caps.get_or_init(|| capabilities(&state)).await.clone();
    tracing::info!(worker = %worker, gpu = caps.gpu, adapter = ?caps.adapter, oidn = caps.oidn, "worker started");
    loop {
        if *shutdown.borrow() {
            break;
        }
        // A task of a split job, unless a whole job this worker can run is ahead of it
        // in the queue order (priority, then age: `claim_task` declines then), then a
        // whole job: one order over both kinds.
        match state
            .queue
            .claim_task(&worker, &caps, state.config.lease, state.db_now())
            .await
        {
            Ok(Some((task, job))) => {
                let span =
                    tracing::info_span!("task", job = %job.id, task = task.index, tasks = task.count, worker = %worker);
                crate::service::farm::run_task(&state, &worker, task, job)
                    .instrument(span)
                    .await;
                continue;
            }
            Ok(None) => {}
            Err(e) => {
                tracing::error!(worker = %worker, error = %e, "cannot claim a task; retrying");
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        }
        match state
            .queue
            .claim(&worker, &caps, state.config.lease, state.db_now())
            .await
        {
            Ok(Some(job)) => {
                let span = tracing::info_span!("job", job = %job.id, technique = %job.spec.technique, worker = %worker);
                run_job(&state, &worker, job, &engine).instrument(span).await;
            }
            Ok(None) => {
                tokio::select! {
                    _ = state.hub.work.notified() => {}
                    _ = tokio::time::sleep(IDLE_POLL) => {}
                    _ = shutdown.changed() => {}
                }
            }
            Err(e) => {
                tracing::error!(worker = %worker, error = %e, "cannot claim a job; retrying");
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }
    tracing::info!(worker = %worker, "worker stopped");
}

/// How often expired leases are looked for: a fifth of the lease, between 0.1 and 1 s, so
/// a dead worker's job is queued again at most a lease plus one period after its last
/// renewal (6 s with the default 5 s lease).
pub fn recovery_period(lease: Duration) -> Duration {
    (lease / 5).clamp(Duration::from_millis(100), Duration::from_secs(1))
}

/// Finds jobs whose worker died (lease expired) at start-up and every
/// [`recovery_period`], comparing leases with the database's clock.
pub async fn recovery_loop(state: AppState) {
    let mut shutdown = state.shutdown.clone();
    let period = recovery_period(state.config.lease);
    loop {
        let recovered = match state.sync_clock().await {
            Ok(now) => state.queue.recover_expired(now).await,
            Err(e) => Err(e),
        };
        match recovered {
            Ok(r) => {
                for id in &r.requeued {
                    tracing::warn!(job = %id, "lease expired: job queued again");
                    state.hub.job_changed(id);
                }
                for id in &r.failed {
                    tracing::error!(job = %id, "lease expired too often: job failed");
                    state.hub.job_changed(id);
                }
                for id in &r.cancelled {
                    state.hub.job_changed(id);
                }
                if !r.requeued.is_empty() {
                    state.hub.work.notify_waiters();
                }
            }
            Err(e) => tracing::error!(error = %e, "lease recovery failed"),
        }
        tokio::select! {
            _ = tokio::time::sleep(period) => {}
            _ = shutting_down(&mut shutdown) => break,
        }
    }
}

/// What the bake thread shares with the job's async supervisor.
#[derive(Default)]
struct Shared {
    progress: Mutex<Option<Progress>>,
    history: Mutex<Vec<HistoryPoint>>,
    plan: Mutex<Option<Value>>,
    /// The scene with the UVs the engine generated, from the bake thread, until the
    /// supervising task stores it (so the console can show snapshots on it).
    generated_scene: Mutex<Option<Arc<Scene>>>,
    /// It is stored: the final upload need not store it again.
    generated_scene_stored: std::sync::atomic::AtomicBool,
    /// The latest stored snapshot's delivered (denoised) relative error.
    delivered_error: Mutex<Option<f32>>,
    /// With a reference job: its value at every valid texel, once the texel set exists.
    reference: OnceLock<Arc<Vec<Option<Vec3>>>>,
    /// The final lightmap's error against the reference.
    final_true_error: Mutex<Option<f32>>,
    /// How far the step in progress is and since when the loop steps, written by the
    /// engine (CPU `path` reports within its steps); the ticker folds it into `progress`.
    step: crate::engine::bake::StepProgress,
}

pub(crate) struct SnapshotFiles {
    pub(crate) exr: Vec<u8>,
    pub(crate) png: Vec<u8>,
    pub(crate) steps: u64,
    pub(crate) error: Option<f32>,
}

async fn run_job(state: &AppState, worker: &str, job: JobRecord, engine: &Arc<EngineShared>) {
    let id = job.id.clone();
    tracing::info!(attempt = job.attempts, "job claimed");
    state.hub.job_changed(&id);
    state.metrics.busy.fetch_add(1, Ordering::Relaxed);
    let flag = state.hub.register(&id);
    let outcome = supervise(state, worker, &job, flag.clone(), engine.clone()).await;
    state.hub.unregister(&id);
    state.metrics.busy.fetch_sub(1, Ordering::Relaxed);
    let now = state.db_now();
    let written = match outcome {
        End::Lost => {
            tracing::warn!("lease lost: another worker owns the job now; nothing written");
            Ok(true)
        }
        End::Release => {
            tracing::info!("shutting down: job handed back to the queue");
            state.queue.release(&id, worker, now).await
        }
        End::Finish(outcome) => {
            let status = match &outcome {
                Outcome::Succeeded { .. } => JobStatus::Succeeded,
                Outcome::Failed { reason } => {
                    tracing::warn!(reason = %reason, "job failed");
                    JobStatus::Failed
                }
                Outcome::Cancelled => JobStatus::Cancelled,
            };
            // Still renewing while the end is written (a slow database must not let the
            // lease lapse between the stored artifacts and the recorded end), and written
            // again after a database error (a restart, a dropped connection) for as long
            // as the lease is ours and the database has not been gone for
            // `--database-timeout-s`: a finished bake is not thrown away for a hiccup.
            // `finish` is guarded by the lease, so a retry can never record it twice.
            let first_try = Instant::now();
            let mut wait = Duration::from_millis(100);
            let r = loop {
                let r = while_holding(
                    state,
                    Lessee::Job(&id),
                    worker,
                    &flag,
                    state.queue.finish(&id, worker, &outcome, state.db_now()),
                )
                .await;
                match r {
                    Err(e)
                        if flag.get() != StopSignal::LeaseLost
                            && first_try.elapsed() + wait < state.config.database_timeout =>
                    {
                        tracing::warn!(error = %e, retry_in_ms = wait.as_millis() as u64, "cannot record the end of the job; trying again");
                        tokio::time::sleep(wait).await;
                        wait = (wait * 2).min(Duration::from_secs(2));
                    }
                    r => break r,
                }
            };
            if matches!(r, Ok(true)) {
                state.metrics.job_finished(status);
                tracing::info!(status = status.as_str(), "job finished");
            }
            r
        }
    };
    match written {
        Ok(true) => {}
        Ok(false) => tracing::warn!("the job was no longer ours when it ended (lease expired); result dropped"),
        Err(e) => {
            tracing::error!(error = %e, "cannot record the end of the job; its lease will expire and it runs again")
        }
    }
    state.hub.job_changed(&id);
}

enum End {
    Finish(Outcome),
    Release,
    Lost,
}

async fn supervise(
    state: &AppState,
    worker: &str,
    job: &JobRecord,
    flag: Arc<StopFlag>,
    engine: Arc<EngineShared>,
) -> End {
    // A database or store outage when the job is claimed delays it (the lease held
    // meanwhile) rather than failing it: measured in tests/service/real_faults.rs, where jobs
    // claimed while the store was unreachable failed after object_store's own 10
    // retries (2.7 s).
    let load = || async { Ok::<_, LoadError>((load_scene(state, job).await?, load_reference(state, job).await?)) };
    let (scene, reference) = match load_patiently(state, Lessee::Job(&job.id), worker, &flag, load).await {
        Ok(s) => s,
        Err(None) => return End::Lost,
        Err(Some(reason)) => return End::Finish(Outcome::Failed { reason }),
    };
    let shared = Arc::new(Shared::default());
    // One encoded snapshot waits at most: while one is being stored (a slow or
    // unreachable store), the encoder waits, the bake thread finds it busy and skips
    // snapshots, so an outage costs no memory beyond two snapshots.
    let (snap_tx, mut snap_rx) = mpsc::channel::<SnapshotFiles>(1);
    let bake = {
        let ctx = BakeThread {
            shared: shared.clone(),
            flag: flag.clone(),
            metrics: state.metrics.clone(),
            engine,
            snapshots: snap_tx,
            snapshot_interval: state.config.snapshot_interval,
            limits: state.config.limits.clone(),
        };
        let spec = job.spec.clone();
        let span = tracing::Span::current();
        tokio::task::spawn_blocking(move || {
            let _e = span.enter();
            run_bake(scene, reference, &spec, &ctx)
        })
    };
    tokio::pin!(bake);
    let mut ticker = tokio::time::interval(TICK);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut shutdown = state.shutdown.clone();
    let mut stopping = false;
    let mut written_progress: Option<Progress> = None;
    let mut written_plan: Option<Value> = None;
    let mut last_renewal = Instant::now();
    let mut snapshots = job.snapshots;
    let lease = state.config.lease;
    let result = loop {
        tokio::select! {
            r = &mut bake => break r,
            Some(files) = snap_rx.recv() => {
                if flag.get() != StopSignal::LeaseLost {
                    let (step, error) = (files.steps, files.error);
                    // The lease is renewed while the store is slow or unreachable (its
                    // client retries for minutes): this loop's own ticker waits meanwhile.
                    let stored = while_holding(state, Lessee::Job(&job.id), worker, &flag, store_snapshot(state, &job.id, snapshots + 1, files)).await;
                    match stored {
                        Ok(()) => {
                            snapshots += 1;
                            let update = JobUpdate { snapshots: Some(snapshots), ..collect(&shared, &mut written_progress, &mut written_plan, true) };
                            beat(state, job, worker, &update, &flag, &mut last_renewal).await;
                            tracing::info!(snapshot = snapshots, step, error, "snapshot stored");
                            while_holding(state, Lessee::Job(&job.id), worker, &flag, thin_snapshots(state, &job.id, snapshots)).await;
                        }
                        Err(e) => tracing::error!(error = %e, "cannot store a snapshot"),
                    }
                }
            }
            _ = ticker.tick() => {
                // A raised flag (cancel, shutdown, lost lease) also reaches inside a long
                // step: CPU `path` abandons it within a chunk instead of running it out.
                if flag.get() != StopSignal::None {
                    shared.step.request_stop();
                }
                let generated = shared.generated_scene.lock().ok().and_then(|mut g| g.take());
                if let Some(scene) = generated && flag.get() != StopSignal::LeaseLost {
                    match while_holding(state, Lessee::Job(&job.id), worker, &flag, store_generated_scene(state, &job.id, scene)).await {
                        Ok(()) => {
                            shared.generated_scene_stored.store(true, Ordering::Relaxed);
                            // The job's plan says where it is; the next beat writes it.
                            if let Ok(mut p) = shared.plan.lock() {
                                p.get_or_insert_with(|| json!({}))["generated_scene"] = json!(format!("/v1/jobs/{}/scene.glb", job.id));
                            }
                            tracing::info!("scene with generated UVs stored");
                        }
                        Err(e) => tracing::warn!(error = %e, "cannot store the scene with generated UVs now; it goes with the final lightmap"),
                    }
                }
                within_step(&shared, &job.spec.stop);
                let update = collect(&shared, &mut written_progress, &mut written_plan, false);
                let changed = update.progress.is_some() || update.plan.is_some();
                if (changed || last_renewal.elapsed() >= lease / 3) && flag.get() != StopSignal::LeaseLost {
                    beat(state, job, worker, &update, &flag, &mut last_renewal).await;
                }
            }
            _ = shutting_down(&mut shutdown), if !stopping => {
                stopping = true;
                flag.set(StopSignal::Shutdown);
            }
        }
    };
    // The bake has ended: a snapshot still in the channel is stored if the job is ours.
    while let Ok(files) = snap_rx.try_recv() {
        if flag.get() == StopSignal::LeaseLost {
            break;
        }
        if while_holding(
            state,
            Lessee::Job(&job.id),
            worker,
            &flag,
            store_snapshot(state, &job.id, snapshots + 1, files),
        )
        .await
        .is_ok()
        {
            snapshots += 1;
            let update = JobUpdate {
                snapshots: Some(snapshots),
                ..collect(&shared, &mut written_progress, &mut written_plan, true)
            };
            beat(state, job, worker, &update, &flag, &mut last_renewal).await;
            while_holding(
                state,
                Lessee::Job(&job.id),
                worker,
                &flag,
                thin_snapshots(state, &job.id, snapshots),
            )
            .await;
        }
    }
    let result = match result {
        Ok(r) => r,
        Err(e) => {
            return End::Finish(Outcome::Failed {
                reason: format!("the bake thread panicked: {e}"),
            });
        }
    };
    match (flag.get(), result) {
        (StopSignal::LeaseLost, _) => End::Lost,
        (_, Err(e)) => End::Finish(Outcome::Failed {
            reason: if e.is_bad_input() {
                format!("bad input: {e}")
            } else {
                e.to_string()
            },
        }),
        (why, Ok(r)) if r.summary.stopped_by == StopReason::Cancelled => {
            if why == StopSignal::Shutdown {
                End::Release
            } else {
                End::Finish(Outcome::Cancelled)
            }
        }
        (_, Ok(r)) => {
            tracing::info!(
                step = r.summary.steps,
                seconds = r.summary.seconds,
                error = r.summary.error.relative,
                stopped_by = ?r.summary.stopped_by,
                "bake finished"
            );
            state.metrics.observe_bake(&job.spec.technique, r.summary.seconds);
            let scene_stored = shared.generated_scene_stored.load(Ordering::Relaxed);
            if let Err(e) = while_holding(
                state,
                Lessee::Job(&job.id),
                worker,
                &flag,
                store_final(state, &job.id, &r, scene_stored),
            )
            .await
            {
                return End::Finish(Outcome::Failed {
                    reason: format!("cannot store the lightmap: {e}"),
                });
            }
            let mut progress = Progress::new(
                r.summary.steps,
                r.summary.seconds,
                r.summary.error.relative,
                &job.spec.stop,
            );
            // The probes' last count stays in the finished job's progress.
            progress.probes = shared.progress.lock().ok().and_then(|p| p.and_then(|p| p.probes));
            let mut history = shared.history.lock().map(|h| h.clone()).unwrap_or_default();
            // The final lightmap's point ends the curve, with the figure the summary gives.
            let e = &r.summary.error;
            history.push(HistoryPoint {
                seconds: r.summary.seconds,
                steps: r.summary.steps,
                error: e.relative,
                raw_error: e.raw_relative.or(e.relative),
                noise: e.noise,
                bias: e.bias,
                true_error: shared.final_true_error.lock().ok().and_then(|e| *e),
            });
            End::Finish(Outcome::Succeeded {
                summary: serde_json::to_value(&r.summary).unwrap_or(Value::Null),
                progress: serde_json::to_value(progress).unwrap_or(Value::Null),
                history: serde_json::to_value(history).unwrap_or(Value::Null),
            })
        }
    }
}

/// Moves the shared progress on while a step that reports its progress runs (a long CPU
/// `path` step on a large level can take minutes; without this the job would stand at
/// its last step count, and its elapsed time, all that while). Not at a step's very
/// start or end: 0 is also what a technique that does not report leaves, and 1000 stands
/// between the step's end and the next one's start.
fn within_step(shared: &Shared, stop: &crate::service::model::StopSpec) {
    let Some(since) = shared.step.stepping_since() else {
        return;
    };
    let permille = shared.step.permille();
    if permille == 0 || permille >= 1000 {
        return;
    }
    if let Ok(mut p) = shared.progress.lock() {
        let base = p.unwrap_or_else(|| Progress::new(0, 0.0, None, stop));
        *p = Some(base.within_step(since.elapsed().as_secs_f64(), f64::from(permille) / 1000.0, stop));
    }
}

/// The parts of the shared state not yet written.
fn collect(
    shared: &Shared,
    written: &mut Option<Progress>,
    written_plan: &mut Option<Value>,
    with_history: bool,
) -> JobUpdate {
    let mut u = JobUpdate::default();
    let p = shared.progress.lock().ok().and_then(|p| *p);
    if p.is_some() && p != *written {
        u.progress = p.and_then(|p| serde_json::to_value(p).ok());
        *written = p;
    }
    let plan = shared.plan.lock().ok().and_then(|p| p.clone());
    if plan.is_some() && plan != *written_plan {
        u.plan = plan.clone();
        *written_plan = plan;
    }
    if with_history {
        u.history = shared.history.lock().ok().and_then(|h| serde_json::to_value(&*h).ok());
    }
    u
}

/// Writes progress and renews the lease; raises the stop flag on cancel or a lost lease.
async fn beat(
    state: &AppState,
    job: &JobRecord,
    worker: &str,
    update: &JobUpdate,
    flag: &StopFlag,
    last: &mut Instant,
) {
    match state
        .queue
        .heartbeat(&job.id, worker, state.config.lease, update, state.db_now())
        .await
    {
        Ok(Lease::Held { cancel }) => {
            *last = Instant::now();
            if cancel {
                flag.set(StopSignal::Cancel);
            }
            state.hub.job_changed(&job.id);
        }
        Ok(Lease::Lost) => flag.set(StopSignal::LeaseLost),
        // A database hiccup is not a lost lease: try again at the next tick.
        Err(e) => tracing::warn!(error = %e, "heartbeat failed"),
    }
}

/// Runs `load` (a claimed job's scene and other inputs) until it succeeds, holding the
/// lease meanwhile: a transient failure (the database or the store did not answer) is
/// tried again with a growing wait for up to [`SCENE_LOAD_PATIENCE`]. `Err(None)`: the
/// lease was lost; `Err(Some(reason))`: it failed for good.
pub(crate) async fn load_patiently<T, F, Fut>(
    state: &AppState,
    lessee: Lessee<'_>,
    worker: &str,
    flag: &StopFlag,
    load: F,
) -> Result<T, Option<String>>
where
    F: Fn() -> Fut,
    Fut: std::future::Future<Output = Result<T, LoadError>>,
{
    let started = Instant::now();
    let mut wait = Duration::from_millis(200);
    loop {
        match while_holding(state, lessee, worker, flag, load()).await {
            Ok(s) => return Ok(s),
            _ if flag.get() == StopSignal::LeaseLost => return Err(None),
            Err(LoadError::Transient(reason)) if started.elapsed() + wait < SCENE_LOAD_PATIENCE => {
                tracing::warn!(
                    reason,
                    retry_in_ms = wait.as_millis() as u64,
                    "cannot load the scene yet; trying again"
                );
                while_holding(state, lessee, worker, flag, tokio::time::sleep(wait)).await;
                wait = (wait * 2).min(Duration::from_secs(5));
            }
            Err(LoadError::Transient(reason) | LoadError::Permanent(reason)) => return Err(Some(reason)),
        }
    }
}

/// Whose lease a worker holds: a whole job's, or one task's of a split job.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Lessee<'a> {
    Job(&'a str),
    Task(&'a str, u32),
}

impl Lessee<'_> {
    /// Renews the lease without writing anything else.
    pub(crate) async fn renew(self, state: &AppState, worker: &str) -> QueueResult<Lease> {
        let (lease, now) = (state.config.lease, state.db_now());
        match self {
            Lessee::Job(id) => {
                state
                    .queue
                    .heartbeat(id, worker, lease, &JobUpdate::default(), now)
                    .await
            }
            Lessee::Task(id, k) => state.queue.task_heartbeat(id, k, worker, lease, None, now).await,
        }
    }
}

/// Runs `work` while renewing the lease every third of a lease (the bake's own ticker
/// has stopped by then): a lost lease raises the flag, and `work` still finishes (its
/// result is then not recorded: `finish` is guarded by the lease).
pub(crate) async fn while_holding<T>(
    state: &AppState,
    lessee: Lessee<'_>,
    worker: &str,
    flag: &StopFlag,
    work: impl std::future::Future<Output = T>,
) -> T {
    tokio::pin!(work);
    let period = (state.config.lease / 3).max(Duration::from_millis(20));
    let mut ticker = tokio::time::interval_at(tokio::time::Instant::now() + period, period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            r = &mut work => return r,
            _ = ticker.tick() => {
                match lessee.renew(state, worker).await {
                    Ok(Lease::Held { .. }) => tracing::debug!("lease renewed while storing the result"),
                    Ok(Lease::Lost) => flag.set(StopSignal::LeaseLost),
                    Err(e) => tracing::warn!(error = %e, "heartbeat failed"),
                }
            }
        }
    }
}

/// Deletes the snapshots that storing snapshot `n` made surplus (snapshot retention).
pub(crate) async fn thin_snapshots(state: &AppState, job: &str, n: u32) {
    for k in store::snapshots_to_drop(n, state.config.snapshot_keep) {
        let exr = state.artifacts.delete(&store::snapshot_exr(job, k)).await;
        let png = state.artifacts.delete(&store::snapshot_png(job, k)).await;
        match exr.and(png) {
            Ok(()) => {
                state.metrics.snapshots_thinned.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(snapshot = k, "snapshot thinned out");
            }
            Err(e) => tracing::warn!(snapshot = k, error = %e, "cannot delete a thinned-out snapshot"),
        }
    }
}

pub(crate) async fn store_snapshot(
    state: &AppState,
    job: &str,
    n: u32,
    files: SnapshotFiles,
) -> Result<(), object_store::Error> {
    state
        .artifacts
        .put(&store::snapshot_exr(job, n), Bytes::from(files.exr))
        .await?;
    state
        .artifacts
        .put(&store::snapshot_png(job, n), Bytes::from(files.png))
        .await
}

/// Exports the scene with its generated UVs as `.glb` (off the runtime's threads) and
/// stores it as the job's `scene.glb`.
async fn store_generated_scene(state: &AppState, job: &str, scene: Arc<Scene>) -> Result<(), object_store::Error> {
    let glb = tokio::task::spawn_blocking(move || crate::engine::scene::export::to_glb(&scene))
        .await
        .map_err(|e| e.to_string())
        .and_then(|r| r)
        .map_err(|e| object_store::Error::Generic {
            store: "export",
            source: format!("cannot export the scene with generated UVs: {e}").into(),
        })?;
    state
        .artifacts
        .put(&store::generated_scene(job), Bytes::from(glb))
        .await
}

/// The final artifacts; `scene_stored`: the scene with generated UVs was stored while
/// the bake ran (it does not change after the UVs are made).
pub(crate) async fn store_final(
    state: &AppState,
    job: &str,
    r: &BakeResult,
    scene_stored: bool,
) -> Result<(), object_store::Error> {
    if r.summary.generated_uvs.is_some() && !scene_stored {
        // The lightmap is only usable with the UVs it was baked for (DESIGN §2).
        store_generated_scene(state, job, r.scene.clone()).await?;
    }
    if let Some(set) = &r.probes {
        let json = serde_json::to_vec(set).map_err(|e| object_store::Error::Generic {
            store: "probes",
            source: format!("cannot encode the probes: {e}").into(),
        })?;
        state.artifacts.put(&store::probes_json(job), Bytes::from(json)).await?;
    }
    // Pages first, the manifest that lists them after, so a manifest never names a page
    // that is not stored.
    for page in &r.pages {
        state
            .artifacts
            .put(&store::page_exr(job, page.entry.page), Bytes::from(page.exr.clone()))
            .await?;
    }
    let manifest = serde_json::to_vec_pretty(&r.manifest).map_err(|e| object_store::Error::Generic {
        store: "manifest",
        source: format!("cannot encode lightmaps.json: {e}").into(),
    })?;
    state
        .artifacts
        .put(&store::manifest_json(job), Bytes::from(manifest))
        .await?;
    state
        .artifacts
        .put(&store::final_png(job), Bytes::from(r.preview_png.clone()))
        .await
}

/// A scene's stored files, ready for import on the bake thread.
pub enum SceneFiles {
    Glb(Bytes),
    /// The main .gltf's name and every file.
    Gltf(String, Vec<(String, Bytes)>),
}

/// Why a job's scene could not be loaded.
pub(crate) enum LoadError {
    /// It never will be (the scene is gone, the job is too big for this worker).
    Permanent(String),
    /// The database or the store did not answer: worth trying again.
    Transient(String),
}

/// How long a worker keeps trying to load a claimed job's scene through a database or
/// store outage (holding the lease) before it fails the job with the last error.
const SCENE_LOAD_PATIENCE: Duration = Duration::from_secs(60);

pub(crate) async fn load_scene(state: &AppState, job: &JobRecord) -> Result<SceneFiles, LoadError> {
    use LoadError::{Permanent, Transient};
    let scene_id = job.scene_id.as_str();
    let rec = match state.queue.scene(scene_id).await {
        Ok(Some(r)) => r,
        Ok(None) => return Err(Permanent(format!("scene {scene_id} no longer exists"))),
        Err(e) => return Err(Transient(format!("cannot read scene {scene_id}: {e}"))),
    };
    // A worker process may have less memory than the server that accepted the job.
    let need = job_memory(&rec.report, &job.spec);
    let limit = state.config.limits.max_job_memory_bytes;
    if need > limit {
        return Err(Permanent(format!(
            "the job needs an estimated {} MiB, more than this worker's limit of {} MiB (--max-job-memory-mb)",
            need >> 20,
            limit >> 20
        )));
    }
    let mut files = Vec::new();
    for f in &rec.files {
        match state.artifacts.get(&store::scene_file(scene_id, f)).await {
            Ok(Some(b)) => files.push((f.clone(), b)),
            Ok(None) => {
                return Err(Permanent(format!(
                    "scene {scene_id}: file {f} is missing from the store"
                )));
            }
            Err(e) => return Err(Transient(format!("scene {scene_id}: cannot read {f}: {e}"))),
        }
    }
    if rec.format == "glb" {
        let bytes = files.pop().map(|(_, b)| b).unwrap_or_default();
        Ok(SceneFiles::Glb(bytes))
    } else {
        Ok(SceneFiles::Gltf(rec.main_file, files))
    }
}

/// A job's reference lightmap as stored, or why there is none to compare with.
pub enum ReferenceFiles {
    None,
    /// The reference job and its final pages, in page order.
    Pages(String, Vec<Bytes>),
    /// The job named a reference that has gone since it was accepted (deleted, or swept
    /// by retention): the bake runs without a true-error curve, and its plan says why.
    Gone(String, String),
}

async fn load_reference(state: &AppState, job: &JobRecord) -> Result<ReferenceFiles, LoadError> {
    let Some(id) = job.spec.reference.clone() else {
        return Ok(ReferenceFiles::None);
    };
    let record = match state.queue.job(&id).await {
        Ok(Some(r)) if r.status == JobStatus::Succeeded => r,
        Ok(_) => return Ok(ReferenceFiles::Gone(id.clone(), format!("job {id} no longer exists"))),
        Err(e) => return Err(LoadError::Transient(format!("cannot read reference job {id}: {e}"))),
    };
    let mut pages = Vec::new();
    for p in store::job_pages(&record) {
        let mut got = state.artifacts.get(&store::page_exr(&id, p)).await;
        if p == 0 && matches!(got, Ok(None)) {
            got = state.artifacts.get(&store::legacy_final_exr(&id)).await;
        }
        match got {
            Ok(Some(b)) => pages.push(b),
            Ok(None) => {
                return Ok(ReferenceFiles::Gone(
                    id.clone(),
                    format!("page {p} of job {id} is no longer stored"),
                ));
            }
            Err(e) => {
                return Err(LoadError::Transient(format!(
                    "reference job {id}: cannot read page {p}: {e}"
                )));
            }
        }
    }
    Ok(ReferenceFiles::Pages(id, pages))
}

/// Why scene files did not import.
#[derive(Debug)]
pub enum ImportFailure {
    /// Over one of the server's caps: `what` is the importer's name for it.
    Limit { what: &'static str, detail: String },
    /// Anything else: the importer's message.
    Invalid(String),
}

impl std::fmt::Display for ImportFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ImportFailure::Limit { detail, .. } => f.write_str(detail),
            ImportFailure::Invalid(m) => f.write_str(m),
        }
    }
}

/// Imports scene files under the server's caps: a .glb from memory, a .gltf from a
/// temporary folder holding its files (the importer resolves relative URIs against a
/// folder; the names were checked to be plain file names when they were uploaded).
pub fn import_files(
    files: &SceneFiles,
    limits: &crate::service::Limits,
) -> Result<(Scene, scene::ImportReport), ImportFailure> {
    match files {
        SceneFiles::Glb(b) => {
            let caps = scene::ImportLimits {
                max_triangles: limits.max_triangles,
                max_texture_side: limits.max_texture_side,
            };
            scene::import_slice_limited(b, None, &caps).map_err(|e| match e {
                scene::ImportError::Limit { what, detail } => ImportFailure::Limit { what, detail },
                other => ImportFailure::Invalid(other.to_string()),
            })
        }
        SceneFiles::Gltf(main, parts) => {
            let dir = tempfile::tempdir()
                .map_err(|e| ImportFailure::Invalid(format!("cannot make a temporary folder: {e}")))?;
            for (name, bytes) in parts {
                std::fs::write(dir.path().join(name), bytes)
                    .map_err(|e| ImportFailure::Invalid(format!("cannot write {name}: {e}")))?;
            }
            import_dir(dir.path(), main, limits)
        }
    }
}

/// Imports a `.gltf` whose files are in `dir` (a spooled upload, `service::upload`),
/// under the server's limits; messages name files, not the folder.
pub fn import_dir(
    dir: &std::path::Path,
    main: &str,
    limits: &crate::service::Limits,
) -> Result<(Scene, scene::ImportReport), ImportFailure> {
    let caps = scene::ImportLimits {
        max_triangles: limits.max_triangles,
        max_texture_side: limits.max_texture_side,
    };
    let bytes =
        std::fs::read(dir.join(main)).map_err(|e| ImportFailure::Invalid(format!("cannot read {main}: {e}")))?;
    scene::import_slice_limited(&bytes, Some(dir), &caps).map_err(|e| match e {
        scene::ImportError::Limit { what, detail } => ImportFailure::Limit { what, detail },
        other => ImportFailure::Invalid(other.to_string().replace(&format!("{}/", dir.display()), "")),
    })
}

/// A job's estimated peak memory (`engine::footprint`) from its scene's import report.
pub fn job_memory(report: &Value, spec: &crate::service::model::JobSpec) -> u64 {
    let count = |k: &str| report.get(k).and_then(Value::as_u64).unwrap_or(0);
    let request = spec.to_request();
    let bake = crate::engine::footprint::estimate_bytes(&crate::engine::footprint::JobShape::new(
        count("triangles"),
        count("texture_texels"),
        spec.resolution,
        &request.outputs,
    ));
    // A reference's page is decoded into the grid (12 bytes a pixel) and picked per
    // texel (16 bytes) before the grid is freed: at most both at once.
    let page = spec.resolution as u64 * spec.resolution as u64;
    bake + if spec.reference.is_some() { 28 * page } else { 0 }
}

/// What the bake thread is given besides the job.
struct BakeThread {
    shared: Arc<Shared>,
    flag: Arc<StopFlag>,
    metrics: Arc<crate::service::metrics::Metrics>,
    /// Unused until a technique needs shared engine state; then handed to `job::bake`.
    #[allow(dead_code)]
    engine: Arc<EngineShared>,
    snapshots: mpsc::Sender<SnapshotFiles>,
    snapshot_interval: Duration,
    limits: crate::service::Limits,
}

/// A snapshot as the bake thread hands it to the encoder thread: the raw estimate.
struct RawSnapshot {
    atlas: Arc<Atlas>,
    estimate: crate::engine::accumulate::Estimate,
    elapsed: Duration,
}

/// The bake thread: import, bake with an observer that shares progress and hands
/// snapshots to an encoder thread, return the result.
///
/// Why a separate encoder: a snapshot is denoised (OIDN: three filters, seconds on a
/// loaded 2-core machine) and encoded twice (EXR, PNG). Done on the bake thread, that
/// time sits between two checks of the stop flag, so a cancel waited for it. The
/// encoder runs beside the bake; the channel holds one snapshot, and a snapshot due
/// while the encoder is still busy is skipped (the next one is due at once), so the
/// bake never waits for it. Once the stop flag is up the encoder drops what is pending.
fn run_bake(
    files: SceneFiles,
    reference: ReferenceFiles,
    spec: &crate::service::model::JobSpec,
    ctx: &BakeThread,
) -> Result<BakeResult, EngineError> {
    let (shared, flag, metrics, snapshots) = (&*ctx.shared, &*ctx.flag, &*ctx.metrics, &ctx.snapshots);
    let snapshot_interval = ctx.snapshot_interval;
    let (scene, _report) = import_files(&files, &ctx.limits).map_err(|e| EngineError::BadInput(e.to_string()))?;
    drop(files);
    // The reference is decoded before the bake; it is matched to the texel set once that
    // exists (`bake_observed`). One that cannot be used leaves the bake as it is.
    let reference = match reference {
        ReferenceFiles::None => None,
        ReferenceFiles::Gone(id, why) => Some((id, Err(why))),
        ReferenceFiles::Pages(id, pages) => {
            let decoded = ReferenceLightmap::from_pages(&pages).map_err(|e| format!("job {id}'s lightmap: {e}"));
            Some((id, decoded))
        }
    };
    let request = spec.to_request();
    let options = BakeOptions {
        snapshot_interval,
        max_memory_bytes: Some(ctx.limits.max_job_memory_bytes),
        step_progress: Some(shared.step.clone()),
        ..Default::default()
    };
    let (raw_tx, raw_rx) = std::sync::mpsc::sync_channel::<RawSnapshot>(1);
    std::thread::scope(|s| {
        let encoder = std::thread::Builder::new()
            .name("snapshot-encoder".into())
            .spawn_scoped(s, || encode_snapshots(raw_rx, &request, flag, snapshots, shared));
        if let Err(e) = encoder {
            return Err(EngineError::Internal(format!("cannot start the snapshot encoder: {e}")));
        }
        // `raw_tx` moves into the bake; dropping it at the end stops the encoder.
        let result = bake_observed(
            scene,
            reference,
            spec,
            &request,
            &options,
            shared,
            flag,
            metrics,
            raw_tx,
            snapshot_interval,
        );
        if let Ok(r) = &result
            && let Some(values) = shared.reference.get()
            && let Ok(mut e) = shared.final_true_error.lock()
        {
            *e = Some(relative_error(&r.estimate.total, values) as f32);
        }
        result
    })
}

/// Encodes the snapshots the bake hands over and passes them to the async side.
fn encode_snapshots(
    raw: std::sync::mpsc::Receiver<RawSnapshot>,
    request: &crate::engine::job::BakeRequest,
    flag: &StopFlag,
    snapshots: &mpsc::Sender<SnapshotFiles>,
    shared: &Shared,
) {
    for snap in raw {
        if flag.get() != StopSignal::None {
            continue;
        }
        // Denoised once: the EXR and the preview show the same delivered lightmap, and the
        // history and the status report its error (issue 22 point 4).
        let delivered = job::finish(&snap.atlas, &snap.estimate, request);
        let point = HistoryPoint {
            seconds: snap.elapsed.as_secs_f64(),
            steps: snap.estimate.steps,
            error: delivered.error.relative,
            raw_error: snap.estimate.error.relative,
            noise: delivered.error.noise,
            bias: delivered.error.bias,
            true_error: shared
                .reference
                .get()
                .map(|values| relative_error(&delivered.total, values) as f32),
        };
        if let Ok(mut h) = shared.history.lock()
            && h.len() < MAX_HISTORY
        {
            h.push(point);
        }
        if let Ok(mut e) = shared.delivered_error.lock() {
            *e = delivered.error.relative;
        }
        let exr = job::delivered_exr(&snap.atlas, &delivered, request, &request.params, snap.elapsed);
        let png = job::preview_png(&snap.atlas, &delivered);
        match (exr, png) {
            (Ok(exr), Ok(png)) => {
                // Waits while the previous one is being stored (this is a plain thread).
                let _ = snapshots.blocking_send(SnapshotFiles {
                    exr,
                    png,
                    steps: snap.estimate.steps,
                    error: delivered.error.relative,
                });
            }
            (Err(e), _) | (_, Err(e)) => tracing::error!(error = %e, "cannot encode a snapshot"),
        }
    }
}

/// [`job::bake`] with the service's observer: progress and history into `shared`,
/// snapshots to the encoder every `snapshot_interval`, the stop flag read after every
/// step.
#[allow(clippy::too_many_arguments)]
fn bake_observed(
    scene: Scene,
    mut reference: Option<(String, Result<ReferenceLightmap, String>)>,
    spec: &crate::service::model::JobSpec,
    request: &crate::engine::job::BakeRequest,
    options: &BakeOptions,
    shared: &Shared,
    flag: &StopFlag,
    metrics: &crate::service::metrics::Metrics,
    raw_tx: std::sync::mpsc::SyncSender<RawSnapshot>,
    snapshot_interval: Duration,
) -> Result<BakeResult, EngineError> {
    let atlas: OnceLock<Arc<Atlas>> = OnceLock::new();
    // The engine's plan (passes run and left out, with reasons) comes first; the texel
    // set is added to it once it is built.
    let mut on_plan = |plan: &Plan| {
        let mut v = serde_json::to_value(plan).unwrap_or_else(|_| json!({}));
        v["resolution"] = json!(request.resolution);
        if let Ok(mut p) = shared.plan.lock() {
            *p = Some(v);
        }
    };
    let mut on_atlas = |a: &Arc<Atlas>| {
        let _ = atlas.set(a.clone());
        if let Ok(mut p) = shared.plan.lock() {
            let plan = p.get_or_insert_with(|| json!({}));
            plan["texel_set"] = json!(a.report());
            plan["validation"] = json!(a.validation);
            // What the history's `true_error` is measured against, or why it is absent.
            // Taken: the decoded grid is freed once its valid texels are picked.
            if let Some((job, decoded)) = reference.take() {
                let matched = decoded.and_then(|r| Ok((r.reported_error, r.per_texel(a)?)));
                plan["reference"] = match matched {
                    Ok((error, values)) => {
                        let texels = values.iter().filter(|v| v.is_some()).count();
                        let _ = shared.reference.set(Arc::new(values));
                        json!({"job": job, "error": error, "texels": texels})
                    }
                    Err(why) => {
                        tracing::warn!(reference = %job, why, "the job's reference cannot be compared with");
                        json!({"job": job, "unavailable": why})
                    }
                };
            }
        }
        tracing::info!(texels = a.report().valid_texels, "texel set built");
    };
    let mut last_step_at = Duration::ZERO;
    let mut last_stored: Option<Duration> = None;
    let mut latest_error: Option<f32> = None;
    let mut observer = |e: BakeEvent<'_>| {
        match e {
            BakeEvent::GeneratedUvs { scene } => {
                if let Ok(mut g) = shared.generated_scene.lock() {
                    *g = Some(scene.clone());
                }
            }
            BakeEvent::Probes { steps, of, probes } => {
                if let Ok(mut p) = shared.progress.lock()
                    && let Some(p) = p.as_mut()
                {
                    p.probes = Some(ProbeProgress { steps, of, probes });
                }
            }
            BakeEvent::Progress { steps, elapsed, .. } => {
                metrics.observe_step(&request.technique, (elapsed - last_step_at).as_secs_f64());
                last_step_at = elapsed;
                if let Some(e) = shared.delivered_error.lock().ok().and_then(|e| *e) {
                    latest_error = Some(e);
                }
                if let Ok(mut p) = shared.progress.lock() {
                    *p = Some(Progress::new(steps, elapsed.as_secs_f64(), latest_error, &spec.stop));
                }
            }
            BakeEvent::Snapshot { estimate, elapsed } => {
                // The history and the status's error are the delivered (denoised)
                // lightmap's, which the encoder thread computes for the snapshots it
                // stores (`encode_snapshots`); until the first, the raw estimate's.
                let delivered = shared.delivered_error.lock().ok().and_then(|e| *e);
                latest_error = delivered.or(estimate.error.relative);
                if let Ok(mut p) = shared.progress.lock() {
                    *p = Some(Progress::new(
                        estimate.steps,
                        elapsed.as_secs_f64(),
                        latest_error,
                        &spec.stop,
                    ));
                }
                let due = last_stored.is_none_or(|t| elapsed >= t + snapshot_interval);
                if due
                    && flag.get() == StopSignal::None
                    && let Some(a) = atlas.get()
                {
                    match raw_tx.try_send(RawSnapshot {
                        atlas: a.clone(),
                        estimate: estimate.clone(),
                        elapsed,
                    }) {
                        Ok(()) => last_stored = Some(elapsed),
                        // The encoder is busy with the previous one: this one is skipped.
                        Err(std::sync::mpsc::TrySendError::Full(_)) => {}
                        Err(std::sync::mpsc::TrySendError::Disconnected(_)) => {
                            tracing::error!("the snapshot encoder has stopped")
                        }
                    }
                }
            }
        }
        if flag.get() == StopSignal::None {
            ControlFlow::Continue(())
        } else {
            ControlFlow::Break(())
        }
    };
    job::bake(
        Arc::new(scene),
        request,
        options,
        &mut observer,
        &mut on_atlas,
        &mut on_plan,
    )
}
