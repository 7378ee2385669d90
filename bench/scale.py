"""Scale-out: passes per second in this process and on Dask workers, the cost of a chunk, and
the scaling this predicts for more devices and machines.

Runs, side by side on one device kind (PoCL on this machine's cores):

* in-process: ``progressive.render`` (PoCL with all cores);
* 1 worker x all cores, 1 worker x 1 core, and W workers x cores/W (``POCL_MAX_PTHREAD_COUNT``),
  each a local Dask cluster of worker processes (``clppm.run.executor.local_cluster``).

Each distributed run is timed from the first chunk submitted to the last chunk reduced
(``report["executor"]["passes_wall_s"]``), after a warm-up render that built the scene on every
worker; the in-process rate is the sum of its photon, grid and gather seconds.  Best of
``--repeat`` runs (this machine is shared: single runs scatter).

Chunk overhead, measured on the W-worker cluster:
* ``latency``: an empty task's round trip (submit -> result at the client);
* ``transfer``: fetching a result of one chunk's size (pixel x band float64 + pair counts) from
  a worker that already holds it;
* ``reduction``: adding it to the total on the client (numpy, float64).

Projection (stated model, nothing measured on the projected hardware): W devices, each taking
``t_pass`` per pass, chunks of k passes of B bytes; a chunk occupies a device for
``k t_pass + B/bw + lat``, and the client takes ``B/bw_client + t_reduce`` per chunk, serially:

    passes/s (W) = min(W k / (k t_pass + B/bw + lat),  k / (B/bw_client + t_reduce))

Efficiency is that over ``W / t_pass``.  ``t_pass*`` is the per-pass time below which the
client's serial share caps the W devices at 90 % efficiency: devices faster than that need
larger chunks (``render.chunk_passes``) or smaller images.  Bandwidths: the client's ingest
rate measured here over loopback (from fetching a chunk-sized and a 50 MB result; it also caps
remote transfers, since the client deserialises them), 10 GbE (1.25 GB/s, 0.2 ms) assumed
between machines.  ``t_pass`` of the projected devices is this machine's (all cores): the rows
say how the same device count would scale, and ``t_pass*`` how fast a device may get.

    python bench/scale.py [CONFIG] [--resolution 80x60] [--photons 25000] [--chunk 2]
                          [--chunks 4] [--workers 2] [--repeat 2]

Prints a table; writes out/bench/scale.json.  Never asserts on time.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np
from distributed import Client, wait

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from clppm import config as C
from clppm.run import entry, executor  # noqa: E402

STAGES = ("photon", "grid", "gather")
NET_10GBE = 1.25e9            # bytes/s, assumed between machines
NET_LAT = 2e-4                # s, assumed per chunk between machines
PAPER_CHUNK = 320 * 240 * (81 * 8 + 8)   # bytes: one chunk's sums at 320x240, 81 bands


def bench_cfg(path, resolution, photons, k, chunks) -> dict:
    cfg = C.load(path)
    for key, v in (("radius", "global"), ("chunk_passes", k), ("checkpoint_every", 0),
                   ("passes", k * chunks), ("photons", photons),
                   ("initial_photons", min(photons, C.load(path)["render"]["initial_photons"]))):
        cfg = C.override(cfg, "render", key, v)
    return C.override(cfg, "camera", "resolution", list(resolution))


def in_process(cfg, repeat) -> dict:
    from clppm.compute.device import open_device
    dev = open_device(None)
    runs = []
    for _ in range(repeat):
        rep = entry.render(cfg, dev=dev).report
        runs.append(sum(rep["seconds"][s] for s in STAGES))
    return {"label": "in-process", "workers": 1, "threads": os.cpu_count(), "seconds": runs,
            "passes": cfg["render"]["passes"], "exr": None}


def device_spec() -> str:
    from clppm.compute.device import list_devices, open_device
    d = open_device(None).device
    return next(f"{ip}:{i}" for ip, i, _, dd in list_devices() if dd == d)


def on_cluster(cfg, label, workers, threads, repeat, measure_overhead=False) -> dict:
    env = {"PYOPENCL_CTX": device_spec(), "POCL_MAX_PTHREAD_COUNT": str(threads)}
    k = cfg["render"]["chunk_passes"]
    warm = C.override(cfg, "render", "passes", k * workers)        # every worker builds the scene
    out = {"label": label, "workers": workers, "threads": threads, "seconds": [],
           "passes": cfg["render"]["passes"]}
    with executor.local_cluster(envs=[env] * workers) as cl, Client(cl, set_as_default=False) as c:
        c.wait_for_workers(workers, timeout=120)
        entry.render_distributed(warm, client=c)
        for _ in range(repeat):
            rep = entry.render_distributed(cfg, client=c).report
            out["seconds"].append(rep["executor"]["passes_wall_s"])
            out["chunk_task_s"] = [ch["seconds"] for ch in rep["executor"]["chunks"]]
            out["bytes_per_chunk"] = rep["executor"]["bytes_moved"] / len(rep["executor"]["chunks"])
        if measure_overhead:
            out["overhead"] = chunk_overhead(c, int(out["bytes_per_chunk"]))
    return out


def _array(nbytes):
    return np.zeros(nbytes // 8)


def fetch_seconds(c, nbytes, n) -> float:
    """Median time to fetch an array of ``nbytes`` that a worker already holds."""
    out = []
    for _ in range(n):
        f = c.submit(_array, nbytes, pure=False)
        with c.as_current():
            wait([f])
        t0 = time.perf_counter()
        f.result()
        out.append(time.perf_counter() - t0)
        del f
    return statistics.median(out)


def chunk_overhead(c, nbytes, n=7, big=PAPER_CHUNK) -> dict:
    """Latency of an empty task; fetch time of a chunk-sized and of a paper-scale result (their
    difference gives the client's ingest bandwidth); the reduction of a chunk (medians)."""
    lat = []
    for _ in range(n):
        t0 = time.perf_counter()
        c.submit(int, 0, pure=False).result()
        lat.append(time.perf_counter() - t0)
    t_small, t_big = fetch_seconds(c, nbytes, n), fetch_seconds(c, big, 3)
    a, b = np.random.default_rng(1).random(nbytes // 8), np.zeros(nbytes // 8)
    red = []
    for _ in range(n):
        t0 = time.perf_counter()
        b += a
        red.append(time.perf_counter() - t0)
    bw = (big - nbytes) / max(t_big - t_small, 1e-9)
    return {"latency_s": statistics.median(lat), "transfer_s": t_small, "transfer_paper_chunk_s": t_big,
            "reduction_s": statistics.median(red), "loopback_bytes_per_s": bw,
            "transfer_fixed_s": max(t_small - nbytes / bw, 0.0)}


def project(t_pass, k, B, bw, lat, bw_client, t_red, W) -> dict:
    """The model in the module docstring: passes/s, efficiency, and t_pass* (90 % efficiency)."""
    dev = W * k / (k * t_pass + B / bw + lat)
    client = k / (B / bw_client + t_red)
    rate = min(dev, client)
    # 90 %: client cap >= 0.9 W / t_pass  <=>  t_pass >= 0.9 W (B/bw_client + t_red) / k
    t_star = 0.9 * W * (B / bw_client + t_red) / k
    return {"passes_per_s": rate, "efficiency": rate * t_pass / W, "t_pass_90pct_s": t_star,
            "limited_by": "client" if client < dev else "devices"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--resolution", default="80x60")
    ap.add_argument("--photons", type=int, default=25000, help="stored photons per pass")
    ap.add_argument("--chunk", type=int, default=2, help="render.chunk_passes")
    ap.add_argument("--chunks", type=int, default=4, help="chunks per timed render")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("-o", "--out", default=os.path.join("out", "bench"))
    a = ap.parse_args(argv)
    res = tuple(int(v) for v in a.resolution.lower().split("x"))
    cfg = bench_cfg(a.config, res, a.photons, a.chunk, a.chunks)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    W = a.workers
    load0 = os.getloadavg()[0]
    print(f"bench/scale.py: {os.path.basename(a.config)} {res[0]}x{res[1]}, {a.photons:,} stored photons/pass, "
          f"chunks of {a.chunk} passes, {a.chunks} chunks, best of {a.repeat}, {cores} cores "
          f"(load average {load0:.1f}: other work shares them)", flush=True)
    rows = [in_process(cfg, a.repeat)]
    print(f"  {rows[-1]['label']}: {min(rows[-1]['seconds']):.2f} s", flush=True)
    for label, w, t, over in (("1 worker x all cores", 1, cores, False), ("1 worker x 1 core", 1, 1, False),
                              (f"{W} workers x {max(1, cores // W)} core(s)", W, max(1, cores // W), True)):
        rows.append(on_cluster(cfg, label, w, t, a.repeat, measure_overhead=over))
        print(f"  {label}: {min(rows[-1]['seconds']):.2f} s", flush=True)
    n = cfg["render"]["passes"]
    for r in rows:
        r["best_s"] = min(r["seconds"])
        r["passes_per_s"] = n / r["best_s"]
    one = rows[2]["passes_per_s"]
    for r in rows:
        r["speedup_vs_1_worker_1_core"] = r["passes_per_s"] / one
    ov = rows[3]["overhead"]
    B = rows[3]["bytes_per_chunk"]
    t_pass_1core = rows[2]["best_s"] / n
    t_pass_dev = rows[0]["best_s"] / n                 # all cores of this machine = one device
    bw_loop = ov["loopback_bytes_per_s"]
    lat0 = ov["latency_s"] + ov["transfer_fixed_s"]
    scen = []
    for name, Wp, bw, lat, t_pass, Bx in (
            (f"this machine, {W} workers (model check)", W, bw_loop, lat0, t_pass_1core, B),
            ("8 devices, one machine (loopback)", 8, bw_loop, lat0, t_pass_dev, B),
            ("8 devices, one machine, 320x240 x 81 bands", 8, bw_loop, lat0, t_pass_dev, PAPER_CHUNK),
            ("4 machines, 10 GbE", 4, NET_10GBE, NET_LAT + lat0, t_pass_dev, B),
            ("4 machines, 10 GbE, 320x240 x 81 bands", 4, NET_10GBE, NET_LAT + lat0, t_pass_dev, PAPER_CHUNK)):
        bw_c = min(bw, bw_loop)           # the client ingests no faster than over loopback
        red_x = ov["reduction_s"] * Bx / B
        p = project(t_pass, a.chunk, Bx, bw, lat, bw_c, red_x, Wp)
        scen.append({"scenario": name, "W": Wp, "t_pass_s": t_pass, "bytes_per_chunk": Bx,
                     "bandwidth_bytes_per_s": bw, "latency_s": lat, **p})
    print()
    print("| run | workers x threads | passes | best s | passes/s | vs 1 worker x 1 core |")
    print("|---|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['label']} | {r['workers']} x {r['threads']} | {n} | {r['best_s']:.2f} | "
              f"{r['passes_per_s']:.3f} | {r['speedup_vs_1_worker_1_core']:.2f}x |")
    print()
    print(f"chunk of {a.chunk} passes: {B / 1e3:.1f} kB back to the client ({B / a.chunk / 1e3:.1f} kB per pass); "
          f"empty-task round trip {1e3 * ov['latency_s']:.1f} ms, fetch {1e3 * ov['transfer_s']:.2f} ms "
          f"(a {PAPER_CHUNK / 1e6:.0f} MB chunk: {1e3 * ov['transfer_paper_chunk_s']:.0f} ms; client ingest "
          f"{bw_loop / 1e6:.0f} MB/s over loopback), reduction {1e3 * ov['reduction_s']:.3f} ms")
    print(f"model check: {W} workers x {rows[3]['threads']} core(s) measured {rows[3]['passes_per_s']:.2f} passes/s, "
          f"the model with 1 worker x 1 core's t_pass predicts {scen[0]['passes_per_s']:.2f}")
    print()
    print("| projection | devices | t_pass (s) | bytes/chunk | bandwidth | passes/s | efficiency | "
          "t_pass for 90 % (s) | limited by |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for s in scen:
        print(f"| {s['scenario']} | {s['W']} | {s['t_pass_s']:.3f} | {s['bytes_per_chunk'] / 1e6:.2f} MB | "
              f"{s['bandwidth_bytes_per_s'] / 1e6:.0f} MB/s | {s['passes_per_s']:.2f} | {100 * s['efficiency']:.0f} % | "
              f"{s['t_pass_90pct_s']:.4f} | {s['limited_by']} |")
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, "scale.json")
    with open(path, "w") as f:
        json.dump({"config": os.path.abspath(a.config), "resolution": list(res), "photons": a.photons,
                   "chunk_passes": a.chunk, "chunks": a.chunks, "cores": cores, "runs": rows,
                   "load_average": [load0, os.getloadavg()[0]],
                   "overhead": ov, "projection": scen,
                   "model": "passes/s = min(W k/(k t_pass + B/bw + lat), k/(B/bw_client + t_reduce))"},
                  f, indent=1, default=str)
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
