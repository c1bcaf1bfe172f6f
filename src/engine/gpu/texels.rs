//! The valid texels' geometry as every GPU technique uploads it (`TexelGeom` in
//! `shaders/gpu/common.wgsl`): sample point in the normalised frame, unit shading normal
//! (the hemisphere the texel integrates) and unit geometric normal (the plane below which
//! samples are rejected), compact over valid texels in atlas order.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::engine::gpu::frame::SceneFrame;

/// One texel's geometry, 48 bytes (three vec4 in WGSL's storage layout).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuTexelGeom {
    pub position: [f32; 4],
    pub normal: [f32; 4],
    pub geo_normal: [f32; 4],
}

impl GpuTexelGeom {
    /// A texel at world-space `position` with its normals, in `frame`.
    pub fn new(frame: &SceneFrame, position: Vec3, normal: Vec3, geo_normal: Vec3) -> Self {
        GpuTexelGeom {
            position: frame.norm(position).extend(0.0).to_array(),
            normal: normal.normalize_or_zero().extend(0.0).to_array(),
            geo_normal: geo_normal.normalize_or_zero().extend(0.0).to_array(),
        }
    }
}

/// Every texel of `texels` (position, shading normal, geometric normal) in `frame`.
pub fn texel_geometry<'a>(
    frame: &SceneFrame,
    texels: impl IntoIterator<Item = (Vec3, Vec3, Vec3)> + 'a,
) -> Vec<GpuTexelGeom> {
    texels
        .into_iter()
        .map(|(p, n, g)| GpuTexelGeom::new(frame, p, n, g))
        .collect()
}

/// Every valid texel of `atlas` in world space (the BVH's space, not a normalised frame):
/// what the ray-traced passes (`gpu::direct_light`, `gpu::shadowmask`, `path`) upload. At
/// least one element, so an empty atlas still binds a buffer. `position.w` carries the
/// texel's pixel index as the bits of a u32 (`bitcast<u32>` in WGSL; no float operation
/// touches it, so the bits arrive as written): `path` keys its random streams by it, so a
/// task baking one region of the grid draws the samples a whole bake draws there.
pub fn world_texels(atlas: &crate::engine::atlas::Atlas) -> Vec<GpuTexelGeom> {
    let mut geom: Vec<GpuTexelGeom> = atlas
        .texels
        .iter()
        .map(|t| GpuTexelGeom {
            position: t.position.extend(f32::from_bits(t.pixel)).to_array(),
            normal: t.normal.normalize_or_zero().extend(0.0).to_array(),
            geo_normal: t.geo_normal.normalize_or_zero().extend(0.0).to_array(),
        })
        .collect();
    if geom.is_empty() {
        geom.push(GpuTexelGeom::zeroed());
    }
    geom
}
