//! Post-processing of a finished estimate before it is written.
//!
//! Dilation ([`dilate`]): bilinear filtering and mip-mapping in a renderer read texels
//! outside a chart, so the empty texels around every chart must hold plausible light, not
//! black. First every gutter link from the atlas is applied (a texel a chart touches takes
//! its own chart's nearest valid value), then rings of empty texels are filled outward,
//! each with the mean of its already-filled 8-neighbours, for `rings` rings.
//!
//! Denoising: [`denoised`] (OIDN or the own filter of [`denoise`], and the local
//! regressions of [`regress`], weighted with the raw estimate by their cross-validated
//! errors).
//!
//! Limits: a ring may average two charts' values where their gutters meet.

pub mod denoise;
pub mod denoised;
pub mod oidn;
pub mod regress;
pub mod seams;

use glam::Vec3;

use crate::engine::atlas::{Atlas, NO_TEXEL};

/// Default gutter width in texels: enough for bilinear filtering at two mip levels.
pub const DEFAULT_RINGS: u32 = 8;

/// Returns a full W × H image from per-texel `values`, with gutters filled.
pub fn dilate(atlas: &Atlas, values: &[Vec3], rings: u32) -> Vec<Vec3> {
    let (w, h) = (atlas.width as usize, atlas.height as usize);
    let mut img = atlas.to_image(values, Vec3::ZERO);
    let mut filled: Vec<bool> = (0..w * h).map(|p| atlas.pixel_texel[p] != NO_TEXEL).collect();
    for link in &atlas.links {
        img[link.pixel as usize] = values[link.texel as usize];
        filled[link.pixel as usize] = true;
    }
    // Rings stay within a page: pages are separate images once written.
    let row_page = atlas.row_pages();
    for _ in 0..rings {
        let mut next = Vec::new();
        for j in 0..h {
            for i in 0..w {
                let pix = j * w + i;
                if filled[pix] {
                    continue;
                }
                let mut sum = Vec3::ZERO;
                let mut count = 0u32;
                for dj in -1i64..=1 {
                    for di in -1i64..=1 {
                        let (ni, nj) = (i as i64 + di, j as i64 + dj);
                        if (di, dj) == (0, 0)
                            || ni < 0
                            || nj < 0
                            || ni >= w as i64
                            || nj >= h as i64
                            || row_page[nj as usize] != row_page[j]
                        {
                            continue;
                        }
                        let np = nj as usize * w + ni as usize;
                        if filled[np] {
                            sum += img[np];
                            count += 1;
                        }
                    }
                }
                if count > 0 {
                    next.push((pix, sum / count as f32));
                }
            }
        }
        if next.is_empty() {
            break;
        }
        for (pix, v) in next {
            img[pix] = v;
            filled[pix] = true;
        }
    }
    img
}

/// Spreads a per-texel scalar into the image without dilation (validity, error maps).
pub fn scatter_scalar(atlas: &Atlas, values: &[f32]) -> Vec<f32> {
    atlas.to_image(values, 0.0)
}
