//! The engine's error type, shared by every layer that can fail a bake.
//!
//! It lives apart from `technique` so that the layers below the techniques (plan, job
//! helpers, post) can name it without importing the technique module, which keeps the
//! engine's import graph free of cycles (docs/architecture.md). The service maps
//! [`EngineError::BadInput`] to HTTP 4xx and the CLI to exit code 2.

use crate::engine::gpu::GpuError;

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// The job asked for something out of range: exit code 2, HTTP 4xx.
    #[error("{0}")]
    BadInput(String),
    #[error("GPU: {0}")]
    Gpu(String),
    #[error("internal error: {0}")]
    Internal(String),
}

impl EngineError {
    pub fn is_bad_input(&self) -> bool {
        matches!(self, EngineError::BadInput(_))
    }
}

/// A GPU error as the engine reports it: too large a map or lightmap for this device is
/// the job's choice (bad input), anything else a GPU fault.
pub fn gpu_error(e: GpuError) -> EngineError {
    match e {
        GpuError::Unsupported { .. } => EngineError::BadInput(e.to_string()),
        other => EngineError::Gpu(other.to_string()),
    }
}
