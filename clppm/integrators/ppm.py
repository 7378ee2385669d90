"""Progressive photon mapping on the skin volume: one :class:`Pipeline` per scene and device.

:meth:`Pipeline.build` puts the scene on a device (volume, eye pass, photon and grid buffers,
kernels, the density estimate); :meth:`Pipeline.calibrate` finds the initial radius and the
storage depth from a photon pass of its own that never reaches the image; then passes.  A pass
(:meth:`Pipeline.run_pass`) is the stages in order: photon pass, grid, density estimate (the
pipeline's estimator, :mod:`clppm.integrators.estimators`: the sphere gather or the beam gather),
which accumulates the pass's radiance into an :class:`Accumulators` and, with the per-point radius,
updates the points' R and N.

Passes are grouped in chunks of ``render.chunk_passes``.  A chunk starts from zeroed
accumulators, and chunk sums are added to the total in chunk order, here and in a distributed
run alike (:mod:`clppm.run.executor`): the float64 sums then round the same way wherever the chunks
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

from . import eyepass, hashgrid, photonpass
from ..scene import volume
from .beam import BeamGather
from .estimators import PassGrid, SphereGather
from ..scene.scene import Scene
from ..config import RenderSettings, render_settings
from ..compute.device import Device, check_alloc, kernel_defines, wide_vectors
from ..compute.kernelcall import Kernel
from ..request import RenderRequest

#: pass index of the calibration photon pass (its photons set R0 and are then dropped)
CAL_PASS = 0xFFFFFFFF
#: the calibration pass stores this fraction of a pass's photons (from CAL_FRACTION_FROM on)
CAL_FRACTION = 0.25
CAL_FRACTION_FROM = 4 * 20_000
CAL_RADIUS_ITERS = 4             # init_radius's refinements of the cell-count estimate
CAL_SUBSAMPLE = 20_000           # points whose exact counts set the global factor (about)
CAL_ROUNDS = 3                   # rounds of counting and scaling
CAL_CLAMP = (0.5, 2.0)           # the global factor of one round, at most
STAGES = ("photon", "grid", "gather")


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
class Calibration:
    """What the calibration pass decides for every later pass."""

    R0: np.ndarray                   # (npts,) float32 initial radius per sample point (um)
    store_zmin: float | None         # photons below this z are never gathered (not stored)
    first_search_mean: float | None  # photons the first search finds per point, on average
    # the whole image's median and largest R0 (they size every pass's grid), kept when R0 is
    # left out (:meth:`head`: a distributed tile gets its own points' R0 apart)
    r0_median: float | None = None
    r0_max: float | None = None

    def radii(self) -> tuple[float, float]:
        """The whole image's median and largest R0."""
        if self.r0_median is not None:
            return self.r0_median, self.r0_max
        return float(np.median(self.R0)), float(self.R0.max())

    def head(self) -> "Calibration":
        """This calibration without the per-point R0 (its median and maximum kept)."""
        med, rmax = self.radii() if self.R0.size else (0.0, 0.0)
        return Calibration(R0=np.zeros(0, np.float32), store_zmin=self.store_zmin,
                           first_search_mean=self.first_search_mean, r0_median=med, r0_max=rmax)

    @classmethod
    def from_checkpoint(cls, st: dict) -> "Calibration":
        """The calibration a checkpoint's state holds (clppm.output.checkpoint.load)."""
        return cls(R0=st["R0"].astype(np.float32), store_zmin=st["store_zmin"],
                   first_search_mean=st["stats"].get("first_search_mean"))


@dataclass
class Accumulators:
    """Pixel x band radiance sums (float64) and photon-point pair counts, on the device: of the
    whole image, or of one tile's pixels (``base``: the first pixel held; the gather kernels
    write pixel ``pix`` at ``pix - base``)."""

    pix: object
    pairs: object
    base: int = 0

    @classmethod
    def zeros(cls, sc: "Pipeline", pixels: tuple[int, int] | None = None) -> "Accumulators":
        """Zeroed sums of pixels ``pixels`` (first, end; default: every pixel)."""
        import pyopencl.array as cla
        q = sc.dev.queue
        p0, p1 = pixels if pixels is not None else (0, sc.npix)
        return cls(cla.zeros(q, (p1 - p0) * sc.vol.nb, np.float64), cla.zeros(q, p1 - p0, np.uint64), base=p0)

    def clear(self) -> None:
        self.pix.fill(0)
        self.pairs.fill(0)

    def add(self, other: "Accumulators") -> None:
        """Accumulate: a closed chunk's sums into the total (in chunk order)."""
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


def device_needs(cfg: dict, vol: volume.Volume, eye_bytes: int, npix: int, photons: int | None = None) -> dict:
    """Device bytes of a render of ``cfg`` (``photons`` stored per pass; None: the config's)."""
    rs = render_settings(cfg)
    capacity = photonpass.capacity_for(int(rs.photons if photons is None else photons))
    from ..config import bands_per_path
    rec = 32 + 4 * (bands_per_path(cfg) - 1)                   # photon record bytes
    sums = 1 if int(rs.passes) <= int(rs.chunk_passes) else 2   # the total, and an open chunk
    return {"stored photons": capacity * rec, "sorted photons": capacity * (rec + 4),
            "grid cells": 4 * (hashgrid.DEFAULT_MAX_CELLS + 1) * 2,
            "sample points": eye_bytes,
            "pixel accumulators": sums * (npix * vol.nb * 8 + npix * 8), **vol.device_bytes()}


@dataclass
class Pipeline:
    """One scene on one device: its buffers and kernels, and a method per stage of a pass."""

    req: RenderRequest
    scene: Scene                     # built once from req: model, light, camera, settings
    dev: Device
    vol: volume.Volume
    vbuf: volume.VolumeBuffers
    eye: eyepass.EyeData
    pp: photonpass.PhotonPass
    prg: object                      # kernels/gather.cl built for this scene (kernel_defines)
    init_radius: Kernel
    count_within: Kernel
    hgtab: object                    # [NL*NB] float4: Volume.hg_table
    layer_z: object                  # [NL] float2: each layer's lowest top and highest bottom
    gbufs: hashgrid.GridBuffers
    target: int                      # stored photons per pass
    capacity: int
    box: tuple                       # x0, y0, x1, y1, deepest sample point z, top z
    tiles: eyepass.EyeTiles | None = None   # the image's pixels in tiles of sample points
    whole: eyepass.EyeData | None = None    # the whole image's eye pass (totals, statistics)
    tile: int = 0                    # the tile whose points are loaded (``eye``)
    gclass: int = 1                  # the beam gather's band classes (band_classes)
    estimator: SphereGather | BeamGather | None = None   # the density estimate, made by build
    tile_state: PointState | None = None    # run_tile's point state (a tile's R0; N and M unused)
    timing: dict = field(default_factory=lambda: {k: 0.0 for k in STAGES})

    @property
    def cfg(self) -> dict:
        """The scene's config, with the run's values at their keys (:attr:`Scene.config`)."""
        return self.scene.config

    @property
    def rs(self) -> RenderSettings:
        """The [render] table with the run's values (RenderRequest.settings)."""
        return self.req.settings

    @property
    def npix(self) -> int:
        return self.eye.camera.width * self.eye.camera.height

    @property
    def npts(self) -> int:
        """Sample points loaded (the current tile's)."""
        return self.eye.npoints

    @property
    def npts_total(self) -> int:
        """Sample points of the whole image."""
        return self.whole.npoints

    @property
    def ntiles(self) -> int:
        return len(self.tiles.tiles)

    @property
    def pixels(self) -> tuple[int, int]:
        """The loaded points' pixels: the first one and the end (a launch's start, its guard)."""
        p1 = self.eye.pix1
        return self.eye.pix0, self.npix if p1 is None else p1

    def load_tile(self, t: int) -> None:
        """Tile ``t``'s sample points on the device (nothing to do when they already are)."""
        if t == self.tile:
            return
        w = self.whole
        self.eye = self.tiles.load(t, self.eye)
        self.eye.zmin, self.eye.grazing, self.eye.cone_deg, self.eye.piece_extent = (
            w.zmin, w.grazing, w.cone_deg, w.piece_extent)
        self.tile = t
        if hasattr(self.estimator, "pslab"):
            self.estimator.pslab = None          # the beam's per-piece depths: this tile's pieces

    def tile_R0(self, cal: "Calibration", st: "PointState", t: int) -> None:
        """Tile ``t`` loaded, its points' R0 in ``st`` (the global radius: R = R0 always)."""
        self.load_tile(t)
        if self.ntiles > 1 and self.npts:
            a, b = self.tiles.point_range(t)
            st.R[:self.npts].set(np.ascontiguousarray(cal.R0[a:b], np.float32))

    @property
    def global_radius(self) -> bool:
        return self.rs.radius == "global"

    @property
    def beam(self) -> bool:
        return self.rs.estimator == "beam"

    @property
    def dim(self) -> int:
        """Dimension of the density estimate's kernel: the radius update's exponent."""
        return self.estimator.dim

    # building ---------------------------------------------------------------------------------
    @classmethod
    def build(cls, req: RenderRequest | dict, dev: Device, plan: list | None = None) -> "Pipeline":
        """Volume on the device, eye pass, photon and grid buffers, kernels, the estimator;
        memory checked first (``req``: a request, or a config rendered with its own values;
        ``plan``: the tiles' pixel ranges to use, as another device planned them; default:
        planned from this device's memory)."""
        req = req if isinstance(req, RenderRequest) else RenderRequest(req)
        t0 = time.perf_counter()
        scene = Scene.of(req)
        cfg, rc, cam = scene.config, scene.settings, scene.camera
        vol = scene.volume
        vbuf = volume.upload_volume(dev, vol)
        timing = {"volume": time.perf_counter() - t0}
        nrays, target = cam.width * cam.height * cam.spp, int(rc.photons)
        check_alloc(dev, device_needs(cfg, vol, (nrays + 1) * 8 + nrays * 8, cam.width * cam.height, target))
        t0 = time.perf_counter()
        tiles, whole, eye = cls.eye_pass(req, scene, dev, vbuf, plan)
        timing["eye"] = time.perf_counter() - t0
        check_alloc(dev, device_needs(cfg, vol, eye.device_bytes(), cam.width * cam.height, target))
        pp = cls.photon_source(scene, dev, vbuf, whole)
        sc = cls(req=req, scene=scene, dev=dev, vol=vol, vbuf=vbuf, eye=eye, pp=pp, target=target,
                 capacity=pp.capacity, gbufs=hashgrid.GridBuffers(dev), tiles=tiles, whole=whole,
                 tile=len(tiles.tiles) - 1, **cls._tables(req, dev, vol, whole, pp))
        sc.estimator = BeamGather(sc) if rc.estimator == "beam" else SphereGather(sc)
        sc.timing.update(timing)
        return sc

    @staticmethod
    def eye_pass(req: RenderRequest, scene: Scene, dev: Device, vbuf, plan: list | None = None) -> tuple:
        """The eye pass: each ray's counts, the tiles, every tile loaded once for what the
        whole image's points decide.  Returns the tiles, the whole image's EyeData and the
        tile left loaded (with one tile: the whole image, loaded for the whole render)."""
        rc = scene.settings
        tiles = eyepass.EyeTiles.count(dev, vbuf, scene, eyepass.scheme(rc.method, rc.spacing_um))
        if plan is None:
            tiles.plan(tile_points(req, dev, scene.volume, tiles))
        else:
            tiles.use(plan)
        whole, eye = tiles.summarise()
        dev.queue.finish()
        return tiles, whole, eye

    @staticmethod
    def photon_source(scene: Scene, dev: Device, vbuf, eye) -> photonpass.PhotonPass:
        """The photon pass's device state: the light, the storage rule, the run's seed."""
        rc = scene.settings
        pp = photonpass.PhotonPass(dev, scene, capacity=photonpass.capacity_for(int(rc.photons)), vbuf=vbuf,
                                   bands=scene.bands())
        pp.set_storage(rc.storage, eye.cone_deg, rc.store_scale, rc.store_min)
        pp.set_emission(rc.emission)
        return pp

    @staticmethod
    def _tables(req: RenderRequest, dev: Device, vol, eye, pp) -> dict:
        """The gather program, the calibration's kernels and the tables every estimator reads."""
        import pyopencl as cl
        gclass = band_classes(vol.nb, pp.hero)
        prg = dev.build("gather.cl", kernel_defines(vol, hero=pp.hero, estimator=req.settings.estimator,
                                                    gclass=gclass, vec16=wide_vectors(dev.device)))
        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        lz = np.stack([np.maximum(vol.iface[1:, 1], -1e30), vol.iface[:-1, 2]], -1).astype(np.float32)
        zdeep = eye.zmin if eye.npoints else vol.z_top      # eye: the whole image's
        return dict(prg=prg, init_radius=Kernel(prg, "init_radius"), count_within=Kernel(prg, "count_within"),
                    hgtab=cl.Buffer(dev.ctx, ro, hostbuf=vol.hg_table()),
                    layer_z=cl.Buffer(dev.ctx, ro, hostbuf=np.ascontiguousarray(lz)), gclass=gclass,
                    box=(vol.x0, vol.y0, vol.x0 + vol.nx * vol.dx, vol.y0 + vol.ny * vol.dy, zdeep, vol.z_top))

    # the stages of a pass -----------------------------------------------------------------------
    def photon_pass(self, p: int, tallies: photonpass.Tallies) -> tuple[dict, int]:
        """Photon pass p: its counts and the photons stored (at most the capacity)."""
        t0 = time.perf_counter()
        info = self.pp.run_pass(p, self.target, tallies=tallies)
        self.dev.queue.finish()
        self.timing["photon"] += time.perf_counter() - t0
        return info, min(info["stored"], self.capacity)

    def grid(self, n: int, radii_median: float, rmax: float, flat: bool = False, key_pos=None,
             hz: float | None = None, nclass: int = 1) -> hashgrid.Grid:
        """Grid over the photons that sample points can reach (the sample points' box padded by
        the largest radius), cells of half the median radius; with ``flat`` (the beam's passes)
        cells ``hz`` deep (not deeper than wide)."""
        x0, y0, x1, y1, zdeep, ztop = self.box
        pad = rmax * 1.001 + 1.0
        # the discs have no depth: pieces not near horizontal reach only their own depth (and the
        # waves of a conforming layer); photons beyond the box still go to its edge cells
        zpad = pad if not flat or self.eye.grazing else 1.0 + float(np.max(np.ptp(self.vol.iface[:, 1:3], 1)))
        lo, hi = (x0 - pad, y0 - pad, zdeep - zpad), (x1 + pad, y1 + pad, ztop + zpad)
        h = hashgrid.choose_cell_size([radii_median], lo, hi)
        hz = min(hz, h) if flat and hz is not None else None
        return hashgrid.build(self.dev, self.pp.pos_w, self.pp.dir_b, n, lo, hi, h, buffers=self.gbufs,
                              extra=self.pp.extra, extra_stride=self.pp.hero - 1, hz=hz, key_pos=key_pos,
                              nclass=nclass if flat else 1)

    def pass_grid(self, n: int, cal: "Calibration", st: "PointState", p: int) -> tuple[PassGrid, float]:
        """The grid stage: the pass's radii (R0 s(p) with the global radius, else the points'
        own) size the estimator's grid.  Returns the grid and s(p)."""
        t0 = time.perf_counter()
        if self.global_radius:
            scale = radius_scale(p, float(self.rs.alpha), self.dim)
            med0, max0 = cal.radii()
            med, rmax = med0 * scale, max0 * scale
        else:
            scale = 1.0
            radii = st.R.get()[:self.npts]
            med, rmax = float(np.median(radii)), float(radii.max())
        pg = self.estimator.grid(n, med, rmax)
        self.dev.queue.finish()
        self.timing["grid"] += time.perf_counter() - t0
        return pg, scale

    def density_estimate(self, pg: PassGrid, st: "PointState", acc: "Accumulators", scale: float,
                         pass_scale: float) -> None:
        """The density estimate stage: the estimator's gather, accumulated into ``acc``."""
        t0 = time.perf_counter()
        extra = pg.grid.sextra.data if pg.grid.sextra is not None else self.pp.extra
        self.estimator.estimate(pg, extra, st, acc, float(self.rs.alpha), scale, pass_scale)
        self.dev.queue.finish()
        self.timing["gather"] += time.perf_counter() - t0

    def run_pass(self, cal: "Calibration", st: "PointState", p: int, acc: "Accumulators",
                 tallies: photonpass.Tallies) -> dict:
        """Photon pass p, grid, density estimate into ``acc``; returns the pass's counts."""
        info, n = self.photon_pass(p, tallies)
        if self.npts_total == 0:
            return info
        pg, scale = self.pass_grid(n, cal, st, p)
        pass_scale = 1.0 / max(info["emitted"], 1) if self.global_radius else 1.0
        # the tiles' pixels are disjoint: each pixel's sum gets the same one term as untiled
        for t in self._tile_order():
            t0 = time.perf_counter()
            self.tile_R0(cal, st, t)
            self.timing["tiles"] = self.timing.get("tiles", 0.0) + time.perf_counter() - t0   # the eye passes
            if self.npts:
                self.density_estimate(pg, st, acc, scale, pass_scale)
        info["radius_scale"] = scale
        return info

    def run_tile(self, cal: "Calibration", R0: np.ndarray, t: int, chunk: int, passes,
                 start: np.ndarray | None = None) -> "ChunkResult":
        """Passes of one chunk over tile ``t``'s pixels alone: a distributed render's piece, which
        needs only that tile's sample points (``R0``: theirs; ``cal``: the calibration, its R0
        not needed).  Each pass's photons and grid are the ones :meth:`run_pass` makes (pass p's
        photons depend on p alone), the tile's gather adds into sums of its own pixels, from
        zero or from ``start`` (the tile's part of the chunk's earlier sums): each pixel's sum
        takes the in-process terms in the in-process order.  Its counts (tallies, emitted,
        stored) are the chunk's, the same for every tile."""
        import pyopencl.array as cla
        self.load_tile(t)
        pixels = self.tiles.tiles[t]
        n_max = max(self.tiles.max_sizes()[0], 1)
        if self.tile_state is None or self.tile_state.R.size < n_max:
            q = self.dev.queue
            self.tile_state = PointState(R=cla.zeros(q, n_max, np.float32), N=cla.zeros(q, n_max, np.float32),
                                         M=cla.zeros(q, n_max, np.uint32))
        st = self.tile_state
        if self.npts:
            st.R[:self.npts].set(np.ascontiguousarray(R0, np.float32))
        acc = Accumulators.zeros(self, pixels)
        if start is not None:
            acc.pix.set(np.ascontiguousarray(start, np.float64))
        tallies = photonpass.Tallies(self.vol.nb, self.vol.nmat)
        before = dict(self.timing)
        infos = []
        for p in passes:
            info, n = self.photon_pass(p, tallies)
            if self.npts:
                pg, scale = self.pass_grid(n, cal, st, p)
                pass_scale = 1.0 / max(info["emitted"], 1) if self.global_radius else 1.0
                self.density_estimate(pg, st, acc, scale, pass_scale)
            infos.append(info)
        pix, pairs = acc.host()
        return ChunkResult(chunk=chunk, passes=list(passes), pix=pix, pairs=pairs, tallies=tallies.counts,
                           emitted=[i["emitted"] for i in infos],
                           stored=sum(min(i["stored"], self.capacity) for i in infos),
                           seconds={k: self.timing[k] - before.get(k, 0.0) for k in STAGES},
                           tile=t, pix0=pixels[0])

    def _tile_order(self) -> list:
        """The tiles of a sweep, the loaded one first (one load fewer per pass)."""
        return [self.tile] + [t for t in range(self.ntiles) if t != self.tile]

    def run_passes(self, cal: "Calibration", st: "PointState", passes, acc: "Accumulators",
                   tallies: photonpass.Tallies) -> list[dict]:
        """Passes ``passes`` added into ``acc`` (not cleared), every tile: the step of the
        in-process run (one pass).  Returns each pass's counts."""
        return [self.run_pass(cal, st, p, acc, tallies) for p in passes]

    # calibration and point state ----------------------------------------------------------------
    def point_state(self, cal: "Calibration") -> "PointState":
        import pyopencl.array as cla
        q = self.dev.queue
        n = max(self.tiles.max_sizes()[0], 1)
        R = cla.zeros(q, n, np.float32)
        st = PointState(R=R, N=cla.zeros(q, n, np.float32), M=cla.zeros(q, n, np.uint32))
        if self.ntiles == 1 and self.npts:
            R[:self.npts].set(np.ascontiguousarray(cal.R0, np.float32))
        elif self.npts:
            self.tile_R0(cal, st, self.tile)
        return st

    def apply(self, cal: "Calibration") -> None:
        """Apply the calibration to the photon pass (storage depth)."""
        if cal.store_zmin is not None:
            self.pp.set_storage_depth(cal.store_zmin, self.rs.depth_roulette_um)

    def calibrate(self) -> "Calibration":
        """The paper's initial radius: the radius at which the first search finds K photons.

        A photon pass of its own (index CAL_PASS) is stored; the radius is estimated per point
        from the grid's cell counts (kernel ``init_radius``), then scaled by one global factor so
        that exact counts on a subsample average K.  Photons deeper than any point's sphere can
        reach are not stored afterwards: they could never be gathered.  The calibration pass
        stores a quarter of a pass's photons and looks for K/4 of them (the same radius, in
        expectation): with importance storage a pass is hundreds of thousands of paths."""
        if self.npts_total == 0:
            return Calibration(R0=np.zeros(0, np.float32), store_zmin=None, first_search_mean=None)
        frac = CAL_FRACTION if self.target >= CAL_FRACTION_FROM else 1.0
        n_cal = int(math.ceil(self.target * frac))
        K = float(self.rs.initial_photons) * n_cal / self.target
        info = self.pp.run_pass(CAL_PASS, n_cal, tallies=photonpass.Tallies(self.vol.nb, self.vol.nmat))
        n = min(info["stored"], self.capacity)
        R0, sub = self._first_radius(n, K)
        mean_m = self._scale_radius(R0, sub, n, K)
        # the beam's disc has no depth extent: nothing below the deepest piece is ever gathered,
        # but for the waves of the interfaces it measures depth along (layer-conforming depth)
        iface = self.vol.iface
        waves = float(np.max(iface[:, 2] - iface[:, 1])) if len(iface) else 0.0
        reach = float(R0.max()) * 1.001 if (not self.beam or self.whole.grazing) else waves
        return Calibration(R0=R0, store_zmin=self.box[4] - reach - 1.0,
                           first_search_mean=mean_m / frac if mean_m > 0 else None)

    def _first_radius(self, n: int, K: float) -> tuple[np.ndarray, dict]:
        """Per point, the radius holding K of the ``n`` calibration photons, from the grid's
        cell counts (kernel init_radius), starting from the uniform-density guess; tile by
        tile (a point's radius depends on its own position only).  Returns the radii (host)
        and the subsample of points whose exact counts set the global factor: every
        ``stride``-th point of the image, their positions and directions (host)."""
        import pyopencl.array as cla
        x0, y0, x1, y1, zdeep, ztop = self.box
        vbox = (x1 - x0) * (y1 - y0) * (max(ztop - zdeep, 1.0) + 1.0)
        r_guess = (3 * K * vbox / (4 * math.pi * max(n, 1))) ** (1 / 3)
        r_guess = min(r_guess, 0.5 * max(x1 - x0, y1 - y0))
        rmax = 4.0 * r_guess
        grid = self.grid(n, r_guess, rmax)
        stride = max(1, self.npts_total // CAL_SUBSAMPLE)
        R0 = np.zeros(self.npts_total, np.float32)
        pos, dirs = [], []
        R = cla.zeros(self.dev.queue, max(self.tiles.max_sizes()[0], 1), np.float32)
        for t in self._tile_order():
            self.load_tile(t)
            a, b = self.tiles.point_range(t)
            if a == b:
                continue
            self.init_radius(self.dev.queue, self.npts, gp=grid.params, cell_start=grid.cell_start,
                             pt_pos=self.eye.pt_pos, pt_R=R, npts=self.npts, K=K, R0=r_guess, Rmax=rmax,
                             iters=CAL_RADIUS_ITERS)
            R0[a:b] = R.get()[:b - a]
            first = (-a) % stride                    # the tile's first point on the stride
            pos.append((a + first, self.eye.pt_pos.get()[first:b - a:stride].copy()))
            dirs.append(self.eye.pt_dir.get()[first:b - a:stride].copy())
        order = np.argsort([p[0] for p in pos], kind="stable")
        sub = {"stride": stride, "pos": np.concatenate([pos[i][1] for i in order]),
               "dir": np.concatenate([dirs[i] for i in order])}
        return R0, sub

    def _scale_radius(self, R0: np.ndarray, sub: dict, n: int, K: float) -> float:
        """Scale R0 (in place) by one global factor (clamped per round) until exact counts on
        the subsample average K; returns the last mean count."""
        import pyopencl.array as cla
        q, stride = self.dev.queue, sub["stride"]
        ns = len(sub["pos"])
        cnt = cla.zeros(q, ns, np.uint32)
        spos, sdir = cla.to_device(q, sub["pos"]), cla.to_device(q, sub["dir"])
        mean_m = 0.0
        for r in range(CAL_ROUNDS):
            grid = self.grid(n, float(np.median(R0)), float(R0.max()))
            sR = cla.to_device(q, np.ascontiguousarray(R0[::stride]))
            self.count_within(q, ns, gp=grid.params, cell_start=grid.cell_start, spos_w=grid.spos_w,
                              sdir_b=grid.sdir_b, pt_pos=spos, pt_dir=sdir, pt_R=sR,
                              layer_z=self.layer_z, npts=ns, stride=1, out=cnt)
            mean_m = float(cnt.get().mean())
            if mean_m <= 0 or r == CAL_ROUNDS - 1:
                break
            R0 *= np.float32(min(max((K / mean_m) ** (1 / 3), CAL_CLAMP[0]), CAL_CLAMP[1]))
        return mean_m


#: automatic tiles: sample-point buffers of at most this share of the device's global memory ...
TILE_MEMORY_SHARE = 8
#: ... and at most this many bytes (on a CPU the device's memory is the host's, and a render there
#: holds about 1 kB of host memory per loaded point: 128 MiB of tile buffers ~ 1 GB resident)
TILE_MEMORY_CAP = 128 * 2**20


def tile_bytes(points: int, pieces_per_point: float, beam: bool) -> int:
    """Device bytes of a tile of ``points`` sample points: position, direction, piece index,
    slab and R, N, M per point; per piece its length and layer, and for the beam its geometry
    and layer-conforming depth."""
    return int(points * (16 + 16 + 4 + 8 + 12 + pieces_per_point * (8 + (32 + 16 if beam else 0))))


def tile_points(req: RenderRequest, dev: Device, vol, tiles: eyepass.EyeTiles) -> int | None:
    """The most sample points a tile may hold (``render.tile_points``; 0: from the device's
    memory); None: one tile.  Tiles need the global radius (with the per-point radius each
    point's R and N live across passes) and the gather layout (the scatter's per-scene state
    is built from all the points).  A ``render.tile_points`` whose tile cannot fit beside the
    photon buffers is refused (ConfigError) before any point is stored."""
    from .beam import choose_layout
    from ..config import bands_per_path
    rc = req.settings
    beam, hero = rc.estimator == "beam", bands_per_path(req.scene)
    if rc.radius != "global" or (beam and choose_layout(rc.layout, dev, vol.nb, band_classes(vol.nb, hero),
                                                          hero, vol.ninc) == "scatter"):
        return None
    npts = int(tiles.counts.sum(dtype=np.int64))
    ppp = tiles.pcounts.sum(dtype=np.int64) / max(npts, 1)
    info = dev.info()
    want = int(getattr(rc, "tile_points", 0) or 0)
    if want == 0:
        budget = min(info["global_mem_bytes"] // TILE_MEMORY_SHARE, TILE_MEMORY_CAP, info["max_alloc_bytes"])
        return max(int(budget // tile_bytes(1, ppp, beam)), 1)
    need = tile_bytes(want, ppp, beam)
    others = sum(device_needs(req.resolved(), vol, 0, tiles.npix, int(rc.photons)).values())
    big = want * max(16, ppp * (32 if beam else 8))
    if need + others > info["global_mem_bytes"] or big > info["max_alloc_bytes"]:
        from ..config import ConfigError
        raise ConfigError("config", "render.tile_points", want,
                          f"a tile of {want} sample points needs {(need + others) / 2**20:.0f} MiB of device "
                          f"memory with the photon buffers (largest buffer {big / 2**20:.0f} MiB) but device "
                          f"'{dev.name}' has {info['global_mem_bytes'] / 2**20:.0f} MiB "
                          f"({info['max_alloc_bytes'] / 2**20:.0f} MiB largest allocation); give fewer, "
                          "or 0 (from the device's memory)")
    return want


def band_classes(nb: int, hero: int) -> int:
    """The beam gather's band classes (GCLASS): the largest divisor of nb / hero up to 9, so a
    work item holds nb / GCLASS bands (9 of 81) and the bands of a photon lie in one class."""
    step = nb // max(hero, 1)
    return max(d for d in range(1, 10) if step % d == 0)


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
    tile: int = 0                    # a tile's piece (Pipeline.run_tile): its tile and first pixel;
    pix0: int = 0                    # pix and pairs then hold that tile's pixels only


def chunk_passes(chunk: int, k: int, n_passes: int) -> range:
    """The passes of chunk ``chunk`` (``k`` passes each, the last one shorter)."""
    return range(chunk * k, min((chunk + 1) * k, n_passes))
