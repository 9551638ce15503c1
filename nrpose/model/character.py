"""Characters (meshes + skeleton + clips) and animation clips; readers are :mod:`nrpose.io`.

A :class:`Character` is what every loader returns: meshes whose rest vertices
are in world space at the skeleton's rest pose, the :class:`Skeleton`, the
inverse bind matrices, and :class:`Clip` animations. Deforming a rest vertex
``v`` by linear blend skinning at a pose with global joint matrices ``G`` is
``sum_i w_i (G[j_i] @ G_rest[j_i]^-1) @ v`` (:meth:`Character.skin_matrices`).

Clips are sets of keyframe :class:`Track` s (one joint, one of translation /
rotation / scale) with glTF's samplers: ``STEP``; ``LINEAR`` (quaternion
slerp along the shortest arc for rotations); ``CUBICSPLINE`` (Hermite, per the
glTF 2.0 spec, tangents scaled by the key interval, quaternions normalised).
Before its first key a track holds its first value, after its last key its
last value; a joint without a track keeps its rest value.

A character's clips are :class:`Clips`: their names are known at load, each clip is made
(its keys decoded and checked) the first time it is asked for, so a job that plays one clip
of a file decodes that clip alone.
"""
from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import InputError
from .rotation import quat_slerp
from .skeleton import LocalPose, Skeleton
from .timing import clip_times

__all__ = ["Track", "Clip", "Clips", "Mesh", "Character"]

PATH_WIDTH = {"translation": 3, "rotation": 4, "scale": 3}
INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")


@dataclass(frozen=True, eq=False)
class Track:
    """Keyframes of one joint property.

    joint: joint index; path: "translation" | "rotation" | "scale";
    times: (K,) float64 strictly increasing seconds; values: (K, C) float64,
    or (K, 3, C) (in-tangent, value, out-tangent) for CUBICSPLINE; C = 4 for
    rotations (x, y, z, w), else 3.
    """

    joint: int
    path: str
    times: np.ndarray
    values: np.ndarray
    interpolation: str = "LINEAR"

    def __post_init__(self):
        if self.path not in PATH_WIDTH or self.interpolation not in INTERPOLATIONS:
            raise InputError(f"track: unknown path {self.path!r} or interpolation {self.interpolation!r}")
        times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        values = np.asarray(self.values, dtype=np.float64)
        tail = (3, PATH_WIDTH[self.path]) if self.interpolation == "CUBICSPLINE" else (PATH_WIDTH[self.path],)
        if len(times) == 0 or values.shape != (len(times),) + tail:
            raise InputError(f"track of joint {self.joint} {self.path}: {len(times)} key times need "
                             f"values of shape {(len(times),) + tail}, got {values.shape}")
        if not (np.isfinite(times).all() and np.isfinite(values).all()):
            raise InputError(f"track of joint {self.joint} {self.path}: NaN or infinite keys")
        if (np.diff(times) <= 0).any():
            raise InputError(f"track of joint {self.joint} {self.path}: key times must increase strictly")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "values", values)

    def sample(self, t: np.ndarray) -> np.ndarray:
        """Values at times t (F,) seconds: (F, C) float64 (unit quaternions for rotations)."""
        return interpolate_keys(self.times, self.values[..., None, :], t, self.interpolation,
                                self.path == "rotation")[:, 0]


def interpolate_keys(times: np.ndarray, values: np.ndarray, t, interpolation: str, rotation: bool) -> np.ndarray:
    """Values (F, G, C) float64 at times t (F,) seconds of G tracks sharing key times (K,)
    seconds and ``interpolation``: values (K, G, C), or (K, 3, G, C) for CUBICSPLINE (as
    :class:`Track`'s, a track per column). ``rotation``: values are quaternions (x, y, z, w),
    slerped (LINEAR) or normalised (CUBICSPLINE). Each track's result is what it gives alone."""
    t = np.asarray(t, dtype=np.float64)
    K, cubic = len(times), interpolation == "CUBICSPLINE"
    k = np.searchsorted(times, t, side="right") - 1
    if interpolation == "STEP" or K == 1:
        out = values[np.clip(k, 0, K - 1)]
        return out[:, 1] if cubic else out
    k = np.clip(k, 0, K - 2)
    dt = (times[k + 1] - times[k])[:, None, None]
    s = np.clip((t - times[k])[:, None, None] / dt, 0.0, 1.0)
    v0, v1 = values[k], values[k + 1]
    if cubic:
        s2, s3 = s * s, s * s * s
        out = ((2 * s3 - 3 * s2 + 1) * v0[:, 1] + (s3 - 2 * s2 + s) * dt * v0[:, 2]
               + (-2 * s3 + 3 * s2) * v1[:, 1] + (s3 - s2) * dt * v1[:, 0])
        return out / np.linalg.norm(out, axis=-1, keepdims=True) if rotation else out
    if rotation:
        shape = v0.shape
        s = np.broadcast_to(s, shape[:-1] + (1,)).reshape(-1, 1)
        return quat_slerp(v0.reshape(-1, 4), v1.reshape(-1, 4), s).reshape(shape)
    return (1 - s) * v0 + s * v1


@dataclass(frozen=True, eq=False)
class Clip:
    """An animation: tracks over a rest pose. duration: seconds (last key time)."""

    name: str
    duration: float
    rest: LocalPose
    tracks: tuple[Track, ...]

    def sample(self, t) -> LocalPose:
        """Local pose at time(s) t in [0, duration] seconds.

        A scalar t gives arrays (J, ...); an array of F times gives (F, J, ...).
        Times outside the clip (to within a float32 step, :func:`nrpose.model.timing.clip_times`)
        raise InputError.
        """
        times = np.asarray(t, dtype=np.float64)
        try:
            flat = clip_times(times, self.duration).reshape(-1)
        except InputError as exc:
            raise InputError(f"clip {self.name!r}: {exc}") from None
        out = {p: np.repeat(getattr(self.rest, p)[None], len(flat), axis=0) for p in PATH_WIDTH}
        for path, joints, keys, values, interpolation in self._groups:
            out[path][:, joints] = interpolate_keys(keys, values, flat, interpolation, path == "rotation")
        if times.ndim == 0:
            return LocalPose(*(out[p][0] for p in PATH_WIDTH))
        return LocalPose(*(out[p].reshape(times.shape + out[p].shape[1:]) for p in PATH_WIDTH))

    @functools.cached_property
    def _groups(self) -> tuple:
        """The tracks sampled together: ``(path, joints (G,), times (K,), values (K, [3,] G, C),
        interpolation)`` per set of tracks sharing path, interpolation and key times (a clip's
        tracks usually share one time accessor); of two tracks of one joint's path, the last.
        A LINEAR or STEP track of equal keys is its first key (a LINEAR rotation's normalised,
        as their slerp gives it)."""
        last = {(track.joint, track.path): track for track in self.tracks}
        groups: dict = {}
        for track in last.values():
            times, values, interpolation = track.times, track.values, track.interpolation
            if interpolation != "CUBICSPLINE" and len(times) > 1 and (values == values[0]).all():
                if track.path == "rotation" and interpolation == "LINEAR":   # unit, as their slerp
                    values = values / np.linalg.norm(values, axis=-1, keepdims=True)
                times, values, interpolation = times[:1], values[:1], "STEP"
            key = (track.path, interpolation, times.tobytes() if len(times) > 1 else b"")
            groups.setdefault(key, []).append((track.joint, times, values))
        return tuple((path, np.array([j for j, _, _ in group], dtype=np.int64), group[0][1],
                      np.stack([v for _, _, v in group], axis=-2), interpolation)
                     for (path, interpolation, _), group in groups.items())


class Clips(Sequence):
    """A character's clips in file order, each made the first time it is asked for.

    names: every clip's name, known without making any; make(i) -> Clip: clip i, called
    when ``clips[i]`` is first asked for (the clip is kept; an error it raises, e.g. a
    reader's FileFormatError for malformed keys, reaches every caller that asks for that
    clip). Iterating, ``len`` and ``in`` behave as on a tuple of the clips (iterating
    makes them all); a slice gives a tuple.
    """

    def __init__(self, names: Sequence[str], make: Callable[[int], Clip]):
        self.names = tuple(names)
        self._make = make
        self._made: dict[int, Clip] = {}

    @classmethod
    def of(cls, clips: Sequence[Clip]) -> Clips:
        """Clips already made."""
        clips = tuple(clips)
        return cls([c.name for c in clips], clips.__getitem__)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return tuple(self[i] for i in range(len(self))[index])
        i = range(len(self))[index]      # IndexError as a tuple's, negative indices allowed
        if i not in self._made:
            self._made[i] = self._make(i)
            if len(self._made) == len(self):
                self._make = None        # every clip made: let go of what made them (a file's bytes)
        return self._made[i]

    def then(self, check: Callable[[Clip], Clip]) -> Clips:
        """These clips, each passed through ``check`` (which returns it, or raises for a bad
        clip) when it is made."""
        return Clips(self.names, functools.partial(_checked, self, check))

    def __repr__(self) -> str:
        return f"Clips({list(self.names)!r}, {len(self._made)} made)"


def _checked(clips: Clips, check: Callable[[Clip], Clip], i: int) -> Clip:
    """``check(clips[i])``: the ``make`` of :meth:`Clips.then` (a module function, so picklable)."""
    return check(clips[i])


@dataclass(frozen=True, eq=False)
class Mesh:
    """One mesh of a character.

    vertices: (N, 3) float64 rest positions in world space; faces: (M, 3) int64;
    joints: (N, K) int64 skeleton joint indices and weights: (N, K) float64
    (rows summing to 1), or None when the file has no skin weights;
    rigid_joint: the joint a rigidly attached mesh follows (its joints/weights
    are then that joint with weight 1), else None;
    bind_vertices: (N, 3) float64 the skinned mesh's own POSITION data (glTF
    bind space, transformed by ``G_j @ inverse_bind_j`` in the glTF skinning
    formula), else None; inverse_bind: (J, 4, 4) its skin's inverse bind
    matrices by skeleton joint (skins may differ), else None;
    source: where a glTF mesh came from, ``(node, mesh, primitive)`` indices of
    its document, else None (writers copy that primitive's other attributes).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray | None = None
    weights: np.ndarray | None = None
    rigid_joint: int | None = None
    bind_vertices: np.ndarray | None = None
    inverse_bind: np.ndarray | None = None
    source: tuple[int, int, int] | None = None


@dataclass(frozen=True, eq=False)
class Character:
    """Meshes, skeleton, inverse bind matrices (J, 4, 4) float64 and clips.

    clips: :class:`Clips` (a sequence of Clip given here is wrapped as ``Clips.of``);
    static_meshes: meshes the skeleton does not move (scenery beside the
    character), in world space; they are never posed, and glTF outputs keep
    them as they are.
    """

    skeleton: Skeleton
    meshes: tuple[Mesh, ...] = ()
    clips: Clips = ()
    inverse_bind: np.ndarray | None = None
    static_meshes: tuple[Mesh, ...] = ()

    def __post_init__(self):
        if not isinstance(self.clips, Clips):
            object.__setattr__(self, "clips", Clips.of(self.clips))
        if self.inverse_bind is None:
            object.__setattr__(self, "inverse_bind", np.linalg.inv(self.skeleton.rest_globals()))

    def clip(self, name: str) -> Clip:
        """The (first) clip called ``name``, made now if it was not (only that clip); InputError
        naming the available clips when there is none."""
        names = self.clips.names
        if name not in names:
            raise InputError(f"no clip {name!r}; available clips: {', '.join(map(repr, names)) or 'none'}")
        return self.clips[names.index(name)]

    def skin_matrices(self, globals_: np.ndarray) -> np.ndarray:
        """Skinning matrices ``G @ G_rest^-1`` (..., J, 4, 4) for world-space rest vertices."""
        return np.asarray(globals_, dtype=np.float64) @ np.linalg.inv(self.skeleton.rest_globals())
