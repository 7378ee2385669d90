"""Progressive photon mapping on the skin volume, as named pieces.

One render is: :func:`setup` (the scene on a device: volume, eye pass, photon and grid
buffers, kernels), :func:`calibrate` (the initial radius and the storage depth, from a photon
pass of its own that never reaches the image), then passes.  A pass (:func:`run_pass`) is a
photon pass, a grid build and a gather; it adds the pass's radiance into an
:class:`Accumulators` and, with the per-point radius, updates the points' R and N.

Passes are grouped in chunks of ``render.chunk_passes``.  A chunk starts from zeroed
accumulators, and chunk sums are added to the total in chunk order, here and in a distributed
run alike (:mod:`clppm.executor`): the float64 sums then round the same way wherever the chunks
ran, so the same seed gives the same bytes.  With ``render.radius = "global"`` (Knaus & Zwicker
2011) pass p's radii are R0 * s(p), a function of p alone, so chunks are independent given the
calibration; with the per-point radius (Hachisuka et al. 2008) each pass needs the R and N that
all earlier passes left, so chunks run in order on one device.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from . import eyepass, hashgrid, photonpass, volume
from .bands import Bands
from .config import RenderSettings, render_settings
from .device import Device, check_alloc, kernel_defines
from .kernelcall import Kernel

#: pass index of the calibration photon pass (its photons set R0 and are then dropped)
CAL_PASS = 0xFFFFFFFF
STAGES = ("photon", "grid", "gather")


def hg_table(vol: volume.Volume) -> np.ndarray:
    """Per layer and band: 1 + g^2, 2g, (1 - g^2)/(4 pi): HG(cos) = h.z (h.x - h.y cos)^-3/2."""
    g = vol.g.astype(np.float64)
    t = np.stack([1 + g * g, 2 * g, (1 - g * g) / (4 * math.pi), np.zeros_like(g)], -1)
    return np.ascontiguousarray(t.reshape(-1, 4), np.float32)


def radius_scale(p: int, alpha: float, dim: int = 3) -> float:
    """Knaus & Zwicker's radius of pass p (0-based) relative to pass 0's:
    r_{i+1}^d = r_i^d (i + alpha)/(i + 1), i = 1, 2, ...  In closed form
    (r_{p+1}/r_1)^d = Gamma(p + 1 + alpha) / (Gamma(1 + alpha) Gamma(p + 2)), evaluated in
    float64 from p alone, so a pass's radii do not depend on which passes ran before it."""
    if p <= 0:
        return 1.0
    ln = math.lgamma(p + 1 + alpha) - math.lgamma(1 + alpha) - math.lgamma(p + 2)
    return math.exp(ln / dim)


@dataclass
class Scene:
    """One scene on one device: what every pass of a render shares."""

    cfg: dict
    rs: RenderSettings               # cfg's [render] table, typed
    dev: Device
    vol: volume.Volume
    vbuf: volume.VolumeBuffers
    eye: eyepass.EyeData
    pp: photonpass.PhotonPass
    kernels: dict
    hgtab: object
    layer_z: object
    vlay: object                     # [NL+1] float4: the beam grid's depth keys (depth_keys)
    gbufs: hashgrid.GridBuffers
    target: int                      # stored photons per pass
    capacity: int
    box: tuple                       # x0, y0, x1, y1, deepest sample point z, top z
    hz: float | None = None          # the beam's grid cell depth (um; None: cubic cells)
    gclass: int = 1                  # the beam gather's band classes (band_classes)
    timing: dict = field(default_factory=lambda: {k: 0.0 for k in STAGES})

    @property
    def npix(self) -> int:
        return self.eye.camera.width * self.eye.camera.height

    @property
    def npts(self) -> int:
        return self.eye.npoints

    @property
    def global_radius(self) -> bool:
        return self.rs.radius == "global"

    @property
    def beam(self) -> bool:
        return self.rs.estimator == "beam"

    @property
    def dim(self) -> int:
        """Dimension of the density estimate's kernel: the radius update's exponent."""
        return 2 if self.beam else 3


@dataclass
class Calibration:
    """What the calibration pass decides for every later pass."""

    R0: np.ndarray                   # (npts,) float32 initial radius per sample point (um)
    store_zmin: float | None         # photons below this z are never gathered (not stored)
    first_search_mean: float | None  # photons the first search finds per point, on average


@dataclass
class Accumulators:
    """Pixel x band radiance sums (float64) and photon-point pair counts, on the device."""

    pix: object
    pairs: object

    @classmethod
    def zeros(cls, sc: Scene) -> "Accumulators":
        import pyopencl.array as cla
        q = sc.dev.queue
        return cls(cla.zeros(q, sc.npix * sc.vol.nb, np.float64), cla.zeros(q, sc.npix, np.uint64))

    def clear(self) -> None:
        self.pix.fill(0)
        self.pairs.fill(0)

    def add(self, other: "Accumulators") -> None:
        self.pix += other.pix
        self.pairs += other.pairs

    def host(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pix.get(), self.pairs.get()


@dataclass
class PointState:
    """Per sample point: R (the radius of the next pass; R0 with the global radius) and N."""

    R: object
    N: object
    M: object                        # photons found in the last pass (statistics, tests)


def device_needs(cfg: dict, vol: volume.Volume, eye_bytes: int, npix: int) -> dict:
    target = int(render_settings(cfg).photons)
    capacity = int(target * 1.2) + 4096
    from .config import bands_per_path
    rec = 32 + 4 * (bands_per_path(cfg) - 1)                   # photon record bytes
    return {"stored photons": capacity * rec, "sorted photons": capacity * (rec + 4),
            "grid cells": 4 * (hashgrid.DEFAULT_MAX_CELLS + 1) * 2,
            "sample points": eye_bytes,
            "pixel accumulators": 2 * (npix * vol.nb * 8 + npix * 8), **vol.device_bytes()}


def setup(cfg: dict, dev: Device, source: str = "<config>") -> Scene:
    """Volume on the device, eye pass, photon and grid buffers, kernels; memory checked first."""
    import pyopencl as cl
    from .camera import from_config
    rc = render_settings(cfg)
    timing = {}
    t0 = time.perf_counter()
    vol = volume.build(cfg, source)
    vbuf = volume.upload_volume(dev, vol)
    timing["volume"] = time.perf_counter() - t0
    cam = from_config(cfg["camera"])
    nrays = cam.width * cam.height * cam.spp
    check_alloc(dev, {**device_needs(cfg, vol, (nrays + 1) * 8 + nrays * 8, cam.width * cam.height)})
    t0 = time.perf_counter()
    eye = eyepass.run(dev, vol, vbuf, cfg, eyepass.scheme(rc.method, rc.spacing_um))
    dev.queue.finish()
    timing["eye"] = time.perf_counter() - t0
    check_alloc(dev, device_needs(cfg, vol, eye.device_bytes(), cam.width * cam.height))
    target = int(rc.photons)
    capacity = int(target * 1.2) + 4096
    pp = photonpass.PhotonPass(dev, vol, cfg, capacity=capacity, vbuf=vbuf, bands=Bands.from_config(cfg))
    pp.set_storage(rc.storage, eye.cone_deg, rc.store_scale, rc.store_min)
    pp.set_emission(rc.emission)
    gclass = band_classes(vol.nb, pp.hero)
    prg = dev.build("gather.cl", kernel_defines(vol, hero=pp.hero, estimator=rc.estimator, gclass=gclass))
    kernels = {k: Kernel(prg, k) for k in ("gather", "gather_beam", "gather_beam_points", "init_radius",
                                              "count_within", "photon_slabs", "photon_keys")}
    mf = cl.mem_flags
    hgtab = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=hg_table(vol))
    lz = np.stack([np.maximum(vol.iface[1:, 1], -1e30), vol.iface[:-1, 2]], -1).astype(np.float32)
    layer_z = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(lz))
    vlay = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=depth_keys(vol.iface))
    zdeep = eye.zmin if eye.npoints else vol.z_top
    box = (vol.x0, vol.y0, vol.x0 + vol.nx * vol.dx, vol.y0 + vol.ny * vol.dy, zdeep, vol.z_top)
    sc = Scene(cfg=cfg, rs=rc, dev=dev, vol=vol, vbuf=vbuf, eye=eye, pp=pp, kernels=kernels, hgtab=hgtab,
               layer_z=layer_z, vlay=vlay, gbufs=hashgrid.GridBuffers(dev), target=target, capacity=capacity,
               box=box, hz=beam_cell_depth(eye) if rc.estimator == "beam" else None, gclass=gclass)
    sc.timing.update(timing)
    return sc


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


def photon_keys(sc: Scene, n: int):
    """Per stored photon (unsorted): its grid position with the depth key (kernel photon_keys)."""
    import pyopencl.cltypes as cltypes
    k = sc.gbufs.get("kpos", max(n, 1), cltypes.float4)
    if n:
        sc.kernels["photon_keys"](
            sc.dev.queue, n, P=sc.pp.pbuf, iface=sc.vbuf.iface, heights=sc.vbuf.heights, vlay=sc.vlay,
            pos_w=sc.pp.pos_w, dir_b=sc.pp.dir_b, n=n, kpos=k)
    return k


def beam_cell_depth(eye: eyepass.EyeData) -> float | None:
    """The beam's grid cell depth: the median depth extent of the eye-ray pieces (at least
    1 um).  The disc has no depth, so a piece's query box is its own depth extent (plus the
    waves of a layer-conforming one) and cells as deep as the lateral R/2 (hundreds of um)
    would make every piece of a ray test the same photons: cells about one piece deep cut the
    candidates per pair (bench/gather.py) without changing which pairs are found."""
    if eye.geo is None or eye.npieces == 0:
        return None
    g = eye.geo.get()[:2 * eye.npieces]
    ext = np.abs(g[0::2]["w"] * g[1::2]["z"])
    return max(float(np.median(ext)), 1.0)


def build_grid(sc: Scene, n: int, radii_median: float, rmax: float, flat: bool = False,
               key_pos=None) -> hashgrid.Grid:
    """Grid over the photons that sample points can reach (the sample points' box padded by
    the largest radius), cells of half the median radius; with ``flat`` (the beam's passes)
    cells ``sc.hz`` deep (not deeper than wide)."""
    x0, y0, x1, y1, zdeep, ztop = sc.box
    pad = rmax * 1.001 + 1.0
    # the discs have no depth: pieces not near horizontal reach only their own depth (and the
    # waves of a conforming layer); photons beyond the box still go to its edge cells
    zpad = pad if not flat or sc.eye.grazing else 1.0 + float(np.max(np.ptp(sc.vol.iface[:, 1:3], 1)))
    lo, hi = (x0 - pad, y0 - pad, zdeep - zpad), (x1 + pad, y1 + pad, ztop + zpad)
    h = hashgrid.choose_cell_size([radii_median], lo, hi)
    hz = min(sc.hz, h) if flat and sc.hz is not None else None
    return hashgrid.build(sc.dev, sc.pp.pos_w, sc.pp.dir_b, n, lo, hi, h, buffers=sc.gbufs,
                          extra=sc.pp.extra, extra_stride=sc.pp.hero - 1, hz=hz, key_pos=key_pos,
                          nclass=sc.gclass if flat else 1)


def photon_slabs(sc: Scene, grid: hashgrid.Grid):
    """Per sorted photon: its layer's top and bottom at its column (kernel photon_slabs)."""
    import pyopencl.cltypes as cltypes
    sl = sc.gbufs.get("sslab", max(grid.n, 1), cltypes.float2)
    if grid.n:
        sc.kernels["photon_slabs"](
            sc.dev.queue, grid.n, P=sc.pp.pbuf, iface=sc.vbuf.iface, heights=sc.vbuf.heights,
            spos_w=grid.spos_w, sdir_b=grid.sdir_b, n=grid.n, sslab=sl)
    return sl


def calibrate(sc: Scene) -> Calibration:
    """The paper's initial radius: the radius at which the first search finds K photons.

    A photon pass of its own (index CAL_PASS) is stored; the radius is estimated per point
    from the grid's cell counts (kernel ``init_radius``), then scaled by one global factor so
    that exact counts on a subsample average K.  Photons deeper than any point's sphere can
    reach are not stored afterwards: they could never be gathered.  The calibration pass
    stores a quarter of a pass's photons and looks for K/4 of them (the same radius, in
    expectation): with importance storage a pass is hundreds of thousands of paths."""
    import pyopencl.array as cla
    q = sc.dev.queue
    npts = sc.npts
    if npts == 0:
        return Calibration(R0=np.zeros(0, np.float32), store_zmin=None, first_search_mean=None)
    frac = 0.25 if sc.target >= 4 * 20_000 else 1.0
    n_cal = int(math.ceil(sc.target * frac))
    K = float(sc.rs.initial_photons) * n_cal / sc.target
    info = sc.pp.run_pass(CAL_PASS, n_cal, tallies=photonpass.Tallies(sc.vol.nb, sc.vol.nl))
    n = min(info["stored"], sc.capacity)
    x0, y0, x1, y1, zdeep, ztop = sc.box
    depth = max(ztop - zdeep, 1.0)
    vbox = (x1 - x0) * (y1 - y0) * (depth + 1.0)
    r_guess = (3 * K * vbox / (4 * math.pi * max(n, 1))) ** (1 / 3)
    r_guess = min(r_guess, 0.5 * max(x1 - x0, y1 - y0))
    rmax = 4.0 * r_guess
    R = cla.zeros(q, npts, np.float32)
    grid = build_grid(sc, n, r_guess, rmax)
    sc.kernels["init_radius"](
        q, npts, gp=grid.params, cell_start=grid.cell_start, pt_pos=sc.eye.pt_pos, pt_R=R,
        npts=npts, K=K, R0=r_guess, Rmax=rmax, iters=4)
    stride = max(1, npts // 20000)
    ns = (npts + stride - 1) // stride
    cnt = cla.zeros(q, ns, np.uint32)
    mean_m = 0.0
    for _ in range(3):
        radii = R.get()
        grid = build_grid(sc, n, float(np.median(radii)), float(radii.max()))
        sc.kernels["count_within"](
            q, ns, gp=grid.params, cell_start=grid.cell_start, spos_w=grid.spos_w, sdir_b=grid.sdir_b,
            pt_pos=sc.eye.pt_pos, pt_dir=sc.eye.pt_dir, pt_R=R, layer_z=sc.layer_z, npts=npts,
            stride=stride, out=cnt)
        mean_m = float(cnt.get().mean())
        if mean_m <= 0 or _ == 2:
            break
        R *= np.float32(min(max((K / mean_m) ** (1 / 3), 0.5), 2.0))
    R0 = R.get()
    # the beam's disc has no depth extent: nothing below the deepest piece is ever gathered,
    # but for the waves of the interfaces it measures depth along (layer-conforming depth)
    iface = sc.vol.iface
    waves = float(np.max(iface[:, 2] - iface[:, 1])) if len(iface) else 0.0
    reach = float(R0.max()) * 1.001 if (not sc.beam or sc.eye.grazing) else waves
    return Calibration(R0=R0, store_zmin=zdeep - reach - 1.0,
                       first_search_mean=mean_m / frac if mean_m > 0 else None)


def point_state(sc: Scene, cal: Calibration) -> PointState:
    import pyopencl.array as cla
    q = sc.dev.queue
    n = max(sc.npts, 1)
    R = cla.zeros(q, n, np.float32)
    if sc.npts:
        R[:sc.npts].set(np.ascontiguousarray(cal.R0, np.float32))
    return PointState(R=R, N=cla.zeros(q, n, np.float32), M=cla.zeros(q, n, np.uint32))


def prepare(sc: Scene, cal: Calibration) -> None:
    """Apply the calibration to the photon pass (storage depth)."""
    if cal.store_zmin is not None:
        sc.pp.p["store_zmin"] = cal.store_zmin


def run_pass(sc: Scene, cal: Calibration, st: PointState, p: int, acc: Accumulators,
             tallies: photonpass.Tallies) -> dict:
    """Photon pass p, grid, gather into ``acc``; returns the pass's counts."""
    q = sc.dev.queue
    rc = sc.rs
    t0 = time.perf_counter()
    info = sc.pp.run_pass(p, sc.target, tallies=tallies)
    n = min(info["stored"], sc.capacity)
    q.finish()
    sc.timing["photon"] += time.perf_counter() - t0
    if sc.npts == 0:
        return info
    t0 = time.perf_counter()
    alpha = float(rc.alpha)
    if sc.global_radius:
        scale = radius_scale(p, alpha, sc.dim)
        med, rmax = float(np.median(cal.R0)) * scale, float(cal.R0.max()) * scale
    else:
        scale = 1.0
        radii = st.R.get()[:sc.npts]
        med, rmax = float(np.median(radii)), float(radii.max())
    keys = photon_keys(sc, n) if sc.beam else None
    grid = build_grid(sc, n, med, rmax, flat=sc.beam, key_pos=keys)
    sslab = photon_slabs(sc, grid) if sc.beam else None
    q.finish()
    sc.timing["grid"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    pass_scale = 1.0 / max(info["emitted"], 1) if sc.global_radius else 1.0
    e = sc.eye
    extra = grid.sextra.data if grid.sextra is not None else sc.pp.extra
    if sc.beam:
        gather_beam(sc, grid, sslab, extra, st, acc, alpha, scale, pass_scale)
    else:
        sc.kernels["gather"](
            q, sc.npix, gp=grid.params, cell_start=grid.cell_start, spos_w=grid.spos_w,
            sdir_b=grid.sdir_b, sextra=extra, hgtab=sc.hgtab, optics=sc.vbuf.optics,
            ray_start=e.ray_start, pt_pos=e.pt_pos, pt_dir=e.pt_dir, pt_piece=e.pt_piece,
            pieces=e.pieces, pt_slab=e.pt_slab, layer_z=sc.layer_z, pt_R=st.R, pt_N=st.N,
            pt_M=st.M, pix_acc=acc.pix, pix_pairs=acc.pairs, npix=sc.npix, spp=e.camera.spp,
            alpha=alpha, global_radius=int(sc.global_radius), radius_scale=scale,
            pass_scale=pass_scale)
    q.finish()
    sc.timing["gather"] += time.perf_counter() - t0
    info["radius_scale"] = scale
    return info


def gather_beam(sc: Scene, grid: hashgrid.Grid, sslab, extra, st: PointState, acc: Accumulators,
                alpha: float, scale: float, pass_scale: float) -> None:
    """The beam gather in the scene's layout (clppm/beam.py: gather or scatter)."""
    from . import beam          # imported here: beam.py imports this module (hg_table)
    beam.run(sc, grid, sslab, extra, st, acc, alpha, scale, pass_scale)


def band_classes(nb: int, hero: int) -> int:
    """The beam gather's band classes (GCLASS): the largest divisor of nb / hero up to 9, so a
    work item holds nb / GCLASS bands (9 of 81) and the bands of a photon lie in one class."""
    step = nb // max(hero, 1)
    return max(d for d in range(1, 10) if step % d == 0)


def run_passes(sc: Scene, cal: Calibration, st: PointState, passes, acc: Accumulators,
               tallies: photonpass.Tallies) -> list[dict]:
    """Passes ``passes`` added into ``acc`` (not cleared): the step of the in-process run (one
    pass) and of a Dask chunk (its passes) alike.  Returns each pass's counts."""
    return [run_pass(sc, cal, st, p, acc, tallies) for p in passes]


@dataclass
class ChunkResult:
    """A chunk of passes: its sums (host arrays, for a distributed reduction) and counts."""

    chunk: int
    passes: list
    pix: np.ndarray
    pairs: np.ndarray
    tallies: list                    # [band][category] python ints
    emitted: list                    # per pass
    stored: int
    seconds: dict


def run_chunk(sc: Scene, cal: Calibration, st: PointState, chunk: int, passes, acc: Accumulators,
              start: np.ndarray | None = None) -> ChunkResult:
    """Passes of one chunk from zeroed accumulators, or from ``start`` (the sums of the chunk's
    earlier passes that an in-process run's checkpoint holds); the sums come back to the host."""
    acc.clear()
    if start is not None:
        acc.pix.set(np.ascontiguousarray(start, np.float64))
    tallies = photonpass.Tallies(sc.vol.nb, sc.vol.nl)
    before = dict(sc.timing)
    infos = run_passes(sc, cal, st, passes, acc, tallies)
    pix, pairs = acc.host()
    return ChunkResult(chunk=chunk, passes=list(passes), pix=pix, pairs=pairs, tallies=tallies.counts,
                       emitted=[i["emitted"] for i in infos],
                       stored=sum(min(i["stored"], sc.capacity) for i in infos),
                       seconds={k: sc.timing[k] - before.get(k, 0.0) for k in STAGES})


def chunk_passes(chunk: int, k: int, n_passes: int) -> range:
    """The passes of chunk ``chunk`` (``k`` passes each, the last one shorter)."""
    return range(chunk * k, min((chunk + 1) * k, n_passes))
