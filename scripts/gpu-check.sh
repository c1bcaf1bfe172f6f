#!/usr/bin/env bash
# Runs on a machine with a GPU (release binaries built elsewhere, unpacked into $BIN):
# 1. the same small bakes as on lavapipe, for `examples/exr_diff` to compare (GPU answers
#    must match lavapipe's within noise: docs/performance.md, "GPU against lavapipe");
# 2. the per-technique timing programs of docs/performance.md;
# 3. `lightmapd bench` (error against time) with a short budget;
# 4. the GPU BVH and `path` on the GPU (issue 20): `gpu_trace_bench` (traversal rays/s, `path`
#    ms a step GPU against CPU) and the GPU tests (`gpu_bvh_test`, `path_gpu_test`: the test
#    binaries of tests/gpu_bvh.rs and tests/path_gpu.rs), which must not skip there;
# 5. `level_bench`: `path` on the 256k-triangle generated level, one 1024^2 page, time to
#    2 % and 1 % true error, and the CPU on all cores at equal error (issue 20's goal).
# 6. `denoise_quality` (issue 22): OIDN's cost at 1024^2 and 4096^2 (its CUDA device when
#    $LIGHTMAPD_OIDN_DIR holds the libraries of scripts/setup-oidn.sh, carried there), and
#    the error table from 4 to 4096 steps on the Cornell box and the occlusion room.
# 7. `routes`: the GPU routes of rays the CPU makes (issue 20 point 3) against their CPU
#    routes on the same machine: texel validation (`prep_bench`: both routes on one
#    generated level, and how many texels they disagree on) and vpl's reflective shadow
#    maps (`params.rays` cpu / gpu on the occlusion room under sun and sky, ms a step at
#    the default `rsm_size` 64 and at 256).
# 8. `farm` (issues 25 and 20): `region_bench` on the 256k-triangle generated level at 24
#    texels/m on 4096^2 pages (a whole-grid task against each page task and their merge:
#    the farm model's preparation split, docs/scaling.md, with validation on the GPU
#    route), and `path` on the GPU with `sampling` independent against sobol (the Cornell
#    box at 512^2, 64 steps: ms a step and the estimated error, docs/performance.md).
# 9. `probes` (issue 26): light probes on the GPU against the CPU, `probe_bench` (closed-form
#    scenes, error against time) with 20^3 = 8000 probes a scene on each device, and the probe
#    tests (`probes_test`: tests/probes.rs, every closed form on both devices), which must not
#    skip there.
# `bench` reads converged references from $BENCH_CACHE (default bench-results/cache) made
# with $BENCH_REFERENCE_SECONDS (default 300; the key includes it): carry the ones made on
# the development machine (`target/tmp/honest-error-references`) so no device time goes
# into a reference.
# Parts run in the order rays, level, routes, farm, probes, bakes, timings, bench, denoise (correctness first).
# Usage: BIN=dir OUT=dir BENCH_BUDGET=5 bash scripts/gpu-check.sh [bakes] [timings] [bench] [rays] [level] [routes] [farm] [probes] [denoise]
set -uo pipefail
: "${BIN:?}" "${OUT:?}"
BENCH_BUDGET=${BENCH_BUDGET:-5}
BENCH_REFERENCE_SECONDS=${BENCH_REFERENCE_SECONDS:-300}
BENCH_CACHE=${BENCH_CACHE:-bench-results/cache}
parts=${*:-bakes timings bench rays level routes denoise}
log() { echo "== $*" | tee -a "$OUT/log.txt"; }
run() { log "$*"; "$@" 2>&1 | tee -a "$OUT/log.txt"; }
export LIGHTMAPD_ADAPTER=${LIGHTMAPD_ADAPTER:-gpu}
run "$BIN/lightmapd" example cornell-box -o /tmp/cornell.glb
if [[ $parts == *rays* ]]; then
    LIGHTMAPD_REQUIRE_GPU=1 run "$BIN/gpu_bvh_test" --nocapture
    LIGHTMAPD_REQUIRE_GPU=1 run "$BIN/path_gpu_test" --nocapture
    run "$BIN/gpu_trace_bench" ${TRACE_ARGS:-RAYS=4194304 STEPS=32 RES=512}
fi
if [[ $parts == *level* ]]; then
    run "$BIN/level_bench" ${LEVEL_ARGS:-}
fi
if [[ $parts == *routes* ]]; then
    run "$BIN/prep_bench" ${PREP_ARGS:-40 8 10 1024}
    for rsm in 64 256; do
        for rays in cpu gpu; do
            run "$BIN/lightmapd" bake scenes/third-party/occlusion_room.glb -o /tmp/vpl-$rays.exr --technique vpl \
                --resolution 256 --steps 32 --seed 1 --no-denoise --sky 0.2,0.3,0.5 --sun 0.3,-1,-0.4,0.5,2000,1900,1800 \
                --params "{\"rays\": \"$rays\", \"rsm_size\": $rsm}"
        done
        run "$BIN/exr_diff" /tmp/vpl-cpu.exr /tmp/vpl-gpu.exr  # within noise: docs/vpl.md
    done
fi
if [[ $parts == *farm* ]]; then
    run "$BIN/region_bench" ${REGION_ARGS:-400 8 24 4096 2 2}
    for sampling in independent sobol; do
        run "$BIN/lightmapd" bake /tmp/cornell.glb -o /tmp/sampling-$sampling.exr --resolution 512 --steps 64 \
            --seed 1 --no-denoise --sky 0.2,0.3,0.5 --params "{\"device\": \"gpu\", \"sampling\": \"$sampling\"}"
    done
fi
if [[ $parts == *probes* ]]; then
    LIGHTMAPD_REQUIRE_GPU=1 run "$BIN/probes_test" --nocapture
    for device in cpu gpu; do
        run "$BIN/probe_bench" ${PROBE_STEPS:-64} $device ${PROBE_SIDE:-20}
    done
fi
if [[ $parts == *bakes* ]]; then
    mkdir -p /tmp/exrs
    for t in path sdb vpl obscurance sdf hemicube; do
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
    run "$BIN/lightmapd" bench --budget-seconds "$BENCH_BUDGET" --reference-seconds "$BENCH_REFERENCE_SECONDS" \
        --out /tmp/bench --cache "$BENCH_CACHE"
    tar cf "$OUT/bench.tar" -C /tmp/bench .
fi
if [[ $parts == *denoise* ]]; then
    run "$BIN/denoise_quality" cost 1024
    run "$BIN/denoise_quality" cost 4096
    MAX_STEPS=4096 run "$BIN/denoise_quality" errors cornell-box 262144
    MAX_STEPS=1024 run "$BIN/denoise_quality" errors scenes/occlusion_room.glb 16384 512
fi
