"""The spectral sampling of a render, built once from the config: the host's counterpart of
``kernels/spectral.h`` (pbrt-v4's ``SampledWavelengths``).

A render samples ``nb`` bands of width ``dl`` nm.  The light's relative spectral power per band
is ``spectrum`` (sums to 1).  A photon path carries ``hero`` bands (hero wavelength sampling:
the hero drawn with probability ``pdf``, the others at fixed offsets), or exactly one band when
the light is monochromatic (``fixed`` >= 0).  Every pass, the film and the path tracer read
these fields from one :class:`Bands` instead of recomputing them from the config.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import bands_per_path, render_settings, wavelengths


def source_spectrum(cfg: dict, wl: np.ndarray) -> np.ndarray:
    """Relative spectral power of the light per band (sums to 1)."""
    if cfg["light"]["spectrum"] == "D65":
        from .spectra import d65
        s = np.asarray(d65(wl), float)
    else:
        s = np.ones(len(wl))
    return s / s.sum()


def hero_pdf(wl: np.ndarray, spectrum: np.ndarray, how: str) -> np.ndarray:
    """The hero band's selection probability per band (sums to 1).

    "power": the light's spectrum (the paper: a photon's band is drawn from D65).  "visual":
    the light's power times the sum of the CIE 1931 colour matching functions, plus a floor of
    10 % of that product's mean so that no band goes unsampled: bands the eye barely sees
    (380-400 and 700-780 nm) then get fewer paths, each weighted s/pi (spectral.h)."""
    s = np.asarray(spectrum, float)
    if how == "power" or len(wl) == 1:
        return s / s.sum()
    from .colorimetry import cmfs
    v = s * cmfs(wl).sum(axis=1)
    v = v + 0.1 * v.mean()
    return v / v.sum()


def fixed_band(cfg: dict, wl: np.ndarray) -> int:
    """The one band of a monochromatic light (``light.band_nm``; a one-band spectrum), else -1."""
    b = cfg["light"]["band_nm"]
    if b is None:
        return 0 if len(wl) == 1 else -1
    return int(np.argmin(np.abs(wl - b)))


def band_width(wl: np.ndarray) -> float:
    """Width of a band in nm (1 for a single band: radiance per band is then per nm)."""
    return float(wl[1] - wl[0]) if len(wl) > 1 else 1.0


def tristimulus(L: np.ndarray, wl) -> np.ndarray:
    """XYZ of spectral radiance ``L`` (..., NB): the rectangle rule over the bands."""
    from .colorimetry import cmfs, spectral_to_xyz
    if len(wl) > 1:
        return spectral_to_xyz(L, wl)
    return L * cmfs(wl)[0] * band_width(wl)


@dataclass(frozen=True)
class Bands:
    """The wavelengths a render samples and how a path picks them."""

    wl: np.ndarray                   # (nb,) band centres, nm
    spectrum: np.ndarray             # (nb,) the light's relative power per band, sums to 1
    pdf: np.ndarray                  # (nb,) the hero band's selection probability
    hero: int                        # bands carried per photon path
    fixed: int                       # the one band of a monochromatic light, else -1

    @property
    def nb(self) -> int:
        return len(self.wl)

    @property
    def dl(self) -> float:
        return band_width(self.wl)

    @classmethod
    def from_config(cls, cfg: dict, hero: int | None = None, sampling: str | None = None) -> "Bands":
        """``hero``: bands per path (default: ``render.bands_per_path`` resolved; a fixed band
        carries one); ``sampling``: the hero's pdf (default: ``render.band_sampling``)."""
        wl = np.asarray(wavelengths(cfg), float)
        spectrum = source_spectrum(cfg, wl)
        fixed = fixed_band(cfg, wl)
        h = bands_per_path(cfg) if hero is None else int(hero)
        return cls(wl=wl, spectrum=spectrum, pdf=hero_pdf(wl, spectrum, sampling or render_settings(cfg).band_sampling),
                   hero=h if fixed < 0 else 1, fixed=fixed)
