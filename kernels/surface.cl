/* Neighbourhood rotations of a posed surface: the rotation that carries a file's own normals
 * (and tangents) onto each welded position of a posed frame. Float64 reference:
 * nrpose/model/normals.py Surface.rotations; bound by nrpose/pose/surface_rotations.py.
 *
 * Per welded position (group): M = sum over the faces around it (a face once per corner of it
 * in the group) of b^T B, b and B the face's posed and bind edge frames (4 x 3: e1, e2, e2 - e1
 * and the normal scaled to |n|^2 = 2 area), then the polar factor of M by the scaled Newton
 * iteration X <- (g X + X^-T / g) / 2, g = det(X)^(-1/3), from M scaled to largest entry 1, as
 * the reference's closest_rotations.
 *
 * Layout: groups in chunks of 8, one per float8 lane (the host sorts them by face count, so a
 * chunk's lanes have about as many faces; a lane with fewer reads the padding face):
 *   starts  (C + 1,) int     : chunk c's face slots are slots[starts[c] .. starts[c + 1])
 *   slots   (S, 8) int       : per slot, the face of each lane; padding: face M
 *   faces   (M + 1, 3) int   : vertex indices of each triangle; row M: 0 0 0
 *   bind    (M + 1, 12) float: each face's bind edge frame, row-major (4 x 3); row M: zeros
 *   rows    (C, 8) int       : the output row (group) of each lane; padding lanes: G
 *   posed   (F, N, 3) float  : the frames' vertex positions, frame f at posed + f * stride
 *   out     (F, G + 1, 10) float: per group R row-major, then a status: 1 where R is the
 *                             converged polar factor (or the identity: no face, a zero sum),
 *                             0 where the host finishes the group (the nine are then M scaled
 *                             to largest entry 1; det <= DET_MIN or no convergence: the
 *                             reference takes the SVD there)
 * Launch: share.h FOR_EACH_ITEM over chunks, blocks of `block` chunks, frames innermost.
 * Per the PoCL notes: explicit float8 lanes, no out-of-line builtins (sqrt, cbrt, fabs, fmax,
 * select are calls on PoCL): bit operations and Newton steps instead.
 */

#include "lanes.h"
#include "share.h"

#define NEWTON_STEPS 30
#define NEWTON_TOL2 1.6e-11f      /* squared Frobenius norm of the last step: (4e-6)^2 */
#define DET_MIN 1e-5f

#define ABS8(x) as_float8(as_int8(x) & (int8)0x7fffffff)
/* a where m (an int8 of 0 / -1 lanes, as a comparison gives), else b */
#define PICK8(m, a, b) as_float8((as_int8(a) & (m)) | (as_int8(b) & ~(m)))
#define MAX8(a, b) PICK8((a) > (b), (a), (b))
#define IGATHER8(p, i) ((int8)((p)[(i).s0], (p)[(i).s1], (p)[(i).s2], (p)[(i).s3], \
                               (p)[(i).s4], (p)[(i).s5], (p)[(i).s6], (p)[(i).s7]))

/* x^(-1/2) per lane for x >= 0, to float precision (x = 0: a large finite number) */
static inline float8 inv_sqrt8(const float8 x)
{
    float8 y = as_float8((int8)0x5f375a86 - (as_int8(x) >> 1));
    y = y * (1.5f - 0.5f * x * y * y);
    y = y * (1.5f - 0.5f * x * y * y);
    return y * (1.5f - 0.5f * x * y * y);
}

/* x^(-1/3) per lane for x > 0, to float precision */
static inline float8 inv_cbrt8(const float8 x)
{
    float8 y = as_float8((int8)0x54a2fa8c - as_int8(x) / 3);
    y = y * (4.0f - x * y * y * y) * (1.0f / 3.0f);
    y = y * (4.0f - x * y * y * y) * (1.0f / 3.0f);
    y = y * (4.0f - x * y * y * y) * (1.0f / 3.0f);
    return y * (4.0f - x * y * y * y) * (1.0f / 3.0f);
}

__kernel void surface_rotations(__global const int *restrict starts,
                                __global const int *restrict slots,
                                __global const int *restrict faces,
                                __global const float *restrict bind,
                                __global const int *restrict rows,
                                __global const float *posed,   /* per frame: not restrict, a standing worker sees it change */
                                __global float *out,
                                const int stride, const int G, const int C,
                                const int block, volatile __global int *jobs, const int role)
{
    FOR_EACH_ITEM(c, F, jobs, role, block, C) {
    const int8 row = LOADI8(0, rows + 8 * (size_t)c);
    for (int f = 0; f < F; ++f) {
        __global const float *P = posed + (size_t)f * (size_t)stride;
        float8 m0 = 0.0f, m1 = 0.0f, m2 = 0.0f, m3 = 0.0f, m4 = 0.0f, m5 = 0.0f, m6 = 0.0f, m7 = 0.0f, m8 = 0.0f;
        for (int s = starts[c]; s < starts[c + 1]; ++s) {
            const int8 face = LOADI8(0, slots + 8 * (size_t)s);
            const int8 t = face * 3;
            const int8 i0 = IGATHER8(faces, t) * 3, i1 = IGATHER8(faces, t + 1) * 3, i2 = IGATHER8(faces, t + 2) * 3;
            const float8 px = GATHER8(P, i0), py = GATHER8(P, i0 + 1), pz = GATHER8(P, i0 + 2);
            const float8 ax = GATHER8(P, i1) - px, ay = GATHER8(P, i1 + 1) - py, az = GATHER8(P, i1 + 2) - pz;
            const float8 bx = GATHER8(P, i2) - px, by = GATHER8(P, i2 + 1) - py, bz = GATHER8(P, i2 + 2) - pz;
            const float8 cx = bx - ax, cy = by - ay, cz = bz - az;
            float8 nx = ay * bz - az * by, ny = az * bx - ax * bz, nz = ax * by - ay * bx;
            const float8 len2 = nx * nx + ny * ny + nz * nz;
            const float8 k = inv_sqrt8(len2 * inv_sqrt8(len2));   /* |n|^(-1/2): |n k|^2 = |n| = 2 area */
            nx *= k; ny *= k; nz *= k;
            const int8 o = face * 12;
            /* M[r][q] += a[r] B[0][q] + b[r] B[1][q] + c[r] B[2][q] + n[r] B[3][q] */
#define COLUMN(q, M0, M1, M2) do {                                                      \
            const float8 B0 = GATHER8(bind, o + (q)), B1 = GATHER8(bind, o + 3 + (q));       \
            const float8 B2 = GATHER8(bind, o + 6 + (q)), B3 = GATHER8(bind, o + 9 + (q));   \
            M0 += ax * B0 + bx * B1 + cx * B2 + nx * B3;                                      \
            M1 += ay * B0 + by * B1 + cy * B2 + ny * B3;                                      \
            M2 += az * B0 + bz * B1 + cz * B2 + nz * B3;                                      \
        } while (0)
            COLUMN(0, m0, m3, m6);
            COLUMN(1, m1, m4, m7);
            COLUMN(2, m2, m5, m8);
#undef COLUMN
        }
        const float8 big = MAX8(MAX8(MAX8(ABS8(m0), ABS8(m1)), MAX8(ABS8(m2), ABS8(m3))),
                                MAX8(MAX8(ABS8(m4), ABS8(m5)), MAX8(MAX8(ABS8(m6), ABS8(m7)), ABS8(m8))));
        const int8 zero = !(big > FLT_MIN);          /* no face, or a zero sum: the identity */
        const float8 inv = 1.0f / PICK8(zero, (float8)1.0f, big);
        m0 *= inv; m1 *= inv; m2 *= inv; m3 *= inv; m4 *= inv; m5 *= inv; m6 *= inv; m7 *= inv; m8 *= inv;
        float8 x0 = m0, x1 = m1, x2 = m2, x3 = m3, x4 = m4, x5 = m5, x6 = m6, x7 = m7, x8 = m8;
        int8 ok = (int8)0, settled = zero;   /* ok: converged; settled: converged, identity or failed */
        for (int it = 0; it < NEWTON_STEPS && or8(~settled) != 0; ++it) {
            const float8 c0 = x4 * x8 - x5 * x7, c1 = x5 * x6 - x3 * x8, c2 = x3 * x7 - x4 * x6;
            const float8 c3 = x2 * x7 - x1 * x8, c4 = x0 * x8 - x2 * x6, c5 = x1 * x6 - x0 * x7;
            const float8 c6 = x1 * x5 - x2 * x4, c7 = x2 * x3 - x0 * x5, c8 = x0 * x4 - x1 * x3;
            const float8 det = x0 * c0 + x1 * c1 + x2 * c2;
            if (it == 0)
                settled |= !(det > DET_MIN);         /* folded or flat: left to the host */
            const float8 d = PICK8(det > 0.0f, det, (float8)1.0f);
            const float8 g = inv_cbrt8(d), h = 1.0f / (d * g);
            const float8 y0 = 0.5f * (g * x0 + h * c0), y1 = 0.5f * (g * x1 + h * c1), y2 = 0.5f * (g * x2 + h * c2);
            const float8 y3 = 0.5f * (g * x3 + h * c3), y4 = 0.5f * (g * x4 + h * c4), y5 = 0.5f * (g * x5 + h * c5);
            const float8 y6 = 0.5f * (g * x6 + h * c6), y7 = 0.5f * (g * x7 + h * c7), y8 = 0.5f * (g * x8 + h * c8);
            const float8 d0 = y0 - x0, d1 = y1 - x1, d2 = y2 - x2, d3 = y3 - x3, d4 = y4 - x4;
            const float8 d5 = y5 - x5, d6 = y6 - x6, d7 = y7 - x7, d8 = y8 - x8;
            const float8 step2 = d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3 + d4 * d4 + d5 * d5 + d6 * d6 + d7 * d7 + d8 * d8;
            const int8 moving = ~settled;            /* a settled lane keeps its matrix */
            x0 = PICK8(moving, y0, x0); x1 = PICK8(moving, y1, x1); x2 = PICK8(moving, y2, x2);
            x3 = PICK8(moving, y3, x3); x4 = PICK8(moving, y4, x4); x5 = PICK8(moving, y5, x5);
            x6 = PICK8(moving, y6, x6); x7 = PICK8(moving, y7, x7); x8 = PICK8(moving, y8, x8);
            const int8 now = moving & (step2 < NEWTON_TOL2);
            ok |= now;
            settled |= now;
        }
        /* identity lanes: I; converged: X; the rest: M for the host */
        const float8 one = 1.0f, nil = 0.0f;
        const float8 r0 = PICK8(zero, one, PICK8(ok, x0, m0)), r1 = PICK8(zero, nil, PICK8(ok, x1, m1));
        const float8 r2 = PICK8(zero, nil, PICK8(ok, x2, m2)), r3 = PICK8(zero, nil, PICK8(ok, x3, m3));
        const float8 r4 = PICK8(zero, one, PICK8(ok, x4, m4)), r5 = PICK8(zero, nil, PICK8(ok, x5, m5));
        const float8 r6 = PICK8(zero, nil, PICK8(ok, x6, m6)), r7 = PICK8(zero, nil, PICK8(ok, x7, m7));
        const float8 r8 = PICK8(zero, one, PICK8(ok, x8, m8)), st = PICK8(zero | ok, one, nil);
        __global float *q = out + (size_t)f * (size_t)(G + 1) * 10;
#define STORE_LANE(l) do {                                                                   \
        __global float *o_ = q + 10 * (size_t)row.s##l;                                           \
        o_[0] = r0.s##l; o_[1] = r1.s##l; o_[2] = r2.s##l; o_[3] = r3.s##l; o_[4] = r4.s##l;      \
        o_[5] = r5.s##l; o_[6] = r6.s##l; o_[7] = r7.s##l; o_[8] = r8.s##l; o_[9] = st.s##l;      \
    } while (0)
        STORE_LANE(0); STORE_LANE(1); STORE_LANE(2); STORE_LANE(3);
        STORE_LANE(4); STORE_LANE(5); STORE_LANE(6); STORE_LANE(7);
#undef STORE_LANE
    }   /* f */
    }   /* c */
}
