"""The beam estimator's gather on the device, in one of two layouts.

``render.layout`` chooses how the (eye-ray piece, photon) pairs are found and summed; both
layouts find the same pairs and add the same 64-bit fixed-point term per pair and band, so
they give the same image (byte-identical under PoCL, tests/test_layouts.py):

* ``"gather"``: a work item per pixel and band class walks its eye rays' pieces and queries
  the photon grid (kernels/gather.cl, ``gather_beam``).
* ``"scatter"``: the design card's atomic flux accumulation (kernels/scatter.cl): a grid over
  the eye-ray pieces (each piece filed in every cell its query box overlaps: the cells the
  gather's query would visit), then a work item per stored photon tests the pieces of its own
  cell and adds its terms into per point x band 64-bit fixed-point accumulators with
  ``atom_add`` (order-independent, so deterministic); a finishing kernel per pixel and band
  class then does the gather's per-point float sums in the same point order.  Needs
  ``cl_khr_int64_base_atomics``; without it the gather runs (:func:`choose_layout`).

``"auto"`` (the default) picks per device type by measurement (``bench/gather.py``,
docs/gather.md): :data:`AUTO`.

:class:`BeamGather` is the estimator (:mod:`clppm.integrators.estimators`) a
:class:`clppm.integrators.ppm.Pipeline` holds with ``render.estimator = "beam"``: it owns the
beam's kernels, tables and grid depth, and its layout (:class:`GatherLayout` or
:class:`ScatterLayout`, which owns the scatter's buffers).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..compute.device import check_alloc, kernel_defines, wide_vectors
from .estimators import PassGrid
from ..compute.kernelcall import Kernel

#: render.layout = "auto": the layout per OpenCL device type (bench/gather.py, docs/gather.md).
#: CPU: the gather, faster under PoCL and Intel's runtime (measured).  GPU and others: not
#: measured (no GPU was lent); the gather until a GPU run of bench/gather.py says otherwise.
AUTO = {"cpu": "gather", "gpu": "gather", "accelerator": "gather", "other": "gather"}


def class_tables(vol, gclass: int, hg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gather's per-class tables: hgc[L][g] = three float16 rows (hg's 1 + g^2, 2g,
    (1 - g^2)/(4 pi) of the bands g + gclass k, k < nb / gclass; lanes beyond: 1, 0, 0) and
    mutc[L][g] = mu_t of those bands (lanes beyond: 0); the same float32 values as
    ``hgtab`` and ``optics``, regrouped.  One row per material: the layers, then the
    inclusions (an eye-ray piece inside an inclusion, a photon stored there)."""
    nl, nb = vol.nmat, vol.nb
    nbc = nb // gclass
    hg = np.asarray(hg, np.float32).reshape(nl, nb, 4)
    opt = np.asarray(vol.device_optics()[:nl * nb], np.float32).reshape(nl, nb, 4)
    hgc = np.zeros((nl, gclass, 3, 16), np.float32)
    hgc[:, :, 0, :] = 1.0
    mutc = np.zeros((nl, gclass, 16), np.float32)
    k = min(nbc, 16)
    for g in range(gclass):
        b = g + gclass * np.arange(k)
        hgc[:, g, 0, :k] = hg[:, b, 0]
        hgc[:, g, 1, :k] = hg[:, b, 1]
        hgc[:, g, 2, :k] = hg[:, b, 2]
        mutc[:, g, :k] = opt[:, b, 3]
    return hgc, mutc


def depth_keys(iface: np.ndarray) -> np.ndarray:
    """Per layer L (kernel photon_keys): the mean heights of its top and bottom interface and
    1 where its photons are filed at their layer-conforming depth (an interface of L varies
    and its bottom is finite); row NL: the lowest and highest z of those photons (+-1 um) and
    the largest distance of a key from its photon's z."""
    nl = len(iface) - 1
    out = np.zeros((nl + 1, 4), np.float32)
    lo, hi, shift = np.inf, -np.inf, 0.0
    for L in range(nl):
        top, bot = iface[L], iface[L + 1]
        if not ((top[3] >= 0 or bot[3] >= 0) and bot[1] > -1e29):
            continue
        zt, zb = 0.5 * (top[1] + top[2]), 0.5 * (bot[1] + bot[2])
        out[L] = (zt, zb, 1.0, 0.0)
        th = zt - zb
        kmin, kmax = zt - 1.5 * th, zt + 0.5 * th         # phi clamped to [-1/2, 3/2]
        lo, hi = min(lo, bot[1]), max(hi, top[2])
        shift = max(shift, top[2] - kmin, kmax - bot[1])
    if np.isfinite(lo):
        out[nl] = (lo - 1.0, hi + 1.0, shift + 1.0, 0.0)
    else:
        out[nl] = (1e30, -1e30, 0.0, 0.0)
    return out


def beam_cell_depth(eye) -> float | None:
    """The beam's grid cell depth: the median depth extent of the eye-ray pieces (at least
    1 um).  The disc has no depth, so a piece's query box is its own depth extent (plus the
    waves of a layer-conforming one) and cells as deep as the lateral R/2 (hundreds of um)
    would make every piece of a ray test the same photons: cells about one piece deep cut the
    candidates per pair (bench/gather.py) without changing which pairs are found."""
    if eye.piece_extent is not None:         # the whole image's, over every tile
        return max(eye.piece_extent, 1.0)
    if eye.geo is None or eye.npieces == 0:
        return None
    g = eye.geo.get()[:2 * eye.npieces]
    ext = np.abs(g[0::2]["w"] * g[1::2]["z"])
    return max(float(np.median(ext)), 1.0)


def supports_scatter(dev, nb: int, gclass: int, hero: int) -> str | None:
    """None when the device and the bands allow the scatter layout, else why not."""
    ext = dev.device.extensions.split()
    if "cl_khr_int64_base_atomics" not in ext:
        return "the device has no cl_khr_int64_base_atomics"
    if nb // max(gclass, 1) != 9 or hero != 9:
        return "the scatter layout needs 9 bands per path in classes of 9 (bands_per_path = 9)"
    if not wide_vectors(dev.device):
        return "the device's compiler cannot pass 16-lane vectors between functions (clppm.compute.device.wide_vectors)"
    return None


def device_kind(dev) -> str:
    import pyopencl as cl
    t = dev.device.type
    if t & cl.device_type.GPU:
        return "gpu"
    if t & cl.device_type.CPU:
        return "cpu"
    if t & cl.device_type.ACCELERATOR:
        return "accelerator"
    return "other"


def choose_layout(layout: str, dev, nb: int, gclass: int, hero: int, ninc: int = 0) -> str:
    """The layout a scene's passes use: ``render.layout``, "auto" resolved per device type
    (:data:`AUTO`); "scatter" falls back to "gather" where :func:`supports_scatter` says no."""
    if layout == "auto":
        layout = AUTO.get(device_kind(dev), "gather")
    if layout == "scatter" and supports_scatter(dev, nb, gclass, hero) is not None:
        layout = "gather"
    if layout == "scatter" and ninc:
        layout = "gather"           # kernels/scatter.cl does not see inclusions
    return layout


def _f4():
    import pyopencl.cltypes as cltypes
    return cltypes.float4


@dataclass
class BeamKernels:
    """The beam's kernels in kernels/gather.cl (the pipeline's program)."""

    gather_beam: Kernel
    gather_beam_points: Kernel
    photon_keys: Kernel
    photon_slabs: Kernel
    photon_weights16: Kernel
    piece_slabs: Kernel

    @classmethod
    def of(cls, prg) -> "BeamKernels":
        return cls(**{f.name: Kernel(prg, f.name) for f in fields(cls)})


class BeamGather:
    """The beam estimator: eye-ray pieces gather the photons within a disc around them.

    Owns the beam's kernels, its band-class tables (``hgc``, ``mutc``), the grid's depth keys
    (``vlay``) and cell depth (``hz``), each piece's layer-conforming depth (once per scene) and
    its layout (:attr:`layout`)."""

    dim = 2

    def __init__(self, pipe):
        import pyopencl as cl
        self.pipe = pipe
        sc = pipe
        self.gclass = sc.gclass
        self.hz = beam_cell_depth(sc.eye)
        self.kernels = BeamKernels.of(sc.prg)
        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        self.vlay = cl.Buffer(sc.dev.ctx, ro, hostbuf=depth_keys(sc.vol.iface))
        hgc, mutc = class_tables(sc.vol, self.gclass, sc.vol.hg_table())
        self.hgc = cl.Buffer(sc.dev.ctx, ro, hostbuf=hgc)
        self.mutc = cl.Buffer(sc.dev.ctx, ro, hostbuf=mutc)
        self.pslab = None
        name = choose_layout(sc.rs.layout, sc.dev, sc.vol.nb, self.gclass, sc.pp.hero, sc.vol.ninc)
        self.layout = ScatterLayout(self) if name == "scatter" else GatherLayout(self)

    def defines(self) -> dict:
        sc = self.pipe
        return kernel_defines(sc.vol, hero=sc.pp.hero, estimator=sc.rs.estimator, gclass=self.gclass,
                              vec16=wide_vectors(sc.dev.device))

    # the grid stage -----------------------------------------------------------------------------
    def grid(self, n: int, radii_median: float, rmax: float) -> PassGrid:
        """Photons filed at their depth keys in flat cells ``hz`` deep, in band classes; then
        each sorted photon's layer slab."""
        keys = self.photon_keys(n)
        grid = self.pipe.grid(n, radii_median, rmax, flat=True, key_pos=keys, hz=self.hz, nclass=self.gclass)
        return PassGrid(grid, self.photon_slabs(grid))

    def photon_keys(self, n: int):
        """Per stored photon (unsorted): its grid position with the depth key (kernel photon_keys)."""
        import pyopencl.cltypes as cltypes
        sc = self.pipe
        k = sc.gbufs.get("kpos", max(n, 1), cltypes.float4)
        if n:
            self.kernels.photon_keys(
                sc.dev.queue, n, P=sc.pp.pbuf, iface=sc.vbuf.iface, heights=sc.vbuf.heights, vlay=self.vlay,
                pos_w=sc.pp.pos_w, dir_b=sc.pp.dir_b, n=n, kpos=k)
        return k

    def photon_slabs(self, grid):
        """Per sorted photon: its layer's top and bottom at its column (kernel photon_slabs)."""
        import pyopencl.cltypes as cltypes
        sc = self.pipe
        sl = sc.gbufs.get("sslab", max(grid.n, 1), cltypes.float2)
        if grid.n:
            self.kernels.photon_slabs(
                sc.dev.queue, grid.n, P=sc.pp.pbuf, iface=sc.vbuf.iface, heights=sc.vbuf.heights,
                spos_w=grid.spos_w, sdir_b=grid.sdir_b, n=grid.n, sslab=sl)
        return sl

    # the density estimate -----------------------------------------------------------------------
    def estimate(self, pg: PassGrid, extra, st, acc, alpha: float, scale: float, pass_scale: float) -> None:
        """The layout's gather, then each point's count, radius update and the pixels' pair
        counts (gather_beam_points)."""
        self.layout.run(pg.grid, pg.slabs, extra, st, acc, scale, pass_scale)
        self.points(st, acc, alpha)

    def piece_slabs(self):
        """Per eye-ray piece: its layer-conforming depth (kernel piece_slabs), once per scene."""
        import pyopencl.array as cla
        if self.pslab is None:
            sc = self.pipe
            q, e = sc.dev.queue, sc.eye
            self.pslab = cla.zeros(q, max(e.npieces, 1), _f4())
            if e.npieces:
                self.kernels.piece_slabs(q, e.npieces, P=sc.pp.pbuf, iface=sc.vbuf.iface,
                                         heights=sc.vbuf.heights, geo=e.geo, npieces=e.npieces,
                                         pslab=self.pslab)
        return self.pslab

    def weights16(self, grid, extra):
        """Per sorted photon: its band weights in class order, one float16 (photon_weights16)."""
        sc = self.pipe
        sw = sc.gbufs.get("sw16", max(grid.n, 1) * 16, np.float32)
        if grid.n:
            self.kernels.photon_weights16(sc.dev.queue, grid.n, spos_w=grid.spos_w, sdir_b=grid.sdir_b,
                                          sextra=extra, n=grid.n, sw16=sw)
        return sw

    def points(self, st, acc, alpha: float) -> None:
        sc = self.pipe
        e = sc.eye
        p0, p1 = sc.pixels
        self.kernels.gather_beam_points(
            sc.dev.queue, p1 - p0, start=p0, ray_start=e.ray_start, pt_R=st.R, pt_N=st.N, pt_M=st.M,
            pix_pairs=acc.pairs, npix=p1, acc_base=acc.base, spp=e.camera.spp, alpha=alpha,
            global_radius=int(sc.global_radius))


class GatherLayout:
    """A work item per pixel and band class walks its eye rays' pieces (kernels/gather.cl)."""

    name = "gather"

    def __init__(self, beam: BeamGather):
        self.beam = beam

    def run(self, grid, sslab, extra, st, acc, scale: float, pass_scale: float) -> None:
        bg, sc = self.beam, self.beam.pipe
        q, e = sc.dev.queue, sc.eye
        st.M.fill(0)
        sw = bg.weights16(grid, extra)
        pslab = bg.piece_slabs()             # launched before gather_beam is (the launch order)
        p0, p1 = sc.pixels
        bg.kernels.gather_beam(
            q, p1 - p0, rows=bg.gclass, start=p0, gp=grid.params, P=sc.pp.pbuf, iface=sc.vbuf.iface,
            cell_start=grid.cell_start, spos_w=grid.spos_w, sdir_b=grid.sdir_b,
            sslab=sslab, vlay=bg.vlay, sextra=extra, hgtab=sc.hgtab, optics=sc.vbuf.optics, hgc=bg.hgc,
            mutc=bg.mutc, sw16=sw, pslab=pslab, ray_start=e.ray_start, pt_pos=e.pt_pos,
            pt_piece=e.pt_piece, geo=e.geo, pt_R=st.R, pt_N=st.N, pt_M=st.M, pix_acc=acc.pix,
            npix=p1, acc_base=acc.base, spp=e.camera.spp, global_radius=int(sc.global_radius),
            radius_scale=scale, pass_scale=pass_scale)


class ScatterState:
    """The scatter layout's per-scene state: its kernels, each piece's point and optical depth."""

    def __init__(self, bg: BeamGather):
        import pyopencl.array as cla
        self.pipe = sc = bg.pipe
        q, e = sc.dev.queue, sc.eye
        check_alloc(sc.dev, {"scatter: per point x band sums": max(e.npoints, 1) * sc.vol.nb * 8,
                             "scatter: per piece x band optical depths": max(e.npieces, 1) * sc.vol.nb * 4,
                             "scatter: piece grid entries (estimate)": max(e.npieces, 1) * 4 * 40})
        prg = sc.dev.build("scatter.cl", bg.defines())
        self.k = {n: Kernel(prg, n) for n in ("piece_points", "piece_od", "piece_cells",
                                                  "scatter_beam", "scatter_finish")}
        self.unused = cla.zeros(q, 1, np.uint32)    # scatter_beam's buffers for a benchmark (off)
        npc = max(e.npieces, 1)
        self.piece_pt = cla.zeros(q, npc, np.uint32)
        self.od = cla.zeros(q, npc * sc.vol.nb, np.float32)
        self.pinfo = cla.zeros(q, npc, _f4())
        if e.npoints:
            self.k["piece_points"](q, e.npoints, pt_piece=e.pt_piece, npts=e.npoints,
                                   piece_pt=self.piece_pt)
        if e.nrays and e.npieces:
            self.k["piece_od"](q, e.nrays, rows=bg.gclass, ray_start=e.ray_start,
                               pt_piece=e.pt_piece, geo=e.geo, mutc=bg.mutc, nrays=e.nrays,
                               od=self.od)

    def nbytes(self) -> int:
        return self.piece_pt.nbytes + self.od.nbytes + self.pinfo.nbytes


class ScatterLayout:
    """The atomic flux accumulation layout (kernels/scatter.cl): the piece grid over the
    photon grid's cells, a work item per stored photon adding its pairs' terms into per point
    x band fixed-point sums (atom_add), then the gather's per-point float sums per pixel and
    band class.  Its buffers (:class:`ScatterState`) are made on the first pass."""

    name = "scatter"

    def __init__(self, beam: BeamGather):
        self.beam = beam
        self.state: ScatterState | None = None
        self.entries = 0                 # piece-cell entries of the last pass (bench, tests)

    def scatter_state(self) -> ScatterState:
        if self.state is None:
            self.state = ScatterState(self.beam)
        return self.state

    def run(self, grid, sslab, extra, st, acc, scale: float, pass_scale: float) -> None:
        ss = self.scatter_state()
        sw = self.beam.weights16(grid, extra)
        pstart, plist = self._piece_grid(grid, st, ss, scale)
        self._scatter(grid, sslab, sw, st, acc, ss, pstart, plist, scale, pass_scale)

    def _piece_grid(self, grid, st, ss: ScatterState, scale: float):
        """Each eye-ray piece filed in every photon-grid cell its query box overlaps: counted
        (fill 0), the counts scanned into starts, then filed at each cell's cursor (fill 1)."""
        import pyopencl as cl
        from . import hashgrid
        bg, sc = self.beam, self.beam.pipe
        q, e = sc.dev.queue, sc.eye
        gp = grid.params
        cxyz = int(gp["nx"]) * int(gp["ny"]) * int(gp["nz"])
        npc = e.npieces
        pstart = sc.gbufs.get("pstart", cxyz + 1, np.uint32)
        pstart.fill(0)
        kc = ss.k["piece_cells"]
        common = dict(gp=gp, P=sc.pp.pbuf, iface=sc.vbuf.iface, heights=sc.vbuf.heights, vlay=bg.vlay,
                      geo=e.geo, pslab=bg.piece_slabs(), piece_pt=ss.piece_pt, pt_R=st.R,
                      npieces=npc, global_radius=int(sc.global_radius), radius_scale=scale,
                      pinfo=ss.pinfo)
        plist = sc.gbufs.get("plist", 1, np.uint32)
        if npc:                             # fill 0: count each cell's pieces into pstart
            kc(q, npc, **common, fill=0, cursor=pstart, plist=plist)
        hashgrid.exclusive_scan(sc.dev)(pstart, allocator=sc.gbufs.pool)
        total = int(pstart[cxyz:cxyz + 1].get()[0])
        plist = sc.gbufs.get("plist", max(total, 1), np.uint32)
        cursor = sc.gbufs.get("pcursor", cxyz + 1, np.uint32)
        cl.enqueue_copy(q, cursor.data, pstart.data, byte_count=4 * (cxyz + 1))
        if npc:                             # fill 1: file each piece at its cell's cursor
            kc(q, npc, **common, fill=1, cursor=cursor, plist=plist)
        self.entries = total
        return pstart, plist

    def _scatter(self, grid, sslab, sw, st, acc, ss: ScatterState, pstart, plist, scale: float,
                 pass_scale: float) -> None:
        """A work item per stored photon adds its pairs' terms (scatter_beam), then per pixel
        and band class the per-point float sums (scatter_finish)."""
        bg, sc = self.beam, self.beam.pipe
        q, e = sc.dev.queue, sc.eye
        pacc = sc.gbufs.get("pacc", max(sc.npts, 1) * sc.vol.nb, np.int64)
        if acc.base != 0:
            raise ValueError("the scatter layout writes every pixel: it needs the whole image's sums")
        pacc.fill(0)
        st.M.fill(0)
        if grid.n:
            ss.k["scatter_beam"](
                q, grid.n, gp=grid.params, P=sc.pp.pbuf, cell_start=grid.cell_start, spos_w=grid.spos_w,
                sdir_b=grid.sdir_b, sslab=sslab, sw16=sw, hgc=bg.hgc, mutc=bg.mutc, pstart=pstart,
                plist=plist, pinfo=ss.pinfo, geo=e.geo, piece_pt=ss.piece_pt, od=ss.od, n=grid.n,
                acc=pacc, pt_M=st.M, spots=0, pt_pix=ss.unused, pt_pos=e.pt_pos, pix_max=ss.unused)
        ss.k["scatter_finish"](
            q, sc.npix, rows=bg.gclass, ray_start=e.ray_start, pt_pos=e.pt_pos, pt_R=st.R, acc=pacc,
            pix_acc=acc.pix, npix=sc.npix, spp=e.camera.spp, global_radius=int(sc.global_radius),
            radius_scale=scale, pass_scale=pass_scale)
