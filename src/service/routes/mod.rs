//! HTTP routes (DESIGN §7): the router, its middleware and the service-wide routes
//! (health, metrics, the OpenAPI document, the technique list, the dashboard); the
//! handlers of scenes, jobs and downloads are in `scenes`, `jobs` and `downloads`, and a
//! job's event stream in `service::events`. Each handler parses and validates, calls the
//! queue or the store, and answers. Errors are `application/problem+json` ([`Problem`]);
//! the OpenAPI document ([`ApiDoc`], served at `/openapi.json`) is generated from the
//! handlers' annotations.
//!
//! Every route gets a [`Caller`](auth::Caller) from [`auth::authenticate`]; with tokens on, a scene or
//! job of another token is answered exactly like a missing one (404). Scene ids come
//! from the content (and the owning token), job ids are random UUIDs: nothing a client
//! sends becomes a filesystem path.
//!
//! Every error leaves as problem+json: handlers return [`Problem`], and
//! `problem_bodies` rewrites the plain-text answers axum and tower-http produce on
//! their own (a malformed path or query, a body over the limit, a timeout).
//!
//! Large bodies (uploads of unknown length or over 16 MiB, downloads over 16 MiB) take
//! one of `--max-large-bodies` permits for as long as they run
//! (`large_body_permit`); past it, 503 with `Retry-After`.

mod downloads;
mod jobs;
mod scenes;

pub use jobs::{describe_job, find_job};

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use utoipa::OpenApi;

use crate::service::auth;
use crate::service::console::{DenoiserInfo, SplitInfo, TechniqueInfo, TechniqueList};
use crate::service::model::{
    Health, JobCreated, JobList, JobSpec, JobStatus, JobView, ProbeProgress, Progress, SceneView,
};
use crate::service::problem::{PROBLEM_JSON, Problem};
use crate::service::{AppState, events};

use downloads::{get_generated_scene, get_job_file, get_lightmap, get_lightmap_rgba16f, get_preview, get_probes};
use jobs::{cancel_job, create_job, delete_job, get_job, list_jobs};
use scenes::{SceneList, delete_scene, get_scene, get_scene_glb, list_scenes, upload_scene};

/// What a client told to come back later is told to wait, in seconds.
pub const RETRY_AFTER_S: u64 = 10;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "lightmapd",
        description = "Lightmap bake service: glTF in, EXR lightmaps out (DESIGN §7). With `serve --auth`, every route but /healthz needs `Authorization: Bearer TOKEN` (401 otherwise) and sees only that token's scenes and jobs. Any route may answer 408 (request timeout; for a scene upload, its body stopped arriving for longer than the idle timeout) or 413 (body over the limit); a large upload or download may answer 503 with Retry-After when too many are in flight; every error is application/problem+json."
    ),
    paths(
        scenes::upload_scene,
        scenes::get_scene,
        scenes::delete_scene,
        jobs::create_job,
        jobs::list_jobs,
        jobs::get_job,
        jobs::cancel_job,
        jobs::delete_job,
        events::job_events,
        downloads::get_lightmap,
        downloads::get_preview,
        downloads::get_probes,
        downloads::get_generated_scene,
        healthz,
        metrics,
        openapi_json,
        dashboard,
        scenes::list_scenes,
        scenes::get_scene_glb,
        list_techniques,
        downloads::get_lightmap_rgba16f,
        downloads::get_job_file
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
