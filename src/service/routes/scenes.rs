//! Scene routes: upload, look up, list, delete, and the stored scene as `.glb`.
//!
//! Scene uploads: a `.glb` body (`model/gltf-binary` or `application/octet-stream`), or
//! `multipart/form-data` with one `.gltf` part and its buffers and images (each part's
//! file name is the name the `.gltf` refers to). The id is the first 32 hex digits of the
//! SHA-256 of the content, so the same upload gives the same id (201 the first time, 200
//! after). The scene is imported before it is stored: a bad one gets 422 with the
//! importer's message and nothing is kept. Part names of a multipart upload must be plain
//! file names (no folders, no leading dot, no control characters, at most 255 bytes), and
//! `.gltf` URIs must be data URIs or the plain names of uploaded parts (no folders), so an
//! upload can never make the server read its own files.
//!
//! Limits: uploads are received into a spool folder on disk as they arrive
//! ([`upload`]), with an idle timeout per chunk instead of the request time limit, then
//! imported (at most `--max-concurrent-imports` at once; the importer parses from memory,
//! so an import holds its scene) and written to the store from the file in parts.

use axum::Extension;
use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use sha2::{Digest, Sha256};

use crate::service::auth::Caller;
use crate::service::model::{SceneView, rfc3339};
use crate::service::problem::Problem;
use crate::service::queue::{SceneDeletion, SceneRecord, now_ms};
use crate::service::worker::{ImportFailure, SceneFiles, import_dir, import_files};
use crate::service::{AppState, store, upload};

use super::downloads::binary;
use super::{content_type, large_body_permit};

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
pub(super) async fn upload_scene(
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
pub(super) async fn get_scene(
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
pub(super) async fn delete_scene(
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
pub(super) async fn list_scenes(
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
pub(super) async fn get_scene_glb(
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
