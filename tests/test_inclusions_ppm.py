"""PPM (its eye pass and gathers) sees inclusions: kernels/eye.cl, gather.cl, inclusion.h.

* The eye pass: every eye-ray piece of a flat forearm with a vessel lies in one material, the one
  its record names (the layer's, or the vessel's inside it: split at the quadric's crossings),
  against the numpy material map of tests/test_inclusions.py; a pixel over the vessel's axis has
  vessel pieces from the vessel's top down.
* PPM against the path tracer on that forearm (bench/studies/vessel.py, small): per 50-nm band
  group the image mean and the vessel's contrast (columns over it / columns away) agree within
  the bounds stated below, and both see the vessel darker and redder than the skin beside it
  (blood absorbs the green far more than the red).
"""
from __future__ import annotations

import os
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "bench", "studies"))

from vessel import vessel_figures, vessel_scene          # noqa: E402

from clppm.run import entry                               # noqa: E402

# PPM: 4 passes of 400,000 stored photons, K = 200 in the first search (a radius small enough
# that the vessel, 0.4 mm across, is not blurred away: with the default's K = 2000 the contrast
# reads 0.78 in the green where the path tracer's is 0.44).  PT: 4 x 128 paths per pixel.
RES, PASSES, PHOTONS, K = (17, 13), 4, 400_000, 200
PT_PASSES, PT_SAMPLES = 4, 128
# Bounds, from 2 PPM seeds and 2 PT seeds on PoCL (bench/studies/vessel.py prints them):
# image mean PPM / PT - 1 within -3.4 % .. +2.5 % per group (the default mode's bias on the
# flat forearm and both noises); contrast PPM / PT - 1 within -2 % .. +17 % (PT's noise on the
# 13 pixels over the vessel, ~5 % per group, and PPM's blur by its radius, which weakens the
# contrast: +8 % on average).  Without the gathers' material handling (the photons of the
# dermis counted at the vessel's transmittance) the red groups' contrast reads 1.2 against 0.6.
MEAN_BOUND = 0.06
CONTRAST_LO, CONTRAST_HI = -0.12, 0.35


def _material(vol, p: np.ndarray) -> np.ndarray:
    depth = vol.layer_depths()
    m = np.clip(np.searchsorted(depth, -p[:, 2], side="right") - 1, 0, vol.nl - 1)
    for i in reversed(range(vol.ninc)):
        m = np.where(vol.inclusions[i].contains(p), vol.nl + i, m)
    return m


def test_eye_pieces_lie_in_the_material_they_name(dev):
    from clppm.integrators import ppm
    from clppm.request import RenderRequest
    cfg = vessel_scene(RES, 1, 20_000, seed=1)
    sc = ppm.Pipeline.build(RenderRequest.of(cfg, dev=dev), dev)
    e, vol = sc.eye, sc.vol
    assert vol.ninc == 1
    g = e.geo.get()[:2 * e.npieces]
    s, d = g[0::2], g[1::2]
    s0 = np.stack([s["x"], s["y"], s["z"]], -1).astype(float)
    dv = np.stack([d["x"], d["y"], d["z"]], -1).astype(float)
    ln, code = s["w"].astype(float), d["w"].astype(int)
    pcs = e.pieces.get()[:e.npieces]
    assert np.array_equal(pcs["y"].astype(int), code)
    keep = ln > 0.05                                    # a piece shorter than the rounding: no test
    for f in (0.5, 0.02, 0.98):                         # its middle and near both ends
        m = _material(vol, s0[keep] + (f * ln[keep])[:, None] * dv[keep])
        bad = m != code[keep]
        assert bad.mean() < 1e-3, (f, bad.sum(), np.unique(code[keep][bad]), np.unique(m[bad]))
    assert (code == vol.nl).sum() > 50                  # the vessel's pieces
    # the pixel over the vessel's axis (the middle column: x = 5 mm): its first vessel piece
    # starts at the vessel's top, 100 um down
    w, h = RES
    pix = (h // 2) * w + w // 2
    rs = e.ray_start.get()
    pp = e.pt_piece.get()
    k0, k1 = pp[rs[pix]], pp[rs[pix + 1]]
    ks = [k for k in range(k0, k1) if code[k] == vol.nl]
    assert ks, "no vessel piece under the vessel's axis"
    assert abs(s0[ks[0], 2] + 100.0) < 0.05, s0[ks[0]]


@pytest.fixture(scope="module")
def vessel_renders(dev):
    pt_cfg = vessel_scene(RES, PT_PASSES, PHOTONS, PT_SAMPLES, seed=101)
    ppm_cfg = vessel_scene(RES, PASSES, PHOTONS, PT_SAMPLES, seed=1, initial_photons=K)
    pt = vessel_figures(pt_cfg, entry.render_pt(pt_cfg, dev=dev).spectral)
    ppm = vessel_figures(ppm_cfg, entry.render(ppm_cfg, dev=dev).spectral)
    return ppm, pt


def test_ppm_matches_pt_per_band_group_with_a_vessel(vessel_renders):
    ppm, pt = vessel_renders
    for grp in pt:
        if grp == "380-425":            # little light and the noisiest contrast: means only
            assert abs(ppm[grp]["mean"] / pt[grp]["mean"] - 1) <= MEAN_BOUND, (grp, ppm[grp], pt[grp])
            continue
        assert abs(ppm[grp]["mean"] / pt[grp]["mean"] - 1) <= MEAN_BOUND, (grp, ppm[grp], pt[grp])
        r = ppm[grp]["contrast"] / pt[grp]["contrast"] - 1
        assert CONTRAST_LO <= r <= CONTRAST_HI, (grp, ppm[grp]["contrast"], pt[grp]["contrast"])


def test_vessel_darker_and_redder_in_both(vessel_renders):
    """Blood absorbs the green (the haemoglobin bands near 540-580 nm) far more than the red:
    over the vessel the skin is darker in every group from 430 nm on, most in the green, so
    the green's contrast is below the red's (redder)."""
    for fig in vessel_renders:
        c = {g: v["contrast"] for g, v in fig.items()}
        assert all(c[g] < 0.9 for g in c if g != "380-425"), c
        assert c["530-575"] < 0.65 and c["580-625"] < 0.65, c
        assert c["530-575"] < c["630-675"] < 1.0 and c["580-625"] < c["680-725"], c
