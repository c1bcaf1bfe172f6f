//! Where probes go when the job does not list them (issue 26 point 1): a uniform grid, or
//! an adaptive set that is denser near geometry.
//!
//! # Grid
//! Cells of side `spacing` over the scene's bounds, a probe at each cell's centre.
//!
//! # Adaptive (`subdivide` L > 0)
//! An octree over the same grid, as Godot's LightmapGI `generate_probes_subdiv` does: a cell
//! that a triangle of the scene passes through is split into its 8 children, down to L
//! levels (cells of side spacing / 2^L); a probe goes at the centre of every leaf, so open
//! space keeps the coarse spacing and the probes crowd where the light changes fastest,
//! at surfaces (contact shadows, colour bleeding, the step in irradiance across a wall's
//! edge). Whether that pays is measured, not assumed: `examples/probe_density.rs` compares
//! the error of probes interpolated at random points against a uniform grid of as many
//! probes (docs/probes.md, *Adaptive density*).
//!
//! "Passes through" is exact: the triangle clipped to the cell's box (Sutherland-Hodgman
//! against its six planes, a few lines; a library for one clip would be more code than the
//! clip) leaves something. Candidates per level: each triangle's bounding box picks the
//! cells it spans whose parent was split, so a level costs a pass over the triangles, not
//! over the cells. Probes in cells at the finest level may sit inside geometry: the
//! baker's inside test removes them as it does for the grid.
//!
//! Limits: at most `max` probes (the job's [`super::probes::MAX_PROBES`]), checked level by
//! level before the next level is built; at most [`MAX_SUBDIVIDE`] levels.

use std::collections::HashSet;

use glam::{IVec3, Vec3};

use crate::engine::error::EngineError;
use crate::engine::scene::Scene;

/// The most octree levels below the grid.
pub const MAX_SUBDIVIDE: u32 = 4;

/// Positions of a grid of cells of side `spacing` over the scene's bounds (cell centres),
/// at most `max` of them.
pub fn grid_positions(scene: &Scene, spacing: f32, max: usize) -> Result<Vec<Vec3>, EngineError> {
    adaptive_positions(scene, spacing, 0, max)
}

/// The grid of [`grid_positions`] with every cell a triangle passes through split into 8,
/// `subdivide` levels down; probes at the leaves' centres (module doc), at most `max`.
pub fn adaptive_positions(scene: &Scene, spacing: f32, subdivide: u32, max: usize) -> Result<Vec<Vec3>, EngineError> {
    if !(spacing.is_finite() && spacing > 0.0) {
        return Err(EngineError::BadInput(format!(
            "probes.spacing must be a positive distance, got {spacing}"
        )));
    }
    if subdivide > MAX_SUBDIVIDE {
        return Err(EngineError::BadInput(format!(
            "probes.subdivide must be in 0..={MAX_SUBDIVIDE}, got {subdivide}"
        )));
    }
    let Some((lo, hi)) = bounds(scene) else {
        return Ok(vec![Vec3::ZERO]);
    };
    let cells = ((hi - lo) / spacing).ceil().max(Vec3::ONE);
    let count = cells.x as f64 * cells.y as f64 * cells.z as f64;
    if count > max as f64 {
        return Err(EngineError::BadInput(format!(
            "probes.spacing {spacing} makes {count} probes over the scene's bounds; at most {max}"
        )));
    }
    let size = (hi - lo) / cells;
    let n = cells.as_ivec3();
    let centre = |level: u32, c: IVec3| lo + size / (1 << level) as f32 * (c.as_vec3() + 0.5);
    // Cells split at the level above (none above the grid: every grid cell is a candidate).
    let mut split: HashSet<IVec3> = HashSet::new();
    let mut out = Vec::new();
    for level in 0..=subdivide {
        let side = size / (1 << level) as f32;
        let dims = n * (1 << level);
        // This level's cells: the grid, or the 8 children of each cell split above.
        let here: Vec<IVec3> = if level == 0 {
            (0..n.z)
                .flat_map(|k| (0..n.y).flat_map(move |j| (0..n.x).map(move |i| IVec3::new(i, j, k))))
                .collect()
        } else {
            let mut v: Vec<IVec3> = split
                .iter()
                .flat_map(|p| (0..8).map(move |b| *p * 2 + IVec3::new(b & 1, (b >> 1) & 1, b >> 2)))
                .collect();
            v.sort_by_key(|c| (c.z, c.y, c.x));
            v
        };
        let candidates: HashSet<IVec3> = here.iter().copied().collect();
        // The cells of this level a triangle passes through, unless this is the last level.
        let mut crossed = HashSet::new();
        if level < subdivide {
            for t in &scene.triangles {
                let (tmin, tmax) = (t.p[0].min(t.p[1]).min(t.p[2]), t.p[0].max(t.p[1]).max(t.p[2]));
                let a = ((tmin - lo) / side).floor().as_ivec3().clamp(IVec3::ZERO, dims - 1);
                let b = ((tmax - lo) / side).floor().as_ivec3().clamp(IVec3::ZERO, dims - 1);
                for z in a.z..=b.z {
                    for y in a.y..=b.y {
                        for x in a.x..=b.x {
                            let c = IVec3::new(x, y, z);
                            if candidates.contains(&c) && !crossed.contains(&c) {
                                let box_lo = lo + side * c.as_vec3();
                                if triangle_meets_box(t.p, box_lo, box_lo + side) {
                                    crossed.insert(c);
                                }
                            }
                        }
                    }
                }
            }
        }
        out.extend(here.iter().filter(|c| !crossed.contains(c)).map(|c| centre(level, *c)));
        if out.len() + 8 * crossed.len() > max {
            return Err(EngineError::BadInput(format!(
                "probes.spacing {spacing} with subdivide {subdivide} makes {}{} probes; at most {max}: \
                 raise the spacing or lower subdivide",
                if level < subdivide { "at least " } else { "" },
                out.len() + 8 * crossed.len(),
            )));
        }
        split = crossed;
    }
    Ok(out)
}

/// The scene's bounding box, `None` without triangles.
pub(super) fn bounds(scene: &Scene) -> Option<(Vec3, Vec3)> {
    let mut points = scene.triangles.iter().flat_map(|t| t.p);
    let first = points.next()?;
    Some(points.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p))))
}

/// How far a ray starts off a surface when no atlas gives the offset (light probes, the
/// feedback gain): relative to the scene's size, far below any feature.
pub(super) fn scene_ray_offset(scene: &Scene) -> f32 {
    bounds(scene).map_or(1e-4, |(lo, hi)| ((hi - lo).length() * 1e-5).max(1e-6))
}

/// True when the triangle `p` and the box [lo, hi] share a point: the triangle clipped
/// by the box's six planes is not empty.
fn triangle_meets_box(p: [Vec3; 3], lo: Vec3, hi: Vec3) -> bool {
    let mut poly: Vec<Vec3> = p.to_vec();
    for axis in 0..3 {
        for (bound, keep_below) in [(lo[axis], false), (hi[axis], true)] {
            // Signed distance inside the half-space (>= 0 is kept).
            let inside = |v: Vec3| if keep_below { bound - v[axis] } else { v[axis] - bound };
            let mut next = Vec::with_capacity(poly.len() + 1);
            for i in 0..poly.len() {
                let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
                let (da, db) = (inside(a), inside(b));
                if da >= 0.0 {
                    next.push(a);
                }
                if (da >= 0.0) != (db >= 0.0) {
                    next.push(a + (b - a) * (da / (da - db)));
                }
            }
            if next.is_empty() {
                return false;
            }
            poly = next;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clip_finds_what_a_triangle_crosses_and_only_that() {
        let (lo, hi) = (Vec3::ZERO, Vec3::ONE);
        // Through the middle, though every vertex is outside the box.
        let through = [
            Vec3::new(-1.0, 0.5, -1.0),
            Vec3::new(3.0, 0.5, -1.0),
            Vec3::new(-1.0, 0.5, 3.0),
        ];
        assert!(triangle_meets_box(through, lo, hi));
        // Its bounding box overlaps the box; the triangle (in the plane x + y = 2.5) passes
        // beside the box's edge at x = y = 1.
        let beside = [
            Vec3::new(2.5, 0.0, 0.2),
            Vec3::new(0.0, 2.5, 0.2),
            Vec3::new(0.0, 2.5, 0.8),
        ];
        assert!(!triangle_meets_box(beside, lo, hi));
        // The same triangle moved to x + y = 1.9 cuts the corner.
        let cutting = beside.map(|v| v - Vec3::new(0.3, 0.3, 0.0));
        assert!(triangle_meets_box(cutting, lo, hi));
        // One vertex inside.
        assert!(triangle_meets_box(
            [Vec3::splat(0.5), Vec3::splat(5.0), Vec3::new(5.0, 0.0, 5.0)],
            lo,
            hi
        ));
        // Touching a face counts (a floor on a cell boundary splits the cells on both sides).
        assert!(triangle_meets_box(
            [
                Vec3::new(-1.0, 1.0, -1.0),
                Vec3::new(3.0, 1.0, -1.0),
                Vec3::new(-1.0, 1.0, 3.0)
            ],
            lo,
            hi
        ));
    }
}
