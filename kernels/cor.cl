/* Skinning with optimized centers of rotation (CoR; Le & Hodgins 2016).
 * Float64 reference: nrpose/pose/cor.py (cor_reference); bound by nrpose/pose/skinning.py
 * Skinner (method "cor"), arguments as skinning.cl's (jobs and role last: nrpose/device).
 *
 * Layout as kernels/skinning.cl (structure of arrays in groups of 8 vertices, one
 * vertex per float8 lane; influences sorted by decreasing weight, padding weight 0;
 * vertices stored sorted by their joints, `rows` run-coded, lanes.h STORE_CHUNKV):
 *
 *   rest    (G, 6, 8) float : rows 0..2 v − c, the vertex relative to its center of rotation,
 *                             rows 3..5 c, the center of rotation (computed at bind,
 *                             nrpose/pose/cor.py)
 *   joints  (G, K, 8) int, weights (G, K, 8) float, rows (G, 8) int: as skinning.cl
 *   out     (F, 8G, 3) float: posed vertices as rows, one slab per frame
 *
 * Per pose: params (F, J, 16) float: rows 0..2 of M_j = G_j @ IBM_j row-major (12), then
 * the unit quaternion (x, y, z, w) of M_j's rotation (its polar factor; the host converts,
 * as for DQS).
 *
 * Per vertex: A = Σ w_k M_jk (the LBS matrix), q = Σ s_k w_k Q_jk with s_k putting Q_jk
 * in the hemisphere of the dominant joint's Q (influence 0), R = R(q / |q|), and
 *     v' = R (v − c) + A c.
 * Launch: as skinning.cl (share.h FOR_EACH_ITEM; bound data read once per group for all
 * frames of a job). Same PoCL notes: no fma()/mad() builtins, explicit float8 lanes.
 */

#include "lanes.h"
#include "share.h"

#define JOINT_BCAST8(p, j, c) ((float8)(((p) + (j).s0)[c]))
#define JOINT_GATHER8(p, j, c) GATHER8(p, (j) + (c))
#define WITH_JOINT8(j, USE) do { if (SAMEV(j)) { USE(JOINT_BCAST8) } else { USE(JOINT_GATHER8) } } while (0)

#define COR_PARAMS 16

__kernel void cor(__global const float *restrict rest,
                  __global const int *restrict joints,
                  __global const float *restrict weights,
                  __global const int *restrict rows,
                  __global const float *params,        /* per pose: not restrict, a standing worker sees it change */
                  __global float *out,
                  const int K, const int J, const int G,
                  const int block, volatile __global int *jobs, const int role)
{
    FOR_EACH_ITEM(g, F, jobs, role, block, G) {
    const int8 j0 = LOADI8(0, joints + (size_t)g * K * 8) * COR_PARAMS;
    for (int f = 0; f < F; ++f) {
    __global const float *P = params + (size_t)f * (size_t)J * COR_PARAMS;

    float8 px, py, pz, pw;              /* dominant joint's quaternion: the hemisphere */
#define READ_ROTATION(PARAM) px = PARAM(P, j0, 12); py = PARAM(P, j0, 13); pz = PARAM(P, j0, 14); pw = PARAM(P, j0, 15);
    WITH_JOINT8(j0, READ_ROTATION);
#undef READ_ROTATION

    float8 a0 = 0.0f, a1 = 0.0f, a2 = 0.0f, a3 = 0.0f;
    float8 a4 = 0.0f, a5 = 0.0f, a6 = 0.0f, a7 = 0.0f;
    float8 a8 = 0.0f, a9 = 0.0f, a10 = 0.0f, a11 = 0.0f;
    float8 rx = 0.0f, ry = 0.0f, rz = 0.0f, rw = 0.0f;

    for (int k = 0; k < K; ++k) {
        const size_t o = ((size_t)g * K + k) * 8;
        const float8 w = LOAD8(0, weights + o);
        if (!ANY_NONZERO8(w)) break;
        const int8 j = LOADI8(0, joints + o) * COR_PARAMS;
        float8 qx, qy, qz, qw;
#define ACCUMULATE(PARAM)                                                                              \
        a0 += w * PARAM(P, j, 0); a1 += w * PARAM(P, j, 1); a2  += w * PARAM(P, j, 2);  a3  += w * PARAM(P, j, 3);  \
        a4 += w * PARAM(P, j, 4); a5 += w * PARAM(P, j, 5); a6  += w * PARAM(P, j, 6);  a7  += w * PARAM(P, j, 7);  \
        a8 += w * PARAM(P, j, 8); a9 += w * PARAM(P, j, 9); a10 += w * PARAM(P, j, 10); a11 += w * PARAM(P, j, 11); \
        qx = PARAM(P, j, 12); qy = PARAM(P, j, 13); qz = PARAM(P, j, 14); qw = PARAM(P, j, 15);
        WITH_JOINT8(j, ACCUMULATE);
#undef ACCUMULATE
        const float8 dot = qx * px + qy * py + qz * pz + qw * pw;
        const float8 s = dot < 0.0f ? -w : w;   /* antipodality */
        rx += s * qx; ry += s * qy; rz += s * qz; rw += s * qw;
    }
    const float8 inv = rsqrt8(rx * rx + ry * ry + rz * rz + rw * rw);
    rx *= inv; ry *= inv; rz *= inv; rw *= inv;

    __global const float *pd = rest + (size_t)g * 48;
    __global const float *pc = pd + 24;
    const float8 dx = LOAD8(0, pd), dy = LOAD8(1, pd), dz = LOAD8(2, pd);
    const float8 cx = LOAD8(0, pc), cy = LOAD8(1, pc), cz = LOAD8(2, pc);

    /* R d = d + 2 r × (r × d + w d) */
    const float8 ux = ry * dz - rz * dy + rw * dx;
    const float8 uy = rz * dx - rx * dz + rw * dy;
    const float8 uz = rx * dy - ry * dx + rw * dz;
    __global float *q = out + (size_t)f * G * 24;
    const float8 ox = dx + 2.0f * (ry * uz - rz * uy) + (a0 * cx + a1 * cy + a2  * cz + a3);
    const float8 oy = dy + 2.0f * (rz * ux - rx * uz) + (a4 * cx + a5 * cy + a6  * cz + a7);
    const float8 oz = dz + 2.0f * (rx * uy - ry * ux) + (a8 * cx + a9 * cy + a10 * cz + a11);
    STORE_CHUNKV(ox, oy, oz, q, rows + (size_t)g * 8);
    }   /* f */
    }   /* g */
}
