//! One `vpl` step (`Vpl::run_step`): the step's lights built (the primary lights, the
//! VPLs of the paths continued from them and from the reflective shadow maps, resampled),
//! their shadow maps drawn into the atlas, and the gather at every texel, in slices a
//! deadline can stop between.

use std::f32::consts::PI;

use bytemuck::Zeroable;
use glam::Vec3;
use rayon::prelude::*;

use super::super::api::{EngineError, go_on_until, gpu_error};
use crate::engine::gpu::shadow::{ShadowDraw, ShadowView, VIEW_ORTHO, VIEW_PERSPECTIVE, cube_faces};
use crate::engine::gpu::slices::{Aside, Sliced};
use crate::engine::raytrace::{basis, cone_sample, cosine_sample, inset};
use crate::engine::rng::Rng;
use crate::engine::scene::{Hemisphere, LightKind};

use super::rsm;
use super::{
    CUBE_NEAR, Emitter, GpuGatherParams, GpuLight, LIGHT_DIRECTIONAL, LIGHT_POINT, LIGHT_SPOT, LIGHT_VPL, MARGIN,
    NO_VIEW, NORMAL_OFFSET_PX, Primary, StepLights, SurfacePoint, Vpl, lum, surface_hit, v4,
};

impl Vpl {
    fn norm(&self, p: Vec3) -> Vec3 {
        (p - self.centre) / self.radius
    }

    fn rect_of(&self, view: u32, kind: u32) -> [u32; 4] {
        let r = self.layout.rects[view as usize];
        [r[0], r[1], r[2], kind]
    }

    /// An orthographic map along `dir` over the normalised unit sphere.
    fn ortho_view(&self, view: u32, dir: Vec3) -> ShadowView {
        let (right, up) = basis(dir);
        ShadowView {
            origin: v4(-dir * MARGIN, 0.0),
            right: v4(right, MARGIN),
            up: v4(up, 0.0),
            fwd: v4(dir, 2.0 * MARGIN),
            rect: self.rect_of(view, VIEW_ORTHO),
        }
    }

    /// The cube faces (first `count` of them) around normalised point `o` in frame
    /// (t, b, n).
    fn cube_views(&self, first: u32, count: usize, o: Vec3, frame: (Vec3, Vec3, Vec3)) -> Vec<ShadowView> {
        let far = o.length() + 2.0 * MARGIN;
        cube_faces(frame.0, frame.1, frame.2)[..count]
            .iter()
            .enumerate()
            .map(|(k, (fwd, right, up))| ShadowView {
                origin: v4(o, CUBE_NEAR),
                right: v4(*right, 0.0),
                up: v4(*up, 0.0),
                fwd: v4(*fwd, far),
                rect: self.rect_of(first + k as u32, VIEW_PERSPECTIVE),
            })
            .collect()
    }

    /// Keller's recursion from one VPL: cosine-distributed rays, Russian roulette by
    /// albedo, up to `max_depth`.
    fn continue_path(&self, start: SurfacePoint, rng: &mut Rng, out: &mut Vec<SurfacePoint>) {
        let mut v = start;
        out.push(v);
        while v.depth < self.params.max_depth {
            let dir = cosine_sample(v.n, rng.next_f32(), rng.next_f32());
            let Some((p, n, albedo)) = surface_hit(
                &self.scene,
                &self.tracer,
                v.p + v.n * self.ray_offset,
                dir,
                f32::INFINITY,
            ) else {
                break;
            };
            let q = albedo.max_element().min(1.0);
            if q <= 0.0 || rng.next_f32() >= q {
                break;
            }
            v = SurfacePoint {
                p,
                n,
                flux: v.flux * albedo / q,
                depth: v.depth + 1,
            };
            out.push(v);
        }
    }

    /// A uniform point on emitter `e` as a depth-0 VPL carrying `scale` x its estimate
    /// of the triangle's emitted flux.
    fn emitter_sample(&self, e: &Emitter, scale: f64, rng: &mut Rng) -> SurfacePoint {
        let tri = &self.scene.triangles[e.triangle as usize];
        let (u1, u2) = (rng.next_f32(), rng.next_f32());
        let s = u1.sqrt();
        let b = inset(Vec3::new(1.0 - s, s * (1.0 - u2), s * u2));
        let double = self.scene.material(tri).double_sided;
        let ng = tri.geometric_normal();
        let n = if double && rng.next_f32() < 0.5 { -ng } else { ng };
        let sides = if double { 2.0 } else { 1.0 };
        let flux = self.scene.emission(tri, b) * (PI * tri.area() * sides);
        SurfacePoint {
            p: tri.point(b),
            n,
            flux: flux * scale as f32,
            depth: 0,
        }
    }

    /// Everything one step lights with: primary lights, RSMs, VPL paths, shadow views.
    fn build_step(&mut self) -> Result<StepLights, EngineError> {
        let step_key = self.rng.next_u64();
        let n_views = self.layout.rects.len();
        let mut views = vec![ShadowView::zeroed(); n_views];
        let mut lights = Vec::with_capacity(self.max_lights as usize);
        let mut draws = Vec::new();
        let mut rsm_rays = Vec::new();
        let r2 = self.radius * self.radius;
        let sky_solid_angle = match self.lighting.sky.map(|s| s.hemisphere) {
            Some(Hemisphere::Full) => 4.0 * PI,
            _ => 2.0 * PI,
        };
        for (slot, primary) in self.primaries.clone().into_iter().enumerate() {
            let view = self.primary_views[slot];
            let key = step_key ^ ((slot as u64 + 1) << 40);
            let distant = match primary {
                Primary::Sun => {
                    let sun = self.lighting.sun.expect("a Sun primary has a sun");
                    let (u1, u2) = (self.rng.next_f64() as f32, self.rng.next_f64() as f32);
                    let towards = cone_sample(-sun.direction.normalize(), sun.cos_half_angle(), u1, u2);
                    Some((-towards, sun.radiance * sun.solid_angle()))
                }
                Primary::Directional { dir, irradiance } => Some((dir, irradiance)),
                Primary::Sky => {
                    let mut w = self.directions.next_direction();
                    if self.lighting.sky.is_some_and(|s| s.hemisphere == Hemisphere::Upper) {
                        // Mirror the lower half up: uniform over the upper hemisphere.
                        w.y = w.y.abs();
                    }
                    let l = self.lighting.sky_radiance(w);
                    Some((-w, l * (sky_solid_angle / self.params.sky_directions as f32)))
                }
                Primary::Punctual(_) => None,
            };
            if let Some((dir, irradiance)) = distant {
                if irradiance == Vec3::ZERO {
                    continue;
                }
                views[view as usize] = self.ortho_view(view, dir);
                draws.push(view);
                lights.push(GpuLight {
                    pos: [0.0; 4],
                    axis_t: [0.0; 4],
                    axis_b: [0.0; 4],
                    axis_n: v4(dir, 0.0),
                    power: v4(irradiance / PI, 0.0),
                    spot: [0.0; 4],
                    info: [LIGHT_DIRECTIONAL, view, 1, 0],
                });
                let disc = (self.centre, self.radius * MARGIN, self.params.rsm_size);
                rsm_rays.extend(rsm::distant_rays(dir, irradiance, disc, (self.seed, key)));
            } else if let Primary::Punctual(i) = primary {
                let l = self.scene.lights[i].clone();
                let spot = matches!(l.kind, LightKind::Spot { .. });
                let frame = if spot {
                    let n = l.direction.normalize();
                    let (t, b) = basis(n);
                    (t, b, n)
                } else {
                    (Vec3::X, Vec3::Y, Vec3::Z)
                };
                let o = self.norm(l.position);
                for (k, v) in self.cube_views(view, 6, o, frame).into_iter().enumerate() {
                    views[view as usize + k] = v;
                    draws.push(view + k as u32);
                }
                let (cos_outer, inv) = match l.kind {
                    LightKind::Spot { inner_cone, outer_cone } => {
                        (outer_cone.cos(), 1.0 / (inner_cone.cos() - outer_cone.cos()).max(1e-3))
                    }
                    _ => (-2.0, 0.0),
                };
                lights.push(GpuLight {
                    pos: v4(o, 0.0),
                    axis_t: v4(frame.0, 0.0),
                    axis_b: v4(frame.1, 0.0),
                    axis_n: v4(frame.2, 0.0),
                    power: v4(l.intensity / (PI * r2), 0.0),
                    spot: [cos_outer, inv, l.range.map_or(0.0, |r| r / self.radius), 0.0],
                    info: [if spot { LIGHT_SPOT } else { LIGHT_POINT }, view, 1, 0],
                });
                let n = (self.params.rsm_size / 2).max(1);
                let faces = cube_faces(frame.0, frame.1, frame.2);
                rsm_rays.extend(rsm::punctual_rays(&self.scene, i, &faces, n, (self.seed, key)));
            }
        }

        let rsm = self.rsm.texels(&self.scene, &rsm_rays)?;

        // Path starts by luminance flux over RSM texels and emitters.
        let m = self.params.vpls_per_step as usize;
        let rsm_weight: f64 = rsm.iter().map(|s| lum(s.flux)).sum();
        let total = rsm_weight + self.emitter_weight;
        let mut vpls: Vec<SurfacePoint> = Vec::new();
        if total > 0.0 && total.is_finite() {
            let mut cdf = Vec::with_capacity(rsm.len() + self.emitters.len());
            let mut acc = 0.0;
            for w in rsm
                .iter()
                .map(|s| lum(s.flux))
                .chain(self.emitters.iter().map(|e| e.weight))
            {
                acc += w;
                cdf.push(acc);
            }
            let picks: Vec<(usize, u64)> = (0..m)
                .map(|k| {
                    let u = self.rng.next_f64() * total;
                    (cdf.partition_point(|&c| c <= u).min(cdf.len() - 1), k as u64)
                })
                .collect();
            let paths: Vec<Vec<SurfacePoint>> = picks
                .par_iter()
                .map(|&(index, k)| {
                    let mut rng = Rng::new(self.seed, step_key, k, 3);
                    let start = if index < rsm.len() {
                        let s = rsm[index];
                        SurfacePoint {
                            flux: s.flux * (total / (m as f64 * lum(s.flux))) as f32,
                            ..s
                        }
                    } else {
                        let e = &self.emitters[index - rsm.len()];
                        self.emitter_sample(e, total / (m as f64 * e.weight), &mut rng)
                    };
                    let mut out = Vec::new();
                    if lum(start.flux) > 0.0 {
                        self.continue_path(start, &mut rng, &mut out);
                    }
                    out
                })
                .collect();
            vpls = paths.into_iter().flatten().collect();
        }
        if vpls.len() > m {
            vpls = self.resample(&vpls, m);
        }

        let clamp2 = self.params.clamp * self.params.clamp;
        for (k, v) in vpls.iter().enumerate() {
            let o = self.norm(v.p);
            let (t, b) = basis(v.n);
            let first = if self.params.visibility {
                let first = self.vpl_views + 5 * k as u32;
                for (f, view) in self.cube_views(first, 5, o, (t, b, v.n)).into_iter().enumerate() {
                    views[first as usize + f] = view;
                    draws.push(first + f as u32);
                }
                first
            } else {
                NO_VIEW
            };
            lights.push(GpuLight {
                pos: v4(o, 0.0),
                axis_t: v4(t, 0.0),
                axis_b: v4(b, 0.0),
                axis_n: v4(v.n, 0.0),
                power: v4(v.flux / (PI * PI * r2), clamp2),
                spot: [0.0; 4],
                info: [LIGHT_VPL, first, u32::from(v.depth == 0), 0],
            });
        }
        Ok(StepLights { lights, views, draws })
    }

    /// `m` VPLs drawn from `vpls` with probability proportional to luminance flux, each
    /// carrying total / m; a VPL drawn k times is kept once with k times that.
    fn resample(&mut self, vpls: &[SurfacePoint], m: usize) -> Vec<SurfacePoint> {
        let mut cdf = Vec::with_capacity(vpls.len());
        let mut acc = 0.0;
        for v in vpls {
            acc += lum(v.flux);
            cdf.push(acc);
        }
        let total = acc;
        let mut counts = std::collections::BTreeMap::new();
        for _ in 0..m {
            let u = self.rng.next_f64() * total;
            *counts
                .entry(cdf.partition_point(|&c| c <= u).min(vpls.len() - 1))
                .or_insert(0u32) += 1;
        }
        counts
            .into_iter()
            .map(|(i, k)| {
                let v = vpls[i];
                SurfacePoint {
                    flux: v.flux * (total * k as f64 / (m as f64 * lum(v.flux))) as f32,
                    ..v
                }
            })
            .collect()
    }

    /// One step: the lights on the CPU, the maps, then the gather over every texel,
    /// whole, or in slices in a watched bake while steps may be long (the gather is the
    /// part that grows with the level: 1.1 s of a step at 1.46 M texels on lavapipe). A
    /// step stopped between slices puts back its half, its random stream and its
    /// directions, so it adds nothing and the next step is the one it would have been.
    pub(super) fn run_step(&mut self) -> Result<(), EngineError> {
        let parity = (self.steps_done % 2) as usize;
        let before = (self.rng.clone(), self.directions.clone());
        let step = self.build_step()?;
        let k = self.half_steps[parity] + 1;
        let q = &self.ctx.queue;
        if !step.lights.is_empty() {
            q.write_buffer(&self.lights_buf, 0, bytemuck::cast_slice(&step.lights));
        }
        if !step.views.is_empty() {
            q.write_buffer(&self.views_buf, 0, bytemuck::cast_slice(&step.views));
        }
        let mut params = GpuGatherParams {
            misc: [parity as u32, self.n_texels, step.lights.len() as u32, 0],
            bias: [1.0 / k as f32, NORMAL_OFFSET_PX, 0.0, 0.0],
            slice: [0, self.n_texels, 0, 0],
        };
        let draws: Vec<ShadowDraw> = step
            .draws
            .iter()
            .map(|&v| {
                let tile = self.layout.rects[v as usize];
                ShadowDraw {
                    view: v,
                    tile,
                    rows: tile[2],
                }
            })
            .collect();
        let gather = |encoder: &mut wgpu::CommandEncoder, size: (u32, u32)| {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("vpl gather"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.gather_pipeline);
            pass.set_bind_group(0, &self.gather_bg, &[]);
            pass.dispatch_workgroups(size.0, size.1, 1);
        };
        let watched = self.deadline.is_some() || self.progress.is_some();
        let progress = self.progress.clone();
        let mut go_on = go_on_until(self.deadline, progress.as_ref());
        if self.slicer.slices(watched) {
            // The maps first, in slices of whole maps (each one the whole scene drawn:
            // 0.17 s a map for a 1M-triangle level on lavapipe, 165 maps a step by
            // default with a sun and a sky), nothing to put back: the atlas is redrawn
            // every step. They are the step's first half of progress, the gather its second.
            let mut first_half = |done: u64, of: u64| go_on(done, 2 * of);
            let done = self
                .shadow
                .render_sliced(
                    &self.ctx,
                    &mut self.map_slicer,
                    &self.vertex_buf,
                    self.vertex_count,
                    &draws,
                    &mut first_half,
                )
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("vpl: the deadline passed or a stop was asked mid-step; the step is undone");
                (self.rng, self.directions) = before;
                return Ok(());
            }
            let aside = [
                Aside::half(&self.acc_buf, parity),
                Aside::half(&self.direct_acc_buf, parity),
            ];
            let mut submit = |first: u64, count: u64| {
                params.slice = [first as u32, count as u32, 0, 0];
                q.write_buffer(&self.gather_buf, 0, bytemuck::bytes_of(&params));
                Ok(self
                    .ctx
                    .submit_compute("vpl gather", &self.gather_pipeline, &self.gather_bg, count as u32))
            };
            let mut second_half = |done: u64, of: u64| go_on(of + done, 2 * of);
            let done = self
                .slicer
                .run(&self.ctx, self.n_texels as u64, &aside, &mut submit, &mut second_half)
                .map_err(gpu_error)?;
            if done == Sliced::Abandoned {
                tracing::debug!("vpl: the deadline passed or a stop was asked mid-step; the step is undone");
                (self.rng, self.directions) = before;
                return Ok(());
            }
        } else {
            let mut encoder = self.ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("vpl step"),
            });
            if !draws.is_empty() {
                self.shadow
                    .render(&mut encoder, &self.vertex_buf, self.vertex_count, draws.iter().copied());
            }
            q.write_buffer(&self.gather_buf, 0, bytemuck::bytes_of(&params));
            gather(&mut encoder, self.texel_dispatch);
            q.submit([encoder.finish()]);
            self.slicer.returned_whole();
        }
        self.half_steps[parity] = k;
        self.steps_done += 1;
        self.ctx.take_error("vpl step").map_err(gpu_error)
    }
}
