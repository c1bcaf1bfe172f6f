// path/estimator.wgsl: `path`'s estimator on the GPU, E/pi at a surface point by one
// whole path (`radiance`), and the randomness and bounds it is built on. A library (no
// entry points, no bindings of its own), prepended to `path`'s two passes: the texel
// megakernel (path/path_trace.wgsl) and the light probes (path/probes.wgsl), each of which
// declares `pu` (its PathUniform, binding 5) and `sobol_vectors` at its own binding. The
// estimator is the CPU's (src/engine/technique/path/mod.rs) line for line: cosine-sampled
// continuation, NEE to punctual lights, the sun's cone and emissive triangles with the
// power heuristic against the continuation, Russian roulette on throughput below tau, the
// barycentric inset and the surface offset at every vertex, black opaque back faces of
// single-sided surfaces. Rays: gpu/bvh.wgsl (bindings 0 and 1), in the scene's world
// space, f32; the scene's materials, lights and next-event estimation: gpu/lights.wgsl
// (bindings 2-4).
//
// Randomness, `sampling: sobol` (the default; PATH_SOBOL): as on the CPU
// (path/sampler.rs), each vertex below the 32nd takes two 4-D sets of an Owen-scrambled
// Sobol sequence (Burley 2020; the `sobol_burley` crate's construction, its direction
// numbers uploaded by gpu.rs into the pass's `sobol_vectors`): (direction, direction, emitter point,
// emitter point) and (emitter pick, sun, sun, roulette). Sample s of step k is point
// (k / 2) * spp + s of the sequence of half k % 2; a texel's half has its own scramble
// per block of 2^16 points (hashed from the seed, the pixel, the half and the block with
// `pcg`, not the CPU's 64-bit SplitMix), so the halves stay independent estimates. The
// point index is computed in 32 bits: exact up to 2^32 points a half (2^31 steps at 4
// samples). The 16 direction-number lookups are written out, not looped: llvmpipe counts
// every loop iteration against the invocation's budget (below). Past the 32nd vertex, and
// with `sampling: independent`, the PCG stream below.
//
// Randomness, the stream: PCG-RXS-M-XS 32/32 (O'Neill 2014; the `pcg` hash of common.wgsl is its
// output step) with a per-stream increment. A texel's streams differ by increment (a hash
// of the seed and the texel's pixel, carried in position.w's bits: gpu/texels.rs), a (step, sample)'s by starting state (a hash chain of the
// seed, step and sample), so no two (seed, step, texel, sample) share a sequence except
// by a 32-bit hash collision of two (step, sample) keys of one texel. Period 2^32; a path
// of 65536 bounces draws at most 8 numbers a vertex, 5e5 in all. The streams are not the
// CPU's (its PCG32 needs 64-bit integers, which WGSL lacks), nor are the Sobol scrambles:
// GPU and CPU bakes agree in the mean, not sample for sample. Floats carry 24 random bits
// from the stream, 23 from the Sobol points (the crate's conversion), as on the CPU.
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
    f: vec4<f32>,        // x: Russian roulette threshold tau; y: surface offset; z: blend 1/k; w: unused
    slice: vec4<u32>,    // texels: x the dispatch's first texel, y its texel count (a sliced step); zw unused
}

const PATH_DIRECT: u32 = 1u;   // keep the direct layer
const PATH_MOMENTS: u32 = 2u;  // keep the first moments (sh layers)
const PATH_SOBOL: u32 = 4u;    // sampling: sobol
const SOBOL_VERTICES: u32 = 32u;

// ---- randomness ------------------------------------------------------------------------
fn rng_for(texel: u32, sample: u32) -> Rng {
    let base = pcg(pu.keys.x ^ pcg(pu.keys.y));
    var r = Rng(pcg(pu.counts.w ^ pcg(sample ^ base)), (pcg(texel ^ pcg(base ^ 0x5bd1e995u)) << 1u) | 1u);
    rng_next(&r);
    return r;
}

// ---- Sobol points (sobol_burley 0.5's sample_4d, line for line) -----------------------
fn sb_hash(x: u32) -> u32 {
    var n = x ^ 0xe6fe3bebu;
    n ^= n >> 16u;
    n *= 0x7feb352du;
    n ^= n >> 15u;
    n *= 0x846ca68bu;
    n ^= n >> 16u;
    return n;
}

fn sb_hash4(x: vec4<u32>) -> vec4<u32> {
    var n = x ^ vec4<u32>(0xe6fe3bebu);
    n ^= n >> vec4<u32>(16u);
    n *= vec4<u32>(0x7feb352du);
    n ^= n >> vec4<u32>(15u);
    n *= vec4<u32>(0x846ca68bu);
    n ^= n >> vec4<u32>(16u);
    return n;
}

fn owen_rev(x: u32, scramble: u32) -> u32 {
    var n = x;
    n ^= n * 0x3d20adeau;
    n += scramble;
    n *= (scramble >> 16u) | 1u;
    n ^= n * 0x05526c56u;
    n ^= n * 0x53a22864u;
    return n;
}

fn owen_rev4(x: vec4<u32>, scramble: vec4<u32>) -> vec4<u32> {
    var n = x;
    n ^= n * vec4<u32>(0x3d20adeau);
    n += scramble;
    n *= (scramble >> vec4<u32>(16u)) | vec4<u32>(1u);
    n ^= n * vec4<u32>(0x05526c56u);
    n ^= n * vec4<u32>(0x53a22864u);
    return n;
}

// The set's Sobol point for a bit-reversed index: bit 31 - k selects direction number k.
fn sobol4_rev(index_rev: u32, dims: u32) -> vec4<u32> {
    let b = dims * 16u;
    var v = vec4<u32>(0u);
    if (index_rev & 0x80000000u) != 0u { v ^= sobol_vectors[b]; }
    if (index_rev & 0x40000000u) != 0u { v ^= sobol_vectors[b + 1u]; }
    if (index_rev & 0x20000000u) != 0u { v ^= sobol_vectors[b + 2u]; }
    if (index_rev & 0x10000000u) != 0u { v ^= sobol_vectors[b + 3u]; }
    if (index_rev & 0x08000000u) != 0u { v ^= sobol_vectors[b + 4u]; }
    if (index_rev & 0x04000000u) != 0u { v ^= sobol_vectors[b + 5u]; }
    if (index_rev & 0x02000000u) != 0u { v ^= sobol_vectors[b + 6u]; }
    if (index_rev & 0x01000000u) != 0u { v ^= sobol_vectors[b + 7u]; }
    if (index_rev & 0x00800000u) != 0u { v ^= sobol_vectors[b + 8u]; }
    if (index_rev & 0x00400000u) != 0u { v ^= sobol_vectors[b + 9u]; }
    if (index_rev & 0x00200000u) != 0u { v ^= sobol_vectors[b + 10u]; }
    if (index_rev & 0x00100000u) != 0u { v ^= sobol_vectors[b + 11u]; }
    if (index_rev & 0x00080000u) != 0u { v ^= sobol_vectors[b + 12u]; }
    if (index_rev & 0x00040000u) != 0u { v ^= sobol_vectors[b + 13u]; }
    if (index_rev & 0x00020000u) != 0u { v ^= sobol_vectors[b + 14u]; }
    if (index_rev & 0x00010000u) != 0u { v ^= sobol_vectors[b + 15u]; }
    return v;
}

// Point `index` (< 2^16) of 4-D set `dims` of the sequence scrambled by `seed`.
fn sobol_4d(index: u32, dims: u32, seed: u32) -> vec4<f32> {
    let shuffled = owen_rev(reverseBits(index), sb_hash(seed ^ 0x79c68e4au));
    let sobol = sobol4_rev(shuffled, dims);
    let scramble = vec4<u32>(seed * 0x9c8f2d3bu) ^ vec4<u32>(dims)
        ^ vec4<u32>(0x912f69bau, 0x174f18abu, 0x691e72cau, 0xb40cc1b8u);
    let bits = reverseBits(owen_rev4(sobol, sb_hash4(scramble)));
    return bitcast<vec4<f32>>((bits >> vec4<u32>(9u)) | vec4<u32>(0x3f800000u)) - vec4<f32>(1.0);
}

// Which point of which scrambled sequence one sample is (the header).
struct SobolPoint {
    on: bool,
    index: u32,
    scramble: u32,
    // The vertex whose sets the path's first vertex takes: 0 for a texel; 1 for a light
    // probe, which takes vertex 0's sets itself (path/probes.wgsl), as the CPU's `Deeper`.
    first: u32,
}

fn sobol_point(pixel: u32, sample: u32) -> SobolPoint {
    let step = pu.counts.w;
    let point = (step >> 1u) * pu.counts.y + sample;
    let base = pcg(pu.keys.x ^ pcg(pu.keys.y));
    let scramble = pcg(base ^ pcg(pixel ^ pcg((step & 1u) ^ pcg((point >> 16u) ^ 0x5ab01c0du))));
    return SobolPoint((pu.keys.w & PATH_SOBOL) != 0u, point & 0xffffu, scramble, 0u);
}

struct PathSample {
    total: vec3<f32>,
    direct: vec3<f32>,
    m: Light,  // sum unused
    cut: bool, // the path was ended from outside (the adapter's loop budget), not by its rules
}

// path::PathContext::radiance.
fn radiance(x0: vec3<f32>, n0: vec3<f32>, ng0: vec3<f32>, rng: ptr<function, Rng>, sp: SobolPoint) -> PathSample {
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
        // This vertex's two Sobol sets (the header), or the stream's numbers.
        let vertex = bounce + sp.first;
        let stratified = sp.on && vertex < SOBOL_VERTICES;
        var a = vec4<f32>(0.0);
        var b = vec4<f32>(0.0);
        var nee: Light;
        if stratified {
            a = sobol_4d(sp.index, 2u * vertex, sp.scramble);
            b = sobol_4d(sp.index, 2u * vertex + 1u, sp.scramble);
            nee = next_event_with(x, n, ng, true, b.yz, vec3<f32>(b.x, a.z, a.w));
        } else {
            nee = next_event(x, n, ng, true, rng);
        }
        total += throughput * nee.sum;
        if bounce == 0u {
            direct += nee.sum;
            first_nee = nee.sum;
            moment = nee;
        }
        var u1 = a.x;
        var u2 = a.y;
        if !stratified {
            u1 = rng_next(rng);
            u2 = rng_next(rng);
        }
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
        let pdf_bsdf = cos_n * INV_PI;
        let hit = bvh_closest(x, dir, RAY_FAR);
        if hit.overflow {
            break;  // the traversal was cut: so is the path (`ended` stays false)
        }
        if hit.slot == BVH_MISS {
            var l = sky_radiance(dir);
            if scene_u.sun.w > 0.0 && dot(dir, scene_u.sun_axis.xyz) >= scene_u.sun_axis.w {
                l += scene_u.sun.xyz * power_heuristic(pdf_bsdf, 1.0 / scene_u.sun.w);
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
            var ur = b.w;
            if !stratified {
                ur = rng_next(rng);
            }
            if ur * tau >= peak {
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

