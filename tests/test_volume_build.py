"""The volume builder (clppm/scene/volume.py) gives the arrays of the builder before it was
vectorised (tests/volume_reference.py, kept as it was), byte for byte: the generated relief,
the papillae, the interfaces (snapped to the voxels or smooth), their packing and the smooth
surfaces' bounds, on open and periodic sides; and a volume read back from the store on disk
is the one built."""
from __future__ import annotations

import copy
import os
import time

import numpy as np
import pytest

import volume_reference as ref
from clppm import config as C
from clppm.scene import volume

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARRAYS = ("wl", "n", "thickness", "mua", "mus", "g", "iface", "heights", "smooth", "tiles")
SCALARS = ("names", "x0", "y0", "dx", "dy", "nx", "ny", "dz", "lateral", "n_above", "n_below",
           "surface", "cell", "info")


def _config(name: str, **changes) -> dict:
    raw = copy.deepcopy(C.load(os.path.join(ROOT, "configs", name)))
    for key, value in changes.items():
        sec, k = key.split(".")
        raw[sec][k] = value
    return raw


CASES = {
    "forearm": ("forearm.toml", {}),
    "forearm voxels, periodic": ("forearm.toml", {"model.size_mm": [2.0, 1.5], "model.surface": "voxels",
                                                  "model.lateral": "periodic"}),
    "forearm voxels, open, 10 um": ("forearm.toml", {"model.size_mm": [1.7, 2.3], "model.surface": "voxels",
                                                     "model.lateral_voxel_um": 10.0}),
    "forearm smooth, periodic": ("forearm.toml", {"model.size_mm": [1.5, 2.0], "model.lateral": "periodic"}),
    "forearm unquantized": ("forearm.toml", {"model.size_mm": [1.0, 1.0], "model.surface": "voxels",
                                             "model.quantize": False}),
    "cheek": ("cheek.toml", {"model.size_mm": [3.0, 2.0]}),
    "flat": ("forearm_flat.toml", {}),
}


def same(a: volume.Volume, b) -> None:
    for k in ARRAYS:
        x, y = getattr(a, k), getattr(b, k)
        assert (x is None) == (y is None), k
        if x is not None:
            assert x.dtype == y.dtype and x.shape == y.shape, k
            assert x.tobytes() == y.tobytes(), f"{k} differs"
    for k in SCALARS:
        assert getattr(a, k) == getattr(b, k), k


@pytest.mark.parametrize("case", sorted(CASES))
def test_volume_is_the_reference_builders(case, monkeypatch):
    monkeypatch.setenv("CLPPM_NO_VOLUME_STORE", "1")
    name, changes = CASES[case]
    cfg = C.validate(_config(name, **changes), case)
    same(volume._build(cfg), ref._build(cfg))


def test_stored_volume_is_the_built_one(tmp_path, monkeypatch):
    """The first build stores the forearm's volume, a second process-fresh build reads it back
    (the same arrays, in a fraction of the build's time); a damaged file is built again."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("CLPPM_NO_VOLUME_STORE", raising=False)
    cfg = C.validate(_config("forearm.toml"), "forearm")
    key = volume.geometry_key(cfg)
    t0 = time.perf_counter()
    built = volume._stored(key, cfg, "forearm")
    t_build = time.perf_counter() - t0
    files = os.listdir(volume.store_dir())
    assert len(files) == 1 and files[0].endswith(".npz"), files
    t0 = time.perf_counter()
    read = volume._stored(key, cfg, "forearm")
    t_read = time.perf_counter() - t0
    assert read is not built
    same(read, built)
    assert t_read < t_build / 3, (t_read, t_build)
    path = os.path.join(volume.store_dir(), files[0])
    with open(path, "r+b") as f:
        f.truncate(1000)
    same(volume._stored(key, cfg, "forearm"), built)
    small = C.validate(_config("forearm.toml", **{"model.size_mm": [1.0, 1.0]}), "small")
    volume._stored(volume.geometry_key(small), small, "small")       # small volumes are not kept
    assert len(os.listdir(volume.store_dir())) == 1


def test_store_keeps_the_most_recent(tmp_path, monkeypatch):
    """At most STORE_MAX volumes stay on disk: the least recently used go first; with
    CLPPM_NO_VOLUME_STORE nothing is written."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("CLPPM_NO_VOLUME_STORE", raising=False)
    monkeypatch.setattr(volume, "STORE_COLUMNS", 1)
    monkeypatch.setattr(volume, "STORE_MAX", 2)
    cfgs = [C.validate(_config("forearm.toml", **{"model.size_mm": [0.5 + 0.1 * i, 0.5]}), f"v{i}")
            for i in range(3)]
    names = []
    for i, cfg in enumerate(cfgs):
        volume._stored(volume.geometry_key(cfg), cfg, f"v{i}")
        names.append(volume._digest(volume.geometry_key(cfg)) + ".npz")
        os.utime(os.path.join(volume.store_dir(), names[-1]), (i + 1, i + 1))   # distinct ages
    assert sorted(os.listdir(volume.store_dir())) == sorted(names[1:])
    monkeypatch.setenv("CLPPM_NO_VOLUME_STORE", "1")
    more = C.validate(_config("forearm.toml", **{"model.size_mm": [0.9, 0.5]}), "more")
    volume._stored(volume.geometry_key(more), more, "more")
    assert sorted(os.listdir(volume.store_dir())) == sorted(names[1:])
