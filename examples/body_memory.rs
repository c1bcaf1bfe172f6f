//! Peak memory of the API process under large bodies (issue 24 point 4), and a slow
//! upload: the figures of docs/reliability.md, "Bounded memory".
//!
//! ```sh
//! cargo build --release
//! target/release/lightmapd serve --workers 0 --data-dir /tmp/bodies &   # note its pid
//! target/release/lightmapd worker --database-url sqlite:///tmp/bodies/lightmapd.db --store /tmp/bodies/objects &
//! cargo run --release --example body_memory -- --server http://127.0.0.1:8080 --pid PID
//! ```
//!
//! How: (1) `--uploads` concurrent uploads of distinct valid `.glb` files of
//! `--upload-mb` MB each (the bundled Cornell box with its binary chunk padded: the
//! importer reads every byte, the mesh stays 32 triangles), sent as streams of 64 kB
//! chunks; (2) one job baked at `--resolution` (its final EXR is the large download) and
//! `--downloads` concurrent downloads of it, each read slowly (64 kB every 2 ms) so they
//! overlap; (3) one upload of `--slow-mb` MB at `--slow-kbps` kB/s, if asked. While each
//! phase runs, the API process's resident set (`VmRSS` in `/proc/PID/status`) is
//! sampled every 20 ms; the report gives the phase's peak above the idle figure, each
//! request's status, and the time taken.
//!
//! Limits: client and server share the machine; the figures are the server process's
//! own memory, not the machine's.

use std::time::{Duration, Instant};

use clap::Parser;
use futures_util::StreamExt;
use serde_json::{Value, json};

#[derive(Parser)]
struct Args {
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    server: String,
    /// The API process, whose memory is measured.
    #[arg(long)]
    pid: u32,
    #[arg(long, default_value_t = 8)]
    uploads: usize,
    #[arg(long, default_value_t = 200)]
    upload_mb: usize,
    #[arg(long, default_value_t = 8)]
    downloads: usize,
    /// Lightmap side of the job whose EXR is downloaded (2048: about 50 MB).
    #[arg(long, default_value_t = 2048)]
    resolution: u32,
    /// Size of the slow upload in MB (0: none).
    #[arg(long, default_value_t = 0)]
    slow_mb: usize,
    #[arg(long, default_value_t = 100)]
    slow_kbps: usize,
}

fn rss_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

/// Samples the process's RSS until `done` is set; the peak in kB.
fn sample(pid: u32, done: std::sync::Arc<std::sync::atomic::AtomicBool>) -> std::thread::JoinHandle<u64> {
    std::thread::spawn(move || {
        let mut peak = 0;
        while !done.load(std::sync::atomic::Ordering::Relaxed) {
            peak = peak.max(rss_kb(pid));
            std::thread::sleep(Duration::from_millis(20));
        }
        peak.max(rss_kb(pid))
    })
}

/// The Cornell box with `pad` bytes appended to its binary chunk (and its buffer), the
/// padding's first byte set to `tag` so every file is a distinct scene.
fn padded_glb(base: &[u8], pad: usize, tag: u8) -> Vec<u8> {
    let u32_at = |o: usize| u32::from_le_bytes(base[o..o + 4].try_into().unwrap()) as usize;
    let json_len = u32_at(12);
    let mut json: Value = serde_json::from_slice(&base[20..20 + json_len]).unwrap();
    let bin_at = 20 + json_len;
    let bin_len = u32_at(bin_at);
    let bin = &base[bin_at + 8..bin_at + 8 + bin_len];
    let new_len = bin_len + pad;
    json["buffers"][0]["byteLength"] = json!(new_len);
    let mut text = serde_json::to_vec(&json).unwrap();
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let total = 12 + 8 + text.len() + 8 + new_len;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(text.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&text);
    out.extend_from_slice(&(new_len as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(bin);
    let start = out.len();
    out.resize(start + pad, 0);
    out[start] = tag;
    out
}

fn chunked(bytes: Vec<u8>, chunk: usize, gap: Duration) -> reqwest::Body {
    let bytes = bytes::Bytes::from(bytes);
    let pieces: Vec<bytes::Bytes> = (0..bytes.len().div_ceil(chunk))
        .map(|i| bytes.slice(i * chunk..((i + 1) * chunk).min(bytes.len())))
        .collect();
    reqwest::Body::wrap_stream(futures_util::stream::iter(pieces).then(move |p| async move {
        if !gap.is_zero() {
            tokio::time::sleep(gap).await;
        }
        Ok::<_, std::io::Error>(p)
    }))
}

#[tokio::main]
async fn main() {
    let a = Args::parse();
    let http = reqwest::Client::builder().pool_max_idle_per_host(0).build().unwrap();
    let base = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/cornell-box.glb")).unwrap();
    let idle = rss_kb(a.pid);
    println!("API process {}: {} MB resident at rest", a.pid, idle / 1024);

    // (1) Concurrent large uploads.
    let files: Vec<Vec<u8>> = (0..a.uploads)
        .map(|i| padded_glb(&base, a.upload_mb << 20, i as u8 + 1))
        .collect();
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let sampler = sample(a.pid, done.clone());
    let t = Instant::now();
    let mut tasks = Vec::new();
    for f in files {
        let (http, url) = (http.clone(), format!("{}/v1/scenes", a.server));
        tasks.push(tokio::spawn(async move {
            let t = Instant::now();
            let r = http
                .post(url)
                .header("content-type", "model/gltf-binary")
                .body(chunked(f, 64 << 10, Duration::ZERO))
                .send()
                .await;
            let status = match r {
                Ok(r) => r.status().as_u16(),
                Err(_) => 0,
            };
            (status, t.elapsed().as_secs_f64())
        }));
    }
    let mut statuses = Vec::new();
    for t in tasks {
        statuses.push(t.await.unwrap());
    }
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    let peak = sampler.join().unwrap();
    println!(
        "{} concurrent uploads of {} MB: {:.1} s; peak {} MB resident ({} MB above rest); status, seconds: {:?}",
        a.uploads,
        a.upload_mb,
        t.elapsed().as_secs_f64(),
        peak / 1024,
        peak.saturating_sub(idle) / 1024,
        statuses
    );

    // (2) Concurrent large downloads of one job's final EXR.
    let r = http
        .post(format!("{}/v1/scenes", a.server))
        .body(base.clone())
        .send()
        .await
        .unwrap();
    let scene = r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let r = http
        .post(format!("{}/v1/jobs", a.server))
        .json(&json!({"scene": scene, "resolution": a.resolution, "stop": {"steps": 1}, "denoise": "none"}))
        .send()
        .await
        .unwrap();
    let job = r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let t = Instant::now();
    loop {
        let j: Value = http
            .get(format!("{}/v1/jobs/{job}", a.server))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        match j["status"].as_str().unwrap() {
            "succeeded" => break,
            "failed" | "cancelled" => panic!("job {job}: {j:#}"),
            _ => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    }
    println!(
        "job {job} ({}²) baked in {:.1} s",
        a.resolution,
        t.elapsed().as_secs_f64()
    );
    let at_rest = rss_kb(a.pid);
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let sampler = sample(a.pid, done.clone());
    let t = Instant::now();
    let mut tasks = Vec::new();
    for _ in 0..a.downloads {
        let (http, url) = (http.clone(), format!("{}/v1/jobs/{job}/lightmap.exr", a.server));
        tasks.push(tokio::spawn(async move {
            let r = http.get(url).send().await.unwrap();
            let status = r.status().as_u16();
            let mut n = 0usize;
            let mut s = r.bytes_stream();
            while let Some(c) = s.next().await {
                n += c.unwrap().len();
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
            (status, n)
        }));
    }
    let mut got = Vec::new();
    for t in tasks {
        got.push(t.await.unwrap());
    }
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    let peak = sampler.join().unwrap();
    println!(
        "{} concurrent downloads: {:.1} s; peak {} MB resident ({} MB above rest); status, bytes: {:?}",
        a.downloads,
        t.elapsed().as_secs_f64(),
        peak / 1024,
        peak.saturating_sub(at_rest) / 1024,
        got
    );

    // (3) A slow upload.
    if a.slow_mb > 0 {
        let f = padded_glb(&base, a.slow_mb << 20, 0xee);
        // 10 chunks a second of kbps/10 kB each.
        let chunk = a.slow_kbps * 1000 / 10;
        let t = Instant::now();
        let r = http
            .post(format!("{}/v1/scenes", a.server))
            .header("content-type", "model/gltf-binary")
            .body(chunked(f, chunk, Duration::from_millis(100)))
            .send()
            .await
            .unwrap();
        println!(
            "one upload of {} MB at {} kB/s: HTTP {} after {:.0} s",
            a.slow_mb,
            a.slow_kbps,
            r.status().as_u16(),
            t.elapsed().as_secs_f64()
        );
    }
}
