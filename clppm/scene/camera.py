"""Pinhole camera: position, look-at, up, vertical field of view, resolution (mm in, um out)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..compute.structs import CAMERA_DTYPE



@dataclass(frozen=True)
class Camera:
    position: np.ndarray      # um
    forward: np.ndarray
    right: np.ndarray
    up: np.ndarray
    tan_half: float           # tan(vertical fov / 2)
    width: int
    height: int
    spp: int = 1

    @property
    def aspect(self) -> float:
        return self.width / self.height

    def ray(self, px: float, py: float) -> np.ndarray:
        """Direction through image point (px, py) in pixels (0,0 = top-left corner)."""
        sx = (2.0 * px / self.width - 1.0) * self.tan_half * self.aspect
        sy = (1.0 - 2.0 * py / self.height) * self.tan_half
        d = self.forward + sx * self.right + sy * self.up
        return d / np.linalg.norm(d)

    def struct(self) -> np.ndarray:
        """The kernels' ``Camera`` (one CAMERA_DTYPE record)."""
        c = np.zeros((), CAMERA_DTYPE)
        c["cpx"], c["cpy"], c["cpz"] = self.position
        c["fx"], c["fy"], c["fz"] = self.forward
        c["rx"], c["ry"], c["rz"] = self.right
        c["ux"], c["uy"], c["uz"] = self.up
        c["tan_half"], c["aspect"] = self.tan_half, self.aspect
        c["width"], c["height"] = self.width, self.height
        return c


def from_config(cam: dict) -> Camera:
    pos = np.asarray(cam["position_mm"], float) * 1000.0
    look = np.asarray(cam["look_at_mm"], float) * 1000.0
    f = look - pos
    f /= np.linalg.norm(f)
    up0 = np.asarray(cam["up"], float)
    up0 /= np.linalg.norm(up0)
    r = np.cross(f, up0)
    if np.linalg.norm(r) < 1e-9:                 # looking along 'up': pick another
        r = np.cross(f, [1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    w, h = cam["resolution"]
    return Camera(position=pos, forward=f, right=r, up=u,
                  tan_half=math.tan(math.radians(cam["fov_deg"]) / 2.0),
                  width=int(w), height=int(h), spp=int(cam["spp"]))
