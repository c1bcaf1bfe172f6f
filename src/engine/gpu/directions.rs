//! Direction sequences for the techniques that work along global directions (orthographic
//! views of the whole scene: `sdb`'s illumination maps, `obscurance`'s depth layers, `vpl`'s
//! sky directions): a seedable CPU generator ([`SplitMix64`]), the R2 low-discrepancy
//! sequence on the sphere with a random rotation per bake, and cone jitter for lights with
//! an angular size.
//!
//! Written by hand because each piece is a few lines with a published definition
//! (SplitMix64, Shoemake's random rotation, Roberts' R2 sequence) and the bake's
//! reproducibility depends on its exact bits; a crate would add a dependency for less.
//! Directions are drawn on the CPU (one per step), so there is no GPU counterpart.

use glam::{Quat, Vec3};
use serde::{Deserialize, Serialize};

/// How directions are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DirectionSequence {
    /// R2 low-discrepancy sequence on the sphere with a random rotation per bake.
    #[default]
    Stratified,
    /// Independent uniform directions.
    Random,
}

/// SplitMix64 (Steele, Lea & Flood 2014): tiny, statistically sound, and seedable from
/// one u64, which is all direction sampling needs.
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1) with 53 bits.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// Area-preserving map of the unit square to the unit sphere (z = 1 - 2u, phi = 2 pi v).
pub fn square_to_sphere(u: f64, v: f64) -> Vec3 {
    let z = 1.0 - 2.0 * u;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * std::f64::consts::PI * v;
    Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32)
}

/// Uniformly random rotation (Shoemake, "Uniform random rotations", Graphics Gems III).
pub fn random_rotation(rng: &mut SplitMix64) -> Quat {
    let (u1, u2, u3) = (rng.next_f64(), rng.next_f64(), rng.next_f64());
    let tau = 2.0 * std::f64::consts::PI;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    Quat::from_xyzw(
        (a * (tau * u2).sin()) as f32,
        (a * (tau * u2).cos()) as f32,
        (b * (tau * u3).sin()) as f32,
        (b * (tau * u3).cos()) as f32,
    )
    .normalize()
}

/// The direction generator for one bake.
#[derive(Debug, Clone)]
pub struct Directions {
    kind: DirectionSequence,
    rotation: Quat,
    shift: (f64, f64),
    rng: SplitMix64,
    index: u64,
}

impl Directions {
    pub fn new(kind: DirectionSequence, seed: u64) -> Self {
        let mut rng = SplitMix64::new(seed ^ 0x5DB0_D1EC_7104_0000);
        let rotation = random_rotation(&mut rng);
        let shift = (rng.next_f64(), rng.next_f64());
        Directions {
            kind,
            rotation,
            shift,
            rng,
            index: 0,
        }
    }

    /// The next direction (unit).
    pub fn next_direction(&mut self) -> Vec3 {
        let i = self.index;
        self.index += 1;
        match self.kind {
            DirectionSequence::Stratified => {
                // R2: alpha = (1/g, 1/g^2), g the plastic number (root of x^3 = x + 1).
                const G: f64 = 1.324_717_957_244_746;
                let (a1, a2) = (1.0 / G, 1.0 / (G * G));
                let u = (self.shift.0 + a1 * i as f64).fract();
                let v = (self.shift.1 + a2 * i as f64).fract();
                self.rotation * square_to_sphere(u, v)
            }
            DirectionSequence::Random => {
                let (u, v) = (self.rng.next_f64(), self.rng.next_f64());
                square_to_sphere(u, v)
            }
        }
    }
}

/// A unit vector uniformly distributed in the cone of half-angle `half` around `axis`.
pub fn sample_cone(axis: Vec3, half: f32, rng: &mut SplitMix64) -> Vec3 {
    if half <= 0.0 {
        return axis;
    }
    let cos_max = (half as f64).cos();
    let cos_t = 1.0 - rng.next_f64() * (1.0 - cos_max);
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
    let (t, b) = axis.any_orthonormal_pair();
    (axis * cos_t as f32 + t * (sin_t * phi.cos()) as f32 + b * (sin_t * phi.sin()) as f32).normalize()
}
