"""``clppm compare``: its options and the run it plans (the experiment itself:
clppm.analysis.compare)."""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass

from .. import config as C
from .. import image
from ..scene import volume
from ..analysis.compare import (BLOCK, METHODS, QUICK, STANDARD, colour_shift_experiment, plot,
                                reference_spec, results_markdown, run_method, run_pt,
                                shift_markdown, summarise, table1_markdown)
from ..analysis.reference import RefSpec, get_reference
from . import options


def _floats(s: str):
    return tuple(float(x) for x in s.split(",") if x.strip())


def _ints(s: str):
    return tuple(int(float(x)) for x in s.split(",") if x.strip())


def resolution_arg(s: str):
    return options.resolution(s, f"{s!r}: expected WxH, e.g. 160x120")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("compare", help="speed against accuracy of methods a-f, both modes and the "
                              "path tracer, against a cached reference", description=__doc__.split("\n\n")[0])
    p.add_argument("config")
    p.add_argument("--methods", default=METHODS, help="comma list or letters, e.g. a,c,f (default: all)")
    p.add_argument("--paper-methods", help="methods also run in the paper's mode (quick: e; standard: all)")
    p.add_argument("--no-pt", action="store_true", help="leave out the path tracer's curve")
    p.add_argument("--budget", type=float, help="render seconds per run (quick 20, standard 90: about "
                   "20 minutes on 2 CPU cores once the reference is cached)")
    p.add_argument("--quick", action="store_true", help="20 s per run, the paper's mode for e only, a smaller "
                   "reference of its own (computed once and cached): a first look")
    p.add_argument("--resolution", type=resolution_arg, help="default 80x60 (multiples of 10: the comparison is per "
                   "10x10-pixel square)")
    p.add_argument("--photons", type=int, help="stored photons per pass (default: the config's)")
    p.add_argument("--max-passes", type=int, help="stop a run at this many passes")
    p.add_argument("--seed", type=int, help="random seed of the runs (default: the config's render.seed)")
    p.add_argument("--ref-paths", type=int, help="path-tracer reference: paths per 10x10 square and half")
    p.add_argument("--ref-passes", type=int, help="PPM reference (scenes the path tracer cannot render): passes")
    p.add_argument("--force-ref", action="store_true", help="recompute the reference even if cached")
    p.add_argument("--cache", default="out/cache", help="reference cache folder (default out/cache)")
    p.add_argument("--no-shift", action="store_true", help="skip the colour-shift experiment")
    p.add_argument("--shift-spacings", type=_floats, help="colour-shift experiment: equal spacings in um, "
                   "comma list (default: the mode's)")
    p.add_argument("--shift-photons", type=_ints, help="colour-shift experiment: stored photons per pass, "
                   "comma list (default: the mode's)")
    p.add_argument("--shift-passes", type=int, help="colour-shift experiment: passes per run (default: the mode's)")
    p.add_argument("-o", "--out", help="output folder (default out/compare or out/compare-quick)")
    options.add_device(p)
    p.set_defaults(func=cmd_compare)


def _letters(s: str, flag: str) -> list[str]:
    ms = [m for m in s.replace(",", "") if m.strip()]
    if not ms or any(m not in METHODS for m in ms):
        raise C.ConfigError("command line", flag, s, "letters from a-f")
    return ms


@dataclass
class _Plan:
    """What ``clppm compare`` runs, from its command line (checked)."""

    cfg: dict
    mode: dict                 # QUICK or STANDARD
    methods: list
    paper_methods: list
    resolution: tuple
    budget: float
    max_passes: int
    out: str


def _plan(a) -> _Plan:
    from ..output import paths
    d = QUICK if a.quick else STANDARD
    # the subsurface image is compared: the GGX highlight is the same function in every run
    cfg = C.override(C.load(C.find(a.config)), "render", "specular", False)
    methods = _letters(a.methods, "--methods")
    paper_methods = _letters(a.paper_methods or d["paper_methods"], "--paper-methods")
    res_ = tuple(a.resolution or d["resolution"])
    if res_[0] % BLOCK or res_[1] % BLOCK:
        raise C.ConfigError("command line", "--resolution", f"{res_[0]}x{res_[1]}", f"must be multiples of {BLOCK}")
    budget = a.budget if a.budget is not None else d["budget"]
    max_passes = a.max_passes or d["max_passes"]
    out = a.out or ("out/compare-quick" if a.quick else "out/compare")
    paths.check_folder(out, "-o/--out")
    paths.check_folder(a.cache, "--cache")
    return _Plan(cfg, d, methods, paper_methods, res_, budget, max_passes, out)


def cmd_compare(a) -> int:
    from ..compute.device import open_device
    pl = _plan(a)
    os.makedirs(os.path.join(pl.out, "images"), exist_ok=True)
    dev = open_device(a.device)
    spec = reference_spec(pl.cfg, pl.resolution, pl.mode, a.ref_paths, a.ref_passes)
    with_pt = spec.integrator == "pt" and not a.no_pt
    res_ = pl.resolution
    print(f"clppm compare {os.path.basename(a.config)} on {dev.name}: default {''.join(pl.methods)}, paper "
          f"{''.join(pl.paper_methods)}{', path tracer' if with_pt else ''}; {res_[0]}x{res_[1]}, budget "
          f"{pl.budget:g} render s per run")
    t_all = time.perf_counter()
    with volume.memoised():
        ref = get_reference(pl.cfg, spec, a.cache, dev=dev, force=a.force_ref, progress=True)
        image.write_png(os.path.join(pl.out, "images", "reference.png"), ref.rgb, ref.exposure)
        runs = _run_all(pl, ref, with_pt, a.photons, a.seed, dev)
        shift = None if a.no_shift else _shift(pl, a, ref, dev)
    summ = summarise(runs)
    md_text = compare_markdown(os.path.basename(a.config), dev.name, pl, spec, ref, runs, summ, shift)
    plot(runs, ref, os.path.join(pl.out, "compare.png"),
         title=f"{os.path.basename(a.config)}: {res_[0]}x{res_[1]}, {dev.name}")
    doc = {"config": os.path.abspath(a.config), "device": dev.info(), "resolution": list(res_),
           "budget_s": pl.budget, "max_passes": pl.max_passes,
           "reference": {"key": ref.key, "spec": ref.spec.as_dict(), "error": ref.error, "info": ref.info},
           "runs": runs, "summary": summ, "colour_shift": shift,
           "wall_seconds": time.perf_counter() - t_all}
    _write_text(os.path.join(pl.out, "compare.json"), json.dumps(doc, indent=1, default=str))
    _write_text(os.path.join(pl.out, "compare.md"), md_text)
    print()
    print(results_markdown(runs, summ, ref))
    if shift is not None:
        print()
        print(shift_markdown(shift))
    print(f"\nwrote {pl.out}/compare.png, compare.md, compare.json, images/ ({time.perf_counter() - t_all:.0f} s)")
    return 0


def _run_all(pl: _Plan, ref, with_pt: bool, photons, seed, dev) -> dict:
    """Every method in each mode, and the path tracer; each final image written."""
    def keep(r: dict, name: str) -> dict:
        image.write_png(os.path.join(pl.out, "images", f"{name}.png"), r.pop("_rgb"), r.pop("_exposure"))
        return r
    runs = {}
    print("runs:")
    for mode, ms in (("default", pl.methods), ("paper", pl.paper_methods)):
        for m in ms:
            r = run_method(pl.cfg, m, ref, budget=pl.budget, max_passes=pl.max_passes, mode=mode,
                           photons=photons, seed=seed, dev=dev)
            runs[f"{m} {mode}"] = keep(r, f"{mode}-{m}")
    if with_pt:
        runs["path tracer"] = keep(run_pt(pl.cfg, ref, budget=pl.budget, seed=seed, dev=dev), "path-tracer")
    return runs


def _shift(pl: _Plan, a, ref, dev) -> dict:
    print("colour-shift experiment (paper mode, equal spacing x stored photons per pass):")
    d = pl.mode
    return colour_shift_experiment(
        pl.cfg, spacings=a.shift_spacings or d["shift_spacings"], photons=a.shift_photons or d["shift_photons"],
        passes=a.shift_passes or d["shift_passes"], resolution=pl.resolution, seed=a.seed, ref=ref, dev=dev,
        log=print)


def _write_text(path: str, text: str) -> None:
    with open(path, "w") as f:
        f.write(text)

def compare_markdown(config_name: str, device_name: str, pl: _Plan, spec: RefSpec, ref, runs: dict,
                     summ: dict, shift: dict | None) -> str:
    """compare.md: the set-up, the reference, the speed and accuracy table, Table 1 and the
    colour-shift experiment."""
    res_ = pl.resolution
    ppm_runs = {k: r for k, r in runs.items() if r["mode"] != "pt"}
    ref_what = (f"the path tracer, {spec.paths:,} paths per {BLOCK}x{BLOCK}-pixel square in each of two halves"
                if spec.integrator == "pt" else
                f"PPM (default mode, method {spec.method}, {spec.passes} passes of {spec.photons:,} stored photons, "
                "two halves; its density-estimation bias is not in its noise estimate)")
    md = [f"# clppm compare: {config_name}", "",
          f"Device {device_name}; {res_[0]}x{res_[1]} pixels, budget {pl.budget:g} render seconds per run (eye + "
          "calibration + photon + grid + gather, or the path tracer's trace time; volume build and snapshots "
          "excluded).  Errors are over the skin's 10x10-pixel squares (bias, and the noise left at that scale).  "
          "Paper mode here is the paper's estimator (config.PAPER_MODE) on the scene's own surface, the "
          "reference's, so that the rows differ by estimator only (`clppm render --paper` also walks the "
          "paper's voxels).", "",
          f"Reference `{ref.key}`: {ref_what}.", "",
          "## Speed and accuracy (last snapshot; equal-time columns interpolated log-log)", "",
          results_markdown(runs, summ, ref), "", "![error against time](compare.png)", "",
          "## Table 1: mean sample points per eye ray per layer", "",
          table1_markdown({r["method"]: r for r in ppm_runs.values() if r["mode"] == "default"})]
    if shift is not None:
        md += ["", "## Colour shift against spacing and photons (the paper's explanation of method a)", "",
               shift_markdown(shift)]
    return "\n".join(md) + "\n"
