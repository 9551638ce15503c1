"""A Y-junction: three unit bones meeting at the origin, and a closed mesh around them.

Bones (segment handles), in this order: ``stem`` (origin → (0, −1, 0)), ``left``
(origin → (−0.7, 0.7, 0)) and ``right`` (origin → (0.7, 0.7, 0)). The mesh is the zero
set of a smooth union of three capsules (radius ``radius``) meshed by
``igl.marching_cubes``: the test case of a joint where three bones with different
rotations meet (hips, shoulders). :func:`spread_pose` turns ``left`` by ``degrees``
about x and ``right`` by ``degrees`` about −z, the stem stays: the rotation spread of the
junction. :func:`probe_line` is a line of closely spaced points crossing the region where
the dominant upper bone changes.
"""
from __future__ import annotations

import numpy as np

from nrpose.model.handles import HandleSet, Pose
from nrpose.model.rotation import Rotation

BONES = np.array([[[0, 0, 0], [0, -1, 0]], [[0, 0, 0], [-0.7, 0.7, 0]], [[0, 0, 0], [0.7, 0.7, 0]]], float)
BONE_NAMES = ("stem", "left", "right")


def rest_handles() -> HandleSet:
    return HandleSet.make(segments=BONES)


def spread_rotations(degrees: float) -> np.ndarray:
    """(3, 3, 3) rotations of stem, left, right for a spread of ``degrees``."""
    a = np.radians(degrees)
    return np.stack([np.eye(3), Rotation.from_rotvec([a, 0, 0]).as_matrix(),
                     Rotation.from_rotvec([0, 0, -a]).as_matrix()])


def spread_pose(degrees: float) -> Pose:
    """The bones turned about the junction (the origin) by :func:`spread_rotations`."""
    R = spread_rotations(degrees)
    posed = np.einsum("bij,bkj->bki", R, BONES)
    return Pose.make(rest_handles(), segments=posed, rotations=R)


def probe_line(count: int = 6001, half: float = 0.3) -> np.ndarray:
    """(count, 3) points on x ∈ [−half, half] at y = 0.4, z = 0.15 (spacing 2 half / (count − 1))."""
    x = np.linspace(-half, half, count)
    return np.stack([x, np.full_like(x, 0.4), np.full_like(x, 0.15)], 1)


def yjunction_mesh(radius: float = 0.15, resolution: float = 0.03, blend: float = 0.05):
    """Closed outward-oriented mesh (vertices (N, 3) float64, faces (M, 3) int64) around the bones."""
    import igl  # local import: libigl is only needed to build the mesh

    lo, hi = BONES.reshape(-1, 3).min(0) - radius - 2 * resolution, BONES.reshape(-1, 3).max(0) + radius + 2 * resolution
    n = np.ceil((hi - lo) / resolution).astype(int) + 1
    gx, gy, gz = (np.linspace(lo[k], hi[k], n[k]) for k in range(3))
    Z, Y, X = np.meshgrid(gz, gy, gx, indexing="ij")        # igl wants S(x + y nx + z nx ny)
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    d = [capsule_distance(P, a, b, radius) for a, b in BONES]
    # polynomial smooth minimum (blend radius ``blend``) of the three capsules
    S = d[0]
    for di in d[1:]:
        h = np.clip(0.5 + 0.5 * (di - S) / blend, 0.0, 1.0)
        S = di * (1 - h) + S * h - blend * h * (1 - h)
    V, F, _ = igl.marching_cubes(S, P, int(n[0]), int(n[1]), int(n[2]), 0.0)
    V, F = np.asarray(V, np.float64), np.asarray(F, np.int64)
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    remap = np.cumsum(used) - 1
    V, F = V[used], remap[F]
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() < 0:
        F = F[:, ::-1].copy()
    return V, F


def capsule_distance(P: np.ndarray, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """Signed distance (M,) of points P (M, 3) to the capsule of axis a → b and radius r."""
    ab = b - a
    t = np.clip((P - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1) - r


def opposed_rotations(degrees: float) -> np.ndarray:
    """(3, 3, 3) rotations: ``left`` by +degrees and ``right`` by −degrees about x, the stem
    fixed. Beyond 90° the two upper bones' unit quaternions are more than 90° apart in
    either sign choice of one of them, so a per-vertex hemisphere choice flips."""
    a = np.radians(degrees)
    return np.stack([np.eye(3), Rotation.from_rotvec([a, 0, 0]).as_matrix(),
                     Rotation.from_rotvec([-a, 0, 0]).as_matrix()])


def opposed_pose(degrees: float) -> Pose:
    """The bones turned about the junction by :func:`opposed_rotations`."""
    R = opposed_rotations(degrees)
    return Pose.make(rest_handles(), segments=np.einsum("bij,bkj->bki", R, BONES), rotations=R)
