"""The shared optics of kernels/common.h, run on the OpenCL device through kernels/testing.cl.

References: the Henyey-Greenstein phase function and its inverse-CDF sampling (Henyey &
Greenstein, ApJ 93 (1941) 70; Wang, Jacques & Zheng, "MCML", Comput. Methods Programs
Biomed. 47 (1995) 131, eqs. 3.28-3.29 for the sampling; the direction update uses the basis
of Duff et al., JCGT 6(1) 2017); the
unpolarised Fresnel reflectance (Born & Wolf, Principles of Optics, sec. 1.5; MCML eq. 3.35).
Everything below compares float32 device results with float64 closed forms.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

cl = pytest.importorskip("pyopencl")
from scipy import integrate, stats  # noqa: E402

from clppm.compute.device import global_size  # noqa: E402

N_HG = 200_000
SEED = 12345


class Kernels:
    """The kernels of testing.cl, each retrieved once (pyopencl warns on repeated retrieval)."""

    def __init__(self, program):
        self._prg, self._k = program, {}

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        if name not in self._k:
            self._k[name] = cl.Kernel(self._prg, name)
        return self._k[name]


@pytest.fixture(scope="module")
def prg(dev):
    return Kernels(dev.build("testing.cl", {"NB": 1, "NL": 1}))


def _buf(dev, a):
    return cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                     hostbuf=np.ascontiguousarray(a))


def _out(dev, shape, dtype=np.float32):
    a = np.zeros(shape, dtype)
    return a, cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE, a.nbytes)


def _get(dev, host, buf):
    cl.enqueue_copy(dev.queue, host, buf)
    dev.queue.finish()
    return host


def hg_sample(dev, prg, g, n=N_HG, seed=SEED):
    out, ob = _out(dev, n)
    prg.t_hg_sample(dev.queue, (global_size(n),), None, np.float32(g), np.uint32(seed),
                    np.uint32(n), ob)
    return _get(dev, out, ob).astype(np.float64)


def rotate(dev, prg, d, ct, phi):
    d = np.asarray(d, np.float64)
    n = len(d)
    d4 = np.zeros((n, 4), np.float32)
    d4[:, :3] = d
    out, ob = _out(dev, (n, 4))
    prg.t_rotate(dev.queue, (global_size(n),), None, np.uint32(n), _buf(dev, d4),
                 _buf(dev, np.asarray(ct, np.float32)), _buf(dev, np.asarray(phi, np.float32)), ob)
    return _get(dev, out, ob)[:, :3].astype(np.float64)


def scatter(dev, prg, g, d, seed=SEED):
    d = np.asarray(d, np.float64)
    n = len(d)
    d4 = np.zeros((n, 4), np.float32)
    d4[:, :3] = d
    out, ob = _out(dev, (n, 4))
    prg.t_scatter(dev.queue, (global_size(n),), None, np.float32(g), np.uint32(seed),
                  np.uint32(n), _buf(dev, d4), ob)
    o = _get(dev, out, ob).astype(np.float64)
    return o[:, :3], o[:, 3]


def hg_eval(dev, prg, g, mu):
    mu = np.asarray(mu, np.float32)
    out, ob = _out(dev, len(mu))
    prg.t_hg_eval(dev.queue, (global_size(len(mu)),), None, np.float32(g), np.uint32(len(mu)),
                  _buf(dev, mu), ob)
    return _get(dev, out, ob).astype(np.float64)


def fresnel(dev, prg, n1, n2, cos_i):
    ci = np.asarray(cos_i, np.float32)
    n = len(ci)
    R, rb = _out(dev, n)
    ct, cb = _out(dev, n)
    prg.t_fresnel(dev.queue, (global_size(n),), None, np.float32(n1), np.float32(n2),
                  np.uint32(n), _buf(dev, ci), rb, cb)
    return _get(dev, R, rb).astype(np.float64), _get(dev, ct, cb).astype(np.float64)


# ----------------------------------------------------------------------- closed forms (float64)
def hg_pdf(g, mu):
    """Density of the scattering cosine mu (integrates to 1 over [-1, 1])."""
    return 0.5 * (1 - g * g) / (1 + g * g - 2 * g * mu) ** 1.5


def hg_cdf(g, mu):
    mu = np.asarray(mu, np.float64)
    if g == 0:
        return (mu + 1) / 2
    return (1 - g * g) / (2 * g) * (1 / np.sqrt(1 + g * g - 2 * g * mu) - 1 / (1 + g))


def hg_quantile(g, p):
    p = np.asarray(p, np.float64)
    if g == 0:
        return 2 * p - 1
    s = 2 * g * p / (1 - g * g) + 1 / (1 + g)
    return (1 + g * g - s ** -2) / (2 * g)


def fresnel_exact(n1, n2, ci):
    ci = np.asarray(ci, np.float64)
    s2 = (n1 / n2) ** 2 * (1 - ci * ci)
    tir = s2 >= 1
    ct = np.sqrt(np.clip(1 - s2, 0, None))
    rs = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)
    rp = (n1 * ct - n2 * ci) / (n1 * ct + n2 * ci)
    R = np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp))
    return R, np.where(tir, 0.0, ct)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_dirs(n, seed):
    return unit(np.random.default_rng(seed).normal(size=(n, 3)))


# ----------------------------------------------------------------------- Henyey-Greenstein
@pytest.mark.parametrize("g", [0.0, 0.75, 0.9, -0.5, 0.3])
def test_hg_sampling_chisquare(dev, prg, g):
    """HG sampling (MCML eq. 3.28) vs the analytic HG cosine CDF: chi-square, 50 equal bins."""
    mu = hg_sample(dev, prg, g)
    assert np.all(np.isfinite(mu)) and mu.min() >= -1 and mu.max() <= 1
    nbins = 50
    edges = hg_quantile(g, np.linspace(0, 1, nbins + 1))
    edges[0], edges[-1] = -1.0, 1.0
    counts, _ = np.histogram(mu, edges)
    expected = np.diff(hg_cdf(g, edges)) * len(mu)
    expected *= counts.sum() / expected.sum()
    chi2, p = stats.chisquare(counts, expected)
    assert p > 1e-3, f"g={g}: chi2={chi2:.1f} over {nbins} bins, p={p:.2e}"


@pytest.mark.parametrize("g", [0.0, 0.75, 0.9, -0.5, 0.99, -0.9])
def test_hg_mean_cosine(dev, prg, g):
    """<cos theta> of HG is g (Henyey & Greenstein 1941): sample mean within 4 standard errors."""
    mu = hg_sample(dev, prg, g, seed=SEED + 1)
    se = mu.std(ddof=1) / math.sqrt(len(mu))
    assert abs(mu.mean() - g) < 4 * se + 1e-6, f"g={g}: mean {mu.mean():.6f} ± {se:.6f}"


@pytest.mark.parametrize("g", [0.0, 1e-5, 0.5, 0.9, 0.99, -0.7])
def test_hg_sample_ends(dev, prg, g):
    """hg_sample_cos at the ends of the uniform's range (0, 1] stays finite in [-1, 1], monotone."""
    u = np.array([2.0 ** -24, 1e-6, 1e-3, 0.25, 0.5, 0.75, 1 - 1e-6, 1.0], np.float32)
    out, ob = _out(dev, len(u))
    prg.t_hg_sample_u(dev.queue, (global_size(len(u)),), None, np.float32(g), _buf(dev, u),
                      np.uint32(len(u)), ob)
    c = _get(dev, out, ob).astype(np.float64)
    assert np.all(np.isfinite(c)) and np.all(c >= -1) and np.all(c <= 1)
    assert np.all(np.diff(c) >= -1e-6)
    assert c[-1] == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(c[3:6], hg_quantile(g, u[3:6].astype(np.float64)), atol=2e-5)


@pytest.mark.parametrize("g", [0.0, 0.5, 0.9, -0.7])
def test_hg_eval_normalised(dev, prg, g):
    """hg_eval is the HG phase function per steradian: 2 pi int_{-1}^{1} p dmu = 1."""
    mu = np.linspace(-1.0, 1.0, 400_001)
    p = hg_eval(dev, prg, g, mu)
    np.testing.assert_allclose(p, hg_pdf(g, mu) / (2 * math.pi), rtol=2e-5)
    total = 2 * math.pi * integrate.simpson(p, x=mu)
    assert total == pytest.approx(1.0, abs=1e-4)


# ----------------------------------------------------------------------- rotate_dir
def _rotate_cases():
    dirs = [unit(v) for v in ([0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [1, 1, 1],
                              [0.3, -0.2, -0.9], [-0.6, 0.0, 0.8])]
    return np.array(dirs)


def test_rotate_dir_unit_and_cosine(dev, prg):
    """rotate_dir (Duff et al. 2017 basis) keeps |d| = 1 and dot(d_in, d_out) = the polar cosine it was
    given, for every azimuth, including incoming directions exactly +z and -z (a past bug:
    the pole branch dropped the sign of d.z, so -z scattered as if it came from +z)."""
    base = _rotate_cases()
    cts = np.array([-1.0, -0.9, -0.5, 0.0, 0.3, 0.75, 0.99, 1.0])
    phis = np.linspace(0, 2 * math.pi, 13)[:-1]
    D, C, F = np.meshgrid(np.arange(len(base)), cts, phis, indexing="ij")
    d_in = base[D.ravel()]
    o = rotate(dev, prg, d_in, C.ravel(), F.ravel())
    np.testing.assert_allclose(np.linalg.norm(o, axis=1), 1.0, atol=2e-6)
    np.testing.assert_allclose(np.einsum("ij,ij->i", o, d_in), C.ravel(), atol=2e-5)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_rotate_dir_poles_exact(dev, prg, sign):
    """At d = (0, 0, ±1) the new direction's z is exactly ±ct (MCML: uz' = SIGN(uz) cos theta)."""
    ct = np.linspace(-1, 1, 41)
    phi = np.linspace(0, 2 * math.pi, 41)
    d = np.tile([0.0, 0.0, sign], (len(ct), 1))
    o = rotate(dev, prg, d, ct, phi)
    np.testing.assert_allclose(o[:, 2], sign * ct.astype(np.float32), atol=1e-6)
    st = np.sqrt(1 - ct ** 2)
    np.testing.assert_allclose(np.hypot(o[:, 0], o[:, 1]), st, atol=1e-5)


def test_rotate_dir_azimuth_isometry(dev, prg):
    """The azimuth is a rotation about d: two outputs with the same ct and azimuths phi1, phi2
    satisfy dot(o1, o2) = ct^2 + st^2 cos(phi1 - phi2) (so azimuths are not distorted), poles too."""
    base = np.concatenate([_rotate_cases(), random_dirs(20, 3)])
    rng = np.random.default_rng(4)
    n = len(base) * 16
    d_in = np.repeat(base, 16, axis=0)
    ct = rng.uniform(-1, 1, n)
    p1 = rng.uniform(0, 2 * math.pi, n)
    p2 = rng.uniform(0, 2 * math.pi, n)
    o1 = rotate(dev, prg, d_in, ct, p1)
    o2 = rotate(dev, prg, d_in, ct, p2)
    ct32 = ct.astype(np.float32).astype(np.float64)
    want = ct32 ** 2 + (1 - ct32 ** 2) * np.cos(p1.astype(np.float32) - p2.astype(np.float32))
    np.testing.assert_allclose(np.einsum("ij,ij->i", o1, o2), want, atol=3e-5)


def test_rotate_dir_near_poles(dev, prg):
    """Directions close to but not on the poles: unit length, cosine kept.  MCML's formula
    needed a pole branch that ignored d's tilt (up to ~4.5e-3 rad); the Duff et al. basis has
    no singularity, so the cosine is kept to float precision right up to the poles."""
    rng = np.random.default_rng(5)
    n = 4000
    zs = np.concatenate([1 - 10.0 ** rng.uniform(-7, -3, n // 2), -(1 - 10.0 ** rng.uniform(-7, -3, n // 2))])
    a = rng.uniform(0, 2 * math.pi, n)
    r = np.sqrt(1 - zs ** 2)
    d = np.stack([r * np.cos(a), r * np.sin(a), zs], 1)
    d32 = unit(d.astype(np.float32).astype(np.float64))
    ct = rng.uniform(-1, 1, n)
    o = rotate(dev, prg, d, ct, rng.uniform(0, 2 * math.pi, n))
    np.testing.assert_allclose(np.linalg.norm(o, axis=1), 1.0, atol=2e-6)
    err = np.abs(np.einsum("ij,ij->i", o, d32) - ct)
    assert err.max() < 2e-6, float(err.max())
    # and the sign of d.z always survives: the photon keeps going the way it was told
    fwd = ct > 0.5
    assert np.all(np.sign(o[fwd, 2]) == np.sign(d[fwd, 2]))


@pytest.mark.parametrize("dz", [1.0, -1.0])
def test_scatter_from_poles_distribution(dev, prg, dz):
    """A full device scattering event (HG cosine + uniform azimuth + rotate_dir) from d = ±z:
    the cosine to the incoming direction is HG (chi-square) and the azimuth is uniform."""
    g = 0.75
    n = N_HG
    o, ct = scatter(dev, prg, g, np.tile([0.0, 0.0, dz], (n, 1)))
    cos_rel = o[:, 2] * dz
    np.testing.assert_allclose(cos_rel, ct, atol=2e-6)
    edges = hg_quantile(g, np.linspace(0, 1, 41))
    edges[0], edges[-1] = -1.0, 1.0
    counts, _ = np.histogram(cos_rel, edges)
    exp = np.diff(hg_cdf(g, edges)) * n
    assert stats.chisquare(counts, exp * counts.sum() / exp.sum()).pvalue > 1e-3
    phi = np.arctan2(o[:, 1], o[:, 0])
    counts, _ = np.histogram(phi, np.linspace(-math.pi, math.pi, 37))
    assert stats.chisquare(counts).pvalue > 1e-3
    assert abs(cos_rel.mean() - g) < 4 * cos_rel.std() / math.sqrt(n)


def test_scatter_general_direction(dev, prg):
    """From random incoming directions the mean cosine to the incoming direction is g."""
    g = 0.9
    d = random_dirs(N_HG, 6)
    o, ct = scatter(dev, prg, g, d)
    rel = np.einsum("ij,ij->i", o, unit(d.astype(np.float32).astype(np.float64)))
    np.testing.assert_allclose(rel, ct, atol=2e-6)
    assert np.median(np.abs(rel - ct)) < 2e-7
    assert abs(rel.mean() - g) < 4 * rel.std() / math.sqrt(len(rel))


def test_rng_uniform(dev, prg):
    """The device Philox uniforms lie in (0, 1], are uniform (chi-square) and differ by seed."""
    n, m = 50_000, 4
    out, ob = _out(dev, n * m)
    prg.t_u01(dev.queue, (global_size(n),), None, np.uint32(1), np.uint32(n), np.uint32(m), ob)
    u = _get(dev, out, ob).copy()
    assert u.min() > 0 and u.max() <= 1
    counts, _ = np.histogram(u, np.linspace(0, 1, 65))
    assert stats.chisquare(counts).pvalue > 1e-3
    prg.t_u01(dev.queue, (global_size(n),), None, np.uint32(2), np.uint32(n), np.uint32(m), ob)
    u2 = _get(dev, out, ob).copy()
    assert np.mean(u == u2) < 1e-3
    assert abs(np.corrcoef(u.reshape(n, m)[:, 0], u.reshape(n, m)[:, 1])[0, 1]) < 4 / math.sqrt(n)


# ----------------------------------------------------------------------- hot-path arithmetic
def test_fast_log_azimuth_hg(dev, prg):
    """common.h's library-free -ln(u), (cos, sin)(2 pi u) and one-division HG against float64
    closed forms, over the whole range the RNG gives (2^-24 .. 1) and at the quadrant seams."""
    rng = np.random.default_rng(11)
    u = np.concatenate([(np.arange(1, 2 ** 12) * 2.0 ** -24), rng.uniform(0, 1, 200_000),
                        np.arange(0, 4097) / 4096.0, [1 - 2.0 ** -24, 1.0, 0.0]])
    u32 = np.clip(u, 0, 1).astype(np.float32)
    n = len(u32)
    g = np.float32(0.78)
    nl, nlb = _out(dev, n)
    cs, csb = _out(dev, (n, 2))
    hg, hgb = _out(dev, n)
    prg.t_fastmath(dev.queue, (global_size(n),), None, g, np.uint32(n), _buf(dev, u32), nlb, csb, hgb)
    nl, cs, hg = _get(dev, nl, nlb), _get(dev, cs, csb), _get(dev, hg, hgb)
    ud = u32.astype(np.float64)
    pos = ud > 0
    want = -np.log(ud[pos])
    assert np.max(np.abs(nl[pos] - want) / np.maximum(want, 1e-7)) < 4e-7
    assert np.max(np.abs(nl[pos] - want)) < 2e-6
    np.testing.assert_allclose(cs[:, 0], np.cos(2 * math.pi * ud), atol=4e-7)
    np.testing.assert_allclose(cs[:, 1], np.sin(2 * math.pi * ud), atol=4e-7)
    np.testing.assert_allclose(hg, hg_quantile(float(g), ud), atol=3e-5)


def test_exp_neg(dev, prg):
    """common.h's library-free exp(-x) against float64 over the optical depths the beam gather
    meets (0 .. 90, dense near 0 and at every power-of-two seam), and 0 beyond exp(-87)."""
    x = np.concatenate([np.linspace(0, 90, 200_001), 2.0 ** np.arange(-24, 7),
                        np.log(2) * np.arange(0, 126) + np.float32(1e-7), [0.0, 1e30, np.inf]])
    x32 = x.astype(np.float32)
    n = len(x32)
    out, ob = _out(dev, n)
    prg.t_exp_neg(dev.queue, (global_size(n),), None, np.uint32(n), _buf(dev, x32), ob)
    out = _get(dev, out, ob)
    want = np.exp(-x32.astype(np.float64))
    ok = want > 1.2e-38
    # float32 y = x log2(e) carries a relative error of 2^-24 y: ~6e-8 x in the result
    rel = np.abs(out[ok] / want[ok] - 1)
    assert np.all(rel < 3e-7 + 8e-8 * x32[ok]), float(np.max(rel / (3e-7 + 8e-8 * x32[ok])))
    assert np.all(out[x32 > 88] == 0.0) and np.all(out >= 0)


# ----------------------------------------------------------------------- Fresnel
@pytest.mark.parametrize("n1,n2", [(1.0, 1.4), (1.4, 1.0), (1.0, 1.5), (1.5, 1.34), (1.34, 1.4)])
def test_fresnel_vs_analytic(dev, prg, n1, n2):
    """fresnel_R vs the unpolarised Fresnel formula 0.5 (rs^2 + rp^2) (Born & Wolf 1.5; MCML
    eq. 3.35) over incidence angles 0..90 deg, and Snell's law for the transmitted cosine."""
    theta = np.radians(np.linspace(0, 89.9, 900))
    ci = np.cos(theta).astype(np.float32).astype(np.float64)
    R, ct = fresnel(dev, prg, n1, n2, ci)
    Rx, ctx = fresnel_exact(n1, n2, ci)
    crit = math.asin(n2 / n1) if n1 > n2 else None
    ok = np.ones_like(ci, bool) if crit is None else np.abs(theta - crit) > 2e-3
    np.testing.assert_allclose(R[ok], Rx[ok], atol=2e-5)
    np.testing.assert_allclose(ct[ok], ctx[ok], atol=2e-5)
    assert np.all((R >= 0) & (R <= 1))
    # normal incidence: ((n1 - n2) / (n1 + n2))^2
    R0, ct0 = fresnel(dev, prg, n1, n2, [1.0])
    assert R0[0] == pytest.approx(((n1 - n2) / (n1 + n2)) ** 2, rel=1e-5, abs=1e-8)
    assert ct0[0] == pytest.approx(1.0, abs=1e-7)
    # the sign of the cosine does not matter (the kernel takes |cos_i|)
    Rn, _ = fresnel(dev, prg, n1, n2, -ci)
    np.testing.assert_array_equal(Rn, R)


def test_fresnel_total_internal_reflection(dev, prg):
    """From n = 1.4 into air: R = 1 exactly (and cos_t = 0) past the critical angle
    asin(1/1.4) = 45.58 deg, R < 1 before it."""
    crit = math.asin(1.0 / 1.4)
    past = np.radians(np.linspace(math.degrees(crit) + 0.01, 90.0, 500))
    R, ct = fresnel(dev, prg, 1.4, 1.0, np.cos(past))
    assert np.all(R == 1.0) and np.all(ct == 0.0)
    before = np.radians(np.linspace(0, math.degrees(crit) - 0.01, 500))
    R, ct = fresnel(dev, prg, 1.4, 1.0, np.cos(before))
    assert np.all(R < 1.0) and np.all(ct > 0.0)
    # into a denser medium there is never total reflection, even at grazing incidence
    R, _ = fresnel(dev, prg, 1.0, 1.4, np.cos(np.radians([89.0, 89.99])))
    assert np.all(R < 1.0)
    assert fresnel(dev, prg, 1.0, 1.4, [0.0])[0][0] == pytest.approx(1.0)


@pytest.mark.parametrize("n", [1.0, 1.33, 1.4])
def test_fresnel_matched(dev, prg, n):
    """n1 == n2: no interface, R = 0 exactly and the direction is unchanged (cos_t = cos_i)."""
    ci = np.linspace(0, 1, 101).astype(np.float32)
    R, ct = fresnel(dev, prg, n, n, ci)
    assert np.all(R == 0.0)
    np.testing.assert_array_equal(ct.astype(np.float32), ci)


def _special(dtype):
    """Edge values (signed zeros, infinities, NaN, subnormals, halves for floor) and a spread of
    ordinary ones, as the arguments a, b, c of t_scalar_math."""
    f = np.finfo(dtype)
    edge = np.array([0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 1.5, -2.5, 2.0, 1e-3, f.tiny, -f.tiny, f.tiny / 4,
                     f.max, -f.max, np.inf, -np.inf, np.nan, 3.0e9, -3.0e9], dtype)
    rng = np.random.default_rng(7)
    spread = (rng.standard_normal(4000) * 10.0 ** rng.integers(-6, 8, 4000)).astype(dtype)
    vals = np.concatenate([edge, spread])
    a, b = (v.ravel() for v in np.meshgrid(edge, edge))          # every pair of edge values
    n = len(vals)
    a = np.concatenate([a, vals, np.roll(vals, 1)]).astype(dtype)
    b = np.concatenate([b, np.roll(vals, 7), vals]).astype(dtype)
    return a, b, np.roll(b, 3) + np.asarray(n, dtype)


def test_scalar_math_forms_equal_builtins(dev, prg):
    """volume.h's fmax1, fmin1, sqrt1, floor1 and clamp1 (on PoCL clang's builtins inline,
    INLINE_MATH; elsewhere the OpenCL builtins) give the builtins' very bits on every input:
    the switch must not move a render's bytes.  (Caught on PoCL: fmax1 as a > b ? a : b, by a NaN
    b; as __builtin_fmaxf, by fmax(-0, +0).)"""
    with np.errstate(invalid="ignore", over="ignore"):
        a, b, c = _special(np.float32)
    n = len(a)
    out, ob = _out(dev, n * 10, np.uint32)
    iout, ib = _out(dev, n * 2, np.int32)
    prg.t_scalar_math(dev.queue, (global_size(n),), None, np.uint32(n), _buf(dev, a), _buf(dev, b),
                      _buf(dev, c), ob, ib)
    pairs = _get(dev, out, ob).reshape(n, 5, 2)
    nan = np.isnan(pairs.view(np.float32))
    for k, name in enumerate(("fmax", "fmin", "sqrt", "floor", "clamp")):
        same = (pairs[:, k, 0] == pairs[:, k, 1]) | (nan[:, k, 0] & nan[:, k, 1])
        assert same.all(), (name, a[~same][:4], b[~same][:4])
    ints = _get(dev, iout, ib).reshape(n, 2)
    assert (ints[:, 0] == ints[:, 1]).all()
    if "cl_khr_fp64" not in dev.device.extensions:
        return
    with np.errstate(invalid="ignore", over="ignore"):
        a, b, _ = _special(np.float64)
    out, ob = _out(dev, len(a) * 8, np.uint64)
    prg.t_scalar_math_d(dev.queue, (global_size(len(a)),), None, np.uint32(len(a)), _buf(dev, a), _buf(dev, b), ob)
    pairs = _get(dev, out, ob).reshape(len(a), 4, 2)
    nan = np.isnan(pairs.view(np.float64))
    same = (pairs[..., 0] == pairs[..., 1]) | (nan[..., 0] & nan[..., 1])
    assert same.all()
