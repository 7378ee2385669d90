/* The walk on the smooth surfaces (SMOOTH_SURFACE builds: model.surface = "smooth"; included by
 * common.h).  Every pass meets interface k where the ray meets the height field z = h_k(x, y) of
 * surface.h itself, refracts there at its normal, and knows its layer from the smooth surfaces
 * alone: there is no staircase, so no lateral step changes a layer (docs/relief.md, section 1).
 *
 * `heights` holds the NVAR rows of samples (surface.h's `smooth`, the same buffer; interface k
 * is row IF_VAR(k) plus IF_Z(k)) followed by, per row and tile of SMOOTH_CELL x SMOOTH_CELL columns, (lowest, highest, K, G): bounds of
 * the Catmull-Rom patches over the tile from their Bernstein coefficients (the convex hull of
 * the Bezier net; clppm/scene/volume.py smooth_tile_bounds), K bounding max(|h_xx|, |h_yy|) +
 * |h_xy|, so that |d^2 h / ds^2| <= K |d_xy|^2 along any ray, and G bounding |grad h|: a ray
 * moving away from the surface more steeply than G never meets it.
 *
 * The walk's regions: the layer core (common.h next_boundary, unchanged), else one tile, left
 * through its walls (cross_cell), the domain's sides, or a crossing of the layer's top or bottom
 * found by smooth_march.  A tile whose bounds the ray's z range misses costs no evaluation. */
#ifndef CLPPM_SMOOTHWALK_H
#define CLPPM_SMOOTHWALK_H

#include "volume.h"
#include "surface.h"

#if !defined(NVAR) || !defined(SMOOTH_CELL)
#error "SMOOTH_SURFACE builds need NVAR (varying interfaces) and SMOOTH_CELL (columns a side of a cell)"
#endif

/* a march's steps before it hands back a safe point (EV_ZONE) and the walk calls again */
#define SMOOTH_STEPS 32
/* the crossing: within this height (um) of the surface and approaching it (float positions at
 * skin depths are good to about 2e-5 um) */
#define SMOOTH_TOL ((real)1e-5)

/* (lowest, highest, K, G) of varying interface k over tile (tx, ty): its row's bounds, shifted
 * by the interface's offset IF_Z(k) (rows are shared by interfaces a constant apart) */
HOT float4 smooth_tile(__constant const Params* P, __constant const float4* iface,
                       __global const float* heights, int k, int tx, int ty) {
    const int ntx = (P->nx + SMOOTH_CELL - 1) / SMOOTH_CELL, nty = (P->ny + SMOOTH_CELL - 1) / SMOOTH_CELL;
    const float4 b = ld4(heights + (size_t)NVAR * (size_t)P->nx * (size_t)P->ny
                         + 4 * (((size_t)IF_VAR(k) * (size_t)nty + (size_t)ty) * (size_t)ntx + (size_t)tx));
    return (float4)(b.x + IF_Z(k), b.y + IF_Z(k), b.z, b.w);
}

/* h, h_x, h_y of row v at grid coordinates (gx, gy) (x / dx - 1/2: surface.h's hf_eval_n, its
 * divisions done by the caller once per march): (h, g_x, g_y) in grid units, h without the
 * interface's offset */
HOT real4 hf_grid1(__constant const Params* P, __global const float* heights, int v, real gx, real gy) {
    const int ix = (int)gx - (gx < 0), iy = (int)gy - (gy < 0);      /* floor */
    const real fx = gx - (real)ix, fy = gy - (real)iy;
    const real fx2 = fx * fx, fx3 = fx2 * fx, fy2 = fy * fy, fy3 = fy2 * fy;
    real a0, a1, a2, a3, b0, b1, b2, b3;
    CR_W(fx, fx2, fx3, a0, a1, a2, a3)
    CR_D(fx, fx2, b0, b1, b2, b3)
    const int per = P->lateral == 2;
    const int i0 = hf_index(ix - 1, P->nx, per), i1 = hf_index(ix, P->nx, per);
    const int i2 = hf_index(ix + 1, P->nx, per), i3 = hf_index(ix + 2, P->nx, per);
    __global const float* base = heights + (size_t)v * (size_t)(P->nx * P->ny);
    real h0, h1, h2, h3, d0, d1, d2, d3;
#define CR_ROW1(j, h, d) { \
        __global const float* row = base + (size_t)hf_index(iy - 1 + (j), P->ny, per) * (size_t)P->nx; \
        const real s0 = row[i0], s1 = row[i1], s2 = row[i2], s3 = row[i3]; \
        h = a0 * s0 + a1 * s1 + a2 * s2 + a3 * s3; \
        d = b0 * s0 + b1 * s1 + b2 * s2 + b3 * s3; }
    CR_ROW1(0, h0, d0) CR_ROW1(1, h1, d1) CR_ROW1(2, h2, d2) CR_ROW1(3, h3, d3)
#undef CR_ROW1
    CR_W(fy, fy2, fy3, a0, a1, a2, a3)
    CR_D(fy, fy2, b0, b1, b2, b3)
    return (real4)(a0 * h0 + a1 * h1 + a2 * h2 + a3 * h3, a0 * d0 + a1 * d1 + a2 * d2 + a3 * d3,
                   b0 * h0 + b1 * h1 + b2 * h2 + b3 * h3, 0);
}

/* The first s in [s0, smax) (none before s0) where the ray p + s d leaves its side of the varying
 * interface with row v and offset c (sg = 1: the ray is below it, z < h; -1: above it).  g = sg (h - z) is the height inside;
 * along the ray g(s + t) >= g + g' t - Kd t^2 / 2 (Kd = K |d_xy|^2), so stepping to the first
 * zero of that bound never passes a root: from the left it is Newton's step made safe, and it
 * converges quadratically on a crossing.  A point on the surface (g ~ 0, just crossed or
 * reflected, moving inside: g' > 0) steps on to 2 g'/Kd.  Returns s with *hit = 1 at a crossing,
 * BIG when there is none before smax, or, out of steps (a grazing ray), the last safe s with
 * *hit = 0. */
HOT float smooth_march(__constant const Params* P, __global const float* heights, int v, real c, float3 p,
                       float3 d, float s0, float smax, float4 b, real sg, int* hit) {
    const real ddx = d.x, ddy = d.y, ddz = d.z, pz = (real)p.z - c;
    const real dxy2 = ddx * ddx + ddy * ddy;
    const real Kd = (real)b.z * dxy2;
    /* the steepest descent of g along the ray (G bounds |grad h|): g(s + t) >= g - gmax t too */
    const real gmax = (real)b.w * sqrt1(dxy2) + sg * ddz;
    /* the ray in grid coordinates, and the gradient's dot with d from grid units */
    const real idx = 1 / (real)P->dx, idy = 1 / (real)P->dy;
    const real gx0 = ((real)p.x - (real)P->x0) * idx - (real)0.5, gy0 = ((real)p.y - (real)P->y0) * idy - (real)0.5;
    const real ux = ddx * idx, uy = ddy * idy;
    real s = s0;
    *hit = 0;
    for (int i = 0; i < SMOOTH_STEPS; ++i) {
        const real4 f = hf_grid1(P, heights, v, gx0 + s * ux, gy0 + s * uy);
        const real g = sg * (f.x - (pz + s * ddz));
        const real gp = sg * (f.y * ux + f.z * uy - ddz);
        if (g <= SMOOTH_TOL && gp < 0) { *hit = 1; return (float)s; }
        const real gg = fmax1(g, (real)0);
        real t;
        if (gp < 0) t = 2 * gg / (sqrt1(gp * gp + 2 * Kd * gg) - gp);
        else t = Kd > 0 ? (gp + sqrt1(gp * gp + 2 * Kd * gg)) / Kd : (real)BIG;
        if (gmax > 0) t = fmax1(t, gg / gmax);
        s += fmax1(t, (real)1e-7);
        if (s >= (real)smax) return BIG;
    }
    return (float)s;
}

/* the current tile's inner walls ahead (at the domain's edge domain_sides decides) */
HOT void tile_walls(const Track* t, __constant const Params* P, float* best, int* e) {
    const int tx = t->ix / SMOOTH_CELL, ty = t->iy / SMOOTH_CELL;
    const int ntx = (P->nx + SMOOTH_CELL - 1) / SMOOTH_CELL, nty = (P->ny + SMOOTH_CELL - 1) / SMOOTH_CELL;
    const float3 d = t->dir;
    if (d.x > 0.0f ? tx + 1 < ntx : (d.x < 0.0f && tx > 0)) {
        const float s = (P->x0 + P->dx * (float)((tx + (d.x > 0.0f)) * SMOOTH_CELL) - t->pos.x) / d.x;
        if (s < *best) { *best = s; *e = EV_WALL_X; }
    }
    if (d.y > 0.0f ? ty + 1 < nty : (d.y < 0.0f && ty > 0)) {
        const float s = (P->y0 + P->dy * (float)((ty + (d.y > 0.0f)) * SMOOTH_CELL) - t->pos.y) / d.y;
        if (s < *best) { *best = s; *e = EV_WALL_Y; }
    }
}

/* Onto the next tile across its wall on axis (0: x, 1: y): the wall's coordinate exactly, and a
 * column of the tile beyond (the walk needs the tile, not the column). */
inline void cross_cell(Track* t, __constant const Params* P, int axis) {
    if (axis == 0) {
        const int tx = t->ix / SMOOTH_CELL, up = t->dir.x > 0.0f;
        t->pos.x = P->x0 + P->dx * (float)((tx + up) * SMOOTH_CELL);
        t->ix = up ? (tx + 1) * SMOOTH_CELL : tx * SMOOTH_CELL - 1;
    } else {
        const int ty = t->iy / SMOOTH_CELL, up = t->dir.y > 0.0f;
        t->pos.y = P->y0 + P->dy * (float)((ty + up) * SMOOTH_CELL);
        t->iy = up ? (ty + 1) * SMOOTH_CELL : ty * SMOOTH_CELL - 1;
    }
}

/* Interface k (j = 0: the top of the ray's layer, 1: its bottom) where the part s >= s_start of
 * the ray p + s d that lies in tile (tx, ty) crosses it within *best (a plane where k is flat):
 * *best and *e (EV_TOP, EV_BOTTOM; EV_ZONE for a march out of steps) updated.  The walk asks for
 * its own tile from s = 0 (smooth_boundary); the photon pass for the tiles a free flight crosses
 * (photon.cl). */
HOT void smooth_face(float3 p, float3 d, int k, int j, int tx, int ty, float s_start,
                     __constant const Params* P, __constant const float4* iface, __global const float* heights,
                     float smax, float* best, int* e) {
    const int v = IF_VAR(k);
    if (v < 0) {
        const float z = IF_Z(k);
        if (j == 0 ? d.z > 0.0f : (d.z < 0.0f && z > -BIG)) {
            const float s = (z - p.z) / d.z;
            if (s < *best) { *best = s; *e = j ? EV_BOTTOM : EV_TOP; }
        }
        return;
    }
    const float lim = fmin1(*best, smax);
    const float4 b = smooth_tile(P, iface, heights, k, tx, ty);
    const float zs = p.z + s_start * d.z, z1 = p.z + fmin1(lim, 1e6f) * d.z;
    if (j == 0 ? fmax1(zs, z1) < b.x : fmin1(zs, z1) > b.y) return;     /* clear of the tile's patches */
    if ((j == 0 ? d.z < 0.0f : d.z > 0.0f) && d.z * d.z * (1.0f + b.w * b.w) >= b.w * b.w)
        return;                                                       /* away, steeper than the surface */
    /* no crossing before the ray enters the tile's height range */
    const float s0 = j == 0 ? (zs < b.x ? (b.x - p.z) / d.z : s_start) : (zs > b.y ? (b.y - p.z) / d.z : s_start);
    int hit;
    const float s = smooth_march(P, heights, v, (real)IF_Z(k), p, d, s0, lim, b, j == 0 ? (real)1 : (real)-1, &hit);
    if (s < *best) { *best = s; *e = hit ? (j ? EV_BOTTOM : EV_TOP) : EV_ZONE; }
}

/* next_boundary outside the layer core: the tile's walls, the domain's sides, the layer's top
 * and bottom where the ray meets them before smax */
HOT float smooth_boundary(const Track* t, __constant const Params* P, __constant const float4* iface,
                             __global const float* heights, float smax, int* ev) {
    float best = BIG;
    int e = EV_NONE;
    tile_walls(t, P, &best, &e);
    domain_sides(t->pos, t->dir, P, &best, &e);
    /* the face the ray moves toward first: its crossing shortens the other's search */
    const int first = t->dir.z < 0.0f;
    const int tx = t->ix / SMOOTH_CELL, ty = t->iy / SMOOTH_CELL;
    smooth_face(t->pos, t->dir, t->L + first, first, tx, ty, 0.0f, P, iface, heights, smax, &best, &e);
    smooth_face(t->pos, t->dir, t->L + 1 - first, 1 - first, tx, ty, 0.0f, P, iface, heights, smax, &best, &e);
    *ev = e;
    return best > 0.0f ? best : 0.0f;
}

/* The height of interface k (varying or not) at (x, y) on its smooth surface: the layers' top
 * and bottom where the gather measures depth in a layer's own coordinates (layer_slab). */
HOT float smooth_z(__constant const Params* P, __constant const float4* iface,
                   __global const float* heights, int k, float x, float y) {
    const int v = IF_VAR(k);
    if (v < 0) return IF_Z(k);
    return (float)((real)IF_Z(k) + hf_grid1(P, heights, v, hf_gx(P, (real)x), hf_gy(P, (real)y)).x);
}

/* hit_surface's walk from the plane of the highest surface point down to the first hit of the
 * surface: tile by tile, interface 0 marched from above.  On a hit, *geo_n is the surface's
 * normal there (the face is the surface itself). */
inline int smooth_hit(Track* t, __constant const Params* P, __constant const float4* iface,
                      __global const float* heights, float3* geo_n) {
    const float3 d = t->dir;
    for (int guard = 0; guard < 4 * (P->nx + P->ny) + 64; ++guard) {
        if (d.z >= 0.0f && t->pos.z >= P->z_top) return 0;      /* above all relief, going up */
        float best = BIG;
        int e = EV_NONE;
        tile_walls(t, P, &best, &e);
        domain_sides(t->pos, d, P, &best, &e);
        const float lim = d.z > 0.0f ? fmin1(best, (P->z_top - t->pos.z) / d.z) : best;
        const float4 b = smooth_tile(P, iface, heights, 0, t->ix / SMOOTH_CELL, t->iy / SMOOTH_CELL);
        if (fmin1(t->pos.z, t->pos.z + fmin1(lim, 1e6f) * d.z) <= b.y) {
            int hit;
            const float s0 = t->pos.z > b.y ? (b.y - t->pos.z) / d.z : 0.0f;
            const float s = smooth_march(P, heights, IF_VAR(0), (real)IF_Z(0), t->pos, d, s0, lim, b, (real)-1, &hit);
            if (s < BIG) {
                t->pos += s * d;
                if (!hit) continue;
                *geo_n = smooth_normal(P, iface, heights, 0, t->pos.x, t->pos.y).xyz;
                t->L = 0;
                return 1;
            }
        }
        if (lim < best || e == EV_NONE) return 0;              /* above the relief, or off the grid */
        t->pos += best * d;
        if (e == EV_WALL_X || e == EV_WALL_Y) { cross_cell(t, P, e == EV_WALL_Y); continue; }
        if (cross_wall(t, P, e == EV_DOMAIN_Y, 1)) return 0;    /* out of an open side */
        locate_column(t, P);
    }
    return 0;
}

#endif
