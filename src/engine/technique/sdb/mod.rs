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
//!   from the texel's ray, blurring contact shadows over about k pixels of the map.
//! - Feedback transient (average mode): early directions see an incomplete bounce
//!   estimate; without the ambient-mode correction the bias decays like
//!   n^-(1 + ramp)(1 - albedo) in the number of directions n. The correction removes the
//!   estimate-shaped part of it; the rest (light distributions unlike the current
//!   estimate) decays at that rate still.
//! - Emitters smaller than two map pixels are taken out of the map and sampled by the
//!   same GPU pass (next-event estimation, one shadow ray per texel per step): the map
//!   could not show them, and the k x k lookup would widen them k-fold.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use serde::{Deserialize, Serialize};

mod lights;

pub use lights::{SmallLights, ambient_mode, sdb_input};

use super::api::{
    AlphaSupport, BakeInputs, Boundary, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry,
    go_on_until, gpu_error, parse_params,
};
use crate::engine::accumulate::{HalfEstimate, Snapshot};
use crate::engine::gpu::directions::sample_cone;
pub use crate::engine::gpu::directions::{
    DirectionSequence, Directions, SplitMix64, random_rotation, square_to_sphere,
};
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_at, group_of, layout_at, layout_of};
pub use crate::engine::gpu::map_scene::{DirectionalLight, Environment, MapScene, MapTexel, MapTriangle};
use crate::engine::gpu::scene_rays::{GpuTables, opaque_material_tables};
use crate::engine::gpu::shadow::{AtlasVertices, ShadowAtlas, ShadowDraw, ShadowView, map_triangle_planes};
use crate::engine::gpu::slices::{Aside, Sliced, StepSlicer};
use crate::engine::gpu::texels::GpuTexelGeom;
pub use crate::engine::gpu::view::cullable_triangles;
use crate::engine::gpu::view::{
    DEPTH_NEAREST, DEPTH_STOCHASTIC, EMPTY_T, GpuDims, GpuVertex, GpuView, NO_TEXEL, TRI_CULL_BACK, TRI_DOUBLE_SIDED,
    TRI_TEXTURED_EMISSION, fill_map, make_view,
};
use crate::engine::gpu::{self, GpuContext, GpuError};
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
    /// maximum texture size); default 512, as in the seed.
    pub map_size: u32,
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
            map_size: 512,
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
        if !(64..=8192).contains(&self.map_size) {
            return err("map_size", format!("{} is outside 64..=8192", self.map_size));
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

impl SdbEngine {
    /// Upload the scene and build the passes. Only the passes the input needs are
    /// created: no shadow maps or direct pass without directional lights.
    pub fn new(ctx: Arc<GpuContext>, input: SdbInput, params: SdbParams) -> Result<Self, GpuError> {
        if params.map_size > ctx.limits.max_texture_dimension_2d {
            return Err(GpuError::Unsupported {
                adapter: ctx.info.name.clone(),
                missing: format!(
                    "illumination map {0}x{0} exceeds max texture size {1}",
                    params.map_size, ctx.limits.max_texture_dimension_2d
                ),
            });
        }
        let (width, height) = (input.width.max(1), input.height.max(1));
        let n_texels = input.texels.len() as u32;
        let storage_need = (width as u64 * height as u64).max(2 * n_texels as u64) * 16;
        ctx.check_storage(&format!("sdb: a {width}x{height} lightmap"), storage_need)?;

        // Normalised scene space: bounds of triangles and texel points together.
        let frame = SceneFrame::of_points(
            input
                .triangles
                .iter()
                .flat_map(|t| t.p)
                .chain(input.texels.iter().map(|t| t.position)),
        );
        let scale = frame.radius;
        let norm = |p: Vec3| frame.norm(p);
        let corners = frame.corners();

        let cullable = cullable_triangles(&input.triangles);
        let mut vertices = Vec::with_capacity(input.triangles.len() * 3);
        let mut tris = Vec::with_capacity(input.triangles.len());
        for (i, t) in input.triangles.iter().enumerate() {
            vertices.extend(GpuVertex::corners(i as u32, t, norm));
            let mut flags = 0;
            if t.double_sided {
                flags |= TRI_DOUBLE_SIDED;
            } else if cullable[i] {
                flags |= TRI_CULL_BACK;
            }
            if t.emission_textured {
                flags |= TRI_TEXTURED_EMISSION;
            }
            tris.push(GpuTriInfo {
                emission: t.emission.to_array(),
                flags,
            });
        }
        let geom: Vec<GpuTexelGeom> = input
            .texels
            .iter()
            .map(|t| GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal))
            .collect();
        // The texel's area in normalised units rides in the albedo's spare channel (only
        // the ambient-mode mean reads it; relative areas are all it needs).
        let area = |k: usize| {
            input
                .ambient
                .as_ref()
                .map_or(0.0, |a| a.texel_area[k] / (scale * scale))
        };
        let shade: Vec<GpuTexelShade> = input
            .texels
            .iter()
            .enumerate()
            .map(|(k, t)| GpuTexelShade {
                albedo: t.albedo.extend(area(k)).to_array(),
            })
            .collect();
        let fill = fill_map(width, height, &input.texels);

        use wgpu::BufferUsages as U;
        let vertex_buf = ctx.buffer_init("sdb vertices", &vertices, U::VERTEX);
        let tris_buf = ctx.buffer_init("sdb triangle info", &tris, U::STORAGE);
        let geom_buf = ctx.buffer_init("sdb texel geometry", &geom, U::STORAGE);
        let shade_buf = ctx.buffer_init("sdb texel materials", &shade, U::STORAGE);
        let fill_buf = ctx.buffer_init("sdb lightmap fill map", &fill, U::STORAGE);
        let radiance_buf = ctx.buffer_zeroed("sdb outgoing radiance", width as u64 * height as u64 * 16, U::STORAGE);
        let acc_buf = ctx.buffer_zeroed(
            "sdb accumulators (even, odd)",
            n_texels as u64 * 2 * 16,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let want_direct = input.want_direct;
        let direct_acc_buf = want_direct.then(|| {
            ctx.buffer_zeroed(
                "sdb direct accumulators (even, odd)",
                n_texels as u64 * 2 * 16,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            )
        });
        let has_light_acc = !input.lights.is_empty() || input.small_lights.is_some();
        let sun_acc_buf = has_light_acc.then(|| {
            ctx.buffer_zeroed(
                "sdb sun and directional light accumulators (even, odd)",
                n_texels as u64 * 2 * 16,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            )
        });
        let ambient_buf = ctx.buffer_zeroed("sdb ambient mode state", 32, U::STORAGE);
        let fed_buf = ctx.buffer_zeroed("sdb estimate fed per texel", n_texels as u64 * 16, U::STORAGE);
        let fed_acc_buf = ctx.buffer_zeroed(
            "sdb fed estimate accumulators (even, odd)",
            n_texels as u64 * 2 * 16,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let ambient_factor = match (&input.ambient, params.mode) {
            (Some(a), AccumulationMode::Average) => {
                let g = a.gain.clamp(Vec3::ZERO, Vec3::splat(MAX_AMBIENT_GAIN));
                Some(g / (Vec3::ONE - g))
            }
            // The leaky blend forgets on purpose; a mean of everything fed does not apply.
            _ => None,
        };
        let view_buf = ctx.uniform("sdb view", &GpuView::zeroed());
        let dims_buf = ctx.uniform(
            "sdb lightmap dims",
            &GpuDims {
                dims: [width, height, n_texels, 0],
            },
        );
        let resolve_buf = ctx.uniform("sdb resolve params", &GpuResolveParams::zeroed());
        let gather_buf = ctx.uniform("sdb gather params", &GpuGatherParams::zeroed());
        let direct_buf = ctx.uniform("sdb direct params", &GpuDirectParams::zeroed());

        // Emitted radiance per lightmap pixel: the emission of triangles with an emissive
        // texture (the others use their material's exact value).
        let emission_px_buf = {
            let px: Vec<[f32; 4]> = fill
                .iter()
                .map(|&k| {
                    if k == NO_TEXEL {
                        [0.0; 4]
                    } else {
                        input.texels[k as usize].emission.extend(1.0).to_array()
                    }
                })
                .collect();
            ctx.buffer_init("sdb emission per lightmap pixel", &px, U::STORAGE)
        };
        let extent = wgpu::Extent3d {
            width: params.map_size,
            height: params.map_size,
            depth_or_array_layers: 1,
        };
        let layers = params.depth_layers;
        let layered = wgpu::Extent3d {
            depth_or_array_layers: layers,
            ..extent
        };
        let illum_tex = ctx.texture_2d(
            "sdb illumination map (rgb radiance, a distance), one layer per depth draw",
            layered,
            wgpu::TextureFormat::Rgba32Float,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let depth_tex = ctx.texture_2d(
            "sdb illumination map depth",
            extent,
            wgpu::TextureFormat::Depth32Float,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
        );
        let emission_tex = want_direct.then(|| {
            ctx.texture_2d(
                "sdb illumination map emission",
                layered,
                wgpu::TextureFormat::Rgba32Float,
                wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            )
        });
        // Per-layer views to render into; one array view for the compute passes.
        let layer_views = |t: &wgpu::Texture, label: &str| -> Vec<wgpu::TextureView> {
            (0..layers)
                .map(|l| {
                    t.create_view(&wgpu::TextureViewDescriptor {
                        label: Some(&format!("{label} layer {l}")),
                        dimension: Some(wgpu::TextureViewDimension::D2),
                        base_array_layer: l,
                        array_layer_count: Some(1),
                        ..Default::default()
                    })
                })
                .collect()
        };
        let array_view = |t: &wgpu::Texture, label: &str| {
            t.create_view(&wgpu::TextureViewDescriptor {
                label: Some(label),
                dimension: Some(wgpu::TextureViewDimension::D2Array),
                ..Default::default()
            })
        };
        let emission_layer_views = emission_tex
            .as_ref()
            .map(|t| layer_views(t, "sdb illumination emission"));
        let emission_view = emission_tex
            .as_ref()
            .map(|t| array_view(t, "sdb illumination emission array view"));
        let illum_layer_views = layer_views(&illum_tex, "sdb illumination map");
        let illum_view = array_view(&illum_tex, "sdb illumination map array view");
        let depth_view = depth_tex.create_view(&wgpu::TextureViewDescriptor {
            label: Some("sdb illumination depth view"),
            ..Default::default()
        });

        use wgpu::ShaderStages as S;
        // Resolve.
        let resolve_module = ctx.shader(&shaders::SDB_RESOLVE)?;
        let resolve_binds = [
            Bind::Uniform(&resolve_buf),
            Bind::Read(&fill_buf),
            Bind::Read(&shade_buf),
            Bind::Read(&acc_buf),
            Bind::Write(&radiance_buf),
            // Without lights the shader reads no sun accumulators (dims.w = 0); the
            // binding still needs a buffer, so it aliases the gathered ones.
            Bind::Read(sun_acc_buf.as_ref().unwrap_or(&acc_buf)),
            Bind::Write(&ambient_buf),
            Bind::Write(&fed_buf),
            Bind::Read(&fed_acc_buf),
        ];
        let resolve_layout = layout_of(&ctx, "sdb resolve layout", S::COMPUTE, &resolve_binds);
        let resolve_pipeline = compute_pipeline(&ctx, "sdb resolve", &resolve_module, "resolve", &resolve_layout);
        let ambient_pipeline = compute_pipeline(
            &ctx,
            "sdb ambient mode",
            &resolve_module,
            "ambient_mode",
            &resolve_layout,
        );
        let resolve_bg = group_of(&ctx, "sdb resolve bindings", &resolve_layout, &resolve_binds);

        // The alpha test's tables: the scene's, or every material opaque.
        let opaque_tables;
        let tables_buf = match &input.tables {
            Some(t) => &t.tables,
            None => {
                let materials = input.triangles.iter().map(|t| t.material + 1).max().unwrap_or(1);
                opaque_tables = ctx.buffer_init(
                    "sdb opaque materials",
                    &opaque_material_tables(materials),
                    wgpu::BufferUsages::STORAGE,
                );
                &opaque_tables
            }
        };

        // Illumination map (and shadow maps).
        let illum_module = ctx.shader(&shaders::SDB_ILLUMINATION)?;
        let illum_binds = [
            Bind::Uniform(&view_buf),
            Bind::Uniform(&dims_buf),
            Bind::Read(&tris_buf),
            Bind::Read(&radiance_buf),
            Bind::Read(&emission_px_buf),
            Bind::Read(tables_buf),
        ];
        let illum_layout = layout_of(&ctx, "sdb illumination layout", S::VERTEX_FRAGMENT, &illum_binds);
        let illum_groups: Vec<Option<&wgpu::BindGroupLayout>> = vec![Some(&illum_layout)];
        let illum_pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("sdb illumination pipeline layout"),
            bind_group_layouts: &illum_groups,
            immediate_size: 0,
        });
        let target = Some(wgpu::ColorTargetState {
            format: wgpu::TextureFormat::Rgba32Float,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        });
        let targets = if want_direct {
            vec![target.clone(), target]
        } else {
            vec![target]
        };
        let illum_pipeline = ctx.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("sdb illumination map"),
            layout: Some(&illum_pl),
            vertex: wgpu::VertexState {
                module: &illum_module,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<GpuVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &GpuVertex::ATTRIBUTES,
                })],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                front_face: wgpu::FrontFace::Ccw,
                // Culling is decided per triangle in the fragment shader (closed meshes
                // vs open or double-sided geometry), and shadow maps keep every face.
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: wgpu::TextureFormat::Depth32Float,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &illum_module,
                entry_point: Some(if want_direct { "fs_main_direct" } else { "fs_main" }),
                compilation_options: Default::default(),
                targets: &targets,
            }),
            multiview_mask: None,
            cache: None,
        });
        let illum_bg = group_of(&ctx, "sdb illumination bindings", &illum_layout, &illum_binds);

        // Gather.
        let gather_module = ctx.shader(&shaders::SDB_GATHER)?;
        let gather_binds = [
            Bind::Uniform(&view_buf),
            Bind::Uniform(&gather_buf),
            Bind::Texture(&illum_view),
            Bind::Read(&geom_buf),
            Bind::Write(&acc_buf),
            Bind::Read(&fed_buf),
            Bind::Write(&fed_acc_buf),
        ];
        let gather_layout = layout_of(&ctx, "sdb gather layout", S::COMPUTE, &gather_binds);
        // Group 1 of the direct-layer gather: the emission map and the direct accumulators
        // (placeholders of the same kinds when there is no direct layer: the layout only).
        let gather_direct_layout = layout_of(
            &ctx,
            "sdb gather direct layout",
            S::COMPUTE,
            &[Bind::Texture(&illum_view), Bind::Write(&acc_buf)],
        );
        let gather_pipeline = if want_direct {
            let pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("sdb gather (direct layer)"),
                bind_group_layouts: &[Some(&gather_layout), Some(&gather_direct_layout)],
                immediate_size: 0,
            });
            ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("sdb gather (direct layer)"),
                layout: Some(&pl),
                module: &gather_module,
                entry_point: Some("gather_direct"),
                compilation_options: Default::default(),
                cache: None,
            })
        } else {
            compute_pipeline(&ctx, "sdb gather", &gather_module, "gather", &gather_layout)
        };
        let gather_direct_bg = match (&emission_view, &direct_acc_buf) {
            (Some(view), Some(direct_acc)) if want_direct => Some(group_of(
                &ctx,
                "sdb gather direct bindings",
                &gather_direct_layout,
                &[Bind::Texture(view), Bind::Write(direct_acc)],
            )),
            _ => None,
        };
        let gather_bg = group_of(&ctx, "sdb gather bindings", &gather_layout, &gather_binds);

        // Direct light: only with directional lights (DESIGN.md section 6), each drawn in
        // turn as one orthographic map of the shared shadow atlas (gpu::shadow).
        let sun_maps = match &sun_acc_buf {
            Some(sun_acc) if !input.lights.is_empty() => {
                let module = ctx.shader(&shaders::SDB_DIRECT)?;
                let n = params.map_size;
                let views_buf = ctx.buffer_zeroed(
                    "sdb sun map view",
                    std::mem::size_of::<ShadowView>() as u64,
                    U::STORAGE | U::COPY_DST,
                );
                let planes = ctx.buffer_init(
                    "sdb triangle planes (sun maps)",
                    &map_triangle_planes(&input.triangles, &frame),
                    U::STORAGE,
                );
                let source = AtlasVertices::MapScene { planes: &planes };
                let atlas = ShadowAtlas::new(&ctx, "sdb sun", n, n, &views_buf, tables_buf, source)?;
                let binds = [
                    Bind::Read(&views_buf),
                    Bind::Uniform(&direct_buf),
                    Bind::Texture2d(&atlas.plane_view),
                    Bind::Read(&geom_buf),
                    Bind::Write(sun_acc),
                ];
                let layout = layout_of(&ctx, "sdb direct layout", S::COMPUTE, &binds);
                let pipeline = compute_pipeline(&ctx, "sdb direct", &module, "direct", &layout);
                let bg = group_of(&ctx, "sdb direct bindings", &layout, &binds);
                Some(SunMaps {
                    views_buf,
                    atlas,
                    pipeline,
                    bg,
                })
            }
            _ => None,
        };
        // Emitters too small for the map, point and spot lights: the direct-light pass's
        // latest estimate per half, folded into the light accumulators.
        let small_emitters = match (input.small_lights, &sun_acc_buf) {
            (Some(lights), Some(sun_acc)) => {
                let module = ctx.shader(&shaders::SDB_DIRECT)?;
                let params_buf = ctx.uniform("sdb small emitters params", &GpuEmitterAddParams::zeroed());
                // Bindings 4..6 of sdb/direct.wgsl (0..3 belong to its `direct` entry point).
                let binds = [
                    Bind::Write(sun_acc),
                    Bind::Read(lights.light.accumulators()),
                    Bind::Uniform(&params_buf),
                ];
                let layout = layout_at(&ctx, "sdb small emitters layout", 4, S::COMPUTE, &binds);
                let pipeline = compute_pipeline(&ctx, "sdb small emitters", &module, "emitter_add", &layout);
                let bg = group_at(&ctx, "sdb small emitters bindings", &layout, 4, &binds);
                Some(SmallEmitterPass {
                    lights,
                    params: params_buf,
                    pipeline,
                    bg,
                })
            }
            _ => None,
        };
        ctx.take_error("sdb setup")?;

        let lights = input
            .lights
            .iter()
            .map(|l| DirectionalLight {
                direction: l.direction.normalize(),
                ..*l
            })
            .collect();
        Ok(SdbEngine {
            texel_dispatch: gpu::dispatch_size_64(n_texels),
            pixel_dispatch: gpu::dispatch_size_64(width * height),
            deadline: None,
            progress: None,
            slicer: StepSlicer::per_unit("sdb directions"),
            receivers: 0..n_texels,
            starts_lit: false,
            directions: Directions::new(params.directions, input.seed),
            rng: SplitMix64::new(input.seed ^ 0x0A11_CE5E_ED00_0001),
            ctx,
            params,
            n_texels,
            lm_dims: [width, height, n_texels, u32::from(has_light_acc)],
            corners,
            scale,
            environment: input.environment,
            lights,
            steps_done: 0,
            dirs: [0, 0],
            weights: [0.0, 0.0],
            half_steps: [0, 0],
            vertex_count: vertices.len() as u32,
            vertex_buf,
            view_buf,
            resolve_buf,
            gather_buf,
            direct_buf,
            acc_buf,
            direct_acc_buf,
            sun_acc_buf,
            fed_acc_buf,
            small_emitters,
            ambient_factor,
            ambient_pipeline,
            illum_layer_views,
            emission_layer_views,
            gather_direct_bg,
            depth_view,
            resolve_pipeline,
            illum_pipeline,
            gather_pipeline,
            resolve_bg,
            illum_bg,
            gather_bg,
            sun_maps,
        })
    }

    pub fn params(&self) -> &SdbParams {
        &self.params
    }

    /// Blocks until the device has done every step submitted so far
    /// ([`Technique::wait_for_steps`]).
    pub fn wait_idle(&self) -> Result<(), GpuError> {
        self.ctx.wait_idle()
    }

    pub fn steps_done(&self) -> u64 {
        self.steps_done
    }

    pub fn texel_count(&self) -> u32 {
        self.n_texels
    }

    /// Block until the GPU has finished every submitted step (benchmarks).
    pub fn finish(&self) -> Result<(), GpuError> {
        self.ctx.wait_idle()?;
        self.ctx.take_error("sdb step")
    }

    /// The adapter this engine runs on.
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        &self.ctx.info
    }

    /// Scene radius in input units (for reports).
    pub fn scene_radius(&self) -> f32 {
        self.scale
    }

    /// Leaky start-up correction: an exponential average started from zero has total
    /// weight 1 - (1 - b)^n.
    fn leaky_correction(&self, n: u64) -> f64 {
        if n == 0 {
            0.0
        } else {
            1.0 / (1.0 - (1.0 - self.params.blend as f64).powf(n as f64))
        }
    }

    /// The weights that turn the two halves into the current estimate: gathered (x, y),
    /// sun accumulators (z, w). The gathered halves are ratios, so a leaky half needs no
    /// start-up correction there; the sun's plain blends do.
    fn half_scales(&self) -> [f32; 4] {
        match self.params.mode {
            AccumulationMode::Average => {
                let total = self.weights[0] + self.weights[1];
                if total == 0.0 {
                    [0.0; 4]
                } else {
                    let (a, b) = ((self.weights[0] / total) as f32, (self.weights[1] / total) as f32);
                    [a, b, a, b]
                }
            }
            AccumulationMode::Leaky => {
                let live = self.dirs.iter().filter(|&&n| n > 0).count().max(1) as f64;
                let share = |h: usize| if self.dirs[h] > 0 { (1.0 / live) as f32 } else { 0.0 };
                [
                    share(0),
                    share(1),
                    (self.leaky_correction(self.dirs[0]) / live) as f32,
                    (self.leaky_correction(self.dirs[1]) / live) as f32,
                ]
            }
        }
    }

    /// Blend factor for the next direction of half `h` (and book-keeping).
    fn next_blend(&mut self, h: usize) -> f32 {
        self.dirs[h] += 1;
        match self.params.mode {
            AccumulationMode::Leaky => self.params.blend,
            AccumulationMode::Average => {
                let w = (self.dirs[h] as f64).powf(self.params.ramp as f64);
                self.weights[h] += w;
                (w / self.weights[h]) as f32
            }
        }
    }

    /// With the ambient-mode correction the first step only bootstraps: it gathers with
    /// nothing fed (so it sees emitters and the sky alone) and gives the correction the
    /// shape of the light, v = x. Once the second step's resolve has fed x + delta, its
    /// gathers are cleared from the accumulators: kept, they would weigh in the mean as a
    /// share of the wrong answer (2 / n^2 of it after n steps with `ramp` 1), which in a
    /// stiff room is most of the error left.
    fn drop_bootstrap_step(&mut self, encoder: &mut wgpu::CommandEncoder) {
        for b in self.accumulators() {
            encoder.clear_buffer(b, 0, None);
        }
        // The other half (odd, about to take this step's directions) is still empty.
        self.dirs[0] = 0;
        self.weights[0] = 0.0;
        self.half_steps[0] = 0;
    }

    /// Every accumulator a step blends into (both halves each): the lightmap's, the fed
    /// estimate's, and the sun's and the direct layer's where they exist.
    fn accumulators(&self) -> impl Iterator<Item = &wgpu::Buffer> {
        [
            Some(&self.acc_buf),
            Some(&self.fed_acc_buf),
            self.sun_acc_buf.as_ref(),
            self.direct_acc_buf.as_ref(),
        ]
        .into_iter()
        .flatten()
    }

    /// Render the map along the current view into array layer `layer`; the layer goes to
    /// the shaders as the instance index and into the depth hash, so layers are
    /// independent draws of the stochastic depth.
    fn render_map(&self, encoder: &mut wgpu::CommandEncoder, label: &str, layer: u32) {
        let attachment = |view, a: f64| {
            Some(wgpu::RenderPassColorAttachment {
                view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color {
                        r: 0.0,
                        g: 0.0,
                        b: 0.0,
                        a,
                    }),
                    store: wgpu::StoreOp::Store,
                },
            })
        };
        let l = layer as usize;
        let mut colors = vec![attachment(&self.illum_layer_views[l], EMPTY_T as f64)];
        if let Some(v) = &self.emission_layer_views {
            colors.push(attachment(&v[l], 0.0));
        }
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some(label),
            color_attachments: &colors,
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &self.depth_view,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.illum_pipeline);
        pass.set_bind_group(0, &self.illum_bg, &[]);
        pass.set_vertex_buffer(0, self.vertex_buf.slice(..));
        pass.draw(0..self.vertex_count, layer..layer + 1);
    }

    fn dispatch(
        encoder: &mut wgpu::CommandEncoder,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        bg: &wgpu::BindGroup,
        size: (u32, u32),
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bg, &[]);
        pass.dispatch_workgroups(size.0, size.1, 1);
    }

    fn jitter(&mut self) -> (f32, f32) {
        (self.rng.next_f64() as f32, self.rng.next_f64() as f32)
    }

    /// The resolve pass (and, with the ambient-mode correction, the bootstrap step's
    /// drop), submitted.
    fn submit_resolve(&mut self) -> wgpu::SubmissionIndex {
        let ambient = self.ambient_factor.map_or([0.0; 4], |f| f.extend(0.0).to_array());
        let resolve = GpuResolveParams {
            scale: self.half_scales(),
            dims: self.lm_dims,
            ambient,
            receivers: [self.receivers.start, self.receivers.end, 0, 0],
        };
        self.ctx
            .queue
            .write_buffer(&self.resolve_buf, 0, bytemuck::bytes_of(&resolve));
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("sdb resolve"),
        });
        if self.ambient_factor.is_some() {
            Self::dispatch(
                &mut encoder,
                "sdb ambient mode",
                &self.ambient_pipeline,
                &self.resolve_bg,
                (1, 1),
            );
        }
        Self::dispatch(
            &mut encoder,
            "sdb resolve",
            &self.resolve_pipeline,
            &self.resolve_bg,
            self.pixel_dispatch,
        );
        if self.bootstraps() {
            self.drop_bootstrap_step(&mut encoder);
        }
        self.ctx.queue.submit([encoder.finish()])
    }

    /// Directions `first .. first + count` of this step (`j` in the pairs rule below),
    /// each its illumination maps, gather, and sun maps and direct passes, submitted;
    /// `previous` is the last direction drawn and `decay` what the blends leave of the old
    /// mean, both carried from one call to the next. Returns the last submission.
    fn submit_directions(
        &mut self,
        parity: u32,
        (first, count): (u64, u64),
        previous: &mut Vec3,
        decay: &mut f64,
    ) -> wgpu::SubmissionIndex {
        // With the ambient-mode correction, directions come in antipodal pairs (d, -d)
        // within one step: every texel of a closed surface then gathers (and records the
        // step's feed in its fed mean M) in exactly one of the two, which the correction's
        // model x = T M + e needs. With one direction a step, the surfaces a texel sees
        // along d face -d and do not gather that step, M lags the feed their neighbours
        // used, <x - M> is biased, and the gain g / (1 - g) (9 at albedo 0.9) fed that bias
        // back: the closed box of albedo 0.9 read 17.6 instead of 1 with seed 7 (issue 21).
        let pairs = self.ambient_factor.is_some();
        let mut last = None;
        for j in first..first + count {
            let d = if pairs && j % 2 == 1 {
                -*previous
            } else {
                self.directions.next_direction()
            };
            *previous = d;
            let dir_index = self.dirs[0] + self.dirs[1];
            let blend = self.next_blend(parity as usize);
            *decay *= 1.0 - blend as f64;
            let seed = (self.rng.next_u64() >> 32) as u32 ^ dir_index as u32;
            let jitter = self.jitter();
            let view = make_view(d, &self.corners, self.params.map_size, jitter, seed, DEPTH_STOCHASTIC);
            let env = self.environment.as_ref().map_or(Vec3::ZERO, |e| e(d));
            let gather = GpuGatherParams {
                env: [env.x, env.y, env.z, blend],
                eps: [EPS_NORMAL_PLANE, EPS_ALONG_D, 0.0, 0.0],
                misc: [
                    (self.params.neighbourhood - 1) / 2,
                    self.params.depth_layers,
                    parity,
                    self.n_texels,
                ],
                texels: [self.receivers.start, self.receivers.len() as u32, 0, 0],
            };
            self.ctx
                .queue
                .write_buffer(&self.view_buf, 0, bytemuck::bytes_of(&view));
            self.ctx
                .queue
                .write_buffer(&self.gather_buf, 0, bytemuck::bytes_of(&gather));
            let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("sdb direction"),
            });
            for layer in 0..self.params.depth_layers {
                self.render_map(&mut encoder, "sdb illumination map", layer);
            }
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("sdb gather"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.gather_pipeline);
                pass.set_bind_group(0, &self.gather_bg, &[]);
                if let Some(bg) = &self.gather_direct_bg {
                    pass.set_bind_group(1, bg, &[]);
                }
                pass.dispatch_workgroups(self.texel_dispatch.0, self.texel_dispatch.1, 1);
            }
            // Uniform writes land before the next submit, so each map that reuses the
            // view buffer goes in its own submission.
            last = Some(self.ctx.queue.submit([encoder.finish()]));

            if let Some(sun) = &self.sun_maps {
                for li in 0..self.lights.len() {
                    let light = self.lights[li];
                    let ld = sample_cone(light.direction, light.cone_half_angle, &mut self.rng);
                    // `jitter()`'s draws, with the maps borrowed.
                    let jitter = (self.rng.next_f64() as f32, self.rng.next_f64() as f32);
                    let view = make_view(ld, &self.corners, self.params.map_size, jitter, 0, DEPTH_NEAREST);
                    let map = ShadowView::ortho_of(&view, [0, 0]);
                    let e = light.irradiance_over_pi;
                    let direct = GpuDirectParams {
                        irradiance: [e.x, e.y, e.z, blend],
                        bias: [SHADOW_OFFSET_PIXELS, 0.0, if li == 0 { 1.0 - blend } else { 1.0 }, 0.0],
                        misc: [parity, self.n_texels, self.receivers.start, self.receivers.len() as u32],
                    };
                    self.ctx.queue.write_buffer(&sun.views_buf, 0, bytemuck::bytes_of(&map));
                    self.ctx
                        .queue
                        .write_buffer(&self.direct_buf, 0, bytemuck::bytes_of(&direct));
                    let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("sdb direct light"),
                    });
                    let n = self.params.map_size;
                    let draw = ShadowDraw {
                        view: 0,
                        tile: [0, 0, n],
                        rows: n,
                    };
                    sun.atlas
                        .render(&mut encoder, &self.vertex_buf, self.vertex_count, [draw]);
                    Self::dispatch(&mut encoder, "sdb direct", &sun.pipeline, &sun.bg, self.texel_dispatch);
                    last = Some(self.ctx.queue.submit([encoder.finish()]));
                }
            }
        }
        last.expect("a slice has at least one direction")
    }

    /// One step: resolve, then `directions_per_step` directions (illumination map and
    /// gather, plus a shadow map and direct pass per directional light), then the small
    /// lights. Submits work and returns without waiting for it; nothing is read back.
    ///
    /// In a bake with a time limit or a watcher (issue 19 point 10) the resolve and the
    /// directions run in slices of whole passes (the resolve, then whole directions), each
    /// waited for (`gpu::slices`,
    /// sized to about 50 ms), with what they write put aside first (the accumulators'
    /// halves of this step's parity; whole buffers on the step that drops the bootstrap
    /// step, which clears them), and the small lights' pass runs sliced when it may be
    /// long. A stop between two slices of either puts back the device's accumulators and
    /// the host's directions, random stream and weights, so the step adds nothing and
    /// the next is the one it would have been.
    pub fn step(&mut self) -> Result<(), GpuError> {
        let parity = (self.steps_done % 2) as u32;
        let before = StepBook {
            directions: self.directions.clone(),
            rng: self.rng.clone(),
            dirs: self.dirs,
            weights: self.weights,
            half_steps: self.half_steps,
        };
        let pairs = self.ambient_factor.is_some();
        let count = (self.params.directions_per_step * if pairs { 2 } else { 1 }) as u64;
        let mut previous = Vec3::Z;
        let mut decay = 1.0f64;
        let watched = self.deadline.is_some() || self.progress.is_some();
        let (deadline, progress) = (self.deadline, self.progress.clone());
        let mut go_on = go_on_until(deadline, progress.as_ref());
        let small = self
            .small_emitters
            .as_ref()
            .is_some_and(|p| p.lights.every_step || self.steps_done < 2);
        let ctx = self.ctx.clone();
        let bootstrap = self.bootstraps();
        // Handles (not borrows): the slices' closure borrows `self` mutably.
        let buffers: Vec<wgpu::Buffer> = self.accumulators().cloned().collect();
        let aside: Vec<Aside<'_>> = buffers
            .iter()
            .map(|b| {
                if bootstrap {
                    Aside::whole(b)
                } else {
                    Aside::half(b, parity as usize)
                }
            })
            .collect();
        if watched {
            // The directions are the step's progress, or its first half with small lights.
            let parts = if small { 2 } else { 1 };
            let mut first_half = |done: u64, of: u64| go_on(done, parts * of);
            let mut slicer = std::mem::replace(&mut self.slicer, StepSlicer::per_unit("sdb directions"));
            // Unit 0 is the resolve (a pass over every lightmap pixel, 0.2 s at 2048² on
            // lavapipe), units 1 ..= count the directions.
            let mut submit = |first: u64, k: u64| {
                let mut last = None;
                if first == 0 {
                    last = Some(self.submit_resolve());
                }
                let directions = (first.max(1) - 1, first + k - first.max(1));
                if directions.1 > 0 {
                    last = Some(self.submit_directions(parity, directions, &mut previous, &mut decay));
                }
                Ok(last.expect("a slice has at least one unit"))
            };
            let done = slicer.run(&ctx, count + 1, &aside, &mut submit, &mut first_half);
            self.slicer = slicer;
            if done? == Sliced::Abandoned {
                self.undo(before);
                return Ok(());
            }
        } else {
            self.submit_resolve();
            if count > 0 {
                self.submit_directions(parity, (0, count), &mut previous, &mut decay);
            }
        }
        if let Some(pass) = &mut self.small_emitters {
            // Point and spot lights alone are the same every step: one step a half.
            if small {
                let mut second_half = |done: u64, of: u64| go_on(of + done, 2 * of);
                let done = pass
                    .lights
                    .light
                    .step_watched(watched.then_some(&mut second_half as &mut dyn FnMut(u64, u64) -> bool))?;
                if done == Sliced::Abandoned {
                    // The directions finished (sliced, so what they wrote is aside).
                    self.slicer.put_back(&ctx, &aside)?;
                    self.undo(before);
                    return Ok(());
                }
            }
            // With directional lights their blends already decayed the mean this step.
            let old = if self.lights.is_empty() { decay } else { 1.0 };
            let params = GpuEmitterAddParams {
                mix: [old as f32, (1.0 - decay) as f32, 0.0, 0.0],
                misc: [parity, self.n_texels, self.receivers.start, self.receivers.len() as u32],
            };
            self.ctx
                .queue
                .write_buffer(&pass.params, 0, bytemuck::bytes_of(&params));
            let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("sdb small emitters"),
            });
            Self::dispatch(
                &mut encoder,
                "sdb small emitters",
                &pass.pipeline,
                &pass.bg,
                self.texel_dispatch,
            );
            self.ctx.queue.submit([encoder.finish()]);
        }
        self.half_steps[parity as usize] += 1;
        self.steps_done += 1;
        self.ctx.take_error("sdb step")
    }

    /// Whether this step drops the bootstrap step ([`SdbEngine::drop_bootstrap_step`]):
    /// step 1 with the ambient-mode correction, unless the accumulators went on from a
    /// round before (their estimate already has the light's shape).
    fn bootstraps(&self) -> bool {
        self.ambient_factor.is_some() && self.steps_done == 1 && !self.starts_lit
    }

    /// Holds every texel outside `receivers` at `held` (E/pi) for the bake's steps and
    /// resumes the receivers' halves from `resume` (`Technique::hold_boundary`, a round
    /// of a bake in rounds, `engine::rounds`). How:
    /// - a held texel's gathered accumulators are (held, 1) in both halves, so the
    ///   resolve's ratio reads `held`, and its fed accumulators (held, 0), so the
    ///   ambient-mode residual there is 0; its light accumulators are zero. The gather,
    ///   the sun's and the small lights' passes run over the receivers only (their
    ///   `texels` range), so nothing writes them; the bootstrap step, whose clear would,
    ///   is skipped when any held light is not zero (in round 0 it all is: cleared, a
    ///   held texel still reads 0).
    /// - a resumed receiver's half is (mean, 1): the half's mean with the weight one
    ///   direction has on average (4 max(<d, n>, 0) over the sphere: 1), so a new
    ///   direction's blend, with the host's weights set to sum i^ramp over the half's
    ///   directions so far, weighs the old mean as one bake's running mean would (up to
    ///   the difference between 1 and the directions' actual mean weight at that texel,
    ///   which stratified directions keep small); its light accumulators start at zero,
    ///   the mean holding their share so far; no bootstrap step.
    /// - the ambient-mode correction is measured over the receivers and added to them
    ///   only (`shaders/sdb/resolve.wgsl`, `receivers`).
    ///
    /// Refused in `leaky` mode, whose blend forgets on purpose (its resumed weights would
    /// mean nothing), and after the first step.
    pub fn hold_boundary(
        &mut self,
        receivers: std::ops::Range<usize>,
        held: &[Vec3],
        resume: Option<(&SdbHalf, &SdbHalf)>,
    ) -> Result<(), String> {
        let n = self.n_texels as usize;
        if self.steps_done > 0 {
            return Err("sdb: a boundary is held from the first step on".into());
        }
        if self.params.mode == AccumulationMode::Leaky {
            return Err(
                "sdb in leaky mode is not baked in rounds (its blend forgets on purpose, so a round cannot resume it); use mode average"
                    .into(),
            );
        }
        if held.len() != n || receivers.start > receivers.end || receivers.end > n {
            return Err(format!(
                "sdb: a boundary of {} held texels and receivers {receivers:?} for {n} texels",
                held.len()
            ));
        }
        let r = receivers.clone();
        let zero = [0.0f32; 4];
        let mut acc = vec![zero; 2 * n];
        let mut fed = vec![zero; 2 * n];
        let mut direct = self.direct_acc_buf.as_ref().map(|_| vec![zero; 2 * n]);
        for h in 0..2 {
            for (i, v) in held.iter().enumerate() {
                if !r.contains(&i) {
                    acc[h * n + i] = v.extend(1.0).to_array();
                    fed[h * n + i] = v.extend(0.0).to_array();
                }
            }
        }
        if let Some((even, odd)) = resume {
            let per_step =
                u64::from(self.params.directions_per_step) * if self.ambient_factor.is_some() { 2 } else { 1 };
            for (h, half) in [even, odd].into_iter().enumerate() {
                if half.total.len() != r.len() || half.direct.is_some() != direct.is_some() {
                    return Err(format!(
                        "sdb: resumed halves of {} texels (direct layer: {}) for {} receivers (direct layer: {})",
                        half.total.len(),
                        half.direct.is_some(),
                        r.len(),
                        direct.is_some()
                    ));
                }
                for (k, v) in half.total.iter().enumerate() {
                    acc[h * n + r.start + k] = v.extend(1.0).to_array();
                    fed[h * n + r.start + k] = v.extend(0.0).to_array();
                }
                if let (Some(d), Some(out)) = (&half.direct, direct.as_mut()) {
                    for (k, v) in d.iter().enumerate() {
                        out[h * n + r.start + k] = v.extend(0.0).to_array();
                    }
                }
                self.half_steps[h] = half.steps;
                self.dirs[h] = half.steps * per_step;
                self.weights[h] = (1..=self.dirs[h])
                    .map(|i| (i as f64).powf(f64::from(self.params.ramp)))
                    .sum();
            }
        }
        self.starts_lit = resume.is_some() || held.iter().any(|v| *v != Vec3::ZERO);
        let q = &self.ctx.queue;
        q.write_buffer(&self.acc_buf, 0, bytemuck::cast_slice(&acc));
        q.write_buffer(&self.fed_acc_buf, 0, bytemuck::cast_slice(&fed));
        if let (Some(b), Some(d)) = (&self.direct_acc_buf, &direct) {
            q.write_buffer(b, 0, bytemuck::cast_slice(d));
        }
        // The light accumulators stay as created, zero: no step has run.
        self.receivers = r.start as u32..r.end as u32;
        self.texel_dispatch = gpu::dispatch_size_64(self.receivers.len() as u32);
        self.ctx.take_error("sdb boundary").map_err(|e| e.to_string())
    }

    /// Runs the first step's resolve once and waits for it, at preparation: the first
    /// resolve of a bake costs seconds more than the others on a large page (1.4 s
    /// against 0.2-0.3 s at 2048² on lavapipe: first use of the lightmap-sized buffers
    /// and of the pass), and a step cannot stop inside one pass. It writes what step 0's
    /// resolve writes again (the resolve reads only the accumulators, still empty), so a
    /// bake's values do not change.
    pub fn warm_up(&mut self) -> Result<(), GpuError> {
        let done = self.submit_resolve();
        self.ctx.wait_for("sdb resolve (warming up)", done)?;
        self.ctx.take_error("sdb resolve (warming up)")
    }

    /// Puts the host's side of a stopped step back (the device's is put back by the
    /// slicer).
    fn undo(&mut self, before: StepBook) {
        tracing::debug!("sdb: the deadline passed or a stop was asked mid-step; the step is undone");
        self.directions = before.directions;
        self.rng = before.rng;
        self.dirs = before.dirs;
        self.weights = before.weights;
        self.half_steps = before.half_steps;
    }

    /// The bake's time limit ([`Technique::set_deadline`]); the next watched step is
    /// timed afresh.
    pub fn set_deadline(&mut self, deadline: Option<std::time::Instant>) {
        self.deadline = deadline;
        self.slicer.forget();
        if let Some(p) = &mut self.small_emitters {
            p.lights.light.forget_step_length();
        }
    }

    /// Where a watched step reports how far it is.
    pub fn set_step_progress(&mut self, progress: StepProgress) {
        self.progress = Some(progress);
        self.slicer.forget();
        if let Some(p) = &mut self.small_emitters {
            p.lights.light.forget_step_length();
        }
    }

    /// Read both halves back (blocks until the GPU is done).
    pub fn read_halves(&self) -> Result<[SdbHalf; 2], GpuError> {
        let n = self.n_texels as usize;
        let acc: Vec<[f32; 4]> = self.ctx.read_buffer("sdb accumulators", &self.acc_buf, 2 * n)?;
        let direct: Option<Vec<[f32; 4]>> = match &self.direct_acc_buf {
            Some(b) => Some(self.ctx.read_buffer("sdb direct accumulators", b, 2 * n)?),
            None => None,
        };
        let sun: Option<Vec<[f32; 4]>> = match &self.sun_acc_buf {
            Some(b) => Some(self.ctx.read_buffer("sdb sun accumulators", b, 2 * n)?),
            None => None,
        };
        let half = |h: usize| {
            // A running mean is already normalised (zero while empty); a leaky blend of the
            // sun needs its start-up correction. Gathered light is a ratio of two blends.
            let sun_scale = match self.params.mode {
                AccumulationMode::Average => 1.0,
                AccumulationMode::Leaky => self.leaky_correction(self.dirs[h]) as f32,
            };
            let range = h * n..(h + 1) * n;
            let sun_at = |k: usize| {
                sun.as_ref()
                    .map_or(Vec3::ZERO, |s| Vec3::from_slice(&s[h * n + k][..3]) * sun_scale)
            };
            let weight = |k: usize| acc[h * n + k][3];
            let over_weight = |v: [f32; 4], k: usize| {
                let w = weight(k);
                if w > 0.0 {
                    Vec3::from_slice(&v[..3]) / w
                } else {
                    Vec3::ZERO
                }
            };
            SdbHalf {
                steps: self.half_steps[h],
                total: acc[range.clone()]
                    .iter()
                    .enumerate()
                    .map(|(k, &a)| over_weight(a, k) + sun_at(k))
                    .collect(),
                direct: direct.as_ref().map(|d| {
                    d[range.clone()]
                        .iter()
                        .enumerate()
                        .map(|(k, &a)| over_weight(a, k) + sun_at(k))
                        .collect()
                }),
            }
        };
        Ok([half(0), half(1)])
    }
}

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
        let params: SdbParams = parse_params("sdb", params)?;
        params.validate().map_err(|e| EngineError::BadInput(e.to_string()))?;
        // One device per process, shared by every sdb bake (`gpu::shared`).
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
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
