//! Edge-aware denoising of a lightmap estimate, guided by the texel set and by the
//! noise the bake itself measured.
//!
//! How: an edge-avoiding à-trous wavelet filter (Dammertz et al., HPG 2010) run in
//! lightmap space, five passes with taps 1, 2, 4, 8 and 16 texels apart, extended with
//! the variance guidance of SVGF (Schied et al., HPG 2017). A tap contributes only when
//! - it belongs to the same chart ([`charts`]: never across charts, whatever their UV
//!   distance);
//! - its normal agrees (n·n')^32;
//! - it lies where the chart says it should: within 1.5 × the expected world distance
//!   for its texel offset and near the texel's tangent plane (no smoothing across folds
//!   or depth discontinuities inside one chart);
//! - its luminance differs by little compared with the noise: exp(−|Δℓ| / (4 σ)), where
//!   σ is the texel's standard error from the two half-accumulators, propagated through
//!   the passes. Strength is therefore tied to the error estimate: a converged texel
//!   (σ → 0) is left as it is, a noisy one is averaged over up to 65 × 65 texels.
//!
//! Limits: the filter trades noise for bias at contact shadows and thin features narrower
//! than the noise can resolve; `docs/accuracy.md` measures both against the reference.
//! This is the fallback denoiser: `engine::post::denoised` uses OpenImageDenoise where it
//! is installed, and blends either filter's output with the raw estimate by error.

use glam::Vec3;
use rayon::prelude::*;

use crate::engine::accumulate::LUMINANCE;
use crate::engine::atlas::{Atlas, NO_TEXEL};

const KERNEL: [f32; 5] = [1.0 / 16.0, 1.0 / 4.0, 3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0];
const PASSES: u32 = 5;
/// Luminance edge-stopping in units of the texel's standard error.
const SIGMA_LUMINANCE: f32 = 4.0;
const NORMAL_POWER: i32 = 32;

/// Denoises per-texel `values` (indexed like `atlas.texels`) whose luminance standard
/// errors are `std_error`; returns the filtered values.
pub fn denoise(atlas: &Atlas, values: &[Vec3], std_error: &[f32]) -> Vec<Vec3> {
    denoise_own(atlas, &charts(atlas), values, std_error)
}

/// [`denoise`] with the chart labels of [`charts`] computed once by the caller.
pub fn denoise_own(atlas: &Atlas, chart: &[u32], values: &[Vec3], std_error: &[f32]) -> Vec<Vec3> {
    let (w, h) = (atlas.width as i64, atlas.height as i64);
    let guides = &atlas.texels;
    let mut current = values.to_vec();
    let variance: Vec<f32> = std_error.iter().map(|e| e * e).collect();
    let mut variance = smooth(atlas, chart, &variance, 3);
    for pass in 0..PASSES {
        let step = 1i64 << pass;
        let filtered: Vec<(Vec3, f32)> = atlas
            .texels
            .par_iter()
            .enumerate()
            .map(|(k, t)| {
                let g = &guides[k];
                let sigma = SIGMA_LUMINANCE * variance[k].sqrt();
                let (pi, pj) = ((t.pixel as i64) % w, (t.pixel as i64) / w);
                let lum = current[k].dot(LUMINANCE);
                let (mut sum, mut wsum, mut vsum) = (Vec3::ZERO, 0.0f32, 0.0f32);
                for (dj, kj) in KERNEL.iter().enumerate() {
                    for (di, ki) in KERNEL.iter().enumerate() {
                        let (oi, oj) = (di as i64 - 2, dj as i64 - 2);
                        let (qi, qj) = (pi + oi * step, pj + oj * step);
                        if qi < 0 || qj < 0 || qi >= w || qj >= h {
                            continue;
                        }
                        let q = atlas.pixel_texel[(qj * w + qi) as usize];
                        if q == NO_TEXEL {
                            continue;
                        }
                        let q = q as usize;
                        let gq = &guides[q];
                        let mut wt = ki * kj;
                        if q != k {
                            if chart[q] != chart[k] {
                                continue;
                            }
                            wt *= g.normal.dot(gq.normal).max(0.0).powi(NORMAL_POWER);
                            let d = gq.position - g.position;
                            let expected = ((oi * oi + oj * oj) as f32).sqrt() * step as f32 * g.size.max(gq.size);
                            let beyond = (d.length() - 1.5 * expected).max(0.0) / expected.max(f32::MIN_POSITIVE);
                            let plane = d.dot(g.normal).abs() / expected.max(f32::MIN_POSITIVE);
                            wt *= (-(beyond * beyond) - 4.0 * plane * plane).exp();
                            let dl = (current[q].dot(LUMINANCE) - lum).abs();
                            wt *= if sigma > 0.0 {
                                (-dl / sigma).exp()
                            } else if dl == 0.0 {
                                1.0
                            } else {
                                0.0
                            };
                        }
                        if wt > 0.0 {
                            sum += current[q] * wt;
                            wsum += wt;
                            vsum += wt * wt * variance[q];
                        }
                    }
                }
                (sum / wsum, vsum / (wsum * wsum))
            })
            .collect();
        for (k, (v, var)) in filtered.into_iter().enumerate() {
            current[k] = v;
            variance[k] = var;
        }
    }
    current
}

/// Each texel's own error comes from one difference of two halves: a very noisy
/// estimate of its variance (a texel whose halves happen to agree would not be filtered
/// at all). As SVGF does, average such per-texel figures over the texel's
/// (2r+1) × (2r+1) neighbourhood in the same chart with agreeing normals before use.
pub fn smooth(atlas: &Atlas, chart: &[u32], values: &[f32], radius: i64) -> Vec<f32> {
    (0..atlas.texels.len())
        .into_par_iter()
        .map(|k| {
            let (mut sum, mut n) = (0.0f32, 0u32);
            for_neighbours(atlas, chart, k, radius, |q| {
                sum += values[q];
                n += 1;
            });
            sum / n.max(1) as f32
        })
        .collect()
}

/// Calls `visit` with every texel in texel `k`'s neighbourhood: within `radius` texels
/// in the image, on its chart, its normal within 25° of `k`'s (`k` itself included).
fn for_neighbours(atlas: &Atlas, chart: &[u32], k: usize, radius: i64, mut visit: impl FnMut(usize)) {
    let (w, h) = (atlas.width as i64, atlas.height as i64);
    let t = &atlas.texels[k];
    let (pi, pj) = ((t.pixel as i64) % w, (t.pixel as i64) / w);
    for qj in (pj - radius).max(0)..=(pj + radius).min(h - 1) {
        for qi in (pi - radius).max(0)..=(pi + radius).min(w - 1) {
            let q = atlas.pixel_texel[(qj * w + qi) as usize];
            if q == NO_TEXEL {
                continue;
            }
            let tq = &atlas.texels[q as usize];
            if chart[q as usize] == chart[k] && tq.normal.dot(t.normal) > 0.9 {
                visit(q as usize);
            }
        }
    }
}

/// Per texel, the mean and the standard error of the mean of `values` over the same
/// neighbourhood as [`smooth`] (same chart, normals within 25°, `radius` texels): the
/// sample standard deviation of the neighbours over the square root of their count.
/// How far a smoothed figure can be trusted (`denoised::combine_weights`). A value that
/// is not finite stands for "none here" (a fit with too few texels) and is left out;
/// with none at all the mean is NaN.
pub fn smooth_with_error(atlas: &Atlas, chart: &[u32], values: &[f32], radius: i64) -> Vec<(f32, f32)> {
    (0..atlas.texels.len())
        .into_par_iter()
        .map(|k| {
            let (mut sum, mut sq, mut n) = (0.0f64, 0.0f64, 0u32);
            for_neighbours(atlas, chart, k, radius, |q| {
                let v = values[q] as f64;
                if v.is_finite() {
                    sum += v;
                    sq += v * v;
                    n += 1;
                }
            });
            if n == 0 {
                return (f32::NAN, f32::NAN);
            }
            let n = n as f64;
            let mean = sum / n;
            // Bessel's correction; a lone texel has no spread to measure: its own value
            // stands as its error.
            let var = if n > 1.0 {
                ((sq - n * mean * mean) / (n - 1.0)).max(0.0)
            } else {
                mean * mean
            };
            (mean as f32, (var / n).sqrt() as f32)
        })
        .collect()
}

/// A chart label per valid texel: the 4-connected islands of valid texels of one mesh in
/// the lightmap image. The atlas keeps no chart index, and islands are what matters to a
/// filter: two islands never exchange light, whatever their UV distance. (Two charts of
/// one mesh that touch in UV form one island; the world-distance test of the filter
/// still keeps them apart.)
pub fn charts(atlas: &Atlas) -> Vec<u32> {
    let w = atlas.width as usize;
    let h = atlas.height as usize;
    let mut label = vec![u32::MAX; atlas.texels.len()];
    let mut next = 0u32;
    let mut stack = Vec::new();
    for start in 0..atlas.texels.len() {
        if label[start] != u32::MAX {
            continue;
        }
        label[start] = next;
        stack.push(start);
        while let Some(k) = stack.pop() {
            let t = &atlas.texels[k];
            let (i, j) = (t.pixel as usize % w, t.pixel as usize / w);
            let mut visit = |ni: usize, nj: usize| {
                let q = atlas.pixel_texel[nj * w + ni];
                if q != NO_TEXEL && label[q as usize] == u32::MAX && atlas.texels[q as usize].mesh == t.mesh {
                    label[q as usize] = next;
                    stack.push(q as usize);
                }
            };
            if i > 0 {
                visit(i - 1, j);
            }
            if i + 1 < w {
                visit(i + 1, j);
            }
            if j > 0 {
                visit(i, j - 1);
            }
            if j + 1 < h {
                visit(i, j + 1);
            }
        }
        next += 1;
    }
    label
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;
    use crate::engine::scene::build::{MaterialDesc, SceneBuilder};
    use crate::engine::scene::import_slice;

    fn two_quads() -> (crate::engine::scene::Scene, Atlas) {
        let mut b = SceneBuilder::new();
        let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
        b.square("a", Vec3::ZERO, 1.0, Vec3::Y, m);
        b.square("b", Vec3::new(3.0, 0.0, 0.0), 1.0, Vec3::Y, m);
        b.margin = Some(0.0);
        let scene = import_slice(&b.to_glb(), None).unwrap().0;
        let atlas = Atlas::build(&scene, 32, 32).unwrap();
        (scene, atlas)
    }

    #[test]
    fn noise_is_reduced_and_charts_never_mix() {
        let (_, atlas) = two_quads();
        // Chart a holds 1, chart b holds 10, both with noise of standard deviation 0.2
        // (and the filter is told so). The charts touch in UV space.
        let sigma = 0.2f32;
        let truth: Vec<f32> = atlas
            .texels
            .iter()
            .map(|t| if t.mesh == 0 { 1.0 } else { 10.0 })
            .collect();
        let mut rng = Rng::new(5, 0, 0, 0);
        let noisy: Vec<Vec3> = truth
            .iter()
            .map(|v| {
                let n = (rng.next_f32() - 0.5) * sigma * 12f32.sqrt();
                Vec3::splat(v + n)
            })
            .collect();
        let se = vec![sigma; noisy.len()];
        let out = denoise(&atlas, &noisy, &se);
        let rms = |v: &[Vec3]| {
            (v.iter().zip(&truth).map(|(a, t)| (a.x - t).powi(2) as f64).sum::<f64>() / truth.len() as f64).sqrt()
        };
        let (before, after) = (rms(&noisy), rms(&out));
        assert!(after < 0.25 * before, "RMS error {before} -> {after}");
        // Not one texel of chart a took anything from chart b's 10.
        for (k, v) in out.iter().enumerate() {
            assert!((v.x - truth[k]).abs() < 0.5, "texel {k}: {} vs {}", v.x, truth[k]);
        }
    }

    #[test]
    fn converged_values_are_left_alone() {
        let (_, atlas) = two_quads();
        let values: Vec<Vec3> = atlas
            .texels
            .iter()
            .map(|t| Vec3::splat(t.position.x.sin() + 2.0))
            .collect();
        let out = denoise(&atlas, &values, &vec![0.0; values.len()]);
        // Only taps of exactly equal value may mix (they change nothing): equal up to rounding.
        let worst = out
            .iter()
            .zip(&values)
            .map(|(a, b)| (*a - *b).abs().max_element())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-6, "largest change {worst}");
    }
}
