//! The shared direct-light module: E/pi, the incident irradiance over pi, from the sun,
//! directional, point and spot lights and emissive triangles at every valid texel, on
//! the GPU with shadow rays through the scene's BVH (`gpu::bvh`). A technique that does
//! not transport some of that light itself (`sdf`: all of it; `obscurance`: point and spot
//! lights) runs one [`DirectLight::step`] per step of its own and adds the halves it
//! reads back ([`DirectLight::halves`]) to its direct light, so no light of the job is
//! dropped (issue 21 point 1).
//!
//! How: `shaders/gpu/direct_light.wgsl`, one invocation per texel, `samples_per_step`
//! next-event estimates of `shaders/gpu/lights.wgsl` (the same estimator `path` uses at
//! each vertex, here with weight 1 since there is no continuation ray: plain light
//! sampling, unbiased), blended into the running mean of the step's half (even and odd
//! steps, DESIGN section 4), so the halves are two independent estimates and their
//! difference is the noise. Delta lights (point, spot, directional) cost one shadow ray
//! each and have no noise but their shadows' aliasing over the texel's sample point; the
//! sun is one direction in its cone per sample (soft penumbrae converge like everything
//! else); emitters are one triangle point per sample, picked by area x luminance
//! (`raytrace::EmitterTable`).
//!
//! With `hits` the pass also estimates, per texel, the cosine-weighted fraction of its
//! hemisphere that sees a surface (one ray to any distance per sample, directions below
//! the geometric plane counted as hits), which `sdf` weights its bounce by.
//!
//! Space: the world space the atlas's sample points are in (the BVH's), not the
//! normalised frame the raster techniques use. The scene and the texels are the bake's
//! shared uploads (`gpu::scene_rays`); the pass itself is a `gpu::texel_pass`, so this
//! module depends on no technique's buffers.
//!
//! Limits: the BVH and tables must fit the adapter's storage-binding limit
//! (`gpu::scene_lights`); `samples_per_step` is capped at [`MAX_SAMPLES_PER_STEP`] so an
//! invocation stays far inside llvmpipe's loop budget (65535 iterations an invocation)
//! even with a few hundred lights; a scene with thousands of punctual lights pays one
//! shadow ray per light per sample (no light tree).

use std::sync::Arc;

use glam::Vec3;

use super::scene_lights::LightSources;
use super::scene_rays::SceneRays;
use super::shaders::DIRECT_LIGHT;
use super::texel_pass::{PassSpec, Sliced, StepUniform, TexelRayPass};
use super::{GpuContext, GpuError};
use crate::engine::atlas::Atlas;
use crate::engine::raytrace::EmitterTable;
use crate::engine::scene::Lighting;

/// The most next-event estimates a texel takes per step.
pub const MAX_SAMPLES_PER_STEP: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct DirectUniform {
    counts: [u32; 4],
    keys: [u32; 4],
    f: [f32; 4],
    /// The dispatch's first texel and texel count (a sliced step).
    slice: [u32; 4],
}

impl StepUniform for DirectUniform {
    fn set_step(&mut self, step: u64, half: u32, weight: f32) {
        self.counts[2] = step as u32;
        self.counts[3] = half;
        self.f[0] = weight;
    }
    fn set_slice(&mut self, first: u32, count: u32) {
        self.slice = [first, count, 0, 0];
    }
}

/// One half's running means per valid texel.
pub struct DirectHalf {
    /// E/pi from the selected sources.
    pub light: Vec<Vec3>,
    /// The fraction of the cosine-weighted hemisphere that sees a surface (0 unless the
    /// pass was made with `hits`).
    pub hit: Vec<f32>,
}

const DIRECT_HITS: u32 = 1;

/// The direct light of one bake's texels, accumulated on the GPU.
pub struct DirectLight {
    pass: TexelRayPass<DirectUniform>,
    sources: LightSources,
}

impl DirectLight {
    /// Prepares the pass for `sources` of the scene of `rays` and `lighting` at `atlas`'s
    /// texels, or `None` when the scene has none of them (nothing to add, no GPU work).
    /// `label` names the technique in labels and errors; `emitters` restricts the
    /// emitters to those scene triangles (all when `None`); `hits` adds the hit-fraction
    /// estimate.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: Arc<GpuContext>,
        label: &str,
        rays: &SceneRays,
        atlas: &Arc<Atlas>,
        lighting: &Lighting,
        seed: u64,
        sources: LightSources,
        emitters: Option<&[bool]>,
        samples_per_step: u32,
        hits: bool,
    ) -> Result<Option<Self>, GpuError> {
        let scene = rays.scene();
        let emitters = match emitters {
            Some(keep) => Arc::new(EmitterTable::of(scene, |i| keep.get(i).copied().unwrap_or(false))),
            None => rays.emitters(),
        };
        let sources = sources.present(scene, lighting, &emitters);
        if sources == LightSources::NONE {
            return Ok(None);
        }
        let what = format!("{label} direct light");
        let n = atlas.texels.len();
        let uniform = DirectUniform {
            counts: [n as u32, samples_per_step.clamp(1, MAX_SAMPLES_PER_STEP), 0, 0],
            keys: [seed as u32, (seed >> 32) as u32, if hits { DIRECT_HITS } else { 0 }, 0],
            f: [1.0, 0.0, 0.0, 0.0],
            slice: [0, n as u32, 0, 0],
        };
        let spec = PassSpec {
            what: &what,
            shader: &DIRECT_LIGHT,
            entry: "direct",
            sources,
            emitters: &emitters,
            accumulators: &[("accumulators", 2 * n as u64 * 16)],
            tables: &[],
        };
        let pass = TexelRayPass::new(ctx, rays, atlas, lighting, spec, uniform)?;
        tracing::debug!(
            technique = label,
            texels = n,
            sources = sources.0,
            "shared direct light"
        );
        Ok(Some(DirectLight { pass, sources }))
    }

    /// The sources this pass estimates (those asked for that the scene has).
    pub fn sources(&self) -> LightSources {
        self.sources
    }

    /// Steps blended into each half so far.
    pub fn half_steps(&self) -> [u64; 2] {
        self.pass.half_steps()
    }

    /// Submits one step (one dispatch) into the half of its parity; does not wait.
    pub fn step(&mut self) -> Result<(), GpuError> {
        self.pass.step()
    }

    /// One step of a bake with a deadline or a watcher (`go_on` Some: sliced when it may
    /// be long, and undone when `go_on` says stop between slices), or of one without
    /// (`TexelRayPass::step_watched`).
    pub fn step_watched(&mut self, go_on: Option<&mut dyn FnMut(u64, u64) -> bool>) -> Result<Sliced, GpuError> {
        self.pass.step_watched(go_on)
    }

    /// The next watched step is sliced and timed again (a new deadline).
    pub fn forget_step_length(&mut self) {
        self.pass.forget_step_length();
    }

    /// From now on each step replaces its half instead of joining its mean, so the
    /// buffer of [`DirectLight::accumulators`] holds, per half, the latest step's
    /// estimate: for a technique that blends steps with weights of its own (`sdb`).
    pub fn keep_latest(&mut self) {
        self.pass.keep_latest = true;
    }

    /// The accumulators on the device: 2 N vec4, the even half's texels then the odd
    /// half's, rgb E/pi and the hit fraction.
    pub fn accumulators(&self) -> &wgpu::Buffer {
        self.pass.accumulator(0)
    }

    /// Both halves' running means per valid texel (blocks on the device). A half no
    /// step has reached yet reads 0.
    pub fn halves(&self) -> Result<[DirectHalf; 2], GpuError> {
        let n = self.pass.texels();
        let raw = self.pass.read(0, 2 * n)?;
        let half = |h: usize| {
            let r = &raw[h * n..(h + 1) * n];
            DirectHalf {
                light: r.iter().map(|a| Vec3::new(a[0], a[1], a[2])).collect(),
                hit: r.iter().map(|a| a[3]).collect(),
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
        assert_mirrors(&[Mirror::of::<DirectUniform>(
            "DirectUniform",
            DIRECT_LIGHT,
            "DirectUniform",
        )]);
    }
}
