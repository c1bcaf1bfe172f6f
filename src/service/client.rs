//! The `lightmapd submit` client: upload a scene, submit a job, follow its events with a
//! progress bar, download the lightmap.
//!
//! How: a `.glb` is sent as the body; a `.gltf` as multipart with every buffer and image
//! it names by relative URI, read from beside it. Progress comes from the job's
//! server-sent events; if the stream breaks (the server restarted), the client
//! reconnects and is sent the current state first, so waiting survives a restart.
//!
//! Exit codes: 2 when the server refuses the input (a 4xx other than 408 and 429), 1 for
//! everything else. A busy server (429: the client's queue is full; 503) is not bad
//! input: the upload and the submission wait as the server's `Retry-After` says (at
//! most a minute at a time) and try again, for up to `retry_for` in all; so does
//! following the job's events (`--wait`), whose stream a server may refuse with 503 when
//! it has too many open.
//!
//! TLS: `https://` servers are reached with rustls and the system's trust store
//! (reqwest's `rustls` feature); `http://` as before.
//!
//! Limits: no client certificates; a private CA must be in the system's trust store (or
//! `SSL_CERT_FILE`).

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Duration;

use futures_util::StreamExt;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::{Value, json};

use crate::engine::output::write_atomically;
use crate::service::model::{JobView, Progress, uri_file_name};
use crate::service::problem::Problem;

/// What `lightmapd submit` does.
pub struct Submit {
    /// e.g. `http://127.0.0.1:8080`
    pub server: String,
    pub scene: PathBuf,
    /// The job body without `scene` (the client fills it in after the upload).
    pub job: Value,
    /// Follow the job until it ends.
    pub wait: bool,
    /// Download the final lightmap here (implies `wait`): a folder gets every page and
    /// `lightmaps.json`, a path ending in `.exr` the one page of a one-page job.
    pub output: Option<PathBuf>,
    /// A bearer token, for a server run with `--auth`.
    pub token: Option<String>,
    /// How long to keep retrying while the server answers 429 or 503.
    pub retry_for: Duration,
}

/// A failure and the exit code it earns (2: the server said the input is bad).
#[derive(Debug)]
pub struct ClientError {
    pub code: u8,
    pub message: String,
}

fn fail(code: u8, message: impl Into<String>) -> ClientError {
    ClientError {
        code,
        message: message.into(),
    }
}

fn http_err(server: &str, e: reqwest::Error) -> ClientError {
    fail(1, format!("cannot reach {server}: {e}"))
}

/// Turns a non-success response into an error carrying the server's problem detail.
async fn check(resp: reqwest::Response, what: &str) -> Result<reqwest::Response, ClientError> {
    let status = resp.status();
    if status.is_success() {
        return Ok(resp);
    }
    let text = resp.text().await.unwrap_or_default();
    let detail = match serde_json::from_str::<Problem>(&text) {
        Ok(p) => match p.field {
            Some(f) => format!("{} ({f})", p.detail),
            None => p.detail,
        },
        Err(_) => text,
    };
    let bad_input = status.is_client_error()
        && status != reqwest::StatusCode::TOO_MANY_REQUESTS
        && status != reqwest::StatusCode::REQUEST_TIMEOUT;
    let code = if bad_input { 2 } else { 1 };
    Err(fail(code, format!("{what}: {} {detail}", status.as_u16())))
}

/// How long a busy answer asks to wait: its `Retry-After` in seconds, 1 to 60 (5 without).
fn retry_after(resp: &reqwest::Response) -> Duration {
    let s = resp
        .headers()
        .get(reqwest::header::RETRY_AFTER)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok())
        .unwrap_or(5)
        .clamp(1, 60);
    Duration::from_secs(s)
}

fn is_busy(status: reqwest::StatusCode) -> bool {
    matches!(
        status,
        reqwest::StatusCode::TOO_MANY_REQUESTS | reqwest::StatusCode::SERVICE_UNAVAILABLE
    )
}

/// Sends the request `make` builds, again while the server answers 429 or 503 and
/// `retry_for` has not run out, waiting as its `Retry-After` says (1 to 60 s).
async fn send_retrying(
    make: impl Fn() -> Result<reqwest::RequestBuilder, ClientError>,
    server: &str,
    what: &str,
    retry_for: Duration,
) -> Result<reqwest::Response, ClientError> {
    let give_up = std::time::Instant::now() + retry_for;
    loop {
        let resp = make()?.send().await.map_err(|e| http_err(server, e))?;
        let busy = is_busy(resp.status());
        let wait = retry_after(&resp);
        if !busy || std::time::Instant::now() + wait > give_up {
            return check(resp, what).await;
        }
        eprintln!(
            "{what}: the server is busy ({}); trying again in {} s",
            resp.status().as_u16(),
            wait.as_secs()
        );
        tokio::time::sleep(wait).await;
    }
}

/// Runs the whole submission; returns the finished (or just queued) job.
pub async fn submit(s: Submit) -> Result<JobView, ClientError> {
    let server = s.server.trim_end_matches('/').to_string();
    let mut headers = reqwest::header::HeaderMap::new();
    if let Some(t) = &s.token {
        let mut v = reqwest::header::HeaderValue::from_str(&format!("Bearer {t}"))
            .map_err(|_| fail(2, "the token has characters a header cannot carry"))?;
        v.set_sensitive(true);
        headers.insert(reqwest::header::AUTHORIZATION, v);
    }
    let http = reqwest::Client::builder()
        .connect_timeout(Duration::from_secs(10))
        .default_headers(headers)
        .build()
        .map_err(|e| fail(1, format!("HTTP client: {e}")))?;

    let resp = send_retrying(
        || scene_request(&http, &server, &s.scene),
        &server,
        "upload",
        s.retry_for,
    )
    .await?;
    let scene: Value = resp.json().await.map_err(|e| fail(1, format!("upload: {e}")))?;
    let scene_id = scene["id"].as_str().unwrap_or_default().to_string();
    for w in scene["report"]["warnings"].as_array().into_iter().flatten() {
        eprintln!("warning: {}", w.as_str().unwrap_or_default());
    }

    let mut body = s.job.clone();
    body["scene"] = json!(scene_id);
    let resp = send_retrying(
        || Ok(http.post(format!("{server}/v1/jobs")).json(&body)),
        &server,
        "submit",
        s.retry_for,
    )
    .await?;
    let created: Value = resp.json().await.map_err(|e| fail(1, format!("submit: {e}")))?;
    let job_id = created["id"].as_str().unwrap_or_default().to_string();
    for w in created["warnings"].as_array().into_iter().flatten() {
        eprintln!("warning: {}", w.as_str().unwrap_or_default());
    }
    eprintln!("job {job_id} queued (scene {scene_id})");

    if !(s.wait || s.output.is_some()) {
        return get_job(&http, &server, &job_id).await;
    }
    let job = follow(&http, &server, &job_id, s.retry_for).await?;
    match job.status {
        crate::service::model::JobStatus::Succeeded => {}
        crate::service::model::JobStatus::Failed => {
            return Err(fail(
                1,
                format!("job {job_id} failed: {}", job.failure.clone().unwrap_or_default()),
            ));
        }
        other => return Err(fail(1, format!("job {job_id} ended {}", other.as_str()))),
    }
    if let Some(out) = &s.output {
        // The pages the job wrote (`summary.pages`), as `bake -o` writes them: a folder
        // gets every page and the manifest, an `.exr` path the one page.
        let pages: Vec<String> = job
            .summary
            .as_ref()
            .and_then(|s| s.get("pages"))
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(|p| p["file"].as_str().map(str::to_owned)).collect())
            .unwrap_or_default();
        let download = |file: String| {
            let http = http.clone();
            let url = format!("{server}/v1/jobs/{job_id}/{file}");
            let server = server.clone();
            async move {
                let resp = http.get(url).send().await.map_err(|e| http_err(&server, e))?;
                check(resp, "download")
                    .await?
                    .bytes()
                    .await
                    .map_err(|e| fail(1, format!("download {file}: {e}")))
            }
        };
        let is_exr = out.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"));
        if is_exr {
            if pages.len() > 1 {
                return Err(fail(
                    2,
                    format!(
                        "job {job_id} wrote {} lightmap pages and -o {} names one EXR file: give -o a folder",
                        pages.len(),
                        out.display()
                    ),
                ));
            }
            let bytes = download("lightmap.exr".into()).await?;
            write_atomically(out, &bytes).map_err(|e| fail(1, format!("cannot write {}: {e}", out.display())))?;
        } else {
            std::fs::create_dir_all(out).map_err(|e| fail(1, format!("cannot create {}: {e}", out.display())))?;
            let pages = if pages.is_empty() {
                vec!["lightmap-0.exr".to_string()]
            } else {
                pages
            };
            for file in pages
                .into_iter()
                .chain([crate::engine::output::pages::MANIFEST_FILE.to_string()])
            {
                let bytes = download(file.clone()).await?;
                let p = out.join(&file);
                write_atomically(&p, &bytes).map_err(|e| fail(1, format!("cannot write {}: {e}", p.display())))?;
            }
        }
    }
    let p = job.progress.unwrap_or_default();
    eprintln!(
        "job {job_id} succeeded: {} steps in {:.1} s, estimated error {}{}",
        p.steps,
        p.elapsed_s,
        p.error.map_or("n/a".into(), |e| format!("{:.2}%", e * 100.0)),
        s.output
            .as_ref()
            .map_or(String::new(), |o| format!(" -> {}", o.display()))
    );
    Ok(job)
}

async fn get_job(http: &reqwest::Client, server: &str, id: &str) -> Result<JobView, ClientError> {
    let resp = http
        .get(format!("{server}/v1/jobs/{id}"))
        .send()
        .await
        .map_err(|e| http_err(server, e))?;
    check(resp, "job")
        .await?
        .json()
        .await
        .map_err(|e| fail(1, format!("job: {e}")))
}

fn scene_request(http: &reqwest::Client, server: &str, path: &Path) -> Result<reqwest::RequestBuilder, ClientError> {
    let read = |p: &Path| std::fs::read(p).map_err(|e| fail(2, format!("cannot read {}: {e}", p.display())));
    let url = format!("{server}/v1/scenes");
    let is_gltf = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("gltf"));
    if !is_gltf {
        return Ok(http
            .post(url)
            .header(reqwest::header::CONTENT_TYPE, "model/gltf-binary")
            .body(read(path)?));
    }
    let main = read(path)?;
    let json: Value =
        serde_json::from_slice(&main).map_err(|e| fail(2, format!("{} is not JSON: {e}", path.display())))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("scene.gltf")
        .to_string();
    let mut form =
        reqwest::multipart::Form::new().part(name.clone(), reqwest::multipart::Part::bytes(main).file_name(name));
    let mut seen = std::collections::HashSet::new();
    for kind in ["buffers", "images"] {
        for item in json[kind].as_array().into_iter().flatten() {
            if let Some(uri) = item["uri"].as_str()
                && !uri.starts_with("data:")
            {
                let file = uri_file_name(uri);
                if seen.insert(file.clone()) {
                    let bytes = read(&dir.join(&file))?;
                    form = form.part(file.clone(), reqwest::multipart::Part::bytes(bytes).file_name(file));
                }
            }
        }
    }
    Ok(http.post(url).multipart(form))
}

/// Follows the job's events until it ends, drawing a progress bar; reconnects when the
/// stream breaks.
async fn follow(http: &reqwest::Client, server: &str, id: &str, retry_for: Duration) -> Result<JobView, ClientError> {
    let give_up = std::time::Instant::now() + retry_for;
    let bar = if std::io::stderr().is_terminal() {
        ProgressBar::new(1000)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} {elapsed_precise} [{wide_bar}] {percent:>3}% {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let show = |p: &Progress, bar: &ProgressBar| {
        bar.set_position((p.fraction * 1000.0) as u64);
        let err = p.error.map_or(String::new(), |e| format!(", error {:.2}%", e * 100.0));
        // Inside a long step, how far it is (as the CLI's own bar shows it).
        let within = p
            .step_fraction
            .map_or(String::new(), |f| format!(" (+{:.0} %)", f * 100.0));
        bar.set_message(format!("step {}{within}{err}", p.steps));
    };
    let mut failures = 0u32;
    loop {
        let resp = match http.get(format!("{server}/v1/jobs/{id}/events")).send().await {
            Ok(r) if is_busy(r.status()) && std::time::Instant::now() + retry_after(&r) <= give_up => {
                let wait = retry_after(&r);
                // Above the bar, not through it (a hidden bar just prints).
                bar.suspend(|| {
                    eprintln!(
                        "events: the server is busy ({}); trying again in {} s",
                        r.status().as_u16(),
                        wait.as_secs()
                    )
                });
                tokio::time::sleep(wait).await;
                continue;
            }
            Ok(r) => check(r, "events").await?,
            Err(e) => {
                failures += 1;
                if failures > 60 {
                    return Err(http_err(server, e));
                }
                bar.set_message(format!("reconnecting: {e}"));
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        failures = 0;
        let mut stream = resp.bytes_stream();
        let mut buf = String::new();
        while let Some(chunk) = stream.next().await {
            let Ok(chunk) = chunk else { break };
            buf.push_str(&String::from_utf8_lossy(&chunk));
            while let Some(end) = buf.find("\n\n") {
                let block: String = buf.drain(..end + 2).collect();
                let (mut name, mut data) = (String::new(), String::new());
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event:") {
                        name = v.trim().to_string();
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push_str(v.strip_prefix(' ').unwrap_or(v));
                    }
                }
                let Ok(v) = serde_json::from_str::<Value>(&data) else {
                    continue;
                };
                match name.as_str() {
                    "status" => {
                        if let Ok(job) = serde_json::from_value::<JobView>(v) {
                            bar.set_message(job.status.as_str().to_string());
                            if let Some(p) = &job.progress {
                                show(p, &bar);
                            }
                        }
                    }
                    "progress" => {
                        if let Ok(p) = serde_json::from_value::<Progress>(v) {
                            show(&p, &bar);
                        }
                    }
                    "done" | "cancelled" => {
                        bar.finish_and_clear();
                        return serde_json::from_value(v).map_err(|e| fail(1, format!("events: {e}")));
                    }
                    "failed" => {
                        bar.finish_and_clear();
                        return serde_json::from_value(v["job"].clone()).map_err(|e| fail(1, format!("events: {e}")));
                    }
                    _ => {}
                }
            }
        }
        // The stream ended without a last event: the server went away. Try again.
        bar.set_message("reconnecting");
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}
