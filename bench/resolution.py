"""Resolution scaling: pixels, sample points, tiles, peak resident memory and seconds per pass
of the default mode (render.radius = "global") at several resolutions.

Each render runs in a child process of its own (so its peak RSS, ``resource.getrusage``'s
``ru_maxrss``, is that render's alone), from the checkout ``--root`` (default: this one; give
another checkout to measure it the same way, e.g. the code before tiles).  Seconds per pass:
the photon, grid and gather stages' seconds (and the tiles' eye passes, when the checkout
tiles) over the passes; per pixel: that over the pixels.

    python bench/resolution.py [CONFIG] [--sizes 320x240,640x480,1920x1080] [--passes 2]
                               [--photons 100000] [--root DIR] [--tile-points N] [--outputs DIR]

``--outputs``: each render also writes its EXR, PNG, report and checkpoint (their size is
printed), so the peak includes the film's and the files' memory.

Prints a markdown table; never asserts on time.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHILD = r"""
import json, resource, sys, time
from clppm import config as C
try:
    from clppm.run.entry import render            # this checkout
except ImportError:
    from clppm.run.progressive import render      # an older one
a = json.loads(sys.argv[1])
cfg = C.load(a["config"])
for k, v in (("radius", "global"), ("passes", a["passes"]), ("photons", a["photons"])):
    cfg = C.override(cfg, "render", k, v)
if not a.get("out"):
    cfg = C.override(cfg, "render", "checkpoint_every", 0)
if a.get("tile_points") is not None:
    cfg = C.override(cfg, "render", "tile_points", a["tile_points"])
cfg = C.override(cfg, "camera", "resolution", a["size"])
t0 = time.perf_counter()
rep = render(cfg, **({"out": a["out"]} if a.get("out") else {})).report
s = rep["seconds"]
print(json.dumps({"points": rep["sample_points"], "tiles": rep.get("tiles", 1),
                  "pass_s": sum(s.get(k, 0.0) for k in ("photon", "grid", "gather", "tiles")),
                  "total_s": time.perf_counter() - t0,
                  "rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""


def run_one(root: str, config: str, size, passes: int, photons: int, tile_points, out=None) -> dict:
    arg = json.dumps({"config": config, "size": list(size), "passes": passes, "photons": photons,
                      "tile_points": tile_points, "out": out})
    env = dict(os.environ, PYTHONPATH=root)
    out = subprocess.run([sys.executable, "-c", CHILD, arg], cwd=root, env=env, capture_output=True,
                         text=True, check=False)
    if out.returncode:
        return {"error": (out.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--sizes", default="320x240,640x480,1920x1080")
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--photons", type=int, default=100_000)
    ap.add_argument("--root", default=ROOT, help="the checkout whose clppm renders")
    ap.add_argument("--tile-points", type=int, default=None, help="render.tile_points (default: the config's)")
    ap.add_argument("--outputs", metavar="DIR", help="write each render's files (EXR, PNG, report, "
                    "checkpoint) under DIR, as `clppm render -o DIR/WxH.exr` does (default: none)")
    a = ap.parse_args(argv)
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in a.sizes.split(",")]
    print(f"bench/resolution.py: {os.path.basename(a.config)}, {a.passes} passes, {a.photons:,} stored "
          f"photons/pass, clppm from {a.root}", flush=True)
    print("| pixels | resolution | sample points | tiles | peak RSS (GB) | s per pass | "
          "us per pixel per pass | total s |" + (" checkpoint MB |" if a.outputs else ""))
    print("|---:|---|---:|---:|---:|---:|---:|---:|" + ("---:|" if a.outputs else ""))
    for w, h in sizes:
        out = os.path.join(os.path.abspath(a.outputs), f"{w}x{h}.exr") if a.outputs else None
        r = run_one(os.path.abspath(a.root), os.path.abspath(a.config), (w, h), a.passes, a.photons,
                    a.tile_points, out)
        if "error" in r:
            print(f"| {w * h:,} | {w}x{h} | failed: {r['error']} |||||", flush=True)
            continue
        sp = r["pass_s"] / a.passes
        print(f"| {w * h:,} | {w}x{h} | {r['points']:,} | {r['tiles']} | {r['rss_bytes'] / 1e9:.2f} | "
              f"{sp:.2f} | {1e6 * sp / (w * h):.2f} | {r['total_s']:.1f} |"
              + (f" {os.path.getsize(out[:-4] + '.ckpt.npz') / 1e6:.0f} |" if out else ""), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
