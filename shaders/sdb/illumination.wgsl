// sdb/illumination.wgsl: the illumination map (seed section 3, Figure 4). An orthographic
// render of the whole scene along the step's direction d into an Rgba32Float target:
// rgb = outgoing radiance toward the camera, a = t = dot(p, d) (distance along d, used to
// pick the nearest sample and to rebuild its position).
//
// DEPTH_STOCHASTIC: every fragment writes a pseudo-random depth, a PCG hash of its pixel,
// its triangle and the step seed, so the depth test keeps a uniformly
// random one of the surfaces along each pixel's ray. Culling follows the seed's section 6:
// back faces of closed single-sided meshes are discarded (they can never be the first
// surface along a ray from a point outside the mesh, so culling only removes overdraw),
// back faces of open single-sided geometry are kept with zero radiance (they must block
// light), double-sided materials reflect and emit on both faces.
//
// The sun and directional lights are shadowed with the shared atlas (gpu/shadow_atlas.wgsl,
// read by sdb/direct.wgsl), not with this pass.
//
// Alpha (gpu/materials.wgsl): a fragment that glTF alpha cuts away is culled
// (MASK below its cutoff; BLEND when a hash of the step seed, the layer, the
// triangle and the pixel, salted apart from the depth's hash, falls at or above the
// coverage), so the surface behind it is what the pixel sees.
//
// `fs_main_direct` (used when the job wants a direct-light layer) also writes the
// fragment's emitted radiance alone to a second target, so the gather can tell light
// coming straight from an emitter (direct) from light reflected by a surface.

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
    @location(3) @interpolate(flat) layer: u32,
    @location(4) alpha_uv: vec2<f32>,
    @location(5) @interpolate(flat) material: u32,
}

struct FsOut {
    @location(0) sample: vec4<f32>,
    @builtin(frag_depth) depth: f32,
}

struct FsOutDirect {
    @location(0) sample: vec4<f32>,
    @location(1) emission: vec4<f32>,
    @builtin(frag_depth) depth: f32,
}

struct LightmapDims {
    dims: vec4<u32>,  // x: lightmap width W, y: height H; z, w: unused
}

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<uniform> lightmap: LightmapDims;
@group(0) @binding(2) var<storage, read> tris: array<TriInfo>;
@group(0) @binding(3) var<storage, read> radiance: array<vec4<f32>>;  // W*H: reflected (sdb_resolve)
// Emitted radiance per lightmap pixel, static; used by triangles with TRI_TEXTURED_EMISSION.
@group(0) @binding(4) var<storage, read> emission_px: array<vec4<f32>>;  // W*H
@group(0) @binding(5) var<storage, read> tables: array<vec4<f32>>;  // gpu/materials.wgsl

@vertex
fn vs_main(v: Vertex, @builtin(instance_index) layer: u32) -> VsOut {
    let a = dot(v.position, view.right.xyz) - view.right.w;
    let b = dot(v.position, view.up.xyz) - view.up.w;
    let t = dot(v.position, view.dir.xyz) - view.dir.w;
    var out: VsOut;
    // NDC: x right, y up, z = 0 at t0 .. 1 at t1 (only used for clipping: the scene's
    // bounds lie inside, and the depth actually tested is written by the fragment).
    out.clip = vec4<f32>(a / view.extent.x * 2.0 - 1.0, b / view.extent.x * 2.0 - 1.0,
                         t / view.extent.y, 1.0);
    out.world = v.position;
    out.lightmap_uv = v.lightmap_uv;
    out.triangle = v.triangle;
    out.layer = layer;
    out.alpha_uv = v.alpha_uv;
    out.material = v.material;
    return out;
}

// True when glTF alpha removes this fragment's surface (module header).
fn alpha_cut(in: VsOut) -> bool {
    if mat_alpha_mode(in.material) == ALPHA_OPAQUE {
        return false;
    }
    let px = vec2<u32>(in.clip.xy);
    let h = pcg(0xa1fa5eedu ^ pcg(view.params.x ^ pcg(in.layer ^ pcg(in.triangle ^ pcg(px.x ^ pcg(px.y))))));
    return !alpha_keeps(in.material, mat_coverage(in.material, in.alpha_uv), unit_float(h));
}

// Bilinear taps of a lightmap lookup: pixel indices and weights (bilinear x coverage,
// so pixels outside every chart do not darken chart borders).
struct Taps {
    index: vec4<u32>,
    weight: vec4<f32>,
}

fn pixel_index(px: vec2<i32>) -> u32 {
    let w = i32(lightmap.dims.x);
    let h = i32(lightmap.dims.y);
    let q = clamp(px, vec2<i32>(0), vec2<i32>(w - 1, h - 1));
    return u32(q.y * w + q.x);
}

fn lightmap_taps(uv: vec2<f32>) -> Taps {
    let size = vec2<f32>(f32(lightmap.dims.x), f32(lightmap.dims.y));
    let f = uv * size - 0.5;
    let base = floor(f);
    let fr = f - base;
    let p = vec2<i32>(base);
    var taps: Taps;
    taps.index = vec4<u32>(pixel_index(p), pixel_index(p + vec2<i32>(1, 0)),
                           pixel_index(p + vec2<i32>(0, 1)), pixel_index(p + vec2<i32>(1, 1)));
    let coverage = vec4<f32>(radiance[taps.index.x].a, radiance[taps.index.y].a,
                             radiance[taps.index.z].a, radiance[taps.index.w].a);
    taps.weight = vec4<f32>((1.0 - fr.x) * (1.0 - fr.y), fr.x * (1.0 - fr.y),
                            (1.0 - fr.x) * fr.y, fr.x * fr.y) * coverage;
    return taps;
}

// What a fragment writes, before culling is applied by the entry point.
struct Shaded {
    sample: vec4<f32>,    // rgb: outgoing radiance, a: t
    emission: vec3<f32>,  // the emitted part of rgb
    depth: f32,
    culled: bool,
}

fn lookup(buffer_is_emission: bool, taps: Taps) -> vec3<f32> {
    let i = taps.index;
    let w = taps.weight;
    if buffer_is_emission {
        return emission_px[i.x].rgb * w.x + emission_px[i.y].rgb * w.y
             + emission_px[i.z].rgb * w.z + emission_px[i.w].rgb * w.w;
    }
    return radiance[i.x].rgb * w.x + radiance[i.y].rgb * w.y
         + radiance[i.z].rgb * w.z + radiance[i.w].rgb * w.w;
}

fn shade(in: VsOut, front: bool) -> Shaded {
    let t = dot(in.world, view.dir.xyz);
    var out: Shaded;
    out.culled = alpha_cut(in);
    out.emission = vec3<f32>(0.0);
    if out.culled {
        return out;
    }
    let info = tris[in.triangle];
    var l = vec3<f32>(0.0);
    if front || (info.flags & TRI_DOUBLE_SIDED) != 0u {
        // Emission: the material's exact value, so a small emitter's light does not
        // depend on how many lightmap texels it got.
        out.emission = info.emission;
        var taps = lightmap_taps(in.lightmap_uv);
        let wsum = dot(taps.weight, vec4<f32>(1.0));
        if wsum > 1.0e-6 {
            taps.weight = taps.weight / wsum;
            l = lookup(false, taps);
            if (info.flags & TRI_TEXTURED_EMISSION) != 0u {
                out.emission = lookup(true, taps);
            }
        }
        // else: no texel near this fragment (a triangle smaller than a texel): its
        // reflected light is unknown and taken as zero; its emission still counts.
        l += out.emission;
    } else if (info.flags & TRI_CULL_BACK) != 0u {
        out.culled = true;
    }
    // else: back face of open single-sided geometry: a black blocker (seed section 6).
    // The instance index is the depth layer (one draw per layer): each layer is an
    // independent draw of the random depths.
    // Keyed by the pixel, not the position's bits: the same fragment then draws the same
    // depth whatever the scene's scale or placement (positions in normalised space still
    // differ in their last bits), so a scaled or moved scene bakes the same lightmap.
    let px = vec2<u32>(in.clip.xy);
    let h = pcg(view.params.x ^ pcg(in.layer ^ pcg(in.triangle ^ pcg(px.x ^ pcg(px.y)))));
    out.sample = vec4<f32>(l, t);
    out.depth = unit_float(h);
    return out;
}

@fragment
fn fs_main(in: VsOut, @builtin(front_facing) front: bool) -> FsOut {
    let s = shade(in, front);
    if s.culled {
        discard;
    }
    var out: FsOut;
    out.sample = s.sample;
    out.depth = s.depth;
    return out;
}

@fragment
fn fs_main_direct(in: VsOut, @builtin(front_facing) front: bool) -> FsOutDirect {
    let s = shade(in, front);
    if s.culled {
        discard;
    }
    var out: FsOutDirect;
    out.sample = s.sample;
    out.emission = vec4<f32>(s.emission, 0.0);
    out.depth = s.depth;
    return out;
}
