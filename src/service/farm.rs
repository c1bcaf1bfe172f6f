//! Workers' side of a job split into tasks (issue 25; docs/scaling.md): bake one task,
//! or merge them all.
//!
//! How: a worker that claims a bake task ([`Queue::claim_task`](crate::service::queue::Queue::claim_task)) loads the job's scene,
//! bakes the task's range of the job's steps of its region of the grid (the job's
//! `regions`) on a blocking thread (`engine::tasks::bake_task`: every random stream keyed
//! by the job's step numbers and the texels' pixels, so the task draws exactly the
//! samples a single bake draws at those steps and texels), and renews
//! the task's lease, at most once a second with its steps, bake time and own error estimate
//! (the queue folds them into the job's progress, `queue::merged_progress`). The result,
//! both halves' means and step counts and its texels' pixels (`engine::tasks::Partial`, 28
//! bytes a texel), goes
//! to the artifact store under `jobs/<id>/tasks/<k>.lmtask` *before* the task is marked
//! succeeded, so a succeeded task's result is always stored. The last bake task to
//! succeed queues the merge; the worker that claims it reads every result, merges the
//! halves (`engine::tasks::merge`: per region the sums of the halves over the sums of
//! their steps, the regions' texels side by side, then the single bake's own finish: error estimate from the merged halves,
//! denoiser, EXR pages, preview, probes), stores the final artifacts like a whole job's,
//! and only then marks the job `succeeded`; the task results are deleted after that.
//!
//! A job in rounds (`JobSpec::rounds`, `engine::rounds`): bake task r P + p bakes region
//! p in round r (`rounds::bake_round_task`), reading every region's result of round r-1
//! from the store (`tasks/<k>.lmtask`, the held light and its own accumulators); the
//! queue queues a round once the round before has succeeded, and the merge reads the last
//! round's results. Rounds before the last state no error: a round's halves cannot see
//! what the rounds still lack, which only the last round's control texels measure. The
//! job's snapshots are its finished rounds, each stating no error (`round_snapshot`).
//!
//! Endings of an attempt: cancelled (the job's cancel flag, read back by every
//! heartbeat) → the task `cancelled`, and the last task to stop ends the job; shutdown
//! → handed back, the attempt not counted; a lost lease → nothing written; an engine
//! error → bad input fails the job at once (every worker would meet it), anything else
//! counts against this worker and the task is tried again, elsewhere once this worker is
//! blocklisted (`queue::BLOCKLIST_AFTER`), up to `queue::MAX_ATTEMPTS` attempts.
//!
//! History: while the tasks run, the queue appends the job's merged progress to its
//! history (`queue::running_history`: the tasks' raw estimates merged, a point when the
//! steps grew by a quarter or every five seconds) until the first running snapshot is
//! stored; from then on each running snapshot adds its point, the delivered error of
//! what it holds, as a single bake's snapshots do; the merge's point, the delivered
//! lightmap's error, ends it.
//!
//! Snapshots while the tasks run: each task stores its halves so far at its snapshots
//! (`tasks/<k>.live.lmtask`), and the task whose turn the queue gives (one a snapshot
//! interval for the job) merges every task's halves so far
//! (`engine::tasks::merge_running`; a region split's on the whole texel set, which that
//! task builds once), denoises and stores them as the job's next snapshot, as a whole
//! job's (`running_snapshots`).
//!
//! Limits: a region split's snapshots wait until every region has halves (with fewer
//! workers than regions, until the last region's task starts), and a task whose worker
//! cannot hold the whole texel set (its memory limit) makes none; the merge re-imports the
//! scene and reads all results into memory (28 bytes a texel a task: 470 MB a task for a
//! full 4096² page, a region's task only its region's texels), so it needs that memory
//! once.

use std::ops::ControlFlow;
use std::ops::Range;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use bytes::Bytes;
use serde_json::{Value, json};
use tracing::Instrument;

use crate::engine::atlas::Atlas;
use crate::engine::bake::{BakeEvent, StepProgress, StopReason};
use crate::engine::job::{self, BakeOptions, BakeRequest};
use crate::engine::plan::Plan;
use crate::engine::rounds;
use crate::engine::scene::Scene;
use crate::engine::tasks::{self, Partial};
use crate::engine::technique::EngineError;
use crate::service::model::{HistoryPoint, Progress};
use crate::service::queue::{JobRecord, Lease, TaskBeat, TaskOutcome, TaskRecord};
use crate::service::worker::{
    Lessee, LoadError, SnapshotFiles, TICK, import_files, load_patiently, load_scene, store_final, store_snapshot,
    thin_snapshots, while_holding,
};
use crate::service::{AppState, StopFlag, StopSignal, shutting_down, store};

/// The shortest time between two progress heartbeats of one task.
const PROGRESS_PERIOD: Duration = Duration::from_secs(1);

enum End {
    Finish(TaskOutcome),
    Release,
    Lost,
}

/// Runs a claimed task to its end and records the end (retried through a database
/// hiccup while the lease is ours, as a whole job's end is).
pub async fn run_task(state: &AppState, worker: &str, task: TaskRecord, job: JobRecord) {
    tracing::info!(attempt = task.attempts, merge = task.is_merge(), "task claimed");
    state.hub.job_changed(&job.id);
    state.metrics.busy.fetch_add(1, Ordering::Relaxed);
    let flag = Arc::new(StopFlag::default());
    let end = if task.is_merge() {
        merge(state, worker, &task, &job, &flag).await
    } else {
        bake(state, worker, &task, &job, &flag).await
    };
    state.metrics.busy.fetch_sub(1, Ordering::Relaxed);
    let lessee = Lessee::Task(&job.id, task.index);
    let written = match end {
        End::Lost => {
            tracing::warn!("lease lost: another worker owns the task now; nothing written");
            Ok(true)
        }
        End::Release => {
            tracing::info!("shutting down: task handed back to the queue");
            state
                .queue
                .release_task(&job.id, task.index, worker, state.db_now())
                .await
        }
        End::Finish(outcome) => {
            if let TaskOutcome::Failed { reason, retry } = &outcome {
                tracing::warn!(reason = %reason, retry, "task failed");
            }
            let first_try = Instant::now();
            let mut wait = Duration::from_millis(100);
            loop {
                let finish = state
                    .queue
                    .finish_task(&job.id, task.index, worker, &outcome, state.db_now());
                match while_holding(state, lessee, worker, &flag, finish).await {
                    Err(e)
                        if flag.get() != StopSignal::LeaseLost
                            && first_try.elapsed() + wait < state.config.database_timeout =>
                    {
                        tracing::warn!(error = %e, retry_in_ms = wait.as_millis() as u64, "cannot record the end of the task; trying again");
                        tokio::time::sleep(wait).await;
                        wait = (wait * 2).min(Duration::from_secs(2));
                    }
                    r => break r,
                }
            }
        }
    };
    match &written {
        Ok(true) => tracing::info!("task ended"),
        Ok(false) => tracing::warn!("the task was no longer ours when it ended (lease expired); result dropped"),
        Err(e) => {
            tracing::error!(error = %e, "cannot record the end of the task; its lease will expire and it runs again")
        }
    }
    state.hub.job_changed(&job.id);
    // The merge's job is over; so is every partial it read.
    if task.is_merge() && matches!(written, Ok(true)) {
        for k in 0..task.count {
            if let Err(e) = state.artifacts.delete(&store::task_partial(&job.id, k)).await {
                tracing::warn!(task = k, error = %e, "cannot delete a merged task's result");
            }
            if let Err(e) = state.artifacts.delete(&store::task_live(&job.id, k)).await {
                tracing::warn!(task = k, error = %e, "cannot delete a merged task's running halves");
            }
        }
    }
}

/// The failure of an engine call: bad input fails the job, anything else is retried.
fn failed(e: EngineError) -> End {
    let retry = !e.is_bad_input();
    End::Finish(TaskOutcome::Failed {
        reason: if retry {
            e.to_string()
        } else {
            format!("bad input: {e}")
        },
        retry,
    })
}

/// Bakes one task and stores its result.
async fn bake(state: &AppState, worker: &str, task: &TaskRecord, job: &JobRecord, flag: &Arc<StopFlag>) -> End {
    let lessee = Lessee::Task(&job.id, task.index);
    let request = job.spec.task_request();
    let range = match job.spec.task_ranges().map(|r| r.get(task.index as usize).copied()) {
        Ok(Some(r)) => r,
        Ok(None) => {
            return failed(EngineError::BadInput(format!(
                "the job has no bake task {}",
                task.index
            )));
        }
        Err(e) => return failed(e),
    };
    // A task of round r > 0 reads every region's result of round r-1 (the held light).
    let before = if range.rounds > 0 && range.round > 0 {
        let per_round = range.regions;
        (range.round - 1) * per_round..range.round * per_round
    } else {
        0..0
    };
    // Its own region's result whole (the halves it resumes), the others' pixels and held
    // light only (region 0's round snapshot reads every result whole itself, below, once
    // the queue has given it the snapshot).
    let whole = |k: u32| k % range.regions.max(1) == range.region;
    let load = || async {
        Ok::<_, LoadError>((
            load_scene(state, job).await?,
            load_round_before(state, job, before.clone(), whole).await?,
        ))
    };
    let (files, previous) = match load_patiently(state, lessee, worker, flag, load).await {
        Ok(f) => f,
        Err(None) => return End::Lost,
        Err(Some(reason)) => return End::Finish(TaskOutcome::Failed { reason, retry: true }),
    };
    // Region 0's task of each round after the first shows the round before as the job's
    // next snapshot, beside its own bake, on the whole texel set the bake thread has
    // prepared anyway (handed over once the grid is prepared).
    let (mut shot_tx, round_shot) = if range.rounds > 0 && range.round > 0 && range.region == 0 {
        let (tx, rx) = tokio::sync::oneshot::channel::<Arc<Atlas>>();
        let shot = round_snapshot(
            state.clone(),
            worker.to_string(),
            job.clone(),
            task.clone(),
            before.clone(),
            rx,
        );
        (Some(tx), Some(tokio::spawn(shot.instrument(tracing::Span::current()))))
    } else {
        (None, None)
    };
    let beat = Arc::new(Mutex::new(TaskBeat::default()));
    let step = StepProgress::default();
    // The job's snapshots while it runs: this task's halves so far go to the store and,
    // on this task's turn, the tasks' halves merged become the next snapshot.
    let (live_tx, live_rx) = tokio::sync::mpsc::channel::<Partial>(1);
    let live = Arc::new(Live::default());
    let snapshots = tokio::spawn(
        running_snapshots(
            state.clone(),
            worker.to_string(),
            job.clone(),
            task.clone(),
            live_rx,
            live.clone(),
            flag.clone(),
        )
        .instrument(tracing::Span::current()),
    );
    let every = state.config.snapshot_interval;
    let thread = {
        let (beat, flag, step, limits) = (beat.clone(), flag.clone(), step.clone(), state.config.limits.clone());
        let span = tracing::Span::current();
        tokio::task::spawn_blocking(move || {
            let _e = span.enter();
            let (scene, _) = import_files(&files, &limits).map_err(|e| EngineError::BadInput(e.to_string()))?;
            drop(files);
            let previous: Vec<Partial> = previous
                .into_iter()
                .zip(before)
                .map(|(b, k)| b.decode(&format!("task {k}'s result")))
                .collect::<Result<_, _>>()?;
            let options = BakeOptions {
                // Snapshots are not stored; they only refresh the task's error estimate.
                snapshot_interval: Duration::from_secs(1),
                max_memory_bytes: Some(limits.max_job_memory_bytes),
                step_progress: Some(step),
                ..Default::default()
            };
            let mut observer = |e: BakeEvent<'_>| {
                if let Ok(mut b) = beat.lock() {
                    match e {
                        BakeEvent::Progress { steps, elapsed, .. } => {
                            b.steps = steps;
                            b.seconds = elapsed.as_secs_f64();
                        }
                        BakeEvent::Snapshot { estimate, elapsed } => {
                            b.steps = estimate.steps;
                            b.seconds = elapsed.as_secs_f64();
                            b.error = estimate.error.relative;
                        }
                        _ => {}
                    }
                }
                if flag.get() == StopSignal::None {
                    ControlFlow::Continue(())
                } else {
                    ControlFlow::Break(())
                }
            };
            let scene = Arc::new(scene);
            let _ = live.scene.set(scene.clone());
            // Halves due while the last are still being stored or merged (a full
            // channel), or within the quiet time the last ones earned, are skipped.
            let sink = {
                let live = live.clone();
                tasks::LiveTask {
                    every,
                    sink: Box::new(move |p: Partial| {
                        let quiet = live.quiet_until.lock().ok().and_then(|q| *q);
                        if quiet.is_none_or(|t| Instant::now() >= t) {
                            let _ = live_tx.try_send(p);
                        }
                    }),
                }
            };
            let partial = if range.rounds > 0 {
                // A round task's halves are not handed on while it runs (a round's estimate
                // states no error, below): the job's snapshots are the finished rounds.
                drop(sink);
                let mut on_atlas = |a: &Arc<Atlas>| {
                    if let Some(tx) = shot_tx.take() {
                        let _ = tx.send(a.clone());
                    }
                };
                rounds::bake_round_task(
                    scene,
                    &request,
                    range,
                    &previous,
                    &options,
                    &mut observer,
                    &mut on_atlas,
                )?
            } else {
                tasks::bake_task_live(
                    scene,
                    &request,
                    range,
                    &options,
                    &mut observer,
                    &mut |a| {
                        let _ = live.atlas.set(a.clone());
                    },
                    &mut |_| {},
                    Some(sink),
                )?
            };
            // Encoded here, off the runtime: a full page's result is hundreds of MB.
            // A round before the last states no error: its halves' difference cannot see
            // the light the held regions still lack (the rounds' lag), which only the
            // last round's control texels measure (`engine::rounds`), so the job's error
            // stays unknown until then rather than understated.
            let error = if range.rounds > 0 && range.round + 1 < range.rounds {
                None
            } else {
                partial.snapshot.estimate().error.relative
            };
            let bytes = partial.encode()?;
            Ok::<_, EngineError>((partial.header, error, bytes))
        })
    };
    tokio::pin!(thread);
    let mut ticker = tokio::time::interval(TICK);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut shutdown = state.shutdown.clone();
    let mut stopping = false;
    let mut written = TaskBeat::default();
    let mut last_renewal = Instant::now();
    let result = loop {
        tokio::select! {
            r = &mut thread => break r,
            _ = ticker.tick() => {
                if flag.get() != StopSignal::None {
                    step.request_stop();
                }
                let now_beat = beat.lock().map(|b| *b).unwrap_or_default();
                // Progress at most once a second: every progress beat rewrites the job's
                // merged progress under the job's lock, so its rate is what limits how
                // many workers one job can have (docs/scaling.md, "A farm model").
                let changed = now_beat != written && last_renewal.elapsed() >= PROGRESS_PERIOD;
                if (changed || last_renewal.elapsed() >= state.config.lease / 3) && flag.get() != StopSignal::LeaseLost {
                    let update = changed.then_some(&now_beat);
                    match state.queue.task_heartbeat(&job.id, task.index, worker, state.config.lease, update, state.db_now()).await {
                        Ok(Lease::Held { cancel }) => {
                            last_renewal = Instant::now();
                            written = now_beat;
                            if cancel {
                                flag.set(StopSignal::Cancel);
                            }
                            if changed {
                                state.hub.job_changed(&job.id);
                            }
                        }
                        Ok(Lease::Lost) => flag.set(StopSignal::LeaseLost),
                        Err(e) => tracing::warn!(error = %e, "task heartbeat failed"),
                    }
                }
            }
            _ = shutting_down(&mut shutdown), if !stopping => {
                stopping = true;
                flag.set(StopSignal::Shutdown);
            }
        }
    };
    // The bake has ended: a running snapshot in hand is finished (the lease renewed
    // meanwhile), unless the task is stopping.
    if flag.get() == StopSignal::None {
        let _ = while_holding(state, lessee, worker, flag, snapshots).await;
        if let Some(shot) = round_shot {
            let _ = while_holding(state, lessee, worker, flag, shot).await;
        }
    } else {
        snapshots.abort();
        if let Some(shot) = round_shot {
            shot.abort();
        }
    }
    let (header, error, bytes) = match (flag.get(), result) {
        (StopSignal::LeaseLost, _) => return End::Lost,
        (_, Err(e)) => {
            return End::Finish(TaskOutcome::Failed {
                reason: format!("the bake thread panicked: {e}"),
                retry: true,
            });
        }
        (_, Ok(Err(e))) => return failed(e),
        (why, Ok(Ok((h, _, _)))) if h.stopped_by == StopReason::Cancelled => {
            return if why == StopSignal::Shutdown {
                End::Release
            } else {
                End::Finish(TaskOutcome::Cancelled)
            };
        }
        (_, Ok(Ok(r))) => r,
    };
    let steps = header.half_steps[0] + header.half_steps[1];
    tracing::info!(
        steps,
        seconds = header.seconds,
        error,
        bytes = bytes.len(),
        "task baked"
    );
    state.metrics.observe_bake(&job.spec.technique, header.seconds);
    let path = store::task_partial(&job.id, task.index);
    let put = state.artifacts.put(&path, Bytes::from(bytes));
    if let Err(e) = while_holding(state, lessee, worker, flag, put).await {
        return End::Finish(TaskOutcome::Failed {
            reason: format!("cannot store the task's result: {e}"),
            retry: true,
        });
    }
    End::Finish(TaskOutcome::Baked(TaskBeat {
        steps,
        seconds: header.seconds,
        error,
    }))
}

/// What a task's running snapshots share with its bake thread.
#[derive(Default)]
struct Live {
    /// The task's own texel set (with one region, the whole grid's).
    atlas: OnceLock<Arc<Atlas>>,
    /// The scene as the task imported it: a region split's whole texel set is built
    /// from it.
    scene: OnceLock<Arc<Scene>>,
    /// No halves are handed on before this ([`running_snapshots`]' cost).
    quiet_until: Mutex<Option<Instant>>,
}

/// The whole grid's texel set a task's running snapshots are made on, and each
/// region's range of its texels.
enum Whole {
    /// Not yet known: with one region the task's own; with several, built once every
    /// region has halves (`tasks::running_atlas`).
    Unknown,
    Ready(Arc<Atlas>, Arc<Vec<Range<usize>>>),
    /// Refused (over this worker's memory limit): this task makes no snapshots.
    Refused,
}

/// A split job's snapshots while its tasks run (issue 25 point 2): each of this task's
/// running halves (`engine::tasks::bake_task_live`) is stored as `tasks/<k>.live.lmtask`;
/// then, when the queue gives this task the job's next snapshot
/// ([`Queue::claim_task_snapshot`](crate::service::queue::Queue::claim_task_snapshot):
/// one a snapshot interval for the whole job, whichever task asks first), every task's
/// halves (a finished task's result, a running one's latest halves, none for one not
/// started) are merged (`tasks::merge_running`), denoised and encoded as a whole job's
/// snapshot is, stored under that number and recorded; a claim that comes to nothing is
/// handed back, so the numbers have no gaps. Ends when the bake drops its sender.
///
/// A job split into regions needs the whole grid's texel set for its snapshots, which a
/// region's task does not hold: the task builds it once, when every region has halves,
/// from the regions' kept texels (`tasks::running_atlas`: the merge's preparation, no
/// validation rays), unless it needs more than this worker's memory limit; then this
/// task makes none.
///
/// What it costs: each round moves this task's halves to the store (28 bytes a texel),
/// and a snapshot's maker reads every task's (N × 28 bytes a texel), merges and denoises
/// them: nothing on a small level, seconds on a 4096² page. So a round that took d keeps
/// the next one off for 9 d (`quiet_until`, read by the bake's sink): this work takes at
/// most a tenth of the task's wall time, on top of the snapshot interval.
async fn running_snapshots(
    state: AppState,
    worker: String,
    job: JobRecord,
    task: TaskRecord,
    mut halves: tokio::sync::mpsc::Receiver<Partial>,
    live: Arc<Live>,
    flag: Arc<StopFlag>,
) {
    let request = Arc::new(job.spec.to_request());
    let mut whole = Whole::Unknown;
    while let Some(own) = halves.recv().await {
        if flag.get() != StopSignal::None {
            return;
        }
        let began = Instant::now();
        let round = Round {
            state: &state,
            worker: &worker,
            job: &job,
            task: &task,
            live: &live,
            request: &request,
        };
        round.run(own, &mut whole).await;
        let took = began.elapsed();
        if let Ok(mut q) = live.quiet_until.lock() {
            *q = Some(Instant::now() + took * 9);
        }
    }
}

/// One round of [`running_snapshots`].
struct Round<'a> {
    state: &'a AppState,
    worker: &'a str,
    job: &'a JobRecord,
    task: &'a TaskRecord,
    live: &'a Arc<Live>,
    request: &'a Arc<BakeRequest>,
}

impl Round<'_> {
    /// Stores this task's halves, and makes the job's next snapshot when it is this
    /// task's turn.
    async fn run(&self, own: Partial, whole: &mut Whole) {
        let (state, job, task) = (self.state, self.job, self.task);
        let began = Instant::now();
        let encoded = tokio::task::spawn_blocking(move || {
            let bytes = own.encode();
            (own, bytes)
        })
        .await;
        let (own, bytes) = match encoded {
            Ok((own, Ok(bytes))) => (own, bytes),
            Ok((_, Err(e))) => {
                tracing::warn!(error = %e, "cannot encode the task's running halves");
                return;
            }
            Err(e) => {
                tracing::warn!(error = %e, "the encoder of the task's running halves panicked");
                return;
            }
        };
        let path = store::task_live(&job.id, task.index);
        if let Err(e) = state.artifacts.put(&path, Bytes::from(bytes)).await {
            tracing::warn!(error = %e, "cannot store the task's running halves");
            return;
        }
        if matches!(whole, Whole::Refused) {
            return;
        }
        let Some(n) = claim_snapshot(state, job, task, self.worker).await else {
            return;
        };
        let (files, point) = match self.snapshot(own, whole).await {
            Ok(f) => f,
            Err(e) => {
                tracing::info!(snapshot = n, why = %e, "no running snapshot this time");
                if let Err(e) = state.queue.release_task_snapshot(&job.id, n).await {
                    tracing::warn!(snapshot = n, error = %e, "cannot hand back the snapshot's number");
                }
                return;
            }
        };
        store_claimed(state, job, n, files, point, began).await;
    }

    /// The job's snapshot from every task's halves so far, this task's `own` among
    /// them; builds the whole texel set into `whole` when it needs it and can.
    async fn snapshot(&self, own: Partial, whole: &mut Whole) -> Result<(SnapshotFiles, HistoryPoint), String> {
        let (state, job, task) = (self.state, self.job, self.task);
        let mut others = Vec::new();
        for k in (0..task.count).filter(|k| *k != task.index) {
            let mut found = None;
            for path in [store::task_partial(&job.id, k), store::task_live(&job.id, k)] {
                match state.artifacts.get(&path).await {
                    Ok(Some(b)) => {
                        found = Some(b);
                        break;
                    }
                    Ok(None) => {}
                    Err(e) => return Err(format!("cannot read task {k}'s halves: {e}")),
                }
            }
            others.extend(found.map(|b| (k, b)));
        }
        let elapsed = job
            .started_at
            .map_or(0.0, |t| (state.db_now() - t).max(0) as f64 / 1000.0);
        let ready = match whole {
            Whole::Ready(a, r) => Some((a.clone(), r.clone())),
            Whole::Unknown if task_regions(job) <= 1 => {
                let a = self
                    .live
                    .atlas
                    .get()
                    .cloned()
                    .ok_or("the task's texel set is not built yet")?;
                // One region: the whole grid's texels.
                let r = Arc::new(std::iter::once(0..a.texels.len()).collect::<Vec<_>>());
                *whole = Whole::Ready(a.clone(), r.clone());
                Some((a, r))
            }
            _ => None,
        };
        let scene = self.live.scene.get().cloned();
        let (request, limit) = (self.request.clone(), state.config.limits.max_job_memory_bytes);
        let made = tokio::task::spawn_blocking(move || {
            let mut parts = vec![own];
            for (k, b) in others {
                parts.push(Partial::decode(&b, &format!("task {k}'s halves")).map_err(|e| (e, false))?);
            }
            let (atlas, regions, built) = match ready {
                Some((a, r)) => (a, r, false),
                None => {
                    let scene = scene.ok_or_else(|| (EngineError::Internal("no scene yet".into()), false))?;
                    let options = BakeOptions {
                        max_memory_bytes: Some(limit),
                        ..Default::default()
                    };
                    // Only a region without halves yet is worth trying again.
                    let (a, r) = tasks::running_atlas(scene, &parts, &options).map_err(|e| {
                        let again = e.to_string().contains("has no halves yet");
                        (e, !again)
                    })?;
                    (a, Arc::new(r), true)
                }
            };
            let made = snapshot_files(&atlas, &regions, &parts, &request, elapsed, true).map_err(|e| (e, false))?;
            Ok::<_, (EngineError, bool)>((made, built.then_some((atlas, regions))))
        });
        match made.await {
            Ok(Ok((files, built))) => {
                if let Some((a, r)) = built {
                    *whole = Whole::Ready(a, r);
                }
                Ok(files)
            }
            Ok(Err((e, refused))) => {
                if refused {
                    tracing::warn!(error = %e, "no running snapshots from this task: the whole texel set cannot be built here");
                    *whole = Whole::Refused;
                }
                Err(e.to_string())
            }
            Err(e) => Err(format!("the snapshot thread panicked: {e}")),
        }
    }
}

/// A running snapshot's files and history point from task halves `parts` on the whole
/// texel set (`atlas`, each region's range `regions`): merged (`tasks::merge_running`),
/// denoised and encoded as a whole job's snapshot. `stated` false leaves its error out
/// (the EXR header, the files and the point say nothing rather than the halves' noise).
fn snapshot_files(
    atlas: &Atlas,
    regions: &[Range<usize>],
    parts: &[Partial],
    request: &BakeRequest,
    elapsed: f64,
    stated: bool,
) -> Result<(SnapshotFiles, HistoryPoint), EngineError> {
    let estimate = tasks::merge_running(atlas, regions, parts)?;
    let mut delivered = job::finish(atlas, &estimate, request);
    if !stated {
        let e = &mut delivered.error;
        (e.relative, e.noise, e.bias, e.interval, e.raw_relative) = (None, None, None, None, None);
    }
    let exr = job::delivered_exr(
        atlas,
        &delivered,
        request,
        &request.params,
        Duration::from_secs_f64(elapsed),
    )?;
    let png = job::preview_png(atlas, &delivered)?;
    let files = SnapshotFiles {
        exr,
        png,
        steps: estimate.steps,
        error: delivered.error.relative,
    };
    // The history's point for this snapshot, as a single bake's: the delivered error,
    // with the raw one beside it (`seconds` is set when it is stored).
    let e = &delivered.error;
    let point = HistoryPoint {
        seconds: elapsed,
        steps: estimate.steps,
        error: e.relative,
        raw_error: e.raw_relative.or(e.relative),
        noise: e.noise,
        bias: e.bias,
        true_error: None,
    };
    Ok((files, point))
}

/// The job's next snapshot number when it is `task`'s turn to make it
/// ([`Queue::claim_task_snapshot`](crate::service::queue::Queue::claim_task_snapshot)),
/// else `None` (a database error is logged, and costs only this snapshot).
async fn claim_snapshot(state: &AppState, job: &JobRecord, task: &TaskRecord, worker: &str) -> Option<u32> {
    let claim = state.queue.claim_task_snapshot(
        &job.id,
        task.index,
        worker,
        state.config.snapshot_interval,
        state.db_now(),
    );
    claim
        .await
        .inspect_err(|e| tracing::warn!(error = %e, "cannot claim the job's next snapshot"))
        .ok()
        .flatten()
}

/// Stores the job's claimed snapshot `n` and records it with its history point, or hands
/// the number back when it cannot be stored; a job that ended meanwhile keeps its final
/// lightmap, and the snapshot's files go.
async fn store_claimed(
    state: &AppState,
    job: &JobRecord,
    n: u32,
    files: SnapshotFiles,
    mut point: HistoryPoint,
    began: Instant,
) {
    let (steps, error) = (files.steps, files.error);
    if let Err(e) = store_snapshot(state, &job.id, n, files).await {
        tracing::warn!(snapshot = n, error = %e, "cannot store the job's running snapshot");
        let _ = state.queue.release_task_snapshot(&job.id, n).await;
        return;
    }
    // On the running history's clock: wall time since the job started, when stored.
    if let Some(t) = job.started_at {
        point.seconds = (state.db_now() - t).max(0) as f64 / 1000.0;
    }
    let point = serde_json::to_value(point).unwrap_or(Value::Null);
    match state.queue.task_snapshot_stored(&job.id, n, &point).await {
        Ok(true) => {
            let seconds = began.elapsed().as_secs_f64();
            tracing::info!(snapshot = n, steps, error, seconds, "running snapshot stored");
            thin_snapshots(state, &job.id, n).await;
            state.hub.job_changed(&job.id);
        }
        // The job ended meanwhile: its final lightmap is what it keeps.
        Ok(false) | Err(_) => {
            let _ = state.artifacts.delete(&store::snapshot_exr(&job.id, n)).await;
            let _ = state.artifacts.delete(&store::snapshot_png(&job.id, n)).await;
        }
    }
}

/// A job in rounds' snapshot of the round before `task`'s (round r-1's results, every
/// region's), made by region 0's task of round r when the queue gives it the job's next
/// snapshot ([`Queue::claim_task_snapshot`](crate::service::queue::Queue::claim_task_snapshot)):
/// the results (tasks `results`, read whole here once the snapshot is claimed: the bake
/// reads only its own region's halves) merged on the whole texel set the task's bake
/// prepared (`atlas`, sent once it is), denoised and stored as a running snapshot. It states **no error**: a round's
/// halves cannot see the light the rounds still lack (module doc), so its EXR header, its
/// files and its history point say nothing rather than understate. Runs beside the task's
/// bake; a failure costs only the snapshot.
async fn round_snapshot(
    state: AppState,
    worker: String,
    job: JobRecord,
    task: TaskRecord,
    results: Range<u32>,
    atlas: tokio::sync::oneshot::Receiver<Arc<Atlas>>,
) {
    // The bake thread drops the sender without sending when it fails before its grid.
    let Ok(atlas) = atlas.await else {
        return;
    };
    let Some(n) = claim_snapshot(&state, &job, &task, &worker).await else {
        return;
    };
    let bytes = match load_partials(&state, &job, results.clone()).await {
        Ok(b) => b,
        Err(LoadError::Permanent(e) | LoadError::Transient(e)) => {
            tracing::info!(snapshot = n, why = %e, "no snapshot of the round before");
            let _ = state.queue.release_task_snapshot(&job.id, n).await;
            return;
        }
    };
    let began = Instant::now();
    let elapsed = job
        .started_at
        .map_or(0.0, |t| (state.db_now() - t).max(0) as f64 / 1000.0);
    let request = job.spec.task_request();
    let made = tokio::task::spawn_blocking(move || {
        let results: Vec<Partial> = bytes
            .iter()
            .zip(results)
            .map(|(b, k)| Partial::decode(b, &format!("task {k}'s result")))
            .collect::<Result<_, _>>()?;
        drop(bytes);
        // The grid holds the regions' texels one after another, in region order (the
        // merge checks each region's fingerprint against its range).
        let mut at = 0;
        let regions: Vec<Range<usize>> = results
            .iter()
            .map(|p| {
                let r = at..at + p.header.texels as usize;
                at = r.end;
                r
            })
            .collect();
        snapshot_files(&atlas, &regions, &results, &request, elapsed, false)
    })
    .await;
    match made {
        Ok(Ok((files, point))) => store_claimed(&state, &job, n, files, point, began).await,
        Ok(Err(e)) => {
            tracing::info!(snapshot = n, why = %e, "no snapshot of the round before");
            let _ = state.queue.release_task_snapshot(&job.id, n).await;
        }
        Err(e) => {
            tracing::warn!(snapshot = n, error = %e, "the round snapshot's thread panicked");
            let _ = state.queue.release_task_snapshot(&job.id, n).await;
        }
    }
}

/// The regions a job's grid is split into.
fn task_regions(job: &JobRecord) -> u32 {
    job.spec.regions.unwrap_or(1)
}

/// The stored results of bake tasks `indices`, in task order.
async fn load_partials(state: &AppState, job: &JobRecord, indices: Range<u32>) -> Result<Vec<Bytes>, LoadError> {
    let mut out = Vec::with_capacity(indices.len());
    for k in indices {
        match state.artifacts.get(&store::task_partial(&job.id, k)).await {
            Ok(Some(b)) => out.push(b),
            // Marked succeeded only after it was stored: a missing one was deleted.
            Ok(None) => {
                return Err(LoadError::Permanent(format!(
                    "task {k}'s result is no longer stored (jobs/{}/tasks/{k}.lmtask)",
                    job.id
                )));
            }
            Err(e) => return Err(LoadError::Transient(format!("cannot read task {k}'s result: {e}"))),
        }
    }
    Ok(out)
}

/// One region's result of the round before, as a round task fetched it.
enum Fetched {
    Whole(Bytes),
    /// The layout, pixels and held light (`Partial::decode_held`): 16 bytes a texel of
    /// the 40 a whole round result holds (64 with the `direct` layer).
    Held {
        layout: Box<tasks::PartialLayout>,
        pixels: Bytes,
        held: Bytes,
    },
}

impl Fetched {
    fn decode(self, what: &str) -> Result<Partial, EngineError> {
        match self {
            Fetched::Whole(b) => Partial::decode(&b, what),
            Fetched::Held { layout, pixels, held } => Partial::decode_held(*layout, &pixels, &held, what),
        }
    }

    /// The bytes fetched, the header's included.
    fn len(&self) -> u64 {
        match self {
            Fetched::Whole(b) => b.len() as u64,
            Fetched::Held { layout, pixels, held } => layout.halves.start + (pixels.len() + held.len()) as u64,
        }
    }
}

/// The results `indices` of the round before a round task's: whole where `whole(k)`
/// holds, else their layout, pixels and held light alone ([`held_parts`]). A result whose
/// parts cannot be read so (missing, damaged, a short read, a store error) is read whole
/// instead, so that what goes wrong is classified as for any result: a missing or
/// unreadable object by [`load_partials`], a damaged one by its decode in the bake thread
/// (bad input: the job fails, as before the parts were read apart).
async fn load_round_before(
    state: &AppState,
    job: &JobRecord,
    indices: Range<u32>,
    whole: impl Fn(u32) -> bool,
) -> Result<Vec<Fetched>, LoadError> {
    let mut out = Vec::with_capacity(indices.len());
    for k in indices.clone() {
        if !whole(k) {
            let key = store::task_partial(&job.id, k);
            match held_parts(&state.artifacts, &key).await {
                Ok(parts) => {
                    out.push(parts);
                    continue;
                }
                Err(why) => tracing::info!(task = k, why, "reading the result whole"),
            }
        }
        let mut b = load_partials(state, job, k..k + 1).await?;
        out.push(Fetched::Whole(b.remove(0)));
    }
    let read: u64 = out.iter().map(Fetched::len).sum();
    tracing::info!(
        results = indices.len(),
        whole = out.iter().filter(|f| matches!(f, Fetched::Whole(_))).count(),
        bytes = read,
        "round before read"
    );
    Ok(out)
}

/// One round result's layout, pixels and held light, in three ranged reads: the first
/// 16 bytes (which give the header's length, and the object's size), the header, then
/// the two parts (side by side in a round result, so object_store joins them into one
/// request). The object's size and every part's length are checked against the header;
/// any trouble is returned as a reason, for the caller to read the result whole.
async fn held_parts(artifacts: &store::Artifacts, key: &object_store::path::Path) -> Result<Fetched, String> {
    let store = |e: object_store::Error| e.to_string();
    let lead = tasks::PartialLayout::LEAD as u64;
    let Some((first, size)) = artifacts.get_range(key, 0..lead).await.map_err(store)? else {
        return Err("not stored".into());
    };
    let len = tasks::PartialLayout::header_len(&first, "").map_err(|e| e.to_string())?;
    if len == 0 || lead.saturating_add(len) > size {
        return Err(format!("a header of {len} bytes in {size}"));
    }
    let Some((header, _)) = artifacts.get_range(key, lead..lead + len).await.map_err(store)? else {
        return Err("not stored".into());
    };
    let layout = tasks::PartialLayout::parse(&[first, header].concat(), "").map_err(|e| e.to_string())?;
    if layout.file_len() != size || !layout.header.held {
        return Err(format!(
            "{size} bytes where the header describes {}, held light {}",
            layout.file_len(),
            layout.header.held
        ));
    }
    let wanted = [layout.pixels.clone(), layout.held.clone()];
    let got = artifacts.get_ranges(key, &wanted).await.map_err(store)?;
    if got.len() != 2 || got.iter().zip(&wanted).any(|(b, r)| b.len() as u64 != r.end - r.start) {
        return Err("a ranged read came back short".into());
    }
    let [pixels, held]: [Bytes; 2] = got.try_into().map_err(|_| "two parts".to_string())?;
    Ok(Fetched::Held {
        layout: Box::new(layout),
        pixels,
        held,
    })
}

/// Merges every task's result into the job's lightmap and stores it.
async fn merge(state: &AppState, worker: &str, task: &TaskRecord, job: &JobRecord, flag: &Arc<StopFlag>) -> End {
    let lessee = Lessee::Task(&job.id, task.index);
    // Every bake task's result, or in rounds the last round's (each region's halves
    // there carry its earlier rounds).
    let merged = if job.spec.in_rounds() {
        task.count - task_regions(job)..task.count
    } else {
        0..task.count
    };
    let load = || async {
        Ok::<_, LoadError>((
            load_scene(state, job).await?,
            load_partials(state, job, merged.clone()).await?,
        ))
    };
    let (files, parts) = match load_patiently(state, lessee, worker, flag, load).await {
        Ok(f) => f,
        Err(None) => return End::Lost,
        Err(Some(reason)) => return End::Finish(TaskOutcome::Failed { reason, retry: true }),
    };
    let limits = state.config.limits.clone();
    let span = tracing::Span::current();
    let plan: Arc<Mutex<Option<Value>>> = Arc::default();
    let plan_out = plan.clone();
    let thread = tokio::task::spawn_blocking(move || {
        let _e = span.enter();
        let partials = parts
            .iter()
            .enumerate()
            .map(|(k, b)| Partial::decode(b, &format!("task {}'s result", merged.start as usize + k)))
            .collect::<Result<Vec<_>, _>>()?;
        drop(parts);
        let (scene, _) = import_files(&files, &limits).map_err(|e| EngineError::BadInput(e.to_string()))?;
        drop(files);
        let options = BakeOptions {
            max_memory_bytes: Some(limits.max_job_memory_bytes),
            ..Default::default()
        };
        let mut on_plan = |p: &Plan| {
            if let Ok(mut slot) = plan_out.lock() {
                *slot = serde_json::to_value(p).ok();
            }
        };
        tasks::merge(Arc::new(scene), &partials, &options, &mut on_plan)
    });
    let r = match while_holding(state, lessee, worker, flag, thread).await {
        _ if flag.get() == StopSignal::LeaseLost => return End::Lost,
        Err(e) => {
            return End::Finish(TaskOutcome::Failed {
                reason: format!("the merge thread panicked: {e}"),
                retry: true,
            });
        }
        Ok(Err(e)) => return failed(e),
        Ok(Ok(r)) => r,
    };
    let stored = store_final(state, &job.id, &r, false);
    if let Err(e) = while_holding(state, lessee, worker, flag, stored).await {
        return End::Finish(TaskOutcome::Failed {
            reason: format!("cannot store the lightmap: {e}"),
            retry: true,
        });
    }
    let s = &r.summary;
    tracing::info!(
        steps = s.steps,
        seconds = s.seconds,
        error = s.error.relative,
        "tasks merged"
    );
    let progress = Progress::new(s.steps, s.seconds, s.error.relative, &job.spec.stop);
    // On the running points' clock (`queue::running_history`): wall time since the job
    // started, not the tasks' bake time added up (the summary's `seconds`).
    let history = [HistoryPoint {
        seconds: job
            .started_at
            .map_or(s.seconds, |t| (state.db_now() - t).max(0) as f64 / 1000.0),
        steps: s.steps,
        error: s.error.relative,
        raw_error: s.error.raw_relative.or(s.error.relative),
        noise: s.error.noise,
        bias: s.error.bias,
        true_error: None,
    }];
    let mut plan = plan.lock().ok().and_then(|p| p.clone()).unwrap_or_else(|| json!({}));
    plan["resolution"] = json!(job.spec.resolution);
    plan["texel_set"] = json!(r.atlas.report());
    plan["tasks"] = json!({"count": task.count});
    End::Finish(TaskOutcome::Merged {
        summary: serde_json::to_value(s).unwrap_or(Value::Null),
        progress: serde_json::to_value(progress).unwrap_or(Value::Null),
        history: serde_json::to_value(history).unwrap_or(Value::Null),
        plan,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::accumulate::{HalfEstimate, Snapshot};
    use glam::Vec3;

    /// A round result of 3 texels, encoded.
    fn round_result() -> Vec<u8> {
        let request = BakeRequest {
            technique: "hemicube".into(),
            stop: crate::engine::bake::StopCriteria {
                steps: Some(8),
                seconds: None,
                target_error: None,
            },
            ..BakeRequest::default()
        };
        let task = tasks::split_rounds(&request, 2, 2).unwrap()[1][0];
        let half = |v: f32| HalfEstimate {
            steps: 3,
            total: vec![Vec3::splat(v); 3],
            direct: None,
            moments: None,
        };
        let p = Partial {
            header: tasks::PartialHeader {
                format: tasks::PARTIAL_FORMAT,
                request,
                task,
                params: json!({}),
                width: 4,
                height: 4,
                texels: 3,
                fingerprint: "ef".repeat(32),
                half_steps: [3, 3],
                direct: false,
                moments: false,
                ao: false,
                ambient: None,
                control: None,
                seconds: 0.5,
                stopped_by: StopReason::Steps,
                live: false,
                held: true,
            },
            snapshot: Snapshot {
                even: half(1.0),
                odd: half(0.5),
            },
            pixels: vec![1, 4, 9],
            ao: None,
            ambient: None,
            held: Some(vec![Vec3::ONE, Vec3::splat(0.5), Vec3::ZERO]),
        };
        p.encode().unwrap()
    }

    /// What a round task fetches of another region's result: its layout, pixels and held
    /// light, in ranged reads, 16 bytes a texel and the header; a missing, truncated or
    /// lengthened result, or one that is not a round's, is refused with a reason (and the
    /// caller, `load_round_before`, reads it whole, to be classified as any result is).
    #[tokio::test]
    async fn a_round_result_is_fetched_in_parts_or_refused() {
        let dir = std::env::temp_dir().join(format!("lightmapd-held-parts-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let artifacts = store::Artifacts::local(&dir).unwrap();
        let bytes = round_result();
        let key = store::task_partial("job", 1);
        artifacts.put(&key, Bytes::from(bytes.clone())).await.unwrap();
        let Ok(Fetched::Held { layout, pixels, held }) = held_parts(&artifacts, &key).await else {
            panic!("a round result is fetched in parts");
        };
        assert_eq!((pixels.len(), held.len()), (12, 36));
        let fetched = Fetched::Held {
            layout: layout.clone(),
            pixels,
            held,
        };
        // All of the file but the halves (3 texels of 24 bytes: no direct layer).
        assert_eq!(fetched.len(), bytes.len() as u64 - 3 * 24);
        let whole = Partial::decode(&bytes, "whole").unwrap();
        let part = fetched.decode("part").unwrap();
        assert!(!part.has_halves());
        assert_eq!((part.pixels, part.held), (whole.pixels, whole.held));

        let refused = |b: Vec<u8>| {
            let (artifacts, key) = (&artifacts, key.clone());
            async move {
                artifacts.put(&key, Bytes::from(b)).await.unwrap();
                held_parts(artifacts, &key).await.err().expect("refused")
            }
        };
        let why = refused(bytes[..bytes.len() - 1].to_vec()).await;
        assert!(why.contains("where the header describes"), "{why}");
        let why = refused([bytes.clone(), vec![0]].concat()).await;
        assert!(why.contains("where the header describes"), "{why}");
        let why = refused(b"not a result".to_vec()).await;
        assert!(why.contains("no LMDTASK1 magic"), "{why}");
        // An empty object: the store refuses the range itself.
        let why = refused(Vec::new()).await;
        assert!(why.contains("range"), "{why}");
        let mut plain = Partial::decode(&bytes, "whole").unwrap();
        plain.header.held = false;
        plain.held = None;
        let why = refused(plain.encode().unwrap()).await;
        assert!(why.contains("held light false"), "{why}");
        let why = held_parts(&artifacts, &store::task_partial("job", 2))
            .await
            .err()
            .expect("refused");
        assert_eq!(why, "not stored");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
