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
//! jobs/{job}/lightmap.exr          the final lightmap
//! jobs/{job}/preview.png           its preview
//! jobs/{job}/scene.glb             the scene with generated lightmap UVs (when it had none)
//! ```
//!
//! Durability: the local store writes each object to a temporary file beside it
//! (`NAME#N`), syncs it, renames it over the name and syncs the folder
//! (`LocalFileSystem::with_fsync`), so an object is either absent or whole, even after a
//! crash or a power cut; workers store the final EXR before they mark a job succeeded.
//! A crash between write and rename can leave a `NAME#N` file, never a short `NAME`.
//!
//! Limits: whole objects are buffered in memory (lightmaps are megabytes, not gigabytes).
//! Only the local filesystem is wired up; `--store` takes a directory today.

use std::path::Path as FsPath;
use std::sync::Arc;

use bytes::Bytes;
use futures_util::TryStreamExt;
use object_store::local::LocalFileSystem;
use object_store::path::Path;
use object_store::{ObjectStore, ObjectStoreExt, PutPayload};

#[derive(Clone)]
pub struct Artifacts {
    store: Arc<dyn ObjectStore>,
}

impl Artifacts {
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
        Ok(Artifacts { store: Arc::new(fs) })
    }

    pub fn from_store(store: Arc<dyn ObjectStore>) -> Artifacts {
        Artifacts { store }
    }

    pub async fn put(&self, key: &Path, bytes: Bytes) -> Result<(), object_store::Error> {
        self.store.put(key, PutPayload::from_bytes(bytes)).await.map(|_| ())
    }

    /// The object, or `None` when there is none.
    pub async fn get(&self, key: &Path) -> Result<Option<Bytes>, object_store::Error> {
        match self.store.get(key).await {
            Ok(r) => Ok(Some(r.bytes().await?)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e),
        }
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

pub fn final_exr(job: &str) -> Path {
    Path::from(format!("jobs/{job}/lightmap.exr"))
}

pub fn final_png(job: &str) -> Path {
    Path::from(format!("jobs/{job}/preview.png"))
}

pub fn generated_scene(job: &str) -> Path {
    Path::from(format!("jobs/{job}/scene.glb"))
}
