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
