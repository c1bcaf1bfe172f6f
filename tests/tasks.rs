//! A bake split into tasks (issue 25, `engine::tasks`): the merged tasks are the single
//! bake, not another bake within noise. `path` on the CPU and on the GPU (lavapipe in
//! CI): every half, layer and the error estimate of three merged step ranges equal the
//! whole bake's to float rounding; split by regions (the pages of a two-page scene, or
//! tiles of one page) they equal it bit for bit on the CPU, and to rounding combined
//! with step ranges and on the GPU; the command line does the same with three processes
//! at once; and the merge refuses what is not every task of one request on this scene.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use glam::Vec3;
use lightmapd::engine::accumulate::{Estimate, LUMINANCE};
use lightmapd::engine::bake::{BakeEvent, StopCriteria};
use lightmapd::engine::job::{self, BakeOptions, BakeRequest};
use lightmapd::engine::output::OutputLayer;
use lightmapd::engine::post::denoised::Denoiser;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder, remove_lightmap_uvs, write_glb};
use lightmapd::engine::scene::library::sphere_over_plane;
use lightmapd::engine::scene::{self, Hemisphere, Scene, Sky};
use lightmapd::engine::tasks::{self, Partial, TaskShape};

fn cornell() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.glb")
}

fn scene() -> Arc<Scene> {
    Arc::new(scene::import_file(&cornell()).expect("bundled scene").0)
}

fn request(device: &str, steps: u64) -> BakeRequest {
    BakeRequest {
        technique: "path".into(),
        resolution: 20,
        stop: StopCriteria {
            steps: Some(steps),
            seconds: None,
            target_error: None,
        },
        params: serde_json::json!({"device": device, "samples_per_step": 2}),
        outputs: vec![OutputLayer::Direct, OutputLayer::Sh],
        seed: 11,
        denoise: Denoiser::None,
        ..BakeRequest::default()
    }
}

fn bake_tasks(scene: &Arc<Scene>, request: &BakeRequest, shape: TaskShape) -> Vec<Partial> {
    tasks::split(request, shape)
        .unwrap()
        .into_iter()
        .map(|t| {
            let p = tasks::bake_task(
                scene.clone(),
                request,
                t,
                &BakeOptions::default(),
                &mut |_: BakeEvent<'_>| std::ops::ControlFlow::Continue(()),
                &mut |_| {},
                &mut |_| {},
            )
            .unwrap();
            // Through the file format, as a farm moves them.
            Partial::decode(&p.encode().unwrap(), "task").unwrap()
        })
        .collect()
}

/// Largest difference between two layers over the RMS luminance of the first.
fn worst(a: &[Vec3], b: &[Vec3]) -> f64 {
    assert_eq!(a.len(), b.len());
    let rms = (a.iter().map(|v| (v.dot(LUMINANCE) as f64).powi(2)).sum::<f64>() / a.len() as f64).sqrt();
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x - *y).abs().max_element() as f64)
        .fold(0.0, f64::max)
        / rms
}

fn assert_same_bake(whole: &Estimate, merged: &Estimate) {
    assert_eq!(merged.steps, whole.steps);
    let ([we, wo], wn) = whole.halves.clone().unwrap();
    let ([me, mo], mn) = merged.halves.clone().unwrap();
    assert_eq!(mn, wn, "half step counts");
    for (name, d) in [
        ("even half", worst(&we, &me)),
        ("odd half", worst(&wo, &mo)),
        ("total", worst(&whole.total, &merged.total)),
        (
            "direct",
            worst(whole.direct.as_ref().unwrap(), merged.direct.as_ref().unwrap()),
        ),
        (
            "sh",
            worst(
                whole.moments.as_ref().unwrap().as_flattened(),
                merged.moments.as_ref().unwrap().as_flattened(),
            ),
        ),
    ] {
        // f32 rounding of a different order of additions, nothing more (a different
        // random stream would differ by the noise, ~10 % at 8 samples a texel).
        assert!(
            d < 1e-5,
            "{name}: merged differs from the whole bake by {d:e} of the RMS"
        );
    }
    let (we, me) = (whole.error.relative.unwrap(), merged.error.relative.unwrap());
    assert!(we > 0.01, "the bake has noise to measure: {we}");
    assert!(
        (me / we - 1.0).abs() < 1e-4,
        "merged error estimate {me} vs the whole bake's {we}"
    );
}

fn whole(scene: &Arc<Scene>, request: &BakeRequest) -> Estimate {
    job::bake_unobserved(scene.clone(), request).unwrap().estimate
}

#[test]
fn three_cpu_tasks_merge_to_the_single_bake() {
    let scene = scene();
    let request = request("cpu", 9);
    let parts = bake_tasks(&scene, &request, TaskShape::steps(3));
    assert_eq!(parts.iter().map(|p| p.header.task.steps).collect::<Vec<_>>(), [4, 2, 3]);
    let merged = tasks::merge(scene.clone(), &parts, &BakeOptions::default(), &mut |_| {}).unwrap();
    assert_eq!(merged.summary.steps, 9);
    assert_same_bake(&whole(&scene, &request), &merged.estimate);
    // Any order of task results merges alike.
    let mut reversed = parts.clone();
    reversed.reverse();
    let again = tasks::merge(scene, &reversed, &BakeOptions::default(), &mut |_| {}).unwrap();
    assert_eq!(again.estimate.total, merged.estimate.total);
}

fn sky() -> Sky {
    Sky {
        radiance: Vec3::ONE,
        hemisphere: Hemisphere::Upper,
    }
}

/// The sphere over a plane with the ball's lightmap UVs removed: the ground keeps its
/// authored page, the ball gets a generated one (two pages, 40² each here).
fn two_pages() -> Arc<Scene> {
    let (mut doc, bin) = sphere_over_plane().to_gltf();
    remove_lightmap_uvs(&mut doc, Some(&[1]));
    Arc::new(scene::import_slice(&write_glb(&doc, &bin), None).unwrap().0)
}

/// A 4 m floor with a 1 m box standing on it: the floor's texels under the box lie
/// inside geometry, and texel validation drops them.
fn box_on_floor() -> Arc<Scene> {
    let mut b = SceneBuilder::new();
    let m = b.material(MaterialDesc::diffuse("grey", [0.5; 3]));
    b.square("floor", Vec3::ZERO, 4.0, Vec3::Y, m);
    b.block("box", Vec3::ZERO, Vec3::splat(0.5), 0.0, m);
    Arc::new(scene::import_slice(&b.to_glb(), None).unwrap().0)
}

/// Regions alone: the pages of a two-page scene, four tiles of the Cornell box's one
/// page, three tiles of a floor whose texels under a box validation drops (each task
/// validates only its region's texels), each baked over every step: the merge is the
/// single bake bit for bit (the same samples per texel, added in the same order).
#[test]
fn page_and_tile_tasks_merge_to_the_single_bake_exactly() {
    for (scene, regions, what) in [
        (two_pages(), 2, "pages"),
        (scene(), 4, "tiles"),
        (box_on_floor(), 3, "tiles over dropped texels"),
    ] {
        let mut request = request("cpu", 4);
        request.resolution = if what == "tiles" { 20 } else { 40 };
        request.lighting.sky = Some(sky());
        let parts = bake_tasks(
            &scene,
            &request,
            TaskShape {
                tasks: regions,
                regions,
            },
        );
        let texels: Vec<u64> = parts.iter().map(|p| p.header.texels).collect();
        let merged = tasks::merge(scene.clone(), &parts, &BakeOptions::default(), &mut |_| {}).unwrap();
        let whole = whole(&scene, &request);
        assert_eq!(texels.iter().sum::<u64>() as usize, whole.total.len(), "{what}");
        assert!(texels.iter().all(|&n| n > 0), "{what}: {texels:?}");
        if what == "tiles over dropped texels" {
            let dropped = merged.summary.validation.inside_geometry_texels;
            assert!(dropped > 0, "{what}: {dropped} texels dropped");
        }
        if what == "pages" {
            assert_eq!(merged.summary.atlas.pages, 2);
            // Each region is one page: the ground's and the ball's texel counts differ.
            assert_ne!(texels[0], texels[1], "{texels:?}");
        }
        assert_eq!(merged.estimate.halves, whole.halves, "{what}: halves");
        assert_eq!(merged.estimate.total, whole.total, "{what}");
        assert_eq!(merged.estimate.moments, whole.moments, "{what}");
        assert_eq!(merged.estimate.error.relative, whole.error.relative, "{what}");
    }
}

/// A region's task builds only its region's texels (`Atlas::build_pixels`), cut from the
/// grid's coverage (one bit a pixel): the same cut as the whole atlas's, and the same
/// texels, pixel for pixel, as the whole atlas narrowed to the region. Two pages (the
/// ground's authored one and the ball's generated one), cut into 1 to 7 regions (pages,
/// then tiles across them), and the Cornell box's one page into 1 to 5 tiles.
#[test]
fn a_region_built_alone_is_the_whole_atlas_narrowed() {
    use lightmapd::engine::atlas::Atlas;
    use lightmapd::engine::atlas::unwrap::{UvUnwrap, generate_lightmap_uvs_paged};
    let mut paged = (*two_pages()).clone();
    generate_lightmap_uvs_paged(&mut paged, 40, 40, Default::default(), None, &UvUnwrap).unwrap();
    let layout = paged.layout.clone().expect("a paged layout");
    let cornell = (*scene()).clone();
    for (scene, width, height, counts) in [
        (&paged, layout.width, layout.height, 1..=7u32),
        (&cornell, 20, 20, 1..=5),
    ] {
        let whole = Atlas::build(scene, width, height).unwrap();
        let coverage = Atlas::coverage(scene, width, height).unwrap();
        assert_eq!(coverage.texels(), whole.texels.len());
        assert_eq!(coverage.pages.len(), whole.pages.len());
        for count in counts {
            let pixels = whole.region_pixels(count).unwrap();
            assert_eq!(coverage.region_pixels(count).unwrap(), pixels, "{count} regions");
            for range in pixels {
                let narrowed = whole.region(whole.texels_in(range.clone()));
                let alone = Atlas::build_pixels(scene, width, height, range.clone()).unwrap();
                assert_eq!(
                    format!("{:?}", alone.texels),
                    format!("{:?}", narrowed.texels),
                    "{count} regions, pixels {range:?}"
                );
                assert_eq!(alone.pixel_texel, narrowed.pixel_texel);
                // Its pixel index covers its own pixels, not the whole grid's.
                let window = alone.pixel_texel.window();
                assert_eq!(window, range.start as usize..range.end as usize);
                for t in &alone.texels {
                    assert_eq!(
                        alone.texels[alone.pixel_texel[t.pixel as usize] as usize].pixel,
                        t.pixel
                    );
                }
                assert_eq!(alone.pixel_texel[window.end], lightmapd::engine::atlas::NO_TEXEL);
                assert_eq!(
                    (alone.pages.len(), alone.surface_offset),
                    (narrowed.pages.len(), narrowed.surface_offset)
                );
            }
        }
    }
    assert!(layout.pages.len() >= 2, "{} pages", layout.pages.len());
}

/// Regions times step ranges: the two pages, each as three step ranges (6 tasks).
#[test]
fn pages_times_step_ranges_merge_to_the_single_bake() {
    let scene = two_pages();
    let mut request = request("cpu", 9);
    request.resolution = 40;
    request.lighting.sky = Some(sky());
    let parts = bake_tasks(&scene, &request, TaskShape { tasks: 6, regions: 2 });
    let regions: Vec<u32> = parts.iter().map(|p| p.header.task.region).collect();
    assert_eq!(regions, [0, 0, 0, 1, 1, 1]);
    // Task results arrive in any order.
    let mut shuffled = parts.clone();
    shuffled.rotate_left(2);
    let merged = tasks::merge(scene.clone(), &shuffled, &BakeOptions::default(), &mut |_| {}).unwrap();
    assert_same_bake(&whole(&scene, &request), &merged.estimate);
}

#[test]
fn three_gpu_tasks_merge_to_the_single_bake() {
    if !common::have_adapter() {
        return;
    }
    let scene = scene();
    let request = request("gpu", 8);
    let parts = bake_tasks(&scene, &request, TaskShape::steps(3));
    assert_eq!(parts[0].header.params["device"], "gpu");
    let merged = tasks::merge(scene.clone(), &parts, &BakeOptions::default(), &mut |_| {}).unwrap();
    let single = whole(&scene, &request);
    assert_same_bake(&single, &merged.estimate);
    // Tiles on the GPU: its streams are keyed by pixel too (position.w's bits).
    let tiles = bake_tasks(&scene, &request, TaskShape { tasks: 4, regions: 2 });
    let merged = tasks::merge(scene.clone(), &tiles, &BakeOptions::default(), &mut |_| {}).unwrap();
    assert_same_bake(&single, &merged.estimate);
}

/// RMS of the luminance difference of two layers over the RMS luminance of the first.
fn rms_difference(a: &[Vec3], b: &[Vec3]) -> f64 {
    let ms = |v: &mut dyn Iterator<Item = f64>| v.map(|x| x * x).sum::<f64>() / a.len() as f64;
    let rms = ms(&mut a.iter().map(|v| v.dot(LUMINANCE) as f64)).sqrt();
    ms(&mut a.iter().zip(b).map(|(x, y)| (*x - *y).dot(LUMINANCE) as f64)).sqrt() / rms
}

/// Every technique but path splits into independent chains (engine::tasks): three
/// chains of 4 steps, each with its own seed, merge to a bake of 12 steps. Not the single
/// bake's samples, so the merge is compared with it within what both say their error is
/// (bias and noise, measured at control texels against path, the chains' references
/// merged); the merged halves are the chains' halves averaged by steps, exactly.
#[test]
fn chains_of_every_other_technique_merge_within_the_stated_error() {
    let _gpu = common::gpu_serial();
    let scene = Arc::new(scene::import_slice(&sphere_over_plane().to_glb(), None).unwrap().0);
    for technique in ["vpl", "sdf", "obscurance", "sdb", "hemicube"] {
        let mut request = request("cpu", 12);
        request.resolution = 40;
        request.technique = technique.into();
        request.params = serde_json::Value::Null;
        request.lighting.sky = Some(sky());
        request.outputs = vec![OutputLayer::Direct];
        let parts = bake_tasks(&scene, &request, TaskShape::steps(3));
        // Each chain bakes its 4 steps; the halves count what the technique keeps (sdb
        // leaves its first, bootstrap step out of them, in every chain).
        let kept = |p: &Partial| p.header.half_steps[0] + p.header.half_steps[1];
        assert!(
            parts
                .iter()
                .all(|p| p.header.task.steps == 4 && (3..=4).contains(&kept(p))),
            "{technique}"
        );
        // Distinct seeds: the chains are different bakes, with the same parameters (sdf's
        // calibration, from the job's seed, included) and the same control texels.
        assert_ne!(
            parts[0].snapshot.even.total, parts[1].snapshot.even.total,
            "{technique}"
        );
        assert!(
            parts.iter().all(|p| p.header.params == parts[0].header.params),
            "{technique}"
        );
        let control = |p: &Partial| p.header.control.as_ref().map(|c| c.texels.clone());
        let texels = parts[0].header.texels as usize;
        assert!(
            control(&parts[0]).is_some_and(|t| t.len() == 256.min(texels)),
            "{technique}"
        );
        assert!(parts.iter().all(|p| control(p) == control(&parts[0])), "{technique}");
        let merged = tasks::merge(scene.clone(), &parts, &BakeOptions::default(), &mut |_| {}).unwrap();
        let m = &merged.estimate;
        let ([even, odd], n) = m.halves.clone().unwrap();
        let sum = |h: usize| parts.iter().map(|p| p.header.half_steps[h]).sum::<u64>();
        assert_eq!(n, [sum(0), sum(1)], "{technique}");
        assert_eq!(merged.summary.steps, sum(0) + sum(1), "{technique}");
        for (k, half) in [(0usize, &even), (1, &odd)] {
            let mean = |i: usize| {
                parts
                    .iter()
                    .map(|p| [&p.snapshot.even, &p.snapshot.odd][k].total[i])
                    .sum::<Vec3>()
                    / 3.0
            };
            assert!(
                worst(half, &(0..half.len()).map(mean).collect::<Vec<_>>()) < 1e-5,
                "{technique}"
            );
        }
        // The merged error: bias measured at the chains' control texels.
        assert_eq!(m.error.control_texels, Some(256.min(texels) as u32), "{technique}");
        let (Some(em), Some(bias)) = (m.error.relative, m.error.bias) else {
            panic!("{technique}: no error estimate {:?}", m.error)
        };
        assert!(bias <= em, "{technique}: bias {bias} over the whole {em}");
        let single = whole(&scene, &request);
        let ew = single.error.relative.unwrap();
        let d = rms_difference(&single.total, &m.total);
        let allowed = 3.0 * ((em * em + ew * ew) as f64).sqrt();
        eprintln!("{technique}: merged {em:.4} (bias {bias:.4}), single {ew:.4}, difference {d:.4}");
        assert!(
            d <= allowed,
            "{technique}: merged differs from a single bake by {d:.4} of the RMS, stated {em:.4} and {ew:.4}"
        );
        if matches!(technique, "obscurance" | "sdf") {
            let ao = m.ao.as_ref().expect("the merged ao layer");
            assert_eq!(ao.len(), m.total.len(), "{technique}");
            let mean: f32 = ao.iter().sum::<f32>() / ao.len() as f32;
            assert!((0.05..1.0).contains(&mean), "{technique}: mean ao {mean}");
        }
    }
}

/// Bakes `task` of `request` handing its halves on at every snapshot: the live halves
/// (through the file format) and the atlas it baked.
fn bake_live(
    scene: &Arc<Scene>,
    request: &BakeRequest,
    task: tasks::TaskRange,
) -> (Vec<Partial>, Partial, Arc<lightmapd::engine::atlas::Atlas>) {
    let got = Arc::new(std::sync::Mutex::new(Vec::new()));
    let sink = got.clone();
    let mut atlas = None;
    let result = tasks::bake_task_live(
        scene.clone(),
        request,
        task,
        &BakeOptions::default(),
        &mut |_: BakeEvent<'_>| std::ops::ControlFlow::Continue(()),
        &mut |a| atlas = Some(a.clone()),
        &mut |_| {},
        Some(tasks::LiveTask {
            every: std::time::Duration::ZERO,
            sink: Box::new(move |p: Partial| sink.lock().unwrap().push(p.encode().unwrap())),
        }),
    )
    .unwrap();
    let live = got
        .lock()
        .unwrap()
        .iter()
        .map(|b| Partial::decode(b, "live halves").unwrap())
        .collect();
    (live, result, atlas.unwrap())
}

/// A split job's snapshots while its tasks run (issue 25 point 2): the running tasks'
/// halves merged are the single bake's at the steps done. `path`'s step ranges draw the
/// single bake's samples, so task 0's halves after 4 steps are the single bake of 4, and
/// task 0's 6 steps with task 1's first 2 (steps 6 and 7) the single bake of 8, halves,
/// layers and error estimate. A running task's halves are never taken as its result.
#[test]
fn running_tasks_merge_to_the_single_bake_at_the_steps_done() {
    let scene = scene();
    let request = request("cpu", 12);
    let split = tasks::split(&request, TaskShape::steps(2)).unwrap();
    let (live0, done0, atlas) = bake_live(&scene, &request, split[0]);
    let (live1, _, atlas1) = bake_live(&scene, &request, split[1]);
    assert_eq!(atlas.texels.len(), atlas1.texels.len());
    // The doubling schedule: snapshots at 2, 4 and the task's end, each handed on.
    let steps = |v: &[Partial]| -> Vec<u64> { v.iter().map(|p| p.header.half_steps.iter().sum()).collect() };
    assert_eq!(steps(&live0), [2, 4, 6]);
    assert_eq!(steps(&live1), [2, 4, 6]);
    assert!(live0.iter().all(|p| p.header.live) && !done0.header.live);
    let at = |n: u64| {
        let mut r = request.clone();
        r.stop.steps = Some(n);
        whole(&scene, &r)
    };
    let whole = 0..atlas.texels.len();
    let all = std::slice::from_ref(&whole);
    let four = tasks::merge_running(&atlas, all, std::slice::from_ref(&live0[1])).unwrap();
    assert_same_bake(&at(4), &four);
    let eight = tasks::merge_running(&atlas, all, &[done0.clone(), live1[0].clone()]).unwrap();
    assert_same_bake(&at(8), &eight);
    // The final merge takes results only, and says which is not one.
    let err = match tasks::merge(
        scene.clone(),
        &[done0.clone(), live1[2].clone()],
        &BakeOptions::default(),
        &mut |_| {},
    ) {
        Ok(_) => panic!("a running task's halves were merged as its result"),
        Err(e) => e.to_string(),
    };
    assert!(
        err.contains("task 1/2) is a running task's halves, not its result"),
        "{err}"
    );
    // A task given twice, or halves of another texel set, are refused by name.
    let err = tasks::merge_running(&atlas, all, &[live0[0].clone(), live0[1].clone()])
        .unwrap_err()
        .to_string();
    assert!(err.contains("task 0/2 is given twice"), "{err}");
    let mut other = request.clone();
    other.resolution = 24;
    let small = tasks::split(&other, TaskShape::steps(2)).unwrap();
    let (_, _, other_atlas) = bake_live(&scene, &other, small[0]);
    let err = tasks::merge_running(
        &other_atlas,
        std::slice::from_ref(&(0..other_atlas.texels.len())),
        &[done0],
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("task 0/2 was baked on another texel set"), "{err}");
}

/// A split by regions: its snapshots need the whole grid's texel set, which no region's
/// task holds; `running_atlas` builds it from the regions' kept texels once every region
/// has halves. The two pages, region 0 after 4 of its 8 steps beside region 1's 8: each
/// region's texels are the single bake's at those steps, bit for bit.
#[test]
fn running_regions_merge_on_the_whole_texel_set() {
    let scene = two_pages();
    let mut request = request("cpu", 8);
    request.resolution = 40;
    request.lighting.sky = Some(sky());
    let split = tasks::split(&request, TaskShape { tasks: 2, regions: 2 }).unwrap();
    let (live0, _, _) = bake_live(&scene, &request, split[0]);
    let (_, done1, _) = bake_live(&scene, &request, split[1]);
    let err = tasks::running_atlas(scene.clone(), std::slice::from_ref(&done1), &BakeOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("region 0 has no halves yet"), "{err}");
    let parts = [live0[1].clone(), done1];
    let (atlas, ranges) = tasks::running_atlas(scene.clone(), &parts, &BakeOptions::default()).unwrap();
    let merged = tasks::merge_running(&atlas, &ranges, &parts).unwrap();
    let at = |n: u64| {
        let mut r = request.clone();
        r.stop.steps = Some(n);
        whole(&scene, &r)
    };
    let (four, eight) = (at(4), at(8));
    assert_eq!(ranges.len(), 2);
    assert_eq!(ranges[1].end, four.total.len());
    assert_eq!(merged.total[ranges[0].clone()], four.total[ranges[0].clone()]);
    assert_eq!(merged.total[ranges[1].clone()], eight.total[ranges[1].clone()]);
    // A half counts the fewest steps any region has, as the final merge's.
    assert_eq!(merged.steps, 4);
    assert!(merged.error.relative.is_some_and(|e| e > 0.0));
}

/// A chained technique's running halves merge with their bias measured: two `vpl` chains'
/// first halves merge to the mean of the two, assessed at the job's control texels.
#[test]
fn running_chains_merge_with_their_bias_measured() {
    let _gpu = common::gpu_serial();
    let scene = Arc::new(scene::import_slice(&sphere_over_plane().to_glb(), None).unwrap().0);
    let mut request = request("cpu", 8);
    request.resolution = 32;
    request.technique = "vpl".into();
    request.params = serde_json::Value::Null;
    request.lighting.sky = Some(sky());
    request.outputs = vec![];
    let split = tasks::split(&request, TaskShape::steps(2)).unwrap();
    let (a, _, atlas) = bake_live(&scene, &request, split[0]);
    let (b, _, _) = bake_live(&scene, &request, split[1]);
    let m = tasks::merge_running(
        &atlas,
        std::slice::from_ref(&(0..atlas.texels.len())),
        &[a[0].clone(), b[0].clone()],
    )
    .unwrap();
    assert_eq!(m.steps, 4);
    let mean: Vec<Vec3> = a[0]
        .snapshot
        .estimate()
        .total
        .iter()
        .zip(&b[0].snapshot.estimate().total)
        .map(|(x, y)| (*x + *y) / 2.0)
        .collect();
    assert!(worst(&mean, &m.total) < 1e-5);
    let texels = atlas.texels.len().min(256) as u32;
    assert_eq!(m.error.control_texels, Some(texels), "{:?}", m.error);
    let (Some(e), Some(bias), Some(noise)) = (m.error.relative, m.error.bias, m.error.noise) else {
        panic!("no bias measured: {:?}", m.error)
    };
    assert!(bias <= e && noise <= e && e > 0.0, "{:?}", m.error);
}

/// vpl splits by region as well (`TaskSplit::ChainsAndRegions`): the two pages as two
/// tasks with the job's seed are the single bake's texels bit for bit (the VPLs come from
/// the scene and the seed alone, and the normalised frame is the scene's); each region
/// measures its bias at its own control texels, which the merge joins. Two pages × two
/// chains merge within the stated errors.
#[test]
fn vpl_pages_are_the_single_bakes_pages() {
    let _gpu = common::gpu_serial();
    let scene = two_pages();
    let mut request = request("cpu", 8);
    request.technique = "vpl".into();
    request.resolution = 40;
    request.params = serde_json::Value::Null;
    request.lighting.sky = Some(sky());
    request.outputs = vec![OutputLayer::Direct];
    let single = whole(&scene, &request);
    let pages = bake_tasks(&scene, &request, TaskShape { tasks: 2, regions: 2 });
    assert_ne!(pages[0].header.texels, pages[1].header.texels);
    let merged = tasks::merge(scene.clone(), &pages, &BakeOptions::default(), &mut |_| {}).unwrap();
    let m = &merged.estimate;
    assert_eq!(m.halves, single.halves, "halves");
    assert_eq!(m.total, single.total);
    assert_eq!(m.direct, single.direct);
    // The error: the two regions' control texels joined (up to 256 each).
    let controls: u32 = pages
        .iter()
        .map(|p| p.header.control.as_ref().unwrap().texels.len() as u32)
        .sum();
    assert!(controls > 256, "{controls}");
    assert_eq!(m.error.control_texels, Some(controls));
    let (em, ew) = (m.error.relative.unwrap(), single.error.relative.unwrap());
    assert!(em / ew > 0.5 && em / ew < 2.0, "merged {em}, single {ew}");
    // Pages times chains.
    let parts = bake_tasks(&scene, &request, TaskShape { tasks: 4, regions: 2 });
    let merged = tasks::merge(scene.clone(), &parts, &BakeOptions::default(), &mut |_| {}).unwrap();
    let em = merged.estimate.error.relative.unwrap();
    let d = rms_difference(&single.total, &merged.estimate.total);
    eprintln!(
        "vpl 2 pages x 2 chains: merged {em:.4}, single {ew:.4}, difference {d:.4}; pages' control texels {controls}"
    );
    assert!(
        d > 0.0 && d <= 3.0 * ((em * em + ew * ew) as f64).sqrt(),
        "{d} against {em} and {ew}"
    );
}

/// `sdf` and `obscurance` split into regions too (issue 25 point 1): their streams (sdf's
/// jitter, the shared direct light's) are keyed by pixel, their frames are the scene's,
/// what they read of the whole grid is built the same in every task (sdf's calibration
/// texels, drawn over the whole grid by pixel; obscurance's material maps and R_ave, from
/// the grid's texels before validation), and their one scene-wide ambient (sdf's bounce,
/// obscurance's I_A) is closed over every region by the merge (`engine::ambient`). The
/// two pages of a grey ground and a red ball under a sky and a low sun (the ground
/// bounces light onto the ball, so each page alone closes another ambient): each page
/// task bakes what the single bake bakes there, to float rounding, which it does not
/// without the closure; sdf's pages calibrate as the single bake does; the running
/// snapshots' merge closes the ambient as the final merge does.
#[test]
fn sdf_and_obscurance_pages_are_the_single_bakes_pages() {
    use lightmapd::engine::scene::Sun;
    let _gpu = common::gpu_serial();
    // The sphere over a plane, in colour (its library version is black: nothing bounces).
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.6; 3]));
    let red = b.material(MaterialDesc::diffuse("red", [0.8, 0.2, 0.1]));
    b.square("ground", Vec3::ZERO, 6.0, Vec3::Y, grey);
    b.sphere("ball", Vec3::new(0.0, 2.0, 0.0), 1.0, 48, 24, red);
    let (mut doc, bin) = b.to_gltf();
    remove_lightmap_uvs(&mut doc, Some(&[1]));
    let scene = Arc::new(scene::import_slice(&write_glb(&doc, &bin), None).unwrap().0);
    for (technique, params) in [
        (
            "sdf",
            serde_json::json!({"resolution": 48, "calibration_texels": 64, "calibration_rays": 32}),
        ),
        (
            "obscurance",
            serde_json::json!({"map_size": 128, "directions_per_step": 4}),
        ),
    ] {
        let mut request = request("cpu", 6);
        request.technique = technique.into();
        request.resolution = 40;
        request.params = params;
        request.lighting.sky = Some(sky());
        request.lighting.sun = Some(Sun {
            direction: Vec3::new(0.6, -0.5, 0.3).normalize(),
            angular_diameter: 0.0093,
            radiance: Vec3::splat(2000.0),
        });
        request.outputs = vec![OutputLayer::Direct];
        let single = job::bake_unobserved(scene.clone(), &request).unwrap();
        let pages = bake_tasks(&scene, &request, TaskShape { tasks: 2, regions: 2 });
        assert_ne!(pages[0].header.texels, pages[1].header.texels);
        assert_eq!(pages[0].header.params, pages[1].header.params, "{technique}");
        // A one-task split is the single bake; its header carries the parameters in effect.
        let one = bake_tasks(&scene, &request, TaskShape::steps(1));
        assert_eq!(one[0].snapshot.estimate().total, single.estimate.total, "{technique}");
        assert_eq!(pages[0].header.params, one[0].header.params, "{technique}");
        if technique == "sdf" {
            assert_eq!(pages[0].header.params["calibration"]["texels"], 64);
        }
        // Each page closed its own ambient, unlike the whole grid's.
        let own: Vec<Vec3> = pages
            .iter()
            .map(|p| p.ambient.as_ref().expect("an ambient reported")[0].sums.closure())
            .collect();
        assert!(
            (own[0] - own[1]).abs().max_element() > 0.01 * own[0].max_element(),
            "{technique}: the pages' own ambients {own:?} should differ"
        );
        let unclosed: Vec<Vec3> = pages.iter().flat_map(|p| p.snapshot.estimate().total).collect();
        let before = worst(&single.estimate.total, &unclosed);
        let merged = tasks::merge(scene.clone(), &pages, &BakeOptions::default(), &mut |_| {}).unwrap();
        let m = &merged.estimate;
        let after = worst(&single.estimate.total, &m.total);
        eprintln!(
            "{technique} two pages: ambients {own:?}; worst difference before the closure {before:.2e}, after {after:.2e}"
        );
        assert!(before > 1e-3, "{technique}: {before}");
        assert!(after < 1e-5, "{technique}: {after}");
        assert_eq!(
            m.direct, single.estimate.direct,
            "{technique}: the direct light bit for bit"
        );
        assert_eq!(m.ao, single.estimate.ao, "{technique}: the ao layer bit for bit");
        let (halves, single_halves) = (m.halves.as_ref().unwrap(), single.estimate.halves.as_ref().unwrap());
        assert_eq!(halves.1, single_halves.1);
        for h in 0..2 {
            assert!(worst(&single_halves.0[h], &halves.0[h]) < 1e-5, "{technique}: half {h}");
        }
        let controls: u32 = pages
            .iter()
            .map(|p| p.header.control.as_ref().unwrap().texels.len() as u32)
            .sum();
        assert_eq!(m.error.control_texels, Some(controls), "{technique}");
        // The running snapshots' merge (the service's, while tasks bake) closes the
        // ambient the same way: on the finished pages it is the final merge.
        let (atlas, ranges) = tasks::running_atlas(scene.clone(), &pages, &BakeOptions::default()).unwrap();
        let running = tasks::merge_running(&atlas, &ranges, &pages).unwrap();
        assert_eq!(running.total, m.total, "{technique}: the running merge");
    }
}

/// The merged error of chains states their true error (issue 25 point 5), bias of short
/// chains included: every technique that splits into chains bakes the closed box of
/// albedo 0.9 (lightmap 1 everywhere: the stiff case, where the first bounces' transient
/// of a short chain shows) as 3 chains of a third of `tests/honest_error.rs`'s steps; the
/// merged error, measured at the chains' merged control texels, lies within a factor 2
/// of the true error from the closed form (or, below the control's resolution, the true
/// error lies inside its stated 90 % interval), as a single bake's must.
#[test]
fn chained_merges_state_their_true_error() {
    use lightmapd::engine::scene::library::benchmark_scenes;
    let _gpu = common::gpu_serial();
    let s = benchmark_scenes()
        .into_iter()
        .find(|s| s.name == "closed-box-0.9")
        .unwrap();
    let scene = Arc::new(scene::import_slice(&(s.glb)(), None).unwrap().0);
    let analytic = s.analytic.expect("a closed form");
    let mut failures = Vec::new();
    for (technique, steps, params) in [
        ("vpl", 400, serde_json::json!({})),
        ("sdf", 3000, serde_json::json!({"resolution": 48})),
        ("obscurance", 400, serde_json::json!({"map_size": 256})),
        ("sdb", 400, serde_json::json!({"map_size": 256})),
        ("hemicube", 150, serde_json::json!({})),
    ] {
        let request = BakeRequest {
            technique: technique.into(),
            resolution: 24,
            lighting: s.lighting,
            stop: StopCriteria {
                steps: Some(steps),
                seconds: None,
                target_error: None,
            },
            params,
            seed: 7,
            denoise: Denoiser::None,
            ..BakeRequest::default()
        };
        let parts = bake_tasks(&scene, &request, TaskShape::steps(3));
        let merged = tasks::merge(scene.clone(), &parts, &BakeOptions::default(), &mut |_| {}).unwrap();
        let l = |v: Vec3| v.dot(LUMINANCE) as f64;
        let (mut err2, mut ref2) = (0.0f64, 0.0f64);
        for (k, t) in merged.atlas.texels.iter().enumerate() {
            let want = analytic(t.position.as_dvec3() + scene.origin_offset, t.geo_normal).expect("defined");
            err2 += (l(merged.estimate.total[k]) - l(want)).powi(2);
            ref2 += l(want).powi(2);
        }
        let truth = (err2 / ref2).sqrt();
        let e = merged.estimate.error;
        let reported = e.relative.unwrap() as f64;
        let ratio = reported / truth;
        eprintln!(
            "{technique}: 3 chains of about {} steps: reported {reported:.4} (bias {:?}, noise {:?}, interval {:?}), true {truth:.4}, ratio {ratio:.2}",
            steps / 3,
            e.bias,
            e.noise,
            e.interval
        );
        let [lo, hi] = e.interval.expect("the control's interval");
        let unresolved = lo <= e.noise.unwrap() * (1.0 + 1e-6) && truth <= hi as f64;
        if !unresolved && !(0.5..=2.0).contains(&ratio) {
            failures.push(format!(
                "{technique}: reported {reported:.4}, true {truth:.4}, ratio {ratio:.2}"
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "merged chains, reported / true error:\n{}",
        failures.join("\n")
    );
}

#[test]
fn the_merge_refuses_what_is_not_every_task_of_one_request() {
    let scene = scene();
    let request = request("cpu", 4);
    let parts = bake_tasks(&scene, &request, TaskShape::steps(2));
    let merge = |p: &[Partial]| {
        tasks::merge(scene.clone(), p, &BakeOptions::default(), &mut |_| {})
            .err()
            .expect("refused")
            .to_string()
    };
    let e = merge(&parts[1..]);
    assert!(e.contains("merge: tasks 0 of 2 are missing"), "{e}");
    let e = merge(&[parts[0].clone(), parts[0].clone(), parts[1].clone()]);
    assert!(e.contains("task 0 is given twice"), "{e}");
    let mut other = request.clone();
    other.seed = 12;
    let foreign = bake_tasks(&scene, &other, TaskShape::steps(2));
    let e = merge(&[parts[0].clone(), foreign[1].clone()]);
    assert!(e.contains("task result 1 (task 1/2) is of another request"), "{e}");
    let mut moved = parts.clone();
    moved[1].header.fingerprint = "0".repeat(64);
    let e = merge(&moved);
    assert!(e.contains("was baked on another texel set"), "{e}");
    // The merge takes the tasks' validation from their texels' pixels, checked first.
    let mut shuffled = parts.clone();
    shuffled[0].pixels.reverse();
    let e = merge(&shuffled);
    assert!(e.contains("not in pixel order"), "{e}");
    // Pixels in order but not the ones the task baked: its fingerprint names it.
    let mut shifted = parts.clone();
    shifted[0].pixels.pop();
    let e = merge(&shifted);
    assert!(e.contains("was baked on another texel set"), "{e}");
}

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_lightmapd"))
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lightmapd-tasks-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

const BAKE: &[&str] = &[
    "--resolution",
    "20",
    "--steps",
    "6",
    "--seed",
    "3",
    "--denoiser",
    "none",
    "--params",
    r#"{"device": "cpu", "samples_per_step": 2}"#,
];

fn channels(path: &Path) -> Vec<(String, Vec<f32>)> {
    common::exr_channels(path)
}

/// Three `bake --task K/3` processes at once, then `merge`: the EXR of a single
/// `bake`, channel for channel.
#[test]
fn three_processes_and_a_merge_write_the_single_bakes_lightmap() {
    let whole = tmp("whole.exr");
    let out = bin()
        .arg("bake")
        .arg(cornell())
        .arg("-o")
        .arg(&whole)
        .args(BAKE)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let parts: Vec<PathBuf> = (0..3).map(|k| tmp(&format!("task-{k}.lmtask"))).collect();
    let children: Vec<_> = parts
        .iter()
        .enumerate()
        .map(|(k, p)| {
            bin()
                .arg("bake")
                .arg(cornell())
                .arg("-o")
                .arg(p)
                .args(BAKE)
                .args(["--task", &format!("{k}/3"), "--regions", "3"])
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for (k, c) in children.into_iter().enumerate() {
        let out = c.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{stderr}");
        assert!(
            stderr.contains(&format!("region {k}/3")) && stderr.contains("(6 steps"),
            "{stderr}"
        );
    }
    let merged = tmp("merged.exr");
    let out = bin()
        .arg("merge")
        .arg("--scene")
        .arg(cornell())
        .args([&parts[2], &parts[0], &parts[1]])
        .arg("-o")
        .arg(&merged)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("merged 3 tasks") && stderr.contains("6 steps"),
        "{stderr}"
    );
    let (a, b) = (channels(&whole), channels(&merged));
    assert_eq!(
        a.iter().map(|c| &c.0).collect::<Vec<_>>(),
        b.iter().map(|c| &c.0).collect::<Vec<_>>()
    );
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        let peak = x.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-3);
        let d = x.iter().zip(y).map(|(p, q)| (p - q).abs()).fold(0f32, f32::max);
        assert!(d <= 1e-5 * peak, "channel {name}: merged differs by {d} (peak {peak})");
    }
    // A task missing: exit 2, naming it.
    let out = bin()
        .arg("merge")
        .arg("--scene")
        .arg(cornell())
        .args([&parts[0], &parts[2]])
        .arg("-o")
        .arg(tmp("never.exr"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("tasks 1 of 3 are missing"), "{stderr}");
}

#[test]
fn a_split_a_technique_does_not_allow_is_refused_before_baking() {
    let out = bin()
        .arg("bake")
        .arg(cornell())
        .arg("-o")
        .arg(tmp("never.lmtask"))
        .args([
            "--technique",
            "hemicube",
            "--steps",
            "8",
            "--task",
            "0/2",
            "--regions",
            "2",
        ])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("hemicube bakes are split into independent chains of the whole grid, not into regions"),
        "{stderr}"
    );
    let out = bin()
        .arg("bake")
        .arg(cornell())
        .arg("-o")
        .arg(tmp("never.lmtask"))
        .args(["--steps", "8", "--task", "2/2"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--task takes K/N with 0 <= K < N"));
    let out = bin()
        .arg("bake")
        .arg(cornell())
        .arg("-o")
        .arg(tmp("never.lmtask"))
        .args(["--steps", "8", "--task", "0/3", "--regions", "2"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("regions must divide tasks"), "{stderr}");
}
