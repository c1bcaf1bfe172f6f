// gpu/bvh_query.wgsl: one BVH query per invocation, for the tests that compare the GPU
// traversal with the CPU's and for the traversal benchmark (src/engine/gpu/bvh.rs,
// `QueryRunner`). Mode 0: closest hit; mode 1: any hit (occlusion) up to tmax.

struct QueryRay {
    origin: vec3<f32>,
    tmax: f32,
    dir: vec3<f32>,
    mode: u32,
}

// Closest hit: (t, slot, u, v), slot BVH_MISS on a miss. Any hit: slot 1 when occluded,
// 0 when not. slot QUERY_OVERFLOW: the traversal stack overflowed (cannot happen on a
// tree the host accepted).
struct QueryResult {
    t: f32,
    slot: u32,
    u: f32,
    v: f32,
}

const QUERY_OVERFLOW: u32 = 0xfffffffeu;

struct QueryParams {
    count: vec4<u32>,  // x: number of rays
}

// Bindings 0-4: the scene (gpu/bvh.wgsl, gpu/lights.wgsl: the alpha test reads its
// materials and textures).
@group(0) @binding(5) var<uniform> qp: QueryParams;
@group(0) @binding(6) var<storage, read> rays: array<QueryRay>;
@group(0) @binding(7) var<storage, read_write> results: array<QueryResult>;

@compute @workgroup_size(64)
fn query(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    if i >= qp.count.x {
        return;
    }
    let r = rays[i];
    if r.mode == 1u {
        let free = bvh_unoccluded(r.origin, r.dir, r.tmax);
        results[i] = QueryResult(0.0, select(1u, 0u, free), 0.0, 0.0);
    } else {
        let h = bvh_closest(r.origin, r.dir, r.tmax);
        results[i] = QueryResult(h.t, select(h.slot, QUERY_OVERFLOW, h.overflow), h.u, h.v);
    }
}
