//! Texel validation: which texels a lightmap should not trust, and a report on the
//! texel set for the user (issue 13's validation report).
//!
//! How: from every texel's sample point, `RAYS` cosine-distributed rays are cast (the
//! same `engine::raytrace` the reference uses). A texel whose rays meet the back of a
//! single-sided surface more often than [`BACKFACE_TOLERANCE`] of the hits is taken to
//! lie inside closed geometry (a floor texel under a box standing on it, a ceiling
//! texel behind a light panel): it is removed from the texel set, so no technique bakes
//! it, and dilation fills it from its valid neighbours. This is what Unity's "backface
//! tolerance" and Bakery's texel validity do, and removes the black footprints that
//! otherwise bleed into bilinear filtering.
//!
//! The report also gives overlapping texels (charts sharing texels), texel density per
//! mesh (texels per metre, from world area over lightmap-UV area) and its spread, and
//! the memory the texel set takes.
//!
//! Cost (issue 19 point 8): the test stops early where it is clear. After the first
//! [`FIRST_BATCH`] rays a texel that met no back face is valid, and one whose hits were
//! all back faces (at least 8 of them) is inside; only the mixed ones trace all [`RAYS`].
//! Most texels of a level are one or the other, so validation costs about a quarter of
//! the rays (measured in docs/performance.md). The price: a texel whose true back-face
//! fraction is just over the tolerance can pass on its first 16 rays, with probability
//! 0.9^16 = 19 % at a fraction of 0.1, 2.8 % at 0.2 and 0.3 % at 0.3 (texels at the
//! edge of a box standing on a floor, which dilation then lights like their
//! neighbours).
//!
//! Routes: this module traces on the CPU; on a hardware GPU `engine::job` traces the same
//! rays (the stream and decision helpers below) through the GPU's BVH query pass instead
//! (`gpu::validate`), and hands the fractions to [`validate_from`].
//!
//! Limits: double-sided surfaces have no inside, so a texel inside a closed double-sided
//! mesh is not detected; 64 rays miss openings narrower than about 1/8 of the
//! hemisphere's projected area.

use rayon::prelude::*;
use serde::Serialize;

use super::{Atlas, NO_TEXEL, Texel};
use crate::engine::raytrace::{Tracer, cosine_sample};
use crate::engine::rng::Rng;
use crate::engine::scene::Scene;

/// Rays per texel for the inside-geometry test, at most.
pub const RAYS: u32 = 64;

/// Rays after which a texel whose hits were all front faces (or misses), or all back
/// faces (at least half of them hits), is decided without the rest (module doc).
pub const FIRST_BATCH: u32 = 16;

/// Largest fraction of back-face hits a valid texel may have (Unity's default backface
/// tolerance of 90 % front faces, expressed the other way round).
pub const BACKFACE_TOLERANCE: f32 = 0.1;

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct MeshDensity {
    pub mesh: String,
    /// Texels per metre along a surface (square root of texels per m²).
    pub texels_per_metre: f32,
}

#[derive(Clone, Debug, Serialize)]
pub struct ValidationReport {
    pub valid_texels: usize,
    /// Texels whose rays mostly met back faces: inside closed geometry, removed.
    pub inside_geometry_texels: usize,
    /// Texels claimed by more than one triangle (overlapping charts).
    pub overlapping_texels: u32,
    /// Texels a chart touches without covering the centre (filled by dilation).
    pub partially_covered_texels: usize,
    pub density: Vec<MeshDensity>,
    /// Largest over smallest texel density across meshes (1 = uniform).
    pub density_spread: f32,
    /// Bytes of the texel set (positions, normals, albedo, emission) as techniques upload it.
    pub texel_set_bytes: usize,
    pub warnings: Vec<String>,
}

/// The stream of the test rays of the texel at `pixel`: ray `i` takes the `i`-th pair of
/// its numbers ([`test_direction`]), so the GPU route (`gpu::validate`) casts the very
/// rays the CPU does and decides the same. Keyed by pixel, not by the texel's place in
/// the list, so a task validating one region of the grid (`job::prepare_regions`)
/// decides each texel as the whole grid's validation does.
pub fn texel_rng(pixel: u32) -> Rng {
    Rng::new(0x7a11d, u64::from(pixel), 0, 0)
}

/// The next test ray's direction from `t`'s sample point, or `None` when it points below
/// the geometric plane (skipped: neither a hit nor a miss).
pub fn test_direction(t: &Texel, rng: &mut Rng) -> Option<glam::Vec3> {
    let d = cosine_sample(t.normal, rng.next_f32(), rng.next_f32());
    (d.dot(t.geo_normal) > 0.0).then_some(d)
}

/// Whether the hit triangle `tri` is met from behind by direction `d` and is
/// single-sided: a back face that says the texel is inside.
pub fn is_back_face(scene: &Scene, tri: u32, d: glam::Vec3) -> bool {
    let tri = &scene.triangles[tri as usize];
    d.dot(tri.cross()) > 0.0 && !scene.material(tri).double_sided
}

/// Whether a texel is decided after the first batch (the sequential stop of the module
/// doc): it met no back face, or nothing but back faces.
pub fn decided_after_first_batch(hits: u32, back: u32) -> bool {
    back == 0 || (back == hits && hits >= FIRST_BATCH / 2)
}

/// Fraction of hits that are back faces of single-sided surfaces, per texel.
pub fn backface_fractions(scene: &Scene, tracer: &Tracer, texels: &[Texel]) -> Vec<f32> {
    texels
        .par_iter()
        .map(|t| {
            let mut rng = texel_rng(t.pixel);
            let (mut hits, mut back) = (0u32, 0u32);
            for ray in 0..RAYS {
                if ray == FIRST_BATCH && decided_after_first_batch(hits, back) {
                    break;
                }
                let Some(d) = test_direction(t, &mut rng) else {
                    continue;
                };
                if let Some(h) = tracer.trace(scene, t.position, d, f32::INFINITY) {
                    hits += 1;
                    if is_back_face(scene, h.triangle, d) {
                        back += 1;
                    }
                }
            }
            if hits == 0 { 0.0 } else { back as f32 / hits as f32 }
        })
        .collect()
}

/// Validates `atlas` in place (removing texels inside geometry) and reports.
pub fn validate(scene: &Scene, atlas: &mut Atlas) -> ValidationReport {
    validate_with(scene, &Tracer::new(scene), atlas)
}

/// [`validate`] with the scene's BVH already built (a bake's, shared with its passes).
pub fn validate_with(scene: &Scene, tracer: &Tracer, atlas: &mut Atlas) -> ValidationReport {
    let fractions = backface_fractions(scene, tracer, &atlas.texels);
    validate_from(scene, atlas, &fractions)
}

/// [`validate`] from the texels' back-face fractions, however they were measured (the CPU
/// route above or the GPU's, `gpu::validate`).
pub fn validate_from(scene: &Scene, atlas: &mut Atlas, fractions: &[f32]) -> ValidationReport {
    let inside: Vec<bool> = fractions.iter().map(|f| *f > BACKFACE_TOLERANCE).collect();
    let inside_count = inside.iter().filter(|i| **i).count();
    if inside_count > 0 && inside_count < atlas.texels.len() {
        atlas.inside_pixels = atlas
            .texels
            .iter()
            .zip(&inside)
            .filter(|(_, i)| **i)
            .map(|(t, _)| t.pixel)
            .collect();
        atlas.remove_texels(&inside);
    }
    let density = mesh_density(scene, atlas);
    let (lo, hi) = density
        .iter()
        .map(|d| d.texels_per_metre)
        .filter(|d| *d > 0.0)
        .fold((f32::INFINITY, 0.0f32), |(lo, hi), d| (lo.min(d), hi.max(d)));
    let density_spread = if hi > 0.0 { hi / lo } else { 1.0 };
    let mut warnings = Vec::new();
    if atlas.overlapping_texels > 0 {
        warnings.push(format!(
            "{} texels are covered by more than one triangle: lightmap UV charts overlap",
            atlas.overlapping_texels
        ));
    }
    if inside_count > 0 {
        warnings.push(format!(
            "{inside_count} texels lie inside closed geometry (more than {:.0} % of their rays hit back faces) and are filled by dilation",
            BACKFACE_TOLERANCE * 100.0
        ));
    }
    if density_spread > 4.0 {
        warnings.push(format!("texel density varies {density_spread:.1}x across meshes"));
    }
    let report = ValidationReport {
        valid_texels: atlas.texels.len(),
        inside_geometry_texels: inside_count,
        overlapping_texels: atlas.overlapping_texels,
        partially_covered_texels: atlas.links.len(),
        density,
        density_spread,
        texel_set_bytes: atlas.texels.len() * std::mem::size_of::<Texel>(),
        warnings,
    };
    atlas.validation = Some(report.clone());
    report
}

fn mesh_density(scene: &Scene, atlas: &Atlas) -> Vec<MeshDensity> {
    let texel_area = 1.0 / (atlas.width as f64 * atlas.height as f64);
    let mut world = vec![0.0f64; scene.meshes.len()];
    let mut uv = vec![0.0f64; scene.meshes.len()];
    for t in &scene.triangles {
        world[t.mesh as usize] += t.area() as f64;
        uv[t.mesh as usize] += 0.5 * ((t.lm[1] - t.lm[0]).perp_dot(t.lm[2] - t.lm[0]) as f64).abs();
    }
    scene
        .meshes
        .iter()
        .enumerate()
        .filter(|(i, _)| world[*i] > 0.0)
        .map(|(i, m)| MeshDensity {
            mesh: if m.name.is_empty() {
                format!("mesh {i}")
            } else {
                m.name.clone()
            },
            texels_per_metre: ((uv[i] / texel_area) / world[i]).sqrt() as f32,
        })
        .collect()
}

impl Atlas {
    /// Drops the texels marked in `remove` (indexed like `texels`); their pixels become
    /// empty, to be filled by dilation, and gutter links to them are dropped.
    pub fn remove_texels(&mut self, remove: &[bool]) {
        let mut remap = vec![NO_TEXEL; self.texels.len()];
        let mut kept = Vec::with_capacity(self.texels.len());
        for (k, t) in self.texels.iter().enumerate() {
            if !remove[k] {
                remap[k] = kept.len() as u32;
                kept.push(*t);
            }
        }
        self.pixel_texel.remap(|k| remap[k as usize]);
        self.links.retain_mut(|l| {
            l.texel = remap[l.texel as usize];
            l.texel != NO_TEXEL
        });
        self.texels = kept;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::scene::build::{MaterialDesc, SceneBuilder};
    use crate::engine::scene::import_slice;
    use glam::Vec3;

    #[test]
    fn texels_under_a_box_are_inside_geometry() {
        // A 4 m floor with a closed-topped box (no bottom) of 1 m standing on its centre.
        let mut b = SceneBuilder::new();
        let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
        b.square("floor", Vec3::ZERO, 4.0, Vec3::Y, m);
        b.block("box", Vec3::ZERO, Vec3::splat(0.5), 0.0, m);
        let scene = import_slice(&b.to_glb(), None).unwrap().0;
        let mut atlas = Atlas::build(&scene, 96, 96).unwrap();
        let before = atlas.texels.len();
        let offset = scene.origin_offset.as_vec3();
        let report = validate(&scene, &mut atlas);
        assert!(report.inside_geometry_texels > 0);
        assert_eq!(atlas.texels.len(), before - report.inside_geometry_texels);
        // No remaining floor texel lies under the box (|x|, |z| < 0.45).
        for t in &atlas.texels {
            let p = t.position + offset;
            if t.geo_normal.y > 0.99 && p.y.abs() < 0.01 {
                assert!(p.x.abs() > 0.45 || p.z.abs() > 0.45, "floor texel under the box at {p}");
            }
        }
        // The floor's footprint under the box is (1/4)² of the floor: about that share of
        // the floor's texels went (the floor's chart is one of six here).
        let floor_texels = before / 6;
        let share = report.inside_geometry_texels as f32 / floor_texels as f32;
        assert!((0.04..0.09).contains(&share), "{share}");
        assert!(report.warnings.iter().any(|w| w.contains("inside closed geometry")));
        // Pixel and link tables stay consistent.
        for (k, t) in atlas.texels.iter().enumerate() {
            assert_eq!(atlas.pixel_texel[t.pixel as usize], k as u32);
        }
        assert!(atlas.links.iter().all(|l| (l.texel as usize) < atlas.texels.len()));
    }

    #[test]
    fn open_scene_loses_nothing_and_density_is_reported() {
        let mut b = SceneBuilder::new();
        let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
        b.square("small", Vec3::ZERO, 1.0, Vec3::Y, m);
        b.square("large", Vec3::new(5.0, 0.0, 0.0), 4.0, Vec3::Y, m);
        let scene = import_slice(&b.to_glb(), None).unwrap().0;
        let mut atlas = Atlas::build(&scene, 64, 64).unwrap();
        let report = validate(&scene, &mut atlas);
        assert_eq!(report.inside_geometry_texels, 0);
        // Equal cells for a 1 m and a 4 m square: densities differ by 4.
        assert!((report.density_spread - 4.0).abs() < 0.01, "{}", report.density_spread);
        assert_eq!(report.density.len(), 2);
    }
}
