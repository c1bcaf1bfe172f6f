//! The command line end to end: the README's main job on the bundled scene, the EXR it
//! writes (read back with the `exr` crate, and with OpenEXR's `exrheader` when it is
//! installed), and exit code 2 with one clear line for bad input.

use std::path::{Path, PathBuf};
use std::process::Command;

use exr::prelude::{ReadChannels, ReadLayers};

mod common;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_lightmapd"))
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lightmapd-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn bundled() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.glb")
}

#[test]
fn bundled_scene_is_what_the_generator_writes() {
    let out = tmp("generated.glb");
    let status = bin().args(["example", "cornell-box", "-o"]).arg(&out).status().unwrap();
    assert!(status.success());
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(bundled()).unwrap(),
        "regenerate scenes/cornell-box.glb with `lightmapd example -o`"
    );
}

/// On a machine without a display session (a server, CI) a GPU bake's stderr holds
/// lightmapd's own lines only: Mesa's device-select layer, which prints "error:
/// XDG_RUNTIME_DIR is invalid or not set" there, is switched off (`quiet_device_select`).
#[test]
fn a_gpu_bake_without_a_display_prints_no_display_errors() {
    let out = tmp("quiet.exr");
    let output = bin()
        .arg("bake")
        .arg(bundled())
        .arg("-o")
        .arg(&out)
        .args(["--resolution", "16", "--steps", "2", "--technique", "hemicube"])
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("NODEVICE_SELECT")
        .env_remove("MESA_VK_DEVICE_SELECT")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(stderr.contains("with hemicube: 2 steps"), "{stderr}");
    assert!(!stderr.contains("XDG_RUNTIME_DIR"), "{stderr}");
    assert!(!stderr.lines().any(|l| l.starts_with("error")), "{stderr}");
}

/// A scene without light of its own (the bundled occlusion room has none), baked without
/// a sky or sun, is warned about before the bake, and its lightmap is exactly zero; with
/// `--sky` there is no warning and the lightmap is lit.
#[test]
fn a_bake_with_no_light_at_all_is_warned_about_before_it_starts() {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/occlusion_room.glb");
    let warning = "warning: the scene has no emissive surface or punctual light and the bake no --sky or --sun: \
                   the lightmap will be exactly zero (give --sky R,G,B for a uniform sky)";
    let bake = |name: &str, extra: &[&str]| -> (String, f32) {
        let out = tmp(name);
        let output = bin()
            .arg("bake")
            .arg(&scene)
            .arg("-o")
            .arg(&out)
            .args([
                "--technique",
                "path",
                "--resolution",
                "64",
                "--steps",
                "1",
                "--no-denoise",
            ])
            .args(extra)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
        assert!(output.status.success(), "{stderr}");
        let peak = common::exr_channels(&out.join("lightmap-0.exr"))
            .iter()
            .flat_map(|(_, v)| v.iter().copied())
            .fold(0.0f32, f32::max);
        (stderr, peak)
    };
    let (dark, peak) = bake("dark", &[]);
    let lines: Vec<&str> = dark.lines().collect();
    let warned = lines.iter().position(|l| *l == warning);
    let baked = lines.iter().position(|l| l.starts_with("baked "));
    assert!(warned.is_some() && warned < baked, "{dark}");
    assert_eq!(peak, 0.0);
    let (lit, peak) = bake("lit", &["--sky", "1,1,1"]);
    assert!(!lit.contains("no emissive surface"), "{lit}");
    assert!(peak > 0.1, "{peak}");
}

/// The engine's warnings read as the command's own do (`warning: …`), not as log lines
/// with a timestamp and a module path: here the bundled Kenney level, whose generated
/// UVs are mostly padding at the default resolution (docs/quality.md), on a software
/// adapter where the GPU techniques would warn about it too.
#[test]
fn engine_warnings_read_as_the_commands_own() {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/third-party/kenney_fps_level.glb");
    let out = tmp("kenney");
    let output = bin()
        .arg("bake")
        .arg(&scene)
        .arg("-o")
        .arg(&out)
        .args(["--technique", "path", "--steps", "1", "--sky", "1,1,1", "--no-denoise"])
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    let padding: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("the generated charts cover"))
        .collect();
    assert_eq!(padding.len(), 1, "{stderr}");
    assert!(
        padding[0].starts_with("warning: the generated charts cover 1 % of their 256x256 page"),
        "{stderr}"
    );
    assert!(
        !stderr.contains(" WARN ") && !stderr.contains("lightmapd::engine"),
        "{stderr}"
    );
}

/// A sun whose radiance was given as if it were an irradiance (40 for a 0.53° disc: 2.7e-3
/// W/m²) is warned about before the bake; one of radiance 1e5 beside the same sky is not.
#[test]
fn a_sun_too_faint_for_its_sky_is_warned_about() {
    let bake = |sun: &str| -> String {
        let output = bin()
            .arg("bake")
            .arg(bundled())
            .arg("-o")
            .arg(tmp(&format!("sun-{sun}.exr")))
            .args(["--resolution", "16", "--steps", "1", "--no-denoise", "--sky", "1,1,1"])
            .arg(format!("--sun=0,-1,0,0.53,{sun},{sun},{sun}"))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
        assert!(output.status.success(), "{stderr}");
        stderr
    };
    let faint = bake("40");
    let line = faint.lines().find(|l| l.contains("the sun gives")).unwrap_or_default();
    assert!(
        line.starts_with("warning: the sun gives 2.688e-3 W/m² (its radiance 4.000e1 per steradian"),
        "{faint}"
    );
    assert!(
        line.ends_with("for an irradiance E give a radiance of E / 6.72e-5"),
        "{line}"
    );
    let bright = bake("100000");
    assert!(!bright.contains("the sun gives"), "{bright}");
}

#[test]
fn bake_writes_a_readable_exr_with_layers_and_metadata() {
    let out = tmp("cornell.exr");
    let output = bin()
        .arg("bake")
        .arg(bundled())
        .arg("-o")
        .arg(&out)
        .args([
            "--resolution",
            "32",
            "--steps",
            "4",
            "--outputs",
            "validity,direct,indirect,sh",
            "--seed",
            "7",
        ])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(stderr.contains("4 steps"), "{stderr}");

    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_file(&out)
        .unwrap();
    let layer = &image.layer_data[0];
    assert_eq!(layer.size.0, 32);
    assert_eq!(layer.size.1, 32);
    let names: Vec<String> = layer.channel_data.list.iter().map(|c| c.name.to_string()).collect();
    for want in [
        "R",
        "G",
        "B",
        "direct.R",
        "indirect.G",
        "validity.Y",
        "sh.x.R",
        "sh.y.G",
        "sh.z.B",
    ] {
        assert!(names.iter().any(|n| n == want), "missing channel {want} in {names:?}");
    }
    let channel = |name: &str| -> Vec<f32> {
        let c = layer
            .channel_data
            .list
            .iter()
            .find(|c| c.name.to_string() == name)
            .unwrap();
        c.sample_data.values_as_f32().collect()
    };
    let (r, dr, ir, valid) = (
        channel("R"),
        channel("direct.R"),
        channel("indirect.R"),
        channel("validity.Y"),
    );
    let n_valid = valid.iter().filter(|v| **v == 1.0).count();
    assert!(n_valid > 100, "{n_valid} valid texels");
    assert!(valid.iter().all(|v| *v == 0.0 || *v == 1.0));
    // The full lightmap is direct + indirect wherever the indirect part is not clamped.
    for k in 0..r.len() {
        if valid[k] == 1.0 && ir[k] > 0.0 {
            assert!(
                (r[k] - dr[k] - ir[k]).abs() <= 1e-5 * r[k].max(1.0),
                "texel {k}: {} != {} + {}",
                r[k],
                dr[k],
                ir[k]
            );
        }
        assert!(r[k].is_finite() && r[k] >= 0.0);
    }
    // Something is lit.
    assert!(r.iter().any(|v| *v > 0.1));
    let attrs = &layer.attributes.other;
    let text = |k: &str| match attrs.get(&exr::prelude::Text::from(k)) {
        Some(exr::prelude::AttributeValue::Text(t)) => t.to_string(),
        other => panic!("attribute {k}: {other:?}"),
    };
    assert_eq!(text("lightmapd:technique"), "path");
    assert_eq!(text("lightmapd:seed"), "7");
    assert!(text("lightmapd:params").contains("samples_per_step"));
    assert!(matches!(
        attrs.get(&exr::prelude::Text::from("lightmapd:steps")),
        Some(exr::prelude::AttributeValue::I32(4))
    ));

    // OpenEXR's own reader, where installed (the README's set-up installs it).
    if let Ok(o) = Command::new("exrheader").arg(&out).output() {
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "exrheader failed: {text}");
        assert!(text.contains("validity.Y, 32-bit floating-point"), "{text}");
        assert!(text.contains("lightmapd:technique (type string): \"path\""), "{text}");
    } else {
        eprintln!("exrheader not installed: checked with the exr crate only");
    }
}

fn assert_bad_input(args: &[&str], scene: &Path, expect: &str) {
    let output = bin()
        .arg("bake")
        .arg(scene)
        .args(["-o"])
        .arg(tmp("never.exr"))
        .args(args)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(2), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "one line, got: {stderr}");
    assert!(stderr.starts_with("error: ") && stderr.contains(expect), "{stderr}");
    assert!(!stderr.contains("panicked"));
}

#[test]
fn malformed_glb_exits_2_with_one_line() {
    let bad = tmp("broken.glb");
    let mut glb = std::fs::read(bundled()).unwrap();
    glb.truncate(glb.len() / 2);
    std::fs::write(&bad, &glb).unwrap();
    assert_bad_input(&[], &bad, "broken.glb: not a glTF 2.0 file: broken GLB container");

    let garbage = tmp("garbage.glb");
    std::fs::write(&garbage, b"definitely not a scene").unwrap();
    assert_bad_input(&[], &garbage, "neither a GLB header");

    assert_bad_input(
        &[],
        Path::new("/nonexistent/scene.glb"),
        "cannot read /nonexistent/scene.glb",
    );
}

#[test]
fn bad_options_exit_2() {
    let scene = bundled();
    assert_bad_input(&["--technique", "magic"], &scene, "unknown technique \"magic\"");
    assert_bad_input(
        &["--resolution", "0", "--steps", "1"],
        &scene,
        "lightmap resolution 0x0 is out of range",
    );
    assert_bad_input(
        &["--params", "{\"samples_per_step\": 0}", "--steps", "1"],
        &scene,
        "params.samples_per_step must be in 1..=4096",
    );
    assert_bad_input(
        &["--params", "{\"bogus\": 1}", "--steps", "1"],
        &scene,
        "unknown field `bogus`",
    );
    assert_bad_input(
        &["--sun", "0,0,0,0.5,1,1,1", "--steps", "1"],
        &scene,
        "sun direction must not be zero",
    );
    assert_bad_input(
        &["--sun", "0,-1,0,0,1,1,1", "--steps", "1"],
        &scene,
        "angular_diameter_deg must be in (0, 180)",
    );
    assert_bad_input(&["--seconds=-1"], &scene, "stop.seconds must be a positive number");
    // What the technique table's row does not allow, refused before baking (issue 21).
    assert_bad_input(
        &["--technique", "path", "--outputs", "ao", "--steps", "1"],
        &scene,
        "outputs[0]: path cannot write the \"ao\" layer; techniques that can: obscurance, sdf",
    );
    assert_bad_input(
        &["--technique", "sdf", "--outputs", "sh", "--steps", "1"],
        &scene,
        "outputs[0]: sdf cannot write the \"sh\" layer; techniques that can: path",
    );
    // The shadowmask's lights are checked against the scene before baking (issue 26).
    assert_bad_input(
        &[
            "--sun",
            "0,-1,0,0.5,1,1,1",
            "--outputs",
            "shadowmask",
            "--shadowmask-lights",
            "sun,Lamp",
            "--steps",
            "1",
        ],
        &scene,
        "shadowmask_lights[1]: no light is called \"Lamp\"; the job has: sun",
    );
    let probes = tmp("never-probes.json");
    assert_bad_input(
        &[
            "--probes",
            probes.to_str().unwrap(),
            "--probe-spacing",
            "0",
            "--steps",
            "1",
        ],
        &scene,
        "probes.spacing must be a positive distance, got 0",
    );
    assert_bad_input(
        &[
            "--probes",
            probes.to_str().unwrap(),
            "--probe-spacing",
            "0.5",
            "--probe-subdivide",
            "7",
            "--steps",
            "1",
        ],
        &scene,
        "probes.subdivide must be in 0..=4, got 7",
    );
    assert!(!probes.exists());
    assert_bad_input(
        &["--resolution", "512", "--max-page-size", "256", "--steps", "1"],
        &scene,
        "max_page_size 256 is below resolution 512: pages start resolution wide and grow up to max_page_size",
    );
    // clap's own errors use exit code 2 as well.
    let o = bin().args(["bake", "--resolution", "abc"]).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn a_failing_bake_leaves_an_existing_lightmap_alone() {
    let out = tmp("keep.exr");
    std::fs::write(&out, b"previous lightmap").unwrap();
    let o = bin()
        .arg("bake")
        .arg(bundled())
        .arg("-o")
        .arg(&out)
        .args(["--technique", "magic"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert_eq!(std::fs::read(&out).unwrap(), b"previous lightmap");
}

#[test]
fn target_error_stops_a_bake_of_the_bundled_scene() {
    let out = tmp("target.exr");
    let output = bin()
        .arg("bake")
        .arg(bundled())
        .arg("-o")
        .arg(&out)
        .args(["--resolution", "16", "--target-error", "0.25", "--steps", "100000"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(stderr.contains("(stopped by TargetError)"), "{stderr}");
    // Never before the minimum step count, and well before the step limit.
    let steps: u64 = stderr
        .split(" steps in ")
        .next()
        .unwrap()
        .rsplit(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!((16..100000).contains(&steps), "{steps} steps");
    assert!(stderr.contains("plan: ran: bvh, path trace"), "{stderr}");
}

#[test]
fn scene_without_lightmap_uvs_bakes_and_writes_them() {
    use lightmapd::engine::scene::build::{cornell_box, remove_lightmap_uvs, write_glb};
    let (mut json, buffer) = cornell_box().to_gltf();
    remove_lightmap_uvs(&mut json, None);
    let scene = tmp("no-uv.glb");
    std::fs::write(&scene, write_glb(&json, &buffer)).unwrap();
    let (out, gltf) = (tmp("no-uv.exr"), tmp("with-uv.glb"));
    let output = bin()
        .arg("bake")
        .arg(&scene)
        .arg("-o")
        .arg(&out)
        .arg("--write-gltf")
        .arg(&gltf)
        .args(["--resolution", "64", "--steps", "2"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(
        stderr.contains("no TEXCOORD_1: lightmap UVs will be generated"),
        "{stderr}"
    );
    assert!(stderr.contains("generated lightmap UVs: "), "{stderr}");
    let (_, report) = lightmapd::engine::scene::import_file(&gltf).unwrap();
    assert!(report.has_lightmap_uvs);
    assert!(out.exists());
}

/// `--probes` writes the documented JSON: convention, basis, and probes with world
/// positions, nine RGB coefficients, validity and an error; the bundled Cornell box is
/// closed, so probes inside its walls' thickness-free box are valid and lit.
#[test]
fn bake_writes_probes_beside_the_lightmap() {
    let out = tmp("probes.exr");
    let probes = tmp("probes.json");
    let o = bin()
        .arg("bake")
        .arg(bundled())
        .args(["-o"])
        .arg(&out)
        .args([
            "--resolution",
            "16",
            "--steps",
            "2",
            "--probe-spacing",
            "0.25",
            "--probe-steps",
            "2",
            "--probes",
        ])
        .arg(&probes)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("probes ("), "{stderr}");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&probes).unwrap()).unwrap();
    assert!(v["convention"].as_str().unwrap().starts_with("incident radiance"));
    let list = v["probes"].as_array().unwrap();
    assert!(list.len() >= 8, "{} probes", list.len());
    let lit = list
        .iter()
        .filter(|p| p["valid"].as_bool().unwrap() && p["sh"][0][0].as_f64().unwrap() > 0.0)
        .count();
    assert!(lit > 0, "no lit probe");
    for p in list {
        assert_eq!(p["sh"].as_array().unwrap().len(), 9);
        assert_eq!(p["position"].as_array().unwrap().len(), 3);
        assert!(p["error"].as_f64().unwrap() >= 0.0);
    }
}

/// Issue 19 point 7: a bake that needs two pages (the ground's authored page and the
/// ball's generated one) writes `lightmap-0.exr`, `lightmap-1.exr` and `lightmaps.json`
/// into the folder `-o` names; an `-o` ending in `.exr` is refused with exit 2 before
/// any sampling, and leaves nothing behind.
#[test]
fn a_bake_of_several_pages_writes_a_folder_with_its_manifest() {
    use lightmapd::engine::scene::build::{remove_lightmap_uvs, write_glb};
    use lightmapd::engine::scene::library::sphere_over_plane;
    let (mut json, bin_data) = sphere_over_plane().to_gltf();
    remove_lightmap_uvs(&mut json, Some(&[1]));
    let scene = tmp("two-pages.glb");
    std::fs::write(&scene, write_glb(&json, &bin_data)).unwrap();

    let one_file = tmp("two-pages.exr");
    let _ = std::fs::remove_file(&one_file);
    let output = bin()
        .arg("bake")
        .arg(&scene)
        .arg("-o")
        .arg(&one_file)
        .args(["--resolution", "64", "--steps", "1000000", "--sky", "1,1,1"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("the bake needs 2 lightmap pages and -o") && stderr.contains("give -o a folder"),
        "{stderr}"
    );
    assert!(!one_file.exists());

    let dir = tmp("two-pages");
    let _ = std::fs::remove_dir_all(&dir);
    let output = bin()
        .arg("bake")
        .arg(&scene)
        .arg("-o")
        .arg(&dir)
        .args(["--resolution", "64", "--steps", "2", "--sky", "1,1,1"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(stderr.contains("(2 pages and lightmaps.json)"), "{stderr}");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("lightmaps.json")).unwrap()).unwrap();
    assert_eq!(manifest["format"], "lightmapd.lightmaps/1");
    let pages = manifest["pages"].as_array().unwrap();
    assert_eq!(pages.len(), 2);
    for (p, page) in pages.iter().enumerate() {
        assert_eq!(page["file"], format!("lightmap-{p}.exr"));
        assert_eq!((page["width"].as_u64(), page["height"].as_u64()), (Some(64), Some(64)));
        assert!(page["valid_texels"].as_u64().unwrap() > 100, "{page}");
        let image = exr::prelude::read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .all_layers()
            .all_attributes()
            .from_file(dir.join(format!("lightmap-{p}.exr")))
            .unwrap();
        let layer = &image.layer_data[0];
        assert_eq!((layer.size.0, layer.size.1), (64, 64));
        let attr = |name: &str| layer.attributes.other.get(&exr::prelude::Text::from(name)).cloned();
        assert_eq!(
            attr("lightmapd:page"),
            Some(exr::prelude::AttributeValue::I32(p as i32))
        );
        assert_eq!(attr("lightmapd:pages"), Some(exr::prelude::AttributeValue::I32(2)));
    }
    let nodes = manifest["nodes"].as_array().unwrap();
    assert_eq!(
        nodes
            .iter()
            .map(|n| (n["name"].clone(), n["page"].clone()))
            .collect::<Vec<_>>(),
        vec![
            (serde_json::json!("ground"), serde_json::json!(0)),
            (serde_json::json!("ball"), serde_json::json!(1))
        ]
    );
    assert_eq!(nodes[0]["scale_offset"], serde_json::json!([1.0, 1.0, 0.0, 0.0]));
}

/// Issue 19 point 10 with the real CPU `path`: one step of 4096 samples per texel over
/// the bundled Cornell box at 64² takes 14.8 s on this machine (3,093 texels); under
/// `--seconds 0.5` the step is cut short at the limit and, with no step done, the bake
/// exits 2 saying so, seconds after it started instead of a step's length later.
#[test]
fn a_step_longer_than_the_budget_stops_at_the_budget() {
    let out = tmp("budget.exr");
    let _ = std::fs::remove_file(&out);
    let started = std::time::Instant::now();
    let output = bin()
        .arg("bake")
        .arg(bundled())
        .arg("-o")
        .arg(&out)
        .args([
            "--resolution",
            "64",
            "--seconds",
            "0.5",
            "--params",
            r#"{"samples_per_step": 4096, "device": "cpu"}"#,
        ])
        .output()
        .unwrap();
    let wall = started.elapsed();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("the time limit of 0.500 s ended before the first step of path was done"),
        "{stderr}"
    );
    assert!(!out.exists());
    // Import, texel validation and the BVH take well under a second here; the step alone
    // would take about 15 s.
    assert!(wall < std::time::Duration::from_secs(8), "{wall:?}");
}

/// Progress inside a step (issue 19 point 10): while one long CPU `path` step runs (the
/// bundled Cornell box at 64², 4096 samples a texel, about 15 s here), the step's
/// progress (`bake::StepProgress`, what the CLI's bar shows beside the step count) moves
/// up from 0 in chunks of 256 texels and never goes back.
#[test]
fn a_long_step_reports_how_far_it_is() {
    use lightmapd::engine::bake::{StepProgress, StopCriteria};
    use lightmapd::engine::job::{self, BakeOptions, BakeRequest};
    let (scene, _) = lightmapd::engine::scene::import_file(&bundled()).unwrap();
    let progress = StepProgress::new();
    let options = BakeOptions {
        step_progress: Some(progress.clone()),
        ..Default::default()
    };
    let request = BakeRequest {
        resolution: 64,
        params: serde_json::json!({"samples_per_step": 4096, "device": "cpu"}),
        stop: StopCriteria {
            seconds: Some(3.0),
            ..Default::default()
        },
        ..Default::default()
    };
    let done = std::sync::atomic::AtomicBool::new(false);
    let mut seen = Vec::new();
    let outcome = std::thread::scope(|scope| {
        let bake = scope.spawn(|| {
            let mut observer = |_: lightmapd::engine::bake::BakeEvent<'_>| std::ops::ControlFlow::Continue(());
            let r = job::bake(
                std::sync::Arc::new(scene),
                &request,
                &options,
                &mut observer,
                &mut |_| {},
                &mut |_| {},
            );
            done.store(true, std::sync::atomic::Ordering::SeqCst);
            r
        });
        while !done.load(std::sync::atomic::Ordering::SeqCst) {
            seen.push(progress.permille());
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        bake.join().unwrap()
    });
    // The limit cut the one step short: no step was done.
    let err = outcome.err().expect("the step is longer than the limit").to_string();
    assert!(err.contains("ended before the first step of path was done"), "{err}");
    let moving: Vec<u32> = seen.iter().copied().filter(|p| *p > 0).collect();
    assert!(
        moving.iter().any(|p| *p < 1000) && !moving.is_empty(),
        "no progress inside the step: {seen:?}"
    );
    assert!(
        moving.windows(2).all(|w| w[0] <= w[1]),
        "progress went back: {moving:?}"
    );
    eprintln!("progress seen inside the step (thousandths): {:?}", {
        let mut d = moving.clone();
        d.dedup();
        d
    });
}
