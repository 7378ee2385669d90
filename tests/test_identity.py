"""Small renders are byte-identical to stored hashes: in-process, stopped and resumed, on a
2-worker Dask cluster, the path tracer (straight and resumed) and paper mode.

A change meant to leave the pictures alone (a refactor, a faster kernel) must keep these.  Each
hash is SHA-256 over the EXR's channels (names and float32 pixels), from the command line as a
user runs it.  The bytes depend on the OpenCL implementation, its version and the device (the
same seed on the same device gives the same bytes, not across devices), so tests/data/identity.json
holds one set per implementation, driver version and device; on a device without a stored set
the comparison with it skips and says so, and the equivalences that hold on any device (resumed
or on two Dask workers = in one go) are checked all the same.  About a minute on 2 idle cores.

    python tests/test_identity.py            # hashes on PYOPENCL_CTX's device, against the stored
    python tests/test_identity.py --store    # store them for this device (on a tree known right)
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile

import numpy as np
import pytest

STORE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "identity.json")

BASE = ["forearm", "--resolution", "32x24", "--photons", "20000", "--seed", "3"]
PT = ["forearm_flat", "--integrator", "pt", "--resolution", "12x9", "--seed", "2",
      "--set", "render.pt_samples_per_pass=4"]


def cases(tmp: str, spec: str) -> dict[str, list[list[str]]]:
    """Each case: the ``clppm render`` runs in order; the last one's ``-o`` is hashed."""
    return {
        "in-process": [[*BASE, "--passes", "3", "-o", f"{tmp}/a.exr"]],
        "resumed": [[*BASE, "--passes", "2", "-o", f"{tmp}/b.exr"],
                    [*BASE, "--passes", "3", "-o", f"{tmp}/b.exr", "--resume", f"{tmp}/b.ckpt.npz"]],
        "dask, 2 workers": [[*BASE, "--passes", "3", "--devices", f"{spec},{spec}", "-o", f"{tmp}/c.exr"]],
        "path tracer": [[*PT, "--passes", "2", "-o", f"{tmp}/d.exr"]],
        "path tracer, resumed": [[*PT, "--passes", "1", "-o", f"{tmp}/e.exr"],
                                 [*PT, "--passes", "2", "-o", f"{tmp}/e.exr", "--resume", f"{tmp}/e.ckpt.npz"]],
        "paper mode": [["forearm", "--paper", "--resolution", "24x18", "--photons", "20000", "--passes", "2",
                        "--seed", "4", "-o", f"{tmp}/f.exr"]],
    }


CASES = list(cases("", "0:0"))


def exr_hash(path: str) -> str:
    import OpenEXR
    ch = OpenEXR.File(path).channels()
    h = hashlib.sha256()
    for k in sorted(ch):
        h.update(k.encode())
        h.update(np.ascontiguousarray(ch[k].pixels).tobytes())
    return h.hexdigest()[:16]


def device_spec(device) -> str:
    """``P:D`` of an opened pyopencl device (``--devices`` takes indices)."""
    from clppm.compute.device import list_devices
    return next(f"{ip}:{idev}" for ip, idev, _, d in list_devices() if d.int_ptr == device.int_ptr)


def implementation_key(info: dict) -> str:
    """What the stored hashes are keyed by: the implementation, its driver version, the device's
    name and OpenCL version string (PoCL's names the CPU target it compiles for), e.g.
    ``intel 2026.22.10.0.01_160000 on Intel(R) Xeon(R) Processor (OpenCL 3.1 (Build 0))``."""
    return f"{info['implementation']} {info['driver_version']} on {info['name']} ({info['version']})"


def render_case(runs: list[list[str]], spec: str) -> str:
    """Run one case's renders on device ``spec``; the hash of the last image."""
    env = dict(os.environ, PYOPENCL_CTX=spec)
    for args in runs:
        r = subprocess.run([sys.executable, "-m", "clppm.cli", "render", *args, "-q"], env=env,
                           capture_output=True, text=True)
        assert r.returncode == 0, f"clppm render {' '.join(args)} exited {r.returncode}\n{r.stderr[-2000:]}"
    return exr_hash(runs[-1][runs[-1].index("-o") + 1])


def load_store() -> dict:
    with open(STORE, encoding="utf-8") as f:
        return json.load(f)


#: cases that must give the same bytes as each other on any device: a render stopped and
#: resumed, or split over two Dask workers, is the render made in one go
SAME = {"resumed and Dask": ("in-process", "resumed", "dask, 2 workers"),
        "path tracer resumed": ("path tracer", "path tracer, resumed")}


class Rendered:
    """Each case's hash on the session's device, rendered once when first asked for."""

    def __init__(self, spec: str, tmp: str):
        self.spec, self.tmp, self.hashes = spec, tmp, {}

    def __getitem__(self, case: str) -> str:
        if case not in self.hashes:
            if case.startswith("dask"):
                pytest.importorskip("distributed")
            self.hashes[case] = render_case(cases(self.tmp, self.spec)[case], self.spec)
        return self.hashes[case]


@pytest.fixture(scope="module")
def rendered(dev, tmp_path_factory):
    return Rendered(device_spec(dev.device), str(tmp_path_factory.mktemp("identity")))


@pytest.fixture(scope="module")
def stored(dev):
    """The stored hashes of the session's device, or None where none are stored."""
    from clppm.compute.device import describe
    key = implementation_key(describe(dev.device))
    return {k: v for k, v in load_store().items() if not k.startswith("_")}.get(key)


@pytest.mark.slow
@pytest.mark.parametrize("group", SAME)
def test_equivalent_runs_give_the_same_bytes(rendered, group):
    """On every device, stored hashes or not: the same seed gives the same bytes whether the
    render ran in one go, was stopped and resumed, or ran on two Dask workers."""
    first, *rest = SAME[group]
    for case in rest:
        assert rendered[case] == rendered[first], f"{case} differs from {first}"


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES)
def test_render_is_byte_identical_to_the_stored_hash(rendered, stored, case):
    if stored is None or case not in stored:
        pytest.skip(f"{case}: no stored hash for this implementation and device (the bytes depend "
                    "on both; test_equivalent_runs_give_the_same_bytes checks it here; python "
                    "tests/test_identity.py --store stores a set)")
    assert rendered[case] == stored[case], f"{case}: the image's bytes changed"


def main(argv: list[str]) -> int:
    from clppm.compute.device import describe, open_device
    dev = open_device(None)
    spec, key = device_spec(dev.device), implementation_key(describe(dev.device))
    store = load_store()
    old = store.get(key, {})
    tmp = tempfile.mkdtemp(prefix="clppm-identity-")
    new = {}
    print(f"{key} ({spec})")
    for name, runs in cases(tmp, spec).items():
        new[name] = render_case(runs, spec)
        print(f"  {name:22s} {new[name]}  {'same' if old.get(name) == new[name] else 'stored: ' + old.get(name, '-')}",
              flush=True)
    if "--store" in argv:
        store[key] = new
        with open(STORE, "w", encoding="utf-8") as f:
            json.dump(store, f, indent=1, sort_keys=True)
            f.write("\n")
        print(f"stored in {STORE}")
        return 0
    return 0 if new == old else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
