/* The beam estimator's disc near the model's open sides (kernels/gather.cl).
 *
 * Beyond an open side there is no skin and no photon, and the in-scattered radiance S falls
 * steeply over the outer few hundred um (photons leave through the side).  Two biases follow
 * for a disc of radius R centred at distance d < R from a side:
 *  - first order: a disc cut by the side averages S over its inside part only, whose centroid
 *    lies inward, where S is higher (+3 to +10 % in the corner 10x10-pixel squares of the flat
 *    forearm at 320x240 against the path tracer, with the cut disc's area as normaliser);
 *  - second order: a whole disc averages the concave fall of S towards the side (R^2/8 d2S/dx2:
 *    -1.3 to -3.2 % one square in from the sides).
 * S changes across a side, not along it.  So the disc keeps its radius R and only narrows across
 * a side at distance d < R / (2 DISC_KAPPA), to the window |u.x| < hx with hx = u + 2 u^2 / R,
 * u = DISC_KAPPA d (not below DISC_FLOOR R, never past the side), and likewise in y: the disc
 * within a centred rectangle, a band along a side, a rounded rectangle in a corner.  Next to the
 * side hx is about DISC_KAPPA d, where S bends most; it grows to the whole R at d = 4R, so the
 * inside keeps the whole disc's photons.  d is that of the eye ray's point at the photon's depth
 * (gather.cl), as the ray drifts sideways with depth.  The window's second-order bias across the
 * side is that of a disc of radius hx (hx^2/6 d2S/dx2 for a narrow band), while it holds about
 * 4 hx R of area instead of pi hx^2: less noise than shrinking the whole disc (the earlier rule,
 * which speckled the outermost pixels).  Measured at 320x240 against the path tracer (6 passes,
 * seeds 1 and 2; the outermost 10x10-pixel squares along the middle of the four sides, mean):
 * hx = d/4 -0.86 %, d/8 (from R/2 of the side on) -0.19 %, this rule -0.16 %; the noise per
 * square inside: +12 % for d/8, which narrows out to 8R, +2 % for this rule, against d/4.  A
 * window symmetric about the centre has zero
 * first moments, so a density linear across it is estimated exactly, and its weights stay
 * positive (a linear boundary kernel, Jones 1993, is exact too but negative far from the side:
 * it gave negative pixels on a 1 mm model).  Area: 4 R^2 quarter_area(hx / R, hy / R). */
#ifndef CLPPM_DISC_H
#define CLPPM_DISC_H

#include "volume.h"

#ifndef DISC_KAPPA
#define DISC_KAPPA 0.125f
#endif
#ifndef DISC_FLOOR
#define DISC_FLOOR 0.0625f
#endif

/* The disc's window: photons count where |u.x| < hx and |u.y| < hy (u = photon - centre); area
 * is that of the disc within the window; cut = 0 for a whole disc. */
typedef struct { float hx, hy, area; int cut; } DiscWindow;

inline float circ_prim(float y) {                 /* integral of sqrt1(1 - y^2) dy from 0 */
    y = clamp1(y, 0.0f, 1.0f);
    return 0.5f * (y * sqrt1(fmax1(1.0f - y * y, 0.0f)) + asin(y));
}

/* Area of {0 < x < ex, 0 < y < ey, x^2 + y^2 < 1}: a quarter of the unit disc within the window. */
inline float quarter_area(float ex, float ey) {
    ex = clamp1(ex, 0.0f, 1.0f);
    ey = clamp1(ey, 0.0f, 1.0f);
    const float yk = sqrt1(fmax1(1.0f - ex * ex, 0.0f));      /* the circle meets x = ex */
    float a = ex * fmin1(ey, yk);
    if (ey > yk) a += circ_prim(ey) - circ_prim(yk);
    return a;
}

/* Distances from c to the nearest x side and the nearest y side. */
inline float2 side_distances(__constant const Params* P, float2 c) {
    return (float2)(fmin1(c.x - P->x0, P->x0 + P->xw - c.x), fmin1(c.y - P->y0, P->y0 + P->yw - c.y));
}

/* The window's half-width across a side at distance d (see above): DISC_KAPPA d (1 + 2 DISC_KAPPA d / R), not below
 * DISC_FLOOR R, never past the side (not below R/1000 there: a centre on the side would leave
 * no window; that zone is 1000x narrower than the floor and its first-order bias negligible),
 * and R where the side is far. */
inline float side_half_width(float d, float R) {
    const float u = DISC_KAPPA * d;
    return clamp1(fmin1(fmax1(u + 2.0f * u * u / R, DISC_FLOOR * R), d), 1e-3f * R, R);
}

/* Beyond this distance from a side the window is the whole disc (side_half_width reaches R). */
inline float window_reach(float R) { return 0.5f * R / DISC_KAPPA; }

/* The area of the disc of radius R within the window |u.x| < hx, |u.y| < hy (window_at's). */
inline float window_area(float hx, float hy, float R) {
    return (hx < R || hy < R) ? 4.0f * R * R * quarter_area(hx / R, hy / R) : PI_F * R * R;
}

/* The window of a disc of radius R whose centre lies s.x, s.y from the nearest x and y side. */
inline DiscWindow window_at(float2 s, float R) {
    DiscWindow w;
    w.hx = side_half_width(s.x, R);
    w.hy = side_half_width(s.y, R);
    w.cut = w.hx < R || w.hy < R;
    w.area = window_area(w.hx, w.hy, R);
    return w;
}

#endif
