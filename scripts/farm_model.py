#!/usr/bin/env python3
"""The farm model of docs/scaling.md ("A farm model"): time to finish one 64-page 4096²
level baked by `path` to 1 %, and the machine time it costs, against the number of
workers, for the two ways a job is split (issue 25).

Every input is a measured figure or a stated assumption (docs/scaling.md says which):
change one and run `python3 scripts/farm_model.py` for the table again.
"""
import math

TEXELS = 497e6             # 64 pages of 4096² at the generated level's 46 % coverage
WORK = 1044.0              # GPU-seconds: 497 M texels x 336 paths / 160 M paths/s (H200)
IMPORT = 1.15              # import and UVs, per process that prepares the level
PREP_WHOLE = 1035.0        # texel set + BVH + validation of the whole level (1.01 s / 485 k texels, H200 + 16 cores)
SCALE = 497 / 15.6 * 2 / 16  # prep_bench's 15.6 M-texel level on 2 cores -> this level on 16
RASTER = (4.47 + 0.08) * SCALE  # of which the whole texel set (4.47 s) and BVH (0.08 s): prep_bench, 2026-12-05
BVH = 0.08 * SCALE
COVER = 0.22 * SCALE       # the grid's coverage and its cut into regions (a bit a pixel): what a page task rasterises whole
VALIDATE = PREP_WHOLE - RASTER  # the rest: validation, proportional to the texels validated
RESULT = 28 * TEXELS / 1e9  # GB of one task result covering every texel (28 B a texel)
BANDWIDTH = 1.0            # GB/s to and from the store per worker (assumed; no farm here)
PAGES = 64


def step_ranges(w):
    """W tasks, each every texel over W-th of the steps; one merge."""
    task = IMPORT + PREP_WHOLE + WORK / w + RESULT / BANDWIDTH
    # The merge takes the tasks' validation (no rays), reads and adds every result.
    merge = IMPORT + RASTER + w * 2 * RESULT / BANDWIDTH
    return task + merge, w * task + merge


def pages_times_ranges(w):
    """64 page regions x k step ranges (k = max(1, W // 64)); one merge."""
    k = max(1, w // PAGES)
    tasks = PAGES * k
    # A page task builds its page's texels only (`Atlas::build_pixels`): the coverage of
    # the whole grid, the BVH of the whole scene, a 64th of the texel set and validation.
    task = IMPORT + COVER + BVH + (RASTER - BVH) / PAGES + VALIDATE / PAGES + WORK / tasks + RESULT / PAGES / BANDWIDTH
    waves = math.ceil(tasks / w)
    merge = IMPORT + RASTER + k * 2 * RESULT / BANDWIDTH
    return waves * task + merge, tasks * task + merge


print("| workers | step-range tasks: time | machine time | page × step-range tasks: time | machine time |")
print("| ---: | ---: | ---: | ---: | ---: |")
for w in [1, 2, 4, 8, 16, 32, 64, 128, 200]:
    (a, am), (b, bm) = step_ranges(w), pages_times_ranges(w)
    print(f"| {w} | {a / 60:.1f} min | {am / 3600:.1f} h | {b / 60:.1f} min | {bm / 3600:.1f} h |")
