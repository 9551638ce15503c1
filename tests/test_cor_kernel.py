"""CoR skinning on the device (kernels/cor.cl through nrpose.pose.skinning.Skinner, method
"cor") against its float64 reference nrpose.pose.cor.cor_reference, on random and adversarial
influences, one pose and batches of frames, shared memory and the copying buffer path."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrpose.errors import InputError
from nrpose.pose import cor
from nrpose.pose.skinning import Skinner

pytest.importorskip("pyopencl")


def run_kernel(rest, joints, weights, centers, mats_frames, svm: bool = True) -> np.ndarray:
    """(F, N, 3) posed by the device's cor kernel with the given centers."""
    d = Skinner(rest, joints, weights, method="cor", centers=centers)
    d._svm = d._svm and svm
    return d.pose_frames(np.asarray(mats_frames, np.float64))


def random_rig(rng, n=1003, J=7, K=4):
    V = rng.uniform(-1, 1, (n, 3))
    joints = np.stack([rng.permutation(J)[:K] for _ in range(n)])
    weights = rng.random((n, K)) ** 3 * (rng.random((n, K)) > 0.3)
    weights[:, 0] += 0.05
    return V, joints, weights


def random_mats(rng, F, J, spread=np.pi):
    M = np.tile(np.eye(4), (F, J, 1, 1))
    M[..., :3, :3] = Rotation.from_rotvec(rng.normal(size=(F * J, 3)) * spread / 2).as_matrix().reshape(F, J, 3, 3)
    M[..., :3, 3] = rng.normal(size=(F, J, 3))
    return M


@pytest.mark.parametrize("svm", [True, False])
def test_kernel_matches_the_reference_on_random_rigs(svm):
    rng = np.random.default_rng(0)
    V, joints, weights = random_rig(rng)
    C = V + 0.3 * rng.normal(size=V.shape)            # any centers: the kernel takes them as given
    mats = random_mats(rng, 3, 7)
    got = run_kernel(V, joints, weights, C, mats, svm)
    for f in range(3):
        want = cor.cor_reference(V, joints, weights, mats[f], C)
        assert np.abs(got[f] - want).max() < 2e-5 * (1 + np.abs(want).max())


def test_cor_skinner_binds_its_centers_and_poses_one_frame():
    rng = np.random.default_rng(2)
    V, joints, weights = random_rig(rng, n=300, J=5, K=3)
    F = rng.integers(0, 300, (400, 3))
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    d = cor.CorSkinner(V, joints, weights, F)
    assert np.allclose(d.centers, cor.centers(V, F, joints, weights))
    M = random_mats(rng, 1, 5)[0]
    want = cor.cor_reference(V, joints, weights, M, d.centers)
    assert np.abs(d.pose(M) - want).max() < 2e-5 * (1 + np.abs(want).max())


def test_centers_only_with_cor():
    V, joints, weights = random_rig(np.random.default_rng(3), n=20, J=3, K=2)
    with pytest.raises(InputError, match="centers"):
        Skinner(V, joints, weights, method="cor")
    with pytest.raises(InputError, match="centers"):
        Skinner(V, joints, weights, method="lbs", centers=V)
    with pytest.raises(InputError, match="centers"):
        Skinner(V, joints, weights, method="cor", centers=V[:5])


def test_kernel_adversarial_antipodal_and_one_joint():
    """Rotations near 180° apart (hemisphere flips), one-joint vertices, a tail group."""
    rng = np.random.default_rng(1)
    V, joints, weights = random_rig(rng, n=13, J=3, K=2)
    weights[:5, 1] = 0.0
    C = cor.centers(V, None, joints, weights)
    M = np.tile(np.eye(4), (1, 3, 1, 1))
    M[0, 1, :3, :3] = Rotation.from_rotvec([0, 0, np.pi * 0.999]).as_matrix()
    M[0, 2, :3, :3] = Rotation.from_rotvec([0, 0, -np.pi * 0.999]).as_matrix()
    got = run_kernel(V, joints, weights, C, M)[0]
    want = cor.cor_reference(V, joints, weights, M[0], C)
    assert np.abs(got - want).max() < 1e-4
