//! The scene's BVH on the GPU: flattened from the CPU tracer's obvhs BVH into two storage
//! buffers, traversed by `shaders/gpu/bvh.wgsl` (closest hit and any hit), plus the query
//! pass the tests and the traversal benchmark use ([`QueryRunner`]).
//!
//! Build: on the CPU with obvhs (`engine::raytrace::Tracer::bvh`, PLOC with reinsertion
//! and leaf collapse, up to 8 triangles a leaf). obvhs is a maintained builder whose trees
//! trace well (PLOC is what GPU builders use too) and it builds 250k triangles in a
//! fraction of a second on all cores. The CPU's own queries traverse a wide tree built
//! beside this one (`engine::raytrace`), so the GPU and CPU answers are compared as
//! answers (hit triangle, distance), not node for node.
//! A GPU builder would pay off only for scenes rebuilt every frame, which bakes are not.
//!
//! Format (not obvhs's compressed wide BVH, whose CPU traversal dropped hits 7e-5 m from
//! the ray origin through an absolute 1e-4 clip, `engine::raytrace`; a wide format on the
//! GPU was not tried): plain f32 boxes, one 32-byte node
//! ([`GpuNode`]) per BVH2 node in obvhs's order (root 0, children adjacent), each box
//! rounded outward by one ulp per face so that the shader's conservative slab test can
//! never cull a box a ray touches. Triangles ([`GpuTri`], 48 bytes) are stored in leaf
//! order ("slots") as the first vertex and two edges computed exactly as the CPU's
//! Moller-Trumbore computes them, with the scene's triangle index and a flags word
//! (`BVH_TRI_ALPHA_TEST` on triangles of MASK and BLEND materials, whose candidate hits
//! the shader tests against the material's alpha as `Scene::stops_ray` does; and
//! `BVH_TRI_SINGLE_SIDED`, the closest-hit tie rule of `raytrace::BACK_FACE_TIE`).
//! The alpha test reads the materials and textures of `gpu/lights.wgsl` (bindings 2-4),
//! so every pass that traverses the BVH composes that library too, the query pass
//! included.
//!
//! Precision: world space (the scene as imported, re-centred on its bounds), f32, as the
//! CPU tracer; see the shader's header for the traversal's robustness argument.
//!
//! Bounds: the shader's stack has [`BVH_STACK`] entries and a near-first traversal needs at
//! most depth - 1, so [`BvhData::new`] refuses a deeper tree with an error naming the
//! depth (PLOC trees of 250k triangles are 30-40 deep). A scene without triangles gets a
//! one-leaf tree whose only triangle is degenerate, so every binding stays valid and
//! every ray misses. Each buffer must fit the adapter's storage-binding limit (128 MiB on
//! lavapipe: 2.8M triangles); [`GpuBvh::upload`] says so when it does not.

use glam::Vec3;
use obvhs::bvh2::Bvh2;
use wgpu::BufferUsages;

use super::layout::{Bind, compute_pipeline, group_of, layout_of};
use super::scene_lights::GpuSceneLights;
use super::shaders::BVH_QUERY;
use super::{GpuContext, GpuError, dispatch_size_64};
use crate::engine::scene::{AlphaMode, Scene};

/// Entries of the traversal stack in `shaders/gpu/bvh.wgsl` (keep the two equal).
pub const BVH_STACK: u32 = 64;
/// `BvhHit.slot` / `QueryHit::slot` when nothing was hit.
pub const BVH_MISS: u32 = u32::MAX;
/// `QueryHit::slot` when the traversal stack overflowed (never on an accepted tree).
pub const QUERY_OVERFLOW: u32 = u32::MAX - 1;
/// Per-triangle flag: the material is MASK or BLEND, so candidate hits must pass the
/// alpha test (`bvh_alpha_accept` in `shaders/gpu/lights.wgsl`).
pub const BVH_TRI_ALPHA_TEST: u32 = 1;
/// `GpuTri::flags`: the triangle is single-sided, so a coincident front face wins a
/// closest-hit tie against its back (`raytrace::BACK_FACE_TIE`).
pub const BVH_TRI_SINGLE_SIDED: u32 = 2;

/// One BVH2 node as the shader reads it (`BvhNode`).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuNode {
    pub min: [f32; 3],
    /// Inner node: index of the first child (the second follows it); leaf: first slot.
    pub first: u32,
    pub max: [f32; 3],
    /// 0 for an inner node, else the leaf's triangle count.
    pub count: u32,
}

/// One triangle in slot order as the shader reads it (`BvhTri`).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuTri {
    pub p0: [f32; 3],
    /// Index into `Scene::triangles`.
    pub id: u32,
    pub e1: [f32; 3],
    /// `BVH_TRI_*` flags.
    pub flags: u32,
    pub e2: [f32; 3],
    pub pad: u32,
}

/// The flattened tree, on the host.
#[derive(Clone, Debug)]
pub struct BvhData {
    pub nodes: Vec<GpuNode>,
    pub tris: Vec<GpuTri>,
    /// `slot_of[triangle]`: a slot holding scene triangle `triangle` (the BVH has no
    /// spatial splits, so it is the only one).
    pub slot_of: Vec<u32>,
    /// Node depth of the deepest leaf (root = 1).
    pub depth: u32,
}

fn next_up(x: f32) -> f32 {
    if x.is_nan() || x == f32::INFINITY {
        return x;
    }
    if x == 0.0 {
        return f32::from_bits(1);
    }
    let b = x.to_bits();
    f32::from_bits(if x > 0.0 { b + 1 } else { b - 1 })
}

fn next_down(x: f32) -> f32 {
    -next_up(-x)
}

impl BvhData {
    /// Flattens `bvh` (built over `scene.triangles` in order, as `raytrace::Tracer` does).
    pub fn new(bvh: &Bvh2, scene: &Scene) -> Result<Self, GpuError> {
        let n = scene.triangles.len();
        if n == 0 || bvh.nodes.is_empty() {
            return Ok(BvhData {
                nodes: vec![GpuNode {
                    min: [0.0; 3],
                    first: 0,
                    max: [0.0; 3],
                    count: 1,
                }],
                tris: vec![GpuTri {
                    p0: [0.0; 3],
                    id: 0,
                    e1: [0.0; 3],
                    flags: 0,
                    e2: [0.0; 3],
                    pad: 0,
                }],
                slot_of: Vec::new(),
                depth: 1,
            });
        }
        let nodes: Vec<GpuNode> = bvh
            .nodes
            .iter()
            .map(|b| {
                let (lo, hi) = (Vec3::from(b.aabb.min), Vec3::from(b.aabb.max));
                GpuNode {
                    min: lo.to_array().map(next_down),
                    first: b.first_index,
                    max: hi.to_array().map(next_up),
                    count: b.prim_count,
                }
            })
            .collect();
        let mut slot_of = vec![u32::MAX; n];
        let tris: Vec<GpuTri> = bvh
            .primitive_indices
            .iter()
            .enumerate()
            .map(|(slot, &id)| {
                let t = &scene.triangles[id as usize];
                slot_of[id as usize] = slot as u32;
                GpuTri {
                    p0: t.p[0].to_array(),
                    id,
                    e1: (t.p[1] - t.p[0]).to_array(),
                    flags: {
                        let m = scene.material(t);
                        let sided = if m.double_sided { 0 } else { BVH_TRI_SINGLE_SIDED };
                        let alpha = if m.alpha_mode == AlphaMode::Opaque {
                            0
                        } else {
                            BVH_TRI_ALPHA_TEST
                        };
                        sided | alpha
                    },
                    e2: (t.p[2] - t.p[0]).to_array(),
                    pad: 0,
                }
            })
            .collect();
        // Depth by an explicit walk (obvhs's `max_depth` is a stack-size hint, not exact).
        let mut depth = 0u32;
        let mut stack = vec![(0u32, 1u32)];
        while let Some((i, d)) = stack.pop() {
            let node = &nodes[i as usize];
            depth = depth.max(d);
            if node.count == 0 {
                stack.push((node.first, d + 1));
                stack.push((node.first + 1, d + 1));
            }
        }
        if depth > BVH_STACK {
            return Err(GpuError::Unsupported {
                adapter: "GPU BVH".into(),
                missing: format!("the scene's BVH is {depth} levels deep; the GPU traversal's stack holds {BVH_STACK}"),
            });
        }
        if slot_of.contains(&u32::MAX) {
            return Err(GpuError::Device {
                during: "BVH flattening".into(),
                message: "a triangle is in no BVH leaf".into(),
            });
        }
        Ok(BvhData {
            nodes,
            tris,
            slot_of,
            depth,
        })
    }
}

/// The tree in GPU buffers: bind `nodes` at binding 0 and `tris` at binding 1 of any pass
/// built with `shaders::pass_with_bvh!`.
pub struct GpuBvh {
    pub nodes: wgpu::Buffer,
    pub tris: wgpu::Buffer,
    pub data: BvhData,
}

/// An error when `bytes` exceed the device's storage-binding limit, naming `what`.
pub fn check_binding_size(ctx: &GpuContext, what: &str, bytes: u64) -> Result<(), GpuError> {
    let max = ctx.limits.max_storage_buffer_binding_size;
    if bytes > max {
        return Err(GpuError::Unsupported {
            adapter: ctx.info.name.clone(),
            missing: format!("{what} needs a {bytes}-byte storage buffer; the adapter binds at most {max} bytes"),
        });
    }
    Ok(())
}

impl GpuBvh {
    pub fn upload(ctx: &GpuContext, data: BvhData) -> Result<Self, GpuError> {
        check_binding_size(ctx, "the BVH's nodes", std::mem::size_of_val(&data.nodes[..]) as u64)?;
        check_binding_size(ctx, "the BVH's triangles", std::mem::size_of_val(&data.tris[..]) as u64)?;
        let usage = BufferUsages::STORAGE | BufferUsages::COPY_DST;
        Ok(GpuBvh {
            nodes: ctx.buffer_init("bvh nodes", &data.nodes, usage),
            tris: ctx.buffer_init("bvh triangles", &data.tris, usage),
            data,
        })
    }

    /// Flattens and uploads `bvh` over `scene`.
    pub fn new(ctx: &GpuContext, bvh: &Bvh2, scene: &Scene) -> Result<Self, GpuError> {
        Self::upload(ctx, BvhData::new(bvh, scene)?)
    }
}

/// One query ray (`QueryRay` in `shaders/gpu/bvh_query.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct QueryRay {
    pub origin: [f32; 3],
    pub tmax: f32,
    pub dir: [f32; 3],
    /// 0: closest hit; 1: any hit.
    pub mode: u32,
}

/// One query's answer. Closest hit: `slot` is [`BVH_MISS`] on a miss; any hit: `slot` is 1
/// when occluded, 0 when free.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct QueryHit {
    pub t: f32,
    pub slot: u32,
    pub u: f32,
    pub v: f32,
}

/// The query pass over one uploaded scene (its BVH, and the materials the alpha test
/// reads), with buffers for up to `capacity` rays.
pub struct QueryRunner {
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    params: wgpu::Buffer,
    rays: wgpu::Buffer,
    results: wgpu::Buffer,
    capacity: usize,
}

impl QueryRunner {
    pub fn new(ctx: &GpuContext, scene: &GpuSceneLights, capacity: usize) -> Result<Self, GpuError> {
        let capacity = capacity.max(1);
        check_binding_size(ctx, "the query rays", (capacity * 32) as u64)?;
        let module = ctx.shader(&BVH_QUERY)?;
        let params = ctx.uniform("bvh query params", &[0u32; 4]);
        let rays = ctx.buffer_zeroed(
            "bvh query rays",
            (capacity * std::mem::size_of::<QueryRay>()) as u64,
            BufferUsages::STORAGE | BufferUsages::COPY_DST,
        );
        let results = ctx.buffer_zeroed(
            "bvh query results",
            (capacity * std::mem::size_of::<QueryHit>()) as u64,
            BufferUsages::STORAGE | BufferUsages::COPY_SRC,
        );
        let [b0, b1, b2, b3, b4] = scene.binds();
        let binds = [
            b0,
            b1,
            b2,
            b3,
            b4,
            Bind::Uniform(&params),
            Bind::Read(&rays),
            Bind::Write(&results),
        ];
        let layout = layout_of(ctx, "bvh query", wgpu::ShaderStages::COMPUTE, &binds);
        let group = group_of(ctx, "bvh query", &layout, &binds);
        let pipeline = compute_pipeline(ctx, "bvh query", &module, "query", &layout);
        Ok(QueryRunner {
            pipeline,
            group,
            params,
            rays,
            results,
            capacity,
        })
    }

    /// Uploads `rays` (at most `capacity`) for the next [`QueryRunner::dispatch`].
    pub fn load(&self, ctx: &GpuContext, rays: &[QueryRay]) {
        assert!(rays.len() <= self.capacity, "more rays than the runner holds");
        ctx.queue.write_buffer(&self.rays, 0, bytemuck::cast_slice(rays));
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&[rays.len() as u32, 0, 0, 0]));
    }

    /// Traces the first `count` loaded rays and waits for the GPU (no readback).
    pub fn dispatch(&self, ctx: &GpuContext, count: usize) -> Result<(), GpuError> {
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("bvh query"),
        });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("bvh query"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &self.group, &[]);
            let (x, y) = dispatch_size_64(count as u32);
            pass.dispatch_workgroups(x, y, 1);
        }
        ctx.queue.submit([enc.finish()]);
        ctx.wait_idle()?;
        ctx.take_error("bvh query")
    }

    /// Traces `rays` and returns one answer each.
    pub fn run(&self, ctx: &GpuContext, rays: &[QueryRay]) -> Result<Vec<QueryHit>, GpuError> {
        let mut out = Vec::with_capacity(rays.len());
        for chunk in rays.chunks(self.capacity) {
            self.load(ctx, chunk);
            self.dispatch(ctx, chunk.len())?;
            out.extend(ctx.read_buffer::<QueryHit>("bvh query results", &self.results, chunk.len())?);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Rust mirrors of WGSL structs have the shaders' sizes (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[
            Mirror::of::<GpuNode>("GpuNode", crate::engine::gpu::shaders::BVH_QUERY, "BvhNode"),
            Mirror::of::<GpuTri>("GpuTri", crate::engine::gpu::shaders::BVH_QUERY, "BvhTri"),
            Mirror::of::<QueryRay>("QueryRay", crate::engine::gpu::shaders::BVH_QUERY, "QueryRay"),
            Mirror::of::<QueryHit>("QueryHit", crate::engine::gpu::shaders::BVH_QUERY, "QueryResult"),
        ]);
    }

    #[test]
    fn ulp_rounding_is_outward() {
        for x in [0.0f32, 1.0, -1.0, 1e-30, -3.5e7, 7e-5] {
            assert!(next_up(x) > x && next_down(x) < x, "{x}");
        }
        assert_eq!(next_up(1.0), 1.0 + f32::EPSILON);
    }

    #[test]
    fn layouts_match_the_shader() {
        // BvhNode: two vec3 + u32 pairs; BvhTri: three. WGSL aligns vec3 to 16 bytes.
        assert_eq!(std::mem::size_of::<GpuNode>(), 32);
        assert_eq!(std::mem::size_of::<GpuTri>(), 48);
        assert_eq!(std::mem::size_of::<QueryRay>(), 32);
        assert_eq!(std::mem::size_of::<QueryHit>(), 16);
    }
}
