"""Handles: control points and line segments, at rest and posed.

A :class:`HandleSet` is one configuration of positions: ``points`` (P, 3) and
``segments`` (S, 2, 3) (start, end), float64, in the units of the geometry.
A :class:`Pose` adds what only a posed configuration has: the rotation of each
segment, (S, 3, 3), column-vector convention, which must carry the rest
direction onto the posed one. Handle order is points first, then segments,
everywhere (weights, distance matrices, kernels).

The handle file format is :mod:`nrpose.io.poses`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..checks import coordinates, real_rows
from ..errors import HandleError
from .rotation import Rotation, minimal_rotvec

#: largest accepted angle between R·(rest direction) and the posed direction
DIRECTION_TOLERANCE = 1e-3  # radians


@dataclass(frozen=True)
class HandleSet:
    """Positions of handles in one configuration.

    points: (P, 3) float64; segments: (S, 2, 3) float64 (start, end).
    """

    points: np.ndarray
    segments: np.ndarray

    @classmethod
    def make(cls, points=(), segments=(), what: str = "handles") -> "HandleSet":
        pts = coordinates(points, f"{what} points", (3,), HandleError, allow_empty=True)
        segs = coordinates(segments, f"{what} segments", (2, 3), HandleError, allow_empty=True)
        if len(pts) + len(segs) == 0:
            raise HandleError(f"{what}: no handles; give at least one point or segment")
        lengths = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
        scale = max(float(np.abs(np.concatenate([pts.ravel(), segs.ravel()])).max(initial=0.0)), 1.0)
        short = np.flatnonzero(lengths <= 1e-9 * scale)
        if len(short):
            raise HandleError(f"{what}: segment {int(short[0])} has zero length; "
                              "use a point handle for it or move its end")
        return cls(pts, segs)

    @property
    def count(self) -> int:
        return len(self.points) + len(self.segments)

    def same_layout(self, other: "HandleSet", what: str) -> None:
        if (len(self.points), len(self.segments)) != (len(other.points), len(other.segments)):
            raise HandleError(f"{what}: {len(other.points)} points and {len(other.segments)} segments "
                              f"given, the binding has {len(self.points)} and {len(self.segments)}")


@dataclass(frozen=True)
class Pose:
    """A posed handle set with each segment's rotation.

    handles: posed positions; rotations: (S, 3, 3) float64, rotation of each
    segment from rest to pose (column vectors), twist included.
    """

    handles: HandleSet
    rotations: np.ndarray

    @classmethod
    def make(cls, rest: HandleSet, points=(), segments=(), rotations=None, twists=None) -> "Pose":
        """Build and validate a pose against ``rest``.

        rotations: optional (S, 3, 3), or a list with None for segments that
        take the minimal rotation; twists: optional (S,) radians about the
        posed direction, only for segments without an explicit rotation.
        """
        posed = HandleSet.make(points, segments, what="posed handles")
        rest.same_layout(posed, "posed handles")
        s = len(rest.segments)
        d_rest = rest.segments[:, 1] - rest.segments[:, 0]
        d_pose = posed.segments[:, 1] - posed.segments[:, 0]
        twist = (np.zeros(s) if twists is None
                 else real_rows([[t] for t in twists], "twists", (1,), HandleError, allow_empty=True)[:, 0])
        if len(twist) != s:
            raise HandleError(f"twists: {len(twist)} values for {s} segments")
        given = _given_rotations(rotations, s)
        both = np.flatnonzero(given & (twist != 0.0))
        if len(both):
            raise HandleError(f"segment {int(both[0])}: give either 'rotation' or 'twist', not both")
        mats = np.empty((s, 3, 3))
        free = ~given
        if free.any():
            minimal = Rotation.from_rotvec(minimal_rotvec(d_rest[free], d_pose[free]))
            if (twist[free] != 0).any():
                axis = d_pose[free] / np.linalg.norm(d_pose[free], axis=1, keepdims=True)
                turn = np.remainder(twist[free, None] + np.pi, 2 * np.pi) - np.pi   # same rotation, any size
                minimal = Rotation.from_rotvec(axis * turn) * minimal
            mats[free] = minimal.as_matrix()
        if given.any():
            idx = np.flatnonzero(given)
            mats[idx] = _rotation_matrices([rotations[i] for i in idx], idx)
            carried = np.einsum("sij,sj->si", mats, d_rest)
            off = np.linalg.norm(minimal_rotvec(carried, d_pose), axis=1)
            bad = np.flatnonzero(off > DIRECTION_TOLERANCE)
            if len(bad):
                i = int(bad[0])
                raise HandleError(f"segment {i}: its rotation turns the rest direction "
                                  f"{math.degrees(off[i]):.3g}° away from the posed direction; "
                                  "give the bone's full rotation or omit 'rotation'")
        return cls(posed, mats)


def _given_rotations(rotations, s: int) -> np.ndarray:
    """(S,) bool: which segments come with an explicit rotation."""
    if rotations is None:
        return np.zeros(s, bool)
    if len(rotations) != s:
        raise HandleError(f"rotations: {len(rotations)} given for {s} segments")
    return np.array([r is not None for r in rotations], bool)


def _rotation_matrices(values, idx: np.ndarray) -> np.ndarray:
    """Validate user rotation matrices (3x3, orthonormal, det +1) of segments ``idx``; re-orthonormalise."""
    rows = []
    for i, v in zip(idx, values):
        rows.append(real_rows(v, f"segment {int(i)} rotation", (3,), HandleError))
        if rows[-1].shape != (3, 3):
            raise HandleError(f"segment {int(i)} rotation: expected a 3x3 matrix, got shape {rows[-1].shape}")
    m = np.stack(rows)
    err = np.abs(np.einsum("sji,sjk->sik", m, m) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > 1e-4) | (np.linalg.det(m) <= 0))
    if len(bad):
        raise HandleError(f"segment {int(idx[bad[0]])} rotation: not a rotation matrix (orthonormal, det +1)")
    return Rotation.from_matrix(m).as_matrix()


def check_alpha(alpha) -> float:
    """Validate the weight exponent α (> 0, finite)."""
    try:
        if isinstance(alpha, (bool, np.bool_)):
            raise TypeError("a truth value is not an exponent")
        a = float(alpha)
    except (TypeError, ValueError, OverflowError):
        raise HandleError(f"alpha must be a number, got {alpha!r}") from None
    if not (math.isfinite(a) and a > 0):
        raise HandleError(f"alpha must be positive and finite, got {alpha!r}")
    return a


def handles_document(rest: HandleSet, pose: Pose, alpha: float | None = None) -> dict:
    """The handle-file structure (inverse of :func:`nrpose.io.poses.parse_handles`), rotations explicit."""
    doc: dict = {} if alpha is None else {"alpha": float(alpha)}
    doc["points"] = [{"rest": r.tolist(), "pose": p.tolist()}
                     for r, p in zip(rest.points, pose.handles.points)]
    doc["segments"] = [{"rest": r.tolist(), "pose": p.tolist(), "rotation": m.tolist()}
                       for r, p, m in zip(rest.segments, pose.handles.segments, pose.rotations)]
    return doc
