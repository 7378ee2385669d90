"""Inclusions (a vessel, an ellipsoid) in the photon pass: kernels/inclusion.h, photon.cl.

* A slab with a buried vessel crossing its two layers and an ellipsoid beside it, traced by the
  photon pass (exact crossings of the quadrics), against a brute-force numpy Monte Carlo written
  here that knows nothing of boundaries: delta tracking against a majorant, the material found
  at each tentative collision point.  Rd, Tt and the fraction absorbed in every material agree
  per band within 4 combined standard errors; the vessel absorbs far more than that tolerance.
* The tallies' fixed-point bookkeeping stays exact with inclusions, on the flat, the smooth-relief
  and the voxel-relief walks.
* A scene without inclusions uploads the same optics bytes and builds without NINC (the README
  render's identity: tests/test_identity.py); an inclusion's material comes from the layers'
  chromophore spectra.
* Bad input: one line naming the key and value, exit 2, before any work; a render of a scene
  with inclusions is refused where a pass does not see them (PPM on the relief; the path tracer
  across periodic sides).  The path tracer through the relief: tests/test_pt_relief_heterogeneous.py;
  PPM against the path tracer with a vessel: tests/test_inclusions_ppm.py.
"""
from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from clppm import cli
from clppm import config as C
from clppm.compute.device import kernel_defines
from clppm.integrators import photonpass
from clppm.integrators.photonpass import NA, W0
from clppm.scene import skin, volume

import slab_mc
from slab_mc import agree, exact_balance, material_of, photon_pass_fractions, raw_toml

SLAB = {
    "model": {"name": "slab with a vessel", "lateral": "infinite", "quantize": False,
              "n_outside": 1.0, "n_below": 1.0},
    "spectrum": {"start_nm": 450.0, "stop_nm": 650.0, "step_nm": 100.0},
    "light": {"kind": "pencil", "direction": [0.0, 0.0, -1.0], "center_mm": [0.0, 0.0], "spectrum": "flat"},
    "render": {"seed": 11},
    "layer": [{"name": "epidermis", "thickness_um": 100.0, "n": 1.0, "melanin": 0.05},
              {"name": "dermis", "thickness_um": 400.0, "n": 1.0, "blood": 0.02}],
    # a vessel across the epidermis-dermis junction under the beam, and an ellipsoid of melanin
    # beside the beam in the epidermis, overlapping the vessel (the vessel, listed first, wins)
    "inclusion": [{"kind": "vessel", "center_mm": [0.0, 0.0], "depth_um": 130.0, "axis": [0.4, 1.0, 0.3],
                   "radius_um": 50.0, "blood": 1.0, "saturation": 0.7},
                  {"kind": "ellipsoid", "center_mm": [0.04, 0.02], "depth_um": 60.0,
                   "semi_axes_um": [80.0, 60.0, 30.0], "melanin": 0.3, "blood": 0.0}],
}
PHOTONS = 200_000          # photon pass, per band
MC_PHOTONS = 40_000        # numpy delta tracking, per band


def slab_cfg(**changes) -> dict:
    raw = {k: (list(v) if isinstance(v, list) else dict(v)) for k, v in SLAB.items()}
    raw.update(changes)
    return C.validate(raw, "slab")


# ----------------------------------------------------------------------------- the reference
def delta_tracking(vol, band: int, n: int, seed: int, start=(0.0, 0.0)) -> dict:
    """slab_mc's brute force with the material at each point: the layer by depth, then the
    first inclusion holding it; periodic sides wrap the position."""
    mua, mus, g = (a[:, band] for a in vol.material_optics())
    width = np.array([vol.nx * vol.dx, vol.ny * vol.dy])
    origin = np.array([vol.x0, vol.y0])

    def medium(p):
        m = material_of(vol, p)
        return m, mua[m], mus[m], g[m]
    wrap = (lambda xy: np.mod(xy - origin, width) + origin) if vol.lateral == "periodic" else None
    return slab_mc.delta_tracking(medium, float((mua + mus).max()), float(vol.layer_depths()[-1]),
                                  vol.nmat, n, seed, start=start, wrap=wrap)


def compare(dev, cfg, band: int, seed: int, start=(0.0, 0.0)):
    """The photon pass and delta tracking on one band: every fraction within 4 combined standard
    errors.  Returns both."""
    vol = volume.build(cfg, "slab")
    got, _ = photon_pass_fractions(dev, vol, cfg, band, PHOTONS)
    ref = delta_tracking(vol, band, MC_PHOTONS, seed=seed, start=start)
    agree(got, ref, 4.0, band)
    return got, ref


# ----------------------------------------------------------------------------- transport
@pytest.mark.parametrize("band", [0, 1, 2])
def test_vessel_slab_matches_delta_tracking(dev, band):
    cfg = slab_cfg()
    assert len(cfg["inclusion"]) == 2
    got, ref = compare(dev, cfg, band, seed=100 + band)
    # the test can see an inclusion that is not traced: the vessel's share is many tolerances
    vessel, tol = got["A2"], 4.0 * math.hypot(got["A2"][1], ref["A2"][1])
    assert vessel[0] > 10 * tol, f"band {band}: vessel absorbs {vessel[0]:.5f}, tolerance {tol:.5f}"


def test_vertical_vessel_entered_at_the_surface(dev):
    """A vessel along the beam (axis parallel to the flight: no crossing of its side) that
    pierces the surface: photons enter the skin inside it (Track.inside found at entry)."""
    inc = [{"kind": "vessel", "center_mm": [0.0, 0.0], "depth_um": 200.0, "axis": [0.0, 0.0, 1.0],
            "radius_um": 40.0, "blood": 0.5}]
    got, _ = compare(dev, slab_cfg(inclusion=inc), 1, seed=7)
    assert got["A2"][0] > 0.05, got["A2"]


def test_periodic_sides_wrap_into_an_inclusion(dev):
    """A 0.3 mm periodic model with an ellipsoid across its x = 0 side, the beam at the centre:
    photons that wrap find their inclusion again from the point (and the inclusion is not
    repeated: the part beyond the side is not there)."""
    inc = [{"kind": "ellipsoid", "center_mm": [0.0, 0.15], "depth_um": 120.0,
            "semi_axes_um": [100.0, 80.0, 60.0], "blood": 1.0, "saturation": 0.9}]
    model = {**SLAB["model"], "lateral": "periodic", "size_mm": [0.3, 0.3]}
    light = {**SLAB["light"], "center_mm": [0.15, 0.15]}
    got, _ = compare(dev, slab_cfg(inclusion=inc, model=model, light=light), 0, seed=8, start=(150.0, 150.0))
    assert got["A2"][0] > 0.02, got["A2"]


def test_flat_ellipsoid_traces_as_a_layer(dev):
    """An ellipsoid 100 um thick and 200 mm wide, inside the dermis, is a layer of its material
    there (its surface departs from the planes by under 0.01 um where the light goes): the photon
    pass with it matches the same slab with that layer written as a [[layer]], per band, within
    4 combined standard errors: the exact crossings against the layers' own walk."""
    mat = {"blood": 0.3, "saturation": 0.6, "melanin": 0.02}
    inc = [{"kind": "ellipsoid", "center_mm": [0.0, 0.0], "depth_um": 250.0,
            "semi_axes_um": [1e5, 1e5, 50.0], **mat}]
    with_inc = slab_cfg(inclusion=inc)
    layered = slab_cfg(layer=[SLAB["layer"][0], {**SLAB["layer"][1], "thickness_um": 100.0},
                              {"name": "ellipsoid as a layer", "thickness_um": 100.0, "n": 1.0, **mat},
                              {**SLAB["layer"][1], "thickness_um": 200.0}])
    layered = {k: v for k, v in layered.items() if k != "inclusion"}
    vi, vl = volume.build(with_inc, "inc"), volume.build(layered, "layers")
    for band in range(3):
        a, _ = photon_pass_fractions(dev, vi, with_inc, band, PHOTONS)
        b, _ = photon_pass_fractions(dev, vl, layered, band, PHOTONS)
        pairs = {"Rd": ("Rd", "Rd"), "Tt": ("Tt", "Tt"), "epidermis": ("A0", "A0"),
                 "dermis": ("A1", None), "ellipsoid": ("A2", "A2")}
        for name, (ka, kb) in pairs.items():
            xa, sa = a[ka]
            xb, sb = (b[kb] if kb else (b["A1"][0] + b["A3"][0], math.hypot(b["A1"][1], b["A3"][1])))
            tol = 4.0 * math.hypot(sa, sb) + 1e-6
            assert abs(xa - xb) <= tol, f"band {band} {name}: inclusion {xa:.5f} ± {sa:.5f}, layer {xb:.5f} ± {sb:.5f}"
        assert a["A2"][0] > 0.05, a["A2"]


@pytest.mark.once
@pytest.mark.parametrize("carried", [3, 9])
def test_hero_bands_unbiased_per_band_with_inclusions(dev, carried):
    """The bands a path carries (spectral.h) through inclusions: their per-material flight and
    collision factors (band table rows NL + i).  Every band's stored power per layer and direction
    with C bands per path equals the one-band-per-path estimate within statistics (the check of
    tests/test_spectral.py on its skin slab, with a vessel and an ellipsoid of melanin added)."""
    from test_spectral import SKIN, photon_pass, stored_power, slab, z_scores
    cfg = slab(SKIN)
    raw = tomllib.loads(C.to_toml(cfg))
    raw["inclusion"] = [{"kind": "vessel", "center_mm": [0.0, 0.0], "depth_um": 110.0, "axis": [0.0, 1.0, 0.0],
                         "radius_um": 40.0, "blood": 0.8},
                        {"kind": "ellipsoid", "center_mm": [0.03, 0.0], "depth_um": 40.0,
                         "semi_axes_um": [60.0, 60.0, 15.0], "melanin": 0.2, "blood": 0.0}]
    cfg = C.validate(raw, "skin slab with inclusions")
    n, launches = 4000, 12
    one = stored_power(photon_pass(dev, cfg, hero=1, seed=1), n * 3, launches, None)
    many = stored_power(photon_pass(dev, cfg, hero=carried, seed=2), n, launches, None)
    z, ok = z_scores(many, one)
    assert ok.sum() >= 40
    assert np.max(np.abs(z)) < 4.5, np.round(z, 1)
    chi2 = float(np.mean(z * z))
    assert 0.4 < chi2 < 2.5, chi2


# ----------------------------------------------------------------------------- the path tracer
#: a layer-wide ellipsoid across the junction of the path tracer tests' 1.5 / 1.34 / 1.4 stack
#: (epidermis 40-120 um): 80-160 um deep, so it takes each layer's index where it is
WIDE = {"kind": "ellipsoid", "center_mm": [2.0, 2.0], "depth_um": 120.0, "semi_axes_um": [1e5, 1e5, 40.0],
        "mua": 40.0, "mus": 150.0, "g": 0.9, "scattering": "none"}


def _with(cfg: dict, inclusions: list) -> dict:
    raw = tomllib.loads(C.to_toml(cfg))
    raw["inclusion"] = inclusions
    return C.validate(raw, "pt scene")


def _unscattered(n: list, mut: list, thick: list, n_above: float) -> float:
    """Light reflected back out unscattered by the index steps of a laterally uniform stack
    (incoherent adding, normal incidence; the last sub-layer semi-infinite), the surface's own
    reflection removed: the photon pass counts it in Rd, the path tracer cannot see it."""
    ns = [n_above] + n
    r = [((a - b) / (a + b)) ** 2 for a, b in zip(ns[:-1], ns[1:])]
    R = 0.0
    for k in range(len(n) - 1, -1, -1):
        t2 = math.exp(-2 * mut[k] * thick[k]) if math.isfinite(thick[k]) else 0.0
        R = r[k] + (1 - r[k]) ** 2 * t2 * R / (1 - r[k] * t2 * R)
    return R - r[0]


def test_path_tracer_matches_the_photon_tally_through_an_inclusion(dev):
    """The path tracer's walk and its light connections (each leg walked through the quadrics)
    against the photon pass's exact exit tally, both through a layer-wide ellipsoid across an
    index step (mu_t 190 against 105 and 100 /cm, g 0.9) under a point light 1 m above: the
    cos-weighted mean radiance over the cone cos > 0.95 equals E R_cone / (pi (1 - c^2)) minus
    the unscattered light of the internal index steps, within 3 sigma + 0.2 % (as
    tests/test_pathtracer.py does without inclusions); without the ellipsoid the tally moves by
    many times that."""
    from clppm.run import entry
    from test_pathtracer import E_FAR, LAYERED, _cone_average, scene
    c = 0.95
    fov = 2 * math.degrees(math.acos(c)) * 1.03
    plain = scene(LAYERED, fov=fov, res=(32, 32), spp=64, passes=3)
    cfg = _with(plain, [WIDE])
    Lc, sec = _cone_average(entry.render_pt(cfg, dev=dev), fov, c)
    k = E_FAR / (math.pi * (1 - c * c))
    unsc = _unscattered([1.5, 1.34, 1.34, 1.4, 1.4], [160e-4, 105e-4, 190e-4, 190e-4, 100e-4],
                        [40.0, 40.0, 40.0, 40.0, math.inf], 1.0)

    def tally(cfg, photons, unscattered):
        pp = photonpass.PhotonPass.of_config(dev, volume.build(cfg, "pt scene"), cfg)
        pp.p["rcone_cos"] = c
        rep = photonpass.trace_report(pp, photons, batches=10)
        return k * (rep["Rd_cone"] - unscattered), k * rep["Rd_cone_se"]
    ref, seref = tally(cfg, 3_000_000, unsc)
    tol = 3 * math.hypot(sec, seref) + 0.002 * ref
    assert abs(Lc - ref) < tol, (Lc, ref, sec, seref)
    from test_pathtracer import _unscattered_reflectance
    without, _ = tally(plain, 1_000_000, _unscattered_reflectance(volume.build(plain, "plain")))
    assert abs(without - ref) > 10 * tol, (without, ref, tol)


def test_trace_report_names_inclusions(dev):
    cfg = slab_cfg()
    vol = volume.build(cfg, "slab")
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg)
    rep = photonpass.trace_report(pp, 20_000, batches=4)
    assert list(rep["absorbed_per_layer"]) == ["epidermis", "dermis"]
    assert list(rep["absorbed_per_inclusion"]) == ["inclusion[0]", "inclusion[1]"]
    assert rep["A"] == pytest.approx(sum(rep["absorbed_per_layer"].values())
                                     + sum(rep["absorbed_per_inclusion"].values()), abs=1e-12)
    assert rep["energy_balance_error"] == 0.0


def test_energy_exact_flat(dev):
    cfg = slab_cfg()
    vol = volume.build(cfg, "slab")
    n = 30_000
    _, tot = photon_pass_fractions(dev, vol, cfg, 1, n)
    assert exact_balance(tot, vol.nmat) == n * W0


def test_every_photon_build_balances_with_inclusions(dev):
    """The photon pass's other builds with inclusions: importance storage with the bands a path
    carries (the stored weights finite and positive), the depth roulette below the storage
    depth, the event counters; the tallies' bookkeeping exact in each."""
    import pyopencl as cl
    from clppm.scene.bands import Bands
    from clppm.scene.scene import Scene
    cfg = slab_cfg()
    vol = volume.build(cfg, "slab")
    sc = Scene.of_config(cfg, volume=vol)
    pp = photonpass.PhotonPass(dev, sc, capacity=60_000, bands=Bands.from_config(cfg, hero=3, sampling="power"))
    pp.set_storage("importance", cone_deg=30.0, scale=10.0, qmin=0.05)
    pp.set_storage_depth(-150.0, roulette_um=50.0)
    tal = photonpass.Tallies(vol.nb, vol.nmat)
    info = pp.run_pass(0, 20_000, tallies=tal)
    assert info["stored"] >= 20_000 and tal.balance_error() == 0.0
    w = np.empty((pp.capacity, 4), np.float32)
    cl.enqueue_copy(dev.queue, w, pp.pos_w)
    w = w[:info["stored"]]
    assert np.all(np.isfinite(w)) and np.all(w[:, 3] > 0) and np.all(w[:, 2] >= -150.0)
    counted = photonpass.PhotonPass(dev, sc, counters=True)
    _, tot = photon_pass_fractions(dev, vol, cfg, 0, 5_000)
    counted.trace(5_000)
    assert counted.counts()["steps"] > 5_000
    assert exact_balance(tot, vol.nmat) == 5_000 * W0


def _relief_cfg(surface: str) -> dict:
    from clppm.checks.tiny import tiny_config
    cfg = tiny_config(size_mm=1.0)
    raw = tomllib.loads(C.to_toml(cfg))
    raw["model"]["surface"] = surface
    raw["light"] = {"kind": "wide", "center_mm": [0.5, 0.5], "width_mm": [0.4, 0.4], "direction": [0.0, 0.0, -1.0]}
    raw["inclusion"] = [{"kind": "vessel", "center_mm": [0.5, 0.5], "depth_um": 150.0, "axis": [1.0, 0.2, 0.0],
                         "radius_um": 80.0},
                        {"kind": "ellipsoid", "center_mm": [0.45, 0.55], "depth_um": 40.0,
                         "semi_axes_um": [120.0, 90.0, 25.0], "melanin": 0.4, "blood": 0.0}]
    return C.validate(raw, "tiny relief")


@pytest.mark.parametrize("surface", ["smooth", "voxels"])
def test_energy_exact_and_vessel_absorbs_on_relief(dev, surface):
    cfg = _relief_cfg(surface)
    vol = volume.build(cfg, "tiny relief")
    assert not vol.flat
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg)
    n = 20_000
    tot = sum(a.astype(object) for a in pp.trace(n, batches=2))
    bal = sum(exact_balance(tot[b], vol.nmat) for b in range(vol.nb))
    assert bal == n * W0
    vessel = sum(int(tot[b][NA + vol.nl]) for b in range(vol.nb)) / (W0 * n)
    mole = sum(int(tot[b][NA + vol.nl + 1]) for b in range(vol.nb)) / (W0 * n)
    assert vessel > 0.01 and mole > 0.01, (vessel, mole)


# ----------------------------------------------------------------------------- the host side
def test_uniform_scene_uploads_the_same_bytes():
    cfg = slab_cfg()
    plain = {k: v for k, v in cfg.items() if k != "inclusion"}
    vol = volume.build(plain, "plain")
    assert vol.ninc == 0 and "NINC" not in kernel_defines(vol)
    assert vol.device_optics().tobytes() == vol.optics_table().tobytes()
    assert "inclusion" not in C.load("forearm")


def test_inclusion_material_from_the_chromophore_spectra():
    cfg = slab_cfg()
    vol = volume.build(cfg, "slab")
    a, s, g = skin.optics(skin.Layer(name="v", thickness_um=1.0, blood=1.0, saturation=0.7), vol.wl)
    inc = vol.inclusions[0]
    np.testing.assert_allclose(inc.mua, a * 1e-4, rtol=1e-12)
    np.testing.assert_allclose(inc.mus, s * 1e-4, rtol=1e-12)
    np.testing.assert_allclose(inc.g, g, rtol=1e-12)
    rows = vol.device_optics()
    mua, mus, gg = vol.material_optics()
    np.testing.assert_array_equal(rows[:vol.nmat * vol.nb], volume.optics_rows(mua, mus, gg))
    assert len(rows) == vol.nmat * vol.nb + volume.INC_ROWS * vol.ninc
    assert "NINC" in kernel_defines(vol) and kernel_defines(vol)["NINC"] == 2


def test_vessel_and_ellipsoid_geometry():
    cfg = slab_cfg()
    vol = volume.build(cfg, "slab")
    v, e = vol.inclusions
    a = np.array([0.4, 1.0, 0.3]) / math.sqrt(0.16 + 1.0 + 0.09)
    c = np.array([0.0, 0.0, -130.0])
    perp = np.cross(a, [1.0, 0.0, 0.0])
    perp /= np.linalg.norm(perp)
    pts = c + 500.0 * a + np.outer([0.99, 1.01], 50.0 * perp)      # far along the axis: unbounded
    assert v.contains(pts).tolist() == [True, False]
    ce = np.array([40.0, 20.0, -60.0])
    pts = ce + np.array([[79.0, 0, 0], [81.0, 0, 0], [0, 59.0, 0], [0, 61.0, 0], [0, 0, -29.0], [0, 0, 31.0]])
    assert e.contains(pts).tolist() == [True, False, True, False, True, False]
    # the z ranges that let a step skip an inclusion out of its layer's depths
    assert e.z_range() == pytest.approx((-90.0, -30.0))
    assert v.z_range() == (-volume.BIG, volume.BIG)                  # a tilted vessel reaches every depth
    level = volume.inclusion_of({**C.validate({**SLAB, "inclusion": [{**SLAB["inclusion"][0], "axis": [1.0, 1.0, 0.0]}]},
                                             "x")["inclusion"][0]}, 0, vol.wl)
    assert level.z_range() == pytest.approx((-180.0, -80.0))
    along_y = volume.inclusion_of({**C.validate({**SLAB, "inclusion": [{**SLAB["inclusion"][0], "axis": [0.0, 1.0, 0.0]}]},
                                               "x")["inclusion"][0]}, 0, vol.wl)
    np.testing.assert_allclose(along_y.half_extents(), [50.0, volume.BIG, 50.0])
    np.testing.assert_allclose(e.half_extents(), [80.0, 60.0, 30.0])
    box = e.rows()[3]                   # the bounding box the light connections' legs test
    assert box[0] < 40.0 - 80.0 and box[1] > 40.0 + 80.0 and box[2] < 20.0 - 60.0 and box[3] > 20.0 + 60.0
    assert box[1] < 40.0 + 80.0 + 0.01 and box[0] > 40.0 - 80.0 - 0.01


BAD = [
    ({"radius_um": 0.0}, "inclusion[0].radius_um = 0.0: must be > 0"),
    ({"radius_um": -3.0}, "inclusion[0].radius_um = -3.0: must be > 0"),
    ({"blood": 1.5}, "inclusion[0].blood = 1.5: must be <= 1"),
    ({"saturation": -0.1}, "inclusion[0].saturation = -0.1: must be >= 0"),
    ({"center_mm": [12.0, 5.0]}, "inclusion[0].center_mm = [12.0, 5.0]: outside the model"),
    ({"depth_um": 800.0}, "inclusion[0].depth_um = 800.0: the centre is below the model's bottom"),
    ({"depth_um": 0.0}, "inclusion[0].depth_um = 0.0: must be > 0"),
    ({"axis": [0.0, 0.0, 0.0]}, "inclusion[0].axis = [0.0, 0.0, 0.0]: must not be zero"),
    ({"kind": "tube"}, "inclusion[0].kind = 'tube': must be one of vessel, ellipsoid"),
    ({"radius": 3.0}, "inclusion[0].radius = 3.0: unknown key (did you mean 'radius_um'?)"),
    ({"semi_axes_um": [10.0, 0.0, 5.0]}, "inclusion[0].semi_axes_um[1] = 0.0: must be > 0"),
    ({"radius_um": 1e-300}, "inclusion[0].radius_um = 1e-300: must be >= 0.1 um"),
    ({"scattering": "none"}, "inclusion[0].scattering = 'none': needs mua and mus"),
    ({"kind": "ellipsoid", "semi_axes_um": [10.0, 5e-324, 5.0]},
     "inclusion[0].semi_axes_um[1] = 5e-324: must be >= 0.1 um"),
]


@pytest.mark.parametrize("change,message", BAD, ids=[m.split(":")[0] for _, m in BAD])
def test_bad_inclusion_one_line_exit_2(tmp_path, capsys, change, message):
    raw = {k: (list(v) if isinstance(v, list) else dict(v)) for k, v in SLAB.items()}
    raw["model"] = {**raw["model"], "lateral": "open", "size_mm": [10.0, 10.0]}
    raw["inclusion"] = [{**SLAB["inclusion"][0], "center_mm": [5.0, 5.0], **change}]
    p = tmp_path / "bad.toml"
    p.write_text(raw_toml(raw))
    rc = cli.main(["trace", str(p), "--photons", "100"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1, err
    assert message in err, err


def test_missing_required_inclusion_key(tmp_path, capsys):
    raw = {k: (list(v) if isinstance(v, list) else dict(v)) for k, v in SLAB.items()}
    raw["inclusion"] = [{"kind": "vessel", "depth_um": 100.0}]
    p = tmp_path / "bad.toml"
    p.write_text(raw_toml(raw))
    assert cli.main(["trace", str(p)]) == 2
    assert "inclusion[0].center_mm = None: missing required key" in capsys.readouterr().err


def test_set_item_reaches_an_inclusion():
    cfg = slab_cfg()
    out = C.set_item(cfg, "inclusion.0.radius_um=30")
    assert out["inclusion"][0]["radius_um"] == 30.0 and cfg["inclusion"][0]["radius_um"] == 50.0
    with pytest.raises(C.ConfigError, match=r"inclusion\[1\]\.melanin = 2.0: must be <= 1"):
        C.set_item(cfg, "inclusion.1.melanin=2")
    with pytest.raises(C.ConfigError, match=r"no such inclusion: give an index 0\.\.1"):
        C.set_item(cfg, "inclusion.5.blood=0.5")
    with pytest.raises(C.ConfigError, match=r"the config has no \[\[inclusion\]\] table"):
        C.set_item(C.load("forearm"), "inclusion.0.blood=0.5")


def test_trace_prints_each_inclusion(tmp_path, capsys):
    p = tmp_path / "slab.toml"
    p.write_text(raw_toml({k: v for k, v in SLAB.items()}))
    assert cli.main(["trace", str(p), "--photons", "4000", "--json", str(tmp_path / "t.json")]) == 0
    out = capsys.readouterr().out
    assert "absorbed in inclusion[0] (vessel)" in out and "absorbed in inclusion[1] (ellipsoid)" in out
    import json
    rep = json.loads((tmp_path / "t.json").read_text())
    assert set(rep["absorbed_per_inclusion"]) == {"inclusion[0]", "inclusion[1]"}


def test_render_refused_where_a_pass_does_not_see_inclusions(tmp_path, capsys):
    """The path tracer across periodic sides does not see inclusions: one line naming the key,
    exit 2, no output; both integrators render on flat layers and through the relief (PPM's eye
    pieces there record their layer beside their material: tests/test_ppm_relief_heterogeneous.py)."""
    from clppm.checks.tiny import tiny_config
    raw = tomllib.loads(C.to_toml(tiny_config(size_mm=1.0)))
    raw["inclusion"] = [{"kind": "vessel", "center_mm": [0.5, 0.5], "depth_um": 150.0}]
    flat = {**raw, "relief": {"kind": "flat"}, "papillae": {"amplitude_um": 0.0}}
    periodic = {**flat, "model": {**flat["model"], "lateral": "periodic"}}
    out = tmp_path / "x.png"
    for scene_raw, extra, needles in [
            (periodic, ["--integrator", "pt"], ("model.lateral = 'periodic'", "periodic sides"))]:
        p = tmp_path / "vessel.toml"
        p.write_text(raw_toml(scene_raw))
        rc = cli.main(["render", str(p), "-o", str(out), "-q", *extra])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and len(err.splitlines()) == 1, err
        assert all(n in err for n in needles), err
        assert not out.exists()
    for scene_raw, integrators in ((flat, (["--integrator", "pt"], [])), (raw, (["--integrator", "pt"], []))):
        p.write_text(raw_toml(scene_raw))
        for extra in integrators:
            assert cli.main(["render", str(p), "-o", str(out), "-q", "--passes", "1", "--resolution", "4x3",
                             "--force", *extra]) == 0
            assert out.exists()


def test_shipped_forearm_vein(tmp_path, capsys):
    """configs/forearm_vein.toml is configs/forearm_flat.toml with four inclusions and nothing
    else; PPM and the path tracer render it."""
    vein, flat = C.load("forearm_vein"), C.load("forearm_flat")
    assert [i["kind"] for i in vein["inclusion"]] == ["vessel", "ellipsoid", "ellipsoid", "ellipsoid"]
    assert {k: v for k, v in vein.items() if k != "inclusion"} == {
        **flat, "model": {**flat["model"], "name": "forearm with a vein"}}
    out = tmp_path / "v.png"
    for extra in (["--integrator", "pt"], ["--photons", "20000"]):
        assert cli.main(["render", "forearm_vein", "-o", str(out), "-q", "--resolution", "4x3", "--passes", "1",
                         "--force", *extra]) == 0
        assert out.exists()




# ----------------------------------------------------------------------------- fuzzing the tables
def _inclusion_value():
    from hypothesis import strategies as st
    from test_config_fuzz import _edge_numbers, junk

    @st.composite
    def one(draw):
        key = draw(st.sampled_from(list(C.INCLUSION_SCHEMA)))
        f = C.INCLUSION_SCHEMA[key]
        kind = draw(st.integers(0, 2))
        if kind == 0:
            v = draw(junk)
        elif kind == 1 or f.kind not in ("vec2", "vec3"):
            v = draw(st.sampled_from(_edge_numbers(f) + list(f.choices) + [0.05, 0.1, 1e-300]))
        else:
            n = {"vec2": 2, "vec3": 3}[f.kind]
            v = draw(st.lists(st.one_of(st.sampled_from(_edge_numbers(f) + [0.05, 1e-300]), st.floats(-2e3, 2e3)),
                              min_size=n, max_size=n))
        return key, v
    return one()


def test_fuzzed_inclusion_is_valid_or_one_line_naming_it():
    """One inclusion key set to an edge or junk value: a config whose inclusion builds (finite
    quadric and optics), or one ConfigError naming that inclusion's key (or the key of the
    cross-check it broke), on one line."""
    from hypothesis import given, settings, HealthCheck
    from test_config_fuzz import BASE

    @settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(_inclusion_value())
    def check(kv):
        key, v = kv
        raw = {k: (list(x) if isinstance(x, list) else dict(x)) for k, x in BASE.items()}
        kind = "ellipsoid" if key == "semi_axes_um" else "vessel"        # the key that kind reads
        raw["inclusion"] = [{"kind": kind, "center_mm": [0.5, 0.5], "depth_um": 100.0, key: v}]
        try:
            cfg = C.validate(raw, "fuzz.toml")
        except C.ConfigError as e:
            msg = str(e)
            assert "\n" not in msg and msg.startswith("fuzz.toml: inclusion"), msg
            assert e.key.startswith(f"inclusion[0].{key}") or e.key.split(".")[-1] in (
                "mua", "mus", "g", "a", "depth_um", "center_mm", "axis", "radius_um") or e.key == "inclusion", msg
            return
        vol = volume.build(cfg, "fuzz")
        inc = vol.inclusions[0]
        assert np.all(np.isfinite(inc.Q)) and np.all(np.isfinite(inc.rows()))
        assert np.all(np.isfinite(vol.device_optics()))
        assert C.validate(tomllib.loads(C.to_toml(cfg)), "fuzz.toml") == cfg
    check()
