"""Where the default's render time buys the most image quality: one image's noise (two seeds,
bench/studies/noise.py's measure) at equal render seconds for variants of the budget, in
alternating rounds (the order reversed every other round; fresh seeds per round).

    python bench/studies/budget.py                       # the variants below, 80x60, 40 s, 2 rounds
    python bench/studies/budget.py --variant ss30:store_scale=30 --variant ph405k:photons=405000

Each variant changes [render] keys of configs/forearm.toml.  Efficiency is 1/(noise^2 x seconds)
with noise the mean CIEDE2000 (and the RMS of Y) of one image.  Noise only: importance storage
(store_scale) leaves the expected image unchanged, the photons per pass change the radius
schedule and so the bias (bench/studies/bias.py measures that).  Writes OUT/budget.json and
prints the table of medians over rounds.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path[:0] = [ROOT, HERE]

import noise as N                                       # noqa: E402  (bench/studies/noise.py)
from clppm import config as C                            # noqa: E402
from clppm.scene import volume                           # noqa: E402

VARIANTS = ["ss10:", "ss3:store_scale=3", "ss30:store_scale=30", "ss100:store_scale=100",
            "ph405k:photons=405000", "ph1620k:photons=1620000"]
KEEP = ("passes", "seconds", "noise_Y", "noise_dE", "eff_Y", "eff_dE", "emitted", "stored")


def variant(s: str) -> tuple[str, dict]:
    name, _, kv = s.partition(":")
    return name, {k: json.loads(v) for k, v in (p.split("=", 1) for p in kv.split(",") if p)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--variant", action="append", help="NAME:key=value[,key=value] of [render]")
    ap.add_argument("--resolution", default="80x60")
    ap.add_argument("--budget", type=float, default=40.0, help="render seconds per image")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("-o", "--out", default="out/bench")
    a = ap.parse_args(argv)
    from clppm.compute.device import open_device
    dev = open_device(None)
    cfg = C.load(a.config)
    cfg = C.override(cfg, "render", "checkpoint_every", 0)
    cfg = C.override(cfg, "camera", "resolution", [int(v) for v in a.resolution.split("x")])
    variants = dict(variant(v) for v in (a.variant or VARIANTS))
    names, out = list(variants), {}
    print(f"bench/studies/budget.py on {dev.name}: {a.resolution}, {a.budget:g} s per image, {a.rounds} rounds")
    with volume.memoised():
        for rnd in range(a.rounds):
            for name in (names if rnd % 2 == 0 else names[::-1]):
                t0 = time.time()
                r = N.run_mode(cfg, variants[name], seeds=(11 + 100 * rnd, 22 + 100 * rnd),
                               budget=a.budget, dev=dev, log=lambda *x: None)
                row = {k: r["rows"][-1][k] for k in KEEP}
                out.setdefault(name, []).append(row)
                print(f"  round {rnd} {name}: {row['passes']} passes, {row['seconds']:.1f} s, "
                      f"noise dE {row['noise_dE']:.2f}, Y {100 * row['noise_Y']:.2f} % "
                      f"({time.time() - t0:.0f} s wall)", flush=True)
    base = statistics.median(r["eff_dE"] for r in out[names[0]])
    print(f"\n| variant | {' | '.join(['passes', 'seconds', 'noise ΔE00', 'noise Y', 'efficiency ΔE (1/s)', f'vs {names[0]}'])} |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in names:
        m = {k: statistics.median(r[k] for r in out[name]) for k in KEEP}
        print(f"| {name} {variants[name] or ''} | {m['passes']:g} | {m['seconds']:.1f} | {m['noise_dE']:.2f} | "
              f"{100 * m['noise_Y']:.2f} % | {m['eff_dE']:.3g} | {m['eff_dE'] / base:.2f}x |")
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "budget.json"), "w") as f:
        json.dump({"device": dev.info(), "resolution": a.resolution, "budget": a.budget,
                   "variants": variants, "rounds": out}, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
