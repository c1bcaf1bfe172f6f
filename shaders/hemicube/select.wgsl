// hemicube/select.wgsl: the step's shooters and their hemicube views, one invocation per
// shooter, all on the GPU (no readback).
//
// Invocations k < K_e copy the emitter samples the CPU drew (a point on an emissive
// triangle, chosen by power). Invocations K_e <= k < K_e + K_r draw a texel shooter
// (seed section 4.1): r uniform in the (k - K_e)-th of K_r equal strata of [0, total)
// from a PCG hash of (step, k), then the
// descent of the sum pyramid from its top, at each level taking the first of the four
// children whose running sum exceeds r and subtracting what came before, so a leaf is
// reached with probability power / total. Texel merging (seed section 5): the shooter is
// the group of texels in the leaf's block at the shooter level L (2^L x 2^L texels) that
// lie on the same surface as the leaf (same mesh and material, normals within 25
// degrees, and near each other in space, so charts that touch in UV space do not merge).
// The group is drawn with probability p = (its summed power) / total, whichever of its
// texels the descent reached, so A / (p K) is its unbiased weight; its radiance is the
// area-weighted mean of its texels' and its normal their mean. The five views of its
// hemicube (gpu/shadow_atlas.wgsl renders them) are written for the CPU's fixed tiles.

@group(0) @binding(0) var<uniform> params: HcParams;
@group(0) @binding(1) var<storage, read> mats: array<TexelMat>;
@group(0) @binding(2) var<storage, read> irr: array<vec4<f32>>;    // 2N: two halves
@group(0) @binding(3) var<storage, read> dirs: array<vec4<f32>>;   // 2N (glossy) or a stub
@group(0) @binding(4) var<storage, read> pyramid: array<f32>;
@group(0) @binding(5) var<storage, read> pixel_texel: array<u32>;
@group(0) @binding(6) var<storage, read> geom: array<TexelGeom>;
@group(0) @binding(7) var<storage, read> emitters: array<Shooter>;  // K_e CPU samples
@group(0) @binding(8) var<storage, read_write> shooters: array<Shooter>;
@group(0) @binding(9) var<storage, read_write> views: array<ShadowView>;  // 5 per shooter
@group(0) @binding(10) var<storage, read> tiles: array<vec4<u32>>;       // 5 per shooter: x, y, side
@group(0) @binding(11) var<storage, read> cell_pieces: array<CellPiece>;

const NO_TEXEL_HC: u32 = 0xffffffffu;
// Near plane of the hemicube faces (normalised units, as vpl's cube faces).
const HC_NEAR: f32 = 1.0e-4;

fn level_offset(l: u32) -> u32 {
    var off = 0u;
    let s = params.dims.w;
    for (var k = 0u; k < l; k++) {
        let side = s >> k;
        off += side * side;
    }
    return off;
}

// Orthonormal tangents of unit n (Duff et al. 2017, as engine::raytrace::basis).
fn hc_basis(n: vec3<f32>) -> array<vec3<f32>, 2> {
    let sign = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    return array<vec3<f32>, 2>(
        vec3<f32>(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        vec3<f32>(b, sign + n.y * n.y * a, -n.y),
    );
}

fn write_views(k: u32, s: Shooter) {
    let far = length(s.pos.xyz) + 2.2;
    for (var f = 0u; f < 5u; f++) {
        let axes = hc_face_axes(s, f);
        let tile = tiles[5u * k + f];
        var v: ShadowView;
        v.origin = vec4<f32>(s.pos.xyz, HC_NEAR);
        v.right = vec4<f32>(axes[1], 0.0);
        v.up = vec4<f32>(axes[2], 0.0);
        v.fwd = vec4<f32>(axes[0], far);
        v.rect = vec4<u32>(tile.x, tile.y, tile.z, VIEW_PERSPECTIVE);
        views[5u * k + f] = v;
    }
}

fn no_shooter() -> Shooter {
    var s: Shooter;
    s.pos = vec4<f32>(0.0);
    s.nrm = vec4<f32>(0.0, 0.0, 1.0, 0.0);
    s.diffuse = vec4<f32>(0.0);
    s.spec = vec4<f32>(0.0);
    s.in_dir = vec4<f32>(0.0, 0.0, 1.0, 0.0);
    s.frame_t = vec4<f32>(1.0, 0.0, 0.0, 0.0);
    s.frame_b = vec4<f32>(0.0, 1.0, 0.0, 0.0);
    return s;
}

// Descends the pyramid with r in [0, total): the leaf pixel (x, y) of the S x S grid.
fn descend(r_in: f32) -> vec2<u32> {
    var r = r_in;
    var cell = vec2<u32>(0u, 0u);
    let top = params.shoot.x;
    for (var l = i32(top) - 1; l >= 0; l--) {
        let side = params.dims.w >> u32(l);
        let off = level_offset(u32(l));
        let base = cell * 2u;
        var chosen = base;
        var last_nonzero = base;
        var found = false;
        for (var c = 0u; c < 4u; c++) {
            let q = base + vec2<u32>(c & 1u, c >> 1u);
            let v = pyramid[off + q.y * side + q.x];
            if v > 0.0 {
                last_nonzero = q;
                if !found {
                    if r < v {
                        chosen = q;
                        found = true;
                    } else {
                        r -= v;
                    }
                }
            }
        }
        // Rounding can leave r just above the children's sum: take the last child with
        // power rather than an empty one.
        cell = select(last_nonzero, chosen, found);
    }
    return cell;
}

// A uniform point of texel c's cell and the surface normal there (engine::atlas::cells):
// a piece by area, then a uniform point of the piece (the square-root map), from three
// more PCG draws chained on the descent's hash h.
fn cell_point(c: u32, mc: TexelMat, h: u32) -> array<vec3<f32>, 2> {
    let h1 = pcg(h ^ 0x68E31DA4u);
    let h2 = pcg(h1);
    let h3 = pcg(h2);
    let first = mc.ids.w;
    let end = select(mats[c + 1u].ids.w, arrayLength(&cell_pieces), c + 1u >= params.dims.x);
    var r = unit_float(h1) * mc.kd.w;
    var k = first;
    // Rounding can leave r past the last piece: the last one is taken.
    for (; k + 1u < end; k++) {
        let a = cell_pieces[k].a.w;
        if r < a {
            break;
        }
        r -= a;
    }
    let piece = cell_pieces[k];
    let su = sqrt(unit_float(h2));
    let v = unit_float(h3);
    let p = piece.a.xyz + piece.e1.xyz * (su * (1.0 - v)) + piece.e2.xyz * (su * v);
    return array<vec3<f32>, 2>(p, normalize(cross(piece.e1.xyz, piece.e2.xyz)));
}

@compute @workgroup_size(64)
fn select_shooters(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    let ke = params.shoot.z;
    let kr = params.shoot.w;
    if k >= ke + kr {
        return;
    }
    if k < ke {
        var s = emitters[k];
        let fr = hc_basis(s.nrm.xyz);
        s.frame_t = vec4<f32>(fr[0], 0.0);
        s.frame_b = vec4<f32>(fr[1], 0.0);
        shooters[k] = s;
        write_views(k, s);
        return;
    }
    let total = pyramid[level_offset(params.shoot.x)];
    var s = no_shooter();
    if total > 0.0 && total < 3.0e38 {
        let h = pcg(params.step.z ^ pcg(k * 0x9E3779B9u + 0x632BE5ABu));
        // Stratified: texel shooter j of K_r draws r in the j-th K_r-th of [0, total), so
        // the step's shooters spread over the pyramid's power (in its quadtree order,
        // which keeps strata spatially coherent); each still has the weight A / (p K_r).
        let stratum = (f32(k - ke) + unit_float(h)) / f32(kr);
        let leaf = descend(min(stratum, 1.0) * total);
        let w = params.dims.y;
        let ht = params.dims.z;
        let c = pixel_texel[min(leaf.y, ht - 1u) * w + min(leaf.x, w - 1u)];
        if c != NO_TEXEL_HC {
            let mc = mats[c];
            let gc = geom[c];
            let cur = params.step.x;
            let prev = 1u - cur;
            let n = params.dims.x;
            let lvl = params.shoot.y;
            let bsize = 1u << lvl;
            let bx = (leaf.x >> lvl) << lvl;
            let by = (leaf.y >> lvl) << lvl;
            let reach = 2.0 * f32(bsize) * sqrt(mc.kd.w);
            var area = 0.0;
            var power = 0.0;
            var pos = vec3<f32>(0.0);
            var nrm = vec3<f32>(0.0);
            var kd_i = vec3<f32>(0.0);
            var ks_i = vec3<f32>(0.0);
            var dir = vec3<f32>(0.0);
            for (var dy = 0u; dy < bsize; dy++) {
                for (var dx = 0u; dx < bsize; dx++) {
                    let x = bx + dx;
                    let y = by + dy;
                    if x >= w || y >= ht {
                        continue;
                    }
                    let j = pixel_texel[y * w + x];
                    if j == NO_TEXEL_HC {
                        continue;
                    }
                    let mj = mats[j];
                    let gj = geom[j];
                    let same = mj.ids.x == mc.ids.x && mj.ids.y == mc.ids.y
                        && dot(gj.normal.xyz, gc.normal.xyz) > 0.9
                        && distance(gj.position.xyz, gc.position.xyz) <= reach;
                    if !same {
                        continue;
                    }
                    let a = mj.kd.w;
                    let ij = irr[prev * n + j].rgb;
                    area += a;
                    power += pyramid[y * params.dims.w + x];
                    pos += a * gj.position.xyz;
                    nrm += a * gj.normal.xyz;
                    kd_i += a * ij * mj.kd.rgb;
                    ks_i += a * ij * mj.ks.rgb;
                    if (params.step.w & HC_GLOSSY) != 0u {
                        dir += dirs[prev * n + j].xyz;
                    }
                }
            }
            if area > 0.0 && power > 0.0 {
                s.pos = vec4<f32>(pos / area, area);
                s.nrm = vec4<f32>(normalize(nrm), area * total / (power * params.f.w));
                if lvl == 0u {
                    // Unmerged: a uniform point of the texel's cell, with no disc term.
                    let p = cell_point(c, mc, h);
                    s.pos = vec4<f32>(p[0], 0.0);
                    s.nrm = vec4<f32>(p[1], s.nrm.w);
                }
                s.diffuse = vec4<f32>(kd_i / (area * 3.14159265), 0.0);
                let has_dir = dot(dir, dir) > 0.0;
                s.in_dir = vec4<f32>(select(s.nrm.xyz, normalize(dir), has_dir), 0.0);
                // Without a known incoming direction (the diffuse-only variant keeps none,
                // and a glossy texel whose light cancelled out has a zero sum) the lobe
                // cannot be aimed: its light goes out diffusely, energy kept.
                let spec_i = ks_i / area;
                if has_dir {
                    s.spec = vec4<f32>(spec_i, mc.ks.w);
                } else {
                    s.diffuse = vec4<f32>(s.diffuse.rgb + spec_i / 3.14159265, 0.0);
                }
            }
        }
    }
    let fr = hc_basis(s.nrm.xyz);
    s.frame_t = vec4<f32>(fr[0], 0.0);
    s.frame_b = vec4<f32>(fr[1], 0.0);
    shooters[k] = s;
    write_views(k, s);
}
