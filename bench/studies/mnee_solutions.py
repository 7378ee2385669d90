"""How many light paths reach a vertex through the forearm's relief, and whether the path
tracer's connection (the flat-seeded solution plus specular manifold sampling of the others)
adds them all up (docs/relief.md).

Vertices are drawn uniformly over the model's inner 9 x 9 mm and at exponentially distributed
depths (mean --depth um, the scattering vertices' depths are of that order), their layer found
on the smooth surfaces; one band (--band-nm).  For each: the kernel's flat-seeded connection;
a dense seed search (Newton from 12 momentum offsets 0.02-0.6 x 16 directions around the flat
seed; distinct converged solutions, |du| > 1e-6, each with its full factor: G, Fresnel,
attenuation); and --samples samples of the render's connection.  Per layer: the share of vertices
with more than one solution, and the light of all solutions over that of the flat-seeded one,
summed over the layer's vertices, by the dense search (a lower bound: seeds find solutions, they
do not prove there are no more) and by the render's connection (unbiased, with its standard
error).  Results go to out/bench/mnee_solutions.json.

    python bench/studies/mnee_solutions.py --vertices 400 --samples 1000
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from clppm import config as C                      # noqa: E402
from clppm.checks import testing                           # noqa: E402
from clppm.scene import volume                           # noqa: E402
from clppm.compute.device import open_device               # noqa: E402


def dense_search(dev, vol, light, verts, r0, use):
    """Distinct solutions per vertex: the flat-seeded one and Newton from 192 seeds around it."""
    sols = [[] for _ in range(len(verts))]

    def add(i, ux, uy, f):
        if all(abs(s[0] - ux) + abs(s[1] - uy) >= 1e-6 for s in sols[i]):
            sols[i].append((ux, uy, f))

    for i in np.flatnonzero(use & r0["ok"]):
        add(i, r0["ux"][i], r0["uy"][i], r0["factor"][i])
    u0 = np.stack([r0["ux"], r0["uy"]], 1)
    for d in np.linspace(0.02, 0.6, 12):
        for phi in np.arange(16) * (np.pi / 8):
            r = testing.mnee_probe(dev, vol, light, verts, 0, seeds=u0 + d * np.array([np.cos(phi), np.sin(phi)]))
            for i in np.flatnonzero(use & r["ok"]):
                add(i, r["ux"][i], r["uy"][i], r["factor"][i])
    return sols


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vertices", type=int, default=400)
    ap.add_argument("--samples", type=int, default=1000, help="samples of the render's connection per vertex")
    ap.add_argument("--depth", type=float, default=100.0, help="mean vertex depth, um")
    ap.add_argument("--band-nm", type=float, default=600.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    cfg = C.load(os.path.join(ROOT, "configs", "forearm.toml"))
    cfg["spectrum"].update(start_nm=a.band_nm, stop_nm=a.band_nm)
    vol = volume.build(cfg)
    dev = open_device(a.device)
    light = tuple(float(v) * 1000.0 for v in cfg["light"]["position_mm"])
    rng = np.random.default_rng(a.seed)
    n = a.vertices
    verts = np.stack([rng.uniform(500, 9500, n), rng.uniform(500, 9500, n),
                      -rng.exponential(a.depth, n) - 0.5, np.zeros(n)], 1)
    verts = verts.astype(np.float32).astype(float)
    r0 = testing.mnee_probe(dev, vol, light, verts, 0)
    use = r0["built"] & (r0["layer"] >= 0)
    sols = dense_search(dev, vol, light, verts, r0, use)
    K = a.samples
    rs = testing.mnee_probe(dev, vol, light, np.repeat(verts, K, 0), 0)
    smp = rs["all_factor"].reshape(n, K)
    layers = r0["layer"].astype(int)
    flat = np.where(r0["ok"], r0["factor"], 0.0)
    dense = np.array([sum(s[2] for s in q) for q in sols])
    nsol = np.array([len(q) for q in sols])
    rows = {}
    for name, m in [("all", use)] + [(vol.names[k], use & (layers == k)) for k in range(vol.nl)]:
        idx = np.flatnonzero(m)
        if not idx.size or flat[idx].sum() <= 0:
            continue
        f0 = flat[idx].sum()
        se = np.sqrt((smp[idx].var(1, ddof=1) / K).sum()) / f0
        rows[name] = {"vertices": int(idx.size), "flat_seeded_solved": float(r0["ok"][idx].mean()),
                      "more_than_one_solution": float((nsol[idx] > 1).mean()),
                      "max_solutions": int(nsol[idx].max()),
                      "dense_over_flat": float(dense[idx].sum() / f0),
                      "sms_over_flat": float(smp[idx].mean(1).sum() / f0), "sms_se": float(se),
                      "connection_found": float((rs["solutions"].reshape(n, K)[idx] > 0).mean()),
                      "trials_per_connection": float(rs["trials"].reshape(n, K)[idx].mean()),
                      "clamped_per_connection": float(rs["clamped"].reshape(n, K)[idx].mean())}
        w = rows[name]
        print(f"{name:24s} {idx.size:4d} vertices: flat-seeded solved {w['flat_seeded_solved']:.4f}, found "
              f"{w['connection_found']:.4f}, >1 solution {w['more_than_one_solution']:.3f} (max {w['max_solutions']}); "
              f"all / flat-seeded light: dense {w['dense_over_flat']:.4f}, sampled {w['sms_over_flat']:.4f} "
              f"+- {w['sms_se']:.4f}; {w['trials_per_connection']:.2f} trials, clamped {w['clamped_per_connection']:.1e}",
              flush=True)
    os.makedirs(os.path.join(ROOT, "out", "bench"), exist_ok=True)
    with open(os.path.join(ROOT, "out", "bench", "mnee_solutions.json"), "w") as f:
        json.dump({"vertices": n, "samples": K, "mean_depth_um": a.depth, "band_nm": a.band_nm,
                   "light_um": light, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
