//! Progressive estimates from two half-accumulators, and the error estimate their
//! difference gives (DESIGN §4).
//!
//! How: steps alternate between an even and an odd half. For an unbiased technique the
//! halves are independent estimates of the same lightmap; with `n_a` and `n_b` steps
//! their difference has variance σ²(1/n_a + 1/n_b) while the combined mean has
//! σ²/(n_a + n_b), so the standard error of the combined mean at a texel is
//! |A − B| · √(n_a n_b) / (n_a + n_b) — half the difference when the halves are equal.
//! The whole-map relative error is the root-mean-square of that over valid texels,
//! divided by the root-mean-square of the estimate (luminance, Rec. 709 weights).
//!
//! Limits: this measures noise only. A biased technique (`sdb`'s finite neighbourhood,
//! `vpl`'s clamping) can report a small error while being off; its true error is
//! measured against the reference by `lightmapd bench`.

use glam::Vec3;
use serde::Serialize;

/// Rec. 709 luminance weights, for scalar error figures.
pub const LUMINANCE: Vec3 = Vec3::new(0.2126, 0.7152, 0.0722);

/// One half's mean per valid texel.
#[derive(Clone, Debug, Default)]
pub struct HalfEstimate {
    pub steps: u64,
    pub total: Vec<Vec3>,
    pub direct: Option<Vec<Vec3>>,
    /// First moments of incident light per world axis (the `sh.*` layers), when kept.
    pub moments: Option<Vec<[Vec3; 3]>>,
}

#[derive(Clone, Debug, Default)]
pub struct Snapshot {
    pub even: HalfEstimate,
    pub odd: HalfEstimate,
}

impl Snapshot {
    /// The two halves from GPU accumulators read back as one buffer of 2n texels (the
    /// even half first, then the odd), rgb of each `[f32; 4]` (the fourth lane is the
    /// shader's own); `direct` likewise when kept. No directional moments.
    pub fn from_gpu_halves(acc: &[[f32; 4]], direct: Option<&[[f32; 4]]>, half_steps: [u64; 2]) -> Snapshot {
        let n = acc.len() / 2;
        let half = |h: usize| {
            let pick = |v: &[[f32; 4]]| -> Vec<Vec3> {
                v[h * n..(h + 1) * n]
                    .iter()
                    .map(|a| Vec3::new(a[0], a[1], a[2]))
                    .collect()
            };
            HalfEstimate {
                steps: half_steps[h],
                total: pick(acc),
                direct: direct.map(pick),
                moments: None,
            }
        };
        Snapshot {
            even: half(0),
            odd: half(1),
        }
    }
}

/// The channels a shadowmask has (RGBA, as the engines that read one expect), and their
/// names in the EXR (`shadowmask.R` …).
pub const MASK_CHANNELS: usize = 4;
pub const MASK_CHANNEL_NAMES: [&str; MASK_CHANNELS] = ["R", "G", "B", "A"];

/// What the delivered lightmap carries of the shadowmask (`engine::shadowmask`).
#[derive(Clone, Debug, PartialEq)]
pub struct ShadowmaskLayer {
    /// The light of each channel (`sun` or the light's name), in channel order.
    pub lights: Vec<String>,
    /// Visibility per valid texel and channel (channels past `lights.len()` are 0).
    pub values: Vec<[f32; MASK_CHANNELS]>,
}

/// The combined estimate with its error.
#[derive(Clone, Debug)]
pub struct Estimate {
    pub steps: u64,
    /// Irradiance / π per valid texel: the full lightmap.
    pub total: Vec<Vec3>,
    pub direct: Option<Vec<Vec3>>,
    pub moments: Option<Vec<[Vec3; 3]>>,
    /// Plain obscurance / sky visibility per valid texel (`ao.Y`), from
    /// `Technique::ao` (the bake loop fills it in; `None` for techniques without one).
    pub ao: Option<Vec<f32>>,
    /// Standard error of `total`'s luminance per texel (absolute); `None` before both
    /// halves have a step.
    pub texel_error: Option<Vec<f32>>,
    pub error: ErrorSummary,
    /// The two halves' means of `total` and their step counts, when both have steps:
    /// the denoiser filters each on its own to estimate its own error
    /// (`engine::post::denoised`).
    pub halves: Option<([Vec<Vec3>; 2], [u64; 2])>,
    /// The chosen lights' baked visibility (`engine::shadowmask`), when asked for; the
    /// bake loop fills it in.
    pub shadowmask: Option<ShadowmaskLayer>,
    /// The unbiased reference at a biased technique's control texels, once they have
    /// assessed this estimate (`control::assess_against`): the denoiser checks there
    /// that what it delivers is closer to the answer than the raw map
    /// (`post::denoised`).
    pub control: Option<std::sync::Arc<ControlValues>>,
}

/// `path`'s luminance at the control texels, as the denoiser's check and the delivered
/// map's assessment read it ([`ControlValues::assess_delivered`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ControlValues {
    /// The control texels, as indices into the estimate's texels.
    pub texels: Vec<usize>,
    /// `path`'s luminance there, in the same order.
    pub luminance: Vec<f32>,
    /// Its variance (squared standard error) there, in the same order.
    pub variance: Vec<f32>,
    /// The answer's RMS luminance as `path`'s values estimate it, less their variance
    /// (what the control's relative errors are relative to).
    pub rms: f32,
}

impl ControlValues {
    /// The delivered (denoised) lightmap's error, measured at the control texels exactly
    /// as `control::assess_against` measures the raw one and folded into `error`:
    /// `relative` the RMS of d_k over the answer's RMS, never below the noise floor,
    /// `bias` what is left above the floor at the control texels, `noise` the floor, and
    /// the 90 % interval. The floor is the denoiser's own bound of its error per texel
    /// (`texel_noise`, absolute, `post::denoised` step 5) over the whole map, calibrated
    /// at the control texels as the raw map's halves are (`noise_calibration`): the
    /// bound is a triangle-inequality sum of the filters' cross-validated errors, which
    /// over-states (`vpl` on the occlusion room stated 1.26-1.51 times its true delivered
    /// error with the bound uncalibrated, 2026-12-06), and where the control measures the
    /// whole error below it the floor is scaled down by that share. The raw map's bias and
    /// noise in quadrature, which this replaced, missed what the filters add to or take
    /// from the bias (the halves that cross-validate them share it): `obscurance` on the
    /// Cornell box stated 1.31 for a delivered true error of 5.78 after 2 steps, and
    /// 11.8 % for 14.1 % after 10 s (2026-12-06). The denoiser chose how much of its move
    /// to keep at the same texels (one share for the whole map,
    /// `post::denoised::checked_share`), which leans this figure low by about one texel's
    /// worth in `texels.len()`. `false` (and `error` untouched) where there is nothing to
    /// measure. It lives here, not in `engine::control`, so that the denoiser needs
    /// nothing of the control's bake machinery (the engine's modules form no cycle,
    /// `tests/architecture.rs`).
    pub fn assess_delivered(&self, delivered: &[Vec3], texel_noise: &[f32], error: &mut ErrorSummary) -> bool {
        let rms = self.rms as f64;
        if self.texels.len() < 2
            || rms <= 0.0
            || self.variance.len() != self.texels.len()
            || texel_noise.len() != delivered.len()
            || delivered.is_empty()
        {
            return false;
        }
        let p: Vec<f64> = self.luminance.iter().map(|x| *x as f64).collect();
        let v: Vec<f64> = self.variance.iter().map(|x| *x as f64).collect();
        let (mean, se) = squared_error_at(&self.texels, delivered, &p, &v);
        let square = |k: usize| (texel_noise[k] as f64).powi(2);
        let noise_map_ms = (0..texel_noise.len()).map(square).sum::<f64>() / texel_noise.len() as f64;
        let noise_control_ms = self.texels.iter().map(|&k| square(k)).sum::<f64>() / self.texels.len() as f64;
        let calibration = noise_calibration(mean, se, noise_control_ms);
        let noise_ms = noise_map_ms * calibration;
        let rel = |ms: f64| (ms.max(noise_ms).sqrt() / rms) as f32;
        error.relative = Some(rel(mean));
        error.noise = Some((noise_ms.sqrt() / rms) as f32);
        error.bias = Some(((mean - noise_control_ms * calibration).max(0.0).sqrt() / rms) as f32);
        error.interval = Some([rel(mean - Z90 * se), rel(mean + Z90 * se)]);
        error.control_texels = Some(self.texels.len() as u32);
        true
    }
}

/// z of the two-sided 90 % interval the control states.
pub(crate) const Z90: f64 = 1.645;

/// d_k = (map_k − P_k)² − sP_k² at the control texels `indices` (into `map`; `p` and
/// `p_var` path's luminance and its variance there, in the same order): their mean, the
/// map's mean squared error at the control texels, bias and noise together, and its
/// standard error.
pub(crate) fn squared_error_at(indices: &[usize], map: &[Vec3], p: &[f64], p_var: &[f64]) -> (f64, f64) {
    let m = indices.len() as f64;
    let d: Vec<f64> = indices
        .iter()
        .zip(p.iter().zip(p_var))
        .map(|(&k, (p, v))| (map[k].dot(LUMINANCE) as f64 - p).powi(2) - v)
        .collect();
    let mean = d.iter().sum::<f64>() / m;
    let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (m - 1.0).max(1.0);
    (mean, (var / m).sqrt())
}

/// The factor a map's noise floor is scaled by: the control's 90 % upper bound of the
/// whole squared error (`mean` of d_k with standard error `se`) over the squared noise
/// the map's own figure states at the same texels (`noise_control_ms`), at most 1. The
/// figure is the halves' difference for the raw map (`control::assess_against`) and the
/// denoiser's bound for the delivered one ([`ControlValues::assess_delivered`]). An
/// honest figure gives 1 (the whole error is at least the noise); one that over-states
/// the noise gives the measured share. A mean pushed below zero by the subtraction of
/// path's variance counts as zero, and the interval's half-width stays on top of it: the
/// bound never falls below what the control can resolve. (Without that, on the H200's
/// 2-s bench, vpl on the sphere over a plane read 0.00 % against a true 0.14 %: the
/// mean had gone negative by more than 1.645 standard errors, and the floor to 0.)
pub(crate) fn noise_calibration(mean: f64, se: f64, noise_control_ms: f64) -> f64 {
    if noise_control_ms > 0.0 {
        ((mean.max(0.0) + Z90 * se) / noise_control_ms).min(1.0)
    } else {
        1.0
    }
}

impl Estimate {
    /// The first non-finite value in any layer it holds (total, direct, the directional
    /// moments, ao, the per-texel error, both halves), as (layer, texel, value): the NaN
    /// guard of DESIGN §5 reads every layer that can reach an output, not only `total`.
    pub fn first_non_finite(&self) -> Option<(&'static str, usize, Vec<f32>)> {
        fn rgb(layer: &'static str, v: &[Vec3]) -> Option<(&'static str, usize, Vec<f32>)> {
            let (k, x) = v.iter().enumerate().find(|(_, x)| !x.is_finite())?;
            Some((layer, k, x.to_array().to_vec()))
        }
        fn scalar(layer: &'static str, v: &[f32]) -> Option<(&'static str, usize, Vec<f32>)> {
            let (k, x) = v.iter().enumerate().find(|(_, x)| !x.is_finite())?;
            Some((layer, k, vec![*x]))
        }
        rgb("total", &self.total)
            .or_else(|| self.direct.as_deref().and_then(|d| rgb("direct", d)))
            .or_else(|| {
                let m = self.moments.as_deref()?;
                let (k, x) = m.iter().enumerate().find(|(_, x)| !x.iter().all(|a| a.is_finite()))?;
                Some(("sh", k, x.iter().flat_map(|a| a.to_array()).collect()))
            })
            .or_else(|| self.ao.as_deref().and_then(|a| scalar("ao", a)))
            .or_else(|| self.texel_error.as_deref().and_then(|e| scalar("texel error", e)))
            .or_else(|| {
                let ([a, b], _) = self.halves.as_ref()?;
                rgb("even half", a).or_else(|| rgb("odd half", b))
            })
            .or_else(|| {
                let m = self.shadowmask.as_ref()?;
                let (k, x) = m
                    .values
                    .iter()
                    .enumerate()
                    .find(|(_, x)| !x.iter().all(|a| a.is_finite()))?;
                Some(("shadowmask", k, x.to_vec()))
            })
    }
}

#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct ErrorSummary {
    /// The relative error the bake reports and stops on: the RMS standard error from the
    /// halves over the RMS estimate (noise) for an unbiased technique; for a biased one
    /// with control texels (`engine::control`) the measured RMS error, bias and noise,
    /// never below the noise. `None` before both halves have a step.
    pub relative: Option<f32>,
    /// The noise part alone (the halves' difference), when `relative` covers more.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub noise: Option<f32>,
    /// The bias part measured at the control texels, relative.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bias: Option<f32>,
    /// 90 % interval of `relative` from the control texels' spread.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub interval: Option<[f32; 2]>,
    /// How many control texels measured the bias.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub control_texels: Option<u32>,
    /// RMS of the luminance estimate over valid texels.
    pub rms_luminance: f32,
    /// After denoising, `relative` is the estimated error of the denoised lightmap and
    /// this the raw estimate's; `None` for a raw estimate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub raw_relative: Option<f32>,
    /// The factor the control texels found the halves' noise over-stated by (at most 1;
    /// `control::assess_against`): the per-texel `texel_error` is the halves' and is left
    /// as it is, and the denoiser's blend scales its variance by this. Internal: not
    /// reported.
    #[serde(skip)]
    pub noise_scale: Option<f32>,
}

fn combine(a: &[Vec3], na: u64, b: &[Vec3], nb: u64) -> Vec<Vec3> {
    let n = (na + nb).max(1) as f32;
    let (wa, wb) = (na as f32 / n, nb as f32 / n);
    a.iter().zip(b).map(|(x, y)| *x * wa + *y * wb).collect()
}

impl Snapshot {
    pub fn estimate(&self) -> Estimate {
        let (na, nb) = (self.even.steps, self.odd.steps);
        let total = combine(&self.even.total, na, &self.odd.total, nb);
        let direct = match (&self.even.direct, &self.odd.direct) {
            (Some(a), Some(b)) => Some(combine(a, na, b, nb)),
            _ => None,
        };
        let moments = match (&self.even.moments, &self.odd.moments) {
            (Some(a), Some(b)) => {
                let n = (na + nb).max(1) as f32;
                let (wa, wb) = (na as f32 / n, nb as f32 / n);
                Some(
                    a.iter()
                        .zip(b)
                        .map(|(x, y)| [0, 1, 2].map(|k| x[k] * wa + y[k] * wb))
                        .collect(),
                )
            }
            _ => None,
        };
        let count = total.len().max(1) as f64;
        let rms_luminance =
            (total.iter().map(|v| (v.dot(LUMINANCE) as f64).powi(2)).sum::<f64>() / count).sqrt() as f32;
        let (texel_error, relative) = if na > 0 && nb > 0 {
            let k = ((na * nb) as f64).sqrt() / (na + nb) as f64;
            let errs: Vec<f32> = self
                .even
                .total
                .iter()
                .zip(&self.odd.total)
                .map(|(a, b)| (((*a - *b).dot(LUMINANCE)) as f64 * k).abs() as f32)
                .collect();
            let rms_err = (errs.iter().map(|e| (*e as f64).powi(2)).sum::<f64>() / count).sqrt();
            let rel = if rms_luminance > 0.0 {
                (rms_err / rms_luminance as f64) as f32
            } else {
                0.0
            };
            (Some(errs), Some(rel))
        } else {
            (None, None)
        };
        Estimate {
            steps: na + nb,
            total,
            direct,
            moments,
            ao: None,
            halves: (na > 0 && nb > 0).then(|| ([self.even.total.clone(), self.odd.total.clone()], [na, nb])),
            texel_error,
            shadowmask: None,
            control: None,
            error: ErrorSummary {
                relative,
                noise: None,
                bias: None,
                interval: None,
                control_texels: None,
                rms_luminance,
                raw_relative: None,
                noise_scale: None,
            },
        }
    }
}

/// Running sums of per-step estimates in two halves, for techniques that compute on the
/// CPU (a GPU technique keeps the same sums in GPU buffers).
#[derive(Clone, Debug)]
pub struct HalfAccumulator {
    sums: [Vec<Vec3>; 2],
    direct: Option<[Vec<Vec3>; 2]>,
    moments: Option<[Vec<[Vec3; 3]>; 2]>,
    steps: [u64; 2],
}

impl HalfAccumulator {
    pub fn new(texels: usize, with_direct: bool) -> Self {
        HalfAccumulator {
            sums: [vec![Vec3::ZERO; texels], vec![Vec3::ZERO; texels]],
            direct: with_direct.then(|| [vec![Vec3::ZERO; texels], vec![Vec3::ZERO; texels]]),
            moments: None,
            steps: [0, 0],
        }
    }

    /// Also keeps first moments of incident light (for the `sh.*` layers).
    pub fn with_moments(mut self, keep: bool) -> Self {
        let n = self.sums[0].len();
        self.moments = keep.then(|| [vec![[Vec3::ZERO; 3]; n], vec![[Vec3::ZERO; 3]; n]]);
        self
    }

    pub fn steps(&self) -> u64 {
        self.steps[0] + self.steps[1]
    }

    /// Adds one step's estimate; the half is the parity of the step index.
    pub fn add(&mut self, total: &[Vec3], direct: Option<&[Vec3]>) {
        self.add_with_moments(total, direct, None);
    }

    pub fn add_with_moments(&mut self, total: &[Vec3], direct: Option<&[Vec3]>, moments: Option<&[[Vec3; 3]]>) {
        let half = (self.steps() % 2) as usize;
        if let (Some(m), Some(v)) = (&mut self.moments, moments) {
            for (s, v) in m[half].iter_mut().zip(v) {
                for k in 0..3 {
                    s[k] += v[k];
                }
            }
        }
        for (s, v) in self.sums[half].iter_mut().zip(total) {
            *s += *v;
        }
        if let (Some(d), Some(v)) = (&mut self.direct, direct) {
            for (s, v) in d[half].iter_mut().zip(v) {
                *s += *v;
            }
        }
        self.steps[half] += 1;
    }

    pub fn snapshot(&self) -> Snapshot {
        let half = |h: usize| {
            let n = self.steps[h].max(1) as f32;
            HalfEstimate {
                steps: self.steps[h],
                total: self.sums[h].iter().map(|s| *s / n).collect(),
                direct: self.direct.as_ref().map(|d| d[h].iter().map(|s| *s / n).collect()),
                moments: self
                    .moments
                    .as_ref()
                    .map(|m| m[h].iter().map(|s| s.map(|v| v / n)).collect()),
            }
        };
        Snapshot {
            even: half(0),
            odd: half(1),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;

    #[test]
    fn mean_of_halves_is_mean_of_steps() {
        let mut acc = HalfAccumulator::new(1, true);
        for v in [1.0, 2.0, 3.0, 4.0, 5.0] {
            acc.add(&[Vec3::splat(v)], Some(&[Vec3::splat(v * 0.5)]));
        }
        let est = acc.snapshot().estimate();
        assert_eq!(est.steps, 5);
        assert!((est.total[0] - Vec3::splat(3.0)).length() < 1e-6);
        assert!((est.direct.unwrap()[0] - Vec3::splat(1.5)).length() < 1e-6);
    }

    #[test]
    fn error_estimate_matches_true_standard_error() {
        // Per-step samples uniform in [0, 2) (σ² = 1/3) at 2000 texels, 64 steps: the
        // true standard error of the mean is sqrt(1/3/64) = 0.0722 relative to a mean of 1.
        // The estimate averages 2000 texels, so it is within a few percent of that.
        let texels = 2000;
        let mut acc = HalfAccumulator::new(texels, false);
        for step in 0..64u64 {
            let vals: Vec<Vec3> = (0..texels)
                .map(|t| Vec3::splat(2.0 * Rng::new(1, step, t as u64, 0).next_f32()))
                .collect();
            acc.add(&vals, None);
        }
        let est = acc.snapshot().estimate();
        let rel = est.error.relative.unwrap();
        let truth = (1.0f32 / 3.0 / 64.0).sqrt();
        assert!((rel / truth - 1.0).abs() < 0.06, "estimated {rel}, true {truth}");
    }

    #[test]
    fn no_light_gives_zero_error_not_nan() {
        let mut acc = HalfAccumulator::new(4, false);
        acc.add(&[Vec3::ZERO; 4], None);
        acc.add(&[Vec3::ZERO; 4], None);
        let est = acc.snapshot().estimate();
        assert_eq!(est.error.relative, Some(0.0));
        assert_eq!(est.error.rms_luminance, 0.0);
    }
}
