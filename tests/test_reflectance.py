"""Spectral reflectance R(λ) from the photon pass, image reflectance per method, NIST comparison.

References: adding-doubling values of tests/data/adding_doubling.json (iadpython 0.5.3, see
tests/test_adding_doubling_refs.py); the NIST skin reflectance set (Cooksey et al. 2017,
clppm/data/README.md quotes its 550 / 700 nm medians).
"""
from __future__ import annotations

import copy
import json
import math
import os

import numpy as np
import pytest

from clppm import config
from clppm.analysis import nist, reflectance
from clppm.config import ConfigError

HERE = os.path.dirname(__file__)
ROOT = os.path.dirname(HERE)
AD = json.load(open(os.path.join(HERE, "data", "adding_doubling.json")))["cases"]


def _forearm(**changes) -> dict:
    cfg = config.load(os.path.join(ROOT, "configs", "forearm.toml"))
    raw = copy.deepcopy(cfg)
    for sec, vals in changes.items():
        raw[sec].update(vals)
    return config.validate(raw, "forearm-test")


# ----------------------------------------------------------------------------- photon pass
@pytest.mark.parametrize("case,spec", [("semi_inf_g0.9_n1.4", "mua=1,mus=100,g=0.9,n=1.4"),
                                       ("semi_inf_g0.9_n1", "mua=1,mus=100,g=0.9,n=1.0")])
def test_semi_infinite_matches_adding_doubling(dev, case, spec):
    """Homogeneous semi-infinite medium, collimated normal incidence: total reflectance (SCI)
    and diffuse reflectance (SCE) against adding-doubling (iadpython UR1 and UR1 - Fresnel)."""
    ref = AD[case]["values"]
    cfg = config.slab_config(spec)
    r = reflectance.spectral_reflectance(cfg, photons=20000, angle_deg=0.0, specular=True, dev=dev)
    assert r.specular_included and r.wl.shape == (1,)
    tol = 4 * r.se[0] + 0.002
    assert abs(r.R[0] - ref["ur1_total_reflectance"]) < tol, (r.R, r.se, ref)
    assert abs(r.Rd[0] - ref["rd_excl_specular"]) < 4 * r.Rd_se[0] + 0.002
    assert abs(r.specular[0] - ref["specular_fresnel"]) < 1e-6
    assert r.lost[0] == 0 and r.balance_error < 1e-9
    assert r.se[0] > 0


def test_forearm_flat_spectrum_in_unit_interval_sci_sce(dev):
    """R(λ) of the flat forearm model lies in [0, 1]; SCI - SCE is the Fresnel reflection of the
    stratum corneum (n = 1.5) at 8°, about 0.04, the same in every band."""
    cfg = _forearm()
    kw = dict(photons=1500, bands=(400.0, 700.0, 100.0), flat=True, dev=dev, batches=5)
    sci = reflectance.spectral_reflectance(cfg, specular=True, **kw)
    sce = reflectance.spectral_reflectance(cfg, specular=False, **kw)
    assert sci.wl.tolist() == [400.0, 500.0, 600.0, 700.0]
    for r in (sci, sce):
        assert np.all((r.R >= 0) & (r.R <= 1)) and np.all(r.se > 0)
        assert np.all(r.lost == 0) and np.all(r.Tt == 0)
        assert np.allclose(r.R + r.A + r.lost, 1.0 - (0 if r.specular_included else r.specular),
                           atol=1e-3)
    assert np.allclose(sci.R - sce.R, sci.specular)            # same photons (common seed)
    assert np.allclose(sci.specular, 0.04, atol=2e-3)
    assert sci.R[-1] > sci.R[0]                                 # skin is redder than blue
    assert "pencil beam on a laterally infinite flat model" in sci.geometry


def test_relief_model_is_periodic_with_a_wide_beam(dev):
    """A model with relief and papillae is traced with periodic sides under a beam over the
    whole model: no light is lost at the sides."""
    cfg = _forearm(model={"size_mm": [0.3, 0.3]}, relief={"spacing_um": 100.0, "width_um": 20.0})
    m = reflectance.measurement_config(cfg, 8.0, bands=(450.0, 650.0, 200.0))
    assert m["model"]["lateral"] == "periodic"
    assert m["light"]["kind"] == "wide" and m["light"]["width_mm"] == [0.3, 0.3]
    assert m["light"]["center_mm"] == [0.15, 0.15] and m["light"]["spectrum"] == "flat"
    assert math.isclose(m["light"]["direction"][2], -math.cos(math.radians(8.0)))
    r = reflectance.spectral_reflectance(cfg, photons=600, bands=(450.0, 650.0, 200.0), dev=dev,
                                         batches=3)
    assert np.all(r.lost == 0) and np.all((r.R > 0) & (r.R < 1))
    assert "periodic" in r.geometry


def test_port_bounds_reflectance_from_below(dev):
    """A 1 mm square port (open sides) collects less than the infinite sample; it needs a
    flat model."""
    cfg = _forearm()
    kw = dict(photons=800, bands=(700.0, 700.0, 10.0), flat=True, dev=dev, batches=4, seed=3)
    inf = reflectance.spectral_reflectance(cfg, **kw)
    port = reflectance.spectral_reflectance(cfg, port_mm=1.0, **kw)
    assert port.lost[0] > 0.02 and port.R[0] < inf.R[0]
    with pytest.raises(ConfigError, match="needs a flat model"):
        reflectance.measurement_config(cfg, port_mm=5.0)
    with pytest.raises(ConfigError, match="0..85"):
        reflectance.measurement_config(cfg, angle_deg=90.0)


# ----------------------------------------------------------------------------- images
def test_method_reflectance_small(dev):
    """Image reflectance at a tiny size: per-pixel white reference, finite values, photon-pass
    reference at the light's incidence angle at the image centre."""
    cfg = _forearm(relief={"kind": "flat"}, papillae={"amplitude_um": 0.0},
                   spectrum={"step_nm": 100.0})
    out = reflectance.method_reflectance(cfg, "e", passes=2, photons=20000, resolution=(8, 6),
                                         band_photons=500, dev=dev)
    assert out["region"] == [2, 1, 6, 4]
    assert out["wavelength_nm"] == [380.0, 480.0, 580.0, 680.0, 780.0]
    m = out["methods"]["e"]
    R = np.asarray(m["R"])
    assert R.shape == (5,) and np.all(np.isfinite(R)) and np.all(R >= 0)
    pp = out["photon_pass"]
    # the point light at (0, 10, 10) mm seen from the model centre (5, 5, 0) mm: 35.26°
    assert abs(pp["angle_deg"] - math.degrees(math.atan(math.sqrt(50) / 10))) < 0.1
    assert len(m["ratio_to_photon_pass"]) == 5
    with pytest.raises(ConfigError, match="methods are letters"):
        reflectance.method_reflectance(cfg, "xz", passes=1, photons=100, resolution=(4, 4), dev=dev)


def test_white_region_matches_white_reference_at_centre():
    from clppm.scene import bands, camera
    from clppm.scene.light import Light, white_reference
    cfg = _forearm(camera={"resolution": [4, 4]})
    cam = camera.from_config(cfg["camera"])
    wl = config.wavelengths(cfg)
    s = bands.source_spectrum(cfg, wl)
    w = reflectance.white_region(cfg, cam, wl, s, (1, 1, 3, 3))
    centre = white_reference(Light.from_config(cfg), cam, wl, s)
    assert w.shape == (2, 2, len(wl))
    assert np.allclose(w.mean((0, 1)), centre, rtol=0.02)    # the four pixels around the centre
    assert w[0, 0, 40] > w[1, 1, 40]                          # nearer the light at the upper left


# ----------------------------------------------------------------------------- NIST
def test_nist_population_matches_readme():
    pop = nist.population(np.array([550.0, 700.0]))
    assert abs(pop["median"][0] - 0.33) < 0.01 and abs(pop["median"][1] - 0.61) < 0.01
    assert abs(pop["p5"][0] - 0.20) < 0.01 and abs(pop["p95"][0] - 0.39) < 0.01
    assert abs(pop["p5"][1] - 0.46) < 0.01 and abs(pop["p95"][1] - 0.67) < 0.01
    wl, R, names = nist.load_nist()
    assert R.shape == (135, 100) and wl[0] == 379 and wl[-1] == 781 and names[0] == "subject_1"
    with pytest.raises(ValueError):
        nist.nist_on([300.0, 500.0])


def test_nist_compare_metrics():
    wl = np.arange(380.0, 781.0, 5.0)
    med = nist.population(wl)["median"]
    c = nist.compare(wl, med)
    assert c["rmse_median"] < 1e-12 and c["delta_e2000_median"] < 1e-9
    assert c["inside_5_95"]["inside"]
    _, s7 = nist.subject(7, wl)
    c7 = nist.compare(wl, s7)
    assert c7["nearest_subject"] == "subject_7" and c7["rmse_nearest"] < 1e-12
    assert c7["delta_e2000_nearest"] < 1e-9
    dark = nist.compare(wl, 0.5 * med)
    assert not dark["inside_5_95"]["inside"] and dark["delta_e2000_median"] > 10
    assert dark["inside_5_95"]["below_p5_nm"]
    # a flat grey 0.5 has a* = b* = 0 under D65 relative to the same white
    lab = nist.lab(wl, np.full(wl.size, 0.5))
    assert abs(lab[1]) < 1e-6 and abs(lab[2]) < 1e-6 and abs(lab[0] - 76.07) < 0.05


def test_nist_plot(tmp_path):
    wl = np.arange(380.0, 781.0, 20.0)
    R = nist.population(wl)["median"]
    p = tmp_path / "r.png"
    nist.plot(str(p), wl, R, se=np.full(wl.size, 0.01), curves={"x": (wl, R * 0.9)},
              nearest="subject_3")
    assert p.stat().st_size > 10000


# ----------------------------------------------------------------------------- CLI
def test_cli_reflectance(tmp_path, capsys):
    from clppm import cli
    from clppm.analysis import fit
    cfg = _forearm(relief={"kind": "flat"}, papillae={"amplitude_um": 0.0})
    toml = tmp_path / "flat.toml"
    toml.write_text(fit.to_toml(cfg))
    js, png = tmp_path / "r.json", tmp_path / "r.png"
    rc = cli.main(["reflectance", str(toml), "--photons", "400", "--bands", "380:780:100",
                   "--batches", "4", "--json", str(js), "--plot", str(png)])
    assert rc == 0
    out = json.loads(js.read_text())
    pp = out["photon_pass"]
    assert pp["wavelength_nm"] == [380.0, 480.0, 580.0, 680.0, 780.0]
    assert all(0 <= v <= 1 for v in pp["R"]) and pp["photons_per_band"] == 400
    assert "rmse_median" in out["nist"] and png.stat().st_size > 10000
    text = capsys.readouterr().out
    assert "NIST 5-95 % band" in text and "ΔE2000" in text
    rc = cli.main(["reflectance", str(toml), "--angle", "95", "--photons", "10"])
    assert rc == 2
    assert "--angle" in capsys.readouterr().err
