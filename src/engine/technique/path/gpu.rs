//! `path` on the GPU (`"device": "gpu"`, or `"auto"` on a machine with a hardware
//! adapter): the CPU reference's estimator (`technique::path`) run as one compute
//! megakernel, `shaders/path/path_trace.wgsl`, over the BVH of `engine::gpu::bvh`.
//!
//! How: one invocation per valid texel traces that texel's `samples_per_step` paths of
//! the step and blends their mean into the step's half accumulator (running means,
//! even/odd steps as on the CPU), so a step is one dispatch and nothing is read back until
//! a snapshot. The scene goes up once: the BVH (nodes, triangles in leaf order), per
//! triangle slot its shading normals, UV sets, material, emitter pick probability and
//! area, and one table buffer with the materials, punctual lights, the emitter CDF (the
//! CPU's `EmitterTable`, so both pick emitters with the same probabilities) and the
//! textures (linear RGBA f32, sampled bilinearly with the same wrap rules as
//! `scene::Texture::sample`).
//!
//! Same estimator and the same sampling, other random numbers: with `sampling: sobol`
//! (the default) each vertex below the 32nd takes its numbers from two 4-D sets of an
//! Owen-scrambled Sobol sequence per texel and half, as on the CPU (`path/sampler.rs`):
//! the shader computes `sobol_burley`'s points itself from the crate's direction numbers,
//! which [`sobol_vectors`] reads out of the crate and uploads; only the scrambles' seeds
//! are hashed differently (32-bit `pcg` for the CPU's 64-bit SplitMix). Past the 32nd
//! vertex, and with `sampling: independent`, PCG-RXS-M-XS 32/32 streams per (seed, step,
//! pixel, sample) (the shader's header), not the CPU's 64-bit PCG32. So a GPU bake agrees
//! with a CPU bake of the same seed in the mean, within noise, not bit for bit; the
//! half-accumulator error estimate is the same. (Until 2026-12-05 the GPU drew every
//! number from the stream, whatever `sampling` said.) A megakernel rather than a
//! wavefront: it needs no ray queues in memory and is the first thing to measure
//! (`docs/performance.md`); paths of very different lengths leave lanes idle, which a
//! wavefront would recover on hardware GPUs.
//!
//! A step is one dispatch, or, when it may be long in a bake with a deadline or a watcher,
//! slices of about 50 ms that can be stopped and undone ([`PathGpu::step_watched`]).
//!
//! Precision: world space f32, as the CPU. Limits: every storage buffer must fit the
//! adapter's binding limit (128 MiB on lavapipe: about 1.4M triangles' shading data, 8M
//! texture texels, 2M texels with moments), checked up front with an error naming the
//! buffer; the steps are counted in 32 bits in the shader.

use std::sync::Arc;

use glam::Vec3;

use super::PathParams;
use super::shaders::PATH_TRACE;
use crate::engine::accumulate::{HalfEstimate, Snapshot};
use crate::engine::gpu::scene_lights::LightSources;
pub use crate::engine::gpu::texel_pass::Sliced;
use crate::engine::gpu::texel_pass::{PassSpec, StepUniform, TexelRayPass};
use crate::engine::gpu::{GpuContext, GpuError};
use crate::engine::technique::api::{BakeInputs, EngineError, go_on_until, gpu_error};

/// Where `path` runs (`params.device`): the shared layer's [`RayDevice`](crate::engine::gpu::RayDevice).
pub use crate::engine::gpu::RayDevice as Device;

/// The GPU context `device` asks for, or `None` for the CPU.
pub fn resolve(device: Device) -> Result<Option<Arc<GpuContext>>, EngineError> {
    device.context("path").map_err(gpu_error)
}

const PATH_DIRECT: u32 = 1;
const PATH_MOMENTS: u32 = 2;
pub(super) const PATH_SOBOL: u32 = 4;

/// Direction numbers per set.
const SOBOL_BITS: u32 = 16;

/// The `sobol_burley` crate's reversed direction numbers, as the shader reads them
/// (binding 10): for each of its 4-D sets, 16 vec4 (number k of the set's four
/// dimensions). The crate keeps its table private; number k is the point of the index
/// whose bit-reversed form has only bit 31 - k set (`parts::sobol_rev` XORs exactly the
/// numbers of the set bits), so the table is read out through the public function, and a
/// test checks the shader's formula against the crate's points.
pub fn sobol_vectors() -> Vec<u32> {
    let sets = sobol_burley::NUM_DIMENSION_SETS_4D;
    let mut out = Vec::with_capacity((sets * SOBOL_BITS * 4) as usize);
    for set in 0..sets {
        for k in 0..SOBOL_BITS {
            for d in 0..4 {
                out.push(sobol_burley::parts::sobol_rev(1 << (31 - k), 4 * set + d));
            }
        }
    }
    out
}

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct PathUniform {
    pub(super) counts: [u32; 4],
    pub(super) keys: [u32; 4],
    pub(super) f: [f32; 4],
    /// The dispatch's first texel and texel count (a sliced step); the probe pass ignores it.
    pub(super) slice: [u32; 4],
}

impl StepUniform for PathUniform {
    fn set_step(&mut self, step: u64, half: u32, weight: f32) {
        self.counts[3] = step as u32;
        self.keys[2] = half;
        self.f[2] = weight;
    }
    fn set_slice(&mut self, first: u32, count: u32) {
        self.slice = [first, count, 0, 0];
    }
}

/// The GPU half of `path`: the pass and its half accumulators on the GPU (total, direct,
/// directional moments).
pub struct PathGpu {
    pass: TexelRayPass<PathUniform>,
    texels: usize,
    want_direct: bool,
    want_moments: bool,
}

impl PathGpu {
    /// `path` on `ctx` for `inputs`, its scene from the bake's shared uploads.
    pub fn new(ctx: Arc<GpuContext>, inputs: &BakeInputs, params: &PathParams) -> Result<Self, EngineError> {
        Self::build(ctx, inputs, params).map_err(gpu_error)
    }

    fn build(ctx: Arc<GpuContext>, inputs: &BakeInputs, params: &PathParams) -> Result<Self, GpuError> {
        let n = inputs.atlas.texels.len();
        let want_direct = inputs.want_direct;
        let want_moments = inputs.plan.runs("directional (sh) layer");
        let vec4 = 16u64;
        // A layer not kept still binds one vec4.
        let acc_len = |keep: bool, per: u64| if keep { 2 * n as u64 * per * vec4 } else { vec4 };
        let seed = inputs.seed;
        let sobol = params.sampling == super::Sampling::Sobol;
        let flags = if want_direct { PATH_DIRECT } else { 0 }
            | if want_moments { PATH_MOMENTS } else { 0 }
            | if sobol { PATH_SOBOL } else { 0 };
        let vectors = sobol_vectors();
        let uniform = PathUniform {
            counts: [n as u32, params.samples_per_step, params.max_bounces, 0],
            keys: [seed as u32, (seed >> 32) as u32, 0, flags],
            f: [params.threshold(), inputs.atlas.surface_offset, 1.0, 0.0],
            slice: [0, n as u32, 0, 0],
        };
        let spec = PassSpec {
            what: "path trace",
            shader: &PATH_TRACE,
            entry: "trace",
            sources: LightSources::ALL,
            emitters: &inputs.rays.emitters(),
            accumulators: &[
                ("accumulators", acc_len(true, 1)),
                ("direct accumulators", acc_len(want_direct, 1)),
                ("moment accumulators", acc_len(want_moments, 3)),
            ],
            tables: &[("sobol direction numbers", &vectors)],
        };
        let pass = TexelRayPass::new(ctx, &inputs.rays, &inputs.atlas, &inputs.lighting, spec, uniform)?;
        tracing::info!(
            adapter = %pass.ctx().info.name,
            triangles = inputs.scene.triangles.len(),
            bvh_nodes = pass.lights.bvh.data.nodes.len(),
            bvh_depth = pass.lights.bvh.data.depth,
            texels = n,
            "path on the GPU"
        );
        Ok(PathGpu {
            pass,
            texels: n,
            want_direct,
            want_moments,
        })
    }

    pub fn steps(&self) -> u64 {
        let [a, b] = self.pass.half_steps();
        a + b
    }

    /// Makes the next step the job's step `first` (a task's, `engine::tasks`).
    pub fn start_at_step(&mut self, first: u64) {
        self.pass.first_step = first;
    }

    /// One step of a bake with a deadline or a watcher (sliced when it may be long), or
    /// of one without (whole): `TexelRayPass::step_watched`.
    pub fn step_watched(
        &mut self,
        deadline: Option<std::time::Instant>,
        progress: Option<&crate::engine::technique::api::StepProgress>,
    ) -> Result<Sliced, EngineError> {
        let mut go_on = go_on_until(deadline, progress);
        let watched = deadline.is_some() || progress.is_some();
        self.pass
            .step_watched(watched.then_some(&mut go_on as &mut dyn FnMut(u64, u64) -> bool))
            .map_err(gpu_error)
    }

    /// The next watched step is sliced and timed again (a new deadline).
    pub fn forget_step_length(&mut self) {
        self.pass.forget_step_length();
    }

    pub fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        let n = self.texels;
        let total = self.pass.read(0, 2 * n).map_err(gpu_error)?;
        let direct = if self.want_direct {
            Some(self.pass.read(1, 2 * n).map_err(gpu_error)?)
        } else {
            None
        };
        // The shader marks a texel whose paths were ended from outside (w, see its
        // header): llvmpipe's loop budget. Its value would be too dark: refused.
        if let Some(i) = total.iter().position(|a| a[3] != 0.0) {
            return Err(EngineError::Gpu(format!(
                "path on {}: the paths of texel {} were cut short by the adapter's loop budget \
                 (llvmpipe ends an invocation's loops after 65535 iterations in all, about 1300 \
                 bounces here), so the lightmap would read too dark; lower params.samples_per_step \
                 or params.max_bounces, or use \"device\": \"cpu\"",
                self.pass.ctx().info.name,
                i % n
            )));
        }
        let mut snap = Snapshot::from_gpu_halves(&total, direct.as_deref(), self.pass.half_steps());
        if self.want_moments {
            let m = self.pass.read(2, 6 * n).map_err(gpu_error)?;
            let v = |a: [f32; 4]| Vec3::new(a[0], a[1], a[2]);
            let half = |h: usize| -> Vec<[Vec3; 3]> {
                (0..n)
                    .map(|i| {
                        let b = (h * n + i) * 3;
                        [v(m[b]), v(m[b + 1]), v(m[b + 2])]
                    })
                    .collect()
            };
            let set = |e: &mut HalfEstimate, h: usize| e.moments = Some(half(h));
            set(&mut snap.even, 0);
            set(&mut snap.odd, 1);
        }
        Ok(snap)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Rust mirror of the pass's uniform has the shader's size (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[Mirror::of::<PathUniform>("PathUniform", PATH_TRACE, "PathUniform")]);
    }

    /// The shader's `sobol_4d` (path_trace.wgsl), line for line in Rust over the table
    /// [`sobol_vectors`] uploads, gives the crate's points exactly: the table and the
    /// formula are the crate's, so the GPU's points are the CPU sampler's construction.
    #[test]
    fn the_shaders_sobol_formula_over_the_uploaded_table_is_the_crates() {
        let table = sobol_vectors();
        let hash = |x: u32| {
            let mut n = x ^ 0xe6fe3beb;
            n ^= n >> 16;
            n = n.wrapping_mul(0x7feb352d);
            n ^= n >> 15;
            n = n.wrapping_mul(0x846ca68b);
            n ^ (n >> 16)
        };
        let owen = |x: u32, s: u32| {
            let mut n = x;
            n ^= n.wrapping_mul(0x3d20adea);
            n = n.wrapping_add(s);
            n = n.wrapping_mul((s >> 16) | 1);
            n ^= n.wrapping_mul(0x05526c56);
            n ^ n.wrapping_mul(0x53a22864)
        };
        let shader = |index: u32, set: u32, seed: u32| -> [f32; 4] {
            let shuffled = owen(index.reverse_bits(), hash(seed ^ 0x79c68e4a));
            let mut v = [0u32; 4];
            for k in 0..SOBOL_BITS {
                if shuffled & (0x8000_0000 >> k) != 0 {
                    for (d, x) in v.iter_mut().enumerate() {
                        *x ^= table[((set * SOBOL_BITS + k) * 4) as usize + d];
                    }
                }
            }
            let lanes = [0x912f69bau32, 0x174f18ab, 0x691e72ca, 0xb40cc1b8];
            std::array::from_fn(|d| {
                let scramble = seed.wrapping_mul(0x9c8f2d3b) ^ set ^ lanes[d];
                let bits = owen(v[d], hash(scramble)).reverse_bits();
                f32::from_bits((bits >> 9) | 0x3f80_0000) - 1.0
            })
        };
        assert_eq!(table.len(), 64 * 16 * 4);
        for (index, set, seed) in [
            (0, 0, 0),
            (1, 0, 7),
            (12345, 3, 99),
            (65535, 63, 0xdead_beef),
            (777, 17, 1),
        ] {
            assert_eq!(
                shader(index, set, seed),
                sobol_burley::sample_4d(index, set, seed),
                "{index} {set} {seed}"
            );
        }
        for index in 0..256 {
            assert_eq!(shader(index, 5, 42), sobol_burley::sample_4d(index, 5, 42));
        }
    }
}
