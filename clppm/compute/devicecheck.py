"""The parent side of a device's known-answer self-test: run the child, classify, cache.

:func:`clppm.compute.device.device_problem` asks :func:`check` before a device is used.  The
test itself (a tiny scene through every kernel family, compared with stored values) runs in a
child process, ``python -m clppm.checks.selftest P:D`` (:mod:`clppm.checks.selftest`): an
implementation that aborts, is killed by a signal or hangs past :data:`TIMEOUT_S` fails the test
with one line naming the kernel it was launching (the child launches each kernel's first time
synchronously and says so).  This side only reads the child's output, so the device layer needs
nothing of the renderer above it.  The result is cached per user, per (device, driver version,
clppm version and kernel sources): ``clppm devices`` shows it and ``clppm devices --check``
reruns it.

``CLPPM_SELF_TEST=0`` turns the self-test off (the child itself runs with it off).
"""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass

from ..version import __version__

#: the child: ``python -m CHILD P:D``
CHILD = "clppm.checks.selftest"
#: a child that has not answered after this long is taken as hung
TIMEOUT_S = float(os.environ.get("CLPPM_SELF_TEST_TIMEOUT", "240"))
#: the stored values the child compares with (in clppm/data)
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


def run_child(spec: str, on_crash=None, timeout: float | None = None) -> SelfTest:
    """Run the self-test of device ``spec`` ("P:D") in a child; ``on_crash()`` after a child that
    aborted or hung (the device layer drops what its kernel caches may hold of a broken build)."""
    timeout = TIMEOUT_S if timeout is None else timeout
    env = {**os.environ, "CLPPM_SELF_TEST": "0", "PYTHONUNBUFFERED": "1"}
    env.pop("PYOPENCL_CTX", None)
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", CHILD, spec], env=env, timeout=timeout,
                           capture_output=True, text=True, stdin=subprocess.DEVNULL)
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as e:
        rc = None
        out = e.stdout.decode(errors="replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
        err = ""
    res = _classify(rc, out, err, time.perf_counter() - t0)
    if (rc is None or rc < 0) and on_crash is not None:
        on_crash()                       # a crashed or killed compile may have left a broken entry
    return res


def cache_dir() -> str:
    base = os.environ.get("CLPPM_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "clppm")
    return os.path.join(base, "selftest")


def _sources_digest() -> str:
    """The kernel sources, the self-test (both sides) and the reference: a change of any reruns the
    self-test."""
    from importlib import resources
    h = hashlib.sha256()
    kdir = resources.files("clppm.kernels")
    for f in sorted(kdir.iterdir(), key=lambda p: p.name):
        if f.name.endswith((".cl", ".h")):
            h.update(f.name.encode() + f.read_bytes())
    h.update(resources.files("clppm.data").joinpath(REFERENCE_FILE).read_bytes())
    h.update(resources.files("clppm.checks").joinpath("selftest.py").read_bytes())
    with open(__file__, "rb") as f:
        h.update(f.read())
    return h.hexdigest()


def cache_key(device) -> str:
    """One self-test per (device, driver version, clppm version, kernel sources, fault switch)."""
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


def check(device, spec: str, rerun: bool = False, on_crash=None) -> SelfTest:
    """The self-test of ``device`` (reachable as ``spec``): cached, else run now and cached
    (:func:`clppm.compute.device.self_test` passes ``on_crash``, see :func:`run_child`)."""
    if not rerun:
        hit = cached(device)
        if hit is not None:
            return hit
    name = f"{spec} ({device.name.strip()}, {device.platform.name.strip()})"
    say(f"self-testing device {name}: a known-answer forearm through every kernel, "
        "once per device, driver and clppm version (usually 10-40 s)...")
    res = run_child(spec, on_crash)
    res = SelfTest(res.passed, res.seconds, res.reason,
                   time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    say(f"device {spec} {res.line()}")
    _store(device, res)
    return res


#: whether :func:`check` says on stderr that it runs a self-test (the CLI's ``-q`` turns it off)
PROGRESS = {"on": True}


def say(line: str) -> None:
    """One line of the self-test's progress on stderr, unless :data:`PROGRESS` is off."""
    if PROGRESS["on"]:
        print(line, file=sys.stderr, flush=True)
