//! Lightmap UV generation for scenes whose meshes have no `TEXCOORD_1`.
//!
//! How: every triangle of the (flattened, world-space) scene goes to an [`Unwrapper`];
//! the one used is the `uvunwrap` crate (region-growing charts within a normal cone,
//! LSCM + ARAP flattening, shape packing), behind this small trait because the crate is
//! young and xatlas-rs does not link here (../shared/NOTES.md). World space means every
//! instance of a mesh gets its own charts, as a lightmap needs. The page is the job's
//! lightmap resolution, with a padding of 3 texels (charts at least 6 apart): enough
//! for the gutter links, bilinear filtering and one mip level, and the dilation fills
//! the rest. `uvunwrap` is built without its `direct-solver` feature: the output is then
//! the same on every CPU, so a lightmap baked on one machine fits UVs made on another.
//!
//! Each mesh's charts are scaled by its `lightmap_scale` (glTF mesh `extras`), the
//! "scale in lightmap" of Unity and Bakery.
//!
//! Limits: all lightmap UVs of the scene are regenerated when any mesh lacks them (the
//! packer cannot place new charts around existing ones); a scene with too many charts
//! for one page at this resolution is an error that says to raise the resolution.

use glam::Vec2;
use serde::Serialize;

use crate::engine::scene::Scene;

/// Padding around each chart, in texels.
pub const PADDING: u32 = 3;

/// One mesh's world-space triangles and its relative texel density.
pub struct UnwrapMesh {
    pub triangles: Vec<[[f32; 3]; 3]>,
    pub scale: f32,
}

/// Meshes in, one lightmap UV per triangle corner out (in [0, 1], DESIGN §2's
/// orientation), in the same order. Charts never span meshes; all share one page.
pub trait Unwrapper {
    fn unwrap(&self, meshes: &[UnwrapMesh], resolution: u32) -> Result<Unwrapped, String>;
}

/// Per mesh, per triangle, the three corners' lightmap UVs; and the report.
pub type Unwrapped = (Vec<Vec<[Vec2; 3]>>, UnwrapReport);

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct UnwrapReport {
    pub charts: u32,
    /// Fraction of the page covered by charts.
    pub utilisation: f32,
    pub texels_per_metre: f32,
}

/// The `uvunwrap` crate.
pub struct UvUnwrap;

impl Unwrapper for UvUnwrap {
    fn unwrap(&self, meshes: &[UnwrapMesh], resolution: u32) -> Result<Unwrapped, String> {
        let positions: Vec<Vec<[f32; 3]>> = meshes
            .iter()
            .map(|m| m.triangles.iter().flatten().copied().collect())
            .collect();
        let indices: Vec<Vec<u32>> = positions.iter().map(|p| (0..p.len() as u32).collect()).collect();
        let inputs: Vec<uvunwrap::MeshInput> = meshes
            .iter()
            .enumerate()
            .map(|(k, m)| {
                let mut input = uvunwrap::MeshInput::new(&positions[k], &indices[k]);
                input.scale = m.scale;
                input
            })
            .collect();
        let options = uvunwrap::Options {
            density: uvunwrap::Density::Auto { page_size: resolution },
            padding: PADDING,
            ..Default::default()
        };
        let atlas = uvunwrap::generate(&inputs, &options).map_err(|e| e.to_string())?;
        if atlas.page_count > 1 {
            return Err(format!(
                "{} charts do not fit one {resolution}x{resolution} lightmap: raise the resolution",
                atlas.chart_count
            ));
        }
        // A cropped page is shorter than it is wide: v is relative to its height.
        let v_scale = atlas.height as f32 / resolution as f32;
        let u_scale = atlas.width as f32 / resolution as f32;
        let out = atlas
            .meshes
            .iter()
            .zip(meshes)
            .map(|(mesh, input)| {
                let uv = |i: u32| {
                    let v = &mesh.vertices[mesh.indices[i as usize] as usize];
                    Vec2::new(v.uv[0] * u_scale, v.uv[1] * v_scale).clamp(Vec2::ZERO, Vec2::ONE)
                };
                (0..input.triangles.len() as u32)
                    .map(|t| [uv(3 * t), uv(3 * t + 1), uv(3 * t + 2)])
                    .collect()
            })
            .collect();
        Ok((
            out,
            UnwrapReport {
                charts: atlas.chart_count,
                utilisation: atlas.utilization * (u_scale * v_scale),
                texels_per_metre: atlas.texels_per_unit,
            },
        ))
    }
}

/// Gives every triangle of `scene` a generated lightmap UV for a `resolution`² lightmap.
pub fn generate_lightmap_uvs(
    scene: &mut Scene,
    resolution: u32,
    unwrapper: &dyn Unwrapper,
) -> Result<UnwrapReport, String> {
    // Group triangles by mesh (each mesh's charts get its own density), remembering where
    // each triangle came from.
    let mut groups: Vec<(usize, UnwrapMesh, Vec<usize>)> = Vec::new();
    let mut slot = std::collections::HashMap::new();
    for (i, t) in scene.triangles.iter().enumerate() {
        let g = *slot.entry(t.mesh).or_insert_with(|| {
            let scale = scene.meshes.get(t.mesh as usize).map_or(1.0, |m| m.lightmap_scale);
            groups.push((
                t.mesh as usize,
                UnwrapMesh {
                    triangles: Vec::new(),
                    scale,
                },
                Vec::new(),
            ));
            groups.len() - 1
        });
        groups[g].1.triangles.push(t.p.map(|p| p.to_array()));
        groups[g].2.push(i);
    }
    let meshes: Vec<UnwrapMesh> = groups
        .iter_mut()
        .map(|g| {
            std::mem::replace(
                &mut g.1,
                UnwrapMesh {
                    triangles: Vec::new(),
                    scale: 1.0,
                },
            )
        })
        .collect();
    let (uvs, report) = unwrapper.unwrap(&meshes, resolution)?;
    for ((_, _, tris), mesh_uvs) in groups.iter().zip(uvs) {
        for (i, uv) in tris.iter().zip(mesh_uvs) {
            scene.triangles[*i].lm = uv;
        }
    }
    scene.needs_lightmap_uvs = false;
    Ok(report)
}
