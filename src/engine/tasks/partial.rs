//! A task's result ([`Partial`]): its header ([`PartialHeader`]: the request, the task,
//! the texel set's fingerprint, what it keeps), its halves, its texels' pixels and what
//! its technique adds, and the file that carries it (`.lmtask`: an 8-byte magic, the
//! JSON header's length and the header, then little-endian f32 arrays per valid texel;
//! docs/scaling.md, "The task result file"). [`PartialLayout`] places every part from the
//! header alone, so a reader may fetch only the parts it needs (a round task reads the
//! other regions' pixels and held light).

use std::ops::Range;
use std::time::Duration;

use glam::Vec3;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::engine::accumulate::{HalfEstimate, Snapshot};
use crate::engine::ambient::{AmbientHalf, AmbientSums};
use crate::engine::bake::StopReason;
use crate::engine::job::BakeRequest;
use crate::engine::technique::EngineError;

use super::TaskRange;

/// The format version a [`Partial`] file carries; a merge refuses others. 2: tasks carry
/// their region (format 1 had step ranges only, and path streams keyed by texel index).
/// 3: chains (`TaskRange::chain`), with their control texels' reference and their `ao`
/// layer. 4: a technique's scene-wide ambient (`ambient`), and `sdf`'s and the shared
/// direct light's streams keyed by pixel.
pub const PARTIAL_FORMAT: u32 = 4;

const MAGIC: &[u8; 8] = b"LMDTASK1";

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
    /// closes over every region (`merge::close_ambient`).
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

    pub(super) fn snapshot(&self) -> Snapshot {
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
    /// A running task's halves so far ([`bake_task_live`](super::bake_task_live)), for the job's snapshots: never
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
    pub(super) fn with_halves(
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
    /// has no `ao` or `ambient` layer. [`merge`](super::merge()) refuses such a result, and a round task
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
