//! The one-ambient closure of the obscurance seed (Méndez-Feliu et al., section 3, Eq. 5,
//! `shared/seeds/obscurances-color-bleeding-depth-peeling.md`), as the techniques without
//! transport between surfaces use it for the light that bounces (`sdf`'s bounce of the
//! shared direct light; `obscurance`'s I_A): one scene-wide radiance
//!
//!   B = mean(X) / (1 - c R_ave),
//!
//! with mean(X) the area-weighted mean of the light the model bounces (per channel), c the
//! area-weighted mean fraction of a texel's hemisphere that sees surfaces and R_ave the
//! area-weighted mean albedo: the first bounce closed over all further ones by the
//! geometric series. Each texel then holds B times its own weight (h for `sdf`, the
//! colour-bleeding obscurance W for `obscurance`) in its indirect light.
//!
//! Why it is shared: B is made of sums over *every* texel, so a task that bakes one
//! region of the grid (`engine::tasks`) sees only its region's part. The sums add over
//! disjoint texels, so a technique that reports its sums and each texel's weight per half
//! ([`AmbientHalf`], `Technique::ambient`) lets the merge close B over the whole grid and
//! move each region's texels from the B it had to the whole bake's
//! ([`AmbientHalf::rebase`]): the region's texels then equal the single bake's to float
//! rounding. The same function computes B in the technique and in the merge, so a
//! single bake and a one-region merge agree to the last bit.
//!
//! Precision: sums in f64 (a level's texels would lose the small ones' share in f32),
//! B in f32 as the lightmap is. [`MIN_ABSORPTION`] bounds 1 - c R_ave from below: an
//! albedo-1 closed scene has no finite ambient.

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};

/// Lower bound on 1 - c R_ave (per channel): small enough that the stiffest closed rooms
/// the tests bake (albedo 0.999, 1 - c R_ave = 1e-3) are not clamped.
pub const MIN_ABSORPTION: f32 = 1e-6;

/// Area-weighted sums over a set of texels, from which [`AmbientSums::closure`] gives B.
/// They add over disjoint sets of texels ([`AmbientSums::add`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AmbientSums {
    /// Sum of A (texel areas, m²).
    pub area: f64,
    /// Sum of A rho (rgb): R_ave's numerator.
    pub albedo: [f64; 3],
    /// Sum of A X (rgb): the light the model bounces.
    pub source: [f64; 3],
    /// Sum of A c (c clamped to [0, 1]): the hit fraction's numerator.
    pub hit: f64,
}

impl AmbientSums {
    /// Adds one texel of area `area`, albedo `albedo`, bounced light `source` and hit
    /// fraction `hit`.
    pub fn add_texel(&mut self, area: f32, albedo: Vec3, source: Vec3, hit: f32) {
        let a = f64::from(area);
        self.area += a;
        self.hit += f64::from(hit.clamp(0.0, 1.0)) * a;
        for c in 0..3 {
            self.albedo[c] += f64::from(albedo[c]) * a;
            self.source[c] += f64::from(source[c]) * a;
        }
    }

    /// The sums of two disjoint texel sets.
    pub fn add(&mut self, other: &AmbientSums) {
        self.area += other.area;
        self.hit += other.hit;
        for c in 0..3 {
            self.albedo[c] += other.albedo[c];
            self.source[c] += other.source[c];
        }
    }

    /// The mean of several sums over the same texels (independent estimates of them, as
    /// a region's chains are): what stands in for a region's part when one of its sums
    /// is missing.
    pub fn mean(parts: &[AmbientSums]) -> AmbientSums {
        let mut m = AmbientSums::default();
        for p in parts {
            m.add(p);
        }
        let k = parts.len().max(1) as f64;
        m.area /= k;
        m.hit /= k;
        for c in 0..3 {
            m.albedo[c] /= k;
            m.source[c] /= k;
        }
        m
    }

    /// R_ave: the area-weighted mean albedo.
    pub fn r_ave(&self) -> Vec3 {
        if self.area <= 0.0 {
            return Vec3::ZERO;
        }
        (DVec3::from_array(self.albedo) / self.area).as_vec3()
    }

    /// B = mean(X) / (1 - c R_ave) (module doc); zero over no area.
    pub fn closure(&self) -> Vec3 {
        if self.area <= 0.0 {
            return Vec3::ZERO;
        }
        let mean = (DVec3::from_array(self.source) / self.area).as_vec3();
        let c = ((self.hit / self.area) as f32).clamp(0.0, 1.0);
        mean / (Vec3::ONE - c * self.r_ave()).max(Vec3::splat(MIN_ABSORPTION))
    }
}

/// One half's ambient as a technique closed it: the sums over its texels and each
/// texel's weight, so that the half's lightmap holds `sums.closure() * weight[k]` at texel
/// k on top of its other light.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AmbientHalf {
    pub sums: AmbientSums,
    pub weight: Vec<Vec3>,
}

impl AmbientHalf {
    /// Moves `total` (this half's lightmap over the same texels) from the B its own sums
    /// give to the B of `whole` (the sums over every texel of the bake): adds
    /// (B_whole - B_own) `weight[k]` at each texel.
    pub fn rebase(&self, whole: &AmbientSums, total: &mut [Vec3]) {
        let delta = whole.closure() - self.sums.closure();
        if delta == Vec3::ZERO {
            return;
        }
        for (t, w) in total.iter_mut().zip(&self.weight) {
            *t += delta * *w;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed room of one albedo: c = 1, so B = mean(X) / (1 - rho), the furnace's
    /// geometric series.
    #[test]
    fn a_closed_room_closes_to_the_geometric_series() {
        let mut s = AmbientSums::default();
        for k in 0..10 {
            s.add_texel(1.0 + k as f32, Vec3::splat(0.5), Vec3::splat(0.25), 1.0);
        }
        let b = s.closure();
        assert!((b - Vec3::splat(0.5)).abs().max_element() < 1e-6, "{b}");
        assert_eq!(AmbientSums::default().closure(), Vec3::ZERO);
    }

    /// Sums add over disjoint texels: two regions' sums close to the whole's B, and
    /// rebasing a region's texels onto it gives the whole's lightmap there.
    #[test]
    fn regions_rebased_onto_the_whole_sums_are_the_whole() {
        let texels: Vec<(f32, Vec3, Vec3, f32, Vec3)> = (0..40)
            .map(|k| {
                let f = k as f32;
                (
                    0.5 + (f * 0.37).fract(),
                    Vec3::new(0.2 + (f * 0.13).fract() * 0.6, 0.5, 0.3),
                    Vec3::new((f * 0.71).fract(), 0.1, 2.0),
                    (f * 0.29).fract(),
                    Vec3::new((f * 0.53).fract(), 0.4, 1.0),
                )
            })
            .collect();
        let sums_of = |part: &[(f32, Vec3, Vec3, f32, Vec3)]| {
            let mut s = AmbientSums::default();
            for t in part {
                s.add_texel(t.0, t.1, t.2, t.3);
            }
            s
        };
        let whole = sums_of(&texels);
        let b = whole.closure();
        let (a, c) = texels.split_at(13);
        let mut joined = sums_of(a);
        joined.add(&sums_of(c));
        assert!((joined.closure() - b).abs().max_element() <= 1e-6 * b.abs().max_element());
        for part in [a, c] {
            let half = AmbientHalf {
                sums: sums_of(part),
                weight: part.iter().map(|t| t.4).collect(),
            };
            let own = half.sums.closure();
            assert!((own - b).abs().max_element() > 1e-3, "the regions' own B must differ");
            let mut total: Vec<Vec3> = part.iter().map(|t| Vec3::ONE + own * t.4).collect();
            half.rebase(&joined, &mut total);
            for (t, x) in total.iter().zip(part) {
                let want = Vec3::ONE + b * x.4;
                assert!((*t - want).abs().max_element() < 1e-5, "{t} against {want}");
            }
        }
    }
}
