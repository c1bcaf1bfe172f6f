//! A bake's true error against a reference lightmap: the measured side of the error plot
//! (issue 23 point 3: "the true error too when the job has a reference").
//!
//! A reference is a lightmap of the same texel grid read back from its EXR pages (the
//! files a finished bake delivers, `output::pages`), stacked into the grid the way the
//! bake holds them (pages one under another, DESIGN §2). [`ReferenceLightmap::per_texel`]
//! picks, for every valid texel of the bake's atlas, the reference's value at the same
//! pixel; [`relative_error`] is the metric of `docs/accuracy.md` (RMS over texels of the
//! luminance difference over the RMS reference luminance), the same one `lightmapd
//! bench` measures with, so a job's curve and the bench's figures are comparable.
//!
//! Why it is a measurement, not the truth: the reference has its own error (its EXR's
//! `lightmapd:relative_error`, kept as [`ReferenceLightmap::reported_error`]). Two
//! independent estimates with relative errors a and b differ by about √(a² + b²), so the
//! measured curve flattens at the reference's error; the console draws that floor beside
//! it. Nothing is subtracted here: for a biased reference the two errors are not
//! independent and a subtraction would be a guess.
//!
//! Limits: the grid must match exactly (width and stacked height); texel validity is the
//! bake's own (a reference of the same scene and layout has the same valid texels, since
//! unwrapping and validation are deterministic). Gutter pixels of the reference are never
//! read: they hold dilated values, not estimates.

use glam::Vec3;

use crate::engine::accumulate::LUMINANCE;
use crate::engine::atlas::{Atlas, NO_TEXEL};
use crate::engine::output;

/// A reference lightmap on a texel grid, with the error its bake reported.
#[derive(Clone, Debug)]
pub struct ReferenceLightmap {
    pub width: u32,
    pub height: u32,
    /// Irradiance / π per pixel, rows top first (the EXR's and the atlas's order).
    pub rgb: Vec<Vec3>,
    /// Page 0's `lightmapd:relative_error`: how far the reference itself is from the truth.
    pub reported_error: Option<f32>,
}

impl ReferenceLightmap {
    /// Reads a lightmap's pages (`lightmap-P.exr` in page order, or one single-page EXR)
    /// and stacks them into one grid. Pages must share their width.
    pub fn from_pages<B: AsRef<[u8]>>(pages: &[B]) -> Result<ReferenceLightmap, String> {
        let mut out = ReferenceLightmap {
            width: 0,
            height: 0,
            rgb: Vec::new(),
            reported_error: None,
        };
        for (p, bytes) in pages.iter().enumerate() {
            let page = output::decode_lightmap(bytes.as_ref()).map_err(|e| format!("page {p}: {e}"))?;
            if p == 0 {
                out.width = page.width;
                out.reported_error = page.relative_error;
            } else if page.width != out.width {
                return Err(format!(
                    "page {p} is {} texels wide, page 0 is {}: not one lightmap",
                    page.width, out.width
                ));
            }
            out.height += page.height;
            out.rgb.extend(page.rgb);
        }
        if pages.is_empty() {
            return Err("a reference needs at least one page".into());
        }
        Ok(out)
    }

    /// The reference's value at every valid texel of `atlas`, in texel order; an error
    /// naming both grids when they differ.
    pub fn per_texel(&self, atlas: &Atlas) -> Result<Vec<Option<Vec3>>, String> {
        if (self.width, self.height) != (atlas.width, atlas.height) {
            return Err(format!(
                "the reference's texel grid is {}x{}, this bake's is {}x{}: not the same scene, resolution or UV layout",
                self.width, self.height, atlas.width, atlas.height
            ));
        }
        let mut out = vec![None; atlas.texels.len()];
        for (pixel, t) in atlas.pixel_texel.iter() {
            if t != NO_TEXEL {
                let v = self.rgb[pixel];
                // A non-finite reference texel is left out rather than poisoning the sum.
                out[t as usize] = v.is_finite().then_some(v);
            }
        }
        Ok(out)
    }
}

/// True relative error of `estimate` against `reference` (`docs/accuracy.md`): RMS of
/// the luminance difference over texels that have a reference value, over the RMS
/// reference luminance (the absolute RMS difference where the reference is black).
pub fn relative_error(estimate: &[Vec3], reference: &[Option<Vec3>]) -> f64 {
    let (mut diff, mut norm) = (0.0f64, 0.0f64);
    for (e, r) in estimate.iter().zip(reference) {
        if let Some(r) = r {
            diff += ((*e - *r).dot(LUMINANCE) as f64).powi(2);
            norm += (r.dot(LUMINANCE) as f64).powi(2);
        }
    }
    if norm > 0.0 { (diff / norm).sqrt() } else { diff.sqrt() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_metric_is_rms_luminance_over_rms_reference() {
        let one = Vec3::ONE;
        // Two texels, one 10 % high and one exact: sqrt(0.01 / 2) over 1.
        let e = relative_error(&[one * 1.1, one], &[Some(one), Some(one)]);
        assert!((e - (0.01f64 / 2.0).sqrt()).abs() < 1e-6, "{e}");
        // Texels without a reference value are left out.
        let e = relative_error(&[one * 1.1, one * 5.0], &[Some(one), None]);
        assert!((e - 0.1).abs() < 1e-6, "{e}");
        // A black reference: the absolute difference.
        let e = relative_error(&[Vec3::ZERO, Vec3::splat(0.5)], &[Some(Vec3::ZERO), Some(Vec3::ZERO)]);
        assert!((e - 0.5).abs() < 1e-6, "{e}");
    }

    #[test]
    fn pages_stack_and_a_different_width_is_refused() {
        let page = |w: u32, h: u32, v: f32, err: Option<f32>| {
            let meta = output::ExrMetadata {
                technique: "path".into(),
                params: serde_json::json!({}),
                steps: 1,
                seconds: 1.0,
                relative_error: err,
                seed: 0,
                denoised: "no".into(),
                raw_relative_error: None,
                shadowmask: Vec::new(),
                page: None,
            };
            let n = (w * h) as usize;
            let chans = ["R", "G", "B"].iter().map(|c| (c.to_string(), vec![v; n])).collect();
            output::encode_exr(w, h, chans, &meta).unwrap()
        };
        let r = ReferenceLightmap::from_pages(&[page(4, 4, 1.0, Some(0.02)), page(4, 4, 2.0, None)]).unwrap();
        assert_eq!((r.width, r.height, r.rgb.len()), (4, 8, 32));
        assert_eq!(r.reported_error, Some(0.02));
        assert_eq!((r.rgb[15], r.rgb[16]), (Vec3::ONE, Vec3::splat(2.0)));
        let e = ReferenceLightmap::from_pages(&[page(4, 4, 1.0, None), page(8, 4, 1.0, None)]).unwrap_err();
        assert!(e.contains("page 1 is 8 texels wide, page 0 is 4"), "{e}");
    }
}
