"""Whether the default keeps its bias per 50-nm band group within 1 % of the path tracer, at a
stated confidence.

The default scene (configs/forearm.toml: method e, its passes, the smooth relief) is rendered
with seeds 1..N; each image's mean skin radiance per band group is compared with the path
tracer's (clppm.analysis.reference, its two halves), and
:func:`clppm.analysis.metrics.band_group_confidence` gives per group the error of the seeds'
mean, its 95 % interval (the seeds' scatter and the reference's own noise, Student's t) and a
verdict: within 1 %, beyond 1 %, or open.  One image's error per group is printed beside it: a
single render reads the bias plus its own noise.  Specular highlights off, as in
bench/studies/bias.py.

    python bench/studies/band_bias.py --resolution 80x60 --seeds 8

Writes out/bench/band_bias.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from clppm import config as C                                        # noqa: E402
from clppm.analysis.compare import render_seconds                    # noqa: E402
from clppm.analysis.metrics import GROUP_BOUND, band_group_confidence, block_mean   # noqa: E402
from clppm.analysis.reference import RefSpec, get_reference          # noqa: E402
from clppm.compute.device import open_device                         # noqa: E402
from clppm.run.entry import render                                   # noqa: E402
from clppm.scene import volume                                       # noqa: E402


def markdown(res: tuple, passes: int, conf: dict, ref, seconds: float, device: str) -> str:
    lv = 100 * conf["level"]
    lines = [f"{res[0]}x{res[1]}, default (method e, {passes} passes), {conf['seeds']} seeds, against the "
             f"path tracer ({ref.spec.paths:,} paths per 10x10-pixel square and half, {conf['squares']} skin "
             f"squares); {device}, {seconds:.0f} s per render (median).  The error of the seeds' mean image "
             f"per 50-nm band group, its {lv:.0f} % interval (Student's t over the seeds' scatter and the "
             f"reference's own noise) and whether the whole interval lies within ±{100 * conf['bound']:.0f} %.", "",
             f"| band group (nm) | error, mean of seeds | {lv:.0f} % interval | SE: seeds, reference | "
             f"one image: range | verdict |", "|---|---|---|---|---|---|"]
    for g, v in conf["groups"].items():
        e, h = 100 * v["error"], 100 * v["half_width"]
        one = 100 * np.array(v["one_image"])
        lines.append(f"| {g} | {e:+.2f} % | {e - h:+.2f} % to {e + h:+.2f} % | "
                     f"{100 * v['se_seeds']:.2f} %, {100 * v['se_reference']:.2f} % | "
                     f"{one.min():+.2f} % to {one.max():+.2f} % | {v['verdict']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--resolution", default="80x60")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--passes", type=int, help="default: the config's")
    ap.add_argument("--ref-paths", type=int, default=400_000, help="reference paths per 10x10 square and half")
    ap.add_argument("--cache", default=os.path.join(ROOT, "out", "cache"))
    ap.add_argument("-o", "--out", default=os.path.join(ROOT, "out", "bench"))
    a = ap.parse_args(argv)
    if a.seeds < 2:
        ap.error(f"--seeds {a.seeds}: a confidence needs 2 seeds or more")
    dev = open_device(None)
    cfg = C.load(a.config)
    cfg = C.override(cfg, "render", "specular", False)
    cfg = C.override(cfg, "render", "checkpoint_every", 0)
    res = tuple(int(v) for v in a.resolution.split("x"))
    passes = a.passes or int(cfg["render"]["passes"])
    spec = RefSpec(integrator="pt", resolution=res, block=10, paths=a.ref_paths)
    ref = get_reference(cfg, spec, a.cache, dev=dev, progress=True)
    if ref.halves_spectral is None:          # cached before the halves' spectra were kept
        ref = get_reference(cfg, spec, a.cache, dev=dev, progress=True, force=True)
    spectra, secs = [], []
    with volume.memoised():
        for seed in range(1, a.seeds + 1):
            r = render(cfg, passes=passes, resolution=res, dev=dev, seed=seed)
            spectra.append(block_mean(r.spectral, ref.block))
            secs.append(render_seconds(r.report))
            print(f"  seed {seed}: {secs[-1]:.0f} s", flush=True)
    conf = band_group_confidence(spectra, ref, GROUP_BOUND)
    md = markdown(res, passes, conf, ref, float(np.median(secs)), dev.name)
    print(md)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "band_bias.json"), "w") as f:
        json.dump({"config": a.config, "resolution": list(res), "passes": passes, "device": dev.name,
                   "reference": {"key": ref.key, "paths": ref.spec.paths, "error": ref.error},
                   "seconds": secs, **conf}, f, indent=1, default=str)
    with open(os.path.join(a.out, "band_bias.md"), "w") as f:
        f.write(md + "\n")
    print(f"wrote {a.out}/band_bias.md, band_bias.json ({time.strftime('%H:%M:%S')})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
