// obscurance/direct.wgsl: direct light from the sun and directional lights through a
// shadow map (obscurance/layers.wgsl, fs_shadow). Parallel bundles cannot find a light
// of near-zero solid angle, so each such light gets a nearest-depth orthographic map
// along its direction of travel and this pass adds E/pi = irradiance/pi max(<n, -d>, 0)
// visibility to the sun part of the direct accumulator, after the gather decayed it by
// (1 - b) for this direction (hence `+ e b`: a running mean over directions). 2x2 percentage-closer filtering, a receiver
// offset of one map pixel along the normal and a depth bias of two, both relative to the
// pixel size, against shadow acne at grazing angles. The sun's direction is jittered
// over its disc per step on the CPU, so penumbrae converge like the rest.

struct DirectParams {
    irradiance: vec4<f32>,  // rgb: E/pi on a surface facing the light; w: blend b
    bias: vec4<f32>,        // x: receiver offset along the normal, y: depth bias (normalised units); z, w: unused
    misc: vec4<u32>,        // x: parity, y: texels to process, z: texel count N, w: 1 = process `subset`
}

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<uniform> params: DirectParams;
@group(0) @binding(2) var shadow: texture_2d_array<f32>;
@group(0) @binding(3) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(4) var<storage, read_write> direct_acc: array<vec4<f32>>;  // 4N; this pass adds to [2N, 4N)
@group(0) @binding(5) var<storage, read> subset: array<u32>;

fn lit(px: vec2<i32>, t: f32) -> f32 {
    let size = i32(view.extent.z);
    let q = clamp(px, vec2<i32>(0), vec2<i32>(size - 1));
    let s = textureLoad(shadow, q, 0, 0);
    return select(0.0, 1.0, t <= s.r + params.bias.y);
}

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
    let d = view.dir.xyz;
    let cos_theta = -dot(n, d);
    if cos_theta <= 0.0 || -dot(ng, d) <= 0.0 {
        return;
    }
    let x = texels[i].position.xyz + ng * params.bias.x;
    let t = dot(x, d);
    let f = project_to_map(view, x) - 0.5;
    let base = floor(f);
    let w = f - base;
    let p = vec2<i32>(base);
    let vis = mix(mix(lit(p, t), lit(p + vec2<i32>(1, 0), t), w.x),
                  mix(lit(p + vec2<i32>(0, 1), t), lit(p + vec2<i32>(1, 1), t), w.x), w.y);
    let slot = 2u * params.misc.z + params.misc.x * params.misc.z + i;
    let e = params.irradiance.rgb * cos_theta * vis * params.irradiance.w;
    direct_acc[slot] = vec4<f32>(direct_acc[slot].rgb + e, direct_acc[slot].a);
}
