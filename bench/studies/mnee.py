"""The path tracer on the relief forearm against the flat forearm: cost per path, cost to
converge, and the manifold solver's statistics (docs/relief.md).

Both configs are path-traced at the same small resolution, side by side in one run,
alternating, best of N (the machine is shared): paths per second of the tracing alone (volumes
built outside the timing), the variance of one path (per pixel, relative to the pixel's mean,
the median over the skin pixels; each path carries one band), and the efficiency
1 / (variance x seconds per path): relief / flat of it is the cost to reach the same error.
The solver's statistics are summed over the relief runs.  Results go to out/bench/mnee.json.

    python bench/studies/mnee.py --resolution 8x6 --spp 128 --passes 2 --repeat 3
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from clppm import config as C                      # noqa: E402
from clppm.integrators import pathtracer as pt                 # noqa: E402
from clppm.scene import volume                           # noqa: E402
from clppm.compute.device import open_device               # noqa: E402


def one(cfg, vol, dev, passes):
    tr = pt.PathTracer(dev, vol, cfg)
    t0 = time.perf_counter()
    for p in range(passes):
        tr.run_pass(p)
    dt = time.perf_counter() - t0
    st = tr.state_arrays()
    n = tr.nspp * passes
    mean = st["pix_sum"].sum(1) / n
    var = st["pix_sq"].sum(1) / n - mean ** 2
    ok = mean > 0
    rv = float(np.median(var[ok] / mean[ok] ** 2))
    pps = tr.npix * n / dt
    return {"paths_per_second": pps, "relative_variance_per_path": rv, "efficiency": pps / rv,
            "manifold": None if vol.flat else tr.mnee_totals()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", default="8x6")
    ap.add_argument("--spp", type=int, default=128, help="paths per pixel per pass")
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.resolution.split("x"))
    dev = open_device(a.device)
    scenes = {}
    for name in ("forearm", "forearm_flat"):
        c = C.load(os.path.join(ROOT, "configs", f"{name}.toml"))
        c["camera"]["resolution"] = [w, h]
        c["render"].update(pt_samples_per_pass=a.spp, specular=False)
        scenes[name] = (c, volume.build(c))
    runs = {k: [] for k in scenes}
    for i in range(a.repeat):
        for k, (c, vol) in scenes.items():
            r = one(c, vol, dev, a.passes)
            runs[k].append(r)
            print(f"  {k} run {i + 1}: {r['paths_per_second']:.0f} paths/s, variance per path "
                  f"{r['relative_variance_per_path']:.3f}", flush=True)
    best = {k: max(v, key=lambda r: r["paths_per_second"]) for k, v in runs.items()}
    per_path = best["forearm_flat"]["paths_per_second"] / best["forearm"]["paths_per_second"]
    var = {k: float(np.median([r["relative_variance_per_path"] for r in v])) for k, v in runs.items()}
    to_converge = per_path * var["forearm"] / var["forearm_flat"]
    tot = [int(sum(r["manifold"][j] for r in runs["forearm"])) for j in range(len(pt.MNEE_STATS))]
    m = pt.mnee_report(tot)
    out = {"resolution": [w, h], "spp": a.spp, "passes": a.passes, "repeat": a.repeat,
           "device": dev.name, "runs": runs, "cost_per_path_relief_over_flat": per_path,
           "variance_per_path": var, "cost_to_converge_relief_over_flat": to_converge,
           "manifold_all_runs": m}
    print(f"relief / flat (best of {a.repeat}): {per_path:.1f}x per path, variance per path "
          f"{var['forearm']:.3f} / {var['forearm_flat']:.3f}, {to_converge:.1f}x to the same error")
    print(f"solver: found {m['success_rate']:.5f} of {m['solves']} connections (flat-seeded "
          f"{m['flat_seeded_rate']:.5f}, continued {m['continued_share']:.4f}), {m['mean_iterations']:.2f} "
          f"Newton iterations, other solutions {m['other_solution_share']:.4f} per connection "
          f"(clamped {m['clamped_share']:.4f} of them), {m['trials_per_connection']:.3f} random trials, "
          f"vertex above the smooth surface {m['vertex_above_smooth_surface']}")
    os.makedirs(os.path.join(ROOT, "out", "bench"), exist_ok=True)
    with open(os.path.join(ROOT, "out", "bench", "mnee.json"), "w") as f:
        json.dump(out, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
