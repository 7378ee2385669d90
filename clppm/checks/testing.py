"""Probes of the kernels for the tests, the benchmarks and the self-test: not part of a render.

* Photon-grid queries (kernels/hashgrid.cl): :func:`gather_counts` asks the grid which photons
  lie within a radius of each query point, :func:`gather_bruteforce` asks every photon; the two
  must agree exactly (tests/test_hashgrid.py, and the self-test's tiny scene, clppm/checks/tiny.py).
* The path tracer's light connections (kernels/pt.cl's t_connect and t_mnee):
  :func:`connect_probe` through flat interfaces, :func:`mnee_probe` through relief
  (tests/test_pathtracer.py, tests/test_mnee.py, bench/studies/mnee_solutions.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..compute import structs as S
from ..scene import volume
from ..compute.device import Device
from ..integrators.hashgrid import WG, Grid, GridBuffers, as_device
from ..compute.kernelcall import Kernel, kernels
from ..integrators.pathtracer import MNEE_TRIALS, build, chain_tables, fp64

def _gather_kernels(dev: Device, nb: int) -> dict:
    """kernels/hashgrid.cl's two queries, built for ``nb`` bands."""
    return kernels(dev, "hashgrid.cl", ("gather_grid", "gather_bruteforce"), {"NB": int(nb)})


# --------------------------------------------------------------------------- photon-grid queries

@dataclass
class GatherResult:
    """Per query: ``count`` (uint32), ``wsum`` (int64 fixed point, weight *
    ``wscale`` rounded per photon), ``band`` ((m, nb) int64 fixed point) and,
    for the grid gather, ``ncand`` (photons tested)."""

    count: np.ndarray
    wsum: np.ndarray
    band: np.ndarray
    ncand: np.ndarray | None = None


def _queries(queries, radii) -> np.ndarray:
    x = np.asarray(queries, dtype=np.float32).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radii, dtype=np.float32), (x.shape[0],))
    return np.ascontiguousarray(np.column_stack([x, r]).astype(np.float32))


def _gather(dev: Device, which: str, photons: dict, queries, radii, nb: int,
            wscale: float, with_cand: bool) -> GatherResult:
    import pyopencl.array as cla
    qh = _queries(queries, radii)
    m = qh.shape[0]
    if m == 0:
        e = np.zeros(0, np.int64)
        return GatherResult(np.zeros(0, np.uint32), e, np.zeros((0, nb), np.int64),
                            np.zeros(0, np.uint32) if with_cand else None)
    q = dev.queue
    qd = cla.to_device(q, qh)
    count = cla.empty(q, m, np.uint32)
    wsum = cla.empty(q, m, np.int64)
    band = cla.empty(q, m * nb, np.int64)
    args = dict(photons, m=m, wscale=wscale, queries=qd, count=count, wsum=wsum, band=band)
    if with_cand:
        ncand = args["ncand"] = cla.empty(q, m, np.uint32)
    _gather_kernels(dev, nb)[which](q, m, want=WG, **args)
    res = GatherResult(count.get(), wsum.get(), band.get().reshape(m, nb),
                       ncand.get() if with_cand else None)
    return res


def gather_counts(dev: Device, grid: Grid, queries, radii, nb: int = 1,
                  wscale: float = 2.0 ** 20) -> GatherResult:
    """Grid gather (one work item per query): count, fixed-point weight sum and
    per-band sums of the photons with ``|p - x|^2 < R^2``, and candidates tested."""
    photons = dict(gp=grid.params, cell_start=grid.cell_start, spos_w=grid.spos_w, sdir_b=grid.sdir_b)
    return _gather(dev, "gather_grid", photons, queries, radii, nb, wscale, True)


def gather_bruteforce(dev: Device, pos_w, dir_b, n: int, queries, radii, nb: int = 1,
                      wscale: float = 2.0 ** 20,
                      buffers: GridBuffers | None = None) -> GatherResult:
    """All-pairs reference for :func:`gather_counts` (same distance test, same
    fixed-point conversion): results must agree exactly."""
    n = int(n)
    if n == 0:
        m = _queries(queries, radii).shape[0]
        return GatherResult(np.zeros(m, np.uint32), np.zeros(m, np.int64),
                            np.zeros((m, nb), np.int64))
    bufs = buffers or GridBuffers(dev)
    pos = as_device(dev, pos_w, n, bufs, "bf_pos_w")
    dirb = as_device(dev, dir_b, n, bufs, "bf_dir_b")
    photons = dict(n=n, pos_w=pos, dir_b=dirb)
    return _gather(dev, "gather_bruteforce", photons, queries, radii, nb, wscale, False)


# --------------------------------------------------------------------------- path-tracer connections
class Probe:
    """The test kernels' set-up (t_connect, t_mnee): the volume, the chain tables, n vertices,
    a light, and (n, nout) results plus (n, points, ncol) chain points in the device's real."""

    def __init__(self, dev: Device, vol: volume.Volume, verts, light_um, nout: int, ncol: int):
        import pyopencl as cl
        import pyopencl.cltypes as cltypes
        self.dev, self.prg = dev, build(dev, vol)
        self.real = np.float64 if fp64(dev) else np.float32
        self.vb = volume.upload_volume(dev, vol)
        p = S.new_params()
        volume.volume_params(p, vol)
        self.pbuf, self.chain = self.buffer(p), self.buffer(chain_tables(vol))
        v = np.ascontiguousarray(verts, np.float32)
        self.n = len(v)
        self.out = np.zeros((self.n, nout), self.real)
        self.pts = np.zeros((self.n, 4 * vol.nl + 10, ncol), self.real)
        self.vbuf = self.buffer(v)
        self.obuf = cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE, self.out.nbytes)
        self.qbuf = cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE, self.pts.nbytes)
        self.light = np.array([*light_um, 0.0], np.float32).view(cltypes.float4)[0]

    def buffer(self, a):
        import pyopencl as cl
        return cl.Buffer(self.dev.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)

    def run(self, name: str, **args):
        """Launch ``name`` with the volume, the chain tables, the light, the vertices, both
        outputs and ``args``, and read both outputs back."""
        import pyopencl as cl
        q = self.dev.queue
        Kernel(self.prg, name)(q, self.n, **self.vb.named(self.pbuf), chain=self.chain,
                               light=self.light, n=self.n, verts=self.vbuf, out=self.obuf,
                               pts=self.qbuf, **args)
        cl.enqueue_copy(q, self.out, self.obuf)
        cl.enqueue_copy(q, self.pts, self.qbuf)
        q.finish()
        return self.out, self.pts


def connect_probe(dev: Device, vol: volume.Volume, light_um, verts: np.ndarray, mode: int = 0) -> dict:
    """Run the kernel's connection for vertices ``verts`` (n, 4: x, y, z um, layer) to the light
    at ``light_um``: mode 0 the direct chain, j > 0 reflected once at interface j, -1 sampled.
    Returns p, dOmega/dA_h, the connection factor (band 0), cos theta_L, the selection
    probability, ok, and the chain's points (vertex first, light last)."""
    pr = Probe(dev, vol, verts, light_um, 8, 4)
    out, pts = pr.run("t_connect", mode=mode)
    n = pr.n
    npts = out[:, 6].astype(int)
    return {"p": out[:, 0], "domega_dA": out[:, 1], "factor": out[:, 2], "cos_L": out[:, 3],
            "wsel": out[:, 4], "ok": out[:, 5] > 0,
            "points": [pts[i, :npts[i]] for i in range(n)]}


def mnee_probe(dev: Device, vol: volume.Volume, light_um, verts: np.ndarray, mode: int = 0,
               seeds: np.ndarray | None = None, trials: float = MNEE_TRIALS, salt: int = 0) -> dict:
    """Run the kernel's manifold connection (relief builds) for vertices ``verts`` (n, 4: x, y, z
    um, a layer guess) to the light at ``light_um``; mode as connect_probe.  Returns ok,
    iterations, halvings, G, the factor (band 0), the Fresnel product, cos theta_v, cos theta_a,
    u, wsel, the vertex's layer, the landing error, and the chain's points (n, 8: x, y, z,
    layer, upward normal, 0; vertex first, the light's height last).  ``seeds`` (n, 2): Newton
    on the surfaces from these momenta instead of the flat seed (no continuation).  Without
    seeds also ``all_factor``, ``solutions``, ``trials`` and ``clamped``: one sample of the
    render's connection (specular manifold sampling with ``trials`` random trials on average, random stream
    (vertex index, ``salt``); band 0, isotropic phase function x 4 pi)."""
    assert not vol.flat
    pr = Probe(dev, vol, verts, light_um, 20, 8)
    n = pr.n
    sd = np.ascontiguousarray(seeds if seeds is not None else np.zeros((n, 2)), pr.real)
    out, pts = pr.run("t_mnee", smooth=pr.buffer(vol.smooth.reshape(-1)), mode=mode,
                      use_seeds=int(seeds is not None), seeds=pr.buffer(sd), mnee_trials=trials,
                      salt=salt)
    npts = out[:, 12].astype(int)
    keys = ["ok", "iters", "halvings", "G", "factor", "F", "cos_v", "cos_a", "ux", "uy", "wsel",
            "layer", "npts", "err", "built", "why", "all_factor", "solutions", "trials", "clamped"]
    r = {k: out[:, j] for j, k in enumerate(keys)}
    r["continued"] = r["ok"] >= 2
    r["ok"] = (r["ok"] % 2) > 0
    r["built"] = r["built"] > 0
    r["points"] = [pts[i, :npts[i]] for i in range(n)]
    return r
