// obscurance/layers.wgsl: every depth layer of a bundle of parallel rays in one raster
// pass (seed section 4.1, with a per-pixel fragment list in place of depth peeling).
//
// An orthographic render of the whole scene along the direction d (the `View` of
// gpu/common.wgsl: the camera looks along +d, so `front_facing` means the surface's normal
// points back toward smaller t = <p, d>). No depth test and no culling: every fragment
// is appended to its pixel's singly linked list (head pointer swapped in atomically),
// so each list holds all the surfaces the pixel's ray crosses, unsorted. The gather
// (obscurance/gather.wgsl) walks a list to find the layer next to a texel.
//
// A node stores what the seed's RGBA pixel stored (patch id, orientation, depth): the
// distance t along d, the triangle index with the front-facing bit, and the lightmap
// pixel under the fragment (for textured albedo or emission). Nodes come from one pool
// of fixed capacity; a fragment past it is dropped (the counter still counts it, so the
// CPU can report the overflow) and its surface is missing from that direction only.
//
// Sun and directional lights are shadowed with the shared atlas (gpu/shadow_atlas.wgsl),
// not here.
//
// Alpha (gpu/materials.wgsl): the fragment shader drops a fragment that glTF alpha cuts away
// (MASK below its cutoff; BLEND when a hash of the pixel, the triangle and the view's
// direction, which changes every step, falls at or above the coverage), so that surface
// is missing from that direction's layers.

struct Vertex {
    @location(0) position: vec3<f32>,
    @location(1) lightmap_uv: vec2<f32>,
    @location(2) triangle: u32,
    @location(3) alpha_uv: vec2<f32>,
    @location(4) material: u32,
}

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) lightmap_uv: vec2<f32>,
    @location(2) @interpolate(flat) triangle: u32,
    @location(3) alpha_uv: vec2<f32>,
    @location(4) @interpolate(flat) material: u32,
}

// The same as obscurance/gather.wgsl's; `GpuNode` in obscurance/mod.rs mirrors both (sizes
// checked in its tests).
struct Node {
    t: f32,         // distance along d (normalised scene units)
    tri: u32,       // triangle index << 1 | 1 when front-facing (normal toward -d)
    lightmap: u32,  // lightmap pixel index under the fragment
    next: u32,      // next node + 1, 0 ends the list
}

struct LayerParams {
    dims: vec4<u32>,  // x: lightmap width, y: height, z: node capacity, w: map size N
}

// Bindings 0 and 1 are what both entry points read (the shadow map's layout has only
// those two); the fragment lists follow.
@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<storage, read> tables: array<vec4<f32>>;            // gpu/materials.wgsl
@group(0) @binding(2) var<uniform> layer_params: LayerParams;
@group(0) @binding(3) var<storage, read_write> heads: array<atomic<u32>>;     // N*N, node + 1 or 0
@group(0) @binding(4) var<storage, read_write> nodes: array<Node>;            // capacity
@group(0) @binding(5) var<storage, read_write> counters: array<atomic<u32>>;  // [0]: fragments this direction

// True when glTF alpha removes this fragment's surface (module header).
fn alpha_cut(in: VsOut) -> bool {
    if mat_alpha_mode(in.material) == ALPHA_OPAQUE {
        return false;
    }
    let px = vec2<u32>(in.clip.xy);
    let h = pcg(in.triangle ^ pcg(px.x ^ pcg(px.y ^ pcg(bitcast<u32>(view.dir.x)
        ^ pcg(bitcast<u32>(view.dir.y) ^ pcg(bitcast<u32>(view.dir.z)))))));
    return !alpha_keeps(in.material, mat_coverage(in.material, in.alpha_uv), unit_float(h));
}

@vertex
fn vs_main(v: Vertex) -> VsOut {
    let a = dot(v.position, view.right.xyz) - view.right.w;
    let b = dot(v.position, view.up.xyz) - view.up.w;
    let t = dot(v.position, view.dir.xyz) - view.dir.w;
    var out: VsOut;
    // NDC x right, y up, z = 0 at t0 .. 1 at t1: the bounds lie inside, nothing clips.
    out.clip = vec4<f32>(a / view.extent.x * 2.0 - 1.0, b / view.extent.x * 2.0 - 1.0,
                         t / view.extent.y, 1.0);
    out.world = v.position;
    out.lightmap_uv = v.lightmap_uv;
    out.triangle = v.triangle;
    out.alpha_uv = v.alpha_uv;
    out.material = v.material;
    return out;
}

@fragment
fn fs_layers(in: VsOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    if alpha_cut(in) {
        discard;
    }
    let idx = atomicAdd(&counters[0], 1u);
    if idx < layer_params.dims.z {
        let n = layer_params.dims.w;
        let px = min(vec2<u32>(floor(in.clip.xy)), vec2<u32>(n - 1u));
        let w = layer_params.dims.x;
        let h = layer_params.dims.y;
        let lm = min(vec2<u32>(max(floor(in.lightmap_uv * vec2<f32>(f32(w), f32(h))), vec2<f32>(0.0))),
                     vec2<u32>(w - 1u, h - 1u));
        nodes[idx].t = dot(in.world, view.dir.xyz);
        nodes[idx].tri = (in.triangle << 1u) | select(0u, 1u, front);
        nodes[idx].lightmap = lm.y * w + lm.x;
        nodes[idx].next = atomicExchange(&heads[px.y * n + px.x], idx + 1u);
    }
    // The colour target is a write-masked dummy (a render pass needs an attachment).
    return vec4<f32>(0.0);
}
