// sdb_resolve.wgsl: reflected radiance of every lightmap pixel from the current
// estimate, albedo * E/pi (seed Eq. 1 with the running estimate in place of the integral;
// the illumination pass adds the emission). The illumination pass reads this buffer at each fragment's lightmap UV, which
// is how bounces happen: each direction gathers light that was itself gathered before.
//
// Pixels outside every chart take the values of a nearby valid texel (`fill`, built on
// the CPU once per bake) so that bilinear lookups at chart borders do not fetch black;
// pixels too far from any chart get coverage 0 and the fragment falls back to the
// triangle's material emission.

struct ResolveParams {
    // x: weight of the even accumulator, y: weight of the odd one (the CPU folds the step
    // counts, the mode and leaky start-up correction into these); z, w: unused.
    scale: vec4<f32>,
    // x: lightmap width, y: height, z: valid texel count N; w: unused.
    dims: vec4<u32>,
}

@group(0) @binding(0) var<uniform> params: ResolveParams;
@group(0) @binding(1) var<storage, read> fill: array<u32>;          // W*H, texel index or NO_TEXEL
@group(0) @binding(2) var<storage, read> shade: array<TexelShade>;  // N
@group(0) @binding(3) var<storage, read> acc: array<vec4<f32>>;     // 2N: even then odd
@group(0) @binding(4) var<storage, read_write> radiance: array<vec4<f32>>;  // W*H: rgb reflected, a coverage

const NO_TEXEL: u32 = 0xffffffffu;

@compute @workgroup_size(64)
fn resolve(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let pixel = invocation_index(wid, nwg, lid);
    if pixel >= params.dims.x * params.dims.y {
        return;
    }
    let src = fill[pixel];
    if src == NO_TEXEL {
        radiance[pixel] = vec4<f32>(0.0);
        return;
    }
    let n = params.dims.z;
    let e = acc[src].rgb * params.scale.x + acc[n + src].rgb * params.scale.y;
    let s = shade[src];
    radiance[pixel] = vec4<f32>(s.albedo.rgb * e, 1.0);
}
