//! What a region task of a split bake costs against a task of the whole grid (issue 25,
//! docs/scaling.md "A farm model"): wall time, its bake time and the rest (import, UVs,
//! texel set, BVH, validation), result size, and the merge of all regions.
//!
//! `cargo run --release --example region_bench -- BOXES CELLS TEXELS_PER_METRE PAGE_SIZE REGIONS STEPS`
//! (defaults 40 8 10 1024 4 2): the generated level of `prep_bench` (a 100 m ground and
//! BOXES boxes of 10 · CELLS² triangles, UVs generated at TEXELS_PER_METRE on pages
//! PAGE_SIZE wide), `path` on the CPU at 1 sample a step for STEPS steps. Rows: one task
//! of the whole grid (`tasks: 1`), then every region task of `tasks = regions = REGIONS`,
//! then the merge of those. The level's glb is built in memory first and imported by each
//! task, as a worker would.
//!
//! Limits: CPU only (the GPU route is what a farm would run; the preparation it times is
//! the same code); one generated layout.

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
        technique: "path".into(),
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
        params: serde_json::json!({"device": "cpu", "samples_per_step": 1}),
        denoise: Denoiser::None,
        ..BakeRequest::default()
    };
    println!(
        "level: {boxes} boxes of {} triangles, {density} texels/m on {page}-wide pages; path {steps} steps of 1 sample; {} threads",
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
    run(TaskShape::steps(1), 0);
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
}
