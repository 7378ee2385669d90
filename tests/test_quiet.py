"""A first run says what it does and nothing else: no pyopencl compiler notices, a self-test that
announces itself and its time (silent under -q), and kernels that build with no compiler warning
(the logs read in full with PYOPENCL_COMPILER_OUTPUT=1).  Every run here starts from empty
caches (pyopencl's, PoCL's, clppm's self-test), so the builds are real."""
import os
import subprocess
import sys

import pytest

from clppm.compute.device import device_spec

SMALL = ["--resolution", "16x12", "--passes", "1", "--photons", "2000"]


def _fresh_env(tmp_path, **extra):
    e = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "xdg"), "CLPPM_CACHE_DIR": str(tmp_path / "clppm"),
         **extra}
    for k in ("POCL_CACHE_DIR", "PYOPENCL_COMPILER_OUTPUT", "PYOPENCL_CTX", "CLPPM_FAULT"):
        if k not in extra:
            e.pop(k, None)
    return e


def _clppm(args, env, cwd):
    return subprocess.run([sys.executable, "-m", "clppm.cli", *args], env=env, cwd=cwd,
                          capture_output=True, text=True, timeout=900)


def test_a_first_self_test_announces_itself_and_is_silent_under_q(dev, tmp_path):
    spec = device_spec(dev.device)
    env = _fresh_env(tmp_path)
    r = _clppm(["devices", "--device", spec], env, tmp_path)
    assert r.returncode == 0, r.stderr
    said = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(said) == 2, r.stderr
    assert said[0].startswith(f"self-testing device {spec} (") and "known-answer" in said[0]
    assert said[1].startswith(f"device {spec} self-test: passed in ") and said[1].endswith(" s"), said[1]
    r = _clppm(["devices", "--device", spec, "--check", "-q"], env, tmp_path)
    assert r.returncode == 0 and "self-test: passed" in r.stdout, r.stdout + r.stderr
    assert r.stderr.strip() == "", r.stderr


def test_a_cold_render_prints_no_compiler_notice(dev, tmp_path):
    env = _fresh_env(tmp_path, CLPPM_SELF_TEST="0")
    r = _clppm(["render", "forearm", *SMALL, "--device", device_spec(dev.device), "-q",
                "-o", "out/q.png"], env, tmp_path)
    assert r.returncode == 0, r.stderr
    assert "Warning" not in r.stderr and r.stderr.strip() == "", r.stderr
    assert (tmp_path / "out" / "q.png").stat().st_size > 0


def test_every_program_of_a_render_builds_without_compiler_warnings(dev, tmp_path):
    env = _fresh_env(tmp_path, CLPPM_SELF_TEST="0", PYOPENCL_COMPILER_OUTPUT="1")
    r = _clppm(["render", "forearm", *SMALL, "--device", device_spec(dev.device), "-q",
                "-o", "out/w.png"], env, tmp_path)
    assert r.returncode == 0, r.stderr
    logs = [ln for ln in r.stderr.splitlines() if "CompilerWarning" not in ln]
    bad = [ln for ln in logs if "warning:" in ln.lower() or "error:" in ln.lower()]
    assert not bad, "\n".join(bad[:20])


def test_a_second_render_loads_what_the_first_built(dev, tmp_path):
    """The report's programs_built: a cold render builds the eye, photon and gather programs (and
    the grid's), each once; a second render with the caches the first left builds the same
    programs, each once, from the cached binaries, in less time."""
    import json
    env = _fresh_env(tmp_path, CLPPM_SELF_TEST="0")
    built = []
    for name in ("cold", "warm"):
        r = _clppm(["render", "forearm", *SMALL, "--device", device_spec(dev.device), "-q",
                    "-o", f"out/{name}.png"], env, tmp_path)
        assert r.returncode == 0, r.stderr
        built.append(json.loads((tmp_path / "out" / f"{name}.json").read_text())["programs_built"])
    cold, warm = built
    assert {"eye.cl", "photon.cl", "gather.cl"} <= set(cold["by_file"])
    assert all(v["count"] == 1 for v in cold["by_file"].values()), cold
    assert {f: v["count"] for f, v in warm["by_file"].items()} == {f: v["count"] for f, v in cold["by_file"].items()}
    assert warm["seconds"] < cold["seconds"], (cold, warm)
