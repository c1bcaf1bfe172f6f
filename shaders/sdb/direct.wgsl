// sdb/direct.wgsl: direct light from the sun and directional lights through a shadow map.
// Gathering along random directions cannot find a light source of near-zero solid angle
// (the seed's section 7 suggests shadow mapping for exactly this), so each such light
// gets an orthographic map along its direction of travel in the shared shadow-map atlas
// (gpu/shadow_atlas.wgsl: every pixel keeps the plane of the nearest surface) and this pass
// adds E/pi = irradiance/pi * max(<n, -d>, 0) * visibility to its own accumulators (the
// gather's are self-normalised by their cosine weights, which a light of one direction
// has no part in); the resolve pass adds both, so the illumination pass picks this light
// up for the next bounces. The sun's direction is jittered over its disc per step (on the
// CPU), so penumbrae converge like everything else. Visibility is the atlas's own test
// (gpu/shadow_view.wgsl's shadow_ortho: 2x2 percentage-closer filtering of "is the receiver
// behind the nearest surface's plane"), the receiver moved along its geometric normal by
// `bias.x` map pixels against self-shadowing on tessellated curved surfaces.

struct DirectParams {
    irradiance: vec4<f32>,  // rgb: E/pi on a surface facing the light, unshadowed; w: the direction's blend b (see sdb/gather.wgsl)
    bias: vec4<f32>,        // x: receiver offset along the geometric normal (map pixels); y: unused; z: decay: 1 - b for the direction's first light, 1 for the others (they add to the same blend); w: unused
    misc: vec4<u32>,        // x: parity, y: texel count N, z: first receiving texel, w: how many (sdb/gather.wgsl's `texels`)
}

@group(0) @binding(0) var<storage, read> views: array<ShadowView>;  // one: the light's map
@group(0) @binding(1) var<uniform> params: DirectParams;
@group(0) @binding(2) var atlas: texture_2d<f32>;
@group(0) @binding(3) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(4) var<storage, read_write> sun_acc: array<vec4<f32>>;  // 2N: rgb E/pi from these lights

@compute @workgroup_size(64)
fn direct(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let k = invocation_index(wid, nwg, lid);
    let n_texels = params.misc.y;
    if k >= params.misc.w {
        return;
    }
    let i = params.misc.z + k;
    let n = texels[i].normal.xyz;
    let v = views[0];
    let d = v.fwd.xyz;
    let ng = texels[i].geo_normal.xyz;
    let cos_theta = -dot(n, d);
    var e = vec3<f32>(0.0);
    if cos_theta > 0.0 && -dot(ng, d) > 0.0 {
        let vis = shadow_ortho(atlas, v, texels[i].position.xyz, ng, params.bias.x);
        e = params.irradiance.rgb * cos_theta * vis;
    }
    let slot = params.misc.x * n_texels + i;
    let scale = params.irradiance.w;
    sun_acc[slot] = vec4<f32>(sun_acc[slot].rgb * params.bias.z + e * scale, 0.0);
}

// `emitter_add`: direct light from emitters smaller than a map pixel, which the map cannot
// resolve (one pixel, dilated k x k, would stand for them), and point and spot lights. The
// shared direct-light pass (gpu/direct_light.wgsl, shadow rays through the BVH) estimates
// them per texel, keeping each half's latest step (`sdb/lights.rs`, `SmallLights`); this
// pass folds that estimate into the same accumulators as the sun, as one more blend of the
// step: acc = acc * decay + sample * weight, where decay is what the step's directions
// have left of the old blend (already applied when directional lights blended this step)
// and weight = 1 - prod(1 - b) over the step's directions, the step's share of the mean.
struct EmitterAddParams {
    mix: vec4<f32>,   // x: decay, y: weight; z, w: unused
    misc: vec4<u32>,  // x: parity, y: texel count N, z: first receiving texel, w: how many
}

// 2 N: the even half's texels, then the odd half's; rgb E/pi (w: the pass's hit fraction).
@group(0) @binding(5) var<storage, read> emitter_samples: array<vec4<f32>>;
@group(0) @binding(6) var<uniform> emitter_params: EmitterAddParams;

@compute @workgroup_size(64)
fn emitter_add(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let k = invocation_index(wid, nwg, lid);
    let n_texels = emitter_params.misc.y;
    if k >= emitter_params.misc.w {
        return;
    }
    let i = emitter_params.misc.z + k;
    let slot = emitter_params.misc.x * n_texels + i;
    let m = emitter_params.mix;
    sun_acc[slot] = vec4<f32>(sun_acc[slot].rgb * m.x + emitter_samples[slot].rgb * m.y, 0.0);
}
