"""Photon transport of kernels/photon.cl against published and adding-doubling references.

Every statistical comparison uses the standard error of batch means (10 batches) from
``photonpass.trace_report`` and a fixed seed, so each run is deterministic; tolerances are
3 standard errors (plus the reference's own accuracy where it has one).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

cl = pytest.importorskip("pyopencl")
from scipy import stats  # noqa: E402

from clppm.scene import bands, volume
from clppm import config
from clppm.integrators import photonpass  # noqa: E402
from clppm.integrators.photonpass import CATEGORIES, W0  # noqa: E402

try:                                   # categories that make up a photon's weight
    from clppm.integrators.photonpass import BALANCE, NA# noqa: E402
except ImportError:                    # pragma: no cover - before the cone tally existed
    BALANCE, NA = list(range(len(CATEGORIES))), len(CATEGORIES)

ROOT = Path(__file__).resolve().parents[1]
AD = json.loads((ROOT / "tests" / "data" / "adding_doubling.json").read_text())["cases"]
AD_ACCURACY = 1e-4          # the JSON's convergence note: max_abs_change < 1e-4 everywhere
SEED = 20240601
BATCHES = 10

# name: (--slab spec, photons).  Photon counts keep the whole file well under a minute on PoCL
# with 2 cores; the resulting standard errors are printed in the assertion messages.
CASES = {
    "vdh_slab_n1": ("mua=10,mus=90,g=0.75,n=1.0,d=0.02", 400_000),
    "slab_n1.4": ("mua=10,mus=90,g=0.75,n=1.4,d=0.02", 200_000),
    "semi_inf_g0.9_n1.4": ("mua=1,mus=100,g=0.9,n=1.4", 50_000),
    "semi_inf_g0.9_n1": ("mua=1,mus=100,g=0.9,n=1.0", 50_000),
    "semi_inf_g0_mua0.1_n1": ("mua=0.1,mus=100,g=0.0,n=1.0", 30_000),
}

I_GAIN, I_LOSS = CATEGORIES.index("rr_gain"), CATEGORIES.index("rr_loss")


def photons_in(row, nl):
    """Whole photons accounted for by one tally row (exact: None if not a whole number)."""
    w = sum(int(row[c]) for c in BALANCE + list(range(NA, NA + nl))) - 2 * int(row[I_GAIN])
    return w // W0 if w % W0 == 0 else None


def slab_pass(dev, spec, seed=SEED, capacity=0, counters=False):
    cfg = config.slab_config(spec)
    vol = volume.build(cfg, "--slab")
    return photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=capacity, seed=seed, counters=counters)


def traced_report(pp, n, batches=BATCHES):
    """``trace_report`` plus the per-batch integer tally arrays it was computed from."""
    captured = []
    inner = pp.trace

    def trace(*a, **k):
        out = inner(*a, **k)
        captured.append(out)
        return out

    pp.trace = trace
    try:
        rep = photonpass.trace_report(pp, n, batches=batches)
    finally:
        del pp.trace
    assert len(captured) == 1
    return rep, captured[0]


_RUNS: dict = {}


@pytest.fixture(scope="module")
def run(dev):
    """Run (once per module) the named reference case: (report, per-batch arrays)."""

    def get(name):
        if name not in _RUNS:
            spec, n = CASES[name]
            _RUNS[name] = traced_report(slab_pass(dev, spec), n)
        return _RUNS[name]

    return get


def within(rep, key, ref, extra=0.0, k=3.0):
    v, se = rep[key], rep[key + "_se"]
    assert se > 0 or v == ref, f"{key}: no standard error"
    assert abs(v - ref) <= k * se + extra, \
        f"{key} = {v:.5f} ± {se:.5f}, reference {ref:.5f} (off by {abs(v - ref) / max(se, 1e-300):.1f} SE)"


# ----------------------------------------------------------------------------- references
def test_mcml_van_de_hulst_slab(run):
    """MCML verification slab (Wang, Jacques & Zheng, Comput. Methods Programs Biomed. 47
    (1995) 131, table 2, from van de Hulst's tables): mua 10, mus 90 /cm, g 0.75, d 0.02 cm,
    n 1: Rd = 0.09739, Tt = 0.66096, within 3 standard errors."""
    rep, _ = run("vdh_slab_n1")
    within(rep, "Rd", 0.09739)
    within(rep, "Tt", 0.66096)
    within(rep, "A", 1 - 0.09739 - 0.66096)
    assert rep["specular"] == 0.0 and rep["lost"] == 0.0 and rep["missed"] == 0.0


def test_mismatched_slab_adding_doubling(run):
    """Slab mua 10, mus 90, g 0.75, d 0.02 cm, n 1.4 in air vs adding-doubling
    (iadpython 0.5.3, tests/data/adding_doubling.json case 'slab_n1.4'): Rd in MCML's
    convention (UR1 - ((n-1)/(n+1))^2) and Tt = UT1 within 3 SE + 1e-4; the specular part is
    ((n-1)/(n+1))^2 = 1/36 exactly (deterministic split at the surface, no variance)."""
    ref = AD["slab_n1.4"]["values"]
    rep, _ = run("slab_n1.4")
    spec = ((1.4 - 1) / (1.4 + 1)) ** 2
    assert ref["specular_fresnel"] == pytest.approx(spec, abs=1e-15)
    assert rep["specular"] == pytest.approx(spec, abs=1e-6) and rep["specular_se"] < 1e-9
    within(rep, "Rd", ref["rd_excl_specular"], AD_ACCURACY)
    within(rep, "Tt", ref["tt"], AD_ACCURACY)


@pytest.mark.parametrize("name", ["semi_inf_g0.9_n1.4", "semi_inf_g0.9_n1", "semi_inf_g0_mua0.1_n1"])
def test_semi_infinite_adding_doubling(run, name):
    """Semi-infinite media vs adding-doubling (iadpython 0.5.3, tests/data/adding_doubling.json;
    the isotropic case also matches Chandrasekhar's H-function, R = 1 - H(1) sqrt(1 - a)):
    Rd (MCML convention, specular excluded) within 3 SE + 1e-4, nothing transmitted."""
    ref = AD[name]
    rep, _ = run(name)
    n = ref["inputs"]["n_sample"]
    assert rep["specular"] == pytest.approx(((n - 1) / (n + 1)) ** 2, abs=1e-6)
    within(rep, "Rd", ref["values"]["rd_excl_specular"], AD_ACCURACY)
    if "independent_check" in ref:
        within(rep, "Rd", ref["independent_check"]["rd"], AD_ACCURACY)
    assert rep["Tt"] == 0.0
    assert rep["lost"] < 1e-4


# ----------------------------------------------------------------------------- energy
@pytest.mark.parametrize("name", list(CASES))
def test_energy_balance_exact(run, name):
    """Conservation (exact integer bookkeeping, photon.cl header): specular + Rd + Tt + A + lost
    + missed + roulette losses - roulette gains = 1, to 1e-6 relative in the report and exactly
    (to the last fixed-point unit) in every band of every batch."""
    rep, arrs = run(name)
    assert rep["energy_balance_error"] < 1e-6
    total = (rep["specular"] + rep["Rd"] + rep["Tt"] + rep["A"] + rep["lost"] + rep["missed"]
             - rep["roulette_net"])
    assert total == pytest.approx(1.0, abs=1e-6)
    n_total = 0
    for a in arrs:
        for row in a:
            k = photons_in(row, 1)
            assert k is not None, "a band's categories do not add up to whole photons"
            n_total += k
    assert n_total == CASES[name][1]


def _batch_fractions(arrs, n, col):
    sizes = [n // len(arrs) + (1 if i < n % len(arrs) else 0) for i in range(len(arrs))]
    return np.array([a[:, col].sum() / (W0 * s) for a, s in zip(arrs, sizes)]), sizes


def test_roulette_unbiased(run):
    """Russian roulette (survive with 1/m, weight x m) is unbiased: in the highest-albedo
    semi-infinite case (a = 0.999, ~1e4 scatterings per photon, so every photon that is not
    reflected early meets roulette) the net gain - loss is consistent with 0 (4 SE)."""
    rep, arrs = run("semi_inf_g0_mua0.1_n1")
    n = CASES["semi_inf_g0_mua0.1_n1"][1]
    gains, sizes = _batch_fractions(arrs, n, I_GAIN)
    losses, _ = _batch_fractions(arrs, n, I_LOSS)
    # below the default threshold (1e-4 of W0) only crumbs are at stake; they must be there
    assert gains.min() > 0 and losses.min() > 0, "roulette did not happen"
    net = gains - losses
    se = net.std(ddof=1) / math.sqrt(len(net))
    assert rep["roulette_net"] == pytest.approx(net @ np.array(sizes) / n, abs=1e-12)
    assert abs(net.mean()) < 4 * se, f"roulette net {net.mean():.3e} ± {se:.3e}"


def test_roulette_high_threshold_unbiased(dev):
    """Roulette at a threshold of 20 % of the launch weight (so it moves a large part of the
    energy) leaves Rd unchanged: semi-infinite g 0.9, n 1 vs adding-doubling (iadpython 0.5.3,
    'semi_inf_g0.9_n1') within 3 SE + 1e-4, and the net roulette gain is 0 within 4 SE."""
    spec, _ = CASES["semi_inf_g0.9_n1"]
    n = 50_000
    pp = slab_pass(dev, spec, seed=SEED + 5)
    pp.p["rr_threshold"] = 0.2
    rep, arrs = traced_report(pp, n)
    gains, _ = _batch_fractions(arrs, n, I_GAIN)
    losses, _ = _batch_fractions(arrs, n, I_LOSS)
    assert losses.mean() > 0.02, "roulette should carry a large share of the energy here"
    net = gains - losses
    se = net.std(ddof=1) / math.sqrt(len(net))
    assert abs(net.mean()) < 4 * se, f"roulette net {net.mean():.3e} ± {se:.3e}"
    within(rep, "Rd", AD["semi_inf_g0.9_n1"]["values"]["rd_excl_specular"], AD_ACCURACY)
    assert rep["energy_balance_error"] < 1e-6


def _stored_flux(pp, passes, target, zmin):
    """Per pass: the stored events' weight per emitted photon, in 100 um slices above zmin."""
    out = []
    for k in range(passes):
        r = pp.run_pass(k, target)
        pos_w, _ = _stored(pp, r["stored"])
        z, w = pos_w[:, 2].astype(np.float64), pos_w[:, 3].astype(np.float64)
        assert np.all(z > zmin)
        out.append(np.histogram(z, bins=np.arange(zmin, 1e-3, 100.0), weights=w)[0] / r["emitted"])
    return np.array(out)


def test_depth_roulette_is_unbiased_and_cuts_the_deep_walk(dev):
    """Depth roulette (render.depth_roulette_um, photon.cl deep_roulette: survival 1/2 at each
    plane 100 um apart below the storage depth) changes no expectation: on a semi-infinite slab
    whose photons wander a millimetre deep (mua 3, mus 100 per cm, g 0.9, n 1.4: 200 collisions
    per photon; storage depth 300 um) Rd, the absorbed fraction and the stored weight in each
    100 um slice above the storage depth agree with the plain pass within 4 standard errors, the
    tallies still add up to whole photons exactly, and the walk is cut: fewer than half the
    collisions per photon (14 against 200 on PoCL)."""
    spec, n = "mua=3,mus=100,g=0.9,n=1.4", 40_000
    zmin = -300.0
    plain = slab_pass(dev, spec, seed=SEED + 9, capacity=120_000, counters=True)
    cut = slab_pass(dev, spec, seed=SEED + 9, capacity=120_000, counters=True)
    plain.set_storage_depth(zmin)
    cut.set_storage_depth(zmin, 100.0)
    reps = {}
    for name, pp in (("plain", plain), ("cut", cut)):
        pp.counts()
        rep, arrs = traced_report(pp, n)
        c = pp.counts()
        reps[name] = rep, c["collisions"] / n
        assert rep["energy_balance_error"] < 1e-6
        assert sum(photons_in(row, 1) for a in arrs for row in a) == n
    (rp, coll_p), (rc, coll_c) = reps["plain"], reps["cut"]
    for key in ("Rd", "A"):
        se = math.hypot(rp[key + "_se"], rc[key + "_se"])
        assert abs(rp[key] - rc[key]) <= 4 * se, f"{key}: {rp[key]:.5f} vs {rc[key]:.5f} ± {se:.5f}"
    assert rc["roulette_net"] != 0.0
    assert coll_c < 0.5 * coll_p, f"collisions per photon {coll_c:.0f} with the roulette, {coll_p:.0f} without"
    fp = _stored_flux(plain, 8, 100_000, zmin)
    fc = _stored_flux(cut, 8, 100_000, zmin)
    se = np.hypot(fp.std(0, ddof=1), fc.std(0, ddof=1)) / math.sqrt(len(fp))
    diff = fc.mean(0) - fp.mean(0)
    assert np.all(np.abs(diff) <= 4 * se), f"stored weight per slice: {diff} ± {se}"
    assert np.all(fp.mean(0) > 10 * se), "each slice holds stored weight"


# ----------------------------------------------------------------------------- determinism
def test_determinism_same_seed(dev):
    """Philox keyed by (seed, pass, photon id): the same seed on the same device gives identical
    integer tallies batch by batch; a different seed or pass index gives different ones."""
    spec = CASES["vdh_slab_n1"][0]
    a = slab_pass(dev, spec, seed=7).trace(30_000, batches=3)
    b = slab_pass(dev, spec, seed=7).trace(30_000, batches=3)
    assert len(a) == len(b) == 3
    for x, y in zip(a, b):
        assert x.dtype == np.int64
        np.testing.assert_array_equal(x, y)
    c = slab_pass(dev, spec, seed=8).trace(30_000, batches=3)
    assert not any(np.array_equal(x, y) for x, y in zip(a, c))
    d = slab_pass(dev, spec, seed=7).trace(30_000, pass_index=1, batches=3)
    assert not any(np.array_equal(x, y) for x, y in zip(a, d))
    # and the report is the same numbers as the arrays
    rep = photonpass.trace_report(slab_pass(dev, spec, seed=7), 30_000, batches=3)
    rd = sum(int(x[0, CATEGORIES.index("diffuse")]) for x in a) / (W0 * 30_000)
    assert rep["Rd"] == rd


def _stored(pp, count):
    pos_w = np.zeros((count, 4), np.float32)
    dir_b = np.zeros((count, 4), np.float32)
    if count:
        cl.enqueue_copy(pp.dev.queue, pos_w, pp.pos_w)
        cl.enqueue_copy(pp.dev.queue, dir_b, pp.dir_b)
        pp.dev.queue.finish()
    return pos_w, dir_b


def _sorted_records(pos_w, dir_b):
    rec = np.concatenate([pos_w, dir_b], 1)
    return rec[np.lexsort(rec.T[::-1])]


def test_stored_photons(dev):
    """run_pass stores >= target scattering events (never beyond capacity), records the photons
    emitted, and stores only events inside the slab (0.02 cm = 200 um thick, surface at z = 0),
    with unit directions, valid band indices and weights in (0, 1.1]; the same seed and pass
    give the same set of stored events (the buffer order may differ), another pass another set."""
    spec = CASES["vdh_slab_n1"][0]
    target, cap = 40_000, 60_000
    pp = slab_pass(dev, spec, seed=11, capacity=cap)
    r = pp.run_pass(0, target)
    assert target <= r["stored"] <= cap
    assert r["emitted"] > 0 and pp.tallies.emitted == r["emitted"]
    assert pp.tallies.balance_error() == 0.0
    # ~ (scatterings inside per photon) ~ 8 for this slab; sanity only
    assert 1 < r["stored"] / r["emitted"] < 50
    pos_w, dir_b = _stored(pp, r["stored"])
    z, w = pos_w[:, 2], pos_w[:, 3]
    assert np.all(np.isfinite(pos_w)) and np.all(np.isfinite(dir_b))
    assert np.all(z <= 1e-3) and np.all(z >= -200.0 - 1e-2)
    assert np.all(w > 0) and np.all(w <= 1.1)
    np.testing.assert_allclose(np.linalg.norm(dir_b[:, :3], axis=1), 1.0, atol=1e-5)
    assert np.all(dir_b[:, 3] == 0.0)                      # one band
    # first collision of a pencil beam at normal incidence: weight albedo = 0.9, straight down
    first = np.isclose(w, 0.9, atol=1e-6) & (pos_w[:, 0] == 0) & (pos_w[:, 1] == 0)
    assert first.sum() > 0.5 * r["emitted"] and np.all(dir_b[first, 2] == -1.0)

    pp2 = slab_pass(dev, spec, seed=11, capacity=cap)
    r2 = pp2.run_pass(0, target)
    assert r2 == r
    np.testing.assert_array_equal(_sorted_records(*_stored(pp2, r2["stored"])),
                                  _sorted_records(pos_w, dir_b))
    r3 = pp2.run_pass(1, target)
    rec3 = _sorted_records(*_stored(pp2, r3["stored"]))
    assert rec3.shape != (r["stored"], 8) or not np.array_equal(rec3, _sorted_records(pos_w, dir_b))


def test_event_counters_count_the_same_photons(dev):
    """The counting build (PHOTON_COUNTERS, bench/photons.py --events) traces the same photons as
    the plain one: the same integer tallies and stored events; and its counts agree with them:
    entered + missed = emitted, stored = the photon map's count, and on the flat slab every loop
    step is a collision or a boundary event but for at most one ending step per photon."""
    spec = CASES["slab_n1.4"][0]
    target, cap = 20_000, 40_000
    plain = slab_pass(dev, spec, seed=5, capacity=cap)
    counted = slab_pass(dev, spec, seed=5, capacity=cap, counters=True)
    r0, r1 = plain.run_pass(0, target), counted.run_pass(0, target)
    assert r0 == r1
    assert plain.tallies.counts == counted.tallies.counts
    np.testing.assert_array_equal(_sorted_records(*_stored(counted, r1["stored"])),
                                  _sorted_records(*_stored(plain, r0["stored"])))
    c = counted.counts()
    assert c["entered"] + c["missed"] == r1["emitted"]
    assert c["stored"] == r1["stored"]
    boundary = sum(c[k] for k in ("interface", "zone", "wall", "domain", "tile"))
    assert c["collisions"] > 0 and c["interface"] >= c["entered"]
    assert 0 <= c["steps"] - c["collisions"] - boundary <= c["entered"], c


# ----------------------------------------------------------------------------- the skin model
@pytest.fixture(scope="module")
def forearm(dev):
    cfg = config.load(str(ROOT / "configs" / "forearm.toml"))
    vol = volume.build(cfg, "forearm.toml")
    return cfg, vol


def test_forearm_photon_pass(dev, forearm):
    """The paper's forearm model (configs/forearm.toml: 9 layers, 81 bands, D65 point light,
    generated relief and papillae): the photon pass runs without NaN, Rd is in the range of
    measured skin (0.1-0.5 of the light reaching the skin, e.g. Jacques 1998 / Zonios 2001
    spectra), red reflects more than blue, bands are drawn in proportion to D65, and the
    per-band tallies add up to the totals exactly."""
    cfg, vol = forearm
    n = 20_000
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=50_000, seed=3)
    rep, arrs = traced_report(pp, n)
    for k, v in rep.items():
        if isinstance(v, float):
            assert math.isfinite(v), k
    assert rep["energy_balance_error"] < 1e-6
    hit = 1.0 - rep["missed"]
    assert 0.3 < hit < 1.0                       # the cone covers the model, some misses its sides
    assert 0.1 < rep["Rd"] / hit < 0.5, rep["Rd"] / hit
    assert 0.1 < rep["Rd"] < 0.5
    assert rep["Tt"] < 1e-3                      # semi-infinite subcutis
    assert 0.01 < rep["specular"] / hit < 0.1    # n = 1.5 stratum corneum at oblique incidence
    # per band: each band's categories are whole photons; they add up to the totals
    tot = sum(a.astype(object) for a in arrs)                       # (nb, nc)
    per_band_photons = [photons_in(row, vol.nl) for row in tot]
    assert None not in per_band_photons
    per_band_photons = np.array(per_band_photons, float)
    assert per_band_photons.sum() == n
    for c in range(tot.shape[1]):
        assert sum(int(tot[b, c]) for b in range(vol.nb)) == sum(int(a[:, c].sum()) for a in arrs)
    pb = rep["per_band"]
    assert len(pb) == vol.nb == 81
    for key, cat in (("Rd", "Rd"), ("Tt", "Tt"), ("A", "A"), ("specular", "specular")):
        s = sum(pb[b]["photons"] * pb[b][key] for b in pb)
        assert s == pytest.approx(rep[cat] * n, rel=1e-6, abs=1e-6), key
    for b, row in pb.items():
        assert all(math.isfinite(v) for v in row.values()), b
        assert 0 <= row["Rd"] <= 1 and 0 <= row["A"] <= 1
    # band sampling follows the D65 source spectrum
    p = bands.source_spectrum(cfg, vol.wl)
    assert stats.chisquare(per_band_photons, p * n).pvalue > 1e-3
    # spectral shape: haemoglobin and melanin absorb blue, so red comes back more
    wl = vol.wl
    rd = np.array([pb[f"{x:g}"]["Rd"] for x in wl])
    assert rd[(wl >= 650)].mean() > rd[(wl >= 400) & (wl <= 450)].mean() + 0.1

    # stored photons of the skin model: inside the model, valid bands, sane weights
    r = pp.run_pass(0, 30_000)
    assert r["stored"] >= 30_000 and pp.tallies.emitted == n + r["emitted"]
    pos_w, dir_b = _stored(pp, r["stored"])
    assert np.all(np.isfinite(pos_w)) and np.all(np.isfinite(dir_b))
    x, y, z, w = pos_w.T
    W = vol.nx * vol.dx
    assert np.all((x >= -1e-2) & (x <= W + 1e-2) & (y >= -1e-2) & (y <= vol.ny * vol.dy + 1e-2))
    assert np.all(z <= vol.z_top + 1e-3)
    assert np.all((w > 0) & (w <= 1.1))
    code = dir_b[:, 3]                       # band + 256 * layer
    assert np.all(code == np.round(code))
    b, lay = code.astype(int) % 256, code.astype(int) // 256
    assert b.min() >= 0 and b.max() < vol.nb
    assert lay.min() >= 0 and lay.max() < vol.nl
