"""The program registry (clppm/compute/programs.py): each program is built once per context,
its binary is kept in clppm's own cache folder so that a second process builds nothing new, and
forgetting the cache removes exactly that folder."""
from __future__ import annotations

import os
import subprocess
import sys

from clppm.compute.kernelcall import kernels
from clppm.compute.programs import REGISTRY, BuildSpec, binary_cache_dir, program_cache_dir

BUILD_TWICE = """
import sys
from clppm.compute.device import open_device
from clppm.compute.programs import REGISTRY
dev = open_device()
a = dev.build("hashgrid.cl", {"NB": 5})
b = dev.build("hashgrid.cl", {"NB": 5})
assert a is b
print(REGISTRY.stats.programs)
"""


def _entries(d: str) -> set[str]:
    """Every file below ``d`` with its size, but PoCL's empty lock files (tempfile_*, one per
    process)."""
    return {(os.path.relpath(os.path.join(r, f), d), os.path.getsize(os.path.join(r, f)))
            for r, _, fs in os.walk(d) for f in fs if not f.startswith("tempfile_")}


def test_options_of_a_spec():
    s = BuildSpec.of("x.cl", {"NB": 81, "FLAT": True, "PT_FP64": False, "DISC_KAPPA": 0.5})
    assert s == BuildSpec.of("x.cl", {"DISC_KAPPA": 0.5, "PT_FP64": False, "FLAT": True, "NB": 81})
    assert s.options() == ["-DDISC_KAPPA=0.5f", "-DFLAT=1", "-DNB=81"]
    assert s.defined() == {"DISC_KAPPA", "FLAT", "NB"}


def test_a_program_is_built_once_per_context(dev):
    spec = {"NB": 7}
    n0 = REGISTRY.stats.programs
    a = dev.build("hashgrid.cl", spec)
    n1 = REGISTRY.stats.programs
    assert dev.build("hashgrid.cl", spec) is a and REGISTRY.stats.programs == n1 <= n0 + 1
    k1 = kernels(dev, "hashgrid.cl", ("grid_count",), spec)["grid_count"]
    assert kernels(dev, "hashgrid.cl", ("grid_count",), spec)["grid_count"] is k1


def test_a_second_process_finds_the_binaries(dev, tmp_path, monkeypatch):
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path), "CLPPM_SELF_TEST": "0"}
    for k in ("PYOPENCL_NO_CACHE", "POCL_CACHE_DIR"):
        env.pop(k, None)
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    d = binary_cache_dir(dev.device)
    assert d.startswith(str(tmp_path))

    def run():
        r = subprocess.run([sys.executable, "-c", BUILD_TWICE], env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return int(r.stdout.split()[-1])

    assert run() == 1
    first = _entries(d)
    assert first, "the first build left no binary in clppm's cache folder"
    assert run() == 1                                   # one program, loaded, per process
    assert _entries(d) == first                         # and nothing new was compiled into it


def test_forgetting_drops_clppm_s_folder_only(tmp_path, monkeypatch):
    from clppm.compute.device import forget_kernel_cache
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    d = program_cache_dir()
    os.makedirs(os.path.join(d, "entry"))
    other = tmp_path / "pyopencl"
    other.mkdir()
    forget_kernel_cache("intel")
    assert not os.path.exists(d) and other.is_dir()
