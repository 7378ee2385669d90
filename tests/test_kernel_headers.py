"""Every kernel header includes what it uses: each compiles alone, first in its program, in the
builds it serves (flat, relief on the smooth surfaces), so no header works only because another
came before it.  mnee.h and photon_lanes.h are the exceptions by design: mnee.h is pt.cl's manifold section (its
chains, traces and connection live in pt.cl) and pt.cl includes it in the middle; photon_lanes.h is
photon.cl's pass in SIMD lanes, built on photon.cl's events."""
from __future__ import annotations

import os

import pytest

from clppm.compute.device import kernel_dir

PART_OF = {"mnee.h": "pt.cl", "photon_lanes.h": "photon.cl"}
#: headers of relief builds only (they #error without the smooth surfaces' switches)
RELIEF_ONLY = {"smoothwalk.h"}
BUILDS = {
    "flat": {"NB": 81, "NL": 9, "HERO_C": 9, "FLAT": True},
    "smooth relief": {"NB": 81, "NL": 9, "HERO_C": 9, "SMOOTH_SURFACE": 1, "NVAR": 4,
                      "SMOOTH_CELL": 8, "PT_FP64": False},
}
HEADERS = sorted(f for f in os.listdir(kernel_dir()) if f.endswith(".h") and f not in PART_OF)


def test_every_header_is_listed():
    """A header that is neither compiled alone here nor named a part of a program fails."""
    assert set(HEADERS) | set(PART_OF) == {f for f in os.listdir(kernel_dir()) if f.endswith(".h")}
    assert {"common.h", "volume.h", "surface.h", "smoothwalk.h"} <= set(HEADERS)


@pytest.mark.parametrize("build", BUILDS)
def test_header_compiles_alone(dev, build):
    from clppm.compute.programs import BuildError, BuildSpec, compile_source
    failed = {}
    for h in HEADERS:
        if build == "flat" and h in RELIEF_ONLY:
            continue
        src = f'#include "{h}"\n__kernel void only_{h[:-2]}(__global int* x) {{ x[0] = 1; }}\n'
        try:
            compile_source(dev.ctx, src, BuildSpec.of(f"{h} alone", BUILDS[build]))
        except BuildError as e:
            failed[h] = [ln for ln in str(e).splitlines() if "error" in ln][:2]
    assert not failed, failed


def test_include_lines_are_followed_by_the_program_cache():
    """pyopencl's program cache keys a binary by the headers it finds through include lines that
    hold nothing but the include (its C_INCLUDE_RE); a comment after one hid photon_lanes.h from
    it, and an edited header then ran a stale binary."""
    from pyopencl.cache import C_INCLUDE_RE
    bad = []
    for f in sorted(os.listdir(kernel_dir())):
        if not f.endswith((".h", ".cl")):
            continue
        for n, line in enumerate(open(os.path.join(kernel_dir(), f), encoding="utf-8"), 1):
            if line.lstrip().startswith("#") and "include" in line and '"' in line:
                if not C_INCLUDE_RE.match(line.rstrip("\n").encode()):
                    bad.append(f"{f}:{n}: {line.strip()}")
    assert not bad, bad
