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
