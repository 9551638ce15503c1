"""The one door from the bake engine to nrpose's load → bind → pose → write path.

Every job runs exactly the functions ``nrpose pose`` runs (and, for a
``retarget`` job, those of ``nrpose retarget`` first), so a baked output is
bitwise the command's output. All imports of nrpose internals by the bake
package go through this module.

``pose_input`` (times and local pose from the motion options) and
``retargeted_clip`` (the clip ``nrpose retarget`` stores) compute what the
pose and retarget commands compute inline; ``write_frames``,
``frames_output_kind``, ``motion_clip`` and ``parse_frames`` are the pose
command's own helpers.
"""
from __future__ import annotations

import numpy as np

from ..blend import BLENDS
from ..character import Clip, Track, load_character, load_pose, sample_times
from ..cli import _frames_output_kind as frames_output_kind
from ..cli import _motion_clip as motion_clip
from ..cli import _write_frames as write_frames
from ..cli import parse_frames
from ..device import usable_cpus
from ..engine import BACKENDS
from ..errors import InputError, NrposeError
from ..meshio import atomic_path
from ..posing import METHODS, WEIGHTS, CharacterPoser
from ..retarget import joint_map, load_map, make_clip, retarget_pose
from ..retargetcli import SOURCE_SUFFIXES, TARGET_SUFFIXES

__all__ = ["BACKENDS", "BLENDS", "METHODS", "WEIGHTS", "SOURCE_SUFFIXES", "TARGET_SUFFIXES", "CharacterPoser",
           "NrposeError", "InputError", "load_character", "frames_output_kind", "write_frames", "parse_frames",
           "pose_input", "retargeted_clip", "check_finite", "usable_cpus", "atomic_path"]


def pose_input(character, *, clip: str | Clip | None = None, motion: str | None = None, pose: str | None = None,
               rest: bool = False, time=None, frames: str | None = None, fps: float = 30.0,
               kind: str = "npz"):
    """(LocalPose (F, J, ...), times (F,) float64 seconds) that ``nrpose pose`` poses for these options.

    clip: a clip name of the character, or a Clip (a retargeted one); kind: the
    output kind (``frames_output_kind``), "glb" needs strictly increasing times.
    """
    skel = character.skeleton
    if (rest or pose) and (time or frames):
        raise InputError("--time and --frames sample a clip; with --rest or --pose there is one frame: drop them")
    if rest:
        return skel.rest_pose, np.zeros(1)
    if pose:
        return load_pose(pose, skel), np.zeros(1)
    if clip is not None:
        source = clip if isinstance(clip, Clip) else character.clip(clip)
    else:
        source = motion_clip(load_character(motion), skel, motion)
    if time and frames:
        raise NrposeError("give either --time or --frames, not both")
    times = (np.asarray(time, dtype=np.float64) if time
             else parse_frames(frames, fps) if frames
             else sample_times(source.duration, fps))
    if kind == "glb" and (np.diff(times) <= 0).any():
        raise NrposeError("--time: an animated .glb needs strictly increasing times; sort them or "
                          "write .npz or a directory")
    return source.sample(times), times


def retargeted_clip(target, source_path: str, map_path: str | None = None, source_clip: str | None = None,
                    in_place: bool = False, fps: float = 30.0) -> Clip:
    """The clip ``nrpose retarget SOURCE TARGET [--map] [--source-clip] [--in-place] --fps`` adds to
    the target's .glb, as ``nrpose pose OUT.glb --clip NAME`` reads it back (keys stored as float32)."""
    source = load_character(source_path)
    mapping = joint_map(source.skeleton, target.skeleton, load_map(map_path) if map_path else None)
    if not mapping:
        raise InputError(f"no joint of the character maps to a joint of {source_path}: the rigs share no known "
                         "joint names; give a joint map")
    if not source.clips:
        raise InputError(f"{source_path}: has no animation: no motion to retarget")
    clip = source.clip(source_clip) if source_clip else source.clips[0]
    times, local, plan = retarget_pose(source, clip, target, mapping, in_place, fps)
    made = make_clip(clip.name, times, local, plan, target.skeleton)
    # the .glb holds float32 keys: the pose command samples those
    tracks = tuple(Track(t.joint, t.path, t.times.astype(np.float32).astype(np.float64),
                         t.values.astype(np.float32).astype(np.float64), t.interpolation) for t in made.tracks)
    return Clip(made.name, max(float(t.times[-1]) for t in tracks), target.skeleton.rest_pose, tracks)


def check_finite(positions: np.ndarray) -> None:
    """The pose command's guard on its result."""
    if not np.isfinite(positions).all():
        raise NrposeError("posing produced non-finite coordinates; please report this input")
