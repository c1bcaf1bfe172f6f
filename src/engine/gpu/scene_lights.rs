//! The scene as rays shade it, on the GPU: the BVH (`gpu::bvh`), every triangle slot's
//! shading data, and one table buffer with the materials, the punctual and directional
//! lights, the emitter CDF and the textures, plus the uniform with the sky, the sun and
//! the table offsets. `shaders/gpu/lights.wgsl` reads them (bindings 0-4: BVH nodes, BVH
//! triangles, [`SceneUniform`], shading, tables) and does next-event estimation to the
//! lights; `path` on the GPU and the shared direct-light pass (`gpu::direct_light`) both
//! compose it, so the two sample light the same way.
//!
//! How: uploaded once per bake from the CPU scene. Per slot (the BVH's leaf order), 6 vec4:
//! the three shading normals with the material index, the emitter pick probability and
//! the area, then the base-colour and lightmap UVs. Emitters are picked with the CPU's
//! [`EmitterTable`] probabilities; textures are linear RGBA f32, sampled bilinearly with
//! `scene::Texture::sample`'s wrap rules. [`LightSources`] says which of the lights a pass
//! estimates (a technique that finds emitters or the sun with its own rays leaves those
//! out).
//!
//! Limits: every buffer must fit the adapter's storage-binding limit (128 MiB on lavapipe:
//! about 1.4M triangles' shading data, 8M texture texels), checked with an error naming
//! the buffer and the pass that needs it.

use glam::Vec3;
use wgpu::BufferUsages;

use super::bvh::{GpuBvh, check_binding_size};
use super::layout::Bind;
use super::{GpuContext, GpuError};
use crate::engine::raytrace::{EmitterTable, Tracer};
use crate::engine::scene::{Hemisphere, LightKind, Lighting, Scene, Wrap};

fn bits(u: u32) -> f32 {
    f32::from_bits(u)
}

/// The per-slot shading data and the table buffer (materials, lights, emitters, texture
/// headers, texels), with the table offsets.
struct SceneTables {
    shade: Vec<[f32; 4]>,
    tables: Vec<[f32; 4]>,
    /// materials, lights, light count, emitters, emitter count, texture headers.
    offsets: [u32; 6],
}

fn scene_tables(scene: &Scene, emitters: &EmitterTable, slot_ids: &[u32], slot_of: &[u32]) -> SceneTables {
    let mut shade = Vec::with_capacity(slot_ids.len() * 6);
    for &id in slot_ids {
        let t = &scene.triangles[id as usize];
        let pick = emitters.emitter_pick.get(id as usize).copied().unwrap_or(0.0);
        shade.push([t.n[0].x, t.n[0].y, t.n[0].z, bits(t.material)]);
        shade.push([t.n[1].x, t.n[1].y, t.n[1].z, pick]);
        shade.push([t.n[2].x, t.n[2].y, t.n[2].z, t.area()]);
        shade.push([t.uv[0].x, t.uv[0].y, t.uv[1].x, t.uv[1].y]);
        shade.push([t.uv[2].x, t.uv[2].y, t.lm[0].x, t.lm[0].y]);
        shade.push([t.lm[1].x, t.lm[1].y, t.lm[2].x, t.lm[2].y]);
    }
    let mut tables: Vec<[f32; 4]> = Vec::new();
    let mat_off = tables.len() as u32;
    for m in &scene.materials {
        let tex = |r: Option<crate::engine::scene::TextureRef>| r.map_or(u32::MAX, |r| r.texture);
        let set = |r: Option<crate::engine::scene::TextureRef>| r.map_or(0, |r| r.texcoord);
        let c = m.base_color;
        tables.push([c.x, c.y, c.z, bits(tex(m.base_color_texture))]);
        let e = m.emissive;
        tables.push([e.x, e.y, e.z, bits(tex(m.emissive_texture))]);
        tables.push([
            bits(set(m.base_color_texture)),
            bits(set(m.emissive_texture)),
            bits(m.double_sided as u32),
            0.0,
        ]);
    }
    let light_off = tables.len() as u32;
    for l in &scene.lights {
        let (kind, cos_outer, scale) = match l.kind {
            LightKind::Directional => (0u32, 0.0, 0.0),
            LightKind::Point => (1, 0.0, 0.0),
            LightKind::Spot { inner_cone, outer_cone } => (
                2,
                outer_cone.cos(),
                1.0 / (inner_cone.cos() - outer_cone.cos()).max(1e-3),
            ),
        };
        tables.push([l.intensity.x, l.intensity.y, l.intensity.z, bits(kind)]);
        tables.push([l.position.x, l.position.y, l.position.z, l.range.unwrap_or(-1.0)]);
        tables.push([l.direction.x, l.direction.y, l.direction.z, 0.0]);
        tables.push([cos_outer, scale, 0.0, 0.0]);
    }
    let emit_off = tables.len() as u32;
    for (k, &id) in emitters.emitters.iter().enumerate() {
        tables.push([bits(slot_of[id as usize]), emitters.emitter_cdf[k], 0.0, 0.0]);
    }
    let tex_off = tables.len() as u32;
    let mut texel_off = tex_off + scene.textures.len() as u32;
    let wrap = |w: Wrap| match w {
        Wrap::Repeat => 0u32,
        Wrap::Mirror => 1,
        Wrap::Clamp => 2,
    };
    for t in &scene.textures {
        tables.push([
            bits(texel_off),
            bits(t.width),
            bits(t.height),
            bits(wrap(t.wrap_u) | (wrap(t.wrap_v) << 8)),
        ]);
        texel_off += t.texels.len() as u32;
    }
    for t in &scene.textures {
        tables.extend(t.texels.iter().map(|c| c.to_array()));
    }
    SceneTables {
        shade,
        tables,
        offsets: [
            mat_off,
            light_off,
            scene.lights.len() as u32,
            emit_off,
            emitters.emitters.len() as u32,
            tex_off,
        ],
    }
}

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
/// `gpu/bvh.wgsl` and `gpu/lights.wgsl` ([`GpuSceneLights::binds`]).
pub struct GpuSceneLights {
    pub bvh: GpuBvh,
    uniform: wgpu::Buffer,
    shade: wgpu::Buffer,
    tables: wgpu::Buffer,
}

impl GpuSceneLights {
    /// Uploads `scene` with `tracer`'s BVH; `what` names the pass in errors and labels.
    pub fn new(
        ctx: &GpuContext,
        what: &str,
        scene: &Scene,
        lighting: &Lighting,
        tracer: &Tracer,
        emitters: &EmitterTable,
        sources: LightSources,
    ) -> Result<Self, GpuError> {
        let bvh = GpuBvh::new(ctx, tracer.bvh(), scene)?;
        let st = if scene.triangles.is_empty() {
            SceneTables {
                shade: vec![[0.0; 4]; 6],
                tables: vec![[0.0; 4]],
                offsets: [0; 6],
            }
        } else {
            let slot_ids: Vec<u32> = bvh.data.tris.iter().map(|t| t.id).collect();
            scene_tables(scene, emitters, &slot_ids, &bvh.data.slot_of)
        };
        let vec4 = 16u64;
        check_binding_size(
            ctx,
            &format!("{what}: the triangles' shading data"),
            st.shade.len() as u64 * vec4,
        )?;
        check_binding_size(
            ctx,
            &format!("{what}: the materials, lights and textures"),
            st.tables.len() as u64 * vec4,
        )?;
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
        let u = SceneUniform {
            tables: [st.offsets[0], st.offsets[1], st.offsets[2], st.offsets[3]],
            tables2: [st.offsets[4], st.offsets[5], sources.0, 0],
            sky: sky.extend(sky_mode).to_array(),
            sun_axis,
            sun,
        };
        let read = BufferUsages::STORAGE | BufferUsages::COPY_DST;
        Ok(GpuSceneLights {
            uniform: ctx.uniform(&format!("{what} scene lights"), &u),
            shade: ctx.buffer_init(&format!("{what} triangle shading"), &st.shade, read),
            tables: ctx.buffer_init(&format!("{what} scene tables"), &st.tables, read),
            bvh,
        })
    }

    /// Bindings 0-4, in the order `gpu/bvh.wgsl` and `gpu/lights.wgsl` declare them.
    pub fn binds(&self) -> [Bind<'_>; 5] {
        [
            Bind::Read(&self.bvh.nodes),
            Bind::Read(&self.bvh.tris),
            Bind::Uniform(&self.uniform),
            Bind::Read(&self.shade),
            Bind::Read(&self.tables),
        ]
    }
}
