//! The shadow-map atlas shared by the techniques that shadow lights or VPLs with depth
//! maps: every map of one step (perspective cube faces around points, orthographic maps
//! along distant lights) packed into one Rgba32Float + Depth32Float texture and drawn in
//! one render pass (`shaders/gpu/shadow_atlas.wgsl`). Each pixel keeps the *plane* of the
//! nearest surface (unit geometric normal and offset), so a reader asks which side of that
//! plane a receiver lies on: exact behind thin walls at any distance, where a depth compare
//! needs a bias (the module doc of `vpl` measures it).
//!
//! `vpl` renders its lights' and VPLs' maps with it; `hemicube` its shooters' hemicube
//! faces (their views written on the GPU); `sdb` and `obscurance` their sun and
//! directional-light maps, one orthographic view at a time ([`ShadowView::ortho_of`] keeps
//! the pixels of their own map views). The first two draw [`ShadowVertex`]es, which carry
//! each triangle's plane; the last two draw from the vertex buffer they already hold for
//! their own maps and a plane a triangle ([`AtlasVertices`]), so no technique uploads the
//! scene's geometry twice. Readers test visibility with `shaders/gpu/shadow_view.wgsl`'s
//! `shadow_pcf` / `shadow_ortho`. The layout is fixed for a bake: shelves of
//! equal-height tiles, largest first.
//!
//! Alpha (issue 19 point 5): each corner carries its material and the UV its base colour
//! texture reads ([`ShadowVertex`]), and the fragment shader drops what glTF alpha cuts
//! away (`gpu/materials.wgsl`, the tables of `gpu::scene_rays`): MASK below its cutoff;
//! BLEND with probability 1 − coverage, drawn from a hash of the pixel, the triangle's
//! plane and the view, so a map that moves between steps (VPLs, the sun's jittered
//! direction, the hemicube's shooters) redraws it, and a fixed one keeps a fixed dither
//! that receivers average over its pixels.
//!
//! Limits: the atlas must fit the device's largest 2D texture; [`pack`] says how large it
//! would have been when it does not, and the technique names its own parameters to lower.

use bytemuck::{Pod, Zeroable};
use glam::{Vec2, Vec3};

use crate::engine::gpu::frame::SceneFrame;
use crate::engine::gpu::layout::{Bind, group_of, layout_of};
use crate::engine::gpu::map_scene::MapTriangle;
use crate::engine::gpu::slices::{Sliced, StepSlicer};
use crate::engine::gpu::view::GpuView;
use crate::engine::gpu::{GpuContext, GpuError, shaders};
use crate::engine::scene::Scene;

/// [`ShadowVertex`]'s attributes, locations 0-3 in field order.
const SHADOW_VERTEX_ATTRIBUTES: [wgpu::VertexAttribute; 4] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x4, 2 => Float32x2, 3 => Uint32];

/// One triangle corner as the atlas draws it (`vs_shadow`'s vertex inputs).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct ShadowVertex {
    /// In the technique's normalised frame.
    pub position: [f32; 3],
    /// The triangle's unit geometric normal and <n, p> in that frame, the same at its
    /// three corners: what a map pixel stores.
    pub plane: [f32; 4],
    /// The corner's UV in the set its material's base colour texture reads (alpha).
    pub alpha_uv: [f32; 2],
    pub material: u32,
}

/// Every triangle of `scene` as three [`ShadowVertex`]es, in `frame`.
pub fn shadow_vertices(scene: &Scene, frame: &SceneFrame) -> Vec<ShadowVertex> {
    scene
        .triangles
        .iter()
        .flat_map(|t| corners(t.p, t.geometric_normal(), scene.base_color_uvs(t), t.material, frame))
        .collect()
}

/// The plane (unit geometric normal, offset in `frame`) of every triangle of a map scene
/// (`gpu::map_scene`, what `sdb` and `obscurance` draw their maps from), in triangle order:
/// what [`AtlasVertices::MapScene`] reads per triangle. A degenerate triangle's normal is
/// zero, which blocks nothing.
pub fn map_triangle_planes(triangles: &[MapTriangle], frame: &SceneFrame) -> Vec<[f32; 4]> {
    triangles
        .iter()
        .map(|t| {
            let n = (t.p[1] - t.p[0]).cross(t.p[2] - t.p[0]).normalize_or_zero();
            [n.x, n.y, n.z, n.dot(frame.norm(t.p[0]))]
        })
        .collect()
}

/// One triangle's corners: its plane (unit normal `n`) is the same at all three.
fn corners(p: [Vec3; 3], n: Vec3, uv: [Vec2; 3], material: u32, frame: &SceneFrame) -> [ShadowVertex; 3] {
    let c = n.dot(frame.norm(p[0]));
    [0, 1, 2].map(|k| ShadowVertex {
        position: frame.norm(p[k]).to_array(),
        plane: [n.x, n.y, n.z, c],
        alpha_uv: uv[k].to_array(),
        material,
    })
}

/// A perspective cube face (90 degrees) around a point.
pub const VIEW_PERSPECTIVE: u32 = 0;
/// An orthographic map along a distant light.
pub const VIEW_ORTHO: u32 = 1;

/// One map of the atlas (`ShadowView` in `shaders/gpu/shadow_view.wgsl`), in the
/// normalised scene frame.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct ShadowView {
    pub origin: [f32; 4],
    pub right: [f32; 4],
    pub up: [f32; 4],
    pub fwd: [f32; 4],
    pub rect: [u32; 4],
}

impl ShadowView {
    /// The orthographic map `view` (a [`make_view`](crate::engine::gpu::view::make_view) map along a distant light: its
    /// lateral square, pixel count and depth range) as one map of the atlas, at tile
    /// corner `at`: the same pixels, so a technique that jitters and fits its maps with
    /// `make_view` keeps its sampling when it draws them here.
    pub fn ortho_of(view: &GpuView, at: [u32; 2]) -> ShadowView {
        let [right, up, dir] = [view.right, view.up, view.dir].map(|v| Vec3::new(v[0], v[1], v[2]));
        let (a0, b0, t0) = (view.right[3], view.up[3], view.dir[3]);
        let [span, range, pixels, _] = view.extent;
        let half = 0.5 * span;
        let origin = right * (a0 + half) + up * (b0 + half) + dir * t0;
        ShadowView {
            origin: [origin.x, origin.y, origin.z, 0.0],
            right: [right.x, right.y, right.z, half],
            up: [up.x, up.y, up.z, 0.0],
            fwd: [dir.x, dir.y, dir.z, range],
            rect: [at[0], at[1], pixels as u32, VIEW_ORTHO],
        }
    }
}

/// The six faces of a cube in the frame (t, b, n): +t, -t, +b, -b, +n, -n (the order
/// vpl/gather.wgsl's face selection uses), as (forward, right, up).
pub fn cube_faces(t: Vec3, b: Vec3, n: Vec3) -> [(Vec3, Vec3, Vec3); 6] {
    [(t, b, n), (-t, b, n), (b, n, t), (-b, n, t), (n, t, b), (-n, t, b)]
}

/// The atlas would exceed the device's largest texture.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AtlasTooLarge {
    pub maps: usize,
    pub width: u32,
    pub height: u32,
    pub max_dim: u32,
}

// Shadow atlas layout
// ---------------------------------------------------------------------------------------

/// Tile rectangles of every shadow view, fixed for the bake: shelves of equal-height
/// tiles, largest first.
#[derive(Debug, Clone)]
pub struct ShadowAtlasLayout {
    pub width: u32,
    pub height: u32,
    /// Per view: x, y of its top-left pixel and its side.
    pub rects: Vec<[u32; 3]>,
}

/// Packs maps of the given sides into one atlas no larger than `max_dim` on a side.
pub fn pack(sizes: &[u32], max_dim: u32) -> Result<ShadowAtlasLayout, AtlasTooLarge> {
    if sizes.is_empty() {
        return Ok(ShadowAtlasLayout {
            width: 1,
            height: 1,
            rects: vec![],
        });
    }
    let area: u64 = sizes.iter().map(|&s| s as u64 * s as u64).sum();
    let largest = *sizes.iter().max().expect("non-empty");
    let width = ((area as f64).sqrt().ceil() as u32)
        .next_power_of_two()
        .max(largest)
        .min(max_dim);
    let mut order: Vec<usize> = (0..sizes.len()).collect();
    order.sort_by_key(|&i| std::cmp::Reverse(sizes[i]));
    let mut rects = vec![[0u32; 3]; sizes.len()];
    let (mut x, mut y, mut row) = (0u32, 0u32, 0u32);
    for i in order {
        let s = sizes[i];
        if x + s > width {
            x = 0;
            y += row;
            row = 0;
        }
        rects[i] = [x, y, s];
        x += s;
        row = row.max(s);
    }
    let height = y + row;
    if height > max_dim || largest > max_dim {
        return Err(AtlasTooLarge {
            maps: sizes.len(),
            width,
            height,
            max_dim,
        });
    }
    Ok(ShadowAtlasLayout { width, height, rects })
}

/// What the atlas draws the scene from.
#[derive(Debug, Clone, Copy)]
pub enum AtlasVertices<'a> {
    /// [`ShadowVertex`]es ([`shadow_vertices`]): every corner carries its triangle's plane
    /// (`vpl`, `hemicube`, which draw nothing else).
    Planes,
    /// The technique's own map-scene vertex buffer ([`GpuVertex`](crate::engine::gpu::view::GpuVertex),
    /// `sdb`, `obscurance`) and one plane a triangle ([`map_triangle_planes`], 16 bytes
    /// where a second vertex buffer would cost 120), so the scene is not uploaded twice.
    MapScene { planes: &'a wgpu::Buffer },
}

/// The plane-storing shadow-map pass (`shaders/gpu/shadow_atlas.wgsl`): a render pipeline that
/// draws the scene into one tile of an Rgba32Float + Depth32Float atlas per view (each
/// pixel keeps the plane of the nearest surface, both faces of every triangle drawn),
/// and its bind group on `views` (each view's matrix and tile) and `tables` (the scene's
/// materials and textures, `gpu::scene_rays`, for the alpha test). `hemicube` draws its
/// hemicube faces with the same pass.
pub fn shadow_pass(
    ctx: &GpuContext,
    label: &str,
    views: &wgpu::Buffer,
    tables: &wgpu::Buffer,
    source: AtlasVertices<'_>,
) -> Result<(wgpu::RenderPipeline, wgpu::BindGroup), GpuError> {
    let module = ctx.shader(&shaders::SHADOW_ATLAS)?;
    let mut binds = vec![Bind::Read(views), Bind::Read(tables)];
    let (entry, vertex_layout) = match source {
        AtlasVertices::Planes => (
            "vs_shadow",
            wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<ShadowVertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &SHADOW_VERTEX_ATTRIBUTES,
            },
        ),
        AtlasVertices::MapScene { planes } => {
            binds.push(Bind::Read(planes));
            (
                "vs_shadow_map",
                wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<crate::engine::gpu::view::GpuVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &crate::engine::gpu::view::GpuVertex::ATTRIBUTES,
                },
            )
        }
    };
    let layout = layout_of(
        ctx,
        &format!("{label} layout"),
        wgpu::ShaderStages::VERTEX_FRAGMENT,
        &binds,
    );
    let pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(&format!("{label} pipeline layout")),
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let pipeline = ctx.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout: Some(&pl),
        vertex: wgpu::VertexState {
            module: &module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            buffers: &[Some(vertex_layout)],
        },
        primitive: wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleList,
            // Every face blocks light, single-sided back faces included.
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
            module: &module,
            entry_point: Some("fs_shadow"),
            compilation_options: Default::default(),
            targets: &[Some(wgpu::ColorTargetState {
                format: wgpu::TextureFormat::Rgba32Float,
                blend: None,
                write_mask: wgpu::ColorWrites::ALL,
            })],
        }),
        multiview_mask: None,
        cache: None,
    });
    let bg = group_of(ctx, &format!("{label} bindings"), &layout, &binds);
    Ok((pipeline, bg))
}

/// The atlas's textures and its render pass, owned by the technique that draws into it.
pub struct ShadowAtlas {
    /// Rgba32Float: per pixel the plane (unit normal, offset) of the nearest surface;
    /// read by the technique's gather pass.
    pub plane_view: wgpu::TextureView,
    depth_view: wgpu::TextureView,
    pipeline: wgpu::RenderPipeline,
    bind_group: wgpu::BindGroup,
    label: String,
}

/// One map to draw: the index of its view in the views buffer (the instance index the
/// vertex shader reads), its tile (x, y, side) and how many of its rows to draw (a
/// hemicube side face needs only its upper half).
#[derive(Debug, Clone, Copy)]
pub struct ShadowDraw {
    pub view: u32,
    pub tile: [u32; 3],
    pub rows: u32,
}

impl ShadowAtlas {
    /// A `width` x `height` atlas whose maps are described by `views` (an array of
    /// [`ShadowView`], written by the technique on the CPU or the GPU), alpha-testing with
    /// the scene's `tables`. Labels start with `label` ("vpl shadow", "hemicube depth").
    pub fn new(
        ctx: &GpuContext,
        label: &str,
        width: u32,
        height: u32,
        views: &wgpu::Buffer,
        tables: &wgpu::Buffer,
        source: AtlasVertices<'_>,
    ) -> Result<Self, GpuError> {
        let size = wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        };
        let texture = |what: &str, format, usage| ctx.texture_2d(&format!("{label} atlas {what}"), size, format, usage);
        let plane = texture(
            "(plane of the nearest surface)",
            wgpu::TextureFormat::Rgba32Float,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let depth = texture(
            "depth",
            wgpu::TextureFormat::Depth32Float,
            wgpu::TextureUsages::RENDER_ATTACHMENT,
        );
        let plane_view = plane.create_view(&wgpu::TextureViewDescriptor {
            label: Some(&format!("{label} atlas view")),
            ..Default::default()
        });
        let depth_view = depth.create_view(&wgpu::TextureViewDescriptor {
            label: Some(&format!("{label} atlas depth view")),
            ..Default::default()
        });
        let (pipeline, bind_group) = shadow_pass(ctx, &format!("{label} maps"), views, tables, source)?;
        Ok(ShadowAtlas {
            plane_view,
            depth_view,
            pipeline,
            bind_group,
            label: label.to_string(),
        })
    }

    /// Records one render pass that clears the atlas and draws every map of `draws` with
    /// the scene's vertices (`vertices`: [`shadow_vertices`], or the map scene's own for
    /// [`AtlasVertices::MapScene`]).
    pub fn render(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        vertices: &wgpu::Buffer,
        vertex_count: u32,
        draws: impl IntoIterator<Item = ShadowDraw>,
    ) {
        self.render_part(encoder, vertices, vertex_count, draws, true);
    }

    /// Draws `draws` in slices of whole maps through `slicer` (a
    /// [`StepSlicer::per_unit`]), each submitted and waited for, asking `go_on` between
    /// two: for a step whose maps grow with the scene (each map is the whole scene drawn:
    /// 0.15-0.65 s a map for a 1M-triangle level on lavapipe). Nothing is put aside: a
    /// step's maps are drawn anew every step, so a stopped step leaves nothing that counts.
    pub fn render_sliced(
        &self,
        ctx: &GpuContext,
        slicer: &mut StepSlicer,
        vertices: &wgpu::Buffer,
        vertex_count: u32,
        draws: &[ShadowDraw],
        go_on: &mut dyn FnMut(u64, u64) -> bool,
    ) -> Result<Sliced, GpuError> {
        let label = format!("{} maps slice", self.label);
        let mut submit = |first: u64, count: u64| {
            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(&label) });
            let part = draws[first as usize..(first + count) as usize].iter().copied();
            self.render_part(&mut encoder, vertices, vertex_count, part, first == 0);
            Ok(ctx.queue.submit([encoder.finish()]))
        };
        slicer.run(ctx, draws.len() as u64, &[], &mut submit, go_on)
    }

    /// As [`ShadowAtlas::render`], for a part of a step's maps: `first` clears the atlas,
    /// a later part keeps the tiles drawn before it. What a step sliced by maps records
    /// (`gpu::slices`: one map is a whole scene drawn, 0.17 s for a 1M-triangle level on
    /// lavapipe). Each map is one draw into its own tile, so the depth buffer is cleared
    /// by every part: no tile's depth is needed across two.
    pub fn render_part(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        vertices: &wgpu::Buffer,
        vertex_count: u32,
        draws: impl IntoIterator<Item = ShadowDraw>,
        first: bool,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some(&format!("{} maps", self.label)),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.plane_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    // n = 0: an empty pixel blocks nothing.
                    load: if first {
                        wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT)
                    } else {
                        wgpu::LoadOp::Load
                    },
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &self.depth_view,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.set_vertex_buffer(0, vertices.slice(..));
        for d in draws {
            let [x, y, s] = d.tile;
            pass.set_viewport(x as f32, y as f32, s as f32, s as f32, 0.0, 1.0);
            pass.set_scissor_rect(x, y, s, d.rows);
            pass.draw(0..vertex_count, d.view..d.view + 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Rust mirrors of WGSL structs have the shaders' sizes (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[Mirror::of::<ShadowView>(
            "ShadowView",
            shaders::SHADOW_ATLAS,
            "ShadowView",
        )]);
    }

    /// A point lands on the same pixel of the atlas map as on the `make_view` map it
    /// was made from (`project_to_map` there, `shadow_view_pixel` here), at the same depth.
    #[test]
    fn an_ortho_map_keeps_its_pixels_in_the_atlas() {
        let corners =
            crate::engine::gpu::frame::SceneFrame::of_points([Vec3::splat(-1.0), Vec3::new(2.0, 1.0, 0.5)]).corners();
        let d = Vec3::new(0.3, -0.9, 0.2).normalize();
        let m = crate::engine::gpu::view::make_view(
            d,
            &corners,
            64,
            (0.37, 0.81),
            0,
            crate::engine::gpu::view::DEPTH_NEAREST,
        );
        let v = ShadowView::ortho_of(&m, [128, 64]);
        let [right, up, dir] = [m.right, m.up, m.dir].map(|r| Vec3::new(r[0], r[1], r[2]));
        for p in [Vec3::ZERO, Vec3::new(0.5, -0.2, 0.1), Vec3::new(-0.7, 0.4, -0.3)] {
            // gpu/common.wgsl's project_to_map.
            let (a, b) = (p.dot(right) - m.right[3], p.dot(up) - m.up[3]);
            let map = glam::Vec2::new(a / m.extent[0] * m.extent[2], (1.0 - b / m.extent[0]) * m.extent[2]);
            // gpu/shadow_view.wgsl's shadow_view_pixel, minus the tile's corner.
            let o = Vec3::new(v.origin[0], v.origin[1], v.origin[2]);
            let q = p - o;
            let ab = glam::Vec2::new(q.dot(right), q.dot(up)) / v.right[3];
            let atlas = glam::Vec2::new(ab.x + 1.0, 1.0 - ab.y) * 0.5 * v.rect[2] as f32;
            assert!((map - atlas).length() < 1e-3, "{p}: {map} against {atlas}");
            // Depth: 0 at the near plane, the map's range at the far one.
            assert!((q.dot(dir) - (p.dot(dir) - m.dir[3])).abs() < 1e-5);
        }
        assert_eq!(v.rect, [128, 64, 64, VIEW_ORTHO]);
    }

    #[test]
    fn the_vertex_is_what_the_pipeline_reads() {
        // Float32x3, Float32x4, Float32x2, Uint32, packed.
        assert_eq!(std::mem::size_of::<ShadowVertex>(), 12 + 16 + 8 + 4);
    }

    #[test]
    fn cube_faces_cover_every_axis() {
        let f = cube_faces(Vec3::X, Vec3::Y, Vec3::Z);
        for (fwd, right, up) in f {
            assert!(fwd.dot(right).abs() < 1e-6 && fwd.dot(up).abs() < 1e-6 && right.dot(up).abs() < 1e-6);
        }
        let fwds: Vec<Vec3> = f.iter().map(|x| x.0).collect();
        assert_eq!(fwds, vec![Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z]);
    }
}
