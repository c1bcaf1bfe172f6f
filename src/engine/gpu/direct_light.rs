//! The shared direct-light module: E/pi, the incident irradiance over pi, from the sun,
//! directional, point and spot lights and emissive triangles at every valid texel, on
//! the GPU with shadow rays through the scene's BVH (`gpu::bvh`). A technique that does
//! not transport some of that light itself (`sdf`: all of it; `obscurance`: point and spot
//! lights) runs one [`DirectLight::step`] per step of its own and adds the halves it
//! reads back ([`DirectLight::halves`]) to its direct light, so no light of the job is
//! dropped (issue 21 point 1).
//!
//! How: `shaders/gpu/direct_light.wgsl`, one invocation per texel, `samples_per_step`
//! next-event estimates of `shaders/gpu/lights.wgsl` (the same estimator `path` uses at
//! each vertex, here with weight 1 since there is no continuation ray: plain light
//! sampling, unbiased), blended into the running mean of the step's half (even and odd
//! steps, DESIGN section 4), so the halves are two independent estimates and their
//! difference is the noise. Delta lights (point, spot, directional) cost one shadow ray
//! each and have no noise but their shadows' aliasing over the texel's sample point; the
//! sun is one direction in its cone per sample (soft penumbrae converge like everything
//! else); emitters are one triangle point per sample, picked by area x luminance
//! (`raytrace::EmitterTable`).
//!
//! With `hits` the pass also estimates, per texel, the cosine-weighted fraction of its
//! hemisphere that sees a surface (one ray to any distance per sample, directions below
//! the geometric plane counted as hits), which `sdf` weights its bounce by.
//!
//! Space: the world space the atlas's sample points are in (the BVH's), not the
//! normalised frame the raster techniques use; the texels are uploaded again here in
//! that space (48 B a texel), so this module depends on no technique's buffers.
//!
//! Limits: the BVH and tables must fit the adapter's storage-binding limit
//! (`gpu::scene_lights`); `samples_per_step` is capped at [`MAX_SAMPLES_PER_STEP`] so an
//! invocation stays far inside llvmpipe's loop budget (65535 iterations an invocation)
//! even with a few hundred lights; a scene with thousands of punctual lights pays one
//! shadow ray per light per sample (no light tree).

use std::sync::Arc;

use glam::Vec3;
use wgpu::BufferUsages;

use super::bvh::check_binding_size;
use super::layout::{Bind, compute_pipeline, group_of, layout_of};
use super::scene_lights::{GpuSceneLights, LightSources};
use super::shaders::DIRECT_LIGHT;
use super::texels::world_texels;
use super::{GpuContext, GpuError};
use crate::engine::atlas::Atlas;
use crate::engine::raytrace::{EmitterTable, Tracer};
use crate::engine::scene::{Lighting, Scene};

/// The most next-event estimates a texel takes per step.
pub const MAX_SAMPLES_PER_STEP: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct DirectUniform {
    counts: [u32; 4],
    keys: [u32; 4],
    f: [f32; 4],
}

/// One half's running means per valid texel.
pub struct DirectHalf {
    /// E/pi from the selected sources.
    pub light: Vec<Vec3>,
    /// The fraction of the cosine-weighted hemisphere that sees a surface (0 unless the
    /// pass was made with `hits`).
    pub hit: Vec<f32>,
}

const DIRECT_HITS: u32 = 1;

/// The direct light of one bake's texels, accumulated on the GPU.
pub struct DirectLight {
    ctx: Arc<GpuContext>,
    label: String,
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    uniform_buf: wgpu::Buffer,
    uniform: DirectUniform,
    acc: wgpu::Buffer,
    texels: usize,
    half_steps: [u64; 2],
    sources: LightSources,
    _scene: GpuSceneLights,
    _texel_buf: wgpu::Buffer,
}

impl DirectLight {
    /// Prepares the pass for `sources` of `scene` and `lighting` at `atlas`'s texels, or
    /// `None` when the scene has none of them (nothing to add, no GPU work). `label`
    /// names the technique in labels and errors; `emitters` restricts the emitters to
    /// those scene triangles (all when `None`); `hits` adds the hit-fraction estimate.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: Arc<GpuContext>,
        label: &str,
        scene: &Scene,
        atlas: &Atlas,
        lighting: &Lighting,
        seed: u64,
        sources: LightSources,
        emitters: Option<&[bool]>,
        samples_per_step: u32,
        hits: bool,
    ) -> Result<Option<Self>, GpuError> {
        let emitters = match emitters {
            Some(keep) => EmitterTable::of(scene, |i| keep.get(i).copied().unwrap_or(false)),
            None => EmitterTable::new(scene),
        };
        let sources = sources.present(scene, lighting, &emitters);
        if sources == LightSources::NONE {
            return Ok(None);
        }
        let what = format!("{label} direct light");
        let tracer = Tracer::new(scene);
        let scene_gpu = GpuSceneLights::new(&ctx, &what, scene, lighting, &tracer, &emitters, sources)?;
        let n = atlas.texels.len();
        let geom = world_texels(atlas);
        let acc_bytes = 2 * n.max(1) as u64 * 16;
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
        let uniform = DirectUniform {
            counts: [n as u32, samples_per_step.clamp(1, MAX_SAMPLES_PER_STEP), 0, 0],
            keys: [seed as u32, (seed >> 32) as u32, if hits { DIRECT_HITS } else { 0 }, 0],
            f: [1.0, 0.0, 0.0, 0.0],
        };
        let uniform_buf = ctx.uniform(&format!("{what} params"), &uniform);
        let module = ctx.shader(&DIRECT_LIGHT)?;
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
        let pipeline = compute_pipeline(&ctx, &what, &module, "direct", &layout);
        ctx.take_error(&format!("{what}: preparing the GPU pass"))?;
        tracing::debug!(
            technique = label,
            texels = n,
            sources = sources.0,
            "shared direct light"
        );
        Ok(Some(DirectLight {
            ctx,
            label: what,
            pipeline,
            group,
            uniform_buf,
            uniform,
            acc,
            texels: n,
            half_steps: [0, 0],
            sources,
            _scene: scene_gpu,
            _texel_buf: texel_buf,
        }))
    }

    /// The sources this pass estimates (those asked for that the scene has).
    pub fn sources(&self) -> LightSources {
        self.sources
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

    /// Both halves' running means per valid texel (blocks on the device). A half no
    /// step has reached yet reads 0.
    pub fn halves(&self) -> Result<[DirectHalf; 2], GpuError> {
        let n = self.texels;
        let raw: Vec<[f32; 4]> = if n == 0 {
            Vec::new()
        } else {
            self.ctx.read_buffer(&self.label, &self.acc, 2 * n)?
        };
        let half = |h: usize| {
            let r = &raw[h * n..(h + 1) * n];
            DirectHalf {
                light: r.iter().map(|a| Vec3::new(a[0], a[1], a[2])).collect(),
                hit: r.iter().map(|a| a[3]).collect(),
            }
        };
        Ok([half(0), half(1)])
    }
}
