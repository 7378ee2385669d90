"""``clppm fit --image``: fitting the reflectance factor of a region of a rendered image.

A flat forearm whose basal layer carries a broad melanin spot (a ``[[map]]``: 0.4 at its
centre over the layer's own 0.1) is rendered by the path tracer, which sees maps on flat
layers; the fit reads the spectral EXR and its report, divides a region's radiance by the white
reference under the render's own light, and fits the uniform model (the render's config without
its maps) to it.  Over the spot the fitted melanin factor must come out several times the one
far from it; far from it, near the model's own value.  Reading the wrong region, dropping the
white reference's per-pixel geometry or fitting with the maps left in the model each break one
of these.
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from clppm import cli
from clppm.analysis.reflectance import image_region
from clppm.config import ConfigError

ROOT = os.path.dirname(os.path.dirname(__file__))
FRECKLES = os.path.join(ROOT, "configs", "forearm_freckles.toml")

pytestmark = pytest.mark.once      # a 45 s path-traced image: one implementation in CI

# 16x12 pixels over the 13.3 x 10 mm view: pixel columns 4-6 lie over x = 1.7-4.2 mm (the
# spot, centred at x = 2 mm, 2 mm across), columns 10-12 over x = 6.7-9.2 mm (no spot).
SPOT, CLEAR = (4, 4, 7, 8), (10, 4, 13, 8)


def _config(tmp_path) -> str:
    text = open(FRECKLES).read()
    text = text[:text.index("[[inclusion]]")] + text[text.index("[[map]]"):]
    text = text[:text.index("spots = [")] + \
        "spots = [{center_mm = [2.0, 5.0], radius_um = 2000.0, peak = 0.4}]\n"
    p = tmp_path / "spot.toml"
    p.write_text(text)
    return str(p)


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    """The path tracer's render of the spot (16x12, 20-nm bands, 4 passes of 256 paths per pixel)."""
    tmp = tmp_path_factory.mktemp("fit_image")
    out = str(tmp / "spot.exr")
    rc = cli.main(["render", _config(tmp), "--integrator", "pt", "--resolution", "16x12", "--passes", "4",
                   "--set", "render.specular=false", "--set", "render.pt_samples_per_pass=256",
                   "--set", "spectrum.step_nm=20",
                   "--seed", "3", "-o", out, "-q"])
    assert rc == 0
    return out


def _fit(image, region, tmp_path, name) -> dict:
    out = tmp_path / f"{name}.toml"
    rc = cli.main(["fit", "--image", image, "--region", ",".join(map(str, region)), "-o", str(out),
                   "--photons", "1500", "--bands", "400:760:40", "--max-iter", "3", "-q"])
    assert rc == 0
    return json.loads((tmp_path / f"{name}.json").read_text())


def test_region_reads_the_spot(image):
    """The region's reflectance factor: below the clear skin's over the spot, by more in the blue
    than in the near infrared (melanin's absorption falls as lambda^-3.3); the light's angle at
    each region's centre, not the image centre's."""
    spot, clear = image_region(image, SPOT), image_region(image, CLEAR)
    blue, nir = spot.wl < 480, spot.wl > 700
    ratio_blue = spot.R[blue].mean() / clear.R[blue].mean()
    ratio_nir = spot.R[nir].mean() / clear.R[nir].mean()
    assert ratio_blue < 0.7 and ratio_blue < ratio_nir - 0.1 and ratio_nir < 1.05
    assert spot.angle_deg != pytest.approx(clear.angle_deg, abs=2.0)
    assert "map" in spot.cfg and spot.region == SPOT


def test_fit_over_the_spot_finds_its_melanin(image, tmp_path):
    """The fitted melanin factor over the spot is 1.5-5 times the one far from it, which lies
    near 1.  The map's basal melanin averages ~3.3 times the layer's own over the spot's
    region; light spreading under the skin from around it lowers what the region reads (2.1
    with this seed on Intel's runtime).  Fitting the wrong region or the maps' model reads ~1."""
    spot = _fit(image, SPOT, tmp_path, "spot")["params"]
    clear = _fit(image, CLEAR, tmp_path, "clear")["params"]
    assert 0.6 < clear["melanin"] < 1.6
    assert 1.5 < spot["melanin"] / clear["melanin"] < 5.0


def test_bad_image_and_region_exit_2(image, tmp_path, capsys):
    """Bad --image / --region: one line naming the flag and value, exit 2, before any work."""
    for argv, key in ((["--image", str(tmp_path / "none.exr")], "--image"),
                      (["--image", image, "--region", "0,0,17,4"], "--region"),
                      (["--region", "0,0,4,4", "--subject", "3"], "--region"),
                      (["--image", image, "--subject", "3"], "--subject"),
                      (["--image", image, "--bands", "300:700:20"], "--bands")):
        rc = cli.main(["fit", *argv, "-o", str(tmp_path / "x.toml"), "-q"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and key in err[0], (argv, err)
    with pytest.raises(ConfigError, match="--image"):
        image_region(os.path.splitext(image)[0] + ".png", None)
    assert not os.path.exists(tmp_path / "x.toml")
