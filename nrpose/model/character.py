"""Characters (meshes + skeleton + clips), animation clips, pose files, and loading.

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

Pose files (JSON) replace rest local values of named joints::

    {"rotations": {"JointName": [x, y, z, w]}, "translations": {"JointName": [x, y, z]}}

A ``.dmat`` pose file is libigl's per-bone quaternions for a TGF skeleton.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import FileFormatError, InputError
from .rotation import Rotation, unit_quaternions
from .skeleton import LocalPose, Skeleton, _match_hint

__all__ = ["Track", "Clip", "Mesh", "Character", "load_character", "load_pose", "parse_pose"]

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
        t = np.asarray(t, dtype=np.float64)
        K, times, v = len(self.times), self.times, self.values
        k = np.searchsorted(times, t, side="right") - 1
        if self.interpolation == "STEP" or K == 1:
            out = v[np.clip(k, 0, K - 1)]
            return out[:, 1] if self.interpolation == "CUBICSPLINE" else out
        k = np.clip(k, 0, K - 2)
        dt = times[k + 1] - times[k]
        s = np.clip((t - times[k]) / dt, 0.0, 1.0)[:, None]
        if self.interpolation == "CUBICSPLINE":
            s2, s3 = s * s, s * s * s
            out = ((2 * s3 - 3 * s2 + 1) * v[k, 1] + (s3 - 2 * s2 + s) * dt[:, None] * v[k, 2]
                   + (-2 * s3 + 3 * s2) * v[k + 1, 1] + (s3 - s2) * dt[:, None] * v[k + 1, 0])
            if self.path == "rotation":
                out = out / np.linalg.norm(out, axis=1, keepdims=True)
            return out
        if self.path == "rotation":
            r0 = Rotation.from_quat(v[k])
            step = (r0.inv() * Rotation.from_quat(v[k + 1])).as_rotvec()
            return (r0 * Rotation.from_rotvec(s * step)).as_quat()
        return (1 - s) * v[k] + s * v[k + 1]


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
        Times outside the clip raise InputError.
        """
        times = np.asarray(t, dtype=np.float64)
        flat = times.reshape(-1)
        tol = 1e-9 * max(self.duration, 1.0)
        if not np.isfinite(flat).all() or (flat < -tol).any() or (flat > self.duration + tol).any():
            bad = flat[~(np.isfinite(flat) & (flat >= -tol) & (flat <= self.duration + tol))][0]
            raise InputError(f"clip {self.name!r}: time {bad} is outside [0, {self.duration:g}] seconds")
        out = {p: np.repeat(getattr(self.rest, p)[None], len(flat), axis=0) for p in PATH_WIDTH}
        for track in self.tracks:
            out[track.path][:, track.joint] = track.sample(flat)
        if times.ndim == 0:
            return LocalPose(*(out[p][0] for p in PATH_WIDTH))
        return LocalPose(*(out[p].reshape(times.shape + out[p].shape[1:]) for p in PATH_WIDTH))


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
    matrices by skeleton joint (skins may differ), else None.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray | None = None
    weights: np.ndarray | None = None
    rigid_joint: int | None = None
    bind_vertices: np.ndarray | None = None
    inverse_bind: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Character:
    """Meshes, skeleton, inverse bind matrices (J, 4, 4) float64 and clips."""

    skeleton: Skeleton
    meshes: tuple[Mesh, ...] = ()
    clips: tuple[Clip, ...] = ()
    inverse_bind: np.ndarray | None = None

    def __post_init__(self):
        if self.inverse_bind is None:
            object.__setattr__(self, "inverse_bind", np.linalg.inv(self.skeleton.rest_globals()))

    def clip(self, name: str) -> Clip:
        """The clip called ``name``; InputError naming the available clips otherwise."""
        for clip in self.clips:
            if clip.name == name:
                return clip
        names = [c.name for c in self.clips]
        raise InputError(f"no clip {name!r}; available clips: {', '.join(map(repr, names)) or 'none'}")

    def skin_matrices(self, globals_: np.ndarray) -> np.ndarray:
        """Skinning matrices ``G @ G_rest^-1`` (..., J, 4, 4) for world-space rest vertices."""
        return np.asarray(globals_, dtype=np.float64) @ np.linalg.inv(self.skeleton.rest_globals())


def load_character(path: str | Path, skeleton: str | Path | None = None) -> Character:
    """Load a character by extension.

    ``.glb``/``.gltf``: meshes, skin, clips. ``.bvh``: skeleton and its motion
    clip, no mesh. ``.tgf``: skeleton only. A mesh (``.obj .off .ply .stl
    .mesh``) needs ``skeleton`` (a ``.tgf`` or ``.bvh``); it gets no skin weights.
    """
    from .formats import bvh, gltf, tgf

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        if skeleton is not None:
            raise InputError(f"{path}: a glTF file carries its own skeleton; do not pass one")
        return gltf.load_gltf(path)
    if suffix in (".bvh", ".tgf"):
        if skeleton is not None:
            raise InputError(f"{path}: is already a skeleton; pass a mesh with it instead")
        if suffix == ".bvh":
            skel, clip = bvh.read_bvh(path)
            return Character(skel, clips=(clip,))
        return Character(tgf.read_tgf(path))
    if suffix in tgf.MESH_SUFFIXES:
        if skeleton is None:
            raise InputError(f"{path}: a mesh needs a skeleton (a .tgf or .bvh file)")
        base = load_character(skeleton)
        V, F = tgf.read_mesh(path)
        return Character(base.skeleton, (Mesh(path.stem, V, F),), base.clips)
    raise FileFormatError(f"{path}: unknown character extension {suffix!r}; use .glb, .gltf, .bvh, "
                          f".tgf or a mesh ({', '.join(tgf.MESH_SUFFIXES)}) with a skeleton")


#: the most frames one call samples (an hour at 30 fps is 108,000 frames)
MAX_FRAMES = 1_000_000


def check_frame_count(count: float, what: str) -> None:
    """InputError when ``count`` frames (``what`` asked for them) exceed :data:`MAX_FRAMES`."""
    if count > MAX_FRAMES:
        raise InputError(f"{what} asks for {float(min(count, 1e300)):.3g} frames, more than {MAX_FRAMES:,}; "
                         f"sample fewer (a shorter range, a larger step or a lower frame rate) or pose the "
                         f"clip in parts")


def sample_times(duration: float, fps: float) -> np.ndarray:
    """Times k / fps (seconds, float64) for 0 <= k / fps <= duration (at least the time 0)."""
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")
    count = np.floor(duration * fps + 1e-6) + 1
    check_frame_count(count, f"{duration:g} s at {fps:g} fps")
    return np.minimum(np.arange(int(count)) / fps, duration)


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
                raise InputError(f"{where}: {key}: unknown joint {name!r}; {_match_hint(name, skeleton.names)}")
            field[skeleton.index(name)] = _vector(value, width, f"{where}: {key}[{name!r}]")
    pose.rotation[:] = unit_quaternions(pose.rotation, [f"{where}: rotation of {n!r}" for n in skeleton.names])
    return pose


def load_pose(path: str | Path, skeleton: Skeleton) -> LocalPose:
    """Local pose from a JSON pose file, or a libigl ``.dmat`` for a TGF skeleton."""
    path = Path(path)
    if path.suffix.lower() == ".dmat":
        from .formats.tgf import read_dmat_pose

        return read_dmat_pose(path, skeleton)
    from .jsonfile import read_json
    return parse_pose(read_json(path, "pose file"), skeleton, str(path))
