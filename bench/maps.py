"""The photon pass's cost of chromophore maps ([[map]]; kernels/maps.h): photons per second of
``PhotonPass.trace`` (one band per path, tallies only) on the flat forearm (configs/forearm_flat.toml)
under a wide beam over the whole 10 mm model, in one process, rounds alternating:

* ``no map``: the forearm as shipped (no MAPS in the build);
* ``uniform basal``: the basal layer's melanin mapped to its own value everywhere (the MAPS build,
  its majorant the layer's mu_t: the cost of the map's branch and column lookup alone);
* ``freckles``: the five freckles of configs/forearm_freckles.toml (the basal layer, 15 um);
* ``dermis spots``: blood spots (0.04 -> 0.3) in the reticular dermis, where most collisions are:
  null collisions in the thick layer.

The fastest round is the rate, the median beside it (a shared machine only slows a run).

    python bench/maps.py [--device P:D] [--photons 300000] [--rounds 5]
"""
from __future__ import annotations

import argparse
import time
import tomllib


def scenes():
    from clppm import config as C
    raw = tomllib.loads(C.to_toml(C.load("forearm_flat")))
    raw["light"] = {"kind": "wide", "center_mm": [5.0, 5.0], "width_mm": [10.0, 10.0],
                    "direction": [0.0, 0.0, -1.0], "spectrum": "D65"}
    spots = [{"center_mm": [x, y], "radius_um": 400.0, "peak": 0.3} for x in (2.5, 5.0, 7.5) for y in (2.5, 7.5)]
    maps = {"no map": None,
            "uniform basal": [{"layer": "basal", "quantity": "melanin", "kind": "constant", "value": 0.1}],
            "freckles": C.load("forearm_freckles")["map"],
            "dermis spots": [{"layer": "reticular dermis", "quantity": "blood", "kind": "spots", "spots": spots}]}
    for name, m in maps.items():
        r = dict(raw)
        if m:
            r["map"] = m
        yield name, C.validate(r, name)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--photons", type=int, default=300_000)
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args(argv)
    from clppm.compute.device import open_device
    from clppm.integrators import photonpass
    from clppm.scene import volume
    dev = open_device(a.device)
    pps = {}
    for name, cfg in scenes():
        pp = photonpass.PhotonPass.of_config(dev, volume.build(cfg, name), cfg)
        pp.trace(20_000)                       # built and warm
        pps[name] = pp
    rates = {k: [] for k in pps}
    for _ in range(a.rounds):
        for k, pp in pps.items():
            t = time.perf_counter()
            pp.trace(a.photons)
            rates[k].append(a.photons / (time.perf_counter() - t))
    print(f"{dev.name}: {a.photons} photons per round, {a.rounds} rounds")
    base = sorted(rates["no map"])[len(rates["no map"]) // 2]
    for k, v in rates.items():
        med = sorted(v)[len(v) // 2]
        print(f"  {k:14s} best {max(v):8.0f}/s  median {med:8.0f}/s  ({med / base - 1:+.1%} against no map)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
