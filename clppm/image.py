"""Colour science and image I/O for clppm.

Everything here is pure NumPy + colour-science + OpenEXR + Pillow; no other clppm
module is imported, so this file can be used (and tested) on its own.

Conventions
-----------
* Spectra are sampled on a wavelength grid ``wl`` in nanometres; spectral radiance is
  "per nm", so tristimulus values are the rectangle-rule sum
  ``XYZ = sum_i L(wl_i) * cmf(wl_i) * dlambda`` over a *uniform* grid.
* Colour matching functions are the CIE 1931 2 degree standard observer from
  colour-science (``colour.MSDS_CMFS['CIE 1931 2 Degree Standard Observer']``,
  1 nm table 360-830 nm), evaluated with colour's own interpolator (Sprague on the
  uniform table, so integer wavelengths return the table values exactly).
  Outside 360-830 nm the CMFs are taken as 0.
* XYZ <-> RGB uses the sRGB colourspace (ITU-R BT.709 primaries, D65 white) *linear*
  (no CCTF), with the 3x3 matrices derived from primaries + white point (see _SRGB). The renderer's light source is D65, whose white point is sRGB's own, so
  no chromatic adaptation is applied (``chromatic_adaptation_transform=None``): the
  XYZ values are taken to be already relative to D65.
* Colour-science is used at its default "reference" domain-range scale: XYZ in
  [0, 1]-ish units (Y = 1 for the white), L* in [0, 100].

Black / zero handling (no NaN ever produced from finite input):
* ``xyz_to_lab(0)`` is Lab (0, 0, 0).
* ``xyz_to_uv_prime(0)`` (and any XYZ with X + 15Y + 3Z == 0) is defined as the
  u'v' of the white point (D65 unless ``white_XYZ`` is given): black is treated as
  an achromatic colour.
* ``delta_e2000`` of two blacks is 0.
* ``encode_srgb`` / ``write_png`` map NaN to 0 and +inf to 1 (after clipping).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

import colour
import OpenEXR

__all__ = [
    "CMFS_NAME",
    "D65_XYZ",
    "cmfs",
    "spectral_to_xyz",
    "xyz_to_linear_srgb",
    "linear_srgb_to_xyz",
    "encode_srgb",
    "xyz_to_uv_prime",
    "xyz_to_lab",
    "delta_e2000",
    "spectral_channel_name",
    "parse_spectral_channel_name",
    "write_exr",
    "read_exr",
    "write_png",
    "load_heightmap",
]

CMFS_NAME = "CIE 1931 2 Degree Standard Observer"
# colour's sRGB colourspace ships the IEC 61966-2-1 4-decimal matrices, which are not
# exact inverses of each other (XYZ->RGB->XYZ is off by ~5e-5 and D65 white maps to
# RGB (0.99984, 1.0001, 1.00007)). We use a copy whose matrices are derived from the
# sRGB primaries and the D65 white point instead: exact inverses, white -> (1, 1, 1).
_SRGB = colour.RGB_COLOURSPACES["sRGB"].copy()
_SRGB.use_derived_transformation_matrices(True)

#: XYZ of the D65 white point with Y = 1 (from colour's CIE 1931 2 deg chromaticity).
D65_XYZ = np.asarray(
    colour.xy_to_XYZ(colour.CCS_ILLUMINANTS[CMFS_NAME]["D65"]), dtype=np.float64
)

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
    *(float(v) for v in np.asarray(_SRGB.primaries).ravel()),
    *(float(v) for v in np.asarray(_SRGB.whitepoint).ravel()),
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


# --------------------------------------------------------------------------- colour


def cmfs(wl) -> np.ndarray:
    """CIE 1931 2 deg colour matching functions at wavelengths ``wl`` (nm).

    Returns an array of shape ``(N, 3)`` (x-bar, y-bar, z-bar), float64. Values are
    interpolated by colour-science's own interpolator for the tabulated CMFs; outside
    the table's 360-830 nm range they are 0.
    """
    wl = np.asarray(wl, dtype=np.float64).ravel()
    table = colour.MSDS_CMFS[CMFS_NAME]
    lo, hi = float(table.shape.start), float(table.shape.end)
    inside = (wl >= lo) & (wl <= hi)
    out = np.zeros((wl.size, 3), dtype=np.float64)
    if np.any(inside):
        out[inside] = np.asarray(table[wl[inside]], dtype=np.float64).reshape(-1, 3)
    return out


def _uniform_step(wl: np.ndarray) -> float:
    if wl.ndim != 1 or wl.size < 2:
        raise ValueError("wavelength grid must be 1-D with at least 2 samples")
    d = np.diff(wl)
    step = float(d[0])
    if step <= 0 or not np.allclose(d, step, rtol=1e-6, atol=1e-9):
        raise ValueError("wavelength grid must be uniform and increasing")
    return step


def spectral_to_xyz(L, wl) -> np.ndarray:
    """Integrate spectral quantities ``L`` (..., N) per nm against the CMFs.

    ``wl`` must be a uniform, increasing grid of N wavelengths (nm). Returns
    ``(..., 3)`` = ``sum_i L[..., i] * cmf(wl_i) * dlambda`` (no normalisation: for
    spectral radiance this is XYZ in radiance units, i.e. Y is the CIE-weighted
    radiance without the 683 lm/W factor).
    """
    wl = np.asarray(wl, dtype=np.float64)
    L = np.asarray(L, dtype=np.float64)
    if L.shape[-1:] != wl.shape:
        raise ValueError(f"spectral data last axis {L.shape[-1:]} != wl shape {wl.shape}")
    step = _uniform_step(wl)
    return (L @ cmfs(wl)) * step


def xyz_to_linear_srgb(XYZ) -> np.ndarray:
    """CIE XYZ (D65-relative, Y=1 white) -> linear sRGB (no CCTF, no adaptation)."""
    return np.asarray(
        colour.XYZ_to_RGB(
            np.asarray(XYZ, dtype=np.float64),
            _SRGB,
            illuminant=None,
            chromatic_adaptation_transform=None,
            apply_cctf_encoding=False,
        ),
        dtype=np.float64,
    )


def linear_srgb_to_xyz(rgb) -> np.ndarray:
    """Linear sRGB -> CIE XYZ (D65-relative), inverse of :func:`xyz_to_linear_srgb`."""
    return np.asarray(
        colour.RGB_to_XYZ(
            np.asarray(rgb, dtype=np.float64),
            _SRGB,
            illuminant=None,
            chromatic_adaptation_transform=None,
            apply_cctf_decoding=False,
        ),
        dtype=np.float64,
    )


def encode_srgb(rgb) -> np.ndarray:
    """Linear values -> sRGB gamma-encoded values in [0, 1] (clipped; NaN -> 0)."""
    x = np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    x = np.clip(x, 0.0, 1.0)
    y = np.asarray(colour.cctf_encoding(x, function="sRGB"), dtype=np.float64)
    # colour's CCTF gives 1 - 1 ulp at 1.0; pin the end points exactly.
    return np.where(x >= 1.0, 1.0, np.clip(y, 0.0, 1.0))


def _white_xyz(white_XYZ) -> np.ndarray:
    w = D65_XYZ if white_XYZ is None else np.asarray(white_XYZ, dtype=np.float64)
    if w.shape[-1:] != (3,):
        raise ValueError(f"white_XYZ must have a last axis of 3, got shape {w.shape}")
    if np.any(~np.isfinite(w)) or np.any(w[..., 1] <= 0):
        raise ValueError("white_XYZ must be finite with Y > 0")
    return w


def xyz_to_uv_prime(XYZ, white_XYZ=None) -> np.ndarray:
    """CIE 1976 UCS chromaticity (u', v') of XYZ, shape (..., 2).

    u' = 4X / (X + 15Y + 3Z), v' = 9Y / (X + 15Y + 3Z). Where the denominator is 0
    (black) the result is the u'v' of the white point (``white_XYZ``, D65 by default)
    rather than NaN. Matches ``colour.xy_to_Luv_uv(colour.XYZ_to_xy(XYZ))`` elsewhere.
    """
    XYZ = np.asarray(XYZ, dtype=np.float64)
    w = _white_xyz(white_XYZ)
    X, Y, Z = XYZ[..., 0], XYZ[..., 1], XYZ[..., 2]
    den = X + 15.0 * Y + 3.0 * Z
    wden = w[..., 0] + 15.0 * w[..., 1] + 3.0 * w[..., 2]
    wu, wv = 4.0 * w[..., 0] / wden, 9.0 * w[..., 1] / wden
    zero = den == 0
    safe = np.where(zero, 1.0, den)
    u = np.where(zero, wu, 4.0 * X / safe)
    v = np.where(zero, wv, 9.0 * Y / safe)
    return np.stack(np.broadcast_arrays(u, v), axis=-1)


def xyz_to_lab(XYZ, white_XYZ=None) -> np.ndarray:
    """CIE 1976 L*a*b* of XYZ relative to the white ``white_XYZ`` (D65, Y=1 default).

    XYZ is scaled by 1 / white_Y and passed to ``colour.XYZ_to_Lab`` with the white's
    xy chromaticity as illuminant, so any absolute scale works as long as XYZ and
    white share it. L* is in [0, 100]; black gives (0, 0, 0).
    """
    XYZ = np.asarray(XYZ, dtype=np.float64)
    w = _white_xyz(white_XYZ)
    xy_w = np.asarray(colour.XYZ_to_xy(w), dtype=np.float64)
    return np.asarray(
        colour.XYZ_to_Lab(XYZ / w[..., 1:2], illuminant=xy_w), dtype=np.float64
    )


def delta_e2000(xyz_a, xyz_b, white_XYZ=None) -> np.ndarray:
    """CIEDE2000 colour difference between two XYZ colours (vectorised, shape (...)).

    Both are converted to Lab with :func:`xyz_to_lab` (same white) and compared with
    ``colour.delta_E(..., method='CIE 2000')``.
    """
    lab_a = xyz_to_lab(xyz_a, white_XYZ)
    lab_b = xyz_to_lab(xyz_b, white_XYZ)
    return np.asarray(colour.delta_E(lab_a, lab_b, method="CIE 2000"), dtype=np.float64)


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
    ``spectralLayoutVersion``), not the structural ones.
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
    tmp = f"{path}.{os.getpid()}.tmp"         # a kill mid-write leaves the old file, not half a PNG
    try:
        Image.fromarray(u8, mode=mode).save(tmp, format="PNG")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


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
