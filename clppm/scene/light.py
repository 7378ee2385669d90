"""The light as the passes see it: a typed view of the config's ``[light]`` table, in the
volume's units (um), built once per render.

Kinds (``SOURCE``, the kernels' encoding in Params.src_kind and EyeParams.light_kind): a point
light at ``position``; a collimated pencil beam at ``center``; a wide collimated beam of full
width ``width`` around ``center``.  ``direction`` is the beams' unit direction of travel.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .bands import band_width
from ..compute.constants import SOURCE  # noqa: F401  (the kernels' light kinds: SRC_* of constants.h)


@dataclass(frozen=True)
class Light:
    kind: str                        # "point", "pencil" or "wide"
    position: np.ndarray             # um (point)
    direction: np.ndarray            # unit vector of travel (beams)
    center: np.ndarray               # um, on the surface (beams)
    width_mm: np.ndarray             # full width (wide), as configured
    power_w: float                   # over all bands

    @property
    def code(self) -> int:
        return SOURCE[self.kind]

    @property
    def width(self) -> np.ndarray:
        """Full width of the wide beam, um."""
        return self.width_mm * 1000.0

    @property
    def width_m(self) -> np.ndarray:
        return self.width_mm * 1e-3

    @classmethod
    def from_config(cls, cfg: dict) -> "Light":
        L = cfg["light"]
        d = np.asarray(L["direction"], float)
        return cls(kind=L["kind"], position=np.asarray(L["position_mm"], float) * 1000.0,
                   direction=d / np.linalg.norm(d), center=np.asarray(L["center_mm"], float) * 1000.0,
                   width_mm=np.asarray(L["width_mm"], float), power_w=L["power_w"])

    def irradiance_factor(self, band_power: np.ndarray) -> np.ndarray:
        """Per band: what one unit of the kernels' unnormalised light transport is worth, in
        W m^-2 (point: intensity / 4 pi per um^2 -> per m^2; wide: power over the beam's
        footprint across its direction; pencil: 0, it has no area)."""
        if self.kind == "point":
            return band_power / (4 * math.pi) * 1e12
        if self.kind == "wide":
            w = self.width_m
            cosb = max(-self.direction[2], 1e-6)
            return band_power / (w[0] * w[1] * cosb)
        return band_power * 0.0


def white_reference(light: Light, cam, wl, spectrum) -> np.ndarray:
    """Spectral radiance of a white Lambertian plane z=0 at the image centre (W m^-2 sr^-1 nm^-1)."""
    d = cam.ray(cam.width / 2, cam.height / 2)
    t = -cam.position[2] / d[2] if d[2] != 0 else 0.0
    x = cam.position + t * d
    Pb = light.power_w * spectrum / band_width(wl)
    if light.kind == "point":
        lp = light.position - x
        d2 = float(lp @ lp)
        if d2 <= 0:
            return Pb * 0.0
        cos = max(lp[2] / math.sqrt(d2), 0.0)
        E = Pb / (4 * math.pi) * cos / d2 * 1e12
    elif light.kind == "wide":
        w = light.width_m
        E = Pb / (w[0] * w[1])
    else:
        E = Pb * 0.0
    return E / math.pi
