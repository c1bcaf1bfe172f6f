//! Deterministic random numbers keyed by (seed, step, texel, sample), so a bake is
//! reproducible for a given seed however rayon schedules the texels.
//!
//! How: the key is folded through SplitMix64 into the state of a PCG32 (XSH-RR)
//! generator (O'Neill 2014). Written here rather than taken from `rand_pcg` because the
//! GPU techniques hash the same way in WGSL (`shaders/gpu/common.wgsl`), and the two sides
//! must be documented together; it is a dozen lines.
//!
//! Limits: 2^64 period per stream, far beyond any path length; floats have 24 random bits.

/// SplitMix64 finaliser: a bijective 64-bit mix with full avalanche.
pub fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The PCG hash of `gpu/common.wgsl`'s `pcg` (one LCG step and PCG's RXS-M-XS output
/// permutation, Jarzynski & Olano 2020), for the decisions the CPU and the GPU must make
/// alike (`scene::blend_draw`).
pub fn pcg_hash(v: u32) -> u32 {
    let state = v.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let word = ((state >> ((state >> 28) + 4)) ^ state).wrapping_mul(277_803_737);
    (word >> 22) ^ word
}

/// PCG32 XSH-RR with a fixed odd increment.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
}

const PCG_MUL: u64 = 6_364_136_223_846_793_005;
const PCG_INC: u64 = 1_442_695_040_888_963_407;

impl Rng {
    /// A generator for one independent stream, keyed by up to four integers.
    pub fn new(seed: u64, a: u64, b: u64, c: u64) -> Rng {
        let k = splitmix64(splitmix64(splitmix64(splitmix64(seed) ^ a) ^ b) ^ c);
        let mut r = Rng { state: k };
        r.next_u32();
        r
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(PCG_MUL).wrapping_add(PCG_INC);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1), 24 bits.
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_key_same_stream_and_keys_differ() {
        let mut a = Rng::new(1, 2, 3, 4);
        let mut b = Rng::new(1, 2, 3, 4);
        let mut c = Rng::new(1, 2, 3, 5);
        let xa: Vec<u32> = (0..8).map(|_| a.next_u32()).collect();
        let xb: Vec<u32> = (0..8).map(|_| b.next_u32()).collect();
        let xc: Vec<u32> = (0..8).map(|_| c.next_u32()).collect();
        assert_eq!(xa, xb);
        assert_ne!(xa, xc);
    }

    #[test]
    fn uniform_mean_and_variance() {
        // 1e5 draws: the mean has standard error sqrt(1/12/1e5) = 9.1e-4, so 5e-3 is 5.5 sigma.
        let mut r = Rng::new(7, 0, 0, 0);
        let n = 100_000;
        let xs: Vec<f64> = (0..n).map(|_| r.next_f32() as f64).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!((mean - 0.5).abs() < 5e-3, "{mean}");
        assert!((var - 1.0 / 12.0).abs() < 2e-3, "{var}");
        assert!(xs.iter().all(|x| (0.0..1.0).contains(x)));
    }
}
