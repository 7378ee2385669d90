"""How many light paths reach a vertex through the forearm's relief, and what the path tracer's
one-solution connection misses (docs/relief.md).

Vertices are drawn uniformly over the model's inner 9 x 9 mm and at exponentially distributed
depths (mean --depth um, the scattering vertices' depths are of that order), their layer found
on the smooth surfaces.  For each: the kernel's connection (Newton from the flat seed, then
continuation), and Newton from 8 x 3 further seeds around the flat seed (momentum offsets 0.03,
0.1, 0.25 in 8 directions).  Distinct converged solutions (|du| > 1e-6) are the light paths
found; the share of the vertex's direct-chain irradiance (G times the Fresnel factors; the
paths' attenuations differ by little and are left out) that the kernel's one solution misses is
a lower bound of the bias of the one-solution estimator there (seeds find solutions, they do not
prove there are no more).  Per layer and in all; results go to out/bench/mnee_solutions.json.

    python bench/mnee_solutions.py --vertices 2000
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from clppm import config as C                      # noqa: E402
from clppm import pathtracer as pt                 # noqa: E402
from clppm import volume                           # noqa: E402
from clppm.device import open_device               # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vertices", type=int, default=2000)
    ap.add_argument("--depth", type=float, default=100.0, help="mean vertex depth, um")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    cfg = C.load(os.path.join(ROOT, "configs", "forearm.toml"))
    vol = volume.build(cfg)
    dev = open_device(a.device)
    light = tuple(float(v) * 1000.0 for v in cfg["light"]["position_mm"])
    rng = np.random.default_rng(a.seed)
    n = a.vertices
    verts = np.stack([rng.uniform(500, 9500, n), rng.uniform(500, 9500, n),
                      -rng.exponential(a.depth, n) - 0.5, np.zeros(n)], 1)
    verts = verts.astype(np.float32).astype(float)
    r0 = pt.mnee_probe(dev, vol, light, verts, 0)
    use = r0["built"] & (r0["layer"] >= 0)
    sols = [[] for _ in range(n)]

    def add(i, ux, uy, g):
        for s in sols[i]:
            if abs(s[0] - ux) + abs(s[1] - uy) < 1e-6:
                return
        sols[i].append((ux, uy, g))

    for i in np.flatnonzero(use & r0["ok"]):
        add(i, r0["ux"][i], r0["uy"][i], r0["G"][i] * r0["F"][i])
    u0 = np.stack([r0["ux"], r0["uy"]], 1)
    # the flat seed itself (where the kernel's u is the solution, re-seed from the flat solution)
    for d in (0.03, 0.1, 0.25):
        for phi in np.arange(8) * (np.pi / 4):
            seeds = u0 + d * np.array([np.cos(phi), np.sin(phi)])
            r = pt.mnee_probe(dev, vol, light, verts, 0, seeds=seeds)
            for i in np.flatnonzero(use & r["ok"]):
                add(i, r["ux"][i], r["uy"][i], r["G"][i] * r["F"][i])
    layers = r0["layer"].astype(int)
    rows = {}
    for name, m in [("all", use)] + [(vol.names[k], use & (layers == k)) for k in range(vol.nl)]:
        idx = np.flatnonzero(m)
        if not idx.size:
            continue
        nsol = np.array([len(sols[i]) for i in idx])
        tot = np.array([sum(s[2] for s in sols[i]) for i in idx])
        mine = np.array([r0["G"][i] * r0["F"][i] if r0["ok"][i] else 0.0 for i in idx])
        rows[name] = {"vertices": int(idx.size), "kernel_solved": float(r0["ok"][idx].mean()),
                      "continued": float(r0["continued"][idx].mean()),
                      "more_than_one_solution": float((nsol > 1).mean()),
                      "max_solutions": int(nsol.max()),
                      "missed_share_of_irradiance": float((tot - mine).sum() / tot.sum()) if tot.sum() > 0 else None}
        print(f"{name:24s} {idx.size:5d} vertices: solved {rows[name]['kernel_solved']:.4f} "
              f"(continued {rows[name]['continued']:.4f}), >1 solution {rows[name]['more_than_one_solution']:.4f} "
              f"(max {rows[name]['max_solutions']}), irradiance missed {rows[name]['missed_share_of_irradiance']:.4%}",
              flush=True)
    os.makedirs(os.path.join(ROOT, "out", "bench"), exist_ok=True)
    with open(os.path.join(ROOT, "out", "bench", "mnee_solutions.json"), "w") as f:
        json.dump({"vertices": n, "mean_depth_um": a.depth, "light_um": light, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
