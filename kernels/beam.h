/* beam.h -- what the beam estimator's two layouts share (kernels/gather.cl gather_beam,
 * kernels/scatter.cl): a piece's query box in grid cells and the (piece, photon) pair test with
 * the disc's window.  Macros, not functions, so that both layouts compile the very same
 * expressions (the same float bits per pair: the layouts must give the same image).
 *
 * Names they expect in scope:
 *   BEAM_PIECE_SLAB: P, iface, heights, s0, d, len, Lk; declares vert, conform, tb_r.
 *   BEAM_PIECE: iface, vlay (kernel args), gp (GridParams), s0, d (float3), len, Lk (the
 *     piece's layer), R, pslab_k (float4: piece_slabs' (tb_r, conform)); declares vert, inv_dz,
 *     wax, conform, tb_r, e, Rp, c0, c1.
 *   BEAM_PAIR: s0, d, len, Lk, vert, inv_dz, conform, tb_r, R, R2, Rwin, P, p (the photon's
 *     float4 position and weight), bl (its band + 256 layer), tb_p (float2: its layer at its
 *     column, read only when conform); declares ts, wl, wwin; `continue`s when the photon is
 *     not in the piece's disc (inside a loop over candidates).
 */
#ifndef CLPPM_BEAM_H
#define CLPPM_BEAM_H

/* exp_neg (common.h) on 16 lanes: both layouts' band math on one vector, the same bits per lane. */
inline float16 exp_neg16(float16 x) {
    const float16 y = fmax(x, 0.0f) * 1.44269504088896f;
    const float16 n = floor(y);
    const float16 t = (y - n - 0.5f) * 0.693147180559945f;
    const float16 p = 1.0f - t * (1.0f - t * (0.5f - t * (1.0f / 6.0f - t * (1.0f / 24.0f
                    - t * (1.0f / 120.0f - t * (1.0f / 720.0f))))));
    const float16 r = as_float16((127 - convert_int16(n)) << 23) * (p * 0.707106781186548f);
    return select(r, (float16)(0.0f), isless(y, (float16)(126.0f)) == 0);
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

/* A photon of a layer-conforming layer is filed at the depth key phi_key of its fraction phi of
 * the layer (photon_keys); a piece queries the key range of its phi range. */
#define PHI_LO (-0.5f)
#define PHI_HI 1.5f
inline float phi_key(float4 vz, float phi) {
    return vz.x - clamp(phi, PHI_LO, PHI_HI) * (vz.x - vz.y);
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
        const float pad = 1e-2f + 1e-5f * (fabs(tb_r.x) + fabs(za) + fabs(H));
        float pa = PHI_LO, pb = PHI_HI;
        if (H > 1e-2f) {
            pa = (tb_r.x - (fmax(za, zb) + pad)) / H;
            pb = (tb_r.x - (fmin(za, zb) - pad)) / H;
        }
        const float kpad = 1e-3f + 1e-5f * (fabs(vz.x) + fabs(vz.y));
        *hi = phi_key(vz, pa) + kpad;
        *lo = phi_key(vz, pb) - kpad;
        return;
    }
    const float4 span = vlay[NL];
    if (*hi >= span.x && *lo <= span.y) { *lo -= span.z; *hi += span.z; }
#endif
}

#ifndef FLAT
#define BEAM_CONFORM_SLAB_                                                                    \
    if (vert && (IF_VAR(Lk) >= 0 || (Lk + 1 <= NL && IF_VAR(Lk + 1) >= 0))) {                \
        conform = 1;                                                                          \
        tb_r = layer_slab(P, iface, heights, s0 + 0.5f * len * d, Lk);                        \
    }
#define BEAM_ZPAD_ (conform ? fmax(IF_ZMAX(Lk) - IF_ZMIN(Lk), IF_ZMAX(Lk + 1) - IF_ZMIN(Lk + 1)) + 1.0f : 0.0f)
#else
#define BEAM_CONFORM_SLAB_
#define BEAM_ZPAD_ 0.0f
#endif

/* the piece's layer-conforming depth (gather.cl): whether it measures depth in its layer's
 * own coordinates and the layer's top and bottom at the ray's column (kernel piece_slabs, once
 * per scene: it needs no R); declares conform, tb_r */
#define BEAM_PIECE_SLAB                                                                       \
    const int vert = fabs(d.z) >= 0.5f;                                                       \
    int conform = 0;                                                                          \
    float2 tb_r = (float2)(0.0f);                                                             \
    BEAM_CONFORM_SLAB_

/* the piece's disc axis and its query box in cells c0..c1, given conform and tb_r (stored
 * per piece by piece_slabs: pslab = (tb_r, conform)) */
#define BEAM_PIECE                                                                            \
    const int vert = fabs(d.z) >= 0.5f;                                                       \
    const float inv_dz = vert ? 1.0f / d.z : 0.0f;                                            \
    const float wax = vert ? fabs(inv_dz) : 1.0f;       /* 1 / |d . axis| */                  \
    const int conform = pslab_k.z != 0.0f;                                                    \
    const float2 tb_r = pslab_k.xy;                                                           \
    const float zpad = BEAM_ZPAD_;                                                            \
    const float3 e = s0 + len * d;                                                            \
    const float Rp = R * (1.0f + GRID_R_PAD);                                                 \
    const float zp = vert ? 1e-3f + 1e-6f * fabs(s0.z) + zpad : Rp;                           \
    float zlo = fmin(s0.z, e.z) - zp, zhi = fmax(s0.z, e.z) + zp;                             \
    query_depth_keys(vlay, conform ? Lk : -1, tb_r, s0.z, e.z, &zlo, &zhi);                  \
    const float3 lo = (float3)(fmin(s0.x, e.x) - Rp, fmin(s0.y, e.y) - Rp, zlo);              \
    const float3 hi = (float3)(fmax(s0.x, e.x) + Rp, fmax(s0.y, e.y) + Rp, zhi);              \
    const int4 c0 = grid_coords(gp, lo), c1 = grid_coords(gp, hi);

/* the disc axis alone (the scatter, with conform and tb_r stored per piece) */
#define BEAM_PIECE_AXIS                                                                       \
    const int vert = fabs(d.z) >= 0.5f;                                                       \
    const float inv_dz = vert ? 1.0f / d.z : 0.0f;                                            \
    const float wax = vert ? fabs(inv_dz) : 1.0f;

#ifndef FLAT
#define BEAM_PAIR_DEPTH_                                                                      \
    if (conform) {                                                                            \
        if ((bl >> 8) != Lk) continue;                                                        \
        if (tb_p.y > -1e29f && tb_r.y > -1e29f) {                                             \
            wl = (tb_r.x - tb_r.y) / fmax(tb_p.x - tb_p.y, 1e-3f);                            \
            pz = tb_r.x - (tb_p.x - p.z) * wl;                                                \
        } else {                                                                              \
            pz = tb_r.x - (tb_p.x - p.z);                                                     \
        }                                                                                     \
    }
#else
#define BEAM_PAIR_DEPTH_
#endif

#ifndef PROF_NOWIN
#define BEAM_LATERAL_ (P->lateral != 0)
#else
#define BEAM_LATERAL_ 0                 /* timing only: no window */
#endif

/* the pair test: the photon's depth along the ray (ts), its distance from the axis, and near
 * an open side the window (disc.h) of the ray's point at the photon's depth */
#define BEAM_PAIR                                                                             \
    float pz = p.z, wl = 1.0f;                                                                \
    BEAM_PAIR_DEPTH_                                                                          \
    float ts, rho2, qx, qy;                                                                   \
    if (vert) {                                                                               \
        ts = (pz - s0.z) * inv_dz;                                                            \
        qx = s0.x + ts * d.x - p.x; qy = s0.y + ts * d.y - p.y;                               \
        rho2 = qx * qx + qy * qy;                                                             \
    } else {                                                                                  \
        const float3 v = p.xyz - s0;                                                          \
        ts = dot(v, d);                                                                       \
        const float3 q = v - ts * d;                                                          \
        rho2 = dot(q, q);                                                                     \
        qx = q.x; qy = q.y;                                                                   \
    }                                                                                         \
    if (!(ts >= 0.0f && ts < len && rho2 < R2)) continue;                                     \
    float wwin = 1.0f;                  /* pi R^2 / the window's area */                      \
    if (BEAM_LATERAL_) {                                                                      \
        const float2 sd = side_distances(P, s0.xy + ts * d.xy);                               \
        if (fmin(sd.x, sd.y) < Rwin) {                                                        \
            /* window_at, its area only for a photon inside the window */                     \
            const float hx = side_half_width(sd.x, R), hy = side_half_width(sd.y, R);         \
            if (fabs(qx) >= hx || fabs(qy) >= hy) continue;                                   \
            wwin = PI_F * R2 / window_area(hx, hy, R);                                        \
        }                                                                                     \
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
    const float pad = 1e-2f + 1e-5f * (fabs(xa) + fabs(xb) + fabs(ya) + fabs(yb) + Rp);
    const float rlo = iy <= 0 ? -INFINITY : gp.lo_y + (float)iy * gp.h;
    const float rhi = iy >= gp.ny - 1 ? INFINITY : gp.lo_y + (float)(iy + 1) * gp.h;
    const float dy = fmax(fmax(rlo - yb, ya - rhi) - pad, 0.0f);
    const float hw = sqrt(fmax(Rp * Rp - dy * dy, 0.0f)) + pad;
    return (int2)(max(cx0, grid_axis(xa - hw, gp.lo_x, gp.inv_h, gp.nx)),
                  min(cx1, grid_axis(xb + hw, gp.lo_x, gp.inv_h, gp.nx)));
}

#define BEAM_ROW_X(iy) beam_row_x(gp, (iy), c0.x, c1.x, fmin(s0.x, e.x), fmax(s0.x, e.x),     \
                                  fmin(s0.y, e.y), fmax(s0.y, e.y), Rp)

#endif
