//! The merges of a split bake's task results: the halves' step-weighted means within a
//! region and side by side across regions ([`merge_halves`]), the `ao` layer, the
//! scene-wide ambient closed over every region (`close_ambient`), the chains' control
//! texels and the merged error estimate; the checks that the results are every task of
//! one request ([`check_partials`]); the final merge ([`merge`]) and the running one of a
//! job in progress ([`merge_running`]).

use std::sync::Arc;
use std::time::Duration;

use glam::Vec3;

use crate::engine::accumulate::{Estimate, HalfEstimate, Snapshot};
use crate::engine::ambient::AmbientSums;
use crate::engine::atlas::Atlas;
use crate::engine::bake::StopReason;
use crate::engine::control;
use crate::engine::job::{self, BakeOptions, BakeRequest, BakeResult};
use crate::engine::plan::Plan;
use crate::engine::scene::Scene;
use crate::engine::technique::EngineError;

use super::partial::{ControlHalves, Partial};
use super::{split, split_rounds, texels_fingerprint};

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
pub(super) fn merge_ao(groups: &[&[&Partial]]) -> Option<Vec<f32>> {
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
pub(super) fn close_ambient(groups: &[&[&Partial]]) -> Option<Vec<Vec<Partial>>> {
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
pub(super) fn merge_control(groups: &[&[&Partial]]) -> Result<Option<(Vec<usize>, Snapshot)>, EngineError> {
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
/// every task given (a running task's so far, from [`bake_task_live`](super::bake_task_live), or a finished
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
