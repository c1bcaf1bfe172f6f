// shadow_view.wgsl: the layout of one map of the shared shadow-map atlas and the one way to
// read it (prelude of every pass that renders or reads the atlas: gpu/shadow_atlas.wgsl,
// vpl/gather.wgsl, sdb/direct.wgsl, obscurance/direct.wgsl, hemicube/select.wgsl).
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

// Smallest distance from a plane (normalised scene units, 1e-5 of the scene radius) at
// which a point counts as on one side of it: f32 resolves about 1e-7 here, and the
// atlas offsets texel points by 4e-5 of the radius off their own surface.
const SIDE_EPS: f32 = 1.0e-5;

// 1 when tap `px` of view `v` of `atlas` lets the light through to `x`. Each atlas pixel
// holds the plane (n, c) of the nearest surface along its ray (gpu/shadow_atlas.wgsl); the
// tap blocks the light when the light and the receiver lie strictly on opposite sides of
// that plane, which is exact behind a surface of any thickness down to SIDE_EPS and at any
// map resolution. The light sits at the view's origin (perspective) or at infinity against
// its axis (orthographic). Taps stay inside the view's own tile (clamped at its border).
fn shadow_tap(atlas: texture_2d<f32>, v: ShadowView, px: vec2<i32>, x: vec3<f32>) -> f32 {
    let lo = vec2<i32>(i32(v.rect.x), i32(v.rect.y));
    let hi = lo + vec2<i32>(i32(v.rect.z) - 1);
    let plane = textureLoad(atlas, clamp(px, lo, hi), 0);
    var side_light = dot(plane.xyz, v.origin.xyz) - plane.w;
    if v.rect.w == VIEW_ORTHO {
        side_light = -dot(plane.xyz, v.fwd.xyz);
    }
    let side_x = dot(plane.xyz, x) - plane.w;
    let blocked = side_light * side_x < 0.0 && abs(side_light) > SIDE_EPS && abs(side_x) > SIDE_EPS;
    return select(1.0, 0.0, blocked);
}

// 2x2 percentage-closer filtering of view `v` at map coordinates `ab` for receiver `x`:
// errors remain only within a pixel of silhouettes, where a neighbour's plane is
// extrapolated.
fn shadow_pcf(atlas: texture_2d<f32>, v: ShadowView, ab: vec2<f32>, x: vec3<f32>) -> f32 {
    let f = shadow_view_pixel(v, ab) - 0.5;
    let base = floor(f);
    let w = f - base;
    let p = vec2<i32>(base);
    return mix(mix(shadow_tap(atlas, v, p, x), shadow_tap(atlas, v, p + vec2<i32>(1, 0), x), w.x),
               mix(shadow_tap(atlas, v, p + vec2<i32>(0, 1), x), shadow_tap(atlas, v, p + vec2<i32>(1, 1), x), w.x), w.y);
}

// Visibility of the distant light of orthographic view `v` from `x` (geometric normal
// `ng`), the receiver moved along `ng` by `offset_pixels` map pixels against
// self-shadowing on tessellated curved surfaces (a neighbouring triangle's plane passing
// just above the receiver).
fn shadow_ortho(atlas: texture_2d<f32>, v: ShadowView, x: vec3<f32>, ng: vec3<f32>, offset_pixels: f32) -> f32 {
    let pixel = 2.0 * v.right.w / f32(v.rect.z);
    let xo = x + ng * (offset_pixels * pixel);
    let q = xo - v.origin.xyz;
    let ab = vec2<f32>(dot(q, v.right.xyz), dot(q, v.up.xyz)) / v.right.w;
    return shadow_pcf(atlas, v, ab, xo);
}
