"""The scene a render renders (:class:`Scene`, built once from its request), and whether it can
give a meaningful image, decided on the host before any work.

A config can be valid key by key and still describe nothing worth rendering: a camera under
the skin (every ray "hits", from below), a light of zero power or under the skin (a black or
blown-out image), a field of view in which the model covers no pixel (a black image).  Those are
refused here in one line naming the key and value.  What is only doubtful becomes a note: one
line printed before work and kept in the run report's ``assumed``.

The skin's surface plateau is z = 0 (relief only cuts furrows below it); the model covers
x, y in [0, size_mm] unless its sides are periodic or infinite.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import from_config as camera_from_config
from ..config import ConfigError, render_settings, wavelengths

@dataclass(frozen=True, eq=False)
class Scene:
    """What one render renders, built once from its request (:meth:`of`) and handed to every
    pass: the request's config with the run's values at their keys (``config``, what the run
    report records), its render settings, camera and light, and the voxel model.  No pass reads
    a value from a config below the request."""

    config: dict
    source: str
    settings: object                 # config.RenderSettings
    camera: object                   # camera.Camera
    light: object                    # light.Light
    volume: object                   # volume.Volume

    @classmethod
    def of(cls, req, volume=None) -> "Scene":
        """The scene of a :class:`clppm.request.RenderRequest` (``volume``: one already built of
        its model, else built now, :func:`clppm.scene.volume.build`)."""
        from . import volume as V
        from .light import Light
        cfg = req.resolved()
        vol = volume if volume is not None else V.build(cfg, req.source)
        return cls(config=cfg, source=req.source, settings=req.settings, camera=req.camera,
                   light=Light.from_config(cfg), volume=vol)

    @classmethod
    def of_config(cls, cfg: dict, volume=None, source: str = "<config>", **run) -> "Scene":
        """The scene of a config rendered with its own values (``run``: RenderRequest's run
        values, e.g. ``seed``): the tools' and tests' way in."""
        from ..request import RenderRequest
        return cls.of(RenderRequest(cfg, source=source, **run), volume)

    @property
    def seed(self) -> int:
        return int(self.settings.seed)

    def bands(self, hero: int | None = None, sampling: str | None = None):
        """The spectral sampling (:meth:`clppm.scene.bands.Bands.from_config` of this config)."""
        from .bands import Bands
        return Bands.from_config(self.config, hero=hero, sampling=sampling)


#: eye rays tried per image axis at most (pixel centres, evenly subsampled)
_PROBE = 64


def _bounded(cfg: dict) -> bool:
    return cfg["model"]["lateral"] == "open"


def _on_model(cfg: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Which surface points (mm) lie on the model."""
    if not _bounded(cfg):
        return np.ones(np.shape(x), bool)
    w, h = cfg["model"]["size_mm"]
    return (x >= 0) & (x <= w) & (y >= 0) & (y <= h)


def eye_rays_on_skin(cfg: dict) -> tuple[int, int]:
    """(rays that reach the model's surface plane on the model, rays tried): pixel centres,
    at most :data:`_PROBE` per axis."""
    cam = camera_from_config(cfg["camera"])
    xs = np.linspace(0.5, cam.width - 0.5, min(cam.width, _PROBE))
    ys = np.linspace(0.5, cam.height - 0.5, min(cam.height, _PROBE))
    px, py = np.meshgrid(xs, ys)
    sx = (2.0 * px / cam.width - 1.0) * cam.tan_half * cam.aspect
    sy = (1.0 - 2.0 * py / cam.height) * cam.tan_half
    d = cam.forward[None, None, :] + sx[..., None] * cam.right + sy[..., None] * cam.up
    down = d[..., 2] < 0
    t = np.where(down, -cam.position[2] / np.where(down, d[..., 2], -1.0), 0.0)
    hit = cam.position[None, None, :2] + t[..., None] * d[..., :2]
    on = down & _on_model(cfg, hit[..., 0] / 1000.0, hit[..., 1] / 1000.0)
    return int(on.sum()), int(on.size)


def problems(cfg: dict, source: str = "<config>") -> list[ConfigError]:
    """Why this scene cannot give a meaningful image (each a one-line ConfigError: key, value,
    why); empty when it can."""
    cam, L = cfg["camera"], cfg["light"]
    out = []
    if cam["position_mm"][2] <= 0:
        out.append(ConfigError(source, "camera.position_mm", cam["position_mm"],
                               "the camera is at or under the skin surface (z = 0 mm); it must be above "
                               "it (z > 0), or it sees the skin from inside"))
    if L["power_w"] <= 0:
        out.append(ConfigError(source, "light.power_w", L["power_w"],
                               "the light emits nothing and the image would be black; give a power > 0"))
    if L["kind"] == "point" and L["position_mm"][2] <= 0:
        out.append(ConfigError(source, "light.position_mm", L["position_mm"],
                               "the point light is at or under the skin surface (z = 0 mm); it must be "
                               "above it (z > 0)"))
    if L["kind"] != "point" and _bounded(cfg) and _beam_misses(cfg):
        w, h = cfg["model"]["size_mm"]
        out.append(ConfigError(source, "light.center_mm", L["center_mm"],
                               f"the {L['kind']} beam misses the model (x, y in [0, {w:g}] x [0, {h:g}] mm): "
                               "it lights nothing"))
    hit, tried = eye_rays_on_skin(cfg)
    if hit == 0:
        out.append(ConfigError(source, "camera.fov_deg", cam["fov_deg"],
                               f"no eye ray of the {tried} tried reaches the skin model from camera.position_mm "
                               f"= {cam['position_mm']} looking at {cam['look_at_mm']}: the image would be black"))
    return out


def refuse_maps(cfg: dict, source: str = "<config>", integrator: str = "ppm") -> None:
    """Refuse to render a scene with ``[[map]]`` tables where the render would not see them, and
    such an image would be wrong, not merely noisy.  The photon pass (clppm trace, clppm
    reflectance) traces maps on every model.  The path tracer renders them on flat layers and
    through the relief (its walk by delta tracking, each leg of its light connections by ratio
    tracking, no map inside an inclusion), with or without inclusions.  PPM renders them on flat
    layers and on the relief, with or without inclusions, with the beam estimator (its eye pieces end at the maps' column walls and
    its gathers take each piece's column's extinction, found at the piece's midpoint,
    kernels/maps.h) and one band per photon path.  Refused: PPM's sphere estimators (their pieces
    have no geometry to find a column by) and more than one band per path; periodic sides (both)."""
    maps = cfg.get("map") or []
    if not maps:
        return
    if cfg["model"]["lateral"] == "periodic":
        raise ConfigError(source, "model.lateral", "periodic",
                          "renders across periodic sides do not see chromophore maps yet (not validated); give "
                          "model.lateral = 'open' or 'infinite', or remove the [[map]] tables")
    if integrator != "pt":
        rs = cfg["render"]
        if rs["estimator"] != "beam":
            raise ConfigError(source, "render.estimator", rs["estimator"],
                              "PPM sees chromophore maps with the beam estimator only (the sphere estimators' "
                              "eye pieces have no geometry to find a map column by); give render.estimator = "
                              "'beam' (not --paper), render with --integrator pt, or remove the [[map]] tables")
        if int(rs["bands_per_path"]) > 1:
            raise ConfigError(source, "render.bands_per_path", rs["bands_per_path"],
                              "chromophore maps are traced with one band per photon path; give "
                              "render.bands_per_path = 1 or 0 (auto), or remove the [[map]] tables")


def refuse_inclusions(cfg: dict, source: str = "<config>", integrator: str = "ppm") -> None:
    """Refuse to render a scene with ``[[inclusion]]`` tables where the render would not see
    them: the photon pass sees them everywhere; PPM's eye pass and gathers on flat layers and on
    the relief (its eye pieces end at an inclusion's wall and record their material for the
    extinction and the mu_s ratio beside their layer for the layer-conforming depth: kernels/eye.cl,
    beam.h); the path tracer (its walk and every leg of its light connections) on flat layers
    and through the relief.  Refused: the path tracer's connections across periodic sides, where
    such an image would be wrong, not merely noisy."""
    refuse_maps(cfg, source, integrator)
    inc = cfg.get("inclusion") or []
    if not inc:
        return
    if integrator == "pt" and cfg["model"]["lateral"] == "periodic":
        raise ConfigError(source, "model.lateral", "periodic",
                          "the path tracer's connections across periodic sides do not see inclusions "
                          "yet; give model.lateral = 'open' or 'infinite', render with PPM, or remove "
                          "the [[inclusion]] tables")


def refuse(cfg: dict, source: str = "<config>") -> None:
    """Raise the first of :func:`problems` (the command line refuses such a scene)."""
    found = problems(cfg, source)
    if found:
        raise found[0]


def _beam_misses(cfg: dict) -> bool:
    L = cfg["light"]
    w, h = cfg["model"]["size_mm"]
    cx, cy = L["center_mm"]
    hx, hy = (L["width_mm"][0] / 2, L["width_mm"][1] / 2) if L["kind"] == "wide" else (0.0, 0.0)
    return cx + hx < 0 or cx - hx > w or cy + hy < 0 or cy - hy > h


def notes(cfg: dict) -> list[str]:
    """What clppm assumes about this scene (one line each; the report's ``assumed``): the
    problems the library renders anyway (the command line refuses them), then the doubts."""
    out = [f"{e.key} = {e.value}: {e.why}" for e in problems(cfg)]
    hit, tried = eye_rays_on_skin(cfg)
    if 0 < hit < 0.01 * tried:
        out.append(f"only {hit} of {tried} eye rays tried reach the skin model: the image is mostly black")
    if render_settings(cfg).exposure is None and white_reference_y(cfg) <= 0:
        out.append("render.exposure is unset and a white diffuser at the image centre gets no light "
                   "from this light: the PNG takes exposure 1.0 (set render.exposure)")
    return out


def white_reference_y(cfg: dict) -> float:
    """Y of the white reference that sets the PNG's exposure (:func:`.light.white_reference`)."""
    from .bands import source_spectrum, tristimulus
    from .light import Light, white_reference
    wl = wavelengths(cfg)
    spectrum = source_spectrum(cfg, wl)
    cam = camera_from_config(cfg["camera"])
    L = white_reference(Light.from_config(cfg), cam, wl, spectrum)
    return float(tristimulus(L[None, :], wl)[0, 1])


def warn_scene(cfg: dict, source: str = "<config>") -> list[str]:
    """Before a render's work (the library's entry points): each note on stderr, one line.  The
    library renders what the command line refuses (tests and scripts explore such scenes)."""
    import sys
    found = notes(cfg)
    for n in found:
        print(f"clppm: warning: {source}: {n}", file=sys.stderr)
    return found
