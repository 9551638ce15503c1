"""``nrpose retarget``: a motion from one rig onto another, written as glTF or BVH.

    nrpose retarget SOURCE (.bvh|.glb|.gltf) TARGET (.glb|.gltf) [--source-clip NAME]
                    [--map MAP.json] [--root origin|keep|in-place] [--in-place] [--force]
                    [--fps F] [--show-map] -o OUT (.glb|.bvh) [--png SHEET.png]

The retargeting itself is :mod:`nrpose.pose.retarget`. Outputs:

* ``OUT.glb``: the target file with the retargeted clip appended as a new
  animation (named after the source clip; `` (2)``... if that name is taken)
  keying every joint node's translation, rotation and scale (float32, LINEAR;
  moving values at ``k / fps`` and at the clip's end, constant ones at the
  start and end) (:func:`nrpose.io.gltf_write.write_glb_with_clip`: the
  original content is kept; skinned mesh nodes are placed so that viewers'
  culling bounds hold the animated geometry,
  :func:`nrpose.pose.retarget.skinned_bounds`). Pose it with
  ``nrpose pose OUT.glb --clip NAME``.
* ``OUT.bvh``: the target skeleton and the clip as BVH
  (:mod:`nrpose.io.bvh_write`), frame time ``1 / fps`` (grid frames only).
* ``--root``: horizontal root motion, ``origin`` (default: the clip starts
  with the hips above the origin), ``keep`` (the capture's positions) or
  ``in-place``; ``--in-place`` is ``--root in-place``.
* ``--force``: retarget even when the mapping drives too little of the target
  (:func:`nrpose.pose.retarget.check_coverage`).
* ``--png``: a contact sheet of the retargeted character with the source
  skeleton beside it (:func:`nrpose.render.retarget_sheet.save_retarget_sheet`).
* ``--show-map``: prints the joint mapping and the joints left unmapped
  (alone, or with ``-o``).

Bad input (unknown joints in the map, no motion, no mapped joint, wrong
extensions) raises :class:`~nrpose.errors.NrposeError` before anything is
written; files are written through :func:`nrpose.io.files.atomic_path`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import load_character
from ..io.bvh_write import write_bvh
from ..io.files import check_writable
from ..io.gltf_write import write_glb_with_clip
from ..io.poses import load_map
from ..pose.retarget import ROOT_MODES, coverage, format_map, joint_map, make_clip, retarget_pose, skinned_bounds
from ..render.retarget_sheet import save_retarget_sheet

__all__ = ["add_parser", "run", "retarget_clip", "SOURCE_SUFFIXES", "TARGET_SUFFIXES"]

#: library argument name -> the flag users type
FLAGS = {"user_map": "--map MAP.json,", "format_map": "--show-map", "root": "--root", "fps": "--fps",
         "force": "--force"}

SOURCE_SUFFIXES = (".bvh", ".glb", ".gltf")
TARGET_SUFFIXES = (".glb", ".gltf")
OUTPUT_SUFFIXES = (".glb", ".bvh")


def add_parser(sub) -> None:
    p = sub.add_parser("retarget", help="play a motion (BVH or glTF clip) on another rig (glTF)")
    p.add_argument("source", help="motion: .bvh, or a .glb/.gltf with an animation")
    p.add_argument("target", help="character to drive: .glb or .gltf")
    p.add_argument("--source-clip", help="animation of a glTF source, by name (default: its first)")
    p.add_argument("--map", help='joint map JSON {"TargetJoint": "SourceJoint"}, overrides the automatic one')
    p.add_argument("--root", choices=ROOT_MODES, default=None,
                   help="horizontal root motion: origin (default; starts above the origin, heading kept), "
                        "keep (the capture's positions) or in-place")
    p.add_argument("--in-place", action="store_true", help="the same as --root in-place")
    p.add_argument("--force", action="store_true",
                   help="retarget even when the mapping drives too little of the target's skeleton")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second of the output (default 30)")
    p.add_argument("--show-map", action="store_true", help="print the joint mapping and the unmapped joints")
    p.add_argument("-o", "--output", help="OUT.glb (target + new animation) or OUT.bvh (target skeleton)")
    p.add_argument("--png", help="write a contact sheet PNG (retargeted character beside the source skeleton)")
    p.set_defaults(func=run, flags=FLAGS)


def _suffix(path: str, allowed: tuple[str, ...], what: str) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise InputError(f"{path}: {what} must end in {', '.join(allowed)}")
    return suffix


def run(args) -> None:
    _suffix(args.source, SOURCE_SUFFIXES, "the source")
    _suffix(args.target, TARGET_SUFFIXES, "the target")
    if args.output is None and not args.show_map:
        raise InputError("give -o OUT.glb or OUT.bvh (or --show-map to print the joint mapping only)")
    if args.output is not None:
        _suffix(args.output, OUTPUT_SUFFIXES, "the output")
        check_writable(args.output)
    if args.png is not None:
        _suffix(args.png, (".png",), "--png")
        check_writable(args.png)
    if not (np.isfinite(args.fps) and args.fps > 0):
        raise InputError(f"--fps {args.fps}: expected a positive number")
    if args.in_place and args.root not in (None, "in-place"):
        raise InputError(f"--in-place and --root {args.root} contradict each other; give one")
    root = "in-place" if args.in_place else args.root or "origin"
    for p in (args.source, args.target) + ((args.map,) if args.map else ()):
        if not Path(p).is_file():
            raise InputError(f"{p}: no such file")

    source = load_character(args.source)
    target = load_character(args.target)
    user_map = load_map(args.map) if args.map else None
    mapping = joint_map(source.skeleton, target.skeleton, user_map)
    if args.show_map:
        print(format_map(mapping, source.skeleton, target.skeleton))
    if args.output is None:
        return
    out = Path(args.output)
    bvh = out.suffix.lower() == ".bvh"
    clip, times, local, plan, result = retarget_clip(source, target, mapping, args.source, args.target,
                                                     args.source_clip, root, args.fps, args.force, close=not bvh)
    if not bvh:
        name = write_glb_with_clip(args.target, out, target, result, skinned_bounds(target, local))
    else:
        write_bvh(out, target.skeleton, local, 1.0 / args.fps, position_joints=[plan.root])
        name = result.name
    if args.png:
        save_retarget_sheet(args.png, source, clip, target, times, local, plan,
                            title=f"{Path(args.target).name} <- {Path(args.source).name} ({clip.name})")
    print(f"{out}: animation {name!r}, {len(times)} frames at {args.fps:g} fps ({times[-1]:.2f} s), "
          f"{len(plan.mapping)} of {target.skeleton.num_joints} target joints mapped "
          f"({100 * coverage(target.skeleton, mapping).fraction:.0f}% of its bone length), root motion x{plan.scale:.4g}"
          f", root {root}, lift {plan.lift:+.3g}")


def retarget_clip(source, target, mapping: dict, source_path: str, target_path: str, source_clip: str | None = None,
                  root: str = "origin", fps: float = 30.0, force: bool = False, close: bool = True):
    """The retargeting ``nrpose retarget`` writes: (source clip, times (F,) s, target local pose,
    plan, the target's new Clip). ``mapping``: :func:`nrpose.pose.retarget.joint_map`; the paths
    name the characters in errors (InputError: no mapped joint, no animation, unknown clip);
    ``root``, ``force``, ``close``: :func:`nrpose.pose.retarget.retarget_pose`'s."""
    if not mapping:
        raise InputError(f"no joint of {target_path} maps to a joint of {source_path}: the rigs share no known "
                         "joint names; give a joint map (--map MAP.json, {\"TargetJoint\": \"SourceJoint\"})")
    if not source.clips:
        raise InputError(f"{source_path}: has no animation: no motion to retarget")
    clip = source.clip(source_clip) if source_clip else source.clips[0]
    times, local, plan = retarget_pose(source, clip, target, mapping, root, fps, force, close=close)
    return clip, times, local, plan, make_clip(clip.name, times, local, plan, target.skeleton)
