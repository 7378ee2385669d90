"""The kernel parameter struct (``Params`` in kernels/common.h) as a numpy dtype.

Only 4-byte fields, in the C order, so the layout needs no padding rules.
"""
from __future__ import annotations

import numpy as np

WG = 64   # fixed work-group size: PoCL compiles a kernel once per work-group size


def global_size(n: int, wg: int = WG) -> int:
    return max(wg, (int(n) + wg - 1) // wg * wg)


def local(kernel, queue, wg: int = WG) -> tuple[int]:
    """Local size for ``kernel``: ``wg``, or the largest power of two below the queried limit."""
    from .device import local_size
    return (local_size(kernel, queue.device, wg),)

_FIELDS = [
    ("x0", "f4"), ("y0", "f4"), ("dx", "f4"), ("dy", "f4"),
    ("xw", "f4"), ("yw", "f4"),
    ("nx", "i4"), ("ny", "i4"),
    ("lateral", "i4"),
    ("n_above", "f4"), ("n_below", "f4"),
    ("z_top", "f4"),
    ("src_kind", "i4"),
    ("sx", "f4"), ("sy", "f4"), ("sz", "f4"),
    ("sdx", "f4"), ("sdy", "f4"), ("sdz", "f4"),
    ("swx", "f4"), ("swy", "f4"),
    ("cone_omc", "f4"),
    ("cax", "f4"), ("cay", "f4"), ("caz", "f4"),
    ("fixed_band", "i4"),
    ("seed_lo", "u4"), ("seed_hi", "u4"), ("pass_", "u4"), ("photon_offset", "u4"),
    ("capacity", "u4"),
    ("store_zmin", "f4"),
    ("rr_threshold", "f4"),
    ("rr_m", "f4"),
    ("max_events", "i4"),
    ("count", "u4"), ("rcone_cos", "f4"), ("offset_hi", "u4"),
    ("store_rule", "i4"), ("store_cos", "f4"), ("store_sin", "f4"), ("store_scale", "f4"),
    ("store_qmin", "f4"),
    ("qmc", "i4"), ("qmc_s0", "u4"), ("qmc_s1", "u4"), ("qmc_s2", "u4"),
]
PARAMS_DTYPE = np.dtype(_FIELDS)
assert PARAMS_DTYPE.itemsize == 4 * len(_FIELDS)

LATERAL = {"infinite": 0, "open": 1, "periodic": 2}
from .light import SOURCE  # noqa: E402  (the kernels' light kinds; one encoding)


def new_params() -> np.ndarray:
    p = np.zeros(1, PARAMS_DTYPE)
    p["fixed_band"] = -1
    p["rr_threshold"] = 1e-4
    p["rr_m"] = 10.0
    p["max_events"] = 1_000_000
    p["store_zmin"] = -3.0e38
    p["rcone_cos"] = 0.98
    p["store_cos"], p["store_sin"], p["store_scale"], p["store_qmin"] = 1.0, 0.0, 1.0, 1.0
    return p


def split_seed(seed: int) -> tuple[int, int]:
    seed = int(seed) & 0xFFFFFFFFFFFFFFFF
    return seed & 0xFFFFFFFF, seed >> 32
