/* The beam estimator's disc near the model's open sides (kernels/gather.cl).
 *
 * Beyond an open side there is no skin and no photon, and the in-scattered radiance S falls
 * steeply over the outer few hundred um (photons leave through the side).  Two biases follow
 * for a disc of radius R centred at distance d < R from a side:
 *  - first order: a disc cut by the side averages S over its inside part only, whose centroid
 *    lies inward, where S is higher (+3 to +10 % in the corner 10x10-pixel squares of the flat
 *    forearm at 320x240 against the path tracer, with the plain area normalisation);
 *  - second order: a whole disc averages the concave fall of S towards the side (R^2/8 d2S/dx2,
 *    -3 % one square in from the bottom side).
 * The disc therefore shrinks near a side to DISC_KAPPA d (not below DISC_FLOOR R: the variance
 * grows as 1/R^2), and a disc that is still cut gets a linear boundary kernel (Jones 1993,
 * "Simple boundary correction for kernel density estimation"): the weight
 *     k(u) = a + b . u        (u = photon - disc centre, in units of the disc's radius)
 * with a, b chosen so that k integrates to 1 and has zero first moments over the part D of the
 * disc inside the model's footprint.  Then a density linear across the disc is estimated
 * exactly, cut or not; k may be negative far from the side (the price of first-order
 * unbiasedness), the pixel sums stay positive in expectation.  The moments of D (the unit disc
 * less one x side and one y side: a corner cuts both) are integrated in y = sin(theta) with
 * 8-point Gauss-Legendre between the kinks where a side meets the circle; the x integrals of
 * each slice are closed-form, so the quadrature error is at float precision. */
#ifndef CLPPM_DISC_H
#define CLPPM_DISC_H

#ifndef DISC_KAPPA
#define DISC_KAPPA 0.5f
#endif
#ifndef DISC_FLOOR
#define DISC_FLOOR 0.125f
#endif

/* k(u) = a + bx u.x + by u.y (u in units of R); m0 = area of D / R^2 (pi for a whole disc) */
typedef struct { float a, bx, by, m0; } DiscKernel;

__constant float GL8_X[8] = {-0.9602898565f, -0.7966664774f, -0.5255324099f, -0.1834346425f,
                             0.1834346425f, 0.5255324099f, 0.7966664774f, 0.9602898565f};
__constant float GL8_W[8] = {0.1012285363f, 0.2223810345f, 0.3137066459f, 0.3626837834f,
                             0.3626837834f, 0.3137066459f, 0.2223810345f, 0.1012285363f};

/* Moments m[0..5] = (1, x, y, x^2, xy, y^2) over theta in [t0, t1] of the unit disc's slices
 * y = sin(theta), x from max(-ex, -cos(theta)) to cos(theta) (dy = cos(theta) dtheta). */
inline void disc_moments_seg(float ex, float t0, float t1, float* m) {
    const float h = 0.5f * (t1 - t0), c = 0.5f * (t1 + t0);
    for (int i = 0; i < 8; ++i) {
        const float t = c + h * GL8_X[i];
        const float y = sin(t), ct = cos(t);
        const float xh = ct, xl = fmax(-ex, -ct);
        const float w = GL8_W[i] * h * ct;
        const float i0 = xh - xl, i1 = 0.5f * (xh * xh - xl * xl), i2 = (xh * xh * xh - xl * xl * xl) / 3.0f;
        m[0] += w * i0; m[1] += w * i1; m[2] += w * y * i0;
        m[3] += w * i2; m[4] += w * y * i1; m[5] += w * y * y * i0;
    }
}

/* The kernel of the unit disc less the half-planes x < -ex and y < -ey (ex, ey >= 0; a side
 * at 1 or beyond does not cut).  Local frame: both sides below/left of the centre. */
inline DiscKernel disc_kernel_local(float ex, float ey) {
    DiscKernel k;
    if (ex >= 1.0f && ey >= 1.0f) {
        k.a = 1.0f / PI_F; k.bx = 0.0f; k.by = 0.0f; k.m0 = PI_F;
        return k;
    }
    ex = fmin(ex, 1.0f);
    const float t0 = -asin(fmin(ey, 1.0f)), t1 = 0.5f * PI_F;
    const float tk = acos(ex);                  /* the x side meets the circle at theta = +-tk */
    float m[6] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    float lo = t0;
    if (-tk > lo) { disc_moments_seg(ex, lo, -tk, m); lo = -tk; }
    if (tk > lo) { disc_moments_seg(ex, lo, tk, m); lo = tk; }
    disc_moments_seg(ex, lo, t1, m);
    /* first column of the inverse of the symmetric moment matrix [[m0 m1 m2][m1 m3 m4][m2 m4 m5]] */
    const float c0 = m[3] * m[5] - m[4] * m[4];
    const float c1 = m[2] * m[4] - m[1] * m[5];
    const float c2 = m[1] * m[4] - m[3] * m[2];
    const float det = m[0] * c0 + m[1] * c1 + m[2] * c2;
    k.a = c0 / det; k.bx = c1 / det; k.by = c2 / det; k.m0 = m[0];
    return k;
}

/* Distance from c to the nearest side, or a large number without sides. */
inline float side_distance(__constant const Params* P, float2 c) {
    if (P->lateral == 0) return 3.0e38f;
    return fmin(fmin(c.x - P->x0, P->x0 + P->xw - c.x), fmin(c.y - P->y0, P->y0 + P->yw - c.y));
}

/* The disc's radius at c for a point whose radius is R (see above). */
inline float disc_radius(__constant const Params* P, float2 c, float R) {
    return clamp(DISC_KAPPA * side_distance(P, c), DISC_FLOOR * R, R);
}

/* The kernel of the disc (centre c, radius R) in the model's frame: k(u) = a + bx u.x + by u.y
 * for u = (photon - c) / R. */
inline DiscKernel disc_kernel(__constant const Params* P, float2 c, float R) {
    if (P->lateral == 0 || side_distance(P, c) >= R) return disc_kernel_local(1.0f, 1.0f);
    const float lx = c.x - P->x0, hx = P->x0 + P->xw - c.x;
    const float ly = c.y - P->y0, hy = P->y0 + P->yw - c.y;
    DiscKernel k = disc_kernel_local(fmax(fmin(lx, hx), 0.0f) / R, fmax(fmin(ly, hy), 0.0f) / R);
    if (hx < lx) k.bx = -k.bx;                  /* the near side is the high one: mirror */
    if (hy < ly) k.by = -k.by;
    return k;
}

#endif
