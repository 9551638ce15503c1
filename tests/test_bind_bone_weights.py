"""bind.bone_weights: the one function behind the poser's and ``nrpose weights``' bone weights."""
import numpy as np
import pytest

from nrpose.bind.bone_weights import SKELETON_K, authored_joint_weights, bone_weights
from nrpose.bind.distances import point_segment_distances
from nrpose.bind.weights import dense_weights, keep_top_k
from nrpose.errors import InputError
from nrpose.model.character import Character
from nrpose.rigs.humanoid import humanoid


@pytest.fixture(scope="module")
def character():
    return humanoid()


def test_authored_weights_keep_each_joints_share(character):
    """Dense authored bone weights summed per owning joint give back the skin weights
    (a weighted joint without a bone hands its weight to its nearest ancestor with one)."""
    res = bone_weights(character, "authored", k="all")
    skel, bones = character.skeleton, res.bones
    jw = authored_joint_weights(character.meshes, skel.num_joints)
    owner = np.arange(skel.num_joints)
    for j in range(skel.num_joints):
        while owner[j] >= 0 and owner[j] not in bones.joints:
            owner[j] = skel.parents[owner[j]]
    expected = np.zeros_like(jw)
    np.add.at(expected.T, owner, jw.T)
    got = np.zeros_like(jw)
    np.add.at(got.T, bones.joints, res.weights.T)
    assert res.k == len(bones)
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_distance_weights_are_the_top_k_of_inverse_distances(character):
    res = bone_weights(character, "euclidean", k=3, alpha=1.5)
    D = point_segment_distances(res.meshes.vertices, res.bones.segments)[0]
    np.testing.assert_allclose(res.distances, D)
    np.testing.assert_allclose(res.weights, keep_top_k(dense_weights(D, 1.5), 3), atol=1e-15)
    assert (np.count_nonzero(res.weights, axis=1) <= 3).all()
    np.testing.assert_allclose(res.weights.sum(axis=1), 1.0)


def test_default_k_and_bad_arguments(character):
    B = len(character.skeleton.bones())
    assert bone_weights(character, "euclidean").k == (SKELETON_K if B > SKELETON_K else B)
    assert bone_weights(character, "euclidean", k=10_000).k == B
    with pytest.raises(InputError, match="weights must be one of"):
        bone_weights(character, "nope")
    with pytest.raises(InputError, match="k must be"):
        bone_weights(character, "euclidean", k=0)
    with pytest.raises(InputError, match="skeleton="):
        bone_weights(Character(character.skeleton), "euclidean")


def dense_joint_to_bone_weights(joint_w, D, bone_joints, parents):
    """The float64 reference: (V, B) from dense (V, J) joint weights and all (V, B) distances."""
    J = joint_w.shape[1]
    owner = np.arange(J)
    for j in range(J):
        while owner[j] >= 0 and owner[j] not in bone_joints:
            owner[j] = parents[owner[j]]
    jw = np.zeros_like(joint_w)
    for j in range(J):
        if owner[j] >= 0:
            jw[:, owner[j]] += joint_w[:, j]
    share = 1.0 / np.maximum(D ** 2, 1e-12)
    per_joint = np.zeros((len(D), J))
    for b, j in enumerate(bone_joints):
        per_joint[:, j] += share[:, b]
    return jw[:, bone_joints] * share / per_joint[:, bone_joints]


def check_against_dense(meshes, skel):
    from nrpose.bind.bone_weights import authored_bone_weights
    bones = skel.bones()
    X = np.concatenate([m.vertices for m in meshes])
    ref = dense_joint_to_bone_weights(authored_joint_weights(meshes, skel.num_joints),
                                      point_segment_distances(X, bones.segments)[0], bones.joints, skel.parents)
    got = authored_bone_weights(meshes, X, bones, skel.parents)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
    assert ((got == 0) == (ref == 0)).all()


def test_authored_bone_weights_equal_the_dense_reference(character):
    check_against_dense(character.meshes, character.skeleton)


def test_authored_bone_weights_adversarial():
    """Joints with several bones, a weighted joint without a bone (its weight goes to the
    parent), a zero-length bone, vertices on a bone (distance 0), repeated joints in a row,
    zero weights, two meshes."""
    from nrpose.bind.bone_weights import authored_bone_weights
    from nrpose.model.character import Mesh
    from nrpose.model.skeleton import Skeleton
    rng = np.random.default_rng(7)
    # root(0) -> a(1) -> {b(2), c(3) at a's place: zero-length bone a->c}, b -> tip(4), root -> d(5) leaf
    parents = np.array([-1, 0, 1, 1, 2, 0])
    pos = np.array([[0, 0, 0], [0, 1, 0], [0, 1, 1], [0, 0, 0], [0, 0, 1], [1, 0, 0.0]])
    skel = Skeleton(tuple("root a b c tip d".split()), parents, pos, np.tile([0.0, 0, 0, 1], (6, 1)), np.ones((6, 3)))
    bones = skel.bones()
    assert len(set(bones.joints.tolist())) < len(bones.joints)      # some joint has several bones
    X = rng.normal(size=(300, 3))
    X[:5] = skel.rest_globals()[[0, 1, 2, 4, 5], :3, 3]               # on the joints (on bones)
    joints = rng.integers(0, 6, size=(300, 4))
    joints[10:20, 1] = joints[10:20, 0]                               # the same joint twice in a row
    w = rng.uniform(size=(300, 4))
    w[20:40, 2:] = 0.0                                                # zero weights
    m1 = Mesh("one", X[:120], np.zeros((0, 3), np.int64), joints[:120], w[:120])
    m2 = Mesh("two", X[120:], np.zeros((0, 3), np.int64), joints[120:, :3], w[120:, :3])
    check_against_dense([m1, m2], skel)
    # a weighted joint none of whose ancestors drives a bone
    lone = Skeleton(("r", "x"), np.array([-1, -1]), np.zeros((2, 3)) + [[0, 0, 0], [5, 0, 0]],
                    np.tile([0.0, 0, 0, 1], (2, 1)), np.ones((2, 3)))
    bad = Mesh("bad", X[:3], np.zeros((0, 3), np.int64), np.array([[1], [1], [1]]), np.ones((3, 1)))
    with pytest.raises(InputError, match="joint 1 carries skin weight"):
        authored_bone_weights([bad], X[:3], lone.bones(), lone.parents)


def test_segment_parameters_come_with_the_weights(character):
    """authored: one bone-weight row and one parameter row per weight group (their centroid's);
    euclidean: closest points (t None); heat: arrival parameters, or None when not asked for."""
    from nrpose.bind.bone_weights import group_centers
    from nrpose.bind.distances import arrival_parameters, segment_parameters
    from nrpose.model.deformation_metrics import weight_groups

    res = bone_weights(character, "authored", k="all")
    V, segs = res.meshes.vertices, res.bones.segments
    labels = weight_groups(authored_joint_weights(character.meshes, character.skeleton.num_joints))
    np.testing.assert_allclose(res.t, segment_parameters(group_centers(V, labels), segs), atol=1e-12)
    for g in np.unique(labels[labels >= 0])[:20]:
        rows = res.weights[labels == g]
        assert np.ptp(rows, axis=0).max() <= 1e-6          # groups agree to 6 decimals
    assert bone_weights(character, "euclidean").t is None
    assert bone_weights(character, "graph", parameters=False).t is None
    t = bone_weights(character, "graph").t
    np.testing.assert_allclose(t, arrival_parameters(V, res.meshes.faces, segs))
