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
 * as exp(lr) hr: the free-flight and collision factors as a log (a multiply-add per band and
 * segment, no exponential on the hot path), the phase-function factors as a product
 * renormalised at every scattering (only ratios enter F).
 */
#ifndef CLPPM_SPECTRAL_H
#define CLPPM_SPECTRAL_H

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
    float lr[HERO_C];   /* log of the flight part of rho: -(mu_t(b_k) - mu_t(h)) l, log mu_t ratios */
    float hr[HERO_C];   /* the phase-function part of rho, renormalised by its largest entry */
    float A[HERO_C];
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
    for (int j = 0; j < HERO_C; ++j) { w->lr[j] = 0.0f; w->hr[j] = 1.0f; w->A[j] = 1.0f; }
#endif
}

/* a free-flight segment of length l in layer L (hero mu_t mut_h), ending anywhere: kept in the
 * log domain, one multiply-add per band (no exponential on the hot path) */
inline void sw_flight(Spectral* w, __global const float4* optics, int L, float mut_h, float l) {
#if HERO_C > 1
    for (int j = 1; j < HERO_C; ++j)
        w->lr[j] -= (optics[L * NB + sw_band(w->h, j)].w - mut_h) * l;
#endif
}

/* a collision in layer L: the mu_t ratio of the collision density (log mu_t from the table
 * logmu), absorption per band */
inline void sw_collide(Spectral* w, __global const float4* optics, __global const float* logmu,
                       int L, float4 op_h) {
#if HERO_C > 1
    w->A[0] *= 1.0f - op_h.x;
    const float lh = logmu[L * NB + w->h];
    for (int j = 1; j < HERO_C; ++j) {
        const int b = sw_band(w->h, j);
        w->lr[j] += logmu[L * NB + b] - lh;
        w->A[j] *= 1.0f - optics[L * NB + b].x;
    }
#endif
}

/* a scattering in layer L by cos_t (sampled with the hero's g): phase-function ratios,
 * HG(g_j)/HG(g_h) = (1-g_j^2)/(1-g_h^2) (a_h/a_j)^(3/2), a = 1 + g^2 - 2 g cos */
inline void sw_scatter(Spectral* w, __global const float4* optics, int L, float g_h, float cos_t) {
#if HERO_C > 1
    const float ah = 1.0f + g_h * g_h - 2.0f * g_h * cos_t;
    const float nh = 1.0f / (1.0f - g_h * g_h);
    float mx = w->hr[0];
    for (int j = 1; j < HERO_C; ++j) {
        const float g = optics[L * NB + sw_band(w->h, j)].y;
        const float r = ah / (1.0f + g * g - 2.0f * g * cos_t);
        w->hr[j] *= (1.0f - g * g) * nh * r * sqrt(r);
        mx = fmax(mx, w->hr[j]);
    }
    if (mx > 0.0f && isfinite(mx)) {
        const float inv = 1.0f / mx;
        for (int j = 0; j < HERO_C; ++j) w->hr[j] *= inv;
    }
#endif
}

/* a band-independent weight factor (the Fresnel transmission at entry, Russian roulette's m) */
inline void sw_scale(Spectral* w, float m) {
#if HERO_C > 1
    for (int j = 0; j < HERO_C; ++j) w->A[j] *= m;
#endif
}

/* the largest albedo product of the bands carried (a_h: the hero's, for one band per path) */
inline float sw_amax(const Spectral* w, float a_h) {
#if HERO_C > 1
    float m = w->A[0];
    for (int j = 1; j < HERO_C; ++j) m = fmax(m, w->A[j]);
    return m;
#else
    return a_h;
#endif
}

/* F_j of a stored event (see above); a_h is the hero's albedo product (its fixed-point weight) */
inline void sw_weights(const Spectral* w, float a_h, __global const float2* band_spi, float* F) {
#if HERO_C > 1
    float lm = w->lr[0];
    for (int j = 1; j < HERO_C; ++j) lm = fmax(lm, w->lr[j]);
    float rho[HERO_C];
    float den = 0.0f;
    for (int j = 0; j < HERO_C; ++j) {
        rho[j] = w->hr[j] * exp_neg(lm - w->lr[j]);
        den += band_spi[sw_band(w->h, j)].y * rho[j];
    }
    const float inv = den > 0.0f ? 1.0f / den : 0.0f;
    for (int j = 0; j < HERO_C; ++j)
        F[j] = band_spi[sw_band(w->h, j)].x * w->A[j] * rho[j] * inv;
#else
    const float2 sp = band_spi[w->h];
    F[0] = sp.x / sp.y * a_h;
#endif
}

#endif
