//! CPU ray casting against the scene, shared by the reference path tracer and the texel
//! validation: a BVH, closest-hit and occlusion queries, and the sampling helpers every
//! CPU estimator needs.
//!
//! The queries traverse obvhs's compressed wide BVH (8 children a node, child boxes
//! quantised to 8 bits, Ylitie et al. 2017); triangles are intersected with a
//! Möller–Trumbore test written here, which also yields the barycentrics the material
//! lookups need. obvhs's binary BVH is built too: it is the tree the GPU flattens
//! (`engine::gpu::bvh`), and what the queries traversed before.
//!
//! ## Near the origin
//! obvhs's wide traversal clips every child box to t >= 1e-4 (`EPSILON` in its
//! `cwbvh::node`, an absolute distance): a box the ray leaves before 1e-4 is skipped.
//! That lost 14 % of the hits of rays starting 7e-5 m off a wall toward it in our
//! closed-box test, exactly the hits a path's next bounce off a corner needs
//! (`docs/stability.md`), and was why this module used the binary tree. The wide tree is
//! now built over the scene as it is and then scaled by a power of two 2^k that puts the
//! scene's extent near 2^20: each node's corner times 2^k and its exponent byte plus k,
//! and each query's origin and farthest distance times 2^k. Scaling by a power of two is
//! exact in f32, so the boxes are the same boxes and a distance divides back without
//! rounding; the 1e-4 now stands for about 1e-10 of the scene's size, far below the f32
//! spacing of its coordinates (6e-8 of it), so no hit a path can ask for is clipped.
//! The triangle test runs in the scene's own coordinates, so hits and their distances
//! are bit for bit the binary tree's, except which of two triangles at the same distance
//! (below) a query returns (a shared edge; traversal order decides). Tested:
//! `hits_next_to_the_origin_are_found_at_every_scale` below (7e-5 and 1e-6 of the size,
//! scales 1e-3 to 1e4, translated by 1e5: every wall found at the brute-force distance;
//! with k = 0 it fails), and `tests/gpu_bvh.rs` against the GPU's tree.
//!
//! ## Near the farthest distance
//! The wide node test is not exact: it measures a child box's slabs from the node's
//! corner, (p - o + q e) / d, so its rounding is a few ulps of the corner's distance
//! (up to 1e-7 of the scene's size at the root, more for rays that graze an axis), not of
//! the box's. A box whose entry falls within that of a query's farthest distance could be
//! culled while it holds a hit before it: an occluder 1e-8 of the scene short of a shadow
//! ray's end was missed on 55 of 4000 rays (1e-6 of the size off a wall, tmax 1 % past
//! the hit; `tests/gpu_bvh.rs`). So the traversal culls against the farthest distance plus
//! a slack of 2^-20 of the scene's extent (about 1e-6), while the triangle test keeps the
//! exact bound: a hit is counted only before `tmax`, and in a closest-hit query each
//! candidate's value reaches the traversal moved out by the same slack, so the boxes
//! beyond the best hit are culled with the same margin and two candidates compare as
//! their distances do (to the f32 rounding of the moved value, 6e-8 of the scene's size:
//! closer than that they are a tie, which traversal order decides).
//!
//! ## Negative zeros
//! obvhs's wide node test takes a direction component's sign from `d < 0` and its inverse
//! from `signum` (-1 for -0.0), so a -0.0 component swapped the slab bounds and the ray
//! hit nothing (straight-down sun rays built as the negated direction to the sun are such
//! rays: `tests/vpl.rs` lost the whole bounce); the traversal's direction has +0.0 added
//! (`Tracer::wide_ray`).
//!
//! ## Speed
//! `path`'s time a step, release build, this 2-core VM (2026-12-06, docs/peers.md), binary
//! tree → wide tree (obvhs's `very_slow_build`: spatial splits, full reinsertion): Cornell
//! box 64² 17.4 → 11.6 ms (1.50×), blocks-25k 128² 17.9 → 17.3 ms (1.03×), the occlusion
//! room 256² 183 → 148 ms (1.24×), the 256k-triangle generated level at 1024² 1670 →
//! 1444 ms (1.16×). The medium preset the binary tree uses gave 12.0, 18.2, 167 and 1599
//! ms. The second build costs less than the steps save on the 256k-triangle level's first
//! four steps (whole process 11.2 → 10.5 s).
//!
//! The traversal loop is obvhs's own (its `traverse!` macro, expanded here in
//! `traversal`), built twice: for the baseline x86-64 the binary targets, with obvhs's
//! node test (SSE, four children a pass); and with x86-64-v3's AVX2, FMA, BMI and LZCNT,
//! with a node test of ours that takes all eight children in one AVX2 pass (the same
//! arithmetic in the same order, so the same boxes are entered). The queries use the
//! second wherever the CPU has those features (checked once per tracer;
//! `LIGHTMAPD_NO_AVX2` set in the environment forces the baseline, for comparisons):
//! Cycles picks its kernels by CPU the same way. Both answer every query bit for bit as
//! testing every triangle does (`both_builds_of_the_traversal_answer_as_brute_force`;
//! the near-origin and -0.0 tests run both). `path` a step, 3 runs each, release, this
//! VM (2026-12-06), baseline → AVX2 loop with obvhs's node test → with the eight-wide
//! one: blocks-25k 15.85 → 14.8 → 13.6 ms, the Cornell box 10.2 → 10.0 → 10.0 ms, the
//! occlusion room 139.7 → 134.1 → 118.9 ms; the lightmaps are the same to the bit.
//! Building the whole binary for x86-64-v3 instead gained 5–10 % and would not run on
//! CPUs without AVX2.
//!
//! Tried and not kept (2026-12-07, this VM, release, 3 alternating runs each): the
//! triangles copied for the queries into the wide tree's leaf order, 48 bytes each
//! (first corner, two edges, the index and the material's alpha and sidedness flags),
//! instead of reading the 128-byte scene triangles and their materials. `path`'s time
//! moved from 0.89 to 0.88 s (blocks-25k 128², 64 steps), 2.12 to 2.06 s (the Cornell
//! box 64², 256 steps) and 1.58 to 1.55 s (the occlusion room 256², 16 steps), within
//! the runs' spread: the first touch of a hit triangle's data still misses the cache, in
//! the shading after the query instead of in its test (`perf` showed the miss move), and
//! the node tests are most of the traversal.
//!
//! Alpha: a candidate hit on a MASK or BLEND triangle counts only where
//! [`Scene::stops_ray`] says the surface is there (glTF alpha, issue 19 point 5), in both
//! queries; opaque triangles pay one material lookup per candidate hit.
//!
//! Limits: single rays, no packets or ray streams (a wide node's eight boxes are tested
//! in one AVX2 pass, or four at a time in SSE without AVX2); memory for two trees; rays
//! hit both faces of every triangle (callers decide what a back face means), except that
//! a closest hit prefers a front face over a coincident single-sided back face
//! ([`BACK_FACE_TIE`]).

use std::f32::consts::PI;
use std::time::Duration;

use glam::{Vec3, Vec3A};
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray, RayHit};

use crate::engine::accumulate::LUMINANCE;
use crate::engine::scene::{AlphaMode, Scene, Triangle};

/// How much farther a back-face hit on a single-sided triangle counts in a closest-hit
/// query ([`Tracer::trace`]; the GPU's `bvh_closest` uses the same factor): 1e-5
/// relative, far above the few-ulp difference between the distances of two coincident
/// triangles, far below any gap between surfaces a lightmap resolves (0.1 mm at 10 m).
pub const BACK_FACE_TIE: f32 = 1.0 + 1e-5;

/// A BVH over a scene's triangles.
pub struct Tracer {
    /// The binary tree: built here, flattened for the GPU (`engine::gpu::bvh`).
    bvh: Bvh2,
    /// The same tree as obvhs's compressed wide BVH, which the CPU queries traverse, its
    /// coordinates multiplied by `scale` (module doc, "Near the origin").
    wide: CwBvh,
    /// A power of two, so that scaling a coordinate or a distance by it is exact.
    scale: f32,
    /// How far past a query's farthest distance the wide traversal still enters boxes, in
    /// scaled units (module doc, "Near the farthest distance").
    slack: f32,
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
        let (wide, scale) = scaled_wide(build_cwbvh_from_tris(
            &tris,
            obvhs::BvhBuildParams::very_slow_build(),
            &mut Duration::default(),
        ));
        let slack = (wide.total_aabb.max - wide.total_aabb.min).max_element() * SLACK;
        #[cfg(target_arch = "x86_64")]
        let v3 = traversal::v3_available() && std::env::var_os("LIGHTMAPD_NO_AVX2").is_none();
        #[cfg(not(target_arch = "x86_64"))]
        let v3 = false;
        Tracer {
            bvh,
            wide,
            scale,
            slack,
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

    /// The wide traversal's ray for a query: origin and farthest distance scaled, the
    /// farthest distance moved out by the slack, and the direction's -0.0s made +0.0
    /// (module doc, "Near the origin", "Near the farthest distance", "Negative zeros").
    fn wide_ray(&self, origin: Vec3, dir: Vec3, tmax: f32) -> Ray {
        // Adding +0.0 turns -0.0 into +0.0 and leaves every other value as it is.
        let dir = Vec3A::from(dir) + Vec3A::ZERO;
        Ray::new(
            Vec3A::from(origin) * self.scale,
            dir,
            0.0,
            tmax * self.scale + self.slack,
        )
    }

    /// Closest hit along `origin + t·dir`, t in (0, tmax).
    ///
    /// Ties: a hit on the back of a single-sided triangle counts [`BACK_FACE_TIE`] times
    /// farther than it is, so where a front face and a single-sided back face coincide
    /// (back-to-back single-sided sheets, the usual way to give each side of a wall its
    /// own lightmap) the front face is the hit, not whichever the BVH visits first. A
    /// back face nearer by more than that still wins: it is a real occluder.
    pub fn trace(&self, scene: &Scene, origin: Vec3, dir: Vec3, tmax: f32) -> Option<Hit> {
        if self.wide.nodes.is_empty() {
            return None;
        }
        let (s, slack) = (self.scale, self.slack);
        // The test runs in the scene's coordinates against the best value so far (`local`'s
        // tmax: a distance, or a back face's distance times the tie factor); the traversal
        // sees each value scaled and moved out by the slack, so that it culls boxes
        // against the best value plus the slack, and compares two values as the test does.
        let mut local = Ray::new(origin.into(), dir.into(), 0.0, tmax);
        let ray = self.wide_ray(origin, dir, tmax);
        let mut hit = RayHit::none();
        let found = self.closest(ray, &mut hit, |r, id| {
            let index = self.wide.primitive_indices[id];
            let tri = &scene.triangles[index as usize];
            let Some((t, b)) = intersect(tri, &local) else {
                return f32::INFINITY;
            };
            let m = scene.material(tri);
            let value = if m.alpha_mode != AlphaMode::Opaque && !scene.stops_ray(index, b, origin, dir) {
                return f32::INFINITY;
            } else if !m.double_sided && dir.dot(tri.cross()) > 0.0 {
                t * BACK_FACE_TIE
            } else {
                t
            };
            let seen = value * s + slack;
            // obvhs keeps the candidate exactly when this holds (`t < tmax` in its
            // traversal); mirror it so `local` holds the value it keeps.
            if seen < r.tmax {
                local.tmax = value;
            }
            seen
        });
        if !found {
            return None;
        }
        let triangle = self.wide.primitive_indices[hit.primitive_id as usize];
        let tri = &scene.triangles[triangle as usize];
        let (t, bary) = intersect(tri, &Ray::new(origin.into(), dir.into(), 0.0, f32::INFINITY))?;
        Some(Hit { triangle, t, bary })
    }

    /// True when nothing lies between `origin` and `origin + tmax·dir`.
    pub fn unoccluded(&self, scene: &Scene, origin: Vec3, dir: Vec3, tmax: f32) -> bool {
        if self.wide.nodes.is_empty() {
            return true;
        }
        let s = self.scale;
        // Any hit the exact test finds before `tmax` is below the traversal's tmax, which
        // the slack moves out (module doc, "Near the farthest distance").
        let local = Ray::new(origin.into(), dir.into(), 0.0, tmax);
        let ray = self.wide_ray(origin, dir, tmax);
        self.missed(ray, |_, id| {
            let index = self.wide.primitive_indices[id];
            let tri = &scene.triangles[index as usize];
            intersect(tri, &local).map_or(f32::INFINITY, |(t, b)| {
                if scene.material(tri).alpha_mode != AlphaMode::Opaque && !scene.stops_ray(index, b, origin, dir) {
                    f32::INFINITY
                } else {
                    s * t
                }
            })
        })
    }
}

/// The traversal loops, written once ([`obvhs::traverse!`], obvhs's own loop, with the
/// node test as a parameter) and built twice: for the baseline x86-64 the binary targets
/// with obvhs's node test, and with AVX2, FMA, BMI and LZCNT and an eight-wide node test
/// for the CPUs that have them, chosen at run time (`Tracer::v3`; module doc, "Speed").
mod traversal {
    // `traverse!` names glam's `UVec2` unqualified.
    use glam::{UVec2, Vec3A};
    use obvhs::cwbvh::CwBvh;
    use obvhs::cwbvh::node::{CwBvhNode, extract_byte64};
    use obvhs::ray::{Ray, RayHit};

    /// Closest hit: obvhs's `CwBvh::ray_traverse`, as its source writes it, with the node
    /// test `hits` (which children the ray enters, as obvhs's `CwBvhNode::intersect_ray`).
    #[inline(always)]
    pub fn closest<N, F>(wide: &CwBvh, ray: Ray, hit: &mut RayHit, hits: N, mut test: F) -> bool
    where
        N: Fn(&CwBvhNode, &Ray, u32) -> u32,
        F: FnMut(&Ray, usize) -> f32,
    {
        let mut traverse_ray = ray;
        let mut state = wide.new_traversal(ray.direction);
        let mut node;
        obvhs::traverse!(wide, node, state, hits(node, &traverse_ray, state.oct_inv4), {
            let t = test(&traverse_ray, state.primitive_id as usize);
            if t < traverse_ray.tmax {
                hit.primitive_id = state.primitive_id;
                hit.t = t;
                traverse_ray.tmax = t;
            }
        });
        hit.t < ray.tmax
    }

    /// True when no primitive's test comes out below the ray's tmax: obvhs's
    /// `CwBvh::ray_traverse_miss`.
    #[inline(always)]
    pub fn missed<N, F>(wide: &CwBvh, ray: Ray, hits: N, mut test: F) -> bool
    where
        N: Fn(&CwBvhNode, &Ray, u32) -> u32,
        F: FnMut(&Ray, usize) -> f32,
    {
        let mut state = wide.new_traversal(ray.direction);
        let mut node;
        let mut miss = true;
        'outer: {
            obvhs::traverse!(wide, node, state, hits(node, &ray, state.oct_inv4), {
                if test(&ray, state.primitive_id as usize) < ray.tmax {
                    miss = false;
                    break 'outer;
                }
            });
        }
        miss
    }

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
    /// small either way), with obvhs's node test (SSE, four children at a time).
    #[inline(never)]
    pub fn closest_base<F: FnMut(&Ray, usize) -> f32>(wide: &CwBvh, ray: Ray, hit: &mut RayHit, test: F) -> bool {
        closest(wide, ray, hit, |n, r, o| n.intersect_ray(r, o), test)
    }

    #[inline(never)]
    pub fn missed_base<F: FnMut(&Ray, usize) -> f32>(wide: &CwBvh, ray: Ray, test: F) -> bool {
        missed(wide, ray, |n, r, o| n.intersect_ray(r, o), test)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    pub fn closest_v3<F: FnMut(&Ray, usize) -> f32>(wide: &CwBvh, ray: Ray, hit: &mut RayHit, test: F) -> bool {
        closest(wide, ray, hit, |n, r, o| node_hits_avx2(n, r, o), test)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    pub fn missed_v3<F: FnMut(&Ray, usize) -> f32>(wide: &CwBvh, ray: Ray, test: F) -> bool {
        missed(wide, ray, |n, r, o| node_hits_avx2(n, r, o), test)
    }

    /// obvhs's `EPSILON`, the nearest entry distance its node test accepts (module doc,
    /// "Near the origin"); crate-private there, so repeated here to give the same answers.
    #[cfg(target_arch = "x86_64")]
    const NODE_EPSILON: f32 = 0.0001;

    /// obvhs's `CwBvhNode::intersect_ray_simd` with all eight children in one AVX2 lane
    /// set instead of two SSE passes: the quantised bounds widened from bytes by
    /// `vpmovzxbd` and converted exactly, then the same products, sums, min/max operand
    /// order (so NaNs, from 0 × inf on an axis-parallel ray, fall as obvhs's do), ordered
    /// comparison and hit-mask assembly. No FMA: a fused product would round differently
    /// from obvhs's, and the two builds answer alike.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    #[inline]
    fn node_hits_avx2(node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32 {
        use std::arch::x86_64::*;
        let adj_inv = node.compute_extent() * ray.inv_direction;
        let adj_orig = (Vec3A::from(node.p) - ray.origin) * ray.inv_direction;
        // SAFETY: each array is 8 bytes, the width `_mm_loadl_epi64` reads (unaligned).
        let widen =
            |b: &[u8; 8]| _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(unsafe { _mm_loadl_epi64(b.as_ptr().cast()) }));
        let slab = |lo: &[u8; 8], hi: &[u8; 8], negative: bool, inv: f32, orig: f32| {
            let (near, far) = if negative {
                (widen(hi), widen(lo))
            } else {
                (widen(lo), widen(hi))
            };
            let (inv, orig) = (_mm256_set1_ps(inv), _mm256_set1_ps(orig));
            (
                _mm256_add_ps(_mm256_mul_ps(near, inv), orig),
                _mm256_add_ps(_mm256_mul_ps(far, inv), orig),
            )
        };
        let d = ray.direction;
        let (tmin_x, tmax_x) = slab(&node.child_min_x, &node.child_max_x, d.x < 0.0, adj_inv.x, adj_orig.x);
        let (tmin_y, tmax_y) = slab(&node.child_min_y, &node.child_max_y, d.y < 0.0, adj_inv.y, adj_orig.y);
        let (tmin_z, tmax_z) = slab(&node.child_min_z, &node.child_max_z, d.z < 0.0, adj_inv.z, adj_orig.z);
        let tmin = _mm256_max_ps(tmin_x, _mm256_max_ps(tmin_y, tmin_z));
        let tmax = _mm256_min_ps(tmax_x, _mm256_min_ps(tmax_y, tmax_z));
        let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(NODE_EPSILON));
        let tmax = _mm256_min_ps(tmax, _mm256_set1_ps(ray.tmax));
        let mut entered = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OS>(tmin, tmax)) as u32;
        let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
        let mut hit_mask = 0u32;
        while entered != 0 {
            let j = entered.trailing_zeros() as usize;
            entered &= entered - 1;
            hit_mask |= extract_byte64(child_bits8, j) << extract_byte64(bit_index8, j);
        }
        hit_mask
    }
}

impl Tracer {
    /// The wide traversal's closest hit, in the build the CPU runs best.
    #[inline(always)]
    fn closest<F: FnMut(&Ray, usize) -> f32>(&self, ray: Ray, hit: &mut RayHit, test: F) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self.v3 {
            // SAFETY: `v3` is true only where the CPU has every feature the build enables.
            return unsafe { traversal::closest_v3(&self.wide, ray, hit, test) };
        }
        traversal::closest_base(&self.wide, ray, hit, test)
    }

    /// The wide traversal's occlusion test, in the build the CPU runs best.
    #[inline(always)]
    fn missed<F: FnMut(&Ray, usize) -> f32>(&self, ray: Ray, test: F) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self.v3 {
            // SAFETY: as in `closest`.
            return unsafe { traversal::missed_v3(&self.wide, ray, test) };
        }
        traversal::missed_base(&self.wide, ray, test)
    }
}

/// [`Tracer::slack`] as a share of the scene's extent: 2^-20, about 1e-6.
const SLACK: f32 = 1.0 / (1 << 20) as f32;

/// `wide` scaled by a power of two that puts the scene's extent near 2^20 (module doc,
/// "Near the origin"), and that factor.
fn scaled_wide(mut wide: CwBvh) -> (CwBvh, f32) {
    if wide.nodes.is_empty() {
        return (wide, 1.0);
    }
    let extent = (wide.total_aabb.max - wide.total_aabb.min)
        .max_element()
        .max(f32::MIN_POSITIVE);
    // A node's exponent byte is a biased f32 exponent (obvhs: the scale of its child
    // grid); adding k to it multiplies that grid by 2^k, as `p * 2^k` moves its corner.
    let lowest = wide.nodes.iter().flat_map(|n| n.e).min().unwrap_or(127) as i32;
    let highest = wide.nodes.iter().flat_map(|n| n.e).max().unwrap_or(127) as i32;
    // Within the exponent byte's range, then within f32's (2^k finite), never a panic.
    let k = (20 - extent.log2().round() as i32)
        .max(1 - lowest)
        .min(254 - highest)
        .clamp(-100, 100);
    let scale = 2f32.powi(k);
    for node in &mut wide.nodes {
        node.p *= scale;
        for e in &mut node.e {
            *e = (*e as i32 + k) as u8;
        }
    }
    wide.total_aabb.min *= scale;
    wide.total_aabb.max *= scale;
    (wide, scale)
}

/// Möller–Trumbore, both faces; returns t in (tmin, tmax) and barycentrics.
#[inline]
pub fn intersect(tri: &Triangle, ray: &Ray) -> Option<(f32, Vec3)> {
    let p0 = Vec3A::from(tri.p[0]);
    let e1 = Vec3A::from(tri.p[1]) - p0;
    let e2 = Vec3A::from(tri.p[2]) - p0;
    let pv = ray.direction.cross(e2);
    let det = e1.dot(pv);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let tv = ray.origin - p0;
    let u = tv.dot(pv) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let qv = tv.cross(e1);
    let v = ray.direction.dot(qv) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(qv) * inv;
    (t > ray.tmin && t < ray.tmax).then_some((t, Vec3::new(1.0 - u - v, u, v)))
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
            let ray = Ray::new(o.into(), d.into(), 0.0, tmax);
            // Brute force: the nearest front-or-back hit, with the closest-hit query's tie
            // rule for single-sided back faces.
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
