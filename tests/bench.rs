//! `lightmapd bench` (src/bench.rs): the scene selection, the real-size scenes it can run,
//! and a short run whose figures are checked against closed forms: `path` exact under a
//! uniform sky over a plane, and obscurance's reported error covering its bias (no
//! interreflection: 7.5 % low in the closed box of albedo 0.5), which the bench showed as
//! its noise alone (0.00 %) before it ran the control texels.

use std::path::PathBuf;
use std::time::Duration;

use lightmapd::bench::{BenchConfig, prepare, run, select_scenes};
use lightmapd::engine::error::EngineError;

fn names(v: &[lightmapd::engine::scene::library::LibraryScene]) -> Vec<&'static str> {
    v.iter().map(|s| s.name).collect()
}

#[test]
fn scenes_are_selected_by_name_or_as_the_real_set() {
    let small = select_scenes(&[]).unwrap();
    assert_eq!(
        names(&small),
        [
            "closed-box-0.5",
            "closed-box-0.9",
            "sky-plane",
            "sphere-over-plane",
            "parallel-plates",
            "cornell-box",
            "blocks-25k"
        ]
    );
    let real = select_scenes(&["real".to_string()]).unwrap();
    assert_eq!(
        names(&real),
        ["occlusion-room", "living-room", "kenney-fps-level", "level-256k"]
    );
    let two = select_scenes(&["level-256k".to_string(), "cornell-box".to_string()]).unwrap();
    assert_eq!(names(&two), ["cornell-box", "level-256k"], "the library's order");
    match select_scenes(&["nope".to_string()]) {
        Err(EngineError::BadInput(m)) => {
            assert!(
                m.contains("\"nope\"") && m.contains("level-256k") && m.contains("real"),
                "{m}"
            )
        }
        other => panic!("an unknown scene is bad input: {:?}", other.map(|v| names(&v))),
    }
}

#[test]
fn the_real_size_scenes_prepare_at_their_size() {
    for lib in select_scenes(&["real".to_string()]).unwrap() {
        let p = prepare(&lib).unwrap_or_else(|e| panic!("{}: {e}", lib.name));
        let (tris, texels) = (p.scene.triangles.len(), p.atlas.texels.len());
        eprintln!(
            "{}: {tris} triangles, {texels} texels, {}x{}",
            lib.name, p.atlas.width, p.atlas.height
        );
        assert_eq!(p.atlas.width, lib.resolution, "{}", lib.name);
        match lib.name {
            "occlusion-room" => assert_eq!(tris, 63_720),
            "level-256k" => {
                assert_eq!(tris, 256_128);
                // One 1024² page at 4.5 texels a metre (551k texels, the ground under the
                // boxes included: the bench does not validate).
                assert_eq!(p.atlas.height, 1024, "one page");
                assert!(texels > 500_000, "{texels}");
            }
            _ => assert!(
                tris > 1000 && texels > 10_000,
                "{}: {tris} triangles, {texels} texels",
                lib.name
            ),
        }
    }
}

#[test]
fn a_short_run_reports_exact_path_and_obscurances_bias() {
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("bench-short-run");
    let _ = std::fs::remove_dir_all(&out);
    let cfg = BenchConfig {
        scenes: vec!["closed-box-0.5".into(), "sky-plane".into()],
        techniques: vec!["path".into(), "obscurance".into()],
        budget: Duration::from_secs_f64(1.0),
        steps: None,
        reference_budget: Duration::from_secs_f64(1.0), // closed forms: never baked
        out_dir: out.clone(),
        cache_dir: out.join("cache"),
        probes: true,
    };
    let samples = run(&cfg, &mut |l| eprintln!("{l}")).expect("the bench runs");
    // Light probes (issue 26 point 5): each closed-form scene measured with both samplings;
    // with independent samples the last true error is small after a second and the reported
    // error within a factor 2 of it (the RMS over 64 probes of their half-difference
    // estimates); with Sobol points the true error is no larger, and the reported one
    // within a factor 2 too unless both are below 0.01 % and 0.1 % (the open sky is exact
    // under Sobol, the module doc of bench::probes; the lamp reads 0.003 %, its estimate
    // 0.005 %, where f32 rounding of the running means is of the same order).
    let csv = std::fs::read_to_string(out.join("probes.csv")).expect("probes.csv");
    let last = |scene: &str, sampling: &str| -> (usize, f64, f64) {
        let line = csv
            .lines()
            .rfind(|l| l.starts_with(scene) && l.split(',').nth(2) == Some(sampling))
            .unwrap_or_else(|| panic!("probes.csv has no {scene} {sampling} row:\n{csv}"));
        let f: Vec<&str> = line.split(',').collect();
        (f[3].parse().unwrap(), f[6].parse().unwrap(), f[7].parse().unwrap())
    };
    for scene in ["furnace", "open sky", "0.2 m lamp"] {
        let (probes, independent, estimated) = last(scene, "independent");
        let (_, sobol, sobol_estimated) = last(scene, "sobol");
        eprintln!(
            "probes, {scene}: {probes} probes; independent: true {independent}, estimated {estimated}; sobol: true {sobol}, estimated {sobol_estimated}"
        );
        assert_eq!(probes, 64);
        assert!(independent < 0.05, "{scene}: true error {independent} after a second");
        assert!(
            (0.5..2.0).contains(&(estimated / independent)),
            "{scene}: reported {estimated} against true {independent}"
        );
        assert!(
            sobol <= independent,
            "{scene}: sobol {sobol} against independent {independent}"
        );
        assert!(
            (sobol < 1e-4 && sobol_estimated < 1e-3) || (0.5..2.0).contains(&(sobol_estimated / sobol)),
            "{scene}: sobol reported {sobol_estimated} against true {sobol}"
        );
    }
    assert!(
        std::fs::read_to_string(out.join("summary.md"))
            .unwrap()
            .contains("Light probes")
    );
    let of = |scene: &str, tech: &str| -> Vec<_> {
        samples
            .iter()
            .filter(|s| s.scene == scene && s.technique == tech)
            .collect()
    };
    for (scene, tech) in [
        ("closed-box-0.5", "path"),
        ("closed-box-0.5", "obscurance"),
        ("sky-plane", "path"),
        ("sky-plane", "obscurance"),
    ] {
        assert!(!of(scene, tech).is_empty(), "{scene} {tech}: no snapshot");
    }
    // Under a uniform sky an upward plane's every path escapes at once: exact.
    for s in of("sky-plane", "path") {
        assert!(s.true_error < 1e-5, "sky-plane path: {}", s.true_error);
    }
    // Obscurance has one bounce of ambient, no interreflection: in the closed box of albedo
    // 0.5 it reads 7.5 % low whatever the time (docs/accuracy.md), and the reported figure
    // must carry that bias, not only its noise.
    let last = of("closed-box-0.5", "obscurance").pop().unwrap();
    assert!(
        (0.06..0.09).contains(&last.true_error),
        "obscurance's bias in the closed box: {}",
        last.true_error
    );
    let reported = last.estimated_error.expect("a reported error") as f64;
    assert!(
        (0.5..2.0).contains(&(reported / last.true_error)),
        "reported {reported} against a true {}",
        last.true_error
    );
    let csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    assert_eq!(csv.lines().count(), samples.len() + 1);
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("| 10 % | 5 % | 2 % | 1 % |"), "{summary}");
    assert!(summary.contains("| sky-plane | path | "), "{summary}");
}

/// `--steps`: snapshots at exactly 4, 16 and 64 steps, each with the denoised figures,
/// where the budget allows; where it does not, the row ends at the steps it reached with
/// one snapshot there (a zero budget: at the first two steps, the fewest a snapshot
/// needs). `path` on the sky plane (closed form 1) takes milliseconds a step.
#[test]
fn a_step_sweep_snapshots_at_powers_of_four() {
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("bench-step-sweep");
    let _ = std::fs::remove_dir_all(&out);
    let cfg = |scene: &str, technique: &str, budget: f64| BenchConfig {
        scenes: vec![scene.into()],
        techniques: vec![technique.into()],
        budget: Duration::from_secs_f64(budget),
        steps: Some(64),
        reference_budget: Duration::from_secs_f64(1.0), // closed forms: never baked
        out_dir: out.clone(),
        cache_dir: out.join("cache"),
        probes: false,
    };
    let samples = run(&cfg("sky-plane", "path", 600.0), &mut |l| eprintln!("{l}")).expect("the bench runs");
    let steps: Vec<u64> = samples.iter().map(|s| s.steps).collect();
    assert_eq!(steps, [4, 16, 64]);
    for s in &samples {
        assert!(s.true_error < 0.05, "{} steps: true error {}", s.steps, s.true_error);
        assert!(
            s.denoised_error <= s.true_error,
            "{} steps: denoised {} against raw {}",
            s.steps,
            s.denoised_error,
            s.true_error
        );
    }
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        summary.starts_with("Snapshots at 4, 16, 64, … up to 64 steps"),
        "{summary}"
    );
    assert!(summary.contains("| sky-plane | path | 4-64 |"), "{summary}");

    let capped = run(&cfg("closed-box-0.5", "path", 0.0), &mut |l| eprintln!("{l}")).expect("the bench runs");
    let steps: Vec<u64> = capped.iter().map(|s| s.steps).collect();
    assert_eq!(steps, [2], "stopped by the budget after the first two steps");
}
