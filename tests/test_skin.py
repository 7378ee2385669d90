"""Skin layers: Table 1 extinction of Kamatani & Kawai from the packaged forearm stack."""
import dataclasses
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from clppm.scene import skin, spectra

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
FIELDS = {f.name for f in dataclasses.fields(skin.Layer)}
NINE = ["stratum corneum", "granular + spinous", "basal", "papillary dermis",
        "subpapillary dermis", "upper blood net plexus", "reticular dermis",
        "deep blood net plexus", "subcutis"]


def load_stack(name):
    with open(CONFIGS / f"{name}.toml", "rb") as fh:
        tables = tomllib.load(fh)["layer"]
    layers = []
    for t in tables:
        t = dict(t)
        if isinstance(t["thickness_um"], str):      # tolerate "inf" written as a string
            t["thickness_um"] = float(t["thickness_um"])
        layers.append(skin.Layer(**t))
    return tables, layers


@pytest.mark.parametrize("site", ["forearm", "cheek"])
def test_stack_files_are_nine_layers_with_layer_keys(site):
    tables, layers = load_stack(site)
    assert [L.name for L in layers] == NINE
    for t in tables:
        assert set(t) <= FIELDS, f"unknown keys {set(t) - FIELDS} in layer {t['name']!r}"
    # only the bottom layer may be semi-infinite
    assert math.isinf(layers[-1].thickness_um)
    assert all(math.isfinite(L.thickness_um) and L.thickness_um > 0 for L in layers[:-1])
    assert [L.bottom for L in layers[:3]] == ["surface", "papillae", "papillae"]
    assert layers[3].bottom == "surface"          # the papillary dermis follows the relief
    assert all(L.bottom == "flat" for L in layers[4:])
    # more blood in the plexuses than in the dermis around them
    by = {L.name: L for L in layers}
    assert by["upper blood net plexus"].blood > by["reticular dermis"].blood
    assert by["deep blood net plexus"].blood > by["reticular dermis"].blood


def test_forearm_thicknesses_are_table1():
    _, layers = load_stack("forearm")
    for L in layers[:5]:
        assert L.thickness_um == skin.PAPER_TABLE1["thickness_um"][L.name], L.name


def test_cheek_is_thinner_and_bloodier_than_forearm():
    _, fore = load_stack("forearm")
    _, cheek = load_stack("cheek")
    assert cheek[0].thickness_um < fore[0].thickness_um
    assert cheek[1].thickness_um + cheek[2].thickness_um < fore[1].thickness_um + fore[2].thickness_um
    assert cheek[3].blood > fore[3].blood


_, _FOREARM = load_stack("forearm")
_CASES = [(L.name, stat) for L in _FOREARM[:5] for stat in ("max", "mean", "min")]


@pytest.mark.parametrize("name,stat", _CASES, ids=[f"{n}-{s}" for n, s in _CASES])
def test_table1_extinction(name, stat):
    layer = next(L for L in _FOREARM if L.name == name)
    got = skin.extinction_stats(layer, spectra.wavelengths())[stat]
    want = skin.PAPER_TABLE1[f"extinction_{stat}"][name]
    assert abs(got - want) <= 0.1, (
        f"Table 1 {stat} extinction of {name!r}: computed {got:.3f} cm^-1, paper {want:.2f} cm^-1 "
        f"(difference {got - want:+.3f}, tolerance 0.1)")


def test_extinction_extremes_at_band_edges():
    wl = spectra.wavelengths()
    for L in _FOREARM[:5]:
        mua, mus, _ = skin.optics(L, wl)
        ext = mua + mus
        assert np.argmax(ext) == 0 and np.argmin(ext) == len(wl) - 1, L.name


@pytest.mark.parametrize("site", ["forearm", "cheek"])
def test_optics_positive_and_g_in_range(site):
    wl = spectra.wavelengths()
    for L in load_stack(site)[1]:
        mua, mus, g = skin.optics(L, wl)
        assert mua.shape == mus.shape == g.shape == wl.shape
        assert np.all(mua > 0) and np.all(mus > 0), L.name
        assert np.all((g > 0) & (g < 1)), L.name


def test_optics_mixture_and_scattering_models():
    wl = np.array([450.0, 550.0, 650.0])
    L = skin.Layer("mix", 10.0, melanin=0.1, blood=0.05, saturation=0.7, baseline=0.85, k=3.0)
    mua, mus, g = skin.optics(L, wl)
    expect = (0.1 * spectra.mua_melanosome(wl) + 0.05 * spectra.mua_blood(wl, 0.7)
              + 0.85 * spectra.mua_baseline(wl))
    assert np.allclose(mua, expect)
    assert np.allclose(mus, 3.0 * spectra.mus_jacques(wl))
    assert np.allclose(g, spectra.g_jacques(wl))

    P = skin.Layer("fat", math.inf, scattering="powerlaw", a=35.2, b=0.988, g=0.8, blood=0.05)
    mua, mus, g = skin.optics(P, np.array([500.0, 600.0]))
    assert np.allclose(g, 0.8)
    assert np.isclose(mus[0] * (1 - 0.8), 35.2)             # mu_s'(500 nm) = a
    assert np.isclose(mus[1] / mus[0], (600 / 500) ** -0.988)
    assert P.semi_infinite


def test_empty_layer_has_zero_absorption():
    mua, _, _ = skin.optics(skin.Layer("clear", 5.0), spectra.wavelengths())
    assert np.all(mua == 0)


@pytest.mark.parametrize("kwargs", [
    dict(thickness_um=0.0), dict(thickness_um=-1.0), dict(scattering="mie"), dict(bottom="round"),
    dict(blood=1.5), dict(melanin=-0.1), dict(g=1.0),
])
def test_layer_validation(kwargs):
    base = dict(name="x", thickness_um=10.0)
    base.update(kwargs)
    with pytest.raises(ValueError):
        skin.Layer(**base)


def test_paper_table1_constant():
    t = skin.PAPER_TABLE1
    assert set(t) == {"thickness_um", "extinction_max", "extinction_mean", "extinction_min",
                      "a", "b", "c", "d", "e", "f"}
    assert all(list(row) == NINE[:5] for row in t.values())
    assert t["extinction_max"]["basal"] == 1083.29
    assert t["d"]["subpapillary dermis"] == 16.49
    assert t["a"]["granular + spinous"] == 12.10
