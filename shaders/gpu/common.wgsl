// gpu/common.wgsl: helpers and layouts shared by every pass of every technique. Concatenated in
// front of each pass file at load time (src/engine/gpu/shaders.rs); WGSL has no #include.
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
    position: vec4<f32>,    // xyz: sample point (normalised scene space); w: unused, or (gpu/texels.rs world_texels) the pixel index as u32 bits
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
