"""Device photon grid: grid gather == brute-force gather exactly, CSR validity."""
from __future__ import annotations

import numpy as np
import pytest

from clppm.integrators import hashgrid as hg
from clppm.checks import testing
from clppm.compute import structs

NB = 8
METHODS = ["counting", "radix"]


@pytest.fixture(scope="module")
def bufs(dev):
    return hg.GridBuffers(dev)


def photons(rng, xyz):
    n = xyz.shape[0]
    pos = np.zeros((n, 4), np.float32)
    pos[:, :3] = xyz
    pos[:, 3] = rng.lognormal(0.0, 1.0, n)          # weights over a wide range
    dirb = np.zeros((n, 4), np.float32)
    d = rng.normal(size=(n, 3))
    dirb[:, :3] = d / np.linalg.norm(d, axis=1, keepdims=True)
    dirb[:, 3] = rng.integers(-1, NB + 1, n)         # a few bands out of range on purpose
    return pos, dirb


def host_cells(params, xyz):
    """Cell of each point, float32 arithmetic as in grid.h."""
    xyz = np.asarray(xyz, np.float32)
    lo = np.array([params["lo_x"], params["lo_y"], params["lo_z"]], np.float32)
    n = np.array([params["nx"], params["ny"], params["nz"]])
    inv = np.array([params["inv_h"], params["inv_h"], params["inv_hz"]], np.float32)
    t = np.floor((xyz - lo) * inv)
    c = np.clip(t, 0, n - 1).astype(np.int64)
    return c[:, 0] + n[0] * (c[:, 1] + n[1] * c[:, 2])


def check_grid(grid, pos, dirb):
    n = pos.shape[0]
    cs = grid.cell_start.get().astype(np.int64)
    assert cs.shape == (grid.ncells + 1,)
    assert cs[0] == 0 and cs[-1] == n
    assert np.all(np.diff(cs) >= 0)
    if n == 0:
        return
    sp = grid.spos_w.get().view(np.float32).reshape(n, 4)
    sd = grid.sdir_b.get().view(np.float32).reshape(n, 4)
    # every sorted photon sits in its cell
    cell_of_slot = np.repeat(np.arange(grid.ncells), np.diff(cs))
    assert np.array_equal(host_cells(grid.params, sp[:, :3]), cell_of_slot)
    # the sorted records are a permutation of the input records (pos and dir together)
    a = np.concatenate([pos, dirb], axis=1)
    b = np.concatenate([sp, sd], axis=1)
    ka = np.lexsort(a.T[::-1])
    kb = np.lexsort(b.T[::-1])
    assert np.array_equal(a[ka], b[kb])


def check_gather(dev, grid, pos, dirb, qx, r):
    n = pos.shape[0]
    g = testing.gather_counts(dev, grid, qx, r, nb=NB)
    b = testing.gather_bruteforce(dev, pos, dirb, n, qx, r, nb=NB)
    assert np.array_equal(g.count, b.count)
    assert np.array_equal(g.wsum, b.wsum)
    assert np.array_equal(g.band, b.band)
    assert np.all(g.ncand >= g.count)
    return g


def run_case(dev, bufs, rng, xyz, qx, r, lo, hi, h, method, max_cells=hg.DEFAULT_MAX_CELLS, hz=None):
    pos, dirb = photons(rng, np.asarray(xyz, np.float32))
    grid = hg.build(dev, pos, dirb, pos.shape[0], lo, hi, h, method=method,
                    max_cells=max_cells, buffers=bufs, hz=hz)
    check_grid(grid, pos, dirb)
    return check_gather(dev, grid, pos, dirb, np.asarray(qx, np.float32),
                        np.asarray(r, np.float32))


@pytest.mark.parametrize("method", METHODS)
def test_random_in_box(dev, bufs, method):
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 100, (20000, 3))
    qx = rng.uniform(0, 100, (2000, 3))
    r = rng.uniform(1, 12, 2000)
    g = run_case(dev, bufs, rng, xyz, qx, r, [0, 0, 0], [100, 100, 100], 4.0, method)
    assert g.count.sum() > 50000  # the test is not vacuous


@pytest.mark.parametrize("method", METHODS)
def test_flat_cells(dev, bufs, method):
    """Cells 0.7 um deep under 6 um wide (the beam's grid): the same photons as brute force,
    and fewer candidates than cubic cells for the same queries."""
    rng = np.random.default_rng(11)
    xyz = rng.uniform(0, 60, (20000, 3))
    qx = rng.uniform(0, 60, (2000, 3))
    r = rng.uniform(1, 8, 2000)
    g = run_case(dev, bufs, rng, xyz, qx, r, [0, 0, 0], [60, 60, 60], 6.0, method, hz=0.7)
    assert g.count.sum() > 20000
    c = run_case(dev, bufs, np.random.default_rng(11), xyz, qx, r, [0, 0, 0], [60, 60, 60], 6.0, method)
    assert g.ncand.sum() < 0.8 * c.ncand.sum()


@pytest.mark.parametrize("method", METHODS)
def test_partly_outside_box(dev, bufs, method):
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-60, 160, (20000, 3))
    qx = rng.uniform(-40, 140, (2000, 3))
    r = rng.uniform(2, 25, 2000)
    g = run_case(dev, bufs, rng, xyz, qx, r, [0, 0, 0], [100, 100, 100], 5.0, method)
    outside = np.any((qx < 0) | (qx > 100), axis=1)
    assert g.count[outside].sum() > 0


@pytest.mark.parametrize("method", METHODS)
def test_clustered(dev, bufs, method):
    rng = np.random.default_rng(3)
    centres = np.array([[10.5, 10.5, 10.5], [50.2, 50.7, 20.1], [90.0, 5.0, 95.0]])
    k = rng.integers(0, 3, 18000)
    xyz = np.concatenate([centres[k] + rng.normal(0, 0.8, (18000, 3)),
                          rng.uniform(0, 100, (2000, 3))])
    qx = np.concatenate([centres[rng.integers(0, 3, 1500)] + rng.normal(0, 4, (1500, 3)),
                         rng.uniform(0, 100, (500, 3))])
    r = rng.uniform(0.5, 6, 2000)
    g = run_case(dev, bufs, rng, xyz, qx, r, [0, 0, 0], [100, 100, 100], 4.0, method)
    assert g.count.max() > 1000


@pytest.mark.parametrize("method", METHODS)
def test_radii_much_larger_than_h(dev, bufs, method):
    rng = np.random.default_rng(4)
    xyz = rng.uniform(0, 100, (10000, 3))
    qx = rng.uniform(0, 100, (800, 3))
    r = rng.uniform(15, 60, 800)
    run_case(dev, bufs, rng, xyz, qx, r, [0, 0, 0], [100, 100, 100], 1.5, method)


@pytest.mark.parametrize("method", METHODS)
def test_lattice_boundaries(dev, bufs, method):
    """Photons on cell faces and distances equal to R (strict test excludes them)."""
    rng = np.random.default_rng(5)
    xyz = rng.integers(0, 41, (15000, 3)).astype(np.float64) * 2.5
    qx = rng.integers(0, 41, (2000, 3)).astype(np.float64) * 2.5
    r = rng.integers(1, 6, 2000) * 2.5
    run_case(dev, bufs, rng, xyz, qx, r, [0, 0, 0], [100, 100, 100], 2.5, method)


@pytest.mark.parametrize("method", METHODS)
def test_cell_cap(dev, bufs, method):
    rng = np.random.default_rng(6)
    xyz = rng.uniform(0, 100, (5000, 3))
    qx = rng.uniform(0, 100, (500, 3))
    r = rng.uniform(1, 10, 500)
    pos, dirb = photons(rng, xyz.astype(np.float32))
    grid = hg.build(dev, pos, dirb, 5000, [0, 0, 0], [100, 100, 100], 0.5,
                    method=method, max_cells=1000, buffers=bufs)
    assert grid.ncells <= 1000 and grid.h > 0.5
    check_grid(grid, pos, dirb)
    check_gather(dev, grid, pos, dirb, qx.astype(np.float32), r.astype(np.float32))


@pytest.mark.parametrize("method", METHODS)
def test_zero_photons(dev, bufs, method):
    rng = np.random.default_rng(7)
    qx = rng.uniform(0, 100, (100, 3))
    g = run_case(dev, bufs, rng, np.zeros((0, 3)), qx, np.full(100, 10.0),
                 [0, 0, 0], [100, 100, 100], 5.0, method)
    assert not g.count.any() and not g.wsum.any() and not g.band.any()


def test_buffer_reuse_across_passes(dev):
    """Same cache, bigger then smaller passes and a different grid shape."""
    rng = np.random.default_rng(8)
    cache = hg.GridBuffers(dev)
    for n, h, method in [(3000, 5.0, "counting"), (12000, 2.0, "radix"),
                         (500, 9.0, "counting"), (12000, 3.0, "counting")]:
        xyz = rng.uniform(0, 100, (n, 3))
        qx = rng.uniform(0, 100, (400, 3))
        r = rng.uniform(1, 15, 400)
        run_case(dev, cache, rng, xyz, qx, r, [0, 0, 0], [100, 100, 100], h, method)


def test_device_resident_inputs(dev, bufs):
    """Photon arrays already on the device (the renderer's case)."""
    import pyopencl.array as cla
    rng = np.random.default_rng(9)
    pos, dirb = photons(rng, rng.uniform(0, 50, (4000, 3)).astype(np.float32))
    pd = cla.to_device(dev.queue, pos.view(hg.cltypes.float4).ravel())
    dd = cla.to_device(dev.queue, dirb.view(hg.cltypes.float4).ravel())
    grid = hg.build(dev, pd, dd, 4000, [0, 0, 0], [50, 50, 50], 3.0, buffers=bufs)
    check_grid(grid, pos, dirb)
    check_gather(dev, grid, pos, dirb, rng.uniform(0, 50, (300, 3)).astype(np.float32),
                 rng.uniform(1, 8, 300).astype(np.float32))


def test_flat_cell_params():
    p = hg.grid_params([0, 0, 0], [100, 50, 10], 4.0, hz=0.5)
    assert (p["nx"], p["ny"], p["nz"]) == (25, 13, 20) and p["hz"] == np.float32(0.5)
    capped = hg.grid_params([0, 0, 0], [100, 100, 100], 1.0, max_cells=10000, hz=0.25)
    assert capped["ncells"] <= 10000
    assert capped["hz"] == pytest.approx(capped["h"] / 4, rel=1e-6)     # grown by one factor
    with pytest.raises(ValueError):
        hg.grid_params([0, 0, 0], [1, 1, 1], 1.0, hz=0.0)


def test_grid_params_and_cell_size():
    p = hg.grid_params([0, 0, 0], [100, 50, 10], 4.0)
    assert (p["nx"], p["ny"], p["nz"]) == (25, 13, 3) and p["ncells"] == 25 * 13 * 3
    assert p.dtype == structs.GRID_PARAMS_DTYPE and p.dtype.itemsize == 48
    capped = hg.grid_params([0, 0, 0], [100, 100, 100], 0.1, max_cells=10000)
    assert capped["ncells"] <= 10000 and capped["h"] > 4.0
    assert hg.choose_cell_size([2.0, 4.0, 6.0], [0, 0, 0], [100, 100, 100]) == pytest.approx(2.0)
    h = hg.choose_cell_size([2.0], [0, 0, 0], [100, 100, 100], max_cells=1000)
    assert h >= 10.0
    with pytest.raises(ValueError):
        hg.grid_params([0, 0, 0], [1, 1, 1], 0.0)


@pytest.mark.parametrize("method", METHODS)
def test_shell_on_cell_faces(dev, bufs, method):
    """Photons within a few ulps of the sphere, sphere extremes on cell faces:
    the float distance test alone must decide (the query range is padded)."""
    rng = np.random.default_rng(10)
    m, per = 1000, 24
    h = np.float32(2.0)
    r = rng.uniform(3, 9, m).astype(np.float32)
    # centres with x - R (and y + R, z - R) on a cell face, in float32
    faces = rng.integers(5, 45, (m, 3)).astype(np.float32) * h
    qx = np.stack([faces[:, 0] + r, faces[:, 1] - r, faces[:, 2] + r], axis=1).astype(np.float32)
    u = rng.normal(size=(m, per, 3))
    u[:, :6] = 0
    u[:, 0, 0], u[:, 1, 0], u[:, 2, 1], u[:, 3, 1], u[:, 4, 2], u[:, 5, 2] = -1, 1, -1, 1, -1, 1
    u[:, 6:9] = rng.choice([-1.0, 1.0], (m, 3, 3)) * np.array([1.0, 1e-4, 1e-4])
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    scale = 1.0 + rng.integers(-4, 5, (m, per, 1)) * 2.0 ** -23
    xyz = (qx[:, None, :].astype(np.float64) + u * (r[:, None, None] * scale)).reshape(-1, 3)
    g = run_case(dev, bufs, rng, xyz.astype(np.float32), qx, r,
                 [0, 0, 0], [100, 100, 100], float(h), method)
    assert g.count.sum() > 0
