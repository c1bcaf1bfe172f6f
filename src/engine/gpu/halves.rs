//! The even/odd half accumulators on the GPU (DESIGN §4): one storage buffer of
//! 2 × texels `vec4<f32>` (half 0, then half 1; rgb = the half's running mean, w spare)
//! and optionally a second one for the direct-light layer, read back into a [`Snapshot`]
//! at snapshot time only, never per step.
//!
//! The techniques that accumulate in this layout (`vpl`, `hemicube`) create their buffers
//! through [`GpuHalves::new`], which checks the device's storage-binding limit first, and
//! read them with [`GpuHalves::snapshot`]. `sdb`, `obscurance` and `sdf` keep their own
//! layouts (leaky averages, moments, masks): see their module docs.

use crate::engine::accumulate::Snapshot;
use crate::engine::gpu::{GpuContext, GpuError};

/// The accumulator buffers of one bake.
pub struct GpuHalves {
    /// `2 * n` vec4: half 0 then half 1.
    pub acc: wgpu::Buffer,
    /// The direct-light layer in the same layout, when the job asked for it.
    pub direct: Option<wgpu::Buffer>,
    pub n: usize,
    label: String,
}

impl GpuHalves {
    /// Zeroed accumulators for `n` texels, labelled `"{label} accumulators"`.
    pub fn new(ctx: &GpuContext, label: &str, n: usize, want_direct: bool) -> Result<Self, GpuError> {
        let bytes = 2 * n.max(1) as u64 * 16;
        ctx.check_storage(&format!("{label}: the accumulators of {n} texels"), bytes)?;
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let acc = ctx.buffer_zeroed(&format!("{label} accumulators"), bytes, usage);
        let direct = want_direct.then(|| ctx.buffer_zeroed(&format!("{label} direct accumulators"), bytes, usage));
        Ok(GpuHalves {
            acc,
            direct,
            n,
            label: label.to_string(),
        })
    }

    /// Both halves' means as of now (blocks on the device).
    pub fn snapshot(&self, ctx: &GpuContext, half_steps: [u64; 2]) -> Result<Snapshot, GpuError> {
        read_halves(ctx, &self.label, &self.acc, self.direct.as_ref(), self.n, half_steps)
    }
}

/// Reads `2 * n` vec4 half accumulators (and the direct layer's, if any) into a snapshot.
pub fn read_halves(
    ctx: &GpuContext,
    label: &str,
    acc: &wgpu::Buffer,
    direct: Option<&wgpu::Buffer>,
    n: usize,
    half_steps: [u64; 2],
) -> Result<Snapshot, GpuError> {
    let total: Vec<[f32; 4]> = ctx.read_buffer(&format!("{label} accumulators"), acc, 2 * n)?;
    let direct: Option<Vec<[f32; 4]>> = match direct {
        Some(b) => Some(ctx.read_buffer(&format!("{label} direct accumulators"), b, 2 * n)?),
        None => None,
    };
    Ok(Snapshot::from_gpu_halves(&total, direct.as_deref(), half_steps))
}
