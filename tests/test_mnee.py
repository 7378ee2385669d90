"""Manifold next-event estimation through the relief (kernels/mnee.h, kernels/pt.cl).

References: Snell's law and the surfaces themselves (a separate float64 evaluation of the
Catmull-Rom height fields written here in Hermite form), a finite-difference Jacobian of a
separate vectorised ray tracer written here (the geometry term), the flat connection as the
amplitude goes to 0, a small spherical light hit by brute-force ray shooting (r -> 0), the flat
path tracer's image, and byte equality (determinism, resume).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from clppm.output import checkpoint as ckpt
from clppm import config
from clppm.integrators import pathtracer as pt
from clppm.run import entry
from clppm.checks import testing
from clppm.scene import volume


def lay(name, t, n, mua=10.0, mus=90.0, g=0.75, bottom="flat"):
    return {"name": name, "thickness_um": t, "n": n, "mua": mua, "mus": mus, "g": g,
            "scattering": "none", "bottom": bottom}


def scene(layers, *, relief=None, papillae=0.0, period=100.0, quantize=False, size=0.5,
          light=(0.3, 0.2, 2.0), res=(8, 8), spp=16, passes=2, seed=1, fov=0.6, lateral="open"):
    raw = {"model": {"name": "relief", "size_mm": [size, size], "lateral": lateral,
                     "quantize": quantize, "voxel_um": 5.0, "lateral_voxel_um": 5.0},
           "spectrum": {"start_nm": 500.0, "stop_nm": 500.0, "step_nm": 5.0},
           "relief": relief or {"kind": "flat"},
           "papillae": {"amplitude_um": papillae, "period_um": period},
           "light": {"kind": "point", "position_mm": list(light), "spectrum": "flat"},
           "camera": {"position_mm": [size / 2, size / 2, 40.0], "look_at_mm": [size / 2, size / 2, 0.0],
                      "fov_deg": fov, "resolution": list(res)},
           "render": {"passes": passes, "pt_samples_per_pass": spp, "specular": False,
                      "checkpoint_every": 0, "seed": seed},
           "layer": layers}
    return config.validate(raw, "test")


# the forearm's structure in small: a relief the top layers follow, a wavy junction
FURROWS = {"kind": "generated", "depth_um": 20.0, "spacing_um": 200.0, "width_um": 80.0, "seed": 3}
SKINLIKE = [lay("sc", 15.0, 1.5, 20.0, 500.0, 0.9, "surface"), lay("epi", 60.0, 1.34, 10.0, 400.0, 0.8, "papillae"),
            lay("pap", 45.0, 1.4, 5.0, 200.0, 0.8, "surface"), lay("derm", math.inf, 1.4, 5.0, 200.0, 0.8)]
WAVY = [lay("a", 40.0, 1.5, 10.0, 300.0, 0.8, "papillae"), lay("b", 50.0, 1.34, 10.0, 300.0, 0.8),
        lay("c", math.inf, 1.4, 10.0, 300.0, 0.8)]
LIGHT = (300.0, 200.0, 2000.0)


# ----------------------------------------------------------------------------- a separate tracer
class Surfaces:
    """The volume's smooth interfaces in float64: the Catmull-Rom bicubic through Volume.smooth
    at the column centres, written as the cubic Hermite spline with central-difference tangents
    (the kernel uses the weight polynomials), edges repeated (lateral open)."""

    def __init__(self, vol):
        self.vol = vol
        self.z = vol.iface[:, 0].astype(float)
        self.var = vol.iface[:, 3].astype(int)
        self.n = np.concatenate([[vol.n_above], np.float32(vol.n).astype(float), [vol.n_below]])

    def _hermite(self, p, f):
        m0, m1 = 0.5 * (p[2] - p[0]), 0.5 * (p[3] - p[1])
        f2, f3 = f * f, f * f * f
        return (2 * f3 - 3 * f2 + 1) * p[1] + (f3 - 2 * f2 + f) * m0 + (-2 * f3 + 3 * f2) * p[2] + (f3 - f2) * m1

    def h(self, k, x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self.var[k] < 0:
            return np.full(np.broadcast(x, y).shape, self.z[k])
        v = self.vol
        H = v.smooth[self.var[k]].astype(float)
        gx, gy = (x - v.x0) / v.dx - 0.5, (y - v.y0) / v.dy - 0.5
        ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
        fx, fy = gx - ix, gy - iy
        rows = []
        for j in range(4):
            r = np.clip(iy - 1 + j, 0, v.ny - 1)
            p = [H[r, np.clip(ix - 1 + i, 0, v.nx - 1)] for i in range(4)]
            rows.append(self._hermite(p, fx))
        return self._hermite(rows, fy) + self.z[k]          # the row's offset (shared rows)

    def normal(self, k, x, y, e=1e-4):
        hx = (self.h(k, x + e, y) - self.h(k, x - e, y)) / (2 * e)
        hy = (self.h(k, x, y + e) - self.h(k, x, y - e)) / (2 * e)
        N = np.stack([-hx, -hy, np.ones_like(hx)], -1)
        return N / np.linalg.norm(N, axis=-1, keepdims=True)

    def shoot(self, v, Ls, u, lz):
        """Rays from vertex v (layer Ls) with momenta u (m, 2) straight up through interfaces
        Ls .. 0 (vector Snell), to the plane z = lz: landing (m, 2), final directions (m, 3);
        the product of the Fresnel transmittances in self.fresnel_t (NaN past the critical angle)."""
        u = np.atleast_2d(np.asarray(u, float))
        nv = self.n[Ls + 1]
        d = np.concatenate([u / nv, np.sqrt(1 - (u * u).sum(1, keepdims=True) / nv ** 2)], 1)
        o = np.tile(np.asarray(v[:3], float), (len(u), 1))
        for i in range(Ls, -1, -1):
            t = (self.h(i, o[:, 0], o[:, 1]) - o[:, 2]) / d[:, 2]
            for _ in range(12):                       # Newton on z - h along the ray
                p = o + t[:, None] * d
                g = p[:, 2] - self.h(i, p[:, 0], p[:, 1])
                nz = self.normal(i, p[:, 0], p[:, 1])
                t = t - g / ((d * nz).sum(1) / nz[:, 2])
            o = o + t[:, None] * d
            nrm = -self.normal(i, o[:, 0], o[:, 1])    # facing the incoming (upgoing) ray
            n1, n2 = self.n[i + 1], self.n[i]
            eta = n1 / n2
            ci = -(d * nrm).sum(1, keepdims=True)
            ct = np.sqrt(1 - eta * eta * (1 - ci * ci))
            rs = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)
            rp = (n1 * ct - n2 * ci) / (n1 * ct + n2 * ci)
            self.fresnel_t = (1.0 if i == Ls else self.fresnel_t) * (1 - 0.5 * (rs * rs + rp * rp))[:, 0]
            d = eta * d + (eta * ci - ct) * nrm
        a = (lz - o[:, 2]) / d[:, 2]
        return o[:, :2] + a[:, None] * d[:, :2], d


def _vertices(vol, rng, n, depth=130.0):
    out = []
    for _ in range(n):
        out.append([rng.uniform(100, 400), rng.uniform(100, 400), rng.uniform(-depth, -1.0), 0])
    return np.array(out, np.float32).astype(float)      # the kernel takes float32 positions


# ----------------------------------------------------------------------------- the connection
@pytest.mark.parametrize("kind", ["wavy junction", "furrows + junction, snapped"])
def test_found_path_obeys_snell_lies_on_the_surfaces_and_lands_on_the_light(dev, kind):
    """Direct chains, and chains reflected once at a flat interface below the vertex: every
    point lies on its smooth surface (the separate Hermite evaluation), the tangential part of
    n d is continuous at every refraction (Snell) and the normal part flips at a reflection, the
    last point is the light.  All solves converge."""
    if kind == "wavy junction":
        vol, refl = volume.build(scene(WAVY, papillae=10.0)), 2
    else:
        vol, refl = volume.build(scene(SKINLIKE, relief=FURROWS, papillae=10.0, quantize=True)), None
    S = Surfaces(vol)
    verts = _vertices(vol, np.random.default_rng(3), 60)
    checked = 0
    for mode in (0, refl) if refl else (0,):
        r = testing.mnee_probe(dev, vol, LIGHT, verts, mode)
        built = r["built"]
        assert built.sum() >= 30 and r["ok"][built].all(), (mode, r["ok"], r["layer"])
        for ok, pts in zip(r["ok"], r["points"]):
            if not ok:
                continue
            P = pts[:, :3]
            assert np.hypot(*(P[-1, :2] - LIGHT[:2])) <= 1e-8 * 3000.0
            for j in range(1, len(P) - 1):
                k_in, k_out = int(pts[j, 3]), int(pts[j + 1, 3])    # layers of the segments around it
                # which interface: the one between the two media, or (a reflection) below k_in
                i = max(k_in, k_out) if k_in != k_out else k_in + 1
                assert abs(P[j, 2] - S.h(i, P[j, 0], P[j, 1])) <= 1e-9 * (1 + abs(P[j, 2]))
                np.testing.assert_allclose(pts[j, 4:7], S.normal(i, P[j, 0], P[j, 1]), atol=2e-7)
                n = pts[j, 4:7]
                d1 = (P[j] - P[j - 1]) / np.linalg.norm(P[j] - P[j - 1])
                d2 = (P[j + 1] - P[j]) / np.linalg.norm(P[j + 1] - P[j])
                n1, n2 = S.n[k_in + 1], S.n[k_out + 1]
                t1, t2 = n1 * (d1 - (d1 @ n) * n), n2 * (d2 - (d2 @ n) * n)
                np.testing.assert_allclose(t1, t2, atol=1e-9)
                if k_in == k_out:                                   # mirror
                    assert abs(d1 @ n + d2 @ n) <= 1e-9
                checked += 1
    assert checked >= 60


@pytest.mark.parametrize("kind", ["wavy junction", "furrows + junction, snapped"])
def test_geometry_term_is_the_finite_difference_jacobian_of_a_separate_tracer(dev, kind):
    """G = 1 / (n_a^2 cos theta_v cos theta_a |det d(landing)/du|) with the Jacobian of the
    separate tracer's landing point by central differences in u, at the kernel's solution."""
    if kind == "wavy junction":
        vol = volume.build(scene(WAVY, papillae=10.0))
    else:
        vol = volume.build(scene(SKINLIKE, relief=FURROWS, papillae=10.0, quantize=True))
    S = Surfaces(vol)
    verts = _vertices(vol, np.random.default_rng(5), 16)
    r = testing.mnee_probe(dev, vol, LIGHT, verts, 0)
    checked = 0
    for i, v in enumerate(verts):
        if not r["ok"][i]:
            continue
        Ls, u = int(r["layer"][i]), np.array([r["ux"][i], r["uy"][i]])
        land, d = S.shoot(v, Ls, u[None, :], LIGHT[2])
        np.testing.assert_allclose(land[0], LIGHT[:2], atol=1e-5)
        # the surfaces are C1 (h'' jumps at the column centres' grid lines, and with it the
        # Jacobian): a step small enough not to straddle one, large enough above the separate
        # tracer's rounding (~1e-10 um in the landing point)
        e = 1e-5
        cols = []
        for a in range(2):
            du = np.zeros(2); du[a] = e
            lp, _ = S.shoot(v, Ls, (u + du)[None, :], LIGHT[2])
            lm, _ = S.shoot(v, Ls, (u - du)[None, :], LIGHT[2])
            cols.append((lp[0] - lm[0]) / (2 * e))
        J = np.stack(cols, 1)
        nv = S.n[Ls + 1]
        cos_v = math.sqrt(1 - (u @ u) / nv ** 2)
        G = 1 / (vol.n_above ** 2 * cos_v * d[0, 2] * abs(np.linalg.det(J)))
        assert r["G"][i] == pytest.approx(G, rel=2e-5), (i, Ls)
        checked += 1
    assert checked >= 12


def test_amplitude_to_zero_gives_the_flat_connection(dev):
    """Junction amplitude a -> 0: G and the whole connection factor (Fresnel, attenuation)
    converge to the flat path tracer's closed-form connection, the difference falling with a."""
    flat = volume.build(scene(WAVY))
    verts = _vertices(flat, np.random.default_rng(7), 24, depth=85.0)
    verts[:, 3] = [0 if z > -40.0 else 1 for z in verts[:, 2]]
    ref = testing.connect_probe(dev, flat, LIGHT, verts, 0)
    errs = []
    for a in (1.0, 0.1, 0.01):
        r = testing.mnee_probe(dev, volume.build(scene(WAVY, papillae=a)), LIGHT, verts, 0)
        far = np.abs(verts[:, 2] + 40.0) > 2 * a               # the vertex's layer is the same
        assert r["ok"][far].all()
        dOdA = ref["domega_dA"][far] / ref["cos_L"][far]        # the flat G
        errs.append(max(np.max(np.abs(r["G"][far] / dOdA - 1)),
                        np.max(np.abs(r["factor"][far] / ref["factor"][far] - 1))))
    assert errs[2] < 2e-3 and errs[2] < errs[1] < errs[0], errs


def test_small_spherical_light_by_brute_force_converges_to_the_manifold_result(dev):
    """A light sphere of radius r: the vertex's irradiance from it, found by shooting rays from
    the vertex (separate tracer, uniform in u over a square holding the sphere's preimage;
    dOmega = du / (n_v^2 cos theta_v)), is I (n_v / n_a)^2 Omega_hit / (pi r^2) for radiance
    I / (pi r^2).  As r -> 0 that ratio tends to the kernel's G (within the shot noise)."""
    vol = volume.build(scene(WAVY, papillae=10.0))
    S = Surfaces(vol)
    verts = np.array([[210.0, 330.0, -70.0, 1], [260.0, 240.0, -60.0, 1]])   # exact in float32
    r = testing.mnee_probe(dev, vol, LIGHT, verts, 0)
    rng = np.random.default_rng(11)
    L = np.array(LIGHT)
    for i, v in enumerate(verts):
        assert r["ok"][i]
        Ls, u0, G = int(r["layer"][i]), np.array([r["ux"][i], r["uy"][i]]), r["G"][i]
        nv = S.n[Ls + 1]
        e = 1e-4
        J = np.stack([(S.shoot(v, Ls, (u0 + e * ax)[None], L[2])[0][0]
                       - S.shoot(v, Ls, (u0 - e * ax)[None], L[2])[0][0]) / (2 * e)
                      for ax in np.eye(2)], 1)
        smin = np.linalg.svd(J, compute_uv=False)[-1]
        ratios = []
        for rad in (20.0, 5.0):
            _, d = S.shoot(v, Ls, u0[None], L[2])
            half = 1.5 * rad / (d[0, 2] * smin)
            m = 40_000
            u = u0 + rng.uniform(-half, half, (m, 2))
            land, dd = S.shoot(v, Ls, u, L[2])
            p = np.concatenate([land, np.full((m, 1), L[2])], 1)     # a point of each ray
            w = L - p
            dist = np.linalg.norm(w - (w * dd).sum(1, keepdims=True) * dd, axis=1)
            cos_v = np.sqrt(1 - (u * u).sum(1) / nv ** 2)
            wts = np.where(dist < rad, 1.0 / (nv ** 2 * cos_v), 0.0) * (2 * half) ** 2 / m
            omega, se = wts.sum(), wts.std() * math.sqrt(m)
            ratios.append(((nv / vol.n_above) ** 2 * omega / (math.pi * rad ** 2) / G,
                           (nv / vol.n_above) ** 2 * se / (math.pi * rad ** 2) / G))
        (r20, s20), (r5, s5) = ratios
        assert abs(r5 - 1) <= 4 * s5 + 2e-3, ratios
        assert abs(r5 - 1) <= abs(r20 - 1) + 4 * math.hypot(s5, s20), ratios


FOCUS = [lay("a", 40.0, 1.5, 0.0, 1e-3, 0.8, "papillae"), lay("b", math.inf, 1.34, 0.0, 1e-3, 0.8)]


def _solutions(dev, vol, verts, r):
    """Distinct converged solutions (u, G F) per vertex: the kernel's flat-seeded one and Newton
    from 96 seeds around the flat seed (momentum offsets 0.02-0.5, 12 directions)."""
    u0 = np.stack([r["ux"], r["uy"]], 1)
    sols = [[(u0[i], r["G"][i] * r["F"][i])] if r["ok"][i] else [] for i in range(len(verts))]
    for d in np.linspace(0.02, 0.5, 8):
        for phi in np.arange(12) * (np.pi / 6):
            rs = testing.mnee_probe(dev, vol, LIGHT, verts, 0, seeds=u0 + d * np.array([np.cos(phi), np.sin(phi)]))
            for i in np.flatnonzero(rs["ok"]):
                u = np.array([rs["ux"][i], rs["uy"][i]])
                if all(np.abs(u - q[0]).sum() > 1e-6 for q in sols[i]):
                    sols[i].append((u, rs["G"][i] * rs["F"][i]))
    return sols


def test_solutions_sum_to_the_brute_force_irradiance(dev):
    """A strongly focusing junction (6 um, 40 um period), vertices 150 and 180 um deep: light
    reaches the deeper one along three paths.  Brute force: rays shot from the vertex uniformly in
    u over the box holding every solution found (plus 0.03), those passing within r = 20 um of the
    light, each weighted by its Fresnel transmittance: (n_v / n_a)^2 int T dOmega / (pi r^2)
    (no attenuation here).  It equals the sum of G F over the distinct solutions that a dense seed
    search finds (each solution's G and Fresnel factors, their de-duplication).  The render's
    connection (the flat-seeded solution plus specular manifold sampling of the others) is unbiased:
    the mean of 4,000 samples of it equals that sum within its standard error (measured 1.002 +-
    0.022 at the deeper vertex, where the flat-seeded solution alone is 0.52 and the earlier
    flat seed + 8 seeds 0.73), and at the shallower vertex, one solution, every sample is exact."""
    vol = volume.build(scene(FOCUS, papillae=6.0, period=40.0))
    S = Surfaces(vol)
    verts = np.array([[230.0, 260.0, -180.0, 1], [190.0, 310.0, -150.0, 1]])
    r = testing.mnee_probe(dev, vol, LIGHT, verts, 0)
    sols = _solutions(dev, vol, verts, r)
    assert [len(q) for q in sols] == [3, 1]
    rng = np.random.default_rng(13)
    L = np.array(LIGHT)
    rad, m = 20.0, 200_000
    for i, v in enumerate(verts):
        Ls = int(r["layer"][i])
        nv = S.n[Ls + 1]
        f = np.array([q[0] for q in sols[i]])
        lo, hi = f.min(0) - 0.03, f.max(0) + 0.03
        u = lo + (hi - lo) * rng.uniform(0, 1, (m, 2))
        with np.errstate(invalid="ignore"):
            land, dd = S.shoot(v, Ls, u, L[2])
            tf = S.fresnel_t
        p = np.concatenate([land, np.full((m, 1), L[2])], 1)
        w = L - p
        dist = np.linalg.norm(w - (w * dd).sum(1, keepdims=True) * dd, axis=1)
        hit = np.nan_to_num(dist, nan=np.inf) < rad
        cos_v = np.sqrt(1 - (u * u).sum(1) / nv ** 2)
        wt = np.where(hit, np.nan_to_num(tf) / (nv ** 2 * cos_v), 0.0) * np.prod(hi - lo)
        k = (nv / vol.n_above) ** 2 / (math.pi * rad ** 2)
        brute, sb = k * wt.mean(), k * wt.std() / math.sqrt(m)
        total = sum(q[1] for q in sols[i])
        assert hit.sum() > 300, hit.sum()
        assert abs(brute / total - 1) <= 4 * sb / brute + 0.03, (brute, sb, total, int(hit.sum()))
        sms = testing.mnee_probe(dev, vol, LIGHT, np.repeat(verts[i:i + 1], 4000, 0), 0)["all_factor"]
        se = sms.std() / math.sqrt(len(sms))
        assert abs(sms.mean() - total) <= 4 * se + 1e-4 * total, (sms.mean(), se, total)
        if len(sols[i]) == 1:
            np.testing.assert_allclose(sms, total, rtol=1e-4)
        else:
            assert se < 0.05 * total and r["factor"][i] < 0.7 * total, (se, r["factor"][i], total)


def test_a_fractional_mean_of_random_trials_stays_unbiased(dev):
    """The random trials' number is drawn per connection with mean t (sms_count: the whole part,
    one more with the probability of the fraction), and a solution they find is weighted by 1/t.
    At t = 0.4, under the same focusing junction: at the vertex with one solution the trials made
    average 0.4 (every sample still exact), and at the vertex with three the mean of the samples
    equals the sum over the solutions of a dense seed search within its standard error (weighted
    by 1 instead of 1/t it would fall short by most of the other paths' share)."""
    vol = volume.build(scene(FOCUS, papillae=6.0, period=40.0))
    verts = np.array([[230.0, 260.0, -180.0, 1], [190.0, 310.0, -150.0, 1]])
    r = testing.mnee_probe(dev, vol, LIGHT, verts, 0)
    sols = _solutions(dev, vol, verts, r)
    assert [len(q) for q in sols] == [3, 1]
    t, n = 0.4, 8000
    one = testing.mnee_probe(dev, vol, LIGHT, np.repeat(verts[1:2], n, 0), 0, trials=t, salt=3)
    total1 = sum(q[1] for q in sols[1])
    np.testing.assert_allclose(one["all_factor"], total1, rtol=1e-4)
    made = one["trials"]
    assert set(np.unique(made)) == {0.0, 1.0}
    assert abs(made.mean() - t) <= 4 * math.sqrt(t * (1 - t) / n), made.mean()
    sms = testing.mnee_probe(dev, vol, LIGHT, np.repeat(verts[0:1], n, 0), 0, trials=t, salt=3)["all_factor"]
    total = sum(q[1] for q in sols[0])
    se = sms.std() / math.sqrt(n)
    assert abs(sms.mean() - total) <= 4 * se + 1e-4 * total, (sms.mean(), se, total)
    assert se < 0.05 * total and r["factor"][0] < 0.7 * total, (se, r["factor"][0], total)


def test_where_the_flat_seeded_solve_fails_the_random_trials_find_every_solution(dev):
    """Under the same focusing junction, the vertices (of 4,000 drawn) whose flat-seeded solve
    fails within its budget (Newton, then continuation, MN_BUDGET traces) get no x0: the
    connection's one random trial is then the whole estimate, a solution it finds weighted by the
    trials until it recurs.  The mean of 8,000 samples equals the sum over the solutions of a
    dense seed search within its standard error at each such vertex (measured within 1.8 SE at
    six vertices, one with three solutions; a trial finds one in 16-77 % of the samples)."""
    vol = volume.build(scene(FOCUS, papillae=6.0, period=40.0))
    rng = np.random.default_rng(1)
    n = 4000
    verts = np.stack([rng.uniform(100, 400, n), rng.uniform(100, 400, n), -rng.uniform(20, 300, n),
                      np.ones(n)], 1)
    r = testing.mnee_probe(dev, vol, LIGHT, verts, 0)
    failed = verts[np.flatnonzero(r["built"] & ~r["ok"])][:6]
    assert len(failed) >= 3, len(failed)
    rf = testing.mnee_probe(dev, vol, LIGHT, failed, 0)
    sols = _solutions(dev, vol, failed, rf)
    checked = 0
    for i, q in enumerate(sols):
        total = sum(s[1] for s in q)
        if not total > 0:
            continue
        sms = testing.mnee_probe(dev, vol, LIGHT, np.repeat(failed[i:i + 1], 8000, 0), 0, salt=5)
        a = sms["all_factor"]
        se = a.std() / math.sqrt(len(a))
        assert 0 < se < 0.1 * total, (i, se, total)
        assert abs(a.mean() - total) <= 4 * se, (i, a.mean(), se, total, len(q))
        checked += 1
    assert checked >= 3, checked


# ----------------------------------------------------------------------------- renders
def test_render_at_vanishing_amplitude_matches_the_flat_path_tracer(dev):
    """A junction of amplitude 1e-3 um (a relief build: column tracking, smooth normals, MNEE)
    against the flat build of the same stack, same seed: nearly every path is the same path, so
    the image means agree within 1e-3 or 3 standard errors of the per-pixel differences; every
    connection solved, in the report."""
    kw = dict(res=(6, 6), spp=16, passes=2, light=(0.3, 0.2, 2.0))
    a = entry.render_pt(scene(WAVY, **kw), dev=dev)
    b = entry.render_pt(scene(WAVY, papillae=1e-3, **kw), dev=dev)
    va, vb = a.spectral[..., 0], b.spectral[..., 0]
    assert va.mean() > 0 and a.report["nee_connections_made"] > 3000
    se = (vb - va).std(ddof=1) / math.sqrt(va.size) / va.mean()
    assert abs(vb.mean() / va.mean() - 1) < max(1e-3, 3 * se), (vb.mean() / va.mean(), se)
    m = b.report["manifold_nee"]
    assert a.report["manifold_nee"] is None
    assert m["solves"] > 0 and m["success_rate"] == 1.0, m


def _relief_small(passes=3, seed=1):
    return scene(SKINLIKE, relief=FURROWS, papillae=10.0, quantize=True, res=(6, 4), spp=4,
                 passes=passes, seed=seed)


def test_relief_same_seed_same_bytes_and_resume_is_byte_identical(dev, tmp_path):
    """The relief path tracer: the same seed gives the same EXR bytes, another seed others; a
    render stopped after 1 of 3 passes and resumed equals the uninterrupted one, and the
    solver's counts in the report cover every pass."""
    outs = []
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        out = tmp_path / f"{name}.exr"
        entry.render_pt(_relief_small(seed=seed), dev=dev, out=str(out))
        outs.append(out.read_bytes())
    assert outs[0] == outs[1] and outs[0] != outs[2]
    part = tmp_path / "part.exr"
    entry.render_pt(_relief_small(), dev=dev, out=str(part), stop_after=1)
    ck = ckpt.default_path(str(part))
    assert ckpt.load(ck, integrator="pt")["pass_index"] == 1
    entry.render_pt(_relief_small(), dev=dev, out=str(part), resume=ck)
    assert part.read_bytes() == outs[0]
    full = json.loads((tmp_path / "a.json").read_text())["manifold_nee"]
    resumed = json.loads(part.with_suffix(".json").read_text())["manifold_nee"]
    assert full == resumed and full["solves"] > 0


def test_compare_and_bias_take_the_path_tracer_as_the_relief_reference():
    """clppm compare (and bench/studies/bias.py through clppm.analysis.reference) use the path tracer on relief
    scenes now, with the manifold kernels in the reference's cache key."""
    from clppm.analysis.compare import QUICK, reference_spec
    from clppm.analysis.reference import RefSpec, reference_key
    from clppm import config as C
    cfg = C.load(C.find("forearm"))
    assert reference_spec(cfg, (80, 60), QUICK).integrator == "pt"
    spec = RefSpec(integrator="pt", resolution=(80, 60), block=10, paths=1000)
    assert reference_key(cfg, spec) != reference_key(C.load(C.find("forearm_flat")), spec)
