"""Helper joints: extra rigid transforms, children of skeleton joints, driven by joint rotations.

A helper h is a child of skeleton joint ``parent``. Its local transform in a pose (the
parent's frame, rotation and translation: a glTF TRS node without scale) is a **fixed rule**
of the local rotations of its ``drivers`` (joints):

    A = phi @ coef      phi = [1, (x, y, z, w - 1) of q_d for each driver d]          (1 + 4 D,)
    L = [polar(A[:9] as 3x3) | A[9:12]]                                             (4, 4)

(``q_d``: the unit quaternion, w >= 0, of driver d's local rotation relative to its rest
rotation, ``q_rest_d^-1 q_d``: bounded, and linear in the angle for small turns, so single-axis
sweeps of the range of motion excite each component; polar: the nearest rotation).
``coef`` (1 + 4 D, 12) is a ridge regression (:func:`fit_rule`) of
per-frame rigid transforms fitted on the training poses, so the helper follows any pose of
the skeleton: it is evaluated for the clips written to the file as ordinary animation
channels. The helper's skinning matrix in a mesh is ``G_parent @ L @ inv(C) @ ibm_parent``
with C the translation to ``centre`` (its region's centre in the parent's bind frame), so
its inverse bind matrix is ``inv(C) @ ibm_parent``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..model.rotation import quat_multiply
from ..model.skeleton import LocalPose, Skeleton, polar_rotation

__all__ = ["HelperJoint", "driver_features", "fit_rule", "evaluate_rule", "rigid_fit", "rule_locals", "helper_skin_matrices"]

RIDGE = 1e-3    # ridge of the rule regression, relative to the mean feature energy


@dataclass(frozen=True)
class HelperJoint:
    """parent: skeleton joint; drivers: joints whose local rotations drive it; centre (3,) float64
    in the parent's bind frame (model units of that frame); coef (1 + 4 len(drivers), 12) float64."""

    parent: int
    drivers: tuple
    centre: np.ndarray
    coef: np.ndarray

    def local(self, skeleton: Skeleton, pose: LocalPose) -> np.ndarray:
        """The helper's local transforms (F, 4, 4) float64 in the parent's frame for pose (F, J, ...)."""
        return evaluate_rule(driver_features(skeleton, pose, self.drivers), self.coef)

    def inverse_bind(self, ibm_parent: np.ndarray) -> np.ndarray:
        """Inverse bind matrix (4, 4) of the helper in a skin whose parent joint has ``ibm_parent``."""
        C = np.eye(4)
        C[:3, 3] = -self.centre
        return C @ ibm_parent


def driver_features(skeleton: Skeleton, pose: LocalPose, drivers) -> np.ndarray:
    """phi (F, 1 + 4 D) float64 of the module docstring for pose (F, J, ...) or a single pose."""
    rotation = np.asarray(pose.rotation, np.float64)
    rotation = rotation[None] if rotation.ndim == 2 else rotation
    F = len(rotation)
    d = list(drivers)
    rest = skeleton.rotation[d] * np.array([-1.0, -1.0, -1.0, 1.0])            # inverses (D, 4)
    rest = rest / np.linalg.norm(rest, axis=1, keepdims=True)
    q = quat_multiply(np.broadcast_to(rest, rotation[:, d].shape), rotation[:, d])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = q * np.where(q[..., 3:] < 0, -1.0, 1.0)
    q[..., 3] -= 1.0
    return np.concatenate([np.ones((F, 1)), q.reshape(F, 4 * len(d))], axis=1)


def fit_rule(phi: np.ndarray, L: np.ndarray, ridge: float = RIDGE) -> np.ndarray:
    """coef (P, 12) of the ridge regression of transforms L (F, 4, 4) on features phi (F, P)
    (ridge: relative to the mean feature energy; the constant column is not penalised)."""
    Y = np.concatenate([L[:, :3, :3].reshape(-1, 9), L[:, :3, 3]], axis=1)
    A = phi.T @ phi
    penalty = ridge * max(float(np.trace(A[1:, 1:])) / max(len(A) - 1, 1), 1e-12)
    A[1:, 1:] += penalty * np.eye(len(A) - 1)
    return np.linalg.solve(A, phi.T @ Y)


def evaluate_rule(phi: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Rigid transforms (F, 4, 4) float64 of the rule with features phi (F, P)."""
    A = phi @ coef
    L = np.tile(np.eye(4), (len(A), 1, 1))
    L[:, :3, :3] = polar_rotation(A[:, :9].reshape(-1, 3, 3))
    L[:, :3, 3] = A[:, 9:]
    return L


def rigid_fit(z: np.ndarray, u: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Per frame the rigid transform (F, 4, 4) minimising sum_n a_n |R z_n + t - u_fn|^2
    (weighted Procrustes, proper rotations); z (n, 3), u (F, n, 3), a (n,) >= 0 not all 0."""
    a = np.asarray(a, np.float64)
    if not (a >= 0).all() or not a.sum() > 0:
        raise InputError("rigid_fit needs non-negative weights, not all zero")
    a = a / a.sum()
    zc = a @ z                                                     # (3,)
    uc = np.einsum("n,fni->fi", a, u)                              # (F, 3)
    H = np.einsum("n,ni,fnj->fji", a, z - zc, u - uc[:, None])     # (F, 3, 3): sum a u z^T
    U, _, Vt = np.linalg.svd(H)
    D = np.ones((len(H), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    R = np.einsum("fij,fj,fjk->fik", U, D, Vt)
    L = np.tile(np.eye(4), (len(H), 1, 1))
    L[:, :3, :3] = R
    L[:, :3, 3] = uc - np.einsum("fij,j->fi", R, zc)
    return L


def rule_locals(helpers, skeleton: Skeleton, pose: LocalPose) -> np.ndarray:
    """Local transforms (F, H, 4, 4) float64 of ``helpers`` by their rules for pose (F, J, ...)."""
    if not helpers:
        return np.zeros((len(pose.rotation), 0, 4, 4))
    return np.stack([h.local(skeleton, pose) for h in helpers], axis=1)


def helper_skin_matrices(helpers, skeleton: Skeleton, G: np.ndarray, pose: LocalPose | None,
                         ibm: np.ndarray, tracks: np.ndarray | None = None) -> np.ndarray:
    """Skinning matrices (F, H, 4, 4) float64 of the helpers in a mesh with inverse binds ibm
    (J, 4, 4), for global joint matrices G (F, J, 4, 4) of pose (F, J, ...); the helpers' local
    transforms are tracks (F, H, 4, 4) if given, else their rules evaluated on pose."""
    out = np.empty((len(G), len(helpers), 4, 4))
    for h, helper in enumerate(helpers):
        local = helper.local(skeleton, pose) if tracks is None else tracks[:, h]
        out[:, h] = G[:, helper.parent] @ local @ helper.inverse_bind(ibm[helper.parent])
    return out
