"""The command line as a user meets it: ``python -m clppm.cli``.

Bad input must end with exit code 2 and exactly one line on stderr that names the file (or
``--slab``/command line), the key and the value, never a Python traceback (cli.py's contract).

Every bad input runs in-process through ``clppm.cli.main`` (an escaping exception fails the
test, as a traceback would); the main kinds also run as real ``python -m clppm.cli``
subprocesses, started together once per module (each one pays ~1.5 s of imports).
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

BASE = """\
[model]
size_mm = [1.0, 1.0]
lateral = "infinite"

[spectrum]
start_nm = 500.0
stop_nm = 600.0
step_nm = 50.0

[light]
kind = "pencil"
center_mm = [0.5, 0.5]
spectrum = "flat"

[[layer]]
name = "epidermis"
thickness_um = 100.0
n = 1.4
melanin = 0.05
baseline = 0.95

[[layer]]
name = "dermis"
thickness_um = inf
n = 1.4
blood = 0.02
"""

SLAB = "mua=10,mus=90,g=0.75,n=1.0,d=0.02"


def clppm(*args, cwd=None, timeout=120):
    """``python -m clppm.cli ARGS`` in a subprocess."""
    return subprocess.run([sys.executable, "-m", "clppm.cli", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)


def clppm_inproc(*args, cwd=None):
    """``clppm.cli.main(ARGS)`` in this process, with the subprocess result's fields."""
    from clppm import cli
    out, err = io.StringIO(), io.StringIO()
    old = os.getcwd()
    try:
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = cli.main([str(a) for a in args])
            except SystemExit as e:               # argparse usage errors
                rc = e.code
    finally:
        os.chdir(old)
    return subprocess.CompletedProcess(args, rc, out.getvalue(), err.getvalue())


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def edit(old: str, new: str, text: str = BASE) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


def assert_one_line_error(r, *needles):
    """Exit 2, one stderr line containing every needle, no traceback."""
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    for n in needles:
        assert n in lines[0], f"{n!r} not in {lines[0]!r}"
    return lines[0]


# ----------------------------------------------------------------------------- bad configs
BAD_CONFIGS = {
    # name: (config text, needles expected in the error line besides the file name)
    "negative thickness": (edit("thickness_um = 100.0", "thickness_um = -100.0"),
                           ["layer[0].thickness_um", "-100"]),
    "zero thickness": (edit("thickness_um = 100.0", "thickness_um = 0.0"),
                       ["layer[0].thickness_um", "0.0"]),
    "fraction above 1": (edit("melanin = 0.05", "melanin = 1.5"), ["layer[0].melanin", "1.5"]),
    "fraction below 0": (edit("blood = 0.02", "blood = -0.1"), ["layer[1].blood", "-0.1"]),
    "saturation above 1": (edit("blood = 0.02", "blood = 0.02\nsaturation = 2"),
                           ["layer[1].saturation", "2"]),
    "unknown layer key": (edit("melanin = 0.05", "melanine = 0.05"),
                          ["layer[0].melanine", "did you mean 'melanin'"]),
    "unknown section": (edit("[light]", "[lihgt]"), ["lihgt", "did you mean 'light'"]),
    "unknown model key": (edit('lateral = "infinite"', 'lateral = "infinite"\nvoxel_size = 5.0'),
                          ["model.voxel_size", "did you mean"]),
    "bad choice": (edit('lateral = "infinite"', 'lateral = "periodc"'),
                   ["model.lateral", "periodc", "did you mean 'periodic'"]),
    "wrong type": (edit("n = 1.4", 'n = "1.4"'), ["layer[0].n", "1.4"]),
    "index below 1": (edit("n = 1.4", "n = 0.9"), ["layer[0].n", "0.9"]),
    "semi-infinite not last": (edit("thickness_um = 100.0", "thickness_um = inf"),
                               ["layer[0].thickness_um", "inf"]),
    "wavelength beyond the Prahl table": (edit("stop_nm = 600.0", "stop_nm = 1100.0"),
                                          ["spectrum.stop_nm", "1100"]),
    "wavelength below the Prahl table": (edit("start_nm = 500.0", "start_nm = 200.0"),
                                         ["spectrum.start_nm", "200"]),
    "D65 below its data": (edit('spectrum = "flat"', 'spectrum = "D65"',
                                edit("start_nm = 500.0", "start_nm = 250.0")),
                           ["spectrum.start_nm", "250", "D65"]),
    "D65 beyond its data": (edit('spectrum = "flat"', 'spectrum = "D65"',
                                 edit("stop_nm = 600.0", "stop_nm = 900.0")),
                            ["spectrum.stop_nm", "900", "D65"]),
    "stop before start": (edit("stop_nm = 600.0", "stop_nm = 400.0"), ["spectrum.stop_nm", "400"]),
    "vector length": (edit("size_mm = [1.0, 1.0]", "size_mm = [1.0]"), ["model.size_mm", "[1.0]"]),
    "upward beam": (edit('spectrum = "flat"', 'spectrum = "flat"\ndirection = [0.0, 0.0, 1.0]'),
                    ["light.direction", "1.0"]),
    "no layers": ("\n".join(BASE.split("[[layer]]")[0].splitlines()), ["layer"]),
    "missing height map": (edit('lateral = "infinite"', 'lateral = "open"')
                           + '\n[relief]\nkind = "file"\nfile = "missing_heights.npy"\n',
                           ["relief.file", "missing_heights.npy"]),
    "height map not given": (edit('lateral = "infinite"', 'lateral = "open"')
                             + '\n[relief]\nkind = "file"\n', ["relief.file"]),
}


@pytest.mark.parametrize("case", list(BAD_CONFIGS))
def test_bad_config_one_line(tmp_path, case):
    """A bad config file ends with exit 2 and one line naming the file, key and value."""
    text, needles = BAD_CONFIGS[case]
    cfg = write(tmp_path, text, "bad_scene.toml")
    r = clppm_inproc("trace", cfg, "--photons", 100, cwd=tmp_path)
    assert_one_line_error(r, "bad_scene.toml", *needles)


# the kinds of bad input named in the CLI's contract, as real subprocesses
# (each costs ~1.5 s of CPU for imports; the full matrix runs in-process above)
SUBPROCESS_CONFIGS = ["negative thickness", "unknown layer key", "missing height map",
                      "D65 below its data"]
SUBPROCESS_SLABS = ["not a number"]


@pytest.fixture(scope="module")
def subprocess_results(tmp_path_factory):
    """Start every subprocess case at once (2 at a time) and collect the results."""
    root = tmp_path_factory.mktemp("cli")
    jobs = {}
    for i, case in enumerate(SUBPROCESS_CONFIGS):
        d = root / f"c{i}"
        d.mkdir()
        cfg = write(d, BAD_CONFIGS[case][0], "bad_scene.toml")
        jobs[("config", case)] = (("trace", cfg, "--photons", 100), d)
    d = root / "toml"
    d.mkdir()
    jobs[("toml", "")] = (("trace", write(d, edit("n = 1.4", "n = = 1.4"), "broken.toml")), d)
    for case in SUBPROCESS_SLABS:
        jobs[("slab", case)] = (("trace", "--slab", BAD_SLABS[case][0], "--photons", 100), root)
    with ThreadPoolExecutor(max_workers=2) as ex:
        futs = {k: ex.submit(clppm, *a, cwd=c) for k, (a, c) in jobs.items()}
        return {k: f.result() for k, f in futs.items()}


@pytest.mark.parametrize("case", SUBPROCESS_CONFIGS)
def test_bad_config_subprocess(subprocess_results, case):
    """The same through ``python -m clppm.cli``: exit 2, one line, no traceback."""
    assert_one_line_error(subprocess_results[("config", case)], "bad_scene.toml",
                          *BAD_CONFIGS[case][1])


@pytest.mark.parametrize("case", SUBPROCESS_SLABS)
def test_bad_slab_subprocess(subprocess_results, case):
    assert_one_line_error(subprocess_results[("slab", case)], "--slab", *BAD_SLABS[case][1])


def test_malformed_toml_subprocess(subprocess_results):
    line = assert_one_line_error(subprocess_results[("toml", "")], "broken.toml", "TOML")
    assert re.search(r"line \d+", line)


def test_malformed_toml(tmp_path):
    """A TOML syntax error: exit 2, one line with the file name and the parser's position."""
    cfg = write(tmp_path, edit("n = 1.4", "n = = 1.4"), "broken.toml")
    line = assert_one_line_error(clppm_inproc("trace", cfg, cwd=tmp_path), "broken.toml", "TOML")
    assert re.search(r"line \d+", line)


def test_missing_config_file(tmp_path):
    assert_one_line_error(clppm_inproc("trace", "nowhere.toml", cwd=tmp_path), "nowhere.toml",
                          "not found")


@pytest.mark.parametrize("content,needle", [
    (b"not a numpy file", "cannot read"),
    (None, "2-D"),
])
def test_bad_height_map_file(tmp_path, content, needle):
    """A height map that exists but is not usable: one line naming relief.file and the file."""
    hm = tmp_path / "heights.npy"
    if content is None:
        np.save(hm, np.zeros(7))
    else:
        hm.write_bytes(content)
    text = edit('lateral = "infinite"', 'lateral = "open"') + \
        '\n[relief]\nkind = "file"\nfile = "heights.npy"\n'
    cfg = write(tmp_path, text, "relief_scene.toml")
    line = assert_one_line_error(clppm_inproc("trace", cfg, "--photons", 100, cwd=tmp_path),
                                 "relief_scene.toml", "relief.file", "heights.npy")
    assert needle in line


BAD_SLABS = {
    "negative mua": ("mua=-1,mus=90,g=0.75", ["layer[0].mua", "-1"]),
    "not a number": ("mua=abc,mus=90,g=0.75", ["mua", "abc"]),
    "g out of range": ("mua=10,mus=90,g=1.5", ["layer[0].g", "1.5"]),
    "negative thickness": ("mua=10,mus=90,g=0.75,d=-0.02", ["layer[0].thickness_um", "-200"]),
    "index below 1": ("mua=10,mus=90,g=0.75,n=0.5", ["layer[0].n", "0.5"]),
    "unknown key": ("mua=10,mus=90,g=0.75,dd=0.1", ["dd", "did you mean 'd'"]),
    "missing g": ("mua=10,mus=90", ["g", "missing"]),
    "no equals sign": ("mua10,mus=90,g=0.75", ["mua10", "key=value"]),
    "nan": ("mua=nan,mus=90,g=0.75", ["layer[0].mua", "nan"]),
    "inf": ("mua=10,mus=inf,g=0.75", ["layer[0].mus", "inf"]),
}


@pytest.mark.parametrize("case", list(BAD_SLABS))
def test_bad_slab(tmp_path, case):
    """Bad --slab values: exit 2, one line naming --slab, the key and the value."""
    spec, needles = BAD_SLABS[case]
    assert_one_line_error(clppm_inproc("trace", "--slab", spec, "--photons", 100, cwd=tmp_path),
                          "--slab", *needles)


@pytest.mark.parametrize("args,needles", [
    (["--photons", "0"], ["--photons", "0"]),
    (["--photons", "-5"], ["--photons", "-5"]),
    (["--seed", "-1"], ["seed", "-1"]),
])
def test_bad_trace_options(tmp_path, args, needles):
    assert_one_line_error(clppm_inproc("trace", "--slab", SLAB, *args, cwd=tmp_path), *needles)


@pytest.mark.parametrize("batches", ["0", "-3"])
def test_bad_batches(tmp_path, batches):
    assert_one_line_error(clppm_inproc("trace", "--slab", SLAB, "--photons", 100, "--batches", batches,
                                cwd=tmp_path), "--batches", batches)


@pytest.mark.parametrize("args,needles", [
    (["--set", "render.store_scale=-1"], ["render.store_scale", "-1"]),
    (["--set", "render.storage=sometimes"], ["render.storage", "sometimes"]),
    (["--set", "render.nope=1"], ["render.nope", "unknown key"]),
    (["--set", "passes"], ["passes", "SECTION.KEY=VALUE"]),
    (["--bands-per-path", "4"], ["render.bands_per_path", "4", "must divide"]),
    (["--integrator", "pt", "--paper"], ["--paper", "ppm only"]),
])
def test_bad_render_options(tmp_path, args, needles):
    """Render options are checked like config keys, before any work: exit 2, one line."""
    (tmp_path / "c.toml").write_text(BASE)
    assert_one_line_error(clppm_inproc("render", tmp_path / "c.toml", "-o", tmp_path / "x.exr", "-q", *args,
                                       cwd=tmp_path), *needles)
    assert not (tmp_path / "x.exr").exists()


# ----------------------------------------------------------------------------- good runs
def test_devices_lists_one():
    """`clppm devices` lists at least one OpenCL device as 'P:D  name  [...]'."""
    r = clppm("devices")
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if re.match(r"^\d+:\d+\s+\S", ln)]
    assert lines, r.stdout


def test_trace_slab_json(tmp_path):
    """`clppm trace --slab ... --json` prints the tallies and writes Rd/Tt/A/specular with SEs
    (MCML slab, Wang et al. 1995: Rd 0.09739, Tt 0.66096; loose check here)."""
    out = tmp_path / "out.json"
    r = clppm("trace", "--slab", SLAB, "--photons", 20000, "--seed", 1, "--json", out,
              cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "Rd" in r.stdout and "Traceback" not in r.stderr
    rep = json.loads(out.read_text())
    for k in ("Rd", "Tt", "A", "specular"):
        assert isinstance(rep[k], float) and isinstance(rep[k + "_se"], float), k
        assert 0.0 <= rep[k] <= 1.0 and rep[k + "_se"] >= 0.0
    assert rep["photons"] == 20000 and rep["seed"] == 1 and rep["device"]
    assert rep["energy_balance_error"] < 1e-6
    assert abs(rep["Rd"] - 0.09739) < 0.01 and abs(rep["Tt"] - 0.66096) < 0.02


def test_trace_config_file(tmp_path):
    """A valid multi-band config file traces and writes per-band results."""
    cfg = write(tmp_path, BASE)
    out = tmp_path / "t.json"
    r = clppm_inproc("trace", cfg, "--photons", 5000, "--bands", "--json", out, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rep = json.loads(out.read_text())
    assert set(rep["per_band"]) == {"500", "550", "600"}
    assert rep["Tt"] == 0.0 and 0.0 < rep["Rd"] < 1.0
