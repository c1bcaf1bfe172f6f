// sdf/dynamic.wgsl: analytic local SDFs composited into the volume (seed section 9.8):
// level 0 = min(static scene distance, every dynamic shape's distance), the albedo of
// whichever is nearest. The static distance (`base`) is kept, so moving a shape reruns
// only this pass and the mips, not the voxelisation and flood.
// Box: the exact signed distance. Ellipsoid: Quilez's bound k0 (k0 - 1) / k1, exact on
// the surface and for spheres, within the radius ratio elsewhere.

struct Shape {
    centre: vec4<f32>,  // xyz: centre (normalised scene space); w: 0 box, 1 ellipsoid
    size: vec4<f32>,    // xyz: half extents (box) or radii (ellipsoid)
    albedo: vec4<f32>,  // rgb: albedo (for colour bleed)
}

struct DynamicParams {
    misc: vec4<u32>,  // x: shape count
}

@group(0) @binding(0) var<uniform> vol: SdfVolume;
@group(0) @binding(1) var<storage, read> base: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> levels: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> shapes: array<Shape>;
@group(0) @binding(4) var<uniform> dp: DynamicParams;

fn shape_distance(s: Shape, p: vec3<f32>) -> f32 {
    let q = p - s.centre.xyz;
    if (s.centre.w < 0.5) {
        let e = abs(q) - s.size.xyz;
        return length(max(e, vec3<f32>(0.0))) + min(max(e.x, max(e.y, e.z)), 0.0);
    }
    let k0 = length(q / s.size.xyz);
    let k1 = length(q / (s.size.xyz * s.size.xyz));
    if (k1 == 0.0) { return -min(s.size.x, min(s.size.y, s.size.z)); }
    return k0 * (k0 - 1.0) / k1;
}

@compute @workgroup_size(64)
fn composite(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    if (i >= vol.dims.x * vol.dims.y * vol.dims.z) { return; }
    var v = base[i];
    let p = sdf_voxel_centre(vol, vec3<u32>(i % vol.dims.x, (i / vol.dims.x) % vol.dims.y,
                                            i / (vol.dims.x * vol.dims.y)));
    for (var k = 0u; k < dp.misc.x; k++) {
        let d = shape_distance(shapes[k], p);
        if (d < v.x) { v = vec4<f32>(d, shapes[k].albedo.xyz); }
    }
    levels[i] = v;
}
