/* Manifold next-event estimation through height-field interfaces (included by pt.cl).
 *
 * The surfaces (docs/relief.md) are the height fields of surface.h, which the photon and eye
 * passes refract at too.
 *
 * The connection (Hanika, Droske & Fascione 2015, "Manifold next event estimation", solved here
 * by shooting).  A chain from the vertex is a fixed sequence of events (interface i from layer
 * k, transmitted or reflected: pt.cl chain_build).  A ray leaves the vertex with horizontal
 * "momentum" u = n_v (d_x, d_y) and is traced through the events: exact intersection with each
 * height field (Newton on z - h(x, y) along the ray), refraction by the vector form of Snell's
 * law or mirror reflection at the surface's normal, and at the end to the light's height z_l.
 * Snell's law holds at every crossing by construction; the constraint is that the ray arrives
 * at the light: c(u) = (x, y)(z_l) - (x_l, y_l) = 0, two equations in two unknowns, solved by
 * Newton's method with step halving, seeded by the flat solution (pt.cl solve_p on the local
 * heights).  dc/du comes from ray differentials carried through every event (Igehy 1999): the
 * intersection's transfer, the normal's derivative from h's second derivatives, the
 * derivative of the refraction or reflection.  So no finite differences and no re-projection.
 *
 * The geometry term.  By the conservation of etendue, n^2 dA_perp dOmega is the same at both
 * ends of the chain, so the solid angle the point light sends into a unit area around the vertex
 * (normal to the light's direction there) is
 *     G = dOmega_l / dA_v,perp = (n_v / n_a)^2 dOmega_v / dA_l,perp,
 * dOmega_v = du / (n_v^2 cos theta_v) and dA_l,perp = |det dc/du| du cos theta_a, so
 *     G = 1 / (n_a^2 cos theta_v cos theta_a |det dc/du|).
 * On flat layers det dc/du = S rho' (pt.cl) and G is the flat connection's, exactly.
 */
#ifndef CLPPM_MNEE_H
#define CLPPM_MNEE_H

#include "surface.h"

#ifdef PT_FP64
#define MN_TOL 1e-9             /* landing error, relative to the vertex-light distance */
#define HF_TOL 1e-13            /* intersection step, relative to the coordinates' size */
#else
#define MN_TOL 2e-6f
#define HF_TOL 1e-6f
#endif
#define MN_MAXIT 16             /* Newton iterations on the landing constraint */
#define MN_HALF 6               /* step halvings per iteration */
#define MN_BUDGET 80            /* traces per flat-seeded solve, continuation included (then:
                                   failed, and the random trials look for every solution) */
#define MN_SEED_BUDGET 24       /* traces per extra seed */
#define HF_MAXIT 24             /* Newton iterations per ray-height-field intersection */
#define MN_CONT 64              /* continuation steps */
#define MN_TAYLOR 1e-5          /* um: the longest last step of an intersection taken without
                                   evaluating the surface again (hf_hit) */
#define MN_WARM 12              /* events whose intersections start from the last trace's,
                                   moved to first order by the solver's step in u (a step moves
                                   the chain a little, so they need fewer evaluations of the
                                   height field) */

/* A ray (o, d) with its differentials (do_a, dd_a), a = 1, 2, with respect to u */
typedef struct { real4 o, d, do1, do2, dd1, dd2; } Ray;

/* The surface deformed from the plane z = zr by lam in [0, 1] (lam = 1: the surface itself):
 * the homotopy the solver continues along when Newton from the flat seed fails. */
inline void hf_eval_l(__constant const Params* P, __constant const float4* iface,
                      __global const float* smooth, int k, real x, real y, real lam, real zr, HF* o) {
    hf_eval(P, iface, smooth, k, x, y, o);
    if (lam != 1) {
        o->h = zr + lam * (o->h - zr);
        o->hx *= lam; o->hy *= lam; o->hxx *= lam; o->hxy *= lam; o->hyy *= lam;
    }
}

/* Whether (x1, y1) and (x2, y2) lie in the same bicubic patch (between the same samples) */
inline int same_patch(__constant const Params* P, real x1, real y1, real x2, real y2) {
    return floor(hf_gx(P, x1)) == floor(hf_gx(P, x2)) && floor(hf_gy(P, y1)) == floor(hf_gy(P, y2));
}

/* Newton along the ray for its intersection with the varying interface k, from *t where it is
 * > 0, else from the plane through h(o.xy); 1 with *t the distance and *f the surface at the hit
 * (at the last iterate, within the step's rounding-level dt of the hit, or its Taylor expansion
 * at the hit). */
inline int hf_newton(__constant const Params* P, __constant const float4* iface,
                     __global const float* smooth, int k, real lam, real zr, const Ray* r, HF* f, real* t_io) {
    real t = *t_io;
    if (!(t > 0)) {
        hf_eval_l(P, iface, smooth, k, r->o.x, r->o.y, lam, zr, f);
        t = (f->h - r->o.z) / r->d.z;
    }
    for (int it = 0; it < HF_MAXIT; ++it) {
        const real4 p = r->o + t * r->d;
        hf_eval_l(P, iface, smooth, k, p.x, p.y, lam, zr, f);
        const real g = p.z - f->h;
        const real gp = r->d.z - f->hx * r->d.x - f->hy * r->d.y;
        if (!(fabs(gp) > (real)1e-6)) return 0;
        const real dt = g / gp;
        t -= dt;
        *t_io = t;
        /* the step's floor is the rounding of the position (~1e-16 of 1e4 um), not of t */
        const real tol = HF_TOL * (1 + fabs(t) + fabs(r->o.x) + fabs(r->o.y));
        if (fabs(dt) <= tol) return 1;
        /* a last step this short (inside one patch): Newton's error after it, dt^2 times the
         * ray's curvature term q / (2 gp), is below the tolerance, and h and its derivatives at
         * the new point are their Taylor expansion from this one (the patch's third derivatives
         * leave < 1e-12 at this distance): the evaluation that would only confirm it is saved */
        const real ex = -dt * r->d.x, ey = -dt * r->d.y;
        if (fabs(ex) + fabs(ey) <= (real)MN_TAYLOR && same_patch(P, p.x, p.y, p.x + ex, p.y + ey)) {
            const real q = f->hxx * r->d.x * r->d.x + 2 * f->hxy * r->d.x * r->d.y + f->hyy * r->d.y * r->d.y;
            if (fabs(q) * dt * dt <= 2 * fabs(gp) * tol) {
                f->h += f->hx * ex + f->hy * ey
                        + (real)0.5 * (f->hxx * ex * ex + 2 * f->hxy * ex * ey + f->hyy * ey * ey);
                f->hx += f->hxx * ex + f->hxy * ey;
                f->hy += f->hxy * ex + f->hyy * ey;
                return 1;
            }
        }
    }
    return 0;
}

/* Intersect the ray with interface k (a flat one in closed form; else hf_newton from t_warm,
 * the last trace's distance for this event predicted to first order, where it is > 0); on
 * success the ray's origin and its differentials move to the hit, *f is h there, *t_out the
 * distance and *dt1, *dt2 its derivatives in u (from the ray differentials: the next trace's
 * prediction).  0: no convergence or a hit behind. */
inline int hf_hit(__constant const Params* P, __constant const float4* iface,
                  __global const float* smooth, int k, real lam, real zr, real t_warm, Ray* r, HF* f,
                  real* t_out, real* dt1, real* dt2) {
    if (r->d.z == 0) return 0;
    real t = t_warm;
    if (IF_VAR(k) < 0) {
        /* a flat interface: its plane (the continuation's plane through it, zr, is the plane) */
        f->h = (real)IF_Z(k);
        f->hx = f->hy = f->hxx = f->hxy = f->hyy = 0;
        t = (f->h - r->o.z) / r->d.z;
    } else if (!hf_newton(P, iface, smooth, k, lam, zr, r, f, &t)) {
        return 0;
    }
    if (!(t > 0)) return 0;
    const real4 p = r->o + t * r->d;
    /* transfer: dt = -(do + t dd) . N / (d . N), N = (-hx, -hy, 1) */
    const real4 N = R4(-f->hx, -f->hy, 1);
    const real dn = rdot(r->d, N);
    const real4 q1 = r->do1 + t * r->dd1, q2 = r->do2 + t * r->dd2;
    *dt1 = -rdot(q1, N) / dn; *dt2 = -rdot(q2, N) / dn;
    r->do1 = q1 + *dt1 * r->d;
    r->do2 = q2 + *dt2 * r->d;
    r->o = R4(p.x, p.y, f->h);
    *t_out = t;
    return 1;
}

/* Derivative of the unit upward normal along a surface displacement dp */
inline real4 hf_dnormal(const HF* f, real4 n, real len, real4 dp) {
    const real4 dN = R4(-(f->hxx * dp.x + f->hxy * dp.y), -(f->hxy * dp.x + f->hyy * dp.y), 0);
    return (dN - n * rdot(n, dN)) / len;
}

/* Refract (eta = n1 / n2) or reflect the ray at the hit with upward normal n; nf faces the
 * incoming ray.  Differentials by the product rule (Igehy 1999).  0 at total internal reflection. */
inline int bend(Ray* r, real4 n, real4 dn1, real4 dn2, real eta, int refl, real* cos_i_out) {
    const real s = rdot(r->d, n) > 0 ? -1 : 1;          /* nf = s n faces the ray */
    const real4 nf = s * n, df1 = s * dn1, df2 = s * dn2;
    const real ci = -rdot(r->d, nf);
    *cos_i_out = ci;
    const real dci1 = -(rdot(r->dd1, nf) + rdot(r->d, df1));
    const real dci2 = -(rdot(r->dd2, nf) + rdot(r->d, df2));
    if (refl) {
        /* d' = d + 2 ci nf */
        r->dd1 = r->dd1 + 2 * (dci1 * nf + ci * df1);
        r->dd2 = r->dd2 + 2 * (dci2 * nf + ci * df2);
        r->d = r->d + 2 * ci * nf;
        return 1;
    }
    const real st2 = eta * eta * (1 - ci * ci);
    if (st2 >= 1) return 0;
    const real ct = sqrt(1 - st2);
    const real mu = eta * ci - ct;
    const real dmu_dci = eta - eta * eta * ci / ct;
    r->dd1 = eta * r->dd1 + mu * df1 + (dmu_dci * dci1) * nf;
    r->dd2 = eta * r->dd2 + mu * df2 + (dmu_dci * dci2) * nf;
    r->d = eta * r->d + mu * nf;
    return 1;
}

/* What one trace of a chain gives: the landing error c, dc/du, and the chain's factors */
typedef struct {
    real c[2], J[4];            /* J = (dc_x/du_1, dc_x/du_2, dc_y/du_1, dc_y/du_2) */
    real cos_v, cos_a;          /* |d_z| at the vertex, d_z in the air */
    real len[NL];               /* path length in each layer */
    real4 s;                    /* the surface crossing (the last event's point) */
    real4 d0;                   /* the direction leaving the vertex */
    real tw[MN_WARM];           /* the first MN_WARM events' distances: the next trace's starts */
    real tw1[MN_WARM], tw2[MN_WARM];    /* and their derivatives in u (the starts' first-order
                                           prediction for a trace at a nearby u) */
#ifdef CHAIN_LEGS
    float4 pe[MAXE];            /* the events' points, in order (pt.cl mnee_legs_factor: the legs
                                   through the inclusions and maps) */
#endif
    float F;                    /* product of Fresnel R or T over the events */
    int why;                    /* where a failed trace stopped: 1 momentum, 2 heading, 3 hit, 4 TIR,
                                   5 side, 6 air (10 x event + code) */
} Trace;

/* Trace the chain's events from vertex v (layer k0) with momentum u to the light's height,
 * each intersection started from the trace warm's (0: none), traced at u - (wdu1, wdu2);
 * pts (tests, else 0): 8 numbers per point (position, layer of the segment ending there,
 * upward normal), the vertex first, the point at the light's height last. */
inline int mnee_trace(const Chain* ch, real4 v, int k0, real ux, real uy, real4 l, real lam,
                      const Trace* warm, real wdu1, real wdu2, __constant const Params* P,
                      __constant const float4* iface, __constant const float* layer_n, __global const float* smooth, Trace* T,
                      __global real* pts) {
    const real nv = layer_n[k0];
    const real sx = ux / nv, sy = uy / nv;
    const real s2 = sx * sx + sy * sy;
    T->why = 1;
    if (!(s2 < 1)) return 0;
    const real cz = sqrt(1 - s2);
    const real dz = ch->up ? cz : -cz;
    Ray r;
    r.o = v;
    r.d = R4(sx, sy, dz);
    r.do1 = r.do2 = (real4)(0);
    r.dd1 = R4(1 / nv, 0, -sx / (nv * dz));
    r.dd2 = R4(0, 1 / nv, -sy / (nv * dz));
    T->d0 = r.d;
    T->cos_v = cz;
    if (pts) { pts[0] = v.x; pts[1] = v.y; pts[2] = v.z; pts[3] = k0; for (int j = 4; j < 8; ++j) pts[j] = 0; }
    T->F = 1.0f;
    for (int k = 0; k < NL; ++k) T->len[k] = 0;
    for (int e = 0; e < ch->ne; ++e) {
        const int i = ch->ev[e] & 255, k = (ch->ev[e] >> 8) & 255, refl = ch->ev[e] >> 16;
        /* the ray must head for the interface the event names (i == k: the top of layer k) */
        if ((i == k) != (r.d.z > 0)) { T->why = 10 * e + 2; return 0; }
        HF f;
        real t;
        const real tw = (warm && e < MN_WARM)
                        ? warm->tw[e] + wdu1 * warm->tw1[e] + wdu2 * warm->tw2[e] : (real)0;
        real t1, t2;
        if (!hf_hit(P, iface, smooth, i, lam, ch->zref[i], tw, &r, &f, &t, &t1, &t2)) { T->why = 10 * e + 3; return 0; }
        if (e < MN_WARM) { T->tw[e] = t; T->tw1[e] = t1; T->tw2[e] = t2; }
#ifdef CHAIN_LEGS
        T->pe[e] = (float4)((float)r.o.x, (float)r.o.y, (float)r.o.z, 0.0f);
#endif
        T->len[k] += t;
        real len;
        const real4 n = hf_normal(&f, &len);
        const real4 dn1 = hf_dnormal(&f, n, len, r.do1), dn2 = hf_dnormal(&f, n, len, r.do2);
        if (pts) {
            __global real* q = pts + 8 * (e + 1);
            q[0] = r.o.x; q[1] = r.o.y; q[2] = r.o.z; q[3] = k; q[4] = n.x; q[5] = n.y; q[6] = n.z; q[7] = 0;
        }
        const real n1 = layer_n[k], n2 = n_across(P, layer_n, i, k);
        real ci;
        if (!bend(&r, n, dn1, dn2, n1 / n2, refl, &ci)) { T->why = 10 * e + 4; return 0; }
        float ctf;
        const float R = fresnel_R((float)n1, (float)n2, (float)ci, &ctf);
        T->F *= refl ? R : 1.0f - R;
        /* the ray leaves on the side the event says (reflected: back, transmitted: through) */
        if ((rdot(r.d, n) > 0) != ((i == k) != refl)) { T->why = 10 * e + 5; return 0; }
    }
    T->why = 6;
    if (!(r.d.z > 0)) return 0;
    T->why = 0;
    T->s = r.o;
    T->cos_a = r.d.z;
    const real a = (l.z - r.o.z) / r.d.z;
    T->c[0] = r.o.x + a * r.d.x - l.x;
    T->c[1] = r.o.y + a * r.d.y - l.y;
    if (pts) {
        __global real* q = pts + 8 * (ch->ne + 1);
        q[0] = r.o.x + a * r.d.x; q[1] = r.o.y + a * r.d.y; q[2] = l.z; q[3] = -1;
        for (int j = 4; j < 8; ++j) q[j] = 0;
    }
    /* dc = do_xy + da d_xy + a dd_xy, da = (-do_z - a dd_z) / d_z */
    const real da1 = (-r.do1.z - a * r.dd1.z) / r.d.z, da2 = (-r.do2.z - a * r.dd2.z) / r.d.z;
    T->J[0] = r.do1.x + da1 * r.d.x + a * r.dd1.x;
    T->J[1] = r.do2.x + da2 * r.d.x + a * r.dd2.x;
    T->J[2] = r.do1.y + da1 * r.d.y + a * r.dd1.y;
    T->J[3] = r.do2.y + da2 * r.d.y + a * r.dd2.y;
    return 1;
}

/* Solver statistics of a connection */
typedef struct { int ok, iters, halvings, cont, traces; } MneeStat;

/* Newton on c(u) = 0 for the surfaces at homotopy lam, from u; 1 with the converged trace. */
inline int mnee_newton(const Chain* ch, real4 v, int k0, real* ux, real* uy, real4 l, real lam,
                       __constant const Params* P, __constant const float4* iface,
                       __constant const float* layer_n, __global const float* smooth,
                       Trace* T, MneeStat* st) {
    const real4 dv = l - v;
    const real tol = (real)MN_TOL * sqrt(rdot(dv, dv));
    if (st->traces >= MN_BUDGET) return 0;
    st->traces++;
    if (!mnee_trace(ch, v, k0, *ux, *uy, l, lam, 0, 0, 0, P, iface, layer_n, smooth, T, 0)) return 0;
    real err = sqrt(T->c[0] * T->c[0] + T->c[1] * T->c[1]);
    for (int it = 0; it < MN_MAXIT; ++it) {
        if (err <= tol) return 1;
        st->iters++;
        const real det = T->J[0] * T->J[3] - T->J[1] * T->J[2];
        if (!(fabs(det) > 0)) return 0;
        const real du = -(T->J[3] * T->c[0] - T->J[1] * T->c[1]) / det;
        const real dv2 = -(-T->J[2] * T->c[0] + T->J[0] * T->c[1]) / det;
        real step = 1;
        int acc = 0;
        Trace Tn;
        for (int hlv = 0; hlv < MN_HALF; ++hlv) {
            if (st->traces >= MN_BUDGET) return 0;
            st->traces++;
            const real nx = *ux + step * du, ny = *uy + step * dv2;
            if (mnee_trace(ch, v, k0, nx, ny, l, lam, T, step * du, step * dv2, P, iface, layer_n, smooth, &Tn, 0)) {
                const real en = sqrt(Tn.c[0] * Tn.c[0] + Tn.c[1] * Tn.c[1]);
                if (en < err) { *ux = nx; *uy = ny; *T = Tn; err = en; acc = 1; break; }
            }
            step *= (real)0.5;
            st->halvings++;
        }
        if (!acc) return 0;
    }
    return err <= tol;
}

/* The connection from the flat seed u (the exact solution for the planes through the
 * interfaces' heights at the vertex, lam = 0): Newton on the surfaces themselves; where that
 * fails (a fold of the map between the seed and the solution, or total internal reflection on
 * the way), continuation in lam from 0 to 1 with adaptive steps, each solved by Newton from
 * the last solution: it follows the solution branch the flat path deforms into. */
inline int mnee_solve(const Chain* ch, real4 v, int k0, real* ux, real* uy, real4 l,
                      __constant const Params* P, __constant const float4* iface,
                      __constant const float* layer_n, __global const float* smooth,
                      Trace* T, MneeStat* st) {
    st->ok = 0; st->iters = 0; st->halvings = 0; st->cont = 0; st->traces = 0;
    const real sx = *ux, sy = *uy;
    if (mnee_newton(ch, v, k0, ux, uy, l, 1, P, iface, layer_n, smooth, T, st)) { st->ok = 1; return 1; }
    st->cont = 1;
    *ux = sx; *uy = sy;
    real lam = 0, dl = (real)0.25;
    for (int g = 0; g < MN_CONT; ++g) {
        const real ln = fmin((real)1, lam + dl);
        real nx = *ux, ny = *uy;
        if (mnee_newton(ch, v, k0, &nx, &ny, l, ln, P, iface, layer_n, smooth, T, st)) {
            *ux = nx; *uy = ny; lam = ln;
            if (lam >= 1) { st->ok = 1; return 1; }
            dl = fmin((real)0.5, dl * 2);
        } else {
            dl *= (real)0.5;
            if (dl < (real)(1.0 / 256)) return 0;
        }
    }
    return 0;
}

/* G = dOmega_light / dA_vertex,perp of a converged trace (see above) */
inline real mnee_G(const Trace* T, real na) {
    const real det = fabs(T->J[0] * T->J[3] - T->J[1] * T->J[2]);
    return 1 / (na * na * T->cos_v * T->cos_a * det);
}

#endif
