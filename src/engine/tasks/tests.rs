//! The split's shapes and step ranges, the task result's file, and the merges: exact
//! against a single bake where they claim to be, and refusing what is not one request's.

use std::ops::Range;

use glam::Vec3;
use serde_json::Value;

use super::merge::{close_ambient, merge_ao, merge_control};
use super::*;
use crate::engine::accumulate::{HalfEstimate, Snapshot};
use crate::engine::ambient::{AmbientHalf, AmbientSums};

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
