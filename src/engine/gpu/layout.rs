//! Bind-group layouts, bind groups and compute pipelines with one bind group, as every
//! technique's GPU passes build them: the wgpu descriptors are long and the same in every
//! pass, so the passes name only what differs. One binding API: a pass lists its bindings
//! once as [`Bind`]s, in binding order, and gets both the layout ([`layout_of`]) and the
//! bind group ([`group_of`]) from that list, so the two cannot disagree. A group whose
//! bindings do not start at 0 uses [`layout_at`] / [`group_at`]; a binding seen by other
//! stages than the rest of its group is wrapped in [`Bind::In`].

use super::GpuContext;

/// A storage buffer at `binding`.
fn storage_entry(binding: u32, visibility: wgpu::ShaderStages, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// A uniform buffer at `binding`.
fn uniform_entry(binding: u32, visibility: wgpu::ShaderStages) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// A 2D-array float texture read with `textureLoad` by a compute pass.
fn texture_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Texture {
            // Read with textureLoad only: no filtering, so Rgba32Float needs no
            // FLOAT32_FILTERABLE.
            sample_type: wgpu::TextureSampleType::Float { filterable: false },
            view_dimension: wgpu::TextureViewDimension::D2Array,
            multisampled: false,
        },
        count: None,
    }
}

/// A compute pipeline whose only bind group has `layout`.
pub fn compute_pipeline(
    ctx: &GpuContext,
    label: &str,
    module: &wgpu::ShaderModule,
    entry: &str,
    layout: &wgpu::BindGroupLayout,
) -> wgpu::ComputePipeline {
    let pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &[Some(layout)],
        immediate_size: 0,
    });
    ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: Some(&pl),
        module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// One binding of a pass, listed in binding order (0, 1, 2, …): the layout entry and the
/// bind-group entry are both made from the same list, so they cannot disagree.
#[derive(Clone, Copy)]
pub enum Bind<'a> {
    Uniform(&'a wgpu::Buffer),
    /// A read-only storage buffer.
    Read(&'a wgpu::Buffer),
    /// A read-write storage buffer.
    Write(&'a wgpu::Buffer),
    /// A 2D-array float texture read with `textureLoad` (see `texture_entry`).
    Texture(&'a wgpu::TextureView),
    /// A plain 2D float texture read with `textureLoad`.
    Texture2d(&'a wgpu::TextureView),
    /// The binding, visible to these stages instead of the group's.
    In(wgpu::ShaderStages, &'a Bind<'a>),
}

impl Bind<'_> {
    fn layout_entry(&self, binding: u32, visibility: wgpu::ShaderStages) -> wgpu::BindGroupLayoutEntry {
        match self {
            Bind::Uniform(_) => uniform_entry(binding, visibility),
            Bind::Read(_) => storage_entry(binding, visibility, true),
            Bind::Write(_) => storage_entry(binding, visibility, false),
            Bind::Texture(_) => wgpu::BindGroupLayoutEntry {
                visibility,
                ..texture_entry(binding)
            },
            Bind::In(stages, inner) => inner.layout_entry(binding, *stages),
            Bind::Texture2d(_) => wgpu::BindGroupLayoutEntry {
                binding,
                visibility,
                ty: wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Float { filterable: false },
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: false,
                },
                count: None,
            },
        }
    }

    fn resource(&self) -> wgpu::BindingResource<'_> {
        match self {
            Bind::Uniform(b) | Bind::Read(b) | Bind::Write(b) => b.as_entire_binding(),
            Bind::Texture(v) | Bind::Texture2d(v) => wgpu::BindingResource::TextureView(v),
            Bind::In(_, inner) => inner.resource(),
        }
    }
}

/// The layout of `binds` (bindings 0, 1, …), visible to `visibility`.
pub fn layout_of(
    ctx: &GpuContext,
    label: &str,
    visibility: wgpu::ShaderStages,
    binds: &[Bind<'_>],
) -> wgpu::BindGroupLayout {
    layout_at(ctx, label, 0, visibility, binds)
}

/// The layout of `binds` at bindings `first`, `first + 1`, …, visible to `visibility`.
pub fn layout_at(
    ctx: &GpuContext,
    label: &str,
    first: u32,
    visibility: wgpu::ShaderStages,
    binds: &[Bind<'_>],
) -> wgpu::BindGroupLayout {
    let entries: Vec<wgpu::BindGroupLayoutEntry> = binds
        .iter()
        .enumerate()
        .map(|(i, b)| b.layout_entry(first + i as u32, visibility))
        .collect();
    ctx.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(label),
        entries: &entries,
    })
}

/// A bind group of `binds` on `layout` (made by [`layout_of`] from a list of the same
/// kinds; another list of the same kinds may be bound on it, e.g. ping-pong buffers).
pub fn group_of(ctx: &GpuContext, label: &str, layout: &wgpu::BindGroupLayout, binds: &[Bind<'_>]) -> wgpu::BindGroup {
    group_at(ctx, label, layout, 0, binds)
}

/// [`group_of`] for a layout made by [`layout_at`] with the same `first`.
pub fn group_at(
    ctx: &GpuContext,
    label: &str,
    layout: &wgpu::BindGroupLayout,
    first: u32,
    binds: &[Bind<'_>],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = binds
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: first + i as u32,
            resource: b.resource(),
        })
        .collect();
    ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &entries,
    })
}
