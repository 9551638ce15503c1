/* R_g of F frames on their own, one work-item per frame (global size F): for
 * tests and diagnostics (nrpose.pose.mls.GlobalFit.fit); a deformer fits R_g in its
 * pose kernel's prologue (nrmls.cl). global_fit.h says what is computed.
 *   pose  [F][pose_stride] float: frame blocks, each starting with the M = m posed
 *         positions; R_g is written at float offset rg_offset of each
 *   fit   [1 + M*3] double: global_fit.h's
 */
#include "global_fit.h"

__kernel void global_rotation(__global float *pose, __global const double *fit, const int m,
                              const int pose_stride, const int rg_offset)
{
    global_rotation_of(pose + get_global_id(0) * pose_stride, fit, m, rg_offset);
}
