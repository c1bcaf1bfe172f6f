//! The CPU queries' tree: obvhs's wide BVH (eight children a node, SAH-collapsed from a
//! binary tree built with spatial splits) decoded into plain `f32` child boxes, with the
//! leaves' triangles copied out in leaf order, and the two queries' traversal loops.
//!
//! Why not traverse obvhs's `CwBvh` as it is: its nodes keep the child boxes quantised to
//! bytes on a per-node grid (Ylitie et al. 2017), a format made for a GPU's memory
//! bandwidth; on a CPU each node test first rebuilds the boxes (the exponents, eight bytes
//! widened and converted per plane), and its traversal keeps the GPU's node-group state.
//! A CPU tree with `f32` boxes in eight-lane rows (Embree's layout) tests a node in a few
//! AVX2 instructions from the same cache lines. The tree's shape is obvhs's, so its build
//! quality (spatial splits, reinsertion) is kept; only the node format and the loop are
//! ours. Measured: `engine::raytrace` module doc, "Speed".
//!
//! ## Boxes
//! A leaf child's box is the bounds of its triangles, clipped to its quantised box (with
//! spatial splits a leaf holds only part of a triangle, and its quantised box bounds that
//! part). Both are first moved out: the bounds by four ulps of their magnitude (the
//! triangle test intersects the triangle its stored edges describe, which can differ from
//! the scene's corners by a rounding), the quantised box by one step of its node's grid
//! (an off-by-one of the quantisation) and the same four ulps (its decoding rounds). An
//! inner child's box is the union of its node's child boxes. So every point of a triangle
//! a ray can hit lies in a box the ray enters, and a box is at most a few ulps larger
//! than the geometry it holds.
//!
//! ## The slab test and its rounding
//! A child is entered when max(tmin, the three near planes' t) <= min(tmax, the three far
//! planes' t) × `ROBUST`, each plane's t computed as (plane - origin) × (1 / direction).
//! - The subtraction comes first (not origin × inverse folded into an FMA) so that a
//!   plane next to the origin is measured without cancellation, at any translation.
//! - Each t has two roundings, so a relative error of at most 2^-23: `ROBUST` = 1 + 2^-20
//!   moves every far distance (and with it the query's farthest distance) out by more
//!   than both ends' error together. No box a ray touches is culled, grazing rays and a
//!   hit just short of a shadow ray's end included (Ize 2013, "Robust BVH ray
//!   traversal", makes the same argument with its γ factors). The triangle test keeps
//!   the exact bounds.
//! - tmin is 0: nothing is clipped near the origin (obvhs's test clips at an absolute
//!   1e-4, which lost hits next to a wall; the previous tree was scaled to avoid it).
//! - The signs of (plane - origin) are exact, so a box behind the origin never enters.
//! - A direction component of ±0 has the inverse +∞ (the component is made +0.0 first),
//!   and a plane through the origin on that axis gives 0 × ∞ = NaN. The maxima and
//!   minima take the plane's value as their first operand (`maxps`/`minps` return the
//!   second when either is NaN), so a NaN plane drops out and the ray counts as inside
//!   that slab: conservative.
//! - An empty lane has the box (+∞, -∞): its near t is +∞ and its far t -∞ whatever the
//!   direction, so it is never entered.
//!
//! The AVX2 test and the scalar one (for CPUs without AVX2) do the same operations in the
//! same order, so they enter the same children.
//!
//! ## Traversal
//! Closest hit: a node's leaf children are tested at once (their triangles are few, and a
//! hit found shrinks the distance the other children are culled against); its inner
//! children that are still in range are visited nearest first, the rest pushed with their
//! entry distance and skipped when popped beyond the best hit. Occlusion: any order, the
//! first hit ends it. The stack holds at most seven entries a level: it is sized from the
//! tree's depth when the tree is built (on the thread's stack up to 36 levels, on the heap
//! beyond), so it never overflows.
//!
//! Limits: single rays (no packets); a leaf holds at most 3 triangles (obvhs's CWBVH).

use std::mem::MaybeUninit;

use glam::{Vec3, Vec3A};
use obvhs::cwbvh::CwBvh;

use crate::engine::scene::{AlphaMode, Scene};

/// The far distances' margin (module doc, "The slab test and its rounding").
pub const ROBUST: f32 = 1.0 + 1.0 / (1 << 20) as f32;

/// One node: eight child boxes in rows of eight lanes, and what each child is.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
pub struct Node {
    /// Rows: min x, max x, min y, max y, min z, max z; lane j is child j.
    b: [[f32; 8]; 6],
    /// Inner child: its node's index; leaf child: its first record; empty: 0.
    child: [u32; 8],
    /// Bit j set: child j is a leaf.
    leaves: u8,
    /// A leaf child's number of records (1 to 3).
    count: [u8; 8],
}

/// A triangle as the queries test it: first corner and the two edges from it (the
/// subtractions `raytrace::intersect` does, done once), the scene's index, and flags.
#[derive(Clone, Copy)]
pub struct Record {
    pub p0: Vec3,
    pub e1: Vec3,
    pub e2: Vec3,
    pub index: u32,
    pub flags: u32,
}

/// [`Record::flags`]: the material is not opaque (the alpha test decides a hit).
pub const ALPHA: u32 = 1;
/// [`Record::flags`]: the material is single-sided.
pub const ONE_SIDED: u32 = 2;

/// The stack entries: a node index in the low half, its entry distance's bits above (a
/// non-negative `f32`, so the bits order as the distances do).
type Entry = u64;

/// Largest stack kept on the thread's stack (36 levels of seven).
pub(super) const INLINE_STACK: usize = 256;

pub struct Bvh8 {
    nodes: Vec<Node>,
    records: Vec<Record>,
    /// Stack entries a traversal can need: seven a level below the root, plus one.
    pub(super) stack_len: usize,
}

/// The per-ray values the node test uses.
#[derive(Clone, Copy)]
pub struct RayData {
    pub origin: Vec3A,
    pub dir: Vec3A,
    inv: [f32; 3],
    /// Row of each axis's near plane (0 or 1 above the axis's first row).
    near: [usize; 3],
}

impl RayData {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        // Adding +0.0 turns -0.0 into +0.0 (module doc).
        let d = Vec3A::from(dir) + Vec3A::ZERO;
        let inv = [1.0 / d.x, 1.0 / d.y, 1.0 / d.z];
        RayData {
            origin: origin.into(),
            dir: dir.into(),
            inv,
            near: inv.map(|i| usize::from(i < 0.0)),
        }
    }
}

impl Bvh8 {
    /// Decodes `wide` (built over `scene`'s triangles, unscaled).
    pub fn new(wide: &CwBvh, scene: &Scene) -> Self {
        let records: Vec<Record> = wide
            .primitive_indices
            .iter()
            .map(|&index| {
                let tri = &scene.triangles[index as usize];
                let m = scene.material(tri);
                let mut flags = 0;
                if m.alpha_mode != AlphaMode::Opaque {
                    flags |= ALPHA;
                }
                if !m.double_sided {
                    flags |= ONE_SIDED;
                }
                Record {
                    p0: tri.p[0],
                    e1: tri.p[1] - tri.p[0],
                    e2: tri.p[2] - tri.p[0],
                    index,
                    flags,
                }
            })
            .collect();
        let empty = Node {
            b: [
                [f32::INFINITY; 8],
                [f32::NEG_INFINITY; 8],
                [f32::INFINITY; 8],
                [f32::NEG_INFINITY; 8],
                [f32::INFINITY; 8],
                [f32::NEG_INFINITY; 8],
            ],
            child: [0; 8],
            leaves: 0,
            count: [0; 8],
        };
        let mut nodes = vec![empty; wide.nodes.len()];
        // Each node's own bounds, once its children are done: children follow their parent
        // in obvhs's layout, so a pass from the last node up finds them done; a child that
        // does not (checked) keeps its quantised box.
        let mut bounds: Vec<Option<(Vec3, Vec3)>> = vec![None; wide.nodes.len()];
        let mut depth = vec![1usize; wide.nodes.len()];
        for i in (0..wide.nodes.len()).rev() {
            let src = &wide.nodes[i];
            let step: Vec3 = src.compute_extent().into();
            let mut node = empty;
            let mut own: Option<(Vec3, Vec3)> = None;
            let mut below = 0;
            for j in 0..8 {
                if src.is_child_empty(j) {
                    continue;
                }
                let q = src.child_aabb(j);
                let (qlo, qhi) = widen(q.min.into(), q.max.into(), step);
                let (lo, hi) = if src.is_leaf(j) {
                    let (start, count) = src.child_primitives(j);
                    let (mut lo, mut hi) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
                    for r in &records[start as usize..(start + count) as usize] {
                        for p in scene.triangles[r.index as usize].p {
                            lo = lo.min(p);
                            hi = hi.max(p);
                        }
                    }
                    node.leaves |= 1 << j;
                    node.child[j] = start;
                    node.count[j] = count as u8;
                    let (lo, hi) = widen(lo, hi, Vec3::ZERO);
                    (lo.max(qlo), hi.min(qhi))
                } else {
                    let c = src.child_node_index(j) as usize;
                    node.child[j] = c as u32;
                    if c > i {
                        below = below.max(depth[c]);
                    }
                    match bounds.get(c).copied().flatten().filter(|_| c > i) {
                        Some(b) => b,
                        None => (qlo, qhi),
                    }
                };
                for (axis, (l, h)) in [(lo.x, hi.x), (lo.y, hi.y), (lo.z, hi.z)].into_iter().enumerate() {
                    node.b[2 * axis][j] = l;
                    node.b[2 * axis + 1][j] = h;
                }
                own = Some(match own {
                    Some((a, b)) => (a.min(lo), b.max(hi)),
                    None => (lo, hi),
                });
            }
            depth[i] = below + 1;
            bounds[i] = own;
            nodes[i] = node;
        }
        // A child placed before its parent breaks the depth pass: count every node then.
        let ordered =
            wide.nodes.iter().enumerate().all(|(i, n)| {
                (0..8).all(|j| n.is_child_empty(j) || n.is_leaf(j) || n.child_node_index(j) as usize > i)
            });
        let levels = if ordered {
            depth.first().copied().unwrap_or(1)
        } else {
            wide.nodes.len()
        };
        Bvh8 {
            nodes,
            records,
            stack_len: 7 * levels + 1,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    pub fn record(&self, k: usize) -> &Record {
        &self.records[k]
    }

    /// Runs `f` with a stack large enough for any traversal of this tree.
    #[inline(always)]
    pub fn with_stack<R>(&self, f: impl FnOnce(&mut Stack<'_>) -> R) -> R {
        if self.stack_len <= INLINE_STACK {
            let mut slots = [MaybeUninit::<Entry>::uninit(); INLINE_STACK];
            f(&mut Stack {
                slots: &mut slots,
                len: 0,
            })
        } else {
            let mut slots = vec![MaybeUninit::<Entry>::uninit(); self.stack_len];
            f(&mut Stack {
                slots: &mut slots,
                len: 0,
            })
        }
    }
}

/// `lo`..`hi` moved out by `by` and by 2^-21 of each bound's magnitude (four ulps: the
/// roundings of the quantised boxes' decoding, and of the edges the triangle test builds
/// its triangle from; module doc, "Boxes").
fn widen(lo: Vec3, hi: Vec3, by: Vec3) -> (Vec3, Vec3) {
    const REL: f32 = 1.0 / (1 << 21) as f32;
    let tiny = Vec3::splat(f32::MIN_POSITIVE);
    (lo - (lo.abs() * REL + by + tiny), hi + (hi.abs() * REL + by + tiny))
}

/// A traversal stack over slots sized for the tree ([`Bvh8::with_stack`]).
pub struct Stack<'a> {
    slots: &'a mut [MaybeUninit<Entry>],
    len: usize,
}

impl Stack<'_> {
    #[inline(always)]
    fn push(&mut self, e: Entry) {
        // In range by the tree's depth (module doc); a bounds check, never a wrong write.
        self.slots[self.len] = MaybeUninit::new(e);
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<Entry> {
        if self.len == 0 {
            return None;
        }
        self.len -= 1;
        // SAFETY: every slot below `len` was written by `push`.
        Some(unsafe { self.slots[self.len].assume_init() })
    }
}

/// The scalar node test: which children the ray enters before `tmax`, and their entry
/// distances. The same operations in the same order as [`node_test_avx2`].
#[inline(always)]
pub fn node_test_scalar(node: &Node, r: &RayData, tmax: f32) -> (u32, [f32; 8]) {
    let mut mask = 0u32;
    let mut tnear = [0f32; 8];
    // maxps / minps: the first operand when the comparison holds, else the second.
    let max = |a: f32, b: f32| if a > b { a } else { b };
    let min = |a: f32, b: f32| if a < b { a } else { b };
    for (j, entry) in tnear.iter_mut().enumerate() {
        let mut near = 0.0f32;
        let mut far = tmax;
        for axis in (0..3).rev() {
            let n = r.near[axis];
            let tn = (node.b[2 * axis + n][j] - r.origin[axis]) * r.inv[axis];
            let tf = (node.b[2 * axis + 1 - n][j] - r.origin[axis]) * r.inv[axis];
            near = max(tn, near);
            far = min(tf, far);
        }
        if near <= far * ROBUST {
            mask |= 1 << j;
        }
        *entry = near;
    }
    (mask, tnear)
}

/// [`node_test_scalar`] in AVX2, all eight lanes at once.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
#[inline]
pub fn node_test_avx2(node: &Node, r: &RayData, tmax: f32) -> (u32, [f32; 8]) {
    use std::arch::x86_64::*;
    // SAFETY: the rows are 32-byte aligned (`Node` is 64-aligned and each row 32 bytes).
    let row = |k: usize| unsafe { _mm256_load_ps(node.b[k].as_ptr()) };
    let mut near = _mm256_setzero_ps();
    let mut far = _mm256_set1_ps(tmax);
    for axis in (0..3).rev() {
        let n = r.near[axis];
        let (o, inv) = (_mm256_set1_ps(r.origin[axis]), _mm256_set1_ps(r.inv[axis]));
        let tn = _mm256_mul_ps(_mm256_sub_ps(row(2 * axis + n), o), inv);
        let tf = _mm256_mul_ps(_mm256_sub_ps(row(2 * axis + 1 - n), o), inv);
        near = _mm256_max_ps(tn, near);
        far = _mm256_min_ps(tf, far);
    }
    let far = _mm256_mul_ps(far, _mm256_set1_ps(ROBUST));
    let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32;
    let mut tnear = [0f32; 8];
    // SAFETY: `tnear` holds eight f32s; the store is unaligned.
    unsafe { _mm256_storeu_ps(tnear.as_mut_ptr(), near) };
    (mask, tnear)
}

/// The records of `node`'s leaf children that `mask` says the ray enters, child by child.
#[inline(always)]
fn leaf_records(node: &Node, mask: u32) -> impl Iterator<Item = usize> + '_ {
    let mut leaves = mask & u32::from(node.leaves);
    std::iter::from_fn(move || {
        (leaves != 0).then(|| {
            let j = leaves.trailing_zeros() as usize;
            leaves &= leaves - 1;
            j
        })
    })
    .flat_map(|j| {
        let first = node.child[j] as usize;
        first..first + usize::from(node.count[j])
    })
}

/// The closest-hit loop: `test(record, best)` tests one record against the best value so
/// far and returns its value when nearer (a distance, or a back face's distance times
/// the tie factor). Returns the best value, or `tmax` when nothing was nearer.
#[inline(always)]
pub fn closest<N, F>(bvh: &Bvh8, r: &RayData, tmax: f32, stack: &mut Stack<'_>, node_test: N, mut test: F) -> f32
where
    N: Fn(&Node, &RayData, f32) -> (u32, [f32; 8]),
    F: FnMut(usize, f32) -> Option<f32>,
{
    let mut best = tmax;
    let mut cur = 0usize;
    loop {
        let node = &bvh.nodes[cur];
        let (mask, tnear) = node_test(node, r, best);
        for k in leaf_records(node, mask) {
            if let Some(v) = test(k, best) {
                best = v;
            }
        }
        let cull = best * ROBUST;
        let mut inner = mask & !u32::from(node.leaves);
        // Up to eight (distance, node) keys of the children still in range, nearest last.
        let mut keys = [0 as Entry; 8];
        let mut n = 0;
        while inner != 0 {
            let j = inner.trailing_zeros() as usize;
            inner &= inner - 1;
            if tnear[j] <= cull {
                let key = (u64::from(tnear[j].to_bits()) << 32) | u64::from(node.child[j]);
                // Insertion, farthest first.
                let mut at = n;
                while at > 0 && keys[at - 1] < key {
                    keys[at] = keys[at - 1];
                    at -= 1;
                }
                keys[at] = key;
                n += 1;
            }
        }
        if n > 0 {
            for &k in &keys[..n - 1] {
                stack.push(k);
            }
            cur = keys[n - 1] as u32 as usize;
            continue;
        }
        loop {
            let Some(e) = stack.pop() else { return best };
            if f32::from_bits((e >> 32) as u32) <= best * ROBUST {
                cur = e as u32 as usize;
                break;
            }
        }
    }
}

/// The occlusion loop: true when no record's `test` holds before `tmax`.
#[inline(always)]
pub fn missed<N, F>(bvh: &Bvh8, r: &RayData, tmax: f32, stack: &mut Stack<'_>, node_test: N, mut test: F) -> bool
where
    N: Fn(&Node, &RayData, f32) -> (u32, [f32; 8]),
    F: FnMut(usize) -> bool,
{
    let mut cur = 0usize;
    loop {
        let node = &bvh.nodes[cur];
        let (mask, _) = node_test(node, r, tmax);
        if leaf_records(node, mask).any(&mut test) {
            return false;
        }
        let mut inner = mask & !u32::from(node.leaves);
        if inner != 0 {
            let j = inner.trailing_zeros() as usize;
            inner &= inner - 1;
            cur = node.child[j] as usize;
            while inner != 0 {
                let j = inner.trailing_zeros() as usize;
                inner &= inner - 1;
                stack.push(u64::from(node.child[j]));
            }
            continue;
        }
        match stack.pop() {
            Some(e) => cur = e as u32 as usize,
            None => return true,
        }
    }
}
