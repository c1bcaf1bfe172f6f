//! The scene as rays shade it, on the GPU: the BVH (`gpu::bvh`), every triangle slot's
//! shading data, and one table buffer with the materials, the punctual and directional
//! lights, the emitter CDF and the textures, plus the uniform with the sky, the sun and
//! the table offsets. `shaders/gpu/lights.wgsl` reads them (bindings 0-4: BVH nodes, BVH
//! triangles, [`SceneUniform`], shading, tables) and does next-event estimation to the
//! lights; `path` on the GPU and the shared direct-light pass (`gpu::direct_light`) both
//! compose it, so the two sample light the same way.
//!
//! How: the BVH, the shading data and the tables are the bake's shared uploads
//! (`gpu::scene_rays`: uploaded once per bake, whatever number of passes read them);
//! each pass has its own [`SceneUniform`]: the table offsets, the sky, the sun and
//! [`LightSources`], which of the lights it estimates (a technique that finds emitters or
//! the sun with its own rays leaves those out). Emitters are picked with the CPU's
//! [`EmitterTable`] probabilities.
//!
//! Limits: those of `gpu::scene_rays` (the storage-binding limit on every buffer).

use std::sync::Arc;

use glam::Vec3;

use super::bvh::GpuBvh;
use super::layout::Bind;
use super::scene_rays::{GpuTables, SceneRays};
use super::{GpuContext, GpuError};
use crate::engine::raytrace::EmitterTable;
use crate::engine::scene::{Hemisphere, LightKind, Lighting, Scene};

/// Which light a pass estimates by next-event estimation (`LIGHTS_*` in
/// `shaders/gpu/lights.wgsl`); the sky is never sampled this way (techniques and `path`
/// find it with their own rays).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LightSources(pub u32);

impl LightSources {
    pub const DIRECTIONAL: LightSources = LightSources(1);
    pub const PUNCTUAL: LightSources = LightSources(2);
    pub const SUN: LightSources = LightSources(4);
    pub const EMITTERS: LightSources = LightSources(8);
    pub const ALL: LightSources = LightSources(15);
    pub const NONE: LightSources = LightSources(0);

    pub fn with(self, other: LightSources) -> LightSources {
        LightSources(self.0 | other.0)
    }

    pub fn contains(self, other: LightSources) -> bool {
        self.0 & other.0 == other.0
    }

    /// The sources among these that this scene and lighting have at all.
    pub fn present(self, scene: &Scene, lighting: &Lighting, emitters: &EmitterTable) -> LightSources {
        let mut out = LightSources::NONE;
        let has = |k: fn(&LightKind) -> bool| scene.lights.iter().any(|l| k(&l.kind));
        if has(|k| matches!(k, LightKind::Directional)) {
            out = out.with(LightSources::DIRECTIONAL);
        }
        if has(|k| !matches!(k, LightKind::Directional)) {
            out = out.with(LightSources::PUNCTUAL);
        }
        if lighting.sun.is_some() {
            out = out.with(LightSources::SUN);
        }
        if !emitters.emitters.is_empty() {
            out = out.with(LightSources::EMITTERS);
        }
        LightSources(out.0 & self.0)
    }
}

/// `SceneUniform` of `shaders/gpu/lights.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct SceneUniform {
    tables: [u32; 4],
    tables2: [u32; 4],
    sky: [f32; 4],
    sun_axis: [f32; 4],
    sun: [f32; 4],
}

/// The scene's rays and light on the GPU: bindings 0-4 of every pass composed with
/// `gpu/bvh.wgsl` and `gpu/lights.wgsl` ([`GpuSceneLights::binds`]). The BVH and the
/// tables are the bake's shared uploads ([`SceneRays`]); only the uniform (which lights,
/// the sky and the sun) is the pass's own.
pub struct GpuSceneLights {
    pub bvh: Arc<GpuBvh>,
    tables: Arc<GpuTables>,
    uniform: wgpu::Buffer,
}

impl GpuSceneLights {
    /// The scene of `rays` with `emitters` as the pickable emitters and `sources` as the
    /// lights sampled; `what` names the pass in errors and labels.
    pub fn new(
        ctx: &Arc<GpuContext>,
        what: &str,
        rays: &SceneRays,
        lighting: &Lighting,
        emitters: &EmitterTable,
        sources: LightSources,
    ) -> Result<Self, GpuError> {
        let bvh = rays.gpu_bvh(ctx)?;
        let tables = rays.gpu_tables(ctx, what, emitters)?;
        let (sky, sky_mode) = match lighting.sky {
            Some(s) => (s.radiance, if s.hemisphere == Hemisphere::Full { 2.0 } else { 1.0 }),
            None => (Vec3::ZERO, 0.0),
        };
        let (sun_axis, sun) = match &lighting.sun {
            Some(s) => (
                (-s.direction.normalize()).extend(s.cos_half_angle()).to_array(),
                s.radiance.extend(s.solid_angle()).to_array(),
            ),
            None => ([0.0, 1.0, 0.0, 2.0], [0.0; 4]),
        };
        let o = tables.offsets;
        let u = SceneUniform {
            tables: [o[0], o[1], o[2], o[3]],
            tables2: [o[4], o[5], sources.0, 0],
            sky: sky.extend(sky_mode).to_array(),
            sun_axis,
            sun,
        };
        Ok(GpuSceneLights {
            uniform: ctx.uniform(&format!("{what} scene lights"), &u),
            bvh,
            tables,
        })
    }

    /// Bindings 0-4, in the order `gpu/bvh.wgsl` and `gpu/lights.wgsl` declare them.
    pub fn binds(&self) -> [Bind<'_>; 5] {
        [
            Bind::Read(&self.bvh.nodes),
            Bind::Read(&self.bvh.tris),
            Bind::Uniform(&self.uniform),
            Bind::Read(&self.tables.shade),
            Bind::Read(&self.tables.tables),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Rust mirror of the pass's uniform has the shader's size (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[Mirror::of::<SceneUniform>(
            "SceneUniform",
            crate::engine::gpu::shaders::DIRECT_LIGHT,
            "SceneUniform",
        )]);
    }
}
