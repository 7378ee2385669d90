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
 * So the disc shrinks near a side to DISC_KAPPA d (not below DISC_FLOOR R: the variance grows
 * as 1/R^2), and a disc that still reaches past a side keeps only its part that is symmetric
 * about the centre: |u.x| < dx, |u.y| < dy for the distances dx, dy to the nearest x and y side
 * (the disc less both caps, or a rounded rectangle in a corner).  A symmetric window has zero
 * first moments, so a density linear across it is estimated exactly, and its weights stay
 * positive (a linear boundary kernel, Jones 1993, is exact too but negative far from the side:
 * it gave negative pixels on a 1 mm model).  Area: 4 R^2 quarter_area(dx / R, dy / R). */
#ifndef CLPPM_DISC_H
#define CLPPM_DISC_H

#ifndef DISC_KAPPA
#define DISC_KAPPA 0.5f
#endif
#ifndef DISC_FLOOR
#define DISC_FLOOR 0.125f
#endif

/* The disc's window: photons count where |u.x| < hx and |u.y| < hy (u = photon - centre); area
 * is that of the disc within the window; cut = 0 for a whole disc. */
typedef struct { float hx, hy, area; int cut; } DiscWindow;

inline float circ_prim(float y) {                 /* integral of sqrt(1 - y^2) dy from 0 */
    y = clamp(y, 0.0f, 1.0f);
    return 0.5f * (y * sqrt(fmax(1.0f - y * y, 0.0f)) + asin(y));
}

/* Area of {0 < x < ex, 0 < y < ey, x^2 + y^2 < 1}: a quarter of the unit disc within the window. */
inline float quarter_area(float ex, float ey) {
    ex = clamp(ex, 0.0f, 1.0f);
    ey = clamp(ey, 0.0f, 1.0f);
    const float yk = sqrt(fmax(1.0f - ex * ex, 0.0f));      /* the circle meets x = ex */
    float a = ex * fmin(ey, yk);
    if (ey > yk) a += circ_prim(ey) - circ_prim(yk);
    return a;
}

/* Distances from c to the nearest x side and the nearest y side. */
inline float2 side_distances(__constant const Params* P, float2 c) {
    return (float2)(fmin(c.x - P->x0, P->x0 + P->xw - c.x), fmin(c.y - P->y0, P->y0 + P->yw - c.y));
}

/* Distance from c to the nearest side, or a large number without sides. */
inline float side_distance(__constant const Params* P, float2 c) {
    if (P->lateral == 0) return 3.0e38f;
    const float2 s = side_distances(P, c);
    return fmin(s.x, s.y);
}

/* The disc's radius at c for a point whose radius is R (see above). */
inline float disc_radius(__constant const Params* P, float2 c, float R) {
    return clamp(DISC_KAPPA * side_distance(P, c), DISC_FLOOR * R, R);
}

/* The window of the disc (centre c, radius R). */
inline DiscWindow disc_window(__constant const Params* P, float2 c, float R) {
    DiscWindow w;
    w.hx = R; w.hy = R; w.area = PI_F * R * R; w.cut = 0;
    if (P->lateral == 0 || side_distance(P, c) >= R) return w;
    /* not below R/1000: a centre on the side would leave no window (the zone is 1000x
     * narrower than the floor disc; its first-order bias is negligible) */
    const float2 s = side_distances(P, c);
    w.hx = clamp(s.x, 1e-3f * R, R);
    w.hy = clamp(s.y, 1e-3f * R, R);
    w.area = 4.0f * R * R * quarter_area(w.hx / R, w.hy / R);
    w.cut = 1;
    return w;
}

#endif
