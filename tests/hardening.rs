//! Issue 12 over real HTTP: every limit answers with its status and exact problem+json
//! body (413, 422 naming the field, 429 and 503 with `Retry-After`, 408), plain-text
//! errors of axum itself come back as problem+json, multipart names cannot be paths, and
//! bearer tokens guard every route but `/healthz` and the dashboard page and keep one token's scenes and jobs
//! invisible (404) to another. Servers run without workers: nothing here needs a bake.

mod service_common;

use std::process::Command;
use std::time::Duration;

use base64::Engine as _;
use futures_util::StreamExt;
use lightmapd::service::Limits;
use serde_json::{Value, json};
use service_common::*;

fn invalid(field: &str, detail: &str) -> Value {
    problem(422, "Unprocessable Entity", "invalid-field", detail, Some(field))
}

/// The Cornell box with one 64x64 PNG texture (only its size matters here).
fn textured_glb() -> Vec<u8> {
    use lightmapd::engine::scene::build::{cornell_box, write_glb};
    let (mut gltf, bin) = cornell_box().to_gltf();
    let img = image::RgbaImage::from_pixel(64, 64, image::Rgba([200, 100, 50, 255]));
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let uri = format!(
        "data:image/png;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&png)
    );
    gltf["images"] = json!([{ "uri": uri }]);
    gltf["textures"] = json!([{ "source": 0 }]);
    write_glb(&gltf, &bin)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limits_answer_with_their_status_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 0);
    config.limits = Limits {
        max_body_bytes: 4096,
        max_texture_side: 32,
        max_resolution: 1024,
        max_job_steps: 1000,
        max_job_seconds: 60.0,
        max_queued_per_client: 2,
        max_event_streams: 1,
        max_job_memory_bytes: 200 << 20,
        ..Limits::default()
    };
    let s = Server::start(config).await;
    let scene = s.upload(None).await;
    let job = |body: Value| s.post("/v1/jobs").json(&body);

    // Scene content over a limit: 422 naming what.
    expect_problem(
        s.post("/v1/scenes").body(textured_glb()),
        422,
        invalid(
            "textures",
            "image 0 is 64x64 pixels, more than the limit of 32 per side of this server (--max-texture-size)",
        ),
    )
    .await;

    // The job's own limits.
    expect_problem(
        job(json!({"scene": scene, "resolution": 2048})),
        422,
        invalid("resolution", "resolution must be between 1 and 1024, got 2048"),
    )
    .await;
    expect_problem(
        job(json!({"scene": scene, "resolution": 16, "stop": {"steps": 1001}})),
        422,
        invalid(
            "stop.steps",
            "stop.steps must be at most 1000 on this server (--max-job-steps), got 1001",
        ),
    )
    .await;
    expect_problem(
        job(json!({"scene": scene, "resolution": 16, "stop": {"seconds": 61}})),
        422,
        invalid(
            "stop.seconds",
            "stop.seconds must be at most 60 on this server (--max-job-seconds), got 61",
        ),
    )
    .await;
    // 1024² texels: 64 MiB for the process plus 208 bytes a texel (engine::footprint)
    // is 272 MiB, over the 200 MiB limit; the 32 triangles add next to nothing.
    expect_problem(
        job(json!({"scene": scene, "resolution": 1024, "stop": {"steps": 1}})),
        422,
        invalid(
            "resolution",
            "the job needs an estimated 272 MiB (1024² texels, 32 triangles), more than this server's limit of 200 MiB per job (--max-job-memory-mb): lower the resolution",
        ),
    )
    .await;

    // A job body over --max-body-bytes: axum's own 413, as problem+json.
    let padding = "x".repeat(5000);
    expect_problem(
        s.post("/v1/jobs")
            .header("content-type", "application/json")
            .body(format!("{{\"scene\": \"{padding}\"}}")),
        413,
        problem(
            413,
            "Payload Too Large",
            "too-large",
            "the request body is larger than this server's limit of 4096 bytes (--max-body-bytes)",
            None,
        ),
    )
    .await;
    // A path axum cannot decode (invalid UTF-8): its plain-text 400, as problem+json.
    let r = s.get("/v1/jobs/%FF").send().await.unwrap();
    assert_eq!(r.status(), 400);
    assert_eq!(r.headers()["content-type"], "application/problem+json");
    let p: Value = r.json().await.unwrap();
    assert_eq!(p["type"], "urn:lightmapd:problem:bad-request");
    assert!(p["detail"].as_str().unwrap().contains("UTF-8"), "{p}");
    // A malformed query value is a 422 naming the parameter.
    expect_problem(
        s.get("/v1/jobs?limit=%FF"),
        422,
        invalid("limit", "limit must be 1 to 500, got \"\u{fffd}\""),
    )
    .await;

    // A job without seconds gets the server's budget; the default stop is replaced by it.
    let first = s
        .submit(None, json!({"scene": scene, "resolution": 16, "stop": {"steps": 5}}))
        .await;
    let j: Value = s
        .get(&format!("/v1/jobs/{first}"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(j["spec"]["stop"], json!({"steps": 5, "seconds": 60.0}));

    // Queue length per client: the third queued job is 429 with Retry-After.
    s.submit(None, json!({"scene": scene, "resolution": 16, "stop": {"steps": 5}}))
        .await;
    let headers = expect_problem(
        job(json!({"scene": scene, "resolution": 16, "stop": {"steps": 5}})),
        429,
        problem(
            429,
            "Too Many Requests",
            "too-many-jobs",
            "2 of your jobs are queued, this server's limit per client (--max-queued-per-client); retry when one has started",
            None,
        ),
    )
    .await;
    assert_eq!(headers["retry-after"], "10");

    // Event streams: one may be open; the second is 503 with Retry-After; once the first
    // is closed a new one is accepted.
    let open = s.get(&format!("/v1/jobs/{first}/events")).send().await.unwrap();
    assert_eq!(open.status(), 200);
    let mut stream = open.bytes_stream();
    assert!(stream.next().await.is_some(), "the first event arrives");
    let headers = expect_problem(
        s.get(&format!("/v1/jobs/{first}/events")),
        503,
        problem(
            503,
            "Service Unavailable",
            "too-many-streams",
            &format!(
                "1 event streams are open, this server's limit (--max-event-streams); poll GET /v1/jobs/{first} or retry later"
            ),
            None,
        ),
    )
    .await;
    assert_eq!(headers["retry-after"], "10");
    drop(stream);
    let start = std::time::Instant::now();
    loop {
        let r = s.get(&format!("/v1/jobs/{first}/events")).send().await.unwrap();
        if r.status() == 200 {
            break;
        }
        assert!(start.elapsed() < DEADLINE, "the stream's permit was never given back");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    // Multipart part names are plain file names, never paths.
    for name in ["../../etc/passwd", "sub/scene.gltf", ".hidden.gltf", "C:x.gltf"] {
        let form = reqwest::multipart::Form::new().part(
            "scene",
            reqwest::multipart::Part::bytes(b"{}".to_vec()).file_name(name.to_string()),
        );
        expect_problem(
            s.post("/v1/scenes").multipart(form),
            422,
            invalid(
                "files",
                &format!("part name {name:?}: give each part the plain file name the .gltf uses"),
            ),
        )
        .await;
    }
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_request_times_out_with_408_and_a_big_scene_is_422() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 0);
    config.limits.request_timeout = Duration::from_millis(300);
    config.limits.max_triangles = 31;
    let s = Server::start(config).await;
    // The Cornell box has 32 triangles.
    expect_problem(
        s.post("/v1/scenes").body(cornell_glb()),
        422,
        invalid(
            "triangles",
            "the scene has more than 31 triangles (instances counted once each), the limit of this server (--max-triangles)",
        ),
    )
    .await;
    // A body that takes longer to arrive than the server waits.
    let slow = futures_util::stream::once(async {
        tokio::time::sleep(Duration::from_secs(2)).await;
        Ok::<_, std::io::Error>(bytes::Bytes::from_static(b"glTF"))
    });
    expect_problem(
        s.post("/v1/scenes")
            .header("content-type", "model/gltf-binary")
            .body(reqwest::Body::wrap_stream(slow)),
        408,
        problem(
            408,
            "Request Timeout",
            "timeout",
            "the request took longer than this server's limit of 0.3 s (--request-timeout-s)",
            None,
        ),
    )
    .await;
    // Quick requests are unaffected.
    assert_eq!(s.get("/healthz").send().await.unwrap().status(), 200);
    s.running.shutdown().await;
}

fn token_cli(dir: &std::path::Path, args: &[&str]) -> std::process::Output {
    Command::new(bin())
        .arg("token")
        .args(args)
        .arg("--data-dir")
        .arg(dir)
        .output()
        .unwrap()
}

fn create_token(dir: &std::path::Path, name: &str) -> String {
    let out = token_cli(dir, &["create", "--name", name]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let secret = String::from_utf8(out.stdout).unwrap().trim().to_string();
    assert!(secret.starts_with("lmd_") && secret.len() == 68, "{secret}");
    secret
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_guard_every_route_and_keep_clients_apart() {
    let dir = tempfile::tempdir().unwrap();
    let (alice, bob) = (create_token(dir.path(), "alice"), create_token(dir.path(), "bob"));
    // Stored hashed: the database file never holds a secret.
    let db = std::fs::read(dir.path().join("lightmapd.db")).unwrap();
    let wal = std::fs::read(dir.path().join("lightmapd.db-wal")).unwrap_or_default();
    for secret in [&alice, &bob] {
        let needle = secret.as_bytes();
        for file in [&db, &wal] {
            assert!(
                !file.windows(needle.len()).any(|w| w == needle),
                "a secret is stored in clear"
            );
        }
    }
    let mut config = test_config(dir.path(), 0);
    config.auth = true;
    let s = Server::start(config).await;

    // Without a token (or with a wrong one) every route but /healthz and the dashboard's
    // page is 401.
    let needs = problem(
        401,
        "Unauthorized",
        "unauthorized",
        "this server requires a bearer token: send `Authorization: Bearer TOKEN`",
        None,
    );
    for path in [
        "/v1/jobs",
        "/v1/jobs/x",
        "/v1/scenes/x",
        "/metrics",
        "/openapi.json",
        "/nope",
    ] {
        let h = expect_problem(s.get(path), 401, needs.clone()).await;
        assert_eq!(h["www-authenticate"], "Bearer realm=\"lightmapd\"", "{path}");
    }
    expect_problem(s.post("/v1/scenes").body(cornell_glb()), 401, needs.clone()).await;
    expect_problem(
        s.get("/v1/jobs").bearer_auth("lmd_wrong"),
        401,
        problem(401, "Unauthorized", "unauthorized", "unknown or revoked token", None),
    )
    .await;
    assert_eq!(s.get("/healthz").send().await.unwrap().status(), 200);
    // The page is static; what it shows comes from the API, with the token it asks for.
    let page = s.get("/").send().await.unwrap();
    assert_eq!(page.status(), 200);
    let html = page.text().await.unwrap();
    assert!(
        html.contains("'Authorization': 'Bearer ' + token"),
        "the page sends the token"
    );
    expect_problem(s.post("/"), 401, needs.clone()).await;
    assert_eq!(
        s.get("/metrics").bearer_auth(&alice).send().await.unwrap().status(),
        200
    );

    // Alice's scene and job.
    let scene = s.upload(Some(&alice)).await;
    let job = s
        .submit(
            Some(&alice),
            json!({"scene": scene, "resolution": 16, "stop": {"steps": 2}}),
        )
        .await;
    let mine: Value = s
        .get(&format!("/v1/jobs/{job}"))
        .bearer_auth(&alice)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(mine["status"], "queued");

    // Bob sees none of it: the same 404 as for ids that do not exist.
    let no_job = problem(
        404,
        "Not Found",
        "not-found",
        &format!("no job with id \"{job}\""),
        None,
    );
    for path in ["", "/events", "/lightmap.exr", "/preview.png", "/scene.glb"] {
        expect_problem(
            s.get(&format!("/v1/jobs/{job}{path}")).bearer_auth(&bob),
            404,
            no_job.clone(),
        )
        .await;
    }
    expect_problem(
        s.post(&format!("/v1/jobs/{job}/cancel")).bearer_auth(&bob),
        404,
        no_job.clone(),
    )
    .await;
    let no_scene = problem(
        404,
        "Not Found",
        "not-found",
        &format!("no scene with id \"{scene}\""),
        None,
    );
    expect_problem(
        s.get(&format!("/v1/scenes/{scene}")).bearer_auth(&bob),
        404,
        no_scene.clone(),
    )
    .await;
    expect_problem(
        s.http.delete(format!("{}/v1/scenes/{scene}", s.url)).bearer_auth(&bob),
        404,
        no_scene,
    )
    .await;
    expect_problem(
        s.post("/v1/jobs")
            .bearer_auth(&bob)
            .json(&json!({"scene": scene, "resolution": 16})),
        422,
        invalid("scene", &format!("no scene with id \"{scene}\"; upload it first")),
    )
    .await;
    let list: Value = s
        .get("/v1/jobs")
        .bearer_auth(&bob)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["total"], 0);
    let list: Value = s
        .get("/v1/jobs")
        .bearer_auth(&alice)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["total"], 1);
    // The same bytes from Bob are Bob's own scene, with another id.
    let bobs = s.upload(Some(&bob)).await;
    assert_ne!(bobs, scene);

    // list shows both; revoking Alice locks her out at her next request.
    let out = token_cli(dir.path(), &["list"]);
    let listing = String::from_utf8(out.stdout).unwrap();
    assert_eq!(listing.lines().count(), 2, "{listing}");
    assert!(listing.lines().all(|l| l.contains("\tactive")), "{listing}");
    let out = token_cli(dir.path(), &["revoke", "alice"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    expect_problem(
        s.get(&format!("/v1/jobs/{job}")).bearer_auth(&alice),
        401,
        problem(401, "Unauthorized", "unauthorized", "unknown or revoked token", None),
    )
    .await;
    let out = token_cli(dir.path(), &["revoke", "alice"]);
    assert_eq!(out.status.code(), Some(2), "revoking twice is bad input");
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_with_less_memory_fails_a_job_over_its_limit() {
    let dir = tempfile::tempdir().unwrap();
    // The API accepts the job (its limit is the default 8 GiB)...
    let s = Server::start(test_config(dir.path(), 0)).await;
    let scene = s.upload(None).await;
    let big = s
        .submit(None, json!({"scene": scene, "resolution": 1024, "stop": {"steps": 1}}))
        .await;
    // ...a worker process with 200 MiB refuses it with the estimate, before baking.
    let mut config = test_config(dir.path(), 1);
    config.limits.max_job_memory_bytes = 200 << 20;
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let workers = tokio::spawn(lightmapd::service::run_workers(config, async {
        let _ = stopped.await;
    }));
    let j = s.wait_end(&big).await;
    assert_eq!(j["status"], "failed");
    assert_eq!(
        j["failure"],
        "the job needs an estimated 272 MiB, more than this worker's limit of 200 MiB (--max-job-memory-mb)"
    );
    let _ = stop.send(());
    workers.await.unwrap().unwrap();
    s.running.shutdown().await;
}

/// `lightmapd submit` against a full queue: 429 is "busy", not bad input. With
/// `--retry-for 0` the client fails at once with exit code 1; with time to wait it follows
/// `Retry-After` (10 s) and gets in once a slot frees.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn submit_waits_out_a_full_queue() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 0);
    config.limits = Limits {
        max_queued_per_client: 1,
        ..Limits::default()
    };
    let s = Server::start(config).await;
    let scene = s.upload(None).await;
    let first = s
        .submit(None, json!({"scene": scene, "resolution": 16, "stop": {"steps": 2}}))
        .await;
    let submit = |retry_for: &str| {
        Command::new(bin())
            .arg("submit")
            .arg(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.glb"))
            .args(["--server", &s.url, "--resolution", "16", "--steps", "2"])
            .args(["--retry-for", retry_for])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    };

    let refused = tokio::task::spawn_blocking({
        let child = submit("0");
        move || child.wait_with_output().unwrap()
    })
    .await
    .unwrap();
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert_eq!(refused.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("submit: 429 "), "{stderr}");

    let waiting = submit("60");
    // The client's first try is refused; cancelling the queued job frees the slot.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let resp = s.post(&format!("/v1/jobs/{first}/cancel")).send().await.unwrap();
    assert!(resp.status().is_success(), "{}", resp.status());
    let started = std::time::Instant::now();
    let out = tokio::task::spawn_blocking(move || waiting.wait_with_output().unwrap())
        .await
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    assert!(
        stderr.contains("submit: the server is busy (429); trying again in 10 s"),
        "{stderr}"
    );
    assert!(started.elapsed() < Duration::from_secs(20), "{stderr}");
    let printed: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(printed["status"], "queued");
    let list: Value = s.get("/v1/jobs").send().await.unwrap().json().await.unwrap();
    assert_eq!(list["total"], 2, "the cancelled job and the one that waited");
}
