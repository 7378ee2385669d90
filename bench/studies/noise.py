"""Per-pixel noise of one image, from two seeds, against render seconds: paper mode and the default.

For each mode and resolution the scene is rendered twice with different seeds; at a schedule
of passes both images are compared over the skin pixels.  With independent errors e1, e2 of
the two images, (I1 - I2) / sqrt(2) has the distribution of one image's error, so

* noise_Y   = RMS over skin pixels of (Y1 - Y2) / sqrt(2), relative to the mean skin Y,
* noise_dE  = mean over skin pixels of CIEDE2000(I1, I2) / sqrt(2)  (first order: dE is
              locally proportional to the colour difference),
* efficiency = 1 / (noise_Y^2 x seconds)  (and the same with noise_dE),

where seconds are the render's own stage seconds (eye + calibration + photon + grid + gather)
of one image.  Bias is not in these numbers (the two images share it): see `clppm compare`
and the path-tracing reference for that.

    python bench/studies/noise.py                      # 80x60 and 320x240, paper mode and default
    python bench/studies/noise.py --quick              # 80x60 only, short budgets
    python bench/studies/noise.py --set storage=all --set estimator=layer --label variant

Prints a table, writes out/bench/noise.json, noise.md and noise.png (noise against seconds,
log-log, one curve per mode and resolution), and each mode's last image of the first seed
(noise-MODE-WxH.png: the two modes at equal time).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from clppm.scene import colorimetry, volume
from clppm import config as C, image                # noqa: E402
from clppm.analysis.compare import render_seconds, schedule          # noqa: E402
from clppm.run.entry import render                       # noqa: E402
from clppm.analysis.metrics import skin_mask_from_eye  # noqa: E402

STAGES = ("eye", "calibration", "photon", "grid", "gather")   # the stage times kept per row
PAPER = C.PAPER_MODE


def two_seed_noise(xyz1, xyz2, mask, exposure) -> dict:
    """One image's noise from two independent images (see the module docstring)."""
    a = np.asarray(xyz1, float)[mask] * exposure
    b = np.asarray(xyz2, float)[mask] * exposure
    mY = 0.5 * (a[:, 1].mean() + b[:, 1].mean())
    dY = (a[:, 1] - b[:, 1]) / math.sqrt(2.0)
    return {"noise_Y": float(np.sqrt(np.mean(dY * dY)) / mY) if mY > 0 else float("nan"),
            "noise_dE": float(np.mean(colorimetry.delta_e2000(a, b)) / math.sqrt(2.0)),
            "mean_Y": float(mY)}


def run_mode(cfg: dict, overrides: dict, seeds=(11, 22), budget: float = 60.0, max_passes: int = 10**6,
             dev=None, log=print) -> dict:
    """Both seeds until ``budget`` render seconds (or max_passes); noise at matching passes."""
    c = cfg
    for k, v in overrides.items():
        c = C.override(c, "render", k, v)
    snaps = []
    for s in seeds:
        shots = {}
        sched = schedule(max_passes, ratio=1.5)
        limit = {"passes": None}

        class Stop(Exception):
            pass

        def on_snapshot(p, wall, res, shots=shots, limit=limit):
            t = render_seconds(res.report)
            if p in sched or t >= budget or (limit["passes"] is not None and p >= limit["passes"]):
                shots[p] = (t, res.xyz.copy(), res.report, res.rgb, res.exposure)
            if limit["passes"] is None and t >= budget:
                raise Stop
            if limit["passes"] is not None and p >= limit["passes"]:
                raise Stop

        if snaps:                               # the second seed runs the first one's passes
            limit["passes"] = max(snaps[0].keys())
        try:
            render(c, seed=s, passes=max_passes, dev=dev, snapshot_every=1, on_snapshot=on_snapshot)
        except Stop:
            pass
        snaps.append(shots)
    common = sorted(set(snaps[0]) & set(snaps[1]))
    # skin pixels and exposure from a one-pass render's report (same for both seeds)
    rep0 = snaps[0][common[-1]][2]
    exposure = rep0["exposure"]
    from clppm.integrators import eyepass
    from clppm.scene import volume
    from clppm.compute.device import open_device
    dev = dev or open_device(None)
    vol = volume.build(c)
    eye = eyepass.run(dev, vol, volume.upload_volume(dev, vol), c, geometry=False)
    mask = skin_mask_from_eye(eye)
    rows = []
    for p in common:
        t1, x1, r1 = snaps[0][p][:3]
        t2, x2, r2 = snaps[1][p][:3]
        n = two_seed_noise(x1, x2, mask, exposure)
        secs = 0.5 * (t1 + t2)
        n.update(passes=p, seconds=secs, emitted=r1["photons_emitted"], stored=r1["photons_stored"],
                 eff_Y=1.0 / (n["noise_Y"] ** 2 * secs), eff_dE=1.0 / (n["noise_dE"] ** 2 * secs),
                 stage_seconds={k: r1["seconds"].get(k, 0.0) for k in STAGES})
        rows.append(n)
    last = rows[-1]
    log(f"    {last['passes']} passes, {last['seconds']:.1f} s: noise Y {100 * last['noise_Y']:.2f} %, "
        f"dE00 {last['noise_dE']:.2f}; {last['emitted'] / last['passes']:.0f} paths/pass; "
        f"efficiency Y {last['eff_Y']:.3g}/s, dE {last['eff_dE']:.3g}/s")
    return {"overrides": overrides, "rows": rows, "skin_pixels": int(mask.sum()),
            "stage_seconds": last["stage_seconds"], "_image": snaps[0][common[-1]][3:5]}


def plot(results: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.3))
    for key, r in results.items():
        xs = [row["seconds"] for row in r["rows"]]
        style = "--" if key.startswith("paper") else "-"
        axs[0].plot(xs, [100 * row["noise_Y"] for row in r["rows"]], style, marker="o", ms=3, label=key)
        axs[1].plot(xs, [row["noise_dE"] for row in r["rows"]], style, marker="o", ms=3, label=key)
    for ax, lab in zip(axs, ("noise of Y (% of mean skin Y)", "noise, mean CIEDE2000")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("render seconds (one image)")
        ax.set_ylabel(lab)
        ax.grid(True, which="both", alpha=0.3)
    axs[1].axhline(1.0, color="gray", lw=0.8)
    axs[1].axhline(2.0, color="gray", lw=0.8, ls=":")
    axs[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _kv(s: str):
    k, v = s.split("=", 1)
    try:
        v = json.loads(v)
    except json.JSONDecodeError:
        pass
    return k, v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--quick", action="store_true", help="80x60 only, 20 s per image")
    ap.add_argument("--resolutions", default=None, help="e.g. 80x60,320x240")
    ap.add_argument("--budget", type=float, help="render seconds per image (default 60 at 80x60, 300 at 320x240)")
    ap.add_argument("--modes", default="paper,default")
    ap.add_argument("--set", action="append", type=_kv, default=[], help="render key=value for an extra mode")
    ap.add_argument("--label", default="variant")
    ap.add_argument("--method", default="e")
    ap.add_argument("-o", "--out", default="out/bench")
    a = ap.parse_args(argv)
    from clppm.compute.device import open_device
    dev = open_device(None)
    cfg = C.load(a.config)
    cfg = C.override(cfg, "render", "method", a.method)
    cfg = C.override(cfg, "render", "checkpoint_every", 0)
    res_list = [tuple(int(v) for v in r.split("x")) for r in (a.resolutions or ("80x60" if a.quick else "80x60,320x240")).split(",")]
    modes = {}
    for m in a.modes.split(","):
        if m == "paper":
            modes["paper"] = dict(PAPER)
        elif m == "default":
            modes["default"] = {}
    if a.set:
        modes[a.label] = dict(a.set)
    results = {}
    t0 = time.perf_counter()
    print(f"bench/studies/noise.py on {dev.name}, method {a.method}")
    with volume.memoised():
        for res in res_list:
            c = C.override(cfg, "camera", "resolution", list(res))
            budget = a.budget or (20.0 if a.quick else (60.0 if res[0] <= 80 else 300.0))
            for name, ov in modes.items():
                print(f"  {name} {res[0]}x{res[1]} ({budget:g} s per image): {ov}")
                r = run_mode(c, ov, budget=budget, dev=dev)
                os.makedirs(a.out, exist_ok=True)
                image.write_png(os.path.join(a.out, f"noise-{name}-{res[0]}x{res[1]}.png"), *r.pop("_image"))
                results[f"{name} {res[0]}x{res[1]}"] = r
    os.makedirs(a.out, exist_ok=True)
    lines = ["| mode | resolution | passes | seconds | paths/pass | noise Y | noise ΔE00 | efficiency Y (1/s) | efficiency ΔE (1/s) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for key, r in results.items():
        name, resn = key.rsplit(" ", 1)
        row = r["rows"][-1]
        lines.append(f"| {name} | {resn} | {row['passes']} | {row['seconds']:.1f} | {row['emitted'] / row['passes']:,.0f} | "
                     f"{100 * row['noise_Y']:.2f} % | {row['noise_dE']:.2f} | {row['eff_Y']:.3g} | {row['eff_dE']:.3g} |")
    for resn in {k.rsplit(" ", 1)[1] for k in results}:
        if f"paper {resn}" in results and f"default {resn}" in results:
            p, d = results[f"paper {resn}"]["rows"][-1], results[f"default {resn}"]["rows"][-1]
            lines.append(f"\n{resn}: default / paper efficiency: Y {d['eff_Y'] / p['eff_Y']:.1f}x, "
                         f"ΔE00 {d['eff_dE'] / p['eff_dE']:.1f}x")
    md = "\n".join(lines)
    print(md)
    with open(os.path.join(a.out, "noise.md"), "w") as f:
        f.write(md + "\n")
    with open(os.path.join(a.out, "noise.json"), "w") as f:
        json.dump({"device": dev.info(), "config": a.config, "method": a.method, "results": results,
                   "wall_seconds": time.perf_counter() - t0}, f, indent=1, default=str)
    plot(results, os.path.join(a.out, "noise.png"))
    print(f"wrote {a.out}/noise.md, noise.json, noise.png ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
