"""The small JSON inputs: pose files, handle files, joint maps (and libigl DMAT poses).

Pose files (JSON) replace rest local values of named joints::

    {"rotations": {"JointName": [x, y, z, w]}, "translations": {"JointName": [x, y, z]}}

A ``.dmat`` pose file is libigl's per-bone quaternions for a TGF skeleton.

The handle file (``HANDLES.json``)::

    {"alpha": 1.0,
     "points":   [{"rest": [x, y, z], "pose": [x, y, z]}],
     "segments": [{"rest": [[x,y,z],[x,y,z]], "pose": [[x,y,z],[x,y,z]],
                   "rotation": [[...],[...],[...]],   # optional, 3x3
                   "twist": 0.5}]}                     # optional, radians

A segment without ``rotation`` turns by the minimal rotation between its rest
and posed directions, followed by ``twist`` radians about its posed direction.

A joint map (JSON) names, for target joints, the source joint that drives
them: ``{"TargetJoint": "SourceJoint"}`` (``null`` unmaps a target joint).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..checks import check_magnitude
from ..errors import FileFormatError, HandleError, InputError
from ..model.handles import HandleSet, Pose, check_alpha
from ..model.rotation import unit_quaternions
from ..model.skeleton import LocalPose, Skeleton, match_hint
from .jsonfile import read_json
from .tgf import read_dmat_pose

__all__ = ["parse_pose", "load_pose", "parse_handles", "load_handles", "load_map"]


def _vector(value, width: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        arr = np.zeros(0)
    if arr.shape != (width,) or not np.isfinite(arr).all():
        raise InputError(f"{what}: expected {width} finite numbers, got {value!r}")
    return arr


def parse_pose(doc, skeleton: Skeleton, where: str = "pose") -> LocalPose:
    """Local pose (J, ...) from a pose document (see the module docstring)."""
    if not isinstance(doc, dict) or set(doc) - {"rotations", "translations"}:
        extra = sorted(set(doc) - {"rotations", "translations"}) if isinstance(doc, dict) else []
        raise InputError(f"{where}: expected an object with 'rotations' and/or 'translations'"
                         + (f", got keys {extra}" if extra else ""))
    pose = skeleton.rest_pose
    for key, field, width in (("rotations", pose.rotation, 4), ("translations", pose.translation, 3)):
        entries = doc.get(key, {})
        if not isinstance(entries, dict):
            raise InputError(f"{where}: '{key}' must map joint names to lists of {width} numbers")
        for name, value in entries.items():
            if name not in skeleton.names:
                raise InputError(f"{where}: {key}: unknown joint {name!r}; {match_hint(name, skeleton.names)}")
            field[skeleton.index(name)] = _vector(value, width, f"{where}: {key}[{name!r}]")
            if key == "translations":
                check_magnitude(field[skeleton.index(name)], f"{where}: {key}[{name!r}]")
    pose.rotation[:] = unit_quaternions(pose.rotation, [f"{where}: rotation of {n!r}" for n in skeleton.names])
    return pose


def load_pose(path: str | Path, skeleton: Skeleton) -> LocalPose:
    """Local pose from a JSON pose file, or a libigl ``.dmat`` for a TGF skeleton."""
    path = Path(path)
    if path.suffix.lower() == ".dmat":
        return read_dmat_pose(path, skeleton)
    return parse_pose(read_json(path, "pose file"), skeleton, str(path))


def load_handles(path: str | Path) -> tuple[HandleSet, Pose, float | None]:
    """Read a handle file; return (rest, pose, alpha or None if the file has none)."""
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


def load_map(path: str | Path) -> dict:
    """A joint map file: JSON object {"TargetJoint": "SourceJoint" or null}."""
    path = Path(path)
    doc = read_json(path, "joint map")
    if not isinstance(doc, dict) or not all(isinstance(v, str) or v is None for v in doc.values()):
        raise FileFormatError(f"{path}: a joint map is a JSON object {{\"TargetJoint\": \"SourceJoint\"}} "
                              "(null unmaps a target joint)")
    return doc
