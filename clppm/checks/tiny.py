"""A tiny scene through every kernel family clppm has, on one device.

Photon pass (plain, and built with the depth roulette), grid build (counting sort with pyopencl's
scan, and the radix-sort variant), eye pass, calibration (initial radius, neighbour counts), both
gathers (the point estimators' and the beam's), the grid's query kernels, the path tracer, the
reflectance tallies, and the photon and eye passes' walk on the smooth surfaces.  Used by
``clppm devices --kernels`` (every kernel's limits and the local size clppm launched it with),
``tests/oclgrind/run.sh`` (memory and race checks) and ``bench/devices.py``.
"""
from __future__ import annotations

import copy
import os
import time
import tomllib

import numpy as np

from .. import config

FAMILIES = ("render: photon pass, grid build, eye pass, calibration, gather",
            "render: the beam estimator's gather, the depth roulette's photon pass", "path tracer",
            "reflectance tallies",
            "grid queries (radix build, gather_grid, gather_bruteforce)",
            "render on the smooth surfaces (model.surface = smooth: photon and eye passes)",
            "the photon pass in SIMD lanes (4 lanes, flat and smooth surfaces)")

#: clppm's kernels the families above launch (each through clppm.compute.device.local_size)
KERNELS = ("photon_pass", "photon_pass_lanes", "grid_count", "grid_scatter", "grid_permute", "grid_keys",
           "grid_starts_from_keys", "eye_pass", "init_radius", "count_within", "gather",
           "gather_beam", "pt_pass", "gather_grid", "gather_bruteforce")


def _config_path(name: str) -> str:
    from ..config import shipped_configs
    return shipped_configs()[name[:-5] if name.endswith(".toml") else name]


def tiny_config(name: str = "forearm.toml", size_mm: float = 2.0, resolution=(8, 6),
                step_nm: float = 40.0, photons: int = 2000) -> dict:
    """``configs/name`` shrunk to a ``size_mm`` square at ``resolution`` with few bands."""
    with open(_config_path(name), "rb") as f:
        raw = tomllib.load(f)
    raw = copy.deepcopy(raw)
    s = float(raw["model"]["size_mm"][0])
    k = size_mm / s
    raw["model"]["size_mm"] = [size_mm, size_mm]
    for sec, key in (("light", "position_mm"), ("camera", "position_mm"), ("camera", "look_at_mm")):
        if sec in raw and key in raw[sec]:
            raw[sec][key] = [v * k for v in raw[sec][key]]
    raw["spectrum"]["step_nm"] = step_nm
    raw["camera"]["resolution"] = list(resolution)
    r = raw["render"]
    r.update(photons=photons, initial_photons=min(200, photons), passes=1, checkpoint_every=0)
    return config.validate(raw, f"tiny {name}", os.path.dirname(_config_path(name)))


def run_all(dev, photons: int = 2000, resolution=(8, 6), families=None) -> dict:
    """Run each family once on ``dev``; seconds per family."""
    from ..integrators import hashgrid
    from ..run import entry
    from ..analysis import reflectance
    todo = families or FAMILIES
    out = {}

    def timed(name, fn):
        if name in todo:
            t0 = time.perf_counter()
            fn()
            out[name] = time.perf_counter() - t0

    cfg = tiny_config(photons=photons, resolution=resolution)
    layer = config.override(copy.deepcopy(cfg), "render", "estimator", "layer")
    timed(FAMILIES[0], lambda: entry.render(layer, dev=dev))
    beam = config.override(copy.deepcopy(cfg), "render", "estimator", "beam")
    timed(FAMILIES[1], lambda: entry.render(config.override(beam, "render", "depth_roulette_um", 20.0),
                                                  dev=dev))
    flat = tiny_config("forearm_flat.toml", photons=photons, resolution=resolution)
    timed(FAMILIES[2], lambda: entry.render_pt(flat, passes=1, dev=dev))
    timed(FAMILIES[3], lambda: reflectance.spectral_reflectance(
        cfg, photons=max(200, photons // 10), batches=2, bands=(500.0, 540.0, 40.0), dev=dev))
    timed(FAMILIES[4], lambda: grid_queries(dev, hashgrid))
    timed(FAMILIES[5], lambda: entry.render(config.override(
        copy.deepcopy(cfg), "model", "surface", "smooth"), dev=dev))
    timed(FAMILIES[6], lambda: photon_lanes(dev, [flat, config.override(copy.deepcopy(cfg), "model", "surface",
                                                                          "smooth")], max(16, photons // 10)))
    return out


def photon_lanes(dev, cfgs, photons: int) -> None:
    """photon_pass_lanes on each config (4 lanes: its fast and slow phases, storage), a few
    photons (a simulator runs it about 7 times slower per photon than photon_pass)."""
    from ..integrators.photonpass import PhotonPass
    from ..scene import volume
    for c in cfgs:
        vol = volume.build(c, "tiny")
        pp = PhotonPass.of_config(dev, vol, c, capacity=4 * photons + 4096, lanes=4)
        pp.run_pass(0, photons)


def grid_queries(dev, hashgrid) -> None:
    """The photon grid's queries on ``dev`` against brute force: equal, exactly (AssertionError)."""
    from . import testing
    rng = np.random.default_rng(1)
    n, m = 500, 50
    pos = np.zeros((n, 4), np.float32)
    pos[:, :3] = rng.random((n, 3), np.float32)
    dirb = np.zeros((n, 4), np.float32)
    dirb[:, 2] = -1.0
    q = rng.random((m, 3)).astype(np.float32)
    r = np.full(m, 0.1, np.float32)
    g = hashgrid.build(dev, pos, dirb, n, np.zeros(3), np.ones(3), 0.1, method="radix")
    a = testing.gather_counts(dev, g, q, r)
    b = testing.gather_bruteforce(dev, pos, dirb, n, q, r)
    if not np.array_equal(a.count, b.count):
        raise AssertionError("gather_grid and gather_bruteforce disagree on the tiny scene")


def kernel_report(spec: str) -> list[dict]:
    """Every clppm kernel the tiny scene launches on device ``spec``: its queried limits and the
    local size clppm used (:func:`clppm.compute.device.local_size`)."""
    from ..compute.device import launched, open_device
    dev = open_device(spec)
    run_all(dev)
    return launched(dev.device)


def print_kernel_report(spec: str) -> None:
    rows = kernel_report(spec)
    print(f"      {'kernel':24s} {'private B':>10s} {'WG limit':>9s} {'multiple':>9s} {'local':>6s}")
    for r in rows:
        print(f"      {r['kernel']:24s} {r['private_mem_bytes'] or '-':>10} {r['work_group_size'] or '-':>9} "
              f"{r['preferred_multiple'] or '-':>9} {r['local_size']:>6}")
