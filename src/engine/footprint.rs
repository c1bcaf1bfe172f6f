//! How much memory a bake will need, estimated before it starts from what the importer
//! reported and what the job asks for, so a server can refuse a job its workers cannot
//! hold instead of being killed by the kernel half-way through it.
//!
//! How: a sum of the big allocations, each bounded from above. Every pixel of the
//! lightmap is counted as a valid texel (the real texel set is smaller: chart gutters and
//! empty space hold none), each with its [`Texel`] record and its accumulators: two
//! halves, the combined estimate, the step's samples, the snapshot's copies and the
//! denoiser's input and output (nine copies of every kept layer: six were counted until
//! a bake without a denoiser measured 232 B a pixel at 1024² against 208 estimated,
//! 2026-12-06), and the denoiser's working set: the local regressions' candidates and
//! their weights ([`DENOISE_BYTES_PER_TEXEL`], whatever the kept layers: they are
//! filtered one at a time) and OIDN's buffers ([`OIDN_BYTES_PER_PIXEL`]). Output images (one f32 RGB image per EXR layer plus
//! its encoding) and the PNG preview are per pixel. Triangles are counted at the import's
//! f64 staging copy plus the scene's own and the BVH's, 512 bytes each; textures at four
//! f32 per pixel plus the 8-bit image they were decoded from. A fixed 64 MiB covers the
//! process itself.
//!
//! A server checks a job against its limit before it is queued, from `resolution`: one
//! page. Generated charts can need more pages than that (authored UVs beside generated
//! ones, or a `texels_per_unit`), which only the layout step knows, so the engine checks
//! again with the real grid before it allocates the texel set
//! (`job::BakeOptions::max_memory_bytes`).
//!
//! Limits: an estimate, not a measurement: it is meant to err high (docs/reliability.md
//! compares it with the peak resident size of real bakes). GPU techniques' device memory
//! is not counted; their host-side copies are the same as `path`'s.

use crate::engine::atlas::Texel;
use crate::engine::output::OutputLayer;

/// Bytes per triangle: import staging (f64 positions), the scene's triangle, the BVH.
pub const BYTES_PER_TRIANGLE: u64 = 512;
/// Bytes per texture pixel: four f32 kept, four u8 while decoding.
pub const BYTES_PER_TEXTURE_TEXEL: u64 = 20;
/// The process before any job: runtime, code, buffers.
pub const BASE_BYTES: u64 = 64 << 20;
/// Copies of every accumulated layer a bake holds at once (module doc).
const ACCUMULATOR_COPIES: u64 = 9;
/// The denoiser's working set per texel (`post::denoised`, `post::regress`): seven fits'
/// values (84 B), their halves' luminance (56) and gains (28), eight candidates'
/// cross-validated errors (32) and their smoothed means and errors (64), nine weights
/// (36), the raw variance twice (8), the delivered error, chart labels and the image
/// denoiser's outputs (28). Measured with the own filter (2026-12-06, Cornell box):
/// 285 B a texel over no denoiser at 1024², 294 B at 2048².
pub const DENOISE_BYTES_PER_TEXEL: u64 = 336;
/// OIDN's buffers per lightmap pixel as a bake uses them (three filter runs on the
/// gutter-filled image; measured over the own filter, Cornell box, 2026-12-06: 552 B a
/// pixel at 512², 513 at 1024², 500 at 2048²; docs/reliability.md).
pub const OIDN_BYTES_PER_PIXEL: u64 = 560;

/// What a job's memory depends on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct JobShape {
    pub triangles: u64,
    pub texture_texels: u64,
    /// Lightmap side in texels.
    pub resolution: u32,
    /// The bake's whole texel grid (width, height) once known (several pages, one under
    /// another: `atlas::unwrap`); None: one `resolution`² page.
    pub grid: Option<(u32, u32)>,
    pub direct: bool,
    pub indirect: bool,
    pub sh: bool,
    pub debug: bool,
    pub shadowmask: bool,
}

impl JobShape {
    /// The shape of a job over a scene of `triangles` and `texture_texels` with these
    /// extra output layers.
    pub fn new(triangles: u64, texture_texels: u64, resolution: u32, outputs: &[OutputLayer]) -> JobShape {
        JobShape {
            triangles,
            texture_texels,
            resolution,
            grid: None,
            direct: outputs.contains(&OutputLayer::Direct) || outputs.contains(&OutputLayer::Indirect),
            indirect: outputs.contains(&OutputLayer::Indirect),
            sh: outputs.contains(&OutputLayer::Sh),
            debug: outputs.contains(&OutputLayer::Debug),
            shadowmask: outputs.contains(&OutputLayer::Shadowmask),
        }
    }
}

impl JobShape {
    /// The same job on a grid of `width` × `height` texels (its pages, once laid out).
    pub fn on_grid(self, width: u32, height: u32) -> JobShape {
        JobShape {
            grid: Some((width, height)),
            ..self
        }
    }
}

/// The estimated peak memory of a bake of this shape, in bytes (an upper bound by
/// intent; module doc).
pub fn estimate_bytes(s: &JobShape) -> u64 {
    let pixels = match s.grid {
        Some((w, h)) => u64::from(w) * u64::from(h),
        None => u64::from(s.resolution) * u64::from(s.resolution),
    };
    const RGB: u64 = 12;
    // Accumulated per texel: the total, the direct part when split, three moment vectors.
    let accumulated = RGB + if s.direct { RGB } else { 0 } + if s.sh { 3 * RGB } else { 0 };
    // The shadowmask: its two halves read back (visibility and light, 32 B each) and the
    // delivered layer (16 B).
    let mask = if s.shadowmask { 2 * 32 + 16 } else { 0 };
    let per_texel = std::mem::size_of::<Texel>() as u64
        + 4
        + ACCUMULATOR_COPIES * accumulated
        + 4
        + mask
        + DENOISE_BYTES_PER_TEXEL
        + OIDN_BYTES_PER_PIXEL;
    // Written per pixel: R,G,B, the optional layers (validity and debug are one channel
    // each, counted as RGB to stay on the high side), and the encoded file.
    let layers = 2
        + u64::from(s.direct)
        + u64::from(s.indirect)
        + 3 * u64::from(s.sh)
        + 3 * u64::from(s.debug)
        + 2 * u64::from(s.shadowmask);
    let per_pixel = per_texel + 2 * layers * RGB + 4;
    BASE_BYTES
        .saturating_add(pixels.saturating_mul(per_pixel))
        .saturating_add(s.triangles.saturating_mul(BYTES_PER_TRIANGLE))
        .saturating_add(s.texture_texels.saturating_mul(BYTES_PER_TEXTURE_TEXEL))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn estimate_grows_with_each_input_and_has_a_floor() {
        let base = JobShape::new(0, 0, 1, &[]);
        assert!(estimate_bytes(&base) >= BASE_BYTES);
        let map = JobShape::new(0, 0, 1024, &[]);
        let sh = JobShape::new(0, 0, 1024, &[OutputLayer::Sh]);
        let tris = JobShape::new(1_000_000, 0, 1, &[]);
        let tex = JobShape::new(0, 4096 * 4096, 1, &[]);
        // 1024² texels cost at least the texel records and two accumulator halves.
        let texel_floor = (1u64 << 20) * (std::mem::size_of::<Texel>() as u64 + 2 * 12);
        assert!(estimate_bytes(&map) - BASE_BYTES >= texel_floor);
        assert!(estimate_bytes(&sh) > estimate_bytes(&map));
        assert_eq!(estimate_bytes(&tris) - estimate_bytes(&base), 512_000_000);
        assert_eq!(
            estimate_bytes(&tex) - estimate_bytes(&base),
            4096 * 4096 * BYTES_PER_TEXTURE_TEXEL
        );
        // Four pages one under another cost four pages.
        let four = JobShape::new(0, 0, 1024, &[]).on_grid(1024, 4096);
        assert_eq!(
            estimate_bytes(&four) - BASE_BYTES,
            4 * (estimate_bytes(&map) - BASE_BYTES)
        );
        // No overflow for absurd shapes.
        assert_eq!(
            estimate_bytes(&JobShape::new(u64::MAX, u64::MAX, u32::MAX, &[])),
            u64::MAX
        );
    }
}
