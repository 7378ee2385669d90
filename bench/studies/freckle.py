"""PPM against the path tracer on the flat forearm with chromophore maps, per 50-nm band group.

configs/forearm_flat.toml's layers (10-nm bands, 380-780 nm) with two [[map]] tables: a dense
melanin freckle in the basal layer (a Gaussian spot of radius 600 um, melanosome fraction 0.5 at
its centre against the layer's 0.1) 0.9 mm left of the middle of a 4 mm field, and a blood spot in
the subpapillary dermis (radius 600 um, blood 0.25 against 0.02) 0.9 mm right of it, seen from 30 mm above
(0.31 mm per pixel at 13 rows).  Both integrators render the same scene; per 50-nm band group
(and the red, 630-780 nm, pooled) this prints

  * the whole image's mean radiance, PPM / PT - 1 (PPM's bias on this stack plus noise), and
  * the contrast of each spot: the mean over the pixels within SPOT_MM of its centre over the
    mean of the pixels farther than AWAY_MM from both centres, for PPM and for PT, and their
    ratio (PPM's bias largely cancels in it: what is left is how PPM sees the maps).

With several PPM seeds the spread of these figures over the seeds is printed too.

    python bench/studies/freckle.py --resolution 17x13 --passes 8 --pt-passes 16 --pt-samples 256 --seeds 3

tests/test_maps_ppm.py runs a small version of this (freckle_scene, freckle_figures).
"""
from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from heterogeneous import arguments, compare, overhead, pixel_xy, sd, shipped, write   # noqa: E402
from clppm import config as C                                        # noqa: E402
from clppm.analysis.metrics import band_groups                       # noqa: E402

FRECKLE_MM, BLOOD_MM = (4.1, 5.0), (5.9, 5.0)
FRECKLE = {"layer": "basal", "quantity": "melanin", "kind": "spots",
           "spots": [{"center_mm": list(FRECKLE_MM), "radius_um": 600.0, "peak": 0.5}]}
BLOOD = {"layer": "subpapillary dermis", "quantity": "blood", "kind": "spots",
         "spots": [{"center_mm": list(BLOOD_MM), "radius_um": 600.0, "peak": 0.25}]}
SPOT_MM, AWAY_MM = 0.5, 1.3


def freckle_scene(res=(17, 13), passes=4, photons=200_000, pt_samples=16, seed=1, maps=True,
                  initial_photons=None, uniform=False, relief=False) -> dict:
    """configs/forearm_flat.toml with FRECKLE and BLOOD (``maps``; ``uniform``: each map a
    constant of its layer's own value instead), 10-nm bands, seen from 30 mm above its centre
    over FIELD_MM; specular highlights off (both integrators alike)."""
    raw = shipped("forearm_flat")
    raw["spectrum"] = {**raw["spectrum"], "step_nm": 10.0}
    if maps:
        own = {L["name"]: L for L in raw["layer"]}
        raw["map"] = ([{"layer": m["layer"], "quantity": m["quantity"], "kind": "constant",
                        "value": own[m["layer"]][m["quantity"]]} for m in (FRECKLE, BLOOD)] if uniform
                      else [dict(FRECKLE), dict(BLOOD)])
    return overhead(raw, res, passes, photons, pt_samples, seed, initial_photons, None, relief, "freckle")


def masks(cfg: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels over the freckle, over the blood spot, and away from both (the camera looks straight
    down at (5, 5) mm; rows run along y downwards in the image)."""
    X, Y = np.meshgrid(*pixel_xy(cfg))
    df = np.hypot(X - FRECKLE_MM[0], Y - FRECKLE_MM[1])
    db = np.hypot(X - BLOOD_MM[0], Y - BLOOD_MM[1])
    return df < SPOT_MM, db < SPOT_MM, (df > AWAY_MM) & (db > AWAY_MM)


def freckle_figures(cfg: dict, spectral: np.ndarray) -> dict:
    """Per band group: the image mean and each spot's contrast (over it / away)."""
    wl = C.wavelengths(cfg)
    fr, bl, away = masks(cfg)
    out = {}
    groups = [(f"{lo:.0f}-{hi:.0f}", idx) for lo, hi, idx in band_groups(wl)] + [("red", np.nonzero(wl >= 630.0)[0])]
    for name, idx in groups:
        g = np.asarray(spectral, float)[..., idx].sum(-1)
        out[name] = {"mean": float(g.mean()), "freckle": float(g[fr].mean() / g[away].mean()),
                     "blood": float(g[bl].mean() / g[away].mean())}
    return out


def main(argv=None) -> int:
    a = arguments(__doc__, "17x13", 256, "freckle.json").parse_args(argv)
    run = compare(a, freckle_scene, freckle_figures)
    pt, ppm = run["pt"], run["ppm"]
    print("group (nm) | PPM/PT - 1 (mean +- sd) | freckle PT | PPM (mean +- sd) | blood PT | PPM (mean +- sd)")
    rows = {}
    for g in pt:
        m = np.array([p[g]["mean"] / pt[g]["mean"] - 1 for p in ppm])
        f = np.array([p[g]["freckle"] for p in ppm])
        b = np.array([p[g]["blood"] for p in ppm])
        rows[g] = {"mean_err": m.tolist(), "freckle_pt": pt[g]["freckle"], "freckle_ppm": f.tolist(),
                   "blood_pt": pt[g]["blood"], "blood_ppm": b.tolist()}
        print(f"{g} | {100 * m.mean():+.2f} +- {100 * sd(m):.2f} % | {pt[g]['freckle']:.4f} | "
              f"{f.mean():.4f} +- {sd(f):.4f} | {pt[g]['blood']:.4f} | {b.mean():.4f} +- {sd(b):.4f}")
    write(a.out, run, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
