"""Bias of every scheme against the path tracer, on the flat forearm (configs/forearm_flat.toml).

For each resolution, the reference is the unbiased path tracer (clppm.integrators.pathtracer) rendered at
1/10 of the resolution with jittered rays: each reference pixel is the exact mean of a 10x10
square of image pixels (clppm.analysis.reference).  Each scheme a-f renders in the paper's mode
(config.PAPER_MODE) and in the default mode, and is compared over the skin's 10x10 squares at
the paper's 200 passes (paper mode) or the config's default budget (default mode), and longer:
1000 paper passes (method e), 4x the default budget (method e).  Reported per run:

* Y per square: RMS and largest |Y / Y_pt - 1| over the skin squares,
* every 50-nm band group: the relative error of the mean skin radiance (and the largest),
* CIEDE2000 of the mean skin colour.

The reference's own noise (from its two halves) is printed beside.  ``--seeds N`` renders each
scheme N times: a row is then the mean image (the same bias, noise / sqrt(N)), with one image's
error and noise (seeds 1 and 2) and the bias per square with both noises removed beside it: at
320x240 one image's noise per square is larger than the 2 % the bias is held to.  Specular highlights are
switched off (the GGX term is the same deterministic function in both integrators, and would
only dilute the relative errors).  This is a long run (hours on 2 cores at 320x240): use
--methods / --resolutions / --modes to do part of it; results go to out/bench/bias.{json,md}.

    python bench/studies/bias.py --resolutions 80x60
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

from clppm import config as C
from clppm.scene import volume              # noqa: E402
from clppm.analysis.compare import MODES, render_seconds    # noqa: E402
from clppm.run.entry import render               # noqa: E402
from clppm.analysis.metrics import accuracy, accuracy_of_seeds, block_mean  # noqa: E402
from clppm.analysis.reference import RefSpec, get_reference  # noqa: E402

#: paths per 10x10 square in each half of the reference (noise ~ 1.6 / sqrt(2 paths))
REF_PATHS = {(80, 60): 1_500_000, (320, 240): 140_000}


def budgets(cfg: dict, mode: str, res: tuple, method: str, long: bool = True) -> list[int]:
    """Pass counts at which a run is measured: the mode's budget, and a longer ("converged") one."""
    if mode == "paper":
        return [200, 1000] if long and method == "e" else [200]
    p = int(cfg["render"]["passes"])
    return [p, 4 * p] if long and method == "e" else [p]


def relief_heights(cfg: dict, res: tuple, vol) -> np.ndarray | None:
    """Per pixel, the surface height under it: the mean of the relief over 4x4 rays through the
    pixel to the plane z = 0 (the relief is 20 um deep under a camera 40 mm away).  None on a
    flat surface."""
    from clppm.scene import camera
    if vol.iface[0, 3] < 0:
        return None
    cam = camera.from_config(cfg["camera"] | {"resolution": list(res)})
    w, h = res
    S, c = vol.smooth_samples(0)
    hs = S.astype(np.float64) + c
    sub = (np.arange(4) + 0.5) / 4
    hgt = np.zeros((h, w))
    for py in range(h):
        for px in range(w):
            acc = 0.0
            for fy in sub:
                for fx in sub:
                    d = cam.ray(px + fx, py + fy)
                    p = cam.position + d * (-cam.position[2] / d[2])
                    ix = int(np.clip((p[0] - vol.x0) / vol.dx, 0, vol.nx - 1))
                    iy = int(np.clip((p[1] - vol.y0) / vol.dy, 0, vol.ny - 1))
                    acc += hs[iy, ix]
            hgt[py, px] = acc / 16
    return hgt


def region_rows(imgs_full: list, ref, heights: np.ndarray) -> dict:
    """Mean Y over the furrow pixels (the lowest quarter of the surface heights under the skin
    squares' pixels) and the plateau pixels (the highest half) against the path tracer's
    full-resolution halves: relative error of the seeds' mean, with the reference's noise
    (halves) and one image's noise (seeds 1, 2) beside it."""
    b = ref.block
    skin = np.kron(ref.mask, np.ones((b, b), bool))
    lo, hi = np.quantile(heights[skin], [0.25, 0.5])
    out = {}
    for name, m in (("furrow", skin & (heights <= lo)), ("plateau", skin & (heights >= hi))):
        halves = [float(x[..., 1][m].mean()) for x in ref.pixels_xyz]
        pt_y = 0.5 * sum(halves)
        ys = [float(y[m].mean()) for y in imgs_full]
        out[name] = {"pixels": int(m.sum()), "error": float(np.mean(ys) / pt_y - 1),
                     "ref_noise": float(abs(halves[0] - halves[1]) / (2 * pt_y)),
                     "one_image_noise": float(abs(ys[0] - ys[1]) / (np.sqrt(2) * pt_y)) if len(ys) > 1 else None}
    return out


def run(cfg: dict, mode: str, method: str, res: tuple, ref, dev, log=print, long: bool = True,
        seeds: int = 1, regions: np.ndarray | None = None) -> dict:
    """Measure one scheme at its marks.  With ``seeds`` > 1 the scheme renders that many times
    (seeds 1, 2, ...): the row is the seed-mean image (the same bias, noise / sqrt(seeds)), and
    beside it the error of one image and its noise from the first two seeds."""
    c = cfg
    for k, v in MODES[mode].items():
        c = C.override(c, "render", k, v)
    marks = budgets(cfg, mode, res, method, long)
    imgs = {p: [] for p in marks}
    full = {p: [] for p in marks}
    secs = {p: [] for p in marks}

    def on_snapshot(p, wall, r):
        if p in marks:
            imgs[p].append((block_mean(r.xyz, ref.block), block_mean(r.spectral, ref.block)))
            full[p].append(r.xyz[..., 1].copy())
            secs[p].append(render_seconds(r.report))
            m = accuracy(r.xyz, r.spectral, ref)
            log(f"    {mode} {method} {p} passes ({secs[p][-1]:.0f} s): Y per square "
                f"{100 * m['block_Y_rms']:.2f} % RMS, {100 * m['block_Y_max']:.2f} % max; band groups "
                f"{100 * m['group_max']:.2f} % max; mean colour dE00 {m['de_mean']:.2f}")

    for s in range(1, seeds + 1):
        render(c, method=method, passes=max(marks), resolution=res, dev=dev, snapshot_every=min(marks),
               on_snapshot=on_snapshot, **({"seed": s} if seeds > 1 else {}))
    rows = [mark_row(p, imgs[p], secs[p], ref, log) for p in marks]
    if regions is not None and ref.pixels_xyz is not None:
        for p, row in zip(marks, rows):
            row["regions"] = region_rows(full[p], ref, regions)
            log(f"    {mode} {method} {p} passes, Y furrows / plateaus: " + ", ".join(
                f"{k} {100 * v['error']:+.2f} % (reference noise {100 * v['ref_noise']:.2f} %)"
                for k, v in row["regions"].items()))
    return {"mode": mode, "method": method, "seeds": seeds, "marks": rows}


def mark_row(p: int, imgs: list, secs: list, ref, log=print) -> dict:
    """A mark's row: :func:`clppm.analysis.metrics.accuracy_of_seeds` of its images, its seconds."""
    row = {"passes": p, "seconds": float(np.median(secs)), **accuracy_of_seeds(imgs, ref)}
    # where the error lies: Y / Y_pt - 1 of the (mean) image per square, NaN off the skin
    Y = np.mean([x[..., 1] for x, _ in imgs], 0)
    Yr = ref.xyz[..., 1]
    rel = np.where(ref.mask, Y / np.where(Yr > 0, Yr, np.nan) - 1, np.nan)
    row["Y_rel_per_square"] = np.round(rel, 5).tolist()
    if "bias_Y_rms" in row:
        log(f"    mean of {row['seeds']} seeds at {p} passes: Y per square {100 * row['block_Y_rms']:.2f} % RMS, "
            f"{100 * row['block_Y_max']:.2f} % max; one image {100 * row['noise_Y_rms']:.2f} % noise; bias "
            f"{100 * row['bias_Y_rms']:.2f} % RMS with the noises removed; {row['beyond']} of {row['squares']} squares "
            f"beyond {100 * row['bound']:.0f} % (noise alone: {row['beyond_noise']:.0f}), {row['beyond_sig']} by more "
            f"than {row['z']:.0f} standard errors")
    return row


def rings(rel: np.ndarray) -> dict:
    """Mean and RMS of a per-square error map (NaN off the skin) by ring: the outer ring of skin
    squares (at the open sides), the second, and the inside."""
    rel = np.asarray(rel, float)
    skin = np.isfinite(rel)
    rows, cols = np.nonzero(skin.any(1))[0], np.nonzero(skin.any(0))[0]
    i, j = np.indices(rel.shape)
    k = np.minimum(np.minimum(i - rows[0], rows[-1] - i), np.minimum(j - cols[0], cols[-1] - j))
    out = {}
    for name, m in (("outer", k == 0), ("second", k == 1), ("inside", k >= 2)):
        e = rel[m & skin]
        if e.size:
            out[name] = {"squares": int(e.size), "mean": float(e.mean()), "rms": float(np.sqrt((e * e).mean()))}
    return out


def markdown(res: tuple, ref, runs: list) -> str:
    groups = list(runs[0]["marks"][0]["groups"]) if runs else []
    many = any(m.get("seeds", 1) > 1 for r in runs for m in r["marks"])
    head = ("| mode | method | passes | seconds | Y per square, RMS | max | "
            + " | ".join(f"{g} nm" for g in groups) + " | mean colour ΔE00 |"
            + (" seeds | one image: RMS, max | one image's noise | bias RMS, noise removed | squares beyond 2 %: all (noise alone), shown |"
               if many else ""))
    lines = [f"{res[0]}x{res[1]}, 10x10-pixel squares, against the path tracer "
             f"(its own noise: Y {100 * ref.error['block_Y_rms']:.2f} % RMS per square, band groups "
             f"{100 * ref.error['group_max']:.2f} % max, mean colour ΔE00 {ref.error['de_mean']:.3f})."
             + (" With several seeds a row is the mean image of its seeds; a square's bias is shown beyond 2 % "
                "when its error exceeds 2 % by more than 3 standard errors (the seeds' and the reference's noise)."
                if many else ""), "",
             head, "|" + "---|" * (head.count("|") - 1)]
    for r in runs:
        for m in r["marks"]:
            line = (f"| {r['mode']} | {r['method']} | {m['passes']} | {m['seconds']:.0f} | "
                    f"{100 * m['block_Y_rms']:.2f} % | {100 * m['block_Y_max']:.2f} % | "
                    + " | ".join(f"{100 * m['groups'][g]:+.2f} %" for g in groups)
                    + f" | {m['de_mean']:.2f} |")
            if many:
                line += (f" {m.get('seeds', 1)} | " + (
                    f"{100 * m['one_Y_rms']:.2f} %, {100 * m['one_Y_max']:.2f} % | {100 * m['noise_Y_rms']:.2f} % | "
                    f"{100 * m['bias_Y_rms']:.2f} % | {m['beyond']} ({m['beyond_noise']:.0f}), {m['beyond_sig']} of {m['squares']} |"
                    if "noise_Y_rms" in m else " | | | |"))
            lines.append(line)
    lines.append("")
    for r in runs:
        for m in r["marks"]:
            g = rings(m["Y_rel_per_square"])
            lines.append(f"- {r['mode']} {r['method']}, {m['passes']} passes, Y per square by ring: "
                         + "; ".join(f"{k} ({v['squares']}) {100 * v['mean']:+.2f} % mean, {100 * v['rms']:.2f} % RMS"
                                     for k, v in g.items()))
            if "seed_Y_max" in m:
                lines.append(f"- {r['mode']} {r['method']}, {m['passes']} passes, worst square of each seed "
                             f"(1, 2, ...): " + ", ".join(f"{100 * v:.2f} %" for v in m["seed_Y_max"]))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm_flat.toml"))
    ap.add_argument("--resolutions", default="80x60,320x240")
    ap.add_argument("--methods", default="abcdef")
    ap.add_argument("--modes", default="default,paper")
    ap.add_argument("--no-long", action="store_true", help="only the modes' budgets, not the longer runs")
    ap.add_argument("--ref-paths", type=int, help="reference paths per 10x10 square and half")
    ap.add_argument("--seeds", type=int, default=1,
                    help="renders per scheme (seeds 1..N): rows of the mean image, one image's noise, the bias")
    ap.add_argument("--cache", default="out/cache")
    ap.add_argument("-o", "--out", default="out/bench")
    a = ap.parse_args(argv)
    from clppm.compute.device import open_device
    dev = open_device(None)
    cfg = C.load(a.config)
    cfg = C.override(cfg, "render", "specular", False)
    cfg = C.override(cfg, "render", "checkpoint_every", 0)
    t0 = time.perf_counter()
    doc, md = {"device": dev.info(), "config": a.config, "results": {}}, []
    os.makedirs(a.out, exist_ok=True)
    with volume.memoised():
        for rs in a.resolutions.split(","):
            res = tuple(int(v) for v in rs.split("x"))
            spec = RefSpec(integrator="pt", resolution=res, block=10, paths=a.ref_paths or REF_PATHS.get(res, 500_000))
            ref = get_reference(cfg, spec, a.cache, dev=dev, progress=True)
            regions = relief_heights(cfg, res, volume.build(cfg))
            runs = []
            for mode in a.modes.split(","):
                for m in a.methods:
                    runs.append(run(cfg, mode, m, res, ref, dev, long=not a.no_long, seeds=a.seeds,
                                    regions=regions))
                    doc["results"][rs] = {"reference": {"key": ref.key, "error": ref.error, "info": ref.info},
                                          "runs": runs}
                    with open(os.path.join(a.out, "bias.json"), "w") as f:
                        json.dump(doc, f, indent=1, default=str)
            md.append(markdown(res, ref, runs))
            with open(os.path.join(a.out, f"bias-{rs}.md"), "w") as f:
                f.write(md[-1] + "\n")
            with open(os.path.join(a.out, "bias.md"), "w") as f:
                f.write("\n\n".join(md) + "\n")
    print("\n\n".join(md))
    print(f"wrote {a.out}/bias.md, bias.json ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
