//! The bake service over real HTTP on 127.0.0.1 (ephemeral ports, temporary folders):
//! the happy path with `lightmapd submit`, every error status with its exact
//! problem+json body, cancel, 50 concurrent submissions with 2 workers, restart recovery
//! of a real `lightmapd serve` killed with SIGKILL (and handed back on SIGTERM), and the
//! OpenAPI document against the committed route list; snapshot retention over a long
//! bake, `DELETE /v1/jobs/{id}`, the retention sweeper and the store usage in `/metrics`
//! (issue 24).
//!
//! Bakes are tiny (the `path` technique on the bundled Cornell box at 16² texels, a few
//! steps), and every wait polls with a short interval up to a deadline.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::service_common::get_json;
use futures_util::StreamExt;
use lightmapd::engine::technique::TECHNIQUES;
use lightmapd::service::{self, Config, Running};
use serde_json::{Value, json};

const DEADLINE: Duration = Duration::from_secs(60);

fn bundled() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.glb")
}

fn glb() -> Vec<u8> {
    std::fs::read(bundled()).unwrap()
}

struct Server {
    running: Running,
    url: String,
    http: reqwest::Client,
    _dir: tempfile::TempDir,
}

async fn start(workers: usize, tweak: impl FnOnce(&mut Config)) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: dir.path().to_path_buf(),
        workers,
        snapshot_interval: Duration::from_millis(50),
        ..Config::default()
    };
    tweak(&mut config);
    let running = service::start(config).await.unwrap();
    let url = format!("http://{}", running.addr);
    Server {
        running,
        url,
        // No pooled connections: a request the server refuses before reading its body
        // (413, 415) ends that connection, and a POST reusing it fails with
        // IncompleteMessage (seen once in CI), not with the server's answer.
        http: reqwest::Client::builder().pool_max_idle_per_host(0).build().unwrap(),
        _dir: dir,
    }
}

impl Server {
    async fn upload(&self) -> String {
        let r = self
            .http
            .post(format!("{}/v1/scenes", self.url))
            .header("content-type", "model/gltf-binary")
            .body(glb())
            .send()
            .await
            .unwrap();
        assert!(r.status().is_success(), "{}", r.text().await.unwrap());
        r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
    }

    async fn submit(&self, body: Value) -> String {
        let r = self
            .http
            .post(format!("{}/v1/jobs", self.url))
            .json(&body)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
        r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
    }

    async fn job(&self, id: &str) -> Value {
        get_json(&self.http, &format!("{}/v1/jobs/{id}", self.url)).await
    }

    /// Polls the job until `pred` holds.
    async fn wait_job(&self, id: &str, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
        let start = Instant::now();
        loop {
            let j = self.job(id).await;
            if pred(&j) {
                return j;
            }
            assert!(start.elapsed() < DEADLINE, "job {id} never became {what}: {j:#}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

/// Reads server-sent events until a terminal one; returns (name, data) in order.
async fn read_events(http: &reqwest::Client, url: &str) -> Vec<(String, Value)> {
    let r = http.get(url).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "text/event-stream");
    let mut stream = r.bytes_stream();
    let mut buf = String::new();
    let mut out = Vec::new();
    let read = async {
        while let Some(chunk) = stream.next().await {
            buf.push_str(&String::from_utf8_lossy(&chunk.unwrap()));
            while let Some(end) = buf.find("\n\n") {
                let block: String = buf.drain(..end + 2).collect();
                let (mut name, mut data) = (String::new(), String::new());
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event: ") {
                        name = v.to_string();
                    } else if let Some(v) = line.strip_prefix("data: ") {
                        data.push_str(v);
                    }
                }
                if name.is_empty() {
                    continue; // keep-alive comment
                }
                let terminal = matches!(name.as_str(), "done" | "failed" | "cancelled");
                out.push((name, serde_json::from_str(&data).unwrap()));
                if terminal {
                    return;
                }
            }
        }
    };
    tokio::time::timeout(DEADLINE, read)
        .await
        .expect("events end with done, failed or cancelled");
    out
}

fn is_exr(b: &[u8]) -> bool {
    b.starts_with(&[0x76, 0x2f, 0x31, 0x01])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn happy_path_upload_bake_follow_download() {
    let s = start(1, |_| {}).await;
    let h = &s.http;

    // Upload: 201 the first time, 200 and the same id for the same bytes.
    let r = h
        .post(format!("{}/v1/scenes", s.url))
        .header("content-type", "model/gltf-binary")
        .body(glb())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let scene: Value = r.json().await.unwrap();
    let scene_id = scene["id"].as_str().unwrap().to_string();
    assert!(scene["content_hash"].as_str().unwrap().starts_with("sha256:"));
    assert_eq!(scene["report"]["has_lightmap_uvs"], true);
    assert!(scene["report"]["triangles"].as_u64().unwrap() > 0);
    let again = h.post(format!("{}/v1/scenes", s.url)).body(glb()).send().await.unwrap();
    assert_eq!(again.status(), 200);
    assert_eq!(again.json::<Value>().await.unwrap()["id"], scene_id.as_str());
    let fetched = get_json(h, &format!("{}/v1/scenes/{scene_id}", s.url)).await;
    assert_eq!(fetched["report"], scene["report"]);

    // Submit and follow the events from the start.
    let id = s
        .submit(json!({"scene": scene_id, "resolution": 16, "stop": {"steps": 8}, "outputs": ["validity"]}))
        .await;
    let events = read_events(h, &format!("{}/v1/jobs/{id}/events", s.url)).await;
    let names: Vec<&str> = events.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names[0], "status", "{names:?}");
    assert_eq!(*names.last().unwrap(), "done", "{names:?}");
    let done = &events.last().unwrap().1;
    assert_eq!(done["status"], "succeeded");

    let job = s.job(&id).await;
    assert_eq!(job["status"], "succeeded");
    assert_eq!(job["attempts"], 1);
    assert_eq!(job["progress"]["steps"], 8);
    assert_eq!(job["progress"]["fraction"], 1.0);
    assert_eq!(job["spec"]["technique"], "path");
    assert_eq!(job["plan"]["texel_set"]["width"], 16);
    assert_eq!(job["plan"]["technique"], "path");
    assert!(!job["plan"]["passes"].as_array().unwrap().is_empty(), "{job:#}");
    assert!(job["plan"]["left_out"].is_array(), "{job:#}");
    assert_eq!(job["summary"]["stopped_by"], "steps");
    let history = job["history"].as_array().unwrap();
    assert!(!history.is_empty(), "{job:#}");
    assert!(history.iter().all(|p| p["steps"].as_u64().unwrap() <= 8));
    // The curve ends at the final lightmap's figure, the summary's (issue 22 point 4: what
    // is reported is the delivered lightmap's error; the raw one beside it).
    let last = history.last().unwrap();
    assert_eq!(last["steps"], 8);
    // (f32 in the history, the same f32 widened to f64 in the summary.)
    let f = |v: &Value| v.as_f64().map(|x| x as f32);
    assert_eq!(f(&last["error"]), f(&job["summary"]["error"]["relative"]), "{job:#}");
    assert_eq!(
        f(&last["raw_error"]),
        f(&job["summary"]["error"]["raw_relative"]),
        "{job:#}"
    );
    assert!(last["raw_error"].as_f64().unwrap() > 0.0, "{last}");
    assert!(job["snapshots"].as_u64().unwrap() >= 1, "{job:#}");
    assert!(job["failure"].is_null());

    // Artifacts: final, latest snapshot, first snapshot, preview.
    for q in ["", "?snapshot=latest", "?snapshot=1"] {
        let r = h
            .get(format!("{}/v1/jobs/{id}/lightmap.exr{q}", s.url))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "lightmap.exr{q}");
        assert_eq!(r.headers()["content-type"], "image/x-exr");
        assert!(is_exr(&r.bytes().await.unwrap()), "lightmap.exr{q}");
    }
    let png = h
        .get(format!("{}/v1/jobs/{id}/preview.png", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(png.status(), 200);
    assert!(png.bytes().await.unwrap().starts_with(b"\x89PNG"));

    // A late client gets the current state, then the end.
    let late = read_events(h, &format!("{}/v1/jobs/{id}/events", s.url)).await;
    let names: Vec<&str> = late.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["status", "done"]);

    // Listing and filtering.
    let list = get_json(h, &format!("{}/v1/jobs?status=succeeded&limit=10", s.url)).await;
    assert_eq!(list["total"], 1);
    assert_eq!(list["jobs"][0]["id"], id.as_str());
    let none = get_json(h, &format!("{}/v1/jobs?status=queued", s.url)).await;
    assert_eq!(none["total"], 0);

    // Health, metrics, dashboard.
    let health = get_json(h, &format!("{}/healthz", s.url)).await;
    assert_eq!(health["status"], "ok");
    let metrics = h
        .get(format!("{}/metrics", s.url))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    for line in [
        "lightmapd_queue_depth 0",
        "lightmapd_jobs{state=\"succeeded\"} 1",
        "lightmapd_jobs_finished_total{outcome=\"succeeded\"} 1",
        "lightmapd_step_seconds_count{technique=\"path\"} 8",
        "lightmapd_bake_seconds_count{technique=\"path\"} 1",
    ] {
        assert!(metrics.lines().any(|l| l == line), "missing {line:?} in\n{metrics}");
    }
    let dash = h.get(format!("{}/", s.url)).send().await.unwrap();
    assert_eq!(dash.status(), 200);
    assert!(dash.text().await.unwrap().contains("/v1/jobs"));

    // The command-line client against the same server: upload (same scene), submit a
    // job split into two tasks, wait, download.
    let out = s._dir.path().join("submitted.exr");
    let url = s.url.clone();
    let output = tokio::task::spawn_blocking(move || {
        Command::new(env!("CARGO_BIN_EXE_lightmapd"))
            .arg("submit")
            .arg(bundled())
            .args([
                "--server",
                &url,
                "--resolution",
                "16",
                "--steps",
                "4",
                "--tasks",
                "2",
                "--wait",
                "-o",
            ])
            .arg(&out)
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(stderr.contains("succeeded: 4 steps"), "{stderr}");
    let printed: Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(printed["status"], "succeeded");
    assert_eq!(printed["spec"]["tasks"], 2);
    assert_eq!(printed["tasks"]["count"], 2);
    assert_eq!(printed["scene"], scene_id.as_str());
    assert!(is_exr(&std::fs::read(s._dir.path().join("submitted.exr")).unwrap()));

    // A job the server rejects is bad input for the client too: exit code 2, the
    // server's detail and field on one line.
    let url = s.url.clone();
    let output = tokio::task::spawn_blocking(move || {
        Command::new(env!("CARGO_BIN_EXE_lightmapd"))
            .arg("submit")
            .arg(bundled())
            .args(["--server", &url, "--technique", "magic"])
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert_eq!(output.status.code(), Some(2));
    assert_eq!(
        String::from_utf8_lossy(&output.stderr).lines().last().unwrap(),
        format!(
            "error: submit: 422 unknown technique \"magic\"; available: {} (technique)",
            TECHNIQUES.join(", ")
        )
    );
    // --regions, --rounds and --requires reach the server as the job's fields; an unknown
    // capability is refused before anything is sent.
    for (args, last) in [
        (
            vec![
                "--technique",
                "path",
                "--regions",
                "2",
                "--rounds",
                "3",
                "--steps",
                "60",
                "--requires",
                "oidn",
            ],
            "error: submit: 422 rounds: technique path is not baked in rounds (only sdb and hemicube are, so far) (rounds)",
        ),
        (
            vec!["--requires", "gpu,tpu"],
            "error: --requires: unknown capability \"tpu\"; one of gpu, oidn",
        ),
    ] {
        let url = s.url.clone();
        let output = tokio::task::spawn_blocking(move || {
            Command::new(env!("CARGO_BIN_EXE_lightmapd"))
                .arg("submit")
                .arg(bundled())
                .args(["--server", &url])
                .args(args)
                .output()
                .unwrap()
        })
        .await
        .unwrap();
        assert_eq!(output.status.code(), Some(2));
        assert_eq!(String::from_utf8_lossy(&output.stderr).lines().last().unwrap(), last);
    }

    // The scene is free again: it can be deleted, and is gone.
    let del = h
        .delete(format!("{}/v1/scenes/{scene_id}", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(del.status(), 204);
    let gone = h.get(format!("{}/v1/scenes/{scene_id}", s.url)).send().await.unwrap();
    assert_eq!(gone.status(), 404);
    s.running.shutdown().await;
}

/// Sends a request and checks the status and the whole problem+json body.
async fn expect_problem(req: reqwest::RequestBuilder, status: u16, body: Value) {
    let r = req.send().await.unwrap();
    assert_eq!(r.status().as_u16(), status);
    assert_eq!(r.headers()["content-type"], "application/problem+json");
    let got: Value = r.json().await.unwrap();
    assert_eq!(got, body);
}

fn problem(status: u16, title: &str, kind: &str, detail: &str, field: Option<&str>) -> Value {
    let mut v = json!({
        "type": format!("urn:lightmapd:problem:{kind}"),
        "title": title,
        "status": status,
        "detail": detail,
    });
    if let Some(f) = field {
        v["field"] = json!(f);
    }
    v
}

/// A biased technique's job reports an error that covers its bias (issue 21): the plan
/// says so, the summary carries the noise, bias, 90 % interval and control texels, and
/// every history point its noise and bias beside the total.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_biased_bake_reports_bias_and_noise() {
    let s = start(1, |_| {}).await;
    let h = &s.http;
    let r = h.post(format!("{}/v1/scenes", s.url)).body(glb()).send().await.unwrap();
    let scene: Value = r.json().await.unwrap();
    let id = s
        .submit(
            json!({"scene": scene["id"], "technique": "sdb", "resolution": 16, "stop": {"steps": 6},
                       "params": {"map_size": 128}, "denoise": "none"}),
        )
        .await;
    read_events(h, &format!("{}/v1/jobs/{id}/events", s.url)).await;
    let job = s.job(&id).await;
    assert_eq!(job["status"], "succeeded", "{job:#}");
    let covers = job["plan"]["error_estimate"].as_str().unwrap();
    assert!(
        covers.starts_with("noise and bias, measured at up to 256 control texels"),
        "{covers}"
    );
    let e = &job["summary"]["error"];
    let (total, noise, bias) = (
        e["relative"].as_f64().unwrap(),
        e["noise"].as_f64().unwrap(),
        e["bias"].as_f64().unwrap(),
    );
    assert!(total >= noise && total >= bias, "{e}");
    assert!(e["control_texels"].as_u64().unwrap() > 0, "{e}");
    let [lo, hi] = [0, 1].map(|i| e["interval"][i].as_f64().unwrap());
    assert!(lo <= total && total <= hi, "{e}");
    let history = job["history"].as_array().unwrap();
    assert!(!history.is_empty());
    // Before both halves have a step there is no error, and while the estimate is still
    // black (sdb's first step only bootstraps) it is 0 with nothing to compare; every
    // point with an error above 0 has its parts.
    let measured: Vec<&Value> = history
        .iter()
        .filter(|p| p["error"].as_f64().unwrap_or(0.0) > 0.0)
        .collect();
    assert!(!measured.is_empty(), "{history:?}");
    for p in measured {
        assert!(p["noise"].is_f64() && p["bias"].is_f64(), "{p}");
    }
}

/// A job that names a finished job as its `reference` (issue 23 point 3): every history
/// point carries the error measured against that job's lightmap, with the metric of
/// docs/accuracy.md. The same seed and steps bake the same lightmap, so its final point
/// reads exactly 0; another seed differs by the two bakes' independent noise, about
/// √(a² + b²) of their own estimates. A reference that cannot be compared is refused at
/// submit, naming `reference` and what differs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reference_job_gives_the_measured_error_curve() {
    let s = start(1, |_| {}).await;
    let scene = s.upload().await;
    let body = |seed: u64, reference: Option<&str>| {
        let mut b = json!({"scene": scene, "resolution": 24, "stop": {"steps": 48}, "seed": seed,
            "denoise": "none", "lighting": {"sky": {"radiance": [1.0, 1.0, 1.0]}}});
        if let Some(r) = reference {
            b["reference"] = json!(r);
        }
        b
    };
    let done = |j: &Value| j["status"] != "queued" && j["status"] != "running";
    let a = s.submit(body(1, None)).await;
    let ja = s.wait_job(&a, "finished", done).await;
    assert_eq!(ja["status"], "succeeded", "{ja:#}");
    assert!(
        ja["history"]
            .as_array()
            .unwrap()
            .iter()
            .all(|p| p.get("true_error").is_none())
    );

    // The same bake against itself: 0 at the end, and a curve falling to it.
    let b = s.submit(body(1, Some(&a))).await;
    let jb = s.wait_job(&b, "finished", done).await;
    assert_eq!(jb["status"], "succeeded", "{jb:#}");
    let history = jb["history"].as_array().unwrap();
    let last = history.last().unwrap();
    assert_eq!(last["true_error"], json!(0.0), "{last}");
    let measured_b: Vec<f64> = history.iter().filter_map(|p| p["true_error"].as_f64()).collect();
    assert_eq!(measured_b.len(), history.len(), "every point is measured: {history:#?}");
    assert!(
        measured_b[0] > 0.0,
        "an early snapshot differs from the final lightmap: {measured_b:?}"
    );
    let ea = ja["summary"]["error"]["relative"].as_f64().unwrap();
    let reference = &jb["plan"]["reference"];
    assert_eq!(reference["job"], json!(a), "{reference}");
    assert!(
        (reference["error"].as_f64().unwrap() - ea).abs() < 1e-6,
        "{reference} vs {ea}"
    );
    assert_eq!(
        reference["texels"], jb["summary"]["atlas"]["valid_texels"],
        "{reference}"
    );

    // Another seed: two independent estimates of the same answer.
    let c = s.submit(body(2, Some(&a))).await;
    let jc = s.wait_job(&c, "finished", done).await;
    assert_eq!(jc["status"], "succeeded", "{jc:#}");
    let ec = jc["summary"]["error"]["relative"].as_f64().unwrap();
    let measured = jc["history"].as_array().unwrap().last().unwrap()["true_error"]
        .as_f64()
        .unwrap();
    let expected = (ea * ea + ec * ec).sqrt();
    eprintln!(
        "seed 2 against seed 1: measured {measured:.5}, expected {expected:.5} (a {ea:.5}, c {ec:.5}); same seed: {measured_b:?}"
    );
    assert!(
        (0.6..1.6).contains(&(measured / expected)),
        "measured {measured} against the two estimates' {expected} (a {ea}, c {ec})"
    );

    // Refused at submit, by field.
    let refused = |detail: String| problem(422, "Unprocessable Entity", "invalid-field", &detail, Some("reference"));
    let mut other = body(1, Some(&a));
    other["resolution"] = json!(16);
    expect_problem(
        s.http.post(format!("{}/v1/jobs", s.url)).json(&other),
        422,
        refused(format!(
            "job {a} has resolution 24, this job 16: a reference must bake the same texel grid and light"
        )),
    )
    .await;
    let mut other = body(1, Some(&a));
    other["lighting"] = json!({"sky": {"radiance": [2.0, 2.0, 2.0]}});
    let r = s
        .http
        .post(format!("{}/v1/jobs", s.url))
        .json(&other)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 422);
    let p: Value = r.json().await.unwrap();
    assert_eq!(p["field"], "reference", "{p}");
    assert!(
        p["detail"]
            .as_str()
            .unwrap()
            .starts_with(&format!("job {a} has lighting ")),
        "{p}"
    );
    expect_problem(
        s.http
            .post(format!("{}/v1/jobs", s.url))
            .json(&body(1, Some("no-such-job"))),
        422,
        refused("no job with id \"no-such-job\": a reference is one of your succeeded jobs".into()),
    )
    .await;
}

/// A job's light probes (issue 26 point 2): baked after the lightmap, stored as the job's
/// `probes.json` artifact; a job without `probes` has none (404), and a job whose probes
/// have nowhere to go is refused at submit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probes_are_an_artifact_of_the_job() {
    let s = start(1, |_| {}).await;
    let h = &s.http;
    let r = h.post(format!("{}/v1/scenes", s.url)).body(glb()).send().await.unwrap();
    let scene: Value = r.json().await.unwrap();
    assert_eq!(scene["report"]["probe_nodes"], 0);
    // The bundled Cornell box is 2 m on a side: a 0.7 m grid is 3 x 3 x 3 probes, plus one
    // given at the room's centre.
    let id = s
        .submit(
            json!({"scene": scene["id"], "resolution": 16, "stop": {"steps": 4}, "denoise": "none",
                       "probes": {"spacing": 0.7, "positions": [[0.0, 1.0, 0.0]], "steps": 4}}),
        )
        .await;
    read_events(h, &format!("{}/v1/jobs/{id}/events", s.url)).await;
    let job = s.job(&id).await;
    assert_eq!(job["status"], "succeeded", "{job:#}");
    eprintln!("progress {}", job["progress"]);
    // The probes' progress (issue 26): all 4 steps of the 28 probes.
    assert_eq!(
        job["progress"]["probes"],
        json!({"steps": 4, "of": 4, "probes": 28}),
        "{job:#}"
    );
    assert!(
        job["plan"]["passes"]
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p["name"] == "light probes"),
        "{job:#}"
    );
    let r = h
        .get(format!("{}/v1/jobs/{id}/probes.json", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "application/json");
    let set: Value = r.json().await.unwrap();
    let probes = set["probes"].as_array().unwrap();
    let n = probes.len();
    assert_eq!(n, 28, "{set:#}");
    assert_eq!(set["steps"], 4);
    assert!(set["error"].as_f64().unwrap() > 0.0, "{}", set["error"]);
    let given = &probes[n - 1];
    assert_eq!(given["position"], json!([0.0, 1.0, 0.0]));
    assert_eq!(given["valid"], true);
    assert_eq!(given["sh"].as_array().unwrap().len(), 9);
    // Lit by the ceiling: the centre's L0 is positive in every channel.
    assert!(
        given["sh"][0]
            .as_array()
            .unwrap()
            .iter()
            .all(|c| c.as_f64().unwrap() > 0.0),
        "{given}"
    );

    let plain = s
        .submit(json!({"scene": scene["id"], "resolution": 8, "stop": {"steps": 2}, "denoise": "none"}))
        .await;
    read_events(h, &format!("{}/v1/jobs/{plain}/events", s.url)).await;
    expect_problem(
        h.get(format!("{}/v1/jobs/{plain}/probes.json", s.url)),
        404,
        problem(
            404,
            "Not Found",
            "not-found",
            &format!("job {plain} asked for no probes (job field `probes`)"),
            None,
        ),
    )
    .await;
    expect_problem(
        h.post(format!("{}/v1/jobs", s.url)).header("content-type", "application/json").body(
            json!({"scene": scene["id"], "probes": {"steps": 4}}).to_string(),
        ),
        422,
        problem(
            422,
            "Unprocessable Entity",
            "invalid-field",
            "probes: no position: give probes.spacing or probes.positions, or mark glTF nodes with extras.light_probe = true",
            Some("probes"),
        ),
    )
    .await;
    expect_problem(
        h.post(format!("{}/v1/jobs", s.url))
            .header("content-type", "application/json")
            .body(json!({"scene": scene["id"], "probes": {"spacing": -1}}).to_string()),
        422,
        problem(
            422,
            "Unprocessable Entity",
            "invalid-field",
            "probes.spacing must be a positive distance, got -1",
            Some("probes.spacing"),
        ),
    )
    .await;
    // Adaptive placement refines a grid: without one, or too deep, it is refused.
    for (probes, detail) in [
        (
            json!({"positions": [[0.0, 1.0, 0.0]], "subdivide": 2}),
            "probes.subdivide refines the grid of probes.spacing: give probes.spacing too",
        ),
        (
            json!({"spacing": 0.7, "subdivide": 9}),
            "probes.subdivide must be in 0..=4, got 9",
        ),
    ] {
        expect_problem(
            h.post(format!("{}/v1/jobs", s.url))
                .header("content-type", "application/json")
                .body(json!({"scene": scene["id"], "probes": probes}).to_string()),
            422,
            problem(
                422,
                "Unprocessable Entity",
                "invalid-field",
                detail,
                Some("probes.subdivide"),
            ),
        )
        .await;
    }
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_error_status_has_its_problem_body() {
    // No workers: a job stays queued, which the 409 cases need.
    let s = start(0, |c| c.limits.max_scene_bytes = 64 << 10).await;
    let (h, u) = (&s.http, &s.url);
    let scene = s.upload().await;
    let job = s
        .submit(json!({"scene": scene, "resolution": 16, "stop": {"steps": 1}}))
        .await;
    let post_job = |body: &str| {
        h.post(format!("{u}/v1/jobs"))
            .header("content-type", "application/json")
            .body(body.to_string())
    };
    let invalid =
        |field: &str, detail: &str| problem(422, "Unprocessable Entity", "invalid-field", detail, Some(field));

    // 400
    expect_problem(
        post_job("{\"scene\": "),
        400,
        problem(
            400,
            "Bad Request",
            "bad-request",
            "the body is not valid JSON: EOF while parsing a value at line 1 column 10",
            None,
        ),
    )
    .await;
    expect_problem(
        h.post(format!("{u}/v1/scenes"))
            .header("content-type", "model/gltf-binary"),
        400,
        problem(
            400,
            "Bad Request",
            "bad-request",
            "empty body: send a .glb (model/gltf-binary) or multipart/form-data with a .gltf and its files",
            None,
        ),
    )
    .await;

    // 404
    expect_problem(
        h.get(format!("{u}/v1/jobs/nope")),
        404,
        problem(404, "Not Found", "not-found", "no job with id \"nope\"", None),
    )
    .await;
    expect_problem(
        h.get(format!("{u}/v1/scenes/nope")),
        404,
        problem(404, "Not Found", "not-found", "no scene with id \"nope\"", None),
    )
    .await;
    expect_problem(
        h.get(format!("{u}/v2/anything")),
        404,
        problem(
            404,
            "Not Found",
            "no-route",
            "no route for GET /v2/anything; see /openapi.json",
            None,
        ),
    )
    .await;
    expect_problem(
        h.get(format!("{u}/v1/jobs/{job}/lightmap.exr?snapshot=3")),
        404,
        problem(
            404,
            "Not Found",
            "not-found",
            &format!("job {job} has 0 snapshot(s); there is no snapshot 3"),
            None,
        ),
    )
    .await;
    expect_problem(
        h.get(format!("{u}/v1/jobs/{job}/preview.png")),
        404,
        problem(
            404,
            "Not Found",
            "not-found",
            &format!("job {job} is queued and has no preview yet"),
            None,
        ),
    )
    .await;

    // 405
    expect_problem(
        h.put(format!("{u}/v1/jobs")),
        405,
        problem(
            405,
            "Method Not Allowed",
            "method-not-allowed",
            "PUT is not allowed on /v1/jobs",
            None,
        ),
    )
    .await;

    // 409
    expect_problem(
        h.delete(format!("{u}/v1/scenes/{scene}")),
        409,
        problem(
            409,
            "Conflict",
            "conflict",
            &format!("scene {scene} is used by 1 queued or running job(s); cancel them or wait for them to finish"),
            None,
        ),
    )
    .await;
    expect_problem(
        h.get(format!("{u}/v1/jobs/{job}/lightmap.exr")),
        409,
        problem(
            409,
            "Conflict",
            "conflict",
            &format!("job {job} is queued and has no final lightmap"),
            None,
        ),
    )
    .await;
    expect_problem(
        h.get(format!("{u}/v1/jobs/{job}/scene.glb")),
        409,
        problem(
            409,
            "Conflict",
            "conflict",
            &format!("job {job} is queued and has no scene with generated UVs yet (a job's plan names it once stored; a scene with its own TEXCOORD_1 gets none)"),
            None,
        ),
    )
    .await;
    let c = h.post(format!("{u}/v1/jobs/{job}/cancel")).send().await.unwrap();
    assert_eq!(c.status(), 202);
    assert_eq!(c.json::<Value>().await.unwrap()["status"], "cancelled");
    expect_problem(
        h.post(format!("{u}/v1/jobs/{job}/cancel")),
        409,
        problem(
            409,
            "Conflict",
            "conflict",
            &format!("job {job} has already finished (cancelled)"),
            None,
        ),
    )
    .await;

    // 413
    expect_problem(
        h.post(format!("{u}/v1/scenes"))
            .header("content-type", "model/gltf-binary")
            .body(vec![0u8; (64 << 10) + 1]),
        413,
        problem(
            413,
            "Payload Too Large",
            "too-large",
            "the scene is larger than this server's limit of 65536 bytes (--max-scene-bytes)",
            None,
        ),
    )
    .await;

    // 415
    expect_problem(
        h.post(format!("{u}/v1/jobs"))
            .header("content-type", "text/plain")
            .body("{}"),
        415,
        problem(
            415,
            "Unsupported Media Type",
            "unsupported-media-type",
            "content type \"text/plain\": send the job as application/json",
            None,
        ),
    )
    .await;

    // 422: the scene, then each job field.
    expect_problem(
        h.post(format!("{u}/v1/scenes"))
            .header("content-type", "model/gltf-binary")
            .body("not a scene"),
        422,
        problem(
            422,
            "Unprocessable Entity",
            "invalid-scene",
            "not a glTF 2.0 file: neither a GLB header (\"glTF\" magic) nor a JSON document",
            None,
        ),
    )
    .await;
    let cases: Vec<(String, &str, String)> = vec![
        (json!({}).to_string(), "scene", "missing field `scene`".into()),
        (
            json!({"scene": scene, "technique": "magic"}).to_string(),
            "technique",
            format!("unknown technique \"magic\"; available: {}", TECHNIQUES.join(", ")),
        ),
        (
            json!({"scene": scene, "resolution": 0}).to_string(),
            "resolution",
            "resolution must be between 1 and 4096, got 0".into(),
        ),
        (
            json!({"scene": scene, "resolution": 5000}).to_string(),
            "resolution",
            "resolution must be between 1 and 4096, got 5000".into(),
        ),
        (
            json!({"scene": scene, "stop": {"steps": -1}}).to_string(),
            "stop.steps",
            "invalid value: integer `-1`, expected u64".into(),
        ),
        (
            json!({"scene": scene, "stop": {"seconds": -2.0}}).to_string(),
            "stop.seconds",
            "stop.seconds must be a positive number, got -2".into(),
        ),
        (
            json!({"scene": scene, "stop": {"target_error": 0}}).to_string(),
            "stop.target_error",
            "stop.target_error must be a positive number, got 0".into(),
        ),
        (
            json!({"scene": scene, "stop": {}}).to_string(),
            "stop",
            "stop: give at least one of steps, seconds, target_error".into(),
        ),
        (
            json!({"scene": scene, "samples": 4}).to_string(),
            "samples",
            "unknown field `samples`, expected one of `scene`, `technique`, `resolution`, `lighting`, `stop`, `params`, `outputs`, `shadowmask_lights`, `probes`, `priority`, `seed`, `denoise`, `lightmap_uvs`, `texels_per_unit`, `max_page_size`, `reference`, `tasks`, `regions`, `rounds`, `requires`".into(),
        ),
        // A split job (issue 25): the engine's own split names why it cannot be.
        (
            json!({"scene": scene, "tasks": 4}).to_string(),
            "tasks",
            "tasks: stop.target_error is a rule about the whole bake's error, which no task sees alone; give stop.steps (the job's total) instead".into(),
        ),
        (
            json!({"scene": scene, "tasks": 4, "stop": {"steps": 6}}).to_string(),
            "tasks",
            "tasks: stop.steps (6) must be at least twice the step ranges per region (4): each task bakes a step of each half".into(),
        ),
        (
            json!({"scene": scene, "tasks": 6, "regions": 4, "stop": {"steps": 60}}).to_string(),
            "regions",
            "regions must divide tasks (each region is baked as tasks / regions step ranges): 4 regions of 6 tasks".into(),
        ),
        (
            json!({"scene": scene, "technique": "sdb", "tasks": 4, "regions": 2, "stop": {"steps": 60}}).to_string(),
            "regions",
            "regions: sdb bakes are split into independent chains of the whole grid, not into regions (each step gathers the reflected light of the running estimate all earlier steps built, over every texel: a range of steps cannot start without the steps before it, and a region's light depends on every other region's; its regions are baked in rounds instead, the others' light held (a job's rounds, bake --rounds, docs/scaling.md)); give regions 1".into(),
        ),
        (
            json!({"scene": scene, "regions": 2, "stop": {"steps": 60}}).to_string(),
            "regions",
            "regions splits a job's tasks: give tasks too (a multiple of regions)".into(),
        ),
        // A job in rounds (issue 25 point 1): regions, one task a region, a technique
        // baked in rounds, a stop rule a round can keep.
        (
            json!({"scene": scene, "technique": "hemicube", "rounds": 3, "stop": {"steps": 60}}).to_string(),
            "rounds",
            "rounds bake a job's regions in turn: give regions too (2 or more)".into(),
        ),
        (
            json!({"scene": scene, "technique": "hemicube", "tasks": 4, "regions": 2, "rounds": 3, "stop": {"steps": 60}}).to_string(),
            "tasks",
            "a job in rounds has one task a region in each round: give tasks equal to regions (2) or leave it out, got 4".into(),
        ),
        (
            json!({"scene": scene, "technique": "path", "regions": 2, "rounds": 3, "stop": {"steps": 60}}).to_string(),
            "rounds",
            "rounds: technique path is not baked in rounds (only sdb and hemicube are, so far)".into(),
        ),
        (
            json!({"scene": scene, "technique": "hemicube", "regions": 2, "rounds": 3, "stop": {"steps": 60, "seconds": 10}}).to_string(),
            "rounds",
            "rounds: stop.seconds and stop.target_error are rules about the whole bake, which no round sees alone; give stop.steps (every region's steps, over all rounds)".into(),
        ),
        (
            json!({"scene": scene, "technique": "hemicube", "regions": 2, "rounds": 3, "stop": {"steps": 5}}).to_string(),
            "rounds",
            "rounds: stop.steps (5) must be at least twice the rounds (3): each round bakes a step of each half".into(),
        ),
        (
            json!({"scene": scene, "technique": "hemicube", "regions": 32, "rounds": 64, "stop": {"steps": 600}}).to_string(),
            "rounds",
            "regions x rounds must be at most 1024 bake tasks, got 32 x 64".into(),
        ),
        (
            json!({"scene": scene, "tasks": 0, "stop": {"steps": 6}}).to_string(),
            "tasks",
            "tasks must be in 1..=1024, got 0".into(),
        ),
        (
            json!({"scene": scene, "denoise": "bm3d"}).to_string(),
            "denoise",
            "unknown denoiser \"bm3d\"; available: auto, oidn, own, none".into(),
        ),
        (
            json!({"scene": scene, "outputs": ["bent_normals"]}).to_string(),
            "outputs[0]",
            "unknown output layer \"bent_normals\"; available: validity, direct, indirect, sh, ao, debug, shadowmask".into(),
        ),
        // The shadowmask's lights against the stored scene's (issue 26): the Cornell box
        // has an emissive ceiling and no KHR_lights_punctual light.
        (
            json!({"scene": scene, "outputs": ["shadowmask"]}).to_string(),
            "outputs",
            "outputs: \"shadowmask\" needs a light to mask, and the job has no lighting.sun and the scene no KHR_lights_punctual light".into(),
        ),
        (
            json!({"scene": scene, "outputs": ["shadowmask"], "shadowmask_lights": ["sun", "Lamp"],
                   "lighting": {"sun": {"direction": [0, -1, 0], "radiance": [1, 1, 1], "angular_diameter_deg": 0.5}}}).to_string(),
            "shadowmask_lights[1]",
            "shadowmask_lights[1]: no light is called \"Lamp\"; the job has: sun".into(),
        ),
        // What the technique table's row does not allow is refused at submit (issue 21):
        // a layer the technique cannot write, a bad parameter (every technique bakes every
        // light now; the light check's refusal is tested on a synthetic row in table.rs).
        (
            json!({"scene": scene, "technique": "sdb", "outputs": ["direct", "sh"]}).to_string(),
            "outputs[1]",
            "outputs[1]: sdb cannot write the \"sh\" layer; techniques that can: path".into(),
        ),
        (
            json!({"scene": scene, "technique": "path", "params": {"samples_per_step": 0}}).to_string(),
            "params.samples_per_step",
            "params.samples_per_step must be in 1..=4096, got 0".into(),
        ),
        (
            json!({"scene": scene, "lighting": {"sky": {"radiance": [1, -1, 1]}}}).to_string(),
            "lighting.sky.radiance",
            "lighting.sky.radiance must be finite and >= 0, got [1.0, -1.0, 1.0]".into(),
        ),
        (
            json!({"scene": scene, "lighting": {"sun": {"direction": [0, -1, 0], "radiance": [1, 1, 1], "angular_diameter_deg": 0}}}).to_string(),
            "lighting.sun.angular_diameter_deg",
            "lighting.sun.angular_diameter_deg must be in (0, 180), got 0".into(),
        ),
        (
            json!({"scene": "0123456789abcdef"}).to_string(),
            "scene",
            "no scene with id \"0123456789abcdef\"; upload it first".into(),
        ),
    ];
    for (body, field, detail) in &cases {
        expect_problem(post_job(body), 422, invalid(field, detail)).await;
    }
    expect_problem(
        h.get(format!("{u}/v1/jobs?status=done")),
        422,
        invalid(
            "status",
            "unknown status \"done\"; one of queued, running, succeeded, failed, cancelled",
        ),
    )
    .await;
    expect_problem(
        h.get(format!("{u}/v1/jobs/{job}/lightmap.exr?snapshot=first")),
        422,
        invalid("snapshot", "snapshot must be `latest` or a number >= 1, got \"first\""),
    )
    .await;
    s.running.shutdown().await;
}

/// A job with no light at all is accepted (an exact zero is a correct answer) but its
/// submitter is told at submit, in the 202's `warnings`, not only by the black lightmap;
/// a job that brings its own sky, or a scene with an emitter, gets no warning.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_with_no_light_is_warned_about_at_submit() {
    use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder};
    let s = start(1, |_| {}).await;
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.5, 0.5, 0.5]));
    b.square("floor", glam::Vec3::ZERO, 2.0, glam::Vec3::Y, grey);
    let glb = b.to_glb();
    let r = s
        .http
        .post(format!("{}/v1/scenes", s.url))
        .body(glb.clone())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let dark = r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let lit = s.upload().await;
    let created = |body: Value| {
        let s = &s;
        async move {
            let r = s
                .http
                .post(format!("{}/v1/jobs", s.url))
                .json(&body)
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 202);
            r.json::<Value>().await.unwrap()
        }
    };
    let job = created(json!({"scene": dark, "resolution": 16, "stop": {"steps": 4}})).await;
    assert_eq!(
        job["warnings"],
        json!([
            "the scene has no emissive surface or punctual light and the job no lighting.sky or lighting.sun: the lightmap will be exactly zero (give lighting.sky for a uniform sky; `lightmapd submit` takes it as --sky R,G,B)"
        ]),
        "{job:#}"
    );
    // The warning does not hold the job back: it bakes, to exactly zero.
    let id = job["id"].as_str().unwrap().to_string();
    let done = s.wait_job(&id, "succeeded", |j| j["status"] == "succeeded").await;
    assert!(
        done["plan"]["left_out"]
            .as_array()
            .unwrap()
            .iter()
            .any(|l| l["name"] == "light"),
        "{done:#}"
    );
    let exr = s
        .http
        .get(format!("{}/v1/jobs/{id}/lightmap.exr", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(exr.status(), 200);
    let rgb = crate::service_common::exr_rgb(&exr.bytes().await.unwrap());
    assert!(
        !rgb.is_empty() && rgb.iter().all(|t| *t == [0.0; 3]),
        "a lightmap with no light is not zero"
    );

    for body in [
        json!({"scene": dark, "resolution": 16, "stop": {"steps": 4}, "lighting": {"sky": {"radiance": [1, 1, 1]}}}),
        json!({"scene": lit, "resolution": 16, "stop": {"steps": 4}}),
        // A sun of radiance 1e5: 6.7 W/m² from its 6.7e-5 sr, twice the sky's π.
        json!({"scene": dark, "resolution": 16, "stop": {"steps": 4}, "lighting": {
            "sky": {"radiance": [1, 1, 1]},
            "sun": {"direction": [0, -1, 0], "angular_diameter_deg": 0.53, "radiance": [1e5, 1e5, 1e5]}}}),
    ] {
        let job = created(body.clone()).await;
        assert!(job.get("warnings").is_none(), "{body}: {job:#}");
    }
    // A sun given as if its radiance were an irradiance (40): 2.7e-3 W/m², 0.09 % of the
    // sky's, is warned about; the job is still accepted.
    let job = created(
        json!({"scene": dark, "resolution": 16, "stop": {"steps": 4}, "lighting": {
        "sky": {"radiance": [1, 1, 1]},
        "sun": {"direction": [0, -1, 0], "angular_diameter_deg": 0.53, "radiance": [40, 40, 40]}}}),
    )
    .await;
    let warnings = job["warnings"].as_array().unwrap();
    assert_eq!(warnings.len(), 1, "{job:#}");
    let w = warnings[0].as_str().unwrap();
    assert!(
        w.starts_with("the sun gives 2.688e-3 W/m² (its radiance 4.000e1 per steradian times its disc's 6.72e-5 sr), 0.09 % of the sky's 3.142 on a surface facing up"),
        "{w}"
    );
    // The job's plan keeps it, for a caller who did not read the 202.
    let id = job["id"].as_str().unwrap().to_string();
    let planned = s.wait_job(&id, "planned", |j| j["plan"].is_object()).await;
    assert_eq!(planned["plan"]["warnings"], json!([w]), "{planned:#}");

    // The command-line client prints the warning as the bake command does.
    let file = s._dir.path().join("dark.glb");
    std::fs::write(&file, &glb).unwrap();
    let url = s.url.clone();
    let output = tokio::task::spawn_blocking(move || {
        Command::new(env!("CARGO_BIN_EXE_lightmapd"))
            .arg("submit")
            .arg(&file)
            .args(["--server", &url, "--resolution", "16", "--steps", "4"])
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    let warning = "warning: the scene has no emissive surface or punctual light and the job no lighting.sky or lighting.sun: the lightmap will be exactly zero (give lighting.sky for a uniform sky; `lightmapd submit` takes it as --sky R,G,B)";
    assert!(stderr.lines().any(|l| l == warning), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_stops_a_running_bake_and_a_queued_job() {
    let s = start(1, |_| {}).await;
    let scene = s.upload().await;
    // Long enough that only a cancel ends it.
    let running = s
        .submit(json!({"scene": scene, "resolution": 16, "stop": {"seconds": 60}}))
        .await;
    let queued = s
        .submit(json!({"scene": scene, "resolution": 16, "stop": {"steps": 1}}))
        .await;
    s.wait_job(&running, "running with steps", |j| {
        j["status"] == "running" && j["progress"]["steps"].as_u64().unwrap_or(0) >= 1
    })
    .await;

    let c = s
        .http
        .post(format!("{}/v1/jobs/{queued}/cancel", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(c.status(), 202);
    assert_eq!(c.json::<Value>().await.unwrap()["status"], "cancelled");

    let asked = Instant::now();
    let c = s
        .http
        .post(format!("{}/v1/jobs/{running}/cancel", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(c.status(), 202);
    assert_eq!(c.json::<Value>().await.unwrap()["cancel_requested"], true);
    let events = read_events(&s.http, &format!("{}/v1/jobs/{running}/events", s.url)).await;
    assert_eq!(events.last().unwrap().0, "cancelled");
    let j = s.job(&running).await;
    assert_eq!(j["status"], "cancelled");
    // One step of a 16² path bake is milliseconds; the whole round trip stays well
    // under a second even on a loaded machine.
    assert!(
        asked.elapsed() < Duration::from_secs(2),
        "cancel took {:?}",
        asked.elapsed()
    );
    assert_eq!(s.job(&queued).await["attempts"], 0, "a cancelled queued job never ran");
    s.running.shutdown().await;
}

/// Issue 19 point 10: a cancel reaches inside a step. One CPU `path` step of 4096
/// samples a texel over the Cornell box at 256² would take minutes on two cores; the job
/// is cancelled while it runs and must end within seconds, with no step done.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_a_long_step_stops_it_inside_the_step() {
    let _cpu = crate::CPU_HEAVY.lock().await;
    let s = start(1, |_| {}).await;
    let scene = s.upload().await;
    let id = s
        .submit(
            json!({"scene": scene, "technique": "path", "resolution": 256, "stop": {"steps": 1},
                       "params": {"samples_per_step": 4096, "device": "cpu"}, "denoise": "none"}),
        )
        .await;
    s.wait_job(&id, "inside its first step", |j| {
        j["status"] == "running" && j["progress"]["step_fraction"].as_f64().is_some_and(|f| f > 0.0)
    })
    .await;
    let within = s.job(&id).await["progress"]["step_fraction"].as_f64().unwrap();
    assert!(within < 0.5, "the step is far from done when cancelled: {within}");
    let asked = Instant::now();
    let c = s
        .http
        .post(format!("{}/v1/jobs/{id}/cancel", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(c.status(), 202);
    let j = s
        .wait_job(&id, "cancelled", |j| {
            ["cancelled", "succeeded", "failed"].contains(&j["status"].as_str().unwrap_or(""))
        })
        .await;
    let took = asked.elapsed();
    assert_eq!(j["status"], "cancelled", "{j:#}");
    assert_eq!(j["progress"]["steps"], 0, "the step was abandoned, not finished: {j:#}");
    // The ticker passes the flag in within 250 ms and a chunk of the step is a fraction
    // of a second; the step itself would have taken minutes.
    assert!(took < Duration::from_secs(5), "cancel took {took:?} (step at {within})");
    eprintln!(
        "cancelled {took:?} after the request, the step {:.1} % done",
        100.0 * within
    );
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fifty_concurrent_jobs_two_workers_all_succeed_once() {
    let s = start(2, |_| {}).await;
    let scene = s.upload().await;
    let mut submits = Vec::new();
    for i in 0..50u64 {
        let (http, url, scene) = (s.http.clone(), s.url.clone(), scene.clone());
        submits.push(tokio::spawn(async move {
            let r = http
                .post(format!("{url}/v1/jobs"))
                .json(&json!({"scene": scene, "resolution": 16, "stop": {"steps": 2}, "seed": i}))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 202);
            r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
        }));
    }
    let mut ids = Vec::new();
    for t in submits {
        ids.push(t.await.unwrap());
    }
    let start = Instant::now();
    loop {
        let list = get_json(&s.http, &format!("{}/v1/jobs?status=succeeded&limit=500", s.url)).await;
        if list["total"] == 50 {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "not all succeeded: {}",
            list["total"]
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let list = get_json(&s.http, &format!("{}/v1/jobs?limit=500", s.url)).await;
    assert_eq!(list["total"], 50, "none lost, none extra");
    for j in list["jobs"].as_array().unwrap() {
        assert!(ids.contains(&j["id"].as_str().unwrap().to_string()));
        assert_eq!(j["status"], "succeeded");
        // Claimed exactly once: a job taken by two workers would show two attempts.
        assert_eq!(j["attempts"], 1, "{j:#}");
        assert_eq!(j["progress"]["steps"], 2);
    }
    let metrics = s
        .http
        .get(format!("{}/metrics", s.url))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(
        metrics.contains("lightmapd_jobs_finished_total{outcome=\"succeeded\"} 50"),
        "{metrics}"
    );
    assert!(metrics.contains("lightmapd_workers 2"), "{metrics}");
    s.running.shutdown().await;
}

/// A `lightmapd serve` child process; its address is read from its first stdout line.
struct Process {
    child: Child,
    url: String,
}

fn spawn_serve(dir: &Path, workers: usize) -> Process {
    let mut child = Command::new(env!("CARGO_BIN_EXE_lightmapd"))
        .arg("serve")
        .args(["--listen", "127.0.0.1:0", "--workers", &workers.to_string()])
        .args(["--lease-seconds", "1", "--snapshot-interval-s", "0.2"])
        .arg("--data-dir")
        .arg(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .trim()
        .strip_prefix("lightmapd listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    Process { child, url }
}

/// A job's document, fetched from a plain thread (the process test has no runtime of
/// its own running).
fn blocking_job(url: &str, id: &str) -> Value {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let text = rt.block_on(async {
        reqwest::get(format!("{url}/v1/jobs/{id}"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap()
    });
    serde_json::from_str(&text).unwrap()
}

fn wait_for(url: &str, id: &str, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    loop {
        let j = blocking_job(url, id);
        if pred(&j) {
            return j;
        }
        assert!(start.elapsed() < DEADLINE, "job never became {what}: {j:#}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn sigterm(p: &Child) {
    let status = Command::new("kill")
        .args(["-TERM", &p.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

#[test]
fn killed_server_recovers_the_job_and_sigterm_hands_it_back() {
    let dir = tempfile::tempdir().unwrap();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();

    // 1. A bake is running when the server is killed with SIGKILL.
    let mut p = spawn_serve(dir.path(), 1);
    let id = rt.block_on(async {
        let http = reqwest::Client::new();
        let scene: Value = http
            .post(format!("{}/v1/scenes", p.url))
            .body(glb())
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let job: Value = http
            .post(format!("{}/v1/jobs", p.url))
            .json(&json!({"scene": scene["id"], "resolution": 16, "stop": {"seconds": 3}}))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        job["id"].as_str().unwrap().to_string()
    });
    wait_for(&p.url, &id, "running", |j| {
        j["status"] == "running" && j["progress"]["steps"].as_u64().unwrap_or(0) >= 1
    });
    p.child.kill().unwrap(); // SIGKILL
    p.child.wait().unwrap();

    // 2. Restarted with no workers: the dead worker's lease expires and the job is
    //    queued again, its first attempt counted.
    let mut p = spawn_serve(dir.path(), 0);
    let j = wait_for(&p.url, &id, "queued again", |j| j["status"] == "queued");
    assert_eq!(j["attempts"], 1);
    assert!(j["worker"].is_null());
    sigterm(&p.child);
    assert!(p.child.wait().unwrap().success());

    // 3. With a worker it runs again; SIGTERM mid-bake hands it back at once (the
    //    attempt is not counted) and the process exits cleanly.
    let mut p = spawn_serve(dir.path(), 1);
    wait_for(&p.url, &id, "running again", |j| {
        j["status"] == "running" && j["attempts"] == 2 && j["progress"]["steps"].as_u64().unwrap_or(0) >= 1
    });
    sigterm(&p.child);
    assert!(p.child.wait().unwrap().success(), "SIGTERM exits 0");
    let mut p = spawn_serve(dir.path(), 0);
    let j = blocking_job(&p.url, &id);
    assert_eq!(j["status"], "queued", "handed back without waiting for a lease: {j:#}");
    assert_eq!(j["attempts"], 1);
    sigterm(&p.child);
    assert!(p.child.wait().unwrap().success());

    // 4. And it completes.
    let mut p = spawn_serve(dir.path(), 1);
    let j = wait_for(&p.url, &id, "succeeded", |j| j["status"] == "succeeded");
    assert_eq!(j["attempts"], 2);
    let exr = rt.block_on(async {
        reqwest::get(format!("{}/v1/jobs/{id}/lightmap.exr", p.url))
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap()
    });
    assert!(is_exr(&exr));
    sigterm(&p.child);
    assert!(p.child.wait().unwrap().success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn openapi_lists_every_route() {
    let s = start(0, |_| {}).await;
    let doc = get_json(&s.http, &format!("{}/openapi.json", s.url)).await;
    let mut routes: Vec<String> = Vec::new();
    for (path, item) in doc["paths"].as_object().unwrap() {
        for method in item.as_object().unwrap().keys() {
            routes.push(format!("{} {path}", method.to_uppercase()));
        }
    }
    routes.sort();
    let got = routes.join("\n") + "\n";
    let snapshot = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/snapshots/openapi-routes.txt");
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() {
        std::fs::write(&snapshot, &got).unwrap();
    }
    let want = std::fs::read_to_string(&snapshot).unwrap();
    assert_eq!(
        got, want,
        "routes changed: rerun with UPDATE_SNAPSHOTS=1 and review the diff"
    );
    // Every listed route answers something other than "no route" on this server.
    for r in &routes {
        let (method, path) = r.split_once(' ').unwrap();
        let url = format!("{}{}", s.url, path.replace("{id}", "x"));
        let resp = s.http.request(method.parse().unwrap(), &url).send().await.unwrap();
        let status = resp.status();
        let body = resp.text().await.unwrap_or_default();
        assert!(!body.contains("no-route") && status != 405, "{r}: {status} {body}");
    }
    s.running.shutdown().await;
}

#[test]
fn worker_process_runs_the_jobs_of_an_api_only_server() {
    let dir = tempfile::tempdir().unwrap();
    let mut api = spawn_serve(dir.path(), 0);
    let mut worker = Command::new(env!("CARGO_BIN_EXE_lightmapd"))
        .arg("worker")
        .arg("--database-url")
        .arg(format!("sqlite://{}", dir.path().join("lightmapd.db").display()))
        .arg("--store")
        .arg(dir.path().join("objects"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let events = rt.block_on(async {
        let http = reqwest::Client::new();
        let scene: Value = http
            .post(format!("{}/v1/scenes", api.url))
            .body(glb())
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let job: Value = http
            .post(format!("{}/v1/jobs", api.url))
            .json(&json!({"scene": scene["id"], "resolution": 16, "stop": {"steps": 4}}))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        // The API process learns of the other process's progress by polling its database.
        read_events(
            &http,
            &format!("{}/v1/jobs/{}/events", api.url, job["id"].as_str().unwrap()),
        )
        .await
    });
    let (last, job) = events.last().unwrap();
    assert_eq!(last, "done");
    assert_eq!(job["progress"]["steps"], 4);
    assert_eq!(job["status"], "succeeded");
    sigterm(&worker);
    assert!(worker.wait().unwrap().success());
    sigterm(&api.child);
    assert!(api.child.wait().unwrap().success());

    // A database no store handles is bad input (exit code 2), named without its password.
    let out = Command::new(env!("CARGO_BIN_EXE_lightmapd"))
        .args(["worker", "--database-url", "mysql://u:secret@db/lightmapd", "--store"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("unsupported --database-url scheme \"mysql\""),
        "{stderr}"
    );
    assert!(!stderr.contains("secret"), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gltf_with_external_buffer_uploads_as_multipart_and_bakes() {
    let s = start(1, |_| {}).await;
    let (mut gltf, bin) = lightmapd::engine::scene::build::cornell_box().to_gltf();
    gltf["buffers"][0]["uri"] = json!("cornell%20box.bin");
    let gltf_bytes = serde_json::to_vec(&gltf).unwrap();
    let dir = s._dir.path().join("upload");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("cornell.gltf"), &gltf_bytes).unwrap();
    std::fs::write(dir.join("cornell box.bin"), &bin).unwrap();

    // A part the .gltf refers to is missing: 422 naming the URI.
    let form = reqwest::multipart::Form::new().part(
        "cornell.gltf",
        reqwest::multipart::Part::bytes(gltf_bytes.clone()).file_name("cornell.gltf"),
    );
    expect_problem(
        s.http.post(format!("{}/v1/scenes", s.url)).multipart(form),
        422,
        problem(
            422,
            "Unprocessable Entity",
            "invalid-field",
            "cornell.gltf refers to \"cornell%20box.bin\", which is not among the uploaded parts",
            Some("buffers[0].uri"),
        ),
    )
    .await;

    // `lightmapd submit` sends the .gltf and the file it names.
    let (url, path) = (s.url.clone(), dir.join("cornell.gltf"));
    let output = tokio::task::spawn_blocking(move || {
        Command::new(env!("CARGO_BIN_EXE_lightmapd"))
            .arg("submit")
            .arg(path)
            .args(["--server", &url, "--resolution", "16", "--steps", "2", "--wait"])
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let job: Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(job["status"], "succeeded");
    let scene = get_json(
        &s.http,
        &format!("{}/v1/scenes/{}", s.url, job["scene"].as_str().unwrap()),
    )
    .await;
    assert_eq!(scene["format"], "gltf");
    assert_eq!(scene["files"], json!(["cornell.gltf", "cornell box.bin"]));
    assert_eq!(scene["report"]["has_lightmap_uvs"], true);
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scene_without_lightmap_uvs_gets_them_generated_and_returned() {
    use lightmapd::engine::scene::build::{cornell_box, remove_lightmap_uvs, write_glb};
    let s = start(1, |_| {}).await;
    let (mut gltf, buffer) = cornell_box().to_gltf();
    remove_lightmap_uvs(&mut gltf, None);
    let r = s
        .http
        .post(format!("{}/v1/scenes", s.url))
        .body(write_glb(&gltf, &buffer))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let scene: Value = r.json().await.unwrap();
    assert_eq!(scene["report"]["has_lightmap_uvs"], false);
    // The job's UV fields (issue 19): refused at submit, naming the field, when they
    // cannot work for this scene or are malformed.
    for (body, field, detail) in [
        (
            json!({"lightmap_uvs": "keep"}),
            "lightmap_uvs",
            "lightmap_uvs is keep, and the scene has meshes without TEXCOORD_1 (its report's warnings name them): use generate-missing",
        ),
        (
            json!({"lightmap_uvs": "sometimes"}),
            "lightmap_uvs",
            "lightmap_uvs must be keep, generate-missing, regenerate-all or repack-instances, got \"sometimes\"",
        ),
        (
            json!({"texels_per_unit": 0.0}),
            "texels_per_unit",
            "texels_per_unit must be a positive number, got 0",
        ),
        (
            json!({"max_page_size": 16}),
            "max_page_size",
            "max_page_size 16 is below resolution 32: pages start resolution wide and grow up to max_page_size",
        ),
        (
            json!({"max_page_size": 20000}),
            "max_page_size",
            "max_page_size must be between 1 and 4096, got 20000",
        ),
    ] {
        let mut job = json!({"scene": scene["id"], "resolution": 32, "stop": {"steps": 2}});
        job.as_object_mut().unwrap().extend(body.as_object().unwrap().clone());
        let r = s
            .http
            .post(format!("{}/v1/jobs", s.url))
            .json(&job)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 422);
        let p: Value = r.json().await.unwrap();
        assert_eq!(
            (p["field"].as_str(), p["detail"].as_str()),
            (Some(field), Some(detail)),
            "{p:#}"
        );
    }
    // A density the job asks for is the one the generated UVs get.
    let id = s
        .submit(json!({"scene": scene["id"], "resolution": 32, "stop": {"steps": 2}, "texels_per_unit": 6.0}))
        .await;
    let job = s
        .wait_job(&id, "finished", |j| j["status"] != "queued" && j["status"] != "running")
        .await;
    assert_eq!(job["status"], "succeeded", "{job:#}");
    assert_eq!(job["summary"]["generated_uvs"]["texels_per_metre"], 6.0, "{job:#}");
    let glb = s
        .http
        .get(format!("{}/v1/jobs/{id}/scene.glb", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(glb.status(), 200);
    let bytes = glb.bytes().await.unwrap();
    let (_, report) = lightmapd::engine::scene::import_slice(&bytes, None).unwrap();
    assert!(
        report.has_lightmap_uvs,
        "the returned scene carries the generated TEXCOORD_1"
    );
    // While a bake runs (issue 23): the scene with its generated UVs is stored once they
    // are made, the job's plan names it, and it is the scene the final lightmap fits.
    let long = s
        .submit(json!({"scene": scene["id"], "resolution": 32, "stop": {"seconds": 60, "steps": 1000000}, "texels_per_unit": 6.0}))
        .await;
    let running = s
        .wait_job(&long, "the generated scene in the plan", |j| {
            j["status"] == "running" && j["plan"]["generated_scene"].is_string()
        })
        .await;
    assert_eq!(running["plan"]["generated_scene"], format!("/v1/jobs/{long}/scene.glb"));
    let early = s
        .http
        .get(format!("{}/v1/jobs/{long}/scene.glb", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(early.status(), 200, "while the job is running");
    let early = early.bytes().await.unwrap();
    assert_eq!(
        early, bytes,
        "the same scene and UVs as the finished job's (same density)"
    );
    let c = s
        .http
        .post(format!("{}/v1/jobs/{long}/cancel", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(c.status(), 202);
    s.running.shutdown().await;
}

/// Snapshot files (EXR and PNG) in a job's folder of the local store, by number.
fn snapshot_files(dir: &Path, job: &str) -> (std::collections::BTreeSet<u32>, usize) {
    let folder = dir.join(format!("objects/jobs/{job}/snapshots"));
    let mut numbers = std::collections::BTreeSet::new();
    let mut files = 0;
    for e in std::fs::read_dir(&folder).into_iter().flatten() {
        let name = e.unwrap().file_name().to_string_lossy().to_string();
        // `NAME#N` is a write in progress (the local store's temporary file).
        let Some((n, ext)) = name.split_once('.') else { continue };
        if (ext == "exr" || ext == "png") && !name.contains('#') {
            numbers.insert(n.parse::<u32>().unwrap());
            files += 1;
        }
    }
    (numbers, files)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_long_bake_keeps_at_most_the_configured_snapshots() {
    const KEEP: u32 = 4;
    let s = start(1, |c| {
        c.snapshot_interval = Duration::from_millis(20);
        c.snapshot_keep = KEEP;
    })
    .await;
    let scene = s.upload().await;
    // Not beside the long CPU path step of `a_long_step_shows_its_progress_in_the_job`:
    // sharing the 2 cores with it, 3 s stored 11 snapshots, not the 13 asked for.
    let _cpu = crate::CPU_HEAVY.lock().await;
    let id = s
        .submit(json!({"scene": scene, "resolution": 16, "stop": {"seconds": 4.0, "steps": 1000000}}))
        .await;
    // While it bakes: never more than KEEP pairs, plus the one being written for the
    // moment between its store and the deletion it makes due.
    let mut most = 0;
    loop {
        let (_, files) = snapshot_files(s._dir.path(), &id);
        most = most.max(files);
        assert!(files <= 2 * (KEEP as usize + 1), "{files} snapshot files");
        let j = s.job(&id).await;
        if ["succeeded", "failed", "cancelled"].contains(&j["status"].as_str().unwrap()) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let j = s.job(&id).await;
    assert_eq!(j["status"], "succeeded", "{j:#}");
    let n = j["snapshots"].as_u64().unwrap() as u32;
    assert!(n > 3 * KEEP, "a long bake stores many snapshots: {n}");
    let (numbers, files) = snapshot_files(s._dir.path(), &id);
    let kept = lightmapd::service::store::kept_snapshots(n, KEEP);
    eprintln!("{n} snapshots stored, kept {kept:?}, at most {most} files at once");
    assert_eq!(numbers.into_iter().collect::<Vec<_>>(), kept);
    assert_eq!(files, 2 * kept.len());
    assert!(kept.len() <= KEEP as usize && kept.last() == Some(&n));

    // A thinned snapshot is 404 naming the retention; a kept one and the latest download.
    let gone = (1..n).find(|k| !kept.contains(k)).unwrap();
    let r = s
        .http
        .get(format!("{}/v1/jobs/{id}/lightmap.exr?snapshot={gone}", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    let p: Value = r.json().await.unwrap();
    let list: Vec<String> = kept.iter().map(u32::to_string).collect();
    assert_eq!(
        p["detail"],
        format!(
            "snapshot {gone} of job {id} was removed by snapshot retention (--snapshot-keep {KEEP}); kept: {}",
            list.join(", ")
        )
    );
    for q in [format!("?snapshot={}", kept[0]), "?snapshot=latest".into()] {
        let r = s
            .http
            .get(format!("{}/v1/jobs/{id}/lightmap.exr{q}", s.url))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{q}");
    }
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deleting_a_job_and_the_retention_sweeper_remove_its_artifacts() {
    let s = start(1, |c| {
        c.job_retention = Some(Duration::from_millis(1500));
        c.sweep_interval = Duration::from_millis(100);
    })
    .await;
    let scene = s.upload().await;
    let body = json!({"scene": scene, "resolution": 16, "stop": {"steps": 4}});
    let (a, b) = (s.submit(body.clone()).await, s.submit(body).await);
    for id in [&a, &b] {
        s.wait_job(id, "succeeded", |j| j["status"] == "succeeded").await;
    }
    let b_done = Instant::now();
    let folder = |id: &str| s._dir.path().join(format!("objects/jobs/{id}"));
    assert!(folder(&a).join("lightmap-0.exr").exists());
    // DELETE: 204, the folder is gone, the job is 404 (and a second DELETE too).
    let r = s.http.delete(format!("{}/v1/jobs/{a}", s.url)).send().await.unwrap();
    assert_eq!(r.status(), 204);
    assert!(!folder(&a).exists(), "artifacts of a deleted job remain");
    let r = s.http.get(format!("{}/v1/jobs/{a}", s.url)).send().await.unwrap();
    assert_eq!(r.status(), 404);
    let r = s.http.delete(format!("{}/v1/jobs/{a}", s.url)).send().await.unwrap();
    assert_eq!(r.status(), 404);
    // The store's usage is in /metrics: the scene's bytes exactly.
    let metrics = || async {
        s.http
            .get(format!("{}/metrics", s.url))
            .send()
            .await
            .unwrap()
            .text()
            .await
            .unwrap()
    };
    let scene_line = format!("lightmapd_store_bytes{{kind=\"scenes\"}} {}", glb().len());
    let start_wait = Instant::now();
    loop {
        let m = metrics().await;
        if m.contains(&scene_line) {
            break;
        }
        assert!(start_wait.elapsed() < DEADLINE, "{m}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // B is still within its retention: downloadable. After it, the sweeper removes it.
    let r = s
        .http
        .get(format!("{}/v1/jobs/{b}/lightmap.exr", s.url))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let start_wait = Instant::now();
    loop {
        let r = s.http.get(format!("{}/v1/jobs/{b}", s.url)).send().await.unwrap();
        if r.status() == 404 {
            break;
        }
        assert!(start_wait.elapsed() < DEADLINE, "never swept");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // Observed as succeeded at or after it finished: the retention (1.5 s) had passed.
    assert!(
        b_done.elapsed() >= Duration::from_millis(1400),
        "swept before its retention ended"
    );
    assert!(!folder(&b).exists(), "artifacts of an expired job remain");
    let start_wait = Instant::now();
    loop {
        let m = metrics().await;
        if m.contains("lightmapd_store_objects{kind=\"jobs\"} 0") {
            assert!(m.contains("lightmapd_jobs_expired_total 1\n"), "{m}");
            break;
        }
        assert!(start_wait.elapsed() < DEADLINE, "{m}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    s.running.shutdown().await;
}

/// Issue 19 point 7 in the service: a job whose scene needs two pages (the ground's
/// authored page, the ball's generated one) stores and serves both pages and the
/// manifest, lists them in its summary, keeps `lightmap.exr` as page 0, serves the
/// console's float lightmap as the two pages one under another, and answers exact
/// problems for pages and files it does not have.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_of_several_pages_serves_every_page_and_the_manifest() {
    use lightmapd::engine::scene::build::{remove_lightmap_uvs, write_glb};
    use lightmapd::engine::scene::library::sphere_over_plane;
    let s = start(1, |_| {}).await;
    let (mut json, bin) = sphere_over_plane().to_gltf();
    remove_lightmap_uvs(&mut json, Some(&[1]));
    let r = s
        .http
        .post(format!("{}/v1/scenes", s.url))
        .header("content-type", "model/gltf-binary")
        .body(write_glb(&json, &bin))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let scene = r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let id = s
        .submit(json!({"scene": scene, "resolution": 32, "stop": {"steps": 2}, "lighting": {"sky": {"radiance": [1, 1, 1]}}}))
        .await;
    let job = s.wait_job(&id, "succeeded", |j| j["status"] == "succeeded").await;
    let pages = job["summary"]["pages"].as_array().unwrap();
    assert_eq!(
        pages.iter().map(|p| p["file"].clone()).collect::<Vec<_>>(),
        vec![json!("lightmap-0.exr"), json!("lightmap-1.exr")]
    );
    assert_eq!(job["summary"]["atlas"]["pages"], 2);

    let get = |path: String| s.http.get(format!("{}{path}", s.url)).send();
    let mut bytes = Vec::new();
    for file in ["lightmap-0.exr", "lightmap-1.exr"] {
        let r = get(format!("/v1/jobs/{id}/{file}")).await.unwrap();
        assert_eq!(r.status(), 200, "{file}");
        assert_eq!(r.headers()["content-type"], "image/x-exr");
        let b = r.bytes().await.unwrap();
        assert_eq!(b[..4], [0x76, 0x2f, 0x31, 0x01], "{file} is an OpenEXR file");
        bytes.push(b);
    }
    assert_ne!(bytes[0], bytes[1]);
    let first = get(format!("/v1/jobs/{id}/lightmap.exr"))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    assert_eq!(first, bytes[0], "lightmap.exr is page 0");

    let r = get(format!("/v1/jobs/{id}/lightmaps.json")).await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "application/json");
    let manifest: Value = r.json().await.unwrap();
    assert_eq!(manifest["format"], "lightmapd.lightmaps/1");
    let key = |pages: &Value| -> Vec<(Value, Value, Value)> {
        pages
            .as_array()
            .unwrap()
            .iter()
            .map(|p| (p["file"].clone(), p["first_row"].clone(), p["valid_texels"].clone()))
            .collect()
    };
    assert_eq!(key(&manifest["pages"]), key(&job["summary"]["pages"]));
    assert_eq!(
        manifest["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n["page"].clone())
            .collect::<Vec<_>>(),
        vec![json!(0), json!(1)]
    );

    let r = get(format!("/v1/jobs/{id}/lightmap.rgba16f")).await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(
        (
            r.headers()["x-lightmap-width"].to_str().unwrap(),
            r.headers()["x-lightmap-height"].to_str().unwrap()
        ),
        ("32", "64")
    );
    assert_eq!(r.bytes().await.unwrap().len(), 32 * 64 * 8);

    let missing = [
        (
            "lightmap-2.exr".to_string(),
            format!("job {id} has 2 page(s); there is no page 2"),
        ),
        (
            "lightmap-01.exr".to_string(),
            "a job has no file \"lightmap-01.exr\": its files are lightmap-P.exr (P = 0, 1, ...) and lightmaps.json"
                .to_string(),
        ),
        (
            "notes.txt".to_string(),
            "a job has no file \"notes.txt\": its files are lightmap-P.exr (P = 0, 1, ...) and lightmaps.json"
                .to_string(),
        ),
    ];
    for (file, detail) in missing {
        expect_problem(
            s.http.get(format!("{}/v1/jobs/{id}/{file}", s.url)),
            404,
            problem(404, "Not Found", "not-found", &detail, None),
        )
        .await;
    }
    s.running.shutdown().await;
}

/// Progress inside a step over HTTP (issue 19 point 10): one CPU `path` step of the
/// bundled Cornell box at 64² with 1024 samples a texel takes seconds; while it runs the
/// job's progress moves with it (`step_fraction` from 0 up to 1, `fraction` with it
/// since the job stops after that one step, `elapsed_s` live), never back, and the
/// finished job's progress has no step in flight.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_long_step_shows_its_progress_in_the_job() {
    let _cpu = crate::CPU_HEAVY.lock().await;
    let s = start(1, |_| {}).await;
    let scene = s.upload().await;
    let id = s
        .submit(
            json!({"scene": scene, "technique": "path", "resolution": 64, "stop": {"steps": 1},
                       "params": {"samples_per_step": 1024, "device": "cpu"}, "denoise": "none"}),
        )
        .await;
    let started = Instant::now();
    let mut seen: Vec<(f64, f64, f64)> = Vec::new();
    let job = loop {
        let j = s.job(&id).await;
        if j["status"] == "succeeded" || j["status"] == "failed" {
            break j;
        }
        let p = &j["progress"];
        if j["status"] == "running"
            && let Some(within) = p["step_fraction"].as_f64()
        {
            assert_eq!(p["steps"], 0, "{p}");
            seen.push((
                within,
                p["fraction"].as_f64().unwrap(),
                p["elapsed_s"].as_f64().unwrap(),
            ));
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "the job did not end: {j:#}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(job["status"], "succeeded", "{job:#}");
    assert_eq!(job["progress"]["steps"], 1, "{job:#}");
    assert!(job["progress"].get("step_fraction").is_none(), "{job:#}");
    let mut distinct = seen.clone();
    distinct.dedup_by(|a, b| a.0 == b.0);
    assert!(
        distinct.len() >= 3,
        "the job's progress did not move inside the step: {seen:?}"
    );
    for (within, fraction, elapsed) in &seen {
        assert!(*within > 0.0 && *within < 1.0, "{seen:?}");
        assert_eq!(within, fraction, "one step asked for: the step's share is the job's");
        assert!(*elapsed > 0.0, "{seen:?}");
    }
    assert!(
        seen.windows(2).all(|w| w[0].0 <= w[1].0 && w[0].2 <= w[1].2),
        "progress went back: {seen:?}"
    );
    eprintln!(
        "step_fraction seen over HTTP: {:?}",
        distinct.iter().map(|d| d.0).collect::<Vec<_>>()
    );
}
