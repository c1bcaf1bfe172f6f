// vpl/gather.wgsl: every lightmap texel gathers this step's lights (vpl.rs builds the
// list on the CPU): the primary lights (point, spot, the sun, directional lights, sampled
// sky directions) and the step's virtual point lights, each with its shadow map(s) from
// gpu/shadow_atlas.wgsl, and blends the sum into the half accumulator of the step's parity.
//
// E/pi per light (power.rgb is pre-divided on the CPU so that these are the whole formula;
// distances are in normalised scene space and the CPU divided fluxes and intensities by
// the scene radius squared):
//   VPL (hemispherical, flux Phi): Phi / pi^2 * cos_vpl * cos_recv / max(d^2, clamp^2)
//   point / spot (intensity I):     I / pi * window(d) * cone(w) * cos_recv / d^2
//   directional (irradiance E):     E / pi * cos_recv
// The clamp (power.w = clamp^2) bounds a VPL's 1/d^2 singularity: the bias it leaves is
// light lost by receivers nearer than `clamp` to a VPL (docs/vpl.md measures it).
// Punctual lights are exact point sources and are not clamped.
//
// Visibility: 2x2 percentage-closer filtering of the light's map (gpu/shadow_view.wgsl's
// shadow_pcf). Each map pixel holds the plane (n, c) of the nearest surface along its ray
// (gpu/shadow_atlas.wgsl); a tap blocks the light when the light and the receiver lie
// strictly on opposite sides of that plane.
// That is exact for a receiver behind the surface, whatever the wall's thickness (down
// to SIDE_EPS) and the map's resolution; errors remain only within a pixel of
// silhouettes, where a neighbour's plane is extrapolated. A plane through the light (the
// VPL's own surface) never blocks. Receivers are moved along their geometric normal by
// `bias.y` map pixels (at the receiver's distance) against self-shadowing on tessellated
// curved surfaces, where a neighbouring triangle's plane passes just above the receiver.

struct Light {
    pos: vec4<f32>,     // xyz: position of a VPL, point or spot light; w: unused
    axis_t: vec4<f32>,  // xyz: the light's cube frame (t, b, n); w: unused
    axis_b: vec4<f32>,
    axis_n: vec4<f32>,  // xyz: VPL surface normal, spot axis, or a distant light's direction of travel
    power: vec4<f32>,   // rgb: see above; w: VPL only: clamp distance squared
    spot: vec4<f32>,    // x: cos outer cone, y: 1 / (cos inner - cos outer), z: range (0: none); w: unused
    info: vec4<u32>,    // x: LIGHT_*; y: first shadow view or NO_VIEW; z: 1 when direct light; w: unused
}

const LIGHT_VPL: u32 = 0u;
const LIGHT_POINT: u32 = 1u;
const LIGHT_SPOT: u32 = 2u;
const LIGHT_DIRECTIONAL: u32 = 3u;
const NO_VIEW: u32 = 0xffffffffu;

struct GatherParams {
    misc: vec4<u32>,   // x: parity, y: texel count N, z: light count; w: unused
    bias: vec4<f32>,   // x: blend b (1 / steps in this half), y: normal offset (pixels); z, w: unused
    slice: vec4<u32>,  // x: this dispatch's first texel, y: its texel count (a sliced step, gpu::slices); zw unused
}

@group(0) @binding(0) var<uniform> params: GatherParams;
@group(0) @binding(1) var<storage, read> lights: array<Light>;
@group(0) @binding(2) var<storage, read> views: array<ShadowView>;
@group(0) @binding(3) var atlas: texture_2d<f32>;
@group(0) @binding(4) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(5) var<storage, read_write> acc: array<vec4<f32>>;         // 2N, everything
@group(0) @binding(6) var<storage, read_write> direct_acc: array<vec4<f32>>;  // 2N, direct light only

fn visibility_ortho(v: ShadowView, x: vec3<f32>, ng: vec3<f32>) -> f32 {
    return shadow_ortho(atlas, v, x, ng, params.bias.y);
}

fn visibility_cube(l: Light, x: vec3<f32>, ng: vec3<f32>) -> f32 {
    let first = l.info.y;
    // A cube face spans [-1, 1] at unit distance: a pixel is at most 2 d / size wide at
    // distance d (less off-axis).
    let pixel = 2.0 * distance(x, l.pos.xyz) / f32(views[first].rect.z);
    let xo = x + ng * (params.bias.y * pixel);
    let w = xo - l.pos.xyz;
    let local = vec3<f32>(dot(w, l.axis_t.xyz), dot(w, l.axis_b.xyz), dot(w, l.axis_n.xyz));
    let a = abs(local);
    var face = 4u + select(1u, 0u, local.z >= 0.0);
    if a.x >= a.y && a.x >= a.z {
        face = select(1u, 0u, local.x >= 0.0);
    } else if a.y >= a.z {
        face = 2u + select(1u, 0u, local.y >= 0.0);
    }
    if face == 5u && l.info.x == LIGHT_VPL {
        // Behind the VPL's surface: it has no map there (and sends no light).
        return 0.0;
    }
    let v = views[first + face];
    let ab = vec2<f32>(dot(w, v.right.xyz), dot(w, v.up.xyz)) / dot(w, v.fwd.xyz);
    return shadow_pcf(atlas, v, ab, xo);
}

@compute @workgroup_size(64)
fn gather(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    // A step is one dispatch or several slices (gpu::slices): this dispatch's
    // invocations are texels slice.x, slice.x + 1, ... (slice.y of them).
    let j = invocation_index(wid, nwg, lid);
    let i = params.slice.x + j;
    let n_texels = params.misc.y;
    if j >= params.slice.y || i >= n_texels {
        return;
    }
    let x = texels[i].position.xyz;
    let n = texels[i].normal.xyz;
    let ng = texels[i].geo_normal.xyz;
    var total = vec3<f32>(0.0);
    var direct = vec3<f32>(0.0);
    for (var k = 0u; k < params.misc.z; k++) {
        let l = lights[k];
        let kind = l.info.x;
        var e = vec3<f32>(0.0);
        if kind == LIGHT_DIRECTIONAL {
            let wi = -l.axis_n.xyz;
            let c = dot(n, wi);
            if c <= 0.0 || dot(ng, wi) <= 0.0 {
                continue;
            }
            e = l.power.rgb * c;
            if l.info.y != NO_VIEW && any(e > vec3<f32>(0.0)) {
                e *= visibility_ortho(views[l.info.y], x, ng);
            }
        } else {
            let to = l.pos.xyz - x;
            let d2 = dot(to, to);
            if d2 <= 0.0 {
                continue;
            }
            let wi = to * inverseSqrt(d2);
            let c = dot(n, wi);
            if c <= 0.0 || dot(ng, wi) <= 0.0 {
                continue;
            }
            if kind == LIGHT_VPL {
                let cv = -dot(l.axis_n.xyz, wi);
                if cv <= 0.0 {
                    continue;
                }
                e = l.power.rgb * (c * cv / max(d2, l.power.w));
            } else {
                var f = 1.0 / d2;
                if l.spot.z > 0.0 {
                    // KHR_lights_punctual's recommended range window (as `path` uses).
                    let r2 = d2 / (l.spot.z * l.spot.z);
                    let win = clamp(1.0 - r2 * r2, 0.0, 1.0);
                    f *= win * win;
                }
                if kind == LIGHT_SPOT {
                    let a = clamp((-dot(wi, l.axis_n.xyz) - l.spot.x) * l.spot.y, 0.0, 1.0);
                    f *= a * a;
                }
                e = l.power.rgb * (c * f);
            }
            if l.info.y != NO_VIEW && any(e > vec3<f32>(0.0)) {
                e *= visibility_cube(l, x, ng);
            }
        }
        total += e;
        if l.info.z == 1u {
            direct += e;
        }
    }
    let slot = params.misc.x * n_texels + i;
    let b = params.bias.x;
    acc[slot] = vec4<f32>(mix(acc[slot].rgb, total, b), 0.0);
    direct_acc[slot] = vec4<f32>(mix(direct_acc[slot].rgb, direct, b), 0.0);
}
