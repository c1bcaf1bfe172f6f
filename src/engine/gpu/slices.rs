//! Steps cut into slices of invocations, so that a deadline or a cancel is seen within a
//! slice of a step and a step stopped there is undone (issue 19 point 10: one step of a
//! large level is a pass over millions of texels, seconds to minutes on a software
//! adapter).
//!
//! What a technique gives [`StepSlicer::run`]: how many invocations its per-texel pass
//! has, the buffer ranges the pass writes (the half of the step's parity in each
//! accumulator, plus any state a later step reads), and a function that submits the pass
//! over invocations `first .. first + count`. The slicer copies those ranges aside, runs
//! the slices one by one, waits for each and asks `go_on(done, of)` between them; when
//! `go_on` says stop it copies the ranges back, so the step leaves the device as it found
//! it. Sliced or whole, a pass whose invocations each write only their own texel's slots
//! writes the same values bit for bit. The technique undoes its own host-side
//! bookkeeping (step counts, random streams) when told [`Sliced::Abandoned`].
//!
//! Policy ([`StepSlicer::slices`]): a step is sliced only in a bake that has a deadline
//! or a watcher that may cancel, and only while steps may be long: the first step (its
//! length not known yet) and any after a step of [`LONG_STEP`] or more. Shorter steps run
//! whole, so they keep their pipelining and pay no copy.
//!
//! Slice sizes: the first is [`FIRST_SLICE`] invocations, small, because one invocation
//! can be long and a pipeline's first dispatch on llvmpipe includes its compilation; the
//! next are sized from the last one's rate to [`SLICE_SECONDS`], growing at most 8x a
//! slice. Costs: one copy of each range a step (aside), a wait a slice (well under a
//! millisecond on hardware drivers and on llvmpipe), and one more buffer the size of the
//! ranges, made on first use.
//!
//! This is hand-written rather than taken from a crate because it is a policy over our
//! own passes' buffers; wgpu offers the pieces (copies, submission indices, polling).

use std::time::{Duration, Instant};

use super::{GpuContext, GpuError};

/// How a sliced step ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sliced {
    /// Every slice ran: the step counts.
    Done,
    /// `go_on` said stop between two slices: the ranges are as they were before the step.
    Abandoned,
}

/// A step at least this long is sliced in a watched bake ([`StepSlicer::slices`]): a
/// deadline or a cancel is then kept to about a slice (50 ms), and shorter steps keep the
/// pipelining of whole dispatches.
pub const LONG_STEP: Duration = Duration::from_millis(250);

/// What a slice aims to take: short enough for a deadline or a cancel to be seen within
/// it, long enough that waiting for each costs little.
pub const SLICE_SECONDS: f64 = 0.05;

/// The first slice's invocations, before any has been timed: small, because one
/// invocation may be long (`path` at 64 samples a texel in a 63,720-triangle room on
/// llvmpipe: a first slice of 4096 texels took seconds).
pub const FIRST_SLICE: u64 = 256;

/// A range of a buffer that a step writes and a stopped step must put back.
#[derive(Clone, Copy)]
pub struct Aside<'a> {
    pub buffer: &'a wgpu::Buffer,
    pub offset: u64,
    pub size: u64,
}

impl<'a> Aside<'a> {
    /// Half `half` (0 or 1) of a buffer that holds the two halves one after the other.
    pub fn half(buffer: &'a wgpu::Buffer, half: usize) -> Self {
        let size = buffer.size() / 2;
        Aside {
            buffer,
            offset: half as u64 * size,
            size,
        }
    }

    /// The whole buffer.
    pub fn whole(buffer: &'a wgpu::Buffer) -> Self {
        Aside {
            buffer,
            offset: 0,
            size: buffer.size(),
        }
    }
}

/// One pass's slicing state: the copies aside, and how long its last step took.
pub struct StepSlicer {
    label: String,
    /// The first slice's invocations and the smallest slice after it.
    first_slice: u64,
    min_slice: u64,
    /// Size slices from the slowest unit seen in the step rather than the last slice:
    /// for units that differ (a part of a scene's layers, a gather, a sun's map).
    by_slowest: bool,
    backups: Vec<wgpu::Buffer>,
    /// A sliced step's own time, or the time between two returns of whole steps (in a
    /// bake with a time limit the loop waits for the device after each step, and
    /// [`TexelRayPass`](super::texel_pass::TexelRayPass) waits while two are in flight, so
    /// that is a step's length); None before the first and after [`StepSlicer::forget`].
    last_step: Option<Duration>,
    returned: Option<Instant>,
}

impl StepSlicer {
    /// `label` names the pass in the copies' labels and in errors.
    pub fn new(label: &str) -> Self {
        StepSlicer {
            label: label.to_string(),
            first_slice: FIRST_SLICE,
            min_slice: 64,
            by_slowest: false,
            backups: Vec::new(),
            last_step: None,
            returned: None,
        }
    }

    /// A slicer whose "invocations" are coarse units of a step, not alike (`obscurance`'s
    /// parts of the depth layers, its gather and its sun's map; `vpl`'s sun map and its
    /// VPLs' maps): the first slice is one unit, a slice is never less than one, and
    /// slices are sized from the slowest unit seen in the step (measured: after seven
    /// 0.03 s parts of a 1M-triangle level's layers, sizing from the last took the gather
    /// and the sun's map, 0.93 s, in one slice).
    pub fn per_unit(label: &str) -> Self {
        StepSlicer {
            first_slice: 1,
            min_slice: 1,
            by_slowest: true,
            ..StepSlicer::new(label)
        }
    }

    /// Whether the next step runs sliced: `watched` (a deadline or a watcher that may
    /// cancel) and its length unknown or last seen at [`LONG_STEP`] or more.
    pub fn slices(&self, watched: bool) -> bool {
        watched && self.last_step.is_none_or(|d| d >= LONG_STEP)
    }

    /// A whole step has returned: times it from the last return.
    pub fn returned_whole(&mut self) {
        let now = Instant::now();
        if let Some(before) = self.returned.replace(now) {
            self.last_step = Some(now - before);
        }
    }

    /// Forgets the last step's length: the next watched step is sliced and timed again
    /// (a new deadline).
    pub fn forget(&mut self) {
        self.last_step = None;
        self.returned = None;
    }

    /// One step of `n` invocations in slices (see the module doc): `aside` is copied
    /// aside first, `submit(first, count)` submits one slice, `go_on(done, n)` is asked
    /// after every slice but the last (and told `(n, n)` after it). On a stop the ranges
    /// are copied back and waited for before this returns [`Sliced::Abandoned`].
    pub fn run(
        &mut self,
        ctx: &GpuContext,
        n: u64,
        aside: &[Aside<'_>],
        submit: &mut dyn FnMut(u64, u64) -> Result<wgpu::SubmissionIndex, GpuError>,
        go_on: &mut dyn FnMut(u64, u64) -> bool,
    ) -> Result<Sliced, GpuError> {
        let t0 = Instant::now();
        let both = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        if let Some(a) = aside.iter().find(|a| a.size >= 16 && !a.buffer.usage().contains(both)) {
            // Without this the copy back fails only when a step is stopped, as a device
            // error about a submission, far from its cause.
            return Err(GpuError::Device {
                during: self.label.clone(),
                message: format!(
                    "a range put aside for a sliced step is in a buffer without COPY_SRC and COPY_DST ({:?})",
                    a.buffer.usage()
                ),
            });
        }
        if self.backups.len() != aside.len() || self.backups.iter().zip(aside).any(|(b, a)| b.size() < a.size) {
            let usage = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
            self.backups = aside
                .iter()
                .enumerate()
                .map(|(i, a)| {
                    ctx.buffer_zeroed(
                        &format!("{} (range {i} aside for a sliced step)", self.label),
                        a.size.max(16).next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
                        usage,
                    )
                })
                .collect();
        }
        self.copy(ctx, aside, true);
        let mut first = 0u64;
        let mut slice = self.first_slice.min(n.max(1));
        let mut slowest = 0.0f64;
        while first < n {
            let count = slice.min(n - first);
            let t = Instant::now();
            let submitted = submit(first, count)?;
            ctx.wait_for(&self.label, submitted)?;
            ctx.take_error(&self.label)?;
            let took = t.elapsed().as_secs_f64();
            tracing::trace!(pass = %self.label, first, count, of = n, seconds = took, "slice");
            first += count;
            if first < n && !go_on(first, n) {
                let undone = self.copy(ctx, aside, false);
                ctx.wait_for(&self.label, undone)?;
                self.last_step = Some(t0.elapsed());
                self.returned = None;
                return Ok(Sliced::Abandoned);
            }
            let per_unit = took / count as f64;
            slowest = slowest.max(per_unit);
            let seconds_each = if self.by_slowest { slowest } else { per_unit };
            // At most eight times the slice just timed, never below the least slice: a
            // short last-but-one slice (count * 8 < min_slice) made `clamp` panic with
            // min > max (seen once in CI, `tests/sdb.rs`, 2026-12-06).
            slice = ((SLICE_SECONDS / seconds_each.max(1e-9)) as u64)
                .clamp(self.min_slice, (count * 8).max(self.min_slice));
        }
        go_on(n, n);
        self.last_step = Some(t0.elapsed());
        self.returned = None;
        Ok(Sliced::Done)
    }

    /// Puts `aside` back as it was before the last [`StepSlicer::run`] that ended
    /// [`Sliced::Done`] (its copies aside are kept until the next run), and waits for it:
    /// for a step whose later part was stopped after this part had finished. `aside` must
    /// be the ranges given to that run.
    pub fn put_back(&self, ctx: &GpuContext, aside: &[Aside<'_>]) -> Result<(), GpuError> {
        if self.backups.len() != aside.len() {
            return Err(GpuError::Device {
                during: self.label.clone(),
                message: "putting back a step that was not run sliced".into(),
            });
        }
        let undone = self.copy(ctx, aside, false);
        ctx.wait_for(&self.label, undone)
    }

    /// Copies `aside` to the copies aside (`to_backup`) or back.
    fn copy(&self, ctx: &GpuContext, aside: &[Aside<'_>], to_backup: bool) -> wgpu::SubmissionIndex {
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some(&format!("{}: ranges aside", self.label)),
        });
        for (a, backup) in aside.iter().zip(&self.backups) {
            // A placeholder binding (one vec4) holds no texels.
            if a.size < 16 {
                continue;
            }
            if to_backup {
                enc.copy_buffer_to_buffer(a.buffer, a.offset, backup, 0, a.size);
            } else {
                enc.copy_buffer_to_buffer(backup, 0, a.buffer, a.offset, a.size);
            }
        }
        ctx.queue.submit([enc.finish()])
    }
}
