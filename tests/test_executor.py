"""Distributed passes: a Dask cluster gives the in-process bytes, loses no work.

* Two PoCL worker processes (one thread each) render the same EXR bytes as the in-process loop
  with the same seed and ``render.chunk_passes``: chunk sums are added in chunk order.
* A run stopped part-way and resumed from its checkpoint (on the cluster or in-process) is
  byte-identical; out-of-order chunks are held in the checkpoint and reused, in order; an
  in-process checkpoint taken inside a chunk resumes on the cluster to the same bytes.
* A worker killed in the middle of a chunk: Dask reruns that chunk elsewhere; same bytes,
  the chunk counted once.
* An unreachable scheduler, a worker without a device, ``render.radius = "ppm"`` and
  unwritable outputs (render, trace, samples) end in one line, exit 2, before any work.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("distributed")

from clppm.output import checkpoint as ckpt  # noqa: E402
from clppm import cli
from clppm.run import entry, executor
from clppm.integrators import ppm  # noqa: E402
from clppm import config as C  # noqa: E402
from scenes import tiny_toml  # noqa: E402

PASSES, K = 8, 2

CONFIG = tiny_toml(photons=50000, initial_photons=50, passes=PASSES,  # ~0.25 s a pass on one core:
                  chunk_passes=K, radius="global", seed=7, checkpoint_every=2)  # a chunk to kill


def _spec(dev) -> str:
    from clppm.compute.device import list_devices
    return next(f"{ip}:{i}" for ip, i, _, d in list_devices() if d == dev.device)


@pytest.fixture(scope="module")
def work(tmp_path_factory, dev):
    d = tmp_path_factory.mktemp("dask")
    (d / "skin.toml").write_text(CONFIG)
    return d


@pytest.fixture(scope="module")
def cfg(work):
    return C.load(str(work / "skin.toml"))


@pytest.fixture(scope="module")
def reference(work, cfg, dev):
    """The in-process render: bytes and report."""
    res = entry.render(cfg, dev=dev, out=str(work / "ref" / "ref.exr"))
    return (work / "ref" / "ref.exr").read_bytes(), res.report


@pytest.fixture(scope="module")
def client(dev):
    """A local cluster of two single-threaded worker processes on the test device."""
    from distributed import Client
    env = {"PYOPENCL_CTX": _spec(dev), "POCL_MAX_PTHREAD_COUNT": "1"}
    with executor.local_cluster(envs=[env, env]) as cluster, Client(cluster, set_as_default=False) as c:
        c.wait_for_workers(2, timeout=60)
        yield c


def _one_line_exit_2(r, *words):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def _clppm(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "clppm.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


# ------------------------------------------------------------------------------ reduction, no device
def _fake_chunk(first, n, rng):
    passes = list(range(first, first + n))
    return ppm.ChunkResult(chunk=first // K, passes=passes, pix=rng.random(12) * 10.0 ** rng.integers(-8, 8, 12),
                           pairs=rng.integers(0, 1000, 4).astype(np.uint64), tallies=[[first, 1], [2, 3]],
                           emitted=[1000 + p for p in passes], stored=7 * n, seconds={"photon": 0.1})


def test_pieces_are_the_in_process_chunks():
    assert executor.pieces(0, 7, 3) == [[0, 1, 2], [3, 4, 5], [6]]
    assert executor.pieces(5, 9, 4) == [[5, 6, 7], [8]]         # resumed inside a chunk
    assert [list(ppm.chunk_passes(c, 3, 7)) for c in range(3)] == executor.pieces(0, 7, 3)


def test_reduction_is_order_independent_and_counts_each_chunk_once(tmp_path):
    """Chunks added in any order, with duplicates (a rerun), give the in-order bits; the held ones
    survive a checkpoint."""
    rng = np.random.default_rng(3)
    chunks = [_fake_chunk(p, min(K, 9 - p), rng) for p in range(0, 9, K)]
    inorder = executor.Reduction.empty(4, 3, [[0, 0], [0, 0]])
    for c in chunks:
        inorder.add(c)
    shuffled = executor.Reduction.empty(4, 3, [[0, 0], [0, 0]])
    order = chunks[::-1] + chunks[:2]                     # reversed, then two duplicates
    for c in order[:3]:
        shuffled.add(c)
    assert shuffled.next_pass == 0 and shuffled.finished == 5 and len(shuffled.held) == 3
    cal = ppm.Calibration(R0=np.ones(5, np.float32), store_zmin=-3.0, first_search_mean=None)
    path = str(tmp_path / "r.ckpt.npz")
    shuffled.save(path, {"m": 1}, cal, 3, {"eye": 1.0})
    back = executor.Reduction.load(ckpt.load(path, {"m": 1}), "r", K, 9)
    assert back.finished == 5 and sorted(back.held) == sorted(shuffled.held)
    for c in order[3:]:
        back.add(c)
    assert back.next_pass == 9 and not back.held
    assert back.pix.tobytes() == inorder.pix.tobytes()
    assert np.array_equal(back.pairs, inorder.pairs) and back.emitted == inorder.emitted
    assert back.tallies == inorder.tallies and back.stored == inorder.stored


# ------------------------------------------------------------------------------------ same bytes
def test_two_workers_give_the_in_process_bytes(work, cfg, reference, client):
    out = work / "two" / "two.exr"
    res = entry.render_distributed(cfg, client=client, out=str(out))
    ref_bytes, ref_rep = reference
    assert out.read_bytes() == ref_bytes, "2 workers: EXR differs from the in-process render"
    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["passes_done"] == PASSES and not rep["interrupted"]
    assert rep["photons_emitted"] == ref_rep["photons_emitted"]
    assert rep["gather_pairs"] == ref_rep["gather_pairs"]
    chunks = res.report["executor"]["chunks"]
    assert sorted(c["passes"][0] for c in chunks) == list(range(0, PASSES, K))
    assert len({c["worker"] for c in chunks}) == 2, "both workers should have run chunks"
    st = ckpt.load(ckpt.default_path(str(out)))
    assert st["pass_index"] == PASSES and not st["held"]


def test_two_workers_over_tiles_give_the_in_process_tiled_bytes(work, cfg, dev, client):
    """A render of 2+ tiles (render.tile_points) on the cluster: each task is one tile over one
    chunk of passes, its worker holding that tile's points and sums alone; the EXR is the
    in-process tiled render's, and the untiled one's, byte for byte, also stopped and resumed."""
    small = C.override(C.override(cfg, "camera", "resolution", [48, 36]), "render", "passes", 3)
    small = C.override(small, "render", "checkpoint_every", 0)
    one = entry.render(small, dev=dev, out=str(work / "t1" / "one.exr"))
    npts = one.report["sample_points"]
    tiled = C.override(small, "render", "tile_points", max(npts // 3, 1))
    ref = entry.render(tiled, dev=dev, out=str(work / "t1" / "ref.exr"))
    ntiles = ref.report["tiles"]
    assert ntiles >= 2, ntiles
    res = entry.render_distributed(tiled, client=client, out=str(work / "t2" / "two.exr"))
    two = (work / "t2" / "two.exr").read_bytes()
    assert two == (work / "t1" / "ref.exr").read_bytes(), "2 workers over tiles: EXR differs from in-process"
    assert two == (work / "t1" / "one.exr").read_bytes()
    ex = res.report["executor"]
    assert ex["tiles"] == ntiles == res.report["tiles"]
    pieces = sorted((c["passes"][0], c["tile"]) for c in ex["chunks"])
    assert pieces == [(p, t) for p in range(0, 3, K) for t in range(ntiles)], "a piece lost or counted twice"
    assert max(c["points"] for c in ex["chunks"]) < npts, "a worker held every sample point"
    assert sum(c["points"] for c in ex["chunks"] if c["passes"][0] == 0) == npts
    assert max(c["pixels"] for c in ex["chunks"]) < 48 * 36, "a piece returned the whole image's sums"
    assert res.report["gather_pairs"] == ref.report["gather_pairs"] > 0
    assert res.report["photons_emitted"] == ref.report["photons_emitted"]
    # stopped after its first whole chunk (pieces of the other then in flight are dropped, not
    # half-added) and resumed: the same bytes
    out = work / "t3" / "s.exr"
    stopped = entry.render_distributed(C.override(tiled, "render", "checkpoint_every", 1), client=client,
                                       out=str(out), stop_after=1)
    assert stopped.report["passes_done"] < 3
    st = ckpt.load(ckpt.default_path(str(out)))
    assert st["pass_index"] + sum(len(h["passes"]) for h in st["held"]) in (1, 2)
    entry.render_distributed(tiled, client=client, out=str(work / "t3" / "r.exr"), resume=ckpt.default_path(str(out)))
    assert (work / "t3" / "r.exr").read_bytes() == two


def test_two_workers_in_the_scatter_layout_give_the_in_process_gather_bytes(work, dev, client):
    """The atomic scatter layout (render.layout = "scatter", clppm/integrators/beam.py) on the cluster: the
    tiny scene with 9 bands, all carried by every path (the layout's condition), rendered by
    two workers in the scatter layout gives the in-process gather's EXR bytes."""
    from clppm.integrators import beam
    text = CONFIG.replace("start_nm = 450.0\nstop_nm = 650.0\nstep_nm = 50.0",
                          "start_nm = 420.0\nstop_nm = 740.0\nstep_nm = 40.0")
    assert text != CONFIG
    (work / "nine.toml").write_text(text)
    nine = C.load(str(work / "nine.toml"))
    gat, sca = (C.override(nine, "render", "layout", v) for v in ("gather", "scatter"))
    sc = ppm.Pipeline.build(sca, dev)
    why = beam.supports_scatter(dev, sc.vol.nb, sc.gclass, sc.pp.hero)
    if why:
        pytest.skip(f"no scatter layout on {dev.name}: {why}")
    assert sc.estimator.layout.name == "scatter"
    entry.render(gat, dev=dev, out=str(work / "nine_ref" / "g.exr"))
    entry.render_distributed(sca, client=client, out=str(work / "nine_two" / "s.exr"))
    assert (work / "nine_two" / "s.exr").read_bytes() == (work / "nine_ref" / "g.exr").read_bytes()


def test_stopped_run_resumes_to_the_same_bytes(work, cfg, reference, client):
    out = work / "stop" / "s.exr"
    ck = ckpt.default_path(str(out))
    res = entry.render_distributed(cfg, client=client, out=str(out), stop_after=3)
    assert res.report["passes_done"] < PASSES
    st = ckpt.load(ck)
    done = st["pass_index"] + sum(len(h["passes"]) for h in st["held"])
    assert 3 <= done < PASSES
    # resumed on the cluster
    entry.render_distributed(cfg, client=client, out=str(work / "stop" / "d.exr"), resume=ck)
    assert (work / "stop" / "d.exr").read_bytes() == reference[0]
    # ... and in this process: a distributed checkpoint is an in-process one (held chunks rerun)
    entry.render(cfg, out=str(work / "stop" / "p.exr"), resume=ck)
    assert (work / "stop" / "p.exr").read_bytes() == reference[0]


def test_in_process_checkpoint_inside_a_chunk_resumes_on_the_cluster(work, cfg, dev, reference, client):
    """An in-process run stopped inside a chunk: the cluster continues that chunk from its sums."""
    out = work / "mid" / "m.exr"
    entry.render(cfg, dev=dev, out=str(out), stop_after=3)     # pass 3: inside chunk 1
    st = ckpt.load(ckpt.default_path(str(out)))
    assert st["pass_index"] == 3 and np.any(st["chunk_acc"])
    entry.render_distributed(cfg, client=client, out=str(work / "mid" / "d.exr"),
                                resume=ckpt.default_path(str(out)))
    assert (work / "mid" / "d.exr").read_bytes() == reference[0]


def test_worker_killed_mid_chunk_is_rerun(work, cfg, reference, client):
    """After the first chunk arrives, kill the worker running another chunk (SIGKILL)."""
    killed = {}

    def kill_one(d):
        if killed:
            return
        t_end = time.monotonic() + 5
        while True:                  # a worker between two chunks has none for a moment
            busy = {w: [k for k in keys if "clppm-chunk" in str(k)] for w, keys in client.processing().items()}
            busy = {w: ks for w, ks in busy.items() if ks}
            if busy or time.monotonic() > t_end:
                break
            time.sleep(0.01)
        assert busy, "no chunk in flight to kill: the scene is too small for this test"
        w = sorted(busy, key=lambda a: a == d.worker)[0]  # prefer the other worker
        pid = client.run(os.getpid, workers=[w])[w]
        os.kill(pid, signal.SIGKILL)
        killed.update(worker=w, keys=busy[w])

    out = work / "kill" / "k.exr"
    res = entry.render_distributed(cfg, client=client, out=str(out), on_chunk=kill_one)
    assert killed
    assert out.read_bytes() == reference[0], "a rerun chunk changed the image"
    chunks = res.report["executor"]["chunks"]
    firsts = [c["passes"][0] for c in chunks]
    assert sorted(firsts) == list(range(0, PASSES, K)), "a chunk was lost or counted twice"
    key = str(killed["keys"][0])
    first = int(key.split("-")[2])
    rerun = next(c for c in chunks if c["passes"][0] == first)
    assert rerun["worker"] != killed["worker"], "the killed chunk must have run on another worker"
    assert res.report["photons_emitted"] == reference[1]["photons_emitted"]


def test_cli_devices_gives_the_in_process_bytes(work, dev, reference):
    """`clppm render --devices P:D,P:D`: its own local cluster, two workers on one device."""
    spec = _spec(dev)
    env = executor.worker_env([spec, spec])
    cores = len(os.sched_getaffinity(0))
    assert env == [{"PYOPENCL_CTX": spec, "POCL_MAX_PTHREAD_COUNT": str(max(1, cores // 2))}] * 2
    out = work / "cli" / "c.exr"
    r = _clppm("render", work / "skin.toml", "--devices", f"{spec},{spec}", "-o", out, "-q", timeout=120)
    assert r.returncode == 0, r.stderr
    assert out.read_bytes() == reference[0]
    assert len(json.loads(out.with_suffix(".json").read_text())["executor"]["workers"]) == 2


# ------------------------------------------------------------------------------- one-line refusals
def test_unreachable_scheduler_is_one_line_and_fast(work):
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()                                         # nothing listens there now
    out = work / "unreach" / "u.exr"
    t0 = time.monotonic()
    r = _clppm("render", work / "skin.toml", "--scheduler", f"tcp://127.0.0.1:{port}", "-o", out, "-q")
    line = _one_line_exit_2(r, "--scheduler", str(port))
    assert time.monotonic() - t0 < executor.CONNECT_TIMEOUT + 10, line
    assert not out.parent.exists()


def test_worker_without_device_is_one_line(work, tmp_path):
    from distributed import Client
    with executor.local_cluster(envs=[{"PYOPENCL_CTX": "9:9"}]) as cluster:
        with Client(cluster, set_as_default=False) as c:
            c.wait_for_workers(1, timeout=60)
        out = tmp_path / "nodev.exr"
        t0 = time.monotonic()
        r = _clppm("render", work / "skin.toml", "--scheduler", cluster.scheduler_address, "-o", out, "-q")
        _one_line_exit_2(r, "no usable OpenCL device", "9:9")
        assert time.monotonic() - t0 < 30
        assert not out.exists() and not os.path.exists(ckpt.default_path(str(out)))


def test_per_point_radius_is_refused(work, capsys):
    rc = cli.main(["render", str(work / "skin.toml"), "--radius", "ppm", "--devices", "all",
                   "-o", str(work / "ppm" / "p.exr"), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "render.radius" in err, err
    assert not (work / "ppm").exists()


@pytest.fixture
def no_work(monkeypatch):
    """Any scene, volume, device or cluster use fails the test."""
    from clppm.compute import device
    from clppm.scene import volume

    def forbidden(*a, **k):
        raise AssertionError("work started before the output paths were checked")
    for mod, name in ((volume, "build"), (device, "open_device"), (ppm.Pipeline, "build"), (executor, "connect")):
        monkeypatch.setattr(mod, name, forbidden)


@pytest.mark.parametrize("args,flag", [
    (["render", "{cfg}", "-o", "{bad}/r.exr"], "-o/--output"),
    (["render", "{cfg}", "-o", "{bad}/r.exr", "--devices", "all"], "-o/--output"),
    (["trace", "{cfg}", "--photons", "1000", "--json", "{bad}/t.json"], "--json"),
    (["samples", "{cfg}", "--json", "{bad}/s.json"], "--json"),
    (["reflectance", "{cfg}", "--plot", "{bad}/r.png"], "--plot"),
    (["fit", "--subject", "3", "-o", "{bad}/f.toml"], "-o/--output"),
    (["compare", "{cfg}", "-o", "{bad}/cmp"], "-o/--out"),
])
def test_unwritable_outputs_fail_before_work(work, capsys, no_work, args, flag):
    bad = work / "a-file"
    bad.write_text("not a folder")
    argv = [a.format(cfg=work / "skin.toml", bad=bad) for a in args]
    capsys.readouterr()
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and flag in err and "cannot be written" in err, err


def test_output_folder_that_can_be_made_is_fine(work, capsys):
    out = work / "new" / "deeper" / "t.json"
    assert cli.main(["trace", str(work / "skin.toml"), "--photons", "2000", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["Rd"] > 0
