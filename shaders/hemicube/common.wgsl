// hemicube/common.wgsl: layouts and lobe shared by hemicube/pyramid, select and transfer.wgsl
// (src/engine/technique/hemicube/); prepended to those passes only.
// Per step uniform of every hemicube pass.
struct HcParams {
    dims: vec4<u32>,   // x: valid texels N, y: lightmap width, z: lightmap height, w: pyramid side S
    shoot: vec4<u32>,  // x: top level, y: shooter (merge) level, z: emitter shooters, w: texel shooters
    step: vec4<u32>,   // x: current irradiance half (0/1), y: accumulator half, z: step hash, w: HC_* flags
    f: vec4<f32>,      // x: accumulator blend, y: depth-map side, z: grazing tolerance kappa, w: texel shooters per step (weight divisor)
    slice: vec4<u32>,  // the transfer's: x its first texel, y its texel count (a sliced step, gpu::slices); zw unused
}

const HC_GLOSSY: u32 = 1u;      // lobes and incoming directions are kept (glossy variant)
const HC_DIRECT: u32 = 2u;      // a direct-light layer is kept
const HC_CPU_LIGHT: u32 = 4u;   // the CPU's sky / sun / punctual estimate is added each step
const HC_LUM: vec3<f32> = vec3<f32>(0.2126, 0.7152, 0.0722);

// Per valid texel: its lobe, area and surface keys (merging never crosses surfaces).
struct TexelMat {
    kd: vec4<f32>,   // rgb: diffuse albedo k_d; w: the area of the texel's cell (normalised scene units)
    ks: vec4<f32>,   // rgb: specular albedo k_s; w: Phong exponent
    ids: vec4<u32>,  // x: mesh, y: material, z: lightmap pixel, w: its first cell piece
}

// A receiver's near-field gather of one step (hemicube module doc, "Unbiased transfer"): the CPU's
// cosine ray within the receiver's near radius hit texel `hit`'s cell; the light it
// brings is gain * that texel's irradiance of the previous step.
struct NearSample {
    gain: vec4<f32>,  // rgb: MIS weight times the hit texel's k_d; w: unused
    dir: vec3<f32>,   // unit direction toward the hit
    hit: u32,         // the hit texel (0xffffffff: none)
}

// One triangle of a texel's cell, the surface the texel stands for (engine::atlas::cells):
// the corners a, a + e1, a + e2 (normalised scene units, off the surface like texel
// points), wound counter-clockwise about the surface normal. A texel's pieces run from its
// `ids.w` to the next texel's.
struct CellPiece {
    a: vec4<f32>,   // xyz: first corner; w: area (normalised units)
    e1: vec4<f32>,  // xyz: second corner - first; w: unused
    e2: vec4<f32>,  // xyz: third corner - first; w: unused
}

// Level l of the sum pyramid for `reduce`.
struct LevelParams {
    v: vec4<u32>,  // x: destination side, y: source offset, z: destination offset, w: unused
}

// One shooter of the step: a merged group of texels or a point on an emitter triangle.
struct Shooter {
    pos: vec4<f32>,      // xyz: position (normalised scene space); w: disc area A of Eq. 8
    nrm: vec4<f32>,      // xyz: unit normal; w: weight A / (p K) (0: no shooter)
    diffuse: vec4<f32>,  // rgb: emitted + diffusely reflected radiance; w: 1 for an emitter sample
    spec: vec4<f32>,     // rgb: k_s I (specular albedo times incident irradiance); w: Phong exponent
    in_dir: vec4<f32>,   // xyz: unit direction the shooter's light came from; w: unused
    frame_t: vec4<f32>,  // xyz: hemicube frame tangent; w: unused
    frame_b: vec4<f32>,  // xyz: hemicube frame bitangent; w: unused
}

// Radiance a shooter sends along unit `w`: the Lambertian part plus the Neumann-Neumann-
// Szirmay-Kalos modified Phong lobe k_s (n + 1) / (2 pi) cos^n(alpha) / max(cos_i, cos_o)
// about the mirror direction of `in_dir` (module doc of hemicube.rs).
fn hc_radiance(s: Shooter, w: vec3<f32>) -> vec3<f32> {
    var l = s.diffuse.rgb;
    if dot(s.spec.rgb, vec3<f32>(1.0)) > 0.0 {
        let n = s.nrm.xyz;
        let wi = s.in_dir.xyz;
        let cos_i = dot(n, wi);
        let cos_o = dot(n, w);
        if cos_i > 0.0 && cos_o > 0.0 {
            let r = 2.0 * cos_i * n - wi;
            let c = max(dot(r, w), 0.0);
            let e = s.spec.w;
            l += s.spec.rgb * ((e + 1.0) / (2.0 * 3.14159265) * pow(c, e) / max(cos_i, cos_o));
        }
    }
    return l;
}

// The five hemicube faces of a shooter as (forward, right, up): 0 the top (along the
// normal), 1..4 the sides (+t, -t, +b, -b), whose upper halves (up = normal) are used.
fn hc_face_axes(s: Shooter, face: u32) -> array<vec3<f32>, 3> {
    let n = s.nrm.xyz;
    let t = s.frame_t.xyz;
    let b = s.frame_b.xyz;
    switch face {
        case 0u: { return array<vec3<f32>, 3>(n, t, b); }
        case 1u: { return array<vec3<f32>, 3>(t, b, n); }
        case 2u: { return array<vec3<f32>, 3>(-t, b, n); }
        case 3u: { return array<vec3<f32>, 3>(b, t, n); }
        default: { return array<vec3<f32>, 3>(-b, t, n); }
    }
}
