// obscurance/gather.wgsl: one global direction's obscurance, colour bleeding and direct
// light for every texel (seed sections 2-4, Eqs. 2 and 4).
//
// Each texel x with normal n looks along s = sign(<n, d>) d, so one bundle serves both
// hemispheres: texels facing +d transfer with the next layer farther along d, texels
// facing -d with the previous one (the seed's two-pass transfer in both directions).
// It projects x into the map, walks its pixel's fragment list (obscurance/layers.wgsl)
// and keeps the nearest fragment beyond x along s that lies above x's geometric normal
// plane (that rejects x's own surface, which sits in the list at about t = <x, d>): the
// consecutive layer. The seed's facing tests follow: the layer must face x (its
// front-facing bit against s) or be double-sided; a layer showing x its back is a black
// blocker (no reflectivity, no emission, distance counts), where the seed dropped the
// pair, so light does not leak through the back of open single-sided geometry.
//
// For a hit at distance d: the obscurance term rho(d / dmax) (1 from dmax on), the
// colour-bleeding term R(Q) rho(d/dmax) below dmax and R_ave from dmax on (Eq. 4), and
// the emitted radiance of Q (direct light from emitters). For no hit: obscurance 1, the
// colour term R_ave with `background = ambient` (the seed) or 0 with `none`, and the
// environment's radiance along s (direct sky light; the CPU evaluates it once per
// direction for +d and -d).
//
// Estimator: for d uniform on the sphere, |<n, d>| f(s) / mean |<n, d>| estimates
// (1/pi) * integral over the hemisphere of f cos(theta) (both signs of d are used): the
// seed's "added and averaged" ratio, sum of f w over sum of w with w = |<n, d>|. The
// ratio is exact for constant f (an open plane reads exactly its sky, a closed box's
// hit fraction is exactly 1) and consistent otherwise. Each half keeps running means of
// numerator and denominator, acc = acc (1 - b) + value b with b = 1/k for its k-th
// direction, so f32 loses no precision over many directions; the CPU divides.
//
// Influence record (seed section 5): a hit ORs bits for the mesh hit into the texel's
// mask (16 + mesh mod 16 at any distance, mesh mod 16 within dmax), so an incremental
// update can find the texels a mesh influenced.

struct Node {
    t: f32,
    tri: u32,
    lightmap: u32,
    next: u32,
}

struct GatherParams {
    env_fwd: vec4<f32>,   // rgb: environment radiance seen looking along +d; w: blend b
    env_back: vec4<f32>,  // rgb: looking along -d; w: dmax (normalised scene units)
    r_ave: vec4<f32>,     // rgb: area-weighted mean reflectivity R_ave; w: along-d epsilon
    misc: vec4<u32>,      // x: parity, y: texels to process, z: falloff (FALLOFF_*), w: flags (FLAG_*)
    dims: vec4<u32>,      // x: lightmap pixels W*H, y: texel count N, z: node capacity, w: normal-plane epsilon (f32 bits)
}

const FALLOFF_SQRT: u32 = 0u;
const FALLOFF_LINEAR: u32 = 1u;
const FALLOFF_STEP: u32 = 2u;
const FALLOFF_EXP: u32 = 3u;
const FLAG_BACKGROUND_AMBIENT: u32 = 1u;
const FLAG_SUBSET: u32 = 2u;

const TRI_TEXTURED_ALBEDO: u32 = 8u;
const TRI_SAMPLED_EMISSION: u32 = 16u;  // its emission comes from the shared direct-light module
const NO_NODE: u32 = 0xffffffffu;
// counters[]: 0 fragments this direction, 1 most fragments in any direction, 2 longest
// list a texel walked, 3 directions that overflowed the node pool; masks from 4 on.
const MASK_BASE: u32 = 4u;

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<uniform> params: GatherParams;
@group(0) @binding(2) var<storage, read> heads: array<u32>;
@group(0) @binding(3) var<storage, read> nodes: array<Node>;
@group(0) @binding(4) var<storage, read> texels: array<TexelGeom>;
// [0, WH): albedo per lightmap pixel (a: coverage); [WH, 2WH): emission per pixel;
// then per triangle two entries: (albedo, flags bits), (emission, mesh bits).
@group(0) @binding(5) var<storage, read> materials: array<vec4<f32>>;
// [0, 2N): rgb colour-bleeding W w, a obscurance w; [2N, 4N): x the weight w.
@group(0) @binding(6) var<storage, read_write> acc: array<vec4<f32>>;
// [0, 2N): rgb emitted/sky radiance seen w, a hit w; [2N, 4N): rgb sun and directional
// light (a plain running mean, added by obscurance/direct.wgsl after this pass decays it).
@group(0) @binding(7) var<storage, read_write> direct_acc: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> counters: array<atomic<u32>>;
@group(0) @binding(9) var<storage, read> subset: array<u32>;  // texels to process with FLAG_SUBSET

// rho(x), x = d / dmax in [0, 1): the seed's sqrt, or another increasing function from
// 0 to 1 (`falloff` parameter).
fn falloff(x: f32, kind: u32) -> f32 {
    switch kind {
        case FALLOFF_LINEAR: { return x; }
        case FALLOFF_STEP: { return 0.0; }
        case FALLOFF_EXP: { return (1.0 - exp(-4.0 * x)) / (1.0 - exp(-4.0)); }
        default: { return sqrt(x); }
    }
}

@compute @workgroup_size(64)
fn gather(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let k = invocation_index(wid, nwg, lid);
    if k == 0u {
        let used = atomicLoad(&counters[0]);
        atomicMax(&counters[1], used);
        if used > params.dims.z {
            atomicAdd(&counters[3], 1u);
        }
    }
    if k >= params.misc.y {
        return;
    }
    var i = k;
    if (params.misc.w & FLAG_SUBSET) != 0u {
        i = subset[k];
    }
    let n_texels = params.dims.y;
    let slot = params.misc.x * n_texels + i;
    let b = params.env_fwd.w;
    let x = texels[i].position.xyz;
    let n = texels[i].normal.xyz;
    let ng = texels[i].geo_normal.xyz;
    let d = view.dir.xyz;
    let c = dot(n, d);
    var w_value = vec4<f32>(0.0);
    var d_value = vec4<f32>(0.0);
    var weight = 0.0;
    // Shading and geometric normals must agree on the side, as in the `path` reference.
    if c * dot(ng, d) > 0.0 {
        let sgn = sign(c);
        weight = abs(c);
        let tx = dot(x, d);
        let size = i32(view.extent.z);
        let px = vec2<i32>(floor(project_to_map(view, x)));
        var best_dt = 3.0e38;
        var best = NO_NODE;
        if all(px >= vec2<i32>(0)) && all(px < vec2<i32>(size)) {
            var node = heads[u32(px.y) * u32(size) + u32(px.x)];
            var layers = 0u;
            loop {
                if node == 0u {
                    break;
                }
                let nd = nodes[node - 1u];
                layers++;
                let dt = (nd.t - tx) * sgn;
                if dt > params.r_ave.w && dt < best_dt {
                    let p = map_sample_position(view, px, nd.t);
                    if dot(p - x, ng) > bitcast<f32>(params.dims.w) {
                        best_dt = dt;
                        best = node - 1u;
                    }
                }
                node = nd.next;
            }
            atomicMax(&counters[2], layers);
        }
        if best != NO_NODE {
            let nd = nodes[best];
            let tri = nd.tri >> 1u;
            let front = (nd.tri & 1u) != 0u;
            let toff = 2u * params.dims.x + 2u * tri;
            let rec0 = materials[toff];
            let rec1 = materials[toff + 1u];
            let flags = bitcast<u32>(rec0.w);
            var albedo = rec0.rgb;
            var emission = rec1.rgb;
            if (flags & TRI_TEXTURED_ALBEDO) != 0u && materials[nd.lightmap].a > 0.0 {
                albedo = materials[nd.lightmap].rgb;
            }
            if (flags & TRI_TEXTURED_EMISSION) != 0u && materials[nd.lightmap].a > 0.0 {
                emission = materials[params.dims.x + nd.lightmap].rgb;
            }
            // Front-facing means facing -d: the layer faces x when x looks along +d.
            let facing = (front == (sgn > 0.0)) || (flags & TRI_DOUBLE_SIDED) != 0u;
            if !facing || (flags & TRI_SAMPLED_EMISSION) != 0u {
                emission = vec3<f32>(0.0);
            }
            if !facing {
                albedo = vec3<f32>(0.0);
            }
            let dmax = params.env_back.w;
            var rho = 1.0;
            var colour = params.r_ave.rgb;
            if best_dt < dmax {
                rho = falloff(best_dt / dmax, params.misc.z);
                colour = albedo * rho;
            }
            w_value = vec4<f32>(colour, rho) * weight;
            d_value = vec4<f32>(emission, 1.0) * weight;
            // Bit 16 + (mesh mod 16): hit at any distance; bit (mesh mod 16): within dmax.
            let bit = bitcast<u32>(rec1.w) & 15u;
            atomicOr(&counters[MASK_BASE + i], (1u << (16u + bit)) | select(0u, 1u << bit, best_dt < dmax));
        } else {
            let env = select(params.env_back.rgb, params.env_fwd.rgb, sgn > 0.0);
            var colour = vec3<f32>(0.0);
            if (params.misc.w & FLAG_BACKGROUND_AMBIENT) != 0u {
                colour = params.r_ave.rgb;
            }
            w_value = vec4<f32>(colour, 1.0) * weight;
            d_value = vec4<f32>(env, 0.0) * weight;
        }
    }
    acc[slot] = acc[slot] * (1.0 - b) + w_value * b;
    direct_acc[slot] = direct_acc[slot] * (1.0 - b) + d_value * b;
    let slot2 = 2u * n_texels + slot;
    acc[slot2] = vec4<f32>(acc[slot2].x * (1.0 - b) + weight * b, 0.0, 0.0, 0.0);
    direct_acc[slot2] = direct_acc[slot2] * (1.0 - b);
}
