"""The beam estimator's disc near the model's open sides (kernels/disc.h).

Where a disc reaches past a side, only its part symmetric about the centre counts (the disc
within |x| < ex, |y| < ey, in units of R).  Checked here: the window's area (quarter_area, on the
device) against a fine-grid integration and closed forms, and that the window lies inside the
model and estimates a density linear across it exactly, while the plain cut disc does not."""
import math

import numpy as np
import pytest

cl = pytest.importorskip("pyopencl")

CASES = [(1.0, 1.0), (2.0, 5.0), (0.0, 1.0), (1.0, 0.0), (0.5, 1.0), (0.9, 3.0), (0.0, 0.0),
         (0.3, 0.4), (0.7, 0.2), (0.05, 0.95), (0.999, 0.999), (0.6, 0.8), (0.001, 0.5)]


@pytest.fixture(scope="module")
def quarter(dev):
    prg = dev.build("testing.cl", {"NB": 1, "NL": 1})
    e = np.asarray(CASES, np.float32)
    out = np.zeros(len(CASES), np.float32)
    mf = cl.mem_flags
    eb = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=e)
    ob = cl.Buffer(dev.ctx, mf.WRITE_ONLY, out.nbytes)
    cl.Kernel(prg, "t_quarter_area")(dev.queue, (len(CASES),), None, np.uint32(len(CASES)), eb, ob)
    cl.enqueue_copy(dev.queue, out, ob)
    dev.queue.finish()
    return out


def _grid(ex, ey, n=4000):
    """Cell centres of a fine grid over the window within the unit disc, cell area."""
    h = 2.0 / n
    c = -1.0 + h * (np.arange(n) + 0.5)
    x, y = np.meshgrid(c, c, indexing="ij")
    m = (x * x + y * y < 1.0) & (np.abs(x) < ex) & (np.abs(y) < ey)
    return x[m], y[m], h * h


@pytest.mark.parametrize("i", range(len(CASES)))
def test_window_area(quarter, i):
    ex, ey = CASES[i]
    x, _, dA = _grid(ex, ey)
    assert 4 * float(quarter[i]) == pytest.approx(x.size * dA, abs=2e-3)


def test_window_area_closed_forms(quarter):
    q = dict(zip(CASES, (float(v) for v in quarter)))
    assert 4 * q[(1.0, 1.0)] == pytest.approx(math.pi, rel=1e-6)           # whole disc
    assert 4 * q[(2.0, 5.0)] == pytest.approx(math.pi, rel=1e-6)
    assert q[(0.0, 1.0)] == 0 and q[(0.0, 0.0)] == 0
    band = 2 * (0.5 * math.sqrt(0.75) + math.asin(0.5))                      # |x| < 1/2
    assert 4 * q[(0.5, 1.0)] == pytest.approx(band, rel=1e-5)


@pytest.mark.parametrize("ex,ey", [(0.3, 5.0), (0.3, 0.6), (0.05, 0.2)])
def test_window_estimates_a_linear_density_at_its_centre(ex, ey):
    """Photons of a density 1 + 3x + 2y (the side at x = -ex, y = -ey: none beyond), the centre
    at 0: the window's estimate is the centre's density, the cut disc's is first-order high."""
    x, y, dA = _grid(5.0, 5.0)                      # the whole unit disc
    inside = (x > -ex) & (y > -ey)
    s = 1 + 3 * x + 2 * y
    win = (np.abs(x) < ex) & (np.abs(y) < ey)
    assert np.all(inside[win])                      # the window lies inside the model
    est = (s[win] * dA).sum() / (win.sum() * dA)
    assert est == pytest.approx(1.0, abs=2e-3)
    cut = (s[inside] * dA).sum() / (inside.sum() * dA)
    assert cut > 1.1


def _header_constant(name):
    import os
    import re
    from clppm.compute.device import kernel_dir
    with open(os.path.join(kernel_dir(), "disc.h")) as f:
        return float(re.search(rf"#define {name} ([0-9.]+)f", f.read()).group(1))


@pytest.fixture(scope="module")
def windows(dev):
    """window_at on the device over side distances d in [0, 5R] (x) and a far or equal y side."""
    R = 300.0
    d = np.linspace(0.0, 5 * R, 1001, dtype=np.float32)
    s = np.stack([np.concatenate([d, d]), np.concatenate([np.full_like(d, 1e4), d])], 1).astype(np.float32)
    prg = dev.build("testing.cl", {"NB": 1, "NL": 1})
    out = np.zeros((len(s), 4), np.float32)
    mf = cl.mem_flags
    sb = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=s)
    ob = cl.Buffer(dev.ctx, mf.WRITE_ONLY, out.nbytes)
    cl.Kernel(prg, "t_window_at")(dev.queue, (len(s),), None, np.uint32(len(s)), sb, np.float32(R), ob)
    cl.enqueue_copy(dev.queue, out, ob)
    dev.queue.finish()
    n = len(d)
    return R, d, out[:n], out[n:]


def test_window_across_one_side(windows):
    """Along one side: narrowed across it to u + 2u^2/R with u = kappa d (floor, never past the
    side), full R along it; the whole disc from d = R / (2 kappa) on, and nowhere nearer."""
    R, d, w, _ = windows
    kappa, floor = _header_constant("DISC_KAPPA"), _header_constant("DISC_FLOOR")
    u = kappa * d
    want = np.clip(np.minimum(np.maximum(u + 2 * u * u / R, floor * R), d), 1e-3 * R, R)
    assert np.allclose(w[:, 0], want, rtol=1e-5, atol=1e-3)
    assert np.all(w[:, 0] <= np.maximum(d, 1e-3 * R) * (1 + 1e-6))      # never past the side
    assert np.all(w[:, 1] == R)                                          # the side's direction: whole
    assert np.all(np.diff(w[:, 0]) >= 0)                                 # grows with the distance
    near = (d > floor * R / kappa * 1.01) & (d < R)                   # above the floor, within R
    assert near.sum() > 50
    ratio = w[near, 0] / d[near]                                         # about kappa d near the side
    assert np.all(ratio >= kappa * (1 - 1e-5)) and np.all(ratio <= 1.25 * kappa * (1 + 1e-5))
    far = d >= R / (2 * kappa) * (1 + 1e-6)
    assert far.sum() > 100 and (~far).sum() > 100
    assert np.all(w[far, 3] == 0) and np.allclose(w[far, 2], math.pi * R * R, rtol=1e-6)
    assert np.all(w[~far & (d < R / (2 * kappa) * (1 - 1e-3)), 3] == 1)


def test_window_area_is_the_disc_within_it(windows):
    """The area of the window as returned equals a grid integration of the disc within it, and
    along one side it exceeds the isotropic disc of radius hx (less noise for the same bias
    across the side: the density changes across a side, not along it)."""
    R, d, w, wc = windows
    for k in (0, 30, 100, 250, 400):
        for ww in (w[k], wc[k]):
            x, _, dA = _grid(ww[0] / R, ww[1] / R, n=2000)
            assert ww[2] == pytest.approx(x.size * dA * R * R, rel=5e-3, abs=2e-3 * R * R)
    assert np.all(w[:, 2] >= math.pi * w[:, 0] ** 2 * (1 - 1e-6))
    narrow = w[:, 0] <= R / 2
    assert np.all(w[narrow, 2] > 2.4 * math.pi * w[narrow, 0] ** 2)
