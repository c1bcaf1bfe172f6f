//! The figures of docs/quality.md's denoising sections (issue 22).
//!
//! `cargo run --release --example denoise_quality -- errors [SCENE] [REF_SAMPLES]`:
//! true error against a converged reference (a `path` bake with another seed and
//! REF_SAMPLES samples per texel, default 65536) at 4 … 1024 steps of `path` (4 samples
//! a step; env `MAX_STEPS` = 4096 adds 4096), raw and after each denoiser, unblended and
//! blended, with the delivered error estimate and the error on chart borders (texels within 2 of another chart or
//! an empty texel), and OIDN run on each chart alone (issue 22 point 2's third way: its
//! bounding box padded by 8 texels, every other pixel filled from that chart only),
//! against the delivered way (the whole image, every gutter filled first, read back at
//! valid texels). SCENE is a bench scene (default cornell-box) or a .glb path. With env
//! `DIAG` set it also prints, to stderr, OIDN's cross-validated error M against its true
//! error (interior and border texels, smoothed and one standard error high), the
//! squared errors of the blend, OIDN alone and raw by the blend's filtered share, and
//! the texels the blend left at least three-quarters raw (where they lose to OIDN).
//!
//! `… -- converged [SEEDS]`: delivered over raw true error on the two closed-form scenes
//! at 16 and 8192 samples, over SEEDS seeds (default 6), per denoiser: what the blend's
//! guards are for (one seed of it is `tests/denoise.rs`).
//!
//! `… -- cost SIZE`: OIDN's time and peak memory on a SIZE² lightmap (run one size per
//! process so the peak is that size's); `… -- cost-denoise SIZE`: the whole denoising
//! step's time at SIZE²; `… -- dump …`: the estimates and filter outputs as JSON for
//! trying filters outside Rust.

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use lightmapd::bench::{prepare, read_cached, true_error, write_cached};
use lightmapd::engine::accumulate::Estimate;
use lightmapd::engine::atlas::{Atlas, GutterLink, NO_TEXEL, PixelTexels};
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::post::denoise::charts;
use lightmapd::engine::post::denoised::{self, Used};
use lightmapd::engine::post::oidn::{Mode, Oidn};
use lightmapd::engine::scene::library::benchmark_scenes;
use lightmapd::engine::scene::{Hemisphere, Lighting, Scene, Sky, import_file};
use lightmapd::engine::technique::{self, BakeInputs, Technique};

fn peak_rss_mb() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or(0.0)
        / 1024.0
}

fn path_tech(scene: &Arc<Scene>, atlas: &Arc<Atlas>, lighting: Lighting, seed: u64, spp: u32) -> Box<dyn Technique> {
    let request = BakeRequest {
        lighting,
        seed,
        ..Default::default()
    };
    let plan = lightmapd::engine::job::plan_for(scene, &request).unwrap();
    let inputs = BakeInputs::new(scene.clone(), atlas.clone(), lighting, seed, plan);
    technique::create("path", inputs, &serde_json::json!({ "samples_per_step": spp })).unwrap()
}

/// OIDN on each chart alone: the chart's bounding box, padded by 8 texels, cut from an
/// image whose other pixels are filled from this chart only (the gutter fill of an atlas
/// holding just its texels), filtered, and read back at the chart's texels.
fn oidn_per_chart(o: &Oidn, atlas: &Atlas, chart: &[u32], values: &[Vec3]) -> Vec<Vec3> {
    const PAD: usize = 8;
    let (w, h) = (atlas.width as usize, atlas.height as usize);
    let mut out = values.to_vec();
    for c in 0..chart.iter().max().map_or(0, |m| m + 1) {
        let members: Vec<usize> = (0..atlas.texels.len()).filter(|&k| chart[k] == c).collect();
        let mut sub = atlas.clone();
        sub.texels = members.iter().map(|&k| atlas.texels[k]).collect();
        sub.pixel_texel = PixelTexels::of(&sub.texels, 0..w * h);
        sub.links = atlas
            .links
            .iter()
            .filter_map(|l| {
                let i = members.binary_search(&(l.texel as usize)).ok()?;
                Some(GutterLink {
                    pixel: l.pixel,
                    texel: i as u32,
                })
            })
            .collect();
        let own: Vec<Vec3> = members.iter().map(|&k| values[k]).collect();
        let img = lightmapd::engine::post::dilate(&sub, &own, denoised::FILL_RINGS);
        let (mut i0, mut j0, mut i1, mut j1) = (w, h, 0, 0);
        for t in &sub.texels {
            let (i, j) = (t.pixel as usize % w, t.pixel as usize / w);
            (i0, j0, i1, j1) = (i0.min(i), j0.min(j), i1.max(i), j1.max(j));
        }
        let (i0, j0) = (i0.saturating_sub(PAD), j0.saturating_sub(PAD));
        let (i1, j1) = ((i1 + PAD).min(w - 1), (j1 + PAD).min(h - 1));
        let (bw, bh) = (i1 - i0 + 1, j1 - j0 + 1);
        let crop: Vec<Vec3> = (j0..=j1)
            .flat_map(|j| img[j * w + i0..=j * w + i1].iter().copied())
            .collect();
        let filtered = o
            .filter(bw as u32, bh as u32, &crop, None, Mode::Lightmap)
            .expect("OIDN filters a chart");
        for (&k, t) in members.iter().zip(&sub.texels) {
            let (i, j) = (t.pixel as usize % w, t.pixel as usize / w);
            out[k] = filtered[(j - j0) * bw + (i - i0)];
        }
    }
    out
}

fn border_mask(atlas: &Atlas, chart: &[u32]) -> Vec<bool> {
    let (w, h) = (atlas.width as i64, atlas.height as i64);
    atlas
        .texels
        .iter()
        .enumerate()
        .map(|(k, t)| {
            let (i, j) = (t.pixel as i64 % w, t.pixel as i64 / w);
            (-2..=2).any(|dj| {
                (-2..=2).any(|di| {
                    let (x, y) = (i + di, j + dj);
                    if x < 0 || y < 0 || x >= w || y >= h {
                        return true;
                    }
                    let q = atlas.pixel_texel[(y * w + x) as usize];
                    q == NO_TEXEL || chart[q as usize] != chart[k]
                })
            })
        })
        .collect()
}

fn masked(reference: &[Option<Vec3>], mask: &[bool]) -> Vec<Option<Vec3>> {
    reference
        .iter()
        .zip(mask)
        .map(|(r, m)| if *m { *r } else { None })
        .collect()
}

/// The reference of `key` from `target/denoise-quality-refs` (the bench's cache format,
/// `bench::read_cached`), or baked by `bake` and kept there: a real interior's reference
/// takes minutes on two cores, and every comparison of a change to the denoiser needs
/// the same one. `bake` returns the values and their own estimated relative error.
fn cached_reference(key: &str, texels: usize, bake: impl FnOnce() -> (Vec<Vec3>, f64)) -> Vec<Option<Vec3>> {
    let file = std::path::Path::new("target/denoise-quality-refs").join(format!("{key}.ref"));
    if let Some(r) = read_cached(&file, texels) {
        eprintln!(
            "reference: {}, own estimated error {:.3} %",
            file.display(),
            r.error * 100.0
        );
        return r.values;
    }
    let (values, error) = bake();
    write_cached(&file, &values, error).unwrap();
    values.into_iter().map(Some).collect()
}

fn errors(args: &[String]) {
    let name = args.first().map(String::as_str).unwrap_or("cornell-box");
    let ref_samples: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(65536);
    let (scene, atlas, lighting) = if name.ends_with(".glb") {
        let scene = import_file(std::path::Path::new(name)).unwrap().0;
        let res: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(256);
        let mut scene = scene;
        if scene.needs_lightmap_uvs {
            lightmapd::engine::atlas::unwrap::generate_lightmap_uvs(
                &mut scene,
                res,
                &lightmapd::engine::atlas::unwrap::UvUnwrap,
            )
            .unwrap();
        }
        let atlas = Atlas::build(&scene, res, res).unwrap();
        // A uniform upper sky of radiance 1. (This was a JSON string parsed with
        // `unwrap_or_default`: it lacked `hemisphere`, so the parse failed and the room
        // was baked with no light at all, every error reading 0.)
        let lighting = Lighting {
            sky: Some(Sky {
                radiance: Vec3::ONE,
                hemisphere: Hemisphere::Upper,
            }),
            sun: None,
        };
        (Arc::new(scene), Arc::new(atlas), lighting)
    } else {
        let lib = benchmark_scenes()
            .into_iter()
            .find(|s| s.name == name)
            .expect("bench scene");
        let p = prepare(&lib).unwrap();
        (p.scene, p.atlas, lib.lighting)
    };
    let chart = charts(&atlas);
    let border = border_mask(&atlas, &chart);
    eprintln!(
        "{name}: {} texels, {} charts, {} on borders; reference {ref_samples} samples/texel…",
        atlas.texels.len(),
        chart.iter().max().map(|m| m + 1).unwrap_or(0),
        border.iter().filter(|b| **b).count()
    );
    let key = format!(
        "{}-{}-{ref_samples}",
        std::path::Path::new(name).file_stem().unwrap().to_string_lossy(),
        atlas.texels.len()
    );
    let reference = cached_reference(&key, atlas.texels.len(), || {
        let t = Instant::now();
        let mut r = path_tech(&scene, &atlas, lighting, 987_654, 64);
        for _ in 0..(ref_samples / 64).max(2) {
            r.step().unwrap();
        }
        let rest = r.snapshot().unwrap().estimate();
        eprintln!(
            "reference: {:.1} s, own estimated error {:.3} %",
            t.elapsed().as_secs_f64(),
            rest.error.relative.unwrap_or(0.0) * 100.0
        );
        (rest.total, rest.error.relative.unwrap_or(0.0) as f64)
    });
    let ref_border = masked(&reference, &border);
    let oidn = Oidn::available();
    println!(
        "| steps | raw | own | own blended | oidn | oidn + normal | oidn blended | estimated (oidn blended) | raw estimated | mean weight | border raw | border oidn | border oidn blended | oidn per chart | border oidn per chart |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    let mut tech = path_tech(&scene, &atlas, lighting, 1, 4);
    let pct = |e: f64| format!("{:.2} %", e * 100.0);
    // Every fourth power of two from 4 to MAX_STEPS (default 1024; 4096 on a GPU, where
    // `path` runs there and the steps are cheap).
    let max_steps: u64 = std::env::var("MAX_STEPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1024);
    for target in std::iter::successors(Some(4u64), |s| Some(s * 4)).take_while(|s| *s <= max_steps) {
        while tech.steps_done() < target {
            tech.step().unwrap();
        }
        let est: Estimate = tech.snapshot().unwrap().estimate();
        let se = est.texel_error.clone().unwrap();
        let raw = true_error(&est.total, &reference);
        let own = denoised::filter_unblended(&atlas, &chart, Used::Own, &est.total, &se);
        let own_b = denoised::apply(&atlas, &est, Used::Own);
        let (oidn_e, oidn_n, oidn_b, est_b, w, b_oidn, b_blend, tiled, b_tiled) = if oidn {
            let o = Oidn::get().unwrap();
            let d = denoised::filter_unblended(&atlas, &chart, Used::Oidn, &est.total, &se);
            let normals: Vec<Vec3> = atlas.texels.iter().map(|t| t.normal).collect();
            let img = lightmapd::engine::post::dilate(&atlas, &est.total, denoised::FILL_RINGS);
            let nimg = lightmapd::engine::post::dilate(&atlas, &normals, denoised::FILL_RINGS);
            let rt = o.filter(atlas.width, atlas.height, &img, Some(&nimg), Mode::RtWithNormal);
            let rt_err = match rt {
                Ok(rt) => {
                    let rt: Vec<Vec3> = atlas.texels.iter().map(|t| rt[t.pixel as usize]).collect();
                    pct(true_error(&rt, &reference))
                }
                Err(e) => {
                    eprintln!("  RT with normals: {e}");
                    "failed".into()
                }
            };
            let tb = Instant::now();
            let (b, weights) = denoised::apply_with_weights(&atlas, &est, Used::Oidn);
            eprintln!("  {target} steps: oidn blended in {:.2} s", tb.elapsed().as_secs_f64());
            let w = weights.iter().map(|w| *w as f64).sum::<f64>() / weights.len().max(1) as f64;
            let tt = Instant::now();
            let per_chart = oidn_per_chart(o, &atlas, &chart, &est.total);
            eprintln!(
                "  {target} steps: oidn per chart in {:.2} s",
                tt.elapsed().as_secs_f64()
            );
            (
                pct(true_error(&d, &reference)),
                rt_err,
                pct(true_error(&b.total, &reference)),
                pct(b.error.relative.unwrap_or(0.0) as f64),
                format!("{w:.2}"),
                pct(true_error(&d, &ref_border)),
                pct(true_error(&b.total, &ref_border)),
                pct(true_error(&per_chart, &reference)),
                pct(true_error(&per_chart, &ref_border)),
            )
        } else {
            let na = || "n/a".to_string();
            (na(), na(), na(), na(), na(), na(), na(), na(), na())
        };
        if std::env::var("DIAG").is_ok() {
            diagnose(&atlas, &chart, &border, &reference, &est, target);
        }
        println!(
            "| {target} | {} | {} | {} | {oidn_e} | {oidn_n} | {oidn_b} | {est_b} | {} | {w} | {} | {b_oidn} | {b_blend} | {tiled} | {b_tiled} |",
            pct(raw),
            pct(true_error(&own, &reference)),
            pct(true_error(&own_b.total, &reference)),
            pct(est.error.relative.unwrap_or(0.0) as f64),
            pct(true_error(&est.total, &ref_border)),
        );
    }
}

fn cost(args: &[String]) {
    let size: u32 = args.first().and_then(|s| s.parse().ok()).unwrap_or(1024);
    let o = Oidn::get().expect("OIDN installed (scripts/setup-oidn.sh)");
    let n = (size * size) as usize;
    let mut x = 0x9e37_79b9u32;
    let img: Vec<Vec3> = (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            Vec3::splat(0.5 + (x as f32 / u32::MAX as f32 - 0.5) * 0.4)
        })
        .collect();
    let before = peak_rss_mb();
    let t = Instant::now();
    let out = o.filter(size, size, &img, None, Mode::Lightmap).unwrap();
    let first = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let _ = o.filter(size, size, &img, None, Mode::Lightmap).unwrap();
    let second = t.elapsed().as_secs_f64();
    println!("| size | device | first run | second run | host peak before | host peak added |");
    println!(
        "| {size}² | {} | {first:.2} s | {second:.2} s | {:.0} MB | {:.0} MB |",
        o.describe(),
        before,
        peak_rss_mb() - before,
    );
    assert_eq!(out.len(), n);
}

/// `cost-denoise SIZE`: the whole denoising step's time (`denoised::apply`: the image
/// denoiser on the lightmap and its halves, the regression pass, the weights) on the
/// sky plane baked at SIZE², 2 steps of `path` at 1 sample, own filter and OIDN.
fn cost_denoise(args: &[String]) {
    let size: u32 = args.first().and_then(|s| s.parse().ok()).unwrap_or(1024);
    let lib = benchmark_scenes().into_iter().find(|s| s.name == "sky-plane").unwrap();
    let p = prepare(&lib).unwrap();
    let atlas = Arc::new(Atlas::build(&p.scene, size, size).unwrap());
    let mut tech = path_tech(&p.scene, &atlas, lib.lighting, 1, 1);
    tech.step().unwrap();
    tech.step().unwrap();
    let est = tech.snapshot().unwrap().estimate();
    let chart = charts(&atlas);
    let t = Instant::now();
    let halves = est.halves.as_ref().unwrap();
    let _ = lightmapd::engine::post::regress::fit(&atlas, &chart, &est.total, Some([&halves.0[0], &halves.0[1]]));
    let regress_s = t.elapsed().as_secs_f64();
    println!("| size | texels | regression pass | own, whole step | oidn, whole step |");
    let mut row = format!("| {size}² | {} | {regress_s:.2} s |", atlas.texels.len());
    for used in [Used::Own, Used::Oidn] {
        if used == Used::Oidn && !Oidn::available() {
            row += " n/a |";
            continue;
        }
        let t = Instant::now();
        let _ = denoised::apply(&atlas, &est, used);
        row += &format!(" {:.2} s |", t.elapsed().as_secs_f64());
    }
    println!("{row}");
}

/// `dump SCENE REF_SAMPLES STEPS… OUT.json`: the reference, and per step count the
/// raw estimate, its halves, standard errors and the OIDN and blended outputs, with each
/// texel's pixel, position, normal and chart: the input for trying filters outside Rust.
fn dump(args: &[String]) {
    let name = args[0].as_str();
    let ref_samples: u64 = args[1].parse().unwrap();
    let out_path = args.last().unwrap();
    let steps: Vec<u64> = args[2..args.len() - 1].iter().map(|s| s.parse().unwrap()).collect();
    let lib = benchmark_scenes()
        .into_iter()
        .find(|s| s.name == name)
        .expect("bench scene");
    let p = prepare(&lib).unwrap();
    let (scene, atlas, lighting) = (p.scene, p.atlas, lib.lighting);
    let chart = charts(&atlas);
    let mut r = path_tech(&scene, &atlas, lighting, 987_654, 64);
    for _ in 0..(ref_samples / 64).max(2) {
        r.step().unwrap();
    }
    let v3 = |v: &[Vec3]| v.iter().map(|x| [x.x, x.y, x.z]).collect::<Vec<_>>();
    let reference = r.snapshot().unwrap().estimate().total;
    let mut runs = Vec::new();
    let mut tech = path_tech(&scene, &atlas, lighting, 1, 4);
    for target in steps {
        while tech.steps_done() < target {
            tech.step().unwrap();
        }
        let est: Estimate = tech.snapshot().unwrap().estimate();
        let se = est.texel_error.clone().unwrap();
        let (halves, hs) = est.halves.clone().unwrap();
        let oidn = denoised::filter_unblended(&atlas, &chart, Used::Oidn, &est.total, &se);
        let oidn_h: Vec<_> = halves
            .iter()
            .map(|h| v3(&denoised::filter_unblended(&atlas, &chart, Used::Oidn, h, &se)))
            .collect();
        let blended = denoised::apply(&atlas, &est, Used::Oidn).total;
        runs.push(serde_json::json!({
            "steps": target, "half_steps": hs, "total": v3(&est.total), "se": se,
            "halves": [v3(&halves[0]), v3(&halves[1])], "oidn": v3(&oidn), "oidn_halves": oidn_h,
            "blended": v3(&blended),
        }));
    }
    let j = serde_json::json!({
        "width": atlas.width, "height": atlas.height,
        "pixel": atlas.texels.iter().map(|t| t.pixel).collect::<Vec<_>>(),
        "position": atlas.texels.iter().map(|t| [t.position.x, t.position.y, t.position.z]).collect::<Vec<_>>(),
        "normal": atlas.texels.iter().map(|t| [t.normal.x, t.normal.y, t.normal.z]).collect::<Vec<_>>(),
        "size": atlas.texels.iter().map(|t| t.size).collect::<Vec<_>>(),
        "chart": chart, "reference": v3(&reference), "runs": runs,
    });
    std::fs::write(out_path, serde_json::to_vec(&j).unwrap()).unwrap();
}

/// `DIAG`: where the blend stands against OIDN alone at one snapshot (stderr): the
/// squared errors of the blend, OIDN alone and raw by the blend's filtered share (texels
/// with no variance apart), the texels the blend left at least three-quarters raw, and
/// OIDN's cross-validated error M against its true error on interior and border texels.
fn diagnose(atlas: &Atlas, chart: &[u32], border: &[bool], reference: &[Option<Vec3>], est: &Estimate, target: u64) {
    let se = est.texel_error.clone().unwrap();
    let (halves, hs) = est.halves.clone().unwrap();
    let n = (hs[0] + hs[1]) as f32;
    let hse = |h: usize| -> Vec<f32> {
        let s = (n / hs[h] as f32).sqrt();
        se.iter().map(|e| e * s).collect()
    };
    let lum = |v: &Vec3| v.dot(lightmapd::engine::accumulate::LUMINANCE);
    let ih: Vec<Vec<f32>> = (0..2)
        .map(|h| {
            denoised::filter_unblended(atlas, chart, Used::Oidn, &halves[h], &hse(h))
                .iter()
                .map(lum)
                .collect()
        })
        .collect();
    let m = denoised::cross_validated(&se, &halves, hs, [&ih[0], &ih[1]], denoised::HalfNoise::Measured);
    let ms = lightmapd::engine::post::denoise::smooth_with_error(atlas, chart, &m, 3);
    let d = denoised::filter_unblended(atlas, chart, Used::Oidn, &est.total, &se);
    let (bl, wts) = denoised::apply_with_weights(atlas, est, Used::Oidn);
    let mut buckets = [[0.0f64; 4]; 5];
    for k in 0..se.len() {
        let Some(r) = reference[k] else { continue };
        let r = lum(&r) as f64;
        let b = if se[k] == 0.0 {
            4
        } else if wts.is_empty() {
            0
        } else {
            ((wts[k] * 4.0) as usize).min(3)
        };
        buckets[b][0] += 1.0;
        buckets[b][1] += (lum(&bl.total[k]) as f64 - r).powi(2);
        buckets[b][2] += (lum(&d[k]) as f64 - r).powi(2);
        buckets[b][3] += (lum(&est.total[k]) as f64 - r).powi(2);
    }
    {
        let vs =
            lightmapd::engine::post::denoise::smooth(atlas, chart, &se.iter().map(|e| e * e).collect::<Vec<f32>>(), 3);
        let (mut c, mut v, mut vr, mut mo, mut mp, mut tr, mut to, mut nb, mut lumv) =
            (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for k in 0..se.len() {
            if wts.is_empty() || wts[k] >= 0.25 || se[k] == 0.0 {
                continue;
            }
            let Some(r) = reference[k] else { continue };
            let r = lum(&r) as f64;
            c += 1.0;
            v += vs[k] as f64;
            vr += (se[k] as f64).powi(2);
            mo += ms[k].0 as f64;
            mp += (ms[k].0 + ms[k].1) as f64;
            tr += (lum(&est.total[k]) as f64 - r).powi(2);
            to += (lum(&d[k]) as f64 - r).powi(2);
            if border[k] {
                nb += 1.0;
            }
            lumv += r;
        }
        eprintln!(
            "  {target} low-share texels {c}: V smoothed {:.3e} own var {:.3e} | M oidn {:.3e} M+ {:.3e} | true raw {:.3e} oidn {:.3e} | border {:.2} | mean ref lum {:.3}",
            v / c,
            vr / c,
            mo / c,
            mp / c,
            tr / c,
            to / c,
            nb / c,
            lumv / c
        );
    }
    for (b, x) in buckets.iter().enumerate() {
        let which = if b < 4 {
            format!("filtered share {:.2}-{:.2}", b as f32 / 4.0, (b + 1) as f32 / 4.0)
        } else {
            "no variance".to_string()
        };
        eprintln!(
            "  {target} {which}: {} texels, sq err blend {:.3e} oidn {:.3e} raw {:.3e}",
            x[0], x[1], x[2], x[3]
        );
    }
    for (label, want) in [("interior", false), ("border", true)] {
        let (mut tr, mut v, mut to, mut mm, mut msm, mut mse, mut c) = (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for k in 0..se.len() {
            if border[k] != want {
                continue;
            }
            let Some(r) = reference[k] else { continue };
            let r = lum(&r) as f64;
            tr += (lum(&est.total[k]) as f64 - r).powi(2);
            to += (lum(&d[k]) as f64 - r).powi(2);
            v += (se[k] as f64).powi(2);
            mm += m[k] as f64;
            msm += ms[k].0 as f64;
            mse += (ms[k].0 + ms[k].1) as f64;
            c += 1.0;
        }
        eprintln!(
            "  {target} {label} ({c}): raw true {:.3e} V {:.3e} | oidn true {:.3e} M {:.3e} M smoothed {:.3e} M+ {:.3e}",
            tr / c,
            v / c,
            to / c,
            mm / c,
            msm / c,
            mse / c
        );
    }
}

/// Delivered over raw true error on the closed-form scenes for `seeds` seeds, at 16
/// samples (2 x 8) and 8192 (512 x 16), for each denoiser this machine has: the check
/// behind the blend's guards (`denoised::combine_weights`), which one seed in
/// `tests/denoise.rs` samples.
fn converged(args: &[String]) {
    let seeds: u64 = args.first().and_then(|s| s.parse().ok()).unwrap_or(6);
    let mut used = vec![Used::Own];
    if Oidn::available() {
        used.push(Used::Oidn);
    }
    println!("| scene | denoiser | samples | delivered / raw: min | max | mean |");
    println!("| --- | --- | --- | --- | --- | --- |");
    for name in ["sphere-over-plane", "parallel-plates"] {
        let lib = benchmark_scenes().into_iter().find(|s| s.name == name).unwrap();
        let p = prepare(&lib).unwrap();
        let reference = lightmapd::bench::analytic_reference(&lib, &p).expect("a closed form");
        for (spp, steps) in [(2u32, 8u64), (512, 16)] {
            let mut ratios: Vec<Vec<f64>> = vec![Vec::new(); used.len()];
            for seed in 1..=seeds {
                let mut tech = path_tech(&p.scene, &p.atlas, lib.lighting, seed, spp);
                for _ in 0..steps {
                    tech.step().unwrap();
                }
                let est = tech.snapshot().unwrap().estimate();
                let raw = true_error(&est.total, &reference);
                for (u, r) in used.iter().zip(ratios.iter_mut()) {
                    let out = denoised::apply(&p.atlas, &est, *u);
                    r.push(true_error(&out.total, &reference) / raw);
                }
            }
            for (u, r) in used.iter().zip(&ratios) {
                let min = r.iter().cloned().fold(f64::INFINITY, f64::min);
                let max = r.iter().cloned().fold(0.0, f64::max);
                let mean = r.iter().sum::<f64>() / r.len() as f64;
                println!(
                    "| {name} | {u:?} | {} | {min:.4} | {max:.4} | {mean:.4} |",
                    spp as u64 * steps
                );
            }
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("cost") => cost(&args[1..]),
        Some("dump") => dump(&args[1..]),
        Some("cost-denoise") => cost_denoise(&args[1..]),
        Some("converged") => converged(&args[1..]),
        Some("errors") | None => errors(args.get(1..).unwrap_or(&[])),
        Some(other) => eprintln!("unknown mode {other:?}: errors, cost, cost-denoise or dump"),
    }
}
