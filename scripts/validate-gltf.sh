#!/usr/bin/env bash
# Runs the Khronos glTF validator (npm package gltf-validator, pinned) on each .glb/.gltf
# given; prints one JSON line per file ({"file", "errors", "warnings", "infos", "hints",
# "messages": first errors, "codes", "unused": the pointers of UNUSED_OBJECT infos}) and
# exits 1 when any file has an error.
# Installs the validator on first use into target/tools/gltf-validator (about 1 s, 0.4 MB);
# needs node and npm (scripts/setup.sh test installs them on Debian). Idempotent.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
dir="${CARGO_TARGET_DIR:-$root/target}/tools/gltf-validator"
version="2.0.0-dev.3.10"
command -v node >/dev/null || { echo "validate-gltf: node not found (apt-get install nodejs npm)" >&2; exit 2; }
# Tests run this from several threads at once: the first installs while the others wait on
# the lock (without it, one could find package.json written before the package was whole).
mkdir -p "$dir"
exec 9>"$dir/.install.lock"
flock 9
if [ ! -f "$dir/node_modules/gltf-validator/package.json" ] ||
    ! grep -q "\"version\": \"$version\"" "$dir/node_modules/gltf-validator/package.json"; then
    (cd "$dir" && npm install --silent --no-audit --no-fund --prefix "$dir" "gltf-validator@$version" >&2)
fi
flock -u 9
NODE_PATH="$dir/node_modules" node - "$@" <<'JS'
const validator = require('gltf-validator');
const fs = require('fs');
const path = require('path');
(async () => {
  let failed = false;
  for (const file of process.argv.slice(2)) {
    const bytes = new Uint8Array(fs.readFileSync(file));
    const report = await validator.validateBytes(bytes, {
      maxIssues: 1000,
      externalResourceFunction: (uri) => new Promise((resolve, reject) => {
        fs.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)), (err, data) => err ? reject(err) : resolve(new Uint8Array(data)));
      }),
    });
    const i = report.issues;
    const errors = i.messages.filter((m) => m.severity === 0).slice(0, 10).map((m) => `${m.code} ${m.pointer || ''}: ${m.message}`);
    console.log(JSON.stringify({file, errors: i.numErrors, warnings: i.numWarnings, infos: i.numInfos, hints: i.numHints,
      messages: errors, codes: [...new Set(i.messages.map((m) => m.code))],
      unused: i.messages.filter((m) => m.code === 'UNUSED_OBJECT').map((m) => m.pointer || '')}));
    if (i.numErrors > 0) failed = true;
  }
  process.exit(failed ? 1 : 0);
})().catch((e) => { console.error(e); process.exit(2); });
JS
