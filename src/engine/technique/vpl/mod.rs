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
//!    *plane* (normal, offset) of the nearest surface per pixel.
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

mod rsm;

use std::f32::consts::PI;
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::api::{
    AlphaSupport, BakeInputs, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry,
    go_on_until, gpu_error, parse_params,
};
use crate::engine::accumulate::{LUMINANCE, Snapshot};
use crate::engine::atlas::SURFACE_OFFSET;
use crate::engine::gpu::directions::{DirectionSequence, Directions, SplitMix64};
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::halves::read_halves;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_of, layout_of};
use crate::engine::gpu::shadow::{
    self, AtlasVertices, ShadowAtlas, ShadowAtlasLayout, ShadowDraw, ShadowView, VIEW_ORTHO, VIEW_PERSPECTIVE,
    cube_faces, shadow_vertices,
};
use crate::engine::gpu::slices::{Aside, Sliced, StepSlicer};
use crate::engine::gpu::texels::GpuTexelGeom;
use crate::engine::gpu::tracer::GpuTracer;
use crate::engine::gpu::{self, GpuContext, RayDevice};
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};
use crate::engine::raytrace::{Tracer, basis, cone_sample, cosine_sample, inset};
use crate::engine::rng::Rng;
use crate::engine::scene::{Hemisphere, LightKind, Lighting, Scene};
use rsm::RsmTracer;

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
    /// half of it). Range 16..=8192; default 512.
    pub shadow_map_size: u32,
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
            shadow_map_size: 512,
            vpl_map_size: 64,
            sky_directions: 4,
            rays: RayDevice::Auto,
        }
    }
}

impl VplParams {
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
        range("shadow_map_size", self.shadow_map_size, 16, 8192)?;
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

impl Vpl {
    pub fn prepare(inputs: BakeInputs, params: &serde_json::Value) -> Result<Self, EngineError> {
        let mut params: VplParams = parse_params("vpl", params)?;
        params.validate()?;
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
        let scene = inputs.scene.clone();
        let atlas = inputs.atlas.clone();
        let lighting = inputs.lighting;

        // Normalised space: the triangles' bounds with room for the texels' sample points
        // (twice their offset), which a region of the grid shares with the whole
        // (`engine::tasks`: a page task's texels are the single bake's, bit for bit).
        let frame = SceneFrame::of_scene(&scene, 2.0 * atlas.surface_offset);
        let (centre, radius) = (frame.centre, frame.radius);

        // Primary lights, fixed for the bake.
        let mut primaries = Vec::new();
        if lighting.sun.is_some_and(|s| s.radiance != Vec3::ZERO) {
            primaries.push(Primary::Sun);
        }
        for (i, l) in scene.lights.iter().enumerate() {
            if l.intensity == Vec3::ZERO {
                continue;
            }
            match l.kind {
                LightKind::Directional => primaries.push(Primary::Directional {
                    dir: l.direction.normalize(),
                    irradiance: l.intensity,
                }),
                LightKind::Point | LightKind::Spot { .. } => primaries.push(Primary::Punctual(i)),
            }
        }
        if lighting.sky.is_some_and(|s| s.radiance != Vec3::ZERO) {
            primaries.extend((0..params.sky_directions).map(|_| Primary::Sky));
        }
        // Shadow views: a map per distant light, six faces per punctual light, five per VPL.
        let mut sizes = Vec::new();
        let mut primary_views = Vec::new();
        for p in &primaries {
            primary_views.push(sizes.len() as u32);
            match p {
                Primary::Punctual(_) => sizes.extend([(params.shadow_map_size / 2).max(1); 6]),
                _ => sizes.push(params.shadow_map_size),
            }
        }
        let vpl_views = sizes.len() as u32;
        if params.visibility {
            sizes.extend(std::iter::repeat_n(
                params.vpl_map_size,
                5 * params.vpls_per_step as usize,
            ));
        }
        let layout = pack(&sizes, ctx.limits.max_texture_dimension_2d)?;

        let emitters: Vec<Emitter> = scene
            .triangles
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let m = scene.material(t);
                let sides = if m.double_sided { 2.0 } else { 1.0 };
                let w = PI as f64 * lum(m.emissive) * t.area() as f64 * sides;
                (w > 0.0 && w.is_finite()).then_some(Emitter {
                    triangle: i as u32,
                    weight: w,
                })
            })
            .collect();
        let emitter_weight = emitters.iter().map(|e| e.weight).sum();

        // GPU resources.
        let n_texels = atlas.texels.len() as u32;
        let storage_need = 2 * n_texels as u64 * 16;
        ctx.check_storage(&format!("vpl: the accumulators of {n_texels} texels"), storage_need)
            .map_err(gpu_error)?;
        let max_lights = primaries.len() as u32 + params.vpls_per_step;
        use wgpu::BufferUsages as U;
        // Per corner: position, the triangle's plane and its alpha inputs (gpu::shadow).
        let vertices = shadow_vertices(&scene, &frame);
        let vertex_buf = ctx.buffer_init("vpl vertices (normalised, with planes)", &vertices, U::VERTEX);
        let geom: Vec<GpuTexelGeom> = atlas
            .texels
            .iter()
            .map(|t| GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal))
            .collect();
        let geom_buf = ctx.buffer_init("vpl texel geometry", &geom, U::STORAGE);
        let lights_buf = ctx.buffer_zeroed(
            "vpl step lights",
            max_lights.max(1) as u64 * std::mem::size_of::<GpuLight>() as u64,
            U::STORAGE | U::COPY_DST,
        );
        let views_buf = ctx.buffer_zeroed(
            "vpl shadow views",
            sizes.len().max(1) as u64 * std::mem::size_of::<ShadowView>() as u64,
            U::STORAGE | U::COPY_DST,
        );
        let gather_buf = ctx.uniform("vpl gather params", &GpuGatherParams::zeroed());
        let acc_buf = ctx.buffer_zeroed(
            "vpl accumulators (even, odd)",
            storage_need,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let direct_acc_buf = ctx.buffer_zeroed(
            "vpl direct accumulators (even, odd)",
            storage_need,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );

        use wgpu::ShaderStages as S;
        let tables = inputs
            .rays
            .gpu_tables(&ctx, "vpl", &inputs.rays.emitters())
            .map_err(gpu_error)?;
        let shadow = ShadowAtlas::new(
            &ctx,
            "vpl shadow",
            layout.width,
            layout.height,
            &views_buf,
            &tables.tables,
            AtlasVertices::Planes,
        )
        .map_err(gpu_error)?;
        let gather_module = ctx.shader(&shaders::VPL_GATHER).map_err(gpu_error)?;
        let gather_binds = [
            Bind::Uniform(&gather_buf),
            Bind::Read(&lights_buf),
            Bind::Read(&views_buf),
            // textureLoad only: Rgba32Float needs no filtering.
            Bind::Texture2d(&shadow.plane_view),
            Bind::Read(&geom_buf),
            Bind::Write(&acc_buf),
            Bind::Write(&direct_acc_buf),
        ];
        let gather_layout = layout_of(&ctx, "vpl gather layout", S::COMPUTE, &gather_binds);
        let gather_pipeline = compute_pipeline(&ctx, "vpl gather", &gather_module, "gather", &gather_layout);
        let gather_bg = group_of(&ctx, "vpl gather bindings", &gather_layout, &gather_binds);
        ctx.take_error("vpl setup").map_err(gpu_error)?;

        let tracer = inputs.rays.tracer();
        let rsm = match params.rays.context("vpl").map_err(gpu_error)? {
            Some(rays_ctx) => {
                // One step's rays: n^2 a distant light, 6 (n/2)^2 a point or spot light.
                let n = params.rsm_size as usize;
                let most: usize = primaries
                    .iter()
                    .map(|p| match p {
                        Primary::Punctual(_) => 6 * (n / 2).max(1).pow(2),
                        _ => n * n,
                    })
                    .sum();
                let capacity = most.clamp(1, rsm::GPU_CHUNK);
                RsmTracer::Gpu(GpuTracer::new(&rays_ctx, "vpl rsm", &inputs.rays, capacity).map_err(gpu_error)?)
            }
            None => RsmTracer::Cpu(tracer.clone()),
        };
        params.rays = match rsm {
            RsmTracer::Gpu(_) => RayDevice::Gpu,
            RsmTracer::Cpu(_) => RayDevice::Cpu,
        };
        let ray_offset = SURFACE_OFFSET * scene.scale();
        Ok(Vpl {
            texel_dispatch: gpu::dispatch_size_64(n_texels),
            directions: Directions::new(DirectionSequence::Stratified, inputs.seed ^ 0x5C1E_D1EC),
            rng: SplitMix64::new(inputs.seed ^ 0x0B1E_55ED_0000_0001),
            ctx,
            params,
            scene,
            tracer,
            rsm,
            lighting,
            seed: inputs.seed,
            want_direct: inputs.want_direct,
            centre,
            radius,
            ray_offset,
            primaries,
            primary_views,
            vpl_views,
            layout,
            emitters,
            emitter_weight,
            steps_done: 0,
            half_steps: [0, 0],
            n_texels,
            max_lights,
            vertex_count: vertices.len() as u32,
            vertex_buf,
            lights_buf,
            views_buf,
            gather_buf,
            acc_buf,
            direct_acc_buf,
            shadow,
            gather_pipeline,
            gather_bg,
            deadline: None,
            progress: None,
            slicer: StepSlicer::new("vpl gather"),
            map_slicer: StepSlicer::per_unit("vpl maps"),
        })
    }

    fn norm(&self, p: Vec3) -> Vec3 {
        (p - self.centre) / self.radius
    }

    fn rect_of(&self, view: u32, kind: u32) -> [u32; 4] {
        let r = self.layout.rects[view as usize];
        [r[0], r[1], r[2], kind]
    }

    /// An orthographic map along `dir` over the normalised unit sphere.
    fn ortho_view(&self, view: u32, dir: Vec3) -> ShadowView {
        let (right, up) = basis(dir);
        ShadowView {
            origin: v4(-dir * MARGIN, 0.0),
            right: v4(right, MARGIN),
            up: v4(up, 0.0),
            fwd: v4(dir, 2.0 * MARGIN),
            rect: self.rect_of(view, VIEW_ORTHO),
        }
    }

    /// The cube faces (first `count` of them) around normalised point `o` in frame
    /// (t, b, n).
    fn cube_views(&self, first: u32, count: usize, o: Vec3, frame: (Vec3, Vec3, Vec3)) -> Vec<ShadowView> {
        let far = o.length() + 2.0 * MARGIN;
        cube_faces(frame.0, frame.1, frame.2)[..count]
            .iter()
            .enumerate()
            .map(|(k, (fwd, right, up))| ShadowView {
                origin: v4(o, CUBE_NEAR),
                right: v4(*right, 0.0),
                up: v4(*up, 0.0),
                fwd: v4(*fwd, far),
                rect: self.rect_of(first + k as u32, VIEW_PERSPECTIVE),
            })
            .collect()
    }

    /// Keller's recursion from one VPL: cosine-distributed rays, Russian roulette by
    /// albedo, up to `max_depth`.
    fn continue_path(&self, start: SurfacePoint, rng: &mut Rng, out: &mut Vec<SurfacePoint>) {
        let mut v = start;
        out.push(v);
        while v.depth < self.params.max_depth {
            let dir = cosine_sample(v.n, rng.next_f32(), rng.next_f32());
            let Some((p, n, albedo)) = surface_hit(
                &self.scene,
                &self.tracer,
                v.p + v.n * self.ray_offset,
                dir,
                f32::INFINITY,
            ) else {
                break;
            };
            let q = albedo.max_element().min(1.0);
            if q <= 0.0 || rng.next_f32() >= q {
                break;
            }
            v = SurfacePoint {
                p,
                n,
                flux: v.flux * albedo / q,
                depth: v.depth + 1,
            };
            out.push(v);
        }
    }

    /// A uniform point on emitter `e` as a depth-0 VPL carrying `scale` x its estimate
    /// of the triangle's emitted flux.
    fn emitter_sample(&self, e: &Emitter, scale: f64, rng: &mut Rng) -> SurfacePoint {
        let tri = &self.scene.triangles[e.triangle as usize];
        let (u1, u2) = (rng.next_f32(), rng.next_f32());
        let s = u1.sqrt();
        let b = inset(Vec3::new(1.0 - s, s * (1.0 - u2), s * u2));
        let double = self.scene.material(tri).double_sided;
        let ng = tri.geometric_normal();
        let n = if double && rng.next_f32() < 0.5 { -ng } else { ng };
        let sides = if double { 2.0 } else { 1.0 };
        let flux = self.scene.emission(tri, b) * (PI * tri.area() * sides);
        SurfacePoint {
            p: tri.point(b),
            n,
            flux: flux * scale as f32,
            depth: 0,
        }
    }

    /// Everything one step lights with: primary lights, RSMs, VPL paths, shadow views.
    fn build_step(&mut self) -> Result<StepLights, EngineError> {
        let step_key = self.rng.next_u64();
        let n_views = self.layout.rects.len();
        let mut views = vec![ShadowView::zeroed(); n_views];
        let mut lights = Vec::with_capacity(self.max_lights as usize);
        let mut draws = Vec::new();
        let mut rsm_rays = Vec::new();
        let r2 = self.radius * self.radius;
        let sky_solid_angle = match self.lighting.sky.map(|s| s.hemisphere) {
            Some(Hemisphere::Full) => 4.0 * PI,
            _ => 2.0 * PI,
        };
        for (slot, primary) in self.primaries.clone().into_iter().enumerate() {
            let view = self.primary_views[slot];
            let key = step_key ^ ((slot as u64 + 1) << 40);
            let distant = match primary {
                Primary::Sun => {
                    let sun = self.lighting.sun.expect("a Sun primary has a sun");
                    let (u1, u2) = (self.rng.next_f64() as f32, self.rng.next_f64() as f32);
                    let towards = cone_sample(-sun.direction.normalize(), sun.cos_half_angle(), u1, u2);
                    Some((-towards, sun.radiance * sun.solid_angle()))
                }
                Primary::Directional { dir, irradiance } => Some((dir, irradiance)),
                Primary::Sky => {
                    let mut w = self.directions.next_direction();
                    if self.lighting.sky.is_some_and(|s| s.hemisphere == Hemisphere::Upper) {
                        // Mirror the lower half up: uniform over the upper hemisphere.
                        w.y = w.y.abs();
                    }
                    let l = self.lighting.sky_radiance(w);
                    Some((-w, l * (sky_solid_angle / self.params.sky_directions as f32)))
                }
                Primary::Punctual(_) => None,
            };
            if let Some((dir, irradiance)) = distant {
                if irradiance == Vec3::ZERO {
                    continue;
                }
                views[view as usize] = self.ortho_view(view, dir);
                draws.push(view);
                lights.push(GpuLight {
                    pos: [0.0; 4],
                    axis_t: [0.0; 4],
                    axis_b: [0.0; 4],
                    axis_n: v4(dir, 0.0),
                    power: v4(irradiance / PI, 0.0),
                    spot: [0.0; 4],
                    info: [LIGHT_DIRECTIONAL, view, 1, 0],
                });
                let disc = (self.centre, self.radius * MARGIN, self.params.rsm_size);
                rsm_rays.extend(rsm::distant_rays(dir, irradiance, disc, (self.seed, key)));
            } else if let Primary::Punctual(i) = primary {
                let l = self.scene.lights[i].clone();
                let spot = matches!(l.kind, LightKind::Spot { .. });
                let frame = if spot {
                    let n = l.direction.normalize();
                    let (t, b) = basis(n);
                    (t, b, n)
                } else {
                    (Vec3::X, Vec3::Y, Vec3::Z)
                };
                let o = self.norm(l.position);
                for (k, v) in self.cube_views(view, 6, o, frame).into_iter().enumerate() {
                    views[view as usize + k] = v;
                    draws.push(view + k as u32);
                }
                let (cos_outer, inv) = match l.kind {
                    LightKind::Spot { inner_cone, outer_cone } => {
                        (outer_cone.cos(), 1.0 / (inner_cone.cos() - outer_cone.cos()).max(1e-3))
                    }
                    _ => (-2.0, 0.0),
                };
                lights.push(GpuLight {
                    pos: v4(o, 0.0),
                    axis_t: v4(frame.0, 0.0),
                    axis_b: v4(frame.1, 0.0),
                    axis_n: v4(frame.2, 0.0),
                    power: v4(l.intensity / (PI * r2), 0.0),
                    spot: [cos_outer, inv, l.range.map_or(0.0, |r| r / self.radius), 0.0],
                    info: [if spot { LIGHT_SPOT } else { LIGHT_POINT }, view, 1, 0],
                });
                let n = (self.params.rsm_size / 2).max(1);
                let faces = cube_faces(frame.0, frame.1, frame.2);
                rsm_rays.extend(rsm::punctual_rays(&self.scene, i, &faces, n, (self.seed, key)));
            }
        }

        let rsm = self.rsm.texels(&self.scene, &rsm_rays)?;

        // Path starts by luminance flux over RSM texels and emitters.
        let m = self.params.vpls_per_step as usize;
        let rsm_weight: f64 = rsm.iter().map(|s| lum(s.flux)).sum();
        let total = rsm_weight + self.emitter_weight;
        let mut vpls: Vec<SurfacePoint> = Vec::new();
        if total > 0.0 && total.is_finite() {
            let mut cdf = Vec::with_capacity(rsm.len() + self.emitters.len());
            let mut acc = 0.0;
            for w in rsm
                .iter()
                .map(|s| lum(s.flux))
                .chain(self.emitters.iter().map(|e| e.weight))
            {
                acc += w;
                cdf.push(acc);
            }
            let picks: Vec<(usize, u64)> = (0..m)
                .map(|k| {
                    let u = self.rng.next_f64() * total;
                    (cdf.partition_point(|&c| c <= u).min(cdf.len() - 1), k as u64)
                })
                .collect();
            let paths: Vec<Vec<SurfacePoint>> = picks
                .par_iter()
                .map(|&(index, k)| {
                    let mut rng = Rng::new(self.seed, step_key, k, 3);
                    let start = if index < rsm.len() {
                        let s = rsm[index];
                        SurfacePoint {
                            flux: s.flux * (total / (m as f64 * lum(s.flux))) as f32,
                            ..s
                        }
                    } else {
                        let e = &self.emitters[index - rsm.len()];
                        self.emitter_sample(e, total / (m as f64 * e.weight), &mut rng)
                    };
                    let mut out = Vec::new();
                    if lum(start.flux) > 0.0 {
                        self.continue_path(start, &mut rng, &mut out);
                    }
                    out
                })
                .collect();
            vpls = paths.into_iter().flatten().collect();
        }
        if vpls.len() > m {
            vpls = self.resample(&vpls, m);
        }

        let clamp2 = self.params.clamp * self.params.clamp;
        for (k, v) in vpls.iter().enumerate() {
            let o = self.norm(v.p);
            let (t, b) = basis(v.n);
            let first = if self.params.visibility {
                let first = self.vpl_views + 5 * k as u32;
                for (f, view) in self.cube_views(first, 5, o, (t, b, v.n)).into_iter().enumerate() {
                    views[first as usize + f] = view;
                    draws.push(first + f as u32);
                }
                first
            } else {
                NO_VIEW
            };
            lights.push(GpuLight {
                pos: v4(o, 0.0),
                axis_t: v4(t, 0.0),
                axis_b: v4(b, 0.0),
                axis_n: v4(v.n, 0.0),
                power: v4(v.flux / (PI * PI * r2), clamp2),
                spot: [0.0; 4],
                info: [LIGHT_VPL, first, u32::from(v.depth == 0), 0],
            });
        }
        Ok(StepLights { lights, views, draws })
    }

    /// `m` VPLs drawn from `vpls` with probability proportional to luminance flux, each
    /// carrying total / m; a VPL drawn k times is kept once with k times that.
    fn resample(&mut self, vpls: &[SurfacePoint], m: usize) -> Vec<SurfacePoint> {
        let mut cdf = Vec::with_capacity(vpls.len());
        let mut acc = 0.0;
        for v in vpls {
            acc += lum(v.flux);
            cdf.push(acc);
        }
        let total = acc;
        let mut counts = std::collections::BTreeMap::new();
        for _ in 0..m {
            let u = self.rng.next_f64() * total;
            *counts
                .entry(cdf.partition_point(|&c| c <= u).min(vpls.len() - 1))
                .or_insert(0u32) += 1;
        }
        counts
            .into_iter()
            .map(|(i, k)| {
                let v = vpls[i];
                SurfacePoint {
                    flux: v.flux * (total * k as f64 / (m as f64 * lum(v.flux))) as f32,
                    ..v
                }
            })
            .collect()
    }

    /// One step: the lights on the CPU, the maps, then the gather over every texel,
    /// whole, or in slices in a watched bake while steps may be long (the gather is the
    /// part that grows with the level: 1.1 s of a step at 1.46 M texels on lavapipe). A
    /// step stopped between slices puts back its half, its random stream and its
    /// directions, so it adds nothing and the next step is the one it would have been.
    fn run_step(&mut self) -> Result<(), EngineError> {
        let parity = (self.steps_done % 2) as usize;
        let before = (self.rng.clone(), self.directions.clone());
        let step = self.build_step()?;
        let k = self.half_steps[parity] + 1;
        let q = &self.ctx.queue;
        if !step.lights.is_empty() {
            q.write_buffer(&self.lights_buf, 0, bytemuck::cast_slice(&step.lights));
        }
        if !step.views.is_empty() {
            q.write_buffer(&self.views_buf, 0, bytemuck::cast_slice(&step.views));
        }
        let mut params = GpuGatherParams {
            misc: [parity as u32, self.n_texels, step.lights.len() as u32, 0],
            bias: [1.0 / k as f32, NORMAL_OFFSET_PX, 0.0, 0.0],
            slice: [0, self.n_texels, 0, 0],
        };
        let draws: Vec<ShadowDraw> = step
            .draws
            .iter()
            .map(|&v| {
                let tile = self.layout.rects[v as usize];
                ShadowDraw {
                    view: v,
                    tile,
                    rows: tile[2],
                }
            })
            .collect();
        let gather = |encoder: &mut wgpu::CommandEncoder, size: (u32, u32)| {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("vpl gather"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.gather_pipeline);
            pass.set_bind_group(0, &self.gather_bg, &[]);
            pass.dispatch_workgroups(size.0, size.1, 1);
        };
        let watched = self.deadline.is_some() || self.progress.is_some();
        let progress = self.progress.clone();
        let mut go_on = go_on_until(self.deadline, progress.as_ref());
        if self.slicer.slices(watched) {
            // The maps first, in slices of whole maps (each one the whole scene drawn:
            // 0.17 s a map for a 1M-triangle level on lavapipe, 165 maps a step by
            // default with a sun and a sky), nothing to put back: the atlas is redrawn
            // every step. They are the step's first half of progress, the gather its second.
            let mut first_half = |done: u64, of: u64| go_on(done, 2 * of);
            let done = self
                .shadow
                .render_sliced(
                    &self.ctx,
                    &mut self.map_slicer,
                    &self.vertex_buf,
                    self.vertex_count,
                    &draws,
                    &mut first_half,
                )
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("vpl: the deadline passed or a stop was asked mid-step; the step is undone");
                (self.rng, self.directions) = before;
                return Ok(());
            }
            let aside = [
                Aside::half(&self.acc_buf, parity),
                Aside::half(&self.direct_acc_buf, parity),
            ];
            let mut submit = |first: u64, count: u64| {
                params.slice = [first as u32, count as u32, 0, 0];
                q.write_buffer(&self.gather_buf, 0, bytemuck::bytes_of(&params));
                Ok(self
                    .ctx
                    .submit_compute("vpl gather", &self.gather_pipeline, &self.gather_bg, count as u32))
            };
            let mut second_half = |done: u64, of: u64| go_on(of + done, 2 * of);
            let done = self
                .slicer
                .run(&self.ctx, self.n_texels as u64, &aside, &mut submit, &mut second_half)
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("vpl: the deadline passed or a stop was asked mid-step; the step is undone");
                (self.rng, self.directions) = before;
                return Ok(());
            }
        } else {
            let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("vpl step"),
            });
            if !draws.is_empty() {
                self.shadow
                    .render(&mut encoder, &self.vertex_buf, self.vertex_count, draws.iter().copied());
            }
            q.write_buffer(&self.gather_buf, 0, bytemuck::bytes_of(&params));
            gather(&mut encoder, self.texel_dispatch);
            q.submit([encoder.finish()]);
            self.slicer.returned_whole();
        }
        self.half_steps[parity] = k;
        self.steps_done += 1;
        self.ctx.take_error("vpl step").map_err(gpu_error)
    }
}

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
