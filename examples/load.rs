//! Load generator (issue 12, item 6): holds API requests against a server that is baking,
//! and reports the latency of `GET /v1/jobs/{id}` and the rate of `POST /v1/jobs`.
//!
//! ```sh
//! cargo run --release -- serve --listen 127.0.0.1:8080 --data-dir /tmp/load --max-queued-per-client 100000
//! cargo run --release --example load -- --server http://127.0.0.1:8080 --seconds 30
//! ```
//!
//! How: it uploads the bundled Cornell box and queues `--background` jobs that keep the
//! server's workers busy for the whole run (each bakes for `--bake-seconds`). Then, for
//! `--seconds`, `--readers` tasks each loop `GET /v1/jobs/{id}` over those jobs (a new
//! request as soon as the last one answered: a closed loop, so the figures are latency
//! at the concurrency given, not at a fixed arrival rate), while `--submitters` tasks
//! loop `POST /v1/jobs` (tiny jobs: 16² texels, 1 step). Every request's time is kept;
//! the report gives count, p50, p90, p99 and max per kind, the rates, and any non-2xx
//! answers by status. Client and server share the machine unless `--server` is remote,
//! so on a small machine the client's own CPU use is part of what is measured.
//!
//! Limits: HTTP/1.1 keep-alive through one reqwest client (a connection pool per task
//! would be the same); no TLS.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use clap::Parser;
use serde_json::{Value, json};

#[derive(Parser)]
struct Args {
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    server: String,
    /// How long to hold the load.
    #[arg(long, default_value_t = 30.0)]
    seconds: f64,
    /// Concurrent GET /v1/jobs/{id} loops.
    #[arg(long, default_value_t = 8)]
    readers: usize,
    /// Concurrent POST /v1/jobs loops.
    #[arg(long, default_value_t = 2)]
    submitters: usize,
    /// Jobs queued first to keep the workers baking.
    #[arg(long, default_value_t = 4)]
    background: usize,
    /// How long each background job bakes.
    #[arg(long, default_value_t = 60.0)]
    bake_seconds: f64,
    /// Bearer token, for a server run with --auth.
    #[arg(long)]
    token: Option<String>,
}

#[derive(Default)]
struct Samples {
    latencies: Vec<Duration>,
    statuses: BTreeMap<u16, u64>,
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn report(name: &str, mut s: Samples, seconds: f64) {
    s.latencies.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "{name}: {} requests, {:.1}/s; latency p50 {:.2} ms, p90 {:.2} ms, p99 {:.2} ms, max {:.2} ms; statuses {:?}",
        s.latencies.len(),
        s.latencies.len() as f64 / seconds,
        ms(percentile(&s.latencies, 0.5)),
        ms(percentile(&s.latencies, 0.9)),
        ms(percentile(&s.latencies, 0.99)),
        ms(s.latencies.last().copied().unwrap_or_default()),
        s.statuses
    );
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let server = args.server.trim_end_matches('/').to_string();
    let mut headers = reqwest::header::HeaderMap::new();
    if let Some(t) = &args.token {
        headers.insert(reqwest::header::AUTHORIZATION, format!("Bearer {t}").parse()?);
    }
    let http = reqwest::Client::builder().default_headers(headers).build()?;
    let glb = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/cornell-box.glb"))?;
    let scene: Value = http
        .post(format!("{server}/v1/scenes"))
        .body(glb)
        .send()
        .await?
        .error_for_status()?
        .json()
        .await?;
    let scene = scene["id"].as_str().unwrap_or_default().to_string();
    let mut jobs = Vec::new();
    for seed in 0..args.background {
        let body = json!({"scene": scene, "resolution": 64, "stop": {"seconds": args.bake_seconds}, "seed": seed});
        let job: Value = http
            .post(format!("{server}/v1/jobs"))
            .json(&body)
            .send()
            .await?
            .error_for_status()?
            .json()
            .await?;
        jobs.push(job["id"].as_str().unwrap_or_default().to_string());
    }
    // Let a bake start, so the load meets a busy server.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let until = Instant::now() + Duration::from_secs_f64(args.seconds);

    let mut readers = Vec::new();
    for r in 0..args.readers {
        let (http, server, jobs) = (http.clone(), server.clone(), jobs.clone());
        readers.push(tokio::spawn(async move {
            let mut s = Samples::default();
            let mut i = r;
            while Instant::now() < until {
                let url = format!("{server}/v1/jobs/{}", jobs[i % jobs.len()]);
                i += 1;
                let t = Instant::now();
                let status = match http.get(&url).send().await {
                    Ok(resp) => {
                        let st = resp.status().as_u16();
                        let _ = resp.bytes().await;
                        st
                    }
                    Err(_) => 0,
                };
                s.latencies.push(t.elapsed());
                *s.statuses.entry(status).or_default() += 1;
            }
            s
        }));
    }
    let mut submitters = Vec::new();
    for n in 0..args.submitters {
        let (http, server, scene) = (http.clone(), server.clone(), scene.clone());
        submitters.push(tokio::spawn(async move {
            let mut s = Samples::default();
            let mut seed = 1_000_000 * (n as u64 + 1);
            while Instant::now() < until {
                seed += 1;
                let body = json!({"scene": scene, "resolution": 16, "stop": {"steps": 1}, "seed": seed});
                let t = Instant::now();
                let status = match http.post(format!("{server}/v1/jobs")).json(&body).send().await {
                    Ok(resp) => {
                        let st = resp.status().as_u16();
                        let _ = resp.bytes().await;
                        st
                    }
                    Err(_) => 0,
                };
                s.latencies.push(t.elapsed());
                *s.statuses.entry(status).or_default() += 1;
            }
            s
        }));
    }
    let mut gets = Samples::default();
    for r in readers {
        let s = r.await?;
        gets.latencies.extend(s.latencies);
        for (k, v) in s.statuses {
            *gets.statuses.entry(k).or_default() += v;
        }
    }
    let mut posts = Samples::default();
    for r in submitters {
        let s = r.await?;
        posts.latencies.extend(s.latencies);
        for (k, v) in s.statuses {
            *posts.statuses.entry(k).or_default() += v;
        }
    }
    let busy: Value = http
        .get(format!("{server}/v1/jobs?status=running&limit=1"))
        .send()
        .await?
        .json()
        .await?;
    println!(
        "{} readers, {} submitters, {:.0} s; jobs running at the end: {}",
        args.readers, args.submitters, args.seconds, busy["total"]
    );
    report("GET /v1/jobs/{id}", gets, args.seconds);
    report("POST /v1/jobs", posts, args.seconds);
    // The background bakes have served their purpose.
    for id in &jobs {
        let _ = http.post(format!("{server}/v1/jobs/{id}/cancel")).send().await;
    }
    Ok(())
}
