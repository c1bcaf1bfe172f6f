//! `sdb`: approximate radiosity by stochastic depth buffering (Thomsen & Nielsen 2011,
//! `shared/seeds/stochastic-depth-buffering-radiosity.md`).
//!
//! # What
//! Multi-bounce diffuse interreflection gathered along global parallel directions. The
//! lightmap quantity is incident irradiance / pi at every valid texel, without the
//! surface's own emission (DESIGN.md section 2).
//!
//! # How (per direction d; one step = `directions_per_step` directions)
//! 1. *Resolve* (`shaders/sdb/resolve.wgsl`, once per step): the reflected radiance of
//!    every lightmap pixel from the running estimate, albedo * E/pi; the fragment adds its
//!    material's emission, exactly (read from the texels only for emissive textures),
//!    so small emitters are not blurred by a coarse lightmap.
//! 2. *Illumination map* (`shaders/sdb/illumination.wgsl`, seed sections 3 and 5,
//!    Figure 4): an orthographic render of the scene along d covering its bounds. Each
//!    fragment writes its outgoing radiance (looked up at its lightmap UV in step 1's
//!    buffer), its distance t = <p, d>, and a pseudo-random depth (PCG hash of its
//!    pixel, triangle index and the direction's seed), so each pixel keeps a
//!    uniformly random one of the surfaces along its ray.
//! 3. *Gather* (`shaders/sdb/gather.wgsl`, seed section 4, Figures 5 and 6): every texel
//!    projects its sample point, reads a k x k neighbourhood, keeps samples in front of it
//!    along d and above its normal plane, takes the nearest, else the environment's
//!    radiance in direction d, and accumulates 4 L max(<d, n>, 0) (seed Eq. 2 without the
//!    albedo) and its weight 4 max(<d, n>, 0) into the even or odd half accumulator; the
//!    estimate is their ratio (self-normalised, so uniform light is exact and the bounce
//!    series keeps energy).
//! 4. *Direct light* (`shaders/sdb/direct.wgsl`), only when the job has a sun or the
//!    scene has directional lights: a shadow map along each such light in the shared
//!    atlas (`gpu::shadow`, each pixel the plane of the nearest surface; until issue 18
//!    finished, a nearest-depth layer of sdb's own map with a two-pixel depth bias) and
//!    E/pi = E_perp/pi cos(theta) visibility into accumulators of their own, which the
//!    resolve pass adds, so these lights also feed the bounces (the seed's section 7
//!    suggests exactly this).
//! 5. *Ambient mode* (`shaders/sdb/resolve.wgsl`, `average` mode, before step 1): a coarse
//!    correction of the feedback on the span of the current estimate (with it on, a step
//!    gathers `directions_per_step` antipodal *pairs* d, -d, so every closed-surface texel
//!    records each step's feed: see `SdbEngine::step`), with the ambient
//!    gain g measured by CPU rays ([`ambient_mode`]); it makes stiff rooms (albedo 0.99,
//!    0.999) converge in a few steps instead of never.
//!
//! Bounces come from step 1: each direction gathers light that earlier directions
//! gathered. `average` mode keeps a running weighted mean over directions (converges to
//! the radiosity solution); the weights ramp up as i^`ramp` because early directions saw
//! an incomplete bounce estimate: with feedback, the plain mean's error decays only like
//! n^-(1 - albedo) (slow in bright rooms), the ramped one like n^-(1 + ramp)(1 - albedo).
//! `leaky` blends every direction with factor `blend` (the seed's interactive mode,
//! value = value (1 - b) + new b), with the usual start-up correction
//! 1 / (1 - (1 - b)^n) so the first steps are not dark.
//!
//! Directions: `stratified` (default) is the R2 sequence (Roberts 2018; the generalised
//! golden ratio, a Kronecker sequence, so every prefix and the even and odd
//! subsequences are low-discrepancy) mapped to the sphere by the area-preserving
//! cylindrical map, then rotated by one uniformly random rotation per bake (Shoemake's
//! quaternion) and offset by a random toroidal shift, so bakes with different seeds are
//! independent. `random` draws i.i.d. uniform directions (the seed's "randomly selected
//! global direction"). The map origin is jittered by a random sub-pixel offset per
//! direction, which turns the map's pixel grid from a fixed aliasing pattern into noise
//! that averages out.
//!
//! Randomness: CPU SplitMix64 seeded from the bake seed for directions, rotations and
//! jitter; per fragment, only the PCG hash on the GPU (no CPU randomness per fragment).
//! Precision: f32 everywhere on the GPU; geometry is uploaded in normalised scene space
//! (p - centre) / radius, so epsilons are relative and translations by 1e5 or scales of
//! 1e-3 .. 1e4 do not change the result (they only cost the precision the f32 input
//! already lost).
//!
//! Culling (seed section 6): back faces of closed surfaces with single-sided materials
//! are discarded (they are never the first surface along a ray from outside, so culling
//! only removes overdraw; closedness is found by welding vertices across the scene, see
//! [`cullable_triangles`]); back faces of open single-sided geometry are kept with zero
//! radiance so they block light; double-sided materials reflect and emit on both faces
//! (with the one lightmap's value: a lightmap stores one side).
//!
//! # Departures from the seed
//! - The gather also requires the sample to be in front of the texel along d (Figure 5
//!   only tests the normal plane).
//! - Two half accumulators (even and odd steps) instead of one, for the error estimate.
//! - Float32 illumination map (the seed used float16): irradiance may exceed half range.
//! - Stratified, randomly rotated directions instead of i.i.d. ones (selectable).
//! - Optional `depth_layers`: several independent stochastic-depth maps per direction,
//!   gathered together (k^2 x layers samples), against overflow (docs/sdb.md, Figure 8).
//! - Emitters use their material's exact emission rather than the lightmap's.
//! - Self-normalised gather and the ambient-mode correction (steps 3 and 5), neither in
//!   the seed; the first step only bootstraps the correction and is dropped.
//! - Point and spot lights (no map direction sees a point): their direct light is
//!   computed on the GPU with one shadow ray per texel and light through the scene's BVH
//!   (the shared direct-light pass, `gpu::direct_light`, `path`'s rules: hard shadows,
//!   KHR_lights_punctual range and cone falloff) in the first two steps, and fed every
//!   step through the same light accumulators as the small emitters, so it bounces like
//!   every other light.
//!
//! # Rounds (issue 25 point 1; `engine::rounds`, docs/scaling.md "Pages in rounds")
//! A bake in rounds bakes one region of the grid at a time with every other texel's light
//! held at the round before's estimate ([`SdbEngine::hold_boundary`]). Held texels keep
//! (held, 1) in both halves' gathered accumulators, so the resolve feeds their held light
//! to the illumination maps; the gather and the light passes run over the receivers only
//! (a texel range in their parameters), so the maps, which render the whole scene, are
//! what a region's task repeats of a single bake. A resumed receiver's half is (mean, 1), a
//! direction's average weight, with the host's weights set to its directions so far; the
//! ambient-mode correction is measured over the receivers and added to them only, and a
//! round that starts from light (resumed, or held) drops no bootstrap step. `leaky` mode
//! is refused (its blend forgets on purpose). The round's own estimate, the next round's
//! held light
//! (`rounds::this_round`), weighs steps by i^ramp where this technique weighs directions
//! (two a step with the ambient mode's pairs): within a few percent of the same shares
//! (0.857 against 0.872 of the weight in a round of 4 steps after 2), so a little of the
//! running mean passes into the held light, which the control texels state with the
//! rest. Measured on the closed box of albedo 0.5 as two pages (96 steps): one round
//! 0.622 of the answer, six rounds 0.988, stated within 1 % of the true error.
//!
//! # Known bias (what the tests' tolerances follow from)
//! - Overdraw: with K surfaces along a ray, a k x k neighbourhood misses the nearest one
//!   with probability (1 - 1/K)^(k^2) (seed section 6, Figure 7): light leaks through
//!   occluders toward farther surfaces or the sky. Exact for K = 1.
//! - Lateral resolution: samples come from pixel centres up to (k/2 + 1/2) pixels away
//!   from the texel's ray, blurring contact shadows over about k pixels of the map and
//!   taking light from geometry that far to the side. Hence `map_size`, unset, is chosen
//!   per scene (`gpu::view::auto_map_size`: a pixel of at most half a texel, 512 to
//!   4096): a fixed 512 made 18 cm pixels on a 91 m level of 10 cm texels, and its
//!   grass tinted the ground green (docs/sdb.md, "The map's size on a level").
//! - Feedback transient (average mode): early directions see an incomplete bounce
//!   estimate; without the ambient-mode correction the bias decays like
//!   n^-(1 + ramp)(1 - albedo) in the number of directions n. The correction removes the
//!   estimate-shaped part of it; the rest (light distributions unlike the current
//!   estimate) decays at that rate still.
//! - Emitters smaller than two map pixels are taken out of the map and sampled by the
//!   same GPU pass (next-event estimation, one shadow ray per texel per step): the map
//!   could not show them, and the k x k lookup would widen them k-fold.
//!
//! Files: this one holds the parameters, the input, the engine's state and the technique
//! behind the trait; `setup.rs` builds the engine (uploads and passes), `step.rs` runs a
//! step and reads the halves back, `lights.rs` turns the scene's lights into the input.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use serde::{Deserialize, Serialize};

mod lights;
mod setup;
mod step;

pub use lights::{SmallLights, ambient_mode, sdb_input};

use super::api::{
    AlphaSupport, BakeInputs, Boundary, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry,
    gpu_error, parse_params,
};
use crate::engine::accumulate::{HalfEstimate, Snapshot};
pub use crate::engine::gpu::directions::{
    DirectionSequence, Directions, SplitMix64, random_rotation, square_to_sphere,
};
use crate::engine::gpu::frame::SceneFrame;
pub use crate::engine::gpu::map_scene::{DirectionalLight, Environment, MapScene, MapTexel, MapTriangle};
use crate::engine::gpu::scene_rays::GpuTables;
use crate::engine::gpu::shadow::ShadowAtlas;
use crate::engine::gpu::slices::StepSlicer;
pub use crate::engine::gpu::view::cullable_triangles;
use crate::engine::gpu::view::{AUTO_MAP_SIZE_MIN, auto_map_size};
use crate::engine::gpu::{self, GpuContext};
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};

// ---------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------

/// How directions are accumulated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum AccumulationMode {
    /// Mean over all directions: converges to the radiosity solution.
    #[default]
    Average,
    /// Exponential moving average with factor `blend` (the seed's interactive mode).
    Leaky,
}

/// `sdb` parameters (the job's `params` object). Unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SdbParams {
    /// Illumination-map size in pixels (square). Range 64..=8192 (and the device's
    /// maximum texture size). Unset (the default), the bake chooses it from the scene's
    /// size and the lightmap's texel density (`gpu::view::auto_map_size`: a map pixel of
    /// at most half a texel, 512 to 4096; 512 for a room, as in the seed) and reports
    /// the size it chose in the job's parameters.
    pub map_size: Option<u32>,
    /// Neighbourhood k (k x k samples): 1, 3 or 5; default 5. The seed found 3 x 3
    /// enough for most of its scenes, but on the bundled Cornell box (open room, light
    /// 5 mm under the ceiling, overdraw 4 to 5 along vertical rays counting the black
    /// back faces of open geometry, which win the depth lottery and are then rejected as
    /// behind the receiver) 3 x 3 bakes 15-25% dark against `path` and 5 x 5 within 5%;
    /// see docs/sdb.md.
    pub neighbourhood: u32,
    /// Directions gathered per step: 1..=256; default 1, so steps count the seed's
    /// iterations. More per step amortises per-step overhead on a fast GPU. With the
    /// ambient-mode correction on, each is an antipodal pair (two maps).
    pub directions_per_step: u32,
    /// Direction sequence: `stratified` (default) or `random`.
    pub directions: DirectionSequence,
    /// Accumulation: `average` (default) or `leaky`.
    pub mode: AccumulationMode,
    /// Leaky blend factor b in (0, 1], used by `leaky` only; default 0.01 (the seed's).
    pub blend: f32,
    /// Independent stochastic-depth maps per direction, 1..=4; default 1 (the seed). The
    /// gather reads the k x k neighbourhood in every layer, so a surface along a ray with
    /// overdraw K is missed with probability (1 - 1/K)^(layers k^2) instead of
    /// (1 - 1/K)^(k^2), at the cost of one more render per layer.
    pub depth_layers: u32,
    /// `average` only: direction i of a half gets weight i^ramp in the mean. 0 is the
    /// seed's plain mean; the default 1 discounts the early directions, which saw an
    /// incomplete bounce estimate, so the feedback transient decays like n^-2(1-albedo)
    /// instead of n^-(1-albedo), for 4/3 the variance. Range 0..=4.
    pub ramp: f32,
}

impl Default for SdbParams {
    fn default() -> Self {
        SdbParams {
            map_size: None,
            neighbourhood: 5,
            directions_per_step: 1,
            directions: DirectionSequence::Stratified,
            mode: AccumulationMode::Average,
            blend: 0.01,
            depth_layers: 1,
            ramp: 1.0,
        }
    }
}

/// A parameter outside its range.
#[derive(Debug, Clone, thiserror::Error)]
#[error("sdb parameter {name}: {message}")]
pub struct ParamError {
    pub name: &'static str,
    pub message: String,
}

impl SdbParams {
    /// Parse from the job's params object (null or absent: defaults) and check ranges.
    pub fn from_json(v: &serde_json::Value) -> Result<Self, ParamError> {
        let p: SdbParams = if v.is_null() {
            SdbParams::default()
        } else {
            serde_json::from_value(v.clone()).map_err(|e| ParamError {
                name: "params",
                message: e.to_string(),
            })?
        };
        p.validate()?;
        Ok(p)
    }

    pub fn validate(&self) -> Result<(), ParamError> {
        let err = |name, message: String| Err(ParamError { name, message });
        if let Some(n) = self.map_size
            && !(64..=8192).contains(&n)
        {
            return err("map_size", format!("{n} is outside 64..=8192"));
        }
        if ![1, 3, 5].contains(&self.neighbourhood) {
            return err("neighbourhood", format!("{} is not 1, 3 or 5", self.neighbourhood));
        }
        if !(1..=256).contains(&self.directions_per_step) {
            return err(
                "directions_per_step",
                format!("{} is outside 1..=256", self.directions_per_step),
            );
        }
        if !(self.blend > 0.0 && self.blend <= 1.0) {
            return err("blend", format!("{} is outside (0, 1]", self.blend));
        }
        if !(1..=4).contains(&self.depth_layers) {
            return err("depth_layers", format!("{} is outside 1..=4", self.depth_layers));
        }
        if !(0.0..=4.0).contains(&self.ramp) {
            return err("ramp", format!("{} is outside 0..=4", self.ramp));
        }
        Ok(())
    }

    /// The illumination map's size: `map_size`, which `Sdb::prepare` sets when the job
    /// leaves it unset; an engine built directly from unset parameters takes the smallest
    /// automatic size.
    pub fn map_pixels(&self) -> u32 {
        self.map_size.unwrap_or(AUTO_MAP_SIZE_MIN)
    }

    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(self).expect("params serialise")
    }
}

// ---------------------------------------------------------------------------------------
// Inputs in the technique's own terms (built from Scene + Atlas + Lighting by the caller)
// ---------------------------------------------------------------------------------------

/// One triangle as the illumination map needs it (the shared map scene's triangle).
pub type SdbTriangle = MapTriangle;
/// One valid lightmap texel (the shared map scene's texel).
pub type SdbTexel = MapTexel;

/// Everything `sdb` bakes from.
pub struct SdbInput {
    pub triangles: Vec<SdbTriangle>,
    pub texels: Vec<SdbTexel>,
    pub width: u32,
    pub height: u32,
    pub environment: Option<Environment>,
    pub lights: Vec<DirectionalLight>,
    pub seed: u64,
    /// Keep a direct-light layer: light arriving straight from emitters, the sky, the sun
    /// and directional lights (the `path` reference's definition: first vertex only).
    pub want_direct: bool,
    /// The coarse-mode (ambient) correction of `average` mode; None runs without it.
    pub ambient: Option<AmbientMode>,
    /// Direct light the map cannot carry, estimated on the GPU (`gpu::direct_light`):
    /// emitters too small for the map (their triangles must then carry no emission in
    /// `triangles`) and point and spot lights; None: there are none.
    pub small_lights: Option<SmallLights>,
    /// The scene's materials and textures on the GPU (`gpu::scene_rays`), which the maps'
    /// alpha test reads; None: every triangle's material is opaque (scenes made in code).
    pub tables: Option<Arc<GpuTables>>,
}

impl SdbInput {
    /// The shared map scene with none of `sdb`'s own additions (no ambient-mode
    /// correction, no small emitters or point lights).
    pub fn from_map(map: MapScene) -> Self {
        SdbInput {
            triangles: map.triangles,
            texels: map.texels,
            width: map.width,
            height: map.height,
            environment: map.environment,
            lights: map.lights,
            seed: map.seed,
            want_direct: map.want_direct,
            ambient: None,
            small_lights: None,
            tables: None,
        }
    }
}

/// What the ambient-mode correction needs (`shaders/sdb/resolve.wgsl`, `ambient_mode`).
#[derive(Debug, Clone)]
pub struct AmbientMode {
    /// g = <T 1> per channel: the area-weighted mean, over texels and cosine-distributed
    /// directions, of the albedo of the surface seen (0 for sky and black back faces).
    pub gain: Vec3,
    /// World area of each texel (same order as [`SdbInput::texels`]).
    pub texel_area: Vec<f32>,
}

/// Largest ambient gain used: at g = 1 the correction g / (1 - g) is infinite (a closed
/// white room has no finite answer), and past 0.9999 single-precision sums of the mean
/// cannot resolve the residual it multiplies.
const MAX_AMBIENT_GAIN: f32 = 0.9999;

// ---------------------------------------------------------------------------------------
// GPU-side layouts: the structs of shaders/sdb/*.wgsl and gpu/common.wgsl's per-texel and
// per-triangle ones, sizes checked against naga's layout (`gpu_layouts_match_the_shaders`)
// ---------------------------------------------------------------------------------------

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuResolveParams {
    scale: [f32; 4],
    dims: [u32; 4],
    ambient: [f32; 4],
    receivers: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuGatherParams {
    env: [f32; 4],
    eps: [f32; 4],
    misc: [u32; 4],
    texels: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuDirectParams {
    irradiance: [f32; 4],
    bias: [f32; 4],
    misc: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuTriInfo {
    emission: [f32; 3],
    flags: u32,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuTexelShade {
    albedo: [f32; 4],
}

// ---------------------------------------------------------------------------------------
// The engine
// ---------------------------------------------------------------------------------------

/// Half-estimates read back at a snapshot, per valid texel.
#[derive(Debug, Clone)]
pub struct SdbHalf {
    /// Steps in this half.
    pub steps: u64,
    /// Mean (average) or start-up-corrected leaky value of E/pi, total.
    pub total: Vec<Vec3>,
    /// The direct part (emitters, sky, sun, directional lights seen from the texel);
    /// None unless the input asked for it.
    pub direct: Option<Vec<Vec3>>,
}

/// GPU state of one `sdb` bake. Memory per valid texel: 32 B of geometry and material,
/// 2 x 16 B accumulators, 2 x 16 B fed-estimate accumulators, 16 B fed estimate, and
/// 2 x 16 B more for the direct layer and for the sun when they exist.
pub struct SdbEngine {
    ctx: Arc<GpuContext>,
    params: SdbParams,
    n_texels: u32,
    /// Lightmap width, height, valid texel count (the resolve pass's dims).
    lm_dims: [u32; 4],
    corners: [Vec3; 8],
    /// Scene radius in input units (normalised space is divided by it).
    scale: f32,
    environment: Option<Environment>,
    lights: Vec<DirectionalLight>,
    directions: Directions,
    rng: SplitMix64,
    steps_done: u64,
    /// Directions accumulated into the even and odd halves.
    dirs: [u64; 2],
    /// `average` mode: total weight of each half's running mean.
    weights: [f64; 2],
    /// Steps in the even and odd halves.
    half_steps: [u64; 2],

    vertex_count: u32,
    vertex_buf: wgpu::Buffer,
    view_buf: wgpu::Buffer,
    resolve_buf: wgpu::Buffer,
    gather_buf: wgpu::Buffer,
    direct_buf: wgpu::Buffer,
    acc_buf: wgpu::Buffer,
    direct_acc_buf: Option<wgpu::Buffer>,
    sun_acc_buf: Option<wgpu::Buffer>,
    fed_acc_buf: wgpu::Buffer,
    small_emitters: Option<SmallEmitterPass>,
    /// g / (1 - g) per channel, or None without the ambient-mode correction.
    ambient_factor: Option<Vec3>,
    ambient_pipeline: wgpu::ComputePipeline,
    illum_layer_views: Vec<wgpu::TextureView>,
    emission_layer_views: Option<Vec<wgpu::TextureView>>,
    gather_direct_bg: Option<wgpu::BindGroup>,
    depth_view: wgpu::TextureView,
    resolve_pipeline: wgpu::ComputePipeline,
    illum_pipeline: wgpu::RenderPipeline,
    gather_pipeline: wgpu::ComputePipeline,
    resolve_bg: wgpu::BindGroup,
    illum_bg: wgpu::BindGroup,
    gather_bg: wgpu::BindGroup,
    sun_maps: Option<SunMaps>,
    texel_dispatch: (u32, u32),
    pixel_dispatch: (u32, u32),
    /// The bake's time limit and watcher (issue 19 point 10): a watched step runs its
    /// directions in slices and its small lights' pass sliced when long, and is undone
    /// when either says stop between two slices ([`SdbEngine::step`]).
    deadline: Option<std::time::Instant>,
    progress: Option<StepProgress>,
    slicer: StepSlicer,
    /// The texels that gather light (all of them, but in a round of a bake in rounds:
    /// its region, [`SdbEngine::hold_boundary`]).
    receivers: std::ops::Range<u32>,
    /// The bake starts from light already estimated (a round's resumed receivers, or
    /// held light): no bootstrap step, whose clear would also wipe the held texels.
    starts_lit: bool,
}

/// What a step changes on the host, kept to undo a stopped step.
struct StepBook {
    directions: Directions,
    rng: SplitMix64,
    dirs: [u64; 2],
    weights: [f64; 2],
    half_steps: [u64; 2],
}

/// The sun's and directional lights' maps in the shared shadow atlas and the direct pass
/// that reads them (`shaders/sdb/direct.wgsl`, `direct`); only with such lights.
struct SunMaps {
    /// The map being drawn: one [`ShadowView`].
    views_buf: wgpu::Buffer,
    /// Drawn from sdb's own vertex buffer with a plane a triangle
    /// ([`AtlasVertices::MapScene`]).
    atlas: ShadowAtlas,
    pipeline: wgpu::ComputePipeline,
    bg: wgpu::BindGroup,
}

/// The light of small emitters and point and spot lights, and the pass that folds it in.
struct SmallEmitterPass {
    lights: SmallLights,
    params: wgpu::Buffer,
    pipeline: wgpu::ComputePipeline,
    bg: wgpu::BindGroup,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuEmitterAddParams {
    mix: [f32; 4],
    misc: [u32; 4],
}

/// Relative epsilons (normalised scene space, radius 1).
const EPS_NORMAL_PLANE: f32 = 1e-5;
const EPS_ALONG_D: f32 = 1e-5;
/// How far a receiver moves along its geometric normal before the sun map's test, in map
/// pixels: against a neighbouring triangle's plane passing just above it on tessellated
/// curved surfaces (the plane test needs no depth bias; gpu/shadow_view.wgsl).
const SHADOW_OFFSET_PIXELS: f32 = 1.0;

// ---------------------------------------------------------------------------------------
// The technique behind the engine's trait
// ---------------------------------------------------------------------------------------

/// `sdb` as a [`Technique`]: builds [`SdbInput`] from the scene, the texel set and the
/// job's lighting, and keeps the accumulators on the GPU (read back only at snapshots).
pub struct Sdb {
    engine: SdbEngine,
    params: SdbParams,
    notes: Vec<String>,
}

impl Sdb {
    pub fn prepare(inputs: BakeInputs, params: &serde_json::Value) -> Result<Self, EngineError> {
        let mut params: SdbParams = parse_params("sdb", params)?;
        params.validate().map_err(|e| EngineError::BadInput(e.to_string()))?;
        // One device per process, shared by every sdb bake (`gpu::shared`).
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
        if params.map_size.is_none() {
            // The triangles' bounds and the grid's texels: what every chain of a split
            // bake and every round has alike.
            let frame = SceneFrame::of_points(inputs.scene.triangles.iter().flat_map(|t| t.p));
            let n = auto_map_size(
                2.0 * frame.radius,
                inputs.atlas.texels.iter().map(|t| t.size),
                ctx.limits.max_texture_dimension_2d,
            );
            tracing::info!(
                map_size = n,
                "sdb: illumination map size chosen from the scene's size and texel density"
            );
            params.map_size = Some(n);
        }
        let (mut input, notes) = sdb_input(&ctx, &inputs, &params).map_err(gpu_error)?;
        for n in &notes {
            tracing::warn!("{n}");
        }
        input.tables = Some(
            inputs
                .rays
                .gpu_tables(&ctx, "sdb", &inputs.rays.emitters())
                .map_err(gpu_error)?,
        );
        let mut engine = SdbEngine::new(ctx, input, params.clone()).map_err(gpu_error)?;
        engine.warm_up().map_err(gpu_error)?;
        Ok(Sdb { engine, params, notes })
    }

    /// What this bake leaves out of the scene's light, for the job's plan.
    pub fn notes(&self) -> &[String] {
        &self.notes
    }
}

impl Technique for Sdb {
    fn id(&self) -> &'static str {
        "sdb"
    }

    fn params(&self) -> serde_json::Value {
        self.params.to_json()
    }

    fn step(&mut self) -> Result<(), EngineError> {
        self.engine.step().map_err(gpu_error)
    }

    fn wait_for_steps(&mut self) -> Result<(), EngineError> {
        self.engine.wait_idle().map_err(gpu_error)
    }

    fn set_deadline(&mut self, deadline: Option<std::time::Instant>) {
        self.engine.set_deadline(deadline);
    }

    fn set_step_progress(&mut self, progress: StepProgress) {
        self.engine.set_step_progress(progress);
    }

    fn steps_done(&self) -> u64 {
        self.engine.steps_done()
    }

    fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        let [even, odd] = self.engine.read_halves().map_err(gpu_error)?;
        let half = |h: SdbHalf| HalfEstimate {
            // No directional (sh) layer: the plan lists it as left out, and an EXR output
            // that asks for `sh` fails with "the technique kept no directional (sh) layer".
            moments: None,
            steps: h.steps,
            total: h.total,
            direct: h.direct,
        };
        Ok(Snapshot {
            even: half(even),
            odd: half(odd),
        })
    }

    fn accumulating_pass(&self) -> &'static str {
        "sdb gather (shaders/sdb/gather.wgsl)"
    }

    fn hold_boundary(&mut self, boundary: &Boundary<'_>) -> Result<(), EngineError> {
        let resume = boundary.resume.map(|s| {
            let half = |h: &HalfEstimate| SdbHalf {
                steps: h.steps,
                total: h.total.clone(),
                direct: h.direct.clone(),
            };
            (half(&s.even), half(&s.odd))
        });
        self.engine
            .hold_boundary(
                boundary.receivers.clone(),
                boundary.held,
                resume.as_ref().map(|(e, o)| (e, o)),
            )
            .map_err(|m| {
                if m.contains("leaky") {
                    EngineError::BadInput(m)
                } else {
                    EngineError::Internal(m)
                }
            })
    }
}

const SH_ASKED: &str = "asked for";

/// `sdb`'s passes, WGSL in `shaders/sdb/`.
pub mod shaders {
    use crate::engine::gpu::shaders::{MATERIALS, PassShader, SHADOW_VIEW, pass};

    /// Outgoing radiance of every lightmap pixel from the running estimate.
    pub const SDB_RESOLVE: PassShader = pass!("sdb/resolve.wgsl");
    /// The illumination map (stochastic depth) and the shadow maps (nearest depth).
    pub const SDB_ILLUMINATION: PassShader = pass!("sdb/illumination.wgsl", [MATERIALS]);
    /// Gather one direction into the lightmap accumulators.
    pub const SDB_GATHER: PassShader = pass!("sdb/gather.wgsl");
    /// Direct light from the sun and directional lights through a shadow map.
    pub const SDB_DIRECT: PassShader = pass!("sdb/direct.wgsl", [SHADOW_VIEW]);
    /// Every pass of `sdb`.
    pub const ALL: &[PassShader] = &[SDB_RESOLVE, SDB_ILLUMINATION, SDB_GATHER, SDB_DIRECT];
}

/// `sdb` in the technique table (`technique/table.rs`).
pub const ENTRY: TechniqueEntry = TechniqueEntry {
    default_params: || serde_json::to_value(SdbParams::default()).unwrap_or_default(),
    id: "sdb",
    summary: "radiosity by stochastic depth buffering: multi-bounce diffuse light gathered along random global parallel directions (GPU)",
    plan,
    prepare: |inputs, params| Ok(Box::new(Sdb::prepare(inputs, params)?)),
    shaders: shaders::ALL,
    layers: &[OutputLayer::Direct, OutputLayer::Indirect],
    lights: LightSource::ALL,
    check_params: |p| {
        parse_params::<SdbParams>("sdb", p)?
            .validate()
            .map_err(|e| EngineError::BadInput(e.to_string()))
    },
    unbiased: false,
    alpha: AlphaSupport::Partly {
        tested: "its illumination and shadow maps, point and spot lights and small emitters (GPU shadow rays)",
        opaque: "the k x k map lookup (neighbourhood, default 5 pixels), which takes the nearest sample among k x k map pixels, closes cut-outs and BLEND coverage finer than k pixels: measured on a canopy, 8 % of the light through its cut-outs arrives at k = 5, about half at k = 1; it",
    },
    rounds: true,
    tasks: TaskSplit::Chains(
        "each step gathers the reflected light of the running estimate all earlier steps built, over every texel: a range of steps cannot start without the steps before it, and a region's light depends on every other region's; its regions are baked in rounds instead, the others' light held (a job's rounds, bake --rounds, docs/scaling.md)",
    ),
};

/// What `sdb` runs for a scene and job, and what it leaves out (DESIGN section 6).
pub fn plan(f: &SceneFeatures) -> Plan {
    let mut p = Plan::new("sdb");
    p.run(
        "resolve",
        "outgoing radiance of every lightmap pixel from the running estimate (bounces)",
    );
    p.run(
        "illumination map",
        "orthographic render with stochastic depth along each direction",
    );
    p.run("gather", "k x k neighbourhood lookup for every texel, per direction");
    p.run(
        "ambient mode",
        "coarse correction of the bounce feedback in `average` mode (the default), after 64k CPU rays measure the mean albedo seen",
    );
    p.decide(
        "small-emitter sampling (GPU rays)",
        f.emissive_triangles > 0,
        "emitter triangles under two map pixels, if any, shine through shadow rays on the GPU, one per texel a step",
        "no emitters",
    );
    let punctual = f.punctual_lights.saturating_sub(f.directional_lights);
    p.decide(
        "point and spot lights (GPU rays)",
        punctual > 0,
        &format!(
            "{punctual} point/spot light(s): one shadow ray per texel and light on the GPU, once a half; they feed the bounces"
        ),
        "no point or spot light",
    );
    let directional = f.sun || f.directional_lights > 0;
    p.decide(
        "shadow maps + direct pass",
        directional,
        "the job has a sun or the scene has directional lights",
        "no sun and no directional light",
    );
    p.decide("sky lookups", f.sky, "the job has a sky", "the job has no sky");
    p.decide(
        DIRECT_LAYER,
        f.want_direct,
        "direct or indirect output asked for (emission target + direct accumulators)",
        "not asked for in outputs",
    );
    if f.want_sh {
        p.leave_out(
            SH_LAYER,
            &format!("{SH_ASKED}, but sdb keeps no directional moments yet: `sh` outputs fail with sdb (use `path`)"),
        );
    } else {
        p.leave_out(SH_LAYER, "not asked for in outputs");
    }
    if f.glossy_materials > 0 {
        p.leave_out(
            "glossy transport",
            "sdb gathers diffuse light only; metallic/roughness are ignored",
        );
    } else {
        p.leave_out("glossy data", "every material is a fully rough dielectric");
    }
    p.error_estimate = "noise only: the bias of the k x k neighbourhood lookup, the overdraw and the \
                        bounce feedback's slow convergence in stiff rooms is not in it (docs/sdb.md)"
        .into();
    p
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::gpu::view::{DEPTH_STOCHASTIC, make_view};
    use glam::Vec2;

    /// The Rust mirrors of WGSL structs have the shaders' sizes (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[
            Mirror::of::<GpuResolveParams>("GpuResolveParams", shaders::SDB_RESOLVE, "ResolveParams"),
            Mirror::of::<GpuGatherParams>("GpuGatherParams", shaders::SDB_GATHER, "GatherParams"),
            Mirror::of::<GpuDirectParams>("GpuDirectParams", shaders::SDB_DIRECT, "DirectParams"),
            Mirror::of::<GpuEmitterAddParams>("GpuEmitterAddParams", shaders::SDB_DIRECT, "EmitterAddParams"),
            Mirror::of::<GpuTriInfo>("GpuTriInfo", shaders::SDB_GATHER, "TriInfo"),
            Mirror::of::<GpuTexelShade>("GpuTexelShade", shaders::SDB_GATHER, "TexelShade"),
        ]);
    }

    fn quad_tris(corners: [Vec3; 4], mesh: u32) -> [SdbTriangle; 2] {
        let t = |a: usize, b: usize, c: usize| SdbTriangle {
            p: [corners[a], corners[b], corners[c]],
            lm: [Vec2::ZERO; 3],
            emission: Vec3::ZERO,
            emission_textured: false,
            double_sided: false,
            mesh,
            material: 0,
            alpha_uv: [Vec2::ZERO; 3],
        };
        [t(0, 1, 2), t(0, 2, 3)]
    }

    /// A unit cube from six separate meshes, outward-facing, counter-clockwise.
    fn cube() -> Vec<SdbTriangle> {
        let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
        let faces = [
            [v(0., 0., 1.), v(1., 0., 1.), v(1., 1., 1.), v(0., 1., 1.)],
            [v(1., 0., 0.), v(0., 0., 0.), v(0., 1., 0.), v(1., 1., 0.)],
            [v(1., 0., 1.), v(1., 0., 0.), v(1., 1., 0.), v(1., 1., 1.)],
            [v(0., 0., 0.), v(0., 0., 1.), v(0., 1., 1.), v(0., 1., 0.)],
            [v(0., 1., 1.), v(1., 1., 1.), v(1., 1., 0.), v(0., 1., 0.)],
            [v(0., 0., 0.), v(1., 0., 0.), v(1., 0., 1.), v(0., 0., 1.)],
        ];
        faces
            .iter()
            .enumerate()
            .flat_map(|(i, f)| quad_tris(*f, i as u32))
            .collect()
    }

    #[test]
    fn closed_surfaces_are_found_across_meshes() {
        let tris = cube();
        assert!(cullable_triangles(&tris).iter().all(|&c| c));
        // Remove one face: the box is open, nothing may be culled.
        let open: Vec<SdbTriangle> = tris[..10].to_vec();
        assert!(cullable_triangles(&open).iter().all(|&c| !c));
        // A closed cube plus a separate open quad: only the cube is cullable.
        let mut mixed = tris.clone();
        mixed.extend(quad_tris(
            [
                Vec3::splat(5.0),
                Vec3::new(6., 5., 5.),
                Vec3::new(6., 6., 5.),
                Vec3::new(5., 6., 5.),
            ],
            9,
        ));
        let c = cullable_triangles(&mixed);
        assert!(c[..12].iter().all(|&x| x) && c[12..].iter().all(|&x| !x));
        // A double-sided face makes its surface open (it is never culled itself).
        let mut ds = tris;
        ds[0].double_sided = true;
        ds[1].double_sided = true;
        assert!(cullable_triangles(&ds).iter().all(|&c| !c));
    }

    #[test]
    fn params_defaults_and_ranges() {
        let p = SdbParams::from_json(&serde_json::Value::Null).unwrap();
        assert_eq!(p, SdbParams::default());
        let p = SdbParams::from_json(&serde_json::json!({"neighbourhood": 5, "mode": "leaky", "blend": 0.05})).unwrap();
        assert_eq!((p.neighbourhood, p.mode, p.blend), (5, AccumulationMode::Leaky, 0.05));
        for bad in [
            serde_json::json!({"neighbourhood": 4}),
            serde_json::json!({"map_size": 32}),
            serde_json::json!({"blend": 0.0}),
            serde_json::json!({"directions_per_step": 0}),
            serde_json::json!({"ramp": 9}),
            serde_json::json!({"directions": "sobol"}),
            serde_json::json!({"unknown": 1}),
        ] {
            assert!(SdbParams::from_json(&bad).is_err(), "{bad} accepted");
        }
    }

    #[test]
    fn stratified_directions_are_uniform_and_seeded() {
        // Mean of a uniform distribution on the sphere is 0, and the mean of |z| is 1/2;
        // R2 with 4096 points gets both far closer than i.i.d. sampling (about 0.009).
        let mut d = Directions::new(DirectionSequence::Stratified, 42);
        let v: Vec<Vec3> = (0..4096).map(|_| d.next_direction()).collect();
        let mean = v.iter().copied().sum::<Vec3>() / v.len() as f32;
        let abs_z = v.iter().map(|w| w.z.abs()).sum::<f32>() / v.len() as f32;
        assert!(mean.length() < 2e-3, "{mean}");
        assert!((abs_z - 0.5).abs() < 2e-3, "{abs_z}");
        assert!(v.iter().all(|w| (w.length() - 1.0).abs() < 1e-5));
        let mut other = Directions::new(DirectionSequence::Stratified, 43);
        assert!(
            other.next_direction().distance(v[0]) > 1e-3,
            "seeds must rotate the sequence"
        );
    }

    #[test]
    fn view_covers_the_bounds_with_a_right_handed_frame() {
        let corners: [Vec3; 8] = std::array::from_fn(|i| {
            Vec3::new((i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32) * 2.0 - 1.0
        });
        let mut dirs = Directions::new(DirectionSequence::Random, 1);
        for _ in 0..64 {
            let d = dirs.next_direction();
            let v = make_view(d, &corners, 256, (0.7, 0.3), 0, DEPTH_STOCHASTIC);
            let (r, u, dd) = (
                Vec3::from_slice(&v.right[..3]),
                Vec3::from_slice(&v.up[..3]),
                Vec3::from_slice(&v.dir[..3]),
            );
            // right x up = -d: a look-at camera, so winding is preserved on screen.
            assert!((r.cross(u) + dd).length() < 1e-5);
            for c in &corners {
                let a = c.dot(r) - v.right[3];
                let b = c.dot(u) - v.up[3];
                let t = c.dot(dd) - v.dir[3];
                assert!(
                    a >= 0.0 && a <= v.extent[0] && b >= 0.0 && b <= v.extent[0],
                    "corner outside the map"
                );
                assert!(t > 0.0 && t < v.extent[1], "corner outside the depth range");
            }
        }
    }
}
