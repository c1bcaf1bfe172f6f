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

use std::sync::Arc;
use std::time::{Duration, Instant};

use lightmapd::service::model::JobSpec;
use lightmapd::service::queue::postgres::PostgresQueue;
use lightmapd::service::queue::{Capabilities, Enqueued, JobUpdate, Outcome, Queue, SceneRecord, now_ms};
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
            .enqueue(&format!("j{i}"), &spec, "bench", u64::MAX, i as i64)
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
        admin.enqueue(&id, &spec, &id, 10, 0).await.unwrap();
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
}
