/* 8-lane helpers shared by the kernels (pasted in place of `#include "lanes.h"`
 * by nrpose/device/programs.py, so that PoCL's kernel cache sees the whole source).
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

/* OR of the 8 lanes. */
static inline int or8(const int8 v)
{
    const int4 a = v.lo | v.hi;
    const int2 b = a.lo | a.hi;
    return b.x | b.y;
}

/* True when some lane of x is not zero. */
#define ANY_NONZERO8(x) (or8((x) != 0.0f) != 0)

#ifdef PLAIN_OPENCL
/* Plain OpenCL C (nrpose/device/env.py plain_opencl; kernels/share.h): no clang vector
 * extensions (__builtin_shufflevector, under-aligned vector types), the 8 rows stored
 * lane by lane, three floats each. Row l of (x, y, z) at q + 3 o (STORE_ROW_). */
#define STORE_ROW_(x, y, z, q, o, l) do {                                           \
    __global float *r_ = (q) + 3 * (size_t)(o);                                     \
    r_[0] = (x).s##l; r_[1] = (y).s##l; r_[2] = (z).s##l;                           \
} while (0)
#define STORE_LANES_(x, y, z, q, o0, o1, o2, o3, o4, o5, o6, o7) do {               \
    const float8 x_ = (x), y_ = (y), z_ = (z);                                      \
    STORE_ROW_(x_, y_, z_, q, o0, 0); STORE_ROW_(x_, y_, z_, q, o1, 1);              \
    STORE_ROW_(x_, y_, z_, q, o2, 2); STORE_ROW_(x_, y_, z_, q, o3, 3);              \
    STORE_ROW_(x_, y_, z_, q, o4, 4); STORE_ROW_(x_, y_, z_, q, o5, 5);              \
    STORE_ROW_(x_, y_, z_, q, o6, 6); STORE_ROW_(x_, y_, z_, q, o7, 7);              \
} while (0)
#define STORE_ROWS(x, y, z, q, o) do {                                              \
    const int8 o_ = (o);                                                            \
    STORE_LANES_(x, y, z, q, o_.s0, o_.s1, o_.s2, o_.s3, o_.s4, o_.s5, o_.s6, o_.s7); \
} while (0)
#define STORE_XYZ8(x, y, z, q) STORE_LANES_(x, y, z, q, 0, 1, 2, 3, 4, 5, 6, 7)
#else
/* Store lane l of (x, y, z) as the 3 floats at q + 3 * o.sl, for the 8 lanes
 * (o: int8 of row indices, one output row per lane): the (x, y) pairs interleaved by two
 * shuffles and stored 8 bytes at a time (a 2-float vector type of 4-byte alignment: rows
 * are 12 bytes apart), then z. Against 24 scalar stores, 18 of them lane extracts, which
 * take the shuffle pipes that the FMA units share: the segment rows' pose kernel on one
 * thread 1.10x (box), 1.06x (dragon); 16-byte masked stores of (x, y, z) were 0.7x, and
 * (x, y) then an overlapping (y, z) pair 1.00x / 1.03x. */
typedef float float2_a4 __attribute__((ext_vector_type(2), aligned(4)));
#define STORE_ROWS(x, y, z, q, o) do {                                              \
    const int8 o_ = (o);                                                            \
    const float8 z_ = (z);                                                          \
    const float8 lo_ = __builtin_shufflevector((x), (y), 0, 8, 1, 9, 4, 12, 5, 13);   \
    const float8 hi_ = __builtin_shufflevector((x), (y), 2, 10, 3, 11, 6, 14, 7, 15); \
    *(__global float2_a4 *)((q) + 3 * o_.s0) = lo_.s01; (q)[3 * o_.s0 + 2] = z_.s0;          \
    *(__global float2_a4 *)((q) + 3 * o_.s1) = lo_.s23; (q)[3 * o_.s1 + 2] = z_.s1;          \
    *(__global float2_a4 *)((q) + 3 * o_.s2) = hi_.s01; (q)[3 * o_.s2 + 2] = z_.s2;          \
    *(__global float2_a4 *)((q) + 3 * o_.s3) = hi_.s23; (q)[3 * o_.s3 + 2] = z_.s3;          \
    *(__global float2_a4 *)((q) + 3 * o_.s4) = lo_.s45; (q)[3 * o_.s4 + 2] = z_.s4;          \
    *(__global float2_a4 *)((q) + 3 * o_.s5) = lo_.s67; (q)[3 * o_.s5 + 2] = z_.s5;          \
    *(__global float2_a4 *)((q) + 3 * o_.s6) = hi_.s45; (q)[3 * o_.s6 + 2] = z_.s6;          \
    *(__global float2_a4 *)((q) + 3 * o_.s7) = hi_.s67; (q)[3 * o_.s7 + 2] = z_.s7;          \
} while (0)

/* Store (x, y, z) of 8 consecutive rows, xyz interleaved, at q (24 floats, q 4-byte
 * aligned: an 8-float vector type of 4-byte alignment, for chunks of consecutive rows that
 * start anywhere): three 8-float vector stores instead of 24 scalar ones, their lanes picked
 * by shuffles from (x, y) and (z, z) (written as a vector of 24 scalars, the segment rows'
 * runs of consecutive rows posed 1.11x slower: the box's kernel on one thread). */
typedef float float8_a4 __attribute__((ext_vector_type(8), aligned(4)));
#define STORE_XYZ8(x, y, z, q) do {                                                 \
    const float16 xy_ = __builtin_shufflevector((x), (y), 0, 1, 2, 3, 4, 5, 6, 7,  \
                                                8, 9, 10, 11, 12, 13, 14, 15);       \
    const float16 zz_ = __builtin_shufflevector((z), (z), 0, 1, 2, 3, 4, 5, 6, 7,  \
                                                0, 1, 2, 3, 4, 5, 6, 7);             \
    __global float8_a4 *v_ = (__global float8_a4 *)(q);                              \
    v_[0] = __builtin_shufflevector(xy_, zz_, 0, 8, 16, 1, 9, 17, 2, 10);           \
    v_[1] = __builtin_shufflevector(xy_, zz_, 18, 3, 11, 19, 4, 12, 20, 5);         \
    v_[2] = __builtin_shufflevector(xy_, zz_, 13, 21, 6, 14, 22, 7, 15, 23);        \
} while (0)

#endif

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

/* 2h/sqrt(x) for a normal float x (as rsqrt8_normal) and any h: on x86 with AVX the estimate
 * y and its Newton step with the scale taken in, h y (3 - x y^2), one multiply fewer than
 * 2h rsqrt8_normal(x) (kernels/nrmls.cl angle_per_sine: point rows' kernel on one thread,
 * box 1.01-1.05x, dragon 1.04-1.06x, bunny 1.03x, armadillo 1.00x; taking k = 2h and
 * halving it here was no faster, the halving not always folded into k's constants). */
static inline float8 rsqrt8_normal_twice(const float8 x, const float8 h)
{
#if defined(__AVX__) && !defined(PORTABLE_RSQRT)
    const float8 y = __builtin_ia32_rsqrtps256(x);
    return (h * y) * (3.0f - x * y * y);
#else
    return (2.0f * h) * rsqrt8_normal(x);
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

/* VW lanes per work-item (-DVW=8 or 16; default 8): the pose kernel's vector types
 * floatv / intv and its helpers, composed of the 8-lane forms above (16 lanes: the
 * .lo and .hi halves). With 16 lanes each operation is two independent 8-lane
 * instructions, which the core overlaps: the point-handle chains (cross product,
 * inverse square root, atan2, ~90 cycles of latency per handle) otherwise leave the
 * FMA pipes half idle (kernels/nrmls.cl, its header). Rows of VW lanes are VW-float
 * aligned: LOADV/LOADIV read row g of a record of such rows. */
#ifndef VW
#define VW 8
#endif
#if VW == 8
typedef float8 floatv;
typedef int8 intv;
#define as_floatv as_float8
#define as_intv as_int8
#define orv or8
#define GATHERV GATHER8
#define STORE_ROWSV STORE_ROWS
#define STORE_XYZV STORE_XYZ8
#define rsqrtv rsqrt8
#define rsqrtv_normal rsqrt8_normal
#define rsqrtv_normal_twice rsqrt8_normal_twice
#elif VW == 16
/* clang notes that a float16 argument's ABI differs without AVX-512 (-Wpsabi) for every
 * function taking a floatv; they are all static inline and inlined, so no call crosses an
 * ABI, and the note only made pyopencl warn at each build of a 16-lane program */
#pragma clang diagnostic ignored "-Wpsabi"
typedef float16 floatv;
typedef int16 intv;
#define as_floatv as_float16
#define as_intv as_int16
#define orv(v) or8((v).lo | (v).hi)
#define GATHERV(p, i) ((float16)(GATHER8(p, (i).lo), GATHER8(p, (i).hi)))
#define STORE_ROWSV(x, y, z, q, o) do {                                             \
    STORE_ROWS((x).lo, (y).lo, (z).lo, q, (o).lo);                                  \
    STORE_ROWS((x).hi, (y).hi, (z).hi, q, (o).hi);                                  \
} while (0)
#define STORE_XYZV(x, y, z, q) do {                                                 \
    STORE_XYZ8((x).lo, (y).lo, (z).lo, q);                                          \
    STORE_XYZ8((x).hi, (y).hi, (z).hi, (q) + 24);                                  \
} while (0)
#define rsqrtv(x) ((float16)(rsqrt8((x).lo), rsqrt8((x).hi)))
#define rsqrtv_normal(x) ((float16)(rsqrt8_normal((x).lo), rsqrt8_normal((x).hi)))
#define rsqrtv_normal_twice(x, h) ((float16)(rsqrt8_normal_twice((x).lo, (h).lo), rsqrt8_normal_twice((x).hi, (h).hi)))
#else
#error "VW (lanes per work-item) must be 8 or 16"
#endif
#define LOADV(g, p) (*(__global const floatv *)((p) + VW * (g)))
/* Store lane l of (x, y, z) as output row r[l] at q (3 floats a row), for the VW lanes of a
 * chunk whose rows r (VW ints) are bound run-coded (nrpose.device.run_coded_rows): a chunk
 * of consecutive rows has its first row bound as ~row (negative) and takes three vector
 * stores per 8 rows (STORE_XYZV), any other chunk its scattered rows (STORE_ROWSV); the
 * box's segment rows, 95 % of them runs, 1.15x, the bunny's (38 %) 1.07x, kernel on one
 * thread. */
#define STORE_CHUNKV(x, y, z, q, r) do {                                            \
    const int r0_ = (r)[0];                                                         \
    if (r0_ < 0)                                                                    \
        STORE_XYZV(x, y, z, (q) + 3 * (size_t)~r0_);                                 \
    else                                                                            \
        STORE_ROWSV(x, y, z, q, LOADIV(0, r));                                      \
} while (0)
#define LOADIV(g, p) (*(__global const intv *)((p) + VW * (g)))
#define ABSV(x) as_floatv(as_intv(x) & (intv)0x7fffffff)      /* |x| (clears the sign bits) */
#define SAMEV(h) (orv((h) ^ (intv)(h).s0) == 0)              /* the lanes hold one value */

