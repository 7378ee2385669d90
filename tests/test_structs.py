"""Each kernel parameter struct is declared twice: a C typedef in kernels/ and the numpy dtype the
host fills.  A size check alone passes two swapped fields of one type, so this test reads every
typedef field by field (name, C type, order, and so offset) and compares it with its dtype.  A
field of a struct type (the ``Camera`` of kernels/camera.h in EyeParams and PtParams) is
expanded into its own fields, on both sides.

Reference: the C declaration itself (the kernels' source text), parsed independently of the host.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

KERNELS = Path(__file__).resolve().parents[1] / "kernels"

C_TYPES = {"float": np.dtype("f4"), "int": np.dtype("i4"), "uint": np.dtype("u4"),
           "unsigned int": np.dtype("u4")}
#: struct types a parameter struct may hold, and the header that declares each
NESTED = {"Camera": "camera.h"}


def _strip_comments(src: str) -> str:
    src = re.sub(r"/\*.*?\*/", " ", src, flags=re.S)
    return re.sub(r"//[^\n]*", " ", src)


def c_struct_fields(filename: str, name: str, kernels: Path = KERNELS) -> list[tuple[str, np.dtype]]:
    """The fields of ``typedef struct { ... } name;`` in kernels/filename, in order."""
    src = _strip_comments((kernels / filename).read_text())
    m = re.search(r"typedef\s+struct\s*\{([^{}]*)\}\s*" + re.escape(name) + r"\s*;", src)
    assert m, f"typedef struct {name} not found in kernels/{filename}"
    body = m.group(1)
    assert "#" not in body, f"{name}: preprocessor lines inside the struct are not mirrored"
    fields = []
    for decl in filter(None, (d.strip() for d in body.split(";"))):
        m1 = re.fullmatch(r"(\w+)\s+([A-Za-z_]\w*)", decl)
        if m1 and m1.group(1) in NESTED:
            sub = c_struct_fields(NESTED[m1.group(1)], m1.group(1), kernels)
            fields += [(f"{m1.group(2)}.{n}", t) for n, t in sub]
            continue
        m2 = re.fullmatch(r"(unsigned int|float|int|uint)\s+(.+)", decl, flags=re.S)
        assert m2, f"{name}: field declaration {decl!r} is not a 4-byte scalar"
        ctype, names = m2.groups()
        for n in names.split(","):
            n = n.strip()
            assert re.fullmatch(r"[A-Za-z_]\w*", n), f"{name}: odd field {n!r}"
            fields.append((n, C_TYPES[ctype]))
    return fields


def flat_fields(dtype: np.dtype, prefix: str = "") -> list[tuple[str, np.dtype, int]]:
    """(name, type, offset) of every scalar field, nested records expanded (``cam.width``)."""
    out = []
    for n in dtype.names:
        t, off = dtype.fields[n][:2]
        if t.names:
            out += [(f"{prefix}{n}.{m}", u, off + o) for m, u, o in flat_fields(t)]
        else:
            out.append((f"{prefix}{n}", t, off))
    return out


def _key(name: str) -> str:
    # `pass` is a Python keyword: the host spells it `pass_`
    return name.rstrip("_")


def _structs():
    from clppm.compute import structs
    return [
        ("volume.h", "Params", structs.PARAMS_DTYPE),
        ("photon.cl", "PhotonLaunch", structs.PHOTON_LAUNCH_DTYPE),
        ("grid.h", "GridParams", structs.GRID_PARAMS_DTYPE),
        ("eye.cl", "EyeParams", structs.EYE_DTYPE),
        ("pt.cl", "PtParams", structs.PT_DTYPE),
    ]


@pytest.mark.parametrize("filename,name", [("volume.h", "Params"), ("photon.cl", "PhotonLaunch"),
                                           ("grid.h", "GridParams"),
                                           ("eye.cl", "EyeParams"), ("pt.cl", "PtParams")])
def test_struct_matches_dtype_field_by_field(filename, name):
    dtype = {n: d for f, n, d in _structs()}[name]
    c = c_struct_fields(filename, name)
    flat = flat_fields(dtype)
    host = [(n, t) for n, t, _ in flat]
    assert [_key(n) for n, _ in c] == [_key(n) for n, _ in host], \
        f"{name}: field names or order differ between kernels/{filename} and the host dtype"
    for (cn, ct), (hn, ht) in zip(c, host):
        assert ct == ht, f"{name}.{cn}: C type {ct} but host dtype {ht}"
    # all fields are 4 bytes wide, so the C offsets are 4*i with no padding
    for i, (n, _, off) in enumerate(flat):
        assert off == 4 * i, f"{name}.{n}: host offset {off}"
    assert dtype.itemsize == 4 * len(c)


def test_parser_catches_a_swapped_pair(tmp_path):
    """The check must fail for two swapped fields of one type (which a size check passes)."""
    src = (KERNELS / "grid.h").read_text().replace("float lo_x, lo_y, lo_z;", "float lo_y, lo_x, lo_z;")
    (tmp_path / "grid.h").write_text(src)
    from clppm.compute import structs
    c = c_struct_fields("grid.h", "GridParams", tmp_path)
    assert [n for n, _ in c] != list(structs.GRID_PARAMS_DTYPE.names)
