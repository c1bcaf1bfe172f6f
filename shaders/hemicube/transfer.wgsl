// hemicube/transfer.wgsl: every receiver texel takes the light of the step's shooters
// (seed section 4.2.2, Eq. 4), then feeds the step's estimate into the half accumulator
// of its parity.
//
// Per shooter s (weight W = A / (p K)) and receiver x at distance d along unit w:
//   I_x += L_s(w) cos_s cos_x / d^2 * W * vis * m
// Point shooters (texel cells, emitter points; pos.w = 0) share the near field with the
// CPU's gather: the diffuse part of L_s takes m = min(1, d^2 / (cos_s cos_x r^2)), r the
// receiver's near radius (geom.position.w), and the gather brings the rest (NearSample:
// gain times the hit texel's irradiance of the previous step). Merged shooters
// (pos.w = A > 0) use the seed's Eq. 8 instead: d^2 + A / pi in the denominator, m = 1.
// I_x starts from the CPU's estimate of the sky, the sun, punctual lights and the
// near field's emission (HC_CPU_LIGHT) and is this step's irradiance, the one the next
// step's shooters reflect. The lightmap estimate is I_x / pi.
//
// Visibility: the hemicube tile the direction falls in holds the plane (n, c) of the
// nearest surface (gpu/shadow_atlas.wgsl). The receiver is hidden when it and the shooter lie on
// opposite sides of that plane by more than a tolerance that grows at grazing angles
// (seed section 4.2.1): SIDE_EPS plus kappa times the pixel's footprint on the occluder,
// d (2 / side) / |cos|, |cos| the occluder's cosine toward the shooter (at least 0.05).
// A plane test rather than the seed's depth difference: exact for planar occluders of any
// thickness, so the tolerance only has to absorb tessellated curved surfaces.

@group(0) @binding(0) var<uniform> params: HcParams;
@group(0) @binding(1) var<storage, read> geom: array<TexelGeom>;
@group(0) @binding(2) var<storage, read_write> irr: array<vec4<f32>>;   // 2N: two halves
@group(0) @binding(3) var<storage, read_write> dirs: array<vec4<f32>>;  // 2N (glossy) or a stub
@group(0) @binding(4) var<storage, read> cpu_light: array<vec4<f32>>;   // 2N: rgb, then direction sum
@group(0) @binding(5) var<storage, read> shooters: array<Shooter>;
@group(0) @binding(6) var atlas: texture_2d<f32>;
@group(0) @binding(7) var<storage, read_write> acc: array<vec4<f32>>;         // 2N
@group(0) @binding(8) var<storage, read_write> direct_acc: array<vec4<f32>>;  // 2N (direct layer) or a stub
@group(0) @binding(9) var<storage, read> tiles: array<vec4<u32>>;            // 5 per shooter
@group(0) @binding(10) var<storage, read> near: array<NearSample>;           // N

// Smallest distance from a plane that counts as a side (normalised units; the atlas
// offsets texel points 4e-5 of the scene radius off their surface).
const SIDE_EPS: f32 = 1.0e-5;

fn visible(k: u32, s: Shooter, x: vec3<f32>, w: vec3<f32>, d: f32) -> bool {
    let local = vec3<f32>(dot(w, s.frame_t.xyz), dot(w, s.frame_b.xyz), dot(w, s.nrm.xyz));
    let a = abs(local);
    var face = 0u;
    if local.z < max(a.x, a.y) {
        if a.x >= a.y {
            face = select(2u, 1u, local.x >= 0.0);
        } else {
            face = select(4u, 3u, local.y >= 0.0);
        }
    }
    let axes = hc_face_axes(s, face);
    let ab = vec2<f32>(dot(w, axes[1]), dot(w, axes[2])) / dot(w, axes[0]);
    let tile = tiles[5u * k + face];
    let side = f32(tile.z);
    let f = vec2<f32>(ab.x + 1.0, 1.0 - ab.y) * 0.5 * side;
    let lo = vec2<i32>(i32(tile.x), i32(tile.y));
    var rows = i32(tile.z);
    if face != 0u {
        rows = i32(tile.z / 2u);  // side faces: only the half above the shooter's plane
    }
    let hi = lo + vec2<i32>(i32(tile.z) - 1, rows - 1);
    let px = clamp(lo + vec2<i32>(floor(f)), lo, hi);
    let plane = textureLoad(atlas, px, 0);
    let side_s = dot(plane.xyz, s.pos.xyz) - plane.w;
    let side_x = dot(plane.xyz, x) - plane.w;
    let cos_occ = max(abs(dot(plane.xyz, w / d)), 0.05);
    let tol = SIDE_EPS + params.f.z * d * (2.0 / side) / cos_occ;
    return !(side_s * side_x < 0.0 && abs(side_s) > SIDE_EPS && abs(side_x) > tol);
}

@compute @workgroup_size(64)
fn transfer(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    // A step's transfer is one dispatch or several slices (gpu::slices): this
    // dispatch's invocations are texels slice.x, slice.x + 1, ... (slice.y of them).
    // Each writes only its own texel's slots, so slices write what one dispatch does.
    let j = invocation_index(wid, nwg, lid);
    let t = params.slice.x + j;
    let n = params.dims.x;
    if j >= params.slice.y || t >= n {
        return;
    }
    let flags = params.step.w;
    let g = geom[t];
    let x = g.position.xyz;
    let r_near = g.position.w;
    var total = vec3<f32>(0.0);
    var dir_sum = vec3<f32>(0.0);
    if (flags & HC_CPU_LIGHT) != 0u {
        total = cpu_light[t].rgb;
        dir_sum = cpu_light[n + t].xyz;
    }
    var direct = total;
    let count = params.shoot.z + params.shoot.w;
    for (var k = 0u; k < count; k++) {
        let s = shooters[k];
        if s.nrm.w <= 0.0 {
            continue;
        }
        let w = x - s.pos.xyz;
        let d2 = dot(w, w);
        if d2 <= 0.0 {
            continue;
        }
        let d = sqrt(d2);
        let u = w / d;
        let cos_s = dot(s.nrm.xyz, u);
        let cos_x = -dot(g.normal.xyz, u);
        if cos_s <= 0.0 || cos_x <= 0.0 || dot(g.geo_normal.xyz, u) >= 0.0 {
            continue;
        }
        if !visible(k, s, x, w, d) {
            continue;
        }
        // Point shooters (no disc, w = 0) share the near field with the CPU's gather:
        // the diffuse part keeps min(1, c / G), c = 1 / (pi r^2), G = cos_s cos_x / (pi d^2)
        // (the gather takes the rest); a glossy lobe is not gathered and stays whole.
        var l = hc_radiance(s, u);
        if s.pos.w == 0.0 && r_near > 0.0 {
            let keep = min(1.0, d2 / (cos_s * cos_x * r_near * r_near));
            l -= s.diffuse.rgb * (1.0 - keep);
        }
        let i = l * (cos_s * cos_x / (d2 + s.pos.w / 3.14159265) * s.nrm.w);
        total += i;
        dir_sum -= dot(i, HC_LUM) * u;
        if s.diffuse.w > 0.5 {
            direct += i;
        }
    }
    let cur = params.step.x;
    let ns = near[t];
    let hit = ns.hit;
    if hit < n {
        let i = ns.gain.rgb * irr[(1u - cur) * n + hit].rgb;
        total += i;
        dir_sum += dot(i, HC_LUM) * ns.dir.xyz;
    }
    irr[cur * n + t] = vec4<f32>(total, 0.0);
    if (flags & HC_GLOSSY) != 0u {
        dirs[cur * n + t] = vec4<f32>(dir_sum, 0.0);
    }
    let slot = params.step.y * n + t;
    let b = params.f.x;
    acc[slot] = vec4<f32>(mix(acc[slot].rgb, total / 3.14159265, b), 0.0);
    if (flags & HC_DIRECT) != 0u {
        direct_acc[slot] = vec4<f32>(mix(direct_acc[slot].rgb, direct / 3.14159265, b), 0.0);
    }
}
