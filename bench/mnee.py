"""The path tracer on the relief forearm against the flat forearm: cost per path and the manifold
solver's statistics (docs/relief.md).

Both configs render with ``--integrator pt`` at the same small resolution and samples, side by
side in one run, alternating, best of N (the machine is shared): paths per second of the
tracing alone (the relief's volume is built once, outside the timing), their ratio, the
manifold connections' success rate, Newton iterations and failures, and what a connection costs
on each.  Results go to out/bench/mnee.json.

    python bench/mnee.py --resolution 16x12 --spp 64 --repeat 3
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from clppm import config as C                      # noqa: E402
from clppm import pathtracer as pt                 # noqa: E402
from clppm import volume                           # noqa: E402
from clppm.device import open_device               # noqa: E402


def one(cfg, dev):
    t0 = time.perf_counter()
    res = pt.render_pt(cfg, dev=dev)
    r = res.report
    return {"seconds_trace": r["seconds"]["trace"], "paths": r["paths_traced"],
            "paths_per_second": r["paths_per_second"],
            "nee_made": r["nee_connections_made"], "nee_blocked": r["nee_connections_blocked"],
            "vertices_per_path": r["mean_vertices_per_path"], "manifold": r["manifold_nee"],
            "mean_Y": float(res.xyz[..., 1].mean()), "wall": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", default="16x12")
    ap.add_argument("--spp", type=int, default=64, help="paths per pixel per pass")
    ap.add_argument("--passes", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.resolution.split("x"))
    dev = open_device(a.device)
    cfgs = {}
    for name in ("forearm", "forearm_flat"):
        c = C.load(os.path.join(ROOT, "configs", f"{name}.toml"))
        c["camera"]["resolution"] = [w, h]
        c["render"]["pt_samples_per_pass"] = a.spp
        c["render"]["passes"] = a.passes
        c["render"]["checkpoint_every"] = 0
        c["render"]["specular"] = False
        t0 = time.perf_counter()
        volume.build(c)
        print(f"{name}: volume {time.perf_counter() - t0:.1f} s", flush=True)
        cfgs[name] = c
    runs = {k: [] for k in cfgs}
    for i in range(a.repeat):
        for k, c in cfgs.items():
            r = one(c, dev)
            runs[k].append(r)
            m = r["manifold"]
            extra = (f", solved {m['success_rate']:.5f} of {m['solves']}, "
                     f"{m['mean_iterations']:.2f} iterations" if m else "")
            print(f"  {k} run {i + 1}: {r['paths_per_second']:.0f} paths/s{extra}", flush=True)
    best = {k: max(v, key=lambda r: r["paths_per_second"]) for k, v in runs.items()}
    ratio = best["forearm_flat"]["paths_per_second"] / best["forearm"]["paths_per_second"]
    tot = [sum(r["manifold"][s] for r in runs["forearm"]) for s in pt.MNEE_STATS]
    out = {"resolution": [w, h], "spp": a.spp, "passes": a.passes, "repeat": a.repeat,
           "device": dev.name, "runs": runs,
           "cost_per_path_relief_over_flat": ratio,
           "manifold_all_runs": pt.mnee_report(tot)}
    print(f"cost per path, relief / flat (best of {a.repeat}): {ratio:.2f}x; "
          f"solver success {out['manifold_all_runs']['success_rate']:.5f} over {tot[0]} connections, "
          f"{out['manifold_all_runs']['mean_iterations']:.2f} Newton iterations per connection; "
          f"flat-seeded {out['manifold_all_runs']['flat_seeded_rate']:.5f}, other solutions "
          f"{out['manifold_all_runs']['other_solution_share']:.4f} per connection, clamped "
          f"{out['manifold_all_runs']['clamped_share']:.4f} of them, trials "
          f"{out['manifold_all_runs']['trials_per_connection']:.3f} per connection")
    os.makedirs(os.path.join(ROOT, "out", "bench"), exist_ok=True)
    with open(os.path.join(ROOT, "out", "bench", "mnee.json"), "w") as f:
        json.dump(out, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
