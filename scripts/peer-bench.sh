#!/usr/bin/env bash
# peer-bench.sh: lightmapd's CPU `path` side by side with Blender Cycles (issue 20, point 5).
#
# Installs Blender from Debian (`apt-get install -y blender python3-numpy time`: 3.4.1;
# skipped when `blender` is on PATH, /usr/bin/python3 imports numpy and /usr/bin/time
# exists), writes the scenes
# (the bundled Cornell box; blocks-25k through examples/peer_scene.rs),
# and for every sample count N and seeds 1 and 2 bakes, one right after the other:
#   - lightmapd `path` on the CPU, raw estimate (no denoiser), N/4 steps of 4 samples;
#   - Cycles on the same TEXCOORD_1 texel grid, N samples (scripts/peer/cycles_bake.py:
#     DIFFUSE, direct + indirect, colour off = irradiance / pi, 1024 bounces, no clamping,
#     no denoising, adaptive sampling off, CPU, 2 threads), one Blender process a bake;
# then one long lightmapd bake (seed 99, with `--outputs validity`) as the reference, and
# prints a markdown report (scripts/peer/compare.py): seconds and true error of every
# bake against the reference, the convention check, and time to the same error.
#
# Takes about 5 minutes on a 2-core machine for the Cornell box (its 16384-sample
# reference is 3 of them); blocks-25k (PEER_SCENES="cornell-box blocks-25k") adds about
# 3.5 more (its reference 3.6), plus a build of examples/peer_scene.rs when missing.
# Kept out of CI on purpose: nothing in .ci/ or the tests calls it (it installs ~400 MB of
# packages and measures wall time, which needs a quiet machine). Method and figures:
# docs/peers.md.
#
# Usage: scripts/peer-bench.sh   (work files in $PEER_WORK, default /tmp/lightmapd-peer)
# Knobs (environment): PEER_SCENES ("cornell-box"), PEER_SAMPLES (per scene, default
# "64 256 1024" for the Cornell box, "16 64 256" for blocks-25k), PEER_REF_STEPS (4096
# steps = 16384 samples: 16x the Cornell box's largest count, 64x blocks-25k's),
# PEER_THREADS (2), PEER_KEEP_REF=1 (reuse a reference already in the work folder).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
WORK=${PEER_WORK:-/tmp/lightmapd-peer}
SCENES=${PEER_SCENES:-cornell-box}
THREADS=${PEER_THREADS:-2}
SEEDS="1 2"
LMD="$ROOT/target/release/lightmapd"
PY=/usr/bin/python3

if ! command -v blender >/dev/null 2>&1 || ! "$PY" -c 'import numpy' >/dev/null 2>&1 || [[ ! -x /usr/bin/time ]]; then
    echo "installing Blender, NumPy and GNU time from Debian" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq blender python3-numpy time >/dev/null
fi
if [[ ! -x "$LMD" ]]; then
    (cd "$ROOT" && cargo build --release --locked --bin lightmapd)
fi

# A copy, so a build running beside the bench cannot swap the binary between bakes.
mkdir -p "$WORK"
cp "$LMD" "$WORK/lightmapd"
LMD="$WORK/lightmapd"

load() { cut -d' ' -f1-3 /proc/loadavg; }
now() { date +%s.%N; }
cpu() { awk '/^CPU/ {printf "%.3f", $2 + $3}' "$1"; }  # user + system seconds of the process
since() { awk "BEGIN{printf \"%.3f\", $(now) - $1}"; }

echo "# lightmapd path against Cycles"
echo
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'); $(date -u +%F)"
echo "lightmapd $(cd "$ROOT" && git rev-parse --short HEAD 2>/dev/null || echo '?'), $(blender --version 2>/dev/null | head -1) (Cycles, CPU, $THREADS threads)"

for scene in $SCENES; do
    dir="$WORK/$scene"
    mkdir -p "$dir"
    case $scene in
    cornell-box)
        res=64; sky=(); csky=(); samples=${PEER_SAMPLES:-"64 256 1024"}; ref_default=4096
        "$LMD" example cornell-box -o "$dir/scene.glb" >/dev/null ;;
    blocks-25k)
        # Its library lighting is a sky of 1 over the upper hemisphere; both bakers get a
        # sky of 1 over the whole sphere (the Cycles script has no hemisphere sky).
        res=128; sky=(--sky 1,1,1 --sky-hemisphere full); csky=(--sky 1,1,1); samples=${PEER_SAMPLES:-"16 64 256"}; ref_default=4096
        # The example's binary when built (the scene is fixed; `cargo run` would first
        # rebuild the library after any change to the tree, minutes on 2 cores).
        ex="$ROOT/target/release/examples/peer_scene"
        [[ -x "$ex" ]] || (cd "$ROOT" && cargo build -q --release --example peer_scene)
        "$ex" blocks-25k "$dir/scene.glb" ;;
    *) echo "unknown scene $scene (cornell-box, blocks-25k)" >&2; exit 2 ;;
    esac
    ref_steps=${PEER_REF_STEPS:-$ref_default}

    # samples, seed, baker, bake seconds, process seconds, load before, process CPU seconds
    : >"$dir/runs.tsv"
    for n in $samples; do
        for seed in $SEEDS; do
            l=$(load); t0=$(now)
            out=$(/usr/bin/time -f 'CPU %U %S' -o "$dir/time.txt" "$LMD" bake "$dir/scene.glb" -o "$dir/lmd_${n}_s${seed}.exr" --technique path \
                --resolution "$res" --steps $((n / 4)) --seed "$seed" --no-denoise "${sky[@]}" 2>&1)
            p=$(since "$t0")
            b=$(grep -o 'steps in [0-9.]* s' <<<"$out" | grep -o '[0-9.]*' | tail -1)
            c=$(cpu "$dir/time.txt")
            printf '%s\t%s\tlightmapd\t%s\t%s\t%s\t%s\n' "$n" "$seed" "$b" "$p" "$l" "$c" >>"$dir/runs.tsv"
            echo "$scene lightmapd $n samples seed $seed: bake $b s, process $p s, CPU $c s (load $l)" >&2

            l=$(load); t0=$(now)
            /usr/bin/time -f 'CPU %U %S' -o "$dir/time.txt" blender -b --factory-startup --python "$ROOT/scripts/peer/cycles_bake.py" -- "$dir/scene.glb" "$dir" \
                --resolution "$res" --samples "$n" --seeds "$seed" --threads "$THREADS" "${csky[@]}" \
                >"$dir/cycles_${n}_s${seed}.log" 2>&1 || { tail -30 "$dir/cycles_${n}_s${seed}.log" >&2; exit 1; }
            p=$(since "$t0")
            b=$(grep -o "^PEER cycles samples $n seed $seed: bake [0-9.]* s" "$dir/cycles_${n}_s${seed}.log" | grep -o '[0-9.]* s$' | grep -o '[0-9.]*')
            c=$(cpu "$dir/time.txt")
            printf '%s\t%s\tcycles\t%s\t%s\t%s\t%s\n' "$n" "$seed" "$b" "$p" "$l" "$c" >>"$dir/runs.tsv"
            echo "$scene Cycles $n samples seed $seed: bake $b s, process $p s, CPU $c s (load $l)" >&2
        done
    done

    if [[ "${PEER_KEEP_REF:-0}" != 1 || ! -f "$dir/lmd_ref.exr" ]]; then
        l=$(load)
        echo "$scene reference: lightmapd $ref_steps steps (load $l)" >&2
        "$LMD" bake "$dir/scene.glb" -o "$dir/lmd_ref.exr" --technique path --resolution "$res" \
            --steps "$ref_steps" --seed 99 --no-denoise --outputs validity "${sky[@]}" 2>&1 | tail -1 >&2
    fi
    echo
    echo "## $scene (${res}x${res})"
    echo
    { grep -h -m1 '^PEER cycles settings' "$dir"/cycles_*.log | head -1 | sed 's/^PEER /- /' || true
      "$PY" "$ROOT/scripts/peer/compare.py" "$dir"; } | tee "$dir/report.md"
done
