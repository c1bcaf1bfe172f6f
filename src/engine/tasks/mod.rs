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
//!   merge closes over every region (`merge::close_ambient`): chain j of every region is one
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
//!
//! Here: the split ([`split`], [`split_rounds`]) and a task's bake ([`bake_task`]);
//! `partial`, a task's result and its file; `merge`, the merges.

mod merge;
mod partial;
#[cfg(test)]
mod tests;

pub use merge::{check_partials, merge, merge_halves, merge_running, running_atlas};
pub use partial::{ControlHalves, PARTIAL_FORMAT, Partial, PartialHeader, PartialLayout};

use std::sync::Arc;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::engine::atlas::Atlas;
use crate::engine::bake::{BakeObserver, LiveHalves, LiveHook, StopCriteria, StopReason};
use crate::engine::job::{self, BakeOptions, BakeRequest};
use crate::engine::output::OutputLayer;
use crate::engine::plan::Plan;
use crate::engine::scene::Scene;
use crate::engine::technique::api::TaskSplit;
use crate::engine::technique::{self, BakeInputs, EngineError};

/// At most this many tasks per bake.
pub const MAX_TASKS: u32 = 1024;

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
