"""The walk on the smooth surfaces (model.surface = "smooth", kernels/smoothwalk.h): every pass
crosses the Catmull-Rom height fields themselves, so a point's layer is the one the smooth
surfaces give, the tilted plane is the rotated flat slab at any slope, and the path tracer has
no vertex between the staircase and the smooth surface (docs/relief.md, section 1).

The references here are independent of the kernels: the Catmull-Rom surfaces evaluated in numpy
from Volume.smooth, and the rotated flat slab traced by the flat build.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from clppm import config
from clppm.integrators import eyepass, photonpass
from clppm.scene import volume

import test_surface as ts

SLOPES = (0.15, 0.3)
INCIDENCES = (0.0, 40.0, 60.0)


# ----------------------------------------------------------------------------- numpy surfaces
def _cr(f):
    return 0.5 * np.stack([-f + 2 * f ** 2 - f ** 3, 2 - 5 * f ** 2 + 3 * f ** 3,
                           f + 4 * f ** 2 - 3 * f ** 3, f ** 3 - f ** 2])


def _cr2(f):
    """the weights' second derivatives (kernels/surface.h CR_S)"""
    return np.stack([2 - 3 * f, -5 + 9 * f, 4 - 9 * f, -1 + 3 * f])


def surface_h(S, x, y, dx, dy, periodic=False, dxx=False):
    """Interface samples S (ny, nx) as the Catmull-Rom bicubic at (x, y) (or its h_xx)."""
    ny, nx = S.shape
    gx, gy = x / dx - 0.5, y / dy - 0.5
    ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
    wx = _cr2(gx - ix) / (dx * dx) if dxx else _cr(gx - ix)
    wy = _cr(gy - iy)

    def idx(i, n):
        return i % n if periodic else np.clip(i, 0, n - 1)
    return sum(wx[a] * wy[b] * S[idx(iy - 1 + b, ny), idx(ix - 1 + a, nx)].astype(float)
               for a in range(4) for b in range(4))


def layer_of(vol, x, y, z):
    """The layer of each point among the smooth surfaces (-1 above, NL below), and how far it
    lies from the nearest surface of that layer."""
    h = []
    for k in range(vol.nl + 1):
        v = int(vol.iface[k, 3])
        h.append(surface_h(vol.smooth[v], x, y, vol.dx, vol.dy, vol.lateral == "periodic") + float(vol.iface[k, 0]) if v >= 0
                 else np.full(np.shape(x), float(vol.iface[k, 0]) if abs(vol.iface[k, 0]) < 1e29 else -1e30))
    L = np.full(np.shape(x), -1)
    for k in range(vol.nl + 1):
        L = np.where(z <= h[k], k, L)
    return L, h


def test_tile_bounds_hold_every_patch_point():
    """smooth_tile_bounds (the march's guarantee): at 600,000 points of random surfaces, open and
    periodic, every height lies within its tile's [lowest, highest] and every h_xx within K; a
    plane's K is 0 (to float rounding)."""
    rng = np.random.default_rng(1)
    for periodic in (False, True):
        S = (rng.normal(size=(300, 23)).cumsum(0).cumsum(1) * 0.1).astype(np.float32)   # two row blocks
        t = volume.smooth_tile_bounds(S, 5.0, 4.0, periodic)
        assert t.shape == (75, 6, 4)
        X, Y = np.meshgrid(np.linspace(0, 23 * 5.0, 400, endpoint=False) + 0.013,
                           np.linspace(0, 300 * 4.0, 1500, endpoint=False) + 0.011)
        tx, ty = (X // 5.0).astype(int) // volume.CELL, (Y // 4.0).astype(int) // volume.CELL
        H = surface_h(S, X, Y, 5.0, 4.0, periodic)
        assert (H >= t[ty, tx, 0]).all() and (H <= t[ty, tx, 1]).all()
        Hxx = surface_h(S, X, Y, 5.0, 4.0, periodic, dxx=True)
        assert (np.abs(Hxx) <= t[ty, tx, 2]).all()
        assert np.median(t[..., 1] - t[..., 0]) < 4 * np.median(np.abs(np.diff(S, axis=1))) * volume.CELL + 10
    plane = (0.3 * (np.arange(40) + 0.5) * 5.0)[None, :].repeat(12, 0).astype(np.float32)
    assert volume.smooth_tile_bounds(plane, 5.0, 5.0, False)[1:-1, 1:-1, 2].max() < 1e-5


def patch_coeffs(S: np.ndarray, ox: int, oy: int, periodic: bool) -> np.ndarray:
    """Bernstein coefficients of d^ox/dfx^ox d^oy/dfy^oy h over every patch (grid units): S is
    (ny, nx); patch (p, q), p = -1 .. nx - 1, lies between the column centres p and p + 1 in x
    (q likewise in y) and uses samples p - 1 .. p + 2, repeated (open) or wrapped (periodic)
    beyond the grid as surface.h hf_index does.  Returns (4 - oy, 4 - ox, ny + 1, nx + 1)."""
    pad = np.pad(S.astype(np.float64), 2, mode="wrap" if periodic else "edge")
    ny, nx = S.shape
    Qx, Qy = volume._weights_bernstein(ox), volume._weights_bernstein(oy)
    R = [sum(Qx[a, i] * pad[:, a:a + nx + 1] for a in range(4)) for i in range(Qx.shape[1])]
    return np.array([[sum(Qy[b, l] * r[b:b + ny + 1] for b in range(4)) for r in R]
                     for l in range(Qy.shape[1])])


def test_tile_bounds_are_the_bounds_of_every_patch_coefficient():
    """smooth_tile_bounds takes its bounds row block by row block, one coefficient at a time:
    the same numbers, bit for bit, as the extremes of patch_coeffs over the whole grid at once
    (open and periodic, a block boundary inside, grids not a whole number of tiles)."""
    rng = np.random.default_rng(4)
    for periodic in (False, True):
        S = rng.normal(size=(301, 45)) * 7.0
        dx, dy = 5.0, 4.0
        c = {o: patch_coeffs(S, *o, periodic) for o in ((0, 0), (2, 0), (0, 2), (1, 1), (1, 0), (0, 1))}
        amax = {o: np.abs(v).max(axis=(0, 1)) for o, v in c.items()}
        k = np.maximum(amax[2, 0] / (dx * dx), amax[0, 2] / (dy * dy)) + amax[1, 1] / (dx * dy)
        g2 = (amax[1, 0] / dx) ** 2 + (amax[0, 1] / dy) ** 2
        t = np.stack([volume._tile_reduce(c[0, 0].min(axis=(0, 1)), np.minimum),
                      volume._tile_reduce(c[0, 0].max(axis=(0, 1)), np.maximum),
                      volume._tile_reduce(k, np.maximum), volume._tile_reduce(g2, np.maximum)], -1)
        np.testing.assert_array_equal(volume.smooth_tile_bounds(S, dx, dy, periodic), volume._outwards(t))


# ----------------------------------------------------------------------------- the tilted plane
def _tilted(tmp_path, slope, tilted, d):
    ts.SLOPE = slope
    sub = tmp_path / f"s{slope}"
    sub.mkdir(exist_ok=True)
    cfg = ts.tilted_scene(sub, tilted, d)
    cfg["model"]["surface"] = "smooth"
    if tilted:       # the beam meets the plane at the model's centre, far from its open sides
        zc = -slope * ts.SIZE_MM * 500.0
        cfg["light"]["center_mm"] = [(ts.SIZE_MM * 500.0 - zc / d[2] * d[0]) / 1000.0, ts.SIZE_MM / 2]
    return cfg


@pytest.mark.parametrize("slope", SLOPES)
def test_tilted_plane_is_the_rotated_slab(dev, tmp_path, slope):
    """A clear layer over an index step 1.0 -> 1.5 into a turbid half-space, tilted by `slope`, under
    a pencil beam at 0, 40 and 60 degrees from the plane's normal (uphill): diffuse reflectance
    and absorption within 2 standard errors of the flat slab under the rotated beam.  The voxel
    staircase misses this by -2.5 % per 0.15 of slope (docs/relief.md)."""
    saved = ts.SLOPE
    try:
        for inc in INCIDENCES:
            a = math.radians(inc)
            local = np.array([math.sin(a), 0.0, -math.cos(a)])
            ts.SLOPE = slope
            nrm, tan = ts.frame()
            out = {}
            for name, tilted, d in (("slab", False, local), ("tilted", True, local[0] * tan + local[2] * nrm)):
                cfg = _tilted(tmp_path, slope, tilted, d)
                vol = volume.build(cfg)
                assert vol.smooth_walk == tilted
                out[name] = photonpass.trace_report(photonpass.PhotonPass.of_config(dev, vol, cfg, seed=11),
                                                    ts.N_PHOTONS, batches=10)
            s, t = out["slab"], out["tilted"]
            assert t["lost"] < 2e-3 and t["energy_balance_error"] == 0.0, t
            for key in ("Rd", "A"):
                se = math.hypot(s[key + "_se"], t[key + "_se"])
                assert abs(t[key] - s[key]) < 2 * se, (slope, inc, key, t[key], s[key], se)
    finally:
        ts.SLOPE = saved


def test_eye_rays_refract_at_the_tilted_plane_smooth(dev, tmp_path):
    """test_surface.py's Snell check on the smooth walk at twice its slope: eye rays straight down
    (within the camera's half field of view, 0.15 degrees) refract at the plane's normal: every
    turbid sample point looks back within 0.16 degrees of the analytic direction for the
    central ray (refraction into n = 1.5 narrows the spread)."""
    saved = ts.SLOPE
    try:
        ts.SLOPE = 0.3
        cfg = ts.tilted_scene(tmp_path, True, (0.0, 0.0, -1.0), camera=True)
        cfg["model"]["surface"] = "smooth"
        ang, _ = ts.turbid_angles(dev, cfg)
        assert ang.max() < 0.16, np.percentile(ang, [50, 99, 100])
    finally:
        ts.SLOPE = saved


# ----------------------------------------------------------------------------- a relief scene
def relief_scene(surface="smooth", depth=20.0, amplitude=12.0, lateral="open", light="wide") -> dict:
    raw = {"model": {"name": "relief", "size_mm": [0.4, 0.3], "lateral": lateral, "quantize": True,
                     "voxel_um": 5.0, "lateral_voxel_um": 5.0, "surface": surface},
           "spectrum": {"start_nm": 500.0, "stop_nm": 600.0, "step_nm": 50.0},
           "relief": {"kind": "generated", "depth_um": depth, "spacing_um": 120.0, "width_um": 25.0,
                      "seed": 3},
           "papillae": {"amplitude_um": amplitude, "period_um": 60.0},
           "light": {"kind": light, "direction": [0.3, 0.1, -0.95], "spectrum": "flat",
                     "center_mm": [0.2, 0.15], "width_mm": [0.3, 0.2]},
           "camera": {"position_mm": [0.2, 0.15, 5.0], "look_at_mm": [0.2, 0.15, 0.0], "fov_deg": 3.0,
                      "resolution": [24, 18]},
           "render": {"method": "a", "threshold": 1e-2},
           "layer": [{"name": "sc", "thickness_um": 15.0, "n": 1.55, "mua": 2.0, "mus": 300.0, "g": 0.8,
                      "bottom": "surface"},
                     {"name": "epi", "thickness_um": 60.0, "n": 1.4, "mua": 5.0, "mus": 400.0, "g": 0.8,
                      "bottom": "papillae"},
                     {"name": "derm", "thickness_um": math.inf, "n": 1.4, "mua": 1.0, "mus": 200.0, "g": 0.8,
                      "bottom": "flat"}]}
    return config.validate(raw, "relief scene")


def _stored(pp, n):
    import pyopencl as cl
    pos = np.empty((n, 4), np.float32)
    db = np.empty((n, 4), np.float32)
    cl.enqueue_copy(pp.dev.queue, pos, pp.pos_w)
    cl.enqueue_copy(pp.dev.queue, db, pp.dir_b)
    return pos, db


def test_points_lie_in_their_smooth_layers(dev):
    """On a relief with papillae (three layers, three indices): every stored photon and every eye
    sample point lies in the layer the smooth surfaces give its position (numpy's Catmull-Rom),
    or within 1e-3 um of that layer's boundary; on the voxel staircase thousands do not."""
    for surface in ("smooth", "voxels"):
        cfg = relief_scene(surface)
        vol = volume.build(cfg)
        pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=120_000, seed=4)
        r = pp.run_pass(0, 60_000)
        pos, db = _stored(pp, r["stored"])
        Lp = db[:, 3].astype(np.int32) >> 8
        ed = eyepass.run(dev, vol, volume.upload_volume(dev, vol), cfg)
        pe = ed.pt_pos.get()[:ed.npoints]
        de = ed.pt_dir.get()[:ed.npoints]
        x = np.concatenate([pos[:, 0], pe["x"]]).astype(float)
        y = np.concatenate([pos[:, 1], pe["y"]]).astype(float)
        z = np.concatenate([pos[:, 2], pe["z"]]).astype(float)
        L = np.concatenate([Lp, de["w"].astype(np.int32)])
        Ls, h = layer_of(vol, x, y, z)
        H = np.stack(h)
        top, bot = H[np.clip(L, 0, vol.nl), np.arange(len(L))], H[np.clip(L + 1, 0, vol.nl), np.arange(len(L))]
        off = np.maximum(z - top, bot - z)            # > 0: outside its layer by that much
        bad = (Ls != L) & (off > 1e-3)
        if surface == "smooth":
            assert len(L) > 50_000 and bad.sum() == 0, (bad.sum(), off[bad][:10])
        else:
            assert bad.sum() > 1000, bad.sum()


def test_gather_frames_follow_the_smooth_surfaces(dev):
    """The beam gather's layer-conforming depth on the smooth walk: every stored photon's slab
    (photon_slabs) is its layer's top and bottom at its own position on the smooth surfaces, so
    it holds the photon; and a conforming piece's frame (piece_slabs) puts both its ends at
    their own fractional depth in the layer, so the pieces of a crossing tile the photons' depths
    (the midpoint's column slab placed them up to half a column's slope off, and the image read
    2 % low)."""
    import pyopencl.array as cla
    import pyopencl.cltypes as cltypes
    from clppm.compute.device import kernel_defines
    from clppm.compute.kernelcall import Kernel
    from clppm.integrators.ppm import band_classes
    cfg = relief_scene("smooth")
    vol = volume.build(cfg)
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=60_000, seed=5)
    n = pp.run_pass(0, 30_000)["stored"]
    pos, db = _stored(pp, n)
    prg = dev.build("gather.cl", kernel_defines(vol, hero=pp.hero, estimator="beam",
                                                gclass=band_classes(vol.nb, pp.hero)))
    q = dev.queue
    sl = cla.empty(q, n, cltypes.float2)
    Kernel(prg, "photon_slabs")(q, n, P=pp.pbuf, iface=pp.vbuf.iface, heights=pp.vbuf.heights,
                                spos_w=pp.pos_w, sdir_b=pp.dir_b, n=n, sslab=sl.data)
    tb = sl.get().view(np.float32).reshape(n, 2).astype(float)
    L = db[:, 3].astype(np.int32) >> 8
    _, h = layer_of(vol, pos[:, 0].astype(float), pos[:, 1].astype(float), pos[:, 2])
    H = np.stack(h)
    top, bot = H[L, np.arange(n)], H[L + 1, np.arange(n)]
    bounded = bot > -1e29
    assert np.abs(tb[:, 0] - top).max() < 1e-3
    assert np.abs(tb[bounded, 1] - bot[bounded]).max() < 1e-3
    assert (pos[:, 2] <= tb[:, 0] + 1e-3).all() and (pos[bounded, 2] >= tb[bounded, 1] - 1e-3).all()

    ed = eyepass.run(dev, vol, pp.vbuf, cfg, geometry=True)
    m = ed.npieces
    ps = cla.zeros(q, m, cltypes.float4)
    Kernel(prg, "piece_slabs")(q, m, P=pp.pbuf, iface=pp.vbuf.iface, heights=pp.vbuf.heights, geo=ed.geo.data,
                               npieces=m, pslab=ps.data)
    fr = ps.get().view(np.float32).reshape(m, 4).astype(float)
    g = ed.geo.get()[:2 * m].view(np.float32).reshape(m, 2, 4).astype(float)
    s0, d, ln, Lk = g[:, 0, :3], g[:, 1, :3], g[:, 0, 3], g[:, 1, 3].astype(int)
    e = s0 + ln[:, None] * d

    def phi(p):
        _, hh = layer_of(vol, p[:, 0], p[:, 1], p[:, 2])
        hh = np.stack(hh)
        t, b = hh[Lk, np.arange(m)], hh[np.minimum(Lk + 1, vol.nl), np.arange(m)]
        return (t - p[:, 2]) / (t - b), b > -1e29
    phi0, ok = phi(s0)
    phi1, _ = phi(e)
    fphi = lambda z: (fr[:, 0] - z) / (fr[:, 0] - fr[:, 1])
    T = (s0[:, 2] - e[:, 2]) / (phi1 - phi0)
    Tm = np.stack(layer_of(vol, *(s0 + 0.5 * ln[:, None] * d).T)[1])
    Tm = Tm[Lk, np.arange(m)] - Tm[np.minimum(Lk + 1, vol.nl), np.arange(m)]
    sel = (fr[:, 2] != 0) & ok & (np.abs(phi1 - phi0) > 0.01) & (T > 0.11 * Tm) & (T < 9 * Tm)
    assert sel.sum() > 200, sel.sum()
    assert np.abs(fphi(s0[:, 2]) - phi0)[sel].max() < 2e-3
    assert np.abs(fphi(e[:, 2]) - phi1)[sel].max() < 2e-3


def test_path_tracer_vertices_are_on_the_smooth_side(dev):
    """The path tracer on the smooth walk: no scattering vertex lies between the staircase and the
    smooth surface (the run report's manifold_nee.vertex_above_smooth_surface is 0; the voxel walk
    has such vertices)."""
    from clppm.integrators import pathtracer
    counts = {}
    for surface in ("smooth", "voxels"):
        cfg = relief_scene(surface, light="point")
        cfg["light"]["position_mm"] = [0.25, 0.2, 3.0]
        pathtracer.check_scene(cfg)
        tracer = pathtracer.PathTracer.of_config(dev, volume.build(cfg), cfg)
        tracer.run_pass(0)
        counts[surface] = dict(zip(pathtracer.MNEE_STATS, tracer.mnee_totals()))["vertex_above_smooth_surface"]
    assert counts["smooth"] == 0 and counts["voxels"] > 0, counts


def test_flat_limit_and_closed_energy(dev):
    """A relief of amplitude 1e-3 um on the smooth walk gives the flat model's tallies (within 2
    standard errors), and a periodic relief (closed sides, semi-infinite) loses no photon: what
    enters is reflected or absorbed, the integer tallies balance exactly."""
    flat = relief_scene("smooth", depth=0.0, amplitude=0.0, light="wide")
    tiny = relief_scene("smooth", depth=1e-3, amplitude=1e-3, light="wide")
    out = {}
    for name, cfg in (("flat", flat), ("tiny", tiny)):
        vol = volume.build(cfg)
        assert vol.flat == (name == "flat")
        out[name] = photonpass.trace_report(photonpass.PhotonPass.of_config(dev, vol, cfg, seed=8), 60_000, batches=10)
    for key in ("Rd", "A", "specular"):
        se = math.hypot(out["flat"].get(key + "_se", 0.0), out["tiny"].get(key + "_se", 0.0))
        assert abs(out["tiny"][key] - out["flat"][key]) < 2 * se + 2e-4, (key, out)
    cfg = relief_scene("smooth", lateral="periodic", light="wide")
    rep = photonpass.trace_report(photonpass.PhotonPass.of_config(dev, volume.build(cfg), cfg, seed=9), 30_000, batches=5)
    assert rep["energy_balance_error"] == 0.0 and rep["lost"] < 1e-4, rep


def test_photon_walk_is_the_plain_walk(dev):
    """The photon pass's own walk (photon.cl photon_smooth_boundary: several tiles in one step)
    against the other passes' walk, tile by tile
    (smoothwalk.h, the PHOTON_PLAIN_WALK build), on a relief with papillae and three indices:
    independent seeds, and every tally, absorption per layer included, agrees within 4 standard
    errors (batch means).  A missed crossing moves light between layers."""
    cfg = relief_scene("smooth")
    vol = volume.build(cfg)
    cats = [photonpass.CATEGORIES.index(c) for c in ("specular", "diffuse", "transmitted", "lost")]
    cats += list(range(photonpass.NA, photonpass.NA + vol.nl))
    n, batches = 160_000, 10
    F = [np.array([a.sum(0)[cats] / (photonpass.W0 * (n // batches))
                   for a in photonpass.PhotonPass.of_config(dev, vol, cfg, seed=s, plain_walk=plain).trace(n, batches=batches)])
         for s, plain in ((21, False), (22, True))]
    se = np.sqrt(F[0].var(0, ddof=1) / batches + F[1].var(0, ddof=1) / batches)
    ok = se > 0                                     # none transmitted: a semi-infinite dermis
    z = (F[0].mean(0) - F[1].mean(0))[ok] / se[ok]
    assert ok.sum() == len(cats) - 1 and np.all(np.abs(z) < 4), (z, F[0].mean(0), F[1].mean(0))


def test_smooth_walk_is_deterministic(dev):
    """The same seed gives the same stored photons and tallies, byte for byte."""
    cfg = relief_scene("smooth")
    vol = volume.build(cfg)
    runs = []
    for _ in range(2):
        pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=40_000, seed=6)
        r = pp.run_pass(0, 20_000)
        pos, db = _stored(pp, r["stored"])
        order = np.lexsort(pos.T[::-1])
        runs.append((r, pos[order].tobytes(), db[order].tobytes(), pp.tallies.counts))
    assert runs[0] == runs[1]
