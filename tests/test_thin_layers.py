"""A layer thinner than anything a photon can resolve costs nothing.

0 is refused as a thickness, so a tiny one is how a layer is switched off.  Snapped to the voxel
grid (or under 1 nm everywhere) such a layer has two coincident interfaces; a photon reflected
by both (total internal reflection toward the air above and the dermis below, at the relief's
tilted normals) did not move and ran to max_events (10^6 steps): the photon pass took 35x as
long.  Now the layer is absent (light crosses it with the index of the layer below), and a
photon trapped between coincident interfaces anywhere is counted lost after 1000 still steps,
the fate max_events gave it.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from clppm import config as C
from clppm.integrators import photonpass
from clppm.scene import volume


def _forearm(*items):
    cfg = C.load("forearm")
    for item in ("model.size_mm=[2.0,2.0]",) + items:   # the relief, fewer columns to build
        cfg = C.set_item(cfg, item)
    return cfg


def test_vanishing_layer_is_absent():
    vol = volume.build(_forearm("layer.0.thickness_um=1e-30"), "t")
    assert vol.info["absent_layers"] == [C.load("forearm")["layer"][0]["name"]]
    assert vol.n[0] == vol.n[1]                 # crossed as if it were not there
    vol = volume.build(_forearm("layer.0.thickness_um=1e-30", "model.quantize=false"), "t")
    assert vol.info["absent_layers"] and vol.n[0] == vol.n[1]
    normal = volume.build(_forearm(), "t")
    assert normal.info["absent_layers"] == [] and normal.n[0] == 1.5


def _photon_seconds(dev, cfg, photons=20000):
    pp = photonpass.PhotonPass.of_config(dev, volume.build(cfg, "t"), cfg)
    photonpass.trace_report(pp, 2000, batches=2)           # build and warm up
    t0 = time.perf_counter()
    rep = photonpass.trace_report(pp, photons, batches=2)
    return time.perf_counter() - t0, rep


@pytest.mark.parametrize("thickness", ["1e-30", "1"])
def test_thin_layer_costs_nothing(dev, thickness):
    """The photon pass with a 1e-30 um (absent) or 1 um (zero in most columns once snapped)
    stratum corneum takes about as long as with the real one (it took 35x and 6x)."""
    base, rep0 = _photon_seconds(dev, _forearm())
    thin, rep = _photon_seconds(dev, _forearm(f"layer.0.thickness_um={thickness}"))
    assert thin < 3.0 * base + 0.5, (thin, base)
    assert rep["lost"] < rep0["lost"] + 0.01, (rep["lost"], rep0["lost"])
    assert np.isfinite(rep["Rd"]) and rep["energy_balance_error"] < 1e-6
