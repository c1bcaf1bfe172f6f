//! The contract between the bake loop and a technique (DESIGN §3): the [`Technique`] trait,
//! what a technique is prepared from ([`BakeInputs`]) and the parameter parser every
//! technique uses. Techniques import this module, never `technique` itself or one another
//! (the rule `tests/architecture.rs` checks), so the table in `table.rs` can import every
//! technique without an import cycle.
//!
//! Contract: a technique is prepared once from the scene, the texel set and the job's
//! lighting; then [`Technique::step`] adds one more batch of samples for every valid
//! texel, alternating between two half-accumulators (even and odd steps, DESIGN §4);
//! [`Technique::snapshot`] returns both halves' means at any time. Keeping the halves
//! inside the technique lets a GPU technique accumulate on the GPU and read back only at
//! a snapshot, never per step.
//!
//! Every layer holds irradiance / π at the texel's sample point (the outgoing radiance of
//! a white Lambertian surface), not including the surface's own emission.

use std::sync::Arc;

use serde_json::Value;

use crate::engine::accumulate::Snapshot;
use crate::engine::atlas::Atlas;
pub use crate::engine::error::{EngineError, gpu_error};
use crate::engine::gpu::scene_rays::SceneRays;
use crate::engine::gpu::shaders::PassShader;
use crate::engine::output::OutputLayer;
use crate::engine::plan::{Plan, SceneFeatures};
use crate::engine::scene::{Lighting, Scene};

/// Everything a technique is prepared from.
#[derive(Clone)]
pub struct BakeInputs {
    pub scene: Arc<Scene>,
    /// `scene`'s ray-tracing structures (CPU BVH, emitter table, GPU uploads), built on
    /// first use and shared by every pass of the bake: a technique asks here instead of
    /// building its own.
    pub rays: Arc<SceneRays>,
    pub atlas: Arc<Atlas>,
    pub lighting: Lighting,
    pub seed: u64,
    /// The seed of what a technique measures once before its steps to choose its own
    /// constants (`sdf`'s calibration): `seed` in a single bake; the job's seed in every
    /// chain of a split one (`engine::tasks`), so the chains bake with the same constants
    /// and report the same parameters while their steps draw from their own `seed`.
    pub prepare_seed: u64,
    /// Keep a separate direct-light layer (for the `direct` / `indirect` outputs).
    pub want_direct: bool,
    /// What to create: a technique builds only the passes its plan lists.
    pub plan: Plan,
}

impl BakeInputs {
    /// Inputs for `scene` with its own [`SceneRays`], no direct layer and `plan`.
    pub fn new(scene: Arc<Scene>, atlas: Arc<Atlas>, lighting: Lighting, seed: u64, plan: Plan) -> Self {
        Self::sharing(SceneRays::new(scene), atlas, lighting, seed, plan)
    }

    /// Inputs for the scene of `rays`, sharing them (the bake's other passes hold the
    /// same `rays`).
    pub fn sharing(rays: Arc<SceneRays>, atlas: Arc<Atlas>, lighting: Lighting, seed: u64, plan: Plan) -> Self {
        BakeInputs {
            scene: rays.scene().clone(),
            rays,
            atlas,
            lighting,
            seed,
            prepare_seed: seed,
            want_direct: false,
            plan,
        }
    }
}

/// How far the step in progress is, in thousandths (0 when a step starts, 1000 when it
/// is done), and since when the bake loop has been stepping, for whoever shows progress
/// while one long step runs (issue 19 point 10): the technique writes the thousandths
/// from its worker threads, the loop its clock; a watcher on another thread reads both.
/// A technique that does not report leaves the thousandths at 0
/// ([`Technique::set_step_progress`]). The watcher can also ask the step in progress to
/// stop ([`StepProgress::request_stop`]: a cancelled job): a technique that checks its
/// deadline between parts of a step checks this with it and abandons the step the same
/// way, so a cancel need not wait for a step of minutes to end.
#[derive(Clone, Debug, Default)]
pub struct StepProgress(Arc<StepProgressState>);

#[derive(Debug, Default)]
struct StepProgressState {
    permille: std::sync::atomic::AtomicU32,
    stop: std::sync::atomic::AtomicBool,
    /// Stop once a step has done this many thousandths (0: no such point).
    stop_at: std::sync::atomic::AtomicU32,
    /// When the loop began its first step; None before, and again once it has ended.
    stepping_since: std::sync::Mutex<Option<std::time::Instant>>,
}

impl StepProgress {
    pub fn new() -> Self {
        Self::default()
    }

    /// Thousandths of the current step done.
    pub fn permille(&self) -> u32 {
        self.0.permille.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Records `done` of `of` parts of the current step.
    pub fn set(&self, done: u64, of: u64) {
        // A step of no parts is done.
        let p = (done.min(of) * 1000).checked_div(of).map_or(1000, |p| p as u32);
        self.0.permille.store(p, std::sync::atomic::Ordering::Relaxed);
    }

    /// When the bake loop began stepping, while it steps (the clock its `elapsed` and
    /// its time limit count from); None before it starts and after it ends.
    pub fn stepping_since(&self) -> Option<std::time::Instant> {
        self.0.stepping_since.lock().ok().and_then(|t| *t)
    }

    /// The bake loop starts (`Some(start)`) or ends (`None`).
    pub fn set_stepping_since(&self, start: Option<std::time::Instant>) {
        if let Ok(mut t) = self.0.stepping_since.lock() {
            *t = start;
        }
    }

    /// Asks the bake to stop inside the step in progress (it stays asked).
    pub fn request_stop(&self) {
        self.0.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }

    /// Whether [`request_stop`](StepProgress::request_stop) was called.
    pub fn stop_requested(&self) -> bool {
        self.0.stop.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Asks a sliced GPU step ([`go_on_until`]) to stop at its first check once it has
    /// done `permille` thousandths of the step (1 to 999; 0 takes the point away). For
    /// tests that choose which part of a step a stop lands in: a deadline already passed
    /// always stops a step at its first check.
    pub fn stop_at_permille(&self, permille: u32) {
        self.0.stop_at.store(permille, std::sync::atomic::Ordering::Relaxed);
    }

    /// Whether the step in progress has passed the point of
    /// [`stop_at_permille`](StepProgress::stop_at_permille).
    pub fn past_stop_point(&self) -> bool {
        let at = self.0.stop_at.load(std::sync::atomic::Ordering::Relaxed);
        at > 0 && self.permille() >= at
    }
}

/// What a step sliced on the GPU asks between slices (`TexelRayPass::step_watched`): it
/// reports `done` of `of` to `progress`, and says go on unless `deadline` has passed or
/// the watcher asked to stop.
pub fn go_on_until(
    deadline: Option<std::time::Instant>,
    progress: Option<&StepProgress>,
) -> impl FnMut(u64, u64) -> bool + '_ {
    move |done, of| {
        if let Some(p) = progress {
            p.set(done, of);
        }
        !(progress.is_some_and(|p| p.stop_requested() || p.past_stop_point())
            || deadline.is_some_and(|d| std::time::Instant::now() >= d))
    }
}

/// One page of a bake in rounds (`engine::rounds`, block Jacobi over the grid's regions):
/// the texels that receive light in this bake, and the light every texel is held at for
/// what the others send. Given to [`Technique::hold_boundary`] before the first step.
pub struct Boundary<'a> {
    /// The receivers: a range of the atlas's texels (a region, `Atlas::regions`). Only
    /// they gather, and only their halves mean anything.
    pub receivers: std::ops::Range<usize>,
    /// Per texel of the atlas, irradiance / π (the lightmap's quantity): what the rounds
    /// before estimated. Texels outside the receivers send light from it all bake long;
    /// the receivers start from it.
    pub held: &'a [glam::Vec3],
    /// The receivers' own halves after the rounds before (none in the first round), in
    /// receiver order: the accumulators go on from them, as one bake's would.
    pub resume: Option<&'a Snapshot>,
}

pub trait Technique: Send {
    fn id(&self) -> &'static str;
    /// The parameters in effect, defaults filled in (written into the EXR header).
    fn params(&self) -> Value;
    /// Adds one step of samples to the half-accumulator of this step's parity.
    fn step(&mut self) -> Result<(), EngineError>;
    fn steps_done(&self) -> u64;
    /// Both halves' current means, per valid texel.
    fn snapshot(&mut self) -> Result<Snapshot, EngineError>;
    /// The pass that writes the accumulators, named when a snapshot is not finite.
    fn accumulating_pass(&self) -> &'static str;
    /// The plain obscurance / sky visibility per valid texel (the `ao.Y` layer) as of
    /// the last snapshot, for techniques that compute one.
    fn ao(&self) -> Option<Vec<f32>> {
        None
    }
    /// A scene-wide ambient the last snapshot's halves hold (`engine::ambient`): per half,
    /// the area-weighted sums over this bake's texels it was closed from and each texel's
    /// weight, for techniques that bounce light through one (`sdf`). A split bake's merge
    /// closes it over every region's texels ([`TaskSplit::ChainsAndRegions`]).
    fn ambient(&self) -> Option<[crate::engine::ambient::AmbientHalf; 2]> {
        None
    }
    /// The instant the bake's time limit ends (issue 19 point 10), set once before the
    /// first step. A technique whose step can be long checks it between parts of a step
    /// and, once it has passed, abandons the step: adds nothing and leaves
    /// [`steps_done`](Technique::steps_done) as it was, so the loop stops within a part of
    /// a step of the limit. The default ignores it (the step runs whole); which
    /// techniques honour it is in docs/quality.md ("Time budget").
    fn set_deadline(&mut self, _deadline: Option<std::time::Instant>) {}
    /// Blocks until the device has finished the work of every step submitted so far, so
    /// that the bake loop's clock measures what a step costs. The loop calls it after each
    /// step of a bake with a time limit. A GPU technique whose step only queues one or a
    /// few dispatches implements it; without it the loop saw a submission's microseconds
    /// as the step's length and queued more steps than the limit had room for (`sdf` on
    /// the Kenney level at 2048², lavapipe: 14.3 s of steps for `--seconds 5`). The
    /// default (CPU techniques, and `path`, which times its own GPU steps) returns at once.
    fn wait_for_steps(&mut self) -> Result<(), EngineError> {
        Ok(())
    }
    /// Where to report how far each step is ([`StepProgress`]), set once before the
    /// first step; the default reports nothing (the watcher sees 0 until the step ends).
    fn set_step_progress(&mut self, _progress: StepProgress) {}
    /// Makes this bake one page of a bake in rounds (`engine::rounds`): light is received
    /// only at `boundary.receivers`, the other texels send what `boundary.held` says, and
    /// the receivers' accumulators go on from `boundary.resume`. Called once, before the
    /// first step. The default refuses: only techniques whose step reads the whole grid's
    /// light from a state they can hold (`hemicube`, `sdb`; the table's `rounds`) bake in
    /// rounds.
    fn hold_boundary(&mut self, _boundary: &Boundary<'_>) -> Result<(), EngineError> {
        Err(EngineError::BadInput(format!(
            "rounds: technique {} is not baked in rounds",
            self.id()
        )))
    }
    /// Makes this bake's first step the job's step `first` (a task of a split bake,
    /// `engine::tasks`): the random streams are keyed by the global step, so the task
    /// draws exactly the samples a whole bake would at those steps. Called once, before
    /// the first step, only for techniques whose row says [`TaskSplit::StepsAndRegions`].
    fn start_at_step(&mut self, first: u64) -> Result<(), EngineError> {
        if first == 0 {
            return Ok(());
        }
        Err(EngineError::Internal(format!(
            "technique {} cannot start at step {first}: its bakes are not split into step ranges",
            self.id()
        )))
    }
}

/// How a bake of a technique may be split into tasks that several workers bake at once
/// (`engine::tasks`, docs/scaling.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TaskSplit {
    /// Every step is an independent batch of samples drawn from streams keyed by
    /// (seed, global step, texel's pixel, sample), and no texel's value depends on
    /// another's: a task bakes a range of steps of one region of the grid (pages or
    /// tiles, `atlas::regions`), the sums of its two half-accumulators add to the whole
    /// bake's exactly, and its region's texels are the whole bake's.
    StepsAndRegions,
    /// A step depends on the whole grid's state or on whole-grid measurements (a chain
    /// of steps, running ratios, a bias measured at control texels spread over the grid),
    /// so no range of steps and no region of the grid is a part of a single bake; but the
    /// whole bake is a function of its seed alone. A task is an *independent chain*: the
    /// whole grid baked from step 0 with its own seed (`tasks::chain_seed`), and the merge
    /// is the step-weighted mean of the chains' halves. The reason says why not step
    /// ranges or regions, for the error a request with regions gets.
    Chains(&'static str),
    /// [`Chains`](TaskSplit::Chains) within regions of the grid (pages or tiles, as
    /// `StepsAndRegions`): a texel's value depends on the scene and the seed, never on
    /// another texel (nor on which texels the grid holds), except through a scene-wide
    /// ambient the technique reports ([`Technique::ambient`]), which the merge closes
    /// over every region's texels; so a region's task with the job's seed bakes the
    /// single bake's texels of its region, and its chains average as `Chains`. The
    /// reason says why not step ranges.
    ChainsAndRegions(&'static str),
}

/// Which of a technique's visibility queries honour glTF alpha (`alphaMode` MASK and
/// BLEND, `Scene::stops_ray`). Rays do (the CPU tracer and the GPU BVH), and so do the
/// rasterised maps (the shared shadow atlas, sdb's illumination and shadow maps,
/// obscurance's depth layers: `gpu/materials.wgsl`); a signed distance field holds
/// occupancy, not partial coverage. A job on a scene with such materials gets a plan line
/// saying which (`job::plan_for`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AlphaSupport {
    /// Every visibility query of its bake tests alpha.
    Everywhere,
    /// Only some: `tested` names those, `opaque` the rest.
    Partly { tested: &'static str, opaque: &'static str },
}

/// Parses a technique's parameter object, naming the technique in the error.
pub fn parse_params<T: serde::de::DeserializeOwned + Default>(
    technique: &str,
    params: &Value,
) -> Result<T, EngineError> {
    if params.is_null() {
        return Ok(T::default());
    }
    serde_json::from_value(params.clone()).map_err(|e| EngineError::BadInput(format!("params for {technique}: {e}")))
}

/// How a technique is prepared for a bake: the inputs and the job's parameter object.
pub type Prepare = fn(BakeInputs, &Value) -> Result<Box<dyn Technique>, EngineError>;

/// What a technique registers.
#[derive(Clone, Copy)]
pub struct TechniqueEntry {
    /// The id a job names (`"technique": "sdb"`).
    pub id: &'static str,
    /// One line for `--help`, the service's description and the docs.
    pub summary: &'static str,
    /// The plan it makes for a scene (DESIGN §6), before any GPU work.
    pub plan: fn(&SceneFeatures) -> Plan,
    /// Prepares it for a bake; `params` is the job's parameter object (unknown fields are
    /// rejected).
    pub prepare: Prepare,
    /// Every WGSL pass it compiles (validated without a device, see the tests below).
    pub shaders: &'static [PassShader],
    /// The optional output layers it writes; `validity` and `debug` come from the texel
    /// set and `shadowmask` from the shared GPU pass, for every technique
    /// ([`TechniqueEntry::writes`]). A job asking for another layer is refused
    /// before baking (`table::check_request`).
    pub layers: &'static [OutputLayer],
    /// The light it transports; a job whose scene or lighting has other light is refused
    /// before baking rather than baked without it (`table::check_lights`).
    pub lights: &'static [LightSource],
    /// Parses and checks a parameter object without preparing anything, so a bad one is
    /// caught when the job is submitted, not when it runs.
    pub check_params: fn(&Value) -> Result<(), EngineError>,
    /// The estimator converges to the answer (only `path`, the reference): its noise is
    /// its whole error. A biased technique's bake measures its bias at control texels
    /// (`engine::control`).
    pub unbiased: bool,
    /// Where it alpha-tests MASK and BLEND surfaces.
    pub alpha: AlphaSupport,
    /// How its bakes split into tasks.
    pub tasks: TaskSplit,
    /// It bakes a region of the grid with the rest held (`engine::rounds`,
    /// [`Technique::hold_boundary`]).
    pub rounds: bool,
    /// Its parameter object with every default filled in (what `params: {}` means):
    /// the names, types and defaults the service's bake form is built from.
    pub default_params: fn() -> Value,
}

impl TechniqueEntry {
    /// Whether a job with this technique may ask for `layer`: the row's own layers, and
    /// those the engine writes for every technique (`validity` and `debug` from the texel
    /// set, `shadowmask` from `gpu::shadowmask`).
    pub fn writes(&self, layer: OutputLayer) -> bool {
        matches!(
            layer,
            OutputLayer::Validity | OutputLayer::Debug | OutputLayer::Shadowmask
        ) || self.layers.contains(&layer)
    }
}

/// A kind of light, as the technique table's `lights` column names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LightSource {
    /// The job's sky (`lighting.sky`).
    Sky,
    /// The job's sun (`lighting.sun`).
    Sun,
    /// The scene's directional `KHR_lights_punctual` lights.
    DirectionalLights,
    /// The scene's point and spot `KHR_lights_punctual` lights.
    PointSpotLights,
    /// The scene's emissive triangles.
    Emitters,
}

impl LightSource {
    pub const ALL: &'static [LightSource] = &[
        LightSource::Sky,
        LightSource::Sun,
        LightSource::DirectionalLights,
        LightSource::PointSpotLights,
        LightSource::Emitters,
    ];

    /// How much of this light a scene and job have (0: none).
    pub fn count(self, f: &SceneFeatures) -> usize {
        match self {
            LightSource::Sky => usize::from(f.sky),
            LightSource::Sun => usize::from(f.sun),
            LightSource::DirectionalLights => f.directional_lights,
            LightSource::PointSpotLights => f.punctual_lights.saturating_sub(f.directional_lights),
            LightSource::Emitters => f.emissive_triangles,
        }
    }

    /// What the light is called in an error, with `n` of it.
    pub fn describe(self, n: usize) -> String {
        match self {
            LightSource::Sky => "the job's sky".into(),
            LightSource::Sun => "the job's sun".into(),
            LightSource::DirectionalLights => format!("the scene's {n} directional light(s)"),
            LightSource::PointSpotLights => format!("the scene's {n} point/spot light(s)"),
            LightSource::Emitters => format!("the scene's {n} emissive triangle(s)"),
        }
    }

    /// The job field that brings this light (scene lights come with the scene).
    pub fn field(self) -> &'static str {
        match self {
            LightSource::Sky => "lighting.sky",
            LightSource::Sun => "lighting.sun",
            _ => "technique",
        }
    }
}
