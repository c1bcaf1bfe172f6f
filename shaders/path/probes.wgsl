// path/probes.wgsl: light probes on the GPU (src/engine/technique/path/probes_gpu.rs), the
// CPU's probe estimator (technique::path::probes, `ProbeBaker::sample`) line for line:
// per sample one uniform direction on the sphere whose radiance is the sky, black on the
// back of a single-sided surface, or the hit's emission (power heuristic against the
// emitter sample below) plus its albedo times `path`'s E/pi there (path/estimator.wgsl's
// `radiance`, the texels' estimator); then every directional, point and spot light and
// the sun's cone by a shadow ray each, and one emissive triangle picked by the bake's
// emitter table; each weighted by the real SH basis to L2 at its direction
// (technique::path::probes's order and normalisation).
//
// Layout: one workgroup of 64 invocations per probe, invocation `lane` running the step's
// samples lane, lane + 64, ... (one each at the job's 64 samples a step), so a step of a
// few thousand probes still fills a GPU, and no invocation runs long enough to meet
// llvmpipe's loop budget (path/estimator.wgsl's header). The 64 lanes' sums are added in
// workgroup memory by a tree reduction (6 halvings); lane 0 blends their mean into the
// step's half accumulator: per probe and half, 9 vec4 (RGB, coefficient order of sh9);
// w of coefficient 0 marks samples cut from outside, which the host refuses.
//
// Randomness, as the CPU's probes: with `sampling: sobol` (PATH_SOBOL, the default) each
// probe and half has its own Owen-scrambled Sobol sequence (path/estimator.wgsl's
// `sobol_point`, keyed by the probe's index in the job's list, position.w's bits); the
// probe's own direction, sun and emitter samples take vertex 0's two sets and the path
// from a hit goes on from vertex 1. With `independent`, the PCG stream (`rng_for`, the
// same key, the step and the sample). GPU and CPU probes agree in the mean, not sample for
// sample (the scrambles and streams are hashed differently). Precision: world space f32; a
// probe's sum over 64 lanes and its mean over the step's samples in f32 (relative rounding
// 1e-7 per addition, far below a step's noise).

@group(0) @binding(5) var<uniform> pu: PathUniform;
// The valid probes: position.xyz in world space, position.w the probe's index as u32 bits.
@group(0) @binding(6) var<storage, read> probes: array<TexelGeom>;
// Per half and probe, 9 vec4: (half * n + probe) * 9 + coefficient.
@group(0) @binding(7) var<storage, read_write> acc_sh: array<vec4<f32>>;
// Bound because `radiance` can read it; unused here (no PATH_SOBOL).
@group(0) @binding(8) var<storage, read> sobol_vectors: array<vec4<u32>>;

const PROBE_LANES: u32 = 64u;
const SH_COEFFS: u32 = 9u;
const FOUR_PI: f32 = 12.5663706144;

// Lane * 9 + coefficient; w of a lane's coefficient 0 counts its cut samples.
var<workgroup> partial: array<vec4<f32>, 576>;

// probes::sh9: the real SH basis to L2 at unit direction w.
fn sh9(w: vec3<f32>) -> array<f32, 9> {
    return array<f32, 9>(
        0.282095,
        0.488603 * w.y,
        0.488603 * w.z,
        0.488603 * w.x,
        1.092548 * w.x * w.y,
        1.092548 * w.y * w.z,
        0.315392 * (3.0 * w.z * w.z - 1.0),
        1.092548 * w.x * w.z,
        0.546274 * (w.x * w.x - w.y * w.y),
    );
}

fn uniform_sphere(u1: f32, u2: f32) -> vec3<f32> {
    let z = 1.0 - 2.0 * u1;
    let r = sqrt(max(1.0 - z * z, 0.0));
    let phi = TWO_PI * u2;
    return vec3<f32>(r * cos(phi), r * sin(phi), z);
}

fn add_sh(sum: ptr<function, array<vec3<f32>, 9>>, l: vec3<f32>, w: vec3<f32>, weight: f32) {
    let y = sh9(w);
    for (var c = 0u; c < SH_COEFFS; c++) {
        (*sum)[c] += l * (y[c] * weight);
    }
}

// One sample's SH estimate at `x` into `sum`; true when a ray or path was cut from
// outside (the traversal's overflow or the adapter's loop budget).
fn probe_sample(x: vec3<f32>, rng: ptr<function, Rng>, sp: SobolPoint, sum: ptr<function, array<vec3<f32>, 9>>) -> bool {
    var cut = false;
    let eps = pu.f.y;
    // The probe's own numbers: vertex 0's two Sobol sets, in the texel path's layout
    // (direction, direction, emitter point, emitter point) and (emitter pick, sun, sun, -),
    // or the stream's; the path from a hit goes on from vertex 1 (`first`).
    var a = vec4<f32>(0.0);
    var b = vec4<f32>(0.0);
    if sp.on {
        a = sobol_4d(sp.index, 0u, sp.scramble);
        b = sobol_4d(sp.index, 1u, sp.scramble);
    } else {
        a = vec4<f32>(rng_next(rng), rng_next(rng), rng_next(rng), rng_next(rng));
        b = vec4<f32>(rng_next(rng), rng_next(rng), rng_next(rng), 0.0);
    }
    // A uniform direction: sky, or a surface's emitted + reflected radiance.
    let w = uniform_sphere(a.x, a.y);
    let hit = bvh_closest(x, w, RAY_FAR);
    if hit.overflow {
        cut = true;
    } else if hit.slot == BVH_MISS {
        add_sh(sum, sky_radiance(w), w, FOUR_PI);
    } else {
        let slot = hit.slot;
        let bary = vec3<f32>(1.0 - hit.u - hit.v, hit.u, hit.v);
        let m = tri_material(slot);
        let geo = tri_geo(slot);
        let front = dot(w, geo) < 0.0;
        if front || mat_double_sided(m) {
            let side = select(-1.0, 1.0, front);
            let ng = geo * side;
            let shading = tri_shading_normal(slot, bary) * side;
            let n = select(ng, shading, dot(shading, ng) > 0.0);
            let p = tri_point(slot, inset(bary)) + ng * eps;
            let r = radiance(p, n, ng, rng, SobolPoint(sp.on, sp.index, sp.scramble, 1u));
            cut = cut || r.cut;
            let emitted = emission_at(slot, bary);
            // The emitter sample below could have drawn this direction too.
            var weight = 1.0;
            if any(emitted != vec3<f32>(0.0)) {
                let cos_l = max(abs(dot(w, geo)), 1.0e-38);
                let pdf_light = tri_pick(slot) / tri_area(slot) * hit.t * hit.t / cos_l;
                weight = power_heuristic(1.0 / FOUR_PI, pdf_light);
            }
            add_sh(sum, emitted * weight + albedo_at(slot, bary) * r.total, w, FOUR_PI);
        }
    }
    // Delta lights and the sun, which uniform directions cannot find.
    for (var li = 0u; li < scene_u.tables.z; li++) {
        let base = scene_u.tables.y + li * 4u;
        let intensity = tables[base].xyz;
        if bitcast<u32>(tables[base].w) == LIGHT_DIRECTIONAL {
            let d = -tables[base + 2u].xyz;
            if bvh_unoccluded(x, d, RAY_FAR) {
                add_sh(sum, intensity, d, 1.0);
            }
        } else {
            let to = tables[base + 1u].xyz - x;
            let dist2 = dot(to, to);
            if dist2 > 0.0 {
                let dist = sqrt(dist2);
                let d = to / dist;
                let falloff = light_attenuation(li, dist, -d) / dist2;
                if falloff > 0.0 && bvh_unoccluded(x, d, dist * (1.0 - 1e-4)) {
                    add_sh(sum, intensity * falloff, d, 1.0);
                }
            }
        }
    }
    if scene_u.sun.w > 0.0 {
        let d = cone_sample(scene_u.sun_axis.xyz, scene_u.sun_axis.w, b.y, b.z);
        if bvh_unoccluded(x, d, RAY_FAR) {
            add_sh(sum, scene_u.sun.xyz, d, scene_u.sun.w);
        }
    }
    // One emitter sample, weighted against the uniform direction (power heuristic).
    let count = scene_u.tables2.x;
    if count > 0u {
        let slot = emitter_pick(b.x);
        let bary = uniform_bary(a.zw);
        let to = tri_point(slot, bary) - x;
        let dist2 = dot(to, to);
        let dist = sqrt(dist2);
        if dist > 0.0 {
            let d = to / dist;
            var cos_l = -dot(d, tri_geo(slot));
            if mat_double_sided(tri_material(slot)) {
                cos_l = abs(cos_l);
            }
            let emitted = emission_at(slot, bary);
            // Stop short of the emitter so it does not occlude its own sample.
            if cos_l > 0.0 && any(emitted != vec3<f32>(0.0)) && bvh_unoccluded(x, d, dist * (1.0 - 1e-4)) {
                let pdf_light = tri_pick(slot) / tri_area(slot) * dist2 / cos_l;
                add_sh(sum, emitted, d, power_heuristic(pdf_light, 1.0 / FOUR_PI) / pdf_light);
            }
        }
    }
    return cut;
}

@compute @workgroup_size(64)
fn probe(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    // One workgroup per probe: `which` is uniform over the workgroup, so the barriers
    // below are reached by all of its invocations or none.
    let which = invocation_index(wid, nwg, lid) / PROBE_LANES;
    let n = pu.counts.x;
    let spp = pu.counts.y;
    var sum: array<vec3<f32>, 9>;
    var cut = 0.0;
    if which < n {
        let t = probes[which];
        let key = bitcast<u32>(t.position.w);
        var ran = 0u;
        for (var s = lid; s < spp; s += PROBE_LANES) {
            var rng = rng_for(key, s);
            if probe_sample(t.position.xyz, &rng, sobol_point(key, s), &sum) {
                cut += 1.0;
            }
            ran += 1u;
        }
        // A sample loop ended from outside (llvmpipe's loop budget) ran fewer samples.
        if lid < spp && ran < (spp - lid + PROBE_LANES - 1u) / PROBE_LANES {
            cut += 1.0;
        }
    }
    for (var c = 0u; c < SH_COEFFS; c++) {
        partial[lid * SH_COEFFS + c] = vec4<f32>(sum[c], select(0.0, cut, c == 0u));
    }
    workgroupBarrier();
    for (var stride = PROBE_LANES / 2u; stride > 0u; stride >>= 1u) {
        if lid < stride {
            for (var c = 0u; c < SH_COEFFS; c++) {
                partial[lid * SH_COEFFS + c] += partial[(lid + stride) * SH_COEFFS + c];
            }
        }
        workgroupBarrier();
    }
    if which < n && lid == 0u {
        let k = 1.0 / f32(spp);
        let base = (pu.keys.z * n + which) * SH_COEFFS;
        for (var c = 0u; c < SH_COEFFS; c++) {
            acc_sh[base + c] = blend(acc_sh[base + c], partial[c].xyz * k);
        }
        if partial[0].w > 0.0 {
            acc_sh[base].w = 1.0;
        }
    }
}
