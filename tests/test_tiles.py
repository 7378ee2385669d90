"""Tiles of sample points (render.tile_points): with the global radius the eye pass and the
gather run tile by tile, and the image is the untiled one, byte for byte.

Why bytes and not a tolerance: a pixel belongs to one tile, its work item walks the same
points in the same order with the same R0 and photon grid, and it adds its one term per pass
to its own accumulator, so no sum changes order.  The calibration's R0 is computed tile by
tile from the same kernel per point, and its global factor from the same subsample.
"""
from __future__ import annotations

import copy

import numpy as np
import pytest

from clppm import config as C
from clppm.compute import device as D
from clppm.config import ConfigError
from clppm.integrators import ppm
from clppm.request import RenderRequest
from clppm.run import entry
from scenes import tiny_dict

BASE = tiny_dict(photons=20000, initial_photons=50, passes=3, checkpoint_every=0, seed=7,
                 chunk_passes=2)

VARIANTS = {
    "beam": {},
    "sphere_spp2": {"render": {"estimator": "sphere", "method": "a"}, "camera": {"spp": 2}},
}


def _cfg(tile_points, changes):
    raw = copy.deepcopy(BASE)
    for sec, kv in changes.items():
        raw[sec].update(kv)
    raw["render"]["tile_points"] = tile_points
    return C.validate(raw, "tiles")


def _render(dev, tmp_path, name, tile_points, changes):
    out = tmp_path / f"{name}.exr"
    res = entry.render(_cfg(tile_points, changes), dev=dev, out=str(out))
    return out.read_bytes(), res


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_tiled_render_is_the_untiled_one(dev, tmp_path, variant):
    changes = VARIANTS[variant]
    b1, one = _render(dev, tmp_path, "one", 0, changes)
    npts = one.report["sample_points"]
    assert one.report["tiles"] == 1
    b2, many = _render(dev, tmp_path, "many", max(npts // 5, 1), changes)
    assert many.report["tiles"] >= 4, many.report["tiles"]
    assert many.report["sample_points"] == npts
    assert many.report["gather_pairs"] == one.report["gather_pairs"] > 0
    assert many.report["first_search_mean_photons"] == one.report["first_search_mean_photons"]
    assert many.report["store_zmin_um"] == one.report["store_zmin_um"]
    assert np.array_equal(many.spectral, one.spectral)
    assert one.spectral.max() > 0
    assert b1 == b2, "tiled and untiled EXR files differ"


def test_tiles_hold_at_most_tile_points(dev):
    """Each tile holds at most render.tile_points points (a tile is at least 64 pixels), the
    tiles cover every pixel once, and the calibration's R0 is the untiled one."""
    cfg = _cfg(0, {})
    whole = ppm.Pipeline.build(RenderRequest(cfg), dev)
    cal1 = whole.calibrate()
    limit = max(whole.npts_total // 6, 1)
    sc = ppm.Pipeline.build(RenderRequest(_cfg(limit, {})), dev)
    tiles = sc.tiles.tiles
    assert tiles[0][0] == 0 and tiles[-1][1] == sc.tiles.npix
    assert all(a[1] == b[0] for a, b in zip(tiles, tiles[1:]))
    for t, (p0, p1) in enumerate(tiles):
        n, _ = sc.tiles.sizes(t)
        assert n <= limit or p1 - p0 <= 64
    cal = sc.calibrate()
    assert np.array_equal(cal.R0, cal1.R0) and cal.store_zmin == cal1.store_zmin


def test_tile_that_cannot_fit_is_refused(dev, monkeypatch):
    real = D.describe

    def describe(device):
        d = real(device)
        d["global_mem_bytes"], d["max_alloc_bytes"] = 512 * 2**20, 128 * 2**20
        return d
    monkeypatch.setattr(D, "describe", describe)
    with pytest.raises(ConfigError, match=r"render.tile_points = 100000000: .* MiB .* 512 MiB"):
        entry.render(_cfg(10**8, {}), dev=dev)
