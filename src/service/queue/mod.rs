//! The durable job queue and scene registry, behind one trait so the embedded SQLite
//! implementation ([`sqlite`]) and the shared PostgreSQL one ([`postgres`], issue 11) are
//! interchangeable for routes and workers; [`open`] picks one from the URL's scheme, the
//! only place that does. Both run the same test suite (`tests.rs`, every test once per
//! store).
//!
//! The model (DESIGN §7): a job is `queued` until a worker claims it, which makes it
//! `running` with a lease (worker id, expiry) and counts an attempt. The worker renews
//! the lease with every progress write ([`Queue::heartbeat`]); a lease that lapses (the
//! worker or its machine died) is found by [`Queue::recover_expired`], run at start-up and
//! periodically, which puts the job back to `queued`, or fails it once it has had
//! [`MAX_ATTEMPTS`] attempts. A worker that stops on purpose hands its job back with
//! [`Queue::release`], which does not count the attempt. Every transition is one
//! statement (or one transaction), so two workers can never hold the same job.
//!
//! Clients: every scene and job records the client that made it (a token id when the
//! server requires tokens, else `ip:ADDR`). [`Queue::enqueue`] refuses a job when its
//! client already has `max_queued` jobs waiting, in the same statement that inserts it,
//! so concurrent submissions cannot overshoot. Tokens live in the same database, hashed.
//!
//! Tasks (issue 25, docs/scaling.md): a job submitted with `tasks: N` is never claimed
//! whole. [`Queue::enqueue`] stores N bake task rows (a range of the job's steps each,
//! `engine::tasks`) and one merge task, `waiting` until every bake task has succeeded.
//! Each task has its own lease and attempts: [`Queue::claim_task`] takes one (the job
//! becomes `running` with its first), [`Queue::task_heartbeat`] renews it and writes the
//! task's steps and error, from which the same statement's transaction writes the job's
//! merged progress ([`merged_progress`]); [`Queue::finish_task`] records a baked task
//! (queueing the merge after the last) or the merge (the job `succeeded`, with its
//! summary). A task whose worker died is queued again by [`Queue::recover_expired`], or
//! fails the job after [`MAX_ATTEMPTS`] attempts; every failed or abandoned attempt counts
//! against its worker in `task_failures`, and a worker with [`BLOCKLIST_AFTER`] of them
//! takes no more of that job's tasks.
//!
//! Rounds (`JobSpec::rounds`, `engine::rounds`): a job of R rounds of P regions stores R P
//! bake task rows, task r P + p being region p's of round r, and the merge (index R P).
//! Round 0's are queued, the later rounds' `waiting`; the success that completes round r
//! queues round r+1's ([`round_after`], in the transaction that records it, under the
//! job's lock, as the last bake task's success queues the merge). A retried task stays a
//! task of its round, and the merge reads the last round's results.
//!
//! Capabilities: every worker registers what it has ([`Capabilities`]) and refreshes its
//! `last_seen`; claims pass the claimer's capabilities and skip jobs whose `requires` it
//! does not meet; the API reads the live workers to say what a job nobody takes is
//! waiting for.
//!
//! Snapshots of a split job while its tasks run: a task's worker claims the next number
//! ([`Queue::claim_task_snapshot`], one claim a snapshot interval for the whole job),
//! stores the merged snapshot under it and records it ([`Queue::task_snapshot_stored`]).
//!
//! Limits: a re-run starts the bake again from step 0 (the engine cannot resume from a
//! snapshot); snapshots of earlier attempts stay, numbered on.

pub mod postgres;
pub mod sqlite;
#[cfg(test)]
mod tests;

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use serde_json::Value;
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::service::Hub;
use crate::service::model::{JobSpec, JobStatus};

/// The schema's migrations, embedded in the binary: (version, description, SQL) as
/// `NNNN_description.sql` files in `migrations/<store>/` spell them. Built here rather
/// than by `sqlx::migrate!` so that sqlx's macros are not compiled at all: they build
/// sqlx's SQLite (with its C library) and PostgreSQL drivers a second time, for the
/// compiler, about 3 CPU-minutes of every cold build and of CI's budget. Version,
/// description and checksum (SHA-384 of the text) are what the macro records, so a
/// database migrated by an earlier build is recognised, not migrated again.
pub(crate) fn migrator(files: &'static [(i64, &'static str, &'static str)]) -> sqlx::migrate::Migrator {
    use sqlx::SqlSafeStr;
    use sqlx::migrate::{Migration, MigrationType, Migrator};
    Migrator::with_migrations(
        files
            .iter()
            .map(|(version, description, sql)| {
                Migration::new(
                    *version,
                    (*description).into(),
                    MigrationType::Simple,
                    sql.into_sql_str(),
                    sql.starts_with("-- no-transaction"),
                )
            })
            .collect(),
    )
}

/// A job (or a task) that has lost its lease this many times fails instead of being
/// re-queued.
pub const MAX_ATTEMPTS: u32 = 3;

/// A worker whose attempts at one job's tasks failed (an error, or its lease lapsed)
/// this many times takes no more of that job's tasks (as Flamenco's blocklist does: a
/// worker with a broken driver or too little memory keeps failing the same job).
pub const BLOCKLIST_AFTER: u32 = 2;

/// A worker not seen for this long is not counted as alive when the API says what a
/// job is waiting for (workers refresh every [`WORKER_REFRESH`]).
pub const WORKER_ALIVE_MS: i64 = 30_000;
/// How often a worker process refreshes its workers' `last_seen`.
pub const WORKER_REFRESH: Duration = Duration::from_secs(10);
/// A worker not seen for this long is removed from `workers` by the retention sweep
/// (`service::retention_loop`): a farm whose worker names change with every start (the
/// default name carries the host and process id) would otherwise grow the table
/// forever. A day, so a worker's row outlives any job it took part in long enough for
/// its blocklist entries (`task_failures`, kept by name) to be read beside it.
pub const WORKER_FORGET_MS: i64 = 24 * 3600 * 1000;

/// What a worker can run (issue 25 point 4), as it registers it.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct Capabilities {
    /// A hardware GPU adapter (discrete, integrated or virtual) is present; a software
    /// rasterizer (lavapipe) is not one.
    pub gpu: bool,
    /// The best adapter's name, when there is any adapter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adapter: Option<String>,
    /// Its kind: `discrete`, `integrated`, `virtual`, `cpu` (software) or `other`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adapter_kind: Option<String>,
    /// Intel Open Image Denoise can be loaded.
    pub oidn: bool,
    /// The most memory one job may take on this worker (`--max-job-memory-mb`).
    pub memory_bytes: u64,
}

/// A registered worker.
#[derive(Clone, Debug)]
pub struct WorkerRecord {
    pub id: String,
    pub capabilities: Capabilities,
    pub started_at: i64,
    pub last_seen: i64,
}

/// A task's state. `Waiting`: the merge, until every bake task has succeeded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum TaskStatus {
    Waiting,
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl TaskStatus {
    pub fn as_str(self) -> &'static str {
        match self {
            TaskStatus::Waiting => "waiting",
            TaskStatus::Queued => "queued",
            TaskStatus::Running => "running",
            TaskStatus::Succeeded => "succeeded",
            TaskStatus::Failed => "failed",
            TaskStatus::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<TaskStatus> {
        [
            TaskStatus::Waiting,
            TaskStatus::Queued,
            TaskStatus::Running,
            TaskStatus::Succeeded,
            TaskStatus::Failed,
            TaskStatus::Cancelled,
        ]
        .into_iter()
        .find(|t| t.as_str() == s)
    }
}

/// One task of a split job: `index` of `count` bake tasks, or the merge (`index ==
/// count`).
#[derive(Clone, Debug)]
pub struct TaskRecord {
    pub job_id: String,
    pub index: u32,
    pub count: u32,
    pub status: TaskStatus,
    pub attempts: u32,
    pub worker: Option<String>,
    pub lease_expires_at: Option<i64>,
    /// Steps this attempt has baked.
    pub steps: u64,
    pub seconds: f64,
    /// The task's own relative error estimate (its halves' difference).
    pub error: Option<f32>,
    pub failure: Option<String>,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
}

impl TaskRecord {
    pub fn is_merge(&self) -> bool {
        self.index == self.count
    }
}

/// What a running task's heartbeat reports.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TaskBeat {
    pub steps: u64,
    pub seconds: f64,
    pub error: Option<f32>,
}

/// The end of a task.
#[derive(Clone, Debug)]
pub enum TaskOutcome {
    /// A bake task's result is stored.
    Baked(TaskBeat),
    /// The merge's artifacts are stored: the job succeeded with these.
    Merged {
        summary: Value,
        progress: Value,
        history: Value,
        plan: Value,
    },
    /// The attempt failed. `retry`: another worker may succeed (a device or store
    /// error); otherwise (bad input, which every worker would meet) the job fails now.
    Failed {
        reason: String,
        retry: bool,
    },
    Cancelled,
}

/// How a job's failure names one of its tasks: `task K of N`, or `the merge`.
fn task_label(index: i64, count: i64) -> String {
    if index == count {
        "the merge".to_string()
    } else {
        format!("task {index} of {count}")
    }
}

/// The failure of a split job whose task's lease lapsed [`MAX_ATTEMPTS`] times (both
/// stores' recoveries write it).
pub(crate) fn lease_given_up(index: i64, count: i64, worker: Option<&str>) -> String {
    format!(
        "{} was given up after {MAX_ATTEMPTS} attempts: the lease of worker {} expired (the worker stopped renewing it: crashed, killed or cut off)",
        task_label(index, count),
        worker.unwrap_or("?")
    )
}

/// The failure of a split job whose task failed for good: bad input (`retry` false) at
/// once, anything else at its last attempt (both stores' `finish_task` write it).
pub(crate) fn task_failed(index: i64, count: i64, attempts: i64, worker: &str, reason: &str, retry: bool) -> String {
    let what = task_label(index, count);
    if retry {
        format!("{what} failed {attempts} times; the last time on worker {worker}: {reason}")
    } else {
        format!("{what} failed: {reason}")
    }
}

/// The progress of a split job from its bake tasks' (steps, error), in task order.
/// Within a region (all its step ranges: `tasks / regions` consecutive tasks), steps
/// add up and the error is that of the step-weighted mean of independent estimates,
/// `sqrt(Σ (s_k/S)² e_k²)` (each task's error is its own halves' difference, DESIGN §4,
/// and the tasks draw disjoint samples, so their errors add in quadrature). Across
/// regions (disjoint texels), the job's steps are the regions' mean and its error the
/// root mean square of theirs: each region's relative error counts alike, which is the
/// whole grid's when the regions have about as many texels and as much light (the queue
/// knows neither; page regions of very different sizes make it approximate). `fraction`
/// as for a whole bake of `spec.stop`. The merge's own error estimate, from the merged
/// halves, replaces it when the job ends.
///
/// Independent chains (every technique but `path`, `engine::tasks`) report errors that
/// include their bias (control texels), which is the same in every chain and does not
/// average down: their error is the step-weighted *mean* `Σ (s_k/S) e_k`, an upper bound
/// of the merged error (the triangle inequality: the noise parts would add in
/// quadrature, the bias parts linearly), never an understatement.
///
/// A job in rounds (`JobSpec::rounds`): a region's steps are its tasks' over every round,
/// and its error that of its latest task that has baked steps (each round's task resumes
/// the region's accumulators, so its own estimate covers the rounds before it). Workers
/// state no error for a round before the last (`service::farm`), so the job's error is
/// unknown until every region's last round has one.
pub fn merged_progress(spec: &JobSpec, started_at: Option<i64>, now: i64, tasks: &[(u64, Option<f32>)]) -> Value {
    let chains = crate::engine::technique::entry(&spec.technique).is_ok_and(|e| {
        use crate::engine::technique::api::TaskSplit;
        matches!(e.tasks, TaskSplit::Chains(_) | TaskSplit::ChainsAndRegions(_))
    });
    let regions = spec.regions.unwrap_or(1).max(1) as usize;
    let parts: Vec<(u64, Option<f64>)> = if spec.in_rounds() {
        (0..regions)
            .map(|p| {
                let own: Vec<&(u64, Option<f32>)> = tasks.iter().skip(p).step_by(regions).collect();
                let steps = own.iter().map(|t| t.0).sum();
                let latest = own.iter().rev().find(|t| t.0 > 0);
                (steps, latest.and_then(|t| t.1).map(f64::from))
            })
            .collect()
    } else {
        split_parts(tasks, regions, chains)
    };
    let n = parts.len().max(1) as u64;
    let steps = parts.iter().map(|p| p.0).sum::<u64>() / n;
    let error = parts
        .iter()
        .map(|p| p.1)
        .collect::<Option<Vec<f64>>>()
        .filter(|e| !e.is_empty())
        .map(|e| (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt() as f32);
    let elapsed = started_at.map_or(0.0, |t| (now - t).max(0) as f64 / 1000.0);
    serde_json::to_value(crate::service::model::Progress::new(steps, elapsed, error, &spec.stop)).unwrap_or(Value::Null)
}

/// Each region's (steps, error) of a split job: its `tasks / regions` consecutive tasks'
/// steps added up, their errors combined as [`merged_progress`] says.
fn split_parts(tasks: &[(u64, Option<f32>)], regions: usize, chains: bool) -> Vec<(u64, Option<f64>)> {
    let per_region = tasks.len().div_ceil(regions).max(1);
    tasks
        .chunks(per_region)
        .map(|group| {
            let steps: u64 = group.iter().map(|t| t.0).sum();
            let error = (steps > 0 && group.iter().all(|t| t.0 == 0 || t.1.is_some())).then(|| {
                let s = steps as f64;
                let weighted = group.iter().filter_map(|&(k, e)| e.map(|e| k as f64 / s * e as f64));
                if chains {
                    weighted.sum::<f64>()
                } else {
                    weighted.map(|x| x * x).sum::<f64>().sqrt()
                }
            });
            (steps, error)
        })
        .collect()
}

/// The bake tasks of a job in rounds that `index`'s success may queue: the next round's,
/// as `[first of index's round, first of the next, end of the next]`, to be queued once
/// every task in the first range has succeeded (in the same transaction that marks
/// `index`, under the job's lock, so exactly one success queues them). `None` for the
/// last round and for jobs not in rounds, whose merge waits for every bake task instead.
pub fn round_after(spec: &JobSpec, index: u32) -> Option<[u32; 3]> {
    if !spec.in_rounds() {
        return None;
    }
    let per_round = spec.regions.unwrap_or(1).max(1);
    let round = index / per_round;
    (round + 1 < spec.rounds.unwrap_or(1)).then(|| {
        let first = round * per_round;
        [first, first + per_round, first + 2 * per_round]
    })
}

/// The most points a split job's running history keeps (as a single bake's worker).
pub const MAX_RUNNING_HISTORY: usize = 2000;

/// A split job's running history: `history` with its merged progress (`progress`, from
/// [`merged_progress`]) appended as a point, or `None` when the progress has not moved on
/// enough since the last point to be worth one. A point is due once the steps have grown
/// by a quarter and a second has passed, or five seconds have passed with any new steps,
/// so the curve is dense while the error falls fast and about one point per five seconds
/// later (a single bake's snapshots thin out the same way). Its `error` and `raw_error`
/// are the merged raw estimate. Once the job has stored a running snapshot (`snapshots`
/// above 0) the history is its snapshots' points instead, each the delivered error of
/// what that snapshot holds ([`Queue::task_snapshot_stored`]), as a single bake's is:
/// `None` then. The merge's own point ([`history_then`]) ends the curve.
pub fn running_history(history: &Value, progress: &Value, snapshots: u32) -> Option<Value> {
    if snapshots > 0 {
        return None;
    }
    let p: crate::service::model::Progress = serde_json::from_value(progress.clone()).ok()?;
    let error = p.error.filter(|_| p.steps > 0)?;
    let mut points: Vec<crate::service::model::HistoryPoint> =
        serde_json::from_value(history.clone()).unwrap_or_default();
    if let Some(last) = points.last() {
        let grown = p.steps as f64 >= 1.25 * last.steps as f64 && p.elapsed_s >= last.seconds + 1.0;
        let due = p.steps > last.steps && p.elapsed_s >= last.seconds + 5.0;
        if !(grown || due) || points.len() >= MAX_RUNNING_HISTORY {
            return None;
        }
    }
    points.push(crate::service::model::HistoryPoint {
        seconds: p.elapsed_s,
        steps: p.steps,
        error: Some(error),
        raw_error: Some(error),
        noise: None,
        bias: None,
        true_error: None,
    });
    serde_json::to_value(points).ok()
}

/// A split job's history with a running snapshot's `point` added: every last point with
/// more steps than it is dropped first, so the curve's steps never go back. Those are
/// merged raw points recorded from the tasks' heartbeats ahead of the halves the
/// snapshot was made from, or, where two snapshots were stored out of their order, the
/// later one's point.
pub fn with_snapshot_point(history: &Value, point: &Value) -> Value {
    let steps = |p: &Value| p["steps"].as_u64().unwrap_or(0);
    let mut points = history.as_array().cloned().unwrap_or_default();
    while points.last().is_some_and(|last| steps(last) > steps(point)) {
        points.pop();
    }
    points.push(point.clone());
    Value::Array(points)
}

/// A split job's history once merged: its running points, then the merge's.
pub fn history_then(running: &Value, merged: &Value) -> Value {
    let mut points = running.as_array().cloned().unwrap_or_default();
    points.extend(merged.as_array().cloned().unwrap_or_default());
    Value::Array(points)
}

pub type QueueResult<T> = Result<T, sqlx::Error>;

#[derive(Clone, Debug)]
pub struct SceneRecord {
    pub id: String,
    pub content_hash: String,
    pub format: String,
    pub main_file: String,
    pub files: Vec<String>,
    pub size_bytes: u64,
    pub report: Value,
    pub created_at: i64,
    /// The token id that uploaded it (when tokens are required), else `None`.
    pub client: Option<String>,
}

#[derive(Clone, Debug)]
pub struct JobRecord {
    pub id: String,
    pub scene_id: String,
    pub spec: JobSpec,
    pub status: JobStatus,
    pub priority: i32,
    pub created_at: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
    pub attempts: u32,
    pub worker: Option<String>,
    pub lease_expires_at: Option<i64>,
    pub cancel_requested: bool,
    pub progress: Option<Value>,
    pub history: Value,
    pub plan: Option<Value>,
    pub snapshots: u32,
    pub summary: Option<Value>,
    pub failure: Option<String>,
    pub updated_at: i64,
    /// Who submitted it: a token id, or `ip:ADDR` when tokens are not required.
    pub client: Option<String>,
    /// Bake tasks it is split into; 0 when it is not split.
    pub tasks: u32,
    /// Its estimated peak memory (0: not known); only workers whose per-job limit is at
    /// least this claim it.
    pub memory_bytes: u64,
}

/// The answer to [`Queue::enqueue`].
#[derive(Clone, Debug)]
pub enum Enqueued {
    Queued(Box<JobRecord>),
    /// No scene with that id.
    NoScene,
    /// The client already has this many jobs queued (the limit).
    QueueFull(u64),
}

/// A bearer token as stored: only the SHA-256 of the secret.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TokenRecord {
    pub id: String,
    pub name: String,
    /// Hex SHA-256 of the secret.
    pub hash: String,
    pub created_at: i64,
    pub revoked_at: Option<i64>,
    /// What the token may do.
    pub role: Role,
    /// `cli` (`lightmapd token create`) or `file` (`serve --tokens-file`).
    pub source: String,
}

/// A token's role (issue 24).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// Its own scenes and jobs; priority up to `--max-priority`.
    Editor,
    /// Every client's jobs and scenes; any priority.
    Admin,
}

impl Role {
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Editor => "editor",
            Role::Admin => "admin",
        }
    }

    pub fn parse(s: &str) -> Option<Role> {
        match s {
            "editor" => Some(Role::Editor),
            "admin" => Some(Role::Admin),
            _ => None,
        }
    }
}

/// The answer to [`Queue::delete_job`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JobDeletion {
    Deleted,
    NotFound,
    /// Queued or running: cancel it first.
    Unfinished(JobStatus),
}

/// What a running worker writes with a heartbeat (each part only when it changed).
#[derive(Clone, Debug, Default)]
pub struct JobUpdate {
    pub progress: Option<Value>,
    pub history: Option<Value>,
    pub plan: Option<Value>,
    /// The number of the snapshot just stored.
    pub snapshots: Option<u32>,
}

/// The answer to a heartbeat.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lease {
    /// Still ours; `cancel` when someone asked to cancel the job.
    Held { cancel: bool },
    /// Not ours any more (expired and re-queued, or the job was cancelled): stop, and
    /// write nothing.
    Lost,
}

#[derive(Clone, Debug)]
pub enum Outcome {
    Succeeded {
        summary: Value,
        progress: Value,
        history: Value,
    },
    Failed {
        reason: String,
    },
    Cancelled,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneDeletion {
    Deleted,
    NotFound,
    /// Queued or running jobs still use it.
    InUse(u64),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Cancellation {
    NotFound,
    /// A queued job, cancelled at once.
    Cancelled,
    /// A running job: its worker stops within one step.
    Requested,
    /// Already finished; nothing to do.
    AlreadyFinished(JobStatus),
}

#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Recovered {
    pub requeued: Vec<String>,
    pub failed: Vec<String>,
    pub cancelled: Vec<String>,
    /// Tasks (job, index) queued again after their worker's lease lapsed.
    pub tasks_requeued: Vec<(String, u32)>,
}

#[async_trait]
pub trait Queue: Send + Sync + 'static {
    /// Starts forwarding other processes' changes into `hub` as they commit (a job became
    /// queued: `Hub::work`; a job changed: `Hub::job_changed`) until `shutdown`. `None`
    /// when the store has no such channel (SQLite): other processes' changes are then
    /// found by polling only.
    fn listen(&self, _hub: Arc<Hub>, _shutdown: watch::Receiver<bool>) -> Option<JoinHandle<()>> {
        None
    }

    /// Stores a scene; `false` when one with the same id (same content) already exists.
    async fn insert_scene(&self, scene: &SceneRecord) -> QueueResult<bool>;
    async fn scene(&self, id: &str) -> QueueResult<Option<SceneRecord>>;
    /// Every scene, newest first; only `client`'s when it is given.
    async fn scenes(&self, client: Option<&str>) -> QueueResult<Vec<SceneRecord>>;
    /// Deletes the scene's row unless a queued or running job uses it.
    async fn delete_scene(&self, id: &str) -> QueueResult<SceneDeletion>;

    /// Stores a queued job for `client`, unless its scene does not exist or the client
    /// already has `max_queued` queued jobs (checked in the same statement).
    /// `memory_bytes`: its estimated peak memory (`worker::job_memory`; 0 if unknown).
    async fn enqueue(
        &self,
        id: &str,
        spec: &JobSpec,
        client: &str,
        max_queued: u64,
        memory_bytes: u64,
        now: i64,
    ) -> QueueResult<Enqueued>;
    async fn job(&self, id: &str) -> QueueResult<Option<JobRecord>>;
    /// Newest first; only `client`'s jobs when it is given.
    async fn list(
        &self,
        status: Option<JobStatus>,
        client: Option<&str>,
        limit: u32,
        offset: u64,
    ) -> QueueResult<(Vec<JobRecord>, u64)>;
    async fn counts(&self) -> QueueResult<Vec<(JobStatus, u64)>>;
    async fn cancel(&self, id: &str, now: i64) -> QueueResult<Cancellation>;

    /// Takes the next queued job that is not split (highest priority, then oldest) and
    /// whose `requires` and estimated memory `caps` meets, for `worker`.
    async fn claim(
        &self,
        worker: &str,
        caps: &Capabilities,
        lease: Duration,
        now: i64,
    ) -> QueueResult<Option<JobRecord>>;
    /// Takes the next queued task (its job's priority, then age, then task order) of a
    /// job whose `requires` `caps` meets and that has not blocklisted `worker`; its job
    /// becomes `running` with its first task. None while a queued whole job that
    /// [`Queue::claim`] would give this worker is ahead of the task's job (higher
    /// priority, or as high and older), so a worker asking for tasks first and then
    /// for whole jobs takes both kinds in one priority order.
    async fn claim_task(
        &self,
        worker: &str,
        caps: &Capabilities,
        lease: Duration,
        now: i64,
    ) -> QueueResult<Option<(TaskRecord, JobRecord)>>;
    /// Renews a task's lease, writes `beat` (and the job's merged progress from it).
    /// `Held { cancel }` says whether the job is being cancelled.
    async fn task_heartbeat(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        lease: Duration,
        beat: Option<&TaskBeat>,
        now: i64,
    ) -> QueueResult<Lease>;
    /// Claims the number of a split job's next snapshot for the worker running task
    /// `index` (snapshots while the tasks run, `service::farm`): `Some(n)` when that task
    /// is this worker's and running, the job is running and no snapshot was claimed in
    /// the last `interval`; `None` otherwise. One claim an interval, whichever task asks
    /// first, so the tasks take turns and a finished task hands the turn on. Numbers go
    /// on from the job's stored snapshots (an earlier attempt's included).
    async fn claim_task_snapshot(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        interval: Duration,
        now: i64,
    ) -> QueueResult<Option<u32>>;
    /// Records a running split job's snapshot `n` as stored: its count becomes `n`
    /// unless a later claim was stored first, and `point` (a `HistoryPoint`: the
    /// delivered error of what the snapshot holds) is added to its history
    /// ([`with_snapshot_point`]), which holds snapshots' points from then on
    /// ([`running_history`]). `false` when the job
    /// is no longer running (the caller deletes what it stored).
    async fn task_snapshot_stored(&self, job: &str, n: u32, point: &Value) -> QueueResult<bool>;
    /// Hands back claim `n` that stored nothing (its snapshot could not be made), when no
    /// later claim was made, so the next claim takes its number again: a job's snapshots
    /// are numbered without gaps.
    async fn release_task_snapshot(&self, job: &str, n: u32) -> QueueResult<()>;
    /// Records the end of a task (see [`TaskOutcome`]); `false` when its lease was lost.
    async fn finish_task(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        outcome: &TaskOutcome,
        now: i64,
    ) -> QueueResult<bool>;
    /// Hands a running task back (graceful shutdown): queued again, attempt not counted.
    async fn release_task(&self, job: &str, index: u32, worker: &str, now: i64) -> QueueResult<bool>;
    /// A job's tasks, in order (the merge last); empty when it is not split.
    async fn tasks(&self, job: &str) -> QueueResult<Vec<TaskRecord>>;
    /// The workers with failed attempts at `job`'s tasks, and how many.
    async fn task_failures(&self, job: &str) -> QueueResult<Vec<(String, u32)>>;
    /// Registers `worker` with `caps`, or refreshes its `last_seen`.
    async fn register_worker(&self, worker: &str, caps: &Capabilities, now: i64) -> QueueResult<()>;
    /// Workers seen at or after `since`.
    async fn workers(&self, since: i64) -> QueueResult<Vec<WorkerRecord>>;
    /// Removes the workers last seen before `before`; how many.
    async fn forget_workers(&self, before: i64) -> QueueResult<u64>;
    /// Renews the lease and writes `update`.
    async fn heartbeat(
        &self,
        id: &str,
        worker: &str,
        lease: Duration,
        update: &JobUpdate,
        now: i64,
    ) -> QueueResult<Lease>;
    /// Records the end of a job; `false` when the lease was lost (nothing written).
    async fn finish(&self, id: &str, worker: &str, outcome: &Outcome, now: i64) -> QueueResult<bool>;
    /// Hands a running job back (graceful shutdown): queued again, attempt not counted.
    async fn release(&self, id: &str, worker: &str, now: i64) -> QueueResult<bool>;
    /// Re-queues (or fails, or cancels) running jobs whose lease has lapsed.
    async fn recover_expired(&self, now: i64) -> QueueResult<Recovered>;

    async fn insert_token(&self, token: &TokenRecord) -> QueueResult<()>;
    /// Every token, oldest first (revoked ones too).
    async fn tokens(&self) -> QueueResult<Vec<TokenRecord>>;
    /// Revokes the token with this id; `false` when there is no such live token. (Names
    /// are resolved to one id by the caller, which refuses an ambiguous name.)
    async fn revoke_token(&self, id: &str, now: i64) -> QueueResult<bool>;
    /// The live (not revoked) token whose secret hashes to `hash`.
    async fn token_by_hash(&self, hash: &str) -> QueueResult<Option<TokenRecord>>;

    /// The database's clock, in Unix milliseconds: leases are set and compared with it,
    /// so machines whose clocks disagree still agree on when a lease ends (issue 24).
    /// The default is this process's clock (for wrappers and stores without one).
    async fn clock(&self) -> QueueResult<i64> {
        Ok(now_ms())
    }

    /// Deletes a finished job's row (one statement, guarded by its status).
    async fn delete_job(&self, id: &str) -> QueueResult<JobDeletion>;
    /// Up to `limit` finished jobs that finished before `before`, oldest first.
    async fn finished_before(&self, before: i64, limit: u32) -> QueueResult<Vec<String>>;
}

/// Opens the queue a `--database-url` names: `postgres://` or `postgresql://` (the shared
/// store), `sqlite://FILE` (the embedded one), or, without a URL, the SQLite file
/// `default_sqlite`. Any other scheme is an error naming the ones supported.
pub async fn open(url: Option<&str>, default_sqlite: &Path) -> anyhow::Result<Arc<dyn Queue>> {
    Ok(match url {
        None => Arc::new(sqlite::SqliteQueue::open(default_sqlite).await?),
        Some(u) if u.starts_with("sqlite:") => Arc::new(sqlite::SqliteQueue::open_url(u).await?),
        Some(u) if u.starts_with("postgres://") || u.starts_with("postgresql://") => {
            Arc::new(postgres::PostgresQueue::open(u).await?)
        }
        Some(u) => anyhow::bail!("{}", unsupported_url(u)),
    })
}

/// The message for a `--database-url` whose scheme no store handles.
pub fn unsupported_url(url: &str) -> String {
    // The URL may carry a password: name the scheme only.
    let scheme = url.split_once("://").map_or(url, |(s, _)| s);
    format!("unsupported --database-url scheme {scheme:?}: use postgres://USER:PASSWORD@HOST/DB or sqlite://FILE")
}

/// Whether [`open`] knows the URL's scheme (the CLI checks before starting anything).
pub fn supported_url(url: &str) -> bool {
    ["sqlite:", "postgres://", "postgresql://"]
        .iter()
        .any(|p| url.starts_with(p))
}

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}
