// common.wgsl: helpers and layouts shared by every pass. Concatenated in front of each
// pass file at load time (src/engine/gpu/shaders.rs); WGSL has no #include.
//
// Precision: f32 throughout. Positions are in *normalised scene space*, (p - centre) /
// radius of the scene's bounding sphere, so every epsilon below is relative to the scene
// size and a scene translated by 1e5 or scaled by 1e-3 or 1e4 gives the same numbers.

// ---- randomness -----------------------------------------------------------------------
// PCG hash ("pcg" in Jarzynski & Olano, "Hash Functions for GPU Rendering", JCGT 2020):
// one LCG step followed by PCG's RXS-M-XS output permutation. It passes BigCrush as a
// 1D hash and costs a handful of integer ops; multi-dimensional inputs are chained,
// pcg(a ^ pcg(b ^ ...)), which the paper recommends over summing.
fn pcg(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// Uniform in [0, 1) with 24 random bits: every value is exactly representable in f32 and
// in a Depth32Float buffer, and 1.0 (the depth clear value) is never produced.
fn unit_float(h: u32) -> f32 {
    return f32(h >> 8u) * (1.0 / 16777216.0);
}

// ---- shared layouts --------------------------------------------------------------------
// An orthographic view along a global direction `dir`. The camera looks along +dir, so
// the surfaces it sees are the ones a receiver x sees when it looks along +dir: the
// illumination map holds L_i(x, dir) for every x (seed, section 2).
// Lateral coordinates: a = dot(p, right) - right.w, b = dot(p, up) - up.w, both in
// [0, extent.x]. Pixel (i, j) of the N x N map covers a in [i, i+1] * S / N and
// b in [N - j - 1, N - j] * S / N (row 0 at the top, as the rasteriser writes it).
struct View {
    right: vec4<f32>,   // xyz: unit right axis; w: lateral origin a0
    up: vec4<f32>,      // xyz: unit up axis;    w: lateral origin b0
    dir: vec4<f32>,     // xyz: unit direction d (camera looks along +d); w: t0 = min dot(p, d)
    extent: vec4<f32>,  // x: lateral size S; y: depth range t1 - t0; z: N (pixels); w: unused
    params: vec4<u32>,  // x: step seed; y: depth mode (DEPTH_*); z, w: unused
}

const DEPTH_STOCHASTIC: u32 = 0u;  // random per-fragment depth (seed, section 3)
const DEPTH_NEAREST: u32 = 1u;     // ordinary depth: nearest to the camera (shadow maps)

// Value of the distance channel where nothing was rendered.
const EMPTY_T: f32 = 1.0e30;

// Flags per triangle (TriInfo.flags).
const TRI_DOUBLE_SIDED: u32 = 1u;  // material.double_sided: both faces reflect and emit
const TRI_CULL_BACK: u32 = 2u;     // single-sided face of a closed surface: back face culled
const TRI_TEXTURED_EMISSION: u32 = 4u;  // emission varies over the triangle: read it from the lightmap

// Per triangle: the material's emitted radiance (exact; with an emissive texture, the
// fallback where the lightmap has no texel to look up) and the TRI_* flags.
struct TriInfo {
    emission: vec3<f32>,
    flags: u32,
}

// One lightmap texel's geometry, compact over valid texels.
struct TexelGeom {
    position: vec4<f32>,    // xyz: sample point (normalised scene space); w: unused
    normal: vec4<f32>,      // xyz: unit shading normal (cosine weight); w: unused
    geo_normal: vec4<f32>,  // xyz: unit geometric normal (the plane samples must be above); w: unused
}

// One lightmap texel's material, compact over valid texels.
struct TexelShade {
    albedo: vec4<f32>,    // rgb: diffuse albedo (linear); a: unused
}

// Centre of pixel (i, j) of the view's map in lateral coordinates (a, b).
fn pixel_centre_lateral(view: View, px: vec2<i32>) -> vec2<f32> {
    let n = view.extent.z;
    let s = view.extent.x;
    return vec2<f32>((f32(px.x) + 0.5) / n * s, (n - f32(px.y) - 0.5) / n * s);
}

// Continuous pixel coordinates (pixel centres at +0.5) of a point.
fn project_to_map(view: View, p: vec3<f32>) -> vec2<f32> {
    let n = view.extent.z;
    let s = view.extent.x;
    let a = dot(p, view.right.xyz) - view.right.w;
    let b = dot(p, view.up.xyz) - view.up.w;
    return vec2<f32>(a / s * n, (1.0 - b / s) * n);
}

// World (normalised scene space) position of a map sample: pixel centre laterally, its
// stored distance t along d.
fn map_sample_position(view: View, px: vec2<i32>, t: f32) -> vec3<f32> {
    let ab = pixel_centre_lateral(view, px) + vec2<f32>(view.right.w, view.up.w);
    return view.right.xyz * ab.x + view.up.xyz * ab.y + view.dir.xyz * t;
}

// Linear index of a compute invocation over a 2D grid of 64-wide workgroups; the grid is
// 2D because 16M texels (a 4096^2 lightmap) need more than 65535 workgroups in x.
fn invocation_index(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.y * nwg.x + wid.x) * 64u + lid;
}

// ---- vpl: shadow views (vpl_shadow.wgsl renders them, vpl_gather.wgsl reads them) ------
// One map in the `vpl` shadow atlas: a perspective cube face (90 degrees) around a point
// or an orthographic map along a distant light. Normalised scene space.
struct ShadowView {
    origin: vec4<f32>,  // xyz: eye (perspective) or the map's near-plane centre (ortho); w: near distance
    right: vec4<f32>,   // xyz: unit right axis; w: ortho half extent
    up: vec4<f32>,      // xyz: unit up axis; w: unused
    fwd: vec4<f32>,     // xyz: unit view axis; w: far distance (perspective) or depth range (ortho)
    rect: vec4<u32>,    // x, y: the tile's top-left pixel in the atlas; z: tile side; w: VIEW_*
}

const VIEW_PERSPECTIVE: u32 = 0u;
const VIEW_ORTHO: u32 = 1u;

// Continuous atlas pixel coordinates (pixel centres at +0.5) of map coordinates (a, b) in
// [-1, 1]^2 (NDC of the view: a right, b up; row 0 of a tile is its top, b = +1).
fn shadow_view_pixel(v: ShadowView, ab: vec2<f32>) -> vec2<f32> {
    let size = f32(v.rect.z);
    return vec2<f32>(f32(v.rect.x), f32(v.rect.y)) + vec2<f32>(ab.x + 1.0, 1.0 - ab.y) * 0.5 * size;
}

// ---- sdf: the signed-distance volume (src/engine/technique/sdf.rs) ---------------------
// A grid of dims.x * dims.y * dims.z voxels of size h over the padded scene bounds
// (normalised scene space), x fastest. Mip level l has ceil(dims / 2^l) voxels of size
// h 2^l, each the mean of its 2 x 2 x 2 children; all levels lie in one buffer of
// vec4 (x: signed distance, outside positive; yzw: albedo of the nearest surface).
struct SdfVolume {
    origin: vec4<f32>,            // xyz: low corner of voxel (0, 0, 0); w: voxel size h
    dims: vec4<u32>,              // xyz: level-0 voxel counts; w: mip levels (<= 8)
    offsets: array<vec4<u32>, 2>, // element offset of level l at [l / 4][l % 4]
}

// One triangle for the distance transform: corners in xyz, albedo in a.w, b.w, c.w,
// unit geometric normal (front side = outside) in n.xyz.
struct SdfTri {
    a: vec4<f32>,
    b: vec4<f32>,
    c: vec4<f32>,
    n: vec4<f32>,
}

const SDF_NO_SEED: u32 = 0xffffffffu;

fn sdf_level_dims(vol: SdfVolume, l: u32) -> vec3<u32> {
    let s = (1u << l) - 1u;
    return max((vol.dims.xyz + vec3<u32>(s)) >> vec3<u32>(l), vec3<u32>(1u));
}

fn sdf_level_offset(vol: SdfVolume, l: u32) -> u32 {
    return vol.offsets[l / 4u][l % 4u];
}

fn sdf_voxel_centre(vol: SdfVolume, v: vec3<u32>) -> vec3<f32> {
    return vol.origin.xyz + (vec3<f32>(v) + 0.5) * vol.origin.w;
}

// Closest point of triangle abc to p (Ericson, Real-Time Collision Detection, 5.1.5):
// Voronoi regions of the vertices, then the edges, then the face. Degenerate triangles
// are dropped before upload, so the face region's denominator is never zero.
fn sdf_closest_on_triangle(p: vec3<f32>, a: vec3<f32>, b: vec3<f32>, c: vec3<f32>) -> vec3<f32> {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if (d1 <= 0.0 && d2 <= 0.0) { return a; }
    let bp = p - b;
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if (d3 >= 0.0 && d4 <= d3) { return b; }
    let vc = d1 * d4 - d3 * d2;
    if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) { return a + ab * (d1 / (d1 - d3)); }
    let cp = p - c;
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if (d6 >= 0.0 && d5 <= d6) { return c; }
    let vb = d5 * d2 - d1 * d6;
    if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) { return a + ac * (d2 / (d2 - d6)); }
    let va = d3 * d6 - d5 * d4;
    if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    return a + ab * (vb * denom) + ac * (vc * denom);
}

// Unsigned distance from p to triangle t.
fn sdf_triangle_distance(p: vec3<f32>, t: SdfTri) -> f32 {
    return length(p - sdf_closest_on_triangle(p, t.a.xyz, t.b.xyz, t.c.xyz));
}

// ---- hemicube: shared by hemicube_pyramid/select/transfer.wgsl (src/engine/technique/hemicube.rs)
// Per step uniform of every hemicube pass.
struct HcParams {
    dims: vec4<u32>,   // x: valid texels N, y: lightmap width, z: lightmap height, w: pyramid side S
    shoot: vec4<u32>,  // x: top level, y: shooter (merge) level, z: emitter shooters, w: texel shooters
    step: vec4<u32>,   // x: current irradiance half (0/1), y: accumulator half, z: step hash, w: HC_* flags
    f: vec4<f32>,      // x: accumulator blend, y: depth-map side, z: grazing tolerance kappa, w: texel shooters per step (weight divisor)
}

const HC_GLOSSY: u32 = 1u;      // lobes and incoming directions are kept (glossy variant)
const HC_DIRECT: u32 = 2u;      // a direct-light layer is kept
const HC_CPU_LIGHT: u32 = 4u;   // the CPU's sky / sun / punctual estimate is added each step
const HC_LUM: vec3<f32> = vec3<f32>(0.2126, 0.7152, 0.0722);

// Per valid texel: its lobe, area and surface keys (merging never crosses surfaces).
struct TexelMat {
    kd: vec4<f32>,   // rgb: diffuse albedo k_d; w: texel area (normalised scene units)
    ks: vec4<f32>,   // rgb: specular albedo k_s; w: Phong exponent
    ids: vec4<u32>,  // x: mesh, y: material, z: lightmap pixel, w: unused
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
