"""Smooth surface normals and the rotation that carries a file's own normals onto a posed surface.

A posed frame's normals are made from the file's normals (custom, split at
seams and hard edges) rather than recomputed, so that what an artist authored
survives: per vertex, :func:`carry` rotates the file's normal (and tangent) by
the smallest rotation taking the vertex's *smooth* normal of the source
geometry to its smooth normal of the posed geometry. Smooth normals are
area-weighted face normals summed over every copy of a position
(:func:`weld`), so seams (UV or material splits) do not show in them.
"""
from __future__ import annotations

import numpy as np

__all__ = ["weld", "smooth_normals", "carry"]


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


def carry(source: np.ndarray, target: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Rotate ``vectors`` (..., N, 3) by the smallest rotation taking unit ``source`` (N, 3) to
    unit ``target`` (..., N, 3), per vertex; float64. Where either normal is zero the vector is
    kept; where they are opposite the rotation is a half turn about an axis normal to ``source``.
    """
    a = np.broadcast_to(np.asarray(source, dtype=np.float64), np.shape(target))
    b = np.asarray(target, dtype=np.float64)
    v = np.asarray(vectors, dtype=np.float64)
    c = np.einsum("...i,...i->...", a, b)[..., None]
    w = np.cross(a, b)
    opposite = (c[..., 0] < -1 + 1e-9)
    safe = np.where(opposite[..., None], 1.0, 1.0 + c)
    out = c * v + np.cross(w, v) + w * np.einsum("...i,...i->...", w, v)[..., None] / safe
    if opposite.any():
        helper = np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        k = np.cross(a, helper)
        k /= np.linalg.norm(k, axis=-1, keepdims=True)
        half = 2 * np.einsum("...i,...i->...", k, v)[..., None] * k - v
        out = np.where(opposite[..., None], half, out)
    degenerate = (np.linalg.norm(a, axis=-1) < 0.5) | (np.linalg.norm(b, axis=-1) < 0.5)
    return np.where(degenerate[..., None], v, out)
