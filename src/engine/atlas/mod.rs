//! The lightmap texel set: which texels of a W × H lightmap lie on the scene, and the
//! surface point, normals and material each one stands for.
//!
//! How: every triangle is rasterised in TEXCOORD_1 space with edge functions, one sample
//! at each texel centre (DESIGN §2: texel (i, j) covers u in [i/W, (i+1)/W], v in
//! [j/H, (j+1)/H], row 0 first, v grows downward as in glTF). A centre on an edge shared
//! by two triangles belongs to exactly one of them (the top-left rule, applied after
//! orienting each UV triangle the same way), so only true overlaps are counted. A centre
//! claimed twice (overlapping charts, coplanar duplicates) keeps the first triangle and
//! is counted in [`Atlas::overlapping_texels`].
//!
//! Texels a chart touches but whose centre lies outside every triangle are not valid;
//! each keeps a link to the nearest valid texel of the chart (a [`GutterLink`]), which
//! dilation copies first, so the partly covered texels at chart borders get their own
//! chart's light rather than a neighbour chart's.
//!
//! The sample point is the surface point pushed off along the geometric normal by
//! [`Atlas::surface_offset`], a fixed fraction (2e-5) of the scene's diagonal: relative,
//! so a scene scaled by 1e-3 or 1e4 bakes the same lightmap, and small enough for walls
//! much thinner than a texel (2 mm in a 100 m scene). Before that, the surface point is
//! moved by that offset toward its triangle's centroid: a texel centre on a chart's
//! border edge (half-texel chart margins put whole rows there) is on the crease with the
//! next mesh, and a ray from there toward that mesh starts in its plane, where a hit at
//! t = 0 does not count, so it passed behind the wall and read the sky (issue 21: in the
//! connected-rooms case `path` read +48 % / +50 % through those texels). The inset was a
//! tenth of the offset at first, 4e-6 of the scene radius: below the 1e-5 of the radius
//! that the plane-storing shadow maps (`vpl`, `hemicube`) need to call a point strictly on
//! one side of a wall, so their crease points still saw the sky through the adjacent wall
//! (`vpl` +47 % / +45 % in the connected rooms, +1.3 % / −4.2 % with the whole offset).
//!
//! A split bake's region task (`engine::tasks`) needs only its region: [`Atlas::coverage`]
//! runs the same rasterisation keeping one bit a pixel (enough to cut the grid into
//! regions, `atlas::regions`), and [`Atlas::build_pixels`] rasterises only the rows of
//! one pixel range and builds only its texels, equal to the whole atlas's texels there.
//!
//! Limits: one sample per texel centre (no supersampling of texels half on a chart); a
//! texel whose sample point lies inside closed geometry is still valid here (techniques
//! see back faces from it).

pub mod cells;
pub mod regions;
pub mod repack;
pub mod seams;
pub mod unwrap;
pub mod validate;

use std::borrow::Cow;
use std::ops::Range;

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::Serialize;

pub use crate::engine::scene::PageRows;
use crate::engine::scene::Scene;

/// How far a sample point on a triangle's edge is moved into the triangle, as a fraction
/// of the surface offset (module doc): the whole offset, so that even along a slanted
/// direction to the centroid a crease point ends up more than the shadow maps' 1e-5 of
/// the scene radius off the adjacent wall's plane.
const EDGE_INSET: f32 = 1.0;

/// Marks a pixel that holds no valid texel in [`Atlas::pixel_texel`].
pub const NO_TEXEL: u32 = u32::MAX;

/// The largest lightmap side accepted (a 16384² lightmap is 3 GiB of texel data).
pub const MAX_RESOLUTION: u32 = 16384;

/// Relative offset of sample points off their surface, as a fraction of the scene diagonal.
pub const SURFACE_OFFSET: f32 = 2e-5;

#[derive(Clone, Copy, Debug)]
pub struct Texel {
    /// Pixel index `j * width + i` in the lightmap image.
    pub pixel: u32,
    /// Sample point: the surface point, pushed off along `geo_normal`.
    pub position: Vec3,
    /// Interpolated shading normal, unit length (the hemisphere the texel integrates).
    pub normal: Vec3,
    /// The triangle's geometric normal, unit length (front side, CCW winding).
    pub geo_normal: Vec3,
    pub albedo: Vec3,
    pub emission: Vec3,
    pub triangle: u32,
    /// The triangle's mesh: texels of different meshes never share light in filtering.
    pub mesh: u32,
    /// World-space side of one texel on this texel's triangle (metres).
    pub size: f32,
}

/// A texel a chart touches but whose centre is outside it, and the valid texel whose
/// value it takes before general dilation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GutterLink {
    pub pixel: u32,
    pub texel: u32,
}

#[derive(Clone, Debug)]
pub struct Atlas {
    pub width: u32,
    pub height: u32,
    /// Valid texels only, in pixel order.
    pub texels: Vec<Texel>,
    /// For every pixel, its index in `texels`, or [`NO_TEXEL`] (indexed by pixel; a
    /// region's atlas holds the window of its pixels only).
    pub pixel_texel: PixelTexels,
    pub links: Vec<GutterLink>,
    pub overlapping_texels: u32,
    pub surface_offset: f32,
    /// Pixels claimed by more than one triangle (for the `debug.overlap` layer).
    pub overlap_pixels: Vec<u32>,
    /// Pixels whose texel validation found inside closed geometry (`debug.inside`).
    pub inside_pixels: Vec<u32>,
    /// The validation report, once `validate::validate` has run.
    pub validation: Option<validate::ValidationReport>,
    /// Sample pairs along UV seams, for `post::seams::stitch`.
    pub seams: Vec<seams::SeamSample>,
    /// The output pages: row bands of this grid, top to bottom, covering it (one band of
    /// every row unless `atlas::unwrap` stacked several pages).
    pub pages: Vec<PageRows>,
}

#[derive(Clone, Debug, Serialize)]
pub struct AtlasReport {
    pub width: u32,
    pub height: u32,
    pub valid_texels: usize,
    pub gutter_texels: usize,
    pub overlapping_texels: u32,
    /// Fraction of the lightmap covered by valid texels.
    pub utilisation: f32,
    /// Output pages (`lightmap-P.exr`) the grid is cut into.
    pub pages: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum AtlasError {
    #[error("lightmap resolution {0}x{1} is out of range (1 to {MAX_RESOLUTION} per side)")]
    Resolution(u32, u32),
    #[error("no texel centre of the {0}x{1} lightmap falls on any triangle: raise the resolution or check TEXCOORD_1")]
    Empty(u32, u32),
}

/// Texel centre of pixel (i, j) in UV space.
pub fn texel_centre_uv(i: u32, j: u32, width: u32, height: u32) -> Vec2 {
    Vec2::new((i as f32 + 0.5) / width as f32, (j as f32 + 0.5) / height as f32)
}

/// `(b - a) × (p - a)`, evaluated from the same endpoint whichever way the edge runs, so
/// the two triangles sharing an edge get exactly opposite values: a texel centre within
/// rounding of a shared edge is then claimed by exactly one of them (evaluated from `a` in
/// one and from `b` in the other, the two roundings could both come out positive).
fn edge_function(a: Vec2, b: Vec2, p: Vec2) -> f32 {
    if (a.x, a.y) <= (b.x, b.y) {
        (b - a).perp_dot(p - a)
    } else {
        -((a - b).perp_dot(p - b))
    }
}

struct Claim {
    triangle: u32,
    bary: Vec3,
}

/// Does the edge a→b (in an oriented triangle) own sample points lying exactly on it?
/// Exactly one of a→b and b→a does, so a shared edge's points go to one triangle.
fn owns_edge(a: Vec2, b: Vec2) -> bool {
    let d = b - a;
    d.y < 0.0 || (d.y == 0.0 && d.x > 0.0)
}

fn check_resolution(width: u32, height: u32) -> Result<(), AtlasError> {
    if width == 0 || height == 0 || width > MAX_RESOLUTION || height > MAX_RESOLUTION {
        return Err(AtlasError::Resolution(width, height));
    }
    Ok(())
}

/// The texels of `claims`, claim k on pixel `pixel_of(k)`, in the claims' order.
fn texels_of(
    scene: &Scene,
    width: u32,
    height: u32,
    claims: &[Option<Claim>],
    pixel_of: impl Fn(usize) -> usize + Sync,
) -> Vec<Texel> {
    let (w, h) = (width as usize, height as usize);
    let offset = SURFACE_OFFSET * scene.scale();
    claims
        .par_iter()
        .enumerate()
        .filter_map(|(k, c)| c.as_ref().map(|c| (pixel_of(k), c)))
        .map(|(pix, c)| {
            let t = &scene.triangles[c.triangle as usize];
            let b = c.bary;
            let mut surface = t.p[0] * b.x + t.p[1] * b.y + t.p[2] * b.z;
            // A centre on or next to an edge (charts laid out with half-texel margins
            // put whole rows exactly on one) puts the sample point on the crease with
            // the next mesh, and a ray from it toward that mesh starts in its plane,
            // where t = 0 is no hit: the ray passes behind it (module doc). Every
            // sample point is moved a fixed small distance toward its triangle's
            // centroid, so none lies on an edge.
            let centroid = (t.p[0] + t.p[1] + t.p[2]) / 3.0;
            surface += (centroid - surface).normalize_or_zero() * (EDGE_INSET * offset);
            let geo = t.geometric_normal();
            let mut n = (t.n[0] * b.x + t.n[1] * b.y + t.n[2] * b.z).normalize_or_zero();
            // A shading normal on the far side of the surface is a broken export;
            // integrate the geometric hemisphere rather than the wrong one.
            if n.dot(geo) <= 0.0 {
                n = geo;
            }
            let uv_area = 0.5 * (t.lm[1] - t.lm[0]).perp_dot(t.lm[2] - t.lm[0]).abs();
            Texel {
                mesh: t.mesh,
                size: (t.area() / (uv_area * (w * h) as f32)).sqrt(),
                pixel: pix as u32,
                position: surface + geo * offset,
                normal: n,
                geo_normal: geo,
                albedo: scene.albedo(t, b),
                emission: scene.emission(t, b),
                triangle: c.triangle,
            }
        })
        .collect()
}

/// Every pixel's texel index, or [`NO_TEXEL`], over a window of the grid's pixels: the
/// whole grid for a whole atlas, a region's pixels for a region's (`build_pixels`), so a
/// region's task does not hold an index of every pixel of the level (4 bytes a pixel:
/// 4.3 GB for 64 pages of 4096²). Indexing a pixel outside the window gives
/// [`NO_TEXEL`]: no texel of this atlas is there.
#[derive(Clone, Debug, Default)]
pub struct PixelTexels {
    first: usize,
    map: Vec<u32>,
}

impl PixelTexels {
    /// The index of `texels` (in pixel order) over the pixels `window`.
    pub fn of(texels: &[Texel], window: Range<usize>) -> PixelTexels {
        let mut map = vec![NO_TEXEL; window.end.saturating_sub(window.start)];
        for (k, t) in texels.iter().enumerate() {
            map[t.pixel as usize - window.start] = k as u32;
        }
        PixelTexels {
            first: window.start,
            map,
        }
    }

    /// The pixels it covers.
    pub fn window(&self) -> Range<usize> {
        self.first..self.first + self.map.len()
    }

    /// The whole grid's index, when it covers the `pixels` of the whole grid (a whole
    /// atlas); `None` for a region's.
    pub fn whole(&self, pixels: usize) -> Option<&[u32]> {
        (self.first == 0 && self.map.len() == pixels).then_some(&self.map)
    }

    /// Every (pixel, texel index) of the window, empty pixels included.
    pub fn iter(&self) -> impl Iterator<Item = (usize, u32)> + '_ {
        self.map.iter().enumerate().map(|(i, &t)| (self.first + i, t))
    }

    /// Maps every texel index through `f` (empty pixels stay empty).
    pub fn remap(&mut self, f: impl Fn(u32) -> u32) {
        for t in self.map.iter_mut().filter(|t| **t != NO_TEXEL) {
            *t = f(*t);
        }
    }
}

/// The same texels at the same pixels, whatever the windows.
impl PartialEq for PixelTexels {
    fn eq(&self, other: &Self) -> bool {
        let held = |p: &PixelTexels| p.iter().filter(|(_, t)| *t != NO_TEXEL).collect::<Vec<_>>();
        held(self) == held(other)
    }
}

impl std::ops::Index<usize> for PixelTexels {
    type Output = u32;

    fn index(&self, pixel: usize) -> &u32 {
        pixel
            .checked_sub(self.first)
            .and_then(|i| self.map.get(i))
            .unwrap_or(&NO_TEXEL)
    }
}

/// The layout's pages when it made this grid; otherwise the grid is one page.
fn grid_pages(scene: &Scene, width: u32, height: u32) -> Vec<PageRows> {
    scene
        .layout
        .as_deref()
        .filter(|l| (l.width, l.height) == (width, height) && !l.pages.is_empty())
        .map_or_else(
            || {
                vec![PageRows {
                    first_row: 0,
                    rows: height,
                }]
            },
            |l| l.pages.clone(),
        )
}

/// Calls `visit(pixel, triangle, barycentrics)` for every texel centre in `pixels` that
/// a triangle of `scene` covers, triangle by triangle in scene order (so the first visit
/// of a pixel is its claim): the rasterisation of the module doc, over the rows the
/// range touches only.
fn rasterise(scene: &Scene, width: u32, height: u32, pixels: Range<u32>, mut visit: impl FnMut(usize, u32, Vec3)) {
    let (w, h) = (width as usize, height as usize);
    let size = Vec2::new(width as f32, height as f32);
    let (first, end) = (pixels.start as usize, pixels.end as usize);
    if first >= end {
        return;
    }
    let (row_lo, row_hi) = (first / w, ((end - 1) / w) as i64);
    for (ti, tri) in scene.triangles.iter().enumerate() {
        let mut q = [tri.lm[0] * size, tri.lm[1] * size, tri.lm[2] * size];
        let mut order = [0usize, 1, 2];
        let area2 = (q[1] - q[0]).perp_dot(q[2] - q[0]);
        if area2 == 0.0 || !area2.is_finite() {
            continue;
        }
        if area2 < 0.0 {
            q.swap(1, 2);
            order.swap(1, 2);
        }
        let area2 = area2.abs();
        let lo = q[0].min(q[1]).min(q[2]);
        let hi = q[0].max(q[1]).max(q[2]);
        let i0 = (lo.x - 0.5).ceil().max(0.0) as usize;
        let j0 = ((lo.y - 0.5).ceil().max(0.0) as usize).max(row_lo);
        let i1 = ((hi.x - 0.5).floor() as i64).min(w as i64 - 1);
        let j1 = ((hi.y - 0.5).floor() as i64).min(h as i64 - 1).min(row_hi);
        if i1 < i0 as i64 || j1 < j0 as i64 {
            continue;
        }
        let edges = [(1usize, 2usize), (2, 0), (0, 1)];
        let owns = edges.map(|(a, b)| owns_edge(q[a], q[b]));
        for j in j0..=j1 as usize {
            for i in i0..=i1 as usize {
                let pix = j * w + i;
                if pix < first || pix >= end {
                    continue;
                }
                let p = Vec2::new(i as f32 + 0.5, j as f32 + 0.5);
                let mut e = [0.0f32; 3];
                let mut inside = true;
                for (k, (a, b)) in edges.iter().enumerate() {
                    e[k] = edge_function(q[*a], q[*b], p);
                    if e[k] < 0.0 || (e[k] == 0.0 && !owns[k]) {
                        inside = false;
                        break;
                    }
                }
                if !inside {
                    continue;
                }
                // e[k] is the weight of the vertex opposite edge k, in oriented order.
                let mut bary = [0.0f32; 3];
                for k in 0..3 {
                    bary[order[k]] = e[k] / area2;
                }
                visit(pix, ti as u32, Vec3::from_array(bary));
            }
        }
    }
}

/// Which pixels of a grid hold a texel (before validation), one bit each: what cutting
/// the grid into a split bake's regions needs (`atlas::regions`) without building the
/// texels themselves, so a region's task builds only its own ([`Atlas::build_pixels`]).
/// 1/8 byte a pixel, against [`Atlas::build`]'s 25 bytes a pixel and some 100 a texel.
pub struct Coverage {
    pub width: u32,
    pub height: u32,
    pub pages: Vec<PageRows>,
    bits: Vec<u64>,
    /// Texels before each 64-pixel word.
    before: Vec<u32>,
}

/// The pixels whose bits are set in coverage word `w`, ascending.
fn word_pixels(w: usize, bits: u64) -> impl Iterator<Item = u32> {
    let mut b = bits;
    std::iter::from_fn(move || {
        (b != 0).then(|| {
            let p = (w * 64) as u32 + b.trailing_zeros();
            b &= b - 1;
            p
        })
    })
}

impl Coverage {
    /// Valid texels (before validation) in the grid.
    pub fn texels(&self) -> usize {
        self.before.last().copied().unwrap_or(0) as usize + self.bits.last().map_or(0, |b| b.count_ones() as usize)
    }

    /// How many texels lie on pixels below `pixel` (where a texel of that pixel would be
    /// in the atlas's texel list).
    pub fn texels_before(&self, pixel: u64) -> usize {
        let word = (pixel / 64) as usize;
        if word >= self.bits.len() {
            return self.texels();
        }
        let mask = (1u64 << (pixel % 64)) - 1;
        self.before[word] as usize + (self.bits[word] & mask).count_ones() as usize
    }

    /// The covered pixels with the `count` smallest `key`s (ties: the smaller pixel), in
    /// that order: a seeded draw of texels from the whole grid that does not depend on
    /// which region of it a task holds. One pass over the covered pixels with a bounded
    /// heap per thread: memory O(count), not a key per pixel.
    pub fn smallest(&self, count: usize, key: impl Fn(u32) -> u64 + Sync) -> Vec<u32> {
        use std::collections::BinaryHeap;
        if count == 0 {
            return Vec::new();
        }
        let push = |heap: &mut BinaryHeap<(u64, u32)>, item: (u64, u32)| {
            if heap.len() < count {
                heap.push(item);
            } else if heap.peek().is_some_and(|top| item < *top) {
                heap.pop();
                heap.push(item);
            }
        };
        const WORDS: usize = 1 << 12;
        let heap = self
            .bits
            .par_chunks(WORDS)
            .enumerate()
            .map(|(c, words)| {
                let mut heap = BinaryHeap::new();
                for (w, &bits) in words.iter().enumerate() {
                    for pixel in word_pixels(c * WORDS + w, bits) {
                        push(&mut heap, (key(pixel), pixel));
                    }
                }
                heap
            })
            .reduce(BinaryHeap::new, |mut a, b| {
                for item in b {
                    push(&mut a, item);
                }
                a
            });
        heap.into_sorted_vec().into_iter().map(|(_, p)| p).collect()
    }

    /// The covered pixels, ascending.
    pub fn pixels(&self) -> impl Iterator<Item = u32> + '_ {
        self.bits.iter().enumerate().flat_map(|(w, &bits)| word_pixels(w, bits))
    }

    /// The pixel of texel `k` (k < [`texels`](Self::texels)).
    pub fn pixel_of(&self, k: usize) -> u32 {
        let word = self.before.partition_point(|&b| b as usize <= k) - 1;
        let mut bits = self.bits[word];
        for _ in 0..(k - self.before[word] as usize) {
            bits &= bits - 1;
        }
        (word * 64) as u32 + bits.trailing_zeros()
    }
}

impl Atlas {
    pub fn build(scene: &Scene, width: u32, height: u32) -> Result<Atlas, AtlasError> {
        check_resolution(width, height)?;
        let (w, h) = (width as usize, height as usize);
        let mut claims: Vec<Option<Claim>> = (0..w * h).map(|_| None).collect();
        let mut overlapping = vec![false; w * h];
        rasterise(scene, width, height, 0..width * height, |pix, triangle, bary| {
            if claims[pix].is_some() {
                overlapping[pix] = true;
            } else {
                claims[pix] = Some(Claim { triangle, bary });
            }
        });
        let texels = texels_of(scene, width, height, &claims, |k| k);
        if texels.is_empty() {
            return Err(AtlasError::Empty(width, height));
        }
        let pixel_texel = PixelTexels::of(&texels, 0..w * h);
        let links = gutter_links(scene, &pixel_texel, &texels, width, height);
        Ok(Atlas {
            width,
            height,
            texels,
            pixel_texel,
            links,
            overlapping_texels: overlapping.iter().filter(|o| **o).count() as u32,
            overlap_pixels: (0..w * h).filter(|p| overlapping[*p]).map(|p| p as u32).collect(),
            inside_pixels: Vec::new(),
            validation: None,
            surface_offset: SURFACE_OFFSET * scene.scale(),
            seams: seams::find_seams(scene, width, height),
            pages: grid_pages(scene, width, height),
        })
    }

    /// The atlas of the texels on `pixels` alone, as [`Atlas::build`]`(..).region(..)`
    /// makes it (the same grid, pages and pixels, only those texels valid, no gutter
    /// links or seams: the merge delivers the whole grid), but rasterising only the rows
    /// the range touches and building only its texels: a region task's texel set
    /// (`job::prepare_regions`), whose memory and time are its region's, not the whole
    /// grid's. Its `overlapping_texels` counts the range's overlaps only.
    pub fn build_pixels(scene: &Scene, width: u32, height: u32, pixels: Range<u32>) -> Result<Atlas, AtlasError> {
        check_resolution(width, height)?;
        let n = (width * height) as usize;
        let (first, end) = (pixels.start as usize, (pixels.end as usize).min(n));
        let mut claims: Vec<Option<Claim>> = (first..end.max(first)).map(|_| None).collect();
        let mut overlapping = 0u32;
        rasterise(scene, width, height, pixels, |pix, triangle, bary| {
            let c = &mut claims[pix - first];
            if c.is_some() {
                overlapping += 1;
            } else {
                *c = Some(Claim { triangle, bary });
            }
        });
        let texels = texels_of(scene, width, height, &claims, |k| first + k);
        if texels.is_empty() {
            return Err(AtlasError::Empty(width, height));
        }
        Ok(Atlas {
            width,
            height,
            pixel_texel: PixelTexels::of(&texels, first..end.max(first)),
            texels,
            links: Vec::new(),
            overlapping_texels: overlapping,
            overlap_pixels: Vec::new(),
            inside_pixels: Vec::new(),
            validation: None,
            surface_offset: SURFACE_OFFSET * scene.scale(),
            seams: Vec::new(),
            pages: grid_pages(scene, width, height),
        })
    }

    /// The texels on `pixels` (ascending, each once) as [`Atlas::build`] makes them,
    /// without building any other (a pixel no chart covers has none): a draw of a few
    /// texels of the whole grid that a region's task makes as a single bake does
    /// ([`Coverage::smallest`]; `sdf`'s calibration). Rasterises the rows the pixels
    /// span.
    pub fn texels_at(scene: &Scene, width: u32, height: u32, pixels: &[u32]) -> Result<Vec<Texel>, AtlasError> {
        check_resolution(width, height)?;
        let (Some(&first), Some(&last)) = (pixels.first(), pixels.last()) else {
            return Ok(Vec::new());
        };
        let mut claims: Vec<Option<Claim>> = (0..pixels.len()).map(|_| None).collect();
        rasterise(scene, width, height, first..last + 1, |pix, triangle, bary| {
            if let Ok(k) = pixels.binary_search(&(pix as u32))
                && claims[k].is_none()
            {
                claims[k] = Some(Claim { triangle, bary });
            }
        });
        Ok(texels_of(scene, width, height, &claims, |k| pixels[k] as usize))
    }

    /// Every texel of the grid *before validation* (the inside texels too), in pixel
    /// order: this atlas's texels and its removed ones when it holds the whole grid,
    /// otherwise (a region's task) the whole grid's built anew. What a technique that
    /// reads the whole grid's materials ( `obscurance`'s albedo map and R_ave) takes, so a
    /// region's task reads the single bake's. A region's call costs the whole grid's
    /// rasterisation and texels (some 100 bytes a texel while it runs).
    pub fn grid_texels(&self, scene: &Scene) -> Result<Cow<'_, [Texel]>, AtlasError> {
        let whole = self.pixel_texel.window() == (0..(self.width * self.height) as usize);
        if whole {
            // A whole grid that validation left whole is its own texel set: no copy.
            if self.inside_pixels.is_empty() {
                return Ok(Cow::Borrowed(&self.texels));
            }
            let mut inside = self.inside_pixels.clone();
            inside.sort_unstable();
            let mut all = self.texels.clone();
            all.extend(Atlas::texels_at(scene, self.width, self.height, &inside)?);
            all.sort_unstable_by_key(|t| t.pixel);
            return Ok(Cow::Owned(all));
        }
        let coverage = Atlas::coverage(scene, self.width, self.height)?;
        let pixels: Vec<u32> = coverage.pixels().collect();
        Ok(Cow::Owned(Atlas::texels_at(scene, self.width, self.height, &pixels)?))
    }

    /// Which pixels of the `width` x `height` grid hold a texel: the rasterisation of
    /// [`Atlas::build`] keeping one bit a pixel.
    pub fn coverage(scene: &Scene, width: u32, height: u32) -> Result<Coverage, AtlasError> {
        check_resolution(width, height)?;
        let n = width as usize * height as usize;
        let mut bits = vec![0u64; n.div_ceil(64)];
        rasterise(scene, width, height, 0..width * height, |pix, _, _| {
            bits[pix / 64] |= 1 << (pix % 64)
        });
        let mut before = Vec::with_capacity(bits.len());
        let mut sum = 0u32;
        for b in &bits {
            before.push(sum);
            sum += b.count_ones();
        }
        if sum == 0 {
            return Err(AtlasError::Empty(width, height));
        }
        Ok(Coverage {
            width,
            height,
            pages: grid_pages(scene, width, height),
            bits,
            before,
        })
    }

    /// Per row of the grid, the index of the page holding it.
    pub fn row_pages(&self) -> Vec<u32> {
        let mut out = vec![0u32; self.height as usize];
        for (p, band) in self.pages.iter().enumerate() {
            let end = (band.first_row + band.rows).min(self.height);
            out[band.first_row as usize..end as usize].fill(p as u32);
        }
        out
    }

    pub fn report(&self) -> AtlasReport {
        AtlasReport {
            width: self.width,
            height: self.height,
            valid_texels: self.texels.len(),
            gutter_texels: self.links.len(),
            overlapping_texels: self.overlapping_texels,
            utilisation: self.texels.len() as f32 / (self.width as f32 * self.height as f32),
            pages: self.pages.len() as u32,
        }
    }

    /// Spreads per-texel values into a full W × H image; invalid pixels get `empty`.
    pub fn to_image<T: Copy>(&self, values: &[T], empty: T) -> Vec<T> {
        let mut img = vec![empty; (self.width * self.height) as usize];
        for (t, v) in self.texels.iter().zip(values) {
            img[t.pixel as usize] = *v;
        }
        img
    }
}

/// Distance from `p` to triangle `q` (all in pixel units), and the closest point.
fn closest_point(p: Vec2, q: &[Vec2; 3]) -> Vec2 {
    let area2 = (q[1] - q[0]).perp_dot(q[2] - q[0]);
    let inside = (0..3).all(|k| {
        let (a, b) = (q[k], q[(k + 1) % 3]);
        (b - a).perp_dot(p - a) * area2.signum() >= 0.0
    });
    if inside {
        return p;
    }
    let mut best = q[0];
    let mut best_d = f32::INFINITY;
    for k in 0..3 {
        let (a, b) = (q[k], q[(k + 1) % 3]);
        let ab = b - a;
        let t = if ab.length_squared() > 0.0 {
            ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let c = a + ab * t;
        let d = c.distance_squared(p);
        if d < best_d {
            best_d = d;
            best = c;
        }
    }
    best
}

/// The valid texel in the 5 x 5 window of pixels around `pix` with the smallest
/// `score(i, j, texel)`; `None` scores leave a texel out. Dilation's links and the texel
/// cells (`cells`) both look for "the texel this bit of chart belongs to" this way.
pub(crate) fn nearest_texel_around(
    pixel_texel: &PixelTexels,
    width: u32,
    height: u32,
    pix: usize,
    score: impl Fn(i64, i64, u32) -> Option<f32>,
) -> Option<u32> {
    let (w, h) = (width as i64, height as i64);
    let (i, j) = ((pix as i64) % w, (pix as i64) / w);
    let mut best: Option<(f32, u32)> = None;
    for nj in (j - 2).max(0)..=(j + 2).min(h - 1) {
        for ni in (i - 2).max(0)..=(i + 2).min(w - 1) {
            let t = pixel_texel[(nj * w + ni) as usize];
            if t == NO_TEXEL {
                continue;
            }
            if let Some(d) = score(ni, nj, t)
                && best.is_none_or(|(bd, _)| d < bd)
            {
                best = Some((d, t));
            }
        }
    }
    best.map(|(_, t)| t)
}

fn gutter_links(
    scene: &Scene,
    pixel_texel: &PixelTexels,
    texels: &[Texel],
    width: u32,
    height: u32,
) -> Vec<GutterLink> {
    let (w, h) = (width as i64, height as i64);
    let size = Vec2::new(width as f32, height as f32);
    let mut linked = vec![false; pixel_texel.window().len()];
    let mut links = Vec::new();
    // A texel square meets the triangle when its centre is within half a diagonal of it.
    let reach = std::f32::consts::FRAC_1_SQRT_2;
    for tri in scene.triangles.iter() {
        let q = [tri.lm[0] * size, tri.lm[1] * size, tri.lm[2] * size];
        if (q[1] - q[0]).perp_dot(q[2] - q[0]) == 0.0 {
            continue;
        }
        let lo = q[0].min(q[1]).min(q[2]);
        let hi = q[0].max(q[1]).max(q[2]);
        let (i0, j0) = (
            (lo.x - 1.0).floor().max(0.0) as i64,
            (lo.y - 1.0).floor().max(0.0) as i64,
        );
        let (i1, j1) = (
            (hi.x + 1.0).ceil().min(w as f32 - 1.0) as i64,
            (hi.y + 1.0).ceil().min(h as f32 - 1.0) as i64,
        );
        for j in j0..=j1 {
            for i in i0..=i1 {
                let pix = (j * w + i) as usize;
                if pixel_texel[pix] != NO_TEXEL || linked[pix] {
                    continue;
                }
                let centre = Vec2::new(i as f32 + 0.5, j as f32 + 0.5);
                let c = closest_point(centre, &q);
                if c.distance(centre) > reach {
                    continue;
                }
                // Nearest valid texel of the mesh to the touched point.
                let best = nearest_texel_around(pixel_texel, width, height, pix, |ni, nj, t| {
                    (scene.triangles[texels[t as usize].triangle as usize].mesh == tri.mesh)
                        .then(|| Vec2::new(ni as f32 + 0.5, nj as f32 + 0.5).distance_squared(c))
                });
                if let Some(t) = best {
                    linked[pix] = true;
                    links.push(GutterLink {
                        pixel: pix as u32,
                        texel: t,
                    });
                }
            }
        }
    }
    links
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::scene::build::{MaterialDesc, SceneBuilder};
    use crate::engine::scene::import_slice;

    /// A draw of texels by a key of their pixel ([`Coverage::smallest`], then
    /// [`Atlas::texels_at`]) gives the texels the whole grid's atlas has on those pixels,
    /// in key order, whatever else is built.
    #[test]
    fn texels_drawn_by_pixel_are_the_whole_grids() {
        let scene = import_slice(&crate::engine::scene::library::procedural_blocks().to_glb(), None)
            .unwrap()
            .0;
        let atlas = Atlas::build(&scene, 48, 48).unwrap();
        let coverage = Atlas::coverage(&scene, 48, 48).unwrap();
        let key = |p: u32| u64::from(p.wrapping_mul(2_654_435_761) >> 7);
        let drawn = coverage.smallest(40, key);
        assert_eq!(drawn.len(), 40);
        let keys: Vec<(u64, u32)> = drawn.iter().map(|&p| (key(p), p)).collect();
        assert!(keys.windows(2).all(|w| w[0] < w[1]), "in key order");
        let mut all: Vec<(u64, u32)> = atlas.texels.iter().map(|t| (key(t.pixel), t.pixel)).collect();
        all.sort_unstable();
        assert_eq!(&all[..40], keys.as_slice(), "the smallest keys of every texel");
        let mut sorted = drawn.clone();
        sorted.sort_unstable();
        let texels = Atlas::texels_at(&scene, 48, 48, &sorted).unwrap();
        assert_eq!(texels.len(), 40);
        for t in &texels {
            let whole = &atlas.texels[atlas.pixel_texel[t.pixel as usize] as usize];
            assert_eq!(
                (t.position, t.normal, t.albedo, t.size, t.triangle),
                (whole.position, whole.normal, whole.albedo, whole.size, whole.triangle)
            );
        }
        assert_eq!(coverage.smallest(usize::MAX >> 1, key).len(), atlas.texels.len());
    }

    fn one_quad(margin: f32) -> Scene {
        let mut b = SceneBuilder::new();
        let m = b.material(MaterialDesc::diffuse("grey", [0.5, 0.5, 0.5]));
        b.square("floor", Vec3::ZERO, 2.0, Vec3::Y, m);
        b.margin = Some(margin);
        import_slice(&b.to_glb(), None).unwrap().0
    }

    #[test]
    fn full_chart_covers_every_texel_exactly_once() {
        // The quad's two triangles share a diagonal through texel centres of a square
        // lightmap: the top-left rule must give each centre to exactly one triangle.
        let scene = one_quad(0.0);
        let atlas = Atlas::build(&scene, 16, 16).unwrap();
        assert_eq!(atlas.texels.len(), 256);
        assert_eq!(atlas.overlapping_texels, 0);
        assert!(atlas.links.is_empty());
    }

    #[test]
    fn texel_positions_match_uv_mapping() {
        let scene = one_quad(0.0);
        let atlas = Atlas::build(&scene, 8, 8).unwrap();
        // The square spans x, z in [-1, 1] at y = 0; the builder's frame for +Y runs u
        // along -X and v along -Z.
        // Within the inset toward the triangle's centroid (the surface offset, module doc).
        let within = atlas.surface_offset * 1.001 + 1e-6;
        for t in &atlas.texels {
            let (i, j) = (t.pixel % 8, t.pixel / 8);
            let uv = texel_centre_uv(i, j, 8, 8);
            assert!(
                (t.position.x - (1.0 - 2.0 * uv.x)).abs() < within,
                "{:?} {uv}",
                t.position
            );
            assert!(
                (t.position.z - (1.0 - 2.0 * uv.y)).abs() < within,
                "{:?} {uv}",
                t.position
            );
            assert!(t.position.y > 0.0 && t.position.y < 1e-3);
            assert_eq!(t.geo_normal, Vec3::Y);
            assert!((t.albedo - Vec3::splat(0.5)).abs().max_element() < 1e-6);
        }
    }

    #[test]
    fn partial_chart_links_border_texels() {
        let scene = one_quad(0.1);
        let atlas = Atlas::build(&scene, 20, 20).unwrap();
        // The chart spans [2, 18] in pixels: centres 2.5..17.5 are inside (16 x 16).
        assert_eq!(atlas.texels.len(), 16 * 16);
        assert_eq!(atlas.overlapping_texels, 0);
        // Every border pixel whose square touches the chart links to a valid texel.
        for l in &atlas.links {
            assert_ne!(
                atlas.pixel_texel[atlas.texels[l.texel as usize].pixel as usize],
                NO_TEXEL
            );
            assert_eq!(atlas.pixel_texel[l.pixel as usize], NO_TEXEL);
        }
        assert!(atlas.links.len() >= 4 * 16, "{} links", atlas.links.len());
    }

    #[test]
    fn duplicated_faces_are_counted_as_overlap() {
        let mut b = SceneBuilder::new();
        let m = b.material(MaterialDesc::diffuse("grey", [0.5, 0.5, 0.5]));
        b.square("a", Vec3::ZERO, 2.0, Vec3::Y, m);
        let (json, bin) = b.to_gltf();
        let mut json = json;
        // Two nodes with the same mesh: coplanar duplicates on the same chart.
        json["nodes"]
            .as_array_mut()
            .unwrap()
            .push(serde_json::json!({"mesh": 0}));
        json["scenes"][0]["nodes"] = serde_json::json!([0, 1]);
        let scene = import_slice(&crate::engine::scene::build::write_glb(&json, &bin), None)
            .unwrap()
            .0;
        let atlas = Atlas::build(&scene, 8, 8).unwrap();
        assert_eq!(atlas.overlapping_texels as usize, atlas.texels.len());
    }

    #[test]
    fn bad_resolution_is_an_error() {
        let scene = one_quad(0.0);
        assert!(matches!(Atlas::build(&scene, 0, 8), Err(AtlasError::Resolution(0, 8))));
        assert!(matches!(
            Atlas::build(&scene, 8, MAX_RESOLUTION + 1),
            Err(AtlasError::Resolution(..))
        ));
    }
}
