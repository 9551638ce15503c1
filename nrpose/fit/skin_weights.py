"""Linear blend skinning weights fitted to example poses (non-negative, summing to one, k per vertex).

For vertex n with homogeneous source position ``b_n`` (glTF bind space), candidate
joints ``c`` and per-frame skinning matrices ``M_f[c]`` (``G_f[c] @ inverse_bind_c``),
LBS gives ``x_fn = sum_c w_c M_f[c] b_n``. Given target positions ``y_fn`` over F
frames the weights minimise

    sum_f || sum_c w_c M_f[c] b_n - y_fn ||^2   subject to  w >= 0,  sum_c w_c = 1.

With ``sum w = 1`` the residual is ``D w`` with ``D[f, :, c] = M_f[c] b_n - y_fn``, so
the objective is ``w^T K w``, ``K = D^T D`` (C x C per vertex, over all frames, in
vertex chunks). Each vertex is solved as a small NNLS (:func:`scipy.optimize.nnls`)
on ``[R; s 1^T] w ≈ [0; s]`` with ``R^T R = K`` (negative rounding of eigenvalues set to 0) and a sum row of
weight ``s = SUM_WEIGHT * sqrt(trace K)``; the result is then divided by its sum. The
``influences`` largest weights are kept and the NNLS is solved again on them alone.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from ..errors import InputError

__all__ = ["candidate_joints", "fit_weights", "skin_positions", "MAX_CANDIDATES"]

MAX_CANDIDATES = 16   # authored joints first, then their parents, then their children
SUM_WEIGHT = 1e3      # sum-to-one row weight relative to sqrt(trace K)
CHUNK_BYTES = 1 << 27  # memory of a vertex chunk's joint positions (3F, J, n) and D (n, C, 3F) float64


def candidate_joints(parents: np.ndarray, joints: np.ndarray, weights: np.ndarray,
                     allowed: np.ndarray | None = None, limit: int = MAX_CANDIDATES) -> np.ndarray:
    """Candidate joints per vertex: (N, C) int64, -1 padded, C <= limit.

    parents: (J,) skeleton parents (-1 roots); joints, weights: (N, K) authored influences
    (joints with weight > 0 count); allowed: (J,) bool joints that may be used (e.g. those of
    the mesh's skin), all by default. Order: authored by decreasing weight, their parents,
    their children.
    """
    parents = np.asarray(parents, np.int64)
    J = len(parents)
    allowed = np.ones(J, bool) if allowed is None else np.asarray(allowed, bool)
    order = np.argsort(-weights, axis=1, kind="stable")
    ranked = np.where(np.take_along_axis(weights, order, 1) > 0, np.take_along_axis(joints, order, 1), -1)
    rows, inverse = np.unique(ranked, axis=0, return_inverse=True)
    children = [np.flatnonzero(parents == j) for j in range(J)]
    table = np.full((len(rows), limit), -1, np.int64)
    for r, row in enumerate(rows):
        own = [int(j) for j in row if j >= 0]
        found = list(dict.fromkeys(own + [int(parents[j]) for j in own if parents[j] >= 0]
                                   + [int(c) for j in own for c in children[j]]))
        found = [j for j in found if allowed[j]][:limit]
        table[r, :len(found)] = found
    width = max(int((table >= 0).sum(axis=1).max()), 1)
    return table[inverse.reshape(-1), :width]


def _gram(source: np.ndarray, mats: np.ndarray, targets: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """K (N, C, C) float64 of the module docstring (zero rows/columns for -1 candidates).

    Per vertex chunk, every joint's position of every vertex in every frame is one matrix
    product ``(3F*J, 4) @ (4, n)``; the candidates' columns of ``D`` are gathered from it and
    ``K = D D^T`` is a batched product (no expanded sums: no digits cancel).
    """
    F, J = mats.shape[:2]
    N, C = candidates.shape
    A = mats[:, :, :3, :].transpose(0, 2, 1, 3).reshape(3 * F * J, 4)   # rows (f, i, j)
    K = np.empty((N, C, C))
    chunk = max(1, CHUNK_BYTES // (3 * F * (J + C) * 8))
    for a in range(0, N, chunk):
        b = min(a + chunk, N)
        cand = candidates[a:b]
        valid = cand >= 0
        P = (A @ np.c_[source[a:b], np.ones(b - a)].T).reshape(3 * F, J, b - a)
        rows = np.arange(b - a)[:, None]
        D = P[:, np.where(valid, cand, 0), rows].transpose(1, 2, 0)        # (n, C, 3F)
        D = (D - targets[:, a:b].transpose(1, 0, 2).reshape(b - a, 1, 3 * F)) * valid[:, :, None]
        K[a:b] = D @ D.transpose(0, 2, 1)
    return K


def _solve(K: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Weights (C,) >= 0 summing to 1 minimising w^T K w over the valid columns."""
    C = len(K)
    scale = max(float(np.trace(K)), 1e-300)
    lam, vec = np.linalg.eigh(K)           # K is PSD up to rounding
    R = np.sqrt(np.maximum(lam, 0.0))[:, None] * vec.T
    s = SUM_WEIGHT * np.sqrt(scale)
    A = np.vstack([R, s * valid.astype(np.float64)])
    rhs = np.zeros(C + 1)
    rhs[-1] = s
    w, _ = nnls(A, rhs, maxiter=50 * C)
    total = w.sum()
    if not total > 0:      # no usable column: all weight on the first candidate
        w = np.zeros(C)
        w[0] = 1.0
        return w
    return w / total


def fit_weights(source, mats, targets, candidates, influences: int) -> tuple[np.ndarray, np.ndarray]:
    """Fitted LBS influences of N vertices.

    source: (N, 3) positions the skinning matrices apply to; mats: (F, J, 4, 4) skinning
    matrices per frame; targets: (F, N, 3) positions to reproduce; candidates: (N, C) int64
    joints per vertex (-1 padding, at least one valid per vertex, see :func:`candidate_joints`);
    influences: k >= 1. Returns joints (N, k) int64 and weights (N, k) float64 (>= 0, rows sum
    to 1, unused slots weight 0 on the vertex's first joint), largest weight first.
    """
    source = np.asarray(source, np.float64)
    mats = np.asarray(mats, np.float64)
    targets = np.asarray(targets, np.float64)
    candidates = np.asarray(candidates, np.int64)
    N = len(source)
    if influences < 1:
        raise InputError(f"influences must be >= 1, got {influences}")
    if source.shape != (N, 3) or mats.ndim != 4 or mats.shape[2:] != (4, 4) or targets.shape != (len(mats), N, 3):
        raise InputError(f"fit_weights: shapes source {source.shape}, mats {mats.shape}, targets "
                         f"{targets.shape} do not match (N, 3), (F, J, 4, 4), (F, N, 3)")
    if len(mats) == 0:
        raise InputError("fit_weights needs at least one training pose")
    if candidates.ndim != 2 or len(candidates) != N or (candidates[:, 0] < 0).any() \
            or candidates.max() >= mats.shape[1]:
        raise InputError(f"candidates: expected (N={N}, C) joint indices below {mats.shape[1]}, "
                         "a valid joint first in each row")
    if not (np.isfinite(source).all() and np.isfinite(mats).all() and np.isfinite(targets).all()):
        raise InputError("fit_weights: NaN or infinite input")
    K = _gram(source, mats, targets, candidates)
    k = min(influences, candidates.shape[1])
    joints = np.repeat(candidates[:, :1], influences, axis=1)
    weights = np.zeros((N, influences))
    for n in range(N):
        valid = candidates[n] >= 0
        w = _solve(K[n], valid)
        keep = np.argsort(-w, kind="stable")[:k]
        keep = keep[valid[keep]]
        if len(keep) < np.count_nonzero(valid):
            w_keep = _solve(K[n][np.ix_(keep, keep)], np.ones(len(keep), bool))
        else:
            w_keep = w[keep]
        order = np.argsort(-w_keep, kind="stable")
        joints[n, :len(keep)] = candidates[n, keep[order]]
        weights[n, :len(keep)] = w_keep[order]
    joints[weights == 0] = joints[:, :1].repeat(influences, axis=1)[weights == 0]
    return joints, weights


def skin_positions(source, mats, joints, weights) -> np.ndarray:
    """LBS positions (F, N, 3) float64 of source (N, 3) with influences (N, k) under mats (F, J, 4, 4)."""
    mats = np.asarray(mats, np.float64)
    out = np.empty((len(mats), len(source), 3))
    for f, mf in enumerate(mats):          # one frame at a time: (N, k, 3, 4) gathered matrices
        M = np.einsum("nk,nkij->nij", weights, mf[joints, :3, :])
        out[f] = np.einsum("nij,nj->ni", M[..., :3], source) + M[..., 3]
    return out
