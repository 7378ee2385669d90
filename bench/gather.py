"""The gather's speed, side by side with an older tree of the code, in one run.

For each code tree (this one and, with ``--base DIR``, a checkout of an older commit, e.g.
``git worktree add /tmp/base aa94d29``) and each OpenCL device, a worker process (the tree
first on ``PYTHONPATH``) sets up ``configs/forearm.toml`` (or ``--config``) at ``--res``,
calibrates, runs photon pass 0 and then repeats that pass's grid build and gather ``--reps``
times on the same stored photons (the photon pass is not repeated: its photons stay in the
buffers).  The trees run one after the other on each device, within the one run.
Reported per tree and device:

* seconds per stage (photon pass once; grid build and gather: best and median of the reps),
* photon-point pairs found and pairs/s over the gather's seconds (best rep),
* candidates per pair: photons tested over pairs found (this tree's kernel built with
  ``-DCOUNT_CANDIDATES`` counts the photons of every cell row a query visits; the count
  with cubic cells is the query of the trees before flat cells),
* each gather kernel's private memory per work item as the implementation reports it
  (``CL_KERNEL_PRIVATE_MEM_SIZE``),
* a hash of the pixel sums: the trees must give the same bytes.

    python bench/gather.py [--base DIR] [--devices 0:0,1:0] [--res 160 120] [--reps 3]
                           [--layout gather,scatter] [--out out/bench_gather.json]

Nothing here asserts on time; the ratios of one run are the result (the machine is shared).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


# --------------------------------------------------------------------------- worker

class _FreeFunctions:
    """A tree before clppm.integrators.ppm.Pipeline: its Scene and free functions, as the pipeline's methods."""

    def __init__(self, ppm, sc):
        self.ppm, self.sc = ppm, sc

    def __getattr__(self, name):
        return getattr(self.sc, name)

    def calibrate(self):
        return self.ppm.calibrate(self.sc)

    def apply(self, cal):
        self.ppm.prepare(self.sc, cal)

    def point_state(self, cal):
        return self.ppm.point_state(self.sc, cal)

    def run_pass(self, cal, st, p, acc, tal):
        return self.ppm.run_pass(self.sc, cal, st, p, acc, tal)


def _pipeline(ppm, cfg, dev):
    """This tree's PPM pipeline on ``cfg`` (an older tree's Scene behind the same methods)."""
    if hasattr(ppm, "Pipeline"):
        return ppm.Pipeline.build(cfg, dev)
    return _FreeFunctions(ppm, ppm.setup(cfg, dev))


def _kernels(sc) -> dict:
    """The gather's and the scatter's kernels by name (this tree's estimator, or an older
    tree's ``kernels`` dict)."""
    est = getattr(sc, "estimator", None)
    if est is None:
        ks = dict(sc.kernels)
        bs = getattr(sc, "_beam", None)
        if bs is not None and getattr(bs, "scatter", None) is not None:
            ks.update(bs.scatter.k)
        return ks
    import dataclasses
    if hasattr(est, "kernels"):             # the beam: its kernels' dataclass
        ks = {f.name: getattr(est.kernels, f.name) for f in dataclasses.fields(est.kernels)}
    else:
        ks = {"gather": est.kernel}
    state = getattr(getattr(est, "layout", None), "state", None)
    if state is not None:
        ks.update(state.k)
    return ks


def _private_mem(sc) -> dict:
    import pyopencl as cl
    out = {}
    for name, k in _kernels(sc).items():
        if name.startswith("gather") or name.startswith("scatter"):
            k = getattr(k, "kernel", k)         # clppm.compute.kernelcall.Kernel wraps the pyopencl one
            out[name] = int(k.get_work_group_info(cl.kernel_work_group_info.PRIVATE_MEM_SIZE,
                                                  sc.dev.device))
    return out


def _candidates(sc, cal, st, info, ppm, photonpass, flat: bool) -> int | None:
    """Photons tested by the beam gather's queries (trees with device.kernel_defines), with flat
    or cubic cells."""
    import dataclasses
    import numpy as np
    try:
        from clppm.compute.device import kernel_defines
    except ImportError:                     # a tree before kernel_defines
        return None
    if not sc.beam:
        return None
    prg = sc.dev.build("gather.cl", kernel_defines(sc.vol, hero=sc.pp.hero, estimator="beam", count_candidates=True))
    from clppm.compute.kernelcall import Kernel
    acc = ppm.Accumulators.zeros(sc)
    if hasattr(ppm, "Pipeline"):
        est = sc.estimator
        saved = est.kernels, est.hz
        est.kernels = dataclasses.replace(est.kernels, gather_beam=Kernel(prg, "gather_beam"))
        est.hz = est.hz if flat else None
        try:
            sc.run_pass(cal, st, 0, acc, photonpass.Tallies(sc.vol.nb, sc.vol.nmat))
        finally:
            est.kernels, est.hz = saved
        return int(acc.pairs.get().astype(np.int64).sum())
    if not hasattr(ppm, "photon_slabs"):
        return None
    inner = sc.sc
    saved_k, saved_hz = inner.kernels["gather_beam"], inner.hz
    inner.kernels["gather_beam"] = Kernel(prg, "gather_beam")
    if not flat:
        inner.hz = None
    try:
        sc.run_pass(cal, st, 0, acc, photonpass.Tallies(sc.vol.nb, sc.vol.nmat))
    finally:
        inner.kernels["gather_beam"], inner.hz = saved_k, saved_hz
    return int(acc.pairs.get().astype(np.int64).sum())


def _tree_kernels() -> str:
    """Make ``clppm.kernels`` this worker's tree's kernels/ (an editable install maps it to the
    installed tree's folder whatever ``PYTHONPATH`` says: the base would compile this tree's
    kernels).  Returns the kernel folder in use."""
    import importlib.util
    import clppm
    tree = os.path.dirname(os.path.dirname(os.path.abspath(clppm.__file__)))
    kdir = os.path.join(tree, "kernels")
    spec = importlib.util.spec_from_file_location("clppm.kernels", os.path.join(kdir, "__init__.py"),
                                                  submodule_search_locations=[kdir])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["clppm.kernels"] = mod
    spec.loader.exec_module(mod)
    from clppm.compute.device import kernel_dir
    return str(kernel_dir())


def worker(a) -> dict:
    kdir = _tree_kernels()
    import numpy as np
    from clppm import config as C
    from clppm.integrators import ppm
    from clppm.compute.device import open_device
    try:
        from clppm.integrators import photonpass
    except ImportError:                     # a tree before the photon pass's module had its name
        from clppm import transport as photonpass
    cfg = C.load(a.config)
    cfg = C.override(cfg, "camera", "resolution", [int(r) for r in a.res])
    if a.layout and "layout" in C.SCHEMA.get("render", {}):
        cfg = C.override(cfg, "render", "layout", a.layout)
    dev = open_device(a.device)
    t0 = time.perf_counter()
    sc = _pipeline(ppm, cfg, dev)
    cal = sc.calibrate()
    sc.apply(cal)
    setup_s = time.perf_counter() - t0
    st = sc.point_state(cal)
    acc = ppm.Accumulators.zeros(sc)
    # the tallies' rows: per material, or per layer in trees before inclusions
    tal = photonpass.Tallies(sc.vol.nb, sc.vol.nmat if hasattr(sc.vol, "nmat") else sc.vol.nl)
    info = sc.run_pass(cal, st, 0, acc, tal)
    photon_s = sc.timing["photon"]
    first = acc.host()
    sc.pp.run_pass = lambda p, n, tallies=None: info        # the same photons again
    grid_s, gather_s = [], []
    for _ in range(a.reps):
        before = dict(sc.timing)
        acc.clear()
        sc.run_pass(cal, st, 0, acc, tal)
        grid_s.append(sc.timing["grid"] - before["grid"])
        gather_s.append(sc.timing["gather"] - before["gather"])
    pix, pairs = acc.host()
    assert np.array_equal(pix, first[0]), "the same photons gave other bytes"
    npairs = int(pairs.astype(np.int64).sum())
    lay = getattr(getattr(sc.estimator, "layout", None), "name", "gather")
    out = {"device": dev.device.name.strip(), "kernels": kdir, "layout_used": lay, "platform": dev.device.platform.name.strip(),
           "setup_s": setup_s, "photon_s": photon_s,
           "grid_s": {"best": min(grid_s), "median": statistics.median(grid_s)},
           "gather_s": {"best": min(gather_s), "median": statistics.median(gather_s)},
           "pairs": npairs, "pairs_per_s": npairs / min(gather_s),
           "npts": sc.npts, "npieces": sc.eye.npieces,
           "private_mem": _private_mem(sc),
           "hash": hashlib.sha1(pix.tobytes()).hexdigest()[:16]}
    if a.candidates and lay == "gather":     # the scatter tests the same cells' photons
        for flat in (True, False):
            c = _candidates(sc, cal, st, info, ppm, photonpass, flat)
            if c is not None:
                out["candidates_per_pair_" + ("flat" if flat else "cubic")] = c / max(npairs, 1)
    return out


# --------------------------------------------------------------------------- driver

def run_worker(tree: str, device: str, a, candidates: bool) -> dict:
    env = dict(os.environ, PYTHONPATH=tree)
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--device", device,
           "--config", a.config, "--res", *map(str, a.res), "--reps", str(a.reps)]
    if candidates:
        cmd.append("--candidates")
    if a.layout_one:
        cmd += ["--layout", a.layout_one]
    r = subprocess.run(cmd, env=env, cwd="/", capture_output=True, text=True)
    if r.returncode != 0:
        return {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else "failed"}
    return json.loads(r.stdout.strip().splitlines()[-1])


def table(rows: list) -> str:
    lines = ["| tree | layout | implementation | gather s (best / median) | pairs | pairs/s | "
             "cand/pair | grid s | photon s | private B/work item | hash |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['tree']} | {r.get('layout', '')} | {r['spec']} | {r['error']} |")
            continue
        cand = r.get("candidates_per_pair_flat")
        cube = r.get("candidates_per_pair_cubic")
        cs = (f"{cand:.1f} (cubic cells {cube:.1f})" if cand is not None else "")
        pm = ", ".join(f"{k} {v}" for k, v in r["private_mem"].items())
        lines.append(f"| {r['tree']} | {r.get('layout', '')} | {r['platform']} | "
                     f"{r['gather_s']['best']:.2f} / {r['gather_s']['median']:.2f} | "
                     f"{r['pairs']:.3g} | {r['pairs_per_s']:.3g} | {cs} | {r['grid_s']['best']:.2f} | "
                     f"{r['photon_s']:.1f} | {pm} | {r['hash']} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--candidates", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--layout", dest="layout_one", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--device", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--base", default=None, help="checkouts of older code to compare with (comma-separated)")
    ap.add_argument("--devices", default=None, help="comma-separated device specs (default: all)")
    ap.add_argument("--layouts", default="", help="comma-separated render.layout values of this tree")
    ap.add_argument("--config", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--res", type=int, nargs=2, default=[160, 120])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "bench_gather.json"))
    a = ap.parse_args(argv)
    a.config = os.path.abspath(a.config)
    if a.worker:
        a.layout = a.layout_one
        print(json.dumps(worker(a)))
        return 0
    if a.devices:
        specs = a.devices.split(",")
    else:
        from clppm.compute.device import list_devices
        specs = [f"{p}:{d}" for p, d, _, _ in list_devices()]
    trees = [("this", ROOT)]
    for b in (a.base.split(",") if a.base else []):     # several: base, base2, ...
        trees.append(("base" if len(trees) == 1 else f"base{len(trees)}", os.path.abspath(b)))
    layouts = [x for x in a.layouts.split(",") if x] or [None]
    rows = []
    for spec in specs:
        for name, tree in trees:
            for lay in (layouts if name == "this" else [None]):
                a.layout_one = lay
                r = run_worker(tree, spec, a, candidates=(name == "this"))
                r.update(tree=name, spec=spec, layout=lay or "")
                rows.append(r)
                print(json.dumps(r), flush=True)
    print(table(rows))
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump({"config": a.config, "res": a.res, "reps": a.reps, "trees": trees, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
