#!/usr/bin/env bash
# Wall time of one split `path` job against the number of local worker processes
# (issue 25 point 6; figures in docs/scaling.md).
#
#   bash scripts/farm-bench.sh [BIN] [WORKERS...]
#
# For each count N (default 1 2 3): one API process (`serve --workers 0`) and N `worker`
# processes on a fresh SQLite file and artifact directory, the bundled Cornell box at
# 128² (12 355 texels), one job of 600 steps split into 12 tasks, no denoiser. Prints
# the time from submission to `succeeded`, the per-task bake times and attempts, and the
# merge's share, as the API reports them. BIN defaults to target/release/lightmapd.
#
# SCENE (a .glb) and JOB (the job body without its scene, JSON) replace the scene and the
# job, e.g. a `hemicube` job in rounds:
#   JOB='{"technique":"hemicube","resolution":128,"stop":{"steps":128},"regions":2,"rounds":4,"denoise":"none","seed":1}' \
#     bash scripts/farm-bench.sh target/debug/lightmapd 1 2
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${1:-target/release/lightmapd}
shift || true
COUNTS=("${@:-1 2 3}")
[ -x "$BIN" ] || { echo "no $BIN: cargo build --release first" >&2; exit 2; }
PORT=18731
SCENE=${SCENE:-scenes/cornell-box.glb}
JOB=${JOB:-'{"technique":"path","resolution":128,"stop":{"steps":600},"tasks":12,"denoise":"none","seed":1}'}
pids=()
# Whatever happens, no server or worker outlives the script (a later run would talk to it).
trap 'kill "${pids[@]}" 2> /dev/null || true' EXIT
for n in ${COUNTS[@]}; do
    dir=$(mktemp -d)
    db="sqlite://$dir/q.db"
    "$BIN" serve --workers 0 --listen 127.0.0.1:$PORT --database-url "$db" --store "$dir/store" \
        > "$dir/api.log" 2>&1 &
    pids=($!)
    for _ in $(seq 60); do curl -sf "http://127.0.0.1:$PORT/healthz" > /dev/null && break; sleep 0.25; done
    for _ in $(seq "$n"); do
        "$BIN" worker --database-url "$db" --store "$dir/store" > "$dir/worker-$_.log" 2>&1 &
        pids+=($!)
    done
    scene=$(curl -sf -H 'content-type: model/gltf-binary' --data-binary "@$SCENE" "http://127.0.0.1:$PORT/v1/scenes" | jq -r .id)
    sleep 1 # the workers start (adapter probe) before the clock does
    start=$(date +%s.%N)
    body=$(echo "$JOB" | jq -c --arg scene "$scene" '. + {scene: $scene}')
    job=$(curl -sf -H 'content-type: application/json' -d "$body" "http://127.0.0.1:$PORT/v1/jobs" | jq -r .id)
    while :; do
        s=$(curl -sf "http://127.0.0.1:$PORT/v1/jobs/$job" | jq -r .status)
        [ "$s" = queued ] || [ "$s" = running ] || break
        sleep 0.1
    done
    end=$(date +%s.%N)
    view=$(curl -sf "http://127.0.0.1:$PORT/v1/jobs/$job")
    echo "workers $n: $s in $(echo "$end - $start" | bc) s; summary: $(echo "$view" | jq -c '{steps: .summary.steps, machine_seconds: .summary.seconds, error: .summary.error.relative}')"
    echo "$view" | jq -r '.tasks.list[] | "  task \(.index) \(.kind) round \(.round) region \(.region) \(.status) attempts \(.attempts) steps \(.steps) seconds \(.seconds) wall_s \(.wall_s) worker \(.worker)"'
    (cd "$dir/store/jobs/$job" && find . -type f -printf "  stored: %P %s B\n") || true
    # A round task's read of the round before (jobs in rounds): results, whole ones, bytes.
    grep -h "round before read" "$dir"/worker-*.log | sed 's/^/  /' || true
    kill "${pids[@]}" 2> /dev/null || true
    wait 2> /dev/null || true
    rm -rf "$dir"
done
