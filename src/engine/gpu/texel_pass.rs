//! A compute pass that traces rays from every valid texel and keeps the even/odd half
//! running means on the GPU (DESIGN §4): what `path` on the GPU, the shared direct-light
//! pass (`gpu::direct_light`) and the shadowmask pass (`gpu::shadowmask`) each are. One
//! type owns their common part, so the bind list, the pipeline and the half bookkeeping
//! exist once: bindings 0-4 are the scene's rays and lights ([`GpuSceneLights`], the
//! bake's shared uploads), 5 the pass's uniform, 6 the world-space texels (shared per
//! texel set, `gpu::scene_rays`), then the pass's accumulators, in the order given, then
//! its read-only tables (`path`'s Sobol direction numbers), in the order given.
//!
//! How a step runs: the step's parity picks its half; the half's k-th step is blended
//! with weight 1/k into that half's running mean (the shader reads the weight), so a
//! half is the mean of its steps and the two halves are independent estimates whose
//! difference is the noise. One dispatch of one invocation per texel. A pass with
//! [`TexelRayPass::keep_latest`] set blends with weight 1 instead, so each half holds its
//! latest step's estimate: for a technique that weights steps its own way (`sdb` folds
//! them into blends of its own) and reads that buffer on the device
//! ([`TexelRayPass::accumulator`]). At most
//! [`STEPS_IN_FLIGHT`] steps are queued: `step` waits for the oldest before it returns
//! when more are. Without that bound a step returned in microseconds, the bake loop
//! queued thousands of them between snapshots, and its clock (time limit, longest step,
//! progress) measured the queueing, not the work: the first snapshot after a burst then
//! waited for all of it, past any time limit. Two in flight keep the device busy while
//! the host prepares the next.
//!
//! A step can also run in slices of invocations, each waited for, with a check between
//! them that may abandon the step and put its half back ([`TexelRayPass::step_sliced`]):
//! what `path` does with a long step in a bake that has a deadline or may be cancelled.
//!
//! Limits: each accumulator must fit the storage-binding limit (checked here, naming the
//! pass); the step counts go to the shader in 32 bits; a sliced step holds one more copy of
//! a half of every accumulator.

use std::collections::VecDeque;
use std::sync::Arc;

use bytemuck::Pod;

use super::bvh::check_binding_size;
use super::layout::{Bind, compute_pipeline, group_of, layout_of};
use super::scene_lights::{GpuSceneLights, LightSources};
use super::scene_rays::SceneRays;
use super::shaders::PassShader;
use super::slices::{Aside, StepSlicer};
pub use super::slices::{LONG_STEP, Sliced};
use super::texels::GpuTexelGeom;
use super::{GpuContext, GpuError};
use crate::engine::atlas::Atlas;
use crate::engine::raytrace::EmitterTable;
use crate::engine::scene::Lighting;

/// The most steps queued on the device at once (see the module doc).
pub const STEPS_IN_FLIGHT: usize = 2;

/// A pass's uniform (binding 5), told which step it is about to run.
pub trait StepUniform: Pod {
    /// `step`: the job's global step index; `half`: 0 (even) or 1 (odd); `weight`: 1/k
    /// for the half's k-th step.
    fn set_step(&mut self, step: u64, half: u32, weight: f32);
    /// The invocations of the next dispatch are `first`, `first + 1`, … of the step's
    /// (a slice, [`TexelRayPass::step_sliced`]); a pass that cannot slice ignores it and
    /// must not be stepped sliced.
    fn set_slice(&mut self, _first: u32, _count: u32) {}
}

/// What a [`TexelRayPass`] is made of beyond the scene and its texels.
pub struct PassSpec<'a> {
    /// Names the pass in labels and errors.
    pub what: &'a str,
    pub shader: &'a PassShader,
    pub entry: &'a str,
    /// The lights its next-event estimation samples, and the emitters it may pick.
    pub sources: LightSources,
    pub emitters: &'a EmitterTable,
    /// Each accumulator's label and size in bytes (bindings 7, 8, ...).
    pub accumulators: &'a [(&'a str, u64)],
    /// Read-only tables the shader reads, each with its label (the bindings after the
    /// accumulators).
    pub tables: &'a [(&'a str, &'a [u32])],
}

/// One texel pass of one bake (see the module doc).
pub struct TexelRayPass<U: StepUniform> {
    ctx: Arc<GpuContext>,
    label: String,
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    uniform_buf: wgpu::Buffer,
    /// The uniform as last written; fields a pass owns may be changed between steps.
    pub uniform: U,
    accumulators: Vec<(String, wgpu::Buffer)>,
    texels: usize,
    half_steps: [u64; 2],
    /// The submissions of the steps not yet known to be done, oldest first.
    in_flight: VecDeque<wgpu::SubmissionIndex>,
    /// The job's index of this bake's first step (a task's, `engine::tasks`).
    pub first_step: u64,
    /// Replace each half with its latest step instead of averaging (see the module doc).
    pub keep_latest: bool,
    pub lights: GpuSceneLights,
    _texels: Arc<wgpu::Buffer>,
    /// Bound in `group`; kept with it.
    _tables: Vec<wgpu::Buffer>,
    /// Its slicing state ([`TexelRayPass::step_watched`]): the half aside, the last
    /// step's length.
    slicer: StepSlicer,
}

impl<U: StepUniform> TexelRayPass<U> {
    pub fn new(
        ctx: Arc<GpuContext>,
        rays: &SceneRays,
        atlas: &Arc<Atlas>,
        lighting: &Lighting,
        spec: PassSpec<'_>,
        uniform: U,
    ) -> Result<Self, GpuError> {
        let texels = rays.gpu_texels(&ctx, spec.what, atlas)?;
        Self::build(ctx, rays, texels, atlas.texels.len(), lighting, spec, uniform)
    }

    /// A pass over `points` given by the caller (in the texels' layout, world space; `path`'s
    /// light probes), each run by `lanes` consecutive invocations: one dispatch runs
    /// `points.len() * lanes` invocations, and the shader finds its point as the
    /// invocation index over `lanes`. At least one point.
    pub fn over_points(
        ctx: Arc<GpuContext>,
        rays: &SceneRays,
        points: &[GpuTexelGeom],
        lanes: u32,
        lighting: &Lighting,
        spec: PassSpec<'_>,
        uniform: U,
    ) -> Result<Self, GpuError> {
        let what = spec.what;
        check_binding_size(&ctx, &format!("{what}: the points"), points.len() as u64 * 48)?;
        let invocations = points.len() as u64 * lanes as u64;
        if invocations > u32::MAX as u64 {
            return Err(GpuError::Unsupported {
                adapter: ctx.info.name.clone(),
                missing: format!(
                    "{what}: {} points of {lanes} invocations each, more than one dispatch counts (2^32)",
                    points.len()
                ),
            });
        }
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let buffer = Arc::new(ctx.buffer_init(&format!("{what} points"), points, usage));
        Self::build(ctx, rays, buffer, invocations as usize, lighting, spec, uniform)
    }

    fn build(
        ctx: Arc<GpuContext>,
        rays: &SceneRays,
        texels: Arc<wgpu::Buffer>,
        invocations: usize,
        lighting: &Lighting,
        spec: PassSpec<'_>,
        uniform: U,
    ) -> Result<Self, GpuError> {
        let what = spec.what;
        let lights = GpuSceneLights::new(&ctx, what, rays, lighting, spec.emitters, spec.sources)?;
        let mut accumulators = Vec::with_capacity(spec.accumulators.len());
        for (name, bytes) in spec.accumulators {
            check_binding_size(&ctx, &format!("{what}: the {name}"), *bytes)?;
            let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
            let label = format!("{what} {name}");
            let buffer = ctx.buffer_zeroed(&label, (*bytes).max(16), usage);
            accumulators.push((label, buffer));
        }
        let tables: Vec<wgpu::Buffer> = spec
            .tables
            .iter()
            .map(|(name, data)| ctx.buffer_init(&format!("{what} {name}"), data, wgpu::BufferUsages::STORAGE))
            .collect();
        let uniform_buf = ctx.uniform(&format!("{what} params"), &uniform);
        let module = ctx.shader(spec.shader)?;
        let mut binds: Vec<Bind<'_>> = lights.binds().to_vec();
        binds.push(Bind::Uniform(&uniform_buf));
        binds.push(Bind::Read(&texels));
        binds.extend(accumulators.iter().map(|(_, b)| Bind::Write(b)));
        binds.extend(tables.iter().map(Bind::Read));
        let layout = layout_of(&ctx, what, wgpu::ShaderStages::COMPUTE, &binds);
        let group = group_of(&ctx, what, &layout, &binds);
        let pipeline = compute_pipeline(&ctx, what, &module, spec.entry, &layout);
        ctx.take_error(&format!("{what}: preparing the GPU pass"))?;
        Ok(TexelRayPass {
            ctx,
            label: what.to_string(),
            pipeline,
            group,
            uniform_buf,
            uniform,
            accumulators,
            texels: invocations,
            half_steps: [0, 0],
            in_flight: VecDeque::with_capacity(STEPS_IN_FLIGHT + 1),
            first_step: 0,
            keep_latest: false,
            lights,
            _texels: texels,
            _tables: tables,
            slicer: StepSlicer::new(what),
        })
    }

    pub fn ctx(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// The invocations of one step: the valid texels the pass runs over, or the points
    /// times their lanes ([`TexelRayPass::over_points`]).
    pub fn texels(&self) -> usize {
        self.texels
    }

    /// Steps blended into each half so far.
    pub fn half_steps(&self) -> [u64; 2] {
        self.half_steps
    }

    /// Submits one step (one dispatch) into the half of its parity; waits only while more
    /// than [`STEPS_IN_FLIGHT`] steps are queued.
    pub fn step(&mut self) -> Result<(), GpuError> {
        let step = self.half_steps[0] + self.half_steps[1];
        let half = (step % 2) as usize;
        let k = self.half_steps[half] + 1;
        if self.texels > 0 {
            let weight = if self.keep_latest { 1.0 } else { 1.0 / k as f32 };
            self.uniform.set_step(self.first_step + step, half as u32, weight);
            self.uniform.set_slice(0, self.texels as u32);
            self.ctx
                .queue
                .write_buffer(&self.uniform_buf, 0, bytemuck::bytes_of(&self.uniform));
            let submitted = self
                .ctx
                .submit_compute(&self.label, &self.pipeline, &self.group, self.texels as u32);
            self.in_flight.push_back(submitted);
            while self.in_flight.len() > STEPS_IN_FLIGHT {
                let oldest = self.in_flight.pop_front().expect("more than one in flight");
                self.ctx.wait_for(&self.label, oldest)?;
            }
            self.ctx.take_error(&self.label)?;
        }
        self.half_steps[half] = k;
        Ok(())
    }

    /// One step of a bake that has a deadline or a watcher that may cancel (`go_on` Some:
    /// asked between slices whether to go on, as in [`TexelRayPass::step_sliced`]), or of
    /// one that has neither (None: a whole step). A watched step that may be long (the
    /// first, its length not known yet, and any after a step of [`LONG_STEP`] or more) runs
    /// in slices; a shorter one runs whole and pipelined.
    pub fn step_watched(&mut self, go_on: Option<&mut dyn FnMut(u64, u64) -> bool>) -> Result<Sliced, GpuError> {
        if let Some(go_on) = go_on
            && self.slicer.slices(true)
        {
            return self.step_sliced(go_on);
        }
        self.step()?;
        self.slicer.returned_whole();
        Ok(Sliced::Done)
    }

    /// Forgets the last step's length: the next watched step is sliced and timed again
    /// (a new deadline).
    pub fn forget_step_length(&mut self) {
        self.slicer.forget();
    }

    /// One step in slices of invocations, each waited for, `go_on(done, of)` asked after
    /// each with the invocations done so far (issue 19 point 10: a step of minutes on a
    /// large level can stop at a deadline or a cancel). Sliced or whole, a step writes the
    /// same values (each invocation reads only its own texel's slots). When `go_on`
    /// says stop before the last slice, the step's half is put back as it was: it is
    /// copied aside before the first slice and copied back, so the step adds nothing and
    /// [`half_steps`](TexelRayPass::half_steps) stays. Needs the uniform's
    /// [`StepUniform::set_slice`], and accumulators that hold the two halves one after the
    /// other (half h is the buffer's h-th half; a one-vec4 placeholder is left alone).
    /// Costs: one copy of a half (aside) a step, and the pipelining of
    /// [`STEPS_IN_FLIGHT`]; slices are sized to [`SLICE_SECONDS`](super::slices::SLICE_SECONDS) from the last one's time.
    pub fn step_sliced(&mut self, go_on: &mut dyn FnMut(u64, u64) -> bool) -> Result<Sliced, GpuError> {
        let step = self.half_steps[0] + self.half_steps[1];
        let half = (step % 2) as usize;
        let k = self.half_steps[half] + 1;
        let n = self.texels as u64;
        if n == 0 {
            self.half_steps[half] = k;
            return Ok(Sliced::Done);
        }
        let weight = if self.keep_latest { 1.0 } else { 1.0 / k as f32 };
        self.uniform.set_step(self.first_step + step, half as u32, weight);
        let aside: Vec<Aside<'_>> = self.accumulators.iter().map(|(_, b)| Aside::half(b, half)).collect();
        let (ctx, label, pipeline, group) = (&self.ctx, &self.label, &self.pipeline, &self.group);
        let (uniform, uniform_buf) = (&mut self.uniform, &self.uniform_buf);
        let mut submit = |first: u64, count: u64| {
            uniform.set_slice(first as u32, count as u32);
            ctx.queue.write_buffer(uniform_buf, 0, bytemuck::bytes_of(&*uniform));
            Ok(ctx.submit_compute(label, pipeline, group, count as u32))
        };
        let done = self.slicer.run(&self.ctx, n, &aside, &mut submit, go_on)?;
        self.in_flight.clear();
        if done == Sliced::Done {
            self.half_steps[half] = k;
        }
        Ok(done)
    }

    /// Accumulator `index` itself, for a pass of the same device that reads it.
    pub fn accumulator(&self, index: usize) -> &wgpu::Buffer {
        &self.accumulators[index].1
    }

    /// The first `count` vec4 of accumulator `index` (blocks on the device).
    pub fn read(&self, index: usize, count: usize) -> Result<Vec<[f32; 4]>, GpuError> {
        if count == 0 {
            return Ok(Vec::new());
        }
        let (label, buffer) = &self.accumulators[index];
        self.ctx.read_buffer(label, buffer, count)
    }
}
