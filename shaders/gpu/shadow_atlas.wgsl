// shadow_atlas.wgsl: the shared shadow-map atlas (src/engine/gpu/shadow.rs): the maps of one
// step, all in one atlas (one render pass, one draw per map, its viewport and scissor set to the
// map's tile on the CPU). Used by vpl (lights and VPLs), hemicube (its shooters' depth maps),
// and sdb and obscurance (their sun and directional-light maps, drawn from their own map-scene
// vertices with `vs_shadow_map`).
//
// A map ("shadow view") is either a perspective face of a cube around a point (a VPL:
// five faces, the one behind its surface is never needed; a point or spot light: six) or
// an orthographic map along a distant light's direction (sun, directional light, one
// sampled sky direction). The vertex shader reads its view from the instance index (the
// draw's first instance is the view's index), so one vertex buffer serves every map.
// The target is Rgba32Float and holds the *plane* of the nearest surface: its unit
// geometric normal n and offset c = <n, p> (flat per triangle), not its distance.
// gpu/shadow_view.wgsl's shadow_tap then asks whether the light and the receiver lie on opposite sides of
// that plane, which is exact for a receiver behind the surface however thin the surface
// is and however far it is from the light (a distance compare needs a bias of a fraction
// of a pixel's footprint, centimetres for a distant wall, and leaked through 1 mm walls
// here). Every face of every triangle is drawn (no culling): single-sided back faces are
// black but still block light. Depth32Float orders the fragments.
//
// Alpha (gpu/materials.wgsl): a fragment that glTF alpha cuts away is discarded, so the
// pixel keeps the next surface behind it. BLEND's draw hashes the pixel, the triangle's
// plane offset and the view's origin and forward axis: a view that moves between steps
// draws anew, a fixed one keeps a fixed dither whose pixels pass 1 - coverage of the light.

@group(0) @binding(0) var<storage, read> views: array<ShadowView>;
@group(0) @binding(1) var<storage, read> tables: array<vec4<f32>>;
// `vs_shadow_map` only: the plane of each triangle of a map scene (gpu::map_scene), whose
// technique draws the atlas from the vertex buffer it already holds for its own maps
// (gpu::view::GpuVertex: position, lightmap UV, triangle, alpha UV, material).
@group(0) @binding(2) var<storage, read> planes: array<vec4<f32>>;

struct ShadowVsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) @interpolate(flat) plane: vec4<f32>,
    @location(1) alpha_uv: vec2<f32>,
    @location(2) @interpolate(flat) material: u32,
    @location(3) @interpolate(flat) view_index: u32,
}

@vertex
fn vs_shadow(
    @location(0) position: vec3<f32>,
    @location(1) plane: vec4<f32>,  // the triangle's unit normal and <n, p>, same at its three corners
    @location(2) alpha_uv: vec2<f32>,
    @location(3) material: u32,
    @builtin(instance_index) view_index: u32,
) -> ShadowVsOut {
    return shadow_vertex(position, plane, alpha_uv, material, view_index);
}

@vertex
fn vs_shadow_map(
    @location(0) position: vec3<f32>,
    @location(2) triangle: u32,
    @location(3) alpha_uv: vec2<f32>,
    @location(4) material: u32,
    @builtin(instance_index) view_index: u32,
) -> ShadowVsOut {
    return shadow_vertex(position, planes[triangle], alpha_uv, material, view_index);
}

fn shadow_vertex(position: vec3<f32>, plane: vec4<f32>, alpha_uv: vec2<f32>, material: u32, view_index: u32) -> ShadowVsOut {
    let v = views[view_index];
    let q = position - v.origin.xyz;
    let x = dot(q, v.right.xyz);
    let y = dot(q, v.up.xyz);
    let z = dot(q, v.fwd.xyz);
    var out: ShadowVsOut;
    if v.rect.w == VIEW_ORTHO {
        let half = v.right.w;
        out.clip = vec4<f32>(x / half, y / half, z / v.fwd.w, 1.0);
    } else {
        // 90-degree frustum: x/z and y/z in [-1, 1]; depth 0 at near .. 1 at far.
        let near = v.origin.w;
        let far = v.fwd.w;
        out.clip = vec4<f32>(x, y, (z - near) * far / (far - near), z);
    }
    out.plane = plane;
    out.alpha_uv = alpha_uv;
    out.material = material;
    out.view_index = view_index;
    return out;
}

@fragment
fn fs_shadow(in: ShadowVsOut) -> @location(0) vec4<f32> {
    if mat_alpha_mode(in.material) != ALPHA_OPAQUE {
        let v = views[in.view_index];
        let px = vec2<u32>(in.clip.xy);
        let h = pcg(bitcast<u32>(in.plane.w) ^ pcg(px.x ^ pcg(px.y ^ pcg(bitcast<u32>(v.origin.x)
            ^ pcg(bitcast<u32>(v.origin.y) ^ pcg(bitcast<u32>(v.origin.z) ^ pcg(bitcast<u32>(v.fwd.x)
            ^ pcg(bitcast<u32>(v.fwd.y) ^ pcg(in.view_index)))))))));
        if !alpha_keeps(in.material, mat_coverage(in.material, in.alpha_uv), unit_float(h)) {
            discard;
        }
    }
    return in.plane;
}
