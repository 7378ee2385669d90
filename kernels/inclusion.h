/* Inclusions: a few regions of their own material inside the layers (a vessel, an ellipsoid),
 * each the inside of a quadric, (p - c)^T Q (p - c) < 1 (clppm/scene/volume.py Inclusion): a
 * vessel of radius r along the unit axis a has Q = (I - a a^T) / r^2, an ellipsoid of semi-axes s
 * Q = diag(1 / s^2).  NINC of them, a compile-time count (volume.h; 0: this code compiled out, a
 * uniform scene runs the walk it always ran).
 *
 * Materials by index: layer L's optics are the rows optics[L*NB + b]; inclusion i's are the rows
 * of material NL + i, appended after the layers' (NMAT = NL + NINC), and after all NMAT*NB rows
 * come INC_ROWS float4 per inclusion: (centre, lowest z), (Q_xx, Q_yy, Q_zz, highest z),
 * (Q_xy, Q_xz, Q_yz, 0), (lowest x, highest x, lowest y, highest y): the bounding box, +-BIG
 * along an axis a vessel's axis follows.
 * Where inclusions overlap, the first one's material holds (the lowest bit of Track.inside).
 * An inclusion takes the index of the layer it is in: there is no Fresnel at its surface, only a
 * change of absorption, scattering and anisotropy.
 *
 * Traced exactly: the walk's next boundary is also the nearest crossing of an inclusion's surface
 * (a root of a quadratic along the ray), so a free flight spends its residual optical depth at each
 * region's own mu_t, as between layers: no majorant and no null collisions.  With a few smooth
 * surfaces that costs a handful of multiply-adds per step, and the hero-wavelength weights
 * (spectral.h) keep their per-segment form (length and collisions per material), where delta
 * tracking would add a null-collision factor per band at every tentative collision.
 *
 * Which root: a photon inside inclusion i leaves at the far root; outside, it enters at the near
 * root when that lies ahead, or within INC_EPS behind (a collision that rounding put a hair
 * outside the surface: it enters at once).  Just after leaving, the near root is the chord's
 * length behind, so a photon is never taken back in by its own crossing (chords under INC_EPS
 * excepted).  Where the position jumps (entering the skin, a periodic side) Track.inside is found
 * again from the point (inclusion_mask). */
#ifndef CLPPM_INCLUSION_H
#define CLPPM_INCLUSION_H

#include "volume.h"

#define INC_ROWS 4
/* um: float32 positions of a few mm carry ~5e-4 um of rounding */
#define INC_EPS 1e-2f

#if NINC > 0
/* (a, b, c) of q(s) = a s^2 + b s + c along p + s d, q < 0 inside inclusion i */
HOT float3 inclusion_poly(__global const float4* optics, int i, float3 p, float3 d) {
    __global const float4* r = optics + NMAT * NB + INC_ROWS * i;
    const float3 w = p - r[0].xyz;
    const float4 q = r[1], o = r[2];
    const float3 qd = (float3)(q.x * d.x + o.x * d.y + o.y * d.z, o.x * d.x + q.y * d.y + o.z * d.z,
                               o.y * d.x + o.z * d.y + q.z * d.z);
    const float3 qw = (float3)(q.x * w.x + o.x * w.y + o.y * w.z, o.x * w.x + q.y * w.y + o.z * w.z,
                               o.y * w.x + o.z * w.y + q.z * w.z);
    return (float3)(dot(d, qd), 2.0f * dot(w, qd), dot(w, qw) - 1.0f);
}

/* the inclusions containing p, one bit each */
HOT int inclusion_mask(__global const float4* optics, float3 p) {
    int m = 0;
    for (int i = 0; i < NINC; ++i)
        if (inclusion_poly(optics, i, p, (float3)(0.0f, 0.0f, 1.0f)).z < 0.0f) m |= 1 << i;
    return m;
}

/* The inclusions among bits `near` that contain p (the gathers: a stored photon's material,
 * testing only the inclusions whose box meets the query's) */
HOT int inclusion_mask_of(__global const float4* optics, float3 p, int near) {
    int m = 0;
    for (int i = 0; i < NINC; ++i)
        if (((near >> i) & 1) && inclusion_poly(optics, i, p, (float3)(0.0f, 0.0f, 1.0f)).z < 0.0f) m |= 1 << i;
    return m;
}

/* the material at a point of layer L with inclusion bits `inside` */
HOT int material_of(int L, int inside) {
    return inside ? NL + (31 - clz(inside & -inside)) : L;
}

/* The inclusions whose bounding box meets the box (xlo .. xhi, ylo .. yhi, zlo .. zhi), one bit
 * each: only they can be crossed by a path inside it.  A step ends at its layer's boundary at
 * the latest, so the walks test the depths of the layer over all columns (a level vessel in the
 * dermis costs the epidermis nothing); a light connection's leg tests its own box. */
HOT int inclusions_near(__global const float4* optics, float xlo, float xhi, float ylo, float yhi,
                        float zlo, float zhi) {
    int m = 0;
    for (int i = 0; i < NINC; ++i) {
        __global const float4* r = optics + NMAT * NB + INC_ROWS * i;
        const float4 bx = r[3];
        if (!(r[0].w > zhi || r[1].w < zlo || bx.x > xhi || bx.y < xlo || bx.z > yhi || bx.w < ylo))
            m |= 1 << i;
    }
    return m;
}

/* Distance along d from p to the next crossing of the surface of an inclusion of bits near or
 * inside (BIG if none), and which inclusion (*which). */
HOT float next_inclusion(__global const float4* optics, float3 p, float3 d, int inside, int near, int* which) {
    float best = BIG;
    for (int i = 0; i < NINC; ++i) {
        if (!(((inside | near) >> i) & 1)) continue;
        const float3 k = inclusion_poly(optics, i, p, d);
        if (!(k.x > 0.0f)) continue;                        /* along a vessel's axis: no crossing */
        const float disc = k.y * k.y - 4.0f * k.x * k.z;
        if (disc < 0.0f) continue;                          /* the line misses the surface */
        /* the two roots without cancellation (Numerical Recipes 5.6) */
        const float h = -0.5f * (k.y + copysign(sqrt(disc), k.y));
        float lo = h != 0.0f ? k.z / h : 0.0f, hi = h / k.x;
        if (lo > hi) { const float t = lo; lo = hi; hi = t; }
        const float s = (inside >> i) & 1 ? fmax(hi, 0.0f)
                        : (hi > 0.0f && lo > -INC_EPS ? fmax(lo, 0.0f) : BIG);
        if (s < best) { best = s; *which = i; }
    }
    return best;
}

/* The inclusions a step of layer L can cross (any column) */
#define INCLUSIONS_OF_LAYER(optics, L) inclusions_near(optics, -BIG, BIG, -BIG, BIG, IF_ZMIN((L) + 1), IF_ZMAX(L))

#define MATERIAL(t) material_of((t)->L, (t)->inside)
#else
#define MATERIAL(t) ((t)->L)
#endif

#endif
