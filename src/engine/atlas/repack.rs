//! `lightmap_uvs: repack-instances` (issue 19 point 3): a mesh with authored `TEXCOORD_1`
//! that several nodes place gets one rectangle per node, its authored UVs kept bit for bit.
//!
//! Why: authored lightmap UVs lay a mesh out once, in [0, 1]; placed by several nodes, every
//! instance addresses the same texels (the import report warns). `regenerate-all` fixes the
//! overlap by throwing the authored layout away; this keeps it, as Unity keeps a prefab's
//! UV2 and gives each renderer its own `lightmapScaleOffset`.
//!
//! How: each such instance's rectangle holds the bounding box of the mesh's authored UVs at
//! a scale `S` (texels per unit of UV) chosen so that its texel area over its world area is
//! the density of the bake: `S = density × sqrt(world area / UV area)`, where the world
//! area is the instance's own (its transform included) and the density is the job's
//! `texels_per_unit` (times the node's and mesh's `extras.lightmap_scale`), or the density
//! the generated charts got, or, with nothing generated and no density asked, the highest
//! that fits one page ([`fit_density`]). Rectangles are `PADDING` texels apart on every
//! side and packed on pages of their own, after the generated pages, by height-sorted
//! shelves ([`shelf_pack`]). Each instance's `scale_offset` maps the mesh's `TEXCOORD_1`
//! into its rectangle; nothing in the mesh changes.
//!
//! Why a hand-written packer: these are whole rectangles, usually tens to a few hundred,
//! placed once; sorted shelves are a few lines, deterministic, and within a few percent of
//! the area for rectangles of a few sizes. The `uvunwrap` crate packs charts it makes
//! itself and takes no fixed rectangles, and atlas allocators (`etagere`, `guillotiere`)
//! are built for allocating and freeing at run time.
//!
//! Limits: the rectangle is the UV bounding box, so an authored layout that leaves much of
//! its box empty wastes that share of the rectangle; an instance whose transform scales
//! non-uniformly gets stretched texels, as generated instances do.

use glam::{DVec2, Vec2};

use super::unwrap::PADDING;

/// One instance to place: the authored UVs' bounding box and the instance's scale.
#[derive(Clone, Debug)]
pub struct Item {
    /// Index into the source document's instances.
    pub instance: usize,
    /// Bounding box of the mesh's authored `TEXCOORD_1`.
    pub lo: Vec2,
    pub hi: Vec2,
    /// Texels per unit of UV at a density of 1 texel per metre: sqrt(world area / UV
    /// area), times the instance's `extras.lightmap_scale`.
    pub uv_scale: f64,
}

/// Where an item went: its page, the rectangle's corner in that page (texels) and its
/// scale `S` (texels per unit of UV).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placed {
    pub page: u32,
    pub x: u32,
    pub y: u32,
    pub texels_per_uv: f64,
}

/// Rectangle side in texels for a box of `extent` UV at `s` texels per unit: whole texels
/// covering it, plus the padding on both sides.
fn side(extent: f32, s: f64) -> u32 {
    ((f64::from(extent) * s).ceil().max(1.0) as u32).saturating_add(2 * PADDING)
}

/// The rectangles of `items` at `density`, each scaled down to fit a `page`-wide page
/// when larger (returned in the second list, by item index).
fn rects(items: &[Item], density: f64, page: u32) -> (Vec<(u32, u32, f64)>, Vec<usize>) {
    let mut shrunk = Vec::new();
    let out = items
        .iter()
        .enumerate()
        .map(|(k, it)| {
            let mut s = it.uv_scale * density;
            let e = it.hi - it.lo;
            let room = f64::from(page.saturating_sub(2 * PADDING + 1).max(1));
            let longest = f64::from(e.x.max(e.y));
            if longest * s > room {
                s = room / longest;
                shrunk.push(k);
            }
            (side(e.x, s), side(e.y, s), s)
        })
        .collect();
    (out, shrunk)
}

/// Packs rectangles (w, h) on `page` × `page` pages: sorted by height, laid left to right
/// on shelves, a new shelf when a row is full, a new page when a shelf does not fit.
/// Returns each rectangle's page and corner, in input order. Every rectangle must fit a
/// page (`rects` makes sure).
pub fn shelf_pack(sizes: &[(u32, u32)], page: u32) -> Vec<(u32, u32, u32)> {
    let mut order: Vec<usize> = (0..sizes.len()).collect();
    // Tallest first; ties by width then index, so the layout is the same on every run.
    order.sort_by(|&a, &b| {
        sizes[b]
            .1
            .cmp(&sizes[a].1)
            .then(sizes[b].0.cmp(&sizes[a].0))
            .then(a.cmp(&b))
    });
    let mut out = vec![(0, 0, 0); sizes.len()];
    let (mut p, mut x, mut y, mut shelf_h) = (0u32, 0u32, 0u32, 0u32);
    for k in order {
        let (w, h) = sizes[k];
        if x + w > page {
            y += shelf_h;
            x = 0;
            shelf_h = 0;
        }
        if y + h > page {
            p += 1;
            x = 0;
            y = 0;
            shelf_h = 0;
        }
        out[k] = (p, x, y);
        x += w;
        shelf_h = shelf_h.max(h);
    }
    out
}

/// The pages `items` take at `density` on `page`-wide pages, and where each went; the
/// second list names the items scaled down to fit a page.
pub fn place(items: &[Item], density: f64, page: u32) -> (u32, Vec<Placed>, Vec<usize>) {
    let (r, shrunk) = rects(items, density, page);
    let sizes: Vec<(u32, u32)> = r.iter().map(|&(w, h, _)| (w, h)).collect();
    let at = shelf_pack(&sizes, page);
    let pages = at.iter().map(|a| a.0 + 1).max().unwrap_or(0);
    let placed = at
        .iter()
        .zip(&r)
        .map(|(&(page, x, y), &(_, _, s))| Placed {
            page,
            x,
            y,
            texels_per_uv: s,
        })
        .collect();
    (pages, placed, shrunk)
}

/// The highest density (texels per metre) at which `items` fit one `page`-wide page: from
/// the density whose rectangles' area (padding aside) is 70 % of the page, lowered by 5 %
/// at a time until the shelves hold them (at most 60 tries; then the last one).
pub fn fit_density(items: &[Item], page: u32) -> f64 {
    let area: f64 = items
        .iter()
        .map(|it| {
            let e = (it.hi - it.lo).as_dvec2();
            e.x * e.y * it.uv_scale * it.uv_scale
        })
        .sum();
    let p = f64::from(page);
    let mut d = if area > 0.0 { (0.7 * p * p / area).sqrt() } else { 1.0 };
    for _ in 0..60 {
        let (pages, _, shrunk) = place(items, d, page);
        if pages <= 1 && shrunk.is_empty() {
            return d;
        }
        d *= 0.95;
    }
    d
}

/// `scale_offset` in the bake's grid (`width` × `height`, the page's first row at `top`)
/// for an item placed at `at`: TEXCOORD_1 `uv` lands at
/// `(x + PADDING + (uv − lo) · S, top + y + PADDING + (uv − lo) · S)` texels.
pub fn scale_offset(item: &Item, at: &Placed, top: u32, width: u32, height: u32) -> [f32; 4] {
    let s = at.texels_per_uv;
    let corner = DVec2::new(f64::from(at.x + PADDING), f64::from(top) + f64::from(at.y + PADDING));
    let o = corner - item.lo.as_dvec2() * s;
    let (w, h) = (f64::from(width), f64::from(height));
    [(s / w) as f32, (s / h) as f32, (o.x / w) as f32, (o.y / h) as f32]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Shelves never overlap and stay inside the page; a rectangle that does not fit the
    /// page's rest opens a new page.
    #[test]
    fn shelves_do_not_overlap() {
        let sizes = [(60, 40), (50, 50), (30, 20), (100, 10), (40, 40), (64, 64), (10, 90)];
        let at = shelf_pack(&sizes, 100);
        for (i, (&(p, x, y), &(w, h))) in at.iter().zip(&sizes).enumerate() {
            assert!(x + w <= 100 && y + h <= 100, "rectangle {i} at {x},{y} leaves the page");
            for (j, (&(q, u, v), &(w2, h2))) in at.iter().zip(&sizes).enumerate().skip(i + 1) {
                let apart = p != q || x + w <= u || u + w2 <= x || y + h <= v || v + h2 <= y;
                assert!(apart, "rectangles {i} and {j} overlap");
            }
        }
        // 90 + 64 + 50 + ... rows: more than one page of 100.
        assert!(at.iter().any(|a| a.0 > 0));
        assert_eq!(
            shelf_pack(&[(10, 10); 4], 20),
            vec![(0, 0, 0), (0, 10, 0), (0, 0, 10), (0, 10, 10)]
        );
    }

    /// The fitted density puts every item on one page and uses it well.
    #[test]
    fn the_fitted_density_fills_one_page() {
        let item = |k: usize, s: f64| Item {
            instance: k,
            lo: Vec2::new(0.1, 0.2),
            hi: Vec2::new(0.9, 0.8),
            uv_scale: s,
        };
        let items: Vec<Item> = (0..5).map(|k| item(k, 1.0 + k as f64)).collect();
        let d = fit_density(&items, 256);
        let (pages, placed, shrunk) = place(&items, d, 256);
        assert_eq!((pages, shrunk.len()), (1, 0));
        // The page is well used: the rectangles cover more than 40 % of it.
        let used: f64 = placed
            .iter()
            .map(|p| {
                let e = (items[0].hi - items[0].lo).as_dvec2() * p.texels_per_uv;
                (e.x.ceil() + 6.0) * (e.y.ceil() + 6.0)
            })
            .sum();
        assert!(used > 0.4 * 256.0 * 256.0, "{used} texels of 65536");
        // Twice the density does not fit one page.
        assert!(place(&items, 2.0 * d, 256).0 > 1);
    }
}
