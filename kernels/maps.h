/* Chromophore maps: a layer's melanin M, blood B and oxygen saturation S varying from column to
 * column (clppm/scene/maps.py).  MAPS, a compile-time switch (volume.h's list); absent, this code
 * is compiled out and a uniform scene runs the walk it always ran.
 *
 * A layer's mu_a is linear in M, B and B S (skin.py: M mel + B deoxy + B S (oxy - deoxy) +
 * baseline), so a column holds those three numbers and the device the three basis spectra: its
 * mu_a in band b is the layer's own plus delta = dM mel(b) + dB deoxy(b) + d(BS) (oxy - deoxy)(b),
 * the d's the column's values minus the layer's own.  Scattering stays the layer's.
 *
 * Traced exactly by weighted delta tracking against a per-layer, per-band majorant
 * mu_maj = mu_s + mu_a(layer) + dmax, dmax >= every column's delta (the host's bound, padded for
 * float rounding): a mapped layer's free flights use mu_maj; at each tentative collision at x the
 * fraction mu_a(x)/mu_maj of the weight is absorbed there (the layer's tally), then the photon
 * scatters with probability mu_s/(mu_maj - mu_a(x)), else the collision is null (no turn, no
 * stored event).  Per tentative collision the expected absorbed weight is W mu_a(x)/mu_maj and the
 * scattering weight W mu_s/mu_maj: the collision densities of the medium itself, so unbiased.
 * Why delta tracking and not exact per-column crossings (inclusion.h's way): a column is 5 um
 * wide, a free flight in the dermis some 50-100 um, so crossings would add tens of steps per
 * flight in every mapped layer, where delta tracking adds only the null collisions, few where
 * dmax is small against mu_s (skin: mu_s 100-500 /cm, a freckle's extra mu_a a few tens).
 *
 * Where no column of a layer exceeds its own absorption in a band (dmax = 0, e.g. a uniform map
 * of the layer's own values) mu_maj is the layer's mu_t bit for bit, the absorbed fraction is
 * the layer's own (mu_a/mu_maj is computed by the host as the optics row's), and no random
 * number is drawn for the null decision: the same path and the same bits as without the map.
 *
 * The path tracer (flat layers) walks a mapped layer the same way, and each straight leg of a
 * light connection through one takes the layer's transmittance times map_leg_factor.  PPM's eye
 * pass and beam gather (flat layers, the relief) split an eye ray's pieces at the columns' walls and take
 * each piece's column's mu_t (the functions at the end of this file).
 *
 * One band per path (HERO_C = 1): the bands a path carries (spectral.h) would each need the
 * null-collision ratios of their own mu_a(x) at every tentative collision; the host builds map
 * scenes with one band per path.
 *
 * Rows after the materials' (NMAT*NB) and inclusions' (INC_ROWS*NINC) rows of optics:
 *   [MAP_BASE]                         (column dx, dy, nx, ny as int bits)
 *   [MAP_BASE + 1 + L]                 layer L's own (M, B, B S) and its columns' first row (int
 *                                      bits; -1: not mapped)
 *   [MAP_BAND(L, b)], [+ 1], [+ 2]     (mu_maj, mu_a/mu_maj, 1/mu_maj, dmax), (mu_s, mel, deoxy,
 *                                      oxy - deoxy), (dmin, 0, 0, 0), um^-1; dmin <= every
 *                                      column's delta <= dmax
 *   [MAP_COLS + first + iy nx + ix]    a column's (M, B, B S, 0)
 * A position beyond the maps' footprint takes the nearest edge column (infinite sides). */
#ifndef CLPPM_MAPS_H
#define CLPPM_MAPS_H

#include "inclusion.h"

#ifdef MAPS
#if HERO_C > 1
#error "chromophore maps trace one band per path (HERO_C = 1)"
#endif
#define MAP_BASE (NMAT * NB + INC_ROWS * NINC)
#define MAP_BAND(L, b) (MAP_BASE + 1 + NL + 3 * ((L) * NB + (b)))
#define MAP_COLS (MAP_BASE + 1 + NL + 3 * NL * NB)

/* the first column row of material m's map, -1 if m is not a mapped layer */
HOT int map_first(__global const float4* optics, int m) {
    return m < NL ? as_int(optics[MAP_BASE + 1 + m].w) : -1;
}

/* the majorant of mapped layer L in band b (its free flights' mu_t) */
HOT float map_majorant(__global const float4* optics, int L, int b) {
    return optics[MAP_BAND(L, b)].x;
}

/* delta: the change of mu_a in band b at (x, y) from mapped layer L's own (columns from row first).
 * Scalars across the calls (the path tracer's note on Intel's float3 arguments, pt.cl connect). */
HOT float map_delta(__global const float4* optics, int L, int b, int first, float x, float y,
                    __constant const Params* P) {
    const float4 g = optics[MAP_BASE];
    const int nx = as_int(g.z), ny = as_int(g.w);
    const int ix = clamp((int)floor((x - P->x0) / g.x), 0, nx - 1);
    const int iy = clamp((int)floor((y - P->y0) / g.y), 0, ny - 1);
    const float4 c = optics[MAP_COLS + first + iy * nx + ix];
    const float4 own = optics[MAP_BASE + 1 + L];
    const float4 r1 = optics[MAP_BAND(L, b) + 1];
    return (c.x - own.x) * r1.y + (c.y - own.y) * r1.z + (c.z - own.z) * r1.w;
}

/* At a tentative collision at p in mapped layer L (columns from row `first`), band b: the
 * fraction of the weight absorbed (x) and the null-collision coefficient mu_maj - mu_a(p) - mu_s
 * (y, >= 0; 0 where the column's mu_a reaches the majorant's) and mu_s (z). */
HOT float4 map_collision(__global const float4* optics, int L, int b, int first, float3 p,
                         __constant const Params* P) {
    const float delta = map_delta(optics, L, b, first, p.x, p.y, P);
    const float4 r0 = optics[MAP_BAND(L, b)];
    const float afrac = r0.y + delta * r0.z;
    const float dn = r0.w - delta;
    return (float4)(clamp(afrac, 0.0f, 1.0f), dn > 0.0f ? dn : 0.0f, optics[MAP_BAND(L, b) + 1].x, 0.0f);
}

/* The factor exp(-integral of delta) by which a straight leg of length len from p along d in
 * mapped layer L changes the transmittance the layer's own mu_t gives (the path tracer's light
 * connections): exp(-dmin len) times a ratio-tracking estimate of the rest (tentative points at
 * rate dmax - dmin, each multiplying by 1 - (delta - dmin)/(dmax - dmin), in [0, 1] where
 * dmin <= delta): unbiased, and no walk over the columns the leg crosses.  With inclusions, delta
 * is 0 at a point inside one (an inclusion has its own material and no map; its extinction
 * against the layer's is the leg's inclusion optical depth): the factor then exceeds 1 where
 * dmin > 0, still unbiased (the expectation of the product over the Poisson points is
 * exp(-integral of (delta - dmin)) whatever the sign). */
HOT float map_leg_factor(__global const float4* optics, int L, int b, int first, float x, float y, float z,
                         float dx, float dy, float dz, float len, __constant const Params* P, Rng* rng) {
    const float dmax = optics[MAP_BAND(L, b)].w, dmin = optics[MAP_BAND(L, b) + 2].x;
    const float R = dmax - dmin;
    float T = exp(-dmin * len);
#if NINC > 0
    if (!(R > 0.0f) && !(dmin != 0.0f)) return T;
    const float Rt = R > 0.0f ? R : fabs(dmin);           /* tentative points even for a constant delta */
#else
    if (!(R > 0.0f)) return T;
    const float Rt = R;
    (void)z; (void)dz;
#endif
    for (float s = neg_log_u01(rng_u01(rng)) / Rt; s < len && T > 0.0f; s += neg_log_u01(rng_u01(rng)) / Rt) {
#if NINC > 0
        const float delta = inclusion_mask(optics, (float3)(x + s * dx, y + s * dy, z + s * dz)) ? 0.0f
                          : map_delta(optics, L, b, first, x + s * dx, y + s * dy, P);
#else
        const float delta = map_delta(optics, L, b, first, x + s * dx, y + s * dy, P);
#endif
        T *= fmax(0.0f, 1.0f - (delta - dmin) / Rt);
    }
    return T;
}

/* ---- PPM's eye pass and gathers (flat layers and the relief; eye.cl, gather.cl).  The columns are piecewise
 * constant (map_delta's floor), so an eye-ray piece in a mapped layer ends at the walls between
 * columns (exact crossings, as at an inclusion's surface) and lies in one column; the gathers
 * find its column at its midpoint and take mu_t = the layer's + delta there in every band the
 * eye path carries.  Why crossings here and delta tracking in the photon pass: an eye ray in
 * the skin runs within a few degrees of the normal (refracted at the surface), so it crosses a
 * wall every ~50 um of path and a layer visit a few at most, and each piece's transmittance stays
 * one exponential per band: the gathers' exact integral of T over a point's cell needs no
 * estimate of it (ratio tracking would make T noisy in all 81 bands of every point). */

/* the first column row of material m's map where its columns change its mu_a in some band, -1
 * if m is not a mapped layer or its map is uniform at its own values (dmin = dmax = 0 in every
 * band: delta is 0, the eye pass splits nothing and a piece's mu_t is the layer's, bit for bit) */
HOT int map_split_first(__global const float4* optics, int m) {
    const int first = map_first(optics, m);
    if (first < 0) return -1;
    for (int b = 0; b < NB; ++b)
        if (optics[MAP_BAND(m, b)].w != 0.0f || optics[MAP_BAND(m, b) + 2].x != 0.0f) return first;
    return -1;
}

/* the column (ix, iy) of (x, y), as map_delta finds it (beyond the footprint: the edge column) */
HOT int2 map_column(__global const float4* optics, float x, float y, __constant const Params* P) {
    const float4 g = optics[MAP_BASE];
    const int nx = as_int(g.z), ny = as_int(g.w);
    return (int2)(clamp((int)floor((x - P->x0) / g.x), 0, nx - 1), clamp((int)floor((y - P->y0) / g.y), 0, ny - 1));
}

/* delta (map_delta's) at column (ix, iy) of mapped layer L (columns from row first), band b */
HOT float map_delta_col(__global const float4* optics, int L, int b, int first, int ix, int iy) {
    const int nx = as_int(optics[MAP_BASE].z);
    const float4 c = optics[MAP_COLS + first + iy * nx + ix];
    const float4 own = optics[MAP_BASE + 1 + L];
    const float4 r1 = optics[MAP_BAND(L, b) + 1];
    return (c.x - own.x) * r1.y + (c.y - own.y) * r1.z + (c.z - own.z) * r1.w;
}

/* The path length from (x, y) in column (ix, iy) along (dx, dy) to the next wall between two
 * columns (BIG where none is ahead: an edge column extends outwards), *axis its axis (0: x). */
HOT float map_wall(__global const float4* optics, float x, float y, float dx, float dy, int ix, int iy, int* axis,
                   __constant const Params* P) {
    const float4 g = optics[MAP_BASE];
    const int nx = as_int(g.z), ny = as_int(g.w);
    float sx = BIG, sy = BIG;
    if (dx > 0.0f && ix + 1 < nx) sx = (P->x0 + (float)(ix + 1) * g.x - x) / dx;
    else if (dx < 0.0f && ix > 0) sx = (P->x0 + (float)ix * g.x - x) / dx;
    if (dy > 0.0f && iy + 1 < ny) sy = (P->y0 + (float)(iy + 1) * g.y - y) / dy;
    else if (dy < 0.0f && iy > 0) sy = (P->y0 + (float)iy * g.y - y) / dy;
    *axis = sy < sx;
    return fmax(fmin(sx, sy), 0.0f);
}

/* mu_t of material m in band b at column (ix, iy) (first: map_split_first's, -1: m's own) */
HOT float map_mut(__global const float4* optics, int m, int b, int first, int ix, int iy) {
    return optics[m * NB + b].w + (first >= 0 ? map_delta_col(optics, m, b, first, ix, iy) : 0.0f);
}
#endif

#endif
