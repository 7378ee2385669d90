"""Shared fixtures: one OpenCL device for the whole session (PYOPENCL_CTX / the first device).
Nothing in the tests mutates it; programs it builds are cached on it, so every module after the
first reuses them."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def dev():
    from clppm.device import DeviceError, open_device
    try:
        return open_device(None)
    except DeviceError as e:            # pragma: no cover - no OpenCL here
        pytest.skip(str(e))
