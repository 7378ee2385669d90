"""Every parameter struct the kernels read, as the numpy dtype the host fills: one place.

Each mirrors a C typedef field by field (tests/test_structs.py parses the C and compares names,
types, order and offsets): ``Params`` (kernels/common.h: the volume, the light, the photon
pass), ``Camera`` (kernels/camera.h), ``EyeParams`` (eye.cl), ``PtParams`` (pt.cl) and
``GridParams`` (grid.h).  Only 4-byte fields (and the 64-byte Camera inside two of them), in
the C order, so the layouts need no padding rules.
"""
from __future__ import annotations

import numpy as np

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
    ("seed_lo", "u4"), ("seed_hi", "u4"),
    ("store_zmin", "f4"),
    ("rr_threshold", "f4"),
    ("rr_m", "f4"),
    ("max_events", "i4"),
    ("rcone_cos", "f4"),
    ("store_rule", "i4"), ("store_cos", "f4"), ("store_sin", "f4"), ("store_scale", "f4"),
    ("store_qmin", "f4"),
    ("qmc", "i4"),
    ("deep_z0", "f4"), ("deep_dz", "f4"),
]
PARAMS_DTYPE = np.dtype(_FIELDS)
assert PARAMS_DTYPE.itemsize == 4 * len(_FIELDS)

#: one launch of the photon pass (kernels/photon.cl PhotonLaunch, a kernel argument by value)
PHOTON_LAUNCH_DTYPE = np.dtype([
    ("pass_", "u4"), ("photon_offset", "u4"), ("offset_hi", "u4"), ("count", "u4"),
    ("capacity", "u4"), ("qmc_s0", "u4"), ("qmc_s1", "u4"), ("qmc_s2", "u4"),
])

#: the model's open, closed or periodic sides (Params.lateral)
LATERAL = {"infinite": 0, "open": 1, "periodic": 2}


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


#: ``Camera`` (kernels/camera.h), held by EyeParams and PtParams
CAMERA_DTYPE = np.dtype([
    ("cpx", "f4"), ("cpy", "f4"), ("cpz", "f4"),
    ("fx", "f4"), ("fy", "f4"), ("fz", "f4"),
    ("rx", "f4"), ("ry", "f4"), ("rz", "f4"),
    ("ux", "f4"), ("uy", "f4"), ("uz", "f4"),
    ("tan_half", "f4"), ("aspect", "f4"),
    ("width", "i4"), ("height", "i4"),
])

#: ``EyeParams`` (kernels/eye.cl)
EYE_DTYPE = np.dtype([
    ("cam", CAMERA_DTYPE), ("spp", "i4"),
    ("scheme", "i4"), ("spacing", "f4"), ("od_cut", "f4"), ("merge", "i4"),
    ("vox_dx", "f4"), ("vox_dz", "f4"), ("max_points", "i4"), ("max_len", "f4"),
    ("light_kind", "i4"), ("lx", "f4"), ("ly", "f4"), ("lz", "f4"), ("alpha", "f4"),
    ("seed_lo", "u4"), ("seed_hi", "u4"), ("jitter", "i4"),
    ("bx0", "f4"), ("by0", "f4"), ("bx1", "f4"), ("by1", "f4"),
])

#: ``PtParams`` (kernels/pt.cl)
PT_DTYPE = np.dtype([
    ("cam", CAMERA_DTYPE), ("nspp", "i4"), ("pass_", "u4"), ("band0", "u4"), ("pix_offset", "u4"), ("count", "u4"),
    ("seed_lo", "u4"), ("seed_hi", "u4"),
    ("lx", "f4"), ("ly", "f4"), ("lz", "f4"),
    ("alpha", "f4"), ("specular", "i4"),
    ("rr_threshold", "f4"), ("rr_m", "f4"), ("max_vertices", "i4"),
    ("nee_od", "f4"), ("nee_q_floor", "f4"), ("mnee_trials", "f4"),
])

#: ``GridParams`` (kernels/grid.h)
GRID_PARAMS_DTYPE = np.dtype([
    ("lo_x", np.float32), ("lo_y", np.float32), ("lo_z", np.float32),
    ("h", np.float32), ("inv_h", np.float32),
    ("nx", np.int32), ("ny", np.int32), ("nz", np.int32),
    ("ncells", np.uint32),
    ("hz", np.float32), ("inv_hz", np.float32), ("nclass", np.uint32),
])
