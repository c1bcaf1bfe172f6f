//! `sdf`: sky light and ambient occlusion from a signed-distance volume of the scene
//! (Evans 2006, `shared/seeds/sdf-skylight-dynamic-scenes.md`).
//!
//! # What
//! Incident sky irradiance / pi at every valid texel (DESIGN section 2) under the job's
//! uniform sky, with the sky's visibility approximated from a distance field. It is an
//! approximation with a calibrated error, not a converging estimator: more steps only
//! average the sample-distance jitter away.
//!
//! # How
//! 1. *Voxelise* (`shaders/sdf/voxelize.wgsl`): a grid of `resolution` voxels along the
//!    scene's longest axis (cubic voxels, the other axes as many as they need, two voxels
//!    of padding per side). One workgroup per triangle seeds every voxel whose centre
//!    lies within half a voxel diagonal of the triangle (conservative; see the shader).
//! 2. *Distance transform* (`shaders/sdf/flood.wgsl`): 3D jump flooding (Rong & Tan
//!    2006) with steps N/2 .. 1 and one more step of 1 ("JFA+1"), where a seed is a
//!    triangle and voxels compare exact point-triangle distances (Ericson 5.1.5). Chosen
//!    over the seed's CPU dead reckoning (section 9.7) and over blurring a binary image:
//!    it runs on the GPU in log2(N) + 1 passes, and the distance it ends with is exact to
//!    the seed triangle (not a voxel-quantised or chamfer distance), so an open plane
//!    reads its exact distance and C = 1 there. Jump flooding can miss the true nearest
//!    triangle in rare configurations; the error is then the gap between two triangles'
//!    distances, small next to the voxel size. Each voxel remembers the last four seeds
//!    it evaluated, since neighbouring seeds repeat (1.15-1.2x faster, same field).
//!    Sign: negative behind the nearest triangle's plane (its geometric normal). Correct
//!    at convex edges (a point outside an edge is in front of both faces), exact for a
//!    plane (the field stays linear across it, so trilinear lookups and box-filtered mips
//!    reproduce it); wrong where two nearest triangles disagree (thin sheets seen edge-on,
//!    non-manifold meshes): unsigned distance would be as good for samples in free space
//!    but cannot tell "inside a wall" from "near a wall", which is what makes a sample
//!    that pierced an occluder count as occluded.
//! 3. *Dynamic shapes* (`shaders/sdf/dynamic.wgsl`, seed section 9.8): analytic boxes and
//!    ellipsoids from the job's `dynamic` param, min-composited into level 0. The static
//!    field is kept, so [`Sdf::set_dynamic`] moves them by rerunning only this pass and
//!    the mips.
//! 4. *Mips* (`shaders/sdf/mips.wgsl`, seed section 9.6): box-filtered 2x2x2 means,
//!    levels up to the sample count (at most 8).
//! 5. *Sky* (`shaders/sdf/sky.wgsl`, seed section 9.6): per texel, samples at
//!    d_i = h 2^(i + u) along N' = normalize(N + alpha U), sample i from mip
//!    min(i, levels - 1), and
//!    C = min(exp(k S), 1) with S = sum_i min(D_i - d_i, 0) / w_i: the seed's
//!    C = exp(k sum SDF + d_i) in our sign convention (outside positive). The texel gets
//!    L_sky F(N) C, F the unoccluded fraction of a cosine-weighted hemisphere that sees the
//!    sky. u in [-1/2, 1/2) is jittered per texel and step, so even and odd steps are two
//!    estimates of the jitter-averaged C (DESIGN section 4).
//! 6. *Calibration* (`Sdf::calibrate`): `calibration_texels` texels, each with
//!    `calibration_rays` cosine-distributed CPU rays (the `path` reference's sky
//!    visibility, dynamic shapes included), against the GPU's sums S for 9 alphas x 8
//!    fixed jitters; k is fitted per alpha by least squares, the best pair is kept and
//!    reported in `params().calibration`.
//!
//! # Departures from the seed
//! - Exact, signed, GPU distance transform instead of the seed's CPU dead reckoning or
//!   blurred binary image; storage buffers with hand-written trilinear lookups instead of
//!   a volume texture laid out in slices (portable: no filterable float32 textures).
//! - The open-sky factor F(N) (the seed has no N.L term and relies on the bent normal
//!   alone): a vertical wall under the upper sky reads 1/2 exactly, not 1.
//! - Each term is clamped to <= 0: free space cannot make a point "more open than open"
//!   (trilinear and mip errors near edges would otherwise cancel real occlusion).
//! - k and alpha are fitted per scene against ray-cast visibility, not chosen by eye.
//! - `weighting`: `distance` (default) divides term i by d_i, so every scale counts
//!   alike; `voxel` divides by the voxel size (the seed's plain sum). Fitted RMS on the
//!   sphere over a plane: 0.014 against 0.024.
//! - Colour bleed (section 9.9) scales each channel's terms by (1 - bleed albedo) of the
//!   surface nearest the sample instead of adding a per-object constant; off by default.
//!
//! 7. *Other light* (`engine::gpu::direct_light`, issue 21): the sun, directional, point
//!    and spot lights and emitters are not sky light, so the volume has nothing to say
//!    about them: the shared direct-light module estimates their E/pi per texel with
//!    shadow rays on the GPU BVH (`light_samples` a step, light sampling only) and, with
//!    `bounce` (default), the fraction h of each texel's cosine-weighted hemisphere that
//!    sees a surface (one ray per sample).
//! 8. *Bounce* of that light, sdf's own model (the obscurance seed's ambient closure,
//!    since sdf has no transport between surfaces): B1 = sum(A rho D) / sum(A), the
//!    area-weighted mean outgoing radiance of the directly lit surfaces, closed over
//!    further bounces as B = B1 / (1 - c R_ave), c the area-weighted mean of h; each
//!    texel adds h B to its indirect light. Exact in a closed room of one albedo (the
//!    furnace: tests/direct_light.rs), zero on open ground (h = 0); light does not
//!    prefer the room it was emitted in (one ambient for the whole scene). Computed per
//!    half from that half's estimates, so the halves stay independent.
//!
//! Split bakes (`engine::tasks`, issue 25): a task may bake one region of the grid and get
//! the single bake's texels there. The volume's frame is the triangles' and the dynamic
//! shapes' (not the texels'), the sky jitter and the shared direct light's streams are
//! keyed by the texel's pixel, the calibration draws its texels over the whole grid by a
//! key of their pixel (`calibrate`), and the bounce's B is closed from sums over the bake's
//! texels (`engine::ambient`), which the merge closes over every region
//! (`Technique::ambient`: the sums and each texel's h per half).
//!
//! A step runs the shared direct light first, then the sky pass. In a bake with a time
//! limit or a watcher, the direct light's step (the long one: the sun's shadow rays over
//! every texel) may run in slices of about 50 ms and be stopped and undone between two
//! (`TexelRayPass::step_watched`); the sky pass then does not run, so the step adds
//! nothing to either half.
//!
//! # Limits
//! - The sky's own bounce only through `bleed`; the bounce of the other light is one
//!   scene-wide ambient (above), so a dark room beside a lit one gets the same ambient
//!   (docs/stability.md measures it).
//! - The volume covers the scene's bounds: detail smaller than a voxel is blurred, and
//!   occluders outside the volume (dynamic shapes moved out) are not seen.
//! - The model is a heuristic: its error against the true visibility is what the
//!   calibration reports (docs/sdf.md has the measured figures).
//! - The bleed-free visibility is the `ao.Y` layer (`Technique::ao`) and, times L_sky,
//!   the `direct` layer.
//!
//! Memory: 24 B a voxel (two u32 seed grids, the f32x4 static field) plus 16 B per mip
//! element (about 1.14 x the voxels): 85 MiB at 128^3, far less for flat scenes; the
//! whole mip chain must fit one storage binding (checked, a clear error otherwise).
//! Randomness: PCG hash per texel and step on the GPU (gpu/common.wgsl); the calibration's
//! rays use [`Rng`] streams keyed by the bake seed. Precision: f32 everywhere, geometry in
//! normalised scene space (p - centre) / radius as in `sdb`, so scale and translation do
//! not change the field.

use std::sync::Arc;
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use glam::{DVec3, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

mod calibrate;

use super::api::{
    AlphaSupport, BakeInputs, EngineError, LightSource, StepProgress, TaskSplit, Technique, TechniqueEntry,
    go_on_until, gpu_error, parse_params,
};
use crate::engine::accumulate::{HalfEstimate, Snapshot};
use crate::engine::ambient::{AmbientHalf, AmbientSums};
use crate::engine::gpu::direct_light::{DirectHalf, DirectLight, MAX_SAMPLES_PER_STEP};
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_of, layout_of};
use crate::engine::gpu::scene_lights::LightSources;
use crate::engine::gpu::slices::{Aside, Sliced, StepSlicer};
use crate::engine::gpu::texels::GpuTexelGeom;
use crate::engine::gpu::{self, GpuContext, GpuError};
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};
use crate::engine::raytrace::cosine_sample;
use crate::engine::rng::Rng;
use crate::engine::scene::Hemisphere;
#[cfg(test)]
use calibrate::{fit_k, ray_hits_shape};

// ---------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------

/// How each occlusion term is normalised before the sum.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Weighting {
    /// (D_i - d_i) / h: the seed's plain sum, in voxels.
    Voxel,
    /// (D_i - d_i) / d_i: each sample as a fraction of its own distance (default: on the
    /// sphere over a plane its fitted RMS error is 0.014 against the seed sum's 0.024).
    #[default]
    Distance,
}

fn grey() -> [f32; 3] {
    [0.5; 3]
}

/// An axis-aligned box (world coordinates, metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxShape {
    pub centre: [f64; 3],
    pub half: [f32; 3],
    /// Only used by colour bleed; default 0.5 grey.
    #[serde(default = "grey")]
    pub albedo: [f32; 3],
}

/// An axis-aligned ellipsoid (world coordinates, metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EllipsoidShape {
    pub centre: [f64; 3],
    pub radii: [f32; 3],
    #[serde(default = "grey")]
    pub albedo: [f32; 3],
}

/// A dynamic object: an analytic SDF composited into the volume (seed section 9.8).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum DynamicShape {
    Box(BoxShape),
    Ellipsoid(EllipsoidShape),
}

impl DynamicShape {
    fn centre(&self) -> DVec3 {
        match self {
            DynamicShape::Box(b) => DVec3::from_array(b.centre),
            DynamicShape::Ellipsoid(e) => DVec3::from_array(e.centre),
        }
    }
    fn size(&self) -> Vec3 {
        match self {
            DynamicShape::Box(b) => Vec3::from_array(b.half),
            DynamicShape::Ellipsoid(e) => Vec3::from_array(e.radii),
        }
    }
    fn albedo(&self) -> Vec3 {
        match self {
            DynamicShape::Box(b) => Vec3::from_array(b.albedo),
            DynamicShape::Ellipsoid(e) => Vec3::from_array(e.albedo),
        }
    }
    fn is_box(&self) -> bool {
        matches!(self, DynamicShape::Box(_))
    }
}

/// Most dynamic shapes a bake takes (the composite pass loops over all of them per voxel).
pub const MAX_DYNAMIC: usize = 64;

/// What the calibration measured (output only: ignored when a job passes it back).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationReport {
    pub texels: u32,
    pub rays: u32,
    /// RMS difference of the sky visibility F C from the rays' estimate, with the fit.
    pub rms_fitted: f32,
    /// The same with no occlusion at all (C = 1): how much the fit explains.
    pub rms_unoccluded: f32,
    /// The rays' own noise (RMS over texels of sqrt(V (1 - V) / rays)): the floor the
    /// fit's figure includes.
    pub rms_ray_noise: f32,
    /// Mean signed difference (fit minus rays).
    pub mean_bias: f32,
}

/// `sdf` parameters (the job's `params` object). Unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SdfParams {
    /// Voxels along the scene's longest axis, 16..=512; default 128 (the seed's 128^3).
    pub resolution: u32,
    /// Samples along the bent normal, 1..=10, at 1, 2, 4, ... voxels; default 6 (out to
    /// a quarter of a 128-voxel volume; a 7th sample reads mips so coarse that the
    /// borders of the scene leak into them, docs/sdf.md).
    pub samples: u32,
    /// Term normalisation: `distance` (default) or `voxel` (the seed's sum).
    pub weighting: Weighting,
    /// Contrast k in C = exp(k S), in (0, 100]. Absent: fitted by the calibration.
    pub k: Option<f32>,
    /// Sky weighting alpha in N' = N + alpha U, in [0, 1]. Absent: fitted.
    pub alpha: Option<f32>,
    /// Colour bleed in [0, 1] (seed section 9.9); default 0 (pure sky visibility).
    pub bleed: f32,
    /// Texels the calibration compares, 0..=4096 (0: no calibration, k and alpha default
    /// to 0.05 and 0.5 unless given); default 256.
    pub calibration_texels: u32,
    /// Rays per calibration texel, 1..=4096; default 64.
    pub calibration_rays: u32,
    /// Analytic dynamic objects, at most 64.
    pub dynamic: Vec<DynamicShape>,
    /// Bounce the shared direct light (sun, directional, point and spot lights, emitters)
    /// with the one-ambient model of the module doc; default true. False: that light is
    /// direct only (the sky's bounce is `bleed` either way).
    pub bounce: bool,
    /// Next-event estimates per texel and step of the shared direct light, 1..=64;
    /// default 4.
    pub light_samples: u32,
    /// Output only: the calibration's fit (ignored on input).
    pub calibration: Option<CalibrationReport>,
}

/// k and alpha when nothing is fitted.
const DEFAULT_K: f32 = 0.05;
const DEFAULT_ALPHA: f32 = 0.5;

impl Default for SdfParams {
    fn default() -> Self {
        SdfParams {
            resolution: 128,
            samples: 6,
            weighting: Weighting::Distance,
            k: None,
            alpha: None,
            bleed: 0.0,
            calibration_texels: 256,
            calibration_rays: 64,
            dynamic: Vec::new(),
            bounce: true,
            light_samples: 4,
            calibration: None,
        }
    }
}

impl SdfParams {
    pub fn validate(&self) -> Result<(), EngineError> {
        let bad = |m: String| Err(EngineError::BadInput(format!("sdf parameter {m}")));
        if !(16..=512).contains(&self.resolution) {
            return bad(format!("resolution: {} is outside 16..=512", self.resolution));
        }
        if !(1..=10).contains(&self.samples) {
            return bad(format!("samples: {} is outside 1..=10", self.samples));
        }
        if !(1..=MAX_SAMPLES_PER_STEP).contains(&self.light_samples) {
            return bad(format!(
                "light_samples: {} is outside 1..={MAX_SAMPLES_PER_STEP}",
                self.light_samples
            ));
        }
        if let Some(k) = self.k
            && !(k > 0.0 && k <= 100.0)
        {
            return bad(format!("k: {k} is outside (0, 100]"));
        }
        if let Some(a) = self.alpha
            && !(0.0..=1.0).contains(&a)
        {
            return bad(format!("alpha: {a} is outside [0, 1]"));
        }
        if !(0.0..=1.0).contains(&self.bleed) {
            return bad(format!("bleed: {} is outside [0, 1]", self.bleed));
        }
        if self.calibration_texels > 4096 {
            return bad(format!("calibration_texels: {} is above 4096", self.calibration_texels));
        }
        if !(1..=4096).contains(&self.calibration_rays) {
            return bad(format!(
                "calibration_rays: {} is outside 1..=4096",
                self.calibration_rays
            ));
        }
        if self.dynamic.len() > MAX_DYNAMIC {
            return bad(format!("dynamic: {} shapes, at most {MAX_DYNAMIC}", self.dynamic.len()));
        }
        for (i, s) in self.dynamic.iter().enumerate() {
            if !s.centre().is_finite() {
                return bad(format!("dynamic[{i}].centre must be finite"));
            }
            let size = s.size();
            if !(size.is_finite() && size.min_element() > 0.0) {
                let name = if s.is_box() { "half" } else { "radii" };
                return bad(format!(
                    "dynamic[{i}].{name} must be finite and > 0, got {:?}",
                    size.to_array()
                ));
            }
            let a = s.albedo();
            if !(a.is_finite() && a.min_element() >= 0.0 && a.max_element() <= 1.0) {
                return bad(format!("dynamic[{i}].albedo must be in [0, 1]"));
            }
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// GPU-side layouts: the structs of shaders/sdf/*.wgsl, sizes checked against naga's layout
// (`gpu_layouts_match_the_shaders`); texels are gpu::texels' `GpuTexelGeom`
// ---------------------------------------------------------------------------------------

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuVolume {
    origin: [f32; 4],
    dims: [u32; 4],
    offsets: [[u32; 4]; 2],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuTri {
    a: [f32; 4],
    b: [f32; 4],
    c: [f32; 4],
    n: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuMisc {
    misc: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuShape {
    centre: [f32; 4],
    size: [f32; 4],
    albedo: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct GpuSkyParams {
    sky: [f32; 4],
    fit: [f32; 4],
    misc: [u32; 4],
    cal: [u32; 4],
    alphas: [[f32; 4]; 4],
    /// The sky step's first texel and texel count (a sliced step, `gpu::slices`).
    slice: [u32; 4],
}

/// Alphas the calibration tries.
const CAL_ALPHAS: [f32; 9] = [0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0];
/// Fixed jitters per alpha: the calibration fits the jitter-averaged C the steps converge to.
const CAL_JITTERS: u32 = 8;
/// Padding voxels on each side of the scene's bounds.
const PAD: u32 = 2;
const MAX_LEVELS: u32 = 8;

/// The volume's layout: origin and voxel size (normalised space), dims, mip offsets.
#[derive(Debug, Clone)]
pub struct VolumeLayout {
    pub origin: Vec3,
    pub voxel: f32,
    pub dims: [u32; 3],
    pub levels: u32,
    pub offsets: Vec<u32>,
    /// Elements in all levels together.
    pub total: u32,
}

impl VolumeLayout {
    /// A grid of `resolution` voxels along the longest axis of [lo, hi], padded.
    pub fn new(lo: Vec3, hi: Vec3, resolution: u32, samples: u32) -> Self {
        let extent = (hi - lo).max(Vec3::ZERO);
        let longest = extent.max_element().max(1e-6);
        let voxel = longest / (resolution - 2 * PAD) as f32;
        let dims = extent
            .to_array()
            .map(|e| (((e / voxel).ceil() as u32) + 2 * PAD).clamp(2 * PAD + 1, resolution));
        let size = Vec3::new(dims[0] as f32, dims[1] as f32, dims[2] as f32) * voxel;
        let origin = (lo + hi) * 0.5 - size * 0.5;
        let max_dim = dims.into_iter().max().unwrap_or(1);
        let mut levels = 1;
        while levels < samples.min(MAX_LEVELS) && (max_dim >> levels) >= 2 {
            levels += 1;
        }
        let mut offsets = Vec::new();
        let mut total = 0u32;
        for l in 0..levels {
            offsets.push(total);
            let d = Self::level_dims_of(dims, l);
            total += d[0] * d[1] * d[2];
        }
        VolumeLayout {
            origin,
            voxel,
            dims,
            levels,
            offsets,
            total,
        }
    }

    fn level_dims_of(dims: [u32; 3], l: u32) -> [u32; 3] {
        dims.map(|d| d.div_ceil(1 << l).max(1))
    }

    pub fn voxels(&self) -> u32 {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    /// GPU memory of the volume: two seed grids (4 B a voxel), the static field and the
    /// composited mip chain (16 B an element).
    pub fn bytes(&self) -> u64 {
        let v = self.voxels() as u64;
        2 * 4 * v + 16 * v + 16 * self.total as u64
    }

    fn gpu(&self) -> GpuVolume {
        let mut offsets = [[0u32; 4]; 2];
        for (l, o) in self.offsets.iter().enumerate() {
            offsets[l / 4][l % 4] = *o;
        }
        GpuVolume {
            origin: [self.origin.x, self.origin.y, self.origin.z, self.voxel],
            dims: [self.dims[0], self.dims[1], self.dims[2], self.levels],
            offsets,
        }
    }
}

// ---------------------------------------------------------------------------------------
// The technique
// ---------------------------------------------------------------------------------------

/// Wall-clock times of the preparation (seconds), for docs/performance.md.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct BuildTimings {
    /// Voxelise + flood + resolve + composite + mips, GPU finished.
    pub volume: f64,
    /// CPU rays and the fit (GPU sums included).
    pub calibration: f64,
}

struct SdfGpu {
    ctx: Arc<GpuContext>,
    layout: VolumeLayout,
    /// Normalisation: p_norm = (p - centre) / scale (scene-local coordinates).
    centre: Vec3,
    scale: f32,
    origin_offset: DVec3,
    vol_buf: wgpu::Buffer,
    shapes_buf: wgpu::Buffer,
    dyn_params: wgpu::Buffer,
    acc_buf: wgpu::Buffer,
    sky_params: wgpu::Buffer,
    dyn_pipeline: wgpu::ComputePipeline,
    dyn_bg: wgpu::BindGroup,
    mips_pipeline: wgpu::ComputePipeline,
    mips_bgs: Vec<wgpu::BindGroup>,
    sky_pipeline: wgpu::ComputePipeline,
    sky_bg: wgpu::BindGroup,
    cal_pipeline: wgpu::ComputePipeline,
    cal_layout: wgpu::BindGroupLayout,
    levels_buf: wgpu::Buffer,
}

/// `sdf` as a [`Technique`]. Accumulators stay on the GPU; read back at snapshots only.
pub struct Sdf {
    params: SdfParams,
    n_texels: u32,
    sky: Vec3,
    upper: bool,
    want_direct: bool,
    seed: u64,
    steps_done: u64,
    half_steps: [u64; 2],
    /// Sky visibility per valid texel as of the last snapshot (the `ao.Y` layer).
    last_ao: Option<Vec<f32>>,
    /// The shared direct light (everything but the sky), when the scene and job have any.
    direct: Option<DirectLight>,
    /// Per valid texel: albedo and area, for the bounce's scene averages.
    texel_albedo: Vec<Vec3>,
    texel_area: Vec<f32>,
    /// The bounce's ambient of the last snapshot's halves (`Technique::ambient`).
    last_ambient: Option<[AmbientHalf; 2]>,
    k: f32,
    alpha: f32,
    gpu: Option<SdfGpu>,
    /// The device the sky pass and the shared direct light run on (None: nothing to bake).
    device: Option<Arc<GpuContext>>,
    /// The bake's time limit and watcher: under them the sky pass runs in slices of
    /// texels, and the shared direct light's step, the long part of a step (the sun's
    /// shadow rays: 13.7 s of a 14 s step on the Kenney level at 2048² on lavapipe, the
    /// sky 0.3 s), runs sliced when long; either can be stopped and undone.
    deadline: Option<Instant>,
    progress: Option<StepProgress>,
    /// The sky pass's slices (`gpu::slices`).
    slicer: StepSlicer,
    timings: BuildTimings,
    notes: Vec<String>,
}

fn run_pass(
    encoder: &mut wgpu::CommandEncoder,
    label: &str,
    pipeline: &wgpu::ComputePipeline,
    bg: &wgpu::BindGroup,
    groups: (u32, u32),
) {
    let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
        label: Some(label),
        timestamp_writes: None,
    });
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bg, &[]);
    pass.dispatch_workgroups(groups.0, groups.1, 1);
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE;
const CS: wgpu::ShaderStages = wgpu::ShaderStages::COMPUTE;

impl Sdf {
    pub fn prepare(inputs: BakeInputs, params: &serde_json::Value) -> Result<Self, EngineError> {
        let mut params: SdfParams = parse_params("sdf", params)?;
        params.validate()?;
        params.calibration = None;
        let sky = inputs.lighting.sky.filter(|s| s.radiance != Vec3::ZERO);
        let notes = Vec::new();
        let scene = &inputs.scene;
        let atlas = &inputs.atlas;
        // Everything but the sky comes from the shared direct-light module (GPU rays).
        let has_other_light = !scene.lights.is_empty()
            || inputs.lighting.sun.is_some()
            || scene.triangles.iter().any(|t| scene.material(t).emissive != Vec3::ZERO);
        let ctx = if (sky.is_some() || has_other_light) && !atlas.texels.is_empty() {
            Some(gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?)
        } else {
            None
        };
        let direct = match &ctx {
            Some(ctx) if has_other_light => DirectLight::new(
                ctx.clone(),
                "sdf",
                &inputs.rays,
                atlas,
                &inputs.lighting,
                inputs.seed,
                LightSources::ALL,
                None,
                params.light_samples,
                params.bounce,
            )
            .map_err(gpu_error)?,
            _ => None,
        };
        let texel_area: Vec<f32> = atlas.texels.iter().map(|t| t.size * t.size).collect();
        let mut sdf = Sdf {
            k: params.k.unwrap_or(DEFAULT_K),
            alpha: params.alpha.unwrap_or(DEFAULT_ALPHA),
            params,
            n_texels: inputs.atlas.texels.len() as u32,
            sky: sky.map_or(Vec3::ZERO, |s| s.radiance),
            upper: sky.is_some_and(|s| s.hemisphere == Hemisphere::Upper),
            want_direct: inputs.want_direct,
            seed: inputs.seed,
            steps_done: 0,
            half_steps: [0, 0],
            last_ao: None,
            direct: None,
            texel_albedo: atlas.texels.iter().map(|t| t.albedo).collect(),
            texel_area,
            last_ambient: None,
            gpu: None,
            device: ctx.clone(),
            deadline: None,
            progress: None,
            slicer: StepSlicer::new("sdf sky"),
            timings: BuildTimings::default(),
            notes,
        };
        sdf.direct = direct;
        // No sky, or nothing to bake: no volume (the plan lists it as left out); the
        // shared direct light and its bounce need none.
        let Some(ctx) = ctx.filter(|_| sky.is_some()) else {
            return Ok(sdf);
        };
        let t0 = Instant::now();
        sdf.gpu = Some(sdf.build(ctx, &inputs).map_err(gpu_error)?);
        sdf.timings.volume = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        if sdf.params.calibration_texels > 0 && (sdf.params.k.is_none() || sdf.params.alpha.is_none()) {
            let report = sdf.calibrate(&inputs).map_err(gpu_error)?;
            sdf.params.calibration = Some(report);
        }
        sdf.timings.calibration = t1.elapsed().as_secs_f64();
        tracing::info!(
            k = sdf.k,
            alpha = sdf.alpha,
            volume_s = sdf.timings.volume,
            calibration_s = sdf.timings.calibration,
            calibration = ?sdf.params.calibration,
            "sdf prepared"
        );
        Ok(sdf)
    }

    /// The fitted (or given) contrast k and sky weighting alpha.
    pub fn fit(&self) -> (f32, f32) {
        (self.k, self.alpha)
    }

    pub fn timings(&self) -> BuildTimings {
        self.timings
    }

    /// The volume's layout (None when no volume was built: no sky and nothing to bounce).
    pub fn layout(&self) -> Option<&VolumeLayout> {
        self.gpu.as_ref().map(|g| &g.layout)
    }

    pub fn notes(&self) -> &[String] {
        &self.notes
    }

    fn build(&self, ctx: Arc<GpuContext>, inputs: &BakeInputs) -> Result<SdfGpu, GpuError> {
        let scene = &inputs.scene;
        let atlas = &inputs.atlas;
        let origin_offset = scene.origin_offset;
        // Bounds: triangles and every dynamic shape; not the texels, so a region's task
        // (engine::tasks), which has only its region's, builds the whole bake's volume
        // (texel points lie on the triangles, pushed off by the atlas's small surface
        // offset, which the volume's two voxels of padding hold). The movable shapes'
        // bounds count, so a shape moved to the scene's edge stays inside the volume.
        let shapes = self.params.dynamic.iter().flat_map(|s| {
            let c = (s.centre() - origin_offset).as_vec3();
            [c - s.size(), c + s.size()]
        });
        let frame = SceneFrame::of_points(scene.triangles.iter().flat_map(|t| t.p).chain(shapes));
        let (lo, hi, centre, scale) = (frame.lo, frame.hi, frame.centre, frame.radius);
        let norm = |p: Vec3| frame.norm(p);
        let layout = VolumeLayout::new(norm(lo), norm(hi), self.params.resolution, self.params.samples);
        ctx.check_storage(
            &format!("sdf: a volume of {:?} voxels (parameter `resolution`)", layout.dims),
            16 * layout.total as u64,
        )?;

        // Triangles with area (zero-area ones have no nearest point to speak of).
        let tris: Vec<GpuTri> = scene
            .triangles
            .iter()
            .filter(|t| t.cross().length() > 0.0)
            .map(|t| {
                let albedo = scene.albedo(t, Vec3::splat(1.0 / 3.0));
                let [a, b, c] = t.p.map(norm);
                let n = (b - a).cross(c - a).normalize_or_zero();
                GpuTri {
                    a: [a.x, a.y, a.z, albedo.x],
                    b: [b.x, b.y, b.z, albedo.y],
                    c: [c.x, c.y, c.z, albedo.z],
                    n: [n.x, n.y, n.z, 0.0],
                }
            })
            .collect();
        let n_tris = tris.len() as u32;
        let texels: Vec<GpuTexelGeom> = atlas
            .texels
            .iter()
            .map(|t| {
                // position.w: the pixel's bits, which the sky pass keys its jitter by
                // (shaders/sdf/sky.wgsl), so a region's task jitters as a whole bake does.
                let mut g = GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal);
                g.position[3] = f32::from_bits(t.pixel);
                g
            })
            .collect();

        let voxels = layout.voxels();
        let vol_buf = ctx.uniform("sdf volume", &layout.gpu());
        let tri_buf = ctx.buffer_init("sdf triangles", &tris, STORAGE);
        let seed_bufs = [
            ctx.buffer_zeroed("sdf seeds A", 4 * voxels as u64, STORAGE),
            ctx.buffer_zeroed("sdf seeds B", 4 * voxels as u64, STORAGE),
        ];
        let base_buf = ctx.buffer_zeroed("sdf static field", 16 * voxels as u64, STORAGE);
        let levels_buf = ctx.buffer_zeroed(
            "sdf levels",
            16 * layout.total as u64,
            STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let shapes_buf = ctx.buffer_zeroed(
            "sdf dynamic shapes",
            (MAX_DYNAMIC * std::mem::size_of::<GpuShape>()) as u64,
            STORAGE | wgpu::BufferUsages::COPY_DST,
        );
        let dyn_params = ctx.uniform("sdf dynamic params", &GpuMisc { misc: [0; 4] });
        let texel_buf = ctx.buffer_init("sdf texels", &texels, STORAGE);
        let acc_buf = ctx.buffer_zeroed(
            "sdf accumulators",
            2 * 16 * self.n_texels as u64,
            STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
        );
        let sky_params = ctx.uniform("sdf sky params", &GpuSkyParams::zeroed());

        // Voxelise.
        let vox_module = ctx.shader(&shaders::SDF_VOXELIZE)?;
        let vox_groups = {
            let x = n_tris.clamp(1, 65535);
            (x, n_tris.div_ceil(x).max(1))
        };
        let vox_params = ctx.uniform(
            "sdf voxelize params",
            &GpuMisc {
                misc: [n_tris, vox_groups.0, 0, 0],
            },
        );
        let vox_binds = [
            Bind::Uniform(&vol_buf),
            Bind::Read(&tri_buf),
            Bind::Write(&seed_bufs[0]),
            Bind::Uniform(&vox_params),
        ];
        let vox_layout = layout_of(&ctx, "sdf voxelize", CS, &vox_binds);
        let vox_bg = group_of(&ctx, "sdf voxelize", &vox_layout, &vox_binds);
        let clear_pipeline = compute_pipeline(&ctx, "sdf clear seeds", &vox_module, "clear_seeds", &vox_layout);
        let vox_pipeline = compute_pipeline(&ctx, "sdf voxelize", &vox_module, "voxelize", &vox_layout);

        // Flood: steps N/2 .. 1, then 1 again (JFA+1), ping-ponging between the seed grids.
        let flood_module = ctx.shader(&shaders::SDF_FLOOD)?;
        // The same kinds as every flood bind group below (the step uniform is a stand-in).
        let flood_layout = layout_of(
            &ctx,
            "sdf flood",
            CS,
            &[
                Bind::Uniform(&vol_buf),
                Bind::Read(&tri_buf),
                Bind::Read(&seed_bufs[0]),
                Bind::Write(&seed_bufs[1]),
                Bind::Uniform(&vol_buf),
                Bind::Write(&base_buf),
            ],
        );
        let flood_pipeline = compute_pipeline(&ctx, "sdf flood", &flood_module, "flood", &flood_layout);
        let resolve_pipeline = compute_pipeline(&ctx, "sdf resolve", &flood_module, "resolve", &flood_layout);
        let max_dim = layout.dims.into_iter().max().unwrap_or(1);
        let mut steps = Vec::new();
        let mut s = max_dim.next_power_of_two() / 2;
        while s >= 1 {
            steps.push(s);
            s /= 2;
        }
        steps.push(1);
        let flood_bg = |label: &str, from: usize, step: u32| {
            let u = ctx.uniform(label, &GpuMisc { misc: [step, 0, 0, 0] });
            group_of(
                &ctx,
                label,
                &flood_layout,
                &[
                    Bind::Uniform(&vol_buf),
                    Bind::Read(&tri_buf),
                    Bind::Read(&seed_bufs[from]),
                    Bind::Write(&seed_bufs[1 - from]),
                    Bind::Uniform(&u),
                    Bind::Write(&base_buf),
                ],
            )
        };
        let voxel_groups = gpu::dispatch_size_64(voxels);
        let mut encoder = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("sdf volume build"),
        });
        run_pass(&mut encoder, "sdf clear seeds", &clear_pipeline, &vox_bg, voxel_groups);
        run_pass(&mut encoder, "sdf voxelize", &vox_pipeline, &vox_bg, vox_groups);
        let mut from = 0;
        for (i, step) in steps.iter().enumerate() {
            let label = format!("sdf flood {i} (step {step})");
            let bg = flood_bg(&label, from, *step);
            run_pass(&mut encoder, &label, &flood_pipeline, &bg, voxel_groups);
            from = 1 - from;
        }
        let resolve_bg = flood_bg("sdf resolve", from, 0);
        run_pass(
            &mut encoder,
            "sdf resolve",
            &resolve_pipeline,
            &resolve_bg,
            voxel_groups,
        );
        ctx.queue.submit([encoder.finish()]);

        // Dynamic composite and mips.
        let dyn_module = ctx.shader(&shaders::SDF_DYNAMIC)?;
        let dyn_binds = [
            Bind::Uniform(&vol_buf),
            Bind::Read(&base_buf),
            Bind::Write(&levels_buf),
            Bind::Read(&shapes_buf),
            Bind::Uniform(&dyn_params),
        ];
        let dyn_layout = layout_of(&ctx, "sdf dynamic", CS, &dyn_binds);
        let dyn_pipeline = compute_pipeline(&ctx, "sdf dynamic composite", &dyn_module, "composite", &dyn_layout);
        let dyn_bg = group_of(&ctx, "sdf dynamic composite", &dyn_layout, &dyn_binds);
        let mips_module = ctx.shader(&shaders::SDF_MIPS)?;
        // The level uniform is a stand-in: each mip's bind group below has its own.
        let mips_layout = layout_of(
            &ctx,
            "sdf mips",
            CS,
            &[
                Bind::Uniform(&vol_buf),
                Bind::Write(&levels_buf),
                Bind::Uniform(&vol_buf),
            ],
        );
        let mips_pipeline = compute_pipeline(&ctx, "sdf mips", &mips_module, "downsample", &mips_layout);
        let mips_bgs = (1..layout.levels)
            .map(|l| {
                let label = format!("sdf mip {l}");
                let u = ctx.uniform(&label, &GpuMisc { misc: [l, 0, 0, 0] });
                group_of(
                    &ctx,
                    &label,
                    &mips_layout,
                    &[Bind::Uniform(&vol_buf), Bind::Write(&levels_buf), Bind::Uniform(&u)],
                )
            })
            .collect();

        // Sky gather and calibration share one layout.
        let sky_module = ctx.shader(&shaders::SDF_SKY)?;
        let sky_binds = [
            Bind::Uniform(&vol_buf),
            Bind::Read(&levels_buf),
            Bind::Read(&texel_buf),
            Bind::Write(&acc_buf),
            Bind::Uniform(&sky_params),
        ];
        let cal_layout = layout_of(&ctx, "sdf sky", CS, &sky_binds);
        let sky_pipeline = compute_pipeline(&ctx, "sdf sky", &sky_module, "sky_step", &cal_layout);
        let cal_pipeline = compute_pipeline(&ctx, "sdf calibrate", &sky_module, "calibrate", &cal_layout);
        let sky_bg = group_of(&ctx, "sdf sky", &cal_layout, &sky_binds);
        let g = SdfGpu {
            ctx,
            layout,
            centre,
            scale,
            origin_offset,
            vol_buf,
            shapes_buf,
            dyn_params,
            acc_buf,
            sky_params,
            dyn_pipeline,
            dyn_bg,
            mips_pipeline,
            mips_bgs,
            sky_pipeline,
            sky_bg,
            cal_pipeline,
            cal_layout,
            levels_buf,
        };
        g.composite(&self.params.dynamic);
        g.ctx.wait_idle()?;
        g.ctx.take_error("sdf volume build")?;
        Ok(g)
    }

    /// Moves, adds or removes the dynamic shapes: reruns the composite and the mips only
    /// (the voxelisation and the flood are kept) and restarts the accumulation. k and
    /// alpha stay as fitted for the first configuration.
    pub fn set_dynamic(&mut self, shapes: Vec<DynamicShape>) -> Result<(), EngineError> {
        let mut p = self.params.clone();
        p.dynamic = shapes;
        p.validate()?;
        if let Some(g) = &self.gpu {
            g.composite(&p.dynamic);
            let mut encoder = g.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("sdf clear accumulators"),
            });
            encoder.clear_buffer(&g.acc_buf, 0, None);
            g.ctx.queue.submit([encoder.finish()]);
            g.ctx.take_error("sdf set_dynamic").map_err(gpu_error)?;
        }
        self.params.dynamic = p.dynamic;
        self.steps_done = 0;
        self.half_steps = [0, 0];
        Ok(())
    }

    fn weighting_flag(&self) -> f32 {
        match self.params.weighting {
            Weighting::Voxel => 0.0,
            Weighting::Distance => 1.0,
        }
    }
}

impl SdfGpu {
    /// Level 0 = min(static field, shapes), then the mips.
    fn composite(&self, shapes: &[DynamicShape]) {
        let gpu_shapes: Vec<GpuShape> = shapes
            .iter()
            .map(|s| {
                let c = ((s.centre() - self.origin_offset).as_vec3() - self.centre) / self.scale;
                let size = s.size() / self.scale;
                let a = s.albedo();
                GpuShape {
                    centre: [c.x, c.y, c.z, if s.is_box() { 0.0 } else { 1.0 }],
                    size: [size.x, size.y, size.z, 0.0],
                    albedo: [a.x, a.y, a.z, 0.0],
                }
            })
            .collect();
        if !gpu_shapes.is_empty() {
            self.ctx
                .queue
                .write_buffer(&self.shapes_buf, 0, bytemuck::cast_slice(&gpu_shapes));
        }
        self.ctx.queue.write_buffer(
            &self.dyn_params,
            0,
            bytemuck::bytes_of(&GpuMisc {
                misc: [gpu_shapes.len() as u32, 0, 0, 0],
            }),
        );
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("sdf composite and mips"),
        });
        run_pass(
            &mut encoder,
            "sdf dynamic composite",
            &self.dyn_pipeline,
            &self.dyn_bg,
            gpu::dispatch_size_64(self.layout.voxels()),
        );
        for (i, bg) in self.mips_bgs.iter().enumerate() {
            let l = i as u32 + 1;
            let d = VolumeLayout::level_dims_of(self.layout.dims, l);
            run_pass(
                &mut encoder,
                &format!("sdf mip {l}"),
                &self.mips_pipeline,
                bg,
                gpu::dispatch_size_64(d[0] * d[1] * d[2]),
            );
        }
        self.ctx.queue.submit([encoder.finish()]);
    }
}

/// The bounce's ambient over one half (the module doc's *Bounce*, `engine::ambient`): the
/// area-weighted sums of rho D (the outgoing radiance of the directly lit surfaces), of h
/// (the fraction of a texel's cosine-weighted hemisphere that sees surfaces, the shared
/// pass's rays) and of the albedo, and each texel's weight h.
fn shared_bounce(d: &DirectHalf, albedo: &[Vec3], area: &[f32]) -> AmbientHalf {
    let mut sums = AmbientSums::default();
    for k in 0..d.light.len() {
        sums.add_texel(area[k], albedo[k], albedo[k] * d.light[k], d.hit[k]);
    }
    AmbientHalf {
        sums,
        weight: d.hit.iter().map(|h| Vec3::splat(h.clamp(0.0, 1.0))).collect(),
    }
}

impl Technique for Sdf {
    fn id(&self) -> &'static str {
        "sdf"
    }

    fn params(&self) -> serde_json::Value {
        let mut p = self.params.clone();
        p.k = Some(self.k);
        p.alpha = Some(self.alpha);
        serde_json::to_value(p).expect("params serialise")
    }

    fn step(&mut self) -> Result<(), EngineError> {
        let parity = (self.steps_done % 2) as usize;
        let watched = self.deadline.is_some() || self.progress.is_some();
        let progress = self.progress.clone();
        let mut go_on = go_on_until(self.deadline, progress.as_ref());
        let parts = if self.direct.is_some() { 2 } else { 1 };
        // The sky pass first: in a watched step in slices of texels with its half aside,
        // so that a stop in it, or in the shared direct light after it, can put it back.
        if let Some(g) = &self.gpu {
            let mut params = GpuSkyParams {
                sky: [self.sky.x, self.sky.y, self.sky.z, if self.upper { 1.0 } else { 0.0 }],
                fit: [self.k, self.alpha, self.params.bleed, self.weighting_flag()],
                misc: [
                    self.n_texels,
                    self.params.samples,
                    (self.seed as u32) ^ ((self.seed >> 32) as u32) ^ (parity as u32).wrapping_mul(0x9E37_79B9),
                    parity as u32,
                ],
                cal: [0, 0, self.half_steps[parity] as u32, 0],
                alphas: [[0.0; 4]; 4],
                slice: [0, self.n_texels, 0, 0],
            };
            let mut submit = |first: u64, count: u64| {
                params.slice = [first as u32, count as u32, 0, 0];
                g.ctx.queue.write_buffer(&g.sky_params, 0, bytemuck::bytes_of(&params));
                Ok(g.ctx
                    .submit_compute("sdf sky", &g.sky_pipeline, &g.sky_bg, count as u32))
            };
            if watched {
                let mut first_part = |done: u64, of: u64| go_on(done, parts * of);
                let aside = [Aside::half(&g.acc_buf, parity)];
                let done = self
                    .slicer
                    .run(&g.ctx, self.n_texels as u64, &aside, &mut submit, &mut first_part)
                    .map_err(gpu_error)?;
                if done == Sliced::Abandoned {
                    tracing::debug!("sdf: the deadline passed or a stop was asked mid-step; the step is undone");
                    return Ok(());
                }
            } else {
                submit(0, self.n_texels as u64).map_err(gpu_error)?;
            }
            g.ctx.take_error("sdf step").map_err(gpu_error)?;
        }
        // Then the shared direct light: sliced when it may be long (with a sun it is
        // nearly all of a step: 13.7 s of 14 on a 2048² level on lavapipe).
        if let Some(d) = &mut self.direct {
            let mut second_part = |done: u64, of: u64| go_on((parts - 1) * of + done, parts * of);
            let done = d
                .step_watched(watched.then_some(&mut second_part as &mut dyn FnMut(u64, u64) -> bool))
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                if let Some(g) = &self.gpu {
                    // The sky pass finished (sliced, so its half is aside): put it back.
                    self.slicer
                        .put_back(&g.ctx, &[Aside::half(&g.acc_buf, parity)])
                        .map_err(gpu_error)?;
                }
                tracing::debug!("sdf: the deadline passed or a stop was asked mid-step; the step is undone");
                return Ok(());
            }
        }
        self.half_steps[parity] += 1;
        self.steps_done += 1;
        Ok(())
    }

    fn set_deadline(&mut self, deadline: Option<Instant>) {
        self.deadline = deadline;
        self.slicer.forget();
        if let Some(d) = &mut self.direct {
            d.forget_step_length();
        }
    }

    fn set_step_progress(&mut self, progress: StepProgress) {
        self.progress = Some(progress);
        self.slicer.forget();
        if let Some(d) = &mut self.direct {
            d.forget_step_length();
        }
    }

    fn wait_for_steps(&mut self) -> Result<(), EngineError> {
        match &self.device {
            Some(ctx) => ctx.wait_idle().map_err(gpu_error),
            None => Ok(()),
        }
    }

    fn steps_done(&self) -> u64 {
        self.steps_done
    }

    fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        let n = self.n_texels as usize;
        let acc: Vec<[f32; 4]> = match &self.gpu {
            Some(g) => g
                .ctx
                .read_buffer("sdf accumulators", &g.acc_buf, 2 * n)
                .map_err(gpu_error)?,
            None => vec![[0.0; 4]; 2 * n],
        };
        let shared: Option<[DirectHalf; 2]> = match &self.direct {
            Some(d) => Some(d.halves().map_err(gpu_error)?),
            None => None,
        };
        let bounce = self.params.bounce;
        let mut bounced: [Option<AmbientHalf>; 2] = [None, None];
        let mut half = |h: usize| {
            let steps = self.half_steps[h];
            let scale = if steps > 0 { 1.0 / steps as f32 } else { 0.0 };
            let slice = &acc[h * n..(h + 1) * n];
            // Sky light straight from the sky is all direct (path's first vertex); only
            // the bleed term would be indirect, so the sky's direct is the bleed-free
            // visibility times the sky.
            let sky_total: Vec<Vec3> = slice.iter().map(|a| Vec3::from_slice(&a[..3]) * scale).collect();
            let mut direct: Vec<Vec3> = slice.iter().map(|a| self.sky * (a[3] * scale)).collect();
            let mut total = sky_total;
            if let Some(sh) = &shared {
                let d = &sh[h];
                for k in 0..n {
                    direct[k] += d.light[k];
                    total[k] += d.light[k];
                }
                if bounce {
                    let ambient = shared_bounce(d, &self.texel_albedo, &self.texel_area);
                    let b = ambient.sums.closure();
                    for (t, w) in total.iter_mut().zip(&ambient.weight) {
                        *t += b * *w;
                    }
                    bounced[h] = Some(ambient);
                }
            }
            HalfEstimate {
                steps,
                total,
                direct: self.want_direct.then_some(direct),
                moments: None,
            }
        };
        // Both halves' visibility sums over all steps: the plain sky visibility, without
        // the sky's colour or the bleed (DESIGN's `ao.Y`).
        let steps = (self.half_steps[0] + self.half_steps[1]) as f32;
        self.last_ao = Some(
            (0..n)
                .map(|k| {
                    if steps > 0.0 {
                        (acc[k][3] + acc[n + k][3]) / steps
                    } else {
                        0.0
                    }
                })
                .collect(),
        );
        let (even, odd) = (half(0), half(1));
        self.last_ambient = match bounced {
            [Some(e), Some(o)] => Some([e, o]),
            _ => None,
        };
        Ok(Snapshot { even, odd })
    }

    fn ambient(&self) -> Option<[AmbientHalf; 2]> {
        self.last_ambient.clone()
    }

    fn ao(&self) -> Option<Vec<f32>> {
        self.last_ao.clone()
    }

    fn accumulating_pass(&self) -> &'static str {
        "sdf sky (shaders/sdf/sky.wgsl)"
    }
}

/// `sdf`'s passes, WGSL in `shaders/sdf/`.
pub mod shaders {
    use crate::engine::gpu::shaders::{PassShader, WgslFile, pass, wgsl_file};

    /// The volume layout and triangle distance every sdf pass starts with.
    pub const SDF_VOLUME: WgslFile = wgsl_file!("sdf/volume.wgsl");
    /// Seed the voxels each triangle touches.
    pub const SDF_VOXELIZE: PassShader = pass!("sdf/voxelize.wgsl", [SDF_VOLUME]);
    /// Jump flooding and the signed distance of the nearest seed triangle.
    pub const SDF_FLOOD: PassShader = pass!("sdf/flood.wgsl", [SDF_VOLUME]);
    /// Analytic dynamic shapes composited into the volume with min.
    pub const SDF_DYNAMIC: PassShader = pass!("sdf/dynamic.wgsl", [SDF_VOLUME]);
    /// The pre-blurred mip chain.
    pub const SDF_MIPS: PassShader = pass!("sdf/mips.wgsl", [SDF_VOLUME]);
    /// Sky visibility along the bent normal, and the calibration sums.
    pub const SDF_SKY: PassShader = pass!("sdf/sky.wgsl", [SDF_VOLUME]);
    /// Every pass of `sdf`.
    pub const ALL: &[PassShader] = &[SDF_VOXELIZE, SDF_FLOOD, SDF_DYNAMIC, SDF_MIPS, SDF_SKY];
}

/// `sdf` in the technique table (`technique/table.rs`).
pub const ENTRY: TechniqueEntry = TechniqueEntry {
    default_params: || serde_json::to_value(SdfParams::default()).unwrap_or_default(),
    id: "sdf",
    summary: "sky light from a signed-distance volume with calibrated constants and movable analytic occluders; other light from the shared GPU direct-light module with a one-ambient bounce (GPU)",
    plan,
    prepare: |inputs, params| Ok(Box::new(Sdf::prepare(inputs, params)?)),
    shaders: shaders::ALL,
    layers: &[OutputLayer::Direct, OutputLayer::Indirect, OutputLayer::Ao],
    lights: LightSource::ALL,
    check_params: |p| parse_params::<SdfParams>("sdf", p)?.validate(),
    unbiased: false,
    alpha: AlphaSupport::Partly {
        tested: "the sun, directional, point and spot lights and emitters (the shared direct-light pass's GPU rays)",
        opaque: "the signed distance field that gathers the sky and the bounce holds occupancy, not coverage (its k and alpha, fitted to alpha-tested CPU rays, absorb cut-outs only on average over the scene); it",
    },
    rounds: false,
    tasks: TaskSplit::ChainsAndRegions(
        "its sky jitter is stratified along each texel's steps and its halves are running means of the shared direct light, so a range of steps is not a part of one bake; a texel's sky and direct light come from the scene, the seed and its pixel, its calibration from texels drawn over the whole grid by pixel, and its bounce from one scene-wide ambient that the merge closes over every region, so a region's texels (pages or tiles) are the single bake's",
    ),
};

/// What `sdf` runs for a scene and job, and what it leaves out (DESIGN section 6).
pub fn plan(f: &SceneFeatures) -> Plan {
    let mut p = Plan::new("sdf");
    let other_light = f.sun || f.punctual_lights > 0 || f.emissive_triangles > 0;
    if f.sky {
        p.run(
            "voxelise",
            "seed the voxels each triangle touches (resolution 128 along the longest axis by default; memory 24 B a voxel + 16 B a mip element)",
        );
        p.run(
            "jump flood",
            "exact point-triangle distance transform, signed by the nearest triangle's normal",
        );
        p.run(
            "dynamic composite + mips",
            "analytic boxes/ellipsoids min-composited, then box-filtered mips",
        );
        p.run(
            "calibration",
            "k and alpha fitted against CPU sky-visibility rays (256 texels x 64 rays by default)",
        );
        p.run("sky", "samples along the bent normal per texel, jittered per step");
    } else {
        p.leave_out("distance volume", "the job has no sky: the volume serves the sky only");
    }
    p.decide(
        "shared direct light",
        other_light,
        "sun, directional, point and spot lights and emitters: E/pi with shadow rays on the GPU BVH (engine::gpu::direct_light)",
        "no sun, no punctual light and no emitter",
    );
    p.decide(
        "bounce of the shared direct light",
        other_light,
        "one scene-wide ambient (the obscurance model): h B1 / (1 - c R_ave), h each texel's hit fraction from the shared pass's rays; off with params.bounce = false",
        "nothing but the sky to bounce",
    );
    // Without this item the job never asks the technique to keep its direct light, and a
    // `direct` or `indirect` output failed after the whole bake.
    p.decide(
        DIRECT_LAYER,
        f.want_direct,
        "direct or indirect output asked for: the sky straight from the sky (visibility times its radiance) and the shared direct light; the bleed and the bounce are indirect",
        "not asked for in outputs",
    );
    p.leave_out(
        "interreflection of the sky",
        "the sky's bounce only through the `bleed` approximation (off by default)",
    );
    if f.want_sh {
        p.leave_out(
            SH_LAYER,
            "asked for, but sdf keeps no directional moments: `sh` outputs fail with sdf (use `path`)",
        );
    } else {
        p.leave_out(SH_LAYER, "not asked for in outputs");
    }
    if f.glossy_materials > 0 {
        p.leave_out("glossy transport", "sdf computes diffuse sky light only");
    }
    p.error_estimate = "noise only (the jitter and the shared direct light's samples): sdf is a calibrated approximation and its bounce a one-ambient model, and that bias (see params().calibration and docs/sdf.md) is not in the half-difference estimate".into();
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
            Mirror::of::<GpuVolume>("GpuVolume", shaders::SDF_VOXELIZE, "SdfVolume"),
            Mirror::of::<GpuTri>("GpuTri", shaders::SDF_VOXELIZE, "SdfTri"),
            Mirror::of::<GpuMisc>("GpuMisc", shaders::SDF_VOXELIZE, "VoxelizeParams"),
            Mirror::of::<GpuMisc>("GpuMisc", shaders::SDF_FLOOD, "FloodParams"),
            Mirror::of::<GpuMisc>("GpuMisc", shaders::SDF_MIPS, "MipParams"),
            Mirror::of::<GpuShape>("GpuShape", shaders::SDF_DYNAMIC, "Shape"),
            Mirror::of::<GpuMisc>("GpuMisc", shaders::SDF_DYNAMIC, "DynamicParams"),
            Mirror::of::<GpuSkyParams>("GpuSkyParams", shaders::SDF_SKY, "SkyParams"),
        ]);
    }

    #[test]
    fn params_defaults_and_ranges() {
        let p: SdfParams = parse_params("sdf", &serde_json::Value::Null).unwrap();
        assert_eq!(p.resolution, 128);
        assert!(p.validate().is_ok());
        for bad in [
            serde_json::json!({"resolution": 8}),
            serde_json::json!({"samples": 0}),
            serde_json::json!({"k": -1.0}),
            serde_json::json!({"alpha": 1.5}),
            serde_json::json!({"bleed": 2.0}),
            serde_json::json!({"dynamic": [{"box": {"centre": [0, 0, 0], "half": [0, 1, 1]}}]}),
        ] {
            let p: SdfParams = parse_params("sdf", &bad).unwrap();
            let e = p.validate().unwrap_err();
            assert!(e.is_bad_input(), "{e}");
        }
        assert!(parse_params::<SdfParams>("sdf", &serde_json::json!({"nope": 1})).is_err());
        assert!(
            parse_params::<SdfParams>("sdf", &serde_json::json!({"dynamic": [{"cone": {}}]})).is_err(),
            "unknown shape kinds are rejected"
        );
    }

    #[test]
    fn layout_pads_and_chains_mips() {
        let l = VolumeLayout::new(Vec3::new(-1.0, 0.0, -1.0), Vec3::new(1.0, 0.5, 1.0), 64, 7);
        assert_eq!(l.dims[0], 64);
        assert_eq!(l.dims[2], 64);
        // 0.5 / (2 / 60) = 15 voxels (16 if rounding lands above) + 4 padding.
        assert!((19..=20).contains(&l.dims[1]), "{:?}", l.dims);
        assert_eq!(l.levels, 6, "64, 32, 16, 8, 4, 2 voxels: no level of one voxel");
        assert_eq!(l.offsets[1], l.voxels());
        // The grid covers the bounds with the padding on each side.
        assert!(l.origin.x <= -1.0 - 1.9 * l.voxel && l.origin.y <= -1.9 * l.voxel);
    }

    #[test]
    fn fit_finds_a_known_k() {
        let (k, e) = fit_k(|k| (k - 0.37).abs());
        assert!((k - 0.37).abs() < 1e-3 && e < 1e-3, "{k} {e}");
    }

    #[test]
    fn analytic_shapes_block_rays() {
        let b = DynamicShape::Box(BoxShape {
            centre: [0.0, 2.0, 0.0],
            half: [1.0, 0.5, 1.0],
            albedo: grey(),
        });
        let c = Vec3::new(0.0, 2.0, 0.0);
        assert!(ray_hits_shape(&b, c, Vec3::ZERO, Vec3::Y));
        assert!(!ray_hits_shape(&b, c, Vec3::ZERO, Vec3::X));
        assert!(!ray_hits_shape(&b, c, Vec3::ZERO, Vec3::NEG_Y));
        let e = DynamicShape::Ellipsoid(EllipsoidShape {
            centre: [0.0, 2.0, 0.0],
            radii: [0.5, 0.5, 0.5],
            albedo: grey(),
        });
        assert!(ray_hits_shape(&e, c, Vec3::ZERO, Vec3::Y));
        assert!(!ray_hits_shape(&e, c, Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0).normalize()));
    }
}
