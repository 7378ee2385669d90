"""Throughput of clppm's kernels on every OpenCL device found, in one run; one markdown table.

Per device (each in its own process, best of N after a warm-up): the photon pass (photons/s on
the MCML slab and on the forearm), the grid build (photons sorted per second), the grid gather
(pairs/s and candidates tested per pair, random photons), the renderer's gather (pairs/s in a
render), the path tracer (paths/s) and a fixed small forearm render's seconds per pass.

    python bench/devices.py [--out out/bench] [--only SUBSTRING] [--repeat 3]
    python bench/devices.py --render [...]     # the former mode: bench/render.py on every device

Writes ``OUT/devices.json`` and ``OUT/devices.md`` and prints the table.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import render as bench_render  # noqa: E402  (bench/render.py)


def render_bench(argv=None) -> int:
    """The former main: bench/render.py on every device (``--render``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=os.path.join("out", "bench"))
    ap.add_argument("--only", help="only devices whose name contains this")
    ap.add_argument("--list", action="store_true")
    a = ap.parse_args(argv)

    from clppm.compute.device import describe, list_devices
    devs = list_devices()
    if not devs:
        print("no OpenCL device found", file=sys.stderr)
        return 3
    for ip, idev, _, d in devs:
        info = describe(d)
        print(f"{ip}:{idev}  {info['name']}  [{info['platform']}; {info['type']}; {info['compute_units']} CUs]")
    if a.list:
        return 0
    os.makedirs(a.out, exist_ok=True)
    paths, rc = [], 0
    for ip, idev, _, d in devs:
        name = d.name.strip()
        if a.only and a.only.lower() not in name.lower():
            continue
        print(f"\n=== {ip}:{idev} {name}", flush=True)
        cmd = [sys.executable, os.path.join(HERE, "render.py"), "--device", f"{ip}:{idev}", "--out", a.out,
               *(["--quick"] if a.quick else []), *extra]
        r = subprocess.run(cmd)
        if r.returncode != 0:
            print(f"bench/render.py failed on {name} (exit {r.returncode})", file=sys.stderr)
            rc = rc or r.returncode
            continue
        p = os.path.join(a.out, f"render-{bench_render.slug(name)}{'-quick' if a.quick else ''}.json")
        if os.path.isfile(p):
            paths.append(p)
    docs = []
    for p in paths:
        with open(p) as f:
            docs.append(json.load(f))
    if docs:
        md = ("# clppm renderer throughput\n\n"
              "Per device and method: photons/s and stored photons/s over the photon-pass seconds, gather "
              "pairs/s over the gather seconds, seconds per pass per stage, device buffers, and the paper's 200 "
              "passes extrapolated (bench/render.py): '200 passes s' with the gather pairs-per-pass decay measured "
              "in the passes sweep, 'model' with the mean-field radius recursion (a lower bound), 'linear' as 200 "
              "times the mean measured pass (an upper bound); speedup = paper seconds / '200 passes s'.  Timings on "
              "a shared machine vary with its load; quick runs are at 160x120 with 202,500 photons per pass, so "
              "their speedups are not comparable with the paper's 320x240 times.\n\n" + bench_render.markdown(docs) + "\n")
        path = os.path.join(a.out, "render-quick.md" if a.quick else "render.md")
        with open(path, "w") as f:
            f.write(md)
        print("\n" + md)
        print(f"wrote {path}")
    return rc





SLAB = "mua=10,mus=90,g=0.75,n=1.4,d=0.02"
# sizes: the 10 mm forearm (81 bands) at RES for the render and the path tracer; the whole run
# takes ~3 minutes per CPU device on a 2-core machine
RES, RENDER_PHOTONS, RENDER_PASSES, FOREARM_PHOTONS = (160, 120), 200_000, 4, 200_000
COLS = [("photons/s slab", "photon_slab", "{:.3g}"), ("photons/s forearm", "photon_forearm", "{:.3g}"),
        ("grid build photons/s", "grid_build", "{:.3g}"), ("grid gather pairs/s", "grid_pairs_s", "{:.3g}"),
        ("candidates/pair", "grid_cand_per_pair", "{:.2f}"), ("render gather pairs/s", "render_pairs_s", "{:.3g}"),
        ("PT paths/s", "pt_paths_s", "{:.3g}"), ("render s/pass", "render_s_per_pass", "{:.2f}")]


def _best(fn, repeat: int) -> float:
    fn()                                                  # warm-up: builds, caches, allocations
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def measure(spec: str, repeat: int = 3) -> dict:
    """The figures for one device (run in a worker process)."""
    import numpy as np
    from clppm import config
    from clppm.compute import device
    from clppm.integrators import hashgrid, photonpass
    from clppm.run import entry
    from clppm.checks import testing, tiny
    from clppm.scene import volume
    dev = device.open_device(spec)
    out = {"device": device.describe(dev.device)}
    for key, cfg, n in (("photon_slab", config.slab_config(SLAB), 200_000),
                        ("photon_forearm", tiny.tiny_config(size_mm=10.0, resolution=RES,
                                                            step_nm=5.0), FOREARM_PHOTONS)):
        pp = photonpass.PhotonPass.of_config(dev, volume.build(cfg), cfg)
        out[key] = n / _best(lambda: pp.trace(n), repeat)
    rng = np.random.default_rng(1)
    n, m, h = 1_000_000, 20_000, 0.02
    pos = np.zeros((n, 4), np.float32)
    pos[:, :3] = rng.random((n, 3), np.float32)
    pos[:, 3] = 1.0
    dirb = np.zeros((n, 4), np.float32)
    dirb[:, 2] = -1.0
    import pyopencl.array as cla
    pos_d, dir_d = cla.to_device(dev.queue, pos), cla.to_device(dev.queue, dirb)
    bufs = hashgrid.default_buffers(dev)

    def build():
        g = hashgrid.build(dev, pos_d, dir_d, n, np.zeros(3), np.ones(3), h, buffers=bufs)
        dev.queue.finish()
        return g
    out["grid_build"] = n / _best(build, repeat)
    g = build()
    qs = rng.random((m, 3)).astype(np.float32)
    rs = np.full(m, h, np.float32)
    res = {}

    def gather():
        res["r"] = testing.gather_counts(dev, g, qs, rs)
    t = _best(gather, repeat)
    pairs = int(res["r"].count.sum())
    out["grid_pairs_s"] = pairs / t
    out["grid_cand_per_pair"] = float(res["r"].ncand.sum()) / max(pairs, 1)
    cfg = tiny.tiny_config(size_mm=10.0, resolution=RES, step_nm=5.0, photons=RENDER_PHOTONS)
    cfg = config.override(cfg, "render", "passes", RENDER_PASSES)
    entry.render(config.override(cfg, "render", "passes", 1), dev=dev)     # warm-up
    r = entry.render(cfg, dev=dev).report
    out["render_s_per_pass"] = sum(r["seconds_per_pass"].values())
    out["render_seconds_per_pass"] = r["seconds_per_pass"]
    out["render_pairs_s"] = r["gather_pairs"] / max(r["seconds"]["gather"], 1e-9)
    flat = tiny.tiny_config("forearm_flat.toml", size_mm=10.0, resolution=RES, step_nm=5.0)
    entry.render_pt(flat, passes=1, dev=dev)                                 # warm-up
    out["pt_paths_s"] = entry.render_pt(flat, passes=2, dev=dev).report["paths_per_second"]
    out["kernels"] = device.launched(dev.device)
    return out


def table(rows: list[dict]) -> str:
    head = "| device | implementation | version | " + " | ".join(c[0] for c in COLS) + " |"
    lines = [head, "|" + "---|" * (3 + len(COLS))]
    for r in rows:
        d = r["device"]
        m = re.search(r"PoCL (\S+)", d["platform_version"])
        ver = f"PoCL {m.group(1)}" if m else d["driver_version"]
        lines.append(f"| {d['name']} | {d['implementation']} | {ver} | "
                     + " | ".join(f.format(r[k]) for _, k, f in COLS) + " |")
    return "\n".join(lines)


def kernel_table(rows: list[dict]) -> str:
    lines = ["| kernel | " + " | ".join(f"{r['device']['implementation']}: private B / WG limit / local"
                                          for r in rows) + " |", "|" + "---|" * (1 + len(rows))]
    names = sorted({k["kernel"] for r in rows for k in r["kernels"]})
    for n in names:
        cells = []
        for r in rows:
            k = next((k for k in r["kernels"] if k["kernel"] == n), None)
            cells.append(f"{k['private_mem_bytes']} / {k['work_group_size']} / {k['local_size']}" if k else "-")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--render" in argv:
        argv.remove("--render")
        return render_bench(argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.path.join("out", "bench"))
    ap.add_argument("--only", help="only devices whose implementation or name contains this")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        with open(a.worker_out, "w") as f:
            json.dump(measure(a.worker, a.repeat), f)
        return 0
    from clppm.compute.device import compiler_problem, implementation, list_devices
    rows, rc = [], 0
    for ip, idev, _, d in list_devices():
        tag = f"{implementation(d)} {d.name.strip()}"
        if (a.only and a.only.lower() not in tag.lower()) or compiler_problem(d) is not None:
            continue
        print(f"=== {ip}:{idev} {tag}", flush=True)
        os.makedirs(a.out, exist_ok=True)
        wout = os.path.join(a.out, f"devices-{ip}-{idev}.json")
        r = subprocess.run([sys.executable, __file__, "--worker", f"{ip}:{idev}", "--repeat", str(a.repeat),
                            "--worker-out", wout], capture_output=True, text=True)
        if r.returncode != 0:
            print(f"failed on {tag}:\n{r.stderr[-2000:]}", file=sys.stderr)
            rc = 1
            continue
        with open(wout) as f:
            rows.append(json.load(f))
    if not rows:
        return rc or 3
    os.makedirs(a.out, exist_ok=True)
    md = table(rows) + "\n\n" + kernel_table(rows) + "\n"
    with open(os.path.join(a.out, "devices.json"), "w") as f:
        json.dump(rows, f, indent=1)
    with open(os.path.join(a.out, "devices.md"), "w") as f:
        f.write(md)
    print(md)
    return rc


if __name__ == "__main__":
    sys.exit(main())
