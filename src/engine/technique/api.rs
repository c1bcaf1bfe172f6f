//! The contract between the bake loop and a technique (DESIGN §3): the [`Technique`] trait,
//! what a technique is prepared from ([`BakeInputs`]) and the parameter parser every
//! technique uses. Techniques import this module, never `technique` itself or one another
//! (the rule `tests/architecture.rs` checks), so the table in `table.rs` can import every
//! technique without an import cycle.
//!
//! Contract: a technique is prepared once from the scene, the texel set and the job's
//! lighting; then [`Technique::step`] adds one more batch of samples for every valid
//! texel, alternating between two half-accumulators (even and odd steps, DESIGN §4);
//! [`Technique::snapshot`] returns both halves' means at any time. Keeping the halves
//! inside the technique lets a GPU technique accumulate on the GPU and read back only at
//! a snapshot, never per step.
//!
//! Every layer holds irradiance / π at the texel's sample point (the outgoing radiance of
//! a white Lambertian surface), not including the surface's own emission.

use std::sync::Arc;

use serde_json::Value;

use crate::engine::accumulate::Snapshot;
use crate::engine::atlas::Atlas;
pub use crate::engine::error::{EngineError, gpu_error};
use crate::engine::gpu::shaders::PassShader;
use crate::engine::plan::{Plan, SceneFeatures};
use crate::engine::scene::{Lighting, Scene};

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

/// What a technique registers.
#[derive(Clone, Copy)]
pub struct TechniqueEntry {
    /// The id a job names (`"technique": "sdb"`).
    pub id: &'static str,
    /// One line for `--help`, the service's description and the docs.
    pub summary: &'static str,
    /// The plan it makes for a scene (DESIGN §6), before any GPU work.
    pub plan: fn(&SceneFeatures) -> Plan,
    /// Prepares it for a bake; `params` is the job's parameter object (unknown fields are
    /// rejected).
    pub prepare: fn(BakeInputs, &Value) -> Result<Box<dyn Technique>, EngineError>,
    /// Every WGSL pass it compiles (validated without a device, see the tests below).
    pub shaders: &'static [PassShader],
}
