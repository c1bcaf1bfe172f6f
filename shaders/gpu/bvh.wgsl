// gpu/bvh.wgsl: ray traversal of the scene BVH (src/engine/gpu/bvh.rs builds and uploads
// it). A library, not a pass: it is concatenated after common.wgsl and before the pass of
// every shader that casts rays (gpu/shaders.rs, `pass_with_bvh!`), and it owns bindings 0
// and 1 of group 0, so those passes number their own bindings from 2.
//
// Format: a binary BVH of plain f32 boxes (obvhs's Bvh2, uncompressed), 32 bytes a node,
// root at 0. An inner node's children are nodes `first` and `first + 1`; a leaf covers
// triangle slots first .. first + count. Triangles are stored in slot order (the BVH's
// leaf order) as p0 and the two edges, so the ray/triangle test is the CPU's
// (engine::raytrace::intersect, Moller-Trumbore, both faces, inclusive edges) operation
// for operation.
//
// Precision and robustness:
// - Coordinates are whatever the host uploaded (the scene's world space, re-centred at
//   import, as the CPU tracer uses), f32.
// - The box test is conservative: the host rounds every box outward by one ulp, a zero
//   direction component is replaced by +-1e-30 (no 0 * inf = NaN), and the far slab
//   distance is scaled by 1 + 2 gamma(3) (Ize, "Robust BVH Ray Traversal", JCGT 2013),
//   so rounding can never cull a box the ray touches. A box containing the origin is
//   entered at t = 0: hits 1e-7 of the scene size from the origin are found (the CPU
//   path's wide BVH lost those; tests/gpu_bvh.rs checks it).
// - The triangle test accepts t in (0, tmax); edges are inclusive on both neighbours, so
//   a ray through a shared edge hits one of them up to rounding (not watertight: a ray
//   can slip through a crack of a few ulps where the CPU would too, which the callers'
//   barycentric inset keeps away from path vertices).
// - Division is 1/det as on the CPU; WGSL allows 2.5 ulp for it, so t and the
//   barycentrics agree with the CPU's to a few ulps, and a tie between two triangles at
//   the same t may resolve to the other one.
//
// Stack: near child first, far child pushed with its entry distance, so the stack never
// holds more than depth - 1 entries. The host refuses a tree deeper than BVH_STACK
// (bvh.rs), so the stack cannot overflow; should it anyway, the push is dropped (never
// out of bounds) and `overflow` is set on the result so a caller can report it. The same
// flag is set when the traversal loop ends without reaching its own exit: llvmpipe
// (lavapipe) ends every loop of an invocation once all its loops together have run
// 65535 iterations, and a traversal cut that way would read as a miss.
//
// Alpha (issue 19): every triangle carries a flags word; BVH_TRI_ALPHA_TEST marks one of
// a MASK or BLEND material, whose candidate hits must pass `bvh_alpha_accept(slot, u, v,
// o, d)`. That function is gpu/lights.wgsl's (it reads the materials and textures there),
// so every pass composed with this library composes that one too (WGSL resolves
// module-scope names in any order).

const BVH_STACK: u32 = 64u;
const BVH_MISS: u32 = 0xffffffffu;
const BVH_TRI_ALPHA_TEST: u32 = 1u;
// A single-sided triangle: in `bvh_closest` a hit on its back counts BVH_BACK_FACE_TIE
// times farther, so a coincident front face wins the tie (back-to-back single-sided
// sheets); the CPU tracer's `raytrace::BACK_FACE_TIE`, the same factor.
const BVH_TRI_SINGLE_SIDED: u32 = 2u;
const BVH_BACK_FACE_TIE: f32 = 1.00001;
// 1 + 2 gamma(3), gamma(n) = n u / (1 - n u), u = 2^-24.
const BVH_ROBUST: f32 = 1.0000003576;

struct BvhNode {
    min: vec3<f32>,
    first: u32,   // inner: first child node; leaf: first triangle slot
    max: vec3<f32>,
    count: u32,   // 0: inner node; else the leaf's triangle count
}

struct BvhTri {
    p0: vec3<f32>,
    id: u32,       // the scene's triangle index
    e1: vec3<f32>, // p1 - p0
    flags: u32,    // BVH_TRI_*
    e2: vec3<f32>, // p2 - p0
    pad: u32,
}

struct BvhHit {
    t: f32,
    slot: u32,     // BVH_MISS when nothing was hit
    u: f32,        // barycentric weight of p1
    v: f32,        // barycentric weight of p2
    overflow: bool,
}

@group(0) @binding(0) var<storage, read> bvh_nodes: array<BvhNode>;
@group(0) @binding(1) var<storage, read> bvh_tris: array<BvhTri>;

fn bvh_safe_inv(d: vec3<f32>) -> vec3<f32> {
    let tiny = vec3<f32>(1e-30);
    let s = select(vec3<f32>(1.0), vec3<f32>(-1.0), d < vec3<f32>(0.0));
    return vec3<f32>(1.0) / select(d, s * tiny, abs(d) < tiny);
}

// Entry distance (>= 0) of the ray into the box within [0, tmax], or -1 when it misses.
fn bvh_slab(bmin: vec3<f32>, bmax: vec3<f32>, o: vec3<f32>, inv: vec3<f32>, tmax: f32) -> f32 {
    let t0 = (bmin - o) * inv;
    let t1 = (bmax - o) * inv;
    let tn = min(t0, t1);
    let tf = max(t0, t1);
    let tnear = max(max(tn.x, tn.y), max(tn.z, 0.0));
    let tfar = min(min(tf.x, tf.y), tf.z) * BVH_ROBUST;
    return select(-1.0, tnear, tnear <= tfar && tnear <= tmax);
}

// Moller-Trumbore as engine::raytrace::intersect: (t, u, v) with t in (0, tmax), or t = -1.
fn bvh_tri_test(tri: BvhTri, o: vec3<f32>, d: vec3<f32>, tmax: f32) -> vec3<f32> {
    let none = vec3<f32>(-1.0, 0.0, 0.0);
    let pv = cross(d, tri.e2);
    let det = dot(tri.e1, pv);
    // det == 0 or not finite (NaN fails every comparison).
    if !(abs(det) > 0.0 && abs(det) <= 3.4028235e38) {
        return none;
    }
    let inv = 1.0 / det;
    let tv = o - tri.p0;
    let u = dot(tv, pv) * inv;
    if !(u >= 0.0 && u <= 1.0) {
        return none;
    }
    let qv = cross(tv, tri.e1);
    let v = dot(d, qv) * inv;
    if !(v >= 0.0 && u + v <= 1.0) {
        return none;
    }
    let t = dot(tri.e2, qv) * inv;
    if !(t > 0.0 && t < tmax) {
        return none;
    }
    return vec3<f32>(t, u, v);
}

// Closest hit along o + t d, t in (0, tmax). `d` need not be unit length (t is in its units).
fn bvh_closest(o: vec3<f32>, d: vec3<f32>, tmax: f32) -> BvhHit {
    var hit = BvhHit(tmax, BVH_MISS, 0.0, 0.0, false);
    // The distance hits are compared by: hit.t, except for a single-sided back face.
    var best = tmax;
    if arrayLength(&bvh_nodes) == 0u {
        return hit;
    }
    let inv = bvh_safe_inv(d);
    var stack_node: array<u32, BVH_STACK>;
    var stack_t: array<f32, BVH_STACK>;
    var sp = 0u;
    let root = bvh_nodes[0];
    if bvh_slab(root.min, root.max, o, inv, tmax) < 0.0 {
        return hit;
    }
    var idx = 0u;
    var finished = false;
    loop {
        let n = bvh_nodes[idx];
        var next = BVH_MISS;
        if n.count > 0u {
            for (var k = 0u; k < n.count; k++) {
                let s = n.first + k;
                let tri = bvh_tris[s];
                let r = bvh_tri_test(tri, o, d, best);
                let back = (tri.flags & BVH_TRI_SINGLE_SIDED) != 0u && dot(d, cross(tri.e1, tri.e2)) > 0.0;
                let key = select(r.x, r.x * BVH_BACK_FACE_TIE, back);
                if r.x > 0.0 && key < best && ((tri.flags & BVH_TRI_ALPHA_TEST) == 0u || bvh_alpha_accept(s, r.y, r.z, o, d)) {
                    best = key;
                    hit.t = r.x;
                    hit.slot = s;
                    hit.u = r.y;
                    hit.v = r.z;
                }
            }
        } else {
            let a = bvh_nodes[n.first];
            let b = bvh_nodes[n.first + 1u];
            let ta = bvh_slab(a.min, a.max, o, inv, best);
            let tb = bvh_slab(b.min, b.max, o, inv, best);
            if ta >= 0.0 && tb >= 0.0 {
                let a_first = ta <= tb;
                next = select(n.first + 1u, n.first, a_first);
                if sp < BVH_STACK {
                    stack_node[sp] = select(n.first, n.first + 1u, a_first);
                    stack_t[sp] = select(ta, tb, a_first);
                    sp += 1u;
                } else {
                    hit.overflow = true;
                }
            } else if ta >= 0.0 {
                next = n.first;
            } else if tb >= 0.0 {
                next = n.first + 1u;
            }
        }
        // Pop until a node still nearer than the closest hit.
        while next == BVH_MISS && sp > 0u {
            sp -= 1u;
            if stack_t[sp] <= best {
                next = stack_node[sp];
            }
        }
        if next == BVH_MISS {
            finished = true;
            break;
        }
        idx = next;
    }
    if !finished {
        hit.overflow = true;  // the loop was ended from outside (header)
    }
    return hit;
}

// True when nothing lies along o + t d for t in (0, tmax) (shadow rays: any hit ends it).
fn bvh_unoccluded(o: vec3<f32>, d: vec3<f32>, tmax: f32) -> bool {
    if arrayLength(&bvh_nodes) == 0u {
        return true;
    }
    let inv = bvh_safe_inv(d);
    var stack: array<u32, BVH_STACK>;
    var sp = 0u;
    let root = bvh_nodes[0];
    if bvh_slab(root.min, root.max, o, inv, tmax) < 0.0 {
        return true;
    }
    var idx = 0u;
    loop {
        let n = bvh_nodes[idx];
        var next = BVH_MISS;
        if n.count > 0u {
            for (var k = 0u; k < n.count; k++) {
                let s = n.first + k;
                let tri = bvh_tris[s];
                let r = bvh_tri_test(tri, o, d, tmax);
                if r.x > 0.0 && ((tri.flags & BVH_TRI_ALPHA_TEST) == 0u || bvh_alpha_accept(s, r.y, r.z, o, d)) {
                    return false;
                }
            }
        } else {
            let ta = bvh_slab(bvh_nodes[n.first].min, bvh_nodes[n.first].max, o, inv, tmax);
            let tb = bvh_slab(bvh_nodes[n.first + 1u].min, bvh_nodes[n.first + 1u].max, o, inv, tmax);
            if ta >= 0.0 && tb >= 0.0 {
                next = n.first;
                if sp < BVH_STACK {
                    stack[sp] = n.first + 1u;
                    sp += 1u;
                }
            } else if ta >= 0.0 {
                next = n.first;
            } else if tb >= 0.0 {
                next = n.first + 1u;
            }
        }
        if next == BVH_MISS {
            if sp == 0u {
                break;
            }
            sp -= 1u;
            next = stack[sp];
        }
        idx = next;
    }
    return true;
}
