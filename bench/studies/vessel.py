"""PPM against the path tracer on the flat forearm with a vessel, per 50-nm band group.

configs/forearm_vein.toml's layers with one vessel (no freckles), shallower and thinner than the
shipped vein so that the image shows it in the green: radius 200 um, centre 300 um deep in the
dermis (100-500 um), along y under the middle of a 4 mm field seen from above (0.31 mm per pixel
at 13 rows; an odd width puts a column over the vessel's axis).  Both integrators render the same
scene; per 50-nm band group (and the red, 630-780 nm, pooled) this prints

  * the whole image's mean radiance, PPM / PT - 1 (PPM's bias on this stack plus noise), and
  * the contrast of the vessel: the mean over the columns above the vessel (|x - 5 mm| < 0.25 mm)
    over the mean of the columns away from it (|x - 5 mm| > 1.2 mm), for PPM and for PT, and
    their ratio (PPM's bias largely cancels in it: what is left is how PPM sees the vessel).

With several PPM seeds the spread of these figures over the seeds is printed too.

    python bench/studies/vessel.py --resolution 17x13 --passes 8 --pt-passes 16 --pt-samples 256 --seeds 3

tests/test_inclusions_ppm.py runs a small version of this (vessel_scene, vessel_figures).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from clppm import config as C                                        # noqa: E402
from clppm.analysis.metrics import band_groups                       # noqa: E402

FIELD_MM = 4.0              # the camera's field, rows
VESSEL = {"kind": "vessel", "center_mm": [5.0, 5.0], "depth_um": 300.0, "axis": [0.0, 1.0, 0.0],
          "radius_um": 200.0, "blood": 1.0, "saturation": 0.6}
OVER_MM, AWAY_MM = 0.25, 1.2


RELIEF = {"kind": "generated", "depth_um": 20.0, "spacing_um": 350.0, "width_um": 100.0, "seed": 7}


def with_relief(raw: dict) -> None:
    """``relief=True``: configs/forearm.toml's relief on the same layers (generated furrows 20 um
    deep, a wavy junction of 10 um, the smooth surfaces): PPM and the path tracer on the relief
    (tests/test_ppm_relief_heterogeneous.py)."""
    raw["relief"] = dict(RELIEF)
    raw["papillae"] = {**raw["papillae"], "amplitude_um": 10.0}
    raw["model"] = {**raw["model"], "surface": "smooth"}


def vessel_scene(res=(32, 24), passes=4, photons=200_000, pt_samples=16, seed=1, vessel=True,
                 initial_photons=None, estimator=None, relief=False) -> dict:
    """configs/forearm_vein.toml, its vein replaced by VESSEL and the freckles removed, seen from
    30 mm above its centre over FIELD_MM; specular highlights off (both integrators alike)."""
    raw = C.load("forearm_vein")
    raw = {k: (list(v) if isinstance(v, list) else dict(v)) for k, v in raw.items()}
    raw["inclusion"] = [dict(VESSEL)] if vessel else []
    if not vessel:
        raw.pop("inclusion")
    fov = 2 * math.degrees(math.atan(FIELD_MM / 2 / 30.0))
    raw["camera"] = {**raw["camera"], "fov_deg": fov, "resolution": list(res)}
    raw["render"] = {**raw["render"], "passes": passes, "photons": photons, "seed": seed, "specular": False,
                     "pt_samples_per_pass": pt_samples}
    if initial_photons:
        raw["render"]["initial_photons"] = initial_photons
    if estimator:
        raw["render"]["estimator"] = estimator
    if relief:
        with_relief(raw)
    return C.validate(raw, "vessel")


def column_masks(cfg: dict) -> tuple[np.ndarray, np.ndarray]:
    """Pixel columns over the vessel and away from it (the camera looks straight down at x = 5 mm)."""
    w, h = cfg["camera"]["resolution"]
    x = 5.0 + (np.arange(w) + 0.5 - w / 2) * FIELD_MM / h       # square pixels, FIELD_MM over the rows
    return np.abs(x - 5.0) < OVER_MM, np.abs(x - 5.0) > AWAY_MM


def vessel_figures(cfg: dict, spectral: np.ndarray) -> dict:
    """Per band group: the image mean and the vessel's contrast (over / away)."""
    wl = C.wavelengths(cfg)
    over, away = column_masks(cfg)
    out = {}
    for lo, hi, idx in band_groups(wl):
        g = np.asarray(spectral, float)[..., idx].sum(-1)
        out[f"{lo:.0f}-{hi:.0f}"] = {"mean": float(g.mean()), "contrast": float(g[:, over].mean() / g[:, away].mean())}
    # the red, pooled (630-780 nm): where blood is clear and scatters 4x less than the dermis
    r = np.asarray(spectral, float)[..., wl >= 630.0].sum(-1)
    out["red"] = {"mean": float(r.mean()), "contrast": float(r[:, over].mean() / r[:, away].mean())}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--resolution", default="48x36")
    ap.add_argument("--passes", type=int, default=8)
    ap.add_argument("--photons", type=int, default=400_000)
    ap.add_argument("--pt-passes", type=int, default=16)
    ap.add_argument("--pt-samples", type=int, default=16)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--initial-photons", type=int, default=200, help="K of the first search (default 200)")
    ap.add_argument("--estimator", default=None, help="render.estimator (default: the config's, beam)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "bench", "vessel.json"))
    a = ap.parse_args(argv)
    from clppm.compute.device import open_device
    from clppm.run.entry import render, render_pt
    dev = open_device(a.device)
    res = tuple(int(v) for v in a.resolution.split("x"))
    t0 = time.perf_counter()
    cfg = vessel_scene(res, a.pt_passes, a.photons, a.pt_samples, seed=101)
    pt = vessel_figures(cfg, render_pt(cfg, dev=dev).spectral)
    t_pt = time.perf_counter() - t0
    ppm, t_ppm = [], []
    for s in range(1, a.seeds + 1):
        t0 = time.perf_counter()
        c = vessel_scene(res, a.passes, a.photons, a.pt_samples, seed=s, initial_photons=a.initial_photons,
                         estimator=a.estimator)
        ppm.append(vessel_figures(c, render(c, dev=dev).spectral))
        t_ppm.append(time.perf_counter() - t0)
    print(f"{res[0]}x{res[1]}, PPM {a.passes} passes x {a.photons} photons, {a.seeds} seeds "
          f"({np.median(t_ppm):.1f} s each); PT {a.pt_passes} passes x {a.pt_samples} paths/pixel "
          f"({t_pt:.1f} s); {dev.device.name.strip()}")
    print("group (nm) | PPM/PT - 1 (mean +- sd) | contrast PT | contrast PPM (mean +- sd) | PPM/PT contrast - 1")
    rows = {}
    for g in pt:
        m = np.array([p[g]["mean"] / pt[g]["mean"] - 1 for p in ppm])
        c = np.array([p[g]["contrast"] for p in ppm])
        rows[g] = {"mean_err": m.tolist(), "contrast_pt": pt[g]["contrast"], "contrast_ppm": c.tolist()}
        sd = lambda v: v.std(ddof=1) if len(v) > 1 else float("nan")
        print(f"{g} | {100 * m.mean():+.2f} +- {100 * sd(m):.2f} % | {pt[g]['contrast']:.4f} | "
              f"{c.mean():.4f} +- {sd(c):.4f} | {100 * (c.mean() / pt[g]['contrast'] - 1):+.2f} %")
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump({"resolution": res, "passes": a.passes, "photons": a.photons, "pt_passes": a.pt_passes,
                   "pt_samples": a.pt_samples, "seeds": a.seeds, "t_ppm_s": t_ppm, "t_pt_s": t_pt,
                   "device": dev.device.name.strip(), "groups": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
