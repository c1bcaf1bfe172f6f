//! Download routes: a job's lightmap pages, snapshots and extra files, its preview,
//! probes, the scene with its generated lightmap UVs, and the half-float page the web
//! console draws.
//!
//! Downloads are streamed from the store as they are read (issue 24), so a large EXR is
//! never held whole by the API; snapshot EXRs (small, and checked against snapshot
//! retention) are read whole.

use std::collections::HashMap;

use axum::Extension;
use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::Response;
use bytes::Bytes;

use crate::service::auth::Caller;
use crate::service::model::JobStatus;
use crate::service::problem::Problem;
use crate::service::queue::JobRecord;
use crate::service::{AppState, store};

use super::jobs::find_job;
use super::large_body_permit;

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

pub(super) fn binary(bytes: Bytes, content_type: &'static str, filename: Option<String>) -> Response {
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
pub(super) async fn get_lightmap(
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
pub(super) async fn get_job_file(
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
pub(super) async fn get_preview(
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
pub(super) async fn get_probes(
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
pub(super) async fn get_generated_scene(
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
pub(super) async fn get_lightmap_rgba16f(
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
