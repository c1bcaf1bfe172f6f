//! Closest-hit rays made on the CPU and traced on the GPU: [`GpuTracer`], the device's
//! counterpart of the CPU [`Tracer::trace`](crate::engine::raytrace::Tracer::trace), for
//! the passes whose rays are made and used on the CPU (texel validation, vpl's reflective
//! shadow maps) but are many enough that tracing them is the cost (issue 20 point 3).
//!
//! How: the rays go through the BVH query pass ([`QueryRunner`], `shaders/gpu/bvh_query.wgsl`)
//! of the scene's shared GPU BVH ([`SceneRays::gpu_bvh`]) in chunks of at most `capacity`,
//! and each answer comes back as the CPU's [`Hit`]: the scene's triangle (the BVH slot's
//! `id`), the distance and the barycentrics (1 - u - v, u, v) of the triangle's own
//! vertices. The alpha test is the query pass's (the scene's materials and textures), as
//! the CPU tracer's is. Where the GPU's closest hit is the CPU's (`tests/gpu_bvh.rs`:
//! the same triangle but within 1e-5 of an edge, distances to float precision), a caller
//! gets the same answers from either.
//!
//! Cost: one submission and one readback a chunk. That latency is why callers keep the
//! CPU for small batches and for chains of dependent rays (each link a round trip), and
//! use this on a hardware GPU only ([`super::hardware_context`]): on lavapipe the same
//! rays through a JIT on the same cores are slower than the CPU's own.
//!
//! Bounds: 32 bytes a ray and 16 an answer on the device, `capacity` of each; the host
//! keeps every answer of a call. A traversal whose stack overflowed (which
//! [`super::bvh::BvhData::new`]'s depth check rules out) is an error naming the ray,
//! never a silent miss.

use std::sync::Arc;

use glam::Vec3;

use super::bvh::{BVH_MISS, QUERY_OVERFLOW, QueryHit, QueryRay, QueryRunner};
use super::scene_lights::{GpuSceneLights, LightSources};
use super::scene_rays::SceneRays;
use super::{GpuContext, GpuError};
use crate::engine::raytrace::Hit;
use crate::engine::scene::Lighting;

/// One closest-hit ray: from `origin` along the unit `dir`, hits up to `tmax`
/// (`f32::INFINITY` for no limit).
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
    pub tmax: f32,
}

/// The query pass over one scene, with room for `capacity` rays a dispatch.
pub struct GpuTracer {
    ctx: Arc<GpuContext>,
    runner: QueryRunner,
    /// BVH slot -> scene triangle.
    ids: Vec<u32>,
    /// Names the caller in errors.
    who: String,
}

impl GpuTracer {
    /// A tracer of `rays`' scene on `ctx`; `who` names the caller in labels and errors.
    pub fn new(ctx: &Arc<GpuContext>, who: &str, rays: &SceneRays, capacity: usize) -> Result<Self, GpuError> {
        // No light is read: only the BVH and the materials the alpha test needs.
        let scene = GpuSceneLights::new(
            ctx,
            who,
            rays,
            &Lighting::default(),
            &rays.emitters(),
            LightSources::NONE,
        )?;
        let runner = QueryRunner::new(ctx, &scene, capacity)?;
        let ids = scene.bvh.data.tris.iter().map(|t| t.id).collect();
        Ok(GpuTracer {
            ctx: ctx.clone(),
            runner,
            ids,
            who: who.to_string(),
        })
    }

    /// The closest hit of every ray, in order (`None`: nothing within its `tmax`).
    pub fn trace(&self, rays: &[Ray]) -> Result<Vec<Option<Hit>>, GpuError> {
        let queries: Vec<QueryRay> = rays
            .iter()
            .map(|r| QueryRay {
                origin: r.origin.to_array(),
                // The query pass compares with tmax; f32::MAX is "no limit" there.
                tmax: r.tmax.min(f32::MAX),
                dir: r.dir.to_array(),
                mode: 0,
            })
            .collect();
        let answers: Vec<QueryHit> = self.runner.run(&self.ctx, &queries)?;
        answers
            .iter()
            .enumerate()
            .map(|(i, h)| match h.slot {
                BVH_MISS => Ok(None),
                QUERY_OVERFLOW => Err(GpuError::Device {
                    during: self.who.clone(),
                    message: format!("ray {i} overflowed the BVH traversal stack"),
                }),
                slot => Ok(Some(Hit {
                    triangle: self.ids[slot as usize],
                    t: h.t,
                    bary: Vec3::new(1.0 - h.u - h.v, h.u, h.v),
                })),
            })
            .collect()
    }
}
