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

use crate::service_common;

use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use bytes::Bytes;
use lightmapd::service::store::{self, Artifacts, MULTIPART_THRESHOLD, PART_SIZE, StoreUrl};
use object_store::ClientConfigKey;
use object_store::aws::AmazonS3ConfigKey;
use serde_json::{Value, json};
use service_common::*;

/// The settings of `s3` (`service_common::S3`) as `AmazonS3Builder` options, for an
/// in-process store.
pub(crate) fn overrides(s3: &S3) -> Vec<(AmazonS3ConfigKey, String)> {
    s3.env
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

pub(crate) async fn open(s3: &S3, url: &str) -> Artifacts {
    Artifacts::open(&StoreUrl::parse(url).unwrap(), &overrides(s3))
        .await
        .unwrap_or_else(|e| panic!("opening {url}: {e}"))
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
    let Some(s3) = S3::find("artifacts_round_trip_on_s3").await else {
        return;
    };
    let url = s3.fresh_url("round-trip");
    let prefix = url.rsplit_once('/').unwrap().1.to_string();
    let a = open(&s3, &url).await;

    let small = Bytes::from_static(b"glTF and more");
    let a_key = store::scene_file("s1", "scene.glb");
    a.put(&a_key, small.clone()).await.unwrap();
    assert_eq!(a.get(&a_key).await.unwrap(), Some(small.clone()));
    assert_eq!(a.get(&store::scene_file("s1", "missing.bin")).await.unwrap(), None);

    // Over the threshold: a multipart upload of ceil(len / PART_SIZE) parts, the last short.
    let big_len = MULTIPART_THRESHOLD + PART_SIZE / 2 + 12_345;
    let big = pattern(big_len);
    let big_key = store::page_exr("j1", 0);
    a.put(&big_key, big.clone()).await.unwrap();
    let back = a.get(&big_key).await.unwrap().expect("the multipart object exists");
    assert_eq!(back.len(), big_len);
    assert!(back == big, "the multipart object differs from what was put");

    // The keys live under the URL's prefix in the bucket: the bucket's root sees them there.
    let root = open(&s3, &format!("s3://{}", s3.bucket)).await;
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
    let Some(s3) = S3::find("a_missing_bucket_fails_at_open").await else {
        return;
    };
    let url = format!("s3://lightmapd-no-such-bucket-{}", uuid::Uuid::new_v4().simple());
    let e = Artifacts::open(&StoreUrl::parse(&url).unwrap(), &overrides(&s3))
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
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let Some(s3) = rt.block_on(S3::find("service_bakes_through_an_s3_store")) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let store = s3.fresh_url("service");
    let (api, url) = spawn_serve_env(dir.path(), 0, &["--store", &store], &s3.env);
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
        let a = open(&s3, &store).await;
        assert_eq!(a.get(&store::page_exr(&job, 0)).await.unwrap(), Some(exr.clone()));
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
