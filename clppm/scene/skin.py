"""Layers of the skin model and their spectral optical properties.

A layer's absorption mixes melanosomes, whole blood and the bloodless baseline by volume
fraction; its scattering is either k × the Jacques skin recipe or a reduced-scattering power
law (S. L. Jacques, "Skin optics", OMLC News 1998; S. L. Jacques, Phys. Med. Biol. 58 (2013)
R37). With the paper's composition this reproduces the extinction rows of Table 1 of
Kamatani & Kawai, "Sampling Schemes for Progressive Photon Mapping Visualizing Volumetric
Human Skin Model".
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import spectra

SCATTERING_MODELS = ("jacques", "powerlaw")
BOTTOM_SHAPES = ("flat", "surface", "papillae")


@dataclass(frozen=True)
class Layer:
    name: str
    thickness_um: float          # math.inf allowed for a semi-infinite bottom layer only
    n: float = 1.4               # refractive index
    melanin: float = 0.0         # volume fraction of melanosomes
    blood: float = 0.0           # volume fraction of whole blood
    saturation: float = 0.8      # blood oxygen saturation
    baseline: float = 0.0        # volume fraction absorbing like the bloodless baseline mua_baseline
    scattering: str = "jacques"  # "jacques" (k * mus_jacques) or "powerlaw"
    k: float = 1.0               # Jacques scale factor
    a: float = 0.0               # powerlaw: reduced scattering at 500 nm, cm^-1
    b: float = 0.0               # powerlaw exponent
    g: float | None = None       # None -> g_jacques(λ); a number -> constant anisotropy
    bottom: str = "flat"         # shape of the interface below this layer: "flat" | "surface" | "papillae"

    def __post_init__(self):
        if not (self.thickness_um > 0):
            raise ValueError(f"layer {self.name!r}: thickness_um must be > 0, got {self.thickness_um}")
        if self.scattering not in SCATTERING_MODELS:
            raise ValueError(f"layer {self.name!r}: scattering must be one of {SCATTERING_MODELS}")
        if self.bottom not in BOTTOM_SHAPES:
            raise ValueError(f"layer {self.name!r}: bottom must be one of {BOTTOM_SHAPES}")
        for f in ("melanin", "blood", "saturation", "baseline"):
            v = getattr(self, f)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"layer {self.name!r}: {f} must lie in [0, 1], got {v}")
        if self.g is not None and not -1.0 < self.g < 1.0:
            raise ValueError(f"layer {self.name!r}: g must lie in (-1, 1), got {self.g}")

    @property
    def semi_infinite(self) -> bool:
        return math.isinf(self.thickness_um)


def optics(layer: Layer, wl) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(μa, μs, g) of ``layer`` at wavelengths ``wl`` (nm); μa and μs in cm^-1."""
    wl = np.asarray(wl, dtype=np.float64)
    mua = np.zeros_like(wl)
    if layer.melanin:
        mua = mua + layer.melanin * spectra.mua_melanosome(wl)
    if layer.blood:
        mua = mua + layer.blood * spectra.mua_blood(wl, layer.saturation)
    if layer.baseline:
        mua = mua + layer.baseline * spectra.mua_baseline(wl)
    g = spectra.g_jacques(wl) if layer.g is None else np.full_like(wl, float(layer.g))
    if layer.scattering == "jacques":  # μs = k·mus_jacques whatever g the layer uses
        mus = layer.k * spectra.mus_jacques(wl)
    else:
        mus = spectra.mus_powerlaw(wl, layer.a, layer.b, g)
    return mua, mus, g


def extinction_stats(layer: Layer, wl) -> dict[str, float]:
    """Max, plain mean and min over the bands of the extinction μa + μs (cm^-1)."""
    mua, mus, _ = optics(layer, wl)
    ext = mua + mus
    return {"max": float(ext.max()), "mean": float(ext.mean()), "min": float(ext.min())}


#: Table 1 of the paper: thickness (µm), extinction (cm^-1) max/mean/min over 380-780 nm, and
#: mean sample points per eye ray for methods a-f. Keyed by row ("thickness_um",
#: "extinction_max", ...; methods by letter "a".."f"), then by layer name.
_T1_LAYERS = ("stratum corneum", "granular + spinous", "basal", "papillary dermis",
              "subpapillary dermis")
_T1_ROWS = {
    "thickness_um": (15, 60, 15, 45, 175),
    "extinction_max": (458.63, 475.54, 1083.29, 1834.78, 1834.78),
    "extinction_mean": (188.33, 193.98, 432.45, 756.83, 756.83),
    "extinction_min": (95.08, 96.62, 205.32, 379.39, 379.39),
    "a": (3.11, 12.10, 3.08, 8.72, 22.71),    # equal spacing 4 µm
    "b": (1.97, 7.82, 2.07, 5.82, 12.08),     # equal spacing 7 µm
    "c": (0.98, 3.62, 1.02, 2.96, 6.62),      # equal spacing 14 µm
    "d": (1.18, 2.78, 1.59, 6.43, 16.49),     # extinction-based, max over λ
    "e": (1.04, 1.46, 1.15, 3.01, 7.05),      # extinction-based, mean over λ
    "f": (1.02, 1.15, 1.05, 1.73, 3.98),      # extinction-based, min over λ
}
PAPER_TABLE1: dict[str, dict[str, float]] = {
    row: dict(zip(_T1_LAYERS, map(float, vals))) for row, vals in _T1_ROWS.items()
}
#: Paper render times in seconds per method (not part of Table 1, quoted in the text).
PAPER_RENDER_TIME_S = {"a": 13238.0, "b": 8020.0, "c": 3947.0, "d": 8158.0, "e": 4036.0, "f": 2864.0}
