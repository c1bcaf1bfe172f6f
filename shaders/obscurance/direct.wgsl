// obscurance/direct.wgsl: direct light from the sun and directional lights through a
// shadow map. Parallel bundles cannot find a light of near-zero solid angle, so each such
// light gets an orthographic map along its direction of travel in the shared shadow-map
// atlas (gpu/shadow_atlas.wgsl: every pixel keeps the plane of the nearest surface) and this
// pass adds E/pi = irradiance/pi max(<n, -d>, 0) visibility to the sun part of the direct
// accumulator, after the gather decayed it by (1 - b) for this direction (hence `+ e b`: a
// running mean over directions). Visibility is the atlas's own test (gpu/shadow_view.wgsl's
// shadow_ortho: 2x2 percentage-closer filtering of "is the receiver behind the nearest
// surface's plane"), the receiver moved along its geometric normal by `bias.x` map pixels
// against self-shadowing on tessellated curved surfaces. The sun's direction is jittered
// over its disc per step on the CPU, so penumbrae converge like the rest.

struct DirectParams {
    irradiance: vec4<f32>,  // rgb: E/pi on a surface facing the light; w: blend b
    bias: vec4<f32>,        // x: receiver offset along the geometric normal (map pixels); y, z, w: unused
    misc: vec4<u32>,        // x: parity, y: texels to process, z: texel count N, w: 1 = process `subset`
}

@group(0) @binding(0) var<storage, read> views: array<ShadowView>;  // one: the light's map
@group(0) @binding(1) var<uniform> params: DirectParams;
@group(0) @binding(2) var atlas: texture_2d<f32>;
@group(0) @binding(3) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(4) var<storage, read_write> direct_acc: array<vec4<f32>>;  // 4N; this pass adds to [2N, 4N)
@group(0) @binding(5) var<storage, read> subset: array<u32>;

@compute @workgroup_size(64)
fn direct(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let k = invocation_index(wid, nwg, lid);
    if k >= params.misc.y {
        return;
    }
    var i = k;
    if params.misc.w != 0u {
        i = subset[k];
    }
    let n = texels[i].normal.xyz;
    let ng = texels[i].geo_normal.xyz;
    let v = views[0];
    let d = v.fwd.xyz;
    let cos_theta = -dot(n, d);
    if cos_theta <= 0.0 || -dot(ng, d) <= 0.0 {
        return;
    }
    let vis = shadow_ortho(atlas, v, texels[i].position.xyz, ng, params.bias.x);
    let slot = 2u * params.misc.z + params.misc.x * params.misc.z + i;
    let e = params.irradiance.rgb * cos_theta * vis * params.irradiance.w;
    direct_acc[slot] = vec4<f32>(direct_acc[slot].rgb + e, direct_acc[slot].a);
}
