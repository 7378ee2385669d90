"""Image files: OpenEXR (RGB plus spectral channels, Fichet et al.'s naming), 8-bit sRGB PNG,
and height maps (.npy, 16-bit PNG, EXR).  The colour conversions are in
:mod:`clppm.scene.colorimetry`.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

import OpenEXR

from .scene.colorimetry import SRGB, encode_srgb

__all__ = [
    "spectral_channel_name",
    "parse_spectral_channel_name",
    "write_exr",
    "read_exr",
    "write_png",
    "load_heightmap",
]

# OpenEXR header attributes managed by the library / by write_exr itself; user
# header keys may not collide with these.
_RESERVED_ATTRS = frozenset(
    {
        "channels",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "type",
        "name",
        "tiles",
        "version",
        "chunkCount",
        "chromaticities",
    }
)

# sRGB / Rec.709 primaries + D65 white, as the OpenEXR 'chromaticities' attribute
# (red x,y, green x,y, blue x,y, white x,y).
_SRGB_CHROMATICITIES = (
    *(float(v) for v in np.asarray(SRGB.primaries).ravel()),
    *(float(v) for v in np.asarray(SRGB.whitepoint).ravel()),
)

# Fichet, Pacanowski & Wilkie (JCGT 2021) emissive channel names: S<stokes>.<number>
# <SI prefix><m|Hz>, with a comma as decimal separator.
_SPECTRAL_RE = re.compile(
    r"^S([0-3])\.(\d*,?\d*(?:[Ee][+-]?\d+)?)(Y|Z|E|P|T|G|M|k|h|da|d|c|m|u|n|p)?(m|Hz)$"
)
_SI_EXP = {
    "Y": 24, "Z": 21, "E": 18, "P": 15, "T": 12, "G": 9, "M": 6, "k": 3, "h": 2,
    "da": 1, "": 0, "d": -1, "c": -2, "m": -3, "u": -6, "n": -9, "p": -12,
}
_SPEED_OF_LIGHT = 299792458.0

SPECTRAL_LAYOUT_VERSION = "1.0"


# ---------------------------------------------------------------------- OpenEXR I/O


def spectral_channel_name(wavelength_nm: float, stokes: int = 0) -> str:
    """Emissive spectral channel name per Fichet et al. 2021, e.g. 'S0.380,000000nm'."""
    return f"S{int(stokes)}." + f"{float(wavelength_nm):.6f}".replace(".", ",") + "nm"


def parse_spectral_channel_name(name: str):
    """Return (stokes, wavelength_nm) for a Fichet et al. 2021 emissive channel name,
    or None if ``name`` is not one."""
    m = _SPECTRAL_RE.match(name)
    if m is None or m.group(2) in ("", ","):
        return None
    value = float(m.group(2).replace(",", "."))
    prefix, unit = m.group(3) or "", m.group(4)
    e = _SI_EXP[prefix]
    if unit == "m":
        k = e + 9  # power of ten from <prefix>m to nm; exact for 'nm' (k == 0)
        wl = value * 10.0**k if k >= 0 else value / 10.0 ** (-k)
    else:  # Hz
        f = value * 10.0**e
        if f == 0:
            return None
        wl = _SPEED_OF_LIGHT / f * 1e9
    return int(m.group(1)), wl


def _as_f32_plane(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def write_exr(path, rgb, spectral=None, wl=None, header: Mapping[str, str] | None = None):
    """Write a scanline, ZIP-compressed, float32 OpenEXR file.

    * ``rgb``: (H, W, 3) linear sRGB, stored as channels R, G, B (plus a
      ``chromaticities`` attribute for sRGB/Rec.709 primaries, D65 white).
    * ``spectral``: optional (H, W, N) emissive spectral data on wavelengths ``wl``
      (N,), nm; one channel per band named ``S0.<wl with 6 decimals, comma>nm``
      (Fichet, Pacanowski & Wilkie, JCGT 2021), plus the string attribute
      ``spectralLayoutVersion`` = "1.0" (unless ``header`` sets it).
    * ``header``: dict str -> str, stored as string attributes. Keys may not be
      OpenEXR structural attribute names (channels, compression, ...).

    The same inputs always give byte-identical files.
    """
    path = os.fspath(path)
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError(f"rgb must have shape (H, W, 3) with H, W > 0, got {rgb.shape}")
    H, W = rgb.shape[:2]
    channels: dict[str, np.ndarray] = {
        "R": _as_f32_plane(rgb[..., 0]),
        "G": _as_f32_plane(rgb[..., 1]),
        "B": _as_f32_plane(rgb[..., 2]),
    }
    attrs: dict[str, Any] = {}
    if spectral is not None:
        spectral = np.asarray(spectral)
        if wl is None:
            raise ValueError("wl is required when spectral is given")
        wl_arr = np.asarray(wl, dtype=np.float64).ravel()
        if spectral.ndim != 3 or spectral.shape[:2] != (H, W):
            raise ValueError(
                f"spectral must have shape ({H}, {W}, N), got {spectral.shape}"
            )
        if spectral.shape[2] != wl_arr.size:
            raise ValueError(
                f"spectral has {spectral.shape[2]} bands but wl has {wl_arr.size}"
            )
        for i, w in enumerate(wl_arr):
            if not (math.isfinite(w) and w > 0):
                raise ValueError(f"invalid wavelength {w!r}")
            name = spectral_channel_name(w)
            if name in channels:
                raise ValueError(f"duplicate spectral channel name {name!r}")
            channels[name] = _as_f32_plane(spectral[..., i])
        attrs["spectralLayoutVersion"] = SPECTRAL_LAYOUT_VERSION
    elif wl is not None:
        raise ValueError("wl given without spectral")

    for k, v in (header or {}).items():
        if not isinstance(k, str) or not isinstance(v, str):
            raise TypeError(f"header must map str -> str, got {k!r}: {type(v).__name__}")
        if k in _RESERVED_ATTRS:
            raise ValueError(f"header key {k!r} is a reserved OpenEXR attribute")
        attrs[k] = v

    exr_header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "chromaticities": _SRGB_CHROMATICITIES,
        **attrs,
    }
    with OpenEXR.File(exr_header, channels) as f:
        f.write(path)


def _open_exr_channels(path: str):
    """(header dict, {name: 2-D ndarray}) of the first part of an EXR file."""
    try:
        # separate_channels=True: otherwise R,G,B(,A) come back merged as one
        # (H, W, 3) channel called "RGB".
        with OpenEXR.File(path, separate_channels=True) as f:
            hdr = dict(f.header())
            chans = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except (RuntimeError, OSError, ValueError) as e:
        raise ValueError(f"cannot read OpenEXR file {path!r}: {e}") from e
    return hdr, chans


def read_exr(path) -> dict:
    """Read a file written by :func:`write_exr` (or any single-part scanline EXR).

    Returns ``dict(rgb=(H, W, 3) float32 or None, spectral=(H, W, N) float32 or None,
    wl=(N,) float64 nm or None, header=dict)``. ``rgb`` comes from channels R, G, B
    (or Y replicated if only Y exists; None if neither). ``spectral`` gathers the
    Stokes-0 emissive channels (``S0.*``) sorted by wavelength. ``header`` contains
    every string-valued attribute of the file (user header plus e.g.
    ``spectralLayoutVersion``; a render's ``clppm_report``, a JSON string), not the
    structural ones.  Raises ValueError naming the file when it is missing or not an EXR.

    >>> exr = read_exr("out/forearm.exr")
    >>> exr["spectral"].shape, exr["wl"][[0, -1]]      # ((240, 320, 81), array([380., 780.]))
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"OpenEXR file not found: {path!r}")
    hdr, chans = _open_exr_channels(path)

    if all(c in chans for c in "RGB"):
        rgb = np.stack([chans[c].astype(np.float32) for c in "RGB"], axis=-1)
    elif "Y" in chans:
        rgb = np.repeat(chans["Y"].astype(np.float32)[..., None], 3, axis=-1)
    else:
        rgb = None

    bands = []
    for name, arr in chans.items():
        parsed = parse_spectral_channel_name(name)
        if parsed is not None and parsed[0] == 0:
            bands.append((parsed[1], name))
    if bands:
        bands.sort()
        wl = np.array([b[0] for b in bands], dtype=np.float64)
        spectral = np.stack([chans[n].astype(np.float32) for _, n in bands], axis=-1)
    else:
        wl = spectral = None

    header = {
        k: v
        for k, v in hdr.items()
        if isinstance(v, str) and k not in _RESERVED_ATTRS
    }
    return dict(rgb=rgb, spectral=spectral, wl=wl, header=header)


# -------------------------------------------------------------------------- PNG I/O


def write_png(path, rgb_linear, exposure: float = 1.0) -> None:
    """Write an 8-bit sRGB PNG of ``rgb_linear * exposure`` ((H, W, 3) or (H, W)).

    Values are clipped to [0, 1], sRGB-encoded and rounded to 0..255. No metadata
    (time stamps etc.) is written, so equal inputs give byte-identical files.
    """
    from PIL import Image

    a = np.asarray(rgb_linear, dtype=np.float64)
    if a.ndim == 2:
        mode = "L"
    elif a.ndim == 3 and a.shape[2] == 3:
        mode = "RGB"
    else:
        raise ValueError(f"rgb_linear must have shape (H, W, 3) or (H, W), got {a.shape}")
    enc = encode_srgb(a * float(exposure))
    u8 = np.ascontiguousarray(np.round(enc * 255.0).astype(np.uint8))
    path = os.fspath(path)
    from .output.paths import write_atomic    # a kill mid-write leaves the old file, not half a PNG
    write_atomic(path, lambda tmp: Image.fromarray(u8, mode=mode).save(tmp, format="PNG"))


# --------------------------------------------------------------------- height maps


def load_heightmap(path) -> np.ndarray:
    """Load a 2-D height map of raw values as float64.

    Supported: ``.npy`` (any real numeric dtype), ``.png`` grayscale 8- or 16-bit
    (16-bit values are kept exactly, 0..65535), ``.exr`` (channel Y, else R, else the
    first channel in name order). No rescaling is applied. Raises ValueError naming
    the file for a missing/unreadable file, unknown extension, data that is not 2-D
    or empty, or non-finite values (NaN/inf).
    """
    p = Path(os.fspath(path))
    name = str(p)
    if not p.is_file():
        raise ValueError(f"height map file not found: {name!r}")
    ext = p.suffix.lower()
    if ext == ".npy":
        try:
            data = np.load(p, allow_pickle=False)
        except Exception as e:  # noqa: BLE001 - any failure is a bad file
            raise ValueError(f"cannot read height map {name!r} as .npy: {e}") from e
        if not isinstance(data, np.ndarray) or not (
            np.issubdtype(data.dtype, np.integer)
            or np.issubdtype(data.dtype, np.floating)
            or data.dtype == np.bool_
        ):
            raise ValueError(f"height map {name!r} does not hold real numeric data")
    elif ext == ".png":
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(p) as im:
                im.load()
                mode = im.mode
                if mode not in ("1", "L", "I", "I;16", "I;16L", "I;16B", "F"):
                    raise ValueError(
                        f"height map {name!r} is not a grayscale PNG (mode {mode!r})"
                    )
                data = np.array(im)
        except ValueError:
            raise
        except (UnidentifiedImageError, OSError, SyntaxError) as e:
            raise ValueError(f"cannot read height map {name!r} as PNG: {e}") from e
    elif ext == ".exr":
        _, chans = _open_exr_channels(name)
        if not chans:
            raise ValueError(f"height map {name!r} has no channels")
        key = "Y" if "Y" in chans else "R" if "R" in chans else sorted(chans)[0]
        data = chans[key]
    else:
        raise ValueError(
            f"height map {name!r}: unknown extension {p.suffix!r} "
            "(expected .npy, .png or .exr)"
        )
    data = np.asarray(data, dtype=np.float64)
    if data.ndim != 2 or data.size == 0:
        raise ValueError(f"height map {name!r} must be non-empty 2-D, got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise ValueError(f"height map {name!r} contains NaN or infinite values")
    return data
