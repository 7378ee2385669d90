"""The smooth walk (model.surface = "smooth") against the voxel staircase, in one run:

* the tilted plane of tests/test_surface.py at slopes 0.15 and 0.3 and incidences 0, 40, 60
  degrees: diffuse reflectance against the flat slab under the rotated beam, in standard errors;
* the forearm's device memory for each walk;
* the photon pass on the forearm per emitted photon (no storage; rounds alternate the walks,
  medians), and its loop steps per photon by kind (the PHOTON_COUNTERS build).

    python bench/surface.py [--photons N] [--rounds R] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))

from clppm import config  # noqa: E402
from clppm.compute.device import open_device  # noqa: E402
from clppm.integrators import photonpass  # noqa: E402
from clppm.scene import volume  # noqa: E402

WALKS = ("voxels", "smooth")


def tilted_plane(dev, photons: int) -> list[dict]:
    """Rd of the tilted plane (each walk) and of the rotated flat slab, per slope and incidence."""
    import test_surface as ts
    rows, saved = [], ts.SLOPE
    tmp = Path(tempfile.mkdtemp())
    try:
        for slope in (0.15, 0.3):
            ts.SLOPE = slope
            nrm, tan = ts.frame()
            sub = tmp / str(slope)
            sub.mkdir()
            for inc in (0.0, 40.0, 60.0):
                a = math.radians(inc)
                local = np.array([math.sin(a), 0.0, -math.cos(a)])
                d = local[0] * tan + local[2] * nrm
                row = {"slope": slope, "incidence_deg": inc}
                slab = ts.tilted_scene(sub, False, local)
                r = photonpass.trace_report(photonpass.PhotonPass.of_config(dev, volume.build(slab), slab, seed=11),
                                            photons, batches=10)
                row["slab"] = (r["Rd"], r["Rd_se"])
                for walk in WALKS:
                    cfg = ts.tilted_scene(sub, True, d)
                    cfg["model"]["surface"] = walk
                    zc = -slope * ts.SIZE_MM * 500.0          # the beam meets the plane at the centre
                    cfg["light"]["center_mm"] = [(ts.SIZE_MM * 500.0 - zc / d[2] * d[0]) / 1000.0, ts.SIZE_MM / 2]
                    t = photonpass.trace_report(photonpass.PhotonPass.of_config(dev, volume.build(cfg), cfg, seed=11),
                                                photons, batches=10)
                    row[walk] = (t["Rd"], t["Rd_se"], (t["Rd"] - r["Rd"]) / math.hypot(t["Rd_se"], r["Rd_se"]))
                rows.append(row)
                print(f"tilted plane slope {slope} incidence {inc:g}: slab {r['Rd']:.4f}, "
                      + ", ".join(f"{w} {row[w][0]:.4f} ({row[w][2]:+.1f} SE)" for w in WALKS), flush=True)
    finally:
        ts.SLOPE = saved
    return rows


def forearm(walk: str) -> tuple[dict, volume.Volume]:
    cfg = config.load(os.path.join(ROOT, "configs", "forearm.toml"))
    cfg["model"]["surface"] = walk
    return cfg, volume.build(cfg)


def photon_cost(dev, photons: int, rounds: int) -> dict:
    """Microseconds per emitted photon on the forearm (trace, no storage) and steps per photon."""
    passes, out = {}, {}
    for walk in WALKS:
        cfg, vol = forearm(walk)
        passes[walk] = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=0, seed=3)
        passes[walk].trace(5000, 99)                       # built and warm
        out[walk] = {"device_bytes": int(sum(vol.device_bytes().values())), "us_per_photon": []}
    for r in range(rounds):
        for walk, pp in passes.items():
            t0 = time.perf_counter()
            pp.trace(photons, r)
            out[walk]["us_per_photon"].append((time.perf_counter() - t0) / photons * 1e6)
            print(f"round {r + 1}: {walk} {out[walk]['us_per_photon'][-1]:.2f} us per emitted photon", flush=True)
    for walk in WALKS:
        cfg, vol = forearm(walk)
        pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=0, seed=3, counters=True)
        pp.trace(min(photons, 100_000), 0)
        c = pp.counts()
        n = min(photons, 100_000)
        out[walk]["per_photon"] = {k: c[k] / n for k in ("steps", "collisions", "interface", "zone", "wall", "tile")}
        out[walk]["median_us"] = statistics.median(out[walk]["us_per_photon"])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photons", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    dev = open_device(None)
    doc = {"device": dev.name, "tilted": tilted_plane(dev, a.photons),
           "forearm": photon_cost(dev, 2 * a.photons, a.rounds)}
    f = doc["forearm"]
    print(f"forearm photon pass: voxels {f['voxels']['median_us']:.2f}, smooth {f['smooth']['median_us']:.2f} "
          f"us per emitted photon ({f['smooth']['median_us'] / f['voxels']['median_us']:.3f}x); device memory "
          f"{f['voxels']['device_bytes'] / 1e6:.0f} MB, {f['smooth']['device_bytes'] / 1e6:.0f} MB")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(doc, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
