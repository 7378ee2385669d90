"""What the surface model changes in the default image: the smooth walk against the voxel model.

The default (method e, its passes) is rendered on both models (`model.surface = "smooth"` and
`"voxels"`) with the same seeds, each image measured per 50-nm band group against one
path-tracer reference of the config as given (its own surface); per seed the difference of the
two relative errors is the relative change of the band group's mean, and the seeds give its
mean and seed-to-seed standard deviation.  Specular highlights off, as in bench/studies/bias.py
(whose cached reference this shares).

    python bench/studies/surface_change.py out/report/forearm-nohighlight.toml --seeds 4

Prints the table and writes out/bench/surface_change.json.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from clppm import config as C                                        # noqa: E402
from clppm.analysis.metrics import accuracy                          # noqa: E402
from clppm.analysis.reference import RefSpec, get_reference          # noqa: E402
from clppm.compute.device import open_device                         # noqa: E402
from clppm.run.entry import render                             # noqa: E402
from clppm.scene import volume                                       # noqa: E402

SURFACES = ("smooth", "voxels")


def band_groups(cfg: dict, res: tuple, passes: int, seed: int, ref, dev) -> dict[str, float]:
    """One render's relative error per band group against ``ref``."""
    r = render(cfg, method="e", passes=passes, resolution=res, dev=dev, seed=seed)
    return {g: float(v) for g, v in accuracy(r.xyz, r.spectral, ref)["groups"].items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--resolution", default="80x60")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--passes", type=int, help="default: the config's")
    ap.add_argument("--ref-paths", type=int, default=60000, help="reference paths per 10x10 square and half")
    ap.add_argument("--cache", default=os.path.join(ROOT, "out", "cache"))
    ap.add_argument("-o", "--out", default=os.path.join(ROOT, "out", "bench"))
    a = ap.parse_args(argv)
    dev = open_device(None)
    cfg = C.load(a.config)
    cfg = C.override(cfg, "render", "specular", False)
    cfg = C.override(cfg, "render", "checkpoint_every", 0)
    res = tuple(int(v) for v in a.resolution.split("x"))
    passes = a.passes or int(cfg["render"]["passes"])
    ref = get_reference(cfg, RefSpec(integrator="pt", resolution=res, block=10, paths=a.ref_paths),
                        a.cache, dev=dev, progress=True)
    per_seed = {s: [] for s in SURFACES}
    with volume.memoised():
        for surf in SURFACES:
            c = C.override(cfg, "model", "surface", surf)
            for seed in range(1, a.seeds + 1):
                per_seed[surf].append(band_groups(c, res, passes, seed, ref, dev))
                print(f"  {surf} seed {seed}: " + ", ".join(f"{g} {100 * v:+.2f} %"
                                                            for g, v in per_seed[surf][-1].items()), flush=True)
    groups = list(per_seed[SURFACES[0]][0])
    d = 100 * np.array([[per_seed["smooth"][i][g] - per_seed["voxels"][i][g] for g in groups]
                        for i in range(a.seeds)])
    sd = d.std(0, ddof=1) if a.seeds > 1 else np.full(len(groups), np.nan)
    print(f"smooth minus voxels, {res[0]}x{res[1]}, {passes} passes, {a.seeds} seeds "
          f"(reference {ref.key}): mean (seed-to-seed SD)")
    for j, g in enumerate(groups):
        print(f"  {g} nm: {d[:, j].mean():+.2f} % ({sd[j]:.2f})")
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "surface_change.json"), "w") as f:
        json.dump({"config": a.config, "resolution": list(res), "passes": passes, "reference": ref.key,
                   "groups": groups, "per_seed": per_seed,
                   "smooth_minus_voxels": {g: [float(d[:, j].mean()), float(sd[j])] for j, g in enumerate(groups)}},
                  f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
