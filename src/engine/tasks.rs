//! One bake split into tasks that several workers (or processes, or machines) bake at
//! once, and the exact merge of what they baked (issue 25; docs/scaling.md).
//!
//! A split has a shape ([`TaskShape`]): `tasks` in all, as `regions` regions of the
//! texel grid times `tasks / regions` ranges of the job's steps; task k bakes region
//! `k / ranges` over step range `k % ranges`. What may be split depends on the technique
//! (its table row's [`TaskSplit`]):
//! - `path` (`StepsAndRegions`): both.
//!   - *Step ranges.* Every random stream is keyed by (seed, *global* step, texel's
//!     pixel, sample) (`Technique::start_at_step`), so a task draws exactly the samples a
//!     single bake draws at those steps. Each range but the last has an even length, so
//!     every task starts on an even step and its local even/odd halves are the job's
//!     even/odd halves. The merge adds the halves' sums (mean × steps) and step counts.
//!   - *Regions* (`atlas::regions`): whole pages when there are at most as many regions
//!     as pages (one page per task when as many), else bands of rows cut to equal texel
//!     counts (tiles as wide as the grid). A path's texels share nothing but the scene, and
//!     the streams are keyed by pixel, not by the texel's place in the list, so a region's
//!     task bakes exactly the region's texels of a single bake. The merge places each
//!     region's halves at its texels.
//!
//!   Either way the merged halves are the single bake's halves up to float rounding (the
//!   order of the step additions; regions alone are bit-identical on the CPU), so the
//!   merged estimate, its error estimate from the halves' difference (DESIGN §4) and the
//!   delivered lightmap are a single bake's, not a different bake "within noise".
//! - `vpl` (`ChainsAndRegions`): regions as `path`'s (a texel gathers from the scene's
//!   lights, which come from the scene and the seed alone, and its frame is the scene's:
//!   a region's task with the job's seed bakes exactly the single bake's texels of its
//!   region, each region measuring its bias at its own control texels, which the merge
//!   joins), and within a region independent chains as below (its lights come from a
//!   stratified sequence advanced step by step, so not step ranges).
//! - `sdf` and `obscurance` (`ChainsAndRegions` too): regions as `vpl`'s, with two more
//!   things made the same in every task. What they read of the whole grid is built alike
//!   whichever region a task holds (sdf's calibration texels, drawn over the whole grid by
//!   a key of their pixel, `Coverage::smallest`; obscurance's material maps and R_ave,
//!   from the grid's texels before validation, `Atlas::grid_texels`), and their light
//!   bounces through one scene-wide ambient made of sums over every texel, which a task
//!   reports with each texel's weight (`Technique::ambient`, `engine::ambient`) and the
//!   merge closes over every region ([`close_ambient`]): chain j of every region is one
//!   whole bake, so each task's texels are moved from the ambient its region alone closed
//!   to that bake's. Their streams (sdf's jitter, the shared direct light's) are keyed by
//!   pixel, and their volumes' and maps' frames are the scene's triangles'.
//! - `sdb` and `hemicube` (`Chains`): *independent chains* only. Each step transports
//!   the light the steps before it left over the whole grid, so no range of their steps
//!   and no region of their grid is a part of a single bake (the row says why). But a
//!   whole bake is a function of its seed, so task k bakes the whole grid from step 0 with its own
//!   seed ([`chain_seed`]: chain 0 the job's) for its share of the job's steps, and the
//!   merge is the same step-weighted mean of the halves ([`merge_halves`]).
//!   - *Why the mean is right.* The chains are independent draws of one estimator (same
//!     scene, parameters and step count up to one), so their mean has the expectation of
//!     one chain, its noise divided by sqrt(chains), and a chain's bias. Each half of the
//!     merge is the mean of the chains' halves, so the halves' difference still measures
//!     the merged noise (DESIGN §4).
//!   - *What it costs.* A chain of S/K steps is not a chain of S steps: what decays with
//!     the steps (sdb's and hemicube's transient of the first bounces, about 1/M² with
//!     their ramp weights; sdb's bootstrap step, left out of its halves, in every chain)
//!     stays at its S/K-step size. That is bias, not noise, and the merge measures it as a
//!     single bake does: each chain's control texels (the job's seed picks them, so every
//!     chain has the same) are traced by path with the chain's own seed; the chains'
//!     references are averaged like the halves, and the merged lightmap is assessed
//!     against that (`control::assess_against`), so the merged error states the bias of
//!     short chains. Preparation-time fits (`sdf`'s calibration of k and alpha) draw from
//!     the job's seed (`BakeInputs::prepare_seed`), so every chain bakes with the same
//!     constants and the parameters the job reports are the chains'.
//!   - Each chain repeats the whole-scene work once (the scene's maps, fields, rays'
//!     structures): chains pay off when steps dominate, which is the long bake.
//!   - `hemicube` and `sdb` also bake regions in rounds, the other regions' light held
//!     (`engine::rounds`; [`split_rounds`]), in one process, on the command line or on
//!     the queue.
//!
//! A split bake's stop rule is `stop.steps`, the job's total; `stop.seconds` bounds
//! each task on its own (a task that runs out of time delivers fewer steps, and the
//! merge counts what each delivered: within a region, the step-weighted mean; across
//! regions, the fewest steps any region got is the step count reported);
//! `stop.target_error` is refused, since it is a rule about the whole bake's error that
//! no task sees.
//!
//! A task's result is a [`Partial`]: the request, the task, a fingerprint of the texel
//! set it baked (its region's), both halves' means with their step counts, the
//! pixel of each texel (what its validation kept), the technique's `ao` layer when it has
//! one, and a chain's control texels with its reference's halves there. Its file
//! format is this module's own (an 8-byte magic, the JSON header's length and the
//! header, then little-endian f32 arrays; docs/scaling.md has the layout): the data is
//! per valid texel, not per pixel, so an image format would only add a layout to undo,
//! and the header is plain JSON any tool reads.
//!
//! While it runs, a task may hand its halves so far on ([`bake_task_live`]: a
//! [`Partial`] marked `live`), and [`merge_running`] merges whatever the tasks have so
//! far into the job's running estimate (the service's snapshots of a split job); the
//! final merge refuses such halves.
//!
//! The merge rebuilds the texel set and its regions from the scene and request
//! (deterministic, `job::prepare_regions`), taking the tasks' validation (the texels
//! they kept) instead of tracing it again, and refuses partials of another request,
//! another texel set, a missing or repeated task, or a cancelled one, naming which.
//!
//! Limits: no shadowmask layer in a split bake yet (its pass would need the same step
//! offset and region); a task's probes are not baked (the merge bakes them, once); every
//! task imports the whole scene and builds its BVH; a region's task rasterises the whole
//! grid only into a bit a pixel to cut it (`Atlas::coverage`) and builds, validates and
//! bakes its region's texels alone (`Atlas::build_pixels`, its pixel-to-texel index
//! a window of its own pixels); a chain's task is a whole bake; the merge builds the
//! whole texel set.

use std::ops::Range;
use std::sync::Arc;
use std::time::Duration;

use glam::Vec3;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use sha2::{Digest, Sha256};

use crate::engine::accumulate::{Estimate, HalfEstimate, Snapshot};
use crate::engine::ambient::{AmbientHalf, AmbientSums};
use crate::engine::atlas::Atlas;
use crate::engine::bake::{BakeObserver, LiveHalves, LiveHook, StopCriteria, StopReason};
use crate::engine::control;
use crate::engine::job::{self, BakeOptions, BakeRequest, BakeResult};
use crate::engine::output::OutputLayer;
use crate::engine::plan::Plan;
use crate::engine::scene::Scene;
use crate::engine::technique::api::TaskSplit;
use crate::engine::technique::{self, BakeInputs, EngineError};

/// At most this many tasks per bake.
pub const MAX_TASKS: u32 = 1024;

/// The format version a [`Partial`] file carries; a merge refuses others. 2: tasks carry
/// their region (format 1 had step ranges only, and path streams keyed by texel index).
/// 3: chains (`TaskRange::chain`), with their control texels' reference and their `ao`
/// layer. 4: a technique's scene-wide ambient (`ambient`), and `sdf`'s and the shared
/// direct light's streams keyed by pixel.
pub const PARTIAL_FORMAT: u32 = 4;

const MAGIC: &[u8; 8] = b"LMDTASK1";

/// How a bake is split: `tasks` in all, `regions` regions of the grid (whole pages, or
/// tiles) each baked as `tasks / regions` step ranges.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct TaskShape {
    pub tasks: u32,
    pub regions: u32,
}

impl TaskShape {
    /// `tasks` step ranges of the whole grid.
    pub fn steps(tasks: u32) -> TaskShape {
        TaskShape { tasks, regions: 1 }
    }

    /// Step ranges per region.
    pub fn ranges(&self) -> u32 {
        self.tasks / self.regions.max(1)
    }
}

/// One task of a split bake: the `index`-th of `count`, baking region `region` of
/// `regions` over the job's steps `first_step .. first_step + steps`.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct TaskRange {
    pub index: u32,
    pub count: u32,
    pub region: u32,
    pub regions: u32,
    pub first_step: u64,
    pub steps: u64,
    /// An independent chain ([`TaskSplit::Chains`]): the whole grid baked from step 0
    /// with the seed [`chain_seed`]`(job's seed, index)`; `first_step` is then 0.
    #[serde(default)]
    pub chain: bool,
    /// A bake in rounds (`engine::rounds`, [`split_rounds`]): this task is region
    /// `region` in round `round` of `rounds`, its steps the round's share; 0 rounds: not
    /// a bake in rounds.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub round: u32,
    #[serde(default, skip_serializing_if = "is_zero")]
    pub rounds: u32,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

impl TaskRange {
    /// The seed this task bakes with, of a job seeded `job`: a chain's own
    /// ([`chain_seed`] of its place among its region's chains, so every region's first
    /// chain has the job's), else the job's.
    pub fn seed(&self, job: u64) -> u64 {
        if self.chain {
            chain_seed(job, self.index % self.shape().ranges().max(1))
        } else {
            job
        }
    }

    pub fn shape(&self) -> TaskShape {
        TaskShape {
            tasks: self.count,
            regions: self.regions,
        }
    }
}

/// The seed chain `index` of a job seeded `seed` bakes with: chain 0 the job's own (so
/// a one-chain split is the single bake), the others SplitMix64 of the seed and the
/// index, so no two chains of a job draw the same streams.
pub fn chain_seed(seed: u64, index: u32) -> u64 {
    if index == 0 {
        seed
    } else {
        crate::engine::rng::splitmix64(seed ^ u64::from(index).wrapping_mul(0x9E37_79B9_7F4A_7C15))
    }
}

/// The tasks `request` splits into with `shape`, or why it cannot be. One task is
/// always possible: it is the whole bake. Whether the grid has as many texels as regions
/// is known only once the scene is prepared ([`bake_task`] says so).
pub fn split(request: &BakeRequest, shape: TaskShape) -> Result<Vec<TaskRange>, EngineError> {
    let bad = |m: String| Err(EngineError::BadInput(m));
    let TaskShape { tasks: count, regions } = shape;
    if !(1..=MAX_TASKS).contains(&count) {
        return bad(format!("tasks must be in 1..={MAX_TASKS}, got {count}"));
    }
    if regions == 0 || regions > count || count % regions != 0 {
        return bad(format!(
            "regions must divide tasks (each region is baked as tasks / regions step ranges): {regions} regions of {count} tasks"
        ));
    }
    let entry = technique::entry(&request.technique)?;
    if count == 1 {
        let steps = request.stop.steps.unwrap_or(u64::MAX);
        return Ok(vec![TaskRange {
            index: 0,
            count: 1,
            region: 0,
            regions: 1,
            first_step: 0,
            steps,
            chain: false,
            round: 0,
            rounds: 0,
        }]);
    }
    let chains = match entry.tasks {
        TaskSplit::StepsAndRegions => false,
        TaskSplit::Chains(why) if regions > 1 => {
            return bad(format!(
                "regions: {} bakes are split into independent chains of the whole grid, not into regions ({why}); \
                 give regions 1",
                request.technique
            ));
        }
        TaskSplit::Chains(_) | TaskSplit::ChainsAndRegions(_) => true,
    };
    if request.stop.target_error.is_some() {
        return bad(
            "tasks: stop.target_error is a rule about the whole bake's error, which no task sees alone; \
             give stop.steps (the job's total) instead"
                .into(),
        );
    }
    let Some(total) = request.stop.steps else {
        return bad("tasks: a split bake needs stop.steps, the job's total steps that its tasks share".into());
    };
    let ranges = shape.ranges();
    if total < 2 * ranges as u64 {
        let what = match (chains, regions > 1) {
            (true, false) => "chains",
            (true, true) => "chains per region",
            (false, _) => "step ranges per region",
        };
        return bad(format!(
            "tasks: stop.steps ({total}) must be at least twice the {what} ({ranges}): each task bakes a step of each half"
        ));
    }
    if request.outputs.contains(&OutputLayer::Shadowmask) {
        return bad("tasks: the shadowmask layer is not baked in split bakes yet; bake it as one task".into());
    }
    if chains {
        // Every chain starts at step 0; each region's chains share the job's steps
        // evenly.
        let n = u64::from(ranges);
        return Ok((0..count)
            .map(|index| {
                let c = u64::from(index % ranges);
                TaskRange {
                    index,
                    count,
                    region: index / ranges,
                    regions,
                    first_step: 0,
                    steps: total / n + u64::from(c < total % n),
                    chain: true,
                    round: 0,
                    rounds: 0,
                }
            })
            .collect());
    }
    // Pairs of steps dealt out evenly, so every range starts on an even step; an odd
    // total leaves one step for the last range.
    let (pairs, odd) = (total / 2, total % 2);
    let n = ranges as u64;
    let mut spans = Vec::with_capacity(ranges as usize);
    let mut first = 0;
    for i in 0..n {
        let steps = 2 * (pairs / n + u64::from(i < pairs % n)) + if i == n - 1 { odd } else { 0 };
        spans.push((first, steps));
        first += steps;
    }
    Ok((0..count)
        .map(|index| {
            let (first_step, steps) = spans[(index % ranges) as usize];
            TaskRange {
                index,
                count,
                region: index / ranges,
                regions,
                first_step,
                steps,
                chain: false,
                round: 0,
                rounds: 0,
            }
        })
        .collect())
}

/// Upper bound on the rounds of a bake in rounds: each repeats every region's preparation.
pub const MAX_ROUNDS: u32 = 64;

/// The steps of each of `rounds` rounds out of `total`: each round twice the one before
/// (rounded down, at least one step; the last takes what is left), so the last round
/// bakes about half the steps. Why not even shares: a region's accumulators go on over
/// the rounds, and a step of round r carries what the held light still lacked then (a
/// page alone in round 0 reads 0.62 of the closed box's 1). With the ramp weights the
/// first rounds' share of the mean is about the square of their share of the steps, so
/// short early rounds leave little of it: on the closed box of albedo 0.5 in four rounds,
/// even shares read 0.898, doubling ones 0.949 (docs/scaling.md).
pub fn round_steps(total: u64, rounds: u32) -> Vec<u64> {
    let r = rounds.clamp(1, MAX_ROUNDS);
    let parts = (1u64 << r) - 1;
    let mut steps: Vec<u64> = (0..r - 1).map(|i| (total * (1u64 << i) / parts).max(1)).collect();
    let before: u64 = steps.iter().sum();
    steps.push(total.saturating_sub(before).max(1));
    steps
}

/// The tasks of a bake in rounds (`engine::rounds`): per round, one task a region, task
/// k of a round baking region k over the round's share of `stop.steps` (every region's
/// steps over all rounds), or why it cannot be. Round r's tasks read every round r-1
/// task's result (the held light), so a round is baked once the round before is.
pub fn split_rounds(request: &BakeRequest, regions: u32, rounds: u32) -> Result<Vec<Vec<TaskRange>>, EngineError> {
    let bad = |m: String| Err(EngineError::BadInput(m));
    if !(1..=MAX_ROUNDS).contains(&rounds) {
        return bad(format!("rounds must be in 1..={MAX_ROUNDS}, got {rounds}"));
    }
    if !(1..=MAX_TASKS).contains(&regions) {
        return bad(format!("rounds: regions must be in 1..={MAX_TASKS}, got {regions}"));
    }
    if !technique::entry(&request.technique)?.rounds {
        return bad(format!(
            "rounds: technique {} is not baked in rounds (only {} are, so far)",
            request.technique,
            technique::TABLE
                .iter()
                .filter(|e| e.rounds)
                .map(|e| e.id)
                .collect::<Vec<_>>()
                .join(" and ")
        ));
    }
    if request.stop.seconds.is_some() || request.stop.target_error.is_some() {
        return bad(
            "rounds: stop.seconds and stop.target_error are rules about the whole bake, which no round sees alone; \
             give stop.steps (every region's steps, over all rounds)"
                .into(),
        );
    }
    let Some(total) = request.stop.steps else {
        return bad("rounds: a bake in rounds needs stop.steps, every region's steps over all rounds".into());
    };
    if total < 2 * u64::from(rounds) {
        return bad(format!(
            "rounds: stop.steps ({total}) must be at least twice the rounds ({rounds}): each round bakes a step of each half"
        ));
    }
    if request.outputs.contains(&OutputLayer::Shadowmask) {
        return bad("rounds: the shadowmask layer is not baked in rounds yet; bake it as one task".into());
    }
    let mut first_step = 0;
    Ok(round_steps(total, rounds)
        .into_iter()
        .enumerate()
        .map(|(round, steps)| {
            let tasks = (0..regions)
                .map(|region| TaskRange {
                    index: region,
                    count: regions,
                    region,
                    regions,
                    first_step,
                    steps,
                    chain: false,
                    round: round as u32,
                    rounds,
                })
                .collect();
            first_step += steps;
            tasks
        })
        .collect())
}

/// What a task baked: its halves' means and step counts, and what the merge checks.
#[derive(Clone, Debug)]
pub struct Partial {
    pub header: PartialHeader,
    pub snapshot: Snapshot,
    /// The pixel of each texel it baked, in order: the texels its validation kept, which
    /// the merge takes instead of validating the whole grid again.
    pub pixels: Vec<u32>,
    /// The technique's `ao` layer (`Technique::ao`) per texel, when it has one.
    pub ao: Option<Vec<f32>>,
    /// The technique's scene-wide ambient per half (`Technique::ambient`): the sums over
    /// the task's texels (also in the header) and each texel's weight, which the merge
    /// closes over every region ([`close_ambient`]).
    pub ambient: Option<[AmbientHalf; 2]>,
    /// A bake in rounds: the task's estimate from its round's own steps, per texel (the
    /// held light of the next round, `engine::rounds`).
    pub held: Option<Vec<Vec3>>,
}

/// A chain's control texels (`engine::control`) and its path reference's halves at them:
/// the merge averages the chains' references and measures the merged lightmap's bias
/// against that, as a single bake measures its own. Small (256 texels), so kept in the
/// JSON header.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ControlHalves {
    /// Indices into the task's texels; every chain of a job has the same (picked with the
    /// job's seed).
    pub texels: Vec<u32>,
    pub half_steps: [u64; 2],
    pub even: Vec<[f32; 3]>,
    pub odd: Vec<[f32; 3]>,
}

impl ControlHalves {
    pub(crate) fn of(indices: &[usize], reference: &Snapshot) -> ControlHalves {
        let flat = |v: &[Vec3]| v.iter().map(|x| x.to_array()).collect();
        ControlHalves {
            texels: indices.iter().map(|&k| k as u32).collect(),
            half_steps: [reference.even.steps, reference.odd.steps],
            even: flat(&reference.even.total),
            odd: flat(&reference.odd.total),
        }
    }

    fn snapshot(&self) -> Snapshot {
        let half = |steps: u64, v: &[[f32; 3]]| HalfEstimate {
            steps,
            total: v.iter().map(|x| Vec3::from_array(*x)).collect(),
            direct: None,
            moments: None,
        };
        Snapshot {
            even: half(self.half_steps[0], &self.even),
            odd: half(self.half_steps[1], &self.odd),
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PartialHeader {
    pub format: u32,
    /// The whole job's request (every task of a job carries the same one).
    pub request: BakeRequest,
    pub task: TaskRange,
    /// The technique's parameters in effect (defaults filled in).
    pub params: Value,
    /// The texel set baked: its size, and a SHA-256 of its sample points and normals.
    pub width: u32,
    pub height: u32,
    pub texels: u64,
    pub fingerprint: String,
    pub half_steps: [u64; 2],
    pub direct: bool,
    pub moments: bool,
    /// Whether an `ao` layer follows the pixels.
    pub ao: bool,
    /// The technique's scene-wide ambient sums per half, when it has one; each half's
    /// texel weights (rgb) follow the `ao` layer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ambient: Option<[AmbientSums; 2]>,
    /// A chain's control texels and reference (a biased technique's, `engine::control`).
    pub control: Option<ControlHalves>,
    /// The task's own bake time.
    pub seconds: f64,
    pub stopped_by: StopReason,
    /// A running task's halves so far ([`bake_task_live`]), for the job's snapshots: never
    /// a result the merge takes.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub live: bool,
    /// Whether the round's own estimate (`Partial::held`) follows the ambient weights.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub held: bool,
}

impl PartialHeader {
    /// This header for `snapshot`'s halves (their steps and layers), with its `ao` layer
    /// or not, its control texels' reference and its bake time.
    fn with_halves(
        &self,
        snapshot: &Snapshot,
        ao: bool,
        ambient: Option<&[AmbientHalf; 2]>,
        control: Option<ControlHalves>,
        elapsed: Duration,
    ) -> PartialHeader {
        PartialHeader {
            half_steps: [snapshot.even.steps, snapshot.odd.steps],
            direct: snapshot.even.direct.is_some(),
            moments: snapshot.even.moments.is_some(),
            ao,
            ambient: ambient.map(|a| [a[0].sums, a[1].sums]),
            control,
            seconds: elapsed.as_secs_f64(),
            ..self.clone()
        }
    }
}

/// The texel set's fingerprint: SHA-256 over the grid's size and every valid texel's
/// pixel, sample point and normal, so a merge notices partials of another texel set even
/// when it has as many texels.
pub fn fingerprint(atlas: &Atlas) -> String {
    texels_fingerprint(atlas, 0..atlas.texels.len())
}

/// The fingerprint of the texels `range` of `atlas` (a region's).
pub(crate) fn texels_fingerprint(atlas: &Atlas, range: std::ops::Range<usize>) -> String {
    let mut h = Sha256::new();
    h.update(atlas.width.to_le_bytes());
    h.update(atlas.height.to_le_bytes());
    for t in &atlas.texels[range] {
        h.update(t.pixel.to_le_bytes());
        for v in [t.position, t.normal] {
            for c in v.to_array() {
                h.update(c.to_le_bytes());
            }
        }
    }
    let digest = h.finalize();
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// Bakes one task of `request`: the bake loop over the task's steps, keyed by the
/// job's step numbers, and its halves read back raw (not denoised: the merge denoises
/// the whole). `observer` sees the task's own steps.
pub fn bake_task(
    scene: Arc<Scene>,
    request: &BakeRequest,
    task: TaskRange,
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
    on_plan: &mut dyn FnMut(&Plan),
) -> Result<Partial, EngineError> {
    bake_task_live(scene, request, task, options, observer, on_atlas, on_plan, None)
}

/// Where a running task's halves go ([`bake_task_live`]): a [`Partial`] marked `live`,
/// at a snapshot, at most once every `every`.
pub struct LiveTask {
    pub every: Duration,
    pub sink: Box<dyn FnMut(Partial) + Send>,
}

/// [`bake_task`] that also hands its halves so far to `live` while it runs (the
/// service merges them into the job's snapshots, [`merge_running`]). The partial is
/// built on the bake thread: a clone of the halves and the texels' pixels.
#[allow(clippy::too_many_arguments)]
pub fn bake_task_live(
    scene: Arc<Scene>,
    request: &BakeRequest,
    task: TaskRange,
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
    on_plan: &mut dyn FnMut(&Plan),
    live: Option<LiveTask>,
) -> Result<Partial, EngineError> {
    let tasks = split(request, task.shape())?;
    if tasks.get(task.index as usize) != Some(&task) {
        return Err(EngineError::BadInput(format!(
            "task {}/{} is not one of this request's tasks",
            task.index, task.count
        )));
    }
    // The task's probes are the merge's to bake, once.
    let mut own = request.clone();
    own.probes = None;
    own.seed = task.seed(request.seed);
    let regions = (task.regions > 1).then_some(job::RegionsOf {
        count: task.regions,
        keep: Some(task.region),
        validated: None,
        trace: None,
    });
    let prepared = job::prepare_regions(scene, &own, options, regions, on_atlas, on_plan)?;
    let pixels: Vec<u32> = prepared.atlas.texels.iter().map(|t| t.pixel).collect();
    let inputs = BakeInputs {
        prepare_seed: request.seed,
        ..prepared.inputs(&own)
    };
    let mut tech = technique::create(&request.technique, inputs, &request.params)?;
    tech.start_at_step(task.first_step)?;
    let stop = StopCriteria {
        steps: Some(task.steps),
        seconds: request.stop.seconds,
        target_error: None,
    };
    // A chain's control texels are the job's (picked with its seed), its reference
    // traced with the chain's seed.
    let mut bake_loop = prepared.bake_loop_picking(&own, stop, options, request.seed)?;
    // What every partial of this task says about it (parameters are fixed at creation);
    // the halves' part is filled in per partial.
    let template = PartialHeader {
        format: PARTIAL_FORMAT,
        request: request.clone(),
        task,
        params: tech.params(),
        width: prepared.atlas.width,
        height: prepared.atlas.height,
        texels: prepared.atlas.texels.len() as u64,
        fingerprint: fingerprint(&prepared.atlas),
        half_steps: [0, 0],
        direct: false,
        moments: false,
        ao: false,
        ambient: None,
        control: None,
        seconds: 0.0,
        stopped_by: StopReason::Steps,
        live: false,
        held: false,
    };
    if let Some(LiveTask { every, mut sink }) = live {
        let template = PartialHeader {
            live: true,
            ..template.clone()
        };
        let pixels = pixels.clone();
        bake_loop.live = Some(LiveHook::new(
            every,
            Box::new(move |h: LiveHalves| {
                let control = h
                    .control
                    .map(|(indices, reference)| ControlHalves::of(&indices, &reference));
                let header = template.with_halves(&h.snapshot, h.ao.is_some(), h.ambient.as_ref(), control, h.elapsed);
                sink(Partial {
                    header,
                    snapshot: h.snapshot,
                    pixels: pixels.clone(),
                    ao: h.ao,
                    ambient: h.ambient,
                    held: None,
                });
            }),
        ));
    }
    let outcome = bake_loop.run(tech.as_mut(), observer)?;
    let snapshot = tech.snapshot()?;
    let control = match &mut bake_loop.control {
        Some(c) => {
            let reference = c.reference()?;
            Some(ControlHalves::of(c.indices(), &reference))
        }
        None => None,
    };
    let ao = tech.ao();
    let ambient = tech.ambient();
    let header = PartialHeader {
        stopped_by: outcome.stopped_by,
        ..template.with_halves(&snapshot, ao.is_some(), ambient.as_ref(), control, outcome.elapsed)
    };
    tracing::info!(
        task = task.index,
        tasks = task.count,
        chain = task.chain,
        first_step = task.first_step,
        steps = snapshot.even.steps + snapshot.odd.steps,
        seconds = header.seconds,
        "task baked"
    );
    Ok(Partial {
        header,
        snapshot,
        pixels,
        ao,
        ambient,
        held: None,
    })
}

impl Partial {
    pub fn encode(&self) -> Result<Vec<u8>, EngineError> {
        let header = serde_json::to_vec(&self.header)
            .map_err(|e| EngineError::Internal(format!("encoding a task's header: {e}")))?;
        let n = self.header.texels as usize;
        let mut out = Vec::with_capacity(16 + header.len() + 2 * n * 4 * 15);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend_from_slice(&header);
        for half in [&self.snapshot.even, &self.snapshot.odd] {
            let mut put = |v: &[Vec3]| {
                for x in v {
                    for c in x.to_array() {
                        out.extend_from_slice(&c.to_le_bytes());
                    }
                }
            };
            put(&half.total);
            if let Some(d) = &half.direct {
                put(d);
            }
            if let Some(m) = &half.moments {
                let flat: Vec<Vec3> = m.iter().flatten().copied().collect();
                put(&flat);
            }
        }
        for p in &self.pixels {
            out.extend_from_slice(&p.to_le_bytes());
        }
        if self.header.ao != self.ao.is_some() {
            return Err(EngineError::Internal(
                "a task's ao layer and its header disagree".into(),
            ));
        }
        for a in self.ao.iter().flatten() {
            out.extend_from_slice(&a.to_le_bytes());
        }
        let sums = self.ambient.as_ref().map(|a| [a[0].sums, a[1].sums]);
        if self.header.ambient != sums || self.ambient.iter().flatten().any(|a| a.weight.len() != n) {
            return Err(EngineError::Internal("a task's ambient and its header disagree".into()));
        }
        for half in self.ambient.iter().flatten() {
            for w in &half.weight {
                for c in w.to_array() {
                    out.extend_from_slice(&c.to_le_bytes());
                }
            }
        }
        if self.header.held != self.held.is_some() || self.held.as_ref().is_some_and(|h| h.len() != n) {
            return Err(EngineError::Internal(
                "a task's held light and its header disagree".into(),
            ));
        }
        for v in self.held.iter().flatten() {
            for c in v.to_array() {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        Ok(out)
    }

    /// Reads a partial; `what` names it in errors (a file name, a task).
    pub fn decode(bytes: &[u8], what: &str) -> Result<Partial, EngineError> {
        let bad = |m: String| EngineError::BadInput(format!("{what}: {m}"));
        let layout = PartialLayout::parse(bytes, what)?;
        let n = layout.texels();
        let want = layout.file_len() - layout.halves.start;
        let got = bytes.len() as u64 - layout.halves.start;
        if got != want {
            return Err(bad(format!(
                "{got} bytes of accumulators, {want} expected for {n} texels"
            )));
        }
        let at = |r: &Range<u64>| &bytes[r.start as usize..r.end as usize];
        let header = &layout.header;
        let mut data = at(&layout.halves);
        let mut take = |count: usize| -> Vec<Vec3> {
            let (now, rest) = data.split_at(count * 12);
            data = rest;
            vec3s(now)
        };
        let mut halves = [0usize, 1].map(|h| {
            let total = take(n);
            let direct = header.direct.then(|| take(n));
            let moments = header
                .moments
                .then(|| take(3 * n).chunks_exact(3).map(|m| [m[0], m[1], m[2]]).collect());
            HalfEstimate {
                steps: header.half_steps[h],
                total,
                direct,
                moments,
            }
        });
        let [even, odd] = std::mem::take(&mut halves);
        let ao = header
            .ao
            .then(|| words(at(&layout.ao)).map(f32::from_le_bytes).collect());
        let ambient = header.ambient.map(|sums| {
            let (even, odd) = at(&layout.ambient).split_at(12 * n);
            [(even, sums[0]), (odd, sums[1])].map(|(w, sums)| AmbientHalf { sums, weight: vec3s(w) })
        });
        let held = header.held.then(|| vec3s(at(&layout.held)));
        let pixels = words(at(&layout.pixels)).map(u32::from_le_bytes).collect();
        Ok(Partial {
            snapshot: Snapshot { even, odd },
            pixels,
            ao,
            ambient,
            held,
            header: layout.header,
        })
    }

    /// A round task's result read without its halves (`engine::rounds`: a round task
    /// needs the other regions' held light and pixels, 16 bytes a texel, not their
    /// accumulators, 24 bytes more, or 48 with the `direct` layer): `layout` from the
    /// file's start ([`PartialLayout::parse`]), `pixels` and `held` the file's bytes at
    /// `layout.pixels` and `layout.held`. The halves keep their step counts and the
    /// header's layers, with no texels in them ([`Partial::has_halves`] is false but for
    /// a region of no texels, which then reads as a whole result does); a round result
    /// has no `ao` or `ambient` layer. [`merge`] refuses such a result, and a round task
    /// refuses it as its own region's.
    pub fn decode_held(layout: PartialLayout, pixels: &[u8], held: &[u8], what: &str) -> Result<Partial, EngineError> {
        let bad = |m: String| EngineError::BadInput(format!("{what}: {m}"));
        if !layout.header.held {
            return Err(bad(
                "not a round task's result: it holds no light for the next round".into()
            ));
        }
        if layout.header.ao || layout.header.ambient.is_some() {
            return Err(bad("a round task's result has no ao or ambient layer".into()));
        }
        for (name, bytes, range) in [("pixels", pixels, &layout.pixels), ("held light", held, &layout.held)] {
            let want = range.end.saturating_sub(range.start);
            if bytes.len() as u64 != want {
                return Err(bad(format!(
                    "{} bytes of {name}, {want} expected for {} texels",
                    bytes.len(),
                    layout.texels()
                )));
            }
        }
        let header = layout.header;
        let empty = |steps: u64| HalfEstimate {
            steps,
            total: Vec::new(),
            direct: header.direct.then(Vec::new),
            moments: header.moments.then(Vec::new),
        };
        Ok(Partial {
            snapshot: Snapshot {
                even: empty(header.half_steps[0]),
                odd: empty(header.half_steps[1]),
            },
            pixels: words(pixels).map(u32::from_le_bytes).collect(),
            ao: None,
            ambient: None,
            held: Some(vec3s(held)),
            header,
        })
    }

    /// Whether the halves were read: false for a result read with
    /// [`Partial::decode_held`] (of a region with texels).
    pub fn has_halves(&self) -> bool {
        let n = self.header.texels as usize;
        self.snapshot.even.total.len() == n && self.snapshot.odd.total.len() == n
    }
}

/// Little-endian 4-byte words.
fn words(bytes: &[u8]) -> impl Iterator<Item = [u8; 4]> + '_ {
    bytes.chunks_exact(4).map(|c| c.try_into().expect("4 bytes"))
}

/// Little-endian f32 triples.
fn vec3s(bytes: &[u8]) -> Vec<Vec3> {
    bytes
        .chunks_exact(12)
        .map(|c| {
            let f = |k: usize| f32::from_le_bytes(c[4 * k..4 * k + 4].try_into().expect("4 bytes"));
            Vec3::new(f(0), f(1), f(2))
        })
        .collect()
}

/// Where the parts of a task result file lie (docs/scaling.md, "The task result file"),
/// as byte ranges of the file, from its header: what lets a reader fetch only the parts
/// it needs (a round task fetches the other regions' `pixels` and `held`, not their
/// halves: `service::farm`, and the command line's `--previous`).
#[derive(Clone, Debug)]
pub struct PartialLayout {
    pub header: PartialHeader,
    /// Both halves' layers: the even half's, then the odd half's.
    pub halves: Range<u64>,
    pub pixels: Range<u64>,
    /// Empty when the result has no `ao` layer.
    pub ao: Range<u64>,
    /// Both halves' ambient weights; empty without an ambient.
    pub ambient: Range<u64>,
    /// Empty unless the result is a round task's.
    pub held: Range<u64>,
}

impl PartialLayout {
    /// The bytes before the header: the magic and the header's length.
    pub const LEAD: usize = 16;

    /// The header's length in bytes, from the file's first [`Self::LEAD`] bytes.
    pub fn header_len(lead: &[u8], what: &str) -> Result<u64, EngineError> {
        if lead.len() < Self::LEAD || &lead[..8] != MAGIC {
            return Err(EngineError::BadInput(format!(
                "{what}: not a lightmapd task result (no LMDTASK1 magic)"
            )));
        }
        Ok(u64::from_le_bytes(lead[8..16].try_into().expect("8 bytes")))
    }

    /// The layout, from the file's first [`Self::LEAD`] + [`Self::header_len`] bytes or
    /// more (the rest is not read); refused, naming `what`, when the header is not one
    /// this lightmapd reads or its sizes overflow.
    pub fn parse(start: &[u8], what: &str) -> Result<PartialLayout, EngineError> {
        let bad = |m: String| EngineError::BadInput(format!("{what}: {m}"));
        let len = Self::header_len(start, what)?;
        let end = (Self::LEAD as u64)
            .checked_add(len)
            .filter(|&e| e <= start.len() as u64);
        let Some(end) = end else {
            return Err(bad(format!("header of {len} bytes runs past the end of the file")));
        };
        let header: PartialHeader = serde_json::from_slice(&start[Self::LEAD..end as usize])
            .map_err(|e| bad(format!("header is not valid: {e}")))?;
        if header.format != PARTIAL_FORMAT {
            return Err(bad(format!(
                "format {} (this lightmapd reads {PARTIAL_FORMAT})",
                header.format
            )));
        }
        if let Some(c) = &header.control
            && (c.even.len() != c.texels.len()
                || c.odd.len() != c.texels.len()
                || c.texels.iter().any(|&k| u64::from(k) >= header.texels))
        {
            return Err(bad("its control texels do not fit its texels".into()));
        }
        let n = header.texels;
        let per_texel = 1 + u64::from(header.direct) + 3 * u64::from(header.moments);
        let sizes = [
            n.checked_mul(2 * 12 * per_texel),
            n.checked_mul(4),
            n.checked_mul(4 * u64::from(header.ao)),
            n.checked_mul(2 * 12 * u64::from(header.ambient.is_some())),
            n.checked_mul(12 * u64::from(header.held)),
        ];
        let mut at = end;
        let mut ranges = [0, 1, 2, 3, 4].map(|_| 0..0);
        for (range, size) in ranges.iter_mut().zip(sizes) {
            let next = size
                .and_then(|s| at.checked_add(s))
                .filter(|&e| usize::try_from(e).is_ok())
                .ok_or_else(|| bad("texel count too large".into()))?;
            *range = at..next;
            at = next;
        }
        let [halves, pixels, ao, ambient, held] = ranges;
        Ok(PartialLayout {
            header,
            halves,
            pixels,
            ao,
            ambient,
            held,
        })
    }

    /// The file's length in bytes.
    pub fn file_len(&self) -> u64 {
        self.held.end
    }

    /// The texels the result holds.
    pub fn texels(&self) -> usize {
        self.header.texels as usize
    }
}

/// The halves of a bake from its tasks' halves: per half, the step-weighted mean of the
/// tasks' means (the sum of their sums over the sum of their steps), in f64.
pub fn merge_halves(parts: &[&Snapshot]) -> Snapshot {
    let n = parts.first().map_or(0, |p| p.even.total.len());
    let half = |pick: fn(&Snapshot) -> &HalfEstimate| {
        let steps: u64 = parts.iter().map(|p| pick(p).steps).sum();
        let w: Vec<f64> = parts
            .iter()
            .map(|p| pick(p).steps as f64 / steps.max(1) as f64)
            .collect();
        let mix = |layer: fn(&HalfEstimate) -> Option<&[Vec3]>, len: usize| -> Option<Vec<Vec3>> {
            let mut acc = vec![[0f64; 3]; len];
            for (p, w) in parts.iter().zip(&w) {
                let v = layer(pick(p))?;
                for (a, x) in acc.iter_mut().zip(v) {
                    for c in 0..3 {
                        a[c] += w * x[c] as f64;
                    }
                }
            }
            Some(
                acc.into_iter()
                    .map(|a| Vec3::new(a[0] as f32, a[1] as f32, a[2] as f32))
                    .collect(),
            )
        };
        HalfEstimate {
            steps,
            total: mix(|h| Some(h.total.as_slice()), n).unwrap_or_default(),
            direct: mix(|h| h.direct.as_deref(), n),
            moments: mix(|h| h.moments.as_deref().map(|m| m.as_flattened()), 3 * n)
                .map(|flat| flat.chunks_exact(3).map(|m| [m[0], m[1], m[2]]).collect()),
        }
    };
    Snapshot {
        even: half(|s| &s.even),
        odd: half(|s| &s.odd),
    }
}

/// Regions' halves side by side, in order (each region's texels a run of the whole's): a
/// half's step count is the fewest any region got, a layer is kept when every region
/// has it.
fn side_by_side(regions: Vec<Snapshot>) -> Snapshot {
    if regions.len() == 1 {
        return regions.into_iter().next().expect("one region");
    }
    let join = |pick: fn(&Snapshot) -> &HalfEstimate| -> HalfEstimate {
        let halves: Vec<&HalfEstimate> = regions.iter().map(pick).collect();
        let cat = |layer: fn(&HalfEstimate) -> Option<&[Vec3]>| -> Option<Vec<Vec3>> {
            halves
                .iter()
                .map(|h| layer(h))
                .collect::<Option<Vec<_>>>()
                .map(|parts| parts.concat())
        };
        HalfEstimate {
            steps: halves.iter().map(|h| h.steps).min().unwrap_or(0),
            total: halves.iter().flat_map(|h| h.total.iter().copied()).collect(),
            direct: cat(|h| h.direct.as_deref()),
            moments: halves
                .iter()
                .map(|h| h.moments.as_deref())
                .collect::<Option<Vec<_>>>()
                .map(|parts| parts.concat()),
        }
    };
    Snapshot {
        even: join(|s| &s.even),
        odd: join(|s| &s.odd),
    }
}

/// The merged `ao` layer (step-weighted per region, the regions side by side, as the
/// halves), when the tasks have one.
fn merge_ao(groups: &[&[&Partial]]) -> Option<Vec<f32>> {
    groups
        .iter()
        .map(|group| {
            let steps = |p: &Partial| (p.snapshot.even.steps + p.snapshot.odd.steps) as f64;
            let all: f64 = group.iter().map(|p| steps(p)).sum::<f64>().max(1.0);
            let n = group[0].ao.as_ref()?.len();
            let mut acc = vec![0f64; n];
            for p in group.iter() {
                for (a, x) in acc.iter_mut().zip(p.ao.as_ref()?) {
                    *a += steps(p) / all * f64::from(*x);
                }
            }
            Some(acc.into_iter().map(|a| a as f32).collect::<Vec<f32>>())
        })
        .collect::<Option<Vec<_>>>()
        .map(|parts| parts.concat())
}

/// The tasks with each one's scene-wide ambient (`engine::ambient`) closed over the whole
/// grid instead of its region alone, grouped as given (per region, its chains), or None
/// when the technique has none. Chain j of every region (its place among its region's
/// chains, whose seed it bakes with, [`TaskRange::seed`]) is one whole bake, so each
/// task's halves are rebased onto the sums of chain j over every region, half by half:
/// its texels then hold what a single bake of that seed holds there. A region without
/// chain j (a running merge, before that chain has halves) lends the mean of its chains'
/// sums instead. The halves are copied (the rebased lightmap is a new layer).
fn close_ambient(groups: &[&[&Partial]]) -> Option<Vec<Vec<Partial>>> {
    let all = || groups.iter().flat_map(|g| g.iter());
    if all().all(|p| p.ambient.is_none()) {
        return None;
    }
    let ranges = all().next()?.header.task.shape().ranges().max(1);
    let sums = |p: &Partial, h: usize| p.ambient.as_ref().map(|a| a[h].sums);
    let whole = |j: u32, h: usize| {
        let mut w = AmbientSums::default();
        for g in groups {
            match g
                .iter()
                .find(|q| q.header.task.index % ranges == j)
                .and_then(|q| sums(q, h))
            {
                Some(s) => w.add(&s),
                None => w.add(&AmbientSums::mean(
                    &g.iter().filter_map(|q| sums(q, h)).collect::<Vec<_>>(),
                )),
            }
        }
        w
    };
    Some(
        groups
            .iter()
            .map(|g| {
                g.iter()
                    .map(|p| {
                        let mut out = (*p).clone();
                        if let Some(own) = &p.ambient {
                            let j = p.header.task.index % ranges;
                            own[0].rebase(&whole(j, 0), &mut out.snapshot.even.total);
                            own[1].rebase(&whole(j, 1), &mut out.snapshot.odd.total);
                        }
                        out
                    })
                    .collect()
            })
            .collect(),
    )
}

/// The merged estimate of tasks grouped by region (each group its region's step ranges
/// or chains, in task order): a scene-wide ambient closed over every region's texels
/// ([`close_ambient`]), each region's halves merged by steps, the regions side by side,
/// the `ao` layer alike, and a biased technique's error assessed against the chains'
/// control references merged, as a single bake's control texels assess its snapshots.
fn merged_estimate(groups: &[&[&Partial]]) -> Result<Estimate, EngineError> {
    let closed = close_ambient(groups);
    let closed_refs: Option<Vec<Vec<&Partial>>> =
        closed.as_ref().map(|c| c.iter().map(|g| g.iter().collect()).collect());
    let groups: Vec<&[&Partial]> = match &closed_refs {
        Some(c) => c.iter().map(|g| g.as_slice()).collect(),
        None => groups.to_vec(),
    };
    let snapshot = side_by_side(
        groups
            .iter()
            .map(|g| merge_halves(&g.iter().map(|p| &p.snapshot).collect::<Vec<_>>()))
            .collect(),
    );
    let mut estimate = snapshot.estimate();
    estimate.ao = merge_ao(&groups);
    if let Some((indices, reference)) = merge_control(&groups)? {
        control::assess_against(&indices, &reference.estimate(), &mut estimate);
    }
    Ok(estimate)
}

/// The tasks' control texels as indices into the merged texels, and their references
/// merged: per region the chains' references averaged by steps (every chain of a region
/// has the same control texels, picked with the job's seed), the regions' side by side.
fn merge_control(groups: &[&[&Partial]]) -> Result<Option<(Vec<usize>, Snapshot)>, EngineError> {
    if groups.iter().flat_map(|g| g.iter()).any(|p| p.header.control.is_none()) {
        return Ok(None);
    }
    let (mut indices, mut parts, mut offset) = (Vec::new(), Vec::new(), 0usize);
    for group in groups {
        let controls: Vec<&ControlHalves> = group.iter().filter_map(|p| p.header.control.as_ref()).collect();
        if controls.iter().any(|c| c.texels != controls[0].texels) {
            return Err(EngineError::BadInput(format!(
                "merge: the chains of task {} measured their bias at other control texels than it: \
                 results of another version or a damaged one",
                group[0].header.task.index
            )));
        }
        let snaps: Vec<Snapshot> = controls.iter().map(|c| c.snapshot()).collect();
        parts.push(merge_halves(&snaps.iter().collect::<Vec<_>>()));
        indices.extend(controls[0].texels.iter().map(|&k| offset + k as usize));
        offset += group[0].header.texels as usize;
    }
    Ok(Some((indices, side_by_side(parts))))
}

/// Checks that `partials` are every task of one request, each baked on its region's
/// texels of `atlas` (when given: the whole texel set and each region's range of it),
/// and returns them in task order.
pub fn check_partials<'a>(
    partials: &'a [Partial],
    atlas: Option<(&Atlas, &[std::ops::Range<usize>])>,
) -> Result<Vec<&'a Partial>, EngineError> {
    let bad = |m: String| Err(EngineError::BadInput(m));
    let Some(first) = partials.first() else {
        return bad("merge: no task results given".into());
    };
    let h0 = &first.header;
    let tasks = if h0.task.rounds > 0 {
        // A bake in rounds is merged from its last round's tasks.
        let mut rounds = split_rounds(&h0.request, h0.task.regions, h0.task.rounds)?;
        if h0.task.round + 1 != h0.task.rounds {
            return bad(format!(
                "merge: task result 0 is of round {} of {}; a bake in rounds is merged from its last round's results",
                h0.task.round, h0.task.rounds
            ));
        }
        rounds.pop().unwrap_or_default()
    } else {
        split(&h0.request, h0.task.shape())?
    };
    let mut by_index: Vec<Option<&Partial>> = vec![None; tasks.len()];
    // Each region's fingerprint, when the atlas is given.
    let prints: Option<Vec<(String, u64)>> = atlas.map(|(a, ranges)| {
        ranges
            .iter()
            .map(|r| (texels_fingerprint(a, r.clone()), r.len() as u64))
            .collect()
    });
    if let Some(p) = &prints
        && p.len() != h0.task.regions.max(1) as usize
    {
        return bad(format!(
            "merge: the tasks are {} regions, the merge cut the grid into {}",
            h0.task.regions,
            p.len()
        ));
    }
    for (k, p) in partials.iter().enumerate() {
        let h = &p.header;
        let name = format!("task result {k} (task {}/{})", h.task.index, h.task.count);
        if h.request != h0.request || h.task.shape() != h0.task.shape() {
            return bad(format!("{name} is of another request than task result 0"));
        }
        if tasks.get(h.task.index as usize) != Some(&h.task) {
            return bad(format!(
                "{name}: its region, step range or round are not ones the request splits into"
            ));
        }
        if h.live {
            return bad(format!(
                "{name} is a running task's halves, not its result: bake the task to its end"
            ));
        }
        if h.stopped_by == StopReason::Cancelled {
            return bad(format!("{name} was cancelled; bake it again"));
        }
        if !p.has_halves() {
            return bad(format!(
                "{name} was read without its halves (a round task's view of it): read it whole to merge it"
            ));
        }
        if (h.direct, h.moments, h.ao, h.ambient.is_some(), &h.params)
            != (h0.direct, h0.moments, h0.ao, h0.ambient.is_some(), &h0.params)
        {
            return bad(format!("{name} kept other layers or parameters than task result 0"));
        }
        if h.control.is_some() != h0.control.is_some() {
            return bad(format!(
                "{name} measured its bias at control texels and task result 0 did not, or the other way round"
            ));
        }
        if let Some((f, texels)) = prints.as_ref().map(|p| &p[h.task.region as usize])
            && (h.fingerprint != *f || h.texels != *texels)
        {
            return bad(format!(
                "{name} was baked on another texel set (fingerprint {}…, this scene's {}…): another scene or version",
                &h.fingerprint[..12.min(h.fingerprint.len())],
                &f[..12]
            ));
        }
        let slot = &mut by_index[h.task.index as usize];
        if slot.is_some() {
            return bad(format!("{name}: task {} is given twice", h.task.index));
        }
        *slot = Some(p);
    }
    let missing: Vec<String> = by_index
        .iter()
        .enumerate()
        .filter(|(_, p)| p.is_none())
        .map(|(i, _)| i.to_string())
        .collect();
    if !missing.is_empty() {
        return bad(format!(
            "merge: tasks {} of {} are missing",
            missing.join(", "),
            tasks.len()
        ));
    }
    Ok(by_index.into_iter().flatten().collect())
}

/// The job's result from all its tasks: the merged halves, then what a single bake
/// delivers (denoised lightmap, EXR, preview, summary, probes). The summary's `seconds`
/// is the tasks' bake time added up (machine time, not wall time).
pub fn merge(
    scene: Arc<Scene>,
    partials: &[Partial],
    options: &BakeOptions,
    on_plan: &mut dyn FnMut(&Plan),
) -> Result<BakeResult, EngineError> {
    let first = partials
        .first()
        .ok_or_else(|| EngineError::BadInput("merge: no task results given".into()))?;
    let request = first.header.request.clone();
    // The tasks' texels, region by region: what their validation kept, which the merge
    // takes instead of tracing the whole grid's validation again.
    let unchecked = check_partials(partials, None)?;
    let ranges = first.header.task.shape().ranges().max(1) as usize;
    let by_region: Vec<&Partial> = unchecked.chunks(ranges).map(|group| group[0]).collect();
    let (prepared, texel_ranges) = prepare_whole(scene, &request, options, &by_region, on_plan)?;
    let ordered = check_partials(partials, Some((&prepared.atlas, &texel_ranges)))?;
    let groups: Vec<&[&Partial]> = ordered.chunks(ranges).collect();
    let estimate = merged_estimate(&groups)?;
    if let Some((layer, k, v)) = estimate.first_non_finite() {
        return Err(EngineError::Internal(format!(
            "merged tasks hold a non-finite value {v:?} at texel {k} of the {layer} layer; the lightmap was not written"
        )));
    }
    let seconds: f64 = ordered.iter().map(|p| p.header.seconds).sum();
    let stopped_by = ordered
        .iter()
        .map(|p| p.header.stopped_by)
        .find(|r| *r != StopReason::Steps)
        .unwrap_or(StopReason::Steps);
    let params = first.header.params.clone();
    prepared.deliver(
        &request,
        &estimate,
        &params,
        Duration::from_secs_f64(seconds),
        stopped_by,
        // Nobody watches a merge: its probes (if any) run to the end.
        &mut |_: crate::engine::bake::BakeEvent<'_>| std::ops::ControlFlow::Continue(()),
    )
}

/// The whole texel set of a split bake from one task's partial of each region, in
/// region order: the grid prepared as the single bake's (`job::prepare_regions`), taking
/// the texels the tasks' validation kept instead of tracing it again, and each region's
/// range of its texels.
fn prepare_whole(
    scene: Arc<Scene>,
    request: &BakeRequest,
    options: &BakeOptions,
    by_region: &[&Partial],
    on_plan: &mut dyn FnMut(&Plan),
) -> Result<(job::Prepared, Vec<std::ops::Range<usize>>), EngineError> {
    let kept: Vec<u32> = by_region.iter().flat_map(|p| p.pixels.iter().copied()).collect();
    if kept.windows(2).any(|w| w[0] >= w[1]) {
        return Err(EngineError::BadInput(
            "merge: the task results' texels are not in pixel order: a damaged or foreign result".into(),
        ));
    }
    let regions = job::RegionsOf {
        count: by_region.len().max(1) as u32,
        keep: None,
        validated: Some(&kept),
        trace: None,
    };
    let prepared = job::prepare_regions(scene, request, options, Some(regions), &mut |_| {}, on_plan)?;
    // Each region's texels in the validated whole (one region: all of them).
    let texel_ranges = prepared
        .region_pixels
        .iter()
        .map(|p| prepared.atlas.texels_in(p.clone()))
        .collect();
    Ok((prepared, texel_ranges))
}

/// The whole grid's texel set, for the running snapshots of a bake split into regions
/// ([`merge_running`]): from `parts`, at least one partial of every region (a task of a
/// region holds its own texels alone). It costs what the merge's preparation costs (the
/// whole texel set and the scene's BVH), and is refused, as a bake is, when it needs
/// more than `options.max_memory_bytes`.
pub fn running_atlas(
    scene: Arc<Scene>,
    parts: &[Partial],
    options: &BakeOptions,
) -> Result<(Arc<Atlas>, Vec<std::ops::Range<usize>>), EngineError> {
    let first = parts
        .first()
        .ok_or_else(|| EngineError::BadInput("running merge: no task halves given".into()))?;
    let count = first.header.task.regions.max(1);
    let by_region = (0..count)
        .map(|r| {
            parts
                .iter()
                .find(|p| p.header.task.region == r)
                .ok_or_else(|| EngineError::BadInput(format!("running merge: region {r} has no halves yet")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let (prepared, ranges) = prepare_whole(scene, &first.header.request, options, &by_region, &mut |_| {})?;
    Ok((prepared.atlas, ranges))
}

/// A running split bake's estimate from what its tasks have baked so far: the halves of
/// every task given (a running task's so far, from [`bake_task_live`], or a finished
/// one's result) merged as the final merge merges them, then assessed at the control
/// texels. These are the job's snapshots while its tasks run (issue 25 point 2).
/// `atlas` is the whole grid's texel set and `regions` each region's range of its
/// texels: with one region, the task's own atlas and all of it; with several,
/// [`running_atlas`]'s.
///
/// Why it means what a single bake's snapshot means: `path`'s step ranges draw the
/// single bake's samples at their steps, so the merged halves are a single bake's over
/// the steps done (a set of steps, not the first ones in order when a later range has
/// run ahead: the same expectation); chains are independent draws, so their running
/// means merge by steps as their results do; regions are disjoint texels side by side,
/// each at the steps its tasks have done (a half's step count is the fewest any region
/// has, as in the final merge). A task with nothing yet is left out (fewer steps or
/// chains, the same expectation), and the halves' difference still measures the merged
/// noise; a region with nothing yet is refused, naming it.
pub fn merge_running(
    atlas: &Atlas,
    regions: &[std::ops::Range<usize>],
    parts: &[Partial],
) -> Result<Estimate, EngineError> {
    let bad = |m: String| Err(EngineError::BadInput(m));
    let Some(first) = parts.first() else {
        return bad("running merge: no task halves given".into());
    };
    let h0 = &first.header;
    if regions.len() != h0.task.regions.max(1) as usize {
        return bad(format!(
            "running merge: the job is split into {} regions, the texel set given into {}",
            h0.task.regions,
            regions.len()
        ));
    }
    let prints: Vec<String> = regions.iter().map(|r| texels_fingerprint(atlas, r.clone())).collect();
    let mut seen = vec![false; h0.task.count as usize];
    let mut groups: Vec<Vec<&Partial>> = vec![Vec::new(); regions.len()];
    for p in parts {
        let h = &p.header;
        let name = format!("task {}/{}", h.task.index, h.task.count);
        if h.request != h0.request || h.task.shape() != h0.task.shape() {
            return bad(format!(
                "running merge: {name} is of another request than task {}",
                h0.task.index
            ));
        }
        if (h.direct, h.moments, h.ao, h.ambient.is_some(), &h.params)
            != (h0.direct, h0.moments, h0.ao, h0.ambient.is_some(), &h0.params)
        {
            return bad(format!(
                "running merge: {name} kept other layers or parameters than task {}",
                h0.task.index
            ));
        }
        let r = h.task.region as usize;
        if regions
            .get(r)
            .is_none_or(|range| h.fingerprint != prints[r] || h.texels != range.len() as u64)
        {
            return bad(format!("running merge: {name} was baked on another texel set"));
        }
        if h.stopped_by == StopReason::Cancelled {
            return bad(format!("running merge: {name} was cancelled"));
        }
        match seen.get_mut(h.task.index as usize) {
            Some(s) if !*s => *s = true,
            _ => {
                return bad(format!(
                    "running merge: {name} is given twice or is not one of the job's"
                ));
            }
        }
        groups[r].push(p);
    }
    if let Some(r) = groups.iter().position(|g| g.is_empty()) {
        return bad(format!("running merge: region {r} has no halves yet"));
    }
    let groups: Vec<&[&Partial]> = groups.iter().map(|g| g.as_slice()).collect();
    let estimate = merged_estimate(&groups)?;
    if let Some((layer, k, v)) = estimate.first_non_finite() {
        return Err(EngineError::Internal(format!(
            "running merge: the tasks' halves hold a non-finite value {v:?} at texel {k} of the {layer} layer"
        )));
    }
    Ok(estimate)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(technique: &str, steps: Option<u64>) -> BakeRequest {
        BakeRequest {
            technique: technique.into(),
            stop: StopCriteria {
                steps,
                seconds: None,
                target_error: None,
            },
            ..BakeRequest::default()
        }
    }

    #[test]
    fn ranges_cover_the_steps_once_and_start_even() {
        for (total, count) in [(64u64, 3u32), (7, 3), (6, 3), (101, 10), (2048, 1024)] {
            let t = split(&request("path", Some(total)), TaskShape::steps(count)).unwrap();
            assert_eq!(t.len(), count as usize);
            let mut next = 0;
            for (i, r) in t.iter().enumerate() {
                assert_eq!((r.index, r.count, r.first_step), (i as u32, count, next));
                assert_eq!(r.first_step % 2, 0, "{r:?}");
                assert!(r.steps >= 2, "{r:?}");
                next += r.steps;
            }
            assert_eq!(next, total);
            let (lo, hi) = (
                t.iter().map(|r| r.steps).min().unwrap(),
                t.iter().map(|r| r.steps).max().unwrap(),
            );
            assert!(hi - lo <= 3, "uneven {total}/{count}: {lo}..{hi}");
        }
    }

    #[test]
    fn what_cannot_be_split_is_refused_naming_why() {
        let err = |r: &BakeRequest, n| split(r, TaskShape::steps(n)).unwrap_err().to_string();
        assert!(err(&request("sdb", None), 2).contains("needs stop.steps"));
        assert!(err(&request("sdb", Some(5)), 3).contains("at least twice the chains (3)"));
        assert!(err(&request("path", None), 2).contains("needs stop.steps"));
        assert!(err(&request("path", Some(3)), 2).contains("at least twice the step ranges per region (2)"));
        assert!(err(&request("path", Some(64)), 0).contains("tasks must be in 1..=1024"));
        let mut r = request("path", Some(64));
        r.stop.target_error = Some(0.01);
        assert!(err(&r, 2).contains("stop.target_error"));
        let mut r = request("path", Some(64));
        r.outputs = vec![OutputLayer::Shadowmask];
        assert!(err(&r, 2).contains("shadowmask"));
        // One task is the whole bake, for every technique.
        assert_eq!(
            split(&request("sdb", Some(64)), TaskShape::steps(1)).unwrap()[0].steps,
            64
        );
        let shaped = |tasks, regions| {
            split(&request("path", Some(64)), TaskShape { tasks, regions })
                .unwrap_err()
                .to_string()
        };
        assert!(shaped(6, 4).contains("regions must divide tasks"), "{}", shaped(6, 4));
        assert!(shaped(2, 0).contains("regions must divide tasks"));
        assert!(shaped(2, 3).contains("regions must divide tasks"));
        // Regions do not ease the two-steps-a-range rule, nor lift the technique's.
        let few = split(&request("path", Some(5)), TaskShape { tasks: 6, regions: 2 })
            .unwrap_err()
            .to_string();
        assert!(few.contains("step ranges per region (3)"), "{few}");
        // A chain technique has no regions, and says why.
        let sdb = split(&request("sdb", Some(64)), TaskShape { tasks: 2, regions: 2 })
            .unwrap_err()
            .to_string();
        assert!(
            sdb.starts_with("regions: sdb bakes are split into independent chains of the whole grid")
                && sdb.contains("a region's light depends on every other region's"),
            "{sdb}"
        );
    }

    /// Chains: every technique but path; each bakes from step 0 over the whole grid, the
    /// job's steps dealt out evenly, each with its own seed (chain 0 the job's).
    #[test]
    fn chains_share_the_steps_and_have_their_own_seeds() {
        for tech in ["vpl", "sdf", "obscurance", "sdb", "hemicube"] {
            let t = split(&request(tech, Some(11)), TaskShape::steps(3)).unwrap();
            let got: Vec<(u32, u32, u64, u64, bool)> = t
                .iter()
                .map(|r| (r.index, r.region, r.first_step, r.steps, r.chain))
                .collect();
            assert_eq!(
                got,
                vec![(0, 0, 0, 4, true), (1, 0, 0, 4, true), (2, 0, 0, 3, true)],
                "{tech}"
            );
        }
        assert!(
            split(&request("path", Some(11)), TaskShape::steps(3))
                .unwrap()
                .iter()
                .all(|r| !r.chain)
        );
        // vpl's chains within regions: each region's first chain has the job's seed.
        let t = split(&request("vpl", Some(9)), TaskShape { tasks: 4, regions: 2 }).unwrap();
        let got: Vec<(u32, u64, u64)> = t.iter().map(|r| (r.region, r.steps, r.seed(7))).collect();
        let other = chain_seed(7, 1);
        assert_eq!(got, vec![(0, 5, 7), (0, 4, other), (1, 5, 7), (1, 4, other)]);
        let few = split(&request("vpl", Some(3)), TaskShape { tasks: 4, regions: 2 }).unwrap_err();
        assert!(
            few.to_string().contains("at least twice the chains per region (2)"),
            "{few}"
        );
        let seeds: Vec<u64> = (0..64).map(|k| chain_seed(7, k)).collect();
        assert_eq!(seeds[0], 7);
        let mut unique = seeds.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), seeds.len());
    }

    /// Task k is region k / ranges over range k % ranges; every region gets every range.
    #[test]
    fn regions_times_ranges_number_region_major() {
        let t = split(&request("path", Some(9)), TaskShape { tasks: 6, regions: 3 }).unwrap();
        let got: Vec<(u32, u64, u64)> = t.iter().map(|r| (r.region, r.first_step, r.steps)).collect();
        assert_eq!(
            got,
            vec![(0, 0, 4), (0, 4, 5), (1, 0, 4), (1, 4, 5), (2, 0, 4), (2, 4, 5)]
        );
        assert!(
            t.iter()
                .enumerate()
                .all(|(k, r)| r.index == k as u32 && r.regions == 3 && r.count == 6)
        );
        // Regions alone: every task bakes every step of its region.
        let r = split(&request("path", Some(7)), TaskShape { tasks: 4, regions: 4 }).unwrap();
        assert!(r.iter().all(|x| (x.first_step, x.steps) == (0, 7)), "{r:?}");
    }

    fn half(steps: u64, v: f32, n: usize) -> HalfEstimate {
        HalfEstimate {
            steps,
            total: vec![Vec3::splat(v); n],
            direct: Some(vec![Vec3::splat(v / 2.0); n]),
            moments: Some(vec![[Vec3::splat(v), Vec3::ZERO, Vec3::splat(-v)]; n]),
        }
    }

    /// Merged means are the step-weighted means: (3·1 + 1·5) / 4 = 2.
    #[test]
    fn halves_merge_by_their_step_counts() {
        let a = Snapshot {
            even: half(3, 1.0, 2),
            odd: half(2, 4.0, 2),
        };
        let b = Snapshot {
            even: half(1, 5.0, 2),
            odd: half(2, 2.0, 2),
        };
        let m = merge_halves(&[&a, &b]);
        assert_eq!((m.even.steps, m.odd.steps), (4, 4));
        assert_eq!(m.even.total[1], Vec3::splat(2.0));
        assert_eq!(m.odd.total[0], Vec3::splat(3.0));
        assert_eq!(m.even.direct.as_ref().unwrap()[0], Vec3::splat(1.0));
        assert_eq!(m.odd.moments.as_ref().unwrap()[1][2], Vec3::splat(-3.0));
    }

    /// A round result read in parts (`PartialLayout`, `decode_held`): the ranges follow the
    /// kept layers (120 bytes a texel of halves with `direct` and `moments`), the pixels and
    /// the held light lie side by side, and what is read apart is what `decode` reads.
    #[test]
    fn a_round_result_is_read_in_parts() {
        let request = request("hemicube", Some(8));
        let task = split_rounds(&request, 2, 2).unwrap()[1][1];
        let header = PartialHeader {
            format: PARTIAL_FORMAT,
            request,
            task,
            params: serde_json::json!({}),
            width: 4,
            height: 4,
            texels: 3,
            fingerprint: "cd".repeat(32),
            half_steps: [3, 3],
            direct: true,
            moments: true,
            ao: false,
            ambient: None,
            control: None,
            seconds: 0.25,
            stopped_by: StopReason::Steps,
            live: false,
            held: true,
        };
        let p = Partial {
            header,
            snapshot: Snapshot {
                even: half(3, 1.5, 3),
                odd: half(3, 0.5, 3),
            },
            pixels: vec![2, 7, 11],
            ao: None,
            ambient: None,
            held: Some(vec![Vec3::ONE, Vec3::new(0.5, 0.25, 0.0), Vec3::splat(2.0)]),
        };
        let bytes = p.encode().unwrap();
        let layout = PartialLayout::parse(&bytes, "r").unwrap();
        assert_eq!(layout.file_len(), bytes.len() as u64);
        assert_eq!(layout.halves.end - layout.halves.start, 3 * 120);
        assert_eq!(
            (layout.pixels.start, layout.pixels.end),
            (layout.halves.end, layout.halves.end + 12)
        );
        assert!(layout.ao.is_empty() && layout.ambient.is_empty());
        assert_eq!(
            (layout.held.start, layout.held.end),
            (layout.pixels.end, layout.pixels.end + 36)
        );
        let at = |r: &Range<u64>| &bytes[r.start as usize..r.end as usize];
        let held = Partial::decode_held(layout.clone(), at(&layout.pixels), at(&layout.held), "r").unwrap();
        assert_eq!(
            (held.pixels.clone(), held.held.clone()),
            (p.pixels.clone(), p.held.clone())
        );
        assert_eq!(held.header, p.header);
        assert!(!held.has_halves() && p.has_halves());
        // The halves' steps and layers as the header says, with no texels in them.
        assert_eq!((held.snapshot.even.steps, held.snapshot.odd.steps), (3, 3));
        assert_eq!(held.snapshot.even.direct, Some(vec![]));
        assert_eq!(held.snapshot.odd.moments, Some(vec![]));
        // The header alone is enough for the layout; a result that is not a round's, or
        // has an `ao` layer, is not read in parts.
        let lead = PartialLayout::LEAD;
        let len = PartialLayout::header_len(&bytes[..lead], "r").unwrap() as usize;
        assert_eq!(
            PartialLayout::parse(&bytes[..lead + len], "r").unwrap().held,
            layout.held
        );
        let short = PartialLayout::parse(&bytes[..lead + len - 1], "r")
            .unwrap_err()
            .to_string();
        assert!(short.contains("runs past the end"), "{short}");
        let mut other = layout.clone();
        other.header.held = false;
        let e = Partial::decode_held(other, &[], &[], "r").unwrap_err().to_string();
        assert!(e.contains("not a round task's result"), "{e}");
        let mut with_ao = layout;
        with_ao.header.ao = true;
        let e = Partial::decode_held(with_ao, &[], &[], "r").unwrap_err().to_string();
        assert!(e.contains("no ao or ambient layer"), "{e}");
    }

    #[test]
    fn a_partial_survives_its_file_and_a_damaged_one_is_refused() {
        let header = PartialHeader {
            format: PARTIAL_FORMAT,
            request: request("path", Some(8)),
            task: split(&request("path", Some(8)), TaskShape { tasks: 4, regions: 2 }).unwrap()[3],
            params: serde_json::json!({"samples_per_step": 4}),
            width: 4,
            height: 4,
            texels: 3,
            fingerprint: "ab".repeat(32),
            half_steps: [2, 2],
            direct: true,
            moments: true,
            ao: true,
            ambient: None,
            control: Some(ControlHalves {
                texels: vec![0, 2],
                half_steps: [3, 4],
                even: vec![[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]],
                odd: vec![[1.5, 2.5, 3.5], [0.25, 0.5, 0.75]],
            }),
            seconds: 0.5,
            stopped_by: StopReason::Steps,
            live: false,
            held: false,
        };
        let p = Partial {
            header,
            snapshot: Snapshot {
                even: half(2, 1.5, 3),
                odd: half(2, 0.25, 3),
            },
            pixels: vec![1, 5, 9],
            ao: Some(vec![0.25, 0.5, 1.0]),
            ambient: None,
            held: None,
        };
        // With a scene-wide ambient: sums in the header, weights after the ao layer.
        let mut p = p;
        let sums = |x: f64| AmbientSums {
            area: 2.0,
            albedo: [x, 0.5, 0.25],
            source: [0.1, x, 0.3],
            hit: 1.5,
        };
        p.ambient = Some([
            AmbientHalf {
                sums: sums(1.0),
                weight: vec![Vec3::splat(0.5), Vec3::new(0.1, 0.2, 0.3), Vec3::ZERO],
            },
            AmbientHalf {
                sums: sums(0.75),
                weight: vec![Vec3::ONE, Vec3::splat(0.25), Vec3::new(1.0, 0.0, 0.5)],
            },
        ]);
        p.header.ambient = Some([sums(1.0), sums(0.75)]);
        let bytes = p.encode().unwrap();
        assert_eq!(Partial::decode(&bytes, "t").unwrap().ambient, p.ambient);
        let mut disagree = p.clone();
        disagree.header.ambient = None;
        assert!(
            disagree
                .encode()
                .unwrap_err()
                .to_string()
                .contains("ambient and its header disagree")
        );
        let back = Partial::decode(&bytes, "t").unwrap();
        assert_eq!(back.pixels, p.pixels);
        assert_eq!(back.ao, p.ao);
        assert_eq!(back.header, p.header);
        assert_eq!(back.snapshot.odd.moments, p.snapshot.odd.moments);
        assert_eq!(back.snapshot.even.direct, p.snapshot.even.direct);
        let short = Partial::decode(&bytes[..bytes.len() - 4], "t.lmtask")
            .unwrap_err()
            .to_string();
        assert!(
            short.contains("t.lmtask:") && short.contains("expected for 3 texels"),
            "{short}"
        );
        // A round task's held light (engine::rounds) follows the ambient weights.
        let mut round = p.clone();
        round.held = Some(vec![Vec3::new(0.5, 0.25, 0.125), Vec3::ONE, Vec3::new(2.0, 0.0, 1.0)]);
        round.header.held = true;
        let back = Partial::decode(&round.encode().unwrap(), "t").unwrap();
        assert_eq!(back.held, round.held);
        assert_eq!(back.ambient, round.ambient);
        assert_eq!(back.header, round.header);
        round.header.held = false;
        assert!(
            round
                .encode()
                .unwrap_err()
                .to_string()
                .contains("held light and its header disagree")
        );
        let junk = Partial::decode(b"not a task result", "x").unwrap_err().to_string();
        assert!(junk.contains("no LMDTASK1 magic"), "{junk}");
        // A control texel past the task's texels.
        let mut bad = p.clone();
        bad.header.control.as_mut().unwrap().texels[1] = 3;
        let err = Partial::decode(&bad.encode().unwrap(), "c").unwrap_err().to_string();
        assert!(err.contains("control texels do not fit"), "{err}");
    }

    /// The chains' controls merge by their steps; the ao layer too, and regions side by side.
    #[test]
    fn controls_and_ao_merge_by_steps() {
        let part = |steps: u64, v: f32, region: u32| {
            let c = ControlHalves {
                texels: vec![1],
                half_steps: [steps, steps],
                even: vec![[v; 3]],
                odd: vec![[2.0 * v; 3]],
            };
            let mut task = split(&request("sdb", Some(8)), TaskShape::steps(2)).unwrap()[0];
            task.region = region;
            Partial {
                header: PartialHeader {
                    format: PARTIAL_FORMAT,
                    request: request("sdb", Some(8)),
                    task,
                    params: Value::Null,
                    width: 2,
                    height: 2,
                    texels: 2,
                    fingerprint: String::new(),
                    half_steps: [steps, steps],
                    direct: false,
                    moments: false,
                    ao: true,
                    ambient: None,
                    control: Some(c),
                    seconds: 0.0,
                    stopped_by: StopReason::Steps,
                    live: false,
                    held: false,
                },
                snapshot: Snapshot {
                    even: half(steps, v, 2),
                    odd: half(steps, v, 2),
                },
                pixels: vec![0, 1],
                ao: Some(vec![v, 0.0]),
                ambient: None,
                held: None,
            }
        };
        let (a, b) = (part(3, 1.0, 0), part(1, 5.0, 0));
        let (texels, reference) = merge_control(&[&[&a, &b]]).unwrap().unwrap();
        assert_eq!(texels, vec![1]);
        assert_eq!((reference.even.steps, reference.odd.steps), (4, 4));
        assert_eq!(reference.even.total[0], Vec3::splat(2.0));
        assert_eq!(reference.odd.total[0], Vec3::splat(4.0));
        assert_eq!(merge_ao(&[&[&a, &b]]), Some(vec![2.0, 0.0]));
        // Two regions of one task each: the second region's control texel is offset by
        // the first region's texels.
        let (texels, reference) = merge_control(&[&[&a], &[&b]]).unwrap().unwrap();
        assert_eq!(texels, vec![1, 3]);
        assert_eq!(reference.even.total, vec![Vec3::splat(1.0), Vec3::splat(5.0)]);
        assert_eq!(reference.even.steps, 1);
        assert_eq!(merge_ao(&[&[&a], &[&b]]), Some(vec![1.0, 0.0, 5.0, 0.0]));
        // Chains that picked other control texels are refused.
        let mut c = part(1, 5.0, 0);
        c.header.control.as_mut().unwrap().texels = vec![0];
        let err = merge_control(&[&[&a, &c]]).unwrap_err().to_string();
        assert!(err.contains("other control texels"), "{err}");
    }

    /// The merge closes a scene-wide ambient per chain over every region: chain j of
    /// region 0 is rebased onto the sums of chain j of both regions, and a region without
    /// chain j (a running merge) lends its chains' mean.
    #[test]
    fn an_ambient_is_closed_per_chain_over_the_regions() {
        let req = request("sdf", Some(8));
        let shape = TaskShape { tasks: 4, regions: 2 };
        let tasks = split(&req, shape).unwrap();
        let sums = |source: f64| AmbientSums {
            area: 1.0,
            albedo: [0.5; 3],
            source: [source; 3],
            hit: 1.0,
        };
        let part = |k: usize, source: f64| {
            let t = tasks[k];
            let b = sums(source).closure();
            let ambient = AmbientHalf {
                sums: sums(source),
                weight: vec![Vec3::ONE],
            };
            let mut snapshot = Snapshot {
                even: half(2, 0.0, 1),
                odd: half(2, 0.0, 1),
            };
            for v in snapshot.even.total.iter_mut().chain(snapshot.odd.total.iter_mut()) {
                *v += b;
            }
            Partial {
                header: PartialHeader {
                    format: PARTIAL_FORMAT,
                    request: req.clone(),
                    task: t,
                    params: Value::Null,
                    width: 2,
                    height: 2,
                    texels: 1,
                    fingerprint: String::new(),
                    half_steps: [2, 2],
                    direct: false,
                    moments: false,
                    ao: false,
                    ambient: Some([sums(source), sums(source)]),
                    control: None,
                    seconds: 0.0,
                    stopped_by: StopReason::Steps,
                    live: false,
                    held: false,
                },
                snapshot,
                pixels: vec![0],
                ao: None,
                ambient: Some([ambient.clone(), ambient]),
                held: None,
            }
        };
        // Region 0: chains 0 and 1 (tasks 0, 1); region 1: tasks 2, 3.
        let (a0, a1, b0, b1) = (part(0, 0.1), part(1, 0.3), part(2, 0.5), part(3, 0.9));
        let closed = close_ambient(&[&[&a0, &a1], &[&b0, &b1]]).unwrap();
        // B over two texels of area 1 and albedo 0.5, every direction a hit: the mean
        // source over 1 - 0.5.
        let want = |s0: f64, s1: f64| ((s0 + s1) / 2.0 / 0.5) as f32;
        let got = |p: &Partial| p.snapshot.even.total[0].x;
        assert!((got(&closed[0][0]) - want(0.1, 0.5)).abs() < 1e-6);
        assert!((got(&closed[1][0]) - want(0.1, 0.5)).abs() < 1e-6);
        assert!((got(&closed[0][1]) - want(0.3, 0.9)).abs() < 1e-6);
        assert!((got(&closed[1][1]) - want(0.3, 0.9)).abs() < 1e-6);
        // Region 1 without chain 1 yet: it lends its one chain's sums.
        let closed = close_ambient(&[&[&a0, &a1], &[&b0]]).unwrap();
        assert!((got(&closed[0][1]) - want(0.3, 0.5)).abs() < 1e-6);
        let mut none = a0.clone();
        none.ambient = None;
        none.header.ambient = None;
        assert!(close_ambient(&[&[&none]]).is_none());
    }
}
