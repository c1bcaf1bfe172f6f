//! The bake loop: steps a technique until a stop criterion holds, reporting progress and
//! snapshots to an observer (the CLI's progress bar, the service's event stream).
//!
//! How: snapshots cost a GPU readback, so they are taken on a schedule rather than every
//! step: at steps 2, 4, 8, … (so early previews come quickly) and at least every
//! `snapshot_interval` seconds after that, and always at the end. A target error is
//! checked at each snapshot, since the error needs both halves' means.
//!
//! Limits: the time limit is checked between steps, so one long step can overrun it.

use std::ops::ControlFlow;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::engine::accumulate::Estimate;
use crate::engine::technique::{EngineError, Technique};

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

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
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
    /// Longest time between snapshots once the doubling schedule has thinned out.
    pub snapshot_interval: Duration,
}

impl BakeLoop {
    pub fn new(stop: StopCriteria) -> Self {
        BakeLoop {
            stop,
            snapshot_interval: Duration::from_secs(5),
        }
    }

    pub fn run(
        &self,
        technique: &mut dyn Technique,
        observer: &mut dyn BakeObserver,
    ) -> Result<BakeOutcome, EngineError> {
        self.stop.validate()?;
        let start = Instant::now();
        let mut last_snapshot = start;
        let mut next_doubling = 2u64;
        loop {
            technique.step()?;
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
            let by_time = self.stop.seconds.is_some_and(|s| elapsed.as_secs_f64() >= s);
            let scheduled = steps >= next_doubling || last_snapshot.elapsed() >= self.snapshot_interval;
            if !(cancelled || by_steps || by_time || scheduled) {
                continue;
            }
            if steps >= next_doubling {
                next_doubling = steps.saturating_mul(2);
            }
            last_snapshot = Instant::now();
            let estimate = technique.snapshot()?.estimate();
            let by_error = match (self.stop.target_error, estimate.error.relative) {
                (Some(target), Some(err)) => err <= target,
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
