"""Bright single-photon spots: the tail of single photons' contributions.

Some seeds show a 2x2-pixel spot many times its surroundings: one stored photon whose storage
weight 1/q meets a forward-peaked phase value toward the eye.  Per seed, this renders
``configs/forearm.toml`` (or ``--config``) at ``--res`` with the default budget in the scatter
layout (the same image as the gather) and records, per pixel, the largest single (photon,
sample point) pair's contribution over all passes (kernels/scatter.cl, ``spots``), summed over
the bands, against the pixel's total.  Reported per seed: the largest share of a pixel taken by
one pair, where it is, and how many pixels one pair holds more than 10 %, 25 %, 50 % of.

    python bench/studies/spots.py [--seeds 1-8] [--res 80 60] [--passes 6] [--device pocl]
                          [--out out/bench_spots.json]

A pair is one photon with one eye-ray sample point; with one ray per pixel a photon meets a
ray at one depth, so this is the photon's share up to the rare ray that crosses its depth twice.

``--photons-tail`` measures the cause instead, on the stored photons of ``--passes`` photon
passes (seed 1): per photon and carried band j the largest contribution it can make toward the
eye cone, X_j = F_j/q HG_j(the cone's most favourable cosine) T_j(vertical eye ray to its
depth), and prints the quantiles of X = sum_j X_j over its median, the hero band's share, and
the 12 largest photons (hero band, the band that holds X, layer, depth).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))


def seeds_of(s: str) -> list[int]:
    out = []
    for part in s.split(","):
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


class SpotsKernel:
    """kernels/scatter.cl's scatter_beam with its benchmark arguments on (``spots = 1``): each
    launch also records per pixel its largest single pair in ``pix_max`` (float bits)."""

    def __init__(self, inner, pt_pix, pix_max):
        self.inner, self.pt_pix, self.pix_max = inner, pt_pix, pix_max

    def __call__(self, queue, size, /, **args):
        return self.inner(queue, size, **{**args, "spots": 1, "pt_pix": self.pt_pix,
                                          "pix_max": self.pix_max})


def measure_spots(sc, ss):
    """From now on each pass of the scatter layout's state ``ss`` records per pixel its largest
    single pair: the returned buffer (float bits; clear it before a pass)."""
    import pyopencl.array as cla
    from clppm.compute.kernelcall import Kernel
    q, e = sc.dev.queue, sc.eye
    prg = sc.dev.build("scatter.cl", sc.estimator.layout.beam.defines())
    pt_pix = cla.zeros(q, max(e.npoints, 1), np.uint32)
    Kernel(prg, "point_pixels")(q, sc.npix, ray_start=e.ray_start, npix=sc.npix,
                                spp=e.camera.spp, pt_pix=pt_pix)
    spots = cla.zeros(q, max(sc.npix, 1), np.uint32)
    ss.k["scatter_beam"] = SpotsKernel(ss.k["scatter_beam"], pt_pix, spots)
    return spots


def one_seed(dev, cfg, passes: int) -> dict:
    from clppm.integrators import beam, ppm, photonpass
    sc = ppm.Pipeline.build(cfg, dev)
    if sc.estimator.layout.name != "scatter":
        why = beam.supports_scatter(dev, sc.vol.nb, sc.gclass, sc.pp.hero)
        raise SystemExit(f"the scatter layout is not available here: {why}")
    cal = sc.calibrate()
    sc.apply(cal)
    st = sc.point_state(cal)
    acc = ppm.Accumulators.zeros(sc)
    ss = sc.estimator.layout.scatter_state()
    spots = measure_spots(sc, ss)
    top = np.zeros(sc.npix, np.float64)
    for p in range(passes):
        spots.fill(0)
        info = sc.run_pass(cal, st, p, acc, photonpass.Tallies(sc.vol.nb, sc.vol.nmat))
        scale = 1.0 / max(info["emitted"], 1) if sc.global_radius else 1.0
        m = spots.get().view(np.float32).astype(np.float64) * scale
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


def photon_tail(dev, cfg, passes: int) -> dict:
    """Per stored photon: X_j (see the module docstring), over ``passes`` photon passes."""
    import math
    import pyopencl as cl
    from clppm.integrators import ppm, photonpass
    sc = ppm.Pipeline.build(cfg, dev)
    cal = sc.calibrate()
    sc.apply(cal)
    pp, vol = sc.pp, sc.vol
    NB, C = vol.nb, pp.hero
    parts = []
    for p in range(passes):
        n = pp.run_pass(p, sc.target, photonpass.Tallies(vol.nb, vol.nmat))["stored"]
        pw = np.empty((n, 4), np.float32); db = np.empty((n, 4), np.float32)
        ex = np.empty((n, max(C - 1, 1)), np.float32)
        for a, b in ((pw, pp.pos_w), (db, pp.dir_b), (ex, pp.extra)):
            cl.enqueue_copy(dev.queue, a, b)
        parts.append((pw, db, ex[:, :C - 1]))
    pw, db, ex = (np.concatenate([q[i] for q in parts]) for i in range(3))
    code = db[:, 3].astype(int)
    h, L = code & 255, code >> 8
    F = np.concatenate([pw[:, 3:4], ex], 1).astype(np.float64)
    bands = (h[:, None] + np.arange(C)[None] * (NB // C)) % NB
    imp = photonpass.storage_importance(vol)[:vol.nl * NB].reshape(vol.nl, NB, 2).astype(np.float64)
    opt = vol.optics_table().reshape(vol.nl, NB, 4).astype(np.float64)
    g, mut = opt[L[:, None], bands, 1], opt[L[:, None], bands, 3]
    z = pw[:, 2:3].astype(np.float64)
    T = np.exp(-(imp[L[:, None], bands, 0] + mut * np.maximum(0, imp[L[:, None], bands, 1] - z)))
    c = db[:, 2].astype(np.float64)
    cs, sn = float(pp.p["store_cos"][0]), float(pp.p["store_sin"][0])
    ce = np.where(c >= cs, 1.0, c * cs + np.sqrt(np.maximum(0, 1 - c * c)) * sn)[:, None]
    X = F * (1 - g * g) / (4 * math.pi) / (1 + g * g - 2 * g * ce) ** 1.5 * T
    Xs = X.sum(1)
    med = float(np.median(Xs))
    qs = [0.9, 0.99, 0.999, 0.9999, 1.0]
    top = np.argsort(Xs)[::-1][:12]
    wl = vol.wl
    return {"photons": int(len(Xs)), "passes": passes,
            "quantiles_over_median": {str(q): float(np.quantile(Xs, q) / med) for q in qs},
            "hero_share_mean": float(np.mean(X[:, 0] / np.maximum(Xs, 1e-300))),
            "top": [{"X_over_median": float(Xs[i] / med), "hero_nm": float(wl[h[i]]),
                     "holding_nm": float(wl[bands[i, np.argmax(X[i])]]),
                     "holding_share": float(X[i].max() / Xs[i]), "hero_share": float(X[i, 0] / Xs[i]),
                     "layer": int(L[i]), "z_um": float(z[i, 0])} for i in top]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--seeds", default="1-8")
    ap.add_argument("--res", type=int, nargs=2, default=[80, 60])
    ap.add_argument("--passes", type=int, default=None, help="default: the config's")
    ap.add_argument("--photons", type=int, default=None, help="stored photons per pass (default: the config's)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--photons-tail", action="store_true", help="the stored photons' largest contributions (the cause)")
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "bench_spots.json"))
    a = ap.parse_args(argv)
    from clppm import config as C
    from clppm.request import resolved_config
    from clppm.compute.device import open_device
    dev = open_device(a.device)
    if a.photons_tail:
        cfg = resolved_config(C.load(a.config), resolution=tuple(a.res), photons=a.photons)
        r = photon_tail(dev, cfg, a.passes or 2)
        print(f"{r['photons']} stored photons, {r['passes']} passes; X / median X at quantiles: "
              + ", ".join(f"{q}: {v:.0f}" for q, v in r["quantiles_over_median"].items())
              + f"; the hero band's mean share of X {r['hero_share_mean']:.2f}")
        print("| X / median | hero nm | X held by (nm) | its share | hero's share | layer | z um |")
        print("|---:|---:|---:|---:|---:|---:|---:|")
        for t in r["top"]:
            print(f"| {t['X_over_median']:.0f} | {t['hero_nm']:.0f} | {t['holding_nm']:.0f} | "
                  f"{t['holding_share']:.2f} | {t['hero_share']:.3f} | {t['layer']} | {t['z_um']:.1f} |")
        os.makedirs(os.path.dirname(a.out), exist_ok=True)
        with open(a.out, "w") as f:
            json.dump(r, f, indent=1)
        return 0
    base = resolved_config(C.load(a.config), resolution=tuple(a.res), photons=a.photons)
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
