// hemicube/pyramid.wgsl: the sum pyramid the shooters are drawn from (seed section 4.1).
//
// `power` writes level 0 (cleared to 0 by the CPU's clear_buffer first): one cell per lightmap pixel of an S x S grid (S the lightmap's
// larger side rounded up to a power of two), holding the luminance of the power the
// texel reflects, lum(I (k_d + k_s)) A, from the previous step's irradiance I (empty and
// invalid pixels hold 0). Emission is not in it: emitters are sampled on the CPU from
// their triangles (exact area and emission), see hemicube.rs.
// `reduce` writes level l + 1 from level l: each cell the sum of its 2 x 2 children (the
// seed's mipmap stores averages; sums keep the top cell the total power and need no
// rescaling while descending). All levels live in one f32 buffer, level l at offset
// sum_{k<l} (S >> k)^2.

@group(0) @binding(0) var<uniform> params: HcParams;
@group(0) @binding(1) var<storage, read> mats: array<TexelMat>;
@group(0) @binding(2) var<storage, read> irr: array<vec4<f32>>;  // 2N: two halves
@group(0) @binding(3) var<storage, read_write> pyramid: array<f32>;

@compute @workgroup_size(64)
fn power(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let t = invocation_index(wid, nwg, lid);
    if t >= params.dims.x {
        return;
    }
    let m = mats[t];
    let prev = 1u - params.step.x;
    let i = irr[prev * params.dims.x + t].rgb;
    let p = max(dot(i * (m.kd.rgb + m.ks.rgb), HC_LUM) * m.kd.w, 0.0);
    let px = m.ids.z % params.dims.y;
    let py = m.ids.z / params.dims.y;
    // A non-finite power would poison every sum above it: such a texel never shoots.
    pyramid[py * params.dims.w + px] = select(0.0, p, p < 3.0e38);
}

@group(0) @binding(4) var<uniform> level: LevelParams;

@compute @workgroup_size(64)
fn reduce(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) lid: u32) {
    let cell = invocation_index(wid, nwg, lid);
    let side = level.v.x;
    if cell >= side * side {
        return;
    }
    let x = cell % side;
    let y = cell / side;
    let src = 2u * side;
    let base = level.v.y + (2u * y) * src + 2u * x;
    pyramid[level.v.z + cell] = pyramid[base] + pyramid[base + 1u] + pyramid[base + src] + pyramid[base + src + 1u];
}
