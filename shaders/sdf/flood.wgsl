// sdf/flood.wgsl: the distance transform (src/engine/technique/sdf.rs).
// `flood` is one step of 3D jump flooding (Rong & Tan 2006) at offset `step`: every voxel
// looks at its own seed and the seeds of its 26 neighbours `step` voxels away and keeps
// the triangle nearest to its centre, by exact point-triangle distance (so seeds are
// triangles, not voxels, and the result is exact wherever flooding found the nearest
// triangle). `resolve` turns the final seeds into the signed distance: the exact distance
// to the seed triangle, negative when the centre is behind that triangle's plane (the
// nearest triangle's normal decides the sign), and the triangle's albedo.

struct FloodParams {
    misc: vec4<u32>,  // x: jump offset in voxels
}

@group(0) @binding(0) var<uniform> vol: SdfVolume;
@group(0) @binding(1) var<storage, read> tris: array<SdfTri>;
@group(0) @binding(2) var<storage, read> seeds_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> seeds_out: array<u32>;
@group(0) @binding(4) var<uniform> fp: FloodParams;
@group(0) @binding(5) var<storage, read_write> base: array<vec4<f32>>;

// Distance far beyond any normalised scene (radius 1): "no surface at all".
const SDF_FAR: f32 = 1.0e3;

fn voxel_of(i: u32) -> vec3<u32> {
    return vec3<u32>(i % vol.dims.x, (i / vol.dims.x) % vol.dims.y, i / (vol.dims.x * vol.dims.y));
}

@compute @workgroup_size(64)
fn flood(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    if (i >= vol.dims.x * vol.dims.y * vol.dims.z) { return; }
    let v = vec3<i32>(voxel_of(i));
    let p = sdf_voxel_centre(vol, vec3<u32>(v));
    var best = seeds_in[i];
    var best_d = SDF_FAR;
    if (best != SDF_NO_SEED) { best_d = sdf_triangle_distance(p, tris[best]); }
    let step = i32(fp.misc.x);
    let dims = vec3<i32>(vol.dims.xyz);
    // Neighbouring seeds repeat (a triangle is nearest over whole regions): the last four
    // seeds evaluated are remembered so a repeated one costs a compare, not a distance.
    var seen = array<u32, 4>(best, SDF_NO_SEED, SDF_NO_SEED, SDF_NO_SEED);
    var slot = 1u;
    for (var dz = -1; dz <= 1; dz++) {
        for (var dy = -1; dy <= 1; dy++) {
            for (var dx = -1; dx <= 1; dx++) {
                let q = v + vec3<i32>(dx, dy, dz) * step;
                if (any(q < vec3<i32>(0)) || any(q >= dims)) { continue; }
                let s = seeds_in[(u32(q.z) * vol.dims.y + u32(q.y)) * vol.dims.x + u32(q.x)];
                if (s == SDF_NO_SEED || s == best || s == seen[0] || s == seen[1] || s == seen[2] ||
                    s == seen[3]) { continue; }
                seen[slot] = s;
                slot = (slot + 1u) % 4u;
                let d = sdf_triangle_distance(p, tris[s]);
                if (d < best_d) {
                    best_d = d;
                    best = s;
                }
            }
        }
    }
    seeds_out[i] = best;
}

@compute @workgroup_size(64)
fn resolve(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    if (i >= vol.dims.x * vol.dims.y * vol.dims.z) { return; }
    let s = seeds_in[i];
    if (s == SDF_NO_SEED) {
        base[i] = vec4<f32>(SDF_FAR, 0.0, 0.0, 0.0);
        return;
    }
    let t = tris[s];
    let p = sdf_voxel_centre(vol, voxel_of(i));
    let q = sdf_closest_on_triangle(p, t.a.xyz, t.b.xyz, t.c.xyz);
    var d = length(p - q);
    if (dot(p - q, t.n.xyz) < 0.0) { d = -d; }
    base[i] = vec4<f32>(d, t.a.w, t.b.w, t.c.w);
}
