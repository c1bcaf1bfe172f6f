#!/usr/bin/env bash
# Fuzzes the glTF importer (and texel-set building) with libFuzzer for a bounded time:
#   bash scripts/fuzz.sh [SECONDS]        (default 300)
# Needs the nightly toolchain and cargo-fuzz (`rustup toolchain install nightly`,
# `cargo install cargo-fuzz`); without them it says so and exits 0, since CI runs the
# stable property tests (tests/import_fuzz.rs) instead. The corpus starts from the
# bundled scene in both encodings; findings land in fuzz/artifacts/import/ and belong in
# tests/import_fuzz.rs as regression cases. The last lines of libFuzzer's output give
# the executions and their rate (docs/reliability.md records a run).
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-300}"
if ! cargo +nightly --version >/dev/null 2>&1 || ! cargo +nightly fuzz --version >/dev/null 2>&1; then
    echo "fuzz.sh: needs the nightly toolchain and cargo-fuzz; skipped" >&2
    exit 0
fi
corpus=fuzz/corpus/import
mkdir -p "$corpus"
cp scenes/cornell-box.glb "$corpus/cornell-box.glb"
# The same scene as .gltf JSON with its buffer as a data URI, so JSON paths get seeds too.
python3 - "$corpus" <<'PY'
import base64, json, struct, sys
data = open("scenes/cornell-box.glb", "rb").read()
json_len = struct.unpack_from("<I", data, 12)[0]
doc = json.loads(data[20:20 + json_len])
bin_start = 20 + json_len
bin_len = struct.unpack_from("<I", data, bin_start)[0]
buf = data[bin_start + 8: bin_start + 8 + bin_len]
doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(buf).decode()
open(sys.argv[1] + "/cornell-box.gltf", "w").write(json.dumps(doc))
PY
# -s none: no AddressSanitizer (the importer is safe Rust; panics and aborts are what we
# look for), which keeps the instrumented build of wgpu and friends tolerable.
cd fuzz
cargo +nightly fuzz run -s none import "corpus/import" -- \
    -max_total_time="$seconds" -rss_limit_mb=4096 -max_len=1048576 -print_final_stats=1 2>&1 |
    tee ../target/fuzz-import.log | grep -E "^(#[0-9]+ *(DONE|pulse|INITED)|stat::|==|SUMMARY|Done)" || true
echo "fuzz.sh: full log in target/fuzz-import.log; findings (if any) in fuzz/artifacts/import/"
ls artifacts/import 2>/dev/null || true
