"""Kernel launches by name (clppm.compute.kernelcall): the parameter lists read from the kernels' source
(macros expanded), and a call with a missing, extra, misspelt or wrongly typed argument refused
with a message naming it.

Reference: the ``__kernel`` declarations themselves; the checks need no device.
"""
from __future__ import annotations

import numpy as np
import pytest

from clppm.compute import kernelcall as K

cl = pytest.importorskip("pyopencl")


def test_every_kernel_is_read_and_volume_args_expanded():
    sigs = K.all_signatures()
    assert {"eye_pass", "gather", "gather_beam", "pt_pass", "grid_count", "scatter_beam"} <= set(sigs)
    eye = sigs["eye_pass"]
    assert eye.names[:5] == ("P", "iface", "layer_n", "optics", "heights")       # VOLUME_ARGS
    assert eye.names[-1] == "smooth"
    assert [p.kind for p in eye.params[:2]] == ["buffer", "buffer"]
    g = {p.name: p for p in sigs["gather"].params}
    assert (g["gp"].kind, g["npix"].kind, g["pass_scale"].ctype) == ("struct", "scalar", "double")
    assert len(sigs["gather_beam"].params) == 29
    for k in ("gather", "gather_beam", "gather_beam_points"):        # sums of a tile's pixels
        assert sigs[k].names[sigs[k].names.index("npix") + 1] == "acc_base", k


def test_parameter_declarations():
    assert K.parse_param("__global const float4 *pos_w") == K.Param("pos_w", "float4", True)
    assert K.parse_param("volatile __global uint* pt_M") == K.Param("pt_M", "uint", True)
    assert K.parse_param("const unsigned int n") == K.Param("n", "uint", False)
    assert K.parse_param("const float4 light").kind == "vector"


def _sig():
    return K.all_signatures()["grid_permute_extra"]      # n, stride, idx, src, dst


def test_missing_extra_and_misspelt_names_are_named():
    sig = _sig()
    with pytest.raises(K.KernelArgError, match="missing stride"):
        sig.bind(dict(n=1, idx=None, src=None, dst=None))
    with pytest.raises(K.KernelArgError, match="no parameter named strid"):
        sig.bind(dict(n=1, strid=2, stride=1, idx=None, src=None, dst=None))
    with pytest.raises(K.KernelArgError, match=r"missing stride; no parameter named strde"):
        sig.bind(dict(n=1, strde=2, idx=None, src=None, dst=None))


def test_scalars_are_converted_to_the_declared_type():
    p = {q.name: q for q in K.all_signatures()["gather"].params}
    assert type(p["npix"].convert("gather", 7)) is np.int32
    assert type(p["alpha"].convert("gather", 0.7)) is np.float32
    assert p["alpha"].convert("gather", 0.7) == np.float32(0.7)
    assert type(p["pass_scale"].convert("gather", 1)) is np.float64
    n = {q.name: q for q in _sig().params}["n"]
    assert type(n.convert("k", np.int64(3))) is np.uint32
    with pytest.raises(K.KernelArgError, match="'n'.*outside"):
        n.convert("k", -1)
    with pytest.raises(K.KernelArgError, match="'n'.*integer, got float"):
        n.convert("k", 2.5)


def test_buffer_for_scalar_and_scalar_for_buffer_are_refused(dev):
    import pyopencl.array as cla
    ctx = dev.ctx
    buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 16)
    p = {q.name: q for q in _sig().params}
    with pytest.raises(K.KernelArgError, match="'stride'.*got Buffer"):
        p["stride"].convert("grid_permute_extra", buf)
    with pytest.raises(K.KernelArgError, match="'src'.*is a buffer, got int"):
        p["src"].convert("grid_permute_extra", 3)
    a = cla.zeros(dev.queue, 4, np.float32)
    assert p["src"].convert("grid_permute_extra", a) is a.data


def test_a_named_launch_runs(dev):
    import pyopencl.array as cla
    prg = dev.build("hashgrid.cl")
    k = K.Kernel(prg, "grid_permute_extra")
    src = cla.to_device(dev.queue, np.arange(6, dtype=np.float32))
    dst = cla.zeros(dev.queue, 6, np.float32)
    idx = cla.to_device(dev.queue, np.array([2, 0, 1], np.int32))
    k(dev.queue, 3, n=3, stride=2, idx=idx, src=src, dst=dst)
    assert dst.get().tolist() == [4, 5, 0, 1, 2, 3]
