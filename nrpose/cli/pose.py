"""``nrpose pose``: a character posed from its clips, a BVH motion, a pose file or its rest pose."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..pose.blend import BLENDS
from ..pose.mls import BACKENDS
from ..errors import NrposeError
from ..io import load_character
from ..io.poses import load_pose
from ..model.character import Clip, Track
from ..model.timing import check_frame_count, sample_times
from ..pose.poser import METHODS, WEIGHTS, CharacterPoser
from ..render.sheet import save_contact_sheet
from .common import add_budget_options, check_budget, check_outputs, frames_output_kind, progress, write_frames

#: library argument name -> the flag users type
FLAGS = {"method": "--method", "weights": "--weights", "alpha": "--alpha", "blend": "--blend",
         "backend": "--backend", "skeleton": "--skeleton"}


def add_parser(sub) -> None:
    p = sub.add_parser("pose", help="pose a character (glTF, mesh + TGF/BVH skeleton) from clips, motion or poses")
    p.add_argument("character", help=".glb/.gltf, or a mesh (OBJ, OFF, PLY, STL, .mesh) with --skeleton")
    p.add_argument("--skeleton", help="skeleton for a mesh character (.tgf or .bvh)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--clip", help="animation clip of the character, by name")
    src.add_argument("--motion", help="BVH motion recorded on the character's skeleton")
    src.add_argument("--pose", help="pose file (JSON local rotations/translations, or libigl DMAT)")
    src.add_argument("--rest", action="store_true", help="the rest pose")
    p.add_argument("--time", type=float, nargs="+", help="clip times in seconds")
    p.add_argument("--frames", help="frame range A:B[:STEP] at --fps")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    p.add_argument("--method", choices=METHODS, default="nrmls", help="posing method (default nrmls)")
    p.add_argument("--weights", choices=WEIGHTS, default="authored", help="weights (default: authored)")
    p.add_argument("--alpha", type=float, default=1.0, help="weight exponent for distance weights (default 1)")
    p.add_argument("--blend", choices=BLENDS, default="relative",
                   help="nrmls rotation blend (default: relative; quaternion is continuous where the "
                        "dominant bone changes, for bones less than 90 degrees apart)")
    p.add_argument("--backend", choices=BACKENDS, default="opencl", help="opencl (default) or numpy reference")
    p.add_argument("--format", choices=("ply", "obj"), default="ply", help="per-frame files for a directory OUT")
    p.add_argument("-o", "--output", required=True, help="OUT.npz, OUT.glb or a directory")
    p.add_argument("--png", help="write a contact sheet PNG")
    add_budget_options(p)
    p.set_defaults(func=run, flags=FLAGS)


def parse_frames(spec: str, fps: float) -> np.ndarray:
    """``A:B[:STEP]`` frame numbers (inclusive) at ``fps`` → times in seconds."""
    parts = spec.split(":")
    try:
        nums = [int(p) for p in parts]
    except ValueError:
        nums = []
    if len(nums) not in (2, 3) or nums[0] < 0 or nums[1] < nums[0] or (len(nums) == 3 and nums[2] < 1):
        raise NrposeError(f"--frames {spec!r}: expected A:B or A:B:STEP with 0 <= A <= B and STEP >= 1")
    if not (np.isfinite(fps) and fps > 0):
        raise NrposeError(f"--fps {fps}: expected a positive number")
    step = nums[2] if len(nums) == 3 else 1
    check_frame_count((nums[1] - nums[0]) // step + 1, f"--frames {spec}")
    return np.arange(nums[0], nums[1] + 1, step) / fps


def run(args) -> None:
    kind = frames_output_kind(args.output)
    if kind == "dir" and Path(args.output).is_file():
        raise NrposeError(f"{args.output}: a file; give a directory (or a name ending in .npz or .glb)")
    check_outputs(args.output, None, args.png, out_is_dir=kind == "dir")
    if not (np.isfinite(args.fps) and args.fps > 0):
        raise NrposeError(f"--fps {args.fps}: expected a positive number of frames per second")
    if (args.rest or args.pose) and (args.time or args.frames):
        raise NrposeError("--time and --frames sample a clip; with --rest or --pose there is one frame: drop them")
    character = load_character(args.character, args.skeleton)
    skel = character.skeleton
    if args.rest:
        local, times = skel.rest_pose, np.zeros(1)
    elif args.pose:
        local, times = load_pose(args.pose, skel), np.zeros(1)
    else:
        if args.clip:
            clip = character.clip(args.clip)
        else:
            motion = load_character(args.motion)
            clip = motion_clip(motion, skel, args.motion)
        if args.time and args.frames:
            raise NrposeError("give either --time or --frames, not both")
        times = (np.asarray(args.time, dtype=np.float64) if args.time
                 else parse_frames(args.frames, args.fps) if args.frames
                 else sample_times(clip.duration, args.fps))
        if kind == "glb" and (np.diff(times) <= 0).any():
            raise NrposeError("--time: an animated .glb needs strictly increasing times; sort them or "
                              "write .npz or a directory")
        vertices = sum(len(m.vertices) for m in character.meshes)
        check_budget(args, len(times), 3.0 * len(times) * vertices + (len(times) ** 2 if kind == "glb" else 0),
                     args.output)
        local = clip.sample(times)
    poser = CharacterPoser(character, method=args.method, weights=args.weights, alpha=args.alpha,
                           backend=args.backend, blend=args.blend)
    frames = poser.pose(local, progress=progress)
    if not np.isfinite(frames.positions).all():
        raise NrposeError("posing produced non-finite coordinates; please report this input")
    write_frames(args.output, frames, times, args.format, character)
    if args.png:
        save_contact_sheet(args.png, frames.positions, frames.faces, times,
                           title=f"{Path(args.character).name}: {args.method}, {args.weights} weights")
    ms = frames.frame_ms
    print(f"{args.output}: {len(ms)} frame(s) × {poser.n} vertices, {args.method} ({args.weights} weights) on "
          f"{args.backend}: bind {poser.bind_ms:.0f} ms; per frame median {np.median(ms):.3f} ms, "
          f"min {ms.min():.3f}, max {ms.max():.3f}; {1e3 / np.median(ms):.0f} frames/s")


def motion_clip(motion, skel, path) -> Clip:
    """The motion file's clip, on a character whose skeleton has the motion's joint names."""
    missing = [n for n in motion.skeleton.names if n not in skel.names]
    if missing:
        raise NrposeError(f"{path}: joint {missing[0]!r} (and {len(missing) - 1} more) not in the character's "
                          "skeleton; --motion drives the skeleton it was recorded on "
                          "(retarget other rigs first)")
    clip = motion.clips[0]
    index = [skel.index(n) for n in motion.skeleton.names]
    tracks = tuple(Track(index[t.joint], t.path, t.times, t.values, t.interpolation) for t in clip.tracks)
    return Clip(clip.name, clip.duration, skel.rest_pose, tracks)
