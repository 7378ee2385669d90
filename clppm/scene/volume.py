"""The skin volume: layers, surface relief, papillae, interface heights, the smooth surfaces.

The paper's model is a grid of 5 um voxels, each with a layer's optical properties.  A
layered model needs no per-voxel storage: for each interface between layers we keep one
height per lateral voxel column (snapped to the voxel thickness, so voxel membership is
exactly the paper's), and only for interfaces that are not planes.  Optical properties are
one table per layer (NB bands).  Below the last interface the last layer may extend to
infinity, so depth from which no light returns costs nothing.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from . import maps as _maps
from . import skin
from ..compute.structs import LATERAL
from ..config import ConfigError, wavelengths

BIG = 1e30
#: columns a side of the smooth walk's cells (kernels/smoothwalk.h SMOOTH_CELL, from Volume.cell by
#: kernel_defines): 4 measured fastest of 2, 4 and 8 on the forearm
CELL = 4


#: float4 rows of one inclusion after the material rows of the kernels' optics buffer
#: (kernels/inclusion.h): the centre, the diagonal and the off-diagonal of Q, the bounding box
INC_ROWS = 4


@dataclass(frozen=True)
class Inclusion:
    """A region of its own material inside the layers: the points p (um) with
    (p - centre)^T Q (p - centre) < 1.  A vessel of radius r along the unit axis a has
    Q = (I - a a^T) / r^2 (a cylinder, unbounded along a), an ellipsoid of semi-axes s
    Q = diag(1 / s^2).  Its material (mua, mus, g: (NB,), um^-1) comes from its chromophores by
    the layers' spectra; it takes the index of the layer around it (no Fresnel at its surface)."""

    kind: str
    center: np.ndarray              # (3,) um
    Q: np.ndarray                   # (3, 3) um^-2, symmetric
    mua: np.ndarray
    mus: np.ndarray
    g: np.ndarray

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Whether each point of ``p`` (..., 3) um lies inside (the kernels' test, in float64)."""
        w = np.asarray(p, float) - self.center
        return np.einsum("...i,ij,...j->...", w, self.Q, w) < 1.0

    def half_extents(self) -> np.ndarray:
        """(3,) um: how far the region reaches from its centre along x, y and z (BIG where a
        vessel's axis has a component along that axis: unbounded).  An ellipsoid's is
        sqrt((Q^-1)_jj), a vessel's its radius across the axes its axis does not follow."""
        if self.kind == "vessel":
            a = np.linalg.svd(self.Q)[2][-1]             # the axis: Q's null direction
            r = 1.0 / math.sqrt(float(np.max(np.linalg.eigvalsh(self.Q))))
            return np.where(np.abs(a) > 1e-12, BIG, r)
        return np.sqrt(np.diag(np.linalg.inv(self.Q)))

    def z_range(self) -> tuple[float, float]:
        """Lowest and highest z of the region (um; +-BIG for a vessel whose axis is not level)."""
        h = float(self.half_extents()[2])
        return (-BIG, BIG) if h >= BIG else (float(self.center[2]) - h, float(self.center[2]) + h)

    def rows(self) -> np.ndarray:
        """(INC_ROWS, 4) float32: the quadric as kernels/inclusion.h reads it, its bounding box
        (widened by a float32 step or two; +-BIG where unbounded) in the first two rows' w (z)
        and the fourth row (x, y)."""
        q = self.Q
        h = self.half_extents()
        lo, hi = [], []
        for c, e in zip(self.center, h):
            if e >= BIG:
                lo.append(-BIG); hi.append(BIG)
            else:
                pad = 1e-3 + 1e-6 * (abs(c) + e)
                lo.append(c - e - pad); hi.append(c + e + pad)
        return np.array([[*self.center, lo[2]], [q[0, 0], q[1, 1], q[2, 2], hi[2]],
                         [q[0, 1], q[0, 2], q[1, 2], 0.0], [lo[0], hi[0], lo[1], hi[1]]], np.float32)


def inclusion_of(table: dict, index: int, wl: np.ndarray, source: str = "<config>") -> Inclusion:
    """The :class:`Inclusion` of a validated ``[[inclusion]]`` table (config lengths: mm
    laterally, um in depth; the material as a layer's, from the same chromophore spectra)."""
    c = np.array([table["center_mm"][0] * 1000.0, table["center_mm"][1] * 1000.0, -table["depth_um"]])
    if table["kind"] == "vessel":
        a = np.asarray(table["axis"], float)
        a = a / np.linalg.norm(a)
        Q = (np.eye(3) - np.outer(a, a)) / table["radius_um"] ** 2
    else:
        Q = np.diag(1.0 / np.asarray(table["semi_axes_um"], float) ** 2)
    mat = {**{k: table[k] for k in ("melanin", "blood", "saturation", "baseline", "scattering",
                                     "k", "a", "b", "g", "mua", "mus")},
           "name": f"inclusion[{index}]", "thickness_um": 1.0, "n": 1.4, "bottom": "flat"}
    mua, mus, g = layer_optics([mat], wl, source)
    return Inclusion(kind=table["kind"], center=c, Q=Q, mua=mua[0] * 1e-4, mus=mus[0] * 1e-4, g=g[0])


def optics_rows(mua: np.ndarray, mus: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(rows*NB, 4) float32 from (rows, NB) arrays (um^-1): the absorbed fraction of a collision
    mua/mut (0 where mut = 0), g, 1/(2g) (0 where |g| < 1e-4: isotropic), mut in um^-1.  Per
    collision the photon pass then needs one division (in the HG inversion) instead of three."""
    mut = mua + mus
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):     # both branches are evaluated
        afrac = np.where(mut > 0, mua / np.where(mut > 0, mut, 1.0), 0.0)
        inv2g = np.where(np.abs(g) >= 1e-4, 0.5 / np.where(g == 0, 1.0, g), 0.0)
    t = np.stack([afrac, g, inv2g, mut], axis=-1)
    return np.ascontiguousarray(t.reshape(-1, 4), dtype=np.float32)


@dataclass
class Volume:
    wl: np.ndarray                  # band centres, nm
    names: list[str]
    n: np.ndarray                   # (NL,) refractive index
    thickness: np.ndarray           # (NL,) um (inf for a semi-infinite last layer)
    mua: np.ndarray                 # (NL, NB) um^-1
    mus: np.ndarray                 # (NL, NB) um^-1
    g: np.ndarray                   # (NL, NB)
    iface: np.ndarray               # (NL+1, 4) float32: z if flat (else the row's offset), zmin, zmax, row (-1 flat)
    heights: np.ndarray             # (rows, ny, nx) float32 heights the walks step on (iface[k, 3]'s row)
    x0: float = 0.0
    y0: float = 0.0
    dx: float = 5.0
    dy: float = 5.0
    nx: int = 1
    ny: int = 1
    dz: float = 5.0
    lateral: str = "infinite"
    n_above: float = 1.0
    n_below: float = 1.0
    info: dict = field(default_factory=dict)
    # (nvar, ny, nx) float32: the varying interfaces' heights before snapping to the voxel grid,
    # the samples of the smooth surfaces (kernels/surface.h) every pass refracts at and the path
    # tracer's manifold connection solves on (docs/relief.md); None where nothing varies.  On the
    # smooth walk interfaces that differ by a constant share a row (smooth_samples)
    smooth: np.ndarray | None = None
    # model.surface: "voxels" (the passes walk the staircase of columns) or "smooth" (they cross
    # the smooth surfaces themselves: kernels/smoothwalk.h; heights is then smooth)
    surface: str = "voxels"
    # (nvar, nty, ntx, 4) float32, surface = "smooth": per cell of CELL x CELL columns the lowest and
    # highest point and a curvature bound of each smooth surface (smooth_tile_bounds)
    tiles: np.ndarray | None = None
    cell: int = CELL
    # [[inclusion]]: regions of their own material (materials NL .. NL + NINC - 1 of the kernels)
    inclusions: list = field(default_factory=list)
    # [[map]]: per-column chromophores of some layers (clppm.scene.maps.ColumnMaps; kernels/maps.h)
    maps: object | None = None

    @property
    def nl(self) -> int:
        return len(self.names)

    @property
    def nb(self) -> int:
        return len(self.wl)

    @property
    def flat(self) -> bool:
        return bool(np.all(self.iface[:, 3] < 0))

    @property
    def z_top(self) -> float:
        return float(self.iface[0, 2])

    @property
    def mut(self) -> np.ndarray:
        return self.mua + self.mus

    @property
    def ninc(self) -> int:
        return len(self.inclusions)

    @property
    def nmat(self) -> int:
        """Materials: the NL layers, then one per inclusion."""
        return self.nl + self.ninc

    def optics_table(self) -> np.ndarray:
        """(NL*NB, 4) float32: the layers' rows of the kernels' ``optics`` (:func:`optics_rows`)."""
        return optics_rows(self.mua, self.mus, self.g)

    def material_optics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mua, mus, g), (NMAT, NB) um^-1: the layers', then the inclusions'."""
        if not self.inclusions:
            return self.mua, self.mus, self.g
        return tuple(np.concatenate([getattr(self, k), np.stack([getattr(i, k) for i in self.inclusions])])
                     for k in ("mua", "mus", "g"))

    def device_optics(self) -> np.ndarray:
        """The kernels' ``optics`` buffer: (NMAT*NB, 4) material rows, then INC_ROWS rows per
        inclusion (kernels/inclusion.h); the layers' table alone when there is no inclusion, so a
        uniform scene uploads the same bytes as before inclusions existed."""
        if not self.inclusions and self.maps is None:
            return self.optics_table()
        rows = [optics_rows(*self.material_optics())] + [i.rows() for i in self.inclusions]
        if self.maps is not None:              # after them, the maps' rows (kernels/maps.h)
            from .maps import device_rows
            rows.append(device_rows(self.maps, self.mua, self.mus))
        return np.ascontiguousarray(np.concatenate(rows), np.float32)

    def hg_table(self) -> np.ndarray:
        """(NMAT*NB, 4) float32, the gathers' ``hgtab``: per material (the layers, then the
        inclusions) and band 1 + g^2, 2g, (1 - g^2)/(4 pi), so that HG(cos) = h.z (h.x - h.y
        cos)^-3/2.  Without inclusions the layers' rows alone, the bytes they always were."""
        g = self.material_optics()[2].astype(np.float64)
        t = np.stack([1 + g * g, 2 * g, (1 - g * g) / (4 * math.pi), np.zeros_like(g)], -1)
        return np.ascontiguousarray(t.reshape(-1, 4), np.float32)

    @property
    def smooth_walk(self) -> bool:
        """The passes cross the smooth surfaces themselves (model.surface = "smooth", relief)."""
        return self.surface == "smooth" and not self.flat

    def smooth_samples(self, k: int) -> tuple[np.ndarray, float]:
        """Interface k's smooth surface as the kernels evaluate it (surface.h): the Catmull-Rom
        samples (ny, nx) of its row and the height added to them (rows are shared on the smooth
        walk: _pack)."""
        v = int(self.iface[k, 3])
        if v < 0 or self.smooth is None:
            raise ValueError(f"interface {k} is flat")
        return self.smooth[v], float(self.iface[k, 0])

    def device_bytes(self) -> dict[str, int]:
        if self.smooth_walk:          # one buffer: the samples, then the tiles' bounds
            return {"smooth surfaces": int(self.smooth.nbytes) + int(self.tiles.nbytes),
                    "layer optics": int(self.device_optics().nbytes), "interfaces": int(self.iface.nbytes)}
        return {
            "interface heights": int(self.heights.nbytes),
            "smooth surfaces": int(self.smooth.nbytes) if self.smooth is not None else 0,
            "layer optics": int(self.device_optics().nbytes),
            "interfaces": int(self.iface.nbytes),
        }

    def layer_depths(self) -> np.ndarray:
        """Nominal depth of each interface below the surface (um)."""
        return np.concatenate([[0.0], np.cumsum(self.thickness)])


# ----------------------------------------------------------------------------- optics
def layer_optics(layers: list[dict], wl: np.ndarray, source: str = "<config>"):
    """(mua, mus, g) arrays (NL, NB) in cm^-1 from validated layer dicts."""
    mua, mus, g = [], [], []
    for i, L in enumerate(layers):
        if L["mua"] is not None:
            if L["g"] is None:
                raise ConfigError(source, f"layer[{i}].g", None,
                                  "a homogeneous layer (mua, mus) needs g")
            a = np.full(len(wl), L["mua"]); s = np.full(len(wl), L["mus"]); gg = np.full(len(wl), L["g"])
        else:
            lay = skin.Layer(**{k: L[k] for k in (
                "name", "thickness_um", "n", "melanin", "blood", "saturation", "baseline",
                "scattering", "k", "a", "b", "g", "bottom")})
            try:
                a, s, gg = skin.optics(lay, wl)
            except ValueError as e:
                raise ConfigError(source, f"layer[{i}]", L["name"], str(e)) from None
        mua.append(a); mus.append(s); g.append(gg)
    return np.array(mua, float), np.array(mus, float), np.array(g, float)


# ----------------------------------------------------------------------------- relief
def _cell_points(gx, gy, sx, sy, key, ncx, ncy, periodic):
    """The jittered feature point of each grid cell (gx, gy): hashed from the cell index (its
    wrapped index where periodic), so any extent works."""
    hx = gx % ncx if periodic else gx
    hy = gy % ncy if periodic else gy
    h = (hx * 73856093) ^ (hy * 19349663) ^ key
    h = (h * 2654435761) & 0xFFFFFFFF
    jx = (h & 0xFFFF) / 65536.0
    jy = (h >> 16) / 65536.0
    return (gx + 0.1 + 0.8 * jx) * sx, (gy + 0.1 + 0.8 * jy) * sy


def _worley_edges(xs, ys, spacing, seed, period=None):
    """Distance to the nearest edge of a jittered-grid Voronoi diagram ((F2-F1)/2) at the points
    (ys[r], xs[c]), (len(ys), len(xs)).  The feature points are computed once per cell (not
    per point), then each point's 3 x 3 cells are looked up: the same numbers as evaluating
    them per point."""
    rng = np.random.default_rng(seed)
    ncx = max(1, int(round(period[0] / spacing))) if period else None
    ncy = max(1, int(round(period[1] / spacing))) if period else None
    sx = period[0] / ncx if period else spacing
    sy = period[1] / ncy if period else spacing
    cx = np.floor(xs / sx).astype(np.int64)
    cy = np.floor(ys / sy).astype(np.int64)
    key = rng.integers(1, 2**31 - 1)
    gx0, gy0 = int(cx.min()) - 1, int(cy.min()) - 1
    gx = np.arange(gx0, int(cx.max()) + 2, dtype=np.int64)[None, :]
    gy = np.arange(gy0, int(cy.max()) + 2, dtype=np.int64)[:, None]
    gx, gy = np.broadcast_arrays(gx, gy)
    PX, PY = _cell_points(gx, gy, sx, sy, key, ncx, ncy, period is not None)
    shape = (len(ys), len(xs))
    f1, f2 = np.full(shape, np.inf), np.full(shape, np.inf)
    d, closer = np.empty(shape), np.empty(shape, bool)
    # rows of one cell row share their 3 x 3 cells' rows: x - px is one row of numbers for them
    starts = np.flatnonzero(np.diff(cy)) + 1
    for r0, r1 in zip(np.concatenate([[0], starts]), np.concatenate([starts, [len(ys)]])):
        y = ys[r0:r1, None]
        a1, a2, dd, cl = f1[r0:r1], f2[r0:r1], d[r0:r1], closer[r0:r1]
        for ox in (-1, 0, 1):
            ix = cx + ox - gx0
            for oy in (-1, 0, 1):
                iy = int(cy[r0]) + oy - gy0
                dx = xs - PX[iy, ix]
                np.subtract(y, PY[iy, ix][None, :], out=dd)
                np.hypot(dx[None, :], dd, out=dd)
                # f2 = d < f1 ? f1 : min(f2, d); f1 = min(f1, d)
                np.less(dd, a1, out=cl)
                np.minimum(a2, dd, out=a2)
                np.copyto(a2, a1, where=cl)
                np.minimum(a1, dd, out=a1)
    np.subtract(f2, f1, out=f2)
    return np.multiply(0.5, f2, out=f2)


#: rows of columns a relief task makes at once (its arrays stay in the cores' caches)
RELIEF_ROWS = 16


def generated_relief(nx, ny, dx, dy, depth, spacing, width, seed, periodic):
    """Skin-like furrows: primary lines on a Voronoi network plus finer secondary lines.

    Heights in um, 0 on the plateaus, down to about -depth in the primary furrows.
    """
    h = np.zeros((ny, nx))
    xs = (np.arange(nx) + 0.5) * dx
    period = (nx * dx, ny * dy) if periodic else None

    def rows(j0):
        j1 = min(ny, j0 + RELIEF_ROWS)
        y = (np.arange(j0, j1) + 0.5) * dy
        e1 = _worley_edges(xs, y, spacing, seed, period)
        e2 = _worley_edges(xs, y, spacing / 3.0, seed + 1, period)
        h[j0:j1] = -depth * np.exp(-(e1 / (0.5 * width)) ** 2) \
                   - 0.4 * depth * np.exp(-(e2 / (0.4 * width)) ** 2)

    # blocks of rows are independent and numpy releases the GIL on them: one thread per core
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(max_workers=max(1, min(os.cpu_count() or 1, 8))) as ex:
        list(ex.map(rows, range(0, ny, RELIEF_ROWS)))
    return h - h.max()


def file_relief(path, pixel_um, scale_um, nx, ny, dx, dy, periodic):
    from ..image import load_heightmap
    raw = load_heightmap(path) * scale_um
    hy, hx = raw.shape
    xs = (np.arange(nx) + 0.5) * dx / pixel_um - 0.5
    ys = (np.arange(ny) + 0.5) * dy / pixel_um - 0.5
    if periodic:
        xi = np.floor(xs).astype(int); yi = np.floor(ys).astype(int)
        fx = xs - xi; fy = ys - yi
        x0, x1 = xi % hx, (xi + 1) % hx; y0, y1 = yi % hy, (yi + 1) % hy
    else:
        xs = np.clip(xs, 0, hx - 1); ys = np.clip(ys, 0, hy - 1)
        xi = np.minimum(np.floor(xs).astype(int), hx - 2 if hx > 1 else 0)
        yi = np.minimum(np.floor(ys).astype(int), hy - 2 if hy > 1 else 0)
        fx = xs - xi; fy = ys - yi
        x0, x1 = xi, np.minimum(xi + 1, hx - 1); y0, y1 = yi, np.minimum(yi + 1, hy - 1)
    a = raw[np.ix_(y0, x0)]; b = raw[np.ix_(y0, x1)]; c = raw[np.ix_(y1, x0)]; d = raw[np.ix_(y1, x1)]
    fx = fx[None, :]; fy = fy[:, None]
    h = (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy
    return h - h.max()


def papillae(nx, ny, dx, dy, amplitude, period):
    """Wavy dermal-epidermal junction: an egg-crate of dermal papillae (zero mean)."""
    x = (np.arange(nx) + 0.5) * dx
    y = (np.arange(ny) + 0.5) * dy
    return amplitude * np.sin(2 * np.pi * y / period)[:, None] * np.sin(2 * np.pi * x / period)[None, :]


# ----------------------------------------------------------------------------- build
#: the config sections a volume is made of: a volume is kept per their values
GEOMETRY_SECTIONS = ("model", "spectrum", "relief", "papillae", "layer")
_RECENT_MAX = 3
_recent: dict = {}             # the last few volumes built, always
_memo: dict | None = None      # every volume built, while memoised() is active


def geometry_key(cfg: dict) -> str:
    """The key a volume is kept under: its config sections (and its inclusions, when it has
    any), as sorted JSON."""
    secs = GEOMETRY_SECTIONS + tuple(k for k in ("inclusion", "map") if cfg.get(k))
    return json.dumps({k: cfg.get(k) for k in secs}, sort_keys=True, default=str)


def build(cfg: dict, source: str = "<config>") -> Volume:
    """The volume of a config; the last few are kept (the forearm's relief takes seconds), and
    every one while :func:`memoised` is active."""
    key = geometry_key(cfg)
    if _memo is None:
        return _build_recent(key, cfg, source)
    if key not in _memo:
        _memo[key] = _build_recent(key, cfg, source)
    return _memo[key]


def _build_recent(key: str, cfg: dict, source: str) -> Volume:
    if key not in _recent:
        if len(_recent) >= _RECENT_MAX:
            _recent.pop(next(iter(_recent)))
        _recent[key] = _stored(key, cfg, source)
    return _recent[key]


# ----------------------------------------------------------------------------- the volume store
#: volumes of at least this many columns are kept on disk (smaller ones build in milliseconds)
STORE_COLUMNS = 1 << 18
#: volumes kept on disk, at most (the forearm's is about 70 MB)
STORE_MAX = 4
_VOLUME_ARRAYS = ("wl", "n", "thickness", "mua", "mus", "g", "iface", "heights", "smooth", "tiles")
_code_digest: str | None = None


def store_dir() -> str:
    """Where built volumes persist: ``$XDG_CACHE_HOME/clppm/volumes`` (default ``~/.cache``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "clppm", "volumes")


def _storing() -> bool:
    """Volumes are kept unless ``CLPPM_NO_VOLUME_STORE`` is set."""
    return not os.environ.get("CLPPM_NO_VOLUME_STORE")


def _digest(key: str) -> str:
    """The stored volume's name: its geometry and the code that builds it (the scene modules,
    the config's defaults and numpy's version), so a changed builder never reads an old file."""
    global _code_digest
    import hashlib
    if _code_digest is None:
        h = hashlib.sha256(np.__version__.encode())
        here = os.path.dirname(os.path.abspath(__file__))
        data = os.path.join(os.path.dirname(here), "data")
        files = [os.path.join(here, f) for f in sorted(os.listdir(here)) if f.endswith(".py")]
        files += [os.path.join(os.path.dirname(here), "config.py")]
        files += [os.path.join(data, f) for f in sorted(os.listdir(data)) if os.path.isfile(os.path.join(data, f))]
        for f in files:
            with open(f, "rb") as fh:
                h.update(os.path.basename(f).encode() + fh.read())
        _code_digest = h.hexdigest()
    return hashlib.sha256((_code_digest + key).encode()).hexdigest()[:32]


def _stored(key: str, cfg: dict, source: str) -> Volume:
    """The volume of ``cfg``: read from the store when a run built it before (the forearm's
    relief and smooth-surface bounds take seconds to build, tens of milliseconds to read),
    else built (and, when large, stored).  A file that cannot be read is built again."""
    # a height map or a chromophore map may change under its name; the store keeps the geometry's
    # arrays alone (not inclusions or maps)
    if not _storing() or cfg["relief"]["kind"] == "file" or cfg.get("inclusion") or cfg.get("map"):
        return _build(cfg, source)
    path = os.path.join(store_dir(), _digest(key) + ".npz")
    if os.path.exists(path):
        try:
            vol = _read(path)
            os.utime(path)                      # the most recently used are kept
            return vol
        except Exception:                       # damaged or partly written: build it again
            pass
    vol = _build(cfg, source)
    if vol.nx * vol.ny >= STORE_COLUMNS:
        with contextlib.suppress(OSError):
            _write(path, vol)
    return vol


def _write(path: str, vol: Volume) -> None:
    """Store ``vol`` at ``path`` (written aside, then renamed: a reader sees all or nothing),
    then drop all but the STORE_MAX most recently used."""
    import tempfile
    d = os.path.dirname(path)
    os.makedirs(d, exist_ok=True)
    meta = {k: getattr(vol, k) for k in ("names", "x0", "y0", "dx", "dy", "nx", "ny", "dz", "lateral",
                                          "n_above", "n_below", "surface", "cell", "info")}
    arrays = {k: getattr(vol, k) for k in _VOLUME_ARRAYS if getattr(vol, k) is not None}
    fd, tmp = tempfile.mkstemp(dir=d, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), **arrays)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    kept = sorted((e for e in os.scandir(d) if e.name.endswith(".npz")), key=lambda e: e.stat().st_mtime,
                  reverse=True)
    for e in kept[STORE_MAX:]:
        with contextlib.suppress(OSError):
            os.unlink(e.path)


def _read(path: str) -> Volume:
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {k: (z[k] if k in z.files else None) for k in _VOLUME_ARRAYS}
    return Volume(**arrays, **meta)


@contextlib.contextmanager
def memoised():
    """While active, :func:`build` keeps every volume it builds, one per geometry (yields that
    memo; nested uses share the outermost one, which is dropped when it ends).

    Building the forearm volume (2000 x 2000 columns, generated relief) takes 1.5-2 s on 2
    cores of the host and does not depend on the method, the camera or the photon counts; a compare or
    benchmark run renders the same volume a dozen times.  The stage timings of the renders
    exclude it anyway (it is ``seconds['volume']``).
    """
    global _memo
    outer = _memo
    if outer is None:
        _memo = {}
    try:
        yield _memo
    finally:
        _memo = outer


#: a layer thinner than this everywhere (um; after snapping to the voxel grid) is absent: no photon
#: or eye ray can resolve it (1 nm, well below a wavelength and float32's step at skin depths
#: is 1e-4 um), so a tiny thickness is how a layer is switched off (0 is refused)
ABSENT_UM = 1e-3


def absent_layers(z: list) -> list[int]:
    """The layers whose thickness z[k] - z[k+1] is below :data:`ABSENT_UM` in every column."""
    return [k for k in range(len(z) - 1)
            if float(np.max(np.asarray(z[k]) - np.asarray(z[k + 1]))) < ABSENT_UM]


def optical_indices(n: list[float], absent: list[int], n_below: float) -> np.ndarray:
    """Each layer's refractive index as the kernels see it: an absent layer takes the index of the
    first present layer below it (or of the medium below), so light crosses it as if it were not
    there: no Fresnel split at a film of no thickness, and nothing to reflect between (two
    coincident interfaces trapped a photon for up to max_events zero-length steps)."""
    out = np.array(n, float)
    for k in sorted(absent, reverse=True):
        out[k] = out[k + 1] if k + 1 < len(out) else n_below
    return out


def _columns(m: dict, varying: bool, source: str) -> tuple[int, int, float, float]:
    """The lateral grid of the interfaces' heights: columns and their size (um); one column
    when every interface is flat."""
    W, H = m["size_mm"][0] * 1000.0, m["size_mm"][1] * 1000.0
    if not varying:
        return 1, 1, W, H
    dx = dy = m["lateral_voxel_um"]
    nx, ny = max(1, int(round(W / dx))), max(1, int(round(H / dy)))
    if nx * ny > 64_000_000:
        raise ConfigError(source, "model.lateral_voxel_um", dx,
                          f"gives {nx}x{ny} columns; at most 64 million")
    return nx, ny, dx, dy


def _surface(cfg: dict, nx: int, ny: int, dx: float, dy: float, source: str):
    """The surface relief s and the papillae w, (ny, nx) each."""
    rel, pap = cfg["relief"], cfg["papillae"]
    periodic = cfg["model"]["lateral"] == "periodic"
    s = np.zeros((ny, nx))
    if rel["kind"] == "generated":
        s = generated_relief(nx, ny, dx, dy, rel["depth_um"], rel["spacing_um"], rel["width_um"],
                             rel["seed"], periodic)
    elif rel["kind"] == "file":
        try:
            s = file_relief(rel["file"], rel["pixel_um"], rel["height_scale_um"], nx, ny, dx, dy, periodic)
        except ValueError as e:
            raise ConfigError(source, "relief.file", rel["file"], str(e)) from None
    w = papillae(nx, ny, dx, dy, pap["amplitude_um"], pap["period_um"]) if pap["amplitude_um"] > 0 \
        else np.zeros((ny, nx))
    return s, w


def _interfaces(layers: list, depth: np.ndarray, s, w, dz: float, quantize: bool):
    """Each interface's height z (quantized to ``dz`` if asked, layers never overlapping) and
    its smooth height zs (before quantizing)."""
    nl = len(layers)
    # one entry per interface: an (ny, nx) array where it varies, a scalar where it is flat (most
    # of the 10 interfaces: full float64 arrays of them cost seconds at 2000 x 2000 columns);
    # the same float64 operations either way, so the same heights
    z = [s]
    sw = s + w
    for i, L in enumerate(layers):
        base = -depth[i + 1]
        if math.isinf(base):
            z.append(np.float64(-BIG))
            continue
        shape = {"flat": None, "surface": s, "papillae": sw}[L["bottom"]]   # papillae ride on the relief
        z.append(np.float64(base + 0.0) if shape is None else base + shape)
    zs = [z[0]]
    for k in range(1, nl + 1):
        zs.append(_below(z[k], zs[k - 1]))
    if quantize:
        for k in range(nl + 1):
            if np.ndim(z[k]):
                fin = np.abs(z[k]) < BIG / 2
                q = np.round(z[k] / dz) * dz
                z[k] = q if fin.all() else np.where(fin, q, z[k])
            elif abs(z[k]) < BIG / 2:
                z[k] = np.round(z[k] / dz) * dz
    for k in range(1, nl + 1):                     # layers never overlap
        z[k] = _below(z[k], z[k - 1])
    return z, zs


def _below(a, b):
    """np.minimum(a, b), kept a scalar where a is a scalar below every point of b (a flat
    interface under a varying one: the same heights, not a full array of one value)."""
    if np.ndim(a) == 0 and np.ndim(b) and a <= np.min(b):
        return a
    return np.minimum(a, b)



# Catmull-Rom: sample a's weight w_a(f) = sum_j CR[a, j] f^j (kernels/surface.h CR_W)
_CR = 0.5 * np.array([[0, -1, 2, -1], [2, 0, -5, 3], [0, 1, 4, -3], [0, 0, -1, 1]], float)


def _bernstein(deg: int) -> np.ndarray:
    """T with monomial coefficients c -> Bernstein coefficients T @ c (degree deg)."""
    T = np.zeros((deg + 1, deg + 1))
    for i in range(deg + 1):
        for j in range(i + 1):
            T[i, j] = math.comb(i, j) / math.comb(deg, j)
    return T


def _weights_bernstein(order: int) -> np.ndarray:
    """(4, 4 - order): the order-th derivative of each sample's weight, in the Bernstein basis of
    degree 3 - order: Q[a, i] with w_a^(order)(f) = sum_i Q[a, i] B_i(f)."""
    c = _CR.copy()
    for _ in range(order):
        c = c[:, 1:] * np.arange(1, c.shape[1])          # d/df of the monomials
    return c @ _bernstein(3 - order).T


def _wsum(weights, arrays) -> np.ndarray:
    """sum_a weights[a] arrays[a] in that order, skipping zero weights (half of the Catmull-Rom
    samples' Bernstein weights): the same numbers as the full sum up to the sign of a zero."""
    out = tmp = None
    for w, a in zip(weights, arrays):
        if w != 0:
            if out is None:
                out = np.multiply(w, a)
            else:
                tmp = np.multiply(w, a, out=tmp)
                out += tmp
    return out


def _x_pass(pad: np.ndarray, nx: int, ox: int) -> list:
    """The x half of the patches' Bernstein coefficients: per index i of d^ox/dfx^ox, the (rows,
    nx + 1) array R[i][r, p + 1] = sum_a Qx[a, i] pad[r, p + 1 + a] (sample s at pad index s + 2;
    patch p, p = -1 .. nx - 1, lies between the column centres p and p + 1 and uses samples
    p - 1 .. p + 2, repeated (open) or wrapped (periodic) beyond the grid as surface.h hf_index
    does)."""
    Qx = _weights_bernstein(ox)
    return [_wsum(Qx[:, i], [pad[:, a:a + nx + 1] for a in range(4)]) for i in range(Qx.shape[1])]


def _tile_reduce(a: np.ndarray, fn) -> np.ndarray:
    """Per tile, fn (np.maximum / np.minimum) over the patches its columns touch: column c lies
    in patches c - 1 and c, so tile t in patches CELL t - 1 .. CELL t + CELL - 1 (index + 1 in a,
    whose last axes are the (ny + 1, nx + 1) patches)."""
    def axis(a, ax):
        n = a.shape[ax] - 1
        nt = -(-n // CELL)
        a = np.moveaxis(a, ax, 0)
        a = np.concatenate([a, np.repeat(a[-1:], CELL * nt + 1 - a.shape[0], 0)]) if a.shape[0] < CELL * nt + 1 else a
        block = fn.reduce(a[:CELL * nt].reshape((nt, CELL) + a.shape[1:]), axis=1)
        return np.moveaxis(fn(block, a[CELL:CELL * nt + 1:CELL]), 0, ax)
    return axis(axis(a, a.ndim - 1), a.ndim - 2)


#: rows of columns smooth_tile_bounds takes at once (whole cells; its arrays stay in the cores' caches)
TILE_ROWS = 8 * CELL


def smooth_tile_bounds(S: np.ndarray, dx: float, dy: float, periodic: bool) -> np.ndarray:
    """(nty, ntx, 4) float32 for one smooth surface (samples S, (ny, nx)): per tile of CELL x CELL
    columns its lowest and highest point, K >= max |h_xx|, |h_yy| plus max |h_xy| (per um), and
    G >= max |grad h|,
    from the Bernstein coefficients of every Catmull-Rom patch it touches (a polynomial lies
    within the convex hull of its Bernstein coefficients), rounded outwards to float32: what
    kernels/smoothwalk.h's march needs to never pass a crossing."""
    def block(j0):                                              # tile rows in blocks (memory)
        j1 = min(S.shape[0], j0 + TILE_ROWS)
        lo_r, hi_r = max(0, j0 - 2), min(S.shape[0], j1 + 2)    # the rows these patches use
        sub = S[lo_r:hi_r] if not periodic or (lo_r == 0 and hi_r == S.shape[0]) else None
        if sub is None:                                         # periodic: wrap whole rows in
            idx = np.arange(j0 - 2, j1 + 2) % S.shape[0]
            sub, cut = S[idx], 2
        else:
            cut = j0 - lo_r
        # patches q = j0 - 1 .. j1 - 1 of the full grid are rows cut .. cut + j1 - j0 of sub's
        pad = np.pad(sub.astype(np.float64), 2, mode="wrap" if periodic else "edge")
        m = j1 - j0 + 1
        R = {ox: _x_pass(pad, sub.shape[1], ox) for ox in (0, 1, 2)}   # shared by the orders

        def coefficients(ox, oy):
            """The Bernstein coefficients of d^ox/dfx^ox d^oy/dfy^oy h on the block's patches,
            one at a time, so that their extremes are kept without holding them all
            (tests/test_smooth.py checks the bounds, bit for bit, against all at once)."""
            Qy = _weights_bernstein(oy)
            for l in range(Qy.shape[1]):
                for r in R[ox]:
                    yield _wsum(Qy[:, l], [r[cut + b:cut + b + m] for b in range(4)])

        def bound(ox, oy):
            """max |coefficient| of that derivative's patches"""
            acc = None
            for c in coefficients(ox, oy):
                c = np.abs(c, out=c)
                acc = c if acc is None else np.maximum(acc, c, out=acc)
            return acc
        lo = hi = None
        for c in coefficients(0, 0):                            # the height's range: one pass
            lo, hi = (c, c.copy()) if lo is None else (np.minimum(lo, c, out=lo), np.maximum(hi, c, out=hi))
        kxx = bound(2, 0) / (dx * dx)
        kyy = bound(0, 2) / (dy * dy)
        kxy = bound(1, 1) / (dx * dy)
        k = np.maximum(kxx, kyy) + kxy
        g2 = (bound(1, 0) / dx) ** 2 + (bound(0, 1) / dy) ** 2
        return np.stack([_tile_reduce(lo, np.minimum), _tile_reduce(hi, np.maximum), _tile_reduce(k, np.maximum),
                         _tile_reduce(g2, np.maximum)], -1)

    # blocks are independent and numpy releases the GIL on them: one thread per core
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(max_workers=max(1, min(os.cpu_count() or 1, 8))) as ex:
        t = np.concatenate(list(ex.map(block, range(0, S.shape[0], TILE_ROWS))), 0)
    return _outwards(t)


def _outwards(t: np.ndarray) -> np.ndarray:
    """Tile bounds (lo, hi, K, G^2) in float64 to the float32 (lo, hi, K, G) the kernels read,
    rounded outwards with room for the kernels' float32 evaluation where a device has no fp64."""
    res = np.zeros(t.shape[:2] + (4,), np.float32)
    res[..., 3] = np.nextafter((np.sqrt(t[..., 3]) * (1 + 1e-5) + 1e-9).astype(np.float32), np.float32(np.inf))
    res[..., 0] = np.nextafter((t[..., 0] - 1e-4 - 1e-6 * np.abs(t[..., 0])).astype(np.float32), np.float32(-np.inf))
    res[..., 1] = np.nextafter((t[..., 1] + 1e-4 + 1e-6 * np.abs(t[..., 1])).astype(np.float32), np.float32(np.inf))
    res[..., 2] = np.nextafter((t[..., 2] * (1 + 1e-5) + 1e-9).astype(np.float32), np.float32(np.inf))
    return res


def _pack(z: list, zs: list, nx: int, ny: int, share: bool = False):
    """The interfaces as the kernels read them: per interface (height, lo, hi, row of
    ``heights``; row -1 where flat), the rows' heights and smooth heights (float32).

    share (the smooth walk): interfaces whose smooth heights differ by a constant share one row,
    the constant being the interface's height field ``iface[k, 0]`` (kernels/surface.h adds it):
    the forearm's five varying interfaces are the relief and the relief plus the papillae, each
    shifted.  Otherwise every varying interface has its own row and ``iface[k, 0]`` is 0."""
    iface = np.zeros((len(z), 4), np.float32)
    var, svar, shapes = [], [], []
    for k in range(len(z)):
        lo, hi = float(np.min(z[k])), float(np.max(z[k]))
        if hi - lo <= 1e-6:
            iface[k] = (hi, hi, hi, -1)
            continue
        row, c = -1, 0.0
        if share:
            for j, sj in enumerate(shapes):
                d = zs[k] - sj
                if float(np.ptp(d)) <= 1e-7:
                    row, c = j, float(np.float32(d.flat[0]))
                    break
        if row < 0:
            row = len(var)
            shapes.append(np.broadcast_to(zs[k], (ny, nx)))
            var.append(np.broadcast_to(z[k], (ny, nx)).astype(np.float32))
            svar.append(np.broadcast_to(zs[k], (ny, nx)).astype(np.float32))
        iface[k] = (c, lo, hi, row)
    heights = np.stack(var) if var else np.zeros((1, 1, 1), np.float32)
    return iface, heights, svar


def _build(cfg: dict, source: str = "<config>") -> Volume:
    wl = wavelengths(cfg)
    layers = cfg["layer"]
    mua, mus, g = layer_optics(layers, wl, source)
    m = cfg["model"]
    thickness = np.array([L["thickness_um"] for L in layers], float)
    depth = np.concatenate([[0.0], np.cumsum(thickness)])
    varying = cfg["relief"]["kind"] != "flat" or cfg["papillae"]["amplitude_um"] > 0
    dz = m["voxel_um"]
    nx, ny, dx, dy = _columns(m, varying, source)
    s, w = _surface(cfg, nx, ny, dx, dy, source)
    smooth = m["surface"] == "smooth"
    z, zs = _interfaces(layers, depth, s, w, dz, m["quantize"] and not smooth)
    absent = absent_layers(z)
    for k in absent:                               # no sliver of a layer that is not there
        z[k + 1], zs[k + 1] = z[k], zs[k]
    n = optical_indices([L["n"] for L in layers], absent, m["n_below"])
    iface, heights, svar = _pack(z, zs, nx, ny, share=smooth)
    tiles = None
    if smooth and svar:
        periodic = m["lateral"] == "periodic"
        tiles = np.stack([smooth_tile_bounds(a, dx, dy, periodic) for a in svar])
        for k in range(len(z)):                  # the layer cores: clear of every patch
            v, c = int(iface[k, 3]), float(iface[k, 0])
            if v >= 0:
                lo, hi = float(tiles[v, ..., 0].min()) + c, float(tiles[v, ..., 1].max()) + c
                iface[k, 1] = np.nextafter(np.float32(lo), np.float32(-np.inf))
                iface[k, 2] = np.nextafter(np.float32(hi), np.float32(np.inf))
    vol = Volume(wl=wl, names=[L["name"] for L in layers], n=n,
                 thickness=thickness, mua=mua * 1e-4, mus=mus * 1e-4, g=g,
                 iface=iface, heights=np.ascontiguousarray(heights, np.float32),
                 x0=0.0, y0=0.0, dx=dx, dy=dy, nx=nx, ny=ny,
                 dz=dz, lateral=m["lateral"], n_above=m["n_outside"], n_below=m["n_below"],
                 smooth=np.ascontiguousarray(np.stack(svar), np.float32) if svar else None,
                 surface=m["surface"], tiles=tiles,
                 inclusions=[inclusion_of(t, i, wl, source) for i, t in enumerate(cfg.get("inclusion", []))],
                 maps=_maps.build(cfg, wl, source))
    vol.info = {"columns": [nx, ny], "varying_interfaces": int(np.sum(iface[:, 3] >= 0)), "surface_rows": len(svar),
                "absent_layers": [layers[k]["name"] for k in absent],
                "device_bytes": sum(vol.device_bytes().values())}
    return vol


# ----------------------------------------------------------------------------- on the device
def volume_params(p: np.ndarray, vol: Volume) -> None:
    """The volume's fields of the kernels' ``Params`` (common.h)."""
    p["x0"], p["y0"], p["dx"], p["dy"] = vol.x0, vol.y0, vol.dx, vol.dy
    p["xw"], p["yw"] = vol.nx * vol.dx, vol.ny * vol.dy
    p["nx"], p["ny"] = vol.nx, vol.ny
    p["lateral"] = LATERAL[vol.lateral]
    p["n_above"], p["n_below"] = vol.n_above, vol.n_below
    p["z_top"] = vol.z_top


@dataclass
class VolumeBuffers:
    """The volume on the device (shared by the photon and eye passes): ``args()`` are the
    kernels' VOLUME_ARGS (common.h); ``smooth`` (Volume.smooth, one float where nothing varies)
    is the photon and eye passes' last argument."""

    iface: object
    layer_n: object
    optics: object
    heights: object
    smooth: object

    def args(self):
        return [self.iface, self.layer_n, self.optics, self.heights]

    def named(self, P) -> dict:
        """VOLUME_ARGS by name, with ``P`` the kernel's Params buffer (clppm.compute.kernelcall)."""
        return {"P": P, "iface": self.iface, "layer_n": self.layer_n, "optics": self.optics,
                "heights": self.heights}


def upload_volume(dev, vol: Volume) -> VolumeBuffers:
    """The volume's arrays as read-only device buffers (interface heights and the smooth
    surfaces' samples as float32)."""
    import pyopencl as cl
    mf = cl.mem_flags

    def buf(a):
        a = np.ascontiguousarray(a)
        return cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
    iface = vol.iface.copy()
    iface[:, 0] = np.where(np.abs(iface[:, 0]) >= 1e29, -1e30, iface[:, 0])
    if vol.smooth_walk:
        # one buffer for both: the smooth surfaces' samples, then the tiles' bounds (smoothwalk.h)
        packed = buf(np.concatenate([vol.smooth.ravel(), vol.tiles.ravel()]).astype(np.float32))
        return VolumeBuffers(iface=buf(iface.astype(np.float32)), layer_n=buf(vol.n.astype(np.float32)),
                             optics=buf(vol.device_optics()), heights=packed, smooth=packed)
    return VolumeBuffers(iface=buf(iface.astype(np.float32)),
                         layer_n=buf(vol.n.astype(np.float32)),
                         optics=buf(vol.device_optics()),
                         heights=buf(vol.heights.astype(np.float32)),
                         smooth=buf((vol.smooth if vol.smooth is not None else np.zeros(1)).astype(np.float32)))
