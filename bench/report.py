"""Every measured table, chart and image of the README and docs/, regenerated from the code as it is.

Each figure is a named job: it runs clppm's command line or a script of bench/ as a subprocess
(never clppm's internals, so that a reorganised package cannot break it), leaves its files under
out/report/JOB/ and returns Markdown blocks and images.  The blocks replace what stands between
``<!-- report:NAME -->`` and ``<!-- /report:NAME -->`` in README.md and docs/*.md; each block and
each PNG's text metadata (key ``Stamp``) carries a stamp: the command, the CPU, the OpenCL
implementation and version of the device used, the clppm commit (``+dirty`` with uncommitted
changes), the date.  A finished job's result is kept in out/report/JOB/result.json, so that an
interrupted run resumes where it stopped (``--fresh`` starts over); pages and images are written
whole (temp file, then rename).

    python bench/report.py --quick            # smaller sizes, fewer seeds (about 20 minutes on 2 cores)
    python bench/report.py                    # the docs' sizes (about 50 minutes on 2 cores, references cached)
    python bench/report.py --only readme,speed --device 1:0
    python bench/report.py --list
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import re
import shlex
import shutil
import struct
import subprocess
import sys
import time
import zlib
from dataclasses import dataclass, field
from typing import Callable

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "out", "report")
CACHE = os.path.join(ROOT, "out", "cache")         # path-tracer references, shared with clppm compare
IMG = os.path.join(ROOT, "docs", "img")
MARK = re.compile(r"(<!-- report:([\w-]+) -->\n)(.*?)(<!-- /report:\2 -->)", re.S)
STAMP_KEY = "Stamp"


# ----------------------------------------------------------------------------- context, stamp
@dataclass
class Device:
    """The OpenCL device every job runs on (as ``clppm devices --json`` names it)."""
    spec: str
    name: str
    platform: str
    implementation: str
    driver: str
    version: str


@dataclass
class Context:
    quick: bool
    device: Device
    cpu: str
    commit: str
    python: str = sys.executable

    def env(self) -> dict:
        """The subprocesses' environment: this checkout first on the path, the chosen device."""
        e = dict(os.environ, PYOPENCL_CTX=self.device.spec, PYTHONPATH=ROOT + os.pathsep
                 + os.environ.get("PYTHONPATH", ""), MPLBACKEND="Agg")
        return e

    def clppm(self, *args: str) -> list[str]:
        return [self.python, "-m", "clppm.cli", *args, "--device", self.device.spec]

    def script(self, path: str, *args: str) -> list[str]:
        return [self.python, os.path.join(ROOT, path), *args]


@dataclass
class Result:
    """What a job made: Markdown per marker name, images (made file -> docs path), the commands."""
    blocks: dict[str, str] = field(default_factory=dict)
    images: dict[str, str] = field(default_factory=dict)
    commands: list[str] = field(default_factory=list)
    seconds: float = 0.0
    stamp: str = ""


@dataclass
class Job:
    name: str
    what: str
    run: Callable[[Context, "Runner"], Result]


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo; platform.processor() elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform
    return platform.processor() or "unknown CPU"


def git_commit() -> str:
    """``git rev-parse --short HEAD``, with ``+dirty`` when tracked files have changes."""
    def git(*a):
        return subprocess.run(["git", "-C", ROOT, *a], capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def pick_device(spec: str | None, python: str) -> Device:
    """The device ``spec`` names, else the one clppm would choose (a GPU, else Intel, else PoCL)."""
    r = subprocess.run([python, "-m", "clppm.cli", "devices", "--json"], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")))
    if r.returncode != 0:
        raise SystemExit(f"report: `clppm devices --json` failed: {r.stderr.strip().splitlines()[-1:]}")
    devs = [d for d in json.loads(r.stdout) if d.get("usable")]
    if spec:
        devs = [d for d in devs if d["spec"] == spec]
    else:
        rank = lambda d: (0 if "GPU" in d["type"] else 1, {"intel": 0, "pocl": 1}.get(d["implementation"], 2))
        devs.sort(key=rank)
    if not devs:
        raise SystemExit(f"report: no usable OpenCL device {spec or ''}".rstrip())
    d = devs[0]
    return Device(d["spec"], d["name"].strip(), d["platform"].strip(), d["implementation"],
                  d["driver_version"].strip(), d["version"].strip())


def stamp_text(ctx: Context, job: str, day: str) -> str:
    """The line under every block and in every PNG: what made it, where, from which code."""
    d = ctx.device
    cmd = f"python bench/report.py --only {job}" + (" --quick" if ctx.quick else "") + f" --device {d.spec}"
    size = " (quick: smaller sizes, fewer seeds)" if ctx.quick else ""
    return (f"*Made by `{cmd}`{size} on {ctx.cpu} with {d.platform} {d.driver} ({d.version}, {d.name}), "
            f"clppm {ctx.commit}, {day}.*")


# ----------------------------------------------------------------------------- running commands
class Runner:
    """Runs a job's commands, logging each to stderr and to the job's folder."""

    def __init__(self, ctx: Context, job: str):
        self.ctx, self.job = ctx, job
        self.dir = os.path.join(OUT, job)
        self.commands: list[str] = []
        os.makedirs(self.dir, exist_ok=True)

    def path(self, name: str) -> str:
        return os.path.join(self.dir, name)

    def __call__(self, cmd: list[str]) -> str:
        shown = " ".join(shlex.quote(os.path.relpath(c, ROOT) if c.startswith(ROOT) else c)
                         for c in cmd).replace(shlex.quote(self.ctx.python), "python")
        self.commands.append(shown)
        log(f"[{self.job}] $ {shown}")
        r = subprocess.run(cmd, cwd=ROOT, env=self.ctx.env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True)
        with open(self.path("log.txt"), "a") as f:
            f.write(f"$ {shown}\n{r.stdout}\n")
        if r.returncode != 0:
            raise RuntimeError(f"exit {r.returncode}: {shown} (log: {os.path.relpath(self.path('log.txt'), ROOT)})")
        return r.stdout

    def render(self, name: str, config: str, *args: str) -> tuple[dict, float]:
        """``clppm render`` to NAME.exr (replacing an earlier set); its run report and the
        command's wall-clock seconds.  A render made by the same command before (NAME.cmd.json,
        which records its seconds and the commit too) is kept, so that redoing a job's figure is
        cheap; a render of other code is made again."""
        exr = self.path(f"{name}.exr")
        cmd = self.ctx.clppm("render", config, "-o", exr, "--force", "-q", *args)
        done = self.path(f"{name}.cmd.json")
        wall = _kept_wall(done, cmd, self.ctx.commit) if os.path.isfile(self.path(f"{name}.json")) else None
        if wall is not None:
            self.commands.append(" ".join(["python", *cmd[1:]]) + "   (done before, kept)")
        else:
            t0 = time.perf_counter()
            self(cmd)
            wall = time.perf_counter() - t0
            write_atomic(done, json.dumps({"args": cmd[2:], "wall_s": wall, "commit": self.ctx.commit}))
        with open(self.path(f"{name}.json")) as f:
            return json.load(f), wall


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- figures
def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def side_by_side(pngs: list[str], labels: list[str], path: str, cols: int | None = None) -> None:
    """PNG images in one row (or ``cols`` columns), each with its label, pixels not resampled."""
    plt = _plt()
    imgs = [plt.imread(p) for p in pngs]
    cols = cols or len(imgs)
    rows = (len(imgs) + cols - 1) // cols
    h, w = imgs[0].shape[:2]
    scale = max(1.0, 240 / h)                       # small renders shown at least 240 px high
    fig, axs = plt.subplots(rows, cols, figsize=(cols * w * scale / 100, rows * (h * scale + 24) / 100),
                            dpi=100, squeeze=False)
    for ax in axs.flat:
        ax.axis("off")
    for ax, im, lab in zip(axs.flat, imgs, labels):
        ax.imshow(im, interpolation="nearest")
        ax.set_title(lab, fontsize=9)
    fig.tight_layout(pad=0.3)
    fig.savefig(path, bbox_inches="tight", pad_inches=0.08)
    plt.close(fig)


def md_table(header: list[str], rows: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
                     + ["| " + " | ".join(r) + " |" for r in rows])


def img_md(alt: str, dest: str, page_dir: str = "docs") -> str:
    return f"![{alt}]({os.path.relpath(os.path.join(ROOT, dest), os.path.join(ROOT, page_dir))})"


def minsec(s: float) -> str:
    m, s = divmod(round(s), 60)
    return f"{m} min {s} s" if m else f"{s} s"


# ----------------------------------------------------------------------------- jobs
def readme_args(ctx: Context) -> list[str]:
    """The README's first command's render (quick: a quarter of the pixels, 2 passes)."""
    return ["--resolution", "160x120", "--passes", "2"] if ctx.quick else []


def job_readme(ctx: Context, run: Runner) -> Result:
    """The README's picture and its command's time: the default render of configs/forearm.toml."""
    rep, wall = run.render("forearm", os.path.join(ROOT, "configs", "forearm.toml"), *readme_args(ctx))
    s = rep["seconds"]
    res = "x".join(str(v) for v in rep["config"]["camera"]["resolution"])
    size = f"{res}, {rep['passes_done']} passes" + (" (the quick report's size)" if ctx.quick else "")
    d = ctx.device
    rest = wall - s["photon"] - s["gather"]
    time_md = (f"It took {minsec(wall)} ({size}) on {ctx.cpu} under {d.platform} {d.driver} "
               f"(photon passes {s['photon']:.0f} s, gather {s['gather']:.0f} s, the rest {rest:.0f} s), "
               "and wrote `out/forearm.exr`, `.png` (the picture above), `.json` and `.ckpt.npz`.")
    rows = [[k, f"{s.get(k, 0.0):.1f}", f"{100 * s.get(k, 0.0) / s['total']:.0f} %"]
            for k in ("photon", "grid", "gather", "volume", "eye", "calibration")]
    rows.append(["total", f"{s['total']:.1f}", "100 %"])
    split = (md_table(["stage", "seconds", "share"], rows)
             + f"\n\n{size}, method {rep['method']}, {rep['stored_per_pass']:,} stored photons per pass, "
             f"{rep['gather_pairs']:,} gather pairs, {rep['sample_points']:,} sample points.")
    return Result(blocks={"readme-picture": img_md("forearm, default mode, method e", "docs/forearm.png", "."),
                          "readme-time": time_md, "time-split": split},
                  images={run.path("forearm.png"): "docs/forearm.png"})


def job_scenes(ctx: Context, run: Runner) -> Result:
    """Forearm and cheek side by side at the README render's size and budget (the forearm is the
    readme job's render when that is done in this mode)."""
    pngs = []
    for scene in ("forearm", "cheek"):
        kept = os.path.join(OUT, "readme", "forearm.png")
        if scene == "forearm" and load_result(ctx, "readme") is not None and os.path.isfile(kept):
            pngs.append(kept)
            continue
        run.render(scene, scene, *readme_args(ctx))
        pngs.append(run.path(f"{scene}.png"))
    side_by_side(pngs, ["forearm", "cheek"], run.path("scenes.png"))
    return Result(blocks={"scenes": img_md("forearm and cheek, default mode, method e", "docs/img/scenes.png")},
                  images={run.path("scenes.png"): "docs/img/scenes.png"})


def job_freckles(ctx: Context, run: Runner) -> Result:
    """The shipped example of chromophore maps and inclusions (configs/forearm_freckles.toml: a
    vein and five freckles) beside the same flat forearm without them, at the README render's
    size and budget."""
    pngs = []
    for scene in ("forearm_flat", "forearm_freckles"):
        rep, _ = run.render(scene, os.path.join(ROOT, "configs", f"{scene}.toml"), *readme_args(ctx))
        pngs.append(run.path(f"{scene}.png"))
    side_by_side(pngs, ["forearm_flat", "forearm_freckles: a vein, five freckles"], run.path("freckles.png"))
    res = "x".join(str(v) for v in rep["config"]["camera"]["resolution"])
    note = (f"Both {res}, default mode, {rep['passes_done']} passes; the maps' render traces one band "
            f"per photon path ({rep['stored_per_pass']:,} stored photons per pass), the plain one carries 9.")
    return Result(blocks={"freckles": img_md("the flat forearm, and with a vein and five freckles",
                                             "docs/img/freckles.png") + "\n\n" + note},
                  images={run.path("freckles.png"): "docs/img/freckles.png"})


def ref_paths(ctx: Context) -> str:
    """Path-tracer reference paths per 10x10-pixel square and half, shared by speed and bias
    (computed once into out/cache: the full run's takes about half an hour on 2 cores)."""
    return "2000" if ctx.quick else "60000"


def relief_config() -> str:
    """configs/forearm.toml with the specular highlight off (the same GGX term in both integrators,
    it only dilutes relative errors), so that clppm compare and bench/studies/bias.py share one
    path-tracer reference."""
    with open(os.path.join(ROOT, "configs", "forearm.toml")) as f:
        text = f.read()
    assert "\nspecular = true" in text, "configs/forearm.toml: no `specular = true` line to switch off"
    path = os.path.join(OUT, "forearm-nohighlight.toml")
    os.makedirs(OUT, exist_ok=True)
    write_atomic(path, text.replace("\nspecular = true", "\nspecular = false", 1))
    return path


def compare_args(ctx: Context) -> list[str]:
    """clppm compare on the relief forearm at 80x60 (quick: 6 s per run, paper mode for e only)."""
    if ctx.quick:
        return ["--budget", "6", "--paper-methods", "e", "--ref-paths", ref_paths(ctx), "--no-shift"]
    return ["--budget", "40", "--ref-paths", ref_paths(ctx), "--no-shift"]


def compare_run(ctx: Context, run: Runner) -> tuple[str, dict]:
    """Runs ``clppm compare`` once for every job that needs it (kept under out/report/compare/)."""
    d = os.path.join(OUT, "compare")
    done = os.path.join(d, "compare.json")
    cmd = ctx.clppm("compare", relief_config(), "-o", d, "--cache", CACHE, "-q", *compare_args(ctx))
    if not (os.path.isfile(done) and _same_args(os.path.join(d, "args.json"), cmd, ctx.commit)):
        run(cmd)
        write_atomic(os.path.join(d, "args.json"), json.dumps({"args": cmd[2:], "commit": ctx.commit}))
    else:
        run.commands.append(" ".join(["python", *cmd[1:]]) + "   (done before, kept)")
    with open(done) as f:
        return d, json.load(f)


def _kept_wall(path: str, cmd: list[str], commit: str) -> float | None:
    """The wall-clock seconds of the render ``path`` records, if it records the same command
    run by the same commit."""
    try:
        with open(path) as f:
            doc = json.load(f)
    except (OSError, json.JSONDecodeError):
        return None
    if (not isinstance(doc, dict) or doc.get("args") != cmd[2:] or doc.get("commit") != commit
            or not isinstance(doc.get("wall_s"), (int, float))):
        return None
    return float(doc["wall_s"])


def _same_args(path: str, cmd: list[str], commit: str) -> bool:
    """Whether ``path`` records the same command (its arguments after the interpreter) run by
    the same commit."""
    try:
        with open(path) as f:
            return json.load(f) == {"args": cmd[2:], "commit": commit}
    except (OSError, json.JSONDecodeError):
        return False


def _runs(doc: dict) -> list[dict]:
    """compare.json's runs, each with its mode, method and final figures."""
    return doc.get("runs", [])


def job_methods(ctx: Context, run: Runner) -> Result:
    """The six methods a-f side by side, default mode, each after the same render seconds."""
    d, doc = compare_run(ctx, run)
    names = [f"{m}-default" for m in "abcdef"]
    pngs = [_image(d, n) for n in names]
    side_by_side(pngs, [f"method {m}" for m in "abcdef"], run.path("methods.png"), cols=3)
    return Result(blocks={"methods": img_md("methods a-f at equal time", "docs/img/methods.png")},
                  images={run.path("methods.png"): "docs/img/methods.png"})


def _image(d: str, name: str) -> str:
    """A compare run's final image (images/NAME.png; names differ by mode and method)."""
    imgs = os.path.join(d, "images")
    for cand in os.listdir(imgs):
        stem = cand[:-4].lower()
        mode, method = name.split("-")[1], name.split("-")[0]
        if cand.endswith(".png") and mode in stem and re.search(rf"(^|[^a-z]){method}([^a-z]|$)", stem):
            return os.path.join(imgs, cand)
    raise RuntimeError(f"compare wrote no image for {name} in {imgs}: {sorted(os.listdir(imgs))}")


def job_modes(ctx: Context, run: Runner) -> Result:
    """The default mode against the paper's, method e, after the same render seconds, and the path tracer."""
    d, _ = compare_run(ctx, run)
    pngs = [_image(d, "e-default"), _image(d, "e-paper"), os.path.join(d, "images", "reference.png")]
    side_by_side(pngs, ["default, method e", "paper mode, method e", "path tracer (reference)"],
                 run.path("modes.png"))
    return Result(blocks={"modes": img_md("default against paper mode at equal time", "docs/img/modes.png")},
                  images={run.path("modes.png"): "docs/img/modes.png"})


def job_speed(ctx: Context, run: Runner) -> Result:
    """Error against render seconds on the relief forearm at 80x60 (clppm compare's chart and table)."""
    d, _ = compare_run(ctx, run)
    with open(os.path.join(d, "compare.md")) as f:
        md = f.read()
    table = _first_table(md, "Y per square")
    return Result(blocks={"speed": img_md("error against render seconds, log-log", "docs/img/speed.png")
                          + "\n\n" + table},
                  images={os.path.join(d, "compare.png"): "docs/img/speed.png"})


def _first_table(md: str, must: str) -> str:
    """The first Markdown table in ``md`` whose header holds ``must``."""
    for t in re.findall(r"((?:^\|.*\|\n?)+)", md, re.M):
        if must in t.splitlines()[0]:
            return t.strip()
    raise RuntimeError(f"no table with '{must}' in the output")


def bias_args(ctx: Context) -> list[str]:
    return ["--resolutions", "80x60", "--methods", "e", "--modes", "default", "--no-long",
            "--seeds", "2" if ctx.quick else "8", "--ref-paths", ref_paths(ctx)]


def job_bias(ctx: Context, run: Runner) -> Result:
    """The default's bias against the path tracer per 10x10-pixel square on the relief forearm."""
    run(ctx.script("bench/studies/bias.py", relief_config(), *bias_args(ctx),
                   "--cache", CACHE, "-o", run.dir))
    with open(run.path("bias.json")) as f:
        doc = json.load(f)
    row = doc["results"]["80x60"]["runs"][0]["marks"][-1]
    bias_map(row, run.path("bias.png"))
    with open(run.path("bias.md")) as f:
        table = f.read().strip()               # the reference's own noise, then the table
    return Result(blocks={"bias": img_md("relative error of Y per 10x10-pixel square", "docs/img/bias.png")
                          + "\n\n" + table},
                  images={run.path("bias.png"): "docs/img/bias.png"})


def bias_map(row: dict, path: str) -> None:
    """Y / Y_pt - 1 per square as a diverging colour map, the value written in each square."""
    import numpy as np
    plt = _plt()
    rel = 100 * np.array(row["Y_rel_per_square"], dtype=float)
    lim = max(2.0, float(np.nanmax(np.abs(rel))))
    fig, ax = plt.subplots(figsize=(6.4, 5.0), dpi=100)
    im = ax.imshow(rel, cmap="RdBu_r", vmin=-lim, vmax=lim)
    for (i, j), v in np.ndenumerate(rel):
        if np.isfinite(v):
            ax.text(j, i, f"{v:+.1f}", ha="center", va="center", fontsize=7)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f"Y / Y(path tracer) - 1 per 10x10-pixel square, %  ({row['seeds']} seeds, {row['passes']} passes)",
                 fontsize=9)
    fig.colorbar(im, ax=ax, shrink=0.8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def job_reflectance(ctx: Context, run: Runner) -> Result:
    """The forearm's R(lambda) from the photon pass over the NIST volar-forearm band."""
    photons = "1000" if ctx.quick else "5000"
    run(ctx.clppm("reflectance", "forearm", "--photons", photons, "--json", run.path("reflectance.json"),
                  "--plot", run.path("reflectance.png"), "-q"))
    with open(run.path("reflectance.json")) as f:
        doc = json.load(f)
    return Result(blocks={"reflectance": img_md("R(lambda) against the NIST forearm band", "docs/img/reflectance.png")
                          + "\n\n" + reflectance_table(doc)},
                  images={run.path("reflectance.png"): "docs/img/reflectance.png"})


def reflectance_table(doc: dict) -> str:
    """R at the quoted wavelengths beside the NIST median and 5-95 % band, and the summary."""
    import numpy as np
    pp = doc["photon_pass"]
    wl, R, se = (np.asarray(pp[k], dtype=float) for k in ("wavelength_nm", "R", "R_se"))
    nist = doc.get("nist") or {}
    at = nist.get("at_nm", {})
    q = [k for k in at if at[k].get("median") is not None] or ["450", "550", "650", "700"]
    rows = [["forearm model R (± standard error)"]
            + [f"{np.interp(float(w), wl, R):.3f} ± {np.interp(float(w), wl, se):.3f}" for w in q]]
    if at:
        rows.append(["NIST median (5-95 %)"] + [f"{at[w]['median']:.3f} ({at[w]['p5']:.3f}-{at[w]['p95']:.3f})"
                                               for w in q])
    text = md_table([""] + [f"{w} nm" for w in q], rows)
    if nist:
        inside = nist["inside_5_95"]
        text += (f"\n\nInside the NIST 5-95 % band over {inside['range_nm'][0]:g}-{inside['range_nm'][1]:g} nm: "
                 f"{'yes' if inside['inside'] else 'no'}. Against the median: spectral RMSE "
                 f"{nist['rmse_median']:.3f}, ΔE00 {nist['delta_e2000_median']:.1f}; nearest subject "
                 f"{nist['nearest_subject']} (RMSE {nist['rmse_nearest']:.3f}).")
    return text


def devices_args(ctx: Context) -> list[str]:
    """Quick: the report's device alone, one repetition; the full run: every device, best of 3."""
    if ctx.quick:
        return ["--repeat", "1", "--only", f"{ctx.device.implementation} {ctx.device.name}"]
    return ["--repeat", "3"]


def job_devices(ctx: Context, run: Runner) -> Result:
    """Every device's throughput (bench/devices.py) as a chart and its table."""
    run(ctx.script("bench/devices.py", *devices_args(ctx), "--out", run.dir))
    with open(run.path("devices.json")) as f:
        rows = json.load(f)
    devices_chart(rows, run.path("devices.png"))
    with open(run.path("devices.md")) as f:
        table = _first_table(f.read(), "device")
    return Result(blocks={"devices": img_md("throughput per device", "docs/img/devices.png") + "\n\n" + table},
                  images={run.path("devices.png"): "docs/img/devices.png"})


def devices_chart(rows: list[dict], path: str) -> None:
    """Bars per device: photon pass, gather and path tracer throughput, and a small render's s/pass."""
    plt = _plt()
    keys = [("photon_forearm", "photons/s, forearm"), ("render_pairs_s", "render gather pairs/s"),
            ("pt_paths_s", "path tracer paths/s"), ("render_s_per_pass", "small render, s/pass (lower is better)")]
    labels = [_device_label(r) for r in rows]
    fig, axs = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 0.5 * len(rows) + 1.6), dpi=100)
    for ax, (k, title) in zip(axs, keys):
        vals = [float(r.get(k) or 0.0) for r in rows]
        ax.barh(range(len(rows)), vals, color="#4878a8")
        ax.set_yticks(range(len(rows)))
        ax.set_yticklabels(labels if ax is axs[0] else [""] * len(rows), fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.invert_yaxis()
        ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _device_label(r: dict) -> str:
    d = r.get("device", {})
    if isinstance(d, dict):
        return f"{d.get('implementation', '')} {d.get('driver_version', '')}".strip()
    return str(d)[:30]


def noise_args(ctx: Context) -> list[str]:
    return ["--quick", "--budget", "8"] if ctx.quick else ["--resolutions", "80x60", "--budget", "60"]


def job_noise(ctx: Context, run: Runner) -> Result:
    """One image's noise against render seconds, default and paper mode (two seeds)."""
    run(ctx.script("bench/studies/noise.py", os.path.join(ROOT, "configs", "forearm.toml"), *noise_args(ctx),
                   "-o", run.dir))
    with open(run.path("noise.md")) as f:
        table = f.read().strip()               # the table, then default / paper efficiency
    return Result(blocks={"noise": img_md("noise against render seconds", "docs/img/noise.png") + "\n\n" + table},
                  images={run.path("noise.png"): "docs/img/noise.png"})


@dataclass
class Case:
    """A validation case: a shipped config traced by the photon pass, against a published value."""
    config: str
    what: str
    quantity: str           # the run's JSON key: Rd, Tt
    reference: float
    source: str


CASES = [
    Case("slab_mcml", "slab μa 10, μs 90 per cm, g 0.75, 0.2 mm, n 1", "Rd", 0.09739, "van de Hulst, MCML"),
    Case("slab_mcml", "slab μa 10, μs 90 per cm, g 0.75, 0.2 mm, n 1", "Tt", 0.66096, "van de Hulst, MCML"),
    Case("slab_semi_infinite", "semi-infinite μa 1, μs 100, g 0.9, n 1.4", "Rd", 0.25238, "adding-doubling"),
]


def job_validation(ctx: Context, run: Runner) -> Result:
    """The photon pass against published slab values (clppm trace)."""
    photons = "200000" if ctx.quick else "1000000"
    docs = {}
    for config in sorted({c.config for c in CASES}):
        run(ctx.clppm("trace", config, "--photons", photons, "--json", run.path(f"{config}.json"), "-q"))
        with open(run.path(f"{config}.json")) as f:
            docs[config] = json.load(f)
    rows = []
    for c in CASES:
        d = docs[c.config]
        v, se = d[c.quantity], d[f"{c.quantity}_se"]
        rows.append([f"`{c.config}`: {c.what}", c.quantity, f"{v:.5f} ± {se:.5f}", f"{c.reference:.5f} ({c.source})",
                     f"{(v - c.reference) / se:+.1f}" if se > 0 else "–"])
    table = md_table(["case", "", "clppm", "reference", "difference / standard error"], rows)
    return Result(blocks={"validation": table + f"\n\n{int(photons):,} photons per case."})


PAPER_ROW = re.compile(r"^\s+(.+?)\s+([\d.]+)\s+paper\s+([\d.]+)", re.M)


def job_samples(ctx: Context, run: Runner) -> Result:
    """The paper's Table 1: sample points per eye ray per layer, methods a-f, beside the paper's."""
    size = ["--resolution", "160x120"] if ctx.quick else []
    rows, layers = [], []
    for m in "abcdef":
        out = run(ctx.clppm("samples", "forearm", "--method", m, *size))
        cells = PAPER_ROW.findall(out)
        if not cells:
            raise RuntimeError(f"clppm samples --method {m} printed no layer beside the paper's")
        layers = [c[0] for c in cells]
        rows.append([f"{m}) {SCHEME[m]}"] + [f"{float(v):.2f} ({float(p):.2f})" for _, v, p in cells])
    res = "160x120" if ctx.quick else "320x240"
    return Result(blocks={"samples": md_table(["method"] + layers, rows)
                          + f"\n\nMean sample points per eye ray on the skin, {res} rays; the paper's value in parentheses."})


SCHEME = {"a": "4 µm", "b": "7 µm", "c": "14 µm", "d": "max", "e": "mean", "f": "min"}


def job_surface(ctx: Context, run: Runner) -> Result:
    """The smooth walk against the voxel staircase: the tilted plane, memory, photon-pass cost."""
    photons = "30000" if ctx.quick else "100000"
    run(ctx.script("bench/surface.py", "--photons", photons, "--json", run.path("surface.json")))
    with open(run.path("surface.json")) as f:
        doc = json.load(f)
    rows = [[f"{r['slope']:g}", f"{r['incidence_deg']:g}°", f"{r['slab'][0]:.4f}",
             f"{r['smooth'][0]:.4f} ({r['smooth'][2]:+.1f} SE)", f"{r['voxels'][0]:.4f} ({r['voxels'][2]:+.1f} SE)"]
            for r in doc["tilted"]]
    tilted = md_table(["slope", "incidence", "flat slab Rd", "smooth walk Rd", "voxel walk Rd"], rows)
    f = doc["forearm"]
    steps = ("steps", "collisions", "interface", "wall", "zone", "tile")
    cost = md_table(["forearm", "voxel walk", "smooth walk"],
                    [["photon pass, µs per emitted photon (median)", f"{f['voxels']['median_us']:.2f}",
                      f"{f['smooth']['median_us']:.2f} ({f['smooth']['median_us'] / f['voxels']['median_us']:.2f}×)"],
                     ["device memory of the volume", f"{f['voxels']['device_bytes'] / 1e6:.0f} MB",
                      f"{f['smooth']['device_bytes'] / 1e6:.0f} MB"]]
                    + [[f"loop steps per photon: {k}", f"{f['voxels']['per_photon'][k]:.1f}",
                        f"{f['smooth']['per_photon'][k]:.1f}"] for k in steps])
    return Result(blocks={"surface-tilted": tilted, "surface-cost": cost})


JOBS = [
    Job("readme", "the README's picture and its first command's time; the render's time split", job_readme),
    Job("scenes", "forearm and cheek side by side", job_scenes),
    Job("freckles", "the shipped example of maps and inclusions beside the plain flat forearm", job_freckles),
    Job("methods", "the six methods a-f at equal render time", job_methods),
    Job("modes", "the default against paper mode at equal time, and the path tracer", job_modes),
    Job("speed", "error against render seconds on the relief forearm at 80x60", job_speed),
    Job("bias", "the default's bias per 10x10-pixel square against the path tracer", job_bias),
    Job("samples", "the paper's Table 1: sample points per eye ray per layer", job_samples),
    Job("reflectance", "R(lambda) inside the NIST forearm band", job_reflectance),
    Job("validation", "the photon pass against published slab values", job_validation),
    Job("noise", "one image's noise against time, default and paper mode", job_noise),
    Job("devices", "every device's throughput, chart and table", job_devices),
    Job("surface", "the smooth walk against the voxel staircase: tilted plane, memory, photon-pass cost", job_surface),
]


# ----------------------------------------------------------------------------- results and pages
def result_path(job: str) -> str:
    return os.path.join(OUT, job, "result.json")


def load_result(ctx: Context, job: str) -> Result | None:
    """A finished job's result, when it was made in this mode on this device."""
    try:
        with open(result_path(job)) as f:
            doc = json.load(f)
    except (OSError, json.JSONDecodeError):
        return None
    if doc.get("quick") != ctx.quick or doc.get("device") != ctx.device.spec:
        return None
    return Result(**doc["result"])


def save_result(ctx: Context, job: str, res: Result) -> None:
    doc = {"quick": ctx.quick, "device": ctx.device.spec, "result": dataclasses.asdict(res)}
    write_atomic(result_path(job), json.dumps(doc, indent=1))


def write_atomic(path: str, text: str) -> None:
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def png_with_stamp(src: str, dest: str, stamp: str, commands: list[str]) -> None:
    """Copies a PNG, adding the stamp and the commands as text chunks (written whole, then renamed)."""
    with open(src, "rb") as f:
        data = f.read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", src
    chunks = [text_chunk(STAMP_KEY, stamp.strip("*")), text_chunk("Commands", "\n".join(commands))]
    end = data.rfind(b"IEND") - 4                    # before the IEND chunk's length field
    os.makedirs(os.path.dirname(dest), exist_ok=True)
    tmp = f"{dest}.{os.getpid()}.tmp"
    with open(tmp, "wb") as f:
        f.write(data[:end] + b"".join(chunks) + data[end:])
    os.replace(tmp, dest)


def text_chunk(key: str, text: str) -> bytes:
    """A PNG iTXt chunk (UTF-8 text, uncompressed)."""
    body = key.encode("latin-1") + b"\0\0\0\0\0" + text.encode("utf-8")
    return struct.pack(">I", len(body)) + b"iTXt" + body + struct.pack(">I", zlib.crc32(b"iTXt" + body))


def pages() -> list[str]:
    docs = os.path.join(ROOT, "docs")
    return [os.path.join(ROOT, "README.md")] + sorted(
        os.path.join(docs, p) for p in os.listdir(docs) if p.endswith(".md"))


def apply(results: dict[str, Result]) -> list[str]:
    """Writes every result's images and replaces its blocks in the pages; the blocks found nowhere."""
    blocks = {}
    for job, res in results.items():
        for name, md in res.blocks.items():
            blocks[name] = md.rstrip() + "\n\n" + res.stamp + "\n"
        for src, dest in res.images.items():
            png_with_stamp(src, os.path.join(ROOT, dest), res.stamp, res.commands)
    seen = set()
    for page in pages():
        with open(page) as f:
            text = f.read()

        def sub(m):
            seen.add(m.group(2))
            return m.group(1) + blocks[m.group(2)] + m.group(4) if m.group(2) in blocks else m.group(0)
        new = MARK.sub(sub, text)
        if new != text:
            write_atomic(page, new)
            log(f"report: updated {os.path.relpath(page, ROOT)}")
    return sorted(set(blocks) - seen)


# ----------------------------------------------------------------------------- main
def parse(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes and fewer seeds (about 20 minutes on 2 cores)")
    ap.add_argument("--only", help="comma list of jobs (see --list)")
    ap.add_argument("--list", action="store_true", help="list the jobs and exit")
    ap.add_argument("--device", help="OpenCL device P:D as `clppm devices` lists (default: clppm's choice)")
    ap.add_argument("--fresh", action="store_true", help="rerun jobs even when a result is kept")
    a = ap.parse_args(argv)
    if a.device and not re.fullmatch(r"\d+:\d+", a.device):
        ap.exit(2, f"report: --device takes P:D as `clppm devices` lists, not {a.device!r}\n")
    names = [j.name for j in JOBS]
    a.jobs = names if not a.only else [s.strip() for s in a.only.split(",") if s.strip()]
    unknown = [n for n in a.jobs if n not in names]
    if unknown:
        ap.exit(2, f"report: unknown job {', '.join(unknown)} (jobs: {', '.join(names)})\n")
    return a


def run_job(ctx: Context, job: Job, fresh: bool) -> Result:
    res = None if fresh else load_result(ctx, job.name)
    if res is not None:
        log(f"[{job.name}] kept from an earlier run ({res.seconds:.0f} s)")
        return res
    runner = Runner(ctx, job.name)
    t0 = time.perf_counter()
    res = job.run(ctx, runner)
    res.seconds = time.perf_counter() - t0
    res.commands = runner.commands
    res.stamp = stamp_text(ctx, job.name, datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"))
    save_result(ctx, job.name, res)
    log(f"[{job.name}] done in {res.seconds:.0f} s")
    return res


def main(argv=None) -> int:
    a = parse(sys.argv[1:] if argv is None else argv)
    if a.list:
        for j in JOBS:
            print(f"{j.name:12s} {j.what}")
        return 0
    ctx = Context(quick=a.quick, device=pick_device(a.device, sys.executable), cpu=cpu_model(), commit=git_commit())
    log(f"report: {len(a.jobs)} jobs on {ctx.device.spec} ({ctx.device.platform} {ctx.device.driver}), "
        f"clppm {ctx.commit}{', quick' if a.quick else ''}")
    results, failed, t0 = {}, [], time.perf_counter()
    for i, name in enumerate(a.jobs, 1):
        job = next(j for j in JOBS if j.name == name)
        log(f"report: job {i}/{len(a.jobs)} {name}: {job.what} ({time.perf_counter() - t0:.0f} s so far)")
        try:
            results[name] = run_job(ctx, job, a.fresh)
        except Exception as e:                     # a failed job is reported at the end; the others go on
            failed.append(f"{name}: {e}")
            log(f"[{name}] FAILED: {e}")
    missing = apply(results)
    for name in missing:
        log(f"report: block {name} has no marker in README.md or docs/*.md")
    log(f"report: {len(results)} of {len(a.jobs)} jobs in {time.perf_counter() - t0:.0f} s; "
        + "; ".join(f"{n} {r.seconds:.0f} s" for n, r in results.items()))
    if failed:
        log("report: failed jobs:\n  " + "\n  ".join(failed))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
