//! Seam stitching: where one surface edge appears twice in the lightmap (two charts
//! meeting at a cube's edge, or a sphere's wrap-around column), a renderer filtering
//! bilinearly on each side reads different values and shows a visible line. This makes
//! the two sides agree.
//!
//! How (the least-squares formulation of the seam optimisers bakers use): seam edges
//! are found at texel-set time (`atlas::seams`, part of the texel set), as triangle edges whose two world-space endpoints are
//! shared by another triangle's edge with different lightmap UVs. Along each seam,
//! sample pairs are taken two per texel of edge length; each pair asks that the bilinear
//! lookups at its two UVs be equal. Every texel those lookups touch becomes an unknown,
//! tied to its baked value by a data term (weight 1 for valid texels, 0.1 for gutter
//! texels, which no surface point samples directly), and the seam terms (weight
//! `SEAM_WEIGHT`) pull the two sides together. The normal equations are solved per
//! colour channel by conjugate gradients, matrix-free.
//!
//! Only smooth seams are stitched: where the shading normals on the two sides differ
//! (a box's 90° edges), the irradiance is discontinuous in reality and is left so.
//!
//! Limits: seam vertices are matched on a grid of 1e-6 of the scene's size, so two
//! positions a rounding error apart that straddle a grid line are not matched;
//! stitching changes texels only near
//! seams, so a seam between truly different lighting (a concave corner) is softened,
//! not removed — which is what the data term is for.

use std::collections::HashMap;

use glam::{Vec2, Vec3};

pub use crate::engine::atlas::seams::{SeamSample, find_seams};
use crate::engine::atlas::{NO_TEXEL, PixelTexels};

/// Weight of a seam term against a valid texel's data term.
pub const SEAM_WEIGHT: f32 = 4.0;
const GUTTER_DATA_WEIGHT: f32 = 0.1;
const ITERATIONS: usize = 64;

/// The four texels and weights of a bilinear lookup at `uv` (texel centres at half
/// integers, as in DESIGN §2), clamped to the image.
fn bilinear(uv: Vec2, w: u32, h: u32) -> [(usize, f32); 4] {
    let x = (uv.x * w as f32 - 0.5).clamp(0.0, w as f32 - 1.0);
    let y = (uv.y * h as f32 - 0.5).clamp(0.0, h as f32 - 1.0);
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let idx = |x: u32, y: u32| (y * w + x) as usize;
    [
        (idx(x0, y0), (1.0 - fx) * (1.0 - fy)),
        (idx(x1, y0), fx * (1.0 - fy)),
        (idx(x0, y1), (1.0 - fx) * fy),
        (idx(x1, y1), fx * fy),
    ]
}

/// RMS over seam samples of the bilinear difference across the seam (luminance-free:
/// per channel), for measuring a lightmap image.
pub fn seam_discontinuity(image: &[Vec3], w: u32, h: u32, seams: &[SeamSample]) -> f32 {
    if seams.is_empty() {
        return 0.0;
    }
    let look = |uv: Vec2| {
        bilinear(uv, w, h)
            .iter()
            .fold(Vec3::ZERO, |s, (i, wt)| s + image[*i] * *wt)
    };
    let sum: f32 = seams
        .iter()
        .map(|s| (look(s.a) - look(s.b)).length_squared() / 3.0)
        .sum();
    (sum / seams.len() as f32).sqrt()
}

/// Makes the two sides of every seam agree in `image` (a full, dilated W × H image);
/// `pixel_texel` tells valid texels from gutter ones.
pub fn stitch(image: &mut [Vec3], w: u32, h: u32, pixel_texel: &PixelTexels, seams: &[SeamSample]) {
    if seams.is_empty() {
        return;
    }
    // Rows: a seam sample's bilinear taps with + weights on side a, − on side b.
    let rows: Vec<Vec<(usize, f32)>> = seams
        .iter()
        .map(|s| {
            let mut row: Vec<(usize, f32)> = bilinear(s.a, w, h).to_vec();
            row.extend(bilinear(s.b, w, h).iter().map(|(i, wt)| (*i, -*wt)));
            row
        })
        .collect();
    // Unknowns: every pixel a row touches, numbered densely.
    let mut index: HashMap<usize, usize> = HashMap::new();
    let mut pixels = Vec::new();
    for row in &rows {
        for (p, _) in row {
            index.entry(*p).or_insert_with(|| {
                pixels.push(*p);
                pixels.len() - 1
            });
        }
    }
    let rows: Vec<Vec<(usize, f32)>> = rows
        .into_iter()
        .map(|r| r.into_iter().map(|(p, wt)| (index[&p], wt)).collect())
        .collect();
    let data: Vec<f32> = pixels
        .iter()
        .map(|p| {
            if pixel_texel[*p] != NO_TEXEL {
                1.0
            } else {
                GUTTER_DATA_WEIGHT
            }
        })
        .collect();
    // (D + λ AᵀA) x = D x0, one channel at a time.
    let apply = |x: &[f32], out: &mut [f32]| {
        for (k, o) in out.iter_mut().enumerate() {
            *o = data[k] * x[k];
        }
        for row in &rows {
            let r: f32 = row.iter().map(|(i, wt)| wt * x[*i]).sum();
            for (i, wt) in row {
                out[*i] += SEAM_WEIGHT * wt * r;
            }
        }
    };
    #[allow(clippy::needless_range_loop)] // c picks the colour channel in image and x0 alike
    for c in 0..3 {
        let x0: Vec<f32> = pixels.iter().map(|p| image[*p][c]).collect();
        let b: Vec<f32> = x0.iter().zip(&data).map(|(x, d)| x * d).collect();
        let mut x = x0.clone();
        let mut ax = vec![0.0; x.len()];
        apply(&x, &mut ax);
        let mut r: Vec<f32> = b.iter().zip(&ax).map(|(b, a)| b - a).collect();
        let mut p = r.clone();
        let mut rr: f32 = r.iter().map(|v| v * v).sum();
        let tolerance = 1e-10 * b.iter().map(|v| v * v).sum::<f32>().max(f32::MIN_POSITIVE);
        let mut ap = vec![0.0; x.len()];
        for _ in 0..ITERATIONS {
            if rr <= tolerance {
                break;
            }
            apply(&p, &mut ap);
            let pap: f32 = p.iter().zip(&ap).map(|(a, b)| a * b).sum();
            if pap <= 0.0 {
                break;
            }
            let alpha = rr / pap;
            for k in 0..x.len() {
                x[k] += alpha * p[k];
                r[k] -= alpha * ap[k];
            }
            let rr_new: f32 = r.iter().map(|v| v * v).sum();
            let beta = rr_new / rr;
            for k in 0..x.len() {
                p[k] = r[k] + beta * p[k];
            }
            rr = rr_new;
        }
        for (k, px) in pixels.iter().enumerate() {
            // Light is never negative; the solve can undershoot by a rounding error.
            image[*px][c] = x[k].max(0.0);
        }
    }
}
