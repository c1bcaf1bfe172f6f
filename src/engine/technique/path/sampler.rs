//! Where `path`'s samples draw their random numbers (`params.sampling`).
//!
//! The estimator asks for its numbers by purpose and vertex ([`PathSampler`]): the
//! continuation's direction, the sun's cone sample, the emitter pick and the point on
//! it, and Russian roulette. Two samplers answer:
//!
//! - `sobol` (the default): Owen-scrambled Sobol points, Burley's "Practical Hash-based
//!   Owen Scrambling" (JCGT 2020) as the `sobol_burley` crate implements it (one
//!   shuffle of the index per sequence, an Owen scramble per dimension). The samples of
//!   a texel in one half of the bake are consecutive points of one sequence: sample `s`
//!   of step `k` is point `(k / 2) * spp + s` of the sequence of half `k % 2`. Each vertex
//!   of a path has two 4-D sets: (direction, direction, emitter point, emitter point) and
//!   (emitter pick, sun, sun, roulette), so the first bounce's direction is a
//!   (0, 2)-sequence over the hemisphere and the light samples are stratified too. The
//!   sets are consecutive dimensions of one 256-dimensional sequence (vertex b has sets
//!   2b and 2b + 1), so the vertices are stratified jointly; they run out at the 32nd
//!   vertex, where the path goes on with the independent stream below. Burley's
//!   padding (every set the first four dimensions under its own seed, vertices
//!   associated at random) was measured worse on the peer bench: 0.725 % against
//!   0.612 % true error at 1024 samples on the Cornell box, 1.436 % against 1.365 % at
//!   256 on blocks-25k. Cost: two 4-D points a vertex. The crate's `sample_4d` made 16 %
//!   of a step on blocks-25k (perf, release, 2 cores); the points are now the crate's
//!   bit for bit from nibble tables of its direction numbers, with the index shuffled
//!   once a path (`point_4d`), 7 % of the step: 17.3 → 15.9 ms a step on blocks-25k at
//!   128², 11.7 → 10.1 ms on the Cornell box at 64². Why: at a texel the
//!   integrand is smooth over most of the hemisphere, and stratified points converge
//!   faster than 1/sqrt(n) there. Measured:
//!   2.2x less error than independent numbers at 128 samples on the sphere over a plane
//!   (`tests/analytic_path.rs`) and 2.0x to 2.1x on the peer bench's scenes, which took
//!   lightmapd from 0.84x and 0.38x of Cycles' speed to the same error to 1.66x and
//!   1.40x (docs/peers.md).
//! - `independent`: one PCG32 stream per (seed, step, texel, sample), drawn in the order
//!   the estimator asks; the sampler of earlier versions, bit for bit.
//!
//! The error estimate stays honest: the estimate's error is measured from the difference
//! of the even and odd halves (`engine::accumulate`), which needs the halves independent.
//! Points of one scrambled sequence are not (their errors cancel on purpose), so each
//! half of each texel has its own scramble (a seed hashed from the bake's seed, the
//! texel and the half): within a half the points are stratified, between halves they
//! are independent randomisations, and each half's mean is an unbiased estimate (an
//! Owen-scrambled point is uniform). The difference of the halves then measures the
//! error of their mean as it does for independent samples: `tests/analytic_path.rs`
//! checks the reported error against the true error on scenes with closed forms.
//!
//! Limits: at very few samples the higher dimensions' poorer projections can cost more
//! than the stratification gains: on the Cornell box (64², 4 seeds, true error against a
//! 16384-sample reference) `sobol` reads 14.7 % against 14.7 % at 8 samples, 11.3 %
//! against 10.3 % at 16, then 3.35 % against 5.04 % at 64 and 0.61 % against 1.27 % at
//! 1024; on blocks-25k it is ahead from 16 samples (7.7 % against 11.0 %). The deficit
//! at 16 is the first vertex's own: with only its sets taken from the sequence and every
//! deeper vertex's padded it stays (11.35 %). Owen's bound lets a scrambled net's
//! variance exceed independent points' by up to a factor e for some integrands; here
//! 1.2. The reported error follows the true one at every count (10.9 % reported at 16).
//!
//! Bounds: the crate's sequences hold 2^16 points; a half with more samples than that
//! goes on in a new, independently scrambled sequence every 2^16 points (unbiased; the
//! stratification restarts). Task splits start on even steps (`engine::tasks`), so a
//! task's samples are the same points the whole bake would draw at those steps, and
//! split bakes merge to the single bake exactly.

use crate::engine::rng::{Rng, splitmix64};

/// The numbers one path draws, by purpose and vertex (`bounce` 0 is the texel's).
pub trait PathSampler {
    /// The cosine-sampled continuation's two numbers.
    fn direction(&mut self, bounce: u32) -> (f32, f32);
    /// The sun's cone sample.
    fn sun(&mut self, bounce: u32) -> (f32, f32);
    /// The emitter pick, then the two numbers of the point on the picked triangle.
    fn emitter(&mut self, bounce: u32) -> (f32, f32, f32);
    /// Russian roulette's number.
    fn roulette(&mut self, bounce: u32) -> f32;
}

/// `independent`: the numbers in the order they are asked for.
impl PathSampler for Rng {
    fn direction(&mut self, _: u32) -> (f32, f32) {
        (self.next_f32(), self.next_f32())
    }
    fn sun(&mut self, _: u32) -> (f32, f32) {
        (self.next_f32(), self.next_f32())
    }
    fn emitter(&mut self, _: u32) -> (f32, f32, f32) {
        (self.next_f32(), self.next_f32(), self.next_f32())
    }
    fn roulette(&mut self, _: u32) -> f32 {
        self.next_f32()
    }
}

/// Points of one sequence (`sobol_burley`) before a new scramble.
pub const SEQUENCE_POINTS: u32 = 1 << 16;
/// Vertices with Sobol sets (two 4-D sets each, of the crate's 64).
pub const SOBOL_VERTICES: u32 = 32;

/// Nibble tables of the crate's direction numbers, for [`SOBOL_VERTICES`]' sets: entry
/// `[set][k][v]` is the 4-D Sobol point (bit-reversed, unscrambled) of the reversed index
/// whose nibble `k` above bit 16 is `v` and every other bit 0.
///
/// Why not `sobol_burley::sample_4d` itself: it walks the index's set bits one at a time
/// (a data-dependent loop of up to 16 rounds, with mispredicted exits) and re-shuffles the
/// index at every call, which made 16 % of a `path` step on blocks-25k. A Sobol point is
/// linear over GF(2) in the index's bits, so the XOR of four table entries is the same
/// point: bit for bit the crate's (`the_tables_give_the_crates_points`), in four loads.
/// 64 sets × 4 nibbles × 16 values × 16 bytes = 64 KiB, of which a path's first vertices
/// touch 1 KiB each.
type Nibbles = [[[[u32; 4]; 16]; 4]; 2 * SOBOL_VERTICES as usize];

fn nibbles() -> &'static Nibbles {
    static TABLES: std::sync::OnceLock<Box<Nibbles>> = std::sync::OnceLock::new();
    TABLES.get_or_init(|| {
        let mut t = Box::new([[[[0u32; 4]; 16]; 4]; 2 * SOBOL_VERTICES as usize]);
        for (set, per_set) in t.iter_mut().enumerate() {
            for (k, per_nibble) in per_set.iter_mut().enumerate() {
                for (v, entry) in per_nibble.iter_mut().enumerate() {
                    let rev_index = (v as u32) << (16 + 4 * k);
                    *entry = sobol_burley::parts::sobol_int4_rev(rev_index, set as u32).into();
                }
            }
        }
        t
    })
}

/// Point `index` of the sequence scrambled by `seed`, as [`point_4d`] takes it: shuffled
/// and bit-reversed, `sobol_burley::sample_4d`'s first stage, as the crate writes it.
fn shuffled_rev_index(index: u32, seed: u32) -> u32 {
    use sobol_burley::parts::{hash, owen_scramble_rev};
    owen_scramble_rev(index.reverse_bits(), hash(seed ^ 0x79c68e4a))
}

/// The 4-D point of dimension set `set` at the already shuffled, reversed index, Owen
/// scrambled with `seed`: `sobol_burley::sample_4d`'s last three stages, as the crate
/// writes them (`lib.rs`), on the table's unscrambled point.
fn point_4d(tables: &Nibbles, shuffled_rev_index: u32, set: u32, seed: u32) -> [f32; 4] {
    use sobol_burley::parts::{Int4, hash_int4, owen_scramble_int4_rev};
    let t = &tables[set as usize];
    let mut sobol = [0u32; 4];
    for (k, per_nibble) in t.iter().enumerate() {
        let e = &per_nibble[((shuffled_rev_index >> (16 + 4 * k)) & 15) as usize];
        for d in 0..4 {
            sobol[d] ^= e[d];
        }
    }
    let scramble: Int4 = {
        let s = seed.wrapping_mul(0x9c8f2d3b) ^ set;
        [s ^ 0x912f69ba, s ^ 0x174f18ab, s ^ 0x691e72ca, s ^ 0xb40cc1b8].into()
    };
    owen_scramble_int4_rev(sobol.into(), hash_int4(scramble))
        .reverse_bits()
        .to_f32_norm()
}

/// `sobol`: one path's point of its texel's half's sequence (module doc).
pub struct Sobol {
    /// The point's index, shuffled by the sequence's scramble and bit-reversed, once for
    /// all its vertices (the crate does it per 4-D set).
    shuffled_rev_index: u32,
    scramble: u32,
    tables: &'static Nibbles,
    /// The vertex whose sets `a` and `b` hold.
    cached: Option<u32>,
    a: [f32; 4],
    b: [f32; 4],
    /// Past [`SOBOL_VERTICES`].
    deep: Rng,
}

impl Sobol {
    /// Sample `sample` (of `spp` a step) of `step` at texel `texel` of the bake `seed`.
    pub fn new(seed: u64, step: u64, texel: u64, sample: u32, spp: u32) -> Sobol {
        let half = step % 2;
        let point = (step / 2) * spp as u64 + sample as u64;
        let block = point / SEQUENCE_POINTS as u64;
        // One scramble per (bake, texel, half, block of 2^16 points).
        let key = splitmix64(seed ^ splitmix64(texel ^ splitmix64(half ^ splitmix64(block ^ 0x5AB0_1C0D))));
        let index = (point % SEQUENCE_POINTS as u64) as u32;
        let scramble = (key >> 32) as u32 ^ key as u32;
        Sobol {
            shuffled_rev_index: shuffled_rev_index(index, scramble),
            scramble,
            tables: nibbles(),
            cached: None,
            a: [0.0; 4],
            b: [0.0; 4],
            deep: Rng::new(seed, step, texel, sample as u64),
        }
    }

    /// The vertex's two sets, or `None` past the Sobol vertices.
    fn sets(&mut self, bounce: u32) -> Option<(&[f32; 4], &[f32; 4])> {
        if bounce >= SOBOL_VERTICES {
            return None;
        }
        if self.cached != Some(bounce) {
            self.a = point_4d(self.tables, self.shuffled_rev_index, 2 * bounce, self.scramble);
            self.b = point_4d(self.tables, self.shuffled_rev_index, 2 * bounce + 1, self.scramble);
            self.cached = Some(bounce);
        }
        Some((&self.a, &self.b))
    }
}

impl PathSampler for Sobol {
    fn direction(&mut self, bounce: u32) -> (f32, f32) {
        match self.sets(bounce) {
            Some((a, _)) => (a[0], a[1]),
            None => self.deep.direction(bounce),
        }
    }
    fn sun(&mut self, bounce: u32) -> (f32, f32) {
        match self.sets(bounce) {
            Some((_, b)) => (b[1], b[2]),
            None => self.deep.sun(bounce),
        }
    }
    fn emitter(&mut self, bounce: u32) -> (f32, f32, f32) {
        match self.sets(bounce) {
            Some((a, b)) => (b[0], a[2], a[3]),
            None => self.deep.emitter(bounce),
        }
    }
    fn roulette(&mut self, bounce: u32) -> f32 {
        match self.sets(bounce) {
            Some((_, b)) => b[3],
            None => self.deep.roulette(bounce),
        }
    }
}

/// `inner`'s numbers one vertex deeper: for an estimator that takes vertex 0's sets
/// itself (a light probe's own direction and light samples, `path::probes`) before it
/// continues as a path, whose vertex b then draws the sets of vertex b + 1.
pub struct Deeper<'a, S: PathSampler>(pub &'a mut S);

impl<S: PathSampler> PathSampler for Deeper<'_, S> {
    fn direction(&mut self, bounce: u32) -> (f32, f32) {
        self.0.direction(bounce + 1)
    }
    fn sun(&mut self, bounce: u32) -> (f32, f32) {
        self.0.sun(bounce + 1)
    }
    fn emitter(&mut self, bounce: u32) -> (f32, f32, f32) {
        self.0.emitter(bounce + 1)
    }
    fn roulette(&mut self, bounce: u32) -> f32 {
        self.0.roulette(bounce + 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_half_is_one_stratified_sequence_and_the_halves_differ() {
        // 4 samples a step: steps 0, 2, 4, 6 of the even half are points 0..16 of one
        // sequence, so each of 16 equal strips of [0, 1) holds exactly one first number.
        let mut strips = [0u32; 16];
        for step in [0u64, 2, 4, 6] {
            for s in 0..4 {
                let (u, _) = Sobol::new(7, step, 3, s, 4).direction(0);
                assert!((0.0..1.0).contains(&u));
                strips[(u * 16.0) as usize] += 1;
            }
        }
        assert_eq!(strips, [1; 16]);
        // The odd half of the same texel and another texel are other scrambles.
        let first = |step: u64, texel: u64| Sobol::new(7, step, texel, 0, 4).direction(0);
        assert_ne!(first(0, 3), first(1, 3));
        assert_ne!(first(0, 3), first(0, 4));
        // Deterministic.
        assert_eq!(first(0, 3), first(0, 3));
    }

    #[test]
    fn past_the_sobol_vertices_the_independent_stream_goes_on() {
        let mut s = Sobol::new(1, 0, 0, 0, 1);
        let mut r = Rng::new(1, 0, 0, 0);
        assert_eq!(s.direction(SOBOL_VERTICES), r.direction(SOBOL_VERTICES));
        assert_eq!(s.roulette(SOBOL_VERTICES + 5), r.roulette(0));
    }

    #[test]
    fn a_long_half_starts_a_new_scramble_every_sequence() {
        // Point 2^16 of a half is point 0 of the next sequence, with another scramble.
        let spp = 4;
        let step_of = |point: u64| 2 * (point / spp as u64);
        let at = |point: u64| Sobol::new(9, step_of(point), 0, 0, spp).direction(0);
        assert_ne!(at(0), at(SEQUENCE_POINTS as u64));
        let mut first = Sobol::new(9, step_of(SEQUENCE_POINTS as u64), 0, 0, spp);
        let scramble = first.scramble;
        assert_eq!(
            first.direction(0),
            {
                let p = sobol_burley::sample_4d(0, 0, scramble);
                (p[0], p[1])
            },
            "the new sequence starts at its first point"
        );
    }

    #[test]
    fn the_tables_give_the_crates_points() {
        // Every set a path uses, indices over the whole 2^16 range (the top and bottom
        // bits both), several scrambles: bit for bit `sobol_burley::sample_4d`.
        let tables = nibbles();
        let mut rng = Rng::new(5, 0, 0, 0);
        for i in 0..4000u32 {
            let index = match i {
                0 => 0,
                1 => SEQUENCE_POINTS - 1,
                _ => (rng.next_f32() * SEQUENCE_POINTS as f32) as u32 % SEQUENCE_POINTS,
            };
            let seed = (rng.next_f32() * u32::MAX as f32) as u32 ^ i;
            let shuffled = shuffled_rev_index(index, seed);
            for set in 0..2 * SOBOL_VERTICES {
                let ours = point_4d(tables, shuffled, set, seed);
                let crates = sobol_burley::sample_4d(index, set, seed);
                assert_eq!(
                    ours.map(f32::to_bits),
                    crates.map(f32::to_bits),
                    "index {index} set {set} seed {seed}"
                );
            }
        }
    }
}
