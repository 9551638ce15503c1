/* R_g, the global rotation of the relative and quaternion blends, fitted on the
 * device: the twin of nrpose.pose.blend.GlobalRotation (its float64 reference).
 *
 * R_g is the rotation R maximising trace(R^T C) for the covariance
 * C = sum_k (q_k - o) p_k^T of the M handle positions (point handles, then
 * segment ends): p_k rest, centred at bind; q_k posed, taken relative to
 * o = q_0 (the rest side sums to zero, so no posed centroid is needed).
 * Solved as Horn's quaternion eigenproblem (nrpose/rotation.py
 * covariance_rotation): the best rotations are the top eigenvectors of a
 * symmetric 4x4 N built from C. Ties (eigenvalues within 1e-9 of the scale of
 * the top one: collinear handles leave a circle of optimal rotations, one
 * handle a sphere) take the optimal rotation nearest the identity, the
 * identity quaternion projected onto their eigenspace; when every optimal
 * rotation is a half turn (that projection vanishes), the one whose axis is
 * nearest x, else y, else z, as the reference decides. The
 * tie tolerance adds the float32 rounding of the posed positions (see below).
 * Everything in double precision after reading the float32 positions; the
 * 4x4 eigenproblem by cyclic Jacobi rotations.
 *
 * global_rotation_of(q, fit, m, rg_offset), for one frame:
 *   q     the frame's pose block (nrmls.cl `pose`), which starts with the M = m
 *         posed positions (xyz, float); R_g is written there, row-major, at
 *         float offset rg_offset
 *   fit   [1 + M*3] double: scale2, the largest |p| component squared of the
 *         centred rest positions (with max |C| it sets the tie tolerance's
 *         scale), then the centred rest positions, same order
 * Used by the pose kernel's prologue (nrmls.cl, built with -DGLOBAL_FIT) and by
 * the kernel global_rotation (global_fit.cl: nrpose.pose.mls.GlobalFit.fit).
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#define JACOBI_SWEEPS 12   /* a 4x4 converges in about 5 (the loop ends then) */

static void global_rotation_of(__global float *q, __global const double *fit, const int m, const int rg_offset)
{
    __global const double *rest = fit + 1;
    const double scale2 = fit[0];
    double c[3][3] = {{0.0, 0.0, 0.0}, {0.0, 0.0, 0.0}, {0.0, 0.0, 0.0}};
    const double o0 = q[0], o1 = q[1], o2 = q[2];
    double qmax = fmax(fabs(o0), fmax(fabs(o1), fabs(o2)));
    for (int k = 1; k < m; ++k) {     /* k = 0 adds (q_0 - o) p_0^T = 0 */
        const double d[3] = {q[3 * k] - o0, q[3 * k + 1] - o1, q[3 * k + 2] - o2};
        qmax = fmax(qmax, fmax(fabs((double)q[3 * k]), fmax(fabs((double)q[3 * k + 1]), fabs((double)q[3 * k + 2]))));
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                c[i][j] += d[i] * rest[3 * k + j];
    }
    double scale = scale2 > 1e-300 ? scale2 : 1e-300;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            scale = fabs(c[i][j]) > scale ? fabs(c[i][j]) : scale;
    const double xx = c[0][0], xy = c[0][1], xz = c[0][2], yx = c[1][0], yy = c[1][1], yz = c[1][2],
                 zx = c[2][0], zy = c[2][1], zz = c[2][2];
    /* quaternion (w, x, y, z): trace(R(q)^T C) = q^T a q */
    double a[4][4] = {{xx + yy + zz, zy - yz, xz - zx, yx - xy},
                      {zy - yz, xx - yy - zz, yx + xy, xz + zx},
                      {xz - zx, yx + xy, yy - xx - zz, zy + yz},
                      {yx - xy, xz + zx, zy + yz, zz - xx - yy}};
    double v[4][4] = {{1.0, 0.0, 0.0, 0.0}, {0.0, 1.0, 0.0, 0.0}, {0.0, 0.0, 1.0, 0.0}, {0.0, 0.0, 0.0, 1.0}};
    for (int sweep = 0; sweep < JACOBI_SWEEPS; ++sweep) {
        double off = 0.0, on = 0.0;
        for (int p = 0; p < 4; ++p) {
            on += a[p][p] * a[p][p];
            for (int r = p + 1; r < 4; ++r)
                off += a[p][r] * a[p][r];
        }
        if (off <= 1e-30 * on)      /* converged: off-diagonal below 1e-15 of the diagonal (or a = 0) */
            break;
        for (int p = 0; p < 3; ++p) {
            for (int r = p + 1; r < 4; ++r) {
                const double apr = a[p][r];
                if (apr == 0.0)
                    continue;
                /* the rotation J in the (p, r) plane with (J^T a J)[p][r] = 0 */
                const double theta = (a[r][r] - a[p][p]) / (2.0 * apr);
                const double t = (theta >= 0.0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
                const double cs = 1.0 / sqrt(t * t + 1.0), sn = t * cs;
                for (int k = 0; k < 4; ++k) {
                    const double akp = a[k][p], akr = a[k][r];
                    a[k][p] = cs * akp - sn * akr;
                    a[k][r] = sn * akp + cs * akr;
                }
                for (int k = 0; k < 4; ++k) {
                    const double apk = a[p][k], ark = a[r][k];
                    a[p][k] = cs * apk - sn * ark;
                    a[r][k] = sn * apk + cs * ark;
                }
                for (int k = 0; k < 4; ++k) {
                    const double vkp = v[k][p], vkr = v[k][r];
                    v[k][p] = cs * vkp - sn * vkr;
                    v[k][r] = sn * vkp + cs * vkr;
                }
            }
        }
    }
    int top = 0;
    for (int k = 1; k < 4; ++k)
        top = a[k][k] > a[top][top] ? k : top;
    /* the identity quaternion projected onto the optimal eigenspace. Tolerance: the
     * reference's 1e-9 of the scale, plus what rounding the posed positions to float32
     * moves N's eigenvalues by (|dC| <= m eps max|q| max|p|, |dN| <= 4 max|dC|...), so
     * that ties made by the posed side (e.g. posed handles on one line) are ties here too */
    const double rounding = 16.0 * m * FLT_EPSILON * qmax * sqrt(scale2);
    const double tol = 1e-9 * scale + rounding;
    double w, x, y, z, norm;
    /* e = 0: the identity (1, 0, 0, 0) projected; when every optimal rotation is a half
     * turn (that projection vanishes) the half turns about x, y, z (e = 1, 2, 3) in turn,
     * the first projection at least 1/2 long: the reference's rule. "Vanishes": below
     * the reference's 1e-6 plus the same float32 rounding relative to the scale (handles
     * far from the origin, posed reversed on a line, left a noise projection of 1e-6 to
     * 3e-6 at 100 handle spans out, which picked a noise half turn); on a unique optimum
     * every projection gives the same rotation, so the threshold only matters in a tie */
    for (int e = 0; e < 4; ++e) {
        w = 0.0; x = 0.0; y = 0.0; z = 0.0;
        for (int k = 0; k < 4; ++k) {
            if (a[k][k] >= a[top][top] - tol) {
                w += v[0][k] * v[e][k]; x += v[1][k] * v[e][k]; y += v[2][k] * v[e][k]; z += v[3][k] * v[e][k];
            }
        }
        norm = sqrt(w * w + x * x + y * y + z * z);
        if (e == 0 ? norm > 1e-6 + rounding / scale : norm >= 0.5)
            break;
    }
    w /= norm; x /= norm; y /= norm; z /= norm;
    __global float *rg = q + rg_offset;
    rg[0] = (float)(w * w + x * x - y * y - z * z); rg[1] = (float)(2.0 * (x * y - w * z));
    rg[2] = (float)(2.0 * (x * z + w * y));
    rg[3] = (float)(2.0 * (x * y + w * z)); rg[4] = (float)(w * w - x * x + y * y - z * z);
    rg[5] = (float)(2.0 * (y * z - w * x));
    rg[6] = (float)(2.0 * (x * z - w * y)); rg[7] = (float)(2.0 * (y * z + w * x));
    rg[8] = (float)(w * w - x * x - y * y + z * z);
}
