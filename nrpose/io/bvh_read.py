"""BVH motion capture: hierarchy (skeleton) and motion (one clip).

Each joint's ``OFFSET`` is its rest local translation (rest rotations are
identity: the rest pose is the hierarchy's own pose). ``CHANNELS`` may list
positions and rotations in any order and on any joint. Rotation channels are
intrinsic rotations applied in the listed order: ``Zrotation Xrotation
Yrotation`` gives ``R = Rz @ Rx @ Ry`` (column vectors), degrees in the file.
Position channels replace the corresponding offset components (the usual
reading: the root's positions are absolute). An ``End Site`` becomes its
joint's tip. Units are the file's; no axis conversion.

The motion is a :class:`~nrpose.model.character.Clip` named after the file, with
LINEAR tracks (slerp for rotations) keyed at ``frame * frame_time`` seconds,
so its duration is ``(frames - 1) * frame_time``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..checks import check_magnitude
from ..errors import FileFormatError, InputError
from ..model.character import Clip, Track
from ..model.rotation import Rotation
from ..model.skeleton import Skeleton
from .files import read_input_text

__all__ = ["read_bvh"]

#: bounds on a hierarchy: deeper or larger files are refused (real rigs have a few hundred joints)
MAX_DEPTH = 256
MAX_JOINTS = 10_000

AXES = {"Xposition": ("P", 0), "Yposition": ("P", 1), "Zposition": ("P", 2),
        "Xrotation": ("R", "X"), "Yrotation": ("R", "Y"), "Zrotation": ("R", "Z")}


class _Tokens:
    """Whitespace tokens of the hierarchy with their line numbers."""

    def __init__(self, path: Path, lines: list[str]):
        self.path = path
        self.items = [(tok, n) for n, line in enumerate(lines, start=1) for tok in line.split()]
        self.pos = 0

    def line(self) -> int:
        return self.items[min(self.pos, len(self.items) - 1)][1] if self.items else 0

    def error(self, message: str) -> FileFormatError:
        return FileFormatError(f"{self.path}:{self.line()}: {message}")

    def peek(self) -> str | None:
        return self.items[self.pos][0] if self.pos < len(self.items) else None

    def take(self, expected: str | None = None) -> str:
        tok = self.peek()
        if tok is None:
            raise self.error(f"unexpected end of file{f', expected {expected!r}' if expected else ''}")
        if expected is not None and tok != expected:
            raise self.error(f"expected {expected!r}, got {tok!r}")
        self.pos += 1
        return tok

    def numbers(self, count: int, what: str) -> list[float]:
        line = self.line()
        try:
            values = [float(self.take()) for _ in range(count)]
        except ValueError:
            raise FileFormatError(f"{self.path}:{line}: {what}: expected {count} numbers") from None
        if not np.isfinite(values).all():
            raise FileFormatError(f"{self.path}:{line}: {what}: NaN or infinite value")
        check_magnitude(np.asarray(values), f"{self.path}:{line}: {what}", FileFormatError)
        return values


def _parse_hierarchy(tokens: _Tokens):
    """Joint records (name, parent, offset, channels, tip) in file (topological) order.

    Iterative (a stack of open joints), so nesting depth costs no Python recursion; at most
    MAX_DEPTH nested and MAX_JOINTS joints in all.
    """
    joints: list[dict] = []
    open_joints: list[int] = []     # joints whose closing '}' is still to come, innermost last
    tokens.take("HIERARCHY")

    def start(parent: int) -> None:
        if len(open_joints) >= MAX_DEPTH:
            raise tokens.error(f"joints nested more than {MAX_DEPTH} deep; is it the right file?")
        if len(joints) >= MAX_JOINTS:
            raise tokens.error(f"more than {MAX_JOINTS} joints; is it the right file?")
        name = tokens.take()
        record = {"name": name, "parent": parent, "tip": None, "channels": [], "line": tokens.line()}
        joints.append(record)
        tokens.take("{")
        tokens.take("OFFSET")
        record["offset"] = tokens.numbers(3, f"OFFSET of {name}")
        if tokens.peek() == "CHANNELS":
            line = tokens.line()
            tokens.take()
            try:
                count = int(tokens.take())
            except ValueError:
                raise tokens.error(f"CHANNELS of {name}: expected a channel count") from None
            if not 0 <= count <= len(AXES):
                raise tokens.error(f"CHANNELS of {name}: {count} channels (0 to {len(AXES)} expected)")
            record["channels"] = [tokens.take() for _ in range(count)]
            unknown = [c for c in record["channels"] if c not in AXES]
            if unknown:
                raise FileFormatError(f"{tokens.path}:{line}: CHANNELS of {name}: unknown channel "
                                      f"{unknown[0]!r} (known: {', '.join(AXES)})")
        open_joints.append(len(joints) - 1)

    while open_joints or tokens.peek() == "ROOT":
        if not open_joints:
            tokens.take()
            start(-1)
            continue
        record = joints[open_joints[-1]]
        keyword = tokens.take("}") if tokens.peek() is None else tokens.take()
        if keyword == "}":
            open_joints.pop()
        elif keyword == "JOINT":
            start(open_joints[-1])
        elif keyword == "End":
            tokens.take("Site")
            tokens.take("{")
            tokens.take("OFFSET")
            tip = tokens.numbers(3, f"End Site OFFSET of {record['name']}")
            if record["tip"] is not None:
                raise tokens.error(f"joint {record['name']} has several End Sites")
            record["tip"] = tip
            tokens.take("}")
        else:
            raise tokens.error(f"expected JOINT, End Site or '}}' in joint {record['name']}, got {keyword!r}")
    if not joints:
        raise tokens.error("no ROOT joint in HIERARCHY")
    if tokens.peek() is not None:
        raise tokens.error(f"expected ROOT or end of HIERARCHY, got {tokens.peek()!r}")
    return joints


def _header(path: Path, lines: list[str], start: int, label: str) -> tuple[str, int]:
    """Value after ``label`` on the first non-empty line from ``start``, and the next line index."""
    i = start
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i == len(lines) or not lines[i].strip().startswith(label):
        raise FileFormatError(f"{path}:{i + 1}: expected '{label} ...' after MOTION")
    return lines[i].strip()[len(label):].strip(), i + 1


def _read_motion(path: Path, lines: list[str], start: int, width: int) -> tuple[np.ndarray, float]:
    """Frames (F, width) float64 and frame time (s) from the MOTION section."""
    text, i = _header(path, lines, start, "Frames:")
    try:
        frames = int(text)
    except ValueError:
        raise FileFormatError(f"{path}:{i}: 'Frames:' needs an integer, got {text!r}") from None
    text, i = _header(path, lines, i, "Frame Time:")
    try:
        frame_time = float(text)
    except ValueError:
        frame_time = float("nan")
    if frames < 1 or not (np.isfinite(frame_time) and frame_time > 0):
        raise FileFormatError(f"{path}:{i}: need at least one frame and a positive frame time, "
                              f"got {frames} frames of {text!r} s")
    rows = [(n, line.split()) for n, line in enumerate(lines[i:], start=i + 1) if line.strip()]
    if len(rows) != frames:
        raise FileFormatError(f"{path}: 'Frames: {frames}' but {len(rows)} frame lines follow")
    for n, fields in rows:
        if len(fields) != width:
            raise FileFormatError(f"{path}:{n}: frame line has {len(fields)} values, the hierarchy "
                                  f"declares {width} channels")
    try:
        data = np.array([fields for _, fields in rows], dtype=np.float64).reshape(frames, width)
    except ValueError:
        n = next(n for n, fields in rows if not all(_is_float(f) for f in fields))
        raise FileFormatError(f"{path}:{n}: frame line has a value that is not a number") from None
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if bad.size:
        raise FileFormatError(f"{path}:{rows[bad[0]][0]}: frame line contains NaN or infinity")
    return data, frame_time


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_bvh(path: str | Path) -> tuple[Skeleton, Clip]:
    """Skeleton (J joints, file order) and its motion clip from a BVH file."""
    path = Path(path)
    lines = read_input_text(path, "BVH file").splitlines()
    motion = next((i for i, line in enumerate(lines) if line.strip() == "MOTION"), None)
    if motion is None:
        raise FileFormatError(f"{path}: no MOTION section")
    joints = _parse_hierarchy(_Tokens(path, lines[:motion]))
    width = sum(len(j["channels"]) for j in joints)
    data, frame_time = _read_motion(path, lines, motion + 1, width)
    J, F = len(joints), len(data)
    try:
        skeleton = Skeleton(names=tuple(j["name"] for j in joints),
                            parents=[j["parent"] for j in joints],
                            translation=[j["offset"] for j in joints],
                            rotation=np.tile([0.0, 0.0, 0.0, 1.0], (J, 1)), scale=np.ones((J, 3)),
                            tips=[j["tip"] if j["tip"] is not None else [np.nan] * 3 for j in joints])
    except InputError as exc:
        raise FileFormatError(f"{path}: {exc}") from None
    times = np.arange(F) * frame_time
    tracks = []
    column = 0
    for index, record in enumerate(joints):
        rot_axes, rot_cols, translation = "", [], None
        for channel in record["channels"]:
            kind, axis = AXES[channel]
            if kind == "R":
                rot_axes += axis
                rot_cols.append(column)
            else:
                if translation is None:
                    translation = np.tile(record["offset"], (F, 1))
                translation[:, axis] = data[:, column]
                check_magnitude(data[:, column], f"{path}: {channel} of joint {record['name']}", FileFormatError)
            column += 1
        if rot_axes:
            try:
                quats = Rotation.from_euler(rot_axes, data[:, rot_cols], degrees=True).as_quat()
            except ValueError:
                raise FileFormatError(f"{path}:{record['line']}: joint {record['name']} has rotation "
                                      f"channels {rot_axes!r}; give 1 to 3 axes, no axis twice in a row") from None
            tracks.append(Track(index, "rotation", times, quats))
        if translation is not None:
            tracks.append(Track(index, "translation", times, translation))
    clip = Clip(path.stem, float(times[-1]), skeleton.rest_pose, tuple(tracks))
    return skeleton, clip
