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
//! Same estimator, different random numbers: the GPU's streams are PCG-RXS-M-XS 32/32 per
//! (seed, step, texel, sample) (the shader's header), not the CPU's 64-bit PCG32, so a
//! GPU bake agrees with a CPU bake of the same seed in the mean, within noise, not bit
//! for bit; the half-accumulator error estimate is the same. A megakernel rather than a
//! wavefront: it needs no ray queues in memory and is the first thing to measure
//! (`docs/performance.md`); paths of very different lengths leave lanes idle, which a
//! wavefront would recover on hardware GPUs.
//!
//! Precision: world space f32, as the CPU. Limits: every storage buffer must fit the
//! adapter's binding limit (128 MiB on lavapipe: about 1.4M triangles' shading data, 8M
//! texture texels, 2M texels with moments), checked up front with an error naming the
//! buffer; the steps are counted in 32 bits in the shader.

use std::sync::{Arc, OnceLock};

use glam::Vec3;
use wgpu::BufferUsages;

use super::PathParams;
use super::shaders::PATH_TRACE;
use crate::engine::accumulate::{HalfEstimate, Snapshot};
use crate::engine::gpu::bvh::check_binding_size;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_of, layout_of};
use crate::engine::gpu::scene_lights::{GpuSceneLights, LightSources};
use crate::engine::gpu::{self, AdapterPreference, GpuContext, GpuError, Requirements};
use crate::engine::raytrace::{EmitterTable, Tracer};
use crate::engine::technique::api::{BakeInputs, EngineError, gpu_error};

/// Where `path` runs (`params.device`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Device {
    /// The GPU when a hardware adapter exists (and `LIGHTMAPD_ADAPTER` does not ask for a
    /// software one), else the CPU: a machine with only lavapipe keeps the CPU path.
    #[default]
    Auto,
    Cpu,
    Gpu,
}

/// True when some adapter is a hardware GPU (enumerated once per process).
pub fn hardware_adapter_present() -> bool {
    static PRESENT: OnceLock<bool> = OnceLock::new();
    *PRESENT.get_or_init(|| {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        adapters.iter().any(|a| {
            matches!(
                a.get_info().device_type,
                wgpu::DeviceType::DiscreteGpu | wgpu::DeviceType::IntegratedGpu | wgpu::DeviceType::VirtualGpu
            )
        })
    })
}

/// The GPU context `device` asks for, or `None` for the CPU.
pub fn resolve(device: Device) -> Result<Option<Arc<GpuContext>>, EngineError> {
    match device {
        Device::Cpu => Ok(None),
        Device::Gpu => gpu::shared(&Requirements::default()).map(Some).map_err(gpu_error),
        Device::Auto => {
            if AdapterPreference::from_env() == AdapterPreference::Cpu || !hardware_adapter_present() {
                return Ok(None);
            }
            match gpu::shared(&Requirements::default()) {
                Ok(ctx) if !ctx.is_software() => Ok(Some(ctx)),
                Ok(_) => Ok(None),
                Err(e) => {
                    tracing::warn!(error = %e, "path: no usable GPU, tracing on the CPU");
                    Ok(None)
                }
            }
        }
    }
}

const PATH_DIRECT: u32 = 1;
const PATH_MOMENTS: u32 = 2;

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct PathUniform {
    counts: [u32; 4],
    keys: [u32; 4],
    f: [f32; 4],
}

/// The GPU half of `path`: buffers, the pass, and the half accumulators on the GPU.
pub struct PathGpu {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    uniform_buf: wgpu::Buffer,
    uniform: PathUniform,
    acc_total: wgpu::Buffer,
    acc_direct: wgpu::Buffer,
    acc_moment: wgpu::Buffer,
    texels: usize,
    want_direct: bool,
    want_moments: bool,
    half_steps: [u64; 2],
    /// The job's index of the first step (a task's, `engine::tasks`): the streams are
    /// keyed by the global step.
    pub first_step: u64,
    _lights: GpuSceneLights,
}

impl PathGpu {
    pub fn new(
        ctx: Arc<GpuContext>,
        inputs: &BakeInputs,
        params: &PathParams,
        tracer: &Tracer,
        emitters: &EmitterTable,
    ) -> Result<Self, EngineError> {
        Self::build(ctx, inputs, params, tracer, emitters).map_err(gpu_error)
    }

    fn build(
        ctx: Arc<GpuContext>,
        inputs: &BakeInputs,
        params: &PathParams,
        tracer: &Tracer,
        emitters: &EmitterTable,
    ) -> Result<Self, GpuError> {
        let scene = &inputs.scene;
        let lights = GpuSceneLights::new(
            &ctx,
            "path",
            scene,
            &inputs.lighting,
            tracer,
            emitters,
            LightSources::ALL,
        )?;
        let n = inputs.atlas.texels.len();
        let want_direct = inputs.want_direct;
        let want_moments = inputs.plan.runs("directional (sh) layer");
        let texel_geom: Vec<[f32; 4]> = inputs
            .atlas
            .texels
            .iter()
            .flat_map(|t| {
                [
                    t.position.extend(0.0).to_array(),
                    t.normal.extend(0.0).to_array(),
                    t.geo_normal.extend(0.0).to_array(),
                ]
            })
            .collect();
        let vec4 = 16u64;
        check_binding_size(&ctx, "path: the texels", texel_geom.len() as u64 * vec4)?;
        let acc_len = |keep: bool, per: u64| if keep { 2 * n as u64 * per * vec4 } else { vec4 };
        check_binding_size(&ctx, "path: the accumulators", acc_len(true, 1))?;
        check_binding_size(&ctx, "path: the directional moments", acc_len(want_moments, 3))?;

        let read = BufferUsages::STORAGE | BufferUsages::COPY_DST;
        let rw = BufferUsages::STORAGE | BufferUsages::COPY_SRC | BufferUsages::COPY_DST;
        let texel_buf = ctx.buffer_init("path texels", &texel_geom, read);
        let acc_total = ctx.buffer_zeroed("path accumulators", acc_len(true, 1), rw);
        let acc_direct = ctx.buffer_zeroed("path direct accumulators", acc_len(want_direct, 1), rw);
        let acc_moment = ctx.buffer_zeroed("path moment accumulators", acc_len(want_moments, 3), rw);

        let seed = inputs.seed;
        let flags = if want_direct { PATH_DIRECT } else { 0 } | if want_moments { PATH_MOMENTS } else { 0 };
        let uniform = PathUniform {
            counts: [n as u32, params.samples_per_step, params.max_bounces, 0],
            keys: [seed as u32, (seed >> 32) as u32, 0, flags],
            f: [params.rr_threshold, inputs.atlas.surface_offset, 1.0, 0.0],
        };
        let uniform_buf = ctx.uniform("path params", &uniform);
        let module = ctx.shader(&PATH_TRACE)?;
        let [b0, b1, b2, b3, b4] = lights.binds();
        let binds = [
            b0,
            b1,
            b2,
            b3,
            b4,
            Bind::Uniform(&uniform_buf),
            Bind::Read(&texel_buf),
            Bind::Write(&acc_total),
            Bind::Write(&acc_direct),
            Bind::Write(&acc_moment),
        ];
        let layout = layout_of(&ctx, "path trace", wgpu::ShaderStages::COMPUTE, &binds);
        let group = group_of(&ctx, "path trace", &layout, &binds);
        let pipeline = compute_pipeline(&ctx, "path trace", &module, "trace", &layout);
        ctx.take_error("path: preparing the GPU pass")?;
        tracing::info!(
            adapter = %ctx.info.name,
            triangles = scene.triangles.len(),
            bvh_nodes = lights.bvh.data.nodes.len(),
            bvh_depth = lights.bvh.data.depth,
            texels = n,
            "path on the GPU"
        );
        Ok(PathGpu {
            ctx,
            pipeline,
            group,
            uniform_buf,
            uniform,
            acc_total,
            acc_direct,
            acc_moment,
            texels: n,
            want_direct,
            want_moments,
            half_steps: [0, 0],
            first_step: 0,
            _lights: lights,
        })
    }

    pub fn steps(&self) -> u64 {
        self.half_steps[0] + self.half_steps[1]
    }

    /// Submits one step (one dispatch); does not wait for it.
    pub fn step(&mut self) -> Result<(), EngineError> {
        let step = self.steps();
        let half = (step % 2) as usize;
        let k = self.half_steps[half] + 1;
        self.uniform.counts[3] = (self.first_step + step) as u32;
        self.uniform.keys[2] = half as u32;
        self.uniform.f[2] = 1.0 / k as f32;
        let ctx = &self.ctx;
        ctx.queue
            .write_buffer(&self.uniform_buf, 0, bytemuck::bytes_of(&self.uniform));
        ctx.submit_compute("path trace", &self.pipeline, &self.group, self.texels as u32);
        ctx.take_error("path trace").map_err(gpu_error)?;
        self.half_steps[half] = k;
        Ok(())
    }

    pub fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        let n = self.texels;
        let ctx = &self.ctx;
        let total: Vec<[f32; 4]> = ctx
            .read_buffer("path accumulators", &self.acc_total, 2 * n)
            .map_err(gpu_error)?;
        let direct: Option<Vec<[f32; 4]>> = if self.want_direct {
            Some(
                ctx.read_buffer("path direct accumulators", &self.acc_direct, 2 * n)
                    .map_err(gpu_error)?,
            )
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
                self.ctx.info.name,
                i % n
            )));
        }
        let mut snap = Snapshot::from_gpu_halves(&total, direct.as_deref(), self.half_steps);
        if self.want_moments {
            let m: Vec<[f32; 4]> = ctx
                .read_buffer("path moment accumulators", &self.acc_moment, 6 * n)
                .map_err(gpu_error)?;
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
