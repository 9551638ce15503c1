"""Blend weights from a distance matrix, dense or sparse (top-k).

The seed paper weights handle ``i`` at a point by ``w_i = 1 / d_i^(2α)``.
Computed literally this overflows for ``d → 0`` and underflows for large
``α``; the blend only needs the weights up to a common factor per point, so
we use ``w_i = (d_min / d_i)^(2α)`` with ``d_min`` the row's smallest
distance: every weight lies in ``[0, 1]``, the nearest handle gets 1. A row
whose smallest distance is exactly 0 gives weight 1 to the handles at
distance 0 and 0 to the others (the point sits on a handle).

Sparsity: keeping only the ``k`` most influential handles per point (top-k by
weight, i.e. the ``k`` smallest distances; ties go to the lower handle index)
bounds the per-point cost at ``k`` instead of ``H``. The result is
``(indices (N, k) int32, weights (N, k) float64)`` with rows summing to 1,
sorted by decreasing weight. :func:`deviation` reports what the truncation
costs: the max and RMS distance between the sparse and the dense deformation.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..model.handles import check_alpha

__all__ = ["relative_weights", "dense_weights", "keep_top_k", "deviation"]


def _check_D(D) -> np.ndarray:
    D = np.asarray(D, dtype=np.float64)
    if D.ndim != 2 or D.shape[0] == 0 or D.shape[1] == 0:
        raise InputError(f"distance matrix must have shape (N, H) with N, H > 0, got {D.shape}")
    if not np.isfinite(D).all():
        raise InputError("distance matrix contains NaN or inf")
    if (D < 0).any():
        raise InputError("distance matrix contains negative distances")
    return D


def relative_weights(D, alpha: float = 1.0) -> np.ndarray:
    """Un-normalised weights (N, H) ``(d_min / d)^(2α)`` in [0, 1]; rows whose
    minimum is 0 get 1 at the zero entries and 0 elsewhere."""
    D = _check_D(D)
    a2 = 2.0 * check_alpha(alpha)
    dmin = D.min(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore", under="ignore"):
        W = np.where(D > 0, dmin / np.where(D > 0, D, 1.0), 1.0) ** a2
    zero_rows = dmin[:, 0] == 0
    if zero_rows.any():
        W[zero_rows] = (D[zero_rows] == 0).astype(np.float64)
    return W


def dense_weights(D, alpha: float = 1.0) -> np.ndarray:
    """Weights (N, H) normalised per row to sum 1."""
    W = relative_weights(D, alpha)
    return W / W.sum(axis=1, keepdims=True)


def keep_top_k(W: np.ndarray, k: int | None) -> np.ndarray:
    """Dense weights (N, H) keeping only the k largest of each row (ties: lower
    handle index), renormalised to sum 1; ``k=None`` or k ≥ H returns W as is."""
    if k is None or k >= W.shape[1]:
        return W
    if isinstance(k, bool) or int(k) != k or k < 1:
        raise InputError(f"k must be a positive integer, got {k!r}")
    k = int(k)
    # the k-th largest value of each row by partition (O(H), not a sort), then every
    # larger entry and, of the entries equal to it, the lowest-index ones up to k
    kth = -np.partition(-W, k - 1, axis=1)[:, k - 1:k]
    above = W > kth
    tied = W == kth
    keep = above | tied
    over = keep.sum(axis=1) > k                   # rows with more ties than room (few)
    if over.any():
        t, a = tied[over], above[over]
        keep[over] = a | (t & (np.cumsum(t, axis=1) <= k - a.sum(axis=1, keepdims=True)))
    W = np.where(keep, W, 0.0)
    return W / W.sum(axis=1, keepdims=True)


def deviation(sparse_result, dense_result, reference_size: float | None = None) -> dict[str, float]:
    """How far a sparse-weight deformation is from the dense one.

    Both arrays (N, 3) (or (..., 3)): deformed positions. Returns ``max`` and
    ``rms`` of the per-point Euclidean distance, and the same divided by
    ``reference_size`` (default: the dense result's bounding-box diagonal)
    as ``max_rel`` / ``rms_rel``.
    """
    a = np.asarray(sparse_result, dtype=np.float64)
    b = np.asarray(dense_result, dtype=np.float64)
    if a.shape != b.shape or a.ndim < 1 or a.shape[-1] != 3 or a.size == 0:
        raise InputError(f"results must be matching non-empty (N, 3) arrays, got {a.shape} and {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError("results contain NaN or inf")
    d = np.linalg.norm((a - b).reshape(-1, 3), axis=1)
    if reference_size is None:
        pts = b.reshape(-1, 3)
        reference_size = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    ref = float(reference_size) if reference_size and reference_size > 0 else 1.0
    mx, rms = float(d.max()), float(np.sqrt(np.mean(d * d)))
    return {"max": mx, "rms": rms, "max_rel": mx / ref, "rms_rel": rms / ref}
