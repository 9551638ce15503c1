"""CoR skinning (Le & Hodgins 2016) float64 reference: centers against the direct formula,
rigid motion, one-joint vertices, equivariance, rigid parts, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrpose.pose import cor
from nrpose.model import deformation_metrics as dm
from nrpose.errors import InputError
from nrpose.rigs import cylinder
from nrpose.pose.skinning import lbs_reference


def tube_rig(rng=None):
    """The two-bone cylinder with smooth two-joint weights around x = 1 (K = 2)."""
    V, F = cylinder.cylinder_mesh(rings=41, sectors=24)
    w1 = np.clip((V[:, 0] - 0.7) / 0.6, 0, 1)
    if rng is not None:
        w1 = np.clip(w1 + 0.05 * rng.random(len(V)) * (w1 > 0) * (w1 < 1), 0, 1)
    joints = np.tile([0, 1], (len(V), 1))
    return V, F, joints, np.stack([1 - w1, w1], 1)


def rigid_mat(rng, scale=1.0):
    M = np.eye(4)
    M[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    M[:3, 3] = rng.normal(size=3) * scale
    return M


def bend_mats(degrees):
    pose = cylinder.bend_pose(degrees)
    M = np.tile(np.eye(4), (2, 1, 1))
    M[1, :3, :3] = pose.rotations[1]
    M[1, :3, 3] = cylinder.BONES[1, 0] - pose.rotations[1] @ cylinder.BONES[1, 0]
    return M


def test_centers_match_the_direct_formula():
    rng = np.random.default_rng(0)
    V, F = cylinder.cylinder_mesh(rings=9, sectors=8)
    J, K = 5, 3
    joints = np.stack([rng.permutation(J)[:K] for _ in V])
    weights = rng.random((len(V), K)) * (rng.random((len(V), K)) > 0.2)
    weights[:, 0] += 0.1
    W = cor.dense(joints, weights / weights.sum(1, keepdims=True), J)
    Vt, Wt = V[F].mean(axis=1), W[F].mean(axis=1)
    A = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    s = cor.similarity(W, Wt) * A[None]
    den = s.sum(axis=1, keepdims=True)
    assert (den > 0).mean() > 0.5
    want = np.where(den > 0, (s @ Vt) / np.where(den > 0, den, 1.0), V)   # no similar triangle: c = v
    got = cor.centers(V, F, joints, weights)
    assert np.abs(got - want).max() < 1e-12
    # with subdivision the centers move little on this smooth-weight mesh, and stay finite
    assert np.isfinite(cor.centers(V, F, joints, weights, subdivisions=1)).all()


def test_centers_of_a_two_bone_tube_lie_near_the_joint():
    V, F, joints, weights = tube_rig()
    C = cor.centers(V, F, joints, weights)
    blended = (weights > 0).all(axis=1)
    assert np.abs(C[blended, 0] - 1.0).max() < 0.3                 # along the tube, near the joint
    assert np.linalg.norm(C[blended, 1:], axis=1).max() < 0.05      # on the axis, by symmetry
    assert np.array_equal(C[~blended], V[~blended])                 # one influence: c = v


def test_rigid_motion_is_reproduced():
    rng = np.random.default_rng(1)
    V, F, joints, weights = tube_rig(rng)
    C = cor.centers(V, F, joints, weights)
    M = rigid_mat(rng, 3.0)
    out = cor.cor_reference(V, joints, weights, np.stack([M, M]), C)
    assert np.abs(out - (V @ M[:3, :3].T + M[:3, 3])).max() < 1e-12


def test_one_joint_vertices_agree_with_lbs_and_equivariance():
    rng = np.random.default_rng(2)
    V, F, joints, weights = tube_rig(rng)
    C = cor.centers(V, F, joints, weights)
    mats = np.stack([rigid_mat(rng), rigid_mat(rng)])
    out = cor.cor_reference(V, joints, weights, mats, C)
    one = (weights == 1).any(axis=1)
    assert np.abs(out[one] - lbs_reference(V, joints, weights, mats)[one]).max() < 1e-12
    G = rigid_mat(rng, 5.0)
    turned = cor.cor_reference(V, joints, weights, G[None] @ mats, C)
    assert np.abs(turned - (out @ G[:3, :3].T + G[:3, 3])).max() < 1e-10


def test_a_part_with_one_weight_set_moves_rigidly_where_lbs_does_not():
    V, F, joints, weights = tube_rig()
    part = (V[:, 0] > 0.9) & (V[:, 0] < 1.1)
    weights[part] = [0.4, 0.6]
    C = cor.centers(V, F, joints, weights)
    E = dm.mesh_edges(F, len(V))
    labels = dm.weight_groups(weights)
    mats = bend_mats(120)
    out = cor.cor_reference(V, joints, weights, mats, C)
    assert dm.group_rigidity(V, out, E, labels) < 1e-12
    assert dm.group_rigidity(V, lbs_reference(V, joints, weights, mats), E, labels) > 0.05
    # and the bend keeps more volume than LBS
    vol = dm.signed_volume(V, F)
    assert dm.signed_volume(out, F) > dm.signed_volume(lbs_reference(V, joints, weights, mats), F)
    assert dm.signed_volume(out, F) > 0.9 * vol


def test_point_cloud_centers():
    V, _, joints, weights = tube_rig()
    C = cor.centers(V, None, joints, weights)
    blended = (weights > 0).all(axis=1)
    assert np.abs(C[blended, 0] - 1.0).max() < 0.3


def test_bad_input():
    V, F, joints, weights = tube_rig()
    with pytest.raises(InputError, match="sigma"):
        cor.centers(V, F, joints, weights, sigma=0.0)
    with pytest.raises(InputError, match="centers"):
        cor.cor_reference(V, joints, weights, bend_mats(30), V[:-1])
    with pytest.raises(InputError, match="out of range"):
        cor.cor_reference(V, joints, weights, bend_mats(30)[:1], V)
    with pytest.raises(InputError, match="faces"):
        cor.centers(V, F + len(V), joints, weights)
