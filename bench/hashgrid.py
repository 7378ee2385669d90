"""Benchmark of the device photon grid at paper scale.

810,000 photons in a 10 mm x 10 mm x 1 mm box (µm units), depth exponentially
concentrated toward the top surface (z = 0); 200,000 query points drawn the
same way, radii from the local photon density scaled so that a query finds
~800 photons on average.  For cell sizes h = f * median(R) (f = 0.5, 1, 2 and,
for reference, 0.25) it measures

* build seconds per pass, counting sort vs pyopencl RadixSort (photons
  already on the device; median of several passes after a warm-up),
* gather throughput: photon-query pairs within R per second (one work item
  per query, count + 64-bit fixed-point weight and per-band sums),
* candidates visited per true pair,

checks the grid gather against brute force on a subset of queries, prints a
table and writes JSON.  Nothing here asserts on time.

    python bench/hashgrid.py [--out out/bench_hashgrid.json] [--passes 5]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np

from clppm.integrators import hashgrid as hg
from clppm.checks import testing
from clppm.compute.device import open_device


def scene(rng, n_ph, n_q, depth_mean, side, thick, target):
    """Photons and queries (float32), exponentially concentrated toward z = 0."""
    def points(k):
        z = rng.exponential(depth_mean, k)
        while np.any(z >= thick):  # truncate to the slab
            bad = z >= thick
            z[bad] = rng.exponential(depth_mean, int(bad.sum()))
        return np.column_stack([rng.uniform(0, side, k), rng.uniform(0, side, k), z])

    pos = np.zeros((n_ph, 4), np.float32)
    pos[:, :3] = points(n_ph)
    pos[:, 3] = rng.uniform(0.5, 1.5, n_ph)
    dirb = np.zeros((n_ph, 4), np.float32)
    d = rng.normal(size=(n_ph, 3))
    dirb[:, :3] = d / np.linalg.norm(d, axis=1, keepdims=True)
    qx = points(n_q).astype(np.float32)
    # photon density at depth z (truncated exponential), radius for `target` photons
    norm = 1.0 - np.exp(-thick / depth_mean)
    rho = n_ph / (side * side) * np.exp(-qx[:, 2] / depth_mean) / (depth_mean * norm)
    r = (target / (4.0 / 3.0 * np.pi * rho)) ** (1.0 / 3.0)
    r *= rng.lognormal(0.0, 0.15, n_q)  # per-point variation, as in PPM
    return pos, dirb, qx, r.astype(np.float32)


def timed(dev, fn, reps):
    out = []
    for _ in range(reps):
        dev.queue.finish()
        t = time.perf_counter()
        res = fn()
        dev.queue.finish()
        out.append(time.perf_counter() - t)
    return out, res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photons", type=int, default=810_000)
    ap.add_argument("--queries", type=int, default=200_000)
    ap.add_argument("--target", type=float, default=800.0, help="photons per query")
    ap.add_argument("--depth", type=float, default=100.0, help="mean photon depth (µm)")
    ap.add_argument("--nb", type=int, default=16, help="bands in the per-band sums")
    ap.add_argument("--passes", type=int, default=7, help="timed build passes")
    ap.add_argument("--factors", default="0.25,0.5,1,2", help="h / median(R)")
    ap.add_argument("--check", type=int, default=400, help="queries checked by brute force")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default="out/bench_hashgrid.json")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)

    import pyopencl.array as cla
    dev = open_device(a.device)
    rng = np.random.default_rng(a.seed)
    side, thick = 10_000.0, 1_000.0
    lo, hi = [0.0, 0.0, 0.0], [side, side, thick]
    pos, dirb, qx, r = scene(rng, a.photons, a.queries, a.depth, side, thick, a.target)
    dirb[:, 3] = rng.integers(0, a.nb, a.photons)
    pos_d = cla.to_device(dev.queue, pos.view(hg.cltypes.float4).ravel())
    dir_d = cla.to_device(dev.queue, dirb.view(hg.cltypes.float4).ravel())
    bufs = hg.GridBuffers(dev)

    # calibrate the radius scale so the mean count is ~target
    h0 = hg.choose_cell_size(r, lo, hi)
    g = hg.build(dev, pos_d, dir_d, a.photons, lo, hi, h0, buffers=bufs)
    sub = rng.choice(a.queries, min(a.queries, 20_000), replace=False)
    for _ in range(2):
        c = testing.gather_counts(dev, g, qx[sub], r[sub], nb=a.nb).count.mean()
        r *= np.float32((a.target / max(c, 1.0)) ** (1.0 / 3.0))
    R = float(np.median(r))

    info = dev.info()
    result = {"device": info["name"], "platform": info["platform"],
              "compute_units": info["compute_units"], "photons": a.photons,
              "queries": a.queries, "nb": a.nb, "box_um": [lo, hi],
              "depth_mean_um": a.depth, "median_R_um": R,
              "R_percentiles_um": {str(p): float(np.percentile(r, p)) for p in (5, 50, 95)},
              "rows": []}
    print(f"device: {info['name']} ({info['platform']}, {info['compute_units']} CUs)")
    print(f"{a.photons} photons, {a.queries} queries, median R = {R:.1f} µm "
          f"(5%..95%: {np.percentile(r, 5):.0f}..{np.percentile(r, 95):.0f}), NB = {a.nb}")

    hdr = (f"{'h/R':>5} {'h µm':>7} {'cells':>9} {'count s':>9} {'radix s':>9} "
           f"{'gather s':>9} {'pairs/q':>8} {'Mpairs/s':>9} {'cand/pair':>9}")
    print(hdr)
    print("-" * len(hdr))
    for f in [float(x) for x in a.factors.split(",")]:
        h = f * R
        row = {"h_over_R": f}
        times = {}
        builds = {m: (lambda m=m: hg.build(dev, pos_d, dir_d, a.photons, lo, hi, h,
                                           method=m, buffers=bufs))
                  for m in ("counting", "radix")}
        all_ts = {m: [] for m in builds}
        for m in builds:  # warm-up (compile, buffer growth)
            timed(dev, builds[m], 1)
        for _ in range(a.passes):  # interleaved, so load changes hit both alike
            for m in builds:
                ts, g = timed(dev, builds[m], 1)
                all_ts[m] += ts
        for m in builds:
            times[m] = statistics.median(all_ts[m])
            row[f"build_{m}_s"] = times[m]
            row[f"build_{m}_all_s"] = all_ts[m]
        for m in builds:  # stage breakdown (serialised; separate from the timings above)
            st = {}
            for _ in range(3):
                hg.build(dev, pos_d, dir_d, a.photons, lo, hi, h, method=m,
                         buffers=bufs, timings=st)
            row[f"build_{m}_stages_s"] = {s_: v / 3 for s_, v in st.items()}
        g = builds["counting"]()  # the default build is what the gather uses
        row.update(h_um=g.h, ncells=g.ncells, shape=list(g.shape))
        gather = lambda: testing.gather_counts(dev, g, qx, r, nb=a.nb)  # noqa: E731
        timed(dev, gather, 1)
        ts, res = timed(dev, gather, 3)
        tg = min(ts)
        pairs = int(res.count.astype(np.int64).sum())
        cand = int(res.ncand.astype(np.int64).sum())
        row.update(gather_s=tg, pairs=pairs, candidates=cand,
                   pairs_per_query=pairs / a.queries,
                   median_pairs_per_query=float(np.median(res.count)),
                   pairs_per_s=pairs / tg, candidates_per_pair=cand / max(pairs, 1))
        # exactness on a subset against brute force
        k = rng.choice(a.queries, min(a.check, a.queries), replace=False)
        bf = testing.gather_bruteforce(dev, pos_d, dir_d, a.photons, qx[k], r[k], nb=a.nb)
        ok = (np.array_equal(bf.count, res.count[k]) and np.array_equal(bf.wsum, res.wsum[k])
              and np.array_equal(bf.band, res.band[k]))
        row["bruteforce_subset_equal"] = bool(ok)
        result["rows"].append(row)
        print(f"{f:>5.2f} {g.h:>7.1f} {g.ncells:>9d} {times['counting']:>9.4f} "
              f"{times['radix']:>9.4f} {tg:>9.3f} {pairs / a.queries:>8.1f} "
              f"{pairs / tg / 1e6:>9.1f} {cand / max(pairs, 1):>9.2f}"
              + ("" if ok else "  BRUTE-FORCE MISMATCH"))

    print("build stages, ms per pass (queue drained after each stage):")
    for rw in result["rows"]:
        print(f"  h/R {rw['h_over_R']:.2f}  counting: " + ", ".join(
            f"{k_} {v * 1e3:.1f}" for k_, v in rw["build_counting_stages_s"].items())
            + "  |  radix: " + ", ".join(
            f"{k_} {v * 1e3:.1f}" for k_, v in rw["build_radix_stages_s"].items()))
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=2)
    print(f"wrote {a.out}")
    return 0 if all(rw["bruteforce_subset_equal"] for rw in result["rows"]) else 1


if __name__ == "__main__":
    sys.exit(main())
