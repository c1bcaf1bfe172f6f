//! Job routes: submit (checked whole before it is queued, with the warnings of a job
//! that will bake to nothing useful), look up with its tasks and what it waits for, list,
//! cancel, delete.

use std::collections::HashMap;

use axum::Extension;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;

use crate::service::auth::Caller;
use crate::service::model::{
    BlocklistEntry, JobCreated, JobList, JobSpec, JobStatus, JobView, TaskView, TasksView, rfc3339,
};
use crate::service::problem::Problem;
use crate::service::queue::{
    BLOCKLIST_AFTER, Cancellation, Enqueued, JobDeletion, JobRecord, TaskStatus, WORKER_ALIVE_MS, WorkerRecord, now_ms,
};
use crate::service::worker::job_memory;
use crate::service::{AppState, StopSignal};

use super::{content_type, retry_later};

/// Submit a bake job.
#[utoipa::path(
    post,
    path = "/v1/jobs",
    tag = "jobs",
    request_body(content = JobSpec, content_type = "application/json"),
    responses(
        (status = 202, description = "Queued", body = JobCreated),
        (status = 400, description = "Not JSON", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "The body is over `--max-body-bytes`", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not application/json", body = Problem, content_type = "application/problem+json"),
        (status = 403, description = "`priority` above `--max-priority` from an editor token (or without authentication); an admin token may set it", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "A field is invalid or over a server limit (`field` names it; an estimated memory over the limit names `resolution`), the scene does not exist, or the body is not a JSON object", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "The client already has `--max-queued-per-client` queued jobs; `Retry-After` says when to try again", body = Problem, content_type = "application/problem+json")
    )
)]
pub(super) async fn create_job(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, Problem> {
    let ct = content_type(&headers);
    if !(ct.is_empty() || ct == "application/json") {
        return Err(Problem::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!("content type {ct:?}: send the job as application/json"),
        ));
    }
    let limits = &state.config.limits;
    // serde reads a struct from a JSON array too (fields in order): only an object is a job.
    if let Ok(v) = serde_json::from_slice::<serde_json::Value>(&body)
        && !v.is_object()
    {
        let kind = match v {
            serde_json::Value::Array(_) => "an array",
            serde_json::Value::String(_) => "a string",
            serde_json::Value::Number(_) => "a number",
            serde_json::Value::Bool(_) => "a boolean",
            _ => "null",
        };
        return Err(Problem::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid-field",
            format!("the job must be a JSON object ({{\"scene\": …}}), got {kind}"),
        ));
    }
    let spec = JobSpec::parse_with(&body, limits)?;
    if spec.priority > limits.max_priority && !caller.admin {
        let mut p = Problem::new(
            StatusCode::FORBIDDEN,
            "forbidden",
            format!(
                "priority {} is above {}, the most this server allows {} (--max-priority); an admin token may set it",
                spec.priority,
                limits.max_priority,
                if caller.token.is_some() {
                    "an editor token"
                } else {
                    "without authentication"
                }
            ),
        );
        p.field = Some("priority".into());
        return Err(p);
    }
    let no_scene = || Problem::invalid_field("scene", format!("no scene with id {:?}; upload it first", spec.scene));
    let scene = match state.queue.scene(&spec.scene).await? {
        Some(s) if caller.owns(s.client.as_deref()) => s,
        _ => return Err(no_scene()),
    };
    crate::service::model::check_against_scene(&scene.report, &spec)?;
    let warnings = crate::service::model::job_warnings(&scene.report, &spec);
    if let Some(id) = &spec.reference {
        let record = state.queue.job(id).await?.filter(|j| caller.owns(j.client.as_deref()));
        crate::service::model::check_reference(&spec, id, record.as_ref().map(|j| (&j.spec, j.status)))?;
    }
    let need = job_memory(&scene.report, &spec);
    if need > limits.max_job_memory_bytes {
        return Err(Problem::invalid_field(
            "resolution",
            format!(
                "the job needs an estimated {} MiB ({}² texels, {} triangles), more than this server's limit of {} MiB per job (--max-job-memory-mb): lower the resolution",
                need >> 20,
                spec.resolution,
                scene.report["triangles"],
                limits.max_job_memory_bytes >> 20
            ),
        ));
    }
    let id = uuid::Uuid::new_v4().to_string();
    let job = match state
        .queue
        .enqueue(&id, &spec, &caller.client, limits.max_queued_per_client, need, now_ms())
        .await?
    {
        Enqueued::Queued(job) => job,
        Enqueued::NoScene => return Err(no_scene()),
        Enqueued::QueueFull(n) => {
            return Ok(retry_later(
                StatusCode::TOO_MANY_REQUESTS,
                "too-many-jobs",
                format!(
                    "{n} of your jobs are queued, this server's limit per client (--max-queued-per-client); retry when one has started"
                ),
            ));
        }
    };
    state.hub.work.notify_one();
    tracing::info!(job = %id, technique = %spec.technique, scene = %spec.scene, warnings = warnings.len(), "job queued");
    let mut resp = (
        StatusCode::ACCEPTED,
        axum::Json(JobCreated {
            id: job.id.clone(),
            status: job.status,
            warnings,
        }),
    )
        .into_response();
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/jobs/{id}")) {
        resp.headers_mut().insert(header::LOCATION, loc);
    }
    Ok(resp)
}

fn job_view(j: &JobRecord) -> JobView {
    JobView {
        id: j.id.clone(),
        status: j.status,
        scene: j.scene_id.clone(),
        spec: j.spec.clone(),
        priority: j.priority,
        attempts: j.attempts,
        worker: j.worker.clone(),
        created_at: rfc3339(j.created_at),
        started_at: j.started_at.map(rfc3339),
        finished_at: j.finished_at.map(rfc3339),
        progress: j.progress.clone().and_then(|p| serde_json::from_value(p).ok()),
        plan: j.plan.clone(),
        history: serde_json::from_value(j.history.clone()).unwrap_or_default(),
        snapshots: j.snapshots,
        summary: j.summary.clone(),
        failure: j.failure.clone(),
        cancel_requested: j.cancel_requested,
        tasks: None,
        waiting_for: None,
    }
}

/// `job_view` with what only one job's page shows: a split job's tasks and
/// blocklist, and what a job nobody takes is waiting for (issue 25). A database error
/// here leaves those parts out rather than failing the request.
pub async fn describe_job(state: &AppState, j: &JobRecord) -> JobView {
    let mut view = job_view(j);
    let (tasks, failures) = if j.tasks > 0 {
        let tasks = state.queue.tasks(&j.id).await.unwrap_or_default();
        let failures = state.queue.task_failures(&j.id).await.unwrap_or_default();
        (tasks, failures)
    } else {
        (Vec::new(), Vec::new())
    };
    let blocklisted: Vec<BlocklistEntry> = failures
        .iter()
        .filter(|(_, n)| *n >= BLOCKLIST_AFTER)
        .map(|(w, n)| BlocklistEntry {
            worker: w.clone(),
            failures: *n,
        })
        .collect();
    let waiting = j.status == JobStatus::Queued
        || (j.status == JobStatus::Running
            && tasks.iter().any(|t| t.status == TaskStatus::Queued)
            && !tasks.iter().any(|t| t.status == TaskStatus::Running));
    if waiting && let Ok(live) = state.queue.workers(state.db_now() - WORKER_ALIVE_MS).await {
        view.waiting_for = waiting_for(j, &live, &blocklisted);
    }
    if j.tasks > 0 {
        let now = state.db_now();
        // What each bake task covers, from the engine's split of the job (a split the
        // submission already accepted; on a failure the tasks are shown without it).
        let ranges = j.spec.task_ranges().unwrap_or_default();
        view.tasks = Some(TasksView {
            count: j.tasks,
            regions: j.spec.regions.unwrap_or(1).max(1),
            rounds: j.spec.in_rounds().then(|| j.spec.rounds.unwrap_or(1)),
            list: tasks
                .into_iter()
                .map(|t| TaskView {
                    index: t.index,
                    region: (!t.is_merge())
                        .then(|| ranges.get(t.index as usize).map(|r| r.region))
                        .flatten(),
                    round: (!t.is_merge())
                        .then(|| ranges.get(t.index as usize).filter(|r| r.rounds > 0).map(|r| r.round))
                        .flatten(),
                    step_range: (!t.is_merge())
                        .then(|| {
                            ranges
                                .get(t.index as usize)
                                .map(|r| [r.first_step, r.first_step + r.steps])
                        })
                        .flatten(),
                    chain_seed: (!t.is_merge())
                        .then(|| ranges.get(t.index as usize).filter(|r| r.chain))
                        .flatten()
                        .map(|r| r.seed(j.spec.seed)),
                    kind: if t.is_merge() { "merge" } else { "bake" }.into(),
                    status: t.status,
                    attempts: t.attempts,
                    worker: t.worker,
                    steps: t.steps,
                    seconds: t.seconds,
                    error: t.error,
                    failure: t.failure,
                    wall_s: t
                        .started_at
                        .map(|a| (t.finished_at.unwrap_or(now).max(a) - a) as f64 / 1000.0),
                })
                .collect(),
            blocklisted,
        });
    }
    view
}

/// Why no live worker takes `j`, or `None` when one can and the job just waits its turn.
fn waiting_for(j: &JobRecord, live: &[WorkerRecord], blocklisted: &[BlocklistEntry]) -> Option<String> {
    if live.is_empty() {
        return Some("a worker: none is running (start `lightmapd worker`, or `serve` with --workers above 0)".into());
    }
    let req = j.spec.requires.unwrap_or_default();
    let able: Vec<&WorkerRecord> = live
        .iter()
        .filter(|w| {
            let c = &w.capabilities;
            (!req.gpu || c.gpu) && (!req.oidn || c.oidn) && c.memory_bytes >= j.memory_bytes
        })
        .collect();
    if able.is_empty() {
        let memory = format!(
            "a per-job memory limit of at least {} MiB (the job's estimate; --max-job-memory-mb)",
            j.memory_bytes >> 20
        );
        let need: Vec<String> = [
            req.gpu.then(|| "a hardware GPU (requires.gpu)".to_string()),
            req.oidn.then(|| "OIDN (requires.oidn)".to_string()),
            live.iter()
                .any(|w| w.capabilities.memory_bytes < j.memory_bytes)
                .then_some(memory),
        ]
        .into_iter()
        .flatten()
        .collect();
        let have: Vec<String> = live
            .iter()
            .take(4)
            .map(|w| {
                let c = &w.capabilities;
                let adapter = match (&c.adapter, &c.adapter_kind) {
                    (Some(a), Some(k)) => format!("{a}, {k}"),
                    _ => "no GPU adapter".into(),
                };
                format!(
                    "{} ({adapter}; OIDN {}; {} MiB a job)",
                    w.id,
                    if c.oidn { "yes" } else { "no" },
                    c.memory_bytes >> 20
                )
            })
            .collect();
        let more = if live.len() > 4 { ", …" } else { "" };
        return Some(format!(
            "a worker with {}: none of the {} live workers has all of it ({}{more})",
            need.join(" and "),
            live.len(),
            have.join("; ")
        ));
    }
    if j.tasks > 0 && able.iter().all(|w| blocklisted.iter().any(|b| b.worker == w.id)) {
        return Some(format!(
            "a worker that has not failed this job's tasks: each of the {} live workers that meet its requires failed them {BLOCKLIST_AFTER} times and is blocklisted for it",
            able.len()
        ));
    }
    None
}

/// List jobs, newest first.
#[utoipa::path(
    get,
    path = "/v1/jobs",
    tag = "jobs",
    params(
        ("status" = Option<JobStatus>, Query, description = "Only jobs in this state"),
        ("limit" = Option<u32>, Query, description = "Page size, 1 to 500 (default 50)"),
        ("offset" = Option<u64>, Query, description = "Jobs to skip (default 0)")
    ),
    responses(
        (status = 200, body = JobList),
        (status = 422, body = Problem, content_type = "application/problem+json")
    )
)]
pub(super) async fn list_jobs(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<axum::Json<JobList>, Problem> {
    for k in q.keys() {
        if !["status", "limit", "offset"].contains(&k.as_str()) {
            return Err(Problem::invalid_field(
                k.clone(),
                format!("unknown query parameter {k:?}; known: status, limit, offset"),
            ));
        }
    }
    let status = match q.get("status") {
        None => None,
        Some(s) => Some(JobStatus::parse(s).ok_or_else(|| {
            Problem::invalid_field(
                "status",
                format!("unknown status {s:?}; one of queued, running, succeeded, failed, cancelled"),
            )
        })?),
    };
    let limit = match q.get("limit") {
        None => 50,
        Some(s) => s
            .parse::<u32>()
            .ok()
            .filter(|n| (1..=500).contains(n))
            .ok_or_else(|| Problem::invalid_field("limit", format!("limit must be 1 to 500, got {s:?}")))?,
    };
    let offset = match q.get("offset") {
        None => 0,
        Some(s) => s
            .parse::<u64>()
            .map_err(|_| Problem::invalid_field("offset", format!("offset must be a whole number >= 0, got {s:?}")))?,
    };
    let (jobs, total) = state.queue.list(status, caller.scope(), limit, offset).await?;
    Ok(axum::Json(JobList {
        jobs: jobs.iter().map(job_view).collect(),
        total,
        limit,
        offset,
    }))
}

/// The job, if it exists and the caller may see it (else 404 either way).
pub async fn find_job(state: &AppState, caller: &Caller, id: &str) -> Result<JobRecord, Problem> {
    match state.queue.job(id).await? {
        Some(j) if caller.owns(j.client.as_deref()) => Ok(j),
        _ => Err(Problem::not_found("job", id)),
    }
}

/// A job's status, progress, plan, error history and failure reason.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}",
    tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, body = JobView),
        (status = 404, body = Problem, content_type = "application/problem+json")
    )
)]
pub(super) async fn get_job(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<axum::Json<JobView>, Problem> {
    let job = find_job(&state, &caller, &id).await?;
    Ok(axum::Json(describe_job(&state, &job).await))
}

/// Cancel a job: a queued one at once, a running one within one bake step.
#[utoipa::path(
    post,
    path = "/v1/jobs/{id}/cancel",
    tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 202, description = "Cancelled, or cancellation requested (a running job stops within one step)", body = JobView),
        (status = 404, body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "The job has already finished", body = Problem, content_type = "application/problem+json")
    )
)]
pub(super) async fn cancel_job(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, Problem> {
    find_job(&state, &caller, &id).await?;
    match state.queue.cancel(&id, now_ms()).await? {
        Cancellation::NotFound => return Err(Problem::not_found("job", &id)),
        Cancellation::AlreadyFinished(s) => {
            return Err(Problem::conflict(format!(
                "job {id} has already finished ({})",
                s.as_str()
            )));
        }
        Cancellation::Cancelled => tracing::info!(job = %id, "queued job cancelled"),
        Cancellation::Requested => {
            tracing::info!(job = %id, "cancel requested");
            state.hub.stop_local(&id, StopSignal::Cancel);
        }
    }
    state.hub.job_changed(&id);
    let job = find_job(&state, &caller, &id).await?;
    Ok((StatusCode::ACCEPTED, axum::Json(describe_job(&state, &job).await)).into_response())
}

/// Delete a finished job and every artifact it made (lightmap, preview, snapshots).
#[utoipa::path(
    delete,
    path = "/v1/jobs/{id}",
    tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 204, description = "Deleted, with its artifacts"),
        (status = 404, body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "The job is queued or running: cancel it first", body = Problem, content_type = "application/problem+json")
    )
)]
pub(super) async fn delete_job(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<StatusCode, Problem> {
    find_job(&state, &caller, &id).await?;
    match crate::service::remove_job(&state, &id).await? {
        JobDeletion::Deleted => {
            tracing::info!(job = %id, "job deleted");
            Ok(StatusCode::NO_CONTENT)
        }
        JobDeletion::NotFound => Err(Problem::not_found("job", &id)),
        JobDeletion::Unfinished(s) => Err(Problem::conflict(format!(
            "job {id} is {}: cancel it first (POST /v1/jobs/{id}/cancel), then delete it once it has ended",
            s.as_str()
        ))),
    }
}
