"""Bright single-photon spots (issue 20, point 5): the tail only, measured, not changed.

Some seeds show a 2x2-pixel spot many times its surroundings: one stored photon whose storage
weight 1/q meets a forward-peaked phase value toward the eye.  Per seed, this renders
``configs/forearm.toml`` (or ``--config``) at ``--res`` with the default budget in the scatter
layout (the same image as the gather) and records, per pixel, the largest single (photon,
sample point) pair's contribution over all passes (kernels/scatter.cl, ``spots``), summed over
the bands, against the pixel's total.  Reported per seed: the largest share of a pixel taken by
one pair, where it is, and how many pixels one pair holds more than 10 %, 25 %, 50 % of.

    python bench/spots.py [--seeds 1-8] [--res 80 60] [--passes 6] [--device pocl]
                          [--out out/bench_spots.json]

A pair is one photon with one eye-ray sample point; with one ray per pixel a photon meets a
ray at one depth, so this is the photon's share up to the rare ray that crosses its depth twice.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def seeds_of(s: str) -> list[int]:
    out = []
    for part in s.split(","):
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


def one_seed(dev, cfg, passes: int) -> dict:
    from clppm import beam, ppm, photonpass
    sc = ppm.setup(cfg, dev)
    if beam.layout(sc) != "scatter":
        raise SystemExit(f"the scatter layout is not available here: {beam.supports_scatter(sc)}")
    cal = ppm.calibrate(sc)
    ppm.prepare(sc, cal)
    st = ppm.point_state(sc, cal)
    acc = ppm.Accumulators.zeros(sc)
    ss = beam.scatter_state(sc)
    ss.measure_spots(sc)
    top = np.zeros(sc.npix, np.float64)
    for p in range(passes):
        ss.spots.fill(0)
        info = ppm.run_pass(sc, cal, st, p, acc, photonpass.Tallies(sc.vol.nb, sc.vol.nl))
        scale = 1.0 / max(info["emitted"], 1) if sc.global_radius else 1.0
        m = ss.spots.get().view(np.float32).astype(np.float64) * scale
        top = np.maximum(top, m)
    pix, _ = acc.host()
    total = pix.reshape(sc.npix, -1).sum(-1)
    share = np.where(total > 0, top / np.where(total > 0, total, 1.0), 0.0)
    w, h = sc.eye.camera.width, sc.eye.camera.height
    k = int(np.argmax(share))
    lit = total > 0
    sh2 = share.reshape(h, w)
    inner = sh2[4:-4, 4:-4] if h > 8 and w > 8 else sh2
    ki = int(np.argmax(inner))
    return {"max_share": float(share.max()), "at_xy": [k % w, k // w],
            "max_share_inside": float(inner.max()),        # 4 pixels or more from the image's border
            "inside_at_xy": [ki % inner.shape[1] + (4 if inner is not sh2 else 0),
                             ki // inner.shape[1] + (4 if inner is not sh2 else 0)],
            "p99_share": float(np.quantile(share[lit], 0.99)) if lit.any() else 0.0,
            "median_share": float(np.median(share[lit])) if lit.any() else 0.0,
            "pixels_over_10pct": int((share > 0.10).sum()), "pixels_over_25pct": int((share > 0.25).sum()),
            "pixels_over_50pct": int((share > 0.50).sum()), "npix": int(sc.npix)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--seeds", default="1-8")
    ap.add_argument("--res", type=int, nargs=2, default=[80, 60])
    ap.add_argument("--passes", type=int, default=None, help="default: the config's")
    ap.add_argument("--photons", type=int, default=None, help="stored photons per pass (default: the config's)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "bench_spots.json"))
    a = ap.parse_args(argv)
    from clppm import config as C, progressive
    from clppm.device import open_device
    dev = open_device(a.device)
    base = progressive.apply_overrides(C.load(a.config), resolution=tuple(a.res), photons=a.photons)
    base = C.override(base, "render", "layout", "scatter")
    passes = a.passes or int(base["render"]["passes"])
    rows = []
    print("| seed | largest share of a pixel | at (x, y) | largest 4+ px from the border | at | 99th pct | "
          "median | pixels > 10 % | > 25 % | > 50 % |")
    print("|---:|---:|---|---:|---|---:|---:|---:|---:|---:|")
    for s in seeds_of(a.seeds):
        t0 = time.perf_counter()
        r = one_seed(dev, C.override(base, "render", "seed", s), passes)
        r.update(seed=s, seconds=time.perf_counter() - t0)
        rows.append(r)
        print(f"| {s} | {r['max_share']:.3f} | {tuple(r['at_xy'])} | {r['max_share_inside']:.3f} | "
              f"{tuple(r['inside_at_xy'])} | {r['p99_share']:.3f} | "
              f"{r['median_share']:.4f} | {r['pixels_over_10pct']} | {r['pixels_over_25pct']} | "
              f"{r['pixels_over_50pct']} |", flush=True)
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump({"config": a.config, "res": a.res, "passes": passes, "photons": base["render"]["photons"],
                   "device": dev.device.name.strip(), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
