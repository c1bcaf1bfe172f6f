// gpu/materials.wgsl: the scene's materials and textures as every GPU pass reads them, and
// glTF alpha (issue 19 point 5). A library (no entry points, no bindings of its own): the
// pass that composes it declares the table buffer
//     var<storage, read> tables: array<vec4<f32>>;
// at a binding of its choice. The buffer is the bake's one upload of the scene's tables
// (src/engine/gpu/scene_rays.rs, `scene_tables`); its row 0 holds the offsets this
// library needs, so a pass binds one buffer and no uniform:
//   row 0: (materials offset, texture headers offset, -, -) as u32 bits;
//   materials, MAT_STRIDE rows each: base colour | texture, emission | texture,
//     (base uv set, emission uv set, double-sided, -), (ALPHA_*, cutoff, alpha factor, -);
//   texture headers, one row each: (first texel, width, height, wrap u | wrap v << 8);
//   texels: one row each, linear RGBA.
// Ray passes (gpu/lights.wgsl, gpu/bvh.wgsl) and raster passes (gpu/shadow_atlas.wgsl,
// sdb/illumination.wgsl, obscurance/layers.wgsl) test alpha with the same functions, so a
// MASK cutoff and a BLEND coverage mean the same everywhere.
//
// Alpha: a surface's coverage is the base colour factor's alpha times the base colour
// texture's alpha (bilinear, as scene::Texture::sample), read at the texture's UV set.
// MASK keeps a point whose coverage reaches the cutoff; BLEND keeps it when a uniform
// draw falls below the coverage, so it stops light in proportion to its coverage. The
// draw is the caller's: rays hash themselves (alpha_draw, the CPU's scene::blend_draw),
// raster passes hash pixel, triangle and view (their headers say how).
//
// Precision: f32; coordinates beyond +-1e9 texels are clamped (no fraction is left there).

const NO_TEXTURE: u32 = 0xffffffffu;
const WRAP_MIRROR: u32 = 1u;
const WRAP_CLAMP: u32 = 2u;
const MAT_STRIDE: u32 = 4u;
const ALPHA_OPAQUE: u32 = 0u;
const ALPHA_MASK: u32 = 1u;
const ALPHA_BLEND: u32 = 2u;

// Row k of material m.
fn mat_row(m: u32, k: u32) -> vec4<f32> {
    return tables[bitcast<u32>(tables[0].x) + m * MAT_STRIDE + k];
}

fn mat_double_sided(m: u32) -> bool {
    return bitcast<u32>(mat_row(m, 2u).z) != 0u;
}

fn mat_alpha_mode(m: u32) -> u32 {
    return bitcast<u32>(mat_row(m, 3u).x);
}

fn wrap_index(i: i32, n: i32, mode: u32) -> i32 {
    if mode == WRAP_CLAMP {
        return clamp(i, 0, n - 1);
    }
    if mode == WRAP_MIRROR {
        let p = ((i % (2 * n)) + 2 * n) % (2 * n);
        return select(2 * n - 1 - p, p, p < n);
    }
    return ((i % n) + n) % n;
}

// Bilinear lookup of texture t with its wrap modes, as scene::Texture::sample.
fn tex_sample(t: u32, uv: vec2<f32>) -> vec4<f32> {
    let h = tables[bitcast<u32>(tables[0].y) + t];
    let off = bitcast<u32>(h.x);
    let w = i32(bitcast<u32>(h.y));
    let ht = i32(bitcast<u32>(h.z));
    let modes = bitcast<u32>(h.w);
    let x = uv.x * f32(w) - 0.5;
    let y = uv.y * f32(ht) - 0.5;
    let x0 = floor(x);
    let y0 = floor(y);
    let fx = x - x0;
    let fy = y - y0;
    let xi = i32(clamp(x0, -1e9, 1e9));
    let yi = i32(clamp(y0, -1e9, 1e9));
    let xa = wrap_index(xi, w, modes & 255u);
    let xb = wrap_index(xi + 1, w, modes & 255u);
    let ya = wrap_index(yi, ht, modes >> 8u);
    let yb = wrap_index(yi + 1, ht, modes >> 8u);
    let c00 = tables[off + u32(ya * w + xa)];
    let c10 = tables[off + u32(ya * w + xb)];
    let c01 = tables[off + u32(yb * w + xa)];
    let c11 = tables[off + u32(yb * w + xb)];
    let top = c00 + (c10 - c00) * fx;
    let bottom = c01 + (c11 - c01) * fx;
    return top + (bottom - top) * fy;
}

// The UV set (0 or 1) material m's base colour texture reads.
fn mat_base_uv_set(m: u32) -> u32 {
    return bitcast<u32>(mat_row(m, 2u).x);
}

// glTF alpha of material m at `uv`, the point's coordinates in the base colour texture's
// UV set (Scene::coverage).
fn mat_coverage(m: u32, uv: vec2<f32>) -> f32 {
    var a = mat_row(m, 3u).z;
    let tex = bitcast<u32>(mat_row(m, 0u).w);
    if tex != NO_TEXTURE {
        a *= tex_sample(tex, uv).w;
    }
    return a;
}

// Whether a point of material m with this coverage stops light, given a uniform draw in
// [0, 1) for BLEND (Scene::stops_ray).
fn alpha_keeps(m: u32, coverage: f32, draw: f32) -> bool {
    let mode = mat_alpha_mode(m);
    if mode == ALPHA_MASK {
        return coverage >= mat_row(m, 3u).y;
    }
    if mode == ALPHA_BLEND {
        return draw < coverage;
    }
    return true;
}

// scene::blend_draw: a ray's draw for triangle `id`, hashed from its index and the ray's
// bits in the CPU's order, so one ray decides alike on the CPU and the GPU.
fn alpha_draw(o: vec3<f32>, d: vec3<f32>, id: u32) -> f32 {
    var x = pcg(id);
    x = pcg(bitcast<u32>(d.z) ^ x);
    x = pcg(bitcast<u32>(d.y) ^ x);
    x = pcg(bitcast<u32>(d.x) ^ x);
    x = pcg(bitcast<u32>(o.z) ^ x);
    x = pcg(bitcast<u32>(o.y) ^ x);
    x = pcg(bitcast<u32>(o.x) ^ x);
    return unit_float(x);
}
