//! Denoising a finished estimate so that it is never worse than the raw one, with an
//! error estimate for what is delivered.
//!
//! What: [`Denoiser`] is the job's choice (`auto`, `oidn`, `own`, `none`); [`apply`]
//! turns a raw [`Estimate`] into the delivered one: every layer denoised, weighted
//! towards the raw value where the bake has converged, and `texel_error` / `error` the
//! estimate of the delivered lightmap's error (the raw figure stays in
//! `error.raw_relative`).
//!
//! How:
//! 1. Candidates. Besides the raw value, every texel has the seven local polynomial
//!    fits of [`super::regress`] (planes and quadrics over windows of radius 1 to 8 in
//!    its chart) and the image denoiser's output: OIDN ([`super::oidn`],
//!    `RTLightmap`, HDR irradiance), which sees the whole lightmap image with the
//!    gutters and every unused texel filled first (dilation from the nearest chart,
//!    [`FILL_RINGS`] rings: a black gutter would pull chart borders dark) and is read
//!    back at valid texels only (mask after), or where OIDN is not installed the own
//!    filter ([`super::denoise`]), which works on texels and never crosses a chart.
//!    `RTLightmap` takes no auxiliary images; the `RT` filter with a normal image was
//!    measured against it (docs/quality.md) and is not used. Directional (`sh`)
//!    layers are filtered by OIDN's directional mode as coefficients normalised by the
//!    lightmap (in [-1, 1]), then scaled back.
//! 2. Estimate each candidate's own error by cross-validation: the candidate filter is
//!    run on each half (even and odd steps) on its own, and the filtered even half is
//!    compared with the raw odd half, which is independent of it and unbiased:
//!    E[(D(a) − b)²] = MSE(D(a)) + Var(b), so (D(a) − b)² − Var(b), averaged over both
//!    pairings ([`cross_validated`]) and smoothed over a 7 × 7 neighbourhood in the
//!    chart, estimates the filter's mean squared error, bias included. That is the
//!    error of a filtered *half*, which carries twice the noise of the filtered
//!    whole; the excess is taken off: for the fits from their known noise gain a₀
//!    (a₀ Var(half) / 2), for the image denoiser as measured between its two
//!    filtered halves ((D(a) − D(b))² / 4, [`HalfNoise`]). For a linear filter both
//!    leave the filtered whole's error; for the image denoiser what is left is the
//!    error of the filter it chose for a half applied to the whole, still an upper
//!    bound of what it does with the whole's lower noise, a tighter one than a
//!    filtered half's (which weighted OIDN below its due, docs/quality.md).
//! 3. Combine ([`combine_weights`]): delivered = Σ w_c D_c, over the raw value (its error
//!    the raw variance V, smoothed like M: V⁺, V plus one standard error of its
//!    neighbourhood mean) and the candidates (M⁺, M plus one standard error of its
//!    neighbourhood mean, `denoise::smooth_with_error`), with w_c ∝ 1 / M_c², normalised.
//!    As the bake converges V → 0 while every filter's M keeps its bias, so the raw value
//!    takes the whole weight: the denoiser fades out instead of blurring a converged
//!    bake; where the bake is noisy the fit that suits the texel (small and curved near
//!    an edge, wide and flat on a plain wall) or the image denoiser takes it. Selecting
//!    one candidate by its noisy M, or blending a single filter with the raw value, lost
//!    a third of the gain on the Cornell box (docs/quality.md). M is taken one standard
//!    error high because it is itself an estimate: one that comes out low by chance lets
//!    a filter's bias in where the bake has converged (measured over six seeds at 8192
//!    samples: up to 0.33 % worse than raw with M, at most 0.04 % with M⁺), while one
//!    that comes out high only gives up a little of the gain at low sample counts. V is
//!    taken one standard error high for the same reason, the other way (since
//!    2026-12-06): a V that came out low leaves a noisy texel raw, which cost most on
//!    chart borders, where a neighbourhood holds fewer texels. For a biased technique V
//!    is the halves' variance times the factor its control texels found the halves
//!    over-state the noise by (`error.noise_scale`, `control::assess_against`; at most
//!    1): a stratified sequence's union (`vpl`, `obscurance`) errs less than its halves
//!    say, and an over-stated V trusted the filter over a raw value that was better. And
//!    a biased technique's map errs by its measured bias b (`error.bias`) besides its
//!    noise; a filter's own bias, at most √M, may add to it. For one filter the weight
//!    best for the worst case of that sum is (V − √M⁺ b) / (V + M⁺), the unbiased weight
//!    times 1 − √M⁺ b / V; each filter's weight here takes that factor (not below 0;
//!    [`Leanings`]): where bias dominates the filters stay out.
//! 4. For a biased technique, check at its control texels ([`checked_share`]): `path`'s
//!    values there are unbiased and independent of the bake, so whether the filters'
//!    move D − R brings the map closer to the answer can be measured there, bias
//!    included, which the halves cannot do (they share the technique's bias). The move
//!    is kept only as far as it measurably helps (the best share of it, B / A, with B
//!    one-sided 95 % low; 0 where no gain can be shown, including a move that touched
//!    no control texel) and scaled down over the whole map otherwise. Without it the
//!    weights of 3 still let a filter's blur move a bias-dominated map the way its bias
//!    already goes (`vpl` on the parallel plates: up to 8 % worse than raw,
//!    docs/quality.md).
//! 5. Delivered error per texel: Σ w_c √M_c (each part's best estimate, M itself and
//!    V): the RMS error of a convex combination is at most the weighted mean of its
//!    parts' RMS errors, whatever their correlation (the triangle inequality, i.e.
//!    Minkowski), so this bounds it, and more tightly than √(Σ w_c M_c) (Jensen, used
//!    until 2026-12-06); the map's relative error is its RMS over the RMS luminance, as
//!    for the raw estimate (`accumulate`). A biased technique's delivered map is then
//!    measured at its control texels as its raw map is (`ControlValues::assess_delivered`),
//!    with that bound, calibrated there as the raw halves' noise is, as the floor: the
//!    halves share the technique's bias, so what the filters do to it is seen only there
//!    (the raw bias added in quadrature, until 2026-12-06, stated 1.31 for a true 5.78 on
//!    the Cornell box after 2 `obscurance` steps).
//!
//! Limits: the weights come from luminance and are used for all three channels and for
//! the direct and directional layers too; the image denoiser's M is an upper bound (it
//! adapts to the noise it sees, and the half's filter is what is measured), so the
//! weights lean a little away from it;
//! the cross-validation needs both halves, so an estimate with one half's steps is not
//! denoised. Each denoised estimate costs three image-filter runs of the lightmap
//! (whole and halves) and one regression pass, plus one of each per extra layer.

use std::fmt;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use rayon::prelude::*;

use super::denoise::{charts, denoise_own, smooth_with_error};
use super::oidn::{Mode, Oidn};
use super::regress;
use crate::engine::accumulate::{ControlValues, Estimate, LUMINANCE};
use crate::engine::atlas::Atlas;

/// Rings of dilation before OIDN sees the image: wider than OIDN's tiles' overlap is
/// not needed, enough that every chart border has filled texels around it.
pub const FILL_RINGS: u32 = 16;
/// One-sided 95 % normal quantile for the control texels' check ([`checked_share`]).
const CHECK_Z: f64 = 1.645;
/// The most candidates [`combine_weights`] takes besides the raw value.
pub const MAX_CANDIDATES: usize = 15;
/// Neighbourhood radius (texels) for the variance and error figures of the blend.
const SMOOTH_RADIUS: i64 = 3;

/// The denoiser a job asks for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Denoiser {
    /// OIDN when its library is installed, else the own filter.
    #[default]
    Auto,
    Oidn,
    Own,
    None,
}

impl Denoiser {
    pub const NAMES: &'static str = "auto, oidn, own, none";
    /// Every choice, in the order `NAMES` lists them.
    pub const ALL: [Denoiser; 4] = [Denoiser::Auto, Denoiser::Oidn, Denoiser::Own, Denoiser::None];

    /// The name a request gives (`--denoiser`, the job field `denoise`).
    pub fn name(self) -> &'static str {
        match self {
            Denoiser::Auto => "auto",
            Denoiser::Oidn => "oidn",
            Denoiser::Own => "own",
            Denoiser::None => "none",
        }
    }

    /// One line on what the choice does.
    pub fn summary(self) -> &'static str {
        match self {
            Denoiser::Auto => "Intel Open Image Denoise when its library is installed, else the own filter",
            Denoiser::Oidn => {
                "Intel Open Image Denoise (RTLightmap, HDR) and local regressions, weighted with the raw estimate by cross-validated error"
            }
            Denoiser::Own => {
                "the own edge-aware a-trous filter and local regressions, guided by chart, weighted with the raw estimate by cross-validated error"
            }
            Denoiser::None => "the raw estimate",
        }
    }

    pub fn parse(s: &str) -> Result<Denoiser, String> {
        match s {
            "auto" => Ok(Denoiser::Auto),
            "oidn" => Ok(Denoiser::Oidn),
            "own" => Ok(Denoiser::Own),
            "none" => Ok(Denoiser::None),
            other => Err(format!("unknown denoiser {other:?}; available: {}", Denoiser::NAMES)),
        }
    }

    /// The denoiser a bake will use; `oidn` without the library is an error that says
    /// how to install it.
    pub fn resolve(self) -> Result<Used, String> {
        match self {
            Denoiser::Auto => Ok(if Oidn::available() { Used::Oidn } else { Used::Own }),
            Denoiser::Oidn => Oidn::get().map(|_| Used::Oidn).map_err(|e| e.to_string()),
            Denoiser::Own => Ok(Used::Own),
            Denoiser::None => Ok(Used::None),
        }
    }
}

/// `true` and `false` are accepted for requests written before the choice existed.
impl<'de> Deserialize<'de> for Denoiser {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Wire {
            Flag(bool),
            Name(String),
        }
        match Wire::deserialize(d)? {
            Wire::Flag(true) => Ok(Denoiser::Auto),
            Wire::Flag(false) => Ok(Denoiser::None),
            Wire::Name(s) => Denoiser::parse(&s).map_err(serde::de::Error::custom),
        }
    }
}

/// The denoiser actually run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Used {
    Oidn,
    Own,
    None,
}

impl fmt::Display for Used {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Used::Oidn => match Oidn::get() {
                Ok(o) => write!(
                    f,
                    "{} RTLightmap with local regressions, weighted by cross-validated error",
                    o.describe()
                ),
                Err(_) => f.write_str("oidn (unavailable)"),
            },
            Used::Own => {
                f.write_str("own (edge-aware a-trous) with local regressions, weighted by cross-validated error")
            }
            Used::None => f.write_str("none"),
        }
    }
}

/// What one filter does to one layer.
#[derive(Clone, Copy)]
enum Layer {
    Irradiance,
    Directional,
}

/// Runs `used` on a lightmap layer without blending (for measurements: the delivered
/// estimate is [`apply`]'s).
pub fn filter_unblended(atlas: &Atlas, chart: &[u32], used: Used, values: &[Vec3], se: &[f32]) -> Vec<Vec3> {
    if used == Used::None {
        return values.to_vec();
    }
    filter(atlas, chart, used, values, se, Layer::Irradiance)
}

/// Runs `used` on per-texel `values` (with per-texel luminance standard errors `se` for
/// the own filter); OIDN failures fall back to the own filter with a warning.
fn filter(atlas: &Atlas, chart: &[u32], used: Used, values: &[Vec3], se: &[f32], layer: Layer) -> Vec<Vec3> {
    if used == Used::Oidn
        && let Ok(oidn) = Oidn::get()
    {
        let img = super::dilate(atlas, values, FILL_RINGS);
        let mode = match layer {
            Layer::Irradiance => Mode::Lightmap,
            Layer::Directional => Mode::Directional,
        };
        match oidn.filter(atlas.width, atlas.height, &img, None, mode) {
            Ok(out) => return atlas.texels.iter().map(|t| out[t.pixel as usize]).collect(),
            Err(e) => tracing::warn!(error = %e, "OIDN failed; using the own denoiser"),
        }
    }
    denoise_own(atlas, chart, values, se)
}

/// Per-texel weights of the candidates and delivered standard errors (see the module
/// doc, 3-5).
pub struct Combination {
    /// Candidates per texel: the raw value first, then those whose errors were given.
    pub stride: usize,
    /// `stride` weights per texel (texel-major), each in [0, 1], summing to 1.
    pub weights: Vec<f32>,
    /// Estimated standard error of the delivered luminance.
    pub texel_error: Vec<f32>,
    /// The raw value's variance V per texel (smoothed; the raw candidate's error).
    pub raw_var: Vec<f32>,
}

impl Combination {
    /// Keeps `share` of the filters' move away from the raw value at every texel:
    /// their weights times `share`, the raw value's the rest; the delivered error by
    /// the same bound, (1 − share) V + share × the combination's.
    pub fn scale_filters(&mut self, share: f32) {
        let share = share.clamp(0.0, 1.0);
        for (k, w) in self.weights.chunks_mut(self.stride).enumerate() {
            for x in w[1..].iter_mut() {
                *x *= share;
            }
            w[0] = 1.0 - w[1..].iter().sum::<f32>();
            let e = &mut self.texel_error[k];
            // The same bound (Minkowski) for the raw value and the combination mixed.
            *e = ((1.0 - share) * self.raw_var[k].max(0.0).sqrt() + share * *e).max(0.0);
        }
    }

    /// Texel `k`'s weights, the raw value's first.
    pub fn at(&self, k: usize) -> &[f32] {
        &self.weights[k * self.stride..(k + 1) * self.stride]
    }

    /// Per texel, the weight left to the filters (1 − the raw value's).
    pub fn filtered_share(&self) -> Vec<f32> {
        self.weights.chunks(self.stride).map(|w| 1.0 - w[0]).collect()
    }
}

/// What leans the blend one way or the other besides the two variances.
#[derive(Clone, Copy, Debug)]
pub struct Leanings {
    /// The factor the halves over-state the raw map's noise by (at most 1).
    pub noise_scale: f32,
    /// The technique's measured bias, absolute (luminance), 0 for an unbiased one.
    pub bias: f32,
}

impl Default for Leanings {
    fn default() -> Self {
        Leanings {
            noise_scale: 1.0,
            bias: 0.0,
        }
    }
}

/// How [`cross_validated`] turns a filtered half's error into the filtered whole's.
#[derive(Clone, Copy, Debug)]
pub enum HalfNoise<'a> {
    /// A linear filter's noise gain per texel (the fits' a₀ = Σ l²): its output's noise
    /// is a₀ times its input's variance.
    Gain(&'a [f32]),
    /// Measured from the two filtered halves (the image denoiser's, whose gain is not
    /// known): D(a) and D(b) are independent draws of the same filter's output, so
    /// ½ (D(a) − D(b))² estimates a filtered half's noise.
    Measured,
}

/// Step 2 for one candidate filter D, per texel: the cross-validated estimate of the
/// mean squared error of D applied to the whole estimate, from D's output on each half
/// (`filtered[h]`, luminance) against the other raw half: ½ Σ_h [(D(h) − other)² −
/// Var(other)], less what a filtered half's noise exceeds the filtered whole's by. A
/// half's variance is s_h times the whole's (s_h = n / n_h, Σ 1/s_h = 1), so D's noise
/// g Var s_h on a half is g Var on the whole, and the pairings' mean carries
/// g Var ((s₀ + s₁)/2 − 1) more than the whole's (g Var with equal halves). For a
/// linear filter (`HalfNoise::Gain`) that is exact. For the image denoiser g Var
/// (s₀ + s₁) is measured as E[(D(a) − D(b))²] (`HalfNoise::Measured`), and what is
/// left is the error of the filter it used on a half applied to the whole, which a
/// denoiser that adapts to its input's noise can only improve on with the whole's
/// lower noise; the figure stays an upper bound, a tighter one than a filtered half's.
/// NaN where D offers no value.
pub fn cross_validated(
    se: &[f32],
    halves: &[Vec<Vec3>; 2],
    half_steps: [u64; 2],
    filtered: [&[f32]; 2],
    noise: HalfNoise,
) -> Vec<f32> {
    let n = (half_steps[0] + half_steps[1]) as f32;
    // Variance of each half's mean: the combined mean's, times n / n_h.
    let scale = [n / half_steps[0].max(1) as f32, n / half_steps[1].max(1) as f32];
    let excess = 0.5 * (scale[0] + scale[1]) - 1.0;
    (0..se.len())
        .map(|k| {
            let var = se[k] * se[k];
            let l = |x: Vec3| x.dot(LUMINANCE);
            let e0 = (filtered[0][k] - l(halves[1][k])).powi(2) - var * scale[1];
            let e1 = (filtered[1][k] - l(halves[0][k])).powi(2) - var * scale[0];
            let own = match noise {
                HalfNoise::Gain(g) => g[k] * var * excess,
                HalfNoise::Measured => (filtered[0][k] - filtered[1][k]).powi(2) * excess / (scale[0] + scale[1]),
            };
            0.5 * (e0 + e1) - own
        })
        .collect()
}

/// Steps 3 and 5: each texel's weights over the raw value (its variance V from the
/// halves, smoothed) and the candidates whose cross-validated errors are `cross` (from
/// [`cross_validated`]; smoothed over the 7 × 7 neighbourhood with their standard
/// error), and the delivered standard error.
pub fn combine_weights(atlas: &Atlas, chart: &[u32], se: &[f32], cross: &[Vec<f32>], lean: Leanings) -> Combination {
    let noise_scale = lean.noise_scale;
    // The raw lightmap's own variance: the halves' figure, scaled down where the control
    // texels measured that they over-state it (a stratified sequence's union errs less
    // than its halves say: `vpl`, `obscurance`), so a filter is not trusted over a raw
    // value that is better than the halves claim.
    let own_var: Vec<f32> = se.iter().map(|e| e * e * noise_scale.clamp(0.0, 1.0)).collect();
    // V smoothed, with the standard error of its neighbourhood mean: V is an estimate
    // too (the halves' difference, squared), and the texels where it came out low by
    // chance are the ones the blend would leave raw.
    let (v, v_err): (Vec<f32>, Vec<f32>) = smooth_with_error(atlas, chart, &own_var, SMOOTH_RADIUS)
        .into_iter()
        .map(|(m, e)| if m.is_finite() { (m, e.max(0.0)) } else { (0.0, 0.0) })
        .unzip();
    let m: Vec<Vec<(f32, f32)>> = cross
        .iter()
        .map(|c| smooth_with_error(atlas, chart, c, SMOOTH_RADIUS))
        .collect();
    let stride = 1 + cross.len();
    assert!(cross.len() <= MAX_CANDIDATES, "{} candidates", cross.len());
    let b = lean.bias.max(0.0);
    let mut weights = vec![0.0f32; v.len() * stride];
    let mut texel_error = vec![0.0f32; v.len()];
    weights
        .par_chunks_mut(stride)
        .zip(texel_error.par_iter_mut())
        .enumerate()
        .for_each(|(k, (w, err))| {
            let v = v[k];
            w[0] = 1.0;
            if v <= 0.0 {
                // Nothing to take away: the raw value stands, and so does its error.
                *err = 0.0;
                return;
            }
            // Every candidate is weighted by the inverse square of its expected squared
            // error. A biased technique's map errs by its bias b besides its noise, and
            // a filter's own bias (at most √M) may add to it: each filter's weight is
            // also scaled by 1 − √M b / V, not below 0, the factor by which the weight
            // best for the worst case of that sum, (V − √M b) / (V + M), falls short of
            // the unbiased one, V / (V + M); where bias dominates the filters stay out.
            // In f64 and relative to the raw value's (1): the squares of a dark texel's
            // variances leave f32's range.
            //
            // Every figure is taken one standard error of its neighbourhood mean high,
            // the raw value's V as each filter's M: they are estimates, and a figure that
            // came out low by chance wins the weight it should not have. For M that lets
            // a filter's bias in where the bake has converged (the delivered map measured
            // 0.2-0.3 % worse than raw at 8192 samples with M itself, 2026-12-05); for V
            // it leaves a noisy texel raw where its halves happened to agree (on the
            // occlusion room at 16 steps, the 317 border texels the blend left at least
            // three-quarters raw had a true squared error 3.6 times their V; taking V one
            // standard error high took the room from 1.90 % to 1.85 %, its borders from
            // 3.70 % to 3.57 %, docs/quality.md). The shrink for bias keeps V itself, the
            // side that trusts the filters less.
            let raw = v as f64;
            let raw_high = (v + v_err[k]) as f64;
            let mut rel = [0.0f64; 1 + MAX_CANDIDATES];
            rel[0] = 1.0;
            for (c, mc) in m.iter().enumerate() {
                let (mean, mean_err) = mc[k];
                if !mean.is_finite() {
                    continue;
                }
                // The cross-validated figure is itself noisy and can fall to zero or
                // below; no filter removes all noise, so M is kept above V / 256 (a
                // filter averaging 256 independent texels).
                let safe = (mean as f64 + mean_err.max(0.0) as f64).max(raw / 256.0);
                let shrink = (1.0 - safe.sqrt() * b as f64 / raw).max(0.0);
                rel[c + 1] = (raw_high / safe).powi(2) * shrink;
            }
            let sum: f64 = rel[..w.len()].iter().sum();
            if !sum.is_finite() {
                // Not expected (every ratio is at most 256²); the raw value is safe.
                w.fill(0.0);
                w[0] = 1.0;
                *err = v.sqrt();
                return;
            }
            for (x, r) in w.iter_mut().zip(&rel) {
                *x = (r / sum) as f32;
            }
            // The delivered error: a convex combination's RMS error is at most the
            // weighted mean of its parts' RMS errors (the triangle inequality for the
            // RMS, Minkowski), whatever their correlation; the parts' own best estimates
            // M (not one standard error high), the raw value's V. (Σ w √M)² is never
            // above Σ w M, the Jensen bound used before 2026-12-06, and is as safe.
            let parts: f32 = m
                .iter()
                .zip(&w[1..])
                .filter(|(_, w)| **w > 0.0)
                .map(|(mc, w)| w * mc[k].0.max(v / 256.0).sqrt())
                .sum();
            *err = (w[0] * v.sqrt() + parts).max(0.0);
        });
    Combination {
        stride,
        weights,
        texel_error,
        raw_var: v,
    }
}

/// Step 5, for a biased technique: the share of the filters' move D − R to keep, as
/// checked at its control texels against `path`'s values P there. With the move scaled
/// by s, the squared error there changes by s² A − 2 s B, A = mean (D − R)², B =
/// mean (D − R)(P − R); P is unbiased and independent of the bake, so B estimates
/// mean (D − R)(T − R) against the answer T, and s = B / A is best. B is taken one-sided
/// 95 % low (1.645 standard errors of its mean over the control texels, which holds
/// P's noise and the spread between texels), so the check keeps the filters' move only
/// as far as it measurably brings the map closer to the answer: 0 where that cannot be
/// shown, never above 1. That includes the cases with nothing to measure: fewer than two
/// control texels, or a move that left every control texel where it was while it moved
/// others (the weights of step 3 can be 0 at the control texels and not elsewhere). An
/// unchecked move there is no safer than an unhelpful one: `sdb` on blocks-25k at 1023
/// steps delivered 18.4003 % against raw's 18.4001 % through exactly that gap, until
/// 2026-12-06.
pub fn checked_share(raw: &[Vec3], delivered: &[Vec3], control: &ControlValues) -> f32 {
    let m = control.texels.len();
    if m < 2 {
        return 0.0;
    }
    let lum = |v: Vec3| v.dot(LUMINANCE) as f64;
    let (mut a, mut b, mut bb) = (0.0f64, 0.0f64, 0.0f64);
    for (&k, &p) in control.texels.iter().zip(&control.luminance) {
        let d = lum(delivered[k]) - lum(raw[k]);
        let x = d * (p as f64 - lum(raw[k]));
        a += d * d;
        b += x;
        bb += x * x;
    }
    let n = m as f64;
    let (a, b) = (a / n, b / n);
    if a <= 0.0 {
        return 0.0;
    }
    let var = ((bb / n - b * b) * n / (n - 1.0)).max(0.0);
    let low = b - CHECK_Z * (var / n).sqrt();
    (low / a).clamp(0.0, 1.0) as f32
}

/// The candidates' values of one layer at every texel: the raw value, the regression
/// fits (a fit not offered at a texel takes the raw value; its weight there is 0) and
/// the image denoiser's output when one ran, mixed by the combination's weights.
fn mix(raw: &[Vec3], fits: &regress::Fits, image: Option<&[Vec3]>, c: &Combination) -> Vec<Vec3> {
    (0..raw.len())
        .into_par_iter()
        .map(|k| {
            // Σ w_c D_c with Σ w_c = 1, written as the raw value plus the weighted moves
            // D_c − raw: where the bake has converged and the filters keep weights of
            // 1e-6, the raw value comes back to its last bit instead of through a sum of
            // rounded products, so rounding alone cannot make a converged map worse.
            let w = c.at(k);
            let r = raw[k];
            let mut moved = Vec3::ZERO;
            for f in 0..regress::CANDIDATES {
                let v = fits.values[k][f];
                if v.is_finite() {
                    moved += (v - r) * w[1 + f];
                }
            }
            if let Some(img) = image {
                moved += (img[k] - r) * w[1 + regress::CANDIDATES];
            }
            r + moved
        })
        .collect()
}

/// The delivered estimate for `estimate` with `used` (see the module doc); the raw
/// estimate is returned unchanged for `Used::None` and before both halves have steps.
pub fn apply(atlas: &Atlas, estimate: &Estimate, used: Used) -> Estimate {
    apply_with_weights(atlas, estimate, used).0
}

/// [`apply`], also returning the weight left to the filters per texel (1 − the raw
/// value's; empty when nothing was filtered).
pub fn apply_with_weights(atlas: &Atlas, estimate: &Estimate, used: Used) -> (Estimate, Vec<f32>) {
    let mut out = estimate.clone();
    let (Some(se), Some((halves, half_steps))) = (&estimate.texel_error, &estimate.halves) else {
        return (out, Vec::new());
    };
    if used == Used::None || estimate.total.is_empty() {
        return (out, Vec::new());
    }
    let started = std::time::Instant::now();
    let chart = charts(atlas);
    let n = (half_steps[0] + half_steps[1]) as f32;
    let half_se = |h: usize| -> Vec<f32> {
        let s = (n / half_steps[h].max(1) as f32).sqrt();
        se.iter().map(|e| e * s).collect()
    };
    // The candidates: the regression fits of the lightmap and of each half, then the
    // image denoiser on the lightmap and on each half.
    let fits = regress::fit(atlas, &chart, &estimate.total, Some([&halves[0], &halves[1]]));
    let image = filter(atlas, &chart, used, &estimate.total, se, Layer::Irradiance);
    let image_halves: [Vec<f32>; 2] = [0, 1].map(|h| {
        filter(atlas, &chart, used, &halves[h], &half_se(h), Layer::Irradiance)
            .iter()
            .map(|v| v.dot(LUMINANCE))
            .collect()
    });
    let fit_halves = fits.halves.as_ref().expect("fitted with halves");
    let mut cross: Vec<Vec<f32>> = (0..regress::CANDIDATES)
        .into_par_iter()
        .map(|f| {
            let column = |h: usize| -> Vec<f32> {
                (0..se.len())
                    .map(|k| {
                        if fits.values[k][f].is_finite() {
                            fit_halves[h][k][f]
                        } else {
                            f32::NAN
                        }
                    })
                    .collect()
            };
            let gain: Vec<f32> = fits.gain.iter().map(|g| g[f]).collect();
            let (a, b) = (column(0), column(1));
            cross_validated(se, halves, *half_steps, [&a, &b], HalfNoise::Gain(&gain))
        })
        .collect();
    cross.push(cross_validated(
        se,
        halves,
        *half_steps,
        [&image_halves[0], &image_halves[1]],
        HalfNoise::Measured,
    ));
    let mut combination = combine_weights(
        atlas,
        &chart,
        se,
        &cross,
        Leanings {
            noise_scale: estimate.error.noise_scale.unwrap_or(1.0),
            // The measured bias on the lightmap's scale (the control texels report it
            // relative to the answer's RMS, which the map's RMS stands in for).
            bias: estimate.error.bias.unwrap_or(0.0) * estimate.error.rms_luminance,
        },
    );
    out.total = mix(&estimate.total, &fits, Some(&image), &combination);
    let checked = estimate
        .control
        .as_deref()
        .map(|c| checked_share(&estimate.total, &out.total, c));
    if let Some(share) = checked.filter(|s| *s < 1.0) {
        combination.scale_filters(share);
        for (d, r) in out.total.iter_mut().zip(&estimate.total) {
            *d = *r + (*d - *r) * share;
        }
    }
    if let Some(d) = &estimate.direct {
        let fits = regress::fit(atlas, &chart, d, None);
        let image = filter(atlas, &chart, used, d, se, Layer::Irradiance);
        out.direct = Some(mix(d, &fits, Some(&image), &combination));
    }
    if let Some(m) = &estimate.moments {
        out.moments = Some(denoise_moments(
            atlas,
            &chart,
            used,
            m,
            &estimate.total,
            &out.total,
            se,
            &combination,
        ));
    }
    let count = out.total.len().max(1) as f64;
    let rms = (out.total.iter().map(|v| (v.dot(LUMINANCE) as f64).powi(2)).sum::<f64>() / count).sqrt();
    let rms_err = (combination.texel_error.iter().map(|e| (*e as f64).powi(2)).sum::<f64>() / count).sqrt();
    out.error.raw_relative = estimate.error.relative;
    let noise = if rms > 0.0 { (rms_err / rms) as f32 } else { 0.0 };
    // A biased technique's delivered map is measured at its control texels as the raw one
    // is (bias, noise and what the filters did to both); its noise bound, calibrated
    // there as the raw halves' is, is the floor. Otherwise (an unbiased technique, or a
    // control with nothing to measure) the noise bound, with the raw map's measured bias
    // in quadrature where there is one.
    let measured = estimate
        .control
        .as_deref()
        .is_some_and(|c| c.assess_delivered(&out.total, &combination.texel_error, &mut out.error));
    if !measured {
        out.error.relative = Some(match estimate.error.bias {
            Some(b) => (noise * noise + b * b).sqrt(),
            None => noise,
        });
        if estimate.error.bias.is_some() {
            out.error.noise = Some(noise);
            out.error.interval = None;
        }
    }
    out.error.rms_luminance = rms as f32;
    out.texel_error = Some(combination.texel_error.clone());
    out.halves = None;
    let share = combination.filtered_share();
    let mean_weight = share.iter().map(|w| *w as f64).sum::<f64>() / count;
    tracing::debug!(
        denoiser = %used,
        steps = estimate.steps,
        raw_error = ?estimate.error.relative,
        delivered_error = ?out.error.relative,
        mean_weight,
        checked_share = ?checked,
        ms = started.elapsed().as_millis() as u64,
        "denoised"
    );
    (out, share)
}

/// Directional moments: OIDN's directional mode wants coefficients in [-1, 1], so each
/// axis is divided by the raw lightmap (per channel), filtered, and multiplied by the
/// delivered lightmap; the own filter takes the moments as they are. Each axis's
/// regression fits and filtered values are mixed by the lightmap's weights.
#[allow(clippy::too_many_arguments)]
fn denoise_moments(
    atlas: &Atlas,
    chart: &[u32],
    used: Used,
    m: &[[Vec3; 3]],
    raw_total: &[Vec3],
    total: &[Vec3],
    se: &[f32],
    combination: &Combination,
) -> Vec<[Vec3; 3]> {
    let axes: Vec<Vec<Vec3>> = (0..3)
        .map(|k| {
            let raw: Vec<Vec3> = m.iter().map(|v| v[k]).collect();
            let filtered = if used == Used::Oidn && Oidn::available() {
                let coef: Vec<Vec3> = raw
                    .iter()
                    .zip(raw_total)
                    .map(|(v, t)| (*v / t.max(Vec3::splat(1e-12))).clamp(Vec3::splat(-1.0), Vec3::ONE))
                    .collect();
                filter(atlas, chart, used, &coef, se, Layer::Directional)
                    .iter()
                    .zip(total)
                    .map(|(c, t)| *c * *t)
                    .collect()
            } else {
                filter(atlas, chart, used, &raw, se, Layer::Directional)
            };
            let fits = regress::fit(atlas, chart, &raw, None);
            mix(&raw, &fits, Some(&filtered), combination)
        })
        .collect();
    (0..m.len()).map(|t| [axes[0][t], axes[1][t], axes[2][t]]).collect()
}
