// sdb_illumination.wgsl: the illumination map (seed section 3, Figure 4). An orthographic
// render of the whole scene along the step's direction d into an Rgba32Float target:
// rgb = outgoing radiance toward the camera, a = t = dot(p, d) (distance along d, used to
// pick the nearest sample and to rebuild its position).
//
// DEPTH_STOCHASTIC: every fragment writes a pseudo-random depth, a PCG hash of its world
// position bits, its triangle and the step seed, so the depth test keeps a uniformly
// random one of the surfaces along each pixel's ray. Culling follows the seed's section 6:
// back faces of closed single-sided meshes are discarded (they can never be the first
// surface along a ray from a point outside the mesh, so culling only removes overdraw),
// back faces of open single-sided geometry are kept with zero radiance (they must block
// light), double-sided materials reflect and emit on both faces.
//
// DEPTH_NEAREST: ordinary nearest-to-camera depth with every face kept; used as a shadow
// map for the sun and directional lights (sdb_direct.wgsl).

struct Vertex {
    @location(0) position: vec3<f32>,
    @location(1) lightmap_uv: vec2<f32>,
    @location(2) triangle: u32,
}

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) lightmap_uv: vec2<f32>,
    @location(2) @interpolate(flat) triangle: u32,
}

struct FsOut {
    @location(0) sample: vec4<f32>,
    @builtin(frag_depth) depth: f32,
}

struct LightmapDims {
    dims: vec4<u32>,  // x: lightmap width W, y: height H; z, w: unused
}

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<uniform> lightmap: LightmapDims;
@group(0) @binding(2) var<storage, read> tris: array<TriInfo>;
@group(0) @binding(3) var<storage, read> radiance: array<vec4<f32>>;  // W*H, from sdb_resolve

@vertex
fn vs_main(v: Vertex) -> VsOut {
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
    return out;
}

fn load_radiance(px: vec2<i32>) -> vec4<f32> {
    let w = i32(lightmap.dims.x);
    let h = i32(lightmap.dims.y);
    let q = clamp(px, vec2<i32>(0), vec2<i32>(w - 1, h - 1));
    return radiance[u32(q.y * w + q.x)];
}

// Bilinear lookup weighted by coverage (alpha), so that pixels outside every chart do
// not darken chart borders. Returns alpha = total coverage weight.
fn lightmap_radiance(uv: vec2<f32>) -> vec4<f32> {
    let size = vec2<f32>(f32(lightmap.dims.x), f32(lightmap.dims.y));
    let f = uv * size - 0.5;
    let base = floor(f);
    let frac = f - base;
    let p = vec2<i32>(base);
    let s00 = load_radiance(p);
    let s10 = load_radiance(p + vec2<i32>(1, 0));
    let s01 = load_radiance(p + vec2<i32>(0, 1));
    let s11 = load_radiance(p + vec2<i32>(1, 1));
    let w00 = (1.0 - frac.x) * (1.0 - frac.y) * s00.a;
    let w10 = frac.x * (1.0 - frac.y) * s10.a;
    let w01 = (1.0 - frac.x) * frac.y * s01.a;
    let w11 = frac.x * frac.y * s11.a;
    let wsum = w00 + w10 + w01 + w11;
    let rgb = s00.rgb * w00 + s10.rgb * w10 + s01.rgb * w01 + s11.rgb * w11;
    return vec4<f32>(rgb, wsum);
}

@fragment
fn fs_main(in: VsOut, @builtin(front_facing) front: bool) -> FsOut {
    let t = dot(in.world, view.dir.xyz);
    var out: FsOut;
    if view.params.y == DEPTH_NEAREST {
        out.sample = vec4<f32>(0.0, 0.0, 0.0, t);
        out.depth = clamp((t - view.dir.w) / view.extent.y, 0.0, 1.0);
        return out;
    }
    let info = tris[in.triangle];
    var l = vec3<f32>(0.0);
    if front || (info.flags & TRI_DOUBLE_SIDED) != 0u {
        let lm = lightmap_radiance(in.lightmap_uv);
        if lm.a > 1.0e-6 {
            l = lm.rgb / lm.a;
        } else {
            // No texel near this fragment (a triangle smaller than a texel): keep at
            // least its own emission so that small emitters still light the scene.
            l = info.emission;
        }
    } else if (info.flags & TRI_CULL_BACK) != 0u {
        discard;
    }
    // else: back face of open single-sided geometry: a black blocker (seed section 6).
    let h = pcg(view.params.x ^ pcg(in.triangle ^ pcg(bitcast<u32>(in.world.x)
        ^ pcg(bitcast<u32>(in.world.y) ^ pcg(bitcast<u32>(in.world.z))))));
    out.sample = vec4<f32>(l, t);
    out.depth = unit_float(h);
    return out;
}
