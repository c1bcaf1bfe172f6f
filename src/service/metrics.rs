//! Prometheus metrics, rendered by hand in the text exposition format (version 0.0.4).
//!
//! What is measured: queue depth and jobs by state (read from the database at scrape
//! time, so they are right across processes), and in this process: time per bake step
//! and whole-bake duration as histograms per technique, finished jobs by outcome, and
//! busy workers; the artifact store's usage (bytes and objects under `scenes/` and
//! `jobs/`, measured by the retention sweeper's listing every sweep, issue 24) and what
//! the sweeper and snapshot retention removed.
//!
//! How: a histogram is a mutex around bucket counts; a step takes milliseconds or more,
//! so an uncontended lock per step costs nothing measurable. No metrics crate: five
//! series do not need a registry.
//!
//! Limits: histograms and counters are per process and reset at restart (Prometheus'
//! `rate()` handles resets); the queue gauges are not.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::service::model::JobStatus;

const STEP_BUCKETS: &[f64] = &[0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0];
const BAKE_BUCKETS: &[f64] = &[
    0.1, 0.5, 1.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0,
];

#[derive(Clone, Default)]
struct Histogram {
    buckets: Vec<u64>,
    sum: f64,
    count: u64,
}

impl Histogram {
    fn observe(&mut self, bounds: &[f64], v: f64) {
        if self.buckets.is_empty() {
            self.buckets = vec![0; bounds.len()];
        }
        for (b, n) in bounds.iter().zip(self.buckets.iter_mut()) {
            if v <= *b {
                *n += 1;
            }
        }
        self.sum += v;
        self.count += 1;
    }

    fn render(&self, out: &mut String, name: &str, labels: &str, bounds: &[f64]) {
        for (b, n) in bounds.iter().zip(&self.buckets) {
            let _ = writeln!(out, "{name}_bucket{{{labels},le=\"{b}\"}} {n}");
        }
        let _ = writeln!(out, "{name}_bucket{{{labels},le=\"+Inf\"}} {}", self.count);
        let _ = writeln!(out, "{name}_sum{{{labels}}} {}", self.sum);
        let _ = writeln!(out, "{name}_count{{{labels}}} {}", self.count);
    }
}

#[derive(Default)]
pub struct Metrics {
    steps: Mutex<BTreeMap<String, Histogram>>,
    bakes: Mutex<BTreeMap<String, Histogram>>,
    finished: Mutex<BTreeMap<&'static str, u64>>,
    pub workers: AtomicUsize,
    pub busy: AtomicUsize,
    /// The store's last measured usage, by top-level prefix (`None` before the first).
    store: Mutex<Option<StoreUsage>>,
    /// Finished jobs the retention sweeper removed.
    pub jobs_expired: AtomicUsize,
    /// Snapshot EXR+PNG pairs thinned out by snapshot retention in this process.
    pub snapshots_thinned: AtomicUsize,
}

/// Bytes and objects in the artifact store, by what they belong to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StoreUsage {
    pub scene_bytes: u64,
    pub scene_objects: u64,
    pub job_bytes: u64,
    pub job_objects: u64,
    /// When it was measured (Unix ms).
    pub at_ms: i64,
}

impl Metrics {
    pub fn observe_step(&self, technique: &str, seconds: f64) {
        if let Ok(mut m) = self.steps.lock() {
            m.entry(technique.to_string())
                .or_default()
                .observe(STEP_BUCKETS, seconds);
        }
    }

    pub fn observe_bake(&self, technique: &str, seconds: f64) {
        if let Ok(mut m) = self.bakes.lock() {
            m.entry(technique.to_string())
                .or_default()
                .observe(BAKE_BUCKETS, seconds);
        }
    }

    pub fn job_finished(&self, outcome: JobStatus) {
        if let Ok(mut m) = self.finished.lock() {
            *m.entry(outcome.as_str()).or_default() += 1;
        }
    }

    pub fn set_store_usage(&self, u: StoreUsage) {
        if let Ok(mut m) = self.store.lock() {
            *m = Some(u);
        }
    }

    pub fn store_usage(&self) -> Option<StoreUsage> {
        self.store.lock().ok().and_then(|m| *m)
    }

    /// The exposition text; `counts` are the jobs by state from the database.
    pub fn render(&self, counts: &[(JobStatus, u64)]) -> String {
        let mut out = String::new();
        let queued = counts.iter().find(|(s, _)| *s == JobStatus::Queued).map_or(0, |c| c.1);
        out.push_str("# HELP lightmapd_queue_depth Jobs waiting for a worker.\n# TYPE lightmapd_queue_depth gauge\n");
        let _ = writeln!(out, "lightmapd_queue_depth {queued}");
        out.push_str("# HELP lightmapd_jobs Jobs by state (all processes).\n# TYPE lightmapd_jobs gauge\n");
        for (s, n) in counts {
            let _ = writeln!(out, "lightmapd_jobs{{state=\"{}\"}} {n}", s.as_str());
        }
        out.push_str("# HELP lightmapd_workers Workers in this process.\n# TYPE lightmapd_workers gauge\n");
        let _ = writeln!(out, "lightmapd_workers {}", self.workers.load(Ordering::Relaxed));
        out.push_str("# HELP lightmapd_workers_busy Workers of this process running a bake.\n# TYPE lightmapd_workers_busy gauge\n");
        let _ = writeln!(out, "lightmapd_workers_busy {}", self.busy.load(Ordering::Relaxed));
        out.push_str(
            "# HELP lightmapd_jobs_finished_total Jobs this process finished, by outcome.\n# TYPE lightmapd_jobs_finished_total counter\n",
        );
        if let Ok(m) = self.finished.lock() {
            for s in [JobStatus::Succeeded, JobStatus::Failed, JobStatus::Cancelled] {
                let n = m.get(s.as_str()).copied().unwrap_or(0);
                let _ = writeln!(out, "lightmapd_jobs_finished_total{{outcome=\"{}\"}} {n}", s.as_str());
            }
        }
        if let Some(u) = self.store_usage() {
            out.push_str(
                "# HELP lightmapd_store_bytes Bytes in the artifact store, by kind (measured every retention sweep).\n# TYPE lightmapd_store_bytes gauge\n",
            );
            let _ = writeln!(out, "lightmapd_store_bytes{{kind=\"scenes\"}} {}", u.scene_bytes);
            let _ = writeln!(out, "lightmapd_store_bytes{{kind=\"jobs\"}} {}", u.job_bytes);
            out.push_str("# HELP lightmapd_store_objects Objects in the artifact store, by kind.\n# TYPE lightmapd_store_objects gauge\n");
            let _ = writeln!(out, "lightmapd_store_objects{{kind=\"scenes\"}} {}", u.scene_objects);
            let _ = writeln!(out, "lightmapd_store_objects{{kind=\"jobs\"}} {}", u.job_objects);
            out.push_str("# HELP lightmapd_store_measured_timestamp_seconds When the store usage was measured.\n# TYPE lightmapd_store_measured_timestamp_seconds gauge\n");
            let _ = writeln!(
                out,
                "lightmapd_store_measured_timestamp_seconds {}",
                u.at_ms as f64 / 1000.0
            );
        }
        out.push_str("# HELP lightmapd_jobs_expired_total Finished jobs removed by the retention sweeper of this process.\n# TYPE lightmapd_jobs_expired_total counter\n");
        let _ = writeln!(
            out,
            "lightmapd_jobs_expired_total {}",
            self.jobs_expired.load(Ordering::Relaxed)
        );
        out.push_str("# HELP lightmapd_snapshots_thinned_total Snapshots removed by snapshot retention in this process.\n# TYPE lightmapd_snapshots_thinned_total counter\n");
        let _ = writeln!(
            out,
            "lightmapd_snapshots_thinned_total {}",
            self.snapshots_thinned.load(Ordering::Relaxed)
        );
        out.push_str("# HELP lightmapd_step_seconds Time per bake step.\n# TYPE lightmapd_step_seconds histogram\n");
        if let Ok(m) = self.steps.lock() {
            for (t, h) in m.iter() {
                h.render(
                    &mut out,
                    "lightmapd_step_seconds",
                    &format!("technique=\"{t}\""),
                    STEP_BUCKETS,
                );
            }
        }
        out.push_str(
            "# HELP lightmapd_bake_seconds Duration of finished bakes.\n# TYPE lightmapd_bake_seconds histogram\n",
        );
        if let Ok(m) = self.bakes.lock() {
            for (t, h) in m.iter() {
                h.render(
                    &mut out,
                    "lightmapd_bake_seconds",
                    &format!("technique=\"{t}\""),
                    BAKE_BUCKETS,
                );
            }
        }
        out
    }
}
