//! Denoising a finished estimate so that it is never worse than the raw one, with an
//! error estimate for what is delivered.
//!
//! What: [`Denoiser`] is the job's choice (`auto`, `oidn`, `own`, `none`); [`apply`]
//! turns a raw [`Estimate`] into the delivered one: every layer denoised, blended back
//! towards the raw value where the bake has converged, and `texel_error` / `error` the
//! estimate of the delivered lightmap's error (the raw figure stays in
//! `error.raw_relative`).
//!
//! How:
//! 1. Filter. OIDN ([`super::oidn`], `RTLightmap`, HDR irradiance) sees the whole
//!    lightmap image with the gutters and every unused texel filled first (dilation from
//!    the nearest chart, [`FILL_RINGS`] rings: a black gutter would pull chart borders
//!    dark) and is read back at valid texels only (mask after). The own filter
//!    ([`super::denoise`]) works on texels and never crosses a chart. `RTLightmap` takes
//!    no auxiliary images; the `RT` filter with a normal image was measured against it
//!    (docs/quality.md) and is not used. Directional (`sh`) layers are filtered by OIDN's
//!    directional mode as coefficients normalised by the lightmap (in [-1, 1]), then
//!    scaled back.
//! 2. Estimate the filter's own error by cross-validation: each half (even and odd
//!    steps) is filtered on its own, and the filtered even half is compared with the raw
//!    odd half, which is independent of it and unbiased: E[(D(a) − b)²] = MSE(D(a)) +
//!    Var(b), so (D(a) − b)² − Var(b), averaged over both pairings and smoothed over a
//!    7 × 7 neighbourhood in the chart, estimates the filter's mean squared error,
//!    bias included. It is the error of a filtered *half*, an upper bound on that of the
//!    filtered whole (fewer samples: more noise and more blur).
//! 3. Blend: delivered = raw + w (filtered − raw) with w = V / (V + M⁺), V the raw
//!    variance (smoothed like M), M the filter's error from 2: the weighting that
//!    minimises the mean squared error of two independent estimates. As the bake
//!    converges V → 0 while M keeps the filter's bias, so w → 0 and the delivered map
//!    becomes the raw one: the denoiser fades out instead of blurring a converged bake.
//!    M⁺ is M plus one standard error of its neighbourhood mean
//!    (`denoise::smooth_with_error`): M is itself an estimate, and one that comes out
//!    low by chance lets the filter's bias in where the bake has converged (measured
//!    over six seeds at 8192 samples: up to 0.33 % worse than raw with M, at most 0.04 %
//!    with M⁺), while one that comes out high only gives up a little of the filter's
//!    gain at low sample counts. For a biased technique V is the halves' variance times
//!    the factor its control texels found the halves over-state the noise by
//!    (`error.noise_scale`, `control::assess_against`; at most 1): a stratified
//!    sequence's union (`vpl`, `obscurance`) errs less than its halves say, and an
//!    over-stated V trusted the filter over a raw value that was better (the bench's
//!    `vpl` on the parallel plates: denoised worse than raw at 8 of 8 snapshots). And a
//!    biased technique's map errs by its measured bias b (`error.bias`) besides its
//!    noise; the filter's own bias, at most √M, may add to it, so the weight is the one
//!    best for the worst case of that sum, w = (V − √M⁺ b) / (V + M⁺), not below 0
//!    ([`Leanings`]): where bias dominates the filter stays out (docs/quality.md, the
//!    bench over every technique).
//! 4. Delivered error per texel: √(w² M + (1 − w)² V) (M itself, the best estimate);
//!    the map's relative error is
//!    its RMS over the RMS luminance, as for the raw estimate (`accumulate`).
//!
//! Limits: the blend weight comes from luminance and is used for all three channels
//! and for the direct and directional layers too; M is an upper bound (a filtered half
//! is worse than the filtered whole), so the blend leans towards raw; the cross-
//! validation needs both halves, so an estimate with one half's steps is not denoised.
//! Each denoised estimate costs three filter runs of the lightmap (whole and halves)
//! plus one per extra layer.

use std::fmt;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::denoise::{charts, denoise_own, smooth, smooth_with_error};
use super::oidn::{Mode, Oidn};
use crate::engine::accumulate::{Estimate, LUMINANCE};
use crate::engine::atlas::Atlas;

/// Rings of dilation before OIDN sees the image: wider than OIDN's tiles' overlap is
/// not needed, enough that every chart border has filled texels around it.
pub const FILL_RINGS: u32 = 16;
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
            Denoiser::Oidn => "Intel Open Image Denoise (RTLightmap, HDR), blended by the bake's error estimate",
            Denoiser::Own => "the own edge-aware a-trous filter, guided by chart, blended by the error estimate",
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
                Ok(o) => write!(f, "{} RTLightmap, blended by error", o.describe()),
                Err(_) => f.write_str("oidn (unavailable)"),
            },
            Used::Own => f.write_str("own (edge-aware a-trous), blended by error"),
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

/// Per-texel blend weights and delivered standard errors (see the module doc, 2-4).
pub struct Blend {
    /// Weight of the filtered value, in [0, 1].
    pub weight: Vec<f32>,
    /// Estimated standard error of the delivered luminance.
    pub texel_error: Vec<f32>,
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

/// The blend of step 3 from the raw standard errors, the raw halves and the filtered
/// halves (`filtered[h]` = D(halves[h])).
pub fn blend_weights(
    atlas: &Atlas,
    chart: &[u32],
    se: &[f32],
    halves: &[Vec<Vec3>; 2],
    half_steps: [u64; 2],
    filtered: &[Vec<Vec3>; 2],
    lean: Leanings,
) -> Blend {
    let noise_scale = lean.noise_scale;
    let n = (half_steps[0] + half_steps[1]) as f32;
    let raw_var: Vec<f32> = se.iter().map(|e| e * e).collect();
    // The raw lightmap's own variance: the halves' figure, scaled down where the control
    // texels measured that they over-state it (a stratified sequence's union errs less
    // than its halves say: `vpl`, `obscurance`), so the filter is not trusted over a raw
    // value that is better than the halves claim. Each half's own variance (below) is the
    // halves' figure as it is.
    let own_var: Vec<f32> = raw_var.iter().map(|v| v * noise_scale.clamp(0.0, 1.0)).collect();
    let v = smooth(atlas, chart, &own_var, SMOOTH_RADIUS);
    // Variance of each half's mean: the combined mean's, times n / n_h.
    let scale = [n / half_steps[0].max(1) as f32, n / half_steps[1].max(1) as f32];
    let cross: Vec<f32> = (0..se.len())
        .map(|k| {
            let l = |x: Vec3| x.dot(LUMINANCE);
            let e0 = l(filtered[0][k] - halves[1][k]).powi(2) - raw_var[k] * scale[1];
            let e1 = l(filtered[1][k] - halves[0][k]).powi(2) - raw_var[k] * scale[0];
            0.5 * (e0 + e1)
        })
        .collect();
    let m = smooth_with_error(atlas, chart, &cross, SMOOTH_RADIUS);
    let (weight, texel_error) = v
        .iter()
        .zip(&m)
        .map(|(&v, &(m, m_err))| {
            // The cross-validated figure is itself noisy and can fall to zero or below;
            // no filter removes all noise, so M is kept above V / 256 (a filter averaging
            // 256 independent texels) and the delivered error is never claimed zero.
            // The weight takes M one standard error high: an M that came out low by
            // chance would let the filter's bias in where the bake has converged (the
            // delivered map measured 0.2-0.3 % worse than raw at 8192 samples with M
            // itself), while one that came out high only gives up a little of the gain.
            let m_best = m.max(v / 256.0);
            let m_safe = (m + m_err).max(v / 256.0);
            // A biased technique's map errs by its bias b besides its noise, and the
            // filter's own bias (at most √M) may add to it: the weight that is best for
            // the worst case of that sum, (V − √M b) / (V + M), not below 0.
            let w = if v > 0.0 {
                ((v - m_safe.sqrt() * lean.bias) / (v + m_safe)).max(0.0)
            } else {
                0.0
            };
            (w, (w * w * m_best + (1.0 - w) * (1.0 - w) * v).sqrt())
        })
        .unzip();
    Blend { weight, texel_error }
}

fn mix(raw: &[Vec3], filtered: &[Vec3], w: &[f32]) -> Vec<Vec3> {
    raw.iter()
        .zip(filtered)
        .zip(w)
        .map(|((r, f), w)| *r + (*f - *r) * *w)
        .collect()
}

/// The delivered estimate for `estimate` with `used` (see the module doc); the raw
/// estimate is returned unchanged for `Used::None` and before both halves have steps.
pub fn apply(atlas: &Atlas, estimate: &Estimate, used: Used) -> Estimate {
    apply_with_weights(atlas, estimate, used).0
}

/// [`apply`], also returning the blend weight of the filtered value per texel (empty
/// when nothing was filtered).
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
    let whole = filter(atlas, &chart, used, &estimate.total, se, Layer::Irradiance);
    let filtered_halves = [
        filter(atlas, &chart, used, &halves[0], &half_se(0), Layer::Irradiance),
        filter(atlas, &chart, used, &halves[1], &half_se(1), Layer::Irradiance),
    ];
    let blend = blend_weights(
        atlas,
        &chart,
        se,
        halves,
        *half_steps,
        &filtered_halves,
        Leanings {
            noise_scale: estimate.error.noise_scale.unwrap_or(1.0),
            // The measured bias on the lightmap's scale (the control texels report it
            // relative to the answer's RMS, which the map's RMS stands in for).
            bias: estimate.error.bias.unwrap_or(0.0) * estimate.error.rms_luminance,
        },
    );
    out.total = mix(&estimate.total, &whole, &blend.weight);
    if let Some(d) = &estimate.direct {
        out.direct = Some(mix(
            d,
            &filter(atlas, &chart, used, d, se, Layer::Irradiance),
            &blend.weight,
        ));
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
            &blend.weight,
        ));
    }
    let count = out.total.len().max(1) as f64;
    let rms = (out.total.iter().map(|v| (v.dot(LUMINANCE) as f64).powi(2)).sum::<f64>() / count).sqrt();
    let rms_err = (blend.texel_error.iter().map(|e| (*e as f64).powi(2)).sum::<f64>() / count).sqrt();
    out.error.raw_relative = estimate.error.relative;
    let noise = if rms > 0.0 { (rms_err / rms) as f32 } else { 0.0 };
    // The bias the control texels measured is still there after denoising (the filter
    // only trades noise for its own blur): added back to the denoised noise.
    out.error.relative = Some(match estimate.error.bias {
        Some(b) => (noise * noise + b * b).sqrt(),
        None => noise,
    });
    if estimate.error.bias.is_some() {
        out.error.noise = Some(noise);
        out.error.interval = None;
    }
    out.error.rms_luminance = rms as f32;
    out.texel_error = Some(blend.texel_error);
    out.halves = None;
    let mean_weight = blend.weight.iter().map(|w| *w as f64).sum::<f64>() / count;
    tracing::debug!(
        denoiser = %used,
        steps = estimate.steps,
        raw_error = ?estimate.error.relative,
        delivered_error = ?out.error.relative,
        mean_weight,
        ms = started.elapsed().as_millis() as u64,
        "denoised"
    );
    (out, blend.weight)
}

/// Directional moments: OIDN's directional mode wants coefficients in [-1, 1], so each
/// axis is divided by the raw lightmap (per channel), filtered, and multiplied by the
/// delivered lightmap; the own filter takes the moments as they are. Blended like the
/// lightmap.
#[allow(clippy::too_many_arguments)]
fn denoise_moments(
    atlas: &Atlas,
    chart: &[u32],
    used: Used,
    m: &[[Vec3; 3]],
    raw_total: &[Vec3],
    total: &[Vec3],
    se: &[f32],
    weight: &[f32],
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
            mix(&raw, &filtered, weight)
        })
        .collect();
    (0..m.len()).map(|t| [axes[0][t], axes[1][t], axes[2][t]]).collect()
}
