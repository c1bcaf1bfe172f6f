//! `obscurance`'s set-up (`Obscurance::prepare`): the parameters checked, the scene's
//! maps and layers, the direct light and the emitters' samples, the texels and the
//! passes built, with the device's limits checked first.

use bytemuck::Zeroable;
use glam::Vec3;

use super::super::api::{BakeInputs, EngineError, gpu_error};
use crate::engine::ambient::{AmbientSums, MIN_ABSORPTION};
use crate::engine::gpu::direct_light::DirectLight;
use crate::engine::gpu::directions::{DirectionSequence, Directions, SplitMix64};
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_of, layout_of};
use crate::engine::gpu::map_scene::{MapScene, MapTexel};
use crate::engine::gpu::scene_lights::LightSources;
use crate::engine::gpu::shadow::{AtlasVertices, ShadowAtlas, ShadowView, map_triangle_planes};
use crate::engine::gpu::slices::StepSlicer;
use crate::engine::gpu::texels::GpuTexelGeom;
use crate::engine::gpu::view::{
    GpuDims, GpuVertex, GpuView, NO_TEXEL, TRI_DOUBLE_SIDED, TRI_TEXTURED_EMISSION, auto_map_size, fill_map,
    largest_fitting,
};
use crate::engine::gpu::{self, GpuError};

use super::{
    EmitterLight, GpuDirectParams, GpuGatherParams, GpuNode, LAYER_PART_TRIANGLES, LayerStats, MASK_BASE, Obscurance,
    ObscuranceParams, SAMPLED_EMITTER_PIXELS, ShadowPass, TRI_SAMPLED_EMISSION, TRI_TEXTURED_ALBEDO, pixel_size,
    shaders,
};

impl Obscurance {
    pub fn prepare(inputs: BakeInputs, params: &serde_json::Value) -> Result<Self, EngineError> {
        let params = ObscuranceParams::from_json(params)?;
        Self::with_params(inputs, params)
    }

    pub(super) fn with_params(inputs: BakeInputs, mut params: ObscuranceParams) -> Result<Self, EngineError> {
        params.validate()?;
        let input = MapScene::new(
            &inputs.scene,
            &inputs.atlas,
            &inputs.lighting,
            inputs.seed,
            inputs.want_direct,
        );
        let mut notes: Vec<String> = Vec::new();
        for n in &mut notes {
            *n = n.replace("sdb ignores", "obscurance ignores");
            tracing::warn!("{n}");
        }
        let scene = &inputs.scene;
        let atlas = &inputs.atlas;
        let ctx = gpu::shared(&gpu::Requirements::default()).map_err(|e| EngineError::Gpu(e.to_string()))?;
        if let Some(n) = params.map_size
            && n > ctx.limits.max_texture_dimension_2d
        {
            return Err(EngineError::BadInput(format!(
                "obscurance parameter map_size: {n} exceeds the device's max texture size {}",
                ctx.limits.max_texture_dimension_2d
            )));
        }
        if ctx.limits.max_storage_buffers_per_shader_stage < 8 {
            return Err(gpu_error(GpuError::Unsupported {
                adapter: ctx.info.name.clone(),
                missing: "8 storage buffers per shader stage (the obscurance gather)".into(),
            }));
        }
        let (width, height) = (atlas.width.max(1), atlas.height.max(1));
        let n_texels = input.texels.len() as u32;

        // Normalised scene space: the triangles' bounds, not the texels' (a region's task
        // has only its region's texels, engine::tasks; a texel's sample point lies on its
        // triangle, pushed off by the atlas's small surface offset).
        let frame = SceneFrame::of_points(input.triangles.iter().flat_map(|t| t.p));
        let (lo, hi, scale) = (frame.lo, frame.hi, frame.radius);
        let norm = |p: Vec3| frame.norm(p);
        let corners: [Vec3; 8] = frame.corners();
        let dmax = params.dmax.unwrap_or(0.25 * (hi - lo).length()).max(f32::MIN_POSITIVE);
        params.dmax = Some(dmax);
        let dmax_norm = dmax / scale;

        // The whole grid's texels before validation: the albedo and emission maps the
        // gather reads at the surfaces it sees, and R_ave, are the grid's, whichever
        // region of it this bake holds (engine::tasks: a region's task reads the single
        // bake's maps). Before validation, so that a region's task, which validates only
        // its own texels, has the same set: a texel validation drops lies inside closed
        // geometry, where no ray sees it, and keeps its own surface's material.
        let grid = atlas
            .grid_texels(scene)
            .map_err(|e| EngineError::Internal(format!("obscurance: the grid's texels: {e}")))?;

        // Node pool: fragments along d <= sum of projected areas / pixel area <= sum of
        // areas / smallest pixel area over directions, plus one per triangle (a triangle
        // smaller than a pixel may still cover one centre) and a margin. The nodes a map
        // of n pixels wants, and its smallest pixel (normalised units).
        let norm_area: f64 = scene
            .triangles
            .iter()
            .map(|t| (t.area() / (scale * scale)) as f64)
            .sum();
        let pool_for = |n: u32| {
            let mut probe = Directions::new(DirectionSequence::Stratified, 7);
            let min_pixel = (0..256)
                .map(|_| pixel_size(probe.next_direction(), &corners, n))
                .fold(f32::MAX, f32::min)
                * 0.95;
            let wanted =
                norm_area / (min_pixel as f64 * min_pixel as f64) * 1.05 + input.triangles.len() as f64 + 4096.0;
            (wanted, min_pixel)
        };
        let max_nodes = (ctx
            .limits
            .max_storage_buffer_binding_size
            .min(ctx.limits.max_buffer_size)
            / 16) as f64;
        // Unset, the map's size follows the scene and its texels (over the grid's texels
        // and the triangles' bounds, so a region's task chooses the single bake's), then
        // steps down while its pool would not fit the device.
        if params.map_size.is_none() {
            let n = largest_fitting(
                auto_map_size(
                    (hi - lo).length(),
                    grid.iter().map(|t| t.size),
                    ctx.limits.max_texture_dimension_2d,
                ),
                |n| pool_for(n).0 <= max_nodes,
            );
            tracing::info!(
                map_size = n,
                "obscurance: map size chosen from the scene's size and texel density"
            );
            params.map_size = Some(n);
        }
        let map_size = params.map_pixels();
        // Scene averages: R_ave over those texels (texture-aware), weighted by texel
        // area; Eq. 5's emission over triangles (exact for small emitters without texels).
        let r_ave = {
            let mut sums = AmbientSums::default();
            for t in grid.iter() {
                sums.add_texel(t.size * t.size, t.albedo, Vec3::ZERO, 0.0);
            }
            sums.r_ave()
        };
        let texel_area: Vec<f32> = atlas.texels.iter().map(|t| t.size * t.size).collect();
        let (mut tri_area, mut emitted) = (0.0f64, glam::DVec3::ZERO);
        for t in &scene.triangles {
            let a = t.area() as f64;
            tri_area += a;
            emitted += scene.material(t).emissive.as_dvec3() * a;
        }
        let e_ave = (emitted / tri_area.max(f64::MIN_POSITIVE)).as_vec3();
        let eq5_ambient = e_ave / (Vec3::ONE - r_ave).max(Vec3::splat(MIN_ABSORPTION));

        // Geometry and materials.
        let mut vertices = Vec::with_capacity(input.triangles.len() * 3);
        let pix = (width * height) as usize;
        let grid: Vec<MapTexel> = grid.iter().map(MapTexel::from).collect();
        let fill = fill_map(width, height, &grid);
        let mut materials: Vec<[f32; 4]> = Vec::with_capacity(2 * pix + 2 * input.triangles.len());
        for &k in &fill {
            materials.push(if k == NO_TEXEL {
                [0.0; 4]
            } else {
                grid[k as usize].albedo.extend(1.0).to_array()
            });
        }
        for &k in &fill {
            materials.push(if k == NO_TEXEL {
                [0.0; 4]
            } else {
                grid[k as usize].emission.extend(1.0).to_array()
            });
        }
        drop(grid);
        // Which emitters the shared module samples (`params.emitters`).
        let world_pixel = (hi - lo).length() / map_size as f32;
        let sampled: Vec<bool> = scene
            .triangles
            .iter()
            .map(|t| match params.emitters {
                EmitterLight::Sampled => true,
                EmitterLight::Gathered => false,
                EmitterLight::Auto => t.area() < SAMPLED_EMITTER_PIXELS * world_pixel * world_pixel,
            })
            .collect();
        for (i, (t, st)) in input.triangles.iter().zip(&scene.triangles).enumerate() {
            vertices.extend(GpuVertex::corners(i as u32, t, norm));
            let m = scene.material(st);
            let mut flags = 0;
            if t.double_sided {
                flags |= TRI_DOUBLE_SIDED;
            }
            if t.emission_textured {
                flags |= TRI_TEXTURED_EMISSION;
            }
            if m.base_color_texture.is_some() {
                flags |= TRI_TEXTURED_ALBEDO;
            }
            if sampled[i] {
                flags |= TRI_SAMPLED_EMISSION;
            }
            let albedo = m.base_color.truncate();
            materials.push([albedo.x, albedo.y, albedo.z, f32::from_bits(flags)]);
            materials.push([t.emission.x, t.emission.y, t.emission.z, f32::from_bits(t.mesh)]);
        }
        let geom: Vec<GpuTexelGeom> = input
            .texels
            .iter()
            .map(|t| GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal))
            .collect();

        let (wanted, min_pixel) = pool_for(map_size);
        let node_capacity = wanted.min(max_nodes) as u32;
        if wanted > max_nodes {
            tracing::warn!(
                wanted,
                max_nodes,
                "obscurance: the fragment pool is capped by the device"
            );
            notes.push(format!(
                "obscurance: the scene may need {wanted:.0} fragment nodes per direction; the device allows \
                 {max_nodes:.0}, so directions with more depth layers drop fragments (reported at snapshots)"
            ));
        }
        // Emitters are found only by the bundles' rays: one smaller than a map pixel is
        // hit by a ray only when a pixel centre falls on it, so its light is mostly lost.
        let pixel_area_world = (min_pixel * scale) as f64 * (min_pixel * scale) as f64;
        let small_emitters = scene
            .triangles
            .iter()
            .filter(|t| scene.material(t).emissive != Vec3::ZERO && (t.area() as f64) < pixel_area_world)
            .count();
        if small_emitters > 0 {
            let note = format!(
                "obscurance: {small_emitters} emissive triangle(s) are smaller than a map pixel \
                 ({:.3e} m^2 at map_size {}): their direct light is found only by rays that happen to hit \
                 them and is mostly missed (raise map_size, or bake with `path`)",
                pixel_area_world, map_size
            );
            tracing::warn!("{note}");
            notes.push(note);
        }
        let n = map_size;
        let storage_need = (2 * pix as u64 + 2 * input.triangles.len() as u64).max(4 * n_texels as u64) * 16;
        ctx.check_storage(&format!("obscurance: a {width}x{height} lightmap"), storage_need)
            .map_err(gpu_error)?;

        use wgpu::BufferUsages as U;
        let vertex_buf = ctx.buffer_init("obscurance vertices", &vertices, U::VERTEX);
        let materials_buf = ctx.buffer_init("obscurance materials (per pixel, per triangle)", &materials, U::STORAGE);
        let geom_buf = ctx.buffer_init("obscurance texel geometry", &geom, U::STORAGE);
        let heads_buf = ctx.buffer_zeroed(
            "obscurance list heads",
            n as u64 * n as u64 * 4,
            U::STORAGE | U::COPY_DST,
        );
        let nodes_buf = ctx.buffer_zeroed(
            "obscurance fragment nodes",
            node_capacity as u64 * std::mem::size_of::<GpuNode>() as u64,
            U::STORAGE,
        );
        let counters_buf = ctx.buffer_zeroed(
            "obscurance counters and influence masks",
            (MASK_BASE as u64 + n_texels as u64) * 4,
            U::STORAGE | U::COPY_DST | U::COPY_SRC,
        );
        let acc_buf = ctx.buffer_zeroed(
            "obscurance W/ao and weight accumulators (even, odd)",
            n_texels as u64 * 4 * 16,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let direct_acc_buf = ctx.buffer_zeroed(
            "obscurance direct/hit and sun accumulators (even, odd)",
            n_texels as u64 * 4 * 16,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let subset_buf = ctx.buffer_zeroed(
            "obscurance texel subset (incremental update)",
            n_texels.max(1) as u64 * 4,
            U::STORAGE | U::COPY_DST,
        );
        let view_buf = ctx.uniform("obscurance view", &GpuView::zeroed());
        let layer_params = ctx.uniform(
            "obscurance layer params",
            &GpuDims {
                dims: [width, height, node_capacity, n],
            },
        );
        let gather_buf = ctx.uniform("obscurance gather params", &GpuGatherParams::zeroed());
        let direct_buf = ctx.uniform("obscurance direct params", &GpuDirectParams::zeroed());

        let extent = wgpu::Extent3d {
            width: n,
            height: n,
            depth_or_array_layers: 1,
        };
        let dummy = ctx.texture_2d(
            "obscurance layers dummy target (write-masked)",
            extent,
            wgpu::TextureFormat::R8Unorm,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
        );
        let dummy_view = dummy.create_view(&wgpu::TextureViewDescriptor {
            label: Some("obscurance layers dummy target view"),
            ..Default::default()
        });

        use wgpu::ShaderStages as S;
        let layers_module = ctx.shader(&shaders::OBSCURANCE_LAYERS).map_err(gpu_error)?;
        let view_bind = Bind::Uniform(&view_buf);
        // The scene's materials and textures, for the alpha test (gpu/materials.wgsl).
        let tables = inputs
            .rays
            .gpu_tables(&ctx, "obscurance", &inputs.rays.emitters())
            .map_err(gpu_error)?;
        let layers_binds = [
            Bind::In(S::VERTEX_FRAGMENT, &view_bind),
            Bind::Read(&tables.tables),
            Bind::Uniform(&layer_params),
            Bind::Write(&heads_buf),
            Bind::Write(&nodes_buf),
            Bind::Write(&counters_buf),
        ];
        let layers_layout = layout_of(&ctx, "obscurance layers layout", S::FRAGMENT, &layers_binds);
        let vertex_layout = wgpu::VertexBufferLayout {
            array_stride: std::mem::size_of::<GpuVertex>() as u64,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &GpuVertex::ATTRIBUTES,
        };
        let layers_pipeline = {
            let label = "obscurance depth layers";
            let pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: &[Some(&layers_layout)],
                immediate_size: 0,
            });
            ctx.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(&pl),
                vertex: wgpu::VertexState {
                    module: &layers_module,
                    entry_point: Some("vs_main"),
                    compilation_options: Default::default(),
                    buffers: &[Some(vertex_layout)],
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    front_face: wgpu::FrontFace::Ccw,
                    // Both faces: texels on either side look for them (section 4.2).
                    cull_mode: None,
                    ..Default::default()
                },
                // Every fragment is kept (in the lists), so no depth test.
                depth_stencil: None,
                multisample: Default::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &layers_module,
                    entry_point: Some("fs_layers"),
                    compilation_options: Default::default(),
                    // A write-masked dummy: a render pass needs an attachment.
                    targets: &[Some(wgpu::ColorTargetState {
                        format: wgpu::TextureFormat::R8Unorm,
                        blend: None,
                        write_mask: wgpu::ColorWrites::empty(),
                    })],
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let layers_bg = group_of(&ctx, "obscurance layers bindings", &layers_layout, &layers_binds);

        let gather_module = ctx.shader(&shaders::OBSCURANCE_GATHER).map_err(gpu_error)?;
        let gather_binds = [
            Bind::Uniform(&view_buf),
            Bind::Uniform(&gather_buf),
            Bind::Read(&heads_buf),
            Bind::Read(&nodes_buf),
            Bind::Read(&geom_buf),
            Bind::Read(&materials_buf),
            Bind::Write(&acc_buf),
            Bind::Write(&direct_acc_buf),
            Bind::Write(&counters_buf),
            Bind::Read(&subset_buf),
        ];
        let gather_layout = layout_of(&ctx, "obscurance gather layout", S::COMPUTE, &gather_binds);
        let gather_pipeline = compute_pipeline(&ctx, "obscurance gather", &gather_module, "gather", &gather_layout);
        let gather_bg = group_of(&ctx, "obscurance gather bindings", &gather_layout, &gather_binds);

        // Sun and directional lights: only when there are some (DESIGN section 6). One
        // orthographic map at a time in the shared atlas (gpu::shadow), redrawn per light
        // and direction.
        let shadow = if input.lights.is_empty() {
            None
        } else {
            let views_buf = ctx.buffer_zeroed(
                "obscurance sun map view",
                std::mem::size_of::<ShadowView>() as u64,
                U::STORAGE | U::COPY_DST,
            );
            let planes = ctx.buffer_init(
                "obscurance triangle planes (sun maps)",
                &map_triangle_planes(&input.triangles, &frame),
                U::STORAGE,
            );
            let source = AtlasVertices::MapScene { planes: &planes };
            let atlas = ShadowAtlas::new(&ctx, "obscurance sun", n, n, &views_buf, &tables.tables, source)
                .map_err(gpu_error)?;
            let direct_module = ctx.shader(&shaders::OBSCURANCE_DIRECT).map_err(gpu_error)?;
            let direct_binds = [
                Bind::Read(&views_buf),
                Bind::Uniform(&direct_buf),
                Bind::Texture2d(&atlas.plane_view),
                Bind::Read(&geom_buf),
                Bind::Write(&direct_acc_buf),
                Bind::Read(&subset_buf),
            ];
            let direct_layout = layout_of(&ctx, "obscurance direct layout", S::COMPUTE, &direct_binds);
            let direct_pipeline = compute_pipeline(&ctx, "obscurance direct", &direct_module, "direct", &direct_layout);
            let direct_bg = group_of(&ctx, "obscurance direct bindings", &direct_layout, &direct_binds);
            Some(ShadowPass {
                views_buf,
                atlas,
                direct_pipeline,
                direct_bg,
            })
        };
        ctx.take_error("obscurance setup").map_err(gpu_error)?;
        let mut sources = LightSources::PUNCTUAL;
        if params.emitters != EmitterLight::Gathered {
            sources = sources.with(LightSources::EMITTERS);
        }
        let shared_direct = DirectLight::new(
            ctx.clone(),
            "obscurance",
            &inputs.rays,
            atlas,
            &inputs.lighting,
            inputs.seed,
            sources,
            Some(&sampled),
            params.light_samples,
            false,
        )
        .map_err(gpu_error)?;

        Ok(Obscurance {
            directions: Directions::new(params.directions, inputs.seed),
            rng: SplitMix64::new(inputs.seed ^ 0x0B5C_0A4C_E000_0001),
            seed: inputs.seed,
            ctx,
            params,
            notes,
            want_direct: inputs.want_direct,
            n_texels,
            lm_pixels: width * height,
            width,
            height,
            texel_pixels: atlas.texels.iter().map(|t| t.pixel).collect(),
            texel_area,
            mesh_names: scene.meshes.iter().map(|m| m.name.clone()).collect(),
            lighting: inputs.lighting,
            corners,
            dmax_norm,
            r_ave,
            eq5_ambient,
            environment: input.environment,
            lights: input.lights,
            steps_done: 0,
            half_steps: [0, 0],
            dirs: [0, 0],
            subset_len: None,
            node_capacity,
            last_ao: None,
            last_ambient: None,
            last_stats: LayerStats::default(),
            shared_direct,
            deadline: None,
            progress: None,
            slicer: StepSlicer::per_unit("obscurance directions"),
            layer_part: LAYER_PART_TRIANGLES,
            vertex_count: vertices.len() as u32,
            vertex_buf,
            view_buf,
            gather_buf,
            direct_buf,
            heads_buf,
            counters_buf,
            acc_buf,
            direct_acc_buf,
            subset_buf,
            dummy_view,
            shadow,
            layers_pipeline,
            gather_pipeline,
            layers_bg,
            gather_bg,
        })
    }
}
