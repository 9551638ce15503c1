"""A closed cylinder mesh around a chain of two bones: the quality test rig.

Two unit bones along +x: (0,0,0)→(1,0,0)→(2,0,0); the tube has radius 0.2 and
flat caps. Used to measure volume preservation and rigidity when the second
bone bends or twists.
"""
from __future__ import annotations

import numpy as np

from nrpose.model.handles import HandleSet, Pose
from nrpose.model.rotation import Rotation

BONES = np.array([[[0.0, 0, 0], [1.0, 0, 0]], [[1.0, 0, 0], [2.0, 0, 0]]])


def cylinder_mesh(radius: float = 0.2, length: float = 2.0, rings: int = 81, sectors: int = 48):
    """Closed, outward-oriented cylinder along +x from 0 to ``length``.

    Returns (vertices (rings*sectors + 2, 3) float64, faces (F, 3) int64).
    """
    x = np.linspace(0.0, length, rings)
    th = np.linspace(0.0, 2 * np.pi, sectors, endpoint=False)
    X, TH = np.meshgrid(x, th, indexing="ij")
    V = np.stack([X, radius * np.cos(TH), radius * np.sin(TH)], axis=-1).reshape(-1, 3)
    V = np.concatenate([V, [[0.0, 0, 0], [length, 0, 0]]])
    idx = np.arange(rings * sectors).reshape(rings, sectors)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    side = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    c0, c1 = len(V) - 2, len(V) - 1
    ring0, ring1 = idx[0], idx[-1]
    cap0 = np.stack([np.full(sectors, c0), np.roll(ring0, -1), ring0], -1)
    cap1 = np.stack([np.full(sectors, c1), ring1, np.roll(ring1, -1)], -1)
    return V, np.concatenate([side, cap0, cap1]).astype(np.int64)


def mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (divergence theorem)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def rest_handles() -> HandleSet:
    return HandleSet.make(segments=BONES)


def bend_pose(degrees: float, axis=(0.0, 0.0, 1.0)) -> Pose:
    """Second bone turned by ``degrees`` about ``axis`` through the joint (1,0,0)."""
    rot = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, dtype=np.float64))
    joint = BONES[1, 0]
    posed = BONES.copy()
    posed[1, 1] = joint + rot.apply(BONES[1, 1] - joint)
    return Pose.make(rest_handles(), segments=posed, rotations=[np.eye(3), rot.as_matrix()])


def twist_pose(degrees: float) -> Pose:
    """Second bone twisted by ``degrees`` about its own axis."""
    return Pose.make(rest_handles(), segments=BONES, twists=[0.0, np.radians(degrees)])
