"""Colorimetry: CIE 1931 colour matching functions, spectral -> XYZ, XYZ <-> linear sRGB,
sRGB encoding, u'v', L*a*b* and CIEDE2000 (colour-science underneath).

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
  (no CCTF), with the 3x3 matrices derived from primaries + white point (see SRGB). The
  renderer's light source is D65, whose white point is sRGB's own, so no chromatic adaptation
  is applied (``chromatic_adaptation_transform=None``): the XYZ values are taken to be
  already relative to D65.
* Colour-science is used at its default "reference" domain-range scale: XYZ in
  [0, 1]-ish units (Y = 1 for the white), L* in [0, 100].

Black / zero handling (no NaN ever produced from finite input):
* ``xyz_to_lab(0)`` is Lab (0, 0, 0).
* ``xyz_to_uv_prime(0)`` (and any XYZ with X + 15Y + 3Z == 0) is defined as the
  u'v' of the white point (D65 unless ``white_XYZ`` is given): black is treated as
  an achromatic colour.
* ``delta_e2000`` of two blacks is 0.
* ``encode_srgb`` maps NaN to 0 and +inf to 1 (after clipping).
"""

from __future__ import annotations

import numpy as np

import colour

CMFS_NAME = "CIE 1931 2 Degree Standard Observer"
# colour's sRGB colourspace ships the IEC 61966-2-1 4-decimal matrices, which are not
# exact inverses of each other (XYZ->RGB->XYZ is off by ~5e-5 and D65 white maps to
# RGB (0.99984, 1.0001, 1.00007)). We use a copy whose matrices are derived from the
# sRGB primaries and the D65 white point instead: exact inverses, white -> (1, 1, 1).
SRGB = colour.RGB_COLOURSPACES["sRGB"].copy()
SRGB.use_derived_transformation_matrices(True)

#: XYZ of the D65 white point with Y = 1 (from colour's CIE 1931 2 deg chromaticity).
D65_XYZ = np.asarray(
    colour.xy_to_XYZ(colour.CCS_ILLUMINANTS[CMFS_NAME]["D65"]), dtype=np.float64
)


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
            SRGB,
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
            SRGB,
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
