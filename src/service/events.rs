//! `GET /v1/jobs/{id}/events`: a job's life as server-sent events.
//!
//! Events (each `data` is JSON):
//! - `status`: the whole job document; sent first (so a client that connects late has the
//!   current state at once) and whenever the status changes (queued → running, or back to
//!   queued when a worker died);
//! - `progress`: `{steps, fraction, elapsed_s, error}` (and `step_fraction` inside a long
//!   step, `probes` once probes run), at most ~4 a second;
//! - `snapshot`: `{n, steps, seconds, error, url}` when a snapshot EXR is stored;
//! - `done` (the job document), `failed` (`{reason, job}`), `cancelled` (the job
//!   document): the last event; the stream then ends.
//!
//! How: the job's database row is the only source. The stream re-reads it when this
//! process hears of a change to the job (`Hub::changed`: from its own workers, or, with
//! PostgreSQL, from a `lightmapd_job` NOTIFY sent by whichever process changed it), and
//! at least every half second otherwise (with SQLite a worker in another process changes
//! it without telling us), and sends what differs from what it last sent.
//!
//! Each open stream holds one of the server's `max_event_streams` permits until it ends;
//! past that a new stream is refused with 503 and `Retry-After`.
//!
//! Limits: intermediate progress between two reads is not replayed; a client that needs
//! every snapshot reads `snapshots` from the job and fetches each by number.

use std::convert::Infallible;
use std::time::Duration;

use axum::Extension;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde_json::json;
use tokio::sync::{broadcast, mpsc};

use crate::service::AppState;
use crate::service::auth::Caller;
use crate::service::model::{JobStatus, JobView};
use crate::service::problem::Problem;
use crate::service::routes::describe_job;
use crate::service::routes::{find_job, retry_later};

const POLL: Duration = Duration::from_millis(500);

/// Follow a job: status, progress, snapshot, done / failed / cancelled.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/events",
    tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "Server-sent events: status, progress, snapshot, done, failed, cancelled", content_type = "text/event-stream", body = String),
        (status = 404, body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Too many event streams are open (`--max-event-streams`); `Retry-After` says when to try again", body = Problem, content_type = "application/problem+json")
    )
)]
pub async fn job_events(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, Problem> {
    // Subscribe before the first read, so no change between the two is missed.
    let changes = state.hub.changed.subscribe();
    let first = find_job(&state, &caller, &id).await?;
    let Ok(permit) = state.streams.clone().try_acquire_owned() else {
        return Ok(retry_later(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-streams",
            format!(
                "{} event streams are open, this server's limit (--max-event-streams); poll GET /v1/jobs/{id} or retry later",
                state.config.limits.max_event_streams
            ),
        ));
    };
    let (tx, rx) = mpsc::channel::<Event>(16);
    tokio::spawn(async move {
        let first = describe_job(&state, &first).await;
        follow(state, id, first, changes, tx).await;
        drop(permit);
    });
    let stream = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|e| (Ok::<_, Infallible>(e), rx))
    });
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
        .into_response())
}

fn event(name: &str, data: serde_json::Value) -> Event {
    Event::default().event(name).data(data.to_string())
}

/// Sends the job's events until it ends, the client goes away, or the server stops.
async fn follow(
    state: AppState,
    id: String,
    mut last: JobView,
    mut changes: broadcast::Receiver<String>,
    tx: mpsc::Sender<Event>,
) {
    let mut shutdown = state.shutdown.clone();
    if tx.send(event("status", json!(last))).await.is_err() {
        return;
    }
    let mut sent_snapshots = last.snapshots;
    loop {
        if last.status.is_terminal() {
            let (name, data) = match last.status {
                JobStatus::Succeeded => ("done", json!(last)),
                JobStatus::Failed => ("failed", json!({"reason": last.failure, "job": last})),
                _ => ("cancelled", json!(last)),
            };
            let _ = tx.send(event(name, data)).await;
            return;
        }
        // Wait for a change to this job, the poll interval, the client leaving, or shutdown.
        let deadline = tokio::time::sleep(POLL);
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                m = changes.recv() => match m {
                    Ok(changed) if changed == id => break,
                    Ok(_) => continue,
                    Err(broadcast::error::RecvError::Lagged(_)) => break,
                    Err(broadcast::error::RecvError::Closed) => return,
                },
                _ = &mut deadline => break,
                _ = tx.closed() => return,
                _ = crate::service::shutting_down(&mut shutdown) => return,
            }
        }
        let job = match state.queue.job(&id).await {
            Ok(Some(j)) => describe_job(&state, &j).await,
            Ok(None) => return,
            Err(e) => {
                tracing::warn!(job = %id, error = %e, "event stream cannot read the job");
                continue;
            }
        };
        let mut out = Vec::new();
        if job.status != last.status && !job.status.is_terminal() {
            out.push(event("status", json!(job)));
        }
        if job.snapshots > sent_snapshots {
            for n in sent_snapshots + 1..=job.snapshots {
                let p = job.progress.unwrap_or_default();
                out.push(event(
                    "snapshot",
                    json!({
                        "n": n,
                        "steps": p.steps,
                        "seconds": p.elapsed_s,
                        "error": p.error,
                        "url": format!("/v1/jobs/{id}/lightmap.exr?snapshot={n}"),
                    }),
                ));
            }
            sent_snapshots = job.snapshots;
        }
        if job.progress != last.progress
            && let Some(p) = job.progress
        {
            out.push(event("progress", json!(p)));
        }
        for e in out {
            if tx.send(e).await.is_err() {
                return;
            }
        }
        last = job;
    }
}
