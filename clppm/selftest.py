"""A known-answer self-test of one OpenCL device, run in a child process.

OpenCL implementations fail in ways a build does not show: pip's PoCL 3.0 compiles a kernel's
work-group function at its first launch and aborts the process there on some CPUs (LLVM 14 and a
float16 sqrt on AMD Zen 4); a kernel cache left by a crash yields programs without kernels;
vectorisers miscompile.  So before clppm renders on a device it runs a tiny scene through every
kernel family (:mod:`clppm.tiny`'s scene) on it, *in a child process*, and compares what comes
back with values stored in the package (``clppm/data/selftest_reference.json``):

* the photon pass's tallies (specular, Rd, Tt, A) and the images' band groups of the layer and
  beam estimators and of the path tracer, each within :data:`SIGMAS` seed-to-seed standard
  deviations of the stored value (the spread over :data:`REFERENCE_SEEDS` seeds; an
  implementation that rounds differently diverges by about one of those);
* energy conservation of the photon pass (specular + Rd + Tt + A + lost + missed = 1);
* integer results exactly: the photon grid's queries against brute force.

A child that aborts, is killed by a signal or hangs past :data:`TIMEOUT_S` fails the test with one
line naming the kernel it was launching (the child launches each kernel's first time
synchronously and says so).  The result is cached per user, per (device, driver version, clppm
version and kernel sources): ``clppm devices`` shows it and ``clppm devices --check`` reruns it.
A device that fails is never chosen by default (:func:`clppm.device.select_device`).

``CLPPM_SELF_TEST=0`` turns the self-test off (the child itself runs with it off).
``python -m clppm.selftest P:D`` is the child; ``python -m clppm.selftest --reference P:D ...``
remakes the stored reference.
"""
from __future__ import annotations

import copy
import hashlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass

import numpy as np

#: seeds the stored spread is measured over (the self-test itself runs the first)
REFERENCE_SEEDS = tuple(range(1, 13))
#: tolerance in seed-to-seed standard deviations
SIGMAS = 6.0
#: the photon pass's energy balance (tallies summed against the photons' weight)
ENERGY_TOL = 1e-4
#: a child that has not answered after this long is taken as hung
TIMEOUT_S = float(os.environ.get("CLPPM_SELF_TEST_TIMEOUT", "240"))
#: photons of the tally check, and of each image's pass
TRACE_PHOTONS, IMAGE_PHOTONS = 20000, 40000
RESOLUTION = (8, 6)
PT_PASSES = 16                  # path-traced passes (one path per pixel and pass)
GROUPS = 3                      # band groups of an image compared

REFERENCE_FILE = "selftest_reference.json"
STAGE = "clppm-selftest-stage: "
RESULT = "clppm-selftest-result: "


@dataclass(frozen=True)
class SelfTest:
    """One device's self-test: passed or not, how long it took, and why it failed (one line)."""

    passed: bool
    seconds: float
    reason: str = ""
    checked: str = ""               # when it ran (UTC, ISO 8601)
    cached: bool = False            # read from the cache rather than run now

    def line(self) -> str:
        """What ``clppm devices`` prints."""
        when = f" (cached, {self.checked})" if self.cached else ""
        if self.passed:
            return f"self-test: passed in {self.seconds:.1f} s{when}"
        return f"self-test: FAILED: {self.reason}{when}"


def enabled() -> bool:
    return os.environ.get("CLPPM_SELF_TEST", "1").lower() not in ("0", "off", "no", "false")


# --- what the child measures ------------------------------------------------------------------

def _band_groups(img: np.ndarray) -> list[float]:
    """Mean radiance of the image in GROUPS contiguous band groups."""
    nb = img.shape[-1]
    return [float(img[..., g].mean()) for g in np.array_split(np.arange(nb), GROUPS)]


def measure(dev, seed: int = REFERENCE_SEEDS[0]) -> dict:
    """Every known-answer quantity of the tiny scene on ``dev`` (a :class:`clppm.device.Device`)
    at ``seed``: name -> value.  Raises AssertionError where an exact check fails."""
    from . import config, hashgrid, pathtracer, photonpass, progressive, tiny, volume
    cfg = config.override(tiny.tiny_config(photons=IMAGE_PHOTONS, resolution=RESOLUTION),
                          "render", "seed", int(seed))
    vol = volume.build(cfg, "self-test forearm")
    rep = photonpass.trace_report(photonpass.PhotonPass(dev, vol, cfg), TRACE_PHOTONS, batches=4)
    out = {k: float(rep[k]) for k in ("specular", "Rd", "Tt", "A")}
    out["energy_balance_error"] = float(rep["energy_balance_error"])
    for est in ("layer", "beam"):
        res = progressive.render(config.override(copy.deepcopy(cfg), "render", "estimator", est),
                                 dev=dev)
        out.update({f"{est}_group{i}": v for i, v in enumerate(_band_groups(res.spectral))})
    flat = config.override(tiny.tiny_config("forearm_flat.toml", photons=IMAGE_PHOTONS,
                                            resolution=RESOLUTION), "render", "seed", int(seed))
    res = pathtracer.render_pt(flat, passes=PT_PASSES, dev=dev)
    out.update({f"pt_group{i}": v for i, v in enumerate(_band_groups(res.spectral))})
    tiny._grid_queries(dev, hashgrid)              # exact: grid queries = brute force
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
    os.environ["CLPPM_SELF_TEST_CHILD"] = "1"      # clppm.device.launch: first launches in sync
    from .device import DeviceError, open_device
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


# --- the parent: run, classify, cache -----------------------------------------------------------

def _signal_name(rc: int) -> str:
    try:
        return signal.Signals(-rc).name
    except ValueError:
        return f"signal {-rc}"


def _classify(rc: int | None, out: str, err: str, seconds: float) -> SelfTest:
    """A SelfTest from the child's exit status and output."""
    stages = [ln[len(STAGE):] for ln in out.splitlines() if ln.startswith(STAGE)]
    where = f" in {stages[-1]}" if stages else ""
    results = [ln[len(RESULT):] for ln in out.splitlines() if ln.startswith(RESULT)]
    if rc is None:
        return SelfTest(False, seconds, f"hung: no answer in {TIMEOUT_S:.0f} s{where}")
    if results:
        r = json.loads(results[-1])
        if r["bad"] and not r["values"]:
            return SelfTest(False, seconds, r["bad"][0][:400])
        if r["bad"]:
            return SelfTest(False, seconds, "wrong results: " + "; ".join(r["bad"][:3])
                            + (f" (+{len(r['bad']) - 3} more)" if len(r["bad"]) > 3 else ""))
        return SelfTest(True, seconds)
    if rc < 0:
        return SelfTest(False, seconds, f"aborted ({_signal_name(rc)}){where}")
    last = [ln.strip() for ln in err.splitlines() if ln.strip()]
    why = last[-1][:300] if last else f"exit status {rc}"
    return SelfTest(False, seconds, f"exit status {rc}{where}: {why}")


def run_child(spec: str, impl: str = "", timeout: float | None = None) -> SelfTest:
    """Run the self-test of device ``spec`` ("P:D", of implementation ``impl``) in a child."""
    timeout = TIMEOUT_S if timeout is None else timeout
    env = {**os.environ, "CLPPM_SELF_TEST": "0", "PYTHONUNBUFFERED": "1"}
    env.pop("PYOPENCL_CTX", None)
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", "clppm.selftest", spec], env=env, timeout=timeout,
                           capture_output=True, text=True, stdin=subprocess.DEVNULL)
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as e:
        rc = None
        out = e.stdout.decode(errors="replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
        err = ""
    res = _classify(rc, out, err, time.perf_counter() - t0)
    if rc is None or rc < 0:
        from .device import forget_kernel_cache
        forget_kernel_cache(impl)        # a crashed or killed compile may have left a broken entry
    return res


def cache_dir() -> str:
    base = os.environ.get("CLPPM_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "clppm")
    return os.path.join(base, "selftest")


def _sources_digest() -> str:
    """The kernel sources, this module and the reference: a change of any reruns the self-test."""
    from importlib import resources
    h = hashlib.sha256()
    kdir = resources.files("clppm.kernels")
    for f in sorted(kdir.iterdir(), key=lambda p: p.name):
        if f.name.endswith((".cl", ".h")):
            h.update(f.name.encode() + f.read_bytes())
    h.update(resources.files("clppm.data").joinpath(REFERENCE_FILE).read_bytes())
    with open(__file__, "rb") as f:
        h.update(f.read())
    return h.hexdigest()


def cache_key(device) -> str:
    """One self-test per (device, driver version, clppm version, kernel sources, fault switch)."""
    from . import __version__
    d = device
    parts = [d.platform.name, d.platform.version, d.name, d.version, d.driver_version,
             __version__, _sources_digest(), os.environ.get("CLPPM_FAULT", "")]
    return hashlib.sha256("\0".join(p.strip() for p in parts).encode()).hexdigest()[:24]


def _cache_path(device) -> str:
    return os.path.join(cache_dir(), cache_key(device) + ".json")


def cached(device) -> SelfTest | None:
    try:
        with open(_cache_path(device), encoding="utf-8") as f:
            return SelfTest(**{**json.load(f), "cached": True})
    except (OSError, ValueError, TypeError):
        return None


def _store(device, res: SelfTest) -> None:
    path = _cache_path(device)
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), prefix=".selftest.")
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump({k: v for k, v in asdict(res).items() if k != "cached"}, f)
        os.replace(tmp, path)
    except OSError:
        pass                                        # no writable cache: it runs again next time


def check(device, spec: str, rerun: bool = False) -> SelfTest:
    """The self-test of ``device`` (reachable as ``spec``): cached, else run now and cached."""
    if not rerun:
        hit = cached(device)
        if hit is not None:
            return hit
    from .device import implementation
    res = run_child(spec, implementation(device))
    res = SelfTest(res.passed, res.seconds, res.reason,
                   time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    _store(device, res)
    return res


# --- the stored reference ------------------------------------------------------------------------

def make_reference(specs: list[str], seeds=REFERENCE_SEEDS) -> dict:
    """Measure every quantity at ``seeds`` on each device of ``specs``: the value is the first
    seed's mean over the devices, the spread the seed-to-seed standard deviation pooled over
    the devices."""
    from .device import describe, open_device
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
    return {"provenance": {"command": "python -m clppm.selftest --reference " + " ".join(specs),
                           "devices": devices, "seeds": list(seeds)},
            "quantities": q}


def main(argv: list[str]) -> int:
    if argv[:1] == ["--reference"]:
        ref = make_reference(argv[1:])
        out = os.path.join(os.path.dirname(__file__), "data", REFERENCE_FILE)
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
