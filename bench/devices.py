"""Run bench/render.py on every OpenCL device found; one JSON per device, one markdown table.

Each device runs in its own process (its own peak-memory figure, no shared program caches).

    python bench/devices.py [--quick] [--out out/bench] [--only SUBSTRING] [-- extra render.py args]

Writes ``OUT/render-<device>.json`` (by bench/render.py) and ``OUT/render.md`` (all devices),
and prints the table.  ``--list`` only lists the devices.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import render as bench_render  # noqa: E402  (bench/render.py)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=os.path.join("out", "bench"))
    ap.add_argument("--only", help="only devices whose name contains this")
    ap.add_argument("--list", action="store_true")
    a = ap.parse_args(argv)

    from clppm.device import describe, list_devices
    devs = list_devices()
    if not devs:
        print("no OpenCL device found", file=sys.stderr)
        return 3
    for ip, idev, _, d in devs:
        info = describe(d)
        print(f"{ip}:{idev}  {info['name']}  [{info['platform']}; {info['type']}; {info['compute_units']} CUs]")
    if a.list:
        return 0
    os.makedirs(a.out, exist_ok=True)
    paths, rc = [], 0
    for ip, idev, _, d in devs:
        name = d.name.strip()
        if a.only and a.only.lower() not in name.lower():
            continue
        print(f"\n=== {ip}:{idev} {name}", flush=True)
        cmd = [sys.executable, os.path.join(HERE, "render.py"), "--device", f"{ip}:{idev}", "--out", a.out,
               *(["--quick"] if a.quick else []), *extra]
        r = subprocess.run(cmd)
        if r.returncode != 0:
            print(f"bench/render.py failed on {name} (exit {r.returncode})", file=sys.stderr)
            rc = rc or r.returncode
            continue
        p = os.path.join(a.out, f"render-{bench_render.slug(name)}{'-quick' if a.quick else ''}.json")
        if os.path.isfile(p):
            paths.append(p)
    docs = []
    for p in paths:
        with open(p) as f:
            docs.append(json.load(f))
    if docs:
        md = ("# clppm renderer throughput\n\n"
              "Per device and method: photons/s and stored photons/s over the photon-pass seconds, gather "
              "pairs/s over the gather seconds, seconds per pass per stage, device buffers, and the paper's 200 "
              "passes extrapolated (bench/render.py): '200 passes s' with the gather pairs-per-pass decay measured "
              "in the passes sweep, 'model' with the mean-field radius recursion (a lower bound), 'linear' as 200 "
              "times the mean measured pass (an upper bound); speedup = paper seconds / '200 passes s'.  Timings on "
              "a shared machine vary with its load; quick runs are at 160x120 with 202,500 photons per pass, so "
              "their speedups are not comparable with the paper's 320x240 times.\n\n" + bench_render.markdown(docs) + "\n")
        path = os.path.join(a.out, "render-quick.md" if a.quick else "render.md")
        with open(path, "w") as f:
            f.write(md)
        print("\n" + md)
        print(f"wrote {path}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
