"""Photon pass (kernels/photon.cl): launch, stored photons, exact tallies.

Determinism.  Photon i of pass p draws its numbers from Philox keyed by (seed, p, i), so its
path is fixed.  A pass emits photons in launches of consecutive ids until the device counter
of stored events reaches the target; each launch size is a function of counts that are
themselves deterministic, so the set of photons of a pass, the number emitted and the set of
stored events are the same on every run (the order of events in the buffer is not, and
nothing downstream depends on it: sums over photons are integer fixed point).

Tallies are int64 fixed point on the device (2^38 per photon weight), read after every
launch into Python integers and reset: exact and unbounded.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..compute import structs as S
from ..scene.bands import Bands
from ..scene.light import Light
from ..scene.scene import Scene
from ..compute.device import Device, kernel_defines, launch, surface_fp64
from ..compute.kernelcall import Kernel
from ..scene.volume import Volume, VolumeBuffers, optics_rows, upload_volume, volume_params

W0 = 2 ** 38
CATEGORIES = ["specular", "diffuse", "transmitted", "lost", "rr_gain", "rr_loss", "missed",
              "diffuse_cone"]
# photon.cl's event counters (PHOTON_COUNTERS), in its order: photons that entered the model or
# missed it, loop steps, collisions, stored events, crossings of layer interfaces (and those at a
# smooth surface's normal), core- and tile-plane, column-wall and domain-side crossings,
# re-entries, tile-wall crossings
COUNTERS = ["entered", "missed", "steps", "collisions", "stored", "interface", "interface_smooth",
            "zone", "wall", "domain", "reenter", "tile", "lane_events", "lane_iterations"]
NA = len(CATEGORIES)        # index of the first per-layer absorption tally
BALANCE = [i for i, c in enumerate(CATEGORIES) if c != "diffuse_cone"]
MAX_LAUNCH = 1 << 20          # photons per launch: tallies stay far below 2^63


def footprint_solid_angle(pos, rect, z: float) -> float:
    """Solid angle of the rectangle rect = (x0, y0, x1, y1) in the plane at height z, seen from
    pos above it: the sum over its corners, with signs, of the solid angle of the rectangle
    between the foot of the perpendicular and the corner, atan(a b / (h sqrt(a^2 + b^2 + h^2)))."""
    h = float(pos[2]) - z

    def corner(a, b):
        return math.atan(a * b / (h * math.sqrt(a * a + b * b + h * h)))
    x0, y0, x1, y1 = (float(v) for v in rect)
    px, py = float(pos[0]), float(pos[1])
    return (corner(x1 - px, y1 - py) - corner(x0 - px, y1 - py) - corner(x1 - px, y0 - py)
            + corner(x0 - px, y0 - py))


def source_params(p: np.ndarray, light: Light, vol: Volume) -> float:
    """Fill the source fields; return the fraction of the light's power the sampling covers."""
    p["src_kind"] = light.code
    p["sdx"], p["sdy"], p["sdz"] = light.direction
    if light.kind == "point":
        pos = light.position
        p["sx"], p["sy"], p["sz"] = pos
        if pos[2] <= vol.z_top:                    # in or below the surface plane: all directions
            p["cone_omc"] = 2.0
            p["cax"], p["cay"], p["caz"] = 0.0, 0.0, -1.0
            return 1.0
        # cone around the model's top face, seen from the light
        x0, y0 = vol.x0, vol.y0
        x1, y1 = vol.x0 + vol.nx * vol.dx, vol.y0 + vol.ny * vol.dy
        corners = np.array([[x, y, vol.z_top] for x in (x0, x1) for y in (y0, y1)])
        vecs = corners - pos
        vecs /= np.linalg.norm(vecs, axis=1)[:, None]
        axis = vecs.sum(0)
        axis /= np.linalg.norm(axis)
        cosmin = float(np.min(vecs @ axis))
        cosmin = max(-1.0, min(cosmin, 1.0)) - 1e-6
        # 1 - cos, not cos: a far light's cone is narrower than float32 resolves near cos = 1
        # (1 m away, 1 mm model: 1 - cos = 1e-6 against a float spacing of 6e-8), which
        # quantised the photons' directions into rings on the skin
        omc = 1.0 - cosmin
        p["cone_omc"] = omc
        p["cax"], p["cay"], p["caz"] = axis
        if vol.lateral == "infinite":
            return omc / 2.0                                     # solid angle / 4 pi
        # photon.cl footprint_dir: only the directions through the top face, by rejection
        return footprint_solid_angle(pos, (x0, y0, x1, y1), vol.z_top) / (4.0 * math.pi)
    p["sx"], p["sy"] = light.center
    if light.kind == "wide":
        p["swx"], p["swy"] = light.width
    return 1.0


TILE = 4          # columns per side of a tile (photon.cl TILE)


def tile_bounds(vol: Volume, tile: int = TILE) -> np.ndarray:
    """(nvar, nty, ntx, 2) float32: the lowest and highest height of every varying interface over
    each tile of tile x tile columns (photon.cl tile mode); the edge tiles of a grid that tile
    does not divide cover the columns left."""
    h = vol.heights
    nv, ny, nx = h.shape
    nty, ntx = -(-ny // tile), -(-nx // tile)
    pad = np.pad(h, ((0, 0), (0, nty * tile - ny), (0, ntx * tile - nx)), mode="edge")
    blocks = pad.reshape(nv, nty, tile, ntx, tile)
    return np.ascontiguousarray(np.stack([blocks.min((2, 4)), blocks.max((2, 4))], -1), np.float32)


def band_table(vol: Volume, hero: int) -> np.ndarray:
    """float32 (spectral.h): per material (the layers, then the inclusions) and band log mu_t, then log albedo (at least -1e4: 0 for mu_s = 0), then per
    layer and hero class (h mod NB/hero) the largest albedo over the bands such a path carries, then per layer and
    band the phase-function pair (1 + g^2, 2 g) (1 - g^2)^(-2/3) of sw_scatter."""
    mua, mus, g64 = vol.material_optics()     # the layers, then the inclusions (spectral.h NMAT)
    mut, nm = mua + mus, vol.nmat
    with np.errstate(divide="ignore", invalid="ignore"):
        logmu = np.log(np.maximum(mut, 1e-30))
        alb = np.where(mut > 0, 1.0 - mua / np.where(mut > 0, mut, 1.0), 0.0)
        logalb = np.maximum(np.log(np.maximum(alb, 1e-300)), -1e4)   # exp_neg gives 0 (mu_s = 0)
    # the kernel's albedo is 1 - optics.x in float32: bound that one
    opt = optics_rows(mua, mus, g64).reshape(nm, vol.nb, 4)
    alb32 = 1.0 - opt[:, :, 0].astype(np.float64)
    step = vol.nb // hero
    maxalb = np.max(np.maximum(alb, alb32).reshape(nm, hero, step), axis=1)
    g = np.clip(opt[:, :, 1].astype(np.float64), -0.999999, 0.999999)
    c = (1.0 - g * g) ** (-2.0 / 3.0)
    hg = np.stack([(1.0 + g * g) * c, 2.0 * g * c], axis=-1)
    return np.ascontiguousarray(np.concatenate([logmu.ravel(), logalb.ravel(), maxalb.ravel() * (1 + 1e-6),
                                                hg.ravel()]), np.float32)


def persistent_items(dev: Device) -> int:
    """Work items of a photon-pass launch: they take the launch's photons from a shared counter
    until none is left (photon.cl), so a few hundred per compute unit keep every SIMD lane and
    core busy to the end of a launch (a GPU's compute unit holds more of them resident)."""
    cu = int(dev.info()["compute_units"])
    per = 256 if dev.device.type & 1 << 1 else 4096       # CL_DEVICE_TYPE_CPU = 2
    return max(64, cu * per)


def photon_lanes(dev: Device, vol: Volume) -> int:
    """Photons per work item of the photon pass: on a CPU the SIMD width (photon_pass_lanes,
    kernels/photon_lanes.h: 16 where kernels may use 16-lane vectors, else 8), on a GPU 1 (its
    work items are its lanes: photon_pass).  Scenes with inclusions take photon_pass (the lanes'
    fast phase knows layers only), and oclgrind's simulator.  CLPPM_PHOTON_LANES (1, 4, 8 or 16)
    overrides, for benchmarks and tests."""
    import os
    from ..compute.device import wide_vectors
    env = os.environ.get("CLPPM_PHOTON_LANES")
    if getattr(vol, "ninc", 0):
        return 1
    if env:
        n = int(env)
        if n not in (1, 4, 8, 16):
            raise ValueError(f"CLPPM_PHOTON_LANES={env}: give 1, 4, 8 or 16")
        return n
    if not dev.device.type & 1 << 1:                        # CL_DEVICE_TYPE_CPU = 2
        return 1
    from ..compute.programs import implementation
    if implementation(dev.device) == "oclgrind":           # a simulator: lanes cost it 7x per photon
        return 1                                            # (clppm.checks.tiny checks them there)
    return 16 if wide_vectors(dev.device) else 8


@dataclass
class Tallies:
    """Exact integer tallies, per band, in units of W0 per photon."""

    nb: int
    nl: int
    counts: list = field(default_factory=list)   # [band][category] python ints
    emitted: int = 0

    def __post_init__(self):
        if not self.counts:
            self.counts = [[0] * (len(CATEGORIES) + self.nl) for _ in range(self.nb)]

    def add(self, arr: np.ndarray, emitted: int) -> None:
        for b in range(self.nb):
            row = self.counts[b]
            for c, v in enumerate(arr[b].tolist()):
                row[c] += int(v)
        self.emitted += emitted

    def total(self) -> np.ndarray:
        """(categories,) totals over bands as float fractions of the emitted weight."""
        tot = [sum(self.counts[b][c] for b in range(self.nb)) for c in range(len(self.counts[0]))]
        return np.array([t / (W0 * max(self.emitted, 1)) for t in tot])

    def balance_error(self) -> float:
        """Exact bookkeeping: all categories minus roulette gains equals the emitted weight."""
        cats = BALANCE + list(range(NA, NA + self.nl))
        tot = sum(sum(self.counts[b][c] for c in cats) for b in range(self.nb))
        gain = sum(self.counts[b][4] for b in range(self.nb))
        tot -= 2 * gain                             # gains were counted once in 'tot'
        return abs(tot - W0 * self.emitted) / (W0 * max(self.emitted, 1))


STORAGE = {"all": 0, "importance": 1}


def qmc_shift(seed: int, pass_index: int) -> tuple[int, int, int]:
    """The Cranley-Patterson shift of a pass's emission sequence: three uniform 32-bit words
    from Philox keyed by the seed, counter = the pass (a function of (seed, pass) alone)."""
    g = np.random.Generator(np.random.Philox(key=int(seed) & (2**64 - 1), counter=[int(pass_index), 0, 0, 7]))
    return tuple(int(v) for v in g.integers(0, 2**32, size=3, dtype=np.uint64))


def storage_importance(vol: Volume) -> np.ndarray:
    """(NL*NB + 2*NL, 2) float32 for importance-driven storage (kernels/photon.cl): per layer and
    band the optical depth of a vertical path from the surface to the layer's nominal top and
    that top's z (um); then per layer the bound's extremes over the bands: (least optical depth
    at the top, least mu_t), (the top's z, least g, or -1 where some g < 0)."""
    depth = vol.layer_depths()[:-1]
    od = np.zeros((vol.nl, vol.nb))
    for L in range(1, vol.nl):
        od[L] = od[L - 1] + vol.mut[L - 1] * vol.thickness[L - 1]
    t = np.stack([od, np.broadcast_to(-depth[:, None], od.shape)], -1).reshape(-1, 2)
    g = vol.g.astype(np.float64)
    gmin = np.where(g.min(1) >= 0, g.min(1), -1.0)
    # float32 rounding of the per-band entries could put a band's od or mu_t below a bound taken
    # in float64: take the extremes of the float32 values the kernel reads
    od32, mut32 = od.astype(np.float32), vol.mut.astype(np.float32)
    b = np.stack([np.stack([od32.min(1), mut32.min(1)], -1),
                  np.stack([-depth.astype(np.float32), gmin.astype(np.float32)], -1)], 1).reshape(-1, 2)
    return np.ascontiguousarray(np.concatenate([t, b]), np.float32)


#: photons one launch may store beyond a pass's target (its last photons overshoot it)
OVERSHOOT = 4096
# A pass emits at most EMIT_PER_TARGET photons per photon it is to store (and at least EMIT_MIN):
# where fewer reach what the camera sees, the pass ends with the photons it has instead of
# running on for hours; the estimate divides by the photons emitted, so it stays right, only
# noisier.  A pass that has stored nothing after EMIT_MIN photons ends there.
EMIT_PER_TARGET = 4096
EMIT_MIN = 1 << 22
#: a render's photon buffer holds this many times the target, plus OVERSHOOT
CAPACITY_FACTOR = 1.2


def capacity_for(target: int) -> int:
    """The photon buffer a render with ``target`` stored photons per pass allocates."""
    return int(target * CAPACITY_FACTOR) + OVERSHOOT


class PhotonPass:
    """Device state for photon passes of one scene."""

    @classmethod
    def of_config(cls, dev: Device, vol: Volume, cfg: dict, seed: int | None = None, **kw) -> "PhotonPass":
        """The photon passes of a config rendered with its own values (``seed``: the run's,
        else ``render.seed``), on the model ``vol`` built from it: the tools' and tests' way in."""
        return cls(dev, Scene.of_config(cfg, volume=vol, seed=seed), **kw)

    def __init__(self, dev: Device, scene: Scene, capacity: int = 0, vbuf: VolumeBuffers | None = None,
                 bands: Bands | None = None, counters: bool = False, plain_walk: bool = False,
                 lanes: int | None = None):
        """``scene``: the render's (its model, light, seed and storage depth).  ``bands``: the
        spectral sampling (default: one band per path, the hero drawn from the light's
        spectrum); the tallies follow the hero band alone, so it does not change them.
        ``counters``: build with the event counters (photon.cl PHOTON_COUNTERS; read them with
        :meth:`counts`).  ``plain_walk`` (tests): on the smooth surfaces, the other passes' walk
        (photon.cl PHOTON_PLAIN_WALK).  ``lanes``: photons per work item (default
        :func:`photon_lanes`: the device's)."""
        import pyopencl as cl
        vol = scene.volume
        self.dev, self.vol, self.scene = dev, vol, scene
        self.bands = bands or scene.bands(hero=1, sampling="power")
        self.hero = self.bands.hero
        if vol.maps is not None and self.hero > 1:
            # kernels/maps.h: delta tracking through the maps with one band per path
            raise ValueError(f"chromophore maps are traced with one band per path, not {self.hero}")
        self.counters = bool(counters)
        self.lanes = photon_lanes(dev, vol) if lanes is None else int(lanes)
        self.items = max(1, persistent_items(dev) // self.lanes)
        self.plain_walk = bool(plain_walk)
        self._build(depth_roulette=False)
        self.vbuf = vbuf or upload_volume(dev, vol)
        self.spectrum = self.bands.spectrum
        self.band = self.bands.fixed
        self.pi = self.bands.pdf
        cdf = np.cumsum(self.pi).astype(np.float32)
        cdf[-1] = 1.0
        mf = cl.mem_flags
        self.cdf = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=cdf)
        spi = np.ascontiguousarray(np.stack([self.spectrum, self.pi], -1), np.float32)
        if self.band >= 0:
            spi[:] = 1.0                    # every photon is of the one band: weight 1
        self.band_spi = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=spi)
        self.logmu = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=band_table(vol, self.hero))
        p = S.new_params()
        volume_params(p, vol)
        self.light = scene.light
        self.power_fraction = source_params(p, self.light, vol)
        # of the light's cone, the part the photons are emitted into (the footprint's solid angle
        # for a point light, photon.cl footprint_dir): trace_report gives the tallies per photon
        # of the cone, with the rest as missed, comparable whatever the emission
        self.emission_share = (self.power_fraction / (float(p["cone_omc"][0]) / 2.0)
                               if self.light.kind == "point" else 1.0)
        self.seed = scene.seed
        p["seed_lo"], p["seed_hi"] = S.split_seed(self.seed)
        p["fixed_band"] = self.band
        sd = scene.settings.store_depth_um
        if sd is not None:
            p["store_zmin"] = -sd
        self.p = p
        self.nc = len(CATEGORIES) + vol.nmat     # absorption per layer, then per inclusion
        self.tally_host = np.zeros((vol.nb, self.nc), np.int64)
        self.tally_buf = cl.Buffer(dev.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=self.tally_host)
        self.count_buf = cl.Buffer(dev.ctx, mf.READ_WRITE, 8)      # stored events, photons taken
        self.capacity = int(capacity)
        cap = max(self.capacity, 1)
        self.pos_w = cl.Buffer(dev.ctx, mf.READ_WRITE, 16 * cap)
        self.dir_b = cl.Buffer(dev.ctx, mf.READ_WRITE, 16 * cap)
        self.extra = cl.Buffer(dev.ctx, mf.READ_WRITE, 4 * max(cap * (self.hero - 1), 1))
        self.tallies = Tallies(vol.nb, vol.nmat)
        self.pbuf = cl.Buffer(dev.ctx, mf.READ_ONLY, S.PARAMS_DTYPE.itemsize)
        self._uploaded = b""                  # the Params bytes on the device
        self.truncated = False
        self.store_imp = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=storage_importance(vol))
        self.tile_z = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR,
                                hostbuf=np.zeros(2, np.float32) if vol.flat or vol.smooth_walk
                                else tile_bounds(vol))    # the smooth walk has its own cells
        if self.counters:
            self.counter_host = np.zeros(len(COUNTERS), np.int64)
            self.counter_buf = cl.Buffer(dev.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=self.counter_host)
            self.lane_buf = cl.Buffer(dev.ctx, mf.READ_WRITE, 8 * (self.items + 64))
            self.lane_steps: list[np.ndarray] = []
        else:       # the kernel declares them always and touches them only in counter builds
            self.counter_buf = self.lane_buf = cl.Buffer(dev.ctx, mf.READ_WRITE, 8)
        self._upload_params()

    def set_emission(self, how: str) -> None:
        """"random" (Philox per photon) or "qmc" (a randomly shifted R3 sequence per pass)."""
        self.p["qmc"] = 1 if how == "qmc" else 0

    def set_storage(self, rule: str, cone_deg: float = 0.0, scale: float = 1.0, qmin: float = 1.0) -> None:
        """Storage rule of later passes: "all" events, or "importance" (see photon.cl): store with
        probability clamp(scale * importance, qmin, 1), eye directions within cone_deg of +z."""
        self.p["store_rule"] = STORAGE[rule]
        c = math.radians(max(0.0, min(float(cone_deg), 90.0)))
        self.p["store_cos"], self.p["store_sin"] = math.cos(c), math.sin(c)
        self.p["store_scale"], self.p["store_qmin"] = float(scale), float(qmin)

    def _build(self, depth_roulette: bool) -> None:
        """The photon pass's program (pyopencl's cache keeps each build), with or without the
        depth roulette (photon.cl DEPTH_ROULETTE)."""
        self.depth_roulette = depth_roulette
        self.prg = self.dev.build("photon.cl", kernel_defines(
            self.vol, hero=self.hero, pt_fp64=surface_fp64(self.dev, self.vol), photon_counters=self.counters,
            photon_plain_walk=self.plain_walk, depth_roulette=depth_roulette, photon_lanes=self.lanes))
        self.kernel = Kernel(self.prg, "photon_pass_lanes" if self.lanes > 1 else "photon_pass")

    def set_storage_depth(self, zmin_um: float, roulette_um: float = 0.0) -> None:
        """Store no event below ``zmin_um`` (they could never be gathered), and with
        ``roulette_um`` > 0 play Russian roulette (survival 1/2, weight x2; unbiased) when a
        photon first reaches each plane ``roulette_um`` apart from ``roulette_um`` below that
        depth (photon.cl deep_roulette): light that goes deeper returns ever less often."""
        self.p["store_zmin"] = zmin_um
        on = roulette_um > 0.0
        if on:                            # read only by the DEPTH_ROULETTE build
            self.p["deep_z0"], self.p["deep_dz"] = zmin_um - roulette_um, roulette_um
        if on != self.depth_roulette:
            self._build(on)

    def _upload_params(self) -> None:
        """The scene's constants (Params) to the device when they changed since the last upload
        (the storage rule and depth are set before the first pass): once per render."""
        import pyopencl as cl
        b = self.p.tobytes()
        if b != self._uploaded:
            cl.enqueue_copy(self.dev.queue, self.pbuf, self.p)
            self._uploaded = b

    def _launch(self, n: int, offset: int, pass_index: int, capacity: int) -> None:
        import pyopencl as cl
        q = self.dev.queue
        if (offset & 0xFFFFFFFF) + n > 2**32:
            raise ValueError("a launch must not cross a multiple of 2^32 photons")
        L = np.zeros(1, S.PHOTON_LAUNCH_DTYPE)[0]
        L["photon_offset"], L["offset_hi"] = offset & 0xFFFFFFFF, offset >> 32
        L["pass_"], L["capacity"], L["count"] = pass_index, capacity, n
        if self.p["qmc"][0]:
            L["qmc_s0"], L["qmc_s1"], L["qmc_s2"] = qmc_shift(self.seed, pass_index)
        self._upload_params()
        cl.enqueue_copy(q, self.count_buf, np.zeros(1, np.uint32), dst_offset=4)   # no photon taken yet
        items = min(-(-n // self.lanes), self.items)
        # a lanes work item is a SIMD group already: work groups of one (PoCL would otherwise loop
        # over a group's work items with every one's lane state in memory)
        want = 1 if self.lanes > 1 else 64
        self.kernel(q, items, want=want, launch=L, **self.vbuf.named(self.pbuf), store_imp=self.store_imp,
                    band_cdf=self.cdf,
                    band_spi=self.band_spi, logmu=self.logmu, store_pos_w=self.pos_w,
                    store_dir_b=self.dir_b, store_extra=self.extra, store_count=self.count_buf,
                    tallies=self.tally_buf, smooth=self.vbuf.smooth, tile_z=self.tile_z,
                    counters=self.counter_buf, lane_steps=self.lane_buf)
        if self.counters:
            steps = np.empty((launch(self.kernel.kernel, q, items, want)[0][0], 2), np.uint32)
            cl.enqueue_copy(q, steps, self.lane_buf)
            self.lane_steps.append(steps[:items])

    def counts(self, reset: bool = True) -> dict:
        """The event counters summed over the launches so far (``counters=True`` builds), and per
        work item launched its transport steps and loop iterations (``lane_steps``, one (items, 2)
        array per launch)."""
        import pyopencl as cl
        cl.enqueue_copy(self.dev.queue, self.counter_host, self.counter_buf)
        out = dict(zip(COUNTERS, (int(v) for v in self.counter_host)))
        out["lane_steps"] = self.lane_steps
        if reset:
            self.counter_host[:] = 0
            cl.enqueue_copy(self.dev.queue, self.counter_buf, self.counter_host)
            self.lane_steps = []
        return out

    def _flush(self, emitted: int, into: Tallies | None = None) -> np.ndarray:
        import pyopencl as cl
        q = self.dev.queue
        cl.enqueue_copy(q, self.tally_host, self.tally_buf)
        arr = self.tally_host.copy()
        (into or self.tallies).add(arr, emitted)
        self.tally_host[:] = 0
        cl.enqueue_copy(q, self.tally_buf, self.tally_host)
        return arr

    def _count(self) -> int:
        import pyopencl as cl
        c = np.zeros(1, np.uint32)
        cl.enqueue_copy(self.dev.queue, c, self.count_buf)
        return int(c[0])

    def _set_count(self, v: int) -> None:
        import pyopencl as cl
        cl.enqueue_copy(self.dev.queue, self.count_buf, np.array([v], np.uint32))

    def trace(self, n_photons: int, pass_index: int = 0, batches: int = 1) -> list[np.ndarray]:
        """Trace ``n_photons`` without storing; return per-batch tally arrays (for errors)."""
        out = []
        per = [n_photons // batches + (1 if i < n_photons % batches else 0) for i in range(batches)]
        offset = 0
        for nb_ in per:
            acc = np.zeros((self.vol.nb, self.nc), np.int64)
            done = 0
            while done < nb_:
                n = min(MAX_LAUNCH, nb_ - done, 2**32 - (offset & 0xFFFFFFFF))
                self._set_count(0)
                self._launch(n, offset, pass_index, 0)
                acc += self._flush(n)
                offset += n; done += n
            out.append(acc)
        return out

    def run_pass(self, pass_index: int, target: int, tallies: Tallies | None = None) -> dict:
        """Emit photons until at least ``target`` scattering events are stored, or
        ``max(EMIT_MIN, EMIT_PER_TARGET * target)`` photons are emitted (``capped``), or none is
        stored after ``EMIT_MIN``.

        Returns emitted and stored counts; the stored photons are in ``pos_w``/``dir_b``.
        The exit and absorption tallies go to ``tallies`` (default: this pass object's own).
        """
        cap = self.capacity
        if target + OVERSHOOT > cap:
            raise ValueError(f"photon buffer capacity {cap} must exceed the target {target} "
                             f"by at least {OVERSHOOT} (one launch's last photons overshoot it)")
        self._set_count(0)
        stored, emitted, launches = 0, 0, 0
        cap_emitted = max(EMIT_MIN, EMIT_PER_TARGET * int(target))
        per_photon = None
        while stored < target and emitted < cap_emitted:
            if per_photon is None:
                n = 256
            else:
                n = int(math.ceil((target - stored) / max(per_photon, 1e-3) * 1.05)) + 16
            room = cap - stored
            if per_photon is not None:
                n = min(n, max(1, int(room / max(per_photon, 1e-3) * 0.5)))
            n = max(1, min(n, MAX_LAUNCH))
            if per_photon is not None:
                n = min(n, max(256, 4 * emitted))     # grow geometrically: no hour-long launch
            n = min(n, cap_emitted - emitted, 2**32 - (emitted & 0xFFFFFFFF))   # no launch across 2^32
            while True:
                self._launch(n, emitted, pass_index, cap)
                c = self._count()
                if c <= cap:
                    break
                if n == 1:
                    # one photon scattered more often than the buffer holds: its first events
                    # were written in order, keep what fits (deterministic)
                    self._set_count(cap)
                    c = cap
                    self.truncated = True
                    break
                # overflow: the batch is deterministic, so halve it and redo it
                self._set_count(stored)
                self.tally_host[:] = 0
                import pyopencl as cl
                cl.enqueue_copy(self.dev.queue, self.tally_buf, self.tally_host)
                n = max(1, n // 2)
            self._flush(n, tallies)
            emitted += n
            stored = c
            launches += 1
            per_photon = stored / emitted
            if per_photon == 0 and emitted >= EMIT_MIN:
                break                     # no photon reaches the stored region
        return {"emitted": emitted, "stored": stored, "launches": launches,
                "capped": stored < target and emitted >= cap_emitted}


def trace_report(pp: PhotonPass, n_photons: int, batches: int = 10) -> dict:
    """Tallies with standard errors (batch means), per band and integrated."""
    arrs = pp.trace(n_photons, batches=batches)
    sizes = [n_photons // batches + (1 if i < n_photons % batches else 0) for i in range(batches)]
    fr = np.array([a.sum(0) / (W0 * s) for a, s in zip(arrs, sizes)])      # (batches, nc)
    tot = sum(a.sum(0).astype(object) for a in arrs)
    mean = np.array([int(t) / (W0 * n_photons) for t in tot])
    se = fr.std(0, ddof=1) / math.sqrt(len(arrs)) if len(arrs) > 1 else np.zeros_like(mean)
    # per photon of the light's cone: the directions not emitted into missed the model
    share = pp.emission_share
    mean, se = mean * share, se * share
    mean[6] += 1.0 - share
    nl = pp.vol.nmat                       # absorbing materials: the layers, then the inclusions
    inc_names = [f"inclusion[{i}]" for i in range(pp.vol.ninc)]
    names = CATEGORIES + [f"absorbed[{n}]" for n in pp.vol.names + inc_names]
    band_tot = sum(a.astype(object) for a in arrs)
    # per band, as fraction of the photons emitted in that band (expected count for D65)
    per_band = {}
    for b, wl in enumerate(pp.vol.wl):
        row = band_tot[b]
        w = sum(int(row[c]) for c in BALANCE + list(range(NA, NA + nl))) - 2 * int(row[4])
        n_b = max(w / W0, 1e-300)
        per_band[f"{wl:g}"] = {
            "photons": round(n_b, 3),
            "specular": share * int(row[0]) / W0 / n_b, "Rd": share * int(row[1]) / W0 / n_b,
            "Tt": share * int(row[2]) / W0 / n_b,
            "A": share * sum(int(row[NA + i]) for i in range(nl)) / W0 / n_b,
            "Rd_cone": share * int(row[7]) / W0 / n_b,
        }
    A = float(mean[NA:].sum())
    A_se = float(np.sqrt((se[NA:] ** 2).sum()))
    total_bal = sum(int(tot[c]) for c in BALANCE + list(range(NA, NA + nl))) - 2 * int(tot[4])
    return {
        "photons": n_photons,
        "specular": float(mean[0]), "specular_se": float(se[0]),
        "Rd": float(mean[1]), "Rd_se": float(se[1]),
        "Tt": float(mean[2]), "Tt_se": float(se[2]),
        "A": A, "A_se": A_se,
        "lost": float(mean[3]), "missed": float(mean[6]), "missed_excluded": 1.0 - share,
        "roulette_net": float(mean[4] - mean[5]),
        "energy_balance_error": abs(total_bal - W0 * n_photons) / (W0 * n_photons),
        "Rd_cone": float(mean[7]), "Rd_cone_se": float(se[7]),
        "rcone_cos": float(pp.p["rcone_cos"][0]),
        "absorbed_per_layer": {n: float(v) for n, v in zip(pp.vol.names, mean[NA:NA + pp.vol.nl])},
        **({"absorbed_per_inclusion": {n: float(v) for n, v in zip(inc_names, mean[NA + pp.vol.nl:])},
            "absorbed_per_inclusion_se": {n: float(v) for n, v in zip(inc_names, se[NA + pp.vol.nl:])}}
           if inc_names else {}),
        "per_band": per_band,
        "categories": dict(zip(names, map(float, mean))),
    }
