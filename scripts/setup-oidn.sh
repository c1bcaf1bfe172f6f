#!/usr/bin/env bash
# Intel Open Image Denoise (OIDN) 2.5.1 for lightmapd's default denoiser
# (src/engine/post/oidn.rs), from PyPI's `pyoidn` wheel, which ships the C library
# (manylinux2014 x86_64; Debian has no package). Only what lightmapd loads is kept:
# libOpenImageDenoise, its core (which carries the trained weights), the CPU device with
# TBB and the CUDA device (used on an NVIDIA machine; it needs only the driver's
# libcuda). 57 MB installed from an 88 MB download; the SYCL/HIP devices and the
# Python bindings are left out.
#
# Installs into $LIGHTMAPD_OIDN_DIR (default /opt/lightmapd-oidn): lib/ with the
# libraries, VERSION. The binary looks there without being told (and in
# $LIGHTMAPD_OIDN_DIR when set). Without this directory lightmapd still builds and
# runs, and uses its own denoiser.
# Idempotent: a directory whose VERSION matches is left as it is (the download runs once
# per machine, like scripts/setup-s3.sh's moto). Cost measured on the 2-core VM: 7.3 s
# the first time (pip download 3.3 s at ~110 MB/s, extraction ~2 s); 0.01 s when installed.
set -euo pipefail

version="2.5.1"
wheel_version="2.5.1.0"
dir="${LIGHTMAPD_OIDN_DIR:-/opt/lightmapd-oidn}"
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

if [ "$(cat "$dir/VERSION" 2>/dev/null)" = "$version" ] && [ -e "$dir/lib/libOpenImageDenoise.so.$version" ]; then
    exit 0
fi
if [ "$(uname -m)" != "x86_64" ]; then
    echo "setup-oidn: no OIDN wheel for $(uname -m) is used; lightmapd will use its own denoiser" >&2
    exit 0
fi

# pip from a throwaway virtual environment: Debian's python3 with venv, as setup-s3.sh.
need=()
for pkg in python3 python3-venv; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need+=("$pkg")
done
if ((${#need[@]})); then
    echo "setup-oidn: installing ${need[*]}" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
echo "setup-oidn: downloading pyoidn $wheel_version (OIDN $version) into $dir" >&2
if command -v pip3 >/dev/null 2>&1; then
    pip3 download --quiet --no-deps --disable-pip-version-check -d "$tmp" "pyoidn==$wheel_version"
else
    /usr/bin/python3 -m venv "$tmp/venv"
    "$tmp/venv/bin/pip" download --quiet --no-deps --disable-pip-version-check -d "$tmp" "pyoidn==$wheel_version"
fi
wheel="$(ls "$tmp"/pyoidn-*.whl)"

# Extract only the libraries lightmapd needs, as real files with the sonames the loader
# asks for (a wheel stores no symlinks).
mkdir -p "$tmp/out/lib"
/usr/bin/python3 - "$wheel" "$tmp/out/lib" "$version" <<'PY'
import sys, zipfile, os
wheel, out, v = sys.argv[1:4]
want = {
    f"libOpenImageDenoise.so.{v}": ["libOpenImageDenoise.so.2"],
    f"libOpenImageDenoise_core.so.{v}": [],
    f"libOpenImageDenoise_device_cpu.so.{v}": [],
    f"libOpenImageDenoise_device_cuda.so.{v}": [],
    "libtbb.so.12": [],
}
with zipfile.ZipFile(wheel) as z:
    names = {os.path.basename(n): n for n in z.namelist() if "/oidn/lib/" in n}
    for lib, links in want.items():
        if lib not in names:
            sys.exit(f"setup-oidn: {lib} is not in {wheel}")
        with z.open(names[lib]) as src, open(os.path.join(out, lib), "wb") as dst:
            dst.write(src.read())
        os.chmod(os.path.join(out, lib), 0o755)
        for link in links:
            os.symlink(lib, os.path.join(out, link))
PY
echo "$version" > "$tmp/out/VERSION"
$SUDO mkdir -p "$dir"
$SUDO rm -rf "$dir/lib"
$SUDO cp -a "$tmp/out/lib" "$tmp/out/VERSION" "$dir/"
echo "setup-oidn: OIDN $version installed in $dir ($(du -sh "$dir" | cut -f1))" >&2
