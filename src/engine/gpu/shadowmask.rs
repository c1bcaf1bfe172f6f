//! The shadowmask pass: per valid texel, the baked visibility (0..1) of up to four chosen
//! lights, one per channel, and the direct light E/pi those lights bring, on the GPU with
//! shadow rays through the scene's BVH (`gpu::bvh`). `engine::shadowmask` chooses the
//! lights, steps this pass beside any technique and takes the lights' direct light out of
//! the lightmap (issue 26 point 3).
//!
//! How: `shaders/gpu/shadowmask.wgsl`, one invocation per texel. The sun is
//! `samples_per_step` directions uniform over its disc (soft penumbra, converging with the
//! steps); a directional, point or spot light of the scene is a delta light (glTF gives it
//! no size), one shadow ray to it, so its channel is 0 or 1 at the texel's sample point.
//! Each step is blended into the running mean of its half (even and odd steps, DESIGN
//! section 4), so the E/pi the bake subtracts keeps two independent halves and the bake's
//! error estimate includes this pass's noise.
//!
//! Space and buffers: world space, like `gpu::direct_light`, with its own upload of the
//! texels and of the scene (`gpu::scene_lights`; emitters are not chosen lights and are
//! left out of the tables' emitter list). Limits: the storage-binding limit
//! (`gpu::bvh::check_binding_size`) on the texels and the 64 B a texel of accumulators;
//! `samples_per_step` capped at [`MAX_SAMPLES_PER_STEP`].

use std::sync::Arc;

use glam::Vec3;
use wgpu::BufferUsages;

use super::bvh::check_binding_size;
use super::layout::{Bind, compute_pipeline, group_of, layout_of};
use super::scene_lights::{GpuSceneLights, LightSources};
use super::shaders::SHADOWMASK;
use super::texels::world_texels;
use super::{GpuContext, GpuError};
use crate::engine::atlas::Atlas;
use crate::engine::raytrace::{EmitterTable, Tracer};
use crate::engine::scene::{Lighting, Scene};

/// The most sun directions a texel takes per step.
pub const MAX_SAMPLES_PER_STEP: u32 = 64;

pub use crate::engine::accumulate::MASK_CHANNELS as CHANNELS;

/// `MASK_SUN` of the shader: the channel holds the job's sun.
const MASK_SUN: u32 = u32::MAX;

/// A light a channel holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskSource {
    /// The job's sun (`lighting.sun`).
    Sun,
    /// The scene's light of that index (`Scene::lights`).
    Light(usize),
}

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct MaskUniform {
    counts: [u32; 4],
    keys: [u32; 4],
    lights: [u32; 4],
    f: [f32; 4],
}

/// One half's running means per valid texel.
pub struct MaskHalf {
    /// Visibility of each channel's light (unused channels 0).
    pub visibility: Vec<[f32; CHANNELS]>,
    /// E/pi of the chosen lights together, shadowed.
    pub light: Vec<Vec3>,
}

/// The shadowmask of one bake's texels, accumulated on the GPU.
pub struct ShadowmaskPass {
    ctx: Arc<GpuContext>,
    label: String,
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    uniform_buf: wgpu::Buffer,
    uniform: MaskUniform,
    acc: wgpu::Buffer,
    texels: usize,
    half_steps: [u64; 2],
    _scene: GpuSceneLights,
    _texel_buf: wgpu::Buffer,
}

impl ShadowmaskPass {
    /// Prepares the pass for `lights` (1 to [`CHANNELS`], in channel order) at `atlas`'s
    /// texels. The caller has checked the lights exist (`engine::shadowmask::resolve`).
    pub fn new(
        ctx: Arc<GpuContext>,
        scene: &Scene,
        atlas: &Atlas,
        lighting: &Lighting,
        seed: u64,
        lights: &[MaskSource],
        samples_per_step: u32,
    ) -> Result<Self, GpuError> {
        let what = "shadowmask".to_string();
        if lights.is_empty() || lights.len() > CHANNELS {
            return Err(GpuError::Device {
                during: what,
                message: format!("1 to {CHANNELS} lights, got {}", lights.len()),
            });
        }
        let tracer = Tracer::new(scene);
        let no_emitters = EmitterTable::of(scene, |_| false);
        let scene_gpu = GpuSceneLights::new(&ctx, &what, scene, lighting, &tracer, &no_emitters, LightSources::NONE)?;
        let n = atlas.texels.len();
        let geom = world_texels(atlas);
        let acc_bytes = 2 * 2 * n.max(1) as u64 * 16;
        check_binding_size(&ctx, &format!("{what}: the texels"), geom.len() as u64 * 48)?;
        check_binding_size(&ctx, &format!("{what}: the accumulators"), acc_bytes)?;
        let texel_buf = ctx.buffer_init(
            &format!("{what} texels"),
            &geom,
            BufferUsages::STORAGE | BufferUsages::COPY_DST,
        );
        let acc = ctx.buffer_zeroed(
            &format!("{what} accumulators"),
            acc_bytes,
            BufferUsages::STORAGE | BufferUsages::COPY_SRC | BufferUsages::COPY_DST,
        );
        let mut slots = [MASK_SUN; 4];
        for (slot, l) in slots.iter_mut().zip(lights) {
            *slot = match l {
                MaskSource::Sun => MASK_SUN,
                MaskSource::Light(i) => *i as u32,
            };
        }
        let uniform = MaskUniform {
            counts: [n as u32, samples_per_step.clamp(1, MAX_SAMPLES_PER_STEP), 0, 0],
            keys: [seed as u32, (seed >> 32) as u32, lights.len() as u32, 0],
            lights: slots,
            f: [1.0, 0.0, 0.0, 0.0],
        };
        let uniform_buf = ctx.uniform(&format!("{what} params"), &uniform);
        let module = ctx.shader(&SHADOWMASK)?;
        let [b0, b1, b2, b3, b4] = scene_gpu.binds();
        let binds = [
            b0,
            b1,
            b2,
            b3,
            b4,
            Bind::Uniform(&uniform_buf),
            Bind::Read(&texel_buf),
            Bind::Write(&acc),
        ];
        let layout = layout_of(&ctx, &what, wgpu::ShaderStages::COMPUTE, &binds);
        let group = group_of(&ctx, &what, &layout, &binds);
        let pipeline = compute_pipeline(&ctx, &what, &module, "shadowmask", &layout);
        ctx.take_error(&format!("{what}: preparing the GPU pass"))?;
        tracing::debug!(texels = n, lights = lights.len(), "shadowmask pass");
        Ok(ShadowmaskPass {
            ctx,
            label: what,
            pipeline,
            group,
            uniform_buf,
            uniform,
            acc,
            texels: n,
            half_steps: [0, 0],
            _scene: scene_gpu,
            _texel_buf: texel_buf,
        })
    }

    /// Steps blended into each half so far.
    pub fn half_steps(&self) -> [u64; 2] {
        self.half_steps
    }

    /// Submits one step (one dispatch) into the half of its parity; does not wait.
    pub fn step(&mut self) -> Result<(), GpuError> {
        if self.texels == 0 {
            return Ok(());
        }
        let step = self.half_steps[0] + self.half_steps[1];
        let half = (step % 2) as usize;
        let k = self.half_steps[half] + 1;
        self.uniform.counts[2] = step as u32;
        self.uniform.counts[3] = half as u32;
        self.uniform.f[0] = 1.0 / k as f32;
        let ctx = &self.ctx;
        ctx.queue
            .write_buffer(&self.uniform_buf, 0, bytemuck::bytes_of(&self.uniform));
        ctx.submit_compute(&self.label, &self.pipeline, &self.group, self.texels as u32);
        ctx.take_error(&self.label)?;
        self.half_steps[half] = k;
        Ok(())
    }

    /// Both halves' running means per valid texel (blocks on the device); a half no step
    /// has reached reads 0.
    pub fn halves(&self) -> Result<[MaskHalf; 2], GpuError> {
        let n = self.texels;
        let raw: Vec<[f32; 4]> = if n == 0 {
            Vec::new()
        } else {
            self.ctx.read_buffer(&self.label, &self.acc, 4 * n)?
        };
        let half = |h: usize| {
            let r = &raw[2 * h * n..2 * (h + 1) * n];
            MaskHalf {
                visibility: r.chunks_exact(2).map(|p| p[0]).collect(),
                light: r
                    .chunks_exact(2)
                    .map(|p| Vec3::new(p[1][0], p[1][1], p[1][2]))
                    .collect(),
            }
        };
        Ok([half(0), half(1)])
    }
}
