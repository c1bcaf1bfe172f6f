// volume.wgsl: the signed-distance volume's layout and triangle distance, the prelude of every
// sdf pass (src/engine/technique/sdf/). Only sdf uses it, so it is not in gpu/common.wgsl.
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
