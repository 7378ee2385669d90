"""Device selection by implementation, local sizes from queried limits, the ICD registration."""
import os

import pytest

from clppm.compute import device as D
from clppm.compute import icd


def test_select_by_implementation_name(dev):
    impl = D.implementation(dev.device)
    got = D.select_device(impl)
    assert D.implementation(got) == impl
    assert D.select_device(impl.upper()) == got              # case-insensitive


def test_local_size_halves_below_the_queried_limit(dev, monkeypatch):
    import pyopencl as cl
    from clppm.compute.programs import quiet_compiler_chatter
    quiet_compiler_chatter()                                  # Intel's build log is not a warning
    prg = cl.Program(dev.ctx, "__kernel void k(__global int* a) { a[get_global_id(0)] = 1; }").build()
    knl = cl.Kernel(prg, "k")
    assert D.local_size(knl, dev.device, 64) == 64 or D.kernel_limits(knl, dev.device)["work_group_size"] < 64
    monkeypatch.setattr(D, "kernel_limits", lambda k, d: {"work_group_size": 40, "preferred_multiple": 8,
                                                          "private_mem_bytes": 0, "local_mem_bytes": 0})
    knl2 = cl.Kernel(prg, "k")                                # a new kernel object: queried afresh
    assert D.local_size(knl2, dev.device, 128) == 32
    row = next(r for r in D.launched(dev.device) if r["kernel"] == "k")
    assert row["local_size"] in (32, 64)


def test_icd_register_writes_real_path_and_keeps_previous(tmp_path, monkeypatch):
    lib = tmp_path / "lib" / "libintelocl.so"
    lib.parent.mkdir()
    lib.write_bytes(b"")
    prev = tmp_path / "vendors"
    prev.mkdir()
    (prev / "other.icd").write_text("/usr/lib/libother.so\n")
    monkeypatch.setenv("OCL_ICD_VENDORS", str(prev))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("CLPPM_NO_ICD", raising=False)
    monkeypatch.setattr(icd, "intel_cpu_library", lambda: str(lib))
    d = icd.register()
    assert d is not None and os.environ["OCL_ICD_VENDORS"] == d
    assert open(os.path.join(d, "clppm-intel-cpu.icd")).read().strip() == str(lib)
    assert os.path.realpath(os.path.join(d, "other.icd")) == str(prev / "other.icd")
    assert icd.register() is None                            # already listed: nothing to do
    assert os.environ["OCL_ICD_VENDORS"] == d


def test_icd_register_off_switch(monkeypatch):
    monkeypatch.setenv("CLPPM_NO_ICD", "1")
    assert icd.register() is None


def test_link_duplicates_makes_identical_copies_one_file(tmp_path):
    """Intel's wheels install libX.so, libX.so.1 and libX.so.1.2 as copies: the identical ones
    become hard links to the fully versioned file, with the same bytes under every name; a copy
    whose bytes differ, and a library of another name, stay as they are."""
    lib = tmp_path / "lib"
    lib.mkdir()
    body = os.urandom(4096)
    for n in ("libfoo.so", "libfoo.so.1", "libfoo.so.1.2"):
        (lib / n).write_bytes(body)
    (lib / "libbar.so").write_bytes(body[:2048])
    (lib / "libbar.so.3").write_bytes(body[:2047] + bytes([body[2047] ^ 1]))   # same size, other bytes
    (lib / "libbaz.so").write_bytes(body)                                      # same bytes, other name
    paths = [str(p) for p in lib.iterdir()]
    assert icd.link_duplicates(paths) == 2 * 4096
    ino = {n: os.stat(lib / n).st_ino for n in os.listdir(lib)}
    assert ino["libfoo.so"] == ino["libfoo.so.1"] == ino["libfoo.so.1.2"]
    assert len({ino["libbar.so"], ino["libbar.so.3"], ino["libbaz.so"], ino["libfoo.so"]}) == 4
    for n in ("libfoo.so", "libfoo.so.1", "libfoo.so.1.2", "libbaz.so"):
        assert (lib / n).read_bytes() == body
    assert sorted(os.listdir(lib)) == sorted(["libfoo.so", "libfoo.so.1", "libfoo.so.1.2", "libbar.so",
                                              "libbar.so.3", "libbaz.so"])     # no temporary left
    assert icd.link_duplicates(paths) == 0                                     # done once
