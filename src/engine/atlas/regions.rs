//! Regions of the texel grid: what one task of a bake split by texels bakes
//! (`engine::tasks`, issue 25).
//!
//! A region is a contiguous run of the valid texels in pixel order. Since texels are
//! kept in pixel order (row-major) and pages are bands of rows, a run of texels is a band
//! of whole rows of the grid (its first and last rows possibly partial), and a run that
//! starts and ends on page boundaries is a set of whole pages.
//!
//! How the grid is cut into `count` regions:
//! - `count` at most the page count: whole pages, grouped into `count` consecutive runs
//!   with about as many texels each (a cut goes at the page boundary nearest the ideal
//!   cumulative share, and every region keeps at least one page). With `count` equal to
//!   the page count, region k is page k: a 64-page level is 64 page tasks.
//! - more regions than pages: the texels are cut into `count` runs of equal length
//!   (within one), ignoring page boundaries: tiles as wide as the grid, for a level of one
//!   large page. So are pages whose grouping would leave a region without a texel (a run
//!   of empty pages): no region is ever empty.
//!
//! The cut is made on the texel set as rasterised, before texel validation drops the
//! texels inside geometry, and kept as pixel ranges ([`Atlas::region_pixels`]): a task
//! validates only its region's texels (`job::prepare_regions`), and the merge, which
//! validates the whole grid, finds each region's texels by the same pixel ranges. The
//! cut depends only on the scene and request, which a bake's tasks and its merge each
//! rebuild identically, so all of them agree on it.
//!
//! A region's own atlas ([`Atlas::region`]) keeps the grid (width, height, pages) and
//! each texel's pixel, and drops what only the delivery of the whole grid uses (the
//! gutter links and the seams: the merge delivers from the whole atlas). A technique
//! whose texels are independent of one another (its table row's `TaskSplit`) bakes
//! exactly the region's share of a whole bake on it, provided its random streams are
//! keyed by pixel (`path`: `Texel::pixel`).

use std::ops::Range;

use super::{Atlas, Coverage, PageRows, PixelTexels};

/// The texel ranges of `count` regions of a grid of `n` texels, `width` wide, cut into
/// `pages`, where `texels_before(pixel)` counts the texels on pixels below `pixel` (the
/// module doc's cut; shared by [`Atlas`] and [`Coverage`], which must agree).
fn cut(
    n: usize,
    count: u32,
    width: u32,
    pages: &[PageRows],
    texels_before: impl Fn(u64) -> usize,
) -> Result<Vec<Range<usize>>, String> {
    let count = count.max(1) as usize;
    if n < count {
        return Err(format!(
            "{count} regions asked of a lightmap with {n} valid texels: at most one region per texel"
        ));
    }
    if count == 1 {
        return Ok(std::iter::once(0..n).collect());
    }
    if count <= pages.len() {
        // The first texel of every page, then n: page p is starts[p]..starts[p + 1].
        let mut starts: Vec<usize> = pages
            .iter()
            .map(|band| texels_before(u64::from(band.first_row) * u64::from(width)))
            .collect();
        starts.push(n);
        let pages = pages.len();
        // Boundary k (1..count) at the page boundary b nearest k/count of the texels,
        // kept strictly increasing and leaving at least one page per later region.
        let mut cuts = vec![0usize];
        for k in 1..count {
            let ideal = n as f64 * k as f64 / count as f64;
            let lo = cuts[k - 1] + 1;
            let hi = pages - (count - k);
            let b = (lo..=hi)
                .min_by(|&a, &b| {
                    let da = (starts[a] as f64 - ideal).abs();
                    let db = (starts[b] as f64 - ideal).abs();
                    da.total_cmp(&db)
                })
                .unwrap_or(lo);
            cuts.push(b);
        }
        cuts.push(pages);
        let grouped: Vec<Range<usize>> = cuts.windows(2).map(|w| starts[w[0]]..starts[w[1]]).collect();
        if grouped.iter().all(|r| !r.is_empty()) {
            return Ok(grouped);
        }
    }
    Ok((0..count).map(|k| k * n / count..(k + 1) * n / count).collect())
}

/// The pixel ranges of texel ranges `ranges` of a grid of `end` pixels: region k is
/// every pixel from its first texel's (`pixel_of`) up to the next region's first
/// texel's (region 0 from pixel 0, the last to the end of the grid).
fn pixel_ranges(ranges: &[Range<usize>], end: u32, pixel_of: impl Fn(usize) -> u32) -> Vec<Range<u32>> {
    let starts: Vec<u32> = ranges
        .iter()
        .enumerate()
        .map(|(k, r)| if k == 0 { 0 } else { pixel_of(r.start) })
        .collect();
    (0..starts.len())
        .map(|k| starts[k]..starts.get(k + 1).copied().unwrap_or(end))
        .collect()
}

impl Coverage {
    /// [`Atlas::region_pixels`] of the atlas this coverage is of, without building it:
    /// what a region's task needs before it builds its region alone
    /// ([`Atlas::build_pixels`]).
    pub fn region_pixels(&self, count: u32) -> Result<Vec<Range<u32>>, String> {
        let ranges = cut(self.texels(), count, self.width, &self.pages, |p| self.texels_before(p))?;
        Ok(pixel_ranges(&ranges, self.width * self.height, |k| self.pixel_of(k)))
    }
}

impl Atlas {
    /// The texel ranges of this grid's `count` regions, in order, covering every texel
    /// once. Refused (with the reason) when there are fewer texels than regions.
    pub fn regions(&self, count: u32) -> Result<Vec<Range<usize>>, String> {
        cut(self.texels.len(), count, self.width, &self.pages, |first_pixel| {
            self.texels.partition_point(|t| u64::from(t.pixel) < first_pixel)
        })
    }

    /// The pixel ranges of [`Atlas::regions`]: region k is every pixel from its first
    /// texel's up to the next region's first texel's (region 0 from pixel 0, the last to
    /// the end of the grid), so the ranges tile the grid and a texel set derived from
    /// this one by dropping texels (validation) is cut at the same places by
    /// [`Atlas::texels_in`].
    pub fn region_pixels(&self, count: u32) -> Result<Vec<Range<u32>>, String> {
        let ranges = self.regions(count)?;
        Ok(pixel_ranges(&ranges, self.width * self.height, |k| {
            self.texels[k].pixel
        }))
    }

    /// The texels whose pixels lie in `pixels` (texels are in pixel order, so a range).
    pub fn texels_in(&self, pixels: Range<u32>) -> Range<usize> {
        let first = self.texels.partition_point(|t| t.pixel < pixels.start);
        let end = self.texels.partition_point(|t| t.pixel < pixels.end);
        first..end
    }

    /// The atlas of the texels in `texels` (a range [`Atlas::regions`] gave): the same
    /// grid and pixels, only those texels valid.
    pub fn region(&self, texels: Range<usize>) -> Atlas {
        let kept = &self.texels[texels.clone()];
        // The window of its texels' pixels: outside it, no texel of the region.
        let window = kept.first().map_or(0..0, |a| {
            a.pixel as usize..kept.last().map_or(a.pixel, |b| b.pixel) as usize + 1
        });
        Atlas {
            width: self.width,
            height: self.height,
            texels: kept.to_vec(),
            pixel_texel: PixelTexels::of(kept, window),
            links: Vec::new(),
            overlapping_texels: self.overlapping_texels,
            surface_offset: self.surface_offset,
            overlap_pixels: Vec::new(),
            inside_pixels: Vec::new(),
            validation: self.validation.clone(),
            seams: Vec::new(),
            pages: self.pages.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::atlas::{NO_TEXEL, Texel};
    use crate::engine::scene::PageRows;
    use glam::Vec3;

    /// A `width` x (rows per page x pages) grid whose valid texels are `pixels`.
    fn atlas(width: u32, page_rows: &[u32], pixels: &[u32]) -> Atlas {
        let mut first = 0;
        let pages: Vec<PageRows> = page_rows
            .iter()
            .map(|&rows| {
                let p = PageRows { first_row: first, rows };
                first += rows;
                p
            })
            .collect();
        let height = first;
        let texels: Vec<Texel> = pixels
            .iter()
            .map(|&pixel| Texel {
                pixel,
                position: Vec3::new(pixel as f32, 0.0, 0.0),
                normal: Vec3::Y,
                geo_normal: Vec3::Y,
                albedo: Vec3::splat(0.5),
                emission: Vec3::ZERO,
                triangle: 0,
                mesh: 0,
                size: 1.0,
            })
            .collect();
        Atlas {
            width,
            height,
            pixel_texel: PixelTexels::of(&texels, 0..(width * height) as usize),
            texels,
            links: Vec::new(),
            overlapping_texels: 0,
            surface_offset: 1e-4,
            overlap_pixels: Vec::new(),
            inside_pixels: Vec::new(),
            validation: None,
            seams: Vec::new(),
            pages,
        }
    }

    #[test]
    fn as_many_regions_as_pages_are_the_pages() {
        // 4 wide, pages of 2, 1 and 3 rows (pixels 0..8, 8..12, 12..24).
        let a = atlas(4, &[2, 1, 3], &[0, 3, 7, 9, 10, 11, 12, 20, 23]);
        assert_eq!(a.regions(3).unwrap(), vec![0..3, 3..6, 6..9]);
        assert_eq!(a.regions(1).unwrap(), vec![0..9]);
        // Two regions: pages grouped at the page boundary nearest half the texels (4.5).
        // After page 0 (3 texels) and after page 1 (6) are as near; the first is kept.
        assert_eq!(a.regions(2).unwrap(), vec![0..3, 3..9]);
    }

    #[test]
    fn more_regions_than_pages_are_equal_runs_of_texels() {
        let a = atlas(4, &[2, 1, 3], &[0, 3, 7, 9, 10, 11, 12, 20, 23]);
        let r = a.regions(4).unwrap();
        assert_eq!(r, vec![0..2, 2..4, 4..6, 6..9]);
        let err = a.regions(10).unwrap_err();
        assert!(err.contains("9 valid texels"), "{err}");
    }

    #[test]
    fn no_region_is_empty_and_regions_cover_every_texel_once() {
        // Page 1 (pixels 8..12) has no texel: three page regions would leave one empty,
        // so the texels are cut into equal runs instead.
        let a = atlas(4, &[2, 1, 3], &[0, 1, 2, 3, 13, 14]);
        assert_eq!(a.regions(3).unwrap(), vec![0..2, 2..4, 4..6]);
        // Two regions still fall on a page boundary (after page 0 or 1: both 4 texels).
        assert_eq!(a.regions(2).unwrap(), vec![0..4, 4..6]);
        for count in 1..=6 {
            let r = a.regions(count).unwrap();
            assert_eq!(r.len(), count as usize);
            assert_eq!(r.first().unwrap().start, 0);
            assert_eq!(r.last().unwrap().end, 6);
            assert!(r.windows(2).all(|w| w[0].end == w[1].start), "{count}: {r:?}");
            assert!(r.iter().all(|x| !x.is_empty()), "{count}: {r:?}");
        }
    }

    #[test]
    fn pixel_ranges_tile_the_grid_and_find_the_same_texels() {
        let a = atlas(4, &[2, 1, 3], &[0, 3, 7, 9, 10, 11, 12, 20, 23]);
        for count in 1..=9 {
            let pixels = a.region_pixels(count).unwrap();
            let texels = a.regions(count).unwrap();
            assert_eq!(pixels.first().unwrap().start, 0);
            assert_eq!(pixels.last().unwrap().end, 24);
            assert!(pixels.windows(2).all(|w| w[0].end == w[1].start));
            let found: Vec<Range<usize>> = pixels.iter().map(|p| a.texels_in(p.clone())).collect();
            assert_eq!(found, texels, "{count}");
        }
        // A region starts at its first texel's pixel (page 1's first texel is pixel 9).
        assert_eq!(a.region_pixels(3).unwrap(), vec![0..9, 9..12, 12..24]);
        // A texel dropped later (validation) leaves the others in their regions.
        let mut b = a.clone();
        b.remove_texels(&[false, false, false, true, false, false, false, false, false]);
        let found: Vec<Range<usize>> = a
            .region_pixels(3)
            .unwrap()
            .into_iter()
            .map(|p| b.texels_in(p))
            .collect();
        assert_eq!(found, vec![0..3, 3..5, 5..8]);
    }

    /// The coverage of `a`'s texels.
    fn coverage(a: &Atlas) -> Coverage {
        let n = (a.width * a.height) as usize;
        let mut bits = vec![0u64; n.div_ceil(64)];
        for t in &a.texels {
            bits[t.pixel as usize / 64] |= 1 << (t.pixel % 64);
        }
        let mut before = Vec::new();
        let mut sum = 0;
        for b in &bits {
            before.push(sum);
            sum += b.count_ones();
        }
        Coverage {
            width: a.width,
            height: a.height,
            pages: a.pages.clone(),
            bits,
            before,
        }
    }

    /// The cut from a coverage is the atlas's, for every count (pages, grouped pages,
    /// runs of texels, and the refusal), here over words of 64 pixels.
    #[test]
    fn a_coverage_cuts_where_its_atlas_cuts() {
        let wide: Vec<u32> = (0..300).filter(|p| p % 7 != 3 && p % 11 != 0).collect();
        for a in [
            atlas(4, &[2, 1, 3], &[0, 3, 7, 9, 10, 11, 12, 20, 23]),
            atlas(4, &[2, 1, 3], &[0, 1, 2, 3, 13, 14]),
            atlas(50, &[2, 3, 1], &wide),
        ] {
            let c = coverage(&a);
            assert_eq!(c.texels(), a.texels.len());
            for (k, t) in a.texels.iter().enumerate() {
                assert_eq!(c.pixel_of(k), t.pixel);
                assert_eq!(c.texels_before(u64::from(t.pixel)), k);
            }
            for count in 1..=a.texels.len() as u32 + 1 {
                assert_eq!(c.region_pixels(count), a.region_pixels(count), "{count}");
            }
        }
    }

    #[test]
    fn a_region_keeps_its_texels_pixels_and_the_grid() {
        let a = atlas(4, &[2, 1, 3], &[0, 3, 7, 9, 10, 11, 12, 20, 23]);
        let r = a.region(3..6);
        assert_eq!((r.width, r.height, r.pages.len()), (4, 6, 3));
        let pixels: Vec<u32> = r.texels.iter().map(|t| t.pixel).collect();
        assert_eq!(pixels, vec![9, 10, 11]);
        assert_eq!(r.pixel_texel[10], 1);
        assert_eq!(r.pixel_texel[0], NO_TEXEL);
        assert_eq!(r.texels[2].position, a.texels[5].position);
    }
}
