//! A bake in rounds: a technique whose every step reads the whole grid's light baked one
//! region (page or band of rows) at a time, the regions exchanging their light between
//! rounds (issue 25 point 1; docs/scaling.md, "Pages for `sdb` and `hemicube`").
//!
//! # Why
//! `hemicube` draws its shooters from every texel's irradiance of the step before, so no
//! region of its grid stands alone, and its split bakes were independent chains of the
//! whole grid: every worker holds the whole level. Rounds bound what a region's bake
//! gathers to its own texels, which is what lets pages of a large level go to different
//! workers.
//!
//! # How: block Jacobi over the regions
//! The radiosity system B = E + K B, with K cut into region blocks. Round r's bake of
//! region p receives light at p's texels only ([`Boundary`]): every other texel sends the
//! light the merge of round r - 1 estimated (held fixed all round; zero in round 0, so the
//! first round is each region lit by the emitters, the sky and its own bounces), and p's
//! texels start from that estimate and from their own halves after round r - 1, which
//! their accumulators go on from. All regions of a round read the same held estimate
//! (Jacobi, not Gauss-Seidel), so a round's regions may bake at once. After the round the
//! regions' halves are placed side by side (each region's texels are a run of the grid's)
//! and their mean is the next round's held estimate.
//!
//! The held estimate's error shrinks each round by the part of the light that crosses
//! regions: about ρ f / (1 - ρ (1 - f)) for albedo ρ and a share f of a region's light that
//! comes from other regions (1/3 for half a closed box at ρ = 0.5). What the early rounds
//! leave in the accumulators is a transient of the same kind as a single bake's first
//! bounces, and the ramp weights (step i of a half weighs i^ramp) make its share small.
//! Neither is noise, so the halves' difference cannot see it; the control texels do: they
//! are picked over the whole grid with the job's seed and traced by `path` as in a single
//! bake, and the merged estimate is assessed against them (`control::assess_against`), so
//! the error reported states what the rounds left as well as the noise.
//!
//! Every region's bake uses the job's seed: its shooters and emitter samples are then the
//! ones a single bake would draw at that step (given the same light), and its CPU rays
//! are keyed by the texel's place in the whole grid.
//!
//! # Limits
//! - Only `hemicube` holds a boundary so far ([`Technique::hold_boundary`]); `sdb`, whose
//!   resolve reads every pixel's running estimate, is the next (docs/scaling.md).
//! - The driver here runs the rounds in one process, one region after another: it is the
//!   engine's half of the split. The farm's half (a round's tasks claimable when the round
//!   before is merged, in both queue backends) is not built; every region's bake still
//!   prepares the whole grid's buffers, so the memory bound a farm would get from pages
//!   is not had here either.
//! - The held light of a glossy texel outside the receivers has no incoming direction:
//!   its lobe reflects light arriving along its normal (`hemicube`'s select pass falls
//!   back to it), a bias the control texels state like any other.
//! - Step count: `stop.steps` is every region's, dealt out over the rounds (the first
//!   rounds one more when it does not divide); `stop.seconds` and `stop.target_error` are
//!   refused, as rules about the whole bake that no round sees alone.

use std::ops::Range;
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::Vec3;

use crate::engine::accumulate::{HalfEstimate, LUMINANCE, Snapshot};
use crate::engine::atlas::Atlas;
use crate::engine::bake::{BakeEvent, BakeObserver, StopReason};
use crate::engine::control::{self, ControlTexels};
use crate::engine::job::{self, BakeOptions, BakeRequest, BakeResult};
use crate::engine::output::OutputLayer;
use crate::engine::scene::Scene;
use crate::engine::technique::{self, Boundary, EngineError};

/// How a bake in rounds is cut: `regions` regions of the grid (whole pages when there are
/// at most as many as pages, else bands of rows: `Atlas::regions`), `rounds` rounds.
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
    /// How far the held estimate moved: the RMS luminance of the change over the RMS
    /// luminance of the new estimate. It falls by the cross-region share of the light
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

/// Upper bound on rounds: each repeats every region's preparation.
pub const MAX_ROUNDS: u32 = 64;

/// The steps of each of `rounds` rounds out of `total`: each round twice the one before
/// (rounded down, at least one step; the last takes what is left), so the last round
/// bakes about half the steps. Why not even shares: the accumulators go on over the
/// rounds, and a step of round r carries what the held estimate still lacked then (a
/// page alone in round 0 reads 0.62 of the closed box's 1). With the ramp weights the
/// first rounds' share of the mean is about the square of their share of the steps, so
/// short early rounds leave little of it: on the closed box of albedo 0.5 in four rounds,
/// even shares read 0.898, doubling ones 0.97 (docs/scaling.md).
pub fn round_steps(total: u64, rounds: u32) -> Vec<u64> {
    let r = rounds.max(1);
    let parts = (1u64 << r) - 1;
    let mut steps: Vec<u64> = (0..r - 1).map(|i| (total * (1u64 << i) / parts).max(1)).collect();
    let before: u64 = steps.iter().sum();
    steps.push(total.saturating_sub(before).max(1));
    steps
}

/// Bakes `request` on `scene` as `shape.regions` regions over `shape.rounds` rounds (module
/// doc), one region after another in this process, and delivers the merged estimate as a
/// single bake does. `observer` sees the steps of every region summed (`regions` times
/// `stop.steps` in all); when it breaks, the bake stops after the region's steps under
/// way and delivers the rounds merged so far (cancelled), or, in the first round, fails.
pub fn bake_in_rounds(
    scene: Arc<Scene>,
    request: &BakeRequest,
    shape: RoundsShape,
    options: &BakeOptions,
    observer: &mut dyn BakeObserver,
    on_atlas: &mut dyn FnMut(&Arc<Atlas>),
) -> Result<RoundsResult, EngineError> {
    let bad = |m: String| Err(EngineError::BadInput(m));
    if !(1..=MAX_ROUNDS).contains(&shape.rounds) {
        return bad(format!("rounds must be in 1..={MAX_ROUNDS}, got {}", shape.rounds));
    }
    if shape.regions == 0 {
        return bad("rounds: regions must be at least 1".into());
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
    if total < 2 * u64::from(shape.rounds) {
        return bad(format!(
            "rounds: stop.steps ({total}) must be at least twice the rounds ({}): each round bakes a step of each half",
            shape.rounds
        ));
    }
    if !technique::entry(&request.technique)?.rounds {
        return bad(format!(
            "rounds: technique {} is not baked in rounds (only hemicube is, so far)",
            request.technique
        ));
    }
    if request.outputs.contains(&OutputLayer::Shadowmask) {
        return bad("rounds: the shadowmask layer is not baked in rounds yet; bake it as one task".into());
    }
    let started = Instant::now();
    let prepared = job::prepare(scene, request, options, on_atlas, &mut |_| {})?;
    let atlas = prepared.atlas.clone();
    let regions = atlas.regions(shape.regions).map_err(EngineError::BadInput)?;
    let n = atlas.texels.len();
    let mut held = vec![Vec3::ZERO; n];
    let mut own: Vec<Option<Snapshot>> = vec![None; regions.len()];
    // Each region's estimate from its last round's steps alone: the next round's held light.
    let mut fresh: Vec<Vec<Vec3>> = vec![Vec::new(); regions.len()];
    let mut reports = Vec::with_capacity(shape.rounds as usize);
    let mut technique_time = Duration::ZERO;
    let mut merged = Snapshot::default();
    let mut stopped_by = StopReason::Steps;
    // The parameters in effect (the same in every region's bake), for the EXR header.
    let mut params = serde_json::Value::Null;
    let mut done = 0u64;
    let stop = request.stop;
    'rounds: for (round, steps) in round_steps(total, shape.rounds).into_iter().enumerate() {
        let round_started = Instant::now();
        for (p, range) in regions.iter().enumerate() {
            let mut tech = technique::create(&request.technique, prepared.inputs(request), &request.params)?;
            tech.hold_boundary(&Boundary {
                receivers: range.clone(),
                held: &held,
                resume: own[p].as_ref(),
            })?;
            for _ in 0..steps {
                tech.step()?;
                done += 1;
            }
            let go_on = observer.event(BakeEvent::Progress {
                steps: done,
                elapsed: started.elapsed(),
                stop: &stop,
            });
            let after = narrow(&tech.snapshot()?, range.clone());
            // Step i of a half weighs i^ramp in the technique's running means.
            params = tech.params();
            let ramp = params.get("ramp").and_then(serde_json::Value::as_f64).unwrap_or(0.0);
            fresh[p] = this_round(own[p].as_ref(), &after, ramp);
            // Cancelled: the regions keep the halves of their last whole round.
            if go_on.is_break() {
                if round == 0 {
                    return bad("rounds: the bake was cancelled before its first round ended".into());
                }
                stopped_by = StopReason::Cancelled;
                break 'rounds;
            }
            own[p] = Some(after);
        }
        merged = join(own.iter().flatten());
        let this: Vec<Vec3> = fresh.concat();
        let change = relative_rms(&this, &held);
        held = this;
        let seconds = round_started.elapsed().as_secs_f64();
        technique_time += round_started.elapsed();
        tracing::info!(
            technique = %request.technique,
            round,
            rounds = shape.rounds,
            regions = regions.len(),
            steps,
            change,
            seconds,
            "round baked"
        );
        reports.push(RoundReport { steps, change, seconds });
    }
    let mut estimate = merged.estimate();
    if prepared.control && n > 0 {
        // The single bake's control texels (picked and traced with the job's seed), given
        // the rounds' time as the technique's: they see the merged lightmap as a single
        // bake's are seen.
        let mut c = ControlTexels::new(&prepared.rays, &atlas, request.lighting, request.seed, request.seed)?;
        c.keep_up(technique_time)?;
        let reference = c.reference()?.estimate();
        control::assess_against(c.indices(), &reference, &mut estimate);
    }
    let result = prepared.deliver(request, &estimate, &params, started.elapsed(), stopped_by, observer)?;
    Ok(RoundsResult {
        result,
        rounds: reports,
    })
}

/// The estimate a region's last round made by its own steps: per half, the running
/// means' sums (weight i^`ramp` for step i) after the round less those before it, over
/// the round's weights; the halves combined by their steps in the round. The held light
/// of the next round, rather than the running mean, which still carries the earlier
/// rounds' lag (on the closed box of albedo 0.5 in 6 rounds of 96 steps the running mean
/// as the held light left the answer 2.2 % short, the round's own steps 1.1 %).
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

/// Regions' halves side by side, in order. Every region bakes the same steps, so the
/// halves' step counts agree.
fn join<'a>(regions: impl Iterator<Item = &'a Snapshot> + Clone) -> Snapshot {
    let half = |pick: fn(&Snapshot) -> &HalfEstimate| {
        let halves: Vec<&HalfEstimate> = regions.clone().map(pick).collect();
        HalfEstimate {
            steps: halves.iter().map(|h| h.steps).min().unwrap_or(0),
            total: halves.iter().flat_map(|h| h.total.iter().copied()).collect(),
            direct: halves
                .iter()
                .map(|h| h.direct.as_deref())
                .collect::<Option<Vec<_>>>()
                .map(|parts| parts.concat()),
            moments: None,
        }
    };
    Snapshot {
        even: half(|s| &s.even),
        odd: half(|s| &s.odd),
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
    fn regions_join_in_order_and_narrow_back() {
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
        let parts = [narrow(&whole, 0..2), narrow(&whole, 2..5)];
        assert_eq!(parts[1].even.total, whole.even.total[2..5].to_vec());
        let joined = join(parts.iter());
        assert_eq!(joined.even.total, whole.even.total);
        assert_eq!(joined.odd.total, whole.odd.total);
        assert_eq!((joined.even.steps, joined.odd.steps), (3, 2));
        assert!((relative_rms(&joined.even.total, &whole.even.total)).abs() < 1e-12);
        let zero = vec![Vec3::ZERO; 5];
        assert!((relative_rms(&whole.even.total, &zero) - 1.0).abs() < 1e-12);
    }
}
