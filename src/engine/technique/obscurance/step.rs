//! One `obscurance` step on the GPU (`Obscurance::step_gpu`): the step's direction's
//! layered depth maps, the gather of obscurance and the bounce through the scene-wide
//! ambient, the direct light, in slices a deadline can stop between; and the halves read
//! back.

use glam::Vec3;

use super::super::api::{EngineError, go_on_until, gpu_error};
use crate::engine::ambient::AmbientSums;
use crate::engine::gpu::direct_light::DirectHalf;
use crate::engine::gpu::directions::sample_cone;
use crate::engine::gpu::shadow::{ShadowDraw, ShadowView};
use crate::engine::gpu::slices::{Aside, Sliced};
use crate::engine::gpu::view::{DEPTH_NEAREST, make_view};
use crate::engine::gpu::{self, GpuError};

use super::{
    AmbientSource, Background, EPS_ALONG_D, EPS_NORMAL_PLANE, FLAG_BACKGROUND_AMBIENT, FLAG_SUBSET, GpuDirectParams,
    GpuGatherParams, LayerStats, MASK_BASE, Obscurance, ObscuranceHalf, SHADOW_OFFSET_PIXELS,
};

impl Obscurance {
    fn texels_to_process(&self) -> u32 {
        self.subset_len.unwrap_or(self.n_texels)
    }

    /// One step: `directions_per_step` directions (layers, gather, then a shadow map and
    /// direct pass per sun or directional light), then the shared direct light's pass.
    /// Submits and returns; nothing is read.
    ///
    /// In a bake with a time limit or a watcher (issue 19 point 10) the directions run in
    /// slices of whole units, each waited for (`gpu::slices`, sized to about 50 ms): a
    /// part of the depth layers ([`LAYER_PART_TRIANGLES`]), the gather, or one light's
    /// shadow map and direct pass; the halves they write are put aside first; the shared
    /// direct light then runs
    /// sliced when it may be long. A stop between two slices of either puts back what the
    /// step wrote (the directions' halves and counters, its random streams and direction
    /// sequence) so the step adds nothing and the next is the one it would have been.
    pub(super) fn step_gpu(&mut self) -> Result<(), GpuError> {
        let parity = (self.steps_done % 2) as usize;
        let n = self.params.map_pixels();
        let count = self.texels_to_process();
        let dispatch = gpu::dispatch_size_64(count);
        let mut flags = 0;
        if self.params.background == Background::Ambient {
            flags |= FLAG_BACKGROUND_AMBIENT;
        }
        if self.subset_len.is_some() {
            flags |= FLAG_SUBSET;
        }
        let watched = self.deadline.is_some() || self.progress.is_some();
        let before = (self.directions.clone(), self.rng.clone(), self.dirs);
        let texels = self.n_texels as u64;
        // The parity's slots of both accumulators ([p N, (p + 1) N) and [(2 + p) N,
        // (3 + p) N), module doc of gather.wgsl) and the counters (an abandoned
        // direction's overflow would be counted).
        fn half(b: &wgpu::Buffer, k: u64, texels: u64) -> Aside<'_> {
            Aside {
                buffer: b,
                offset: k * texels * 16,
                size: texels * 16,
            }
        }
        let p = parity as u64;
        let aside = [
            half(&self.acc_buf, p, texels),
            half(&self.acc_buf, 2 + p, texels),
            half(&self.direct_acc_buf, p, texels),
            half(&self.direct_acc_buf, 2 + p, texels),
            Aside {
                buffer: &self.counters_buf,
                offset: 0,
                size: MASK_BASE as u64 * 4,
            },
        ];
        // A direction is `parts` draws of the layers (a part of the triangles each), the
        // gather, then a shadow map and direct pass per sun or directional light: each a
        // unit of a sliced step.
        let parts = (self.vertex_count / 3).div_ceil(self.layer_part).max(1);
        let lights = if self.shadow.is_some() {
            self.lights.len() as u32
        } else {
            0
        };
        let per_direction = (parts + 1 + lights) as u64;
        let mut b = 0.0f32;
        let mut submit = |first: u64, k: u64| -> Result<wgpu::SubmissionIndex, GpuError> {
            let mut last = None;
            for unit in first..first + k {
                let sub = (unit % per_direction) as u32;
                if sub == 0 {
                    let d = self.directions.next_direction();
                    self.dirs[parity] += 1;
                    b = 1.0 / self.dirs[parity] as f32;
                    let jitter = (self.rng.next_f64() as f32, self.rng.next_f64() as f32);
                    let view = make_view(d, &self.corners, n, jitter, 0, DEPTH_NEAREST);
                    let env = |w: Vec3| self.environment.as_ref().map_or(Vec3::ZERO, |e| e(w));
                    let (fwd, back) = (env(d), env(-d));
                    let gather = GpuGatherParams {
                        env_fwd: [fwd.x, fwd.y, fwd.z, b],
                        env_back: [back.x, back.y, back.z, self.dmax_norm],
                        r_ave: [self.r_ave.x, self.r_ave.y, self.r_ave.z, EPS_ALONG_D],
                        misc: [parity as u32, count, self.params.falloff.code(), flags],
                        dims: [
                            self.lm_pixels,
                            self.n_texels,
                            self.node_capacity,
                            EPS_NORMAL_PLANE.to_bits(),
                        ],
                    };
                    // Uniform writes land before the next submit, and every unit is its
                    // own submission: the view and the gather's parameters hold until the
                    // next direction writes them.
                    self.ctx
                        .queue
                        .write_buffer(&self.view_buf, 0, bytemuck::bytes_of(&view));
                    self.ctx
                        .queue
                        .write_buffer(&self.gather_buf, 0, bytemuck::bytes_of(&gather));
                }
                if sub < parts {
                    let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("obscurance depth layers"),
                    });
                    if sub == 0 {
                        encoder.clear_buffer(&self.heads_buf, 0, None);
                        encoder.clear_buffer(&self.counters_buf, 0, Some(4));
                    }
                    {
                        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                            label: Some("obscurance depth layers"),
                            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                                view: &self.dummy_view,
                                depth_slice: None,
                                resolve_target: None,
                                ops: wgpu::Operations {
                                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                                    store: wgpu::StoreOp::Discard,
                                },
                            })],
                            depth_stencil_attachment: None,
                            timestamp_writes: None,
                            occlusion_query_set: None,
                            multiview_mask: None,
                        });
                        pass.set_pipeline(&self.layers_pipeline);
                        pass.set_bind_group(0, &self.layers_bg, &[]);
                        pass.set_vertex_buffer(0, self.vertex_buf.slice(..));
                        // The lists are unsorted and the gather looks for the nearest
                        // layer, so drawing the triangles in parts builds the same lists.
                        let from = 3 * self.layer_part * sub;
                        let to = (from + 3 * self.layer_part).min(self.vertex_count);
                        pass.draw(from..to, 0..1);
                    }
                    last = Some(self.ctx.queue.submit([encoder.finish()]));
                } else if sub == parts {
                    let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("obscurance gather"),
                    });
                    {
                        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                            label: Some("obscurance gather"),
                            timestamp_writes: None,
                        });
                        pass.set_pipeline(&self.gather_pipeline);
                        pass.set_bind_group(0, &self.gather_bg, &[]);
                        pass.dispatch_workgroups(dispatch.0, dispatch.1, 1);
                    }
                    last = Some(self.ctx.queue.submit([encoder.finish()]));
                } else if let Some(shadow) = &self.shadow {
                    let light = self.lights[(sub - parts - 1) as usize];
                    let ld = sample_cone(light.direction, light.cone_half_angle, &mut self.rng);
                    let jitter = (self.rng.next_f64() as f32, self.rng.next_f64() as f32);
                    let view = make_view(ld, &self.corners, n, jitter, 0, DEPTH_NEAREST);
                    let map = ShadowView::ortho_of(&view, [0, 0]);
                    let e = light.irradiance_over_pi;
                    let direct = GpuDirectParams {
                        irradiance: [e.x, e.y, e.z, b],
                        bias: [SHADOW_OFFSET_PIXELS, 0.0, 0.0, 0.0],
                        misc: [
                            parity as u32,
                            count,
                            self.n_texels,
                            u32::from(self.subset_len.is_some()),
                        ],
                    };
                    self.ctx
                        .queue
                        .write_buffer(&shadow.views_buf, 0, bytemuck::bytes_of(&map));
                    self.ctx
                        .queue
                        .write_buffer(&self.direct_buf, 0, bytemuck::bytes_of(&direct));
                    let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                        label: Some("obscurance direct light"),
                    });
                    let draw = ShadowDraw {
                        view: 0,
                        tile: [0, 0, n],
                        rows: n,
                    };
                    shadow
                        .atlas
                        .render(&mut encoder, &self.vertex_buf, self.vertex_count, [draw]);
                    {
                        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                            label: Some("obscurance direct"),
                            timestamp_writes: None,
                        });
                        pass.set_pipeline(&shadow.direct_pipeline);
                        pass.set_bind_group(0, &shadow.direct_bg, &[]);
                        pass.dispatch_workgroups(dispatch.0, dispatch.1, 1);
                    }
                    last = Some(self.ctx.queue.submit([encoder.finish()]));
                }
            }
            Ok(last.expect("a slice has at least one unit"))
        };
        let units = self.params.directions_per_step as u64 * per_direction;
        let progress = self.progress.clone();
        let mut go_on = go_on_until(self.deadline, progress.as_ref());
        if watched {
            // Directions are the step's first half of progress, the direct light its second.
            let mut first_half = |done: u64, of: u64| go_on(done, 2 * of);
            let done = self
                .slicer
                .run(&self.ctx, units, &aside, &mut submit, &mut first_half)?;
            if done == Sliced::Abandoned {
                tracing::debug!("obscurance: the deadline passed or a stop was asked mid-step; the step is undone");
                (self.directions, self.rng, self.dirs) = before;
                return Ok(());
            }
        } else if units > 0 {
            submit(0, units)?;
        }
        if let Some(d) = &mut self.shared_direct {
            let mut second_half = |done: u64, of: u64| go_on(of + done, 2 * of);
            let done = d.step_watched(watched.then_some(&mut second_half as &mut dyn FnMut(u64, u64) -> bool))?;
            if done == Sliced::Abandoned {
                // The directions finished (sliced, so their halves are aside): put them back.
                self.slicer.put_back(&self.ctx, &aside)?;
                tracing::debug!("obscurance: the deadline passed or a stop was asked mid-step; the step is undone");
                (self.directions, self.rng, self.dirs) = before;
                return Ok(());
            }
        }
        self.half_steps[parity] += 1;
        self.steps_done += 1;
        self.ctx.take_error("obscurance step")
    }

    /// Block until every submitted step is done (timings).
    pub fn finish(&self) -> Result<(), EngineError> {
        self.ctx.wait_idle().map_err(gpu_error)?;
        self.ctx.take_error("obscurance step").map_err(gpu_error)
    }

    /// Both halves read back, with the ambient term each uses (blocks on the GPU).
    pub fn halves(&mut self) -> Result<[ObscuranceHalf; 2], EngineError> {
        let n = self.n_texels as usize;
        let acc: Vec<[f32; 4]> = self
            .ctx
            .read_buffer("obscurance accumulators", &self.acc_buf, 4 * n)
            .map_err(gpu_error)?;
        let direct: Vec<[f32; 4]> = self
            .ctx
            .read_buffer("obscurance direct accumulators", &self.direct_acc_buf, 4 * n)
            .map_err(gpu_error)?;
        let counters: Vec<u32> = self
            .ctx
            .read_buffer("obscurance counters", &self.counters_buf, MASK_BASE)
            .map_err(gpu_error)?;
        self.last_stats = LayerStats {
            capacity: self.node_capacity,
            max_fragments: counters[1],
            max_layers: counters[2],
            overflowing_directions: counters[3],
        };
        if counters[3] > 0 {
            tracing::warn!(
                stats = ?self.last_stats,
                "obscurance: some directions had more fragments than the node pool holds; surfaces behind them were missed"
            );
        }
        let shared: Option<[DirectHalf; 2]> = match &self.shared_direct {
            Some(d) => Some(d.halves().map_err(gpu_error)?),
            None => None,
        };
        let half = |h: usize| {
            let (mut w, mut ao, mut dir, mut hit) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for k in 0..n {
                let (a, d) = (acc[h * n + k], direct[h * n + k]);
                let weight = acc[2 * n + h * n + k][0];
                let sun = direct[2 * n + h * n + k];
                // The ratio estimator's denominator; 0 only before any direction reached
                // the texel's side.
                let inv = if weight > 0.0 { 1.0 / weight } else { 0.0 };
                w.push(Vec3::new(a[0], a[1], a[2]) * inv);
                ao.push(a[3] * inv);
                dir.push(Vec3::new(d[0], d[1], d[2]) * inv + Vec3::new(sun[0], sun[1], sun[2]));
                hit.push(d[3] * inv);
            }
            // The shared module's light is direct light like the rest: it feeds I_A
            // through D_ave, so its first (and every further) bounce is the model's.
            if let Some(sh) = &shared {
                for (d, e) in dir.iter_mut().zip(&sh[h].light) {
                    *d += *e;
                }
            }
            // I_A: Eq. 5's from the triangles, or the measured closure over this bake's
            // texels (`engine::ambient`, with R_ave the grid's), whose sums a split bake's
            // merge closes over every region.
            let (ambient, sums) = match self.params.ambient {
                AmbientSource::Emitters => (self.eq5_ambient, None),
                AmbientSource::Measured => {
                    let mut sums = AmbientSums::default();
                    for k in 0..n {
                        sums.add_texel(self.texel_area[k], self.r_ave, dir[k], hit[k]);
                    }
                    (sums.closure(), Some(sums))
                }
            };
            ObscuranceHalf {
                steps: self.half_steps[h],
                w,
                ao,
                direct: dir,
                hit,
                ambient,
                sums,
            }
        };
        Ok([half(0), half(1)])
    }

    /// The plain obscurance (Eq. 2) per valid texel, both halves combined, as of the last
    /// snapshot.
    pub fn ao(&self) -> Option<&[f32]> {
        self.last_ao.as_deref()
    }

    pub(super) fn dims(&self) -> (u32, u32) {
        (self.width, self.height)
    }
}
