"""The seed paper's "Figure 2" shape: a palm with two parallel fingers.

A closed, connected triangle mesh made by marching cubes on the signed
distance function of a union (``min``) of a rounded box (the palm) and two
capsules (the fingers). The fingers point along +y, side by side in x, with a
gap between them much smaller than their length: spatially, a vertex on one
finger is close to the other finger's bone, while over the surface it is far
(down one finger, across the palm, up the other). This is the case where
spatial weights fail and topological (surface-distance) weights work.

Bones (line-segment handles, inside the body), in this order:
``palm``, ``finger_a`` (x < 0), ``finger_b`` (x > 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FingersShape", "fingers_shape", "BONE_NAMES"]

BONE_NAMES = ("palm", "finger_a", "finger_b")


@dataclass(frozen=True)
class FingersShape:
    vertices: np.ndarray  # (N, 3) float64
    faces: np.ndarray  # (F, 3) int64
    bones: np.ndarray  # (3, 2, 3) float64: palm, finger_a, finger_b
    bone_names: tuple[str, ...]
    finger_radius: float
    finger_gap: float  # surface-to-surface gap between the fingers
    finger_length: float  # base of the finger (palm top) to its tip


def _sd_capsule(P: np.ndarray, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    ab = b - a
    t = np.clip(((P - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1) - r


def _sd_round_box(P: np.ndarray, centre: np.ndarray, half: np.ndarray, r: float) -> np.ndarray:
    q = np.abs(P - centre) - (half - r)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside - r


def fingers_shape(
    resolution: float = 0.09,
    finger_radius: float = 0.3,
    finger_spacing: float = 1.0,
    finger_length: float = 2.5,
) -> FingersShape:
    """Build the palm-and-two-fingers mesh.

    resolution: marching-cubes grid step (0.09 gives about 3-4k vertices).
    finger_spacing: distance between the two finger axes; the surface gap is
    ``finger_spacing - 2 * finger_radius`` (0.4 by default, vs a length 2.5).
    Deterministic: the same arguments give the same arrays.
    """
    import igl  # local import: libigl is only needed to build the mesh

    r = float(finger_radius)
    xs = 0.5 * float(finger_spacing)
    L = float(finger_length)
    palm_c = np.array([0.0, -0.6, 0.0])
    palm_h = np.array([xs + r + 0.25, 0.6, r + 0.05])  # palm top at y = 0
    fa0, fa1 = np.array([-xs, 0.0, 0.0]), np.array([-xs, L - r, 0.0])
    fb0, fb1 = np.array([xs, 0.0, 0.0]), np.array([xs, L - r, 0.0])

    lo = np.array([-palm_h[0], -1.2, -palm_h[2]]) - 2 * resolution
    hi = np.array([palm_h[0], L, palm_h[2]]) + 2 * resolution
    n = np.ceil((hi - lo) / resolution).astype(int) + 1
    gx = np.linspace(lo[0], hi[0], n[0])
    gy = np.linspace(lo[1], hi[1], n[1])
    gz = np.linspace(lo[2], hi[2], n[2])
    # igl.marching_cubes wants S(x + y*nx + z*nx*ny)
    Z, Y, X = np.meshgrid(gz, gy, gx, indexing="ij")
    GV = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    S = np.minimum.reduce([
        _sd_round_box(GV, palm_c, palm_h, 0.15),
        _sd_capsule(GV, fa0 - [0, 0.3, 0], fa1, r),
        _sd_capsule(GV, fb0 - [0, 0.3, 0], fb1, r),
    ])
    V, F, _ = igl.marching_cubes(S, GV, int(n[0]), int(n[1]), int(n[2]), 0.0)
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    # drop degenerate (repeated-index) faces and unreferenced vertices
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    remap = -np.ones(len(V), np.int64)
    remap[used] = np.arange(used.sum())
    V, F = V[used], remap[F]
    # outward orientation: signed volume must be positive
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0
    if vol < 0:
        F = F[:, ::-1].copy()
    bones = np.array([
        [palm_c + [0.0, -0.35, 0.0], palm_c + [0.0, 0.35, 0.0]],
        [fa0 - [0, 0.2, 0], fa1],
        [fb0 - [0, 0.2, 0], fb1],
    ], dtype=np.float64)
    return FingersShape(V, F, bones, BONE_NAMES, r, float(finger_spacing) - 2 * r, L)
