"""The one render loop (as Mitsuba 3's ``integrator.cpp``): every integrator and executor
supplies a :class:`Run` (its own step, checkpoint and image), and :func:`drive` does the rest:
steps until a stop rule (the pass count, ``stop_after``, a snapshot callback's answer, a
signal), checkpoints, snapshots and previews at their cadence, progress, the first-signal
stop and device errors.  Nothing here knows what a pass computes.

Cadences count passes: a checkpoint is written whenever the passes done cross a multiple of
``render.checkpoint_every`` (a step of the Dask executor can finish several passes), at a stop
and at the end.
"""
from __future__ import annotations

import os
import signal
import sys
import time
from dataclasses import dataclass
from typing import Callable, Protocol

from ..output import film
from ..output.paths import WriteError
from ..config import ConfigError, RenderSettings
from ..compute.device import DeviceError


class Run(Protocol):
    """A render in progress, as the driver sees it."""

    n_passes: int                    # passes requested in all
    resume_flags: str                # how the command line resumes it ("--resume")

    @property
    def passes_done(self) -> int: ...           # passes whose results the run holds

    def step(self) -> None: ...                 # more passes (in-process: one; Dask: 0 or more)

    def save(self, path: str) -> None: ...      # a checkpoint of the passes done

    def image(self, interrupted: bool) -> film.RenderResult: ...

    def close(self) -> None: ...                # give back what the steps hold (Dask futures)


@dataclass
class Cadence:
    """What the driver does around the steps; 0 / None: never."""

    out: str | None = None           # the render's output (previews beside it)
    checkpoint: str | None = None    # the checkpoint's path
    checkpoint_every: int = 0
    preview_every: int = 0
    snapshot_every: int = 0
    on_snapshot: Callable | None = None   # (passes, wall s, RenderResult) -> True to stop
    stop_after: int | None = None    # stop once this many passes are done (a checkpoint is written)
    progress: bool = False

    @classmethod
    def of(cls, rc: RenderSettings, out: str | None, checkpoint: str | None, **kw) -> "Cadence":
        """From the render settings (``config.render_settings``) and the call's options."""
        return cls(out=out, checkpoint=checkpoint, checkpoint_every=int(rc.checkpoint_every),
                   preview_every=int(rc.preview_every), **kw)


class Interrupt:
    """First SIGINT/SIGTERM: finish the current step and stop; second: abort.  The signal that
    stopped the last render is kept in ``Interrupt.received`` (the command's exit code)."""

    received: int | None = None

    def __init__(self):
        self.flag = False
        self.old = {}

    def __enter__(self):
        Interrupt.received = None

        def handler(sig, frame):
            if self.flag:
                raise KeyboardInterrupt
            self.flag = True
            Interrupt.received = sig
        for s in (signal.SIGINT, signal.SIGTERM):
            try:
                self.old[s] = signal.signal(s, handler)
            except ValueError:           # not the main thread
                pass
        return self

    def __exit__(self, *a):
        for s, h in self.old.items():
            signal.signal(s, h)


def interrupt_signal() -> int | None:
    """The signal (SIGINT or SIGTERM) that stopped the last render in this process, or None."""
    return Interrupt.received


class PlainProgress:
    """Progress as plain lines (stderr is a file or a pipe: a log, a batch job): about every
    10 % of the passes or every 30 s, and at the end."""

    def __init__(self, total: int, initial: int):
        self.total, self.n, self.t0, self.last = total, initial, time.perf_counter(), 0.0
        self.every = max(1, total // 10)
        self.start = initial

    def update(self, k: int = 1) -> None:
        self.n += k
        t = time.perf_counter() - self.t0
        if self.n % self.every and self.n != self.total and t - self.last < 30:
            return
        self.last = t
        rate = (self.n - self.start) / t if t > 0 else 0.0
        eta = f", {(self.total - self.n) / rate:.0f} s to go" if rate > 0 and self.n < self.total else ""
        print(f"pass {self.n}/{self.total}: {t:.1f} s{eta}", file=sys.stderr, flush=True)

    def close(self) -> None:
        pass


def progress_bar(total: int, initial: int, enabled: bool):
    """tqdm on a terminal, plain lines otherwise, nothing when quiet."""
    if not enabled:
        return None
    if not sys.stderr.isatty():
        return PlainProgress(total, initial)
    try:
        from tqdm import tqdm
        return tqdm(total=total, initial=initial, unit="pass", dynamic_ncols=True, leave=True)
    except ImportError:      # pragma: no cover
        return None


def say(enabled: bool, msg: str) -> None:
    """A setup status line on stderr (``building the volume...``) unless quiet."""
    if enabled:
        print(msg, file=sys.stderr, flush=True)


def check_resume_passes(resume: str | None, passes: int, flag: str = "--passes") -> None:
    """Resuming must not ask for fewer passes than the checkpoint holds (it cannot un-render)."""
    if not resume:
        return
    from ..output.paths import pass_index
    have = pass_index(resume)
    if have is not None and passes < have:
        raise ConfigError("command line", flag, passes,
                          f"is below the {have} passes checkpoint {os.path.basename(resume)} holds; "
                          f"give --passes {have} or more (or start over without --resume)")


def _crossed(before: int, after: int, every: int) -> bool:
    return bool(every) and after // every > before // every


def _device_error(run: Run, e, cad: Cadence, last_ckpt: int | None) -> DeviceError:
    msg = " ".join(str(e).split())
    keep = (f"checkpoint {cad.checkpoint} (pass {last_ckpt}) is kept: resume with "
            f"{run.resume_flags} {cad.checkpoint}" if last_ckpt else "no checkpoint was written yet")
    err = DeviceError(f"device '{run.device_name}' failed in pass {run.passes_done + 1} of "
                      f"{run.n_passes} ({msg}); {keep}")
    err.checkpoint = cad.checkpoint if last_ckpt else None     # the command line's resume command
    err.resume_hint = f"{run.resume_flags} {cad.checkpoint}" if last_ckpt else None
    return err


def drive(run: Run, cad: Cadence, t_start: float, resumed: bool = False) -> film.RenderResult:
    """Step ``run`` until its passes are done or a stop rule holds; write its outputs.
    ``t_start``: when the render began (the snapshots' wall seconds)."""
    import pyopencl as cl
    bar = progress_bar(run.n_passes, min(run.passes_done, run.n_passes), cad.progress)
    last_ckpt = run.passes_done if resumed else None
    stopped = False
    with Interrupt() as intr:
        try:
            while run.passes_done < run.n_passes and not stopped:
                before = run.passes_done
                run.step()
                done = run.passes_done
                stopped = intr.flag or (cad.stop_after is not None and done >= cad.stop_after)
                if done == before:
                    continue
                if bar is not None:
                    bar.update(done - before)
                end = stopped or done >= run.n_passes
                if cad.on_snapshot and cad.snapshot_every and (_crossed(before, done, cad.snapshot_every) or end):
                    stopped = bool(cad.on_snapshot(done, time.perf_counter() - t_start, run.image(False))) or stopped
                    end = end or stopped
                if cad.checkpoint and (_crossed(before, done, cad.checkpoint_every) or end):
                    run.save(cad.checkpoint)
                    last_ckpt = done
                if cad.out and cad.preview_every and done < run.n_passes and _crossed(before, done, cad.preview_every):
                    film.write_preview(cad.out, run.image(False))
        except cl.Error as e:
            raise _device_error(run, e, cad, last_ckpt) from None
        except WriteError as e:
            raise _kept(e, cad, last_ckpt) from None
        finally:
            run.close()
            if bar is not None:
                bar.close()
    try:
        if cad.checkpoint and last_ckpt != run.passes_done:
            run.save(cad.checkpoint)
            last_ckpt = run.passes_done
        res = run.image(intr.flag and run.passes_done < run.n_passes)
        film.write_outputs(cad.out, res)
    except WriteError as e:
        raise _kept(e, cad, last_ckpt) from None
    return res


def _kept(e: WriteError, cad: Cadence, last_ckpt: int | None) -> WriteError:
    """``e`` with the checkpoint that is still whole on disk (written atomically), if any."""
    if cad.checkpoint and last_ckpt and os.path.exists(cad.checkpoint):
        e.checkpoint, e.checkpoint_pass = cad.checkpoint, last_ckpt
    return e
