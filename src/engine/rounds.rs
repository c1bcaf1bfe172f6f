//! A bake in rounds: a technique whose every step reads the whole grid's light baked one
//! region (page or band of rows) at a time, the regions exchanging their light between
//! rounds (issue 25 point 1; docs/scaling.md, "Pages in rounds").
//!
//! # Why
//! `hemicube` draws its shooters from every texel's irradiance of the step before, and
//! `sdb`'s resolve turns every lightmap pixel's running estimate into the radiance its
//! illumination maps show, so no region of their grids stands alone, and their split
//! bakes were independent chains of the whole grid: every worker holds the whole level. Rounds bound what a region's bake
//! gathers to its own texels, which is what lets pages of a large level go to different
//! workers.
//!
//! # How: block Jacobi over the regions
//! The radiosity system B = E + K B, with K cut into region blocks. A bake in rounds is
//! R rounds of P tasks (`tasks::split_rounds`), task p of round r baking region p
//! ([`bake_round_task`]): its texels receive light ([`Boundary`]); every other texel sends
//! the light round r - 1 estimated for it (held fixed all round; zero in round 0, so the
//! first round is each region lit by the emitters, the sky and its own bounces); its
//! texels start from that estimate and their accumulators go on from the region's halves
//! after round r - 1. A task reads every region's result of round r - 1: its own region's
//! whole (the halves it resumes), the others' pixels and held light alone (16 bytes a
//! texel of a result's 40, or 64 with the `direct` layer: `tasks::PartialLayout`,
//! `Partial::decode_held`; the queue's workers fetch those parts with ranged reads, the
//! command line seeks to them), and writes its own (`tasks::Partial` with `held`): its
//! halves and the estimate made by its round's own steps, which is the next round's held
//! light (the running mean would still carry the earlier rounds' lag). All regions of a round read the same held light
//! (Jacobi, not Gauss-Seidel), so a round's tasks may bake at once, on separate machines;
//! the last round's results merge as a split bake's regions do (`tasks::merge`, their
//! texels side by side). [`bake_in_rounds`] runs every task in this process, one after
//! another, through the same functions, so its lightmap is the processes' lightmap.
//!
//! The held light's error shrinks each round by the part of the light that crosses
//! regions: about ρ f / (1 - ρ (1 - f)) for albedo ρ and a share f of a region's light that
//! comes from other regions (1/3 for half a closed box at ρ = 0.5). What the early rounds
//! leave in the accumulators is a transient of the same kind as a single bake's first
//! bounces; the rounds' doubling step shares (`tasks::round_steps`) and the ramp weights
//! (step i of a half weighs i^ramp) keep its share small. Neither is noise, so the
//! halves' difference cannot see it; the control texels do: the last round's task of each
//! region picks them from its texels with the job's seed and traces them by `path` for a
//! fifth of its time, and the merge assesses the merged lightmap against the regions'
//! references joined (`control::assess_against`), so the error reported states what the
//! rounds left as well as the noise.
//!
//! Every region's bake uses the job's seed: its shooters and emitter samples are then the
//! ones a single bake would draw at that step (given the same light), and its CPU rays
//! are keyed by the texel's pixel.
//!
//! # Limits
//! - `hemicube` and `sdb` hold a boundary (`Technique::hold_boundary`; `sdb` in its
//!   `average` mode only). Their per-texel passes run over the receivers, but what
//!   renders the whole scene (`hemicube`'s hemicubes, `sdb`'s illumination maps) every
//!   region's task renders again, so P regions cost P times that share of a step; the
//!   other techniques split into regions without rounds or not at all (docs/scaling.md,
//!   "What a task is, per technique").
//! - The service's queue bakes rounds (`JobSpec::rounds`: round r's tasks queued once
//!   round r - 1's have succeeded, in both backends, `service::farm`), as does the command
//!   line (`bake --rounds R --regions P --task K/P --round r --previous ...`, then
//!   `merge`), and any render-farm manager that runs it.
//! - Every task prepares the whole grid (texel set, the technique's per-texel buffers:
//!   the held light must be readable at every texel), so a region's task bounds the work
//!   of its gather, not its memory; its hemicubes render the whole scene.
//! - Validation is traced in round 0 only, each task over its own region (so the round
//!   traces the grid once, not once a task); later rounds take the texels the round
//!   before kept, as the merge does. In round 0 the other regions' texels are untested,
//!   and where some lie inside geometry the round bakes a little differently from one on
//!   the validated grid: `sdb`'s ambient gain is measured over a set that includes them
//!   (their rays meet back faces: a lower gain, a smaller correction), its maps read
//!   their pixels as held light (zero) where a dropped texel's pixel is filled from a
//!   neighbour, and `hemicube`'s receivers next to them do not take over their surface
//!   (smaller cells; `atlas::cells`) nor do merged shooters (`shooter_level` above 0)
//!   leave them out. All of it is round 0's, the iteration's starting point, whose held
//!   light (zero) is far from the answer anyway: the rounds after start from its estimate
//!   as from any other, and the control texels state what is left (measured in
//!   docs/scaling.md, "Round 0 validates its own region"). In one process
//!   ([`bake_in_rounds`]) round 0 builds the grid's texel set once a region, as its tasks
//!   do on their machines, so that its lightmap is theirs; validation is still traced
//!   once in all, and generated lightmap UVs are generated once for every task and the
//!   merge (the same UVs each task's machine generates).
//! - The held light of a glossy texel outside the receivers has no incoming direction:
//!   its lobe reflects light arriving along its normal (`hemicube`'s select pass falls
//!   back to it), a bias the control texels state like any other.
//! - Step count: `stop.steps` is every region's, dealt out over the rounds
//!   (`tasks::round_steps`); `stop.seconds` and `stop.target_error` are refused, as rules
//!   about the whole bake that no round sees alone; a cancelled bake in rounds delivers
//!   nothing.

use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;

use crate::engine::accumulate::{HalfEstimate, LUMINANCE, Snapshot};
use crate::engine::atlas::Atlas;
use crate::engine::bake::{BakeEvent, BakeObserver, StopReason};
use crate::engine::control::ControlTexels;
use crate::engine::job::{self, BakeOptions, BakeRequest, BakeResult};
use crate::engine::scene::Scene;
use crate::engine::tasks::{self, ControlHalves, PARTIAL_FORMAT, Partial, PartialHeader, TaskRange};
use crate::engine::technique::{self, Boundary, EngineError};

/// How a bake in rounds is cut: `regions` regions of the grid (whole pages when there are
/// at most as many as pages, else bands of rows, cut as a split bake's regions are:
/// `job::prepare_regions`), `rounds` rounds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RoundsShape {
    pub regions: u32,
    pub rounds: u32,
}

/// What one round did.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundReport {
    /// Steps every region baked in this round.
    pub steps: u64,
    /// How far the held light moved: the RMS luminance of the change over the RMS
    /// luminance of the new held light. It falls by the cross-region share of the light
    /// each round, down to the noise of the round's steps.
    pub change: f64,
    pub seconds: f64,
}

/// A bake in rounds: what a single bake delivers (the merged estimate, its error assessed
/// at the control texels when the technique is biased, the pages, the summary), and each
/// round's report.
pub struct RoundsResult {
    pub result: BakeResult,
    pub rounds: Vec<RoundReport>,
}

/// Bakes one task of a bake in rounds (one region in one round, `tasks::split_rounds`):
/// the whole grid prepared as the single bake's, the region's texels receiving, every
/// texel's light held at round r-1's estimate (the `held` of every task of `previous`,
/// which are all round r-1's results, one a region; none in round 0), the region's
/// accumulators resumed from its own result there. Its result holds the region's halves
/// and its round's own estimate (the next round's held light); in the last round, when
/// the technique is biased, the region's control texels too (picked from its texels with
/// the job's seed), which the merge joins as it joins regions'. `observer` sees the task's
/// steps; when it breaks, the result is marked cancelled (a merge refuses it).
pub fn bake_round_task(
    scene: Arc<Scene>,
    request: &BakeRequest,
    task: TaskRange,
    previous: &[Partial],
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
) -> Result<Partial, EngineError> {
    check_task(request, task)?;
    let started = Instant::now();
    // After round 0 the grid's validation is known: every region's result of the round
    // before lists the texels it kept (the merge takes them the same way), so the task
    // builds the texel set without tracing validation's rays again (most of a large
    // level's preparation).
    let kept: Option<Vec<u32>> =
        check_previous(request, task, previous)?.map(|p| p.iter().flat_map(|x| x.pixels.iter().copied()).collect());
    let prepared = prepare(scene, request, task, options, kept.as_deref(), on_atlas)?;
    bake_prepared(&prepared, request, task, previous, observer, started)
}

/// Refused unless `task` is one of `request`'s round tasks.
fn check_task(request: &BakeRequest, task: TaskRange) -> Result<(), EngineError> {
    let rounds = tasks::split_rounds(request, task.regions, task.rounds)?;
    if rounds.get(task.round as usize).and_then(|r| r.get(task.index as usize)) != Some(&task) {
        return Err(EngineError::BadInput(format!(
            "rounds: task {}/{} of round {} is not one of this request's tasks",
            task.index, task.count, task.round
        )));
    }
    Ok(())
}

/// The whole grid as the single bake's, cut into `task.regions` regions as a split bake's
/// merge cuts them (before validation): what every task of a bake in rounds starts from.
/// Deterministic, so tasks on different machines prepare the same. `kept`: the pixels of
/// the texels validation kept, in pixel order, when a round before has told them (then
/// nothing is traced, as in the merge, and the texel set is the same). In round 0 only
/// the task's own region is validated (`job::RegionsOf::trace`), so the round's tasks
/// trace the grid's validation once between them, each its own share (validation's rays
/// are keyed by the texel's pixel, so each region keeps the texels the whole grid's
/// validation keeps there, which round 1 then reads as `kept`); what the other regions'
/// untested texels change in round 0 is in the module doc's limits.
fn prepare(
    scene: Arc<Scene>,
    request: &BakeRequest,
    task: TaskRange,
    options: &BakeOptions,
    kept: Option<&[u32]>,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
) -> Result<job::Prepared, EngineError> {
    if kept.is_some_and(|k| k.windows(2).any(|w| w[0] >= w[1])) {
        return Err(EngineError::BadInput(
            "rounds: the round before's texels are not in pixel order: a damaged or foreign result".into(),
        ));
    }
    let regions = job::RegionsOf {
        count: task.regions,
        keep: None,
        validated: kept,
        trace: (task.round == 0 && kept.is_none()).then_some(task.region),
    };
    job::prepare_regions(scene, request, options, Some(regions), on_atlas, &mut |_| {})
}

/// [`bake_round_task`] on a grid already prepared ([`prepare`]); its time counts from
/// `started`.
fn bake_prepared(
    prepared: &job::Prepared,
    request: &BakeRequest,
    task: TaskRange,
    previous: &[Partial],
    observer: &mut dyn BakeObserver,
    started: Instant,
) -> Result<Partial, EngineError> {
    let bad = |m: String| Err(EngineError::BadInput(m));
    let previous = check_previous(request, task, previous)?;
    let atlas = prepared.atlas.clone();
    let range = region_texels(prepared, task.region)?;
    let held: Vec<Vec3> = match &previous {
        Some(p) => p.iter().flat_map(|x| x.held.iter().flatten().copied()).collect(),
        None => vec![Vec3::ZERO; atlas.texels.len()],
    };
    if held.len() != atlas.texels.len() {
        return bad(format!(
            "rounds: the round before holds light for {} texels, this scene has {}: results of another scene or version",
            held.len(),
            atlas.texels.len()
        ));
    }
    let own = previous.as_ref().map(|p| p[task.region as usize]);
    if own.is_some_and(|p| !p.has_halves()) {
        return bad(format!(
            "rounds: region {}'s own result of the round before was read without its halves; this task resumes them, so it reads them whole",
            task.region
        ));
    }
    let fingerprint = tasks::texels_fingerprint(&atlas, range.clone());
    if let Some(own) = own
        && own.header.fingerprint != fingerprint
    {
        return bad(format!(
            "rounds: region {}'s result of the round before was baked on another texel set: another scene or version",
            task.region
        ));
    }
    let mut tech = technique::create(&request.technique, prepared.inputs(request), &request.params)?;
    tech.hold_boundary(&Boundary {
        receivers: range.clone(),
        held: &held,
        resume: own.map(|p| &p.snapshot),
    })?;
    let stop = request.stop;
    let mut stopped_by = StopReason::Steps;
    for k in 1..=task.steps {
        tech.step()?;
        let go_on = observer.event(BakeEvent::Progress {
            steps: k,
            elapsed: started.elapsed(),
            stop: &stop,
        });
        if go_on.is_break() {
            stopped_by = StopReason::Cancelled;
            break;
        }
    }
    let snapshot = narrow(&tech.snapshot()?, range.clone());
    let params = tech.params();
    // Step i of a half weighs i^ramp in the technique's running means.
    let ramp = params.get("ramp").and_then(serde_json::Value::as_f64).unwrap_or(0.0);
    let fresh = this_round(own.map(|p| &p.snapshot), &snapshot, ramp);
    let technique_time = started.elapsed();
    // The last round measures the region's bias at its own control texels, as a region
    // task of a split bake does; the merge joins them.
    let control = if prepared.control && task.round + 1 == task.rounds && !range.is_empty() {
        let mut c = ControlTexels::new(
            &prepared.rays,
            &atlas.region(range.clone()),
            request.lighting,
            request.seed,
            request.seed,
        )?;
        c.keep_up(technique_time)?;
        let reference = c.reference()?;
        Some(ControlHalves::of(c.indices(), &reference))
    } else {
        None
    };
    let header = PartialHeader {
        format: PARTIAL_FORMAT,
        request: request.clone(),
        task,
        params,
        width: atlas.width,
        height: atlas.height,
        texels: range.len() as u64,
        fingerprint,
        half_steps: [snapshot.even.steps, snapshot.odd.steps],
        direct: snapshot.even.direct.is_some(),
        moments: false,
        ao: false,
        ambient: None,
        control,
        seconds: started.elapsed().as_secs_f64(),
        stopped_by,
        live: false,
        held: true,
    };
    tracing::info!(
        technique = %request.technique,
        region = task.region,
        regions = task.regions,
        round = task.round,
        rounds = task.rounds,
        steps = task.steps,
        seconds = header.seconds,
        "round task baked"
    );
    Ok(Partial {
        header,
        pixels: atlas.texels[range].iter().map(|t| t.pixel).collect(),
        snapshot,
        ao: None,
        ambient: None,
        held: Some(fresh),
    })
}

/// The results of the round before `task`'s, in region order, or none in round 0; refused,
/// naming the result, when they are not every region's result of that round of this
/// request.
fn check_previous<'a>(
    request: &BakeRequest,
    task: TaskRange,
    previous: &'a [Partial],
) -> Result<Option<Vec<&'a Partial>>, EngineError> {
    let bad = |m: String| Err(EngineError::BadInput(m));
    if task.round == 0 {
        if !previous.is_empty() {
            return bad("rounds: round 0 reads no results of a round before it".into());
        }
        return Ok(None);
    }
    let mut by_region: Vec<Option<&Partial>> = vec![None; task.regions as usize];
    for (k, p) in previous.iter().enumerate() {
        let h = &p.header;
        let name = format!(
            "result {k} of the round before (region {}, round {})",
            h.task.region, h.task.round
        );
        if h.request != *request || (h.task.regions, h.task.rounds) != (task.regions, task.rounds) {
            return bad(format!(
                "rounds: {name} is of another request or another cut into rounds"
            ));
        }
        if h.task.round + 1 != task.round {
            return bad(format!("rounds: {name} is not of round {}", task.round - 1));
        }
        if h.live || h.stopped_by == StopReason::Cancelled || p.held.is_none() {
            return bad(format!("rounds: {name} is not a finished round task's result"));
        }
        let slot = &mut by_region[h.task.region as usize];
        if slot.is_some() {
            return bad(format!("rounds: {name}: region {} is given twice", h.task.region));
        }
        *slot = Some(p);
    }
    let missing: Vec<String> = (0..by_region.len())
        .filter(|&r| by_region[r].is_none())
        .map(|r| r.to_string())
        .collect();
    if !missing.is_empty() {
        return bad(format!(
            "rounds: round {} needs every region's result of round {}; regions {} are missing",
            task.round,
            task.round - 1,
            missing.join(", ")
        ));
    }
    Ok(Some(by_region.into_iter().flatten().collect()))
}

/// Region `region`'s texels in the prepared grid: cut before validation, as the merge
/// cuts them (`tasks::merge`).
fn region_texels(prepared: &job::Prepared, region: u32) -> Result<Range<usize>, EngineError> {
    let pixels = prepared
        .region_pixels
        .get(region as usize)
        .ok_or_else(|| EngineError::BadInput(format!("rounds: the grid has no region {region}")))?;
    Ok(prepared.atlas.texels_in(pixels.clone()))
}

/// Bakes `request` on `scene` as `shape.regions` regions over `shape.rounds` rounds (module
/// doc): every round's region tasks ([`bake_round_task`]) one after another in this
/// process, each round reading the round before's results, then the last round's
/// merged as a split bake's regions are (`tasks::merge`). `observer` sees the steps of
/// every task summed (`regions` times `stop.steps` in all); when it breaks, the bake
/// fails: a bake in rounds delivers nothing before its last round.
pub fn bake_in_rounds(
    scene: Arc<Scene>,
    request: &BakeRequest,
    shape: RoundsShape,
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
) -> Result<RoundsResult, EngineError> {
    let rounds = tasks::split_rounds(request, shape.regions, shape.rounds)?;
    // Lightmap UVs generated once for every task and the merge: the same UVs each task
    // generates on its own machine (the unwrap is deterministic), a second a prepare on
    // the occlusion room.
    let (scene, generated_uvs) = job::lightmap_uvs(scene, request)?;
    // The grid prepared as each task on its own machine prepares it (`prepare` is
    // deterministic), so the lightmap is the processes' lightmap: in round 0 once a task
    // (each validates its own region), from round 1 on once for all, from the texels
    // round 0 kept. `on_atlas` sees the grid the last round bakes on (with one round,
    // region 0's).
    let seen_in = shape.rounds.min(2) - 1;
    let mut on_atlas = Some(on_atlas);
    let mut prepared: Option<(u32, job::Prepared)> = None;
    let mut previous: Vec<Partial> = Vec::new();
    let mut held_before: Vec<Vec3> = Vec::new();
    let mut reports = Vec::with_capacity(rounds.len());
    let mut done = 0u64;
    for round in rounds {
        let started = Instant::now();
        let mut results = Vec::with_capacity(round.len());
        for task in &round {
            let mut cancelled = false;
            let mut relay = |e: BakeEvent<'_>| {
                let e = match e {
                    BakeEvent::Progress { steps, elapsed, stop } => BakeEvent::Progress {
                        steps: done + steps,
                        elapsed,
                        stop,
                    },
                    other => other,
                };
                let flow = observer.event(e);
                cancelled |= flow.is_break();
                flow
            };
            check_task(request, *task)?;
            // Round 0's preparations are each their task's; the one after is every later round's.
            if task.round <= 1 && prepared.as_ref().is_none_or(|(round, _)| *round == 0) {
                let kept: Option<Vec<u32>> =
                    (task.round > 0).then(|| previous.iter().flat_map(|x| x.pixels.iter().copied()).collect());
                let see = if task.round == seen_in { on_atlas.take() } else { None };
                // One whole grid at a time: the one before is let go first.
                drop(prepared.take());
                let grid = prepare(
                    scene.clone(),
                    request,
                    *task,
                    options,
                    kept.as_deref(),
                    see.unwrap_or(&mut |_| {}),
                )?;
                prepared = Some((task.round, grid));
            }
            let (_, prepared) = prepared.as_ref().expect("prepared above");
            let p = bake_prepared(prepared, request, *task, &previous, &mut relay, Instant::now())?;
            if cancelled {
                return Err(EngineError::BadInput(
                    "rounds: the bake was cancelled; a bake in rounds delivers nothing before its last round".into(),
                ));
            }
            done += task.steps;
            results.push(p);
        }
        let held: Vec<Vec3> = results.iter().flat_map(|p| p.held.iter().flatten().copied()).collect();
        let change = if held_before.is_empty() {
            1.0
        } else {
            relative_rms(&held, &held_before)
        };
        let seconds = started.elapsed().as_secs_f64();
        tracing::info!(
            technique = %request.technique,
            round = round[0].round,
            rounds = shape.rounds,
            regions = shape.regions,
            steps = round[0].steps,
            change,
            seconds,
            "round baked"
        );
        reports.push(RoundReport {
            steps: round[0].steps,
            change,
            seconds,
        });
        held_before = held;
        previous = results;
    }
    let mut result = tasks::merge(scene, &previous, options, &mut |_| {})?;
    result.summary.generated_uvs = generated_uvs;
    Ok(RoundsResult {
        result,
        rounds: reports,
    })
}

/// The estimate a region's round made by its own steps: per half, the running means'
/// sums (weight i^`ramp` for step i) after the round less those before it, over the
/// round's weights; the halves combined by their steps in the round. The held light of
/// the next round, rather than the running mean, which still carries the earlier rounds'
/// lag (on the closed box of albedo 0.5 in 6 rounds of 96 steps the running mean as the
/// held light left the answer 2.2 % short, the round's own steps 1.1 %).
fn this_round(before: Option<&Snapshot>, after: &Snapshot, ramp: f64) -> Vec<Vec3> {
    let weight = |n: u64| -> f64 { (1..=n).map(|i| (i as f64).powf(ramp)).sum() };
    let mut sum = vec![Vec3::ZERO; after.even.total.len()];
    let mut steps = 0u64;
    for h in 0..2 {
        let a = [&after.even, &after.odd][h];
        let b = before.map(|s| [&s.even, &s.odd][h]);
        let nb = b.map_or(0, |b| b.steps);
        if a.steps <= nb {
            continue;
        }
        let (wa, wb) = (weight(a.steps), weight(nb));
        let k = (a.steps - nb) as f32;
        for (i, out) in sum.iter_mut().enumerate() {
            let prior = b.map_or(Vec3::ZERO, |b| b.total[i] * wb as f32);
            *out += (a.total[i] * wa as f32 - prior) / (wa - wb) as f32 * k;
        }
        steps += a.steps - nb;
    }
    let k = steps.max(1) as f32;
    sum.into_iter().map(|v| v / k).collect()
}

/// The texels `range` of a snapshot's halves.
fn narrow(s: &Snapshot, range: Range<usize>) -> Snapshot {
    let half = |h: &HalfEstimate| HalfEstimate {
        steps: h.steps,
        total: h.total[range.clone()].to_vec(),
        direct: h.direct.as_ref().map(|d| d[range.clone()].to_vec()),
        moments: h.moments.as_ref().map(|m| m[range.clone()].to_vec()),
    };
    Snapshot {
        even: half(&s.even),
        odd: half(&s.odd),
    }
}

/// RMS luminance of `a - b` over the RMS luminance of `a` (0 for a black `a`).
fn relative_rms(a: &[Vec3], b: &[Vec3]) -> f64 {
    let lum = |v: Vec3| f64::from(v.dot(LUMINANCE));
    let d: f64 = a.iter().zip(b).map(|(x, y)| lum(*x - *y).powi(2)).sum();
    let r: f64 = a.iter().map(|x| lum(*x).powi(2)).sum();
    if r > 0.0 { (d / r).sqrt() } else { 0.0 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::tasks::round_steps;

    #[test]
    fn steps_are_dealt_over_the_rounds() {
        assert_eq!(round_steps(14, 3), vec![2, 4, 8]);
        assert_eq!(round_steps(96, 4), vec![6, 12, 25, 53]);
        assert_eq!(round_steps(8, 4), vec![1, 1, 2, 4]);
        assert_eq!(round_steps(5, 1), vec![5]);
        for (total, rounds) in [(8, 4), (96, 4), (1000, 7), (12, 6)] {
            let s = round_steps(total, rounds);
            assert_eq!(s.iter().sum::<u64>(), total, "{total} in {rounds}");
            assert!(s.iter().all(|&x| x >= 1), "{s:?}");
        }
    }

    #[test]
    fn a_rounds_own_estimate_is_its_steps_alone() {
        let half = |v: f32, steps| HalfEstimate {
            steps,
            total: vec![Vec3::splat(v)],
            direct: None,
            moments: None,
        };
        // Ramp 1: steps 1..=2 of a half at 1.0, then steps 3..=4 at 4.0: the running mean
        // is (1 + 2 + 4 * 3 + 4 * 4) / 10 = 3.1; the round's own steps read 4.0.
        let before = Snapshot {
            even: half(1.0, 2),
            odd: half(1.0, 2),
        };
        let after = Snapshot {
            even: half(3.1, 4),
            odd: half(3.1, 4),
        };
        let own = this_round(Some(&before), &after, 1.0);
        assert!((own[0].x - 4.0).abs() < 1e-5, "{own:?}");
        // The first round: the running mean itself.
        assert_eq!(this_round(None, &after, 1.0), vec![Vec3::splat(3.1)]);
        // Plain means (ramp 0): (2 * 1 + 2 * x) / 4 = 2.5 gives x = 4.
        let plain = Snapshot {
            even: half(2.5, 4),
            odd: half(2.5, 4),
        };
        assert!((this_round(Some(&before), &plain, 0.0)[0].x - 4.0).abs() < 1e-5);
    }

    #[test]
    fn a_snapshot_narrows_to_a_region() {
        let half = |v: &[f32], steps| HalfEstimate {
            steps,
            total: v.iter().map(|&x| Vec3::splat(x)).collect(),
            direct: None,
            moments: None,
        };
        let whole = Snapshot {
            even: half(&[1.0, 2.0, 3.0, 4.0, 5.0], 3),
            odd: half(&[6.0, 7.0, 8.0, 9.0, 10.0], 2),
        };
        let part = narrow(&whole, 2..5);
        assert_eq!(part.even.total, whole.even.total[2..5].to_vec());
        assert_eq!(part.odd.total, whole.odd.total[2..5].to_vec());
        assert_eq!((part.even.steps, part.odd.steps), (3, 2));
        let zero = vec![Vec3::ZERO; 5];
        assert!((relative_rms(&whole.even.total, &zero) - 1.0).abs() < 1e-12);
        assert!(relative_rms(&whole.even.total, &whole.even.total).abs() < 1e-12);
    }
}
