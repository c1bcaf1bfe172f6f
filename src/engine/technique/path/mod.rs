//! `path`: the reference. Unbiased Monte Carlo path tracing on the CPU from every texel's
//! sample point; every error figure in this project is measured against it.
//!
//! How, per texel and sample: cosine-weighted directions about the texel's normal (the
//! ideal density for irradiance / π under a uniform sky), then at every vertex
//! - next-event estimation to punctual lights (delta lights: light sampling only), to
//!   the sun (a cone sampled uniformly) and to emissive triangles (a triangle chosen in
//!   proportion to area × emitted luminance, a uniform point on it);
//! - the cosine-sampled continuation, whose hits on emitters and on the sun's disc are
//!   weighted against the light samples by the power heuristic (Veach's MIS), so neither
//!   tiny bright emitters nor large dim ones are noisy;
//! - Russian roulette on the path's throughput rather than on each surface's albedo:
//!   a path continues with certainty while its largest throughput component is at least
//!   τ = `rr_threshold`; below τ it survives with probability throughput/τ and is
//!   rescaled back to τ. Unbiased either way, but the textbook rule (survive with the
//!   albedo at every bounce) makes the *number* of bounces random, and in a closed bright
//!   room that is nearly all the variance: with ρ = 0.999 a path's value has a relative
//!   standard deviation of √ρ ≈ 1. Here the first ln τ / ln ρ bounces (3000 for
//!   ρ = 0.999 and τ = 0.05) are deterministic and only the last τ of the energy is left
//!   to chance: about 20 times less noise per path for ρ ≥ 0.9 at τ = 0.05. A hard cap of
//!   `max_bounces` (default 65536) only bounds run time for albedo 1 in a closed room;
//!   its bias is ρ^65536.
//! - τ itself trades path length against that noise, and the best trade depends on the
//!   scene ([`auto_rr_threshold`]): where light bounces little (open scenes, ordinary
//!   rooms) the tail a roulette randomises is small against a path's own noise, so a
//!   high τ saves bounces for little variance; in a stiff closed room a path's value is
//!   nearly all bounced light and τ must stay low. By default (`rr_threshold` unset) τ is
//!   chosen from the scene's feedback gain g, the mean albedo a diffuse ray from the
//!   scene's surface finds (4096 rays, [`feedback_gain`]): τ = 0.5 (1 - g), clamped to
//!   [0.05, 0.3]. Measured (docs/performance.md, "Russian roulette's threshold"), work
//!   to equal error against τ = 0.05: the occlusion room 25 % less, the ρ = 0.5 box 27 %,
//!   the Cornell box 13 %, blocks-25k 3 %, the closed ρ = 0.9 box unchanged (τ = 0.05
//!   there; a fixed τ = 0.3 would cost it 4x).
//!
//! The sky has no light sampling: for uniform radiance cosine sampling is already ideal.
//!
//! Surfaces are Lambertian with glTF's base colour as albedo (metallic/roughness are
//! ignored here: the lightmap stores irradiance, and glossy transport belongs to the
//! techniques that model it). A hit on the back of a single-sided surface is black and
//! opaque: it blocks light and reflects none, as back-face-culled geometry in a
//! renderer would show it. Double-sided surfaces reflect and emit on both sides.
//!
//! Rays are cast with `engine::raytrace` (obvhs's wide BVH, eight children a node,
//! decoded into `f32` boxes, with an AVX2 node test picked at run time where the CPU has
//! it).
//!
//! Device (`params.device`): `cpu` traces here on all cores; `gpu` runs the same estimator
//! as a compute megakernel (`technique::path::gpu`, same tables, other random streams);
//! `auto` (the default) takes the GPU only when a hardware adapter exists, so a machine
//! with only a software rasteriser (lavapipe) keeps the CPU path.
//!
//! Randomness (`params.sampling`, `path/sampler.rs`): by default each texel's samples in
//! each half of the bake are points of one Owen-scrambled Sobol sequence, scrambled
//! independently per texel and half so the halves' difference still measures the error;
//! `independent` draws one PCG32 stream per (seed, step, texel, sample) (`engine::rng`).
//! Either way the result is bit-identical for a seed regardless of thread count. The GPU
//! megakernel samples the same way (the same Sobol construction, `path/gpu.rs`; its
//! scrambles and streams are hashed in 32 bits). "Texel" in these keys is the texel's pixel
//! in the grid (`Texel::pixel`), not its place in the valid-texel list, and "step" is the
//! job's step: a task that bakes some steps of one region of the grid (`engine::tasks`)
//! draws exactly the samples the whole bake draws there.
//!
//! Time limit: a CPU step runs in chunks of [`DEADLINE_PATHS`] paths and is abandoned,
//! adding nothing, when the bake's deadline passes mid-step (`Technique::set_deadline`)
//! or its watcher asks it to stop (`StepProgress::request_stop`: a cancelled job), so one
//! step over a large level's texels cannot carry a bake far past its limit or its cancel. The
//! samples of the chunks already done are dropped: the half accumulators count whole
//! steps, and a step over part of the texels would weight those texels differently.
//! On the GPU, in a bake with a deadline or a watcher, a step that may be long (the first,
//! and any seen to take `gpu::texel_pass::LONG_STEP` or more) runs in slices of texels of about 50 ms
//! (`PathGpu::step_watched`, `TexelRayPass::step_watched`) with the same checks between
//! slices; a step stopped there is undone on the device (its half copied aside and back),
//! and shorter steps keep two whole dispatches in flight. The chunks (or slices) done are
//! also reported as the step's progress (`bake::StepProgress`), for a long step's watchers.
//!
//! Limits: no glossy transport, no textures' alpha, no participating media. The sample
//! point of a texel inside closed geometry sees back faces and bakes black.

use std::f32::consts::FRAC_1_PI;
use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

mod gpu;
pub mod probe_placement;
pub mod probes;
pub mod probes_gpu;
pub(crate) mod sampler;

use super::api::{
    AlphaSupport, BakeInputs, EngineError, LightSource, TaskSplit, Technique, TechniqueEntry, parse_params,
};
use crate::engine::accumulate::{HalfAccumulator, LUMINANCE, Snapshot};
pub use crate::engine::gpu::hardware_adapter_present;
use crate::engine::output::OutputLayer;
use crate::engine::plan::{DIRECT_LAYER, Plan, SH_LAYER, SceneFeatures};
use crate::engine::raytrace::{EmitterTable, Tracer, cone_sample, cosine_sample, inset};
use crate::engine::rng::Rng;
use crate::engine::scene::{LightKind, Scene};
pub use gpu::Device;
use gpu::PathGpu;
use sampler::{PathSampler, Sobol};

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PathParams {
    /// Paths per texel in one step (1 to 4096).
    pub samples_per_step: u32,
    /// Hard cap on path length (1 to 65536); Russian roulette ends paths long before.
    pub max_bounces: u32,
    /// Throughput below which Russian roulette starts (0 < τ ≤ 1); unset (the default):
    /// chosen from the scene's feedback gain ([`auto_rr_threshold`]). `params()` reports
    /// the value used.
    pub rr_threshold: Option<f32>,
    /// Where to trace: `auto`, `cpu` or `gpu` (module doc).
    pub device: Device,
    /// Sample placement, on the CPU and the GPU: `sobol` (default) or `independent`
    /// (`path/sampler.rs`).
    pub sampling: Sampling,
}

/// How a texel's samples are placed (`params.sampling`), on either device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Sampling {
    /// Owen-scrambled Sobol points, one sequence per texel and half.
    #[default]
    Sobol,
    /// Independent PCG32 numbers per sample.
    Independent,
}

impl Default for PathParams {
    fn default() -> Self {
        PathParams {
            samples_per_step: 4,
            max_bounces: 65536,
            rr_threshold: None,
            device: Device::Auto,
            sampling: Sampling::Sobol,
        }
    }
}

impl PathParams {
    fn validate(&self) -> Result<(), EngineError> {
        if !(1..=4096).contains(&self.samples_per_step) {
            return Err(EngineError::BadInput(format!(
                "params.samples_per_step must be in 1..=4096, got {}",
                self.samples_per_step
            )));
        }
        if let Some(t) = self.rr_threshold
            && !(t > 0.0 && t <= 1.0)
        {
            return Err(EngineError::BadInput(format!(
                "params.rr_threshold must be in (0, 1], got {t}"
            )));
        }
        if !(1..=65536).contains(&self.max_bounces) {
            return Err(EngineError::BadInput(format!(
                "params.max_bounces must be in 1..=65536, got {}",
                self.max_bounces
            )));
        }
        Ok(())
    }

    /// τ as the bake uses it: the job's, or the scene's choice once
    /// [`PathParams::choose_rr_threshold`] has filled it in.
    pub(crate) fn threshold(&self) -> f32 {
        self.rr_threshold.unwrap_or(RR_THRESHOLD_STIFF)
    }

    /// Fills in τ from the scene when the job left it unset ([`auto_rr_threshold`]),
    /// before anything reads it, so the CPU, the GPU and `params()` see one value.
    pub(crate) fn choose_rr_threshold(&mut self, scene: &Scene, tracer: &Tracer) {
        if self.rr_threshold.is_none() {
            let started = Instant::now();
            let g = feedback_gain(scene, tracer);
            let tau = auto_rr_threshold(g);
            tracing::debug!(
                gain = g,
                rr_threshold = tau,
                ms = started.elapsed().as_secs_f64() * 1e3,
                "path: Russian roulette threshold from the scene"
            );
            self.rr_threshold = Some(tau);
        }
    }
}

/// τ for the stiffest rooms, and the lowest the automatic choice takes: the value every
/// bake used before τ was chosen per scene (docs/stability.md, "Noise in stiff rooms").
pub const RR_THRESHOLD_STIFF: f32 = 0.05;
/// The highest τ the automatic choice takes: beyond it the roulette's noise outgrows the
/// bounces it saves even in open scenes (work to equal error against τ = 0.05: the
/// Cornell box 21 % less at 0.3, 10 % less at 0.5, 42 % more at 1; blocks-25k 10 % less
/// at 0.3, 3 % more at 0.5, 43 % more at 1).
pub const RR_THRESHOLD_OPEN: f32 = 0.3;
/// Rays [`feedback_gain`] casts: g to about ±0.008 (its standard error at g = 0.5), far
/// finer than the threshold's sensitivity. Measured with the CDF build (2-core VM): 0.5 ms
/// on the Cornell box, 3 ms on the 64k-triangle occlusion room, 7-10 ms on the
/// 256k-triangle generated level.
pub const GAIN_RAYS: u32 = 4096;

/// The automatic Russian-roulette threshold for a scene of feedback gain `g` (module
/// doc): τ = 0.5 (1 - g) in [0.05, 0.3]. What a path at throughput τ has still to
/// gather is about τ / (1 - g) times what one vertex gathers at throughput 1 (a geometric
/// series of gain g), so this rule leaves to chance about half of one vertex's light
/// whatever the scene. Calibrated on five scenes (docs/performance.md):
/// the best fixed τ was 0.05 for the ρ = 0.9 box (g = 0.9), 0.2-0.3 for the ρ = 0.5 box,
/// the Cornell box and the occlusion room, and 0.3 for blocks-25k.
pub fn auto_rr_threshold(g: f32) -> f32 {
    (0.5 * (1.0 - g)).clamp(RR_THRESHOLD_STIFF, RR_THRESHOLD_OPEN)
}

/// The scene's feedback gain g: the mean luminance of the albedo that a cosine-distributed
/// ray from a uniformly chosen point of the scene's surface finds, counting 0 where it
/// leaves the scene or meets the back of a single-sided surface (which reflects nothing
/// here, as in the estimator). A closed box of albedo ρ has g = ρ; an open scene's g is
/// its surfaces' albedo times the fraction of their hemisphere that sees other surfaces.
/// Points are drawn by area over every triangle (the front side; either side of a
/// double-sided one), from a fixed stream: g is a property of the scene, the same for
/// every seed and in every task of a split bake (`engine::tasks`), so every task uses
/// the single bake's τ, and a job's light probes the lightmap's. 0 for a scene without
/// area.
pub fn feedback_gain(scene: &Scene, tracer: &Tracer) -> f32 {
    let mut cdf = Vec::with_capacity(scene.triangles.len());
    let mut total = 0.0f64;
    for t in &scene.triangles {
        total += f64::from(t.area());
        cdf.push(total);
    }
    // The probes' offset, not the atlas's, so that a bake and its probes measure one g.
    let eps = probe_placement::scene_ray_offset(scene);
    if !(total > 0.0) {
        return 0.0;
    }
    // A key of its own: these numbers are no texel's or step's.
    const GAIN_KEY: u64 = 0x6A1_F33D;
    let sum: f64 = (0..GAIN_RAYS)
        .into_par_iter()
        .map(|i| {
            let mut rng = Rng::new(GAIN_KEY, 0, 0, u64::from(i));
            let u = f64::from(rng.next_f32()) * total;
            let k = cdf.partition_point(|c| *c <= u).min(cdf.len() - 1);
            let tri = &scene.triangles[k];
            let ng = tracer.geometric_normal(k as u32);
            let side = if scene.material(tri).double_sided && rng.next_f32() < 0.5 {
                -1.0
            } else {
                1.0
            };
            let (mut b1, mut b2) = (rng.next_f32(), rng.next_f32());
            if b1 + b2 > 1.0 {
                b1 = 1.0 - b1;
                b2 = 1.0 - b2;
            }
            let n = ng * side;
            let x = tri.point(Vec3::new(1.0 - b1 - b2, b1, b2)) + n * eps;
            let dir = cosine_sample(n, rng.next_f32(), rng.next_f32());
            let Some(hit) = tracer.trace(scene, x, dir, f32::INFINITY) else {
                return 0.0;
            };
            let htri = &scene.triangles[hit.triangle as usize];
            let front = dir.dot(tracer.geometric_normal(hit.triangle)) < 0.0;
            if !front && !scene.material(htri).double_sided {
                return 0.0;
            }
            let a = scene.albedo(htri, hit.bary);
            f64::from(a.dot(LUMINANCE))
        })
        .sum();
    (sum / f64::from(GAIN_RAYS)) as f32
}

/// `path`'s GPU pass, WGSL in `shaders/path/` (the CPU route needs none).
pub mod shaders {
    use crate::engine::gpu::shaders::{BVH, LIGHTS, MATERIALS, PassShader, WgslFile, pass, wgsl_file};

    /// The estimator (E/pi at a surface point by one path), its randomness and bounds: the
    /// prelude both passes share (no bindings of its own).
    pub const ESTIMATOR: WgslFile = wgsl_file!("path/estimator.wgsl");
    /// The whole estimator per texel and sample (megakernel) over the GPU BVH.
    pub const PATH_TRACE: PassShader = pass!("path/path_trace.wgsl", [BVH, MATERIALS, LIGHTS, ESTIMATOR]);
    /// Light probes: one workgroup per probe, its SH to L2 (`probes_gpu`).
    pub const PROBES: PassShader = pass!("path/probes.wgsl", [BVH, MATERIALS, LIGHTS, ESTIMATOR]);
    /// Every pass of `path`.
    pub const ALL: &[PassShader] = &[PATH_TRACE, PROBES];
}

/// `path` in the technique table (`technique/table.rs`).
pub const ENTRY: TechniqueEntry = TechniqueEntry {
    default_params: || serde_json::to_value(PathParams::default()).unwrap_or_default(),
    id: "path",
    summary: "the unbiased reference: Monte Carlo path tracing with next-event estimation and MIS (CPU, all cores)",
    plan,
    prepare: |inputs, params| Ok(Box::new(PathTracer::prepare(inputs, params)?)),
    shaders: shaders::ALL,
    layers: &[OutputLayer::Direct, OutputLayer::Indirect, OutputLayer::Sh],
    lights: LightSource::ALL,
    check_params: |p| parse_params::<PathParams>("path", p)?.validate(),
    unbiased: true,
    alpha: AlphaSupport::Everywhere,
    rounds: false,
    tasks: TaskSplit::StepsAndRegions,
};

/// The path tracer's plan: one CPU pass, and light sampling only for the kinds of light
/// the scene and job have.
pub fn plan(f: &SceneFeatures) -> Plan {
    let mut p = Plan::new("path");
    p.error_estimate = "all of the error: path is unbiased, so the half-difference estimate covers it".into();
    p.run("bvh", "binary BVH over all triangles, for every ray");
    p.run("path trace", "cosine-sampled paths from every texel, on all CPU cores");
    p.decide(
        "light sampling: punctual lights",
        f.punctual_lights > 0,
        "the scene has KHR_lights_punctual lights",
        "the scene has no punctual lights",
    );
    p.decide(
        "light sampling: emissive triangles",
        f.emissive_triangles > 0,
        "the scene has emissive materials",
        "no triangle emits light",
    );
    p.decide("light sampling: sun", f.sun, "the job has a sun", "the job has no sun");
    p.decide("sky lookups", f.sky, "the job has a sky", "the job has no sky");
    p.decide(
        DIRECT_LAYER,
        f.want_direct,
        "direct or indirect output asked for",
        "not asked for in outputs",
    );
    p.decide(SH_LAYER, f.want_sh, "sh output asked for", "not asked for in outputs");
    if f.glossy_materials > 0 {
        p.leave_out(
            "glossy transport",
            "path treats every surface as Lambertian (base colour as albedo); metallic/roughness are ignored",
        );
    } else {
        p.leave_out("glossy data", "every material is a fully rough dielectric");
    }
    p
}

pub struct PathTracer {
    inputs: BakeInputs,
    params: PathParams,
    tracer: Arc<Tracer>,
    emitters: Arc<EmitterTable>,
    acc: HalfAccumulator,
    /// The GPU estimator, when `params.device` resolved to the GPU.
    gpu: Option<PathGpu>,
    /// The job's index of this bake's first step (a task's, `engine::tasks`; else 0):
    /// the random streams are keyed by the global step.
    first_step: u64,
    /// The bake's time limit, checked between chunks of a CPU step (module doc).
    deadline: Option<Instant>,
    /// Where a CPU step reports its chunks done (and a sliced GPU step its slices).
    progress: Option<crate::engine::technique::api::StepProgress>,
}

/// Paths a CPU step traces between two looks at the deadline: a chunk is this many paths'
/// worth of texels (256 texels at the default 4 samples, one texel at 1024 or more), a
/// few milliseconds on one core, so a limit is kept to about that much while the look
/// itself (one clock read) costs nothing measurable.
pub const DEADLINE_PATHS: usize = 1024;

/// Texels in one chunk of a step of `spp` samples a texel ([`DEADLINE_PATHS`]).
pub fn deadline_chunk(spp: u32) -> usize {
    (DEADLINE_PATHS / spp.max(1) as usize).max(1)
}

impl PathTracer {
    pub fn prepare(inputs: BakeInputs, params: &Value) -> Result<Self, EngineError> {
        let mut params: PathParams = parse_params("path", params)?;
        params.validate()?;
        let tracer = inputs.rays.tracer();
        let emitters = inputs.rays.emitters();
        params.choose_rr_threshold(&inputs.scene, &tracer);
        let gpu = match gpu::resolve(params.device)? {
            Some(ctx) => Some(PathGpu::new(ctx, &inputs, &params)?),
            None => None,
        };
        params.device = if gpu.is_some() { Device::Gpu } else { Device::Cpu };
        let texels = if gpu.is_some() { 0 } else { inputs.atlas.texels.len() };
        let acc = HalfAccumulator::new(texels, inputs.want_direct).with_moments(inputs.plan.runs(SH_LAYER));
        Ok(PathTracer {
            inputs,
            params,
            tracer,
            emitters,
            acc,
            gpu,
            first_step: 0,
            deadline: None,
            progress: None,
        })
    }
}

impl Technique for PathTracer {
    fn id(&self) -> &'static str {
        "path"
    }

    fn params(&self) -> Value {
        serde_json::to_value(&self.params).unwrap_or(Value::Null)
    }

    fn step(&mut self) -> Result<(), EngineError> {
        if let Some(gpu) = self.gpu.as_mut() {
            // A step that may be long, in a bake that has a limit or may be cancelled, runs
            // in slices (the first step always: its length is not known yet).
            if gpu.step_watched(self.deadline, self.progress.as_ref())? == gpu::Sliced::Abandoned {
                tracing::debug!(
                    "path on the GPU: the deadline passed or a stop was asked mid-step; the step is undone"
                );
            }
            return Ok(());
        }
        let step = self.first_step + self.acc.steps();
        let spp = self.params.samples_per_step;
        let ctx = PathContext {
            scene: &self.inputs.scene,
            tracer: &self.tracer,
            emitters: &self.emitters,
            lighting: &self.inputs.lighting,
            max_bounces: self.params.max_bounces,
            rr_threshold: self.params.threshold(),
            eps: self.inputs.atlas.surface_offset,
        };
        let seed = self.inputs.seed;
        let sampling = self.params.sampling;
        let deadline = self.deadline;
        // Streams are keyed by the texel's pixel, not its place in the texel list, so a
        // task that bakes one region of the grid (`engine::tasks`) draws exactly the
        // samples the whole bake draws for those texels.
        let texel_sample = |texel: &crate::engine::atlas::Texel| {
            let key = u64::from(texel.pixel);
            let mut sum = PathSample {
                total: Vec3::ZERO,
                direct: Vec3::ZERO,
                moment: Moment::default(),
            };
            for s in 0..spp {
                let (x, n, ng) = (texel.position, texel.normal, texel.geo_normal);
                let r = match sampling {
                    Sampling::Sobol => ctx.radiance(x, n, ng, &mut Sobol::new(seed, step, key, s, spp)),
                    Sampling::Independent => ctx.radiance(x, n, ng, &mut Rng::new(seed, step, key, s as u64)),
                };
                sum.total += r.total;
                sum.direct += r.direct;
                for a in 0..3 {
                    sum.moment.0[a] += r.moment.0[a];
                }
            }
            let k = 1.0 / spp as f32;
            PathSample {
                total: sum.total * k,
                direct: sum.direct * k,
                moment: Moment(sum.moment.0.map(|m| m * k)),
            }
        };
        let progress = self.progress.clone();
        let chunk_texels = deadline_chunk(spp);
        let n_chunks = self.inputs.atlas.texels.len().div_ceil(chunk_texels) as u64;
        let chunks_done = std::sync::atomic::AtomicU64::new(0);
        let chunks: Vec<Option<Vec<PathSample>>> = self
            .inputs
            .atlas
            .texels
            .par_chunks(chunk_texels)
            .map(|chunk| {
                let stop_asked = progress.as_ref().is_some_and(|p| p.stop_requested());
                if stop_asked || deadline.is_some_and(|d| Instant::now() >= d) {
                    return None;
                }
                let out = chunk.iter().map(texel_sample).collect();
                if let Some(p) = &progress {
                    let done = chunks_done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                    p.set(done, n_chunks);
                }
                Some(out)
            })
            .collect();
        if chunks.iter().any(Option::is_none) {
            tracing::debug!(
                step,
                "path: the deadline passed or a stop was asked mid-step; the step is abandoned"
            );
            return Ok(());
        }
        let results: Vec<PathSample> = chunks.into_iter().flatten().flatten().collect();
        let total: Vec<Vec3> = results.iter().map(|r| r.total).collect();
        // Layers exist only when an output asked for them (the plan says so).
        let direct: Option<Vec<Vec3>> = self
            .inputs
            .want_direct
            .then(|| results.iter().map(|r| r.direct).collect());
        let moments: Option<Vec<[Vec3; 3]>> = self
            .inputs
            .plan
            .runs(SH_LAYER)
            .then(|| results.iter().map(|r| r.moment.0).collect());
        self.acc.add_with_moments(&total, direct.as_deref(), moments.as_deref());
        Ok(())
    }

    fn set_deadline(&mut self, deadline: Option<Instant>) {
        self.deadline = deadline;
        // A GPU step's length is measured again, in slices, under the new limit.
        if let Some(gpu) = self.gpu.as_mut() {
            gpu.forget_step_length();
        }
    }

    fn set_step_progress(&mut self, progress: crate::engine::technique::api::StepProgress) {
        self.progress = Some(progress);
    }

    fn steps_done(&self) -> u64 {
        match &self.gpu {
            Some(gpu) => gpu.steps(),
            None => self.acc.steps(),
        }
    }

    fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
        match self.gpu.as_mut() {
            Some(gpu) => gpu.snapshot(),
            None => Ok(self.acc.snapshot()),
        }
    }

    fn start_at_step(&mut self, first: u64) -> Result<(), EngineError> {
        if self.steps_done() > 0 {
            return Err(EngineError::Internal(format!(
                "path: start_at_step({first}) after {} steps",
                self.steps_done()
            )));
        }
        self.first_step = first;
        if let Some(gpu) = self.gpu.as_mut() {
            gpu.start_at_step(first);
        }
        Ok(())
    }

    fn accumulating_pass(&self) -> &'static str {
        "path trace"
    }
}

/// Power heuristic weight of a sample of density `a` against one of density `b`.
fn power_heuristic(a: f32, b: f32) -> f32 {
    if a.is_infinite() {
        return 1.0;
    }
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 { a2 / (a2 + b2) } else { 0.0 }
}

/// Σ c·ω over a path's contributions c arriving from directions ω: per world axis, an
/// RGB value (the `sh.*` layers' L1 moments).
#[derive(Clone, Copy, Debug, Default)]
pub struct Moment(pub [Vec3; 3]);

impl Moment {
    fn add(&mut self, c: Vec3, dir: Vec3) {
        self.0[0] += c * dir.x;
        self.0[1] += c * dir.y;
        self.0[2] += c * dir.z;
    }
}

struct PathSample {
    total: Vec3,
    direct: Vec3,
    moment: Moment,
}

struct PathContext<'a> {
    scene: &'a Scene,
    tracer: &'a Tracer,
    emitters: &'a EmitterTable,
    lighting: &'a crate::engine::scene::Lighting,
    max_bounces: u32,
    rr_threshold: f32,
    eps: f32,
}

impl PathContext<'_> {
    /// Irradiance / π at `x0` (normal `n0`, geometric normal `ng0`), its direct part, and
    /// the first moment of where it came from.
    fn radiance(&self, x0: Vec3, n0: Vec3, ng0: Vec3, rng: &mut impl PathSampler) -> PathSample {
        let (mut x, mut n, mut ng) = (x0, n0, ng0);
        let mut throughput = Vec3::ONE;
        let mut total = Vec3::ZERO;
        let mut direct = Vec3::ZERO;
        let mut bounce = 0u32;
        let mut moment = Moment::default();
        let mut first_dir = None;
        let mut first_nee = Vec3::ZERO;
        loop {
            let (nee, nee_moment) = self.next_event(x, n, ng, bounce, rng);
            total += throughput * nee;
            if bounce == 0 {
                direct += nee;
                first_nee = nee;
                moment = nee_moment;
            }

            let (u1, u2) = rng.direction(bounce);
            let dir = cosine_sample(n, u1, u2);
            let cos = dir.dot(n);
            if dir.dot(ng) <= 0.0 || cos <= 0.0 {
                break; // below the geometric surface: the surface itself blocks it
            }
            if bounce == 0 {
                first_dir = Some(dir);
            }
            let pdf_bsdf = cos * FRAC_1_PI;
            let Some(hit) = self.tracer.trace(self.scene, x, dir, f32::INFINITY) else {
                let mut l = self.lighting.sky_radiance(dir);
                if let Some(sun) = &self.lighting.sun
                    && dir.dot(-sun.direction.normalize()) >= sun.cos_half_angle()
                {
                    l += sun.radiance * power_heuristic(pdf_bsdf, 1.0 / sun.solid_angle());
                }
                total += throughput * l;
                if bounce == 0 {
                    direct += l;
                }
                break;
            };
            let tri = &self.scene.triangles[hit.triangle as usize];
            let material = self.scene.material(tri);
            let geo = self.tracer.geometric_normal(hit.triangle);
            let front = dir.dot(geo) < 0.0;
            if !front && !material.double_sided {
                break; // back of a single-sided surface: black and opaque
            }
            let p = tri.point(inset(hit.bary));
            let emission = self.scene.emission(tri, hit.bary);
            if emission != Vec3::ZERO {
                // Density with which next-event estimation would have picked this point.
                let density = self.emitters.pick_density[hit.triangle as usize];
                let cos_l = dir.dot(geo).abs();
                let pdf_light = if cos_l > 0.0 {
                    density * hit.t * hit.t / cos_l
                } else {
                    f32::INFINITY
                };
                let l = emission * power_heuristic(pdf_bsdf, pdf_light);
                total += throughput * l;
                if bounce == 0 {
                    direct += l;
                }
            }
            bounce += 1;
            if bounce >= self.max_bounces {
                break;
            }
            let albedo = self.scene.albedo(tri, hit.bary);
            throughput *= albedo;
            let peak = throughput.max_element();
            if peak < self.rr_threshold {
                // Below τ: survive with probability peak/τ, then carry on at τ (module doc).
                // The vertex's roulette number: `bounce` was counted up for the hit above.
                if peak <= 0.0 || rng.roulette(bounce - 1) * self.rr_threshold >= peak {
                    break;
                }
                throughput *= self.rr_threshold / peak;
            }
            let side = if front { 1.0 } else { -1.0 };
            let shading =
                (tri.n[0] * hit.bary.x + tri.n[1] * hit.bary.y + tri.n[2] * hit.bary.z).normalize_or_zero() * side;
            ng = geo * side;
            n = if shading.dot(ng) > 0.0 { shading } else { ng };
            x = p + ng * self.eps;
        }
        // Everything but the first vertex's light samples arrived along the first direction.
        if let Some(d) = first_dir {
            moment.add(total - first_nee, d);
        }
        PathSample { total, direct, moment }
    }

    /// Direct light at `x` from punctual lights, the sun and emissive triangles, as
    /// irradiance / π (visibility tested, MIS-weighted where the continuation can also
    /// find the light).
    fn next_event(&self, x: Vec3, n: Vec3, ng: Vec3, bounce: u32, rng: &mut impl PathSampler) -> (Vec3, Moment) {
        let mut sum = Vec3::ZERO;
        let mut moment = Moment::default();
        let front = |d: Vec3| d.dot(n) > 0.0 && d.dot(ng) > 0.0;
        for light in &self.scene.lights {
            match light.kind {
                LightKind::Directional => {
                    let d = -light.direction;
                    if front(d) && self.tracer.unoccluded(self.scene, x, d, f32::INFINITY) {
                        let c = light.intensity * d.dot(n) * FRAC_1_PI;
                        sum += c;
                        moment.add(c, d);
                    }
                }
                LightKind::Point | LightKind::Spot { .. } => {
                    let to = light.position - x;
                    let dist2 = to.length_squared();
                    if dist2 <= 0.0 {
                        continue;
                    }
                    let dist = dist2.sqrt();
                    let d = to / dist;
                    if !front(d) {
                        continue;
                    }
                    let falloff = light.attenuation(dist, -d) / dist2;
                    if falloff > 0.0 && self.tracer.unoccluded(self.scene, x, d, dist * (1.0 - 1e-4)) {
                        let c = light.intensity * falloff * d.dot(n) * FRAC_1_PI;
                        sum += c;
                        moment.add(c, d);
                    }
                }
            }
        }
        if let Some(sun) = &self.lighting.sun {
            let axis = -sun.direction.normalize();
            let (u1, u2) = rng.sun(bounce);
            let d = cone_sample(axis, sun.cos_half_angle(), u1, u2);
            if front(d) && self.tracer.unoccluded(self.scene, x, d, f32::INFINITY) {
                let pdf_light = 1.0 / sun.solid_angle();
                let cos = d.dot(n);
                let w = power_heuristic(pdf_light, cos * FRAC_1_PI);
                let c = sun.radiance * cos * FRAC_1_PI / pdf_light * w;
                sum += c;
                moment.add(c, d);
            }
        }
        if !self.emitters.emitters.is_empty() {
            let (u, b1, b2) = rng.emitter(bounce);
            let k = self
                .emitters
                .emitter_cdf
                .partition_point(|c| *c <= u)
                .min(self.emitters.emitters.len() - 1);
            let ti = self.emitters.emitters[k];
            let tri = &self.scene.triangles[ti as usize];
            let (mut b1, mut b2) = (b1, b2);
            if b1 + b2 > 1.0 {
                b1 = 1.0 - b1;
                b2 = 1.0 - b2;
            }
            let bary = Vec3::new(1.0 - b1 - b2, b1, b2);
            let y = tri.p[0] * bary.x + tri.p[1] * bary.y + tri.p[2] * bary.z;
            let to = y - x;
            let dist2 = to.length_squared();
            let dist = dist2.sqrt();
            if dist > 0.0 {
                let d = to / dist;
                let geo = self.tracer.geometric_normal(ti);
                let cos_l = -d.dot(geo);
                let two_sided = self.scene.material(tri).double_sided;
                let cos_l = if two_sided { cos_l.abs() } else { cos_l };
                if front(d) && cos_l > 0.0 {
                    let emission = self.scene.emission(tri, bary);
                    // Stop short of the emitter itself so it does not occlude its own sample.
                    if emission != Vec3::ZERO && self.tracer.unoccluded(self.scene, x, d, dist * (1.0 - 1e-4)) {
                        let pdf_light = self.emitters.pick_density[ti as usize] * dist2 / cos_l;
                        let cos = d.dot(n);
                        let w = power_heuristic(pdf_light, cos * FRAC_1_PI);
                        let c = emission * cos * FRAC_1_PI / pdf_light * w;
                        sum += c;
                        moment.add(c, d);
                    }
                }
            }
        }
        (sum, moment)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::scene::build::{MaterialDesc, SceneBuilder};
    use crate::engine::scene::import_slice;
    use crate::engine::scene::library::{closed_box, sky_plane};

    fn gain_of(b: &SceneBuilder) -> f32 {
        let (scene, _) = import_slice(&b.to_glb(), None).unwrap();
        feedback_gain(&scene, &Tracer::new(&scene))
    }

    /// Every ray from a closed box's walls finds a wall: g is the walls' albedo; nothing
    /// above a lone plane: g = 0.
    #[test]
    fn the_gain_of_a_closed_box_is_its_albedo_and_of_a_plane_zero() {
        for rho in [0.5f32, 0.9] {
            let g = gain_of(&closed_box(rho));
            assert!((g - rho).abs() < 1e-5, "closed box of albedo {rho}: g = {g}");
        }
        assert_eq!(gain_of(&sky_plane()), 0.0);
    }

    /// A cube without its top, walls of albedo 0.6: a face sees each adjacent face with
    /// form factor 0.20004 and the opposite one with 0.19982, so the floor sends
    /// 4 x 0.20004 of its rays to walls and each wall 3 x 0.20004 + 0.19982; over the five
    /// equal faces g = 0.6 x 0.79995 = 0.47997. 4096 rays: standard error 0.0038.
    #[test]
    fn the_gain_of_an_open_cube_is_its_form_factor_sum() {
        let mut b = SceneBuilder::new();
        let m = b.material(MaterialDesc::diffuse("wall", [0.6; 3]));
        // `closed_box`'s faces (centre -n, facing n) but the top (centre +y).
        for n in [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::Z, Vec3::NEG_Z] {
            b.square(&format!("face {n}"), -n, 2.0, n, m);
        }
        let g = gain_of(&b);
        let expected = 0.6 * (4.0 * 0.20004 + 4.0 * (3.0 * 0.20004 + 0.19982)) / 5.0;
        assert!(
            (g - expected).abs() < 0.016,
            "open cube: g = {g}, form factors give {expected}"
        );
    }

    /// τ from g: the stiff end, the open end and the line between.
    #[test]
    fn the_automatic_threshold_follows_the_gain() {
        assert_eq!(auto_rr_threshold(0.95), RR_THRESHOLD_STIFF);
        assert_eq!(auto_rr_threshold(0.0), RR_THRESHOLD_OPEN);
        assert!((auto_rr_threshold(0.5) - 0.25).abs() < 1e-6);
    }
}
