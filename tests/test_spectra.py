"""Spectral building blocks: bands, haemoglobin table, Jacques formulae, D65 and CMFs."""
import numpy as np
import pytest

from clppm.scene import colorimetry, spectra


def test_wavelengths_default_81_bands_inclusive():
    wl = spectra.wavelengths()
    assert wl.shape == (81,)
    assert wl[0] == 380.0 and wl[-1] == 780.0
    assert np.allclose(np.diff(wl), 5.0)
    assert spectra.wavelengths(400, 700, 10).tolist() == list(np.arange(400.0, 701.0, 10.0))


def test_hb_extinction_table_values_and_interpolation():
    e_oxy, e_deoxy = spectra.hb_extinction([250.0, 1000.0])
    assert e_oxy.tolist() == [106112.0, 1024.0]          # first and last rows of Prahl's table
    assert e_deoxy.tolist() == [112736.0, 206.784]
    mid_oxy, mid_deoxy = spectra.hb_extinction(251.0)     # halfway between the 250 and 252 rows
    oxy, deoxy = spectra.hb_extinction([250.0, 252.0])
    assert np.isclose(mid_oxy, oxy.mean()) and np.isclose(mid_deoxy, deoxy.mean())


@pytest.mark.parametrize("bad", [249.0, 1000.5, 1200.0])
def test_hb_extinction_outside_table_names_wavelength(bad):
    with pytest.raises(ValueError, match=f"{bad:g}"):
        spectra.hb_extinction(np.array([500.0, bad]))
    with pytest.raises(ValueError, match=f"{bad:g}"):
        spectra.mua_blood(bad, 0.8)


def test_mua_blood_formula():
    e_oxy, e_deoxy = spectra.hb_extinction(550.0)
    expect = 2.303 * (0.7 * e_oxy + 0.3 * e_deoxy) * 150.0 / 64500.0
    assert np.isclose(spectra.mua_blood(550.0, 0.7), expect)
    # Oxygenated blood absorbs less than deoxygenated in the red (the colour of arterial blood).
    assert spectra.mua_blood(660.0, 1.0) < 0.2 * spectra.mua_blood(660.0, 0.0)


def test_coefficients_positive_over_visible():
    wl = spectra.wavelengths()
    for arr in (spectra.mua_blood(wl, 0.8), spectra.mua_melanosome(wl), spectra.mua_baseline(wl),
                spectra.mus_jacques(wl), spectra.mus_powerlaw(wl, 20.0, 1.0, 0.9)):
        assert arr.shape == wl.shape and np.all(np.isfinite(arr)) and np.all(arr > 0)
    g = spectra.g_jacques(wl)
    assert np.all((g > 0.7) & (g < 0.9))


def test_jacques_formulae_spot_values():
    assert np.isclose(spectra.mua_melanosome(500.0), 6.6e11 * 500.0 ** -3.33)
    assert np.isclose(spectra.mua_baseline(154.0), 0.244 + 85.3)
    assert np.isclose(spectra.g_jacques(500.0), 0.765)
    assert np.isclose(spectra.mus_jacques(500.0) * (1 - 0.765), 2e5 * 500 ** -1.5 + 2e12 * 500.0 ** -4)


def test_powerlaw_reduced_scattering_at_500nm_is_a():
    for a, b, g in [(35.2, 0.988, 0.8), (20.0, 1.5, 0.0), (46.0, 1.421, 0.9)]:
        mus = spectra.mus_powerlaw(500.0, a, b, g)
        assert np.isclose(mus * (1 - g), a)
    assert np.isclose(spectra.mus_powerlaw(1000.0, 10.0, 1.0, 0.0), 5.0)


def test_d65_normalisation():
    wl = spectra.wavelengths()
    s = spectra.d65(wl)
    assert s.shape == (81,)
    assert np.isclose(spectra.d65(560.0), 100.0)               # CIE normalisation
    assert np.isclose(s.max(), 117.812, atol=1e-3)              # peak at 460 nm
    assert wl[np.argmax(s)] == 460.0
    assert 45.0 < s[0] < 55.0 and 60.0 < s[-1] < 70.0           # 380 nm ~50, 780 nm ~63


def test_cmfs_shape_and_values():
    wl = spectra.wavelengths()
    c = colorimetry.cmfs(wl)
    assert c.shape == (81, 3)
    assert np.all(c >= 0)
    assert np.allclose(colorimetry.cmfs([555.0])[0], [0.5120501, 1.0, 0.00575], atol=1e-6)
    # y-bar peaks at 555 nm; on the 5 nm grid 555 is a band centre.
    assert wl[np.argmax(c[:, 1])] == 555.0
    # Integrals of the 2-degree observer over 380-780 nm are nearly equal (equal-energy white).
    sums = c.sum(axis=0) * 5.0
    assert np.allclose(sums, sums[1], rtol=0.01)
