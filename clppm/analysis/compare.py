"""``clppm compare``: speed against accuracy of the sampling schemes a-f, both estimators and
the path tracer.

For one scene, every method is rendered progressively until its time budget is spent, in the
new default mode and in the paper's mode (config.PAPER_MODE: every event stored, one band per
path, the sphere estimator); the path tracer runs too, where the scene allows it.  At a
geometric schedule of passes (and at the last one) each image is compared with a converged
reference (:mod:`clppm.analysis.reference`, computed once and cached): the unbiased path tracer
where the scene allows it (flat, point light), else a long PPM run.  The comparison is over squares
of ``block`` x ``block`` skin pixels (the path tracer's reference pixels), so that it measures
bias plus the noise left at that scale:

* ``block_Y_rms`` / ``block_Y_max``: relative error of Y per square (RMS, largest),
* ``de2000``: mean CIEDE2000 of the squares, ``de_mean``: CIEDE2000 of the mean skin colour,
* ``group_max``: largest relative error of the mean skin radiance in a 50-nm band group,
* RMSE of linear XYZ, mean signed Δb*, chromaticity of the mean colour (as before).

The per-pixel noise of one image is measured by ``bench/studies/noise.py`` (two seeds).

Time is the render's own stage time (eye + calibration + photon + grid + gather seconds, or
the path tracer's trace seconds): the host-side volume build (memoised here) and the snapshot
overhead are left out.

Outputs (``-o DIR``): ``compare.png`` (error against seconds, log-log, one curve per method and
mode, the path tracer in black), ``compare.md`` and ``compare.json`` (the same numbers; Table 1
of sample points per layer beside the paper's; the colour-shift experiment), and the final
image of each run.

The colour-shift experiment (:func:`colour_shift_experiment`) tests the paper's explanation
of method a's bluish cast ("with closely spaced sample points the same stored photon is
reused by many sample points, and short-wavelength photons, stored more often near the
surface, weigh in more"): it renders equal spacings (4, 7, 14, 28 um ...) in paper mode at
several stored photon counts per pass with the same seed (the same photons for every spacing)
and records the mean skin colour's shift against the reference next to the reuse factor
(gather pairs / stored photons).  If reuse caused a colour bias, the shift would grow with the
reuse factor.
"""
from __future__ import annotations

import math
import time

import numpy as np

from .. import config as C
from ..scene import colorimetry, volume
from .metrics import accuracy, block_mean, error_metrics
from .reference import RefSpec, pt_possible, skin_mask

METHODS = "abcdef"
STAGES = ("eye", "calibration", "photon", "grid", "gather", "trace")
MODES = {"default": {}, "paper": C.PAPER_MODE}

QUICK = {
    "resolution": (80, 60),
    "budget": 20.0,
    "max_passes": 400,
    "paper_methods": "e",
    "ref_paths": 300_000,         # path-tracer reference: paths per 10x10-pixel square and half
    "ref_ppm_passes": 40,         # PPM reference (scenes the path tracer cannot render)
    "shift_spacings": (4.0, 7.0, 14.0, 28.0),
    "shift_photons": (12_656, 50_625, 202_500),
    "shift_passes": 2,
}
STANDARD = {
    "resolution": (80, 60),
    "budget": 90.0,
    "max_passes": 2000,
    "paper_methods": "abcdef",
    "ref_paths": 1_500_000,
    "ref_ppm_passes": 200,
    "shift_spacings": (4.0, 7.0, 14.0, 28.0),
    "shift_photons": (50_625, 202_500, 810_000),
    "shift_passes": 4,
}
BLOCK = 10


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


# ----------------------------------------------------------------------------- one run
def _snapshot(p: int, t: float, wall: float, res, ref, extra: dict) -> dict:
    m = accuracy(res.xyz, res.spectral, ref)
    r = res.report
    return {"pass": p, "seconds": t, "wall": wall,
            "stage_seconds": {k: r["seconds"].get(k, 0.0) for k in STAGES}, **extra, **m}


def run_method(cfg: dict, method: str, ref, *, budget: float, max_passes: int, mode: str = "default",
               photons: int | None = None, seed: int | None = None, spacing: float | None = None,
               dev=None, log=print) -> dict:
    """Render ``method`` in ``mode`` until ``budget`` render seconds; accuracy at snapshots."""
    from ..run.entry import render
    c = cfg
    for k, v in MODES[mode].items():
        c = C.override(c, "render", k, v)
    w, h = ref.spec.resolution
    sched = schedule(max_passes)
    snaps: list = []
    last = {}

    def on_pass(p, st):
        last["pt_R"], last["scale"] = st["pt_R"], st.get("radius_scale", 1.0)

    def on_snapshot(p, wall, res):
        t = render_seconds(res.report)
        if p in sched or t >= budget or p >= max_passes:
            r = res.report
            R = median_radius(last, r)
            snaps.append(_snapshot(p, t, wall, res, ref, {
                "R_median_um": None if R is None else R * last.get("scale", 1.0),
                "photons_emitted": r["photons_emitted"], "photons_stored": r["photons_stored"],
                "gather_pairs": r["gather_pairs"]}))
        last["res"] = res
        return t >= budget                  # the time budget: the driver stops the run

    t0 = time.perf_counter()
    render(c, method=method, spacing=spacing, passes=max_passes, photons=photons, resolution=(w, h),
           seed=seed, dev=dev, snapshot_every=1, on_snapshot=on_snapshot, on_pass=on_pass)
    res = last["res"]
    r = res.report
    f = snaps[-1]
    log(f"  {mode} {method}: {f['pass']} passes, {f['seconds']:.1f} s ({time.perf_counter() - t0:.0f} s wall): "
        f"Y per square {100 * f['block_Y_rms']:.2f} % RMS ({100 * f['block_Y_max']:.2f} % max), "
        f"dE00 {f['de2000']:.2f}, mean colour dE00 {f['de_mean']:.2f}, band groups "
        f"{100 * f['group_max']:.2f} % max, db* {f['db']:+.2f}, median R {f['R_median_um'] or 0:.0f} um")
    return {
        "method": method, "mode": mode, "scheme": r["scheme"], "snapshots": snaps,
        "passes": f["pass"], "seconds": f["seconds"],
        "sample_points": r["sample_points"], "eye_rays_hit": r["eye_rays_hit"],
        "sample_points_per_ray_per_layer": r["sample_points_per_ray_per_layer"],
        "first_search_mean_photons": r.get("first_search_mean_photons"),
        "reuse": r["gather_pairs"] / max(r["photons_stored"], 1),
        "final": dict(f),
        "_rgb": res.rgb, "_exposure": res.exposure,
    }


def run_pt(cfg: dict, ref, *, budget: float, seed: int | None = None, dev=None, log=print,
           samples_per_pass: int = 4) -> dict:
    """The path tracer at the compared resolution until ``budget`` trace seconds."""
    from ..run.entry import render_pt
    w, h = ref.spec.resolution
    c = C.override(cfg, "render", "pt_samples_per_pass", samples_per_pass)
    snaps: list = []
    last = {}
    sched = schedule(10**6)
    nb = len(C.wavelengths(cfg))

    def on_snapshot(p, wall, res):
        t = float(res.report["seconds"].get("trace", 0.0))
        # a band is stratified over a pixel's samples: until every band has one, the image
        # lacks the missing bands (dark), which is coverage, not the estimator's error
        if (p in sched and p * samples_per_pass >= nb) or t >= budget:
            snaps.append(_snapshot(p, t, wall, res, ref, {"paths": res.report.get("paths_traced")}))
        last["res"] = res
        return t >= budget                  # the time budget: the driver stops the run

    t0 = time.perf_counter()
    render_pt(c, passes=10**6, resolution=(w, h), seed=seed, dev=dev, snapshot_every=1,
              on_snapshot=on_snapshot)
    res = last["res"]
    f = snaps[-1]
    log(f"  path tracer: {f['pass']} passes ({f['paths']:,} paths), {f['seconds']:.1f} s "
        f"({time.perf_counter() - t0:.0f} s wall): Y per square {100 * f['block_Y_rms']:.2f} % RMS, "
        f"dE00 {f['de2000']:.2f}, mean colour dE00 {f['de_mean']:.2f}")
    return {"method": "pt", "mode": "pt", "scheme": "path tracer (unbiased)", "snapshots": snaps,
            "passes": f["pass"], "seconds": f["seconds"], "final": dict(f),
            "_rgb": res.rgb, "_exposure": res.exposure}


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
    log = log or (lambda *a, **k: None)
    cfg = C.paper_mode(cfg)               # reuse by overlapping spheres is the paper's estimator's
    if resolution is None:
        resolution = tuple(cfg["camera"]["resolution"]) if ref is None else tuple(ref.spec.resolution)
    rows, imgs, mask = _shift_renders(cfg, spacings, photons, passes, resolution, seed, dev, log)
    against = _add_shifts(rows, imgs, mask, ref, spacings, photons)
    return {"against": against, "passes": int(passes), "resolution": list(resolution), "rows": rows,
            "summary": [_fine_minus_coarse(rows, n) for n in photons]}


def _shift_renders(cfg: dict, spacings, photons, passes: int, resolution, seed, dev, log):
    """Every (photons, spacing) render: its row (mean skin colour, reuse ...), its image
    (xyz, exposure) by (spacing, photons), and the skin mask."""
    from ..run.entry import render
    from ..request import resolved_config
    rows, imgs = [], {}
    with volume.memoised():
        mask = None
        for n in photons:
            for s in spacings:
                last = {}
                res = render(cfg, spacing=float(s), passes=int(passes), photons=int(n), resolution=resolution,
                             seed=seed, dev=dev, on_pass=lambda p, st, last=last: last.update(pt_R=st["pt_R"]))
                if mask is None:
                    mask = skin_mask(resolved_config(cfg, resolution=resolution, spacing=float(s)), dev)
                row = {"spacing_um": float(s), "photons": int(n), "passes": int(passes),
                       **_mean_colour(res, last, mask)}
                imgs[(float(s), int(n))] = (res.xyz, res.exposure)
                rows.append(row)
                log(f"  spacing {s:g} um, {n} photons/pass: reuse {row['reuse']:.0f}, "
                    f"u'v' ({row['u']:.4f}, {row['v']:.4f}), b* {row['b']:.2f}")
    return rows, imgs, mask


def _mean_colour(res, last: dict, mask) -> dict:
    """A render's sample points per ray, reuse, seconds, median radius, and the u'v' and Lab of
    its mean skin colour."""
    r = res.report
    mean = (res.xyz[mask] * res.exposure).mean(0)
    uv = colorimetry.xyz_to_uv_prime(mean)
    lab = colorimetry.xyz_to_lab(mean)
    return {"points_per_ray": r["sample_points"] / max(r["eye_rays_hit"], 1),
            "reuse": r["gather_pairs"] / max(r["photons_stored"], 1),
            "seconds": render_seconds(r), "R_median_um": median_radius(last, r),
            "u": float(uv[0]), "v": float(uv[1]),
            "L": float(lab[0]), "a": float(lab[1]), "b": float(lab[2])}


def _add_shifts(rows: list, imgs: dict, mask, ref, spacings, photons) -> str:
    """Each row's colour shift against ``ref`` (over its squares), or without one against the
    finest spacing at the most photons; returns what they are against."""
    b, bmask = 1, mask
    if ref is not None:
        base_xyz, base_exp, against = ref.xyz, ref.exposure, f"reference {ref.key}"
        b, bmask = ref.block, ref.mask
    else:
        k = (float(min(spacings)), int(max(photons)))
        base_xyz, base_exp = imgs[k]
        against = f"spacing {k[0]:g} um at {k[1]} photons/pass"
    for row in rows:
        xyz, e = imgs[(row["spacing_um"], row["photons"])]
        m = error_metrics(block_mean(xyz, b) * (e / base_exp), base_xyz, bmask, base_exp)
        row.update({k: m[k] for k in ("du_mean", "dv_mean", "du", "dv", "db", "da", "dL", "dY",
                                      "de2000", "rmse_xyz")})
    return against


def _fine_minus_coarse(rows: list, n: int) -> dict:
    """At ``n`` photons per pass: the finest spacing's shift minus the coarsest's, and the
    slopes of Δv' and b* against log(reuse)."""
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
    return d


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


def summarise(runs: dict, key: str = "block_Y_rms") -> dict:
    """Per run: the error ``key`` at the shortest run's time (log-log interpolated) and the
    time to the largest final error of all runs."""
    t_eq = min(r["seconds"] for r in runs.values())
    e_eq = max(r["final"][key] for r in runs.values())
    out = {"key": key, "equal_time_s": t_eq, "equal_error": e_eq, "runs": {}}
    for name, r in runs.items():
        xs = [s["seconds"] for s in r["snapshots"]]
        out["runs"][name] = {
            "at_equal_time": _interp_loglog(xs, [s[key] for s in r["snapshots"]], t_eq),
            "de2000_at_equal_time": _interp_loglog(xs, [s["de2000"] for s in r["snapshots"]], t_eq),
            "seconds_to_equal_error": _time_to(xs, [s[key] for s in r["snapshots"]], e_eq),
        }
    return out


def table1_markdown(runs: dict) -> str:
    from ..scene.skin import PAPER_TABLE1
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
    from ..scene.skin import PAPER_RENDER_TIME_S
    t = summ["equal_time_s"]
    head = ("| run | scheme | passes | seconds | R (um) | Y per square, RMS | max | ΔE00 | ΔE00 mean colour | "
            f"band groups, max | Δb* | Y RMS @ {t:.0f} s | s to Y RMS ≤ {100 * summ['equal_error']:.1f} % | "
            "paper s (200 passes) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, r in runs.items():
        f = r["final"]
        s = summ["runs"][name]

        def g(x, fmt, scale=1.0):
            return "–" if x is None else format(x * scale, fmt)
        paper_s = PAPER_RENDER_TIME_S.get(r["method"]) if r["mode"] == "paper" else None
        lines.append(
            f"| {name} | {r['scheme']} | {r['passes']} | {r['seconds']:.1f} | {g(f.get('R_median_um'), '.0f')} | "
            f"{100 * f['block_Y_rms']:.2f} % | {100 * f['block_Y_max']:.2f} % | {f['de2000']:.2f} | "
            f"{f['de_mean']:.2f} | {100 * f['group_max']:.2f} % | {f['db']:+.2f} | "
            f"{g(s['at_equal_time'], '.2f', 100)} % | {g(s['seconds_to_equal_error'], '.1f')} | "
            f"{g(paper_s, '.0f')} |")
    e = ref.error
    lines += ["", f"Reference noise (from its halves), per {ref.block}x{ref.block}-pixel square: Y "
              f"{100 * e['block_Y_rms']:.2f} % RMS, ΔE00 {e['de2000']:.3f}, mean colour ΔE00 {e['de_mean']:.3f}, "
              f"band groups {100 * e['group_max']:.2f} %.  Smallest error reported: Y "
              f"{100 * min(r['final']['block_Y_rms'] for r in runs.values()):.2f} % RMS "
              f"(reference noise / smallest error = "
              f"{e['block_Y_rms'] / max(min(r['final']['block_Y_rms'] for r in runs.values()), 1e-12):.2f})."]
    return "\n".join(lines)


def plot(runs: dict, ref, path: str, title: str = "") -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    fmt = FuncFormatter(lambda x, _: f"{x:g}")
    panels = [("block_Y_rms", "relative error of Y per 10x10 square (RMS)", True, 1.0),
              ("de2000", "mean CIEDE2000 of the squares", True, 1.0),
              ("de_mean", "CIEDE2000 of the mean skin colour", True, 1.0),
              ("group_max", "largest 50-nm band-group error of the mean", True, 1.0),
              ("db", "mean Δb* (negative: bluer)", False, 1.0),
              ("dv_mean", "Δv' of the mean skin colour", False, 1.0)]
    fig, axs = plt.subplots(2, 3, figsize=(15, 8.5))
    colors = dict(zip(METHODS, ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]))
    for ax, (k, lab, log, sc) in zip(axs.ravel(), panels):
        for name, r in runs.items():
            pts = [(s["seconds"], s[k] * sc) for s in r["snapshots"] if k in s]
            if not pts:
                continue
            xs, ys = zip(*pts)
            if log:
                xs, ys = zip(*[(x, y) for x, y in zip(xs, ys) if y > 0] or [(xs[0], 1e-9)])
            if r["mode"] == "pt":
                ax.plot(xs, ys, "s-", ms=3, lw=2, color="black", label="path tracer")
            else:
                ax.plot(xs, ys, "o-" if r["mode"] == "default" else "o--", ms=3,
                        color=colors.get(r["method"]), alpha=1.0 if r["mode"] == "default" else 0.6,
                        label=f"{r['method']} {r['mode']}")
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
    axs[0, 0].legend(fontsize=7, ncol=2)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------- command


def reference_spec(cfg: dict, resolution, d: dict, paths_: int | None = None, passes: int | None = None) -> RefSpec:
    """The path tracer where the scene allows it, else a long PPM run in the default mode."""
    if pt_possible(cfg):
        return RefSpec(integrator="pt", resolution=tuple(resolution), block=BLOCK,
                       paths=int(paths_ or d["ref_paths"]))
    return RefSpec(integrator="ppm", resolution=tuple(resolution), block=BLOCK, method="a",
                   photons=int(cfg["render"]["photons"]), passes=int(passes or d["ref_ppm_passes"]),
                   initial_photons=int(cfg["render"]["initial_photons"]))

