"""libigl DMAT files for tests: animation matrices of a TGF skeleton's motion, written by libigl."""
from __future__ import annotations

from pathlib import Path

import igl
import numpy as np

from nrpose.io.tgf import bone_joints


def transforms_matrix(A: np.ndarray) -> np.ndarray:
    """The (12·B) × F libigl animation matrix of per-bone rigid transforms A (F, B, 4, 4) (world,
    rest to posed): frame f's column is the column-major (4·B) × 3 matrix of [R | t] transposed."""
    F, B = A.shape[:2]
    T = np.zeros((12 * B, F))
    for f in range(F):
        Tf = np.concatenate([A[f, e, :3, :].T for e in range(B)])    # (4B, 3)
        T[:, f] = Tf.ravel(order="F")
    return T


def motion_matrix(skeleton, globals_: np.ndarray) -> np.ndarray:
    """The animation matrix of a TGF skeleton's motion, given its global joint transforms
    (F, J, 4, 4) (``skeleton.forward_kinematics``)."""
    joints = bone_joints(skeleton, "test")
    return transforms_matrix(globals_[:, joints] @ np.linalg.inv(skeleton.rest_globals()[joints]))


def write_dmat(path, matrix) -> Path:
    """``matrix`` written by libigl as an ASCII DMAT; the path."""
    igl.writeDMAT(str(path), np.asarray(matrix, dtype=np.float64), True)
    return Path(path)
