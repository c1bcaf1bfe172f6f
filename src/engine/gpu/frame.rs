//! The normalised scene frame every GPU technique works in: positions are uploaded as
//! (p − centre) / radius of the bounding sphere of the scene's triangles and texels, so
//! every epsilon in the shaders is relative to the scene's size, and a scene translated by
//! 1e5 or scaled by 1e-3 or 1e4 gives the same numbers (DESIGN §5).
//!
//! The bounds are those of the triangles' corners and the texels' sample points (plus
//! whatever a technique adds, e.g. `sdf`'s movable shapes). An empty scene gets the unit
//! frame at the origin; the radius never falls below 1e6 × the smallest positive f32, so
//! the division is always finite.

use glam::Vec3;

use crate::engine::atlas::Atlas;
use crate::engine::scene::Scene;

/// Bounds and the normalisation derived from them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneFrame {
    /// World-space bounds of everything the frame covers (both zero when empty).
    pub lo: Vec3,
    pub hi: Vec3,
    pub centre: Vec3,
    /// Half the bounds' diagonal: the bounding sphere's radius about `centre`.
    pub radius: f32,
}

impl SceneFrame {
    /// The frame of a set of world-space points.
    pub fn of_points(points: impl IntoIterator<Item = Vec3>) -> Self {
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for p in points {
            lo = lo.min(p);
            hi = hi.max(p);
        }
        if lo.x > hi.x {
            (lo, hi) = (Vec3::ZERO, Vec3::ZERO);
        }
        let centre = (lo + hi) * 0.5;
        let radius = ((hi - lo).length() * 0.5).max(f32::MIN_POSITIVE * 1e6);
        SceneFrame { lo, hi, centre, radius }
    }

    /// The frame of the scene's triangles grown by `margin` on every side: one that
    /// holds every texel sample point of any atlas of the scene when `margin` is at least
    /// the atlas's surface offset (a sample point is that far off its triangle, along the
    /// normal), and is the same for the whole grid and a region of it (`vpl`'s page tasks
    /// bake exactly a single bake's texels of their page, `engine::tasks`).
    pub fn of_scene(scene: &Scene, margin: f32) -> Self {
        let f = Self::of_points(scene.triangles.iter().flat_map(|t| t.p));
        if scene.triangles.is_empty() {
            return f;
        }
        Self::of_points([f.lo - Vec3::splat(margin), f.hi + Vec3::splat(margin)])
    }

    /// The frame of the scene's triangles and the atlas's texel sample points.
    pub fn of(scene: &Scene, atlas: &Atlas) -> Self {
        Self::of_points(
            scene
                .triangles
                .iter()
                .flat_map(|t| t.p)
                .chain(atlas.texels.iter().map(|t| t.position)),
        )
    }

    /// A world-space point in the normalised frame.
    pub fn norm(&self, p: Vec3) -> Vec3 {
        (p - self.centre) / self.radius
    }

    /// The eight corners of the bounds, in the normalised frame (bit i of the index picks
    /// the upper bound of axis i).
    pub fn corners(&self) -> [Vec3; 8] {
        let (nlo, nhi) = (self.norm(self.lo), self.norm(self.hi));
        std::array::from_fn(|i| {
            Vec3::new(
                if i & 1 == 0 { nlo.x } else { nhi.x },
                if i & 2 == 0 { nlo.y } else { nhi.y },
                if i & 4 == 0 { nlo.z } else { nhi.z },
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalised_frame_is_translation_and_scale_invariant() {
        let pts = [
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(4.0, -2.0, 5.0),
            Vec3::new(0.5, 0.0, 3.5),
        ];
        let a = SceneFrame::of_points(pts);
        let b = SceneFrame::of_points(pts.map(|p| p * 1e4 + Vec3::splat(1e5)));
        for p in pts {
            let (na, nb) = (a.norm(p), b.norm(p * 1e4 + Vec3::splat(1e5)));
            assert!((na - nb).abs().max_element() < 1e-3, "{na} vs {nb}");
            assert!(na.length() <= 1.0 + 1e-6);
        }
        let empty = SceneFrame::of_points([]);
        assert_eq!(empty.centre, Vec3::ZERO);
        assert!(empty.radius > 0.0 && empty.norm(Vec3::ONE).is_finite());
    }
}
