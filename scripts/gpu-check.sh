#!/usr/bin/env bash
# Runs on a machine with a GPU (release binaries built elsewhere, unpacked into $BIN):
# 1. the same small bakes as on lavapipe, for `examples/exr_diff` to compare (GPU answers
#    must match lavapipe's within noise: docs/performance.md, "GPU against lavapipe");
# 2. the per-technique timing programs of docs/performance.md;
# 3. `lightmapd bench` (error against time) with a short budget;
# 4. the GPU BVH and `path` on the GPU (issue 20): `gpu_trace_bench` (traversal rays/s, `path`
#    ms a step GPU against CPU) and the GPU tests (`gpu_bvh_test`, `path_gpu_test`: the test
#    binaries of tests/gpu_bvh.rs and tests/path_gpu.rs), which must not skip there.
# Usage: BIN=dir OUT=dir BENCH_BUDGET=5 bash scripts/gpu-check.sh [bakes] [timings] [bench] [rays]
set -uo pipefail
: "${BIN:?}" "${OUT:?}"
BENCH_BUDGET=${BENCH_BUDGET:-5}
parts=${*:-bakes timings bench rays}
log() { echo "== $*" | tee -a "$OUT/log.txt"; }
run() { log "$*"; "$@" 2>&1 | tee -a "$OUT/log.txt"; }
export LIGHTMAPD_ADAPTER=${LIGHTMAPD_ADAPTER:-gpu}
run "$BIN/lightmapd" example cornell-box -o /tmp/cornell.glb
if [[ $parts == *bakes* ]]; then
    mkdir -p /tmp/exrs
    for t in path sdb vpl obscurance sdf; do
        run "$BIN/lightmapd" bake /tmp/cornell.glb -o /tmp/exrs/$t.exr --technique $t --resolution 128 \
            --steps 16 --seed 1 --no-denoise --sky 0.2,0.3,0.5
    done
    tar cf "$OUT/exrs.tar" -C /tmp/exrs .
fi
if [[ $parts == *timings* ]]; then
    run "$BIN/sdb_direction" DIRECTIONS=64
    run "$BIN/obscurance_timings" DIRECTIONS=32
    run "$BIN/vpl_test" --ignored --nocapture measure_clamp_bias_and_step_times
    run "$BIN/sdf_test" --ignored --nocapture timings
    for t in sdb vpl obscurance sdf; do
        for r in 256 1024; do
            run "$BIN/lightmapd" bake /tmp/cornell.glb -o /tmp/t.exr --technique $t --resolution $r --steps 64 \
                --seed 1 --no-denoise --sky 0.2,0.3,0.5
        done
    done
fi
if [[ $parts == *bench* ]]; then
    run "$BIN/lightmapd" bench --budget-seconds "$BENCH_BUDGET" --out /tmp/bench --cache bench-results/cache
    tar cf "$OUT/bench.tar" -C /tmp/bench .
fi
if [[ $parts == *rays* ]]; then
    LIGHTMAPD_REQUIRE_GPU=1 run "$BIN/gpu_bvh_test" --nocapture
    LIGHTMAPD_REQUIRE_GPU=1 run "$BIN/path_gpu_test" --nocapture
    run "$BIN/gpu_trace_bench" RAYS=4194304 STEPS=32 RES=512
fi
