"""The embedded capsule humanoid: mesh, skeleton, skin weights and walk clip."""
import time

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from nrpose.model.character import Character, Clip
from nrpose.rigs.humanoid import JOINT_NAMES, humanoid


@pytest.fixture(scope="module")
def built():
    t0 = time.perf_counter()
    c = humanoid()
    return c, time.perf_counter() - t0


@pytest.fixture(scope="module")
def character(built):
    return built[0]


def lbs(character, G):
    """Reference linear blend skinning of the body at globals G (F, J, 4, 4)."""
    m = character.meshes[0]
    K = character.skin_matrices(G)
    M = np.einsum("nk,fnkab->fnab", m.weights, K[:, m.joints])
    return np.einsum("fnab,nb->fna", M, np.c_[m.vertices, np.ones(len(m.vertices))])[..., :3]


def test_build_is_deterministic(built):
    c, _ = built
    again = humanoid()
    assert np.array_equal(c.meshes[0].vertices, again.meshes[0].vertices)
    assert np.array_equal(c.meshes[0].faces, again.meshes[0].faces)
    assert np.array_equal(c.meshes[0].weights, again.meshes[0].weights)


def test_closed_manifold_mesh(character):
    assert isinstance(character, Character) and len(character.meshes) == 1
    m = character.meshes[0]
    V, F = m.vertices, m.faces
    assert 8_000 <= len(V) <= 15_000
    assert V.dtype == np.float64 and F.dtype == np.int64 and F.shape[1] == 3
    # every undirected edge in exactly two faces, with opposite directions (closed, oriented)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    directed = np.unique(e, axis=0)
    assert len(directed) == len(e)                     # no directed edge twice
    und, counts = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    assert (counts == 2).all()
    assert len(V) - len(und) + len(F) == 2            # sphere topology
    A = sp.coo_matrix((np.ones(len(und)), (und[:, 0], und[:, 1])), shape=(len(V),) * 2)
    assert connected_components(A, directed=False)[0] == 1
    tri = V[F]
    volume = np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6
    assert 0.03 < volume < 0.12                       # outward orientation, human-like volume (m^3)


def test_proportions(character):
    V = character.meshes[0].vertices
    lo, hi = V.min(axis=0), V.max(axis=0)
    assert lo[1] == 0.0 and 1.7 < hi[1] < 1.9         # feet on y = 0, ~1.8 tall
    assert np.allclose(lo[0], -hi[0], atol=1e-9)       # left/right symmetric
    assert hi[2] - lo[2] < 0.45                        # a body, not a blob


def test_skeleton(character):
    sk = character.skeleton
    assert 15 <= sk.num_joints <= 21 and sk.names == JOINT_NAMES
    for name in ("Hips", "Spine", "Chest", "Neck", "Head", "LeftUpperArm", "RightHand",
                 "LeftUpLeg", "RightFoot", "LeftToe"):
        sk.index(name)
    assert sk.parents[0] == -1 and (sk.parents[1:] >= 0).all()
    assert np.allclose(character.inverse_bind, np.linalg.inv(sk.rest_globals()))
    # joints lie inside the body: on the capsule axes, below the head top, above the ground
    P = sk.rest_globals()[:, :3, 3]
    assert (P[:, 1] > 0).all() and (P[:, 1] < 1.8).all()
    left = [j for j, n in enumerate(sk.names) if n.startswith("Left")]
    for j in left:
        k = sk.index("Right" + sk.names[j][4:])
        assert np.allclose(P[k], P[j] * [-1, 1, 1])


def test_skin_weights(character):
    m = character.meshes[0]
    assert m.joints.shape == (len(m.vertices), 4) and m.weights.shape == m.joints.shape
    assert m.joints.dtype == np.int64 and m.joints.min() >= 0
    assert m.joints.max() < character.skeleton.num_joints
    assert (m.weights >= 0).all() and np.allclose(m.weights.sum(axis=1), 1.0, atol=1e-12)
    # every joint influences something, and the left leg never follows the right one
    names = character.skeleton.names
    used = np.unique(m.joints[m.weights > 0])
    assert set(used) == set(range(len(names)))
    foot = m.joints[:, 0] == names.index("LeftFoot")
    right = [j for j, n in enumerate(names) if n.startswith("Right")]
    assert not np.isin(m.joints[foot][m.weights[foot] > 0], right).any()


def test_skin_at_rest_is_identity(character):
    G = character.skeleton.rest_globals()
    K = character.skin_matrices(G)
    assert np.allclose(K, np.eye(4), atol=1e-12)
    posed = lbs(character, G[None])[0]
    assert np.allclose(posed, character.meshes[0].vertices, atol=1e-12)


def test_walk_clip(character):
    clip = character.clip("walk")
    assert isinstance(clip, Clip) and clip.duration == pytest.approx(1.0)
    assert all(tr.interpolation == "LINEAR" and len(tr.times) == 30 for tr in clip.tracks)
    t = np.linspace(0.0, clip.duration, 31)
    pose = clip.sample(t)
    G = character.skeleton.forward_kinematics(pose)
    assert np.isfinite(G).all()
    assert np.allclose(np.linalg.norm(pose.rotation, axis=-1), 1.0)
    sk = character.skeleton
    feet = G[:, [sk.index("LeftFoot"), sk.index("RightFoot")]][..., :3, 3]
    hips = G[:, 0, :3, 3]
    rel = feet - hips[:, None]
    # the feet swing relative to the hips, in opposition
    assert np.ptp(rel[:, 0, 2]) > 0.3 and np.ptp(rel[:, 1, 2]) > 0.3
    assert np.corrcoef(rel[:, 0, 2], rel[:, 1, 2])[0, 1] < -0.5
    # the arms swing against the legs on the same side
    hand = G[:, sk.index("LeftHand"), 2, 3] - hips[:, 2]
    assert np.ptp(hand) > 0.15 and np.corrcoef(hand, rel[:, 0, 2])[0, 1] < -0.5
    # root: moves forward (+z), bobs, comes back to the same height; the loop closes
    assert 0.8 < hips[-1, 2] - hips[0, 2] < 1.8
    assert 0.01 < np.ptp(hips[:, 1]) < 0.08
    start, end = clip.sample(0.0), clip.sample(clip.duration)
    assert np.allclose(np.abs(np.sum(start.rotation * end.rotation, axis=-1)), 1.0, atol=1e-9)
    assert np.allclose(start.translation[0, :2], end.translation[0, :2], atol=1e-9)
    # skinned: finite, the lowest point stays on the ground, nothing sinks into it
    V = lbs(character, G)
    assert np.isfinite(V).all()
    low = V[..., 1].min(axis=1)
    assert (low > -0.01).all() and (low < 0.01).all()
