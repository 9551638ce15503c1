"""Welding, smooth normals and neighbourhood rotations (nrpose.model.normals)."""
import numpy as np
from scipy.spatial.transform import Rotation

from nrpose.model.normals import Surface, closest_rotations, local_rotations, smooth_normals, weld


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


def svd_rotations(M):
    """The float64 oracle: the polar factor by SVD, its last axis flipped to det +1."""
    U, S, Vt = np.linalg.svd(M)
    flip = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= np.where(flip == 0, 1.0, flip)[:, None]
    return U @ Vt


def test_closest_rotations_equal_the_svd_polar_factor_on_random_and_adversarial_matrices():
    rng = np.random.default_rng(1)
    R = Rotation.random(600, random_state=2).as_matrix()
    # SPD stretches of condition 1 to 1e10: M = R C has the polar factor R
    axes = Rotation.random(600, random_state=3).as_matrix()
    stretch = 10.0 ** rng.uniform(-5, 5, size=(600, 3))
    C = np.einsum("nab,nb,ncb->nac", axes, stretch, axes)
    M = np.concatenate([R @ C, rng.normal(size=(400, 3, 3)),                 # any sign of det
                        np.zeros((2, 3, 3)), 1e-200 * rng.normal(size=(2, 3, 3)),
                        np.outer([1.0, 2, 3], [0.5, -1, 2])[None],           # rank 1
                        np.diag([1.0, 1.0, 0.0])[None], np.diag([1.0, 1.0, -1e-9])[None]])
    got = closest_rotations(M)
    assert np.abs(np.einsum("nba,nbc->nac", got, got) - np.eye(3)).max() < 1e-12
    assert np.allclose(np.linalg.det(got), 1.0, atol=1e-12)
    # the polar factor is as sensitive as the matrix is ill-conditioned: error <= 1e-15 x condition
    S = np.linalg.svd(M, compute_uv=False)
    cond = S[:, 0] / np.maximum(S[:, 2], 1e-300)
    assert (np.abs(got[:600] - R).max(axis=(1, 2)) < 1e-15 * cond[:600] + 1e-12).all()
    full_rank = cond < 1e12      # elsewhere the closest rotation is not unique
    err = np.abs(got[full_rank] - svd_rotations(M[full_rank])).max(axis=(1, 2))
    assert (err < 1e-15 * cond[full_rank] + 1e-12).all()
    assert np.allclose(got[1000:1002], np.eye(3))


def test_surface_reuse_equals_fresh_calls():
    V, F = sphere()
    groups = weld(V)
    surface = Surface(V, F, groups)
    rng = np.random.default_rng(4)
    for _ in range(3):
        posed = V + 0.05 * rng.normal(size=V.shape)
        assert np.array_equal(surface.rotations(posed), local_rotations(V, posed, F, groups))
        assert np.array_equal(surface.smooth_normals(posed), smooth_normals(posed, F, groups))
        assert np.abs(surface.rotations(posed) - svd_rotations(_neighbourhood_sums(V, posed, F, groups))).max() < 1e-9


def _neighbourhood_sums(bind, posed, F, groups):
    """The float64 oracle of the per-group sum e' e^T, summed face by face in a Python loop."""
    def frame(V, f):
        e1, e2 = V[f[1]] - V[f[0]], V[f[2]] - V[f[0]]
        n = np.cross(e1, e2)
        n = n / np.sqrt(max(np.linalg.norm(n), 1e-300))
        return np.stack([e1, e2, e2 - e1, n])
    total = np.zeros((groups.max() + 1, 3, 3))
    for f in F:
        a, b = frame(bind, f), frame(posed, f)
        for g in groups[f]:
            total[g] += b.T @ a
    return total[groups]
