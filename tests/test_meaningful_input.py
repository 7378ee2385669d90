"""Nothing silently wrong: a scene without an image is refused before work, every value a
command uses is one the user gave or one it prints, messages name what the user gave, and the
Python API does what its words say.
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest

from clppm import config as C
from test_cli import assert_one_line_error, clppm_inproc
from test_outputs import no_work, tiny  # noqa: F401  (the fixture)

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- scenes without an image
@pytest.mark.parametrize("item,needles", [
    ("camera.position_mm=[5,5,-30]", ("camera.position_mm", "under the skin")),
    ("light.power_w=0", ("light.power_w", "emits nothing")),
    ("light.position_mm=[0,10,-1]", ("light.position_mm", "under the skin")),
    ("camera.fov_deg=170", ("camera.fov_deg", "170", "black")),
])
def test_scene_without_an_image_refused_before_work(tmp_path, no_work, item, needles):
    r = clppm_inproc("render", "forearm", "--resolution", "32x24", "--set", item, "-o", tmp_path / "a.png")
    assert_one_line_error(r, *needles)


def test_exposure_that_cannot_be_computed_is_said_and_reported(tmp_path):
    """A pencil beam puts no light on the white reference: one warning line before work, and
    the report says the exposure was assumed."""
    cfg, out = tiny(tmp_path, passes=1), tmp_path / "p.png"
    r = clppm_inproc("render", cfg, "--set", 'light.kind="pencil"', "--set", "light.center_mm=[0.5,0.5]",
                     "-o", out, "-q")
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "warning" in ln]
    assert len(warn) == 1 and "render.exposure" in warn[0], r.stderr
    rep = json.loads((tmp_path / "p.json").read_text())
    assert rep["exposure_from"].startswith("assumed 1.0") and rep["exposure"] == 1.0
    assert any("render.exposure" in a for a in rep["assumed"])


# ----------------------------------------------------------------------------- trace --slab
def test_trace_slab_echoes_and_names_defaults(tmp_path):
    out = tmp_path / "t.json"
    r = clppm_inproc("trace", "--slab", "mua=10,mus=90,g=0.75", "--photons", 2000, "--json", out)
    assert r.returncode == 0, r.stderr
    first = r.stdout.splitlines()[0]
    for needle in ("mua=10", "mus=90", "g=0.75", "n=1", "d=inf", "not given", "semi-infinite"):
        assert needle in first, first
    rep = json.loads(out.read_text())
    assert rep["slab"]["not_given"] == ["n", "d"] and rep["slab"]["mua"] == 10


def test_trace_slab_duplicate_key_refused(no_work):
    r = clppm_inproc("trace", "--slab", "mua=10,mua=20,mus=90,g=0.75")
    assert_one_line_error(r, "mua", "twice")


# ----------------------------------------------------------------------------- messages
def test_photons_below_initial_photons_answers_about_photons():
    from clppm.request import resolved_config
    cfg = resolved_config(C.load("forearm"), photons=1)
    assert cfg["render"]["photons"] == 1 and cfg["render"]["initial_photons"] == 1
    with pytest.raises(C.ConfigError) as e:
        resolved_config(C.load("forearm"), photons=0)
    assert "--photons" in str(e.value) and "initial_photons" not in str(e.value)


def test_photons_zero_message_names_the_flag(no_work):
    r = clppm_inproc("render", "forearm", "--photons", 0)
    assert_one_line_error(r, "--photons", "0")


def test_unwritable_folder_message_is_clear(no_work):
    r = clppm_inproc("render", "forearm", "-o", "/proc/self/a.exr")
    line = assert_one_line_error(r, "/proc/self/a.exr", "does not take new files")
    assert "folder /proc/self:" not in line


def test_set_without_key_message(no_work):
    r = clppm_inproc("render", "forearm", "--set", "=")
    line = assert_one_line_error(r, "--set", "SECTION.KEY=VALUE")
    assert "= = " not in line


@pytest.mark.parametrize("args", [("render", "forearm", "--photons", "x"), ("trace", "--batches", "y"),
                                  ("config", "--nope"), ("render",)])
def test_one_error_prefix_for_every_command(args):
    r = clppm_inproc(*args)
    line = assert_one_line_error(r)
    assert line.startswith("clppm: error: "), line


def test_scheme_label_reads_as_words():
    from clppm.integrators.eyepass import scheme
    assert scheme("e").label() == "e: random spacing, mean 1/extinction (mean over the bands)"
    assert scheme("b").label() == "b: equal spacing 7 um"


# ----------------------------------------------------------------------------- the API and its words
def test_set_item_returns_a_copy_as_documented():
    cfg = C.load("forearm")
    new = C.set_item(cfg, "layer.0.n=1.45")
    assert new["layer"][0]["n"] == 1.45 and cfg["layer"][0]["n"] == 1.5
    readme = (ROOT / "README.md").read_text()
    assert "changes one value" not in readme
    assert "set_item" in readme and "returns a copy" in readme
    assert "unchanged" in C.set_item.__doc__


def test_load_accepts_a_shipped_name():
    assert C.load("forearm") == C.load(C.shipped_configs()["forearm"])


def test_a_folder_does_not_shadow_a_shipped_config(tmp_path):
    (tmp_path / "forearm").mkdir()
    old = os.getcwd()
    try:
        os.chdir(tmp_path)
        assert C.find("forearm") == C.shipped_configs()["forearm"]
        (tmp_path / "mine").mkdir()
        with pytest.raises(C.ConfigError, match="folder"):
            C.find("mine")
    finally:
        os.chdir(old)


def test_render_help_does_not_limit_pt_to_flat_scenes():
    r = clppm_inproc("render", "--help")
    text = " ".join(r.stdout.split())
    assert "flat scenes," not in text and "(flat scenes" not in text
    assert "relief" in text


def _headings(md: Path) -> set[str]:
    return {ln.lstrip("#").strip().lower() for ln in md.read_text().splitlines() if ln.startswith("#")}


def test_shipped_configs_point_at_sections_that_exist():
    """A config comment citing a section (README, "X" / docs/F.md, "X") names a heading that
    exists in that file."""
    for toml in sorted((ROOT / "configs").glob("*.toml")):
        for m in re.finditer(r'(README|docs/[\w.]+)[:,]?\s*"([^"]+)"', toml.read_text()):
            md = ROOT / ("README.md" if m.group(1) == "README" else m.group(1))
            assert md.exists() and m.group(2).lower() in _headings(md), f"{toml.name}: {m.group(0)}"
