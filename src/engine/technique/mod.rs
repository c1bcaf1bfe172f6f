//! The techniques, behind one trait. Each technique owns its resources (BVH, GPU buffers,
//! passes) in one place: `technique/<id>.rs` here and its WGSL in `shaders/`.
//!
//! Contract (DESIGN §3): a technique is prepared once from the scene, the texel set and
//! the job's lighting; then [`Technique::step`] adds one more batch of samples for every
//! valid texel, alternating between two half-accumulators (even and odd steps, DESIGN §4);
//! [`Technique::snapshot`] returns both halves' means at any time. Keeping the halves
//! inside the technique lets a GPU technique accumulate on the GPU and read back only at a
//! snapshot, never per step.
//!
//! Every layer holds irradiance / π at the texel's sample point (the outgoing radiance of
//! a white Lambertian surface), not including the surface's own emission.

pub mod hemicube;
pub mod obscurance;
pub mod path;
pub mod path_gpu;
pub mod sdb;
pub mod sdf;
pub mod vpl;

use std::sync::Arc;

use serde_json::Value;

use crate::engine::accumulate::Snapshot;
use crate::engine::atlas::Atlas;
use crate::engine::gpu::GpuError;
use crate::engine::plan::{Plan, SceneFeatures};
use crate::engine::scene::{Lighting, Scene};

/// The identifiers [`create`] accepts.
pub const TECHNIQUES: &[&str] = &["path", "sdb", "vpl", "obscurance", "sdf", "hemicube"];

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

/// Everything a technique is prepared from.
#[derive(Clone)]
pub struct BakeInputs {
    pub scene: Arc<Scene>,
    pub atlas: Arc<Atlas>,
    pub lighting: Lighting,
    pub seed: u64,
    /// Keep a separate direct-light layer (for the `direct` / `indirect` outputs).
    pub want_direct: bool,
    /// What to create: a technique builds only the passes its plan lists.
    pub plan: Plan,
}

pub trait Technique: Send {
    fn id(&self) -> &'static str;
    /// The parameters in effect, defaults filled in (written into the EXR header).
    fn params(&self) -> Value;
    /// Adds one step of samples to the half-accumulator of this step's parity.
    fn step(&mut self) -> Result<(), EngineError>;
    fn steps_done(&self) -> u64;
    /// Both halves' current means, per valid texel.
    fn snapshot(&mut self) -> Result<Snapshot, EngineError>;
    /// The pass that writes the accumulators, named when a snapshot is not finite.
    fn accumulating_pass(&self) -> &'static str;
    /// The plain obscurance / sky visibility per valid texel (the `ao.Y` layer) as of
    /// the last snapshot, for techniques that compute one.
    fn ao(&self) -> Option<Vec<f32>> {
        None
    }
}

/// Prepares technique `id` with `params` (a JSON object; unknown fields are rejected).
pub fn create(id: &str, inputs: BakeInputs, params: &Value) -> Result<Box<dyn Technique>, EngineError> {
    match id {
        "path" => Ok(Box::new(path::PathTracer::prepare(inputs, params)?)),
        "sdb" => Ok(Box::new(sdb::Sdb::prepare(inputs, params)?)),
        "vpl" => Ok(Box::new(vpl::Vpl::prepare(inputs, params)?)),
        "obscurance" => Ok(Box::new(obscurance::Obscurance::prepare(inputs, params)?)),
        "sdf" => Ok(Box::new(sdf::Sdf::prepare(inputs, params)?)),
        "hemicube" => Ok(Box::new(hemicube::Hemicube::prepare(inputs, params)?)),
        other => Err(EngineError::BadInput(format!(
            "unknown technique {other:?}; available: {}",
            TECHNIQUES.join(", ")
        ))),
    }
}

/// The plan technique `id` makes for a scene with `features` (see `engine::plan`).
pub fn plan(id: &str, features: &SceneFeatures) -> Result<Plan, EngineError> {
    match id {
        "path" => Ok(path::plan(features)),
        "sdb" => Ok(sdb::plan(features)),
        "vpl" => Ok(vpl::plan(features)),
        "obscurance" => Ok(obscurance::plan(features)),
        "sdf" => Ok(sdf::plan(features)),
        "hemicube" => Ok(hemicube::plan(features)),
        other => Err(EngineError::BadInput(format!(
            "unknown technique {other:?}; available: {}",
            TECHNIQUES.join(", ")
        ))),
    }
}

/// A GPU error as the engine reports it: too large a map or lightmap for this device is
/// the job's choice (bad input), anything else a GPU fault.
pub fn gpu_error(e: GpuError) -> EngineError {
    match e {
        // Too large a map or lightmap for this device is the job's choice, not a fault.
        GpuError::Unsupported { .. } => EngineError::BadInput(e.to_string()),
        other => EngineError::Gpu(other.to_string()),
    }
}

/// Parses a technique's parameter object, naming the technique in the error.
pub fn parse_params<T: serde::de::DeserializeOwned + Default>(
    technique: &str,
    params: &Value,
) -> Result<T, EngineError> {
    if params.is_null() {
        return Ok(T::default());
    }
    serde_json::from_value(params.clone()).map_err(|e| EngineError::BadInput(format!("params for {technique}: {e}")))
}
