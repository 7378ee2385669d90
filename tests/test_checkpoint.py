"""Interruption and resume: a killed render leaves a checkpoint that resumes to the same bytes.

* A render killed with SIGKILL in the middle of a pass leaves a loadable checkpoint, and
  ``clppm render --resume`` finishes it with an EXR byte-identical to an uninterrupted
  run with the same seed.
* SIGINT (SIGTERM) finishes the current pass, writes the image so far and a checkpoint, says
  how to resume and exits 130 (143), so that ``&&`` and batch schedulers see a cut-short render;
  resuming that checkpoint also gives the uninterrupted bytes.
* A checkpoint from different parameters, a corrupt, truncated, empty or tampered file
  is refused: exit code 2 and one line naming the file and the reason.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from clppm.output import checkpoint as ckpt
from clppm import cli
from scenes import tiny_toml

PASSES = 8

CONFIG = tiny_toml(photons=500000, initial_photons=50, passes=PASSES, seed=11,  # ~0.3 s a pass:
                  checkpoint_every=1)                                        # time to kill one


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    from clppm.compute.device import DeviceError, open_device
    try:
        open_device(None)
    except DeviceError as e:               # pragma: no cover - no OpenCL here
        pytest.skip(str(e))
    d = tmp_path_factory.mktemp("ckpt")
    (d / "skin.toml").write_text(CONFIG)
    return d


def _cli(capsys, *args) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = cli.main(["render", *map(str, args)])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.fixture(scope="module")
def reference(work):
    """An uninterrupted render (in this process, through the command line)."""
    out = work / "ref" / "ref.exr"
    rc = cli.main(["render", str(work / "skin.toml"), "-o", str(out), "-q"])
    assert rc == 0
    rep = json.loads((work / "ref" / "ref.json").read_text())
    assert rep["passes_done"] == PASSES and not rep["interrupted"]
    return out.read_bytes()


def _spawn(work, out):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "clppm.cli", "render", str(work / "skin.toml"),
                             "-o", str(out), "-q"], cwd=work, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _pass_index(path) -> int | None:
    try:
        return ckpt.load(str(path))["pass_index"]
    except (ckpt.CheckpointError, OSError):
        return None


def _wait_for_pass(proc, path, k, timeout=90.0) -> float:
    """Wait until the checkpoint at ``path`` holds pass ``k`` or later; return the time."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"render ended (rc {proc.returncode}) before pass {k}:\n{out}\n{err}")
        if os.path.exists(path):
            p = _pass_index(path)
            if p is not None and p >= k:
                return time.monotonic()
        time.sleep(0.01)
    proc.kill()
    pytest.fail(f"no checkpoint of pass {k} after {timeout} s")


def test_sigkill_mid_pass_then_resume_is_byte_identical(work, reference, capsys):
    out = work / "kill" / "x.exr"
    ck = ckpt.default_path(str(out))
    proc = _spawn(work, out)
    try:
        t1 = _wait_for_pass(proc, ck, 1)
        t2 = _wait_for_pass(proc, ck, 2)             # a pass takes t2 - t1; pass 3 runs now
        time.sleep(0.5 * (t2 - t1))                  # ... so this is in the middle of it
        if proc.poll() is not None:                  # pragma: no cover - a much faster device
            pytest.skip("the render finished before it could be killed")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists(), "the killed render must not have finished"
    st = ckpt.load(ck)                               # the last complete checkpoint, intact
    assert 2 <= st["pass_index"] < PASSES
    rc, so, se = _cli(capsys, work / "skin.toml", "--resume", ck, "-o", out, "-q")
    assert rc == 0, se
    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["passes_done"] == PASSES and not rep["interrupted"]
    assert out.read_bytes() == reference, "resumed render differs from the uninterrupted one"


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_writes_image_and_checkpoint_exits_nonzero_and_resumes(work, reference, capsys, sig, code):
    out = work / f"int{int(sig)}" / "y.exr"
    ck = ckpt.default_path(str(out))
    proc = _spawn(work, out)
    try:
        _wait_for_pass(proc, ck, 1)
        proc.send_signal(sig)
        so, se = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code, se
    assert "interrupted by " + signal.Signals(sig).name in so and "--resume " + ck in so, so
    assert out.exists() and out.with_suffix(".png").exists()
    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["interrupted"] is True
    st = ckpt.load(ck)
    assert st["pass_index"] == rep["passes_done"] < PASSES
    assert not [f for f in os.listdir(out.parent) if f.endswith(".tmp")], "temporary files left"
    rc, so, se = _cli(capsys, work / "skin.toml", "--resume", ck, "-o", out, "-q")
    assert rc == 0, se
    assert out.read_bytes() == reference


# ----------------------------------------------------------------------------- refused checkpoints
@pytest.fixture(scope="module")
def good_ckpt(work):
    out = work / "good" / "g.exr"
    rc = cli.main(["render", str(work / "skin.toml"), "-o", str(out), "-q", "--passes", "2"])
    assert rc == 0
    return ckpt.default_path(str(out))


def _refused(capsys, work, ck, *extra):
    rc, so, se = _cli(capsys, work / "skin.toml", "--resume", ck, "-o", work / "refused" / "r.exr",
                      "-q", *extra)
    lines = [ln for ln in se.splitlines() if ln.strip()]
    assert rc == 2, (rc, se)
    assert len(lines) == 1, se
    assert lines[0].startswith("clppm: error: checkpoint "), lines[0]
    assert os.path.basename(ck) in lines[0]
    assert not (work / "refused" / "r.exr").exists()
    return lines[0]


def test_global_radius_checkpoint_is_the_film_and_the_first_radii(work, good_ckpt):
    """With the global radius a checkpoint holds the pixel x band sums (closed chunks and the open
    one, each only once made) and each sample point's R0: no per-point R and N.  A finished
    2-pass render (one chunk, closed) writes one pixel x band sum and an empty open chunk: the
    file is that sum, the pair counts, R0 and a header."""
    st = ckpt.load(good_ckpt)
    rep = json.loads((work / "good" / "g.json").read_text())
    assert st["pt_R"].size == 0 and st["pt_N"].size == 0
    npix, nb = st["pix_acc"].shape
    assert npix == 24 * 16 and st["chunk_acc"].shape == (0, nb)
    assert st["R0"].shape == (rep["sample_points"],)
    film = npix * nb * 8 + npix * 8                   # pix_acc (float64), pix_pairs
    assert os.path.getsize(good_ckpt) <= film + 4 * rep["sample_points"] + 64 * 1024


def test_resume_with_more_passes_is_accepted(work, good_ckpt, capsys):
    """The number of passes is not part of a checkpoint's identity."""
    rc, so, se = _cli(capsys, work / "skin.toml", "--resume", good_ckpt, "-o", work / "more" / "m.exr",
                      "-q", "--passes", "3")
    assert rc == 0, se
    assert json.loads((work / "more" / "m.json").read_text())["passes_done"] == 3


@pytest.mark.parametrize("flag,value,word", [("--seed", "12", "seed"),
                                             ("--resolution", "20x16", "resolution"),
                                             ("--photons", "10000", "photons"),
                                             ("--method", "a", "method")])
def test_refuses_different_parameters(work, good_ckpt, capsys, flag, value, word):
    line = _refused(capsys, work, good_ckpt, flag, value)
    assert "different parameters" in line and word in line, line


def _variant(work, name, make):
    p = work / "bad" / name
    p.parent.mkdir(exist_ok=True)
    make(p)
    return str(p)


def _rewrite(src, dst, **changes):
    with np.load(src) as z:
        d = {k: z[k] for k in z.files}
    for k, f in changes.items():
        d[k] = f(d[k])
    with open(dst, "wb") as f:
        np.savez(f, **d)


def _header(change):
    def f(h):
        hd = json.loads(str(h))
        change(hd)
        return np.array(json.dumps(hd))
    return f


BAD = {
    "random.ckpt.npz": (lambda p, g: p.write_bytes(os.urandom(3000)), "corrupt"),
    "empty.ckpt.npz": (lambda p, g: p.write_bytes(b""), "corrupt"),
    "truncated.ckpt.npz": (lambda p, g: p.write_bytes(open(g, "rb").read()[: os.path.getsize(g) // 2]),
                           "corrupt"),
    "tail_cut.ckpt.npz": (lambda p, g: p.write_bytes(open(g, "rb").read()[:-100]), "corrupt"),
    "flipped.ckpt.npz": (lambda p, g: p.write_bytes(_flip(open(g, "rb").read())), "corrupt"),
    "array.ckpt.npz": (lambda p, g: np.save(open(p, "wb"), np.zeros(3)), "corrupt"),
    "nan.ckpt.npz": (lambda p, g: _rewrite(g, p, pix_acc=lambda a: np.where(np.arange(a.size).reshape(a.shape) == 5,
                                                                           np.nan, a)), "non-finite"),
    "shape.ckpt.npz": (lambda p, g: _rewrite(g, p, pix_acc=lambda a: a[:-1]), "shape"),
    "version.ckpt.npz": (lambda p, g: _rewrite(g, p, header=_header(lambda h: h.update(version=99))),
                         "version"),
    "device.ckpt.npz": (lambda p, g: _rewrite(g, p, header=_header(lambda h: h["meta"].update(device="Other GPU"))),
                        "device (checkpoint 'Other GPU'"),
    "header.ckpt.npz": (lambda p, g: _rewrite(g, p, header=lambda h: np.array("[1, 2]")), "corrupt"),
    "nostate.ckpt.npz": (lambda p, g: _rewrite(g, p, header=_header(lambda h: h["state"].pop("pass_index"))),
                         "corrupt"),
}


def _flip(b: bytes) -> bytes:
    """Flip bytes inside the stored arrays (past the zip header): a CRC error."""
    a = bytearray(b)
    for i in range(len(a) // 3, len(a) // 3 + 64):
        a[i] ^= 0xFF
    return bytes(a)


@pytest.mark.parametrize("name", sorted(BAD))
def test_refuses_bad_file(work, good_ckpt, capsys, name):
    make, word = BAD[name]
    p = _variant(work, name, lambda p: make(p, good_ckpt))
    line = _refused(capsys, work, p)
    assert word in line, line


def test_refuses_missing_file(work, capsys):
    line = _refused(capsys, work, work / "nope.ckpt.npz")
    assert "not found" in line


def test_save_is_atomic_on_failure(tmp_path, monkeypatch):
    """A write that fails half-way keeps the previous checkpoint and leaves no temporary file."""
    path = str(tmp_path / "a.ckpt.npz")
    state = dict(pass_index=1, emitted_total=10, store_zmin=None, tallies=[[1, 2]], tallies_emitted=10,
                 stats={"stored": 1, "emitted": [10], "first_search_mean": None}, timing={})
    z = np.zeros(4, np.float32)
    arrays = dict(pt_R=z, pt_N=z, R0=z, pix_acc=np.zeros((2, 3)), chunk_acc=np.zeros((2, 3)),
                  pix_pairs=np.zeros(2, np.uint64))
    ckpt.save(path, {"m": 1}, state, arrays)
    before = open(path, "rb").read()

    def boom(*a, **k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError):
        ckpt.save(path, {"m": 1}, dict(state, pass_index=2), arrays)
    assert open(path, "rb").read() == before
    assert os.listdir(tmp_path) == ["a.ckpt.npz"]
    monkeypatch.undo()
    st = ckpt.load(path, {"m": 1})
    assert st["pass_index"] == 1 and st["tallies"] == [[1, 2]]
