//! The shared queue: PostgreSQL, for API and worker processes on several machines
//! (DESIGN §8, issue 11). Migrations from `migrations/postgres/` are applied at start-up
//! by whichever process comes first (sqlx's migrator holds an advisory lock while it
//! runs, so processes starting together do not race).
//!
//! How each [`Queue`] operation keeps the guarantees the SQLite store gets from its
//! single writer:
//! - **claim** is one `UPDATE … WHERE id = (SELECT … ORDER BY priority DESC, created_at,
//!   seq LIMIT 1 FOR UPDATE SKIP LOCKED) RETURNING *`: a claimer skips the row another
//!   claimer has locked instead of waiting for it, so N workers take N different jobs in
//!   one round trip each, and no job is taken twice (the row lock is held until the
//!   update commits; a claimer that looks after that sees `running`).
//! - **heartbeat / finish / release** are single `UPDATE`s guarded by `worker = $me AND
//!   status = 'running'`; PostgreSQL re-checks that guard on the newest row version after
//!   waiting for a lock, so a worker whose lease was recovered and re-claimed writes
//!   nothing.
//! - **recover_expired** takes expired rows with `FOR UPDATE SKIP LOCKED`, so the
//!   recovery loops of several processes split the work instead of deadlocking.
//! - **enqueue** runs in a transaction holding a per-client advisory lock
//!   (`pg_advisory_xact_lock(KEY_CLASS, hashtext(client))`): the count of the client's
//!   queued jobs and the insert cannot interleave with the same client's other
//!   submissions on other API processes, so the per-client limit cannot be overshot. It
//!   also reads the scene `FOR SHARE`, and **delete_scene** reads it `FOR UPDATE` before
//!   counting the jobs that use it, so a job cannot be queued for a scene being deleted.
//!
//! LISTEN/NOTIFY: a trigger on `jobs` (in the migration) sends, on commit,
//! - `lightmapd_work` with the job id when a job becomes `queued` (submitted, recovered,
//!   handed back): [`Queue::listen`] turns it into `Hub::work`, which wakes this process's
//!   idle workers at once instead of at their next poll;
//! - `lightmapd_job` with the job id when its status, progress, plan, snapshot count or
//!   cancel flag changed: turned into `Hub::job_changed`, the same signal the event
//!   streams of `events.rs` already wait on, so an API process follows a bake run by a
//!   worker on another machine within a round trip, not at its next 500 ms poll.
//!
//! Each process holds one extra connection for LISTEN. Notifications are a latency
//! optimisation only: a lost one (the connection dropped, or the listener is restarting)
//! costs at most one poll interval, since workers still poll every 500 ms and event
//! streams still re-read the row every 500 ms. Channels are per database, not per schema:
//! processes using different schemas of one database (the tests do) see each other's
//! notifications, which only causes a spurious re-read or claim attempt.
//!
//! Tasks (issue 25): every transaction that writes a split job's tasks (heartbeat,
//! finish, release, cancel, lease recovery) first takes a transaction-level advisory
//! lock on the job (`pg_advisory_xact_lock(KEY_TASKS, hashtext(job))`), so they run one
//! at a time per job and always in the same lock order (job lock, then rows): the
//! merged progress, a failure that ends the job and a cancel each see and write a
//! consistent set of task rows. The claim picks a task row with `FOR UPDATE OF t SKIP
//! LOCKED` (claimers never wait for each other's rows) and then only *tries* the job's
//! lock; when another transaction holds it, the claim lets the row go and tries again
//! (a claim that waited for the job lock while holding a row another holder wants would
//! be a deadlock: `examples/claim_bench.rs` found exactly that with 3 claimers before
//! this). The recovery takes the locks of the jobs it recovers in sorted order.
//!
//! Schemas: `open` uses the URL's `search_path` (`?options=-csearch_path%3Dname`), and
//! [`PostgresQueue::open_in_schema`] creates a schema and uses it; the tests give each
//! test its own schema so they run in parallel on one database.
//!
//! Clocks: the `now` arguments are the caller's, but workers and recovery loops pass the
//! database's clock ([`Queue::clock`], `clock_timestamp()`), so a lease is set and
//! compared on one clock and machines whose clocks disagree still agree on when it ends
//! (issue 24). Limits: the pool
//! holds at most [`MAX_CONNECTIONS`] connections per process (a worker needs one at a
//! time per running job, an API process one per request in flight).

use std::str::FromStr;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use serde_json::Value;
use sqlx::postgres::{PgConnectOptions, PgConnection, PgListener, PgPool, PgPoolOptions, PgRow};
use sqlx::{AssertSqlSafe, Row};
use tokio::sync::watch;
use tokio::task::JoinHandle;

use super::{
    BLOCKLIST_AFTER, Cancellation, Capabilities, Enqueued, JobDeletion, JobRecord, JobUpdate, Lease, MAX_ATTEMPTS,
    Outcome, Queue, QueueResult, Recovered, Role, SceneDeletion, SceneRecord, TaskBeat, TaskOutcome, TaskRecord,
    TaskStatus, TokenRecord, WorkerRecord, history_then, lease_given_up, merged_progress, round_after, running_history,
    task_failed, with_snapshot_point,
};
use crate::service::model::{JobSpec, JobStatus};
use crate::service::{Hub, shutting_down};

/// `migrations/postgres/`, embedded (`super::migrator`; a test checks the folder holds
/// exactly these).
pub(crate) const MIGRATIONS: &[(i64, &str, &str)] = &[
    (1, "init", include_str!("../../../migrations/postgres/0001_init.sql")),
    (
        2,
        "roles and retention",
        include_str!("../../../migrations/postgres/0002_roles_and_retention.sql"),
    ),
    (3, "tasks", include_str!("../../../migrations/postgres/0003_tasks.sql")),
    (
        4,
        "task snapshots",
        include_str!("../../../migrations/postgres/0004_task_snapshots.sql"),
    ),
];

static MIGRATOR: std::sync::LazyLock<sqlx::migrate::Migrator> =
    std::sync::LazyLock::new(|| super::migrator(MIGRATIONS));

/// Connections per process, besides the one LISTEN holds.
pub const MAX_CONNECTIONS: u32 = 8;
/// Channel of "a job became queued" (payload: its id).
pub const WORK_CHANNEL: &str = "lightmapd_work";
/// Channel of "a job's visible state changed" (payload: its id).
pub const JOB_CHANNEL: &str = "lightmapd_job";
/// The first half of the two-part advisory-lock key of the per-client enqueue lock
/// ("lmdq"); two-part keys never collide with sqlx's one-part migration lock.
const KEY_CLASS: i32 = 0x6c6d_6471;
/// The first half of the advisory-lock key every write to one split job's tasks takes
/// first ("lmdt"; the module doc's "Tasks").
const KEY_TASKS: i32 = 0x6c6d_6474;

/// The environment variable the tests read a PostgreSQL URL from.
pub const TEST_URL_VAR: &str = "LIGHTMAPD_TEST_POSTGRES";
/// Set to `1` in CI: a test that cannot reach its service fails instead of skipping.
pub const REQUIRE_SERVICES_VAR: &str = "LIGHTMAPD_REQUIRE_SERVICES";

/// Where `scripts/setup-postgres.sh` makes the test database.
pub const DEFAULT_TEST_URL: &str = "postgres://lightmapd:lightmapd@127.0.0.1:5432/lightmapd";

/// For tests: the PostgreSQL URL from [`TEST_URL_VAR`], else [`DEFAULT_TEST_URL`] when
/// something listens on its port (so the README's test command, after
/// `scripts/setup.sh`, runs the PostgreSQL variants too), else `None` after printing a
/// loud skip line naming `test`. Panics instead of skipping when
/// [`REQUIRE_SERVICES_VAR`] is `1`, so CI cannot pass by skipping.
pub fn test_url(test: &str) -> Option<String> {
    if let Ok(url) = std::env::var(TEST_URL_VAR)
        && !url.is_empty()
    {
        return Some(url);
    }
    let port = std::net::SocketAddr::from(([127, 0, 0, 1], 5432));
    if std::net::TcpStream::connect_timeout(&port, Duration::from_millis(300)).is_ok() {
        return Some(DEFAULT_TEST_URL.into());
    }
    if std::env::var(REQUIRE_SERVICES_VAR).is_ok_and(|v| v == "1") {
        panic!(
            "{test}: {TEST_URL_VAR} is not set and nothing listens on 127.0.0.1:5432, but {REQUIRE_SERVICES_VAR}=1 (run `bash scripts/setup.sh test`)"
        );
    }
    eprintln!(
        "\n==== SKIPPED {test}: PostgreSQL variant: {TEST_URL_VAR} is not set and nothing listens on 127.0.0.1:5432 (run `bash scripts/setup.sh test`, or export {TEST_URL_VAR}=postgres://…) ====\n"
    );
    None
}

#[derive(Clone)]
pub struct PostgresQueue {
    pool: PgPool,
}

impl PostgresQueue {
    /// Connects to a `postgres://` URL and migrates the database.
    pub async fn open(url: &str) -> QueueResult<PostgresQueue> {
        Self::connect(PgConnectOptions::from_str(url)?).await
    }

    /// Connects, creates `schema` if it does not exist, and keeps every table there.
    pub async fn open_in_schema(url: &str, schema: &str) -> QueueResult<PostgresQueue> {
        let schema = plain_identifier(schema)?;
        let opts = PgConnectOptions::from_str(url)?;
        crate::service::install_crypto_provider();
        let admin = PgPoolOptions::new()
            .max_connections(1)
            .connect_with(opts.clone())
            .await?;
        sqlx::query(AssertSqlSafe(format!("CREATE SCHEMA IF NOT EXISTS {schema}")))
            .execute(&admin)
            .await?;
        admin.close().await;
        Self::connect(opts.options([("search_path", schema)])).await
    }

    async fn connect(opts: PgConnectOptions) -> QueueResult<PostgresQueue> {
        crate::service::install_crypto_provider();
        let pool = PgPoolOptions::new()
            .max_connections(MAX_CONNECTIONS + 1)
            .acquire_timeout(Duration::from_secs(10))
            .connect_with(opts)
            .await?;
        MIGRATOR.run(&pool).await?;
        Ok(PostgresQueue { pool })
    }

    /// Drops `schema` and everything in it (tests clean up with this).
    pub async fn drop_schema(&self, schema: &str) -> QueueResult<()> {
        let schema = plain_identifier(schema)?;
        sqlx::query(AssertSqlSafe(format!("DROP SCHEMA IF EXISTS {schema} CASCADE")))
            .execute(&self.pool)
            .await?;
        Ok(())
    }
}

/// A schema name is spliced into DDL (it cannot be a bind parameter): only letters,
/// digits and `_` pass, so it can neither quote nor inject.
fn plain_identifier(name: &str) -> QueueResult<&str> {
    if name.is_empty() || name.len() > 63 || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
        return Err(sqlx::Error::Configuration(
            format!("schema name {name:?}: use 1 to 63 letters, digits and '_'").into(),
        ));
    }
    Ok(name)
}

fn job_from_row(row: &PgRow) -> QueueResult<JobRecord> {
    let spec: Value = row.try_get("spec")?;
    let spec: JobSpec = serde_json::from_value(spec).map_err(|e| sqlx::Error::Decode(Box::new(e)))?;
    let status: String = row.try_get("status")?;
    let status = JobStatus::parse(&status)
        .ok_or_else(|| sqlx::Error::Decode(format!("unknown job status {status:?}").into()))?;
    Ok(JobRecord {
        id: row.try_get("id")?,
        scene_id: row.try_get("scene_id")?,
        spec,
        status,
        priority: row.try_get("priority")?,
        created_at: row.try_get("created_at")?,
        started_at: row.try_get("started_at")?,
        finished_at: row.try_get("finished_at")?,
        attempts: row.try_get::<i32, _>("attempts")?.max(0) as u32,
        worker: row.try_get("worker")?,
        lease_expires_at: row.try_get("lease_expires_at")?,
        cancel_requested: row.try_get("cancel_requested")?,
        progress: row.try_get("progress")?,
        history: row
            .try_get::<Option<Value>, _>("history")?
            .unwrap_or(Value::Array(vec![])),
        plan: row.try_get("plan")?,
        snapshots: row.try_get::<i32, _>("snapshots")?.max(0) as u32,
        summary: row.try_get("summary")?,
        failure: row.try_get("failure")?,
        updated_at: row.try_get("updated_at")?,
        client: row.try_get("client")?,
        tasks: row.try_get::<i32, _>("tasks")?.max(0) as u32,
        memory_bytes: row.try_get::<i64, _>("memory_bytes")?.max(0) as u64,
    })
}

fn task_from_row(row: &PgRow) -> QueueResult<TaskRecord> {
    let status: String = row.try_get("status")?;
    Ok(TaskRecord {
        job_id: row.try_get("job_id")?,
        index: row.try_get::<i32, _>("idx")?.max(0) as u32,
        count: row.try_get::<i32, _>("count")?.max(0) as u32,
        status: TaskStatus::parse(&status)
            .ok_or_else(|| sqlx::Error::Decode(format!("unknown task status {status:?}").into()))?,
        attempts: row.try_get::<i32, _>("attempts")?.max(0) as u32,
        worker: row.try_get("worker")?,
        lease_expires_at: row.try_get("lease_expires_at")?,
        steps: row.try_get::<i64, _>("steps")?.max(0) as u64,
        seconds: row.try_get("seconds")?,
        error: row.try_get("error")?,
        failure: row.try_get("failure")?,
        started_at: row.try_get("started_at")?,
        finished_at: row.try_get("finished_at")?,
    })
}

fn worker_from_row(row: &PgRow) -> QueueResult<WorkerRecord> {
    let caps: Value = row.try_get("capabilities")?;
    Ok(WorkerRecord {
        id: row.try_get("id")?,
        capabilities: serde_json::from_value(caps).unwrap_or_default(),
        started_at: row.try_get("started_at")?,
        last_seen: row.try_get("last_seen")?,
    })
}

/// Takes the job's task lock for the rest of the transaction (see the module doc: every
/// write to a split job's tasks holds it, so they run one at a time per job).
async fn lock_job(c: &mut PgConnection, job: &str) -> QueueResult<()> {
    sqlx::query("SELECT pg_advisory_xact_lock($1, hashtext($2))")
        .bind(KEY_TASKS)
        .bind(job)
        .execute(&mut *c)
        .await?;
    Ok(())
}

/// [`lock_job`] if it is free now; `false` otherwise (the claim's way in, which already
/// holds a task row and so must not wait).
async fn try_lock_job(c: &mut PgConnection, job: &str) -> QueueResult<bool> {
    sqlx::query_scalar("SELECT pg_try_advisory_xact_lock($1, hashtext($2))")
        .bind(KEY_TASKS)
        .bind(job)
        .fetch_one(&mut *c)
        .await
}

/// A job's spec, as submitted.
async fn job_spec(c: &mut PgConnection, job: &str) -> QueueResult<JobSpec> {
    let spec: Value = sqlx::query_scalar("SELECT spec FROM jobs WHERE id = $1")
        .bind(job)
        .fetch_one(&mut *c)
        .await?;
    serde_json::from_value(spec).map_err(|e| sqlx::Error::Decode(Box::new(e)))
}

/// Writes a split job's merged progress from its bake tasks' rows.
async fn refresh_progress(c: &mut PgConnection, job: &str, now: i64) -> QueueResult<()> {
    let Some(row) = sqlx::query("SELECT spec, started_at, history, snapshots FROM jobs WHERE id = $1")
        .bind(job)
        .fetch_optional(&mut *c)
        .await?
    else {
        return Ok(());
    };
    let spec: Value = row.try_get("spec")?;
    let spec: JobSpec = serde_json::from_value(spec).map_err(|e| sqlx::Error::Decode(Box::new(e)))?;
    let tasks: Vec<(i64, Option<f32>)> =
        sqlx::query_as("SELECT steps, error FROM tasks WHERE job_id = $1 AND idx < count ORDER BY idx")
            .bind(job)
            .fetch_all(&mut *c)
            .await?;
    let tasks: Vec<(u64, Option<f32>)> = tasks.into_iter().map(|(s, e)| (s.max(0) as u64, e)).collect();
    let progress = merged_progress(&spec, row.try_get("started_at")?, now, &tasks);
    let history = row
        .try_get::<Option<Value>, _>("history")?
        .unwrap_or(Value::Array(vec![]));
    let snapshots: i32 = row.try_get("snapshots")?;
    let history = running_history(&history, &progress, snapshots.max(0) as u32);
    sqlx::query(
        "UPDATE jobs SET progress = $2, updated_at = $3, history = COALESCE($4, history)
         WHERE id = $1 AND status = 'running'",
    )
    .bind(job)
    .bind(progress)
    .bind(now)
    .bind(history)
    .execute(&mut *c)
    .await?;
    Ok(())
}

/// Counts a failed or abandoned attempt against `worker` (the blocklist's count).
async fn count_failure(c: &mut PgConnection, job: &str, worker: &str, reason: &str, now: i64) -> QueueResult<()> {
    sqlx::query(
        "INSERT INTO task_failures (job_id, worker, failures, last_reason, updated_at) VALUES ($1, $2, 1, $3, $4)
         ON CONFLICT (job_id, worker) DO UPDATE SET failures = task_failures.failures + 1, last_reason = $3,
             updated_at = $4",
    )
    .bind(job)
    .bind(worker)
    .bind(reason)
    .bind(now)
    .execute(&mut *c)
    .await?;
    Ok(())
}

/// Fails a split job for good: the job `failed` with `reason`, its unfinished tasks
/// `cancelled` (a running one's next heartbeat finds its lease lost).
async fn fail_split_job(c: &mut PgConnection, job: &str, reason: &str, now: i64) -> QueueResult<bool> {
    let r = sqlx::query(
        "UPDATE jobs SET status = 'failed', finished_at = $2, updated_at = $2, failure = $3
         WHERE id = $1 AND status IN ('queued', 'running')",
    )
    .bind(job)
    .bind(now)
    .bind(reason)
    .execute(&mut *c)
    .await?;
    sqlx::query(
        "UPDATE tasks SET status = 'cancelled', updated_at = $2, lease_expires_at = NULL
         WHERE job_id = $1 AND status IN ('waiting', 'queued', 'running')",
    )
    .bind(job)
    .bind(now)
    .execute(&mut *c)
    .await?;
    Ok(r.rows_affected() == 1)
}

/// A split job being cancelled: its tasks not running are cancelled, and once none
/// runs the job is `cancelled`. True when the job ended here.
async fn settle_cancel(c: &mut PgConnection, job: &str, now: i64) -> QueueResult<bool> {
    sqlx::query(
        "UPDATE tasks SET status = 'cancelled', updated_at = $2
         WHERE job_id = $1 AND status IN ('waiting', 'queued')
           AND (SELECT cancel_requested FROM jobs WHERE id = $1)",
    )
    .bind(job)
    .bind(now)
    .execute(&mut *c)
    .await?;
    let r = sqlx::query(
        "UPDATE jobs SET status = 'cancelled', finished_at = $2, updated_at = $2
         WHERE id = $1 AND tasks > 0 AND cancel_requested AND status IN ('queued', 'running')
           AND NOT EXISTS (SELECT 1 FROM tasks WHERE job_id = $1 AND status = 'running')",
    )
    .bind(job)
    .bind(now)
    .execute(&mut *c)
    .await?;
    Ok(r.rows_affected() == 1)
}

/// The task half of [`Queue::recover_expired`] (as in the SQLite store): job by job,
/// in id order, under each job's task lock.
#[allow(clippy::type_complexity)]
async fn recover_tasks(c: &mut PgConnection, now: i64) -> QueueResult<(Vec<(String, u32)>, Vec<String>, Vec<String>)> {
    let jobs: Vec<String> = sqlx::query_scalar(
        "SELECT DISTINCT job_id FROM tasks WHERE status = 'running' AND lease_expires_at < $1 ORDER BY job_id",
    )
    .bind(now)
    .fetch_all(&mut *c)
    .await?;
    let (mut requeued, mut failed, mut cancelled) = (Vec::new(), Vec::new(), Vec::new());
    for job in jobs {
        lock_job(c, &job).await?;
        let (stopping, status): (bool, String) =
            sqlx::query_as("SELECT cancel_requested, status FROM jobs WHERE id = $1")
                .bind(&job)
                .fetch_one(&mut *c)
                .await?;
        // Read again under the lock: a late heartbeat may have renewed a lease meanwhile.
        let expired: Vec<(i32, i32, i32, Option<String>)> = sqlx::query_as(
            "SELECT idx, count, attempts, worker FROM tasks
             WHERE job_id = $1 AND status = 'running' AND lease_expires_at < $2 ORDER BY idx",
        )
        .bind(&job)
        .bind(now)
        .fetch_all(&mut *c)
        .await?;
        if stopping || status != "running" {
            sqlx::query(
                "UPDATE tasks SET status = 'cancelled', updated_at = $2, lease_expires_at = NULL
                 WHERE job_id = $1 AND status = 'running' AND lease_expires_at < $2",
            )
            .bind(&job)
            .bind(now)
            .execute(&mut *c)
            .await?;
            if settle_cancel(c, &job, now).await? {
                cancelled.push(job);
            }
            continue;
        }
        for (idx, count, attempts, worker) in expired {
            if let Some(w) = &worker {
                count_failure(c, &job, w, "its lease expired (the worker stopped renewing it)", now).await?;
            }
            if attempts >= MAX_ATTEMPTS as i32 {
                sqlx::query(
                    "UPDATE tasks SET status = 'failed', finished_at = $3, updated_at = $3, lease_expires_at = NULL,
                         failure = 'its lease expired ' || attempts || ' times'
                     WHERE job_id = $1 AND idx = $2",
                )
                .bind(&job)
                .bind(idx)
                .bind(now)
                .execute(&mut *c)
                .await?;
                let why = lease_given_up(i64::from(idx), i64::from(count), worker.as_deref());
                if fail_split_job(c, &job, &why, now).await? {
                    failed.push(job.clone());
                }
                break;
            }
            sqlx::query(
                "UPDATE tasks SET status = 'queued', updated_at = $3, worker = NULL, lease_expires_at = NULL
                 WHERE job_id = $1 AND idx = $2",
            )
            .bind(&job)
            .bind(idx)
            .bind(now)
            .execute(&mut *c)
            .await?;
            requeued.push((job.clone(), idx.max(0) as u32));
        }
    }
    Ok((requeued, failed, cancelled))
}

fn scene_from_row(row: &PgRow) -> QueueResult<SceneRecord> {
    let files: Value = row.try_get("files")?;
    Ok(SceneRecord {
        id: row.try_get("id")?,
        content_hash: row.try_get("content_hash")?,
        format: row.try_get("format")?,
        main_file: row.try_get("main_file")?,
        files: serde_json::from_value(files).unwrap_or_default(),
        size_bytes: row.try_get::<i64, _>("size_bytes")?.max(0) as u64,
        report: row.try_get("report")?,
        created_at: row.try_get("created_at")?,
        client: row.try_get("client")?,
    })
}

fn token_from_row(row: &PgRow) -> QueueResult<TokenRecord> {
    Ok(TokenRecord {
        id: row.try_get("id")?,
        name: row.try_get("name")?,
        hash: row.try_get("hash")?,
        created_at: row.try_get("created_at")?,
        revoked_at: row.try_get("revoked_at")?,
        role: Role::parse(&row.try_get::<String, _>("role")?).unwrap_or(Role::Editor),
        source: row.try_get("source")?,
    })
}

fn lease_until(now: i64, lease: Duration) -> i64 {
    now + lease.as_millis() as i64
}

fn clamp_i64(v: u64) -> i64 {
    i64::try_from(v).unwrap_or(i64::MAX)
}

/// Forwards notifications into `hub` until shutdown; reconnects after a lost connection.
async fn forward_notifications(pool: PgPool, hub: Arc<Hub>, mut shutdown: watch::Receiver<bool>) {
    loop {
        let listener = async {
            let mut l = PgListener::connect_with(&pool).await?;
            l.listen_all([WORK_CHANNEL, JOB_CHANNEL]).await?;
            Ok::<_, sqlx::Error>(l)
        };
        let mut listener = tokio::select! {
            l = listener => match l {
                Ok(l) => l,
                Err(e) => {
                    tracing::warn!(error = %e, "cannot LISTEN; polling only, trying again in 1 s");
                    tokio::select! {
                        _ = tokio::time::sleep(Duration::from_secs(1)) => continue,
                        _ = shutting_down(&mut shutdown) => return,
                    }
                }
            },
            _ = shutting_down(&mut shutdown) => return,
        };
        loop {
            tokio::select! {
                n = listener.try_recv() => match n {
                    Ok(Some(n)) if n.channel() == WORK_CHANNEL => hub.work.notify_waiters(),
                    Ok(Some(n)) => hub.job_changed(n.payload()),
                    // The connection dropped (the listener reconnects on the next call);
                    // what was sent meanwhile is lost, so idle workers look now.
                    Ok(None) => hub.work.notify_waiters(),
                    Err(e) => {
                        tracing::warn!(error = %e, "LISTEN connection failed; reconnecting");
                        break;
                    }
                },
                _ = shutting_down(&mut shutdown) => return,
            }
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_secs(1)) => {}
            _ = shutting_down(&mut shutdown) => return,
        }
    }
}

#[async_trait]
impl Queue for PostgresQueue {
    fn listen(&self, hub: Arc<Hub>, shutdown: watch::Receiver<bool>) -> Option<JoinHandle<()>> {
        Some(tokio::spawn(forward_notifications(self.pool.clone(), hub, shutdown)))
    }

    async fn insert_scene(&self, s: &SceneRecord) -> QueueResult<bool> {
        let r = sqlx::query(
            "INSERT INTO scenes (id, content_hash, format, main_file, files, size_bytes, report, created_at, client)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) ON CONFLICT (id) DO NOTHING",
        )
        .bind(&s.id)
        .bind(&s.content_hash)
        .bind(&s.format)
        .bind(&s.main_file)
        .bind(serde_json::to_value(&s.files).unwrap_or(Value::Array(vec![])))
        .bind(clamp_i64(s.size_bytes))
        .bind(&s.report)
        .bind(s.created_at)
        .bind(&s.client)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    async fn scene(&self, id: &str) -> QueueResult<Option<SceneRecord>> {
        let row = sqlx::query("SELECT * FROM scenes WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(scene_from_row).transpose()
    }

    async fn scenes(&self, client: Option<&str>) -> QueueResult<Vec<SceneRecord>> {
        let rows =
            sqlx::query("SELECT * FROM scenes WHERE ($1::text IS NULL OR client = $1) ORDER BY created_at DESC, id")
                .bind(client)
                .fetch_all(&self.pool)
                .await?;
        rows.iter().map(scene_from_row).collect()
    }

    async fn delete_scene(&self, id: &str) -> QueueResult<SceneDeletion> {
        let mut tx = self.pool.begin().await?;
        // The row lock makes a concurrent enqueue (which reads the scene FOR SHARE) either
        // finish first, so its job is counted below, or wait and find no scene.
        let exists: Option<i32> = sqlx::query_scalar("SELECT 1 FROM scenes WHERE id = $1 FOR UPDATE")
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?;
        if exists.is_none() {
            return Ok(SceneDeletion::NotFound);
        }
        let in_use: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE scene_id = $1 AND status IN ('queued', 'running')")
                .bind(id)
                .fetch_one(&mut *tx)
                .await?;
        if in_use > 0 {
            return Ok(SceneDeletion::InUse(in_use as u64));
        }
        sqlx::query("DELETE FROM scenes WHERE id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(SceneDeletion::Deleted)
    }

    async fn enqueue(
        &self,
        id: &str,
        spec: &JobSpec,
        client: &str,
        max_queued: u64,
        memory_bytes: u64,
        now: i64,
    ) -> QueueResult<Enqueued> {
        let mut tx = self.pool.begin().await?;
        // Serialises this client's submissions (on every API process) until commit.
        sqlx::query("SELECT pg_advisory_xact_lock($1, hashtext($2))")
            .bind(KEY_CLASS)
            .bind(client)
            .execute(&mut *tx)
            .await?;
        let scene: Option<i32> = sqlx::query_scalar("SELECT 1 FROM scenes WHERE id = $1 FOR SHARE")
            .bind(&spec.scene)
            .fetch_optional(&mut *tx)
            .await?;
        if scene.is_none() {
            return Ok(Enqueued::NoScene);
        }
        let queued: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE client = $1 AND status = 'queued'")
            .bind(client)
            .fetch_one(&mut *tx)
            .await?;
        if queued >= clamp_i64(max_queued) {
            return Ok(Enqueued::QueueFull(queued as u64));
        }
        let tasks = spec.bake_tasks();
        let first_queued = spec.first_queued();
        let requires = spec.requires.unwrap_or_default();
        let row = sqlx::query(
            "INSERT INTO jobs (id, scene_id, spec, status, priority, created_at, updated_at, client, tasks,
                               requires_gpu, requires_oidn, memory_bytes)
             VALUES ($1, $2, $3, 'queued', $4, $5, $5, $6, $7, $8, $9, $10)
             RETURNING *",
        )
        .bind(id)
        .bind(&spec.scene)
        .bind(serde_json::to_value(spec).map_err(|e| sqlx::Error::Encode(Box::new(e)))?)
        .bind(spec.priority)
        .bind(now)
        .bind(client)
        .bind(tasks as i32)
        .bind(requires.gpu)
        .bind(requires.oidn)
        .bind(clamp_i64(memory_bytes))
        .fetch_one(&mut *tx)
        .await?;
        if tasks > 0 {
            // Bake tasks 0..n queued (in rounds, round 0's; the later rounds wait for the
            // round before), the merge (index n) waiting for them.
            sqlx::query(
                "INSERT INTO tasks (job_id, idx, count, status, updated_at)
                 SELECT $1, i, $2, CASE WHEN i < $4 THEN 'queued' ELSE 'waiting' END, $3
                 FROM generate_series(0, $2) AS i",
            )
            .bind(id)
            .bind(tasks as i32)
            .bind(now)
            .bind(first_queued as i32)
            .execute(&mut *tx)
            .await?;
        }
        let job = job_from_row(&row)?;
        tx.commit().await?;
        Ok(Enqueued::Queued(Box::new(job)))
    }

    async fn job(&self, id: &str) -> QueueResult<Option<JobRecord>> {
        let row = sqlx::query("SELECT * FROM jobs WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(job_from_row).transpose()
    }

    async fn list(
        &self,
        status: Option<JobStatus>,
        client: Option<&str>,
        limit: u32,
        offset: u64,
    ) -> QueueResult<(Vec<JobRecord>, u64)> {
        let status = status.map(JobStatus::as_str);
        let rows = sqlx::query(
            "SELECT * FROM jobs WHERE ($1::text IS NULL OR status = $1) AND ($4::text IS NULL OR client = $4)
             ORDER BY created_at DESC, seq DESC LIMIT $2 OFFSET $3",
        )
        .bind(status)
        .bind(i64::from(limit))
        .bind(clamp_i64(offset))
        .bind(client)
        .fetch_all(&self.pool)
        .await?;
        let total: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM jobs WHERE ($1::text IS NULL OR status = $1) AND ($2::text IS NULL OR client = $2)",
        )
        .bind(status)
        .bind(client)
        .fetch_one(&self.pool)
        .await?;
        let jobs = rows.iter().map(job_from_row).collect::<QueueResult<Vec<_>>>()?;
        Ok((jobs, total as u64))
    }

    async fn counts(&self) -> QueueResult<Vec<(JobStatus, u64)>> {
        let rows = sqlx::query("SELECT status, COUNT(*) AS n FROM jobs GROUP BY status")
            .fetch_all(&self.pool)
            .await?;
        let mut out: Vec<(JobStatus, u64)> = JobStatus::ALL.iter().map(|s| (*s, 0)).collect();
        for row in rows {
            let s: String = row.try_get("status")?;
            let n: i64 = row.try_get("n")?;
            if let Some(slot) = out.iter_mut().find(|(st, _)| st.as_str() == s) {
                slot.1 = n as u64;
            }
        }
        Ok(out)
    }

    async fn cancel(&self, id: &str, now: i64) -> QueueResult<Cancellation> {
        let r = sqlx::query(
            "UPDATE jobs SET status = 'cancelled', finished_at = $2, updated_at = $2
             WHERE id = $1 AND status = 'queued'",
        )
        .bind(id)
        .bind(now)
        .execute(&self.pool)
        .await?;
        if r.rows_affected() == 1 {
            // A split job's tasks end with it.
            sqlx::query(
                "UPDATE tasks SET status = 'cancelled', updated_at = $2 WHERE job_id = $1 AND status IN ('waiting', 'queued')",
            )
            .bind(id)
            .bind(now)
            .execute(&self.pool)
            .await?;
            return Ok(Cancellation::Cancelled);
        }
        let mut tx = self.pool.begin().await?;
        lock_job(&mut tx, id).await?;
        let r = sqlx::query(
            "UPDATE jobs SET cancel_requested = TRUE, updated_at = $2 WHERE id = $1 AND status = 'running'",
        )
        .bind(id)
        .bind(now)
        .execute(&mut *tx)
        .await?;
        if r.rows_affected() == 1 {
            // A split job with no task running ends now; otherwise its running tasks
            // stop at their next heartbeat and the last one to stop ends it.
            let ended = settle_cancel(&mut tx, id, now).await?;
            tx.commit().await?;
            return Ok(if ended {
                Cancellation::Cancelled
            } else {
                Cancellation::Requested
            });
        }
        drop(tx);
        let status: Option<String> = sqlx::query_scalar("SELECT status FROM jobs WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(match status.as_deref().and_then(JobStatus::parse) {
            None => Cancellation::NotFound,
            Some(s) => Cancellation::AlreadyFinished(s),
        })
    }

    async fn claim(
        &self,
        worker: &str,
        caps: &Capabilities,
        lease: Duration,
        now: i64,
    ) -> QueueResult<Option<JobRecord>> {
        let row = sqlx::query(
            "UPDATE jobs SET status = 'running', worker = $1, attempts = attempts + 1, lease_expires_at = $2,
                 started_at = $3, updated_at = $3, progress = NULL, history = '[]', plan = NULL
             WHERE id = (SELECT id FROM jobs WHERE status = 'queued' AND tasks = 0
                           AND (NOT requires_gpu OR $4) AND (NOT requires_oidn OR $5) AND memory_bytes <= $6
                         ORDER BY priority DESC, created_at, seq LIMIT 1
                         FOR UPDATE SKIP LOCKED)
             RETURNING *",
        )
        .bind(worker)
        .bind(lease_until(now, lease))
        .bind(now)
        .bind(caps.gpu)
        .bind(caps.oidn)
        .bind(clamp_i64(caps.memory_bytes))
        .fetch_optional(&self.pool)
        .await?;
        row.as_ref().map(job_from_row).transpose()
    }

    async fn claim_task(
        &self,
        worker: &str,
        caps: &Capabilities,
        lease: Duration,
        now: i64,
    ) -> QueueResult<Option<(TaskRecord, JobRecord)>> {
        for attempt in 0..8u64 {
            let mut tx = self.pool.begin().await?;
            let pick: Option<(String, i32)> = sqlx::query_as(
                "SELECT t.job_id, t.idx FROM tasks t JOIN jobs j ON j.id = t.job_id
                 WHERE t.status = 'queued' AND j.status IN ('queued', 'running') AND NOT j.cancel_requested
                   AND (NOT j.requires_gpu OR $2) AND (NOT j.requires_oidn OR $3) AND j.memory_bytes <= $5
                   AND NOT EXISTS (SELECT 1 FROM task_failures f
                                   WHERE f.job_id = t.job_id AND f.worker = $1 AND f.failures >= $4)
                   AND NOT EXISTS (SELECT 1 FROM jobs w
                                   WHERE w.status = 'queued' AND w.tasks = 0
                                     AND (NOT w.requires_gpu OR $2) AND (NOT w.requires_oidn OR $3)
                                     AND w.memory_bytes <= $5
                                     AND (w.priority, -w.created_at, -w.seq) > (j.priority, -j.created_at, -j.seq))
                 ORDER BY j.priority DESC, j.created_at, j.seq, t.idx LIMIT 1
                 FOR UPDATE OF t SKIP LOCKED",
            )
            .bind(worker)
            .bind(caps.gpu)
            .bind(caps.oidn)
            .bind(BLOCKLIST_AFTER as i32)
            .bind(clamp_i64(caps.memory_bytes))
            .fetch_optional(&mut *tx)
            .await?;
            let Some((job_id, idx)) = pick else {
                return Ok(None);
            };
            if !try_lock_job(&mut tx, &job_id).await? {
                // Someone is writing this job's tasks: let the row go, look again.
                drop(tx);
                tokio::time::sleep(Duration::from_millis(1 + 2 * attempt)).await;
                continue;
            }
            let row = sqlx::query(
                "UPDATE tasks SET status = 'running', worker = $3, attempts = attempts + 1, lease_expires_at = $4,
                     started_at = $5, updated_at = $5, steps = 0, seconds = 0, error = NULL, failure = NULL,
                     finished_at = NULL
                 WHERE job_id = $1 AND idx = $2
                 RETURNING *",
            )
            .bind(&job_id)
            .bind(idx)
            .bind(worker)
            .bind(lease_until(now, lease))
            .bind(now)
            .fetch_one(&mut *tx)
            .await?;
            let task = task_from_row(&row)?;
            sqlx::query(
                "UPDATE jobs SET status = 'running', started_at = COALESCE(started_at, $2), updated_at = $2
                 WHERE id = $1 AND status = 'queued'",
            )
            .bind(&job_id)
            .bind(now)
            .execute(&mut *tx)
            .await?;
            let job = job_from_row(
                &sqlx::query("SELECT * FROM jobs WHERE id = $1")
                    .bind(&job_id)
                    .fetch_one(&mut *tx)
                    .await?,
            )?;
            if job.status != JobStatus::Running || job.cancel_requested {
                // Cancelled (or ended) between the pick and the lock: the task ends with it.
                sqlx::query("UPDATE tasks SET status = 'cancelled', worker = NULL, lease_expires_at = NULL WHERE job_id = $1 AND idx = $2")
                    .bind(&job_id)
                    .bind(idx)
                    .execute(&mut *tx)
                    .await?;
                tx.commit().await?;
                continue;
            }
            tx.commit().await?;
            return Ok(Some((task, job)));
        }
        // Every try met a busy job: the worker's next poll looks again.
        Ok(None)
    }

    async fn task_heartbeat(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        lease: Duration,
        beat: Option<&TaskBeat>,
        now: i64,
    ) -> QueueResult<Lease> {
        let mut tx = self.pool.begin().await?;
        lock_job(&mut tx, job).await?;
        let cancel: Option<bool> = sqlx::query_scalar(
            "UPDATE tasks SET lease_expires_at = $4, updated_at = $5,
                 steps = COALESCE($6, steps), seconds = COALESCE($7, seconds),
                 error = CASE WHEN $6::bigint IS NULL THEN error ELSE $8 END
             WHERE job_id = $1 AND idx = $2 AND worker = $3 AND status = 'running'
             RETURNING (SELECT cancel_requested FROM jobs WHERE id = $1)",
        )
        .bind(job)
        .bind(index as i32)
        .bind(worker)
        .bind(lease_until(now, lease))
        .bind(now)
        .bind(beat.map(|b| clamp_i64(b.steps)))
        .bind(beat.map(|b| b.seconds))
        .bind(beat.and_then(|b| b.error))
        .fetch_optional(&mut *tx)
        .await?;
        let Some(cancel) = cancel else {
            return Ok(Lease::Lost);
        };
        if beat.is_some() {
            refresh_progress(&mut tx, job, now).await?;
        }
        tx.commit().await?;
        Ok(Lease::Held { cancel })
    }

    async fn claim_task_snapshot(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        interval: Duration,
        now: i64,
    ) -> QueueResult<Option<u32>> {
        // One statement: concurrent claims queue on the job's row and see the winner's
        // `snapshot_claimed_at` when they re-check it, so one wins an interval.
        let n: Option<i32> = sqlx::query_scalar(
            "UPDATE jobs SET snapshot_claims = GREATEST(snapshot_claims, snapshots) + 1, snapshot_claimed_at = $3
             WHERE id = $1 AND status = 'running'
               AND (snapshot_claimed_at IS NULL OR snapshot_claimed_at <= $3 - $4)
               AND EXISTS (SELECT 1 FROM tasks WHERE job_id = $1 AND idx = $2 AND worker = $5 AND status = 'running')
             RETURNING snapshot_claims",
        )
        .bind(job)
        .bind(index as i32)
        .bind(now)
        .bind(interval.as_millis().min(i64::MAX as u128) as i64)
        .bind(worker)
        .fetch_optional(&self.pool)
        .await?;
        Ok(n.map(|n| n.max(0) as u32))
    }

    async fn task_snapshot_stored(&self, job: &str, n: u32, point: &Value) -> QueueResult<bool> {
        // Under the job's lock: `refresh_progress` reads the history and writes it back,
        // and must not write over the point added here.
        let mut tx = self.pool.begin().await?;
        lock_job(&mut tx, job).await?;
        let history: Option<Value> =
            sqlx::query_scalar("SELECT history FROM jobs WHERE id = $1 AND status = 'running'")
                .bind(job)
                .fetch_optional(&mut *tx)
                .await?;
        let Some(history) = history else {
            return Ok(false);
        };
        let done = sqlx::query(
            "UPDATE jobs SET snapshots = GREATEST(snapshots, $2), history = $3 WHERE id = $1 AND status = 'running'",
        )
        .bind(job)
        .bind(i32::try_from(n).unwrap_or(i32::MAX))
        .bind(with_snapshot_point(&history, point))
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(done.rows_affected() == 1)
    }

    async fn release_task_snapshot(&self, job: &str, n: u32) -> QueueResult<()> {
        sqlx::query("UPDATE jobs SET snapshot_claims = $2 - 1 WHERE id = $1 AND snapshot_claims = $2")
            .bind(job)
            .bind(i32::try_from(n).unwrap_or(i32::MAX))
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    async fn finish_task(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        outcome: &TaskOutcome,
        now: i64,
    ) -> QueueResult<bool> {
        let mut tx = self.pool.begin().await?;
        lock_job(&mut tx, job).await?;
        let row: Option<(i32, i32)> = sqlx::query_as(
            "UPDATE tasks SET updated_at = $4, lease_expires_at = NULL
             WHERE job_id = $1 AND idx = $2 AND worker = $3 AND status = 'running'
             RETURNING attempts, count",
        )
        .bind(job)
        .bind(index as i32)
        .bind(worker)
        .bind(now)
        .fetch_optional(&mut *tx)
        .await?;
        let Some((attempts, count)) = row else {
            return Ok(false);
        };
        let set = |status: &'static str| {
            sqlx::query(
                "UPDATE tasks SET status = $3, finished_at = CASE WHEN $3 = 'queued' THEN NULL ELSE $4 END,
                     worker = CASE WHEN $3 = 'queued' THEN NULL ELSE worker END, failure = $5
                 WHERE job_id = $1 AND idx = $2",
            )
            .bind(job)
            .bind(index as i32)
            .bind(status)
            .bind(now)
        };
        match outcome {
            TaskOutcome::Baked(b) => {
                set("succeeded").bind(None::<String>).execute(&mut *tx).await?;
                sqlx::query("UPDATE tasks SET steps = $3, seconds = $4, error = $5 WHERE job_id = $1 AND idx = $2")
                    .bind(job)
                    .bind(index as i32)
                    .bind(clamp_i64(b.steps))
                    .bind(b.seconds)
                    .bind(b.error)
                    .execute(&mut *tx)
                    .await?;
                // The last task of a round in queues the next round's.
                if let Some([first, next, end]) = round_after(&job_spec(&mut tx, job).await?, index) {
                    sqlx::query(
                        "UPDATE tasks SET status = 'queued', updated_at = $2
                         WHERE job_id = $1 AND idx >= $4 AND idx < $5 AND status = 'waiting'
                           AND NOT EXISTS (SELECT 1 FROM tasks WHERE job_id = $1 AND idx >= $3 AND idx < $4
                                             AND status <> 'succeeded')",
                    )
                    .bind(job)
                    .bind(now)
                    .bind(first as i32)
                    .bind(next as i32)
                    .bind(end as i32)
                    .execute(&mut *tx)
                    .await?;
                }
                // The last bake task in queues the merge.
                sqlx::query(
                    "UPDATE tasks SET status = 'queued', updated_at = $2
                     WHERE job_id = $1 AND idx = count AND status = 'waiting'
                       AND NOT EXISTS (SELECT 1 FROM tasks WHERE job_id = $1 AND idx < count AND status <> 'succeeded')",
                )
                .bind(job)
                .bind(now)
                .execute(&mut *tx)
                .await?;
                refresh_progress(&mut tx, job, now).await?;
                settle_cancel(&mut tx, job, now).await?;
            }
            TaskOutcome::Merged {
                summary,
                progress,
                history,
                plan,
            } => {
                set("succeeded").bind(None::<String>).execute(&mut *tx).await?;
                let running: Option<Value> = sqlx::query_scalar("SELECT history FROM jobs WHERE id = $1")
                    .bind(job)
                    .fetch_optional(&mut *tx)
                    .await?
                    .flatten();
                let history = history_then(&running.unwrap_or(Value::Null), history);
                sqlx::query(
                    "UPDATE jobs SET status = 'succeeded', finished_at = $2, updated_at = $2, summary = $3,
                         progress = $4, history = $5, plan = $6
                     WHERE id = $1 AND status = 'running'",
                )
                .bind(job)
                .bind(now)
                .bind(summary)
                .bind(progress)
                .bind(history)
                .bind(plan)
                .execute(&mut *tx)
                .await?;
            }
            TaskOutcome::Failed { reason, retry } => {
                count_failure(&mut tx, job, worker, reason, now).await?;
                if *retry && attempts < MAX_ATTEMPTS as i32 {
                    set("queued").bind(Some(reason.clone())).execute(&mut *tx).await?;
                    settle_cancel(&mut tx, job, now).await?;
                } else {
                    set("failed").bind(Some(reason.clone())).execute(&mut *tx).await?;
                    let why = task_failed(
                        i64::from(index),
                        i64::from(count),
                        i64::from(attempts),
                        worker,
                        reason,
                        *retry,
                    );
                    fail_split_job(&mut tx, job, &why, now).await?;
                }
            }
            TaskOutcome::Cancelled => {
                set("cancelled").bind(None::<String>).execute(&mut *tx).await?;
                settle_cancel(&mut tx, job, now).await?;
            }
        }
        tx.commit().await?;
        Ok(true)
    }

    async fn release_task(&self, job: &str, index: u32, worker: &str, now: i64) -> QueueResult<bool> {
        let mut tx = self.pool.begin().await?;
        lock_job(&mut tx, job).await?;
        let r = sqlx::query(
            "UPDATE tasks SET status = 'queued', attempts = GREATEST(attempts - 1, 0), worker = NULL,
                 lease_expires_at = NULL, updated_at = $4
             WHERE job_id = $1 AND idx = $2 AND worker = $3 AND status = 'running'",
        )
        .bind(job)
        .bind(index as i32)
        .bind(worker)
        .bind(now)
        .execute(&mut *tx)
        .await?;
        // A cancel that arrived during shutdown wins over the hand-back.
        settle_cancel(&mut tx, job, now).await?;
        tx.commit().await?;
        Ok(r.rows_affected() == 1)
    }

    async fn tasks(&self, job: &str) -> QueueResult<Vec<TaskRecord>> {
        let rows = sqlx::query("SELECT * FROM tasks WHERE job_id = $1 ORDER BY idx")
            .bind(job)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(task_from_row).collect()
    }

    async fn task_failures(&self, job: &str) -> QueueResult<Vec<(String, u32)>> {
        let rows: Vec<(String, i32)> =
            sqlx::query_as("SELECT worker, failures FROM task_failures WHERE job_id = $1 ORDER BY worker")
                .bind(job)
                .fetch_all(&self.pool)
                .await?;
        Ok(rows.into_iter().map(|(w, n)| (w, n.max(0) as u32)).collect())
    }

    async fn register_worker(&self, worker: &str, caps: &Capabilities, now: i64) -> QueueResult<()> {
        sqlx::query(
            "INSERT INTO workers (id, capabilities, started_at, last_seen) VALUES ($1, $2, $3, $3)
             ON CONFLICT (id) DO UPDATE SET capabilities = $2, last_seen = $3",
        )
        .bind(worker)
        .bind(serde_json::to_value(caps).map_err(|e| sqlx::Error::Encode(Box::new(e)))?)
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    async fn workers(&self, since: i64) -> QueueResult<Vec<WorkerRecord>> {
        let rows = sqlx::query("SELECT * FROM workers WHERE last_seen >= $1 ORDER BY id")
            .bind(since)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(worker_from_row).collect()
    }

    async fn forget_workers(&self, before: i64) -> QueueResult<u64> {
        let done = sqlx::query("DELETE FROM workers WHERE last_seen < $1")
            .bind(before)
            .execute(&self.pool)
            .await?;
        Ok(done.rows_affected())
    }

    async fn heartbeat(&self, id: &str, worker: &str, lease: Duration, u: &JobUpdate, now: i64) -> QueueResult<Lease> {
        let cancel: Option<bool> = sqlx::query_scalar(
            "UPDATE jobs SET lease_expires_at = $3, updated_at = $4,
                 progress = COALESCE($5, progress), history = COALESCE($6, history),
                 plan = COALESCE($7, plan), snapshots = COALESCE($8, snapshots)
             WHERE id = $1 AND worker = $2 AND status = 'running'
             RETURNING cancel_requested",
        )
        .bind(id)
        .bind(worker)
        .bind(lease_until(now, lease))
        .bind(now)
        .bind(&u.progress)
        .bind(&u.history)
        .bind(&u.plan)
        .bind(u.snapshots.map(|n| i32::try_from(n).unwrap_or(i32::MAX)))
        .fetch_optional(&self.pool)
        .await?;
        Ok(match cancel {
            Some(cancel) => Lease::Held { cancel },
            None => Lease::Lost,
        })
    }

    async fn finish(&self, id: &str, worker: &str, outcome: &Outcome, now: i64) -> QueueResult<bool> {
        let (status, summary, progress, history, failure) = match outcome {
            Outcome::Succeeded {
                summary,
                progress,
                history,
            } => ("succeeded", Some(summary), Some(progress), Some(history), None),
            Outcome::Failed { reason } => ("failed", None, None, None, Some(reason.as_str())),
            Outcome::Cancelled => ("cancelled", None, None, None, None),
        };
        let r = sqlx::query(
            "UPDATE jobs SET status = $3, finished_at = $4, updated_at = $4, lease_expires_at = NULL,
                 summary = COALESCE($5, summary), progress = COALESCE($6, progress),
                 history = COALESCE($7, history), failure = $8
             WHERE id = $1 AND worker = $2 AND status = 'running'",
        )
        .bind(id)
        .bind(worker)
        .bind(status)
        .bind(now)
        .bind(summary)
        .bind(progress)
        .bind(history)
        .bind(failure)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    async fn release(&self, id: &str, worker: &str, now: i64) -> QueueResult<bool> {
        // A cancel that arrived during shutdown wins over the hand-back.
        let r = sqlx::query(
            "UPDATE jobs SET
                 status = CASE WHEN cancel_requested THEN 'cancelled' ELSE 'queued' END,
                 finished_at = CASE WHEN cancel_requested THEN $3 ELSE NULL END,
                 attempts = GREATEST(attempts - 1, 0), worker = NULL, lease_expires_at = NULL, updated_at = $3
             WHERE id = $1 AND worker = $2 AND status = 'running'",
        )
        .bind(id)
        .bind(worker)
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    async fn recover_expired(&self, now: i64) -> QueueResult<Recovered> {
        let mut tx = self.pool.begin().await?;
        // Same order as SQLite: cancelled, failed, then re-queued; each statement changes
        // the status, so no row is taken twice. SKIP LOCKED: a row another process is
        // recovering (or its late heartbeat is renewing) is left to that process.
        let cancelled: Vec<String> = sqlx::query_scalar(
            "UPDATE jobs SET status = 'cancelled', finished_at = $1, updated_at = $1, worker = NULL,
                 lease_expires_at = NULL
             WHERE id IN (SELECT id FROM jobs
                          WHERE status = 'running' AND lease_expires_at < $1 AND cancel_requested
                          FOR UPDATE SKIP LOCKED)
             RETURNING id",
        )
        .bind(now)
        .fetch_all(&mut *tx)
        .await?;
        let failed: Vec<String> = sqlx::query_scalar(
            "UPDATE jobs SET status = 'failed', finished_at = $1, updated_at = $1, lease_expires_at = NULL,
                 failure = 'gave up after ' || attempts || ' attempts: the lease of worker ' || COALESCE(worker, '?')
                     || ' expired (the worker stopped renewing it: crashed, killed or cut off)'
             WHERE id IN (SELECT id FROM jobs
                          WHERE status = 'running' AND lease_expires_at < $1 AND attempts >= $2
                          FOR UPDATE SKIP LOCKED)
             RETURNING id",
        )
        .bind(now)
        .bind(MAX_ATTEMPTS as i32)
        .fetch_all(&mut *tx)
        .await?;
        let requeued: Vec<String> = sqlx::query_scalar(
            "UPDATE jobs SET status = 'queued', updated_at = $1, worker = NULL, lease_expires_at = NULL
             WHERE id IN (SELECT id FROM jobs
                          WHERE status = 'running' AND lease_expires_at < $1
                          FOR UPDATE SKIP LOCKED)
             RETURNING id",
        )
        .bind(now)
        .fetch_all(&mut *tx)
        .await?;
        let (tasks_requeued, tasks_failed, tasks_cancelled) = recover_tasks(&mut tx, now).await?;
        tx.commit().await?;
        Ok(Recovered {
            requeued,
            failed: failed.into_iter().chain(tasks_failed).collect(),
            cancelled: cancelled.into_iter().chain(tasks_cancelled).collect(),
            tasks_requeued,
        })
    }

    async fn insert_token(&self, t: &TokenRecord) -> QueueResult<()> {
        sqlx::query(
            "INSERT INTO tokens (id, name, hash, created_at, revoked_at, role, source)
             VALUES ($1, $2, $3, $4, $5, $6, $7)",
        )
        .bind(&t.id)
        .bind(&t.name)
        .bind(&t.hash)
        .bind(t.created_at)
        .bind(t.revoked_at)
        .bind(t.role.as_str())
        .bind(&t.source)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    async fn tokens(&self) -> QueueResult<Vec<TokenRecord>> {
        let rows = sqlx::query("SELECT * FROM tokens ORDER BY created_at, seq")
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(token_from_row).collect()
    }

    async fn revoke_token(&self, id: &str, now: i64) -> QueueResult<bool> {
        let r = sqlx::query("UPDATE tokens SET revoked_at = $2 WHERE id = $1 AND revoked_at IS NULL")
            .bind(id)
            .bind(now)
            .execute(&self.pool)
            .await?;
        Ok(r.rows_affected() > 0)
    }

    async fn token_by_hash(&self, hash: &str) -> QueueResult<Option<TokenRecord>> {
        let row = sqlx::query("SELECT * FROM tokens WHERE hash = $1 AND revoked_at IS NULL")
            .bind(hash)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(token_from_row).transpose()
    }

    async fn clock(&self) -> QueueResult<i64> {
        // clock_timestamp(), not now(): now() is the start of the transaction.
        sqlx::query_scalar("SELECT (extract(epoch FROM clock_timestamp()) * 1000)::BIGINT")
            .fetch_one(&self.pool)
            .await
    }

    async fn delete_job(&self, id: &str) -> QueueResult<JobDeletion> {
        let r = sqlx::query("DELETE FROM jobs WHERE id = $1 AND status IN ('succeeded', 'failed', 'cancelled')")
            .bind(id)
            .execute(&self.pool)
            .await?;
        if r.rows_affected() == 1 {
            return Ok(JobDeletion::Deleted);
        }
        let status: Option<String> = sqlx::query_scalar("SELECT status FROM jobs WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(match status.as_deref().and_then(JobStatus::parse) {
            None => JobDeletion::NotFound,
            Some(s) => JobDeletion::Unfinished(s),
        })
    }

    async fn finished_before(&self, before: i64, limit: u32) -> QueueResult<Vec<String>> {
        sqlx::query_scalar(
            "SELECT id FROM jobs WHERE status IN ('succeeded', 'failed', 'cancelled') AND finished_at < $1
             ORDER BY finished_at LIMIT $2",
        )
        .bind(before)
        .bind(i64::from(limit))
        .fetch_all(&self.pool)
        .await
    }
}
