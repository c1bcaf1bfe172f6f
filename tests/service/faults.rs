//! Fault injection (issue 12, item 5): whatever breaks, every job ends `succeeded` with a
//! whole lightmap, `failed` with a reason, or `queued` again; none is lost and none is
//! marked succeeded without its EXR.
//!
//! - SIGKILL loop: a `lightmapd serve` (API and a worker) and a `lightmapd worker` bake
//!   tiny jobs (two more each round) while one of the two is killed at a random moment,
//!   24 times (a fixed seed,
//!   so a failure replays); then a fresh server drains the queue and every job and every
//!   stored EXR is checked (decoded whole).
//! - A full disk: an artifact store whose writes under `jobs/` fail ("no space left on
//!   device", injected by a wrapper: a real tmpfs needs root) fails the job with that
//!   reason and no lightmap; once writes work again a job succeeds.
//! - A dropped database: a queue wrapper that answers every call with a connection error
//!   for longer than a lease, while a bake runs and finishes: the API answers 500
//!   problem+json meanwhile, and afterwards every job ends.
//! - Leases (issue 24): a final upload five leases long keeps the lease (one attempt);
//!   a worker whose database is gone exits after `--database-timeout-s`; and the job of a
//!   SIGKILLed `lightmapd worker` is queued again within 10 s with the default lease
//!   (the time is printed: docs/reliability.md).
//!
//! Bakes are the `path` technique on the bundled Cornell box at 16² texels for a few
//! tenths of a second, so the whole file runs in well under a minute.

use crate::service_common;

use std::process::Child;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use futures_util::stream::BoxStream;
use lightmapd::engine::rng::Rng;
use lightmapd::service::model::{JobSpec, JobStatus};
use lightmapd::service::queue::sqlite::SqliteQueue;
use lightmapd::service::queue::{
    Cancellation, Capabilities, Enqueued, JobDeletion, JobRecord, JobUpdate, Lease, Outcome, Queue, QueueResult,
    Recovered, SceneDeletion, SceneRecord, TaskBeat, TaskOutcome, TaskRecord, TokenRecord, WorkerRecord,
};
use lightmapd::service::store::Artifacts;
use object_store::local::LocalFileSystem;
use object_store::path::Path as StorePath;
use object_store::{
    CopyOptions, GetOptions, GetResult, ListResult, MultipartUpload, ObjectMeta, ObjectStore, PutMultipartOptions,
    PutOptions, PutPayload, PutResult,
};
use serde_json::{Value, json};
use service_common::*;

/// Fetches JSON from a plain thread's own small runtime (the process test has none).
fn get_json(rt: &tokio::runtime::Runtime, url: &str) -> Value {
    rt.block_on(async { reqwest::get(url).await.unwrap().json().await.unwrap() })
}

/// Checks the end state of every job of a drained server: what the module doc promises.
async fn check_every_job(http: &reqwest::Client, url: &str, submitted: &[String]) -> (usize, usize) {
    let list: Value = http
        .get(format!("{url}/v1/jobs?limit=500"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["total"], submitted.len(), "none lost, none extra");
    let (mut succeeded, mut failed) = (0, 0);
    for j in list["jobs"].as_array().unwrap() {
        let id = j["id"].as_str().unwrap();
        assert!(submitted.iter().any(|s| s == id), "unknown job {id}");
        match j["status"].as_str().unwrap() {
            "succeeded" => {
                let r = http
                    .get(format!("{url}/v1/jobs/{id}/lightmap.exr"))
                    .send()
                    .await
                    .unwrap();
                assert_eq!(r.status(), 200, "succeeded job {id} has no lightmap: {j:#}");
                let bytes = r.bytes().await.unwrap();
                exr_is_whole(&bytes).unwrap_or_else(|e| panic!("job {id}'s lightmap is not whole: {e}"));
                assert!(j["summary"].is_object(), "{j:#}");
                succeeded += 1;
            }
            "failed" => {
                let reason = j["failure"].as_str().unwrap_or("");
                assert!(!reason.is_empty(), "failed without a reason: {j:#}");
                eprintln!("job {id} failed: {reason}");
                failed += 1;
            }
            other => panic!("job {id} is still {other} after the queue drained: {j:#}"),
        }
    }
    (succeeded, failed)
}

#[test]
fn sigkill_at_random_points_loses_no_job() {
    const KILLS: usize = 24;
    let dir = tempfile::tempdir().unwrap();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let http = reqwest::Client::new();
    let fast = ["--lease-seconds", "0.5", "--snapshot-interval-s", "0.1"];
    let (mut serve, mut url) = spawn_serve(dir.path(), 1, &fast);
    let mut worker: Child = spawn_worker(dir.path(), &fast);
    let scene = rt.block_on(service_common::upload_cornell(&http, &url));
    let mut rng = Rng::new(12, 0, 0, 0);
    let mut submitted = Vec::new();
    let (mut serve_kills, mut worker_kills) = (0, 0);
    for kill in 0..KILLS {
        // Two new jobs each round keep both workers busy, so kills land on claims,
        // bakes, snapshot and final writes, and finishes alike.
        for n in 0..2 {
            let body = json!({"scene": scene, "resolution": 16, "stop": {"seconds": 0.3}, "seed": 2 * kill + n});
            let id = rt.block_on(async {
                let r = http.post(format!("{url}/v1/jobs")).json(&body).send().await.unwrap();
                assert_eq!(r.status(), 202);
                r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
            });
            submitted.push(id);
        }
        std::thread::sleep(Duration::from_millis(50 + u64::from(rng.next_u32() % 550)));
        if rng.next_u32().is_multiple_of(2) {
            serve.kill().unwrap(); // SIGKILL
            serve.wait().unwrap();
            serve_kills += 1;
            (serve, url) = spawn_serve(dir.path(), 1, &fast);
        } else {
            worker.kill().unwrap();
            worker.wait().unwrap();
            worker_kills += 1;
            worker = spawn_worker(dir.path(), &fast);
        }
    }
    eprintln!("{serve_kills} server kills, {worker_kills} worker kills");
    assert_eq!(serve_kills + worker_kills, KILLS);
    // Drain with the last server and worker alive.
    let start = Instant::now();
    loop {
        let queued = get_json(&rt, &format!("{url}/v1/jobs?status=queued"))["total"].clone();
        let running = get_json(&rt, &format!("{url}/v1/jobs?status=running"))["total"].clone();
        if queued == 0 && running == 0 {
            break;
        }
        assert!(
            start.elapsed() < DEADLINE,
            "the queue never drained: {queued} queued, {running} running"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let (succeeded, failed) = rt.block_on(check_every_job(&http, &url, &submitted));
    let list = get_json(&rt, &format!("{url}/v1/jobs?limit=500"));
    let retried = list["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|j| j["attempts"].as_u64().unwrap_or(0) >= 2)
        .count();
    eprintln!(
        "{} jobs: {succeeded} succeeded, {failed} failed, {retried} taken up again after a kill",
        submitted.len()
    );
    assert!(retried > 0, "no kill landed on a running bake: the test tested nothing");
    assert!(succeeded > 0);
    // Every final EXR in the store is whole, and only succeeded jobs have one.
    let jobs_dir = store_dir(dir.path()).join("jobs");
    for entry in std::fs::read_dir(&jobs_dir).unwrap() {
        let path = entry.unwrap().path().join("lightmap-0.exr");
        if let Ok(bytes) = std::fs::read(&path) {
            exr_is_whole(&bytes).unwrap_or_else(|e| panic!("{} is not whole: {e}", path.display()));
        }
    }
    for mut child in [serve, worker] {
        child.kill().unwrap();
        child.wait().unwrap();
    }
}

/// An artifact store whose writes under `jobs/` fail while `full` is set.
#[derive(Debug)]
struct FullDisk {
    inner: LocalFileSystem,
    full: Arc<AtomicBool>,
    /// How long each write of a final `lightmap-0.exr` takes (a slow link to the store).
    slow_final: Duration,
}

impl std::fmt::Display for FullDisk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "FullDisk({})", self.inner)
    }
}

#[async_trait]
impl ObjectStore for FullDisk {
    async fn put_opts(
        &self,
        location: &StorePath,
        payload: PutPayload,
        opts: PutOptions,
    ) -> object_store::Result<PutResult> {
        if self.full.load(Ordering::SeqCst) && location.as_ref().starts_with("jobs/") {
            return Err(object_store::Error::Generic {
                store: "FullDisk",
                source: Box::new(std::io::Error::new(
                    std::io::ErrorKind::StorageFull,
                    "No space left on device (injected)",
                )),
            });
        }
        if location.as_ref().ends_with("/lightmap-0.exr") {
            tokio::time::sleep(self.slow_final).await;
        }
        self.inner.put_opts(location, payload, opts).await
    }

    async fn put_multipart_opts(
        &self,
        location: &StorePath,
        opts: PutMultipartOptions,
    ) -> object_store::Result<Box<dyn MultipartUpload>> {
        self.inner.put_multipart_opts(location, opts).await
    }

    async fn get_opts(&self, location: &StorePath, options: GetOptions) -> object_store::Result<GetResult> {
        self.inner.get_opts(location, options).await
    }

    fn delete_stream(
        &self,
        locations: BoxStream<'static, object_store::Result<StorePath>>,
    ) -> BoxStream<'static, object_store::Result<StorePath>> {
        self.inner.delete_stream(locations)
    }

    fn list(&self, prefix: Option<&StorePath>) -> BoxStream<'static, object_store::Result<ObjectMeta>> {
        self.inner.list(prefix)
    }

    async fn list_with_delimiter(&self, prefix: Option<&StorePath>) -> object_store::Result<ListResult> {
        self.inner.list_with_delimiter(prefix).await
    }

    async fn copy_opts(&self, from: &StorePath, to: &StorePath, options: CopyOptions) -> object_store::Result<()> {
        self.inner.copy_opts(from, to, options).await
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_artifact_disk_fails_the_job_with_its_reason_and_no_lightmap() {
    let dir = tempfile::tempdir().unwrap();
    let config = test_config(dir.path(), 1);
    let queue: Arc<dyn Queue> = Arc::new(SqliteQueue::open(&dir.path().join("lightmapd.db")).await.unwrap());
    let full = Arc::new(AtomicBool::new(true));
    std::fs::create_dir_all(dir.path().join("objects")).unwrap();
    let store = FullDisk {
        inner: LocalFileSystem::new_with_prefix(dir.path().join("objects")).unwrap(),
        full: full.clone(),
        slow_final: Duration::ZERO,
    };
    let running = lightmapd::service::start_with(config, queue, Artifacts::from_store(Arc::new(store)))
        .await
        .unwrap();
    let s = Server::wrap(running);
    let scene = s.upload(None).await;
    let body = json!({"scene": scene, "resolution": 16, "stop": {"steps": 8}});

    let id = s.submit(None, body.clone()).await;
    let j = s.wait_end(&id).await;
    assert_eq!(j["status"], "failed", "{j:#}");
    assert_eq!(
        j["failure"],
        "cannot store the lightmap: Generic FullDisk error: No space left on device (injected)"
    );
    assert_eq!(j["snapshots"], 0, "no snapshot could be stored either");
    expect_problem(
        s.get(&format!("/v1/jobs/{id}/lightmap.exr")),
        409,
        problem(
            409,
            "Conflict",
            "conflict",
            &format!("job {id} is failed and has no final lightmap"),
            None,
        ),
    )
    .await;
    assert!(!dir.path().join(format!("objects/jobs/{id}/lightmap-0.exr")).exists());

    // Space again: the same job body succeeds, with a whole lightmap.
    full.store(false, Ordering::SeqCst);
    let id = s.submit(None, body).await;
    let j = s.wait_end(&id).await;
    assert_eq!(j["status"], "succeeded", "{j:#}");
    let exr = s.get(&format!("/v1/jobs/{id}/lightmap.exr")).send().await.unwrap();
    exr_is_whole(&exr.bytes().await.unwrap()).unwrap();
    s.running.shutdown().await;
}

/// A queue whose every call fails with a dropped connection while `down` is set.
struct DroppedDb {
    inner: SqliteQueue,
    down: Arc<AtomicBool>,
}

impl DroppedDb {
    fn check(&self) -> QueueResult<()> {
        if self.down.load(Ordering::SeqCst) {
            Err(sqlx::Error::Io(std::io::Error::new(
                std::io::ErrorKind::ConnectionReset,
                "connection dropped (injected)",
            )))
        } else {
            Ok(())
        }
    }
}

#[async_trait]
impl Queue for DroppedDb {
    async fn insert_scene(&self, scene: &SceneRecord) -> QueueResult<bool> {
        self.check()?;
        self.inner.insert_scene(scene).await
    }
    async fn scene(&self, id: &str) -> QueueResult<Option<SceneRecord>> {
        self.check()?;
        self.inner.scene(id).await
    }
    async fn scenes(&self, client: Option<&str>) -> QueueResult<Vec<SceneRecord>> {
        self.check()?;
        self.inner.scenes(client).await
    }
    async fn delete_scene(&self, id: &str) -> QueueResult<SceneDeletion> {
        self.check()?;
        self.inner.delete_scene(id).await
    }
    async fn enqueue(
        &self,
        id: &str,
        spec: &JobSpec,
        client: &str,
        max: u64,
        memory: u64,
        now: i64,
    ) -> QueueResult<Enqueued> {
        self.check()?;
        self.inner.enqueue(id, spec, client, max, memory, now).await
    }
    async fn job(&self, id: &str) -> QueueResult<Option<JobRecord>> {
        self.check()?;
        self.inner.job(id).await
    }
    async fn list(
        &self,
        status: Option<JobStatus>,
        client: Option<&str>,
        limit: u32,
        offset: u64,
    ) -> QueueResult<(Vec<JobRecord>, u64)> {
        self.check()?;
        self.inner.list(status, client, limit, offset).await
    }
    async fn counts(&self) -> QueueResult<Vec<(JobStatus, u64)>> {
        self.check()?;
        self.inner.counts().await
    }
    async fn cancel(&self, id: &str, now: i64) -> QueueResult<Cancellation> {
        self.check()?;
        self.inner.cancel(id, now).await
    }
    async fn claim(
        &self,
        worker: &str,
        caps: &Capabilities,
        lease: Duration,
        now: i64,
    ) -> QueueResult<Option<JobRecord>> {
        self.check()?;
        self.inner.claim(worker, caps, lease, now).await
    }
    async fn claim_task(
        &self,
        worker: &str,
        caps: &Capabilities,
        lease: Duration,
        now: i64,
    ) -> QueueResult<Option<(TaskRecord, JobRecord)>> {
        self.check()?;
        self.inner.claim_task(worker, caps, lease, now).await
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
        self.check()?;
        self.inner.task_heartbeat(job, index, worker, lease, beat, now).await
    }
    async fn claim_task_snapshot(
        &self,
        job: &str,
        index: u32,
        worker: &str,
        interval: Duration,
        now: i64,
    ) -> QueueResult<Option<u32>> {
        self.check()?;
        self.inner.claim_task_snapshot(job, index, worker, interval, now).await
    }
    async fn task_snapshot_stored(&self, job: &str, n: u32, point: &serde_json::Value) -> QueueResult<bool> {
        self.check()?;
        self.inner.task_snapshot_stored(job, n, point).await
    }
    async fn release_task_snapshot(&self, job: &str, n: u32) -> QueueResult<()> {
        self.check()?;
        self.inner.release_task_snapshot(job, n).await
    }
    async fn finish_task(&self, job: &str, index: u32, worker: &str, o: &TaskOutcome, now: i64) -> QueueResult<bool> {
        self.check()?;
        self.inner.finish_task(job, index, worker, o, now).await
    }
    async fn release_task(&self, job: &str, index: u32, worker: &str, now: i64) -> QueueResult<bool> {
        self.check()?;
        self.inner.release_task(job, index, worker, now).await
    }
    async fn tasks(&self, job: &str) -> QueueResult<Vec<TaskRecord>> {
        self.check()?;
        self.inner.tasks(job).await
    }
    async fn task_failures(&self, job: &str) -> QueueResult<Vec<(String, u32)>> {
        self.check()?;
        self.inner.task_failures(job).await
    }
    async fn register_worker(&self, worker: &str, caps: &Capabilities, now: i64) -> QueueResult<()> {
        self.check()?;
        self.inner.register_worker(worker, caps, now).await
    }
    async fn workers(&self, since: i64) -> QueueResult<Vec<WorkerRecord>> {
        self.check()?;
        self.inner.workers(since).await
    }
    async fn forget_workers(&self, before: i64) -> QueueResult<u64> {
        self.check()?;
        self.inner.forget_workers(before).await
    }
    async fn heartbeat(&self, id: &str, w: &str, lease: Duration, u: &JobUpdate, now: i64) -> QueueResult<Lease> {
        self.check()?;
        self.inner.heartbeat(id, w, lease, u, now).await
    }
    async fn finish(&self, id: &str, worker: &str, outcome: &Outcome, now: i64) -> QueueResult<bool> {
        self.check()?;
        self.inner.finish(id, worker, outcome, now).await
    }
    async fn release(&self, id: &str, worker: &str, now: i64) -> QueueResult<bool> {
        self.check()?;
        self.inner.release(id, worker, now).await
    }
    async fn recover_expired(&self, now: i64) -> QueueResult<Recovered> {
        self.check()?;
        self.inner.recover_expired(now).await
    }
    async fn insert_token(&self, token: &TokenRecord) -> QueueResult<()> {
        self.check()?;
        self.inner.insert_token(token).await
    }
    async fn tokens(&self) -> QueueResult<Vec<TokenRecord>> {
        self.check()?;
        self.inner.tokens().await
    }
    async fn revoke_token(&self, id_or_name: &str, now: i64) -> QueueResult<bool> {
        self.check()?;
        self.inner.revoke_token(id_or_name, now).await
    }
    async fn token_by_hash(&self, hash: &str) -> QueueResult<Option<TokenRecord>> {
        self.check()?;
        self.inner.token_by_hash(hash).await
    }
    async fn clock(&self) -> QueueResult<i64> {
        self.check()?;
        self.inner.clock().await
    }
    async fn delete_job(&self, id: &str) -> QueueResult<JobDeletion> {
        self.check()?;
        self.inner.delete_job(id).await
    }
    async fn finished_before(&self, before: i64, limit: u32) -> QueueResult<Vec<String>> {
        self.check()?;
        self.inner.finished_before(before, limit).await
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_database_connection_loses_no_job() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 1);
    config.lease = Duration::from_millis(600);
    let down = Arc::new(AtomicBool::new(false));
    let queue = DroppedDb {
        inner: SqliteQueue::open(&dir.path().join("lightmapd.db")).await.unwrap(),
        down: down.clone(),
    };
    let artifacts = Artifacts::local(&dir.path().join("objects")).unwrap();
    let running = lightmapd::service::start_with(config, Arc::new(queue), artifacts)
        .await
        .unwrap();
    let s = Server::wrap(running);
    let scene = s.upload(None).await;
    let mut ids = Vec::new();
    for seed in 0..3 {
        let body = json!({"scene": scene, "resolution": 16, "stop": {"seconds": 0.5}, "seed": seed});
        ids.push(s.submit(None, body).await);
    }
    // The first bake is under way when the connection drops, and ends during the outage
    // (its end cannot be recorded), and its lease lapses meanwhile.
    let start = Instant::now();
    loop {
        let j: Value = s
            .get(&format!("/v1/jobs/{}", ids[0]))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if j["status"] == "running" && j["progress"]["steps"].as_u64().unwrap_or(0) >= 1 {
            break;
        }
        assert!(start.elapsed() < DEADLINE, "never ran: {j:#}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    down.store(true, Ordering::SeqCst);
    let database_down = |what: &str| {
        problem(
            500,
            "Internal Server Error",
            "internal",
            &format!("database: error communicating with database: connection dropped (injected){what}"),
            None,
        )
    };
    expect_problem(s.get("/healthz"), 500, database_down("")).await;
    expect_problem(
        s.post("/v1/jobs").json(&json!({"scene": scene, "resolution": 16})),
        500,
        database_down(""),
    )
    .await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    down.store(false, Ordering::SeqCst);

    for id in &ids {
        s.wait_end(id).await;
    }
    let (succeeded, failed) = check_every_job(&s.http, &s.url, &ids).await;
    assert_eq!((succeeded, failed), (3, 0), "a lost connection is not the job's fault");
    let first: Value = s
        .get(&format!("/v1/jobs/{}", ids[0]))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        first["attempts"], 2,
        "the bake that ended during the outage ran again once its lease lapsed: {first:#}"
    );
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_lease_is_renewed_while_a_slow_final_upload_runs() {
    // Storing the final EXR takes five leases: before issue 24 the heartbeat stopped with
    // the bake, the lease lapsed during the upload, and the job ran again (three times,
    // then failed). Now it is renewed until the end is recorded: one attempt.
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 1);
    config.lease = Duration::from_millis(300);
    let queue: Arc<dyn Queue> = Arc::new(SqliteQueue::open(&dir.path().join("lightmapd.db")).await.unwrap());
    std::fs::create_dir_all(dir.path().join("objects")).unwrap();
    let store = FullDisk {
        inner: LocalFileSystem::new_with_prefix(dir.path().join("objects")).unwrap(),
        full: Arc::new(AtomicBool::new(false)),
        slow_final: Duration::from_millis(1500),
    };
    let running = lightmapd::service::start_with(config, queue, Artifacts::from_store(Arc::new(store)))
        .await
        .unwrap();
    let s = Server::wrap(running);
    let scene = s.upload(None).await;
    let id = s
        .submit(None, json!({"scene": scene, "resolution": 16, "stop": {"steps": 4}}))
        .await;
    let j = s.wait_end(&id).await;
    assert_eq!(
        (j["status"].as_str(), j["attempts"].as_u64()),
        (Some("succeeded"), Some(1)),
        "{j:#}"
    );
    let exr = s.get(&format!("/v1/jobs/{id}/lightmap.exr")).send().await.unwrap();
    exr_is_whole(&exr.bytes().await.unwrap()).unwrap();
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_without_its_database_exits_after_the_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 1);
    config.database_timeout = Duration::from_millis(800);
    let queue = DroppedDb {
        inner: SqliteQueue::open(&dir.path().join("lightmapd.db")).await.unwrap(),
        down: Arc::new(AtomicBool::new(true)),
    };
    let artifacts = Artifacts::local(&dir.path().join("objects")).unwrap();
    let start = Instant::now();
    let r = lightmapd::service::run_workers_with(config, Arc::new(queue), artifacts, std::future::pending()).await;
    let took = start.elapsed();
    let e = r.expect_err("the worker gives up");
    assert_eq!(
        e.to_string(),
        "the database has not answered for 0.8 s (--database-timeout-s): error communicating with database: connection dropped (injected)"
    );
    // Checked every timeout/4: it gives up at the timeout, then waits for its workers to
    // stop (a worker whose claim failed sleeps 1 s before it looks again).
    assert!(
        took >= Duration::from_millis(800) && took < Duration::from_secs(5),
        "{took:?}"
    );
}

#[test]
fn a_killed_workers_job_is_queued_again_within_ten_seconds_by_default() {
    // Default lease (5 s) and recovery period (1 s): the API process (no workers of its
    // own) finds the lapsed lease of the SIGKILLed worker's job and queues it again.
    let dir = tempfile::tempdir().unwrap();
    let (mut api, url) = spawn_serve(dir.path(), 0, &[]);
    let mut worker = spawn_worker(dir.path(), &["--snapshot-interval-s", "0.5"]);
    let rt = tokio::runtime::Runtime::new().unwrap();
    let http = reqwest::Client::new();
    let requeued = rt.block_on(async {
        let up = http
            .post(format!("{url}/v1/scenes"))
            .body(cornell_glb())
            .send()
            .await
            .unwrap();
        let scene = up.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
        let r = http
            .post(format!("{url}/v1/jobs"))
            .json(&json!({"scene": scene, "resolution": 16, "stop": {"seconds": 60}}))
            .send()
            .await
            .unwrap();
        let id = r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
        let job = |id: String| {
            let http = http.clone();
            let url = url.clone();
            async move {
                http.get(format!("{url}/v1/jobs/{id}"))
                    .send()
                    .await
                    .unwrap()
                    .json::<Value>()
                    .await
                    .unwrap()
            }
        };
        let start = Instant::now();
        loop {
            let j = job(id.clone()).await;
            if j["status"] == "running" && j["progress"]["steps"].as_u64().unwrap_or(0) >= 1 {
                break;
            }
            assert!(start.elapsed() < DEADLINE, "never ran: {j:#}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        worker.kill().unwrap(); // SIGKILL
        let killed = Instant::now();
        let _ = worker.wait();
        loop {
            let j = job(id.clone()).await;
            if j["status"] == "queued" {
                return killed.elapsed();
            }
            assert_eq!(j["status"], "running", "{j:#}");
            assert!(killed.elapsed() < Duration::from_secs(20), "still running: {j:#}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    api.kill().unwrap();
    let _ = api.wait();
    eprintln!("requeued {:.2} s after SIGKILL of the worker", requeued.as_secs_f64());
    assert!(requeued < Duration::from_secs(10), "{requeued:?}");
    // Not before the lease could have lapsed: the last renewal was at most 0.25 s before
    // the kill.
    assert!(requeued > Duration::from_millis(4500), "{requeued:?}");
}
