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
  ``cl_khr_int64_base_atomics``; without it the gather runs (:func:`layout`).

``"auto"`` (the default) picks per device type by measurement (``bench/gather.py``,
docs/gather.md): :data:`AUTO`.

The host side of ``clppm.ppm`` calls :func:`run` where the beam gather runs; everything here
keeps its state on the :class:`clppm.ppm.Scene` (attribute ``_beam``).
"""
from __future__ import annotations

import numpy as np

from .device import kernel_defines
from .kernelcall import Kernel

#: render.layout = "auto": the layout per OpenCL device type (bench/gather.py, docs/gather.md).
#: CPU: the gather, faster under PoCL and Intel's runtime (measured).  GPU and others: not
#: measured (no GPU was lent); the gather until a GPU run of bench/gather.py says otherwise.
AUTO = {"cpu": "gather", "gpu": "gather", "accelerator": "gather", "other": "gather"}


def class_tables(vol, gclass: int, hg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gather's per-class tables: hgc[L][g] = three float16 rows (hg's 1 + g^2, 2g,
    (1 - g^2)/(4 pi) of the bands g + gclass k, k < nb / gclass; lanes beyond: 1, 0, 0) and
    mutc[L][g] = mu_t of those bands (lanes beyond: 0); the same float32 values as
    ``hgtab`` and ``optics``, regrouped."""
    nl, nb = vol.nl, vol.nb
    nbc = nb // gclass
    hg = np.asarray(hg, np.float32).reshape(nl, nb, 4)
    opt = np.asarray(vol.optics_table(), np.float32).reshape(nl, nb, 4)
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


class _State:
    """Per scene: the class tables on the device and the scatter layout's buffers."""

    def __init__(self, sc):
        import pyopencl as cl
        from .ppm import hg_table
        mf = cl.mem_flags
        hgc, mutc = class_tables(sc.vol, sc.gclass, hg_table(sc.vol))
        self.hgc = cl.Buffer(sc.dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=hgc)
        self.mutc = cl.Buffer(sc.dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=mutc)
        self.scatter = None
        self.pslab = None

    def piece_slabs(self, sc):
        """Per eye-ray piece: its layer-conforming depth (kernel piece_slabs), once per scene."""
        import pyopencl.array as cla
        if self.pslab is None:
            q, e = sc.dev.queue, sc.eye
            self.pslab = cla.zeros(q, max(e.npieces, 1), _f4())
            if e.npieces:
                prg = sc.dev.build("gather.cl", _defines(sc))
                Kernel(prg, "piece_slabs")(q, e.npieces, P=sc.pp.pbuf, iface=sc.vbuf.iface,
                                           heights=sc.vbuf.heights, geo=e.geo,
                                           npieces=e.npieces, pslab=self.pslab)
        return self.pslab


def state(sc) -> _State:
    s = getattr(sc, "_beam", None)
    if s is None or getattr(s, "gclass", None) != sc.gclass:
        s = _State(sc)
        s.gclass = sc.gclass
        sc._beam = s
    return s


def gather(sc, grid, sslab, extra, st, acc, alpha: float, scale: float, pass_scale: float) -> None:
    """The beam gather: a work item per pixel and band class (kernels/gather.cl), then each
    point's count, radius update and the pixels' pair counts (gather_beam_points)."""
    q, e = sc.dev.queue, sc.eye
    bs = state(sc)
    st.M.fill(0)
    sw = weights16(sc, grid, extra)
    pslab = bs.piece_slabs(sc)           # launched before gather_beam is (the launch order)
    sc.kernels["gather_beam"](
        q, sc.npix, rows=sc.gclass, gp=grid.params, P=sc.pp.pbuf, iface=sc.vbuf.iface,
        heights=sc.vbuf.heights, cell_start=grid.cell_start, spos_w=grid.spos_w, sdir_b=grid.sdir_b,
        sslab=sslab, vlay=sc.vlay, sextra=extra, hgtab=sc.hgtab, optics=sc.vbuf.optics, hgc=bs.hgc,
        mutc=bs.mutc, sw16=sw, pslab=pslab, ray_start=e.ray_start, pt_pos=e.pt_pos,
        pt_piece=e.pt_piece, geo=e.geo, pt_R=st.R, pt_N=st.N, pt_M=st.M, pix_acc=acc.pix,
        npix=sc.npix, spp=e.camera.spp, global_radius=int(sc.global_radius), radius_scale=scale,
        pass_scale=pass_scale)
    points(sc, st, acc, alpha)


def weights16(sc, grid, extra):
    """Per sorted photon: its band weights in class order, one float16 (photon_weights16)."""
    q = sc.dev.queue
    sw = sc.gbufs.get("sw16", max(grid.n, 1) * 16, np.float32)
    k = sc.kernels.get("photon_weights16")
    if k is None:
        prg = sc.dev.build("gather.cl", _defines(sc))
        k = sc.kernels["photon_weights16"] = Kernel(prg, "photon_weights16")
    if grid.n:
        k(q, grid.n, spos_w=grid.spos_w, sdir_b=grid.sdir_b, sextra=extra, n=grid.n, sw16=sw)
    return sw


def _defines(sc) -> dict:
    return kernel_defines(sc.vol, hero=sc.pp.hero, estimator=sc.rs.estimator, gclass=sc.gclass)


def points(sc, st, acc, alpha: float) -> None:
    q, e = sc.dev.queue, sc.eye
    sc.kernels["gather_beam_points"](
        q, sc.npix, ray_start=e.ray_start, pt_R=st.R, pt_N=st.N, pt_M=st.M, pix_pairs=acc.pairs,
        npix=sc.npix, spp=e.camera.spp, alpha=alpha, global_radius=int(sc.global_radius))


def supports_scatter(sc) -> str | None:
    """None when the scene's device and bands allow the scatter layout, else why not."""
    ext = sc.dev.device.extensions.split()
    if "cl_khr_int64_base_atomics" not in ext:
        return "the device has no cl_khr_int64_base_atomics"
    if sc.vol.nb // max(sc.gclass, 1) != 9 or sc.pp.hero != 9:
        return "the scatter layout needs 9 bands per path in classes of 9 (bands_per_path = 9)"
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


def layout(sc) -> str:
    """The layout this scene's passes use: render.layout, "auto" resolved per device type
    (:data:`AUTO`); "scatter" falls back to "gather" where :func:`supports_scatter` says no."""
    lay = sc.rs.layout
    if lay == "auto":
        lay = AUTO.get(device_kind(sc.dev), "gather")
    if lay == "scatter" and supports_scatter(sc) is not None:
        lay = "gather"
    return lay


def run(sc, grid, sslab, extra, st, acc, alpha: float, scale: float, pass_scale: float) -> None:
    """The beam gather of one pass in the scene's layout (:func:`layout`)."""
    if layout(sc) == "scatter":
        scatter(sc, grid, sslab, extra, st, acc, alpha, scale, pass_scale)
    else:
        gather(sc, grid, sslab, extra, st, acc, alpha, scale, pass_scale)


class _Scatter:
    """The scatter layout's per-scene state: its kernels, each piece's point and optical depth."""

    def __init__(self, sc, bs: _State):
        import pyopencl.array as cla
        from .device import check_alloc
        q, e = sc.dev.queue, sc.eye
        check_alloc(sc.dev, {"scatter: per point x band sums": max(e.npoints, 1) * sc.vol.nb * 8,
                             "scatter: per piece x band optical depths": max(e.npieces, 1) * sc.vol.nb * 4,
                             "scatter: piece grid entries (estimate)": max(e.npieces, 1) * 4 * 40})
        prg = sc.dev.build("scatter.cl", _defines(sc))
        self.k = {n: Kernel(prg, n) for n in ("piece_points", "piece_od", "piece_cells",
                                                  "scatter_beam", "scatter_finish",
                                                  "point_pixels")}
        self.spots = None                # bench/studies/spots.py: per pixel the largest pair (float bits)
        self.pt_pix = cla.zeros(q, max(e.npoints, 1), np.uint32)
        npc = max(e.npieces, 1)
        self.piece_pt = cla.zeros(q, npc, np.uint32)
        self.od = cla.zeros(q, npc * sc.vol.nb, np.float32)
        self.pinfo = cla.zeros(q, npc, _f4())
        if e.npoints:
            self.k["piece_points"](q, e.npoints, pt_piece=e.pt_piece, npts=e.npoints,
                                   piece_pt=self.piece_pt)
        if e.nrays and e.npieces:
            self.k["piece_od"](q, e.nrays, rows=sc.gclass, ray_start=e.ray_start,
                               pt_piece=e.pt_piece, geo=e.geo, mutc=bs.mutc, nrays=e.nrays,
                               od=self.od)

    def nbytes(self) -> int:
        return self.piece_pt.nbytes + self.od.nbytes + self.pinfo.nbytes

    def measure_spots(self, sc) -> None:
        """bench/studies/spots.py: from now on each pass records per pixel its largest single pair
        (``self.spots``, float bits; clear it before a pass)."""
        import pyopencl.array as cla
        q, e = sc.dev.queue, sc.eye
        self.k["point_pixels"](q, sc.npix, ray_start=e.ray_start, npix=sc.npix,
                               spp=e.camera.spp, pt_pix=self.pt_pix)
        self.spots = cla.zeros(q, max(sc.npix, 1), np.uint32)


def _f4():
    import pyopencl.cltypes as cltypes
    return cltypes.float4


def scatter_state(sc) -> _Scatter:
    bs = state(sc)
    if bs.scatter is None:
        bs.scatter = _Scatter(sc, bs)
    return bs.scatter


def scatter(sc, grid, sslab, extra, st, acc, alpha: float, scale: float, pass_scale: float) -> None:
    """The atomic flux accumulation layout (kernels/scatter.cl): the piece grid over the
    photon grid's cells, a work item per stored photon adding its pairs' terms into per point
    x band fixed-point sums (atom_add), the gather's per-point float sums per pixel and band
    class, then the points' counts and radius update (gather_beam_points)."""
    import pyopencl as cl
    from . import hashgrid
    q, e = sc.dev.queue, sc.eye
    bs = state(sc)
    ss = scatter_state(sc)
    gp = grid.params
    cxyz = int(gp["nx"]) * int(gp["ny"]) * int(gp["nz"])
    npc = e.npieces
    sw = weights16(sc, grid, extra)
    pstart = sc.gbufs.get("pstart", cxyz + 1, np.uint32)
    pstart.fill(0)
    kc = ss.k["piece_cells"]
    common = dict(gp=gp, P=sc.pp.pbuf, iface=sc.vbuf.iface, heights=sc.vbuf.heights, vlay=sc.vlay,
                  geo=e.geo, pslab=bs.piece_slabs(sc), piece_pt=ss.piece_pt, pt_R=st.R,
                  npieces=npc, global_radius=int(sc.global_radius), radius_scale=scale,
                  pinfo=ss.pinfo)
    plist = sc.gbufs.get("plist", 1, np.uint32)
    if npc:                             # fill 0: count each cell's pieces into pstart
        kc(q, npc, **common, fill=0, cursor=pstart, plist=plist)
    hashgrid._scan(sc.dev)(pstart, allocator=sc.gbufs.pool)
    total = int(pstart[cxyz:cxyz + 1].get()[0])
    plist = sc.gbufs.get("plist", max(total, 1), np.uint32)
    cursor = sc.gbufs.get("pcursor", cxyz + 1, np.uint32)
    cl.enqueue_copy(q, cursor.data, pstart.data, byte_count=4 * (cxyz + 1))
    if npc:                             # fill 1: file each piece at its cell's cursor
        kc(q, npc, **common, fill=1, cursor=cursor, plist=plist)
    pacc = sc.gbufs.get("pacc", max(sc.npts, 1) * sc.vol.nb, np.int64)
    pacc.fill(0)
    st.M.fill(0)
    ks = ss.k["scatter_beam"]
    if grid.n:
        ks(q, grid.n, gp=gp, P=sc.pp.pbuf, cell_start=grid.cell_start, spos_w=grid.spos_w,
           sdir_b=grid.sdir_b, sslab=sslab, sw16=sw, hgc=bs.hgc, mutc=bs.mutc, pstart=pstart,
           plist=plist, pinfo=ss.pinfo, geo=e.geo, piece_pt=ss.piece_pt, od=ss.od, n=grid.n,
           acc=pacc, pt_M=st.M, spots=int(ss.spots is not None), pt_pix=ss.pt_pix, pt_pos=e.pt_pos,
           pix_max=ss.spots if ss.spots is not None else ss.pt_pix)
    kf = ss.k["scatter_finish"]
    kf(q, sc.npix, rows=sc.gclass, ray_start=e.ray_start, pt_pos=e.pt_pos, pt_R=st.R, acc=pacc,
       pix_acc=acc.pix, npix=sc.npix, spp=e.camera.spp, global_radius=int(sc.global_radius),
       radius_scale=scale, pass_scale=pass_scale)
    points(sc, st, acc, alpha)
    bs.entries = total                                     # piece-cell entries (bench)
