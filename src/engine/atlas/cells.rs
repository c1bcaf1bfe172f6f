//! The surface each valid texel stands for: its *cell*, as a list of world-space triangles.
//!
//! A lightmap texel is one value for a patch of surface: a renderer reads it for every
//! surface point whose lightmap UV falls in the texel's square (DESIGN §2's texel grid),
//! and dilation gives the partly covered squares at chart borders the value of a valid
//! texel of their chart. A technique that *shoots* light from texels (`hemicube`) has to
//! know that patch exactly: shooting a texel's light from its centre with the area of a
//! full square misplaces light near every edge and miscounts the area of every border
//! texel, and that shows as light lost or gained at every bounce (issue 21: the closed
//! box lost 4 to 5 % a bounce at 64²).
//!
//! How: every triangle is clipped in lightmap pixel space against each texel square its
//! UV bounding box touches (Sutherland-Hodgman against the square's four sides). Each
//! non-empty piece is fanned into triangles, mapped back to the surface through the
//! triangle's barycentric coordinates (the UV map is affine on a triangle), and given to
//! a texel:
//! - the square's own valid texel when that texel lies on the same mesh (its chart) and
//!   faces the same way (not the other side of a thin wall);
//! - otherwise (a border square whose centre is outside the chart, or a square whose
//!   texel belongs to another mesh's chart) the valid texel of the same mesh, facing the
//!   same way, within two texels in the grid whose sample point is nearest the piece in
//!   world space: the texel dilation would give the square, chosen in world space so
//!   that two charts of a mesh that meet in UV but not on the surface are told apart;
//! - a piece with no such texel is not shot from, and its area is counted in
//!   [`Cells::lost_area`] (a triangle smaller than a texel that missed every centre,
//!   far from its chart's texels; a UV outside [0, 1]).
//!
//! A triangle whose UV triangle has no area (degenerate UVs) is one piece, given to the
//! texel at its UV centroid by the same rule.
//!
//! The cells of a mesh tile its surface: their areas sum to the mesh's area less the lost
//! area (a unit test checks it, and that a box face's cells are 4 m² to float rounding).
//! Points are pushed off the surface along the triangle's geometric normal by the atlas's
//! [`Atlas::surface_offset`], as texel sample points are.
//!
//! Limits: a double-sided triangle has one cell side (a lightmap stores one side). Pieces
//! are kept as triangles (48 bytes each on the GPU); a mesh much finer than its texels
//! makes about one piece per triangle and texel it touches.

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use super::{Atlas, NO_TEXEL};
use crate::engine::scene::{Scene, Triangle};

/// One triangle of a texel's cell, on the surface (pushed off it by the surface offset).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellPiece {
    /// Corners, counter-clockwise about `normal`.
    pub p: [Vec3; 3],
    /// The source triangle's unit geometric normal.
    pub normal: Vec3,
    /// World area.
    pub area: f32,
}

/// The cells of every valid texel of an atlas.
#[derive(Clone, Debug, Default)]
pub struct Cells {
    /// Texel k's pieces are `pieces[first[k]..first[k + 1]]` (`first` has one entry more
    /// than there are texels).
    pub first: Vec<u32>,
    pub pieces: Vec<CellPiece>,
    /// Per texel: the area of its cell (the sum of its pieces).
    pub area: Vec<f32>,
    /// Surface area that no texel stands for (module doc).
    pub lost_area: f64,
}

impl Cells {
    /// Texel `k`'s pieces.
    pub fn of(&self, k: usize) -> &[CellPiece] {
        &self.pieces[self.first[k] as usize..self.first[k + 1] as usize]
    }
}

/// Pieces smaller than this fraction of a texel square are dropped as clipping round-off.
const MIN_PIECE: f32 = 1e-9;

/// The cells of `atlas`'s valid texels on `scene` (module doc).
pub fn cells(scene: &Scene, atlas: &Atlas) -> Cells {
    let (w, h) = (atlas.width as usize, atlas.height as usize);
    let size = Vec2::new(atlas.width as f32, atlas.height as f32);
    let per_triangle: Vec<(Vec<(u32, CellPiece)>, f64)> = scene
        .triangles
        .par_iter()
        .map(|t| {
            let mut out = Vec::new();
            let mut lost = 0.0f64;
            let geo = t.geometric_normal();
            let world_area = t.area();
            if !(world_area > 0.0) || geo == Vec3::ZERO {
                return (out, 0.0);
            }
            let offset = geo * atlas.surface_offset;
            let q = [t.lm[0] * size, t.lm[1] * size, t.lm[2] * size];
            let uv_area2 = (q[1] - q[0]).perp_dot(q[2] - q[0]);
            if uv_area2.abs() <= f32::EPSILON * (q[1] - q[0]).length_squared().max(1.0) {
                // Degenerate lightmap UVs: the whole triangle to the texel at its centroid.
                let c = (q[0] + q[1] + q[2]) / 3.0;
                let piece = CellPiece {
                    p: t.p.map(|p| p + offset),
                    normal: geo,
                    area: world_area,
                };
                match pixel_of(c, w, h).and_then(|pix| owner(atlas, t, pix, centroid(&piece))) {
                    Some(k) => out.push((k, piece)),
                    None => lost += world_area as f64,
                }
                return (out, lost);
            }
            let lo = q[0].min(q[1]).min(q[2]);
            let hi = q[0].max(q[1]).max(q[2]);
            let (i0, j0) = (lo.x.floor().max(0.0) as usize, lo.y.floor().max(0.0) as usize);
            let i1 = (hi.x.ceil() as i64).min(w as i64) as usize;
            let j1 = (hi.y.ceil() as i64).min(h as i64) as usize;
            let mut covered = 0.0f64;
            for j in j0..j1 {
                for i in i0..i1 {
                    let poly = clip_to_square(&q, i as f32, j as f32);
                    if poly.len() < 3 {
                        continue;
                    }
                    let pieces = fan(&poly, &q, uv_area2, t, offset, geo);
                    let area: f32 = pieces.iter().map(|p| p.area).sum();
                    if area <= MIN_PIECE * world_area {
                        continue;
                    }
                    covered += area as f64;
                    let mid = pieces.iter().map(|p| centroid(p) * p.area).sum::<Vec3>() / area;
                    match owner(atlas, t, j * w + i, mid) {
                        Some(k) => out.extend(pieces.into_iter().map(|p| (k, p))),
                        None => lost += area as f64,
                    }
                }
            }
            // What lies outside the grid ([0, 1] UV) is in no square.
            let uncovered = world_area as f64 - covered;
            if uncovered > 1e-5 * world_area as f64 {
                lost += uncovered;
            }
            (out, lost)
        })
        .collect();
    let mut lost_area = 0.0;
    let mut all: Vec<(u32, CellPiece)> = Vec::new();
    for (pieces, lost) in per_triangle {
        lost_area += lost;
        all.extend(pieces);
    }
    // Stable: a texel's pieces keep the triangle order, so a bake is reproducible.
    all.sort_by_key(|(k, _)| *k);
    let n = atlas.texels.len();
    let mut first = vec![0u32; n + 1];
    let mut area = vec![0.0f32; n];
    for (k, p) in &all {
        first[*k as usize + 1] += 1;
        area[*k as usize] += p.area;
    }
    for k in 0..n {
        first[k + 1] += first[k];
    }
    Cells {
        first,
        pieces: all.into_iter().map(|(_, p)| p).collect(),
        area,
        lost_area,
    }
}

/// The texel whose cell holds the point at barycentric weights `bary` of triangle
/// `triangle` (the rule the pieces follow, applied to the point), or `None` where no
/// texel stands for it. A ray's hit is read back through this: the light a gathering
/// estimator finds there is the light that texel's shooters send.
pub fn texel_at(scene: &Scene, atlas: &Atlas, triangle: u32, bary: Vec3) -> Option<u32> {
    let t = &scene.triangles[triangle as usize];
    let size = Vec2::new(atlas.width as f32, atlas.height as f32);
    let uv = (t.lm[0] * bary.x + t.lm[1] * bary.y + t.lm[2] * bary.z) * size;
    let pix = pixel_of(uv, atlas.width as usize, atlas.height as usize)?;
    owner(atlas, t, pix, t.point(bary))
}

fn centroid(p: &CellPiece) -> Vec3 {
    (p.p[0] + p.p[1] + p.p[2]) / 3.0
}

fn pixel_of(c: Vec2, w: usize, h: usize) -> Option<usize> {
    let (i, j) = (c.x.floor(), c.y.floor());
    (i >= 0.0 && j >= 0.0 && (i as usize) < w && (j as usize) < h).then(|| j as usize * w + i as usize)
}

/// The texel whose cell a piece of triangle `t` in pixel `pix` (world centroid `at`)
/// belongs to (module doc), or `None`.
fn owner(atlas: &Atlas, t: &Triangle, pix: usize, at: Vec3) -> Option<u32> {
    // A texel facing away is never the owner: the two sides of a thin wall can be one
    // mesh, their charts side by side in UV and their texels a millimetre apart.
    let facing = t.geometric_normal();
    let fits = |k: u32| {
        let texel = &atlas.texels[k as usize];
        texel.mesh == t.mesh && texel.geo_normal.dot(facing) > 0.0
    };
    let own = atlas.pixel_texel[pix];
    if own != NO_TEXEL && fits(own) {
        return Some(own);
    }
    super::nearest_texel_around(&atlas.pixel_texel, atlas.width, atlas.height, pix, |_, _, k| {
        fits(k).then(|| atlas.texels[k as usize].position.distance_squared(at))
    })
}

/// The part of UV triangle `q` (pixel units) inside the square [i, i+1] x [j, j+1].
fn clip_to_square(q: &[Vec2; 3], i: f32, j: f32) -> Vec<Vec2> {
    let mut poly: Vec<Vec2> = q.to_vec();
    // (axis, bound, keep when coordinate >= bound)
    for (axis, bound, above) in [(0, i, true), (0, i + 1.0, false), (1, j, true), (1, j + 1.0, false)] {
        if poly.is_empty() {
            break;
        }
        let inside = |p: Vec2| if above { p[axis] >= bound } else { p[axis] <= bound };
        let mut out = Vec::with_capacity(poly.len() + 1);
        for k in 0..poly.len() {
            let a = poly[k];
            let b = poly[(k + 1) % poly.len()];
            let (ia, ib) = (inside(a), inside(b));
            if ia {
                out.push(a);
            }
            if ia != ib {
                let s = (bound - a[axis]) / (b[axis] - a[axis]);
                let mut p = a + (b - a) * s;
                p[axis] = bound;
                out.push(p);
            }
        }
        poly = out;
    }
    poly
}

/// The surface triangles of UV polygon `poly` (inside `t`'s UV triangle `q`), fanned
/// from its first corner and wound like `t`.
fn fan(poly: &[Vec2], q: &[Vec2; 3], uv_area2: f32, t: &Triangle, offset: Vec3, geo: Vec3) -> Vec<CellPiece> {
    let world = |p: Vec2| {
        // Barycentric coordinates of p in q (affine, so exact for points inside).
        let b1 = (p - q[0]).perp_dot(q[2] - q[0]) / uv_area2;
        let b2 = (q[1] - q[0]).perp_dot(p - q[0]) / uv_area2;
        t.point(Vec3::new(1.0 - b1 - b2, b1, b2)) + offset
    };
    let pts: Vec<Vec3> = poly.iter().map(|p| world(*p)).collect();
    (1..pts.len() - 1)
        .filter_map(|k| {
            let (a, mut b, mut c) = (pts[0], pts[k], pts[k + 1]);
            // Clipping can leave repeated or collinear corners: their slivers have no
            // area and no trustworthy winding, so they are dropped.
            let along = (b - a).cross(c - a).dot(geo);
            let area = 0.5 * along.abs();
            if !(area > MIN_PIECE * t.area()) {
                return None;
            }
            if along < 0.0 {
                std::mem::swap(&mut b, &mut c);
            }
            Some(CellPiece {
                p: [a, b, c],
                normal: geo,
                area,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::scene::build::{MaterialDesc, SceneBuilder};
    use crate::engine::scene::library::closed_box;

    fn import(b: &SceneBuilder) -> Scene {
        crate::engine::scene::import_slice(&b.to_glb(), None).expect("import").0
    }

    #[test]
    fn the_cells_of_a_box_tile_each_face() {
        let scene = import(&closed_box(0.5));
        for res in [17u32, 48, 64, 100] {
            let atlas = Atlas::build(&scene, res, res).unwrap();
            let c = cells(&scene, &atlas);
            assert_eq!(c.first.len(), atlas.texels.len() + 1);
            assert!(c.lost_area < 1e-9, "{res}: lost {}", c.lost_area);
            let mut per_mesh = [0.0f64; 6];
            for (k, t) in atlas.texels.iter().enumerate() {
                let pieces = c.of(k);
                assert!(!pieces.is_empty(), "texel {k} has no cell");
                for p in pieces {
                    // On the texel's face, pushed off by the surface offset, facing its way.
                    assert!((p.normal - t.geo_normal).length() < 1e-6);
                    for v in p.p {
                        let plane = v.dot(t.geo_normal) - (t.position.dot(t.geo_normal));
                        assert!(plane.abs() < 1e-5, "{plane}");
                    }
                    let cross = (p.p[1] - p.p[0]).cross(p.p[2] - p.p[0]);
                    assert!(cross.dot(p.normal) > 0.0);
                }
                per_mesh[t.mesh as usize] += c.area[k] as f64;
            }
            for (m, a) in per_mesh.iter().enumerate() {
                assert!((a - 4.0).abs() < 4e-5, "{res}^2: face {m} cells sum to {a} m², not 4");
            }
        }
    }

    #[test]
    fn cells_conserve_area_on_a_curved_mesh_with_many_small_triangles() {
        // A sphere of 96 x 48 faces at 32^2: most triangles are smaller than a texel and
        // many miss every texel centre; their area still belongs to some texel.
        let mut b = SceneBuilder::new();
        let grey = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
        b.sphere("ball", Vec3::ZERO, 1.0, 96, 48, grey);
        b.square("floor", Vec3::new(0.0, -1.0, 0.0), 4.0, Vec3::Y, grey);
        let scene = import(&b);
        let atlas = Atlas::build(&scene, 32, 32).unwrap();
        let c = cells(&scene, &atlas);
        let total: f64 = scene.triangles.iter().map(|t| t.area() as f64).sum();
        let cells_total: f64 = c.area.iter().map(|a| *a as f64).sum();
        assert!(
            ((cells_total + c.lost_area) / total - 1.0).abs() < 1e-5,
            "{cells_total} + {} vs {total}",
            c.lost_area
        );
        assert!(c.lost_area / total < 1e-3, "lost {} of {total}", c.lost_area);
        // Every piece is near its texel (within a few texel sizes on the surface).
        for (k, t) in atlas.texels.iter().enumerate() {
            for p in c.of(k) {
                let d = centroid(p).distance(t.position);
                assert!(d < 4.0 * t.size, "texel {k}: piece {d} m away, texel size {}", t.size);
            }
        }
    }

    #[test]
    fn a_point_of_a_cell_reads_back_as_its_texel() {
        let scene = import(&closed_box(0.5));
        let atlas = Atlas::build(&scene, 48, 48).unwrap();
        let c = cells(&scene, &atlas);
        for (k, t) in atlas.texels.iter().enumerate() {
            // The texel's own sample point, on its own triangle.
            let tri = &scene.triangles[t.triangle as usize];
            let (e1, e2) = (tri.p[1] - tri.p[0], tri.p[2] - tri.p[0]);
            let q = t.position - t.geo_normal * atlas.surface_offset - tri.p[0];
            // Barycentric coordinates of q in the triangle's plane.
            let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
            let (q1, q2) = (q.dot(e1), q.dot(e2));
            let den = d11 * d22 - d12 * d12;
            let b1 = (d22 * q1 - d12 * q2) / den;
            let b2 = (d11 * q2 - d12 * q1) / den;
            assert_eq!(
                texel_at(&scene, &atlas, t.triangle, Vec3::new(1.0 - b1 - b2, b1, b2)),
                Some(k as u32)
            );
            assert!(!c.of(k).is_empty());
        }
    }

    #[test]
    fn clipping_keeps_the_part_inside_the_square() {
        let q = [Vec2::new(-1.0, 0.5), Vec2::new(3.0, 0.5), Vec2::new(-1.0, 4.5)];
        let poly = clip_to_square(&q, 0.0, 0.0);
        let area: f32 = (1..poly.len() - 1)
            .map(|k| 0.5 * (poly[k] - poly[0]).perp_dot(poly[k + 1] - poly[0]))
            .sum();
        // The square's part under the line x + y = 3 and above y = 0.5: all of [0,1] x [0.5,1].
        assert!((area.abs() - 0.5).abs() < 1e-6, "{area} {poly:?}");
        assert!(clip_to_square(&q, 5.0, 5.0).is_empty());
    }
}
