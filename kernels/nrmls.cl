/* Near-rigid MLS pose kernel (Jeong & Kim): the tree-signed quaternion blend (built with
 * -DQUAT_BLEND; nrpose's default), the relative-rotation blend or the paper's blend.
 *
 * Reference: nrpose/pose/blend.py (pose_reference), float64. Everything that
 * depends only on the rest configuration is bound once (see nrpose/pose/mls.py);
 * a pose uploads one small float buffer of per-handle data.
 *
 * Each work-item poses a chunk of VW consecutive points (-DVW: 8, or 16 on rigs
 * without segments, nrpose/pose/mls.py lanes_for) with vector lanes (floatv,
 * kernels/lanes.h): on PoCL CPU explicit vectors were worth ~4x over scalar
 * work-items (shared/notes/pocl.md), and at 16 lanes each operation is two
 * independent 8-lane instructions, which keeps the FMA pipes busier through the
 * point-handle chains (the Table-1 point rows 1.00-1.17x in one process, two runs).
 * On rigs of segments only, two consecutive chunks of one reference are posed together
 * (pose_pair), so that the per-pose values of the slot loop are loaded once for both.
 * No fma()/mad() builtins: they are ~10x slower than a*b+c on PoCL.
 * -DBATCHES_ONLY leaves out the single-pose path (a job of one frame takes the batch path,
 * bitwise the same): whole-job processes, which pose clips in batches, compile ~0.15 s less.
 *
 * Bound data is stored chunk-major: chunk g (points VW g .. VW g + VW-1 of the
 * stored order) has one float record and one int record, each a list of rows of VW
 * lanes, so a work-item streams through two contiguous regions of memory
 * (with SoA rows of all N points, 20-40 rows 4 MB apart each cost a
 * prefetch stream and a TLB entry: 1M points x 8 slots posed ~2x slower).
 * Np = number of points padded to a multiple of VW.
 *   float record, FREC(P, K) floats, rows:
 *   u      [3]            v - p*
 *   coef   [P+2K]         q* coefficients: point handles (w), then per segment slot
 *                         (w, w t): w on the segment's posed start a, w t on its posed
 *                         direction b - a (segv, below), so that w is also the slot's
 *                         lever coefficient
 *   phat   [3P]           p_i - p* of the point handles (x, y, z rows per handle), times
 *                         2^-e, e the binary exponent of the largest |component| over all
 *                         points (nrpose/pose/mls.py device_layout): exact, and the blend
 *                         does not change (the rotations depend on phat's direction only;
 *                         the derived levers w |phat|^2 and len2 scale alike and are
 *                         normalised per point), but |phat x y|^2 stays a normal float
 *   lever  [P+K]          normalised levers (points, then segment slots), or, built with
 *                         -DDERIVED_LEVER (lever rules "weight" and "length" on rigs with
 *                         segments: nrpose/pose/mls.py levers_stored), instead
 *   inv    [1]            1 / the point's lever sum, sum_p w_p |phat_p|^2 + sum_k w_k len2[s_k]
 *                         (rest-only): the kernel derives the point levers w_p |phat_p|^2,
 *                         and the segment levers w_k len2[s] are folded into the per-pose
 *                         table (table' below), so that a slot costs no lever arithmetic
 *                         (the armadillo's 13 segment slots: 1.10x, kernel on one thread)
 *   int record, IREC(K) ints, rows:
 *   ref    [1]            reference rotation index: segment s, or S for global;
 *                         points are stored sorted by ref (stable), so the VW lanes
 *                         of a work-item nearly always share it (scalar loads
 *                         instead of gathers)
 *   row    [1]            output row of each stored point (undoes the sort), run-coded:
 *                         a chunk of consecutive rows has its first bound as ~row
 *                         (lanes.h STORE_CHUNKV)
 *   slot   [K]            (sparse only, K < S) segment held by each slot
 *   K                     segment slots per point: S (dense) or k < S (sparse:
 *                         the k most influential segments of each point)
 *   len2   [S]            per-segment lever factor: L^2 ("weight") or the squared
 *                         rest length ("length"), see nrpose/pose/blend.py; times 2^-2e, e as
 *                         for phat (without point handles, the longest lever's exponent;
 *                         at most 2^50 / the longest lever: nrpose/pose/mls.py device_layout)
 * Per-pose data, F frames of a launch in `frames`, frame f at f frame_stride floats: its
 * pose block (pose_stride floats, written by the host), then its derived block:
 *   pose   qpos [(P+2S)*3] | rots [(S+1)*9] | slot [1]: posed handle positions, the
 *          rotations of the segments and the global rotation R_g, row-major, and
 *          the output slot of the frame (int bits): slot s >= 0 is written at out + s Np*3,
 *          slot code s < 0 at handed + (-1 - s) Np*3
 *   derived (written by the job's prologue from the pose block, once per pose: pose_prologue)
 *          refs [(S+1)*9] row-major | quats [(S+1)*4] | ploc [(S+1)*P*3] | segv [S*6]
 *          | table [(S+1)*S*TW]:
 *          refs[j], the matrix of reference j (segment j, or R_g for j = S; identity for
 *          the paper blend); quats[j] = Q_j, the unit quaternion (x, y, z, w) of rotation j;
 *          ploc[j][p] = R_ref_j^T q_p, the posed point handles in reference j's
 *          frame (when P > 0; the pose kernel reads it where a chunk's
 *          lanes share their reference);
 *          segv[s]: segment s's posed start a_s (x, y, z) and direction b_s - a_s;
 *          table[j][s]: relative/paper blends, TW = 3: log(R_j^-1 R_s) (paper: log R_s), on
 *          rigs of segments only (P = 0) turned into the world frame, R_j log(R_j^-1 R_s) =
 *          log(R_s R_j^-1) (the pose then needs no R_ref product after the rotation);
 *          QUAT_BLEND, TW = 4: Q_s signed by the sign tree (j < S), in the hemisphere of Q_g (j = S); table' (-DDERIVED_LEVER):
 *          each entry times len2[s].
 *          (Each value as a row of VW equal floats, so that the slot loop's multiply-adds
 *          took vector memory operands instead of broadcast loads, made single poses
 *          1.02-1.07x faster on one thread, but batched dense poses 1.5-2x slower: a
 *          launch's frames then read 8 times the per-frame data per chunk, more than L1.)
 *   out    [F][Np*3]      posed points, xyz interleaved, in the caller's order; each
 *                         frame in the slot its pose block names (nrpose/pose/mls.py)
 *   handed [2][Np*3]      the same, slots whose frames are handed to the caller without
 *                         a copy (nrpose.device.Handoff)
 *
 * The rest-only arrays (the records above, len2, the prologue's pairs and the R_g fit's
 * data) and the deformer's constants are one `bound` block (BOUND_*, below), and each
 * frame's pose and derived blocks are one, so that the kernel takes six arguments: PoCL's
 * enqueue costs ~0.1 us per argument (~0.15 a buffer), paid by the calling thread before
 * it joins a standing worker (eighteen arguments, ten of them arrays, had cost ~1-1.5 us
 * more than six, five of them arrays).
 *
 * A launch poses F frames. It is one job (share.h) whose prologue, run by the first
 * work-item to arrive, fits R_g (-DGLOBAL_FIT) and fills the derived block of every
 * frame; then the blocks of points.
 * (As kernels of their own, enqueued before this one, the R_g fit and the
 * tables cost a box's point pose 14 us of its 84 (1.21x), its segment pose 5 of
 * 47 us; a standing worker now runs them while the calling thread enters.)
 */

#include "lanes.h"
#include "share.h"
#ifdef GLOBAL_FIT
#include "global_fit.h"
#endif

/* Handle counts known at build time (nrpose/pose/mls.py builds one program per
 * configuration): P point handles (-DNPOINTS) and K segment slots per point
 * (-DNSLOTS). Dense (K = S) the segment count is K too and the slot loop unrolls;
 * sparse (-DSPARSE, K < S, skeletons with top-k weights) S stays a kernel
 * argument, so that every skeleton with the same k shares one program, and the
 * slot loop is not unrolled (that tripled the ~1.2 s build of a k = 8 program
 * and was no faster). Against P, S, K as arguments (kernel events, interleaved in
 * one process): dense segment rows -19 to -27 %, point rows -16 to -18 %.
 * Loops longer than UNROLL_MAX are left to the compiler. */
#ifndef NPOINTS
#error "build with -DNPOINTS=<point handles> -DNSLOTS=<segment slots per point> (nrpose/pose/mls.py)"
#endif
#define P NPOINTS
#define K NSLOTS
#ifdef SPARSE
#define S nsegs      /* the kernels' argument */
#else
#define S K
#endif
/* 16 handles at 8 lanes, 8 at 16 lanes: the armadillo's 13 point handles unrolled at 16
 * lanes (2,500 instructions, a third of them spill traffic) posed 1.18x slower than
 * the loop (bench/kernel_ab.py, one thread) */
#define UNROLL_MAX (128 / VW)
#if P <= UNROLL_MAX
#define UNROLL_P _Pragma("unroll")
#else
#define UNROLL_P
#endif
#if K <= UNROLL_MAX && !defined(SPARSE)
#define UNROLL_K _Pragma("unroll")
#else
#define UNROLL_K
#endif
/* Dense rigs pose a chunk whose lanes do not share their reference (under 1 % of the
 * Table-1 chunks) by a second slot loop that gathers; above this many slots it is not
 * unrolled, which keeps the body small enough to inline twice (pose_chunk, in the single-pose
 * and the batch loop; finish_chunk is inlined six times where chunks are also paired): the
 * armadillo's 13 slots unrolled there made its segment row 0.95-0.97x as fast, rolled
 * 1.035x; with 4-5 slots rolling it cost 1-2 % */
#define GATHERED_UNROLL_MAX 8
#if !defined(SPARSE) && K > GATHERED_UNROLL_MAX
#define UNROLL_GATHERED _Pragma("nounroll")
#else
#define UNROLL_GATHERED UNROLL_K
#endif

#ifdef QUAT_BLEND
#define TW 4      /* floats per rotation-table entry */
#else
#define TW 3
#endif

/* R_ref, each lane's reference rotation matrix (row-major), into m00..m22 */
#define LOAD_REF() do {                                                                     \
        if (uniform) {                                                                      \
            __global const float *m = refs + 9 * rf.s0;                                     \
            m00 = m[0]; m01 = m[1]; m02 = m[2]; m10 = m[3]; m11 = m[4]; m12 = m[5];         \
            m20 = m[6]; m21 = m[7]; m22 = m[8];                                             \
        } else {                                                                            \
            const intv r9 = rf * 9;                                                         \
            m00 = GATHERV(refs, r9);     m01 = GATHERV(refs, r9 + 1); m02 = GATHERV(refs, r9 + 2); \
            m10 = GATHERV(refs, r9 + 3); m11 = GATHERV(refs, r9 + 4); m12 = GATHERV(refs, r9 + 5); \
            m20 = GATHERV(refs, r9 + 6); m21 = GATHERV(refs, r9 + 7); m22 = GATHERV(refs, r9 + 8); \
        }                                                                                   \
    } while (0)

/* Q_ref, the unit quaternion of each lane's reference rotation (QUAT_BLEND), into gx..gw */
#define LOAD_QREF() do {                                                                    \
        __global const float *qt = refs + QUATS_OFFSET(S);                                  \
        if (uniform) {                                                                      \
            gx = qt[4 * rf.s0]; gy = qt[4 * rf.s0 + 1]; gz = qt[4 * rf.s0 + 2]; gw = qt[4 * rf.s0 + 3]; \
        } else {                                                                            \
            const intv r4 = 4 * rf;                                                         \
            gx = GATHERV(qt, r4); gy = GATHERV(qt, r4 + 1); gz = GATHERV(qt, r4 + 2); gw = GATHERV(qt, r4 + 3); \
        }                                                                                   \
    } while (0)

#ifdef DERIVED_LEVER
#define FREC(P, K) (VW * (3 + 4 * (P) + 2 * (K) + 1))
#else
#define FREC(P, K) (VW * (3 + 5 * (P) + 3 * (K)))
#endif
/* offsets in a frame's derived block (floats; nrpose/pose/mls.py derived_layout) */
#define QUATS_OFFSET(S) (9 * ((S) + 1))
#define PLOC_OFFSET(S) (QUATS_OFFSET(S) + 4 * ((S) + 1))
#define SEGV_OFFSET(S) (PLOC_OFFSET(S) + 3 * P * ((S) + 1))
#define TABLE_OFFSET(S) (SEGV_OFFSET(S) + 6 * (S))
#ifdef SPARSE
#define IREC(K) (VW * (2 + (K)))
#else
#define IREC(K) (2 * VW)
#endif
/* chunk g's float and int records (the header's) */
#define FREC_AT(frec, g) ((frec) + (size_t)(g) * FREC(P, K))
#define IREC_AT(irec, g) ((irec) + (size_t)(g) * IREC(K))

/* The bound block (nrpose/pose/mls.py bound_block): a header of ints, the deformer's constants
 * and the byte offsets of its arrays, each at a multiple of 128 bytes from the block's start:
 *   BOUND_NP          Np, points padded to a multiple of VW
 *   BOUND_NSEGS       S, segments
 *   BOUND_BLOCK       chunks per block of work (share.h)
 *   BOUND_POSE_STRIDE floats of a frame's pose block
 *   BOUND_FRAME_STRIDE floats from one frame's pose block to the next
 *   BOUND_PAPER       1: the paper's blend (no reference rotation), 0: relative
 *   BOUND_NPAIRS      (j, i) pairs of the rotation table (table_block)
 *   BOUND_FREC, BOUND_IREC  the float and int chunk records (the header's records)
 *   BOUND_LEN2        len2 [S] float; BOUND_PAIRS [npairs][2] int
 *   BOUND_FIT         the R_g fit's data (double, global_fit.h; GLOBAL_FIT builds)
 *   BOUND_TREE        the quaternion blend's sign tree [S][2] int: (segment, parent), parents
 *                     first, parent -1 at a root (nrpose/pose/blend.py sign_tree) */
#define BOUND_NP 0
#define BOUND_NSEGS 1
#define BOUND_BLOCK 2
#define BOUND_POSE_STRIDE 3
#define BOUND_FRAME_STRIDE 4
#define BOUND_PAPER 5
#define BOUND_NPAIRS 6
#define BOUND_FREC 7
#define BOUND_IREC 8
#define BOUND_LEN2 9
#define BOUND_PAIRS 10
#define BOUND_FIT 11
#define BOUND_TREE 12
#define BOUND_AT(bound, i, type) ((__global const type *)((bound) + ((__global const int *)(bound))[i]))

/* Unit quaternion (x, y, z, w) of a row-major rotation matrix (Shepperd). */
static float4 quat_of(__global const float *m)
{
    const float tr = m[0] + m[4] + m[8];
    float4 q;
    if (tr > 0.0f) {
        const float s = 2.0f * sqrt(tr + 1.0f);
        q = (float4)((m[7] - m[5]) / s, (m[2] - m[6]) / s, (m[3] - m[1]) / s, 0.25f * s);
    } else if (m[0] > m[4] && m[0] > m[8]) {
        const float s = 2.0f * sqrt(1.0f + m[0] - m[4] - m[8]);
        q = (float4)(0.25f * s, (m[1] + m[3]) / s, (m[2] + m[6]) / s, (m[7] - m[5]) / s);
    } else if (m[4] > m[8]) {
        const float s = 2.0f * sqrt(1.0f + m[4] - m[0] - m[8]);
        q = (float4)((m[1] + m[3]) / s, 0.25f * s, (m[5] + m[7]) / s, (m[2] - m[6]) / s);
    } else {
        const float s = 2.0f * sqrt(1.0f + m[8] - m[0] - m[4]);
        q = (float4)((m[2] + m[6]) / s, (m[5] + m[7]) / s, 0.25f * s, (m[3] - m[1]) / s);
    }
    return normalize(q);
}

/* sqrt(x) for finite x >= 0 (rsqrtv: lanes.h); sqrtv(0) = 0. */
static inline floatv sqrtv(const floatv x)
{
    return x * rsqrtv(x);
}

/* atan2(s, c) / s for s = sqrt(s2), s2 a normal float (>= FLT_MIN), c finite: the angle
 * in [0, pi] between two vectors, divided by the sine part, from |a x b|^2 = s2 and a.b = c,
 * without computing s on the way. atan(a) for a ratio a in [0, 1] is a p(a^2), a p(a^2) an
 * odd polynomial of degree 15 (coefficients fitted minimax on [0, 1], error 7e-8 rad; ~2e-7
 * evaluated in float32), p evaluated by Estrin's scheme (pairs, then t^2, then t^4). With
 * h = max(s2, c^2) and t = min(s2, c^2) / h (the ratio squared):
 *   s2 <= c^2 (within pi/4 of 0 or pi): atan2(s, c) = [c < 0] pi + (s / c) p(t),
 *   s2 >  c^2:                         atan2(s, c) = pi/2 - (c / s) p(t),
 * so atan2(s, c) / s = A / s + B p(t), A = [c < 0] pi or pi/2, B = c / h or -c / h.
 * 1/s (an inverse square root) is then off the chain from s2 to the result, which is
 * one division and the polynomial: the point-handle loop waits on this chain (its ~90
 * cycles a handle were the point rows' bound; atan2 of s = s2 / sqrt(s2), then times
 * 1/s, put the inverse square root and s's multiply before the division). Point rows
 * 1.07-1.16x faster, kernel on one thread (box 1.09-1.12x, dragon 1.09-1.10x, armadillo
 * 1.16x), as many flops; A/s then takes A/2 into the inverse square root's Newton step
 * (rsqrtv_normal_twice, lanes.h), a multiply fewer. */
static inline floatv angle_per_sine(const floatv s2, const floatv c)
{
    const floatv c2 = c * c;
    const intv steep = s2 > c2;
    const floatv ih = 1.0f / (steep ? s2 : c2);
    const floatv t = (steep ? c2 : s2) * ih;
    const floatv b = (steep ? -c : c) * ih;
    const floatv ha = steep ? (floatv)0.785398163f : (c < 0.0f ? (floatv)1.57079633f : (floatv)0.0f);   /* A/2 */
    const floatv t2 = t * t, t4 = t2 * t2;
    const floatv p = ((0.99999934f - 0.33329859f * t) + (0.19946566f - 0.13908629f * t) * t2)
                   + ((0.09642197f - 0.05591232f * t) + (0.02186295f - 0.00405457f * t) * t2) * t4;
    return rsqrtv_normal_twice(s2, ha) + b * p;
}

/* Per-pose data of rotation j in [0, S] (segment j, or R_g for j = S) of one frame
 * (`pose`: its pose block, `refs`: its derived block): refs[j] (identity for the paper
 * blend), quats[j] and ploc[j]; then segv, the posed segments' starts and directions. */
static void rotation_items(const int nsegs, const int paper, __global const float *pose, __global float *refs)
{
    __global const float *rots = pose + 3 * (P + 2 * S);
    for (int j = 0; j <= S; ++j) {
        for (int k = 0; k < 9; ++k)
            refs[9 * j + k] = paper ? (k % 4 == 0 ? 1.0f : 0.0f) : rots[9 * j + k];
        vstore4(quat_of(rots + 9 * j), j, refs + QUATS_OFFSET(S));
        /* ploc[j][p] = R_j^T q_p: the posed point handles in reference j's frame */
        __global float *ploc = refs + PLOC_OFFSET(S) + 3 * P * j;
        for (int p = 0; p < P; ++p)
            for (int k = 0; k < 3; ++k)
                ploc[3 * p + k] = paper ? pose[3 * p + k]
                    : rots[9 * j + k] * pose[3 * p] + rots[9 * j + 3 + k] * pose[3 * p + 1]
                      + rots[9 * j + 6 + k] * pose[3 * p + 2];
    }
    __global float *segv = refs + SEGV_OFFSET(S);
    for (int s = 0; s < S; ++s)
        for (int k = 0; k < 3; ++k) {
            segv[6 * s + k] = pose[3 * (P + 2 * s) + k];
            segv[6 * s + 3 + k] = pose[3 * (P + 2 * s + 1) + k] - pose[3 * (P + 2 * s) + k];
        }
}

/* Rotation-table entries of one frame (`refs`: its derived block, its quats written) for
 * pairs g0 .. g0 + VW-1 of the `npairs` (j, i) pairs that some point uses (listed at
 * bind; lanes past the last pair repeat it), one pair per lane: ~30 times faster than
 * one scalar pair at a time with the library's atan2 (the armadillo's 169 pairs took
 * 21 us of a 0.19 ms pose). Relative blend: table[j][i] = log(R_j^-1 R_i), computed as
 * +-log(Q_a^-1 Q_b) with (a, b) = (min, max)(i, j), so that the logs are exactly
 * antisymmetric, log(R_j^-1 R_i) = -log(R_i^-1 R_j) (table' entries: each times its
 * own len2), and blends seen from either handle agree even at an angle of exactly pi;
 * paper blend log(R_i); QUAT_BLEND, Q_i as signed by the sign tree (tree_signs) for a segment
 * reference j < S, in the hemisphere of Q_j for j = S (R_g). Rigs of segments only
 * (P = 0) keep the relative logs in the world frame (the header's table).
 * DERIVED_LEVER: times len2[i], segment i's lever factor (the header's table'). */
static void table_block(const int g0, const int nsegs, const int paper, const int npairs,
                        __global const int *pairs, __global const float *len2, __global float *refs)
{
    __global float *table = refs + TABLE_OFFSET(S);
    __global const float *quats = refs + QUATS_OFFSET(S);
    float qa[4][VW] __attribute__((aligned(64))), qb[4][VW] __attribute__((aligned(64)));
    float fac[VW] __attribute__((aligned(64)));
    int dst[VW];
    for (int l = 0; l < VW; ++l) {
        const int g = min(g0 + l, npairs - 1);
        const int j = pairs[2 * g], i = pairs[2 * g + 1];
        dst[l] = TW * (j * S + i);
#ifdef QUAT_BLEND
        /* a segment reference: Q_i as signed by the tree (tree_signs; A = B keeps the sign);
         * the global reference R_g: Q_i in its hemisphere */
        const float4 B = vload4(i, quats);
        const float4 A = j < S ? B : vload4(j, quats);
        float f = 1.0f;
#else
        /* paper: Q_a the identity, so that Q_a^-1 Q_b = Q_i */
        const float4 A = paper ? (float4)(0.0f, 0.0f, 0.0f, 1.0f) : vload4(min(i, j), quats);
        const float4 B = vload4(paper ? i : max(i, j), quats);
        float f = paper ? 1.0f : (i == j ? 0.0f : (j < i ? 1.0f : -1.0f));
#endif
#ifdef DERIVED_LEVER
        f *= len2[i];
#endif
        fac[l] = f;
        qa[0][l] = A.x; qa[1][l] = A.y; qa[2][l] = A.z; qa[3][l] = A.w;
        qb[0][l] = B.x; qb[1][l] = B.y; qb[2][l] = B.z; qb[3][l] = B.w;
    }
    const floatv ax = *(const floatv *)qa[0], ay = *(const floatv *)qa[1];
    const floatv az = *(const floatv *)qa[2], aw = *(const floatv *)qa[3];
    const floatv bx = *(const floatv *)qb[0], by = *(const floatv *)qb[1];
    const floatv bz = *(const floatv *)qb[2], bw = *(const floatv *)qb[3];
    const floatv f = *(const floatv *)fac;
    const floatv dot = ax * bx + ay * by + az * bz + aw * bw;
    const floatv sf = dot < 0.0f ? -f : f;
    float out[TW][VW] __attribute__((aligned(64)));
#ifdef QUAT_BLEND
    *(floatv *)out[0] = sf * bx; *(floatv *)out[1] = sf * by;
    *(floatv *)out[2] = sf * bz; *(floatv *)out[3] = sf * bw;
#else
    /* Q_a^-1 Q_b = (aw b - bw a - a x b, a.b); its log: the angle 2 atan2(s, |w|) about
     * the axis (x, y, z) / s (the sign of w taken into sf) */
    const floatv x = aw * bx - bw * ax - (ay * bz - az * by);
    const floatv y = aw * by - bw * ay - (az * bx - ax * bz);
    const floatv z = aw * bz - bw * az - (ax * by - ay * bx);
    const floatv s2 = x * x + y * y + z * z;
    const intv normal = s2 >= 1.17549435e-38f;    /* else a rotation below float resolution */
    const floatv k = sf * (normal ? 2.0f * angle_per_sine(s2, ABSV(dot)) : (floatv)2.0f);
#if P == 0
    /* segments only: into the world frame, table[j][i] = R_j log(R_j^-1 R_i) = log(R_i R_j^-1)
     * (the pose kernel's header), turned by Q_a: R_a v = R_b v for v on the axis of
     * R_a^-1 R_b, so that the entries stay exactly antisymmetric */
    const floatv vx = k * x, vy = k * y, vz = k * z;
    const floatv cx = ay * vz - az * vy, cy = az * vx - ax * vz, cz = ax * vy - ay * vx;
    const floatv dx = ay * cz - az * cy, dy = az * cx - ax * cz, dz = ax * cy - ay * cx;
    *(floatv *)out[0] = vx + 2.0f * (aw * cx + dx);
    *(floatv *)out[1] = vy + 2.0f * (aw * cy + dy);
    *(floatv *)out[2] = vz + 2.0f * (aw * cz + dz);
#else
    *(floatv *)out[0] = k * x; *(floatv *)out[1] = k * y; *(floatv *)out[2] = k * z;
#endif
#endif
    for (int l = 0; l < VW; ++l)
        for (int c = 0; c < TW; ++c)
            table[dst[l] + c] = out[c][l];
}

#ifdef QUAT_BLEND
/* The quaternion blend's signs, once per pose: each segment's Q_s (quats, written by
 * rotation_items) negated where it lies in the opposite hemisphere of its parent's along the
 * bound sign tree (BOUND_TREE, parents first). One sign per segment for every point, so
 * that the lever-weighted sum, and the blend, is continuous wherever the levers are. */
static void tree_signs(const int nsegs, __global const int *tree, __global float *refs)
{
    __global float *quats = refs + QUATS_OFFSET(S);
    for (int m = 0; m < S; ++m) {
        const int s = tree[2 * m], p = tree[2 * m + 1];
        if (p >= 0 && dot(vload4(s, quats), vload4(p, quats)) < 0.0f)
            vstore4(-vload4(s, quats), s, quats);
    }
}
#endif

/* The pose kernel's prologue (share.h), once per job, for its F frames (`frames`): R_g,
 * where some point takes it as its reference (built with -DGLOBAL_FIT: global_fit.h, from
 * the posed handle positions and the bound fit data, written into the frame's pose block),
 * then the frame's rotation data into its derived block (rotation_items, table_block). */
static void pose_prologue(const int F, const int nsegs, const int paper, const int npairs,
                          __global const uchar *bound, __global float *frames, const int pose_stride,
                          const int frame_stride)
{
    __global const int *pairs = BOUND_AT(bound, BOUND_PAIRS, int);
    __global const float *len2 = BOUND_AT(bound, BOUND_LEN2, float);
    for (int f = 0; f < F; ++f) {
        __global float *frame = frames + f * frame_stride;
        __global float *refs = frame + pose_stride;
#ifdef GLOBAL_FIT
        global_rotation_of(frame, BOUND_AT(bound, BOUND_FIT, double), P + 2 * S, 3 * (P + 2 * S) + 9 * S);
#endif
        rotation_items(nsegs, paper, frame, refs);
#ifdef QUAT_BLEND
        tree_signs(nsegs, BOUND_AT(bound, BOUND_TREE, int), refs);
#endif
        for (int g0 = 0; g0 < npairs; g0 += VW)
            table_block(g0, nsegs, paper, npairs, pairs, len2, refs);
    }
}

/* Frame f of a launch: its pose block (`qpos`), its derived block (`refs`) and its output,
 * the slot its pose block names (the header's `out` and `handed`). */
typedef struct {
    __global const float *qpos, *refs;
    __global float *out;
} frame_t;

static inline frame_t frame_at(const int f, __global const float *frames, __global float *out_frames,
                               __global float *handed, const int pose_stride, const int frame_stride,
                               const int np)
{
    frame_t fr;
    fr.qpos = frames + f * frame_stride;
    fr.refs = fr.qpos + pose_stride;
    const int slot = as_int(fr.qpos[pose_stride - 1]);
    fr.out = slot >= 0 ? out_frames + (size_t)slot * 3 * np : handed + (size_t)(-1 - slot) * 3 * np;
    return fr;
}

/* Chunk g's posed points from its sums (pose_chunk, pose_pair): q* (qx, qy, qz) and r (rx, ry,
 * rz; QUAT_BLEND rw, else unused), for the lanes' references rf (`uniform`: all rf.s0): the
 * derived levers' normalisation, the rotation, and the output rows. */
static inline __attribute__((always_inline)) void finish_chunk(const int g, const int nsegs,
                                                               __global const float *frec,
                                                               __global const int *irec, const frame_t fr,
                                                               const intv rf, const int uniform,
                                                               const floatv qx, const floatv qy, const floatv qz,
                                                               floatv rx, floatv ry, floatv rz, floatv rw)
{
    __global const float *u = FREC_AT(frec, g);
    __global const int *ints = IREC_AT(irec, g);
    __global const float *refs = fr.refs;
    __global float *out = fr.out;
#ifdef QUAT_BLEND
    floatv gx, gy, gz, gw;               /* Q_ref, where the quaternion sum is too short */
#else
    floatv m00, m01, m02, m10, m11, m12, m20, m21, m22;   /* R_ref */
#endif
#ifdef DERIVED_LEVER
    /* derived levers are normalised per point here (stored ones already are) */
    const floatv inv = LOADV(3 + 4 * P + 2 * K, u);   /* 1 / the point's lever sum (FREC's last row) */
    rx *= inv;
    ry *= inv;
    rz *= inv;
#ifdef QUAT_BLEND
    rw *= inv;   /* so that the floor below is relative, as in the reference */
#endif
#endif

    const floatv ux = LOADV(0, u), uy = LOADV(1, u), uz = LOADV(2, u);
#ifdef QUAT_BLEND
    /* v' = R(r) u + q*, R(r) the rotation of the quaternion sum r = (rx, ry, rz, rw)
     * (normalised by n2 = |r|^2): u + (2 / n2) (rw (r x u) + r x (r x u)).
     * Where the levers all vanish (|r| <= 1e-6 with levers summing to 1), R = R_ref. */
    const floatv n2 = rx * rx + ry * ry + rz * rz + rw * rw;
    const intv low = n2 <= 1e-12f;
    if (orv(low)) {
        LOAD_QREF();
        rx = low ? gx : rx; ry = low ? gy : ry; rz = low ? gz : rz; rw = low ? gw : rw;
    }
    const floatv s2 = 2.0f / (low ? (floatv)1.0f : n2);
    const floatv kx = ry * uz - rz * uy, ky = rz * ux - rx * uz, kz = rx * uy - ry * ux;
    const floatv jx = ry * kz - rz * ky, jy = rz * kx - rx * kz, jz = rx * ky - ry * kx;
    const floatv ox = ux + s2 * (rw * kx + jx) + qx;
    const floatv oy = uy + s2 * (rw * ky + jy) + qy;
    const floatv oz = uz + s2 * (rw * kz + jz) + qz;
#else
    /* w = exp(r) u for r = 2 h, h the summed half rotation vector (the levers are bound
     * halved: nrpose/pose/mls.py device_layout), by Rodrigues through the half angle
     * t = |h| = th/2: w = u + A (h x u) + B h x (h x u) with A = 2 sin(th)/th = 2 sinc(t) cos(t)
     * and B = 4 (1 - cos th)/th^2 = 2 sinc(t)^2, so A = S C and B = S S for S = sqrt2 sinc(t),
     * C = sqrt2 cos(t). S and C are polynomials in x = t^2 = |h|^2 on [0, (pi/2)^2]
     * (|r| <= pi), degrees 4 and 5: sinc and cos least-squares fitted in a Chebyshev basis,
     * their coefficients times sqrt2; evaluated in float32 their error is 8e-8 and 1.3e-7
     * (relative), as low as the degree-6/8 Taylor polynomials' (float rounding); no sqrt,
     * no division, no transcendental call. The halved vector spares the multiplies of |r|^2
     * by 1/4 and of sinc^2 by 1/2 (box segments 1.04x, box points and bunny segments 1.03x,
     * kernel on one thread). Evaluated by Estrin's scheme (x, x^2, x^4: 4 dependent steps
     * instead of Horner's 5): segment rows 1.02-1.03x (kernel on one thread), where the
     * pose waits on this chain. */
    const floatv x = rx * rx + ry * ry + rz * rz;
    const floatv x2 = x * x, x4 = x2 * x2;
    const floatv sinc = (1.4142135501f - 2.3570211044e-1f * x) + (1.1784686429e-2f - 2.8013486103e-4f * x) * x2
                      + 3.6842162911e-6f * x4;
    const floatv ch = (1.4142135617f - 7.0710676943e-1f * x) + (5.8925517357e-2f - 1.9641079022e-3f * x) * x2
                    + (3.5015516057e-5f - 3.6841466854e-7f * x) * x4;
    const floatv a = sinc * ch;
    const floatv b = sinc * sinc;
#if P == 0
    /* segments only, r in the world frame (the table's entries turned by R_ref): v' =
     * exp(r) e + q* with e = R_ref u, which (with e + q*) is computed while r is summed,
     * rather than R_ref exp(r) u + q*, whose R_ref product waited for the rotation (segment
     * rows 1.02-1.05x, kernel on one thread, bench/kernel_ab.py) */
    LOAD_REF();
    const floatv ex = m00 * ux + m01 * uy + m02 * uz;
    const floatv ey = m10 * ux + m11 * uy + m12 * uz;
    const floatv ez = m20 * ux + m21 * uy + m22 * uz;
    const floatv cx = ex + qx, cy = ey + qy, cz = ez + qz;
#else
    const floatv ex = ux, ey = uy, ez = uz, cx = ux, cy = uy, cz = uz;
#endif
    const floatv kx = ry * ez - rz * ey, ky = rz * ex - rx * ez, kz = rx * ey - ry * ex;
    const floatv jx = ry * kz - rz * ky, jy = rz * kx - rx * kz, jz = rx * ky - ry * kx;
    const floatv wx = cx + a * kx + b * jx;
    const floatv wy = cy + a * ky + b * jy;
    const floatv wz = cz + a * kz + b * jz;
#if P == 0
    const floatv ox = wx, oy = wy, oz = wz;
#else
    /* v' = R_ref w + q* */
    LOAD_REF();
    const floatv ox = m00 * wx + m01 * wy + m02 * wz + qx;
    const floatv oy = m10 * wx + m11 * wy + m12 * wz + qy;
    const floatv oz = m20 * wx + m21 * wy + m22 * wz + qz;
#endif
#endif
#if K == 0 && !defined(SPARSE)
    /* no segments: points are stored in their own order, chunk g holds rows VW g ..
     * VW g + VW-1: three 8-float vector stores per 8 rows (point rows 3-5 % faster) */
    STORE_XYZV(ox, oy, oz, out + 3 * VW * (size_t)g);
#else
    /* elsewhere the rows are scattered, except in runs of points of one reference in the
     * caller's order (the box 95 % of its chunks, bunny 38 %, dragon 9 %, armadillo 0.2 %):
     * the row record is run-coded */
    STORE_CHUNKV(ox, oy, oz, out, ints + VW);
#endif
}

/* Pose chunk g (points VW g .. VW g + VW-1 of the stored order) for frame `fr`. Inlined
 * into both of the kernel's loops (single pose, batch). */
static inline __attribute__((always_inline)) void pose_chunk(const int g, const int nsegs, __global const float *frec,
                                                             __global const int *irec, const frame_t fr)
{
    /* the chunk's records: row j of a record is at + VW j (LOADV(j, ...)) */
    __global const float *u = FREC_AT(frec, g);
    __global const float *coef = u + VW * 3;
    __global const float *phat = coef + VW * (P + 2 * K);
#ifndef DERIVED_LEVER
    __global const float *lever = phat + VW * 3 * P;
#endif
    __global const int *ints = IREC_AT(irec, g);
    __global const float *qpos = fr.qpos, *refs = fr.refs;
    __global const float *table = refs + TABLE_OFFSET(S), *segv = refs + SEGV_OFFSET(S);

    /* reference rotation: shared by the lanes (points are sorted by it) or gathered;
     * its matrix is loaded where it is used (LOAD_REF), not held in 9 registers
     * across the slot loop, where they were spilled */
    const intv rf = LOADIV(0, ints);
#if K == 0 && !defined(SPARSE)
    /* no segments: every point's reference is R_g, and without the per-lane branch the
     * point-handle loop keeps fewer registers live (point rows 2-6 % faster) */
    const int uniform = 1;
#else
    const int uniform = SAMEV(rf);
#endif
    floatv m00, m01, m02, m10, m11, m12, m20, m21, m22;   /* R_ref, for y below */

    /* q* (weighted posed centroid, linear in the posed handle positions) and r: half the
     * blended rotation vector relative to the reference (the levers are bound halved), or
     * (QUAT_BLEND) the lever-weighted quaternion sum */
    floatv qx = 0.0f, qy = 0.0f, qz = 0.0f, rx = 0.0f, ry = 0.0f, rz = 0.0f;
#ifdef QUAT_BLEND
    floatv rw = 0.0f;                    /* r: the lever-weighted quaternion sum */
    floatv gx, gy, gz, gw;               /* Q_ref */
#endif
    UNROLL_P
    for (int p = 0; p < P; ++p) {
        const floatv c = LOADV(p, coef);
        qx += c * qpos[3 * p];
        qy += c * qpos[3 * p + 1];
        qz += c * qpos[3 * p + 2];
    }
    /* slot k's terms from the entries that the lanes share: segment hs's posed start and
     * direction, and the table entry (reference rf.s0, segment hs). q* += w a, then += w t (b - a)
     * (two multiply-adds, not a product added to one: segment rows 1.00-1.04x on one thread);
     * r += lever * table entry, the lever w (the table holds len2 log(...)) or, stored,
     * normalised */
#ifdef DERIVED_LEVER
#define SLOT_LEVER(k) w
#else
#define SLOT_LEVER(k) LOADV(P + (k), lever)
#endif
#ifdef QUAT_BLEND
#define SLOT_W(l, t) rw += (l) * (t)[3]
#else
#define SLOT_W(l, t) ((void)0)
#endif
#define SLOT_SHARED(k, hs) do {                                                              \
        const floatv w = LOADV(P + 2 * (k), coef), wt = LOADV(P + 2 * (k) + 1, coef);        \
        const floatv l = SLOT_LEVER(k);                                                        \
        __global const float *a = segv + 6 * (hs);                                             \
        __global const float *t = table + TW * (S * rf.s0 + (hs));                             \
        qx += w * a[0]; qx += wt * a[3];                                                       \
        qy += w * a[1]; qy += wt * a[4];                                                       \
        qz += w * a[2]; qz += wt * a[5];                                                       \
        rx += l * t[0];                                                                        \
        ry += l * t[1];                                                                        \
        rz += l * t[2];                                                                        \
        SLOT_W(l, t);                                                                          \
    } while (0)
#ifndef SPARSE
    /* dense: one test of the chunk's lanes for all slots, so that the slots' loads and
     * multiply-adds are one straight run (dragon segments 1.05-1.06x, bunny 1.02-1.03x,
     * box 1.02-1.03x on one thread, bench/kernel_ab.py) */
    if (uniform) {
        UNROLL_K
        for (int k = 0; k < K; ++k)
            SLOT_SHARED(k, k);
    } else
#endif
    {
    UNROLL_GATHERED
    for (int k = 0; k < K; ++k) {
        /* segment slot k: dense, slot k is segment k; sparse, slot[k] names it per point */
#ifdef SPARSE
        const intv h = LOADIV(2 + k, ints);
#else
        const intv h = (intv)k;
#endif
        if (uniform && SAMEV(h)) {   /* the lanes read one table entry */
            SLOT_SHARED(k, h.s0);
        } else {
            const floatv w = LOADV(P + 2 * k, coef), wt = LOADV(P + 2 * k + 1, coef);
            const floatv l = SLOT_LEVER(k);
            const intv a = 6 * h, t = TW * (S * rf + h);
            qx += w * GATHERV(segv, a); qx += wt * GATHERV(segv, a + 3);
            qy += w * GATHERV(segv, a + 1); qy += wt * GATHERV(segv, a + 4);
            qz += w * GATHERV(segv, a + 2); qz += wt * GATHERV(segv, a + 5);
            rx += l * GATHERV(table, t);
            ry += l * GATHERV(table, t + 1);
            rz += l * GATHERV(table, t + 2);
#ifdef QUAT_BLEND
            rw += l * GATHERV(table, t + 3);
#endif
        }
    }
    }
    /* y = R_ref^-1 qhat = R_ref^T q_p - R_ref^T q*: with a shared reference, R_ref^T q_p
     * comes from the per-pose table ploc and only R_ref^T q* is computed per point */
#if P > 0
#ifdef QUAT_BLEND
    LOAD_QREF();
#endif
    LOAD_REF();
    __global const float *ploc = refs + PLOC_OFFSET(S) + 3 * P * rf.s0;
    floatv Yx = 0.0f, Yy = 0.0f, Yz = 0.0f;
    if (uniform) {
        Yx = m00 * qx + m10 * qy + m20 * qz;
        Yy = m01 * qx + m11 * qy + m21 * qz;
        Yz = m02 * qx + m12 * qy + m22 * qz;
    }
#endif
    UNROLL_P
    for (int p = 0; p < P; ++p) {
        /* minimal rotation taking phat onto y */
        floatv yx, yy, yz;
#if P > 0
        if (uniform) {
            yx = ploc[3 * p] - Yx; yy = ploc[3 * p + 1] - Yy; yz = ploc[3 * p + 2] - Yz;
        } else
#endif
        {
            const floatv hx = qpos[3 * p] - qx, hy = qpos[3 * p + 1] - qy, hz = qpos[3 * p + 2] - qz;
            yx = m00 * hx + m10 * hy + m20 * hz;
            yy = m01 * hx + m11 * hy + m21 * hz;
            yz = m02 * hx + m12 * hy + m22 * hz;
        }
        const floatv px = LOADV(3 * p, phat);
        const floatv py = LOADV(3 * p + 1, phat);
        const floatv pz = LOADV(3 * p + 2, phat);
        const floatv cx = py * yz - pz * yy, cy = pz * yx - px * yz, cz = px * yy - py * yx;
        const floatv cs = px * yx + py * yy + pz * yz;
        const floatv pp = px * px + py * py + pz * pz;
#ifdef DERIVED_LEVER
        const floatv lp = LOADV(p, coef) * pp;
#else
        const floatv lp = LOADV(p, lever);
#endif
#ifdef QUAT_BLEND
        /* m = (c, |phat||y| + phat.y) / |.|, the half-angle quaternion of the minimal
         * rotation (identity for opposite or zero vectors); r += lp Q_ref (x) m */
        const floatv w0 = sqrtv(pp * (yx * yx + yy * yy + yz * yz)) + cs;
        const floatv mn2 = w0 * w0 + cx * cx + cy * cy + cz * cz;
        const floatv k = mn2 > 0.0f ? lp * rsqrtv(mn2) : (floatv)0.0f;
        const floatv mx = k * cx, my = k * cy, mz = k * cz;
        const floatv mw = mn2 > 0.0f ? k * w0 : lp;
        rx += gw * mx + mw * gx + (gy * mz - gz * my);
        ry += gw * my + mw * gy + (gz * mx - gx * mz);
        rz += gw * mz + mw * gz + (gx * my - gy * mx);
        rw += gw * mw - (gx * mx + gy * my + gz * mz);
#else
        /* the angle from phat to y over |c| (angle_per_sine), for normal |c|^2 only
         * (its 1/|c| is an inverse square root without a denormal guard): phat is bound scaled to about
         * unit size (the header's phat row), so |c|^2 < FLT_MIN means |phat| |y| sin(angle)
         * below 1.1e-19 with the largest |phat| near 1: an angle below float32's resolution
         * on any model 1e-12 across or larger, or a phat so short that its lever w |phat|^2
         * is negligible; such contributions count as no rotation. Not
         * guarding denormals inside the inverse square root made point rows 10-11 %
         * faster (bench/kernel_ab.py: box 0.089 -> 0.081 ms, dragon 0.607 -> 0.545,
         * armadillo 0.760 -> 0.682), and the scaled phat made tiny models exact (1e-12
         * across: 10 % of the size off before, 5e-8 now) */
        const floatv sn2 = cx * cx + cy * cy + cz * cz;
        const floatv l = lp * (sn2 >= 1.17549435e-38f ? angle_per_sine(sn2, cs) : (floatv)0.0f);
        rx += l * cx;
        ry += l * cy;
        rz += l * cz;
#endif
    }
#ifdef QUAT_BLEND
    finish_chunk(g, nsegs, frec, irec, fr, rf, uniform, qx, qy, qz, rx, ry, rz, rw);
#else
    finish_chunk(g, nsegs, frec, irec, fr, rf, uniform, qx, qy, qz, rx, ry, rz, 0.0f);
#endif
}


#if P == 0 && K > 0 && !defined(SPARSE) && !defined(QUAT_BLEND) && defined(DERIVED_LEVER)
/* Rigs of segments only (dense, the relative or paper blend, derived levers): two consecutive
 * chunks whose lanes all share one reference are posed together (pose_pair), so that each
 * per-pose value of the slot loop (a segment's posed start and direction, a rotation-table
 * entry) is loaded and broadcast once for both. The kernel's time here follows its count of
 * loads about as closely as its count of arithmetic (one thread: 16 fewer broadcast loads a
 * chunk, the arithmetic unchanged, made the box's segment row 1.13x faster); the pairs halve the
 * slot loop's 9 K broadcasts a chunk. Kernel on one thread, paired in one process
 * (bench/kernel_ab.py, 300-600 launches, three runs): box segments 1.09-1.15x, bunny
 * 1.04-1.06x, dragon 1.06x, armadillo 1.085x; outputs bit-identical. Two chunks' slot loops
 * in one (12 sums, 4 coefficient rows) were as fast as a loop for q* and then one for r. */
#define CHUNK_PAIRS 1

/* The reference shared by every lane of chunks g and g + 1 (both before g_end), else -1. */
static inline int pair_ref(const int g, const int g_end, __global const int *irec)
{
    if (g + 1 >= g_end)
        return -1;
    const intv ra = LOADIV(0, IREC_AT(irec, g)), rb = LOADIV(0, IREC_AT(irec, g + 1));
    return orv((ra ^ (intv)ra.s0) | (rb ^ (intv)ra.s0)) == 0 ? ra.s0 : -1;
}

/* Chunks g and g + 1 of reference r0 (pair_ref) for frame `fr`: pose_chunk's sums for both,
 * in the same order per lane (the same results), then finish_chunk for each. */
static inline __attribute__((always_inline)) void pose_pair(const int g, const int r0, const int nsegs,
                                                            __global const float *frec,
                                                            __global const int *irec, const frame_t fr)
{
    __global const float *ca = FREC_AT(frec, g) + VW * 3, *cb = FREC_AT(frec, g + 1) + VW * 3;
    __global const float *segv = fr.refs + SEGV_OFFSET(S), *table = fr.refs + TABLE_OFFSET(S) + TW * S * r0;
    floatv qxa = 0.0f, qya = 0.0f, qza = 0.0f, rxa = 0.0f, rya = 0.0f, rza = 0.0f;
    floatv qxb = 0.0f, qyb = 0.0f, qzb = 0.0f, rxb = 0.0f, ryb = 0.0f, rzb = 0.0f;
    UNROLL_K
    for (int k = 0; k < K; ++k) {
        const floatv wa = LOADV(2 * k, ca), wta = LOADV(2 * k + 1, ca);
        const floatv wb = LOADV(2 * k, cb), wtb = LOADV(2 * k + 1, cb);
        __global const float *a = segv + 6 * k, *t = table + TW * k;
        qxa += wa * a[0]; qxb += wb * a[0]; qxa += wta * a[3]; qxb += wtb * a[3];
        qya += wa * a[1]; qyb += wb * a[1]; qya += wta * a[4]; qyb += wtb * a[4];
        qza += wa * a[2]; qzb += wb * a[2]; qza += wta * a[5]; qzb += wtb * a[5];
        rxa += wa * t[0]; rxb += wb * t[0];
        rya += wa * t[1]; ryb += wb * t[1];
        rza += wa * t[2]; rzb += wb * t[2];
    }
    const intv rf = (intv)r0;
    finish_chunk(g, nsegs, frec, irec, fr, rf, 1, qxa, qya, qza, rxa, rya, rza, 0.0f);
    finish_chunk(g + 1, nsegs, frec, irec, fr, rf, 1, qxb, qyb, qzb, rxb, ryb, rzb, 0.0f);
}
#endif

__kernel void nrmls_pose(__global const uchar *bound, __global float *frames, __global float *out_frames,
                         __global float *handed, volatile __global int *jobs, const int role)
{
    /* blocks of `block` chunks, shared by the devices of the launch (share.h); the
     * host publishes ceil(chunks / block) blocks and the job's frames F, with a
     * prologue that writes the frames' rotation data (pose_prologue) */
    __global const int *head = (__global const int *)bound;
    const int np = head[BOUND_NP], nsegs = head[BOUND_NSEGS], block = head[BOUND_BLOCK];
    const int pose_stride = head[BOUND_POSE_STRIDE], frame_stride = head[BOUND_FRAME_STRIDE];
    __global const float *frec = BOUND_AT(bound, BOUND_FREC, float);
    __global const int *irec = BOUND_AT(bound, BOUND_IREC, int);
    const int chunks = np / VW;
    FOR_EACH_JOB(jobs, role) {
    if (claim_prologue(jobs, job_tag_)) {
        pose_prologue(JOB_FRAMES_OF(jobs, job_tag_), nsegs, head[BOUND_PAPER], head[BOUND_NPAIRS], bound, frames,
                      pose_stride, frame_stride);
        open_job(jobs, job_tag_);
    }
    FOR_EACH_BLOCK(b, jobs) {
        const int g_end = min((b + 1) * block, chunks), F = JOB_FRAMES_OF(jobs, job_tag_);
#ifndef BATCHES_ONLY
        if (F == 1) {
            /* a single pose: its frame's pointers found once per block, not per chunk (kernel
             * on one thread: segment rows 1.04-1.12x, point rows 1.01-1.04x) */
            const frame_t fr = frame_at(0, frames, out_frames, handed, pose_stride, frame_stride, np);
            for (int g = b * block; g < g_end; ++g) {
#ifdef CHUNK_PAIRS
                const int r0 = pair_ref(g, g_end, irec);
                if (r0 >= 0) {
                    pose_pair(g++, r0, nsegs, frec, irec, fr);
                    continue;
                }
#endif
                pose_chunk(g, nsegs, frec, irec, fr);
            }
        } else
#endif
        {
            /* frames innermost: a chunk's bound data is read from memory once and reused
             * from L1 for every frame of the batch */
            for (int g = b * block; g < g_end; ++g) {
#ifdef CHUNK_PAIRS
                const int r0 = pair_ref(g, g_end, irec);
                if (r0 >= 0) {
                    for (int f = 0; f < F; ++f)
                        pose_pair(g, r0, nsegs, frec, irec,
                                  frame_at(f, frames, out_frames, handed, pose_stride, frame_stride, np));
                    ++g;
                    continue;
                }
#endif
                for (int f = 0; f < F; ++f)
                    pose_chunk(g, nsegs, frec, irec,
                               frame_at(f, frames, out_frames, handed, pose_stride, frame_stride, np));
            }
        }
    }
    }   /* job */
}
