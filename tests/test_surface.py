"""The photon and eye passes refract at the smooth surfaces (kernels/surface.h), not at the voxel
staircase's faces (docs/relief.md, section 1).

The scene: a tilted plane z = SLOPE x (a height map), a clear layer of the air's index that
follows it, and below it, across an index step 1.0 -> 1.5, a turbid half-space.  Rotating the
whole scene by the tilt gives a flat slab under a rotated beam: the same physics, so the same
energy split.  The staircase the passes walk (5 um columns, 0.75 um steps) is the only
difference left; its faces' own normals (+z on the column tops, +-x on the walls: the passes
before) made the internal interface a different surface.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from clppm import config
from clppm.integrators import eyepass, photonpass
from clppm.scene import volume

SLOPE = 0.15                    # 8.5 degrees
SIZE_MM = 1.0
N_PHOTONS = 100_000


def tilted_scene(tmp_path, tilted: bool, direction, camera: bool = False) -> dict:
    half = SIZE_MM / 2
    raw = {"model": {"name": "tilt", "size_mm": [SIZE_MM, SIZE_MM], "lateral": "open", "quantize": False,
                     "voxel_um": 5.0, "lateral_voxel_um": 5.0},
           "spectrum": {"start_nm": 500.0, "stop_nm": 500.0, "step_nm": 5.0},
           "relief": {"kind": "flat"},
           "light": {"kind": "pencil", "direction": [float(v) for v in direction], "spectrum": "flat",
                     "center_mm": [half, half]},
           "layer": [{"name": "clear", "thickness_um": 30.0, "n": 1.0, "mua": 0.0, "mus": 0.0, "g": 0.0,
                      "scattering": "none", "bottom": "surface"},
                     {"name": "turbid", "thickness_um": math.inf, "n": 1.5, "mua": 50.0, "mus": 200.0,
                      "g": 0.0, "scattering": "none", "bottom": "flat"}]}
    if tilted:
        n = int(round(SIZE_MM * 1000 / 5.0))               # one height-map pixel per column
        np.save(tmp_path / "plane.npy", np.tile(SLOPE * (np.arange(n) + 0.5) * 5.0, (2, 1)))
        raw["relief"] = {"kind": "file", "file": str(tmp_path / "plane.npy"), "pixel_um": 5.0,
                         "height_scale_um": 1.0}
    if camera:
        raw["camera"] = {"position_mm": [half, half, 40.0], "look_at_mm": [half, half, 0.0],
                         "fov_deg": 0.3, "resolution": [16, 16]}
        raw["render"] = {"method": "a", "threshold": 1e-2}
    return config.validate(raw, "tilted plane")


def frame():
    """The tilted plane's unit normal and its uphill tangent (x-z plane)."""
    c = 1 / math.sqrt(1 + SLOPE * SLOPE)
    return np.array([-SLOPE * c, 0.0, c]), np.array([c, 0.0, SLOPE * c])


def turbid_angles(dev, cfg):
    """The eye pass on a tilted-plane scene with its camera looking straight down: each turbid
    sample point's angle (degrees) from the analytic direction back to the eye of the central
    ray refracted by Snell's law at the plane's normal (1.0 -> 1.5), and that direction."""
    vol = volume.build(cfg)
    ed = eyepass.run(dev, vol, volume.upload_volume(dev, vol), cfg)
    dirs = ed.pt_dir.get()[:ed.npoints]
    turbid = dirs["w"] == 1
    assert turbid.sum() > 200
    to_eye = np.stack([dirs["x"], dirs["y"], dirs["z"]], -1)[turbid].astype(float)
    nrm, _ = frame()
    d = np.array([0.0, 0.0, -1.0])
    ci = -d @ nrm
    eta = 1.0 / 1.5
    t = eta * d + (eta * ci - math.sqrt(1 - eta * eta * (1 - ci * ci))) * nrm
    return np.degrees(np.arccos(np.clip(to_eye @ -t / np.linalg.norm(to_eye, axis=1), -1, 1))), t


def test_tilted_plane_energy_split_is_the_rotated_slabs(dev, tmp_path):
    """A pencil beam at 60 degrees from the tilted plane's normal (uphill) against the flat slab
    under the beam at 60 degrees: diffuse reflectance and the turbid layer's absorption agree
    within 0.015 (measured: -0.005 and +0.002, the staircase positions: grazing rays cross the
    steps where they would not cross the plane); the staircase faces' normals gave +0.056 and
    -0.058 (Fresnel at the column tops' 68.5 degrees instead of 60)."""
    a = math.radians(60.0)
    local = np.array([math.sin(a), 0.0, -math.cos(a)])
    nrm, tan = frame()
    out = {}
    for name, tilted, d in (("slab", False, local), ("tilted", True, local[0] * tan + local[2] * nrm)):
        cfg = tilted_scene(tmp_path, tilted, d)
        vol = volume.build(cfg)
        assert vol.flat != tilted
        out[name] = photonpass.trace_report(photonpass.PhotonPass.of_config(dev, vol, cfg, seed=11), N_PHOTONS, batches=10)
    s, t = out["slab"], out["tilted"]
    assert s["lost"] < 1e-3 and t["lost"] < 5e-3, (s["lost"], t["lost"])     # the beam stays in the model
    for key in ("Rd", "A"):
        se = math.hypot(s[key + "_se"], t[key + "_se"])
        assert abs(t[key] - s[key]) < 0.015 + 3 * se, (key, t[key], s[key], se)
    assert t["absorbed_per_layer"]["clear"] == 0.0            # all of A is the turbid layer's


def test_eye_rays_refract_at_the_tilted_plane(dev, tmp_path):
    """Eye rays straight down (within 0.15 degrees) cross the clear layer unbent (equal indices)
    and refract into the turbid half-space by Snell's law at the plane's normal: every sample
    point in the turbid layer looks back along the analytic direction within 0.3 degrees (at
    the column tops' +z normal the rays would not bend at all: 2.8 degrees off)."""
    ang, t = turbid_angles(dev, tilted_scene(tmp_path, True, (0.0, 0.0, -1.0), camera=True))
    assert np.degrees(np.arccos(-t[2])) > 2.5                # the plane does bend them
    assert ang.max() < 0.3, np.percentile(ang, [50, 99, 100])
