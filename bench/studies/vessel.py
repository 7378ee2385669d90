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

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from heterogeneous import arguments, compare, overhead, pixel_xy, sd, shipped, write   # noqa: E402
from clppm import config as C                                        # noqa: E402
from clppm.analysis.metrics import band_groups                       # noqa: E402

VESSEL = {"kind": "vessel", "center_mm": [5.0, 5.0], "depth_um": 300.0, "axis": [0.0, 1.0, 0.0],
          "radius_um": 200.0, "blood": 1.0, "saturation": 0.6}
OVER_MM, AWAY_MM = 0.25, 1.2


def vessel_scene(res=(32, 24), passes=4, photons=200_000, pt_samples=16, seed=1, vessel=True,
                 initial_photons=None, estimator=None, relief=False) -> dict:
    """configs/forearm_vein.toml, its vein replaced by VESSEL and the freckles removed, seen from
    30 mm above its centre over FIELD_MM; specular highlights off (both integrators alike)."""
    raw = shipped("forearm_vein")
    raw["inclusion"] = [dict(VESSEL)] if vessel else []
    if not vessel:
        raw.pop("inclusion")
    return overhead(raw, res, passes, photons, pt_samples, seed, initial_photons, estimator, relief, "vessel")


def column_masks(cfg: dict) -> tuple[np.ndarray, np.ndarray]:
    """Pixel columns over the vessel and away from it (the camera looks straight down at x = 5 mm)."""
    x, _ = pixel_xy(cfg)
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
    ap = arguments(__doc__, "48x36", 16, "vessel.json")
    ap.add_argument("--estimator", default=None, help="render.estimator (default: the config's, beam)")
    a = ap.parse_args(argv)
    run = compare(a, vessel_scene, vessel_figures, estimator=a.estimator)
    pt, ppm = run["pt"], run["ppm"]
    print("group (nm) | PPM/PT - 1 (mean +- sd) | contrast PT | contrast PPM (mean +- sd) | PPM/PT contrast - 1")
    rows = {}
    for g in pt:
        m = np.array([p[g]["mean"] / pt[g]["mean"] - 1 for p in ppm])
        c = np.array([p[g]["contrast"] for p in ppm])
        rows[g] = {"mean_err": m.tolist(), "contrast_pt": pt[g]["contrast"], "contrast_ppm": c.tolist()}
        print(f"{g} | {100 * m.mean():+.2f} +- {100 * sd(m):.2f} % | {pt[g]['contrast']:.4f} | "
              f"{c.mean():.4f} +- {sd(c):.4f} | {100 * (c.mean() / pt[g]['contrast'] - 1):+.2f} %")
    write(a.out, run, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
