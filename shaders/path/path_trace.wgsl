// path/path_trace.wgsl: `path` on the GPU, as one megakernel: one invocation per valid
// texel runs that texel's samples of the step, each a whole path (path/estimator.wgsl's
// `radiance`, the CPU's estimator line for line), and blends the mean into the step's half
// accumulator (src/engine/technique/path/gpu.rs). Randomness, precision and bounds:
// path/estimator.wgsl's header.

@group(0) @binding(5) var<uniform> pu: PathUniform;
@group(0) @binding(6) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(7) var<storage, read_write> acc_total: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> acc_direct: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read_write> acc_moment: array<vec4<f32>>;
// Per 4-D set of the sequence (64), its 16 reversed direction numbers, one vec4 (the set's
// four dimensions) each: set * 16 + bit.
@group(0) @binding(10) var<storage, read> sobol_vectors: array<vec4<u32>>;


@compute @workgroup_size(64)
fn trace(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    // A step runs as one dispatch or in slices (TexelRayPass::step_sliced): this
    // dispatch's invocations are texels slice.x, slice.x + 1, … (slice.y of them).
    let j = invocation_index(wid, nwg, lid);
    let i = pu.slice.x + j;
    let n = pu.counts.x;
    if j >= pu.slice.y || i >= n {
        return;
    }
    let t = texels[i];
    var total = vec3<f32>(0.0);
    var direct = vec3<f32>(0.0);
    var m0 = vec3<f32>(0.0);
    var m1 = vec3<f32>(0.0);
    var m2 = vec3<f32>(0.0);
    let spp = pu.counts.y;
    var ran = 0u;
    var cut = false;
    for (var s = 0u; s < spp; s++) {
        let pixel = bitcast<u32>(t.position.w);
        var rng = rng_for(pixel, s);
        let r = radiance(t.position.xyz, t.normal.xyz, t.geo_normal.xyz, &rng, sobol_point(pixel, s));
        ran += 1u;
        cut = cut || r.cut;
        total += r.total;
        direct += r.direct;
        m0 += r.m.m0;
        m1 += r.m.m1;
        m2 += r.m.m2;
    }
    let k = 1.0 / f32(spp);
    let slot = pu.keys.z * n + i;
    acc_total[slot] = blend(acc_total[slot], total * k);
    // A sample loop or a path ended from outside (llvmpipe's loop budget, see the header):
    // marked in w, which the host checks at every snapshot rather than deliver it dark.
    if cut || ran < spp {
        acc_total[slot].w = 1.0;
    }
    if (pu.keys.w & PATH_DIRECT) != 0u {
        acc_direct[slot] = blend(acc_direct[slot], direct * k);
    }
    if (pu.keys.w & PATH_MOMENTS) != 0u {
        acc_moment[slot * 3u] = blend(acc_moment[slot * 3u], m0 * k);
        acc_moment[slot * 3u + 1u] = blend(acc_moment[slot * 3u + 1u], m1 * k);
        acc_moment[slot * 3u + 2u] = blend(acc_moment[slot * 3u + 2u], m2 * k);
    }
}
