"""The render driver (clppm/integrators/driver.py) on a stand-in run that counts what it is asked to do:
the stop rules, the checkpoint and preview cadence when a step finishes several passes (as a
Dask step can), and a device error's one line.  Reference: the cadence rules as documented in
the driver (a checkpoint whenever the passes done cross a multiple of checkpoint_every, at a
stop and at the end)."""
from __future__ import annotations

import numpy as np
import pytest

from clppm.integrators import driver
from clppm.output import film
from clppm.compute.device import DeviceError


class FakeRun:
    resume_flags = "--resume"
    device_name = "fake device"

    def __init__(self, n_passes, per_step=(1,), fail_at=None):
        self.n_passes, self.per_step, self.fail_at = n_passes, list(per_step), fail_at
        self.done, self.steps, self.saved, self.closed = 0, 0, [], False

    @property
    def passes_done(self):
        return self.done

    def step(self):
        if self.fail_at is not None and self.done >= self.fail_at:
            import pyopencl as cl
            raise cl.Error("CL_OUT_OF_RESOURCES")
        k = self.per_step[self.steps % len(self.per_step)]
        self.steps += 1
        self.done = min(self.done + k, self.n_passes)

    def save(self, path):
        self.saved.append(self.done)

    def image(self, interrupted):
        rep = {"passes_done": self.done, "interrupted": interrupted, "seconds": {}}
        z = np.zeros((1, 1, 3))
        return film.RenderResult(spectral=np.zeros((1, 1, 1)), xyz=z, rgb=z, wl=np.array([550.0]),
                                 report=rep)

    def close(self):
        self.closed = True


def test_checkpoints_follow_the_cadence_and_the_end():
    run = FakeRun(10)
    res = driver.drive(run, driver.Cadence(checkpoint="x.ckpt", checkpoint_every=4), 0.0)
    assert run.saved == [4, 8, 10] and res.report["passes_done"] == 10
    assert not res.report["interrupted"] and run.closed


def test_a_step_of_several_passes_crosses_the_cadence_once():
    """Steps of 3 passes with checkpoint_every 2: a checkpoint after every step that crosses an
    even count (3 crosses 2, 6 crosses 4 and 6, 9 crosses 8), and at the end."""
    run = FakeRun(10, per_step=(3,))
    driver.drive(run, driver.Cadence(checkpoint="x.ckpt", checkpoint_every=2), 0.0)
    assert run.saved == [3, 6, 9, 10]


def test_a_step_that_finishes_nothing_changes_nothing():
    run = FakeRun(4, per_step=(0, 0, 1))
    seen = []
    driver.drive(run, driver.Cadence(checkpoint="x.ckpt", checkpoint_every=1, snapshot_every=1,
                                     on_snapshot=lambda p, wall, res: seen.append(p)), 0.0)
    assert seen == [1, 2, 3, 4] and run.saved == [1, 2, 3, 4] and run.steps == 12


def test_the_snapshot_callback_stops_the_run_with_a_checkpoint():
    """compare's time budget: the callback answers True; the run stops there, checkpointed."""
    run = FakeRun(100)
    res = driver.drive(run, driver.Cadence(checkpoint="x.ckpt", checkpoint_every=0, snapshot_every=1,
                                           on_snapshot=lambda p, wall, res: p >= 7), 0.0)
    assert run.done == 7 and run.saved == [7] and res.report["passes_done"] == 7


def test_stop_after_writes_a_checkpoint_and_is_not_an_interrupt():
    run = FakeRun(10)
    res = driver.drive(run, driver.Cadence(checkpoint="x.ckpt", stop_after=3), 0.0)
    assert run.saved == [3] and res.report["passes_done"] == 3 and not res.report["interrupted"]


def test_a_resumed_run_with_nothing_to_do_writes_no_checkpoint():
    run = FakeRun(5)
    run.done = 5
    driver.drive(run, driver.Cadence(checkpoint="x.ckpt", checkpoint_every=1), 0.0, resumed=True)
    assert run.saved == [] and run.steps == 0


def test_a_device_error_is_one_line_naming_the_pass_and_the_checkpoint():
    run = FakeRun(10, fail_at=5)
    with pytest.raises(DeviceError) as e:
        driver.drive(run, driver.Cadence(checkpoint="x.ckpt", checkpoint_every=2), 0.0)
    msg = str(e.value)
    assert "\n" not in msg and "fake device" in msg and "pass 6 of 10" in msg
    assert "x.ckpt (pass 4) is kept: resume with --resume x.ckpt" in msg and run.closed


def test_previews_are_written_at_their_cadence_but_not_at_the_end(tmp_path, monkeypatch):
    written = []
    monkeypatch.setattr(film, "write_preview", lambda out, res: written.append(res.report["passes_done"]))
    run = FakeRun(6)
    driver.drive(run, driver.Cadence(out=str(tmp_path / "a.png"), preview_every=2), 0.0)
    assert written == [2, 4]
