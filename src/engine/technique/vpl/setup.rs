//! `vpl`'s set-up (`Vpl::prepare`): the parameters checked, the emitters and the scene's
//! lights sorted into what the shadow atlas will hold, its tiles packed, the texels and
//! the GPU tracer uploaded, and the passes built.

use std::f32::consts::PI;

use bytemuck::Zeroable;
use glam::Vec3;

use super::super::api::{BakeInputs, EngineError, gpu_error, parse_params};
use crate::engine::atlas::SURFACE_OFFSET;
use crate::engine::gpu::directions::{DirectionSequence, Directions, SplitMix64};
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_of, layout_of};
use crate::engine::gpu::shadow::{self, AtlasVertices, ShadowAtlas, ShadowView, shadow_vertices};
use crate::engine::gpu::slices::StepSlicer;
use crate::engine::gpu::texels::GpuTexelGeom;
use crate::engine::gpu::tracer::GpuTracer;
use crate::engine::gpu::view::{auto_map_size, largest_fitting};
use crate::engine::gpu::{self, RayDevice};
use crate::engine::scene::LightKind;

use super::rsm::{self, RsmTracer};
use super::{AUTO_ATLAS_BYTES, Emitter, GpuGatherParams, GpuLight, Primary, Vpl, VplParams, lum, pack, shaders};

impl Vpl {
    pub fn prepare(inputs: BakeInputs, params: &serde_json::Value) -> Result<Self, EngineError> {
        let mut params: VplParams = parse_params("vpl", params)?;
        params.validate()?;
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
        let scene = inputs.scene.clone();
        let atlas = inputs.atlas.clone();
        let lighting = inputs.lighting;

        // Normalised space: the triangles' bounds with room for the texels' sample points
        // (twice their offset), which a region of the grid shares with the whole
        // (`engine::tasks`: a page task's texels are the single bake's, bit for bit).
        let frame = SceneFrame::of_scene(&scene, 2.0 * atlas.surface_offset);
        let (centre, radius) = (frame.centre, frame.radius);

        // Primary lights, fixed for the bake.
        let mut primaries = Vec::new();
        if lighting.sun.is_some_and(|s| s.radiance != Vec3::ZERO) {
            primaries.push(Primary::Sun);
        }
        for (i, l) in scene.lights.iter().enumerate() {
            if l.intensity == Vec3::ZERO {
                continue;
            }
            match l.kind {
                LightKind::Directional => primaries.push(Primary::Directional {
                    dir: l.direction.normalize(),
                    irradiance: l.intensity,
                }),
                LightKind::Point | LightKind::Spot { .. } => primaries.push(Primary::Punctual(i)),
            }
        }
        if lighting.sky.is_some_and(|s| s.radiance != Vec3::ZERO) {
            primaries.extend((0..params.sky_directions).map(|_| Primary::Sky));
        }
        // Shadow views: a map per distant light, six faces per punctual light, five per VPL.
        let views_of = |shadow_map_size: u32| {
            let mut sizes = Vec::new();
            let mut primary_views = Vec::new();
            for p in &primaries {
                primary_views.push(sizes.len() as u32);
                match p {
                    Primary::Punctual(_) => sizes.extend([(shadow_map_size / 2).max(1); 6]),
                    _ => sizes.push(shadow_map_size),
                }
            }
            let vpl_views = sizes.len() as u32;
            if params.visibility {
                sizes.extend(std::iter::repeat_n(
                    params.vpl_map_size,
                    5 * params.vpls_per_step as usize,
                ));
            }
            (sizes, primary_views, vpl_views)
        };
        let max_dim = ctx.limits.max_texture_dimension_2d;
        // Unset, the distant lights' maps follow the scene and its texels (the grid's
        // texels, so a page's task chooses the single bake's size), then step down while
        // the atlas would not fit the device or the memory bound.
        if params.shadow_map_size.is_none() {
            let texel_sizes: Vec<f32> = match atlas.grid_texels(&scene) {
                Ok(grid) => grid.iter().map(|t| t.size).collect(),
                Err(_) => atlas.texels.iter().map(|t| t.size).collect(),
            };
            let n = largest_fitting(auto_map_size(2.0 * frame.radius, texel_sizes, max_dim), |n| {
                shadow::pack(&views_of(n).0, max_dim)
                    .is_ok_and(|l| l.width as u64 * l.height as u64 * 20 <= AUTO_ATLAS_BYTES)
            });
            tracing::info!(
                shadow_map_size = n,
                "vpl: distant lights' shadow map size chosen from the scene's size and texel density"
            );
            params.shadow_map_size = Some(n);
        }
        let (sizes, primary_views, vpl_views) = views_of(params.shadow_map_pixels());
        let layout = pack(&sizes, max_dim)?;

        let emitters: Vec<Emitter> = scene
            .triangles
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let m = scene.material(t);
                let sides = if m.double_sided { 2.0 } else { 1.0 };
                let w = PI as f64 * lum(m.emissive) * t.area() as f64 * sides;
                (w > 0.0 && w.is_finite()).then_some(Emitter {
                    triangle: i as u32,
                    weight: w,
                })
            })
            .collect();
        let emitter_weight = emitters.iter().map(|e| e.weight).sum();

        // GPU resources.
        let n_texels = atlas.texels.len() as u32;
        let storage_need = 2 * n_texels as u64 * 16;
        ctx.check_storage(&format!("vpl: the accumulators of {n_texels} texels"), storage_need)
            .map_err(gpu_error)?;
        let max_lights = primaries.len() as u32 + params.vpls_per_step;
        use wgpu::BufferUsages as U;
        // Per corner: position, the triangle's plane and its alpha inputs (gpu::shadow).
        let vertices = shadow_vertices(&scene, &frame);
        let vertex_buf = ctx.buffer_init("vpl vertices (normalised, with planes)", &vertices, U::VERTEX);
        let geom: Vec<GpuTexelGeom> = atlas
            .texels
            .iter()
            .map(|t| GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal))
            .collect();
        let geom_buf = ctx.buffer_init("vpl texel geometry", &geom, U::STORAGE);
        let lights_buf = ctx.buffer_zeroed(
            "vpl step lights",
            max_lights.max(1) as u64 * std::mem::size_of::<GpuLight>() as u64,
            U::STORAGE | U::COPY_DST,
        );
        let views_buf = ctx.buffer_zeroed(
            "vpl shadow views",
            sizes.len().max(1) as u64 * std::mem::size_of::<ShadowView>() as u64,
            U::STORAGE | U::COPY_DST,
        );
        let gather_buf = ctx.uniform("vpl gather params", &GpuGatherParams::zeroed());
        let acc_buf = ctx.buffer_zeroed(
            "vpl accumulators (even, odd)",
            storage_need,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let direct_acc_buf = ctx.buffer_zeroed(
            "vpl direct accumulators (even, odd)",
            storage_need,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );

        use wgpu::ShaderStages as S;
        let tables = inputs
            .rays
            .gpu_tables(&ctx, "vpl", &inputs.rays.emitters())
            .map_err(gpu_error)?;
        let shadow = ShadowAtlas::new(
            &ctx,
            "vpl shadow",
            layout.width,
            layout.height,
            &views_buf,
            &tables.tables,
            AtlasVertices::Planes,
        )
        .map_err(gpu_error)?;
        let gather_module = ctx.shader(&shaders::VPL_GATHER).map_err(gpu_error)?;
        let gather_binds = [
            Bind::Uniform(&gather_buf),
            Bind::Read(&lights_buf),
            Bind::Read(&views_buf),
            // textureLoad only: Rgba32Float needs no filtering.
            Bind::Texture2d(&shadow.plane_view),
            Bind::Read(&geom_buf),
            Bind::Write(&acc_buf),
            Bind::Write(&direct_acc_buf),
        ];
        let gather_layout = layout_of(&ctx, "vpl gather layout", S::COMPUTE, &gather_binds);
        let gather_pipeline = compute_pipeline(&ctx, "vpl gather", &gather_module, "gather", &gather_layout);
        let gather_bg = group_of(&ctx, "vpl gather bindings", &gather_layout, &gather_binds);
        ctx.take_error("vpl setup").map_err(gpu_error)?;

        let tracer = inputs.rays.tracer();
        let rsm = match params.rays.context("vpl").map_err(gpu_error)? {
            Some(rays_ctx) => {
                // One step's rays: n^2 a distant light, 6 (n/2)^2 a point or spot light.
                let n = params.rsm_size as usize;
                let most: usize = primaries
                    .iter()
                    .map(|p| match p {
                        Primary::Punctual(_) => 6 * (n / 2).max(1).pow(2),
                        _ => n * n,
                    })
                    .sum();
                let capacity = most.clamp(1, rsm::GPU_CHUNK);
                RsmTracer::Gpu(GpuTracer::new(&rays_ctx, "vpl rsm", &inputs.rays, capacity).map_err(gpu_error)?)
            }
            None => RsmTracer::Cpu(tracer.clone()),
        };
        params.rays = match rsm {
            RsmTracer::Gpu(_) => RayDevice::Gpu,
            RsmTracer::Cpu(_) => RayDevice::Cpu,
        };
        let ray_offset = SURFACE_OFFSET * scene.scale();
        Ok(Vpl {
            texel_dispatch: gpu::dispatch_size_64(n_texels),
            directions: Directions::new(DirectionSequence::Stratified, inputs.seed ^ 0x5C1E_D1EC),
            rng: SplitMix64::new(inputs.seed ^ 0x0B1E_55ED_0000_0001),
            ctx,
            params,
            scene,
            tracer,
            rsm,
            lighting,
            seed: inputs.seed,
            want_direct: inputs.want_direct,
            centre,
            radius,
            ray_offset,
            primaries,
            primary_views,
            vpl_views,
            layout,
            emitters,
            emitter_weight,
            steps_done: 0,
            half_steps: [0, 0],
            n_texels,
            max_lights,
            vertex_count: vertices.len() as u32,
            vertex_buf,
            lights_buf,
            views_buf,
            gather_buf,
            acc_buf,
            direct_acc_buf,
            shadow,
            gather_pipeline,
            gather_bg,
            deadline: None,
            progress: None,
            slicer: StepSlicer::new("vpl gather"),
            map_slicer: StepSlicer::per_unit("vpl maps"),
        })
    }
}
