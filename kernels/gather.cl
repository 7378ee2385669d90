/* Gather and radiance: one work item per pixel walks its eye rays' sample points in order.
 *
 * Per sample point i and pass: gather the stored photons within R_i from the grid,
 *   M_i = number found,  F_i(b) = sum over found photons of band b of  w_p * HG(g_L(b), w_p . w_eye)
 * (w_p the photon's travel direction, w_eye toward the camera, L the point's layer), then the
 * progressive update of Hachisuka, Ogaki & Jensen (2008) in 3-D:
 *   N' = N + alpha M,  R'^3 = R^3 (N + alpha M)/(N + M),  Phi' = (Phi + F)(N + alpha M)/(N + M).
 * Since Phi and V = 4/3 pi R^3 shrink by the same factor, Phi'/V' = Phi/V + F/V: the radiance
 * estimate Phi/(V N_emitted) of every point only ever grows by F/V of each pass.  So no per-point
 * spectral flux is stored: F/V, weighted by the point's path weight integral of T over its
 * interval (per band, exact for the layered extinction), is added straight into the pixel's
 * spectral accumulator.  The per-point state is just R and N.  (The global-radius variant of
 * Knaus & Zwicker 2011: pt_R holds R0, pass p uses R0 * radius_scale(p) and the pass estimates
 * are averaged, each scaled by 1 / its emitted photons.)
 *
 * Estimator.  The in-scattered radiance is discontinuous across layers (mu_s jumps by 4x from
 * epidermis to dermis) and zero in air, while R is 100-300 um against 15-60 um layers.
 *   ESTIMATOR 2 "layer" (default): only photons stored in the point's own layer count, and V is
 *     the exact volume of the sphere between the layer's top and bottom planes at the point's
 *     column (which also removes the air above the surface and below a finite slab);
 *   ESTIMATOR 1 "clip": all photons, V = the sphere minus the cap above the skin surface;
 *   ESTIMATOR 0 "sphere" (the paper): all photons, V = 4/3 pi R^3.
 * The photon record keeps its band and layer as band + 256 * layer.
 *
 * Layout (gather per pixel, not scatter per photon).  Scattering each photon into the points
 * whose sphere holds it needs float atomics on per-point spectral flux (PoCL 3.0 has none; an
 * int64 atomic per pair on CPU costs more than the pair test) and per-point spectral storage
 * (81 accumulators x 2.5 M points for method a).  Gathering per pixel needs neither: a work item
 * owns its pixel's points, sums into private arrays and writes its pixel once per pass.
 *
 * Determinism: F is summed in 64-bit fixed point (order-independent: photons inside a grid
 * cell come in arbitrary order), the per-pixel float sums run in a fixed order, and the pixel
 * accumulators are doubles added once per pass.  The same photons give the same bits.
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#include "common.h"
#include "grid.h"
#include "spectral.h"
#include "disc.h"
#include "beam.h"
#include "inclusion.h"


/* Inclusions (inclusion.h).  A photon stored in material m' estimates there the in-scattered
 * radiance mu_s(m') int f_m'(w . w') L(w') dw' (its weight carries m''s albedo, spectral.h; the
 * photons' density, m''s mu_t).  An eye-ray piece inside an inclusion has the inclusion's
 * material (eye.cl; on the relief its layer too, beam.h BeamPiece.Ll, for the layer-conforming
 * depth), so its transmittance runs at the inclusion's extinction; what it needs is
 * the in-scattered radiance of its own material m.  Across an inclusion's wall (no change of
 * index) the radiance L is continuous and mu_s and g jump, so a photon of m' != m within the
 * disc (or sphere) of a query of material m counts with m's phase function and its weight times
 * mu_s(m) / mu_s(m') per band: the estimate then blurs L, continuous, and not mu_s, which jumps
 * (4x between the dermis and whole blood): without this, a query inside a vessel near its wall
 * counts the dermis's photons at the vessel's transmittance, and a vessel shows brighter than
 * the path tracer sees it where blood is clear (red).  Pairs of two layers keep their layer's
 * estimate, as without inclusions.  The photon record keeps its layer only, so a gather finds a
 * photon's material from its position, testing only the inclusions whose box meets the query's
 * (near: none for a query away from every inclusion, which then pays one box test). */
/* the arguments only builds with inclusions pass (without, the kernels are the ones before them) */
#if NINC > 0
#define INC_ARGS(...) , __VA_ARGS__
#else
#define INC_ARGS(...)
#endif

/* Chromophore maps (maps.h, MAPS; flat layers and the relief, the beam estimator).  An eye-ray piece in a mapped
 * layer lies in one of the maps' columns (eye.cl ends it at their walls), so its extinction is
 * mu_t = the layer's + delta of its column (found at the piece's midpoint) in every band:
 * the transmittance to each photon's depth and the optical depth on past the piece.  A stored
 * photon of a mapped layer needs nothing more: the maps change mu_a only, and the photon pass's
 * delta tracking stores a real scattering event with the weight left after the absorbed fractions
 * mu_a(x)/mu_maj of its tentative collisions, whose density is the medium's own mu_s L (maps.h),
 * as a uniform layer's events are; the estimate reads mu_s(x) int f L, and mu_s is the layer's.
 * The photons carry one band each (HERO_C = 1): the band math runs lane by lane (no BAND16).
 * The sphere estimators' pieces have no geometry to find a column by: the beam's only. */
#ifdef MAPS
#if ESTIMATOR != 3
#error "gather.cl: chromophore maps with the beam estimator only"
#endif
#include "maps.h"
#endif

#if NINC > 0
HOT int photon_material(__global const float4* optics, float3 p, int L, int near) {
    const int in = near ? inclusion_mask_of(optics, p, near) : 0;
    return material_of(L, in);
}

/* whether a photon of material mp counts in a query of material m with m's estimate */
HOT int material_swap(int m, int mp) {
    return mp != m && (mp >= NL || m >= NL);
}

/* mu_s(m) / mu_s(mp) in band b (optics: mu_a / mu_t, ..., mu_t) */
HOT float mus_ratio(__global const float4* optics, int m, int mp, int b) {
    const float4 a = optics[m * NB + b], o = optics[mp * NB + b];
    const float d = o.w * (1.0f - o.x);
    return d > 0.0f ? a.w * (1.0f - a.x) / d : 0.0f;
}
#endif

#define FIX 4294967296.0f               /* 2^32 per unit of weight x phase */
#define INV_FIX (1.0f / 4294967296.0f)

#ifndef ESTIMATOR
#define ESTIMATOR 2
#endif

/* The beam gather's band classes: class g holds the bands g + GCLASS k, k < NBC.  GCLASS
 * divides NB / HERO_C, so the bands of one photon (h + j NB / HERO_C) are all of one class. */
#ifndef GCLASS
#define GCLASS 1
#endif
#define NBC (NB / GCLASS)

/* The beam gather's band math on one vector of 16 lanes (9 used) when a photon carries the 9
 * bands of its class (the default: 81 bands, 9 per path): the same float operations per band
 * as the scalar loop, lane by lane (exp_neg16, kernels/beam.h, is exp_neg's expression), so the
 * same bits.  NO_VEC16 (a compiler that cannot pass 16-lane vectors): the scalar loop. */
#if NBC == 9 && HERO_C == 9 && !defined(NO_VEC16)
#define BAND16 1
#endif

/* Volume of the sphere (centre height z, radius R) between the planes slab.x (top) and slab.y
 * (bottom): integral of pi (R^2 - u^2) du over the part of [-R, R] inside the slab. */
inline float estimator_volume(float z, float R, float2 slab) {
    const float full = 4.0f / 3.0f * PI_F * R * R * R;
#if ESTIMATOR == 0
    return full;
#else
    float hi = fmin1(R, slab.x - z);
#if ESTIMATOR == 2
    float lo = fmax1(-R, slab.y - z);
#else
    float lo = -R;
#endif
    hi = fmax1(hi, lo);
    const float v = PI_F * ((R * R * hi - hi * hi * hi / 3.0f) - (R * R * lo - lo * lo * lo / 3.0f));
    return fmax1(v, 1e-3f * full);
#endif
}

/* Cells to visit for a query: the sphere's box, and with the layer estimator only the depths
 * where photons of the point's layer can be (a thin layer's query then skips the 2R of depth
 * its sphere spans in the layers around it).  Padded by 1 um: photons of layer L lie in
 * [lowest point of its bottom interface, highest point of its top interface]. */
inline int query_z0(const GridParams gp, int z0, int L, __constant const float2* layer_z) {
#if ESTIMATOR == 2
    return max1(z0, grid_axis(layer_z[L].x - 1.0f, gp.lo_z, gp.inv_hz, gp.nz));
#else
    return z0;
#endif
}

inline int query_z1(const GridParams gp, int z1, int L, __constant const float2* layer_z) {
#if ESTIMATOR == 2
    return min1(z1, grid_axis(layer_z[L].y + 1.0f, gp.lo_z, gp.inv_hz, gp.nz));
#else
    return z1;
#endif
}

/* The cells a sphere query at x (radius R, layer L) visits: the rows (iy, iz), iy in c0.y..c1.y
 * and iz in z0..z1, of cells c0.x..c1.x; each row is one contiguous range of cell-sorted
 * photons (grid_row_range).  query_box is HOT: x is a 3-vector, which Intel's compiler
 * miscompiles across a call it does not inline (surface.h). */
typedef struct {
    int4 c0, c1;
    int z0, z1;
} QueryBox;

HOT QueryBox query_box(const GridParams gp, float3 x, float R, int L, __constant const float2* layer_z) {
    QueryBox q;
    grid_query_range(gp, x, R, &q.c0, &q.c1);
    q.z1 = query_z1(gp, q.c1.z, L, layer_z);
    q.z0 = query_z0(gp, q.c0.z, L, layer_z);
    return q;
}

/* Gather over a sphere: the photons within R of sample point x (of layer L, toward the eye
 * w_eye), per band the sum of w_p HG(g_L(b), w_p . w_eye) in fixed point.  Returns the number
 * found. */
HOT uint gather_sphere(const GridParams gp, __global const uint* cell_start, __global const float4* spos_w,
                       __global const float4* sdir_b, __global const float* sextra,
                       __global const float4* hg, __constant const float2* layer_z, float3 x, float R,
                       int L, float3 w_eye, long* acc INC_ARGS(__global const float4* hgtab,
                                                               __global const float4* optics)) {
    const float R2 = R * R;
    uint M = 0;
#if NINC > 0
    const int near = inclusions_near(optics, x.x - R, x.x + R, x.y - R, x.y + R, x.z - R, x.z + R);
    const int mx = material_of(L, near ? inclusion_mask_of(optics, x, near) : 0);   /* the point's */
#endif
    const QueryBox qb = query_box(gp, x, R, L, layer_z);
    for (int iz = qb.z0; iz <= qb.z1; ++iz)
        for (int iy = qb.c0.y; iy <= qb.c1.y; ++iy) {
            const uint2 jr = grid_row_range(gp, cell_start, qb.c0.x, qb.c1.x, iy, iz);
            for (uint j = jr.x; j < jr.y; ++j) {
                const float4 p = spos_w[j];
                if (grid_within(p.xyz, x, R2)) {
                    const float4 d = sdir_b[j];
                    const int bl = (int)d.w;
#if ESTIMATOR == 2
                    if ((bl >> 8) != L) continue;
#endif
#if NINC > 0
                    /* a photon of another material than the point's, either an inclusion: the
                     * point's phase function, its weight times mu_s(point's) / mu_s(photon's) */
                    const int mp = photon_material(optics, p.xyz, L, near);
                    const int swap = material_swap(mx, mp);
                    hg = hgtab + (swap || mx >= NL ? mx : L) * NB;
#endif
                    const float cw = dot(d.xyz, w_eye);
                    for (int c = 0; c < HERO_C; ++c) {     /* the bands the photon carries */
                        const int b = sw_band(bl & 255, c);
#if NINC > 0
                        const float w = (c == 0 ? p.w : sextra[(size_t)j * (HERO_C - 1) + c - 1])
                                        * (swap ? mus_ratio(optics, mx, mp, b) : 1.0f);
#else
                        const float w = c == 0 ? p.w : sextra[(size_t)j * (HERO_C - 1) + c - 1];
#endif
                        const float4 h = hg[b];
                        const float q = h.x - h.y * cw;
                        const float rq = rsqrt(q);
                        acc[b] = add_sat(acc[b], (long)fmin1(h.z * rq * rq * rq * w * FIX, 9.0e18f));
                    }
                    ++M;
                }
            }
        }
    return M;
}

/* The point's estimate F/V into the pixel's per-band sums (accp), weighted per band by the
 * integral of T over the point's cell (its pieces k0..k1, exact per piece); od, the optical
 * depth from the ray's entry, runs on through the pieces. */
HOT void add_point_bands(float* accp, float* od, const long* acc, __global const float4* optics,
                         __global const float2* pieces, uint k0, uint k1, float f) {
    for (int b = 0; b < NB; ++b) {
        float o = od[b];
        if (acc[b] != 0) {          /* integral of T over the cell, exact per piece */
            float Wb = 0.0f;
            for (uint k = k0; k < k1; ++k) {
                const float2 pc = pieces[k];
                const float m = optics[(int)pc.y * NB + b].w;
                const float ml = m * pc.x;
                Wb += exp(-o) * (ml > 1e-6f ? -expm1(-ml) / m : pc.x);
                o += ml;
            }
            accp[b] += Wb * f * (float)acc[b];
        } else {
            for (uint k = k0; k < k1; ++k) {
                const float2 pc = pieces[k];
                o += optics[(int)pc.y * NB + b].w * pc.x;
            }
        }
        od[b] = o;
    }
}

__kernel void gather(const GridParams gp,
                     __global const uint* cell_start,
                     __global const float4* spos_w,
                     __global const float4* sdir_b,
                     __global const float* sextra,          /* HERO_C-1 band weights per photon */
                     __global const float4* hgtab,          /* [NMAT*NB]: 1+g^2, 2g, (1-g^2)/(4 pi) */
                     __global const float4* optics,         /* [NMAT*NB]: mua, mus, g, mut (um^-1), inclusions */
                     __global const uint* ray_start,        /* [nrays+1] first point of each ray */
                     __global const float4* pt_pos,         /* xyz, tw */
                     __global const float4* pt_dir,         /* toward the eye, layer */
                     __global const uint* pt_piece,         /* [npts+1] */
                     __global const float2* pieces,         /* length (um), layer */
                     __global const float2* pt_slab,        /* top, bottom of the point's layer */
                     __constant const float2* layer_z,      /* [NL] lowest, highest z of each layer */
                     __global float* pt_R,
                     __global float* pt_N,
                     __global uint* pt_M,                   /* photons found in this pass */
                     __global double* pix_acc,              /* [(npix-acc_base)*NB] */
                     __global ulong* pix_pairs,             /* [npix-acc_base] photon-point pairs found */
                     const int npix, const int acc_base,    /* the first pixel the sums hold */
                     const int spp,
                     const float alpha, const int global_radius, const float radius_scale,
                     const double pass_scale)
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    float accp[NB];
    for (int b = 0; b < NB; ++b) accp[b] = 0.0f;
    ulong pairs = 0;
    for (int s = 0; s < spp; ++s) {
        const uint r = (uint)pix * (uint)spp + (uint)s;
        const uint i0 = ray_start[r], i1 = ray_start[r + 1];
        float od[NB];                   /* optical depth from the entry, per band */
        for (int b = 0; b < NB; ++b) od[b] = 0.0f;
        for (uint i = i0; i < i1; ++i) {
            const float4 pp = pt_pos[i];
            const float4 pd = pt_dir[i];
            const int L = (int)pd.w;
            const float R = global_radius ? pt_R[i] * radius_scale : pt_R[i];
            const float3 x = pp.xyz;
            long acc[NB];
            for (int b = 0; b < NB; ++b) acc[b] = 0;
            uint M = 0;
            if (R > 0.0f)
                M = gather_sphere(gp, cell_start, spos_w, sdir_b, sextra, hgtab + L * NB, layer_z, x, R,
                                  L, pd.xyz, acc INC_ARGS(hgtab, optics));
            /* path weight integral of T over the point's interval, per band */
            const float V = estimator_volume(x.z, R, pt_slab[i]);
            const float f = (R > 0.0f) ? pp.w / V * INV_FIX : 0.0f;
            add_point_bands(accp, od, acc, optics, pieces, pt_piece[i], pt_piece[i + 1], f);
            /* progressive radius update */
            if (!global_radius && M > 0u) {
                const float N = pt_N[i];
                const float Nn = N + alpha * (float)M;
                pt_N[i] = Nn;
                pt_R[i] = R * cbrt(Nn / (N + (float)M));
            }
            pt_M[i] = M;
            pairs += M;
        }
    }
    __global double* out = pix_acc + (size_t)(pix - acc_base) * NB;
    for (int b = 0; b < NB; ++b) out[b] += (double)accp[b] * pass_scale;
    pix_pairs[pix - acc_base] += pairs;
}

/* Initial radius: the radius at which the first search finds K photons, estimated from the
 * grid's cell counts (photons per unit volume in the block of cells around the sphere), a few
 * fixed-point iterations R = (3K / (4 pi rho))^(1/3).  Costs cells, not photons. */
__kernel void init_radius(const GridParams gp,
                          __global const uint* cell_start,
                          __global const float4* pt_pos,
                          __global float* pt_R,
                          const uint npts, const float K, const float R0, const float Rmax,
                          const int iters)
{
    const uint i = get_global_id(0);
    if (i >= npts) return;
    const float3 x = pt_pos[i].xyz;
    float R = R0;
    for (int it = 0; it < iters; ++it) {
        int4 c0, c1;
        grid_query_range(gp, x, R, &c0, &c1);
        ulong n = 0;
        for (int iz = c0.z; iz <= c1.z; ++iz)
            for (int iy = c0.y; iy <= c1.y; ++iy) {
                uint row = grid_cell_index(gp, c0.x, iy, iz);
                n += cell_start[row + (uint)(c1.x - c0.x) + 1u] - cell_start[row];
            }
        const float vol = (float)(c1.x - c0.x + 1) * (float)(c1.y - c0.y + 1) * (float)(c1.z - c0.z + 1)
                          * gp.h * gp.h * gp.hz;
        float Rn;
        if (n == 0) Rn = 2.0f * R;
        else Rn = cbrt(3.0f * K * vol / (4.0f * PI_F * (float)n));
        R = clamp1(Rn, 0.25f * R, 4.0f * R);
        R = fmin1(R, Rmax);
    }
    pt_R[i] = R;
}

/* Exact photon count within R for every stride-th point (calibrates the initial radius). */
__kernel void count_within(const GridParams gp,
                           __global const uint* cell_start,
                           __global const float4* spos_w,
                           __global const float4* sdir_b,
                           __global const float4* pt_pos,
                           __global const float4* pt_dir,
                           __global const float* pt_R,
                           __constant const float2* layer_z,
                           const uint npts, const uint stride,
                           __global uint* out)
{
    const uint k = get_global_id(0);
    const uint i = k * stride;
    if (i >= npts) return;
    const float3 x = pt_pos[i].xyz;
    const float R = pt_R[i];
    const float R2 = R * R;
    const int L = (int)pt_dir[i].w;
    uint M = 0;
    const QueryBox qb = query_box(gp, x, R, L, layer_z);
    for (int iz = qb.z0; iz <= qb.z1; ++iz)
        for (int iy = qb.c0.y; iy <= qb.c1.y; ++iy) {
            const uint2 jr = grid_row_range(gp, cell_start, qb.c0.x, qb.c1.x, iy, iz);
            for (uint j = jr.x; j < jr.y; ++j)
                if (grid_within(spos_w[j].xyz, x, R2)) {
#if ESTIMATOR == 2
                    if (((int)sdir_b[j].w >> 8) != L) continue;
#endif
                    ++M;
                }
        }
    out[k] = M;
}

/* ---------------------------------------------------------------- the beam estimator
 * ESTIMATOR "beam": the radiance of an eye ray is  L = tw * integral over the ray of T(t) S(x(t)) dt,
 * S the in-scattered radiance density.  With S(x) ~ sum_p Phi_p HG(w_p . w_eye) K(x - x_p) for a
 * normalised kernel K, the integral over t can be done for each photon exactly:
 *   L ~ tw * sum_p Phi_p HG(w_p . w_eye) * integral T(t) K(x(t) - x_p) dt.
 * K here is a disc of radius R in the horizontal plane times a delta in depth:
 *   K(u) = delta(u.z) [|u.xy| < R] / A   ->   integral = T(t*) [rho < R] / (A |d.z|),
 * t* where the ray reaches the photon's depth, rho the horizontal distance there, A the disc's
 * area pi R^2 (near the model's open sides: a smaller disc, and where it still reaches past
 * a side only its part symmetric about the centre, kernels/disc.h).  The kernel
 * never reaches across depth, so the jumps of S at the layer interfaces (mu_s changes 4x between
 * epidermis and dermis) and the steep depth profile of S cost no bias: what is smoothed is only
 * the lateral variation, and a symmetric disc's bias is second order in R there (R^2/8 lap_xy S).
 *
 * Depth is measured in the layers' own coordinates.  Where a layer's top or bottom follows the
 * relief or the papillae, a photon's depth is its fractional depth within its layer at its own
 * column, placed at the same fraction of the layer at the eye ray's column (weight h_ray / h_photon,
 * the Jacobian of that map): so the disc follows the furrows instead of reaching into the air
 * over them (40 % of the plane 2 um below the plateau is furrow) and layers meet only layers.
 * A photon of another layer never counts.  Flat layers: plain z (compiled away with FLAT).
 *
 * The sample points keep the paper's role as owners of path cells: each has its own R
 * (progressive per point, in 2-D: R'^2 = R^2 (N + alpha M)/(N + M)), and its cell's pieces
 * (straight, one layer each) are integrated exactly, so no quadrature error is left from the
 * point placement either.  A piece nearly parallel to the surface (|d.z| < 1/2: after total
 * internal reflection at a furrow wall) uses the disc perpendicular to itself instead (the beam
 * radiance estimate of Jarosz, Zwicker & Jensen 2008), whose depth smoothing is unavoidable.
 * T(t*) is per band, from the optical depth at the piece's start plus mu_t of the piece's layer.
 * Phase: the photon's layer's g (the scattering happens at the photon). */

/* Top and bottom of each stored photon's layer at its own column (layer_slab), once per pass
 * instead of once per (piece, candidate): the beam gather's layer-conforming depth reads it. */
__kernel void photon_slabs(__constant const Params* P, __constant const float4* iface,
                           __global const float* heights, __global const float4* spos_w,
                           __global const float4* sdir_b, const uint n, __global float2* sslab)
{
    const uint j = get_global_id(0);
    if (j >= n) return;
#ifdef FLAT
    sslab[j] = (float2)(0.0f);
#else
    sslab[j] = layer_slab(P, iface, heights, spos_w[j].xyz, (int)sdir_b[j].w >> 8);
#endif
}

/* The grid's depth key of each photon.  The beam gather measures a photon's depth in its
 * layer's own coordinates (its fraction phi of the layer at its column, placed at the same
 * fraction at the eye ray's column), so a piece of a layer-conforming layer L accepts photons
 * whose phi lies in a narrow range, while their z spans the waves of L's interfaces (tens of
 * um against a piece a few um deep).  Photons of such a layer ("virtual" in vlay[L].z) are
 * filed at the depth key  zr_top - phi (zr_top - zr_bot)  (vlay[L].xy: the mean heights of
 * L's interfaces), every other photon at its z.  phi = (top - z) / max(top - bottom, 1e-3) as
 * in gather_beam, from the same subtraction, clamped to [-1/2, 3/2] (the query clamps alike). */

__kernel void photon_keys(__constant const Params* P, __constant const float4* iface,
                          __global const float* heights, __constant const float4* vlay,
                          __global const float4* pos_w, __global const float4* dir_b,
                          const uint n, __global float4* kpos)
{
    const uint j = get_global_id(0);
    if (j >= n) return;
    const float4 p = pos_w[j];
    float z = p.z;
#ifndef FLAT
    const int L = clamp1((int)dir_b[j].w >> 8, 0, NL - 1);
    const float4 vz = vlay[L];
    if (vz.z != 0.0f) {
        const float2 tb = layer_slab(P, iface, heights, p.xyz, L);
        z = phi_key(vz, (tb.x - p.z) / fmax1(tb.x - tb.y, 1e-3f));
    }
#endif
    kpos[j] = (float4)(p.x, p.y, z, (float)((((int)dir_b[j].w) & 255) % GCLASS));
}

/* Per sorted photon: its HERO_C band weights in class order (lane k: band g + GCLASS k, the
 * member c = k - kh mod NBC, c = 0 the hero's p.w), lanes from NBC on 0: what gather_beam's
 * band math reads per pair as one vector (BAND16). */
__kernel void photon_weights16(__global const float4* spos_w, __global const float4* sdir_b,
                               __global const float* sextra, const uint n, __global float* sw16)
{
    const uint j = get_global_id(0);
    if (j >= n) return;
#ifdef BAND16
    const int kh = ((int)sdir_b[j].w & 255) / GCLASS;
    __global float* o = sw16 + (size_t)j * 16;
    for (int k = 0; k < 16; ++k) {
        const int c = k >= kh ? k - kh : k - kh + NBC;
        o[k] = k >= NBC ? 0.0f : c == 0 ? spos_w[j].w : sextra[(size_t)j * (HERO_C - 1) + c - 1];
    }
#endif
}

/* Per eye-ray piece, once per scene: its layer-conforming depth (beam_piece_slab):
 * (top, bottom of its layer at the ray's column, conform, 0).  Read by both layouts' queries
 * instead of evaluating the height field per piece and band class. */
__kernel void piece_slabs(__constant const Params* P, __constant const float4* iface,
                          __global const float* heights, __global const float4* geo,
                          const uint npieces, __global float4* pslab)
{
    const uint k = get_global_id(0);
    if (k >= npieces) return;
    const BeamPiece pc = beam_piece_at(geo, k);
    pslab[k] = beam_piece_slab(P, iface, heights, &pc);
}

/* A ray's optical depth from its entry to a piece's start, and a sample point's 64-bit
 * fixed-point sums, per band of the class (band g + GCLASS k): one vector of 16 lanes (9 used)
 * with BAND16, else arrays. */
#ifdef BAND16
typedef struct { float16 v; } ClassOd;
typedef struct { long16 v; } ClassAcc;
#else
typedef struct { float v[NBC]; } ClassOd;
typedef struct { long v[NBC]; } ClassAcc;
#endif

HOT void class_od_clear(ClassOd* od) {
#ifdef BAND16
    od->v = (float16)(0.0f);
#else
    for (int k = 0; k < NBC; ++k) od->v[k] = 0.0f;
#endif
}

HOT void class_acc_clear(ClassAcc* acc) {
#ifdef BAND16
    acc->v = (long16)(0);
#else
    for (int k = 0; k < NBC; ++k) acc->v[k] = 0;
#endif
}

/* The optical depth on over a piece of layer Lk and length len. */
HOT void class_od_advance(ClassOd* od, __global const float4* optics, __global const float16* mutc,
                          int Lk, int g, float len) {
#ifdef BAND16
    od->v += mutc[Lk * GCLASS + g] * len;
#else
    for (int k = 0; k < NBC; ++k) od->v[k] += optics[Lk * NB + g + GCLASS * k].w * len;
#endif
}

/* The band terms of one (piece, photon) pair, added to the point's sums: per band the photon's
 * weight times the disc's factors (wax, wl, wwin), the phase function of its layer toward the
 * eye (cw = w_p . d, w_eye = -d) and the transmittance from the ray's entry to depth ts of the
 * piece, in fixed point. */
#ifdef BAND16
HOT void beam_pair_bands(ClassAcc* acc, const ClassOd* od, float16 mut16, __global const float16* hgc,
                         __global const float16* sw16, uint j, int bl, int g, float cw, float wax,
                         const BeamHit* h INC_ARGS(float16 wsc)) {
    const float wl = h->wl, wwin = h->wwin, ts = h->ts;
    /* the photon's weights in class order (sw16: lane k holds member c = k - kh (mod 9), c = 0
     * the hero's p.w; lanes 9-15: 0) */
#if NINC > 0
    const float16 w = sw16[j] * wsc * wax * wl * wwin;     /* wsc: mu_s(piece's) / mu_s(photon's) */
#else
    const float16 w = sw16[j] * wax * wl * wwin;
#endif
    __global const float16* hh = hgc + ((bl >> 8) * GCLASS + g) * 3;    /* its material (gather_piece) */
    const float16 q = hh[0] + hh[1] * cw;
#ifdef EXACT_RSQRT                      /* tests on implementations whose native_rsqrt differs
                                         * between vector widths (Intel's: up to 0.9 % per pixel) */
    const float16 rq = rsqrt16(q);
#else
    const float16 rq = native_rsqrt16(q);
#endif
    const float16 T = exp_neg16(od->v + mut16 * ts);
    /* add_sat for the nonnegative terms (fmin maps NaN to 9e18): the sum of two values in
     * [0, 2^63) does not wrap as ulong */
    acc->v = as_long16(min16(as_ulong16(acc->v) + as_ulong16(convert_long16(
                 fmin16(hh[2] * rq * rq * rq * w * T * FIX, 9.0e18f))),
                 (ulong16)(0x7fffffffffffffffUL)));
}
#else
/* the term of band b (class member k, the photon's band c: c = 0 the hero) */
HOT void beam_band_term(ClassAcc* acc, const ClassOd* od, __global const float4* mut_k,
                        __global const float4* hg, __global const float* sextra, uint j, int c,
                        int k, int b, float wk, float cw, float wax, float wl, float wwin, float ts
#ifdef MAPS
                        INC_ARGS(float wsc), const float* mtk) {
#else
                        INC_ARGS(float wsc)) {
#endif
#if NINC > 0
    const float w = (c == 0 ? wk : sextra[(size_t)j * (HERO_C - 1) + c - 1] * wax * wl * wwin) * wsc;
#else
    const float w = c == 0 ? wk : sextra[(size_t)j * (HERO_C - 1) + c - 1] * wax * wl * wwin;
#endif
    const float4 hq = hg[b];
    const float q = hq.x + hq.y * cw;
#ifdef EXACT_RSQRT
    const float rq = rsqrt(q);
#else
    const float rq = native_rsqrt(q);
#endif
#ifdef MAPS
    const float T = exp_neg(od->v[k] + mtk[k] * ts);      /* the piece's column's mu_t (gather_point) */
#else
    const float T = exp_neg(od->v[k] + mut_k[b].w * ts);
#endif
    acc->v[k] = add_sat(acc->v[k], (long)fmin1(hq.z * rq * rq * rq * w * T * FIX, 9.0e18f));
}

HOT void beam_pair_bands(ClassAcc* acc, const ClassOd* od, __global const float4* mut_k,
                         __global const float4* hgtab, __global const float* sextra, uint j,
                         float4 p, int bl, int g, float cw, float wax, const BeamHit* h
#ifdef MAPS
                         INC_ARGS(__global const float4* optics, int mp), const float* mtk) {
#else
                         INC_ARGS(__global const float4* optics, int mp)) {
#endif
    const float wl = h->wl, wwin = h->wwin, ts = h->ts;
    const float wk = p.w * wax * wl * wwin;
    __global const float4* hg = hgtab + (bl >> 8) * NB;           /* its material (gather_piece) */
#if HERO_C == NBC                       /* the photon carries every band of the class */
    const int kh = (bl & 255) / GCLASS;         /* its hero's place */
    for (int k = 0; k < NBC; ++k) {
        const int c = k >= kh ? k - kh : k - kh + NBC;
#if NINC > 0
        const float wsc = mp != (bl >> 8) ? mus_ratio(optics, bl >> 8, mp, g + GCLASS * k) : 1.0f;
#endif
#ifdef MAPS
        beam_band_term(acc, od, mut_k, hg, sextra, j, c, k, g + GCLASS * k, wk, cw, wax, wl, wwin, ts INC_ARGS(wsc), mtk);
#else
        beam_band_term(acc, od, mut_k, hg, sextra, j, c, k, g + GCLASS * k, wk, cw, wax, wl, wwin, ts INC_ARGS(wsc));
#endif
    }
#else
    for (int c = 0; c < HERO_C; ++c) {     /* the bands the photon carries */
        const int b = sw_band(bl & 255, c);
#if NINC > 0
        const float wsc = mp != (bl >> 8) ? mus_ratio(optics, bl >> 8, mp, b) : 1.0f;
#endif
#ifdef MAPS
        beam_band_term(acc, od, mut_k, hg, sextra, j, c, b / GCLASS, b, wk, cw, wax, wl, wwin, ts INC_ARGS(wsc), mtk);
#else
        beam_band_term(acc, od, mut_k, hg, sextra, j, c, b / GCLASS, b, wk, cw, wax, wl, wwin, ts INC_ARGS(wsc));
#endif
    }
#endif
}
#endif

/* Gather over a beam segment: the photons of band class g in the disc of one eye-ray piece
 * (query box, rows narrowed to the disc's chord, the candidates of each row, the pair test),
 * their band terms added to the point's sums.  Returns the pairs found. */
HOT uint gather_piece(const GridParams gp, __constant const Params* P, __constant const float4* iface,
                      __constant const float4* vlay, __global const uint* cell_start, uint cls0,
                      __global const float4* spos_w, __global const float4* sdir_b,
                      __global const float2* sslab, __global const float* sextra,
                      __global const float4* hgtab, __global const float4* optics,
                      __global const float16* hgc, __global const float16* mutc,
                      __global const float16* sw16, const BeamPiece* pc, float R, float R2,
#ifdef MAPS
                      float Rwin, int g, const ClassOd* od, ClassAcc* acc, const float* mtk) {
#else
                      float Rwin, int g, const ClassOd* od, ClassAcc* acc) {
#endif
    uint M = 0;
    const BeamBox bx = beam_box(gp, vlay, iface, pc, R);
    __global const float4* mut_k = optics + pc->Lk * NB;          /* the piece's material */
#if NINC > 0
    const float3 pe = pc->s0 + pc->len * pc->d;
    const int near = inclusions_near(optics, bx.xa - bx.Rp, bx.xb + bx.Rp, bx.ya - bx.Rp, bx.yb + bx.Rp,
                                     fmin1(pc->s0.z, pe.z) - bx.Rp, fmax1(pc->s0.z, pe.z) + bx.Rp);
#endif
#ifdef BAND16
    const float16 mut16 = mutc[pc->Lk * GCLASS + g];
#endif
    for (int iy = bx.c0.y; iy <= bx.c1.y; ++iy) {
        const int2 xr = beam_box_row(gp, &bx, iy);      /* the disc's chord over the row */
        if (xr.y < xr.x) continue;
        for (int iz = bx.c0.z; iz <= bx.c1.z; ++iz) {
            const uint row = grid_cell_index(gp, xr.x, iy, iz) + cls0;
            const uint jb = cell_start[row], je = cell_start[row + (uint)(xr.y - xr.x) + 1u];
#ifdef COUNT_CANDIDATES         /* bench/gather.py: the photons tested, in place of the pairs */
            M += je - jb;
            continue;
#endif
            for (uint j = jb; j < je; ++j) {
                const float4 p = spos_w[j];
                const float4 dd = sdir_b[j];
                const int bl = (int)dd.w;
#ifndef FLAT
                const float2 tb_p = pc->conform ? sslab[j] : (float2)(0.0f);
#else
                const float2 tb_p = (float2)(0.0f);
#endif
                BeamHit h;
                if (!beam_pair(P, pc, R, R2, Rwin, p, bl, tb_p, &h)) continue;
                const float cw = dot(dd.xyz, pc->d);                /* w_eye = -d */
#if NINC > 0
                /* the phase function and mu_s of the piece's material where the photon's is
                 * another and either is an inclusion's (see photon_material); the material
                 * rides in bl's layer bits, its band bits unread here */
                const int mp = photon_material(optics, p.xyz, bl >> 8, near);
                const int mat = material_swap(pc->Lk, mp) ? pc->Lk : mp;
#ifdef BAND16
                float16 wsc = (float16)(1.0f);
                if (mat != mp) {
                    float sc[16];
                    for (int k = 0; k < 16; ++k)
                        sc[k] = k < NBC ? mus_ratio(optics, mat, mp, g + GCLASS * k) : 0.0f;
                    wsc = vload16(0, sc);
                }
                beam_pair_bands(acc, od, mut16, hgc, sw16, j, (mat << 8) | (bl & 255), g, cw, pc->wax, &h, wsc);
#else
                beam_pair_bands(acc, od, mut_k, hgtab, sextra, j, p, (mat << 8) | (bl & 255), g, cw, pc->wax, &h,
#ifdef MAPS
                                optics, mp, mtk);
#else
                                optics, mp);
#endif
#endif
#else
#ifdef BAND16
                beam_pair_bands(acc, od, mut16, hgc, sw16, j, bl, g, cw, pc->wax, &h);
#else
#ifdef MAPS
                beam_pair_bands(acc, od, mut_k, hgtab, sextra, j, p, bl, g, cw, pc->wax, &h, mtk);
#else
                beam_pair_bands(acc, od, mut_k, hgtab, sextra, j, p, bl, g, cw, pc->wax, &h);
#endif
#endif
#endif
                ++M;
            }
        }
    }
    return M;
}

#ifdef MAPS
/* mtk[k]: mu_t of band g + GCLASS k of the piece's material at its column (its midpoint's; the
 * layer's own outside the mapped layers and where the map leaves its mu_a: + 0) */
HOT void map_piece_mut(float* mtk, __global const float4* optics, const BeamPiece* pc, int g,
                       __constant const Params* P) {
    const int first = map_first(optics, pc->Lk);
    const float x = pc->s0.x + 0.5f * pc->len * pc->d.x, y = pc->s0.y + 0.5f * pc->len * pc->d.y;
    for (int k = 0; k < NBC; ++k) {
        const int b = g + GCLASS * k;
        mtk[k] = optics[pc->Lk * NB + b].w + (first >= 0 ? map_delta(optics, pc->Lk, b, first, x, y, P) : 0.0f);
    }
}
#endif

/* A point's pieces, each gathered over (gather_piece) with the ray's optical depth at its start;
 * the depth runs on through them.  Returns the pairs found. */
HOT uint gather_point(const GridParams gp, __constant const Params* P, __constant const float4* iface,
                      __constant const float4* vlay,
                      __global const uint* cell_start, uint cls0, __global const float4* spos_w,
                      __global const float4* sdir_b, __global const float2* sslab,
                      __global const float* sextra, __global const float4* hgtab,
                      __global const float4* optics, __global const float16* hgc,
                      __global const float16* mutc, __global const float16* sw16,
                      __global const float4* pslab, __global const float4* geo, uint k0, uint k1,
                      float R, float R2, int g, ClassOd* od, ClassAcc* acc) {
    /* the window near an open side (disc.h) is that of the ray's point at the photon's depth:
     * the ray drifts sideways with depth (outwards at the sides, ~0.1 per unit depth), so a
     * window placed at the sample point would reach past the side */
    const float Rwin = window_reach(R);
    uint M = 0;
    for (uint k = k0; k < k1; ++k) {
        BeamPiece pc = beam_piece_at(geo, k);
#ifdef MAPS
        float mtk[NBC];
        map_piece_mut(mtk, optics, &pc, g, P);
#endif
        if (R > 0.0f && pc.len > 0.0f) {
            const float4 pslab_k = pslab[k];
            beam_axis(&pc);
            beam_frame(&pc, pslab_k);
            M += gather_piece(gp, P, iface, vlay, cell_start, cls0, spos_w, sdir_b, sslab, sextra,
#ifdef MAPS
                              hgtab, optics, hgc, mutc, sw16, &pc, R, R2, Rwin, g, od, acc, mtk);
#else
                              hgtab, optics, hgc, mutc, sw16, &pc, R, R2, Rwin, g, od, acc);
#endif
        }
#ifdef MAPS
        for (int kk = 0; kk < NBC; ++kk) od->v[kk] += mtk[kk] * pc.len;
#else
        class_od_advance(od, optics, mutc, pc.Lk, g, pc.len);
#endif
    }
    return M;
}

/* The point's sums as radiance over the disc's area, into the pixel's per-band sums (accp). */
HOT void add_point(float* accp, const ClassAcc* acc, float4 pp, float R, float R2) {
#ifdef BAND16
    long a[16];
    vstore16(acc->v, 0, a);
#else
    const long* a = acc->v;
#endif
    if (R > 0.0f) {
        const float f = pp.w / (PI_F * R2) * INV_FIX;
        for (int k = 0; k < NBC; ++k)
            if (a[k] != 0) accp[k] += f * (float)a[k];
    }
}

__kernel void gather_beam(const GridParams gp,
                          __constant const Params* P,       /* the volume: columns, sides */
                          __constant const float4* iface,
                          __global const uint* cell_start,
                          __global const float4* spos_w,
                          __global const float4* sdir_b,
                          __global const float2* sslab,     /* photon_slabs: its layer at its column */
                          __constant const float4* vlay,    /* [NL+1] depth keys (photon_keys) */
                          __global const float* sextra,     /* HERO_C-1 band weights per photon */
                          __global const float4* hgtab,     /* [NMAT*NB]: 1+g^2, 2g, (1-g^2)/(4 pi) */
                          __global const float4* optics,    /* [NMAT*NB]: ..., mut (um^-1) in .w; inclusions */
                          __global const float16* hgc,      /* [NMAT][GCLASS][3]: hgtab's x, y, z by class */
                          __global const float16* mutc,     /* [NMAT][GCLASS]: mu_t by class (band g + GCLASS k) */
                          __global const float16* sw16,     /* photon_weights16: band weights in class order */
                          __global const float4* pslab,     /* piece_slabs */
                          __global const uint* ray_start,
                          __global const float4* pt_pos,    /* xyz, tw */
                          __global const uint* pt_piece,    /* [npts+1] */
                          __global const float4* geo,       /* per piece: (start, len), (dir, layer) */
                          __global float* pt_R,
                          __global float* pt_N,
                          volatile __global uint* pt_M,     /* zeroed; photons found, all classes */
                          __global double* pix_acc,         /* [(npix-acc_base)*NB] */
                          const int npix, const int acc_base, const int spp,
                          const int global_radius, const float radius_scale,
                          const double pass_scale)
{
    const int pix = get_global_id(0);
    const int g = get_global_id(1);                 /* the band class: bands g + GCLASS k */
    if (pix >= npix) return;
    const uint cls0 = grid_cells_xyz(gp) * (uint)g; /* the class's grid */
    float accp[NBC];
    for (int k = 0; k < NBC; ++k) accp[k] = 0.0f;
    for (int s = 0; s < spp; ++s) {
        const uint r = (uint)pix * (uint)spp + (uint)s;
        const uint i0 = ray_start[r], i1 = ray_start[r + 1];
        ClassOd od;                     /* optical depth from the entry to the piece's start */
        class_od_clear(&od);
        for (uint i = i0; i < i1; ++i) {
            const float4 pp = pt_pos[i];
            const float R = global_radius ? pt_R[i] * radius_scale : pt_R[i];
            const float R2 = R * R;
            ClassAcc acc;
            class_acc_clear(&acc);
            const uint M = gather_point(gp, P, iface, vlay, cell_start, cls0, spos_w, sdir_b,
                                        sslab, sextra, hgtab, optics, hgc, mutc, sw16, pslab, geo,
                                        pt_piece[i], pt_piece[i + 1], R, R2, g, &od, &acc);
            add_point(accp, &acc, pp, R, R2);
            if (M > 0u) atomic_add(&pt_M[i], M);    /* integers: the classes' order is immaterial */
        }
    }
    __global double* out = pix_acc + (size_t)(pix - acc_base) * NB + g;
    for (int k = 0; k < NBC; ++k) out[GCLASS * k] += (double)accp[k] * pass_scale;
}

/* After gather_beam: each point's photons found (all classes), its progressive radius update
 * (in 2-D: the disc's area shrinks as N grows) and the pixel's pair count. */
__kernel void gather_beam_points(__global const uint* ray_start, __global float* pt_R,
                                 __global float* pt_N, __global const uint* pt_M,
                                 __global ulong* pix_pairs, const int npix, const int acc_base,
                                 const int spp, const float alpha, const int global_radius)
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    ulong pairs = 0;
    const uint i0 = ray_start[(uint)pix * (uint)spp], i1 = ray_start[(uint)(pix + 1) * (uint)spp];
    for (uint i = i0; i < i1; ++i) {
        const uint M = pt_M[i];
        if (!global_radius && M > 0u) {
            const float R = pt_R[i];
            const float N = pt_N[i];
            const float Nn = N + alpha * (float)M;
            pt_N[i] = Nn;
            pt_R[i] = R * sqrt1(Nn / (N + (float)M));
        }
        pairs += M;
    }
    pix_pairs[pix - acc_base] += pairs;
}
