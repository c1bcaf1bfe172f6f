//! One job baked as tasks by several worker processes (issue 25, point 5), with the real
//! parts: one API process (`serve --workers 0`) and three `worker` processes on one
//! PostgreSQL schema and one S3-protocol store (moto, as `scale_out` uses).
//!
//! `three_workers_bake_one_job_and_survive_a_sigkill`: a `path` job of 1200 steps on a
//! scene of two lightmap pages (the sphere over a plane, the ground's authored page and
//! the ball's generated one, 64² each) split into 6 tasks: 2 regions (one page each) of
//! 3 step ranges (400 steps each: sample batches keyed by the job's step numbers and the
//! texels' pixels). Once a task has run for half a second, its worker is killed with
//! SIGKILL. Checks:
//! - the job succeeds; the killed task was taken up again by another worker after its
//!   lease lapsed (2 attempts), every other task at its first, and the dead worker's
//!   abandoned attempt is counted against it (`task_failures`);
//! - both merged pages, downloaded through the API, equal the pages of a single-process
//!   bake of the same job (same request, same seed) to 1e-6: the merge is exact, not
//!   "another bake within noise";
//! - the merged error estimate (from the merged halves) matches its true error, measured
//!   against a 6000-step bake of another seed, within [0.6, 1.5];
//! - the job's history ran while the tasks baked (at least one point of their merged
//!   progress before the merge's, steps rising, the error falling to the merge's);
//! - the task results are deleted from the store once the lightmap is stored;
//! - then a `path` job on the Cornell box's one page split into 3 tiles (bands of rows,
//!   `tasks: 3, regions: 3`) on the two surviving workers: its lightmap equals the
//!   single-process bake's to 1e-6;
//! - then a `path` job on the Cornell box's page split into 2 bands of rows: snapshots
//!   are stored while its tasks run, each the tasks' halves so far merged
//!   (`tasks::merge_running`) on the whole texel set (`tasks::running_atlas`); the latest
//!   taken while the job runs differs from the final lightmap by less than three times
//!   the error it states, the job's history holds its point with that error, and the
//!   tasks' running halves are deleted with their results;
//! - then a `vpl` job on the two pages split into 2 independent chains (each with its
//!   own seed, shown as the task's `chain_seed`): its lightmap is within three times the
//!   stated errors of the single-process bake's, its error carries the bias measured
//!   at the chains' merged control texels, and it stored snapshots while it ran;
//! - then a `hemicube` job on the Cornell box's page as 2 bands of rows in 3 rounds
//!   (`regions: 2, rounds: 3`): round r's tasks wait for round r-1's and read their
//!   results from the store, the merge reads the last round's, and only the last
//!   round's tasks state an error; the round before is shown as a snapshot stating no
//!   error; its lightmap equals the
//!   one-process bake in rounds' (`rounds::bake_in_rounds`), its stated error is within
//!   25 % of that bake's (the control texels' reference is timed), and every
//!   round's results are deleted after the merge;
//! - the surviving processes exit 0 on SIGTERM.
//!
//! `cancelling_a_split_job_stops_its_tasks_within_seconds`: one worker process bakes a
//! split job long enough that only a cancel ends it; `POST /cancel` while a task runs
//! ends the job `cancelled` within 5 s (the running task reads the flag at its next
//! heartbeat, at most a third of the 3 s lease, and stops within a step), the task
//! `cancelled` and the queued ones with it.
//!
//! `a_job_no_worker_can_run_says_what_it_waits_for`: with one worker whose per-job memory
//! limit is 1 MiB, a job that requires a hardware GPU (this machine has lavapipe at most)
//! and a job bigger than 1 MiB both stay queued, and each one's status names what it
//! waits for and what the live worker has; both cancel at once.
//!
//! Skips (fails under `LIGHTMAPD_REQUIRE_SERVICES=1`) without PostgreSQL or the S3 server.

use crate::service_common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use lightmapd::engine::bake::BakeEvent;
use lightmapd::engine::job::{self, BakeOptions};
use lightmapd::engine::reference::{ReferenceLightmap, relative_error};
use lightmapd::engine::scene;
use lightmapd::engine::scene::build::{remove_lightmap_uvs, write_glb};
use lightmapd::engine::scene::library::sphere_over_plane;
use lightmapd::service::model::JobSpec;
use lightmapd::service::store;
use serde_json::{Value, json};
use service_common::pg::{Children, Db, signal, spawn_pg_worker, wait_exit, worker_pid};
use service_common::{S3, cornell_glb, get_json, spawn_serve_env, submit};
use sqlx::Row;

/// One API process and `workers` worker processes on a fresh schema and store prefix.
struct Farm {
    db: Db,
    s3: S3,
    store: String,
    url: String,
    procs: Children,
    _dir: tempfile::TempDir,
}

const LEASE: &str = "3";

impl Farm {
    async fn start(test: &str, workers: usize) -> Option<Farm> {
        let db = Db::new(test).await?;
        let s3 = S3::find(test).await?;
        let store = s3.fresh_url("farm");
        let dir = tempfile::tempdir().unwrap();
        let (api, url) = spawn_serve_env(
            dir.path(),
            0,
            &["--database-url", &db.url, "--store", &store, "--lease-seconds", LEASE],
            &s3.env,
        );
        let mut procs = Children(vec![api]);
        for _ in 0..workers {
            procs.0.push(spawn_pg_worker(&db.url, &store, &s3.env, LEASE, &[]));
        }
        Some(Farm {
            db,
            s3,
            store,
            url,
            procs,
            _dir: dir,
        })
    }

    async fn upload(&self, http: &reqwest::Client) -> String {
        self.upload_glb(http, cornell_glb()).await
    }

    async fn upload_glb(&self, http: &reqwest::Client, glb: Vec<u8>) -> String {
        let r = http
            .post(format!("{}/v1/scenes", self.url))
            .header("content-type", "model/gltf-binary")
            .body(glb)
            .send()
            .await
            .unwrap();
        assert!(r.status().is_success());
        r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
    }

    async fn stop(mut self) {
        for c in &self.procs.0 {
            signal(c, "-TERM");
        }
        for c in &mut self.procs.0 {
            assert!(wait_exit(c, Duration::from_secs(20)).success());
        }
        self.procs.0.clear();
        self.db.drop().await;
    }
}

/// A bake's lightmap as delivered (its stored pages: seams stitched, gutters dilated),
/// read back per texel of its atlas.
fn delivered(r: &job::BakeResult) -> Vec<glam::Vec3> {
    ReferenceLightmap::from_pages(&r.pages.iter().map(|p| &p.exr[..]).collect::<Vec<_>>())
        .unwrap()
        .per_texel(&r.atlas)
        .unwrap()
        .into_iter()
        .map(|v| v.unwrap_or_default())
        .collect()
}

/// Polls the job at `url` until it has ended, failing after `limit` with `what`.
async fn until_ended(http: &reqwest::Client, url: &str, limit: Duration, what: &str) -> Value {
    let t = Instant::now();
    loop {
        let j = get_json(http, url).await;
        if j["status"] != "queued" && j["status"] != "running" {
            return j;
        }
        assert!(t.elapsed() < limit, "{what} never ended: {j:#}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Submits `body` to the API at `url` and waits, at most `limit_s` seconds, for the job to
/// succeed: its id, its URL and its final document.
async fn succeeded(
    http: &reqwest::Client,
    url: &str,
    body: Value,
    limit_s: u64,
    what: &str,
) -> (String, String, Value) {
    let id = submit(http, url, body).await;
    let job_url = format!("{url}/v1/jobs/{id}");
    let job = until_ended(http, &job_url, Duration::from_secs(limit_s), what).await;
    assert_eq!(job["status"], "succeeded", "{job:#}");
    (id, job_url, job)
}

/// Waits for `key` to be deleted: a merged job's task results go right *after* the job
/// is marked succeeded (its lightmap is stored first), so a poll that saw the end can
/// still see them for a moment; ten seconds is far beyond that moment.
async fn until_deleted(artifacts: &lightmapd::service::store::Artifacts, key: &object_store::path::Path) {
    let t = Instant::now();
    while artifacts.get(key).await.unwrap().is_some() {
        assert!(t.elapsed() < Duration::from_secs(10), "{key} is still stored");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_workers_bake_one_job_and_survive_a_sigkill() {
    let _cpu = crate::CPU_HEAVY.lock().await;
    let test = "farm::three_workers_bake_one_job_and_survive_a_sigkill";
    let Some(mut farm) = Farm::start(test, 3).await else {
        return;
    };
    let started = Instant::now();
    let http = reqwest::Client::new();
    // Two pages: the ground keeps its authored UVs, the ball's are generated.
    let (mut doc, bin) = sphere_over_plane().to_gltf();
    remove_lightmap_uvs(&mut doc, Some(&[1]));
    let glb = write_glb(&doc, &bin);
    let scene = farm.upload_glb(&http, glb.clone()).await;
    let body = json!({
        "scene": scene, "technique": "path", "resolution": 64, "seed": 7,
        "lighting": {"sky": {"radiance": [1, 1, 1]}},
        "stop": {"steps": 1200}, "tasks": 6, "regions": 2, "denoise": "none",
    });
    let id = submit(&http, &farm.url, body.clone()).await;
    let job_url = format!("{}/v1/jobs/{id}", farm.url);

    // Kill the worker of the first task seen mid-bake.
    let t = Instant::now();
    let (victim_task, victim) = loop {
        let j = get_json(&http, &job_url).await;
        let running = j["tasks"]["list"].as_array().and_then(|l| {
            l.iter()
                .find(|t| t["status"] == "running" && t["kind"] == "bake" && t["wall_s"].as_f64().unwrap_or(0.0) >= 0.5)
                .cloned()
        });
        if let Some(task) = running {
            break (
                task["index"].as_u64().unwrap(),
                task["worker"].as_str().unwrap().to_string(),
            );
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no task ever ran: {j:#}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let mut child = farm
        .procs
        .by_pid(worker_pid(&victim))
        .unwrap_or_else(|| panic!("{victim} is not one of this test's workers"));
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let killed_at = started.elapsed();

    let job = until_ended(&http, &job_url, Duration::from_secs(180), "the job").await;
    let drained = started.elapsed();
    assert_eq!(job["status"], "succeeded", "{job:#}");
    let list = job["tasks"]["list"].as_array().unwrap();
    assert_eq!(list.len(), 7, "6 bake tasks and the merge: {job:#}");
    for t in list {
        let k = t["index"].as_u64().unwrap();
        assert_eq!(t["status"], "succeeded", "{t}");
        if k == victim_task {
            assert_eq!(t["attempts"], 2, "the killed task ran again: {t}");
            assert_ne!(
                t["worker"].as_str(),
                Some(victim.as_str()),
                "finished by another worker: {t}"
            );
        } else {
            assert_eq!(t["attempts"], 1, "{t}");
        }
        if k < 6 {
            // Region k / 3 (a page), steps 400 (k % 3) onwards.
            assert_eq!(t["steps"], 400, "{t}");
            assert_eq!(t["region"], k / 3, "{t}");
            assert_eq!(t["step_range"], json!([400 * (k % 3), 400 * (k % 3 + 1)]), "{t}");
        }
    }
    assert_eq!(job["tasks"]["regions"], 2);
    assert_eq!(list[6]["kind"], "merge");
    assert_eq!(job["summary"]["steps"], 1200);
    assert_eq!(job["progress"]["steps"], 1200);
    assert_eq!(job["summary"]["atlas"]["pages"], 2, "{job:#}");
    // One abandoned attempt counts against the dead worker (not yet blocklisted).
    let failures: Vec<(String, i32)> = sqlx::query("SELECT worker, failures FROM task_failures WHERE job_id = $1")
        .bind(&id)
        .fetch_all(&farm.db.pool)
        .await
        .unwrap()
        .iter()
        .map(|r| (r.get("worker"), r.get("failures")))
        .collect();
    assert_eq!(failures, vec![(victim.clone(), 1)]);
    assert_eq!(job["tasks"]["blocklisted"], json!([]));
    // The task results went once the lightmap was stored.
    let artifacts = crate::s3_store::open(&farm.s3, &farm.store).await;
    for k in 0..6 {
        for key in [store::task_partial(&id, k), store::task_live(&id, k)] {
            until_deleted(&artifacts, &key).await;
        }
    }

    // Both merged pages are the single-process bake of the same job.
    let mut pages = Vec::new();
    for p in 0..2 {
        let r = http.get(format!("{job_url}/lightmap-{p}.exr")).send().await.unwrap();
        assert_eq!(r.status(), 200, "page {p}");
        pages.push(r.bytes().await.unwrap());
    }
    let merged = ReferenceLightmap::from_pages(&pages).unwrap();
    let spec = JobSpec::parse(body.to_string().as_bytes()).unwrap();
    let request = spec.to_request();
    let two_pages = Arc::new(scene::import_slice(&glb, None).unwrap().0);
    let bake = |request: &job::BakeRequest| {
        job::bake(
            two_pages.clone(),
            request,
            &BakeOptions::default(),
            &mut |_: BakeEvent<'_>| std::ops::ControlFlow::Continue(()),
            &mut |_| {},
            &mut |_| {},
        )
        .unwrap()
    };
    let single = bake(&request);
    // Delivered against delivered: both pages as stored (seams stitched, gutters dilated).
    let merged_values = merged.per_texel(&single.atlas).unwrap();
    let single_values = delivered(&single);
    let single_vs_merged = relative_error(&single_values, &merged_values);
    assert!(
        single_vs_merged < 1e-6,
        "merged and single bake differ by {single_vs_merged:.2e} (relative RMS)"
    );
    let single_error = single.summary.error.relative.unwrap();
    let merged_error = job["summary"]["error"]["relative"].as_f64().unwrap() as f32;
    // The history ran while the tasks baked (their merged progress), and the merge's
    // point, the delivered lightmap's error, ends it.
    let history = job["history"].as_array().unwrap();
    let steps: Vec<u64> = history.iter().map(|p| p["steps"].as_u64().unwrap()).collect();
    assert!(history.len() >= 2, "a running history: {history:#?}");
    assert!(steps.windows(2).all(|w| w[0] <= w[1]), "{steps:?}");
    assert_eq!(steps.last(), Some(&1200));
    assert_eq!(history.last().unwrap()["error"].as_f64().unwrap() as f32, merged_error);
    let first = history[0]["error"].as_f64().unwrap() as f32;
    assert!(
        first > merged_error,
        "the running error fell: {first} then {merged_error}"
    );
    assert!(
        (merged_error / single_error - 1.0).abs() < 1e-3,
        "merged error estimate {merged_error}, single bake's {single_error}"
    );

    // The merged error estimate against the true error (a 6000-step bake of another seed).
    let mut long = request.clone();
    long.seed = 99;
    long.stop.steps = Some(6000);
    let truth = bake(&long);
    // As delivered too (the seams stitched the same way in both).
    let truth_values = ReferenceLightmap::from_pages(&truth.pages.iter().map(|p| &p.exr[..]).collect::<Vec<_>>())
        .unwrap()
        .per_texel(&truth.atlas)
        .unwrap();
    let true_error = relative_error(&single_values, &truth_values) as f32;
    let ratio = merged_error / true_error;
    assert!(
        (0.6..=1.5).contains(&ratio),
        "merged estimate {merged_error:.4} against true {true_error:.4}: ratio {ratio:.2}"
    );
    eprintln!(
        "farm: 1200 steps of 2 pages as 2 pages x 3 step ranges on 3 workers, one SIGKILL at {:.1} s: done in {:.1} s; merged vs single {single_vs_merged:.1e}; estimate {merged_error:.4}, true {true_error:.4} (ratio {ratio:.2})",
        killed_at.as_secs_f64(),
        drained.as_secs_f64()
    );

    // Tiles: one page cut into three bands of rows, on the two surviving workers.
    let cornell = farm.upload(&http).await;
    let tiles = json!({
        "scene": cornell, "technique": "path", "resolution": 32, "seed": 5,
        "stop": {"steps": 40}, "tasks": 3, "regions": 3, "denoise": "none",
    });
    let (_, tiled_url, job) = succeeded(&http, &farm.url, tiles.clone(), 120, "the tiled job").await;
    let regions: Vec<u64> = job["tasks"]["list"].as_array().unwrap()[..3]
        .iter()
        .map(|t| t["region"].as_u64().unwrap())
        .collect();
    assert_eq!(regions, [0, 1, 2]);
    let r = http.get(format!("{tiled_url}/lightmap.exr")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let merged = ReferenceLightmap::from_pages(&[r.bytes().await.unwrap()]).unwrap();
    let request = JobSpec::parse(tiles.to_string().as_bytes()).unwrap().to_request();
    let box_scene = Arc::new(scene::import_slice(&cornell_glb(), None).unwrap().0);
    let single = job::bake(
        box_scene,
        &request,
        &BakeOptions::default(),
        &mut |_: BakeEvent<'_>| std::ops::ControlFlow::Continue(()),
        &mut |_| {},
        &mut |_| {},
    )
    .unwrap();
    let single_values = delivered(&single);
    let tiles_vs_single = relative_error(&single_values, &merged.per_texel(&single.atlas).unwrap());
    assert!(
        tiles_vs_single < 1e-6,
        "tiled and single bake differ by {tiles_vs_single:.2e} (relative RMS)"
    );
    eprintln!("farm: 40 steps of one page as 3 tiles on 2 workers: merged vs single {tiles_vs_single:.1e}");

    // Snapshots while the tasks run: the page in two bands of rows, 2000 steps each
    // (several seconds here), the snapshots made from the tasks' halves so far on the
    // whole texel set, which the task making them builds from the bands' kept texels.
    let ranges = json!({
        "scene": cornell, "technique": "path", "resolution": 32, "seed": 3,
        "stop": {"steps": 2000}, "tasks": 2, "regions": 2, "denoise": "none",
    });
    let ranged = submit(&http, &farm.url, ranges).await;
    let ranged_url = format!("{}/v1/jobs/{ranged}", farm.url);
    let t = Instant::now();
    let mut running = None;
    let job = loop {
        let j = get_json(&http, &ranged_url).await;
        if j["status"] != "queued" && j["status"] != "running" {
            break j;
        }
        let n = j["snapshots"].as_u64().unwrap();
        if n >= 1 && running.as_ref().is_none_or(|(m, _)| *m < n) {
            let r = http
                .get(format!("{ranged_url}/lightmap.exr?snapshot={n}"))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200, "snapshot {n} of a running job");
            running = Some((n, r.bytes().await.unwrap()));
        }
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "the ranged job never ended: {j:#}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(job["status"], "succeeded", "{job:#}");
    let (n, bytes) = running.expect("a snapshot stored while the tasks ran");
    let snapshot = ReferenceLightmap::from_pages(&[bytes]).unwrap();
    let stated = snapshot.reported_error.expect("the snapshot states its error") as f64;
    let r = http.get(format!("{ranged_url}/lightmap.exr")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let done = ReferenceLightmap::from_pages(&[r.bytes().await.unwrap()]).unwrap();
    let final_error = done.reported_error.unwrap() as f64;
    let finals = done.per_texel(&single.atlas).unwrap();
    let shown: Vec<glam::Vec3> = snapshot
        .per_texel(&single.atlas)
        .unwrap()
        .into_iter()
        .map(|v| v.unwrap_or_default())
        .collect();
    let apart = relative_error(&shown, &finals);
    assert!(
        // The last one may be made after the tasks' final halves (all the steps, the
        // final lightmap itself) or a little before them. It states no less error than
        // the final's, up to the estimate's own noise: the RMS of the halves' difference
        // over the box's ~800 texels varies by some 2.5 % from one step count to the next
        // (√(1/(2·800))), and one run on a loaded machine read just under 0.99 of it, so
        // 0.9 is four of those standard deviations.
        apart <= 3.0 * stated && stated >= 0.9 * final_error,
        "running snapshot {n} differs from the final lightmap by {apart:.4}; it states {stated:.4}, the final {final_error:.4}"
    );
    // The job's history holds that snapshot's point with the error it states, as a
    // single bake's history holds its snapshots' (the merged raw progress only before
    // the first).
    let history = job["history"].as_array().unwrap();
    assert!(
        history
            .iter()
            .any(|p| p["error"].as_f64().map(|e| e as f32) == Some(stated as f32)),
        "no history point states snapshot {n}'s {stated}: {history:#?}"
    );
    for k in 0..2 {
        until_deleted(&artifacts, &store::task_live(&ranged, k)).await;
    }
    eprintln!(
        "farm: 2000 steps as 2 bands of rows: {} snapshots while running; snapshot {n} states {stated:.4}, differs from the final ({final_error:.4}) by {apart:.4}",
        job["snapshots"]
    );

    // Chains: a `vpl` job (a biased technique with control texels) as two independent
    // chains, each with its own seed, on the two workers. Not the single bake's samples:
    // the merged lightmap is compared with it within the errors both state, and the
    // merged error carries the bias measured at the chains' merged control texels.
    let chained = json!({
        "scene": scene, "technique": "vpl", "resolution": 40, "seed": 5,
        "lighting": {"sky": {"radiance": [1, 1, 1]}},
        "stop": {"steps": 8}, "tasks": 2, "denoise": "none",
    });
    let (_, chain_url, job) = succeeded(&http, &farm.url, chained.clone(), 180, "the chained job").await;
    let list = job["tasks"]["list"].as_array().unwrap();
    let chains: Vec<(Value, Value)> = list[..2]
        .iter()
        .map(|t| (t["step_range"].clone(), t["chain_seed"].clone()))
        .collect();
    assert_eq!(
        chains,
        [
            (json!([0, 4]), json!(5)),
            (json!([0, 4]), json!(lightmapd::engine::tasks::chain_seed(5, 1)))
        ]
    );
    let error = &job["summary"]["error"];
    assert!(error["control_texels"].as_u64().unwrap() > 0, "{error:#}");
    // One region: every chain's first halves make a snapshot at once.
    assert!(job["snapshots"].as_u64().unwrap() >= 1, "{job:#}");
    let merged_error = error["relative"].as_f64().unwrap();
    let r = http.get(format!("{chain_url}/lightmap-0.exr")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let mut pages = vec![r.bytes().await.unwrap()];
    let r = http.get(format!("{chain_url}/lightmap-1.exr")).send().await.unwrap();
    pages.push(r.bytes().await.unwrap());
    let merged = ReferenceLightmap::from_pages(&pages).unwrap();
    let single = bake(&JobSpec::parse(chained.to_string().as_bytes()).unwrap().to_request());
    let single_values = delivered(&single);
    let chains_vs_single = relative_error(&single_values, &merged.per_texel(&single.atlas).unwrap());
    let single_error = single.summary.error.relative.unwrap() as f64;
    let stated = (merged_error.powi(2) + single_error.powi(2)).sqrt();
    assert!(
        chains_vs_single > 0.0 && chains_vs_single < 3.0 * stated,
        "chains and single bake differ by {chains_vs_single:.4}, stated {merged_error:.4} and {single_error:.4}"
    );
    eprintln!(
        "farm: 8 vpl steps as 2 chains on 2 workers: merged vs single {chains_vs_single:.4} (stated {merged_error:.4} and {single_error:.4})"
    );

    // Rounds: a `hemicube` job on the Cornell box's page as 2 bands of rows in 3 rounds,
    // on the two workers. Round r's tasks wait for round r-1's and read their results
    // from the store; the merge reads the last round's. Same request, same seed: the
    // lightmap is the one-process bake in rounds' (`rounds::bake_in_rounds`), texel for
    // texel.
    let in_rounds = json!({
        "scene": cornell, "technique": "hemicube", "resolution": 24, "seed": 5,
        "stop": {"steps": 14}, "regions": 2, "rounds": 3, "denoise": "none",
    });
    let (rounds_id, rounds_url, job) = succeeded(&http, &farm.url, in_rounds.clone(), 180, "the job in rounds").await;
    let tasks = &job["tasks"];
    assert_eq!((tasks["count"].clone(), tasks["rounds"].clone()), (json!(6), json!(3)));
    let list = tasks["list"].as_array().unwrap();
    let shape: Vec<(Value, Value, Value, Value)> = list
        .iter()
        .map(|t| {
            (
                t["kind"].clone(),
                t["region"].clone(),
                t["round"].clone(),
                t["step_range"].clone(),
            )
        })
        .collect();
    let bake_task =
        |region: u64, round: u64, range: [u64; 2]| (json!("bake"), json!(region), json!(round), json!(range));
    assert_eq!(
        shape,
        [
            bake_task(0, 0, [0, 2]),
            bake_task(1, 0, [0, 2]),
            bake_task(0, 1, [2, 6]),
            bake_task(1, 1, [2, 6]),
            bake_task(0, 2, [6, 14]),
            bake_task(1, 2, [6, 14]),
            (json!("merge"), Value::Null, Value::Null, Value::Null),
        ]
    );
    assert_eq!(job["progress"]["steps"], 14, "{job:#}");
    // Rounds before the last state no error (the rounds' lag is measured only at the last
    // round's control texels); the last round's tasks state their halves'.
    let stated: Vec<bool> = list[..6].iter().map(|t| t["error"].is_number()).collect();
    assert_eq!(stated, [false, false, false, false, true, true], "{job:#}");
    // Round 1's first task showed round 0 as the job's first snapshot, stating no error;
    // the history's points before the merge's state none either.
    assert!(job["snapshots"].as_u64().unwrap() >= 1, "{job:#}");
    let history = job["history"].as_array().unwrap();
    let (last, running) = history.split_last().unwrap();
    assert!(last["error"].is_number(), "{job:#}");
    assert!(
        !running.is_empty() && running.iter().all(|p| p["error"].is_null()),
        "{job:#}"
    );
    let r = http.get(format!("{rounds_url}/lightmap.exr")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let merged = ReferenceLightmap::from_pages(&[r.bytes().await.unwrap()]).unwrap();
    let request = JobSpec::parse(in_rounds.to_string().as_bytes()).unwrap().task_request();
    let box_scene = Arc::new(scene::import_slice(&cornell_glb(), None).unwrap().0);
    let one_process = lightmapd::engine::rounds::bake_in_rounds(
        box_scene,
        &request,
        lightmapd::engine::rounds::RoundsShape { regions: 2, rounds: 3 },
        &BakeOptions::default(),
        &mut |_: BakeEvent<'_>| std::ops::ControlFlow::Continue(()),
        &mut |_| {},
    )
    .unwrap()
    .result;
    let one_values = delivered(&one_process);
    let apart = relative_error(&one_values, &merged.per_texel(&one_process.atlas).unwrap());
    assert!(
        apart < 1e-6,
        "the job in rounds and the one-process bake in rounds differ by {apart:.2e} (relative RMS)"
    );
    // The stated error includes the bias measured at control texels, whose `path`
    // reference bakes for as long as the technique took (`ControlTexels::keep_up`): a
    // matter of timing, so alike, not equal.
    let stated = job["summary"]["error"]["relative"].as_f64().unwrap();
    let stated_one = f64::from(one_process.summary.error.relative.unwrap());
    assert!(
        (stated - stated_one).abs() < 0.25 * stated_one,
        "the job in rounds states {stated:.4}, the one-process bake {stated_one:.4}"
    );
    for k in 0..6 {
        until_deleted(&artifacts, &store::task_partial(&rounds_id, k)).await;
    }
    eprintln!(
        "farm: hemicube, 2 bands x 3 rounds on 2 workers: merged vs one process {apart:.1e}; stated {stated:.4} and {stated_one:.4}; {} snapshots",
        job["snapshots"]
    );
    farm.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_a_split_job_stops_its_tasks_within_seconds() {
    let test = "farm::cancelling_a_split_job_stops_its_tasks_within_seconds";
    let Some(farm) = Farm::start(test, 1).await else {
        return;
    };
    let http = reqwest::Client::new();
    let scene = farm.upload(&http).await;
    // 3 tasks of 20 000 steps at 64²: minutes each, so only the cancel ends them.
    let id = submit(
        &http,
        &farm.url,
        json!({"scene": scene, "resolution": 64, "stop": {"steps": 60000}, "tasks": 3, "denoise": "none"}),
    )
    .await;
    let job_url = format!("{}/v1/jobs/{id}", farm.url);
    let t = Instant::now();
    loop {
        let j = get_json(&http, &job_url).await;
        if j["tasks"]["list"][0]["status"] == "running" && j["tasks"]["list"][0]["steps"].as_u64().unwrap_or(0) >= 1 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no task ever ran: {j:#}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let asked = Instant::now();
    let r = http.post(format!("{job_url}/cancel")).send().await.unwrap();
    assert_eq!(r.status(), 202);
    let job = loop {
        let j = get_json(&http, &job_url).await;
        if j["status"] != "running" {
            break j;
        }
        assert!(
            asked.elapsed() < Duration::from_secs(5),
            "still running 5 s after the cancel: {j:#}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let took = asked.elapsed();
    assert_eq!(job["status"], "cancelled", "{job:#}");
    let statuses: Vec<&str> = job["tasks"]["list"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["status"].as_str().unwrap())
        .collect();
    assert_eq!(statuses, ["cancelled"; 4], "{job:#}");
    eprintln!(
        "farm: a split job cancelled {:.2} s after the request",
        took.as_secs_f64()
    );
    farm.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_no_worker_can_run_says_what_it_waits_for() {
    let test = "farm::a_job_no_worker_can_run_says_what_it_waits_for";
    let Some(mut farm) = Farm::start(test, 0).await else {
        return;
    };
    // One worker, with a per-job memory limit of 1 MiB (the API process keeps 8 GiB).
    let small = spawn_pg_worker(
        &farm.db.url,
        &farm.store,
        &farm.s3.env,
        LEASE,
        &["--max-job-memory-mb", "1"],
    );
    farm.procs.0.push(small);
    let http = reqwest::Client::new();
    let scene = farm.upload(&http).await;
    let gpu = submit(
        &http,
        &farm.url,
        json!({"scene": scene, "resolution": 16, "stop": {"steps": 4}, "requires": {"gpu": true}}),
    )
    .await;
    let big = submit(
        &http,
        &farm.url,
        json!({"scene": scene, "resolution": 256, "stop": {"steps": 4}}),
    )
    .await;
    // Once the worker has registered (at its start), each job says why it waits.
    let waiting = |id: String| {
        let (http, url) = (http.clone(), format!("{}/v1/jobs/{id}", farm.url));
        async move {
            let t = Instant::now();
            loop {
                let j = get_json(&http, &url).await;
                assert_eq!(j["status"], "queued", "{j:#}");
                let w = j["waiting_for"].as_str().unwrap_or_default().to_string();
                if w.starts_with("a worker with ") {
                    return w;
                }
                assert!(t.elapsed() < Duration::from_secs(30), "{j:#}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    };
    let w = waiting(gpu.clone()).await;
    assert!(
        // Both are missing: the GPU, and the memory (even a 16² job's estimate, about 65 MiB,
        // is over 1 MiB).
        w.starts_with("a worker with a hardware GPU (requires.gpu) and a per-job memory limit of at least ")
            && w.contains(": none of the 1 live workers has all of it ("),
        "{w}"
    );
    assert!(w.ends_with("; 1 MiB a job))"), "{w}");
    let w = waiting(big.clone()).await;
    assert!(
        w.starts_with("a worker with a per-job memory limit of at least ")
            && w.contains(" MiB (the job's estimate; --max-job-memory-mb): none of the 1 live workers has all of it ("),
        "{w}"
    );
    // Still queued a while later: the worker took neither (it would have failed the big
    // one for its memory before requirements were claims' filters).
    tokio::time::sleep(Duration::from_secs(2)).await;
    for id in [&gpu, &big] {
        let url = format!("{}/v1/jobs/{id}", farm.url);
        assert_eq!(get_json(&http, &url).await["status"], "queued");
        let r = http.post(format!("{url}/cancel")).send().await.unwrap();
        assert_eq!(r.status(), 202);
        assert_eq!(r.json::<Value>().await.unwrap()["status"], "cancelled");
    }
    farm.stop().await;
}
