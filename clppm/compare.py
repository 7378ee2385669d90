"""``clppm compare``: speed against accuracy of the sampling schemes a-f.

For one scene, every method is rendered progressively until its time budget is spent; at a
geometric schedule of passes (and at the last one) the image is compared with a converged
reference (:mod:`clppm.reference`, computed once and cached) over the skin pixels:

* RMSE of linear XYZ (white diffuser at the image centre = 1),
* mean CIEDE2000,
* mean chromaticity shift u'v', signed (test - reference), per pixel and of the mean skin
  colour, and mean signed Δb* (b* < 0: bluer) -- so a bluish cast of method a shows as a
  negative Δv' / Δb*,
* mean FLIP (LDR, of the displayed images) when ``flip-evaluator`` is installed.

Time is the render's own stage time (eye + photon + grid + gather seconds from its report):
the host-side volume build (shared by all methods, memoised here) and the snapshot overhead
(reading the image back and converting it) are left out.

Outputs (``-o DIR``): ``compare.png`` (error against seconds, log-log, one curve per method),
``compare.md`` and ``compare.json`` (the same numbers; Table 1 of sample points per layer
beside the paper's; the colour-shift experiment), and the final image of each method.

The colour-shift experiment (:func:`colour_shift_experiment`) tests the paper's explanation
of method a's bluish cast ("with closely spaced sample points the same stored photon is
reused by many sample points, and short-wavelength photons, stored more often near the
surface, weigh in more"): it renders equal spacings (4, 7, 14, 28 um ...) at several stored
photon counts per pass with the same seed (common random numbers: the same photons for every
spacing) and records the mean skin colour's shift against the reference next to the reuse
factor (gather pairs / stored photons: how many sample points count a stored photon on
average).  If reuse caused a colour bias, the shift would grow with the reuse factor:
with spacing at fixed photons, and fall with more photons per pass (smaller radius) at fixed
spacing.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

from . import image
from .reference import RefSpec, cached_volumes, error_metrics, flip_available, get_reference, skin_mask

METHODS = "abcdef"
STAGES = ("eye", "photon", "grid", "gather")

QUICK = {
    "resolution": (80, 60),
    "photons": 50_625,            # the paper's 810,000 per 320x240, per pixel
    "budget": 20.0,
    "max_passes": 200,
    "ref": {"photons": 405_000, "passes": 40, "initial_photons": 200},
    "shift_spacings": (4.0, 7.0, 14.0, 28.0),
    "shift_photons": (12_656, 50_625, 202_500),
    "shift_passes": 2,
}
FULL = {
    "resolution": (160, 120),
    "photons": 202_500,
    "budget": 600.0,
    "max_passes": 200,
    "ref": {"photons": 1_620_000, "passes": 120, "initial_photons": 200},
    "shift_spacings": (4.0, 7.0, 14.0, 28.0),
    "shift_photons": (50_625, 202_500, 810_000),
    "shift_passes": 8,
}


class _Stop(Exception):
    pass


def render_seconds(report: dict) -> float:
    s = report["seconds"]
    return float(sum(s.get(k, 0.0) for k in STAGES))


def median_radius(last: dict, report: dict):
    """Median progressive radius (um) over the sample points, from the device array an
    ``on_pass`` hook kept in ``last['pt_R']`` (None if there is none)."""
    a, n = last.get("pt_R"), int(report.get("sample_points", 0))
    if a is None or n == 0:
        return None
    return float(np.median(a.get()[:n]))


def schedule(max_passes: int, ratio: float = 1.25) -> set:
    out, x = set(), 1.0
    while x <= max_passes:
        out.add(int(round(x)))
        x = max(x * ratio, x + 1)
    out.add(max_passes)
    return out


# ----------------------------------------------------------------------------- one method
def run_method(cfg: dict, method: str, ref, *, budget: float, max_passes: int, photons: int,
               seed: int | None = None, spacing: float | None = None, dev=None, flip: bool = False,
               log=print) -> dict:
    """Render ``method`` until ``budget`` render seconds; error against ``ref`` at snapshots."""
    from .progressive import render
    w, h = ref.xyz.shape[1], ref.xyz.shape[0]
    sched = schedule(max_passes)
    snaps: list = []
    last = {}

    def on_pass(p, st):
        last["pt_R"] = st["pt_R"]

    def on_snapshot(p, wall, res):
        t = render_seconds(res.report)
        due = p in sched or t >= budget or p >= max_passes
        if due:
            m = error_metrics(res.xyz, ref.xyz, ref.mask, ref.exposure, res.rgb, ref.rgb, flip=flip)
            r = res.report
            # the reference's own noise adds in quadrature to the RMSE; take it out
            m["rmse_xyz_net"] = math.sqrt(max(m["rmse_xyz"] ** 2 - ref.error["rmse_xyz"] ** 2, 0.0))
            snaps.append({"pass": p, "seconds": t, "wall": wall, "R_median_um": median_radius(last, r),
                          "stage_seconds": {k: r["seconds"].get(k, 0.0) for k in STAGES},
                          "photons_emitted": r["photons_emitted"], "photons_stored": r["photons_stored"],
                          "gather_pairs": r["gather_pairs"], **m})
        last["res"] = res
        if t >= budget:
            raise _Stop

    t0 = time.perf_counter()
    try:
        render(cfg, method=method, spacing=spacing, passes=max_passes, photons=photons, resolution=(w, h),
               seed=seed, dev=dev, snapshot_every=1, on_snapshot=on_snapshot, on_pass=on_pass)
    except _Stop:
        pass
    res = last["res"]
    r = res.report
    f = snaps[-1]
    log(f"  {method}: {f['pass']} passes, {f['seconds']:.1f} s render ({time.perf_counter() - t0:.0f} s wall), "
        f"RMSE {f['rmse_xyz']:.4f}, dE00 {f['de2000']:.2f}, du'v' mean colour ({f['du_mean']:+.4f}, "
        f"{f['dv_mean']:+.4f}), db* {f['db']:+.2f}, median R {f['R_median_um'] or 0:.0f} um" + (f", FLIP {f['flip']:.3f}" if "flip" in f else ""))
    return {
        "method": method, "scheme": r["scheme"], "snapshots": snaps,
        "passes": f["pass"], "seconds": f["seconds"],
        "sample_points": r["sample_points"], "eye_rays_hit": r["eye_rays_hit"],
        "sample_points_per_ray_per_layer": r["sample_points_per_ray_per_layer"],
        "first_search_mean_photons": r.get("first_search_mean_photons"),
        "reuse": r["gather_pairs"] / max(r["photons_stored"], 1),
        "final": {k: v for k, v in f.items() if k not in ("stage_seconds",)},
        "_rgb": res.rgb, "_exposure": res.exposure,
    }


# ----------------------------------------------------------------------------- colour shift
def colour_shift_experiment(cfg: dict, spacings=(4.0, 7.0, 14.0, 28.0), photons=(12_656, 50_625),
                            passes: int = 4, resolution=None, seed: int | None = None, ref=None,
                            dev=None, log=None) -> dict:
    """Mean skin colour of equal-spacing renders against spacing and stored photons per pass.

    All renders use the same seed (the same photons for every spacing), ``passes`` passes.
    Against ``ref`` when given (same resolution), else against the finest spacing at the
    largest photon count.  Each row: spacing, photons per pass, sample points per eye ray,
    reuse factor (gather pairs / stored photons), u'v' and Lab of the mean skin colour, and
    the shift (du_mean, dv_mean, db, de2000 ...).  ``summary`` gives, per photon count, the
    shift of the finest spacing minus the coarsest, and the fitted slopes of Δv' and Δb*
    against log(reuse).
    """
    from . import config as C
    from .progressive import render
    log = log or (lambda *a, **k: None)
    cfg = C.paper_mode(cfg)               # reuse by overlapping spheres is the paper's estimator's
    if resolution is None:
        resolution = tuple(cfg["camera"]["resolution"]) if ref is None else (ref.xyz.shape[1], ref.xyz.shape[0])
    rows, imgs = [], {}
    with cached_volumes():
        mask = ref.mask if ref is not None else None
        for n in photons:
            for s in spacings:
                last = {}
                res = render(cfg, spacing=float(s), passes=int(passes), photons=int(n), resolution=resolution,
                             seed=seed, dev=dev, on_pass=lambda p, st, last=last: last.update(pt_R=st["pt_R"]))
                if mask is None:
                    from .progressive import apply_overrides
                    mask = skin_mask(apply_overrides(cfg, resolution=resolution, spacing=float(s)), dev)
                r = res.report
                xyz = res.xyz[mask] * res.exposure
                mean = xyz.mean(0)
                uv = image.xyz_to_uv_prime(mean)
                lab = image.xyz_to_lab(mean)
                row = {"spacing_um": float(s), "photons": int(n), "passes": int(passes),
                       "points_per_ray": r["sample_points"] / max(r["eye_rays_hit"], 1),
                       "reuse": r["gather_pairs"] / max(r["photons_stored"], 1),
                       "seconds": render_seconds(r), "R_median_um": median_radius(last, r),
                       "u": float(uv[0]), "v": float(uv[1]),
                       "L": float(lab[0]), "a": float(lab[1]), "b": float(lab[2])}
                imgs[(float(s), int(n))] = (res.xyz, res.exposure)
                rows.append(row)
                log(f"  spacing {s:g} um, {n} photons/pass: reuse {row['reuse']:.0f}, "
                    f"u'v' ({row['u']:.4f}, {row['v']:.4f}), b* {row['b']:.2f}")
    if ref is not None:
        base_xyz, base_exp, against = ref.xyz, ref.exposure, f"reference {ref.key}"
    else:
        k = (float(min(spacings)), int(max(photons)))
        base_xyz, base_exp = imgs[k]
        against = f"spacing {k[0]:g} um at {k[1]} photons/pass"
    for row in rows:
        xyz, e = imgs[(row["spacing_um"], row["photons"])]
        m = error_metrics(xyz * (e / base_exp), base_xyz, mask, base_exp)
        row.update({k: m[k] for k in ("du_mean", "dv_mean", "du", "dv", "db", "da", "dL", "dY",
                                      "de2000", "rmse_xyz")})
    summary = []
    for n in photons:
        rs = sorted((r for r in rows if r["photons"] == n), key=lambda r: r["spacing_um"])
        fine, coarse = rs[0], rs[-1]
        d = {"photons": int(n), "fine_um": fine["spacing_um"], "coarse_um": coarse["spacing_um"],
             "du_fine_minus_coarse": fine["du_mean"] - coarse["du_mean"],
             "dv_fine_minus_coarse": fine["dv_mean"] - coarse["dv_mean"],
             "db_fine_minus_coarse": fine["db"] - coarse["db"],
             "reuse_fine": fine["reuse"], "reuse_coarse": coarse["reuse"]}
        if len(rs) >= 2:
            x = np.log([max(r["reuse"], 1e-9) for r in rs])
            if np.ptp(x) > 0:
                d["slope_dv_per_log_reuse"] = float(np.polyfit(x, [r["dv_mean"] for r in rs], 1)[0])
                d["slope_db_per_log_reuse"] = float(np.polyfit(x, [r["b"] for r in rs], 1)[0])
        summary.append(d)
    return {"against": against, "passes": int(passes), "resolution": list(resolution), "rows": rows,
            "summary": summary}


def shift_markdown(exp: dict) -> str:
    lines = [f"Against {exp['against']}; {exp['passes']} passes, {exp['resolution'][0]}x{exp['resolution'][1]}, "
             "same seed for every spacing.  reuse = gather pairs / stored photons (sample points counting a "
             "stored photon, on average); R = median radius after the last pass.", "",
             "| spacing (um) | photons/pass | points/ray | reuse | R (um) | u' | v' | b* | Δu' | Δv' | Δb* | ΔE00 |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in exp["rows"]:
        lines.append(f"| {r['spacing_um']:g} | {r['photons']:,} | {r['points_per_ray']:.1f} | {r['reuse']:.0f} | "
                     f"{r['R_median_um'] or 0:.0f} | "
                     f"{r['u']:.4f} | {r['v']:.4f} | {r['b']:.2f} | {r['du_mean']:+.4f} | {r['dv_mean']:+.4f} | "
                     f"{r['db']:+.2f} | {r['de2000']:.2f} |")
    lines += ["", "| photons/pass | finest − coarsest Δu' | Δv' | Δb* | reuse finest / coarsest |",
              "|---:|---:|---:|---:|---:|"]
    for s in exp["summary"]:
        lines.append(f"| {s['photons']:,} | {s['du_fine_minus_coarse']:+.4f} | {s['dv_fine_minus_coarse']:+.4f} | "
                     f"{s['db_fine_minus_coarse']:+.2f} | {s['reuse_fine']:.0f} / {s['reuse_coarse']:.0f} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- summaries
def _interp_loglog(xs, ys, x):
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = (xs > 0) & (ys > 0)
    xs, ys = xs[ok], ys[ok]
    if len(xs) == 0 or x < xs[0] or x > xs[-1]:
        return None
    return float(np.exp(np.interp(np.log(x), np.log(xs), np.log(ys))))


def _time_to(xs, ys, target):
    """First time the (log-log interpolated) curve falls to ``target``."""
    for i in range(len(ys)):
        if ys[i] <= target:
            if i == 0:
                return float(xs[0])
            x0, x1, y0, y1 = xs[i - 1], xs[i], ys[i - 1], ys[i]
            if y0 <= 0 or y1 <= 0 or x0 <= 0:
                return float(x1)
            f = (math.log(target) - math.log(y0)) / (math.log(y1) - math.log(y0))
            return float(math.exp(math.log(x0) + f * (math.log(x1) - math.log(x0))))
    return None


def summarise(runs: dict) -> dict:
    t_eq = min(r["seconds"] for r in runs.values())
    e_eq = max(r["final"]["de2000"] for r in runs.values())
    out = {"equal_time_s": t_eq, "equal_de2000": e_eq, "methods": {}}
    for m, r in runs.items():
        xs = [s["seconds"] for s in r["snapshots"]]
        out["methods"][m] = {
            "rmse_at_equal_time": _interp_loglog(xs, [s["rmse_xyz"] for s in r["snapshots"]], t_eq),
            "de2000_at_equal_time": _interp_loglog(xs, [s["de2000"] for s in r["snapshots"]], t_eq),
            "seconds_to_equal_de2000": _time_to(xs, [s["de2000"] for s in r["snapshots"]], e_eq),
        }
    return out


def table1_markdown(runs: dict) -> str:
    from .skin import PAPER_TABLE1
    layers = list(PAPER_TABLE1["a"].keys())
    lines = ["| method | " + " | ".join(layers) + " |", "|---|" + "---:|" * len(layers)]
    for m, r in runs.items():
        ours = r["sample_points_per_ray_per_layer"]
        paper = PAPER_TABLE1.get(m, {})
        cells = []
        for L in layers:
            o = ours.get(L)
            p = paper.get(L)
            cells.append((f"{o:.2f}" if o is not None else "–") + (f" ({p:.2f})" if p is not None else ""))
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\nours (paper): mean sample points per eye ray that hits the skin."


def results_markdown(runs: dict, summ: dict, ref) -> str:
    from .skin import PAPER_RENDER_TIME_S
    has_flip = any("flip" in r["final"] for r in runs.values())
    head = ("| method | scheme | passes | seconds | points | R (um) | RMSE XYZ | net of ref noise | ΔE00 | Δu' | Δv' | Δb* |"
            + (" FLIP |" if has_flip else "")
            + f" RMSE @ {summ['equal_time_s']:.0f} s | ΔE00 @ {summ['equal_time_s']:.0f} s |"
            + f" s to ΔE00 ≤ {summ['equal_de2000']:.2f} | paper s (200 passes) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for m, r in runs.items():
        f = r["final"]
        s = summ["methods"][m]

        def g(x, fmt):
            return "–" if x is None else format(x, fmt)
        lines.append(
            f"| {m} | {r['scheme']} | {r['passes']} | {r['seconds']:.1f} | {r['sample_points']:,} | "
            f"{f.get('R_median_um') or 0:.0f} | "
            f"{f['rmse_xyz']:.4f} | {f['rmse_xyz_net']:.4f} | {f['de2000']:.2f} | {f['du_mean']:+.4f} | {f['dv_mean']:+.4f} | {f['db']:+.2f} |"
            + (f" {f['flip']:.3f} |" if has_flip and "flip" in f else (" – |" if has_flip else ""))
            + f" {g(s['rmse_at_equal_time'], '.4f')} | {g(s['de2000_at_equal_time'], '.2f')} |"
            f" {g(s['seconds_to_equal_de2000'], '.1f')} | {PAPER_RENDER_TIME_S.get(m, float('nan')):.0f} |")
    e = ref.error
    lines += ["", f"Reference noise (from its halves): RMSE XYZ {e['rmse_xyz']:.4f}, ΔE00 {e['de2000']:.3f}, "
              f"Δu'v' of the mean colour ({e['du_mean']:+.1e}, {e['dv_mean']:+.1e}), Δb* {e['db']:+.3f}."
              " Δu', Δv' are of the mean skin colour, Δb* the mean per pixel (negative: bluer)."]
    return "\n".join(lines)


def plot(runs: dict, ref, path: str, title: str = "") -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    fmt = FuncFormatter(lambda x, _: f"{x:g}")
    has_flip = any("flip" in s for r in runs.values() for s in r["snapshots"])
    panels = [("rmse_xyz", "RMSE of linear XYZ (white = 1)", True),
              ("de2000", "mean CIEDE2000", True),
              ("flip" if has_flip else "rel_rmse", "mean FLIP (LDR)" if has_flip else "RMSE / mean skin Y", True),
              ("du_mean", "Δu' of the mean skin colour (test − ref)", False),
              ("dv_mean", "Δv' of the mean skin colour (test − ref)", False),
              ("db", "mean Δb* (negative: bluer)", False)]
    fig, axs = plt.subplots(2, 3, figsize=(15, 8.5))
    colors = dict(zip(METHODS, ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]))
    for ax, (k, lab, log) in zip(axs.ravel(), panels):
        for m, r in runs.items():
            pts = [(s["seconds"], s[k]) for s in r["snapshots"] if k in s]
            if not pts:
                continue
            xs, ys = zip(*pts)
            ax.plot(xs, ys, "o-", ms=3, color=colors.get(m), label=f"{m}) {r['scheme'].split(') ', 1)[-1]}")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(fmt)
        ax.xaxis.set_minor_formatter(NullFormatter())
        if log:
            ax.set_yscale("log")
            ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
            ax.yaxis.set_major_formatter(fmt)
            ax.yaxis.set_minor_formatter(NullFormatter())
            if ref.error.get(k):
                ax.axhline(ref.error[k], ls="--", color="gray", lw=1, label="reference noise")
        else:
            ax.axhline(0.0, color="gray", lw=0.8)
        ax.set_xlabel("render seconds")
        ax.set_ylabel(lab)
        ax.grid(True, which="both", alpha=0.3)
    axs[0, 0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------- command
def _floats(s: str):
    return tuple(float(x) for x in s.split(",") if x.strip())


def _ints(s: str):
    return tuple(int(float(x)) for x in s.split(",") if x.strip())


def _res(s: str):
    try:
        w, h = s.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r}: expected WxH, e.g. 160x120") from None


def add_parser(subparsers, add_device) -> None:
    p = subparsers.add_parser("compare", help="speed against accuracy of methods a-f vs a cached reference",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("config")
    p.add_argument("--methods", default=METHODS, help="comma list or letters, e.g. a,c,f (default: all)")
    p.add_argument("--budget", type=float, help="render seconds per method (quick 20, full 600; the full run "
                   "takes ~2 h on 2 CPU cores: reference ~30 min, methods 6 x 10 min, colour shift ~20 min)")
    p.add_argument("--quick", action="store_true", help="80x60, 50,625 photons/pass, 20 s per method, small reference (~5 min, ~3 once cached)")
    p.add_argument("--resolution", type=_res, help="default: quick 80x60, full 160x120")
    p.add_argument("--photons", type=int, help="stored photons per pass (default: the paper's per pixel)")
    p.add_argument("--max-passes", type=int, help="stop a method at this many passes (default 200)")
    p.add_argument("--seed", type=int)
    p.add_argument("--ref-method", default="a", choices=list(METHODS))
    p.add_argument("--ref-spacing", type=float, help="reference equal spacing in um (overrides --ref-method)")
    p.add_argument("--ref-photons", type=int)
    p.add_argument("--ref-passes", type=int)
    p.add_argument("--ref-k", type=int, help="reference photons in the first search (default 200)")
    p.add_argument("--force-ref", action="store_true", help="recompute the reference even if cached")
    p.add_argument("--cache", default="out/cache", help="reference cache folder (default out/cache)")
    p.add_argument("--no-shift", action="store_true", help="skip the colour-shift experiment")
    p.add_argument("--shift-spacings", type=_floats)
    p.add_argument("--shift-photons", type=_ints)
    p.add_argument("--shift-passes", type=int)
    p.add_argument("--no-flip", action="store_true", help="skip FLIP even if flip-evaluator is installed")
    p.add_argument("-o", "--out", help="output folder (default out/compare or out/compare-quick)")
    add_device(p)
    p.set_defaults(func=cmd_compare)


def _ref_R(ref) -> str:
    rs = [h.get("R_median_um") for h in ref.info.get("halves", [])]
    rs = [r for r in rs if r is not None]
    return f"{np.mean(rs):.0f}" if rs else "?"


def cmd_compare(a) -> int:
    from . import config, paths
    from .device import open_device
    d = QUICK if a.quick else FULL
    cfg = config.load(a.config)
    methods = [m for m in a.methods.replace(",", "") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise config.ConfigError("command line", "--methods", a.methods, "letters from a-f")
    res_ = a.resolution or d["resolution"]
    photons = a.photons or d["photons"]
    budget = a.budget if a.budget is not None else d["budget"]
    max_passes = a.max_passes or d["max_passes"]
    out = a.out or ("out/compare-quick" if a.quick else "out/compare")
    paths.check_folder(out, "-o/--out")
    paths.check_folder(a.cache, "--cache")
    os.makedirs(os.path.join(out, "images"), exist_ok=True)
    flip = flip_available() and not a.no_flip
    dev = open_device(a.device)
    spec = RefSpec(method=a.ref_method, spacing_um=a.ref_spacing, resolution=tuple(res_),
                   photons=a.ref_photons or d["ref"]["photons"], passes=a.ref_passes or d["ref"]["passes"],
                   initial_photons=a.ref_k or d["ref"]["initial_photons"])
    print(f"clppm compare {os.path.basename(a.config)} on {dev.name}: methods {''.join(methods)}, "
          f"{res_[0]}x{res_[1]}, {photons:,} stored photons/pass, budget {budget:g} render s per method"
          f"{', FLIP on' if flip else ', FLIP off (pip install flip-evaluator)' if not a.no_flip else ''}")
    t_all = time.perf_counter()
    with cached_volumes():
        ref = get_reference(cfg, spec, a.cache, dev=dev, force=a.force_ref, flip=flip)
        image.write_png(os.path.join(out, "images", "reference.png"), ref.rgb, ref.exposure)
        runs = {}
        print("methods:")
        for m in methods:
            r = run_method(cfg, m, ref, budget=budget, max_passes=max_passes, photons=photons, seed=a.seed,
                           dev=dev, flip=flip)
            image.write_png(os.path.join(out, "images", f"method-{m}.png"), r.pop("_rgb"), r.pop("_exposure"))
            runs[m] = r
        shift = None
        if not a.no_shift:
            print("colour-shift experiment (equal spacing x stored photons per pass):")
            shift = colour_shift_experiment(
                cfg, spacings=a.shift_spacings or d["shift_spacings"], photons=a.shift_photons or d["shift_photons"],
                passes=a.shift_passes or d["shift_passes"], resolution=tuple(res_), seed=a.seed, ref=ref, dev=dev,
                log=print)
    summ = summarise(runs)
    md = [f"# clppm compare: {os.path.basename(a.config)}", "",
          f"Device {dev.name}; {res_[0]}x{res_[1]} pixels, {photons:,} stored photons per pass, "
          f"K = {cfg['render']['initial_photons']}, budget {budget:g} render seconds per method "
          f"(eye + photon + grid + gather; volume build and snapshots excluded).", "",
          f"Reference `{ref.key}`: method {spec.method}"
          f"{'' if spec.spacing_um is None else f' spacing {spec.spacing_um:g} um'}, {spec.photons:,} stored "
          f"photons/pass, {spec.passes} passes, K = {spec.initial_photons}, mean of two seeds; median radius "
          f"{_ref_R(ref)} um.  Its error estimate (from the halves) is noise only: the density-estimation bias "
          "of its finite radius is not in it (the compared runs' radii are in the R column).", "",
          "All methods use the same seed (the same photons in every pass), so the differences between them "
          "at equal passes are not photon noise.", "",
          "## Speed and accuracy (last snapshot; equal-time columns interpolated log-log)", "",
          results_markdown(runs, summ, ref), "", "![error against time](compare.png)", "",
          "## Table 1: mean sample points per eye ray per layer", "", table1_markdown(runs)]
    if shift is not None:
        md += ["", "## Colour shift against spacing and photons (the paper's explanation of method a)", "",
               shift_markdown(shift)]
    md_text = "\n".join(md) + "\n"
    plot(runs, ref, os.path.join(out, "compare.png"),
         title=f"{os.path.basename(a.config)}: {res_[0]}x{res_[1]}, {photons:,} photons/pass, {dev.name}")
    doc = {"config": os.path.abspath(a.config), "device": dev.info(), "resolution": list(res_),
           "photons_per_pass": photons, "budget_s": budget, "max_passes": max_passes,
           "initial_photons": cfg["render"]["initial_photons"],
           "reference": {"key": ref.key, "spec": ref.spec.as_dict(), "error": ref.error, "info": ref.info},
           "methods": runs, "summary": summ, "colour_shift": shift,
           "wall_seconds": time.perf_counter() - t_all}
    with open(os.path.join(out, "compare.json"), "w") as f:
        json.dump(doc, f, indent=1, default=str)
    with open(os.path.join(out, "compare.md"), "w") as f:
        f.write(md_text)
    print()
    print(results_markdown(runs, summ, ref))
    print()
    print("Table 1, mean sample points per eye ray per layer: ours (paper)")
    print(table1_markdown(runs))
    if shift is not None:
        print()
        print(shift_markdown(shift))
    print(f"\nwrote {out}/compare.png, compare.md, compare.json, images/ ({time.perf_counter() - t_all:.0f} s)")
    return 0


def main(argv=None) -> int:      # python -m clppm.compare
    from .cli import _add_device
    ap = argparse.ArgumentParser(prog="clppm")
    sub = ap.add_subparsers(dest="cmd", required=True)
    add_parser(sub, _add_device)
    a = ap.parse_args(["compare", *(sys.argv[1:] if argv is None else argv)])
    return a.func(a)


if __name__ == "__main__":
    sys.exit(main())
