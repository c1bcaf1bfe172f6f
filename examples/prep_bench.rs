//! Preparation before sampling on a generated level (issue 19 point 8): seconds and peak
//! memory of each phase, for docs/performance.md.
//!
//! `cargo run --release --example prep_bench -- BOXES CELLS TEXELS_PER_METRE PAGE_SIZE`
//! (defaults 40 8 10 1024): a ground plane of 100 m square (8 × 8 cells) and BOXES boxes
//! in a square grid over it, each with five faces of CELLS × CELLS quads (10 · CELLS²
//! triangles a box), every mesh without `TEXCOORD_1`, so the bake generates them at
//! TEXELS_PER_METRE on pages PAGE_SIZE wide. Phases, each timed on its own with the
//! process's peak resident size after it (`VmHWM`, which only grows):
//! import (the .glb in memory), UV generation (`atlas::unwrap`: unwrap, pack, pages),
//! a page task's share (`Atlas::coverage` and the cut into page regions, then
//! `Atlas::build_pixels` of region 0: what a split bake's page task builds instead of the
//! whole texel set), texel set (`Atlas::build`: rasterisation, gutter links, seam search), BVH
//! (`SceneRays::new`, the tracer built on first use), texel validation (backface rays:
//! the GPU route of `gpu::validate` first when a hardware GPU is present, or with
//! `PREP_GPU=1` on any adapter, then the CPU's, and how many texels the two disagree on).
//!
//! Limits: one generated layout (boxes over a ground); the glb is built and held in
//! memory before the first phase and counted in every peak.

use std::time::Instant;

use lightmapd::engine::atlas::{Atlas, unwrap, validate};
use lightmapd::engine::gpu::scene_rays::SceneRays;
use lightmapd::engine::scene::import_slice;
use lightmapd::engine::scene::library::generated_level;
use std::sync::Arc;

/// The process's peak resident size so far, in MiB (Linux `VmHWM`; 0 elsewhere).
fn peak_mib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|k| k.parse::<u64>().ok()))
        })
        .map_or(0, |kb| kb / 1024)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |k: usize, d: f64| args.get(k).and_then(|a| a.parse::<f64>().ok()).unwrap_or(d);
    let (boxes, cells, density, page) = (
        arg(0, 40.0) as u32,
        arg(1, 8.0) as u32,
        arg(2, 10.0) as f32,
        arg(3, 1024.0) as u32,
    );
    let glb = generated_level(boxes, cells);
    println!(
        "level: {boxes} boxes of {} triangles, ground 100 m; {density} texels/m on {page}-wide pages; glb {} MiB; {} threads",
        10 * cells * cells,
        glb.len() >> 20,
        rayon::current_num_threads()
    );
    println!("| phase | seconds | peak resident MiB after it |");
    println!("| --- | --- | --- |");
    let row = |phase: &str, t: Instant| println!("| {phase} | {:.2} | {} |", t.elapsed().as_secs_f64(), peak_mib());

    let t = Instant::now();
    let (mut scene, report) = import_slice(&glb, None).expect("the generated level imports");
    row(&format!("import ({} triangles)", report.triangles), t);

    let t = Instant::now();
    let u = unwrap::generate_lightmap_uvs_with(
        &mut scene,
        page,
        unwrap::LightmapUvs::GenerateMissing,
        Some(density),
        &unwrap::UvUnwrap,
    )
    .expect("UVs");
    row(
        &format!(
            "UV generation ({} charts, {} pages, {:.1} texels/m)",
            u.charts, u.generated_pages, u.texels_per_metre
        ),
        t,
    );
    for w in u.warnings.iter().take(3) {
        println!("warning: {w}");
    }

    // What a page's task of a split bake prepares instead of the whole texel set
    // (issue 25, docs/scaling.md): the grid's coverage (a bit a pixel) to cut it, then
    // page 0's texels alone. Before the whole texel set, so the peak after them is theirs.
    let (w, h) = scene.layout.as_ref().map_or((page, page), |l| (l.width, l.height));
    let scene = Arc::new(scene);
    let pages = scene.layout.as_ref().map_or(1, |l| l.pages.len()) as u32;
    let t = Instant::now();
    let coverage = Atlas::coverage(&scene, w, h).expect("coverage");
    let cut = coverage.region_pixels(pages).expect("regions");
    row(
        &format!(
            "coverage and the cut into {pages} page regions ({} texels)",
            coverage.texels()
        ),
        t,
    );
    drop(coverage);
    let t = Instant::now();
    let page0 = Atlas::build_pixels(&scene, w, h, cut[0].clone()).expect("page 0's texels");
    row(
        &format!("texel set of region 0 alone ({} texels)", page0.texels.len()),
        t,
    );
    drop(page0);

    let t = Instant::now();
    let mut atlas = Atlas::build(&scene, w, h).expect("texel set");
    row(
        &format!(
            "texel set ({w}x{h} grid, {} valid texels, {} seam samples)",
            atlas.texels.len(),
            atlas.seams.len()
        ),
        t,
    );

    let t = Instant::now();
    let rays = SceneRays::new(scene.clone());
    let tracer = rays.tracer();
    row("BVH", t);

    // The GPU route of the engine's preparation (`gpu::validate`, what `engine::job` takes
    // on a hardware GPU), timed first on the same texels, then the CPU's; the two must
    // agree texel for texel. On lavapipe only with PREP_GPU=1 (it is slower there).
    let gpu = lightmapd::engine::gpu::hardware_context("prep_bench").or_else(|| {
        (std::env::var("PREP_GPU").as_deref() == Ok("1"))
            .then(|| lightmapd::engine::gpu::shared(&Default::default()).ok())
            .flatten()
    });
    let gpu_fractions = gpu.map(|ctx| {
        let t = Instant::now();
        let f = lightmapd::engine::gpu::validate::backface_fractions(&ctx, &rays, &atlas.texels)
            .expect("the GPU route traces");
        row(&format!("texel validation, GPU route ({})", ctx.info.name), t);
        f
    });
    let t = Instant::now();
    let cpu_fractions = validate::backface_fractions(&scene, &tracer, &atlas.texels);
    let v = validate::validate_from(&scene, &mut atlas, &cpu_fractions);
    row(
        &format!(
            "texel validation, CPU route ({} inside geometry)",
            v.inside_geometry_texels
        ),
        t,
    );
    if let Some(g) = gpu_fractions {
        let differ = g.iter().zip(&cpu_fractions).filter(|(a, b)| a != b).count();
        println!(
            "GPU and CPU routes: {differ} of {} texels' back-face fractions differ",
            g.len()
        );
    }
}
