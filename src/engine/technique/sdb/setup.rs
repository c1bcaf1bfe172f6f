//! `sdb`'s engine set up: the scene, texels and lights uploaded, and the passes the
//! input needs built (maps, resolve, gather, direct light, small emitters, sun maps),
//! with the device's limits checked first; and what the engine answers about itself.

use std::sync::Arc;

use bytemuck::Zeroable;
use glam::Vec3;

use crate::engine::gpu::directions::{Directions, SplitMix64};
use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::layout::{Bind, compute_pipeline, group_at, group_of, layout_at, layout_of};
use crate::engine::gpu::map_scene::DirectionalLight;
use crate::engine::gpu::scene_rays::opaque_material_tables;
use crate::engine::gpu::shadow::{AtlasVertices, ShadowAtlas, ShadowView, map_triangle_planes};
use crate::engine::gpu::slices::StepSlicer;
use crate::engine::gpu::texels::GpuTexelGeom;
use crate::engine::gpu::view::cullable_triangles;
use crate::engine::gpu::view::{
    GpuDims, GpuVertex, GpuView, NO_TEXEL, TRI_CULL_BACK, TRI_DOUBLE_SIDED, TRI_TEXTURED_EMISSION, fill_map,
};
use crate::engine::gpu::{self, GpuContext, GpuError};

use super::{
    AccumulationMode, GpuDirectParams, GpuEmitterAddParams, GpuGatherParams, GpuResolveParams, GpuTexelShade,
    GpuTriInfo, MAX_AMBIENT_GAIN, SdbEngine, SdbInput, SdbParams, SmallEmitterPass, SunMaps, shaders,
};

impl SdbEngine {
    /// Upload the scene and build the passes. Only the passes the input needs are
    /// created: no shadow maps or direct pass without directional lights.
    pub fn new(ctx: Arc<GpuContext>, input: SdbInput, params: SdbParams) -> Result<Self, GpuError> {
        if params.map_pixels() > ctx.limits.max_texture_dimension_2d {
            return Err(GpuError::Unsupported {
                adapter: ctx.info.name.clone(),
                missing: format!(
                    "illumination map {0}x{0} exceeds max texture size {1}",
                    params.map_pixels(),
                    ctx.limits.max_texture_dimension_2d
                ),
            });
        }
        let (width, height) = (input.width.max(1), input.height.max(1));
        let n_texels = input.texels.len() as u32;
        let storage_need = (width as u64 * height as u64).max(2 * n_texels as u64) * 16;
        ctx.check_storage(&format!("sdb: a {width}x{height} lightmap"), storage_need)?;

        // Normalised scene space: bounds of triangles and texel points together.
        let frame = SceneFrame::of_points(
            input
                .triangles
                .iter()
                .flat_map(|t| t.p)
                .chain(input.texels.iter().map(|t| t.position)),
        );
        let scale = frame.radius;
        let norm = |p: Vec3| frame.norm(p);
        let corners = frame.corners();

        let cullable = cullable_triangles(&input.triangles);
        let mut vertices = Vec::with_capacity(input.triangles.len() * 3);
        let mut tris = Vec::with_capacity(input.triangles.len());
        for (i, t) in input.triangles.iter().enumerate() {
            vertices.extend(GpuVertex::corners(i as u32, t, norm));
            let mut flags = 0;
            if t.double_sided {
                flags |= TRI_DOUBLE_SIDED;
            } else if cullable[i] {
                flags |= TRI_CULL_BACK;
            }
            if t.emission_textured {
                flags |= TRI_TEXTURED_EMISSION;
            }
            tris.push(GpuTriInfo {
                emission: t.emission.to_array(),
                flags,
            });
        }
        let geom: Vec<GpuTexelGeom> = input
            .texels
            .iter()
            .map(|t| GpuTexelGeom::new(&frame, t.position, t.normal, t.geo_normal))
            .collect();
        // The texel's area in normalised units rides in the albedo's spare channel (only
        // the ambient-mode mean reads it; relative areas are all it needs).
        let area = |k: usize| {
            input
                .ambient
                .as_ref()
                .map_or(0.0, |a| a.texel_area[k] / (scale * scale))
        };
        let shade: Vec<GpuTexelShade> = input
            .texels
            .iter()
            .enumerate()
            .map(|(k, t)| GpuTexelShade {
                albedo: t.albedo.extend(area(k)).to_array(),
            })
            .collect();
        let fill = fill_map(width, height, &input.texels);

        use wgpu::BufferUsages as U;
        let vertex_buf = ctx.buffer_init("sdb vertices", &vertices, U::VERTEX);
        let tris_buf = ctx.buffer_init("sdb triangle info", &tris, U::STORAGE);
        let geom_buf = ctx.buffer_init("sdb texel geometry", &geom, U::STORAGE);
        let shade_buf = ctx.buffer_init("sdb texel materials", &shade, U::STORAGE);
        let fill_buf = ctx.buffer_init("sdb lightmap fill map", &fill, U::STORAGE);
        let radiance_buf = ctx.buffer_zeroed("sdb outgoing radiance", width as u64 * height as u64 * 16, U::STORAGE);
        let acc_buf = ctx.buffer_zeroed(
            "sdb accumulators (even, odd)",
            n_texels as u64 * 2 * 16,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let want_direct = input.want_direct;
        let direct_acc_buf = want_direct.then(|| {
            ctx.buffer_zeroed(
                "sdb direct accumulators (even, odd)",
                n_texels as u64 * 2 * 16,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            )
        });
        let has_light_acc = !input.lights.is_empty() || input.small_lights.is_some();
        let sun_acc_buf = has_light_acc.then(|| {
            ctx.buffer_zeroed(
                "sdb sun and directional light accumulators (even, odd)",
                n_texels as u64 * 2 * 16,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            )
        });
        let ambient_buf = ctx.buffer_zeroed("sdb ambient mode state", 32, U::STORAGE);
        let fed_buf = ctx.buffer_zeroed("sdb estimate fed per texel", n_texels as u64 * 16, U::STORAGE);
        let fed_acc_buf = ctx.buffer_zeroed(
            "sdb fed estimate accumulators (even, odd)",
            n_texels as u64 * 2 * 16,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let ambient_factor = match (&input.ambient, params.mode) {
            (Some(a), AccumulationMode::Average) => {
                let g = a.gain.clamp(Vec3::ZERO, Vec3::splat(MAX_AMBIENT_GAIN));
                Some(g / (Vec3::ONE - g))
            }
            // The leaky blend forgets on purpose; a mean of everything fed does not apply.
            _ => None,
        };
        let view_buf = ctx.uniform("sdb view", &GpuView::zeroed());
        let dims_buf = ctx.uniform(
            "sdb lightmap dims",
            &GpuDims {
                dims: [width, height, n_texels, 0],
            },
        );
        let resolve_buf = ctx.uniform("sdb resolve params", &GpuResolveParams::zeroed());
        let gather_buf = ctx.uniform("sdb gather params", &GpuGatherParams::zeroed());
        let direct_buf = ctx.uniform("sdb direct params", &GpuDirectParams::zeroed());

        // Emitted radiance per lightmap pixel: the emission of triangles with an emissive
        // texture (the others use their material's exact value).
        let emission_px_buf = {
            let px: Vec<[f32; 4]> = fill
                .iter()
                .map(|&k| {
                    if k == NO_TEXEL {
                        [0.0; 4]
                    } else {
                        input.texels[k as usize].emission.extend(1.0).to_array()
                    }
                })
                .collect();
            ctx.buffer_init("sdb emission per lightmap pixel", &px, U::STORAGE)
        };
        let extent = wgpu::Extent3d {
            width: params.map_pixels(),
            height: params.map_pixels(),
            depth_or_array_layers: 1,
        };
        let layers = params.depth_layers;
        let layered = wgpu::Extent3d {
            depth_or_array_layers: layers,
            ..extent
        };
        let illum_tex = ctx.texture_2d(
            "sdb illumination map (rgb radiance, a distance), one layer per depth draw",
            layered,
            wgpu::TextureFormat::Rgba32Float,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let depth_tex = ctx.texture_2d(
            "sdb illumination map depth",
            extent,
            wgpu::TextureFormat::Depth32Float,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
        );
        let emission_tex = want_direct.then(|| {
            ctx.texture_2d(
                "sdb illumination map emission",
                layered,
                wgpu::TextureFormat::Rgba32Float,
                wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            )
        });
        // Per-layer views to render into; one array view for the compute passes.
        let layer_views = |t: &wgpu::Texture, label: &str| -> Vec<wgpu::TextureView> {
            (0..layers)
                .map(|l| {
                    t.create_view(&wgpu::TextureViewDescriptor {
                        label: Some(&format!("{label} layer {l}")),
                        dimension: Some(wgpu::TextureViewDimension::D2),
                        base_array_layer: l,
                        array_layer_count: Some(1),
                        ..Default::default()
                    })
                })
                .collect()
        };
        let array_view = |t: &wgpu::Texture, label: &str| {
            t.create_view(&wgpu::TextureViewDescriptor {
                label: Some(label),
                dimension: Some(wgpu::TextureViewDimension::D2Array),
                ..Default::default()
            })
        };
        let emission_layer_views = emission_tex
            .as_ref()
            .map(|t| layer_views(t, "sdb illumination emission"));
        let emission_view = emission_tex
            .as_ref()
            .map(|t| array_view(t, "sdb illumination emission array view"));
        let illum_layer_views = layer_views(&illum_tex, "sdb illumination map");
        let illum_view = array_view(&illum_tex, "sdb illumination map array view");
        let depth_view = depth_tex.create_view(&wgpu::TextureViewDescriptor {
            label: Some("sdb illumination depth view"),
            ..Default::default()
        });

        use wgpu::ShaderStages as S;
        // Resolve.
        let resolve_module = ctx.shader(&shaders::SDB_RESOLVE)?;
        let resolve_binds = [
            Bind::Uniform(&resolve_buf),
            Bind::Read(&fill_buf),
            Bind::Read(&shade_buf),
            Bind::Read(&acc_buf),
            Bind::Write(&radiance_buf),
            // Without lights the shader reads no sun accumulators (dims.w = 0); the
            // binding still needs a buffer, so it aliases the gathered ones.
            Bind::Read(sun_acc_buf.as_ref().unwrap_or(&acc_buf)),
            Bind::Write(&ambient_buf),
            Bind::Write(&fed_buf),
            Bind::Read(&fed_acc_buf),
        ];
        let resolve_layout = layout_of(&ctx, "sdb resolve layout", S::COMPUTE, &resolve_binds);
        let resolve_pipeline = compute_pipeline(&ctx, "sdb resolve", &resolve_module, "resolve", &resolve_layout);
        let ambient_pipeline = compute_pipeline(
            &ctx,
            "sdb ambient mode",
            &resolve_module,
            "ambient_mode",
            &resolve_layout,
        );
        let resolve_bg = group_of(&ctx, "sdb resolve bindings", &resolve_layout, &resolve_binds);

        // The alpha test's tables: the scene's, or every material opaque.
        let opaque_tables;
        let tables_buf = match &input.tables {
            Some(t) => &t.tables,
            None => {
                let materials = input.triangles.iter().map(|t| t.material + 1).max().unwrap_or(1);
                opaque_tables = ctx.buffer_init(
                    "sdb opaque materials",
                    &opaque_material_tables(materials),
                    wgpu::BufferUsages::STORAGE,
                );
                &opaque_tables
            }
        };

        // Illumination map (and shadow maps).
        let illum_module = ctx.shader(&shaders::SDB_ILLUMINATION)?;
        let illum_binds = [
            Bind::Uniform(&view_buf),
            Bind::Uniform(&dims_buf),
            Bind::Read(&tris_buf),
            Bind::Read(&radiance_buf),
            Bind::Read(&emission_px_buf),
            Bind::Read(tables_buf),
        ];
        let illum_layout = layout_of(&ctx, "sdb illumination layout", S::VERTEX_FRAGMENT, &illum_binds);
        let illum_groups: Vec<Option<&wgpu::BindGroupLayout>> = vec![Some(&illum_layout)];
        let illum_pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("sdb illumination pipeline layout"),
            bind_group_layouts: &illum_groups,
            immediate_size: 0,
        });
        let target = Some(wgpu::ColorTargetState {
            format: wgpu::TextureFormat::Rgba32Float,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        });
        let targets = if want_direct {
            vec![target.clone(), target]
        } else {
            vec![target]
        };
        let illum_pipeline = ctx.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("sdb illumination map"),
            layout: Some(&illum_pl),
            vertex: wgpu::VertexState {
                module: &illum_module,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<GpuVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &GpuVertex::ATTRIBUTES,
                })],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                front_face: wgpu::FrontFace::Ccw,
                // Culling is decided per triangle in the fragment shader (closed meshes
                // vs open or double-sided geometry), and shadow maps keep every face.
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: wgpu::TextureFormat::Depth32Float,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &illum_module,
                entry_point: Some(if want_direct { "fs_main_direct" } else { "fs_main" }),
                compilation_options: Default::default(),
                targets: &targets,
            }),
            multiview_mask: None,
            cache: None,
        });
        let illum_bg = group_of(&ctx, "sdb illumination bindings", &illum_layout, &illum_binds);

        // Gather.
        let gather_module = ctx.shader(&shaders::SDB_GATHER)?;
        let gather_binds = [
            Bind::Uniform(&view_buf),
            Bind::Uniform(&gather_buf),
            Bind::Texture(&illum_view),
            Bind::Read(&geom_buf),
            Bind::Write(&acc_buf),
            Bind::Read(&fed_buf),
            Bind::Write(&fed_acc_buf),
        ];
        let gather_layout = layout_of(&ctx, "sdb gather layout", S::COMPUTE, &gather_binds);
        // Group 1 of the direct-layer gather: the emission map and the direct accumulators
        // (placeholders of the same kinds when there is no direct layer: the layout only).
        let gather_direct_layout = layout_of(
            &ctx,
            "sdb gather direct layout",
            S::COMPUTE,
            &[Bind::Texture(&illum_view), Bind::Write(&acc_buf)],
        );
        let gather_pipeline = if want_direct {
            let pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("sdb gather (direct layer)"),
                bind_group_layouts: &[Some(&gather_layout), Some(&gather_direct_layout)],
                immediate_size: 0,
            });
            ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("sdb gather (direct layer)"),
                layout: Some(&pl),
                module: &gather_module,
                entry_point: Some("gather_direct"),
                compilation_options: Default::default(),
                cache: None,
            })
        } else {
            compute_pipeline(&ctx, "sdb gather", &gather_module, "gather", &gather_layout)
        };
        let gather_direct_bg = match (&emission_view, &direct_acc_buf) {
            (Some(view), Some(direct_acc)) if want_direct => Some(group_of(
                &ctx,
                "sdb gather direct bindings",
                &gather_direct_layout,
                &[Bind::Texture(view), Bind::Write(direct_acc)],
            )),
            _ => None,
        };
        let gather_bg = group_of(&ctx, "sdb gather bindings", &gather_layout, &gather_binds);

        // Direct light: only with directional lights (DESIGN.md section 6), each drawn in
        // turn as one orthographic map of the shared shadow atlas (gpu::shadow).
        let sun_maps = match &sun_acc_buf {
            Some(sun_acc) if !input.lights.is_empty() => {
                let module = ctx.shader(&shaders::SDB_DIRECT)?;
                let n = params.map_pixels();
                let views_buf = ctx.buffer_zeroed(
                    "sdb sun map view",
                    std::mem::size_of::<ShadowView>() as u64,
                    U::STORAGE | U::COPY_DST,
                );
                let planes = ctx.buffer_init(
                    "sdb triangle planes (sun maps)",
                    &map_triangle_planes(&input.triangles, &frame),
                    U::STORAGE,
                );
                let source = AtlasVertices::MapScene { planes: &planes };
                let atlas = ShadowAtlas::new(&ctx, "sdb sun", n, n, &views_buf, tables_buf, source)?;
                let binds = [
                    Bind::Read(&views_buf),
                    Bind::Uniform(&direct_buf),
                    Bind::Texture2d(&atlas.plane_view),
                    Bind::Read(&geom_buf),
                    Bind::Write(sun_acc),
                ];
                let layout = layout_of(&ctx, "sdb direct layout", S::COMPUTE, &binds);
                let pipeline = compute_pipeline(&ctx, "sdb direct", &module, "direct", &layout);
                let bg = group_of(&ctx, "sdb direct bindings", &layout, &binds);
                Some(SunMaps {
                    views_buf,
                    atlas,
                    pipeline,
                    bg,
                })
            }
            _ => None,
        };
        // Emitters too small for the map, point and spot lights: the direct-light pass's
        // latest estimate per half, folded into the light accumulators.
        let small_emitters = match (input.small_lights, &sun_acc_buf) {
            (Some(lights), Some(sun_acc)) => {
                let module = ctx.shader(&shaders::SDB_DIRECT)?;
                let params_buf = ctx.uniform("sdb small emitters params", &GpuEmitterAddParams::zeroed());
                // Bindings 4..6 of sdb/direct.wgsl (0..3 belong to its `direct` entry point).
                let binds = [
                    Bind::Write(sun_acc),
                    Bind::Read(lights.light.accumulators()),
                    Bind::Uniform(&params_buf),
                ];
                let layout = layout_at(&ctx, "sdb small emitters layout", 4, S::COMPUTE, &binds);
                let pipeline = compute_pipeline(&ctx, "sdb small emitters", &module, "emitter_add", &layout);
                let bg = group_at(&ctx, "sdb small emitters bindings", &layout, 4, &binds);
                Some(SmallEmitterPass {
                    lights,
                    params: params_buf,
                    pipeline,
                    bg,
                })
            }
            _ => None,
        };
        ctx.take_error("sdb setup")?;

        let lights = input
            .lights
            .iter()
            .map(|l| DirectionalLight {
                direction: l.direction.normalize(),
                ..*l
            })
            .collect();
        Ok(SdbEngine {
            texel_dispatch: gpu::dispatch_size_64(n_texels),
            pixel_dispatch: gpu::dispatch_size_64(width * height),
            deadline: None,
            progress: None,
            slicer: StepSlicer::per_unit("sdb directions"),
            receivers: 0..n_texels,
            starts_lit: false,
            directions: Directions::new(params.directions, input.seed),
            rng: SplitMix64::new(input.seed ^ 0x0A11_CE5E_ED00_0001),
            ctx,
            params,
            n_texels,
            lm_dims: [width, height, n_texels, u32::from(has_light_acc)],
            corners,
            scale,
            environment: input.environment,
            lights,
            steps_done: 0,
            dirs: [0, 0],
            weights: [0.0, 0.0],
            half_steps: [0, 0],
            vertex_count: vertices.len() as u32,
            vertex_buf,
            view_buf,
            resolve_buf,
            gather_buf,
            direct_buf,
            acc_buf,
            direct_acc_buf,
            sun_acc_buf,
            fed_acc_buf,
            small_emitters,
            ambient_factor,
            ambient_pipeline,
            illum_layer_views,
            emission_layer_views,
            gather_direct_bg,
            depth_view,
            resolve_pipeline,
            illum_pipeline,
            gather_pipeline,
            resolve_bg,
            illum_bg,
            gather_bg,
            sun_maps,
        })
    }

    pub fn params(&self) -> &SdbParams {
        &self.params
    }

    /// Blocks until the device has done every step submitted so far
    /// ([`Technique::wait_for_steps`](super::super::api::Technique::wait_for_steps)).
    pub fn wait_idle(&self) -> Result<(), GpuError> {
        self.ctx.wait_idle()
    }

    pub fn steps_done(&self) -> u64 {
        self.steps_done
    }

    pub fn texel_count(&self) -> u32 {
        self.n_texels
    }

    /// Block until the GPU has finished every submitted step (benchmarks).
    pub fn finish(&self) -> Result<(), GpuError> {
        self.ctx.wait_idle()?;
        self.ctx.take_error("sdb step")
    }

    /// The adapter this engine runs on.
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        &self.ctx.info
    }

    /// Scene radius in input units (for reports).
    pub fn scene_radius(&self) -> f32 {
        self.scale
    }
}
