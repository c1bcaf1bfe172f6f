//! The artifact store on a real S3-protocol server (issue 11, point 2): `Artifacts` round
//! trips (small objects by one PUT, a large one by a multipart upload, a prefix delete),
//! and the service with `--store s3://…`: an API process and a separate worker process
//! that share only the SQLite file and the bucket, a scene upload and a bake's lightmap
//! download, and the CLI's exit code 2 for a bad `--store`.
//!
//! The server: `AWS_ENDPOINT_URL` (default `http://127.0.0.1:9000`, where
//! `scripts/setup-s3.sh` starts moto's server mode), keys `test`/`test`, region us-east-1
//! unless the environment says otherwise. The bucket (`LIGHTMAPD_TEST_BUCKET`, default
//! `lightmapd-test`) is created with an unsigned `PUT`, which moto accepts; on a server that
//! checks signatures, create it beforehand. Each test works under its own random prefix, so
//! tests run in parallel and runs do not see each other's objects.
//! With no server listening, the tests print a loud SKIPPED line and pass, unless
//! `LIGHTMAPD_REQUIRE_SERVICES=1` (CI) makes them fail.

mod service_common;

use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use bytes::Bytes;
use lightmapd::service::store::{self, Artifacts, MULTIPART_THRESHOLD, PART_SIZE, StoreUrl};
use object_store::ClientConfigKey;
use object_store::aws::AmazonS3ConfigKey;
use serde_json::{Value, json};
use service_common::*;

/// The S3 server the tests use, or `None` (after a loud message) when there is none.
struct S3 {
    endpoint: String,
    bucket: String,
    /// `AWS_*` settings, as environment variables for child processes.
    env: Vec<(&'static str, String)>,
}

impl S3 {
    fn find() -> Option<S3> {
        let var = |k: &str, d: &str| std::env::var(k).ok().filter(|v| !v.is_empty()).unwrap_or(d.into());
        let endpoint = var("AWS_ENDPOINT_URL", "http://127.0.0.1:9000");
        let bucket = var("LIGHTMAPD_TEST_BUCKET", "lightmapd-test");
        if !reachable(&endpoint) {
            let msg =
                format!("no S3-protocol server at {endpoint} (run `bash scripts/setup.sh`, which starts moto there)");
            if std::env::var("LIGHTMAPD_REQUIRE_SERVICES").as_deref() == Ok("1") {
                panic!("{msg}; LIGHTMAPD_REQUIRE_SERVICES=1 makes this a failure");
            }
            // Straight to the stderr handle: libtest captures `eprintln!` of passing tests.
            use std::io::Write;
            let _ = writeln!(std::io::stderr(), "\n######## SKIPPED: {msg} ########\n");
            return None;
        }
        let env = vec![
            ("AWS_ENDPOINT_URL", endpoint.clone()),
            ("AWS_ACCESS_KEY_ID", var("AWS_ACCESS_KEY_ID", "test")),
            ("AWS_SECRET_ACCESS_KEY", var("AWS_SECRET_ACCESS_KEY", "test")),
            ("AWS_REGION", var("AWS_REGION", "us-east-1")),
            ("AWS_ALLOW_HTTP", "true".to_string()),
        ];
        let s3 = S3 { endpoint, bucket, env };
        s3.create_bucket();
        Some(s3)
    }

    fn create_bucket(&self) {
        let status = put_unsigned(&self.endpoint, &self.bucket);
        // 200: made; 409: it exists (BucketAlreadyOwnedByYou / BucketAlreadyExists).
        assert!(
            status == 200 || status == 409,
            "creating bucket {} at {}: HTTP {status}",
            self.bucket,
            self.endpoint
        );
    }

    /// The same settings as `AmazonS3Builder` options, for an in-process store.
    fn overrides(&self) -> Vec<(AmazonS3ConfigKey, String)> {
        self.env
            .iter()
            .map(|(k, v)| {
                let key = match *k {
                    "AWS_ENDPOINT_URL" => AmazonS3ConfigKey::Endpoint,
                    "AWS_ACCESS_KEY_ID" => AmazonS3ConfigKey::AccessKeyId,
                    "AWS_SECRET_ACCESS_KEY" => AmazonS3ConfigKey::SecretAccessKey,
                    "AWS_REGION" => AmazonS3ConfigKey::Region,
                    _ => AmazonS3ConfigKey::Client(ClientConfigKey::AllowHttp),
                };
                (key, v.clone())
            })
            .collect()
    }

    /// A fresh `s3://BUCKET/PREFIX` for one test.
    fn fresh_url(&self, test: &str) -> String {
        format!("s3://{}/{test}-{}", self.bucket, uuid::Uuid::new_v4().simple())
    }

    async fn open(&self, url: &str) -> Artifacts {
        Artifacts::open(&StoreUrl::parse(url).unwrap(), &self.overrides())
            .await
            .unwrap_or_else(|e| panic!("opening {url}: {e}"))
    }
}

/// `PUT /BUCKET` with no signature, which moto takes as "create the bucket": one plain
/// HTTP/1.1 exchange, so it works from sync and async tests alike.
fn put_unsigned(endpoint: &str, bucket: &str) -> u16 {
    use std::io::{Read, Write};
    let host = host_port(endpoint);
    let mut s = TcpStream::connect(&host).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "PUT /{bucket} HTTP/1.1\r\nHost: {host}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut answer = String::new();
    let _ = s.read_to_string(&mut answer);
    answer
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP answer: {answer:?}"))
}

/// `host:port` of an endpoint URL.
fn host_port(endpoint: &str) -> String {
    let hostport = endpoint
        .split_once("://")
        .map_or(endpoint, |(_, r)| r)
        .split('/')
        .next()
        .unwrap_or_default();
    if hostport.contains(':') {
        hostport.to_string()
    } else {
        let port = if endpoint.starts_with("https://") { 443 } else { 80 };
        format!("{hostport}:{port}")
    }
}

fn reachable(endpoint: &str) -> bool {
    let addrs: Vec<SocketAddr> = host_port(endpoint)
        .to_socket_addrs()
        .map(Iterator::collect)
        .unwrap_or_default();
    addrs
        .iter()
        .any(|a| TcpStream::connect_timeout(a, Duration::from_secs(1)).is_ok())
}

/// Bytes that differ from part to part, so a part stored in the wrong place is caught.
fn pattern(len: usize) -> Bytes {
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect::<Vec<u8>>()
        .into()
}

#[tokio::test]
async fn artifacts_round_trip_on_s3() {
    let Some(s3) = S3::find() else { return };
    let url = s3.fresh_url("round-trip");
    let prefix = url.rsplit_once('/').unwrap().1.to_string();
    let a = s3.open(&url).await;

    let small = Bytes::from_static(b"glTF and more");
    let a_key = store::scene_file("s1", "scene.glb");
    a.put(&a_key, small.clone()).await.unwrap();
    assert_eq!(a.get(&a_key).await.unwrap(), Some(small.clone()));
    assert_eq!(a.get(&store::scene_file("s1", "missing.bin")).await.unwrap(), None);

    // Over the threshold: a multipart upload of ceil(len / PART_SIZE) parts, the last short.
    let big_len = MULTIPART_THRESHOLD + PART_SIZE / 2 + 12_345;
    let big = pattern(big_len);
    let big_key = store::final_exr("j1");
    a.put(&big_key, big.clone()).await.unwrap();
    let back = a.get(&big_key).await.unwrap().expect("the multipart object exists");
    assert_eq!(back.len(), big_len);
    assert!(back == big, "the multipart object differs from what was put");

    // The keys live under the URL's prefix in the bucket: the bucket's root sees them there.
    let root = s3.open(&format!("s3://{}", s3.bucket)).await;
    let under_prefix = object_store::path::Path::from(format!("{prefix}/scenes/s1/scene.glb"));
    assert_eq!(root.get(&under_prefix).await.unwrap(), Some(small.clone()));

    // A second put replaces the object whole.
    a.put(&a_key, Bytes::from_static(b"v2")).await.unwrap();
    assert_eq!(a.get(&a_key).await.unwrap().as_deref(), Some(&b"v2"[..]));

    // Deleting a scene's prefix takes its files and nothing else.
    a.put(&store::scene_file("s1", "buffer.bin"), small.clone())
        .await
        .unwrap();
    a.put(&store::scene_file("s10", "scene.glb"), small.clone())
        .await
        .unwrap();
    a.delete_prefix(&store::scene_prefix("s1")).await.unwrap();
    assert_eq!(a.get(&a_key).await.unwrap(), None);
    assert_eq!(a.get(&store::scene_file("s1", "buffer.bin")).await.unwrap(), None);
    assert_eq!(
        a.get(&store::scene_file("s10", "scene.glb")).await.unwrap(),
        Some(small),
        "s10 shares s1's leading characters but is another scene"
    );
    assert!(a.get(&big_key).await.unwrap().is_some());
    a.delete_prefix(&store::job_prefix("j1")).await.unwrap();
    a.delete_prefix(&store::scene_prefix("s10")).await.unwrap();
    assert_eq!(a.get(&big_key).await.unwrap(), None);
}

#[tokio::test]
async fn a_missing_bucket_fails_at_open() {
    let Some(s3) = S3::find() else { return };
    let url = format!("s3://lightmapd-no-such-bucket-{}", uuid::Uuid::new_v4().simple());
    let e = Artifacts::open(&StoreUrl::parse(&url).unwrap(), &s3.overrides())
        .await
        .err()
        .expect("a bucket that does not exist is refused at start-up");
    assert!(e.to_string().contains("cannot reach the artifact store"), "{e}");
}

fn lightmapd(args: &[&str], env: &[(&'static str, String)]) -> Command {
    let mut c = Command::new(bin());
    // The children log warnings only: their info lines would bury the test output.
    c.args(args)
        .env("RUST_LOG", "warn")
        .envs(env.iter().map(|(k, v)| (*k, v.as_str())));
    c
}

/// `lightmapd serve --workers 0` with the S3 store; the address from its first line.
fn spawn_api(dir: &Path, store: &str, env: &[(&'static str, String)]) -> (Child, String) {
    let mut child = lightmapd(
        &["serve", "--listen", "127.0.0.1:0", "--workers", "0", "--store", store],
        env,
    )
    .arg("--data-dir")
    .arg(dir)
    .stdout(Stdio::piped())
    .stderr(Stdio::inherit())
    .spawn()
    .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(child.stdout.take().unwrap()), &mut line).unwrap();
    let url = line
        .trim()
        .strip_prefix("lightmapd listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    (child, url)
}

/// Ends a child this test started, whatever the assertions did.
struct Reap(Child);

impl Drop for Reap {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn service_bakes_through_an_s3_store() {
    let Some(s3) = S3::find() else { return };
    let dir = tempfile::tempdir().unwrap();
    let store = s3.fresh_url("service");
    let (api, url) = spawn_api(dir.path(), &store, &s3.env);
    let _api = Reap(api);
    let db = format!("sqlite://{}", dir.path().join("lightmapd.db").display());
    let worker = lightmapd(
        &[
            "worker",
            "--database-url",
            &db,
            "--store",
            &store,
            "--snapshot-interval-s",
            "0.1",
        ],
        &s3.env,
    )
    .stdout(Stdio::null())
    .stderr(Stdio::inherit())
    .spawn()
    .unwrap();
    let _worker = Reap(worker);

    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let http = reqwest::Client::new();
    let glb = cornell_glb();
    let (scene, job, exr) = rt.block_on(async {
        let r = http
            .post(format!("{url}/v1/scenes"))
            .body(glb.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
        let scene = r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
        let body = json!({"scene": scene, "resolution": 16, "stop": {"steps": 2}, "seed": 1});
        let r = http.post(format!("{url}/v1/jobs")).json(&body).send().await.unwrap();
        assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
        let job = r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
        let start = Instant::now();
        loop {
            let j: Value = http
                .get(format!("{url}/v1/jobs/{job}"))
                .send()
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
            match j["status"].as_str().unwrap() {
                "succeeded" => break,
                "failed" | "cancelled" => panic!("the bake did not succeed: {j:#}"),
                _ => {}
            }
            assert!(start.elapsed() < DEADLINE, "job {job} never ended: {j:#}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let r = http
            .get(format!("{url}/v1/jobs/{job}/lightmap.exr"))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        (scene, job, r.bytes().await.unwrap())
    });
    exr_is_whole(&exr).unwrap();

    // What the API served is what the worker stored in the bucket, and the scene the API
    // stored is the upload, byte for byte; nothing went to a local folder.
    rt.block_on(async {
        let a = s3.open(&store).await;
        assert_eq!(a.get(&store::final_exr(&job)).await.unwrap(), Some(exr.clone()));
        assert_eq!(
            a.get(&store::scene_file(&scene, "scene.glb")).await.unwrap().as_deref(),
            Some(glb.as_slice())
        );
        a.delete_prefix(&store::job_prefix(&job)).await.unwrap();
        a.delete_prefix(&store::scene_prefix(&scene)).await.unwrap();
    });
    assert!(
        !dir.path().join("objects").exists(),
        "an S3 store writes no local objects/"
    );
}

fn run(args: &[&str]) -> Output {
    lightmapd(args, &[]).stdin(Stdio::null()).output().unwrap()
}

#[test]
fn a_bad_store_url_is_exit_code_2() {
    let dir = tempfile::tempdir().unwrap();
    let db = format!("sqlite://{}", dir.path().join("lightmapd.db").display());
    let data = dir.path().to_str().unwrap();
    for (args, says) in [
        (
            vec!["serve", "--data-dir", data, "--store", "gs://maps/x"],
            "unsupported store scheme \"gs\"",
        ),
        (
            vec!["serve", "--data-dir", data, "--store", "s3://Maps_2024/x"],
            "may hold only lower-case letters",
        ),
        (
            vec!["worker", "--database-url", &db, "--store", "s3://maps/a//b"],
            "is not a valid key",
        ),
        (
            vec!["worker", "--database-url", &db, "--store", "file://"],
            "names no directory",
        ),
    ] {
        let out = run(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
        assert!(stderr.contains("--store"), "the error names the flag: {stderr}");
        assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    }
    // Nothing was started, so nothing was made.
    assert!(!dir.path().join("lightmapd.db").exists());
}
