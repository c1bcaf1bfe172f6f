//! One `hemicube` step (`Hemicube::run_step`): the power pyramid, the shooters (texel
//! shooters on the GPU, emitter samples on the CPU), their depth maps, the CPU's sky,
//! sun and punctual light and near-field gather, and the transfer, in slices a deadline
//! can stop between (the module doc of `hemicube`, "How" and "Stopping inside a step").

use std::f32::consts::PI;

use glam::Vec3;
use rayon::prelude::*;

use super::super::api::{EngineError, go_on_until, gpu_error};
use crate::engine::gpu;
use crate::engine::gpu::shadow::ShadowDraw;
use crate::engine::gpu::slices::{Aside, Sliced};
use crate::engine::raytrace::{Tracer, cone_sample, cosine_sample};
use crate::engine::rng::Rng;
use crate::engine::scene::LightKind;

use super::{CPU_LIGHT_CHUNK, GpuNear, GpuParams, GpuShooter, HC_CPU_LIGHT, Hemicube, lum, v4};

impl Hemicube {
    fn norm(&self, p: Vec3) -> Vec3 {
        (p - self.centre) / self.radius
    }

    /// The step's emitter shooters: a triangle by power, a uniform point, its emission.
    /// `count` of them, each weighted 1 / `share` (the expected number of emitter samples
    /// a step).
    fn emitter_samples(&self, step: u64, count: u32, share: f64) -> Vec<GpuShooter> {
        let scene = &self.scene;
        let r2 = self.radius * self.radius;
        (0..count)
            .map(|k| {
                let mut rng = Rng::new(self.seed, 0x4E17_0E11, step, k as u64);
                // Stratified over the power: sample k of `count` in the k-th stratum.
                let u = (k as f64 + rng.next_f32() as f64) / count as f64;
                let j = self
                    .emitter_cdf
                    .partition_point(|&c| c <= u)
                    .min(self.emitters.len() - 1);
                let e = self.emitters[j];
                let p_tri = e.weight / self.emitters.iter().map(|e| e.weight).sum::<f64>();
                let tri = &scene.triangles[e.triangle as usize];
                let material = scene.material(tri);
                let (mut b1, mut b2) = (rng.next_f32(), rng.next_f32());
                if b1 + b2 > 1.0 {
                    b1 = 1.0 - b1;
                    b2 = 1.0 - b2;
                }
                let bary = Vec3::new(1.0 - b1 - b2, b1, b2);
                let mut normal = tri.geometric_normal();
                let mut sides = 1.0;
                if material.double_sided {
                    sides = 2.0;
                    if rng.next_f32() < 0.5 {
                        normal = -normal;
                    }
                }
                let p = tri.point(bary) + normal * self.atlas.surface_offset;
                let weight = (tri.area() as f64 * sides / (p_tri * share)) as f32 / r2;
                // No disc (w = 0): the point is exact, and the near-field split bounds it.
                GpuShooter {
                    pos: v4(self.norm(p), 0.0),
                    nrm: v4(normal, weight),
                    diffuse: v4(scene.emission(tri, bary), 1.0),
                    spec: [0.0; 4],
                    in_dir: v4(normal, 0.0),
                    frame_t: [0.0; 4],
                    frame_b: [0.0; 4],
                }
            })
            .collect()
    }

    /// Per receiver, one-sample irradiance estimates of the sky, the sun, punctual lights
    /// and the emission of the near field (first R entries: rgb), their luminance-weighted
    /// direction sums (next R), and the near-field gather of reflected light; R the
    /// receivers (every texel but in a bake in rounds).
    ///
    /// With `go_on` (a watched step), texels go in chunks of [`CPU_LIGHT_CHUNK`] and
    /// `go_on(done, of)` is asked between two; None when it says stop (nothing is kept:
    /// every texel's rays are keyed by step and texel, so the step redone draws the same).
    #[allow(clippy::type_complexity)]
    fn cpu_light(
        &self,
        step: u64,
        go_on: Option<&mut dyn FnMut(u64, u64) -> bool>,
    ) -> Option<(Vec<[f32; 4]>, Vec<GpuNear>)> {
        let Some(tracer) = &self.tracer else {
            return Some((Vec::new(), Vec::new()));
        };
        let scene = &self.scene;
        let lighting = &self.lighting;
        let seed = self.seed;
        let receivers = self.receivers.clone();
        let texels = &self.atlas.texels[receivers.clone()];
        let n = texels.len();
        let chunk = if go_on.is_some() { CPU_LIGHT_CHUNK } else { n.max(1) };
        let mut go_on = go_on;
        let mut per: Vec<(Vec3, Vec3, GpuNear)> = Vec::with_capacity(n);
        for first in (0..n).step_by(chunk) {
            if first > 0
                && let Some(go_on) = go_on.as_mut()
                && !go_on(first as u64, n as u64)
            {
                return None;
            }
            let end = (first + chunk).min(n);
            per.par_extend(texels[first..end].par_iter().map(|t| {
                // Keyed by the texel's pixel, not its index: a texel draws the same
                // stream whichever texels the set around it holds (a region's bake in
                // rounds, whose round 0 keeps other regions' texels untested).
                let mut rng = Rng::new(seed, 0xC9_11_6E, step, u64::from(t.pixel));
                let (x, n, ng) = (t.position, t.normal, t.geo_normal);
                let front = |d: Vec3| d.dot(n) > 0.0 && d.dot(ng) > 0.0;
                let (mut sum, mut dir) = (Vec3::ZERO, Vec3::ZERO);
                let mut add = |c: Vec3, d: Vec3| {
                    sum += c;
                    dir += d * lum(c);
                };
                if lighting.sky.is_some() {
                    // Cosine sampling: E = π L is the irradiance estimate.
                    let d = cosine_sample(n, rng.next_f32(), rng.next_f32());
                    let l = lighting.sky_radiance(d);
                    if l != Vec3::ZERO && d.dot(ng) > 0.0 && tracer.unoccluded(scene, x, d, f32::INFINITY) {
                        add(l * PI, d);
                    }
                }
                if let Some(sun) = &lighting.sun {
                    let axis = -sun.direction.normalize();
                    let d = cone_sample(axis, sun.cos_half_angle(), rng.next_f32(), rng.next_f32());
                    if front(d) && tracer.unoccluded(scene, x, d, f32::INFINITY) {
                        add(sun.radiance * (d.dot(n) * sun.solid_angle()), d);
                    }
                }
                for light in &scene.lights {
                    match light.kind {
                        LightKind::Directional => {
                            let d = -light.direction;
                            if front(d) && tracer.unoccluded(scene, x, d, f32::INFINITY) {
                                add(light.intensity * d.dot(n), d);
                            }
                        }
                        LightKind::Point | LightKind::Spot { .. } => {
                            let to = light.position - x;
                            let dist2 = to.length_squared();
                            if dist2 <= 0.0 {
                                continue;
                            }
                            let dist = dist2.sqrt();
                            let d = to / dist;
                            if !front(d) {
                                continue;
                            }
                            // The same falloff and cone as `path` (KHR_lights_punctual).
                            let mut falloff = 1.0 / dist2;
                            if let Some(range) = light.range {
                                falloff *= (1.0 - (dist / range).powi(4)).clamp(0.0, 1.0).powi(2);
                            }
                            if let LightKind::Spot { inner_cone, outer_cone } = light.kind {
                                let cd = (-d).dot(light.direction);
                                let scale = 1.0 / (inner_cone.cos() - outer_cone.cos()).max(1e-3);
                                let a = ((cd - outer_cone.cos()) * scale).clamp(0.0, 1.0);
                                falloff *= a * a;
                            }
                            if falloff > 0.0 && tracer.unoccluded(scene, x, d, dist * (1.0 - 1e-4)) {
                                add(light.intensity * (falloff * d.dot(n)), d);
                            }
                        }
                    }
                }
                let near = self.near_field(tracer, t, step, &mut add);
                (sum, dir, near)
            }));
        }
        let light = per
            .iter()
            .map(|(s, _, _)| v4(*s, 0.0))
            .chain(per.iter().map(|(_, d, _)| v4(*d, 0.0)))
            .collect();
        Some((light, per.into_iter().map(|(_, _, n)| n).collect()))
    }

    /// The near-field gather at texel `t`, its stream keyed by the texel's pixel
    /// (module doc, "Unbiased transfer"): one cosine ray to the near radius r. A hit at
    /// distance t with cosines cos_x, cos_y takes the MIS weight w = max(0, 1 - t^2 /
    /// (cos_x cos_y r^2)), the part of G = cos_x cos_y / (π t^2) above c = 1 / (π r^2);
    /// the shooters keep min(1, c / G) of the same pair. Emission found there is added
    /// through `add` (π Le w, direct light); reflected light is left to the GPU, which
    /// knows the hit texel's irradiance: the returned gain is w k_d.
    fn near_field(
        &self,
        tracer: &Tracer,
        t: &crate::engine::atlas::Texel,
        step: u64,
        add: &mut impl FnMut(Vec3, Vec3),
    ) -> GpuNear {
        let r = self.params.near_field * t.size;
        if !(r > 0.0) {
            return GpuNear::NONE;
        }
        let scene = &self.scene;
        let mut rng = Rng::new(self.seed, 0x4EA2_F1E1, step, u64::from(t.pixel));
        let (x, n, ng) = (t.position, t.normal, t.geo_normal);
        let d = cosine_sample(n, rng.next_f32(), rng.next_f32());
        let cos_x = d.dot(n);
        if d.dot(ng) <= 0.0 || cos_x <= 0.0 {
            return GpuNear::NONE;
        }
        let Some(hit) = tracer.trace(scene, x, d, r) else {
            return GpuNear::NONE;
        };
        let tri = &scene.triangles[hit.triangle as usize];
        let material = scene.material(tri);
        // Positive on the front face, which is the side texel shooters send light from.
        let facing = -d.dot(tri.geometric_normal());
        let cos_y = if material.double_sided { facing.abs() } else { facing };
        if cos_y <= 0.0 {
            return GpuNear::NONE;
        }
        let w = (1.0 - hit.t * hit.t / (cos_x * cos_y * r * r)).max(0.0);
        if w <= 0.0 {
            return GpuNear::NONE;
        }
        let le = scene.emission(tri, hit.bary);
        if le != Vec3::ZERO {
            add(le * (PI * w), d);
        }
        // Merged shooters (level > 0) keep their whole transfer: no texel part here.
        if facing <= 0.0 || self.params.shooter_level > 0 {
            return GpuNear::NONE;
        }
        match crate::engine::atlas::cells::texel_at(scene, &self.atlas, hit.triangle, hit.bary) {
            Some(j) => GpuNear {
                gain: v4(self.texel_albedo[j as usize] * w, 0.0),
                dir: d.to_array(),
                hit: j,
            },
            None => GpuNear::NONE,
        }
    }

    pub(super) fn run_step(&mut self) -> Result<(), EngineError> {
        let step = self.steps_done;
        let parity = (step % 2) as usize;
        // One shooter a step with emitters: a fair coin picks the kind, and the shooter
        // counts as half a shooter of that kind (weight x 2), so every step's estimate is
        // an unbiased transfer of all the light.
        let (k_emit, k_texel, share_emit, share_texel) = if self.params.shooters_per_step == 1 && self.k_emit == 1 {
            let mut rng = Rng::new(self.seed, 0xC0_14, step, 0);
            if rng.next_f32() < 0.5 {
                (1, 0, 0.5, 1.0)
            } else {
                (0, 1, 1.0, 0.5)
            }
        } else {
            (self.k_emit, self.k_texel, self.k_emit as f64, self.k_texel as f64)
        };
        let watched = self.deadline.is_some() || self.progress.is_some();
        let sliced = self.slicer.slices(watched);
        let progress = self.progress.clone();
        // A watched step reports its CPU rays as its first half and its transfer as the
        // second.
        let mut go_on = go_on_until(self.deadline, progress.as_ref());
        let q = &self.ctx.queue;
        if k_emit > 0 {
            let samples = self.emitter_samples(step, k_emit, share_emit);
            q.write_buffer(&self.emitters_buf, 0, bytemuck::cast_slice(&samples));
        }
        if self.flags & HC_CPU_LIGHT != 0 {
            let mut first_third = |done: u64, of: u64| go_on(done, 3 * of);
            let Some((light, near)) = self.cpu_light(
                step,
                sliced.then_some(&mut first_third as &mut dyn FnMut(u64, u64) -> bool),
            ) else {
                tracing::debug!("hemicube: the deadline passed or a stop was asked mid-step; the step is undone");
                return Ok(());
            };
            // The receivers' slots of the two N-texel halves (sums, then directions).
            let (first, r) = (self.receivers.start as u64, near.len());
            let n = self.n_texels as u64;
            q.write_buffer(&self.cpu_light_buf, first * 16, bytemuck::cast_slice(&light[..r]));
            q.write_buffer(&self.cpu_light_buf, (n + first) * 16, bytemuck::cast_slice(&light[r..]));
            let near_size = std::mem::size_of::<GpuNear>() as u64;
            q.write_buffer(&self.near_buf, first * near_size, bytemuck::cast_slice(&near));
        }
        // Kept only once the step is done (a stopped step leaves them).
        let i = (self.half_steps[parity] + 1) as f64;
        let w = i.powf(self.params.ramp as f64);
        let half_weight = self.half_weight[parity] + w;
        let blend = (w / half_weight) as f32;
        let hash = (crate::engine::rng::splitmix64(self.seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15)) >> 32) as u32;
        let mut gp = GpuParams {
            dims: [self.n_texels, self.atlas.width, self.atlas.height, self.pyr_side],
            shoot: [self.top_level, self.params.shooter_level, k_emit, k_texel],
            step: [(step % 2) as u32, parity as u32, hash, self.flags],
            f: [
                blend,
                self.params.depth_map_size as f32,
                self.params.grazing_tolerance,
                share_texel as f32,
            ],
            // The receivers only: the other texels keep what they hold (a bake in rounds).
            slice: [self.receivers.start as u32, self.receivers.len() as u32, 0, 0],
        };
        q.write_buffer(&self.params_buf, 0, bytemuck::bytes_of(&gp));
        let shooters = k_emit + k_texel;
        let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("hemicube step"),
        });
        if k_texel > 0 {
            let level0 = (self.pyr_side as u64).pow(2) * 4;
            encoder.clear_buffer(&self.pyramid_buf, 0, Some(level0));
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hemicube power pyramid"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.power_pipeline);
            pass.set_bind_group(0, &self.power_bg, &[]);
            let (x, y) = gpu::dispatch_size_64(self.n_texels);
            pass.dispatch_workgroups(x, y, 1);
            pass.set_pipeline(&self.reduce_pipeline);
            for (bg, cells) in &self.reduce_bgs {
                pass.set_bind_group(0, bg, &[]);
                let (x, y) = gpu::dispatch_size_64(*cells);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hemicube select shooters"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.select_pipeline);
            pass.set_bind_group(0, &self.select_bg, &[]);
            pass.dispatch_workgroups(shooters.div_ceil(64).max(1), 1, 1);
        }
        let draws: Vec<ShadowDraw> = (0..5 * shooters)
            .map(|v| {
                let [x, y, side, _] = self.tiles[v as usize];
                // Side faces: only the half above the shooter's plane is ever looked up.
                let rows = if v % 5 == 0 { side } else { side / 2 };
                ShadowDraw {
                    view: v,
                    tile: [x, y, side],
                    rows,
                }
            })
            .collect();
        if !sliced && !draws.is_empty() {
            self.shadow
                .render(&mut encoder, &self.vertex_buf, self.vertex_count, draws.iter().copied());
        }
        let transfer = |encoder: &mut wgpu::CommandEncoder, (x, y): (u32, u32)| {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("hemicube transfer"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.transfer_pipeline);
            pass.set_bind_group(0, &self.transfer_bg, &[]);
            pass.dispatch_workgroups(x, y, 1);
        };
        if sliced {
            // The pyramid and the shooters, then their maps in slices of whole maps (each
            // the whole scene drawn, 5 a shooter: 8 s a step for a 1M-triangle level on
            // lavapipe), nothing to put back there (the atlas is redrawn every step), then
            // the transfer in slices of texels. This step's irradiance half (`step.x`) is
            // the accumulators' (`step.y`): both are the step's parity.
            q.submit([encoder.finish()]);
            let mut second_third = |done: u64, of: u64| go_on(of + done, 3 * of);
            let done = self
                .shadow
                .render_sliced(
                    &self.ctx,
                    &mut self.map_slicer,
                    &self.vertex_buf,
                    self.vertex_count,
                    &draws,
                    &mut second_third,
                )
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("hemicube: the deadline passed or a stop was asked mid-step; the step is undone");
                return Ok(());
            }
            // Only the accumulators: this step's irradiance and directions half is
            // rewritten whole by the step that follows before any pass reads it (the
            // pyramid, the selection and the near field read the other half).
            let aside = [
                Aside::half(&self.acc_buf, parity),
                Aside::half(&self.direct_acc_buf, parity),
            ];
            let first_receiver = self.receivers.start as u64;
            let mut submit = |first: u64, count: u64| {
                gp.slice = [(first_receiver + first) as u32, count as u32, 0, 0];
                q.write_buffer(&self.params_buf, 0, bytemuck::bytes_of(&gp));
                Ok(self.ctx.submit_compute(
                    "hemicube transfer",
                    &self.transfer_pipeline,
                    &self.transfer_bg,
                    count as u32,
                ))
            };
            let mut last_third = |done: u64, of: u64| go_on(2 * of + done, 3 * of);
            let done = self
                .slicer
                .run(
                    &self.ctx,
                    self.receivers.len() as u64,
                    &aside,
                    &mut submit,
                    &mut last_third,
                )
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("hemicube: the deadline passed or a stop was asked mid-step; the step is undone");
                return Ok(());
            }
        } else {
            transfer(&mut encoder, gpu::dispatch_size_64(self.receivers.len() as u32));
            q.submit([encoder.finish()]);
            self.slicer.returned_whole();
        }
        self.half_weight[parity] = half_weight;
        self.half_steps[parity] += 1;
        self.steps_done += 1;
        self.ctx.take_error("hemicube step").map_err(gpu_error)
    }
}
