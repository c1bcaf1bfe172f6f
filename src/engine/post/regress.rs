//! Local polynomial regressions of a lightmap: the candidate filters that the denoiser
//! combines with the raw estimate and the image denoiser's output (`denoised`).
//!
//! What: for every texel, the value at its centre of a least-squares polynomial fitted
//! to the texels around it: planes over squares of radius 1, 2, 4 and 8 texels, and
//! quadrics over radius 2, 4 and 8 ([`CANDIDATES`] fits). A neighbour counts when it lies
//! on the texel's chart (`denoise::charts`) with its normal within 25° of the texel's,
//! as for the denoiser's other neighbourhoods, so no fit reaches across a chart, a
//! crease or another page.
//!
//! Why these: a lightmap is smooth across most of a chart, with steep but regular
//! gradients near lights and corners and sharp edges only at shadows and contacts. A
//! fit of low order follows a gradient that a plain average would flatten (on the
//! Cornell box at 64² the lighting changes by 6.7 % between neighbouring texels on
//! average, so averaging even 3 × 3 texels costs 4 % of bias), and a family from
//! small to large windows holds a good fit for every texel: small and quadratic where
//! the light changes, wide and planar where it is flat. Which fit a texel should take is
//! not decided here: each fit's error is estimated by cross-validation between the
//! bake's two halves, and `denoised` weights the fits, the raw value and the image
//! denoiser by those estimates, texel by texel. This is local polynomial regression
//! with a data-driven choice of bandwidth in the manner of the regression denoisers of
//! Moon et al. (weighted local regression, ACM TOG 2014) and of Rousselle et al.'s
//! dual-buffer selection (2012), in lightmap space with box weights; the weighting
//! itself is `denoised`'s.
//!
//! How: one pass per texel over its 17 × 17 window. Each neighbour's offset (di, dj)
//! gives the monomials x = (1, di, dj, di², di·dj, dj²); its moments x xᵀ and its values
//! times x are added into the bucket of the smallest radius that holds it (1, 2, 4 or
//! 8 by Chebyshev distance), and the buckets are summed outward, so every radius's sums
//! cost one visit per neighbour. For each fit, a = (A + ridge)⁻¹ e₀ gives the texel's
//! weights l_q = a · x_q (box weights: every neighbour counts once), so the fitted value
//! is a · Σ x_q v_q. The same a is used for the two halves, and a₀ = Σ l_q² (exactly, for
//! A a = e₀) is the fit's noise gain: a filtered half's variance is a₀ times the
//! half's. A small ridge on the slopes and curvatures keeps a fit defined on a strip one
//! texel wide (the slope across it is then zero); a fit with fewer than twice as many
//! neighbours as it has terms is not offered. The 6 × 6 systems are solved by
//! Cholesky in f64 here, written out because no dependency of the project solves small
//! fixed-size systems without a heap allocation per texel.
//!
//! Limits: box weights and square windows (a window is clipped by its chart, so near a
//! chart's edge the fit extrapolates one-sidedly, which the cross-validated error
//! measures); the neighbour test is the centre texel's, so a window may hold texels
//! whose own neighbourhoods differ; 289 neighbour visits a texel (about 2.5 × 10⁴
//! floating-point operations: ~1 s for a million texels on two cores), plus one more
//! pass for each extra layer (`direct`, directional moments).

use glam::Vec3;
use rayon::prelude::*;

use crate::engine::accumulate::LUMINANCE;
use crate::engine::atlas::{Atlas, NO_TEXEL};

/// The window radii, in texels, smallest first (the buckets of the moments).
const RADII: [i64; 4] = [1, 2, 4, 8];
/// The fits: (radius index into [`RADII`], number of monomials: 3 planar, 6 quadric).
const FITS: [(usize, usize); CANDIDATES] = [(0, 3), (1, 3), (2, 3), (3, 3), (1, 6), (2, 6), (3, 6)];
/// How many fits each texel has.
pub const CANDIDATES: usize = 7;
/// Ridge on each monomial's diagonal (the constant, slopes, curvatures; in texel units):
/// small against the moments of any window of two or more texels along an axis.
const RIDGE: [f64; 6] = [1e-9, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2];

/// The fits of one layer and, for the lightmap itself, of its halves.
pub struct Fits {
    /// Per texel, each fit's value of the layer (NaN where the fit is not offered: too
    /// few neighbours; `Vec3` rather than `Option`, a quarter less memory a texel).
    pub values: Vec<[Vec3; CANDIDATES]>,
    /// Per texel and fit, the fitted luminance of each half.
    pub halves: Option<[Vec<[f32; CANDIDATES]>; 2]>,
    /// Per texel and fit, the noise gain a₀ = Σ l_q²: a fitted value's variance over
    /// that of the values fitted (for neighbours of equal variance).
    pub gain: Vec<[f32; CANDIDATES]>,
}

/// Index of the first monomial of the upper triangle's row `r` in a packed 6 × 6.
const fn packed(r: usize, c: usize) -> usize {
    // Row-major upper triangle: rows 0..r hold 6 + 5 + … entries.
    r * 6 - r * (r.saturating_sub(1)) / 2 + (c - r)
}

/// Moments of one bucket: Σ x xᵀ (packed upper triangle), Σ x v for the layer's three
/// channels and the two halves' luminance, and the count.
#[derive(Clone, Copy)]
struct Moments {
    a: [f64; 21],
    v: [[f64; 6]; 3],
    h: [[f64; 6]; 2],
    n: u32,
}

impl Moments {
    const ZERO: Moments = Moments {
        a: [0.0; 21],
        v: [[0.0; 6]; 3],
        h: [[0.0; 6]; 2],
        n: 0,
    };

    fn add(&mut self, o: &Moments) {
        for (a, b) in self.a.iter_mut().zip(&o.a) {
            *a += b;
        }
        for (a, b) in self.v.iter_mut().flatten().zip(o.v.iter().flatten()) {
            *a += b;
        }
        for (a, b) in self.h.iter_mut().flatten().zip(o.h.iter().flatten()) {
            *a += b;
        }
        self.n += o.n;
    }
}

/// Solves (A + ridge) a = e₀ for the leading `m` monomials by Cholesky; `None` when the
/// system is not positive definite (it is, with the ridge, unless the moments are empty).
fn hat(a: &[f64; 21], m: usize) -> Option<[f64; 6]> {
    let mut l = [[0.0f64; 6]; 6];
    for i in 0..m {
        for j in 0..=i {
            let mut s = a[packed(j, i)] + if i == j { RIDGE[i] } else { 0.0 };
            for (lik, ljk) in l[i][..j].iter().zip(&l[j][..j]) {
                s -= lik * ljk;
            }
            if i == j {
                if s <= 0.0 {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    // L y = e₀, then Lᵀ a = y.
    let mut y = [0.0f64; 6];
    for i in 0..m {
        let mut s = if i == 0 { 1.0 } else { 0.0 };
        for k in 0..i {
            s -= l[i][k] * y[k];
        }
        y[i] = s / l[i][i];
    }
    let mut x = [0.0f64; 6];
    for i in (0..m).rev() {
        let mut s = y[i];
        for k in i + 1..m {
            s -= l[k][i] * x[k];
        }
        x[i] = s / l[i][i];
    }
    Some(x)
}

/// One texel's fits: each candidate's value, its halves' luminance and its weight.
type TexelFits = ([Vec3; CANDIDATES], [[f32; CANDIDATES]; 2], [f32; CANDIDATES]);

/// The fits of `values` at every texel (indexed like `atlas.texels`), with the halves'
/// luminance fitted alongside when `halves` is given. `chart` is `denoise::charts`.
pub fn fit(atlas: &Atlas, chart: &[u32], values: &[Vec3], halves: Option<[&[Vec3]; 2]>) -> Fits {
    let (w, h) = (atlas.width as i64, atlas.height as i64);
    let reach = RADII[RADII.len() - 1];
    let per_texel: Vec<TexelFits> = atlas
        .texels
        .par_iter()
        .enumerate()
        .map(|(k, t)| {
            let (pi, pj) = ((t.pixel as i64) % w, (t.pixel as i64) / w);
            let mut bucket = [Moments::ZERO; 4];
            for qj in (pj - reach).max(0)..=(pj + reach).min(h - 1) {
                for qi in (pi - reach).max(0)..=(pi + reach).min(w - 1) {
                    let q = atlas.pixel_texel[(qj * w + qi) as usize];
                    if q == NO_TEXEL {
                        continue;
                    }
                    let q = q as usize;
                    if chart[q] != chart[k] || atlas.texels[q].normal.dot(t.normal) <= 0.9 {
                        continue;
                    }
                    let (di, dj) = ((qi - pi) as f64, (qj - pj) as f64);
                    let c = (qi - pi).abs().max((qj - pj).abs());
                    let b = &mut bucket[RADII.iter().position(|r| c <= *r).unwrap_or(3)];
                    let x = [1.0, di, dj, di * di, di * dj, dj * dj];
                    for r in 0..6 {
                        for s in r..6 {
                            b.a[packed(r, s)] += x[r] * x[s];
                        }
                    }
                    let v = values[q];
                    for (ch, val) in [v.x, v.y, v.z].into_iter().enumerate() {
                        for (bv, xr) in b.v[ch].iter_mut().zip(&x) {
                            *bv += xr * val as f64;
                        }
                    }
                    if let Some(hs) = halves {
                        for (hh, half) in hs.iter().enumerate() {
                            let l = half[q].dot(LUMINANCE) as f64;
                            for (bh, xr) in b.h[hh].iter_mut().zip(&x) {
                                *bh += xr * l;
                            }
                        }
                    }
                    b.n += 1;
                }
            }
            // Each radius holds every bucket within it.
            for i in 1..bucket.len() {
                let inner = bucket[i - 1];
                bucket[i].add(&inner);
            }
            let mut out = [Vec3::NAN; CANDIDATES];
            let mut out_h = [[0.0f32; CANDIDATES]; 2];
            let mut gain = [0.0f32; CANDIDATES];
            for (f, &(r, m)) in FITS.iter().enumerate() {
                let b = &bucket[r];
                if (b.n as usize) < 2 * m {
                    continue;
                }
                let Some(a) = hat(&b.a, m) else { continue };
                let dot = |s: &[f64; 6]| (0..m).map(|i| a[i] * s[i]).sum::<f64>();
                let v = Vec3::new(dot(&b.v[0]) as f32, dot(&b.v[1]) as f32, dot(&b.v[2]) as f32);
                if !v.is_finite() {
                    continue;
                }
                out[f] = v;
                out_h[0][f] = dot(&b.h[0]) as f32;
                out_h[1][f] = dot(&b.h[1]) as f32;
                gain[f] = a[0] as f32;
            }
            (out, out_h, gain)
        })
        .collect();
    let mut fits = Fits {
        values: Vec::with_capacity(per_texel.len()),
        halves: halves.map(|_| [Vec::with_capacity(per_texel.len()), Vec::with_capacity(per_texel.len())]),
        gain: Vec::with_capacity(per_texel.len()),
    };
    for (v, h, g) in per_texel {
        fits.values.push(v);
        if let Some(hs) = fits.halves.as_mut() {
            hs[0].push(h[0]);
            hs[1].push(h[1]);
        }
        fits.gain.push(g);
    }
    fits
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::scene::build::{MaterialDesc, SceneBuilder};
    use crate::engine::scene::import_slice;

    fn quad(res: u32) -> Atlas {
        let mut b = SceneBuilder::new();
        let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
        b.square("a", Vec3::ZERO, 1.0, Vec3::Y, m);
        b.margin = Some(0.0);
        let scene = import_slice(&b.to_glb(), None).unwrap().0;
        Atlas::build(&scene, res, res).unwrap()
    }

    fn pixel_xy(atlas: &Atlas, k: usize) -> (f32, f32) {
        let p = atlas.texels[k].pixel;
        ((p % atlas.width) as f32, (p / atlas.width) as f32)
    }

    #[test]
    fn packed_indices_cover_the_upper_triangle_once() {
        let mut seen = [false; 21];
        for r in 0..6 {
            for c in r..6 {
                assert!(!seen[packed(r, c)], "({r}, {c})");
                seen[packed(r, c)] = true;
            }
        }
        assert!(seen.iter().all(|s| *s));
    }

    /// A quadric in the texel grid is reproduced by every quadric fit and a plane by
    /// every fit, up to the ridge's pull (1e-3 of a slope over windows of 9+ texels).
    #[test]
    fn polynomials_of_the_fits_order_are_reproduced() {
        let atlas = quad(32);
        let chart = crate::engine::post::denoise::charts(&atlas);
        let plane: Vec<Vec3> = (0..atlas.texels.len())
            .map(|k| {
                let (x, y) = pixel_xy(&atlas, k);
                Vec3::new(1.0 + 0.1 * x, 2.0 - 0.05 * y, 0.5 + 0.02 * (x + y))
            })
            .collect();
        let quadric: Vec<Vec3> = (0..atlas.texels.len())
            .map(|k| {
                let (x, y) = pixel_xy(&atlas, k);
                Vec3::splat(1.0 + 0.01 * (x - 16.0).powi(2) + 0.005 * x * y)
            })
            .collect();
        let fp = fit(&atlas, &chart, &plane, Some([&plane, &plane]));
        let fq = fit(&atlas, &chart, &quadric, None);
        let mut offered = 0;
        for k in 0..atlas.texels.len() {
            for f in 0..CANDIDATES {
                let v = fp.values[k][f];
                if v.is_finite() {
                    offered += 1;
                    assert!(
                        (v - plane[k]).abs().max_element() < 2e-3,
                        "plane, texel {k}, fit {f}: {v} vs {}",
                        plane[k]
                    );
                    let l = plane[k].dot(LUMINANCE);
                    let h = fp.halves.as_ref().unwrap();
                    assert!((h[0][k][f] - l).abs() < 2e-3 && (h[1][k][f] - l).abs() < 2e-3);
                }
                let v = fq.values[k][f];
                if f >= 4 && v.is_finite() {
                    assert!(
                        (v.x - quadric[k].x).abs() < 2e-2,
                        "quadric, texel {k}, fit {f}: {} vs {}",
                        v.x,
                        quadric[k].x
                    );
                }
            }
        }
        assert!(offered > atlas.texels.len() * CANDIDATES / 2, "{offered} fits offered");
    }

    /// Each fit's noise gain is the variance it leaves of independent unit noise: a₀
    /// against the measured variance over many texels of a flat field with noise.
    #[test]
    fn the_noise_gain_is_the_fits_variance() {
        let atlas = quad(64);
        let chart = crate::engine::post::denoise::charts(&atlas);
        let mut rng = crate::engine::rng::Rng::new(9, 0, 0, 0);
        let noisy: Vec<Vec3> = (0..atlas.texels.len())
            .map(|_| Vec3::splat((rng.next_f32() - 0.5) * 12f32.sqrt()))
            .collect();
        let fits = fit(&atlas, &chart, &noisy, None);
        // Interior texels only (the whole 17 × 17 window on the chart): one gain each fit.
        let (w, h) = (atlas.width as f32, atlas.height as f32);
        let interior: Vec<usize> = (0..atlas.texels.len())
            .filter(|&k| {
                let (x, y) = pixel_xy(&atlas, k);
                x >= 10.0 && y >= 10.0 && x < w - 10.0 && y < h - 10.0
            })
            .collect();
        assert!(interior.len() > 1000);
        for f in 0..CANDIDATES {
            let var = interior
                .iter()
                .map(|&k| fits.values[k][f].x.powi(2) as f64)
                .sum::<f64>()
                / interior.len() as f64;
            let gain = fits.gain[interior[0]][f] as f64;
            // Window sizes 9, 25, 81, 289: a plane's centre weight is 1/n.
            if f < 4 {
                let n = (2 * RADII[FITS[f].0] + 1).pow(2) as f64;
                assert!((gain * n - 1.0).abs() < 1e-2, "fit {f}: gain {gain}, 1/n = {}", 1.0 / n);
            }
            // Neighbouring outputs share inputs, so the sample variance over the texels
            // is the gain itself to within its sampling error (a few %).
            assert!((var / gain - 1.0).abs() < 0.25, "fit {f}: variance {var}, gain {gain}");
        }
    }
}
