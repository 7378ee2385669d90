/* Eye-ray pass: one work item per eye ray.  Run twice with the same random numbers: WRITE = 0
 * counts sample points and path pieces per ray (the host scans the counts), WRITE = 1 writes them
 * and WRITE = 2 also each piece's geometry (start, direction: the beam estimator's input).
 *
 * Sample points (paper section 5).  The refracted ray is walked through the constant regions
 * of the volume; candidates are placed
 *   scheme 0 (a-c, any spacing s): at path length k*s from the entry point, k = 1, 2, ...
 *   scheme 1 (d-f): as a Poisson process whose rate is the current layer's extinction
 *                   statistic (max / mean / min over bands), restarted at every region
 *                   boundary (memoryless, so this is one Poisson process of piecewise rate);
 *                   a layer visit that gets no point gets a point at its exit.
 * A candidate is kept only while the transmittance from the entry point, in the most
 * transparent band, is above the threshold (max_b T_b >= threshold, i.e. the cut is where the
 * last band falls below it).  With merge on, a candidate in the voxel of the previous point is
 * merged into it (one sample point per voxel, as the paper's 4 um spacing implies).
 *
 * Radiance weights.  The sampled path (entry to cut or exit) is split among the points by a
 * Voronoi partition along the ray, within each layer visit: point i owns the path from the
 * midpoint with its predecessor to the midpoint with its successor, and a cell ends at a layer
 * boundary (S jumps there with mu_s: a cell that crossed it would credit one layer with the
 * other's in-scattered radiance).  Only a visit with no point (equal spacing wider than the
 * layer) leaves its path to its neighbours' cells.  The pixel
 * radiance is  sum_i S(x_i) tw_i * integral over cell_i of T(l, lambda) dl,  S the in-scattered
 * radiance density, T the per-band transmittance from the entry (integrated exactly: the layer
 * extinction is piecewise constant).  Derivation: the path integral int T(l) S(l) dl is split
 * over the cells and S is frozen at the cell's point.  For equal spacing the cells are centred
 * on the points (the midpoint rule: the error is second order in the spacing; the paper's
 * rho and dx with S at the cell's end is first order).  For Poisson points of rate r the two
 * half-gaps of a cell are independent Exp(2r) lengths, so the cell is symmetric about its point
 * in distribution and E|cell| = 1/r: the estimate is unbiased to first order in S' too (the
 * estimator sum_i T S / r of Campbell's theorem is unbiased but far noisier, and gives the exit
 * fallback point no weight).  The cell is stored as pieces (length, material) so the gather kernel
 * evaluates the integral per band exactly (no 81 floats per point).
 *
 * Inclusions (inclusion.h, NINC > 0; flat layers and the relief): a region also ends at an
 * inclusion's surface, so a piece lies in one material, the layer's or the inclusion's it is in,
 * and records that material (its extinction: the transmittance, the cut, scheme 1's rate); a
 * sample point records its layer (the layer estimator's photons and volume).  On the relief a
 * piece's record is material + 256 layer (geo; pieces keep the material): the beam gather
 * measures its depth in its layer's own coordinates, which an inclusion's index would misread.
 *
 * Chromophore maps (maps.h, MAPS; flat layers and the relief): in a layer whose map changes its mu_a a region
 * also ends at the walls between the maps' columns, so a piece lies in one column too (maps.h
 * says why crossings and not tracking); the transmittance and the cut run at mu_t = the layer's +
 * delta of the column, the gathers find a piece's column at its midpoint (the beam's geometry).
 * A wall is no region boundary for the points (mu_s and so S do not jump there): the cells cross
 * it, an empty visit gets no point at it, and scheme 1 keeps the layer's own rate (the rate only
 * places the points; their cells' pieces are integrated exactly at the column's extinction).
 */
#include "common.h"
#include "camera.h"
#include "inclusion.h"
#ifndef FLAT
#include "surface.h"
#endif
#ifdef MAPS
#include "maps.h"
#endif

typedef struct {
    Camera cam;
    int spp;
    int scheme;                 /* 0 equal spacing, 1 extinction-based */
    float spacing;
    float od_cut;               /* -ln(threshold) */
    int merge;
    float vox_dx, vox_dz;
    int max_points;
    float max_len;
    int light_kind;             /* SRC_PENCIL, SRC_WIDE, SRC_POINT (constants.h) */
    float lx, ly, lz;           /* point: position; collimated: unit vector toward the light */
    float alpha;                /* GGX roughness */
    uint seed_lo, seed_hi;
    int jitter;
    float bx0, by0, bx1, by1;   /* wide beam footprint on z = 0 (specular only inside it) */
} EyeParams;

#ifdef MAPS
/* pieces also end at the maps' column walls (a few per cell: the rays run near the normal); past
 * MAXPEND pending pieces the rest joins the last one */
#define MAXPEND (2 * NL + 4 + 16)
#else
#define MAXPEND (2 * NL + 4)
#endif

typedef struct {
    float pend_total;           /* path length since the last point */
    uint npts, npcs;            /* counts so far */
    uint pt_base, pc_base;      /* output offsets (WRITE) */
    int npend;
    float pend_len[MAXPEND];
    int pend_layer[MAXPEND];
    float3 pend_start[MAXPEND]; /* where each pending piece starts, and its direction: the */
    float3 pend_dir[MAXPEND];   /* beam estimator integrates along the pieces themselves */
    int4 last_vox;
    int have_point;
    int split_ok;               /* the last point is in the current layer visit */
#ifdef MAPS
    int col;                    /* the maps' column of the path now added (-1: none) */
    int pend_col[MAXPEND];      /* each pending piece's: pieces of two columns do not join */
#endif
} Emit;

/* A piece of path of length len in layer L, from start along dir.  It joins the last pending
 * piece when that one is in the same layer and goes the same way (one straight piece). */
inline void pend_add(Emit* e, int L, float len, float3 start, float3 dir) {
    if (len <= 0.0f) return;
    e->pend_total += len;
    const int k = e->npend - 1;
#ifdef MAPS
    if (k >= 0 && e->pend_layer[k] == L && e->pend_col[k] == e->col && all(e->pend_dir[k] == dir)) {
        e->pend_len[k] += len;
        return;
    }
#else
    if (k >= 0 && e->pend_layer[k] == L && all(e->pend_dir[k] == dir)) { e->pend_len[k] += len; return; }
#endif
    if (e->npend == MAXPEND) { e->pend_len[MAXPEND - 1] += len; return; }
#ifdef MAPS
    e->pend_col[e->npend] = e->col;
#endif
    e->pend_len[e->npend] = len; e->pend_layer[e->npend] = L;
    e->pend_start[e->npend] = start; e->pend_dir[e->npend] = dir;
    e->npend++;
}

/* Piece j of the output: (length, layer) and, for the beam estimator, (start, length) and
 * (direction, layer). */
inline void write_piece(uint j, float len, int L, float3 start, float3 dir, __global float2* pieces,
                        __global float4* geo, int write) {
    if (!write) return;
#if NINC > 0 && !defined(FLAT)
    /* inclusions on the relief: L is material + 256 layer (sample_points); pieces keep the
     * material (the sphere gathers' extinction), geo both (beam.h beam_piece_at) */
    pieces[j] = (float2)(len, (float)(L & 255));
#else
    pieces[j] = (float2)(len, (float)L);
#endif
    if (write == EYE_STORE_GEOMETRY) {
        geo[2 * j] = (float4)(start, len);
        geo[2 * j + 1] = (float4)(dir, (float)L);
    }
}

inline int4 voxel_of(float3 p, __constant const EyeParams* E) {
    return (int4)((int)floor(p.x / E->vox_dx), (int)floor(p.y / E->vox_dx), (int)floor(p.z / E->vox_dz), 0);
}

inline void flush_pieces(Emit* e, __global float2* pieces, __global float4* geo, int write) {
    if (write)
        for (int k = 0; k < e->npend; ++k)
            write_piece(e->pc_base + e->npcs + k, e->pend_len[k], e->pend_layer[k], e->pend_start[k],
                        e->pend_dir[k], pieces, geo, write);
    e->npcs += e->npend;
    e->npend = 0;
    e->pend_total = 0.0f;
}

/* Write the first D of the pending path (it belongs to the previous point) and keep the rest. */
inline void flush_first(Emit* e, float D, __global float2* pieces, __global float4* geo, int write) {
    int k = 0;
    float acc = 0.0f;
    while (k < e->npend && acc + e->pend_len[k] <= D) {
        write_piece(e->pc_base + e->npcs, e->pend_len[k], e->pend_layer[k], e->pend_start[k],
                    e->pend_dir[k], pieces, geo, write);
        e->npcs++; acc += e->pend_len[k]; k++;
    }
    if (k < e->npend && D - acc > 0.0f) {
        const float d = D - acc;
        write_piece(e->pc_base + e->npcs, d, e->pend_layer[k], e->pend_start[k], e->pend_dir[k],
                    pieces, geo, write);
        e->npcs++;
        e->pend_len[k] -= d;
        e->pend_start[k] += d * e->pend_dir[k];
    }
    int m = 0;
    for (int j = k; j < e->npend; ++j, ++m) {
        e->pend_len[m] = e->pend_len[j]; e->pend_layer[m] = e->pend_layer[j];
        e->pend_start[m] = e->pend_start[j]; e->pend_dir[m] = e->pend_dir[j];
#ifdef MAPS
        e->pend_col[m] = e->pend_col[j];
#endif
    }
    e->npend = m;
    e->pend_total -= D;
}

/* place a candidate at p (layer L); returns 1 if a new point was made */
inline int place(Emit* e, float3 p, float3 to_eye, int L, float tw, __constant const EyeParams* E,
                 __global float4* pt_pos, __global float4* pt_dir, __global uint* pt_piece,
                 __global float2* pieces, __global float4* geo, __global float2* pt_slab, float2 slab,
                 int write) {
    int4 v = voxel_of(p, E);
    if (E->merge && e->have_point && all(v.xyz == e->last_vox.xyz)) return 0;
    if (e->npts >= (uint)E->max_points) return 0;
    /* Voronoi partition of the path: the previous point owns up to the midpoint */
    if (e->have_point && e->split_ok) flush_first(e, 0.5f * e->pend_total, pieces, geo, write);
    if (write) {
        uint i = e->pt_base + e->npts;
        pt_pos[i] = (float4)(p, tw);
        pt_dir[i] = (float4)(to_eye, (float)L);
        pt_piece[i] = e->pc_base + e->npcs;
        pt_slab[i] = slab;
    }
    flush_pieces(e, pieces, geo, write);
    e->npts++;
    e->last_vox = v;
    e->have_point = 1;
    e->split_ok = 1;
    return 1;
}

/* The skin surface's normal where an eye ray meets it (upward; w = 0): the smooth surface's */
inline float4 entry_normal(__constant const Params* P, __constant const float4* iface,
                           __global const float* smooth, float x, float y) {
#ifdef FLAT
    return (float4)(0.0f, 0.0f, 1.0f, 0.0f);
#else
    return smooth_normal(P, iface, smooth, 0, x, y);
#endif
}

/* A sample point's layer at its column (top, bottom; the layer estimator's volume), written
 * only by the passes that store */
HOT float2 point_slab(__constant const Params* P, __constant const float4* iface,
                      __global const float* heights, float3 p, int L, int write) {
    return write ? layer_slab(P, iface, heights, p, L) : (float2)(0.0f);
}

/* Eye ray r: its pixel (spp rays each), jittered within the pixel when asked, from the camera. */
HOT void eye_ray(Track* t, Rng* rng, __constant const EyeParams* E, uint r) {
    const uint pix = r / (uint)E->spp;
    const int px = (int)(pix % (uint)E->cam.width), py = (int)(pix / (uint)E->cam.width);
    rng_init(rng, r, 0u, 1u, E->seed_lo, E->seed_hi);
    float jx = 0.5f, jy = 0.5f;
    if (E->jitter) { jx = rng_u01(rng); jy = rng_u01(rng); }
    t->pos = camera_pos(&E->cam).xyz;
    t->dir = camera_dir(&E->cam, (float)px + jx, (float)py + jy).xyz;
    t->L = -1; t->ix = 0; t->iy = 0;
#if NINC > 0
    t->inside = 0;
#endif
}

HOT void emit_init(Emit* e, uint pt_base, uint pc_base) {
    e->npts = 0; e->npcs = 0; e->npend = 0; e->have_point = 0; e->split_ok = 0; e->last_vox = (int4)(0); e->pend_total = 0.0f;
    e->pt_base = pt_base;
    e->pc_base = pc_base;
#ifdef MAPS
    e->col = -1;
#endif
}

/* The specular highlight of the surface point the eye ray hit (t->pos, geometric normal gn, sn
 * the normal shaded with): GGX toward the light, by the inverse square of a point light's
 * distance; a wide beam lights only the points whose line to the light crosses its footprint,
 * a pencil beam's highlight has no area. */
HOT float surface_specular(const Track* t, float3 sn, __constant const EyeParams* E,
                           __constant const Params* P, __constant const float* layer_n) {
    float3 v = -t->dir;
    float3 l;
    float inv_d2 = 1.0f;
    if (E->light_kind == SRC_POINT) {
        float3 lp = (float3)(E->lx, E->ly, E->lz) - t->pos;
        float d2 = dot(lp, lp);
        l = lp * rsqrt(d2);
        inv_d2 = 1.0f / d2;
    } else {
        l = (float3)(E->lx, E->ly, E->lz);
    }
    float spec = specular_geo(sn, v, l, E->alpha, P->n_above, layer_n[0]) * inv_d2;
    if (E->light_kind == SRC_WIDE) {
        /* where this surface point's line to the light crosses z = 0 */
        float s0 = -t->pos.z / l.z;
        float fx = t->pos.x + s0 * l.x, fy = t->pos.y + s0 * l.y;
        if (fx < E->bx0 || fx > E->bx1 || fy < E->by0 || fy > E->by1) spec = 0.0f;
    } else if (E->light_kind == SRC_PENCIL) {
        spec = 0.0f;                /* a pencil beam's highlight has no area */
    }
    return spec;
}

/* Interface crossing into the skin where the eye ray hit it (geometric normal gn): refraction
 * at the smooth surface's normal (the face's where the ray does not cross the smooth one) into
 * layer 0.  Returns the Fresnel transmittance; *spec takes the specular term. */
HOT float enter_skin(Track* t, float3 gn, float* spec, __constant const EyeParams* E,
                     __constant const Params* P, __constant const float4* iface,
                     __constant const float* layer_n, __global const float* smooth) {
    float3 sn = entry_normal(P, iface, smooth, t->pos.x, t->pos.y).xyz;
    float ci = -dot(t->dir, sn);
    if (ci <= 1e-6f) { sn = gn; ci = -dot(t->dir, gn); }
    *spec = surface_specular(t, sn, E, P, layer_n);
    float ct;
    float R = fresnel_R(P->n_above, layer_n[0], ci, &ct);
    float3 d = refract3(t->dir, sn, P->n_above / layer_n[0], ci, ct);
    if (dot(d, gn) >= 0.0f) d = reflect3(d, gn);
    t->dir = normalize(d);
    return 1.0f - R;
}

/* The path length into layer L's region at which the most transparent band's optical depth
 * from the entry (od) reaches the threshold's (od_cut); BIG where some band never does. */
HOT float threshold_cut(const float* od, int L, __constant const EyeParams* E, __global const float4* optics) {
    float smax = 0.0f;
    int never = 0;
    for (int b = 0; b < NB; ++b) {
        float m = optics[L * NB + b].w;
        float rem = E->od_cut - od[b];
        if (m <= 0.0f) { if (rem > 0.0f) never = 1; continue; }
        smax = fmax(smax, rem / m);
    }
    return never ? BIG : smax;
}

#ifdef MAPS
/* threshold_cut in material m at the maps' column (ix, iy) (first: map_split_first's) */
HOT float threshold_cut_map(const float* od, int m, int first, int ix, int iy, __constant const EyeParams* E,
                            __global const float4* optics) {
    float smax = 0.0f;
    int never = 0;
    for (int b = 0; b < NB; ++b) {
        float mt = map_mut(optics, m, b, first, ix, iy);
        float rem = E->od_cut - od[b];
        if (mt <= 0.0f) { if (rem > 0.0f) never = 1; continue; }
        smax = fmax(smax, rem / mt);
    }
    return never ? BIG : smax;
}
#endif

/* Sample points along the eye ray's path seg through a region of layer L and material m (L
 * itself, or the inclusion the ray is in: inclusion.h), from t->pos at path length ell from the
 * entry: at the equal spacing's lengths (scheme 0, *next_eq the next one) or as a Poisson
 * process of the material's rate (scheme 1); the path between them pending as pieces of
 * material m (the gathers read their extinction by it).  twp: the points' radiance weight.
 * Returns the points made. */
HOT int sample_points(Emit* e, const Track* t, int L, int m, float seg, float ell, float twp, float* next_eq,
                      Rng* rng, __constant const EyeParams* E, __constant const float* rate,
                      __constant const Params* P, __constant const float4* iface,
                      __global const float* heights, __global float4* pt_pos, __global float4* pt_dir,
                      __global uint* pt_piece, __global float2* pieces, __global float4* geo,
                      __global float2* pt_slab, int write) {
    const float3 to_eye = -t->dir;
#if NINC > 0 && !defined(FLAT)
    /* the pieces' record on the relief: material + 256 layer (the beam gather's layer-conforming
     * depth reads the layer, its extinction and mu_s ratio the material: beam.h beam_piece_at) */
    const int pm = m | (L << 8);
#else
#define pm m
#endif
    int n = 0;
    float x = 0.0f;                 /* position of the last placement in this region */
    if (E->scheme == 0) {
        while (*next_eq <= ell + seg) {
            float xc = *next_eq - ell;
            pend_add(e, pm, xc - x, t->pos + x * t->dir, t->dir); x = xc;
            n += place(e, t->pos + xc * t->dir, to_eye, L, twp, E, pt_pos, pt_dir, pt_piece, pieces, geo, pt_slab,
                       point_slab(P, iface, heights, t->pos + xc * t->dir, L, write), write);
            *next_eq += E->spacing;
        }
    } else {
        float rt = rate[m];
        if (rt > 0.0f) {
            float xc = x;
            while (1) {
                xc += neg_log_u01(rng_u01(rng)) / rt;
                if (xc > seg) break;
                pend_add(e, pm, xc - x, t->pos + x * t->dir, t->dir); x = xc;
                n += place(e, t->pos + xc * t->dir, to_eye, L, twp, E, pt_pos, pt_dir, pt_piece, pieces, geo, pt_slab,
                           point_slab(P, iface, heights, t->pos + xc * t->dir, L, write), write);
            }
        }
    }
    pend_add(e, pm, seg - x, t->pos + x * t->dir, t->dir);
    return n;
}
#undef pm

/* The layer on the other side of a boundary event ev of layer L (L itself for a zone change, a
 * column wall within the layer, or after a wall left the domain: then *out).  Moves t onto the
 * interface or across the wall. */
HOT int layer_beyond(Track* t, int ev, int L, int* out, __constant const Params* P,
                     __constant const float4* iface, __global const float* heights) {
    int L2 = L;
    if (ev == EV_TOP || ev == EV_BOTTOM) {
        L2 = ev == EV_TOP ? L - 1 : L + 1;
#ifndef SMOOTH_SURFACE
        t->pos.z = iface_z(iface, heights, P, ev == EV_TOP ? L : L + 1, col_index(P, t->ix, t->iy));
#endif
    } else if (ev == EV_ZONE) {
        locate_column(t, P);
    } else {
        int axis = (ev == EV_WALL_X || ev == EV_DOMAIN_X) ? 0 : 1;
        int donly = (ev == EV_DOMAIN_X || ev == EV_DOMAIN_Y);
#ifdef SMOOTH_SURFACE
        /* a tile's wall or a side: the layers do not change across it */
        if (!donly) { cross_cell(t, P, axis); return L; }
        if (cross_wall(t, P, axis, 1)) { *out = 1; return L; }
        locate_column(t, P);
        return L;
#endif
        if (cross_wall(t, P, axis, donly)) { *out = 1; return L; }
#ifndef FLAT
        if (donly) locate_column(t, P);
        L2 = layer_at(iface, heights, P, col_index(P, t->ix, t->iy), t->pos.z, L);
#endif
    }
    return L2;
}

/* A face between layers L and L2 where the eye ray crosses it: the face's own normal gn
 * (pointing from L into L2), the normal refracted at (sn), the indices, the cosines and the
 * Fresnel reflectance. */
typedef struct {
    float3 gn, sn;
    float n1, n2, ci, ct, R;
} Face;

/* the normal refracted at: the smooth surface's where interface k varies and the indices differ
 * (as the photon pass and the path tracer), else the face's own; the face's where the ray does
 * not cross the smooth one (fresnel_cross, common.h) */
HOT void eye_face(Face* out, const Track* t, int ev, int L, int L2, __constant const Params* P,
                  __constant const float4* iface, __constant const float* layer_n,
                  __global const float* smooth) {
    Face fc;
    fc.gn = (ev == EV_TOP) ? (float3)(0.0f, 0.0f, 1.0f) : (ev == EV_BOTTOM) ? (float3)(0.0f, 0.0f, -1.0f)
          : ((ev == EV_WALL_X || ev == EV_DOMAIN_X) ? (float3)(t->dir.x > 0.0f ? 1.0f : -1.0f, 0.0f, 0.0f)
                                                    : (float3)(0.0f, t->dir.y > 0.0f ? 1.0f : -1.0f, 0.0f));
    fc.n1 = layer_n[L];
    fc.n2 = L2 < 0 ? P->n_above : (L2 >= NL ? P->n_below : layer_n[L2]);
#ifdef SMOOTH_SURFACE
    /* the crossing is on the smooth surface itself: its normal is the face's */
    fc.gn = face_normal(P, iface, smooth, L2 < L ? L : L + 1, L, L2, t->pos.x, t->pos.y, (float4)(fc.gn, 0.0f)).xyz;
#endif
    float3 sn = fc.gn;
#if !defined(FLAT) && !defined(SMOOTH_SURFACE)
    if (fc.n1 != fc.n2)
        sn = face_normal(P, iface, smooth, L2 < L ? L : L + 1, L, L2, t->pos.x, t->pos.y, (float4)(fc.gn, 0.0f)).xyz;
#endif
    float ci = dot(t->dir, sn);
    if (ci <= 1e-6f) { sn = fc.gn; ci = dot(t->dir, fc.gn); }
    fc.sn = sn;
    fc.ci = ci;
    fc.R = fresnel_R(fc.n1, fc.n2, ci, &fc.ct);
    *out = fc;      /* written out, not returned: oclgrind cannot run a struct return's inlined form */
}

/* Out through the relief (a furrow wall): leave with Fresnel, cross the air gap and enter again
 * where the ray meets the skin.  *tw takes both transmittances, *nfac layer 0's n^2 law.
 * Returns 0 when the ray does not meet the skin again. */
HOT int cross_furrow(Track* t, const Face* fc, float* tw, float* nfac, __constant const Params* P,
                     __constant const float4* iface, __constant const float* layer_n,
                     __global const float* heights, __global const float* smooth) {
    float ct = fc->ct;
    *tw *= 1.0f - fc->R;
    t->dir = refract3(t->dir, -fc->sn, fc->n1 / fc->n2, fc->ci, ct);
    if (dot(t->dir, fc->gn) <= 0.0f) t->dir = reflect3(t->dir, fc->gn);
    t->pos += 1e-3f * t->dir;
    float3 gn2;
    if (!hit_surface(t, P, iface, heights, &gn2)) return 0;
    float3 sn2 = entry_normal(P, iface, smooth, t->pos.x, t->pos.y).xyz;
    float ci2 = -dot(t->dir, sn2);
    if (ci2 <= 1e-6f) { sn2 = gn2; ci2 = -dot(t->dir, gn2); }
    float R2 = fresnel_R(P->n_above, layer_n[0], ci2, &ct);
    *tw *= 1.0f - R2;
    float3 d2 = refract3(t->dir, sn2, P->n_above / layer_n[0], ci2, ct);
    if (dot(d2, gn2) >= 0.0f) d2 = reflect3(d2, gn2);
    t->dir = normalize(d2);
    *nfac = P->n_above / layer_n[0];
    *nfac *= *nfac;
    t->L = 0;
    return 1;
}

/* Interface crossing into L2 with its Fresnel transmittance (a transmission crosses the face),
 * refracted where the indices differ; *nfac takes L2's n^2 law. */
HOT void refract_into(Track* t, const Face* fc, int L2, float* tw, float* nfac, __constant const Params* P) {
    if (fc->n1 != fc->n2) {
        *tw *= 1.0f - fc->R;
        t->dir = refract3(t->dir, -fc->sn, fc->n1 / fc->n2, fc->ci, fc->ct);
        if (dot(t->dir, fc->gn) <= 0.0f) t->dir = reflect3(t->dir, fc->gn);
        *nfac = P->n_above / fc->n2;
        *nfac *= *nfac;
    }
    t->L = L2;
}

__kernel void eye_pass(VOLUME_ARGS,
                       __constant const EyeParams* E,
                       __constant const float* rate,            /* per material, um^-1 */
                       int write,                               /* EYE_COUNT, EYE_STORE, EYE_STORE_GEOMETRY */
                       __global uint* n_points, __global uint* n_pieces,
                       __global const uint* pt_start, __global const uint* pc_start,
                       __global float4* pt_pos, __global float4* pt_dir, __global uint* pt_piece,
                       __global float2* pieces, __global float* ray_spec, __global float* ray_hit,
                       __global float2* pt_slab, __global float4* geo,
                       __global const float* smooth)            /* Volume.smooth (relief builds) */
{
    const uint r = (uint)get_global_id(0);
    const uint npix = (uint)(E->cam.width * E->cam.height);
    if (r >= npix * (uint)E->spp) return;
    Rng rng;
    Track t;
    eye_ray(&t, &rng, E, r);
    Emit e;
    emit_init(&e, write ? pt_start[r] : 0u, write ? pc_start[r] : 0u);

    float3 gn;
    float spec = 0.0f;
    if (!hit_surface(&t, P, iface, heights, &gn)) {
        if (write) { ray_spec[r] = 0.0f; ray_hit[r] = 0.0f; }
        else { n_points[r] = 0u; n_pieces[r] = 0u; }
        return;
    }
    /* ---- surface: specular term and refraction, weighted by the Fresnel transmittance */
    float tw = enter_skin(&t, gn, &spec, E, P, iface, layer_n, smooth);
#if NINC > 0
    t.inside = inclusion_mask(optics, t.pos);   /* an inclusion may reach the surface */
#endif

    float od[NB];
    for (int b = 0; b < NB; ++b) od[b] = 0.0f;
    float ell = 0.0f;                   /* path length from the entry */
    float next_eq = E->spacing;         /* next equal-spacing candidate */
    float nfac = P->n_above / layer_n[0];
    nfac *= nfac;                       /* radiance n^2 law, (n_outside / n_layer)^2 */
    int visit_pts = 0;
    int guard = 0;
#ifdef MAPS
    int mcx = 0, mcy = 0;               /* the maps' column the ray is in */
    int walled = 0;                     /* the last region ended at a column wall (mcx, mcy tracked) */
#endif
    while (++guard < 1000000) {
        int ev;
        const int L = t.L;
        float db = next_boundary(&t, P, iface, heights, BIG, &ev);
        if (ev == EV_NONE) db = E->max_len;
#ifdef MAPS
        /* a mapped layer (outside the inclusions): the region ends at the next column wall too.
         * The column is found from the position at a region's start, except just past a wall
         * (there the position lies on the wall: the crossing's index is kept instead) */
        if (!walled) {
            const int2 c = map_column(optics, t.pos.x, t.pos.y, P);
            mcx = c.x; mcy = c.y;
        }
        walled = 0;
#if NINC > 0
        const int mfirst = map_split_first(optics, MATERIAL(&t));
#else
        const int mfirst = map_split_first(optics, L);
#endif
        int at_wall = 0, wall_axis = 0;
        if (mfirst >= 0) {
            const float dw = map_wall(optics, t.pos.x, t.pos.y, t.dir.x, t.dir.y, mcx, mcy, &wall_axis, P);
            if (dw < db) { db = dw; ev = EV_ZONE; at_wall = 1; }
        }
        if (at_wall && ell + db > E->max_len) { at_wall = 0; ev = EV_NONE; }      /* the ray ends first */
        e.col = mfirst >= 0 ? mcy * as_int(optics[MAP_BASE].z) + mcx : -1;
#endif
#if NINC > 0
        /* the region ends at an inclusion's surface too (as the photon pass's flights): inside
         * one the ray's pieces and points take its material, its extinction and its rate */
        const int m = MATERIAL(&t);
        int inc = -1;
        const float dinc = next_inclusion(optics, t.pos, t.dir, t.inside, INCLUSIONS_OF_LAYER(optics, L), &inc);
        const int at_inc = dinc <= db;
        if (at_inc) { db = dinc; ev = EV_ZONE; }       /* not EV_NONE: the walk goes on past it */
#else
        const int m = L;
#endif
        /* where the most transparent band falls below the threshold inside this region */
#ifdef MAPS
        float s_cut = threshold_cut_map(od, m, mfirst, mcx, mcy, E, optics);
#else
        float s_cut = threshold_cut(od, m, E, optics);
#endif
        if (ell + db > E->max_len) { db = fmax(0.0f, E->max_len - ell); s_cut = fmin(s_cut, db); }
        const float seg = fmin(db, fmax(s_cut, 0.0f));
        visit_pts += sample_points(&e, &t, L, m, seg, ell, tw * nfac, &next_eq, &rng, E, rate, P, iface, heights,
                                   pt_pos, pt_dir, pt_piece, pieces, geo, pt_slab, write);
#ifdef MAPS
        for (int b = 0; b < NB; ++b) od[b] += map_mut(optics, m, b, mfirst, mcx, mcy) * seg;
#else
        for (int b = 0; b < NB; ++b) od[b] += optics[m * NB + b].w * seg;
#endif
        if (seg < db || ev == EV_NONE) break;           /* cut by the threshold */
        t.pos += db * t.dir;
        ell += db;
#ifdef MAPS
        if (at_wall
#if NINC > 0
            && !at_inc
#endif
           ) {
            /* into the next column: no region boundary for the points (the cells go on) */
            if (wall_axis == 0) mcx += t.dir.x > 0.0f ? 1 : -1;
            else mcy += t.dir.y > 0.0f ? 1 : -1;
            walled = 1;
            continue;
        }
#endif
#if NINC > 0
        if (at_inc) {
            /* into or out of inclusion inc: a region boundary like a layer's (S jumps with mu_s
             * there), so an empty visit of the extinction schemes gets its exit point and the
             * cells do not cross it; no Fresnel (an inclusion has its layer's index) */
            if (E->scheme == 1 && visit_pts == 0) {
                visit_pts += place(&e, t.pos - 1e-3f * t.dir, -t.dir, L, tw * nfac, E, pt_pos, pt_dir, pt_piece,
                                   pieces, geo, pt_slab, point_slab(P, iface, heights, t.pos - 1e-3f * t.dir, L, write),
                                   write);
            }
            if (visit_pts > 0 && e.have_point) { flush_pieces(&e, pieces, geo, write); e.split_ok = 0; }
            visit_pts = 0;
            t.inside ^= 1 << inc;
            locate_column(&t, P);
            continue;
        }
#endif

        /* ---- boundary events: the eye ray takes the transmitted branch only */
        const int oix = t.ix, oiy = t.iy;
        const float3 opos = t.pos;
        int out = 0;
        const int L2 = layer_beyond(&t, ev, L, &out, P, iface, heights);
        if (out) break;
#if NINC > 0
        if (ev == EV_DOMAIN_X || ev == EV_DOMAIN_Y) t.inside = inclusion_mask(optics, t.pos);  /* wrapped */
#endif
        if (L2 == L) continue;
        Face fc;
        eye_face(&fc, &t, ev, L, L2, P, iface, layer_n, smooth);
        if (fc.R >= 1.0f) {
            /* total internal reflection: all the radiance comes along the mirrored path, so the
             * eye ray reflects and stays in L (at a 5 um stair step of the relief a steep ray
             * meets a side wall at grazing incidence); it stays on this side of the face */
            t.ix = oix; t.iy = oiy; t.pos = opos;
            t.dir = reflect3(t.dir, fc.sn);
            if (dot(t.dir, fc.gn) > 0.0f) t.dir = reflect3(t.dir, fc.gn);
            continue;
        }
        /* leaving layer L: extinction-based schemes give an empty visit its exit point */
        if (E->scheme == 1 && visit_pts == 0) {
            visit_pts += place(&e, t.pos - 1e-3f * t.dir, -t.dir, L, tw * nfac, E, pt_pos, pt_dir, pt_piece, pieces,
                               geo, pt_slab, point_slab(P, iface, heights, t.pos - 1e-3f * t.dir, L, write), write);
        }
        /* cells do not cross layers: a visit with points keeps its whole path */
        if (visit_pts > 0 && e.have_point) { flush_pieces(&e, pieces, geo, write); e.split_ok = 0; }
        visit_pts = 0;
        if (L2 >= NL) break;
        if (L2 < 0) {
            if (!cross_furrow(&t, &fc, &tw, &nfac, P, iface, layer_n, heights, smooth)) break;
#if NINC > 0
            t.inside = inclusion_mask(optics, t.pos);   /* back in somewhere else */
#endif
            continue;
        }
        refract_into(&t, &fc, L2, &tw, &nfac, P);
    }
    /* the tail after the last point belongs to the last point */
    if (e.have_point) flush_pieces(&e, pieces, geo, write);
    else e.npend = 0;
    if (write) { ray_spec[r] = spec; ray_hit[r] = 1.0f; }
    else { n_points[r] = e.npts; n_pieces[r] = e.npcs; }
}
