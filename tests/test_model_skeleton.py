"""Skeleton model: forward kinematics and bone formation on synthetic skeletons."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrpose.errors import InputError
from nrpose.model.skeleton import LocalPose, Skeleton, local_matrices

IDENTITY = [0.0, 0.0, 0.0, 1.0]


def make(parents, translation, rotation=None, **kw):
    J = len(parents)
    return Skeleton(names=tuple(f"j{i}" for i in range(J)), parents=parents, translation=translation,
                    rotation=np.tile(IDENTITY, (J, 1)) if rotation is None else rotation,
                    scale=np.ones((J, 3)), **kw)


def chain(n=3):
    """n joints along +x, one unit apart, root at the origin."""
    return make(list(range(-1, n - 1)), [[0, 0, 0]] + [[1, 0, 0]] * (n - 1))


def quat(axis, degrees):
    return Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, float)).as_quat()


def test_identity_rotations_accumulate_translations():
    rng = np.random.default_rng(0)
    parents = [-1, 0, 1, 1, 3, -1]
    t = rng.normal(size=(6, 3))
    G = make(parents, t).forward_kinematics()
    expected = t.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            expected[j] += expected[p]
    assert G.shape == (6, 4, 4) and G.dtype == np.float64
    np.testing.assert_allclose(G[:, :3, 3], expected, atol=1e-12)
    np.testing.assert_allclose(G[:, :3, :3], np.broadcast_to(np.eye(3), (6, 3, 3)), atol=1e-12)


def test_known_rotations_move_children():
    skel = chain(3)
    pose = skel.rest_pose
    pose.rotation[0] = quat([0, 0, 1], 90)
    G = skel.forward_kinematics(pose)
    np.testing.assert_allclose(G[:, :3, 3], [[0, 0, 0], [0, 1, 0], [0, 2, 0]], atol=1e-12)
    pose.rotation[1] = quat([0, 0, 1], 90)
    G = skel.forward_kinematics(pose)
    np.testing.assert_allclose(G[2, :3, 3], [-1, 1, 0], atol=1e-12)
    np.testing.assert_allclose(G[2, :3, :3], Rotation.from_rotvec([0, 0, np.pi]).as_matrix(), atol=1e-12)


def test_batch_matches_frame_by_frame_and_uses_pre_and_scale():
    rng = np.random.default_rng(1)
    parents = [-1, 0, 1, 0]
    pre = np.tile(np.eye(4), (4, 1, 1))
    pre[0, :3, 3] = [5, 0, 0]
    pre[0, :3, :3] = 2.0 * Rotation.from_rotvec([0.3, 0, 0]).as_matrix()
    pre[2, :3, 3] = [0, 1, -2]                   # a pre below the root (joints 1 and 3 have none)
    pre[2, :3, :3] = Rotation.from_rotvec([0, 0.7, 0.2]).as_matrix()
    skel = make(parents, rng.normal(size=(4, 3)), pre=pre)
    F = 5
    pose = LocalPose(rng.normal(size=(F, 4, 3)), Rotation.random(F * 4, random_state=2).as_quat().reshape(F, 4, 4),
                     rng.uniform(0.5, 2, size=(F, 4, 3)))
    G = skel.forward_kinematics(pose)
    assert G.shape == (F, 4, 4, 4)
    for f in range(F):
        L = local_matrices(pose.translation[f], pose.rotation[f], pose.scale[f])
        expected = np.empty((4, 4, 4))
        for j, p in enumerate(parents):
            expected[j] = (pre[j] @ L[j]) if p < 0 else expected[p] @ pre[j] @ L[j]
        np.testing.assert_allclose(G[f], expected, atol=1e-12)


def test_invalid_skeletons_and_unknown_names():
    with pytest.raises(InputError, match="topological order"):
        make([1, -1], np.zeros((2, 3)))
    with pytest.raises(InputError, match="duplicate"):
        Skeleton(("a", "a"), [-1, 0], np.zeros((2, 3)), np.tile(IDENTITY, (2, 1)), np.ones((2, 3)))
    with pytest.raises(InputError, match="zero quaternion"):
        make([-1], np.zeros((1, 3)), rotation=np.zeros((1, 4)))
    # a rest frame the inverse bind cannot undo: zero, subnormal, or a chain of scales past 1e8
    for scale in ([[1, 1, 1], [1, 0, 1]], [[1, 1, 1], [1e-320, 1, 1]], [[1e5, 1, 1], [1e4, 1, 1]]):
        with pytest.raises(InputError, match=r"rest transform of joint 'j1' scales by .* must lie between"):
            Skeleton(("j0", "j1"), [-1, 0], np.zeros((2, 3)), np.tile(IDENTITY, (2, 1)), scale)
    Skeleton(("j0", "j1"), [-1, 0], np.zeros((2, 3)), np.tile(IDENTITY, (2, 1)), [[0.01, 0.01, 0.01], [1e-4, 1, 1]])
    # quaternions near the float64 limit normalise without overflow
    huge = make([-1, 0], np.zeros((2, 3)), rotation=[[1e308, 1e308, 0, 0], [0, 0, 0, 1e-6]])
    np.testing.assert_allclose(huge.rotation, [[0.5 ** 0.5, 0.5 ** 0.5, 0, 0], [0, 0, 0, 1]], atol=1e-15)
    skel = Skeleton(("LeftArm", "LeftForeArm", "RightArm"), [-1, 0, -1], np.zeros((3, 3)),
                    np.tile(IDENTITY, (3, 1)), np.ones((3, 3)))
    assert skel.index("RightArm") == 2
    with pytest.raises(InputError, match="did you mean 'LeftArm'"):
        skel.index("LeftArn")


def segments_by_name(bones):
    return {name: seg for name, seg in zip(bones.names, bones.segments)}


def test_branching_joint_gets_one_segment_per_child():
    skel = make([-1, 0, 0, 0], [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2]])
    bones = skel.bones()
    drivers = {n: j for n, j in zip(bones.names, bones.joints)}
    assert [drivers[f"j0->j{c}"] for c in (1, 2, 3)] == [0, 0, 0]
    np.testing.assert_allclose(segments_by_name(bones)["j0->j3"], [[0, 0, 0], [0, 0, 2]])


def test_leaf_gets_half_parent_bone_and_tip_wins():
    bones = chain(3).bones()
    segs = segments_by_name(bones)
    assert list(segs) == ["j0->j1", "j1->j2", "j2->(leaf)"]
    np.testing.assert_allclose(segs["j2->(leaf)"], [[2, 0, 0], [2.5, 0, 0]])
    tips = np.full((3, 3), np.nan)
    tips[2] = [0, 3, 0]
    segs = segments_by_name(make([-1, 0, 1], [[0, 0, 0], [1, 0, 0], [1, 0, 0]], tips=tips).bones())
    np.testing.assert_allclose(segs["j2->j2_tip"], [[2, 0, 0], [2, 3, 0]])
    assert "j2->(leaf)" not in segs


def test_zero_length_bones_are_looked_through():
    # root -> hipjoint (offset 0) -> hip -> knee, like BVH LHipJoint
    skel = make([-1, 0, 1, 2], [[0, 0, 0], [0, 0, 0], [1, -1, 0], [0, -2, 0]])
    bones = skel.bones()
    segs = segments_by_name(bones)
    assert set(segs) == {"j0->j2", "j1->j2", "j2->j3", "j3->(leaf)"}
    assert np.all(np.linalg.norm(bones.segments[:, 1] - bones.segments[:, 0], axis=1) > 0)
    # a leaf coinciding with its parent extends along the grandparent direction
    skel = make([-1, 0, 1], [[0, 0, 0], [0, 2, 0], [0, 0, 0]])
    np.testing.assert_allclose(segments_by_name(skel.bones())["j2->(leaf)"], [[0, 2, 0], [0, 3, 0]])


def test_isolated_joint_and_non_deform_joints_drive_nothing():
    assert len(make([-1], [[1, 2, 3]]).bones()) == 0
    skel = make([-1, 0, 1], [[0, 0, 0], [1, 0, 0], [1, 0, 0]], deform=[False, True, True])
    assert 0 not in skel.bones().joints


def test_posed_bones_carry_rest_direction_and_twist():
    skel = chain(3)
    bones = skel.bones()
    pose = skel.rest_pose
    pose.rotation[0] = quat([0, 0, 1], 90)
    pose.rotation[1] = quat([1, 0, 0], 30)  # pure twist about the bone j1->j2
    pose.translation[0] = [0, 0, 5]
    segs, R = bones.pose(skel.forward_kinematics(pose))
    G = skel.forward_kinematics(pose)
    assert segs.shape == (3, 2, 3) and R.shape == (3, 3, 3)
    np.testing.assert_allclose(segs[0], G[[0, 1], :3, 3], atol=1e-12)
    rest_dir = bones.segments[:, 1] - bones.segments[:, 0]
    posed_dir = segs[:, 1] - segs[:, 0]
    np.testing.assert_allclose(np.einsum("bij,bj->bi", R, rest_dir), posed_dir, atol=1e-12)
    expected = Rotation.from_quat(pose.rotation[0]) * Rotation.from_quat(pose.rotation[1])
    np.testing.assert_allclose(R[1], expected.as_matrix(), atol=1e-12)  # twist included
    segs_batch, R_batch = bones.pose(skel.forward_kinematics(
        LocalPose(*(np.stack([getattr(skel.rest_pose, k), getattr(pose, k)]) for k in
                    ("translation", "rotation", "scale")))))
    np.testing.assert_allclose(segs_batch[0], bones.segments, atol=1e-12)
    np.testing.assert_allclose(R_batch[1], R, atol=1e-12)


def test_polar_rotation_fast_path_matches_the_svd():
    """Near-rotations times a uniform scale (float32 data, 1e-3 noise) take polar_rotation's
    Newton–Schulz fast path; the rest (axis scales, reflections) the SVD: both give the
    polar factor, orthonormal to rounding."""
    from scipy.spatial.transform import Rotation as Rot

    from nrpose.model.skeleton import polar_rotation

    def by_svd(A):
        U, _, Vt = np.linalg.svd(A)
        U[..., :, 2] *= np.sign(np.linalg.det(U @ Vt))[..., None]
        return U @ Vt

    R = Rot.random(70, random_state=3).as_matrix()
    A = np.concatenate([R[:20] * 2.5, R[20:30] @ np.diag([1.0, 2.0, 3.0]), R[30:40] @ np.diag([1.0, 1.0, -1.0]),
                        R[40:50] + 1e-3 * np.random.default_rng(0).normal(size=(10, 3, 3)), R[50:60] * 1e-4,
                        (R[60:] + 1e-7 * np.random.default_rng(1).normal(size=(10, 3, 3))).astype(np.float32)])
    out = polar_rotation(A.reshape(7, 10, 3, 3)).reshape(70, 3, 3)
    assert np.abs(out - by_svd(A)).max() <= 1e-12
    assert np.abs(out @ np.swapaxes(out, 1, 2) - np.eye(3)).max() <= 1e-12 and (np.linalg.det(out) > 0).all()


def test_polar_rotation_shapes_layouts_and_input_untouched():
    """One matrix, empty and one-element batches, strided and transposed views (the fast
    path works on component-major copies): same polar factor, input unchanged; other
    shapes are refused."""
    from scipy.spatial.transform import Rotation as Rot

    from nrpose.model.skeleton import polar_rotation

    R = Rot.random(12, random_state=5).as_matrix() * 1.7
    big = np.zeros((12, 3, 6))
    big[:, :, ::2] = R                                       # strided view of R
    for A in (R[0], R[:0], R[:1], big[:, :, ::2], np.swapaxes(R, 1, 2), np.asfortranarray(R[3])):
        before = np.array(A, copy=True)
        out = polar_rotation(A)
        assert out.shape == A.shape and np.array_equal(A, before)
        expect = np.stack([u @ vt for u, _, vt in (np.linalg.svd(m) for m in A.reshape(-1, 3, 3))]) \
            if A.size else np.zeros((0, 3, 3))
        np.testing.assert_allclose(out.reshape(-1, 3, 3), expect, atol=1e-12)
    for bad in (np.zeros(9), np.zeros((3, 6)), np.zeros((6, 3)), np.zeros(0)):
        with pytest.raises(InputError, match="3, 3"):
            polar_rotation(bad)


def _polar_by_svd(A):
    U, _, Vt = np.linalg.svd(A)
    U[..., :, 2] *= np.sign(np.linalg.det(U @ Vt))[..., None]
    return U @ Vt


def test_posed_bones_match_a_per_bone_reference():
    """Bones.pose (component-major, vectorised over frames and bones) against the plain
    per-frame, per-bone computation: each end through its joint's global matrix, the
    rotation the SVD polar factor of the joint's linear part times the rest one's inverse.
    Scales: uniform on most joints (the Newton–Schulz path), per axis on one (the SVD)."""
    rng = np.random.default_rng(11)
    parents = [-1, 0, 1, 2, 1, 4, 0]
    skel = make(parents, rng.normal(size=(7, 3)), rotation=Rotation.random(7, random_state=4).as_quat())
    bones = skel.bones()
    F = 6
    scale = np.repeat(rng.uniform(0.5, 2.0, size=(F, 7, 1)), 3, axis=2)
    scale[:, 4] = [1.0, 2.0, 0.5]                                     # non-uniform: SVD path
    pose = LocalPose(rng.normal(size=(F, 7, 3)), Rotation.random(F * 7, random_state=5).as_quat().reshape(F, 7, 4),
                     scale)
    G = skel.forward_kinematics(pose)
    ends, R = bones.pose(G)
    assert ends.shape == (F, len(bones), 2, 3) and R.shape == (F, len(bones), 3, 3)
    Gr = skel.rest_globals()
    for f in range(F):
        for b, j in enumerate(bones.joints):
            local = np.linalg.inv(Gr[j]) @ np.c_[bones.segments[b], np.ones(2)].T      # (4, 2)
            np.testing.assert_allclose(ends[f, b], (G[f, j] @ local)[:3].T, atol=1e-12)
            expect = _polar_by_svd(G[f, j, :3, :3]) @ _polar_by_svd(Gr[j, :3, :3]).T
            np.testing.assert_allclose(R[f, b], expect, atol=1e-12)
    one_ends, one_R = bones.pose(G[2])                              # no batch axis
    np.testing.assert_allclose(one_ends, ends[2], atol=1e-15)
    np.testing.assert_allclose(one_R, R[2], atol=1e-15)


def test_polar_components_layout_and_steps():
    """polar_components on component-major maps equals polar_rotation; exact rotations
    times a scale come back without a step (to rounding), float32-rounded ones orthonormal
    to 1e-14 after the steps the tolerance asks for."""
    from nrpose.model.skeleton import polar_components, polar_rotation
    R = Rotation.random(40, random_state=9).as_matrix()
    A = R * np.linspace(0.1, 10.0, 40)[:, None, None]
    out = polar_components(np.ascontiguousarray(np.moveaxis(A, 0, -1)))
    assert out.shape == (3, 3, 40)
    np.testing.assert_array_equal(np.moveaxis(out, -1, 0), polar_rotation(A))
    np.testing.assert_allclose(polar_rotation(A), R, atol=4e-16)
    R32 = R.astype(np.float32).astype(np.float64)                     # ~1e-7 off orthonormal
    P = polar_rotation(R32)
    assert np.abs(P @ np.swapaxes(P, 1, 2) - np.eye(3)).max() <= 1e-14
    np.testing.assert_allclose(P, _polar_by_svd(R32), atol=1e-14)
