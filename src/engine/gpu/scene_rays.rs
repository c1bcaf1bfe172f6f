//! The scene as rays see it, built once per bake and shared by every pass of that bake:
//! the CPU BVH ([`Tracer`]) and the emitter table, and on the GPU the BVH's nodes and
//! triangles, every triangle slot's shading data with the material, light, emitter and
//! texture tables, and the valid texels in world space. The technique, its shared
//! direct-light pass (`gpu::direct_light`), the shadowmask pass (`gpu::shadowmask`), the
//! control texels' `path` and the texel validation all ask one [`SceneRays`] for these,
//! so a bake builds the BVH once and holds the scene on the GPU once (issue 18 point 2).
//!
//! How: everything is built on first use and kept. The CPU parts live in `OnceLock`s; the
//! GPU parts in one cache for one device (the bake's, normally `gpu::shared`; a pass on
//! another device gets its own uploads, not cached). The shading data depends on which
//! emitters a pass may pick (a pass that gathers some emitters itself samples only the
//! rest, with their own probabilities), so it is kept per emitter set: one entry for
//! almost every bake, two when `obscurance` samples only its small emitters. Texel
//! buffers are kept per texel set (the bake's atlas, the control texels' sub-atlas),
//! known by its `Arc`, and held weakly so a dropped atlas is not kept alive.
//!
//! Per slot (the BVH's leaf order), 6 vec4: the three shading normals with the material
//! index, the emitter pick probability and the area, then the base-colour and lightmap
//! UVs. The tables: row 0 the offsets of the materials and texture headers, then the
//! materials (4 rows each, with glTF alpha), lights, emitters, texture headers and
//! texels. Textures are linear RGBA f32, sampled bilinearly with
//! `scene::Texture::sample`'s wrap rules. `shaders/gpu/materials.wgsl` and
//! `shaders/gpu/lights.wgsl` read these layouts; the raster passes that alpha-test
//! (shadow atlas, sdb, obscurance) bind the tables alone.
//!
//! Limits: every buffer must fit the adapter's storage-binding limit (128 MiB on lavapipe:
//! about 1.4M triangles' shading data, 8M texture texels), checked with an error naming
//! the buffer and the pass that first needed it. The cache lives as long as the bake's
//! [`SceneRays`]; nothing is evicted during a bake.

use std::sync::{Arc, Mutex, OnceLock, Weak};

use wgpu::BufferUsages;

use super::bvh::{GpuBvh, check_binding_size};
use super::texels::world_texels;
use super::{GpuContext, GpuError};
use crate::engine::atlas::Atlas;
use crate::engine::raytrace::{EmitterTable, Tracer};
use crate::engine::scene::{AlphaMode, LightKind, Scene, TextureRef, Wrap};

fn bits(u: u32) -> f32 {
    f32::from_bits(u)
}

/// The shading data and tables of one emitter set on the GPU, with the tables' offsets
/// (materials, lights, light count, emitters, emitter count, texture headers).
pub struct GpuTables {
    pub shade: wgpu::Buffer,
    pub tables: wgpu::Buffer,
    pub offsets: [u32; 6],
}

/// What one bake shares of its scene's ray-tracing structures (see the module doc).
pub struct SceneRays {
    scene: Arc<Scene>,
    tracer: OnceLock<Arc<Tracer>>,
    emitters: OnceLock<Arc<EmitterTable>>,
    gpu: Mutex<GpuCache>,
    built: Mutex<Builds>,
}

/// How many times each structure was built or uploaded: what the sharing saves is
/// checked on these (`tests/direct_light.rs`) and logged at the end of a bake.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Builds {
    pub cpu_bvh: u32,
    pub gpu_bvh: u32,
    pub gpu_tables: u32,
    pub gpu_texels: u32,
}

#[derive(Default)]
struct GpuCache {
    /// The device the uploads below live on.
    device: Weak<GpuContext>,
    bvh: Option<Arc<GpuBvh>>,
    /// Per emitter set (the table's emitter triangle ids).
    tables: Vec<(Vec<u32>, Arc<GpuTables>)>,
    /// Per texel set.
    texels: Vec<(Weak<Atlas>, Arc<wgpu::Buffer>)>,
}

impl SceneRays {
    /// Nothing is built until a pass asks.
    pub fn new(scene: Arc<Scene>) -> Arc<Self> {
        Arc::new(SceneRays {
            scene,
            tracer: OnceLock::new(),
            emitters: OnceLock::new(),
            gpu: Mutex::new(GpuCache::default()),
            built: Mutex::new(Builds::default()),
        })
    }

    /// The builds and uploads so far.
    pub fn builds(&self) -> Builds {
        *self.built.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn count(&self, f: impl FnOnce(&mut Builds)) {
        f(&mut self.built.lock().unwrap_or_else(|p| p.into_inner()));
    }

    /// The scene these rays trace.
    pub fn scene(&self) -> &Arc<Scene> {
        &self.scene
    }

    /// The CPU BVH (built on first use).
    pub fn tracer(&self) -> Arc<Tracer> {
        self.tracer
            .get_or_init(|| {
                self.count(|b| b.cpu_bvh += 1);
                Arc::new(Tracer::new(&self.scene))
            })
            .clone()
    }

    /// The table over every emissive triangle (built on first use).
    pub fn emitters(&self) -> Arc<EmitterTable> {
        self.emitters
            .get_or_init(|| Arc::new(EmitterTable::new(&self.scene)))
            .clone()
    }

    fn cache(&self, ctx: &Arc<GpuContext>) -> Option<std::sync::MutexGuard<'_, GpuCache>> {
        let mut cache = self.gpu.lock().unwrap_or_else(|p| p.into_inner());
        let same = cache.device.upgrade().is_some_and(|d| Arc::ptr_eq(&d, ctx));
        if !same {
            if cache.device.strong_count() > 0 {
                return None;
            }
            // The first device asked for (or the next, once that one is gone) owns it.
            *cache = GpuCache {
                device: Arc::downgrade(ctx),
                ..GpuCache::default()
            };
        }
        Some(cache)
    }

    /// The BVH on `ctx` (uploaded on first use).
    pub fn gpu_bvh(&self, ctx: &Arc<GpuContext>) -> Result<Arc<GpuBvh>, GpuError> {
        let upload = || -> Result<Arc<GpuBvh>, GpuError> {
            self.count(|b| b.gpu_bvh += 1);
            Ok(Arc::new(GpuBvh::new(ctx, self.tracer().bvh(), &self.scene)?))
        };
        let Some(mut cache) = self.cache(ctx) else {
            return upload();
        };
        if let Some(b) = &cache.bvh {
            return Ok(b.clone());
        }
        let bvh = upload()?;
        cache.bvh = Some(bvh.clone());
        Ok(bvh)
    }

    /// The shading data and tables with `emitters` as the pickable emitters, on `ctx`
    /// (uploaded on first use for that emitter set); `what` names the pass in errors.
    pub fn gpu_tables(
        &self,
        ctx: &Arc<GpuContext>,
        what: &str,
        emitters: &EmitterTable,
    ) -> Result<Arc<GpuTables>, GpuError> {
        let bvh = self.gpu_bvh(ctx)?;
        let upload = || -> Result<Arc<GpuTables>, GpuError> {
            self.count(|b| b.gpu_tables += 1);
            Ok(Arc::new(upload_tables(ctx, what, &self.scene, emitters, &bvh)?))
        };
        let Some(mut cache) = self.cache(ctx) else {
            return upload();
        };
        if let Some((_, t)) = cache.tables.iter().find(|(ids, _)| *ids == emitters.emitters) {
            return Ok(t.clone());
        }
        let t = upload()?;
        cache.tables.push((emitters.emitters.clone(), t.clone()));
        Ok(t)
    }

    /// `atlas`'s valid texels in world space (`texels::world_texels`, 48 B a texel) on
    /// `ctx`, uploaded on first use for that texel set.
    pub fn gpu_texels(
        &self,
        ctx: &Arc<GpuContext>,
        what: &str,
        atlas: &Arc<Atlas>,
    ) -> Result<Arc<wgpu::Buffer>, GpuError> {
        let upload = || -> Result<Arc<wgpu::Buffer>, GpuError> {
            self.count(|b| b.gpu_texels += 1);
            let geom = world_texels(atlas);
            check_binding_size(ctx, &format!("{what}: the texels"), geom.len() as u64 * 48)?;
            let usage = BufferUsages::STORAGE | BufferUsages::COPY_DST;
            Ok(Arc::new(ctx.buffer_init("world-space texels", &geom, usage)))
        };
        let Some(mut cache) = self.cache(ctx) else {
            return upload();
        };
        cache.texels.retain(|(a, _)| a.strong_count() > 0);
        if let Some((_, b)) = cache
            .texels
            .iter()
            .find(|(a, _)| a.upgrade().is_some_and(|a| Arc::ptr_eq(&a, atlas)))
        {
            return Ok(b.clone());
        }
        let b = upload()?;
        cache.texels.push((Arc::downgrade(atlas), b.clone()));
        Ok(b)
    }
}

/// Uploads the shading data (in `bvh`'s slot order) and the tables for `emitters`.
fn upload_tables(
    ctx: &GpuContext,
    what: &str,
    scene: &Scene,
    emitters: &EmitterTable,
    bvh: &GpuBvh,
) -> Result<GpuTables, GpuError> {
    let (shade, tables, offsets) = if scene.triangles.is_empty() {
        (
            vec![[0.0; 4]; 6],
            vec![[bits(1), bits(1), 0.0, 0.0]],
            [1, 1, 0, 1, 0, 1],
        )
    } else {
        let slot_ids: Vec<u32> = bvh.data.tris.iter().map(|t| t.id).collect();
        scene_tables(scene, emitters, &slot_ids, &bvh.data.slot_of)
    };
    let vec4 = 16u64;
    check_binding_size(
        ctx,
        &format!("{what}: the triangles' shading data"),
        shade.len() as u64 * vec4,
    )?;
    check_binding_size(
        ctx,
        &format!("{what}: the materials, lights and textures"),
        tables.len() as u64 * vec4,
    )?;
    let read = BufferUsages::STORAGE | BufferUsages::COPY_DST;
    Ok(GpuTables {
        shade: ctx.buffer_init("scene triangle shading", &shade, read),
        tables: ctx.buffer_init("scene tables", &tables, read),
        offsets,
    })
}

type Tables = (Vec<[f32; 4]>, Vec<[f32; 4]>, [u32; 6]);

/// Tables in `gpu/materials.wgsl`'s layout with `materials` opaque materials and no
/// textures, for map passes fed by scenes made in code rather than imported (their
/// triangles name material indices but no [`SceneRays`] holds their materials).
pub fn opaque_material_tables(materials: u32) -> Vec<[f32; 4]> {
    let mut t = vec![[bits(1), bits(1 + 4 * materials), 0.0, 0.0]];
    for _ in 0..materials {
        t.extend([
            [0.0, 0.0, 0.0, bits(u32::MAX)],
            [0.0, 0.0, 0.0, bits(u32::MAX)],
            [0.0; 4],
            [0.0, 0.0, 1.0, 0.0],
        ]);
    }
    t
}

fn scene_tables(scene: &Scene, emitters: &EmitterTable, slot_ids: &[u32], slot_of: &[u32]) -> Tables {
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
    // Row 0: the offsets `gpu/materials.wgsl` reads (materials, texture headers), filled
    // in below, so raster passes bind this one buffer and no uniform.
    let mut tables: Vec<[f32; 4]> = vec![[0.0; 4]];
    let mat_off = tables.len() as u32;
    for m in &scene.materials {
        let tex = |r: Option<TextureRef>| r.map_or(u32::MAX, |r| r.texture);
        let set = |r: Option<TextureRef>| r.map_or(0, |r| r.texcoord);
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
        let (mode, cutoff) = match m.alpha_mode {
            AlphaMode::Opaque => (0u32, 0.0),
            AlphaMode::Mask { cutoff } => (1, cutoff),
            AlphaMode::Blend => (2, 0.0),
        };
        tables.push([bits(mode), cutoff, m.base_color.w, 0.0]);
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
    tables[0] = [bits(mat_off), bits(tex_off), 0.0, 0.0];
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
    let offsets = [
        mat_off,
        light_off,
        scene.lights.len() as u32,
        emit_off,
        emitters.emitters.len() as u32,
        tex_off,
    ];
    (shade, tables, offsets)
}
