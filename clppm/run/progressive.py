"""Progressive photon mapping in this process: the run that :func:`clppm.integrators.driver.drive`
steps.

The passes themselves are the stages of a :class:`clppm.integrators.ppm.Pipeline`.  State between
passes stays on the device (sample-point R and N, the pixel x band accumulators of the closed chunks
and of the open one); the host sees counters, the radii (to size the grid) and, at snapshots, the image.
A checkpoint is the pass index plus that state: photon pass p draws its random numbers from
(seed, p) alone, so a resumed render repeats the remaining passes bit for bit.
"""
from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass, field

import numpy as np

from ..output import checkpoint as ckpt
from ..integrators import driver, photonpass, ppm
from ..output import film
from ..compute.device import open_device
from ..output.film import RenderResult
from ..request import RenderRequest

FIX_NOTE = "fixed point 2^32 per unit weight x phase; pixel sums in float64"


def open_run(req: RenderRequest, t_start: float) -> "PPMRun":
    """The PPM run of ``req`` in this process (after :func:`clppm.run.entry.render`'s checks):
    the device, the pipeline built, then calibration or a checkpoint's state."""
    rs, out = req.settings, req.outputs
    dev = req.dev or open_device(req.device)
    if req.resume:
        ckpt.check_matches(req.resume, device=dev.name)
    cam = req.camera
    driver.say(out.progress, f"building the volume and the eye pass ({cam.width}x{cam.height}, "
                             f"method {rs.method}) on {dev.name}...")
    sc = ppm.Pipeline.build(req, dev)
    tiles = f" in {sc.ntiles} tiles" if sc.ntiles > 1 else ""
    driver.say(out.progress, f"{sc.npts_total} sample points{tiles}; " + (
        f"resuming {os.path.basename(req.resume)}..." if req.resume else "calibrating the first photon search..."))
    return PPMRun.start(sc, run_identity(req, sc), req.resume, t_start, req.budget.on_pass)


@dataclass
class PPMRun:
    """A PPM render in progress: the scene, its calibration and point state, the reduced total,
    the open chunk, and the counts.  A checkpoint is this, minus the device."""

    sc: ppm.Pipeline
    cal: ppm.Calibration
    points: ppm.PointState
    # pixel x band sums on the device, each made when first needed (at 1920x1080 one is 1.3 GB):
    total: ppm.Accumulators | None    # sum of the closed chunks, added in chunk order
    chunk: ppm.Accumulators | None    # the open chunk
    tallies: photonpass.Tallies
    meta: dict                        # what a checkpoint must match (run_identity)
    t_start: float
    on_pass: object = None
    p: int = 0                        # passes done
    emitted: list = field(default_factory=list)
    stored: int = 0
    resume_flags: str = "--resume"
    closed: bool = False              # close() called: the last image() works in the sums' own memory

    @property
    def passes_done(self) -> int:
        return self.p

    @property
    def n_passes(self) -> int:
        return int(self.sc.rs.passes)

    @property
    def device_name(self) -> str:
        return self.sc.dev.name

    @classmethod
    def start(cls, sc: ppm.Pipeline, meta: dict, resume: str | None, t_start: float, on_pass=None) -> "PPMRun":
        """Calibrated afresh, or from a checkpoint's state."""
        st = ckpt.load(resume, meta) if resume else None
        if st is None:
            t0 = time.perf_counter()
            cal = sc.calibrate()
            sc.dev.queue.finish()
            sc.timing["calibration"] = time.perf_counter() - t0
        else:
            cal = ppm.Calibration.from_checkpoint(st)
        run = cls(sc=sc, cal=cal, points=sc.point_state(cal), total=None, chunk=None,
                  tallies=photonpass.Tallies(sc.vol.nb, sc.vol.nmat), meta=meta, t_start=t_start,
                  on_pass=on_pass)
        if st is not None:
            run._restore(st)
        sc.apply(cal)
        return run

    def _restore(self, st: dict) -> None:
        sc = self.sc
        self.p, self.emitted, self.stored = st["pass_index"], list(st["stats"]["emitted"]), st["stats"]["stored"]
        if sc.npts and not sc.global_radius:      # with the global radius R = R0 and N = 0 always
            self.points.R[:sc.npts].set(st["pt_R"].astype(np.float32))
            self.points.N[:sc.npts].set(st["pt_N"].astype(np.float32))
        # an empty or all-zero sum stays unmade: 0 + x is x, so the bits are the same
        if np.any(st["pix_acc"]) or np.any(st["pix_pairs"]):
            self.total = ppm.Accumulators.zeros(sc)
            if st["pix_acc"].size:
                self.total.pix.set(st["pix_acc"].reshape(-1))
            self.total.pairs.set(st["pix_pairs"])
        if np.any(st["chunk_acc"]):
            self.chunk = ppm.Accumulators.zeros(sc)
            self.chunk.pix.set(st["chunk_acc"].reshape(-1))
        self.tallies.counts = st["tallies"]
        self.tallies.emitted = st["tallies_emitted"]
        sc.timing.update({k: v for k, v in st["timing"].items() if k in ppm.STAGES + ("calibration",)})

    def step(self) -> None:
        """Pass p into the open chunk (:meth:`clppm.integrators.ppm.Pipeline.run_passes`, as a Dask
        chunk runs it); the chunk closes every ``render.chunk_passes`` passes."""
        p = self.p
        if self.chunk is None:
            self.chunk = ppm.Accumulators.zeros(self.sc)
        info, = self.sc.run_passes(self.cal, self.points, [p], self.chunk, self.tallies)
        self.emitted.append(info["emitted"])
        self.stored += min(info["stored"], self.sc.capacity)
        if self.on_pass is not None:
            self.on_pass(p, {"pt_R": self.points.R, "pt_N": self.points.N, "pt_M": self.points.M,
                             "emitted": info["emitted"], "radius_scale": info.get("radius_scale", 1.0)})
        self.p = p + 1
        if self.p % int(self.sc.rs.chunk_passes) == 0 or self.p == self.n_passes:
            self.close_chunk()

    def close_chunk(self) -> None:
        """The open chunk joins the total (the first becomes it: 0 + x is x); a chunk is kept
        for the next pass only while passes remain."""
        if self.total is None:
            self.total, self.chunk = self.chunk, None
        else:
            self.total.add(self.chunk)
            self.chunk.clear()
        if self.p >= self.n_passes:
            self.chunk = None

    def _sums(self) -> list:
        return [a for a in (self.total, self.chunk) if a is not None]

    def host_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """The image's sums: the closed chunks plus the open one (which stays open).  After
        close(), the first sum mapped and the others added into it: the caller's to overwrite,
        on a CPU device the device's own memory (no film-sized copy)."""
        parts = self._sums()
        if not parts:
            return np.zeros(self.sc.npix * self.sc.vol.nb), np.zeros(self.sc.npix, np.uint64)
        if self.closed:
            pix = parts[0].pix.map_to_host()
            pairs = parts[0].pairs.get()
            for a in parts[1:]:
                with mapped(a.pix) as cpix:
                    pix += cpix
                pairs += a.pairs.get()
            return pix, pairs
        pix, pairs = parts[0].host()
        for a in parts[1:]:
            cpix, cpairs = a.host()
            pix += cpix                 # in place: at 1920x1080 a pixel x band array is 1.3 GB
            pairs += cpairs
        return pix, pairs

    def save(self, path: str) -> None:
        n, nb = self.sc.npts_total, self.sc.vol.nb
        stats = {"emitted": self.emitted, "stored": self.stored,
                 "first_search_mean": self.cal.first_search_mean}
        state = dict(pass_index=self.p, emitted_total=sum(self.emitted), store_zmin=self.cal.store_zmin,
                     tallies=self.tallies.counts, tallies_emitted=self.tallies.emitted, stats=stats,
                     timing=self.sc.timing)
        pairs = np.zeros(self.sc.npix, np.uint64)
        for a in self._sums():
            pairs += a.pairs.get()
        if self.sc.global_radius:             # R = R0 and N = 0 at every point: R0 says it all
            pt_R = pt_N = np.zeros(0, np.float32)
        else:
            pt_R, pt_N = self.points.R.get()[:n], self.points.N.get()[:n]
        # the sums written from maps of the device's buffers (on a CPU device no copy); a sum
        # not made yet is written empty (zeros): the file is at most the two sums
        with mapped(self.total, nb) as pix, mapped(self.chunk, nb) as cpix:
            ckpt.save(path, self.meta, state, dict(pt_R=pt_R, pt_N=pt_N, R0=self.cal.R0, pix_acc=pix,
                                                   chunk_acc=cpix, pix_pairs=pairs))

    def image(self, interrupted: bool) -> RenderResult:
        """The image and run report of the passes done so far."""
        sc = self.sc
        pix, pairs = self.host_sums()
        return finish(sc, pix, int(pairs.sum()), sum(self.emitted), self.p, sc.timing,
                      {"stored": self.stored, "first_search_mean": self.cal.first_search_mean},
                      self.t_start, interrupted, own=True)

    def close(self) -> None:
        self.closed = True


@contextlib.contextmanager
def mapped(a, nb: int | None = None):
    """A device array (or Accumulators' pix; None: an empty (0, nb) array) read through a map
    while the block runs, as (-1, nb) rows with ``nb``: on a CPU device the device's own memory."""
    import pyopencl as cl
    if a is None:
        yield np.zeros((0, nb))
        return
    arr = a.pix if isinstance(a, ppm.Accumulators) else a
    h = arr.map_to_host(flags=cl.map_flags.READ)
    try:
        yield h if nb is None else h.reshape(-1, nb)
    finally:
        h.base.release()


def run_identity(req: RenderRequest, sc: ppm.Pipeline) -> dict:
    """What a checkpoint of this PPM run must match to be resumed."""
    eye = sc.whole
    return req.checkpoint_identity(sc.dev.name, npoints=int(eye.npoints), npieces=int(eye.npieces),
                                   nrays=int(eye.nrays))


def finish(sc: ppm.Pipeline, pix: np.ndarray, pairs: int, emitted_total: int, passes_done: int,
           timing: dict, stats: dict, t_start: float, interrupted: bool, own: bool = False) -> RenderResult:
    """Pixel x band sums -> spectral radiance (the film does the rest) and the run report;
    ``own``: ``pix`` is the caller's to overwrite (no film-sized copy is made)."""
    cfg, vol, eye, pp, rc = sc.cfg, sc.vol, sc.whole, sc.pp, sc.rs    # cfg: the scene's config
    cam = eye.camera
    bands = pp.bands
    acc = (pix if own else pix.copy()).reshape(cam.height * cam.width, vol.nb)
    P = cfg["light"]["power_w"] * pp.power_fraction
    scale = P / max(passes_done if rc.radius == "global" else emitted_total, 1)
    L = np.multiply(acc, scale * 1e12 / bands.dl / cam.spp, out=acc)    # in place (film-sized)
    if rc.specular:
        add_specular(L, sc.scene.light, eye, bands)
    res = film.develop(L, cam, vol.wl, bands.spectrum, sc.scene.light, rc.exposure)
    per_layer = eye.per_layer(vol.nl)
    res.report = {
        **film.common_report(sc.req.resolved(), "ppm", sc.dev, passes_done, interrupted),
        "method": rc.method, "scheme": eye.scheme.label(),
        "photons_emitted": emitted_total, "photons_stored": stats["stored"],
        "stored_per_pass": rc.photons, "store_zmin_um": None if pp.p["store_zmin"][0] < -1e37
        else float(pp.p["store_zmin"][0]),
        "sample_points": eye.npoints, "path_pieces": eye.npieces, "tiles": sc.ntiles,
        "eye_rays": eye.nrays, "eye_rays_hit": int(eye.ray_hit.sum()),
        "sample_points_per_ray_per_layer": {n: float(v) for n, v in zip(vol.names, per_layer)},
        "first_search_mean_photons": stats["first_search_mean"],
        "gather_pairs": pairs,
        "seconds": dict(timing, total=time.perf_counter() - t_start),
        "seconds_per_pass": {k: timing.get(k, 0.0) / max(passes_done, 1) for k in ppm.STAGES},
        **res.report,
        "volume": vol.info, "accumulation": FIX_NOTE,
        "units": film.UNITS,
    }
    return res


def add_specular(L: np.ndarray, light, eye, bands) -> None:
    """L += specular_radiance, band by band (no second film-sized array)."""
    cam = eye.camera
    spec = eye.ray_spec.reshape(cam.height * cam.width, cam.spp).mean(1)
    fac = light.irradiance_factor(light.power_w * bands.spectrum / bands.dl)
    for b in range(L.shape[1]):
        L[:, b] += spec * fac[b]


def specular_radiance(light, eye, bands) -> np.ndarray:
    """(npix, NB) the light seen in the surface's mirror reflection (the eye pass's ray_spec)."""
    cam = eye.camera
    spec = eye.ray_spec.reshape(cam.height * cam.width, cam.spp).mean(1)
    fac = light.irradiance_factor(light.power_w * bands.spectrum / bands.dl)
    return spec[:, None] * fac[None, :]
