//! `vpl`: instant radiosity (Keller 1997) from reflective shadow maps, with VPL visibility
//! (`shared/seeds/instant-radiosity-vpl-light-prepass.md`, a blog post on light-prepass
//! instant radiosity; docs/vpl.md has the measurements).
//!
//! # What
//! Direct and multi-bounce diffuse light at every valid lightmap texel, as incident
//! irradiance / pi without the surface's own emission (DESIGN.md section 2), from every
//! light a scene and job can have: point and spot lights, directional lights, the sun,
//! the sky and emissive surfaces.
//!
//! # How (one step)
//! 1. *Primary lights* (CPU): the sun with its direction jittered over its disc,
//!    directional lights, `sky_directions` directions of the sky (a stratified R2
//!    sequence over the sphere, randomly rotated per bake, the upper half mirrored up for
//!    an `upper` sky; each is a distant light of irradiance L(w) Omega / K), and every point
//!    and spot light.
//! 2. *Reflective shadow maps* (ray casting, seed: "cast rays from a (primary) light
//!    into the scene and mark the positions where they hit"; `vpl/rsm.rs`, the rays traced
//!    on the CPU or in one batch through the GPU BVH, `params.rays`): per distant light an
//!    orthographic `rsm_size`^2 grid over the scene's bounding disc, per point or spot
//!    light a cube of six perspective faces of (`rsm_size`/2)^2 (spot texels outside the
//!    cone are skipped). One jittered ray per texel; a texel stores the hit's position,
//!    normal and reflected flux = incident flux x albedo (RGB, so coloured lights and
//!    surfaces work; the seed stored albedo only). Maps are redrawn with new jitter every
//!    step, so they add noise, not aliasing.
//! 3. *Path starts*: `vpls_per_step` draws, with probability proportional to luminance
//!    flux, from the RSM texels of every light and the emissive triangles (by power
//!    pi Le A); a drawn RSM texel is a VPL of depth 1, a drawn triangle gives a uniform
//!    point on it, a VPL of depth 0 (the emitter's own light). Each carries flux
//!    total / count (in luminance), so the estimator is unbiased.
//! 4. *Bounces* (Keller's recursion, CPU, rayon): from each VPL a cosine-distributed ray;
//!    its hit is the next VPL with flux x albedo / q, surviving with probability
//!    q = max albedo channel (Russian roulette), up to depth `max_depth`.
//! 5. *Resampling*: when the paths made more than `vpls_per_step` VPLs, that many are
//!    drawn from them by luminance flux (duplicates merged), so the shadow-map budget per
//!    step is fixed whatever the albedo.
//! 6. *Shadow maps* (`shaders/gpu/shadow_atlas.wgsl`, one render pass): an orthographic map per
//!    distant light (`shadow_map_size`^2), six cube faces per point or spot light
//!    ((`shadow_map_size`/2)^2 each), five faces per VPL (`vpl_map_size`^2; the face
//!    behind its surface gets no light), all tiles of one Rgba32Float atlas holding the
//!    *plane* (normal, offset) of the nearest surface per pixel. `shadow_map_size` unset
//!    is chosen per scene (`gpu::view::auto_map_size`, then lowered to fit the device and
//!    [`AUTO_ATLAS_BYTES`]): a fixed 512 made 18 cm pixels on a 91 m level of 10 cm
//!    texels and blurred its sun's shadows (docs/vpl.md, "The map's size on a level").
//! 7. *Gather* (`shaders/vpl/gather.wgsl`): every texel sums every light of the step with
//!    its shadow-map visibility (2x2 PCF): VPLs as hemispherical emitters,
//!    Phi cos cos / (pi^2 max(d^2, clamp^2)); point and spot lights and distant lights
//!    exactly; and blends the sum into the even or odd half accumulator (a running mean).
//!    Light from primary lights and depth-0 VPLs also goes into a direct accumulator.
//!
//! In a bake with a time limit or a watcher that may cancel, a step that may be long runs
//! its gather in slices of texels of about 50 ms (`gpu::slices`: the gather is the part
//! of a step that grows with the level, 1.1 s of a step at 1.46 M texels on lavapipe);
//! a step stopped between two slices puts back its halves, its random stream and its
//! direction sequence, so it adds nothing (issue 19 point 10). Steps 1 to 6 stay whole:
//! they grow with the lights and the scene, not the texels.
//!
//! Readback only at snapshots (and the RSM rays' hits on the GPU route). No GPU
//! randomness: every random number is drawn on the
//! CPU (SplitMix64 per step and PCG32 streams per RSM row and path, keyed by bake seed,
//! step and index), so a bake is reproducible from its seed. Precision: f32; geometry on
//! the GPU in normalised scene space (p - centre) / radius, fluxes and intensities divided
//! by radius^2 to match, so the clamp, the shadow biases and the near planes are relative
//! and scaled or translated scenes bake the same. The RSMs' and bounces' rays run in
//! world space (the GPU route's BVH is the world-space one the CPU's mirrors) with the
//! atlas's relative surface offset. Bounds: the shadow atlas is laid out once per bake
//! and checked against the device's largest texture (a bad-input error names the
//! parameters to lower); the step's light list (primaries + `vpls_per_step`) and views
//! are storage buffers sized at preparation; the accumulators (2 x texels x 16 bytes
//! each) are checked against the storage-binding limit.
//!
//! # Departures from the seed
//! - RSM texels are found by ray casting (the seed's first option) instead of
//!   rasterising from the light: one code path for orthographic, perspective and cube
//!   maps, jitter per step for free, and the texels on the host to pick VPLs by flux
//!   (the GPU route reads back the hits, 16 bytes a ray). The maps have the seed's
//!   content (position, normal, flux) and resolution, as parameters.
//! - Reflected flux (albedo x light colour), not albedo: coloured lights work; normals are
//!   stored, so VPLs are hemispherical emitters (the seed's own wish).
//! - VPL visibility (the seed left it out): a five-face cube shadow map per VPL. The leak
//!   it removes is measured (docs/vpl.md); `visibility: false` reproduces the seed.
//!   The maps store planes, not distances (a plane-side test instead of a biased depth
//!   compare), so 1 mm walls do not leak (a distance compare leaked 5% through them).
//! - Point lights (cube maps) and spot lights, the sky and emissive surfaces start VPL
//!   paths too, and bounces recurse (Keller) instead of stopping at the first.
//! - A progressive, unbiased-but-for-the-clamp estimator: fresh VPLs every step, two half
//!   accumulators (even and odd steps) for the error estimate.
//!
//! # Known bias and limits
//! - The clamp: a receiver closer than `clamp` (relative to the scene radius) to a VPL
//!   gets Phi cos cos / (pi^2 clamp^2) instead of the 1/d^2 singularity: light is lost in
//!   corners and contact regions (measured in docs/vpl.md). `clamp: 0` is unbiased but its
//!   variance is unbounded near VPLs.
//! - Shadow maps store the nearest surface's plane, and a tap blocks when light and
//!   receiver are on opposite sides of it: exact behind walls of any thickness (down to
//!   1e-5 of the radius), but within a pixel of a silhouette a neighbour's plane is
//!   extrapolated, and the receiver's normal offset (1 map pixel at its distance, against
//!   self-shadowing on tessellated curved surfaces) shifts contact shadows; coarse VPL
//!   maps blur VPL shadows.
//! - Cost: each VPL renders the whole scene five times: per step O(VPLs x triangles) on the
//!   GPU and O(texels x VPLs) in the gather. Fine for small scenes on lavapipe, slow for
//!   25k triangles (docs/performance.md).
//! - Diffuse only; no directional (`sh`) layer.
//!
//! Files: this one holds the parameters, the GPU layouts, the technique's state and its
//! trait; `setup.rs` prepares it, `step.rs` builds a step's lights and runs the step,
//! `rsm.rs` casts the reflective shadow maps' rays.

mod rsm;

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::api::{
    AlphaSupport, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry, gpu_error, parse_params,
};
use crate::engine::accumulate::{LUMINANCE, Snapshot};
use crate::engine::gpu::directions::{Directions, SplitMix64};
use crate::engine::gpu::halves::read_halves;
use crate::engine::gpu::shadow::{self, ShadowAtlas, ShadowAtlasLayout, ShadowView};
use crate::engine::gpu::slices::StepSlicer;
use crate::engine::gpu::view::AUTO_MAP_SIZE_MIN;
use crate::engine::gpu::{GpuContext, RayDevice};
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};
use crate::engine::raytrace::Tracer;
use crate::engine::scene::{Lighting, Scene};
use rsm::RsmTracer;

mod setup;
mod step;

// ---------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------

/// `vpl` parameters (the job's `params` object). Unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VplParams {
    /// Reflective shadow map side in texels per distant light (each cube face of a point
    /// or spot light has half of it). Range 4..=1024; default 64.
    pub rsm_size: u32,
    /// VPLs gathered (and shadow-mapped) per step. Range 1..=1024; default 32.
    pub vpls_per_step: u32,
    /// Clamp distance of the VPLs' 1/d^2, relative to the scene's bounding radius.
    /// Range 0..=0.5; default 0.02.
    pub clamp: f32,
    /// Deepest VPL generation (number of reflections; 1 = the seed's single bounce).
    /// Russian roulette ends paths anyway, so the default 100000 is effectively no limit.
    /// Range 1..=1000000.
    pub max_depth: u32,
    /// Shadow maps for the VPLs (default true); false gathers VPLs unoccluded (the seed).
    pub visibility: bool,
    /// Shadow map side for distant lights (each cube face of a point or spot light has
    /// half of it). Range 16..=8192. Unset (the default), chosen per scene as `sdb`'s
    /// map (`gpu::view::auto_map_size`: a pixel of at most half the grid's median texel,
    /// from 512), then lowered while the shadow atlas would not fit the device or
    /// [`AUTO_ATLAS_BYTES`]; the bake's echoed parameters give the size used.
    pub shadow_map_size: Option<u32>,
    /// Side of each of a VPL's five cube-face shadow maps. Range 4..=1024; default 64.
    pub vpl_map_size: u32,
    /// Sky directions per step (each a distant light with its own RSM and shadow map).
    /// Range 1..=64; default 4.
    pub sky_directions: u32,
    /// Where the reflective shadow maps' rays are traced: `auto` (default: the GPU on a
    /// hardware adapter, else the CPU), `cpu` or `gpu` (the BVH query pass, also on
    /// lavapipe). The bake's echoed parameters name the route taken. The VPL paths'
    /// bounces stay on the CPU (`vpl/rsm.rs` says why).
    pub rays: RayDevice,
}

impl Default for VplParams {
    fn default() -> Self {
        VplParams {
            rsm_size: 64,
            vpls_per_step: 32,
            clamp: 0.02,
            max_depth: 100_000,
            visibility: true,
            shadow_map_size: None,
            vpl_map_size: 64,
            sky_directions: 4,
            rays: RayDevice::Auto,
        }
    }
}

/// The most memory an automatically sized shadow atlas may take (its plane and depth
/// textures, 20 bytes a pixel): 512 MiB, the sun's and four sky directions' maps at
/// about 2300² each beside the VPLs' faces.
pub const AUTO_ATLAS_BYTES: u64 = 512 << 20;

impl VplParams {
    /// The distant lights' shadow map side: `shadow_map_size`, which `Vpl::prepare` sets
    /// when the job leaves it unset.
    pub fn shadow_map_pixels(&self) -> u32 {
        self.shadow_map_size.unwrap_or(AUTO_MAP_SIZE_MIN)
    }

    pub fn validate(&self) -> Result<(), EngineError> {
        let err = |name: &str, msg: String| Err(EngineError::BadInput(format!("vpl parameter {name}: {msg}")));
        let range = |name: &str, v: u32, lo: u32, hi: u32| {
            if (lo..=hi).contains(&v) {
                Ok(())
            } else {
                err(name, format!("{v} is outside {lo}..={hi}"))
            }
        };
        range("rsm_size", self.rsm_size, 4, 1024)?;
        range("vpls_per_step", self.vpls_per_step, 1, 1024)?;
        range("max_depth", self.max_depth, 1, 1_000_000)?;
        if let Some(n) = self.shadow_map_size {
            range("shadow_map_size", n, 16, 8192)?;
        }
        range("vpl_map_size", self.vpl_map_size, 4, 1024)?;
        range("sky_directions", self.sky_directions, 1, 64)?;
        if !(0.0..=0.5).contains(&self.clamp) {
            return err("clamp", format!("{} is outside 0..=0.5", self.clamp));
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// GPU layouts: the structs of vpl/gather.wgsl, sizes checked against naga's layout
// (`gpu_layouts_match_the_shaders`); the atlas's views are gpu::shadow's
// ---------------------------------------------------------------------------------------

const LIGHT_VPL: u32 = 0;
const LIGHT_POINT: u32 = 1;
const LIGHT_SPOT: u32 = 2;
const LIGHT_DIRECTIONAL: u32 = 3;
const NO_VIEW: u32 = u32::MAX;
/// Receiver offset along its normal, in shadow-map pixels at the receiver, against
/// self-shadowing by neighbouring triangles of tessellated curved surfaces (the plane
/// test is exact on flat ones).
const NORMAL_OFFSET_PX: f32 = 1.0;
/// Near plane of cube faces (normalised scene units).
const CUBE_NEAR: f32 = 1e-4;
/// Margin around the unit bounding sphere for orthographic maps and far planes.
const MARGIN: f32 = 1.05;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuLight {
    pos: [f32; 4],
    axis_t: [f32; 4],
    axis_b: [f32; 4],
    axis_n: [f32; 4],
    power: [f32; 4],
    spot: [f32; 4],
    info: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuGatherParams {
    misc: [u32; 4],
    bias: [f32; 4],
    /// The dispatch's first texel and texel count (a sliced step, `gpu::slices`).
    slice: [u32; 4],
}

fn v4(v: Vec3, w: f32) -> [f32; 4] {
    [v.x, v.y, v.z, w]
}

fn lum(v: Vec3) -> f64 {
    v.dot(LUMINANCE) as f64
}

/// The shared atlas layout, with `vpl`'s parameters named when it does not fit.
fn pack(sizes: &[u32], max_dim: u32) -> Result<ShadowAtlasLayout, EngineError> {
    shadow::pack(sizes, max_dim).map_err(|e| {
        EngineError::BadInput(format!(
            "vpl: the shadow atlas ({} maps) needs {}x{} pixels, more than the device's {}; \
             lower vpls_per_step, vpl_map_size, shadow_map_size or sky_directions",
            e.maps, e.width, e.height, e.max_dim
        ))
    })
}

// ---------------------------------------------------------------------------------------
// Lights, RSM texels, VPLs (CPU)
// ---------------------------------------------------------------------------------------

/// A light that starts VPL paths and lights texels directly, fixed for the bake.
#[derive(Debug, Clone, Copy)]
enum Primary {
    Sun,
    /// A directional light: direction of travel, irradiance facing it.
    Directional {
        dir: Vec3,
        irradiance: Vec3,
    },
    /// The k-th sky direction of a step.
    Sky,
    /// A point or spot light (index into the scene's lights).
    Punctual(usize),
}

/// A VPL or RSM texel in world space: a point on a surface, the side it faces, and the
/// flux it reflects (or, at depth 0, emits).
#[derive(Debug, Clone, Copy)]
struct SurfacePoint {
    p: Vec3,
    n: Vec3,
    flux: Vec3,
    depth: u32,
}

/// An emissive triangle, sampled by power.
#[derive(Debug, Clone, Copy)]
struct Emitter {
    triangle: u32,
    /// pi x luminance of the material's emission x area x sides.
    weight: f64,
}

/// The hit of a light ray: the point and the side it faces; None when nothing reflects
/// (a miss, or the black back face of single-sided geometry).
fn surface_hit(scene: &Scene, tracer: &Tracer, origin: Vec3, dir: Vec3, tmax: f32) -> Option<(Vec3, Vec3, Vec3)> {
    rsm::surface_of(scene, &tracer.trace(scene, origin, dir, tmax)?, dir)
}

// ---------------------------------------------------------------------------------------
// The technique
// ---------------------------------------------------------------------------------------

pub struct Vpl {
    ctx: Arc<GpuContext>,
    params: VplParams,
    scene: Arc<Scene>,
    /// The VPL paths' bounces (CPU).
    tracer: Arc<Tracer>,
    /// The reflective shadow maps' rays (`params.rays`).
    rsm: RsmTracer,
    lighting: Lighting,
    seed: u64,
    want_direct: bool,
    /// Normalisation: GPU space is (p - centre) / radius.
    centre: Vec3,
    radius: f32,
    /// Surface offset of continuation rays (world units).
    ray_offset: f32,
    primaries: Vec<Primary>,
    /// First view of each primary (its orthographic map or its six cube faces).
    primary_views: Vec<u32>,
    /// First VPL view (five per VPL) when `visibility`.
    vpl_views: u32,
    layout: ShadowAtlasLayout,
    emitters: Vec<Emitter>,
    emitter_weight: f64,
    directions: Directions,
    rng: SplitMix64,
    steps_done: u64,
    half_steps: [u64; 2],
    n_texels: u32,
    max_lights: u32,

    vertex_count: u32,
    vertex_buf: wgpu::Buffer,
    lights_buf: wgpu::Buffer,
    views_buf: wgpu::Buffer,
    gather_buf: wgpu::Buffer,
    acc_buf: wgpu::Buffer,
    direct_acc_buf: wgpu::Buffer,
    shadow: ShadowAtlas,
    gather_pipeline: wgpu::ComputePipeline,
    gather_bg: wgpu::BindGroup,
    texel_dispatch: (u32, u32),
    /// The bake's time limit and watcher (issue 19 point 10): a step that may be long
    /// runs its gather in slices and is undone when either says stop between two.
    deadline: Option<std::time::Instant>,
    progress: Option<StepProgress>,
    slicer: StepSlicer,
    /// The maps' slices (whole maps) in a sliced step.
    map_slicer: StepSlicer,
}

/// One step's lights and maps, built on the CPU.
struct StepLights {
    lights: Vec<GpuLight>,
    views: Vec<ShadowView>,
    /// Views to render this step.
    draws: Vec<u32>,
}

impl Vpl {}

impl Technique for Vpl {
    fn id(&self) -> &'static str {
        "vpl"
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

    fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        let direct = (self.want_direct).then_some(&self.direct_acc_buf);
        // No directional layer: the plan lists it as left out.
        read_halves(
            &self.ctx,
            "vpl",
            &self.acc_buf,
            direct,
            self.n_texels as usize,
            self.half_steps,
        )
        .map_err(gpu_error)
    }

    fn accumulating_pass(&self) -> &'static str {
        "vpl gather (shaders/vpl/gather.wgsl)"
    }
}

/// `vpl`'s passes, WGSL in `shaders/vpl/`.
pub mod shaders {
    use crate::engine::gpu::shaders::{PassShader, SHADOW_VIEW, pass};

    /// Gather the step's lights and VPLs into the lightmap accumulators.
    pub const VPL_GATHER: PassShader = pass!("vpl/gather.wgsl", [SHADOW_VIEW]);
    /// Every pass of `vpl`.
    pub const ALL: &[PassShader] = &[VPL_GATHER];
}

/// `vpl` in the technique table (`technique/table.rs`).
pub const ENTRY: TechniqueEntry = TechniqueEntry {
    default_params: || serde_json::to_value(VplParams::default()).unwrap_or_default(),
    id: "vpl",
    summary: "instant radiosity: reflective shadow maps turned into shadow-mapped virtual point lights (GPU)",
    plan,
    prepare: |inputs, params| Ok(Box::new(Vpl::prepare(inputs, params)?)),
    shaders: shaders::ALL,
    layers: &[OutputLayer::Direct, OutputLayer::Indirect],
    lights: LightSource::ALL,
    check_params: |p| parse_params::<VplParams>("vpl", p)?.validate(),
    unbiased: false,
    alpha: AlphaSupport::Everywhere,
    rounds: false,
    tasks: TaskSplit::ChainsAndRegions(
        "its lights are drawn from a stratified sequence advanced step by step, so a range of steps is not a part of one bake; every texel gathers from the scene's lights alone, so a region's texels (pages or tiles) are the single bake's",
    ),
};

/// What `vpl` runs for a scene and job, and what it leaves out (DESIGN section 6).
pub fn plan(f: &SceneFeatures) -> Plan {
    let mut p = Plan::new("vpl");
    let distant = f.sun || f.directional_lights > 0;
    p.decide(
        "orthographic RSMs + shadow maps (sun, directional lights)",
        distant,
        "the job has a sun or the scene has directional lights",
        "no sun and no directional light",
    );
    let punctual = f.punctual_lights.saturating_sub(f.directional_lights);
    p.decide(
        "cube RSMs + cube shadow maps (point and spot lights)",
        punctual > 0,
        &format!("{punctual} point/spot light(s): six perspective faces each (spot texels outside the cone skipped)"),
        "no point or spot light",
    );
    p.decide(
        "sky: orthographic RSMs + shadow maps along sampled directions",
        f.sky,
        "the job has a sky",
        "the job has no sky",
    );
    p.decide(
        "emitter sampling",
        f.emissive_triangles > 0,
        &format!(
            "{} emissive triangle(s) start VPL paths, sampled by power",
            f.emissive_triangles
        ),
        "no emissive surface",
    );
    let light = f.has_light();
    p.decide(
        "VPL paths (Keller bounces)",
        light,
        "recursive VPL generation with Russian roulette up to max_depth",
        "no light",
    );
    p.decide(
        "VPL shadow maps",
        light,
        "five cube faces per VPL (unless params.visibility is false)",
        "no light, so no VPLs",
    );
    p.run("gather", "every texel sums the step's lights and VPLs");
    p.decide(
        DIRECT_LAYER,
        f.want_direct,
        "direct or indirect output asked for (direct accumulators)",
        "not asked for in outputs",
    );
    if f.want_sh {
        p.leave_out(
            SH_LAYER,
            "asked for, but vpl keeps no directional moments: `sh` outputs fail with vpl (use `path`)",
        );
    } else {
        p.leave_out(SH_LAYER, "not asked for in outputs");
    }
    if f.glossy_materials > 0 {
        p.leave_out(
            "glossy transport",
            "vpl gathers diffuse light only; metallic/roughness are ignored",
        );
    } else {
        p.leave_out("glossy data", "every material is a fully rough dielectric");
    }
    p.error_estimate = "noise only: the clamp's bias and the shadow maps' bias are not in it (docs/vpl.md)".into();
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
            Mirror::of::<GpuLight>("GpuLight", shaders::VPL_GATHER, "Light"),
            Mirror::of::<GpuGatherParams>("GpuGatherParams", shaders::VPL_GATHER, "GatherParams"),
        ]);
    }

    #[test]
    fn params_defaults_and_ranges() {
        let p: VplParams = parse_params("vpl", &serde_json::Value::Null).unwrap();
        assert_eq!(p, VplParams::default());
        p.validate().unwrap();
        for bad in [
            serde_json::json!({"rsm_size": 2}),
            serde_json::json!({"vpls_per_step": 0}),
            serde_json::json!({"clamp": -0.1}),
            serde_json::json!({"clamp": 0.9}),
            serde_json::json!({"max_depth": 0}),
            serde_json::json!({"sky_directions": 65}),
            serde_json::json!({"vpl_map_size": 2048}),
        ] {
            let p: VplParams = parse_params("vpl", &bad).unwrap();
            let e = p.validate().unwrap_err().to_string();
            let name = bad.as_object().unwrap().keys().next().unwrap().clone();
            assert!(e.contains(&name), "{e}");
        }
        assert!(parse_params::<VplParams>("vpl", &serde_json::json!({"unknown": 1})).is_err());
    }

    #[test]
    fn atlas_packing_keeps_tiles_apart() {
        let sizes = [512, 256, 256, 256, 256, 256, 256, 64, 64, 64, 64, 64, 64, 64];
        let l = pack(&sizes, 8192).unwrap();
        for (i, a) in l.rects.iter().enumerate() {
            assert_eq!(a[2], sizes[i]);
            assert!(a[0] + a[2] <= l.width && a[1] + a[2] <= l.height);
            for b in &l.rects[i + 1..] {
                let apart = a[0] + a[2] <= b[0] || b[0] + b[2] <= a[0] || a[1] + a[2] <= b[1] || b[1] + b[2] <= a[1];
                assert!(apart, "{a:?} overlaps {b:?}");
            }
        }
        assert!(pack(&[64; 100_000], 1024).unwrap_err().is_bad_input());
    }
}
