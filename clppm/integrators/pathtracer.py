"""Unbiased path tracer (kernels/pt.cl): ground truth for the skin scenes, flat or with relief.

Eye paths from the same pinhole camera as the eye pass, next-event estimation to the point
light at every scattering vertex through the refracting interfaces.  Through flat interfaces
the connection is exact (Snell's law solved for it, the point source's divergence through the
planes, Fresnel at every crossing; derivation in kernels/pt.cl); through relief it is the
manifold connection described below.  Images have PPM's units, exposure and outputs, so the
two integrators are directly comparable.

The pixel value is the average radiance over the pixel's footprint (every sample is jittered
uniformly in the pixel), where PPM with ``camera.spp = 1`` takes the pixel centre: on smooth
images the two agree, at edges the path tracer is the box-filtered one.

Spectral sampling: one band per path, stratified per pixel (sample k of pixel q takes band
(k + h(q)) mod NB), so after K samples every band has floor or ceil of K/NB of them, known
exactly on the host (``band_counts``); each band's radiance is the mean over its samples.
A pass is N = ``render.pt_samples_per_pass`` paths per pixel, a pure function of (seed, pass):
sums are float64, added per pixel in a fixed order, so a resumed render is byte-identical.

Relief (a furrowed surface, interfaces that follow it, the wavy junction): the eye path walks
the voxel volume as the photon pass does and refracts at the smooth surfaces' normals; the
connection to the light goes through those smooth height fields by manifold next-event
estimation (kernels/mnee.h, docs/relief.md), and the report gives the solver's statistics.

Scope: a point light above the surface; anything else is refused before any work
(``check_scene``).
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..output import checkpoint as ckpt
from ..scene import colorimetry, volume
from ..output import film
from ..compute import structs as S
from ..scene.bands import Bands, band_width
from ..scene.scene import Scene
from ..scene.light import Light
from ..config import ConfigError
from ..compute.device import Device, check_alloc, kernel_defines, open_device
from ..compute.kernelcall import Kernel
from ..request import RenderRequest

NBIN = 8
BIN_LABELS = ["1", "2", "3", "4", "5-8", "9-16", "17-64", "65+"]
STATS = ["vertices", "nee_made", "nee_blocked", "paths_cut"]
SCHEME = "path tracer: NEE through the flat interfaces, one band per path"
SCHEME_RELIEF = ("path tracer: manifold NEE through the smooth height-field interfaces "
                 "(the flat-seeded solution, the others by unbiased specular manifold sampling), "
                 "one band per path")
# kernels/pt.cl pix_mnee, in this order (NMNEE)
MNEE_STATS = ["solves", "solved", "newton_iterations", "continued", "vertex_above_smooth_surface",
              "solutions", "found", "other_solutions", "random_trials", "clamped"]
# Random trials of specular manifold sampling per connection (relief): the light paths through a
# furrow or over a papilla can be several (caustics); a trial that finds one other than the
# flat-seeded solution adds it weighted by its trial count to recur.  A mean (the number drawn
# per connection, kernels/pt.cl sms_count); below 1 it saved time but not error on the forearm
# (docs/relief.md section 4)
MNEE_TRIALS = 1
FLAT_REF = "configs/forearm_flat.toml"


RR_THRESHOLD = 1e-3      # roulette below this fraction of the weight after entering the skin
RR_M = 10.0
MAX_VERTICES = 1_000_000
# NEE roulette: above this optical depth straight up (exp(-6) = 0.25 %) the connection is made
# with probability exp(6 - od) (>= 1e-6) and weighted by its inverse: unbiased, and deep
# vertices, whose light is attenuated by at least exp(-od), skip the connection solve.
NEE_OD = 6.0
# Relief: a manifold connection costs ~20x a flat one, so connecting only with the probability
# exp(-od) beyond od = 0.5 pays (bench: efficiency 1/(variance x time) 6x that at 6.0)
NEE_OD_RELIEF = 0.5
NEE_Q_FLOOR = 1e-6
LAUNCH_MIN = 64          # pixels per launch at least (a work group)
LAUNCH_SECONDS = 1.0     # target duration of one kernel launch (PoCL: keep the host responsive)


def check_scene(cfg: dict, source: str = "<config>") -> None:
    """Refuse what the path tracer does not handle, before any work (one line, key and value)."""
    L = cfg["light"]
    if L["kind"] != "point":
        raise ConfigError(source, "light.kind", L["kind"],
                          "the path tracer's next-event estimation needs a point light "
                          f"(a collimated beam cannot be connected to); {FLAT_REF} is the reference scene")
    if L["position_mm"][2] <= 0:
        raise ConfigError(source, "light.position_mm", L["position_mm"],
                          "the path tracer needs the point light above the skin surface (z > 0)")


def chain_tables(vol: volume.Volume) -> np.ndarray:
    """r0[i] (normal-incidence Fresnel R of interface i; 0 for equal indices and below a
    semi-infinite layer) and tail[i] = sum_{j >= i} r0[j]: the chain sampling probabilities."""
    n = np.concatenate([[vol.n_above], vol.n, [vol.n_below]])
    r0 = ((n[:-1] - n[1:]) / (n[:-1] + n[1:])) ** 2
    if not np.isfinite(vol.thickness[-1]):
        r0[-1] = 0.0
    tail = np.concatenate([np.cumsum(r0[::-1])[::-1], [0.0]])
    return np.ascontiguousarray(np.concatenate([r0, tail]), np.float32)


def lowbias32(x: np.ndarray) -> np.ndarray:
    """The kernel's pixel hash (C. Wellons' lowbias32), in uint32 arithmetic."""
    x = np.asarray(x, np.uint32).copy()
    x ^= x >> np.uint32(16)
    x *= np.uint32(0x7FEB352D)
    x ^= x >> np.uint32(15)
    x *= np.uint32(0x846CA68B)
    x ^= x >> np.uint32(16)
    return x


def band_offsets(npix: int, nb: int) -> np.ndarray:
    return (lowbias32(np.arange(npix, dtype=np.uint32)) % np.uint32(nb)).astype(np.int64)


def band_counts(offsets: np.ndarray, nb: int, samples: int) -> np.ndarray:
    """(npix, nb) number of the first ``samples`` samples of each pixel that took each band:
    sample k takes band (k + h) mod nb, so band b gets the k = r, r + nb, ... with
    r = (b - h) mod nb."""
    r = (np.arange(nb)[None, :] - offsets[:, None]) % nb
    return np.maximum(0, (samples - r + nb - 1) // nb)


def fp64(dev: Device) -> bool:
    return bool(dev.info()["fp64"])


def build(dev: Device, vol: volume.Volume):
    return dev.build("pt.cl", kernel_defines(vol, pt_fp64=fp64(dev)))


class PathTracer:
    """Device state of one path-traced render: the volume, the parameters, the pixel sums."""

    @classmethod
    def of_config(cls, dev: Device, vol: volume.Volume, cfg: dict, **run) -> "PathTracer":
        """The path tracer of a config rendered with its own values (``run``: RenderRequest's run
        values), on the model ``vol`` built from it: the tools' and tests' way in."""
        return cls(dev, Scene.of_config(cfg, volume=vol, **run))

    def __init__(self, dev: Device, scene: Scene):
        """``scene``: the render's (its model, settings, camera and light)."""
        import pyopencl as cl
        import pyopencl.array as cla
        vol = scene.volume
        self.dev, self.vol, self.scene, self.cfg = dev, vol, scene, scene.config
        self.rs = rc = scene.settings
        self.cam = cam = scene.camera
        self.npix = cam.width * cam.height
        self.nspp = int(rc.pt_samples_per_pass)
        q, mf = dev.queue, cl.mem_flags
        self.kernel = Kernel(build(dev, vol), "pt_pass")
        self.vbuf = volume.upload_volume(dev, vol)
        p = S.new_params()
        volume.volume_params(p, vol)
        self.pbuf = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=p)
        self.chain = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=chain_tables(vol))
        e = np.zeros(1, S.PT_DTYPE)
        e["cam"] = cam.struct()
        self.light = scene.light
        e["nspp"] = self.nspp
        e["seed_lo"], e["seed_hi"] = S.split_seed(rc.seed)
        e["lx"], e["ly"], e["lz"] = self.light.position
        e["alpha"] = rc.roughness
        e["specular"] = 1 if rc.specular else 0
        e["rr_threshold"], e["rr_m"], e["max_vertices"] = RR_THRESHOLD, RR_M, MAX_VERTICES
        e["nee_od"], e["nee_q_floor"] = NEE_OD if vol.flat else NEE_OD_RELIEF, NEE_Q_FLOOR
        e["mnee_trials"] = MNEE_TRIALS
        self.e = e
        self.ebuf = cl.Buffer(dev.ctx, mf.READ_ONLY, S.PT_DTYPE.itemsize)
        nb = vol.nb
        self.pix_sum = cla.zeros(q, self.npix * nb, np.float64)
        self.pix_sq = cla.zeros(q, self.npix * nb, np.float64)
        self.pix_stats = cla.zeros(q, self.npix * 4, np.uint64)
        self.pix_bins = cla.zeros(q, self.npix * NBIN, np.float64)
        self.pix_mnee = cla.zeros(q, self.npix * len(MNEE_STATS), np.uint64)
        self.mnee_base = np.zeros(len(MNEE_STATS), np.int64)         # counts of the passes before a resume
        self.smooth = self.vbuf.smooth
        self.launch = min(self.npix, max(LAUNCH_MIN, 16384 // self.nspp))   # ~16k paths, then timed
        self.bands = scene.bands(hero=1)
        self.spectrum = self.bands.spectrum
        self.offsets = band_offsets(self.npix, nb)

    def run_pass(self, p: int) -> int:
        """Trace pass ``p`` (N paths per pixel) in launches of about LAUNCH_SECONDS; returns the
        number of launches.  The launch partition does not change any result."""
        import pyopencl as cl
        q = self.dev.queue
        self.e["pass_"] = p & 0xFFFFFFFF
        self.e["band0"] = (p * self.nspp) % self.vol.nb
        done, launches = 0, 0
        while done < self.npix:
            n = min(self.launch, self.npix - done)
            self.e["pix_offset"], self.e["count"] = done, n
            cl.enqueue_copy(q, self.ebuf, self.e)
            t0 = time.perf_counter()
            self.kernel(q, n, **self.vbuf.named(self.pbuf), E=self.ebuf, chain=self.chain,
                        pix_sum=self.pix_sum, pix_sq=self.pix_sq, pix_stats=self.pix_stats,
                        pix_bins=self.pix_bins, smooth=self.smooth, pix_mnee=self.pix_mnee)
            q.finish()
            dt = time.perf_counter() - t0
            done += n
            launches += 1
            if n == self.launch:
                grow = LAUNCH_SECONDS / max(dt, 1e-3)
                self.launch = int(min(max(self.launch * min(grow, 4.0), LAUNCH_MIN), self.npix))
        return launches

    def state_arrays(self) -> dict:
        nb = self.vol.nb
        return {"pix_sum": self.pix_sum.get().reshape(self.npix, nb),
                "pix_sq": self.pix_sq.get().reshape(self.npix, nb),
                "pix_stats": self.pix_stats.get().reshape(self.npix, 4),
                "pix_bins": self.pix_bins.get().reshape(self.npix, NBIN)}

    def mnee_totals(self) -> list[int]:
        """The manifold solver's counts (MNEE_STATS) over all passes, resumed ones included."""
        return [int(a) + int(b) for a, b in zip(self.mnee_base,
                                                 self.pix_mnee.get().reshape(-1, len(MNEE_STATS)).sum(0))]

    def set_state(self, st: dict) -> None:
        if "mnee" in st:
            self.mnee_base = np.asarray(st["mnee"], np.int64)
        self.pix_sum.set(np.ascontiguousarray(st["pix_sum"].reshape(-1), np.float64))
        self.pix_sq.set(np.ascontiguousarray(st["pix_sq"].reshape(-1), np.float64))
        self.pix_stats.set(np.ascontiguousarray(st["pix_stats"].reshape(-1), np.uint64))
        self.pix_bins.set(np.ascontiguousarray(st["pix_bins"].reshape(-1), np.float64))


def run_identity(req: RenderRequest, tracer: PathTracer) -> dict:
    """What a path-tracer checkpoint must match to be resumed."""
    return req.checkpoint_identity(tracer.dev.name, npix=tracer.npix, nb=tracer.vol.nb, nbin=NBIN,
                                   **({} if tracer.vol.flat else {"mnee": ["sms", MNEE_TRIALS]}))


def band_scale(light: Light, bands: Bands) -> np.ndarray:
    """Per band: kernel value (um^-2 per unit intensity) -> W m^-2 sr^-1 nm^-1.
    I_b = P s_b / 4 pi (W/sr), 1e12 um^2/m^2, per nm of the band (the PPM units)."""
    return light.power_w * bands.spectrum / (4 * math.pi) * 1e12 / bands.dl


def radiance(sums: np.ndarray, counts: np.ndarray, scale: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """(npix, nb) radiance: each band's mean over its samples.  Each sample takes one band, so
    with fewer samples per pixel than bands some bands of a pixel have none: those are
    interpolated linearly in wavelength between the pixel's nearest sampled bands (the nearest
    one beyond the ends; 0 in a pixel with no sample).  Writing 0 there instead would darken the
    image by the unsampled fraction (a quarter at 64 samples for 81 bands)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0) * scale[None, :]
    gaps = counts <= 0
    if gaps.any():
        mean = fill_unsampled(mean, ~gaps, np.asarray(wl, float))
    return mean


def fill_unsampled(mean: np.ndarray, sampled: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """``mean`` with its unsampled entries (``~sampled``, per pixel and band) interpolated
    linearly in wavelength between the pixel's nearest sampled bands below and above."""
    npix, nb = mean.shape
    idx = np.arange(nb)
    lo = np.maximum.accumulate(np.where(sampled, idx, -1), axis=1)            # sampled band below
    hi = np.minimum.accumulate(np.where(sampled, idx, nb)[:, ::-1], axis=1)[:, ::-1]   # above
    rows = np.arange(npix)[:, None]
    has_lo, has_hi = lo >= 0, hi < nb
    lo_c, hi_c = np.clip(lo, 0, nb - 1), np.clip(hi, 0, nb - 1)
    v_lo, v_hi = mean[rows, lo_c], mean[rows, hi_c]
    span = wl[hi_c] - wl[lo_c]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(span > 0, (wl[None, :] - wl[lo_c]) / span, 0.0)
    fill = np.where(has_lo & has_hi, v_lo + t * (v_hi - v_lo),
                    np.where(has_lo, v_lo, np.where(has_hi, v_hi, 0.0)))
    return np.where(sampled, mean, fill)


def noise(sums, sq, counts, scale, wl) -> dict:
    """Per-pixel standard error of the luminance Y from the per-band sample variances
    (bands are independent estimates: Var Y = sum_b (ybar_b dl s_b)^2 Var(mean_b)); pixels
    where a band has fewer than 2 samples get none."""
    dl = band_width(wl)
    ybar = colorimetry.cmfs(wl)[:, 1] * dl * scale
    c = np.maximum(counts, 1).astype(float)
    mean = sums / c
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.maximum(sq / c - mean * mean, 0.0) / (c - 1)
    ok = (counts >= 2).all(1)
    Y = (mean * ybar[None, :]).sum(1)
    varY = (var * (ybar ** 2)[None, :]).sum(1)
    good = ok & (Y > 0)
    rel = np.sqrt(varY[good]) / Y[good]
    out = {"pixels_with_estimate": int(good.sum()),
           "median_rel_se_Y": float(np.median(rel)) if rel.size else None,
           "mean_rel_se_Y": float(rel.mean()) if rel.size else None,
           "p90_rel_se_Y": float(np.percentile(rel, 90)) if rel.size else None,
           "image_mean_Y_rel_se": float(math.sqrt(varY[ok].sum()) / Y[ok].sum())
           if ok.any() and Y[ok].sum() > 0 else None}
    return out


def _finish(tracer: PathTracer, arrays: dict, passes_done, timing, dev, t_start,
            interrupted, record: dict) -> film.RenderResult:
    """The path tracer's sums -> radiance (the film does the rest) and the run report
    (``record``: the config as the run rendered it, RenderRequest.resolved)."""
    vol = tracer.vol
    wl = vol.wl
    samples = passes_done * tracer.nspp
    counts = band_counts(tracer.offsets, vol.nb, samples)
    scale = band_scale(tracer.light, tracer.bands)
    res = film.develop(radiance(arrays["pix_sum"], counts, scale, wl), tracer.cam, wl, tracer.spectrum,
                       tracer.light, tracer.rs.exposure)
    stats = dict(zip(STATS, (int(v) for v in arrays["pix_stats"].sum(0))))
    paths = tracer.npix * samples
    bins = arrays["pix_bins"].sum(0)
    btot = float(bins.sum())
    trace_s = timing.get("trace", 0.0)
    res.report = {
        **film.common_report(record, "pt", dev, passes_done, interrupted),
        "method": "pt", "scheme": SCHEME if vol.flat else SCHEME_RELIEF,
        "samples_per_pass": tracer.nspp, "samples_per_pixel": samples,
        "samples_per_pixel_per_band": [int(counts.min()), int(counts.max())] if counts.size else [0, 0],
        "bands_interpolated": float((counts <= 0).mean()) if counts.size else 0.0,
        "paths_traced": paths, "photons_emitted": 0,
        "scattering_vertices": stats["vertices"],
        "mean_vertices_per_path": stats["vertices"] / paths if paths else 0.0,
        "nee_connections_made": stats["nee_made"], "nee_connections_blocked": stats["nee_blocked"],
        "paths_cut_at_vertex_bound": stats["paths_cut"],
        "paths_per_second": paths / trace_s if trace_s > 0 else None,
        "nee_connections_per_second": (stats["nee_made"] + stats["nee_blocked"]) / trace_s
        if trace_s > 0 else None,
        "nee_value_by_vertex_index": {k: (float(v) / btot if btot > 0 else 0.0)
                                      for k, v in zip(BIN_LABELS, bins)},
        "manifold_nee": None if vol.flat else mnee_report(tracer.mnee_totals()),
        "noise": noise(arrays["pix_sum"], arrays["pix_sq"], counts, scale, wl),
        "seconds": dict(timing, total=time.perf_counter() - t_start),
        **res.report,
        "volume": vol.info,
        "accumulation": "per pixel and band: float64 sums of path values in a fixed order",
        "units": film.UNITS + "; pixel = average over the pixel footprint",
    }
    return res


def mnee_report(tot: list[int]) -> dict:
    """The run report's solver statistics: success rate, iterations, failures, clamping."""
    d = dict(zip(MNEE_STATS, tot))
    n = d["solves"]

    def share(k):
        return d[k] / n if n else None
    d["success_rate"] = share("found")                 # at least one light path found
    d["flat_seeded_rate"] = share("solved")
    d["failed_share"] = (n - d["found"]) / n if n else None
    d["mean_iterations"] = share("newton_iterations")
    d["continued_share"] = share("continued")
    d["mean_solutions"] = share("solutions")
    d["other_solution_share"] = share("other_solutions")
    d["clamped_share"] = d["clamped"] / d["other_solutions"] if d["other_solutions"] else 0.0
    d["trials_per_connection"] = share("random_trials")
    d["method"] = ("Newton on the landing constraint over the ray's momentum at the vertex, "
                   "ray differentials for the Jacobian, step halving, seeded by the flat solution; "
                   "where that fails, continuation from the flat surfaces; the other solutions by "
                   f"specular manifold sampling, unbiased: {MNEE_TRIALS} random trial(s) per connection "
                   "(where the flat-seeded solve fails, they look for every solution), a solution "
                   "found weighted by the trials "
                   "until it recurs (capped at 256: clamped) "
                   "(docs/relief.md)")
    return d


def check_request(req: RenderRequest) -> None:
    """What the path tracer refuses before any work: a scene it cannot trace
    (:func:`check_scene`), more paths in a pass than it has ids."""
    rc, source = req.settings, req.source
    check_scene(req.resolved(), source)
    cam = req.camera
    if cam.width * cam.height * rc.pt_samples_per_pass > 2**32:
        raise ConfigError(source, "render.pt_samples_per_pass", rc.pt_samples_per_pass,
                          f"{cam.width}x{cam.height} pixels x {rc.pt_samples_per_pass} exceeds the "
                          "2^32 path ids of a pass")


def open_run(req: RenderRequest, t_start: float) -> "PTRun":
    """The path tracer's run of ``req`` (after :func:`clppm.run.entry.render`'s checks): the
    device, the volume, the tracer, and a checkpoint's sums when resumed."""
    dev = req.dev or open_device(req.device)
    if req.resume:
        ckpt.check_matches(req.resume, device=dev.name)
    t0 = time.perf_counter()
    scene = Scene.of(req)
    vol, cam = scene.volume, scene.camera
    w, h = cam.width, cam.height
    timing = {"volume": time.perf_counter() - t0, "trace": 0.0, "output": 0.0}
    check_alloc(dev, {"pixel sums": w * h * vol.nb * 8, "pixel sums of squares": w * h * vol.nb * 8,
                      "pixel statistics": w * h * 64, "value by vertex index": w * h * NBIN * 8,
                      "smooth heights": 0 if vol.smooth is None else int(vol.smooth.nbytes),
                      **vol.device_bytes()})
    run = PTRun(PathTracer(dev, scene), req, timing, t_start)
    if req.resume:
        run.restore(req.resume)
    return run


class PTRun:
    """A path-traced render in progress, as :func:`clppm.integrators.driver.drive` steps it: a step
    is a pass of N paths per pixel."""

    resume_flags = "--integrator pt --resume"

    def __init__(self, tracer: PathTracer, req: RenderRequest, timing: dict, t_start: float):
        self.tracer, self.req, self.timing, self.t_start = tracer, req, timing, t_start
        self.meta = run_identity(req, tracer)
        self.p = 0
        self.n_passes = int(req.settings.passes)
        self.device_name = tracer.dev.name

    @property
    def passes_done(self) -> int:
        return self.p

    def restore(self, path: str) -> None:
        st = ckpt.load(path, self.meta, integrator="pt")
        self.tracer.set_state(st)
        self.p = st["pass_index"]
        self.timing.update({k: v for k, v in st.get("timing", {}).items() if k == "trace"})

    def step(self) -> None:
        t0 = time.perf_counter()
        self.tracer.run_pass(self.p)
        self.timing["trace"] += time.perf_counter() - t0
        self.p += 1

    def save(self, path: str) -> None:
        ckpt.save(path, self.meta, {"pass_index": self.p, "timing": self.timing,
                                    "mnee": self.tracer.mnee_totals()},
                  self.tracer.state_arrays(), integrator="pt")

    def image(self, interrupted: bool) -> film.RenderResult:
        return _finish(self.tracer, self.tracer.state_arrays(), self.p, self.timing, self.tracer.dev,
                       self.t_start, interrupted, self.req.resolved())

    def close(self) -> None:
        pass
