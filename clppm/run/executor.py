"""Passes on a Dask cluster: every device of a machine, or many machines; the same bytes.

The engine is dask.distributed: ``--devices`` starts a local cluster with one worker process
per listed device, ``--scheduler`` (or ``CLPPM_SCHEDULER``) joins a running ``dask scheduler``
with its ``dask worker``s.  Nothing here schedules, retries or moves data itself.

Client (:func:`clppm.run.entry.render_distributed`): one worker builds the scene, plans its
tiles of sample points (``render.tile_points``) and calibrates (R0 per sample point, the
storage depth); the request, the tiles and the calibration then travel to the workers once, as
task results the pieces depend on (a lost copy is recomputed, unlike scattered data).  A task
is one piece: one tile's pixels over one chunk of passes
(:meth:`clppm.integrators.ppm.Pipeline.run_tile`).  It gets that tile's R0 alone, loads that
tile's sample points alone, runs the chunk's photon passes (pass p's photons depend on p
alone, so every tile sees the in-process photons) and returns the sums of the tile's pixels,
so a worker never holds more points than the largest tile, nor more sums than a tile's, at
any resolution.  The client joins a chunk's pieces once all have come (tiles are disjoint
pixel ranges in order), and adds the chunk sums in chunk order, holding chunks that arrive
early (:class:`Reduction`): per pixel the float64 total takes the same terms in the same order
as the in-process loop, so the EXR is byte-identical to a render in this process
(``clppm.run.entry.render``) with the same seed and ``render.chunk_passes`` on the same kind of
device, with one tile or many.  A piece whose worker dies is rerun by Dask; since a piece is a
pure function of (request, tiles, calibration, tile, passes), the rerun gives the same bits,
and each piece is taken once.  Checkpoints hold the reduced sums, the whole chunks held and
which passes they cover (:mod:`clppm.output.checkpoint`; a chunk with pieces missing is rerun
after a resume); they are in-process checkpoints too, and an in-process checkpoint taken inside
a chunk resumes here by continuing that chunk's tiles from its sums.

Worker (:class:`ClppmWorker`, a ``WorkerPlugin``): the device is the one the worker process
was started with (``PYOPENCL_CTX``, else clppm's default choice); the scene (volume, eye pass
counts, buffers, kernels) is built once per scene key (``RenderRequest.scene_key``) and tile
plan and kept, one at a time.  The tiles are the calibrating worker's plan on every worker
(another device's memory could plan others).  A lock runs one piece at a time per worker,
whatever ``--nthreads`` says: a scene's buffers are not shared.

Only ``render.radius = "global"`` distributes.  With the per-point radius ("ppm") pass p needs
the R and N that passes 0..p-1 left at every point, so passes form one chain; independent
chains, each with its own radii, would be a different estimator (larger radii, more bias per
pass) whose image depends on the number of chains, so one seed would no longer give one
image.  A distributed ``ppm`` render is refused with one line naming ``render.radius``.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import threading
import time
import uuid
from dataclasses import dataclass, field

import numpy as np
from distributed import WorkerPlugin

from ..output import checkpoint as ckpt
from ..integrators import photonpass, ppm
from ..output import film
from . import progressive
from ..config import ConfigError, RenderSettings
from ..compute.device import DeviceError
from ..request import Cluster, RenderRequest

CONNECT_TIMEOUT = 5.0        # s: an unreachable scheduler fails this fast
WORKER_WAIT = 10.0           # s: a scheduler without workers fails this fast
PLUGIN = "clppm"


class ExecutorError(RuntimeError):
    """The cluster cannot run this render (no scheduler, no workers, a worker without a device);
    ``str()`` is the whole one-line message (exit 2)."""


# ----------------------------------------------------------------------------------- worker side
@dataclass
class _Loaded:
    """A scene on a worker's device and the calibration applied to it."""

    key: str
    sc: ppm.Pipeline
    cal_key: str | None = None

    def calibrated(self, cal: ppm.Calibration, cal_key: str) -> "_Loaded":
        """``cal`` applied (its storage depth; ``cal``: a head, without R0, will do)."""
        if self.cal_key != cal_key:
            self.sc.apply(cal)
            self.cal_key = cal_key
        return self


class ClppmWorker(WorkerPlugin):
    """Worker plugin: the worker's device and its last scene (one render's, keyed by hash)."""

    name = PLUGIN
    idempotent = True            # a second render's registration keeps the loaded scene

    def setup(self, worker=None):
        self.lock = threading.Lock()
        self.loaded: _Loaded | None = None

    def scene(self, req: RenderRequest, key: str, fresh: bool = False, plan: list | None = None) -> _Loaded:
        """The scene of ``req`` on this worker's device, built on first use with the tiles
        ``plan`` (None: planned here), the lock held."""
        from ..compute.device import open_device
        ld = self.loaded
        if (fresh or ld is None or ld.key != key
                or (plan is not None and ld.sc.tiles.tiles != [tuple(t) for t in plan])):
            self.loaded = None           # free the previous scene's device memory first
            self.loaded = _Loaded(key=key, sc=ppm.Pipeline.build(req, open_device(None), plan=plan))
        return self.loaded


def dask_setup(worker) -> None:
    """Preload hook of :func:`local_cluster`'s workers (``preload=["clppm.run.executor"]``): they
    share the client's terminal, and Ctrl-C is the client's to handle (stop, checkpoint, image),
    not a reason for its workers to die under it."""
    import signal
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:                    # not the main thread: nothing to do
        pass


def _plugin() -> ClppmWorker:
    from distributed import get_worker
    w = get_worker()
    plug = w.plugins.get(PLUGIN)
    if plug is None:                      # joined while the plugin was being registered
        plug = ClppmWorker()
        plug.setup(w)
        w.plugins[PLUGIN] = plug
    return plug


def _worker_errors(fn):
    """Config errors cross the wire as ExecutorError (ConfigError does not unpickle)."""
    def wrapped(*a, **k):
        try:
            return fn(*a, **k)
        except ConfigError as e:
            raise ExecutorError(str(e)) from None
    wrapped.__name__ = wrapped.__qualname__ = fn.__name__
    return wrapped


def probe_device() -> dict:
    """Run on every worker before any work: its OpenCL device, or why it has none."""
    from ..compute.device import describe, open_device
    try:
        dev = open_device(None)
        info = describe(dev.device)
        return {"device": dev.name, "type": info["type"], "pid": os.getpid()}
    except DeviceError as e:
        return {"error": " ".join(str(e).split())}
    except Exception as e:                 # pyopencl's own errors: still one line
        return {"error": f"{type(e).__name__}: {' '.join(str(e).split())}"}


@_worker_errors
def scene_task(req: RenderRequest, key: str, calibrate: bool) -> dict:
    """Build the scene; calibrate it on a fresh one (as the in-process run does)."""
    plug = _plugin()
    with plug.lock:
        ld = plug.scene(req, key, fresh=calibrate)
        sc = ld.sc
        cal = None
        if calibrate:
            t0 = time.perf_counter()
            cal = sc.calibrate()
            sc.dev.queue.finish()
            sc.timing["calibration"] = time.perf_counter() - t0
        meta = progressive.run_identity(req, sc)
        timing = {k: v for k, v in sc.timing.items() if k not in ppm.STAGES}
        return {"meta": meta, "cal": cal, "timing": timing, "npix": sc.npix, "nb": sc.vol.nb,
                "tallies": photonpass.Tallies(sc.vol.nb, sc.vol.nmat).counts, "tiles": list(sc.tiles.tiles),
                "point_ranges": [sc.tiles.point_range(t) for t in range(sc.ntiles)]}


@dataclass
class ChunkDone:
    """A piece's result (one tile over one chunk) and where and how long it ran (the task's
    own wall time)."""

    result: ppm.ChunkResult
    worker: str
    wall: float
    points: int = 0                  # sample points the worker held for it (its tile's)


@_worker_errors
def tile_task(req: RenderRequest, key: str, plan: list, cal: ppm.Calibration, cal_key: str,
              R0: np.ndarray, tile: int, passes: list, start: np.ndarray | None = None) -> ChunkDone:
    """Tile ``tile`` over one chunk of passes (``cal``: the calibration's head; ``R0``: the
    tile's points' radii; ``start``: the tile's part of the chunk's earlier sums, to continue)."""
    from distributed import get_worker
    plug = _plugin()
    with plug.lock:
        t0 = time.perf_counter()
        ld = plug.scene(req, key, plan=plan).calibrated(cal, cal_key)
        chunk = passes[0] // int(req.settings.chunk_passes)
        res = ld.sc.run_tile(cal, R0, tile, chunk, passes, start)
        return ChunkDone(result=res, worker=get_worker().address, wall=time.perf_counter() - t0,
                         points=ld.sc.npts)


@_worker_errors
def finish_task(req: RenderRequest, key: str, plan: list, cal: ppm.Calibration, cal_key: str,
                pix: np.ndarray, pairs: int, emitted_total: int, passes_done: int, timing: dict,
                stats: dict, elapsed: float, interrupted: bool):
    """The image and report of the reduced sums (:func:`progressive.finish`, on a worker: it
    needs the scene's volume, eye pass and light spectrum)."""
    plug = _plugin()
    with plug.lock:
        ld = plug.scene(req, key, plan=plan).calibrated(cal, cal_key)
        return progressive.finish(ld.sc, pix, pairs, emitted_total, passes_done, timing, stats,
                                  time.perf_counter() - elapsed, interrupted)


def _value(x):
    """A task that returns its argument: data the chunks depend on, recomputable if lost."""
    return x


# ----------------------------------------------------------------------------------- client side
def check_distributable(rs: RenderSettings, how: str) -> None:
    radius = rs.radius
    if radius != "global":
        raise ConfigError(how, "render.radius", radius,
                          "the per-point radius makes every pass depend on all earlier ones; "
                          "a distributed render needs render.radius = \"global\" (--radius global)")


def parse_devices(spec: str) -> list[str]:
    """``all`` or ``P:D,P:D`` -> usable local devices as ``P:D`` (a device may repeat: one worker
    per entry).  Bad entries -> one line naming --devices."""
    from ..compute.device import device_problem, list_devices
    devs = {f"{ip}:{idev}": d for ip, idev, _, d in list_devices()}
    if spec.strip().lower() == "all":
        out = [k for k, d in devs.items() if device_problem(d, k) is None]
        if not out:
            raise ConfigError("command line", "--devices", spec, "no usable OpenCL device here "
                              "(`clppm devices` lists them)")
        return out
    out = []
    for part in (p.strip() for p in spec.split(",")):
        if ":" not in part:
            part += ":0"
        if part not in devs:
            raise ConfigError("command line", "--devices", spec,
                              f"no device {part}; `clppm devices` lists {', '.join(devs) or 'none'}")
        why = device_problem(devs[part], part)
        if why:
            raise ConfigError("command line", "--devices", spec, f"device {part} is not usable: {why}")
        out.append(part)
    return out


def worker_env(devices: list[str]) -> list[dict]:
    """Per worker: its device (PYOPENCL_CTX) and, for PoCL CPU workers sharing this machine, an
    equal share of the cores (POCL_MAX_PTHREAD_COUNT), so they do not oversubscribe it."""
    from ..compute.device import list_devices
    import pyopencl as cl
    kinds = {f"{ip}:{idev}": d.type for ip, idev, _, d in list_devices()}
    cpu = [bool(kinds[d] & cl.device_type.CPU) for d in devices]
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    share = max(1, cores // max(sum(cpu), 1))
    return [{"PYOPENCL_CTX": d, **({"POCL_MAX_PTHREAD_COUNT": str(share)} if c else {})}
            for d, c in zip(devices, cpu)]


def local_cluster(devices: list[str] | None = None, envs: list[dict] | None = None):
    """A cluster on this machine: one single-threaded worker process (a Nanny, so a dead worker
    is restarted) per entry of ``envs`` (default: :func:`worker_env` of ``devices``)."""
    import logging
    from distributed import Nanny, Scheduler, SpecCluster
    envs = envs if envs is not None else worker_env(devices or [])
    # task errors come back to the client as exceptions: the workers' own logs would repeat them
    opts = {"nthreads": 1, "memory_limit": 0, "silence_logs": logging.CRITICAL, "preload": [__name__]}
    workers = {f"clppm-{i}": {"cls": Nanny, "options": {**opts, "env": e}} for i, e in enumerate(envs)}
    sched = {"cls": Scheduler, "options": {"host": "127.0.0.1", "port": 0, "dashboard": False,
                                           "dashboard_address": ":0"}}
    return SpecCluster(workers=workers, scheduler=sched, silence_logs=logging.ERROR, name="clppm")


@contextlib.contextmanager
def connect(scheduler: str | None = None, devices: list[str] | None = None, client=None,
            flag: str = "--scheduler"):
    """A Client: the given one, the scheduler at ``scheduler``, a local cluster on ``devices``,
    or (none of these) one in-process worker thread."""
    from distributed import Client, LocalCluster
    if client is not None:
        yield client
        return
    if scheduler:
        try:
            c = Client(scheduler, timeout=CONNECT_TIMEOUT, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as e:
            why = " ".join(str(e).split()) or type(e).__name__
            raise ConfigError("command line", flag, scheduler,
                              f"no Dask scheduler answers there within {CONNECT_TIMEOUT:g} s ({why[:120]})") from None
        with c:
            yield c
        return
    if devices:
        cluster = local_cluster(devices)
    else:
        cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    with cluster, Client(cluster, set_as_default=False) as c:
        yield c


def check_workers(client, where: str) -> dict:
    """Every worker's device; one line (ExecutorError) for no workers or a worker without one."""
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT)
    except TimeoutError:
        raise ExecutorError(f"{where} has no workers after {WORKER_WAIT:g} s; start one per device: "
                            f"PYOPENCL_CTX=P:D dask worker ADDRESS --nthreads 1") from None
    client.register_plugin(ClppmWorker(), name=PLUGIN)
    found = client.run(probe_device)
    bad = {a: r["error"] for a, r in found.items() if "error" in r}
    if bad:
        addr, why = sorted(bad.items())[0]
        more = f" (and {len(bad) - 1} more workers)" if len(bad) > 1 else ""
        raise ExecutorError(f"worker {addr}{more} has no usable OpenCL device: {why}")
    return found


def cal_hash(cal: ppm.Calibration) -> str:
    h = hashlib.sha256(np.ascontiguousarray(cal.R0).tobytes())
    h.update(repr((cal.store_zmin, cal.first_search_mean)).encode())
    return h.hexdigest()[:16]


def pieces(start: int, n_passes: int, k: int) -> list[list[int]]:
    """Passes start..n_passes-1 in chunks that end at multiples of k (the in-process loop's
    chunks, also after a resume that began inside one)."""
    out, p = [], start
    while p < n_passes:
        end = min((p // k + 1) * k, n_passes)
        out.append(list(range(p, end)))
        p = end
    return out


def join(parts: dict) -> ppm.ChunkResult:
    """A chunk's pieces (tile -> piece, every tile's) as the chunk: the tiles' sums side by side
    (the tiles are the image's pixels in order), the chunk's counts (each piece has them) and
    the seconds the pieces took together."""
    first = parts[min(parts)]
    if len(parts) == 1:
        return first
    order = [parts[t] for t in sorted(parts)]
    seconds: dict = {}
    for r in order:
        for k, v in r.seconds.items():
            seconds[k] = seconds.get(k, 0.0) + v
    return ppm.ChunkResult(chunk=first.chunk, passes=first.passes, pix=np.concatenate([r.pix for r in order]),
                           pairs=np.concatenate([r.pairs for r in order]), tallies=first.tallies,
                           emitted=first.emitted, stored=first.stored, seconds=seconds)


@dataclass
class Reduction:
    """The client's running sum: a chunk's tile pieces joined once all have come, chunks added in
    pass order, early ones held until their turn."""

    pix: np.ndarray                  # float64 (npix * NB): chunks before ``next_pass``
    pairs: np.ndarray                # uint64 (npix)
    tallies: list                    # [band][category] python ints (exact)
    next_pass: int = 0               # passes before this are in pix (or in open_pix)
    open_pix: np.ndarray | None = None   # an in-process checkpoint's open chunk: its passes before
    #                                      next_pass, continued by the chunk that starts there
    held: dict = field(default_factory=dict)     # first pass -> ChunkResult
    emitted: list = field(default_factory=list)  # per pass, passes before next_pass
    stored: int = 0
    seconds: dict = field(default_factory=lambda: {k: 0.0 for k in ppm.STAGES})
    ntiles: int = 1                  # pieces per chunk
    parts: dict = field(default_factory=dict)    # first pass -> {tile: piece}: chunks not yet whole

    @classmethod
    def empty(cls, npix: int, nb: int, tallies: list, ntiles: int = 1) -> "Reduction":
        return cls(pix=np.zeros(npix * nb), pairs=np.zeros(npix, np.uint64), tallies=tallies, ntiles=ntiles)

    def add(self, r: ppm.ChunkResult) -> None:
        """Take a piece (each once: a rerun's duplicate is ignored); a chunk whose pieces have
        all come is held, and what is in order is reduced."""
        if r.passes[0] < self.next_pass or r.passes[0] in self.held:
            return
        parts = self.parts.setdefault(r.passes[0], {})
        if r.tile in parts:
            return
        parts[r.tile] = r
        if len(parts) < self.ntiles:
            return
        self.held[r.passes[0]] = join(self.parts.pop(r.passes[0]))
        while self.next_pass in self.held:
            c = self.held.pop(self.next_pass)
            self.open_pix = None             # c continued it: its sums include the open ones
            self.pix += c.pix
            self.pairs += c.pairs
            self.tallies = [[x + y for x, y in zip(a, b)] for a, b in zip(self.tallies, c.tallies)]
            self.emitted += list(c.emitted)
            self.stored += int(c.stored)
            for k, v in c.seconds.items():
                self.seconds[k] = self.seconds.get(k, 0.0) + v
            self.next_pass = c.passes[-1] + 1

    @property
    def finished(self) -> int:
        """Passes whose results the client holds, reduced or not."""
        return len(self.emitted) + sum(len(r.passes) for r in self.held.values())

    def covers(self, passes: list) -> bool:
        return passes[0] < self.next_pass or passes[0] in self.held

    # checkpoints --------------------------------------------------------------------------------
    def save(self, path: str, meta: dict, cal: ppm.Calibration, nb: int, timing: dict) -> None:
        held = [self.held[p] for p in sorted(self.held)]
        stats = {"emitted": self.emitted, "stored": self.stored,
                 "first_search_mean": cal.first_search_mean}
        state = dict(pass_index=self.next_pass, emitted_total=sum(self.emitted), store_zmin=cal.store_zmin,
                     tallies=self.tallies, tallies_emitted=sum(self.emitted), stats=stats,
                     timing={**timing, **self.seconds},
                     held=[{"passes": r.passes, "emitted": r.emitted, "stored": r.stored,
                            "tallies": r.tallies, "seconds": r.seconds} for r in held])
        none = np.zeros(0, np.float32)        # the global radius: no per-point state but R0
        open_pix = self.open_pix if self.open_pix is not None else np.zeros(0)   # none: written empty
        ckpt.save(path, meta, state, dict(pt_R=none, pt_N=none, R0=cal.R0, pix_acc=self.pix.reshape(-1, nb),
                                          chunk_acc=open_pix.reshape(-1, nb), pix_pairs=self.pairs,
                                          held_pix=np.stack([r.pix for r in held]) if held else None,
                                          held_pairs=np.stack([r.pairs for r in held]) if held else None))

    @classmethod
    def load(cls, st: dict, name: str, k: int, n_passes: int, ntiles: int = 1) -> "Reduction":
        p = st["pass_index"]
        open_pix = st["chunk_acc"].reshape(-1).astype(np.float64) if np.any(st["chunk_acc"]) else None
        pix = st["pix_acc"].reshape(-1).astype(np.float64)
        if not pix.size:                     # an in-process checkpoint before its first chunk closed
            pix = np.zeros(st["pix_pairs"].size * st["chunk_acc"].shape[-1])
        red = cls(pix=pix, pairs=st["pix_pairs"].astype(np.uint64),
                  tallies=st["tallies"], next_pass=p, open_pix=open_pix, emitted=list(st["stats"]["emitted"]),
                  stored=int(st["stats"]["stored"]), ntiles=ntiles,
                  seconds={k_: float(st["timing"].get(k_, 0.0)) for k_ in ppm.STAGES})
        plan = {tuple(q) for q in pieces(p, n_passes, k)}
        for h, hp, hq in zip(st["held"], st.get("held_pix", []), st.get("held_pairs", [])):
            if tuple(h["passes"]) in plan:   # a chunk of another pass count's plan is rerun
                red.held[h["passes"][0]] = ppm.ChunkResult(
                    chunk=h["passes"][0] // k, passes=h["passes"], pix=hp.astype(np.float64),
                    pairs=hq.astype(np.uint64), tallies=h["tallies"], emitted=h["emitted"],
                    stored=h["stored"], seconds=h.get("seconds", {}))
        return red


@contextlib.contextmanager
def open_run(req: RenderRequest, t_start: float):
    """The run of ``req`` on its cluster (after :func:`clppm.run.entry.render`'s checks): the
    cluster connected, its workers checked, the scene built and calibrated on one of them (or
    the checkpoint's sums loaded); the client is current while the run is stepped."""
    cl_ = req.cluster or Cluster()
    devices = parse_devices(cl_.devices) if isinstance(cl_.devices, str) else cl_.devices
    where = cl_.scheduler or ("local cluster" if devices else "client" if cl_.client else "in-process")
    with connect(cl_.scheduler, devices, cl_.client, cl_.flag) as c:
        workers = check_workers(c, f"scheduler {cl_.scheduler}" if cl_.scheduler else "the cluster")
        job = _Job.start(c, req, t_start, workers)
        run = DaskRun(job, job.reduction(req.resume), req.checkpoint, req.budget.on_chunk, where, workers)
        with c.as_current():
            yield run


@dataclass
class _Job:
    """One render on a cluster: the request and calibration as futures, and the run's identity."""

    client: object
    req: RenderRequest               # as the workers get it (RenderRequest.portable)
    key: str                         # scene hash (RenderRequest.scene_key)
    run: str                         # this call's token: task keys never collide across calls
    req_f: object
    meta: dict
    first: dict                      # scene_task's answer
    t_start: float
    cal: ppm.Calibration | None = None
    cal_f: object = None             # the calibration's head (no R0), on every worker
    cal_key: str = ""
    r0_f: dict = field(default_factory=dict)    # tile -> its points' R0, made when first needed
    timing: dict = field(default_factory=dict)

    @property
    def tiles(self) -> list:
        """The tiles' pixel ranges (the calibrating worker's plan)."""
        return self.first["tiles"]

    @classmethod
    def start(cls, c, req: RenderRequest, t_start, workers) -> "_Job":
        """Ship the request; one worker builds the scene and (no resume) calibrates."""
        key, run = req.scene_key(), uuid.uuid4().hex[:8]
        wreq = req.portable()
        req_f = c.submit(_value, wreq, key=f"clppm-config-{key}-{run}", pure=False)
        first = c.submit(scene_task, req_f, key, not req.resume, key=f"clppm-scene-{key}-{run}",
                         pure=False).result()
        meta = first["meta"]
        kinds = sorted({w["device"] for w in workers.values()})
        if len(kinds) > 1:                   # chunks may land on any kind: say so in the identity
            meta["device"] = " + ".join(kinds)
        return cls(client=c, req=wreq, key=key, run=run, req_f=req_f, meta=meta, first=first,
                   t_start=t_start)

    @property
    def n_passes(self) -> int:
        return int(self.req.settings.passes)

    @property
    def k(self) -> int:
        return int(self.req.settings.chunk_passes)

    def reduction(self, resume: str | None) -> Reduction:
        """The calibration (new, or the checkpoint's) on every worker, and the sums so far."""
        if resume:
            st = ckpt.load(resume, self.meta)
            self.cal = ppm.Calibration.from_checkpoint(st)
            red = Reduction.load(st, os.path.basename(resume), self.k, self.n_passes, len(self.tiles))
            self.timing = {k: v for k, v in st["timing"].items() if k not in ppm.STAGES}
        else:
            self.cal = self.first["cal"]
            red = Reduction.empty(self.first["npix"], self.first["nb"], self.first["tallies"], len(self.tiles))
            self.timing = dict(self.first["timing"])
        self.cal_key = cal_hash(self.cal)
        self.cal_f = self.client.submit(_value, self.cal.head(), key=f"clppm-cal-{self.cal_key}-{self.run}",
                                        pure=False)
        self.client.replicate([self.req_f, self.cal_f])    # on every worker: no pull toward one
        return red

    def r0(self, t: int):
        """Tile ``t``'s points' R0 as a task result (moved to the workers that load the tile)."""
        if t not in self.r0_f:
            a, b = self.first["point_ranges"][t]
            self.r0_f[t] = self.client.submit(_value, np.ascontiguousarray(self.cal.R0[a:b]),
                                              key=f"clppm-r0-{t}-{self.cal_key}-{self.run}", pure=False)
        return self.r0_f[t]

    def submit_piece(self, passes: list, t: int, red: Reduction, worker: str | None = None):
        """Tile ``t`` over chunk ``passes`` as a task, placed on ``worker`` first (a loose
        restriction: an idle worker may still steal it)."""
        start = None
        if red.open_pix is not None and passes[0] == red.next_pass:
            p0, p1 = self.tiles[t]
            nb = self.first["nb"]
            start = self.client.scatter(red.open_pix[p0 * nb:p1 * nb], hash=False)
        return self.client.submit(tile_task, self.req_f, self.key, self.tiles, self.cal_f, self.cal_key,
                                  self.r0(t), t, passes, start,
                                  key=f"clppm-chunk-{passes[0]}-{t}-{self.key}-{self.run}",
                                  workers=None if worker is None else [worker], allow_other_workers=True,
                                  pure=False)

    def save(self, red: Reduction, path: str | None) -> None:
        if path:
            red.save(path, self.meta, self.cal, self.first["nb"], self.timing)

    def image(self, red: Reduction, interrupted: bool) -> film.RenderResult:
        """The image of the reduced passes (finished on a worker, which holds the scene)."""
        c = self.client
        pix_f = c.scatter(red.pix, hash=False)
        stats = {"stored": red.stored, "first_search_mean": self.cal.first_search_mean}
        f = c.submit(finish_task, self.req_f, self.key, self.tiles, self.cal_f, self.cal_key, pix_f,
                     int(red.pairs.sum()), sum(red.emitted), red.next_pass, {**self.timing, **red.seconds},
                     stats, time.perf_counter() - self.t_start, interrupted, pure=False)
        return f.result()


class DaskRun:
    """A render on a cluster, as :func:`clppm.integrators.driver.drive` steps it: every piece
    (tile, chunk) of a chunk not yet done is submitted at once; a step waits (at most half a
    second, so a signal is seen) for pieces to finish and reduces the whole chunks in pass
    order."""

    resume_flags = "--resume"

    def __init__(self, job: "_Job", red: Reduction, ckpath: str | None, on_chunk, where: str,
                 workers: dict):
        self.job, self.red, self.ckpath, self.on_chunk = job, red, ckpath, on_chunk
        self.n_passes, self.device_name = job.n_passes, job.meta["device"]
        self.report = {"engine": "dask.distributed", "where": where, "chunk_passes": job.k,
                       "workers": {a: {kk: w[kk] for kk in ("device", "type")} for a, w in workers.items()},
                       "chunks": [], "bytes_moved": 0}
        # pieces dealt to the workers in turn: each device starts with a share (a worker still
        # building its scene would otherwise find every piece taken by one that has), and work
        # stealing evens out the rest
        todo = [(q, t) for q in pieces(red.next_pass, job.n_passes, job.k) if not red.covers(q)
                for t in range(len(job.tiles))]
        addrs = sorted(workers)
        self.futs = {job.submit_piece(q, t, red, addrs[i % len(addrs)] if addrs else None): (q, t)
                     for i, (q, t) in enumerate(todo)}
        self.t0 = time.perf_counter()

    @property
    def passes_done(self) -> int:
        return min(self.red.finished, self.n_passes)

    def step(self) -> None:
        from distributed import wait
        try:
            done, _ = wait(list(self.futs), timeout=0.5, return_when="FIRST_COMPLETED")
        except TimeoutError:
            return
        for f in done:
            q, t = self.futs.pop(f)
            d = _result(f, q, self.ckpath)
            self.red.add(d.result)
            self.report["bytes_moved"] += d.result.pix.nbytes + d.result.pairs.nbytes
            self.report["chunks"].append({"passes": [q[0], q[-1]], "tile": t, "worker": d.worker,
                                          "seconds": d.wall, "points": d.points,
                                          "pixels": int(d.result.pairs.size)})
            if self.on_chunk is not None:
                self.on_chunk(d)

    def save(self, path: str) -> None:
        self.job.save(self.red, path)

    def image(self, interrupted: bool) -> film.RenderResult:
        res = self.job.image(self.red, interrupted)
        res.report["executor"] = dict(self.report, tiles=len(self.job.tiles), held_passes=sorted(self.red.held),
                                      passes_wall_s=time.perf_counter() - self.t0)
        return res

    def close(self) -> None:
        for f in self.futs:
            f.cancel()


def _result(f, passes, ckpath) -> ChunkDone:
    """A finished chunk, or the failure as one line (the last checkpoint is kept)."""
    from distributed import KilledWorker
    keep = f"; resume from {ckpath} with --resume" if ckpath and os.path.exists(ckpath) else ""
    try:
        return f.result()
    except KilledWorker as e:
        raise ExecutorError(f"passes {passes[0]}-{passes[-1]} killed their workers repeatedly ({e}){keep}") from None
    except DeviceError as e:
        raise DeviceError(f"{' '.join(str(e).split())} (passes {passes[0]}-{passes[-1]}){keep}") from None
