#!/usr/bin/env bash
# Installs what lightmapd needs on a fresh Debian machine with the Rust toolchain:
# Mesa's software Vulkan driver (GPU techniques run on lavapipe when there is no GPU; on
# bookworm, Mesa 25 from bookworm-backports) and
# OpenEXR's command-line tools (tests read the EXR back with `exrheader`). With the
# argument `test`, also the services the tests run against: PostgreSQL
# (scripts/setup-postgres.sh) and an S3-protocol server on loopback (scripts/setup-s3.sh);
# the embedded service (SQLite, local files) needs neither.
# Idempotent: installs only what is missing.
set -euo pipefail

SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
need=()
for pkg in mesa-vulkan-drivers libvulkan1 openexr; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need+=("$pkg")
done
if ((${#need[@]})); then
    echo "setup: installing ${need[*]}" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

# --- Mesa 25's lavapipe on Debian bookworm (docs/deploy.md, "Machines without a GPU") ---
# bookworm's own, Mesa 22.3.6, keeps memory on every step of obscurance, sdb and hemicube
# (a driver leak: their long bakes grow without bound) and runs the GPU techniques three
# to five times slower; bookworm-backports carries Mesa 25.
codename=$(. /etc/os-release 2>/dev/null && echo "${VERSION_CODENAME:-}")
mesa=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
if [ "$codename" = bookworm ] && ! dpkg --compare-versions "${mesa:-0}" ge 25; then
    if ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
        echo "deb http://deb.debian.org/debian bookworm-backports main" |
            $SUDO tee /etc/apt/sources.list.d/bookworm-backports.list >/dev/null
    fi
    echo "setup: installing Mesa 25's Vulkan drivers from bookworm-backports (Mesa ${mesa:-none} installed)" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
        -t bookworm-backports mesa-vulkan-drivers >/dev/null
fi
command -v cargo >/dev/null || { echo "setup: cargo not found; install the Rust toolchain (rustup) first" >&2; exit 1; }

# --- Intel Open Image Denoise, the default denoiser (issue 22): its own script. ---
bash "$(dirname "$0")/setup-oidn.sh"

[ "${1:-}" = "test" ] || exit 0

# --- node and npm for scripts/validate-gltf.sh (Khronos glTF validator, tests/gltf_roundtrip.rs) ---
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    echo "setup: installing nodejs npm" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends nodejs npm >/dev/null
fi

# --- PostgreSQL for the shared-queue tests (issue 11): its own script, see there. ---
bash "$(dirname "$0")/setup-postgres.sh"

# --- S3-compatible object store for tests/service/s3_store.rs (moto on 127.0.0.1:9000) ---
bash "$(dirname "$0")/setup-s3.sh"

# --- A real browser for tests/service/console.rs (issue 23): Debian's chromium, driven headless over
# the DevTools protocol (no chromium-driver needed); fonts so screenshots have glyphs. ---
browser=()
for pkg in chromium fonts-dejavu-core; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || browser+=("$pkg")
done
if ((${#browser[@]})); then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    echo "setup: installing ${browser[*]}" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${browser[@]}" >/dev/null
fi
