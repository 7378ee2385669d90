"""What the heterogeneous studies share (bench/studies/vessel.py: an inclusion; freckle.py: maps):
the view from 30 mm above a FIELD_MM field, the relief they can add, one budget for the tests that
run small versions of them, and the comparison itself: the path tracer once, PPM over seeds, a
scene's figures per 50-nm band group for each.

tests/test_inclusions_ppm.py, test_maps_ppm.py and test_ppm_relief_heterogeneous.py render at
TEST_BUDGET."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from clppm import config as C                                        # noqa: E402

FIELD_MM = 4.0              # the camera's field, rows
RELIEF = {"kind": "generated", "depth_um": 20.0, "spacing_um": 350.0, "width_um": 100.0, "seed": 7}


@dataclass(frozen=True)
class Budget:
    """PPM: ``passes`` of ``photons`` stored photons, K = ``initial_photons`` in the first search;
    the path tracer: ``pt_passes`` x ``pt_samples`` paths per pixel; ``res`` pixels over FIELD_MM."""

    res: tuple = (17, 13)
    passes: int = 4
    photons: int = 400_000
    initial_photons: int = 200
    pt_passes: int = 4
    pt_samples: int = 256

    def pt(self, scene: Callable, seed: int = 101, **kw) -> dict:
        """``scene``'s config for the path tracer's render."""
        return scene(self.res, self.pt_passes, self.photons, self.pt_samples, seed=seed, **kw)

    def ppm(self, scene: Callable, seed: int = 1, **kw) -> dict:
        """``scene``'s config for a PPM render."""
        return scene(self.res, self.passes, self.photons, self.pt_samples, seed=seed,
                     initial_photons=self.initial_photons, **kw)


#: The tests' budget: K = 200 (a radius small enough not to blur a 0.4 mm vessel or a 1.2 mm
#: spot away: with the default's K = 2000 the vessel's green contrast reads 0.78 against the path
#: tracer's 0.44), 17x13 pixels (0.31 mm each; an odd width puts a column over the middle).
TEST_BUDGET = Budget()


def with_relief(raw: dict) -> None:
    """``relief=True``: configs/forearm.toml's relief on the same layers (generated furrows 20 um
    deep, a wavy junction of 10 um, the smooth surfaces): PPM and the path tracer on the relief
    (tests/test_ppm_relief_heterogeneous.py)."""
    raw["relief"] = dict(RELIEF)
    raw["papillae"] = {**raw["papillae"], "amplitude_um": 10.0}
    raw["model"] = {**raw["model"], "surface": "smooth"}


def shipped(name: str) -> dict:
    """The shipped config ``name`` as plain, editable tables."""
    raw = C.load(name)
    return {k: (list(v) if isinstance(v, list) else dict(v)) for k, v in raw.items()}


def overhead(raw: dict, res, passes: int, photons: int, pt_samples: int, seed: int,
             initial_photons: int | None = None, estimator: str | None = None, relief: bool = False,
             name: str = "study") -> dict:
    """``raw`` seen from 30 mm above its centre over FIELD_MM at ``res``, rendered with this budget,
    specular highlights off (both integrators alike); validated."""
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
    return C.validate(raw, name)


def pixel_xy(cfg: dict) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel column's x and row's y (mm): the camera looks straight down at (5, 5) mm with
    square pixels, FIELD_MM over the rows."""
    w, h = cfg["camera"]["resolution"]
    return (5.0 + (np.arange(w) + 0.5 - w / 2) * FIELD_MM / h,
            5.0 + (np.arange(h) + 0.5 - h / 2) * FIELD_MM / h)


def arguments(doc: str, resolution: str, pt_samples: int, out: str) -> argparse.ArgumentParser:
    """The studies' command line."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--resolution", default=resolution)
    ap.add_argument("--passes", type=int, default=8)
    ap.add_argument("--photons", type=int, default=400_000)
    ap.add_argument("--pt-passes", type=int, default=16)
    ap.add_argument("--pt-samples", type=int, default=pt_samples)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--initial-photons", type=int, default=200, help="K of the first search (default 200)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "bench", out))
    return ap


def compare(a: argparse.Namespace, scene: Callable, figures: Callable, **kw) -> dict:
    """The path tracer (seed 101) and PPM (seeds 1..a.seeds) on ``scene`` at ``a``'s budget;
    ``figures(cfg, spectral)`` of each, the times, and the budget (written to ``a.out``)."""
    from clppm.compute.device import open_device
    from clppm.run.entry import render, render_pt
    dev = open_device(a.device)
    res = tuple(int(v) for v in a.resolution.split("x"))
    b = Budget(res, a.passes, a.photons, a.initial_photons, a.pt_passes, a.pt_samples)
    t0 = time.perf_counter()
    cfg = b.pt(scene)
    pt = figures(cfg, render_pt(cfg, dev=dev).spectral)
    t_pt = time.perf_counter() - t0
    ppm, t_ppm = [], []
    for s in range(1, a.seeds + 1):
        t0 = time.perf_counter()
        c = b.ppm(scene, seed=s, **kw)
        ppm.append(figures(c, render(c, dev=dev).spectral))
        t_ppm.append(time.perf_counter() - t0)
    print(f"{res[0]}x{res[1]}, PPM {a.passes} passes x {a.photons} photons, {a.seeds} seeds "
          f"({np.median(t_ppm):.1f} s each); PT {a.pt_passes} passes x {a.pt_samples} paths/pixel "
          f"({t_pt:.1f} s); {dev.device.name.strip()}")
    return {"resolution": res, "passes": a.passes, "photons": a.photons, "pt_passes": a.pt_passes,
            "pt_samples": a.pt_samples, "seeds": a.seeds, "t_ppm_s": t_ppm, "t_pt_s": t_pt,
            "device": dev.device.name.strip(), "pt": pt, "ppm": ppm}


def write(out: str, run: dict, rows: dict) -> None:
    """The run's budget and times and its ``rows`` per band group, as JSON."""
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        json.dump({**{k: v for k, v in run.items() if k not in ("pt", "ppm")}, "groups": rows}, f, indent=1)


def sd(v: np.ndarray) -> float:
    """The sample standard deviation (NaN for one value)."""
    return float(v.std(ddof=1)) if len(v) > 1 else float("nan")
