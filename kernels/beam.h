/* beam.h -- what the beam estimator's two layouts share (kernels/gather.cl gather_beam,
 * kernels/scatter.cl): an eye-ray piece with its disc's axis and depth frame, its query box in
 * grid cells and the (piece, photon) pair test with the disc's window.  Both layouts call the
 * very same functions, so they compute the same float bits per pair (the layouts must give the
 * same image).  All are inlined (HOT): they run per pair in the gather's innermost loop.
 */
#ifndef CLPPM_BEAM_H
#define CLPPM_BEAM_H

#include "common.h"
#include "disc.h"
#include "grid.h"

#ifndef NO_VEC16
/* The band math's vector minima and maxima as comparisons and selects (the ternary operator on
 * vectors), which every compiler keeps inline: PoCL calls its kernel library for fmin, fmax,
 * floor, min and select on vectors, spilling the live vector registers around each call (a
 * tenth of the gather's time under PoCL 3.0; photon_lanes.h's min_v and sel_f are the same for
 * its lanes).  The same bits as the builtins: a NaN loses, and equal arguments give the second. */
inline float16 fmin16(float16 x, float c) {
    const float16 cv = (float16)(c);
    return x < cv ? x : cv;
}
inline ulong16 min16(ulong16 a, ulong16 b) { return a < b ? a : b; }

/* exp_neg (common.h) on 16 lanes: both layouts' band math on one vector, the same bits per lane
 * (floor(y) is the truncation of y in [0, 127], and lanes with y >= 126 give 0). */
inline float16 exp_neg16(float16 x) {
    const float16 zero = (float16)(0.0f);
    const float16 y = (x > zero ? x : zero) * 1.44269504088896f;
    const float16 ymax = (float16)(127.0f);
    const int16 ni = convert_int16(y < ymax ? y : ymax);
    const float16 n = convert_float16(ni);
    const float16 t = (y - n - 0.5f) * 0.693147180559945f;
    const float16 p = 1.0f - t * (1.0f - t * (0.5f - t * (1.0f / 6.0f - t * (1.0f / 24.0f
                    - t * (1.0f / 120.0f - t * (1.0f / 720.0f))))));
    const float16 r = as_float16((127 - ni) << 23) * (p * 0.707106781186548f);
    return y < (float16)(126.0f) ? r : zero;
}

/* (native_)rsqrt on 16 lanes as two 8-lane halves, the same value per lane: pip's PoCL 3.0
 * (LLVM 14) aborts at the first launch of a kernel that takes any sqrt-family builtin of a
 * float16 on AVX2 targets (AMD Zen 4: "Cannot select: fsqrt"); float8 compiles everywhere. */
inline float16 native_rsqrt16(float16 q) {
    return (float16)(native_rsqrt(q.lo), native_rsqrt(q.hi));
}
inline float16 rsqrt16(float16 q) {
    return (float16)(rsqrt(q.lo), rsqrt(q.hi));
}
#endif

/* A photon of a layer-conforming layer is filed at the depth key phi_key of its fraction phi of
 * the layer (photon_keys); a piece queries the key range of its phi range. */
#define PHI_LO (-0.5f)
#define PHI_HI 1.5f
inline float phi_key(float4 vz, float phi) {
    return vz.x - clamp1(phi, PHI_LO, PHI_HI) * (vz.x - vz.y);
}

/* The depth-key range of a piece's query (photon_keys).  A conforming piece of a virtual layer
 * L accepts photons of L whose conformed depth tb_r.x - phi (tb_r.x - tb_r.y) lies in its depth
 * range [za, zb] (padded: 1e-2 um plus 1e-5 of the magnitudes, far above the rounding of
 * either side's phi, which share the subtraction top - z), so phi in [(tb_r.x - zb)/H,
 * (tb_r.x - za)/H]; a layer at most 1e-2 um thick at the ray's column takes every phi.  Any
 * other query keeps its z range, widened by the largest shift of a virtual photon's key from
 * its z (vlay[NL].z) where it reaches the virtual layers' z span (vlay[NL].xy). */
inline void query_depth_keys(__constant const float4* vlay, int L, float2 tb_r, float za, float zb,
                             float* lo, float* hi) {
#ifndef FLAT
    const float4 vz = L >= 0 ? vlay[L] : (float4)(0.0f);
    if (vz.z != 0.0f) {
        const float H = tb_r.x - tb_r.y;
        const float pad = 1e-2f + 1e-5f * (fabs1(tb_r.x) + fabs1(za) + fabs1(H));
        float pa = PHI_LO, pb = PHI_HI;
        if (H > 1e-2f) {
            pa = (tb_r.x - (fmax1(za, zb) + pad)) / H;
            pb = (tb_r.x - (fmin1(za, zb) - pad)) / H;
        }
        const float kpad = 1e-3f + 1e-5f * (fabs1(vz.x) + fabs1(vz.y));
        *hi = phi_key(vz, pa) + kpad;
        *lo = phi_key(vz, pb) - kpad;
        return;
    }
    const float4 span = vlay[NL];
    if (*hi >= span.x && *lo <= span.y) { *lo -= span.z; *hi += span.z; }
#endif
}

/* An eye-ray piece (the eye pass's geometry, geo[2k], geo[2k + 1]): its start, direction,
 * length and layer; its disc's axis: vert (|d.z| >= 1/2: the horizontal disc, depth along z;
 * else the disc perpendicular to the piece), 1 / d.z and wax = 1 / |d . axis|; and its
 * layer-conforming depth: conform (depth in its layer's own coordinates) and tb_r, the layer's
 * top and bottom at the ray's column. */
typedef struct {
    float3 s0, d;
    float len;
    int Lk;
#if NINC > 0 && !defined(FLAT)
    int Ll;                     /* its layer (Lk: its material, an inclusion's inside one) */
#endif
    int vert;
    float inv_dz, wax;
    int conform;
    float2 tb_r;
} BeamPiece;

/* A candidate photon of a piece's disc: its depth along the ray (ts), the Jacobian of the
 * layer-conforming depth map (wl) and the disc's area over its window's near an open side
 * (wwin, pi R^2 / the window's area). */
typedef struct {
    float ts, wl, wwin;
} BeamHit;

HOT BeamPiece beam_piece_at(__global const float4* geo, uint k) {
    const float4 g0 = geo[2 * k], g1 = geo[2 * k + 1];
    BeamPiece pc;
    pc.s0 = g0.xyz; pc.d = g1.xyz;
    pc.len = g0.w;
#if NINC > 0 && !defined(FLAT)
    /* inclusions on the relief: the record is material + 256 layer (eye.cl write_piece) */
    const int code = (int)g1.w;
    pc.Lk = code & 255;
    pc.Ll = code >> 8;
#else
    pc.Lk = (int)g1.w;
#endif
    return pc;
}

/* the disc's axis of the piece */
HOT void beam_axis(BeamPiece* pc) {
    pc->vert = fabs1(pc->d.z) >= 0.5f;
    pc->inv_dz = pc->vert ? 1.0f / pc->d.z : 0.0f;
    pc->wax = pc->vert ? fabs1(pc->inv_dz) : 1.0f;       /* 1 / |d . axis| */
}

/* the piece's layer-conforming depth as piece_slabs stores it: (top, bottom, conform, 0) */
HOT void beam_frame(BeamPiece* pc, float4 pslab_k) {
    pc->conform = pslab_k.z != 0.0f;
    pc->tb_r = pslab_k.xy;
}

#ifdef SMOOTH_SURFACE
/* On the smooth surfaces a slanted piece's ends lie at fractional depths phi0, phi1 of the layer
 * at their own (x, y), which its midpoint's slab (tb_mid) places a little off: a piece entering
 * where the top is lower than at its midpoint would miss the photons just under the top, and
 * nothing would make up for them.  The frame (top, top - T) that puts both ends at their own
 * phi, T = (z0 - z1) / (phi1 - phi0), makes the pieces of one crossing of the layer tile its
 * photons' phi exactly (any T > 0 is the piece's own frame: a steep furrow wall gives a small
 * one).  The midpoint's slab where the ends' phi are too close to fix T (a short piece), phi
 * does not grow along the piece's way down (a ray that the surface falls away from faster), or
 * the layer is unbounded below. */
HOT float2 beam_piece_ends(__constant const Params* P, __constant const float4* iface,
                           __global const float* heights, const BeamPiece* pc, float2 tb_mid) {
    if (!(tb_mid.y > -1e29f)) return tb_mid;
    const float3 e = pc->s0 + pc->len * pc->d;
#if NINC > 0
    const float2 t0 = layer_slab(P, iface, heights, pc->s0, pc->Ll);
    const float2 t1 = layer_slab(P, iface, heights, e, pc->Ll);
#else
    const float2 t0 = layer_slab(P, iface, heights, pc->s0, pc->Lk);
    const float2 t1 = layer_slab(P, iface, heights, e, pc->Lk);
#endif
    const float phi0 = (t0.x - pc->s0.z) / fmax1(t0.x - t0.y, 1e-3f);
    const float phi1 = (t1.x - e.z) / fmax1(t1.x - t1.y, 1e-3f);
    const float Tm = tb_mid.x - tb_mid.y;
    const float T = (pc->s0.z - e.z) / (phi1 - phi0);
    if (!(fabs1(phi1 - phi0) > 1e-3f && T > 0.1f * Tm && T < 10.0f * Tm)) return tb_mid;
    const float top = pc->s0.z + phi0 * T;
    return (float2)(top, top - T);
}
#endif

/* The piece's layer-conforming depth (kernel piece_slabs, once per scene: it needs no R):
 * whether it measures depth in its layer's own coordinates (a vertical piece where either of
 * its layer's interfaces varies), and the layer's top and bottom at the ray's column; as
 * (tb_r, conform, 0). */
HOT float4 beam_piece_slab(__constant const Params* P, __constant const float4* iface,
                           __global const float* heights, const BeamPiece* pc) {
    const int vert = fabs1(pc->d.z) >= 0.5f;
    int conform = 0;
    float2 tb_r = (float2)(0.0f);
#ifndef FLAT
#if NINC > 0
    const int Lk = pc->Ll;          /* the layer's depth, whatever the material */
#else
    const int Lk = pc->Lk;
#endif
    if (vert && (IF_VAR(Lk) >= 0 || (Lk + 1 <= NL && IF_VAR(Lk + 1) >= 0))) {
        conform = 1;
        tb_r = layer_slab(P, iface, heights, pc->s0 + 0.5f * pc->len * pc->d, Lk);
#ifdef SMOOTH_SURFACE
        tb_r = beam_piece_ends(P, iface, heights, pc, tb_r);
#endif
    }
#endif
    return (float4)(tb_r.x, tb_r.y, (float)conform, 0.0f);
}

/* the depth padding of a conforming piece's query: its layer's interfaces' amplitude */
HOT float beam_zpad(__constant const float4* iface, const BeamPiece* pc) {
#ifndef FLAT
#if NINC > 0
    const int Lk = pc->Ll;
#else
    const int Lk = pc->Lk;
#endif
    return pc->conform ? fmax1(IF_ZMAX(Lk) - IF_ZMIN(Lk), IF_ZMAX(Lk + 1) - IF_ZMIN(Lk + 1)) + 1.0f : 0.0f;
#else
    return 0.0f;
#endif
}

/* A piece's query box in grid cells c0..c1, and what beam_row_x narrows each row by: the
 * piece's x and y range and the padded radius Rp. */
typedef struct {
    int4 c0, c1;
    float xa, xb, ya, yb;
    float Rp;
} BeamBox;

HOT BeamBox beam_box(const GridParams gp, __constant const float4* vlay, __constant const float4* iface,
                     const BeamPiece* pc, float R) {
    const float3 s0 = pc->s0, d = pc->d;
    const float len = pc->len;
    const float zpad = beam_zpad(iface, pc);
    const float3 e = s0 + len * d;
    const float Rp = R * (1.0f + GRID_R_PAD);
    const float zp = pc->vert ? 1e-3f + 1e-6f * fabs1(s0.z) + zpad : Rp;
    float zlo = fmin1(s0.z, e.z) - zp, zhi = fmax1(s0.z, e.z) + zp;
#if NINC > 0 && !defined(FLAT)
    query_depth_keys(vlay, pc->conform ? pc->Ll : -1, pc->tb_r, s0.z, e.z, &zlo, &zhi);
#else
    query_depth_keys(vlay, pc->conform ? pc->Lk : -1, pc->tb_r, s0.z, e.z, &zlo, &zhi);
#endif
    const float3 lo = (float3)(fmin1(s0.x, e.x) - Rp, fmin1(s0.y, e.y) - Rp, zlo);
    const float3 hi = (float3)(fmax1(s0.x, e.x) + Rp, fmax1(s0.y, e.y) + Rp, zhi);
    BeamBox bx;
    bx.c0 = grid_coords(gp, lo); bx.c1 = grid_coords(gp, hi);
    bx.xa = fmin1(s0.x, e.x); bx.xb = fmax1(s0.x, e.x);
    bx.ya = fmin1(s0.y, e.y); bx.yb = fmax1(s0.y, e.y);
    bx.Rp = Rp;
    return bx;
}

/* A photon's depth in the piece's frame: its z, or in a conforming piece its fractional depth
 * in its layer at its own column (tb_p) placed at the same fraction of the layer at the ray's
 * column, with the map's Jacobian *wl.  Returns 0 for a photon of another layer. */
HOT int beam_pair_depth(const BeamPiece* pc, float4 p, int bl, float2 tb_p, float* pz, float* wl) {
#ifndef FLAT
    if (pc->conform) {
        const float2 tb_r = pc->tb_r;
#if NINC > 0
        if ((bl >> 8) != pc->Ll) return 0;      /* the photon's layer against the piece's */
#else
        if ((bl >> 8) != pc->Lk) return 0;
#endif
        if (tb_p.y > -1e29f && tb_r.y > -1e29f) {
            const float w = (tb_r.x - tb_r.y) / fmax1(tb_p.x - tb_p.y, 1e-3f);
            *wl = w;
            *pz = tb_r.x - (tb_p.x - p.z) * w;
        } else {
            *pz = tb_r.x - (tb_p.x - p.z);
        }
    }
#endif
    return 1;
}

/* whether the model has open or periodic sides, where a disc takes a window (disc.h) */
HOT int beam_lateral(__constant const Params* P) {
    return P->lateral != 0;
}

/* The pair test of a piece and a photon (p: position and weight, bl: band + 256 layer, tb_p:
 * its layer at its column, read only when conform): the photon's depth along the ray (ts), its
 * distance from the axis, and near an open side the window (disc.h) of the ray's point at the
 * photon's depth.  Returns 0 when the photon is not in the piece's disc; else fills *h. */
HOT int beam_pair(__constant const Params* P, const BeamPiece* pc, float R, float R2, float Rwin,
                  float4 p, int bl, float2 tb_p, BeamHit* h) {
    const float3 s0 = pc->s0, d = pc->d;
    float pz = p.z, wl = 1.0f;
    if (!beam_pair_depth(pc, p, bl, tb_p, &pz, &wl)) return 0;
    float ts, rho2, qx, qy;
    if (pc->vert) {
        ts = (pz - s0.z) * pc->inv_dz;
        qx = s0.x + ts * d.x - p.x; qy = s0.y + ts * d.y - p.y;
        rho2 = qx * qx + qy * qy;
    } else {
        const float3 v = p.xyz - s0;
        ts = dot(v, d);
        const float3 q = v - ts * d;
        rho2 = dot(q, q);
        qx = q.x; qy = q.y;
    }
    if (!(ts >= 0.0f && ts < pc->len && rho2 < R2)) return 0;
    float wwin = 1.0f;                  /* pi R^2 / the window's area */
    if (beam_lateral(P)) {
        const float2 sd = side_distances(P, s0.xy + ts * d.xy);
        if (fmin1(sd.x, sd.y) < Rwin) {
            /* window_at, its area only for a photon inside the window */
            const float hx = side_half_width(sd.x, R), hy = side_half_width(sd.y, R);
            if (fabs1(qx) >= hx || fabs1(qy) >= hy) return 0;
            wwin = PI_F * R2 / window_area(hx, hy, R);
        }
    }
    h->ts = ts; h->wl = wl; h->wwin = wwin;
    return 1;
}

/* Row iy of a piece's query box: the cells in x that can hold a photon within R of the axis.
 * The row's y range lies dy from the piece's y range [ya, yb], so such a photon lies within
 * sqrt(R^2 - dy^2) of the piece's x range [xa, xb] (the disc's chord; a grazing piece's disc
 * projects within R of its axis too).  Padded by Rp (R (1 + GRID_R_PAD)) and 1e-2 um plus 1e-5
 * of the magnitudes, far above the rounding of the positions (~1e-3 um at 1e4 um) and of the
 * cell boundaries.  Returns (first, last) cell in x, last < first for an empty row. */
inline int2 beam_row_x(const GridParams gp, int iy, int cx0, int cx1, float xa, float xb, float ya,
                       float yb, float Rp)
{
    const float pad = 1e-2f + 1e-5f * (fabs1(xa) + fabs1(xb) + fabs1(ya) + fabs1(yb) + Rp);
    const float rlo = iy <= 0 ? -INFINITY : gp.lo_y + (float)iy * gp.h;
    const float rhi = iy >= gp.ny - 1 ? INFINITY : gp.lo_y + (float)(iy + 1) * gp.h;
    const float dy = fmax1(fmax1(rlo - yb, ya - rhi) - pad, 0.0f);
    const float hw = sqrt1(fmax1(Rp * Rp - dy * dy, 0.0f)) + pad;
    return (int2)(max1(cx0, grid_axis(xa - hw, gp.lo_x, gp.inv_h, gp.nx)),
                  min1(cx1, grid_axis(xb + hw, gp.lo_x, gp.inv_h, gp.nx)));
}

/* beam_row_x of the piece's query box */
HOT int2 beam_box_row(const GridParams gp, const BeamBox* bx, int iy) {
    return beam_row_x(gp, iy, bx->c0.x, bx->c1.x, bx->xa, bx->xb, bx->ya, bx->yb, bx->Rp);
}

#endif
