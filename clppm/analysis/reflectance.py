"""Spectral reflectance R(λ) as an integrating-sphere spectrophotometer measures it.

Photon-pass reflectance (:func:`spectral_reflectance`).  A collimated beam falls on the model
at ``angle_deg`` from the normal (8° as in 8°/hemispherical spectrophotometers, or 0°), and
the photon pass counts what leaves the top surface: every band is traced with the band fixed
(the same photon ids, so the same random numbers, in every band and every call with the same
seed), with exact integer tallies and a standard error from batch means.  With the specular
component included (SCI, the default) R = first-surface Fresnel reflection + diffuse
reflectance Rd; excluded (SCE) R = Rd.  Geometry:

* flat model (no relief, no papillae): ``model.lateral = "infinite"`` and a pencil beam -- an
  infinitely wide sample under an infinitely large sphere port, which for a laterally
  uniform slab stack is the same as any beam size;
* a model with relief or papillae: ``model.lateral = "periodic"`` and a wide beam over the
  whole model (or a centred square spot of ``spot_mm``), so no light leaves at the sides and
  every part of the relief is lit equally;
* ``port_mm`` (flat models): a square sample port of that side; the model is cut to the port
  and made laterally open, so light crossing the side of the tissue under the port is lost.
  This bounds the reflectance a finite port collects from below (some of that light would
  come back up inside the port);
* SCE with relief: the first-surface reflection is removed whole (a sphere's specular trap
  only removes the mirror direction, so this over-removes a little on rough surfaces).

Reflectance from rendered images (:func:`method_reflectance`): render with each sampling
scheme a-f under the configured light and camera, divide the spectral radiance of an image
region by the radiance of a white Lambertian plane under the same light
(:func:`clppm.scene.light.white_reference`, evaluated per pixel), per band, and set it next to
the photon-pass value at the same angle of incidence.
"""
from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from .. import config as C
from ..config import ConfigError

DEFAULT_ANGLE = 8.0


# ----------------------------------------------------------------------------- geometry
def beam_direction(angle_deg: float) -> list[float]:
    t = math.radians(angle_deg)
    return [math.sin(t), 0.0, -math.cos(t)]


def measurement_config(cfg: dict, angle_deg: float = DEFAULT_ANGLE, direction=None,
                       spot_mm: float | None = None, port_mm: float | None = None,
                       bands: tuple[float, float, float] | None = None, flat: bool = False,
                       seed: int | None = None, source: str = "<config>") -> dict:
    """The config the photon pass traces for R(λ): light, sides and bands set as described
    in the module docstring.  ``direction`` (a downward vector) overrides ``angle_deg``;
    ``bands`` = (start, stop, step) nm overrides the spectrum grid."""
    if direction is None:
        if not (0.0 <= float(angle_deg) <= 85.0):
            raise ConfigError(source, "--angle", angle_deg, "must be in 0..85 degrees")
        direction = beam_direction(float(angle_deg))
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    if d[2] >= -1e-6:
        raise ConfigError(source, "direction", list(direction), "the beam must point down")
    raw = copy.deepcopy(cfg)
    if flat:
        raw["relief"]["kind"] = "flat"
        raw["papillae"]["amplitude_um"] = 0.0
    varying = not C.is_flat(raw)
    size = list(map(float, raw["model"]["size_mm"]))
    L = raw["light"]
    L.update(spectrum="flat", band_nm=None, power_w=1.0, direction=[float(x) for x in d])
    if spot_mm is not None and not spot_mm > 0:
        raise ConfigError(source, "--spot-mm", spot_mm, "must be > 0")
    if port_mm is not None:
        if not port_mm > 0:
            raise ConfigError(source, "--port-mm", port_mm, "must be > 0")
        if varying:
            raise ConfigError(source, "--port-mm", port_mm,
                              "a port needs a flat model (relief and papillae off; add --flat)")
        if spot_mm is not None and spot_mm > port_mm:
            raise ConfigError(source, "--spot-mm", spot_mm, f"must not exceed the port ({port_mm:g} mm)")
        raw["model"]["size_mm"] = [float(port_mm), float(port_mm)]
        raw["model"]["lateral"] = "open"
        c = [port_mm / 2.0, port_mm / 2.0]
        if spot_mm is None:
            L.update(kind="pencil", center_mm=c)
        else:
            L.update(kind="wide", center_mm=c, width_mm=[float(spot_mm)] * 2)
    elif varying:
        raw["model"]["lateral"] = "periodic"
        w = [float(spot_mm)] * 2 if spot_mm is not None else size
        L.update(kind="wide", center_mm=[size[0] / 2.0, size[1] / 2.0], width_mm=w)
    else:
        raw["model"]["lateral"] = "infinite"
        L.update(kind="pencil", center_mm=[size[0] / 2.0, size[1] / 2.0])
    if bands is not None:
        _set_bands(raw, bands)
    if seed is not None:
        raw["render"]["seed"] = int(seed)
    return C.validate(raw, source)


def geometry_note(mcfg: dict, angle_deg: float, specular: bool) -> str:
    m, L = mcfg["model"], mcfg["light"]
    if m["lateral"] == "periodic":
        beam = (f"wide beam {L['width_mm'][0]:g} x {L['width_mm'][1]:g} mm over a periodic "
                f"{m['size_mm'][0]:g} x {m['size_mm'][1]:g} mm model (relief/papillae kept; no side loss)")
    elif m["lateral"] == "open":
        beam = (f"{'pencil beam' if L['kind'] == 'pencil' else 'spot %g mm' % L['width_mm'][0]} "
                f"at the centre of a {m['size_mm'][0]:g} mm square port (light leaving the tissue "
                f"below the port sideways is lost: a lower bound)")
    else:
        beam = "pencil beam on a laterally infinite flat model"
    return (f"collimated {angle_deg:.3g}° incidence, {beam}, specular "
            f"{'included (SCI)' if specular else 'excluded (SCE)'}")


# ----------------------------------------------------------------------------- photon pass
@dataclass
class Reflectance:
    """R(λ) from the photon pass; fractions of the incident power per band."""

    wl: np.ndarray
    R: np.ndarray               # the measured quantity: specular + Rd (SCI) or Rd (SCE)
    se: np.ndarray              # standard error of R (batch means)
    Rd: np.ndarray
    Rd_se: np.ndarray
    specular: np.ndarray
    Tt: np.ndarray
    A: np.ndarray
    lost: np.ndarray
    photons: int                # per band
    specular_included: bool
    angle_deg: float
    geometry: str
    seed: int
    seconds: float = 0.0
    balance_error: float = 0.0
    device: str = ""
    extra: dict = field(default_factory=dict)

    def at(self, nm: float) -> float:
        return float(np.interp(nm, self.wl, self.R))

    def to_dict(self) -> dict:
        return {
            "quantity": ("total reflectance incl. specular (SCI)" if self.specular_included
                         else "diffuse reflectance excl. specular (SCE)"),
            "geometry": self.geometry, "angle_deg": self.angle_deg,
            "photons_per_band": self.photons, "seed": self.seed, "device": self.device,
            "seconds": self.seconds, "energy_balance_error": self.balance_error,
            "wavelength_nm": self.wl.tolist(), "R": self.R.tolist(), "R_se": self.se.tolist(),
            "Rd": self.Rd.tolist(), "Rd_se": self.Rd_se.tolist(),
            "specular": self.specular.tolist(), "Tt": self.Tt.tolist(), "A": self.A.tolist(),
            "lost": self.lost.tolist(), **self.extra,
        }


def trace_bands(dev, vol, mcfg: dict, photons: int, batches: int = 10,
                specular: bool = True) -> dict:
    """Trace ``photons`` per band with the band fixed; fractions and batch standard errors."""
    from ..integrators import photonpass
    if photons < 2:
        raise ConfigError("command line", "--photons", photons, "must be >= 2")
    batches = max(2, min(int(batches), int(photons)))
    pp = photonpass.PhotonPass.of_config(dev, vol, mcfg)
    nb, nl = vol.nb, vol.nmat                        # absorbed in the layers and the inclusions
    cats = list(photonpass.CATEGORIES)
    ix = {c: cats.index(c) for c in ("specular", "diffuse", "transmitted", "lost", "rr_gain",
                                      "rr_loss", "missed")}
    na = len(cats)                                  # first per-layer absorption column
    sinks = [ix[c] for c in ("specular", "diffuse", "transmitted", "lost", "rr_loss", "missed")]
    sizes = np.array([photons // batches + (1 if i < photons % batches else 0) for i in range(batches)],
                     float)
    out = {k: np.zeros(nb) for k in ("R", "se", "Rd", "Rd_se", "specular", "Tt", "A", "lost", "missed")}
    bal = 0.0
    W0 = photonpass.W0
    n = float(photons) * W0
    for b in range(nb):
        pp.p["fixed_band"] = b
        pp.band = b
        arrs = pp.trace(int(photons), batches=batches)
        rows = np.array([a[b] for a in arrs], dtype=np.float64)           # (batches, nc)
        tot = [sum(int(a[b][c]) for a in arrs) for c in range(rows.shape[1])]
        spec, rd = tot[ix["specular"]] / n, tot[ix["diffuse"]] / n
        out["specular"][b], out["Rd"][b] = spec, rd
        out["Tt"][b], out["lost"][b] = tot[ix["transmitted"]] / n, tot[ix["lost"]] / n
        out["missed"][b] = tot[ix["missed"]] / n
        absorbed = sum(tot[na:na + nl])
        out["A"][b] = absorbed / n
        fr = rows / (sizes[:, None] * W0)
        r_b = fr[:, ix["diffuse"]] + (fr[:, ix["specular"]] if specular else 0.0)
        out["R"][b] = spec + rd if specular else rd
        out["se"][b] = r_b.std(ddof=1) / math.sqrt(batches)
        out["Rd_se"][b] = fr[:, ix["diffuse"]].std(ddof=1) / math.sqrt(batches)
        w = sum(tot[c] for c in sinks) + absorbed - tot[ix["rr_gain"]]
        bal = max(bal, abs(w - photons * W0) / (photons * W0))
    out["balance_error"] = bal
    return out


def spectral_reflectance(cfg: dict, photons: int = 20000, angle_deg: float = DEFAULT_ANGLE,
                         specular: bool = True, spot_mm: float | None = None,
                         port_mm: float | None = None, bands=None, flat: bool = False,
                         direction=None, seed: int | None = None, batches: int = 10,
                         dev=None, device: str | None = None,
                         source: str = "<config>") -> Reflectance:
    """R(λ) of ``cfg`` from the photon pass alone (see the module docstring)."""
    from ..scene import volume
    from ..compute.device import open_device
    t0 = time.perf_counter()
    mcfg = measurement_config(cfg, angle_deg, direction, spot_mm, port_mm, bands, flat, seed, source)
    if direction is not None:
        d = np.asarray(direction, float)
        angle_deg = math.degrees(math.acos(min(1.0, -d[2] / np.linalg.norm(d))))
    vol = volume.build(mcfg, source)
    dev = dev or open_device(device)
    t = trace_bands(dev, vol, mcfg, int(photons), batches, specular)
    return Reflectance(wl=np.asarray(vol.wl, float), R=t["R"], se=t["se"], Rd=t["Rd"],
                       Rd_se=t["Rd_se"], specular=t["specular"], Tt=t["Tt"], A=t["A"],
                       lost=t["lost"] + t["missed"], photons=int(photons),
                       specular_included=bool(specular), angle_deg=float(angle_deg),
                       geometry=geometry_note(mcfg, angle_deg, specular),
                       seed=int(mcfg["render"]["seed"]), seconds=time.perf_counter() - t0,
                       balance_error=t["balance_error"], device=dev.name)


# ----------------------------------------------------------------------------- images
class _PixelCam:
    """A camera whose 'image centre' is pixel point (px, py) of ``cam`` (for white_reference)."""

    def __init__(self, cam, px: float, py: float):
        self._cam, self._px, self._py = cam, px, py
        self.position = cam.position
        self.width, self.height = cam.width, cam.height

    def ray(self, _px, _py):
        return self._cam.ray(self._px, self._py)


def default_region(width: int, height: int, frac: float = 0.5) -> tuple[int, int, int, int]:
    """Central box (x0, y0, x1, y1), ``frac`` of each side, at least one pixel."""
    w = max(1, int(round(width * frac)))
    h = max(1, int(round(height * frac)))
    x0, y0 = (width - w) // 2, (height - h) // 2
    return x0, y0, x0 + w, y0 + h


def white_region(cfg: dict, cam, wl, spectrum, region) -> np.ndarray:
    """White Lambertian reference radiance per pixel of ``region``: (h, w, NB)."""
    from ..scene.light import Light, white_reference
    light = Light.from_config(cfg)
    x0, y0, x1, y1 = region
    out = np.empty((y1 - y0, x1 - x0, len(wl)))
    for j in range(y0, y1):
        for i in range(x0, x1):
            out[j - y0, i - x0] = white_reference(light, _PixelCam(cam, i + 0.5, j + 0.5), wl, spectrum)
    return out


def incidence_direction(cfg: dict, cam) -> np.ndarray:
    """Direction of the configured light's rays at the surface point seen at the image centre."""
    L = cfg["light"]
    if L["kind"] == "point":
        d = cam.ray(cam.width / 2, cam.height / 2)
        t = -cam.position[2] / d[2] if d[2] != 0 else 0.0
        x = cam.position + t * d
        v = x - np.asarray(L["position_mm"], float) * 1000.0
    else:
        v = np.asarray(L["direction"], float)
    return v / np.linalg.norm(v)


def method_reflectance(cfg: dict, methods="abcdef", passes: int | None = None,
                       photons: int | None = None, resolution=None, region=None,
                       specular: bool = False, band_photons: int = 20000, seed: int | None = None,
                       bands=None, dev=None, device: str | None = None, source: str = "<config>",
                       progress: bool = False, log=None) -> dict:
    """Per-method reflectance from rendered images, next to the photon-pass value.

    Each method renders ``cfg`` (with ``passes``, ``photons`` per pass, ``resolution``
    overriding the config, and ``bands`` = (start, stop, step) nm the spectrum grid of both the
    renders and the photon pass; the render's specular highlight off unless ``specular``); the
    spectral radiance of ``region`` (x0, y0, x1, y1 pixels; default the central 50 % box) is
    divided pixel by pixel by the white Lambertian reference under the same light and camera,
    and averaged.  The photon-pass R(λ) is traced for the same bands at the configured light's
    angle of incidence at the image centre (SCE unless ``specular``).  The image value is a
    reflectance *factor* toward the camera: a perfect renderer of a non-Lambertian skin does
    not give exactly Rd, but the difference is the same for every method, so the methods'
    ratios to each other show their spectral bias.
    """
    from ..scene import camera
    from ..compute.device import open_device
    methods = _method_letters(methods, source)
    if bands is not None:
        raw = copy.deepcopy(cfg)
        _set_bands(raw, bands)
        cfg = C.validate(raw, source)
    cfg_r = render_config(cfg, passes, photons, resolution, seed, specular, source)
    cam = camera.from_config(cfg_r["camera"])
    wl = C.wavelengths(cfg_r)
    region = _image_region(region, cam, source)
    white = _white_in_region(cfg_r, cam, wl, region, source)
    dev = dev or open_device(device)
    out = {"wavelength_nm": wl.tolist(), "region": list(region),
           "resolution": [cam.width, cam.height], "passes": cfg_r["render"]["passes"],
           "photons_per_pass": cfg_r["render"]["photons"], "specular": bool(specular),
           "methods": {}}
    for m in methods:
        out["methods"][m] = _image_reflectance(cfg_r, m, white, region, dev, source, progress, log)
    d = incidence_direction(cfg_r, cam)
    truth = spectral_reflectance(cfg, photons=band_photons, specular=specular, direction=d,
                                 seed=seed, dev=dev, source=source)
    out["photon_pass"] = {"angle_deg": math.degrees(math.acos(min(1.0, -d[2]))),
                          "geometry": truth.geometry, "R": truth.R.tolist(),
                          "se": truth.se.tolist(), "photons_per_band": truth.photons}
    for v in out["methods"].values():
        v.update(against_photon_pass(np.asarray(v["R"]), truth.R, wl))
    return out


def _method_letters(methods, source: str) -> list[str]:
    """``methods`` as a list of letters a-f (a string of letters, a comma list, or a list)."""
    methods = [m.strip() for m in (methods.split(",") if isinstance(methods, str) and "," in methods
                                   else list(methods)) if m.strip()]
    for m in methods:
        if m not in "abcdef" or len(m) != 1:
            raise ConfigError(source, "--methods", m, "methods are letters a-f")
    return methods


def _set_bands(raw: dict, bands) -> None:
    """Set the spectrum grid of the raw config ``raw`` to ``bands`` = (start, stop, step) nm."""
    a, b, s = map(float, bands)
    raw["spectrum"].update(start_nm=a, stop_nm=b, step_nm=s)


def render_config(cfg: dict, passes, photons, resolution, seed, specular: bool, source: str) -> dict:
    """The config the methods render: passes, photons, resolution and seed overridden, the
    specular highlight as asked, a light that has a white-reference irradiance."""
    from ..request import resolved_config
    if photons is not None and 0 < photons < cfg["render"]["initial_photons"]:
        # (resolved_config checks photons >= initial_photons before clamping)
        cfg = C.override(cfg, "render", "initial_photons", int(photons))
    cfg_r = resolved_config(cfg, passes=passes, photons=photons, resolution=resolution, seed=seed)
    cfg_r = C.override(cfg_r, "render", "specular", bool(specular))
    if cfg_r["light"]["kind"] == "pencil":
        raise ConfigError(source, "light.kind", "pencil",
                          "image reflectance needs a point or wide light (a pencil beam has no "
                          "white-reference irradiance)")
    return cfg_r


def _image_region(region, cam, source: str) -> tuple[int, int, int, int]:
    """``region`` (default: the central box), checked to lie inside the image."""
    region = tuple(region) if region is not None else default_region(cam.width, cam.height)
    x0, y0, x1, y1 = region
    if not (0 <= x0 < x1 <= cam.width and 0 <= y0 < y1 <= cam.height):
        raise ConfigError(source, "--region", list(region),
                          f"must be x0,y0,x1,y1 inside the {cam.width}x{cam.height} image")
    return region


def _white_in_region(cfg_r: dict, cam, wl, region, source: str) -> np.ndarray:
    """:func:`white_region` under the configured light, which must light every pixel of it."""
    from ..scene.bands import source_spectrum
    white = white_region(cfg_r, cam, wl, source_spectrum(cfg_r, wl), region)
    if not np.all(white > 0):
        raise ConfigError(source, "light", cfg_r["light"]["kind"],
                          "the white reference is zero in the region (light behind the surface?)")
    return white


def _image_reflectance(cfg_r: dict, m: str, white, region, dev, source: str, progress: bool,
                       log) -> dict:
    """Render method ``m``; its reflectance factor over ``region`` (mean and standard error)."""
    from ..run import entry
    t0 = time.perf_counter()
    res = entry.render(cfg_r, method=m, dev=dev, source=source, progress=progress)
    Rm, se = region_ratio(res.spectral, white, region)
    row = {"scheme": res.report["scheme"], "R": Rm.tolist(), "se": se.tolist(),
           "sample_points": res.report["sample_points"], "seconds": time.perf_counter() - t0}
    if log:
        log(f"  method {m}: {res.report['scheme']}, {res.report['sample_points']} sample points, "
            f"{time.perf_counter() - t0:.1f} s")
    return row


def region_ratio(spectral, white, region) -> tuple[np.ndarray, np.ndarray]:
    """Per band: the mean over the pixels of ``region`` of the radiance / the white reference,
    and its standard error (NaN for a single pixel)."""
    x0, y0, x1, y1 = region
    ratio = spectral[y0:y1, x0:x1, :].astype(np.float64) / white
    n = ratio.shape[0] * ratio.shape[1]
    Rm = ratio.reshape(n, -1).mean(0)
    se = ratio.reshape(n, -1).std(0, ddof=1) / math.sqrt(n) if n > 1 else np.full(ratio.shape[2], np.nan)
    return Rm, se


@dataclass
class ImageRegion:
    """The reflectance factor of a region of a rendered image: per band, the region's mean
    spectral radiance over a white Lambertian plane's under the render's own light and camera
    (:func:`region_ratio`), with the render's config and the light's angle of incidence at
    the region's centre: what ``clppm fit --image`` fits."""
    wl: np.ndarray
    R: np.ndarray
    se: np.ndarray
    cfg: dict                 # the render's config (its report's), maps and inclusions included
    region: tuple[int, int, int, int]
    angle_deg: float
    label: str


def image_region(exr_path: str, region, source: str = "--image") -> ImageRegion:
    """:class:`ImageRegion` of ``region`` (x0, y0, x1, y1 pixels) of the spectral EXR a render
    wrote at ``exr_path``; its report (``NAME.json`` beside it) gives the config the image was
    rendered with.  Bad paths and regions raise ConfigError naming them."""
    import json
    from .. import image
    from ..output import paths
    from ..scene import camera
    from ..scene.bands import source_spectrum
    rep_path = paths.render_outputs(exr_path)["report"] if exr_path.lower().endswith(".exr") else None
    if rep_path is None:
        raise ConfigError(source, "--image", exr_path, "must be the .exr file a clppm render wrote")
    try:
        exr = image.read_exr(exr_path)
    except ValueError as e:
        raise ConfigError(source, "--image", exr_path, str(e)) from None
    if exr["spectral"] is None:
        raise ConfigError(source, "--image", exr_path, "has no spectral channels (S0.*)")
    try:
        with open(rep_path) as f:
            rep = json.load(f)
        cfg = C.validate(rep["config"], rep_path)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(source, "--image", exr_path,
                          f"needs the render's report beside it ({rep_path}): {e}") from None
    cam = camera.from_config(cfg["camera"])
    h, w = exr["spectral"].shape[:2]
    if (w, h) != (cam.width, cam.height):
        raise ConfigError(source, "--image", exr_path,
                          f"is {w}x{h} but its report's camera is {cam.width}x{cam.height}")
    wl = np.asarray(exr["wl"], float)
    if not np.allclose(wl, C.wavelengths(cfg)):
        raise ConfigError(source, "--image", exr_path, "its bands differ from its report's spectrum")
    if cfg["light"]["kind"] == "pencil":
        raise ConfigError(source, "--image", exr_path,
                          "was lit by a pencil beam, which has no white-reference irradiance")
    region = _image_region(region, cam, source)
    white = _white_in_region(cfg, cam, wl, region, source)
    R, se = region_ratio(exr["spectral"], white, region)
    x0, y0, x1, y1 = region
    d = incidence_direction(cfg, _PixelCam(cam, (x0 + x1) / 2, (y0 + y1) / 2))
    angle = math.degrees(math.acos(min(1.0, -d[2])))
    label = f"{os.path.basename(exr_path)} region {x0},{y0},{x1},{y1}"
    return ImageRegion(wl=wl, R=R, se=se, cfg=cfg, region=region, angle_deg=angle, label=label)


def against_photon_pass(Rm, tr, wl) -> dict:
    """An image reflectance ``Rm`` against the photon pass's ``tr``: ratio per band, mean
    absolute difference, and the spectral bias: the blue (< 500 nm) over the red (> 600 nm)
    ratio, less one."""
    out = {"ratio_to_photon_pass": (Rm / np.where(tr > 0, tr, np.nan)).tolist(),
           "mean_abs_diff": float(np.mean(np.abs(Rm - tr)))}
    blue, red = wl < 500, wl > 600
    if blue.any() and red.any():
        rb = np.nanmean(Rm[blue] / tr[blue]); rr = np.nanmean(Rm[red] / tr[red])
        out["blue_red_bias"] = float(rb / rr - 1.0)
    return out


# ----------------------------------------------------------------------------- CLI


