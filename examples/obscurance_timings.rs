//! `obscurance` timings for docs/performance.md and docs/obscurance.md:
//! 1. milliseconds per direction (depth-layer raster + gather, up to GPU completion) for
//!    scenes of about 1k, 25k, 100k and 193k triangles (the seed's cathedral size), with
//!    lightmaps 256^2 and 1024^2 and the 512^2 map, plus the depth complexity the
//!    per-pixel lists held (the layer count the scene needs);
//! 2. the incremental update of seed section 5: a moved block in the 25k-triangle blocks
//!    scene, time and lightmap against a full rebake of the moved scene.
//!
//! Usage: cargo run --release --example obscurance_timings [-- DIRECTIONS=32]

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use lightmapd::engine::atlas::Atlas;
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::scene::build::{MaterialDesc, SceneBuilder};
use lightmapd::engine::scene::library::procedural_blocks;
use lightmapd::engine::scene::{Hemisphere, Lighting, Scene, Sky, import_slice};
use lightmapd::engine::technique::obscurance::{Obscurance, UpdateReach};
use lightmapd::engine::technique::{BakeInputs, Technique};
use serde_json::json;

/// Ground plane plus `n x n` spheres of `segments x segments/2` quads (as the sdb bench).
fn spheres(n: usize, segments: u32) -> SceneBuilder {
    let mut b = SceneBuilder::new();
    let grey = b.material(MaterialDesc::diffuse("grey", [0.6; 3]));
    b.square("ground", Vec3::ZERO, 20.0, Vec3::Y, grey);
    let step = 16.0 / n as f32;
    for i in 0..n {
        for j in 0..n {
            let c = Vec3::new(
                -8.0 + (i as f32 + 0.5) * step,
                0.5 * step,
                -8.0 + (j as f32 + 0.5) * step,
            );
            b.sphere(&format!("ball {i} {j}"), c, 0.4 * step, segments, segments / 2, grey);
        }
    }
    b
}

fn lighting() -> Lighting {
    Lighting {
        sky: Some(Sky {
            radiance: Vec3::ONE,
            hemisphere: Hemisphere::Upper,
        }),
        sun: None,
    }
}

fn inputs(scene: &Arc<Scene>, atlas: &Arc<Atlas>) -> BakeInputs {
    let request = BakeRequest {
        technique: "obscurance".into(),
        lighting: lighting(),
        ..Default::default()
    };
    let plan = lightmapd::engine::job::plan_for(scene, &request).expect("plan");
    BakeInputs::new(scene.clone(), atlas.clone(), lighting(), 1, plan)
}

fn main() {
    let directions: u64 = std::env::args()
        .skip(1)
        .find_map(|a| a.strip_prefix("DIRECTIONS=").and_then(|v| v.parse().ok()))
        .unwrap_or(32);
    let only_update = std::env::args().any(|a| a == "ONLY=update");
    println!("| scene | triangles | lightmap | valid texels | ms / direction | max layers | max fragments |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    let table = if only_update {
        &[][..]
    } else {
        &[
            ("1 sphere", 1, 32),
            ("25 spheres", 5, 32),
            ("25 fine spheres", 5, 64),
            ("25 spheres, 193k", 5, 88),
        ][..]
    };
    for &(name, n, segments) in table {
        let scene = Arc::new(import_slice(&spheres(n, segments).to_glb(), None).expect("scene").0);
        for res in [256u32, 1024] {
            let atlas = Arc::new(Atlas::build(&scene, res, res).expect("atlas"));
            let t_prep = Instant::now();
            let mut tech = Obscurance::prepare(inputs(&scene, &atlas), &json!({"map_size": 512})).expect("prepare");
            let prep = t_prep.elapsed().as_secs_f64();
            for _ in 0..4 {
                tech.step().expect("step");
            }
            tech.finish().expect("finish");
            let t0 = Instant::now();
            for _ in 0..directions {
                tech.step().expect("step");
            }
            tech.finish().expect("finish");
            let ms = t0.elapsed().as_secs_f64() * 1e3 / directions as f64;
            tech.snapshot().expect("snapshot");
            let s = tech.layer_stats();
            println!(
                "| {name} | {} | {res}^2 | {} | {ms:.1} | {} | {} (pool {}, overflows {}) | prepare {prep:.2} s",
                scene.triangles.len(),
                atlas.texels.len(),
                s.max_layers,
                s.max_fragments,
                s.capacity,
                s.overflowing_directions
            );
        }
    }

    // Incremental update: the blocks scene, its first block moved 1 m along x.
    let res = 512;
    let steps = 96;
    let builder = procedural_blocks();
    let (json_doc, bin) = builder.to_gltf();
    let base = Arc::new(import_slice(&builder.to_glb(), None).expect("blocks").0);
    let block = "block 0";
    let moved_names: Vec<String> = base
        .meshes
        .iter()
        .filter(|m| m.name.starts_with(&format!("{block} face ")))
        .map(|m| m.name.clone())
        .collect();
    assert_eq!(
        moved_names.len(),
        5,
        "the blocks scene names its faces 'block K face F'"
    );
    // Move that block's meshes by translating their nodes.
    let mut moved_doc = json_doc.clone();
    for node in moved_doc["nodes"].as_array_mut().unwrap() {
        if node["name"]
            .as_str()
            .is_some_and(|n| moved_names.iter().any(|m| m == n))
        {
            let t = node["translation"]
                .as_array()
                .map(|a| a.iter().map(|v| v.as_f64().unwrap()).collect::<Vec<_>>());
            let t = t.unwrap_or(vec![0.0; 3]);
            node["translation"] = json!([t[0] + 1.0, t[1], t[2]]);
        }
    }
    let moved = Arc::new(
        import_slice(&lightmapd::engine::scene::build::write_glb(&moved_doc, &bin), None)
            .expect("moved")
            .0,
    );
    let atlas0 = Arc::new(Atlas::build(&base, res, res).unwrap());
    let atlas1 = Arc::new(Atlas::build(&moved, res, res).unwrap());
    let bake = |tech: &mut Obscurance, n: u64| {
        let t = Instant::now();
        for _ in 0..n {
            tech.step().unwrap();
        }
        tech.finish().unwrap();
        let halves = tech.halves().unwrap();
        let s = t.elapsed().as_secs_f64();
        let lm: Vec<Vec3> = (0..halves[0].w.len())
            .map(|k| {
                (halves[0].direct[k]
                    + halves[0].ambient * halves[0].w[k]
                    + halves[1].direct[k]
                    + halves[1].ambient * halves[1].w[k])
                    * 0.5
            })
            .collect();
        (s, lm)
    };
    let t_atlas = Instant::now();
    let atlas_check = Atlas::build(&moved, res, res).unwrap();
    let atlas_seconds = t_atlas.elapsed().as_secs_f64();
    drop(atlas_check);
    println!("\n(texel set of the moved scene: {atlas_seconds:.2} s, paid by both the rebake and the update)");
    for params in [json!({"map_size": 512}), json!({"map_size": 512, "dmax": 1.0})] {
        println!("\nparams {params}");
        let mut first_bake = Obscurance::prepare(inputs(&base, &atlas0), &params).unwrap();
        let (t_base, _) = bake(&mut first_bake, steps);
        let state = first_bake.state().unwrap();
        let t_full0 = Instant::now();
        let mut full = Obscurance::prepare(inputs(&moved, &atlas1), &params).unwrap();
        let (t_full, lm_full) = bake(&mut full, steps);
        let t_full_total = t_full0.elapsed().as_secs_f64();
        println!(
            "blocks-25k ({} triangles), lightmap {res}^2 ({} texels), map 512^2, {steps} steps; moved {block:?} \
             ({} meshes) by 1 m",
            moved.triangles.len(),
            atlas1.texels.len(),
            moved_names.len()
        );
        println!("first bake: {t_base:.2} s; full rebake: {t_full:.2} s ({t_full_total:.2} s with preparation)");
        let rms = |v: &[Vec3]| (v.iter().map(|x| x.length_squared() as f64).sum::<f64>() / v.len() as f64).sqrt();
        for reach in [UpdateReach::All, UpdateReach::Dmax] {
            let t_upd0 = Instant::now();
            let (mut upd, report) = Obscurance::update(inputs(&moved, &atlas1), &state, &moved_names, reach).unwrap();
            let (t_upd, lm_upd) = bake(&mut upd, report.steps);
            let t_upd_total = t_upd0.elapsed().as_secs_f64();
            let diff: Vec<Vec3> = lm_full.iter().zip(&lm_upd).map(|(a, b)| *a - *b).collect();
            let max_rel = lm_full
                .iter()
                .zip(&lm_upd)
                .map(|(a, b)| ((*a - *b).length() / a.length().max(1e-6)) as f64)
                .fold(0.0, f64::max);
            println!(
                "update ({reach:?}): {t_upd:.2} s ({t_upd_total:.2} s with preparation), recomputed {} of {} texels; \
                 vs full rebake: relative RMS difference {:.2e}, largest per-texel relative difference {max_rel:.2e}",
                report.recomputed_texels,
                report.total_texels,
                rms(&diff) / rms(&lm_full)
            );
        }
    }
}
