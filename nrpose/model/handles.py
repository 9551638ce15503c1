"""Handles: control points and line segments, at rest and posed.

A :class:`HandleSet` is one configuration of positions: ``points`` (P, 3) and
``segments`` (S, 2, 3) (start, end), float64, in the units of the geometry.
A :class:`Pose` adds what only a posed configuration has: the rotation of each
segment, (S, 3, 3), column-vector convention, which must carry the rest
direction onto the posed one. Handle order is points first, then segments,
everywhere (weights, distance matrices, kernels).

The handle file (``HANDLES.json``)::

    {"alpha": 1.0,
     "points":   [{"rest": [x, y, z], "pose": [x, y, z]}],
     "segments": [{"rest": [[x,y,z],[x,y,z]], "pose": [[x,y,z],[x,y,z]],
                   "rotation": [[...],[...],[...]],   # optional, 3x3
                   "twist": 0.5}]}                     # optional, radians

A segment without ``rotation`` turns by the minimal rotation between its rest
and posed directions, followed by ``twist`` radians about its posed direction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .checks import real_rows
from .errors import HandleError
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
        pts = real_rows(points, f"{what} points", (3,), HandleError, allow_empty=True)
        segs = real_rows(segments, f"{what} segments", (2, 3), HandleError, allow_empty=True)
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


def load_handles(path: str | Path) -> tuple[HandleSet, Pose, float | None]:
    """Read a handle file; return (rest, pose, alpha or None if the file has none)."""
    from .jsonfile import read_json
    return parse_handles(read_json(path, "handle file", HandleError), str(path))


def parse_handles(doc, where: str = "handles") -> tuple[HandleSet, Pose, float | None]:
    """Parse a handle document (the JSON structure above)."""
    if not isinstance(doc, dict):
        raise HandleError(f"{where}: expected a JSON object with 'points' and/or 'segments'")
    unknown = set(doc) - {"alpha", "points", "segments"}
    if unknown:
        raise HandleError(f"{where}: unknown key(s) {sorted(unknown)}; expected alpha, points, segments")
    alpha = doc.get("alpha")
    if alpha is not None:
        alpha = check_alpha(alpha)
    points = _entries(doc, "points", where, {"rest", "pose"})
    segments = _entries(doc, "segments", where, {"rest", "pose", "rotation", "twist"})
    rest = HandleSet.make([p["rest"] for p in points], [s["rest"] for s in segments], what=f"{where}: rest")
    rotations = [s.get("rotation") for s in segments]
    twists = [s.get("twist", 0.0) for s in segments]
    pose = Pose.make(rest, [p["pose"] for p in points], [s["pose"] for s in segments],
                     rotations=rotations, twists=twists)
    return rest, pose, alpha


def _entries(doc: dict, key: str, where: str, allowed: set[str]) -> list[dict]:
    items = doc.get(key, [])
    if not isinstance(items, list):
        raise HandleError(f"{where}: '{key}' must be a list")
    for n, item in enumerate(items):
        if not isinstance(item, dict) or not {"rest", "pose"} <= set(item):
            raise HandleError(f"{where}: {key}[{n}] needs 'rest' and 'pose'")
        extra = set(item) - allowed
        if extra:
            raise HandleError(f"{where}: {key}[{n}] has unknown key(s) {sorted(extra)}")
    return items


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
    """The handle-file structure (inverse of :func:`parse_handles`), rotations explicit."""
    doc: dict = {} if alpha is None else {"alpha": float(alpha)}
    doc["points"] = [{"rest": r.tolist(), "pose": p.tolist()}
                     for r, p in zip(rest.points, pose.handles.points)]
    doc["segments"] = [{"rest": r.tolist(), "pose": p.tolist(), "rotation": m.tolist()}
                       for r, p, m in zip(rest.segments, pose.handles.segments, pose.rotations)]
    return doc
