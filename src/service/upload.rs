//! Scene uploads received to disk (issue 24 point 4): a body is written to a spool folder
//! as it arrives, never held whole by the API, and each chunk must come within an idle
//! timeout rather than the whole upload within the request timeout, so a large scene on a
//! slow link succeeds while a stalled client is cut off.
//!
//! How: [`receive_glb`] streams a `.glb` body into `spool/<random>/scene.glb`, hashing it
//! as it goes; [`receive_gltf`] streams each multipart part into its own file of the same
//! folder (the part names are checked to be plain file names first). [`Spooled::content_digest`]
//! then hashes exactly what the in-memory upload hashed before (SHA-256 of the bytes for a
//! `.glb`; for a `.gltf` every file's name length, name, size and bytes in name order), so a
//! scene uploaded before this change keeps its id. The folder is removed when the
//! [`Spooled`] is dropped, whatever happened to the request; the API clears `spool/` at
//! start for folders a killed process left.
//!
//! Memory: one chunk per upload while receiving. The import (which parses from memory)
//! reads the spooled `.glb` once, under a semaphore of `--max-concurrent-imports`, and the
//! store writes from the file in parts ([`crate::service::store::Artifacts::put_file`]).
//!
//! Limits: the spool needs disk for the uploads in flight (at most `--max-large-bodies`
//! of `--max-scene-bytes` each, plus the small ones); a client that trickles one byte per
//! idle period can hold an upload open for long (bounded by `--max-scene-bytes` bytes ×
//! the idle timeout), which the large-body cap bounds in number.

use std::path::{Path, PathBuf};
use std::time::Duration;

use axum::body::Body;
use axum::extract::Multipart;
use axum::http::StatusCode;
use bytes::Bytes;
use futures_util::StreamExt;
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;

use crate::service::model::uri_file_name;
use crate::service::problem::Problem;

/// A received upload: its files in a private spool folder, removed on drop.
pub struct Spooled {
    dir: tempfile::TempDir,
    /// (file name, size in bytes), in arrival order.
    pub files: Vec<(String, u64)>,
    /// The file the importer starts from (`scene.glb`, or the one `.gltf`).
    pub main: String,
    /// `"glb"` or `"gltf"`.
    pub format: &'static str,
    /// SHA-256 of a `.glb` body, hashed while it arrived.
    glb_digest: Option<[u8; 32]>,
}

impl Spooled {
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    pub fn total_bytes(&self) -> u64 {
        self.files.iter().map(|(_, n)| n).sum()
    }

    /// The hex SHA-256 the scene id is made from (see the module doc).
    pub async fn content_digest(&self) -> Result<String, Problem> {
        let digest = match self.glb_digest {
            Some(d) => d.to_vec(),
            None => {
                let mut sorted = self.files.clone();
                sorted.sort();
                let dir = self.dir.path().to_path_buf();
                tokio::task::spawn_blocking(move || -> std::io::Result<Vec<u8>> {
                    let mut h = Sha256::new();
                    for (name, size) in &sorted {
                        h.update((name.len() as u64).to_le_bytes());
                        h.update(name.as_bytes());
                        h.update(size.to_le_bytes());
                        let mut f = std::fs::File::open(dir.join(name))?;
                        std::io::copy(&mut f, &mut HashWriter(&mut h))?;
                    }
                    Ok(h.finalize().to_vec())
                })
                .await
                .map_err(Problem::internal)?
                .map_err(|e| Problem::internal(format!("cannot read the spooled upload: {e}")))?
            }
        };
        Ok(digest.iter().map(|b| format!("{b:02x}")).collect())
    }
}

struct HashWriter<'a>(&'a mut Sha256);

impl std::io::Write for HashWriter<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.update(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// What an upload is received under.
#[derive(Clone, Debug)]
pub struct UploadLimits {
    /// The spool folder (`DATA_DIR/spool`).
    pub spool: PathBuf,
    /// Largest upload, all files together (413 beyond).
    pub max_bytes: usize,
    /// Longest wait for the next chunk of the body (408 beyond).
    pub idle: Duration,
}

pub fn too_large(max: usize) -> Problem {
    Problem::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "too-large",
        format!("the scene is larger than this server's limit of {max} bytes (--max-scene-bytes)"),
    )
}

fn stalled(idle: Duration, received: u64) -> Problem {
    Problem::new(
        StatusCode::REQUEST_TIMEOUT,
        "timeout",
        format!(
            "the upload sent nothing for {} s after {received} bytes (--upload-idle-timeout-s)",
            idle.as_secs_f64()
        ),
    )
}

fn spool_error(e: std::io::Error) -> Problem {
    Problem::internal(format!("cannot spool the upload: {e}"))
}

fn new_spool(limits: &UploadLimits) -> Result<tempfile::TempDir, Problem> {
    std::fs::create_dir_all(&limits.spool).map_err(spool_error)?;
    tempfile::Builder::new()
        .prefix("upload-")
        .tempdir_in(&limits.spool)
        .map_err(spool_error)
}

/// Receives a `.glb` body into the spool, chunk by chunk, each within the idle timeout.
pub async fn receive_glb(body: Body, limits: &UploadLimits) -> Result<Spooled, Problem> {
    let dir = new_spool(limits)?;
    let path = dir.path().join("scene.glb");
    let mut file = tokio::fs::File::create(&path).await.map_err(spool_error)?;
    let mut stream = body.into_data_stream();
    let mut h = Sha256::new();
    let mut size = 0u64;
    loop {
        let next = tokio::time::timeout(limits.idle, stream.next())
            .await
            .map_err(|_| stalled(limits.idle, size))?;
        let Some(chunk) = next else { break };
        let chunk = chunk.map_err(|e| Problem::bad_request(format!("the upload was cut short: {e}")))?;
        size += chunk.len() as u64;
        if size > limits.max_bytes as u64 {
            return Err(too_large(limits.max_bytes));
        }
        h.update(&chunk);
        file.write_all(&chunk).await.map_err(spool_error)?;
    }
    file.flush().await.map_err(spool_error)?;
    if size == 0 {
        return Err(Problem::bad_request(
            "empty body: send a .glb (model/gltf-binary) or multipart/form-data with a .gltf and its files",
        ));
    }
    Ok(Spooled {
        dir,
        files: vec![("scene.glb".to_string(), size)],
        main: "scene.glb".to_string(),
        format: "glb",
        glb_digest: Some(h.finalize().into()),
    })
}

/// Receives a multipart `.gltf` upload: each part into its own spool file, the one
/// `.gltf` among them found, and every URI it has checked to be a data URI or a part.
pub async fn receive_gltf(mut mp: Multipart, limits: &UploadLimits) -> Result<Spooled, Problem> {
    let max = limits.max_bytes;
    let dir = new_spool(limits)?;
    let mut files: Vec<(String, u64)> = Vec::new();
    let mut total = 0u64;
    let multipart_error = |e: axum::extract::multipart::MultipartError| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            too_large(max)
        } else {
            Problem::bad_request(format!("malformed multipart body: {}", e.body_text()))
        }
    };
    loop {
        let next = tokio::time::timeout(limits.idle, mp.next_field())
            .await
            .map_err(|_| stalled(limits.idle, total))?;
        let Some(mut field) = next.map_err(multipart_error)? else {
            break;
        };
        let name = field
            .file_name()
            .or(field.name())
            .map(str::to_string)
            .unwrap_or_default();
        // The name becomes a file of the spool folder: a plain name only.
        if name.is_empty()
            || name.len() > 255
            || name.contains(['/', '\\', ':'])
            || name.starts_with('.')
            || name.chars().any(char::is_control)
        {
            return Err(Problem::invalid_field(
                "files",
                format!("part name {name:?}: give each part the plain file name the .gltf uses"),
            ));
        }
        if files.iter().any(|(n, _)| *n == name) {
            return Err(Problem::invalid_field("files", format!("file {name:?} is given twice")));
        }
        let mut file = tokio::fs::File::create(dir.path().join(&name))
            .await
            .map_err(spool_error)?;
        let mut size = 0u64;
        loop {
            let chunk = tokio::time::timeout(limits.idle, field.chunk())
                .await
                .map_err(|_| stalled(limits.idle, total))?
                .map_err(multipart_error)?;
            let Some(chunk) = chunk else { break };
            size += chunk.len() as u64;
            total += chunk.len() as u64;
            if total > max as u64 {
                return Err(too_large(max));
            }
            file.write_all(&chunk).await.map_err(spool_error)?;
        }
        file.flush().await.map_err(spool_error)?;
        files.push((name, size));
    }
    let mains: Vec<&String> = files
        .iter()
        .map(|(n, _)| n)
        .filter(|n| n.to_ascii_lowercase().ends_with(".gltf"))
        .collect();
    let main = match mains.as_slice() {
        [one] => (*one).clone(),
        [] => {
            return Err(Problem::invalid_field(
                "files",
                "no .gltf part: a multipart upload is one .gltf and the files it refers to",
            ));
        }
        _ => return Err(Problem::invalid_field("files", "more than one .gltf part")),
    };
    // Every URI must be a data URI or an uploaded part: never a path on this server.
    let text = tokio::fs::read(dir.path().join(&main)).await.map_err(spool_error)?;
    let json: serde_json::Value = serde_json::from_slice(&text).map_err(|_| {
        Problem::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid-scene",
            format!("{main} is not JSON"),
        )
    })?;
    for kind in ["buffers", "images"] {
        for (i, item) in json[kind].as_array().into_iter().flatten().enumerate() {
            if let Some(uri) = item["uri"].as_str()
                && !uri.starts_with("data:")
                && !files.iter().any(|(n, _)| *n == uri_file_name(uri))
            {
                return Err(Problem::invalid_field(
                    format!("{kind}[{i}].uri"),
                    format!("{main} refers to {uri:?}, which is not among the uploaded parts"),
                ));
            }
        }
    }
    Ok(Spooled {
        dir,
        files,
        main,
        format: "gltf",
        glb_digest: None,
    })
}

/// Removes what a killed process left in the spool folder (called once at start-up,
/// before the API takes requests).
pub fn clear_spool(spool: &Path) {
    if let Ok(entries) = std::fs::read_dir(spool) {
        for e in entries.flatten() {
            let p = e.path();
            let removed = if p.is_dir() {
                std::fs::remove_dir_all(&p)
            } else {
                std::fs::remove_file(&p)
            };
            if let Err(err) = removed {
                tracing::warn!(path = %p.display(), error = %err, "cannot clear a left-over upload");
            }
        }
    }
}

/// Bytes of the spooled file, read once for the importer.
pub async fn read_file(path: &Path) -> Result<Bytes, Problem> {
    tokio::fs::read(path).await.map(Bytes::from).map_err(spool_error)
}
