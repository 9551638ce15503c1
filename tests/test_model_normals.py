"""Welding, smooth normals and neighbourhood rotations (nrpose.model.normals)."""
import numpy as np
from scipy.spatial.transform import Rotation

from nrpose.model.normals import local_rotations, smooth_normals, weld


def sphere(n=12):
    """A UV sphere whose seam column is duplicated (as texture seams are): vertices, faces."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n + 1), np.linspace(0.2, np.pi - 0.2, n))
    V = np.stack([np.sin(v) * np.cos(u), np.cos(v), np.sin(v) * np.sin(u)], axis=-1).reshape(-1, 3)
    idx = np.arange(n * (n + 1)).reshape(n, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    F = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return V, F[:, ::-1].copy()   # counter-clockwise seen from outside


def test_weld_joins_seams_and_smooth_normals_cross_them():
    V, F = sphere()
    groups = weld(V)
    n = 12
    seam = np.arange(n) * (n + 1)
    assert (groups[seam] == groups[seam + n]).all() and len(np.unique(groups)) == n * n
    N = smooth_normals(V, F, groups)
    assert np.allclose(N[seam], N[seam + n])                  # no crease at the texture seam
    inner = np.arange(n + 1, len(V) - n - 1)   # away from the open rims, a sphere's normal is radial
    assert np.degrees(np.arccos(np.einsum("na,na->n", N[inner], V[inner] / np.linalg.norm(V[inner], axis=1,
                                                                                      keepdims=True)))).max() < 6


def test_local_rotations_exact_for_rigid_motion_and_proper_otherwise():
    V, F = sphere()
    groups = weld(V)
    R = Rotation.from_rotvec([0.4, -1.9, 0.7]).as_matrix()
    got = local_rotations(V, V @ R.T + [1.0, 2.0, 3.0], F, groups)
    assert np.abs(got - R).max() < 1e-12
    # a twist about y: every vertex's rotation is orthonormal with det +1, close to the local twist
    rng = np.random.default_rng(0)
    angle = 0.8 * V[:, 1]
    twist = Rotation.from_rotvec(angle[:, None] * [0, 1, 0]).as_matrix()
    posed = np.einsum("nab,nb->na", twist, V) + 1e-3 * rng.normal(size=V.shape)
    got = local_rotations(V, posed, F, groups)
    assert np.abs(np.einsum("nba,nbc->nac", got, got) - np.eye(3)).max() < 1e-12
    assert np.allclose(np.linalg.det(got), 1.0)
    off = np.degrees(Rotation.from_matrix(np.einsum("nba,nbc->nac", twist, got)).magnitude())
    assert off.max() < 10
    # a vertex in no face keeps the identity
    lone = local_rotations(np.r_[V, [[5.0, 5, 5]]], np.r_[posed, [[6.0, 5, 5]]], F, weld(np.r_[V, [[5.0, 5, 5]]]))
    assert np.allclose(lone[-1], np.eye(3))
