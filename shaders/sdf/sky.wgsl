// sdf/sky.wgsl: sky light from the distance volume (seed section 9.6).
// For a texel at P with normal N, samples along the bent normal N' = normalize(N + alpha U)
// (U = +Y, the sky's up) at d_i = h 2^(i + u), i = 0 .. samples - 1, read mip level
// min(i, levels - 1) trilinearly and sum the seed's occlusion terms
// S = sum_i min(D(P + d_i N') - d_i, 0) / w_i  (w_i = h: the seed's sum in voxel units;
// w_i = d_i: each term as a fraction of its distance). C = min(exp(k S), 1), and the
// texel's sky visibility is F(N) C, F the unoccluded cosine-weighted fraction of the sky
// (1 for a full sky, (1 + N.y) / 2 for the upper hemisphere), so an open surface is
// exact whatever its orientation. Colour bleed (seed section 9.9): channel c's terms are
// scaled by (1 - bleed * albedo_c) of the surface nearest the sample, so bright occluders
// darken less in their own colour.
// `sky_step` adds L_sky F C (rgb) and F C (w, bleed-free: the sky visibility) into the
// half accumulator of this step. u, the sample-distance jitter in [-1/2, 1/2), is a
// PCG hash of the texel's pixel (position.w's bits: a region's task draws the jitters a
// whole bake draws there, engine::tasks) plus the step index times the golden ratio, so
// the steps of a texel stratify u and both halves converge to the mean over u.
// `calibrate` writes the raw sums S for calibration texels x alphas x fixed jitters.
// Trilinear lookups past the volume's outermost voxel centres add the distance to the
// clamped point (the triangle inequality's bound, exact for surfaces inside the volume).

struct SkyParams {
    sky: vec4<f32>,                // rgb: sky radiance; w: 1 upper hemisphere, 0 full sphere
    fit: vec4<f32>,                // x: k; y: alpha; z: bleed; w: 1 terms over d_i, 0 over h
    misc: vec4<u32>,               // x: texel count; y: samples; z: step seed; w: half (0, 1)
    cal: vec4<u32>,                // x: jitters per alpha; y: alpha count; z: step index
    alphas: array<vec4<f32>, 4>,   // calibrate: up to 16 alphas
    slice: vec4<u32>,              // sky_step: x this dispatch's first texel, y its count (gpu::slices); zw unused
}

@group(0) @binding(0) var<uniform> vol: SdfVolume;
@group(0) @binding(1) var<storage, read> levels: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> texels: array<TexelGeom>;
@group(0) @binding(3) var<storage, read_write> acc: array<vec4<f32>>;
@group(0) @binding(4) var<uniform> sp: SkyParams;

fn level_load(o: u32, d: vec3<u32>, v: vec3<u32>) -> vec4<f32> {
    return levels[o + (v.z * d.y + v.y) * d.x + v.x];
}

fn sample_level(p: vec3<f32>, l: u32) -> vec4<f32> {
    let hl = vol.origin.w * f32(1u << l);
    let d = sdf_level_dims(vol, l);
    let o = sdf_level_offset(vol, l);
    let g = (p - vol.origin.xyz) / hl - 0.5;
    let gc = clamp(g, vec3<f32>(0.0), vec3<f32>(d - 1u));
    let outside = length(g - gc) * hl;
    let i0 = vec3<u32>(floor(gc));
    let i1 = min(i0 + 1u, d - 1u);
    let f = gc - floor(gc);
    let x00 = mix(level_load(o, d, vec3<u32>(i0.x, i0.y, i0.z)), level_load(o, d, vec3<u32>(i1.x, i0.y, i0.z)), f.x);
    let x10 = mix(level_load(o, d, vec3<u32>(i0.x, i1.y, i0.z)), level_load(o, d, vec3<u32>(i1.x, i1.y, i0.z)), f.x);
    let x01 = mix(level_load(o, d, vec3<u32>(i0.x, i0.y, i1.z)), level_load(o, d, vec3<u32>(i1.x, i0.y, i1.z)), f.x);
    let x11 = mix(level_load(o, d, vec3<u32>(i0.x, i1.y, i1.z)), level_load(o, d, vec3<u32>(i1.x, i1.y, i1.z)), f.x);
    let v = mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
    return vec4<f32>(v.x + outside, v.yzw);
}

// xyz: per-channel sums with colour bleed; w: the plain sum S.
fn occlusion_sums(p: vec3<f32>, n: vec3<f32>, alpha: f32, u: f32) -> vec4<f32> {
    var dir = n + alpha * vec3<f32>(0.0, 1.0, 0.0);
    if (dot(dir, dir) < 1e-8) { dir = n; }
    dir = normalize(dir);
    let h = vol.origin.w;
    var s = vec4<f32>(0.0);
    for (var i = 0u; i < sp.misc.y; i++) {
        let d = h * exp2(f32(i) + u);
        let v = sample_level(p + d * dir, min(i, vol.dims.w - 1u));
        let w = select(h, d, sp.fit.w > 0.5);
        let term = min(v.x - d, 0.0) / w;
        let bleed = vec3<f32>(1.0) - sp.fit.z * clamp(v.yzw, vec3<f32>(0.0), vec3<f32>(1.0));
        s += vec4<f32>(term * bleed, term);
    }
    return s;
}

fn open_fraction(n: vec3<f32>) -> f32 {
    if (sp.sky.w > 0.5) { return clamp(0.5 * (1.0 + n.y), 0.0, 1.0); }
    return 1.0;
}

@compute @workgroup_size(64)
fn sky_step(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    // A step is one dispatch or several slices (gpu::slices): this dispatch's
    // invocations are texels slice.x, slice.x + 1, ... (slice.y of them).
    let j = invocation_index(wid, nwg, lid);
    let i = sp.slice.x + j;
    let n_texels = sp.misc.x;
    if (j >= sp.slice.y || i >= n_texels) { return; }
    let t = texels[i];
    let n = t.normal.xyz;
    let f = open_fraction(n);
    let u = fract(unit_float(pcg(bitcast<u32>(t.position.w) ^ pcg(sp.misc.z))) + f32(sp.cal.z) * 0.618034) - 0.5;
    let s = occlusion_sums(t.position.xyz, n, sp.fit.y, u);
    let c = min(exp(sp.fit.x * s), vec4<f32>(1.0));
    let slot = sp.misc.w * n_texels + i;
    acc[slot] += vec4<f32>(sp.sky.xyz * f * c.xyz, f * c.w);
}

@compute @workgroup_size(64)
fn calibrate(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    let jitters = sp.cal.x;
    let n_texels = sp.misc.x;
    if (i >= jitters * sp.cal.y * n_texels) { return; }
    let j = i % jitters;
    let t = (i / jitters) % n_texels;
    let a = i / (jitters * n_texels);
    let alpha = sp.alphas[a / 4u][a % 4u];
    let u = (f32(j) + 0.5) / f32(jitters) - 0.5;
    let s = occlusion_sums(texels[t].position.xyz, texels[t].normal.xyz, alpha, u);
    acc[i] = vec4<f32>(s.w, 0.0, 0.0, 0.0);
}
