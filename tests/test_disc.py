"""The beam estimator's boundary kernel near the model's open sides (kernels/disc.h).

Checked against a brute-force integration on a fine grid of the unit disc less the cut-off
half-planes: the kernel integrates to 1, has zero first moments (so a density linear across
the disc, cut or not, is estimated exactly), its area is the region's, and a whole disc gives
the plain 1/pi."""
import numpy as np
import pytest

cl = pytest.importorskip("pyopencl")

CASES = [(1.0, 1.0), (2.0, 5.0), (0.0, 1.0), (1.0, 0.0), (0.5, 1.0), (0.9, 3.0), (0.0, 0.0),
         (0.3, 0.4), (0.7, 0.2), (0.05, 0.95), (0.999, 0.999), (0.6, 0.8)]


@pytest.fixture(scope="module")
def kernel_values(dev):
    prg = dev.build("testing.cl", {"NB": 1, "NL": 1})
    e = np.asarray(CASES, np.float32)
    out = np.zeros((len(CASES), 4), np.float32)
    mf = cl.mem_flags
    eb = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=e)
    ob = cl.Buffer(dev.ctx, mf.WRITE_ONLY, out.nbytes)
    cl.Kernel(prg, "t_disc_kernel")(dev.queue, (len(CASES),), None, np.uint32(len(CASES)), eb, ob)
    cl.enqueue_copy(dev.queue, out, ob)
    dev.queue.finish()
    return out


def _grid(ex, ey, n=2000):
    """Cell centres of a fine grid over the region (unit disc, x > -ex, y > -ey), cell area."""
    h = 2.0 / n
    c = -1.0 + h * (np.arange(n) + 0.5)
    x, y = np.meshgrid(c, c, indexing="ij")
    m = (x * x + y * y < 1.0) & (x > -ex) & (y > -ey)
    return x[m], y[m], h * h


@pytest.mark.parametrize("i", range(len(CASES)))
def test_boundary_kernel_moments(kernel_values, i):
    ex, ey = CASES[i]
    a, bx, by, m0 = (float(v) for v in kernel_values[i])
    x, y, dA = _grid(ex, ey)
    area = x.size * dA
    assert m0 == pytest.approx(area, rel=2e-3)
    k = a + bx * x + by * y
    assert (k * dA).sum() == pytest.approx(1.0, abs=2e-3)          # normalised
    assert abs((k * x * dA).sum()) < 2e-3                          # first moments vanish
    assert abs((k * y * dA).sum()) < 2e-3
    # a linear density is estimated exactly at the centre: 3 + 2x - 5y -> 3
    assert ((3 + 2 * x - 5 * y) * k * dA).sum() == pytest.approx(3.0, abs=2e-2)
    if ex >= 1 and ey >= 1:
        assert (a, bx, by) == pytest.approx((1 / np.pi, 0.0, 0.0), abs=1e-6)
        assert m0 == pytest.approx(np.pi, rel=1e-6)
    else:
        # the weight grows towards the cut sides (the inside part's centroid is inward)
        assert bx <= 1e-6 and by <= 1e-6
        assert bx < -1e-3 or by < -1e-3 or min(ex, ey) > 0.9


def test_half_disc_closed_form(kernel_values):
    """Cut through the centre by one side: m0 = pi/2, m1 = 2/3, m2 = pi/8 (closed form)."""
    a, bx, by, m0 = (float(v) for v in kernel_values[CASES.index((0.0, 1.0))])
    m0_, m1, m2 = np.pi / 2, 2 / 3, np.pi / 8
    det = m0_ * m2 - m1 * m1
    assert m0 == pytest.approx(m0_, rel=1e-5)
    assert a == pytest.approx(m2 / det, rel=1e-4)
    assert bx == pytest.approx(-m1 / det, rel=1e-4)
    assert by == pytest.approx(0.0, abs=1e-5)
