//! One bake from an imported scene to EXR bytes: the sequence the command line and the
//! service's workers share (texel set → technique → bake loop → dilation → EXR).
//!
//! The caller owns I/O: it imports the scene, decides where the bytes go, and turns
//! progress events into a progress bar or an event stream.

use std::sync::Arc;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::engine::accumulate::{ErrorSummary, Estimate};
use crate::engine::atlas::{Atlas, AtlasReport};
use crate::engine::bake::{BakeLoop, BakeObserver, StopCriteria, StopReason};
use crate::engine::output::{self, ExrMetadata, OutputLayer};
use crate::engine::post::DEFAULT_RINGS;
use crate::engine::scene::{Lighting, Scene};
use crate::engine::technique::{self, BakeInputs, EngineError};

/// What to bake, independent of where the scene came from.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct BakeRequest {
    pub technique: String,
    pub resolution: u32,
    pub lighting: Lighting,
    pub stop: StopCriteria,
    pub params: Value,
    pub outputs: Vec<OutputLayer>,
    pub seed: u64,
}

impl Default for BakeRequest {
    fn default() -> Self {
        BakeRequest {
            technique: "path".into(),
            resolution: 256,
            lighting: Lighting::default(),
            stop: StopCriteria {
                steps: Some(4096),
                seconds: Some(120.0),
                target_error: Some(0.02),
            },
            params: Value::Null,
            outputs: Vec::new(),
            seed: 0,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct BakeSummary {
    pub technique: String,
    pub atlas: AtlasReport,
    pub steps: u64,
    pub seconds: f64,
    pub stopped_by: StopReason,
    pub error: ErrorSummary,
}

pub struct BakeResult {
    pub exr: Vec<u8>,
    /// Tone-mapped PNG of the dilated lightmap.
    pub preview_png: Vec<u8>,
    pub estimate: Estimate,
    pub atlas: Arc<Atlas>,
    pub summary: BakeSummary,
}

/// Runs `request` on `scene`; `on_atlas` is told the texel set before the first step.
pub fn bake(
    scene: Arc<Scene>,
    request: &BakeRequest,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&AtlasReport),
) -> Result<BakeResult, EngineError> {
    request.lighting.validate().map_err(EngineError::BadInput)?;
    request.stop.validate()?;
    let atlas = Arc::new(
        Atlas::build(&scene, request.resolution, request.resolution)
            .map_err(|e| EngineError::BadInput(e.to_string()))?,
    );
    let report = atlas.report();
    on_atlas(&report);
    let want_direct = request
        .outputs
        .iter()
        .any(|o| matches!(o, OutputLayer::Direct | OutputLayer::Indirect));
    let inputs = BakeInputs {
        scene,
        atlas: atlas.clone(),
        lighting: request.lighting,
        seed: request.seed,
        want_direct,
    };
    let mut tech = technique::create(&request.technique, inputs, &request.params)?;
    let outcome = BakeLoop::new(request.stop).run(tech.as_mut(), observer)?;
    let channels =
        output::lightmap_channels(&atlas, &outcome.estimate, &request.outputs, DEFAULT_RINGS)
            .map_err(EngineError::Internal)?;
    let meta = ExrMetadata {
        technique: request.technique.clone(),
        params: tech.params(),
        steps: outcome.estimate.steps,
        seconds: outcome.elapsed.as_secs_f64(),
        relative_error: outcome.estimate.error.relative,
        seed: request.seed,
    };
    let preview = crate::engine::post::dilate(&atlas, &outcome.estimate.total, DEFAULT_RINGS);
    let preview_png = output::encode_preview_png(atlas.width, atlas.height, &preview)
        .map_err(EngineError::Internal)?;
    let exr = output::encode_exr(atlas.width, atlas.height, channels, &meta)
        .map_err(EngineError::Internal)?;
    let summary = BakeSummary {
        technique: request.technique.clone(),
        atlas: report,
        steps: outcome.estimate.steps,
        seconds: outcome.elapsed.as_secs_f64(),
        stopped_by: outcome.stopped_by,
        error: outcome.estimate.error,
    };
    Ok(BakeResult {
        exr,
        preview_png,
        estimate: outcome.estimate,
        atlas,
        summary,
    })
}
