"""Chromophore maps: a layer's melanin, blood or oxygen saturation varying from column to column
(``[[map]]`` tables; docs/config.md, docs/method.md "Chromophore maps").

A layer's absorption is linear in its chromophores (clppm/scene/skin.py optics):

    mu_a(b) = M mel(b) + B deoxy(b) + (B S) (oxy(b) - deoxy(b)) + baseline base(b),

so three numbers per column, M, B and B S, give every band's mu_a with three per-band basis
spectra (the same Prahl haemoglobin and melanosome spectra the layers use): the device holds the
map's columns and the basis, never a table per column and band.  The maps share one grid of
columns, ``model.lateral_voxel_um`` a side over the model's footprint (the paper's 5 um columns),
whatever the volume's own column grid (a flat model has one column).  A file coarser or finer than
that grid is resampled bilinearly onto the column centres: chromophore concentrations vary
smoothly, so a map's pixels should not show as squares, and a bilinear value lies between its
four pixels' (a fraction stays in [0, 1], a uniform map stays exactly uniform).  Beyond the
footprint (infinite sides) a map keeps its edge values.

Scattering is not mapped: the photon pass traces a mapped layer by weighted delta tracking against
a per-band majorant of its mu_t (kernels/maps.h), and keeping mu_s constant makes that majorant
mu_s + max mu_a, tight wherever the absorption is.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import ConfigError
from . import spectra

#: quantities per column on the device: melanin, blood, blood x saturation (then a pad)
COLS = 4


def grid(cfg: dict) -> tuple[int, int, float, float]:
    """The maps' columns: nx, ny and their size (um) over the model's footprint."""
    W, H = (v * 1000.0 for v in cfg["model"]["size_mm"])
    d = cfg["model"]["lateral_voxel_um"]
    nx, ny = max(1, int(round(W / d))), max(1, int(round(H / d)))
    return nx, ny, W / nx, H / ny


def _read_file(path: str, src: str, key: str) -> tuple[np.ndarray, bool]:
    """A map file's values as float64 (rows along y), and whether they are an image's (to be taken
    between low and high) rather than raw .npy values."""
    import os
    ext = os.path.splitext(path)[1].lower()
    if ext in (".png", ".tif", ".tiff"):
        from PIL import Image
        try:
            with Image.open(path) as im:
                im.load()
                mode = im.mode
                if mode not in ("1", "L", "I", "I;16", "I;16L", "I;16B", "I;16N", "F"):
                    raise ConfigError(src, key, path, f"not a grayscale image (mode {mode!r})")
                data = np.asarray(im, dtype=np.float64)
        except ConfigError:
            raise
        except Exception as e:  # noqa: BLE001 - any failure is a bad file
            raise ConfigError(src, key, path, f"cannot read the image: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
        scale = {"1": 1.0, "L": 255.0, "F": 1.0}.get(mode, 65535.0)
        data = data / scale
        image = True
    elif ext in (".npy", ".exr"):
        from ..image import load_heightmap
        try:
            data = load_heightmap(path)
        except ValueError as e:
            why = str(e).replace(f"height map {str(path)!r} ", "").replace(f" {str(path)!r}", "")
            raise ConfigError(src, key, path, why.replace("height map", "map")) from None
        image = ext == ".exr"
    else:
        raise ConfigError(src, key, path, f"unknown extension {ext!r} (expected .png, .tif, .tiff, .exr or .npy)")
    if data.ndim != 2 or data.size == 0:
        raise ConfigError(src, key, path, f"must be a non-empty 2-D map, got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise ConfigError(src, key, path, "contains NaN or infinite values")
    return data, image


def _file_values(cfg: dict, m: dict, src: str, key: str) -> np.ndarray:
    """A file map's values in [0, 1] at its own pixels (refused in one line otherwise)."""
    data, image = _read_file(m["file"], src, f"{key}.file")
    if image:
        lo, hi = float(data.min()), float(data.max())
        if lo < 0.0 or hi > 1.0:
            raise ConfigError(src, f"{key}.file", m["file"], f"a float image's values must lie in [0, 1] "
                              f"(black .. white), found {lo:g} .. {hi:g}")
        data = m["low"] + (m["high"] - m["low"]) * data
    else:
        lo, hi = float(data.min()), float(data.max())
        if lo < 0.0 or hi > 1.0:
            raise ConfigError(src, f"{key}.file", m["file"], f"{m['quantity']} is a fraction: the .npy's values "
                              f"must lie in [0, 1], found {lo:g} .. {hi:g}")
    hy, hx = data.shape
    if m["pixel_um"] is None:
        W, H = (v * 1000.0 for v in cfg["model"]["size_mm"])
        px, py = W / hx, H / hy
        if abs(px - py) > 0.01 * max(px, py):
            raise ConfigError(src, f"{key}.file", m["file"],
                              f"{hx}x{hy} pixels do not have the model's aspect ({W / 1000:g} x {H / 1000:g} mm: "
                              f"pixels {px:g} x {py:g} um); give pixel_um or a map of the model's shape")
    return data


def _resample(data: np.ndarray, px: float, py: float, nx: int, ny: int, dx: float, dy: float) -> np.ndarray:
    """Bilinear values at the column centres of a map of pixels px x py um (pixel centres at
    (i + 0.5) px), edge values beyond it; the map itself where it is the columns' grid."""
    hy, hx = data.shape
    if (hx, hy) == (nx, ny) and math.isclose(px, dx) and math.isclose(py, dy):
        return data.copy()

    def axis(n, d, p, h):
        s = np.clip((np.arange(n) + 0.5) * d / p - 0.5, 0.0, h - 1.0)
        i = np.minimum(np.floor(s).astype(int), max(h - 2, 0))
        return i, np.minimum(i + 1, h - 1), s - i
    x0, x1, fx = axis(nx, dx, px, hx)
    y0, y1, fy = axis(ny, dy, py, hy)
    a, b = data[np.ix_(y0, x0)], data[np.ix_(y0, x1)]
    c, d = data[np.ix_(y1, x0)], data[np.ix_(y1, x1)]
    fx, fy = fx[None, :], fy[:, None]
    top = a + (b - a) * fx                  # lerp form: a uniform map stays exactly uniform
    bot = c + (d - c) * fx
    return np.clip(top + (bot - top) * fy, data.min(), data.max())


def _spots(m: dict, own: float, nx: int, ny: int, dx: float, dy: float) -> np.ndarray:
    """background + sum of (peak - background) exp(-(r / radius)^2) at the column centres
    (separable: one outer product per spot)."""
    bg = own if m["value"] is None else m["value"]
    xs, ys = (np.arange(nx) + 0.5) * dx, (np.arange(ny) + 0.5) * dy
    v = np.full((ny, nx), bg)
    for s in m["spots"]:
        cx, cy = (c * 1000.0 for c in s["center_mm"])
        r = s["radius_um"]
        with np.errstate(over="ignore"):          # far from a narrow spot: exp(-inf) = 0
            v += (s["peak"] - bg) * np.outer(np.exp(-((ys - cy) / r) ** 2), np.exp(-((xs - cx) / r) ** 2))
    return v


def _values(cfg: dict, i: int, src: str, nx: int, ny: int, dx: float, dy: float) -> np.ndarray:
    """Map i's values at the columns (ny, nx), checked to lie in [0, 1]."""
    m = cfg["map"][i]
    key = f"map[{i}]"
    L = next(L for L in cfg["layer"] if L["name"] == m["layer"])
    own = float(L[m["quantity"]])
    if m["kind"] == "constant":
        return np.full((ny, nx), float(m["value"]))
    if m["kind"] == "spots":
        v = _spots(m, own, nx, ny, dx, dy)
        lo, hi = float(v.min()), float(v.max())
        if lo < -1e-12 or hi > 1.0 + 1e-12:
            raise ConfigError(src, f"{key}.spots", m["spots"], f"the spots add up to {m['quantity']} "
                              f"{hi if hi > 1 else lo:g} where they overlap: a fraction must lie in [0, 1]")
        return np.clip(v, 0.0, 1.0)
    data = _file_values(cfg, m, src, key)
    hy, hx = data.shape
    if m["pixel_um"] is None:
        px, py = nx * dx / hx, ny * dy / hy
    else:
        px = py = m["pixel_um"]
    return _resample(data, px, py, nx, ny, dx, dy)


@dataclass
class ColumnMaps:
    """The maps of a scene on their column grid: per mapped layer (ny, nx, 4) float32 columns of
    melanin, blood, blood x saturation, 0; the layers' own values (NL, 3) float32; the basis
    spectra (3, NB) um^-1 of those three quantities."""

    nx: int
    ny: int
    dx: float
    dy: float
    columns: dict                    # layer index -> (ny, nx, 4) float32
    own: np.ndarray                  # (NL, 3) float32
    basis: np.ndarray                # (3, NB) float64, um^-1

    def delta_range(self, L: int) -> tuple[np.ndarray, np.ndarray]:
        """Per quantity the least and greatest column value minus the layer's own (float64 of the
        float32 values the kernel subtracts)."""
        c = self.columns[L][..., :3].reshape(-1, 3).astype(np.float64) - self.own[L].astype(np.float64)
        return c.min(axis=0), c.max(axis=0)

    def mua_range(self, L: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(NB,) each: the greatest and least change of mu_a from the layer's own over its
        columns, as the kernel bounds them from the per-quantity extremes, and their rounding pad
        (maps.h: dmax = max(top, 0) + pad, dmin = bottom - pad)."""
        lo, hi = self.delta_range(L)
        k = self.basis
        top = np.sum(np.where(k >= 0, hi[:, None], lo[:, None]) * k, axis=0)
        bottom = np.sum(np.where(k >= 0, lo[:, None], hi[:, None]) * k, axis=0)
        pad = 1e-5 * np.sum(np.maximum(np.abs(lo), np.abs(hi))[:, None] * np.abs(k), axis=0)
        return top, bottom, pad


def basis(wl: np.ndarray) -> np.ndarray:
    """(3, NB) um^-1: mu_a per unit melanin, blood (deoxygenated) and blood x saturation
    (oxygenated minus deoxygenated), the layers' spectra (skin.optics)."""
    d0 = spectra.mua_blood(wl, 0.0)
    return np.stack([spectra.mua_melanosome(wl), d0, spectra.mua_blood(wl, 1.0) - d0]) * 1e-4


def build(cfg: dict, wl: np.ndarray, src: str = "<config>") -> ColumnMaps | None:
    """The scene's :class:`ColumnMaps` (None without [[map]] tables)."""
    if not cfg.get("map"):
        return None
    nx, ny, dx, dy = grid(cfg)
    names = [L["name"] for L in cfg["layer"]]
    own64 = np.array([[L["melanin"], L["blood"], L["blood"] * L["saturation"]] for L in cfg["layer"]], float)
    per_layer: dict[int, dict[str, np.ndarray]] = {}
    for i, m in enumerate(cfg["map"]):
        per_layer.setdefault(names.index(m["layer"]), {})[m["quantity"]] = _values(cfg, i, src, nx, ny, dx, dy)
    cols = {}
    for L, q in sorted(per_layer.items()):
        lay = cfg["layer"][L]
        mel = q.get("melanin", lay["melanin"])
        blood = q.get("blood", lay["blood"])
        sat = q.get("saturation", lay["saturation"])
        a = np.zeros((ny, nx, COLS), np.float32)
        a[..., 0] = mel
        a[..., 1] = blood
        a[..., 2] = np.asarray(blood, float) * np.asarray(sat, float)
        cols[L] = a
    return ColumnMaps(nx=nx, ny=ny, dx=dx, dy=dy, columns=cols, own=own64.astype(np.float32), basis=basis(wl))


def device_rows(cm: ColumnMaps, mua: np.ndarray, mus: np.ndarray) -> np.ndarray:
    """float4 rows after the materials' and inclusions' rows of the kernels' optics buffer
    (kernels/maps.h): the grid; per layer its own values and where its columns start (-1: not
    mapped, as int bits); per layer and band (majorant, mu_a/majorant, 1/majorant, dmax),
    (mu_s, the three basis values) and (dmin, 0, 0, 0); then the mapped layers' columns.  ``mua``, ``mus``: the
    layers' (NL, NB), um^-1."""
    nl, nb = mua.shape
    head = np.zeros((1 + nl + 3 * nl * nb, 4), np.float32)
    iv = head.view(np.int32)
    head[0, :2] = cm.dx, cm.dy
    iv[0, 2:] = cm.nx, cm.ny
    head[1:1 + nl, :3] = cm.own
    iv[1:1 + nl, 3] = -1
    band = head[1 + nl:].reshape(nl, nb, 3, 4)
    off, blocks = 0, []
    for L in range(nl):
        dmax, dmin = np.zeros(nb), np.zeros(nb)
        if L in cm.columns:
            iv[1 + L, 3] = off
            off += cm.nx * cm.ny
            blocks.append(cm.columns[L].reshape(-1, 4))
            top, bottom, pad = cm.mua_range(L)
            dmax = np.maximum(top, 0.0) + pad
            dmin = bottom - pad
        maj = mua[L] + mus[L] + dmax          # = the layer's mu_t, exactly, where dmax is 0
        with np.errstate(divide="ignore", invalid="ignore"):
            band[L, :, 0, 0] = maj
            band[L, :, 0, 1] = np.where(maj > 0, mua[L] / np.where(maj > 0, maj, 1.0), 0.0)
            band[L, :, 0, 2] = np.where(maj > 0, 1.0 / np.where(maj > 0, maj, 1.0), 0.0)
        band[L, :, 0, 3] = dmax
        band[L, :, 1, 0] = mus[L]
        band[L, :, 1, 1:] = cm.basis.T
        band[L, :, 2, 0] = dmin
    return np.ascontiguousarray(np.concatenate([head] + blocks), np.float32)
