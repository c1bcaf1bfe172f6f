//! vpl's reflective shadow maps (step 2 of the technique's doc): the rays of every
//! primary light's map, made on the CPU, traced on the CPU or on the GPU (`params.rays`,
//! issue 20 point 3), and the map's texels from their hits.
//!
//! How: a distant light's map is an orthographic `rsm_size`^2 grid over the scene's
//! bounding disc, a point or spot light's a cube of six (`rsm_size`/2)^2 faces; one
//! jittered ray a texel, each row from its own stream (keyed by bake seed, step, light
//! and row), so the rays do not depend on the route or the core count. A texel's flux
//! is the light's share through it (irradiance x texel area, or intensity x the texel's
//! solid angle x the falloff at the hit) times the albedo at the hit; back faces of
//! single-sided surfaces and misses reflect nothing.
//!
//! Routes: `cpu` traces with the shared CPU BVH on every core (rayon); `gpu` sends the
//! step's rays of every light in one batch through the shared [`GpuTracer`] (the BVH
//! query pass), whose answers are the CPU's [`Hit`]s, so the two routes give the same
//! texels wherever the GPU's closest hit is the CPU's (`tests/vpl.rs` compares whole
//! bakes). `auto` is the GPU on a hardware adapter only: on lavapipe the query pass runs
//! on the same cores through a JIT. A step's maps are 4096 to a few hundred thousand
//! rays (`rsm_size` 64 to 1024, one to 64 distant lights): enough to be worth one round
//! trip to a GPU. The VPL paths' bounces stay on the CPU on every route: at most
//! `vpls_per_step` (<= 1024) rays a generation, each generation waiting for the one
//! before, so a GPU would pay a round trip for every bounce of the longest path (tens
//! in a bright room) to trace what the CPU does in well under a millisecond.
//!
//! Bounds: the GPU route's buffers hold [`GPU_CHUNK`] rays (32 MiB); larger steps go in
//! several dispatches.

use std::sync::Arc;

use glam::Vec3;
use rayon::prelude::*;

use super::SurfacePoint;
use crate::engine::gpu::tracer::{GpuTracer, Ray};
use crate::engine::raytrace::{Hit, Tracer, basis, inset};
use crate::engine::rng::Rng;
use crate::engine::scene::Scene;
use crate::engine::technique::api::{EngineError, gpu_error};

/// Rays the GPU route sends in one dispatch at most.
pub const GPU_CHUNK: usize = 1 << 20;

/// One texel's ray of a light's map and the light's share through it.
#[derive(Clone, Copy, Debug)]
pub struct RsmRay {
    pub ray: Ray,
    /// The flux through the texel before the albedo at the hit (and, for a point or
    /// spot light, before its falloff with distance).
    pub flux: Vec3,
    /// The point or spot light whose falloff applies at the hit.
    pub punctual: Option<usize>,
}

/// Who traces the maps' rays.
pub enum RsmTracer {
    Cpu(Arc<Tracer>),
    Gpu(GpuTracer),
}

/// The point, the side it faces and the albedo where a ray along `dir` hit; `None`
/// when it reflects nothing (the black back face of single-sided geometry).
pub fn surface_of(scene: &Scene, hit: &Hit, dir: Vec3) -> Option<(Vec3, Vec3, Vec3)> {
    let tri = &scene.triangles[hit.triangle as usize];
    let ng = tri.geometric_normal();
    let front = ng.dot(dir) < 0.0;
    if !front && !scene.material(tri).double_sided {
        return None;
    }
    let b = inset(hit.bary);
    Some((tri.point(b), if front { ng } else { -ng }, scene.albedo(tri, b)))
}

/// The rays of a distant light's map: travelling along `dir` with `irradiance`
/// (facing it), over the disc of radius `r` around `centre`, `n`^2 texels.
pub fn distant_rays(
    dir: Vec3,
    irradiance: Vec3,
    (centre, r, n): (Vec3, f32, u32),
    (seed, key): (u64, u64),
) -> Vec<RsmRay> {
    let (t, b) = basis(dir);
    let pixel = 2.0 * r / n as f32;
    let flux = irradiance * (pixel * pixel);
    let rows: Vec<Vec<RsmRay>> = (0..n)
        .into_par_iter()
        .map(|j| {
            let mut rng = Rng::new(seed, key, j as u64, 1);
            (0..n)
                .map(|i| {
                    let x = -r + (i as f32 + rng.next_f32()) * pixel;
                    let y = -r + (j as f32 + rng.next_f32()) * pixel;
                    RsmRay {
                        ray: Ray {
                            origin: centre + t * x + b * y - dir * (2.0 * r),
                            dir,
                            tmax: 4.0 * r,
                        },
                        flux,
                        punctual: None,
                    }
                })
                .collect()
        })
        .collect();
    rows.into_iter().flatten().collect()
}

/// The rays of point or spot light `light`'s cube map (faces from `faces`, `n`^2 texels
/// each); texels outside a spot's cone get none.
pub fn punctual_rays(
    scene: &Scene,
    light: usize,
    faces: &[(Vec3, Vec3, Vec3); 6],
    n: u32,
    (seed, key): (u64, u64),
) -> Vec<RsmRay> {
    let l = &scene.lights[light];
    let pixel = 2.0 / n as f32;
    let rows: Vec<Vec<RsmRay>> = (0..6 * n)
        .into_par_iter()
        .map(|row_index| {
            let (face, j) = (row_index / n, row_index % n);
            let (fwd, right, up) = faces[face as usize];
            let mut rng = Rng::new(seed, key, row_index as u64, 2);
            let mut row = Vec::new();
            for i in 0..n {
                let u = -1.0 + (i as f32 + rng.next_f32()) * pixel;
                let v = -1.0 + (j as f32 + rng.next_f32()) * pixel;
                let w = fwd + right * u + up * v;
                let len2 = w.length_squared();
                let dir = w / len2.sqrt();
                // The cone alone first: most of a spot's cube misses it.
                if l.attenuation(0.0, dir) <= 0.0 {
                    continue;
                }
                // Solid angle of a pixel of a unit-distance face at (u, v).
                let d_omega = pixel * pixel / (len2 * len2.sqrt());
                row.push(RsmRay {
                    ray: Ray {
                        origin: l.position,
                        dir,
                        tmax: f32::INFINITY,
                    },
                    flux: l.intensity * d_omega,
                    punctual: Some(light),
                });
            }
            row
        })
        .collect();
    rows.into_iter().flatten().collect()
}

impl RsmTracer {
    /// The maps' texels, in the order of `rays`, of the rays that hit a surface that
    /// reflects light (depth 1: the first bounce's VPL candidates).
    pub fn texels(&self, scene: &Scene, rays: &[RsmRay]) -> Result<Vec<SurfacePoint>, EngineError> {
        let shade = |r: &RsmRay, hit: Option<&Hit>| -> Option<SurfacePoint> {
            let (p, n, albedo) = surface_of(scene, hit?, r.ray.dir)?;
            let falloff = r.punctual.map_or(1.0, |i| {
                scene.lights[i].attenuation(p.distance(scene.lights[i].position), r.ray.dir)
            });
            let flux = r.flux * falloff * albedo;
            (super::lum(flux) > 0.0).then_some(SurfacePoint { p, n, flux, depth: 1 })
        };
        Ok(match self {
            RsmTracer::Cpu(tracer) => rays
                .par_iter()
                .filter_map(|r| shade(r, tracer.trace(scene, r.ray.origin, r.ray.dir, r.ray.tmax).as_ref()))
                .collect(),
            RsmTracer::Gpu(tracer) => {
                let plain: Vec<Ray> = rays.iter().map(|r| r.ray).collect();
                let hits = tracer.trace(&plain).map_err(gpu_error)?;
                rays.par_iter()
                    .zip(hits.par_iter())
                    .filter_map(|(r, h)| shade(r, h.as_ref()))
                    .collect()
            }
        })
    }
}
