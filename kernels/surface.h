/* The smooth surfaces: what every pass refracts and reflects at (docs/relief.md, section 1).
 *
 * Interface k is the height field z = h_k(x, y), the Catmull-Rom bicubic through the
 * interface's heights before voxel snapping (Volume.smooth) at the column centres
 * x0 + (i + 1/2) dx, y0 + (j + 1/2) dy: C1, its second derivatives piecewise linear.  Flat
 * interfaces are their plane.  Beyond the grid the edge samples repeat (open, infinite sides) or
 * wrap (periodic).  The passes walk the voxel staircase (positions: column tops at the snapped
 * heights, vertical walls), or with SMOOTH_SURFACE these surfaces themselves (smoothwalk.h), and
 * take the normal of a crossing from here, at the crossing point:
 * the path tracer's walk and its manifold connection (pt.cl, mnee.h), the photon pass
 * (photon.cl) and the eye pass (eye.cl).
 *
 * Relief builds only (not -DFLAT).  `real` (unless the includer defined it, CLPPM_REAL): double
 * where the device has fp64 (PT_FP64, set for every pass's relief build), else float; the path tracer's manifold
 * solver needs the double (tests/test_mnee.py compares it to float64 references), and the other
 * passes share it so that all make the same decision at a crossing.
 */
#ifndef CLPPM_SURFACE_H
#define CLPPM_SURFACE_H

#include "volume.h"

#ifndef CLPPM_REAL
#define CLPPM_REAL
#ifdef PT_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#else
typedef float real;
#endif
#endif

/* Points and directions are 4-vectors with w = 0, never 3-vectors.  Intel's OpenCL CPU
 * compiler (2026.2) miscompiles a 3-vector that crosses the boundary of a function it does not
 * inline (an argument by value or through a pointer, a field of a struct read through a
 * pointer, a return value) when it vectorises the caller across work items: only the first lane
 * of each vectorised group gets the right value (tests/test_mnee.py failed on Intel; reproduced
 * with a 6-line kernel and a noinline function; 4-vectors, 2-vectors and scalars are right).
 * The solver's functions (mnee.h) are large and called from several places, so Intel keeps
 * them as calls.  The w component costs nothing on PoCL: xyz is computed by the same operations. */
#ifdef PT_FP64
typedef double4 real4;
#define convert_real4 convert_double4
#else
typedef float4 real4;
#define convert_real4 convert_float4
#endif
#define R4(x, y, z) ((real4)((x), (y), (z), 0))

/* dot product written out (PoCL calls its library's dot out of line) */
inline real rdot(real4 a, real4 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
/* all four components (sample rows, not points) */
inline real rdot4(real4 a, real4 b) { const real4 p = a * b; return (p.x + p.y) + (p.z + p.w); }

/* h and its derivatives up to second order at (x, y) */
typedef struct { real h, hx, hy, hxx, hxy, hyy; } HF;

/* Catmull-Rom weights of the samples -1..2 at fraction f (W), their first (D) and second (S)
 * derivatives: scalars, so nothing is indexed (an indexed array would live on the stack) */
#define CR_W(f, f2, f3, w0, w1, w2, w3) \
    w0 = (real)0.5 * (-(f) + 2 * (f2) - (f3)); w1 = (real)0.5 * (2 - 5 * (f2) + 3 * (f3)); \
    w2 = (real)0.5 * ((f) + 4 * (f2) - 3 * (f3)); w3 = (real)0.5 * ((f3) - (f2));
#define CR_D(f, f2, w0, w1, w2, w3) \
    w0 = (real)0.5 * (-1 + 4 * (f) - 3 * (f2)); w1 = (real)0.5 * (-10 * (f) + 9 * (f2)); \
    w2 = (real)0.5 * (1 + 8 * (f) - 9 * (f2)); w3 = (real)0.5 * (-2 * (f) + 3 * (f2));
#define CR_S(f, w0, w1, w2, w3) \
    w0 = 2 - 3 * (f); w1 = -5 + 9 * (f); w2 = 4 - 9 * (f); w3 = -1 + 3 * (f);

inline int hf_index(int i, int n, int periodic) {
    if (periodic) { i %= n; return i < 0 ? i + n : i; }
    return clamp1(i, 0, n - 1);
}

/* (x, y) in the samples' grid coordinates: sample i lies at i + 1/2 (the patch of (x, y) is
 * between samples floor(g) and floor(g) + 1) */
inline real hf_gx(__constant const Params* P, real x) { return (x - (real)P->x0) / (real)P->dx - (real)0.5; }
inline real hf_gy(__constant const Params* P, real y) { return (y - (real)P->y0) / (real)P->dy - (real)0.5; }

/* h and its derivatives up to `order` (1: h, hx, hy; 2: the second ones too; a constant at
 * every call, so the compiler drops the rest).  The patch's 4 x 4 samples as four row vectors
 * (one ld4 each inside the grid), combined over y first, then dotted with the x weights. */
inline void hf_eval_n(__constant const Params* P, __constant const float4* iface,
                      __global const float* smooth, int k, real x, real y, HF* o, const int order) {
    o->hx = o->hy = o->hxx = o->hxy = o->hyy = 0;
    const int v = IF_VAR(k);
    if (v < 0) { o->h = (real)IF_Z(k); return; }
    const real gx = hf_gx(P, x), gy = hf_gy(P, y);
    const int ix = (int)gx - (gx < 0), iy = (int)gy - (gy < 0);      /* floor */
    const real fx = gx - (real)ix, fy = gy - (real)iy;
    const real fx2 = fx * fx, fx3 = fx2 * fx, fy2 = fy * fy, fy3 = fy2 * fy;
    real a0, a1, a2, a3, b0, b1, b2, b3, c0, c1, c2, c3;
    const int per = P->lateral == 2;
    __global const float* base = smooth + (size_t)v * (size_t)(P->nx * P->ny);
    real4 s0, s1, s2, s3;
    if (ix >= 1 && ix + 2 < P->nx && iy >= 1 && iy + 2 < P->ny) {
        __global const float* q = base + (size_t)(iy - 1) * (size_t)P->nx + (size_t)(ix - 1);
        s0 = convert_real4(ld4(q)); q += P->nx;
        s1 = convert_real4(ld4(q)); q += P->nx;
        s2 = convert_real4(ld4(q)); q += P->nx;
        s3 = convert_real4(ld4(q));
    } else {
        const int i0 = hf_index(ix - 1, P->nx, per), i1 = hf_index(ix, P->nx, per);
        const int i2 = hf_index(ix + 1, P->nx, per), i3 = hf_index(ix + 2, P->nx, per);
#define CR_ROW(j, out) { \
        __global const float* row = base + (size_t)hf_index(iy - 1 + (j), P->ny, per) * (size_t)P->nx; \
        out = (real4)(row[i0], row[i1], row[i2], row[i3]); }
        CR_ROW(0, s0) CR_ROW(1, s1) CR_ROW(2, s2) CR_ROW(3, s3)
#undef CR_ROW
    }
    CR_W(fy, fy2, fy3, a0, a1, a2, a3)
    CR_D(fy, fy2, b0, b1, b2, b3)
    const real4 V = a0 * s0 + a1 * s1 + a2 * s2 + a3 * s3;
    const real4 VD = b0 * s0 + b1 * s1 + b2 * s2 + b3 * s3;
    CR_W(fx, fx2, fx3, a0, a1, a2, a3)
    CR_D(fx, fx2, b0, b1, b2, b3)
    const real4 AX = (real4)(a0, a1, a2, a3), BX = (real4)(b0, b1, b2, b3);
    const real idx = 1 / (real)P->dx, idy = 1 / (real)P->dy;
    /* the row's height plus the interface's offset (0 unless rows are shared: smoothwalk.h) */
    o->h = rdot4(AX, V) + (real)IF_Z(k);
    o->hx = rdot4(BX, V) * idx;
    o->hy = rdot4(AX, VD) * idy;
    if (order < 2) return;
    CR_S(fy, c0, c1, c2, c3)
    const real4 VS = c0 * s0 + c1 * s1 + c2 * s2 + c3 * s3;
    CR_S(fx, c0, c1, c2, c3)
    const real4 CX = (real4)(c0, c1, c2, c3);
    o->hxx = rdot4(CX, V) * idx * idx;
    o->hxy = rdot4(BX, VD) * idx * idy;
    o->hyy = rdot4(AX, VS) * idy * idy;
}

inline void hf_eval(__constant const Params* P, __constant const float4* iface,
                    __global const float* smooth, int k, real x, real y, HF* o) {
    hf_eval_n(P, iface, smooth, k, x, y, o, 2);
}

/* Upward unit normal of the height field (and the unnormalised (-hx, -hy, 1)'s length) */
inline real4 hf_normal(const HF* f, real* len) {
    const real4 N = R4(-f->hx, -f->hy, 1);
    *len = sqrt(rdot(N, N));
    return N / *len;
}

/* Upward smooth normal of interface k at (x, y) (float; w = 0: no 3-vectors across calls) */
inline float4 smooth_normal(__constant const Params* P, __constant const float4* iface,
                            __global const float* smooth, int k, float x, float y) {
    HF f;
    hf_eval_n(P, iface, smooth, k, x, y, &f, 1);
    real len;
    const real4 n = hf_normal(&f, &len);
    return (float4)((float)n.x, (float)n.y, (float)n.z, 0.0f);
}

/* The shading normal of a crossing of interface k at (x, y) from layer L into L2 (pointing into
 * L2), for fresnel_cross (common.h); gn, the staircase face's own normal, where interface k is
 * flat (the same normal, without the evaluation) */
inline float4 face_normal(__constant const Params* P, __constant const float4* iface,
                          __global const float* smooth, int k, int L, int L2, float x, float y, float4 gn) {
    if (IF_VAR(k) < 0) return gn;
    const float4 sn = smooth_normal(P, iface, smooth, k, x, y);
    return L2 > L ? -sn : sn;
}

#endif
