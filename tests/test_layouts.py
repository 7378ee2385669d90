"""The beam gather's two layouts (render.layout, clppm/integrators/beam.py): the gather (a work item per pixel
and band class querying the photon grid) and the scatter (a work item per photon adding its
terms into per point x band 64-bit fixed-point sums with atomic adds, kernels/scatter.cl).
They find the same (piece, photon) pairs and add the same fixed-point terms, and the scatter
redoes the gather's per-point float sums in the same point order, so they give the same image,
per pixel and band, exactly; and the same photons found and radii per point.  Checked on the
relief forearm at small size (layer-conforming depth), the flat forearm, with the per-point
radius, and at the model's open sides (the image's top and bottom rows: the disc's window);
each layout byte-identical with itself; a render resumed in the other layout gives the
uninterrupted bytes."""
from __future__ import annotations

import os

import numpy as np
import pytest

cl = pytest.importorskip("pyopencl")

from clppm.integrators import beam, photonpass, ppm
from clppm import config as C
from clppm.run import entry  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _cfg(name: str, layout: str, **render):
    cfg = C.load(os.path.join(ROOT, "configs", name))
    small = {("model", "size_mm"): [2.0, 2.0], ("camera", "position_mm"): [1.0, 1.0, 6.0],
             ("camera", "look_at_mm"): [1.0, 1.0, 0.0], ("camera", "resolution"): [28, 21],
             ("light", "position_mm"): [0.0, 2.0, 2.0], ("render", "photons"): 60000,
             ("render", "initial_photons"): 300, ("render", "layout"): layout}
    small.update({("render", k): v for k, v in render.items()})
    for (sec, key), v in small.items():
        cfg = C.override(cfg, sec, key, v)
    return cfg


def _no_scatter(sc) -> str | None:
    return beam.supports_scatter(sc.dev, sc.vol.nb, sc.gclass, sc.pp.hero)


def _passes(dev, cfg, n=2):
    sc = ppm.Pipeline.build(cfg, dev)
    why = _no_scatter(sc)
    if cfg["render"]["layout"] == "scatter" and why is not None:
        pytest.skip(why)
    cal = sc.calibrate()
    sc.apply(cal)
    st = sc.point_state(cal)
    acc = ppm.Accumulators.zeros(sc)
    for p in range(n):
        sc.run_pass(cal, st, p, acc, photonpass.Tallies(sc.vol.nb, sc.vol.nmat))
    pix, pairs = acc.host()
    return sc, (pix, pairs, st.M.get()[:sc.npts], st.R.get()[:sc.npts], st.N.get()[:sc.npts])


CASES = [("forearm.toml", {}), ("forearm_flat.toml", {}), ("forearm.toml", {"radius": "ppm"})]


@pytest.mark.parametrize("name,render", CASES, ids=["relief", "flat", "relief-ppm-radius"])
def test_layouts_same_image(dev, name, render):
    sg, g = _passes(dev, _cfg(name, "gather", **render))
    ss, s = _passes(dev, _cfg(name, "scatter", **render))
    assert sg.estimator.layout.name == "gather" and ss.estimator.layout.name == "scatter"
    pix, pairs = g[0], g[1]
    assert pairs.sum() > 100 * sg.npix                     # not vacuous
    for what, a, b in zip(("pixels", "pairs", "photons found", "R", "N"), g, s):
        assert np.array_equal(a, b), what
    # the top and bottom rows lie on the model's open sides, where the window cuts the disc
    img = pix.reshape(sg.eye.camera.height, sg.eye.camera.width, -1).sum(-1)
    assert (img[0] > 0).sum() > 14 and (img[-1] > 0).sum() > 14
    # the scatter's piece grid is not vacuous either: pieces filed in several cells each
    assert ss.estimator.layout.entries > 2 * ss.eye.npieces


@pytest.mark.parametrize("layout", ["gather", "scatter"])
def test_layout_same_bytes_twice(dev, layout):
    _, a = _passes(dev, _cfg("forearm.toml", layout), n=1)
    _, b = _passes(dev, _cfg("forearm.toml", layout), n=1)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_layout_resolution(dev, monkeypatch):
    sc = ppm.Pipeline.build(_cfg("forearm.toml", "auto"), dev)
    assert sc.estimator.layout.name == beam.AUTO[beam.device_kind(dev)]
    monkeypatch.setattr(beam, "supports_scatter", lambda *a: "no int64 atomics")
    assert beam.choose_layout("scatter", dev, sc.vol.nb, sc.gclass, sc.pp.hero) == "gather"   # the fallback
    # a scene whose paths carry other than 9 bands cannot scatter
    monkeypatch.undo()
    sc3 = ppm.Pipeline.build(_cfg("forearm.toml", "scatter", bands_per_path=3), dev)
    assert _no_scatter(sc3) is not None and sc3.estimator.layout.name == "gather"


def test_resume_in_the_other_layout(dev, tmp_path):
    """The layout does not change the picture (config.NOT_PICTURE): a checkpoint written by one
    layout resumes in the other, and gives the uninterrupted render's bytes."""
    assert "layout" in C.NOT_PICTURE
    full = entry.render(_cfg("forearm.toml", "gather", passes=2, chunk_passes=1), dev=dev)
    out = str(tmp_path / "a.exr")
    entry.render(_cfg("forearm.toml", "gather", passes=2, chunk_passes=1), dev=dev, out=out,
                       stop_after=1)
    from clppm.output import checkpoint as ckpt
    res = entry.render(_cfg("forearm.toml", "scatter", passes=2, chunk_passes=1), dev=dev,
                             out=str(tmp_path / "b.exr"), resume=ckpt.default_path(out))
    assert np.array_equal(np.asarray(full.spectral), np.asarray(res.spectral))


def test_band_math_lane_by_lane_gives_the_16_lane_bits(dev, monkeypatch):
    """Where wide_vectors is false (pip's PoCL on AVX-512 AMD CPUs) the beam gather builds its
    band math lane by lane (NO_VEC16); that loop does the 16-lane path's float operations per
    band, so the same passes give the same pixel sums, pairs and radii bit for bit.  On a device
    whose compiler cannot pass 16-lane vectors only the lane-by-lane build runs: skipped."""
    from clppm.compute import device
    if not device.wide_vectors(dev.device):
        pytest.skip(f"{dev.name}: no 16-lane vectors between functions (wide_vectors)")
    cfg = _cfg("forearm.toml", "gather")
    sw, w = _passes(dev, cfg, n=1)
    assert "NO_VEC16" not in sw.estimator.defines()
    for mod in (ppm, beam):
        monkeypatch.setattr(mod, "wide_vectors", lambda d: False)
    sn, n = _passes(dev, cfg, n=1)
    assert sn.estimator.defines().get("NO_VEC16") == 1
    assert w[1].sum() > 100 * sw.npix                      # not vacuous
    for what, a, b in zip(("pixels", "pairs", "photons found", "R", "N"), w, n):
        assert np.array_equal(a, b), what
