"""Adding-doubling reference values (iadpython) for validating the photon transport.

The numbers live in ``tests/data/adding_doubling.json``; this test recomputes every one of
them with iadpython so that their provenance is checked on each run. Regenerate the file with
``python tests/test_adding_doubling_refs.py --write``.

iadpython (S. Prahl) ``Sample.rt()`` returns UR1/UT1 for collimated normal incidence. Reading
iadpython 0.5.3's source (ad.py, start.py): the boundary matrices put the Fresnel reflection on
the diagonal and the thin-layer start puts the unscattered beam on the diagonal of T, so UR1
is the TOTAL reflectance (specular included) and UT1 the TOTAL transmittance (unscattered
included). ``Sample.unscattered_rt()`` gives the unscattered parts. Checked here against van de
Hulst's slab (a = 0.9, b = 2, g = 0.75, n = 1), Rd = 0.09739, Tt = 0.66096, the classic MCML
verification case (Wang, Jacques & Zheng, Comput. Methods Programs Biomed. 47 (1995) 131).

Conventions stored: ``rd_excl_specular`` = UR1 − (first-surface Fresnel reflectance at normal
incidence), i.e. MCML's Rd, which counts unscattered light that comes back out after
reflecting off the slab's bottom surface; ``rd_scattered_only`` = UR1 − unscattered
reflectance (iadpython's convention). For a semi-infinite medium both are equal.

Quadrature: iadpython 0.5.3 builds its Radau points from high-degree polynomial
coefficients, which lose accuracy above about 24 points (sum of weights off by 4e-5 at 32,
wrong at 64). For n = 1 all quad_pts points are Radau, so 24 is the limit; for n != 1 half
are Gauss (accurate) and half Radau, so up to 48. Convergence is checked by halving.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import iadpython as iad  # in the "test" extra of pyproject.toml; a missing install must fail CI
import pytest

DATA = Path(__file__).resolve().parent / "data" / "adding_doubling.json"

# name: (mua [1/cm], mus [1/cm], g, n, thickness [cm] or None for semi-infinite, quad_pts)
CASES = {
    "vdh_slab_n1": (10.0, 90.0, 0.75, 1.0, 0.02, 24),
    "slab_n1.4": (10.0, 90.0, 0.75, 1.4, 0.02, 48),
    "semi_inf_g0.9_n1.4": (1.0, 100.0, 0.9, 1.4, None, 48),
    "semi_inf_g0.9_n1": (1.0, 100.0, 0.9, 1.0, None, 24),
    "semi_inf_g0_mua0.1_n1": (0.1, 100.0, 0.0, 1.0, None, 24),
}
PUBLISHED = {"vdh_slab_n1": {"rd_excl_specular": 0.09739, "tt": 0.66096}}


def chandrasekhar_albedo(albedo, mu0=1.0, nodes=200):
    """Reflectance of a semi-infinite isotropic scatterer, n = 1: 1 - H(mu0) sqrt(1 - albedo).

    Independent of iadpython: Chandrasekhar's H-function (Radiative Transfer, 1950), solved by
    iterating 1/H(mu) = sqrt(1 - w) + (w/2) int_0^1 mu' H(mu') / (mu + mu') dmu' on Gauss nodes.
    """
    import numpy as np

    x, wt = np.polynomial.legendre.leggauss(nodes)
    mu, wt = 0.5 * (x + 1.0), 0.5 * wt
    root = math.sqrt(1.0 - albedo)
    H = np.ones_like(mu)
    for _ in range(20000):
        H_new = 1.0 / (root + 0.5 * albedo * (wt * mu * H / (mu[:, None] + mu)).sum(axis=1))
        done = np.max(np.abs(H_new - H)) < 1e-14
        H = H_new
        if done:
            break
    H0 = 1.0 / (root + 0.5 * albedo * float((wt * mu * H / (mu0 + mu)).sum()))
    return 1.0 - H0 * root


def call_string(mua, mus, g, n, d_cm, quad_pts):
    b = "math.inf" if d_cm is None else f"({mua} + {mus}) * {d_cm}"
    return (f"s = iadpython.Sample(a={mus}/({mua} + {mus}), b={b}, g={g}, n={n}, n_above=1.0, "
            f"n_below=1.0, quad_pts={quad_pts}); ur1, ut1, uru, utu = s.rt(); "
            f"r_un, t_un = s.unscattered_rt()")


def compute(mua, mus, g, n, d_cm, quad_pts):
    """All stored quantities for one case, from iadpython."""
    a = mus / (mua + mus)
    b = math.inf if d_cm is None else (mua + mus) * d_cm
    s = iad.Sample(a=a, b=b, g=g, n=n, n_above=1.0, n_below=1.0, quad_pts=quad_pts)
    ur1, ut1, _, _ = s.rt()
    r_un, t_un = s.unscattered_rt()
    fresnel = ((n - 1.0) / (n + 1.0)) ** 2
    out = {
        "ur1_total_reflectance": float(ur1),
        "specular_fresnel": fresnel,
        "unscattered_reflectance": float(r_un),
        "rd_excl_specular": float(ur1) - fresnel,
        "rd_scattered_only": float(ur1) - float(r_un),
    }
    if d_cm is not None:
        out["tt"] = float(ut1)
        out["unscattered_transmittance"] = float(t_un)
    return out


def build():
    cases = {}
    for name, (mua, mus, g, n, d_cm, N) in CASES.items():
        vals = compute(mua, mus, g, n, d_cm, N)
        half = compute(mua, mus, g, n, d_cm, N // 2)
        change = max(abs(vals[k] - half[k]) for k in vals)
        cases[name] = {
            "inputs": {"mua_per_cm": mua, "mus_per_cm": mus, "g": g, "n_sample": n,
                       "n_outside": 1.0, "thickness_cm": d_cm if d_cm is not None else "semi-infinite",
                       "albedo": mus / (mua + mus),
                       "optical_thickness": "inf" if d_cm is None else (mua + mus) * d_cm,
                       "illumination": "collimated, normal incidence", "phase_function": "Henyey-Greenstein"},
            "call": call_string(mua, mus, g, n, d_cm, N),
            "quad_pts": N,
            "values": vals,
            "rounded_4dp": {k: round(v, 4) for k, v in vals.items()},
            "convergence": {"quad_pts": N // 2, "values": half, "max_abs_change": change},
        }
        if name in PUBLISHED:
            cases[name]["published"] = PUBLISHED[name]
        if d_cm is None and g == 0.0 and n == 1.0:
            cases[name]["independent_check"] = {
                "method": "Chandrasekhar H-function, R = 1 - H(1) sqrt(1 - albedo), 200 Gauss nodes",
                "rd": chandrasekhar_albedo(mus / (mua + mus))}
    return {
        "description": "Adding-doubling reference reflectance/transmittance for validating clppm's "
                       "photon transport. See tests/test_adding_doubling_refs.py for conventions.",
        "iadpython_version": iad.__version__,
        "generated_by": "python tests/test_adding_doubling_refs.py --write",
        "conventions": {
            "ur1_total_reflectance": "iadpython UR1: total reflectance incl. specular",
            "specular_fresnel": "((n-1)/(n+1))^2, first-surface reflection at normal incidence",
            "unscattered_reflectance": "iadpython unscattered_rt()[0]: Fresnel incl. unscattered echo off the bottom surface",
            "rd_excl_specular": "UR1 - specular_fresnel (MCML's Rd)",
            "rd_scattered_only": "UR1 - unscattered_reflectance",
            "tt": "iadpython UT1: total transmittance incl. unscattered (MCML's Tt = Td + unscattered)",
        },
        "quadrature_note": "iadpython 0.5.3 Radau points lose accuracy above ~24 points; n=1 cases "
                           "use 24 (all Radau), n=1.4 cases 48 (24 Gauss + 24 Radau). Convergence: "
                           "same case at half the points; max_abs_change < 1e-4 everywhere.",
        "cases": cases,
    }


def _stored():
    with open(DATA) as fh:
        return json.load(fh)


def test_stored_cases_match_definitions():
    stored = _stored()
    assert set(stored["cases"]) == set(CASES)
    for name, (mua, mus, g, n, d_cm, N) in CASES.items():
        c = stored["cases"][name]
        assert c["quad_pts"] == N and c["call"] == call_string(mua, mus, g, n, d_cm, N)


@pytest.mark.parametrize("name", list(CASES))
def test_recompute_matches_stored(name):
    stored = _stored()["cases"][name]
    mua, mus, g, n, d_cm, N = CASES[name]
    got = compute(mua, mus, g, n, d_cm, N)
    for key, want in stored["values"].items():
        assert got[key] == pytest.approx(want, abs=1e-7), f"{name}: {key} recomputed {got[key]!r}, stored {want!r}"
    half = compute(mua, mus, g, n, d_cm, N // 2)
    change = max(abs(got[k] - half[k]) for k in got)
    assert change < 1e-4, f"{name}: quad_pts {N} vs {N // 2} differ by {change:.2e} (not 4-digit converged)"


def test_van_de_hulst_slab():
    vals = _stored()["cases"]["vdh_slab_n1"]["values"]
    assert vals["rd_excl_specular"] == pytest.approx(0.09739, abs=3e-5)
    assert vals["tt"] == pytest.approx(0.66096, abs=3e-5)
    assert vals["unscattered_transmittance"] == pytest.approx(math.exp(-2.0), rel=1e-12)


def test_isotropic_semi_infinite_against_chandrasekhar():
    mua, mus, *_ = CASES["semi_inf_g0_mua0.1_n1"]
    stored = _stored()["cases"]["semi_inf_g0_mua0.1_n1"]
    expect = chandrasekhar_albedo(mus / (mua + mus))
    assert stored["independent_check"]["rd"] == pytest.approx(expect, abs=1e-9)
    assert stored["values"]["rd_excl_specular"] == pytest.approx(expect, abs=1e-5)


def test_ur1_includes_specular():
    """A non-scattering slab reflects exactly its unscattered (Fresnel) part in UR1."""
    s = iad.Sample(a=0.0, b=2.0, g=0.0, n=1.4, quad_pts=16)
    ur1, ut1, _, _ = s.rt()
    r_un, t_un = s.unscattered_rt()
    assert ur1 == pytest.approx(r_un, abs=1e-5) and ut1 == pytest.approx(t_un, abs=1e-5)


if __name__ == "__main__":
    result = build()
    text = json.dumps(result, indent=2) + "\n"
    if "--write" in sys.argv:
        DATA.parent.mkdir(parents=True, exist_ok=True)
        DATA.write_text(text)
    print(text)
