/* Linear blend skinning (LBS) and dual quaternion skinning (DQS).
 *
 * Layout (structure of arrays in groups of 8 vertices, one vertex per
 * float8 lane):
 *
 *   rest    (G, 3, 8) float : group g holds x[8], y[8], z[8] of vertices 8g..8g+7
 *   joints  (G, K, 8) int   : influence k of the 8 vertices of group g
 *   weights (G, K, 8) float : matching weights; rows sum to 1; within a vertex
 *                             the influences are sorted by decreasing weight
 *                             (so k = 0 is the dominant joint) and padding has
 *                             weight 0 and joint 0. Padding vertices (beyond N)
 *                             have weight 1 on joint 0.
 *   rows    (G, 8) int      : output row of each stored vertex. Vertices are stored
 *                             sorted by their joints (influence 0, then 1, ...;
 *                             nrpose/pose/skinning.py), so that the 8 lanes of a group
 *                             nearly always share influence k's joint: then its
 *                             parameters are read once for the 8 (broadcast loads)
 *                             instead of gathered lane by lane (12 or 8 gathers
 *                             per influence were most of the kernel's time).
 *                             Run-coded (lanes.h STORE_CHUNKV): a group of
 *                             consecutive rows has its first bound as ~row.
 *   out     (F, 8G, 3) float: posed vertices as rows (array of structures) in the
 *           caller's order, one slab per frame, padding vertices last.
 *
 * Per pose:
 *   lbs: mats (F, J, 12) float: rows 0..2 of M_j = G_j @ IBM_j, row-major
 *        (m00 m01 m02 m03 m10 ... m23); x' = M x for column vectors.
 *   dqs: dq   (F, J, 8) float: unit dual quaternion (qr.xyzw, qd.xyzw) per
 *        joint, scalar last, qd = 0.5 (t, 0) qr.
 *
 * Launch (nrpose/device/launch.py launch_shared): any number of work-items, local
 * size 1, on PoCL's worker threads and the calling thread at once. Each takes
 * the next block of `block` groups of the job published in `jobs` (share.h:
 * ceil(G / block) blocks, F frames) until none are left, and poses every group
 * of its block for the F frames, frames innermost: a group's bound data (rest,
 * joints, weights) is read from memory once and reused from L1 for every frame.
 * Which work-item takes a block does not change its result.
 *
 * Because influences are sorted by decreasing weight, once every lane of a
 * group has weight 0 at influence k all later influences are 0 too: the loop
 * stops there.
 *
 * Per the PoCL notes: no fma()/mad() builtins, explicit float8 lanes; no
 * out-of-line builtins in loops (kernels/lanes.h).
 *
 * A program holds the one kernel its deformer launches: built with -DLBS_KERNEL or
 * -DDQS_KERNEL (nrpose/pose/skinning.py PROGRAMS), since PoCL compiles every kernel of a
 * program for each device at its build.
 */
#if !defined(LBS_KERNEL) && !defined(DQS_KERNEL)
#error "build with -DLBS_KERNEL or -DDQS_KERNEL"
#endif

#include "lanes.h"
#include "share.h"

/* lanes.h's 8-lane helpers; SAMEV at its default VW of 8 lanes (no -DVW here) */

/* Parameter c of each lane's joint, the float8 (p[j.s0 + c], ..., p[j.s7 + c]) (p: the
 * per-joint records, j: int8 of record offsets into p): JOINT_BCAST8 when the 8 lanes
 * share the joint (one load, broadcast), JOINT_GATHER8 for any lanes (8 loads). The outer
 * parentheses of JOINT_BCAST8's operand matter: `(float8)(x)[c]` is a vector literal
 * indexed by c. */
#define JOINT_BCAST8(p, j, c) ((float8)(((p) + (j).s0)[c]))
#define JOINT_GATHER8(p, j, c) GATHER8(p, (j) + (c))

/* USE(JOINT_BCAST8) when the 8 lanes of j share the joint (the usual case, vertices being
 * sorted by joint), else USE(JOINT_GATHER8); USE is a macro of statements that read the
 * joint's parameters with the reader it is given. A macro rather than an inline function
 * returning the parameters: expanded in each branch, USE consumes every value where it
 * is read, whereas reading lbs's 12 into an array and accumulating after the branch kept
 * them live across the join, spilled to the stack at every influence. */
#define WITH_JOINT8(j, USE) do { if (SAMEV(j)) { USE(JOINT_BCAST8) } else { USE(JOINT_GATHER8) } } while (0)

#ifdef LBS_KERNEL
__kernel void lbs(__global const float *restrict rest,
                  __global const int *restrict joints,
                  __global const float *restrict weights,
                  __global const int *restrict rows,
                  __global const float *mats,          /* per pose: not restrict, a standing worker sees it change */
                  __global float *out,
                  const int K, const int J, const int G,
                  const int block, volatile __global int *jobs, const int role)
{
    FOR_EACH_ITEM(g, F, jobs, role, block, G) {
    for (int f = 0; f < F; ++f) {
    __global const float *M = mats + (size_t)f * (size_t)J * 12;

    float8 a0 = 0.0f, a1 = 0.0f, a2 = 0.0f, a3 = 0.0f;
    float8 a4 = 0.0f, a5 = 0.0f, a6 = 0.0f, a7 = 0.0f;
    float8 a8 = 0.0f, a9 = 0.0f, a10 = 0.0f, a11 = 0.0f;

    for (int k = 0; k < K; ++k) {
        const size_t o = ((size_t)g * K + k) * 8;
        const float8 w = LOAD8(0, weights + o);
        if (!ANY_NONZERO8(w)) break;
        const int8 j = LOADI8(0, joints + o) * 12;
#define ACCUMULATE(PARAM)                                                            \
        a0 += w * PARAM(M, j, 0); a1 += w * PARAM(M, j, 1); a2  += w * PARAM(M, j, 2);  a3  += w * PARAM(M, j, 3);  \
        a4 += w * PARAM(M, j, 4); a5 += w * PARAM(M, j, 5); a6  += w * PARAM(M, j, 6);  a7  += w * PARAM(M, j, 7);  \
        a8 += w * PARAM(M, j, 8); a9 += w * PARAM(M, j, 9); a10 += w * PARAM(M, j, 10); a11 += w * PARAM(M, j, 11);
        WITH_JOINT8(j, ACCUMULATE);
#undef ACCUMULATE
    }

    __global const float *p = rest + (size_t)g * 24;
    const float8 x = LOAD8(0, p), y = LOAD8(1, p), z = LOAD8(2, p);
    __global float *q = out + (size_t)f * G * 24;
    const float8 ox = a0 * x + a1 * y + a2  * z + a3;
    const float8 oy = a4 * x + a5 * y + a6  * z + a7;
    const float8 oz = a8 * x + a9 * y + a10 * z + a11;
    STORE_CHUNKV(ox, oy, oz, q, rows + (size_t)g * 8);
    }   /* f */
    }   /* g */
}
#endif

#ifdef DQS_KERNEL
__kernel void dqs(__global const float *restrict rest,
                  __global const int *restrict joints,
                  __global const float *restrict weights,
                  __global const int *restrict rows,
                  __global const float *dq,            /* per pose, likewise */
                  __global float *out,
                  const int K, const int J, const int G,
                  const int block, volatile __global int *jobs, const int role)
{
    FOR_EACH_ITEM(g, F, jobs, role, block, G) {
    /* dominant joint (influence 0) of each lane, for the hemisphere test */
    const int8 j0 = LOADI8(0, joints + (size_t)g * K * 8) * 8;
    for (int f = 0; f < F; ++f) {
    __global const float *D = dq + (size_t)f * (size_t)J * 8;

    /* Dominant joint's rotation quaternion for the hemisphere test. */
    float8 px, py, pz, pw;
#define READ_ROTATION(PARAM) px = PARAM(D, j0, 0); py = PARAM(D, j0, 1); pz = PARAM(D, j0, 2); pw = PARAM(D, j0, 3);
    WITH_JOINT8(j0, READ_ROTATION);
#undef READ_ROTATION

    float8 rx = 0.0f, ry = 0.0f, rz = 0.0f, rw = 0.0f;
    float8 dx = 0.0f, dy = 0.0f, dz = 0.0f, dw = 0.0f;

    for (int k = 0; k < K; ++k) {
        const size_t o = ((size_t)g * K + k) * 8;
        const float8 w = LOAD8(0, weights + o);
        if (!ANY_NONZERO8(w)) break;
        const int8 j = LOADI8(0, joints + o) * 8;
        float8 qx, qy, qz, qw, ex, ey, ez, ew;
#define READ_DQ(PARAM)                                                                           \
        qx = PARAM(D, j, 0); qy = PARAM(D, j, 1); qz = PARAM(D, j, 2); qw = PARAM(D, j, 3); \
        ex = PARAM(D, j, 4); ey = PARAM(D, j, 5); ez = PARAM(D, j, 6); ew = PARAM(D, j, 7);
        WITH_JOINT8(j, READ_DQ);
#undef READ_DQ
        const float8 dot = qx * px + qy * py + qz * pz + qw * pw;
        const float8 s = dot < 0.0f ? -w : w;   /* antipodality */
        rx += s * qx; ry += s * qy; rz += s * qz; rw += s * qw;
        dx += s * ex; dy += s * ey; dz += s * ez; dw += s * ew;
    }

    /* Normalise by the blended real part's norm. */
    const float8 inv = rsqrt8(rx * rx + ry * ry + rz * rz + rw * rw);
    rx *= inv; ry *= inv; rz *= inv; rw *= inv;
    dx *= inv; dy *= inv; dz *= inv; dw *= inv;

    __global const float *p = rest + (size_t)g * 24;
    const float8 x = LOAD8(0, p), y = LOAD8(1, p), z = LOAD8(2, p);

    /* x' = x + 2 r × (r × x + w x) + 2 (w d - dw r + r × d) */
    const float8 cx = ry * z - rz * y + rw * x;
    const float8 cy = rz * x - rx * z + rw * y;
    const float8 cz = rx * y - ry * x + rw * z;
    const float8 tx = rw * dx - dw * rx + (ry * dz - rz * dy);
    const float8 ty = rw * dy - dw * ry + (rz * dx - rx * dz);
    const float8 tz = rw * dz - dw * rz + (rx * dy - ry * dx);

    __global float *q = out + (size_t)f * G * 24;
    const float8 ox = x + 2.0f * ((ry * cz - rz * cy) + tx);
    const float8 oy = y + 2.0f * ((rz * cx - rx * cz) + ty);
    const float8 oz = z + 2.0f * ((rx * cy - ry * cx) + tz);
    STORE_CHUNKV(ox, oy, oz, q, rows + (size_t)g * 8);
    }   /* f */
    }   /* g */
}
#endif
