// gpu/shadowmask.wgsl: the shadowmask pass (src/engine/gpu/shadowmask.rs, issue 26 point 3).
// One invocation per valid texel estimates, for each of up to four chosen lights (one per
// channel), the light's baked visibility V in 0..1 and, summed over the chosen lights, the
// direct light E/pi they bring (shadowed), which the bake takes out of the lightmap so that
// a renderer adding those lights in real time, times V, does not count them twice.
//
// Visibility is the fraction of the light's samples that leave the texel's sample point in
// front of both its normals and reach the light unoccluded: for the job's sun, directions
// uniform over its disc's solid angle (gpu/lights.wgsl `cone_sample`, as its next-event
// estimate draws them), so the penumbra is the disc's; for the scene's directional, point
// and spot lights (deltas in KHR_lights_punctual: no size), the one ray to the light, so V
// is 0 or 1 at the sample point. E uses the same rays and the same terms as `next_event`,
// so it is an estimate of exactly what a technique's direct light holds of those lights.
// V is unweighted by the cosine on purpose: it is what a renderer multiplies its own
// N.L-weighted light by (over the sun's 0.5 degree the two differ by < 1e-4).
//
// Randomness: gpu/lights.wgsl's PCG streams, keyed like gpu/direct_light.wgsl (seed, texel,
// step, sample) with a salt of their own, so no stream is shared with the technique's,
// the direct-light pass's or the control texels'. Bounds: `samples` per step is capped on
// the host (64) and the delta lights cost one ray a texel a step, so an invocation stays far
// inside llvmpipe's loop budget. Precision: world space f32; running means in f32.

struct MaskUniform {
    counts: vec4<u32>,  // x: valid texels n, y: sun samples per step, z: step index, w: half (0 even, 1 odd)
    keys: vec4<u32>,    // x: seed low 32 bits, y: seed high; z: chosen lights (1..4); w: unused
    lights: vec4<u32>,  // per channel: MASK_SUN, or the index of the scene light (gpu/lights.wgsl's table)
    f: vec4<f32>,       // x: blend 1/k of the half's k-th step; y, z, w: unused
}

@group(0) @binding(5) var<uniform> mu: MaskUniform;
@group(0) @binding(6) var<storage, read> texels: array<TexelGeom>;
// 4n vec4: per half (even then odd) and texel, two vec4: visibility of channels 0-3, then
// rgb E/pi of the chosen lights together (w unused).
@group(0) @binding(7) var<storage, read_write> acc: array<vec4<f32>>;

const MASK_SUN: u32 = 0xffffffffu;

fn mask_rng(texel: u32, sample: u32) -> Rng {
    let base = pcg(mu.keys.x ^ pcg(mu.keys.y ^ 0x5bd1e995u));
    var r = Rng(pcg(mu.counts.z ^ pcg(sample ^ base)), (pcg(texel ^ pcg(base ^ 0x27d4eb2fu)) << 1u) | 1u);
    rng_next(&r);
    return r;
}

struct Seen {
    visible: f32,
    light: vec3<f32>,
}

// One scene light (directional, point or spot) from x: visible or not, and E/pi as
// gpu/lights.wgsl's next_event adds it.
fn scene_light(li: u32, x: vec3<f32>, n: vec3<f32>, ng: vec3<f32>) -> Seen {
    let base = scene_u.tables.y + li * 4u;
    let intensity = tables[base].xyz;
    let kind = bitcast<u32>(tables[base].w);
    if kind == LIGHT_DIRECTIONAL {
        let d = -tables[base + 2u].xyz;
        if front_of(d, n, ng) && bvh_unoccluded(x, d, RAY_FAR) {
            return Seen(1.0, intensity * dot(d, n) * INV_PI);
        }
        return Seen(0.0, vec3<f32>(0.0));
    }
    let to = tables[base + 1u].xyz - x;
    let dist2 = dot(to, to);
    if dist2 <= 0.0 {
        return Seen(0.0, vec3<f32>(0.0));
    }
    let dist = sqrt(dist2);
    let d = to / dist;
    if !front_of(d, n, ng) || !bvh_unoccluded(x, d, dist * (1.0 - 1e-4)) {
        return Seen(0.0, vec3<f32>(0.0));
    }
    let falloff = light_attenuation(li, dist, -d) / dist2;
    return Seen(1.0, intensity * falloff * dot(d, n) * INV_PI);
}

@compute @workgroup_size(64)
fn shadowmask(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    let n = mu.counts.x;
    if i >= n {
        return;
    }
    let t = texels[i];
    let x = t.position.xyz;
    let nrm = t.normal.xyz;
    let ng = t.geo_normal.xyz;
    var vis = vec4<f32>(0.0);
    var e = vec3<f32>(0.0);
    let spp = max(mu.counts.y, 1u);
    for (var c = 0u; c < min(mu.keys.z, 4u); c++) {
        let which = mu.lights[c];
        if which != MASK_SUN {
            let s = scene_light(which, x, nrm, ng);
            vis[c] = s.visible;
            e += s.light;
            continue;
        }
        if scene_u.sun.w <= 0.0 {
            continue;
        }
        var seen = 0.0;
        var sun = vec3<f32>(0.0);
        for (var s = 0u; s < spp; s++) {
            var rng = mask_rng(i, s);
            let u1 = rng_next(&rng);
            let u2 = rng_next(&rng);
            let d = cone_sample(scene_u.sun_axis.xyz, scene_u.sun_axis.w, u1, u2);
            if front_of(d, nrm, ng) && bvh_unoccluded(x, d, RAY_FAR) {
                seen += 1.0;
                // next_event's sun term with weight 1: L cos / pi over the disc's density.
                sun += scene_u.sun.xyz * dot(d, nrm) * INV_PI * scene_u.sun.w;
            }
        }
        let k = 1.0 / f32(spp);
        vis[c] = seen * k;
        e += sun * k;
    }
    let slot = 2u * (mu.counts.w * n + i);
    let old_v = acc[slot];
    let old_e = acc[slot + 1u];
    acc[slot] = old_v + (vis - old_v) * mu.f.x;
    acc[slot + 1u] = old_e + (vec4<f32>(e, 0.0) - old_e) * mu.f.x;
}
