//! Writes a library scene that the CLI has no `example` for as .glb, for
//! scripts/peer-bench.sh (issue 20 point 5: a peer baker on the same scene).
//!
//! Usage: `cargo run --release --example peer_scene -- blocks-25k OUT.glb`
//!
//! The scene is `engine::scene::library::procedural_blocks` (25,728 triangles, its own
//! TEXCOORD_1 from the scene builder); its lighting (a sky) is not in the file: the
//! bench passes it to both bakers.

use std::process::ExitCode;

use lightmapd::engine::scene::library;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [name, out] = args.as_slice() else {
        eprintln!("usage: peer_scene blocks-25k|level-256k|closed-box-0.5|closed-box-0.9 OUT.glb");
        return ExitCode::from(2);
    };
    let glb = match name.as_str() {
        "blocks-25k" => library::procedural_blocks().to_glb(),
        // The bench's 256k-triangle generated level (no lightmap UVs: a bake generates
        // them at `--texels-per-unit 4.5` for its 1024² page).
        "level-256k" => library::generated_level(400, 8),
        // Closed cubes of albedo 0.5 and 0.9 whose walls emit 1 - albedo: every texel's
        // answer is 1 (library::closed_box), for Russian roulette's cost in stiff rooms.
        "closed-box-0.5" => library::closed_box(0.5).to_glb(),
        "closed-box-0.9" => library::closed_box(0.9).to_glb(),
        other => {
            eprintln!("unknown scene {other} (known: blocks-25k, level-256k, closed-box-0.5, closed-box-0.9)");
            return ExitCode::from(2);
        }
    };
    if let Err(e) = std::fs::write(out, glb) {
        eprintln!("{out}: {e}");
        return ExitCode::FAILURE;
    }
    ExitCode::SUCCESS
}
