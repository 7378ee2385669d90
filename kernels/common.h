/* The walk through the layers that every pass takes: a layer's slab at a point, the next
 * boundary of a constant region, crossing the surface.  On top of volume.h (parameters, random
 * numbers, optics, columns) and, for SMOOTH_SURFACE builds, smoothwalk.h (the walk on the smooth
 * surfaces).  See volume.h for the model and the compile-time switches. */
#ifndef CLPPM_COMMON_H
#define CLPPM_COMMON_H

#include "volume.h"

#if defined(SMOOTH_SURFACE) && !defined(FLAT)
#include "smoothwalk.h"
#endif

/* Top and bottom of layer L at position p (the bottom is -BIG when unbounded): on the smooth
 * surfaces at p itself when the walks cross them (a point lies between them exactly), else in
 * p's column (the staircase's slab, which holds every point of the layer there).  Always inlined:
 * Intel's CPU compiler miscompiles the float3 argument of a call it keeps (surface.h). */
HOT float2 layer_slab(__constant const Params* P, __constant const float4* iface,
                      __global const float* heights, float3 p, int L) {
#if defined(FLAT)
    return (float2)(IF_Z(L), IF_Z(L + 1));
#elif defined(SMOOTH_SURFACE)
    return (float2)(smooth_z(P, iface, heights, L, p.x, p.y), smooth_z(P, iface, heights, L + 1, p.x, p.y));
#else
    int ix = clamp1((int)floor1((p.x - P->x0) / P->dx), 0, P->nx - 1);
    int iy = clamp1((int)floor1((p.y - P->y0) / P->dy), 0, P->ny - 1);
    int col = col_index(P, ix, iy);
    return (float2)(iface_z(iface, heights, P, L, col), iface_z(iface, heights, P, L + 1, col));
#endif
}


/* Distance along t->dir to the next boundary of the constant region around t->pos and its kind.
 * smax: the caller's free path (a collision comes first beyond it); the smooth surfaces' walk
 * (smoothwalk.h) looks for crossings no further. */
inline float next_boundary(const Track* t, __constant const Params* P,
                           __constant const float4* iface, __global const float* heights,
                           float smax, int* ev) {
    float best = BIG;
    int e = EV_NONE;
    const float3 d = t->dir;
    const float z = t->pos.z;
    const int L = t->L;
#ifdef FLAT
    if (d.z > 0.0f) { best = (IF_Z(L) - z) / d.z; e = EV_TOP; }
    else if (d.z < 0.0f && L + 1 <= NL && IF_Z(L + 1) > -BIG) { best = (IF_Z(L + 1) - z) / d.z; e = EV_BOTTOM; }
    if (P->lateral != 0) domain_sides(t->pos, d, P, &best, &e);
#else
    const float ztop_core = IF_ZMIN(L);           /* lowest point of the interface above */
    const float zbot_core = IF_ZMAX(L + 1);       /* highest point of the interface below */
    /* in the core unless on a core plane and moving out through it (then: column mode) */
    const int in_core = (d.z > 0.0f ? z < ztop_core : z <= ztop_core) &&
                        (d.z < 0.0f ? z > zbot_core : z >= zbot_core);
    if (in_core) {
        /* core mode: only two planes and the domain sides */
        if (d.z > 0.0f) {
            best = (ztop_core - z) / d.z;
            e = (IF_VAR(L) < 0) ? EV_TOP : EV_ZONE;
        } else if (d.z < 0.0f && zbot_core > -BIG) {
            best = (zbot_core - z) / d.z;
            e = (IF_VAR(L + 1) < 0) ? EV_BOTTOM : EV_ZONE;
        }
        domain_sides(t->pos, d, P, &best, &e);
    } else {
#ifdef SMOOTH_SURFACE
        return smooth_boundary(t, P, iface, heights, smax, ev);
#endif
        /* column mode: this column's two interfaces and its four walls */
        const int col = col_index(P, t->ix, t->iy);
        if (d.z > 0.0f) {
            best = (iface_z(iface, heights, P, L, col) - z) / d.z; e = EV_TOP;
        } else if (d.z < 0.0f) {
            float zb = iface_z(iface, heights, P, L + 1, col);
            if (zb > -BIG) { best = (zb - z) / d.z; e = EV_BOTTOM; }
        }
        if (d.x != 0.0f) {
            float w = P->x0 + P->dx * (float)(t->ix + (d.x > 0.0f ? 1 : 0));
            float s = (w - t->pos.x) / d.x;
            if (s < best) { best = s; e = EV_WALL_X; }
        }
        if (d.y != 0.0f) {
            float w = P->y0 + P->dy * (float)(t->iy + (d.y > 0.0f ? 1 : 0));
            float s = (w - t->pos.y) / d.y;
            if (s < best) { best = s; e = EV_WALL_Y; }
        }
    }
#endif
    *ev = e;
    return best > 0.0f ? best : 0.0f;
}

/* First hit of a ray coming from above with the skin surface (the top of layer 0).
 * On a hit, t->pos is the hit point, t->ix/iy its column, *geo_n the geometric face normal
 * (z for a column top, x or y for a column side).  Returns 0 on a miss. */
inline int hit_surface(Track* t, __constant const Params* P, __constant const float4* iface,
                       __global const float* heights, float3* geo_n) {
    float3 d = t->dir;
    if (d.z >= 0.0f && t->pos.z >= P->z_top) return 0;
    /* advance to the plane of the highest surface point */
    if (t->pos.z > P->z_top) {
        float s = (P->z_top - t->pos.z) / d.z;
        t->pos += s * d;
        t->pos.z = P->z_top;
    }
    *geo_n = (float3)(0.0f, 0.0f, 1.0f);
    if (P->lateral != 0) {
        if (t->pos.x < P->x0 || t->pos.x > P->x0 + P->xw || t->pos.y < P->y0 || t->pos.y > P->y0 + P->yw) {
            /* outside the model's footprint on that plane: march to the footprint if heading to it */
            float tmin = 0.0f, tmax = BIG;
            float lo[2] = {P->x0, P->y0}, hi[2] = {P->x0 + P->xw, P->y0 + P->yw};
            float o[2] = {t->pos.x, t->pos.y}, dd[2] = {d.x, d.y};
            for (int a = 0; a < 2; ++a) {
                if (dd[a] == 0.0f) { if (o[a] < lo[a] || o[a] > hi[a]) return 0; continue; }
                float t1 = (lo[a] - o[a]) / dd[a], t2 = (hi[a] - o[a]) / dd[a];
                tmin = fmax1(tmin, fmin1(t1, t2)); tmax = fmin1(tmax, fmax1(t1, t2));
            }
            if (tmin > tmax || d.z >= 0.0f) return 0;
#ifdef FLAT
            return 0;   /* flat surface: the footprint plane is the surface; missed it */
#else
            /* entering through the side of the model below z_top */
            t->pos += tmin * d;
            locate_column(t, P);
            int col = col_index(P, t->ix, t->iy);
            if (t->pos.z <= iface_z(iface, heights, P, 0, col)) {
                /* side hit: treated as leaving nothing; outside light entering the side is ignored */
                return 0;
            }
#endif
        }
    }
    locate_column(t, P);
#ifdef FLAT
    t->L = 0;
    return 1;
#else
    if (IF_VAR(0) < 0) { t->L = 0; return 1; }
#ifdef SMOOTH_SURFACE
    return smooth_hit(t, P, iface, heights, geo_n);
#endif
    /* 2-D walk over columns until the ray is below the column top */
    for (int guard = 0; guard < 4 * (P->nx + P->ny) + 8; ++guard) {
        if (d.z >= 0.0f && t->pos.z > P->z_top) return 0;     /* above all relief, going up */
        int col = col_index(P, t->ix, t->iy);
        float zs = iface_z(iface, heights, P, 0, col);
        if (t->pos.z <= zs) { t->L = 0; return 1; }         /* came in through a side wall */
        float sx = BIG, sy = BIG;
        if (d.x != 0.0f) sx = (P->x0 + P->dx * (float)(t->ix + (d.x > 0.0f)) - t->pos.x) / d.x;
        if (d.y != 0.0f) sy = (P->y0 + P->dy * (float)(t->iy + (d.y > 0.0f)) - t->pos.y) / d.y;
        float sw = fmin1(sx, sy);
        float sz = (d.z < 0.0f) ? (zs - t->pos.z) / d.z : BIG;
        if (sz <= sw) {
            t->pos += sz * d; t->pos.z = zs;
            *geo_n = (float3)(0.0f, 0.0f, 1.0f);
            t->L = 0;
            return 1;
        }
        t->pos += sw * d;
        int axis = (sx <= sy) ? 0 : 1;
        if (cross_wall(t, P, axis, 0)) return 0;
        *geo_n = axis == 0 ? (float3)(d.x > 0.0f ? -1.0f : 1.0f, 0.0f, 0.0f)
                           : (float3)(0.0f, d.y > 0.0f ? -1.0f : 1.0f, 0.0f);
    }
    return 0;
#endif
}

#endif
