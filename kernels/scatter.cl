/* scatter.cl -- the beam estimator's atomic flux accumulation layout (render.layout = "scatter",
 * clppm/integrators/beam.py): the same (piece, photon) pairs and the same 64-bit fixed-point terms as
 * gather_beam (kernels/gather.cl), found from the photon's side.
 *
 *   piece_points   once per scene: the sample point of each eye-ray piece
 *   piece_od       once per scene: each piece's optical depth from the ray's entry, per band
 *                  (the gather's running sum, the same expression in the same order)
 *   piece_cells    per pass (R changes): each piece's query box in the photon grid's cells
 *                  (beam_box, the box the gather's query visits); pass 0 counts the pieces per
 *                  cell, pass 1 files them (atomic cursors: the order inside a cell is
 *                  arbitrary, the sums are integers); also the piece's layer at its column
 *   scatter_beam   a work item per stored photon (in the grid's cell order, so neighbouring
 *                  lanes test the same pieces): the pieces of its cell, beam_pair, the band
 *                  terms (BAND16's expressions) added with atom_add into acc[point][band]
 *   scatter_finish a work item per pixel and band class: the gather's per-point float sums,
 *                  in the same point order, into the pixel accumulators
 *
 * The gather saturates its per-point sums at 2^63 - 1 (add_sat); atom_add wraps.  A term is at
 * most 9e18 and the sums of this renderer are below 1e16, so neither ever happens: the same
 * sums.  Needs cl_khr_int64_base_atomics and the default band layout (9 bands per photon, all
 * of one class of 9): clppm/integrators/beam.py falls back to the gather otherwise.
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#include "common.h"
#include "grid.h"
#include "spectral.h"
#include "disc.h"

#define FIX 4294967296.0f
#define INV_FIX (1.0f / 4294967296.0f)
#ifndef GCLASS
#define GCLASS 9
#endif
#define NBC (NB / GCLASS)
#if NINC > 0
#error "scatter.cl: no inclusions (clppm/integrators/beam.py choose_layout: the gather)"
#endif
#if NBC != 9 || HERO_C != 9
#error "scatter.cl: 9 bands per photon, all of one class of 9 (NB / GCLASS == 9)"
#endif

#include "beam.h"

__kernel void piece_points(__global const uint* pt_piece, const uint npts, __global uint* piece_pt)
{
    const uint i = get_global_id(0);
    if (i >= npts) return;
    for (uint k = pt_piece[i]; k < pt_piece[i + 1]; ++k) piece_pt[k] = i;
}

/* per ray and band class: od[k][g][0..8] = the optical depth from the entry to piece k's start */
__kernel void piece_od(__global const uint* ray_start, __global const uint* pt_piece,
                       __global const float4* geo, __global const float16* mutc, const uint nrays,
                       __global float* od)
{
    const uint r = get_global_id(0);
    const int g = get_global_id(1);
    if (r >= nrays) return;
    const uint i0 = ray_start[r], i1 = ray_start[r + 1];
    if (i0 >= i1) return;
    float16 od16 = (float16)(0.0f);
    for (uint k = pt_piece[i0]; k < pt_piece[i1]; ++k) {
        __global float* o = od + (size_t)k * NB + g * NBC;
        vstore8(od16.lo, 0, o);
        o[8] = od16.s8;
        const float len = geo[2 * k].w;
        const int Lk = (int)geo[2 * k + 1].w;
        od16 += mutc[Lk * GCLASS + g] * len;
    }
}

/* pass 0: count the pieces per cell; pass 1: file them.  pinfo[k] = (its layer at its column
 * (tb_r), R, conform) for scatter_beam. */
__kernel void piece_cells(const GridParams gp, __constant const Params* P,
                          __constant const float4* iface, __global const float* heights,
                          __constant const float4* vlay, __global const float4* geo,
                          __global const float4* pslab,       /* piece_slabs (gather.cl) */
                          __global const uint* piece_pt, __global const float* pt_R,
                          const uint npieces, const int global_radius, const float radius_scale,
                          const int fill, volatile __global uint* cursor, __global uint* plist,
                          __global float4* pinfo)
{
    const uint k = get_global_id(0);
    if (k >= npieces) return;
    BeamPiece pc = beam_piece_at(geo, k);
    const uint i = piece_pt[k];
    const float R = global_radius ? pt_R[i] * radius_scale : pt_R[i];
    if (!(R > 0.0f && pc.len > 0.0f)) {
        if (fill) pinfo[k] = (float4)(0.0f, 0.0f, 0.0f, 0.0f);
        return;
    }
    beam_axis(&pc);
    beam_frame(&pc, pslab[k]);
    const BeamBox bx = beam_box(gp, vlay, iface, &pc, R);
    if (fill) pinfo[k] = (float4)(pc.tb_r.x, pc.tb_r.y, R, (float)pc.conform);
    for (int iy = bx.c0.y; iy <= bx.c1.y; ++iy) {
        const int2 xr = beam_box_row(gp, &bx, iy);      /* the disc's chord over the row */
        for (int iz = bx.c0.z; iz <= bx.c1.z; ++iz)
            for (int ix = xr.x; ix <= xr.y; ++ix) {
                const uint c = grid_cell_index(gp, ix, iy, iz);
                const uint slot = atomic_inc(&cursor[c]);
                if (fill) plist[slot] = k;
            }
    }
}

__kernel void scatter_beam(const GridParams gp, __constant const Params* P,
                           __global const uint* cell_start,    /* the photon grid (with classes) */
                           __global const float4* spos_w, __global const float4* sdir_b,
                           __global const float2* sslab, __global const float16* sw16,
                           __global const float16* hgc, __global const float16* mutc,
                           __global const uint* pstart,        /* the piece grid: [cells + 1] */
                           __global const uint* plist, __global const float4* pinfo,
                           __global const float4* geo, __global const uint* piece_pt,
                           __global const float* od,           /* piece_od */
                           const uint n, volatile __global long* acc,   /* [npts][NB] */
                           volatile __global uint* pt_M,
                           /* bench/studies/spots.py only (spots != 0): per pixel the largest single
                            * pair's share, f_i x its fixed-point terms summed over the bands,
                            * as float bits (positive floats order as their bits) */
                           const int spots, __global const uint* pt_pix,
                           __global const float4* pt_pos, volatile __global uint* pix_max)
{
    const uint j = get_global_id(0);
    if (j >= n) return;
    /* the photon's grid cell (and class): the last cell starting at or before j */
    uint a = 0, b = gp.ncells;
    while (b - a > 1u) {
        const uint m = (a + b) >> 1;
        if (cell_start[m] <= j) a = m; else b = m;
    }
    const uint cxyz = grid_cells_xyz(gp);
    const int g = (int)(a / cxyz);
    const uint cell = a - (uint)g * cxyz;
    const float4 p = spos_w[j];
    const float4 dd = sdir_b[j];
    const int bl = (int)dd.w;
    const float2 tb_p = sslab[j];
    const float16 wj = sw16[j];
    __global const float16* hh = hgc + ((bl >> 8) * GCLASS + g) * 3;
    const float16 hx = hh[0], hy = hh[1], hz = hh[2];
    const uint t1 = pstart[cell + 1];
    for (uint t = pstart[cell]; t < t1; ++t) {
        const uint k = plist[t];
        BeamPiece pc = beam_piece_at(geo, k);
        const float4 pi = pinfo[k];
        pc.tb_r = pi.xy;
        const float R = pi.z;
        pc.conform = pi.w != 0.0f;
        const float R2 = R * R;
        const float Rwin = window_reach(R);
        beam_axis(&pc);
        BeamHit h;
        if (!beam_pair(P, &pc, R, R2, Rwin, p, bl, tb_p, &h)) continue;
        const float cw = dot(dd.xyz, pc.d);                /* w_eye = -d */
        __global const float* ok = od + (size_t)k * NB + g * NBC;
        const float16 od16 = (float16)(vload8(0, ok), ok[8], 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f);
        const float16 w = wj * pc.wax * h.wl * h.wwin;
        const float16 q = hx + hy * cw;
        const float16 rq = native_rsqrt16(q);
        const float16 T = exp_neg16(od16 + mutc[pc.Lk * GCLASS + g] * h.ts);
        const long16 x = convert_long16(fmin16(hz * rq * rq * rq * w * T * FIX, 9.0e18f));
        const uint i = piece_pt[k];
        volatile __global long* ai = acc + (size_t)i * NB + g;
        if (x.s0) atom_add(ai, x.s0);
        if (x.s1) atom_add(ai + GCLASS, x.s1);
        if (x.s2) atom_add(ai + 2 * GCLASS, x.s2);
        if (x.s3) atom_add(ai + 3 * GCLASS, x.s3);
        if (x.s4) atom_add(ai + 4 * GCLASS, x.s4);
        if (x.s5) atom_add(ai + 5 * GCLASS, x.s5);
        if (x.s6) atom_add(ai + 6 * GCLASS, x.s6);
        if (x.s7) atom_add(ai + 7 * GCLASS, x.s7);
        if (x.s8) atom_add(ai + 8 * GCLASS, x.s8);
        atomic_inc(&pt_M[i]);
        if (spots) {
            const float16 xf = convert_float16(x);
            const float sx = xf.s0 + xf.s1 + xf.s2 + xf.s3 + xf.s4 + xf.s5 + xf.s6 + xf.s7 + xf.s8;
            const float c = pt_pos[i].w / (PI_F * R2) * INV_FIX * sx;
            atomic_max(&pix_max[pt_pix[i]], as_uint(c));
        }
    }
}

/* bench/studies/spots.py: the pixel of each sample point */
__kernel void point_pixels(__global const uint* ray_start, const int npix, const int spp,
                           __global uint* pt_pix)
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const uint i0 = ray_start[(uint)pix * (uint)spp], i1 = ray_start[(uint)(pix + 1) * (uint)spp];
    for (uint i = i0; i < i1; ++i) pt_pix[i] = (uint)pix;
}

/* per pixel and band class: gather_beam's per-point float sums, in the same order */
__kernel void scatter_finish(__global const uint* ray_start, __global const float4* pt_pos,
                             __global const float* pt_R, __global const long* acc,
                             __global double* pix_acc, const int npix, const int spp,
                             const int global_radius, const float radius_scale,
                             const double pass_scale)
{
    const int pix = get_global_id(0);
    const int g = get_global_id(1);
    if (pix >= npix) return;
    float accp[NBC];
    for (int k = 0; k < NBC; ++k) accp[k] = 0.0f;
    const uint i0 = ray_start[(uint)pix * (uint)spp], i1 = ray_start[(uint)(pix + 1) * (uint)spp];
    for (uint i = i0; i < i1; ++i) {
        const float R = global_radius ? pt_R[i] * radius_scale : pt_R[i];
        const float R2 = R * R;
        if (R > 0.0f) {
            const float f = pt_pos[i].w / (PI_F * R2) * INV_FIX;
            __global const long* ai = acc + (size_t)i * NB + g;
            for (int k = 0; k < NBC; ++k) {
                const long v = ai[GCLASS * k];
                if (v != 0) accp[k] += f * (float)v;
            }
        }
    }
    __global double* out = pix_acc + (size_t)pix * NB + g;
    for (int k = 0; k < NBC; ++k) out[GCLASS * k] += (double)accp[k] * pass_scale;
}
