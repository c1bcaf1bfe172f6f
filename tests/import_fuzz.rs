//! Hostile input never panics the importer: thousands of deterministic mutations of a
//! valid scene (bit flips, overwritten words, truncations, JSON value swaps) must each
//! import or fail with an error, never unwind; what imports also bakes a step, finite.
//! (This test found two panics inside the gltf crate: a BYTE texture coordinate reaches
//! an `unreachable!`, and an out-of-range POSITION index panics in its validator.)

use std::sync::Arc;

use lightmapd::engine::atlas::{Atlas, validate};
use lightmapd::engine::job::BakeRequest;
use lightmapd::engine::rng::Rng;
use lightmapd::engine::scene::build::{cornell_box, write_glb};
use lightmapd::engine::scene::import_slice;
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
                let plan = lightmapd::engine::plan::build(&scene, &request).unwrap();
                let inputs = BakeInputs {
                    scene,
                    atlas: Arc::new(atlas),
                    lighting: Default::default(),
                    seed: 0,
                    want_direct: false,
                    plan,
                };
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
