"""The one render entry: ``render(request)`` over integrators laid out alike.

Every render goes through the same prologue, in the same order, before any work: the
integrator's own refusals, the output paths, a resumed checkpoint (readable, of this
integrator, not beyond the passes asked for, of this config), the scene's notes.  Then the
integrator opens its run (a device or a cluster, the scene built once, calibrated or restored)
and :func:`clppm.integrators.driver.drive` steps it: a :class:`clppm.integrators.driver.Run`
whatever the integrator.

* :class:`Progressive`: progressive photon mapping in this process (:mod:`clppm.run.progressive`);
* :class:`Distributed`: the same passes on a Dask cluster (:mod:`clppm.run.executor`);
* :class:`PathTracing`: the unbiased path tracer (:mod:`clppm.integrators.pathtracer`).
"""
from __future__ import annotations

import contextlib
import time
from typing import ContextManager, Protocol

from ..integrators import driver
from ..output import checkpoint as ckpt
from ..output import paths
from ..output.film import RenderResult
from ..request import RenderRequest
from ..scene.scene import refuse_inclusions, warn_scene


class Integrator(Protocol):
    """What :func:`render` needs of an integrator."""

    #: the checkpoint kind it writes and resumes (:func:`clppm.output.checkpoint.load`)
    checkpoint_kind: str
    #: whether its run takes snapshots (``Budget.snapshot_every``, ``on_snapshot``)
    snapshots: bool

    def check(self, req: RenderRequest) -> None:
        """Refuse, before any work, what this integrator cannot render (one line, exit 2)."""

    def open(self, req: RenderRequest, t_start: float) -> ContextManager[driver.Run]:
        """The run of ``req``: its device or cluster opened, its scene built, started or resumed."""


class Progressive:
    checkpoint_kind, snapshots = "ppm", True

    def check(self, req: RenderRequest) -> None:
        pass

    @contextlib.contextmanager
    def open(self, req: RenderRequest, t_start: float):
        from . import progressive
        yield progressive.open_run(req, t_start)


class Distributed:
    checkpoint_kind, snapshots = "ppm", False

    def check(self, req: RenderRequest) -> None:
        from .executor import check_distributable
        from ..request import Cluster
        check_distributable(req.settings, (req.cluster or Cluster()).how)

    def open(self, req: RenderRequest, t_start: float):
        from . import executor
        return executor.open_run(req, t_start)


class PathTracing:
    checkpoint_kind, snapshots = "pt", True

    def check(self, req: RenderRequest) -> None:
        from ..integrators.pathtracer import check_request
        check_request(req)

    @contextlib.contextmanager
    def open(self, req: RenderRequest, t_start: float):
        from ..integrators.pathtracer import open_run
        yield open_run(req, t_start)


def integrator(req: RenderRequest) -> Integrator:
    """The integrator of ``req``: the path tracer, a Dask cluster (a scheduler, devices or a
    client named), else progressive photon mapping in this process."""
    if req.integrator == "pt":
        return PathTracing()
    if req.cluster is not None:
        return Distributed()
    return Progressive()


def render(req: RenderRequest | dict, **kw) -> RenderResult:
    """Render a request; return the image and its run report.

    ``req``: a :class:`clppm.request.RenderRequest`, or a config and :meth:`RenderRequest.of`'s
    keywords.  The budget's ``on_snapshot(passes, wall s, result)`` every ``snapshot_every``
    passes (True: stop), ``on_pass`` after every pass (in this process), ``on_chunk`` as each
    cluster chunk arrives, ``stop_after`` passes.  See ``clppm render --help``."""
    t_start = time.perf_counter()
    req = req if isinstance(req, RenderRequest) else RenderRequest.of(req, **kw)
    integ = integrator(req)
    refuse_inclusions(req.resolved(), req.source, req.integrator)
    integ.check(req)
    rs, out, b = req.settings, req.outputs, req.budget
    paths.check_outputs(out=out.out, checkpoint=req.checkpoint)
    if req.resume:
        ckpt.load(req.resume, integrator=integ.checkpoint_kind)    # missing or corrupt: now
        driver.check_resume_passes(req.resume, int(rs.passes), req.flag_or_key("passes"))
        ckpt.check_matches(req.resume, config=req.config_identity())
    warn_scene(req.resolved(), req.source)
    snap = dict(snapshot_every=b.snapshot_every, on_snapshot=b.on_snapshot) if integ.snapshots else {}
    cad = driver.Cadence.of(rs, out.out, req.checkpoint, stop_after=b.stop_after,
                            progress=out.progress, **snap)
    with integ.open(req, t_start) as run:
        return driver.drive(run, cad, t_start, resumed=bool(req.resume))


def render_pt(req: RenderRequest | dict, **kw) -> RenderResult:
    """:func:`render` with the path tracer (point light): the image and report as a PPM render."""
    req = req if isinstance(req, RenderRequest) else RenderRequest.of(req, "pt", **kw)
    return render(req.replace(integrator="pt", cluster=None))


def render_distributed(req: RenderRequest | dict, **kw) -> RenderResult:
    """:func:`render` on a Dask cluster, the same bytes as in this process.  Its cluster:
    ``scheduler``, the address of a running scheduler; ``devices``, ``P:D`` strings (or
    ``"all"``) for a local cluster, one worker each; ``client``, an existing
    ``distributed.Client``; none of these: one in-process worker.  The budget's ``stop_after``:
    stop once this many passes are finished (a checkpoint is written); ``on_chunk(ChunkDone)``:
    called as each chunk arrives."""
    from ..request import Cluster
    req = req if isinstance(req, RenderRequest) else RenderRequest.of(req, **kw)
    return render(req.replace(cluster=req.cluster or Cluster(), integrator="ppm"))
