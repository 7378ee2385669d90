"""Start-up, cold and warm: the README's render run twice in fresh processes, the first with
empty caches (no self-test result, no program binaries, no PoCL kernel cache: a new user's
first run), the second with the caches the first left.

Per run: the process's wall seconds (imports, the device's self-test, everything), the report's
seconds per stage (volume, eye, calibration, photon, grid, gather, output) and the programs built
(count and seconds, inside the stages); the passes' share (photon + grid + gather) of the wall.

    python bench/startup.py [CONFIG] [--resolution 320x240] [--passes 7] [--photons N] [--device P:D]

Prints a markdown table; never asserts on time.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STAGES = ("volume", "eye", "calibration", "photon", "grid", "gather", "output")
PASS_STAGES = ("photon", "grid", "gather")


def run_once(args: list[str], cache: str, out: str) -> dict:
    env = dict(os.environ, XDG_CACHE_HOME=cache)
    env.pop("POCL_CACHE_DIR", None)               # clppm's own, under XDG_CACHE_HOME
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "clppm.cli", "render", *args, "-o", out, "-q"],
                       env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise SystemExit(f"bench/startup.py: clppm render exited {p.returncode}: "
                         f"{(p.stderr.strip().splitlines() or ['?'])[-1]}")
    rep = json.loads(open(os.path.splitext(out)[0] + ".json").read())
    return {"wall": wall, "seconds": rep["seconds"], "programs": rep.get("programs_built", {}),
            "device": rep["device"]["name"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--resolution", default="320x240")
    ap.add_argument("--passes", type=int, default=7)
    ap.add_argument("--photons", type=int)
    ap.add_argument("--device")
    a = ap.parse_args(argv)
    args = [a.config, "--resolution", a.resolution, "--passes", str(a.passes)]
    args += ["--photons", str(a.photons)] if a.photons else []
    args += ["--device", a.device] if a.device else []
    with tempfile.TemporaryDirectory(prefix="clppm-startup-") as d:
        cold = run_once(args, os.path.join(d, "cache"), os.path.join(d, "cold.exr"))
        warm = run_once(args, os.path.join(d, "cache"), os.path.join(d, "warm.exr"))
    print(f"bench/startup.py: {os.path.basename(a.config)} at {a.resolution}, {a.passes} passes, "
          f"on {cold['device']}")
    print("| seconds | cold (empty caches) | warm |")
    print("|---|---:|---:|")
    for k in STAGES:
        print(f"| {k} | {cold['seconds'].get(k, 0.0):.2f} | {warm['seconds'].get(k, 0.0):.2f} |")
    pc, pw = cold["programs"], warm["programs"]
    print(f"| programs built (count; inside the stages) | {pc.get('seconds', 0):.2f} ({pc.get('count', 0)}) | "
          f"{pw.get('seconds', 0):.2f} ({pw.get('count', 0)}) |")
    print(f"| render (report total) | {cold['seconds']['total']:.2f} | {warm['seconds']['total']:.2f} |")
    print(f"| process wall (imports, self-test, render, files) | {cold['wall']:.2f} | {warm['wall']:.2f} |")
    for name, r in (("cold", cold), ("warm", warm)):
        passes = sum(r["seconds"].get(k, 0.0) for k in PASS_STAGES)
        print(f"- {name}: the passes (photon + grid + gather) {passes:.1f} s, "
              f"{100 * passes / r['wall']:.0f} % of the process's wall; all else "
              f"{100 * (1 - passes / r['wall']):.0f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
