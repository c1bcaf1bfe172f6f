//! One `sdb` step on the engine: the random direction's maps rendered, the resolve and
//! gather passes, the direct light and the small emitters, the halves' blend and
//! weights, stopping inside a step and putting back what it wrote, a boundary held for a
//! bake in rounds, and the halves read back (the module doc of `sdb`, "How").

use glam::Vec3;

use super::super::api::{StepProgress, go_on_until};
use crate::engine::gpu::directions::sample_cone;
use crate::engine::gpu::shadow::{ShadowDraw, ShadowView};
use crate::engine::gpu::slices::{Aside, Sliced, StepSlicer};
use crate::engine::gpu::view::{DEPTH_NEAREST, DEPTH_STOCHASTIC, EMPTY_T, make_view};
use crate::engine::gpu::{self, GpuError};

use super::{
    AccumulationMode, EPS_ALONG_D, EPS_NORMAL_PLANE, GpuDirectParams, GpuEmitterAddParams, GpuGatherParams,
    GpuResolveParams, SHADOW_OFFSET_PIXELS, SdbEngine, SdbHalf, StepBook,
};

impl SdbEngine {
    /// Leaky start-up correction: an exponential average started from zero has total
    /// weight 1 - (1 - b)^n.
    fn leaky_correction(&self, n: u64) -> f64 {
        if n == 0 {
            0.0
        } else {
            1.0 / (1.0 - (1.0 - self.params.blend as f64).powf(n as f64))
        }
    }

    /// The weights that turn the two halves into the current estimate: gathered (x, y),
    /// sun accumulators (z, w). The gathered halves are ratios, so a leaky half needs no
    /// start-up correction there; the sun's plain blends do.
    fn half_scales(&self) -> [f32; 4] {
        match self.params.mode {
            AccumulationMode::Average => {
                let total = self.weights[0] + self.weights[1];
                if total == 0.0 {
                    [0.0; 4]
                } else {
                    let (a, b) = ((self.weights[0] / total) as f32, (self.weights[1] / total) as f32);
                    [a, b, a, b]
                }
            }
            AccumulationMode::Leaky => {
                let live = self.dirs.iter().filter(|&&n| n > 0).count().max(1) as f64;
                let share = |h: usize| if self.dirs[h] > 0 { (1.0 / live) as f32 } else { 0.0 };
                [
                    share(0),
                    share(1),
                    (self.leaky_correction(self.dirs[0]) / live) as f32,
                    (self.leaky_correction(self.dirs[1]) / live) as f32,
                ]
            }
        }
    }

    /// Blend factor for the next direction of half `h` (and book-keeping).
    fn next_blend(&mut self, h: usize) -> f32 {
        self.dirs[h] += 1;
        match self.params.mode {
            AccumulationMode::Leaky => self.params.blend,
            AccumulationMode::Average => {
                let w = (self.dirs[h] as f64).powf(self.params.ramp as f64);
                self.weights[h] += w;
                (w / self.weights[h]) as f32
            }
        }
    }

    /// With the ambient-mode correction the first step only bootstraps: it gathers with
    /// nothing fed (so it sees emitters and the sky alone) and gives the correction the
    /// shape of the light, v = x. Once the second step's resolve has fed x + delta, its
    /// gathers are cleared from the accumulators: kept, they would weigh in the mean as a
    /// share of the wrong answer (2 / n^2 of it after n steps with `ramp` 1), which in a
    /// stiff room is most of the error left.
    fn drop_bootstrap_step(&mut self, encoder: &mut wgpu::CommandEncoder) {
        for b in self.accumulators() {
            encoder.clear_buffer(b, 0, None);
        }
        // The other half (odd, about to take this step's directions) is still empty.
        self.dirs[0] = 0;
        self.weights[0] = 0.0;
        self.half_steps[0] = 0;
    }

    /// Every accumulator a step blends into (both halves each): the lightmap's, the fed
    /// estimate's, and the sun's and the direct layer's where they exist.
    fn accumulators(&self) -> impl Iterator<Item = &wgpu::Buffer> {
        [
            Some(&self.acc_buf),
            Some(&self.fed_acc_buf),
            self.sun_acc_buf.as_ref(),
            self.direct_acc_buf.as_ref(),
        ]
        .into_iter()
        .flatten()
    }

    /// Render the map along the current view into array layer `layer`; the layer goes to
    /// the shaders as the instance index and into the depth hash, so layers are
    /// independent draws of the stochastic depth.
    fn render_map(&self, encoder: &mut wgpu::CommandEncoder, label: &str, layer: u32) {
        let attachment = |view, a: f64| {
            Some(wgpu::RenderPassColorAttachment {
                view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color {
                        r: 0.0,
                        g: 0.0,
                        b: 0.0,
                        a,
                    }),
                    store: wgpu::StoreOp::Store,
                },
            })
        };
        let l = layer as usize;
        let mut colors = vec![attachment(&self.illum_layer_views[l], EMPTY_T as f64)];
        if let Some(v) = &self.emission_layer_views {
            colors.push(attachment(&v[l], 0.0));
        }
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some(label),
            color_attachments: &colors,
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &self.depth_view,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.illum_pipeline);
        pass.set_bind_group(0, &self.illum_bg, &[]);
        pass.set_vertex_buffer(0, self.vertex_buf.slice(..));
        pass.draw(0..self.vertex_count, layer..layer + 1);
    }

    fn dispatch(
        encoder: &mut wgpu::CommandEncoder,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        bg: &wgpu::BindGroup,
        size: (u32, u32),
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bg, &[]);
        pass.dispatch_workgroups(size.0, size.1, 1);
    }

    fn jitter(&mut self) -> (f32, f32) {
        (self.rng.next_f64() as f32, self.rng.next_f64() as f32)
    }

    /// The resolve pass (and, with the ambient-mode correction, the bootstrap step's
    /// drop), submitted.
    fn submit_resolve(&mut self) -> wgpu::SubmissionIndex {
        let ambient = self.ambient_factor.map_or([0.0; 4], |f| f.extend(0.0).to_array());
        let resolve = GpuResolveParams {
            scale: self.half_scales(),
            dims: self.lm_dims,
            ambient,
            receivers: [self.receivers.start, self.receivers.end, 0, 0],
        };
        self.ctx
            .queue
            .write_buffer(&self.resolve_buf, 0, bytemuck::bytes_of(&resolve));
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("sdb resolve"),
        });
        if self.ambient_factor.is_some() {
            Self::dispatch(
                &mut encoder,
                "sdb ambient mode",
                &self.ambient_pipeline,
                &self.resolve_bg,
                (1, 1),
            );
        }
        Self::dispatch(
            &mut encoder,
            "sdb resolve",
            &self.resolve_pipeline,
            &self.resolve_bg,
            self.pixel_dispatch,
        );
        if self.bootstraps() {
            self.drop_bootstrap_step(&mut encoder);
        }
        self.ctx.queue.submit([encoder.finish()])
    }

    /// Directions `first .. first + count` of this step (`j` in the pairs rule below),
    /// each its illumination maps, gather, and sun maps and direct passes, submitted;
    /// `previous` is the last direction drawn and `decay` what the blends leave of the old
    /// mean, both carried from one call to the next. Returns the last submission.
    fn submit_directions(
        &mut self,
        parity: u32,
        (first, count): (u64, u64),
        previous: &mut Vec3,
        decay: &mut f64,
    ) -> wgpu::SubmissionIndex {
        // With the ambient-mode correction, directions come in antipodal pairs (d, -d)
        // within one step: every texel of a closed surface then gathers (and records the
        // step's feed in its fed mean M) in exactly one of the two, which the correction's
        // model x = T M + e needs. With one direction a step, the surfaces a texel sees
        // along d face -d and do not gather that step, M lags the feed their neighbours
        // used, <x - M> is biased, and the gain g / (1 - g) (9 at albedo 0.9) fed that bias
        // back: the closed box of albedo 0.9 read 17.6 instead of 1 with seed 7 (issue 21).
        let pairs = self.ambient_factor.is_some();
        let mut last = None;
        for j in first..first + count {
            let d = if pairs && j % 2 == 1 {
                -*previous
            } else {
                self.directions.next_direction()
            };
            *previous = d;
            let dir_index = self.dirs[0] + self.dirs[1];
            let blend = self.next_blend(parity as usize);
            *decay *= 1.0 - blend as f64;
            let seed = (self.rng.next_u64() >> 32) as u32 ^ dir_index as u32;
            let jitter = self.jitter();
            let view = make_view(
                d,
                &self.corners,
                self.params.map_pixels(),
                jitter,
                seed,
                DEPTH_STOCHASTIC,
            );
            let env = self.environment.as_ref().map_or(Vec3::ZERO, |e| e(d));
            let gather = GpuGatherParams {
                env: [env.x, env.y, env.z, blend],
                eps: [EPS_NORMAL_PLANE, EPS_ALONG_D, 0.0, 0.0],
                misc: [
                    (self.params.neighbourhood - 1) / 2,
                    self.params.depth_layers,
                    parity,
                    self.n_texels,
                ],
                texels: [self.receivers.start, self.receivers.len() as u32, 0, 0],
            };
            self.ctx
                .queue
                .write_buffer(&self.view_buf, 0, bytemuck::bytes_of(&view));
            self.ctx
                .queue
                .write_buffer(&self.gather_buf, 0, bytemuck::bytes_of(&gather));
            let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("sdb direction"),
            });
            for layer in 0..self.params.depth_layers {
                self.render_map(&mut encoder, "sdb illumination map", layer);
            }
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("sdb gather"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.gather_pipeline);
                pass.set_bind_group(0, &self.gather_bg, &[]);
                if let Some(bg) = &self.gather_direct_bg {
                    pass.set_bind_group(1, bg, &[]);
                }
                pass.dispatch_workgroups(self.texel_dispatch.0, self.texel_dispatch.1, 1);
            }
            // Uniform writes land before the next submit, so each map that reuses the
            // view buffer goes in its own submission.
            last = Some(self.ctx.queue.submit([encoder.finish()]));

            if let Some(sun) = &self.sun_maps {
                for li in 0..self.lights.len() {
                    let light = self.lights[li];
                    let ld = sample_cone(light.direction, light.cone_half_angle, &mut self.rng);
                    // `jitter()`'s draws, with the maps borrowed.
                    let jitter = (self.rng.next_f64() as f32, self.rng.next_f64() as f32);
                    let view = make_view(ld, &self.corners, self.params.map_pixels(), jitter, 0, DEPTH_NEAREST);
                    let map = ShadowView::ortho_of(&view, [0, 0]);
                    let e = light.irradiance_over_pi;
                    let direct = GpuDirectParams {
                        irradiance: [e.x, e.y, e.z, blend],
                        bias: [SHADOW_OFFSET_PIXELS, 0.0, if li == 0 { 1.0 - blend } else { 1.0 }, 0.0],
                        misc: [parity, self.n_texels, self.receivers.start, self.receivers.len() as u32],
                    };
                    self.ctx.queue.write_buffer(&sun.views_buf, 0, bytemuck::bytes_of(&map));
                    self.ctx
                        .queue
                        .write_buffer(&self.direct_buf, 0, bytemuck::bytes_of(&direct));
                    let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("sdb direct light"),
                    });
                    let n = self.params.map_pixels();
                    let draw = ShadowDraw {
                        view: 0,
                        tile: [0, 0, n],
                        rows: n,
                    };
                    sun.atlas
                        .render(&mut encoder, &self.vertex_buf, self.vertex_count, [draw]);
                    Self::dispatch(&mut encoder, "sdb direct", &sun.pipeline, &sun.bg, self.texel_dispatch);
                    last = Some(self.ctx.queue.submit([encoder.finish()]));
                }
            }
        }
        last.expect("a slice has at least one direction")
    }

    /// One step: resolve, then `directions_per_step` directions (illumination map and
    /// gather, plus a shadow map and direct pass per directional light), then the small
    /// lights. Submits work and returns without waiting for it; nothing is read back.
    ///
    /// In a bake with a time limit or a watcher (issue 19 point 10) the resolve and the
    /// directions run in slices of whole passes (the resolve, then whole directions), each
    /// waited for (`gpu::slices`,
    /// sized to about 50 ms), with what they write put aside first (the accumulators'
    /// halves of this step's parity; whole buffers on the step that drops the bootstrap
    /// step, which clears them), and the small lights' pass runs sliced when it may be
    /// long. A stop between two slices of either puts back the device's accumulators and
    /// the host's directions, random stream and weights, so the step adds nothing and
    /// the next is the one it would have been.
    pub fn step(&mut self) -> Result<(), GpuError> {
        let parity = (self.steps_done % 2) as u32;
        let before = StepBook {
            directions: self.directions.clone(),
            rng: self.rng.clone(),
            dirs: self.dirs,
            weights: self.weights,
            half_steps: self.half_steps,
        };
        let pairs = self.ambient_factor.is_some();
        let count = (self.params.directions_per_step * if pairs { 2 } else { 1 }) as u64;
        let mut previous = Vec3::Z;
        let mut decay = 1.0f64;
        let watched = self.deadline.is_some() || self.progress.is_some();
        let (deadline, progress) = (self.deadline, self.progress.clone());
        let mut go_on = go_on_until(deadline, progress.as_ref());
        let small = self
            .small_emitters
            .as_ref()
            .is_some_and(|p| p.lights.every_step || self.steps_done < 2);
        let ctx = self.ctx.clone();
        let bootstrap = self.bootstraps();
        // Handles (not borrows): the slices' closure borrows `self` mutably.
        let buffers: Vec<wgpu::Buffer> = self.accumulators().cloned().collect();
        let aside: Vec<Aside<'_>> = buffers
            .iter()
            .map(|b| {
                if bootstrap {
                    Aside::whole(b)
                } else {
                    Aside::half(b, parity as usize)
                }
            })
            .collect();
        if watched {
            // The directions are the step's progress, or its first half with small lights.
            let parts = if small { 2 } else { 1 };
            let mut first_half = |done: u64, of: u64| go_on(done, parts * of);
            let mut slicer = std::mem::replace(&mut self.slicer, StepSlicer::per_unit("sdb directions"));
            // Unit 0 is the resolve (a pass over every lightmap pixel, 0.2 s at 2048² on
            // lavapipe), units 1 ..= count the directions.
            let mut submit = |first: u64, k: u64| {
                let mut last = None;
                if first == 0 {
                    last = Some(self.submit_resolve());
                }
                let directions = (first.max(1) - 1, first + k - first.max(1));
                if directions.1 > 0 {
                    last = Some(self.submit_directions(parity, directions, &mut previous, &mut decay));
                }
                Ok(last.expect("a slice has at least one unit"))
            };
            let done = slicer.run(&ctx, count + 1, &aside, &mut submit, &mut first_half);
            self.slicer = slicer;
            if done? == Sliced::Abandoned {
                self.undo(before);
                return Ok(());
            }
        } else {
            self.submit_resolve();
            if count > 0 {
                self.submit_directions(parity, (0, count), &mut previous, &mut decay);
            }
        }
        if let Some(pass) = &mut self.small_emitters {
            // Point and spot lights alone are the same every step: one step a half.
            if small {
                let mut second_half = |done: u64, of: u64| go_on(of + done, 2 * of);
                let done = pass
                    .lights
                    .light
                    .step_watched(watched.then_some(&mut second_half as &mut dyn FnMut(u64, u64) -> bool))?;
                if done == Sliced::Abandoned {
                    // The directions finished (sliced, so what they wrote is aside).
                    self.slicer.put_back(&ctx, &aside)?;
                    self.undo(before);
                    return Ok(());
                }
            }
            // With directional lights their blends already decayed the mean this step.
            let old = if self.lights.is_empty() { decay } else { 1.0 };
            let params = GpuEmitterAddParams {
                mix: [old as f32, (1.0 - decay) as f32, 0.0, 0.0],
                misc: [parity, self.n_texels, self.receivers.start, self.receivers.len() as u32],
            };
            self.ctx
                .queue
                .write_buffer(&pass.params, 0, bytemuck::bytes_of(&params));
            let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("sdb small emitters"),
            });
            Self::dispatch(
                &mut encoder,
                "sdb small emitters",
                &pass.pipeline,
                &pass.bg,
                self.texel_dispatch,
            );
            self.ctx.queue.submit([encoder.finish()]);
        }
        self.half_steps[parity as usize] += 1;
        self.steps_done += 1;
        self.ctx.take_error("sdb step")
    }

    /// Whether this step drops the bootstrap step ([`SdbEngine::drop_bootstrap_step`]):
    /// step 1 with the ambient-mode correction, unless the accumulators went on from a
    /// round before (their estimate already has the light's shape).
    fn bootstraps(&self) -> bool {
        self.ambient_factor.is_some() && self.steps_done == 1 && !self.starts_lit
    }

    /// Holds every texel outside `receivers` at `held` (E/pi) for the bake's steps and
    /// resumes the receivers' halves from `resume` (`Technique::hold_boundary`, a round
    /// of a bake in rounds, `engine::rounds`). How:
    /// - a held texel's gathered accumulators are (held, 1) in both halves, so the
    ///   resolve's ratio reads `held`, and its fed accumulators (held, 0), so the
    ///   ambient-mode residual there is 0; its light accumulators are zero. The gather,
    ///   the sun's and the small lights' passes run over the receivers only (their
    ///   `texels` range), so nothing writes them; the bootstrap step, whose clear would,
    ///   is skipped when any held light is not zero (in round 0 it all is: cleared, a
    ///   held texel still reads 0).
    /// - a resumed receiver's half is (mean, 1): the half's mean with the weight one
    ///   direction has on average (4 max(<d, n>, 0) over the sphere: 1), so a new
    ///   direction's blend, with the host's weights set to sum i^ramp over the half's
    ///   directions so far, weighs the old mean as one bake's running mean would (up to
    ///   the difference between 1 and the directions' actual mean weight at that texel,
    ///   which stratified directions keep small); its light accumulators start at zero,
    ///   the mean holding their share so far; no bootstrap step.
    /// - the ambient-mode correction is measured over the receivers and added to them
    ///   only (`shaders/sdb/resolve.wgsl`, `receivers`).
    ///
    /// Refused in `leaky` mode, whose blend forgets on purpose (its resumed weights would
    /// mean nothing), and after the first step.
    pub fn hold_boundary(
        &mut self,
        receivers: std::ops::Range<usize>,
        held: &[Vec3],
        resume: Option<(&SdbHalf, &SdbHalf)>,
    ) -> Result<(), String> {
        let n = self.n_texels as usize;
        if self.steps_done > 0 {
            return Err("sdb: a boundary is held from the first step on".into());
        }
        if self.params.mode == AccumulationMode::Leaky {
            return Err(
                "sdb in leaky mode is not baked in rounds (its blend forgets on purpose, so a round cannot resume it); use mode average"
                    .into(),
            );
        }
        if held.len() != n || receivers.start > receivers.end || receivers.end > n {
            return Err(format!(
                "sdb: a boundary of {} held texels and receivers {receivers:?} for {n} texels",
                held.len()
            ));
        }
        let r = receivers.clone();
        let zero = [0.0f32; 4];
        let mut acc = vec![zero; 2 * n];
        let mut fed = vec![zero; 2 * n];
        let mut direct = self.direct_acc_buf.as_ref().map(|_| vec![zero; 2 * n]);
        for h in 0..2 {
            for (i, v) in held.iter().enumerate() {
                if !r.contains(&i) {
                    acc[h * n + i] = v.extend(1.0).to_array();
                    fed[h * n + i] = v.extend(0.0).to_array();
                }
            }
        }
        if let Some((even, odd)) = resume {
            let per_step =
                u64::from(self.params.directions_per_step) * if self.ambient_factor.is_some() { 2 } else { 1 };
            for (h, half) in [even, odd].into_iter().enumerate() {
                if half.total.len() != r.len() || half.direct.is_some() != direct.is_some() {
                    return Err(format!(
                        "sdb: resumed halves of {} texels (direct layer: {}) for {} receivers (direct layer: {})",
                        half.total.len(),
                        half.direct.is_some(),
                        r.len(),
                        direct.is_some()
                    ));
                }
                for (k, v) in half.total.iter().enumerate() {
                    acc[h * n + r.start + k] = v.extend(1.0).to_array();
                    fed[h * n + r.start + k] = v.extend(0.0).to_array();
                }
                if let (Some(d), Some(out)) = (&half.direct, direct.as_mut()) {
                    for (k, v) in d.iter().enumerate() {
                        out[h * n + r.start + k] = v.extend(0.0).to_array();
                    }
                }
                self.half_steps[h] = half.steps;
                self.dirs[h] = half.steps * per_step;
                self.weights[h] = (1..=self.dirs[h])
                    .map(|i| (i as f64).powf(f64::from(self.params.ramp)))
                    .sum();
            }
        }
        self.starts_lit = resume.is_some() || held.iter().any(|v| *v != Vec3::ZERO);
        let q = &self.ctx.queue;
        q.write_buffer(&self.acc_buf, 0, bytemuck::cast_slice(&acc));
        q.write_buffer(&self.fed_acc_buf, 0, bytemuck::cast_slice(&fed));
        if let (Some(b), Some(d)) = (&self.direct_acc_buf, &direct) {
            q.write_buffer(b, 0, bytemuck::cast_slice(d));
        }
        // The light accumulators stay as created, zero: no step has run.
        self.receivers = r.start as u32..r.end as u32;
        self.texel_dispatch = gpu::dispatch_size_64(self.receivers.len() as u32);
        self.ctx.take_error("sdb boundary").map_err(|e| e.to_string())
    }

    /// Runs the first step's resolve once and waits for it, at preparation: the first
    /// resolve of a bake costs seconds more than the others on a large page (1.4 s
    /// against 0.2-0.3 s at 2048² on lavapipe: first use of the lightmap-sized buffers
    /// and of the pass), and a step cannot stop inside one pass. It writes what step 0's
    /// resolve writes again (the resolve reads only the accumulators, still empty), so a
    /// bake's values do not change.
    pub fn warm_up(&mut self) -> Result<(), GpuError> {
        let done = self.submit_resolve();
        self.ctx.wait_for("sdb resolve (warming up)", done)?;
        self.ctx.take_error("sdb resolve (warming up)")
    }

    /// Puts the host's side of a stopped step back (the device's is put back by the
    /// slicer).
    fn undo(&mut self, before: StepBook) {
        tracing::debug!("sdb: the deadline passed or a stop was asked mid-step; the step is undone");
        self.directions = before.directions;
        self.rng = before.rng;
        self.dirs = before.dirs;
        self.weights = before.weights;
        self.half_steps = before.half_steps;
    }

    /// The bake's time limit ([`Technique::set_deadline`](super::super::api::Technique::set_deadline)); the next watched step is
    /// timed afresh.
    pub fn set_deadline(&mut self, deadline: Option<std::time::Instant>) {
        self.deadline = deadline;
        self.slicer.forget();
        if let Some(p) = &mut self.small_emitters {
            p.lights.light.forget_step_length();
        }
    }

    /// Where a watched step reports how far it is.
    pub fn set_step_progress(&mut self, progress: StepProgress) {
        self.progress = Some(progress);
        self.slicer.forget();
        if let Some(p) = &mut self.small_emitters {
            p.lights.light.forget_step_length();
        }
    }

    /// Read both halves back (blocks until the GPU is done).
    pub fn read_halves(&self) -> Result<[SdbHalf; 2], GpuError> {
        let n = self.n_texels as usize;
        let acc: Vec<[f32; 4]> = self.ctx.read_buffer("sdb accumulators", &self.acc_buf, 2 * n)?;
        let direct: Option<Vec<[f32; 4]>> = match &self.direct_acc_buf {
            Some(b) => Some(self.ctx.read_buffer("sdb direct accumulators", b, 2 * n)?),
            None => None,
        };
        let sun: Option<Vec<[f32; 4]>> = match &self.sun_acc_buf {
            Some(b) => Some(self.ctx.read_buffer("sdb sun accumulators", b, 2 * n)?),
            None => None,
        };
        let half = |h: usize| {
            // A running mean is already normalised (zero while empty); a leaky blend of the
            // sun needs its start-up correction. Gathered light is a ratio of two blends.
            let sun_scale = match self.params.mode {
                AccumulationMode::Average => 1.0,
                AccumulationMode::Leaky => self.leaky_correction(self.dirs[h]) as f32,
            };
            let range = h * n..(h + 1) * n;
            let sun_at = |k: usize| {
                sun.as_ref()
                    .map_or(Vec3::ZERO, |s| Vec3::from_slice(&s[h * n + k][..3]) * sun_scale)
            };
            let weight = |k: usize| acc[h * n + k][3];
            let over_weight = |v: [f32; 4], k: usize| {
                let w = weight(k);
                if w > 0.0 {
                    Vec3::from_slice(&v[..3]) / w
                } else {
                    Vec3::ZERO
                }
            };
            SdbHalf {
                steps: self.half_steps[h],
                total: acc[range.clone()]
                    .iter()
                    .enumerate()
                    .map(|(k, &a)| over_weight(a, k) + sun_at(k))
                    .collect(),
                direct: direct.as_ref().map(|d| {
                    d[range.clone()]
                        .iter()
                        .enumerate()
                        .map(|(k, &a)| over_weight(a, k) + sun_at(k))
                        .collect()
                }),
            }
        };
        Ok([half(0), half(1)])
    }
}
