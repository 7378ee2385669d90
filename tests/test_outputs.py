"""Nothing lost, nothing hidden: every output a render promises is written, every failure said.

* ``-o`` decides the format by its extension (.exr: the EXR and a PNG beside it; .png: the PNG
  alone); anything else, an empty name, a folder or an unwritable place (tried for real: CI runs
  as root, and root passes ``os.access``) is refused with one line before any work, for every
  command's path options; the sidecars never collide with the main file or each other.
* A second render to the same output is refused (a lock); a stale lock is taken over; the
  checkpoint of an earlier render is not replaced without ``--force`` (or ``--resume``).
* Conflicting options are refused; ``--set layer.N.key`` works; ``--version``; help for every
  option; errors one line (exit 1 internal, 3 device), details with ``--verbose``.
* ``clppm config`` prints defaults, a resolved file, the shipped examples and the schema, and
  docs/config.md is that schema.
* A wheel installed into a fresh environment renders a shipped config by name.
(SIGINT/SIGTERM exit codes: tests/test_checkpoint.py.)
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from clppm import cli
from clppm.output import paths
from clppm import config as C

from test_cli import assert_one_line_error, clppm, clppm_inproc

ROOT = Path(__file__).resolve().parents[1]



def _tiny_text(photons: int, passes: int) -> str:
    """tests/test_checkpoint.py's scene at 8x6 pixels with this budget."""
    import re
    from test_checkpoint import CONFIG
    text = CONFIG.replace("resolution = [24, 16]", "resolution = [8, 6]")
    text = re.sub(r"\nphotons = \d+[^\n]*", f"\nphotons = {photons}", text)
    return re.sub(r"\npasses = \d+", f"\npasses = {passes}", text)


def tiny(tmp_path, photons=3000, passes=2) -> Path:
    p = tmp_path / "tiny.toml"
    p.write_text(_tiny_text(photons, passes))
    return p


@pytest.fixture
def no_work(monkeypatch):
    """Any render, trace or reflectance that gets as far as a device fails the test."""
    import clppm.compute.device as D

    def boom(*a, **k):
        pytest.fail("work started before the bad input was refused")
    import clppm.analysis.compare, clppm.analysis.fit, clppm.integrators.pathtracer, clppm.run.progressive, clppm.analysis.reflectance  # noqa: F401
    for m in list(sys.modules.values()):     # all imported first: none binds the patched name
        if getattr(m, "__name__", "").startswith("clppm") and getattr(m, "open_device", None) is D.open_device:
            monkeypatch.setattr(m, "open_device", boom)


# ----------------------------------------------------------------------------- sidecars
@pytest.mark.parametrize("name", ["x", "x.preview", "x.ckpt", "x.json", "a.b/x", "x.lock", "x.png"])
@pytest.mark.parametrize("ext", [".exr", ".png", ".EXR"])
def test_sidecars_never_collide(name, ext):
    """Every file a render writes is distinct, for every main name and format."""
    files = paths.render_outputs(name + ext)
    real = [os.path.normcase(os.path.abspath(p)) for p in files.values()]
    assert len(set(real)) == len(real), files
    assert files["image"] == name + ext
    assert ("png" in files) == (ext.lower() == ".exr")


def test_exr_and_png_of_one_name_share_the_lock():
    """-o x.exr writes x.png: a render to -o x.png is the same output (lock and checkpoint)."""
    a, b = paths.render_outputs("d/x.exr"), paths.render_outputs("d/x.png")
    assert a["png"] == b["image"] and a["lock"] == b["lock"] and a["checkpoint"] == b["checkpoint"]


@pytest.mark.parametrize("out,needles", [
    ("x.json", ["x.json", ".exr", ".png"]),
    ("x.jpg", ["x.jpg", ".exr", ".png"]),
    ("x", ["'x'", ".exr"]),
    ("", ["''", ".exr"]),
    ("sub/", ["sub/", "file"]),
    ("/proc/nope/x.exr", ["/proc/nope/x.exr", "cannot be written"]),
    ("/proc/x.png", ["/proc/x.png", "cannot be written"]),
])
def test_render_output_refused_before_work(tmp_path, no_work, out, needles):
    cfg = tiny(tmp_path)
    r = clppm_inproc("render", cfg, "-o", out, "-q", cwd=tmp_path)
    assert_one_line_error(r, "-o/--output", *needles)
    assert sorted(os.listdir(tmp_path)) == ["tiny.toml"]


def test_output_a_folder_refused(tmp_path, no_work):
    (tmp_path / "d.exr").mkdir()
    r = clppm_inproc("render", tiny(tmp_path), "-o", tmp_path / "d.exr", "-q", cwd=tmp_path)
    assert_one_line_error(r, "-o/--output", "folder")


def test_sidecar_a_folder_refused(tmp_path, no_work):
    """x.exr is fine but its report x.json is a folder: refused before work, not at the end."""
    (tmp_path / "x.json").mkdir()
    r = clppm_inproc("render", tiny(tmp_path), "-o", tmp_path / "x.exr", "-q", cwd=tmp_path)
    assert_one_line_error(r, "-o/--output", "x.json", "folder")


@pytest.mark.parametrize("args,needles", [
    (["trace", "--slab", "mua=1,mus=9,g=0.7", "--json", "/proc/t.json"], ["--json", "/proc/t.json"]),
    (["trace", "--slab", "mua=1,mus=9,g=0.7", "--json", ""], ["--json", "empty"]),
    (["samples", "CFG", "--json", "/proc/s.json"], ["--json", "/proc/s.json"]),
    (["reflectance", "CFG", "--plot", "r.xyz"], ["--plot", "r.xyz", ".png"]),
    (["reflectance", "CFG", "--plot", "/proc/r.png"], ["--plot", "/proc/r.png", "cannot be written"]),
    (["reflectance", "CFG", "--plot", "r.png", "--json", "r.png"], ["r.png", "same file"]),
    (["fit", "--subject", "1", "--config", "CFG", "-o", "h.json"], ["-o/--output", "h.json", ".toml"]),
    (["fit", "--subject", "1", "--config", "CFG", "-o", "h.toml", "--json", "h.png"], ["h.png", "same file"]),
    (["fit", "--subject", "1", "--config", "CFG", "-o", "h.toml", "--plot", "h.xyz"], ["--plot", "h.xyz"]),
    (["compare", "CFG", "-o", "/proc/cmp"], ["-o/--out", "/proc/cmp"]),
    (["compare", "CFG", "--cache", "/proc/cache"], ["--cache", "/proc/cache"]),
])
def test_every_path_option_checked_before_work(tmp_path, no_work, args, needles):
    cfg = tiny(tmp_path)
    r = clppm_inproc(*[str(cfg) if a == "CFG" else a for a in args], cwd=tmp_path)
    assert_one_line_error(r, *needles)
    assert sorted(os.listdir(tmp_path)) == ["tiny.toml"]


def test_check_makes_nothing(tmp_path):
    """The check creates its folder and a temporary file to know, then removes both."""
    assert paths.writable_problem(str(tmp_path / "a" / "b" / "x.exr")) is None
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------------------------- formats
def test_png_output_is_a_png_and_exr_an_exr(tmp_path):
    cfg = tiny(tmp_path)
    r = clppm_inproc("render", cfg, "-o", tmp_path / "p" / "x.png", "-q")
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(tmp_path / "p")) == ["x.ckpt.npz", "x.json", "x.png"]
    assert (tmp_path / "p" / "x.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "p" / "x.json").read_text())["passes_done"] == 2
    r = clppm_inproc("render", cfg, "-o", tmp_path / "e" / "x.exr", "-q")
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(tmp_path / "e")) == ["x.ckpt.npz", "x.exr", "x.json", "x.png"]
    assert (tmp_path / "e" / "x.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"     # OpenEXR magic
    assert (tmp_path / "e" / "x.png").read_bytes() == (tmp_path / "p" / "x.png").read_bytes()


# ----------------------------------------------------------------------------- runs that must not collide
def test_earlier_checkpoint_not_replaced_without_force(tmp_path):
    cfg, out = tiny(tmp_path), tmp_path / "x.png"
    assert clppm_inproc("render", cfg, "-o", out, "-q").returncode == 0
    ck = tmp_path / "x.ckpt.npz"
    before = ck.read_bytes()
    r = clppm_inproc("render", cfg, "-o", out, "-q", "--seed", 9)
    line = assert_one_line_error(r, "x.ckpt.npz", "pass 2", "--resume", "--force")
    assert ck.read_bytes() == before, line
    r = clppm_inproc("render", cfg, "-o", out, "-q", "--resume", ck, "--passes", 3)
    assert r.returncode == 0, r.stderr
    r = clppm_inproc("render", cfg, "-o", out, "-q", "--force", "--seed", 9)
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "x.json").read_text())["config"]["render"]["seed"] == 9


def test_resume_with_fewer_passes_refused(tmp_path):
    cfg, out = tiny(tmp_path), tmp_path / "x.png"
    assert clppm_inproc("render", cfg, "-o", out, "-q").returncode == 0
    r = clppm_inproc("render", cfg, "-o", out, "-q", "--resume", tmp_path / "x.ckpt.npz", "--passes", 1)
    assert_one_line_error(r, "--passes", "1", "2 passes", "x.ckpt.npz")


def test_second_concurrent_render_refused(tmp_path):
    """While one render writes -o x.exr, another to x.exr (or x.png: the same files) is refused
    with one line naming the first one's pid; the first finishes unharmed."""
    cfg = tiny(tmp_path, photons=300_000, passes=40)
    out = tmp_path / "x.exr"
    first = subprocess.Popen([sys.executable, "-m", "clppm.cli", "render", str(cfg), "-o", str(out), "-q"],
                             cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t_end = time.monotonic() + 120
        while not (tmp_path / "x.lock").exists():
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < t_end, "no lock file"
            time.sleep(0.05)
        for o in (out, tmp_path / "x.png"):
            r = clppm_inproc("render", cfg, "-o", o, "-q", "--force")
            assert_one_line_error(r, "another clppm", f"pid {first.pid}", "x.lock")
        first.send_signal(signal.SIGTERM)
        so, se = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 143, se
    assert not (tmp_path / "x.lock").exists(), "the lock outlived its render"


def test_stale_lock_taken_over(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    import socket
    (tmp_path / "x.lock").write_text(f"{dead.pid} {socket.gethostname()}\n")
    r = clppm_inproc("render", tiny(tmp_path), "-o", tmp_path / "x.png", "-q")
    assert r.returncode == 0, r.stderr
    assert not (tmp_path / "x.lock").exists()


def test_live_lock_refused_unit(tmp_path):
    with paths.OutputLock(str(tmp_path / "y.exr")):
        with pytest.raises(C.ConfigError, match=f"pid {os.getpid()}"):
            with paths.OutputLock(str(tmp_path / "y.png")):
                pass
    assert not (tmp_path / "y.lock").exists()


# ----------------------------------------------------------------------------- options
def test_method_with_spacing_refused(tmp_path, no_work):
    r = clppm_inproc("render", tiny(tmp_path), "--method", "e", "--spacing", 4, "-o", tmp_path / "x.exr", "-q")
    assert_one_line_error(r, "--method", "--spacing", "not both")
    r = clppm_inproc("samples", tiny(tmp_path), "--method", "e", "--spacing", 4)
    assert_one_line_error(r, "--method", "--spacing")


def test_set_layer_value(tmp_path):
    cfg = tiny(tmp_path)
    r = clppm_inproc("render", cfg, "--set", "layer.0.n=1.45", "--set", "layer.1.blood=0.03",
                     "-o", tmp_path / "x.png", "-q")
    assert r.returncode == 0, r.stderr
    layers = json.loads((tmp_path / "x.json").read_text())["config"]["layer"]
    assert layers[0]["n"] == 1.45 and layers[1]["blood"] == 0.03 and layers[1]["n"] == 1.4


@pytest.mark.parametrize("item,needles", [
    ("layer.0.nn=1.45", ["layer.0.nn", "did you mean 'n'", "valid keys", "melanin"]),
    ("layer.5.n=1.45", ["layer.5", "0..1", "epidermis"]),
    ("layer.0.n=0.5", ["layer[0].n", "0.5", ">= 1"]),
    ("layr.0.n=1.4", ["layr", "did you mean 'layer'"]),
])
def test_set_layer_errors(tmp_path, no_work, item, needles):
    r = clppm_inproc("render", tiny(tmp_path), "--set", item, "-o", tmp_path / "x.exr", "-q")
    assert_one_line_error(r, "--set", *needles)


def test_version():
    r = clppm("--version")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    import clppm as pkg
    import pyopencl
    assert lines[0] == f"clppm {pkg.__version__}"
    assert lines[1] == f"pyopencl {pyopencl.VERSION_TEXT}"
    assert any(ln.startswith("OpenCL platform: ") for ln in lines[2:]), r.stdout


def _commands():
    ap = cli.build_parser()
    sub = next(a for a in ap._actions if a.__class__.__name__ == "_SubParsersAction")
    return sub.choices


def test_every_option_has_help_and_quiet_verbose():
    for name, p in _commands().items():
        opts = {s for a in p._actions for s in a.option_strings}
        assert {"-q", "-v", "--device"} <= opts, name
        for a in p._actions:
            if a.option_strings and a.help != "show this help message and exit":
                assert a.help and len(a.help) > 8, (name, a.option_strings)
        if "render" == name:
            text = p.format_help()
            for m in "abcdef":
                assert f"\n  {m}  " in text
            assert "(default: out/render.exr)" in text and "examples:" in text


def test_bare_clppm_prints_help(capsys):
    assert cli.main([]) == 2
    assert "COMMAND" in capsys.readouterr().err


def test_internal_error_one_line_and_verbose_traceback(tmp_path, monkeypatch, capsys):
    from clppm.integrators import photonpass  # noqa: F401 (monkeypatched below)

    def bug(*a, **k):
        raise RuntimeError("a bug\nover two lines")
    monkeypatch.setattr(photonpass, "trace_report", bug)
    args = ["trace", "--slab", "mua=1,mus=9,g=0.7", "--photons", "100"]
    capsys.readouterr()
    assert cli.main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "internal error: RuntimeError: a bug over two lines" in err[0], err
    assert cli.main(args + ["-v"]) == 1
    assert "Traceback" in capsys.readouterr().err


def test_device_error_one_line_details_with_verbose(tmp_path, monkeypatch, capsys):
    import clppm.compute.device as D

    def nope(*a, **k):
        raise D.DeviceError("this render needs 9 MiB:\n  pixels: 9 MiB\noptions: fewer --photons")
    monkeypatch.setattr(D, "open_device", nope)
    args = ["trace", "--slab", "mua=1,mus=9,g=0.7", "--photons", "100"]
    capsys.readouterr()
    assert cli.main(args) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["clppm: device error: this render needs 9 MiB: options: fewer --photons"]
    assert cli.main(args + ["--verbose"]) == 3
    assert "pixels: 9 MiB" in capsys.readouterr().err


def test_plain_progress_and_status_lines_off_a_terminal(tmp_path):
    """stderr is a pipe: setup status lines and plain 'pass k/N' lines, no progress bar."""
    r = clppm("render", tiny(tmp_path), "-o", tmp_path / "x.png", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "building the volume" in r.stderr and "calibrating" in r.stderr
    assert "pass 2/2" in r.stderr and "\r" not in r.stderr and "it/s" not in r.stderr


# ----------------------------------------------------------------------------- clppm config
def test_config_defaults_and_resolved_file_round_trip(tmp_path):
    r = clppm_inproc("config")
    assert r.returncode == 0, r.stderr
    raw = tomllib.loads(r.stdout)
    assert raw["render"]["passes"] == C.SCHEMA["render"]["passes"].default
    for name in C.shipped_configs():
        r = clppm_inproc("config", name)
        assert r.returncode == 0, r.stderr
        assert C.validate(tomllib.loads(r.stdout), name, ".") == C.load(C.find(name)), name
    r = clppm_inproc("config", tiny(tmp_path), "--set", "layer.0.n=1.45")
    assert tomllib.loads(r.stdout)["layer"][0]["n"] == 1.45


def test_config_example_and_schema():
    r = clppm_inproc("config", "--example", "forearm")
    assert r.returncode == 0 and r.stdout == (ROOT / "configs" / "forearm.toml").read_text()
    listing = clppm_inproc("config", "--example").stdout
    for name in ("forearm", "cheek", "slab_mcml", "slab_semi_infinite", "forearm_flat", "forearm_paper"):
        assert name in listing
    assert_one_line_error(clppm_inproc("config", "--example", "elbow"), "--example", "elbow", "forearm")
    text = clppm_inproc("config", "--schema").stdout
    for key, typ, default, rng, meaning in C.schema_rows():
        assert key in text and meaning in text


def test_config_reference_page_matches_the_schema():
    """docs/config.md is generated from config.SCHEMA; regenerate with
    `clppm config --schema --markdown > docs/config.md`."""
    page = (ROOT / "docs" / "config.md").read_text()
    assert page == C.schema_markdown(), "docs/config.md is out of date: clppm config --schema --markdown > docs/config.md"
    assert all(f.doc for s in list(C.SCHEMA.values()) + [C.LAYER_SCHEMA] for f in s.values())


# ----------------------------------------------------------------------------- the wheel
SOURCES = ("clppm", "kernels", "configs", "pyproject.toml", "README.md")


@pytest.mark.wheel
def test_wheel_install_renders_a_shipped_config(tmp_path):
    """Build the wheel from a copy of the sources, install it (no dependencies: those come from
    this environment's site-packages through a .pth, not its editable clppm) into a fresh venv,
    and render a shipped config by name from a folder far from the source tree."""
    import shutil
    import site
    src = tmp_path / "src"
    for s in SOURCES:
        (shutil.copytree if (ROOT / s).is_dir() else shutil.copy)(
            ROOT / s, src / s, **({"ignore": shutil.ignore_patterns("__pycache__")} if (ROOT / s).is_dir() else {}))
    pip = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]
    subprocess.run(pip + ["wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", str(tmp_path / "dist"),
                          str(src)], check=True, capture_output=True, timeout=300)
    whl = next((tmp_path / "dist").glob("clppm-*.whl"))
    import zipfile
    names = zipfile.ZipFile(whl).namelist()
    for n in ("clppm/configs/forearm.toml", "clppm/configs/cheek.toml", "clppm/kernels/eye.cl"):
        assert n in names, n
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    vsite = subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                           capture_output=True, text=True, check=True).stdout.strip()
    subprocess.run(pip + ["install", "--no-deps", "--no-index", "--target", vsite, str(whl)],
                   check=True, capture_output=True, timeout=300)
    Path(vsite, "_clppm_test_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}

    def run(*args):
        return subprocess.run([py, "-m", "clppm.cli", *args], cwd=work, env=env, capture_output=True,
                              text=True, timeout=300)
    where = subprocess.run([py, "-c", "import clppm, clppm.analysis.fit as f; print(clppm.__file__); "
                            "print(f.default_config_path())"], cwd=work, env=env, capture_output=True,
                           text=True, check=True).stdout.split()
    assert all(w.startswith(vsite) for w in where), where
    r = run("config", "--example", "forearm")
    assert r.returncode == 0 and r.stdout == (ROOT / "configs" / "forearm.toml").read_text(), r.stderr
    r = run("render", "forearm_flat", "--resolution", "16x12", "--passes", "1", "--photons", "5000",
            "-o", "out/ff.png", "-q")
    assert r.returncode == 0, r.stderr
    assert (work / "out" / "ff.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((work / "out" / "ff.json").read_text())["passes_done"] == 1
