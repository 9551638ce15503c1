"""Skinning with optimized centers of rotation (CoR; Le & Hodgins 2016): the device deformer
:class:`CorSkinner` (kernels/cor.cl through :class:`nrpose.pose.skinning.Skinner`) and its
float64 reference :func:`cor_reference`.

Inputs as for :mod:`nrpose.pose.skinning`: rest vertices (N, 3), influences ``joints``
(N, K) int and ``weights`` (N, K) (rows normalised at bind), skinning matrices
``mats`` (J, 4, 4) = ``G_j @ IBM_j``; plus the rest triangles (M, 3) for the bind.

Bind (rest only): each vertex i gets a center of rotation

    c_i = Σ_t s(w_i, w_t) A_t v_t / Σ_t s(w_i, w_t) A_t

over the rest triangles t (area A_t, centroid v_t, weights w_t = mean of its three
vertices' weights), with the paper's weight similarity

    s(w_p, w_v) = Σ_{j≠k} w_pj w_pk w_vj w_vk exp(−(w_pj w_vk − w_pk w_vj)² / σ²),  σ = 0.1.

Approximation (stated): one-point quadrature per triangle (centroid, mean weights) on
the mesh as given, optionally after ``subdivide`` rounds of 1→4 midpoint subdivision
(weights interpolated linearly); the paper subdivides adaptively until the weights in a
triangle differ by less than ε = 0.1. The sum is exact otherwise: it runs over the pairs
(j, k) of influences, each pair only over the vertices and triangles that carry both
(the similarity vanishes elsewhere), in chunks of bounded memory. Vertices with zero
total similarity (one influence, or no triangle sharing two of their influences) keep
c_i = v_i: with one influence the result does not depend on c. Without triangles (a point
cloud) each vertex is a sample of area 1.

Pose: per vertex, the unit quaternion ``q = Σ w_j s_j q_j / |Σ w_j s_j q_j|`` of the
joints' rotations (polar factors of the 3×3 blocks, as DQS; signs s_j put q_j in the
hemisphere of the vertex's dominant joint), and

    v' = R(q) (v − c) + Σ_j w_j M_j c          (LBS of the center)

Properties (tests): one rigid transform for every joint gives exactly that transform;
a vertex on one joint moves with it rigidly; vertices sharing one weight set share c,
R and the translation, so such a part moves rigidly; a global rigid motion commutes.
"""
from __future__ import annotations

import numpy as np

from ..checks import triangles
from ..errors import InputError
from .skinning import Skinner, dual_quaternions, lbs_reference, prepare_influences

SIGMA = 0.1
#: (vertices × triangles) products per chunk of the center sums
CHUNK = 1 << 22


def subdivide(V: np.ndarray, F: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One round of 1→4 midpoint subdivision of (V (N, 3), F (M, 3), W (N, J) dense weights)."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(E, axis=0, return_inverse=True)
    mid = len(V) + inv.reshape(3, -1).T                       # (M, 3): midpoints of edges 01, 12, 20
    V2 = np.concatenate([V, 0.5 * (V[uniq[:, 0]] + V[uniq[:, 1]])])
    W2 = np.concatenate([W, 0.5 * (W[uniq[:, 0]] + W[uniq[:, 1]])])
    a, b, c = F.T
    m01, m12, m20 = mid.T
    F2 = np.concatenate([np.stack(x, 1) for x in ((a, m01, m20), (m01, b, m12), (m20, m12, c), (m01, m12, m20))])
    return V2, F2, W2


def similarity(wp: np.ndarray, wv: np.ndarray, sigma: float = SIGMA) -> np.ndarray:
    """s(w_p, w_v) (P, T) of dense weight rows wp (P, J) and wv (T, J) (direct formula, O(P T J²))."""
    a = wp[:, None, :, None] * wv[None, :, None, :]            # w_pj w_vk  (P, T, J, J)
    prod = a * np.swapaxes(a, 2, 3)                            # w_pj w_vk w_pk w_vj
    diff = a - np.swapaxes(a, 2, 3)                            # w_pj w_vk − w_pk w_vj
    J = wp.shape[1]
    off = ~np.eye(J, dtype=bool)
    return np.sum(np.where(off, prod * np.exp(-(diff / sigma) ** 2), 0.0), axis=(2, 3))


def dense(joints: np.ndarray, weights: np.ndarray, J: int) -> np.ndarray:
    """(N, J) dense weights from (N, K) influences."""
    W = np.zeros((len(joints), J))
    np.add.at(W, (np.repeat(np.arange(len(joints)), joints.shape[1]), joints.ravel()), weights.ravel())
    return W


def centers(rest, faces, joints, weights, sigma: float = SIGMA, subdivisions: int = 0) -> np.ndarray:
    """Centers of rotation (N, 3) float64 (see the module docstring).

    faces: (M, 3) rest triangles, or None for a point cloud. sigma > 0."""
    V, joints, weights, max_joint = prepare_influences(rest, joints, weights)
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"sigma must be a positive number, got {sigma!r}")
    J = max_joint + 1
    W = dense(joints, weights, J)
    if faces is None:
        Vt, Wt, At = V, W, np.ones(len(V))
    else:
        F = triangles(faces, len(V))
        Vs, Fs, Ws = V, F, W
        for _ in range(int(subdivisions)):
            Vs, Fs, Ws = subdivide(Vs, Fs, Ws)
        Vt = Vs[Fs].mean(axis=1)
        Wt = Ws[Fs].mean(axis=1)
        At = 0.5 * np.linalg.norm(np.cross(Vs[Fs[:, 1]] - Vs[Fs[:, 0]], Vs[Fs[:, 2]] - Vs[Fs[:, 0]]), axis=1)
    num = np.zeros((len(V), 3))
    den = np.zeros(len(V))
    # each unordered pair (j, k) contributes 2 w_pj w_pk w_vj w_vk exp(...) (the ordered
    # pairs (j, k) and (k, j) give equal terms); the factor 2 cancels in the ratio
    on_v, on_t = W > 0, Wt > 0
    pairs = np.unique(np.sort(np.stack(np.nonzero(np.triu(on_v.T.astype(int) @ on_v.astype(int), 1)), 1), axis=1),
                      axis=0)
    for j, k in pairs:
        vi = np.flatnonzero(on_v[:, j] & on_v[:, k])
        ti = np.flatnonzero(on_t[:, j] & on_t[:, k])
        if len(vi) == 0 or len(ti) == 0:
            continue
        wt_j, wt_k = Wt[ti, j], Wt[ti, k]
        coef = At[ti] * wt_j * wt_k
        step = max(1, CHUNK // len(ti))
        for a in range(0, len(vi), step):
            v = vi[a:a + step]
            wj, wk = W[v, j][:, None], W[v, k][:, None]
            s = wj * wk * coef[None] * np.exp(-((wj * wt_k[None] - wk * wt_j[None]) / sigma) ** 2)
            den[v] += s.sum(axis=1)
            num[v] += s @ Vt[ti]
    C = V.copy()
    ok = den > 0
    C[ok] = num[ok] / den[ok, None]
    return C


def blended_rotations(joints: np.ndarray, weights: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """Per-vertex unit quaternions (N, 4) xyzw: the weighted sum of the joints' quats (J, 4),
    each in the hemisphere of the vertex's dominant (first largest weight) joint's, normalised."""
    Q = quats[joints]                                            # (N, K, 4)
    dom = Q[np.arange(len(joints)), np.argmax(weights, axis=1)]
    sign = np.where(np.einsum("nkc,nc->nk", Q, dom) < 0, -1.0, 1.0)
    q = np.einsum("nk,nkc->nc", weights * sign, Q)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quat_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of unit quaternions (N, 4) xyzw."""
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def cor_reference(rest, joints, weights, mats, centers_) -> np.ndarray:
    """CoR skinning in float64: posed vertices (N, 3). centers_: (N, 3) from :func:`centers`."""
    V, joints, weights, _ = prepare_influences(rest, joints, weights)
    C = np.asarray(centers_, np.float64)
    if C.shape != V.shape or not np.isfinite(C).all():
        raise InputError(f"centers: expected finite values of shape {V.shape}, got {np.shape(centers_)}")
    lbs_c = lbs_reference(C, joints, weights, mats)            # validates mats as LBS does
    R = quat_matrices(blended_rotations(joints, weights, dual_quaternions(mats)[:, :4]))
    return np.einsum("nij,nj->ni", R, V - C) + lbs_c


class CorSkinner(Skinner):
    """CoR skinning on the device: ``CorSkinner(rest, joints, weights, faces).pose(mats)``.

    faces: (M, 3) rest triangles (None: a point cloud); the centers of rotation
    (:func:`centers`, sigma, subdivisions) are computed at bind and kept as ``centers`` (N, 3)."""

    def __init__(self, rest, joints, weights, faces, sigma: float = SIGMA, subdivisions: int = 0):
        self.centers = centers(rest, faces, joints, weights, sigma, subdivisions)
        super().__init__(rest, joints, weights, method="cor", centers=self.centers)
