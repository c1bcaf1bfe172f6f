//! `hemicube`: stochastic iteration by random hemicube shooting, with glossy transport
//! (`shared/seeds/stochastic-glossy-gi-hemicube-shooting.md`, Barsi, Szirmay-Kalos and
//! Szijártó; docs/hemicube.md has the measurements).
//!
//! # What
//! Multi-bounce light at every valid lightmap texel as incident irradiance / π (DESIGN
//! §2), from emissive surfaces, the sky, the sun and punctual lights, with glossy
//! (Phong-type) reflection at the shooters. Receivers store irradiance, which is what a
//! lightmap holds whatever the BRDF; the lobe only shapes where a shooter's light goes.
//!
//! # How (one step = one iteration of the seed's random transport operator)
//! 1. *Power pyramid* (`shaders/hemicube/pyramid.wgsl`, seed §4.1): level 0 holds, per
//!    lightmap pixel, the luminance of the power the texel reflects, lum(I (k_d + k_s)) A,
//!    from the previous step's irradiance I; `reduce` sums 2 x 2 cells up to one cell,
//!    the total. Sums instead of the seed's averages, so no rescaling while descending.
//! 2. *Shooters* (`shaders/hemicube/select.wgsl`): K_r texel shooters, each drawn by
//!    descending the pyramid with a GPU random number (PCG hash of the step and the
//!    shooter's index), stratified: shooter j draws in the j-th K_r-th of the total power.
//!    At shooter level 0 (the default) the shooter is a uniform point of the texel's
//!    *cell*, the surface the texel stands for (`engine::atlas::cells`), with weight
//!    A / (p K_r), A the cell's area. At level L > 0 it is the seed's merged group (§5):
//!    the texels of the same surface in its 2^L x 2^L block, at their area-weighted
//!    centroid with their mean radiance (below: biased). K_e emitter shooters are drawn on
//!    the CPU, stratified the same way: a triangle by power, a uniform point on it, its
//!    exact emission (textures included). Nothing is read back.
//! 3. *Depth maps* (`shaders/gpu/shadow_atlas.wgsl`, reused): a hemicube per shooter, the top
//!    face and the upper halves of four side faces, `depth_map_size`^2 each, all the
//!    step's shooters in one render pass into tiles of one atlas.
//! 4. *Transfer* (`shaders/hemicube/transfer.wgsl`, seed §4.2.2): every receiver texel
//!    adds, for every shooter it sees, L_s(w) cos_s cos_x / d^2 W (Eq. 4) times the
//!    shooter's near-field weight (below); merged shooters use Eq. 8's disc term,
//!    d^2 + A/π, instead. The sum, plus the CPU's estimate of the sky, sun, punctual light
//!    and the near field, is this step's irradiance I_m, kept for the next step's
//!    pyramid, and I_m / π goes into the half accumulator of the step's parity.
//!
//! ## Unbiased transfer: cells, points and the near field (issue 21)
//! The seed shoots from texel centres with the texel's nominal area and bounds the 1/d^2
//! of nearby receivers with Eq. 8's disc term. Both lose light wherever shooter and
//! receiver are close, i.e. in every crease: the closed box (answer 1) read -4.8 % at
//! 64^2 with ρ = 0.5 and -26 % with ρ = 0.9 after 256 steps, -14 % in the texels next to an
//! edge, because the loss repeats at every bounce. Three changes remove it:
//! - *Cells*: a texel shoots from a uniform point of its cell, the surface its value
//!   stands for (its square clipped to its chart, plus the border squares whose centres
//!   miss the chart), with the cell's exact area. Centres and nominal areas misplace and
//!   miscount light at every chart border.
//! - *No disc*: a point shooter sends cos_s cos_x / d^2 exactly. The expected transfer
//!   over the point is then the exact form factor of the cell, but a receiver next to a
//!   crease sees 1/d^2 spikes (its variance grows as 1/u^2 at distance u from the edge).
//! - *Near field by multiple importance*: each receiver x has a near radius r =
//!   `near_field` x its texel size, and c = 1 / (π r^2). For a pair (x, y) with
//!   G = cos_x cos_y / (π d^2), the shooters keep the weight min(1, c / G) and one CPU
//!   gather ray a texel a step (cosine-distributed, at most r long) takes
//!   max(0, 1 - c / G) of what it hits: π w L(y), L(y) the emission there plus k_d I_{m-1}
//!   of the texel whose cell holds y (`cells::texel_at`; the GPU adds the reflected part,
//!   which only it knows). The weights sum to one for every pair, so the sum is unbiased,
//!   and each part is bounded: a shooter sends at most L W / r^2, a gather ray π L.
//!   The glossy lobe is not gathered (its part of the shooter stays whole).
//!
//! Measured (docs/hemicube.md, 4 seeds, 512 steps): the closed box at 64^2 and 128^2,
//! ρ = 0.5 and 0.9, reads within 1 % of 1 (-0.13 %, -0.23 %, +0.16 %, -0.95 %), and one
//! transfer's bias in the light level is -0.0007 ± 0.0018 (ρ = 0.9, 580 steps).
//! `near_field` trades the edge texels' noise against the light level's: 2 (default)
//! gives a level noise of 0.046 a step at ρ = 0.9, 8 gives 0.071 but a third of the edge
//! texels' noise; 0 (no gather) gives 0.131.
//!
//! ## Why a hemicube
//! Rasterisation keeps straight edges straight only under perspective projection: a
//! single-pass paraboloid or octahedral map bends every edge, so large triangles (a
//! Cornell box wall is two) would be drawn with wrong silhouettes unless the scene were
//! tessellated first. The hemicube costs five draws per shooter instead of one, which is
//! cheap next to the transfer pass for the scenes lightmaps are baked for, and exact.
//! The side faces are drawn with a scissor over their upper half only.
//!
//! ## Visibility
//! Each map pixel stores the *plane* of the nearest surface (as `vpl`'s maps); a receiver
//! is hidden when it and the shooter lie on opposite sides of it by more than a tolerance
//! that grows at grazing angles as the seed's §4.2.1 asks: `grazing_tolerance` times the
//! pixel's footprint on the occluder, d (2 / side) / |cos θ| (|cos θ| ≥ 0.05). A plane
//! test is exact for planar occluders of any thickness; the tolerance only absorbs the
//! facets of tessellated curved surfaces.
//!
//! ## Glossy lobe (Deliver 3)
//! From glTF metallic m and roughness r: roughness 1 is Lambertian with the base colour as
//! albedo (so an all-diffuse scene bakes exactly what the other techniques bake); below 1,
//! k_s = mix(0.04, base, m), k_d = base (1 - m)(1 - 0.04), Phong exponent
//! n = 2 / r^4 - 2 (the Blinn-Phong equivalent of α = r², clamped to [1, 1e5]), and the
//! Neumann-Neumann-Szirmay-Kalos modification of Phong the seed cites,
//! f_s = k_s (n + 1) / (2π) cos^n α / max(cos θ_i, cos θ_o): reciprocal, its directional
//! albedo at most k_s (the unit test integrates it), and a mirror of reflectance
//! k_s (n + 1)/(n + 2) in the limit. The incoming direction of a texel's irradiance is the luminance-weighted mean of
//! the directions it came from in the previous step (exact with one shooter a step, as in
//! the seed; an approximation with several). An all-diffuse scene runs the diffuse-only
//! variant: no lobe data, no direction buffers (the plan says which).
//!
//! ## Progressive estimate (DESIGN §4)
//! The seed's stochastic iteration averages I_m over iterations. Step m's estimate is
//! I_m / π, a random transfer of the previous step's light; the expected value of I_m
//! holds the bounces up to m, so the plain average carries a transient that decays like
//! 1/M. Step i of a half gets weight i^`ramp` (default 1, as `sdb`): the transient then
//! decays like 1/M², for 4/3 the variance. Limits of the error estimate: consecutive
//! steps are correlated through I_{m-1}, so the half difference under-reports the noise
//! (measured in docs/hemicube.md), and the transient is a bias it cannot see.
//!
//! ## Stopping inside a step (issue 19 point 10)
//! The parts of a step that grow with the level are the CPU's rays (three or four a
//! texel) and the transfer (one invocation a texel). In a bake with a time limit or a
//! watcher that may cancel, a step that may be long runs the CPU rays in chunks of
//! [`CPU_LIGHT_CHUNK`] texels, the shooters' depth maps in slices of whole maps (each the
//! whole scene drawn: they grow with the triangles, 8 s a step for a 1M-triangle level on
//! lavapipe) and the transfer in slices of about 50 ms (`gpu::slices`), checking between
//! two. Stopped among the rays or the maps it has written nothing that counts; stopped
//! among the transfer's slices it puts back the accumulators' halves of its parity and
//! its weights, so it adds nothing and the next step is the one it would have been (the
//! irradiance and directions half it wrote is rewritten whole by that next step before
//! anything reads it). The pyramid and the shooters'
//! selection run whole: they grow with the lightmap's pixels, in a few passes.
//!
//! ## Rounds: one region of the grid with the rest held (issue 25)
//! A bake in rounds (`engine::rounds`, block Jacobi over the grid's regions) gives each
//! region's bake a boundary (`Technique::hold_boundary`): both irradiance halves of every
//! texel are set to π times the held light the round before estimated, so the pyramid
//! draws shooters over the whole grid and the near-field gather reads the held light where
//! it lands; the transfer runs over the receivers' texel range only (the transfer's
//! `slice`, as a sliced step's), and so do the CPU rays; the texels outside it are never
//! written, so they keep the held light all bake. The receivers start from the held light
//! too (I_{m-1} is the merged estimate rather than the last iterate: the expected transfer
//! is the same operator applied to a less noisy field) and their accumulators from their
//! halves after the round before, with the weights i^ramp those halves had. The held
//! light of a glossy texel has no incoming direction: its lobe is drawn about its normal
//! (the select pass's fallback for a texel with none).
//!
//! # Departures from the seed
//! - Emitters shoot from their triangles (exact area and emission, CPU-sampled) rather than
//!   from their texels, so a 1 cm² lamp is as exact as a large one; the pyramid holds
//!   reflected power only. They are point shooters with the near-field split, no disc.
//!   The sky, the sun and punctual lights, which are not surfaces,
//!   are estimated on the CPU per texel per step (one cosine-sampled sky ray, one sun-cone
//!   ray, one shadow ray per punctual light) and added to I_m.
//! - Texel shooters are points of the texels' cells, not centres, and the near field is
//!   shared with a gather (above); the disc term stays only for merged shooters.
//! - Texel merging (seed §5, `shooter_level` > 0) is kept as the seed has it, and it is
//!   biased: a group shoots its mean radiance from its centroid with a disc of its area.
//!   Made unbiased (a uniform point of the group, each texel's own radiance) it would be
//!   level-0 shooting with a coarser importance function, so it could not lower the noise;
//!   the variance it saves in the seed is the smoothing that is its bias. Measured in
//!   docs/hemicube.md; the default is level 0.
//! - Several shooters per step (`shooters_per_step`, half of them emitter samples when the
//!   scene has emitters), all rendered in one pass and transferred in one dispatch.
//! - Plane-side visibility (above) instead of depth difference; a merged shooter's group
//!   is checked by mesh, material, normal and distance (the seed used a patch-id texture).
//! - Two half accumulators with weights i^ramp instead of one running mean.
//!
//! # Limits
//! - Double-sided surfaces receive and shoot from their front face only (a lightmap
//!   stores one side).
//! - A texel's glossy reflection uses one mean incoming direction per step.
//! - Stiff scenes (albedo near 1, closed): the iteration adds one bounce a step, so a
//!   closed box of albedo ρ needs many times 1/(1 - ρ) steps (docs/stability.md), and the
//!   light level's noise is carried on with gain ρ: the mean of M steps has a level noise
//!   of about σ / ((1 - ρ) sqrt(M)), σ the step's (0.043 at ρ = 0.9, 64^2).
//! - The near-field gather is one CPU ray per texel a step (short: at most `near_field`
//!   texels long), beside the sky/sun pass's.
//! - Memory: per texel 3 to 7 vec4 (irradiance, directions, accumulators), 2 more for the
//!   near-field gather, and 48 bytes a cell piece (about one a texel, more at chart
//!   borders and on meshes finer than their texels); the depth atlas
//!   is 6 `depth_map_size`^2 Rgba32Float + depth texels per shooter. Both are checked
//!   against the device's limits with a bad-input error naming the parameters.
//!
//! Randomness: GPU PCG hash (`shaders/gpu/common.wgsl`) of the step's CPU-drawn hash and the
//! shooter's index for the pyramid descent, and three more chained PCG draws for the
//! point of the cell; CPU `engine::rng` streams keyed by (seed, step, index) for emitter
//! samples and by (seed, step, the texel's pixel) for the direct light and the near-field
//! gather, so a bake is reproducible from its seed and a texel's rays do not depend on
//! which other texels its set holds (a region's round-0 set in `engine::rounds`).
//! Precision: f32 everywhere; geometry in normalised scene space (p - centre) / radius
//! and areas divided by radius², so scaled and translated scenes bake the same.

use std::f32::consts::PI;
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::api::{
    AlphaSupport, BakeInputs, Boundary, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry,
    go_on_until, gpu_error, parse_params,
};
use crate::engine::accumulate::{LUMINANCE, Snapshot};
use crate::engine::atlas::Atlas;
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::halves::read_halves;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_at, group_of, layout_at, layout_of};
use crate::engine::gpu::shadow::{AtlasVertices, ShadowAtlas, ShadowDraw, ShadowView, shadow_vertices};
use crate::engine::gpu::slices::{Aside, Sliced, StepSlicer};
use crate::engine::gpu::texels::GpuTexelGeom;
use crate::engine::gpu::{self, GpuContext};
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};
use crate::engine::raytrace::{Tracer, cone_sample, cosine_sample};
use crate::engine::rng::Rng;
use crate::engine::scene::{LightKind, Lighting, Material, Scene};

// ---------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------

/// `hemicube` parameters (the job's `params` object). Unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HemicubeParams {
    /// Side of each hemicube face in pixels. Range 16..=2048; default 256 (the seed's).
    pub depth_map_size: u32,
    /// Pyramid level shooters are merged at: a shooter is the same-surface part of a
    /// 2^L x 2^L block of texels (seed §5). Range 0..=4; default 0: merging lowers the
    /// noise but its larger disc (Eq. 8) darkens corners, and on the Cornell box up to
    /// 64^2 the bias outweighed the noise it saved (docs/hemicube.md).
    pub shooter_level: u32,
    /// Shooters per step (each its own hemicube). Range 1..=64; default 8. With emitters
    /// in the scene, half of them (rounded up) are emitter samples.
    pub shooters_per_step: u32,
    /// Step i of a half gets weight i^ramp in the mean. Range 0..=4; default 1.
    pub ramp: f32,
    /// Visibility tolerance in pixel footprints on the occluder (grows as 1/cos at
    /// grazing angles). Range 0..=2; default 0.1.
    pub grazing_tolerance: f32,
    /// Radius of each receiver's near field in its own texel sizes: light from surface
    /// this close is shared between the shooters and one CPU gather ray a texel a step
    /// by multiple importance (module doc). Range 0..=16; default 2; 0 shoots everything
    /// (unbiased, but texels next to a crease see the shooters' 1/d^2 spikes).
    pub near_field: f32,
}

impl Default for HemicubeParams {
    fn default() -> Self {
        HemicubeParams {
            depth_map_size: 256,
            shooter_level: 0,
            shooters_per_step: 8,
            ramp: 1.0,
            grazing_tolerance: 0.1,
            near_field: 2.0,
        }
    }
}

impl HemicubeParams {
    pub fn validate(&self) -> Result<(), EngineError> {
        let bad = |name: &str, v: String, range: &str| {
            Err(EngineError::BadInput(format!(
                "hemicube: params.{name} must be in {range}, got {v}"
            )))
        };
        if !(16..=2048).contains(&self.depth_map_size) {
            return bad("depth_map_size", self.depth_map_size.to_string(), "16..=2048");
        }
        if self.shooter_level > 4 {
            return bad("shooter_level", self.shooter_level.to_string(), "0..=4");
        }
        if !(1..=64).contains(&self.shooters_per_step) {
            return bad("shooters_per_step", self.shooters_per_step.to_string(), "1..=64");
        }
        if !(0.0..=4.0).contains(&self.ramp) {
            return bad("ramp", self.ramp.to_string(), "0..=4");
        }
        if !(0.0..=2.0).contains(&self.grazing_tolerance) {
            return bad("grazing_tolerance", self.grazing_tolerance.to_string(), "0..=2");
        }
        if !(0.0..=16.0).contains(&self.near_field) {
            return bad("near_field", self.near_field.to_string(), "0..=16");
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// The lobe
// ---------------------------------------------------------------------------------------

/// The hemicube lobe of a material at a texel of diffuse colour `base`: (k_d, k_s,
/// exponent). See the module doc; roughness 1 is Lambertian with albedo `base`.
pub fn lobe(material: &Material, base: Vec3) -> (Vec3, Vec3, f32) {
    let r = material.roughness.clamp(0.0, 1.0);
    if r >= 1.0 {
        return (base, Vec3::ZERO, 0.0);
    }
    let m = material.metallic.clamp(0.0, 1.0);
    let ks = Vec3::splat(0.04).lerp(base, m);
    let kd = base * ((1.0 - m) * (1.0 - 0.04));
    let exponent = (2.0 / r.powi(4).max(1e-12) - 2.0).clamp(1.0, 1e5);
    (kd, ks, exponent)
}

// ---------------------------------------------------------------------------------------
// GPU layouts: the structs of shaders/hemicube/common.wgsl, sizes checked against naga's
// layout (`gpu_layouts_match_the_shaders`)
// ---------------------------------------------------------------------------------------

const HC_GLOSSY: u32 = 1;
const HC_DIRECT: u32 = 2;
const HC_CPU_LIGHT: u32 = 4;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuParams {
    dims: [u32; 4],
    shoot: [u32; 4],
    step: [u32; 4],
    f: [f32; 4],
    /// The transfer dispatch's first texel and texel count (a sliced step, `gpu::slices`).
    slice: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuTexelMat {
    kd: [f32; 4],
    ks: [f32; 4],
    ids: [u32; 4],
}

/// `NearSample` of hemicube/common.wgsl: a receiver's near-field gather of one step.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuNear {
    gain: [f32; 4],
    /// Unit direction to the hit.
    dir: [f32; 3],
    /// The hit texel (`NO_NEAR`: none).
    hit: u32,
}

const NO_NEAR: u32 = u32::MAX;

impl GpuNear {
    const NONE: GpuNear = GpuNear {
        gain: [0.0; 4],
        dir: [0.0; 3],
        hit: NO_NEAR,
    };
}

/// `CellPiece` of hemicube/common.wgsl: one triangle of a texel's cell.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuCellPiece {
    a: [f32; 4],
    e1: [f32; 4],
    e2: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuShooter {
    pos: [f32; 4],
    nrm: [f32; 4],
    diffuse: [f32; 4],
    spec: [f32; 4],
    in_dir: [f32; 4],
    frame_t: [f32; 4],
    frame_b: [f32; 4],
}

fn v4(v: Vec3, w: f32) -> [f32; 4] {
    [v.x, v.y, v.z, w]
}

fn lum(v: Vec3) -> f32 {
    v.dot(LUMINANCE)
}

/// An emissive triangle as the CPU samples it.
#[derive(Debug, Clone, Copy)]
struct Emitter {
    triangle: u32,
    /// Luminance power over π (lum(Le) A, both faces of a double-sided one).
    weight: f64,
}

pub struct Hemicube {
    ctx: Arc<GpuContext>,
    params: HemicubeParams,
    scene: Arc<Scene>,
    atlas: Arc<Atlas>,
    lighting: Lighting,
    seed: u64,
    flags: u32,
    centre: Vec3,
    radius: f32,
    tracer: Option<Arc<Tracer>>,
    /// Per texel: the k_d its shooters reflect with (the near-field gather's gain).
    texel_albedo: Vec<Vec3>,
    emitters: Vec<Emitter>,
    emitter_cdf: Vec<f64>,
    k_emit: u32,
    k_texel: u32,
    steps_done: u64,
    half_steps: [u64; 2],
    half_weight: [f64; 2],
    n_texels: u32,
    pyr_side: u32,
    top_level: u32,
    /// Per shooter and face: the tile's (x, y, side).
    tiles: Vec<[u32; 4]>,
    vertex_count: u32,

    params_buf: wgpu::Buffer,
    emitters_buf: wgpu::Buffer,
    cpu_light_buf: wgpu::Buffer,
    near_buf: wgpu::Buffer,
    pyramid_buf: wgpu::Buffer,
    /// Two steps' irradiance (the one a step writes, the one before it that it reads).
    irr_buf: wgpu::Buffer,
    acc_buf: wgpu::Buffer,
    direct_acc_buf: wgpu::Buffer,
    vertex_buf: wgpu::Buffer,
    shadow: ShadowAtlas,
    power_pipeline: wgpu::ComputePipeline,
    power_bg: wgpu::BindGroup,
    reduce_pipeline: wgpu::ComputePipeline,
    reduce_bgs: Vec<(wgpu::BindGroup, u32)>,
    select_pipeline: wgpu::ComputePipeline,
    select_bg: wgpu::BindGroup,
    transfer_pipeline: wgpu::ComputePipeline,
    transfer_bg: wgpu::BindGroup,
    /// The bake's time limit and watcher (issue 19 point 10): a step that may be long
    /// checks them between chunks of its CPU rays and between slices of its transfer,
    /// and is undone when either says stop.
    deadline: Option<std::time::Instant>,
    progress: Option<StepProgress>,
    slicer: StepSlicer,
    /// The depth maps' slices (whole maps) in a sliced step.
    map_slicer: StepSlicer,
    /// The texels that receive light: all of them, or one page's in a bake in rounds
    /// (`Technique::hold_boundary`; the others keep the irradiance they were given).
    receivers: std::ops::Range<usize>,
}

/// Texels per chunk of the CPU rays of a watched step (a check of the deadline between
/// two): about 20 ms on two cores at three or four rays a texel.
const CPU_LIGHT_CHUNK: usize = 16_384;

impl Hemicube {
    pub fn prepare(inputs: BakeInputs, params: &serde_json::Value) -> Result<Self, EngineError> {
        let params: HemicubeParams = parse_params("hemicube", params)?;
        params.validate()?;
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
        let scene = inputs.scene.clone();
        let atlas = inputs.atlas.clone();
        let lighting = inputs.lighting;
        let plan = &inputs.plan;
        let glossy = plan.runs(GLOSSY_PASS);
        let cpu_light = plan.runs(CPU_LIGHT_PASS);
        let mut flags = 0;
        if glossy {
            flags |= HC_GLOSSY;
        }
        if inputs.want_direct {
            flags |= HC_DIRECT;
        }
        // The near-field gather rides on the CPU pass, so with it the pass always runs.
        let near_field = params.near_field > 0.0;
        if cpu_light || near_field {
            flags |= HC_CPU_LIGHT;
        }

        // Normalised space: the bounds of triangles and texel points together.
        let frame = SceneFrame::of(&scene, &atlas);
        let (centre, radius) = (frame.centre, frame.radius);
        let area_scale = 1.0 / (radius * radius);

        // Emitters, sampled on the CPU by power.
        let emitters: Vec<Emitter> = scene
            .triangles
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let m = scene.material(t);
                let sides = if m.double_sided { 2.0 } else { 1.0 };
                // Textured emitters: the factor bounds the texture (glTF multiplies them),
                // and any positive weight keeps the estimator unbiased.
                let w = lum(m.emissive).max(m.emissive.max_element() * 1e-3) as f64 * t.area() as f64 * sides;
                (w > 0.0 && w.is_finite()).then_some(Emitter {
                    triangle: i as u32,
                    weight: w,
                })
            })
            .collect();
        let total: f64 = emitters.iter().map(|e| e.weight).sum();
        let emitter_cdf: Vec<f64> = emitters
            .iter()
            .scan(0.0, |acc, e| {
                *acc += e.weight / total;
                Some(*acc)
            })
            .collect();
        let k = params.shooters_per_step;
        // With one shooter a step and emitters, each step tosses a coin between the kinds
        // (`run_step`); otherwise half the shooters (rounded up) are emitter samples.
        let k_emit = match (emitters.is_empty(), k) {
            (true, _) => 0,
            (false, 1) => 1,
            (false, k) => k.div_ceil(2),
        };
        let k_texel = if k == 1 { 1 } else { k - k_emit };
        let shooters = k;

        // GPU resources.
        let n_texels = atlas.texels.len() as u32;
        let max_binding = ctx.limits.max_storage_buffer_binding_size;
        let need = 2 * n_texels.max(1) as u64 * 16;
        ctx.check_storage(&format!("hemicube: the per-texel buffers of {n_texels} texels"), need)
            .map_err(gpu_error)?;
        let pyr_side = atlas.width.max(atlas.height).max(1).next_power_of_two();
        let top_level = pyr_side.trailing_zeros();
        let pyramid_len: u64 = (0..=top_level).map(|l| ((pyr_side >> l) as u64).pow(2)).sum();
        if pyramid_len * 4 > max_binding {
            return Err(EngineError::BadInput(format!(
                "hemicube: a {}x{} lightmap needs a {}-byte power pyramid; the device allows {max_binding}",
                atlas.width,
                atlas.height,
                pyramid_len * 4
            )));
        }
        // Depth atlas: per shooter a 3N x 2N block (top face and four side faces).
        let n = params.depth_map_size;
        let max_dim = ctx.limits.max_texture_dimension_2d;
        let cols = (max_dim / (3 * n)).min(shooters).max(1);
        let rows = shooters.div_ceil(cols);
        let (atlas_w, atlas_h) = (cols * 3 * n, rows * 2 * n);
        if atlas_w > max_dim || atlas_h > max_dim {
            return Err(EngineError::BadInput(format!(
                "hemicube: {shooters} shooters with depth_map_size {n} need a {atlas_w}x{atlas_h} depth atlas; \
                 the device allows {max_dim}: lower params.depth_map_size or params.shooters_per_step"
            )));
        }
        let mut tiles = Vec::with_capacity(5 * shooters as usize);
        for s in 0..shooters {
            let (bx, by) = ((s % cols) * 3 * n, (s / cols) * 2 * n);
            for (fx, fy) in [(0, 0), (1, 0), (2, 0), (0, 1), (1, 1)] {
                tiles.push([bx + fx * n, by + fy * n, n, 0]);
            }
        }

        use wgpu::BufferUsages as U;
        // position.w: the receiver's near-field radius (normalised units; 0: none).
        let geom: Vec<GpuTexelGeom> = atlas
            .texels
            .iter()
            .map(|t| {
                let mut g = GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal);
                g.position[3] = params.near_field * t.size / radius;
                g
            })
            .collect();
        // The surface each texel stands for: texel shooters are points of it.
        let cells = crate::engine::atlas::cells::cells(&scene, &atlas);
        if cells.lost_area > 0.0 {
            tracing::debug!(
                lost_area = cells.lost_area,
                "hemicube: surface outside every texel's cell does not shoot"
            );
        }
        let pieces: Vec<GpuCellPiece> = cells
            .pieces
            .iter()
            .map(|p| {
                let a = (p.p[0] - centre) / radius;
                GpuCellPiece {
                    a: v4(a, p.area * area_scale),
                    e1: v4((p.p[1] - p.p[0]) / radius, 0.0),
                    e2: v4((p.p[2] - p.p[0]) / radius, 0.0),
                }
            })
            .collect();
        ctx.check_storage(
            &format!("hemicube: the {} cell pieces of {n_texels} texels", pieces.len()),
            (pieces.len() * std::mem::size_of::<GpuCellPiece>()) as u64,
        )
        .map_err(gpu_error)?;
        let mats: Vec<GpuTexelMat> = atlas
            .texels
            .iter()
            .enumerate()
            .map(|(k, t)| {
                let tri = &scene.triangles[t.triangle as usize];
                let (kd, ks, e) = if glossy {
                    lobe(scene.material(tri), t.albedo)
                } else {
                    (t.albedo, Vec3::ZERO, 0.0)
                };
                GpuTexelMat {
                    kd: v4(kd, cells.area[k] * area_scale),
                    ks: v4(ks, e),
                    ids: [t.mesh, tri.material, t.pixel, cells.first[k]],
                }
            })
            .collect();
        let geom_buf = ctx.buffer_init("hemicube texel geometry", &geom, U::STORAGE);
        let mats_buf = ctx.buffer_init("hemicube texel lobes", &mats, U::STORAGE);
        // Hemicube bakes the whole grid (its tasks are chains, never regions).
        let whole = atlas
            .pixel_texel
            .whole(atlas.width as usize * atlas.height as usize)
            .ok_or_else(|| EngineError::Internal("hemicube needs the whole grid's texels, not a region's".into()))?;
        let pixel_texel_buf = ctx.buffer_init("hemicube pixel to texel", whole, U::STORAGE);
        let pieces_buf = ctx.buffer_init("hemicube texel cells", &pieces, U::STORAGE);
        let texel_bytes = 2 * n_texels as u64 * 16;
        // COPY_DST: a page of a bake in rounds starts from held irradiance (`hold_boundary`).
        let irr_buf = ctx.buffer_zeroed("hemicube irradiance (two steps)", texel_bytes, U::STORAGE | U::COPY_DST);
        let dirs_buf = ctx.buffer_zeroed(
            "hemicube incoming directions (two steps)",
            if glossy { texel_bytes } else { 16 },
            U::STORAGE,
        );
        let cpu_light_buf = ctx.buffer_zeroed(
            "hemicube sky/sun/punctual estimate",
            if flags & HC_CPU_LIGHT != 0 { texel_bytes } else { 16 },
            U::STORAGE | U::COPY_DST,
        );
        let near_buf = ctx.buffer_init(
            "hemicube near-field gather",
            &vec![GpuNear::NONE; n_texels.max(1) as usize],
            U::STORAGE | U::COPY_DST,
        );
        let acc_buf = ctx.buffer_zeroed(
            "hemicube accumulators (even, odd)",
            texel_bytes,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let direct_acc_buf = ctx.buffer_zeroed(
            "hemicube direct accumulators (even, odd)",
            if inputs.want_direct { texel_bytes } else { 16 },
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let pyramid_buf = ctx.buffer_zeroed("hemicube power pyramid", pyramid_len * 4, U::STORAGE | U::COPY_DST);
        let params_buf = ctx.uniform("hemicube step params", &GpuParams::zeroed());
        let shooter_size = std::mem::size_of::<GpuShooter>() as u64;
        let emitters_buf = ctx.buffer_zeroed(
            "hemicube emitter samples",
            k_emit.max(1) as u64 * shooter_size,
            U::STORAGE | U::COPY_DST,
        );
        let shooters_buf = ctx.buffer_zeroed("hemicube shooters", shooters as u64 * shooter_size, U::STORAGE);
        let views_buf = ctx.buffer_zeroed(
            "hemicube views",
            5 * shooters as u64 * std::mem::size_of::<ShadowView>() as u64,
            U::STORAGE,
        );
        let tiles_buf = ctx.buffer_init("hemicube depth tiles", &tiles, U::STORAGE);
        // Per corner: position, the triangle's plane and its alpha inputs (gpu::shadow).
        let vertices = shadow_vertices(&scene, &frame);
        let vertex_buf = ctx.buffer_init("hemicube vertices (normalised, with planes)", &vertices, U::VERTEX);

        use wgpu::ShaderStages as S;
        // Pyramid.
        let pyr_module = ctx.shader(&shaders::HEMICUBE_PYRAMID).map_err(gpu_error)?;
        let power_binds = [
            Bind::Uniform(&params_buf),
            Bind::Read(&mats_buf),
            Bind::Read(&irr_buf),
            Bind::Write(&pyramid_buf),
        ];
        let power_layout = layout_of(&ctx, "hemicube power layout", S::COMPUTE, &power_binds);
        let power_pipeline = compute_pipeline(&ctx, "hemicube power", &pyr_module, "power", &power_layout);
        let power_bg = group_of(&ctx, "hemicube power bindings", &power_layout, &power_binds);
        // Bindings 3 and 4 of hemicube/pyramid.wgsl (0..2 belong to its `power` entry point).
        let reduce_layout = layout_at(
            &ctx,
            "hemicube reduce layout",
            3,
            S::COMPUTE,
            &[Bind::Write(&pyramid_buf), Bind::Uniform(&params_buf)],
        );
        let reduce_pipeline = compute_pipeline(&ctx, "hemicube reduce", &pyr_module, "reduce", &reduce_layout);
        let level_offset = |l: u32| -> u32 { (0..l).map(|k| (pyr_side >> k) * (pyr_side >> k)).sum() };
        let reduce_bgs: Vec<(wgpu::BindGroup, u32)> = (1..=top_level)
            .map(|l| {
                let side = pyr_side >> l;
                let buf = ctx.uniform(
                    &format!("hemicube pyramid level {l}"),
                    &[side, level_offset(l - 1), level_offset(l), 0u32],
                );
                let bg = group_at(
                    &ctx,
                    &format!("hemicube reduce level {l}"),
                    &reduce_layout,
                    3,
                    &[Bind::Write(&pyramid_buf), Bind::Uniform(&buf)],
                );
                (bg, side * side)
            })
            .collect();
        // Shooter selection.
        let select_module = ctx.shader(&shaders::HEMICUBE_SELECT).map_err(gpu_error)?;
        let select_binds = [
            Bind::Uniform(&params_buf),
            Bind::Read(&mats_buf),
            Bind::Read(&irr_buf),
            Bind::Read(&dirs_buf),
            Bind::Read(&pyramid_buf),
            Bind::Read(&pixel_texel_buf),
            Bind::Read(&geom_buf),
            Bind::Read(&emitters_buf),
            Bind::Write(&shooters_buf),
            Bind::Write(&views_buf),
            Bind::Read(&tiles_buf),
            Bind::Read(&pieces_buf),
        ];
        let select_layout = layout_of(&ctx, "hemicube select layout", S::COMPUTE, &select_binds);
        let select_pipeline = compute_pipeline(
            &ctx,
            "hemicube select",
            &select_module,
            "select_shooters",
            &select_layout,
        );
        let select_bg = group_of(&ctx, "hemicube select bindings", &select_layout, &select_binds);
        // Depth maps: the shared shadow atlas (gpu::shadow), views from the select pass.
        let tables = inputs
            .rays
            .gpu_tables(&ctx, "hemicube", &inputs.rays.emitters())
            .map_err(gpu_error)?;
        let shadow = ShadowAtlas::new(
            &ctx,
            "hemicube depth",
            atlas_w,
            atlas_h,
            &views_buf,
            &tables.tables,
            AtlasVertices::Planes,
        )
        .map_err(gpu_error)?;
        // Transfer and accumulation.
        let transfer_module = ctx.shader(&shaders::HEMICUBE_TRANSFER).map_err(gpu_error)?;
        let transfer_binds = [
            Bind::Uniform(&params_buf),
            Bind::Read(&geom_buf),
            Bind::Write(&irr_buf),
            Bind::Write(&dirs_buf),
            Bind::Read(&cpu_light_buf),
            Bind::Read(&shooters_buf),
            // textureLoad only: Rgba32Float needs no filtering.
            Bind::Texture2d(&shadow.plane_view),
            Bind::Write(&acc_buf),
            Bind::Write(&direct_acc_buf),
            Bind::Read(&tiles_buf),
            Bind::Read(&near_buf),
        ];
        let transfer_layout = layout_of(&ctx, "hemicube transfer layout", S::COMPUTE, &transfer_binds);
        let transfer_pipeline = compute_pipeline(
            &ctx,
            "hemicube transfer",
            &transfer_module,
            "transfer",
            &transfer_layout,
        );
        let transfer_bg = group_of(&ctx, "hemicube transfer bindings", &transfer_layout, &transfer_binds);
        ctx.take_error("hemicube setup").map_err(gpu_error)?;

        let tracer = (flags & HC_CPU_LIGHT != 0).then(|| inputs.rays.tracer());
        let texel_albedo: Vec<Vec3> = mats.iter().map(|m| Vec3::from_slice(&m.kd[..3])).collect();
        Ok(Hemicube {
            ctx,
            params,
            scene,
            atlas,
            lighting,
            seed: inputs.seed,
            flags,
            centre,
            radius,
            tracer,
            texel_albedo,
            emitters,
            emitter_cdf,
            k_emit,
            k_texel,
            steps_done: 0,
            half_steps: [0, 0],
            half_weight: [0.0, 0.0],
            n_texels,
            pyr_side,
            top_level,
            tiles,
            vertex_count: vertices.len() as u32,
            params_buf,
            emitters_buf,
            cpu_light_buf,
            near_buf,
            pyramid_buf,
            irr_buf,
            acc_buf,
            direct_acc_buf,
            vertex_buf,
            shadow,
            power_pipeline,
            power_bg,
            reduce_pipeline,
            reduce_bgs,
            select_pipeline,
            select_bg,
            transfer_pipeline,
            transfer_bg,
            deadline: None,
            progress: None,
            slicer: StepSlicer::new("hemicube transfer"),
            map_slicer: StepSlicer::per_unit("hemicube depth maps"),
            receivers: 0..n_texels as usize,
        })
    }

    fn norm(&self, p: Vec3) -> Vec3 {
        (p - self.centre) / self.radius
    }

    /// The step's emitter shooters: a triangle by power, a uniform point, its emission.
    /// `count` of them, each weighted 1 / `share` (the expected number of emitter samples
    /// a step).
    fn emitter_samples(&self, step: u64, count: u32, share: f64) -> Vec<GpuShooter> {
        let scene = &self.scene;
        let r2 = self.radius * self.radius;
        (0..count)
            .map(|k| {
                let mut rng = Rng::new(self.seed, 0x4E17_0E11, step, k as u64);
                // Stratified over the power: sample k of `count` in the k-th stratum.
                let u = (k as f64 + rng.next_f32() as f64) / count as f64;
                let j = self
                    .emitter_cdf
                    .partition_point(|&c| c <= u)
                    .min(self.emitters.len() - 1);
                let e = self.emitters[j];
                let p_tri = e.weight / self.emitters.iter().map(|e| e.weight).sum::<f64>();
                let tri = &scene.triangles[e.triangle as usize];
                let material = scene.material(tri);
                let (mut b1, mut b2) = (rng.next_f32(), rng.next_f32());
                if b1 + b2 > 1.0 {
                    b1 = 1.0 - b1;
                    b2 = 1.0 - b2;
                }
                let bary = Vec3::new(1.0 - b1 - b2, b1, b2);
                let mut normal = tri.geometric_normal();
                let mut sides = 1.0;
                if material.double_sided {
                    sides = 2.0;
                    if rng.next_f32() < 0.5 {
                        normal = -normal;
                    }
                }
                let p = tri.point(bary) + normal * self.atlas.surface_offset;
                let weight = (tri.area() as f64 * sides / (p_tri * share)) as f32 / r2;
                // No disc (w = 0): the point is exact, and the near-field split bounds it.
                GpuShooter {
                    pos: v4(self.norm(p), 0.0),
                    nrm: v4(normal, weight),
                    diffuse: v4(scene.emission(tri, bary), 1.0),
                    spec: [0.0; 4],
                    in_dir: v4(normal, 0.0),
                    frame_t: [0.0; 4],
                    frame_b: [0.0; 4],
                }
            })
            .collect()
    }

    /// Per receiver, one-sample irradiance estimates of the sky, the sun, punctual lights
    /// and the emission of the near field (first R entries: rgb), their luminance-weighted
    /// direction sums (next R), and the near-field gather of reflected light; R the
    /// receivers (every texel but in a bake in rounds).
    ///
    /// With `go_on` (a watched step), texels go in chunks of [`CPU_LIGHT_CHUNK`] and
    /// `go_on(done, of)` is asked between two; None when it says stop (nothing is kept:
    /// every texel's rays are keyed by step and texel, so the step redone draws the same).
    #[allow(clippy::type_complexity)]
    fn cpu_light(
        &self,
        step: u64,
        go_on: Option<&mut dyn FnMut(u64, u64) -> bool>,
    ) -> Option<(Vec<[f32; 4]>, Vec<GpuNear>)> {
        let Some(tracer) = &self.tracer else {
            return Some((Vec::new(), Vec::new()));
        };
        let scene = &self.scene;
        let lighting = &self.lighting;
        let seed = self.seed;
        let receivers = self.receivers.clone();
        let texels = &self.atlas.texels[receivers.clone()];
        let n = texels.len();
        let chunk = if go_on.is_some() { CPU_LIGHT_CHUNK } else { n.max(1) };
        let mut go_on = go_on;
        let mut per: Vec<(Vec3, Vec3, GpuNear)> = Vec::with_capacity(n);
        for first in (0..n).step_by(chunk) {
            if first > 0
                && let Some(go_on) = go_on.as_mut()
                && !go_on(first as u64, n as u64)
            {
                return None;
            }
            let end = (first + chunk).min(n);
            per.par_extend(texels[first..end].par_iter().map(|t| {
                // Keyed by the texel's pixel, not its index: a texel draws the same
                // stream whichever texels the set around it holds (a region's bake in
                // rounds, whose round 0 keeps other regions' texels untested).
                let mut rng = Rng::new(seed, 0xC9_11_6E, step, u64::from(t.pixel));
                let (x, n, ng) = (t.position, t.normal, t.geo_normal);
                let front = |d: Vec3| d.dot(n) > 0.0 && d.dot(ng) > 0.0;
                let (mut sum, mut dir) = (Vec3::ZERO, Vec3::ZERO);
                let mut add = |c: Vec3, d: Vec3| {
                    sum += c;
                    dir += d * lum(c);
                };
                if lighting.sky.is_some() {
                    // Cosine sampling: E = π L is the irradiance estimate.
                    let d = cosine_sample(n, rng.next_f32(), rng.next_f32());
                    let l = lighting.sky_radiance(d);
                    if l != Vec3::ZERO && d.dot(ng) > 0.0 && tracer.unoccluded(scene, x, d, f32::INFINITY) {
                        add(l * PI, d);
                    }
                }
                if let Some(sun) = &lighting.sun {
                    let axis = -sun.direction.normalize();
                    let d = cone_sample(axis, sun.cos_half_angle(), rng.next_f32(), rng.next_f32());
                    if front(d) && tracer.unoccluded(scene, x, d, f32::INFINITY) {
                        add(sun.radiance * (d.dot(n) * sun.solid_angle()), d);
                    }
                }
                for light in &scene.lights {
                    match light.kind {
                        LightKind::Directional => {
                            let d = -light.direction;
                            if front(d) && tracer.unoccluded(scene, x, d, f32::INFINITY) {
                                add(light.intensity * d.dot(n), d);
                            }
                        }
                        LightKind::Point | LightKind::Spot { .. } => {
                            let to = light.position - x;
                            let dist2 = to.length_squared();
                            if dist2 <= 0.0 {
                                continue;
                            }
                            let dist = dist2.sqrt();
                            let d = to / dist;
                            if !front(d) {
                                continue;
                            }
                            // The same falloff and cone as `path` (KHR_lights_punctual).
                            let mut falloff = 1.0 / dist2;
                            if let Some(range) = light.range {
                                falloff *= (1.0 - (dist / range).powi(4)).clamp(0.0, 1.0).powi(2);
                            }
                            if let LightKind::Spot { inner_cone, outer_cone } = light.kind {
                                let cd = (-d).dot(light.direction);
                                let scale = 1.0 / (inner_cone.cos() - outer_cone.cos()).max(1e-3);
                                let a = ((cd - outer_cone.cos()) * scale).clamp(0.0, 1.0);
                                falloff *= a * a;
                            }
                            if falloff > 0.0 && tracer.unoccluded(scene, x, d, dist * (1.0 - 1e-4)) {
                                add(light.intensity * (falloff * d.dot(n)), d);
                            }
                        }
                    }
                }
                let near = self.near_field(tracer, t, step, &mut add);
                (sum, dir, near)
            }));
        }
        let light = per
            .iter()
            .map(|(s, _, _)| v4(*s, 0.0))
            .chain(per.iter().map(|(_, d, _)| v4(*d, 0.0)))
            .collect();
        Some((light, per.into_iter().map(|(_, _, n)| n).collect()))
    }

    /// The near-field gather at texel `t`, its stream keyed by the texel's pixel
    /// (module doc, "Unbiased transfer"): one cosine ray to the near radius r. A hit at
    /// distance t with cosines cos_x, cos_y takes the MIS weight w = max(0, 1 - t^2 /
    /// (cos_x cos_y r^2)), the part of G = cos_x cos_y / (π t^2) above c = 1 / (π r^2);
    /// the shooters keep min(1, c / G) of the same pair. Emission found there is added
    /// through `add` (π Le w, direct light); reflected light is left to the GPU, which
    /// knows the hit texel's irradiance: the returned gain is w k_d.
    fn near_field(
        &self,
        tracer: &Tracer,
        t: &crate::engine::atlas::Texel,
        step: u64,
        add: &mut impl FnMut(Vec3, Vec3),
    ) -> GpuNear {
        let r = self.params.near_field * t.size;
        if !(r > 0.0) {
            return GpuNear::NONE;
        }
        let scene = &self.scene;
        let mut rng = Rng::new(self.seed, 0x4EA2_F1E1, step, u64::from(t.pixel));
        let (x, n, ng) = (t.position, t.normal, t.geo_normal);
        let d = cosine_sample(n, rng.next_f32(), rng.next_f32());
        let cos_x = d.dot(n);
        if d.dot(ng) <= 0.0 || cos_x <= 0.0 {
            return GpuNear::NONE;
        }
        let Some(hit) = tracer.trace(scene, x, d, r) else {
            return GpuNear::NONE;
        };
        let tri = &scene.triangles[hit.triangle as usize];
        let material = scene.material(tri);
        // Positive on the front face, which is the side texel shooters send light from.
        let facing = -d.dot(tri.geometric_normal());
        let cos_y = if material.double_sided { facing.abs() } else { facing };
        if cos_y <= 0.0 {
            return GpuNear::NONE;
        }
        let w = (1.0 - hit.t * hit.t / (cos_x * cos_y * r * r)).max(0.0);
        if w <= 0.0 {
            return GpuNear::NONE;
        }
        let le = scene.emission(tri, hit.bary);
        if le != Vec3::ZERO {
            add(le * (PI * w), d);
        }
        // Merged shooters (level > 0) keep their whole transfer: no texel part here.
        if facing <= 0.0 || self.params.shooter_level > 0 {
            return GpuNear::NONE;
        }
        match crate::engine::atlas::cells::texel_at(scene, &self.atlas, hit.triangle, hit.bary) {
            Some(j) => GpuNear {
                gain: v4(self.texel_albedo[j as usize] * w, 0.0),
                dir: d.to_array(),
                hit: j,
            },
            None => GpuNear::NONE,
        }
    }

    fn run_step(&mut self) -> Result<(), EngineError> {
        let step = self.steps_done;
        let parity = (step % 2) as usize;
        // One shooter a step with emitters: a fair coin picks the kind, and the shooter
        // counts as half a shooter of that kind (weight x 2), so every step's estimate is
        // an unbiased transfer of all the light.
        let (k_emit, k_texel, share_emit, share_texel) = if self.params.shooters_per_step == 1 && self.k_emit == 1 {
            let mut rng = Rng::new(self.seed, 0xC0_14, step, 0);
            if rng.next_f32() < 0.5 {
                (1, 0, 0.5, 1.0)
            } else {
                (0, 1, 1.0, 0.5)
            }
        } else {
            (self.k_emit, self.k_texel, self.k_emit as f64, self.k_texel as f64)
        };
        let watched = self.deadline.is_some() || self.progress.is_some();
        let sliced = self.slicer.slices(watched);
        let progress = self.progress.clone();
        // A watched step reports its CPU rays as its first half and its transfer as the
        // second.
        let mut go_on = go_on_until(self.deadline, progress.as_ref());
        let q = &self.ctx.queue;
        if k_emit > 0 {
            let samples = self.emitter_samples(step, k_emit, share_emit);
            q.write_buffer(&self.emitters_buf, 0, bytemuck::cast_slice(&samples));
        }
        if self.flags & HC_CPU_LIGHT != 0 {
            let mut first_third = |done: u64, of: u64| go_on(done, 3 * of);
            let Some((light, near)) = self.cpu_light(
                step,
                sliced.then_some(&mut first_third as &mut dyn FnMut(u64, u64) -> bool),
            ) else {
                tracing::debug!("hemicube: the deadline passed or a stop was asked mid-step; the step is undone");
                return Ok(());
            };
            // The receivers' slots of the two N-texel halves (sums, then directions).
            let (first, r) = (self.receivers.start as u64, near.len());
            let n = self.n_texels as u64;
            q.write_buffer(&self.cpu_light_buf, first * 16, bytemuck::cast_slice(&light[..r]));
            q.write_buffer(&self.cpu_light_buf, (n + first) * 16, bytemuck::cast_slice(&light[r..]));
            let near_size = std::mem::size_of::<GpuNear>() as u64;
            q.write_buffer(&self.near_buf, first * near_size, bytemuck::cast_slice(&near));
        }
        // Kept only once the step is done (a stopped step leaves them).
        let i = (self.half_steps[parity] + 1) as f64;
        let w = i.powf(self.params.ramp as f64);
        let half_weight = self.half_weight[parity] + w;
        let blend = (w / half_weight) as f32;
        let hash = (crate::engine::rng::splitmix64(self.seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15)) >> 32) as u32;
        let mut gp = GpuParams {
            dims: [self.n_texels, self.atlas.width, self.atlas.height, self.pyr_side],
            shoot: [self.top_level, self.params.shooter_level, k_emit, k_texel],
            step: [(step % 2) as u32, parity as u32, hash, self.flags],
            f: [
                blend,
                self.params.depth_map_size as f32,
                self.params.grazing_tolerance,
                share_texel as f32,
            ],
            // The receivers only: the other texels keep what they hold (a bake in rounds).
            slice: [self.receivers.start as u32, self.receivers.len() as u32, 0, 0],
        };
        q.write_buffer(&self.params_buf, 0, bytemuck::bytes_of(&gp));
        let shooters = k_emit + k_texel;
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("hemicube step"),
        });
        if k_texel > 0 {
            let level0 = (self.pyr_side as u64).pow(2) * 4;
            encoder.clear_buffer(&self.pyramid_buf, 0, Some(level0));
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hemicube power pyramid"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.power_pipeline);
            pass.set_bind_group(0, &self.power_bg, &[]);
            let (x, y) = gpu::dispatch_size_64(self.n_texels);
            pass.dispatch_workgroups(x, y, 1);
            pass.set_pipeline(&self.reduce_pipeline);
            for (bg, cells) in &self.reduce_bgs {
                pass.set_bind_group(0, bg, &[]);
                let (x, y) = gpu::dispatch_size_64(*cells);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hemicube select shooters"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.select_pipeline);
            pass.set_bind_group(0, &self.select_bg, &[]);
            pass.dispatch_workgroups(shooters.div_ceil(64).max(1), 1, 1);
        }
        let draws: Vec<ShadowDraw> = (0..5 * shooters)
            .map(|v| {
                let [x, y, side, _] = self.tiles[v as usize];
                // Side faces: only the half above the shooter's plane is ever looked up.
                let rows = if v % 5 == 0 { side } else { side / 2 };
                ShadowDraw {
                    view: v,
                    tile: [x, y, side],
                    rows,
                }
            })
            .collect();
        if !sliced && !draws.is_empty() {
            self.shadow
                .render(&mut encoder, &self.vertex_buf, self.vertex_count, draws.iter().copied());
        }
        let transfer = |encoder: &mut wgpu::CommandEncoder, (x, y): (u32, u32)| {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hemicube transfer"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.transfer_pipeline);
            pass.set_bind_group(0, &self.transfer_bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
        };
        if sliced {
            // The pyramid and the shooters, then their maps in slices of whole maps (each
            // the whole scene drawn, 5 a shooter: 8 s a step for a 1M-triangle level on
            // lavapipe), nothing to put back there (the atlas is redrawn every step), then
            // the transfer in slices of texels. This step's irradiance half (`step.x`) is
            // the accumulators' (`step.y`): both are the step's parity.
            q.submit([encoder.finish()]);
            let mut second_third = |done: u64, of: u64| go_on(of + done, 3 * of);
            let done = self
                .shadow
                .render_sliced(
                    &self.ctx,
                    &mut self.map_slicer,
                    &self.vertex_buf,
                    self.vertex_count,
                    &draws,
                    &mut second_third,
                )
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("hemicube: the deadline passed or a stop was asked mid-step; the step is undone");
                return Ok(());
            }
            // Only the accumulators: this step's irradiance and directions half is
            // rewritten whole by the step that follows before any pass reads it (the
            // pyramid, the selection and the near field read the other half).
            let aside = [
                Aside::half(&self.acc_buf, parity),
                Aside::half(&self.direct_acc_buf, parity),
            ];
            let first_receiver = self.receivers.start as u64;
            let mut submit = |first: u64, count: u64| {
                gp.slice = [(first_receiver + first) as u32, count as u32, 0, 0];
                q.write_buffer(&self.params_buf, 0, bytemuck::bytes_of(&gp));
                Ok(self.ctx.submit_compute(
                    "hemicube transfer",
                    &self.transfer_pipeline,
                    &self.transfer_bg,
                    count as u32,
                ))
            };
            let mut last_third = |done: u64, of: u64| go_on(2 * of + done, 3 * of);
            let done = self
                .slicer
                .run(
                    &self.ctx,
                    self.receivers.len() as u64,
                    &aside,
                    &mut submit,
                    &mut last_third,
                )
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("hemicube: the deadline passed or a stop was asked mid-step; the step is undone");
                return Ok(());
            }
        } else {
            transfer(&mut encoder, gpu::dispatch_size_64(self.receivers.len() as u32));
            q.submit([encoder.finish()]);
            self.slicer.returned_whole();
        }
        self.half_weight[parity] = half_weight;
        self.half_steps[parity] += 1;
        self.steps_done += 1;
        self.ctx.take_error("hemicube step").map_err(gpu_error)
    }
}

impl Technique for Hemicube {
    fn id(&self) -> &'static str {
        "hemicube"
    }

    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).expect("params serialise")
    }

    fn step(&mut self) -> Result<(), EngineError> {
        self.run_step()
    }

    fn wait_for_steps(&mut self) -> Result<(), EngineError> {
        self.ctx.wait_idle().map_err(gpu_error)
    }

    fn set_deadline(&mut self, deadline: Option<std::time::Instant>) {
        self.deadline = deadline;
        self.slicer.forget();
    }

    fn set_step_progress(&mut self, progress: StepProgress) {
        self.progress = Some(progress);
        self.slicer.forget();
    }

    fn steps_done(&self) -> u64 {
        self.steps_done
    }

    /// A page of a bake in rounds (module doc, "Rounds"): both irradiance halves of every
    /// texel are set to π times the held value, so the pyramid draws shooters from the
    /// whole grid's held light and the near-field gather reads it where it lands; the
    /// transfer and the CPU rays then run over the receivers only, which start from the
    /// held value too and from their own halves after the rounds before.
    fn hold_boundary(&mut self, boundary: &Boundary<'_>) -> Result<(), EngineError> {
        let n = self.n_texels as usize;
        let r = boundary.receivers.clone();
        if self.steps_done > 0 {
            return Err(EngineError::Internal(
                "hemicube: a boundary is held from the first step on".into(),
            ));
        }
        if boundary.held.len() != n || r.start > r.end || r.end > n {
            return Err(EngineError::Internal(format!(
                "hemicube: a boundary of {} held texels and receivers {r:?} for {n} texels",
                boundary.held.len()
            )));
        }
        let q = &self.ctx.queue;
        let held: Vec<[f32; 4]> = boundary.held.iter().map(|v| v4(*v * PI, 0.0)).collect();
        for h in 0..2u64 {
            q.write_buffer(&self.irr_buf, h * n as u64 * 16, bytemuck::cast_slice(&held));
        }
        if let Some(resume) = boundary.resume {
            let halves = [&resume.even, &resume.odd];
            if halves.iter().any(|h| h.total.len() != r.len()) {
                return Err(EngineError::Internal(format!(
                    "hemicube: resumed halves of {} texels for {} receivers",
                    resume.even.total.len(),
                    r.len()
                )));
            }
            let direct = self.flags & HC_DIRECT != 0;
            for (h, half) in halves.iter().enumerate() {
                let at = (h * n + r.start) as u64 * 16;
                let means: Vec<[f32; 4]> = half.total.iter().map(|v| v4(*v, 0.0)).collect();
                q.write_buffer(&self.acc_buf, at, bytemuck::cast_slice(&means));
                match (&half.direct, direct) {
                    (Some(d), true) => {
                        let means: Vec<[f32; 4]> = d.iter().map(|v| v4(*v, 0.0)).collect();
                        q.write_buffer(&self.direct_acc_buf, at, bytemuck::cast_slice(&means));
                    }
                    (None, false) => {}
                    _ => {
                        return Err(EngineError::Internal(
                            "hemicube: resumed halves with another direct layer".into(),
                        ));
                    }
                }
                // The running means' weights are i^ramp for i = 1..steps: the next step
                // of the half blends in as it would have in one bake.
                self.half_steps[h] = half.steps;
                self.half_weight[h] = (1..=half.steps).map(|i| (i as f64).powf(self.params.ramp as f64)).sum();
            }
            self.steps_done = resume.even.steps + resume.odd.steps;
        }
        self.receivers = r;
        self.ctx.take_error("hemicube boundary").map_err(gpu_error)
    }

    fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        let direct = (self.flags & HC_DIRECT != 0).then_some(&self.direct_acc_buf);
        // No directional layer: the plan lists it as left out.
        read_halves(
            &self.ctx,
            "hemicube",
            &self.acc_buf,
            direct,
            self.n_texels as usize,
            self.half_steps,
        )
        .map_err(gpu_error)
    }

    fn accumulating_pass(&self) -> &'static str {
        "hemicube transfer (shaders/hemicube/transfer.wgsl)"
    }
}

const GLOSSY_PASS: &str = "glossy lobes";
const CPU_LIGHT_PASS: &str = "sky, sun and punctual lights (CPU rays)";
const NEAR_FIELD_PASS: &str = "near-field gather (CPU rays)";

/// `hemicube`'s passes, WGSL in `shaders/hemicube/`.
pub mod shaders {
    use crate::engine::gpu::shaders::{PassShader, SHADOW_VIEW, WgslFile, pass, wgsl_file};

    /// Layouts and the lobe shared by the hemicube passes.
    pub const HEMICUBE_COMMON: WgslFile = wgsl_file!("hemicube/common.wgsl");
    /// The power pyramid (level 0 and the 2 x 2 sums).
    pub const HEMICUBE_PYRAMID: PassShader = pass!("hemicube/pyramid.wgsl", [HEMICUBE_COMMON]);
    /// The step's shooters (pyramid descent, texel merging) and their views.
    pub const HEMICUBE_SELECT: PassShader = pass!("hemicube/select.wgsl", [SHADOW_VIEW, HEMICUBE_COMMON]);
    /// Every receiver takes the shooters' light; the half accumulators.
    pub const HEMICUBE_TRANSFER: PassShader = pass!("hemicube/transfer.wgsl", [HEMICUBE_COMMON]);
    /// Every pass of `hemicube`.
    pub const ALL: &[PassShader] = &[HEMICUBE_PYRAMID, HEMICUBE_SELECT, HEMICUBE_TRANSFER];
}

/// `hemicube` in the technique table (`technique/table.rs`).
pub const ENTRY: TechniqueEntry = TechniqueEntry {
    default_params: || serde_json::to_value(HemicubeParams::default()).unwrap_or_default(),
    id: "hemicube",
    summary: "stochastic iteration by random hemicube shooting with glossy (Phong-type) transport and texel merging (GPU)",
    plan,
    prepare: |inputs, params| Ok(Box::new(Hemicube::prepare(inputs, params)?)),
    shaders: shaders::ALL,
    layers: &[OutputLayer::Direct, OutputLayer::Indirect],
    lights: LightSource::ALL,
    check_params: |p| parse_params::<HemicubeParams>("hemicube", p)?.validate(),
    unbiased: false,
    alpha: AlphaSupport::Everywhere,
    rounds: true,
    tasks: TaskSplit::Chains(
        "each step is one iteration of the random transport operator applied to the radiosity the steps before it left, over every texel: a range of steps cannot start without the steps before it, and a region's light depends on every other region's; its regions are baked in rounds instead, the others' light held (a job's rounds, bake --rounds, docs/scaling.md)",
    ),
};

/// What `hemicube` runs for a scene and job, and what it leaves out (DESIGN §6).
pub fn plan(f: &SceneFeatures) -> Plan {
    let mut p = Plan::new("hemicube");
    p.run(
        "power pyramid",
        "reflected power per texel summed 2 x 2 up to the total, for shooter selection",
    );
    p.run(
        "shooter selection",
        "pyramid descent with a GPU random number, texel merging at the shooter level",
    );
    p.decide(
        "emitter sampling (CPU)",
        f.emissive_triangles > 0,
        &format!(
            "{} emissive triangle(s) shoot from exact points, chosen by power",
            f.emissive_triangles
        ),
        "no emissive surface",
    );
    p.decide(
        CPU_LIGHT_PASS,
        f.sky || f.sun || f.punctual_lights > 0,
        "one shadow ray per texel a step for the sky, the sun and each punctual light (point, spot, directional)",
        "no sky, sun or punctual light",
    );
    p.run("hemicube depth maps", "five faces per shooter, one render pass");
    p.run(
        "transfer",
        "every texel takes every shooter's light (Eq. 4; shooters are points of the texels' cells)",
    );
    p.run(
        NEAR_FIELD_PASS,
        "one CPU ray per texel a step within params.near_field texel sizes (default 2), sharing the near field with the shooters by multiple importance, so creases lose no light",
    );
    p.decide(
        GLOSSY_PASS,
        f.glossy_materials > 0,
        &format!(
            "{} material(s) with metallic > 0 or roughness < 1: Phong lobes at shooters, incoming directions kept",
            f.glossy_materials
        ),
        "every material is a fully rough dielectric: the diffuse-only variant runs (no lobe data, no direction buffers)",
    );
    p.decide(
        DIRECT_LAYER,
        f.want_direct,
        "direct or indirect output asked for (direct accumulators)",
        "not asked for in outputs",
    );
    if f.want_sh {
        p.leave_out(
            SH_LAYER,
            "asked for, but hemicube keeps no directional moments: `sh` outputs fail with hemicube (use `path`)",
        );
    } else {
        p.leave_out(SH_LAYER, "not asked for in outputs");
    }
    p.error_estimate = "noise only, and low: consecutive steps are correlated through the light they reflect, so \
                        the halves share the light level's noise, and the iteration's start-up transient is a bias \
                        (docs/hemicube.md)"
        .into();
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Rust mirrors of WGSL structs have the shaders' sizes (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[
            Mirror::of::<GpuParams>("GpuParams", shaders::HEMICUBE_SELECT, "HcParams"),
            Mirror::of::<GpuTexelMat>("GpuTexelMat", shaders::HEMICUBE_SELECT, "TexelMat"),
            Mirror::of::<GpuNear>("GpuNear", shaders::HEMICUBE_SELECT, "NearSample"),
            Mirror::of::<GpuCellPiece>("GpuCellPiece", shaders::HEMICUBE_SELECT, "CellPiece"),
            Mirror::of::<GpuShooter>("GpuShooter", shaders::HEMICUBE_SELECT, "Shooter"),
        ]);
    }

    #[test]
    fn params_defaults_and_ranges() {
        let p: HemicubeParams = parse_params("hemicube", &serde_json::Value::Null).unwrap();
        assert_eq!(p, HemicubeParams::default());
        p.validate().unwrap();
        for bad in [
            serde_json::json!({"depth_map_size": 8}),
            serde_json::json!({"shooter_level": 5}),
            serde_json::json!({"shooters_per_step": 0}),
            serde_json::json!({"ramp": -1}),
            serde_json::json!({"grazing_tolerance": 3}),
        ] {
            let p: HemicubeParams = parse_params("hemicube", &bad).unwrap();
            let e = p.validate().unwrap_err().to_string();
            let name = bad.as_object().unwrap().keys().next().unwrap().clone();
            assert!(e.contains(&name), "{e} does not name {name}");
        }
        assert!(parse_params::<HemicubeParams>("hemicube", &serde_json::json!({"iterations": 3})).is_err());
    }

    #[test]
    fn lobe_is_lambertian_at_full_roughness_and_energy_bounded() {
        let base = Vec3::new(0.8, 0.5, 0.2);
        let rough = Material {
            roughness: 1.0,
            metallic: 1.0,
            ..Default::default()
        };
        assert_eq!(lobe(&rough, base), (base, Vec3::ZERO, 0.0));
        // Directional albedo of the specular lobe (numerically, over the hemisphere) is at
        // most k_s for every incidence, and close to k_s at normal incidence for a sharp lobe.
        let shiny = Material {
            roughness: 0.3,
            metallic: 1.0,
            ..Default::default()
        };
        let (kd, ks, e) = lobe(&shiny, base);
        assert_eq!(kd, Vec3::ZERO);
        assert!((ks - base).length() < 1e-6);
        for cos_i in [1.0f32, 0.7, 0.3] {
            let wi = Vec3::new((1.0 - cos_i * cos_i).sqrt(), 0.0, cos_i);
            let r = Vec3::new(-wi.x, 0.0, wi.z);
            let (nt, np) = (400, 400);
            let mut albedo = 0.0f64;
            for a in 0..nt {
                let ct = (a as f32 + 0.5) / nt as f32; // cos θ_o, uniform in cos: dω = dcos dφ
                let st = (1.0 - ct * ct).sqrt();
                for b in 0..np {
                    let phi = 2.0 * PI * (b as f32 + 0.5) / np as f32;
                    let wo = Vec3::new(st * phi.cos(), st * phi.sin(), ct);
                    let c = r.dot(wo).max(0.0);
                    let f = (e + 1.0) / (2.0 * PI) * c.powf(e) / cos_i.max(ct);
                    albedo += (f * ct) as f64 * (1.0 / nt as f64) * (2.0 * PI as f64 / np as f64);
                }
            }
            assert!(albedo <= 1.0 + 2e-3, "cos_i {cos_i}: albedo {albedo}");
            if cos_i == 1.0 {
                assert!(albedo > 0.97, "normal incidence albedo {albedo}");
            }
        }
    }
}
