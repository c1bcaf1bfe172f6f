//! CPU ray casting against the scene, shared by the reference path tracer and the texel
//! validation: a BVH, closest-hit and occlusion queries, and the sampling helpers every
//! CPU estimator needs.
//!
//! The queries traverse obvhs's wide BVH (8 children a node, built with spatial splits and
//! reinsertion, SAH-collapsed from a binary tree: Ylitie et al. 2017), decoded from its
//! compressed nodes into `f32` child boxes in eight-lane rows, with the leaves' triangles
//! copied out in leaf order (`bvh8`: why, the slab test's rounding, the traversal).
//! Triangles are intersected with a Möller–Trumbore test written here, which also yields
//! the barycentrics the material lookups need. obvhs's binary BVH is built too: it is the
//! tree the GPU flattens (`engine::gpu::bvh`).
//!
//! ## Near the origin
//! Nothing is clipped near a ray's origin: the node test starts at t = 0, and the triangle
//! test counts any t > 0. (obvhs's own wide traversal clips every child box to an
//! absolute t >= 1e-4. That lost 14 % of the hits of rays starting 7e-5 m off a wall
//! toward it in our closed-box test, exactly the hits a path's next bounce off a corner
//! needs, `docs/stability.md`; until 2026-12-07 the tree was scaled by a power of two to
//! make that 1e-4 negligible.) Tested: `hits_next_to_the_origin_are_found_at_every_scale`
//! below (7e-5 and 1e-6 of the size, scales 1e-3 to 1e4, translated by 1e5: every wall
//! found at the brute-force distance), and `tests/gpu_bvh.rs` against the GPU's tree.
//!
//! ## Near the farthest distance
//! The node test's distances are rounded (two roundings each), so a box whose entry lies
//! within that of a query's farthest distance could be culled while it holds a hit before
//! it (an occluder 1e-8 of the scene short of a shadow ray's end, `tests/gpu_bvh.rs`). The
//! node test moves every far distance, the query's farthest one included, out by a factor
//! 1 + 2^-20, more than the rounding of both ends (`bvh8`, "The slab test and its
//! rounding"), while the triangle test keeps the exact bound: a hit is counted only
//! before `tmax`, and in a closest-hit query each candidate is tested against the best
//! value so far, so two candidates compare as their distances do (closer than the f32
//! rounding of a distance they are a tie, which traversal order decides).
//!
//! ## Negative zeros
//! A direction component of -0.0 has the inverse -∞, which would pick the wrong plane of
//! the slab as the near one and miss everything (straight-down sun rays built as the
//! negated direction to the sun are such rays: `tests/vpl.rs` lost the whole bounce with
//! obvhs's test); the node test's direction has +0.0 added first (`bvh8::RayData`).
//!
//! ## Speed
//! The traversal is built twice and picked at run time: for the baseline x86-64 the
//! binary targets, with a scalar node test; and with x86-64-v3's AVX2, FMA, BMI and LZCNT,
//! with a node test that takes the eight children in one AVX2 pass (the same operations
//! in the same order, so the same children are entered). The queries use the second
//! wherever the CPU has those features (checked once per tracer; `LIGHTMAPD_NO_AVX2` set
//! in the environment forces the baseline, for comparisons): Cycles picks its kernels by
//! CPU the same way. Both answer every query as testing every triangle does
//! (`both_builds_of_the_traversal_answer_as_brute_force`; the near-origin and -0.0 tests
//! run both). When a candidate becomes the closest hit, its scene triangle and normal are
//! prefetched: the caller shades from them next, and the traversal usually runs on long
//! enough to hide the miss.
//!
//! `path`'s time a step, release build, this 2-core VM (an `Intel(R) Xeon(R) Processor`),
//! 2026-12-07, 3 alternating runs each (docs/performance.md, docs/peers.md): obvhs's
//! compressed nodes with our AVX2 node test → the `f32` tree, blocks-25k 128² 19.3 →
//! 14.3 ms (1.35×), the Cornell box 64² 9.8 → 7.8 ms (1.25×), the occlusion room 256²
//! 148 → 104 ms (1.42×), with the lightmaps the same but for near-ties (blocks-25k: 3 of
//! 49,152 values; the other two bit for bit). Before (2026-12-06,
//! another VM): binary tree → compressed wide tree 17.4 → 11.6 ms (Cornell box), 17.9 →
//! 17.3 ms (blocks-25k), 183 → 148 ms (the occlusion room at 256²), 1670 → 1444 ms (the
//! 256k-triangle generated level at 1024²); the eight-wide AVX2 node test on the
//! compressed nodes took blocks-25k from 15.85 to 13.6 ms and the occlusion room from
//! 139.7 to 118.9 ms. Building the whole binary for x86-64-v3 instead gained 5–10 % then
//! and would not run on CPUs without AVX2.
//!
//! Alpha: a candidate hit on a MASK or BLEND triangle counts only where
//! [`Scene::stops_ray`] says the surface is there (glTF alpha, issue 19 point 5), in both
//! queries; the leaf records carry the material's flags, so opaque triangles need no
//! material lookup.
//!
//! Limits: single rays, no packets or ray streams; memory for two trees (the binary one
//! for the GPU, 256 bytes a wide node and 44 a leaf triangle for the CPU); rays hit both
//! faces of every triangle (callers decide what a back face means), except that a
//! closest hit prefers a front face over a coincident single-sided back face
//! ([`BACK_FACE_TIE`]).

use std::f32::consts::PI;
use std::time::Duration;

use glam::{Vec3, Vec3A};
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::Ray;

use crate::engine::accumulate::LUMINANCE;
use crate::engine::scene::{Scene, Triangle};

mod bvh8;
use bvh8::{Bvh8, RayData};

/// How much farther a back-face hit on a single-sided triangle counts in a closest-hit
/// query ([`Tracer::trace`]; the GPU's `bvh_closest` uses the same factor): 1e-5
/// relative, far above the few-ulp difference between the distances of two coincident
/// triangles, far below any gap between surfaces a lightmap resolves (0.1 mm at 10 m).
pub const BACK_FACE_TIE: f32 = 1.0 + 1e-5;

/// A BVH over a scene's triangles.
pub struct Tracer {
    /// The binary tree: built here, flattened for the GPU (`engine::gpu::bvh`).
    bvh: Bvh2,
    /// obvhs's wide BVH with `f32` child boxes and the leaves' triangles in leaf order,
    /// which the CPU queries traverse ([`bvh8`]).
    wide: Bvh8,
    /// Each triangle's unit geometric normal (`Triangle::geometric_normal`), which the
    /// estimators need at every hit.
    normals: Vec<Vec3>,
    /// Whether the traversal's AVX2 build runs (`traversal::v3_available`).
    v3: bool,
}

pub struct Hit {
    pub triangle: u32,
    pub t: f32,
    /// Barycentric weights of the three vertices.
    pub bary: Vec3,
}

impl Tracer {
    pub fn new(scene: &Scene) -> Self {
        let tris: Vec<obvhs::triangle::Triangle> = scene
            .triangles
            .iter()
            .map(|t| obvhs::triangle::Triangle {
                v0: t.p[0].into(),
                v1: t.p[1].into(),
                v2: t.p[2].into(),
            })
            .collect();
        let bvh = build_bvh2_from_tris(&tris, obvhs::BvhBuildParams::medium_build(), &mut Duration::default());
        // The wide tree is built on its own (obvhs converts only a binary tree with one
        // triangle a leaf, and the GPU's keeps up to 8), with obvhs's slowest preset
        // (spatial splits, full reinsertion): module doc, "Speed".
        let wide = build_cwbvh_from_tris(
            &tris,
            obvhs::BvhBuildParams::very_slow_build(),
            &mut Duration::default(),
        );
        #[cfg(target_arch = "x86_64")]
        let v3 = traversal::v3_available() && std::env::var_os("LIGHTMAPD_NO_AVX2").is_none();
        #[cfg(not(target_arch = "x86_64"))]
        let v3 = false;
        Tracer {
            bvh,
            wide: Bvh8::new(&wide, scene),
            normals: scene.triangles.iter().map(Triangle::geometric_normal).collect(),
            v3,
        }
    }

    /// Triangle `index`'s unit geometric normal, following its winding.
    #[inline]
    pub fn geometric_normal(&self, index: u32) -> Vec3 {
        self.normals[index as usize]
    }

    /// The binary tree, which the GPU BVH flattens (`engine::gpu::bvh`); the CPU queries
    /// traverse the wide one.
    pub fn bvh(&self) -> &Bvh2 {
        &self.bvh
    }

    /// Closest hit along `origin + t·dir`, t in (0, tmax).
    ///
    /// Ties: a hit on the back of a single-sided triangle counts [`BACK_FACE_TIE`] times
    /// farther than it is, so where a front face and a single-sided back face coincide
    /// (back-to-back single-sided sheets, the usual way to give each side of a wall its
    /// own lightmap) the front face is the hit, not whichever the BVH visits first. A
    /// back face nearer by more than that still wins: it is a real occluder.
    pub fn trace(&self, scene: &Scene, origin: Vec3, dir: Vec3, tmax: f32) -> Option<Hit> {
        if self.wide.is_empty() {
            return None;
        }
        let r = RayData::new(origin, dir);
        let mut found: Option<Hit> = None;
        // Each candidate is tested against the best value so far (a distance, or a back
        // face's distance times the tie factor) and kept when its own value is below it.
        self.closest(&r, tmax, |k, best| {
            let rec = self.wide.record(k);
            let (t, b) = intersect_edges(rec.p0.into(), rec.e1.into(), rec.e2.into(), r.origin, r.dir, 0.0, best)?;
            if rec.flags & bvh8::ALPHA != 0 && !scene.stops_ray(rec.index, b, origin, dir) {
                return None;
            }
            let value = if rec.flags & bvh8::ONE_SIDED != 0 && dir.dot(rec.e1.cross(rec.e2)) > 0.0 {
                t * BACK_FACE_TIE
            } else {
                t
            };
            (value < best).then(|| {
                // The caller reads this triangle and its normal next; the traversal usually
                // goes on for a while, long enough to fetch them (module doc, "Speed").
                prefetch(&scene.triangles[rec.index as usize]);
                prefetch(&self.normals[rec.index as usize]);
                found = Some(Hit {
                    triangle: rec.index,
                    t,
                    bary: b,
                });
                value
            })
        });
        found
    }

    /// True when nothing lies between `origin` and `origin + tmax·dir`.
    pub fn unoccluded(&self, scene: &Scene, origin: Vec3, dir: Vec3, tmax: f32) -> bool {
        if self.wide.is_empty() {
            return true;
        }
        let r = RayData::new(origin, dir);
        self.missed(&r, tmax, |k| {
            let rec = self.wide.record(k);
            intersect_edges(rec.p0.into(), rec.e1.into(), rec.e2.into(), r.origin, r.dir, 0.0, tmax)
                .is_some_and(|(_, b)| rec.flags & bvh8::ALPHA == 0 || scene.stops_ray(rec.index, b, origin, dir))
        })
    }
}

/// Asks the CPU to bring `value`'s cache lines in (a hint: no effect on any result).
#[inline(always)]
fn prefetch<T>(value: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let start = (value as *const T).cast::<i8>();
        // Every line the value touches: its first byte, each 64 bytes on, its last byte.
        // SAFETY: SSE is part of every x86-64 target, and a prefetch of any address is
        // only a hint (it never faults).
        unsafe {
            let mut offset = 0;
            while offset < size_of::<T>() {
                _mm_prefetch::<_MM_HINT_T0>(start.wrapping_add(offset));
                offset += 64;
            }
            _mm_prefetch::<_MM_HINT_T0>(start.wrapping_add(size_of::<T>().saturating_sub(1)));
        }
    }
}

/// The traversal loops ([`bvh8::closest`], [`bvh8::missed`]) built twice: for the
/// baseline x86-64 the binary targets with the scalar node test, and with AVX2, FMA, BMI
/// and LZCNT and the eight-lane AVX2 node test for the CPUs that have them, chosen at run
/// time (`Tracer::v3`; module doc, "Speed").
mod traversal {
    use super::bvh8::{self, Bvh8, RayData, Stack};

    /// Whether the CPU has the features of the second build (x86-64-v3's that it
    /// enables).
    #[cfg(target_arch = "x86_64")]
    pub fn v3_available() -> bool {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("bmi1")
            && std::arch::is_x86_feature_detected!("bmi2")
            && std::arch::is_x86_feature_detected!("lzcnt")
            && std::arch::is_x86_feature_detected!("popcnt")
    }

    /// The baseline build, a function of its own as the AVX2 one is (so the caller stays
    /// small either way).
    #[inline(never)]
    pub fn closest_base<F: FnMut(usize, f32) -> Option<f32>>(
        bvh: &Bvh8,
        r: &RayData,
        tmax: f32,
        stack: &mut Stack<'_>,
        test: F,
    ) -> f32 {
        bvh8::closest(bvh, r, tmax, stack, bvh8::node_test_scalar, test)
    }

    #[inline(never)]
    pub fn missed_base<F: FnMut(usize) -> bool>(
        bvh: &Bvh8,
        r: &RayData,
        tmax: f32,
        stack: &mut Stack<'_>,
        test: F,
    ) -> bool {
        bvh8::missed(bvh, r, tmax, stack, bvh8::node_test_scalar, test)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    pub fn closest_v3<F: FnMut(usize, f32) -> Option<f32>>(
        bvh: &Bvh8,
        r: &RayData,
        tmax: f32,
        stack: &mut Stack<'_>,
        test: F,
    ) -> f32 {
        // SAFETY (inside the closure): this function runs only where AVX2 is present.
        bvh8::closest(bvh, r, tmax, stack, |n, r, t| bvh8::node_test_avx2(n, r, t), test)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    pub fn missed_v3<F: FnMut(usize) -> bool>(
        bvh: &Bvh8,
        r: &RayData,
        tmax: f32,
        stack: &mut Stack<'_>,
        test: F,
    ) -> bool {
        bvh8::missed(bvh, r, tmax, stack, |n, r, t| bvh8::node_test_avx2(n, r, t), test)
    }
}

impl Tracer {
    /// The closest-hit traversal, in the build the CPU runs best.
    #[inline(always)]
    fn closest<F: FnMut(usize, f32) -> Option<f32>>(&self, r: &RayData, tmax: f32, test: F) -> f32 {
        self.wide.with_stack(|stack| {
            #[cfg(target_arch = "x86_64")]
            if self.v3 {
                // SAFETY: `v3` is true only where the CPU has every feature the build enables.
                return unsafe { traversal::closest_v3(&self.wide, r, tmax, stack, test) };
            }
            traversal::closest_base(&self.wide, r, tmax, stack, test)
        })
    }

    /// The occlusion traversal, in the build the CPU runs best.
    #[inline(always)]
    fn missed<F: FnMut(usize) -> bool>(&self, r: &RayData, tmax: f32, test: F) -> bool {
        self.wide.with_stack(|stack| {
            #[cfg(target_arch = "x86_64")]
            if self.v3 {
                // SAFETY: as in `closest`.
                return unsafe { traversal::missed_v3(&self.wide, r, tmax, stack, test) };
            }
            traversal::missed_base(&self.wide, r, tmax, stack, test)
        })
    }
}

/// Möller–Trumbore, both faces; returns t in (tmin, tmax) and barycentrics.
#[inline]
pub fn intersect(tri: &Triangle, ray: &Ray) -> Option<(f32, Vec3)> {
    let p0 = Vec3A::from(tri.p[0]);
    intersect_edges(
        p0,
        Vec3A::from(tri.p[1]) - p0,
        Vec3A::from(tri.p[2]) - p0,
        ray.origin,
        ray.direction,
        ray.tmin,
        ray.tmax,
    )
}

/// [`intersect`] from the first corner and the two edges from it (the queries keep them:
/// [`bvh8::Record`]).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn intersect_edges(
    p0: Vec3A,
    e1: Vec3A,
    e2: Vec3A,
    origin: Vec3A,
    direction: Vec3A,
    tmin: f32,
    tmax: f32,
) -> Option<(f32, Vec3)> {
    let pv = direction.cross(e2);
    let det = e1.dot(pv);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let tv = origin - p0;
    let u = tv.dot(pv) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let qv = tv.cross(e1);
    let v = direction.dot(qv) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(qv) * inv;
    (t > tmin && t < tmax).then_some((t, Vec3::new(1.0 - u - v, u, v)))
}

/// An orthonormal basis with `n` as its third axis (Duff et al. 2017).
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        Vec3::new(b, sign + n.y * n.y * a, -n.y),
    )
}

/// Cosine-weighted direction about `n`; pdf = cos θ / π.
pub fn cosine_sample(n: Vec3, u1: f32, u2: f32) -> Vec3 {
    let r = u1.sqrt();
    let phi = 2.0 * PI * u2;
    let (t, b) = basis(n);
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u1).max(0.0).sqrt()).normalize()
}

/// Uniform direction in the cone of half-angle acos(`cos_max`) about `axis`; pdf = 1/Ω.
pub fn cone_sample(axis: Vec3, cos_max: f32, u1: f32, u2: f32) -> Vec3 {
    let cos_t = 1.0 - u1 * (1.0 - cos_max);
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * PI * u2;
    let (t, b) = basis(axis);
    (t * (sin_t * phi.cos()) + b * (sin_t * phi.sin()) + axis * cos_t).normalize()
}

/// Moves barycentrics a relative 1e-5 toward the centroid. A hit point on or within a
/// rounding error of a triangle edge, offset along its normal, can land on the far side
/// of the adjacent face's plane at a closed corner; the next ray then sees that face's
/// back (black) or escapes. Measured in a closed box of albedo 0.999 under a sky (4000
/// bounces a path): without the inset, sky light worth 4e-5 of a unit radiance leaked
/// in through the corners; with it, none in 1e6 paths.
pub fn inset(b: Vec3) -> Vec3 {
    const DELTA: f32 = 1e-5;
    b * (1.0 - DELTA) + Vec3::splat(DELTA / 3.0)
}

/// The light-sampling tables: emissive triangles chosen in proportion to area × emitted
/// luminance. Shared by the CPU `path` and the GPU scene tables (`gpu::scene_lights`), so
/// every estimator picks emitters with the same probabilities.
pub struct EmitterTable {
    pub(crate) emitters: Vec<u32>,
    pub(crate) emitter_cdf: Vec<f32>,
    /// Selection probability of each scene triangle as an emitter (0 for non-emitters).
    pub(crate) emitter_pick: Vec<f32>,
    /// `emitter_pick` over the triangle's area: the density over the surface with which
    /// next-event estimation picks a point of it (the value the estimators computed at
    /// every vertex, kept).
    pub(crate) pick_density: Vec<f32>,
}

impl EmitterTable {
    pub fn new(scene: &Scene) -> Self {
        Self::of(scene, |_| true)
    }

    /// The table over the emissive triangles `keep` accepts (by scene triangle index);
    /// the others are never picked.
    pub fn of(scene: &Scene, keep: impl Fn(usize) -> bool) -> Self {
        let mut emitters = Vec::new();
        let mut weights = Vec::new();
        for (i, t) in scene.triangles.iter().enumerate() {
            if !keep(i) {
                continue;
            }
            let e = scene.materials[t.material as usize].emissive;
            let w = t.area() * e.dot(LUMINANCE).max(e.max_element() * 1e-3);
            if w > 0.0 && w.is_finite() {
                emitters.push(i as u32);
                weights.push(w as f64);
            }
        }
        let sum: f64 = weights.iter().sum();
        let mut emitter_pick = vec![0.0f32; scene.triangles.len()];
        let mut acc = 0.0f64;
        let mut emitter_cdf = Vec::with_capacity(weights.len());
        for (k, w) in weights.iter().enumerate() {
            acc += w / sum;
            emitter_cdf.push(acc as f32);
            emitter_pick[emitters[k] as usize] = (w / sum) as f32;
        }
        if let Some(last) = emitter_cdf.last_mut() {
            *last = 1.0;
        }
        let pick_density = emitter_pick
            .iter()
            .zip(&scene.triangles)
            .map(|(&pick, t)| if pick > 0.0 { pick / t.area() } else { 0.0 })
            .collect();
        EmitterTable {
            emitters,
            emitter_cdf,
            emitter_pick,
            pick_density,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;

    #[test]
    fn basis_is_orthonormal() {
        for n in [
            Vec3::X,
            Vec3::NEG_Z,
            Vec3::new(0.3, -0.5, 0.81).normalize(),
            Vec3::new(0.0, 0.0, -1.0),
        ] {
            let (t, b) = basis(n);
            assert!(t.dot(b).abs() < 1e-6 && t.dot(n).abs() < 1e-6 && b.dot(n).abs() < 1e-6);
            assert!((t.length() - 1.0).abs() < 1e-6 && (b.length() - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn cosine_samples_have_mean_cos_two_thirds() {
        // E[cos θ] under pdf cos θ/π is 2/3; 20000 samples give a standard error of 0.0017.
        let n = Vec3::new(0.2, 0.9, -0.1).normalize();
        let mut rng = Rng::new(3, 0, 0, 0);
        let m: f32 = (0..20000)
            .map(|_| cosine_sample(n, rng.next_f32(), rng.next_f32()).dot(n))
            .sum::<f32>()
            / 20000.0;
        assert!((m - 2.0 / 3.0).abs() < 0.01, "{m}");
    }

    /// Rays from 7e-5 and 1e-6 of the scene's size off a wall of a closed box, toward it
    /// (a path's next bounce after a corner), at 1e-3, 1 and 1e4 scale and translated by
    /// 1e5: the tracer finds the wall at the distance every triangle tested in turn gives,
    /// for every ray. obvhs's wide BVH unscaled lost 14 % of the 7e-5 rays at scale 1
    /// (module doc, "Near the origin").
    #[test]
    fn hits_next_to_the_origin_are_found_at_every_scale() {
        use crate::engine::scene::import_slice;
        use crate::engine::scene::library::closed_box;
        let glb = closed_box(0.5).to_glb();
        for (scale, offset) in [(1.0f32, 0.0f32), (1e-3, 0.0), (1e4, 0.0), (1.0, 1e5)] {
            let (mut scene, _) = import_slice(&glb, None).unwrap();
            for t in &mut scene.triangles {
                for p in &mut t.p {
                    *p = *p * scale + Vec3::splat(offset);
                }
            }
            let mut tracer = Tracer::new(&scene);
            let size = 2.0 * scale;
            for v3 in builds() {
                tracer.v3 = v3;
                let mut rng = Rng::new(5, 0, 0, 0);
                let (mut misses, mut wrong) = (0, 0);
                let rays = 20000;
                for i in 0..rays {
                    let k = (rng.next_f32() * scene.triangles.len() as f32) as usize % scene.triangles.len();
                    let tri = &scene.triangles[k];
                    let (a, b) = (0.05 + 0.45 * rng.next_f32(), 0.05 + 0.45 * rng.next_f32());
                    let p = tri.point(Vec3::new(1.0 - a - b, a, b));
                    let n = tri.geometric_normal();
                    // At least 4 ulps of the coordinates: closer, the origin rounds onto the
                    // wall (the 1e5-translated box resolves 1/128).
                    let ulps = 4.0 * p.abs().max_element() * f32::EPSILON;
                    let off = (if i % 2 == 0 { 7e-5 } else { 1e-6 } * size).max(ulps);
                    let origin = p + n * off;
                    let (u, v) = basis(n);
                    let (x, y) = (rng.next_f32() * 2.0 - 1.0, rng.next_f32() * 2.0 - 1.0);
                    let dir = (-n + (u * x + v * y) * 0.9).normalize();
                    let truth = scene
                        .triangles
                        .iter()
                        .filter_map(|t| intersect(t, &Ray::new(origin.into(), dir.into(), 0.0, f32::INFINITY)))
                        .map(|(t, _)| t)
                        .fold(f32::INFINITY, f32::min);
                    match tracer.trace(&scene, origin, dir, f32::INFINITY) {
                        None => misses += 1,
                        Some(hit) if hit.t != truth => wrong += 1,
                        Some(_) => {}
                    }
                }
                assert_eq!(
                    (misses, wrong),
                    (0, 0),
                    "scale {scale}, offset {offset}, AVX2 build {v3}: misses and wrong distances of {rays} rays"
                );
            }
        }
    }

    /// The traversal builds this CPU runs: the baseline, and the AVX2 one where it has
    /// AVX2 (said on stderr where not).
    fn builds() -> Vec<bool> {
        #[cfg(target_arch = "x86_64")]
        if traversal::v3_available() {
            return vec![false, true];
        }
        eprintln!("this CPU has no AVX2: only the baseline traversal is checked");
        vec![false]
    }

    /// Every triangle tested in turn: the nearest front-or-back hit before `tmax`, with the
    /// closest-hit query's tie rule for single-sided back faces, as (value, triangle,
    /// distance).
    fn brute_force(scene: &Scene, o: Vec3, d: Vec3, tmax: f32) -> Option<(f32, u32, f32)> {
        let ray = Ray::new(o.into(), d.into(), 0.0, tmax);
        let mut best: Option<(f32, u32, f32)> = None;
        for (k, tri) in scene.triangles.iter().enumerate() {
            if let Some((t, _)) = intersect(tri, &ray) {
                let back = !scene.material(tri).double_sided && d.dot(tri.cross()) > 0.0;
                let value = if back { t * BACK_FACE_TIE } else { t };
                if best.is_none_or(|(v, _, _)| value < v) {
                    best = Some((value, k as u32, t));
                }
            }
        }
        best
    }

    /// The traversal's two builds (baseline and AVX2, `traversal`) answer every query as
    /// testing every triangle in turn does, and as each other do, bit for bit: the same
    /// triangle, the same distance, the same occlusion. Rays from anywhere in the sphere
    /// scene's box, in every direction, some with a finite farthest distance. On a CPU
    /// without AVX2 only the baseline build runs (and is checked); it says so.
    #[test]
    fn both_builds_of_the_traversal_answer_as_brute_force() {
        use crate::engine::scene::import_slice;
        use crate::engine::scene::library::sphere_over_plane;
        let (scene, _) = import_slice(&sphere_over_plane().to_glb(), None).unwrap();
        let mut tracer = Tracer::new(&scene);
        let builds = builds();
        let (lo, hi) = scene
            .triangles
            .iter()
            .flat_map(|t| t.p)
            .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), p| {
                (lo.min(p), hi.max(p))
            });
        let mut rng = Rng::new(11, 0, 0, 0);
        let (mut hits, mut occluded) = (0, 0);
        for i in 0..3000 {
            let o = lo + (hi - lo) * Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            let d = (Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - 1.0).normalize_or(Vec3::Y);
            let tmax = if i % 3 == 0 {
                rng.next_f32() * (hi - lo).length()
            } else {
                f32::INFINITY
            };
            let best = brute_force(&scene, o, d, tmax);
            for &v3 in &builds {
                tracer.v3 = v3;
                let hit = tracer.trace(&scene, o, d, tmax);
                assert_eq!(
                    hit.as_ref().map(|h| (h.triangle, h.t.to_bits())),
                    best.map(|(_, k, t)| (k, t.to_bits())),
                    "ray {i}, AVX2 build {v3}"
                );
                assert_eq!(
                    tracer.unoccluded(&scene, o, d, tmax),
                    best.is_none(),
                    "ray {i}, AVX2 build {v3}"
                );
            }
            hits += usize::from(best.is_some());
            occluded += usize::from(best.is_some() && tmax.is_finite());
        }
        // Both kinds of answer were asked for, many times.
        assert!(
            hits > 500 && hits < 2900 && occluded > 100,
            "{hits} hits, {occluded} finite"
        );
    }

    /// On the 25,000-triangle blocks scene (its wide tree has spatial-split leaves and
    /// several levels), in both builds and with the stack on the thread's stack and on the
    /// heap: rays from just off the surfaces in cosine directions (a path's bounces), and
    /// axis-parallel rays in the planes of the blocks' tops, where a node's box face holds
    /// the origin and the slab test meets 0 × ∞ (`bvh8`, "The slab test and its rounding"),
    /// give the closest hit and the occlusion every triangle tested in turn gives.
    #[test]
    fn the_tree_answers_as_brute_force_on_a_level() {
        use crate::engine::scene::import_slice;
        use crate::engine::scene::library::procedural_blocks;
        let (scene, _) = import_slice(&procedural_blocks().to_glb(), None).unwrap();
        let mut tracer = Tracer::new(&scene);
        let mut rng = Rng::new(17, 0, 0, 0);
        let tops: Vec<f32> = scene
            .triangles
            .iter()
            .filter(|t| t.geometric_normal().y > 0.99 && t.p[0].y > 0.1)
            .map(|t| t.p[0].y)
            .collect();
        let mut rays = Vec::new();
        for i in 0..600 {
            let k = (rng.next_f32() * scene.triangles.len() as f32) as usize % scene.triangles.len();
            let tri = &scene.triangles[k];
            let (origin, dir) = if i % 3 == 0 {
                let y = tops[(rng.next_f32() * tops.len() as f32) as usize % tops.len()];
                let origin = Vec3::new(rng.next_f32() * 20.0 - 10.0, y, rng.next_f32() * 20.0 - 10.0);
                let axis = [Vec3::X, Vec3::NEG_X, Vec3::Z, Vec3::NEG_Z][i % 4];
                (origin, axis)
            } else {
                let (a, b) = (rng.next_f32() * 0.5, rng.next_f32() * 0.5);
                let n = tri.geometric_normal();
                let origin = tri.point(Vec3::new(1.0 - a - b, a, b)) + n * 1e-4;
                (origin, cosine_sample(n, rng.next_f32(), rng.next_f32()))
            };
            let tmax = if i % 4 == 1 {
                rng.next_f32() * 5.0
            } else {
                f32::INFINITY
            };
            rays.push((origin, dir, tmax));
        }
        let mut hits = [0; 2];
        let own = tracer.wide.stack_len;
        for (heap, v3) in [false, true]
            .into_iter()
            .flat_map(|h| builds().into_iter().map(move |b| (h, b)))
        {
            tracer.v3 = v3;
            // Past the inline stack's size, `with_stack` takes a heap stack of that size.
            tracer.wide.stack_len = if heap { own.max(bvh8::INLINE_STACK + 1) } else { own };
            hits = [0; 2];
            for (i, &(o, d, tmax)) in rays.iter().enumerate() {
                let best = brute_force(&scene, o, d, tmax);
                let hit = tracer.trace(&scene, o, d, tmax);
                // The distance exactly; the triangle too, except where two are at the same
                // distance (a shared edge), where the tree may name the other one.
                assert_eq!(
                    hit.as_ref().map(|h| h.t.to_bits()),
                    best.map(|(_, _, t)| t.to_bits()),
                    "ray {i} ({o}, {d}, {tmax}), AVX2 build {v3}, heap stack {heap}"
                );
                assert_eq!(
                    tracer.unoccluded(&scene, o, d, tmax),
                    best.is_none(),
                    "ray {i}, AVX2 build {v3}, heap stack {heap}"
                );
                hits[usize::from(i % 3 == 0)] += usize::from(best.is_some());
            }
        }
        // Both answers were asked for, many times, of both kinds of ray.
        assert!(
            hits[0] > 100 && hits[0] < 390 && hits[1] > 20 && hits[1] < 190,
            "{hits:?} of 400 bounce rays and 200 axis-parallel rays hit"
        );
    }

    /// Axis-aligned rays whose other components are -0.0 (a straight-down sun ray built
    /// by negating the direction to the sun) hit what lies on them, in both builds.
    #[test]
    fn negative_zero_directions_hit() {
        use crate::engine::scene::import_slice;
        use crate::engine::scene::library::closed_box;
        let (scene, _) = import_slice(&closed_box(0.5).to_glb(), None).unwrap();
        let mut tracer = Tracer::new(&scene);
        for (v3, axis) in builds()
            .into_iter()
            .flat_map(|b| [(b, Vec3::X), (b, Vec3::Y), (b, Vec3::Z)])
        {
            tracer.v3 = v3;
            for sign in [1.0f32, -1.0] {
                let dir = Vec3::from_array((axis * sign).to_array().map(|c| if c == 0.0 { -0.0 } else { c }));
                let origin = Vec3::splat(0.1);
                let hit = tracer.trace(&scene, origin, dir, f32::INFINITY);
                assert!(
                    hit.is_some_and(|h| (h.t - (1.0 - 0.1 * sign)).abs() < 1e-5),
                    "{dir:?} {v3}"
                );
                assert!(!tracer.unoccluded(&scene, origin, dir, 10.0), "{dir:?} {v3}");
            }
        }
    }

    #[test]
    fn cone_samples_stay_in_cone() {
        let axis = Vec3::new(0.0, 1.0, 1.0).normalize();
        let cos_max = 0.99;
        let mut rng = Rng::new(4, 0, 0, 0);
        for _ in 0..1000 {
            let d = cone_sample(axis, cos_max, rng.next_f32(), rng.next_f32());
            assert!(d.dot(axis) >= cos_max - 1e-5);
        }
    }
}
