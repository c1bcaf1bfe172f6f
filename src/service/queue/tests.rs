//! The queue's behaviour, once per store: every test below runs against SQLite (always)
//! and against PostgreSQL (when `LIGHTMAPD_TEST_POSTGRES` names a server; a loud skip
//! line otherwise, a failure under `LIGHTMAPD_REQUIRE_SERVICES=1`). The [`on_both_stores`]
//! macro makes the two variants, so a new test is written once.
//!
//! Each PostgreSQL variant works in a schema of its own (dropped when it passes), so the
//! variants run in parallel on one database. "Another process" is a second handle on the
//! same store (a second SQLite connection pool on the file, a second PostgreSQL pool on the
//! schema), which shares nothing in memory with the first.

use std::collections::HashSet;
use std::sync::Arc;
use std::time::Duration;

use serde_json::json;

use super::postgres::{PostgresQueue, test_url};
use super::sqlite::SqliteQueue;
use super::*;
use crate::service::Hub;
use crate::service::model::{JobSpec, JobStatus};

/// One store under test, and how to open a second, independent handle on it.
struct Fixture {
    queue: Arc<dyn Queue>,
    store: Store,
}

enum Store {
    Sqlite(tempfile::TempDir),
    Postgres {
        url: String,
        schema: String,
        queue: PostgresQueue,
    },
}

impl Fixture {
    async fn sqlite() -> Fixture {
        let dir = tempfile::tempdir().unwrap();
        let q = SqliteQueue::open(&dir.path().join("q.db")).await.unwrap();
        Fixture {
            queue: Arc::new(q),
            store: Store::Sqlite(dir),
        }
    }

    async fn postgres(test: &str) -> Option<Fixture> {
        let url = test_url(test)?;
        let schema = format!("test_{}", uuid::Uuid::new_v4().simple());
        let q = PostgresQueue::open_in_schema(&url, &schema)
            .await
            .unwrap_or_else(|e| panic!("{test}: cannot open PostgreSQL at {url}: {e}"));
        Some(Fixture {
            queue: Arc::new(q.clone()),
            store: Store::Postgres { url, schema, queue: q },
        })
    }

    /// A handle that shares nothing with `self.queue` but the database.
    async fn other_process(&self) -> Arc<dyn Queue> {
        match &self.store {
            Store::Sqlite(dir) => Arc::new(SqliteQueue::open(&dir.path().join("q.db")).await.unwrap()),
            Store::Postgres { url, schema, .. } => Arc::new(PostgresQueue::open_in_schema(url, schema).await.unwrap()),
        }
    }

    async fn cleanup(self) {
        if let Store::Postgres { schema, queue, .. } = self.store {
            queue.drop_schema(&schema).await.unwrap();
        }
    }
}

macro_rules! on_both_stores {
    ($($name:ident),* $(,)?) => {
        mod sqlite_store {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() {
                    let f = super::Fixture::sqlite().await;
                    super::$name(&f).await;
                    f.cleanup().await;
                }
            )*
        }
        mod postgres_store {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() {
                    let test = concat!("queue::tests::postgres_store::", stringify!($name));
                    let Some(f) = super::Fixture::postgres(test).await else { return };
                    super::$name(&f).await;
                    f.cleanup().await;
                }
            )*
        }
    };
}

on_both_stores!(
    per_client_queue_limit_and_tokens,
    lease_expiry_requeues_then_fails_after_three_attempts,
    release_does_not_count_the_attempt_and_scene_in_use_is_kept,
    claims_follow_priority_then_age,
    concurrent_claimers_never_share_a_job,
    concurrent_submissions_never_overshoot_the_client_limit,
    heartbeat_progress_cancel_and_finish,
    other_processes_hear_of_new_work_and_job_changes,
    finished_jobs_are_deleted_and_found_by_age,
    the_database_clock_is_the_wall_clock,
    split_jobs_run_as_tasks_and_merge_once,
    a_dead_workers_task_is_retried_and_a_failing_worker_is_blocklisted,
    cancelling_a_split_job_stops_its_tasks,
    claims_meet_the_jobs_requirements,
    tasks_and_whole_jobs_share_one_priority_order,
    a_split_jobs_tasks_take_turns_at_its_snapshots,
    a_job_in_rounds_queues_each_round_once_the_one_before_has_succeeded,
);

fn split_spec(tasks: u32, steps: u64, extra: &str) -> JobSpec {
    JobSpec::parse(format!(r#"{{"scene": "s", "tasks": {tasks}, "stop": {{"steps": {steps}}}{extra}}}"#).as_bytes())
        .unwrap()
}

async fn enqueue_ok(q: &dyn Queue, id: &str, spec: &JobSpec, at: i64) {
    assert!(matches!(
        q.enqueue(id, spec, "c", 100, 0, at).await.unwrap(),
        Enqueued::Queued(_)
    ));
}

fn gpu() -> Capabilities {
    Capabilities {
        gpu: true,
        ..Capabilities::default()
    }
}

async fn split_jobs_run_as_tasks_and_merge_once(f: &Fixture) {
    let q = &*f.queue;
    let lease = Duration::from_secs(30);
    let none = Capabilities::default();
    with_scene(q).await;
    enqueue_ok(q, "j", &split_spec(3, 12, ""), 10).await;
    let tasks = q.tasks("j").await.unwrap();
    assert_eq!(
        tasks.iter().map(|t| (t.index, t.count, t.status)).collect::<Vec<_>>(),
        vec![
            (0, 3, TaskStatus::Queued),
            (1, 3, TaskStatus::Queued),
            (2, 3, TaskStatus::Queued),
            (3, 3, TaskStatus::Waiting)
        ]
    );
    // A split job is never claimed whole.
    assert!(q.claim("w0", &none, lease, 20).await.unwrap().is_none());
    let mut taken = Vec::new();
    for w in ["w1", "w2", "w3"] {
        let (t, j) = q.claim_task(w, &none, lease, 20).await.unwrap().unwrap();
        assert_eq!(
            (j.id.as_str(), j.status, j.started_at, j.tasks),
            ("j", JobStatus::Running, Some(20), 3)
        );
        assert!(!t.is_merge());
        assert_eq!((t.attempts, t.worker.as_deref()), (1, Some(w)));
        taken.push(t.index);
    }
    assert_eq!(taken, vec![0, 1, 2]);
    // The merge waits for every bake task.
    assert!(q.claim_task("w4", &none, lease, 21).await.unwrap().is_none());
    // Progress: steps added, errors of the step-weighted mean in quadrature.
    let beat = |steps, error| TaskBeat {
        steps,
        seconds: 1.0,
        error: Some(error),
    };
    assert_eq!(
        q.task_heartbeat("j", 0, "w1", lease, Some(&beat(4, 0.1)), 1020)
            .await
            .unwrap(),
        Lease::Held { cancel: false }
    );
    q.task_heartbeat("j", 1, "w2", lease, Some(&beat(2, 0.2)), 1020)
        .await
        .unwrap();
    // Not its task: lost.
    assert_eq!(
        q.task_heartbeat("j", 0, "w2", lease, None, 1020).await.unwrap(),
        Lease::Lost
    );
    let p = q.job("j").await.unwrap().unwrap().progress.unwrap();
    let want = ((4.0f64 / 6.0 * 0.1).powi(2) + (2.0f64 / 6.0 * 0.2).powi(2)).sqrt();
    assert_eq!(p["steps"], 6);
    assert!((p["error"].as_f64().unwrap() - want).abs() < 1e-6, "{p}");
    assert!((p["fraction"].as_f64().unwrap() - 0.5).abs() < 1e-9, "{p}");
    assert!((p["elapsed_s"].as_f64().unwrap() - 1.0).abs() < 1e-9, "{p}");
    for (k, w) in [(0u32, "w1"), (1, "w2")] {
        assert!(
            q.finish_task("j", k, w, &TaskOutcome::Baked(beat(4, 0.1)), 1100)
                .await
                .unwrap()
        );
    }
    assert!(q.claim_task("w4", &none, lease, 1100).await.unwrap().is_none());
    // A second end of the same task is refused (no longer running).
    assert!(
        !q.finish_task("j", 0, "w1", &TaskOutcome::Baked(beat(4, 0.1)), 1101)
            .await
            .unwrap()
    );
    assert!(
        q.finish_task("j", 2, "w3", &TaskOutcome::Baked(beat(4, 0.1)), 1200)
            .await
            .unwrap()
    );
    let (m, _) = q.claim_task("w4", &none, lease, 1300).await.unwrap().unwrap();
    assert!(m.is_merge() && m.index == 3);
    assert!(q.claim_task("w5", &none, lease, 1300).await.unwrap().is_none());
    let merged = TaskOutcome::Merged {
        summary: json!({"steps": 12}),
        progress: json!({"steps": 12, "fraction": 1.0}),
        history: json!([{"seconds": 3.0, "steps": 12, "error": 0.05}]),
        plan: json!({"tasks": {"count": 3}}),
    };
    assert!(q.finish_task("j", 3, "w4", &merged, 1400).await.unwrap());
    let j = q.job("j").await.unwrap().unwrap();
    assert_eq!((j.status, j.finished_at), (JobStatus::Succeeded, Some(1400)));
    assert_eq!(j.summary.unwrap()["steps"], 12);
    assert_eq!(j.plan.unwrap()["tasks"]["count"], 3);
    assert!(
        q.tasks("j")
            .await
            .unwrap()
            .iter()
            .all(|t| t.status == TaskStatus::Succeeded)
    );
    // Deleting the job deletes its tasks.
    assert_eq!(q.delete_job("j").await.unwrap(), JobDeletion::Deleted);
    assert!(q.tasks("j").await.unwrap().is_empty());
}

async fn a_dead_workers_task_is_retried_and_a_failing_worker_is_blocklisted(f: &Fixture) {
    let q = &*f.queue;
    let lease = Duration::from_secs(1);
    let none = Capabilities::default();
    with_scene(q).await;
    enqueue_ok(q, "j", &split_spec(2, 8, ""), 0).await;
    let (t0, _) = q.claim_task("w1", &none, lease, 0).await.unwrap().unwrap();
    let (t1, _) = q
        .claim_task("w2", &none, Duration::from_secs(60), 0)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((t0.index, t1.index), (0, 1));
    // w1 dies: its task (not the job) is queued again, and the attempt counts against w1.
    let r = q.recover_expired(5000).await.unwrap();
    assert_eq!(r.tasks_requeued, vec![("j".to_string(), 0)]);
    assert!(r.requeued.is_empty() && r.failed.is_empty());
    assert_eq!(q.job("j").await.unwrap().unwrap().status, JobStatus::Running);
    assert_eq!(q.task_failures("j").await.unwrap(), vec![("w1".to_string(), 1)]);
    // One failure does not blocklist: w1 takes it again, and fails it (a device error).
    let (again, _) = q.claim_task("w1", &none, lease, 5000).await.unwrap().unwrap();
    assert_eq!((again.index, again.attempts), (0, 2));
    let gpu_lost = TaskOutcome::Failed {
        reason: "device lost".into(),
        retry: true,
    };
    assert!(q.finish_task("j", 0, "w1", &gpu_lost, 5100).await.unwrap());
    let t = &q.tasks("j").await.unwrap()[0];
    assert_eq!(
        (t.status, t.worker.as_deref(), t.failure.as_deref()),
        (TaskStatus::Queued, None, Some("device lost"))
    );
    // Two: w1 takes none of this job's tasks any more; w3 does.
    assert!(q.claim_task("w1", &none, lease, 5200).await.unwrap().is_none());
    let (third, _) = q.claim_task("w3", &none, lease, 5200).await.unwrap().unwrap();
    assert_eq!((third.index, third.attempts), (0, 3));
    // Its third attempt fails too: the job fails, naming the task and the last worker, and
    // the other task's worker finds its lease gone.
    assert!(q.finish_task("j", 0, "w3", &gpu_lost, 5300).await.unwrap());
    let j = q.job("j").await.unwrap().unwrap();
    assert_eq!(j.status, JobStatus::Failed);
    assert_eq!(
        j.failure.as_deref(),
        Some("task 0 of 2 failed 3 times; the last time on worker w3: device lost")
    );
    assert_eq!(
        q.task_heartbeat("j", 1, "w2", lease, None, 5400).await.unwrap(),
        Lease::Lost
    );
    assert_eq!(q.tasks("j").await.unwrap()[1].status, TaskStatus::Cancelled);
    // Bad input fails the job at its first attempt.
    enqueue_ok(q, "k", &split_spec(2, 8, ""), 6000).await;
    q.claim_task("w9", &none, lease, 6000).await.unwrap().unwrap();
    let bad = TaskOutcome::Failed {
        reason: "bad input: mesh 3 has no normals".into(),
        retry: false,
    };
    assert!(q.finish_task("k", 0, "w9", &bad, 6100).await.unwrap());
    let k = q.job("k").await.unwrap().unwrap();
    assert_eq!(
        (k.status, k.failure.as_deref()),
        (
            JobStatus::Failed,
            Some("task 0 of 2 failed: bad input: mesh 3 has no normals")
        )
    );
    // A task whose lease lapses a third time fails its job too.
    enqueue_ok(q, "m", &split_spec(2, 8, ""), 7000).await;
    for (i, w) in ["a", "b", "c"].into_iter().enumerate() {
        let at = 7000 + 10_000 * i as i64;
        let (t, _) = q.claim_task(w, &none, lease, at).await.unwrap().unwrap();
        assert_eq!((t.index, t.attempts), (0, i as u32 + 1));
        // Task 1 stays queued: only task 0 is taken each round.
        q.recover_expired(at + 5000).await.unwrap();
    }
    let m = q.job("m").await.unwrap().unwrap();
    assert_eq!(m.status, JobStatus::Failed);
    assert!(
        m.failure
            .unwrap()
            .starts_with("task 0 of 2 was given up after 3 attempts: the lease of worker c expired")
    );
}

async fn cancelling_a_split_job_stops_its_tasks(f: &Fixture) {
    let q = &*f.queue;
    let lease = Duration::from_secs(30);
    let none = Capabilities::default();
    with_scene(q).await;
    // Queued: cancelled at once, with its tasks.
    enqueue_ok(q, "a", &split_spec(2, 8, ""), 0).await;
    assert_eq!(q.cancel("a", 10).await.unwrap(), Cancellation::Cancelled);
    assert!(
        q.tasks("a")
            .await
            .unwrap()
            .iter()
            .all(|t| t.status == TaskStatus::Cancelled)
    );
    // Running: the tasks not running are cancelled now, the running one is told at its
    // next heartbeat, and the job ends when it stops.
    enqueue_ok(q, "b", &split_spec(3, 12, ""), 20).await;
    q.claim_task("w1", &none, lease, 30).await.unwrap().unwrap();
    assert_eq!(q.cancel("b", 40).await.unwrap(), Cancellation::Requested);
    assert!(q.claim_task("w2", &none, lease, 50).await.unwrap().is_none());
    assert_eq!(
        q.task_heartbeat("b", 0, "w1", lease, None, 60).await.unwrap(),
        Lease::Held { cancel: true }
    );
    assert_eq!(q.job("b").await.unwrap().unwrap().status, JobStatus::Running);
    assert!(q.finish_task("b", 0, "w1", &TaskOutcome::Cancelled, 70).await.unwrap());
    let b = q.job("b").await.unwrap().unwrap();
    assert_eq!((b.status, b.finished_at), (JobStatus::Cancelled, Some(70)));
    assert!(
        q.tasks("b")
            .await
            .unwrap()
            .iter()
            .all(|t| t.status == TaskStatus::Cancelled)
    );
    // A running split job whose worker died is cancelled by the recovery.
    enqueue_ok(q, "c", &split_spec(2, 8, ""), 100).await;
    q.claim_task("w1", &none, Duration::from_secs(1), 100)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(q.cancel("c", 110).await.unwrap(), Cancellation::Requested);
    let r = q.recover_expired(5000).await.unwrap();
    assert_eq!(r.cancelled, vec!["c".to_string()]);
    assert_eq!(q.job("c").await.unwrap().unwrap().status, JobStatus::Cancelled);
}

async fn claims_meet_the_jobs_requirements(f: &Fixture) {
    let q = &*f.queue;
    let lease = Duration::from_secs(30);
    with_scene(q).await;
    let needs_gpu = JobSpec::parse(br#"{"scene": "s", "requires": {"gpu": true}}"#).unwrap();
    enqueue_ok(q, "g", &needs_gpu, 0).await;
    enqueue_ok(q, "o", &split_spec(2, 8, r#", "requires": {"oidn": true}"#), 1).await;
    let cpu_only = Capabilities::default();
    assert!(q.claim("cpu", &cpu_only, lease, 10).await.unwrap().is_none());
    assert!(q.claim_task("cpu", &cpu_only, lease, 10).await.unwrap().is_none());
    assert!(q.claim_task("gpu", &gpu(), lease, 10).await.unwrap().is_none());
    assert_eq!(q.claim("gpu", &gpu(), lease, 10).await.unwrap().unwrap().id, "g");
    let with_oidn = Capabilities {
        oidn: true,
        ..Capabilities::default()
    };
    let (t, j) = q.claim_task("oidn", &with_oidn, lease, 20).await.unwrap().unwrap();
    assert_eq!((j.id.as_str(), t.index), ("o", 0));
    // A job's estimated memory: only workers whose per-job limit covers it claim it (or
    // its tasks).
    let gib = 1u64 << 30;
    assert!(matches!(
        q.enqueue("m", &spec("s"), "c", 100, 2 * gib, 30).await.unwrap(),
        Enqueued::Queued(_)
    ));
    assert!(matches!(
        q.enqueue("mt", &split_spec(2, 8, ""), "c", 100, 2 * gib, 31)
            .await
            .unwrap(),
        Enqueued::Queued(_)
    ));
    let small = Capabilities {
        memory_bytes: gib,
        ..Capabilities::default()
    };
    let big = Capabilities {
        memory_bytes: 4 * gib,
        ..Capabilities::default()
    };
    assert!(q.claim("small", &small, lease, 40).await.unwrap().is_none());
    assert!(q.claim_task("small", &small, lease, 40).await.unwrap().is_none());
    let m = q.claim("big", &big, lease, 40).await.unwrap().unwrap();
    assert_eq!((m.id.as_str(), m.memory_bytes), ("m", 2 * gib));
    assert_eq!(q.claim_task("big", &big, lease, 40).await.unwrap().unwrap().1.id, "mt");
    // Workers register what they have; `workers` lists those seen since a time.
    let caps = Capabilities {
        gpu: true,
        adapter: Some("NVIDIA H200".into()),
        adapter_kind: Some("discrete".into()),
        oidn: true,
        memory_bytes: 1 << 34,
    };
    q.register_worker("w-old", &cpu_only, 100).await.unwrap();
    q.register_worker("w-new", &caps, 100).await.unwrap();
    q.register_worker("w-new", &caps, 5000).await.unwrap();
    let live = q.workers(1000).await.unwrap();
    assert_eq!(live.len(), 1);
    assert_eq!((live[0].id.as_str(), &live[0].capabilities), ("w-new", &caps));
    assert_eq!((live[0].started_at, live[0].last_seen), (100, 5000));
    // The retention sweep forgets workers not seen since a time; the others stay.
    assert_eq!(q.forget_workers(1000).await.unwrap(), 1);
    let all = q.workers(0).await.unwrap();
    assert_eq!(all.iter().map(|w| w.id.as_str()).collect::<Vec<_>>(), ["w-new"]);
    assert_eq!(q.forget_workers(1000).await.unwrap(), 0);
}

async fn finished_jobs_are_deleted_and_found_by_age(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    for (id, at) in [("old", 10), ("new", 20), ("running", 30)] {
        assert!(matches!(
            q.enqueue(id, &spec("s"), "c", 100, 0, at).await.unwrap(),
            Enqueued::Queued(_)
        ));
    }
    for (id, at) in [("old", 100), ("new", 200)] {
        let j = q
            .claim("w", &Capabilities::default(), Duration::from_secs(30), at)
            .await
            .unwrap()
            .unwrap();
        assert_eq!(j.id, id);
        assert!(
            q.finish(id, "w", &Outcome::Failed { reason: "x".into() }, at)
                .await
                .unwrap()
        );
    }
    q.claim("w", &Capabilities::default(), Duration::from_secs(30), 300)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(q.finished_before(150, 10).await.unwrap(), vec!["old".to_string()]);
    assert_eq!(
        q.finished_before(1000, 10).await.unwrap(),
        vec!["old".to_string(), "new".into()]
    );
    assert_eq!(q.finished_before(1000, 1).await.unwrap(), vec!["old".to_string()]);
    assert_eq!(
        q.delete_job("running").await.unwrap(),
        JobDeletion::Unfinished(JobStatus::Running)
    );
    assert_eq!(q.delete_job("old").await.unwrap(), JobDeletion::Deleted);
    assert_eq!(q.delete_job("old").await.unwrap(), JobDeletion::NotFound);
    assert!(q.job("old").await.unwrap().is_none());
    assert_eq!(q.finished_before(1000, 10).await.unwrap(), vec!["new".to_string()]);
}

async fn the_database_clock_is_the_wall_clock(f: &Fixture) {
    // Both databases run on this machine in the tests, so their clock and ours agree to
    // well within a second; a wrong unit or epoch would be off by years.
    let db = f.queue.clock().await.unwrap();
    assert!((db - now_ms()).abs() < 1000, "database clock {db}, local {}", now_ms());
}

fn spec(scene: &str) -> JobSpec {
    JobSpec::parse(format!(r#"{{"scene": "{scene}"}}"#).as_bytes()).unwrap()
}

fn spec_with_priority(scene: &str, priority: i32) -> JobSpec {
    JobSpec::parse(format!(r#"{{"scene": "{scene}", "priority": {priority}}}"#).as_bytes()).unwrap()
}

async fn with_scene(q: &dyn Queue) {
    let scene = SceneRecord {
        id: "s".into(),
        content_hash: "sha256:00".into(),
        format: "glb".into(),
        main_file: "scene.glb".into(),
        files: vec!["scene.glb".into()],
        size_bytes: 1,
        report: json!({"triangles": 12}),
        created_at: 0,
        client: None,
    };
    assert!(q.insert_scene(&scene).await.unwrap());
    assert!(!q.insert_scene(&scene).await.unwrap(), "same id twice is one scene");
    let back = q.scene("s").await.unwrap().unwrap();
    assert_eq!((back.files, back.report), (scene.files, scene.report));
}

async fn enqueue(q: &dyn Queue, id: &str, spec: &JobSpec, now: i64) {
    let r = q.enqueue(id, spec, "c", 1000, 0, now).await.unwrap();
    assert!(matches!(r, Enqueued::Queued(_)), "{r:?}");
}

async fn per_client_queue_limit_and_tokens(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    for i in 0..2 {
        let r = q.enqueue(&format!("a{i}"), &spec("s"), "alice", 2, 0, 0).await.unwrap();
        assert!(matches!(r, Enqueued::Queued(_)));
    }
    assert!(matches!(
        q.enqueue("a2", &spec("s"), "alice", 2, 0, 0).await.unwrap(),
        Enqueued::QueueFull(2)
    ));
    // Another client is not held back by alice's queue.
    assert!(matches!(
        q.enqueue("b0", &spec("s"), "bob", 2, 0, 0).await.unwrap(),
        Enqueued::Queued(_)
    ));
    // A running job no longer counts as queued.
    q.claim("w", &Capabilities::default(), Duration::from_secs(30), 1)
        .await
        .unwrap()
        .unwrap();
    let (alice, total) = q.list(None, Some("alice"), 10, 0).await.unwrap();
    assert_eq!((alice.len(), total), (2, 2));
    assert!(alice.iter().all(|j| j.client.as_deref() == Some("alice")));
    assert!(matches!(
        q.enqueue("a2", &spec("s"), "alice", 2, 0, 0).await.unwrap(),
        Enqueued::Queued(_)
    ));

    let t = TokenRecord {
        id: "tok_1".into(),
        name: "ci".into(),
        hash: "ab".into(),
        created_at: 5,
        revoked_at: None,
        role: Role::Admin,
        source: "file".into(),
    };
    q.insert_token(&t).await.unwrap();
    assert_eq!(q.token_by_hash("ab").await.unwrap(), Some(t.clone()));
    // Revocation is by id only: a name is resolved (and refused when ambiguous) by the CLI.
    assert!(!q.revoke_token("ci", 6).await.unwrap(), "a name is not an id");
    assert!(q.revoke_token("tok_1", 6).await.unwrap());
    assert!(!q.revoke_token("tok_1", 7).await.unwrap(), "already revoked");
    assert_eq!(q.token_by_hash("ab").await.unwrap(), None);
    assert_eq!(q.tokens().await.unwrap()[0].revoked_at, Some(6));
}

async fn lease_expiry_requeues_then_fails_after_three_attempts(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    enqueue(q, "j", &spec("s"), 0).await;
    let lease = Duration::from_millis(100);
    let mut now = 1000;
    for attempt in 1..=MAX_ATTEMPTS {
        let job = q
            .claim("w", &Capabilities::default(), lease, now)
            .await
            .unwrap()
            .expect("queued job is claimed");
        assert_eq!(job.attempts, attempt);
        assert!(
            q.claim("w2", &Capabilities::default(), lease, now)
                .await
                .unwrap()
                .is_none(),
            "one job, one holder"
        );
        // Renewed in time: nothing is recovered.
        let held = q
            .heartbeat("j", "w", lease, &JobUpdate::default(), now + 50)
            .await
            .unwrap();
        assert_eq!(held, Lease::Held { cancel: false });
        assert_eq!(q.recover_expired(now + 140).await.unwrap(), Recovered::default());
        now += 1000;
        let r = q.recover_expired(now).await.unwrap();
        if attempt < MAX_ATTEMPTS {
            assert_eq!(r.requeued, vec!["j".to_string()]);
        } else {
            assert_eq!(r.failed, vec!["j".to_string()]);
        }
        // The old holder finds out at its next heartbeat and writes nothing more.
        let lost = q.heartbeat("j", "w", lease, &JobUpdate::default(), now).await.unwrap();
        assert_eq!(lost, Lease::Lost);
    }
    let job = q.job("j").await.unwrap().unwrap();
    assert_eq!(job.status, JobStatus::Failed);
    assert!(job.failure.unwrap().starts_with("gave up after 3 attempts"));
}

async fn release_does_not_count_the_attempt_and_scene_in_use_is_kept(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    assert!(matches!(
        q.enqueue("j", &spec("missing"), "c", 10, 0, 0).await.unwrap(),
        Enqueued::NoScene
    ));
    enqueue(q, "j", &spec("s"), 0).await;
    assert_eq!(q.delete_scene("s").await.unwrap(), SceneDeletion::InUse(1));
    q.claim("w", &Capabilities::default(), Duration::from_secs(30), 1)
        .await
        .unwrap()
        .unwrap();
    assert!(
        !q.release("j", "someone-else", 2).await.unwrap(),
        "only the holder hands back"
    );
    assert!(q.release("j", "w", 2).await.unwrap());
    let job = q.job("j").await.unwrap().unwrap();
    assert_eq!((job.status, job.attempts, job.worker), (JobStatus::Queued, 0, None));
    assert_eq!(q.cancel("j", 3).await.unwrap(), Cancellation::Cancelled);
    assert_eq!(q.delete_scene("s").await.unwrap(), SceneDeletion::Deleted);
    assert_eq!(q.delete_scene("s").await.unwrap(), SceneDeletion::NotFound);
    assert!(matches!(
        q.enqueue("k", &spec("s"), "c", 10, 0, 4).await.unwrap(),
        Enqueued::NoScene
    ));
}

async fn claims_follow_priority_then_age(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    // Made in this order; "b1" and "b2" in the same millisecond (submission order breaks
    // the tie).
    enqueue(q, "a", &spec_with_priority("s", 0), 10).await;
    enqueue(q, "b1", &spec_with_priority("s", 5), 20).await;
    enqueue(q, "b2", &spec_with_priority("s", 5), 20).await;
    enqueue(q, "c", &spec_with_priority("s", -3), 5).await;
    enqueue(q, "d", &spec_with_priority("s", 0), 30).await;
    let mut order = Vec::new();
    while let Some(j) = q
        .claim("w", &Capabilities::default(), Duration::from_secs(30), 100)
        .await
        .unwrap()
    {
        order.push(j.id);
    }
    assert_eq!(order, ["b1", "b2", "a", "d", "c"]);
    let (listed, total) = q.list(Some(JobStatus::Running), None, 2, 1).await.unwrap();
    assert_eq!(total, 5);
    // Newest first: d (30), b2, b1 (20, later submission first), a, c; offset 1, limit 2.
    let listed: Vec<_> = listed.iter().map(|j| j.id.as_str()).collect();
    assert_eq!(listed, ["b2", "b1"]);
    let counts = q.counts().await.unwrap();
    assert!(counts.contains(&(JobStatus::Running, 5)) && counts.contains(&(JobStatus::Queued, 0)));
}

async fn concurrent_claimers_never_share_a_job(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    const JOBS: usize = 40;
    for i in 0..JOBS {
        enqueue(q, &format!("j{i:02}"), &spec("s"), i as i64).await;
    }
    // Eight claimers over two independent handles ("processes"), each claiming until the
    // queue is empty.
    let handles = [f.queue.clone(), f.other_process().await];
    let mut tasks = Vec::new();
    for w in 0..8 {
        let q = handles[w % 2].clone();
        tasks.push(tokio::spawn(async move {
            let me = format!("w{w}");
            let mut got = Vec::new();
            while let Some(j) = q
                .claim(&me, &Capabilities::default(), Duration::from_secs(30), 1000)
                .await
                .unwrap()
            {
                assert_eq!(j.worker.as_deref(), Some(me.as_str()));
                got.push(j.id);
            }
            (me, got)
        }));
    }
    let mut seen = HashSet::new();
    for t in tasks {
        let (me, got) = t.await.unwrap();
        for id in got {
            assert!(seen.insert(id.clone()), "{id} was claimed twice (second time by {me})");
            // Only the holder can finish it.
            let other = if me == "w0" { "w1" } else { "w0" };
            let done = Outcome::Failed { reason: "test".into() };
            assert!(!q.finish(&id, other, &done, 2000).await.unwrap());
            assert!(q.finish(&id, &me, &done, 2000).await.unwrap());
            assert!(!q.finish(&id, &me, &done, 2001).await.unwrap(), "finished once only");
        }
    }
    assert_eq!(seen.len(), JOBS);
    for j in q.list(None, None, 100, 0).await.unwrap().0 {
        assert_eq!((j.status, j.attempts), (JobStatus::Failed, 1), "{}", j.id);
    }
}

async fn concurrent_submissions_never_overshoot_the_client_limit(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    const LIMIT: u64 = 5;
    let handles = [f.queue.clone(), f.other_process().await];
    let mut tasks = Vec::new();
    for i in 0..16 {
        let q = handles[i % 2].clone();
        tasks.push(tokio::spawn(async move {
            q.enqueue(&format!("e{i}"), &spec("s"), "eve", LIMIT, 0, i as i64)
                .await
                .unwrap()
        }));
    }
    let (mut queued, mut refused) = (0, 0);
    for t in tasks {
        match t.await.unwrap() {
            Enqueued::Queued(_) => queued += 1,
            Enqueued::QueueFull(n) => {
                assert_eq!(n, LIMIT);
                refused += 1;
            }
            Enqueued::NoScene => panic!("the scene exists"),
        }
    }
    assert_eq!((queued, refused), (LIMIT, 16 - LIMIT));
    assert_eq!(
        q.list(Some(JobStatus::Queued), Some("eve"), 100, 0).await.unwrap().1,
        LIMIT
    );
}

async fn heartbeat_progress_cancel_and_finish(f: &Fixture) {
    let q = &*f.queue;
    with_scene(q).await;
    enqueue(q, "j", &spec("s"), 0).await;
    let lease = Duration::from_secs(10);
    q.claim("w", &Capabilities::default(), lease, 1).await.unwrap().unwrap();
    let update = JobUpdate {
        progress: Some(json!({"steps": 3, "fraction": 0.25})),
        history: Some(json!([{"seconds": 0.5, "steps": 3, "error": 0.1}])),
        plan: Some(json!({"passes": ["direct"]})),
        snapshots: Some(2),
    };
    assert_eq!(
        q.heartbeat("j", "w", lease, &update, 50).await.unwrap(),
        Lease::Held { cancel: false }
    );
    // An empty update renews the lease and keeps what was written.
    q.heartbeat("j", "w", lease, &JobUpdate::default(), 60).await.unwrap();
    let j = q.job("j").await.unwrap().unwrap();
    assert_eq!(j.progress, update.progress);
    assert_eq!(Some(j.history), update.history);
    assert_eq!(j.plan, update.plan);
    assert_eq!(
        (j.snapshots, j.lease_expires_at, j.started_at),
        (2, Some(10_060), Some(1))
    );

    assert_eq!(q.cancel("j", 70).await.unwrap(), Cancellation::Requested);
    assert_eq!(
        q.heartbeat("j", "w", lease, &JobUpdate::default(), 80).await.unwrap(),
        Lease::Held { cancel: true }
    );
    assert!(q.finish("j", "w", &Outcome::Cancelled, 90).await.unwrap());
    assert_eq!(
        q.cancel("j", 95).await.unwrap(),
        Cancellation::AlreadyFinished(JobStatus::Cancelled)
    );
    assert_eq!(q.cancel("nope", 95).await.unwrap(), Cancellation::NotFound);

    enqueue(q, "k", &spec("s"), 100).await;
    q.claim("w", &Capabilities::default(), lease, 101)
        .await
        .unwrap()
        .unwrap();
    let summary = json!({"steps": 8, "seconds": 1.5});
    let done = Outcome::Succeeded {
        summary: summary.clone(),
        progress: json!({"steps": 8, "fraction": 1.0}),
        history: json!([]),
    };
    assert!(q.finish("k", "w", &done, 200).await.unwrap());
    let k = q.job("k").await.unwrap().unwrap();
    assert_eq!(
        (k.status, k.summary, k.finished_at),
        (JobStatus::Succeeded, Some(summary), Some(200))
    );
    assert_eq!(k.lease_expires_at, None);
}

async fn other_processes_hear_of_new_work_and_job_changes(f: &Fixture) {
    let listener = f.other_process().await;
    let hub = Arc::new(Hub::default());
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let Some(task) = listener.listen(hub.clone(), stop_rx) else {
        assert!(matches!(f.store, Store::Sqlite(_)), "PostgreSQL must notify");
        return;
    };
    let q = &*f.queue;
    with_scene(q).await;
    let mut changes = hub.changed.subscribe();
    // LISTEN is issued by the task: wait until it is in place (a first enqueue may come
    // before it; the retry loop covers that).
    let wait = Duration::from_secs(5);
    let mut n = 0;
    let woke = tokio::time::timeout(wait, async {
        loop {
            let notified = hub.work.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            n += 1;
            enqueue(q, &format!("n{n}"), &spec("s"), n).await;
            if tokio::time::timeout(Duration::from_millis(500), notified).await.is_ok() {
                break;
            }
        }
    })
    .await;
    assert!(woke.is_ok(), "no lightmapd_work notification within {wait:?}");
    // A progress write by the holder reaches the other process's event streams.
    let job = q
        .claim("w", &Capabilities::default(), Duration::from_secs(30), 1000)
        .await
        .unwrap()
        .unwrap();
    let update = JobUpdate {
        progress: Some(json!({"steps": 1})),
        ..JobUpdate::default()
    };
    q.heartbeat(&job.id, "w", Duration::from_secs(30), &update, 1001)
        .await
        .unwrap();
    let heard = tokio::time::timeout(wait, async {
        loop {
            match changes.recv().await {
                Ok(id) if id == job.id => return,
                Ok(_) => continue,
                Err(e) => panic!("{e}"),
            }
        }
    })
    .await;
    assert!(
        heard.is_ok(),
        "no lightmapd_job notification for {} within {wait:?}",
        job.id
    );
    let _ = stop_tx.send(true);
    task.await.unwrap();
}

/// Snapshots while a split job's tasks run: one claim a snapshot interval for the whole
/// job, whichever running task asks first; only a running task's own worker may claim;
/// numbers go on from the stored count, and a snapshot stored late never lowers it.
async fn a_split_jobs_tasks_take_turns_at_its_snapshots(f: &Fixture) {
    let q = &*f.queue;
    let lease = Duration::from_secs(30);
    let every = Duration::from_secs(2);
    let none = Capabilities::default();
    with_scene(q).await;
    enqueue_ok(q, "j", &split_spec(2, 12, ""), 10).await;
    // Not running yet: nobody's turn.
    assert_eq!(q.claim_task_snapshot("j", 0, "w1", every, 15).await.unwrap(), None);
    for w in ["w1", "w2"] {
        q.claim_task(w, &none, lease, 20).await.unwrap().unwrap();
    }
    assert_eq!(
        q.claim_task_snapshot("j", 0, "w2", every, 100).await.unwrap(),
        None,
        "not w2's task"
    );
    assert_eq!(q.claim_task_snapshot("j", 0, "w1", every, 100).await.unwrap(), Some(1));
    assert_eq!(
        q.claim_task_snapshot("j", 1, "w2", every, 1000).await.unwrap(),
        None,
        "within the interval"
    );
    assert_eq!(q.claim_task_snapshot("j", 1, "w2", every, 2100).await.unwrap(), Some(2));
    // A claim that stored nothing is handed back: the next takes its number again; one
    // with a later claim after it is not.
    q.release_task_snapshot("j", 2).await.unwrap();
    assert_eq!(q.claim_task_snapshot("j", 0, "w1", every, 4100).await.unwrap(), Some(2));
    q.release_task_snapshot("j", 1).await.unwrap();
    assert_eq!(q.claim_task_snapshot("j", 0, "w1", every, 6100).await.unwrap(), Some(3));
    q.release_task_snapshot("j", 3).await.unwrap();
    // Before any snapshot, the merged progress is a history point once every task has
    // an error.
    let beat_of = |steps, error| TaskBeat {
        steps,
        seconds: 1.0,
        error: Some(error),
    };
    for (k, w) in [(0, "w1"), (1, "w2")] {
        q.task_heartbeat("j", k, w, lease, Some(&beat_of(4, 0.1)), 6200)
            .await
            .unwrap();
    }
    let raw = q.job("j").await.unwrap().unwrap().history;
    assert_eq!(raw.as_array().map(Vec::len), Some(1), "{raw}");
    let raw_steps = raw[0]["steps"].as_u64().unwrap();
    // Claim 2 is stored first, then claim 1: the count stays at the later. Each adds its
    // point (the delivered error of what it holds) to the history; claim 1's, made from
    // fewer steps, takes the place of claim 2's, so the steps never go back.
    let point = |steps: u64, error: f32| json!({"seconds": 7.0, "steps": steps, "error": error, "raw_error": 0.3f32});
    assert!(
        q.task_snapshot_stored("j", 2, &point(raw_steps + 4, 0.2))
            .await
            .unwrap()
    );
    let history = q.job("j").await.unwrap().unwrap().history;
    assert_eq!(
        history.as_array().unwrap()[1..],
        [point(raw_steps + 4, 0.2)],
        "{history}"
    );
    assert!(
        q.task_snapshot_stored("j", 1, &point(raw_steps + 2, 0.25))
            .await
            .unwrap()
    );
    assert_eq!(q.job("j").await.unwrap().unwrap().snapshots, 2);
    // From the first snapshot on, heartbeats add no raw points: the history is the
    // snapshots' points, as a single bake's.
    q.task_heartbeat("j", 1, "w2", lease, Some(&beat_of(6, 0.1)), 9200)
        .await
        .unwrap();
    let history = q.job("j").await.unwrap().unwrap().history;
    assert_eq!(
        history.as_array().unwrap()[..],
        [raw[0].clone(), point(raw_steps + 2, 0.25)],
        "{history}"
    );
    // A finished task hands the turn to the other.
    let beat = TaskBeat {
        steps: 6,
        seconds: 1.0,
        error: Some(0.1),
    };
    assert!(
        q.finish_task("j", 0, "w1", &TaskOutcome::Baked(beat), 12200)
            .await
            .unwrap()
    );
    assert_eq!(
        q.claim_task_snapshot("j", 0, "w1", every, 14200).await.unwrap(),
        None,
        "task 0 has ended"
    );
    assert_eq!(
        q.claim_task_snapshot("j", 1, "w2", every, 14200).await.unwrap(),
        Some(3)
    );
    // Once the job is over, nothing more is recorded.
    assert!(
        q.finish_task("j", 1, "w2", &TaskOutcome::Baked(beat), 14300)
            .await
            .unwrap()
    );
    let (m, _) = q.claim_task("w3", &none, lease, 14400).await.unwrap().unwrap();
    let merged = TaskOutcome::Merged {
        summary: json!({"steps": 12}),
        progress: json!({"steps": 12, "fraction": 1.0}),
        history: json!([]),
        plan: json!({}),
    };
    assert!(q.finish_task("j", m.index, "w3", &merged, 14500).await.unwrap());
    assert!(!q.task_snapshot_stored("j", 3, &point(12, 0.1)).await.unwrap());
    let job = q.job("j").await.unwrap().unwrap();
    assert_eq!(job.snapshots, 2);
    assert_eq!(job.history.as_array().map(Vec::len), Some(2), "nothing added once over");
}

/// The embedded migrations are exactly the files of `migrations/<store>/`, with the
/// version and description sqlx's macro would read off each name (so a database an
/// earlier build migrated is recognised), and a new file cannot be forgotten.
#[test]
fn embedded_migrations_are_the_migration_folders() {
    for (store, embedded) in [
        ("sqlite", super::sqlite::MIGRATIONS),
        ("postgres", super::postgres::MIGRATIONS),
    ] {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("migrations")
            .join(store);
        let mut files: Vec<(i64, String, String)> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "sql"))
            .map(|p| {
                let name = p.file_stem().unwrap().to_string_lossy().into_owned();
                let (version, description) = name.split_once('_').unwrap();
                (
                    version.parse().unwrap(),
                    description.replace('_', " "),
                    std::fs::read_to_string(&p).unwrap(),
                )
            })
            .collect();
        files.sort();
        let embedded: Vec<(i64, String, String)> = embedded
            .iter()
            .map(|(v, d, s)| (*v, d.to_string(), s.to_string()))
            .collect();
        assert_eq!(embedded, files, "migrations/{store}/ and {store}::MIGRATIONS differ");
    }
}

/// A split job's running history: a point when the merged progress has moved on (a
/// quarter more steps and a second, or any new steps and five seconds), none without an
/// error or steps; the merge's point appended after them.
#[test]
fn a_split_jobs_history_runs_until_the_merge() {
    let progress = |steps: u64, elapsed_s: f64, error: Option<f32>| json!({"steps": steps, "fraction": 0.5, "elapsed_s": elapsed_s, "error": error});
    let empty = json!([]);
    let steps_of = |h: &Value| -> Vec<u64> {
        h.as_array()
            .unwrap()
            .iter()
            .map(|p| p["steps"].as_u64().unwrap())
            .collect()
    };
    assert_eq!(running_history(&empty, &progress(0, 1.0, Some(0.5)), 0), None);
    assert_eq!(running_history(&empty, &progress(10, 1.0, None), 0), None);
    let h = running_history(&empty, &progress(10, 1.0, Some(0.2)), 0).unwrap();
    assert_eq!(
        h,
        json!([{"seconds": 1.0, "steps": 10, "error": 0.2f32, "raw_error": 0.2f32}])
    );
    // 12 steps (under a quarter more) a second later, 13 after half a second: not yet.
    assert_eq!(running_history(&h, &progress(12, 2.0, Some(0.19)), 0), None);
    assert_eq!(running_history(&h, &progress(13, 1.5, Some(0.19)), 0), None);
    // A quarter more and a second: due; so are any new steps after five seconds.
    let h = running_history(&h, &progress(13, 2.0, Some(0.18)), 0).unwrap();
    assert_eq!(h.as_array().unwrap().len(), 2);
    assert_eq!(running_history(&h, &progress(13, 9.0, Some(0.18)), 0), None);
    let h = running_history(&h, &progress(14, 7.0, Some(0.17)), 0).unwrap();
    assert_eq!(steps_of(&h), [10, 13, 14]);
    // Once a running snapshot is stored, its points are the history: no raw point.
    assert_eq!(running_history(&h, &progress(40, 30.0, Some(0.1)), 1), None);
    // A snapshot's point drops the last points that have more steps than it (raw points
    // recorded ahead of the halves it was made from): steps never go back.
    let snap = json!({"seconds": 8.0, "steps": 13, "error": 0.15f32});
    let with = with_snapshot_point(&h, &snap);
    assert_eq!(steps_of(&with), [10, 13, 13]);
    assert_eq!(with[2], snap);
    let ahead = json!({"seconds": 9.0, "steps": 20, "error": 0.1f32});
    assert_eq!(with_snapshot_point(&with, &ahead).as_array().unwrap().len(), 4);
    let behind = json!({"seconds": 9.0, "steps": 12, "error": 0.1f32});
    assert_eq!(steps_of(&with_snapshot_point(&with, &behind)), [10, 12]);
    let merged = history_then(&h, &json!([{"seconds": 8.0, "steps": 14, "error": 0.05f32}]));
    assert_eq!(merged.as_array().unwrap().len(), 4);
    assert_eq!(merged[3]["error"], json!(0.05f32));
    // A job that ran no point yet (or a store's NULL) keeps just the merge's.
    assert_eq!(
        history_then(&Value::Null, &json!([{"steps": 1}])),
        json!([{"steps": 1}])
    );
}

/// A split job's progress from its tasks (no store involved): step ranges of one region
/// add their steps and their errors in quadrature by step weight; regions average.
#[test]
fn split_progress_adds_ranges_and_averages_regions() {
    let spec = split_spec(4, 400, "");
    // One region, four ranges of 100 steps, each with error 0.2: 400 steps, 0.2 / 2.
    let p = merged_progress(&spec, Some(0), 1000, &[(100, Some(0.2)); 4]);
    assert_eq!(p["steps"], 400);
    assert!((p["error"].as_f64().unwrap() - 0.1).abs() < 1e-6, "{p}");
    // Two regions of two ranges: region 0 has baked 200 steps (error 0.1), region 1 100
    // (its second range not started, error 0.3): steps (200 + 100) / 2, error
    // sqrt((0.1² + 0.3²) / 2).
    let spec = split_spec(4, 400, r#", "regions": 2"#);
    let p = merged_progress(
        &spec,
        Some(0),
        1000,
        &[
            (100, Some(0.1 * 2f32.sqrt())),
            (100, Some(0.1 * 2f32.sqrt())),
            (100, Some(0.3)),
            (0, None),
        ],
    );
    assert_eq!(p["steps"], 150);
    let want = ((0.01f64 + 0.09) / 2.0).sqrt();
    assert!((p["error"].as_f64().unwrap() - want).abs() < 1e-6, "{p}");
    // A region that has baked nothing has no error yet, so neither has the job.
    let p = merged_progress(
        &spec,
        Some(0),
        1000,
        &[(100, Some(0.1)), (0, None), (0, None), (0, None)],
    );
    assert!(p["error"].is_null(), "{p}");
    // Chains (sdb): their errors carry a bias every chain shares, so the job's is their
    // step-weighted mean, not the quadrature sum: four chains of error 0.2 are 0.2, and
    // 300 steps at 0.1 with 100 at 0.3 are 0.15.
    let spec = split_spec(4, 400, r#", "technique": "sdb""#);
    let p = merged_progress(&spec, Some(0), 1000, &[(100, Some(0.2)); 4]);
    assert_eq!(p["steps"], 400);
    assert!((p["error"].as_f64().unwrap() - 0.2).abs() < 1e-6, "{p}");
    let p = merged_progress(
        &spec,
        Some(0),
        1000,
        &[(100, Some(0.1)), (100, Some(0.1)), (100, Some(0.1)), (100, Some(0.3))],
    );
    assert!((p["error"].as_f64().unwrap() - 0.15).abs() < 1e-6, "{p}");
}

async fn tasks_and_whole_jobs_share_one_priority_order(f: &Fixture) {
    let q = &*f.queue;
    let lease = Duration::from_secs(30);
    let cpu = Capabilities::default();
    with_scene(q).await;
    // A split job, then a whole job of higher priority: the whole job goes first.
    enqueue_ok(q, "split", &split_spec(2, 8, ""), 0).await;
    enqueue_ok(q, "urgent", &spec_with_priority("s", 5), 1).await;
    assert!(q.claim_task("w", &cpu, lease, 10).await.unwrap().is_none());
    assert_eq!(q.claim("w", &cpu, lease, 10).await.unwrap().unwrap().id, "urgent");
    let (t, j) = q.claim_task("w", &cpu, lease, 11).await.unwrap().unwrap();
    assert_eq!((j.id.as_str(), t.index), ("split", 0));
    // Equal priority: the older first, whichever kind it is.
    enqueue_ok(q, "older", &spec("s"), 2).await;
    enqueue_ok(q, "newer-split", &split_spec(2, 8, ""), 3).await;
    // "split" (enqueued at 0) is still ahead of "older" (2): its second task.
    let (t, j) = q.claim_task("w", &cpu, lease, 12).await.unwrap().unwrap();
    assert_eq!((j.id.as_str(), t.index), ("split", 1));
    assert!(q.claim_task("w", &cpu, lease, 13).await.unwrap().is_none());
    assert_eq!(q.claim("w", &cpu, lease, 13).await.unwrap().unwrap().id, "older");
    assert_eq!(
        q.claim_task("w", &cpu, lease, 14).await.unwrap().unwrap().1.id,
        "newer-split"
    );
    // A whole job this worker cannot run does not hold its tasks back.
    enqueue_ok(
        q,
        "gpu-only",
        &JobSpec::parse(br#"{"scene": "s", "priority": 9, "requires": {"gpu": true}}"#).unwrap(),
        4,
    )
    .await;
    assert_eq!(
        q.claim_task("w", &cpu, lease, 15).await.unwrap().unwrap().1.id,
        "newer-split"
    );
    assert!(q.claim_task("w", &cpu, lease, 16).await.unwrap().is_none());
    assert!(q.claim("w", &cpu, lease, 16).await.unwrap().is_none());
    assert_eq!(q.claim("g", &gpu(), lease, 17).await.unwrap().unwrap().id, "gpu-only");
}

/// A job of 3 rounds of 2 regions (issue 25 point 1): 6 bake tasks, task r 2 + p being
/// region p's of round r, and the merge. Round 0's are queued, the rest wait; a round is
/// queued by the success that completes the round before (not by a failed attempt, which
/// is retried within its round), the merge by the last round's; the job's progress counts
/// each region's steps over its rounds, with the error of its latest round.
async fn a_job_in_rounds_queues_each_round_once_the_one_before_has_succeeded(f: &Fixture) {
    let q = &*f.queue;
    let lease = Duration::from_secs(30);
    let none = Capabilities::default();
    with_scene(q).await;
    let spec =
        JobSpec::parse(br#"{"scene": "s", "technique": "hemicube", "regions": 2, "rounds": 3, "stop": {"steps": 14}}"#)
            .unwrap();
    assert_eq!((spec.bake_tasks(), spec.first_queued()), (6, 2));
    enqueue_ok(q, "j", &spec, 10).await;
    let states = || async {
        q.tasks("j")
            .await
            .unwrap()
            .iter()
            .map(|t| (t.index, t.count, t.status))
            .collect::<Vec<_>>()
    };
    use TaskStatus::{Queued, Running, Succeeded, Waiting};
    assert_eq!(
        states().await,
        vec![
            (0, 6, Queued),
            (1, 6, Queued),
            (2, 6, Waiting),
            (3, 6, Waiting),
            (4, 6, Waiting),
            (5, 6, Waiting),
            (6, 6, Waiting)
        ]
    );
    let beat = |steps, error| TaskBeat {
        steps,
        seconds: 1.0,
        error: Some(error),
    };
    let claim = |w: &'static str, at| {
        let none = none.clone();
        async move { q.claim_task(w, &none, lease, at).await.unwrap().map(|(t, _)| t.index) }
    };
    // Task k, running on worker w, baked `steps` with its own `error`.
    let baked = |k: u32, w: &'static str, steps: u64, error: f32, at: i64| async move {
        let outcome = TaskOutcome::Baked(beat(steps, error));
        assert!(q.finish_task("j", k, w, &outcome, at).await.unwrap(), "task {k} on {w}");
    };
    let progress = || async { q.job("j").await.unwrap().unwrap().progress.unwrap() };
    assert_eq!(claim("w1", 20).await, Some(0));
    assert_eq!(claim("w2", 20).await, Some(1));
    // Round 1 waits for all of round 0.
    assert_eq!(claim("w3", 21).await, None);
    baked(0, "w1", 2, 0.3, 30).await;
    assert_eq!(claim("w3", 31).await, None);
    // A failed attempt is retried as a task of its round; round 1 still waits.
    let failed = TaskOutcome::Failed {
        reason: "device lost".into(),
        retry: true,
    };
    assert!(q.finish_task("j", 1, "w2", &failed, 40).await.unwrap());
    assert_eq!(states().await[1..4], [(1, 6, Queued), (2, 6, Waiting), (3, 6, Waiting)]);
    assert_eq!(claim("w3", 41).await, Some(1));
    baked(1, "w3", 2, 0.1, 50).await;
    let p = progress().await;
    assert_eq!(p["steps"], 2);
    let want = ((0.09f64 + 0.01) / 2.0).sqrt();
    assert!((p["error"].as_f64().unwrap() - want).abs() < 1e-6, "{p}");
    // Round 1 is queued, round 2 and the merge still wait.
    assert_eq!(
        states().await[2..],
        [
            (2, 6, Queued),
            (3, 6, Queued),
            (4, 6, Waiting),
            (5, 6, Waiting),
            (6, 6, Waiting)
        ]
    );
    assert_eq!(claim("w1", 51).await, Some(2));
    assert_eq!(claim("w2", 51).await, Some(3));
    baked(2, "w1", 4, 0.05, 60).await;
    // Region 0: 2 + 4 steps at its latest round's 0.05; region 1: 2 steps at 0.1 so far.
    let p = progress().await;
    assert_eq!(p["steps"], 4);
    let want = ((0.0025f64 + 0.01) / 2.0).sqrt();
    assert!((p["error"].as_f64().unwrap() - want).abs() < 1e-6, "{p}");
    assert!((p["fraction"].as_f64().unwrap() - 4.0 / 14.0).abs() < 1e-9, "{p}");
    assert_eq!(claim("w3", 61).await, None);
    baked(3, "w2", 4, 0.04, 70).await;
    assert_eq!(claim("w1", 71).await, Some(4));
    assert_eq!(claim("w2", 71).await, Some(5));
    assert_eq!(states().await[4..], [(4, 6, Running), (5, 6, Running), (6, 6, Waiting)]);
    baked(4, "w1", 8, 0.02, 80).await;
    assert_eq!(claim("w3", 81).await, None);
    baked(5, "w2", 8, 0.02, 90).await;
    let p = progress().await;
    assert_eq!(p["steps"], 14);
    assert!((p["error"].as_f64().unwrap() - 0.02).abs() < 1e-6, "{p}");
    // The merge is queued once the last round has succeeded.
    assert_eq!(claim("w3", 91).await, Some(6));
    assert!(states().await[..6].iter().all(|t| t.2 == Succeeded));
}
