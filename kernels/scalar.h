#ifndef CLPPM_SCALAR_H
#define CLPPM_SCALAR_H

/* Scalar fmin, fmax, clamp, floor, sqrt, fabs, and min and max of integers, written fmin1 ...
 * max1 in the hot code of the walk and the gather (included by volume.h and grid.h).
 * PoCL (INLINE_MATH, set per device by clppm/compute/programs.py) keeps these builtins of its
 * kernel library as calls even on scalars, and the x86-64 calling convention saves no vector
 * register across a call, so each one spills the walk's live state: a tenth of the relief photon
 * pass's time on PoCL 3.0.  Here they are inline and give the library's bits on every input
 * (its fmax and fmin return b on equal arguments, so fmax(-0, +0) is +0; a NaN loses; sqrt and
 * floor are clang's builtins, the same IEEE operations): the renders' bytes are unchanged
 * (tests/test_optics_kernels.py compares them with the builtins on every device).  Elsewhere
 * they are the OpenCL builtins themselves. */
#ifdef INLINE_MATH
#define OVERLOAD __attribute__((overloadable, always_inline)) inline
OVERLOAD float fmax1(float a, float b) { return a > b || b != b ? a : b; }
OVERLOAD double fmax1(double a, double b) { return a > b || b != b ? a : b; }
OVERLOAD float fmin1(float a, float b) { return a < b || b != b ? a : b; }
OVERLOAD double fmin1(double a, double b) { return a < b || b != b ? a : b; }
OVERLOAD float sqrt1(float a) { return __builtin_sqrtf(a); }
OVERLOAD double sqrt1(double a) { return __builtin_sqrt(a); }
OVERLOAD float floor1(float a) { return __builtin_floorf(a); }
OVERLOAD double floor1(double a) { return __builtin_floor(a); }
OVERLOAD int clamp1(int x, int lo, int hi) { return x < lo ? lo : (x > hi ? hi : x); }
OVERLOAD long clamp1(long x, long lo, long hi) { return x < lo ? lo : (x > hi ? hi : x); }
OVERLOAD float clamp1(float x, float lo, float hi) { return fmin1(fmax1(x, lo), hi); }
OVERLOAD float fabs1(float a) { return __builtin_fabsf(a); }
OVERLOAD double fabs1(double a) { return __builtin_fabs(a); }
OVERLOAD int min1(int a, int b) { return a < b ? a : b; }
OVERLOAD uint min1(uint a, uint b) { return a < b ? a : b; }
OVERLOAD int max1(int a, int b) { return a > b ? a : b; }
OVERLOAD uint max1(uint a, uint b) { return a > b ? a : b; }
#undef OVERLOAD
#else
#define fabs1 fabs
#define min1 min
#define max1 max
#define fmax1 fmax
#define fmin1 fmin
#define sqrt1 sqrt
#define floor1 floor
#define clamp1 clamp
#endif

#endif
