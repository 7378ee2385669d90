"""Fitting melanin, blood, saturation and scattering to a measured spectrum; measured CSVs.

The recovery test fits a spectrum that clppm's own photon pass generated at known parameters
(same seed and photon count as the fit: common random numbers).  Tolerances are set by the
photon noise of the small run (1500 photons per band, standard error ~0.009 per band):
melanin and scattering factors within 15 %, blood factor within 35 %, saturation within 0.15.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from clppm import config
from clppm.analysis import fit, nist
from clppm.config import ConfigError

ROOT = os.path.dirname(os.path.dirname(__file__))
FOREARM = os.path.join(ROOT, "configs", "forearm.toml")


@pytest.fixture(scope="module")
def cfg():
    return config.load(FOREARM)


def _csv(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def _good_rows(lo=380, hi=780, step=10, f=lambda w: 0.2 + 0.4 * (w - 380) / 400):
    return "".join(f"{w},{f(w):.4f}\n" for w in range(lo, hi + 1, step))


# ----------------------------------------------------------------------------- measured CSV
def test_read_good_csv(tmp_path):
    p = _csv(tmp_path, "m.csv", "wavelength_nm,reflectance\n# a comment\n" + _good_rows())
    wl, R, label = nist.read_spectrum(p)
    assert wl[0] == 380 and wl[-1] == 780 and R.shape == wl.shape and label == "m.csv"
    p2 = _csv(tmp_path, "tabs.txt", _good_rows().replace(",", "\t"))
    assert np.allclose(nist.read_spectrum(p2)[1], R)
    # the packaged NIST file, one subject by --subject
    wl3, R3, lab3 = nist.read_spectrum(nist.nist_path(), subject=5)
    w5, r5 = nist.subject(5)
    assert np.allclose(wl3, w5) and np.allclose(R3, r5) and lab3.endswith("subject_5")


@pytest.mark.parametrize("name,text,problem", [
    ("nonnum.csv", "380,0.2\n390,abc\n" + _good_rows(400), "'abc' is not a number"),
    ("one.csv", "".join(f"{w}\n" for w in range(380, 781, 10)), "only one column"),
    ("short.csv", _good_rows(400, 700), "does not cover 380-780 nm"),
    ("percent.csv", _good_rows(f=lambda w: 35.0), "outside [0, 1.5] (percent?"),
    ("negative.csv", _good_rows(f=lambda w: -0.1 if w == 500 else 0.3), "reflectance at 500 nm"),
    ("ragged.csv", "380,0.2\n390,0.3,0.4\n", "has 3 columns"),
    ("multi.csv", "wl,a,b\n" + "".join(f"{w},0.3,0.4\n" for w in range(380, 781, 10)),
     "choose one with --subject"),
    ("dup.csv", _good_rows() + "500,0.3\n", "appears twice"),
    ("empty.csv", "wavelength_nm,reflectance\n", "no numeric rows"),
])
def test_bad_csv_is_a_clear_error(tmp_path, name, text, problem):
    p = _csv(tmp_path, name, text)
    with pytest.raises(ConfigError) as e:
        nist.read_spectrum(p)
    msg = str(e.value)
    assert name in msg and problem in msg, msg


def test_missing_csv_and_cli_exit_2(tmp_path, capsys):
    from clppm import cli
    missing = str(tmp_path / "nope.csv")
    with pytest.raises(ConfigError, match="nope.csv.*file not found"):
        nist.read_spectrum(missing)
    out = str(tmp_path / "f.toml")
    assert cli.main(["fit", missing, "--config", FOREARM, "-o", out]) == 2
    err = capsys.readouterr().err
    assert "nope.csv" in err and "file not found" in err
    bad = _csv(tmp_path, "bad.csv", _good_rows(450, 700))
    assert cli.main(["fit", bad, "--config", FOREARM, "-o", out]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "does not cover" in err
    assert cli.main(["fit", "--config", FOREARM, "-o", out]) == 2          # nothing to fit
    assert "--subject" in capsys.readouterr().err
    assert not os.path.exists(out)


# ----------------------------------------------------------------------------- model
def test_fit_model_applies_parameters(cfg):
    m = fit.FitModel.from_config(cfg, "forearm.toml")
    names = [L["name"] for L in cfg["layer"]]
    assert [names[i] for i in m.melanin_layers] == ["granular + spinous", "basal"]
    assert "subcutis" not in [names[i] for i in m.blood_layers]
    assert len(m.blood_layers) == 5 and len(m.scatter_layers) == 8
    c = m.apply({"melanin": 2.0, "blood": 0.5, "saturation": 0.6, "scattering": 1.25})
    L = {x["name"]: x for x in c["layer"]}
    assert math.isclose(L["basal"]["melanin"], 0.2) and math.isclose(L["basal"]["baseline"], 0.8)
    assert math.isclose(L["granular + spinous"]["melanin"], 0.02)
    assert math.isclose(L["granular + spinous"]["baseline"], 0.98)
    assert math.isclose(L["papillary dermis"]["blood"], 0.01)
    assert math.isclose(L["upper blood net plexus"]["blood"], 0.15)
    assert L["upper blood net plexus"]["saturation"] == 0.6
    assert L["subcutis"]["blood"] == 0.05 and L["subcutis"]["saturation"] == 0.8
    assert math.isclose(L["basal"]["k"], 2.5) and math.isclose(L["reticular dermis"]["k"], 5.0)
    assert c["relief"] == cfg["relief"] and c["light"] == cfg["light"]     # the rest unchanged
    b = m.bounds()
    assert b["melanin"][1] == pytest.approx(10.0) and b["blood"][1] == pytest.approx(1 / 0.3)


def test_toml_round_trip(cfg, tmp_path):
    p = tmp_path / "x.toml"
    fit.write_toml(cfg, str(p), ["a header", ""])
    back = config.load(str(p))
    assert back == cfg
    assert p.read_text().startswith("# a header\n#\n")
    assert "thickness_um = inf" in p.read_text()


def test_surrogate_tracks_photon_pass(cfg):
    """The adding-doubling surrogate (one index) stays within 0.03 of the photon pass on the
    flat forearm model, and moves the same way with melanin."""
    m = fit.FitModel.from_config(cfg, "forearm.toml")
    wl = np.array([450.0, 550.0, 650.0])
    with threadpool_limits(limits=1, user_api="blas"):      # as the fit runs it
        sur = fit.Surrogate(m, wl, n=1.34)
        p0 = m.start()
        a0 = sur(p0)
        a1 = sur(dict(p0, melanin=2.0))
    fwd = fit.Forward(m, (450.0, 650.0, 100.0), 1500, seed=2)
    r0 = fwd(p0)[0]
    assert np.all(np.abs(a0 - r0) < 0.03), (a0, r0)
    assert np.all(a1 < a0)


# ----------------------------------------------------------------------------- fits
def test_fit_recovers_known_truth(cfg):
    """A spectrum from clppm's photon pass at known parameters is fitted back (hybrid fit,
    same seed and photons: common random numbers); tolerances in the module docstring."""
    truth = {"melanin": 1.7, "blood": 0.65, "saturation": 0.65, "scattering": 1.15}
    bands, photons, seed = (420.0, 700.0, 20.0), 1500, 3
    m = fit.FitModel.from_config(cfg, "forearm.toml")
    fwd = fit.Forward(m, bands, photons, seed=seed)
    R, _ = fwd(truth)
    res, model = fit.fit(fwd.wl, R, cfg, photons=photons, bands=bands, seed=seed, max_iter=4,
                         source="forearm.toml", label="truth")
    p = res.params
    assert abs(p["melanin"] / truth["melanin"] - 1) < 0.15, p
    assert abs(p["scattering"] / truth["scattering"] - 1) < 0.15, p
    assert abs(p["blood"] / truth["blood"] - 1) < 0.35, p
    assert abs(p["saturation"] - truth["saturation"]) < 0.15, p
    assert res.rms < 0.25 * res.rms_initial and res.rms < 2 * res.settings["mc_se_mean"]
    assert res.evaluations <= 6
    assert res.delta_e is not None and res.delta_e < res.delta_e_initial


def test_cli_fit_nist_subject_writes_loadable_toml(tmp_path, capsys):
    """`clppm fit --subject N` on the packaged NIST set (tiny run): the TOML loads, keeps the
    model's relief and light, and holds the fitted layer values; plot and report are written."""
    from clppm import cli
    out = tmp_path / "fitted.toml"
    rc = cli.main(["fit", "--subject", "12", "--config", FOREARM, "-o", str(out), "--photons", "200",
                   "--bands", "450:650:100", "--max-iter", "1", "-q"])
    assert rc == 0
    got = config.load(str(out))
    base = config.load(FOREARM)
    rep = json.loads((tmp_path / "fitted.json").read_text())
    assert (tmp_path / "fitted.png").stat().st_size > 10000
    assert got["relief"] == base["relief"] and got["light"] == base["light"]
    L = {x["name"]: x for x in got["layer"]}
    p = rep["params"]
    assert math.isclose(L["basal"]["melanin"], min(1.0, 0.1 * p["melanin"]), rel_tol=1e-9)
    assert math.isclose(L["papillary dermis"]["blood"], 0.02 * p["blood"], rel_tol=1e-9)
    assert rep["measured"] == "NIST subject_12" and len(rep["fitted_R"]) == 3
    assert "wrote" in capsys.readouterr().out


def test_cli_fit_mc_forward_runs(tmp_path):
    from clppm import cli
    p = _csv(tmp_path, "m.csv", _good_rows(f=lambda w: 0.25 + 0.3 * (w > 600)))
    out = tmp_path / "mc.toml"
    rc = cli.main(["fit", p, "--config", FOREARM, "-o", str(out), "--photons", "150",
                   "--bands", "500:700:200", "--max-iter", "1", "--forward", "mc", "-q"])
    assert rc == 0 and config.load(str(out))["layer"][0]["name"] == "stratum corneum"


# ----------------------------------------------------------------------------- solver
def test_solver_on_a_linear_problem():
    """The bounded least squares and its Jacobian on r(u) = A u - b, whose answers are known:
    inside the box the normal equations' solution, with a bound active the solution along the
    free parameters; the Jacobian is A, also at an upper bound (one-sided inwards)."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(12, 4))
    u_true = np.array([0.3, -0.2, 0.5, 0.1])
    b = A @ u_true + 0.01 * rng.normal(size=12)
    box = fit._Box({}, np.full(4, -1.0), np.full(4, 1.0))

    def resid(u):
        return A @ u - b
    res = fit.solve(resid, np.zeros(4), box, fit._STEP_AD, 60, 1e-12, 1e-10)
    assert np.allclose(res.x, np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-6)
    assert res.converged and res.iterations == len(res.history) - 1 >= 1
    assert res.history[-1]["rms"] < res.history[0]["rms"]
    # at an upper bound, where the model clips (as FitModel.apply clips fractions), the step
    # goes inwards: a step outwards would see a flat residual
    clipped = lambda u: resid(np.minimum(u, box.hi))                      # noqa: E731
    assert np.allclose(fit.jacobian(clipped, np.array([1.0, 0.0, 0.0, 0.0]), box.hi, fit._STEP_AD), A)
    # the unconstrained answer beyond u0 <= 0: u0 sits on the bound, the rest solve the remainder
    tight = fit._Box({}, np.array([-1.0, -1, -1, -1]), np.array([0.0, 1, 1, 1]))
    got = fit.solve(resid, np.full(4, -0.5), tight, fit._STEP_AD, 60, 1e-12, 1e-10).x
    rest = np.linalg.lstsq(A[:, 1:], b, rcond=None)[0]
    assert abs(got[0]) < 1e-6 and np.allclose(got[1:], rest, atol=1e-5), got
    # the iteration limit holds and is no convergence
    one = fit.solve(resid, np.full(4, -0.9), box, fit._STEP_AD, 1, 1e-12, 1e-10)
    assert one.iterations == 1 and not one.converged


def test_fit_runs_blas_on_one_thread(cfg):
    """Inside the fit every BLAS library runs one thread (OpenBLAS's spinning workers slowed the
    surrogate several times on a small shared CPU), and the caller's thread counts come back."""
    from threadpoolctl import threadpool_info

    def blas_threads():
        return [d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"]
    before = blas_threads()
    seen = []
    wl = np.arange(380.0, 781.0, 10.0)
    fit.fit(wl, 0.3 + 0.0 * wl, cfg, photons=150, bands=(500.0, 700.0, 200.0), max_iter=1,
            forward="mc", source="forearm.toml", log=lambda *a: seen.append(blas_threads()))
    assert before and seen and all(t == [1] * len(before) for t in seen), (before, seen)
    assert blas_threads() == before
