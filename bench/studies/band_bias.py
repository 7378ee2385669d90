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
    python bench/studies/band_bias.py --seeds 6 --group 530-575 --ref-paths 200000

``--group LO-HI[:PATHS]`` (repeatable) decides one band group: the path tracer, one band per path, then traces only
that group's bands (its spectrum from LO to HI nm), so each band gets NB/nb times the paths at the
same time; its light spectrum, which sums to 1 over the bands traced, is scaled back to the whole
spectrum's.  The renders stay the default's, over the whole spectrum (the radius is calibrated on
photons of every band).

Writes out/bench/band_bias.{json,md} (band_bias_LO-HI.* with ``--group``).
"""
from __future__ import annotations

import argparse
import dataclasses
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
from clppm.scene.bands import Bands                                  # noqa: E402
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


def group_config(cfg: dict, group: str | None) -> dict:
    """``cfg`` with its spectrum cut to the band group ``LO-HI`` (nm), or ``cfg`` itself."""
    if group is None:
        return cfg
    lo, hi = (float(v) for v in group.split("-"))
    cfg = C.override(cfg, "spectrum", "start_nm", lo)
    return C.override(cfg, "spectrum", "stop_nm", hi)


def group_reference(ref, cfg: dict, cfg_group: dict):
    """``ref`` (traced over ``cfg_group``'s bands) in the units of the whole spectrum: each band's
    radiance scales with the light's relative power there, which sums to 1 over the bands traced."""
    whole, part = Bands.from_config(cfg), Bands.from_config(cfg_group)
    idx = np.searchsorted(whole.wl, part.wl)
    if not np.allclose(whole.wl[idx], part.wl):
        raise SystemExit(f"--group: bands {part.wl[0]:g}-{part.wl[-1]:g} nm are not on the spectrum's grid")
    k = (whole.spectrum[idx] / part.spectrum).astype(np.float32)
    return dataclasses.replace(ref, spectral=ref.spectral * k, halves_spectral=ref.halves_spectral * k), idx


def parse_group(text: str, paths: int) -> tuple[str, int]:
    """``LO-HI`` or ``LO-HI:PATHS`` -> (``LO-HI``, paths per square and half)."""
    g, _, p = text.partition(":")
    lo, _, hi = g.partition("-")
    try:
        lo_, hi_, n = float(lo), float(hi), int(p) if p else paths
    except ValueError:
        raise SystemExit(f"--group {text!r}: expected LO-HI or LO-HI:PATHS (nm, paths)") from None
    if not lo_ < hi_ or n < 1:
        raise SystemExit(f"--group {text!r}: expected LO < HI and PATHS >= 1")
    return g, n


def references(cfg: dict, a, res: tuple, dev) -> list:
    """(group or None, reference in the whole spectrum's units, band indices) per reference."""
    groups = [parse_group(g, a.ref_paths) for g in a.group] or [(None, a.ref_paths)]
    out = []
    for g, paths in groups:
        spec = RefSpec(integrator="pt", resolution=res, block=10, paths=paths)
        cfg_ref = group_config(cfg, g)
        ref = get_reference(cfg_ref, spec, a.cache, dev=dev, progress=True)
        if ref.halves_spectral is None:          # cached before the halves' spectra were kept
            ref = get_reference(cfg_ref, spec, a.cache, dev=dev, progress=True, force=True)
        out.append((g, *(group_reference(ref, cfg, cfg_ref) if g else (ref, slice(None)))))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--resolution", default="80x60")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--passes", type=int, help="default: the config's")
    ap.add_argument("--ref-paths", type=int, default=400_000, help="reference paths per 10x10 square and half")
    ap.add_argument("--group", action="append", default=[],
                    help="LO-HI[:PATHS] nm: decide this band group, its reference tracing its bands only "
                         "(PATHS per square and half; default --ref-paths); repeatable")
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
    refs = references(cfg, a, res, dev)
    spectra, secs = [], []
    with volume.memoised():
        for seed in range(1, a.seeds + 1):
            r = render(cfg, passes=passes, resolution=res, dev=dev, seed=seed)
            spectra.append(block_mean(r.spectral, refs[0][1].block))
            secs.append(render_seconds(r.report))
            print(f"  seed {seed}: {secs[-1]:.0f} s", flush=True)
    os.makedirs(a.out, exist_ok=True)
    for g, ref, idx in refs:
        conf = band_group_confidence([s[..., idx] for s in spectra], ref, GROUP_BOUND)
        md = markdown(res, passes, conf, ref, float(np.median(secs)), dev.name)
        if g:
            md = f"Reference tracing {g} nm only.  " + md
        print(md)
        name = f"band_bias_{g}" if g else "band_bias"
        with open(os.path.join(a.out, name + ".json"), "w") as f:
            json.dump({"config": a.config, "resolution": list(res), "passes": passes, "device": dev.name,
                       "reference": {"key": ref.key, "paths": ref.spec.paths, "error": ref.error,
                                     "seconds": ref.info.get("seconds")},
                       "group": g, "seconds": secs, **conf}, f, indent=1, default=str)
        with open(os.path.join(a.out, name + ".md"), "w") as f:
            f.write(md + "\n")
        print(f"wrote {a.out}/{name}.md, {name}.json ({time.strftime('%H:%M:%S')})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
