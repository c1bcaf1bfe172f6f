//! `hemicube`'s set-up (`Hemicube::prepare`): the parameters checked, the texels'
//! geometry, lobes and cells uploaded with the device's storage limits checked first, the
//! depth atlas laid out and the passes built (pyramid, selection, transfer).

use bytemuck::Zeroable;
use glam::Vec3;

use super::super::api::{BakeInputs, EngineError, gpu_error, parse_params};
use crate::engine::gpu;
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_at, group_of, layout_at, layout_of};
use crate::engine::gpu::shadow::{AtlasVertices, ShadowAtlas, ShadowView, shadow_vertices};
use crate::engine::gpu::slices::StepSlicer;
use crate::engine::gpu::texels::GpuTexelGeom;

use super::{
    CPU_LIGHT_PASS, Emitter, GLOSSY_PASS, GpuCellPiece, GpuNear, GpuParams, GpuShooter, GpuTexelMat, HC_CPU_LIGHT,
    HC_DIRECT, HC_GLOSSY, Hemicube, HemicubeParams, lobe, lum, shaders, v4,
};

impl Hemicube {
    pub fn prepare(inputs: BakeInputs, params: &serde_json::Value) -> Result<Self, EngineError> {
        let params: HemicubeParams = parse_params("hemicube", params)?;
        params.validate()?;
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
        let scene = inputs.scene.clone();
        let atlas = inputs.atlas.clone();
        let lighting = inputs.lighting;
        let plan = &inputs.plan;
        let glossy = plan.runs(GLOSSY_PASS);
        let cpu_light = plan.runs(CPU_LIGHT_PASS);
        let mut flags = 0;
        if glossy {
            flags |= HC_GLOSSY;
        }
        if inputs.want_direct {
            flags |= HC_DIRECT;
        }
        // The near-field gather rides on the CPU pass, so with it the pass always runs.
        let near_field = params.near_field > 0.0;
        if cpu_light || near_field {
            flags |= HC_CPU_LIGHT;
        }

        // Normalised space: the bounds of triangles and texel points together.
        let frame = SceneFrame::of(&scene, &atlas);
        let (centre, radius) = (frame.centre, frame.radius);
        let area_scale = 1.0 / (radius * radius);

        // Emitters, sampled on the CPU by power.
        let emitters: Vec<Emitter> = scene
            .triangles
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let m = scene.material(t);
                let sides = if m.double_sided { 2.0 } else { 1.0 };
                // Textured emitters: the factor bounds the texture (glTF multiplies them),
                // and any positive weight keeps the estimator unbiased.
                let w = lum(m.emissive).max(m.emissive.max_element() * 1e-3) as f64 * t.area() as f64 * sides;
                (w > 0.0 && w.is_finite()).then_some(Emitter {
                    triangle: i as u32,
                    weight: w,
                })
            })
            .collect();
        let total: f64 = emitters.iter().map(|e| e.weight).sum();
        let emitter_cdf: Vec<f64> = emitters
            .iter()
            .scan(0.0, |acc, e| {
                *acc += e.weight / total;
                Some(*acc)
            })
            .collect();
        let k = params.shooters_per_step;
        // With one shooter a step and emitters, each step tosses a coin between the kinds
        // (`run_step`); otherwise half the shooters (rounded up) are emitter samples.
        let k_emit = match (emitters.is_empty(), k) {
            (true, _) => 0,
            (false, 1) => 1,
            (false, k) => k.div_ceil(2),
        };
        let k_texel = if k == 1 { 1 } else { k - k_emit };
        let shooters = k;

        // GPU resources.
        let n_texels = atlas.texels.len() as u32;
        let max_binding = ctx.limits.max_storage_buffer_binding_size;
        let need = 2 * n_texels.max(1) as u64 * 16;
        ctx.check_storage(&format!("hemicube: the per-texel buffers of {n_texels} texels"), need)
            .map_err(gpu_error)?;
        let pyr_side = atlas.width.max(atlas.height).max(1).next_power_of_two();
        let top_level = pyr_side.trailing_zeros();
        let pyramid_len: u64 = (0..=top_level).map(|l| ((pyr_side >> l) as u64).pow(2)).sum();
        if pyramid_len * 4 > max_binding {
            return Err(EngineError::BadInput(format!(
                "hemicube: a {}x{} lightmap needs a {}-byte power pyramid; the device allows {max_binding}",
                atlas.width,
                atlas.height,
                pyramid_len * 4
            )));
        }
        // Depth atlas: per shooter a 3N x 2N block (top face and four side faces).
        let n = params.depth_map_size;
        let max_dim = ctx.limits.max_texture_dimension_2d;
        let cols = (max_dim / (3 * n)).min(shooters).max(1);
        let rows = shooters.div_ceil(cols);
        let (atlas_w, atlas_h) = (cols * 3 * n, rows * 2 * n);
        if atlas_w > max_dim || atlas_h > max_dim {
            return Err(EngineError::BadInput(format!(
                "hemicube: {shooters} shooters with depth_map_size {n} need a {atlas_w}x{atlas_h} depth atlas; \
                 the device allows {max_dim}: lower params.depth_map_size or params.shooters_per_step"
            )));
        }
        let mut tiles = Vec::with_capacity(5 * shooters as usize);
        for s in 0..shooters {
            let (bx, by) = ((s % cols) * 3 * n, (s / cols) * 2 * n);
            for (fx, fy) in [(0, 0), (1, 0), (2, 0), (0, 1), (1, 1)] {
                tiles.push([bx + fx * n, by + fy * n, n, 0]);
            }
        }

        use wgpu::BufferUsages as U;
        // position.w: the receiver's near-field radius (normalised units; 0: none).
        let geom: Vec<GpuTexelGeom> = atlas
            .texels
            .iter()
            .map(|t| {
                let mut g = GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal);
                g.position[3] = params.near_field * t.size / radius;
                g
            })
            .collect();
        // The surface each texel stands for: texel shooters are points of it.
        let cells = crate::engine::atlas::cells::cells(&scene, &atlas);
        if cells.lost_area > 0.0 {
            tracing::debug!(
                lost_area = cells.lost_area,
                "hemicube: surface outside every texel's cell does not shoot"
            );
        }
        let pieces: Vec<GpuCellPiece> = cells
            .pieces
            .iter()
            .map(|p| {
                let a = (p.p[0] - centre) / radius;
                GpuCellPiece {
                    a: v4(a, p.area * area_scale),
                    e1: v4((p.p[1] - p.p[0]) / radius, 0.0),
                    e2: v4((p.p[2] - p.p[0]) / radius, 0.0),
                }
            })
            .collect();
        ctx.check_storage(
            &format!("hemicube: the {} cell pieces of {n_texels} texels", pieces.len()),
            (pieces.len() * std::mem::size_of::<GpuCellPiece>()) as u64,
        )
        .map_err(gpu_error)?;
        let mats: Vec<GpuTexelMat> = atlas
            .texels
            .iter()
            .enumerate()
            .map(|(k, t)| {
                let tri = &scene.triangles[t.triangle as usize];
                let (kd, ks, e) = if glossy {
                    lobe(scene.material(tri), t.albedo)
                } else {
                    (t.albedo, Vec3::ZERO, 0.0)
                };
                GpuTexelMat {
                    kd: v4(kd, cells.area[k] * area_scale),
                    ks: v4(ks, e),
                    ids: [t.mesh, tri.material, t.pixel, cells.first[k]],
                }
            })
            .collect();
        let geom_buf = ctx.buffer_init("hemicube texel geometry", &geom, U::STORAGE);
        let mats_buf = ctx.buffer_init("hemicube texel lobes", &mats, U::STORAGE);
        // Hemicube bakes the whole grid (its tasks are chains, never regions).
        let whole = atlas
            .pixel_texel
            .whole(atlas.width as usize * atlas.height as usize)
            .ok_or_else(|| EngineError::Internal("hemicube needs the whole grid's texels, not a region's".into()))?;
        let pixel_texel_buf = ctx.buffer_init("hemicube pixel to texel", whole, U::STORAGE);
        let pieces_buf = ctx.buffer_init("hemicube texel cells", &pieces, U::STORAGE);
        let texel_bytes = 2 * n_texels as u64 * 16;
        // COPY_DST: a page of a bake in rounds starts from held irradiance (`hold_boundary`).
        let irr_buf = ctx.buffer_zeroed("hemicube irradiance (two steps)", texel_bytes, U::STORAGE | U::COPY_DST);
        let dirs_buf = ctx.buffer_zeroed(
            "hemicube incoming directions (two steps)",
            if glossy { texel_bytes } else { 16 },
            U::STORAGE,
        );
        let cpu_light_buf = ctx.buffer_zeroed(
            "hemicube sky/sun/punctual estimate",
            if flags & HC_CPU_LIGHT != 0 { texel_bytes } else { 16 },
            U::STORAGE | U::COPY_DST,
        );
        let near_buf = ctx.buffer_init(
            "hemicube near-field gather",
            &vec![GpuNear::NONE; n_texels.max(1) as usize],
            U::STORAGE | U::COPY_DST,
        );
        let acc_buf = ctx.buffer_zeroed(
            "hemicube accumulators (even, odd)",
            texel_bytes,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let direct_acc_buf = ctx.buffer_zeroed(
            "hemicube direct accumulators (even, odd)",
            if inputs.want_direct { texel_bytes } else { 16 },
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let pyramid_buf = ctx.buffer_zeroed("hemicube power pyramid", pyramid_len * 4, U::STORAGE | U::COPY_DST);
        let params_buf = ctx.uniform("hemicube step params", &GpuParams::zeroed());
        let shooter_size = std::mem::size_of::<GpuShooter>() as u64;
        let emitters_buf = ctx.buffer_zeroed(
            "hemicube emitter samples",
            k_emit.max(1) as u64 * shooter_size,
            U::STORAGE | U::COPY_DST,
        );
        let shooters_buf = ctx.buffer_zeroed("hemicube shooters", shooters as u64 * shooter_size, U::STORAGE);
        let views_buf = ctx.buffer_zeroed(
            "hemicube views",
            5 * shooters as u64 * std::mem::size_of::<ShadowView>() as u64,
            U::STORAGE,
        );
        let tiles_buf = ctx.buffer_init("hemicube depth tiles", &tiles, U::STORAGE);
        // Per corner: position, the triangle's plane and its alpha inputs (gpu::shadow).
        let vertices = shadow_vertices(&scene, &frame);
        let vertex_buf = ctx.buffer_init("hemicube vertices (normalised, with planes)", &vertices, U::VERTEX);

        use wgpu::ShaderStages as S;
        // Pyramid.
        let pyr_module = ctx.shader(&shaders::HEMICUBE_PYRAMID).map_err(gpu_error)?;
        let power_binds = [
            Bind::Uniform(&params_buf),
            Bind::Read(&mats_buf),
            Bind::Read(&irr_buf),
            Bind::Write(&pyramid_buf),
        ];
        let power_layout = layout_of(&ctx, "hemicube power layout", S::COMPUTE, &power_binds);
        let power_pipeline = compute_pipeline(&ctx, "hemicube power", &pyr_module, "power", &power_layout);
        let power_bg = group_of(&ctx, "hemicube power bindings", &power_layout, &power_binds);
        // Bindings 3 and 4 of hemicube/pyramid.wgsl (0..2 belong to its `power` entry point).
        let reduce_layout = layout_at(
            &ctx,
            "hemicube reduce layout",
            3,
            S::COMPUTE,
            &[Bind::Write(&pyramid_buf), Bind::Uniform(&params_buf)],
        );
        let reduce_pipeline = compute_pipeline(&ctx, "hemicube reduce", &pyr_module, "reduce", &reduce_layout);
        let level_offset = |l: u32| -> u32 { (0..l).map(|k| (pyr_side >> k) * (pyr_side >> k)).sum() };
        let reduce_bgs: Vec<(wgpu::BindGroup, u32)> = (1..=top_level)
            .map(|l| {
                let side = pyr_side >> l;
                let buf = ctx.uniform(
                    &format!("hemicube pyramid level {l}"),
                    &[side, level_offset(l - 1), level_offset(l), 0u32],
                );
                let bg = group_at(
                    &ctx,
                    &format!("hemicube reduce level {l}"),
                    &reduce_layout,
                    3,
                    &[Bind::Write(&pyramid_buf), Bind::Uniform(&buf)],
                );
                (bg, side * side)
            })
            .collect();
        // Shooter selection.
        let select_module = ctx.shader(&shaders::HEMICUBE_SELECT).map_err(gpu_error)?;
        let select_binds = [
            Bind::Uniform(&params_buf),
            Bind::Read(&mats_buf),
            Bind::Read(&irr_buf),
            Bind::Read(&dirs_buf),
            Bind::Read(&pyramid_buf),
            Bind::Read(&pixel_texel_buf),
            Bind::Read(&geom_buf),
            Bind::Read(&emitters_buf),
            Bind::Write(&shooters_buf),
            Bind::Write(&views_buf),
            Bind::Read(&tiles_buf),
            Bind::Read(&pieces_buf),
        ];
        let select_layout = layout_of(&ctx, "hemicube select layout", S::COMPUTE, &select_binds);
        let select_pipeline = compute_pipeline(
            &ctx,
            "hemicube select",
            &select_module,
            "select_shooters",
            &select_layout,
        );
        let select_bg = group_of(&ctx, "hemicube select bindings", &select_layout, &select_binds);
        // Depth maps: the shared shadow atlas (gpu::shadow), views from the select pass.
        let tables = inputs
            .rays
            .gpu_tables(&ctx, "hemicube", &inputs.rays.emitters())
            .map_err(gpu_error)?;
        let shadow = ShadowAtlas::new(
            &ctx,
            "hemicube depth",
            atlas_w,
            atlas_h,
            &views_buf,
            &tables.tables,
            AtlasVertices::Planes,
        )
        .map_err(gpu_error)?;
        // Transfer and accumulation.
        let transfer_module = ctx.shader(&shaders::HEMICUBE_TRANSFER).map_err(gpu_error)?;
        let transfer_binds = [
            Bind::Uniform(&params_buf),
            Bind::Read(&geom_buf),
            Bind::Write(&irr_buf),
            Bind::Write(&dirs_buf),
            Bind::Read(&cpu_light_buf),
            Bind::Read(&shooters_buf),
            // textureLoad only: Rgba32Float needs no filtering.
            Bind::Texture2d(&shadow.plane_view),
            Bind::Write(&acc_buf),
            Bind::Write(&direct_acc_buf),
            Bind::Read(&tiles_buf),
            Bind::Read(&near_buf),
        ];
        let transfer_layout = layout_of(&ctx, "hemicube transfer layout", S::COMPUTE, &transfer_binds);
        let transfer_pipeline = compute_pipeline(
            &ctx,
            "hemicube transfer",
            &transfer_module,
            "transfer",
            &transfer_layout,
        );
        let transfer_bg = group_of(&ctx, "hemicube transfer bindings", &transfer_layout, &transfer_binds);
        ctx.take_error("hemicube setup").map_err(gpu_error)?;

        let tracer = (flags & HC_CPU_LIGHT != 0).then(|| inputs.rays.tracer());
        let texel_albedo: Vec<Vec3> = mats.iter().map(|m| Vec3::from_slice(&m.kd[..3])).collect();
        Ok(Hemicube {
            ctx,
            params,
            scene,
            atlas,
            lighting,
            seed: inputs.seed,
            flags,
            centre,
            radius,
            tracer,
            texel_albedo,
            emitters,
            emitter_cdf,
            k_emit,
            k_texel,
            steps_done: 0,
            half_steps: [0, 0],
            half_weight: [0.0, 0.0],
            n_texels,
            pyr_side,
            top_level,
            tiles,
            vertex_count: vertices.len() as u32,
            params_buf,
            emitters_buf,
            cpu_light_buf,
            near_buf,
            pyramid_buf,
            irr_buf,
            acc_buf,
            direct_acc_buf,
            vertex_buf,
            shadow,
            power_pipeline,
            power_bg,
            reduce_pipeline,
            reduce_bgs,
            select_pipeline,
            select_bg,
            transfer_pipeline,
            transfer_bg,
            deadline: None,
            progress: None,
            slicer: StepSlicer::new("hemicube transfer"),
            map_slicer: StepSlicer::per_unit("hemicube depth maps"),
            receivers: 0..n_texels as usize,
        })
    }
}
