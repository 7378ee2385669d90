"""Spectral building blocks of the skin model (λ in nm, coefficients in cm^-1).

References
----------
* S. Prahl, "Optical absorption of hemoglobin", Oregon Medical Laser Center (compiled from
  W. B. Gratzer and N. Kollias): molar extinction of HbO2/Hb, packaged as
  ``clppm/data/prahl_hb_molar_extinction.tsv`` (base 10, cm^-1/M).
* S. L. Jacques, "Skin optics", Oregon Medical Laser Center News (1998), and
  S. L. Jacques, "Optical properties of biological tissues: a review",
  Phys. Med. Biol. 58 (2013) R37: melanosome and bloodless baseline absorption, the skin
  scattering recipe and the reduced-scattering power law.
* CIE D65 and the CIE 1931 2° observer, taken from colour-science.
"""
from __future__ import annotations

from functools import lru_cache
from importlib import resources

import colour
import numpy as np

#: Whole-blood haemoglobin concentration (g/L) and molar mass of haemoglobin (g/mol).
HB_CONCENTRATION_G_PER_L = 150.0
HB_MOLAR_MASS_G_PER_MOL = 64500.0


def wavelengths(start: float = 380.0, stop: float = 780.0, step: float = 5.0) -> np.ndarray:
    """Band centres from ``start`` to ``stop`` inclusive (81 bands by default)."""
    n = int(round((stop - start) / step)) + 1
    return start + step * np.arange(n, dtype=np.float64)


@lru_cache(maxsize=1)
def _prahl_table() -> np.ndarray:
    """(N, 3) array: λ nm, ε_HbO2, ε_Hb (cm^-1/M), from the packaged Prahl table."""
    text = resources.files("clppm.data").joinpath("prahl_hb_molar_extinction.tsv").read_text()
    rows = [line.split("\t") for line in text.splitlines()[2:] if line.strip()]
    table = np.array(rows, dtype=np.float64)
    table.flags.writeable = False
    return table


def hb_extinction(wl) -> tuple[np.ndarray, np.ndarray]:
    """Molar extinction (ε_HbO2, ε_Hb) in cm^-1/M, linearly interpolated from Prahl's table.

    Raises ValueError naming the first wavelength outside the table's range.
    """
    wl = np.asarray(wl, dtype=np.float64)
    t = _prahl_table()
    lo, hi = t[0, 0], t[-1, 0]
    bad = wl[(wl < lo) | (wl > hi) | ~np.isfinite(wl)]
    if bad.size:
        raise ValueError(f"wavelength {bad.flat[0]:g} nm is outside the Prahl haemoglobin "
                         f"table ({lo:g}-{hi:g} nm)")
    return np.interp(wl, t[:, 0], t[:, 1]), np.interp(wl, t[:, 0], t[:, 2])


def mua_blood(wl, saturation: float) -> np.ndarray:
    """Absorption of whole blood (150 g/L Hb) at oxygen saturation S, cm^-1."""
    e_oxy, e_deoxy = hb_extinction(wl)
    eps = saturation * e_oxy + (1.0 - saturation) * e_deoxy
    return 2.303 * eps * HB_CONCENTRATION_G_PER_L / HB_MOLAR_MASS_G_PER_MOL


def mua_melanosome(wl) -> np.ndarray:
    """Absorption inside a melanosome, 6.6e11 λ^-3.33 cm^-1 (Jacques 1998)."""
    return 6.6e11 * np.asarray(wl, dtype=np.float64) ** -3.33


def mua_baseline(wl) -> np.ndarray:
    """Bloodless skin baseline absorption, 0.244 + 85.3 exp(-(λ-154)/66.2) cm^-1 (Jacques 1998)."""
    wl = np.asarray(wl, dtype=np.float64)
    return 0.244 + 85.3 * np.exp(-(wl - 154.0) / 66.2)


def g_jacques(wl) -> np.ndarray:
    """Anisotropy of dermis, g = 0.62 + 0.29e-3 λ (Jacques 1998)."""
    return 0.62 + 0.29e-3 * np.asarray(wl, dtype=np.float64)


def mus_jacques(wl) -> np.ndarray:
    """Base scattering coefficient μs = (2e5 λ^-1.5 + 2e12 λ^-4) / (1 - g) cm^-1 (Jacques 1998).

    The numerator is the reduced scattering μs' of dermis (Mie + Rayleigh parts).
    """
    wl = np.asarray(wl, dtype=np.float64)
    return (2e5 * wl ** -1.5 + 2e12 * wl ** -4) / (1.0 - g_jacques(wl))


def mus_powerlaw(wl, a: float, b: float, g) -> np.ndarray:
    """μs = a (λ/500 nm)^-b / (1 - g); ``a`` is μs' at 500 nm in cm^-1 (Jacques 2013, eq. 2)."""
    wl = np.asarray(wl, dtype=np.float64)
    return a * (wl / 500.0) ** -b / (1.0 - np.asarray(g, dtype=np.float64))


def d65(wl) -> np.ndarray:
    """Relative spectral power of CIE D65 (100 at 560 nm) at ``wl``, via colour's interpolator."""
    sd = colour.SDS_ILLUMINANTS["D65"]
    return np.asarray(sd[np.asarray(wl, dtype=np.float64)], dtype=np.float64)
