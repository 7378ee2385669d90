/* Path tracer: unbiased ground truth for flat layered skin under a point light.
 *
 * One work item owns one pixel and traces the pass's N eye paths of it in order, adding each
 * path's value into the pixel's float64 accumulator of the path's band (no races, fixed order:
 * the bytes do not depend on the launch partition).  Path s of pixel q in pass p draws from
 * Philox keyed by (seed, p, q N + s), domain 5.  Band of the k-th sample of a pixel (k = p N + s):
 * (k + h(q)) mod NB, h a hash of the pixel (stratified bands; the host knows every count).
 *
 * Eye path (the adjoint of the photon pass).  Pinhole ray as eye.cl builds it, jittered over
 * the pixel; at the surface: the GGX highlight (as eye.cl) plus refraction with the Fresnel
 * transmittance weight tw and the radiance factor (n_outside/n_0)^2 (the reflected branch sees
 * black sky: the point light cannot be hit).  Inside: exact free flight with a residual optical
 * depth (photon.cl), absorption by weight (albedo), HG scattering, Fresnel at every index change
 * sampled (reflect with R, refract with 1 - R and radiance factor (n_from/n_to)^2), out through
 * the top, a finite bottom or an open side ends the path, unbiased roulette.
 *
 * Next-event estimation at every scattering vertex: the light reaches the vertex along specular
 * chains through the flat interfaces, the direct one (refracted straight down to the vertex)
 * and ones with Fresnel reflections at interfaces (a reflection below the vertex brings the
 * light up to it).  One chain is sampled per vertex (backwards from the vertex: reflect at an
 * interface with probability ~ its normal-incidence R0), weighted by (product of R or T at the
 * solved angles) / (selection probability): the sum over all chains is estimated without bias.
 * All segments share p = n sin(theta) (Snell; reflection keeps it).  With H_k the total vertical
 * distance the chain runs in medium k (air: the light's height above the surface), the lateral
 * offset is rho(p) = p S(p), S(p) = sum_k H_k / sqrt(n_k^2 - p^2), increasing and convex in p;
 * rho(p) = rho_target (vertex to light, horizontally) is solved by Newton from the air-only
 * root (an upper bound: the tissue terms only add offset), which converges monotonically on a
 * convex function, safeguarded by a bisection bracket; in float64 where the device has it.
 *
 * Divergence of the point source through the planes.  Emission angles (theta0, phi) in air,
 * dOmega = sin theta0 dtheta0 dphi.  The chain lands on the vertex's horizontal plane at
 * distance rho(p) from below the light, azimuth phi: dA_h = rho drho dphi = rho rho'(p) dp dphi,
 * and p = n_air sin theta0 gives dp = n_air cos theta0 dtheta0.  So
 *     dOmega/dA_h = sin theta0 / (n_air rho rho'(p) cos theta0) = p / (n_air^2 rho cos theta0 rho'(p))
 *                 = 1 / (n_air^2 cos theta0 S(p) rho'(p)),   rho'(p) = sum_k H_k n_k^2 / (n_k^2 - p^2)^(3/2)
 * (the last form is finite at p = 0).  n = 1 everywhere: rho = H tan theta, rho' = H / cos^3,
 * dOmega/dA_h = cos^3 theta / H^2 = cos theta / r^2.  The irradiance on the plane normal to the
 * light's direction at the vertex is E_perp = I T_F T_att (dOmega/dA_h) / cos theta_L,
 * T_F the Fresnel factors, T_att = exp(-sum_k mu_t,k H_k / cos theta_k), theta_L the angle in
 * the vertex's layer.  The contribution is beta * HG(cos(light travel dir, to-eye dir)) * E_perp;
 * the kernel works per unit intensity (um^-2) and the host multiplies by I_b = P s_b / 4 pi,
 * 1e12 um^2/m^2 and 1/dlambda: the PPM units.  A chain whose surface crossing falls outside the
 * model's footprint (lateral open or periodic) gives 0: no skin there (photons miss it too);
 * the in-tissue part then stays inside too, as its horizontal projection is the straight segment
 * from the crossing to the vertex.  Periodic sides: the light's images one period away are
 * connected as well (a photon entering the footprint reaches the vertex through the wrap).
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable      /* the accumulators are double (as gather.cl) */
#include "common.h"
#include "camera.h"
#include "inclusion.h"
#include "maps.h"

#ifdef PT_FP64
#define REL_TOL 1e-15
#else
#define REL_TOL 1e-7f
#endif
#ifndef CLPPM_REAL              /* (smooth builds: common.h has included surface.h) */
#ifdef PT_FP64
typedef double real;
#else
typedef float real;
#endif
#define CLPPM_REAL              /* surface.h: real is defined */
#endif

/* Mirrors clppm/integrators/pathtracer.py PT_DTYPE: 4-byte fields only, in this order. */
typedef struct {
    Camera cam;
    int nspp;                   /* samples per pixel in this pass */
    uint pass_;
    uint band0;                 /* (pass * nspp) mod NB */
    uint pix_offset, count;     /* pixels of this launch */
    uint seed_lo, seed_hi;
    float lx, ly, lz;           /* point light (um) */
    float alpha;                /* GGX roughness */
    int specular;
    float rr_threshold;         /* roulette below this fraction of the weight after entry */
    float rr_m;                 /* survive with probability 1/rr_m */
    int max_vertices;           /* safety bound per path (counted as cut) */
    float nee_od;               /* NEE roulette: optical depth straight up beyond which ... */
    float nee_q_floor;          /* ... the connection is made with probability exp(nee_od - od) */
    float mnee_trials;          /* relief: random trials of manifold sampling per connection, on average */
} PtParams;

#define MAXE (4 * NL + 8)       /* chain events; a longer chain (R^4 smaller) counts as blocked */
#if NINC > 0 || defined(MAPS)
#define CHAIN_LEGS              /* relief connections keep their legs' points (mnee.h Trace.pe) to walk
                                   them through the inclusions and maps (mnee_legs_factor) */
#endif
#define NMNEE 10                /* solver counts per pixel (clppm/integrators/pathtracer.py MNEE_STATS) */
/* Counts of specular manifold sampling over a pixel's connections (relief builds) */
typedef struct { uint found, other, trials, clamped; } SmsStat;
#define NBIN 8                  /* contribution by vertex index: 1, 2, 3, 4, 5-8, 9-16, 17-64, 65+ */

/* The chain tables (host, clppm/integrators/pathtracer.py chain_tables): r0[i] normal-incidence Fresnel R
 * of interface i (0 where the indices are equal or below a semi-infinite layer) and
 * tail[i] = sum_{j >= i} r0[j]; 2 NL + 3 floats. */
#define R0(i) (chain[(i)])
#define TAIL(i) (chain[NL + 1 + (i)])

inline uint lowbias32(uint x) {
    x ^= x >> 16; x *= 0x7feb352du; x ^= x >> 15; x *= 0x846ca68bu; x ^= x >> 16;
    return x;
}

inline int vertex_bin(int v) {
    return v <= 4 ? v - 1 : (v <= 8 ? 4 : (v <= 16 ? 5 : (v <= 64 ? 6 : 7)));
}

/* n of the medium on the other side of interface i seen from layer k */
inline float n_across(__constant const Params* P, __constant const float* layer_n, int i, int k) {
    const int o = (i == k) ? k - 1 : k + 1;
    return o < 0 ? P->n_above : (o >= NL ? P->n_below : layer_n[o]);
}

/* ---------------------------------------------------------------- specular chains */
typedef struct {
    real H[NL];                 /* vertical distance run in each layer (um) */
#ifndef FLAT
    real zref[NL + 1];          /* the interfaces' heights at the vertex (mnee.h continuation) */
#endif
    real Hair;                  /* the light's height above the surface */
    int ne;
    int ev[MAXE];               /* interface | from layer << 8 | reflected << 16, vertex first */
    float wsel;                 /* probability of having sampled this chain */
    int up;                     /* 1: the light arrives at the vertex travelling down */
#if NINC > 0
    int inside;                 /* the vertex's inclusion bits (relief: mnee_legs_factor) */
#endif
} Chain;

inline real thick(__constant const float4* iface, int k) { return (real)IF_Z(k) - (real)IF_Z(k + 1); }

/* Build a chain backwards from the vertex (layer k, height zv).  sampled = 1: reflections are
 * drawn (probabilities as above); sampled = 0: the direct chain (force_j < 0) or the one
 * reflected once at interface force_j below the vertex.  Returns 0 if the chain cannot carry
 * light (out through the bottom, too long). */
inline int chain_build(Chain* ch, int k, float zv, float lz, int sampled, int force_j, Rng* rng,
                       __constant const float4* iface, __constant const float* chain) {
    for (int i = 0; i < NL; ++i) ch->H[i] = 0;
    ch->ne = 0; ch->wsel = 1.0f;
    ch->Hair = (real)lz - (real)IF_Z(0);
    int up = 1;
    if (sampled) {
        const float qd = fmin(TAIL(k + 1), 0.5f);
        if (qd > 0.0f) {
            up = rng_u01(rng) > qd;
            ch->wsel *= up ? 1.0f - qd : qd;
        }
    } else {
        up = force_j < 0;
    }
    ch->up = up;
    ch->H[k] = up ? (real)IF_Z(k) - (real)zv : (real)zv - (real)IF_Z(k + 1);
    for (int guard = 0; guard < MAXE; ++guard) {
        if (ch->ne == MAXE) return 0;
        if (up) {
            const int i = k;
            int refl = 0;
            if (sampled && R0(i) > 0.0f && TAIL(i + 1) > 0.0f) {
                const float r = fmin(R0(i), 0.5f);
                refl = rng_u01(rng) <= r;
                ch->wsel *= refl ? r : 1.0f - r;
            }
            ch->ev[ch->ne++] = i | (k << 8) | (refl << 16);
            if (refl) { up = 0; ch->H[k] += thick(iface, k); continue; }
            if (k == 0) return 1;                           /* into the air: complete */
            k -= 1;
            ch->H[k] += thick(iface, k);
        } else {
            const int i = k + 1;
            int refl;
            if (sampled) {
                if (TAIL(i) <= 0.0f) return 0;              /* nothing below reflects */
                const float r = fmin(R0(i) / TAIL(i), 1.0f);
                refl = r >= 1.0f || rng_u01(rng) <= r;
                ch->wsel *= refl ? r : 1.0f - r;
            } else {
                refl = i == force_j;
            }
            if (IF_Z(i) < -1e29f) return 0;                 /* a semi-infinite layer has no bottom */
            ch->ev[ch->ne++] = i | (k << 8) | (refl << 16);
            if (refl) { up = 1; ch->H[k] += thick(iface, k); continue; }
            if (i >= NL) return 0;                          /* out through the bottom */
            k += 1;
            ch->H[k] += thick(iface, k);
        }
    }
    return 0;
}

/* Solve rho(p) = rt for the chain; returns p and S(p), rho'(p). */
inline real solve_p(const Chain* ch, real rt, real na, __constant const float* layer_n,
                    real* S_out, real* dR_out) {
    real pmax = na;
    for (int k = 0; k < NL; ++k)
        if (ch->H[k] > 0) pmax = fmin(pmax, (real)layer_n[k]);
    const real p0 = rt > 0 ? na * rt / sqrt(rt * rt + ch->Hair * ch->Hair) : 0;
    real lo = 0, hi = fmin(p0, pmax);
    real p = p0 < pmax ? p0 : 0.5 * hi;
    real S = 0, dR = 0;
    for (int it = 0; it < 100; ++it) {
        const real a2 = na * na - p * p;
        const real ra = 1 / sqrt(a2);
        S = ch->Hair * ra;
        dR = ch->Hair * na * na * ra * ra * ra;
        for (int k = 0; k < NL; ++k) {
            const real h = ch->H[k];
            if (h > 0) {
                const real n = layer_n[k];
                const real r = 1 / sqrt(n * n - p * p);
                S += h * r;
                dR += h * n * n * r * r * r;
            }
        }
        if (rt <= 0) break;
        const real f = p * S - rt;
        if (f == 0) break;
        if (f > 0) hi = p; else lo = p;
        real pn = p - f / dR;
        if (!(pn > lo && pn < hi)) pn = 0.5 * (lo + hi);
        if (fabs(pn - p) <= REL_TOL * p || hi - lo <= REL_TOL * hi) { p = pn; rt = -rt; continue; }
        p = pn;
    }
    /* (rt < 0 marks "converged: evaluate S, rho' once more at the final p and stop") */
    *S_out = S; *dR_out = dR;
    return p;
}

/* The light's irradiance factor at the vertex along chain ch (per unit intensity and excluding
 * the phase function): T_F T_att (dOmega/dA_h) / cos theta_L / (selection probability).
 * v, lpos: the vertex's and the light's (or its periodic image's) horizontal position (float2,
 * not float3: with float3 arguments Intel's CPU compiler 2026.2 gave the right light position
 * to some of its vectorised lanes only; no 3-vector crosses a call in the relief code either,
 * mnee.h).  shift: the image offset (the footprint test
 * uses the footprint shifted back).  *dirL: the light's travel direction at the vertex. */
inline float connect(const Chain* ch, float2 v, int Lv, float2 lpos, float2 shift, int b,
                     __constant const Params* P, __constant const float* layer_n,
                     __global const float4* optics, float3* dirL, real* p_out, real* G_out) {
    const real dx = (real)lpos.x - (real)v.x, dy = (real)lpos.y - (real)v.y;
    const real rt = sqrt(dx * dx + dy * dy);
    const real na = P->n_above;
    real S, dR;
    const real p = solve_p(ch, rt, na, layer_n, &S, &dR);
    *p_out = p;
    const real ca = sqrt(fmax((real)0, 1 - (p / na) * (p / na)));
    const real ux = rt > 0 ? dx / rt : 1, uy = rt > 0 ? dy / rt : 0;
    if (P->lateral != 0) {
        /* surface crossing: Hair tan(theta0) from below the light toward the vertex */
        const real back = ca > 0 ? ch->Hair * (p / na) / ca : 0;
        const float sx = (float)((real)lpos.x - back * ux) + shift.x;
        const float sy = (float)((real)lpos.y - back * uy) + shift.y;
        if (sx < P->x0 || sx > P->x0 + P->xw || sy < P->y0 || sy > P->y0 + P->yw) { *G_out = 0; return 0.0f; }
    }
    const real nL = layer_n[Lv];
    const real sL = p / nL;
    const real cL = sqrt(fmax((real)0, 1 - sL * sL));
    const real G = 1 / (na * na * ca * S * dR * cL);
    *G_out = G;
    /* attenuation along the chain and the Fresnel factors of its events */
    real od = 0;
    for (int k = 0; k < NL; ++k) {
        const real h = ch->H[k];
        if (h > 0) {
            const real n = layer_n[k];
            od += (real)optics[k * NB + b].w * h / sqrt(fmax((real)1e-300, 1 - (p / n) * (p / n)));
        }
    }
    float F = 1.0f;
    for (int e = 0; e < ch->ne; ++e) {
        const int i = ch->ev[e] & 255, k = (ch->ev[e] >> 8) & 255, refl = ch->ev[e] >> 16;
        const float n1 = layer_n[k], n2 = n_across(P, layer_n, i, k);
        const float sk = (float)(p / (real)n1);
        float ct;
        const float R = fresnel_R(n1, n2, sqrt(fmax(0.0f, 1.0f - sk * sk)), &ct);
        F *= refl ? R : 1.0f - R;
    }
    *dirL = (float3)((float)(-sL * ux), (float)(-sL * uy), (float)(ch->up ? -cL : cL));
    if (!(G > 0) || !isfinite((float)G)) return 0.0f;
    return (float)G * F * exp(-(float)od) / ch->wsel;
}

#if NINC > 0
/* The optical depth that inclusions add to one straight leg of a light connection in layer k,
 * band b: from (px, py, pz) along the unit (dx, dy, dz) for len, walked through the quadrics as a
 * flight is (next_inclusion: an inclusion whose box the leg's misses is skipped), with mu_t of
 * the inclusion instead of the layer's where the leg is inside one.  *inside: the inclusion bits
 * at the leg's start, on return at its end (an inclusion can straddle layers: the next leg
 * starts inside it).  Scalars only across the call (Intel's float3 miscompilation, connect). */
inline float leg_inclusion_od(float px, float py, float pz, float dx, float dy, float dz, float len, int k,
                              int* inside, int b, __global const float4* optics) {
    const float3 pos = (float3)(px, py, pz), d = (float3)(dx, dy, dz);
    const float3 end = pos + len * d;
    const int near = inclusions_near(optics, fmin(pos.x, end.x), fmax(pos.x, end.x), fmin(pos.y, end.y),
                                     fmax(pos.y, end.y), fmin(pos.z, end.z), fmax(pos.z, end.z));
    const float mut_k = optics[k * NB + b].w;
    int in = *inside;
    float od = 0.0f, done = 0.0f;
    for (int guard = 0; guard < 2 * NINC + 2 && done < len && (near | in); ++guard) {
        int which = -1;
        const float s = fmin(next_inclusion(optics, pos + done * d, d, in, near, &which), len - done);
        if (in) od += (optics[material_of(k, in) * NB + b].w - mut_k) * s;
        done += s;
        if (done < len && which >= 0) in ^= 1 << which;
    }
    *inside = in;
    return od;
}

/* The optical depth that inclusions add to a flat chain's attenuation in band b: the chain's
 * legs from the vertex (x, y, zv; inclusion bits inside) back toward the light, each a straight
 * line in one layer k at horizontal slowness p (sin = p / n_k along (ux, uy), the light's
 * horizontal direction from the vertex) up or down to its event's interface, by
 * leg_inclusion_od.  Scalars only across the call (connect). */
inline float chain_inclusion_od(const Chain* ch, float x, float y, float zv, int inside, float ux, float uy,
                                float p, int b, __constant const float4* iface,
                                __constant const float* layer_n, __global const float4* optics) {
    float3 pos = (float3)(x, y, zv);
    int up = ch->up;
    float od = 0.0f;
    for (int e = 0; e < ch->ne; ++e) {
        const int i = ch->ev[e] & 255, k = (ch->ev[e] >> 8) & 255, refl = ch->ev[e] >> 16;
        const float sk = p / layer_n[k], ck = sqrt(fmax(0.0f, 1.0f - sk * sk));
        const float3 d = (float3)(sk * ux, sk * uy, up ? ck : -ck);
        const float len = ck > 0.0f ? fabs(IF_Z(i) - pos.z) / ck : 0.0f;
        od += leg_inclusion_od(pos.x, pos.y, pos.z, d.x, d.y, d.z, len, k, &inside, b, optics);
        pos += len * d;
        pos.z = IF_Z(i);
        if (refl) up = !up;
    }
    return od;
}
#endif

#ifdef MAPS
/* The factor by which chromophore maps change a flat chain's attenuation in band b: the chain's
 * legs from the vertex (x, y, zv) back toward the light as chain_inclusion_od walks them, each
 * leg in a mapped layer by map_leg_factor (maps.h: ratio tracking of the map's change of mu_a
 * along it).  Scalars only across the call (connect). */
inline float chain_map_factor(const Chain* ch, float x, float y, float zv, float ux, float uy, float p, int b,
                              Rng* rng, __constant const Params* P, __constant const float4* iface,
                              __constant const float* layer_n, __global const float4* optics) {
    float px = x, py = y, pz = zv;
    int up = ch->up;
    float T = 1.0f;
    for (int e = 0; e < ch->ne; ++e) {
        const int i = ch->ev[e] & 255, k = (ch->ev[e] >> 8) & 255, refl = ch->ev[e] >> 16;
        const float sk = p / layer_n[k], ck = sqrt(fmax(0.0f, 1.0f - sk * sk));
        const float len = ck > 0.0f ? fabs(IF_Z(i) - pz) / ck : 0.0f;
        const int first = map_first(optics, k);
        if (first >= 0 && len > 0.0f)
            T *= map_leg_factor(optics, k, b, first, px, py, pz, sk * ux, sk * uy, (IF_Z(i) - pz) / len, len, P, rng);
        px += len * sk * ux;
        py += len * sk * uy;
        pz = IF_Z(i);
        if (refl) up = !up;
    }
    return T;
}
#endif

#ifndef FLAT
#include "mnee.h"

/* The layer of height z at (x, y) among the smooth surfaces (mnee.h), starting from the voxel
 * model's layer L: the two differ within half a voxel of an interface.  -1: above the surface. */
inline int smooth_layer(__constant const Params* P, __constant const float4* iface,
                        __global const float* smooth, real4 v, int L) {
    HF f;
    for (int g = 0; g < 2 * NL + 2; ++g) {
        if (L >= 0) { hf_eval(P, iface, smooth, L, v.x, v.y, &f); if (v.z > f.h) { L--; continue; } }
        if (L + 1 < NL) { hf_eval(P, iface, smooth, L + 1, v.x, v.y, &f); if (v.z <= f.h) { L++; continue; } }
        break;
    }
    return L;
}

/* The chain's vertical runs H_k and the light's height above the surface on the planes through
 * the smooth surfaces' heights below the vertex: the flat problem whose solution seeds Newton. */
inline void chain_local_H(Chain* ch, real4 v, real lz, __constant const Params* P,
                          __constant const float4* iface, __global const float* smooth) {
    for (int k = 0; k < NL; ++k) ch->H[k] = 0;
    real z = v.z;
    HF f;
    for (int e = 0; e < ch->ne; ++e) {
        const int i = ch->ev[e] & 255, k = (ch->ev[e] >> 8) & 255;
        hf_eval(P, iface, smooth, i, v.x, v.y, &f);
        ch->zref[i] = f.h;
        ch->H[k] += fabs(f.h - z);
        z = f.h;
    }
    ch->Hair = lz - z;
}

/* The flat seed: the momentum of the flat solution on the planes through the interfaces'
 * heights at the vertex (chain_local_H). */
inline void mnee_seed(Chain* ch, real4 v, real4 l, __constant const Params* P,
                      __constant const float4* iface, __constant const float* layer_n,
                      __global const float* smooth, real* ux, real* uy) {
    chain_local_H(ch, v, l.z, P, iface, smooth);
    const real dx = l.x - v.x, dy = l.y - v.y;
    const real rt = sqrt(dx * dx + dy * dy);
    real S, dR;
    const real p = solve_p(ch, rt, (real)P->n_above, layer_n, &S, &dR);
    *ux = rt > 0 ? p * dx / rt : 0;
    *uy = rt > 0 ? p * dy / rt : 0;
}

/* The factor of a converged trace, as connect() gives it: G, Fresnel, attenuation, over the
 * chain's selection probability; 0 where the surface crossing is off the model. */
inline float mnee_factor(const Trace* T, const Chain* ch, float2 shift, int b,
                         __constant const Params* P, __global const float4* optics, float4* dirL) {
    if (P->lateral != 0) {
        const float sx = (float)T->s.x + shift.x, sy = (float)T->s.y + shift.y;
        if (sx < P->x0 || sx > P->x0 + P->xw || sy < P->y0 || sy > P->y0 + P->yw) return 0.0f;
    }
    const real G = mnee_G(T, (real)P->n_above);
    real od = 0;
    for (int k = 0; k < NL; ++k)
        if (T->len[k] > 0) od += (real)optics[k * NB + b].w * T->len[k];
    *dirL = (float4)((float)-T->d0.x, (float)-T->d0.y, (float)-T->d0.z, 0.0f);
    if (!(G > 0) || !isfinite((float)G)) return 0.0f;
    return (float)G * T->F * exp(-(float)od) / ch->wsel;
}

#ifdef CHAIN_LEGS
/* The factor by which inclusions and maps change the attenuation of a converged connection
 * through the relief (trace T of chain ch) in band b: its legs from the vertex v (inclusion bits
 * ch->inside) through the events' points T->pe, each a straight segment in its event's layer
 * (between two interface points, or from the vertex to the first), by leg_inclusion_od and
 * map_leg_factor as on flat layers (chain_inclusion_od, chain_map_factor). */
inline float mnee_legs_factor(const Trace* T, const Chain* ch, real4 v, int b, Rng* rng,
                              __constant const Params* P, __global const float4* optics) {
    float px = (float)v.x, py = (float)v.y, pz = (float)v.z;
    float F = 1.0f;
#if NINC > 0
    int inside = ch->inside;
    float od = 0.0f;
#endif
    for (int e = 0; e < ch->ne; ++e) {
        const int k = (ch->ev[e] >> 8) & 255;
        const float4 q = T->pe[e];
        const float ex = q.x - px, ey = q.y - py, ez = q.z - pz;
        const float len = sqrt(ex * ex + ey * ey + ez * ez);
        if (len > 0.0f) {
            const float dx = ex / len, dy = ey / len, dz = ez / len;
#if NINC > 0
            od += leg_inclusion_od(px, py, pz, dx, dy, dz, len, k, &inside, b, optics);
#endif
#ifdef MAPS
            const int first = map_first(optics, k);
            if (first >= 0) F *= map_leg_factor(optics, k, b, first, px, py, pz, dx, dy, dz, len, P, rng);
#endif
        }
        px = q.x; py = q.y; pz = q.z;
    }
#if NINC > 0
    F *= exp(-od);
#endif
    return F;
}
#endif

/* The connection through the height fields (mnee.h) from the flat seed: as connect(), with the
 * solver's outcome in *st. */
inline float connect_mnee(Chain* ch, real4 v, int Ls, float4 lpos, float2 shift, int b,
                          __constant const Params* P, __constant const float4* iface,
                          __constant const float* layer_n, __global const float4* optics,
                          __global const float* smooth, float4* dirL, MneeStat* st, Trace* T) {
    const real4 l = R4((real)lpos.x, (real)lpos.y, (real)lpos.z);
    real ux, uy;
    mnee_seed(ch, v, l, P, iface, layer_n, smooth, &ux, &uy);
    if (!mnee_solve(ch, v, Ls, &ux, &uy, l, P, iface, layer_n, smooth, T, st)) return 0.0f;
    return mnee_factor(T, ch, shift, b, P, optics, dirL);
}

#ifdef PT_FP64
#define MN_SAME 1e-6            /* two converged momenta closer than this are one solution */
#else
#define MN_SAME 1e-4f
#endif
#define MN_SMS_SIGMA 0.2        /* momentum spread of the random seeds around the flat seed */
#define MN_SMS_CAP 256          /* trials to a solution's recurrence, then clamped (counted) */

/* One random trial: Newton on the surfaces from a seed u0 + N(0, sigma^2) in each component of
 * the momentum (Box-Muller; full support, so every solution's basin has a chance). */
inline int sms_trial(const Chain* ch, real4 v, int Ls, real u0x, real u0y, real4 l, Rng* rng,
                     __constant const Params* P, __constant const float4* iface,
                     __constant const float* layer_n, __global const float* smooth,
                     real* ux, real* uy, Trace* T, MneeStat* st) {
    const float r = MN_SMS_SIGMA * sqrt(2.0f * neg_log_u01(rng_u01(rng)));
    const float ph = 2.0f * PI_F * rng_u01(rng);
    *ux = u0x + (real)(r * cos(ph)); *uy = u0y + (real)(r * sin(ph));
    MneeStat s2;
    s2.iters = 0; s2.halvings = 0; s2.cont = 0; s2.traces = MN_BUDGET - MN_SEED_BUDGET;
    const int ok = mnee_newton(ch, v, Ls, ux, uy, l, 1, P, iface, layer_n, smooth, T, &s2);
    st->iters += s2.iters;
    return ok;
}

/* How many random trials a connection makes: the whole part of the mean t, and one more with
 * the probability of its fraction (a draw only when t is not whole), so E[n] = t.  A trial costs
 * a Newton solve and rarely finds a solution the flat seed missed, so a mean below 1 trades a
 * little of that rare light's noise for most of the connection's time. */
inline int sms_count(float t, Rng* rng) {
    const float w = floor(t);
    return (int)w + ((t > w && rng_u01(rng) < t - w) ? 1 : 0);
}

inline int same_solution(real ax, real ay, real bx, real by) {
    return fabs(ax - bx) + fabs(ay - by) < MN_SAME;
}

/* The number of random trials until the solution a recurs (its estimate of 1/p(a), p the chance
 * that a trial finds a), at most MN_SMS_CAP. */
inline int sms_recurrence(const Chain* ch, real4 v, int Ls, real u0x, real u0y, real4 l, Rng* rng,
                          real ax, real ay, __constant const Params* P, __constant const float4* iface,
                          __constant const float* layer_n, __global const float* smooth,
                          MneeStat* st, SmsStat* ss) {
    for (int n = 1; n < MN_SMS_CAP; ++n) {
        real bx, by;
        Trace T;
        ss->trials++;
        if (sms_trial(ch, v, Ls, u0x, u0y, l, rng, P, iface, layer_n, smooth, &bx, &by, &T, st)
            && same_solution(ax, ay, bx, by)) return n;
    }
    ss->clamped++;
    return MN_SMS_CAP;
}

/* Every light path through the chain, by specular manifold sampling (Zeltner, Georgiev & Jakob
 * 2020, unbiased variant), each with its own phase function value for the path direction wdir.
 * The flat-seeded solution x0 (Newton, continuation: mnee_solve) is added as it is.  The others
 * by random trials (sms_trial), trials of them on average (sms_count): a trial that finds a
 * solution x other than x0 adds f(x) times the number of further trials until x recurs, an
 * estimate of 1/p(x), over the mean number of trials; so the expected sum is that of f over every
 * solution other than x0 that a trial can reach (any: the seeds have full support), whatever
 * their number.  Where the flat-seeded solve fails, the same number of trials find every
 * solution (none is x0).  Bias only from the cap (counted: ss->clamped). */
inline float connect_mnee_sms(Chain* ch, real4 v, int Ls, float4 lpos, float2 shift, int b,
                              float g, float4 wdir, float trials, Rng* rng,
                              __constant const Params* P, __constant const float4* iface,
                              __constant const float* layer_n, __global const float4* optics,
                              __global const float* smooth, MneeStat* st, SmsStat* ss, int* nsol) {
    const real4 l = R4((real)lpos.x, (real)lpos.y, (real)lpos.z);
    real u0x, u0y;
    mnee_seed(ch, v, l, P, iface, layer_n, smooth, &u0x, &u0y);
    float c = 0.0f;
    Trace T;
    float4 dl;
    real sx = u0x, sy = u0y;
    const int have0 = mnee_solve(ch, v, Ls, &sx, &sy, l, P, iface, layer_n, smooth, &T, st);
    if (have0) {
#ifdef CHAIN_LEGS
        float f = mnee_factor(&T, ch, shift, b, P, optics, &dl);
        if (f > 0.0f) f *= mnee_legs_factor(&T, ch, v, b, rng, P, optics);
#else
        const float f = mnee_factor(&T, ch, shift, b, P, optics, &dl);
#endif
        if (f > 0.0f) c += f * hg_eval(g, -dot(dl.xyz, wdir.xyz));
    }
    int ns = have0;
    const int ntrials = sms_count(trials, rng);
    for (int j = 0; j < ntrials; ++j) {
        real ax, ay;
        ss->trials++;
        if (!sms_trial(ch, v, Ls, u0x, u0y, l, rng, P, iface, layer_n, smooth, &ax, &ay, &T, st)) continue;
        if (have0 && same_solution(ax, ay, sx, sy)) continue;
        ss->other++; ns++;
#ifdef CHAIN_LEGS
        float f = mnee_factor(&T, ch, shift, b, P, optics, &dl);
        if (f > 0.0f) f *= mnee_legs_factor(&T, ch, v, b, rng, P, optics);
#else
        const float f = mnee_factor(&T, ch, shift, b, P, optics, &dl);
#endif
        if (!(f > 0.0f)) continue;
        const int n = sms_recurrence(ch, v, Ls, u0x, u0y, l, rng, ax, ay, P, iface, layer_n, smooth, st, ss);
        c += f * hg_eval(g, -dot(dl.xyz, wdir.xyz)) * (float)n / trials;
    }
    ss->found += ns > 0;
    *nsol = ns;
    return c;
}

/* Enter the skin from the air at the first hit of t (an eye ray): Fresnel sampled at the smooth
 * normal; 0 when it misses or is reflected (to the black sky). */
inline int pt_enter(Track* t, VOLUME_ARGS, __global const float* smooth, Rng* rng) {
    float3 gn;
    if (!hit_surface(t, P, iface, heights, &gn)) return 0;
    const float4 sn = smooth_normal(P, iface, smooth, 0, t->pos.x, t->pos.y);
    float4 d = (float4)(t->dir, 0.0f);
    if (!fresnel_cross(&d, (float4)(-gn, 0.0f), -sn, P->n_above, layer_n[0], rng_u01(rng))) return 0;
    t->dir = d.xyz; t->L = 0;
    return 1;
}

/* A boundary event of the eye path in the voxel volume, refracting at the smooth surfaces'
 * normals; *beta takes the radiance factor.  Returns 0 when the path ends. */
inline int pt_boundary(Track* t, int ev, float* beta, Rng* rng, VOLUME_ARGS,
                       __global const float* smooth) {
    if (ev == EV_NONE) return 0;
    if (ev == EV_ZONE) { locate_column(t, P); return 1; }
    const int L = t->L;
    int L2, k;
    float3 gn;
    const int oix = t->ix, oiy = t->iy;
    const float3 opos = t->pos;
    if (ev == EV_TOP || ev == EV_BOTTOM) {
        const int up = ev == EV_TOP;
        L2 = up ? L - 1 : L + 1;
        k = up ? L : L + 1;
        gn = (float3)(0.0f, 0.0f, up ? 1.0f : -1.0f);
#ifdef SMOOTH_SURFACE
        /* the crossing is on the smooth surface itself: its normal is the face's */
        gn = face_normal(P, iface, smooth, k, L, L2, t->pos.x, t->pos.y, (float4)(gn, 0.0f)).xyz;
#else
        t->pos.z = iface_z(iface, heights, P, k, col_index(P, t->ix, t->iy));
#endif
    } else {
        const int axis = (ev == EV_WALL_X || ev == EV_DOMAIN_X) ? 0 : 1;
        const int donly = (ev == EV_DOMAIN_X || ev == EV_DOMAIN_Y);
#ifdef SMOOTH_SURFACE
        /* a tile's wall or a side: the layers do not change across it */
        if (!donly) { cross_cell(t, P, axis); return 1; }
        if (cross_wall(t, P, axis, 1)) return 0;
        locate_column(t, P);
        return 1;
#endif
        if (cross_wall(t, P, axis, donly)) return 0;
        if (donly) locate_column(t, P);
        L2 = layer_at(iface, heights, P, col_index(P, t->ix, t->iy), t->pos.z, L);
        if (L2 == L) return 1;
        k = L2 < L ? L : L + 1;
        gn = axis == 0 ? (float3)(t->dir.x > 0.0f ? 1.0f : -1.0f, 0.0f, 0.0f)
                       : (float3)(0.0f, t->dir.y > 0.0f ? 1.0f : -1.0f, 0.0f);
    }
    const float n1 = layer_n[L];
    const float n2 = L2 < 0 ? P->n_above : (L2 >= NL ? P->n_below : layer_n[L2]);
    if (n1 != n2) {
#ifdef SMOOTH_SURFACE
        const float4 sn = (float4)(gn, 0.0f);
#else
        const float4 sn = face_normal(P, iface, smooth, k, L, L2, t->pos.x, t->pos.y, (float4)(gn, 0.0f));
#endif
        float4 d = (float4)(t->dir, 0.0f);
        const int through = fresnel_cross(&d, (float4)(gn, 0.0f), sn, n1, n2, rng_u01(rng));
        t->dir = d.xyz;
        if (!through) {
            if (ev != EV_TOP && ev != EV_BOTTOM) { t->ix = oix; t->iy = oiy; t->pos = opos; }
            return 1;
        }
        if (L2 < 0) {
            /* out through the relief: across the air to where the ray meets the skin again (the
             * radiance factors out and back in cancel) */
            t->pos += 1e-3f * t->dir;
#if NINC > 0
            if (!pt_enter(t, VOLUME_PASS, smooth, rng)) return 0;
            t->inside = inclusion_mask(optics, t->pos);     /* back in somewhere else (photon.cl) */
            return 1;
#else
            return pt_enter(t, VOLUME_PASS, smooth, rng);
#endif
        }
        if (L2 >= NL) return 0;
        *beta *= (n1 / n2) * (n1 / n2);
    } else if (L2 < 0 || L2 >= NL) {
        return 0;
    }
    t->L = L2;
    return 1;
}
#endif

/* ---------------------------------------------------------------- the pass */
/* A pixel's counts over its samples: vertices, connections made and blocked, paths cut; the
 * manifold solver's (NMNEE, clppm/integrators/pathtracer.py MNEE_STATS); the value by vertex index. */
typedef struct {
    ulong nvert, nmade, nblock, ncut;
    ulong m_try, m_ok, m_it, m_cont, m_mis, m_sol;
    SmsStat ss;
    double bins[NBIN];
} PtStats;

HOT void pt_stats_clear(PtStats* st) {
    st->nvert = 0; st->nmade = 0; st->nblock = 0; st->ncut = 0;
    st->m_try = 0; st->m_ok = 0; st->m_it = 0; st->m_cont = 0; st->m_mis = 0; st->m_sol = 0;
    st->ss.found = 0u; st->ss.other = 0u; st->ss.trials = 0u; st->ss.clamped = 0u;
    for (int i = 0; i < NBIN; ++i) st->bins[i] = 0.0;
}

HOT void pt_stats_add(const PtStats* st, uint pix, __global ulong* pix_stats, __global ulong* pix_mnee,
                      __global double* pix_bins) {
    __global ulong* sp = pix_stats + (size_t)pix * 4;
    sp[0] += st->nvert; sp[1] += st->nmade; sp[2] += st->nblock; sp[3] += st->ncut;
    __global ulong* sm = pix_mnee + (size_t)pix * NMNEE;
    sm[0] += st->m_try; sm[1] += st->m_ok; sm[2] += st->m_it; sm[3] += st->m_cont; sm[4] += st->m_mis;
    sm[5] += st->m_sol;
    sm[6] += st->ss.found; sm[7] += st->ss.other; sm[8] += st->ss.trials; sm[9] += st->ss.clamped;
    for (int i = 0; i < NBIN; ++i) pix_bins[(size_t)pix * NBIN + i] += st->bins[i];
}

/* Interface crossing into the skin where the eye ray hit it (geometric normal gn): the
 * highlight toward the point light (added to *value when asked), then refraction at the smooth
 * surface's normal into layer 0.  Returns the path's radiance factor: the Fresnel transmittance
 * times (n_outside / n_0)^2. */
HOT float pt_enter_surface(Track* t, float3 gn, float3 lpos, float* value, __constant const PtParams* E,
                           __constant const Params* P, __constant const float4* iface,
                           __constant const float* layer_n, __global const float* smooth) {
#ifdef FLAT
    const float3 sn = (float3)(0.0f, 0.0f, 1.0f);
#else
    float3 sn = smooth_normal(P, iface, smooth, 0, t->pos.x, t->pos.y).xyz;
    if (-dot(t->dir, sn) <= 1e-6f) sn = gn;
#endif
    if (E->specular) {
        const float3 lp = lpos - t->pos;
        const float d2 = dot(lp, lp);
        *value += specular_geo(sn, -t->dir, lp * rsqrt(d2), E->alpha, P->n_above, layer_n[0]) / d2;
    }
    const float ci = -dot(t->dir, sn);
    float ct;
    const float R = fresnel_R(P->n_above, layer_n[0], ci, &ct);
    float beta = (1.0f - R) * (P->n_above / layer_n[0]) * (P->n_above / layer_n[0]);
    t->dir = refract3(t->dir, sn, P->n_above / layer_n[0], ci, ct);
#ifndef FLAT
    if (dot(t->dir, gn) >= 0.0f) t->dir = reflect3(t->dir, gn);
#endif
    t->L = 0;
    return beta;
}

/* The optical depth in band b straight up from the vertex t->pos to the surface (the NEE
 * roulette's measure of how far the light is). */
HOT float nee_depth(const Track* t, int b, __constant const Params* P, __constant const float4* iface,
                    __global const float* heights, __global const float4* optics) {
    float odv = 0.0f;
#ifdef FLAT
    odv += optics[t->L * NB + b].w * (IF_Z(t->L) - t->pos.z);
    for (int k = 0; k < t->L; ++k) odv += optics[k * NB + b].w * (IF_Z(k) - IF_Z(k + 1));
#else
    const int col = col_index(P, t->ix, t->iy);
    float zt = iface_z(iface, heights, P, t->L, col);
    odv += optics[t->L * NB + b].w * fmax(zt - t->pos.z, 0.0f);
    for (int k = t->L - 1; k >= 0; --k) {
        const float zk = iface_z(iface, heights, P, k, col);
        odv += optics[k * NB + b].w * (zk - zt);
        zt = zk;
    }
#endif
    return odv;
}

/* The light's contribution at a scattering vertex (phase function g toward the path's direction
 * t->dir) through a sampled specular chain, per unit intensity: flat layers in closed form
 * (connect), the relief by manifold sampling (connect_mnee_sms) from the smooth layer of the
 * vertex; with periodic sides the light's images one period away as well (nimg). */
HOT float connect_light(const Track* t, float g, float3 lpos, int nimg, int b, Rng* rng, Rng* mrng,
                        __constant const PtParams* E, __constant const float* chain, VOLUME_ARGS,
                        __global const float* smooth, PtStats* st) {
    Chain ch;
    float c = 0.0f;
#ifndef FLAT
#if NINC > 0
    ch.inside = t->inside;
#endif
    real4 vr = R4((real)t->pos.x, (real)t->pos.y, (real)t->pos.z);
    int Ls = smooth_layer(P, iface, smooth, vr, t->L);
    if (Ls < 0) {
        /* in the staircase's skin but above the smooth surface (within half a voxel): connected
         * from the smooth surface just below, as the photons that reach this voxel light it in
         * the photon pass */
        HF f0;
        hf_eval(P, iface, smooth, 0, vr.x, vr.y, &f0);
        vr.z = f0.h - (real)1e-3;
        Ls = smooth_layer(P, iface, smooth, vr, 0);
        st->m_mis++;
#if NINC > 0
        ch.inside = inclusion_mask(optics, (float3)((float)vr.x, (float)vr.y, (float)vr.z));
#endif
    }
    if (Ls >= 0 && chain_build(&ch, Ls, (float)vr.z, lpos.z, 1, -1, rng, iface, chain)) {
        for (int ix = -nimg; ix <= nimg; ++ix)
            for (int iy = -nimg; iy <= nimg; ++iy) {
                const float2 sh = (float2)((float)ix * P->xw, (float)iy * P->yw);
                MneeStat ms;
                int nsol;
                c += connect_mnee_sms(&ch, vr, Ls, (float4)(lpos - (float3)(sh, 0.0f), 0.0f), sh, b,
                                      g, (float4)(t->dir, 0.0f), E->mnee_trials, mrng, P, iface,
                                      layer_n, optics, smooth, &ms, &st->ss, &nsol);
                st->m_try++; st->m_ok += (ulong)ms.ok; st->m_it += (ulong)ms.iters;
                st->m_cont += (ulong)ms.cont; st->m_sol += (ulong)nsol;
            }
    }
#else
    if (chain_build(&ch, t->L, t->pos.z, lpos.z, 1, -1, rng, iface, chain)) {
        for (int ix = -nimg; ix <= nimg; ++ix)
            for (int iy = -nimg; iy <= nimg; ++iy) {
                const float2 sh = (float2)((float)ix * P->xw, (float)iy * P->yw);
                float3 dl;
                real pp, G;
                float f = connect(&ch, t->pos.xy, t->L, lpos.xy - sh, sh, b,
                                  P, layer_n, optics, &dl, &pp, &G);
#if NINC > 0
                if (f > 0.0f) {                 /* the inclusions on the chain's legs */
                    const float2 u = (lpos.xy - sh) - t->pos.xy;
                    const float ru = length(u);
                    f *= exp(-chain_inclusion_od(&ch, t->pos.x, t->pos.y, t->pos.z, t->inside,
                                                 ru > 0.0f ? u.x / ru : 1.0f, ru > 0.0f ? u.y / ru : 0.0f,
                                                 (float)pp, b, iface, layer_n, optics));
                }
#endif
#ifdef MAPS
                if (f > 0.0f) {                 /* the maps on the chain's legs */
                    const float2 u = (lpos.xy - sh) - t->pos.xy;
                    const float ru = length(u);
                    f *= chain_map_factor(&ch, t->pos.x, t->pos.y, t->pos.z, ru > 0.0f ? u.x / ru : 1.0f,
                                          ru > 0.0f ? u.y / ru : 0.0f, (float)pp, b, rng, P, iface, layer_n, optics);
                }
#endif
                if (f > 0.0f) c += f * hg_eval(g, -dot(dl, t->dir));
            }
    }
#endif
    return c;
}

/* Next-event estimation at the nv-th scattering vertex (path factor beta), with roulette where
 * the light is hopelessly far: made with probability q = exp(nee_od - od) (at least
 * nee_q_floor) beyond optical depth nee_od, and weighted 1 / q.  Adds to *value. */
HOT void next_event(const Track* t, float4 op, float beta, int nv, int b, float3 lpos, int nimg,
                    Rng* rng, Rng* mrng, float* value, __constant const PtParams* E,
                    __constant const float* chain, VOLUME_ARGS, __global const float* smooth,
                    PtStats* st) {
    float odv = nee_depth(t, b, P, iface, heights, optics);
    float q = 1.0f;
    if (odv > E->nee_od) q = fmax(exp(E->nee_od - odv), E->nee_q_floor);
    if (q >= 1.0f || rng_u01(rng) <= q) {
        float c = connect_light(t, op.y, lpos, nimg, b, rng, mrng, E, chain, VOLUME_PASS, smooth, st);
        if (c > 0.0f) {
            c *= beta / q;
            *value += c;
            st->bins[vertex_bin(nv)] += (double)c;
            st->nmade++;
        } else {
            st->nblock++;
        }
    }
}

#ifdef FLAT
/* A boundary event of the eye path between flat layers: Fresnel sampled at the interface
 * (reflected: mirrored in z), the n^2 law into *beta; a domain side ends the path (open) or
 * wraps it (periodic).  Returns 0 when the path ends. */
HOT int pt_flat_boundary(Track* t, int ev, float* beta, Rng* rng, __constant const Params* P,
                         __constant const float4* iface, __constant const float* layer_n) {
    if (ev == EV_NONE) return 0;
    if (ev == EV_TOP || ev == EV_BOTTOM) {
        const int up = ev == EV_TOP;
        const int L2 = up ? t->L - 1 : t->L + 1;
        t->pos.z = IF_Z(up ? t->L : t->L + 1);
        const float n1 = layer_n[t->L];
        const float n2 = L2 < 0 ? P->n_above : (L2 >= NL ? P->n_below : layer_n[L2]);
        if (n1 != n2) {
            const float c1 = fabs(t->dir.z);
            float c2;
            const float Rf = fresnel_R(n1, n2, c1, &c2);
            if (rng_u01(rng) <= Rf) { t->dir.z = -t->dir.z; return 1; }
            if (L2 < 0 || L2 >= NL) return 0;
            t->dir = refract3(t->dir, (float3)(0.0f, 0.0f, up ? -1.0f : 1.0f), n1 / n2, c1, c2);
            *beta *= (n1 / n2) * (n1 / n2);
        } else if (L2 < 0 || L2 >= NL) {
            return 0;
        }
        t->L = L2;
        return 1;
    }
    /* a domain side: open ends the path, periodic wraps it */
    return !cross_wall(t, P, (ev == EV_DOMAIN_X || ev == EV_WALL_X) ? 0 : 1, 1);
}
#endif

/* The eye path's walk in band b from the skin's entry (path factor beta): free flight to a
 * scattering vertex or a boundary; at a vertex absorption, next-event estimation, scattering
 * and Russian roulette below rr_threshold of the entry's factor. */
HOT void pt_walk(Track* t, float beta, int b, float3 lpos, int nimg, Rng* rng, Rng* mrng, float* value,
                 __constant const PtParams* E, __constant const float* chain, VOLUME_ARGS,
                 __global const float* smooth, PtStats* st) {
    const float rr_w = E->rr_threshold * beta;
    float tau = neg_log_u01(rng_u01(rng));
    int nv = 0;
    while (beta > 0.0f) {
#ifndef MAPS
        const float4 op = optics[MATERIAL(t) * NB + b];  /* mua/mut, g, 1/(2g), mut: the layer's or an inclusion's */
#else
        float4 op = optics[MATERIAL(t) * NB + b];
        const int mfirst = map_first(optics, MATERIAL(t));   /* a mapped layer: flights at its majorant */
        if (mfirst >= 0) op.w = map_majorant(optics, t->L, b);
#endif
        const float mut = op.w;
        int ev;
        const float sfl = mut > 0.0f ? tau / mut : BIG;
        float db = next_boundary(t, P, iface, heights, sfl, &ev);
#if NINC > 0
        int inc = -1;                   /* an inclusion's surface before the boundary (photon.cl) */
        const float dinc = next_inclusion(optics, t->pos, t->dir, t->inside, INCLUSIONS_OF_LAYER(optics, t->L), &inc);
        const int at_inc = dinc <= db;
        if (at_inc) db = dinc;
#endif
        if (sfl < db) {
            /* ---- scattering vertex */
            t->pos += sfl * t->dir;
#ifdef MAPS
            if (mfirst >= 0) {              /* delta tracking (maps.h): absorb, then null or scatter */
                const float4 c = map_collision(optics, t->L, b, mfirst, t->pos, P);
                op.x = c.x;
                if (c.y > 0.0f && rng_u01(rng) * (c.z + c.y) < c.y) {
                    beta *= 1.0f - op.x;
                    tau = neg_log_u01(rng_u01(rng));
                    continue;
                }
            }
#endif
            if (++nv > E->max_vertices) { st->ncut++; break; }
            beta *= 1.0f - op.x;
            if (!(beta > 0.0f)) break;
            next_event(t, op, beta, nv, b, lpos, nimg, rng, mrng, value, E, chain, VOLUME_PASS, smooth, st);
            /* scatter and roulette */
            const float cth = hg_sample_cos_t(op.y, op.z, rng_u01(rng));
            t->dir = scatter_dir(t->dir, cth, rng_u01(rng));
            if (beta < rr_w) {
                if (rng_u01(rng) * E->rr_m <= 1.0f) beta *= E->rr_m;
                else break;
            }
            tau = neg_log_u01(rng_u01(rng));
            continue;
        }
        /* ---- boundary */
        t->pos += db * t->dir;
        if (mut > 0.0f) tau = fmax(tau - db * mut, 0.0f);
#if NINC > 0
        if (at_inc) { t->inside ^= 1 << inc; locate_column(t, P); continue; }
#endif
#ifndef FLAT
        if (!pt_boundary(t, ev, &beta, rng, VOLUME_PASS, smooth)) break;
#else
        if (!pt_flat_boundary(t, ev, &beta, rng, P, iface, layer_n)) break;
#endif
    }
    st->nvert += (ulong)nv;
}

/* Sample s of pixel pix in band b: the camera ray (jittered in the pixel), the highlight and
 * the path through the skin.  Returns the path's value. */
HOT float pt_sample(uint pix, int s, int b, int nimg, __constant const PtParams* E,
                    __constant const float* chain, VOLUME_ARGS, __global const float* smooth,
                    PtStats* st) {
    const int px = (int)(pix % (uint)E->cam.width), py = (int)(pix / (uint)E->cam.width);
    const float3 lpos = (float3)(E->lx, E->ly, E->lz);
    Rng rng;
    rng_init(&rng, pix * (uint)E->nspp + (uint)s, E->pass_, 5u, E->seed_lo, E->seed_hi);
    Rng mrng;   /* the connections' own stream: their trials leave the walk's decisions as they are */
#ifndef FLAT
    rng_init(&mrng, pix * (uint)E->nspp + (uint)s, E->pass_, 10u, E->seed_lo, E->seed_hi);
#endif
    const float jx = rng_u01(&rng), jy = rng_u01(&rng);
    Track t;
    t.pos = camera_pos(&E->cam).xyz;
    t.dir = camera_dir(&E->cam, (float)px + jx, (float)py + jy).xyz;
    t.L = -1; t.ix = 0; t.iy = 0;
    float value = 0.0f;
    float3 gn;
    if (hit_surface(&t, P, iface, heights, &gn)) {
        const float beta = pt_enter_surface(&t, gn, lpos, &value, E, P, iface, layer_n, smooth);
#if NINC > 0
        t.inside = inclusion_mask(optics, t.pos);
#endif
        pt_walk(&t, beta, b, lpos, nimg, &rng, &mrng, &value, E, chain, VOLUME_PASS, smooth, st);
    }
    return value;
}

__kernel void pt_pass(VOLUME_ARGS,
                      __constant const PtParams* E,
                      __constant const float* chain,
                      __global double* pix_sum,         /* [npix * NB] sum of path values */
                      __global double* pix_sq,          /* [npix * NB] sum of their squares */
                      __global ulong* pix_stats,        /* [npix * 4] vertices, NEE made, blocked, cut */
                      __global double* pix_bins,        /* [npix * NBIN] value by vertex index */
                      __global const float* smooth,     /* Volume.smooth (relief builds) */
                      __global ulong* pix_mnee)         /* [npix * NMNEE] clppm/integrators/pathtracer.py MNEE_STATS */
{
    const uint gid = (uint)get_global_id(0);
    if (gid >= E->count) return;
    const uint pix = E->pix_offset + gid;
    const uint hb = lowbias32(pix) % (uint)NB;
    PtStats st;
    pt_stats_clear(&st);
    const int nimg = P->lateral == 2 ? 1 : 0;           /* periodic: images -1..1 in x and y */
    for (int s = 0; s < E->nspp; ++s) {
        const int b = (int)((E->band0 + (uint)s + hb) % (uint)NB);
        const float value = pt_sample(pix, s, b, nimg, E, chain, VOLUME_PASS, smooth, &st);
        pix_sum[(size_t)pix * NB + b] += (double)value;
        pix_sq[(size_t)pix * NB + b] += (double)value * (double)value;
    }
    pt_stats_add(&st, pix, pix_stats, pix_mnee, pix_bins);
}

/* ---------------------------------------------------------------- test entry point */
/* For each vertex (xyz, layer in w): the chain (mode -1: sampled with Philox (seed, 0, i),
 * mode 0: direct, mode j > 0: reflected once at interface j), the solved p, dOmega/dA_h,
 * the factor connect() returns, cos theta_L and the chain's points from the vertex to the
 * light (the last should be the light): out[i * 8 + ...] = p, dOmega/dA_h, factor, cos theta_L,
 * selection probability, ok, number of points; pts[(i * (MAXE + 2) + j) * 4 + ...] = x, y, z, layer. */
/* point *np of a chain's walk (x, y, z, the layer after it; -1: the light) */
inline void put_point(__global real* pp, int* np, real qx, real qy, real qz, int k) {
    pp[4 * *np] = qx; pp[4 * *np + 1] = qy; pp[4 * *np + 2] = qz; pp[4 * *np + 3] = k;
    (*np)++;
}

__kernel void t_connect(VOLUME_ARGS, __constant const float* chain, const float4 light,
                        const int mode, const uint n, __global const float4* verts,
                        __global real* out, __global real* pts) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    const float4 vw = verts[i];
    const float3 v = vw.xyz;
    const int Lv = (int)vw.w;
    Rng rng;
    rng_init(&rng, i, 0u, 6u, 12345u, 0u);
    Chain ch;
    const int ok = chain_build(&ch, Lv, v.z, light.z, mode < 0, mode > 0 ? mode : -1, &rng, iface, chain);
    __global real* o = out + (size_t)i * 8;
    for (int j = 0; j < 8; ++j) o[j] = 0;
    o[5] = ok;
    if (!ok) return;
    float3 dl;
    real p, G;
    const float f = connect(&ch, v.xy, Lv, light.xy, (float2)(0.0f), 0, P, layer_n, optics, &dl, &p, &G);
    const real nL = layer_n[Lv];
    o[0] = p; o[1] = G * sqrt(fmax((real)0, 1 - (p / nL) * (p / nL))); o[2] = f;
    o[3] = sqrt(fmax((real)0, 1 - (p / nL) * (p / nL))); o[4] = ch.wsel;
    /* the points: walk the events from the vertex */
    const real dx = (real)light.x - v.x, dy = (real)light.y - v.y;
    const real rt = sqrt(dx * dx + dy * dy);
    const real ux = rt > 0 ? dx / rt : 1, uy = rt > 0 ? dy / rt : 0;
    real qx = v.x, qy = v.y, qz = v.z;
    int up = ch.up, np = 0;
    __global real* pp = pts + (size_t)i * (MAXE + 2) * 4;
    put_point(pp, &np, qx, qy, qz, Lv);
    for (int e = 0; e < ch.ne; ++e) {
        const int fi = ch.ev[e] & 255, k = (ch.ev[e] >> 8) & 255, refl = ch.ev[e] >> 16;
        const real n = layer_n[k];
        const real tn = (p / n) / sqrt(1 - (p / n) * (p / n));
        const real zi = IF_Z(fi);
        const real adv = fabs(zi - qz) * tn;
        qx += adv * ux; qy += adv * uy; qz = zi;
        put_point(pp, &np, qx, qy, qz, k);
        if (refl) up = !up;
    }
    const real na = P->n_above;
    const real adv = ((real)light.z - qz) * (p / na) / sqrt(1 - (p / na) * (p / na));
    qx += adv * ux; qy += adv * uy; qz = light.z;
    put_point(pp, &np, qx, qy, qz, -1);
    o[6] = np;
}

#ifndef FLAT
/* For each vertex (xyz; its layer is found on the smooth surfaces): the chain (mode as t_connect)
 * connected through the height fields.  out[i * 20 + ...] = ok, Newton iterations, halvings, G,
 * factor (band 0), Fresnel product, cos theta_v, cos theta_a, u_x, u_y, selection probability,
 * vertex layer, number of points, landing error, chain built, why, one sample of the render's
 * connection (salt), its solutions, trials and clamped; pts[(i * (MAXE + 2) + j) * 8 + ...]
 * = x, y, z, layer of the segment ending there (-1 air), upward normal there (0 at the ends). */
__kernel void t_mnee(VOLUME_ARGS, __constant const float* chain, __global const float* smooth,
                     const float4 light, const int mode, const uint n, __global const float4* verts,
                     __global real* out, __global real* pts, const int use_seeds,
                     __global const real* seeds, const float mnee_trials, const uint salt) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    __global real* o = out + (size_t)i * 20;
    for (int j = 0; j < 20; ++j) o[j] = 0;
    const real4 v = R4((real)verts[i].x, (real)verts[i].y, (real)verts[i].z);
    const int Ls = smooth_layer(P, iface, smooth, v, clamp((int)verts[i].w, 0, NL - 1));
    o[11] = Ls;
    if (Ls < 0) return;
    Rng rng;
    rng_init(&rng, i, 0u, 6u, 12345u, 0u);
    Chain ch;
    if (!chain_build(&ch, Ls, (float)v.z, light.z, mode < 0, mode > 0 ? mode : -1, &rng, iface, chain)) return;
#if NINC > 0
    ch.inside = inclusion_mask(optics, (float3)(verts[i].x, verts[i].y, verts[i].z));
#endif
    o[14] = 1;
    float4 dl;
    MneeStat ms;
    Trace T;
    float f = 0.0f;
    if (use_seeds) {
        /* Newton on the surfaces from the given seed (several seeds: the solutions there are) */
        const real4 l = R4((real)light.x, (real)light.y, (real)light.z);
        chain_local_H(&ch, v, l.z, P, iface, smooth);
        real ux = seeds[2 * i], uy = seeds[2 * i + 1];
        ms.iters = 0; ms.halvings = 0; ms.cont = 0; ms.traces = 0;
        ms.ok = mnee_newton(&ch, v, Ls, &ux, &uy, l, 1, P, iface, layer_n, smooth, &T, &ms);
        if (ms.ok) f = mnee_factor(&T, &ch, (float2)(0.0f), 0, P, optics, &dl);
    } else {
        f = connect_mnee(&ch, v, Ls, (float4)(light.xyz, 0.0f), (float2)(0.0f), 0, P, iface, layer_n, optics,
                         smooth, &dl, &ms, &T);
    }
    if (use_seeds == 0) {
        /* the render's connection, one sample of it with the random stream (i, salt):
         * specular manifold sampling (isotropic phase function, times 4 pi: the sum of the factors) */
        MneeStat s3;
        SmsStat ss = {0u, 0u, 0u, 0u};
        int nsol;
        Chain c2 = ch;
        Rng r2;
        rng_init(&r2, i, salt, 7u, 12345u, 0u);
        o[16] = 4 * PI_F * connect_mnee_sms(&c2, v, Ls, (float4)(light.xyz, 0.0f), (float2)(0.0f), 0, 0.0f,
                                            (float4)(0.0f, 0.0f, 1.0f, 0.0f), mnee_trials, &r2, P, iface,
                                            layer_n, optics, smooth, &s3, &ss, &nsol);
        o[17] = nsol; o[18] = ss.trials; o[19] = ss.clamped;
    }
    o[0] = ms.ok + 2 * ms.cont; o[1] = ms.iters; o[2] = ms.halvings; o[15] = T.why;
    o[13] = sqrt(T.c[0] * T.c[0] + T.c[1] * T.c[1]);
    if (!ms.ok) return;
    o[3] = mnee_G(&T, P->n_above); o[4] = f; o[5] = T.F; o[6] = T.cos_v; o[7] = T.cos_a;
    o[8] = T.d0.x * layer_n[Ls]; o[9] = T.d0.y * layer_n[Ls]; o[10] = ch.wsel;
    const real4 l = R4((real)light.x, (real)light.y, (real)light.z);
    Trace T2;
    mnee_trace(&ch, v, Ls, o[8], o[9], l, 1, 0, 0, 0, P, iface, layer_n, smooth, &T2,
               pts + (size_t)i * (MAXE + 2) * 8);
    o[12] = ch.ne + 2;
}
#endif
