"""PPM (its eye pass and beam gather) sees inclusions and chromophore maps on the relief:
kernels/eye.cl, beam.h, gather.cl, inclusion.h, maps.h.

On the relief a piece's record is material + 256 layer (geo; the pieces' own record keeps the
material): the beam gather measures a piece's depth in its layer's own coordinates (the layer's
top and bottom at the ray's column, the photons of that layer only) and takes its extinction and
the inclusions' mu_s ratio from its material.

* The eye pass, a vessel on the relief (smooth surfaces and the voxel walk): every piece lies in
  the material it records (split at the quadric's crossings) and records the layer of the sample
  point whose cell holds it (cells never cross a layer: method e gives every layer visit a point).
* The eye pass, maps on the relief: in a mapped layer every piece lies in one column.
* PPM against the path tracer on the relief forearm (configs/forearm.toml's furrows and wavy
  junction on configs/forearm_vein.toml's / forearm_flat.toml's layers) with a vessel
  (bench/studies/vessel.py, ``relief=True``) and with a freckle and a blood spot
  (bench/studies/freckle.py, ``relief=True``): per 50-nm band group the image mean and the
  contrast (pixels over the vessel / spot against pixels away) within the bounds below, the
  flat tests' (tests/test_inclusions_ppm.py, tests/test_maps_ppm.py) where the relief's figures
  allow them.
* A constant map on the relief renders like the layer given that value (the eye path's and the
  gather's column extinction).
"""
from __future__ import annotations

import tomllib

import numpy as np
import pytest

from freckle import freckle_figures, freckle_scene
from heterogeneous import TEST_BUDGET as BUDGET
from vessel import vessel_figures, vessel_scene

from clppm import config as C                             # noqa: E402
from clppm.analysis.metrics import band_groups            # noqa: E402
from clppm.run import entry                               # noqa: E402

# As the flat tests: bench/studies/heterogeneous.py TEST_BUDGET (PPM 4 passes of 400,000 stored
# photons, K = 200 in the first search; PT 4 x 256 paths per pixel, 17x13 pixels over a 4 mm field).

# Vessel on the relief, bounds.  Measured (Intel's CPU runtime, PT seeds 101-103, PPM seed 1):
#   image mean, PPM / PT - 1 per group: -1.5 % .. +3.4 %; allowed: 5 % (the flat test's);
#   the vessel's contrast per group against PT seed 101: +6 % .. +22 %; PT's own contrast over
#     its three seeds spreads by up to +-10 % per group (the red pooled 0.625, 0.639, 0.684), and
#     PPM's radius blurs the vessel (+10 % on flat layers); allowed: -12 % .. +30 % (the flat
#     test's), from 430 nm on;
#   the red pooled (630-780 nm): PPM 0.699 against PT 0.625-0.684 (+2 % .. +12 %); allowed:
#     -8 % .. +18 % (PT's noise on the relief is twice the flat forearm's at this budget).
MEAN_BOUND = 0.05
CONTRAST_LO, CONTRAST_HI = -0.12, 0.30
RED_LO, RED_HI = -0.08, 0.18
# Maps on the relief, bounds (tests/test_maps_ppm.py's).  Measured (Intel, PT seed 101, PPM seed
# 1): mean -1.9 % .. +2.9 %; each spot's contrast -17 % .. +12 % per group; red pooled -0.9 %.
MAP_MEAN_BOUND = 0.05
MAP_CONTRAST_LO, MAP_CONTRAST_HI = -0.20, 0.25
MAP_RED_BOUND = 0.10


def _pieces(sc):
    e = sc.eye
    g = e.geo.get()[:2 * e.npieces]
    s, d = g[0::2], g[1::2]
    s0 = np.stack([s["x"], s["y"], s["z"]], -1).astype(float)
    dv = np.stack([d["x"], d["y"], d["z"]], -1).astype(float)
    return s0, dv, s["w"].astype(float), d["w"].astype(int)


@pytest.mark.parametrize("surface", ["smooth", "voxels"])
def test_eye_pieces_on_the_relief_record_their_material_and_layer(dev, surface):
    """A vessel (forearm_vein's layers, 100-500 um deep) under the relief.  Caught: a record
    that holds the material only (the gathers would read the vessel's index as its layer: the
    layer asserts), a record whose material is wrong or a split missing at the vessel's wall
    (the containment asserts), the pieces' own record (the sphere estimators' extinction) not
    the material."""
    from clppm.integrators import ppm
    from clppm.request import RenderRequest
    raw = tomllib.loads(C.to_toml(vessel_scene(BUDGET.res, 1, 20_000, seed=1, relief=True)))
    raw["model"]["surface"] = surface
    cfg = C.validate(raw, "relief vessel")
    sc = ppm.Pipeline.build(RenderRequest.of(cfg, dev=dev), dev)
    e, vol = sc.eye, sc.vol
    assert vol.ninc == 1 and not vol.flat
    s0, dv, ln, code = _pieces(sc)
    mat, lay = code & 255, code >> 8
    assert np.array_equal(e.pieces.get()[:e.npieces]["y"].astype(int), mat)
    assert ((lay >= 0) & (lay < vol.nl)).all()
    assert np.array_equal(mat[mat < vol.nl], lay[mat < vol.nl])         # a layer's piece: its layer
    keep = ln > 0.05                                    # a piece shorter than the rounding: no test
    inc = vol.inclusions[0]
    for f in (0.5, 0.02, 0.98):                         # its middle and near both ends
        p = s0[keep] + (f * ln[keep])[:, None] * dv[keep]
        inside = inc.contains(p)
        bad = inside != (mat[keep] == vol.nl)
        assert bad.mean() < 1e-3, (f, bad.sum())
    vessel = mat == vol.nl
    assert vessel.sum() > 50
    assert len(np.unique(lay[vessel])) >= 2             # the vessel crosses layers on the relief
    # each piece's layer is its point's (a point's cell lies in one layer visit), but for the
    # few a merged exit point (one point per voxel) or the threshold's cut leaves to the next or
    # last point: 4 of 3,000 here
    pts = e.pt_dir.get()[:e.npoints]["w"].astype(int)
    pp = e.pt_piece.get()[:e.npoints + 1].astype(np.int64)
    owner = np.repeat(np.arange(e.npoints), np.diff(pp))
    assert len(owner) == e.npieces
    wrong = lay != pts[owner]
    assert wrong.mean() < 5e-3, (wrong.sum(), np.unique(lay[wrong]), np.unique(pts[owner][wrong]))
    assert (wrong & vessel).sum() <= max(2, 0.01 * vessel.sum())


def test_eye_pieces_on_the_relief_lie_in_one_map_column(dev):
    """As tests/test_maps_ppm.py's on flat layers: in the mapped layers (basal, subpapillary
    dermis, both following the relief) every piece starts and ends in its midpoint's column.
    Caught: the eye pass ignoring the columns' walls on the relief."""
    from clppm.integrators import ppm
    from clppm.request import RenderRequest
    from clppm.scene import maps as M
    cfg = freckle_scene(BUDGET.res, 1, 20_000, seed=1, relief=True)
    sc = ppm.Pipeline.build(RenderRequest.of(cfg, dev=dev), dev)
    vol = sc.vol
    assert not vol.flat
    s0, dv, ln, mat = _pieces(sc)
    nx, ny, dx, dy = M.grid(cfg)

    def col(at):
        p = s0 + at[:, None] * dv
        return (np.clip(np.floor((p[:, 0] - vol.x0) / dx), 0, nx - 1) * ny
                + np.clip(np.floor((p[:, 1] - vol.y0) / dy), 0, ny - 1))
    names = [L["name"] for L in cfg["layer"]]
    mapped = np.isin(mat, [names.index("basal"), names.index("subpapillary dermis")])
    keep = mapped & (ln > 0.05)
    mid = col(0.5 * ln)
    # 10 nm sideways from each end (positions round to ~0.5 nm; the rays run within a few
    # degrees of the normal, so 10 nm along a piece moves it only ~0.3 nm across a wall)
    eps = np.minimum(0.01 / np.maximum(np.hypot(dv[:, 0], dv[:, 1]), 1e-6), 0.25 * ln)
    for at in (eps, ln - eps):
        bad = keep & (col(at) != mid)
        assert bad.sum() == 0, (bad.sum(), keep.sum())
    assert keep.sum() > 100, keep.sum()


@pytest.fixture(scope="module")
def vessel_renders(dev):
    pt_cfg, ppm_cfg = BUDGET.pt(vessel_scene, relief=True), BUDGET.ppm(vessel_scene, relief=True)
    pt = vessel_figures(pt_cfg, entry.render_pt(pt_cfg, dev=dev).spectral)
    ppm = vessel_figures(ppm_cfg, entry.render(ppm_cfg, dev=dev).spectral)
    return ppm, pt


@pytest.mark.once     # ~70 s on 2 cores (the path tracer through the relief: 40 s)
@pytest.mark.slow
def test_ppm_matches_pt_per_band_group_with_a_vessel_on_relief(vessel_renders):
    """Caught: a pass that does not see the vessel on the relief, a bias of the mean.  Tried by
    hand (Intel, PPM seed 1 against PT seed 101), not caught here: the gather taking the
    layer's extinction and mu_s for the vessel's pieces (beam.h beam_piece_at ``Lk = code >>
    8``): the red's contrast +16.5 % (correct: +11.8 %; PT's own seeds spread by 9 %), the
    green's +18.8 % (+11.7 %); the gather reading the material as the layer (``Ll = code &
    255``): every figure within 0.5 % of the correct build's (the vessel's pieces lie 10 um
    and more from the interfaces, where the layer-conforming depth and plain z nearly agree).
    The eye pieces' record is checked exactly by the first test."""
    ppm, pt = vessel_renders
    for grp in pt:
        assert abs(ppm[grp]["mean"] / pt[grp]["mean"] - 1) <= MEAN_BOUND, (grp, ppm[grp], pt[grp])
        r = ppm[grp]["contrast"] / pt[grp]["contrast"] - 1
        if grp == "red":
            assert RED_LO <= r <= RED_HI, (ppm[grp]["contrast"], pt[grp]["contrast"])
        elif grp != "380-425":              # little light, the noisiest contrast: its mean only
            assert CONTRAST_LO <= r <= CONTRAST_HI, (grp, ppm[grp]["contrast"], pt[grp]["contrast"])


@pytest.mark.once
@pytest.mark.slow
def test_vessel_on_relief_darker_and_redder_in_both(vessel_renders):
    """As on flat layers: over the vessel darker from 430 nm on, most in the green.  Caught: a
    pass that does not see the vessel (a contrast of 1)."""
    for fig in vessel_renders:
        c = {g: v["contrast"] for g, v in fig.items() if g != "red"}
        assert all(c[g] < 0.9 for g in c if g != "380-425"), c
        assert c["530-575"] < 0.65 and c["580-625"] < 0.65, c
        assert c["530-575"] < c["630-675"] < 1.0, c


@pytest.fixture(scope="module")
def freckle_renders(dev):
    pt_cfg, ppm_cfg = BUDGET.pt(freckle_scene, relief=True), BUDGET.ppm(freckle_scene, relief=True)
    pt = freckle_figures(pt_cfg, entry.render_pt(pt_cfg, dev=dev).spectral)
    ppm = freckle_figures(ppm_cfg, entry.render(ppm_cfg, dev=dev).spectral)
    return ppm, pt


@pytest.mark.once     # ~120 s on 2 cores (10-nm bands, one band per path)
@pytest.mark.slow
def test_ppm_matches_pt_per_band_group_with_maps_on_relief(freckle_renders):
    """Caught: a pass not seeing the maps on the relief (a spot's contrast near 1 where PT's is
    0.6-0.75 in the blue and green), a bias of the mapped scene's mean."""
    ppm, pt = freckle_renders
    for grp in pt:
        assert abs(ppm[grp]["mean"] / pt[grp]["mean"] - 1) <= MAP_MEAN_BOUND, (grp, ppm[grp], pt[grp])
        for spot in ("freckle", "blood"):
            r = ppm[grp][spot] / pt[grp][spot] - 1
            if grp == "red":
                assert abs(r) <= MAP_RED_BOUND, (spot, ppm[grp][spot], pt[grp][spot])
            elif grp != "380-420":
                assert MAP_CONTRAST_LO <= r <= MAP_CONTRAST_HI, (grp, spot, ppm[grp][spot], pt[grp][spot])


def _relief_map_cfg(maps, **render) -> dict:
    """A small relief forearm (configs/forearm_flat.toml's layers under configs/forearm.toml's
    relief, 10-nm bands) with ``maps``."""
    cfg = freckle_scene((9, 7), 2, 100_000, 16, seed=4, maps=False, initial_photons=100, relief=True)
    raw = tomllib.loads(C.to_toml(cfg))
    if maps:
        raw["map"] = maps
    raw["render"].update(render)
    return C.validate(raw, "relief map")


def test_constant_map_on_relief_renders_like_the_layer_with_that_value(dev):
    """As tests/test_maps_ppm.py's on flat layers, on the relief: the granular + spinous layer
    (between the surface's furrows and the papillae: its pieces measure their depth in its own
    coordinates) with its melanin 0.01 raised to 0.2 by a constant map, against the layer given
    0.2: measured (Intel, seed 4) per 50-nm group -8.1 % .. +14.0 % (9x7 pixels on the relief:
    noisier than flat layers' -7.7 % .. +6.6 %), pooled over 430-620 nm -1.7 %, over all bands
    -2.2 %; allowed: 20 %, 5 % and 4 %.  Caught (tried by hand): the gather taking the layer's
    own mu_t in a mapped layer on the relief (map_piece_mut's delta zeroed): +27.5 % pooled over
    430-620 nm, +18.2 % over all bands, up to +40.6 % in a group."""
    mapped = _relief_map_cfg([{"layer": "granular + spinous", "quantity": "melanin", "kind": "constant",
                               "value": 0.2}], photons=400_000)
    raw = tomllib.loads(C.to_toml(_relief_map_cfg(None, bands_per_path=1, photons=400_000)))
    raw["layer"][[L["name"] for L in raw["layer"]].index("granular + spinous")]["melanin"] = 0.2
    plain = C.validate(raw, "plain")
    a = entry.render(mapped, dev=dev).spectral
    b = entry.render(plain, dev=dev).spectral
    wl = C.wavelengths(plain)
    for lo, hi, idx in band_groups(wl):
        r = a[..., idx].sum() / b[..., idx].sum() - 1
        assert abs(r) <= 0.20, (lo, hi, r)
    blue_green = (wl >= 430) & (wl <= 620)
    assert abs(a[..., blue_green].sum() / b[..., blue_green].sum() - 1) <= 0.05
    assert abs(a.sum() / b.sum() - 1) <= 0.04
