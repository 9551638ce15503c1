"""Smooth surface normals, and the rotation that carries a file's own normals onto a posed surface.

A posed frame's normals are made from the file's normals (custom, split at
seams and hard edges) rather than recomputed, so that what an artist authored
survives: per vertex, the file's normal (and tangent) is turned by the rotation
of the vertex's neighbourhood from the source geometry to the posed one
(:func:`local_rotations`). Neighbourhoods and smooth normals (area-weighted
face normals) are taken over every copy of a position (:func:`weld`), so seams
(UV or material splits) do not show in them and the copies of a split vertex
turn together: split normals stay split.
"""
from __future__ import annotations

import numpy as np

__all__ = ["weld", "smooth_normals", "local_rotations"]


def weld(vertices: np.ndarray, tolerance: float = 1e-7) -> np.ndarray:
    """Group index (N,) int64 per vertex: vertices at the same position (within ``tolerance``
    times the bounding-box diagonal, on a grid) share a group. vertices: (N, 3)."""
    V = np.asarray(vertices, dtype=np.float64)
    if len(V) == 0:
        return np.zeros(0, np.int64)
    span = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) or 1.0
    cells = np.round((V - V.min(axis=0)) / (tolerance * span)).astype(np.int64)
    return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)


def smooth_normals(vertices: np.ndarray, faces: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Area-weighted unit normals (N, 3) float64 of welded positions.

    vertices: (N, 3); faces: (M, 3) int; groups: (N,) from :func:`weld`. A vertex
    in no face (or only in degenerate ones) gets the zero vector.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    area = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    corners = groups[F].reshape(-1)
    total = np.stack([np.bincount(corners, np.repeat(area[:, i], 3), n_groups) for i in range(3)], axis=1)
    length = np.linalg.norm(total, axis=1, keepdims=True)
    unit = np.divide(total, length, out=np.zeros_like(total), where=length > 1e-300)
    return unit[groups]


def local_rotations(bind: np.ndarray, posed: np.ndarray, faces: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Rotation (N, 3, 3) float64 of each vertex's neighbourhood from ``bind`` (N, 3) to ``posed``
    (N, 3): the closest rotation (polar factor) to ``sum e' e^T`` over the edges ``e`` and scaled
    normals of the faces around the vertex's welded position (``groups`` from :func:`weld`), so a
    rigidly moved neighbourhood gets exactly its rotation, twist about the normal included.
    A vertex in no face gets the identity."""
    F = np.asarray(faces, dtype=np.int64)

    def frames(V):
        e1, e2 = V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
        n = np.cross(e1, e2)
        n = n / np.sqrt(np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300))  # |n|^2 = 2 area
        return np.stack([e1, e2, e2 - e1, n], axis=1)          # (M, 4, 3)

    a, b = frames(np.asarray(bind, dtype=np.float64)), frames(np.asarray(posed, dtype=np.float64))
    per_face = np.einsum("mki,mkj->mij", b, a).reshape(len(F), 9)
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    corners = groups[F].reshape(-1)
    total = np.stack([np.bincount(corners, np.repeat(per_face[:, c], 3), n_groups) for c in range(9)], axis=1)
    U, S, Vt = np.linalg.svd(total.reshape(-1, 3, 3))
    flip = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= np.where(flip == 0, 1.0, flip)[:, None]
    R = U @ Vt
    R[S[:, 0] <= 1e-300] = np.eye(3)
    return R[groups]
