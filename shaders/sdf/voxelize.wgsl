// sdf/voxelize.wgsl: seeds for the distance transform (src/engine/technique/sdf.rs).
// `clear_seeds` empties the seed grid; `voxelize` runs one 64-wide workgroup per
// triangle, whose threads stride over the voxels of the triangle's bounds (grown by one
// voxel) and seed every voxel the triangle may touch. The test is conservative: the
// voxel's centre lies within half a voxel diagonal of the triangle, a superset of the
// exact separating-axis overlap test; the extra seeds cost nothing in accuracy because
// the flood compares exact point-triangle distances. Ties go to the lowest triangle
// index (atomicMin), so the result does not depend on thread order.

struct VoxelizeParams {
    misc: vec4<u32>,  // x: triangle count; y: workgroups per row of the dispatch grid
}

@group(0) @binding(0) var<uniform> vol: SdfVolume;
@group(0) @binding(1) var<storage, read> tris: array<SdfTri>;
@group(0) @binding(2) var<storage, read_write> seeds: array<atomic<u32>>;
@group(0) @binding(3) var<uniform> vp: VoxelizeParams;

@compute @workgroup_size(64)
fn clear_seeds(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    if (i >= vol.dims.x * vol.dims.y * vol.dims.z) { return; }
    atomicStore(&seeds[i], SDF_NO_SEED);
}

@compute @workgroup_size(64)
fn voxelize(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let tri = wid.y * vp.misc.y + wid.x;
    if (tri >= vp.misc.x) { return; }
    let t = tris[tri];
    let h = vol.origin.w;
    let lo_p = min(t.a.xyz, min(t.b.xyz, t.c.xyz));
    let hi_p = max(t.a.xyz, max(t.b.xyz, t.c.xyz));
    let dims = vec3<i32>(vol.dims.xyz);
    let lo = clamp(vec3<i32>(floor((lo_p - vol.origin.xyz) / h)) - 1, vec3<i32>(0), dims - 1);
    let hi = clamp(vec3<i32>(floor((hi_p - vol.origin.xyz) / h)) + 1, vec3<i32>(0), dims - 1);
    let size = vec3<u32>(hi - lo + 1);
    let count = size.x * size.y * size.z;
    let reach = 0.8660254 * h;  // half the voxel diagonal
    for (var k = lid; k < count; k += 64u) {
        let v = vec3<u32>(lo) + vec3<u32>(k % size.x, (k / size.x) % size.y, k / (size.x * size.y));
        if (sdf_triangle_distance(sdf_voxel_centre(vol, v), t) <= reach) {
            atomicMin(&seeds[(v.z * vol.dims.y + v.y) * vol.dims.x + v.x], tri);
        }
    }
}
