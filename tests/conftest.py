"""Shared fixtures: one OpenCL device for the whole session (PYOPENCL_CTX / the first device).
Nothing in the tests mutates it; programs it builds are cached on it, so every module after the
first reuses them.  bench/studies is importable: tests run small versions of its studies' scenes."""
from __future__ import annotations

import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench", "studies"))


@pytest.fixture(scope="session")
def dev():
    from clppm.compute.device import DeviceError, open_device
    try:
        return open_device(None)
    except DeviceError as e:            # pragma: no cover - no OpenCL here
        pytest.skip(str(e))


_EXIT = {}


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session, exitstatus):
    _EXIT["status"] = int(exitstatus)


def pytest_unconfigure(config):
    """End with pytest's own exit status, without the interpreter's teardown: pip's PoCL 3.0 can
    abort there ("still have references to IRs") and SIGABRT would replace the status."""
    import os
    import sys
    if "status" in _EXIT and os.environ.get("CLPPM_PYTEST_PLAIN_EXIT") != "1":
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT["status"])
