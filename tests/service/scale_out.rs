//! Scale-out with real parts (issue 11, points 3 and 4): separate `lightmapd` processes
//! sharing one PostgreSQL database and one artifact store.
//!
//! - `one_api_three_workers_survive_two_sigkills`: one API process (`serve --workers 0`)
//!   and three `worker` processes; 100 small jobs, two of them longer (2.5 s) and of
//!   higher priority so they are claimed next and are surely mid-bake when their worker
//!   is killed with SIGKILL (twice, two different worker processes, each replaced by a
//!   fresh worker at once so three keep running; the second long job is submitted after
//!   the first kill). Checks: every job succeeded exactly once, observed by an audit
//!   trigger the test installs on `jobs` (every status transition is recorded, so a second
//!   `succeeded` or a job run to the end by two workers would show), the two killed jobs
//!   went back to `queued` by lease expiry and succeeded at their second attempt on another
//!   worker, every other job at its first; every lightmap downloads through the API and
//!   decodes as a whole EXR; every surviving process exits 0 on SIGTERM.
//! - `worker_sigterm_hands_the_job_back`: a `worker` process on PostgreSQL stops within a
//!   step of SIGTERM, exits 0, and its job is `queued` again with the attempt not counted
//!   (long before its 30 s lease could have expired).
//!
//! PostgreSQL comes from `LIGHTMAPD_TEST_POSTGRES`; without it the tests print a loud
//! skip line and pass, unless `LIGHTMAPD_REQUIRE_SERVICES=1` (CI). Each test works in a
//! schema of its own (`?options=-csearch_path=…` on the URL the processes get), dropped
//! when it passes. Artifacts: the first test stores them in the S3-protocol server
//! (`service_common::S3`: moto on 127.0.0.1:9000, started by `scripts/setup.sh test`) under a
//! fresh `s3://lightmapd-test/scale-out-…` prefix, passing `AWS_*` to every process, and
//! skips (fails under `LIGHTMAPD_REQUIRE_SERVICES=1`) without it; the second uses a local
//! directory, since only the queue matters there.
//!
//! Time on the development machine (2 cores, no GPU, Debian, lavapipe; shared with two
//! other builds): see docs/scaling.md.

use crate::service_common;

use std::collections::HashMap;
use std::time::{Duration, Instant};

use lightmapd::service::model::JobSpec;

use lightmapd::service::queue::{Enqueued, Queue, SceneRecord};
use lightmapd::service::store::{self, Artifacts};
use serde_json::{Value, json};
use service_common::pg::{AUDIT, Children, Db, signal, spawn_pg_worker, wait_exit, worker_pid};
use service_common::{S3, cornell_glb, exr_is_whole, get_json, spawn_serve_env, submit};
use sqlx::Row;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_api_three_workers_survive_two_sigkills() {
    let _cpu = crate::CPU_HEAVY.lock().await;
    let test = "scale_out::one_api_three_workers_survive_two_sigkills";
    let Some(db) = Db::new(test).await else {
        return;
    };
    let Some(s3) = S3::find(test).await else {
        return;
    };
    let store = s3.fresh_url("scale-out");
    let started = Instant::now();
    for sql in AUDIT {
        sqlx::query(*sql).execute(&db.pool).await.unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    // A short lease, so a killed worker's job is back in the queue within 3-4.5 s.
    let lease = "3";
    let (api, url) = spawn_serve_env(
        dir.path(),
        0,
        &[
            "--database-url",
            &db.url,
            "--store",
            &store,
            "--lease-seconds",
            lease,
            "--max-queued-per-client",
            "1000",
        ],
        &s3.env,
    );
    let mut procs = Children(vec![api]);
    // Every worker of this test, the first three and the replacements alike.
    let spawn_worker = || spawn_pg_worker(&db.url, &store, &s3.env, lease, &["--snapshot-interval-s", "60"]);
    for _ in 0..3 {
        procs.0.push(spawn_worker());
    }
    let http = reqwest::Client::new();
    let scene = service_common::upload_cornell(&http, &url).await;

    // A long job first in line (priority), then 98 small ones; the second long job is
    // submitted once the first kill is done, so each long job is surely mid-bake (it runs
    // 2.5 s) when its worker is killed, however the workers are scheduled.
    let long_job =
        |seed: u64| json!({"scene": scene, "resolution": 16, "stop": {"seconds": 2.5}, "priority": 5, "seed": seed});
    let mut ids = vec![submit(&http, &url, long_job(0)).await];
    // Submitted meanwhile (98 requests take seconds on a loaded machine: the first long
    // job could end before they do).
    let short = {
        let (http, url, scene) = (http.clone(), url.clone(), scene.clone());
        tokio::spawn(async move {
            let mut ids = Vec::new();
            for i in 2..100u64 {
                let body = json!({"scene": scene, "resolution": 16, "stop": {"steps": 2}, "seed": i});
                ids.push(submit(&http, &url, body).await);
            }
            ids
        })
    };
    let mut short = Some(short);

    // Kill the worker of each long job once it has made progress, and start a replacement.
    let mut killed: HashMap<String, String> = HashMap::new();
    for round in 0..2 {
        if round == 1 {
            if let Some(short) = short.take() {
                ids.extend(short.await.unwrap());
            }
            ids.push(submit(&http, &url, long_job(1)).await);
        }
        let job = ids.last().filter(|_| round == 1).unwrap_or(&ids[0]).clone();
        let t = Instant::now();
        let worker = loop {
            let j = get_json(&http, &format!("{url}/v1/jobs/{job}")).await;
            if j["status"] == "running" && j["progress"]["steps"].as_u64().unwrap_or(0) >= 1 {
                break j["worker"].as_str().unwrap().to_string();
            }
            assert!(t.elapsed() < Duration::from_secs(30), "{job} never ran: {j:#}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        let mut victim = procs
            .by_pid(worker_pid(&worker))
            .unwrap_or_else(|| panic!("{worker} is not one of this test's workers"));
        victim.kill().unwrap(); // SIGKILL
        victim.wait().unwrap();
        killed.insert(job, worker);
        procs.0.push(spawn_worker());
    }

    // Every job ends; none fails.
    let t = Instant::now();
    loop {
        let done = get_json(&http, &format!("{url}/v1/jobs?status=succeeded&limit=1")).await;
        if done["total"] == 100 {
            break;
        }
        let failed = get_json(&http, &format!("{url}/v1/jobs?status=failed&limit=5")).await;
        assert_eq!(failed["total"], 0, "{failed:#}");
        assert!(
            t.elapsed() < Duration::from_secs(90),
            "only {} of 100 succeeded",
            done["total"]
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let drained = started.elapsed();

    // Exactly once, from the audit trail: each job went queued → running → succeeded once,
    // except the two killed ones, which went back to queued by lease expiry first.
    let rows = sqlx::query("SELECT job, old_status, new_status, worker, attempts FROM audit ORDER BY seq")
        .fetch_all(&db.pool)
        .await
        .unwrap();
    let mut trail: HashMap<String, Vec<(String, String, String, i32)>> = HashMap::new();
    for r in &rows {
        trail.entry(r.get("job")).or_default().push((
            r.get("old_status"),
            r.get("new_status"),
            r.get::<Option<String>, _>("worker").unwrap_or_default(),
            r.get("attempts"),
        ));
    }
    assert_eq!(trail.len(), 100);
    for id in &ids {
        let t = &trail[id];
        let steps: Vec<(&str, &str)> = t.iter().map(|(a, b, _, _)| (a.as_str(), b.as_str())).collect();
        let succeeded = t.iter().filter(|s| s.1 == "succeeded").count();
        assert_eq!(succeeded, 1, "{id} succeeded {succeeded} times: {t:?}");
        match killed.get(id) {
            None => {
                assert_eq!(steps, [("queued", "running"), ("running", "succeeded")], "{id}: {t:?}");
                assert_eq!(t[1].3, 1, "{id}: first attempt");
            }
            Some(victim) => {
                assert_eq!(
                    steps,
                    [
                        ("queued", "running"),
                        ("running", "queued"),
                        ("queued", "running"),
                        ("running", "succeeded")
                    ],
                    "{id}: {t:?}"
                );
                assert_eq!(&t[0].2, victim);
                assert_ne!(&t[3].2, victim, "finished by another worker");
                assert_eq!(t[3].3, 2, "{id}: the killed attempt counts");
            }
        }
    }

    // Every lightmap downloads whole through the API.
    let mut downloads = Vec::new();
    for id in ids.clone() {
        let (http, url) = (http.clone(), url.clone());
        downloads.push(tokio::spawn(async move {
            let r = http
                .get(format!("{url}/v1/jobs/{id}/lightmap.exr"))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200, "{id}");
            let b = r.bytes().await.unwrap();
            exr_is_whole(&b).unwrap_or_else(|e| panic!("{id}: {e}"));
        }));
    }
    for d in downloads {
        d.await.unwrap();
    }

    // Every process still running stops cleanly.
    for c in &procs.0 {
        signal(c, "-TERM");
    }
    for c in &mut procs.0 {
        assert!(wait_exit(c, Duration::from_secs(20)).success());
    }
    procs.0.clear();
    eprintln!(
        "scale_out: 100 jobs, 2 SIGKILLs, drained in {:.1} s; whole test {:.1} s",
        drained.as_secs_f64(),
        started.elapsed().as_secs_f64()
    );
    db.drop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worker_sigterm_hands_the_job_back() {
    let _cpu = crate::CPU_HEAVY.lock().await;
    let Some(db) = Db::new("scale_out::worker_sigterm_hands_the_job_back").await else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("objects");
    // The job is put in place the way the API would: the scene's file in the store, its
    // row and a queued job in the database.
    let artifacts = Artifacts::local(&store).unwrap();
    artifacts
        .put(&store::scene_file("s", "scene.glb"), cornell_glb().into())
        .await
        .unwrap();
    let scene = SceneRecord {
        id: "s".into(),
        content_hash: "sha256:test".into(),
        format: "glb".into(),
        main_file: "scene.glb".into(),
        files: vec!["scene.glb".into()],
        size_bytes: 1,
        report: Value::Null,
        created_at: 0,
        client: None,
    };
    assert!(db.queue.insert_scene(&scene).await.unwrap());
    let mut procs = Children(vec![spawn_pg_worker(
        &db.url,
        store.to_str().unwrap(),
        &[],
        "30",
        &["--snapshot-interval-s", "60"],
    )]);
    let spec = JobSpec::parse(br#"{"scene": "s", "resolution": 16, "stop": {"seconds": 30}}"#).unwrap();
    let queued = db.queue.enqueue("j", &spec, "test", 10, 0, 1).await.unwrap();
    assert!(matches!(queued, Enqueued::Queued(_)));

    let t = Instant::now();
    let job = loop {
        let j = db.queue.job("j").await.unwrap().unwrap();
        if j.progress.as_ref().and_then(|p| p["steps"].as_u64()).unwrap_or(0) >= 1 {
            break j;
        }
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "the worker never ran the job: {j:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(job.attempts, 1);
    let worker = &mut procs.0[0];
    assert_eq!(worker_pid(job.worker.as_deref().unwrap()), worker.id());
    let term = Instant::now();
    signal(worker, "-TERM");
    // Within a step (milliseconds at 16²), far from the bake's 30 s or the lease's 30 s.
    assert!(wait_exit(worker, Duration::from_secs(10)).success(), "SIGTERM exits 0");
    let stopped = term.elapsed();
    procs.0.clear();
    let j = db.queue.job("j").await.unwrap().unwrap();
    assert_eq!(j.status, lightmapd::service::model::JobStatus::Queued, "{j:?}");
    assert_eq!((j.attempts, j.worker, j.lease_expires_at), (0, None, None));
    eprintln!("worker stopped {:.2} s after SIGTERM", stopped.as_secs_f64());
    db.drop().await;
}
