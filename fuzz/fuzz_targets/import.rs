//! libFuzzer target: any bytes through the service's import path (glTF binary or JSON,
//! with the service's default caps so a hostile size is an error, not an out-of-memory
//! kill), then, for what imports, UV generation when the scene has none, the texel set
//! and its validation, at a 16² lightmap. A panic or an abort is a finding; an error is
//! the expected answer to most inputs, and must say something.
#![no_main]

use libfuzzer_sys::fuzz_target;
use lightmapd::engine::atlas::{Atlas, unwrap, validate};
use lightmapd::engine::scene::{ImportLimits, import_slice_limited};

fuzz_target!(|data: &[u8]| {
    let limits = ImportLimits {
        max_triangles: 200_000,
        max_texture_side: 2048,
    };
    match import_slice_limited(data, None, &limits) {
        Err(e) => assert!(!e.to_string().is_empty()),
        Ok((mut scene, _)) => {
            if scene.needs_lightmap_uvs
                && let Err(e) = unwrap::generate_lightmap_uvs(&mut scene, 16, &unwrap::UvUnwrap)
            {
                assert!(!e.is_empty());
                return;
            }
            if let Ok(mut atlas) = Atlas::build(&scene, 16, 16) {
                validate::validate(&scene, &mut atlas);
            }
        }
    }
});
