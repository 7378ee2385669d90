"""``clppm bench``: one ``--quick --json`` run on the selected device, its numbers checked
against each other (rates are counts over the times that were measured), against physics (the
MCML slab's Rd; the slab's photons take fewer events than the forearm's, so more go per ms) and
against the text it prints; bad options exit 2 with one line."""
from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import pytest

#: MCML verification slab (Wang, Jacques & Zheng 1995): diffuse reflectance
MCML_RD = 0.09739


@pytest.fixture(scope="module")
def result():
    r = subprocess.run([sys.executable, "-m", "clppm.cli", "bench", "--quick", "--json", "-q"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _scene(entry, name):
    return next(s for s in entry["scenes"] if s["scene"] == name)


def test_bench_json_fields(result):
    """One device (the selected one), named, with its implementation and version, and the three
    measurements."""
    assert result["quick"] is True and result["repeats"] == 3
    (entry,) = result["devices"]
    assert re.fullmatch(r"\d+:\d+", entry["spec"])
    for k in ("device", "implementation", "version"):
        assert isinstance(entry[k], str) and entry[k], k
    assert [s["scene"] for s in entry["scenes"]] == ["mcml slab", "forearm"]
    assert entry["gather"]["scene"] == "forearm"


def test_bench_rates_are_counts_over_times(result):
    """Each rate is its count over the fastest of its timed runs (the median's over the median),
    positive and finite, best >= median."""
    (entry,) = result["devices"]
    for s in entry["scenes"]:
        assert len(s["seconds_all"]) == s["repeats"] == 3
        assert s["seconds"] == min(s["seconds_all"])
        assert s["photons_per_ms"] == pytest.approx(s["photons"] / s["seconds"] / 1000, rel=1e-12)
        assert s["photons_per_ms_median"] == pytest.approx(
            s["photons"] / sorted(s["seconds_all"])[1] / 1000, rel=1e-12)
        assert math.isfinite(s["photons_per_ms"]) and s["photons_per_ms"] > 0
        assert s["photons_per_ms"] >= s["photons_per_ms_median"]
    g = entry["gather"]
    assert g["pairs"] > 0 and g["seconds"] == min(g["seconds_all"])
    assert g["pairs_per_s"] == pytest.approx(g["pairs"] / g["seconds"], rel=1e-12)
    assert math.isfinite(g["pairs_per_s"]) and g["pairs_per_s"] >= g["pairs_per_s_median"] > 0


def test_bench_traces_the_scenes(result):
    """The slab traced is MCML's (its Rd within ~5 standard errors of 200k photons), and its
    photons, with fewer events each than the forearm's 9 layers and 81 bands, go faster."""
    (entry,) = result["devices"]
    slab, fore = _scene(entry, "mcml slab"), _scene(entry, "forearm")
    assert abs(slab["Rd"] - MCML_RD) < 0.004, slab["Rd"]
    assert slab["photons_per_ms"] > fore["photons_per_ms"]


def test_bench_text_says_the_json_rates(result):
    """The text form (MCX's "simulation speed: N photons/ms") prints the same rates."""
    from clppm.analysis.bench import speed_lines
    (entry,) = result["devices"]
    text = "\n".join(speed_lines(entry))
    got = [float(x) for x in re.findall(r"simulation speed: ([\d.]+) photons/ms", text)]
    assert got == pytest.approx([s["photons_per_ms"] for s in entry["scenes"]], abs=0.006)
    assert entry["implementation"] in text and entry["version"] in text


@pytest.mark.parametrize("args, needle", [
    (["--devices", "2"], "--devices = '2'"),
    (["--devices", "all", "--device", "0:0"], "not both"),
    (["--repeats", "0"], "--repeats = 0"),
])
def test_bench_bad_options(args, needle):
    """Bad options: exit 2, one line naming the option and value, before any work."""
    from clppm import cli
    import contextlib
    import io
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = cli.main(["bench", *args])
    lines = err.getvalue().strip().splitlines()
    assert rc == 2 and len(lines) == 1 and needle in lines[0], err.getvalue()
