//! What a region task of a split bake costs against a task of the whole grid (issue 25,
//! docs/scaling.md "A farm model"): wall time, its bake time and the rest (import, UVs,
//! texel set, BVH, validation), result size, and the merge of all regions.
//!
//! `cargo run --release --example region_bench -- BOXES CELLS TEXELS_PER_METRE PAGE_SIZE REGIONS STEPS [TECHNIQUE]`
//! (defaults 40 8 10 1024 4 2 path): the generated level of `prep_bench` (a 100 m ground
//! and BOXES boxes of 10 · CELLS² triangles, UVs generated at TEXELS_PER_METRE on pages
//! PAGE_SIZE wide), baked for STEPS steps by TECHNIQUE: `path` on the CPU at 1 sample a
//! step, any other technique that splits by regions with its defaults (on the GPU).
//! Rows: one task of the whole grid (`tasks: 1`), then every region task of `tasks =
//! regions = REGIONS`, then the merge of those, and how far the merge is from the whole
//! grid's task (the largest texel difference over the RMS). The level's glb is built in
//! memory first and imported by each task, as a worker would.
//!
//! Limits: `path` on the CPU only (the GPU route is what a farm would run; the
//! preparation it times is the same code); one generated layout.

use std::sync::Arc;
use std::time::Instant;

use lightmapd::engine::bake::{BakeEvent, StopCriteria};
use lightmapd::engine::job::{BakeOptions, BakeRequest};
use lightmapd::engine::post::denoised::Denoiser;
use lightmapd::engine::scene::import_slice;
use lightmapd::engine::scene::library::{generated_level, outdoor_lighting};
use lightmapd::engine::tasks::{self, Partial, TaskShape};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |k: usize, d: f64| args.get(k).and_then(|a| a.parse::<f64>().ok()).unwrap_or(d);
    let technique = args.get(6).cloned().unwrap_or_else(|| "path".into());
    let (boxes, cells, density, page, regions, steps) = (
        arg(0, 40.0) as u32,
        arg(1, 8.0) as u32,
        arg(2, 10.0) as f32,
        arg(3, 1024.0) as u32,
        arg(4, 4.0) as u32,
        arg(5, 2.0) as u64,
    );
    let glb = generated_level(boxes, cells);
    let request = BakeRequest {
        technique: technique.clone(),
        resolution: page,
        texels_per_unit: Some(density),
        // The pages this bench measures, not grown to fit the density.
        max_page_size: Some(page),
        lighting: outdoor_lighting(),
        stop: StopCriteria {
            steps: Some(steps),
            seconds: None,
            target_error: None,
        },
        params: if technique == "path" {
            serde_json::json!({"device": "cpu", "samples_per_step": 1})
        } else {
            serde_json::Value::Null
        },
        denoise: Denoiser::None,
        ..BakeRequest::default()
    };
    println!(
        "level: {boxes} boxes of {} triangles, {density} texels/m on {page}-wide pages; {technique} {steps} steps; {} threads",
        10 * cells * cells,
        rayon::current_num_threads()
    );
    println!("| task | texels | wall s | bake s | the rest s | result MB |");
    println!("| --- | ---: | ---: | ---: | ---: | ---: |");
    let run = |shape: TaskShape, k: usize| -> Partial {
        let t = Instant::now();
        let (scene, _) = import_slice(&glb, None).expect("the generated level imports");
        let task = tasks::split(&request, shape).expect("a split")[k];
        let p = tasks::bake_task(
            Arc::new(scene),
            &request,
            task,
            &BakeOptions::default(),
            &mut |_: BakeEvent<'_>| std::ops::ControlFlow::Continue(()),
            &mut |_| {},
            &mut |_| {},
        )
        .expect("the task bakes");
        let wall = t.elapsed().as_secs_f64();
        let bytes = p.encode().expect("encodes").len();
        let what = if shape.regions > 1 {
            format!("region {k} of {}", shape.regions)
        } else {
            "whole grid".into()
        };
        println!(
            "| {what} | {} | {wall:.2} | {:.2} | {:.2} | {:.1} |",
            p.header.texels,
            p.header.seconds,
            wall - p.header.seconds,
            bytes as f64 / 1e6
        );
        p
    };
    let whole = run(TaskShape::steps(1), 0);
    let shape = TaskShape {
        tasks: regions,
        regions,
    };
    let parts: Vec<Partial> = (0..regions as usize).map(|k| run(shape, k)).collect();
    let t = Instant::now();
    let (scene, _) = import_slice(&glb, None).expect("the generated level imports");
    let merged = tasks::merge(Arc::new(scene), &parts, &BakeOptions::default(), &mut |_| {}).expect("merges");
    println!(
        "| merge of the {regions} regions | {} | {:.2} | | | |",
        merged.estimate.total.len(),
        t.elapsed().as_secs_f64()
    );
    let single = whole.snapshot.estimate().total;
    let lum = |v: glam::Vec3| f64::from(v.dot(lightmapd::engine::accumulate::LUMINANCE));
    let rms = (single.iter().map(|v| lum(*v).powi(2)).sum::<f64>() / single.len().max(1) as f64).sqrt();
    let worst = single
        .iter()
        .zip(&merged.estimate.total)
        .map(|(a, b)| (lum(*a) - lum(*b)).abs())
        .fold(0.0f64, f64::max);
    println!(
        "merged against the whole grid's task: largest texel difference {:.2e} of the RMS",
        worst / rms.max(f64::MIN_POSITIVE)
    );
}
