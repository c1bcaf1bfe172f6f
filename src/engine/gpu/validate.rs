//! Texel validation's rays on the GPU (issue 20 point 3): the back-face test of
//! `atlas::validate` with its rays traced by the BVH query pass ([`GpuTracer`], the
//! shared tracer of CPU-made rays) instead of the CPU tracer.
//!
//! How: the CPU makes the rays, the GPU traces them, the CPU counts. Every texel's rays
//! come from its own stream ([`validate::texel_rng`], [`validate::test_direction`]) exactly
//! as on the CPU, the first [`FIRST_BATCH`] of them for every texel, then the rest of the
//! [`RAYS`] only for the texels the first batch left undecided
//! ([`validate::decided_after_first_batch`]); a hit's triangle is tested by the same
//! [`validate::is_back_face`]. So the route only changes who traces: where the GPU's
//! closest hit is the CPU's (`tests/gpu_bvh.rs`), both routes give every texel the same
//! fraction, which `tests/validation.rs` checks on lavapipe.
//!
//! Why a query pass and not a shader of its own: validation runs once a bake, its rays
//! are few beside a bake's (16 a texel for most), and its cost on a real level was the
//! CPU's tracing (56.6 s of the 60.5 s preparation of a 15.6 M-texel level on 2 cores,
//! docs/performance.md), which the query pass moves to the device; generating the rays
//! and counting stay on all cores (rayon).
//!
//! Bounds: texels go in chunks of [`CHUNK_TEXELS`] (up to 16 rays each in the first
//! batch, 32 bytes a ray: 32 MiB of rays a dispatch), so memory does not grow with the
//! level. A traversal that overflowed its stack (which `BvhData::new`'s depth check
//! rules out) is an error ([`GpuTracer::trace`]), never a silent miss.
//!
//! Who uses it: `engine::job` on a hardware GPU ([`super::hardware_context`]); on lavapipe
//! the CPU route is faster, since the query pass runs on the same cores through a JIT.

use std::sync::Arc;

use rayon::prelude::*;

use super::scene_rays::SceneRays;
use super::tracer::{GpuTracer, Ray};
use super::{GpuContext, GpuError};
use crate::engine::atlas::Texel;
use crate::engine::atlas::validate::{self, FIRST_BATCH, RAYS};
use crate::engine::rng::Rng;

/// Texels whose rays go to the device together.
pub const CHUNK_TEXELS: usize = 65_536;

/// Fraction of hits that are back faces of single-sided surfaces, per texel: the CPU's
/// [`validate::backface_fractions`], traced on `ctx`.
pub fn backface_fractions(ctx: &Arc<GpuContext>, rays: &SceneRays, texels: &[Texel]) -> Result<Vec<f32>, GpuError> {
    let scene = rays.scene();
    let tracer = GpuTracer::new(ctx, "texel validation", rays, CHUNK_TEXELS * FIRST_BATCH as usize)?;
    let mut fractions = Vec::with_capacity(texels.len());
    for chunk in texels.chunks(CHUNK_TEXELS) {
        // Each texel's stream, and its (hits, back faces) so far.
        let mut streams: Vec<Rng> = chunk.iter().map(|t| validate::texel_rng(t.pixel)).collect();
        let mut counts = vec![(0u32, 0u32); chunk.len()];
        let everyone: Vec<usize> = (0..chunk.len()).collect();
        let back_face = |tri: u32, d| validate::is_back_face(scene, tri, d);
        trace_batch(
            &tracer,
            chunk,
            &everyone,
            FIRST_BATCH,
            &mut streams,
            &mut counts,
            back_face,
        )?;
        let undecided: Vec<usize> = everyone
            .into_iter()
            .filter(|&i| !validate::decided_after_first_batch(counts[i].0, counts[i].1))
            .collect();
        trace_batch(
            &tracer,
            chunk,
            &undecided,
            RAYS - FIRST_BATCH,
            &mut streams,
            &mut counts,
            back_face,
        )?;
        fractions.extend(
            counts
                .iter()
                .map(|&(hits, back)| if hits == 0 { 0.0 } else { back as f32 / hits as f32 }),
        );
    }
    Ok(fractions)
}

/// Casts the next `per_texel` rays of each texel `who` (indices into `chunk`) and adds
/// their hits and back faces to `counts`; `back_face(triangle, d)` classifies a hit.
fn trace_batch(
    tracer: &GpuTracer,
    chunk: &[Texel],
    who: &[usize],
    per_texel: u32,
    streams: &mut [Rng],
    counts: &mut [(u32, u32)],
    back_face: impl Fn(u32, glam::Vec3) -> bool + Sync,
) -> Result<(), GpuError> {
    if who.is_empty() {
        return Ok(());
    }
    // The rays in texel order; a ray below the geometric plane is skipped as on the CPU.
    let mut per: Vec<(usize, Vec<Ray>, Rng)> = who
        .par_iter()
        .map(|&i| {
            let t = &chunk[i];
            // Each texel's stream is its own: cloned out, advanced (two numbers a ray,
            // skipped or not, as on the CPU), written back below.
            let mut rng = streams[i].clone();
            let rays = (0..per_texel)
                .filter_map(|_| validate::test_direction(t, &mut rng))
                .map(|dir| Ray {
                    origin: t.position,
                    dir,
                    tmax: f32::INFINITY,
                })
                .collect();
            (i, rays, rng)
        })
        .collect();
    let flat: Vec<Ray> = per.iter().flat_map(|(_, r, _)| r.iter().copied()).collect();
    let hits = tracer.trace(&flat)?;
    let mut at = 0;
    for (i, rays, rng) in per.drain(..) {
        streams[i] = rng;
        for r in &rays {
            if let Some(h) = &hits[at] {
                counts[i].0 += 1;
                if back_face(h.triangle, r.dir) {
                    counts[i].1 += 1;
                }
            }
            at += 1;
        }
    }
    Ok(())
}
