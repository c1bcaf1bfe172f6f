//! The embedded queue: one SQLite file, migrations from `migrations/sqlite/` applied at
//! start-up.
//!
//! How: WAL journal (readers never wait for the writer) with `synchronous = FULL`, so a
//! job acknowledged with 202 survives a power cut, not only a killed process. A claim is
//! a single `UPDATE … WHERE id = (SELECT … LIMIT 1) RETURNING *`; SQLite runs one writer
//! at a time, so the select and the update cannot interleave with another claim. That is
//! the property `FOR UPDATE SKIP LOCKED` gives the PostgreSQL implementation.
//!
//! Limits: one machine (SQLite over a network filesystem is not safe); the writer lock is
//! held for milliseconds per statement, which is plenty for a few hundred workers' 4 Hz
//! progress writes, not for thousands.

use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

use async_trait::async_trait;
use serde_json::Value;
use sqlx::Row;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteConnection, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow,
    SqliteSynchronous,
};

use super::{
    BLOCKLIST_AFTER, Cancellation, Capabilities, Enqueued, JobDeletion, JobRecord, JobUpdate, Lease, MAX_ATTEMPTS,
    Outcome, Queue, QueueResult, Recovered, Role, SceneDeletion, SceneRecord, TaskBeat, TaskOutcome, TaskRecord,
    TaskStatus, TokenRecord, WorkerRecord, history_then, lease_given_up, merged_progress, round_after, running_history,
    task_failed, with_snapshot_point,
};
use crate::service::model::{JobSpec, JobStatus};

/// `migrations/sqlite/`, embedded (`super::migrator`; a test checks the folder holds
/// exactly these).
pub(crate) const MIGRATIONS: &[(i64, &str, &str)] = &[
    (1, "init", include_str!("../../../migrations/sqlite/0001_init.sql")),
    (
        2,
        "clients and tokens",
        include_str!("../../../migrations/sqlite/0002_clients_and_tokens.sql"),
    ),
    (
        3,
        "roles and retention",
        include_str!("../../../migrations/sqlite/0003_roles_and_retention.sql"),
    ),
    (4, "tasks", include_str!("../../../migrations/sqlite/0004_tasks.sql")),
    (
        5,
        "task snapshots",
        include_str!("../../../migrations/sqlite/0005_task_snapshots.sql"),
    ),
];

static MIGRATOR: std::sync::LazyLock<sqlx::migrate::Migrator> =
    std::sync::LazyLock::new(|| super::migrator(MIGRATIONS));

#[derive(Clone)]
pub struct SqliteQueue {
    pool: SqlitePool,
}

impl SqliteQueue {
    /// Opens (creating if needed) the database file at `path` and migrates it.
    pub async fn open(path: &Path) -> QueueResult<SqliteQueue> {
        let opts = SqliteConnectOptions::new().filename(path);
        Self::connect(opts).await
    }

    /// Opens a `sqlite:` URL (`sqlite://path/to/file.db`).
    pub async fn open_url(url: &str) -> QueueResult<SqliteQueue> {
        Self::connect(SqliteConnectOptions::from_str(url)?).await
    }

    async fn connect(opts: SqliteConnectOptions) -> QueueResult<SqliteQueue> {
        let opts = opts
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Full)
            .foreign_keys(true)
            // Writers queue on the lock rather than fail: 50 submissions at once must all land.
            .busy_timeout(Duration::from_secs(10));
        let pool = SqlitePoolOptions::new().max_connections(8).connect_with(opts).await?;
        MIGRATOR.run(&pool).await?;
        Ok(SqliteQueue { pool })
    }
}

fn json_col(row: &SqliteRow, col: &str) -> QueueResult<Option<Value>> {
    let s: Option<String> = row.try_get(col)?;
    Ok(s.and_then(|s| serde_json::from_str(&s).ok()))
}

fn job_from_row(row: &SqliteRow) -> QueueResult<JobRecord> {
    let spec: String = row.try_get("spec")?;
    let spec: JobSpec = serde_json::from_str(&spec).map_err(|e| sqlx::Error::Decode(Box::new(e)))?;
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
        attempts: row.try_get::<i64, _>("attempts")? as u32,
        worker: row.try_get("worker")?,
        lease_expires_at: row.try_get("lease_expires_at")?,
        cancel_requested: row.try_get::<i64, _>("cancel_requested")? != 0,
        progress: json_col(row, "progress")?,
        history: json_col(row, "history")?.unwrap_or(Value::Array(vec![])),
        plan: json_col(row, "plan")?,
        snapshots: row.try_get::<i64, _>("snapshots")? as u32,
        summary: json_col(row, "summary")?,
        failure: row.try_get("failure")?,
        updated_at: row.try_get("updated_at")?,
        client: row.try_get("client")?,
        tasks: row.try_get::<i64, _>("tasks")? as u32,
        memory_bytes: row.try_get::<i64, _>("memory_bytes")?.max(0) as u64,
    })
}

fn task_from_row(row: &SqliteRow) -> QueueResult<TaskRecord> {
    let status: String = row.try_get("status")?;
    Ok(TaskRecord {
        job_id: row.try_get("job_id")?,
        index: row.try_get::<i64, _>("idx")? as u32,
        count: row.try_get::<i64, _>("count")? as u32,
        status: TaskStatus::parse(&status)
            .ok_or_else(|| sqlx::Error::Decode(format!("unknown task status {status:?}").into()))?,
        attempts: row.try_get::<i64, _>("attempts")? as u32,
        worker: row.try_get("worker")?,
        lease_expires_at: row.try_get("lease_expires_at")?,
        steps: row.try_get::<i64, _>("steps")? as u64,
        seconds: row.try_get("seconds")?,
        error: row.try_get::<Option<f64>, _>("error")?.map(|e| e as f32),
        failure: row.try_get("failure")?,
        started_at: row.try_get("started_at")?,
        finished_at: row.try_get("finished_at")?,
    })
}

/// The write transaction every task operation runs in: `BEGIN IMMEDIATE` takes the
/// writer lock first, so a read followed by a write can never fail to upgrade.
async fn write_tx(pool: &SqlitePool) -> QueueResult<sqlx::Transaction<'static, sqlx::Sqlite>> {
    pool.begin_with("BEGIN IMMEDIATE").await
}

/// A job's spec, as submitted.
async fn job_spec(c: &mut SqliteConnection, job: &str) -> QueueResult<JobSpec> {
    let spec: String = sqlx::query_scalar("SELECT spec FROM jobs WHERE id = ?")
        .bind(job)
        .fetch_one(&mut *c)
        .await?;
    serde_json::from_str(&spec).map_err(|e| sqlx::Error::Decode(Box::new(e)))
}

/// Writes a split job's merged progress from its bake tasks' rows.
async fn refresh_progress(c: &mut SqliteConnection, job: &str, now: i64) -> QueueResult<()> {
    let Some(row) = sqlx::query("SELECT spec, started_at, history, snapshots FROM jobs WHERE id = ?")
        .bind(job)
        .fetch_optional(&mut *c)
        .await?
    else {
        return Ok(());
    };
    let spec: String = row.try_get("spec")?;
    let spec: JobSpec = serde_json::from_str(&spec).map_err(|e| sqlx::Error::Decode(Box::new(e)))?;
    let tasks: Vec<(i64, Option<f64>)> =
        sqlx::query_as("SELECT steps, error FROM tasks WHERE job_id = ? AND idx < count ORDER BY idx")
            .bind(job)
            .fetch_all(&mut *c)
            .await?;
    let tasks: Vec<(u64, Option<f32>)> = tasks
        .into_iter()
        .map(|(s, e)| (s as u64, e.map(|e| e as f32)))
        .collect();
    let progress = merged_progress(&spec, row.try_get("started_at")?, now, &tasks);
    let history = json_col(&row, "history")?.unwrap_or(Value::Array(vec![]));
    let snapshots: i64 = row.try_get("snapshots")?;
    let history = running_history(&history, &progress, snapshots.clamp(0, i64::from(u32::MAX)) as u32);
    sqlx::query(
        "UPDATE jobs SET progress = ?2, updated_at = ?3, history = COALESCE(?4, history)
         WHERE id = ?1 AND status = 'running'",
    )
    .bind(job)
    .bind(progress.to_string())
    .bind(now)
    .bind(history.as_ref().map(Value::to_string))
    .execute(&mut *c)
    .await?;
    Ok(())
}

/// Counts a failed or abandoned attempt against `worker` (the blocklist's count).
async fn count_failure(c: &mut SqliteConnection, job: &str, worker: &str, reason: &str, now: i64) -> QueueResult<()> {
    sqlx::query(
        "INSERT INTO task_failures (job_id, worker, failures, last_reason, updated_at) VALUES (?1, ?2, 1, ?3, ?4)
         ON CONFLICT (job_id, worker) DO UPDATE SET failures = failures + 1, last_reason = ?3, updated_at = ?4",
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
async fn fail_split_job(c: &mut SqliteConnection, job: &str, reason: &str, now: i64) -> QueueResult<bool> {
    let r = sqlx::query(
        "UPDATE jobs SET status = 'failed', finished_at = ?2, updated_at = ?2, failure = ?3
         WHERE id = ?1 AND status IN ('queued', 'running')",
    )
    .bind(job)
    .bind(now)
    .bind(reason)
    .execute(&mut *c)
    .await?;
    sqlx::query(
        "UPDATE tasks SET status = 'cancelled', updated_at = ?2, lease_expires_at = NULL
         WHERE job_id = ?1 AND status IN ('waiting', 'queued', 'running')",
    )
    .bind(job)
    .bind(now)
    .execute(&mut *c)
    .await?;
    Ok(r.rows_affected() == 1)
}

/// A split job being cancelled: its tasks not running are cancelled, and once none
/// runs the job is `cancelled`. True when the job ended here.
async fn settle_cancel(c: &mut SqliteConnection, job: &str, now: i64) -> QueueResult<bool> {
    sqlx::query(
        "UPDATE tasks SET status = 'cancelled', updated_at = ?2
         WHERE job_id = ?1 AND status IN ('waiting', 'queued')
           AND (SELECT cancel_requested FROM jobs WHERE id = ?1) = 1",
    )
    .bind(job)
    .bind(now)
    .execute(&mut *c)
    .await?;
    let r = sqlx::query(
        "UPDATE jobs SET status = 'cancelled', finished_at = ?2, updated_at = ?2
         WHERE id = ?1 AND tasks > 0 AND cancel_requested = 1 AND status IN ('queued', 'running')
           AND NOT EXISTS (SELECT 1 FROM tasks WHERE job_id = ?1 AND status = 'running')",
    )
    .bind(job)
    .bind(now)
    .execute(&mut *c)
    .await?;
    Ok(r.rows_affected() == 1)
}

/// The task half of [`Queue::recover_expired`]: tasks whose lease lapsed are cancelled
/// (their job is being cancelled or has ended), or count against their worker and are
/// queued again, or, at their last attempt, fail their job. Returns the re-queued tasks,
/// and the jobs failed and cancelled.
#[allow(clippy::type_complexity)]
async fn recover_tasks(
    c: &mut SqliteConnection,
    now: i64,
) -> QueueResult<(Vec<(String, u32)>, Vec<String>, Vec<String>)> {
    let stopped: Vec<String> = sqlx::query_scalar(
        "UPDATE tasks SET status = 'cancelled', updated_at = ?1, lease_expires_at = NULL
         WHERE status = 'running' AND lease_expires_at < ?1
           AND (SELECT cancel_requested = 1 OR status <> 'running' FROM jobs WHERE id = job_id)
         RETURNING job_id",
    )
    .bind(now)
    .fetch_all(&mut *c)
    .await?;
    let mut cancelled = Vec::new();
    for job in dedup(stopped) {
        if settle_cancel(c, &job, now).await? {
            cancelled.push(job);
        }
    }
    sqlx::query(
        "INSERT INTO task_failures (job_id, worker, failures, last_reason, updated_at)
         SELECT job_id, worker, 1, 'its lease expired (the worker stopped renewing it)', ?1 FROM tasks
         WHERE status = 'running' AND lease_expires_at < ?1 AND worker IS NOT NULL
         ON CONFLICT (job_id, worker) DO UPDATE SET failures = failures + 1, last_reason = excluded.last_reason,
             updated_at = excluded.updated_at",
    )
    .bind(now)
    .execute(&mut *c)
    .await?;
    let given_up: Vec<(String, i64, i64, Option<String>)> = sqlx::query_as(
        "UPDATE tasks SET status = 'failed', finished_at = ?1, updated_at = ?1, lease_expires_at = NULL,
             failure = 'its lease expired ' || attempts || ' times'
         WHERE status = 'running' AND lease_expires_at < ?1 AND attempts >= ?2
         RETURNING job_id, idx, count, worker",
    )
    .bind(now)
    .bind(i64::from(MAX_ATTEMPTS))
    .fetch_all(&mut *c)
    .await?;
    let mut failed = Vec::new();
    for (job, idx, count, worker) in given_up {
        let why = lease_given_up(idx, count, worker.as_deref());
        if fail_split_job(c, &job, &why, now).await? {
            failed.push(job);
        }
    }
    let requeued: Vec<(String, i64)> = sqlx::query_as(
        "UPDATE tasks SET status = 'queued', updated_at = ?1, worker = NULL, lease_expires_at = NULL
         WHERE status = 'running' AND lease_expires_at < ?1
         RETURNING job_id, idx",
    )
    .bind(now)
    .fetch_all(&mut *c)
    .await?;
    Ok((
        requeued.into_iter().map(|(j, i)| (j, i as u32)).collect(),
        failed,
        cancelled,
    ))
}

/// The distinct values of `v`, in first-seen order.
fn dedup(v: Vec<String>) -> Vec<String> {
    let mut seen = std::collections::HashSet::new();
    v.into_iter().filter(|x| seen.insert(x.clone())).collect()
}

fn worker_from_row(row: &SqliteRow) -> QueueResult<WorkerRecord> {
    let caps: String = row.try_get("capabilities")?;
    Ok(WorkerRecord {
        id: row.try_get("id")?,
        capabilities: serde_json::from_str(&caps).unwrap_or_default(),
        started_at: row.try_get("started_at")?,
        last_seen: row.try_get("last_seen")?,
    })
}

fn scene_from_row(row: &SqliteRow) -> QueueResult<SceneRecord> {
    let files: String = row.try_get("files")?;
    Ok(SceneRecord {
        id: row.try_get("id")?,
        content_hash: row.try_get("content_hash")?,
        format: row.try_get("format")?,
        main_file: row.try_get("main_file")?,
        files: serde_json::from_str(&files).unwrap_or_default(),
        size_bytes: row.try_get::<i64, _>("size_bytes")? as u64,
        report: json_col(row, "report")?.unwrap_or(Value::Null),
        created_at: row.try_get("created_at")?,
        client: row.try_get("client")?,
    })
}

fn token_from_row(row: &SqliteRow) -> QueueResult<TokenRecord> {
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

#[async_trait]
impl Queue for SqliteQueue {
    async fn insert_scene(&self, s: &SceneRecord) -> QueueResult<bool> {
        let r = sqlx::query(
            "INSERT INTO scenes (id, content_hash, format, main_file, files, size_bytes, report, created_at, client)
             VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (id) DO NOTHING",
        )
        .bind(&s.id)
        .bind(&s.content_hash)
        .bind(&s.format)
        .bind(&s.main_file)
        .bind(serde_json::to_string(&s.files).unwrap_or_default())
        .bind(s.size_bytes as i64)
        .bind(s.report.to_string())
        .bind(s.created_at)
        .bind(&s.client)
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected() == 1)
    }

    async fn scene(&self, id: &str) -> QueueResult<Option<SceneRecord>> {
        let row = sqlx::query("SELECT * FROM scenes WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(scene_from_row).transpose()
    }

    async fn scenes(&self, client: Option<&str>) -> QueueResult<Vec<SceneRecord>> {
        let rows = sqlx::query("SELECT * FROM scenes WHERE (?1 IS NULL OR client = ?1) ORDER BY created_at DESC, id")
            .bind(client)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(scene_from_row).collect()
    }

    async fn delete_scene(&self, id: &str) -> QueueResult<SceneDeletion> {
        // One statement, so a job cannot be queued for the scene between the check and
        // the delete (a read in a WAL transaction does not hold the write lock).
        let r = sqlx::query(
            "DELETE FROM scenes WHERE id = ?1 AND NOT EXISTS
                 (SELECT 1 FROM jobs WHERE scene_id = ?1 AND status IN ('queued', 'running'))",
        )
        .bind(id)
        .execute(&self.pool)
        .await?;
        if r.rows_affected() == 1 {
            return Ok(SceneDeletion::Deleted);
        }
        let in_use: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE scene_id = ? AND status IN ('queued', 'running')")
                .bind(id)
                .fetch_one(&self.pool)
                .await?;
        let exists: Option<i64> = sqlx::query_scalar("SELECT 1 FROM scenes WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(match exists {
            None => SceneDeletion::NotFound,
            Some(_) => SceneDeletion::InUse(in_use.max(1) as u64),
        })
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
        // One statement: the scene check, the client's queue length and the insert
        // cannot be split by a DELETE or by the same client's other submissions. The
        // tasks of a split job go in the same transaction.
        let tasks = spec.bake_tasks();
        let first_queued = spec.first_queued();
        let requires = spec.requires.unwrap_or_default();
        let mut tx = write_tx(&self.pool).await?;
        let row = sqlx::query(
            "INSERT INTO jobs (id, scene_id, spec, status, priority, created_at, updated_at, client, tasks,
                               requires_gpu, requires_oidn, memory_bytes)
             SELECT ?1, ?2, ?3, 'queued', ?4, ?5, ?5, ?6, ?8, ?9, ?10, ?11
             WHERE EXISTS (SELECT 1 FROM scenes WHERE id = ?2)
               AND (SELECT COUNT(*) FROM jobs WHERE client = ?6 AND status = 'queued') < ?7
             RETURNING *",
        )
        .bind(id)
        .bind(&spec.scene)
        .bind(serde_json::to_string(spec).unwrap_or_default())
        .bind(spec.priority)
        .bind(now)
        .bind(client)
        .bind(i64::try_from(max_queued).unwrap_or(i64::MAX))
        .bind(i64::from(tasks))
        .bind(requires.gpu)
        .bind(requires.oidn)
        .bind(i64::try_from(memory_bytes).unwrap_or(i64::MAX))
        .fetch_optional(&mut *tx)
        .await?;
        if row.is_some() && tasks > 0 {
            // Bake tasks 0..n queued (in rounds, round 0's; the later rounds wait for the
            // round before), the merge (index n) waiting for them.
            sqlx::query(
                "WITH RECURSIVE k(i) AS (SELECT 0 UNION ALL SELECT i + 1 FROM k WHERE i < ?2)
                 INSERT INTO tasks (job_id, idx, count, status, updated_at)
                 SELECT ?1, i, ?2, CASE WHEN i < ?4 THEN 'queued' ELSE 'waiting' END, ?3 FROM k",
            )
            .bind(id)
            .bind(i64::from(tasks))
            .bind(now)
            .bind(i64::from(first_queued))
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        if let Some(row) = row {
            return Ok(Enqueued::Queued(Box::new(job_from_row(&row)?)));
        }
        let scene: Option<i64> = sqlx::query_scalar("SELECT 1 FROM scenes WHERE id = ?")
            .bind(&spec.scene)
            .fetch_optional(&self.pool)
            .await?;
        if scene.is_none() {
            return Ok(Enqueued::NoScene);
        }
        let queued: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE client = ? AND status = 'queued'")
            .bind(client)
            .fetch_one(&self.pool)
            .await?;
        Ok(Enqueued::QueueFull(queued as u64))
    }

    async fn job(&self, id: &str) -> QueueResult<Option<JobRecord>> {
        let row = sqlx::query("SELECT * FROM jobs WHERE id = ?")
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
            "SELECT * FROM jobs WHERE (?1 IS NULL OR status = ?1) AND (?4 IS NULL OR client = ?4)
             ORDER BY created_at DESC, rowid DESC LIMIT ?2 OFFSET ?3",
        )
        .bind(status)
        .bind(limit as i64)
        .bind(i64::try_from(offset).unwrap_or(i64::MAX))
        .bind(client)
        .fetch_all(&self.pool)
        .await?;
        let total: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM jobs WHERE (?1 IS NULL OR status = ?1) AND (?2 IS NULL OR client = ?2)",
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
            "UPDATE jobs SET status = 'cancelled', finished_at = ?2, updated_at = ?2
             WHERE id = ?1 AND status = 'queued'",
        )
        .bind(id)
        .bind(now)
        .execute(&self.pool)
        .await?;
        if r.rows_affected() == 1 {
            // A split job's tasks end with it.
            sqlx::query("UPDATE tasks SET status = 'cancelled', updated_at = ?2 WHERE job_id = ?1 AND status IN ('waiting', 'queued')")
                .bind(id)
                .bind(now)
                .execute(&self.pool)
                .await?;
            return Ok(Cancellation::Cancelled);
        }
        let mut tx = write_tx(&self.pool).await?;
        let r =
            sqlx::query("UPDATE jobs SET cancel_requested = 1, updated_at = ?2 WHERE id = ?1 AND status = 'running'")
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
        let status: Option<String> = sqlx::query_scalar("SELECT status FROM jobs WHERE id = ?")
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
            "UPDATE jobs SET status = 'running', worker = ?1, attempts = attempts + 1, lease_expires_at = ?2,
                 started_at = ?3, updated_at = ?3, progress = NULL, history = '[]', plan = NULL
             WHERE id = (SELECT id FROM jobs WHERE status = 'queued' AND tasks = 0
                           AND (requires_gpu = 0 OR ?4) AND (requires_oidn = 0 OR ?5) AND memory_bytes <= ?6
                         ORDER BY priority DESC, created_at, rowid LIMIT 1)
             RETURNING *",
        )
        .bind(worker)
        .bind(lease_until(now, lease))
        .bind(now)
        .bind(caps.gpu)
        .bind(caps.oidn)
        .bind(i64::try_from(caps.memory_bytes).unwrap_or(i64::MAX))
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
        let mut tx = write_tx(&self.pool).await?;
        let row = sqlx::query(
            "UPDATE tasks SET status = 'running', worker = ?1, attempts = attempts + 1, lease_expires_at = ?2,
                 started_at = ?3, updated_at = ?3, steps = 0, seconds = 0, error = NULL, failure = NULL,
                 finished_at = NULL
             WHERE rowid = (SELECT t.rowid FROM tasks t JOIN jobs j ON j.id = t.job_id
                            WHERE t.status = 'queued' AND j.status IN ('queued', 'running')
                              AND j.cancel_requested = 0
                              AND (j.requires_gpu = 0 OR ?4) AND (j.requires_oidn = 0 OR ?5)
                              AND j.memory_bytes <= ?7
                              AND NOT EXISTS (SELECT 1 FROM task_failures f
                                              WHERE f.job_id = t.job_id AND f.worker = ?1 AND f.failures >= ?6)
                              AND NOT EXISTS (SELECT 1 FROM jobs w
                                              WHERE w.status = 'queued' AND w.tasks = 0
                                                AND (w.requires_gpu = 0 OR ?4) AND (w.requires_oidn = 0 OR ?5)
                                                AND w.memory_bytes <= ?7
                                                AND (w.priority > j.priority
                                                     OR (w.priority = j.priority
                                                         AND (w.created_at < j.created_at
                                                              OR (w.created_at = j.created_at AND w.rowid < j.rowid)))))
                            ORDER BY j.priority DESC, j.created_at, j.rowid, t.idx LIMIT 1)
             RETURNING *",
        )
        .bind(worker)
        .bind(lease_until(now, lease))
        .bind(now)
        .bind(caps.gpu)
        .bind(caps.oidn)
        .bind(i64::from(BLOCKLIST_AFTER))
        .bind(i64::try_from(caps.memory_bytes).unwrap_or(i64::MAX))
        .fetch_optional(&mut *tx)
        .await?;
        let Some(row) = row else {
            return Ok(None);
        };
        let task = task_from_row(&row)?;
        let job = sqlx::query(
            "UPDATE jobs SET status = 'running', started_at = COALESCE(started_at, ?2), updated_at = ?2
             WHERE id = ?1 RETURNING *",
        )
        .bind(&task.job_id)
        .bind(now)
        .fetch_one(&mut *tx)
        .await?;
        let job = job_from_row(&job)?;
        tx.commit().await?;
        Ok(Some((task, job)))
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
        let mut tx = write_tx(&self.pool).await?;
        let cancel: Option<i64> = sqlx::query_scalar(
            "UPDATE tasks SET lease_expires_at = ?4, updated_at = ?5,
                 steps = COALESCE(?6, steps), seconds = COALESCE(?7, seconds),
                 error = CASE WHEN ?6 IS NULL THEN error ELSE ?8 END
             WHERE job_id = ?1 AND idx = ?2 AND worker = ?3 AND status = 'running'
             RETURNING (SELECT cancel_requested FROM jobs WHERE id = ?1)",
        )
        .bind(job)
        .bind(i64::from(index))
        .bind(worker)
        .bind(lease_until(now, lease))
        .bind(now)
        .bind(beat.map(|b| b.steps as i64))
        .bind(beat.map(|b| b.seconds))
        .bind(beat.and_then(|b| b.error.map(f64::from)))
        .fetch_optional(&mut *tx)
        .await?;
        let Some(cancel) = cancel else {
            return Ok(Lease::Lost);
        };
        if beat.is_some() {
            refresh_progress(&mut tx, job, now).await?;
        }
        tx.commit().await?;
        Ok(Lease::Held { cancel: cancel != 0 })
    }

    async fn claim_task_snapshot(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        interval: Duration,
        now: i64,
    ) -> QueueResult<Option<u32>> {
        // One statement; SQLite runs one writer at a time, so one claim wins an interval.
        let n: Option<i64> = sqlx::query_scalar(
            "UPDATE jobs SET snapshot_claims = MAX(snapshot_claims, snapshots) + 1, snapshot_claimed_at = ?3
             WHERE id = ?1 AND status = 'running'
               AND (snapshot_claimed_at IS NULL OR snapshot_claimed_at <= ?3 - ?4)
               AND EXISTS (SELECT 1 FROM tasks WHERE job_id = ?1 AND idx = ?2 AND worker = ?5 AND status = 'running')
             RETURNING snapshot_claims",
        )
        .bind(job)
        .bind(i64::from(index))
        .bind(now)
        .bind(interval.as_millis().min(i64::MAX as u128) as i64)
        .bind(worker)
        .fetch_optional(&self.pool)
        .await?;
        Ok(n.map(|n| n.clamp(0, i64::from(u32::MAX)) as u32))
    }

    async fn task_snapshot_stored(&self, job: &str, n: u32, point: &Value) -> QueueResult<bool> {
        // The count's write comes first, so the transaction holds SQLite's one write lock
        // before it reads the history (no `refresh_progress` can come in between).
        let mut tx = self.pool.begin().await?;
        let done = sqlx::query("UPDATE jobs SET snapshots = MAX(snapshots, ?2) WHERE id = ?1 AND status = 'running'")
            .bind(job)
            .bind(i64::from(n))
            .execute(&mut *tx)
            .await?;
        if done.rows_affected() != 1 {
            return Ok(false);
        }
        let history: String = sqlx::query_scalar("SELECT history FROM jobs WHERE id = ?")
            .bind(job)
            .fetch_one(&mut *tx)
            .await?;
        let history: Value = serde_json::from_str(&history).unwrap_or(Value::Array(vec![]));
        sqlx::query("UPDATE jobs SET history = ?2 WHERE id = ?1")
            .bind(job)
            .bind(with_snapshot_point(&history, point).to_string())
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(true)
    }

    async fn release_task_snapshot(&self, job: &str, n: u32) -> QueueResult<()> {
        sqlx::query("UPDATE jobs SET snapshot_claims = ?2 - 1 WHERE id = ?1 AND snapshot_claims = ?2")
            .bind(job)
            .bind(i64::from(n))
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
        let mut tx = write_tx(&self.pool).await?;
        // The guard: the task is ours and running; its attempts say whether a failure
        // is retried.
        let row: Option<(i64, i64)> = sqlx::query_as(
            "UPDATE tasks SET updated_at = ?4, lease_expires_at = NULL
             WHERE job_id = ?1 AND idx = ?2 AND worker = ?3 AND status = 'running'
             RETURNING attempts, count",
        )
        .bind(job)
        .bind(i64::from(index))
        .bind(worker)
        .bind(now)
        .fetch_optional(&mut *tx)
        .await?;
        let Some((attempts, count)) = row else {
            return Ok(false);
        };
        let set = |status: &'static str| {
            sqlx::query(
                "UPDATE tasks SET status = ?3, finished_at = CASE WHEN ?3 = 'queued' THEN NULL ELSE ?4 END,
                     worker = CASE WHEN ?3 = 'queued' THEN NULL ELSE worker END, failure = ?5
                 WHERE job_id = ?1 AND idx = ?2",
            )
            .bind(job)
            .bind(i64::from(index))
            .bind(status)
            .bind(now)
        };
        match outcome {
            TaskOutcome::Baked(b) => {
                set("succeeded").bind(None::<String>).execute(&mut *tx).await?;
                sqlx::query("UPDATE tasks SET steps = ?3, seconds = ?4, error = ?5 WHERE job_id = ?1 AND idx = ?2")
                    .bind(job)
                    .bind(i64::from(index))
                    .bind(b.steps as i64)
                    .bind(b.seconds)
                    .bind(b.error.map(f64::from))
                    .execute(&mut *tx)
                    .await?;
                // The last task of a round in queues the next round's.
                if let Some([first, next, end]) = round_after(&job_spec(&mut tx, job).await?, index) {
                    sqlx::query(
                        "UPDATE tasks SET status = 'queued', updated_at = ?2
                         WHERE job_id = ?1 AND idx >= ?4 AND idx < ?5 AND status = 'waiting'
                           AND NOT EXISTS (SELECT 1 FROM tasks WHERE job_id = ?1 AND idx >= ?3 AND idx < ?4
                                             AND status <> 'succeeded')",
                    )
                    .bind(job)
                    .bind(now)
                    .bind(i64::from(first))
                    .bind(i64::from(next))
                    .bind(i64::from(end))
                    .execute(&mut *tx)
                    .await?;
                }
                // The last bake task in queues the merge.
                sqlx::query(
                    "UPDATE tasks SET status = 'queued', updated_at = ?2
                     WHERE job_id = ?1 AND idx = count AND status = 'waiting'
                       AND NOT EXISTS (SELECT 1 FROM tasks WHERE job_id = ?1 AND idx < count AND status <> 'succeeded')",
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
                let running: Option<String> = sqlx::query_scalar("SELECT history FROM jobs WHERE id = ?1")
                    .bind(job)
                    .fetch_optional(&mut *tx)
                    .await?
                    .flatten();
                let running = running
                    .and_then(|h| serde_json::from_str(&h).ok())
                    .unwrap_or(Value::Null);
                let history = history_then(&running, history);
                sqlx::query(
                    "UPDATE jobs SET status = 'succeeded', finished_at = ?2, updated_at = ?2, summary = ?3,
                         progress = ?4, history = ?5, plan = ?6
                     WHERE id = ?1 AND status = 'running'",
                )
                .bind(job)
                .bind(now)
                .bind(summary.to_string())
                .bind(progress.to_string())
                .bind(history.to_string())
                .bind(plan.to_string())
                .execute(&mut *tx)
                .await?;
            }
            TaskOutcome::Failed { reason, retry } => {
                count_failure(&mut tx, job, worker, reason, now).await?;
                if *retry && attempts < i64::from(MAX_ATTEMPTS) {
                    set("queued").bind(Some(reason.clone())).execute(&mut *tx).await?;
                    settle_cancel(&mut tx, job, now).await?;
                } else {
                    set("failed").bind(Some(reason.clone())).execute(&mut *tx).await?;
                    let why = task_failed(i64::from(index), count, attempts, worker, reason, *retry);
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
        let mut tx = write_tx(&self.pool).await?;
        let r = sqlx::query(
            "UPDATE tasks SET status = 'queued', attempts = MAX(attempts - 1, 0), worker = NULL,
                 lease_expires_at = NULL, updated_at = ?4
             WHERE job_id = ?1 AND idx = ?2 AND worker = ?3 AND status = 'running'",
        )
        .bind(job)
        .bind(i64::from(index))
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
        let rows = sqlx::query("SELECT * FROM tasks WHERE job_id = ? ORDER BY idx")
            .bind(job)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(task_from_row).collect()
    }

    async fn task_failures(&self, job: &str) -> QueueResult<Vec<(String, u32)>> {
        let rows: Vec<(String, i64)> =
            sqlx::query_as("SELECT worker, failures FROM task_failures WHERE job_id = ? ORDER BY worker")
                .bind(job)
                .fetch_all(&self.pool)
                .await?;
        Ok(rows.into_iter().map(|(w, n)| (w, n as u32)).collect())
    }

    async fn register_worker(&self, worker: &str, caps: &Capabilities, now: i64) -> QueueResult<()> {
        sqlx::query(
            "INSERT INTO workers (id, capabilities, started_at, last_seen) VALUES (?1, ?2, ?3, ?3)
             ON CONFLICT (id) DO UPDATE SET capabilities = ?2, last_seen = ?3",
        )
        .bind(worker)
        .bind(serde_json::to_string(caps).unwrap_or_default())
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    async fn workers(&self, since: i64) -> QueueResult<Vec<WorkerRecord>> {
        let rows = sqlx::query("SELECT * FROM workers WHERE last_seen >= ? ORDER BY id")
            .bind(since)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(worker_from_row).collect()
    }

    async fn forget_workers(&self, before: i64) -> QueueResult<u64> {
        let done = sqlx::query("DELETE FROM workers WHERE last_seen < ?")
            .bind(before)
            .execute(&self.pool)
            .await?;
        Ok(done.rows_affected())
    }

    async fn heartbeat(&self, id: &str, worker: &str, lease: Duration, u: &JobUpdate, now: i64) -> QueueResult<Lease> {
        let cancel: Option<i64> = sqlx::query_scalar(
            "UPDATE jobs SET lease_expires_at = ?3, updated_at = ?4,
                 progress = COALESCE(?5, progress), history = COALESCE(?6, history),
                 plan = COALESCE(?7, plan), snapshots = COALESCE(?8, snapshots)
             WHERE id = ?1 AND worker = ?2 AND status = 'running'
             RETURNING cancel_requested",
        )
        .bind(id)
        .bind(worker)
        .bind(lease_until(now, lease))
        .bind(now)
        .bind(u.progress.as_ref().map(Value::to_string))
        .bind(u.history.as_ref().map(Value::to_string))
        .bind(u.plan.as_ref().map(Value::to_string))
        .bind(u.snapshots.map(i64::from))
        .fetch_optional(&self.pool)
        .await?;
        Ok(match cancel {
            Some(c) => Lease::Held { cancel: c != 0 },
            None => Lease::Lost,
        })
    }

    async fn finish(&self, id: &str, worker: &str, outcome: &Outcome, now: i64) -> QueueResult<bool> {
        let (status, summary, progress, history, failure) = match outcome {
            Outcome::Succeeded {
                summary,
                progress,
                history,
            } => (
                "succeeded",
                Some(summary.to_string()),
                Some(progress.to_string()),
                Some(history.to_string()),
                None,
            ),
            Outcome::Failed { reason } => ("failed", None, None, None, Some(reason.clone())),
            Outcome::Cancelled => ("cancelled", None, None, None, None),
        };
        let r = sqlx::query(
            "UPDATE jobs SET status = ?3, finished_at = ?4, updated_at = ?4, lease_expires_at = NULL,
                 summary = COALESCE(?5, summary), progress = COALESCE(?6, progress),
                 history = COALESCE(?7, history), failure = ?8
             WHERE id = ?1 AND worker = ?2 AND status = 'running'",
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
                 status = CASE WHEN cancel_requested = 1 THEN 'cancelled' ELSE 'queued' END,
                 finished_at = CASE WHEN cancel_requested = 1 THEN ?3 ELSE NULL END,
                 attempts = MAX(attempts - 1, 0), worker = NULL, lease_expires_at = NULL, updated_at = ?3
             WHERE id = ?1 AND worker = ?2 AND status = 'running'",
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
        // Order matters: cancelled first, then failed, then the rest re-queued; each
        // statement changes the status, so no row is taken twice.
        let cancelled: Vec<String> = sqlx::query_scalar(
            "UPDATE jobs SET status = 'cancelled', finished_at = ?1, updated_at = ?1, worker = NULL,
                 lease_expires_at = NULL
             WHERE status = 'running' AND lease_expires_at < ?1 AND cancel_requested = 1
             RETURNING id",
        )
        .bind(now)
        .fetch_all(&mut *tx)
        .await?;
        let failed: Vec<String> = sqlx::query_scalar(
            "UPDATE jobs SET status = 'failed', finished_at = ?1, updated_at = ?1, lease_expires_at = NULL,
                 failure = 'gave up after ' || attempts || ' attempts: the lease of worker ' || COALESCE(worker, '?')
                     || ' expired (the worker stopped renewing it: crashed, killed or cut off)'
             WHERE status = 'running' AND lease_expires_at < ?1 AND attempts >= ?2
             RETURNING id",
        )
        .bind(now)
        .bind(MAX_ATTEMPTS as i64)
        .fetch_all(&mut *tx)
        .await?;
        let requeued: Vec<String> = sqlx::query_scalar(
            "UPDATE jobs SET status = 'queued', updated_at = ?1, worker = NULL, lease_expires_at = NULL
             WHERE status = 'running' AND lease_expires_at < ?1
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
            "INSERT INTO tokens (id, name, hash, created_at, revoked_at, role, source) VALUES (?, ?, ?, ?, ?, ?, ?)",
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
        let rows = sqlx::query("SELECT * FROM tokens ORDER BY created_at, rowid")
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(token_from_row).collect()
    }

    async fn revoke_token(&self, id: &str, now: i64) -> QueueResult<bool> {
        let r = sqlx::query("UPDATE tokens SET revoked_at = ?2 WHERE id = ?1 AND revoked_at IS NULL")
            .bind(id)
            .bind(now)
            .execute(&self.pool)
            .await?;
        Ok(r.rows_affected() > 0)
    }

    async fn token_by_hash(&self, hash: &str) -> QueueResult<Option<TokenRecord>> {
        let row = sqlx::query("SELECT * FROM tokens WHERE hash = ? AND revoked_at IS NULL")
            .bind(hash)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(token_from_row).transpose()
    }

    async fn clock(&self) -> QueueResult<i64> {
        // julianday works on every SQLite version (unixepoch('subsec') needs 3.42).
        sqlx::query_scalar("SELECT CAST(ROUND((julianday('now') - 2440587.5) * 86400000.0) AS INTEGER)")
            .fetch_one(&self.pool)
            .await
    }

    async fn delete_job(&self, id: &str) -> QueueResult<JobDeletion> {
        let r = sqlx::query("DELETE FROM jobs WHERE id = ? AND status IN ('succeeded', 'failed', 'cancelled')")
            .bind(id)
            .execute(&self.pool)
            .await?;
        if r.rows_affected() == 1 {
            return Ok(JobDeletion::Deleted);
        }
        let status: Option<String> = sqlx::query_scalar("SELECT status FROM jobs WHERE id = ?")
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
            "SELECT id FROM jobs WHERE status IN ('succeeded', 'failed', 'cancelled') AND finished_at < ?
             ORDER BY finished_at LIMIT ?",
        )
        .bind(before)
        .bind(i64::from(limit))
        .fetch_all(&self.pool)
        .await
    }
}
