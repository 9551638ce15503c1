/* 8-lane helpers shared by the kernels (pasted in place of `#include "lanes.h"`
 * by nrpose/device.py, so that PoCL's kernel cache sees the whole source).
 *
 * PoCL's builtins vload8, vstore3, all, any, select, fabs, sqrt, rsqrt and atan2
 * are out-of-line calls in the binary it builds here, and each call spills
 * every live float8 register around it: the dragon pose kernel spent half its
 * time on them. These macros and functions do the same with pointer casts,
 * scalar stores, bit operations and Newton steps, which compile inline. Vector
 * selects are written `c ? a : b`. Check a build with
 * `objdump -d ~/.cache/pocl/kcache/<xx>/<hash>/<kernel>/<local size>/<kernel>.so | grep call`.
 */

/* Chunk g (8 consecutive floats / ints starting at p + 8g); p + 8g must be
 * 32-byte aligned: rows of a multiple of 8 elements in an OpenCL buffer are. */
#define LOAD8(g, p) (*(__global const float8 *)((p) + 8 * (g)))
#define LOADI8(g, p) (*(__global const int8 *)((p) + 8 * (g)))

/* |x| of the 8 lanes (clears the sign bits). */
#define ABS8(x) as_float8(as_int8(x) & (int8)0x7fffffff)

/* OR of the 8 lanes. */
static inline int or8(const int8 v)
{
    const int4 a = v.lo | v.hi;
    const int2 b = a.lo | a.hi;
    return b.x | b.y;
}

/* True when the 8 lanes hold one value. */
#define SAME8(h) (or8((h) ^ (int8)(h).s0) == 0)

/* True when some lane of x is not zero. */
#define ANY_NONZERO8(x) (or8((x) != 0.0f) != 0)

/* Store lane l of (x, y, z) as the 3 floats at q + 3 * o.sl, for the 8 lanes
 * (o: int8 of row indices; rows 0..7 for consecutive rows). */
#define STORE_ROWS(x, y, z, q, o) do {                                              \
    (q)[3 * (o).s0] = (x).s0; (q)[3 * (o).s0 + 1] = (y).s0; (q)[3 * (o).s0 + 2] = (z).s0; \
    (q)[3 * (o).s1] = (x).s1; (q)[3 * (o).s1 + 1] = (y).s1; (q)[3 * (o).s1 + 2] = (z).s1; \
    (q)[3 * (o).s2] = (x).s2; (q)[3 * (o).s2 + 1] = (y).s2; (q)[3 * (o).s2 + 2] = (z).s2; \
    (q)[3 * (o).s3] = (x).s3; (q)[3 * (o).s3 + 1] = (y).s3; (q)[3 * (o).s3 + 2] = (z).s3; \
    (q)[3 * (o).s4] = (x).s4; (q)[3 * (o).s4 + 1] = (y).s4; (q)[3 * (o).s4 + 2] = (z).s4; \
    (q)[3 * (o).s5] = (x).s5; (q)[3 * (o).s5 + 1] = (y).s5; (q)[3 * (o).s5 + 2] = (z).s5; \
    (q)[3 * (o).s6] = (x).s6; (q)[3 * (o).s6 + 1] = (y).s6; (q)[3 * (o).s6 + 2] = (z).s6; \
    (q)[3 * (o).s7] = (x).s7; (q)[3 * (o).s7 + 1] = (y).s7; (q)[3 * (o).s7 + 2] = (z).s7; \
} while (0)

/* Store (x, y, z) of 8 consecutive rows, xyz interleaved, at q (24 floats, q
 * 32-byte aligned): three 8-float vector stores instead of 24 scalar ones. */
#define STORE_XYZ8(x, y, z, q) do {                                                 \
    __global float8 *v_ = (__global float8 *)(q);                                    \
    v_[0] = (float8)((x).s0, (y).s0, (z).s0, (x).s1, (y).s1, (z).s1, (x).s2, (y).s2); \
    v_[1] = (float8)((z).s2, (x).s3, (y).s3, (z).s3, (x).s4, (y).s4, (z).s4, (x).s5); \
    v_[2] = (float8)((y).s5, (z).s5, (x).s6, (y).s6, (z).s6, (x).s7, (y).s7, (z).s7); \
} while (0)

/* float8 of p[i.s0], ..., p[i.s7]. */
#define GATHER8(p, i) ((float8)((p)[(i).s0], (p)[(i).s1], (p)[(i).s2], (p)[(i).s3], \
                                (p)[(i).s4], (p)[(i).s5], (p)[(i).s6], (p)[(i).s7]))

/* 1/sqrt(x) for a normal float x > 0 (x >= FLT_MIN, finite) without PoCL's out-of-line
 * rsqrt/sqrt calls. On x86 with AVX: the hardware estimate (rsqrtps, relative error
 * <= 3.7e-4) and one Newton step (-> ~1e-7); point rows' pose wall 1.01-1.12x faster
 * than the portable way (alternated processes). Elsewhere (or built with
 * -DPORTABLE_RSQRT): the exponent-halving bit trick, then three Newton steps (relative
 * error 3.4e-2 -> 1.7e-3 -> 4.4e-6 -> float rounding). 0 and denormal x give a wrong
 * (on AVX non-finite) value: callers that can meet them mask those lanes, or use rsqrt8. */
static inline float8 rsqrt8_normal(const float8 x)
{
#if defined(__AVX__) && !defined(PORTABLE_RSQRT)
    const float8 y = __builtin_ia32_rsqrtps256(x);
    return y * (1.5f - 0.5f * x * y * y);
#else
    float8 y = as_float8((int8)0x5f375a86 - (as_int8(x) >> 1));
    y = y * (1.5f - 0.5f * x * y * y);
    y = y * (1.5f - 0.5f * x * y * y);
    return y * (1.5f - 0.5f * x * y * y);
#endif
}

/* 1/sqrt(x) for finite x >= 0: rsqrt8_normal, with denormal x (< 2^-126; |c|^2 of a
 * point handle on a model ~1e-19 across) scaled by 2^64 first and the result by 2^32.
 * rsqrt8(0) is large but finite (2^95, so that 0 * rsqrt8(0) = 0); infinite x gives a
 * wrong value (callers use finite x). */
static inline float8 rsqrt8(const float8 x)
{
    const int8 tiny = x < 1.17549435e-38f;
    const float8 xs = tiny ? x * 18446744073709551616.0f : x;          /* 2^64 */
    /* 0 (and scaled denormals that flushed to 0) take 2^-126 */
    const float8 y = rsqrt8_normal(xs > 0.0f ? xs : (float8)1.17549435e-38f);
    return (tiny ? (float8)4294967296.0f : (float8)1.0f) * y;                    /* 2^32 */
}
