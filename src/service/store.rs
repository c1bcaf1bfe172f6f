//! The artifact store: scene files, snapshot and final EXRs, PNG previews.
//!
//! How: a thin wrapper over `object_store`, so the local directory of the embedded mode
//! and an S3-compatible bucket (DESIGN §8) are the same to every caller. The wrapper owns
//! the key layout, so no route or worker spells a key:
//!
//! ```text
//! scenes/{scene}/{file}            the uploaded .glb, or a .gltf and its buffers and images
//! jobs/{job}/snapshots/{n}.exr     snapshot n (1, 2, ...) of the running bake
//! jobs/{job}/snapshots/{n}.png     its tone-mapped preview
//! jobs/{job}/lightmap-{p}.exr      page p (0, 1, ...) of the final lightmap
//! jobs/{job}/lightmaps.json        the final lightmap's manifest (pages, nodes)
//! jobs/{job}/lightmap.exr          the final lightmap of a job stored before pages
//!                                  existed (read as its page 0; never written now)
//! jobs/{job}/preview.png           its preview
//! jobs/{job}/scene.glb             the scene with generated lightmap UVs (when it had none)
//! ```
//!
//! Where (`--store`, [`StoreUrl`]): `s3://BUCKET/PREFIX` is a bucket of any S3-compatible
//! server (AWS, MinIO, Ceph, moto...), the keys above under PREFIX; `file://DIR` or a plain
//! directory is the local store. The S3 endpoint, region and credentials come from the
//! usual environment variables through `AmazonS3Builder::from_env` (`AWS_ENDPOINT_URL`,
//! `AWS_REGION`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`,
//! `AWS_ALLOW_HTTP`...), or, for the keys, the files `LIGHTMAPD_S3_ACCESS_KEY_ID_FILE` and
//! `LIGHTMAPD_S3_SECRET_ACCESS_KEY_FILE` name (mounted secrets); never from the URL, so no secret lands in a process list or a
//! log line. Requests are path-style (`ENDPOINT/BUCKET/KEY`, what self-hosted servers
//! expect) unless `AWS_VIRTUAL_HOSTED_STYLE_REQUEST=true`.
//! [`Artifacts::open`] makes one cheap request (a listing of a prefix that holds nothing)
//! so a wrong endpoint, bucket or key fails at start-up, not at the first upload.
//!
//! Durability: the local store writes each object to a temporary file beside it
//! (`NAME#N`), syncs it, renames it over the name and syncs the folder
//! (`LocalFileSystem::with_fsync`), so an object is either absent or whole, even after a
//! crash or a power cut; workers store the final EXR before they mark a job succeeded.
//! A crash between write and rename can leave a `NAME#N` file, never a short `NAME`.
//! On S3 an object appears whole when its `PUT` (or the multipart upload's completion)
//! returns, which is S3's own guarantee; a failed multipart upload is aborted so its parts
//! do not linger (a crash mid-upload leaves parts that only a bucket lifecycle rule for
//! incomplete multipart uploads removes: docs/deploy.md says so).
//!
//! What is buffered, and why: [`Artifacts::put`] takes the object as one `Bytes`, because
//! its callers already hold it whole: an EXR or a preview is encoded in memory by the
//! engine. Nothing is copied on the way out: on S3, an object larger than
//! [`MULTIPART_THRESHOLD`] goes up as a multipart upload of [`PART_SIZE`] parts that are
//! slices of the caller's buffer (at most [`PART_CONCURRENCY`] in flight), so a large
//! object is neither copied into request bodies nor sent as one request that a network
//! hiccup restarts from byte 0. The local store writes the buffer to its temporary file.
//! A scene upload is not held whole: the API spools it to disk (`service::upload`) and
//! [`Artifacts::put_file`] sends the file in parts read one at a time.
//!
//! Snapshot retention (issue 24): a running bake stores a snapshot every
//! `--snapshot-interval-s`, so a long bake would store hundreds. [`snapshot_kept`] says
//! which survive once `n` exist with `keep` allowed: the latest, and every `s`-th before
//! it, where the stride `s` is the smallest power of two that leaves at most `keep - 1`
//! of them. As `n` grows the stride doubles and every other old snapshot goes, so the
//! history stays evenly spread over the whole bake; and since a stride only ever grows
//! (and each divides the next), a snapshot removed once is never wanted again. The
//! worker deletes what stopped being kept right after it stores a new one.
//!
//! Limits: EXRs are held whole in memory while they are written, and a worker reads its
//! scene whole (the importer parses from memory); API
//! downloads are streamed ([`Artifacts::get_stream`]). Only S3 and local directories are wired up (object_store's GCS and Azure
//! back-ends are not compiled in). Listing a prefix to delete a scene is eventually
//! consistent on some S3-compatible servers (AWS itself is strongly consistent).

use std::fmt;
use std::path::{Path as FsPath, PathBuf};
use std::sync::Arc;

use bytes::Bytes;
use futures_util::TryStreamExt;
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::local::LocalFileSystem;
use object_store::path::Path;
use object_store::prefix::PrefixStore;
use object_store::{ClientConfigKey, ObjectStore, ObjectStoreExt, PutPayload, WriteMultipart};

/// On S3, objects larger than this go up as a multipart upload.
pub const MULTIPART_THRESHOLD: usize = 16 << 20;
/// Part size of a multipart upload (S3's minimum is 5 MiB for all parts but the last).
pub const PART_SIZE: usize = 8 << 20;
/// Parts of one upload in flight at once.
pub const PART_CONCURRENCY: usize = 4;

/// How the S3 client retries a request that failed for a transient reason (no
/// connection, a 5xx): for up to two minutes, with decorrelated jittered backoff from
/// 200 ms growing up to 10 s between tries. object_store's default (10 tries from 100 ms)
/// gave up after 2.2 to 3 s against a store that refused connections, failing jobs that
/// stored their lightmap in a 6 s outage (tests/service/real_faults.rs); a store that is down for
/// longer than two minutes fails the operation with its last error.
fn s3_retry() -> object_store::RetryConfig {
    object_store::RetryConfig {
        backoff: object_store::BackoffConfig {
            init_backoff: std::time::Duration::from_millis(200),
            max_backoff: std::time::Duration::from_secs(10),
            base: 3.0,
        },
        max_retries: 40,
        retry_timeout: std::time::Duration::from_secs(120),
    }
}

/// Where artifacts live, as `--store` spells it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum StoreUrl {
    /// A local directory: `file://DIR` or a plain path.
    Local(PathBuf),
    /// `s3://BUCKET/PREFIX`: keys go under PREFIX (empty: the bucket's root).
    S3 { bucket: String, prefix: String },
}

impl StoreUrl {
    /// Parses `s3://BUCKET[/PREFIX]`, `file://DIR` or a plain directory; the error says
    /// what is wrong and what is accepted.
    pub fn parse(s: &str) -> Result<StoreUrl, String> {
        const FORMS: &str = "use s3://BUCKET/PREFIX, file://DIR or a directory";
        if s.trim().is_empty() {
            return Err(format!("the store is empty: {FORMS}"));
        }
        let Some((scheme, rest)) = s.split_once("://") else {
            return Ok(StoreUrl::Local(PathBuf::from(s)));
        };
        match scheme.to_ascii_lowercase().as_str() {
            "file" => {
                if rest.is_empty() {
                    return Err(format!("{s:?} names no directory: {FORMS}"));
                }
                Ok(StoreUrl::Local(PathBuf::from(rest)))
            }
            "s3" => {
                if rest.contains(['?', '#']) {
                    return Err(format!(
                        "{s:?}: an s3:// store takes no query or fragment; endpoint, region and \
                         credentials come from AWS_ENDPOINT_URL, AWS_REGION, AWS_ACCESS_KEY_ID and \
                         AWS_SECRET_ACCESS_KEY"
                    ));
                }
                let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
                check_bucket(bucket).map_err(|why| format!("{s:?}: bucket {bucket:?} {why}"))?;
                let prefix = prefix.trim_end_matches('/');
                if !prefix.is_empty() {
                    Path::parse(prefix).map_err(|e| format!("{s:?}: prefix {prefix:?} is not a valid key: {e}"))?;
                }
                Ok(StoreUrl::S3 {
                    bucket: bucket.to_string(),
                    prefix: prefix.to_string(),
                })
            }
            other => Err(format!("{s:?}: unsupported store scheme {other:?}: {FORMS}")),
        }
    }
}

impl std::str::FromStr for StoreUrl {
    type Err = String;
    fn from_str(s: &str) -> Result<StoreUrl, String> {
        StoreUrl::parse(s)
    }
}

impl fmt::Display for StoreUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StoreUrl::Local(dir) => write!(f, "{}", dir.display()),
            StoreUrl::S3 { bucket, prefix } if prefix.is_empty() => write!(f, "s3://{bucket}"),
            StoreUrl::S3 { bucket, prefix } => write!(f, "s3://{bucket}/{prefix}"),
        }
    }
}

/// S3's bucket naming rules (3 to 63 characters of lower-case letters, digits, dots and
/// hyphens, a letter or digit at each end), checked here so a typo is named at start-up
/// rather than answered by the server as a bare 400.
fn check_bucket(b: &str) -> Result<(), &'static str> {
    if !(3..=63).contains(&b.len()) {
        return Err("must be 3 to 63 characters long");
    }
    if !b
        .bytes()
        .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'.' || c == b'-')
    {
        return Err("may hold only lower-case letters, digits, '.' and '-'");
    }
    let alnum = |c: u8| c.is_ascii_lowercase() || c.is_ascii_digit();
    if !alnum(b.as_bytes()[0]) || !alnum(b.as_bytes()[b.len() - 1]) {
        return Err("must begin and end with a letter or a digit");
    }
    if b.contains("..") {
        return Err("must not hold two dots in a row");
    }
    Ok(())
}

#[derive(Clone)]
pub struct Artifacts {
    store: Arc<dyn ObjectStore>,
    /// Objects larger than this go up in parts (S3 only; `None` for the local store, whose
    /// `put` is the durable write-sync-rename).
    multipart_above: Option<usize>,
}

impl Artifacts {
    /// The store `url` names. S3 settings come from the environment, then `overrides`
    /// (tests pass their endpoint and keys here rather than changing the process's
    /// environment); a store that cannot be reached is an error here.
    pub async fn open(url: &StoreUrl, overrides: &[(AmazonS3ConfigKey, String)]) -> anyhow::Result<Artifacts> {
        let (artifacts, check) = match url {
            StoreUrl::Local(dir) => return Ok(Artifacts::local(dir)?),
            StoreUrl::S3 { bucket, prefix } => {
                let mut b = AmazonS3Builder::from_env().with_bucket_name(bucket);
                // Keys from files (mounted secrets) win over the variables.
                for (var, key) in [
                    ("LIGHTMAPD_S3_ACCESS_KEY_ID_FILE", AmazonS3ConfigKey::AccessKeyId),
                    (
                        "LIGHTMAPD_S3_SECRET_ACCESS_KEY_FILE",
                        AmazonS3ConfigKey::SecretAccessKey,
                    ),
                ] {
                    if let Some(path) = std::env::var_os(var).filter(|p| !p.is_empty()) {
                        let v = std::fs::read_to_string(&path).map_err(|e| {
                            anyhow::anyhow!("{var}={}: cannot read it: {e}", FsPath::new(&path).display())
                        })?;
                        b = b.with_config(key, v.trim());
                    }
                }
                for (k, v) in overrides {
                    b = b.with_config(*k, v);
                }
                // `AWS_ENDPOINT_URL_S3` wins over `AWS_ENDPOINT_URL`, as in the builder.
                let endpoint = b
                    .get_config_value(&AmazonS3ConfigKey::S3Endpoint)
                    .or_else(|| b.get_config_value(&AmazonS3ConfigKey::Endpoint))
                    .unwrap_or_default();
                let allow_http = b
                    .get_config_value(&AmazonS3ConfigKey::Client(ClientConfigKey::AllowHttp))
                    .is_some_and(|v| ["true", "1", "yes", "on"].contains(&v.to_ascii_lowercase().as_str()));
                if endpoint.starts_with("http://") && !allow_http {
                    anyhow::bail!("the S3 endpoint {endpoint} is plain HTTP: set AWS_ALLOW_HTTP=true to allow it");
                }
                // The start-up check below answers within seconds with object_store's
                // own retries; the store kept for work retries through outages.
                let prefixed = |s3: object_store::aws::AmazonS3| -> Arc<dyn ObjectStore> {
                    if prefix.is_empty() {
                        Arc::new(s3)
                    } else {
                        Arc::new(PrefixStore::new(s3, prefix.as_str()))
                    }
                };
                let check = prefixed(b.clone().build()?);
                let store = prefixed(b.with_retry(s3_retry()).build()?);
                (
                    Artifacts {
                        store,
                        multipart_above: Some(MULTIPART_THRESHOLD),
                    },
                    check,
                )
            }
        };
        // A listing, not a HEAD: a HEAD's 404 has no body, so a missing bucket would look
        // like a missing key. Any error (no bucket, refused keys, nothing listening) stops
        // the process before it accepts work it could not store.
        let probe = Path::from("lightmapd-store-check");
        check.list(Some(&probe)).try_next().await.map_err(|e| {
            // object_store repeats each cause inside its parent's message, so the chain
            // is not kept: its top message and its root cause (say, "Connection
            // refused") say it all.
            let root = std::iter::successors(Some(&e as &dyn std::error::Error), |e| e.source())
                .last()
                .map(ToString::to_string)
                .unwrap_or_default();
            anyhow::anyhow!("cannot reach the artifact store {url}: {e} (cause: {root})")
        })?;
        Ok(artifacts)
    }

    /// A store rooted at `dir` (created if missing).
    pub fn local(dir: &FsPath) -> Result<Artifacts, object_store::Error> {
        std::fs::create_dir_all(dir).map_err(|e| object_store::Error::Generic {
            store: "LocalFileSystem",
            source: Box::new(e),
        })?;
        // Automatic cleanup removes emptied directories, so a deleted scene leaves nothing.
        let fs = LocalFileSystem::new_with_prefix(dir)?
            .with_automatic_cleanup(true)
            .with_fsync(true);
        Ok(Artifacts {
            store: Arc::new(fs),
            multipart_above: None,
        })
    }

    pub fn from_store(store: Arc<dyn ObjectStore>) -> Artifacts {
        Artifacts {
            store,
            multipart_above: None,
        }
    }

    /// Stores `bytes` at `key`, replacing what was there; the object is whole or absent.
    pub async fn put(&self, key: &Path, bytes: Bytes) -> Result<(), object_store::Error> {
        match self.multipart_above {
            Some(t) if bytes.len() > t => self.put_in_parts(key, bytes).await,
            _ => self.store.put(key, PutPayload::from_bytes(bytes)).await.map(|_| ()),
        }
    }

    /// A multipart upload whose parts are slices of `bytes` (no copy).
    async fn put_in_parts(&self, key: &Path, mut bytes: Bytes) -> Result<(), object_store::Error> {
        let upload = self.store.put_multipart(key).await?;
        let mut w = WriteMultipart::new_with_chunk_size(upload, PART_SIZE);
        while !bytes.is_empty() {
            if let Err(e) = w.wait_for_capacity(PART_CONCURRENCY - 1).await {
                // The upload's own error is the one worth reporting.
                let _ = w.abort().await;
                return Err(e);
            }
            let part = bytes.split_to(PART_SIZE.min(bytes.len()));
            w.put(part);
        }
        // `finish` aborts the upload itself when a part or the completion fails.
        w.finish().await.map(|_| ())
    }

    /// Stores the file at `path` under `key` without reading it whole (a spooled upload,
    /// `service::upload`): a file of at most one part is read and put; a larger one goes
    /// up as a multipart upload read from the file one part at a time, on either back-end
    /// (the local store's multipart upload is its staged write-sync-rename too), so the
    /// memory held is at most [`PART_CONCURRENCY`] parts.
    pub async fn put_file(&self, key: &Path, path: &FsPath) -> Result<(), object_store::Error> {
        use tokio::io::AsyncReadExt;
        let io = |e: std::io::Error| object_store::Error::Generic {
            store: "spool",
            source: Box::new(e),
        };
        let size = tokio::fs::metadata(path).await.map_err(io)?.len();
        if size <= PART_SIZE as u64 {
            let bytes = tokio::fs::read(path).await.map_err(io)?;
            return self.store.put(key, PutPayload::from(bytes)).await.map(|_| ());
        }
        let mut file = tokio::fs::File::open(path).await.map_err(io)?;
        let upload = self.store.put_multipart(key).await?;
        let mut w = WriteMultipart::new_with_chunk_size(upload, PART_SIZE);
        let mut left = size;
        while left > 0 {
            if let Err(e) = w.wait_for_capacity(PART_CONCURRENCY - 1).await {
                let _ = w.abort().await;
                return Err(e);
            }
            let n = (PART_SIZE as u64).min(left) as usize;
            let mut part = vec![0u8; n];
            if let Err(e) = file.read_exact(&mut part).await {
                let _ = w.abort().await;
                return Err(io(e));
            }
            left -= n as u64;
            w.put(Bytes::from(part));
        }
        w.finish().await.map(|_| ())
    }

    /// The object, or `None` when there is none.
    pub async fn get(&self, key: &Path) -> Result<Option<Bytes>, object_store::Error> {
        match self.store.get(key).await {
            Ok(r) => Ok(Some(r.bytes().await?)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Bytes `range` of the object and the object's whole size, or `None` when there is
    /// none. `range` must not be empty (object_store refuses an empty range).
    pub async fn get_range(
        &self,
        key: &Path,
        range: std::ops::Range<u64>,
    ) -> Result<Option<(Bytes, u64)>, object_store::Error> {
        let options = object_store::GetOptions::new().with_range(Some(range));
        match self.store.get_opts(key, options).await {
            Ok(r) => {
                let size = r.meta.size;
                Ok(Some((r.bytes().await?, size)))
            }
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Bytes `ranges` of the object, one piece a range in order (object_store joins near
    /// ones into one request); empty ranges read nothing. A piece is shorter than its range
    /// only where the object is; the caller checks.
    pub async fn get_ranges(
        &self,
        key: &Path,
        ranges: &[std::ops::Range<u64>],
    ) -> Result<Vec<Bytes>, object_store::Error> {
        let asked: Vec<std::ops::Range<u64>> = ranges.iter().filter(|r| !r.is_empty()).cloned().collect();
        let got = self.store.get_ranges(key, &asked).await?;
        if got.len() != asked.len() {
            return Err(object_store::Error::Generic {
                store: "artifacts",
                source: format!("{} pieces for {} ranges of {key}", got.len(), asked.len()).into(),
            });
        }
        let mut got = got.into_iter();
        Ok(ranges
            .iter()
            .map(|r| {
                if r.is_empty() {
                    Bytes::new()
                } else {
                    got.next().unwrap_or_default()
                }
            })
            .collect())
    }

    /// The object as a stream of chunks, with its size, or `None` when there is none:
    /// downloads are sent as they are read, never held whole (issue 24).
    pub async fn get_stream(
        &self,
        key: &Path,
    ) -> Result<
        Option<(
            u64,
            futures_util::stream::BoxStream<'static, object_store::Result<Bytes>>,
        )>,
        object_store::Error,
    > {
        match self.store.get(key).await {
            Ok(r) => Ok(Some((r.meta.size, r.into_stream()))),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Deletes one object (absent is fine).
    pub async fn delete(&self, key: &Path) -> Result<(), object_store::Error> {
        match self.store.delete(key).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(e),
        }
    }

    /// Bytes and objects under `scenes/` and `jobs/`, by listing the whole store (one
    /// request per 1000 objects on S3). `NAME#N` temporaries of the local store are
    /// counted too: they take disk.
    pub async fn usage(&self) -> Result<crate::service::metrics::StoreUsage, object_store::Error> {
        let mut u = crate::service::metrics::StoreUsage::default();
        let mut list = self.store.list(None);
        while let Some(m) = list.try_next().await? {
            let first = m.location.parts().next().map(|p| p.as_ref().to_string());
            match first.as_deref() {
                Some("scenes") => {
                    u.scene_bytes += m.size;
                    u.scene_objects += 1;
                }
                Some("jobs") => {
                    u.job_bytes += m.size;
                    u.job_objects += 1;
                }
                _ => {}
            }
        }
        u.at_ms = crate::service::queue::now_ms();
        Ok(u)
    }

    /// Deletes every object under `prefix`.
    pub async fn delete_prefix(&self, prefix: &Path) -> Result<(), object_store::Error> {
        let keys: Vec<Path> = self
            .store
            .list(Some(prefix))
            .map_ok(|m| m.location)
            .try_collect()
            .await?;
        for key in keys {
            match self.store.delete(&key).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

pub fn scene_prefix(scene: &str) -> Path {
    Path::from(format!("scenes/{scene}"))
}

pub fn scene_file(scene: &str, file: &str) -> Path {
    // `Path::from_iter` percent-encodes each part, so a file name cannot climb out.
    Path::from_iter(["scenes", scene, file])
}

pub fn job_prefix(job: &str) -> Path {
    Path::from(format!("jobs/{job}"))
}

pub fn snapshot_exr(job: &str, n: u32) -> Path {
    Path::from(format!("jobs/{job}/snapshots/{n}.exr"))
}

pub fn snapshot_png(job: &str, n: u32) -> Path {
    Path::from(format!("jobs/{job}/snapshots/{n}.png"))
}

/// The stride of the kept history once `n` snapshots exist and `keep` may stay: the
/// smallest power of two `s` with `n / s <= keep - 1` (so the multiples of `s` up to `n`,
/// plus the latest, are at most `keep`). With `keep` 1 only the latest stays.
pub fn snapshot_stride(n: u32, keep: u32) -> u64 {
    let room = u64::from(keep.max(1) - 1);
    let mut s: u64 = 1;
    while u64::from(n) / s > room {
        s *= 2;
    }
    s
}

/// Whether snapshot `k` (1-based) is kept once `n` exist: the latest, and the multiples
/// of [`snapshot_stride`].
pub fn snapshot_kept(k: u32, n: u32, keep: u32) -> bool {
    k >= 1 && k <= n && (k == n || u64::from(k) % snapshot_stride(n, keep) == 0)
}

/// The snapshots kept once `n` exist, oldest first.
pub fn kept_snapshots(n: u32, keep: u32) -> Vec<u32> {
    let s = snapshot_stride(n, keep);
    let mut v: Vec<u32> = (1..=u64::from(n) / s).map(|i| (i * s) as u32).collect();
    if v.last() != Some(&n) && n > 0 {
        v.push(n);
    }
    v
}

/// What storing snapshot `n` makes removable: kept at `n - 1`, not at `n`.
pub fn snapshots_to_drop(n: u32, keep: u32) -> Vec<u32> {
    if n < 2 {
        return vec![];
    }
    kept_snapshots(n - 1, keep)
        .into_iter()
        .filter(|k| !snapshot_kept(*k, n, keep))
        .collect()
}

/// The pages a succeeded job's summary lists (`summary.pages[].page`); page 0 alone for
/// a job finished before pages existed.
pub fn job_pages(job: &crate::service::queue::JobRecord) -> Vec<u32> {
    let listed: Vec<u32> = job
        .summary
        .as_ref()
        .and_then(|s| s.get("pages"))
        .and_then(|p| p.as_array())
        .map(|a| {
            a.iter()
                .filter_map(|e| e.get("page").and_then(|p| p.as_u64()).map(|p| p as u32))
                .collect()
        })
        .unwrap_or_default();
    if listed.is_empty() { vec![0] } else { listed }
}

/// Page `page` of the final lightmap (`lightmap-P.exr`, `engine::output::pages`).
pub fn page_exr(job: &str, page: u32) -> Path {
    Path::from(format!("jobs/{job}/lightmap-{page}.exr"))
}

/// The final lightmap's `lightmaps.json`.
pub fn manifest_json(job: &str) -> Path {
    Path::from(format!("jobs/{job}/lightmaps.json"))
}

/// Where jobs finished before pages existed keep their one final lightmap; the routes
/// read it as page 0 when `lightmap-0.exr` is absent, so nothing stored is lost.
pub fn legacy_final_exr(job: &str) -> Path {
    Path::from(format!("jobs/{job}/lightmap.exr"))
}

pub fn final_png(job: &str) -> Path {
    Path::from(format!("jobs/{job}/preview.png"))
}

/// The job's light probes (`probes` in the job), JSON as `lightmapd bake --probes` writes.
pub fn probes_json(job: &str) -> Path {
    Path::from(format!("jobs/{job}/probes.json"))
}

pub fn generated_scene(job: &str) -> Path {
    Path::from(format!("jobs/{job}/scene.glb"))
}

/// Bake task `k`'s result (`engine::tasks::Partial`, docs/scaling.md's `.lmtask`) of a
/// split job, kept until the merge has stored the lightmap.
pub fn task_partial(job: &str, k: u32) -> Path {
    Path::from(format!("jobs/{job}/tasks/{k}.lmtask"))
}

/// Bake task `k`'s halves so far while it runs (a `.lmtask` marked live), which the
/// job's running snapshots merge; replaced as it bakes on, deleted with the results.
pub fn task_live(job: &str, k: u32) -> Path {
    Path::from(format!("jobs/{job}/tasks/{k}.live.lmtask"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn store_urls_parse() {
        assert_eq!(
            StoreUrl::parse("s3://lightmaps/studio/a").unwrap(),
            StoreUrl::S3 {
                bucket: "lightmaps".into(),
                prefix: "studio/a".into()
            }
        );
        assert_eq!(
            StoreUrl::parse("s3://lightmaps/").unwrap(),
            StoreUrl::S3 {
                bucket: "lightmaps".into(),
                prefix: String::new()
            }
        );
        assert_eq!(
            StoreUrl::parse("file:///srv/objects").unwrap(),
            StoreUrl::Local("/srv/objects".into())
        );
        assert_eq!(
            StoreUrl::parse("data/objects").unwrap(),
            StoreUrl::Local("data/objects".into())
        );
        assert_eq!(
            StoreUrl::parse("s3://lightmaps/studio/a/").unwrap().to_string(),
            "s3://lightmaps/studio/a"
        );
    }

    #[test]
    fn snapshot_retention_keeps_the_latest_and_an_even_history() {
        // keep 4: stride 1 up to 3 snapshots... then the multiples of 2, 4, 8.
        assert_eq!(kept_snapshots(3, 4), vec![1, 2, 3]);
        assert_eq!(kept_snapshots(4, 4), vec![2, 4]);
        assert_eq!(kept_snapshots(7, 4), vec![2, 4, 6, 7]);
        assert_eq!(kept_snapshots(8, 4), vec![4, 8]);
        assert_eq!(kept_snapshots(13, 4), vec![4, 8, 12, 13]);
        assert_eq!(kept_snapshots(1000, 8), vec![128, 256, 384, 512, 640, 768, 896, 1000]);
        assert_eq!(kept_snapshots(5, 1), vec![5]);
        assert_eq!(kept_snapshots(0, 4), Vec::<u32>::new());
        // Over a long bake: never more than `keep`, the latest always there, a removed
        // snapshot never wanted again, and dropping exactly what stopped being kept.
        for keep in [1, 2, 3, 8, 16] {
            let mut stored: std::collections::BTreeSet<u32> = Default::default();
            let mut ever_dropped: std::collections::BTreeSet<u32> = Default::default();
            for n in 1..=3000u32 {
                stored.insert(n);
                for k in snapshots_to_drop(n, keep) {
                    assert!(stored.remove(&k), "keep {keep}, n {n}: {k} dropped twice");
                    ever_dropped.insert(k);
                }
                let kept: std::collections::BTreeSet<u32> = kept_snapshots(n, keep).into_iter().collect();
                assert_eq!(stored, kept, "keep {keep}, n {n}");
                assert!(stored.len() <= keep as usize && stored.contains(&n));
                assert!(
                    kept.is_disjoint(&ever_dropped),
                    "keep {keep}, n {n}: a dropped one came back"
                );
            }
        }
    }

    #[test]
    fn bad_store_urls_are_named() {
        for (url, says) in [
            ("", "the store is empty"),
            ("gs://bucket/x", "unsupported store scheme \"gs\""),
            ("s3://", "must be 3 to 63 characters"),
            ("s3://Light_Maps/x", "may hold only lower-case letters"),
            ("s3://-maps", "must begin and end with a letter or a digit"),
            ("s3://a..b", "two dots"),
            ("s3://maps/a//b", "prefix \"a//b\" is not a valid key"),
            ("s3://maps/x?region=eu", "takes no query"),
            ("file://", "names no directory"),
        ] {
            let e = StoreUrl::parse(url).unwrap_err();
            assert!(e.contains(says), "{url:?}: {e}");
        }
    }

    #[tokio::test]
    async fn plain_http_endpoint_needs_allow_http() {
        let url = StoreUrl::parse("s3://maps").unwrap();
        let overrides = [
            (AmazonS3ConfigKey::Endpoint, "http://127.0.0.1:1".to_string()),
            (
                AmazonS3ConfigKey::Client(ClientConfigKey::AllowHttp),
                "false".to_string(),
            ),
        ];
        let e = Artifacts::open(&url, &overrides).await.err().expect("refused");
        assert!(e.to_string().contains("AWS_ALLOW_HTTP"), "{e}");
    }
}
