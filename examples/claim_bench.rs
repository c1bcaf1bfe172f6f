//! Claim throughput and latency of the PostgreSQL queue (issue 11, point 6; the numbers
//! are in docs/scaling.md).
//!
//! `cargo run --release --example claim_bench [-- URL [JOBS]]` (URL defaults to
//! `$LIGHTMAPD_TEST_POSTGRES`). For 1, 3 and 10 concurrent claimers, each with a pool of
//! its own (as separate worker processes would have), on a queue pre-filled with JOBS
//! queued jobs (default 3000): every claimer loops claim → finish until the queue is
//! empty. Reported: claims per second (jobs claimed and finished / wall time), and the
//! p50 / p99 latency of one claim as the claimer sees it (round trip included). Then the
//! same claimers send progress heartbeats (the 4 Hz write of a running bake) as fast as
//! they can: heartbeats per second and their p50 / p99. Every run uses a fresh schema,
//! dropped at the end.
//!
//! Then the task queue of split jobs (issue 25): 10 jobs of JOBS/10 tasks each; every
//! claimer loops claim_task → one progress heartbeat (which rewrites the job's merged
//! progress from all its task rows) → finish_task until every bake task is done (each
//! job's last bake task queues its merge, which is claimed and finished too). Reported:
//! tasks per second and the p50 / p99 of one task claim and of one progress heartbeat.

use std::sync::Arc;
use std::time::{Duration, Instant};

use lightmapd::service::model::JobSpec;
use lightmapd::service::queue::postgres::PostgresQueue;
use lightmapd::service::queue::{
    Capabilities, Enqueued, JobUpdate, Outcome, Queue, SceneRecord, TaskBeat, TaskOutcome, now_ms,
};
use serde_json::{Value, json};

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

async fn fill(q: &PostgresQueue, jobs: usize) {
    let scene = SceneRecord {
        id: "s".into(),
        content_hash: "sha256:bench".into(),
        format: "glb".into(),
        main_file: "scene.glb".into(),
        files: vec!["scene.glb".into()],
        size_bytes: 1,
        report: Value::Null,
        created_at: 0,
        client: None,
    };
    q.insert_scene(&scene).await.unwrap();
    let spec = JobSpec::parse(br#"{"scene": "s", "resolution": 64, "stop": {"steps": 16}}"#).unwrap();
    for i in 0..jobs {
        let r = q
            .enqueue(&format!("j{i}"), &spec, "bench", u64::MAX, 0, i as i64)
            .await
            .unwrap();
        assert!(matches!(r, Enqueued::Queued(_)));
    }
}

async fn run(url: &str, claimers: usize, jobs: usize) {
    let schema = format!("bench_{}", uuid::Uuid::new_v4().simple());
    let admin = PostgresQueue::open_in_schema(url, &schema).await.unwrap();
    fill(&admin, jobs).await;
    let mut handles = Vec::new();
    for _ in 0..claimers {
        handles.push(Arc::new(PostgresQueue::open_in_schema(url, &schema).await.unwrap()));
    }
    let lease = Duration::from_secs(60);

    // Claim → finish until empty.
    let start = Instant::now();
    let mut tasks = Vec::new();
    for (w, q) in handles.iter().enumerate() {
        let q = q.clone();
        tasks.push(tokio::spawn(async move {
            let me = format!("bench-{w}");
            let mut lat = Vec::new();
            loop {
                let t = Instant::now();
                let Some(job) = q.claim(&me, &Capabilities::default(), lease, now_ms()).await.unwrap() else {
                    break;
                };
                lat.push(t.elapsed());
                let done = Outcome::Failed { reason: "bench".into() };
                assert!(q.finish(&job.id, &me, &done, now_ms()).await.unwrap());
            }
            lat
        }));
    }
    let mut lat = Vec::new();
    for t in tasks {
        lat.extend(t.await.unwrap());
    }
    let wall = start.elapsed();
    assert_eq!(lat.len(), jobs, "every job claimed exactly once");
    lat.sort();
    println!(
        "claim+finish  claimers {claimers:>2}  jobs {jobs}  {:>7.0} claims/s  claim p50 {:>6.2} ms  p99 {:>6.2} ms",
        jobs as f64 / wall.as_secs_f64(),
        percentile(&lat, 0.5),
        percentile(&lat, 0.99)
    );

    // Heartbeats with progress on one running job per claimer, for a fixed time.
    let spec = JobSpec::parse(br#"{"scene": "s"}"#).unwrap();
    let mut running = Vec::new();
    for (w, q) in handles.iter().enumerate() {
        let id = format!("hb{w}");
        admin.enqueue(&id, &spec, &id, 10, 0, 0).await.unwrap();
        let me = format!("bench-{w}");
        let job = q
            .claim(&me, &Capabilities::default(), lease, now_ms())
            .await
            .unwrap()
            .unwrap();
        running.push((q.clone(), me, job.id));
    }
    let span = Duration::from_secs(3);
    let start = Instant::now();
    let mut tasks = Vec::new();
    for (q, me, id) in running {
        tasks.push(tokio::spawn(async move {
            let mut lat = Vec::new();
            let mut step = 0u64;
            while start.elapsed() < span {
                step += 1;
                let u = JobUpdate {
                    progress: Some(json!({"steps": step, "fraction": 0.5, "elapsed_s": 1.0, "error": 0.01})),
                    ..JobUpdate::default()
                };
                let t = Instant::now();
                q.heartbeat(&id, &me, lease, &u, now_ms()).await.unwrap();
                lat.push(t.elapsed());
            }
            lat
        }));
    }
    let mut lat = Vec::new();
    for t in tasks {
        lat.extend(t.await.unwrap());
    }
    let wall = start.elapsed();
    lat.sort();
    println!(
        "heartbeat     claimers {claimers:>2}  {:>7.0} beats/s  beat p50 {:>6.2} ms  p99 {:>6.2} ms",
        lat.len() as f64 / wall.as_secs_f64(),
        percentile(&lat, 0.5),
        percentile(&lat, 0.99)
    );
    admin.drop_schema(&schema).await.unwrap();
}

/// Split jobs: `jobs / 10` tasks each, 10 jobs, `claimers` claiming tasks.
async fn run_tasks(url: &str, claimers: usize, jobs: usize) {
    let schema = format!("bench_{}", uuid::Uuid::new_v4().simple());
    let admin = PostgresQueue::open_in_schema(url, &schema).await.unwrap();
    fill(&admin, 0).await;
    let per_job = (jobs / 10).max(2);
    let spec = JobSpec::parse(
        format!(
            r#"{{"scene": "s", "resolution": 64, "stop": {{"steps": {}}}, "tasks": {per_job}}}"#,
            2 * per_job
        )
        .as_bytes(),
    )
    .unwrap();
    for j in 0..10 {
        let r = admin
            .enqueue(&format!("split{j}"), &spec, "bench", u64::MAX, 0, j)
            .await
            .unwrap();
        assert!(matches!(r, Enqueued::Queued(_)));
    }
    let mut handles = Vec::new();
    for _ in 0..claimers {
        handles.push(Arc::new(PostgresQueue::open_in_schema(url, &schema).await.unwrap()));
    }
    let lease = Duration::from_secs(60);
    let start = Instant::now();
    let mut running = Vec::new();
    for (w, q) in handles.iter().enumerate() {
        let q = q.clone();
        running.push(tokio::spawn(async move {
            let me = format!("bench-{w}");
            let caps = Capabilities::default();
            let (mut claim, mut beat) = (Vec::new(), Vec::new());
            loop {
                let t = Instant::now();
                let Some((task, job)) = q.claim_task(&me, &caps, lease, now_ms()).await.unwrap() else {
                    break;
                };
                claim.push(t.elapsed());
                let outcome = if task.is_merge() {
                    TaskOutcome::Merged {
                        summary: json!({}),
                        progress: json!({}),
                        history: json!([]),
                        plan: json!({}),
                    }
                } else {
                    let b = TaskBeat {
                        steps: 1,
                        seconds: 0.1,
                        error: Some(0.05),
                    };
                    let t = Instant::now();
                    q.task_heartbeat(&job.id, task.index, &me, lease, Some(&b), now_ms())
                        .await
                        .unwrap();
                    beat.push(t.elapsed());
                    TaskOutcome::Baked(TaskBeat { steps: 2, ..b })
                };
                assert!(
                    q.finish_task(&job.id, task.index, &me, &outcome, now_ms())
                        .await
                        .unwrap()
                );
            }
            (claim, beat)
        }));
    }
    let (mut claim, mut beat) = (Vec::new(), Vec::new());
    for t in running {
        let (c, b) = t.await.unwrap();
        claim.extend(c);
        beat.extend(b);
    }
    let wall = start.elapsed();
    // A merge is claimable only once its job's bake tasks are done, so a claimer can find
    // nothing while others finish the last ones; claim whatever is left.
    let me = "bench-last";
    while let Some((task, job)) = admin
        .claim_task(me, &Capabilities::default(), lease, now_ms())
        .await
        .unwrap()
    {
        assert!(task.is_merge());
        let o = TaskOutcome::Merged {
            summary: json!({}),
            progress: json!({}),
            history: json!([]),
            plan: json!({}),
        };
        assert!(admin.finish_task(&job.id, task.index, me, &o, now_ms()).await.unwrap());
    }
    for j in 0..10 {
        let job = admin.job(&format!("split{j}")).await.unwrap().unwrap();
        assert_eq!(job.status.as_str(), "succeeded", "every split job merged once");
    }
    claim.sort();
    beat.sort();
    println!(
        "tasks         claimers {claimers:>2}  10 jobs x {per_job} tasks  {:>7.0} tasks/s  claim p50 {:>6.2} ms  p99 {:>6.2} ms  progress beat p50 {:>6.2} ms  p99 {:>6.2} ms",
        claim.len() as f64 / wall.as_secs_f64(),
        percentile(&claim, 0.5),
        percentile(&claim, 0.99),
        percentile(&beat, 0.5),
        percentile(&beat, 0.99)
    );
    admin.drop_schema(&schema).await.unwrap();
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .or_else(|| std::env::var("LIGHTMAPD_TEST_POSTGRES").ok())
        .expect("give a postgres:// URL or set LIGHTMAPD_TEST_POSTGRES");
    let jobs: usize = args.next().map_or(3000, |s| s.parse().expect("JOBS is a number"));
    for claimers in [1, 3, 10] {
        run(&url, claimers, jobs).await;
    }
    for claimers in [1, 3, 10] {
        run_tasks(&url, claimers, jobs).await;
    }
}
