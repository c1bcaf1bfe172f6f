// sdf/mips.wgsl: the pre-blurred mips (seed section 9.6). Level l is the mean of the
// 2 x 2 x 2 children in level l - 1 (a box pre-filter of width 2^l voxels, the seed's
// blur radius proportional to the sample distance); children past the edge of an odd
// dimension are extrapolated (see `child`). A linear distance field (a plane) is kept
// exactly, since the mean of the children sits at the parent's centre.

struct MipParams {
    misc: vec4<u32>,  // x: the level written (>= 1)
}

@group(0) @binding(0) var<uniform> vol: SdfVolume;
@group(0) @binding(1) var<storage, read_write> levels: array<vec4<f32>>;
@group(0) @binding(2) var<uniform> mp: MipParams;

// Child `c` of level l - 1 at index f (per axis possibly one past the last voxel when the
// finer level has an odd size): past the edge, the value is extrapolated linearly from
// the last two voxels of that axis, 2 v(n - 1) - v(n - 2), so that the parent's mean
// still sits at its centre and a linear field stays exact up to the volume's border.
fn child(fo: u32, fd: vec3<u32>, f: vec3<u32>) -> vec4<f32> {
    var i0 = f;
    var i1 = f;
    var w0 = vec3<f32>(1.0);
    for (var a = 0u; a < 3u; a++) {
        if (f[a] >= fd[a]) {
            i0[a] = fd[a] - 1u;
            if (fd[a] >= 2u) {
                i1[a] = fd[a] - 2u;
                w0[a] = 2.0;
            } else {
                i1[a] = fd[a] - 1u;
            }
        }
    }
    var sum = vec4<f32>(0.0);
    for (var c = 0u; c < 8u; c++) {
        let pick = vec3<bool>((c & 1u) != 0u, (c & 2u) != 0u, (c & 4u) != 0u);
        let idx = select(i0, i1, pick);
        let w = select(w0, vec3<f32>(1.0) - w0, pick);
        let weight = w.x * w.y * w.z;
        if (weight != 0.0) {
            sum += weight * levels[fo + (idx.z * fd.y + idx.y) * fd.x + idx.x];
        }
    }
    return sum;
}

@compute @workgroup_size(64)
fn downsample(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let l = mp.misc.x;
    let d = sdf_level_dims(vol, l);
    let i = invocation_index(wid, nwg, lid);
    if (i >= d.x * d.y * d.z) { return; }
    let v = vec3<u32>(i % d.x, (i / d.x) % d.y, i / (d.x * d.y));
    let fd = sdf_level_dims(vol, l - 1u);
    let fo = sdf_level_offset(vol, l - 1u);
    var sum = vec4<f32>(0.0);
    for (var c = 0u; c < 8u; c++) {
        sum += child(fo, fd, v * 2u + vec3<u32>(c & 1u, (c >> 1u) & 1u, c >> 2u));
    }
    levels[sdf_level_offset(vol, l) + i] = sum * 0.125;
}
