"""The tiny test scene shared by the render, checkpoint, determinism and executor tests: a 1 mm
two-layer model (epidermis over dermis), four 50 nm bands, a point light at the upper left and
a 24x16 camera straight above.  Each test sets only its [render] table."""
from __future__ import annotations

import json
import tomllib

_SCENE = """\
[model]
size_mm = [1.0, 1.0]
voxel_um = 5.0
lateral_voxel_um = 10.0
[spectrum]
start_nm = 450.0
stop_nm = 650.0
step_nm = 50.0
[light]
kind = "point"
position_mm = [0.0, 1.0, 2.0]
[camera]
position_mm = [0.5, 0.5, 5.0]
look_at_mm = [0.5, 0.5, 0.0]
fov_deg = 12.0
resolution = [24, 16]
"""

_LAYERS = """\
[[layer]]
name = "epidermis"
thickness_um = 60.0
n = 1.4
melanin = 0.05
[[layer]]
name = "dermis"
thickness_um = inf
n = 1.4
blood = 0.02
"""


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return json.dumps(v) if isinstance(v, str) else repr(v)


def tiny_toml(**render) -> str:
    """The scene as TOML text with ``[render]`` holding ``render``'s items, in order."""
    lines = "".join(f"{k} = {_value(v)}\n" for k, v in render.items())
    return _SCENE + "[render]\n" + lines + _LAYERS


def tiny_dict(**render) -> dict:
    """The same scene as the raw config dict ``tomllib`` reads from ``tiny_toml``."""
    return tomllib.loads(tiny_toml(**render))
