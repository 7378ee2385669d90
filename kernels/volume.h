/* clppm shared kernel code: parameters, random numbers, optics, volume geometry, the columns'
 * walls (included by common.h, surface.h and every header that needs no more).
 *
 * Compile-time switches (-D):
 *   NB    number of wavelength bands          NL   number of layers
 *   NINC  number of inclusions (inclusion.h; 0 or absent: none, the code compiled out)
 *   MAPS  per-column chromophore maps (maps.h; absent: none, the code compiled out)
 *   FLAT  every interface is a plane (no per-column heights, no lateral stepping)
 *   SMOOTH_SURFACE, NVAR  the walks cross the smooth surfaces themselves (smoothwalk.h), not the
 *         voxel staircase; NVAR varying interfaces
 *
 * Units: micrometres, coefficients in um^-1, z axis up, the mean skin surface at z = 0.
 *
 * The volume.  Layer L (0 = stratum corneum) occupies z_{L+1}(col) < z <= z_L(col) in the
 * column col; interface k = 0 is the surface, k = NL the bottom of the last layer (-inf for a
 * semi-infinite one).  Columns are the lateral voxels (lateral_voxel_um); interface heights
 * are snapped to the voxel thickness in z on the host, so this is exactly the paper's voxel
 * model, stored as one height per varying interface per column instead of a layer id per voxel.
 * Flat interfaces cost one float in total.
 *
 * Free flight: per-layer stepping with a residual optical depth.  The medium is piecewise
 * constant, so the exact free path is found by walking the boundaries of constant regions and
 * spending tau = -ln(u) at mu_t of each region: no majorant, no null collisions, and every
 * interface crossing is seen (Fresnel between layers of different n needs that; delta tracking
 * would miss crossings).  Lateral column walls are visited only inside the depth band where
 * some column's interface differs from another's ("column mode"); in the core of a layer
 * (above the lowest point of the interface below and below the highest point of the one above)
 * the photon moves between two planes ("core mode").  A flat layered slab therefore costs no
 * lateral steps at all.
 */
#ifndef CLPPM_VOLUME_H
#define CLPPM_VOLUME_H

#include <pyopencl-random123/philox.cl>
#include "constants.h"

#include "scalar.h"

#ifndef NB
#error "NB (number of bands) must be defined"
#endif
#ifndef NL
#error "NL (number of layers) must be defined"
#endif

#ifndef NINC
#define NINC 0
#endif
/* materials: the NL layers, then one per inclusion (rows of optics and of the band table) */
#define NMAT (NL + NINC)

#define PI_F 3.14159265358979f

/* Forced inline: PoCL otherwise calls some helpers out of line, and a call forces their state
 * (the random-number block) out of registers into memory.  Inlining rng_u01 alone gave the
 * photon pass +35 % photons/s under PoCL; forcing more helpers inline measured no further gain. */
#define HOT __attribute__((always_inline)) inline
#define BIG 1e30f
/* columns a side of a tile: the photon pass's tile mode and the smooth surfaces' walk
 * (clppm.integrators.photonpass.TILE, clppm.scene.volume.TILE) */
#define TILE 4

/* The scene's constants, uploaded once per scene (a launch's own values are kernel arguments:
 * photon.cl's PhotonLaunch).  Mirrors clppm/compute/structs.py PARAMS_DTYPE (checked by
 * tests/test_structs.py): 4-byte fields only, in this order. */
typedef struct {
    /* volume */
    float x0, y0, dx, dy;       /* column grid origin and pitch */
    float xw, yw;               /* domain width nx*dx, ny*dy */
    int nx, ny;
    int lateral;                /* 0 infinite, 1 open, 2 periodic */
    float n_above, n_below;
    float z_top;                /* highest surface point */
    /* source */
    int src_kind;               /* SRC_PENCIL, SRC_WIDE, SRC_POINT (constants.h) */
    float sx, sy, sz;           /* point position, or beam centre (z unused) */
    float sdx, sdy, sdz;        /* collimated direction */
    float swx, swy;             /* wide beam full widths */
    float cone_omc;             /* point light: 1 - cos of the sampling cone half angle */
    float cax, cay, caz;        /* cone axis */
    int fixed_band;             /* -1: draw from band_cdf */
    /* the photon passes (the values of one launch are photon.cl's PhotonLaunch) */
    uint seed_lo, seed_hi;
    float store_zmin;           /* store scattering events only above this z */
    float rr_threshold;         /* Russian roulette below this weight (fraction of W0) */
    float rr_m;                 /* survive with probability 1/rr_m */
    int max_events;             /* safety bound on boundary + collision events per photon */
    float rcone_cos;            /* exits with cos(theta) above this also go to the cone tally */
    /* storage rule (photon pass): 0 every scattering event, 1 importance-driven */
    int store_rule;             /* STORE_RULE_ALL, STORE_RULE_IMPORTANCE (constants.h) */
    float store_cos, store_sin; /* half angle of the cone of eye directions around +z */
    float store_scale;          /* storage probability = clamp(scale * importance, qmin, 1) */
    float store_qmin;
    int qmc;                    /* 1: emission (band, direction or footprint) from a shifted R3 sequence */
    float deep_z0, deep_dz;     /* depth roulette (photon.cl, DEPTH_ROULETTE builds): planes deep_z0 - k deep_dz */
} Params;

/* Interface k: (z if flat, zmin, zmax, var index as float; -1 = flat). */
#define IF_Z(k)    (iface[(k)].x)
#define IF_ZMIN(k) (iface[(k)].y)
#define IF_ZMAX(k) (iface[(k)].z)
#define IF_VAR(k)  ((int)iface[(k)].w)

#define VOLUME_ARGS __constant const Params* P, __constant const float4* iface, \
    __constant const float* layer_n, __global const float4* optics, \
    __global const float* heights
#define VOLUME_PASS P, iface, layer_n, optics, heights

/* ---------------------------------------------------------------- random numbers */
/* Philox4x32-10 (Random123, via pyopencl): counter = (stream id, draw, pass, domain),
 * key = seed.  Same seed, pass and id -> same numbers on any device. */
typedef struct {
    philox4x32_ctr_t c;
    philox4x32_key_t k;
    philox4x32_ctr_t r;
    int used;
} Rng;

inline void rng_init(Rng* g, uint id, uint pass, uint domain, uint seed_lo, uint seed_hi) {
    g->c.v[0] = id; g->c.v[1] = 0u; g->c.v[2] = pass; g->c.v[3] = domain;
    g->k.v[0] = seed_lo; g->k.v[1] = seed_hi;
    g->used = 4;
}

/* uniform in (0, 1]: never 0, so -log(u) is finite.  The block is consumed by shifting, not
 * by indexing (an indexed array would live on the stack), and the function is forced inline:
 * PoCL otherwise calls it, and it is drawn three times per collision. */
HOT float rng_u01(Rng* g) {
    if (g->used == 4) {
        g->r = philox4x32(g->c, g->k);
        g->c.v[1] += 1u;
        g->used = 0;
    }
    const uint x = g->r.v[0];
    g->r.v[0] = g->r.v[1]; g->r.v[1] = g->r.v[2]; g->r.v[2] = g->r.v[3];
    g->used++;
    return ((float)(x >> 8) + 1.0f) * (1.0f / 16777216.0f);
}

/* Roberts' R3 sequence, point i, dimension k: frac(s_k + i a_k), a_k = g^-(k+1), g the root of
 * x^4 = x + 1 (the generalised golden ratio), in 32-bit fixed point so any i is exact.  With a
 * uniform random shift s per pass (Cranley & Patterson 1976) each point is uniform: unbiased,
 * and the points of a pass fill the unit cube evenly in every projection. */
#define R3_A0 3518319155u      /* 2^32 / g   */
#define R3_A1 2882110345u      /* 2^32 / g^2 */
#define R3_A2 2360945575u      /* 2^32 / g^3 */
inline float r3_u01(uint i, uint a, uint shift) {
    return ((float)((i * a + shift) >> 8) + 0.5f) * (1.0f / 16777216.0f);
}

/* Four and two consecutive floats from any float boundary: vload4/vload2's values, loaded inline
 * (PoCL calls its kernel library for every vloadn, which put 7 % of the relief photon pass's time
 * in _cl_vload4). */
inline float4 ld4(__global const float* p) { return (float4)(p[0], p[1], p[2], p[3]); }
inline float2 ld2(__global const float* p) { return (float2)(p[0], p[1]); }

/* ---------------------------------------------------------------- optics */
/* Unpolarised Fresnel reflectance from n1 into n2 at incidence cosine cos_i (> 0). */
inline float fresnel_R(float n1, float n2, float cos_i, float* cos_t_out) {
    cos_i = fmin1(fabs(cos_i), 1.0f);
    if (n1 == n2) { *cos_t_out = cos_i; return 0.0f; }
    float eta = n1 / n2;
    float sin2_t = eta * eta * fmax1(0.0f, 1.0f - cos_i * cos_i);
    if (sin2_t >= 1.0f) { *cos_t_out = 0.0f; return 1.0f; }      /* total internal reflection */
    float cos_t = sqrt1(1.0f - sin2_t);
    *cos_t_out = cos_t;
    float rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
    float rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i);
    return 0.5f * (rs * rs + rp * rp);
}

/* Henyey-Greenstein: cosine of the scattering angle, with inv2g = 1/(2g) precomputed (0 for
 * isotropic; the photon pass reads it from the optics table): one division. */
inline float hg_sample_cos_t(float g, float inv2g, float u) {
    if (inv2g == 0.0f) return 2.0f * u - 1.0f;
    const float t = (1.0f - g * g) / (1.0f - g + 2.0f * g * u);
    const float c = (1.0f + g * g - t * t) * inv2g;
    return c < -1.0f ? -1.0f : (c > 1.0f ? 1.0f : c);
}

/* The same from g alone. */
inline float hg_sample_cos(float g, float u) {
    return hg_sample_cos_t(g, fabs(g) < 1e-4f ? 0.0f : 0.5f / g, u);
}

inline float hg_eval(float g, float cos_t) {
    float d = 1.0f + g * g - 2.0f * g * cos_t;
    return (1.0f - g * g) / (4.0f * PI_F * d * sqrt1(d));
}

/* GGX microfacet specular (Walter et al. 2007) times cos(light): the host multiplies by the
 * light's radiant intensity / d^2 (point) or irradiance (collimated).  Shared by the eye pass
 * (PPM) and the path tracer, so both integrators show the same highlight. */
inline float specular_geo(float3 n, float3 v, float3 l, float alpha, float n1, float n2) {
    float nl = dot(n, l), nv = dot(n, v);
    if (nl <= 0.0f || nv <= 0.0f) return 0.0f;
    float3 h = normalize(l + v);
    float nh = dot(n, h);
    float a2 = alpha * alpha;
    float den = nh * nh * (a2 - 1.0f) + 1.0f;
    float D = a2 / (PI_F * den * den);
    float g1l = 2.0f * nl / (nl + sqrt1(a2 + (1.0f - a2) * nl * nl));
    float g1v = 2.0f * nv / (nv + sqrt1(a2 + (1.0f - a2) * nv * nv));
    float ct;
    float F = fresnel_R(n1, n2, dot(h, l), &ct);
    return D * g1l * g1v * F / (4.0f * nl * nv) * nl;
}

/* Hot-path arithmetic.  PoCL calls its kernel library for cos/sin (with a general argument
 * reduction), log (SLEEF, 1 ulp), normalize (overflow-safe scaling) and even fmax/dot, out of
 * line: profiling the photon pass under PoCL (perf, skin slab at 550 nm) put 31 % of the
 * kernel's time in cos/sin of the azimuth, 15 % in log and 10 % in normalize.  The azimuth and
 * the free path only need a uniform angle and -ln(u) for u in (0, 1], so both are done here
 * without library calls, accurate to a few float32 ulp (tests/test_optics_kernels.py). */

/* unit vector, for vectors whose length is far from 0 and overflow (all directions here).
 * rsqrt, not native_rsqrt: native_'s precision is the implementation's (Intel's CPU runtime
 * gives 1 - 2^-24 for 1, so a unit vector such as a pencil beam's (0, 0, -1) came out as
 * -0.99999994); PoCL computes both the same way (same bytes). */
inline float3 unit3(float3 v) {
    return v * rsqrt(v.x * v.x + v.y * v.y + v.z * v.z);
}

/* -ln(u) for u in (0, 1] (never 0: rng_u01).  u = m 2^e with m in [sqrt(1/2), sqrt(2)),
 * ln m = 2 atanh(s), s = (m - 1)/(m + 1), |s| <= 0.1716: the series to s^9 leaves < 1e-9. */
inline float neg_log_u01(float u) {
    uint bits = as_uint(u);
    int e = (int)(bits >> 23) - 127;
    float m = as_float((bits & 0x007fffffu) | 0x3f800000u);     /* [1, 2) */
    if (m > 1.41421356f) { m *= 0.5f; e += 1; }
    const float s = (m - 1.0f) / (m + 1.0f);
    const float s2 = s * s;
    const float lnm = 2.0f * s * (1.0f + s2 * (1.0f / 3.0f + s2 * (0.2f + s2 * (1.0f / 7.0f
                      + s2 * (1.0f / 9.0f)))));
    return -(lnm + (float)e * 0.693147180559945f);
}

/* exp(-x) for x >= 0 without a library call (the beam gather takes one per band and photon):
 * 2^-y, y = x log2(e) = n + f, n an integer, f in [0, 1); 2^-f = 2^-1/2 exp(-t), t = (f - 1/2) ln 2
 * in [-0.347, 0.347] by its Taylor polynomial to t^6 (truncation < 1.3e-7), 2^-n into the exponent
 * bits.  0 for y >= 126 (and for NaN). */
inline float exp_neg(float x) {
    const float y = fmax1(x, 0.0f) * 1.44269504088896f;
    if (!(y < 126.0f)) return 0.0f;
    const float n = floor1(y);
    const float t = (y - n - 0.5f) * 0.693147180559945f;
    const float p = 1.0f - t * (1.0f - t * (0.5f - t * (1.0f / 6.0f - t * (1.0f / 24.0f
                    - t * (1.0f / 120.0f - t * (1.0f / 720.0f))))));
    return as_float((127 - (int)n) << 23) * (p * 0.707106781186548f);
}

/* (cos 2 pi u, sin 2 pi u) for u in [0, 1]: the quadrant from 4u, then a = the remaining angle
 * minus pi/4, |a| <= pi/4, by Taylor polynomials (truncation < 4e-9), and a rotation by pi/4. */
inline float2 azimuth_cs(float u) {
    const float x = 4.0f * u;
    const int iq = (int)x;                                   /* x >= 0: truncation is floor */
    const float fq = (float)iq;
    const int q = iq & 3;
    const float a = (x - fq - 0.5f) * 1.57079632679490f;
    const float a2 = a * a;
    const float sa = a * (1.0f + a2 * (-1.0f / 6.0f + a2 * (1.0f / 120.0f + a2 * (-1.0f / 5040.0f
                     + a2 * (1.0f / 362880.0f)))));
    const float ca = 1.0f + a2 * (-0.5f + a2 * (1.0f / 24.0f + a2 * (-1.0f / 720.0f
                     + a2 * (1.0f / 40320.0f))));
    const float c = (ca - sa) * 0.707106781186548f;          /* cos(a + pi/4) */
    const float s = (ca + sa) * 0.707106781186548f;          /* sin(a + pi/4) */
    return q == 0 ? (float2)(c, s) : q == 1 ? (float2)(-s, c) : q == 2 ? (float2)(-c, -s)
                                                              : (float2)(s, -c);
}

/* Rotate direction d by polar cosine ct and the azimuth with cosine cp, sine sp.  The azimuth
 * is measured in the orthonormal basis (b1, b2) of Duff et al., "Building an orthonormal
 * basis, revisited", JCGT 6(1) 2017: no pole singularity and one division, where MCML's
 * formula needs sqrt(dx^2 + dy^2) and a special case at the poles.  d is assumed unit; the
 * result's length is restored by one Newton step of 1/sqrt around 1 (the error of a unit
 * vector computed in float is ~1e-7, so the step leaves ~1e-14). */
inline float3 rotate_dir_cst(float3 d, float ct, float st, float cp, float sp);

inline float3 rotate_dir_cs(float3 d, float ct, float cp, float sp) {
    const float st2 = 1.0f - ct * ct;
    return rotate_dir_cst(d, ct, st2 > 0.0f ? sqrt1(st2) : 0.0f, cp, sp);
}

/* The same with sin(theta) given (exact where ct rounds to 1). */
inline float3 rotate_dir_cst(float3 d, float ct, float st, float cp, float sp) {
    const float sg = d.z >= 0.0f ? 1.0f : -1.0f;
    const float a = -1.0f / (sg + d.z);
    const float bb = d.x * d.y * a;
    const float3 b1 = (float3)(1.0f + sg * d.x * d.x * a, sg * bb, -sg * d.x);
    const float3 b2 = (float3)(bb, sg + d.y * d.y * a, -d.y);
    const float3 o = (st * cp) * b1 + (st * sp) * b2 + ct * d;
    const float l2 = o.x * o.x + o.y * o.y + o.z * o.z;
    return o * (1.5f - 0.5f * l2);
}

/* The same with the azimuth phi in radians. */
inline float3 rotate_dir(float3 d, float ct, float phi) {
    return rotate_dir_cs(d, ct, cos(phi), sin(phi));
}

/* Scattering: new direction from d at polar cosine ct and azimuth 2 pi u. */
inline float3 scatter_dir(float3 d, float ct, float u) {
    const float2 cs = azimuth_cs(u);
    return rotate_dir_cs(d, ct, cs.x, cs.y);
}

/* Mirror d about unit normal n. */
inline float3 reflect3(float3 d, float3 n) { return d - 2.0f * dot(d, n) * n; }

/* Refract d through the interface with unit normal n facing the incoming side (dot(d,n) < 0). */
inline float3 refract3(float3 d, float3 n, float eta, float cos_i, float cos_t) {
    return unit3(eta * d + (eta * cos_i - cos_t) * n);
}

/* Fresnel decision at a face of the staircase, shared by the photon pass and the path tracer's
 * walk (the same decision for the same inputs): gn the face's geometric normal and sn the
 * shading normal (surface.h face_normal; gn at flat interfaces), both pointing from the current
 * medium into the next; sn gives way to gn where the direction does not cross it.  u: the
 * uniform that decides.  Returns 1 (transmitted, dir refracted) or 0 (reflected).  A reflection
 * must stay on this side of the face, a transmission must cross it (mirrored at gn otherwise).
 * float4 with w = 0: no 3-vectors across calls (surface.h). */
inline int fresnel_cross(float4* dir, float4 gn4, float4 sn4, float n1, float n2, float u) {
    const float3 d = (*dir).xyz, gn = gn4.xyz;
    float3 sn = sn4.xyz;
    float ci = dot(d, sn);
    if (ci <= 1e-6f) { sn = gn; ci = dot(d, gn); }
    float ct;
    const float R = fresnel_R(n1, n2, ci, &ct);
    if (u < R) {
        float3 r = reflect3(d, sn);
        if (dot(r, gn) > 0.0f) r = reflect3(r, gn);
        *dir = (float4)(unit3(r), 0.0f);
        return 0;
    }
    float3 t = refract3(d, -sn, n1 / n2, ci, ct);
    if (dot(t, gn) <= 0.0f) t = reflect3(t, gn);
    *dir = (float4)(unit3(t), 0.0f);
    return 1;
}

/* ---------------------------------------------------------------- volume geometry */
inline int col_index(__constant const Params* P, int ix, int iy) { return iy * P->nx + ix; }

inline float iface_z(__constant const float4* iface, __global const float* heights,
                     __constant const Params* P, int k, int col) {
#ifdef FLAT
    return IF_Z(k);
#else
    int v = IF_VAR(k);
    return v < 0 ? IF_Z(k) : heights[(size_t)v * (size_t)(P->nx * P->ny) + (size_t)col];
#endif
}

/* Layer containing height z in column col: -1 above the surface, NL below the bottom.
 * Starts from a guess and walks, since neighbouring columns differ by little. */
inline int layer_at(__constant const float4* iface, __global const float* heights,
                    __constant const Params* P, int col, float z, int guess) {
    int L = clamp1(guess, -1, NL);
    while (L >= 0 && z > iface_z(iface, heights, P, L, col)) L--;
    while (L < NL && z <= iface_z(iface, heights, P, L + 1, col)) L++;
    return L;
}

/* Tracking state shared by photons and eye rays. */
typedef struct {
    float3 pos, dir;
    int L;          /* current layer */
    int ix, iy;     /* current column (unused with FLAT and lateral infinite) */
#if NINC > 0
    int inside;     /* bit i: inside inclusion i (inclusion.h) */
#endif
} Track;

enum { EV_NONE = 0, EV_TOP, EV_BOTTOM, EV_WALL_X, EV_WALL_Y, EV_ZONE, EV_DOMAIN_X, EV_DOMAIN_Y };

/* The domain sides (x0 .. x0 + xw, y0 .. y0 + yw) when they come before *best along d from p.
 * The domain is convex and p inside, so if the end point p + best d is inside no side is
 * crossed: two products and four comparisons replace two divisions on almost every step. */
inline void domain_sides(float3 p, float3 d, __constant const Params* P, float* best, int* e) {
    if (*best < BIG) {
        const float ex = p.x + *best * d.x, ey = p.y + *best * d.y;
        if (ex >= P->x0 && ex <= P->x0 + P->xw && ey >= P->y0 && ey <= P->y0 + P->yw) return;
    }
    if (d.x != 0.0f) {
        float w = d.x > 0.0f ? P->x0 + P->xw : P->x0;
        float s = (w - p.x) / d.x;
        if (s < *best) { *best = s; *e = EV_DOMAIN_X; }
    }
    if (d.y != 0.0f) {
        float w = d.y > 0.0f ? P->y0 + P->yw : P->y0;
        float s = (w - p.y) / d.y;
        if (s < *best) { *best = s; *e = EV_DOMAIN_Y; }
    }
}

/* Column of a position (clamped into the grid). */
inline void locate_column(Track* t, __constant const Params* P) {
#ifndef FLAT
    t->ix = clamp1((int)floor1((t->pos.x - P->x0) / P->dx), 0, P->nx - 1);
    t->iy = clamp1((int)floor1((t->pos.y - P->y0) / P->dy), 0, P->ny - 1);
#endif
}

/* Result of moving across a lateral wall: 0 = stays inside, 1 = left the domain (open). */
inline int cross_wall(Track* t, __constant const Params* P, int axis, int domain_only) {
    float3 d = t->dir;
    if (axis == 0) {
        int step = d.x > 0.0f ? 1 : -1;
        int nix = t->ix + step;
        int at_edge = domain_only || nix < 0 || nix >= P->nx;
        if (!domain_only) t->pos.x = P->x0 + P->dx * (float)(t->ix + (step > 0 ? 1 : 0));
        if (at_edge) {
            if (P->lateral != 2) return 1;
            /* periodic: re-enter at the opposite side */
            if (step > 0) { t->pos.x = P->x0; nix = 0; } else { t->pos.x = P->x0 + P->xw; nix = P->nx - 1; }
        }
        t->ix = nix;
    } else {
        int step = d.y > 0.0f ? 1 : -1;
        int niy = t->iy + step;
        int at_edge = domain_only || niy < 0 || niy >= P->ny;
        if (!domain_only) t->pos.y = P->y0 + P->dy * (float)(t->iy + (step > 0 ? 1 : 0));
        if (at_edge) {
            if (P->lateral != 2) return 1;
            if (step > 0) { t->pos.y = P->y0; niy = 0; } else { t->pos.y = P->y0 + P->yw; niy = P->ny - 1; }
        }
        t->iy = niy;
    }
    return 0;
}

#endif
