//! Light probes on the GPU (issue 26 point 1, "baked by `path`, GPU when there is one"):
//! the CPU probe estimator of [`super::probes`] as one compute pass,
//! `shaders/path/probes.wgsl`, over the bake's GPU BVH and scene tables (the uploads
//! `path`'s texel megakernel uses, shared through [`SceneRays`]).
//!
//! How: the valid probes go up once as points in the texels' layout (world position, the
//! probe's index in the job's list as the bits of `position.w`: it keys the probe's random
//! streams, so a probe draws the same samples whichever probes around it are invalid).
//! One step is one dispatch of one 64-invocation workgroup per probe
//! ([`TexelRayPass::over_points`]): each invocation runs every 64th of the step's samples,
//! the workgroup adds the 64 sums in workgroup memory and blends their mean into the step's
//! half accumulator (9 vec4 a probe and half), so the halves and the error estimate are the
//! CPU's, and nothing is read back until [`ProbeGpu::halves`]. A workgroup per probe
//! rather than an invocation per probe: a level's few thousand probes would occupy a few
//! thousand lanes of a GPU that has tens of thousands, and one invocation running all 64
//! samples of a closed room's long paths would meet llvmpipe's loop budget (65535 loop
//! iterations an invocation, `shaders/path/estimator.wgsl`).
//!
//! The samples are placed as on the CPU (`params.sampling`: Owen-scrambled Sobol points per
//! probe and half by default, the probe's own numbers from vertex 0's sets and the path
//! from a hit from vertex 1's; or independent PCG streams); the GPU's scrambles and
//! streams are hashed differently, so the two agree in the mean within noise, not bit for
//! bit (`tests/probes.rs` runs the closed forms on both devices).
//!
//! Limits: at most [`super::probes::MAX_PROBES`] probes (6.4 M invocations a dispatch);
//! each buffer within the adapter's storage-binding limit (checked, naming it); the
//! inside-geometry test stays on the CPU (64 rays a probe, `ProbeBaker`).

use std::sync::Arc;

use glam::Vec3;

use super::PathParams;
use super::gpu::{PATH_SOBOL, PathUniform, sobol_vectors};
use super::probes::SH9;
use super::shaders::PROBES;
use crate::engine::gpu::GpuContext;
use crate::engine::gpu::scene_lights::LightSources;
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::gpu::texel_pass::{PassSpec, TexelRayPass};
use crate::engine::gpu::texels::GpuTexelGeom;
use crate::engine::scene::Lighting;
use crate::engine::technique::api::{EngineError, gpu_error};

/// Invocations per probe (`PROBE_LANES` in the shader).
pub const PROBE_LANES: u32 = 64;

/// The probe pass and its half accumulators on the GPU.
pub struct ProbeGpu {
    pass: TexelRayPass<PathUniform>,
    probes: usize,
    /// Each point's index in the job's list (errors name it).
    keys: Vec<u32>,
}

impl ProbeGpu {
    /// The pass for `points` (each the probe's index in the job's list and its position in
    /// the scene's frame, the BVH's space), `params`' samples a step, bounces and roulette,
    /// `eps` the offset of secondary rays off surfaces.
    pub fn new(
        ctx: Arc<GpuContext>,
        rays: &SceneRays,
        lighting: &Lighting,
        points: &[(u32, Vec3)],
        params: &PathParams,
        seed: u64,
        eps: f32,
    ) -> Result<Self, EngineError> {
        let n = points.len();
        let mut geom: Vec<GpuTexelGeom> = points
            .iter()
            .map(|(key, p)| GpuTexelGeom {
                position: p.extend(f32::from_bits(*key)).to_array(),
                normal: [0.0; 4],
                geo_normal: [0.0; 4],
            })
            .collect();
        if geom.is_empty() {
            // Binds a buffer; the shader runs no probe (counts.x is 0).
            geom.push(bytemuck::Zeroable::zeroed());
        }
        // No moments or direct layer: the SH only.
        let flags = if params.sampling == super::Sampling::Sobol {
            PATH_SOBOL
        } else {
            0
        };
        // The probes' own key, as on the CPU: probe i's streams and scrambles are not the
        // lightmap texel's at pixel i of the same bake.
        let seed = seed ^ 0x9B_0BE5;
        let uniform = PathUniform {
            counts: [n as u32, params.samples_per_step, params.max_bounces, 0],
            keys: [seed as u32, (seed >> 32) as u32, 0, flags],
            f: [params.threshold(), eps, 1.0, 0.0],
            slice: [0, 0, 0, 0],
        };
        let vectors = sobol_vectors();
        let emitters = rays.emitters();
        let spec = PassSpec {
            what: "path probes",
            shader: &PROBES,
            entry: "probe",
            sources: LightSources::ALL,
            emitters: &emitters,
            accumulators: &[("probe SH accumulators", (2 * n * SH9) as u64 * 16)],
            tables: &[("sobol direction numbers", &vectors)],
        };
        let lanes = if n == 0 { 0 } else { PROBE_LANES };
        let pass = TexelRayPass::over_points(ctx, rays, &geom, lanes, lighting, spec, uniform).map_err(gpu_error)?;
        tracing::info!(adapter = %pass.ctx().info.name, probes = n, "light probes on the GPU");
        Ok(ProbeGpu {
            pass,
            probes: n,
            keys: points.iter().map(|(k, _)| *k).collect(),
        })
    }

    /// The adapter's name.
    pub fn adapter(&self) -> &str {
        &self.pass.ctx().info.name
    }

    /// Submits one step (one dispatch); does not wait for it.
    pub fn step(&mut self) -> Result<(), EngineError> {
        self.pass.step().map_err(gpu_error)
    }

    /// Steps blended into each half so far.
    pub fn half_steps(&self) -> [u64; 2] {
        self.pass.half_steps()
    }

    /// The two half means per probe, in `points`' order (blocks on the device). Refuses
    /// probes whose samples were cut short by the adapter's loop budget, as `path` does for
    /// texels: their values would read too dark.
    pub fn halves(&self) -> Result<[Vec<[Vec3; SH9]>; 2], EngineError> {
        let n = self.probes;
        let raw = self.pass.read(0, 2 * n * SH9).map_err(gpu_error)?;
        if let Some(k) = (0..2 * n).find(|k| raw[k * SH9][3] != 0.0) {
            let probe = self.keys[k % n];
            return Err(EngineError::Gpu(format!(
                "light probes on {}: the samples of probe {} were cut short by the adapter's loop \
                 budget (llvmpipe ends an invocation's loops after 65535 iterations in all), so it \
                 would read too dark; lower the path's max_bounces or bake the probes on the CPU",
                self.adapter(),
                probe
            )));
        }
        let half = |h: usize| -> Vec<[Vec3; SH9]> {
            (0..n)
                .map(|i| std::array::from_fn(|c| Vec3::from_slice(&raw[(h * n + i) * SH9 + c][..3])))
                .collect()
        };
        Ok([half(0), half(1)])
    }
}
