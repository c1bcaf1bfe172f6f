//! The bake loop: steps a technique until a stop criterion holds, reporting progress and
//! snapshots to an observer (the CLI's progress bar, the service's event stream).
//!
//! How: snapshots cost a GPU readback, so they are taken on a schedule rather than every
//! step: at steps 2, 4, 8, … (so early previews come quickly) and at least every
//! `snapshot_interval` seconds after that, and always at the end. A target error is
//! checked at each snapshot, since the error needs both halves' means.
//!
//! The time limit is kept by prediction: after each step the loop stops when one more step
//! of the longest duration seen so far would end past the limit (or when the limit has
//! passed), so a bake whose steps are each a small part of its budget ends within one
//! step's length *before* it, never after.
//!
//! A step longer than the rest of the budget is cut short instead (issue 19 point 10):
//! the loop hands the limit's instant to the technique ([`Technique::set_deadline`]),
//! which abandons a step the moment the limit passes, adding nothing, and the loop stops
//! with the steps done before. If not one step was done by then the bake fails with
//! an error that says so (a lightmap of no samples is black, not an answer).
//!
//! A GPU technique's step only queues its dispatches; under a time limit the loop waits
//! for them ([`Technique::wait_for_steps`]) before it times the step, so the prediction
//! sees what a step costs on the device rather than what its submission took. It also
//! waits once before its clock starts, for the uploads preparation queued (0.8 s of
//! `sdb`'s first step at 2048² on lavapipe), which are preparation, not a step.
//!
//! Every technique honours the deadline (issue 19 point 10): CPU `path` between chunks of paths;
//! on the GPU, in a watched bake (a deadline, or a watcher that may cancel), the parts of
//! a step that grow with the level run in slices of about 50 ms, each waited for, with
//! what they write put aside first and put back when the step is stopped between two
//! (`gpu::slices`): `path`'s and the shared direct light's texels (`sdf`, `obscurance`,
//! `sdb`'s small lights), `vpl`'s gather, `hemicube`'s CPU rays (in chunks) and transfer,
//! `obscurance`'s and `sdb`'s directions (whole directions a slice).
//!
//! A task of a split bake (`engine::tasks`) may also ask for its halves while it runs
//! ([`LiveHook`]): at a snapshot, at most once every `every`, the loop hands the
//! technique's halves (and its control texels' reference) to the hook, so the service can
//! merge the tasks' halves into the job's snapshots while they bake (issue 25 point 2).
//! A clone of the halves, so only when asked for.
//!
//! Limits: what a slice cannot split still finishes (one direction of `sdb` or
//! `obscurance`, one slice's texels, the parts of a step that grow with the lights and the
//! scene rather than the texels: `vpl`'s RSMs, VPL paths and shadow maps, `hemicube`'s
//! pyramid and depth maps); the control texels' reference and the shadowmask pass keep
//! pace with the technique and are not cut short either.

use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::engine::accumulate::{Estimate, Snapshot};
use crate::engine::control::ControlTexels;
use crate::engine::error::EngineError;
use crate::engine::scene::Scene;
use crate::engine::shadowmask::ShadowmaskBake;
pub use crate::engine::technique::api::StepProgress;
use crate::engine::technique::api::Technique;

/// A target error is not trusted before this many steps: with few steps per half the
/// half-difference is itself too noisy, and a lucky early estimate could stop a bake
/// that is far from converged (with 8 steps per half the estimate's own relative
/// spread is about 1/sqrt(2 · 8 · texels) per texel, but correlated early bounces in
/// progressive techniques need a few steps to show).
pub const MIN_STEPS_FOR_TARGET_ERROR: u64 = 16;

/// When a bake stops: whichever criterion is met first. At least one must be set.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StopCriteria {
    pub steps: Option<u64>,
    pub seconds: Option<f64>,
    pub target_error: Option<f32>,
}

impl StopCriteria {
    pub fn validate(&self) -> Result<(), EngineError> {
        if self.steps.is_none() && self.seconds.is_none() && self.target_error.is_none() {
            return Err(EngineError::BadInput(
                "stop: give at least one of steps, seconds, target_error".into(),
            ));
        }
        if self.steps == Some(0) {
            return Err(EngineError::BadInput("stop.steps must be at least 1".into()));
        }
        if let Some(s) = self.seconds
            && !(s.is_finite() && s > 0.0)
        {
            return Err(EngineError::BadInput(format!(
                "stop.seconds must be a positive number, got {s}"
            )));
        }
        if let Some(e) = self.target_error
            && !(e.is_finite() && e > 0.0)
        {
            return Err(EngineError::BadInput(format!(
                "stop.target_error must be a positive number, got {e}"
            )));
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    Steps,
    Seconds,
    TargetError,
    Cancelled,
}

pub enum BakeEvent<'a> {
    Progress {
        steps: u64,
        elapsed: Duration,
        stop: &'a StopCriteria,
    },
    Snapshot {
        estimate: &'a Estimate,
        elapsed: Duration,
    },
    /// Once, before the first step, when the engine generated lightmap UVs (the scene had
    /// none, or the request regenerates them): the scene as baked, whose `TEXCOORD_1` the
    /// lightmap and every snapshot fit, so a viewer can show snapshots on it while the
    /// bake runs.
    GeneratedUvs {
        scene: &'a Arc<Scene>,
    },
    /// Light probes after the lightmap (`job::BakeRequest::probes`): `steps` of `of` done
    /// for `probes` probes; sent before the first probe step and after each. Returning
    /// `Break` stops the probes where they are (the steps done are kept).
    Probes {
        steps: u32,
        of: u32,
        probes: usize,
    },
}

/// Receives progress and snapshots; returning `Break` cancels the bake (the last
/// snapshot is still returned).
pub trait BakeObserver {
    fn event(&mut self, event: BakeEvent<'_>) -> ControlFlow<()>;
}

impl<F: FnMut(BakeEvent<'_>) -> ControlFlow<()>> BakeObserver for F {
    fn event(&mut self, event: BakeEvent<'_>) -> ControlFlow<()> {
        self(event)
    }
}

pub struct BakeOutcome {
    pub estimate: Estimate,
    pub elapsed: Duration,
    pub stopped_by: StopReason,
}

pub struct BakeLoop {
    pub stop: StopCriteria,
    /// Where the technique reports how far each step is (None: nobody watches).
    pub step_progress: Option<StepProgress>,
    /// Longest time between snapshots once the doubling schedule has thinned out.
    pub snapshot_interval: Duration,
    /// The bias measurement of a biased technique (`engine::control`): stepped alongside,
    /// folded into every snapshot's error, which the target error then stops on.
    pub control: Option<ControlTexels>,
    /// The shadowmask pass (`engine::shadowmask`): stepped once per technique step; every
    /// snapshot loses its lights' direct light after the control texels assessed it.
    pub shadowmask: Option<ShadowmaskBake>,
    /// Where a split bake's task hands its halves while it runs (None: nowhere).
    pub live: Option<LiveHook>,
}

/// What a running task hands on at a snapshot: the technique's halves as they are, its
/// `ao` layer, its scene-wide ambient (`Technique::ambient`), its control texels with
/// their reference's halves (a biased technique's), and the loop's time.
pub struct LiveHalves {
    pub snapshot: Snapshot,
    pub ao: Option<Vec<f32>>,
    pub ambient: Option<[crate::engine::ambient::AmbientHalf; 2]>,
    pub control: Option<(Vec<usize>, Snapshot)>,
    pub elapsed: Duration,
}

/// Receives a running bake's halves ([`LiveHalves`]) at its snapshots, at most once every
/// `every` (the first snapshot always).
pub struct LiveHook {
    pub every: Duration,
    pub sink: Box<dyn FnMut(LiveHalves) + Send>,
    last: Option<Instant>,
}

impl LiveHook {
    pub fn new(every: Duration, sink: Box<dyn FnMut(LiveHalves) + Send>) -> LiveHook {
        LiveHook {
            every,
            sink,
            last: None,
        }
    }
}

/// Takes the loop's clock out of its step progress when `run` returns, whichever way,
/// so a watcher stops counting the loop's time during delivery.
struct SteppingGuard(Option<StepProgress>);

impl Drop for SteppingGuard {
    fn drop(&mut self) {
        if let Some(p) = &self.0 {
            p.set_stepping_since(None);
        }
    }
}

impl BakeLoop {
    pub fn new(stop: StopCriteria) -> Self {
        BakeLoop {
            stop,
            step_progress: None,
            snapshot_interval: Duration::from_secs(5),
            control: None,
            shadowmask: None,
            live: None,
        }
    }

    pub fn run(
        &mut self,
        technique: &mut dyn Technique,
        observer: &mut dyn BakeObserver,
    ) -> Result<BakeOutcome, EngineError> {
        self.stop.validate()?;
        // Preparation's queued device work is not the first step's (module doc).
        technique.wait_for_steps()?;
        let start = Instant::now();
        let mut last_snapshot = start;
        let mut next_doubling = 2u64;
        let mut longest_step = Duration::ZERO;
        let mut technique_time = Duration::ZERO;
        let deadline = self.stop.seconds.map(|s| start + Duration::from_secs_f64(s));
        technique.set_deadline(deadline);
        if let Some(p) = &self.step_progress {
            technique.set_step_progress(p.clone());
            p.set_stepping_since(Some(start));
        }
        let _stepping = SteppingGuard(self.step_progress.clone());
        loop {
            let step_start = Instant::now();
            if let Some(p) = &self.step_progress {
                p.set(0, 1);
            }
            let before = technique.steps_done();
            technique.step()?;
            let stop_asked = self.step_progress.as_ref().is_some_and(|p| p.stop_requested());
            if technique.steps_done() == before && (stop_asked || deadline.is_some_and(|d| Instant::now() >= d)) {
                // The technique abandoned the step at the limit, or because the watcher
                // asked it to stop (a cancelled job: the observer says so below).
                let elapsed = start.elapsed();
                tracing::info!(
                    technique = technique.id(),
                    steps = before,
                    seconds = elapsed.as_secs_f64(),
                    step_seconds = step_start.elapsed().as_secs_f64(),
                    stop_asked,
                    "a step was cut short"
                );
                if before == 0 && !stop_asked {
                    return Err(EngineError::BadInput(format!(
                        "the time limit of {:.3} s ended before the first step of {} was done ({:.2} s in): give the bake more time (stop.seconds / --seconds), fewer texels (resolution, texels_per_unit) or fewer samples a step (params.samples_per_step)",
                        self.stop.seconds.unwrap_or(0.0),
                        technique.id(),
                        elapsed.as_secs_f64()
                    )));
                }
                let estimate = self.snapshot(technique, elapsed)?;
                let cancelled = observer
                    .event(BakeEvent::Snapshot {
                        estimate: &estimate,
                        elapsed,
                    })
                    .is_break();
                return Ok(BakeOutcome {
                    estimate,
                    elapsed,
                    stopped_by: if cancelled || stop_asked {
                        StopReason::Cancelled
                    } else {
                        StopReason::Seconds
                    },
                });
            }
            if deadline.is_some() {
                technique.wait_for_steps()?;
            }
            let step_time = step_start.elapsed();
            longest_step = longest_step.max(step_time);
            technique_time += step_time;
            if let Some(c) = &mut self.control {
                c.keep_up(technique_time)?;
            }
            if let Some(s) = &mut self.shadowmask {
                s.step()?;
            }
            let steps = technique.steps_done();
            let elapsed = start.elapsed();
            let cancelled = observer
                .event(BakeEvent::Progress {
                    steps,
                    elapsed,
                    stop: &self.stop,
                })
                .is_break();
            let by_steps = self.stop.steps.is_some_and(|n| steps >= n);
            // Another step of the longest length seen would end past the limit.
            let by_time = self
                .stop
                .seconds
                .is_some_and(|s| (elapsed + longest_step).as_secs_f64() > s);
            let error_check_due = self.stop.target_error.is_some() && steps == MIN_STEPS_FOR_TARGET_ERROR;
            let scheduled =
                steps >= next_doubling || error_check_due || last_snapshot.elapsed() >= self.snapshot_interval;
            if !(cancelled || by_steps || by_time || scheduled) {
                continue;
            }
            if steps >= next_doubling {
                next_doubling = steps.saturating_mul(2);
            }
            last_snapshot = Instant::now();
            let estimate = self.snapshot(technique, elapsed)?;
            tracing::debug!(
                technique = technique.id(),
                step = steps,
                seconds = elapsed.as_secs_f64(),
                relative_error = ?estimate.error.relative,
                "snapshot"
            );
            let by_error = match (self.stop.target_error, estimate.error.relative) {
                (Some(target), Some(err)) => err <= target && steps >= MIN_STEPS_FOR_TARGET_ERROR,
                _ => false,
            };
            let cancelled = cancelled
                || observer
                    .event(BakeEvent::Snapshot {
                        estimate: &estimate,
                        elapsed,
                    })
                    .is_break();
            let stopped_by = if cancelled {
                StopReason::Cancelled
            } else if by_error {
                StopReason::TargetError
            } else if by_steps {
                StopReason::Steps
            } else if by_time {
                StopReason::Seconds
            } else {
                continue;
            };
            return Ok(BakeOutcome {
                estimate,
                elapsed,
                stopped_by,
            });
        }
    }
}

impl BakeLoop {
    /// The technique's estimate now, with its obscurance, its bias assessed at the
    /// control texels and the shadowmask lights taken out, checked finite; the halves go
    /// to the live hook when it is due.
    fn snapshot(&mut self, technique: &mut dyn Technique, elapsed: Duration) -> Result<Estimate, EngineError> {
        let snapshot = technique.snapshot()?;
        let mut estimate = snapshot.estimate();
        estimate.ao = technique.ao();
        check_finite(technique, &estimate)?;
        if let Some(c) = &mut self.control {
            c.assess(&mut estimate)?;
        }
        if let Some(live) = &mut self.live
            && live.last.is_none_or(|t| t.elapsed() >= live.every)
        {
            live.last = Some(Instant::now());
            let control = match &mut self.control {
                Some(c) => Some((c.indices().to_vec(), c.reference()?)),
                None => None,
            };
            (live.sink)(LiveHalves {
                snapshot: snapshot.clone(),
                ao: estimate.ao.clone(),
                ambient: technique.ambient(),
                control,
                elapsed,
            });
        }
        if let Some(s) = &self.shadowmask {
            estimate = s.apply(snapshot, &estimate)?;
            check_finite(technique, &estimate)?;
        }
        Ok(estimate)
    }
}

/// The guard of DESIGN §5: a non-finite value in any layer of a snapshot fails the bake,
/// naming the technique, the layer and the pass, so no NaN or infinity ever reaches an
/// EXR. (The delivered lightmap is checked again after denoising and seam stitching,
/// channel by channel, in `output::lightmap_channels`.)
fn check_finite(technique: &dyn Technique, estimate: &Estimate) -> Result<(), EngineError> {
    if let Some((layer, k, v)) = estimate.first_non_finite() {
        return Err(EngineError::Internal(format!(
            "technique {} produced a non-finite value {v:?} at texel {k} of the {layer} layer in pass \"{}\" \
             (by step {}); the lightmap was not written",
            technique.id(),
            technique.accumulating_pass(),
            estimate.steps
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::accumulate::{HalfAccumulator, Snapshot};
    use glam::Vec3;

    /// A technique that returns given values, to drive the loop and the guard.
    struct Fixed {
        acc: HalfAccumulator,
        value: Vec3,
    }

    impl Technique for Fixed {
        fn id(&self) -> &'static str {
            "fixed"
        }
        fn params(&self) -> serde_json::Value {
            serde_json::Value::Null
        }
        fn step(&mut self) -> Result<(), EngineError> {
            self.acc.add(&[Vec3::ONE, self.value], None);
            Ok(())
        }
        fn steps_done(&self) -> u64 {
            self.acc.steps()
        }
        fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
            Ok(self.acc.snapshot())
        }
        fn accumulating_pass(&self) -> &'static str {
            "test pass"
        }
    }

    fn run(value: Vec3, stop: StopCriteria) -> Result<BakeOutcome, EngineError> {
        let mut t = Fixed {
            acc: HalfAccumulator::new(2, false),
            value,
        };
        BakeLoop::new(stop).run(&mut t, &mut |_: BakeEvent<'_>| ControlFlow::Continue(()))
    }

    #[test]
    fn non_finite_values_fail_the_bake_naming_technique_and_pass() {
        for bad in [f32::NAN, f32::INFINITY] {
            let stop = StopCriteria {
                steps: Some(4),
                ..Default::default()
            };
            let err = run(Vec3::new(1.0, bad, 1.0), stop)
                .err()
                .expect("must fail")
                .to_string();
            assert!(err.contains("technique fixed produced a non-finite value"), "{err}");
            assert!(
                err.contains("at texel 1 of the total layer in pass \"test pass\""),
                "{err}"
            );
        }
    }

    /// A technique whose steps take the given times and honour the deadline: a step
    /// sleeps in 5 ms slices and is abandoned, adding nothing, once the deadline passed.
    struct Slow {
        acc: HalfAccumulator,
        step_times: Vec<Duration>,
        deadline: Option<Instant>,
    }

    impl Technique for Slow {
        fn id(&self) -> &'static str {
            "slow"
        }
        fn params(&self) -> serde_json::Value {
            serde_json::Value::Null
        }
        fn set_deadline(&mut self, deadline: Option<Instant>) {
            self.deadline = deadline;
        }
        fn step(&mut self) -> Result<(), EngineError> {
            let k = (self.acc.steps() as usize).min(self.step_times.len() - 1);
            let end = Instant::now() + self.step_times[k];
            while Instant::now() < end {
                if self.deadline.is_some_and(|d| Instant::now() >= d) {
                    return Ok(());
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            self.acc.add(&[Vec3::ONE, Vec3::splat(0.5)], None);
            Ok(())
        }
        fn steps_done(&self) -> u64 {
            self.acc.steps()
        }
        fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
            Ok(self.acc.snapshot())
        }
        fn accumulating_pass(&self) -> &'static str {
            "test pass"
        }
    }

    fn run_slow(step_times: &[u64], seconds: f64) -> (Result<BakeOutcome, EngineError>, Duration) {
        let mut t = Slow {
            acc: HalfAccumulator::new(2, false),
            step_times: step_times.iter().map(|ms| Duration::from_millis(*ms)).collect(),
            deadline: None,
        };
        let stop = StopCriteria {
            seconds: Some(seconds),
            ..Default::default()
        };
        let started = Instant::now();
        let r = BakeLoop::new(stop).run(&mut t, &mut |_: BakeEvent<'_>| ControlFlow::Continue(()));
        (r, started.elapsed())
    }

    /// Issue 19 point 10: a step far longer than the budget does not carry the bake past
    /// it. Two short steps, then one of 20 s under a 0.4 s limit: the bake ends at the
    /// limit (not 20 s later) with the two steps done, stopped by time.
    #[test]
    fn a_long_step_is_cut_short_at_the_limit() {
        let (r, wall) = run_slow(&[20, 20, 20_000], 0.4);
        let out = r.unwrap();
        assert_eq!(out.estimate.steps, 2);
        assert_eq!(out.stopped_by, StopReason::Seconds);
        assert_eq!(out.estimate.total, vec![Vec3::ONE, Vec3::splat(0.5)]);
        assert!(
            wall < Duration::from_secs(3),
            "the bake ran {wall:?} under a 0.4 s limit"
        );
        assert!(out.elapsed >= Duration::from_millis(400), "{:?}", out.elapsed);
    }

    /// A first step that the limit cuts short leaves no samples: the bake fails saying
    /// so, at the limit, rather than delivering a black lightmap.
    #[test]
    fn a_first_step_past_the_limit_fails_at_the_limit() {
        let (r, wall) = run_slow(&[20_000], 0.3);
        let err = r.err().expect("no step was done").to_string();
        assert!(
            err.starts_with("the time limit of 0.300 s ended before the first step of slow was done"),
            "{err}"
        );
        assert!(
            wall < Duration::from_secs(3),
            "the bake ran {wall:?} under a 0.3 s limit"
        );
    }

    /// A technique whose step only queues its work, like a GPU technique's dispatch: the
    /// step returns at once and the device time is paid in `wait_for_steps` (or never,
    /// here, when the loop does not ask).
    struct Queued {
        acc: HalfAccumulator,
        step_time: Duration,
        queued: Duration,
        waits: u32,
    }

    impl Technique for Queued {
        fn id(&self) -> &'static str {
            "queued"
        }
        fn params(&self) -> serde_json::Value {
            serde_json::Value::Null
        }
        fn step(&mut self) -> Result<(), EngineError> {
            self.queued += self.step_time;
            self.acc.add(&[Vec3::ONE, Vec3::splat(0.5)], None);
            Ok(())
        }
        fn wait_for_steps(&mut self) -> Result<(), EngineError> {
            std::thread::sleep(std::mem::take(&mut self.queued));
            self.waits += 1;
            Ok(())
        }
        fn steps_done(&self) -> u64 {
            self.acc.steps()
        }
        fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
            Ok(self.acc.snapshot())
        }
        fn accumulating_pass(&self) -> &'static str {
            "test pass"
        }
    }

    /// Under a time limit the loop waits for each step's device work before timing it, so
    /// steps of 150 ms queued without waiting are seen as 150 ms long: under a 0.5 s limit
    /// the bake stops after 3 steps (3 × 150 + 150 > 500), where a loop that timed only the
    /// submissions would have gone on until some other limit. Without a time limit the
    /// loop does not wait between steps; either way it waits once before its clock starts
    /// (preparation's queued work).
    #[test]
    fn queued_steps_are_timed_with_their_device_work() {
        let mut t = Queued {
            acc: HalfAccumulator::new(2, false),
            step_time: Duration::from_millis(150),
            queued: Duration::ZERO,
            waits: 0,
        };
        let stop = StopCriteria {
            seconds: Some(0.5),
            steps: Some(1000),
            ..Default::default()
        };
        let out = BakeLoop::new(stop)
            .run(&mut t, &mut |_: BakeEvent<'_>| ControlFlow::Continue(()))
            .unwrap();
        assert_eq!((out.stopped_by, out.estimate.steps), (StopReason::Seconds, 3));
        assert_eq!(t.waits, 1 + 3);
        assert!(out.elapsed >= Duration::from_millis(450), "{:?}", out.elapsed);

        let mut t = Queued {
            acc: HalfAccumulator::new(2, false),
            step_time: Duration::from_millis(150),
            queued: Duration::ZERO,
            waits: 0,
        };
        let stop = StopCriteria {
            steps: Some(10),
            ..Default::default()
        };
        let out = BakeLoop::new(stop)
            .run(&mut t, &mut |_: BakeEvent<'_>| ControlFlow::Continue(()))
            .unwrap();
        assert_eq!(
            (out.stopped_by, out.estimate.steps, t.waits),
            (StopReason::Steps, 10, 1)
        );
    }

    /// The guard reads every layer a snapshot holds, not only `total` (issue 21).
    #[test]
    fn the_guard_reads_every_layer() {
        let mut t = Fixed {
            acc: HalfAccumulator::new(2, false),
            value: Vec3::ONE,
        };
        t.step().unwrap();
        t.step().unwrap();
        let clean = t.snapshot().unwrap().estimate();
        assert_eq!(clean.first_non_finite(), None);
        let mut sh = clean.clone();
        sh.moments = Some(vec![[Vec3::ZERO, Vec3::new(0.0, f32::NAN, 0.0), Vec3::ZERO]; 2]);
        let mut ao = clean.clone();
        ao.ao = Some(vec![0.5, f32::INFINITY]);
        let mut direct = clean.clone();
        direct.direct = Some(vec![Vec3::ONE, Vec3::NAN]);
        for (e, layer, texel) in [(sh, "sh", 0), (ao, "ao", 1), (direct, "direct", 1)] {
            let (l, k, _) = e.first_non_finite().unwrap();
            assert_eq!((l, k), (layer, texel));
            let err = check_finite(&t, &e).unwrap_err().to_string();
            assert!(err.contains(&format!("at texel {texel} of the {layer} layer")), "{err}");
        }
    }

    #[test]
    fn stops_on_steps_and_on_zero_error() {
        let out = run(
            Vec3::ONE,
            StopCriteria {
                steps: Some(5),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!((out.stopped_by, out.estimate.steps), (StopReason::Steps, 5));
        // Constant values have zero error: a target error is met at the first snapshot
        // after the minimum number of steps.
        let out = run(
            Vec3::ONE,
            StopCriteria {
                target_error: Some(0.01),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(out.stopped_by, StopReason::TargetError);
        assert_eq!(out.estimate.steps, MIN_STEPS_FOR_TARGET_ERROR);
    }

    #[test]
    fn cancel_stops_within_one_step() {
        let mut t = Fixed {
            acc: HalfAccumulator::new(2, false),
            value: Vec3::ONE,
        };
        let stop = StopCriteria {
            steps: Some(1000),
            ..Default::default()
        };
        let mut observer = |e: BakeEvent<'_>| match e {
            BakeEvent::Progress { steps, .. } if steps >= 3 => ControlFlow::Break(()),
            _ => ControlFlow::Continue(()),
        };
        let out = BakeLoop::new(stop).run(&mut t, &mut observer).unwrap();
        assert_eq!((out.stopped_by, out.estimate.steps), (StopReason::Cancelled, 3));
    }

    /// Steps of 40 ms under a 0.3 s budget: the loop stops when one more step would end
    /// past it, so it ends before 0.3 s (plus scheduling jitter), after several steps.
    #[test]
    fn time_budget_is_kept_by_predicting_the_next_step() {
        struct Slow(Fixed);
        impl Technique for Slow {
            fn id(&self) -> &'static str {
                "slow"
            }
            fn params(&self) -> serde_json::Value {
                serde_json::Value::Null
            }
            fn step(&mut self) -> Result<(), EngineError> {
                std::thread::sleep(Duration::from_millis(40));
                self.0.step()
            }
            fn steps_done(&self) -> u64 {
                self.0.steps_done()
            }
            fn snapshot(&mut self) -> Result<Snapshot, EngineError> {
                self.0.snapshot()
            }
            fn accumulating_pass(&self) -> &'static str {
                "test pass"
            }
        }
        let mut t = Slow(Fixed {
            acc: HalfAccumulator::new(2, false),
            value: Vec3::ONE,
        });
        let stop = StopCriteria {
            seconds: Some(0.3),
            ..Default::default()
        };
        let out = BakeLoop::new(stop)
            .run(&mut t, &mut |_: BakeEvent<'_>| ControlFlow::Continue(()))
            .unwrap();
        assert_eq!(out.stopped_by, StopReason::Seconds);
        assert!(out.estimate.steps >= 3, "{} steps", out.estimate.steps);
        // Without prediction the loop would run its 8th step to 0.32 s.
        assert!(out.elapsed.as_secs_f64() < 0.3 + 0.015, "{:?}", out.elapsed);
    }
}
