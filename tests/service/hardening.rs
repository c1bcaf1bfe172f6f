//! Issue 12 over real HTTP: every limit answers with its status and exact problem+json
//! body (413, 422 naming the field, 429 and 503 with `Retry-After`, 408), plain-text
//! errors of axum itself come back as problem+json, multipart names cannot be paths, and
//! bearer tokens guard every route but `/healthz` and the dashboard page and keep one token's scenes and jobs
//! invisible (404) to another. Most servers run without workers: little here needs a bake.
//!
//! Issue 24: `serve` refuses a network address without `--auth` (exit code 2, exact
//! message) unless `--insecure-no-auth`; admin and editor roles (403 for a priority above
//! the cap); unique token names and unambiguous revocation; tokens from a secret file,
//! rotated; a non-object job body is 422; `submit --wait` waits out a 503 on its event
//! stream; and PostgreSQL over TLS as `sslmode` says (against the local server's
//! self-signed certificate).

use crate::service_common;

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
    // 1024² texels: 64 MiB for the process plus 1140 bytes a texel (engine::footprint:
    // 244 for the texel set, its accumulators and the written images, 896 for the
    // denoiser's working set and OIDN's) is 1204 MiB, over the 200 MiB limit; the 32
    // triangles add next to nothing.
    expect_problem(
        job(json!({"scene": scene, "resolution": 1024, "stop": {"steps": 1}})),
        422,
        invalid(
            "resolution",
            "the job needs an estimated 1204 MiB (1024² texels, 32 triangles), more than this server's limit of 200 MiB per job (--max-job-memory-mb): lower the resolution",
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

/// Files left in the server's upload spool (every upload's folder is removed when its
/// request ends, whatever happened).
fn spool_entries(dir: &std::path::Path) -> usize {
    std::fs::read_dir(dir.join("spool")).map(|d| d.count()).unwrap_or(0)
}

/// A body sent as `chunks` pieces, each after `gap`.
fn trickled(bytes: Vec<u8>, chunks: usize, gap: Duration) -> reqwest::Body {
    let size = bytes.len().div_ceil(chunks);
    let pieces: Vec<bytes::Bytes> = bytes.chunks(size).map(bytes::Bytes::copy_from_slice).collect();
    reqwest::Body::wrap_stream(futures_util::stream::iter(pieces).then(move |piece| async move {
        tokio::time::sleep(gap).await;
        Ok::<_, std::io::Error>(piece)
    }))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_upload_succeeds_a_stalled_one_is_408_and_a_big_scene_is_422() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 0);
    config.limits.request_timeout = Duration::from_millis(300);
    config.limits.upload_idle_timeout = Duration::from_millis(700);
    let mut s = Server::start(config).await;
    // A refused upload's connection is closed by the server: no client-side pooling.
    s.http = reqwest::Client::builder().pool_max_idle_per_host(0).build().unwrap();
    // Issue 24 point 4: an upload has no total time, only an idle one. The Cornell box
    // in 10 pieces 150 ms apart takes 1.5 s, five times the request time limit.
    let started = std::time::Instant::now();
    let r = s
        .post("/v1/scenes")
        .header("content-type", "model/gltf-binary")
        .body(trickled(cornell_glb(), 10, Duration::from_millis(150)))
        .send()
        .await
        .unwrap();
    let took = started.elapsed();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    assert!(took > Duration::from_millis(1400), "the upload took only {took:?}");
    let slow: Value = r.json().await.unwrap();
    // The spooled upload keeps the content-addressed id: the same bytes sent at once
    // are the same scene (200), and its report is the whole scene's.
    let r = s.post("/v1/scenes").body(cornell_glb()).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let fast: Value = r.json().await.unwrap();
    assert_eq!(fast["id"], slow["id"]);
    assert_eq!(slow["report"]["triangles"], 32, "{slow:#}");
    let stored = s
        .get(&format!("/v1/scenes/{}/scene.glb", slow["id"].as_str().unwrap()))
        .send()
        .await
        .unwrap();
    assert_eq!(stored.status(), 200);
    // A body that stops arriving for longer than the idle time is cut off.
    let stalled = futures_util::stream::iter([0u64, 2000]).then(|wait| async move {
        tokio::time::sleep(Duration::from_millis(wait)).await;
        Ok::<_, std::io::Error>(bytes::Bytes::from_static(b"glTF"))
    });
    expect_problem(
        s.post("/v1/scenes")
            .header("content-type", "model/gltf-binary")
            .body(reqwest::Body::wrap_stream(stalled)),
        408,
        problem(
            408,
            "Request Timeout",
            "timeout",
            "the upload sent nothing for 0.7 s after 4 bytes (--upload-idle-timeout-s)",
            None,
        ),
    )
    .await;
    // Every other route keeps the request time limit: a job body that takes 2 s.
    let slow_job = futures_util::stream::once(async {
        tokio::time::sleep(Duration::from_secs(2)).await;
        Ok::<_, std::io::Error>(bytes::Bytes::from_static(b"{}"))
    });
    expect_problem(
        s.post("/v1/jobs")
            .header("content-type", "application/json")
            .body(reqwest::Body::wrap_stream(slow_job)),
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
    assert_eq!(spool_entries(dir.path()), 0, "an upload left files in the spool");
    // Quick requests are unaffected.
    assert_eq!(s.get("/healthz").send().await.unwrap().status(), 200);
    s.running.shutdown().await;

    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 0);
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
    assert_eq!(spool_entries(dir.path()), 0, "a refused upload left files in the spool");
    s.running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn large_bodies_past_the_cap_wait_with_503_and_retry_after() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 0);
    config.limits.max_large_bodies = 1;
    let mut s = Server::start(config).await;
    // A refused upload's connection is closed by the server: no client-side pooling.
    s.http = reqwest::Client::builder().pool_max_idle_per_host(0).build().unwrap();
    let glb = cornell_glb();
    // An upload of unknown length (a stream) is a large body: it holds the one permit
    // until its last piece, which the test releases.
    let (release, released) = tokio::sync::oneshot::channel::<()>();
    let (head, tail) = glb.split_at(glb.len() / 2);
    let (head, tail) = (bytes::Bytes::copy_from_slice(head), bytes::Bytes::copy_from_slice(tail));
    let held = futures_util::stream::iter([Some(head), None, Some(tail)]).then({
        let mut released = Some(released);
        move |piece| {
            let wait = if piece.is_none() { released.take() } else { None };
            async move {
                if let Some(rx) = wait {
                    let _ = rx.await;
                }
                Ok::<_, std::io::Error>(piece.unwrap_or_default())
            }
        }
    });
    let first = tokio::spawn(
        s.post("/v1/scenes")
            .header("content-type", "model/gltf-binary")
            .body(reqwest::Body::wrap_stream(held))
            .send(),
    );
    // Wait until the server holds the first upload's first half.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while spool_entries(dir.path()) == 0 {
        assert!(
            std::time::Instant::now() < deadline,
            "the first upload never reached the spool"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let second = s
        .post("/v1/scenes")
        .header("content-type", "model/gltf-binary")
        .body(reqwest::Body::wrap_stream(futures_util::stream::iter([Ok::<
            _,
            std::io::Error,
        >(
            bytes::Bytes::from(glb.clone()),
        )])))
        .send()
        .await
        .unwrap();
    assert_eq!(second.status(), 503);
    assert_eq!(second.headers()["retry-after"], "10");
    assert_eq!(
        second.json::<Value>().await.unwrap(),
        problem(
            503,
            "Service Unavailable",
            "too-many-bodies",
            "1 large uploads or downloads are in flight, this server's limit (--max-large-bodies); try again later",
            None,
        )
    );
    // A small body of known length is not held back.
    let r = s.post("/v1/jobs").json(&json!({"scene": "nope"})).send().await.unwrap();
    assert_ne!(r.status(), 503);
    // The first upload finishes, and its permit is free again.
    release.send(()).unwrap();
    let first = first.await.unwrap().unwrap();
    assert_eq!(first.status(), 201, "{}", first.text().await.unwrap());
    let third = s
        .post("/v1/scenes")
        .header("content-type", "model/gltf-binary")
        .body(reqwest::Body::wrap_stream(futures_util::stream::iter([Ok::<
            _,
            std::io::Error,
        >(
            bytes::Bytes::from(glb),
        )])))
        .send()
        .await
        .unwrap();
    assert_eq!(third.status(), 200, "the same scene again");
    assert_eq!(spool_entries(dir.path()), 0);
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
    for path in [
        "",
        "/events",
        "/lightmap.exr",
        "/lightmap-0.exr",
        "/lightmaps.json",
        "/preview.png",
        "/scene.glb",
    ] {
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

/// A job over a worker's per-job memory limit is left to a worker whose limit covers it
/// (issue 25: claims filter on the job's estimate); until one runs, the job says so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_with_less_memory_leaves_a_job_over_its_limit_to_a_bigger_one() {
    let dir = tempfile::tempdir().unwrap();
    // The API accepts the job (its limit is the default 8 GiB)...
    let s = Server::start(test_config(dir.path(), 0)).await;
    let scene = s.upload(None).await;
    let big = s
        .submit(None, json!({"scene": scene, "resolution": 1024, "stop": {"steps": 1}}))
        .await;
    // ...a worker process with 200 MiB leaves it queued, and the job says why.
    let start_workers = |memory: u64| {
        let mut config = test_config(dir.path(), 1);
        config.limits.max_job_memory_bytes = memory;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let workers = tokio::spawn(lightmapd::service::run_workers(config, async {
            let _ = stopped.await;
        }));
        (stop, workers)
    };
    let (stop_small, small) = start_workers(200 << 20);
    let t = std::time::Instant::now();
    let waiting = loop {
        let j = get_json(&s.http, &format!("{}/v1/jobs/{big}", s.url)).await;
        assert_eq!(j["status"], "queued", "{j:#}");
        if let Some(w) = j["waiting_for"].as_str().filter(|w| w.starts_with("a worker with")) {
            break w.to_string();
        }
        assert!(t.elapsed() < Duration::from_secs(30), "{j:#}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(
        waiting.starts_with(
            "a worker with a per-job memory limit of at least 1204 MiB (the job's estimate; --max-job-memory-mb): none of the 1 live workers has all of it ("
        ) && waiting.ends_with("; 200 MiB a job))"),
        "{waiting}"
    );
    tokio::time::sleep(Duration::from_secs(1)).await;
    let j = get_json(&s.http, &format!("{}/v1/jobs/{big}", s.url)).await;
    assert_eq!((&j["status"], &j["attempts"]), (&json!("queued"), &json!(0)), "{j:#}");
    // A worker with the default 8 GiB takes it and bakes it.
    let (stop_big, bigger) = start_workers(8 << 30);
    let j = s.wait_end(&big).await;
    assert_eq!(j["status"], "succeeded", "{j:#}");
    assert_eq!(j["attempts"], 1);
    for (stop, workers) in [(stop_small, small), (stop_big, bigger)] {
        let _ = stop.send(());
        workers.await.unwrap().unwrap();
    }
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

/// A `lightmapd serve` on `listen` with `extra`; its exit code and stderr if it exits
/// within 20 s, `None` (after killing it) if it started serving.
fn serve_outcome(dir: &std::path::Path, listen: &str, extra: &[&str]) -> Option<(i32, String)> {
    use std::io::{BufRead, BufReader};
    let mut child = Command::new(bin())
        .args(["serve", "--listen", listen, "--workers", "0", "--data-dir"])
        .arg(dir)
        .args(extra)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    if line.starts_with("lightmapd listening on ") {
        child.kill().unwrap();
        let _ = child.wait();
        return None;
    }
    let out = child.wait_with_output().unwrap();
    Some((
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).to_string(),
    ))
}

#[test]
fn a_network_address_without_auth_is_refused_unless_trusted() {
    let dir = tempfile::tempdir().unwrap();
    let (code, stderr) = serve_outcome(dir.path(), "0.0.0.0:0", &[]).expect("refused");
    assert_eq!(code, 2);
    assert_eq!(
        stderr,
        "error: refusing to serve 0.0.0.0:0 without authentication: anyone who can reach it could list, \
         download, cancel and delete every job. Add --auth (tokens from `lightmapd token create` or \
         --tokens-file), or --insecure-no-auth on a network you trust, or listen on 127.0.0.1\n"
    );
    assert!(
        !dir.path().join("lightmapd.db").exists(),
        "refused before anything was opened"
    );
    // Loopback, --auth, or the explicit opt-out start.
    assert_eq!(serve_outcome(dir.path(), "127.0.0.1:0", &[]), None);
    assert_eq!(serve_outcome(dir.path(), "0.0.0.0:0", &["--auth"]), None);
    assert_eq!(serve_outcome(dir.path(), "0.0.0.0:0", &["--insecure-no-auth"]), None);
    // A tokens file is checked before start: a bad line is named, exit code 2.
    let file = dir.path().join("tokens");
    std::fs::write(&file, "ops superuser 0123456789abcdef0123456789abcdef\n").unwrap();
    let (code, stderr) = serve_outcome(
        dir.path(),
        "0.0.0.0:0",
        &["--auth", "--tokens-file", file.to_str().unwrap()],
    )
    .unwrap();
    assert_eq!(code, 2);
    assert_eq!(
        stderr,
        format!(
            "error: tokens file {}: line 1: role \"superuser\": use admin or editor\n",
            file.display()
        )
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn admin_and_editor_tokens_differ_in_priority_and_reach() {
    let dir = tempfile::tempdir().unwrap();
    let editor = create_token(dir.path(), "editor");
    let out = token_cli(dir.path(), &["create", "--name", "ops", "--role", "admin"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let admin = String::from_utf8(out.stdout).unwrap().trim().to_string();
    let mut config = test_config(dir.path(), 0);
    config.auth = true;
    let s = Server::start(config).await;
    let scene = s.upload(Some(&editor)).await;

    // Editors: priority up to --max-priority (10 by default), 403 above.
    expect_problem(
        s.post("/v1/jobs")
            .bearer_auth(&editor)
            .json(&json!({"scene": scene, "resolution": 16, "priority": 11})),
        403,
        problem(
            403,
            "Forbidden",
            "forbidden",
            "priority 11 is above 10, the most this server allows an editor token (--max-priority); an admin token may set it",
            Some("priority"),
        ),
    )
    .await;
    let job = s
        .submit(Some(&editor), json!({"scene": scene, "resolution": 16, "priority": 10}))
        .await;
    // Admins: any priority, on anyone's scene; they see, cancel and delete every job.
    let urgent = s
        .submit(
            Some(&admin),
            json!({"scene": scene, "resolution": 16, "priority": 1000}),
        )
        .await;
    let list: Value = s
        .get("/v1/jobs")
        .bearer_auth(&admin)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["total"], 2, "{list:#}");
    assert_eq!(list["jobs"][0]["priority"], 1000);
    let list: Value = s
        .get("/v1/jobs")
        .bearer_auth(&editor)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["total"], 1, "an editor sees only its own: {list:#}");
    expect_problem(
        s.get(&format!("/v1/jobs/{urgent}")).bearer_auth(&editor),
        404,
        problem(
            404,
            "Not Found",
            "not-found",
            &format!("no job with id {urgent:?}"),
            None,
        ),
    )
    .await;
    expect_problem(
        s.http.delete(format!("{}/v1/jobs/{job}", s.url)).bearer_auth(&admin),
        409,
        problem(
            409,
            "Conflict",
            "conflict",
            &format!(
                "job {job} is queued: cancel it first (POST /v1/jobs/{job}/cancel), then delete it once it has ended"
            ),
            None,
        ),
    )
    .await;
    let r = s
        .post(&format!("/v1/jobs/{job}/cancel"))
        .bearer_auth(&admin)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    let r = s
        .http
        .delete(format!("{}/v1/jobs/{job}", s.url))
        .bearer_auth(&admin)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    expect_problem(
        s.get(&format!("/v1/jobs/{job}")).bearer_auth(&editor),
        404,
        problem(404, "Not Found", "not-found", &format!("no job with id {job:?}"), None),
    )
    .await;
    s.running.shutdown().await;

    // Without authentication nobody is trusted with a priority above the cap either.
    let open = Server::start(test_config(dir.path(), 0)).await;
    let scene = open.upload(None).await;
    expect_problem(
        open.post("/v1/jobs").json(&json!({"scene": scene, "priority": 2147483647})),
        403,
        problem(
            403,
            "Forbidden",
            "forbidden",
            "priority 2147483647 is above 10, the most this server allows without authentication (--max-priority); an admin token may set it",
            Some("priority"),
        ),
    )
    .await;
    open.running.shutdown().await;
}

#[test]
fn token_names_are_unique_and_revocation_is_unambiguous() {
    let dir = tempfile::tempdir().unwrap();
    create_token(dir.path(), "alice");
    let out = token_cli(dir.path(), &["create", "--name", "alice"]);
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(
        stderr.starts_with("error: a live token is already named \"alice\" (tok_")
            && stderr.ends_with("); pick another name, or revoke that one first\n"),
        "{stderr}"
    );
    // Two live tokens of one name (made before names were unique): the name is refused,
    // each id works.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let ids: Vec<String> = rt.block_on(async {
        use lightmapd::service::queue::{Queue, Role, TokenRecord, sqlite::SqliteQueue};
        let q = SqliteQueue::open(&dir.path().join("lightmapd.db")).await.unwrap();
        for (id, hash) in [("tok_old1", "h1"), ("tok_old2", "h2")] {
            q.insert_token(&TokenRecord {
                id: id.into(),
                name: "build".into(),
                hash: hash.into(),
                created_at: 1,
                revoked_at: None,
                role: Role::Editor,
                source: "cli".into(),
            })
            .await
            .unwrap();
        }
        vec!["tok_old1".into(), "tok_old2".into()]
    });
    let out = token_cli(dir.path(), &["revoke", "build"]);
    assert_eq!(out.status.code(), Some(2));
    assert_eq!(
        String::from_utf8(out.stderr).unwrap(),
        "error: 2 active tokens are named \"build\" (tok_old1, tok_old2): revoke one by its id\n"
    );
    let out = token_cli(dir.path(), &["revoke", &ids[0]]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(
        String::from_utf8(out.stderr).unwrap(),
        "token tok_old1 (build) revoked\n"
    );
    // Now one live token has the name: revoking by name means it.
    let out = token_cli(dir.path(), &["revoke", "build"]);
    assert_eq!(
        String::from_utf8(out.stderr).unwrap(),
        "token tok_old2 (build) revoked\n"
    );
    let listing = String::from_utf8(token_cli(dir.path(), &["list"]).stdout).unwrap();
    let roles: Vec<&str> = listing.lines().map(|l| l.split('\t').nth(2).unwrap()).collect();
    assert_eq!(roles, ["editor", "editor", "editor"], "{listing}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_from_a_secret_file_are_added_and_rotated_out() {
    use lightmapd::service::auth::parse_tokens_file;
    let dir = tempfile::tempdir().unwrap();
    let (old, new) = ("a".repeat(64), "b".repeat(64));
    let start = |text: String| {
        let mut config = test_config(dir.path(), 0);
        config.auth = true;
        config.tokens_file = Some(parse_tokens_file(&text).unwrap());
        Server::start(config)
    };
    let status = |s: &Server, secret: &str| {
        let r = s.get("/v1/jobs").bearer_auth(secret).send();
        async move { r.await.unwrap().status().as_u16() }
    };
    // 1. Only the old secret.
    let s = start(format!("# rotated 2026-12\nci editor {old}\n")).await;
    assert_eq!((status(&s, &old).await, status(&s, &new).await), (200, 401));
    s.running.shutdown().await;
    // 2. Both, while clients move over (the old token is kept, not re-made).
    let s = start(format!("ci editor {old}\nci2 editor {new}\n")).await;
    assert_eq!((status(&s, &old).await, status(&s, &new).await), (200, 200));
    s.running.shutdown().await;
    // 3. The old line removed: its token is revoked at start-up.
    let s = start(format!("ci2 editor {new}\n")).await;
    assert_eq!((status(&s, &old).await, status(&s, &new).await), (401, 200));
    s.running.shutdown().await;
    let listing = String::from_utf8(token_cli(dir.path(), &["list"]).stdout).unwrap();
    let rows: Vec<(String, bool, String)> = listing
        .lines()
        .map(|l| {
            let f: Vec<&str> = l.split('\t').collect();
            (f[1].to_string(), f[4] == "active", f[5].to_string())
        })
        .collect();
    assert_eq!(
        rows,
        [("ci".into(), false, "file".into()), ("ci2".into(), true, "file".into())],
        "{listing}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_body_must_be_an_object() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(test_config(dir.path(), 0)).await;
    let scene = s.upload(None).await;
    for (body, kind) in [
        (json!([scene, "path", 16]), "an array"),
        (json!("scene"), "a string"),
        (json!(16), "a number"),
        (json!(null), "null"),
    ] {
        expect_problem(
            s.post("/v1/jobs").json(&body),
            422,
            problem(
                422,
                "Unprocessable Entity",
                "invalid-field",
                &format!("the job must be a JSON object ({{\"scene\": …}}), got {kind}"),
                None,
            ),
        )
        .await;
    }
    s.running.shutdown().await;
}

/// `url` with `extra` added to its query string.
fn with_query(url: &str, extra: &str) -> String {
    format!("{url}{}{extra}", if url.contains('?') { '&' } else { '?' })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_connections_use_tls_as_sslmode_says() {
    use lightmapd::service::queue::postgres::{PostgresQueue, test_url};
    use sqlx::postgres::PgPoolOptions;
    let Some(url) = test_url("hardening::postgres_connections_use_tls_as_sslmode_says") else {
        return;
    };
    // What the session runs over: (TLS?, protocol version).
    let session = |url: String| async move {
        let pool = PgPoolOptions::new().max_connections(1).connect(&url).await?;
        let row: (bool, Option<String>) =
            sqlx::query_as("SELECT ssl, version FROM pg_stat_ssl WHERE pid = pg_backend_pid()")
                .fetch_one(&pool)
                .await?;
        pool.close().await;
        Ok::<_, sqlx::Error>(row)
    };
    let plain = session(with_query(&url, "sslmode=disable")).await.unwrap();
    assert_eq!(plain, (false, None), "sslmode=disable is plain");
    let pool = PgPoolOptions::new().max_connections(1).connect(&url).await.unwrap();
    let (ssl, cert): (String, String) =
        sqlx::query_as("SELECT current_setting('ssl'), current_setting('ssl_cert_file')")
            .fetch_one(&pool)
            .await
            .unwrap();
    pool.close().await;
    assert_eq!(ssl, "on", "scripts/setup-postgres.sh turns TLS on");
    // require: encrypted, the certificate not checked (it is self-signed).
    let (tls, version) = session(with_query(&url, "sslmode=require")).await.unwrap();
    assert!(tls, "sslmode=require is not TLS");
    assert!(
        version.as_deref().is_some_and(|v| v.starts_with("TLSv1.")),
        "{version:?}"
    );
    // The default (prefer) takes TLS when offered.
    assert!(session(url.clone()).await.unwrap().0, "sslmode=prefer did not take TLS");
    // verify-full against the self-signed server certificate, which no root trusts: the
    // queue refuses to connect with a certificate error. (Before the queue installed a
    // process-wide crypto provider, rustls' verifier builder panicked here: both ring
    // and aws-lc-rs are compiled in, so it had no default.)
    let schema = format!("tlsv_{}", uuid::Uuid::new_v4().simple());
    let untrusted = PostgresQueue::open_in_schema(&with_query(&url, "sslmode=verify-full"), &schema).await;
    let msg = untrusted
        .err()
        .expect("an untrusted self-signed certificate is refused")
        .to_string();
    assert!(msg.to_lowercase().contains("certificate"), "{msg}");
    // verify-ca with the server's own certificate as the root: trusted, and TLS.
    let with_root = with_query(&url, &format!("sslmode=verify-ca&sslrootcert={cert}"));
    let q = PostgresQueue::open_in_schema(&with_root, &schema).await.unwrap();
    assert!(q.counts().await.unwrap().iter().all(|(_, n)| *n == 0));
    q.drop_schema(&schema).await.unwrap();
    // The queue itself opens, migrates and works over TLS.
    let schema = format!("tls_{}", uuid::Uuid::new_v4().simple());
    let q = PostgresQueue::open_in_schema(&with_query(&url, "sslmode=require"), &schema)
        .await
        .unwrap();
    use lightmapd::service::queue::Queue;
    assert!(q.counts().await.unwrap().iter().all(|(_, n)| *n == 0));
    q.drop_schema(&schema).await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn submit_wait_retries_a_busy_event_stream() {
    // One event stream allowed, held by the test on a 3 s bake: `submit --wait` is told
    // 503 with Retry-After 10 for its own job's stream, waits, and then follows it to the
    // end (before issue 24 it gave up at once with exit code 1).
    let dir = tempfile::tempdir().unwrap();
    let mut config = test_config(dir.path(), 1);
    config.limits.max_event_streams = 1;
    let s = Server::start(config).await;
    let scene = s.upload(None).await;
    let a = s
        .submit(
            None,
            json!({"scene": scene, "resolution": 16, "stop": {"seconds": 3.0, "steps": 1000000}}),
        )
        .await;
    let held = s.get(&format!("/v1/jobs/{a}/events")).send().await.unwrap();
    assert_eq!(held.status(), 200);
    let scene_file = dir.path().join("cornell.glb");
    std::fs::write(&scene_file, cornell_glb()).unwrap();
    let url = s.url.clone();
    let cli = tokio::task::spawn_blocking(move || {
        Command::new(bin())
            .arg("submit")
            .arg(&scene_file)
            .args(["--server", &url, "--resolution", "16", "--steps", "4", "--wait"])
            .output()
            .unwrap()
    });
    // Drain the held stream until its bake ends (the stream then closes).
    let mut body = held.bytes_stream();
    while body.next().await.is_some() {}
    let out = cli.await.unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("events: the server is busy (503); trying again in 10 s"),
        "{stderr}"
    );
    let job: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(job["status"], "succeeded");
    s.running.shutdown().await;
}
