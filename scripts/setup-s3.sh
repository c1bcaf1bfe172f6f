#!/usr/bin/env bash
# An S3-protocol server on loopback for the S3 artifact-store tests (tests/service/s3_store.rs):
# moto's server mode (PyPI `moto` with flask) in a virtual environment under
# $LIGHTMAPD_MOTO_DIR (default /opt/lightmapd-moto), started detached on
# 127.0.0.1:$LIGHTMAPD_MOTO_PORT (default 9000) unless something already listens there.
# Moto keeps buckets in memory: a restart empties it, which suits tests.
# Idempotent: installs only what is missing, starts only what is not running.
set -euo pipefail

dir="${LIGHTMAPD_MOTO_DIR:-/opt/lightmapd-moto}"
port="${LIGHTMAPD_MOTO_PORT:-9000}"
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

listening() {
    # bash's /dev/tcp: no curl or netcat needed.
    (exec 3<>"/dev/tcp/127.0.0.1/$port") 2>/dev/null
}

if listening; then
    echo "setup-s3: something already listens on 127.0.0.1:$port; using it" >&2
    exit 0
fi

# Debian's python3 with venv; the venv's own pip fetches moto from PyPI.
need=()
for pkg in python3 python3-venv; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need+=("$pkg")
done
if ((${#need[@]})); then
    echo "setup-s3: installing ${need[*]}" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi
if [ ! -x "$dir/bin/moto_server" ]; then
    # moto and the web framework its server mode runs on, not `moto[server]`: that extra
    # also pulls the dependencies of every other AWS service moto mocks (CloudFormation
    # linting, Docker, GraphQL...), 64 packages and 114 s against 30 and 19 s here, for
    # nothing S3 needs.
    echo "setup-s3: installing moto's S3 server into $dir" >&2
    $SUDO /usr/bin/python3 -m venv "$dir"
    $SUDO "$dir/bin/pip" install --quiet --disable-pip-version-check 'moto>=5,<6' 'flask!=2.2.0,!=2.2.1' flask-cors
fi

log="${LIGHTMAPD_MOTO_LOG:-$dir/moto.log}"
[ -w "$(dirname "$log")" ] || log="${TMPDIR:-/tmp}/lightmapd-moto.log"
echo "setup-s3: starting moto on 127.0.0.1:$port (log: $log)" >&2
setsid "$dir/bin/moto_server" -H 127.0.0.1 -p "$port" >>"$log" 2>&1 < /dev/null &
for _ in $(seq 1 100); do
    listening && exit 0
    sleep 0.1
done
echo "setup-s3: moto did not start listening on 127.0.0.1:$port within 10 s; see $log" >&2
exit 1
