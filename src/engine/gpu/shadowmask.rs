//! The shadowmask pass: per valid texel, the baked visibility (0..1) of up to four chosen
//! lights, one per channel, and the direct light E/pi those lights bring, on the GPU with
//! shadow rays through the scene's BVH (`gpu::bvh`). `engine::shadowmask` chooses the
//! lights, steps this pass beside any technique and takes the lights' direct light out of
//! the lightmap (issue 26 point 3).
//!
//! How: `shaders/gpu/shadowmask.wgsl`, one invocation per texel. The sun is
//! `samples_per_step` directions uniform over its disc (soft penumbra, converging with the
//! steps); a directional, point or spot light of the scene is a delta light (glTF gives it
//! no size), one shadow ray to it, so its channel is 0 or 1 at the texel's sample point.
//! Each step is blended into the running mean of its half (even and odd steps, DESIGN
//! section 4), so the E/pi the bake subtracts keeps two independent halves and the bake's
//! error estimate includes this pass's noise.
//!
//! Space and buffers: world space, like `gpu::direct_light`; the scene and the texels are
//! the bake's shared uploads (`gpu::scene_rays`) and the pass is a `gpu::texel_pass`
//! (emitters are not chosen lights: the pass samples no emitter). Limits: the storage-binding limit
//! (`gpu::bvh::check_binding_size`) on the texels and the 64 B a texel of accumulators;
//! `samples_per_step` capped at [`MAX_SAMPLES_PER_STEP`].

use std::sync::Arc;

use glam::Vec3;

use super::scene_lights::LightSources;
use super::scene_rays::SceneRays;
use super::shaders::SHADOWMASK;
use super::texel_pass::{PassSpec, StepUniform, TexelRayPass};
use super::{GpuContext, GpuError};
use crate::engine::atlas::Atlas;
use crate::engine::scene::Lighting;

/// The most sun directions a texel takes per step.
pub const MAX_SAMPLES_PER_STEP: u32 = 64;

pub use crate::engine::accumulate::MASK_CHANNELS as CHANNELS;

/// `MASK_SUN` of the shader: the channel holds the job's sun.
const MASK_SUN: u32 = u32::MAX;

/// A light a channel holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskSource {
    /// The job's sun (`lighting.sun`).
    Sun,
    /// The scene's light of that index (`Scene::lights`).
    Light(usize),
}

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct MaskUniform {
    counts: [u32; 4],
    keys: [u32; 4],
    lights: [u32; 4],
    f: [f32; 4],
}

impl StepUniform for MaskUniform {
    fn set_step(&mut self, step: u64, half: u32, weight: f32) {
        self.counts[2] = step as u32;
        self.counts[3] = half;
        self.f[0] = weight;
    }
}

/// One half's running means per valid texel.
pub struct MaskHalf {
    /// Visibility of each channel's light (unused channels 0).
    pub visibility: Vec<[f32; CHANNELS]>,
    /// E/pi of the chosen lights together, shadowed.
    pub light: Vec<Vec3>,
}

/// The shadowmask of one bake's texels, accumulated on the GPU.
pub struct ShadowmaskPass {
    pass: TexelRayPass<MaskUniform>,
}

impl ShadowmaskPass {
    /// Prepares the pass for `lights` (1 to [`CHANNELS`], in channel order) at `atlas`'s
    /// texels of the scene of `rays`. The caller has checked the lights exist
    /// (`engine::shadowmask::resolve`).
    pub fn new(
        ctx: Arc<GpuContext>,
        rays: &SceneRays,
        atlas: &Arc<Atlas>,
        lighting: &Lighting,
        seed: u64,
        lights: &[MaskSource],
        samples_per_step: u32,
    ) -> Result<Self, GpuError> {
        let what = "shadowmask";
        if lights.is_empty() || lights.len() > CHANNELS {
            return Err(GpuError::Device {
                during: what.into(),
                message: format!("1 to {CHANNELS} lights, got {}", lights.len()),
            });
        }
        let n = atlas.texels.len();
        let mut slots = [MASK_SUN; 4];
        for (slot, l) in slots.iter_mut().zip(lights) {
            *slot = match l {
                MaskSource::Sun => MASK_SUN,
                MaskSource::Light(i) => *i as u32,
            };
        }
        let uniform = MaskUniform {
            counts: [n as u32, samples_per_step.clamp(1, MAX_SAMPLES_PER_STEP), 0, 0],
            keys: [seed as u32, (seed >> 32) as u32, lights.len() as u32, 0],
            lights: slots,
            f: [1.0, 0.0, 0.0, 0.0],
        };
        // The tables' emitter set is the bake's (shared); `LightSources::NONE` keeps the
        // pass from sampling any of it.
        let spec = PassSpec {
            what,
            shader: &SHADOWMASK,
            entry: "shadowmask",
            sources: LightSources::NONE,
            emitters: &rays.emitters(),
            accumulators: &[("accumulators", 2 * 2 * n as u64 * 16)],
            tables: &[],
        };
        let pass = TexelRayPass::new(ctx, rays, atlas, lighting, spec, uniform)?;
        tracing::debug!(texels = n, lights = lights.len(), "shadowmask pass");
        Ok(ShadowmaskPass { pass })
    }

    /// Steps blended into each half so far.
    pub fn half_steps(&self) -> [u64; 2] {
        self.pass.half_steps()
    }

    /// Submits one step (one dispatch) into the half of its parity; does not wait.
    pub fn step(&mut self) -> Result<(), GpuError> {
        self.pass.step()
    }

    /// Both halves' running means per valid texel (blocks on the device); a half no step
    /// has reached reads 0.
    pub fn halves(&self) -> Result<[MaskHalf; 2], GpuError> {
        let n = self.pass.texels();
        let raw = self.pass.read(0, 4 * n)?;
        let half = |h: usize| {
            let r = &raw[2 * h * n..2 * (h + 1) * n];
            MaskHalf {
                visibility: r.chunks_exact(2).map(|p| p[0]).collect(),
                light: r
                    .chunks_exact(2)
                    .map(|p| Vec3::new(p[1][0], p[1][1], p[1][2]))
                    .collect(),
            }
        };
        Ok([half(0), half(1)])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Rust mirror of the pass's uniform has the shader's size (naga's layout).
    #[test]
    fn gpu_layouts_match_the_shaders() {
        use crate::engine::gpu::shaders::{Mirror, assert_mirrors};
        assert_mirrors(&[Mirror::of::<MaskUniform>(
            "MaskUniform",
            crate::engine::gpu::shaders::SHADOWMASK,
            "MaskUniform",
        )]);
    }
}
