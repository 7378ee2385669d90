"""The codes shared by host and kernels are defined twice: kernels/constants.h for the kernels,
clppm/compute/constants.py for the host.  This test reads the header's ``#define``s and compares them
with the Python names one by one, and checks the photon pass's own copies (its tally enum in
kernels/photon.cl, its storage and category tables in clppm/integrators/photonpass.py) against them.

Reference: the header's text, parsed independently of the host.
"""
from __future__ import annotations

import re
from pathlib import Path

from clppm.compute import constants as C
from clppm.compute.kernelcall import object_macros, strip_comments

KERNELS = Path(__file__).resolve().parents[1] / "kernels"


def header_constants() -> dict[str, int]:
    return {k: int(v) for k, v in object_macros((KERNELS / "constants.h").read_text()).items()
            if re.fullmatch(r"-?\d+", v)}


def test_header_and_module_define_the_same_names_and_values():
    assert header_constants() == C.c_names()


def test_photon_kernel_tally_order_matches():
    src = strip_comments((KERNELS / "photon.cl").read_text())
    m = re.search(r"enum\s*\{([^}]*)\}", src)
    names = [n.split("=")[0].strip() for n in m.group(1).split(",")]
    assert len(names) == len(C.TALLIES) + 1 and names[-1] == "T_ABS0"
    assert names.index("T_RRGAIN") == C.TALLY["rr_gain"]
    assert names.index("T_MISS") == C.TALLY["missed"]
    assert names.index("T_RCONE") == C.TALLY["diffuse_cone"]


def test_photon_pass_tables_match():
    from clppm.scene import light
    from clppm.integrators import photonpass
    assert photonpass.STORAGE == C.STORAGE
    assert tuple(photonpass.CATEGORIES) == C.TALLIES
    assert photonpass.NA == C.TALLY_ABSORBED0
    assert light.SOURCE is C.SOURCE


def test_common_header_includes_the_constants():
    """common.h reaches constants.h through volume.h, the header every other one builds on."""
    assert '#include "volume.h"' in (KERNELS / "common.h").read_text()
    assert '#include "constants.h"' in (KERNELS / "volume.h").read_text()
