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
//! `CPU_LIGHT_CHUNK` texels, the shooters' depth maps in slices of whole maps (each the
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
//!
//! Files: this one holds the parameters, the GPU layouts, the technique's state and its
//! trait; `setup.rs` prepares it (uploads, atlas, passes), `step.rs` runs a step.

use std::f32::consts::PI;
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::api::{
    AlphaSupport, Boundary, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry, gpu_error,
    parse_params,
};
use crate::engine::accumulate::{LUMINANCE, Snapshot};
use crate::engine::atlas::Atlas;
use crate::engine::gpu::GpuContext;
use crate::engine::gpu::halves::read_halves;
use crate::engine::gpu::shadow::ShadowAtlas;
use crate::engine::gpu::slices::StepSlicer;
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};
use crate::engine::raytrace::Tracer;
use crate::engine::scene::{Lighting, Material, Scene};

mod setup;
mod step;

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
