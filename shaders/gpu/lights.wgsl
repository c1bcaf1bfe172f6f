// gpu/lights.wgsl: the scene as rays shade it, and next-event estimation to its lights.
// A library (no entry points), prepended after gpu/bvh.wgsl to every pass that samples the
// scene's light with rays: `path` (path/path_trace.wgsl) and the shared direct-light pass
// (gpu/direct_light.wgsl, src/engine/gpu/direct_light.rs), after gpu/materials.wgsl, whose
// `tables` it declares (binding 4). It owns bindings 2-4; the buffers are built once by
// src/engine/gpu/scene_rays.rs. It also defines gpu/bvh.wgsl's alpha test.
//
// Sampling (engine::raytrace, line for line): cosine-weighted directions, cones, the
// power heuristic. Next-event estimation (path::PathContext::next_event): every punctual
// and directional light (delta lights: light sampling only), the sun's cone (one uniform
// direction) and one emissive triangle (picked in proportion to area x emitted luminance
// from the CPU's EmitterTable, a uniform point on it). `mis` weights the sun and emitter
// samples with the power heuristic against a cosine-sampled continuation (what `path`
// also traces); without a continuation (`mis` false) the weight is 1, the plain light-
// sampling estimator, unbiased on its own. `scene_u.tables2.z` selects the sources
// (LIGHTS_*), so a technique that transports some light itself can leave it out.
//
// Randomness: PCG-RXS-M-XS 32/32 streams (O'Neill 2014), 24 random bits a float; each pass
// seeds its own streams (see its header). Precision: world space f32, as the CPU tracer.
// Bounds: a shadow ray to a punctual light or an emitter stops 1e-4 of the distance short,
// so the light's own surface does not occlude it.

struct SceneUniform {
    // x: materials offset, y: lights offset, z: light count, w: emitters offset (the
    // materials and textures are found through the tables' own row 0, gpu/materials.wgsl)
    tables: vec4<u32>,
    tables2: vec4<u32>,  // x: emitter count, y: texture headers offset, z: sources (LIGHTS_*), w: unused
    sky: vec4<f32>,      // rgb: radiance; w: SKY_*
    sun_axis: vec4<f32>, // xyz: unit direction toward the sun; w: cos of the disc's half angle
    sun: vec4<f32>,      // rgb: radiance; w: solid angle (0: no sun)
}

const LIGHTS_DIRECTIONAL: u32 = 1u;  // directional lights of the scene
const LIGHTS_PUNCTUAL: u32 = 2u;     // point and spot lights
const LIGHTS_SUN: u32 = 4u;          // the job's sun
const LIGHTS_EMITTERS: u32 = 8u;     // emissive triangles
const SKY_UPPER: f32 = 1.0;
const SKY_FULL: f32 = 2.0;
const LIGHT_DIRECTIONAL: u32 = 0u;
const INV_PI: f32 = 0.31830988618;
const TWO_PI: f32 = 6.28318530718;
const RAY_FAR: f32 = 3.4e38;       // "no limit" for a ray
const PDF_INFINITE: f32 = 3.0e38;  // a density that is a delta (power heuristic weight 1)
const SHADE_STRIDE: u32 = 6u;


@group(0) @binding(2) var<uniform> scene_u: SceneUniform;
// Per triangle slot, 6 vec4: n0 | material (bits), n1 | emitter pick probability,
// n2 | area, (uv0, uv1), (uv2, lm0), (lm1, lm2).
@group(0) @binding(3) var<storage, read> shade: array<vec4<f32>>;
// The offsets row and the materials and textures that gpu/materials.wgsl reads, then the
// lights (4 vec4 each) and emitters (1 each) at the offsets in `scene_u.tables`.
@group(0) @binding(4) var<storage, read> tables: array<vec4<f32>>;

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
    let phi = TWO_PI * u2;
    return normalize(basis_t(n) * (r * cos(phi)) + basis_b(n) * (r * sin(phi)) + n * sqrt(max(1.0 - u1, 0.0)));
}

fn cone_sample(axis: vec3<f32>, cos_max: f32, u1: f32, u2: f32) -> vec3<f32> {
    let cos_t = 1.0 - u1 * (1.0 - cos_max);
    let sin_t = sqrt(max(1.0 - cos_t * cos_t, 0.0));
    let phi = TWO_PI * u2;
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
    return select(vec3<f32>(0.0), v / l, l > 0.0 && l < RAY_FAR);
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

fn albedo_at(slot: u32, b: vec3<f32>) -> vec3<f32> {
    let m = tri_material(slot);
    let row = mat_row(m, 0u);
    var c = row.xyz;
    let tex = bitcast<u32>(row.w);
    if tex != NO_TEXTURE {
        c *= tex_sample(tex, tri_uv(slot, mat_base_uv_set(m), b)).xyz;
    }
    return c;
}

// The alpha test of gpu/bvh.wgsl (Scene::stops_ray) for a candidate hit at (u, v) on the
// triangle in `slot`, of a MASK or BLEND material (gpu/materials.wgsl).
fn bvh_alpha_accept(slot: u32, u: f32, v: f32, o: vec3<f32>, d: vec3<f32>) -> bool {
    let m = tri_material(slot);
    let a = mat_coverage(m, tri_uv(slot, mat_base_uv_set(m), vec3<f32>(1.0 - u - v, u, v)));
    return alpha_keeps(m, a, alpha_draw(o, d, bvh_tris[slot].id));
}

fn emission_at(slot: u32, b: vec3<f32>) -> vec3<f32> {
    let m = tri_material(slot);
    let row = mat_row(m, 1u);
    var e = row.xyz;
    let tex = bitcast<u32>(row.w);
    if any(e != vec3<f32>(0.0)) && tex != NO_TEXTURE {
        let uv_set = bitcast<u32>(mat_row(m, 2u).y);
        e *= tex_sample(tex, tri_uv(slot, uv_set, b)).xyz;
    }
    return e;
}

fn sky_radiance(w: vec3<f32>) -> vec3<f32> {
    if scene_u.sky.w == SKY_FULL || (scene_u.sky.w == SKY_UPPER && w.y > 0.0) {
        return scene_u.sky.xyz;
    }
    return vec3<f32>(0.0);
}

// scene::PunctualLight::attenuation without the 1/d^2.
fn light_attenuation(li: u32, dist: f32, dir: vec3<f32>) -> f32 {
    let base = scene_u.tables.y + li * 4u;
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

// path::PathContext::next_event: E/pi from every selected source, one sample each, and
// its first moments (the sh layers).
// MIS weight of a light sample of density `pdf_light` at cosine `cos_n`: the power
// heuristic against the cosine-sampled continuation when there is one (`mis`), else 1.
fn light_weight(mis: bool, pdf_light: f32, cos_n: f32) -> f32 {
    if mis {
        return power_heuristic(pdf_light, cos_n * INV_PI);
    }
    return 1.0;
}

// The emitter triangle's slot that uniform number `u` picks from the emitter table's CDF
// (EmitterTable::emitter_cdf's partition_point(cdf <= u): the first entry whose cdf exceeds
// u), for a scene with at least one emitter (scene_u.tables2.x > 0).
fn emitter_pick(u: f32) -> u32 {
    let count = scene_u.tables2.x;
    var lo = 0u;
    var hi = count;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if tables[scene_u.tables.w + mid].y <= u {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return bitcast<u32>(tables[scene_u.tables.w + min(lo, count - 1u)].x);
}

// Barycentrics of a uniform point on a triangle from two uniform numbers (the square
// folded along its diagonal, as raytrace's emitter sampling does).
fn uniform_bary(u: vec2<f32>) -> vec3<f32> {
    var b1 = u.x;
    var b2 = u.y;
    if b1 + b2 > 1.0 {
        b1 = 1.0 - b1;
        b2 = 1.0 - b2;
    }
    return vec3<f32>(1.0 - b1 - b2, b1, b2);
}

fn next_event(x: vec3<f32>, n: vec3<f32>, ng: vec3<f32>, mis: bool, rng: ptr<function, Rng>) -> Light {
    // The numbers drawn in the order, and under the conditions, that the estimate below
    // uses them: the sun's two, then the emitter pick and the point on it.
    let sources = scene_u.tables2.z;
    var sun_u = vec2<f32>(0.0);
    if scene_u.sun.w > 0.0 && (sources & LIGHTS_SUN) != 0u {
        sun_u.x = rng_next(rng);
        sun_u.y = rng_next(rng);
    }
    var emitter_u = vec3<f32>(0.0);
    if scene_u.tables2.x > 0u && (sources & LIGHTS_EMITTERS) != 0u {
        emitter_u.x = rng_next(rng);
        emitter_u.y = rng_next(rng);
        emitter_u.z = rng_next(rng);
    }
    return next_event_with(x, n, ng, mis, sun_u, emitter_u);
}

// next_event with its random numbers given: `sun_u` the sun's cone sample, `emitter_u` the
// emitter pick (x) and the point on the picked triangle (y, z). For a caller whose numbers
// come from a stratified sequence (`path` with `sampling: sobol`).
fn next_event_with(x: vec3<f32>, n: vec3<f32>, ng: vec3<f32>, mis: bool, sun_u: vec2<f32>, emitter_u: vec3<f32>) -> Light {
    var out = Light(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    let sources = scene_u.tables2.z;
    for (var li = 0u; li < scene_u.tables.z; li++) {
        let base = scene_u.tables.y + li * 4u;
        let intensity = tables[base].xyz;
        let kind = bitcast<u32>(tables[base].w);
        let want = select(LIGHTS_PUNCTUAL, LIGHTS_DIRECTIONAL, kind == LIGHT_DIRECTIONAL);
        if (sources & want) == 0u {
            continue;
        }
        if kind == LIGHT_DIRECTIONAL {
            let d = -tables[base + 2u].xyz;
            if front_of(d, n, ng) && bvh_unoccluded(x, d, RAY_FAR) {
                let c = intensity * dot(d, n) * INV_PI;
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
                let c = intensity * falloff * dot(d, n) * INV_PI;
                out.sum += c;
                moment_add(&out, c, d);
            }
        }
    }
    if scene_u.sun.w > 0.0 && (sources & LIGHTS_SUN) != 0u {
        let u1 = sun_u.x;
        let u2 = sun_u.y;
        let d = cone_sample(scene_u.sun_axis.xyz, scene_u.sun_axis.w, u1, u2);
        if front_of(d, n, ng) && bvh_unoccluded(x, d, RAY_FAR) {
            let pdf_light = 1.0 / scene_u.sun.w;
            let cos_n = dot(d, n);
            let w = light_weight(mis, pdf_light, cos_n);
            let c = scene_u.sun.xyz * cos_n * INV_PI / pdf_light * w;
            out.sum += c;
            moment_add(&out, c, d);
        }
    }
    let count = scene_u.tables2.x;
    if count > 0u && (sources & LIGHTS_EMITTERS) != 0u {
        let slot = emitter_pick(emitter_u.x);
        let bary = uniform_bary(emitter_u.yz);
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
                    let w = light_weight(mis, pdf_light, cos_n);
                    let c = emission * cos_n * INV_PI / pdf_light * w;
                    out.sum += c;
                    moment_add(&out, c, d);
                }
            }
        }
    }
    return out;
}

