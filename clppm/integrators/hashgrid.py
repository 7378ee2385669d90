"""Device photon lookup grid, rebuilt every pass with no host round trip.

A uniform grid of cubic cells (edge ``h`` µm) over a caller-given box
``[lo, hi)``; cells are linearised x-fastest (``c = ix + nx*(iy + ny*iz)``),
a collision-free spatial hash, so a query visits a photon at most once and
needs no per-candidate cell check.  Photons and queries outside the box clamp
to the boundary cells; lookups stay exact because the distance test decides.
The number of cells is capped (``max_cells``): where the box would need more,
``h`` grows.

Build (``method="counting"``, the default -- it is faster, see
``bench/hashgrid.py``): ``grid_count`` puts each photon in its cell with an
``atomic_inc`` histogram and keeps the value ``atomic_inc`` returned (the
photon's rank in its cell); an exclusive scan of the ``ncells+1`` counts
(:class:`pyopencl.scan.ExclusiveScanKernel`) gives the CSR ``cell_start``;
``grid_scatter`` writes index ``i`` to ``perm[cell_start[cell] + rank]`` and
``grid_permute`` gathers the records in that order (scattering a 4-byte index
and gathering was ~40% faster on PoCL than scattering the 32-byte records).  The
order inside a cell is arbitrary, which is fine for an order-independent
(integer fixed-point) accumulation.  ``method="radix"`` sorts (cell, index)
pairs with :class:`pyopencl.algorithm.RadixSort` instead (stable, so the
order inside a cell is the input order) and derives ``cell_start`` from the
sorted keys.

Device side, kernels ``#include "grid.h"``, take a query's cell range from
``grid_query_range`` and loop over its (iy, iz) rows of cells, each one
contiguous photon range (``grid_row_range``); the struct
``GridParams`` there is mirrored by :data:`S.GRID_PARAMS_DTYPE`.

Buffers are kept in a :class:`GridBuffers` cache and reused from pass to pass
while they are large enough.  A :class:`Grid` refers to those buffers, so it is
valid until the next :func:`build` with the same cache.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyopencl.cltypes as cltypes

from ..compute import structs as S
from ..compute.device import Device
from ..compute.kernelcall import kernels

DEFAULT_MAX_CELLS = 2 ** 23


WG = 128  # global sizes are rounded up to this (PoCL picks a work-group size dividing it)


def _cl():
    import pyopencl as cl
    return cl


# --------------------------------------------------------------------------- params

def _cells_for(extent: np.ndarray, h: float) -> np.ndarray:
    return np.maximum(1, np.ceil(extent / h)).astype(np.int64)


def grid_params(lo, hi, h: float, max_cells: int = DEFAULT_MAX_CELLS, hz: float | None = None,
                nclass: int = 1) -> np.void:
    """``GridParams`` (a numpy record of :data:`S.GRID_PARAMS_DTYPE`) for the box
    ``[lo, hi)`` and cell edge ``h`` (µm; cells ``hz`` deep, default ``h``: cubic), ``h``
    and ``hz`` grown by one factor as needed so that ``nx*ny*nz <= max_cells``.  The
    effective sizes are ``params["h"]`` and ``params["hz"]``.  With ``nclass > 1`` the grid
    is that many grids (the photon's class in its key position's ``.w``): ``ncells`` counts
    them all."""
    lo = np.asarray(lo, dtype=np.float64).reshape(3)
    hi = np.asarray(hi, dtype=np.float64).reshape(3)
    h = float(h)
    aspect = 1.0 if hz is None else float(hz) / h if h > 0 else float("nan")
    max_cells = int(max_cells)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"grid box must be finite, got lo={lo}, hi={hi}")
    if not (math.isfinite(h) and h > 0):
        raise ValueError(f"grid cell size must be positive and finite, got {h}")
    if not (math.isfinite(aspect) and aspect > 0):
        raise ValueError(f"grid cell depth must be positive and finite, got {hz}")
    if not 1 <= max_cells <= 2 ** 31 - 1:
        raise ValueError(f"max_cells must be in [1, 2**31-1], got {max_cells}")
    extent = np.maximum(hi - lo, 0.0)

    nclass = int(nclass)
    if not 1 <= nclass <= max_cells:
        raise ValueError(f"grid classes must be in [1, max_cells], got {nclass}")

    def cells(h):
        return _cells_for(extent, np.array([h, h, h * aspect]))

    n = cells(h)
    if int(np.prod(n)) * nclass > max_cells:
        h *= (float(np.prod(n)) * nclass / max_cells) ** (1.0 / 3.0)
        n = cells(h)
        while int(np.prod(n)) * nclass > max_cells:
            h *= 1.01
            n = cells(h)
    rec = np.zeros((), dtype=S.GRID_PARAMS_DTYPE)
    rec["lo_x"], rec["lo_y"], rec["lo_z"] = lo.astype(np.float32)
    h32 = np.float32(h)
    hz32 = h32 if hz is None else np.float32(h * aspect)
    rec["h"], rec["hz"] = h32, hz32
    rec["inv_h"] = np.float32(1.0) / h32
    rec["inv_hz"] = np.float32(1.0) / hz32
    rec["nx"], rec["ny"], rec["nz"] = n
    rec["ncells"] = int(np.prod(n)) * nclass
    rec["nclass"] = nclass
    return rec[()]


def choose_cell_size(radii_sample, lo, hi, max_cells: int = DEFAULT_MAX_CELLS) -> float:
    """Cell edge for a pass: ``median(R) / 2`` unless the cell cap forces larger.

    A query of radius R reads every photon of the cells that overlap the cube
    ``[x-R, x+R]^3``; a segment of length L covers on average ``L/h + 1`` cells,
    so the visited volume is about ``(2R + h)^3`` against the sphere's
    ``4/3 pi R^3``: candidates per true pair ~ ``(2 + h/R)^3 / 4.19``, i.e.
    1.9 (h -> 0), 3.7 (h = R/2), 6.4 (h = R), 15.3 (h = 2R).  Smaller cells
    cost more rows per query (``(2R/h + 1)^2`` contiguous ranges: 25 at
    h = R/2, 81 at R/4), a larger ``cell_start`` to clear and scan every pass,
    and little further saving (2.7 candidates per pair at R/4), so R/2 is the
    balance; radii vary per point, hence the median.  ``bench/hashgrid.py``
    measures h = R/2, R, 2R.
    """
    r = np.asarray(radii_sample, dtype=np.float64).ravel()
    r = r[np.isfinite(r) & (r > 0)]
    if r.size == 0:
        raise ValueError("choose_cell_size needs at least one positive finite radius")
    h = 0.5 * float(np.median(r))
    return float(grid_params(lo, hi, h, max_cells)["h"])


# --------------------------------------------------------------------------- buffers

class GridBuffers:
    """Device buffers reused from pass to pass (grown by 1.5x when too small).

    One cache per renderer (or per :class:`Device` via :func:`default_buffers`).
    A :class:`Grid` built with it is valid until the next build with it.
    """

    def __init__(self, dev: Device):
        import pyopencl.tools as cl_tools
        self.dev = dev
        self._arrays: dict[str, object] = {}
        # RadixSort allocates its ping-pong arrays per call: a pool makes that reuse.
        self.pool = cl_tools.MemoryPool(cl_tools.ImmediateAllocator(dev.queue))

    def get(self, name: str, n: int, dtype) -> object:
        """A ``pyopencl.array.Array`` view of ``n`` elements (offset 0) of buffer ``name``."""
        import pyopencl.array as cla
        dtype = np.dtype(dtype)
        a = self._arrays.get(name)
        if a is None or a.dtype != dtype or a.size < n:
            cap = max(int(n), 1)
            if a is not None and a.dtype == dtype:
                cap = max(cap, int(a.size * 1.5))
            a = cla.empty(self.dev.queue, cap, dtype)
            self._arrays[name] = a
        return a[:n]

    def nbytes(self) -> int:
        return sum(a.nbytes for a in self._arrays.values())


_DEFAULT_BUFFERS: dict[int, GridBuffers] = {}


def default_buffers(dev: Device) -> GridBuffers:
    key = id(dev)
    b = _DEFAULT_BUFFERS.get(key)
    if b is None or b.dev is not dev:
        b = _DEFAULT_BUFFERS[key] = GridBuffers(dev)
    return b


# --------------------------------------------------------------------------- programs

GRID_KERNELS = ("grid_count", "grid_scatter", "grid_keys", "grid_permute", "grid_permute_extra",
                "grid_starts_from_keys")


def _kernels(dev: Device) -> dict:
    return kernels(dev, "hashgrid.cl", GRID_KERNELS)


def _make_scan(ctx):
    from pyopencl.scan import ExclusiveScanKernel
    return ExclusiveScanKernel(ctx, np.uint32, "a+b", "0")


def exclusive_scan(dev: Device):
    """The exclusive prefix sum of uint32 (pyopencl ExclusiveScanKernel), one per context."""
    return dev.library("exclusive_scan_uint32", _make_scan)


def _make_radix(ctx):
    from pyopencl.algorithm import RadixSort
    return RadixSort(ctx, "__global uint *keys, __global int *idx", key_expr="keys[i]",
                     sort_arg_names=["keys", "idx"], key_dtype=np.uint32, index_dtype=np.int32)


def _radix(dev: Device):
    return dev.library("radix_sort_uint32_by_int32", _make_radix)


# --------------------------------------------------------------------------- build

@dataclass
class Grid:
    """A built grid: params and device arrays (``pyopencl.array.Array``).

    ``cell_start`` has ``ncells + 1`` entries (CSR, last == n); ``spos_w`` and
    ``sdir_b`` are the ``n`` photon records sorted by cell.  Pass ``params`` by
    value to kernels (the ``GridParams`` struct of grid.h).  The arrays' ``.data``
    is a valid buffer even when ``n == 0`` (capacity >= 1), so kernels can be
    launched unconditionally (every row is then empty).
    """

    params: np.void
    n: int
    cell_start: object
    spos_w: object
    sdir_b: object
    method: str = "counting"
    sextra: object = None            # the extra per-photon floats, sorted the same way

    @property
    def ncells(self) -> int:
        return int(self.params["ncells"])

    @property
    def h(self) -> float:
        return float(self.params["h"])

    @property
    def shape(self) -> tuple[int, int, int]:
        p = self.params
        return int(p["nx"]), int(p["ny"]), int(p["nz"])

    @property
    def lo(self) -> np.ndarray:
        p = self.params
        return np.array([p["lo_x"], p["lo_y"], p["lo_z"]], dtype=np.float32)


def as_device(dev: Device, a, n: int, bufs: GridBuffers, name: str):
    """Kernel argument (cl.Buffer) for a float4 photon array given as a
    ``pyopencl.array.Array``, a ``cl.Buffer`` or host data (uploaded: tests)."""
    cl = _cl()
    import pyopencl.array as cla
    if isinstance(a, cla.Array):
        if a.size * a.dtype.itemsize < 16 * n:
            raise ValueError(f"{name} holds fewer than n={n} float4 records")
        return a.data if n else None
    if isinstance(a, cl.MemoryObjectHolder):
        return a
    h = np.ascontiguousarray(np.asarray(a, dtype=np.float32).reshape(-1, 4)[:n])
    if h.shape[0] < n:
        raise ValueError(f"{name} holds fewer than n={n} float4 records")
    if n == 0:
        return None
    d = bufs.get("upload_" + name, n, cltypes.float4)
    cl.enqueue_copy(dev.queue, d.data, h)
    return d.data


def build(dev: Device, pos_w, dir_b, n: int, lo, hi, h: float,
          method: str = "counting", max_cells: int = DEFAULT_MAX_CELLS,
          buffers: GridBuffers | None = None, timings: dict | None = None,
          extra=None, extra_stride: int = 0, hz: float | None = None, key_pos=None,
          nclass: int = 1) -> Grid:
    """Sort ``n`` photons (``pos_w`` = (x, y, z µm, weight), ``dir_b`` = (dx, dy,
    dz, band) float4 device arrays) into a grid over ``[lo, hi)`` with cell edge
    ``h`` (cells ``hz`` deep, default cubic; grown if the box needs more than ``max_cells``
    cells).

    Everything stays on the device; the call enqueues work and returns without
    waiting (the queue is in order).  ``method`` is ``"counting"`` (default:
    histogram with ``atomic_inc`` + exclusive scan + scatter) or ``"radix"``
    (``pyopencl.algorithm.RadixSort`` of (cell, index) pairs).  With a
    ``timings`` dict, the queue is drained after each stage and the stage's
    seconds are added to ``timings[stage]`` (bench only: it serialises).  With ``key_pos``
    (float4 per photon) the cell of photon i is that of ``key_pos[i]`` instead of its position
    (the beam's layer-conforming depth, kernels/gather.cl); the records sorted are still
    ``pos_w`` and ``dir_b``; with ``nclass > 1`` its ``.w`` is the photon's class (a grid
    per class, :func:`grid_params`).
    """
    n = int(n)
    if n < 0 or n > 2 ** 32 - 2:
        raise ValueError(f"photon count out of range: {n}")
    bufs = buffers or default_buffers(dev)
    params = grid_params(lo, hi, h, max_cells, hz, nclass)
    ncells = int(params["ncells"])
    q = dev.queue
    k = _kernels(dev)
    f4 = cltypes.float4
    pos = as_device(dev, pos_w, n, bufs, "pos_w")
    dirb = as_device(dev, dir_b, n, bufs, "dir_b")
    kpos = pos if key_pos is None else as_device(dev, key_pos, n, bufs, "key_pos")
    cell_start = bufs.get("cell_start", ncells + 1, np.uint32)
    spos = bufs.get("spos_w", n, f4)
    sdir = bufs.get("sdir_b", n, f4)
    un = np.uint32(n)
    stage = _Stages(q, timings)
    if n == 0:
        cell_start.fill(0)
        sorted_idx = None
    elif method == "counting":
        sorted_idx = _counting_sort(dev, k, bufs, params, un, kpos, pos, dirb, cell_start, spos, sdir, stage)
    elif method == "radix":
        sorted_idx = _radix_sort(dev, k, bufs, params, un, ncells, kpos, pos, dirb, cell_start, spos, sdir, stage)
    else:
        raise ValueError(f"unknown grid build method {method!r} (counting, radix)")
    sextra = None
    if extra is not None and extra_stride > 0:
        sextra = bufs.get("sextra", max(n, 1) * extra_stride, np.float32)
        if n:
            k["grid_permute_extra"](q, n, want=WG, n=n, stride=extra_stride, idx=sorted_idx,
                                    src=extra, dst=sextra)
    return Grid(params=params, n=n, cell_start=cell_start, spos_w=spos, sdir_b=sdir,
                method=method, sextra=sextra)


class _Stages:
    """With a ``timings`` dict: drain the queue after each stage and add its seconds (bench only:
    it serialises); without one, nothing."""

    def __init__(self, q, timings: dict | None):
        self.q, self.timings = q, timings
        self.t = self._now() if timings is not None else 0.0

    def _now(self) -> float:
        import time
        self.q.finish()
        return time.perf_counter()

    def __call__(self, name: str) -> None:
        if self.timings is not None:
            t = self._now()
            self.timings[name] = self.timings.get(name, 0.0) + t - self.t
            self.t = t


def _counting_sort(dev, k, bufs, params, un, kpos, pos, dirb, cell_start, spos, sdir, stage):
    """Histogram with atomic_inc, exclusive scan, scatter, permute; returns the sorted order."""
    q, n = dev.queue, int(un)
    rank = bufs.get("rank", n, np.uint32)
    cell_start.fill(0)
    stage("clear")
    k["grid_count"](q, n, want=WG, gp=params, n=n, pos_w=kpos, counts=cell_start, rank=rank)
    stage("count")
    # in place: counts -> exclusive prefix sums, cell_start[ncells] == n
    exclusive_scan(dev)(cell_start, allocator=bufs.pool)
    stage("scan")
    perm = bufs.get("idx", n, np.int32)
    k["grid_scatter"](q, n, want=WG, gp=params, n=n, pos_w=kpos, cell_start=cell_start,
                      rank=rank, perm=perm)
    stage("scatter")
    k["grid_permute"](q, n, want=WG, n=n, idx=perm, pos_w=pos, dir_b=dirb, spos_w=spos,
                      sdir_b=sdir)
    stage("permute")
    return perm


def _radix_sort(dev, k, bufs, params, un, ncells, kpos, pos, dirb, cell_start, spos, sdir, stage):
    """pyopencl's RadixSort of (cell, index), permute, cell starts; returns the sorted order."""
    q, n = dev.queue, int(un)
    keys = bufs.get("keys", n, np.uint32)
    idx = bufs.get("idx", n, np.int32)
    k["grid_keys"](q, n, want=WG, gp=params, n=n, pos_w=kpos, keys=keys, idx=idx)
    stage("keys")
    key_bits = max(1, (ncells - 1).bit_length())
    (skeys, sidx), _ = _radix(dev)(keys, idx, key_bits=key_bits, queue=q, allocator=bufs.pool)
    stage("sort")
    k["grid_permute"](q, n, want=WG, n=n, idx=sidx, pos_w=pos, dir_b=dirb, spos_w=spos,
                      sdir_b=sdir)
    stage("permute")
    k["grid_starts_from_keys"](q, n + 1, want=WG, n=n, ncells=ncells, skeys=skeys,
                               cell_start=cell_start)
    stage("starts")
    return sidx
