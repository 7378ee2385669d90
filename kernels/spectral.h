/* spectral.h -- the bands a photon path carries, and their weights (hero-wavelength sampling).
 *
 * A path is traced in its hero band h (free flights with mu_t(h), Henyey-Greenstein with g(h),
 * absorption by weight with mu_a/mu_t of h) and carries HERO_C bands spaced evenly over the
 * spectrum, b_j = (h + j NB/HERO_C) mod NB, j = 0 (the hero) .. HERO_C-1.  Every member of that
 * set could have been the hero, with the hero-selection probability pi(b) of the host's band
 * table; so the path is one sample of one-sample multiple importance sampling over the set's
 * HERO_C techniques (Wilkie, Nawaz, Droske, Weidlich & Hanika 2014, "Hero wavelength spectral
 * sampling"; pbrt-v4's SampledWavelengths carries the bands the same way), and the balance
 * heuristic gives the weight of band b_j at a stored event
 *
 *     F_j = s(b_j) A_j rho_j / sum_k pi(b_k) rho_k,
 *
 * s the light's relative power per band, A_j the product of band b_j's single-scattering
 * albedos along the path (its absorption, exact per band), rho_k the ratio of the path's pdf
 * under band b_k to any common reference: per free-flight segment of length l in a layer
 * exp(-mu_t(b_k) l), times mu_t(b_k) at a collision, times HG(g(b_k), cos) at a scattering;
 * Fresnel decisions and roulette are the same for every band and cancel.  With HERO_C = 1 this
 * is the one-band path of the paper, weight s(h)/pi(h) A_h.  Unbiased per band for any pi > 0
 * on the set (tests/test_spectral.py).
 *
 * Far bands' rho drift apart over a long path (a path typical for red is atypical for blue), so
 * the balance heuristic then gives the event to the band with the largest s pi-weighted pdf:
 * bounded weights (F_j <= s A_j / pi(b_j)), never worse than one band per path in variance
 * beyond a constant; the benefit is largest for the short paths near the surface.  rho is kept
 * as exp(lr) hq^(-3/2): the free-flight and collision factors as a log (a multiply-add per band
 * and segment, no exponential on the hot path), the phase-function factors as a product of
 * linear functions of the scattering cosine (sw_scatter: a multiply-add and a multiply per band,
 * no root or division), folded into the log when it strays far from 1.
 */
#ifndef CLPPM_SPECTRAL_H
#define CLPPM_SPECTRAL_H

#include "volume.h"

#ifndef HERO_C
#define HERO_C 1
#endif
#if (NB % HERO_C) != 0
#error "HERO_C must divide NB"
#endif
#define HERO_STEP (NB / HERO_C)

typedef struct {
    int h;
#if HERO_C > 1
    float lr[HERO_C];   /* log of the flight part of rho, up to the pending part below */
    float hq[HERO_C];   /* the phase-function part of rho is hq^(-3/2) (sw_scatter), hq[0] = 1 */
    float la[HERO_C];   /* log of the albedo product, up to the pending collisions */
    float scale;        /* the band-independent factors of the albedo products (Fresnel, roulette) */
    float amax;         /* an upper bound of the largest albedo product (sw_amax) */
    int pL, pn;         /* pending: the layer, the collisions in it */
    float pl;           /* pending: the path length in it */
#endif
} Spectral;

inline int sw_band(int h, int j) {
#if HERO_C > 1
    const int b = h + j * HERO_STEP;
    return b >= NB ? b - NB : b;
#else
    return h;
#endif
}

inline void sw_init(Spectral* w, int h) {
    w->h = h;
#if HERO_C > 1
    for (int j = 0; j < HERO_C; ++j) { w->lr[j] = 0.0f; w->hq[j] = 1.0f; w->la[j] = 0.0f; }
    w->scale = 1.0f; w->amax = 1.0f;
    w->pL = 0; w->pn = 0; w->pl = 0.0f;
#endif
}

/* The band table (photonpass.py band_table), per material (the NL layers, then the inclusions:
 * NMAT, volume.h; "layer" L below is a material): [NMAT*NB] log mu_t, [NMAT*NB] log albedo
 * (1 - mu_a/mu_t, at least e^-10000: none without scattering), [NMAT*HERO_STEP] the largest albedo
 * over the bands a path of each hero class h mod HERO_STEP carries, [NMAT*NB] pairs
 * (A, B) = (1 + g^2, 2 g) (1 - g^2)^(-2/3) (sw_scatter). */
#define TAB_LOGMU(L, b) tab[(L) * NB + (b)]
#define TAB_LOGALB(L, b) tab[NMAT * NB + (L) * NB + (b)]
#define TAB_MAXALB(L, h) tab[2 * NMAT * NB + (L) * HERO_STEP + (h) % HERO_STEP]
#define TAB_HG(L, b) ld2(tab + 2 * NMAT * NB + NMAT * HERO_STEP + 2 * ((L) * NB + (b)))

/* Lazy per-band work.  Within one layer the per-band factors of a flight and of a collision are
 * constants, so a path keeps only its length and its collisions in the current layer (two
 * scalars per event) and applies them to every band when it leaves the layer: the per-band loop
 * runs once per layer visited and per stored event, not at every event (the sums are the same
 * up to float rounding).  A stored event reads the pending part without applying it (sw_weights),
 * so the weights do not depend on which events were looked at before. */
inline float sw_lr_pending(const Spectral* w, __global const float4* optics, __global const float* tab, int b) {
#if HERO_C > 1
    const int L = w->pL;
    return (float)w->pn * (TAB_LOGMU(L, b) - TAB_LOGMU(L, w->h))
           - w->pl * (optics[L * NB + b].w - optics[L * NB + w->h].w);
#else
    return 0.0f;
#endif
}

inline void sw_sync(Spectral* w, __global const float4* optics, __global const float* tab) {
#if HERO_C > 1
    if (w->pn == 0 && w->pl == 0.0f) return;
    for (int j = 0; j < HERO_C; ++j) {
        const int b = sw_band(w->h, j);
        w->lr[j] += sw_lr_pending(w, optics, tab, b);
        w->la[j] += (float)w->pn * TAB_LOGALB(w->pL, b);
    }
    w->pn = 0; w->pl = 0.0f;
#endif
}

/* a free-flight segment of length l in layer L (hero mu_t mut_h), ending anywhere: its length
 * joins the pending path in the layer (the per-band factor exp(-(mu_t(b_k) - mu_t(h)) l) later) */
inline void sw_flight(Spectral* w, __global const float4* optics, __global const float* tab,
                      int L, float mut_h, float l) {
#if HERO_C > 1
    if (L != w->pL) { sw_sync(w, optics, tab); w->pL = L; }
    w->pl += l;
#endif
}

/* a collision in layer L, right after its flight (sw_flight): the mu_t ratio of the collision
 * density and the absorption per band, pending; the bound of the largest albedo product now */
inline void sw_collide(Spectral* w, __global const float* tab, int L) {
#if HERO_C > 1
    w->pn++;
    w->amax *= TAB_MAXALB(L, w->h);
#endif
}

/* The phase-function part of rho.  HG(g, c) = (1 - g^2) / (4 pi a^(3/2)), a = 1 + g^2 - 2 g c, so
 * the ratio of band j to the hero h at a scattering by c is
 *
 *     HG(g_j, c) / HG(g_h, c) = [(A_j - B_j c) / (A_h - B_h c)]^(-3/2),
 *     (A, B) = (1 + g^2, 2 g) (1 - g^2)^(-2/3)   (the band table's TAB_HG, per layer and band),
 *
 * and the product over the path's scatterings is hq_j^(-3/2) with hq_j the product of the
 * bracketed ratios: one multiply-add and one multiply per band and scattering.  hq_j leaves
 * [2^-40, 2^40] only after many scatterings; then it is folded into lr_j as -3/2 ln hq_j and
 * restarts at 1 (one factor is at most ((1 + |g|) / (1 - |g|))^2 (1 - g^2)^(-2/3), far from
 * float's range for any g of skin), so no band's factor overflows or underflows. */
inline void sw_fold_hq(Spectral* w, int j) {
#if HERO_C > 1
    w->lr[j] -= 1.5f * log(w->hq[j]);
    w->hq[j] = 1.0f;
#endif
}

/* a scattering in layer L by cos_t (sampled with the hero's g) */
inline void sw_scatter(Spectral* w, __global const float* tab, int L, float cos_t) {
#if HERO_C > 1
    const float2 abh = TAB_HG(L, w->h);
    const float inv = 1.0f / (abh.x - abh.y * cos_t);
    float lo = 1.0f, hi = 1.0f;
    for (int j = 1; j < HERO_C; ++j) {
        const float2 ab = TAB_HG(L, sw_band(w->h, j));
        w->hq[j] *= (ab.x - ab.y * cos_t) * inv;
        lo = fmin1(lo, w->hq[j]);
        hi = fmax1(hi, w->hq[j]);
    }
    if (lo < 0x1p-40f || hi > 0x1p40f)
        for (int j = 1; j < HERO_C; ++j) sw_fold_hq(w, j);
#endif
}

/* a band-independent weight factor (the Fresnel transmission at entry, Russian roulette's m) */
inline void sw_scale(Spectral* w, float m) {
#if HERO_C > 1
    w->scale *= m;
    w->amax *= m;
#endif
}

/* an upper bound of the largest albedo product of the bands carried (a_h: the hero's, for one
 * band per path): the product over the collisions of the largest albedo among the bands */
inline float sw_amax(const Spectral* w, float a_h) {
#if HERO_C > 1
    return w->amax;
#else
    return a_h;
#endif
}

/* F_j of a stored event (see above); a_h is the hero's albedo product (its fixed-point weight) */
inline void sw_weights(const Spectral* w, float a_h, __global const float2* band_spi, __global const float4* optics,
                       __global const float* tab, float* F) {
#if HERO_C > 1
    float lr[HERO_C], la[HERO_C];
    for (int j = 0; j < HERO_C; ++j) {
        const int b = sw_band(w->h, j);
        lr[j] = w->lr[j] + sw_lr_pending(w, optics, tab, b);
        la[j] = w->la[j] + (float)w->pn * TAB_LOGALB(w->pL, b);
    }
    float lm = lr[0];
    for (int j = 1; j < HERO_C; ++j) lm = fmax1(lm, lr[j]);
    float rho[HERO_C];
    float den = 0.0f;
    for (int j = 0; j < HERO_C; ++j) {
        /* hq^(-3/2) lies within 2^-60 .. 2^60 (sw_scatter), so rho neither overflows nor, for the
         * band of the largest lr, underflows */
        rho[j] = exp_neg(lm - lr[j]) / (w->hq[j] * sqrt1(w->hq[j]));
        den += band_spi[sw_band(w->h, j)].y * rho[j];
    }
    const float inv = den > 0.0f ? w->scale / den : 0.0f;
    for (int j = 0; j < HERO_C; ++j)
        F[j] = band_spi[sw_band(w->h, j)].x * exp_neg(-la[j]) * rho[j] * inv;
#else
    const float2 sp = band_spi[w->h];
    F[0] = sp.x / sp.y * a_h;
#endif
}

#endif
