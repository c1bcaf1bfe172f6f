"""Compare lightmapd and Cycles bakes of one scene against a long lightmapd reference.

    /usr/bin/python3 scripts/peer/compare.py WORK_DIR/SCENE

The folder holds what scripts/peer-bench.sh writes: lmd_ref.exr (the long lightmapd
`path` bake, with `validity.Y`), lmd_<samples>_s<seed>.exr, cycles_<samples>_s<seed>.npy
(scripts/peer/cycles_bake.py) and runs.tsv (samples, seed, baker, bake seconds, process
seconds, load before, process CPU seconds). Prints markdown: per baker and sample count
the seconds, the true error against the reference (RMS luminance difference / RMS
luminance of the reference over the compared texels, the reference's own noise taken
out in quadrature) over all compared texels and over interior ones, the noise from the
two seeds, the convention checks (mean ratio, row orientation) and, for each Cycles
row, lightmapd's time to the same error.

Limits: needs exactly two seeds per count; the reference's noise is the error it
reports itself (its halves' difference), and its sample count assumes 4 samples a step
(the default).
Needs only NumPy (Debian's python3-numpy); reads the scanline OpenEXR files lightmapd
writes (single or multi-part, NONE / ZIPS / ZIP compression, HALF / FLOAT channels).
"""

import math
import os
import struct
import sys
import zlib

import numpy as np

LUM = np.array([0.2126, 0.7152, 0.0722])


# ---------------------------------------------------------------- OpenEXR reading
def _cstr(b, i):
    j = b.index(b"\0", i)
    return b[i:j].decode(), j + 1


def _header(b, i):
    h = {}
    while b[i] != 0:
        name, i = _cstr(b, i)
        typ, i = _cstr(b, i)
        size = struct.unpack_from("<i", b, i)[0]
        i += 4
        v = b[i:i + size]
        i += size
        if typ == "chlist":
            chans, k = [], 0
            while v[k] != 0:
                cn, k = _cstr(v, k)
                pt = struct.unpack_from("<i", v, k)[0]
                k += 16
                chans.append((cn, pt))
            h[name] = chans
        elif typ == "box2i":
            h[name] = struct.unpack("<4i", v)
        elif typ == "compression":
            h[name] = v[0]
        elif typ in ("int",):
            h[name] = struct.unpack("<i", v)[0]
        elif typ == "float":
            h[name] = struct.unpack("<f", v)[0]
        elif typ == "double":
            h[name] = struct.unpack("<d", v)[0]
        elif typ == "string":
            h[name] = v.decode(errors="replace")
        else:
            h[name] = v
    return h, i + 1


def _unzip(data, expected):
    if len(data) == expected:
        return data
    t = np.frombuffer(zlib.decompress(data), dtype=np.uint8).astype(np.int64)
    t[1:] -= 128  # undo the predictor: t[i] = t[i-1] + t[i] - 128 (mod 256)
    t = (np.cumsum(t) % 256).astype(np.uint8)
    half = (len(t) + 1) // 2
    out = np.empty_like(t)
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()


def read_exr(path):
    """{channel name: H x W float32 array} over all parts, plus the first part's header."""
    b = open(path, "rb").read()
    if struct.unpack_from("<I", b, 0)[0] != 20000630:
        raise ValueError(f"{path}: not OpenEXR")
    flags = struct.unpack_from("<I", b, 4)[0]
    if flags & 0x200:
        raise ValueError(f"{path}: tiled EXR not supported")
    multipart = bool(flags & 0x1000)
    i = 8
    headers = []
    while True:
        h, i = _header(b, i)
        headers.append(h)
        if not multipart or b[i] == 0:
            break
    if multipart:
        i += 1
    lines_per = {0: 1, 2: 1, 3: 16}
    tables = []
    for h in headers:
        x0, y0, x1, y1 = h["dataWindow"]
        n = h.get("chunkCount") or -(-(y1 - y0 + 1) // lines_per[h["compression"]])
        tables.append(struct.unpack_from(f"<{n}Q", b, i))
        i += 8 * n
    out = {}
    for p, (h, table) in enumerate(zip(headers, tables)):
        if h["compression"] not in lines_per:
            raise ValueError(f"{path}: compression {h['compression']} not supported")
        x0, y0, x1, y1 = h["dataWindow"]
        w, hh = x1 - x0 + 1, y1 - y0 + 1
        chans = sorted(h["channels"])
        arrays = {c: np.zeros((hh, w), np.float32) for c, _ in chans}
        for off in table:
            k = off
            if multipart:
                k += 4
            y, size = struct.unpack_from("<ii", b, k)
            k += 8
            nl = min(lines_per[h["compression"]], y1 + 1 - y)
            widths = [4 if pt in (0, 2) else 2 for _, pt in chans]
            expected = nl * w * sum(widths)
            raw = b[k:k + size]
            data = raw if h["compression"] == 0 else _unzip(raw, expected)
            pos = 0
            for line in range(nl):
                for (c, pt), cw in zip(chans, widths):
                    dt = np.float32 if pt == 2 else (np.float16 if pt == 1 else np.uint32)
                    arrays[c][y - y0 + line] = np.frombuffer(data, dtype=dt, count=w, offset=pos)
                    pos += w * cw
        for c, a in arrays.items():
            out[c] = a
    return out, headers[0]


# ---------------------------------------------------------------- analysis
def lum(rgb):
    return rgb[..., :3] @ LUM


def rel_rms(a, b, ref, mask):
    d = (a - b)[mask]
    return math.sqrt(np.mean(d * d)) / math.sqrt(np.mean(ref[mask] ** 2))


def main():
    work = sys.argv[1]
    ref, ref_h = read_exr(os.path.join(work, "lmd_ref.exr"))
    ref_rgb = np.stack([ref["R"], ref["G"], ref["B"]], -1)
    ref_l = lum(ref_rgb)
    valid = ref["validity.Y"] > 0
    ref_spp = 4 * int(float(ref_h["lightmapd:steps"]))  # samples_per_step 4 (the default)

    # bakes[baker][(samples, seed)] = (luminance, rgb, bake s, process s, load)
    bakes = {"lightmapd": {}, "cycles": {}}
    covered = np.ones_like(valid)
    for line in open(os.path.join(work, "runs.tsv")):
        n, seed, baker, bake_s, proc_s, load, cpu_s = line.rstrip("\n").split("\t")
        n, seed = int(n), int(seed)
        if baker == "lightmapd":
            e, _ = read_exr(os.path.join(work, f"lmd_{n}_s{seed}.exr"))
            rgb = np.stack([e["R"], e["G"], e["B"]], -1)
        else:
            a = np.load(os.path.join(work, f"cycles_{n}_s{seed}.npy"))
            rgb = a[..., :3]
            covered &= a[..., 3] > 0
        bakes[baker][(n, seed)] = (lum(rgb), rgb, float(bake_s), float(proc_s), load, float(cpu_s))

    mask = valid & covered & (ref_l > 0)
    pad = np.pad(mask, 1)
    interior = mask.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            interior &= pad[1 + dy:1 + dy + mask.shape[0], 1 + dx:1 + dx + mask.shape[1]]
    masks = {"all": mask, "interior": interior}

    def noise(baker, n, m):
        seeds = sorted(sd for s, sd in bakes[baker] if s == n)
        a, b = bakes[baker][(n, seeds[0])][0], bakes[baker][(n, seeds[1])][0]
        return rel_rms(a, b, ref_l, m) / math.sqrt(2)

    # The reference's own noise: the error it reports itself (the RMS over its texels of
    # its halves' difference, DESIGN's estimate; honest for Sobol samples too, whose error
    # does not fall as 1/sqrt(samples), so it cannot be scaled from a shorter bake's seed
    # pair); taken out of every true error in quadrature.
    ref_noise = {k: float(ref_h["lightmapd:relative_error"]) for k in masks}

    def true_err(l, k):
        e = rel_rms(l, ref_l, ref_l, masks[k])
        return math.sqrt(max(0.0, e * e - ref_noise[k] ** 2))

    # Convention checks on the largest Cycles count (both seeds averaged).
    cmax = max(s for s, _ in bakes["cycles"])
    c_rgb = np.mean([v[1] for (s, _), v in bakes["cycles"].items() if s == cmax], axis=0)
    c_l = lum(c_rgb)
    ratio = {k: float(c_l[m].mean() / ref_l[m].mean()) for k, m in masks.items()}
    ratio_rgb = [float(c_rgb[..., i][mask].mean() / ref_rgb[..., i][mask].mean()) for i in range(3)]
    both = mask & mask[::-1]
    flip_ok = rel_rms(c_l, ref_l, ref_l, both)
    flip_no = rel_rms(c_l[::-1], ref_l, ref_l, both)

    rows = []
    for baker, label in (("lightmapd", "lightmapd path"), ("cycles", "Cycles 3.4.1")):
        for n in sorted({s for s, _ in bakes[baker]}):
            pts = [v for (s, _), v in bakes[baker].items() if s == n]
            rows.append({
                "baker": baker, "label": label, "n": n,
                "bake": float(np.mean([p[2] for p in pts])), "proc": float(np.mean([p[3] for p in pts])),
                "cpu": float(np.mean([p[5] for p in pts])),
                "all": float(np.sqrt(np.mean([true_err(p[0], "all") ** 2 for p in pts]))),
                "interior": float(np.sqrt(np.mean([true_err(p[0], "interior") ** 2 for p in pts]))),
                "noise": noise(baker, n, interior),
                "load": " / ".join(p[4].split()[0] for p in pts),
            })

    print(f"- reference: lightmapd path, {ref_spp} samples per texel (seed 99), "
          f"{float(ref_h['lightmapd:seconds']):.1f} s; "
          f"its estimated error {100 * ref_noise['all']:.3f} % (its halves' difference), "
          f"taken out of the true errors in quadrature")
    print(f"- texels compared: {int(mask.sum())} (valid in lightmapd and covered by every Cycles bake; "
          f"lightmapd valid {int(valid.sum())}, Cycles covered {int(covered.sum())}); "
          f"interior {int(interior.sum())} (their 8 neighbours compared too)")
    print(f"- convention: mean Cycles / lightmapd reference (luminance, Cycles {cmax} samples, both seeds) "
          f"{ratio['all']:.4f} over all texels, {ratio['interior']:.4f} interior; "
          f"R {ratio_rgb[0]:.4f}, G {ratio_rgb[1]:.4f}, B {ratio_rgb[2]:.4f}")
    print(f"- orientation: Cycles' rows flipped (Blender row 0 = bottom): error {100 * flip_ok:.2f} %; "
          f"not flipped: {100 * flip_no:.2f} %")
    print()
    print("| baker | samples / texel | bake s | process s | process CPU s | true error, all texels | "
          "true error, interior | noise (seed pair), interior | load before (seed 1 / 2) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for r in rows:
        print(f"| {r['label']} | {r['n']} | {r['bake']:.2f} | {r['proc']:.2f} | {r['cpu']:.2f} | {100 * r['all']:.3f} % | "
              f"{100 * r['interior']:.3f} % | {100 * r['noise']:.3f} % | {r['load']} |")
    print()
    def lmd_time(err, key, clock):
        # lightmapd's seconds to reach err: from its row of nearest error, error ~ 1/sqrt(s).
        o = min((r for r in rows if r["baker"] == "lightmapd" and r[key] > 0),
                key=lambda o: abs(math.log(o[key] / err)))
        return o[clock] * (o[key] / err) ** 2

    print("Time to the same error: for each Cycles row, lightmapd's seconds to reach that row's "
          "error, scaled from lightmapd's row of nearest error with error ~ 1/sqrt(seconds); "
          "ratio = Cycles seconds / lightmapd seconds:")
    print()
    print("| Cycles samples | its true error, interior | Cycles bake s | lightmapd bake s to it | "
          "ratio, bake | ratio, whole process | ratio, process CPU | ratio on true error, all texels (bake) | ratio on noise (bake) |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        if r["baker"] != "cycles":
            continue
        t = lmd_time(r["interior"], "interior", "bake")
        tp = lmd_time(r["interior"], "interior", "proc")
        tc = lmd_time(r["interior"], "interior", "cpu")
        ta = lmd_time(r["all"], "all", "bake")
        tn = lmd_time(r["noise"], "noise", "bake")
        print(f"| {r['n']} | {100 * r['interior']:.3f} % | {r['bake']:.2f} | {t:.2f} | {r['bake'] / t:.2f}x | "
              f"{r['proc'] / tp:.2f}x | {r['cpu'] / tc:.2f}x | {r['bake'] / ta:.2f}x | {r['bake'] / tn:.2f}x |")

main()
