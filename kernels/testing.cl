/* Test wrappers around the shared device functions of common.h, so that the tests check the
 * very code the photon and eye passes run (tests/test_optics_kernels.py).
 * Build with NB = NL = 1 (common.h requires them; nothing here uses them).
 * Directions travel as float4 (xyz, w unused) to avoid float3 buffer layout questions. */
#include "common.h"
#include "disc.h"

/* n cosines of the HG scattering angle, uniforms from the device RNG (Philox, domain 7). */
__kernel void t_hg_sample(float g, uint seed, uint n, __global float* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    Rng rng;
    rng_init(&rng, i, 0u, 7u, seed, 0u);
    out[i] = hg_sample_cos(g, rng_u01(&rng));
}

/* hg_sample_cos at given uniforms u (host-chosen, e.g. the ends of (0, 1]). */
__kernel void t_hg_sample_u(float g, __global const float* u, uint n, __global float* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    out[i] = hg_sample_cos(g, u[i]);
}

/* Full scattering event as photon.cl does it: new direction from d_in, HG cosine and a uniform
 * azimuth, both drawn on the device. */
__kernel void t_scatter(float g, uint seed, uint n, __global const float4* d_in,
                        __global float4* d_out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    Rng rng;
    rng_init(&rng, i, 0u, 8u, seed, 0u);
    const float4 d = d_in[i];
    const float ct = hg_sample_cos(g, rng_u01(&rng));
    const float3 o = scatter_dir(d.xyz, ct, rng_u01(&rng));
    d_out[i] = (float4)(o, ct);     /* w: the sampled cosine */
}

/* rotate_dir with host-given direction, polar cosine and azimuth. */
__kernel void t_rotate(uint n, __global const float4* d_in, __global const float* ct,
                       __global const float* phi, __global float4* d_out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    const float3 o = rotate_dir(d_in[i].xyz, ct[i], phi[i]);
    d_out[i] = (float4)(o, 0.0f);
}

__kernel void t_hg_eval(float g, uint n, __global const float* cos_t, __global float* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    out[i] = hg_eval(g, cos_t[i]);
}

/* Fresnel reflectance and transmitted cosine from n1 into n2. */
__kernel void t_fresnel(float n1, float n2, uint n, __global const float* cos_i,
                        __global float* R, __global float* cos_t) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    float ct;
    R[i] = fresnel_R(n1, n2, cos_i[i], &ct);
    cos_t[i] = ct;
}

/* Raw uniforms of the device RNG (stream i, domain 9), m per stream. */
__kernel void t_u01(uint seed, uint n, uint m, __global float* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    Rng rng;
    rng_init(&rng, i, 0u, 9u, seed, 0u);
    for (uint j = 0; j < m; ++j) out[(size_t)i * m + j] = rng_u01(&rng);
}

/* The hot-path arithmetic of common.h: -ln(u), (cos, sin)(2 pi u), HG sampling. */
__kernel void t_fastmath(float g, uint n, __global const float* u, __global float* nlog,
                         __global float2* cs, __global float* hg) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    nlog[i] = neg_log_u01(u[i]);
    cs[i] = azimuth_cs(u[i]);
    hg[i] = hg_sample_cos(g, u[i]);
}

/* exp_neg of common.h (the beam gather's transmittance) */
__kernel void t_exp_neg(uint n, __global const float* x, __global float* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    out[i] = exp_neg(x[i]);
}

/* quarter_area of disc.h: the unit disc's quarter within the window 0 < x < ex, 0 < y < ey. */
__kernel void t_quarter_area(uint n, __global const float2* e, __global float* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    out[i] = quarter_area(e[i].x, e[i].y);
}

/* window_at of disc.h: the beam disc's window (hx, hy, area, cut) at side distances s, radius R. */
__kernel void t_window_at(uint n, __global const float2* s, const float R, __global float4* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    const DiscWindow w = window_at(s[i], R);
    out[i] = (float4)(w.hx, w.hy, w.area, (float)w.cut);
}

/* The scalar forms of volume.h (fmax1 ... sqrt1: clang's builtins inline where INLINE_MATH is
 * set) and the OpenCL builtins on the same inputs, as bits: out[10 i + k], k = fmax, fmin,
 * sqrt, floor, clamp to (b, c) in pairs (the scalar form first); iout[2 i + k]: int clamp. */
__kernel void t_scalar_math(uint n, __global const float* a, __global const float* b, __global const float* c,
                            __global uint* out, __global int* iout) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    const float x = a[i], y = b[i], lo = fmin(b[i], c[i]), hi = fmax(b[i], c[i]);
    __global uint* o = out + 10 * i;
    o[0] = as_uint(fmax1(x, y)); o[1] = as_uint(fmax(x, y));
    o[2] = as_uint(fmin1(x, y)); o[3] = as_uint(fmin(x, y));
    o[4] = as_uint(sqrt1(x)); o[5] = as_uint(sqrt(x));
    o[6] = as_uint(floor1(x)); o[7] = as_uint(floor(x));
    o[8] = as_uint(clamp1(x, lo, hi)); o[9] = as_uint(clamp(x, lo, hi));
    const int k = (int)clamp(x, -3e9f, 3e9f), l = (int)clamp(lo, -3e9f, 3e9f), h = (int)clamp(hi, -3e9f, 3e9f);
    iout[2 * i] = clamp1(k, min(l, h), max(l, h)); iout[2 * i + 1] = clamp(k, min(l, h), max(l, h));
}

#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
/* the same in double (the smooth surfaces' march, PT_FP64 builds): out[8 i + k] as above, no clamp */
__kernel void t_scalar_math_d(uint n, __global const double* a, __global const double* b, __global ulong* out) {
    const uint i = (uint)get_global_id(0);
    if (i >= n) return;
    const double x = a[i], y = b[i];
    __global ulong* o = out + 8 * i;
    o[0] = as_ulong(fmax1(x, y)); o[1] = as_ulong(fmax(x, y));
    o[2] = as_ulong(fmin1(x, y)); o[3] = as_ulong(fmin(x, y));
    o[4] = as_ulong(sqrt1(x)); o[5] = as_ulong(sqrt(x));
    o[6] = as_ulong(floor1(x)); o[7] = as_ulong(floor(x));
}
#endif
