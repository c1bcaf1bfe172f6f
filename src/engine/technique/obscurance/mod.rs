//! `obscurance`: obscurances with colour bleeding along global parallel directions, with
//! every depth layer per pixel, and incremental updates for moved objects (Méndez-Feliu,
//! Sbert, Catà, Sunyer & Funtané, "Real-time obscurances with color bleeding",
//! `shared/seeds/obscurances-color-bleeding-depth-peeling.md`).
//!
//! # What
//! For every valid texel P, with s = direction, d = distance to the surface Q seen,
//! rho = the falloff (sqrt(d/dmax) by default, 1 from dmax on):
//! - the plain obscurance W0(P) = 1/pi * integral of rho(d) cos (seed Eq. 2), written to
//!   the `ao.Y` layer;
//! - the colour-bleeding obscurance W(P) = 1/pi * integral of R(Q) rho(d) cos (Eq. 4), with
//!   R_ave, the area-weighted mean reflectivity, where no surface lies within dmax;
//! - the direct light: emitters and the sky seen along the same rays, the sun and
//!   directional lights through shadow maps.
//!
//! The lightmap (incident irradiance / pi, DESIGN section 2) is direct + I_A W(P): Eq. 1
//! with I(P) = R(P) I_A W(P) and W carrying the 1/pi, so a renderer's albedo * lightmap is
//! the seed's indirect term plus the direct light.
//!
//! # How (per direction d, uniform on the sphere; one step = `directions_per_step` of them)
//! 1. *Layers* (`shaders/obscurance/layers.wgsl`, seed section 4.1): one orthographic
//!    raster pass of the whole scene along d appends every fragment to its pixel's linked
//!    list (atomic head swap into a fixed node pool): all depth layers of every pixel in a
//!    single pass. Chosen over depth peeling because peeling renders the scene once per
//!    layer (L + 1 passes for L layers, and the vertex-bound software rasteriser this runs
//!    on in CI pays the whole scene each time), while the list costs one pass, the layer
//!    count is not needed in advance, and the gather needs no sorting: it only wants the
//!    layer next to each texel. The node pool is sized from the scene (sum of triangle
//!    areas over the smallest pixel area of any direction, plus slack) so every fragment
//!    fits; a fragment past the pool is dropped and counted ([`LayerStats`]), and the
//!    texels behind it see the next surface instead for that direction.
//! 2. *Gather* (`shaders/obscurance/gather.wgsl`, section 4.2): each texel projects its
//!    sample point into the map and walks its pixel's list for the layer consecutive to
//!    it along +d (if it faces +d) or -d (if it faces -d): the seed's transfer between
//!    consecutive layers in both directions in one pass. The seed's facing tests: the
//!    texel must face the layer (its normal's sign against d picks the direction) and the
//!    layer must face the texel (its front-facing bit) or be double-sided.
//! 3. *Direct* (`shaders/obscurance/direct.wgsl`): a shadow map per sun or directional
//!    light per direction step, drawn in the shared atlas (`gpu::shadow`: each pixel keeps
//!    the plane of the nearest surface, so a receiver behind it is shadowed without a
//!    depth bias), with E/pi cos visibility added to the direct accumulator. Until issue
//!    18 finished, this was obscurance's own nearest-depth map with a two-pixel depth
//!    bias.
//! 4. *Ambient* (on the CPU, at a snapshot): R_ave and I_A (below), and the lightmap
//!    direct + I_A W for each half.
//!
//! Estimator: the seed's "added and averaged" ratio, sum of f(s) |<n, d>| over sum of
//! |<n, d>| across directions (both signs of d used): consistent for the cosine-weighted
//! hemisphere integrals, and exact for a constant f, so an open plane reads exactly its
//! sky and a closed room's hit fraction is exactly 1 (the plain unbiased form,
//! 2 |<n, d>| f, carries the noise of the cosine weight itself into every term, and into
//! I_A's ratio). Each half accumulator keeps running means of numerator and denominator
//! (DESIGN section 4: even and odd steps); the CPU divides at a snapshot.
//!
//! Directions: `stratified` (R2 sequence, randomly rotated per bake) or `random`, shared
//! with `sdb` ([`super::sdb::Directions`]); the map origin is jittered by a random
//! sub-pixel offset per direction. Randomness: CPU SplitMix64 from the bake seed only;
//! the GPU passes use no hash (the lists' order depends on fragment scheduling, but the
//! nearest layer does not, barring exact ties in distance). Precision: f32 throughout, in normalised
//! scene space ((p - centre) / radius, as `sdb`), so epsilons are relative and scaling or
//! translating the scene does not change the result; `dmax` is converted to that space.
//! Bounds: the node pool is capped by the device's storage-binding size; lists are walked
//! to their end (no fixed k).
//!
//! Map size: unset, chosen per scene (`gpu::view::auto_map_size`: a pixel of at most half
//! the grid's median texel over the triangles' diagonal, 512 to 4096), then lowered while
//! the node pool it needs would pass the device's cap. A fixed 512 made 18 cm pixels on a
//! 91 m level of 10 cm texels, which blurred its sun shadows and put the gathered layer up
//! to 9 cm beside the texel's ray (docs/obscurance.md, "The map's size on a level").
//!
//! # Departures from the seed
//! - A per-pixel fragment list in one pass instead of depth peeling (above), and a
//!   texel-driven gather (each texel looks up its own pixel) instead of point streams
//!   writing into the obscurance map, so every texel gets exactly one sample per direction.
//! - A layer showing the texel its back face (single-sided) is a black blocker (R = 0,
//!   no emission, rho counts), where the seed dropped the pair: dropping would let light
//!   through the back of open geometry.
//! - Rays that leave the scene (no surface at any distance): the seed gives them R_ave
//!   like any open direction; here that is `background = ambient`, and the default
//!   `none` gives them 0 because the environment they see is already counted as direct
//!   light (an open plane under a sky would otherwise get R_ave I_A on top of the sky).
//!   Surfaces beyond dmax still give R_ave (the seed's "open directions").
//! - I_A: Eq. 5 holds for a closed scene lit only by emitters. The default `ambient =
//!   measured` generalises it with quantities the bake measures: I_A = D_ave / (1 - c
//!   R_ave), D_ave the area-weighted mean direct light (emitters, sky, sun) and c the
//!   area-weighted fraction of directions that hit a surface. In a closed scene c = 1 and
//!   D_ave is the mean emission (every emitted photon lands once), so this is Eq. 5; in an
//!   open one it accounts for the sky and for the reflected light that escapes.
//!   `ambient = emitters` is Eq. 5 as printed.
//! - Two half accumulators (even and odd steps) for the error estimate.
//! - Point and spot lights, which parallel bundles cannot find, come from the shared
//!   direct-light module (`engine::gpu::direct_light`: shadow rays on the GPU BVH), and
//!   so do emitters under `emitters = auto` when a triangle is smaller than
//!   [`SAMPLED_EMITTER_PIXELS`] map pixels (`sampled`: every emitter; `gathered`: none, the
//!   seed), whose emission the gather then ignores (`TRI_SAMPLED_EMISSION`). Their light is
//!   added to the direct light of each half before D_ave, so I_A bounces it like the rest.
//!
//! # Split bakes (`engine::tasks`, issue 25)
//! A task may bake one region of the grid (pages or bands of rows) and get the single
//! bake's texels there: the layers, directions and map jitter come from the scene and the
//! seed, the frame from the triangles alone, the map's size from the frame and the grid's
//! texels, the shared direct light's streams are keyed
//! by pixel, and the two things made of the whole grid are built alike in every task: the
//! albedo and emission maps the gather reads at the surfaces it sees, and R_ave, from the
//! grid's texels *before validation* (`Atlas::grid_texels`; a texel validation drops lies
//! inside closed geometry, where no ray sees it, and keeps its own surface's material).
//! The measured I_A is closed from sums over the bake's texels (`engine::ambient`), which
//! the merge closes over every region (`Technique::ambient`: the sums and W per half).
//!
//! # Incremental update (seed section 5)
//! During a bake every hit ORs two bits for the mesh it hit into the texel's influence
//! mask: 16 + (mesh index mod 16) for a hit at any distance, (mesh index mod 16) for one
//! within dmax. [`Obscurance::state`] saves accumulators, masks and the direction state;
//! [`Obscurance::update`] prepares a bake of the changed scene that recomputes only the
//! texels a changed (moved or added) mesh influenced: those whose mask has its bit
//! (before the move), the mesh's own texels, texels new to the atlas, and texels within
//! dmax of the mesh's new bounding box (the ones it now occludes or tints); every other
//! texel keeps its values and is skipped by the gather. Rerunning the same direction
//! sequence makes a recomputed texel equal to its full-rebake value. [`UpdateReach`]
//! picks the mask: `All` (hits at any distance: the direct sky light the mesh blocked
//! too) or `Dmax` (the seed's set: hits within dmax, i.e. the obscurance it influenced;
//! much smaller in open scenes). What it misses: texels farther than dmax from the new
//! position whose sky or far field the mesh now blocks, and with `Dmax` also those it
//! blocked before from farther than dmax (measured in docs/obscurance.md). Bits alias
//! mod 16 meshes, so the set is a superset (more work, never fewer texels).
//!
//! # Known bias and limits
//! - Obscurance is not radiosity: I_A is one scene-wide value, so a closed room of
//!   albedo near 1 does not converge to Le / (1 - rho) near its corners (rho < 1 there),
//!   and light from a bright corner does not reach a dark one. Measured in
//!   docs/obscurance.md and docs/stability.md.
//! - Lateral resolution: list samples sit at pixel centres, up to half a pixel from the
//!   texel's ray, which blurs contact shadows over a map pixel.
//! - Large emitters are found only by the rays that hit them (under `auto`); their noise
//!   is the directions', not light sampling's.
//!
//! Files: this one holds the parameters, the GPU layouts, the technique's state and its
//! trait; `setup.rs` prepares it, `step.rs` runs a step and reads the halves back,
//! `update.rs` updates a saved bake where meshes moved.

use std::sync::Arc;

use crate::engine::ambient::{AmbientHalf, AmbientSums};
use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use serde::{Deserialize, Serialize};

mod update;

pub use update::{ObscuranceState, UpdateReach, UpdateReport};

use super::api::{
    AlphaSupport, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry, gpu_error, parse_params,
};
use crate::engine::accumulate::{HalfEstimate, Snapshot};
use crate::engine::gpu::GpuContext;
use crate::engine::gpu::direct_light::{DirectLight, MAX_SAMPLES_PER_STEP};
use crate::engine::gpu::directions::{DirectionSequence, Directions, SplitMix64};
use crate::engine::gpu::map_scene::{DirectionalLight, Environment};
use crate::engine::gpu::shadow::ShadowAtlas;
use crate::engine::gpu::slices::StepSlicer;
use crate::engine::gpu::view::{AUTO_MAP_SIZE_MIN, DEPTH_NEAREST, make_view};
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};
use crate::engine::scene::Lighting;

mod setup;
mod step;

// ---------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------

/// rho(d / dmax) below dmax (1 from dmax on).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Falloff {
    /// sqrt(d / dmax): the seed's function.
    #[default]
    Sqrt,
    /// d / dmax.
    Linear,
    /// 0: classic ambient occlusion within dmax.
    Step,
    /// (1 - exp(-4 d/dmax)) / (1 - exp(-4)): saturates sooner than sqrt.
    Exp,
}

impl Falloff {
    fn code(self) -> u32 {
        match self {
            Falloff::Sqrt => 0,
            Falloff::Linear => 1,
            Falloff::Step => 2,
            Falloff::Exp => 3,
        }
    }

    /// rho(x) for x = d / dmax (the WGSL `falloff` in double precision, for tests).
    pub fn rho(self, x: f64) -> f64 {
        if x >= 1.0 {
            return 1.0;
        }
        let x = x.max(0.0);
        match self {
            Falloff::Sqrt => x.sqrt(),
            Falloff::Linear => x,
            Falloff::Step => 0.0,
            Falloff::Exp => (1.0 - (-4.0 * x).exp()) / (1.0 - (-4.0f64).exp()),
        }
    }
}

/// What the colour-bleeding term takes for rays that leave the scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Background {
    /// 0: what such a ray sees (the sky) is direct light already.
    #[default]
    None,
    /// R_ave, like any direction with no surface within dmax (the seed).
    Ambient,
}

/// Where the ambient intensity I_A comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum AmbientSource {
    /// D_ave / (1 - c R_ave) from the bake's own direct light and hit fraction.
    #[default]
    Measured,
    /// Eq. 5: mean emission over all triangles / (1 - R_ave) (closed scenes, emitters only).
    Emitters,
}

/// How emitters reach the direct light.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum EmitterLight {
    /// Emissive triangles smaller than [`SAMPLED_EMITTER_PIXELS`] map pixels through the
    /// shared module's light sampling, larger ones through the gather (default): the
    /// parallel bundles find a large emitter with every direction and no noise from its
    /// shape, and miss one smaller than a few pixels.
    #[default]
    Auto,
    /// Every emitter through the shared module's light sampling.
    Sampled,
    /// Only the gather's rays (the seed): noise-free for large emitters, blind to small ones.
    Gathered,
}

/// An emissive triangle with less area than this many pixels of the largest map pixel
/// (the scene's bounding-box diagonal over `map_size`) is light-sampled under
/// `emitters = auto`: 64 pixels is where the gather's per-direction hit count stops being
/// a few pixels' worth of aliasing.
pub const SAMPLED_EMITTER_PIXELS: f32 = 64.0;

/// `obscurance` parameters (the job's `params` object). Unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ObscuranceParams {
    /// dmax in scene units (metres): occlusions farther away do not count. Default: a
    /// quarter of the scene's bounding-box diagonal (so the default does not depend on the
    /// scene's scale); `params()` reports the value used. Finite and > 0.
    pub dmax: Option<f32>,
    /// rho: `sqrt` (default, the seed), `linear`, `step` or `exp`.
    pub falloff: Falloff,
    /// Map size in pixels (square) per direction: 64..=4096. Unset (the default), chosen
    /// per scene as `sdb`'s (`gpu::view::auto_map_size`: a map pixel of at most half the
    /// median texel, 512 to 4096, and no larger than the device's fragment pool holds at
    /// the scene's area); `params()` reports the size used.
    pub map_size: Option<u32>,
    /// Directions per step: 1..=256, default 1.
    pub directions_per_step: u32,
    /// `stratified` (default) or `random`.
    pub directions: DirectionSequence,
    /// Rays leaving the scene: `none` (default) or `ambient` (the seed).
    pub background: Background,
    /// I_A: `measured` (default) or `emitters` (Eq. 5 as printed).
    pub ambient: AmbientSource,
    /// Emitters: `auto` (default: small ones through the shared direct-light module,
    /// large ones through the gather), `sampled` or `gathered`.
    pub emitters: EmitterLight,
    /// Next-event estimates per texel and step of the shared direct light (point and
    /// spot lights, sampled emitters), 1..=64; default 4.
    pub light_samples: u32,
}

impl Default for ObscuranceParams {
    fn default() -> Self {
        ObscuranceParams {
            dmax: None,
            falloff: Falloff::Sqrt,
            map_size: None,
            directions_per_step: 1,
            directions: DirectionSequence::Stratified,
            background: Background::None,
            ambient: AmbientSource::Measured,
            emitters: EmitterLight::Auto,
            light_samples: 4,
        }
    }
}

impl ObscuranceParams {
    pub fn from_json(v: &serde_json::Value) -> Result<Self, EngineError> {
        let p: ObscuranceParams = parse_params("obscurance", v)?;
        p.validate()?;
        Ok(p)
    }

    /// The map's size: `map_size`, which `Obscurance::prepare` sets when the job leaves
    /// it unset.
    pub fn map_pixels(&self) -> u32 {
        self.map_size.unwrap_or(AUTO_MAP_SIZE_MIN)
    }

    pub fn validate(&self) -> Result<(), EngineError> {
        let bad = |m: String| Err(EngineError::BadInput(format!("obscurance parameter {m}")));
        if let Some(d) = self.dmax
            && !(d.is_finite() && d > 0.0)
        {
            return bad(format!("dmax: {d} is not a positive finite distance"));
        }
        if let Some(n) = self.map_size
            && !(64..=4096).contains(&n)
        {
            return bad(format!("map_size: {n} is outside 64..=4096"));
        }
        if !(1..=MAX_SAMPLES_PER_STEP).contains(&self.light_samples) {
            return bad(format!(
                "light_samples: {} is outside 1..={MAX_SAMPLES_PER_STEP}",
                self.light_samples
            ));
        }
        if !(1..=256).contains(&self.directions_per_step) {
            return bad(format!(
                "directions_per_step: {} is outside 1..=256",
                self.directions_per_step
            ));
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// GPU-side layouts: the structs of shaders/obscurance/*.wgsl, sizes checked against naga's
// layout (`gpu_layouts_match_the_shaders`)
// ---------------------------------------------------------------------------------------

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuNode {
    t: f32,
    tri: u32,
    lightmap: u32,
    next: u32,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuGatherParams {
    env_fwd: [f32; 4],
    env_back: [f32; 4],
    r_ave: [f32; 4],
    misc: [u32; 4],
    dims: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuDirectParams {
    irradiance: [f32; 4],
    bias: [f32; 4],
    misc: [u32; 4],
}

const TRI_TEXTURED_ALBEDO: u32 = 8;
/// Triangles drawn into a direction's depth layers in one draw: a direction of a larger
/// scene draws them in parts, each a unit of a sliced step (`step_gpu`), so a deadline is
/// seen within a part (about 0.3 s on lavapipe; a whole direction of a 1M-triangle level
/// took 2.2 s).
const LAYER_PART_TRIANGLES: u32 = 131_072;

/// The triangle's emission comes from the shared direct-light module, not the gather.
const TRI_SAMPLED_EMISSION: u32 = 16;
const FLAG_BACKGROUND_AMBIENT: u32 = 1;
const FLAG_SUBSET: u32 = 2;
/// counters[0..4] in obscurance/gather.wgsl; influence masks follow.
const MASK_BASE: usize = 4;
const EPS_NORMAL_PLANE: f32 = 1e-5;
const EPS_ALONG_D: f32 = 1e-5;
/// How far a receiver moves along its geometric normal before the sun map's test, in map
/// pixels: against a neighbouring triangle's plane passing just above it on tessellated
/// curved surfaces (the plane test needs no depth bias; gpu/shadow_view.wgsl).
const SHADOW_OFFSET_PIXELS: f32 = 1.0;

/// Per-pixel list statistics since the bake started (read at a snapshot).
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq, Eq)]
pub struct LayerStats {
    /// Node pool size.
    pub capacity: u32,
    /// Most fragments any direction produced.
    pub max_fragments: u32,
    /// Longest list a texel walked: the depth complexity (layer count) the scene needs.
    pub max_layers: u32,
    /// Directions whose fragments did not all fit in the pool.
    pub overflowing_directions: u32,
}

/// One half's per-texel means, as read back.
#[derive(Debug, Clone, Default)]
pub struct ObscuranceHalf {
    pub steps: u64,
    /// Colour-bleeding obscurance W (Eq. 4).
    pub w: Vec<Vec3>,
    /// Plain obscurance (Eq. 2).
    pub ao: Vec<f32>,
    /// Direct E/pi (emitters, sky, sun, directional lights).
    pub direct: Vec<Vec3>,
    /// Fraction (cosine-weighted) of directions that hit a surface.
    pub hit: Vec<f32>,
    /// The ambient intensity this half's lightmap used.
    pub ambient: Vec3,
    /// The sums it was closed from (`ambient = measured`), for a split bake's merge.
    pub sums: Option<AmbientSums>,
}

// ---------------------------------------------------------------------------------------
// The technique
// ---------------------------------------------------------------------------------------

/// GPU state of one `obscurance` bake.
pub struct Obscurance {
    ctx: Arc<GpuContext>,
    params: ObscuranceParams,
    seed: u64,
    notes: Vec<String>,
    want_direct: bool,
    n_texels: u32,
    lm_pixels: u32,
    width: u32,
    height: u32,
    texel_pixels: Vec<u32>,
    texel_area: Vec<f32>,
    mesh_names: Vec<String>,
    lighting: Lighting,
    corners: [Vec3; 8],
    /// dmax in normalised scene space.
    dmax_norm: f32,
    r_ave: Vec3,
    /// Eq. 5's I_A (for `ambient = emitters`).
    eq5_ambient: Vec3,
    environment: Option<Environment>,
    lights: Vec<DirectionalLight>,
    directions: Directions,
    rng: SplitMix64,
    steps_done: u64,
    half_steps: [u64; 2],
    dirs: [u64; 2],
    subset_len: Option<u32>,
    node_capacity: u32,
    last_ao: Option<Vec<f32>>,
    /// The measured I_A's sums and weights as of the last snapshot (`Technique::ambient`).
    last_ambient: Option<[AmbientHalf; 2]>,
    last_stats: LayerStats,
    /// Point and spot lights, and emitters unless `emitters = gathered`: the shared
    /// direct-light module, stepped once per step, after the directions: in a bake with a
    /// time limit or a watcher its step may run in slices and be stopped and undone
    /// between two (`TexelRayPass::step_watched`), and the directions are then put back
    /// too (`step_gpu`).
    shared_direct: Option<DirectLight>,
    deadline: Option<std::time::Instant>,
    progress: Option<StepProgress>,
    /// The directions' slices in a watched step (`gpu::slices`).
    slicer: StepSlicer,
    /// Triangles a direction draws into its depth layers at once ([`LAYER_PART_TRIANGLES`]).
    layer_part: u32,

    vertex_count: u32,
    vertex_buf: wgpu::Buffer,
    view_buf: wgpu::Buffer,
    gather_buf: wgpu::Buffer,
    direct_buf: wgpu::Buffer,
    heads_buf: wgpu::Buffer,
    counters_buf: wgpu::Buffer,
    acc_buf: wgpu::Buffer,
    direct_acc_buf: wgpu::Buffer,
    subset_buf: wgpu::Buffer,
    dummy_view: wgpu::TextureView,
    shadow: Option<ShadowPass>,
    layers_pipeline: wgpu::RenderPipeline,
    gather_pipeline: wgpu::ComputePipeline,
    layers_bg: wgpu::BindGroup,
    gather_bg: wgpu::BindGroup,
}

/// The sun / directional-light passes, created only when the job has such a light.
struct ShadowPass {
    /// The map being drawn: one [`ShadowView`].
    views_buf: wgpu::Buffer,
    /// Drawn from obscurance's own vertex buffer with a plane a triangle
    /// ([`AtlasVertices::MapScene`]).
    atlas: ShadowAtlas,
    direct_pipeline: wgpu::ComputePipeline,
    direct_bg: wgpu::BindGroup,
}

/// `obscurance`'s passes, WGSL in `shaders/obscurance/`.
pub mod shaders {
    use crate::engine::gpu::shaders::{MATERIALS, PassShader, SHADOW_VIEW, pass};

    /// Every depth layer per pixel as fragment lists.
    pub const OBSCURANCE_LAYERS: PassShader = pass!("obscurance/layers.wgsl", [MATERIALS]);
    /// Obscurance, colour bleeding and direct light along one direction.
    pub const OBSCURANCE_GATHER: PassShader = pass!("obscurance/gather.wgsl");
    /// Direct light from the sun and directional lights through the shared shadow atlas.
    pub const OBSCURANCE_DIRECT: PassShader = pass!("obscurance/direct.wgsl", [SHADOW_VIEW]);
    /// Every pass of `obscurance`.
    pub const ALL: &[PassShader] = &[OBSCURANCE_LAYERS, OBSCURANCE_GATHER, OBSCURANCE_DIRECT];
}

/// `obscurance` in the technique table (`technique/table.rs`).
pub const ENTRY: TechniqueEntry = TechniqueEntry {
    default_params: || serde_json::to_value(ObscuranceParams::default()).unwrap_or_default(),
    id: "obscurance",
    summary: "obscurances with colour bleeding along random directions with all depth layers, an ao layer and incremental updates (GPU)",
    plan,
    prepare: |inputs, params| Ok(Box::new(Obscurance::prepare(inputs, params)?)),
    shaders: shaders::ALL,
    layers: &[OutputLayer::Direct, OutputLayer::Indirect, OutputLayer::Ao],
    lights: LightSource::ALL,
    check_params: |p| ObscuranceParams::from_json(p).map(|_| ()),
    unbiased: false,
    alpha: AlphaSupport::Everywhere,
    rounds: false,
    tasks: TaskSplit::ChainsAndRegions(
        "its halves are running ratios over a stratified direction sequence rotated once per bake, so a range of steps is not a part of one bake; a texel's obscurance comes from the scene's layers along the bake's directions, the maps of the whole grid's materials and R_ave (built from the grid's texels before validation, whichever region the task holds), and I_A from one scene-wide closure that the merge closes over every region, so a region's texels (pages or tiles) are the single bake's",
    ),
};

/// What `obscurance` runs for a scene and job, and what it leaves out (DESIGN section 6).
pub fn plan(f: &SceneFeatures) -> Plan {
    let mut p = Plan::new("obscurance");
    p.run(
        "depth layers",
        "one raster pass per direction appending every fragment to per-pixel lists (all layers)",
    );
    p.run(
        "gather",
        "consecutive-layer transfer for every texel along +d and -d: obscurance, colour bleeding, direct",
    );
    p.run(
        "ambient term",
        "R_ave and I_A from scene averages at each snapshot (CPU)",
    );
    let directional = f.sun || f.directional_lights > 0;
    p.decide(
        "shadow maps + direct pass",
        directional,
        "the job has a sun or the scene has directional lights",
        "no sun and no directional light",
    );
    p.decide(
        "sky lookups",
        f.sky,
        "the job has a sky: rays leaving the scene bring it as direct light",
        "the job has no sky",
    );
    p.decide(
        DIRECT_LAYER,
        f.want_direct,
        "direct or indirect output asked for (kept anyway for I_A; costs only a readback)",
        "not asked for in outputs",
    );
    if f.want_sh {
        p.leave_out(
            SH_LAYER,
            "asked for, but obscurance keeps no directional moments: `sh` outputs fail with obscurance (use `path`)",
        );
    } else {
        p.leave_out(SH_LAYER, "not asked for in outputs");
    }
    let point_spot = f.punctual_lights.saturating_sub(f.directional_lights);
    p.decide(
        "shared direct light",
        point_spot > 0 || f.emissive_triangles > 0,
        "point and spot lights, and emitters smaller than 64 map pixels (params.emitters = auto): E/pi with shadow rays \
         on the GPU BVH (engine::gpu::direct_light), feeding I_A like the rest of the direct light",
        "no point or spot light and no emitter",
    );
    if f.glossy_materials > 0 {
        p.leave_out(
            "glossy transport",
            "obscurance is diffuse only; metallic/roughness are ignored",
        );
    } else {
        p.leave_out("glossy data", "every material is a fully rough dielectric");
    }
    p.leave_out(
        "multi-bounce transport",
        "by design: indirect light is R(Q) I_A with one scene-wide I_A (Eq. 1), not a radiosity solution",
    );
    p.error_estimate = "noise only: the obscurance model's bias (one scene-wide ambient term) is not in it".into();
    p
}

/// Pixel side of the map along `d` (normalised units), as `make_view` sizes it.
fn pixel_size(d: Vec3, corners: &[Vec3; 8], map_size: u32) -> f32 {
    let v = make_view(d, corners, map_size, (0.0, 0.0), 0, DEPTH_NEAREST);
    v.extent[0] / v.extent[2]
}

impl Obscurance {
    /// What this bake leaves out of the scene's light.
    pub fn notes(&self) -> &[String] {
        &self.notes
    }

    /// Area-weighted mean reflectivity of the scene.
    pub fn r_ave(&self) -> Vec3 {
        self.r_ave
    }

    /// dmax in scene units.
    pub fn dmax(&self) -> f32 {
        self.params.dmax.unwrap_or(0.0)
    }

    /// Draws a direction's depth layers `triangles` at a time instead of
    /// [`LAYER_PART_TRIANGLES`]: for a test that a scene drawn in parts bakes what it
    /// bakes drawn whole, on a scene small enough to bake in a test.
    #[doc(hidden)]
    pub fn set_layer_part_triangles(&mut self, triangles: u32) {
        self.layer_part = triangles.max(1);
    }

    /// List statistics as of the last snapshot.
    pub fn layer_stats(&self) -> LayerStats {
        self.last_stats
    }
}

fn obscurance_snapshot(halves: [ObscuranceHalf; 2], want_direct: bool) -> (Snapshot, Vec<f32>) {
    let [even, odd] = halves;
    let (ne, no) = (even.steps as f32, odd.steps as f32);
    let total_steps = (ne + no).max(1.0);
    let ao: Vec<f32> = even
        .ao
        .iter()
        .zip(&odd.ao)
        .map(|(a, b)| (a * ne + b * no) / total_steps)
        .collect();
    let half = |h: ObscuranceHalf| {
        let total = h.direct.iter().zip(&h.w).map(|(d, w)| *d + h.ambient * *w).collect();
        HalfEstimate {
            steps: h.steps,
            total,
            direct: want_direct.then_some(h.direct),
            moments: None,
        }
    };
    (
        Snapshot {
            even: half(even),
            odd: half(odd),
        },
        ao,
    )
}

impl Technique for Obscurance {
    fn id(&self) -> &'static str {
        "obscurance"
    }

    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).expect("params serialise")
    }

    fn step(&mut self) -> Result<(), EngineError> {
        self.step_gpu().map_err(gpu_error)
    }

    fn wait_for_steps(&mut self) -> Result<(), EngineError> {
        self.ctx.wait_idle().map_err(gpu_error)
    }

    fn set_deadline(&mut self, deadline: Option<std::time::Instant>) {
        self.deadline = deadline;
        self.slicer.forget();
        if let Some(d) = &mut self.shared_direct {
            d.forget_step_length();
        }
    }

    fn set_step_progress(&mut self, progress: StepProgress) {
        self.progress = Some(progress);
        self.slicer.forget();
        if let Some(d) = &mut self.shared_direct {
            d.forget_step_length();
        }
    }

    fn steps_done(&self) -> u64 {
        self.steps_done
    }

    fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        let halves = self.halves()?;
        // A measured I_A is B = I_A times W in each texel's indirect light.
        self.last_ambient = match &halves {
            [
                ObscuranceHalf {
                    sums: Some(a), w: wa, ..
                },
                ObscuranceHalf {
                    sums: Some(b), w: wb, ..
                },
            ] => Some([
                AmbientHalf {
                    sums: *a,
                    weight: wa.clone(),
                },
                AmbientHalf {
                    sums: *b,
                    weight: wb.clone(),
                },
            ]),
            _ => None,
        };
        let (snapshot, ao) = obscurance_snapshot(halves, self.want_direct);
        self.last_ao = Some(ao);
        Ok(snapshot)
    }

    fn ao(&self) -> Option<Vec<f32>> {
        self.last_ao.clone()
    }

    fn ambient(&self) -> Option<[AmbientHalf; 2]> {
        self.last_ambient.clone()
    }

    fn accumulating_pass(&self) -> &'static str {
        "obscurance gather (shaders/obscurance/gather.wgsl)"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Rust mirrors of WGSL structs have the shaders' sizes (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[
            Mirror::of::<GpuNode>("GpuNode", shaders::OBSCURANCE_GATHER, "Node"),
            Mirror::of::<GpuGatherParams>("GpuGatherParams", shaders::OBSCURANCE_GATHER, "GatherParams"),
            Mirror::of::<GpuDirectParams>("GpuDirectParams", shaders::OBSCURANCE_DIRECT, "DirectParams"),
            Mirror::of::<GpuNode>("GpuNode", shaders::OBSCURANCE_LAYERS, "Node"),
        ]);
    }

    #[test]
    fn params_defaults_and_ranges() {
        let p = ObscuranceParams::from_json(&serde_json::Value::Null).unwrap();
        assert_eq!(p, ObscuranceParams::default());
        let p = ObscuranceParams::from_json(&serde_json::json!({"dmax": 2.5, "falloff": "linear"})).unwrap();
        assert_eq!((p.dmax, p.falloff), (Some(2.5), Falloff::Linear));
        for bad in [
            serde_json::json!({"dmax": 0.0}),
            serde_json::json!({"dmax": -1.0}),
            serde_json::json!({"map_size": 32}),
            serde_json::json!({"directions_per_step": 0}),
            serde_json::json!({"falloff": "cubic"}),
            serde_json::json!({"background": "sky"}),
            serde_json::json!({"unknown": 1}),
        ] {
            let e = ObscuranceParams::from_json(&bad).expect_err("accepted");
            assert!(e.is_bad_input(), "{bad}: {e}");
        }
    }

    #[test]
    fn falloffs_rise_from_0_to_1() {
        for f in [Falloff::Sqrt, Falloff::Linear, Falloff::Exp] {
            assert_eq!(f.rho(0.0), 0.0);
            assert!((f.rho(0.999_999) - 1.0).abs() < 1e-5, "{f:?}");
            assert!(f.rho(0.3) < f.rho(0.6));
        }
        assert_eq!(Falloff::Sqrt.rho(0.25), 0.5);
        assert_eq!(Falloff::Step.rho(0.5), 0.0);
        assert_eq!(Falloff::Step.rho(1.0), 1.0);
    }
}
