// shadow_view.wgsl: the layout of one map of the shared shadow-map atlas (prelude of every pass
// that renders or reads the atlas: gpu/shadow_atlas.wgsl, vpl/gather.wgsl, hemicube/transfer.wgsl).
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
