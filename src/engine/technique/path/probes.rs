//! Light probes baked by `path` (issue 26 point 1): the incident radiance at points in
//! free space as real spherical harmonics up to L2, for the dynamic objects a lightmap
//! cannot light.
//!
//! # Convention
//! Each probe stores the SH projection of the *incident radiance* L(w) (w pointing away
//! from the probe, toward where the light comes from): c_i = integral over the sphere of
//! L(w) Y_i(w) dw, RGB, nine coefficients in the order
//! Y_00; Y_1-1, Y_10, Y_11; Y_2-2, Y_2-1, Y_20, Y_21, Y_22 with the usual real,
//! orthonormal basis in *world* axes (x, y, z; y is up in glTF):
//! Y_00 = 0.282095, Y_1-1 = 0.488603 y, Y_10 = 0.488603 z, Y_11 = 0.488603 x,
//! Y_2-2 = 1.092548 x y, Y_2-1 = 1.092548 y z, Y_20 = 0.315392 (3 z^2 - 1),
//! Y_21 = 1.092548 x z, Y_22 = 0.546274 (x^2 - y^2) ([`sh9`]). L1 is the first four.
//! A renderer gets irradiance E(n) = sum_i A_l c_i Y_i(n) with A_0 = pi, A_1 = 2 pi / 3,
//! A_2 = pi / 4 (Ramamoorthi & Hanrahan 2001), and the lightmap's quantity, E / pi
//! (DESIGN section 2), by dividing by pi ([`irradiance_over_pi`]).
//!
//! # How (per probe and sample, on all CPU cores)
//! - One direction w uniform on the sphere (density 1 / 4 pi); the ray's radiance is the
//!   sky where it leaves the scene (not the sun's disc: that is sampled below), black on
//!   the back of a single-sided surface, else the surface's emission plus albedo times
//!   `path`'s own estimate of E / pi there (next-event estimation and a cosine-sampled
//!   continuation: the same estimator as a texel's). Weighted 4 pi Y_i(w).
//! - Next-event estimation for the light a uniform direction cannot find: every point,
//!   spot and directional light (a delta in direction d with E_perp = I att / r^2, or the
//!   directional light's irradiance: E_perp Y_i(d)) and the sun (one direction in its
//!   cone, radiance x solid angle x Y_i(d)), each with a shadow ray.
//! - Emitters both ways, combined by multiple importance sampling (Veach's power
//!   heuristic): the uniform direction's hit counts its emission with weight
//!   w(1/4pi, p_light), and one emissive triangle (picked by the bake's [`EmitterTable`],
//!   in proportion to area x emitted luminance, a uniform point on it) is sampled with a
//!   shadow ray and weight w(p_light, 1/4pi), p_light the solid-angle density
//!   pick / area x d^2 / cos. A small emitter a uniform direction rarely finds is then
//!   found every sample (measured in tests/probes.rs, a 0.2 m emitter 1 m up, 16 x 64
//!   samples: with uniform directions alone c00 read 24 % high with an estimated error of
//!   50 %; with emitter sampling it is within 0.04 % of the closed form, estimated error
//!   0.006 %).
//! - Two half accumulators (even and odd steps) as for texels; a probe's error is the
//!   standard error of its L0 luminance, |even - odd| sqrt(n_e n_o) / (n_e + n_o), over
//!   its L0 luminance.
//! - Random numbers as the texels' (`params.sampling`, `path/sampler.rs`): by default an
//!   Owen-scrambled Sobol sequence per probe and half; the probe's own direction, sun and
//!   emitter samples take vertex 0's two sets in the texel path's layout, and the path
//!   from a hit goes on from vertex 1's (`sampler::Deeper`). The halves stay independent
//!   (their own scrambles), so the error estimate holds. Under an upper sky the sky is
//!   seen where y = r sin 2πu2 > 0, one stratified coordinate: an unoccluded probe's L0 is
//!   then exact and so is its estimate (0). Measured (`probe_bench`, docs/probes.md), true
//!   L0 error at 4096 samples against independent numbers: 0.109 % against 0.276 % in the
//!   furnace (+14 % time), 0.020 % against 0.200 % under the small lamp.
//!
//! # Placement
//! Given positions, or a grid at `spacing` over the scene's bounds (cell centres). A
//! probe inside geometry would read the black backs of the surfaces around it: 64
//! stratified directions are cast from it, and a probe that sees the back face of a
//! single-sided surface in more than half of them is marked invalid (`valid = false`)
//! and not baked; a probe in open space or beside a wall sees back faces in none.
//!
//! # Where
//! On all CPU cores, or on the GPU (`params.device`, the job's `probes.device`): the same
//! estimator as one compute pass over the bake's GPU uploads ([`super::probes_gpu`]), with
//! the same half accumulators; the inside test stays on the CPU either way.
//!
//! Limits: the GPU's random streams are not the CPU's (the two agree
//! in the mean within noise, `tests/probes.rs`).

use std::sync::Arc;

use glam::Vec3;
use rayon::prelude::*;
use serde::Serialize;

use super::probe_placement::scene_ray_offset;
pub use super::probe_placement::{MAX_SUBDIVIDE, adaptive_positions, grid_positions};
use super::probes_gpu::ProbeGpu;
use super::sampler::{Deeper, PathSampler, Sobol};
use super::{Device, PathContext, PathParams, Sampling, power_heuristic};
use crate::engine::accumulate::LUMINANCE;
use crate::engine::error::EngineError;
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::raytrace::{EmitterTable, Tracer, cone_sample, inset};
use crate::engine::rng::Rng;
use crate::engine::scene::{LightKind, Lighting, Scene};
use crate::engine::technique::api::gpu_error;

/// Coefficients of L2 spherical harmonics.
pub const SH9: usize = 9;
/// Directions of the inside test.
const INSIDE_RAYS: u32 = 64;

/// The real SH basis up to L2 at unit direction `w` (order in the module doc).
pub fn sh9(w: Vec3) -> [f32; SH9] {
    let (x, y, z) = (w.x, w.y, w.z);
    [
        0.282_095,
        0.488_603 * y,
        0.488_603 * z,
        0.488_603 * x,
        1.092_548 * x * y,
        1.092_548 * y * z,
        0.315_392 * (3.0 * z * z - 1.0),
        1.092_548 * x * z,
        0.546_274 * (x * x - y * y),
    ]
}

/// E(n) / pi from radiance coefficients `c`: the cosine lobe's convolution, band by band.
pub fn irradiance_over_pi(c: &[Vec3; SH9], n: Vec3) -> Vec3 {
    let y = sh9(n);
    let band = [1.0, 2.0 / 3.0, 2.0 / 3.0, 2.0 / 3.0, 0.25, 0.25, 0.25, 0.25, 0.25];
    (0..SH9).map(|i| c[i] * (band[i] * y[i])).sum()
}

fn uniform_sphere(u1: f32, u2: f32) -> Vec3 {
    let z = 1.0 - 2.0 * u1;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * std::f32::consts::PI * u2;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// One baked probe.
#[derive(Clone, Debug, Serialize)]
pub struct Probe {
    /// World space (the glTF's coordinates).
    pub position: [f32; 3],
    /// False when the probe lies inside geometry (not baked; its coefficients are 0).
    pub valid: bool,
    /// Radiance SH, 9 x RGB (module doc).
    pub sh: [[f32; 3]; SH9],
    /// Relative standard error of the L0 luminance (0 for an invalid or black probe);
    /// None (JSON null) until both halves have a step: one half alone cannot estimate it.
    pub error: Option<f32>,
}

/// The probes file's body (`--probes`): convention, basis and the probes.
#[derive(Clone, Debug, Serialize)]
pub struct ProbeSet {
    pub convention: &'static str,
    pub basis: &'static str,
    pub steps: u64,
    /// The whole set's relative error: the RMS over valid probes of the L0 luminance's
    /// standard error, over the RMS L0 luminance (the texels' estimate, DESIGN section 4);
    /// None (JSON null) until both halves have a step, as for texels.
    pub error: Option<f32>,
    pub probes: Vec<Probe>,
}

/// The most probes a bake places.
pub const MAX_PROBES: usize = 100_000;

/// Where a job's probes go, in the scene's frame: a grid at `spacing` (if given; split
/// `subdivide` levels down where geometry passes, `probe_placement`), the
/// `given` world positions, and the scene's probe nodes (`extras.light_probe`), at most
/// [`MAX_PROBES`]. Errors name the job field (`probes.spacing`, `probes.positions[k]`).
pub fn positions_for(
    scene: &Scene,
    spacing: Option<f32>,
    subdivide: u32,
    given: &[[f64; 3]],
) -> Result<Vec<Vec3>, EngineError> {
    let mut out = match spacing {
        Some(s) => adaptive_positions(scene, s, subdivide, MAX_PROBES)?,
        None if subdivide > 0 => {
            return Err(EngineError::BadInput(
                "probes.subdivide refines the grid of probes.spacing: give probes.spacing too".into(),
            ));
        }
        None => Vec::new(),
    };
    for (k, p) in given.iter().enumerate() {
        let p = glam::DVec3::from_array(*p);
        if !p.is_finite() {
            return Err(EngineError::BadInput(format!("probes.positions[{k}] is not finite")));
        }
        out.push((p - scene.origin_offset).as_vec3());
    }
    out.extend(scene.probe_nodes.iter().map(|(_, p)| *p));
    if out.is_empty() {
        return Err(EngineError::BadInput(
            "probes: no position: give probes.spacing or probes.positions, or mark glTF nodes with extras.light_probe = true"
                .into(),
        ));
    }
    if out.len() > MAX_PROBES {
        return Err(EngineError::BadInput(format!(
            "probes: {} probes, at most {MAX_PROBES}",
            out.len()
        )));
    }
    Ok(out)
}

/// Bakes probes at `positions` (the scene's own frame: world minus `Scene::origin_offset`,
/// as [`grid_positions`] gives them; [`Probe::position`] is world space again) with
/// `path`'s estimator.
pub struct ProbeBaker<'a> {
    scene: &'a Scene,
    lighting: Lighting,
    tracer: Arc<Tracer>,
    emitters: Arc<EmitterTable>,
    params: PathParams,
    positions: Vec<Vec3>,
    valid: Vec<bool>,
    seed: u64,
    halves: [Vec<[Vec3; SH9]>; 2],
    steps: [u64; 2],
    /// Offset of secondary rays off surfaces (the atlas's surface offset for the scene).
    eps: f32,
    /// The valid probes' pass when they bake on the GPU (`params.device`); `halves` then
    /// stay zero until [`ProbeBaker::result`] reads them back.
    gpu: Option<ProbeGpu>,
}

impl<'a> ProbeBaker<'a> {
    /// A baker on the CPU: `params.device` must be `cpu` or `auto` (which stays on the CPU
    /// here: the GPU route needs the bake's [`SceneRays`], [`ProbeBaker::sharing`]).
    pub fn new(
        scene: &'a Scene,
        lighting: Lighting,
        positions: Vec<Vec3>,
        params: &serde_json::Value,
        seed: u64,
    ) -> Result<Self, EngineError> {
        let params: PathParams = crate::engine::technique::api::parse_params("path", params)?;
        if params.device == Device::Gpu {
            return Err(EngineError::BadInput(
                "probes: device gpu needs the bake's scene rays (ProbeBaker::sharing)".into(),
            ));
        }
        let parts = (Arc::new(Tracer::new(scene)), Arc::new(EmitterTable::new(scene)));
        Self::build(scene, parts, lighting, positions, params, seed)
    }

    /// [`ProbeBaker::new`] on the scene of `rays`, tracing the BVH the bake built: on the
    /// GPU when `params.device` asks for it (`auto`: a hardware adapter), with the bake's
    /// GPU uploads of the scene.
    pub fn sharing(
        rays: &'a SceneRays,
        lighting: Lighting,
        positions: Vec<Vec3>,
        params: &serde_json::Value,
        seed: u64,
    ) -> Result<Self, EngineError> {
        let params: PathParams = crate::engine::technique::api::parse_params("path", params)?;
        let ctx = params.device.context("light probes").map_err(gpu_error)?;
        let parts = (rays.tracer(), rays.emitters());
        let mut baker = Self::build(rays.scene(), parts, lighting, positions, params, seed)?;
        if let Some(ctx) = ctx {
            let points: Vec<(u32, Vec3)> = (0..baker.positions.len())
                .filter(|&i| baker.valid[i])
                .map(|i| (i as u32, baker.positions[i]))
                .collect();
            baker.gpu = Some(ProbeGpu::new(
                ctx,
                rays,
                &baker.lighting,
                &points,
                &baker.params,
                seed,
                baker.eps,
            )?);
        }
        Ok(baker)
    }

    /// Where the probes bake: the GPU adapter's name, or `cpu`.
    pub fn device(&self) -> String {
        self.gpu
            .as_ref()
            .map_or_else(|| "cpu".to_string(), |g| g.adapter().to_string())
    }

    fn build(
        scene: &'a Scene,
        (tracer, emitters): (Arc<Tracer>, Arc<EmitterTable>),
        lighting: Lighting,
        positions: Vec<Vec3>,
        mut params: PathParams,
        seed: u64,
    ) -> Result<Self, EngineError> {
        params.validate()?;
        if let Some(k) = positions.iter().position(|p| !p.is_finite()) {
            return Err(EngineError::BadInput(format!("probes.positions[{k}] is not finite")));
        }
        let eps = scene_ray_offset(scene);
        params.choose_rr_threshold(scene, &tracer);
        let valid: Vec<bool> = positions
            .par_iter()
            .map(|p| !inside_geometry(scene, &tracer, *p))
            .collect();
        let n = positions.len();
        Ok(ProbeBaker {
            scene,
            lighting,
            emitters,
            tracer,
            params,
            positions,
            valid,
            seed,
            halves: [vec![[Vec3::ZERO; SH9]; n], vec![[Vec3::ZERO; SH9]; n]],
            steps: [0, 0],
            eps,
            gpu: None,
        })
    }

    pub fn valid(&self) -> &[bool] {
        &self.valid
    }

    /// One step: `samples_per_step` samples for every valid probe, into the half of the
    /// step's parity (running means); on the GPU one dispatch, not waited for.
    pub fn step(&mut self) -> Result<(), EngineError> {
        let step = self.steps[0] + self.steps[1];
        let half = (step % 2) as usize;
        let k = self.steps[half] + 1;
        if let Some(gpu) = &mut self.gpu {
            gpu.step()?;
            self.steps[half] = k;
            return Ok(());
        }
        let ctx = PathContext {
            scene: self.scene,
            tracer: &self.tracer,
            emitters: &self.emitters,
            lighting: &self.lighting,
            max_bounces: self.params.max_bounces,
            rr_threshold: self.params.threshold(),
            eps: self.eps,
        };
        let spp = self.params.samples_per_step;
        let seed = self.seed;
        let this = &*self;
        let means: Vec<[Vec3; SH9]> = (0..this.positions.len())
            .into_par_iter()
            .map(|i| {
                if !this.valid[i] {
                    return [Vec3::ZERO; SH9];
                }
                let mut sum = [Vec3::ZERO; SH9];
                let key = seed ^ 0x9B_0BE5;
                for s in 0..spp {
                    match this.params.sampling {
                        Sampling::Sobol => {
                            let mut sobol = Sobol::new(key, step, i as u64, s, spp);
                            this.sample(&ctx, this.positions[i], &mut sobol, &mut sum);
                        }
                        Sampling::Independent => {
                            let mut rng = Rng::new(key, step, i as u64, s as u64);
                            this.sample(&ctx, this.positions[i], &mut rng, &mut sum);
                        }
                    }
                }
                sum.map(|c| c / spp as f32)
            })
            .collect();
        let blend = 1.0 / k as f32;
        for (acc, m) in self.halves[half].iter_mut().zip(&means) {
            for c in 0..SH9 {
                acc[c] += (m[c] - acc[c]) * blend;
            }
        }
        self.steps[half] = k;
        Ok(())
    }

    /// Adds one sample's SH estimate at `x` to `sum`.
    fn sample(&self, ctx: &PathContext<'_>, x: Vec3, rng: &mut impl PathSampler, sum: &mut [Vec3; SH9]) {
        let scene = self.scene;
        let mut add = |l: Vec3, w: Vec3, weight: f32| {
            let y = sh9(w);
            for c in 0..SH9 {
                sum[c] += l * (y[c] * weight);
            }
        };
        // A uniform direction: sky, or a surface's emitted + reflected radiance.
        // Vertex 0's numbers are the probe's own (its direction, the sun, the emitter); the
        // path from the hit goes on from vertex 1's (`Deeper`).
        let (u1, u2) = rng.direction(0);
        let w = uniform_sphere(u1, u2);
        let (sun_u1, sun_u2) = rng.sun(0);
        let (pick_u, b1, b2) = rng.emitter(0);
        let four_pi = 4.0 * std::f32::consts::PI;
        match self.tracer.trace(scene, x, w, f32::INFINITY) {
            None => add(self.lighting.sky_radiance(w), w, four_pi),
            Some(hit) => {
                let tri = &scene.triangles[hit.triangle as usize];
                let material = scene.material(tri);
                let geo = self.tracer.geometric_normal(hit.triangle);
                let front = w.dot(geo) < 0.0;
                if front || material.double_sided {
                    let side = if front { 1.0 } else { -1.0 };
                    let ng = geo * side;
                    let shading = (tri.n[0] * hit.bary.x + tri.n[1] * hit.bary.y + tri.n[2] * hit.bary.z)
                        .normalize_or_zero()
                        * side;
                    let n = if shading.dot(ng) > 0.0 { shading } else { ng };
                    let p = tri.point(inset(hit.bary)) + ng * self.eps;
                    let reflected = scene.albedo(tri, hit.bary) * ctx.radiance(p, n, ng, &mut Deeper(&mut *rng)).total;
                    let emitted = scene.emission(tri, hit.bary);
                    // The emitter sampling below could have drawn this direction too.
                    let weight = if emitted == Vec3::ZERO {
                        1.0
                    } else {
                        let density = self.emitters.pick_density[hit.triangle as usize];
                        let cos_l = w.dot(geo).abs();
                        let pdf_light = density * hit.t * hit.t / cos_l.max(f32::MIN_POSITIVE);
                        power_heuristic(1.0 / four_pi, pdf_light)
                    };
                    add(emitted * weight + reflected, w, four_pi);
                }
            }
        }
        // Delta lights and the sun, which uniform directions cannot find.
        for light in &scene.lights {
            match light.kind {
                LightKind::Directional => {
                    let d = -light.direction;
                    if self.tracer.unoccluded(scene, x, d, f32::INFINITY) {
                        add(light.intensity, d, 1.0);
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
                    let falloff = light.attenuation(dist, -d) / dist2;
                    if falloff > 0.0 && self.tracer.unoccluded(scene, x, d, dist * (1.0 - 1e-4)) {
                        add(light.intensity * falloff, d, 1.0);
                    }
                }
            }
        }
        if let Some(sun) = &self.lighting.sun {
            let axis = -sun.direction.normalize();
            let d = cone_sample(axis, sun.cos_half_angle(), sun_u1, sun_u2);
            if self.tracer.unoccluded(scene, x, d, f32::INFINITY) {
                add(sun.radiance, d, sun.solid_angle());
            }
        }
        // One emitter sample (module doc), MIS-weighted against the uniform direction.
        let table = &*self.emitters;
        if !table.emitters.is_empty() {
            let u = pick_u;
            let k = table
                .emitter_cdf
                .partition_point(|c| *c <= u)
                .min(table.emitters.len() - 1);
            let ti = table.emitters[k];
            let tri = &scene.triangles[ti as usize];
            let (mut b1, mut b2) = (b1, b2);
            if b1 + b2 > 1.0 {
                b1 = 1.0 - b1;
                b2 = 1.0 - b2;
            }
            let bary = Vec3::new(1.0 - b1 - b2, b1, b2);
            let to = tri.point(bary) - x;
            let dist2 = to.length_squared();
            let dist = dist2.sqrt();
            if dist > 0.0 {
                let d = to / dist;
                let cos_l = -d.dot(self.tracer.geometric_normal(ti));
                let cos_l = if scene.material(tri).double_sided {
                    cos_l.abs()
                } else {
                    cos_l
                };
                let emitted = scene.emission(tri, bary);
                // Stop short of the emitter so it does not occlude its own sample.
                if cos_l > 0.0 && emitted != Vec3::ZERO && self.tracer.unoccluded(scene, x, d, dist * (1.0 - 1e-4)) {
                    let pdf_light = table.pick_density[ti as usize] * dist2 / cos_l;
                    add(emitted, d, power_heuristic(pdf_light, 1.0 / four_pi) / pdf_light);
                }
            }
        }
    }

    /// The probes as of now (on the GPU, read back first: this waits for the steps).
    pub fn result(&mut self) -> Result<ProbeSet, EngineError> {
        if let Some(gpu) = &self.gpu {
            let [even, odd] = gpu.halves()?;
            let valid = (0..self.positions.len()).filter(|&i| self.valid[i]);
            for (i, (e, o)) in valid.zip(even.into_iter().zip(odd)) {
                self.halves[0][i] = e;
                self.halves[1][i] = o;
            }
        }
        let (ne, no) = (self.steps[0] as f32, self.steps[1] as f32);
        let both_halves = ne > 0.0 && no > 0.0;
        let n = (ne + no).max(1.0);
        let k = (ne * no).sqrt() / n;
        let (mut se2, mut l02, mut valid) = (0.0f64, 0.0f64, 0usize);
        let probes: Vec<Probe> = (0..self.positions.len())
            .map(|i| {
                let (a, b) = (&self.halves[0][i], &self.halves[1][i]);
                let c: [Vec3; SH9] = std::array::from_fn(|j| (a[j] * ne + b[j] * no) / n);
                let l0 = c[0].dot(LUMINANCE);
                let se = ((a[0] - b[0]).dot(LUMINANCE) * k).abs();
                if self.valid[i] {
                    se2 += (se as f64).powi(2);
                    l02 += (l0 as f64).powi(2);
                    valid += 1;
                }
                Probe {
                    position: (self.positions[i].as_dvec3() + self.scene.origin_offset)
                        .as_vec3()
                        .to_array(),
                    valid: self.valid[i],
                    sh: c.map(|v| v.to_array()),
                    error: both_halves.then_some(if l0 > 0.0 { se / l0 } else { 0.0 }),
                }
            })
            .collect();
        Ok(ProbeSet {
            convention: "incident radiance, projected on real orthonormal SH to L2 (W m^-2 sr^-1 x sr); E(n)/pi = sum_i A_l c_i Y_i(n) / pi with A = pi, 2pi/3, pi/4",
            basis: "world axes; order Y00, Y1-1 (y), Y10 (z), Y11 (x), Y2-2 (xy), Y2-1 (yz), Y20 (3z^2-1), Y21 (xz), Y22 (x^2-y^2)",
            steps: self.steps[0] + self.steps[1],
            error: both_halves.then_some(if valid > 0 && l02 > 0.0 {
                (se2 / l02).sqrt() as f32
            } else {
                0.0
            }),
            probes,
        })
    }
}

/// True when `x` sees the back of a single-sided surface (the rule of
/// `atlas::validate::backface_fractions` for texels, here over the whole sphere since a
/// probe has no normal) in more than half of
/// [`INSIDE_RAYS`] stratified directions (module doc, *Placement*).
fn inside_geometry(scene: &Scene, tracer: &Tracer, x: Vec3) -> bool {
    let side = (INSIDE_RAYS as f32).sqrt() as u32;
    let mut backs = 0;
    for i in 0..side {
        for j in 0..side {
            let w = uniform_sphere((i as f32 + 0.5) / side as f32, (j as f32 + 0.5) / side as f32);
            if let Some(hit) = tracer.trace(scene, x, w, f32::INFINITY) {
                let tri = &scene.triangles[hit.triangle as usize];
                if w.dot(tracer.geometric_normal(hit.triangle)) > 0.0 && !scene.material(tri).double_sided {
                    backs += 1;
                }
            }
        }
    }
    backs * 2 > side * side
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The basis is orthonormal: a Monte Carlo-free check on a fine stratified grid.
    #[test]
    fn basis_is_orthonormal() {
        let n = 400;
        let mut gram = [[0.0f64; SH9]; SH9];
        for i in 0..n {
            for j in 0..n {
                let w = uniform_sphere((i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32);
                let y = sh9(w);
                for a in 0..SH9 {
                    for b in 0..SH9 {
                        gram[a][b] += (y[a] * y[b]) as f64;
                    }
                }
            }
        }
        let da = 4.0 * std::f64::consts::PI / (n * n) as f64;
        for (a, row) in gram.iter().enumerate() {
            for (b, g) in row.iter().enumerate() {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((g * da - want).abs() < 2e-3, "<Y{a}, Y{b}> = {}", g * da);
            }
        }
    }

    /// A constant radiance L gives c_0 = L sqrt(4 pi) and E/pi = L for every normal.
    #[test]
    fn constant_radiance_has_irradiance_over_pi_equal_to_it() {
        let mut c = [Vec3::ZERO; SH9];
        c[0] = Vec3::splat(2.0 * (4.0 * std::f32::consts::PI).sqrt());
        for n in [Vec3::Y, Vec3::X, Vec3::new(0.3, -0.8, 0.52).normalize()] {
            assert!((irradiance_over_pi(&c, n) - Vec3::splat(2.0)).abs().max_element() < 1e-5);
        }
    }
}
