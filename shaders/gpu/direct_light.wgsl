// gpu/direct_light.wgsl: the shared direct-light pass (src/engine/gpu/direct_light.rs).
// One invocation per valid texel estimates E/pi, the incident irradiance over pi from
// the sources the host selected (scene_u.tables2.z: sun, directional, point and spot
// lights, emitters), with `samples` next-event estimates of gpu/lights.wgsl per step and
// no continuation ray, so every sample is weighted 1 (plain light sampling: unbiased on
// its own, where `path`'s power heuristic needs the continuation's half). The step's mean
// is blended into its half's running mean (even and odd steps, DESIGN section 4).
// With DIRECT_HITS each sample also casts one cosine-distributed ray to any distance and
// w accumulates the fraction that hits a surface (directions below the geometric plane
// count as hits: the surface itself blocks them): the cosine-weighted fraction of the
// hemisphere that sees the scene, which a technique's bounce model weights its ambient by.
//
// Randomness: the PCG-RXS-M-XS 32/32 streams of gpu/lights.wgsl, keyed as `path` keys
// them (increment from the seed and the texel's pixel, state from the seed, step and
// sample) but with a different salt. The pixel, not the texel's place in the list
// (position.w carries it, gpu/texels.rs world_texels): a task baking one region of the
// grid draws the streams a whole bake draws at those texels (engine::tasks), so a technique that runs this pass beside `path`'s control texels
// never shares a stream with them. Bounds: `samples` <= 65535 / (lights + 2) keeps the
// invocation far inside llvmpipe's loop budget (the host caps it); steps in 32 bits.
// Precision: world space f32; running means in f32 (1e-7 relative a step).

struct DirectUniform {
    counts: vec4<u32>,  // x: valid texels n, y: samples per step, z: step index, w: half (0 even, 1 odd)
    keys: vec4<u32>,    // x: seed low 32 bits, y: seed high; z: DIRECT_* flags; w: unused
    f: vec4<f32>,       // x: blend 1/k of the half's k-th step; y, z, w: unused
    slice: vec4<u32>,   // texels: x the dispatch's first, y its count (a sliced step); zw unused
}

@group(0) @binding(5) var<uniform> du: DirectUniform;
@group(0) @binding(6) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(7) var<storage, read_write> acc: array<vec4<f32>>;  // 2n: rgb E/pi, w hit fraction; even half then odd

const DIRECT_HITS: u32 = 1u;

fn direct_rng(texel: u32, sample: u32) -> Rng {
    let base = pcg(du.keys.x ^ pcg(du.keys.y ^ 0x2c1b3c6du));
    var r = Rng(pcg(du.counts.z ^ pcg(sample ^ base)), (pcg(texel ^ pcg(base ^ 0x68e31da4u)) << 1u) | 1u);
    rng_next(&r);
    return r;
}

@compute @workgroup_size(64)
fn direct(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) lid: u32) {
    // A step runs as one dispatch or in slices (TexelRayPass::step_sliced): this
    // dispatch's invocations are texels slice.x, slice.x + 1, ... (slice.y of them).
    let j = invocation_index(wid, nwg, lid);
    let i = du.slice.x + j;
    let n = du.counts.x;
    if j >= du.slice.y || i >= n {
        return;
    }
    let t = texels[i];
    let spp = du.counts.y;
    var e = vec3<f32>(0.0);
    var hits = 0.0;
    let x = t.position.xyz;
    for (var s = 0u; s < spp; s++) {
        var rng = direct_rng(bitcast<u32>(t.position.w), s);
        e += next_event(x, t.normal.xyz, t.geo_normal.xyz, false, &rng).sum;
        if (du.keys.z & DIRECT_HITS) != 0u {
            let u1 = rng_next(&rng);
            let u2 = rng_next(&rng);
            let d = cosine_sample(t.normal.xyz, u1, u2);
            if dot(d, t.geo_normal.xyz) <= 0.0 || !bvh_unoccluded(x, d, RAY_FAR) {
                hits += 1.0;
            }
        }
    }
    let slot = du.counts.w * n + i;
    let old = acc[slot];
    let k = 1.0 / f32(spp);
    acc[slot] = old + (vec4<f32>(e * k, hits * k) - old) * du.f.x;
}
