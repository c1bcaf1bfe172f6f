//! Control texels: the bias of a biased technique, measured while it bakes (issue 21
//! point 2), so the error a job reports and stops on covers its bias as well as its noise.
//!
//! What: a stratified random subset of the atlas's texels (systematic sampling over the
//! texels in atlas order with a random start, so every region of the page is represented
//! in proportion to its texels) is baked alongside by the unbiased reference, `path`
//! (through the technique table, on the GPU when there is a hardware adapter, else the
//! CPU), on a sub-atlas that holds only those texels. At every snapshot the technique's
//! values T_k at the control texels are compared with path's P_k:
//!
//! - d_k = (T_k - P_k)^2 - sP_k^2 estimates the technique's mean squared error at texel
//!   k, bias and noise together (E[(T - P)^2] = (T's bias)^2 + sT^2 + sP^2 for independent
//!   estimates; subtracting path's own variance sP^2, from its halves, leaves T's error);
//! - their mean over the M control texels estimates the technique's mean squared error
//!   over the page; its standard error s_d / sqrt(M) gives the stated confidence interval
//!   (90 %, normal approximation: mean +- 1.645 standard errors);
//! - the reported relative error is sqrt(max(mean d, c noise^2)) over the RMS luminance
//!   of the answer (estimated from path's values, less path's variance: relative to the
//!   answer, not to the technique's own values, which a biased technique gets wrong);
//!   noise^2 is the technique's own half-difference estimate over the whole page, and
//!   c = min(1, (max(mean d, 0) + 1.645 s_d / sqrt(M)) / mean sT_k^2) calibrates it at
//!   the control texels: the halves of a stratified step sequence (sdb's and
//!   obscurance's directions, vpl's lights, hemicube's shooters) each err more than
//!   their union, so |A - B| / 2 over-states the noise (vpl on the open sky plane:
//!   1.2 % against a true 0.01 %);
//!   where the control's 90 % upper bound of the whole error is below what the halves
//!   say the noise is at the same texels, the page's noise floor is scaled down by that
//!   ratio (a scale, so noise in texels the control does not see keeps its share); the
//!   bias part is sqrt(max(mean d - c mean sT_k^2, 0)) and the noise part the calibrated
//!   floor sqrt(c noise^2), both on the same scale, so neither part exceeds the whole.
//!   A denoised lightmap is measured at the same texels the same way
//!   ([`ControlValues::assess_delivered`], which lives beside the values so that the
//!   denoiser needs nothing of this module), with the denoiser's own noise bound,
//!   calibrated at the same texels by the same rule (`accumulate::noise_calibration`),
//!   as its floor: what the filters did to the bias is in the figure, and a bound that
//!   over-states (it sums the filters' errors by the triangle inequality) is scaled to
//!   what the control measures.
//!
//! Luminance (`accumulate::LUMINANCE`) throughout, as the noise estimate.
//!
//! Split bakes (`engine::tasks`): every chain of a job picks the same control texels (the
//! job's seed) and traces them with its own seed; the merge averages the chains'
//! references by steps and assesses the merged lightmap with [`assess_against`], the
//! comparison [`ControlTexels::assess`] makes during a bake.
//!
//! Budget: the control is stepped after a technique step while its time is below
//! [`CONTROL_SHARE`] of the technique's, so it costs at most about a fifth of the bake (and
//! one step at least, so a bake of one long step still has a control estimate).
//!
//! Limits: M texels resolve a bias that covers a fraction f of the page only when f M is
//! several texels (a bias confined to 1 % of the texels is seen by about 2.6 of 256);
//! path's noise at the control texels limits how small a bias can be told from zero (the
//! estimate is clamped at the calibrated noise figure, never reported as less; a true
//! error far below path's noise at the control, such as sdb's 1e-7 in the closed boxes,
//! reads as that noise's residue); the control's own
//! estimate carries path's limits (its `max_bounces`, the adapter's loop budget on
//! lavapipe, for which path runs on the CPU here).

use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::Vec3;
use serde::Serialize;

use crate::engine::accumulate::{
    ControlValues, Estimate, LUMINANCE, Snapshot, Z90, noise_calibration, squared_error_at,
};
use crate::engine::atlas::Atlas;
use crate::engine::error::EngineError;
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::plan::SceneFeatures;
use crate::engine::rng::Rng;
use crate::engine::scene::Lighting;
use crate::engine::technique::{self, BakeInputs, Technique};

/// Control texels per bake (fewer when the atlas has fewer texels).
pub const CONTROL_TEXELS: usize = 256;
/// The control's share of the technique's stepping time.
pub const CONTROL_SHARE: f64 = 0.25;

/// The bias measurement of one snapshot.
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct ControlReport {
    /// Control texels compared.
    pub texels: usize,
    /// path's steps at the control texels.
    pub reference_steps: u64,
    /// Relative RMS error over the control texels, noise and bias (before the noise floor).
    pub relative: f32,
    /// The bias part, relative.
    pub bias: f32,
    /// 90 % interval of the reported relative error.
    pub interval: [f32; 2],
}

/// The control texels of one bake and their `path` reference.
pub struct ControlTexels {
    indices: Vec<usize>,
    reference: Box<dyn Technique>,
    time: Duration,
}

impl ControlTexels {
    /// Picks up to [`CONTROL_TEXELS`] texels of `atlas` with `pick_seed` and prepares
    /// `path` on them with streams from `seed`. A single bake gives its seed for both; the
    /// chains of a split bake (`engine::tasks`) give the job's seed to pick with, so
    /// every chain's control sees the same texels, and their own seeds to trace with, so
    /// their references are independent and average in the merge.
    pub fn new(
        rays: &Arc<SceneRays>,
        atlas: &Atlas,
        lighting: Lighting,
        pick_seed: u64,
        seed: u64,
    ) -> Result<Self, EngineError> {
        let scene = rays.scene();
        let n = atlas.texels.len();
        let m = n.min(CONTROL_TEXELS);
        let mut rng = Rng::new(pick_seed, 0xC0_17_20_1E, 0x51, 0);
        let stride = n as f64 / m.max(1) as f64;
        let start = rng.next_f32() as f64 * stride;
        let indices: Vec<usize> = (0..m)
            .map(|i| ((start + i as f64 * stride) as usize).min(n - 1))
            .collect();
        let sub = Atlas {
            width: atlas.width,
            height: atlas.height,
            texels: indices.iter().map(|&k| atlas.texels[k]).collect(),
            pixel_texel: Default::default(),
            links: Vec::new(),
            overlapping_texels: 0,
            surface_offset: atlas.surface_offset,
            overlap_pixels: Vec::new(),
            inside_pixels: Vec::new(),
            validation: None,
            seams: Vec::new(),
            pages: atlas.pages.clone(),
        };
        let features = SceneFeatures::of(scene, &lighting, &[]);
        // The bake's rays: the reference traces the BVH the technique's passes use.
        let inputs = BakeInputs::sharing(
            rays.clone(),
            Arc::new(sub),
            lighting,
            seed ^ 0x5EED_C0A7_0000_0001,
            technique::plan("path", &features)?,
        );
        let reference = technique::create("path", inputs, &serde_json::json!({"samples_per_step": 4}))?;
        Ok(ControlTexels {
            indices,
            reference,
            time: Duration::ZERO,
        })
    }

    pub fn texels(&self) -> usize {
        self.indices.len()
    }

    /// The control texels, as indices into the bake's texels.
    pub fn indices(&self) -> &[usize] {
        &self.indices
    }

    /// The reference's halves at the control texels, in [`indices`](Self::indices)'
    /// order: what a task of a split bake hands the merge (`engine::tasks`).
    pub fn reference(&mut self) -> Result<Snapshot, EngineError> {
        self.reference.snapshot()
    }

    /// Steps the reference while its time is below [`CONTROL_SHARE`] of `technique_time`
    /// (at least once in all).
    pub fn keep_up(&mut self, technique_time: Duration) -> Result<(), EngineError> {
        while self.reference.steps_done() < 2 || self.time.as_secs_f64() < CONTROL_SHARE * technique_time.as_secs_f64()
        {
            let t0 = Instant::now();
            self.reference.step()?;
            self.time += t0.elapsed();
        }
        Ok(())
    }

    /// Compares `estimate` with the reference at the control texels, and folds the result
    /// into `estimate.error` (see the module doc). Does nothing before both halves of both
    /// have a step.
    pub fn assess(&mut self, estimate: &mut Estimate) -> Result<Option<ControlReport>, EngineError> {
        if estimate.texel_error.is_none() || estimate.error.relative.is_none() {
            return Ok(None);
        }
        let reference = self.reference.snapshot()?.estimate();
        Ok(assess_against(&self.indices, &reference, estimate))
    }
}

/// Compares `estimate` with `reference`, path's estimate at the control texels
/// `indices` (indices into `estimate`'s texels, in the reference's order), and folds the
/// result into `estimate.error` (see the module doc). Does nothing before both halves of
/// both have a step. [`ControlTexels::assess`] during a bake; the merge of a split bake's
/// chains with their references merged (`engine::tasks`).
pub fn assess_against(indices: &[usize], reference: &Estimate, estimate: &mut Estimate) -> Option<ControlReport> {
    let (Some(se_t), Some(noise)) = (estimate.texel_error.as_ref(), estimate.error.relative) else {
        return None;
    };
    let se_p = reference.texel_error.as_ref()?;
    let rms_t = estimate.error.rms_luminance as f64;
    let lum = |v: Vec3| v.dot(LUMINANCE) as f64;
    let m = indices.len() as f64;
    // The error relative to the answer, not to the technique's own values (a
    // technique that reads 3x too bright would otherwise divide its error by 3):
    // the RMS of the answer estimated from path's values, less path's variance.
    let ms_ref = reference
        .total
        .iter()
        .zip(se_p)
        .map(|(p, s)| lum(*p).powi(2) - (*s as f64).powi(2))
        .sum::<f64>()
        / m;
    let rms = ms_ref.max(0.0).sqrt();
    if rms <= 0.0 || rms_t <= 0.0 || indices.is_empty() {
        return None;
    }
    let p_lum: Vec<f64> = reference.total.iter().map(|p| lum(*p)).collect();
    let p_var: Vec<f64> = se_p.iter().map(|s| (*s as f64).powi(2)).collect();
    let (mean, se) = squared_error_at(indices, &estimate.total, &p_lum, &p_var);
    let noise_at_control: f64 = indices.iter().map(|&k| (se_t[k] as f64).powi(2)).sum();
    // The noise floor, calibrated at the control texels: where the control's 90 %
    // upper bound of the whole error (noise included) is below what the halves say
    // the noise alone is there, the halves over-state it (a stratified sequence whose
    // union errs less than either half), and the page's noise figure is scaled down
    // by the same factor. The scale, not a replacement: noise the control texels do
    // not see keeps its share of the floor.
    let noise_control_ms = noise_at_control / m;
    let calibration = noise_calibration(mean, se, noise_control_ms);
    let noise_ms = (noise as f64 * rms_t).powi(2) * calibration;
    let rel = |ms: f64| (ms.max(noise_ms).sqrt() / rms) as f32;
    let report = ControlReport {
        texels: indices.len(),
        reference_steps: reference.steps,
        relative: (mean.max(0.0).sqrt() / rms) as f32,
        bias: ((mean - noise_control_ms * calibration).max(0.0).sqrt() / rms) as f32,
        interval: [rel(mean - Z90 * se), rel(mean + Z90 * se)],
    };
    // The noise part as the floor stands: calibrated, on the answer's scale (as the
    // total and the bias), so the parts never exceed the whole.
    estimate.error.noise = Some((noise_ms.sqrt() / rms) as f32);
    estimate.error.relative = Some(rel(mean));
    estimate.error.bias = Some(report.bias);
    estimate.error.interval = Some(report.interval);
    estimate.error.control_texels = Some(report.texels as u32);
    estimate.error.noise_scale = Some(calibration as f32);
    estimate.control = Some(std::sync::Arc::new(ControlValues {
        texels: indices.to_vec(),
        luminance: p_lum.iter().map(|p| *p as f32).collect(),
        variance: p_var.iter().map(|v| *v as f32).collect(),
        rms: rms as f32,
    }));
    tracing::debug!(
        control_texels = report.texels,
        reference_steps = report.reference_steps,
        halves_noise = noise,
        calibration,
        bias = report.bias,
        relative = ?estimate.error.relative,
        "control texels"
    );
    Some(report)
}

#[cfg(test)]
mod tests {
    use crate::engine::accumulate::{Z90, noise_calibration};

    #[test]
    fn honest_halves_keep_the_whole_noise_floor() {
        // The whole error is the noise the halves state, or more (a bias on top).
        assert_eq!(noise_calibration(4.0e-4, 1.0e-5, 4.0e-4), 1.0);
        assert_eq!(noise_calibration(9.0e-4, 0.0, 4.0e-4), 1.0);
        // Within the interval's reach of the stated noise: still the whole floor.
        let c = noise_calibration(3.0e-4, 1.0e-4 / Z90, 4.0e-4);
        assert!((c - 1.0).abs() < 1e-12, "{c}");
    }

    #[test]
    fn over_stated_noise_is_scaled_to_the_controls_upper_bound() {
        // Halves that say 4e-4 where the control bounds the whole error by 1e-4.
        let c = noise_calibration(0.5e-4, 0.5e-4 / Z90, 4.0e-4);
        assert!((c - 0.25).abs() < 1e-12, "{c}");
        // An exact technique against an exact control: no floor left.
        assert_eq!(noise_calibration(0.0, 0.0, 4.0e-4), 0.0);
        // Path's variance subtracted past zero reads as zero, never negative...
        assert_eq!(noise_calibration(-1.0e-4, 0.0, 4.0e-4), 0.0);
        // ...and the control's resolution stays: 1.645 se over the stated noise.
        let c = noise_calibration(-1.0e-4, 1.0e-5, 4.0e-4);
        assert!((c - Z90 * 1.0e-5 / 4.0e-4).abs() < 1e-12, "{c}");
    }

    #[test]
    fn no_stated_noise_leaves_nothing_to_scale() {
        assert_eq!(noise_calibration(1.0e-4, 1.0e-5, 0.0), 1.0);
    }
}
