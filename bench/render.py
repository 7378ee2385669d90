"""Renderer throughput on one OpenCL device: methods a-f at paper scale, and scaling runs.

For each method (default a-f) one render of a few passes at the paper's scale (320x240
pixels, 810,000 stored photons per pass, K = 810; ``configs/forearm.toml``), after a warm-up
render that compiles every kernel, measures

* photons/s (emitted), stored photons/s (both over the photon-pass seconds), gather pairs/s
  (photon-sample-point pairs found, over the gather seconds);
* seconds per pass per stage: eye (once), photon, grid build, gather, radiance/output
  (reading back and converting the image, once per image);
* device memory: the buffers the render allocates (the same sizes its allocation check
  uses: stored and sorted photons, grid cells, sample points, pixel accumulators, volume),
  and the process's peak resident memory (on a CPU device the buffers live there);
* the time of the paper's 200 passes, extrapolated, and the speedup over the paper's times.

Extrapolation.  The photon pass and the grid build cost the same every pass (same stored
photon count).  The gather does not: every sample point finds ~K photons in pass 1, and
progressive photon mapping then shrinks the radius, so the photons found per pass fall.  The
gather seconds per pass are fitted as c0 + c1 * pairs over the measured passes and summed over
a pairs-per-pass curve anchored at the measured passes 2..n (pass 1 stores photons at every
depth, later passes only those a sample point can reach, so pass 1 sees a lower density).
Three estimates are given:

* ``seconds`` (the headline): the curve measured in the passes sweep (method e, 24 passes at
  80x60 quick, 32 at 160x120 full): pairs_p ~ p^-beta, fitted over passes 2..n;
* ``model_seconds``: the mean-field curve.  With the expected count M_p = K x_p
  (x_p = R_p^3 / R_1^3 at constant photon density) the update N' = N + alpha M,
  R'^3 = R^3 (N + alpha M) / (N + M) becomes the scale-free recursion n_1 = 0, x_1 = 1;
  n_{p+1} = n_p + alpha x_p, x_{p+1} = x_p (n_p + alpha x_p) / (n_p + x_p)  (n = N / K).
  It decays faster than measured (spheres cut by the skin surface and the depth gradient of
  the photon density make the found photons fall slower than R^3), so it is a lower bound;
* ``linear_seconds``: 200 x the mean measured pass, an upper bound.

Scaling runs (method e unless --scaling-method): seconds per pass per stage against stored
photons per pass and against pixels, and cumulative seconds against passes; the fitted
log-log exponents are printed.

    python bench/render.py [--device P:D] [--quick] [--methods abcdef] [--passes 3]
                           [--out out/bench] [--no-scaling]

``--quick`` runs 160x120 pixels with the paper's photons per pixel (202,500 per pass), two
passes, and small scaling sweeps (about 3 minutes on 2 CPU cores); its speedups are of that
smaller render against the paper's full-size times, so not comparable to them.  The JSON goes to
``OUT/render-<device>.json``; ``bench/devices.py`` runs this for every device and writes
the combined markdown table.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import sys
import time
from types import SimpleNamespace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

PAPER_PASSES = 200
STAGES = ("photon", "grid", "gather")


def shrink_model(alpha: float, n: int) -> np.ndarray:
    """x_p = expected photons found in pass p / in pass 1, p = 1..n (see the module doc)."""
    x = np.empty(n)
    N, xp = 0.0, 1.0
    for p in range(n):
        x[p] = xp
        Nn = N + alpha * xp
        xp = xp * Nn / (N + xp)
        N = Nn
    return x


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-").lower()[:48]


def peak_rss_bytes() -> int:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(r * 1024) if sys.platform != "darwin" else int(r)


def device_bytes(report: dict, photons: int) -> dict:
    """The buffers a render allocates (as progressive.render's allocation check counts them)."""
    from clppm.integrators import eyepass, hashgrid
    from clppm.config import wavelengths
    cap = int(photons * 1.2) + 4096
    res = report["config"]["camera"]["resolution"]
    npix = int(res[0]) * int(res[1])
    nb = len(wavelengths(report["config"]))
    eye = eyepass.EyeData.device_bytes(SimpleNamespace(npoints=report["sample_points"],
                                                       npieces=report["path_pieces"],
                                                       nrays=report["eye_rays"]))
    d = {"stored photons": cap * 32, "sorted photons": cap * 36,
         "grid cells": 4 * (hashgrid.DEFAULT_MAX_CELLS + 1) * 2,
         "sample points": int(eye), "pixel accumulators": npix * nb * 8 + npix * 8,
         "volume": int(report.get("volume", {}).get("device_bytes", 0))}
    d["total"] = sum(d.values())
    return d


def run_series(cfg, method, passes, photons, resolution, dev, seed=None):
    """One render; per-pass stage seconds, pairs, emitted and stored photons."""
    from clppm.run.entry import render
    cum = []

    def snap(p, wall, res):
        r = res.report
        cum.append({"pass": p, "wall": wall, **{k: r["seconds"].get(k, 0.0) for k in ("eye",) + STAGES},
                    "pairs": r["gather_pairs"], "emitted": r["photons_emitted"], "stored": r["photons_stored"]})

    res = render(cfg, method=method, passes=passes, photons=photons, resolution=resolution, seed=seed,
                 dev=dev, snapshot_every=1, on_snapshot=snap)
    per = []
    prev = {k: 0.0 for k in STAGES + ("pairs", "emitted", "stored")}
    for c in cum:
        per.append({k: c[k] - prev[k] for k in prev})
        prev = {k: c[k] for k in prev}
    return res, cum, per


def decay_curve(alpha: float, passes: int, beta: float | None = None) -> np.ndarray:
    """Relative gather pairs per pass, p = 1..passes, normalised to 1 at pass 2: the mean-field
    model (``beta`` None) or the power law (p / 2)^-beta fitted to a measured pass series."""
    x = shrink_model(alpha, passes)
    d = x / x[1] if passes > 1 else x
    if beta is not None:
        p = np.arange(1, passes + 1, dtype=float)
        d = np.concatenate([d[:1], (p[1:] / 2.0) ** (-beta)])
    return d


def extrapolate(per: list, eye_s: float, output_s: float, curve: np.ndarray) -> dict:
    """Seconds for len(curve) passes from the measured passes ``per`` and a pairs-per-pass curve."""
    passes = len(curve)
    n = len(per)
    ph = float(np.mean([q["photon"] for q in per]))
    grid_first = per[0]["grid"]
    grid_rest = float(np.mean([q["grid"] for q in per[1:]])) if n > 1 else grid_first
    pairs = np.array([q["pairs"] for q in per], float)
    g = np.array([q["gather"] for q in per], float)
    c0, c1 = 0.0, float(g.sum() / max(pairs.sum(), 1.0))
    if n >= 3 and np.ptp(pairs) > 0.05 * pairs.mean():
        A = np.column_stack([np.ones(n), pairs])
        sol, *_ = np.linalg.lstsq(A, g, rcond=None)
        if sol[0] >= 0 and sol[1] > 0:
            c0, c1 = float(sol[0]), float(sol[1])
    # anchor the curve at passes 2..n: pass 1 stores photons at every depth, later passes only
    # where a sample point can reach them (store_zmin), so pass 1 sees a lower density
    sel = np.arange(1, n) if n >= 2 else np.arange(0, 1)
    scale = float(np.dot(pairs[sel], curve[sel]) / np.dot(curve[sel], curve[sel]))
    pred_pairs = np.concatenate([pairs, scale * curve[n:passes]])
    gather = float(np.sum(g[:min(n, passes)]) + np.sum(c0 + c1 * pred_pairs[n:]))
    photon = ph * passes
    grid = grid_first + grid_rest * (passes - 1)
    total = eye_s + photon + grid + gather + output_s
    check = [{"pass": i + 1, "pairs_measured": int(pairs[i]), "pairs_curve": int(round(scale * curve[i]))}
             for i in range(n)]
    return {"passes": passes, "seconds": total,
            "stages": {"eye": eye_s, "photon": photon, "grid": grid, "gather": gather, "output": output_s},
            "gather_fit": {"c0_s": c0, "c1_s_per_pair": c1}, "pairs_total": float(pred_pairs.sum()),
            "pairs_check": check}


def bench_method(cfg, method, dev, passes, photons, resolution, alpha, beta=None) -> dict:
    from clppm.scene.skin import PAPER_RENDER_TIME_S
    t0 = time.perf_counter()
    res, cum, per = run_series(cfg, method, passes, photons, resolution, dev)
    r = res.report
    s = r["seconds"]
    ph_s = sum(q["photon"] for q in per)
    ga_s = sum(q["gather"] for q in per)
    ex_model = extrapolate(per, s["eye"], s.get("output", 0.0), decay_curve(alpha, PAPER_PASSES))
    ex = ex_model
    if beta is not None:
        ex = extrapolate(per, s["eye"], s.get("output", 0.0), decay_curve(alpha, PAPER_PASSES, beta))
        ex["decay"] = f"measured: pairs per pass ~ p^-{beta:.3f} (passes sweep)"
    else:
        ex["decay"] = "mean-field radius model"
    ex["model_seconds"] = ex_model["seconds"]
    ex["linear_seconds"] = eye_s_linear(per, s["eye"], s.get("output", 0.0))
    paper = PAPER_RENDER_TIME_S.get(method)
    out = {
        "method": method, "scheme": r["scheme"], "passes": len(per), "resolution": list(resolution),
        "stored_per_pass": photons, "initial_photons": r["config"]["render"]["initial_photons"],
        "sample_points": r["sample_points"], "photons_emitted": r["photons_emitted"],
        "photons_stored": r["photons_stored"], "gather_pairs": r["gather_pairs"],
        "photons_per_s": r["photons_emitted"] / ph_s if ph_s > 0 else None,
        "stored_photons_per_s": r["photons_stored"] / ph_s if ph_s > 0 else None,
        "gather_pairs_per_s": r["gather_pairs"] / ga_s if ga_s > 0 else None,
        "seconds_per_pass": {k: float(np.mean([q[k] for q in per])) for k in STAGES},
        "seconds_once": {"eye": s["eye"], "output": s.get("output", 0.0), "volume": s.get("volume", 0.0)},
        "per_pass": per,
        "device_memory_bytes": device_bytes(r, photons),
        "peak_rss_bytes": peak_rss_bytes(),
        "extrapolated_200": ex,
        "paper_seconds": paper,
        "speedup_vs_paper": (paper / ex["seconds"]) if paper else None,
        "wall_seconds": time.perf_counter() - t0,
    }
    return out


def eye_s_linear(per, eye_s, output_s, passes=PAPER_PASSES):
    """Naive extrapolation: every pass as long as the mean measured pass (an upper bound)."""
    return eye_s + passes * float(np.mean([q["photon"] + q["grid"] + q["gather"] for q in per])) + output_s


def fit_exponent(xs, ys):
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = (xs > 0) & (ys > 0)
    if ok.sum() < 2:
        return None
    return float(np.polyfit(np.log(xs[ok]), np.log(ys[ok]), 1)[0])


def sweep_photons(cfg, dev, method, photons_list, res, log=print) -> dict:
    """Seconds per pass per stage against stored photons per pass (2 passes each)."""
    rows = []
    for n in photons_list:
        _, _, per = run_series(cfg, method, 2, n, res, dev)
        rows.append({"photons": n, **{k: float(np.mean([q[k] for q in per])) for k in STAGES},
                     "pairs": float(np.mean([q["pairs"] for q in per]))})
        rows[-1]["total"] = sum(rows[-1][k] for k in STAGES)
        log(f"  photons {n:>9,}: " + ", ".join(f"{k} {rows[-1][k]:.3f}" for k in STAGES + ("total",)) + " s/pass")
    return {"resolution": list(res), "rows": rows,
            "exponents": {k: fit_exponent([r["photons"] for r in rows], [r[k] for r in rows])
                          for k in STAGES + ("total", "pairs")}}


def sweep_pixels(cfg, dev, method, res_list, photons, log=print) -> dict:
    """Seconds per pass per stage (and the eye pass) against pixels (2 passes each)."""
    rows = []
    for rs in res_list:
        res, _, per = run_series(cfg, method, 2, photons, rs, dev)
        rows.append({"pixels": rs[0] * rs[1], "resolution": list(rs), "eye": res.report["seconds"]["eye"],
                     "sample_points": res.report["sample_points"],
                     **{k: float(np.mean([q[k] for q in per])) for k in STAGES}})
        rows[-1]["total"] = sum(rows[-1][k] for k in STAGES)
        log(f"  pixels {rs[0]}x{rs[1]:<5}: eye {rows[-1]['eye']:.3f} s, " +
            ", ".join(f"{k} {rows[-1][k]:.3f}" for k in STAGES + ("total",)) + " s/pass")
    return {"photons": photons, "rows": rows,
            "exponents": {k: fit_exponent([r["pixels"] for r in rows], [r[k] for r in rows])
                          for k in ("eye",) + STAGES + ("total", "sample_points")}}


def sweep_passes(cfg, dev, method, passes_n, res, photons, log=print) -> dict:
    """Cumulative seconds and pairs against passes; the per-pass pairs decay exponent beta
    (pairs_p ~ p^-beta, fitted over passes 2..n) used to extrapolate the gather."""
    _, cum, per = run_series(cfg, method, passes_n, photons, res, dev)
    alpha = float(cfg["render"]["alpha"])
    x = shrink_model(alpha, passes_n)
    t = np.cumsum([q["photon"] + q["grid"] + q["gather"] for q in per])
    pairs = np.cumsum([q["pairs"] for q in per])
    ps = np.arange(1, passes_n + 1)
    sel = ps >= 2
    pp_ = np.array([q["pairs"] for q in per], float)
    sc_ = float(np.dot(pp_[1:], x[1:]) / np.dot(x[1:], x[1:])) if passes_n > 1 else pp_[0]
    slope = fit_exponent(ps[sel], pp_[sel])
    out = {"resolution": list(res), "photons": photons,
           "cumulative_seconds": t.tolist(), "cumulative_pairs": pairs.tolist(),
           "pairs_per_pass": pp_.tolist(), "pairs_per_pass_model": (sc_ * x).tolist(),
           "beta": None if slope is None else -slope,
           "beta_model": -fit_exponent(ps[sel], x[sel]),
           "exponents": {"seconds": fit_exponent(ps[sel], t[sel]), "pairs": fit_exponent(ps[sel], pairs[sel]),
                         "pairs_model": fit_exponent(ps[sel], np.cumsum(x)[sel])}}
    log(f"  passes 1..{passes_n} at {res[0]}x{res[1]}: cumulative seconds ~ passes^"
        f"{out['exponents']['seconds']:.2f}, cumulative pairs ~ passes^{out['exponents']['pairs']:.2f} "
        f"(mean-field model {out['exponents']['pairs_model']:.2f}); pairs per pass ~ p^-{out['beta']:.3f} "
        f"(model p^-{out['beta_model']:.3f})")
    return out


def markdown(docs: list) -> str:
    """Combined table over devices (one JSON document per device)."""
    lines = ["| device | method | res | stored/pass | passes | photons/s | stored/s | pairs/s | "
             "s/pass photon | grid | gather | eye s | output s | device MiB | 200 passes s | model | linear | "
             "paper s | speedup |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for d in docs:
        for r in d["methods"]:
            sp = r["seconds_per_pass"]
            ex = r["extrapolated_200"]
            lines.append(
                f"| {d['device']['name']} | {r['method']} | {r['resolution'][0]}x{r['resolution'][1]} | "
                f"{r['stored_per_pass']:,} | {r['passes']} | {r['photons_per_s']:.3g} | {r['stored_photons_per_s']:.3g} | "
                f"{r['gather_pairs_per_s']:.3g} | {sp['photon']:.3f} | {sp['grid']:.3f} | {sp['gather']:.2f} | "
                f"{r['seconds_once']['eye']:.2f} | {r['seconds_once']['output']:.3f} | "
                f"{r['device_memory_bytes']['total'] / 2**20:.0f} | {ex['seconds']:.0f} | {ex['model_seconds']:.0f} | "
                f"{ex['linear_seconds']:.0f} | "
                f"{r['paper_seconds']:.0f} | {r['speedup_vs_paper']:.2f} |")
    for d in docs:
        sc = d.get("scaling")
        if not sc:
            continue
        e1, e2, e3 = sc["photons"]["exponents"], sc["pixels"]["exponents"], sc["passes"]["exponents"]
        lines += ["", f"Scaling on {d['device']['name']} (method {sc['method']}), fitted log-log exponents:", "",
                  "| sweep | photon | grid | gather | total | other |", "|---|---:|---:|---:|---:|---|"]

        def g(v):
            return "–" if v is None else f"{v:.2f}"
        lines.append(f"| s/pass vs stored photons/pass | {g(e1['photon'])} | {g(e1['grid'])} | {g(e1['gather'])} | "
                     f"{g(e1['total'])} | pairs {g(e1['pairs'])} |")
        lines.append(f"| s/pass vs pixels | {g(e2['photon'])} | {g(e2['grid'])} | {g(e2['gather'])} | "
                     f"{g(e2['total'])} | eye {g(e2['eye'])}, sample points {g(e2['sample_points'])} |")
        lines.append(f"| cumulative s vs passes | – | – | – | {g(e3['seconds'])} | pairs {g(e3['pairs'])} "
                     f"(model {g(e3['pairs_model'])}); pairs/pass ~ p^-{g(sc['passes']['beta'])} "
                     f"(model p^-{g(sc['passes']['beta_model'])}) |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--device", default=None)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--methods", default="abcdef")
    ap.add_argument("--passes", type=int, help="measured passes per method (default 3, quick 2)")
    ap.add_argument("--resolution", help="WxH (default 320x240, quick 160x120)")
    ap.add_argument("--photons", type=int, help="stored photons per pass (default 810000, quick 202500)")
    ap.add_argument("--no-scaling", action="store_true")
    ap.add_argument("--scaling-method", default="e")
    ap.add_argument("--out", default=os.path.join("out", "bench"))
    a = ap.parse_args(argv)

    from clppm import config
    from clppm.scene import volume
    from clppm.compute.device import open_device
    from clppm.run.entry import render

    cfg = config.load(a.config)
    dev = open_device(a.device)
    info = dev.info()
    if a.resolution:
        w, h = (int(v) for v in a.resolution.lower().split("x"))
    else:
        w, h = (160, 120) if a.quick else (320, 240)
    photons = a.photons or (202_500 if a.quick else 810_000)
    passes = a.passes or (2 if a.quick else 3)
    alpha = float(cfg["render"]["alpha"])
    print(f"device {info['name']} [{info['platform']}; {info['type']}; {info['compute_units']} CUs]; "
          f"{w}x{h}, {photons:,} stored photons/pass, K = {cfg['render']['initial_photons']}, {passes} passes")
    doc = {"device": info, "config": os.path.abspath(a.config), "quick": a.quick,
           "resolution": [w, h], "stored_per_pass": photons, "passes": passes, "methods": []}
    t_all = time.perf_counter()
    with volume.memoised():
        t0 = time.perf_counter()
        render(cfg, method="f", passes=2, photons=20_000, resolution=(16, 12), dev=dev)   # compile everything
        for m in "abcde":      # the eye kernel's JIT per scheme, cheaply
            render(cfg, method=m, passes=1, photons=5_000, resolution=(8, 6), dev=dev)
        doc["warmup_seconds"] = time.perf_counter() - t0
        print(f"warm-up (kernel builds, volume) {doc['warmup_seconds']:.1f} s")
        beta = None
        if not a.no_scaling:
            print(f"scaling (method {a.scaling_method}), passes first (its pairs decay extrapolates the gather):")
            if a.quick:
                sp = sweep_passes(cfg, dev, a.scaling_method, 24, (80, 60), 50_625)
            else:
                sp = sweep_passes(cfg, dev, a.scaling_method, 32, (160, 120), 202_500)
            doc["scaling"] = {"method": a.scaling_method, "passes": sp}
            beta = sp["beta"]
        hdr = (f"{'m':1} {'photons/s':>10} {'stored/s':>10} {'pairs/s':>10} {'photon':>7} {'grid':>7} {'gather':>7} "
               f"{'eye':>6} {'output':>6} {'dev MiB':>7} {'200 passes s':>13} {'model':>7} {'linear':>7} "
               f"{'paper s':>7} {'speedup':>7}")
        print(hdr)
        for m in a.methods.replace(",", ""):
            r = bench_method(cfg, m, dev, passes, photons, (w, h), alpha, beta)
            doc["methods"].append(r)
            sp_, ex = r["seconds_per_pass"], r["extrapolated_200"]
            print(f"{m:1} {r['photons_per_s']:>10.3g} {r['stored_photons_per_s']:>10.3g} {r['gather_pairs_per_s']:>10.3g} "
                  f"{sp_['photon']:>7.3f} {sp_['grid']:>7.3f} {sp_['gather']:>7.2f} {r['seconds_once']['eye']:>6.2f} "
                  f"{r['seconds_once']['output']:>6.3f} {r['device_memory_bytes']['total'] / 2**20:>7.0f} "
                  f"{ex['seconds']:>13.0f} {ex['model_seconds']:>7.0f} {ex['linear_seconds']:>7.0f} "
                  f"{r['paper_seconds']:>7.0f} {r['speedup_vs_paper']:>7.2f}", flush=True)
        if doc["methods"]:
            ex = doc["methods"][0]["extrapolated_200"]
            print(f"200 passes: {ex['decay']}; gather pairs per pass, measured / curve (method "
                  f"{doc['methods'][0]['method']}): " + ", ".join(
                      f"p{c['pass']} {c['pairs_measured']:.3g}/{c['pairs_curve']:.3g}" for c in ex["pairs_check"]))
        print(f"peak process RSS {peak_rss_bytes() / 2**20:.0f} MiB")
        if not a.no_scaling:
            if a.quick:
                doc["scaling"]["photons"] = sweep_photons(cfg, dev, a.scaling_method,
                                                          [12_656, 25_312, 50_625, 101_250], (80, 60))
                doc["scaling"]["pixels"] = sweep_pixels(cfg, dev, a.scaling_method,
                                                        [(40, 30), (80, 60), (160, 120)], 50_625)
            else:
                doc["scaling"]["photons"] = sweep_photons(cfg, dev, a.scaling_method,
                                                          [101_250, 202_500, 405_000, 810_000], (320, 240))
                doc["scaling"]["pixels"] = sweep_pixels(cfg, dev, a.scaling_method,
                                                        [(80, 60), (160, 120), (320, 240)], 810_000)
            for k in ("photons", "pixels", "passes"):
                print(f"  exponents vs {k}: " + ", ".join(
                    f"{kk} {v:.2f}" for kk, v in doc["scaling"][k]["exponents"].items() if v is not None))
    doc["peak_rss_bytes"] = peak_rss_bytes()
    doc["wall_seconds"] = time.perf_counter() - t_all
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, f"render-{slug(info['name'])}{'-quick' if a.quick else ''}.json")
    with open(path, "w") as f:
        json.dump(doc, f, indent=1, default=str)
    print()
    print(markdown([doc]))
    print(f"\nwrote {path} ({doc['wall_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
