"""The film: spectral radiance per pixel and band -> XYZ -> linear sRGB, the white reference
and exposure, the run report's common fields, and the files a render writes (EXR, PNG, JSON).

Both integrators hand the film their radiance (W m^-2 sr^-1 nm^-1, one value per pixel and
band); the film never sees how it was estimated.  XYZ is the rectangle rule over the bands,
XYZ = sum L(l) xyz-bar(l) dl (without the 683 lm/W factor).  The exposure makes a white
Lambertian plane at the image centre, lit by the same light, come out white (Y = 1) unless
``render.exposure`` sets it.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass

import numpy as np

from ..scene import colorimetry, scene
from .. import image
from . import paths
from ..config import render_settings
from ..scene.bands import tristimulus
from ..scene.light import white_reference
from ..version import __version__

UNITS = "spectral radiance W m^-2 sr^-1 nm^-1 (EXR spectral channels); RGB linear sRGB"


@dataclass
class RenderResult:
    """What :func:`clppm.render` returns: the image in three forms and the run report.

    * ``spectral``: (H, W, NB) float spectral radiance, W m^-2 sr^-1 nm^-1, one value per band
      (the EXR's ``S0.*`` channels); ``wl``: (NB,) the band centres, nm (380, 385, .. 780 by
      default);
    * ``xyz``: (H, W, 3) CIE 1931 XYZ of ``spectral`` (rectangle rule over the bands, without
      the 683 lm/W factor);
    * ``rgb``: (H, W, 3) linear sRGB (D65), unexposed (the EXR's R, G, B channels);
    * ``exposure``: the factor the PNG applies to ``rgb`` (a white diffuser at the image
      centre comes out white, unless ``render.exposure`` sets it): the PNG is
      ``clppm.image.write_png(path, res.rgb, res.exposure)``;
    * ``report``: the run report, the dict written to ``NAME.json`` (docs/outputs.md lists
      its fields).
    """
    spectral: np.ndarray          # (H, W, NB) spectral radiance W m^-2 sr^-1 nm^-1
    xyz: np.ndarray               # (H, W, 3)
    rgb: np.ndarray               # (H, W, 3) linear sRGB
    wl: np.ndarray
    report: dict
    exposure: float = 1.0


def exposure_of(set_by_hand: float | None, white_y: float) -> tuple[float, str]:
    """The PNG's exposure and where it came from (the report's ``exposure_from``)."""
    if set_by_hand is not None:
        return set_by_hand, "render.exposure"
    if white_y > 0:
        return 1.0 / white_y, "white reference"
    return 1.0, "assumed 1.0: the white reference at the image centre gets no light"


def develop(L: np.ndarray, cam, wl, spectrum, light, exposure: float | None = None) -> RenderResult:
    """Radiance (npix, NB) -> the image; its report holds the exposure (``exposure``, else from
    the white reference under ``light``), the white reference and the count of non-finite
    values (set to 0).  The film knows the camera, the bands and the light, not the integrator."""
    nonfinite = int(np.size(L) - np.count_nonzero(np.isfinite(L)))
    L = np.nan_to_num(L, copy=False, nan=0.0, posinf=0.0, neginf=0.0).reshape(cam.height, cam.width, len(wl))
    xyz = tristimulus(L, wl)
    rgb = colorimetry.xyz_to_linear_srgb(xyz)
    Yw = float(tristimulus(white_reference(light, cam, wl, spectrum)[None, :], wl)[0, 1])
    exposure, source = exposure_of(exposure, Yw)
    report = {"exposure": exposure, "exposure_from": source, "white_reference_Y": Yw,
              "nonfinite_values_zeroed": nonfinite}
    return RenderResult(spectral=L, xyz=xyz, rgb=rgb, wl=np.asarray(wl), report=report,
                        exposure=exposure)


def common_report(cfg: dict, integrator: str, dev, passes_done: int, interrupted: bool) -> dict:
    """The report's fields that every integrator has, in the order they are written."""
    return {"clppm": __version__,
            "config": json.loads(json.dumps(cfg, default=str)),
            "integrator": integrator, "device": dev.info(),
            "passes_done": passes_done, "passes_requested": render_settings(cfg).passes,
            "interrupted": interrupted, "assumed": scene.notes(cfg),
            "programs_built": programs_built()}


def programs_built() -> dict:
    """The programs this process built (or loaded from the binary caches) so far: count,
    seconds, per kernel file (clppm.compute.programs.REGISTRY)."""
    from ..compute.programs import REGISTRY
    st = REGISTRY.stats
    return {"count": st.programs, "seconds": st.seconds,
            "by_file": {f: {"count": n, "seconds": s} for f, (n, s) in sorted(st.by_file.items())}}


def sibling(out: str, suffix: str) -> str:
    """``out`` with its extension replaced by ``suffix`` (``.preview.png``)."""
    base, _ = os.path.splitext(out)
    return base + suffix


def write_image(out: str, res: RenderResult) -> None:
    """The image at ``out``: ``.exr`` the spectral + RGB EXR and the PNG beside it; ``.png``
    the PNG alone (:func:`clppm.output.paths.render_outputs`).  Each file whole or not at all."""
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    files = paths.render_outputs(out)
    if "png" in files:
        hdr = {"clppm_report": json.dumps({k: res.report[k] for k in ("method", "scheme", "passes_done",
                                                                       "photons_emitted", "exposure")})}
        paths.write_atomic(out, lambda tmp: image.write_exr(
            tmp, res.rgb.astype(np.float32), spectral=res.spectral, wl=res.wl, header=hdr))   # planes made float32 one by one
    _write_png(files.get("png", out), res)


def _write_png(path: str, res: RenderResult) -> None:
    image.write_png(path, res.rgb, res.exposure)          # atomic itself


def write_preview(out: str, res: RenderResult) -> None:
    _write_png(sibling(out, ".preview.png"), res)


def write_report(out: str, report: dict) -> None:
    def fill(tmp):
        with open(tmp, "w") as f:
            json.dump(report, f, indent=1, default=str)
    paths.write_atomic(paths.render_outputs(out)["report"], fill)


def write_outputs(out: str | None, res: RenderResult) -> None:
    """The finished render's files: the image(s), then the report with the output seconds."""
    t0 = time.perf_counter()
    if out:
        write_image(out, res)
    res.report["seconds"]["output"] = time.perf_counter() - t0
    if out:
        write_report(out, res.report)
