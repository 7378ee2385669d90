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
#include "inclusion.h"
#include "maps.h"
#ifndef FLAT
#include "surface.h"
#endif

/* The values of one launch of the photon pass (the scene's are Params).  Mirrors
 * clppm/compute/structs.py PHOTON_LAUNCH_DTYPE. */
typedef struct {
    uint pass;                  /* the pass: the random streams' counter */
    uint photon_offset;         /* the launch's first photon in the pass (low 32 bits) */
    uint offset_hi;             /* its high 32 bits (traces beyond 2^32 photons) */
    uint count;                 /* photons in this launch (the work items take them in turn) */
    uint capacity;              /* photon records the store buffers hold */
    uint qmc_s0, qmc_s1, qmc_s2;  /* the pass's random shift (Cranley-Patterson), 2^-32 units */
} PhotonLaunch;

#define W0F 274877906944.0f           /* 2^38 */
/* A photon between two interfaces that coincide in its column (a layer of no thickness there)
 * can be reflected back and forth by both without moving: after this many boundary events in a
 * row each shorter than 1 nm it is trapped for good and counted lost, as it would be after
 * max_events; no photon that moves is affected, so no image changes. */
#define TRAPPED_STEPS 1000
#define TRAP_UM 1e-3f
#define W0L ((long)274877906944L)

/* tally categories (per band); NC = T_ABS0 + NMAT: absorption per layer, then per inclusion */
/* T_RCONE: the part of T_RD leaving within the cone cos(theta) > rcone_cos around the normal
 * (not a separate fate: it is excluded from the energy balance) */
enum { T_SPEC = 0, T_RD, T_TT, T_LOST, T_RRGAIN, T_RRLOSS, T_MISS, T_RCONE, T_ABS0 };
#define NC (T_ABS0 + NMAT)

/* Event counters for bench/photons.py (-DPHOTON_COUNTERS; compiled out otherwise): per launch,
 * what the photons did, and per work item its loop steps (the host groups neighbouring work
 * items as SIMD lanes to estimate lane utilisation).  Not part of the estimator. */
enum { K_ENTERED = 0, K_MISSED, K_STEPS, K_COLLISIONS, K_STORED, K_IFACE, K_IFACE_SMOOTH,
       K_ZONE, K_WALL, K_DOMAIN, K_REENTER, K_TILE, K_LANES, K_LANE_ITERS, K_NCOUNT };
/* K_LANES: events done in photon_pass_lanes's fast phase, K_LANE_ITERS: its iterations (each
 * LANES lanes wide) */
#ifdef PHOTON_COUNTERS
typedef struct { uint k[K_NCOUNT]; } Counters;
#define COUNT(c, i) ((c)->k[i]++)
#else
typedef struct { uint none; } Counters;
#define COUNT(c, i)
#endif

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
 * photon's contribution (bench/studies/spots.py).  With I over all bands every stored photon
 * obeys F_j / q hrel_j T_j <= s_j / (pi_j store_scale) for every band it carries
 * (tests/test_spectral.py checks it); store_probability below computes q, store_bound a
 * per-layer upper bound of it. */

/* the cosine within the eye cone closest to d (the most favourable eye direction) */
inline float cone_cos(__constant const Params* P, float3 d) {
    const float c = d.z;
    return c >= P->store_cos ? 1.0f : c * P->store_cos + sqrt1(fmax1(0.0f, 1.0f - c * c)) * P->store_sin;
}

/* HG(g, ce) / max HG(g, .) */
inline float hg_rel(float g, float ce) {
    const float a = 1.0f + g * g - 2.0f * g * ce;
    const float omg = 1.0f - fabs(g);
    return omg * omg * omg / (a * sqrt1(a));
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
    return 1.001f * hrel * exp_neg(m.x + m.y * fmax1(0.0f, zg.x - z)) * amax;
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
        const float T = exp_neg(imp.x + op.w * fmax1(0.0f, imp.y - z));
        I += spi.x > 0.0f ? F[j] * (spi.y / spi.x) * hg_rel(op.y, ce) * T : 0.0f;
    }
    return clamp1(P->store_scale * I, P->store_qmin, 1.0f);
}


#ifndef FLAT
/* Tiles: the column grid in squares of TILE columns a side (photonpass.py TILE, tile_bounds),
 * with the lowest and highest point of every varying interface over each.  Where a photon's depth
 * lies between the lowest point of its layer's top and the highest of its bottom over the tile
 * it is in, no column of the tile can change its layer: it flies to the tile's walls or those
 * two planes instead of from column wall to column wall ("tile mode", between the core and the
 * column modes of common.h next_boundary).  Under the relief most of the skin's surface is a
 * plateau, so the depth band where layers vary somewhere is mostly flat over a tile: the column
 * walls crossed there were a third of all the photon's steps (bench/photons.py --events). */
enum { EV_TILE_X = 8, EV_TILE_Y, EV_TILE_Z };

/* lowest and highest point of interface k over tile (tx, ty) */
HOT float2 tile_bound(__constant const Params* P, __constant const float4* iface,
                      __global const float2* tile_z, int k, int tx, int ty) {
    const int v = IF_VAR(k);
    if (v < 0) return (float2)(IF_ZMIN(k), IF_ZMAX(k));
    const int ntx = (P->nx + TILE - 1) / TILE, nty = (P->ny + TILE - 1) / TILE;
    return tile_z[((size_t)v * nty + ty) * ntx + tx];
}

#ifdef SMOOTH_SURFACE
/* The photon pass's walk on the smooth surfaces outside the layer core: smoothwalk.h's
 * (smooth_boundary: the tile's walls, the domain's sides, the layer's top and bottom by
 * smooth_march, the same crossings), except that a flight goes on from tile to tile within one
 * call, up to PHOTON_TILES tiles: a free flight across tiles is one step of the photon's loop,
 * not one per tile wall (the walls were an eighth of the forearm's steps).  *tile is the tile the
 * step ends in (at its boundary, or at the collision within it). */
#define PHOTON_TILES 8

HOT float photon_smooth_boundary(const Track* t, __constant const Params* P, __constant const float4* iface,
                                 __global const float* heights, float smax, int* ev, int2* tile) {
    const float3 p = t->pos, d = t->dir;
    const int ntx = (P->nx + SMOOTH_CELL - 1) / SMOOTH_CELL, nty = (P->ny + SMOOTH_CELL - 1) / SMOOTH_CELL;
    const int first = d.z < 0.0f;          /* the face the ray moves toward first */
    int tx = t->ix / SMOOTH_CELL, ty = t->iy / SMOOTH_CELL;
    float s_start = 0.0f;
    for (int i = 0;; ++i) {
        float best = BIG;
        int e = EV_NONE;
        if (d.x > 0.0f ? tx + 1 < ntx : (d.x < 0.0f && tx > 0)) {
            const float s = (P->x0 + P->dx * (float)((tx + (d.x > 0.0f)) * SMOOTH_CELL) - p.x) / d.x;
            if (s < best) { best = s; e = EV_WALL_X; }
        }
        if (d.y > 0.0f ? ty + 1 < nty : (d.y < 0.0f && ty > 0)) {
            const float s = (P->y0 + P->dy * (float)((ty + (d.y > 0.0f)) * SMOOTH_CELL) - p.y) / d.y;
            if (s < best) { best = s; e = EV_WALL_Y; }
        }
        domain_sides(p, d, P, &best, &e);
        smooth_face(p, d, t->L + first, first, tx, ty, s_start, P, iface, heights, smax, &best, &e);
        smooth_face(p, d, t->L + 1 - first, 1 - first, tx, ty, s_start, P, iface, heights, smax, &best, &e);
        if ((e != EV_WALL_X && e != EV_WALL_Y) || best >= smax || i + 1 == PHOTON_TILES) {
            *ev = e;
            *tile = (int2)(tx, ty);
            return best > 0.0f ? best : 0.0f;
        }
        s_start = best;                    /* on into the next tile */
        if (e == EV_WALL_X) tx += d.x > 0.0f ? 1 : -1; else ty += d.y > 0.0f ? 1 : -1;
    }
}
#endif

/* Distance to the next boundary of the photon's constant region, by next_boundary (common.h)
 * in the core and where tile mode does not hold; in tile mode the tile's planes (*plane: the
 * one ahead), its inner walls and the domain's sides.  On the smooth walk outside the core,
 * photon_smooth_boundary, and *tile the tile the step ends in (else x < 0). */
HOT float photon_boundary(const Track* t, VOLUME_ARGS, __global const float2* tile_z, float smax, int* ev,
                          float* plane, int2* tile) {
    *tile = (int2)(-1, -1);
#ifdef SMOOTH_SURFACE
    {
        const float z = t->pos.z, dz = t->dir.z;
        const int in_core = (dz > 0.0f ? z < IF_ZMIN(t->L) : z <= IF_ZMIN(t->L)) &&
                            (dz < 0.0f ? z > IF_ZMAX(t->L + 1) : z >= IF_ZMAX(t->L + 1));
#ifndef PHOTON_PLAIN_WALK          /* tests: the walk of the other passes, smoothwalk.h's */
        if (!in_core) return photon_smooth_boundary(t, P, iface, heights, smax, ev, tile);
#endif
        return next_boundary(t, P, iface, heights, smax, ev);
    }
#endif
    const float3 d = t->dir;
    const float z = t->pos.z;
    const int L = t->L;
    const int in_core = (d.z > 0.0f ? z < IF_ZMIN(L) : z <= IF_ZMIN(L)) &&
                        (d.z < 0.0f ? z > IF_ZMAX(L + 1) : z >= IF_ZMAX(L + 1));
    const int tx = t->ix / TILE, ty = t->iy / TILE;
    const float top = in_core ? 0.0f : tile_bound(P, iface, tile_z, L, tx, ty).x;
    const float bot = in_core ? 0.0f : tile_bound(P, iface, tile_z, L + 1, tx, ty).y;
    const int in_tile = !in_core && (d.z > 0.0f ? z < top : z <= top) && (d.z < 0.0f ? z > bot : z >= bot);
    if (!in_tile) return next_boundary(t, P, iface, heights, smax, ev);
    float best = BIG;
    int e = EV_NONE;
    if (d.z > 0.0f) { best = (top - z) / d.z; e = EV_TILE_Z; *plane = top; }
    else if (d.z < 0.0f && bot > -BIG) { best = (bot - z) / d.z; e = EV_TILE_Z; *plane = bot; }
    /* inner walls only: at the domain's edge domain_sides decides (leaving or wrapping) */
    const int ntx = (P->nx + TILE - 1) / TILE, nty = (P->ny + TILE - 1) / TILE;
    if (d.x > 0.0f ? tx + 1 < ntx : (d.x < 0.0f && tx > 0)) {
        const float w = P->x0 + P->dx * (float)((tx + (d.x > 0.0f)) * TILE);
        const float s = (w - t->pos.x) / d.x;
        if (s < best) { best = s; e = EV_TILE_X; }
    }
    if (d.y > 0.0f ? ty + 1 < nty : (d.y < 0.0f && ty > 0)) {
        const float w = P->y0 + P->dy * (float)((ty + (d.y > 0.0f)) * TILE);
        const float s = (w - t->pos.y) / d.y;
        if (s < best) { best = s; e = EV_TILE_Y; }
    }
    domain_sides(t->pos, d, P, &best, &e);
    *ev = e;
    return best > 0.0f ? best : 0.0f;
}

/* The column of coordinate c (origin c0, pitch dc, n columns) that a photon moving by dd is in
 * or enters: on a wall, the one ahead (locate_column's floor gives the one above whatever the
 * direction, and tile mode would then meet that wall again at distance 0). */
HOT int column_ahead(float c, float c0, float dc, int n, float dd) {
    const float g = (c - c0) / dc;
    const float f = floor1(g);
    return clamp1((int)f - (g == f && dd < 0.0f), 0, n - 1);
}

HOT void locate_column_ahead(Track* t, __constant const Params* P) {
    t->ix = column_ahead(t->pos.x, P->x0, P->dx, P->nx, t->dir.x);
    t->iy = column_ahead(t->pos.y, P->y0, P->dy, P->ny, t->dir.y);
}

/* Onto the next tile across its wall on axis (0: x, 1: y): the wall's coordinate exactly and
 * the column beyond it, the other coordinate's column from the position. */
HOT void cross_tile(Track* t, __constant const Params* P, int axis) {
    if (axis == 0) {
        const int tx = t->ix / TILE, up = t->dir.x > 0.0f;
        t->pos.x = P->x0 + P->dx * (float)((tx + up) * TILE);
        t->ix = up ? (tx + 1) * TILE : tx * TILE - 1;
        t->iy = column_ahead(t->pos.y, P->y0, P->dy, P->ny, t->dir.y);
    } else {
        const int ty = t->iy / TILE, up = t->dir.y > 0.0f;
        t->pos.y = P->y0 + P->dy * (float)((ty + up) * TILE);
        t->iy = up ? (ty + 1) * TILE : ty * TILE - 1;
        t->ix = column_ahead(t->pos.x, P->x0, P->dx, P->nx, t->dir.x);
    }
}
#endif

/* The fates of one photon's weight, summed while it travels and added to the tallies of its
 * hero band when it ends (one atomic per fate that occurred, not per event). */
typedef struct {
    long spec, rd, tt, lost, gain, loss, rcone;
    long absorbed[NMAT];        /* per material: the layers, then the inclusions */
} Fates;

HOT void fates_clear(Fates* f) {
    f->spec = f->rd = f->tt = f->lost = f->gain = f->loss = f->rcone = 0;
    for (int i = 0; i < NMAT; ++i) f->absorbed[i] = 0;
}

HOT void fates_flush(const Fates* f, __global long* tal) {
    if (f->spec) atom_add(tal + T_SPEC, f->spec);
    if (f->rd) atom_add(tal + T_RD, f->rd);
    if (f->tt) atom_add(tal + T_TT, f->tt);
    if (f->lost) atom_add(tal + T_LOST, f->lost);
    if (f->gain) atom_add(tal + T_RRGAIN, f->gain);
    if (f->loss) atom_add(tal + T_RRLOSS, f->loss);
    if (f->rcone) atom_add(tal + T_RCONE, f->rcone);
    for (int i = 0; i < NMAT; ++i)
        if (f->absorbed[i]) atom_add(tal + T_ABS0 + i, f->absorbed[i]);
}

/* A direction of the point light's cone (around the model's top face, photonpass.py
 * source_params) from two uniforms. */
HOT float3 cone_dir(__constant const Params* P, float u1, float u2) {
    const float s = u1 * P->cone_omc;      /* 1 - cos(theta): exact for a narrow cone */
    const float2 cs = azimuth_cs(u2);
    return rotate_dir_cst((float3)(P->cax, P->cay, P->caz), 1.0f - s, sqrt1(fmax1(s * (2.0f - s), 0.0f)), cs.x, cs.y);
}

/* Whether the ray from the point light along d crosses the plane of the highest surface point
 * inside the model's footprint: the test hit_surface makes, in the same arithmetic.  A ray
 * outside it can only meet a side of the model below that plane, which takes no light. */
HOT int reaches_footprint(__constant const Params* P, float3 d) {
    if (d.z >= 0.0f) return 0;
    const float s = (P->z_top - P->sz) / d.z;
    const float x = P->sx + s * d.x, y = P->sy + s * d.y;
    return !(x < P->x0 || x > P->x0 + P->xw || y < P->y0 || y > P->y0 + P->yw);
}

/* The point light's emission: uniform over the solid angle of the model's footprint (the
 * rectangle of its top face) as seen from the light, by rejection from the cone around it.  The
 * first try takes the emission's uniforms (QMC or not), later ones the photon's own stream: each
 * accepted direction is uniform over the footprint's solid angle whatever the tries before it,
 * so the photon carries the light's power over that solid angle (photonpass.py
 * footprint_solid_angle), and the directions excluded are exactly those that missed the model.
 * Without a footprint (infinite sides, or the light at or below the top) the cone alone. */
HOT float3 footprint_dir(__constant const Params* P, float u1, float u2, Rng* rng) {
    float3 d = cone_dir(P, u1, u2);
    if (P->lateral == 0 || P->sz <= P->z_top) return d;
    for (int k = 0; k < 256 && !reaches_footprint(P, d); ++k)
        d = cone_dir(P, rng_u01(rng), rng_u01(rng));
    return d;
}

/* Emit photon id of the pass from the light: its random streams, hero band, position and
 * direction; then its first hit with the skin and the deterministic Fresnel split there (the
 * reflected part to f->spec).  Returns the weight that enters layer 0 (0 if it missed the
 * model: then the whole weight went to the missed tally). */
HOT long emit_photon(uint id, const PhotonLaunch* L, VOLUME_ARGS, __global const float* band_cdf,
                     __global const float* smooth, __global long* tallies, Rng* rng, Rng* srng,
                     Track* t, Spectral* sw, int* band, Fates* f) {
    rng_init(rng, id, L->pass, 2u * L->offset_hi, P->seed_lo, P->seed_hi);   /* eye rays: odd domain */
    /* storage decisions draw from a stream of their own: the path is the same under every rule */
    rng_init(srng, id, L->pass, (2u * L->offset_hi) | 0x80000001u, P->seed_lo, P->seed_hi);

    /* the emission's three uniforms: band, then direction (point) or footprint (wide beam) */
    float ue0, ue1, ue2;
    if (P->qmc) {
        ue0 = r3_u01(id, R3_A0, L->qmc_s0);
        ue1 = r3_u01(id, R3_A1, L->qmc_s1);
        ue2 = r3_u01(id, R3_A2, L->qmc_s2);
    } else {
        ue0 = P->fixed_band >= 0 ? 0.5f : rng_u01(rng);
        ue1 = P->src_kind != 0 ? rng_u01(rng) : 0.5f;
        ue2 = P->src_kind != 0 ? rng_u01(rng) : 0.5f;
    }
    const int b = P->fixed_band >= 0 ? P->fixed_band : sample_band(band_cdf, ue0);
    *band = b;
    sw_init(sw, b);

    if (P->src_kind == 2) {                       /* isotropic point light */
        t->dir = footprint_dir(P, ue1, ue2, rng);
        t->pos = (float3)(P->sx, P->sy, P->sz);
    } else {
        float3 d = (float3)(P->sdx, P->sdy, P->sdz);
        float fx = P->sx, fy = P->sy;
        if (P->src_kind == 1) {
            fx += (ue1 - 0.5f) * P->swx;
            fy += (ue2 - 0.5f) * P->swy;
        }
        /* start above the relief on the line through the footprint point (fx, fy, 0) */
        float back = (P->z_top + 1.0f) / (-d.z);
        t->pos = (float3)(fx, fy, 0.0f) - back * d;
        t->dir = d;
    }
    t->L = -1; t->ix = 0; t->iy = 0;
    float3 gn;
    if (!hit_surface(t, P, iface, heights, &gn)) {
        atom_add(tallies + (size_t)b * NC + T_MISS, W0L);
        t->L = -1;
        return 0;
    }

    /* deterministic Fresnel split at the smooth surface's normal */
    long W = W0L;
#ifdef FLAT
    float3 sn = (float3)(0.0f, 0.0f, 1.0f);
#else
    float3 sn = smooth_normal(P, iface, smooth, 0, t->pos.x, t->pos.y).xyz;
#endif
    float ci = -dot(t->dir, sn);
    if (ci <= 1e-6f) { sn = gn; ci = -dot(t->dir, gn); }
    float ct;
    const float R = fresnel_R(P->n_above, layer_n[0], ci, &ct);
    long ws = convert_long_rte((float)W * R);
    ws = clamp1(ws, 0L, W);
    f->spec += ws; W -= ws;
    if (W > 0) {
        float3 d = refract3(t->dir, sn, P->n_above / layer_n[0], ci, ct);
        if (dot(d, gn) >= 0.0f) d = reflect3(d, gn);
        t->dir = unit3(d);
    }
    sw_scale(sw, (float)W * (1.0f / W0F));           /* the entry's Fresnel transmission */
    return W;
}

/* The photon map's buffers: where an event is stored, and the launch's counters
 * ([0] events stored, [1] photons taken). */
typedef struct {
    __global float4* pos_w;            /* x, y, z, weight of the hero band */
    __global float4* dir_b;            /* direction, hero band + 256 layer */
    __global float* extra;             /* HERO_C-1 weights of the other bands */
    __global volatile uint* count;
    uint capacity;                     /* records the buffers hold (0: store nothing) */
} PhotonMap;


/* Store the scattering event at t with weight W, its storage uniform u already drawn (rule 1;
 * unused under rule 0) and, under rule 1, the bound of q already passed (store_bound): the bands'
 * weights, q, and the record if u <= q. */
HOT void store_record(__constant const Params* P, const Track* t, const Spectral* sw, long W, int b, float u,
                      __global const float2* store_imp, __global const float2* band_spi,
                      __global const float4* optics, __global const float* logmu, PhotonMap map,
                      Counters* cnt) {
    const float a_h = (float)W * (1.0f / W0F);
    float F[HERO_C];
    float q = 1.0f;
    sw_weights(sw, a_h, band_spi, optics, logmu, F);
    if (P->store_rule == 1) {
        q = store_probability(P, cone_cos(P, t->dir), t->L, b, F, band_spi, optics, store_imp, t->pos.z);
        if (!(u <= q)) return;
    }
    const float iq = 1.0f / q;
    for (int j = 0; j < HERO_C; ++j) F[j] *= iq;
    COUNT(cnt, K_STORED);
    uint i = atomic_inc(map.count);
    if (i < map.capacity) {
        map.pos_w[i] = (float4)(t->pos, F[0]);
        map.dir_b[i] = (float4)(t->dir, (float)(b + 256 * t->L));   /* band, layer */
        for (int j = 1; j < HERO_C; ++j) map.extra[(size_t)i * (HERO_C - 1) + j - 1] = F[j];
    }
}

/* Store the scattering event at t with weight W (importance storage under store rule 1: kept
 * with probability q and weighted 1/q; every event under rule 0).  The decision draws from the
 * storage stream srng only, so the path is the same under every rule.  Most events fail the
 * bound of q (store_bound) and cost no more. */
HOT void store_event(__constant const Params* P, const Track* t, Spectral* sw, long W, int b,
                     Rng* srng, __global const float2* store_imp, __global const float2* band_spi,
                     __global const float4* optics, __global const float* logmu, PhotonMap map,
                     Counters* cnt) {
    float u = 0.0f;
    if (P->store_rule == 1) {
        u = rng_u01(srng);
#ifndef STORE_EXACT                     /* tests: q for every event (the same decisions) */
        const float a_h = (float)W * (1.0f / W0F);
        if (!(u <= clamp1(P->store_scale * store_bound(store_imp, t->L, cone_cos(P, t->dir), sw_amax(sw, a_h),
                                                      t->pos.z), P->store_qmin, 1.0f))) return;
#endif
    }
    store_record(P, t, sw, W, b, u, store_imp, band_spi, optics, logmu, map, cnt);
}

/* A new direction from material m's Henyey-Greenstein phase function (op: its optics), then
 * Russian roulette below rr_threshold (survivors multiplied by rr_m, the gain and loss tallied). */
HOT void scatter_photon(__constant const Params* P, float4 op, int m, Track* t, Spectral* sw, long* W, Fates* f,
                        __global const float* logmu, Rng* rng) {
    float ct = hg_sample_cos_t(op.y, op.z, rng_u01(rng));
    t->dir = scatter_dir(t->dir, ct, rng_u01(rng));
    sw_scatter(sw, logmu, m, ct);
    if (*W >= (long)(P->rr_threshold * W0F)) return;
    if (rng_u01(rng) * P->rr_m <= 1.0f) {
        long g2 = *W * (long)(P->rr_m) - *W;
        f->gain += g2; *W += g2;
        sw_scale(sw, P->rr_m);
    } else {
        f->loss += *W; *W = 0;
    }
}

/* Depth roulette (render.depth_roulette_um; built with DEPTH_ROULETTE only, so the plain pass
 * carries none of it): below the storage depth a photon counts only through its return, which
 * the deeper it goes the less likely it is.  On first reaching each plane deep_z0 - k deep_dz
 * (k = 0 .. DEEP_PLANES - 1, checked after a scattering) it survives with probability 1/2, its
 * weight doubled, the gain and loss tallied with the weight roulette's: unbiased, and the deep
 * wanderings are cut short. */
#ifdef DEPTH_ROULETTE
#define DEEP_PLANES 6
HOT void deep_roulette(__constant const Params* P, const Track* t, Spectral* sw, long* W, Fates* f,
                       int* planes, Rng* rng) {
    if (t->pos.z >= P->deep_z0 || *planes >= DEEP_PLANES) return;
    const int reached = min((int)((P->deep_z0 - t->pos.z) / P->deep_dz) + 1, DEEP_PLANES);
    while (*planes < reached && *W > 0) {
        (*planes)++;
        if (rng_u01(rng) <= 0.5f) {
            f->gain += *W; *W += *W;
            sw_scale(sw, 2.0f);
        } else {
            f->loss += *W; *W = 0;
        }
    }
}
#else
#define deep_roulette(P, t, sw, W, f, planes, rng)
#endif

/* A collision after free path s in material m (a layer or an inclusion; op its optics): absorb by
 * weight (its albedo), store the event inside the storage depth, scatter; then the next optical
 * depth to travel. */
HOT void collide(__constant const Params* P, float4 op, int m, float s, Track* t, Spectral* sw, long* W, int b,
                 Fates* f, int* planes, float* tau, Rng* rng, Rng* srng, __global const float2* store_imp,
                 __global const float2* band_spi, __global const float4* optics,
                 __global const float* logmu, PhotonMap map, Counters* cnt) {
    COUNT(cnt, K_COLLISIONS);
    t->pos += s * t->dir;
    sw_flight(sw, optics, logmu, m, op.w, s);
    sw_collide(sw, logmu, m);
    long dw = convert_long_rte((float)*W * op.x);
#ifdef CLPPM_FAULT_WRONG                /* the self-test's tests only: a miscompiled absorption */
    dw = convert_long_rte((float)dw * 1.5f);
#endif
    dw = dw < 0 ? 0 : (dw > *W ? *W : dw);
    f->absorbed[m] += dw; *W -= dw;
    if (*W > 0 && op.x < 1.0f) {
        if (map.capacity > 0u && t->pos.z > P->store_zmin)
            store_event(P, t, sw, *W, b, srng, store_imp, band_spi, optics, logmu, map, cnt);
        scatter_photon(P, op, m, t, sw, W, f, logmu, rng);
        deep_roulette(P, t, sw, W, f, planes, rng);
    } else if (*W > 0) {
        /* pure absorber reached here only when mus = 0 and mua > 0: all absorbed */
        f->absorbed[m] += *W; *W = 0;
    }
    *tau = neg_log_u01(rng_u01(rng));
}

#ifdef MAPS
/* A tentative collision after free path s in mapped layer m (maps.h: flights at the majorant maj,
 * columns from row first): absorb the fraction mu_a(x)/maj by weight, then a null collision (no
 * turn, no stored event, a new optical depth) with probability (maj - mu_a(x) - mu_s)/(maj -
 * mu_a(x)), else collide() as in a uniform layer (its scattering, storage and roulettes).  No
 * random number is drawn where the null probability is 0 (a column at the majorant's mu_a). */
HOT void collide_mapped(__constant const Params* P, float4 op, float maj, int first, int m, float s, Track* t,
                        Spectral* sw, long* W, int b, Fates* f, int* planes, float* tau, Rng* rng, Rng* srng,
                        __global const float2* store_imp, __global const float2* band_spi,
                        __global const float4* optics, __global const float* logmu, PhotonMap map, Counters* cnt) {
    const float4 c = map_collision(optics, m, b, first, t->pos + s * t->dir, P);
    op.x = c.x;
    op.w = maj;
    if (c.y > 0.0f && rng_u01(rng) * (c.z + c.y) < c.y) {
        COUNT(cnt, K_COLLISIONS);
        t->pos += s * t->dir;
        long dw = convert_long_rte((float)*W * op.x);
        dw = dw < 0 ? 0 : (dw > *W ? *W : dw);
        f->absorbed[m] += dw; *W -= dw;
        *tau = neg_log_u01(rng_u01(rng));
        return;
    }
    collide(P, op, m, s, t, sw, W, b, f, planes, tau, rng, srng, store_imp, band_spi, optics, logmu, map, cnt);
}
#endif

/* The photon went through a face into layer L2: out of the top (unless the relief takes it
 * back in: returns 1), out of the bottom, or on in layer L2. */
HOT int enter_layer(Track* t, int L2, long* W, Fates* f, VOLUME_ARGS, __global const float* smooth,
                    Rng* rng, Counters* cnt) {
    if (L2 < 0 && reenter(t, VOLUME_PASS, smooth, rng)) {
        COUNT(cnt, K_REENTER);
#if NINC > 0
        t->inside = inclusion_mask(optics, t->pos);         /* back in somewhere else */
#endif
        return 1;
    }
    if (L2 < 0) { f->rd += *W; if (t->dir.z > P->rcone_cos) f->rcone += *W; *W = 0; return 0; }
    if (L2 >= NL) { f->tt += *W; *W = 0; return 0; }
    t->L = L2;
    return 0;
}

/* The photon is at the top (up) or bottom face of its layer's slab in its column: snap onto
 * that interface (in core mode only flat interfaces raise TOP/BOTTOM), then reflect or refract
 * there.  Returns 1 if it left through the top and the relief took it back in. */
HOT int cross_interface(int up, Track* t, long* W, Fates* f, VOLUME_ARGS, __global const float* smooth,
                        Rng* rng, Counters* cnt) {
    COUNT(cnt, K_IFACE);
    const int L2 = up ? t->L - 1 : t->L + 1;
    const int k = up ? t->L : t->L + 1;
    const float n1 = layer_n[t->L];
    const float n2 = L2 < 0 ? P->n_above : (L2 >= NL ? P->n_below : layer_n[L2]);
    float4 gn2 = (float4)(0.0f, 0.0f, up ? 1.0f : -1.0f, 0.0f);
#ifndef FLAT
    if (n1 != n2 && IF_VAR(k) >= 0) COUNT(cnt, K_IFACE_SMOOTH);
#endif
    float4 d = (float4)(t->dir, 0.0f);
#ifdef SMOOTH_SURFACE
    /* at the crossing on the smooth surface itself: its normal is the face's */
    gn2 = face_normal(P, iface, smooth, k, t->L, L2, t->pos.x, t->pos.y, gn2);
    const int through = fresnel_cross(&d, gn2, gn2, n1, n2, rng_u01(rng));
#else
    t->pos.z = iface_z(iface, heights, P, k, col_index(P, t->ix, t->iy));
    const int through = cross_face(&d, gn2, k, t->L, L2, t->pos.x, t->pos.y, n1, n2,
                                   P, iface, smooth, rng_u01(rng));
#endif
    t->dir = d.xyz;
    return through && enter_layer(t, L2, W, f, VOLUME_PASS, smooth, rng, cnt);
}

/* The photon meets a column wall or a side of the domain (ev): into the next column (or lost
 * out of the side); in a relief build, if that column's interfaces put it in another layer,
 * reflect or refract at the wall's face into it, or back into the old column. */
HOT void cross_lateral(int ev, Track* t, long* W, Fates* f, VOLUME_ARGS, __global const float* smooth,
                       Rng* rng, Counters* cnt) {
    const int axis = (ev == EV_WALL_X || ev == EV_DOMAIN_X) ? 0 : 1;
    const int domain_only = (ev == EV_DOMAIN_X || ev == EV_DOMAIN_Y);
#ifdef PHOTON_COUNTERS
    if (domain_only) COUNT(cnt, K_DOMAIN); else COUNT(cnt, K_WALL);
#endif
#ifdef SMOOTH_SURFACE
    /* a tile's wall or a side: the layers do not change across it */
    if (!domain_only) { cross_cell(t, P, axis); return; }
    if (cross_wall(t, P, axis, 1)) { f->lost += *W; *W = 0; return; }
    locate_column(t, P);
    return;
#endif
#ifndef FLAT
    const int oix = t->ix, oiy = t->iy;
    const float3 opos = t->pos;
#endif
    if (cross_wall(t, P, axis, domain_only)) { f->lost += *W; *W = 0; return; }
#ifndef FLAT
    if (domain_only) { locate_column(t, P); }
    const int col = col_index(P, t->ix, t->iy);
    const int L2 = layer_at(iface, heights, P, col, t->pos.z, t->L);
    if (L2 == t->L) return;
    const float n1 = layer_n[t->L];
    const float n2 = L2 < 0 ? P->n_above : (L2 >= NL ? P->n_below : layer_n[L2]);
    if (n1 != n2 && IF_VAR(L2 < t->L ? t->L : t->L + 1) >= 0) COUNT(cnt, K_IFACE_SMOOTH);
    COUNT(cnt, K_IFACE);
    const float4 gnw = axis == 0 ? (float4)(t->dir.x > 0.0f ? 1.0f : -1.0f, 0.0f, 0.0f, 0.0f)
                                 : (float4)(0.0f, t->dir.y > 0.0f ? 1.0f : -1.0f, 0.0f, 0.0f);
    float4 d = (float4)(t->dir, 0.0f);
    const int through = cross_face(&d, gnw, L2 < t->L ? t->L : t->L + 1, t->L, L2, t->pos.x, t->pos.y, n1, n2,
                                   P, iface, smooth, rng_u01(rng));
    t->dir = d.xyz;
    if (through) {
        enter_layer(t, L2, W, f, VOLUME_PASS, smooth, rng, cnt);
    } else {
        t->ix = oix; t->iy = oiy; t->pos = opos;      /* reflected back into the old column */
    }
#endif
}

/* One event of a live photon (W > 0): its free path against the next boundary of its region,
 * then a collision (collide) or the boundary's crossing.  The photon has ended when *W <= 0. */
HOT void photon_event(Track* t, Spectral* sw, long* W, int b, Fates* f, int* events, int* planes, int* still,
                      float* tau, Rng* rng, Rng* srng, VOLUME_ARGS, __global const float2* store_imp,
                      __global const float2* band_spi, __global const float* logmu,
                      __global const float* smooth, __global const float2* tile_z, PhotonMap map,
                      Counters* cnt) {
    if (++*events > P->max_events) { f->lost += *W; *W = 0; return; }
    COUNT(cnt, K_STEPS);
    const int m = MATERIAL(t);                  /* the layer, or the inclusion the photon is in */
    const float4 op = optics[m * NB + b];       /* mua/mut, g, 1/(2g), mut in um^-1 */
#ifdef MAPS
    const int mfirst = map_first(optics, m);    /* a mapped layer: flights at its majorant */
    const float mut = mfirst >= 0 ? map_majorant(optics, m, b) : op.w;
#else
    const float mut = op.w;
#endif
    int ev;
    const float s = mut > 0.0f ? *tau / mut : BIG;
#ifdef FLAT
    float db = next_boundary(t, P, iface, heights, s, &ev);
#else
    float plane = 0.0f;
    int2 tile;
    float db = photon_boundary(t, VOLUME_PASS, tile_z, s, &ev, &plane, &tile);
#ifdef SMOOTH_SURFACE
    if (tile.x >= 0) { t->ix = tile.x * SMOOTH_CELL; t->iy = tile.y * SMOOTH_CELL; }
#endif
#endif
#if NINC > 0
    int inc = -1;                                /* an inclusion's surface before the boundary */
    const float dinc = next_inclusion(optics, t->pos, t->dir, t->inside, INCLUSIONS_OF_LAYER(optics, t->L), &inc);
    const int at_inc = dinc <= db;
    if (at_inc) db = dinc;
#endif
    if (s < db) {
#ifdef MAPS
        if (mfirst >= 0) {
            collide_mapped(P, op, mut, mfirst, m, s, t, sw, W, b, f, planes, tau, rng, srng, store_imp, band_spi,
                           optics, logmu, map, cnt);
            return;
        }
#endif
        collide(P, op, m, s, t, sw, W, b, f, planes, tau, rng, srng, store_imp, band_spi, optics, logmu, map, cnt);
        return;
    }
    /* ---- boundary: move onto it */
    *still = db < TRAP_UM ? *still + 1 : 0;
    if (*still > TRAPPED_STEPS) { f->lost += *W; *W = 0; return; }
    t->pos += db * t->dir;
    sw_flight(sw, optics, logmu, m, mut, db);
    if (mut > 0.0f) { *tau -= db * mut; *tau = *tau > 0.0f ? *tau : 0.0f; }
#if NINC > 0
    if (at_inc) { t->inside ^= 1 << inc; locate_column(t, P); return; }   /* into or out of it */
#endif
    if (ev == EV_NONE) { f->lost += *W; *W = 0; return; }   /* semi-infinite, direction flat */
    if (ev == EV_TOP || ev == EV_BOTTOM) {
        if (cross_interface(ev == EV_TOP, t, W, f, VOLUME_PASS, smooth, rng, cnt)) ++*events;
        return;
    }
    if (ev == EV_ZONE) { COUNT(cnt, K_ZONE); locate_column(t, P); return; }
#ifndef FLAT
    if (ev == EV_TILE_Z) { COUNT(cnt, K_ZONE); t->pos.z = plane; locate_column_ahead(t, P); return; }
    if (ev == EV_TILE_X || ev == EV_TILE_Y) { COUNT(cnt, K_TILE); cross_tile(t, P, ev == EV_TILE_Y); return; }
#endif
    cross_lateral(ev, t, W, f, VOLUME_PASS, smooth, rng, cnt);
#if NINC > 0
    if (ev == EV_DOMAIN_X || ev == EV_DOMAIN_Y) t->inside = inclusion_mask(optics, t->pos);  /* wrapped */
#endif
}

/* A photon's start: emission, and its walk's counters and first optical depth.  Returns whether
 * it entered the skin (its fates are flushed when it ends). */
HOT int photon_start(uint id, const PhotonLaunch* L, VOLUME_ARGS, __global const float* band_cdf,
                     __global const float* smooth, __global long* tallies, Rng* rng, Rng* srng, Track* t,
                     Spectral* sw, int* b, Fates* f, long* W, int* events, int* planes, int* still, float* tau,
                     Counters* cnt) {
    *W = emit_photon(id, L, VOLUME_PASS, band_cdf, smooth, tallies, rng, srng, t, sw, b, f);
#ifdef PHOTON_COUNTERS
    if (t->L < 0) COUNT(cnt, K_MISSED); else COUNT(cnt, K_ENTERED);
#endif
    const int live = t->L >= 0;
#if NINC > 0
    t->inside = live ? inclusion_mask(optics, t->pos) : 0;
#endif
    *events = 0;
    *planes = 0;
    *still = 0;
    *tau = neg_log_u01(rng_u01(rng));
    return live;
}

/* The photons of a launch are drawn from a shared counter by a fixed number of work items
 * (persistent threads): a work item whose photon has ended takes the next one at the top of the
 * same loop, so neighbouring work items that a SIMD compiler runs in lanes (Intel's CPU runtime,
 * a GPU) stay busy however unequal the paths are (one photon per work item left on average
 * three quarters of the lanes idle, bench/photons.py --events).  A photon's path depends on its
 * id alone, and the tallies are integer sums: the same results whichever work item traces it. */
__kernel void photon_pass(const PhotonLaunch launch,
                          VOLUME_ARGS,
                          __global const float2* store_imp,  /* [NL*NB] see store_probability */
                          __global const float* band_cdf,    /* hero selection pi, as a cdf */
                          __global const float2* band_spi,   /* [NB] light power s, pi (spectral.h) */
                          __global const float* logmu,       /* the band table (spectral.h) */
                          __global float4* store_pos_w,      /* PhotonMap.pos_w */
                          __global float4* store_dir_b,      /* PhotonMap.dir_b */
                          __global float* store_extra,       /* PhotonMap.extra */
                          __global volatile uint* store_count,   /* [0] stored, [1] photons taken */
                          __global long* tallies,
                          __global const float* smooth,     /* Volume.smooth (relief builds) */
                          __global const float2* tile_z,    /* tile_bounds (relief builds) */
                          __global long* counters,          /* PHOTON_COUNTERS builds only */
                          __global uint* lane_steps)        /* PHOTON_COUNTERS builds only */
{
    const PhotonMap map = { store_pos_w, store_dir_b, store_extra, store_count, launch.capacity };
    Counters cnt;
#ifdef PHOTON_COUNTERS
    for (int k = 0; k < K_NCOUNT; ++k) cnt.k[k] = 0u;
    uint iterations = 0u;
#endif
    Rng rng, srng;
    Spectral sw;
    Track t;
    Fates f;
    fates_clear(&f);
    long W = 0;
    int b = 0, events = 0, live = 0, planes = 0;   /* depth-roulette planes passed */
    int still = 0;                                     /* boundary events in a row under TRAP_UM */
    float tau = 0.0f;
    for (;;) {
#ifdef PHOTON_COUNTERS
        iterations++;
#endif
        if (W <= 0) {
            /* ---- the photon has ended (or none yet): its tallies, then the next photon */
            if (live) { fates_flush(&f, tallies + (size_t)b * NC); fates_clear(&f); live = 0; }
            const uint k = atomic_inc(store_count + 1);
            if (k >= launch.count) break;
            live = photon_start(launch.photon_offset + k, &launch, VOLUME_PASS, band_cdf, smooth, tallies, &rng,
                                &srng, &t, &sw, &b, &f, &W, &events, &planes, &still, &tau, &cnt);
            continue;
        }
        photon_event(&t, &sw, &W, b, &f, &events, &planes, &still, &tau, &rng, &srng, VOLUME_PASS, store_imp,
                     band_spi, logmu, smooth, tile_z, map, &cnt);
    }
#ifdef PHOTON_COUNTERS
    for (int k = 0; k < K_NCOUNT; ++k)
        if (cnt.k[k]) atom_add(counters + k, (long)cnt.k[k]);
    lane_steps[2 * get_global_id(0)] = cnt.k[K_STEPS];
    lane_steps[2 * get_global_id(0) + 1] = iterations;
#endif
}

#if defined(LANES) && LANES > 1
/* the same pass in explicit SIMD lanes (CPUs); an include line holds nothing else: pyopencl's
 * program cache follows only such lines to the headers it keys binaries by */
#include "photon_lanes.h"

/* photon_pass in lanes: the same arguments, launched with a LANES-th of its work items */
__kernel
void photon_pass_lanes(const PhotonLaunch launch,
                       VOLUME_ARGS,
                       __global const float2* store_imp,
                       __global const float* band_cdf,
                       __global const float2* band_spi,
                       __global const float* logmu,
                       __global float4* store_pos_w,
                       __global float4* store_dir_b,
                       __global float* store_extra,
                       __global volatile uint* store_count,
                       __global long* tallies,
                       __global const float* smooth,
                       __global const float2* tile_z,
                       __global long* counters,
                       __global uint* lane_steps)
{
    const PhotonMap map = { store_pos_w, store_dir_b, store_extra, store_count, launch.capacity };
    Counters cnt;
#ifdef PHOTON_COUNTERS
    for (int k = 0; k < K_NCOUNT; ++k) cnt.k[k] = 0u;
    uint iterations = 0u;
#endif
    Lanes S;
    for (int i = 0; i < LANES; ++i) {
        S.W.s[i] = 0; S.live.s[i] = 0; S.on.s[i] = 1; S.fast.s[i] = 0; S.b.s[i] = 0; S.L.s[i] = 0;
        S.gain.s[i] = 0; S.loss.s[i] = 0; S.acur.s[i] = 0; S.rnv.s[i] = 0;
        fates_clear(&S.f[i]);
    }
    for (;;) {
        int on = 0;
        for (int i = 0; i < LANES; ++i) {
            if (S.on.s[i] && !S.fast.s[i])
                lane_slow(&S, i, &launch, VOLUME_PASS, store_imp, band_cdf, band_spi, logmu, store_count, tallies,
                          smooth, tile_z, map, &cnt);
            on += S.on.s[i];
        }
        if (!on) break;
        const int n = lanes_fast(&S, P, optics, logmu, store_imp, band_spi, map, &cnt);
#ifdef PHOTON_COUNTERS
        cnt.k[K_STEPS] += n;
        cnt.k[K_COLLISIONS] += n;
        cnt.k[K_LANES] += n;
        iterations++;
#endif
    }
#ifdef PHOTON_COUNTERS
    for (int k = 0; k < K_NCOUNT; ++k)
        if (cnt.k[k]) atom_add(counters + k, (long)cnt.k[k]);
    lane_steps[2 * get_global_id(0)] = cnt.k[K_STEPS];
    lane_steps[2 * get_global_id(0) + 1] = iterations;
#endif
}
#endif
