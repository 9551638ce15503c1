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

__all__ = ["weld", "Surface", "closest_rotations", "smooth_normals", "local_rotations"]


def weld(vertices: np.ndarray, tolerance: float = 1e-7) -> np.ndarray:
    """Group index (N,) int64 per vertex: vertices at the same position (within ``tolerance``
    times the bounding-box diagonal, on a grid) share a group. vertices: (N, 3)."""
    V = np.asarray(vertices, dtype=np.float64)
    if len(V) == 0:
        return np.zeros(0, np.int64)
    span = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) or 1.0
    cells = np.round((V - V.min(axis=0)) / (tolerance * span)).astype(np.int64)
    return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)


class Surface:
    """The welded neighbourhoods of one mesh, built once and used for every posed frame.

    bind: (N, 3) source positions; faces: (M, 3) int; groups: (N,) int64 from :func:`weld`.
    Sums over the faces around each welded position are gathered in group order once
    (``numpy.add.reduceat``), so a frame costs a few array passes and no per-group loop.

    Attributes: ``faces`` (M, 3) int64, ``groups`` (N,) int64, ``n_groups``; the faces
    around each group, ``corner_faces`` (3M,) int64 (a face once per corner of it in the
    group), group g's at ``corner_faces[group_starts[g]:group_starts[g + 1]]``
    (``group_starts`` (n_groups + 1,) int64); ``bind_frames`` (M, 4, 3) float64, each face's
    edge frame at the bind positions (:meth:`rotations`).
    """

    def __init__(self, bind: np.ndarray, faces: np.ndarray, groups: np.ndarray):
        self.faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        self.groups = np.asarray(groups, dtype=np.int64)
        self.n_groups = int(self.groups.max()) + 1 if len(self.groups) else 0
        corners = self.groups[self.faces].reshape(-1)
        order = np.argsort(corners, kind="stable")
        self.corner_faces = order // 3
        sorted_groups = corners[order]
        self.group_starts = np.searchsorted(sorted_groups, np.arange(self.n_groups + 1))
        self._present = np.unique(sorted_groups)
        self._starts = self.group_starts[self._present]
        self.bind_frames = _edge_frames(np.asarray(bind, dtype=np.float64), self.faces)

    def _group_sums(self, per_face: np.ndarray) -> np.ndarray:
        """(n_groups, C) sums of ``per_face`` (M, C) over each group's face corners."""
        total = np.zeros((self.n_groups, per_face.shape[1]))
        if len(self._present):
            total[self._present] = np.add.reduceat(per_face[self.corner_faces], self._starts, axis=0)
        return total

    def smooth_normals(self, vertices: np.ndarray) -> np.ndarray:
        """Area-weighted unit normals (N, 3) float64 of the welded positions of ``vertices`` (N, 3).
        A vertex in no face (or only in degenerate ones) gets the zero vector."""
        V = np.asarray(vertices, dtype=np.float64)
        F = self.faces
        total = self._group_sums(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]))
        length = np.linalg.norm(total, axis=1, keepdims=True)
        unit = np.divide(total, length, out=np.zeros_like(total), where=length > 1e-300)
        return unit[self.groups]

    def rotations(self, posed: np.ndarray) -> np.ndarray:
        """Rotation (N, 3, 3) float64 of each vertex's neighbourhood from the bind positions to
        ``posed`` (N, 3): the closest rotation (polar factor) to ``sum e' e^T`` over the edges ``e``
        and scaled normals of the faces around the vertex's welded position, so a rigidly moved
        neighbourhood gets exactly its rotation, twist about the normal included. A vertex in no
        face gets the identity. Frames (B, N, 3) give (B, N, 3, 3), one frame at a time."""
        posed = np.asarray(posed, dtype=np.float64)
        if posed.ndim == 3:
            return np.stack([self.rotations(p) for p in posed]) if len(posed) else np.zeros((0, len(self.groups), 3, 3))
        b = _edge_frames(posed, self.faces)
        per_face = np.matmul(b.transpose(0, 2, 1), self.bind_frames).reshape(len(self.faces), 9)
        return closest_rotations(self._group_sums(per_face).reshape(-1, 3, 3))[self.groups]


def _edge_frames(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(M, 4, 3) per face: two edges, the third, and the normal scaled to sqrt(2 area)."""
    e1, e2 = V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    n = np.cross(e1, e2)
    n = n / np.sqrt(np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300))  # |n|^2 = 2 area
    return np.stack([e1, e2, e2 - e1, n], axis=1)


def closest_rotations(M: np.ndarray, iterations: int = 30) -> np.ndarray:
    """The rotation (K, 3, 3) float64 closest to each matrix of ``M`` (K, 3, 3) (its polar factor
    with det +1); the identity for a zero matrix.

    Scaled Newton iteration ``X <- (g X + X^-T / g) / 2``, ``g = |det X|^(-1/3)``, on rows of positive
    determinant, written on the nine entries as separate arrays (a batched 3x3 SVD costs ~10x more;
    :func:`nrpose.model.skeleton.polar_components` covers only maps near a scaled rotation, and a
    neighbourhood's sum is far from one);
    rows with det <= 0 or not converged to 1e-13 take the SVD with its last axis flipped to det +1."""
    M = np.asarray(M, dtype=np.float64).reshape(-1, 3, 3)
    R = np.broadcast_to(np.eye(3), M.shape).copy()
    scale = np.abs(M).reshape(len(M), -1).max(axis=1) if len(M) else np.zeros(0)
    live = np.flatnonzero(scale > 1e-300)
    X = M[live] / scale[live, None, None]
    x = [np.ascontiguousarray(X[:, r, c]) for r in range(3) for c in range(3)]
    newton = _cofactor_det(x)[1] > 1e-12
    y = [v[newton] for v in x]
    done = np.zeros(len(y[0]), bool)
    for _ in range(iterations):
        cof, det = _cofactor_det(y)
        g = np.cbrt(det) ** -1
        h = 1.0 / (det * g)
        z = [0.5 * (g * v + h * c) for v, c in zip(y, cof)]
        step = np.max([np.abs(v - w) for v, w in zip(z, y)], axis=0)
        y = z
        done = step < 1e-13
        if done.all():
            break
    fit = X.copy()
    rows = np.flatnonzero(newton)
    fit[rows] = np.stack(y, axis=1).reshape(-1, 3, 3)
    svd = ~newton
    svd[rows[~done]] = True
    if svd.any():
        U, _, Vt = np.linalg.svd(X[svd])
        flip = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= np.where(flip == 0, 1.0, flip)[:, None]
        fit[svd] = U @ Vt
    R[live] = fit
    return R


def _cofactor_det(x: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """Cofactors (nine (K,) arrays, row-major) and determinants (K,) of matrices given as their
    nine row-major entries ``x`` (each (K,))."""
    a, b, c, d, e, f, g, h, i = x
    cof = [e * i - f * h, f * g - d * i, d * h - e * g,
           c * h - b * i, a * i - c * g, b * g - a * h,
           b * f - c * e, c * d - a * f, a * e - b * d]
    return cof, a * cof[0] + b * cof[1] + c * cof[2]


def smooth_normals(vertices: np.ndarray, faces: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Area-weighted unit normals (N, 3) float64 of welded positions (:meth:`Surface.smooth_normals`).

    vertices: (N, 3); faces: (M, 3) int; groups: (N,) from :func:`weld`.
    """
    return Surface(vertices, faces, groups).smooth_normals(vertices)


def local_rotations(bind: np.ndarray, posed: np.ndarray, faces: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Rotation (N, 3, 3) float64 of each vertex's neighbourhood from ``bind`` (N, 3) to ``posed``
    (N, 3) (:meth:`Surface.rotations`); faces (M, 3) int, groups (N,) from :func:`weld`."""
    return Surface(bind, faces, groups).rotations(posed)
