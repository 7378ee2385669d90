"""A known-answer self-test of one OpenCL device, run in a child process.

OpenCL implementations fail in ways a build does not show: pip's PoCL 3.0 compiles a kernel's
work-group function at its first launch and aborts the process there on some CPUs (LLVM 14 and a
float16 sqrt on AMD Zen 4); a kernel cache left by a crash yields programs without kernels;
vectorisers miscompile.  So before clppm renders on a device it runs a tiny scene through every
kernel family (:mod:`clppm.checks.tiny`'s scene) on it, *in a child process*, and compares what
comes back with values stored in the package (``clppm/data/selftest_reference.json``):

* the photon pass's tallies (specular, Rd, Tt, A) and the images' band groups of the layer and
  beam estimators (the beam's on 9 bands, all carried by every path, as the default's 81 in
  classes of 9) and of the path tracer, each within :data:`SIGMAS` seed-to-seed standard
  deviations of the stored value (the spread over :data:`REFERENCE_SEEDS` seeds; an
  implementation that rounds differently diverges by about one of those);
* energy conservation of the photon pass (specular + Rd + Tt + A + lost + missed = 1);
* integer results exactly: the photon grid's queries against brute force.

This module is the child, ``python -m clppm.checks.selftest P:D``; the parent that runs it,
reads its answer and caches the result is :mod:`clppm.compute.devicecheck`.  A device that
fails is never chosen by default (:func:`clppm.compute.device.select_device`).
``python -m clppm.checks.selftest --reference P:D ...`` remakes the stored reference.
"""
from __future__ import annotations

import copy
import json
import os
import sys
import time

import numpy as np

from ..compute.devicecheck import REFERENCE_FILE, RESULT, STAGE

#: seeds the stored spread is measured over (the self-test itself runs the first)
REFERENCE_SEEDS = tuple(range(1, 13))
#: tolerance in seed-to-seed standard deviations
SIGMAS = 6.0
#: the photon pass's energy balance (tallies summed against the photons' weight)
ENERGY_TOL = 1e-4
#: photons of the tally check, and of each image's pass
TRACE_PHOTONS, IMAGE_PHOTONS = 20000, 40000
RESOLUTION = (8, 6)
PT_PASSES = 16                  # path-traced passes (one path per pixel and pass)
GROUPS = 3                      # band groups of an image compared
BEAM_STEP_NM = 50.0             # the beam's image: 9 bands, 9 per path (the default's band math)


# --- what the child measures ------------------------------------------------------------------

def _band_groups(img: np.ndarray) -> list[float]:
    """Mean radiance of the image in GROUPS contiguous band groups."""
    nb = img.shape[-1]
    return [float(img[..., g].mean()) for g in np.array_split(np.arange(nb), GROUPS)]


def measure(dev, seed: int = REFERENCE_SEEDS[0]) -> dict:
    """Every known-answer quantity of the tiny scene on ``dev`` (a
    :class:`clppm.compute.device.Device`) at ``seed``: name -> value.  Raises AssertionError where
    an exact check fails."""
    from .. import config
    from ..integrators import hashgrid, photonpass
    from ..run import entry
    from . import tiny
    from ..scene import volume
    cfg = config.override(tiny.tiny_config(photons=IMAGE_PHOTONS, resolution=RESOLUTION),
                          "render", "seed", int(seed))
    vol = volume.build(cfg, "self-test forearm")
    rep = photonpass.trace_report(photonpass.PhotonPass.of_config(dev, vol, cfg), TRACE_PHOTONS, batches=4)
    out = {k: float(rep[k]) for k in ("specular", "Rd", "Tt", "A")}
    out["energy_balance_error"] = float(rep["energy_balance_error"])
    res = entry.render(config.override(copy.deepcopy(cfg), "render", "estimator", "layer"), dev=dev)
    out.update({f"layer_group{i}": v for i, v in enumerate(_band_groups(res.spectral))})
    # the beam on 9 bands, all carried by every path: the default's 16-lane band math (BAND16)
    nine = config.override(tiny.tiny_config(photons=IMAGE_PHOTONS, resolution=RESOLUTION, step_nm=BEAM_STEP_NM),
                           "render", "seed", int(seed))
    res = entry.render(config.override(nine, "render", "estimator", "beam"), dev=dev)
    out.update({f"beam_group{i}": v for i, v in enumerate(_band_groups(res.spectral))})
    flat = config.override(tiny.tiny_config("forearm_flat.toml", photons=IMAGE_PHOTONS,
                                            resolution=RESOLUTION), "render", "seed", int(seed))
    res = entry.render_pt(flat, passes=PT_PASSES, dev=dev)
    out.update({f"pt_group{i}": v for i, v in enumerate(_band_groups(res.spectral))})
    tiny.grid_queries(dev, hashgrid)              # exact: grid queries = brute force
    return out


def compare(values: dict, reference: dict) -> list[str]:
    """The quantities outside their tolerance, one phrase each (empty: all agree)."""
    bad = []
    if values.get("energy_balance_error", 1.0) > ENERGY_TOL:
        bad.append(f"photon pass energy balance off by {values.get('energy_balance_error'):.1e}")
    for name, ref in reference["quantities"].items():
        v = values.get(name)
        tol = SIGMAS * ref["spread"] + 1e-6 * abs(ref["value"])
        if v is None or not np.isfinite(v) or abs(v - ref["value"]) > tol:
            dev_ = "missing" if v is None else f"{v:.5g}"
            bad.append(f"{name} {dev_} against {ref['value']:.5g} ± {tol:.2g}")
    return bad


def load_reference() -> dict:
    from importlib import resources
    return json.loads(resources.files("clppm.data").joinpath(REFERENCE_FILE).read_text())


# --- the child ----------------------------------------------------------------------------------

def _child(spec: str) -> int:
    """Run in the child: open ``spec``, measure, compare; print the result as one JSON line."""
    os.environ["CLPPM_SELF_TEST"] = "0"
    os.environ["CLPPM_SELF_TEST_CHILD"] = "1"      # clppm.compute.device.launch: first launches in sync
    from ..compute.device import DeviceError, open_device
    t0 = time.perf_counter()
    print(f"{STAGE}opening the device", flush=True)
    dev = open_device(spec)
    try:
        values = measure(dev)
        bad = compare(values, load_reference())
    except (AssertionError, DeviceError) as e:
        values, bad = {}, [" ".join(str(e).split())]
    dev.queue.finish()
    sys.stdout.write(RESULT + json.dumps({"values": values, "bad": bad,
                               "seconds": time.perf_counter() - t0}) + "\n")
    sys.stdout.flush()
    return 0


# --- the stored reference ------------------------------------------------------------------------

def make_reference(specs: list[str], seeds=REFERENCE_SEEDS) -> dict:
    """Measure every quantity at ``seeds`` on each device of ``specs``: the value is the first
    seed's mean over the devices, the spread the seed-to-seed standard deviation pooled over
    the devices."""
    from ..compute.device import describe, open_device
    runs, devices = {}, []
    for spec in specs:
        dev = open_device(spec)
        devices.append(f"{describe(dev.device)['name']} ({describe(dev.device)['implementation']} "
                       f"{describe(dev.device)['platform_version']})")
        runs[spec] = [measure(dev, s) for s in seeds]
    names = [k for k in runs[specs[0]][0] if k != "energy_balance_error"]
    q = {}
    for n in names:
        per = np.array([[r[n] for r in runs[s]] for s in specs])        # (devices, seeds)
        q[n] = {"value": float(per[:, 0].mean()),
                "spread": float(np.sqrt(np.mean(per.var(axis=1, ddof=1))))}
    return {"provenance": {"command": "python -m clppm.checks.selftest --reference " + " ".join(specs),
                           "devices": devices, "seeds": list(seeds)},
            "quantities": q}


def main(argv: list[str]) -> int:
    if argv[:1] == ["--reference"]:
        ref = make_reference(argv[1:])
        out = os.path.join(os.path.dirname(os.path.dirname(__file__)), "data", REFERENCE_FILE)
        with open(out, "w", encoding="utf-8") as f:
            json.dump(ref, f, indent=1)
            f.write("\n")
        print(f"wrote {out}")
        return 0
    return _child(argv[0])


if __name__ == "__main__":
    code = main(sys.argv[1:])
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)                   # no interpreter teardown: PoCL 3.0 can abort in it
