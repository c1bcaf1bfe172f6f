// sdb/gather.wgsl: one global direction's contribution to every lightmap texel (seed
// section 4, Figures 5 and 6). Each texel projects its sample point x into the
// illumination map, reads the k x k neighbourhood around it, keeps the samples that lie
// in front of x along d and above x's normal plane, and takes the nearest along d; with
// none left the environment's radiance in direction d (the same for every texel, so the
// CPU evaluates it once per direction) is used. The estimator of E/pi is the seed's
// Eq. 2 without the albedo: 4 * L_i(x, d) * max(<d, n>, 0), unbiased for uniformly
// distributed d over the sphere.
//
// Departures from the seed: the "in front of x" test (the seed's Figure 5 checks only the
// normal plane, which lets a sample behind x along d win when x faces d obliquely), small
// epsilons relative to the scene size, and accumulation into two half accumulators (even
// and odd steps) so the bake can estimate its own error.
//
// Accumulation is always a running blend, acc = acc (1 - b) + c b, with b from the CPU:
// for `average` mode b = w_i / W_i (a running weighted mean whose weights ramp up, see
// sdb.rs), for `leaky` mode the fixed blend. The running form keeps values at the scale
// of one estimate, so f32 sums lose no precision over many thousand directions.
//
// Self-normalised (a departure from the seed): rgb blends 4 L max(<d, n>, 0) and alpha
// blends the weight 4 max(<d, n>, 0) itself; the estimate is rgb / alpha, a ratio
// estimator of the cosine-weighted mean radiance over the hemisphere (E/pi exactly, since
// the weights integrate to pi). Its denominator's error cancels the numerator's wherever
// the radiance is uniform, so a furnace texel is exact after any number of directions
// and the transport keeps energy to rounding: with albedo rho the bounce series amplifies
// any relative error of the plain estimator by 1 / (1 - rho), 1000 at rho = 0.999.
// Bias O(1/n) (a ratio of means), consistent.

struct GatherParams {
    env: vec4<f32>,   // rgb: environment radiance arriving along -d (seen looking along +d); w: blend b
    eps: vec4<f32>,   // x: normal-plane epsilon, y: along-d epsilon (normalised scene units); z, w: unused
    misc: vec4<u32>,  // x: neighbourhood radius r (k = 2r+1), y: depth layers, z: parity (0 even, 1 odd), w: texel count N
    // x: the first receiving texel, y: how many (every texel, 0 and N, but in a round of a
    // bake in rounds: its region, the other texels holding their light); z, w: unused.
    texels: vec4<u32>,
}

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<uniform> params: GatherParams;
@group(0) @binding(2) var illum: texture_2d_array<f32>;  // one layer per independent depth draw
@group(0) @binding(3) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(4) var<storage, read_write> acc: array<vec4<f32>>;  // 2N: even then odd
// The estimate the resolve pass fed this step at each texel, and its blend with the same
// weights as `acc` (rgb over acc's alpha): the mean of what was fed, per texel, which the
// ambient-mode correction compares with the estimate (sdb/resolve.wgsl).
@group(0) @binding(5) var<storage, read> fed: array<vec4<f32>>;           // N
@group(0) @binding(6) var<storage, read_write> fed_acc: array<vec4<f32>>;  // 2N
// Only with gather_direct: the illumination map's emitted-radiance target and the
// direct-light accumulators (direct = light straight from an emitter or the sky).
@group(1) @binding(0) var illum_emission: texture_2d_array<f32>;
@group(1) @binding(1) var<storage, read_write> direct_acc: array<vec4<f32>>;  // 2N, rgb over acc's alpha

struct Gathered {
    contribution: vec3<f32>,  // 4 L max(<d, n>, 0)
    weight: f32,              // 4 max(<d, n>, 0)
    best: vec2<i32>,          // winning map pixel, or (-1, -1) for the environment
    best_layer: i32,
}

fn gather_texel(i: u32) -> Gathered {
    var g: Gathered;
    g.contribution = vec3<f32>(0.0);
    g.weight = 0.0;
    g.best = vec2<i32>(-1);
    g.best_layer = 0;
    let x = texels[i].position.xyz;
    let n = texels[i].normal.xyz;
    let ng = texels[i].geo_normal.xyz;
    let d = view.dir.xyz;
    let cos_theta = dot(n, d);
    // Below the geometric surface the surface itself blocks the direction (as in the
    // `path` reference), whatever the interpolated shading normal says.
    if cos_theta <= 0.0 || dot(ng, d) <= 0.0 {
        return g;
    }
    let tx = dot(x, d);
    let centre = vec2<i32>(floor(project_to_map(view, x)));
    let size = i32(view.extent.z);
    let r = i32(params.misc.x);
    var best_t = EMPTY_T;
    var best = params.env.rgb;
    let layers = i32(params.misc.y);
    for (var layer = 0; layer < layers; layer++) {
        for (var dy = -r; dy <= r; dy++) {
            for (var dx = -r; dx <= r; dx++) {
                let px = centre + vec2<i32>(dx, dy);
                if any(px < vec2<i32>(0)) || any(px >= vec2<i32>(size)) {
                    continue;
                }
                let s = textureLoad(illum, px, layer, 0);
                if s.a >= 0.5 * EMPTY_T || s.a >= best_t {
                    continue;
                }
                let p = map_sample_position(view, px, s.a);
                if s.a - tx > params.eps.y && dot(p - x, ng) > params.eps.x {
                    best_t = s.a;
                    best = s.rgb;
                    g.best = px;
                    g.best_layer = layer;
                }
            }
        }
    }
    g.weight = 4.0 * cos_theta;
    g.contribution = best * g.weight;
    return g;
}

// Every direction blends, including the ones facing away from the texel, whose
// estimator value is zero.
fn blend_into(slot: u32, i: u32, value: vec3<f32>, weight: f32) {
    let b = params.env.w;
    acc[slot] = acc[slot] * (1.0 - b) + vec4<f32>(value, weight) * b;
    fed_acc[slot] = fed_acc[slot] * (1.0 - b) + vec4<f32>(fed[i].rgb * weight, 0.0) * b;
}

@compute @workgroup_size(64)
fn gather(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let k = invocation_index(wid, nwg, lid);
    let n_texels = params.misc.w;
    if k >= params.texels.y {
        return;
    }
    let i = params.texels.x + k;
    let g = gather_texel(i);
    blend_into(params.misc.z * n_texels + i, i, g.contribution, g.weight);
}

@compute @workgroup_size(64)
fn gather_direct(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let k = invocation_index(wid, nwg, lid);
    let n_texels = params.misc.w;
    if k >= params.texels.y {
        return;
    }
    let i = params.texels.x + k;
    let g = gather_texel(i);
    let slot = params.misc.z * n_texels + i;
    blend_into(slot, i, g.contribution, g.weight);
    // Direct part: the environment on a miss, the winner's emission on a hit.
    var direct = params.env.rgb * g.weight;
    if g.best.x >= 0 {
        direct = textureLoad(illum_emission, g.best, g.best_layer, 0).rgb * g.weight;
    }
    let b = params.env.w;
    direct_acc[slot] = vec4<f32>(direct_acc[slot].rgb * (1.0 - b) + direct * b, 0.0);
}
