"""Photon weights: the bands a path carries (kernels/spectral.h) and the storage rules.

References: the same estimator with one band per path (each band's stored power is an
independent estimate of the same expectation), and storing every event (the same paths, since
storage decisions draw from a stream of their own).  Statistics are batch means over
launches; tolerances are z-scores over all bins.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

cl = pytest.importorskip("pyopencl")

from clppm import config
from clppm.integrators import photonpass
from clppm.scene import volume  # noqa: E402
from clppm.scene.bands import Bands, source_spectrum  # noqa: E402

SKIN = [  # the Jacques recipe over 9 bands: mu_s ~ lambda^-1.5, g(lambda), melanin and blood absorption
    {"name": "epidermis", "thickness_um": 60.0, "n": 1.4, "melanin": 0.05, "baseline": 0.95},
    {"name": "papillary", "thickness_um": 100.0, "n": 1.34, "blood": 0.04, "k": 4.0},
    {"name": "dermis", "thickness_um": math.inf, "n": 1.4, "blood": 0.01, "k": 4.0},
]


def slab(layers=SKIN, start=420.0, stop=740.0, step=40.0):
    raw = {"model": {"name": "slab", "lateral": "infinite", "quantize": False},
           "spectrum": {"start_nm": start, "stop_nm": stop, "step_nm": step},
           "light": {"kind": "pencil", "direction": [0.0, 0.0, -1.0], "center_mm": [0.0, 0.0]},
           "layer": layers}
    return config.validate(raw, "test")


def stored_power(pp, n, launches, bins, seed_pass0=0):
    """Per launch (a batch of n photons, ids 0..n-1 of pass p): stored power per emitted photon
    in (band, layer, going up or down) bins, from the photon buffers."""
    q = pp.dev.queue
    nb, nl, C = pp.vol.nb, pp.vol.nl, pp.hero
    out = np.zeros((launches, nb, nl, 2))
    for k in range(launches):
        pp._set_count(0)
        pp._launch(n, 0, seed_pass0 + k, pp.capacity)
        m = pp._count()
        assert m <= pp.capacity, "capacity too small for the test"
        pw = np.empty((pp.capacity, 4), np.float32)
        db = np.empty((pp.capacity, 4), np.float32)
        cl.enqueue_copy(q, pw, pp.pos_w)
        cl.enqueue_copy(q, db, pp.dir_b)
        ex = np.empty(max(pp.capacity * (C - 1), 1), np.float32)
        cl.enqueue_copy(q, ex, pp.extra)
        pw, db = pw[:m], db[:m]
        code = db[:, 3].astype(int)
        h, L = code & 255, code >> 8
        up = (db[:, 2] > 0).astype(int)
        F = np.empty((m, C), np.float64)
        F[:, 0] = pw[:, 3]
        if C > 1:
            F[:, 1:] = ex[:m * (C - 1)].reshape(m, C - 1)
        assert np.all(np.isfinite(F)) and np.all(F >= 0)
        for j in range(C):
            b = (h + j * (nb // C)) % nb
            np.add.at(out[k], (b, L, up), F[:, j])
        out[k] /= n
    return out


def z_scores(a, b):
    """Per bin: (mean a - mean b) / its standard error, from batch means of two independent runs."""
    da, db = a.mean(0), b.mean(0)
    se = np.sqrt(a.var(0, ddof=1) / len(a) + b.var(0, ddof=1) / len(b))
    ok = se > 0
    return (da - db)[ok] / se[ok], ok


def photon_pass(dev, cfg, hero=1, capacity=2_000_000, seed=5, band=None):
    vol = volume.build(cfg)
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=capacity, seed=seed, bands=Bands.from_config(cfg, hero=hero, sampling="power"))
    pp.p["store_zmin"] = -250.0                # the depths eye rays see; the paths go deeper
    if band is not None:                       # every photon in one band (a single-band run)
        pp.p["fixed_band"] = band
        spi = np.ones((vol.nb, 2), np.float32)
        cl.enqueue_copy(dev.queue, pp.band_spi, spi)
    return pp


@pytest.mark.once
@pytest.mark.parametrize("C", [3, 9])
def test_hero_bands_unbiased_per_band(dev, C):
    """Every band's stored power per layer and direction with C bands per path (hero h and
    h + k 9/C) equals the one-band-per-path estimate of the same power within statistics, over
    all 9 x 3 x 2 bins (|z| < 4.5 everywhere, mean z^2 within the chi-square band)."""
    cfg = slab()
    n, launches = 4000, 12
    one = stored_power(photon_pass(dev, cfg, hero=1, seed=1), n * 3, launches, None)
    many = stored_power(photon_pass(dev, cfg, hero=C, seed=2), n, launches, None)
    z, ok = z_scores(many, one)
    assert ok.sum() >= 40
    assert np.max(np.abs(z)) < 4.5, np.round(z, 1)
    chi2 = float(np.mean(z * z))        # t^2 of batch means: mean ~1.1, bins of one path correlated
    assert 0.4 < chi2 < 2.5, chi2


def test_hero_band_far_from_the_hero_matches_a_single_band_run(dev):
    """Band 8 (740 nm) carried by paths whose hero is any band (C = 9) against a run where every
    photon is of band 8 (weight 1/s of that band, so both estimate the power per unit source
    power of band 8): the same per layer and direction.  Also band 0 (420 nm), the far end."""
    cfg = slab()
    spec = source_spectrum(cfg, config.wavelengths(cfg))
    n, launches = 3000, 12
    many = stored_power(photon_pass(dev, cfg, hero=9, seed=3), n, launches, None)
    for b in (8, 0):
        single = stored_power(photon_pass(dev, cfg, hero=1, seed=4, band=b), n // 3, launches, None)
        z, ok = z_scores(many[:, b] / spec[b], single[:, b])
        assert ok.sum() >= 4
        assert np.max(np.abs(z)) < 4.0, (b, np.round(z, 2))


def test_hero_weights_finite_for_degenerate_bands(dev):
    """A band with no scattering (mu_s = 0) and one with a huge absorption (mu_a = 1 um^-1,
    single-scattering albedo ~0.03): all stored weights stay finite and non-negative, the first
    band receives no power and the second only what its albedo lets through."""
    cfg = slab()
    vol = volume.build(cfg)
    vol = volume.Volume(**{**vol.__dict__})          # a private copy to edit
    vol.mus = vol.mus.copy()
    vol.mua = vol.mua.copy()
    vol.mus[:, 2] = 0.0
    vol.mua[:, 6] = 1.0
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=2_000_000, seed=6, bands=Bands.from_config(cfg, hero=9, sampling="power"))
    pp.p["store_zmin"] = -250.0
    pw = stored_power(pp, 4000, 3, None)
    assert np.all(np.isfinite(pw))
    per_band = pw.sum(axis=(0, 2, 3))
    assert per_band[2] == 0.0 and 0 < per_band[6] < 0.1 * per_band.mean(), per_band
    assert pw.sum() > 0


@pytest.mark.once
@pytest.mark.parametrize("C", [1, 9])
def test_importance_storage_unbiased(dev, C):
    """Importance-driven storage against storing every event, on the same paths (the storage
    decisions draw from a stream of their own): the stored power per band, layer and direction
    agrees within its thinning noise, while far fewer events are stored."""
    cfg = slab()
    n, launches = 3000, 12
    pa = photon_pass(dev, cfg, hero=C, seed=7)
    pi = photon_pass(dev, cfg, hero=C, seed=7)
    pi.set_storage("importance", cone_deg=8.0, scale=10.0, qmin=0.02)
    a = stored_power(pa, n, launches, None)
    b = stored_power(pi, n, launches, None)
    # paired: the same paths, so the difference is the thinning alone
    d = b - a
    se = d.std(0, ddof=1) / math.sqrt(launches)
    ok = se > 0
    z = d.mean(0)[ok] / se[ok]
    assert ok.sum() >= 20
    assert np.max(np.abs(z)) < 4.5, np.round(z, 1)
    assert np.mean(z * z) < 2.5         # t(11)^2 has mean 1.22; the bins of one event are correlated
    pa._set_count(0); pa._launch(n, 0, 0, pa.capacity); na = pa._count()
    pi._set_count(0); pi._launch(n, 0, 0, pi.capacity); ni = pi._count()
    assert ni < 0.5 * na, (ni, na)


def test_storage_rule_leaves_transport_unchanged(dev):
    """The tallies (exit and absorption per band, exact integers) do not depend on the storage
    rule or the number of carried bands: the path is the hero's in every case."""
    cfg = slab()
    tallies = []
    for C, rule in ((1, "all"), (1, "importance"), (9, "importance")):
        pp = photon_pass(dev, cfg, hero=C, seed=8)
        pp.set_storage(rule, cone_deg=8.0, scale=10.0, qmin=0.02)
        pp._set_count(0)
        pp._launch(5000, 0, 0, pp.capacity)
        tallies.append(pp._flush(5000))
    assert np.array_equal(tallies[0], tallies[1]) and np.array_equal(tallies[0], tallies[2])


def test_qmc_emission_unbiased(dev):
    """Emission from the shifted R3 sequence against independent uniforms: the same stored power
    per band, layer and direction (independent runs, batch means)."""
    cfg = slab()
    n, launches = 4000, 12
    rnd = photon_pass(dev, cfg, seed=9)
    qmc = photon_pass(dev, cfg, seed=10)
    qmc.set_emission("qmc")
    z, ok = z_scores(stored_power(qmc, n, launches, None), stored_power(rnd, n, launches, None))
    assert np.max(np.abs(z)) < 4.5 and 0.4 < float(np.mean(z * z)) < 2.5, np.round(z, 1)


def _slab_render_cfg(storage, C, seed, photons):
    raw = {"model": {"name": "slab", "size_mm": [4.0, 4.0], "lateral": "infinite", "quantize": False},
           "spectrum": {"start_nm": 420.0, "stop_nm": 740.0, "step_nm": 40.0},
           "light": {"kind": "wide", "direction": [0.0, 0.0, -1.0], "center_mm": [2.0, 2.0],
                     "width_mm": [4.0, 4.0]},
           "camera": {"position_mm": [2.0, 2.0, 40.0], "look_at_mm": [2.0, 2.0, 0.0], "fov_deg": 5.0,
                      "resolution": [8, 8]},
           "render": {"method": "e", "photons": photons, "initial_photons": 60, "passes": 6, "seed": seed,
                      "specular": False, "checkpoint_every": 0, "storage": storage, "bands_per_path": C},
           "layer": SKIN}
    return config.validate(raw, "test")


@pytest.mark.once
@pytest.mark.slow
def test_layered_slab_radiance_unchanged_by_storage_and_bands(dev):
    """The rendered radiance of a layered skin slab (9 bands, wide beam, view from above) per band:
    every event stored with one band per path, against importance-driven storage with 9 bands
    per path -- the same within their seed-to-seed spread in every band.  The view spans most of
    the lit square so that every path counts; storing every event needs 100x the stored photons
    for a comparable spread (one band per path, ~100 correlated events each)."""
    from clppm.run import entry
    runs = {}
    for key, photons in ((("all", 1), 2_000_000), (("importance", 9), 20_000)):
        runs[key] = np.array([entry.render(_slab_render_cfg(*key, seed, photons), dev=dev).spectral.mean(axis=(0, 1))
                              for seed in (1, 2, 3, 4)])
    a, b = runs[("all", 1)], runs[("importance", 9)]
    z, ok = z_scores(b, a)
    assert ok.all() and np.max(np.abs(z)) < 4.0, (np.round(b.mean(0) / a.mean(0), 3), np.round(z, 1))
    assert np.all(np.abs(b.mean(0) / a.mean(0) - 1) < 0.08), np.round(b.mean(0) / a.mean(0), 3)


def _stored_all(pp, m):
    """The first m stored photons: positions and hero weights, directions and codes, the
    other bands' weights (n, C)."""
    q = pp.dev.queue
    C = pp.hero
    pw = np.empty((pp.capacity, 4), np.float32)
    db = np.empty((pp.capacity, 4), np.float32)
    ex = np.empty(max(pp.capacity * (C - 1), 1), np.float32)
    for a, b in ((pw, pp.pos_w), (db, pp.dir_b), (ex, pp.extra)):
        cl.enqueue_copy(q, a, b)
    q.finish()
    F = np.concatenate([pw[:m, 3:4], ex[:m * (C - 1)].reshape(m, C - 1)], 1).astype(np.float64)
    return pw[:m], db[:m], F


def _forearm_pass(dev, scale, qmin, exact=False, seed=4):
    cfg = config.load(config.find("forearm"))
    vol = volume.build(cfg, "forearm")
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=60_000, seed=seed, bands=Bands.from_config(cfg))
    if exact:
        from clppm.compute.device import kernel_defines, surface_fp64
        from clppm.compute.kernelcall import Kernel
        pp.prg = dev.build("photon.cl", {**kernel_defines(vol, hero=pp.hero, pt_fp64=surface_fp64(dev, vol)),
                                         "STORE_EXACT": 1})
        pp.kernel = Kernel(pp.prg, "photon_pass")
    pp.p["store_zmin"] = -320.0
    pp.set_storage("importance", cone_deg=8.0, scale=scale, qmin=qmin)
    return pp


def test_importance_storage_bounds_every_carried_band(dev):
    """The storage probability weighs every band a photon carries (against the bright single-photon spots of bench/studies/spots.py): on
    the forearm (81 bands, 9 per path), for every stored photon
        store_scale * sum_j F_j/q (pi_j/s_j) hrel_j T_j <= 1,
    with hrel_j the band's HG toward the most favourable eye direction in the cone over its peak
    and T_j the vertical eye ray's transmittance to the photon's depth (the kernel's I, evaluated
    here in float64).  With store_scale = 0.1 q never reaches 1, so the sum is exactly 1 where q
    is not clamped at store_qmin (7 % of the stored photons here).  A probability from the hero band alone gave sums of 10^3:
    a 577 nm hero absorbed by haemoglobin while the 622 nm band it carries is not."""
    import math as m
    scale, qmin = 0.1, 1e-3
    pp = _forearm_pass(dev, scale, qmin)
    pp._set_count(0)
    pp._launch(60_000, 0, 0, pp.capacity)
    n = pp._count()
    assert 2000 < n <= pp.capacity, n
    pw, db, F = _stored_all(pp, n)
    vol, NB, C = pp.vol, pp.vol.nb, pp.hero
    code = db[:, 3].astype(int)
    h, L = code & 255, code >> 8
    bands = (h[:, None] + np.arange(C)[None] * (NB // C)) % NB
    imp = photonpass.storage_importance(vol)[:vol.nl * NB].reshape(vol.nl, NB, 2).astype(np.float64)
    opt = vol.optics_table().reshape(vol.nl, NB, 4).astype(np.float64)
    g, mut = opt[L[:, None], bands, 1], opt[L[:, None], bands, 3]
    c = db[:, 2].astype(np.float64)
    cs, sn = m.cos(m.radians(8.0)), m.sin(m.radians(8.0))
    ce = np.where(c >= cs, 1.0, c * cs + np.sqrt(np.maximum(0, 1 - c * c)) * sn)[:, None]
    hrel = (1 - np.abs(g)) ** 3 / (1 + g * g - 2 * g * ce) ** 1.5
    T = np.exp(-(imp[L[:, None], bands, 0] + mut * np.maximum(0, imp[L[:, None], bands, 1] - pw[:, 2:3])))
    ratio = pp.pi[bands] / pp.spectrum[bands]
    S = scale * (F * ratio * hrel * T).sum(1)
    assert S.max() < 1.002, np.sort(S)[-5:]
    assert np.mean(np.abs(S - 1) < 2e-3) > 0.03, np.quantile(S, [0.1, 0.5, 0.9])   # the rest: q = store_qmin


def test_importance_storage_bound_shortcut_exact(dev):
    """Most events are dropped on a per-layer upper bound of the importance before their band
    weights are computed (store_bound): the stored photons are the very ones that computing q
    for every event stores (STORE_EXACT), bit for bit, at the default scale and store_qmin."""
    recs = []
    for exact in (False, True):
        pp = _forearm_pass(dev, 10.0, 0.02, exact=exact)
        pp._set_count(0)
        pp._launch(20_000, 0, 0, pp.capacity)
        n = pp._count()
        pw, db, F = _stored_all(pp, n)
        rec = np.concatenate([pw, db, F], 1)
        recs.append(rec[np.lexsort(rec.T[::-1])])
    assert len(recs[0]) > 10_000
    np.testing.assert_array_equal(recs[0], recs[1])
