//! Hostile input never panics the importer: thousands of deterministic mutations of a
//! valid scene (bit flips, overwritten words, truncations, JSON value swaps) must each
//! import or fail with an error, never unwind; what imports also bakes a step, finite.
//! (This test found two panics inside the gltf crate: a BYTE texture coordinate reaches
//! an `unreachable!`, and an out-of-range POSITION index panics in its validator.)
//!
//! Issue 12 adds the service's path: scenes without lightmap UVs, mutated, go through
//! import with the service's caps, UV generation and the texel set; and the `.gltf` JSON
//! form is truncated at every length and has whole values swapped for hostile ones.
//! Every refusal must say something. `scripts/fuzz.sh` runs the same path under
//! libFuzzer (fuzz/fuzz_targets/import.rs) for longer; the inputs it found crashing are
//! kept in tests/fuzz_regressions/ and replayed here.

use std::sync::Arc;

use lightmapd::engine::atlas::{Atlas, unwrap, validate};
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::rng::Rng;
use lightmapd::engine::scene::build::{cornell_box, remove_lightmap_uvs, write_glb};
use lightmapd::engine::scene::{ImportLimits, import_slice, import_slice_limited};
use lightmapd::engine::technique::{self, BakeInputs};

#[test]
fn mutated_glb_files_never_panic() {
    let glb = cornell_box().to_glb();
    let (mut ok, mut err) = (0, 0);
    for case in 0..3000u64 {
        let mut rng = Rng::new(42, case, 0, 0);
        let mut bytes = glb.clone();
        match case % 3 {
            0 => {
                for _ in 0..1 + rng.next_u32() % 8 {
                    let i = rng.next_u32() as usize % bytes.len();
                    bytes[i] ^= 1 << (rng.next_u32() % 8);
                }
            }
            1 => {
                let i = rng.next_u32() as usize % (bytes.len() - 4);
                let word = [0u32, u32::MAX, 0x7fc0_0000, 0x7f80_0000, 1 << 31][rng.next_u32() as usize % 5];
                bytes[i..i + 4].copy_from_slice(&word.to_le_bytes());
            }
            _ => bytes.truncate(rng.next_u32() as usize % bytes.len()),
        }
        // What imports must also bake: texel set, validation and a path step.
        let run = || {
            let (scene, _) = import_slice(&bytes, None)?;
            if let Ok(mut atlas) = Atlas::build(&scene, 16, 16) {
                validate::validate(&scene, &mut atlas);
                let scene = Arc::new(scene);
                let request = BakeRequest::default();
                let plan = lightmapd::engine::job::plan_for(&scene, &request).unwrap();
                let inputs = BakeInputs::new(scene, Arc::new(atlas), Default::default(), 0, plan);
                let mut t = technique::create("path", inputs, &serde_json::Value::Null).unwrap();
                t.step().unwrap();
                assert!(t.snapshot().unwrap().estimate().total.iter().all(|v| v.is_finite()));
            }
            Ok::<(), lightmapd::engine::scene::ImportError>(())
        };
        match std::panic::catch_unwind(run) {
            Ok(Ok(())) => ok += 1,
            Ok(Err(_)) => err += 1,
            Err(_) => panic!("case {case}: the importer panicked"),
        }
    }
    eprintln!("{ok} mutated files imported, {err} refused with an error");
    assert!(err > 1000, "most mutations break the file");
}

#[test]
fn mutated_json_values_never_panic() {
    let (json, bin) = cornell_box().to_gltf();
    let text = serde_json::to_string(&json).unwrap();
    // Every number in the document, replaced in turn by hostile values.
    let positions: Vec<usize> = text
        .match_indices(|c: char| c.is_ascii_digit())
        .map(|(i, _)| i)
        .collect();
    let hostile = ["-1", "4294967296", "1e309", "0", "99999999"];
    // Only the first digit of each number (a run of digits is one number).
    let starts: Vec<usize> = positions
        .iter()
        .copied()
        .filter(|p| *p == 0 || !text.as_bytes()[p - 1].is_ascii_digit())
        .collect();
    for (pos, value) in starts.iter().flat_map(|p| hostile.iter().map(move |v| (p, *v))) {
        let end = text[*pos..]
            .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == 'e' || c == '-'))
            .unwrap()
            + pos;
        let mutated = format!("{}{}{}", &text[..*pos], value, &text[end..]);
        let Ok(doc) = serde_json::from_str::<serde_json::Value>(&mutated) else {
            continue;
        };
        let bytes = write_glb(&doc, &bin);
        if std::panic::catch_unwind(|| import_slice(&bytes, None).map(|_| ())).is_err() {
            panic!(
                "the importer panicked with {value} at byte {pos}: …{}…",
                &mutated[pos.saturating_sub(40)..(*pos + 40).min(mutated.len())]
            );
        }
    }
}

/// What the service does with an upload and then a job: import under caps, generate
/// lightmap UVs when there are none, build and validate the texel set. `Err` carries the
/// message a client would see.
fn service_path(bytes: &[u8]) -> Result<usize, String> {
    let limits = ImportLimits {
        max_triangles: 100_000,
        max_texture_side: 1024,
    };
    let (mut scene, _) = import_slice_limited(bytes, None, &limits).map_err(|e| e.to_string())?;
    if scene.needs_lightmap_uvs {
        unwrap::generate_lightmap_uvs(&mut scene, 32, &unwrap::UvUnwrap)?;
    }
    let mut atlas = Atlas::build(&scene, 32, 32).map_err(|e| e.to_string())?;
    validate::validate(&scene, &mut atlas);
    Ok(atlas.report().valid_texels)
}

/// Runs `service_path` on `bytes`; a panic fails the test with `what`, an error must
/// have a message. Returns whether it imported.
fn never_panics(bytes: &[u8], what: &str) -> bool {
    match std::panic::catch_unwind(|| service_path(bytes)) {
        Ok(Ok(_)) => true,
        Ok(Err(msg)) => {
            assert!(!msg.trim().is_empty(), "{what}: an error without a message");
            false
        }
        Err(_) => panic!("{what}: import, UV generation or the texel set panicked"),
    }
}

#[test]
fn mutated_scenes_without_lightmap_uvs_never_panic_through_uv_generation_and_texel_set() {
    let (mut gltf, bin) = cornell_box().to_gltf();
    remove_lightmap_uvs(&mut gltf, None);
    let glb = write_glb(&gltf, &bin);
    assert!(
        never_panics(&glb, "the unmutated scene"),
        "the UV-less Cornell box bakes"
    );
    let (mut ok, mut err) = (0, 0);
    for case in 0..600u64 {
        let mut rng = Rng::new(7, case, 0, 0);
        let mut bytes = glb.clone();
        match case % 3 {
            0 => {
                for _ in 0..1 + rng.next_u32() % 8 {
                    let i = rng.next_u32() as usize % bytes.len();
                    bytes[i] ^= 1 << (rng.next_u32() % 8);
                }
            }
            1 => {
                // Hostile floats and counts in the binary chunk (positions, indices).
                let i = rng.next_u32() as usize % (bytes.len() - 4);
                let word = [0u32, u32::MAX, 0x7fc0_0000, 0x7f80_0000, 0x4f00_0000][rng.next_u32() as usize % 5];
                bytes[i..i + 4].copy_from_slice(&word.to_le_bytes());
            }
            _ => bytes.truncate(rng.next_u32() as usize % bytes.len()),
        }
        if never_panics(&bytes, &format!("case {case}")) {
            ok += 1;
        } else {
            err += 1;
        }
    }
    eprintln!("{ok} mutated UV-less scenes went through, {err} refused with an error");
    assert!(
        ok >= 10 && err >= 100,
        "the mutations both keep and break scenes: {ok} / {err}"
    );
}

#[test]
fn truncated_and_rewritten_gltf_json_never_panics() {
    use base64::Engine as _;
    let (mut gltf, bin) = cornell_box().to_gltf();
    gltf["buffers"][0]["uri"] = serde_json::json!(format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    ));
    let text = serde_json::to_string(&gltf).unwrap();
    assert!(never_panics(text.as_bytes(), "the unmutated .gltf"));
    // Every prefix up to the buffer (past it only the base64 gets shorter), in steps.
    let json_end = text.find("data:").unwrap();
    for len in (0..json_end).step_by(7) {
        assert!(!never_panics(
            &text.as_bytes()[..len],
            &format!("prefix of {len} bytes")
        ));
    }
    // Each JSON value of the structure (not the buffer) replaced by a hostile one.
    let hostile = [
        serde_json::json!(null),
        serde_json::json!(-1),
        serde_json::json!(4294967296u64),
        serde_json::json!("x"),
        serde_json::json!([]),
        serde_json::json!({}),
    ];
    let mut paths = Vec::new();
    fn walk(v: &serde_json::Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
        match v {
            serde_json::Value::Object(m) => {
                for (k, c) in m {
                    path.push(k.clone());
                    out.push(path.clone());
                    walk(c, path, out);
                    path.pop();
                }
            }
            serde_json::Value::Array(a) => {
                for (i, c) in a.iter().enumerate() {
                    path.push(i.to_string());
                    out.push(path.clone());
                    walk(c, path, out);
                    path.pop();
                }
            }
            _ => {}
        }
    }
    walk(&gltf, &mut Vec::new(), &mut paths);
    let mut tried = 0;
    for (n, path) in paths.iter().enumerate() {
        if path.first().map(String::as_str) == Some("buffers") && path.len() > 2 {
            continue;
        }
        let mut doc = gltf.clone();
        let mut slot = &mut doc;
        for key in path {
            slot = match slot {
                serde_json::Value::Array(a) => &mut a[key.parse::<usize>().unwrap()],
                other => &mut other[key.as_str()],
            };
        }
        *slot = hostile[n % hostile.len()].clone();
        never_panics(
            serde_json::to_string(&doc).unwrap().as_bytes(),
            &format!("{} = {}", path.join("."), hostile[n % hostile.len()]),
        );
        tried += 1;
    }
    eprintln!("{tried} rewritten .gltf documents");
    assert!(tried > 100);
}

/// Inputs libFuzzer found crashing (docs/reliability.md), replayed: each must now be
/// refused with a message.
#[test]
fn fuzzer_findings_are_refused_with_a_message() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_regressions");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let bytes = std::fs::read(&path).unwrap();
        assert!(
            !never_panics(&bytes, &path.display().to_string()),
            "{} imports",
            path.display()
        );
        n += 1;
    }
    assert!(n >= 1);
    // The first finding: a GLB header declaring a total length below its own 12 bytes,
    // which gltf 1.4 subtracts from unchecked.
    let bytes = std::fs::read(dir.join("glb-length-underflow.bin")).unwrap();
    let err = import_slice(&bytes, None).unwrap_err().to_string();
    assert_eq!(
        err,
        "not a glTF 2.0 file: broken GLB container: the header declares 0 bytes in all, less than the header itself"
    );
}
