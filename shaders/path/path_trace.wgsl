// path/path_trace.wgsl: `path` on the GPU, as one megakernel: one invocation per valid
// texel runs that texel's samples of the step, each a whole path, and blends the mean into
// the step's half accumulator (src/engine/technique/path_gpu.rs). The estimator is the
// CPU's (src/engine/technique/path.rs) line for line: cosine-sampled continuation, NEE to
// punctual lights, the sun's cone and emissive triangles with the power heuristic against
// the continuation, Russian roulette on throughput below tau, the barycentric inset and
// the surface offset at every vertex, black opaque back faces of single-sided surfaces.
// Rays: gpu/bvh.wgsl (bindings 0 and 1), in the scene's world space, f32.
//
// Randomness: PCG-RXS-M-XS 32/32 (O'Neill 2014; the `pcg` hash of common.wgsl is its
// output step) with a per-stream increment. A texel's streams differ by increment (a hash
// of the seed and the texel), a (step, sample)'s by starting state (a hash chain of the
// seed, step and sample), so no two (seed, step, texel, sample) share a sequence except
// by a 32-bit hash collision of two (step, sample) keys of one texel. Period 2^32; a path
// of 65536 bounces draws at most 8 numbers a vertex, 5e5 in all. The streams are not the
// CPU's (its PCG32 needs 64-bit integers, which WGSL lacks): GPU and CPU bakes agree in
// the mean, not sample for sample. Floats carry 24 random bits, as on the CPU.
//
// Bounds: a path ends at max_bounces vertices (<= 65536); steps are counted in 32 bits
// here (4e9 steps); the accumulators are running means in f32 (blend 1/k of the k-th step
// of a half), whose rounding is 1e-7 relative a step, far below any bake's noise.
// llvmpipe (lavapipe) ends every loop of an invocation once all of them together have run
// 65535 iterations (its `looplimiter`), about 1300 bounces here across a step's samples:
// paths that long (albedo 0.99 and above in closed rooms) would be cut and read dark.
// A path or sample loop ended from outside is detected (`cut`: no exit of its own taken,
// or the traversal's `overflow`), marked in the accumulator's w, and the host refuses the
// snapshot; hardware drivers have no such budget.

struct PathUniform {
    counts: vec4<u32>,   // x: valid texels n, y: samples per step, z: max bounces, w: step index
    keys: vec4<u32>,     // x: seed low 32 bits, y: seed high, z: half (0 even, 1 odd), w: PATH_* flags
    tables: vec4<u32>,   // x: materials offset, y: lights offset, z: light count, w: emitters offset
    tables2: vec4<u32>,  // x: emitter count, y: texture headers offset, z, w: unused
    sky: vec4<f32>,      // rgb: radiance; w: SKY_*
    sun_axis: vec4<f32>, // xyz: unit direction toward the sun; w: cos of the disc's half angle
    sun: vec4<f32>,      // rgb: radiance; w: solid angle (0: no sun)
    f: vec4<f32>,        // x: Russian roulette threshold tau; y: surface offset; z: blend 1/k; w: unused
}

const PATH_DIRECT: u32 = 1u;   // keep the direct layer
const PATH_MOMENTS: u32 = 2u;  // keep the first moments (sh layers)
const SKY_UPPER: f32 = 1.0;
const SKY_FULL: f32 = 2.0;
const LIGHT_DIRECTIONAL: u32 = 0u;
const WRAP_MIRROR: u32 = 1u;
const WRAP_CLAMP: u32 = 2u;
const NO_TEXTURE: u32 = 0xffffffffu;
const PATH_INV_PI: f32 = 0.31830988618;
const PATH_TWO_PI: f32 = 6.28318530718;
const PATH_FAR: f32 = 3.4e38;      // "no limit" for a ray
const PDF_INFINITE: f32 = 3.0e38;  // a density that is a delta (power heuristic weight 1)
const SHADE_STRIDE: u32 = 6u;

@group(0) @binding(2) var<uniform> pu: PathUniform;
@group(0) @binding(3) var<storage, read> texels: array<TexelGeom>;
// Per triangle slot, 6 vec4: n0 | material (bits), n1 | emitter pick probability,
// n2 | area, (uv0, uv1), (uv2, lm0), (lm1, lm2).
@group(0) @binding(4) var<storage, read> shade: array<vec4<f32>>;
// Materials (3 vec4 each), lights (4 each), emitters (1 each), texture headers (1 each)
// and texture texels (1 each, linear RGBA), at the offsets in `pu.tables`.
@group(0) @binding(5) var<storage, read> tables: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> acc_total: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> acc_direct: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> acc_moment: array<vec4<f32>>;

// ---- randomness ------------------------------------------------------------------------
struct Rng {
    state: u32,
    inc: u32,
}

fn rng_next(r: ptr<function, Rng>) -> f32 {
    let old = (*r).state;
    (*r).state = old * 747796405u + (*r).inc;
    let word = ((old >> ((old >> 28u) + 4u)) ^ old) * 277803737u;
    return f32(((word >> 22u) ^ word) >> 8u) * (1.0 / 16777216.0);
}

fn rng_for(texel: u32, sample: u32) -> Rng {
    let base = pcg(pu.keys.x ^ pcg(pu.keys.y));
    var r = Rng(pcg(pu.counts.w ^ pcg(sample ^ base)), (pcg(texel ^ pcg(base ^ 0x5bd1e995u)) << 1u) | 1u);
    rng_next(&r);
    return r;
}

// ---- sampling (engine::raytrace) -------------------------------------------------------
// Duff et al. 2017; the sign of n.z read from its bit, as f32::copysign does.
fn basis_t(n: vec3<f32>) -> vec3<f32> {
    let sgn = select(1.0, -1.0, (bitcast<u32>(n.z) & 0x80000000u) != 0u);
    let a = -1.0 / (sgn + n.z);
    let b = n.x * n.y * a;
    return vec3<f32>(1.0 + sgn * n.x * n.x * a, sgn * b, -sgn * n.x);
}

fn basis_b(n: vec3<f32>) -> vec3<f32> {
    let sgn = select(1.0, -1.0, (bitcast<u32>(n.z) & 0x80000000u) != 0u);
    let a = -1.0 / (sgn + n.z);
    let b = n.x * n.y * a;
    return vec3<f32>(b, sgn + n.y * n.y * a, -n.y);
}

fn cosine_sample(n: vec3<f32>, u1: f32, u2: f32) -> vec3<f32> {
    let r = sqrt(u1);
    let phi = PATH_TWO_PI * u2;
    return normalize(basis_t(n) * (r * cos(phi)) + basis_b(n) * (r * sin(phi)) + n * sqrt(max(1.0 - u1, 0.0)));
}

fn cone_sample(axis: vec3<f32>, cos_max: f32, u1: f32, u2: f32) -> vec3<f32> {
    let cos_t = 1.0 - u1 * (1.0 - cos_max);
    let sin_t = sqrt(max(1.0 - cos_t * cos_t, 0.0));
    let phi = PATH_TWO_PI * u2;
    return normalize(basis_t(axis) * (sin_t * cos(phi)) + basis_b(axis) * (sin_t * sin(phi)) + axis * cos_t);
}

fn inset(b: vec3<f32>) -> vec3<f32> {
    return b * (1.0 - 1e-5) + vec3<f32>(1e-5 / 3.0);
}

// Power heuristic, written as 1 / (1 + (b/a)^2) so that huge densities cannot overflow
// a^2 into inf / inf (the same weight as a^2 / (a^2 + b^2)).
fn power_heuristic(a: f32, b: f32) -> f32 {
    if a >= PDF_INFINITE {
        return 1.0;
    }
    if a <= 0.0 {
        return 0.0;
    }
    if b <= 0.0 {
        return 1.0;
    }
    if a >= b {
        let r = b / a;
        return 1.0 / (1.0 + r * r);
    }
    let r = a / b;
    let r2 = r * r;
    return r2 / (1.0 + r2);
}

fn normalize_or_zero(v: vec3<f32>) -> vec3<f32> {
    let l = length(v);
    return select(vec3<f32>(0.0), v / l, l > 0.0 && l < PATH_FAR);
}

// ---- scene data --------------------------------------------------------------------------

fn tri_geo(slot: u32) -> vec3<f32> {
    let t = bvh_tris[slot];
    return normalize_or_zero(cross(t.e1, t.e2));
}

fn tri_point(slot: u32, b: vec3<f32>) -> vec3<f32> {
    let t = bvh_tris[slot];
    return t.p0 + t.e1 * b.y + t.e2 * b.z;
}

fn tri_material(slot: u32) -> u32 { return bitcast<u32>(shade[slot * SHADE_STRIDE].w); }
fn tri_pick(slot: u32) -> f32 { return shade[slot * SHADE_STRIDE + 1u].w; }
fn tri_area(slot: u32) -> f32 { return shade[slot * SHADE_STRIDE + 2u].w; }

fn tri_uv(slot: u32, uv_set: u32, b: vec3<f32>) -> vec2<f32> {
    let base = slot * SHADE_STRIDE;
    let a = shade[base + 3u];
    let c = shade[base + 4u];
    let d = shade[base + 5u];
    if uv_set == 1u {
        return c.zw * b.x + d.xy * b.y + d.zw * b.z;
    }
    return a.xy * b.x + a.zw * b.y + c.xy * b.z;
}

fn tri_shading_normal(slot: u32, b: vec3<f32>) -> vec3<f32> {
    let base = slot * SHADE_STRIDE;
    return normalize_or_zero(shade[base].xyz * b.x + shade[base + 1u].xyz * b.y + shade[base + 2u].xyz * b.z);
}

fn mat_double_sided(m: u32) -> bool {
    return bitcast<u32>(tables[pu.tables.x + m * 3u + 2u].z) != 0u;
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

// Bilinear lookup with the texture's wrap modes, as scene::Texture::sample. Coordinates
// beyond +-1e9 texels are clamped there (i32), where f32 has no fraction left anyway.
fn tex_sample(t: u32, uv: vec2<f32>) -> vec4<f32> {
    let h = tables[pu.tables2.y + t];
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

fn albedo_at(slot: u32, b: vec3<f32>) -> vec3<f32> {
    let m = tri_material(slot);
    let row = tables[pu.tables.x + m * 3u];
    var c = row.xyz;
    let tex = bitcast<u32>(row.w);
    if tex != NO_TEXTURE {
        let uv_set = bitcast<u32>(tables[pu.tables.x + m * 3u + 2u].x);
        c *= tex_sample(tex, tri_uv(slot, uv_set, b)).xyz;
    }
    return c;
}

fn emission_at(slot: u32, b: vec3<f32>) -> vec3<f32> {
    let m = tri_material(slot);
    let row = tables[pu.tables.x + m * 3u + 1u];
    var e = row.xyz;
    let tex = bitcast<u32>(row.w);
    if any(e != vec3<f32>(0.0)) && tex != NO_TEXTURE {
        let uv_set = bitcast<u32>(tables[pu.tables.x + m * 3u + 2u].y);
        e *= tex_sample(tex, tri_uv(slot, uv_set, b)).xyz;
    }
    return e;
}

fn sky_radiance(w: vec3<f32>) -> vec3<f32> {
    if pu.sky.w == SKY_FULL || (pu.sky.w == SKY_UPPER && w.y > 0.0) {
        return pu.sky.xyz;
    }
    return vec3<f32>(0.0);
}

// scene::PunctualLight::attenuation without the 1/d^2.
fn light_attenuation(li: u32, dist: f32, dir: vec3<f32>) -> f32 {
    let base = pu.tables.y + li * 4u;
    let range = tables[base + 1u].w;
    var window = 1.0;
    if range > 0.0 {
        let q = dist / range;
        let q2 = q * q;
        let a = clamp(1.0 - q2 * q2, 0.0, 1.0);
        window = a * a;
    }
    let kind = bitcast<u32>(tables[base].w);
    if kind == 2u {
        let cone = tables[base + 3u];
        let a = clamp((dot(dir, tables[base + 2u].xyz) - cone.x) * cone.y, 0.0, 1.0);
        return window * a * a;
    }
    return window;
}

// ---- the estimator ---------------------------------------------------------------------
struct Light {
    sum: vec3<f32>,
    m0: vec3<f32>,  // first moment along world x (rgb), as path::Moment
    m1: vec3<f32>,
    m2: vec3<f32>,
}

fn moment_add(l: ptr<function, Light>, c: vec3<f32>, d: vec3<f32>) {
    (*l).m0 += c * d.x;
    (*l).m1 += c * d.y;
    (*l).m2 += c * d.z;
}

fn front_of(d: vec3<f32>, n: vec3<f32>, ng: vec3<f32>) -> bool {
    return dot(d, n) > 0.0 && dot(d, ng) > 0.0;
}

// path::PathContext::next_event.
fn next_event(x: vec3<f32>, n: vec3<f32>, ng: vec3<f32>, rng: ptr<function, Rng>) -> Light {
    var out = Light(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    for (var li = 0u; li < pu.tables.z; li++) {
        let base = pu.tables.y + li * 4u;
        let intensity = tables[base].xyz;
        let kind = bitcast<u32>(tables[base].w);
        if kind == LIGHT_DIRECTIONAL {
            let d = -tables[base + 2u].xyz;
            if front_of(d, n, ng) && bvh_unoccluded(x, d, PATH_FAR) {
                let c = intensity * dot(d, n) * PATH_INV_PI;
                out.sum += c;
                moment_add(&out, c, d);
            }
        } else {
            let to = tables[base + 1u].xyz - x;
            let dist2 = dot(to, to);
            if dist2 <= 0.0 {
                continue;
            }
            let dist = sqrt(dist2);
            let d = to / dist;
            if !front_of(d, n, ng) {
                continue;
            }
            let falloff = light_attenuation(li, dist, -d) / dist2;
            if falloff > 0.0 && bvh_unoccluded(x, d, dist * (1.0 - 1e-4)) {
                let c = intensity * falloff * dot(d, n) * PATH_INV_PI;
                out.sum += c;
                moment_add(&out, c, d);
            }
        }
    }
    if pu.sun.w > 0.0 {
        let u1 = rng_next(rng);
        let u2 = rng_next(rng);
        let d = cone_sample(pu.sun_axis.xyz, pu.sun_axis.w, u1, u2);
        if front_of(d, n, ng) && bvh_unoccluded(x, d, PATH_FAR) {
            let pdf_light = 1.0 / pu.sun.w;
            let cos_n = dot(d, n);
            let w = power_heuristic(pdf_light, cos_n * PATH_INV_PI);
            let c = pu.sun.xyz * cos_n * PATH_INV_PI / pdf_light * w;
            out.sum += c;
            moment_add(&out, c, d);
        }
    }
    let count = pu.tables2.x;
    if count > 0u {
        let u = rng_next(rng);
        // partition_point(cdf <= u): the first entry whose cdf exceeds u.
        var lo = 0u;
        var hi = count;
        while lo < hi {
            let mid = (lo + hi) / 2u;
            if tables[pu.tables.w + mid].y <= u {
                lo = mid + 1u;
            } else {
                hi = mid;
            }
        }
        let k = min(lo, count - 1u);
        let slot = bitcast<u32>(tables[pu.tables.w + k].x);
        var b1 = rng_next(rng);
        var b2 = rng_next(rng);
        if b1 + b2 > 1.0 {
            b1 = 1.0 - b1;
            b2 = 1.0 - b2;
        }
        let bary = vec3<f32>(1.0 - b1 - b2, b1, b2);
        let y = tri_point(slot, bary);
        let to = y - x;
        let dist2 = dot(to, to);
        let dist = sqrt(dist2);
        if dist > 0.0 {
            let d = to / dist;
            let geo = tri_geo(slot);
            var cos_l = -dot(d, geo);
            if mat_double_sided(tri_material(slot)) {
                cos_l = abs(cos_l);
            }
            if front_of(d, n, ng) && cos_l > 0.0 {
                let emission = emission_at(slot, bary);
                // Stop short of the emitter so it does not occlude its own sample.
                if any(emission != vec3<f32>(0.0)) && bvh_unoccluded(x, d, dist * (1.0 - 1e-4)) {
                    let pdf_light = tri_pick(slot) / tri_area(slot) * dist2 / cos_l;
                    let cos_n = dot(d, n);
                    let w = power_heuristic(pdf_light, cos_n * PATH_INV_PI);
                    let c = emission * cos_n * PATH_INV_PI / pdf_light * w;
                    out.sum += c;
                    moment_add(&out, c, d);
                }
            }
        }
    }
    return out;
}

struct PathSample {
    total: vec3<f32>,
    direct: vec3<f32>,
    m: Light,  // sum unused
    cut: bool, // the path was ended from outside (the adapter's loop budget), not by its rules
}

// path::PathContext::radiance.
fn radiance(x0: vec3<f32>, n0: vec3<f32>, ng0: vec3<f32>, rng: ptr<function, Rng>) -> PathSample {
    var x = x0;
    var n = n0;
    var ng = ng0;
    var throughput = vec3<f32>(1.0);
    var total = vec3<f32>(0.0);
    var direct = vec3<f32>(0.0);
    var bounce = 0u;
    var moment = Light(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    var first_dir = vec3<f32>(0.0);
    var have_first = false;
    var first_nee = vec3<f32>(0.0);
    let tau = pu.f.x;
    let eps = pu.f.y;
    var ended = false;
    loop {
        let nee = next_event(x, n, ng, rng);
        total += throughput * nee.sum;
        if bounce == 0u {
            direct += nee.sum;
            first_nee = nee.sum;
            moment = nee;
        }
        let u1 = rng_next(rng);
        let u2 = rng_next(rng);
        let dir = cosine_sample(n, u1, u2);
        let cos_n = dot(dir, n);
        if dot(dir, ng) <= 0.0 || cos_n <= 0.0 {
            ended = true;
            break;  // below the geometric surface: the surface itself blocks it
        }
        if bounce == 0u {
            first_dir = dir;
            have_first = true;
        }
        let pdf_bsdf = cos_n * PATH_INV_PI;
        let hit = bvh_closest(x, dir, PATH_FAR);
        if hit.overflow {
            break;  // the traversal was cut: so is the path (`ended` stays false)
        }
        if hit.slot == BVH_MISS {
            var l = sky_radiance(dir);
            if pu.sun.w > 0.0 && dot(dir, pu.sun_axis.xyz) >= pu.sun_axis.w {
                l += pu.sun.xyz * power_heuristic(pdf_bsdf, 1.0 / pu.sun.w);
            }
            total += throughput * l;
            if bounce == 0u {
                direct += l;
            }
            ended = true;
            break;
        }
        let slot = hit.slot;
        let bary = vec3<f32>(1.0 - hit.u - hit.v, hit.u, hit.v);
        let m = tri_material(slot);
        let geo = tri_geo(slot);
        let front = dot(dir, geo) < 0.0;
        if !front && !mat_double_sided(m) {
            ended = true;
            break;  // back of a single-sided surface: black and opaque
        }
        let p = tri_point(slot, inset(bary));
        let emission = emission_at(slot, bary);
        if any(emission != vec3<f32>(0.0)) {
            // Density with which next-event estimation would have picked this point.
            let cos_l = abs(dot(dir, geo));
            var pdf_light = PDF_INFINITE;
            if cos_l > 0.0 {
                pdf_light = tri_pick(slot) / tri_area(slot) * hit.t * hit.t / cos_l;
            }
            let l = emission * power_heuristic(pdf_bsdf, pdf_light);
            total += throughput * l;
            if bounce == 0u {
                direct += l;
            }
        }
        bounce += 1u;
        if bounce >= pu.counts.z {
            ended = true;
            break;
        }
        throughput *= albedo_at(slot, bary);
        let peak = max(throughput.x, max(throughput.y, throughput.z));
        if peak < tau {
            // Below tau: survive with probability peak / tau, then carry on at tau.
            if peak <= 0.0 {
                ended = true;
                break;
            }
            if rng_next(rng) * tau >= peak {
                ended = true;
                break;
            }
            throughput *= tau / peak;
        }
        let side = select(-1.0, 1.0, front);
        let shading = tri_shading_normal(slot, bary) * side;
        ng = geo * side;
        n = select(ng, shading, dot(shading, ng) > 0.0);
        x = p + ng * eps;
    }
    // Everything but the first vertex's light samples arrived along the first direction.
    if have_first {
        moment_add(&moment, total - first_nee, first_dir);
    }
    return PathSample(total, direct, moment, !ended);
}

fn blend(old: vec4<f32>, v: vec3<f32>) -> vec4<f32> {
    return vec4<f32>(old.xyz + (v - old.xyz) * pu.f.z, old.w);  // w: the cut mark, kept
}

@compute @workgroup_size(64)
fn trace(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = invocation_index(wid, nwg, lid);
    let n = pu.counts.x;
    if i >= n {
        return;
    }
    let t = texels[i];
    var total = vec3<f32>(0.0);
    var direct = vec3<f32>(0.0);
    var m0 = vec3<f32>(0.0);
    var m1 = vec3<f32>(0.0);
    var m2 = vec3<f32>(0.0);
    let spp = pu.counts.y;
    var ran = 0u;
    var cut = false;
    for (var s = 0u; s < spp; s++) {
        var rng = rng_for(i, s);
        let r = radiance(t.position.xyz, t.normal.xyz, t.geo_normal.xyz, &rng);
        ran += 1u;
        cut = cut || r.cut;
        total += r.total;
        direct += r.direct;
        m0 += r.m.m0;
        m1 += r.m.m1;
        m2 += r.m.m2;
    }
    let k = 1.0 / f32(spp);
    let slot = pu.keys.z * n + i;
    acc_total[slot] = blend(acc_total[slot], total * k);
    // A sample loop or a path ended from outside (llvmpipe's loop budget, see the header):
    // marked in w, which the host checks at every snapshot rather than deliver it dark.
    if cut || ran < spp {
        acc_total[slot].w = 1.0;
    }
    if (pu.keys.w & PATH_DIRECT) != 0u {
        acc_direct[slot] = blend(acc_direct[slot], direct * k);
    }
    if (pu.keys.w & PATH_MOMENTS) != 0u {
        acc_moment[slot * 3u] = blend(acc_moment[slot * 3u], m0 * k);
        acc_moment[slot * 3u + 1u] = blend(acc_moment[slot * 3u + 1u], m1 * k);
        acc_moment[slot * 3u + 2u] = blend(acc_moment[slot * 3u + 2u], m2 * k);
    }
}
