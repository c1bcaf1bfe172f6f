//! Helpers the hardening and fault-injection tests share: start an in-process server or
//! a `lightmapd serve` / `lightmapd worker` child, and check problem+json answers.
#![allow(dead_code)]

pub mod pg;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use lightmapd::service::{self, Config, Running};
use serde_json::{Value, json};

pub const DEADLINE: Duration = Duration::from_secs(60);

pub fn cornell_glb() -> Vec<u8> {
    std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.glb")).unwrap()
}

/// Uploads the Cornell box to the server at `url` and returns the scene's id.
pub async fn upload_cornell(http: &reqwest::Client, url: &str) -> String {
    let r = http
        .post(format!("{url}/v1/scenes"))
        .body(cornell_glb())
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "upload: {}", r.status());
    r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
}

pub fn test_config(dir: &Path, workers: usize) -> Config {
    Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: dir.to_path_buf(),
        workers,
        snapshot_interval: Duration::from_millis(50),
        ..Config::default()
    }
}

/// An in-process server, its URL and a client.
pub struct Server {
    pub running: Running,
    pub url: String,
    pub http: reqwest::Client,
}

impl Server {
    pub async fn start(config: Config) -> Server {
        Server::wrap(service::start(config).await.unwrap())
    }

    pub fn wrap(running: Running) -> Server {
        let url = format!("http://{}", running.addr);
        Server {
            running,
            url,
            http: reqwest::Client::new(),
        }
    }

    pub fn get(&self, path: &str) -> reqwest::RequestBuilder {
        self.http.get(format!("{}{path}", self.url))
    }

    pub fn post(&self, path: &str) -> reqwest::RequestBuilder {
        self.http.post(format!("{}{path}", self.url))
    }

    pub async fn upload(&self, token: Option<&str>) -> String {
        let mut r = self.post("/v1/scenes").body(cornell_glb());
        if let Some(t) = token {
            r = r.bearer_auth(t);
        }
        let r = r.send().await.unwrap();
        assert!(r.status().is_success(), "{}", r.text().await.unwrap());
        r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
    }

    pub async fn submit(&self, token: Option<&str>, body: Value) -> String {
        let mut r = self.post("/v1/jobs").json(&body);
        if let Some(t) = token {
            r = r.bearer_auth(t);
        }
        let r = r.send().await.unwrap();
        assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
        r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
    }

    /// Polls a job until it has ended (succeeded, failed, cancelled).
    pub async fn wait_end(&self, id: &str) -> Value {
        let start = Instant::now();
        loop {
            let j: Value = self
                .get(&format!("/v1/jobs/{id}"))
                .send()
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
            if ["succeeded", "failed", "cancelled"].contains(&j["status"].as_str().unwrap_or("")) {
                return j;
            }
            assert!(start.elapsed() < DEADLINE, "job {id} never ended: {j:#}");
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    }
}

/// Checks the status, the content type and the whole problem+json body.
pub async fn expect_problem(req: reqwest::RequestBuilder, status: u16, body: Value) -> reqwest::header::HeaderMap {
    let r = req.send().await.unwrap();
    let headers = r.headers().clone();
    let got_status = r.status().as_u16();
    let text = r.text().await.unwrap();
    assert_eq!(got_status, status, "{text}");
    assert_eq!(headers["content-type"], "application/problem+json", "{text}");
    let got: Value = serde_json::from_str(&text).unwrap();
    assert_eq!(got, body);
    headers
}

/// Submits a job (202 expected); its id.
pub async fn submit(http: &reqwest::Client, url: &str, body: Value) -> String {
    let r = http.post(format!("{url}/v1/jobs")).json(&body).send().await.unwrap();
    assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
    r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
}

pub fn problem(status: u16, title: &str, kind: &str, detail: &str, field: Option<&str>) -> Value {
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

pub fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_lightmapd")
}

/// A `lightmapd serve` child; the address comes from its first stdout line.
pub fn spawn_serve(dir: &Path, workers: usize, extra: &[&str]) -> (Child, String) {
    spawn_serve_env(dir, workers, extra, &[])
}

/// Where a spawned server's log goes: appended to `$LIGHTMAPD_TEST_SERVE_LOG` when set
/// (to read after a failure), else nowhere.
fn serve_log() -> Stdio {
    std::env::var_os("LIGHTMAPD_TEST_SERVE_LOG")
        .and_then(|p| std::fs::OpenOptions::new().create(true).append(true).open(p).ok())
        .map_or_else(Stdio::null, Stdio::from)
}

/// [`spawn_serve`] with extra environment variables (an S3 store's `AWS_*`).
pub fn spawn_serve_env(dir: &Path, workers: usize, extra: &[&str], env: &[(&str, String)]) -> (Child, String) {
    let mut child = Command::new(bin())
        .arg("serve")
        .args(["--listen", "127.0.0.1:0", "--workers", &workers.to_string()])
        .arg("--data-dir")
        .arg(dir)
        .args(extra)
        .envs(env.iter().map(|(k, v)| (k, v)))
        .stdout(Stdio::piped())
        .stderr(serve_log())
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
    (child, url)
}

/// A `lightmapd worker` child on the database and store of a `serve` in `dir`.
pub fn spawn_worker(dir: &Path, extra: &[&str]) -> Child {
    Command::new(bin())
        .arg("worker")
        .arg("--database-url")
        .arg(format!("sqlite://{}", dir.join("lightmapd.db").display()))
        .arg("--store")
        .arg(dir.join("objects"))
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

pub fn store_dir(dir: &Path) -> PathBuf {
    dir.join("objects")
}

/// Decodes every channel of every layer of an EXR: a truncated or half-written file
/// fails here.
pub fn exr_is_whole(bytes: &[u8]) -> Result<(), String> {
    read_exr(bytes).map(|_| ()).map_err(|e| e.to_string())
}

/// Every layer and channel of an EXR in memory.
fn read_exr(bytes: &[u8]) -> exr::error::Result<exr::prelude::FlatImage> {
    use exr::prelude::*;
    read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
}

/// An S3-protocol server for tests (`scripts/setup.sh test` starts moto's server mode on
/// 127.0.0.1:9000): the endpoint (`AWS_ENDPOINT_URL`, default `http://127.0.0.1:9000`),
/// a bucket (`LIGHTMAPD_TEST_BUCKET`, default `lightmapd-test`, created with an unsigned
/// `PUT`, which moto accepts), and the `AWS_*` settings child processes get (keys
/// `test`/`test` and region us-east-1 unless the environment says otherwise).
pub struct S3 {
    pub endpoint: String,
    pub bucket: String,
    pub env: Vec<(&'static str, String)>,
}

impl S3 {
    /// The server, or `None` after a loud skip line naming `test` when nothing answers
    /// there; a failure instead under `LIGHTMAPD_REQUIRE_SERVICES=1`.
    pub async fn find(test: &str) -> Option<S3> {
        let var = |k: &str, d: &str| std::env::var(k).ok().filter(|v| !v.is_empty()).unwrap_or(d.into());
        let endpoint = var("AWS_ENDPOINT_URL", "http://127.0.0.1:9000");
        let bucket = var("LIGHTMAPD_TEST_BUCKET", "lightmapd-test");
        let http = reqwest::Client::builder()
            .timeout(Duration::from_secs(10))
            .build()
            .unwrap();
        let made = match http.put(format!("{endpoint}/{bucket}")).send().await {
            Ok(r) => r.status().as_u16(),
            Err(e) => {
                let msg =
                    format!("{test}: no S3-protocol server at {endpoint} ({e}); run `bash scripts/setup.sh test`");
                if std::env::var("LIGHTMAPD_REQUIRE_SERVICES").as_deref() == Ok("1") {
                    panic!("{msg}; LIGHTMAPD_REQUIRE_SERVICES=1 makes this a failure");
                }
                eprintln!("\n==== SKIPPED {msg} ====\n");
                return None;
            }
        };
        // 200: made; 409: it exists already.
        assert!(
            made == 200 || made == 409,
            "creating bucket {bucket} at {endpoint}: HTTP {made}"
        );
        let env = vec![
            ("AWS_ENDPOINT_URL", endpoint.clone()),
            ("AWS_ACCESS_KEY_ID", var("AWS_ACCESS_KEY_ID", "test")),
            ("AWS_SECRET_ACCESS_KEY", var("AWS_SECRET_ACCESS_KEY", "test")),
            ("AWS_REGION", var("AWS_REGION", "us-east-1")),
            ("AWS_ALLOW_HTTP", "true".to_string()),
        ];
        Some(S3 { endpoint, bucket, env })
    }

    /// A fresh `s3://BUCKET/PREFIX` for one test, so runs and tests do not meet.
    pub fn fresh_url(&self, test: &str) -> String {
        format!("s3://{}/{test}-{}", self.bucket, uuid::Uuid::new_v4().simple())
    }
}

/// A TCP proxy on loopback in front of a real service (PostgreSQL, the S3 server), so a
/// fault test can break the network between lightmapd and it: [`FaultProxy::cut`] closes
/// every open connection at once (a dropped link, or what a restarting server does to
/// its clients), and [`FaultProxy::set_down`] makes the service unreachable (open
/// connections cut, new ones closed as soon as they are accepted) until it is set up
/// again. Runs on the calling test's tokio runtime.
pub struct FaultProxy {
    pub port: u16,
    down: std::sync::Arc<std::sync::atomic::AtomicBool>,
    cut: tokio::sync::watch::Sender<u64>,
    /// Connections accepted, and those refused while down.
    pub accepted: std::sync::Arc<std::sync::atomic::AtomicU64>,
    pub refused: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl FaultProxy {
    pub async fn start(target: String) -> FaultProxy {
        use std::sync::Arc;
        use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let down = Arc::new(AtomicBool::new(false));
        let (cut, cuts) = tokio::sync::watch::channel(0u64);
        let accepted = Arc::new(AtomicU64::new(0));
        let refused = Arc::new(AtomicU64::new(0));
        let (d, a, r) = (down.clone(), accepted.clone(), refused.clone());
        tokio::spawn(async move {
            loop {
                let Ok((mut client, _)) = listener.accept().await else {
                    return;
                };
                if d.load(Ordering::SeqCst) {
                    r.fetch_add(1, Ordering::Relaxed);
                    drop(client);
                    continue;
                }
                a.fetch_add(1, Ordering::Relaxed);
                let mut cuts = cuts.clone();
                cuts.borrow_and_update();
                let target = target.clone();
                tokio::spawn(async move {
                    let Ok(mut server) = tokio::net::TcpStream::connect(&target).await else {
                        return;
                    };
                    tokio::select! {
                        _ = tokio::io::copy_bidirectional(&mut client, &mut server) => {}
                        _ = cuts.changed() => {}
                    }
                });
            }
        });
        FaultProxy {
            port,
            down,
            cut,
            accepted,
            refused,
        }
    }

    /// Closes every connection open now.
    pub fn cut(&self) {
        self.cut.send_modify(|n| *n += 1);
    }

    /// Down: every open connection is cut and new ones are closed at once; up: normal.
    pub fn set_down(&self, down: bool) {
        self.down.store(down, std::sync::atomic::Ordering::SeqCst);
        if down {
            self.cut();
        }
    }
}

/// `HOST:PORT` of a URL (`postgres://u:p@127.0.0.1:5432/db?…`, `http://127.0.0.1:9000`).
pub fn host_port(url: &str) -> String {
    let rest = url.split_once("://").map_or(url, |(_, r)| r);
    let rest = rest.rsplit_once('@').map_or(rest, |(_, r)| r);
    rest.split(['/', '?']).next().unwrap().to_string()
}

/// GET `url`, which must succeed, as JSON.
pub async fn get_json(http: &reqwest::Client, url: &str) -> serde_json::Value {
    let r = http.get(url).send().await.unwrap();
    assert!(r.status().is_success(), "GET {url}: {}", r.status());
    r.json().await.unwrap()
}

/// An EXR's default `R`, `G`, `B` channels, texel by texel.
pub fn exr_rgb(bytes: &[u8]) -> Vec<[f32; 3]> {
    let image = read_exr(bytes).unwrap();
    let layer = &image.layer_data[0];
    let chan = |n: &str| -> Vec<f32> {
        let c = layer.channel_data.list.iter().find(|c| c.name == *n).unwrap();
        c.sample_data.values_as_f32().collect()
    };
    let (r, g, b) = (chan("R"), chan("G"), chan("B"));
    (0..r.len()).map(|i| [r[i], g[i], b[i]]).collect()
}
