// sdb/resolve.wgsl: reflected radiance of every lightmap pixel from the current
// estimate, albedo * E/pi (seed Eq. 1 with the running estimate in place of the integral;
// the illumination pass adds the emission). The illumination pass reads this buffer at
// each fragment's lightmap UV, which is how bounces happen: each direction gathers light
// that was itself gathered before.
//
// Pixels outside every chart take the values of a nearby valid texel (`fill`, built on
// the CPU once per bake) so that bilinear lookups at chart borders do not fetch black;
// pixels too far from any chart get coverage 0 and the fragment falls back to the
// triangle's material emission.
//
// `ambient_mode` (one workgroup, before `resolve`; average mode only) is a coarse-mode
// correction of the feedback, beyond the seed: with albedo rho the running mean's
// transient decays like n^-(1 - rho) directions, hopeless at rho = 0.99. Write M for the
// mean of the estimates the resolve pass has fed so far, per texel and with the very
// weights of the estimate x (the gather blends both; any other weighting would put their
// difference, times 1 / (1 - rho), into the correction). In expectation x = T M + e (T:
// one bounce, e: emitted and sky light), so the residual r = x - M is what one more
// bounce adds. Take the coarse space spanned by the current estimate's own shape v = x
// (a Ritz vector: repeated bounces turn any field toward T's dominant mode, and where no
// light has arrived, v = 0, nothing is added, so light never spreads into rooms it
// cannot reach). With T v ~ g v, g the "ambient gain" (the area-weighted mean albedo seen,
// measured on the CPU by ray casting), the Galerkin correction on span{v} is
// delta = g / (1 - g) <r> v / <v> per channel: the pass feeds x + delta (a two-level
// method with the Jacobi-like gathers as the smoother). At convergence <r> = 0 and
// delta = 0, so the fixed point is unchanged; in a closed room of uniform albedo v is T's
// dominant mode and the correction is exact. Other modes converge as before (docs/sdb.md).

struct ResolveParams {
    // x, y: weights of the even and odd gathered estimates (ratio of their blends);
    // z, w: weights of the even and odd sun accumulators. The CPU folds the step counts,
    // the mode and the leaky start-up correction into these.
    scale: vec4<f32>,
    // x: lightmap width, y: height, z: valid texel count N; w: 1 when there are sun
    // accumulators, else 0 (binding 5 then aliases the gathered ones and is not read).
    dims: vec4<u32>,
    // rgb: g / (1 - g) per channel (0 switches the correction off); w: unused.
    ambient: vec4<f32>,
    // x .. y: the receiving texels, where the correction is measured and added (every
    // texel, 0 .. N, but in a round of a bake in rounds: the others hold the light the
    // round before estimated, which the correction must neither average nor amplify);
    // z, w: unused.
    receivers: vec4<u32>,
}

@group(0) @binding(0) var<uniform> params: ResolveParams;
@group(0) @binding(1) var<storage, read> fill: array<u32>;          // W*H, texel index or NO_TEXEL
@group(0) @binding(2) var<storage, read> shade: array<TexelShade>;  // N; albedo.a: texel area (normalised)
@group(0) @binding(3) var<storage, read> acc: array<vec4<f32>>;     // 2N: even then odd; rgb / a = E/pi
@group(0) @binding(4) var<storage, read_write> radiance: array<vec4<f32>>;  // W*H: rgb reflected, a coverage
@group(0) @binding(5) var<storage, read> sun_acc: array<vec4<f32>>;  // 2N: rgb E/pi from the sun and directional lights
// [0].rgb: g / (1 - g) <r> / <x>, the correction per unit of estimate fed this step;
// [1].rgb: <r>, [1].a unused.
@group(0) @binding(6) var<storage, read_write> ambient: array<vec4<f32>, 2>;
@group(0) @binding(7) var<storage, read_write> fed: array<vec4<f32>>;      // N: what resolve fed each texel
@group(0) @binding(8) var<storage, read> fed_acc: array<vec4<f32>>;        // 2N: blends of `fed` (see sdb/gather.wgsl)

const NO_TEXEL: u32 = 0xffffffffu;

fn ratio(v: vec4<f32>) -> vec3<f32> {
    // No direction has reached this texel's hemisphere yet: nothing is known, 0.
    return select(vec3<f32>(0.0), v.rgb / v.a, v.a > 0.0);
}

// The current estimate of E/pi at valid texel i, both halves combined.
fn estimate(i: u32) -> vec3<f32> {
    let n = params.dims.z;
    var e = ratio(acc[i]) * params.scale.x + ratio(acc[n + i]) * params.scale.y;
    if params.dims.w != 0u {
        e += sun_acc[i].rgb * params.scale.z + sun_acc[n + i].rgb * params.scale.w;
    }
    return e;
}

fn over_weight(v: vec3<f32>, w: f32) -> vec3<f32> {
    return select(vec3<f32>(0.0), v / w, w > 0.0);
}

// M at texel i: the mean of what was fed, with the estimate's weights.
fn fed_mean(i: u32) -> vec3<f32> {
    let n = params.dims.z;
    return over_weight(fed_acc[i].rgb, acc[i].a) * params.scale.x
        + over_weight(fed_acc[n + i].rgb, acc[n + i].a) * params.scale.y;
}

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
    // An overshooting correction must not turn into negative light.
    let x = estimate(src);
    let receives = src >= params.receivers.x && src < params.receivers.y;
    let e = select(x, max(x + x * ambient[0].rgb, vec3<f32>(0.0)), receives);
    radiance[pixel] = vec4<f32>(shade[src].albedo.rgb * e, 1.0);
    // Every pixel that copies texel src writes the same value.
    fed[src] = vec4<f32>(e, 0.0);
}

const AMBIENT_THREADS: u32 = 256u;
var<workgroup> partial_r: array<vec4<f32>, AMBIENT_THREADS>;  // rgb: area x r, a: area
var<workgroup> partial_x: array<vec4<f32>, AMBIENT_THREADS>;  // rgb: area x x

// Dispatched as a single workgroup: each thread sums a strided share of the texels (in
// f32; at 16M texels a thread adds 65k terms, so the mean residual is good to ~1e-5 of
// the estimate, which the factor g / (1 - g) multiplies: at rho = 0.999 that is 1 %
// of noise in delta at 4096^2, and far less at the resolutions stiff rooms are baked at),
// then a tree reduction in workgroup memory.
@compute @workgroup_size(256)
fn ambient_mode(@builtin(local_invocation_index) lid: u32) {
    let n = params.dims.z;
    var sum_r = vec4<f32>(0.0);
    var sum_x = vec4<f32>(0.0);
    for (var i = params.receivers.x + lid; i < min(params.receivers.y, n); i += AMBIENT_THREADS) {
        let area = shade[i].albedo.a;
        let x = estimate(i);
        sum_r += vec4<f32>((x - fed_mean(i)) * area, area);
        sum_x += vec4<f32>(x * area, 0.0);
    }
    partial_r[lid] = sum_r;
    partial_x[lid] = sum_x;
    workgroupBarrier();
    for (var stride = AMBIENT_THREADS / 2u; stride > 0u; stride /= 2u) {
        if lid < stride {
            partial_r[lid] += partial_r[lid + stride];
            partial_x[lid] += partial_x[lid + stride];
        }
        workgroupBarrier();
    }
    if lid == 0u {
        let area = partial_r[0].w;
        let r = over_weight(partial_r[0].rgb, area);
        let x = over_weight(partial_x[0].rgb, area);
        // Per channel: no light in a channel yet, no correction in it.
        let per_unit = select(vec3<f32>(0.0), params.ambient.rgb * r / x, x > vec3<f32>(0.0));
        ambient[0] = vec4<f32>(per_unit, 0.0);
        ambient[1] = vec4<f32>(r, 0.0);
    }
}
