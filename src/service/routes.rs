//! HTTP routes (DESIGN §7): each parses and validates, calls the queue or the store, and
//! answers. Errors are `application/problem+json` ([`Problem`]); the OpenAPI document
//! ([`ApiDoc`], served at `/openapi.json`) is generated from the annotations here.
//!
//! Scene uploads: a `.glb` body (`model/gltf-binary` or `application/octet-stream`), or
//! `multipart/form-data` with one `.gltf` part and its buffers and images (each part's
//! file name is the name the `.gltf` refers to). The id is the first 32 hex digits of the
//! SHA-256 of the content, so the same upload gives the same id (201 the first time, 200
//! after). The scene is imported before it is stored: a bad one gets 422 with the
//! importer's message and nothing is kept.
//!
//! Every route gets a [`Caller`] from [`auth::authenticate`]; with tokens on, a scene or
//! job of another token is answered exactly like a missing one (404). Scene ids come
//! from the content (and the owning token), job ids are random UUIDs: nothing a client
//! sends becomes a filesystem path, and part names of a multipart upload must be plain
//! file names (no folders, no leading dot, no control characters, at most 255 bytes).
//!
//! Every error leaves as problem+json: handlers return [`Problem`], and
//! [`problem_bodies`] rewrites the plain-text answers axum and tower-http produce on
//! their own (a malformed path or query, a body over the limit, a timeout).
//!
//! Downloads (lightmaps, previews, scenes) are streamed from the store as they are read
//! (issue 24), so a large EXR is never held whole by the API; snapshot EXRs (small, and
//! checked against snapshot retention) are read whole.
//!
//! Limits: uploads are received into a spool folder on disk as they arrive
//! ([`upload`]), with an idle timeout per chunk instead of the request time limit, then
//! imported (at most `--max-concurrent-imports` at once; the importer parses from memory,
//! so an import holds its scene) and written to the store from the file in parts. Large
//! bodies (uploads of unknown length or over 16 MiB, downloads over 16 MiB) take one of
//! `--max-large-bodies` permits for as long as they run; past it, 503 with
//! `Retry-After`. `.gltf` URIs must be
//! data URIs or the plain names of uploaded parts (no folders), so an upload can never
//! make the server read its own files.

use std::collections::HashMap;

use axum::Extension;
use axum::Router;
use axum::body::Body;
use axum::extract::{DefaultBodyLimit, FromRequest, Multipart, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use bytes::Bytes;
use sha2::{Digest, Sha256};
use utoipa::OpenApi;

use crate::service::auth::{self, Caller};
use crate::service::console::{DenoiserInfo, SplitInfo, TechniqueInfo, TechniqueList};
use crate::service::model::{
    BlocklistEntry, Health, JobCreated, JobList, JobSpec, JobStatus, JobView, ProbeProgress, Progress, SceneView,
    TaskView, TasksView, rfc3339,
};
use crate::service::problem::{PROBLEM_JSON, Problem};
use crate::service::queue::{
    BLOCKLIST_AFTER, Cancellation, Enqueued, JobDeletion, JobRecord, SceneDeletion, SceneRecord, TaskStatus,
    WORKER_ALIVE_MS, WorkerRecord, now_ms,
};
use crate::service::worker::{ImportFailure, SceneFiles, import_dir, import_files, job_memory};
use crate::service::{AppState, StopSignal, events, store, upload};

/// What a client told to come back later is told to wait, in seconds.
pub const RETRY_AFTER_S: u64 = 10;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "lightmapd",
        description = "Lightmap bake service: glTF in, EXR lightmaps out (DESIGN §7). With `serve --auth`, every route but /healthz needs `Authorization: Bearer TOKEN` (401 otherwise) and sees only that token's scenes and jobs. Any route may answer 408 (request timeout; for a scene upload, its body stopped arriving for longer than the idle timeout) or 413 (body over the limit); a large upload or download may answer 503 with Retry-After when too many are in flight; every error is application/problem+json."
    ),
    paths(
        upload_scene,
        get_scene,
        delete_scene,
        create_job,
        list_jobs,
        get_job,
        cancel_job,
        delete_job,
        events::job_events,
        get_lightmap,
        get_preview,
        get_probes,
        get_generated_scene,
        healthz,
        metrics,
        openapi_json,
        dashboard,
        list_scenes,
        get_scene_glb,
        list_techniques,
        get_lightmap_rgba16f,
        get_job_file
    ),
    components(schemas(
        Problem,
        JobSpec,
        JobView,
        JobList,
        JobCreated,
        JobStatus,
        Progress,
        ProbeProgress,
        SceneView,
        Health,
        SceneList,
        TechniqueList,
        TechniqueInfo,
        SplitInfo,
        DenoiserInfo
    ))
)]
pub struct ApiDoc;

pub fn router(state: AppState) -> Router {
    let limits = &state.config.limits;
    let max = limits.max_scene_bytes;
    Router::new()
        .route(
            "/v1/scenes",
            // The limit is enforced (as a 413 problem) by the handler; the general body
            // limit below must not cut in first.
            post(upload_scene)
                .layer(DefaultBodyLimit::max(max.saturating_add(1 << 20)))
                .get(list_scenes),
        )
        .route("/v1/scenes/{id}", get(get_scene).delete(delete_scene))
        .route("/v1/jobs", post(create_job).get(list_jobs))
        .route("/v1/jobs/{id}", get(get_job).delete(delete_job))
        .route("/v1/jobs/{id}/cancel", post(cancel_job))
        .route("/v1/jobs/{id}/events", get(events::job_events))
        .route("/v1/jobs/{id}/lightmap.exr", get(get_lightmap))
        .route("/v1/jobs/{id}/preview.png", get(get_preview))
        .route("/v1/jobs/{id}/probes.json", get(get_probes))
        .route("/v1/jobs/{id}/scene.glb", get(get_generated_scene))
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(openapi_json))
        .route("/", get(dashboard))
        .route("/v1/scenes/{id}/scene.glb", get(get_scene_glb))
        .route("/v1/techniques", get(list_techniques))
        .route("/v1/jobs/{id}/lightmap.rgba16f", get(get_lightmap_rgba16f))
        .route("/v1/jobs/{id}/{file}", get(get_job_file))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        // Innermost first: body limit, caller, time limit, then plain-text errors of
        // any of them (or of axum's extractors) rewritten as problem+json.
        .layer(DefaultBodyLimit::max(limits.max_body_bytes))
        .layer(axum::middleware::from_fn_with_state(state.clone(), auth::authenticate))
        .layer(axum::middleware::from_fn_with_state(state.clone(), time_limit))
        .layer(axum::middleware::map_response_with_state(state.clone(), problem_bodies))
        .with_state(state)
}

/// The request time limit (`--request-timeout-s`, 408), on every route but a scene
/// upload: an upload's body only has to keep arriving (`--upload-idle-timeout-s`,
/// `service::upload`), so a large scene on a slow link is not cut off by a total time.
async fn time_limit(State(state): State<AppState>, req: Request, next: axum::middleware::Next) -> Response {
    if req.method() == axum::http::Method::POST && req.uri().path() == "/v1/scenes" {
        return next.run(req).await;
    }
    match tokio::time::timeout(state.config.limits.request_timeout, next.run(req)).await {
        Ok(resp) => resp,
        Err(_) => StatusCode::REQUEST_TIMEOUT.into_response(),
    }
}

/// Rewrites an error answer that is not problem+json (axum's extractor rejections, the
/// body limit, the timeout) into one, keeping its status and saying what it was.
async fn problem_bodies(State(state): State<AppState>, resp: Response) -> Response {
    let status = resp.status();
    let is_problem = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(PROBLEM_JSON.as_bytes()));
    if !(status.is_client_error() || status.is_server_error()) || is_problem {
        return resp;
    }
    let limits = &state.config.limits;
    let (_, body) = resp.into_parts();
    let text = axum::body::to_bytes(body, 16 << 10).await.unwrap_or_default();
    let text = String::from_utf8_lossy(&text).trim().to_string();
    let (kind, detail) = match status {
        StatusCode::PAYLOAD_TOO_LARGE => (
            "too-large",
            format!(
                "the request body is larger than this server's limit of {} bytes (--max-body-bytes)",
                limits.max_body_bytes
            ),
        ),
        StatusCode::REQUEST_TIMEOUT => (
            "timeout",
            format!(
                "the request took longer than this server's limit of {} s (--request-timeout-s)",
                limits.request_timeout.as_secs_f64()
            ),
        ),
        StatusCode::BAD_REQUEST => ("bad-request", text),
        StatusCode::UNSUPPORTED_MEDIA_TYPE => ("unsupported-media-type", text),
        StatusCode::UNPROCESSABLE_ENTITY => ("invalid-field", text),
        s if s.is_server_error() => ("internal", text),
        _ => ("client-error", text),
    };
    let detail = if detail.is_empty() {
        status.canonical_reason().unwrap_or("error").to_string()
    } else {
        detail
    };
    Problem::new(status, kind, detail).into_response()
}

/// 429 or 503 with `Retry-After`.
pub(crate) fn retry_later(status: StatusCode, kind: &str, detail: String) -> Response {
    let mut resp = Problem::new(status, kind, detail).into_response();
    resp.headers_mut()
        .insert(header::RETRY_AFTER, HeaderValue::from(RETRY_AFTER_S));
    resp
}

async fn not_found(req: Request) -> Problem {
    Problem::new(
        StatusCode::NOT_FOUND,
        "no-route",
        format!("no route for {} {}; see /openapi.json", req.method(), req.uri().path()),
    )
}

async fn method_not_allowed(req: Request) -> Problem {
    Problem::new(
        StatusCode::METHOD_NOT_ALLOWED,
        "method-not-allowed",
        format!("{} is not allowed on {}", req.method(), req.uri().path()),
    )
}

fn content_type(headers: &HeaderMap) -> String {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|v| v.split(';').next().unwrap_or("").trim().to_ascii_lowercase())
        .unwrap_or_default()
}

/// Upload a scene.
#[utoipa::path(
    post,
    path = "/v1/scenes",
    tag = "scenes",
    request_body(
        description = "A .glb (model/gltf-binary), or multipart/form-data with a .gltf and its buffers and images",
        content(
            (Vec<u8> = "model/gltf-binary"),
            (Vec<u8> = "multipart/form-data")
        )
    ),
    responses(
        (status = 201, description = "Stored", body = SceneView),
        (status = 200, description = "The same content was stored before: the same scene", body = SceneView),
        (status = 400, description = "Empty or malformed upload", body = Problem, content_type = "application/problem+json"),
        (status = 401, description = "A bearer token is required (`serve --auth`)", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Larger than the server's limit", body = Problem, content_type = "application/problem+json"),
        (status = 408, description = "The body stopped arriving for longer than the idle timeout (--upload-idle-timeout-s); an upload has no total time limit", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Neither a .glb nor multipart", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "The importer rejected the scene, or it is over a limit (`field`: `triangles`, `textures`)", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Too many large uploads and downloads in flight (--max-large-bodies); retry after Retry-After seconds", body = Problem, content_type = "application/problem+json")
    )
)]
async fn upload_scene(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    req: Request,
) -> Result<Response, Problem> {
    let limits = &state.config.limits;
    let max = limits.max_scene_bytes;
    let declared = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|len| len > max as u64) {
        return Err(upload::too_large(max));
    }
    // A body of unknown or large size takes a large-body permit for the whole request.
    let _permit = match declared {
        Some(n) if n <= limits.large_body_bytes => None,
        _ => match large_body_permit(&state) {
            Ok(p) => Some(p),
            Err(busy) => return Ok(busy),
        },
    };
    let into = upload::UploadLimits {
        spool: state.config.data_dir.join("spool"),
        max_bytes: max,
        idle: limits.upload_idle_timeout,
    };
    let ct = content_type(req.headers());
    let spooled = if ct == "multipart/form-data" {
        let mp = Multipart::from_request(req, &state)
            .await
            .map_err(|e| Problem::bad_request(format!("malformed multipart body: {}", e.body_text())))?;
        upload::receive_gltf(mp, &into).await?
    } else if ct.is_empty() || ct == "model/gltf-binary" || ct == "application/octet-stream" {
        upload::receive_glb(req.into_body(), &into).await?
    } else {
        return Err(Problem::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!(
                "content type {ct:?}: send model/gltf-binary (a .glb) or multipart/form-data (a .gltf and its files)"
            ),
        ));
    };
    let format = spooled.format;

    // The id follows the content (`upload::Spooled::content_digest`).
    let digest = spooled.content_digest().await?;
    // With tokens, each token has its own scenes: the id also hashes the owner, so the
    // same bytes from two tokens are two scenes and neither learns of the other's.
    let id = match &caller.token {
        None => digest[..32].to_string(),
        Some(t) => {
            let owned: String = Sha256::digest(format!("{t}:{digest}").as_bytes())
                .iter()
                .map(|b| format!("{b:02x}"))
                .collect();
            owned[..32].to_string()
        }
    };

    if let Some(existing) = state.queue.scene(&id).await? {
        return Ok((StatusCode::OK, axum::Json(scene_view(&existing))).into_response());
    }

    // Import is CPU work and holds the scene in memory: off the runtime's threads, and
    // at most `--max-concurrent-imports` at once (the others wait their turn).
    let _importing = state.imports.clone().acquire_owned().await.map_err(Problem::internal)?;
    let glb = if format == "glb" {
        Some(upload::read_file(&spooled.path(&spooled.main)).await?)
    } else {
        None
    };
    let (dir, main) = (spooled.dir().to_path_buf(), spooled.main.clone());
    let limits = state.config.limits.clone();
    let imported = tokio::task::spawn_blocking(move || match glb {
        Some(bytes) => import_files(&SceneFiles::Glb(bytes), &limits).map(|(_, r)| r),
        None => import_dir(&dir, &main, &limits).map(|(_, r)| r),
    })
    .await
    .map_err(Problem::internal)?;
    drop(_importing);
    let report = imported.map_err(|e| match e {
        ImportFailure::Limit { what, detail } => {
            let (field, flag) = match what {
                "triangles" => ("triangles", "--max-triangles"),
                _ => ("textures", "--max-texture-size"),
            };
            Problem::invalid_field(field, format!("{detail} of this server ({flag})"))
        }
        ImportFailure::Invalid(msg) => Problem::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid-scene", msg),
    })?;

    for (name, _) in &spooled.files {
        state
            .artifacts
            .put_file(&store::scene_file(&id, name), &spooled.path(name))
            .await?;
    }
    let rec = SceneRecord {
        id: id.clone(),
        content_hash: format!("sha256:{digest}"),
        format: format.to_string(),
        main_file: spooled.main.clone(),
        files: spooled.files.iter().map(|(n, _)| n.clone()).collect(),
        size_bytes: spooled.total_bytes(),
        report: serde_json::to_value(&report).map_err(Problem::internal)?,
        created_at: now_ms(),
        client: caller.token.clone(),
    };
    let created = state.queue.insert_scene(&rec).await?;
    tracing::info!(scene = %id, format, bytes = rec.size_bytes, triangles = report.triangles, "scene stored");
    let status = if created { StatusCode::CREATED } else { StatusCode::OK };
    let mut resp = (status, axum::Json(scene_view(&rec))).into_response();
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/scenes/{id}")) {
        resp.headers_mut().insert(header::LOCATION, loc);
    }
    Ok(resp)
}

/// A permit for one large body, or 503 with `Retry-After` when `--max-large-bodies` are
/// in flight.
// The refusal is the response a handler returns as it is (axum's way), built once a
// refusal is certain: its size on the error path costs nothing on the permitted one.
#[allow(clippy::result_large_err)]
fn large_body_permit(state: &AppState) -> Result<tokio::sync::OwnedSemaphorePermit, Response> {
    state.large_bodies.clone().try_acquire_owned().map_err(|_| {
        retry_later(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-bodies",
            format!(
                "{} large uploads or downloads are in flight, this server's limit (--max-large-bodies); try again later",
                state.config.limits.max_large_bodies
            ),
        )
    })
}

fn scene_view(s: &SceneRecord) -> SceneView {
    SceneView {
        id: s.id.clone(),
        content_hash: s.content_hash.clone(),
        format: s.format.clone(),
        files: s.files.clone(),
        size_bytes: s.size_bytes,
        report: s.report.clone(),
        created_at: rfc3339(s.created_at),
    }
}

/// A scene's import report.
#[utoipa::path(
    get,
    path = "/v1/scenes/{id}",
    tag = "scenes",
    params(("id" = String, Path, description = "Scene id")),
    responses(
        (status = 200, body = SceneView),
        (status = 404, body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_scene(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<axum::Json<SceneView>, Problem> {
    Ok(axum::Json(scene_view(&find_scene(&state, &caller, &id).await?)))
}

/// The scene, if it exists and the caller may see it (else 404 either way).
async fn find_scene(state: &AppState, caller: &Caller, id: &str) -> Result<SceneRecord, Problem> {
    match state.queue.scene(id).await? {
        Some(s) if caller.owns(s.client.as_deref()) => Ok(s),
        _ => Err(Problem::not_found("scene", id)),
    }
}

/// Delete a scene (not while a queued or running job uses it).
#[utoipa::path(
    delete,
    path = "/v1/scenes/{id}",
    tag = "scenes",
    params(("id" = String, Path, description = "Scene id")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 404, body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "A queued or running job uses it", body = Problem, content_type = "application/problem+json")
    )
)]
async fn delete_scene(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<StatusCode, Problem> {
    find_scene(&state, &caller, &id).await?;
    match state.queue.delete_scene(&id).await? {
        SceneDeletion::Deleted => {
            state.artifacts.delete_prefix(&store::scene_prefix(&id)).await?;
            Ok(StatusCode::NO_CONTENT)
        }
        SceneDeletion::NotFound => Err(Problem::not_found("scene", &id)),
        SceneDeletion::InUse(n) => Err(Problem::conflict(format!(
            "scene {id} is used by {n} queued or running job(s); cancel them or wait for them to finish"
        ))),
    }
}

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
async fn create_job(
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

pub fn job_view(j: &JobRecord) -> JobView {
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

/// [`job_view`] with what only one job's page shows: a split job's tasks and
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
async fn list_jobs(
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
async fn get_job(
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
async fn cancel_job(
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
async fn delete_job(
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

/// A stored object as a streamed download (never read whole into memory), or 500 when the
/// job's record names an object the store does not have.
async fn download(
    state: &AppState,
    key: &object_store::path::Path,
    content_type: &'static str,
    filename: Option<String>,
) -> Result<Response, Problem> {
    let (size, stream) = state
        .artifacts
        .get_stream(key)
        .await?
        .ok_or_else(|| Problem::internal(format!("{key} is recorded but missing from the store")))?;
    Ok(streamed(state, size, stream, content_type, filename))
}

/// A download's stream with the large-body permit it holds: dropped together when the
/// body has been sent or the client went away.
struct Permitted<S> {
    inner: S,
    _permit: Option<tokio::sync::OwnedSemaphorePermit>,
}

impl<S: futures_util::Stream + Unpin> futures_util::Stream for Permitted<S> {
    type Item = S::Item;
    fn poll_next(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Self::Item>> {
        std::pin::Pin::new(&mut self.inner).poll_next(cx)
    }
}

/// A streamed body of `size` bytes; a large one holds a large-body permit until it has
/// been sent (or the client went away), and gets 503 with `Retry-After` when none is free.
fn streamed(
    state: &AppState,
    size: u64,
    stream: futures_util::stream::BoxStream<'static, object_store::Result<Bytes>>,
    content_type: &'static str,
    filename: Option<String>,
) -> Response {
    let permit = if size > state.config.limits.large_body_bytes {
        match large_body_permit(state) {
            Ok(p) => Some(p),
            Err(busy) => return busy,
        }
    } else {
        None
    };
    let body = Body::from_stream(Permitted {
        inner: stream,
        _permit: permit,
    });
    let mut resp = binary_body(body, content_type, filename);
    resp.headers_mut()
        .insert(header::CONTENT_LENGTH, HeaderValue::from(size));
    resp
}

fn binary(bytes: Bytes, content_type: &'static str, filename: Option<String>) -> Response {
    binary_body(Body::from(bytes), content_type, filename)
}

fn binary_body(body: Body, content_type: &'static str, filename: Option<String>) -> Response {
    let mut resp = Response::new(body);
    resp.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    if let Some(f) = filename
        && let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"{f}\""))
    {
        resp.headers_mut().insert(header::CONTENT_DISPOSITION, v);
    }
    resp
}

/// The lightmap: final (page 0, the whole lightmap of a one-page job; every page is
/// `lightmap-P.exr`, listed in the job's `summary.pages`), or a snapshot of the running
/// bake (the bake's grid: its pages one under another, at `summary.pages[].first_row`).
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/lightmap.exr",
    tag = "jobs",
    params(
        ("id" = String, Path, description = "Job id"),
        ("snapshot" = Option<String>, Query, description = "`latest` or a snapshot number (1 = first); absent: the final lightmap")
    ),
    responses(
        (status = 200, description = "OpenEXR", content_type = "image/x-exr", body = Vec<u8>),
        (status = 404, description = "No such job or snapshot", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "No final lightmap (yet): the job has not succeeded", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Bad `snapshot` value", body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_lightmap(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, Problem> {
    let job = find_job(&state, &caller, &id).await?;
    match q.get("snapshot").map(String::as_str) {
        None => {
            if job.status != JobStatus::Succeeded {
                return Err(Problem::conflict(format!(
                    "job {id} is {} and has no final lightmap{}",
                    job.status.as_str(),
                    if job.snapshots > 0 {
                        "; ?snapshot=latest gives the latest snapshot"
                    } else {
                        ""
                    }
                )));
            }
            final_page(&state, &id, 0, format!("{id}.exr")).await
        }
        Some(s) => {
            let n = if s == "latest" {
                job.snapshots
            } else {
                s.parse::<u32>().ok().filter(|n| *n >= 1).ok_or_else(|| {
                    Problem::invalid_field(
                        "snapshot",
                        format!("snapshot must be `latest` or a number >= 1, got {s:?}"),
                    )
                })?
            };
            if n == 0 || n > job.snapshots {
                return Err(Problem::new(
                    StatusCode::NOT_FOUND,
                    "not-found",
                    format!("job {id} has {} snapshot(s); there is no snapshot {s}", job.snapshots),
                ));
            }
            let keep = state.config.snapshot_keep;
            if !store::snapshot_kept(n, job.snapshots, keep) {
                return Err(thinned(&job, n, keep));
            }
            match state.artifacts.get(&store::snapshot_exr(&id, n)).await? {
                Some(bytes) => Ok(binary(bytes, "image/x-exr", Some(format!("{id}.exr")))),
                // Another process may keep fewer (its own --snapshot-keep): still 404.
                None => Err(thinned(&job, n, keep)),
            }
        }
    }
}

/// Page `page` of a succeeded job's final lightmap, streamed; page 0 of a job stored
/// before pages existed is its one `lightmap.exr`.
async fn final_page(state: &AppState, id: &str, page: u32, filename: String) -> Result<Response, Problem> {
    if let Some((size, stream)) = state.artifacts.get_stream(&store::page_exr(id, page)).await? {
        return Ok(streamed(state, size, stream, "image/x-exr", Some(filename)));
    }
    if page == 0
        && let Some((size, stream)) = state.artifacts.get_stream(&store::legacy_final_exr(id)).await?
    {
        return Ok(streamed(state, size, stream, "image/x-exr", Some(filename)));
    }
    Err(Problem::new(
        StatusCode::NOT_FOUND,
        "not-found",
        format!("job {id} has no lightmap page {page} (its summary lists the pages)"),
    ))
}

/// The pages a succeeded job's summary lists (`[0]` for a job stored before pages).
/// One of a succeeded job's final files by name: a page (`lightmap-P.exr`) or the
/// manifest (`lightmaps.json`), as `extras.lightmap.file` and the manifest name them.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/{file}",
    tag = "jobs",
    params(
        ("id" = String, Path, description = "Job id"),
        ("file" = String, Path, description = "`lightmap-P.exr` (page P = 0, 1, ...) or `lightmaps.json`")
    ),
    responses(
        (status = 200, description = "The page (OpenEXR) or the manifest (JSON: format, pages, nodes)", content_type = "image/x-exr", body = Vec<u8>),
        (status = 404, description = "No such job, file or page", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "The job has not succeeded", body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_job_file(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path((id, file)): Path<(String, String)>,
) -> Result<Response, Problem> {
    let page = crate::engine::output::pages::parse_page_file(&file);
    if page.is_none() && file != crate::engine::output::pages::MANIFEST_FILE {
        return Err(Problem::new(
            StatusCode::NOT_FOUND,
            "not-found",
            format!("a job has no file {file:?}: its files are lightmap-P.exr (P = 0, 1, ...) and lightmaps.json"),
        ));
    }
    let job = find_job(&state, &caller, &id).await?;
    if job.status != JobStatus::Succeeded {
        return Err(Problem::conflict(format!(
            "job {id} is {} and has no final {file}",
            job.status.as_str()
        )));
    }
    match page {
        Some(p) => {
            if !store::job_pages(&job).contains(&p) {
                return Err(Problem::new(
                    StatusCode::NOT_FOUND,
                    "not-found",
                    format!(
                        "job {id} has {} page(s); there is no page {p}",
                        store::job_pages(&job).len()
                    ),
                ));
            }
            final_page(&state, &id, p, format!("{id}-{file}")).await
        }
        None => match state.artifacts.get_stream(&store::manifest_json(&id)).await? {
            Some((size, stream)) => Ok(streamed(&state, size, stream, "application/json", None)),
            None => Err(Problem::new(
                StatusCode::NOT_FOUND,
                "not-found",
                format!("job {id} finished before lightmaps.json existed; its one page is lightmap-0.exr"),
            )),
        },
    }
}

/// 404 for a snapshot that snapshot retention removed, listing those kept.
fn thinned(job: &JobRecord, n: u32, keep: u32) -> Problem {
    let kept: Vec<String> = store::kept_snapshots(job.snapshots, keep)
        .iter()
        .map(u32::to_string)
        .collect();
    Problem::new(
        StatusCode::NOT_FOUND,
        "not-found",
        format!(
            "snapshot {n} of job {} was removed by snapshot retention (--snapshot-keep {keep}); kept: {}",
            job.id,
            kept.join(", ")
        ),
    )
}

/// A tone-mapped PNG of the final lightmap, or of the latest snapshot while running.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/preview.png",
    tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "PNG", content_type = "image/png", body = Vec<u8>),
        (status = 404, description = "No such job, or no snapshot yet", body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_preview(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, Problem> {
    let job = find_job(&state, &caller, &id).await?;
    let key = if job.status == JobStatus::Succeeded {
        store::final_png(&id)
    } else if job.snapshots > 0 {
        store::snapshot_png(&id, job.snapshots)
    } else {
        return Err(Problem::new(
            StatusCode::NOT_FOUND,
            "not-found",
            format!("job {id} is {} and has no preview yet", job.status.as_str()),
        ));
    };
    download(&state, &key, "image/png", None).await
}

/// The job's light probes: positions, validity, radiance SH to L2 and error estimates
/// (docs/probes.md), stored with the final lightmap.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/probes.json",
    tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "The probes file", content_type = "application/json", body = Object),
        (status = 404, description = "No such job, or the job asked for no probes", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "The job has not succeeded", body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_probes(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, Problem> {
    let job = find_job(&state, &caller, &id).await?;
    if job.spec.probes.is_none() {
        return Err(Problem::new(
            StatusCode::NOT_FOUND,
            "not-found",
            format!("job {id} asked for no probes (job field `probes`)"),
        ));
    }
    if job.status != JobStatus::Succeeded {
        return Err(Problem::conflict(format!(
            "job {id} is {}; its probes come with the final lightmap",
            job.status.as_str()
        )));
    }
    download(&state, &store::probes_json(&id), "application/json", None).await
}

/// The scene with the lightmap UVs the engine generated for it (only when it had none:
/// the lightmap fits these UVs, not the uploaded scene).
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/scene.glb",
    tag = "jobs",
    params(("id" = String, Path, description = "Job id")),
    responses(
        (status = 200, description = "glTF binary with TEXCOORD_1", content_type = "model/gltf-binary", body = Vec<u8>),
        (status = 404, description = "No such job, or its scene had lightmap UVs of its own", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "The job has not succeeded and its UVs are not generated yet (its plan's `generated_scene` names this route once they are)", body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_generated_scene(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, Problem> {
    let job = find_job(&state, &caller, &id).await?;
    // Stored as soon as the engine has made the UVs (before the bake's first snapshot,
    // usually), so snapshots can be shown on it; it does not change afterwards.
    match state.artifacts.get_stream(&store::generated_scene(&id)).await? {
        Some((size, stream)) => Ok(streamed(
            &state,
            size,
            stream,
            "model/gltf-binary",
            Some(format!("{id}.glb")),
        )),
        None if job.status == JobStatus::Succeeded => Err(Problem::new(
            StatusCode::NOT_FOUND,
            "not-found",
            format!("job {id} baked the scene's own lightmap UVs (TEXCOORD_1): use the uploaded scene"),
        )),
        None => Err(Problem::conflict(format!(
            "job {id} is {} and has no scene with generated UVs yet (a job's plan names it once stored; a scene with its own TEXCOORD_1 gets none)",
            job.status.as_str()
        ))),
    }
}

/// Liveness and database reachability.
#[utoipa::path(
    get,
    path = "/healthz",
    tag = "service",
    responses(
        (status = 200, body = Health),
        (status = 500, description = "The database cannot be read", body = Problem, content_type = "application/problem+json")
    )
)]
async fn healthz(State(state): State<AppState>) -> Result<axum::Json<Health>, Problem> {
    state.queue.counts().await?;
    Ok(axum::Json(Health {
        status: "ok".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        workers: state.config.workers,
    }))
}

/// Prometheus metrics (text format 0.0.4).
#[utoipa::path(
    get,
    path = "/metrics",
    tag = "service",
    responses((status = 200, description = "Prometheus text", content_type = "text/plain", body = String))
)]
async fn metrics(State(state): State<AppState>) -> Result<Response, Problem> {
    let counts = state.queue.counts().await?;
    let mut resp = state.metrics.render(&counts).into_response();
    resp.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
    );
    Ok(resp)
}

/// This document.
#[utoipa::path(
    get,
    path = "/openapi.json",
    tag = "service",
    responses((status = 200, description = "OpenAPI 3.1", content_type = "application/json", body = serde_json::Value))
)]
async fn openapi_json() -> Response {
    axum::Json(ApiDoc::openapi()).into_response()
}

/// The web console (`src/service/console/`): upload, bake, follow a job, see the
/// lightmap on the scene. One static HTML document with its style and scripts inlined;
/// it holds no data, so it is served without a token even under `--auth`.
#[utoipa::path(
    get,
    path = "/",
    tag = "service",
    responses((status = 200, description = "HTML", content_type = "text/html", body = String))
)]
async fn dashboard() -> Html<&'static str> {
    Html(crate::service::console::page())
}

/// `GET /v1/scenes`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct SceneList {
    pub scenes: Vec<SceneView>,
}

/// The caller's scenes (with `--auth`, only its token's), newest first.
#[utoipa::path(
    get,
    path = "/v1/scenes",
    tag = "scenes",
    responses((status = 200, body = SceneList))
)]
async fn list_scenes(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
) -> Result<axum::Json<SceneList>, Problem> {
    let scenes = state.queue.scenes(caller.token.as_deref()).await?;
    Ok(axum::Json(SceneList {
        scenes: scenes.iter().map(scene_view).collect(),
    }))
}

/// The uploaded scene as one flat `.glb` (what the engine imported: every instance in
/// world space, its `TEXCOORD_1` when it has lightmap UVs of its own, materials with
/// their factors and textures), for a viewer: the console draws the lightmap on it.
#[utoipa::path(
    get,
    path = "/v1/scenes/{id}/scene.glb",
    tag = "scenes",
    params(("id" = String, Path, description = "Scene id")),
    responses(
        (status = 200, description = "glTF binary", content_type = "model/gltf-binary", body = Vec<u8>),
        (status = 404, body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_scene_glb(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, Problem> {
    let rec = find_scene(&state, &caller, &id).await?;
    // The scene is read, imported and exported in memory: a large one takes a large-body
    // permit and waits for an import slot, like an upload.
    let _permit = if rec.size_bytes > state.config.limits.large_body_bytes {
        match large_body_permit(&state) {
            Ok(p) => Some(p),
            Err(busy) => return Ok(busy),
        }
    } else {
        None
    };
    let _importing = state.imports.clone().acquire_owned().await.map_err(Problem::internal)?;
    let mut files = Vec::new();
    for name in &rec.files {
        let key = store::scene_file(&id, name);
        let bytes = state
            .artifacts
            .get(&key)
            .await?
            .ok_or_else(|| Problem::internal(format!("{key} is recorded but missing from the store")))?;
        files.push((name.clone(), bytes));
    }
    let scene_files = if rec.format == "glb" {
        let (_, bytes) = files
            .pop()
            .ok_or_else(|| Problem::internal(format!("scene {id} is recorded with no file")))?;
        SceneFiles::Glb(bytes)
    } else {
        SceneFiles::Gltf(rec.main_file.clone(), files)
    };
    let limits = state.config.limits.clone();
    let glb = tokio::task::spawn_blocking(move || {
        let (scene, _) = import_files(&scene_files, &limits).map_err(|e| match e {
            ImportFailure::Limit { detail, .. } => detail,
            ImportFailure::Invalid(m) => m,
        })?;
        crate::engine::scene::export::to_glb(&scene)
    })
    .await
    .map_err(Problem::internal)?
    .map_err(|e| Problem::internal(format!("cannot export scene {id}: {e}")))?;
    Ok(binary(Bytes::from(glb), "model/gltf-binary", None))
}

/// The techniques a job may name, with their parameters and defaults, what each runs and
/// leaves out, the output layers, the job defaults and this server's limits: what the
/// console's bake form is built from.
#[utoipa::path(
    get,
    path = "/v1/techniques",
    tag = "jobs",
    responses((status = 200, body = TechniqueList))
)]
async fn list_techniques(State(state): State<AppState>) -> axum::Json<TechniqueList> {
    axum::Json(crate::service::console::techniques(&state.config.limits))
}

/// The lightmap as half floats for a browser: width × height texels of four little-endian
/// IEEE 754 binary16 values (R, G, B of the EXR's default layer; A = 1), rows top first
/// (v = 0 first, as glTF UVs count). `X-Lightmap-Width` and `X-Lightmap-Height` give the
/// size. WebGL2 uploads it as an `RGBA16F` texture as it is.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/lightmap.rgba16f",
    tag = "jobs",
    params(
        ("id" = String, Path, description = "Job id"),
        ("snapshot" = Option<String>, Query, description = "`latest` or a snapshot number (1 = first); absent: the final lightmap when the job has succeeded, else the latest snapshot")
    ),
    responses(
        (status = 200, description = "Half floats, RGBA, rows top first", content_type = "application/octet-stream", body = Vec<u8>,
            headers(("X-Lightmap-Width" = u32, description = "Texels per row"), ("X-Lightmap-Height" = u32, description = "Rows"))),
        (status = 404, description = "No such job, or no lightmap or snapshot yet", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Bad `snapshot` value", body = Problem, content_type = "application/problem+json")
    )
)]
async fn get_lightmap_rgba16f(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, Problem> {
    let job = find_job(&state, &caller, &id).await?;
    let none_yet = |what: String| Problem::new(StatusCode::NOT_FOUND, "not-found", what);
    let key = match q.get("snapshot").map(String::as_str) {
        None if job.status == JobStatus::Succeeded => return final_rgba16f(&state, &job).await,
        None | Some("latest") if job.snapshots > 0 => store::snapshot_exr(&id, job.snapshots),
        None | Some("latest") => {
            return Err(none_yet(format!(
                "job {id} is {} and has no snapshot yet",
                job.status.as_str()
            )));
        }
        Some(s) => {
            let n = s.parse::<u32>().ok().filter(|n| *n >= 1).ok_or_else(|| {
                Problem::invalid_field(
                    "snapshot",
                    format!("snapshot must be `latest` or a number >= 1, got {s:?}"),
                )
            })?;
            if n > job.snapshots {
                return Err(none_yet(format!(
                    "job {id} has {} snapshot(s); there is no snapshot {n}",
                    job.snapshots
                )));
            }
            store::snapshot_exr(&id, n)
        }
    };
    let exr = state
        .artifacts
        .get(&key)
        .await?
        .ok_or_else(|| Problem::internal(format!("{key} is recorded but missing from the store")))?;
    let (w, h, data) = tokio::task::spawn_blocking(move || crate::service::console::rgba16f(&exr))
        .await
        .map_err(Problem::internal)?
        .map_err(Problem::internal)?;
    Ok(rgba16f_response(w, h, data))
}

fn rgba16f_response(w: usize, h: usize, data: Vec<u8>) -> Response {
    let mut resp = binary(Bytes::from(data), "application/octet-stream", None);
    let headers = resp.headers_mut();
    headers.insert("x-lightmap-width", HeaderValue::from(w));
    headers.insert("x-lightmap-height", HeaderValue::from(h));
    resp
}

/// The final lightmap as the bake's grid: its pages one under another (they share the
/// width, in page order), as a snapshot holds it, so the console's view reads both alike.
async fn final_rgba16f(state: &AppState, job: &JobRecord) -> Result<Response, Problem> {
    let mut pages = Vec::new();
    for p in store::job_pages(job) {
        let key = store::page_exr(&job.id, p);
        let bytes = match state.artifacts.get(&key).await? {
            Some(b) => b,
            None if p == 0 => state
                .artifacts
                .get(&store::legacy_final_exr(&job.id))
                .await?
                .ok_or_else(|| Problem::internal(format!("{key} is recorded but missing from the store")))?,
            None => {
                return Err(Problem::internal(format!(
                    "{key} is recorded but missing from the store"
                )));
            }
        };
        pages.push(bytes);
    }
    let (w, h, data) = tokio::task::spawn_blocking(move || {
        let mut out = Vec::new();
        let (mut width, mut height) = (None, 0usize);
        for exr in &pages {
            let (w, h, data) = crate::service::console::rgba16f(exr)?;
            if *width.get_or_insert(w) != w {
                return Err(format!(
                    "the job's pages differ in width ({} and {w})",
                    width.unwrap_or(0)
                ));
            }
            height += h;
            out.extend(data);
        }
        Ok::<_, String>((width.unwrap_or(0), height, out))
    })
    .await
    .map_err(Problem::internal)?
    .map_err(Problem::internal)?;
    Ok(rgba16f_response(w, h, data))
}

#[cfg(test)]
mod tests {
    use super::*;
    use futures_util::StreamExt;

    /// A large streamed download holds its permit until its body is dropped (sent, or
    /// the client gone), and one past `--max-large-bodies` is 503 with `Retry-After`;
    /// a small one takes no permit.
    #[tokio::test]
    async fn a_large_download_holds_its_permit_until_its_body_ends() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = crate::service::Config {
            data_dir: dir.path().to_path_buf(),
            workers: 0,
            ..Default::default()
        };
        config.limits.max_large_bodies = 1;
        config.limits.large_body_bytes = 100;
        let state = AppState::for_tests(&config).await;
        let never = || futures_util::stream::pending::<object_store::Result<Bytes>>().boxed();
        let first = streamed(&state, 101, never(), "application/octet-stream", None);
        assert_eq!(first.status(), StatusCode::OK);
        assert_eq!(state.large_bodies.available_permits(), 0);
        let small = streamed(&state, 100, never(), "application/octet-stream", None);
        assert_eq!(small.status(), StatusCode::OK, "a small body takes no permit");
        let second = streamed(&state, 101, never(), "application/octet-stream", None);
        assert_eq!(second.status(), StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(second.headers()[header::RETRY_AFTER], "10");
        drop(first);
        assert_eq!(
            state.large_bodies.available_permits(),
            1,
            "the permit goes with the body"
        );
        let third = streamed(&state, 101, never(), "application/octet-stream", None);
        assert_eq!(third.status(), StatusCode::OK);
    }
}
