"""An output set is one render, and nothing written is lost.

* NAME.exr / .png / .json / .ckpt.npz / .preview.png belong to one render: a render to a NAME
  holding an earlier render's files is refused, or with ``--force`` replaces the whole set and
  says so; an existing image is never overwritten without ``--force``; an input is never an
  output.
* Names too long for the file system (the temporary ``.NAME.ckpt.npz.PID.tmp`` included) and a
  checkpoint of another resolution, config or seed are refused before any work.
* A full disk names the file, keeps the checkpoint, leaves no partial file and exits 2 with the
  resume command; the command printed after an interruption works as printed.
"""
from __future__ import annotations

import errno
import json
import os
import shlex
import shutil
import signal

import pytest

from test_cli import assert_one_line_error, clppm_inproc
from test_outputs import no_work, tiny  # noqa: F401  (the fixture)


def _render(cfg, out, *more):
    return clppm_inproc("render", cfg, "-o", out, "-q", *more)


def _snapshot(folder) -> dict:
    return {p: (folder / p).read_bytes() for p in sorted(os.listdir(folder))}


# ----------------------------------------------------------------------------- one render per set
def test_png_beside_an_earlier_exr_refused_then_force_replaces_the_set(tmp_path):
    cfg, d = tiny(tmp_path), tmp_path / "out"
    assert _render(cfg, d / "n.exr").returncode == 0
    (d / "n.ckpt.npz").unlink()
    before = _snapshot(d)
    r = _render(cfg, d / "n.png", "--seed", 9)
    assert_one_line_error(r, "n.exr", "--force")
    assert _snapshot(d) == before
    r = _render(cfg, d / "n.png", "--seed", 9, "--force")
    assert r.returncode == 0, r.stderr
    assert "n.exr" in r.stderr and "removed" in r.stderr
    assert sorted(os.listdir(d)) == ["n.ckpt.npz", "n.json", "n.png"]
    assert json.loads((d / "n.json").read_text())["config"]["render"]["seed"] == 9


def test_final_image_not_overwritten_without_force(tmp_path):
    cfg, d = tiny(tmp_path), tmp_path / "out"
    assert _render(cfg, d / "x.exr").returncode == 0
    (d / "x.ckpt.npz").unlink()                 # what the README says to do with a final image
    exr = (d / "x.exr").read_bytes()
    r = _render(cfg, d / "x.exr", "--seed", 3)
    assert_one_line_error(r, "x.exr", "--force")
    assert (d / "x.exr").read_bytes() == exr


def test_resume_to_png_beside_its_exr_refused(tmp_path):
    cfg, d = tiny(tmp_path), tmp_path / "out"
    assert _render(cfg, d / "n.exr").returncode == 0
    r = _render(cfg, d / "n.png", "--resume", d / "n.ckpt.npz", "--passes", 3)
    assert_one_line_error(r, "n.exr", "-o")


def test_input_config_is_never_an_output(tmp_path, no_work):
    cfg = tiny(tmp_path)
    same = tmp_path / "same.exr"
    shutil.copy(cfg, same)
    text = same.read_bytes()
    r = _render(same, same)
    assert_one_line_error(r, "same.exr", "CONFIG", "output")
    assert same.read_bytes() == text


def test_force_with_resume_refused(tmp_path, no_work):
    cfg = tiny(tmp_path)
    r = _render(cfg, tmp_path / "x.png", "--resume", tmp_path / "x.ckpt.npz", "--force")
    assert_one_line_error(r, "--force", "--resume")


# ----------------------------------------------------------------------------- before any work
@pytest.mark.parametrize("stem", [245, 300])
def test_long_names_refused_before_work(tmp_path, no_work, stem):
    """A stem whose temporary checkpoint name (.NAME.ckpt.npz.PID.tmp) or own name exceeds the
    file system's 255 bytes is refused up front, not after the passes."""
    cfg = tiny(tmp_path)
    r = _render(cfg, tmp_path / ("a" * stem + ".png"))
    assert_one_line_error(r, "-o/--output", "too long")
    assert os.listdir(tmp_path) == ["tiny.toml"]


@pytest.mark.parametrize("change,needle", [
    (("--resolution", "16x12"), "camera.resolution"),
    (("--seed", "9"), "render.seed"),
    (("--set", "layer.0.n=1.45"), "layer.0.n"),
])
def test_checkpoint_of_another_render_refused_before_work(tmp_path, monkeypatch, change, needle):
    cfg, out = tiny(tmp_path), tmp_path / "x.png"
    assert _render(cfg, out).returncode == 0
    import clppm.scene.volume as V

    def boom(*a, **k):
        pytest.fail("the volume was built before the checkpoint was refused")
    monkeypatch.setattr(V, "build", boom)
    r = _render(cfg, out, "--resume", tmp_path / "x.ckpt.npz", "--passes", 3, *change)
    line = assert_one_line_error(r, "x.ckpt.npz", needle)
    assert len(line) < 400, line


# ----------------------------------------------------------------------------- later errors
def _enospc(path):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), path)


def test_disk_full_at_the_image_keeps_the_checkpoint(tmp_path, monkeypatch):
    cfg, d = tiny(tmp_path), tmp_path / "out"
    import clppm.image as I

    def half_exr(path, *a, **k):
        with open(path, "wb") as f:
            f.write(b"v/1\x01 partial")
        _enospc(path)
    monkeypatch.setattr(I, "write_exr", half_exr)
    r = _render(cfg, d / "a.exr", "--passes", 2)
    line = assert_one_line_error(r, "a.exr", "No space left", "a.ckpt.npz", "resume with clppm render")
    assert sorted(os.listdir(d)) == ["a.ckpt.npz"], os.listdir(d)      # no partial file
    monkeypatch.undo()
    cmd = shlex.split(line.split("resume with ", 1)[1])
    assert cmd[:2] == ["clppm", "render"]
    r = clppm_inproc(*cmd[1:], "-q")
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(d)) == ["a.ckpt.npz", "a.exr", "a.json", "a.png"]


def test_disk_full_at_the_first_checkpoint_names_it(tmp_path, monkeypatch):
    cfg, d = tiny(tmp_path), tmp_path / "out"
    import clppm.output.checkpoint as K
    real = K.np.savez

    def full(f, *a, **k):
        real(f, *a, **k)
        _enospc(getattr(f, "name", "?"))
    monkeypatch.setattr(K.np, "savez", full)
    r = _render(cfg, d / "a.png")
    assert_one_line_error(r, "a.ckpt.npz", "No space left", "no checkpoint")
    assert not d.exists() or not [p for p in os.listdir(d) if p.endswith(".tmp")]


def test_printed_resume_command_works_as_printed(tmp_path, monkeypatch):
    """Interrupted after its first pass, a render given --resolution, --passes, --photons,
    --seed and --set prints a command that, run as printed, finishes it."""
    from clppm.integrators import driver
    cfg, out = tiny(tmp_path), tmp_path / "out" / "s.png"
    real_enter = driver.Interrupt.__enter__

    def stop_at_once(self):
        real_enter(self)
        self.flag, driver.Interrupt.received = True, signal.SIGINT
        return self
    monkeypatch.setattr(driver.Interrupt, "__enter__", stop_at_once)
    r = clppm_inproc("render", cfg, "-o", out, "-q", "--resolution", "10x8", "--passes", 3,
                     "--photons", 2500, "--seed", 5, "--set", "render.store_scale=20")
    assert r.returncode == 130, r.stderr
    monkeypatch.undo()
    cmd = shlex.split(r.stdout.strip().splitlines()[-1].split("resume with ", 1)[1])
    assert cmd[:2] == ["clppm", "render"] and "--resume" in cmd
    r = clppm_inproc(*cmd[1:], "-q")
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "out" / "s.json").read_text())
    assert rep["passes_done"] == 3 and rep["config"]["render"]["seed"] == 5
    assert rep["config"]["camera"]["resolution"] == [10, 8]
    assert rep["config"]["render"]["store_scale"] == 20


def test_device_error_prints_the_whole_resume_command(dev, monkeypatch, tmp_path):
    """A device lost mid-render keeps its checkpoint and prints a command that resumes it as
    printed (the options that shaped the render included)."""
    from test_guards import _lost_setup
    p, out, ck = _lost_setup(monkeypatch, tmp_path)
    r = clppm_inproc("render", p, "-o", out, "-q", "--seed", 4, "--resolution", "6x4")
    assert r.returncode == 3, r.stderr
    line = r.stderr.strip().splitlines()[-1]
    cmd = shlex.split(line.split("resume with ", 1)[1])
    assert cmd[:2] == ["clppm", "render"] and "--seed" in cmd and "6x4" in cmd
    monkeypatch.undo()
    r = clppm_inproc(*cmd[1:], "-q")
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "x.json").read_text())
    assert rep["passes_done"] == 5 and rep["config"]["render"]["seed"] == 4
