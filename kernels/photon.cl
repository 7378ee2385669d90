/* Photon pass: one work item traces one photon of one wavelength band through the layered
 * voxel volume and stores every scattering event inside the skin.
 *
 * Weights are 64-bit fixed point (W0 = 2^38 per emitted photon).  Absorption removes an
 * integer part of the weight, so the bookkeeping specular + Rd + Tt + lost + missed + A
 * + roulette losses - roulette gains = W0 holds exactly for every photon, and the tallies
 * (atomic 64-bit integer adds, flushed to Python integers by the host after every launch)
 * lose nothing however many photons are traced.  Russian roulette is the unbiased kind: below
 * rr_threshold a photon survives with probability 1/rr_m and is multiplied by rr_m.
 */
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#include "common.h"
#include "spectral.h"
#ifndef FLAT
#include "surface.h"
#endif

#define W0F 274877906944.0f           /* 2^38 */
/* A photon between two interfaces that coincide in its column (a layer of no thickness there)
 * can be reflected back and forth by both without moving: after this many boundary events in a
 * row each shorter than 1 nm it is trapped for good and counted lost, as it would be after
 * max_events; no photon that moves is affected, so no image changes. */
#define TRAPPED_STEPS 1000
#define TRAP_UM 1e-3f
#define W0L ((long)274877906944L)

/* tally categories (per band); NC = T_ABS0 + NL */
/* T_RCONE: the part of T_RD leaving within the cone cos(theta) > rcone_cos around the normal
 * (not a separate fate: it is excluded from the energy balance) */
enum { T_SPEC = 0, T_RD, T_TT, T_LOST, T_RRGAIN, T_RRLOSS, T_MISS, T_RCONE, T_ABS0 };
#define NC (T_ABS0 + NL)

inline int sample_band(__global const float* cdf, float u) {
    int lo = 0, hi = NB - 1;
    while (lo < hi) {
        int mid = (lo + hi) >> 1;
        if (cdf[mid] >= u) hi = mid; else lo = mid + 1;
    }
    return lo;
}

/* A photon that has just left the skin at t->pos going t->dir: if the straight way out meets
 * the relief again (a furrow), enter there (Fresnel decided at the new point).  Returns 1 if the
 * photon is back in layer 0, 0 if it escaped for good.  Reflections at re-entry send it on its
 * way out again (up to a few bounces). */
inline int reenter(Track* t, VOLUME_ARGS, __global const float* smooth, Rng* rng) {
#ifdef FLAT
    return 0;
#else
    if (IF_VAR(0) < 0) return 0;
    for (int k = 0; k < 4; ++k) {
        t->pos += 1e-3f * t->dir;
        float3 gn;
        if (!hit_surface(t, P, iface, heights, &gn)) return 0;
        const float4 sn = smooth_normal(P, iface, smooth, 0, t->pos.x, t->pos.y);
        float4 d = (float4)(t->dir, 0.0f);
        const int in = fresnel_cross(&d, (float4)(-gn, 0.0f), -sn, P->n_above, layer_n[0], rng_u01(rng));
        t->dir = d.xyz;
        if (in) { t->L = 0; return 1; }
    }
    return 0;
#endif
}

/* The Fresnel decision crossing from layer L into L2 through a face of geometric normal gn
 * (pointing into L2) at (x, y): at the smooth surface's normal there (surface.h) where interface
 * k varies and the indices differ, as the path tracer's walk decides (pt.cl pt_boundary).
 * Scalars and 4-vectors only across the call (surface.h: Intel's 3-vector miscompilation). */
inline int cross_face(float4* dir, float4 gn, int k, int L, int L2, float x, float y, float n1, float n2,
                      __constant const Params* P, __constant const float4* iface,
                      __global const float* smooth, float u) {
    float4 sn = gn;
#ifndef FLAT
    if (n1 != n2) sn = face_normal(P, iface, smooth, k, L, L2, x, y, gn);
#endif
    return fresnel_cross(dir, gn, sn, n1, n2, u);
}

/* Importance-driven storage (Peter & Pietrek 1998, in direction and depth instead of position).
 * A stored event travelling along w at depth z counts, for an eye ray, as much as
 * sum_j F_j HG(g_j, w . w_eye) T_j(z) over the bands j it carries: most events travel away from
 * the eye (the phase function of skin, g = 0.73-0.85, peaks 20-50x above its mean) or lie where
 * the eye rays' transmittance has died, or carry little weight (absorbed on the way).  Storing
 * each event with probability q and weight 1/q is unbiased for any q > 0; with q proportional
 * to that importance the stored events become near-equal contributors, and the budget of stored
 * events per pass buys many more independent paths.  The importance is bounded per band by the
 * most favourable eye direction within the cone around +z (half angle from the eye pass),
 * relative to the band's phase-function peak (hrel_j), times the transmittance T_j of a vertical
 * eye ray down to z (imp = optical depth at the layer's nominal top, that top's z), times the
 * band's weight a_j = F_j pi_j / s_j (its balance-heuristic share times its albedo product:
 * a_h = W / W0 for one band per path, and sum_j a_j = A when the bands agree):
 *
 *     I = sum_j a_j hrel_j T_j,   q = clamp(store_scale I, store_qmin, 1).
 *
 * Every band enters, not the hero alone: a path whose hero is strongly absorbed (577 nm, the
 * haemoglobin peak) while a band it carries is not (620 nm) had a hero-only I near 0, so q fell
 * to store_qmin, and the carried band's F_j / q made single photons 10^3 times the median
 * photon's contribution (bench/spots.py; issue 20).  With I over all bands every stored photon
 * obeys F_j / q hrel_j T_j <= s_j / (pi_j store_scale) for every band it carries
 * (tests/test_spectral.py checks it); store_probability below computes q, store_bound a
 * per-layer upper bound of it. */

/* the cosine within the eye cone closest to d (the most favourable eye direction) */
inline float cone_cos(__constant const Params* P, float3 d) {
    const float c = d.z;
    return c >= P->store_cos ? 1.0f : c * P->store_cos + sqrt(fmax(0.0f, 1.0f - c * c)) * P->store_sin;
}

/* HG(g, ce) / max HG(g, .) */
inline float hg_rel(float g, float ce) {
    const float a = 1.0f + g * g - 2.0f * g * ce;
    const float omg = 1.0f - fabs(g);
    return omg * omg * omg / (a * sqrt(a));
}

/* An upper bound of I for the event's layer, from per-layer extremes over all bands
 * (store_imp[NL*NB + 2L]: the least optical depth at the layer's top and the least mu_t;
 * [NL*NB + 2L + 1]: the top's z and the least g, or -1 when some g < 0) and the largest albedo
 * product: sum_j a_j <= max_j A_j (the balance weights sum to 1), hrel_j <= hrel(g_min) (HG
 * toward a fixed cosine below 1 falls as g grows), T_j <= exp(-(od_min + mu_min dz)).  An event
 * whose uniform exceeds clamp(store_scale U) is not stored whatever q is, so I is computed only
 * for the others (most events are dropped): the same decisions as computing q for every event. */
inline float store_bound(__global const float2* store_imp, int L, float ce, float amax, float z) {
    const float2 m = store_imp[NL * NB + 2 * L], zg = store_imp[NL * NB + 2 * L + 1];
    const float hrel = zg.y >= 0.0f ? hg_rel(zg.y, ce) : 1.0f;
    return 1.001f * hrel * exp_neg(m.x + m.y * fmax(0.0f, zg.x - z)) * amax;
}

inline float store_probability(__constant const Params* P, float ce, int L, int h, const float* F,
                               __global const float2* band_spi, __global const float4* optics,
                               __global const float2* store_imp, float z) {
    float I = 0.0f;
    for (int j = 0; j < HERO_C; ++j) {
        const int bj = sw_band(h, j);
        const float4 op = optics[L * NB + bj];
        const float2 imp = store_imp[L * NB + bj];
        const float2 spi = band_spi[bj];
        const float T = exp_neg(imp.x + op.w * fmax(0.0f, imp.y - z));
        I += spi.x > 0.0f ? F[j] * (spi.y / spi.x) * hg_rel(op.y, ce) * T : 0.0f;
    }
    return clamp(P->store_scale * I, P->store_qmin, 1.0f);
}

__kernel void photon_pass(VOLUME_ARGS,
                          __global const float2* store_imp,  /* [NL*NB] see store_probability */
                          __global const float* band_cdf,    /* hero selection pi, as a cdf */
                          __global const float2* band_spi,   /* [NB] light power s, pi (spectral.h) */
                          __global const float* logmu,       /* [NL*NB] log mu_t (spectral.h) */
                          __global float4* store_pos_w,      /* x, y, z, weight of the hero band */
                          __global float4* store_dir_b,      /* direction, hero band + 256 layer */
                          __global float* store_extra,       /* HERO_C-1 weights of the other bands */
                          __global volatile uint* store_count,
                          __global long* tallies,
                          __global const float* smooth)      /* Volume.smooth (relief builds) */
{
    if ((uint)get_global_id(0) >= P->count) return;
    const uint id = P->photon_offset + (uint)get_global_id(0);
    Rng rng;
    rng_init(&rng, id, P->pass, 2u * P->offset_hi, P->seed_lo, P->seed_hi);   /* eye rays: odd domain */
    /* storage decisions draw from a stream of their own: the path is the same under every rule */
    Rng srng;
    rng_init(&srng, id, P->pass, (2u * P->offset_hi) | 0x80000001u, P->seed_lo, P->seed_hi);

    /* the emission's three uniforms: band, then direction (point) or footprint (wide beam) */
    float ue0, ue1, ue2;
    if (P->qmc) {
        ue0 = r3_u01(id, R3_A0, P->qmc_s0);
        ue1 = r3_u01(id, R3_A1, P->qmc_s1);
        ue2 = r3_u01(id, R3_A2, P->qmc_s2);
    } else {
        ue0 = P->fixed_band >= 0 ? 0.5f : rng_u01(&rng);
        ue1 = P->src_kind != 0 ? rng_u01(&rng) : 0.5f;
        ue2 = P->src_kind != 0 ? rng_u01(&rng) : 0.5f;
    }
    const int b = P->fixed_band >= 0 ? P->fixed_band : sample_band(band_cdf, ue0);
    __global long* tal = tallies + (size_t)b * NC;     /* the tallies follow the hero band alone */
    Spectral sw;
    sw_init(&sw, b);

    Track t;
    /* ---- launch */
    if (P->src_kind == 2) {                       /* isotropic point light, cone-sampled */
        const float s = ue1 * P->cone_omc;      /* 1 - cos(theta): exact for a narrow cone */
        const float2 cs = azimuth_cs(ue2);
        t.dir = rotate_dir_cst((float3)(P->cax, P->cay, P->caz), 1.0f - s, sqrt(fmax(s * (2.0f - s), 0.0f)), cs.x, cs.y);
        t.pos = (float3)(P->sx, P->sy, P->sz);
    } else {
        float3 d = (float3)(P->sdx, P->sdy, P->sdz);
        float fx = P->sx, fy = P->sy;
        if (P->src_kind == 1) {
            fx += (ue1 - 0.5f) * P->swx;
            fy += (ue2 - 0.5f) * P->swy;
        }
        /* start above the relief on the line through the footprint point (fx, fy, 0) */
        float back = (P->z_top + 1.0f) / (-d.z);
        t.pos = (float3)(fx, fy, 0.0f) - back * d;
        t.dir = d;
    }
    t.L = -1; t.ix = 0; t.iy = 0;
    float3 gn;
    if (!hit_surface(&t, P, iface, heights, &gn)) {
        atom_add(tal + T_MISS, W0L);
        return;
    }

    long W = W0L;
    long spec = 0, rd = 0, tt = 0, lost = 0, gain = 0, loss = 0, rcone = 0;
    long absorbed[NL];
    for (int i = 0; i < NL; ++i) absorbed[i] = 0;

    /* ---- enter: deterministic Fresnel split at the smooth surface's normal */
    {
#ifdef FLAT
        float3 sn = (float3)(0.0f, 0.0f, 1.0f);
#else
        float3 sn = smooth_normal(P, iface, smooth, 0, t.pos.x, t.pos.y).xyz;
#endif
        float ci = -dot(t.dir, sn);
        if (ci <= 1e-6f) { sn = gn; ci = -dot(t.dir, gn); }
        float ct;
        float R = fresnel_R(P->n_above, layer_n[0], ci, &ct);
        long ws = convert_long_rte((float)W * R);
        ws = clamp(ws, 0L, W);
        spec += ws; W -= ws;
        if (W > 0) {
            float3 d = refract3(t.dir, sn, P->n_above / layer_n[0], ci, ct);
            if (dot(d, gn) >= 0.0f) d = reflect3(d, gn);
            t.dir = unit3(d);
        }
    }

    sw_scale(&sw, (float)W * (1.0f / W0F));           /* the entry's Fresnel transmission */
    const long rr_w = (long)(P->rr_threshold * W0F);
    float tau = neg_log_u01(rng_u01(&rng));
    int events = 0;
    int still = 0;                                     /* boundary events in a row under TRAP_UM */
    while (W > 0) {
        if (++events > P->max_events) { lost += W; W = 0; break; }
        const float4 op = optics[t.L * NB + b];     /* mua/mut, g, 1/(2g), mut in um^-1 */
        const float mut = op.w;
        int ev;
        const float db = next_boundary(&t, P, iface, heights, &ev);
        const float s = mut > 0.0f ? tau / mut : BIG;
        if (s < db) {
            /* ---- collision: absorb by weight, store, scatter, roulette */
            t.pos += s * t.dir;
            sw_flight(&sw, optics, t.L, mut, s);
            sw_collide(&sw, optics, logmu, t.L, op);
            long dw = convert_long_rte((float)W * op.x);
#ifdef CLPPM_FAULT_WRONG                /* the self-test's tests only: a miscompiled absorption */
            dw = convert_long_rte((float)dw * 1.5f);
#endif
            dw = dw < 0 ? 0 : (dw > W ? W : dw);
            absorbed[t.L] += dw; W -= dw;
            if (W > 0 && op.x < 1.0f) {
                if (P->capacity > 0u && t.pos.z > P->store_zmin) {
                    const float a_h = (float)W * (1.0f / W0F);
                    float F[HERO_C];
                    float q = 1.0f;
                    int keep = 1;
                    if (P->store_rule == 1) {
                        const float u = rng_u01(&srng);
                        const float ce = cone_cos(P, t.dir);
#ifndef STORE_EXACT                     /* tests: q for every event (the same decisions) */
                        keep = u <= clamp(P->store_scale * store_bound(store_imp, t.L, ce, sw_amax(&sw, a_h), t.pos.z),
                                          P->store_qmin, 1.0f);
#endif
                        if (keep) {
                            sw_weights(&sw, a_h, band_spi, F);
                            q = store_probability(P, ce, t.L, b, F, band_spi, optics, store_imp, t.pos.z);
                            keep = u <= q;
                        }
                    } else {
                        sw_weights(&sw, a_h, band_spi, F);
                    }
                    if (keep) {
                        const float iq = 1.0f / q;
                        for (int j = 0; j < HERO_C; ++j) F[j] *= iq;
                        uint i = atomic_inc(store_count);
                        if (i < P->capacity) {
                            store_pos_w[i] = (float4)(t.pos, F[0]);
                            store_dir_b[i] = (float4)(t.dir, (float)(b + 256 * t.L));   /* band, layer */
                            for (int j = 1; j < HERO_C; ++j) store_extra[(size_t)i * (HERO_C - 1) + j - 1] = F[j];
                        }
                    }
                }
                float ct = hg_sample_cos_t(op.y, op.z, rng_u01(&rng));
                t.dir = scatter_dir(t.dir, ct, rng_u01(&rng));
                sw_scatter(&sw, optics, t.L, op.y, ct);
                if (W < rr_w) {
                    if (rng_u01(&rng) * P->rr_m <= 1.0f) {
                        long g2 = W * (long)(P->rr_m) - W;
                        gain += g2; W += g2;
                        sw_scale(&sw, P->rr_m);
                    } else {
                        loss += W; W = 0;
                    }
                }
            } else if (W > 0) {
                /* pure absorber reached here only when mus = 0 and mua > 0: all absorbed */
                absorbed[t.L] += W; W = 0;
            }
            tau = neg_log_u01(rng_u01(&rng));
            continue;
        }
        /* ---- boundary */
        still = db < TRAP_UM ? still + 1 : 0;
        if (still > TRAPPED_STEPS) { lost += W; W = 0; break; }
        t.pos += db * t.dir;
        sw_flight(&sw, optics, t.L, mut, db);
        if (mut > 0.0f) { tau -= db * mut; tau = tau > 0.0f ? tau : 0.0f; }
        if (ev == EV_NONE) { lost += W; W = 0; break; }   /* semi-infinite, direction flat */
        if (ev == EV_TOP || ev == EV_BOTTOM) {
            const int up = (ev == EV_TOP);
            const int L2 = up ? t.L - 1 : t.L + 1;
            /* snap onto the interface (in core mode only flat interfaces raise TOP/BOTTOM) */
            t.pos.z = iface_z(iface, heights, P, up ? t.L : t.L + 1, col_index(P, t.ix, t.iy));
            const float n1 = layer_n[t.L];
            const float n2 = L2 < 0 ? P->n_above : (L2 >= NL ? P->n_below : layer_n[L2]);
            const float4 gn2 = (float4)(0.0f, 0.0f, up ? 1.0f : -1.0f, 0.0f);
            float4 d = (float4)(t.dir, 0.0f);
            const int through = cross_face(&d, gn2, up ? t.L : t.L + 1, t.L, L2, t.pos.x, t.pos.y, n1, n2,
                                           P, iface, smooth, rng_u01(&rng));
            t.dir = d.xyz;
            if (through) {
                if (L2 < 0 && reenter(&t, VOLUME_PASS, smooth, &rng)) { events++; continue; }
                if (L2 < 0) { rd += W; if (t.dir.z > P->rcone_cos) rcone += W; W = 0; break; }
                if (L2 >= NL) { tt += W; W = 0; break; }
                t.L = L2;
            }
            continue;
        }
        if (ev == EV_ZONE) { locate_column(&t, P); continue; }
        /* lateral: column wall or domain side */
        const int axis = (ev == EV_WALL_X || ev == EV_DOMAIN_X) ? 0 : 1;
        const int domain_only = (ev == EV_DOMAIN_X || ev == EV_DOMAIN_Y);
#ifndef FLAT
        const int oix = t.ix, oiy = t.iy;
        const float3 opos = t.pos;
#endif
        if (cross_wall(&t, P, axis, domain_only)) { lost += W; W = 0; break; }
#ifdef FLAT
        continue;
#else
        if (domain_only) { locate_column(&t, P); }
        const int col = col_index(P, t.ix, t.iy);
        const int L2 = layer_at(iface, heights, P, col, t.pos.z, t.L);
        if (L2 == t.L) continue;
        const float n1 = layer_n[t.L];
        const float n2 = L2 < 0 ? P->n_above : (L2 >= NL ? P->n_below : layer_n[L2]);
        const float4 gnw = axis == 0 ? (float4)(t.dir.x > 0.0f ? 1.0f : -1.0f, 0.0f, 0.0f, 0.0f)
                                     : (float4)(0.0f, t.dir.y > 0.0f ? 1.0f : -1.0f, 0.0f, 0.0f);
        float4 d = (float4)(t.dir, 0.0f);
        const int through = cross_face(&d, gnw, L2 < t.L ? t.L : t.L + 1, t.L, L2, t.pos.x, t.pos.y, n1, n2,
                                       P, iface, smooth, rng_u01(&rng));
        t.dir = d.xyz;
        if (through) {
            if (L2 < 0 && reenter(&t, VOLUME_PASS, smooth, &rng)) continue;
            if (L2 < 0) { rd += W; if (t.dir.z > P->rcone_cos) rcone += W; W = 0; break; }
            if (L2 >= NL) { tt += W; W = 0; break; }
            t.L = L2;
        } else {
            t.ix = oix; t.iy = oiy; t.pos = opos;      /* reflected back into the old column */
        }
#endif
    }

    if (spec) atom_add(tal + T_SPEC, spec);
    if (rd) atom_add(tal + T_RD, rd);
    if (tt) atom_add(tal + T_TT, tt);
    if (lost) atom_add(tal + T_LOST, lost);
    if (gain) atom_add(tal + T_RRGAIN, gain);
    if (loss) atom_add(tal + T_RRLOSS, loss);
    if (rcone) atom_add(tal + T_RCONE, rcone);
    for (int i = 0; i < NL; ++i)
        if (absorbed[i]) atom_add(tal + T_ABS0 + i, absorbed[i]);
}
