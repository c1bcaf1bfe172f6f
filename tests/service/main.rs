//! The service's tests, one binary: the HTTP API (`api`), its limits and guards
//! (`hardening`), the web console in a real browser (`console`), injected faults
//! (`faults`), PostgreSQL and S3 outages (`real_faults`), the S3 artifact store
//! (`s3_store`), the scale-out across processes (`scale_out`) and one job baked as tasks
//! by several worker processes (`farm`).
//!
//! Why one binary instead of seven: each test crate compiles the client side of the
//! same stack again (tokio, reqwest, sqlx, object_store, tungstenite), and seven copies
//! cost about four CPU-minutes of CI's cold build on two cores (docs/performance.md,
//! "CI: where its time goes"). The tests still run two at a time, as they did per
//! binary; the ones that load the CPU hard hold `api::CPU_HEAVY` as before.
//!
//! Run one module with a filter: `cargo test --test service hardening::`.

mod api;
mod console;
mod farm;
mod faults;
mod hardening;
mod real_faults;
mod s3_store;
mod scale_out;
mod service_common;

/// Held by the tests that load both cores for seconds (a long CPU step, three worker
/// processes, a browser baking) and by those whose measure is what a few seconds of CPU
/// buys (snapshots stored in 4 s), so no two of them overlap: in seven binaries only
/// the `api` ones could meet, and they took this lock then too.
static CPU_HEAVY: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());
