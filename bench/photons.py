"""Photon-pass throughput on every OpenCL device, and MCX-CL side by side when available.

Per device:

* ``mcml slab``: the MCML verification slab (mua 10, mus 90 /cm, g 0.75, d 0.02 cm, n 1),
  ``PhotonPass.trace`` (tallies only, no storing): photons per second;
* ``forearm``: the paper's model (configs/forearm.toml: 9 layers, 81 bands, D65 point light,
  generated relief + papillae on 5 um voxels), ``PhotonPass.trace`` (photons/s) and
  ``PhotonPass.run_pass`` storing every scattering event (the photon pass of the renderer):
  emitted photons and stored scattering events per second;
* ``skin slab``: the 5 upper forearm layers (stratum corneum ... subpapillary dermis, 310 um),
  flat, one band (550 nm), pencil beam, 2 mm x 2 mm open model: photons per second.

If ``pmcxcl`` (MCX-CL's Python module) is importable, the skin slab is also run by MCX-CL as a
voxel volume with 5 um voxels (the same layers, optical properties, indices and Fresnel at
every interface: isreflect = isrefint = 1) on the same device, and the photon throughput
ratio clppm / MCX-CL is reported together with the absorbed fractions of both as a sanity
check.  MCX-CL finds PoCL only through the ICD loader, so this script writes an ICD folder
naming the libpocl*.so inside the pyopencl wheel (pocl-binary-distribution) and points
OCL_ICD_VENDORS at it (pyopencl is imported first).  Whatever goes wrong there, the clppm
numbers still come out and the reason for skipping the comparison is printed.

Times exclude kernel builds (a warm-up launch first); nothing here asserts on time.  Traces
are timed 3 times (the skin slab 5, MCX-CL 3; storing passes: the fastest of 5 passes) and
the fastest run is the rate, the median beside it: on a shared machine interference only slows a run, and single runs here scattered
by +-25 %.

    python bench/photons.py [--quick] [--out out/bench_photons.json] [--device P:D] [--no-mcx]

Events and A/B (``--events``): per implementation (pocl, intel) and scene (the MCML slab, the flat
forearm, the relief forearm; the renderer's bands per path, importance storage and QMC emission),
this tree against another (``--base DIR``: a checkout with its own ``.venv``, e.g. a git worktree
of the commit before), each timed in its own process, alternating A B A B (``--rounds``): photons
emitted and entered (reaching the model) per second, median and best, and from a build with the
event counters (photon.cl PHOTON_COUNTERS, each tree's own) per entered photon: loop steps
(events), collisions, stored events, crossings by kind; events/s, cycles per event (the clock
from /proc/cpuinfo times the compute units), and lane utilisation: sum of loop steps over
(width x the longest) in groups of 8 and 16 neighbouring work items, what a SIMD compiler that
runs neighbouring work items in lanes (Intel's) can use at best; then the photon pass's lanes
per work item (W: photon_pass_lanes on a CPU, kernels/photon_lanes.h), the share of events its
fast phase did in vector arithmetic, and the active lanes: events over 16 x (vector iterations
+ events done lane by lane), 1/16 for a pass that runs every event in one lane.  ``--render``: the same
alternation for ``clppm render configs/forearm.toml``, each tree its own (seconds.photon and the
total from the run report).

    python bench/photons.py --events --base /tmp/photons-base [--rounds 3] [--impl pocl,intel]
    python bench/photons.py --render --base /tmp/photons-base [--rounds 2] [--impl intel]
"""
from __future__ import annotations

import argparse
import contextlib
import glob
import hashlib
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
try:
    from clppm.analysis.bench import MCML_SLAB  # noqa: E402
except ImportError:                  # a --base tree from before clppm bench
    MCML_SLAB = "mua=10,mus=90,g=0.75,n=1.0,d=0.02"
SKIN_BAND_NM = 550.0
SKIN_SIZE_MM = 2.0
VOXEL_UM = 5.0


# ----------------------------------------------------------------------------- helpers
def _now():
    return time.perf_counter()


@contextlib.contextmanager
def quiet_fds(log_path: Path):
    """Send C-level stdout/stderr (MCX-CL's banner and progress) to a log file."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(log_path, "ab") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def open_all_devices(spec: str | None):
    from clppm.compute import device
    if spec is not None:
        return [device.open_device(spec)]
    out = []
    for ip, idev, _, _ in device.list_devices():
        out.append(device.open_device(f"{ip}:{idev}"))
    return out


# ----------------------------------------------------------------------------- clppm
def photon_pass(photonpass, dev, vol, cfg, **kw):
    """The photon passes of ``cfg`` on ``vol``, in this checkout or an older one (whose
    PhotonPass took the config itself)."""
    return getattr(photonpass.PhotonPass, "of_config", photonpass.PhotonPass)(dev, vol, cfg, **kw)


def bench_trace(dev, cfg, vol, n, label, repeats=3):
    """Best of ``repeats`` timed traces of n photons after a warm-up (on a shared machine the
    interference only ever slows a run down, so the fastest run is the estimate of the device's
    rate; the median is reported beside it): clppm.analysis.bench.trace_rate, what `clppm bench`
    runs, or for an older checkout without it the same measurement here."""
    try:
        from clppm.analysis import bench
    except ImportError:
        return _bench_trace_inline(dev, cfg, vol, n, label, repeats)
    r = bench.trace_rate(dev, cfg, vol, n, label, repeats)
    return {"case": label, "mode": "trace", "photons": n, "seconds": r.rate.best_s,
            "repeats": repeats, "photons_per_s": r.rate.per_s(),
            "photons_per_s_median": r.rate.per_s(median=True), "setup_s": r.setup_s,
            "Rd": r.Rd, "A": r.A, "specular": r.specular}


def _bench_trace_inline(dev, cfg, vol, n, label, repeats):
    from clppm.integrators import photonpass
    t0 = _now()
    pp = photon_pass(photonpass, dev, vol, cfg, seed=1)
    pp.trace(min(n, 4096), pass_index=99)                  # build + first launch
    setup = _now() - t0
    times = []
    for k in range(repeats):
        t0 = _now()
        arrs = pp.trace(n, pass_index=k)
        times.append(_now() - t0)
        if k == 0:
            tot = arrs[0].sum(0)
    dt = min(times)
    rd = float(tot[1]) / (photonpass.W0 * n)
    return {"case": label, "mode": "trace", "photons": n, "seconds": dt, "repeats": repeats,
            "photons_per_s": n / dt, "photons_per_s_median": n / float(np.median(times)),
            "setup_s": setup, "Rd": rd,
            "A": float(tot[photonpass.NA:].sum()) / (photonpass.W0 * n)
            if hasattr(photonpass, "NA") else None,
            "specular": float(tot[0]) / (photonpass.W0 * n)}


def bench_store(dev, cfg, vol, target, passes, label):
    from clppm.integrators import photonpass
    t0 = _now()
    # the renderer's slack (progressive.py): a pass stops past the target, by up to one launch
    pp = photon_pass(photonpass, dev, vol, cfg, capacity=int(target * 1.2) + 4096, seed=1)
    pp.run_pass(10_000, min(target, 20_000))               # build + warm-up (another pass)
    setup = _now() - t0
    emitted = stored = 0
    per_pass = []                                          # (seconds, emitted, stored)
    for p in range(passes):
        t0 = _now()
        r = pp.run_pass(p, target)
        per_pass.append((_now() - t0, r["emitted"], r["stored"]))
        emitted += r["emitted"]
        stored += r["stored"]
    dt = sum(x[0] for x in per_pass)
    best = max(per_pass, key=lambda x: x[1] / x[0])        # the fastest pass (see bench_trace)
    return {"case": label, "mode": "run_pass (storing)", "passes": passes, "target": target,
            "photons": emitted, "stored": stored, "seconds": best[0],
            "photons_per_s": best[1] / best[0], "stored_per_s": best[2] / best[0],
            "photons_per_s_all_passes": emitted / dt, "stored_per_s_all_passes": stored / dt,
            "stored_per_photon": stored / max(emitted, 1), "setup_s": setup}


def skin_slab_config():
    """The 5 upper layers of configs/forearm.toml, flat, one band, pencil beam at the centre."""
    from clppm import config
    fore = config.load(str(ROOT / "configs" / "forearm.toml"))
    layers = []
    for L in fore["layer"][:5]:
        L = dict(L)
        L["bottom"] = "flat"
        layers.append({k: v for k, v in L.items() if v is not None})
    raw = {
        "model": {"name": "skin slab", "size_mm": [SKIN_SIZE_MM, SKIN_SIZE_MM],
                  "voxel_um": VOXEL_UM, "lateral_voxel_um": VOXEL_UM, "lateral": "open",
                  "quantize": True, "n_outside": 1.0, "n_below": 1.0},
        "spectrum": {"start_nm": SKIN_BAND_NM, "stop_nm": SKIN_BAND_NM, "step_nm": 5.0},
        "light": {"kind": "pencil", "direction": [0.0, 0.0, -1.0], "spectrum": "flat",
                  "center_mm": [SKIN_SIZE_MM / 2, SKIN_SIZE_MM / 2]},
        "layer": layers,
    }
    return config.validate(raw, "skin slab")


# ----------------------------------------------------------------------------- MCX-CL
def find_libpocl() -> str | None:
    cands = []
    try:
        import pyopencl
        base = Path(pyopencl.__file__).resolve().parent
        cands += glob.glob(str(base / ".libs" / "libpocl*.so*"))
        cands += glob.glob(str(base.parent / "pyopencl.libs" / "libpocl*.so*"))
    except ImportError:
        pass
    try:
        import pocl_binary_distribution as pbd
        base = Path(pbd.__file__).resolve().parent
        cands += glob.glob(str(base / "**" / "libpocl*.so*"), recursive=True)
    except ImportError:
        pass
    return cands[0] if cands else None


def setup_mcx(workdir: Path):
    """Import pmcxcl so it sees PoCL.  Returns (module, None) or (None, reason)."""
    try:
        import pyopencl  # noqa: F401  (first: its libpocl is then loaded in the process)
    except ImportError as e:
        return None, f"pyopencl not importable ({e})"
    lib = find_libpocl()
    vendors = workdir / "ocl_vendors"
    vendors.mkdir(parents=True, exist_ok=True)
    if lib:
        (vendors / "pocl-clppm-bench.icd").write_text(lib + "\n")
    for icd in glob.glob("/etc/OpenCL/vendors/*.icd"):          # keep system drivers visible
        try:
            (vendors / Path(icd).name).write_text(Path(icd).read_text())
        except OSError:
            pass
    if not any(vendors.glob("*.icd")):
        return None, "no libpocl*.so in the pyopencl wheel and no system OpenCL ICD"
    os.environ["OCL_ICD_VENDORS"] = str(vendors)
    try:
        with quiet_fds(workdir / "mcx.log"):
            import pmcxcl
    except Exception as e:  # noqa: BLE001 - any import failure means: skip
        return None, f"pmcxcl not importable ({type(e).__name__}: {e}); pip install pmcxcl"
    if not hasattr(pmcxcl, "run") or not hasattr(pmcxcl, "gpuinfo"):
        return None, "pmcxcl's binary extension could not be loaded (see its message above)"
    return pmcxcl, None


def mcx_devices(pmcxcl, workdir: Path):
    try:
        with quiet_fds(workdir / "mcx.log"):
            info = pmcxcl.gpuinfo()
    except Exception as e:  # noqa: BLE001
        return None, f"pmcxcl.gpuinfo() failed: {e}"
    if not info:
        return None, "pmcxcl found no OpenCL device"
    return info, None


def mcx_spec(vol, nphoton, device_name, repeats=3):
    """What the MCX-CL child needs: layer voxel counts and MCX prop rows (mua, mus /mm, g, n)."""
    prop = [[0.0, 0.0, 1.0, 1.0]]
    for i in range(vol.nl):
        prop.append([float(vol.mua[i, 0]) * 1000.0, float(vol.mus[i, 0]) * 1000.0,
                     float(vol.g[i, 0]), float(vol.n[i])])
    return {"nz_layers": [int(round(t / VOXEL_UM)) for t in vol.thickness],
            "n_lat": int(round(SKIN_SIZE_MM * 1000 / VOXEL_UM)), "prop": prop,
            "nphoton": int(nphoton), "device": device_name, "repeats": repeats}


def _timed(fn, **kw):
    t0 = _now()
    fn(**kw)
    return _now() - t0


def run_mcx(pmcxcl, gpuid, spec, workdir: Path):
    n_lat = spec["n_lat"]
    labels = np.concatenate([np.full(k, i + 1, np.uint8) for i, k in enumerate(spec["nz_layers"])])
    volume = np.asfortranarray(np.broadcast_to(labels[None, None, :], (n_lat, n_lat, len(labels))))
    nphoton = spec["nphoton"]
    cfg = dict(nphoton=nphoton, vol=volume, prop=np.array(spec["prop"], np.float32),
               unitinmm=VOXEL_UM / 1000.0, tstart=0.0, tend=5e-9, tstep=5e-9,
               srcpos=[n_lat / 2, n_lat / 2, 0], srcdir=[0, 0, 1], issrcfrom0=1, isreflect=1,
               isrefint=1, isspecular=0, gpuid=int(gpuid), seed=1648335518, autopilot=1)
    kernel_times, walls = [], []
    with quiet_fds(workdir / "mcx.log"):
        pmcxcl.run(**{**cfg, "nphoton": 2000})           # warm-up (kernel build)
        for k in range(spec.get("repeats", 1)):          # best of: as for clppm's runs
            t0 = _now()
            res = pmcxcl.run(**{**cfg, "seed": cfg["seed"] + k})
            walls.append(_now() - t0)
            st = res.get("stat", {}) if isinstance(res, dict) else {}
            kernel_times.append(st.get("runtime", float("nan")) / 1000.0)   # ms, no build
        # MCX-CL with no volume output (issave2pt = 0): transport only, nothing to read back
        # (not even the absorbed fraction), and no runtime in its stat, so its rate is taken
        # from wall times at n and 2n photons: the difference cancels the fixed set-up.
        bare = {}
        for m in (1, 2):
            bare[m] = min(_timed(pmcxcl.run, **{**cfg, "nphoton": m * nphoton, "issave2pt": 0,
                                                "seed": cfg["seed"] + 10 * m + k})
                          for k in range(max(1, spec.get("repeats", 1) - 1)))
    bare_rate = nphoton / (bare[2] - bare[1]) if bare[2] > bare[1] else float("nan")
    wall = min(walls)
    kernel_s = min(kernel_times)
    etot = st.get("energytot", float("nan"))
    return {"photons": nphoton, "wall_s": wall, "kernel_s": kernel_s,
            "photons_per_s": nphoton / kernel_s if kernel_s > 0 else float("nan"),
            "photons_per_s_median": nphoton / float(np.median(kernel_times)),
            "repeats": len(kernel_times),
            "photons_per_s_wall": nphoton / wall,
            "no_output_photons_per_s": bare_rate, "no_output_wall_s": [bare[1], bare[2]],
            "absorbed_fraction": st.get("energyabs", float("nan")) / etot if etot else float("nan"),
            "voxels": list(volume.shape)}


def mcx_child(spec_path: str, out_path: str) -> int:
    """Child process: MCX-CL must not share the process with clppm's OpenCL contexts (PoCL
    loaded by two ICD loaders, with pyopencl's already initialised, segfaults in
    pmcxcl.gpuinfo), so it runs here, with pyopencl imported but never initialised."""
    spec = json.loads(Path(spec_path).read_text())
    workdir = Path(spec_path).parent
    out = {"ok": False}
    pm, why = setup_mcx(workdir)
    info = None
    if pm is not None:
        info, why = mcx_devices(pm, workdir)
    if info is not None:
        match = [d for d in info if d.get("name", "").strip() == spec["device"]]
        if not match:
            why = ("pmcxcl sees " + ", ".join(d.get("name", "?") for d in info)
                   + f", not clppm's device '{spec['device']}'")
        else:
            try:
                out.update(run_mcx(pm, match[0].get("id", 1), spec, workdir))
                out["ok"] = True
            except Exception as e:  # noqa: BLE001
                why = f"pmcxcl.run failed: {type(e).__name__}: {e}"
    out["why"] = why
    Path(out_path).write_text(json.dumps(out))
    return 0


def mcx_compare(vol, nphoton, device_name, workdir: Path, timeout: float):
    """Run the MCX-CL child; return (result dict, None) or (None, reason)."""
    import subprocess
    tag = "".join(c if c.isalnum() else "_" for c in device_name)[:40]
    spec_path, out_path = workdir / f"mcx_spec_{tag}.json", workdir / f"mcx_out_{tag}.json"
    spec_path.write_text(json.dumps(mcx_spec(vol, nphoton, device_name)))
    try:
        r = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--mcx-child",
                            str(spec_path), str(out_path)], capture_output=True, text=True,
                           timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, f"MCX-CL run exceeded {timeout:.0f} s"
    if not out_path.exists():
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or [""]
        return None, f"MCX-CL child exited with code {r.returncode} {tail[0]!r} (log {workdir / 'mcx.log'})"
    res = json.loads(out_path.read_text())
    if not res.get("ok"):
        return None, res.get("why") or "unknown"
    return res, None


# ----------------------------------------------------------------------------- events, A/B
EVENT_SCENES = {"slab": "slab_mcml", "flat": "forearm_flat", "relief": "forearm"}
STORE_CONE_DEG = 12.0          # the forearm eye pass's cone of eye directions (about 11-12 deg)


def cpu_hz() -> float:
    try:
        mhz = [float(l.split(":")[1]) for l in open("/proc/cpuinfo") if l.startswith("cpu MHz")]
        return 1e6 * float(np.median(mhz))
    except (OSError, ValueError):
        return float("nan")


def lane_utilisation(steps: list, width: int) -> float:
    """transport steps / (width x the group's most loop iterations) over groups of neighbouring
    work items; steps: per launch, per work item (steps, iterations) (one photon per work item
    before the refill loop: its steps alone)"""
    num = den = 0
    for s in steps:
        s = np.asarray(s).reshape(len(s), -1)
        n = len(s) // width * width
        g = s[:n, 0].reshape(-1, width).astype(np.int64)
        it = s[:n, -1].reshape(-1, width).astype(np.int64)
        num += int(g.sum())
        den += int(it.max(1).sum()) * width
    return num / den if den else float("nan")


def events_worker(spec: dict) -> dict:
    """One tree, one implementation, one scene: timed traces (and counters if asked and built)."""
    import inspect
    from clppm import config
    from clppm.compute import device
    from clppm.integrators import photonpass
    from clppm.scene import volume
    from clppm.scene.bands import Bands
    from clppm.config import render_settings
    cfg = config.load(str(ROOT / "configs" / (spec["scene"] + ".toml")))
    vol = volume.build(cfg, spec["scene"])
    dev = device.open_device(spec["impl"])
    rc = render_settings(cfg)
    kw = {}
    if spec.get("counters"):
        if "counters" not in inspect.signature(photonpass.PhotonPass).parameters:
            return {"counters": None}
        kw["counters"] = True
    target = spec["stored"]
    pp = photon_pass(photonpass, dev, vol, cfg, seed=1, bands=Bands.from_config(cfg),
                               capacity=int(target * 1.2) + 4096, **kw)
    pp.set_storage(rc.storage, STORE_CONE_DEG, rc.store_scale, rc.store_min)
    pp.set_emission(rc.emission)
    pp.run_pass(99, min(target, 4096))                     # build + first launches

    def one(k):
        tal = photonpass.Tallies(vol.nb, getattr(vol, "nmat", vol.nl))
        t0 = _now()
        r = pp.run_pass(k, target, tal)
        dt = _now() - t0
        missed = sum(tal.counts[b][6] for b in range(vol.nb)) / (photonpass.W0 * r["emitted"])
        return dt, r, missed

    if kw:
        pp.counts()
        _, r, missed = one(0)
        c = pp.counts()
        steps = c.pop("lane_steps")
        c["lane_util_8"] = lane_utilisation(steps, 8)
        c["lane_util_16"] = lane_utilisation(steps, 16)
        # SIMD lanes doing an event, of the lane slots the pass occupied: photon_pass_lanes runs
        # lane_events in lane_iterations vector iterations of W lanes and the other events one
        # lane of W at a time; photon_pass (no vectorising CPU compiler) one lane of W always
        w = int(getattr(pp, "lanes", 1))
        c["lanes"] = w
        le, li = c.get("lane_events", 0), c.get("lane_iterations", 0)
        simd = w if w > 1 else 16
        c["active_lanes"] = c["steps"] / (simd * (li + c["steps"] - le))
        c["lane_share"] = le / max(c["steps"], 1)
        c["missed_fraction"] = missed
        c["emitted"] = r["emitted"]
        return {"counters": c}
    times, emitted, missed = [], [], []
    for k in range(spec["repeats"]):
        dt, r, m = one(k)
        times.append(dt); emitted.append(r["emitted"]); missed.append(m)
    return {"times": times, "emitted": emitted, "missed": missed}


def tree_env(**extra: str) -> dict:
    """The environment of a run in another tree: without this process's PYTHONPATH, so that each
    tree's python imports its own clppm (and kernels)."""
    return {**{k: v for k, v in os.environ.items() if k != "PYTHONPATH"}, **extra}


def run_worker(tree: Path, spec: dict) -> dict:
    import subprocess
    py = tree / ".venv" / "bin" / "python"
    r = subprocess.run([str(py), str(Path(__file__).resolve()), "--events-worker", json.dumps(spec)],
                       capture_output=True, text=True, cwd=str(tree), env=tree_env())
    lines = [l for l in r.stdout.splitlines() if l.startswith("{")]
    if r.returncode != 0 or not lines:
        raise RuntimeError(f"worker in {tree} failed: {r.stderr.strip().splitlines()[-3:]}")
    out = json.loads(lines[-1])
    kdir = Path(out.pop("kernel_dir")).resolve()
    if not kdir.is_relative_to(tree.resolve()):       # an editable install can map another tree's kernels
        raise RuntimeError(f"worker in {tree} built the kernels of {kdir}: give that tree a python "
                           f"that imports its own clppm and kernels")
    return out


def events_ab(base: Path | None, impls: list, rounds: int, photons: dict, out_path: Path) -> int:
    trees = [("A", ROOT)] + ([("B", base)] if base else [])
    hz = cpu_hz()
    res = {"cpu_hz": hz, "rounds": rounds, "trees": {k: str(t) for k, t in trees}, "rows": []}
    print(f"{'impl':6s} {'scene':7s} {'tree':4s} {'emitted/s':>10s} {'entered/s':>10s} {'best':>10s} "
          f"{'missed':>7s} {'events/ph':>9s} {'events/s':>9s} {'cyc/event':>9s} {'lanes8':>6s} {'lanes16':>7s} "
          f"{'W':>3s} {'in lanes':>8s} {'active':>6s}")
    for impl in impls:
        for scene, name in EVENT_SCENES.items():
            n = photons[scene]
            # each tree's own counts (a tree without the counting build: this tree's)
            cnts = {k: run_worker(tree, {"impl": impl, "scene": name, "stored": n, "counters": True})["counters"]
                    for k, tree in trees}
            cnts = {k: c if c is not None else cnts["A"] for k, c in cnts.items()}
            times = {k: [] for k, _ in trees}
            meta = {}
            for r in range(rounds):                          # A B A B
                for k, tree in trees:
                    w = run_worker(tree, {"impl": impl, "scene": name, "stored": n, "repeats": 2})
                    for dt, e, m in zip(w["times"], w["emitted"], w["missed"]):
                        times[k].append((dt, e, e * (1 - m)))
            rows = {}
            for k, _ in trees:
                cnt = cnts[k]
                em = np.array([e / dt for dt, e, _ in times[k]])
                en = np.array([e / dt for dt, _, e in times[k]])
                missed = 1 - sum(x[2] for x in times[k]) / sum(x[1] for x in times[k])
                ev = cnt["steps"] / max(cnt["entered"], 1)
                row = {"impl": impl, "scene": scene, "tree": k, "emitted_per_s": float(np.median(em)),
                       "entered_per_s": float(np.median(en)), "entered_per_s_best": float(en.max()),
                       "seconds_per_pass": float(np.median([x[0] for x in times[k]])),
                       "missed": missed, "events_per_entered": ev,
                       "events_per_s": ev * float(np.median(en)), "runs": times[k]}
                row["cycles_per_event"] = hz * 2 / row["events_per_s"]
                rows[k] = row
                print(f"{impl:6s} {scene:7s} {k:4s} {row['emitted_per_s']:10.3e} {row['entered_per_s']:10.3e} "
                      f"{row['entered_per_s_best']:10.3e} {row['missed']:7.4f} {ev:9.1f} "
                      f"{row['events_per_s']:9.2e} {row['cycles_per_event']:9.0f} "
                      f"{cnt['lane_util_8']:6.2f} {cnt['lane_util_16']:7.2f} {cnt.get('lanes', 1):3d} "
                      f"{cnt.get('lane_share', 0.0):8.3f} {cnt.get('active_lanes', 1 / 16):6.3f}", flush=True)
            if "B" in rows:
                print(f"{'':19s} A/B entered photons/s (median): {rows['A']['entered_per_s'] / rows['B']['entered_per_s']:.2f}x, "
                      f"seconds per pass B/A {rows['B']['seconds_per_pass'] / rows['A']['seconds_per_pass']:.2f}x")
            for k, _ in trees:
                e = max(cnts[k]["entered"], 1)
                print(f"  {k} per entered photon: " + ", ".join(f"{c} {v / e:.2f}" for c, v in cnts[k].items()
                                                              if isinstance(v, int) and c not in ("entered",)))
                rows[k]["counters"] = cnts[k]
            res["rows"] += list(rows.values())
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(res, indent=1, default=str))
    print(f"wrote {out_path}")
    return 0


def spectral_hash(exr: Path) -> str:
    """A hash of an EXR's spectral pixels (its header holds the run's times and tree)."""
    from clppm.image import read_exr
    return hashlib.sha1(np.ascontiguousarray(read_exr(exr)["spectral"]).tobytes()).hexdigest()[:16]


def render_ab(base: Path | None, impls: list, rounds: int, extra: list, out_path: Path) -> int:
    """clppm render configs/forearm.toml in each tree, alternating: the run report's seconds."""
    import subprocess
    trees = [("A", ROOT)] + ([("B", base)] if base else [])
    res = []
    for impl in impls:
        for r in range(rounds):
            for k, tree in trees:
                o = Path(tempfile.mkdtemp(prefix="clppm_ab_")) / "forearm.exr"
                env = tree_env(PYOPENCL_CTX=impl)
                cfg = tree / "configs" / "forearm.toml"    # each tree renders its own default scene
                subprocess.run([str(tree / ".venv" / "bin" / "python"), "-m", "clppm.cli", "render", str(cfg),
                                "-o", str(o), "-q", *extra], check=True, env=env, cwd=str(tree))
                rep = json.loads(o.with_suffix(".json").read_text())
                sec = rep["seconds"]
                row = {"impl": impl, "tree": k, "round": r, "photon": sec["photon"], "gather": sec.get("gather"),
                       "photon+gather": sec["photon"] + (sec.get("gather") or 0.0),
                       "total": sec["total"], "emitted": rep["photons_emitted"], "stored": rep["photons_stored"],
                       "spectral_sha1": spectral_hash(o)}
                res.append(row)
                print(json.dumps(row), flush=True)
        for key in ("photon", "gather", "photon+gather", "total"):
            med = {k: float(np.median([x[key] for x in res if x["impl"] == impl and x["tree"] == k])) for k, _ in trees}
            line = f"{impl}: seconds.{key} median " + ", ".join(f"{k} {v:.1f}" for k, v in med.items())
            if "B" in med:
                line += f"  B/A {med['B'] / med['A']:.2f}x"
            print(line, flush=True)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(res, indent=1))
    return 0


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small runs (~1 minute)")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_photons.json"))
    ap.add_argument("--device", default=None, help="only this device ('P:D' or name part)")
    ap.add_argument("--no-mcx", action="store_true", help="skip the MCX-CL comparison")
    ap.add_argument("--mcx-child", nargs=2, metavar=("SPEC", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--events", action="store_true", help="events per photon and A/B photons/s (see above)")
    ap.add_argument("--render", action="store_true", help="A/B of the forearm render's seconds")
    ap.add_argument("--base", default=None, help="the other tree (with its own .venv) for --events/--render")
    ap.add_argument("--rounds", type=int, default=3, help="A B rounds for --events/--render")
    ap.add_argument("--impl", default="pocl,intel", help="implementations for --events/--render")
    ap.add_argument("--render-args", default="", help="extra arguments of clppm render (--render)")
    ap.add_argument("--events-worker", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.mcx_child:
        return mcx_child(*a.mcx_child)
    if a.events_worker:
        from clppm.compute.device import kernel_dir
        print(json.dumps({**events_worker(json.loads(a.events_worker)), "kernel_dir": kernel_dir()}))
        return 0
    base = Path(a.base).resolve() if a.base else None
    impls = [x for x in a.impl.split(",") if x]
    if a.events:
        ph = {"slab": 100_000, "flat": 50_000, "relief": 50_000} if a.quick else \
             {"slab": 400_000, "flat": 200_000, "relief": 200_000}      # stored events per pass
        return events_ab(base, impls, a.rounds, ph, ROOT / "out" / "bench_photons_events.json")
    if a.render:
        return render_ab(base, impls, a.rounds, a.render_args.split(), ROOT / "out" / "bench_photons_render.json")

    from clppm import config
    from clppm.compute import device
    from clppm.scene import volume

    q = a.quick
    n_mcml = 400_000 if q else 4_000_000
    n_fore = 20_000 if q else 200_000
    store_target, store_passes = (200_000, 2) if q else (810_000, 5)
    n_skin = 50_000 if q else 500_000
    n_mcx = 20_000 if q else 200_000

    out_path = Path(a.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    workdir = Path(tempfile.mkdtemp(prefix="clppm_bench_"))

    t0 = _now()
    mcml_cfg = config.slab_config(MCML_SLAB)
    mcml_vol = volume.build(mcml_cfg, "--slab")
    fore_cfg = config.load(str(ROOT / "configs" / "forearm.toml"))
    fore_vol = volume.build(fore_cfg, "forearm.toml")
    fore_build = _now() - t0
    skin_cfg = skin_slab_config()
    skin_vol = volume.build(skin_cfg, "skin slab")

    try:
        devs = open_all_devices(a.device)
    except device.DeviceError as e:
        print(f"no device: {e}", file=sys.stderr)
        return 3

    results = {"host": platform.node(), "python": sys.version.split()[0], "quick": q,
               "forearm_volume_build_s": fore_build,
               "forearm_columns": fore_vol.info.get("columns"), "devices": []}
    rows = []
    for dev in devs:
        info = dev.info()
        print(f"device {dev.name} [{info['platform']}; {info['compute_units']} CUs]", flush=True)
        entry = {"device": info, "runs": []}
        runs = entry["runs"]
        runs.append(bench_trace(dev, mcml_cfg, mcml_vol, n_mcml, "mcml slab"))
        runs.append(bench_trace(dev, fore_cfg, fore_vol, n_fore, "forearm 5 um"))
        runs.append(bench_store(dev, fore_cfg, fore_vol, store_target, store_passes, "forearm 5 um"))
        runs.append(bench_trace(dev, skin_cfg, skin_vol, n_skin, "skin slab 550 nm", repeats=5))
        for r in runs:
            rows.append((dev.name, r))
        results["devices"].append(entry)

    # ---- MCX-CL side by side
    mcx = {"available": False}
    if a.no_mcx:
        mcx["skipped"] = "--no-mcx"
    else:
        import importlib.util
        why = None
        if importlib.util.find_spec("pmcxcl") is None:      # not imported here: see mcx_child
            why = "pmcxcl is not installed (pip install pmcxcl)"
        if why is None:
            for dev, entry in zip(devs, results["devices"]):
                m, why = mcx_compare(skin_vol, n_mcx, dev.name, workdir, timeout=300)
                if m is None:
                    continue
                ours = next(r for r in entry["runs"] if r["case"].startswith("skin slab"))
                m["device"] = dev.name
                m["clppm_photons_per_s"] = ours["photons_per_s"]
                m["ratio_clppm_over_mcx"] = ours["photons_per_s"] / m["photons_per_s"]
                m["ratio_median"] = ours["photons_per_s_median"] / m["photons_per_s_median"]
                m["ratio_no_output"] = ours["photons_per_s"] / m["no_output_photons_per_s"]
                m["clppm_absorbed_fraction_excl_specular"] = ours["A"] / (1 - ours["specular"])
                mcx.setdefault("runs", []).append(m)
                mcx["available"] = True
        if not mcx["available"]:
            mcx["skipped"] = why
        mcx["log"] = str(workdir / "mcx.log")
    results["mcx"] = mcx

    # ---- table
    print()
    hdr = f"{'device':24s} {'case':18s} {'mode':20s} {'photons':>10s} {'s':>7s} " \
          f"{'photons/s':>11s} {'stored/s':>11s} {'stored/ph':>9s}"
    print(hdr)
    print("-" * len(hdr))
    for name, r in rows:
        st = f"{r['stored_per_s']:11.3e}" if "stored_per_s" in r else f"{'':>11s}"
        sp = f"{r['stored_per_photon']:9.1f}" if "stored_per_photon" in r else f"{'':>9s}"
        print(f"{name[:24]:24s} {r['case']:18s} {r['mode']:20s} {r['photons']:10d} "
              f"{r['seconds']:7.2f} {r['photons_per_s']:11.3e} {st} {sp}")
    if mcx["available"]:
        for m in mcx["runs"]:
            print(f"{m['device'][:24]:24s} {'skin slab 550 nm':18s} {'MCX-CL (pmcxcl)':20s} "
                  f"{m['photons']:10d} {m['kernel_s']:7.2f} {m['photons_per_s']:11.3e}")
            print(f"  clppm / MCX-CL photon throughput: {m['ratio_clppm_over_mcx']:.2f}x best/best, "
                  f"{m['ratio_median']:.2f}x median/median   "
                  f"(absorbed: clppm {m['clppm_absorbed_fraction_excl_specular']:.4f}, "
                  f"MCX-CL {m['absorbed_fraction']:.4f}; voxels {m['voxels']})")
            print(f"{m['device'][:24]:24s} {'skin slab 550 nm':18s} {'MCX-CL, no output':20s} "
                  f"{2 * m['photons']:10d} {'':>7s} {m['no_output_photons_per_s']:11.3e}")
            print(f"  clppm / MCX-CL without its fluence volume (issave2pt=0, transport only): "
                  f"{m['ratio_no_output']:.2f}x")
    else:
        print(f"MCX-CL comparison skipped: {mcx.get('skipped')}")
    print(f"forearm volume build: {fore_build:.1f} s ({fore_vol.info.get('columns')} columns)")

    with open(out_path, "w") as f:
        json.dump(results, f, indent=1, default=str)
    print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
