"""The path tracer on the relief forearm against the flat forearm: cost per path, cost to
converge, and the manifold solver's statistics (docs/relief.md).

Both configs are path-traced at the same small resolution, side by side in one run,
alternating, best of N (the machine is shared): paths per second of the tracing alone (volumes
built outside the timing), the variance of one path (per pixel, relative to the pixel's mean,
the median over the skin pixels; each path carries one band), and the cost to reach the same
error, relief / flat of 1 / (variance x seconds per path).  --trials compares means of the
manifold connection's random trials on the relief (kernels/pt.cl sms_count) side by side, by the
relative variance of the image's sum per path (where a rare large contribution counts as it
does in a block's mean; a median pixel hides it) and the image's efficiency against the first.
The solver's statistics are summed over the relief runs.  Results go to out/bench/mnee.json.

    python bench/studies/mnee.py --resolution 8x6 --spp 128 --passes 2 --repeat 3
    python bench/studies/mnee.py --trials 1,0.5,0.25,0.1 --repeat 4
    python bench/studies/mnee.py --surface voxels
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


def one(cfg, vol, dev, passes, trials=None):
    tr = pt.PathTracer.of_config(dev, vol, cfg)
    if trials is not None:
        tr.e["mnee_trials"] = trials
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
    # the image's sum: its relative variance per path (each pixel's variance by its own weight,
    # so that rare large contributions count as they do in a block's or the image's mean)
    rv_sum = float(var[ok].sum() * ok.sum() / mean[ok].sum() ** 2)
    pps = tr.npix * n / dt
    return {"paths_per_second": pps, "relative_variance_per_path": rv, "image_relative_variance": rv_sum,
            "efficiency": pps / rv, "image": float(mean[ok].sum()),
            "manifold": None if vol.flat else tr.mnee_totals()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", default="8x6")
    ap.add_argument("--spp", type=int, default=128, help="paths per pixel per pass")
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--trials", default=None,
                    help="comma-separated mean random trials per connection to compare on the relief "
                         f"(default: the path tracer's {pt.MNEE_TRIALS:g})")
    ap.add_argument("--surface", choices=("smooth", "voxels"), default=None,
                    help="model.surface of the relief forearm (default: its config's, the smooth walk)")
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.resolution.split("x"))
    trials = [float(v) for v in a.trials.split(",")] if a.trials else [pt.MNEE_TRIALS]
    dev = open_device(a.device)
    built = {}
    for name in ("forearm", "forearm_flat"):
        c = C.load(os.path.join(ROOT, "configs", f"{name}.toml"))
        c["camera"]["resolution"] = [w, h]
        c["render"].update(pt_samples_per_pass=a.spp, specular=False)
        if a.surface and name == "forearm":
            c["model"]["surface"] = a.surface
        built[name] = (c, volume.build(c))
    scenes = {label(t): built["forearm"] + (t,) for t in trials}
    scenes["forearm_flat"] = built["forearm_flat"] + (None,)
    relief = [label(t) for t in trials]
    runs = {k: [] for k in scenes}
    for i in range(a.repeat):
        for k in (list(scenes) if i % 2 == 0 else list(scenes)[::-1]):
            c, vol, t = scenes[k]
            r = one(c, vol, dev, a.passes, t)
            runs[k].append(r)
            print(f"  {k} run {i + 1}: {r['paths_per_second']:.0f} paths/s, relative variance per path "
                  f"{r['relative_variance_per_path']:.3f} (median pixel), {r['image_relative_variance']:.3f} (image)",
                  flush=True)
    best = {k: max(v, key=lambda r: r["paths_per_second"]) for k, v in runs.items()}
    var = {k: float(np.median([r["relative_variance_per_path"] for r in v])) for k, v in runs.items()}
    vimg = {k: float(np.mean([r["image_relative_variance"] for r in v])) for k, v in runs.items()}
    out = {"resolution": [w, h], "spp": a.spp, "passes": a.passes, "repeat": a.repeat,
           "device": dev.name, "runs": runs, "variance_per_path": var, "image_variance_per_path": vimg,
           "relief": {}}
    flat = best["forearm_flat"]["paths_per_second"]
    for k in relief:
        per_path = flat / best[k]["paths_per_second"]
        to_converge = per_path * var[k] / var["forearm_flat"]
        eff = (best[k]["paths_per_second"] / vimg[k]) / (best[relief[0]]["paths_per_second"] / vimg[relief[0]])
        tot = [int(sum(r["manifold"][j] for r in runs[k])) for j in range(len(pt.MNEE_STATS))]
        m = pt.mnee_report(tot)
        image = np.mean([r["image"] for r in runs[k]]) / np.mean([r["image"] for r in runs[relief[0]]])
        out["relief"][k] = {"trials": scenes[k][2], "cost_per_path_relief_over_flat": per_path,
                            "cost_to_converge_relief_over_flat": to_converge, "image_over_first": image,
                            "image_efficiency_over_first": eff,
                            "manifold_all_runs": m}
        print(f"{k}: relief / flat (best of {a.repeat}): {per_path:.1f}x per path, relative variance per "
              f"path {var[k]:.3f} / {var['forearm_flat']:.3f} (median pixel), {to_converge:.1f}x to the same "
              f"error; the image's relative variance per path {vimg[k]:.3f}, its efficiency "
              f"1 / (variance x time) {eff:.2f}x {relief[0]}'s, its sum {image:.4f}x")
        print(f"  solver: found {m['success_rate']:.5f} of {m['solves']} connections (flat-seeded "
              f"{m['flat_seeded_rate']:.5f}, continued {m['continued_share']:.4f}), {m['mean_iterations']:.2f} "
              f"Newton iterations, other solutions {m['other_solution_share']:.4f} per connection "
              f"(clamped {m['clamped_share']:.4f} of them), {m['trials_per_connection']:.3f} random trials, "
              f"vertex above the smooth surface {m['vertex_above_smooth_surface']}")
    os.makedirs(os.path.join(ROOT, "out", "bench"), exist_ok=True)
    with open(os.path.join(ROOT, "out", "bench", "mnee.json"), "w") as f:
        json.dump(out, f, indent=1, default=str)
    return 0


def label(t: float) -> str:
    return f"forearm (trials {t:g})"


if __name__ == "__main__":
    sys.exit(main())
