"""``nrpose pose``: a character posed from its clips, a BVH motion, a pose file or its rest pose."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import NrposeError
from ..io import load_character
from ..model.character import Clip, Track
from ..model.timing import check_frame_count, sample_times
from ..options import BACKENDS, BLENDS, DEFAULT_BLEND, METHODS, WEIGHTS
from ..pose.poser import CharacterPoser, prefetch
from .common import (add_budget_options, character_with_weights, check_budget, check_outputs, frames_output_kind,
                     median, output_values, progress, write_frames)

#: library argument name -> the flag users type
FLAGS = {"method": "--method", "weights": "--weights", "alpha": "--alpha", "blend": "--blend",
         "backend": "--backend", "skeleton": "--skeleton"}


def add_parser(sub) -> None:
    p = sub.add_parser("pose", help="pose a character (glTF, mesh + TGF/BVH skeleton) from clips, motion or poses")
    p.add_argument("character", help=".glb/.gltf, or a mesh (OBJ, OFF, PLY, STL, .mesh) with --skeleton")
    p.add_argument("--skeleton", help="skeleton for a mesh character (.tgf or .bvh)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--clip", help="animation clip of the character, by name")
    src.add_argument("--motion", help="BVH motion recorded on the character's skeleton, or a libigl animation "
                                      "DMAT (per frame, a stacked 4x3 transform per TGF bone; frame k at k / --fps)")
    src.add_argument("--pose", help="pose file (JSON local rotations/translations, or libigl DMAT)")
    src.add_argument("--rest", action="store_true", help="the rest pose")
    p.add_argument("--time", type=float, nargs="+", help="clip times in seconds")
    p.add_argument("--frames", help="frame range A:B[:STEP] at --fps")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    p.add_argument("--method", choices=METHODS, default="nrmls",
                   help="posing method (default nrmls; docs/quality.md compares them)")
    p.add_argument("--weights", choices=WEIGHTS, default="authored", help="weights (default: authored)")
    p.add_argument("--weights-file", help="libigl weight DMAT for a mesh + TGF character (rows = vertices, "
                                          "columns = bones in TGF order); used as its authored weights")
    p.add_argument("--alpha", type=float, default=1.0, help="weight exponent for distance weights (default 1)")
    p.add_argument("--blend", choices=BLENDS, default=None,
                   help=f"nrmls rotation blend (default: {DEFAULT_BLEND}, continuous at any spread of the "
                        "bones' rotations; relative jumps where the dominant bone changes among three or more)")
    p.add_argument("--backend", choices=BACKENDS, default="opencl", help="opencl (default) or numpy reference")
    p.add_argument("--format", choices=("ply", "obj"), default="ply", help="per-frame files for a directory OUT")
    p.add_argument("-o", "--output", required=True, help="OUT.npz, OUT.glb or a directory")
    p.add_argument("--bake", choices=BAKES, default="morph",
                   help="form of an OUT.glb: morph (default) stores every posed frame as a morph target "
                        "(positions and normals; any method); skin keeps the source glTF's own skin and "
                        "writes the clip as an ordinary animation of its joints, sampled at the frame times: "
                        "only for --method lbs --weights authored, where the file's skinning is the result, "
                        "so no bake is needed")
    p.add_argument("--quantize", action="store_true",
                   help="morph bakes: compact targets (KHR_mesh_quantization; position error at most 1e-4 of "
                        "the bounding-box diagonal, float where that does not hold)")
    p.add_argument("--png", help="write a contact sheet PNG")
    add_budget_options(p)
    p.set_defaults(func=run, flags=FLAGS)


#: forms of a baked .glb (--bake)
BAKES = ("morph", "skin")


def check_bake(args, kind: str) -> None:
    """Refuse --bake/--quantize combinations that cannot be honoured, before any work."""
    gltf_source = Path(args.character).suffix.lower() in (".glb", ".gltf")
    if kind != "glb" and (args.bake != "morph" or args.quantize):
        raise NrposeError("--bake and --quantize choose the form of a .glb output; the output is not .glb")
    if args.bake == "skin":
        if not gltf_source:
            raise NrposeError("--bake skin keeps the source glTF's skin; the character is not a glTF file")
        if args.method != "lbs" or args.weights != "authored":
            raise NrposeError(f"--bake skin is the file's own skinning, which equals --method lbs --weights "
                              f"authored only (got --method {args.method} --weights {args.weights}); "
                              "use --bake morph for other methods")
        if args.quantize:
            raise NrposeError("--quantize compacts morph targets; --bake skin writes none")
    elif kind == "glb" and gltf_source:
        from ..io.gltf_write import check_copyable     # pygltflib: imported for .glb outputs only
        check_copyable(args.character)


def sampled_clip(name: str, times: np.ndarray, local, rest) -> Clip:
    """A clip keying every joint's translation, rotation and scale at ``times`` (F,) from
    ``local`` (a LocalPose of shape (F, J, ...)), LINEAR."""
    tracks = tuple(Track(j, path, times, getattr(local, path)[:, j], "LINEAR")
                   for j in range(local.rotation.shape[1]) for path in ("translation", "rotation", "scale"))
    return Clip(name, float(times[-1]), rest, tracks)


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
    check_bake(args, kind)
    if not (np.isfinite(args.fps) and args.fps > 0):
        raise NrposeError(f"--fps {args.fps}: expected a positive number of frames per second")
    if (args.rest or args.pose) and (args.time or args.frames):
        raise NrposeError("--time and --frames sample a clip; with --rest or --pose there is one frame: drop them")
    prefetch(args.method, args.backend)       # a skinning program compiles while the character loads
    if args.weights_file and args.weights != "authored":
        raise NrposeError(f"--weights-file gives the weights; drop --weights {args.weights}")
    character = character_with_weights(args.character, args.skeleton, args.weights_file)
    local, times, name = pose_input(character, clip=args.clip, motion=args.motion, pose=args.pose, rest=args.rest,
                                    time=args.time, frames=args.frames, fps=args.fps, kind=kind)
    vertices = sum(len(m.vertices) for m in character.meshes)
    check_budget(args, len(times), output_values(len(times), vertices, kind), args.output)
    if kind == "glb" and args.bake == "morph":
        from ..pose.surface_rotations import prefetch_program, surface_rotations_for
        if surface_rotations_for(vertices, len(times), args.backend):
            prefetch_program()      # the bake's normals kernel compiles while the frames are posed
    poser = CharacterPoser(character, method=args.method, weights=args.weights, alpha=args.alpha,
                           backend=args.backend, blend=args.blend or DEFAULT_BLEND)
    # an .npz or a directory takes the frames as they are posed, unless a contact sheet needs them all
    frames = posed_frames(poser, local, progress, stream=kind != "glb" and not args.png)
    if args.bake == "skin":
        single = local.rotation.ndim == 2
        keys = type(local)(*(getattr(local, p)[None] if single else getattr(local, p)
                             for p in ("translation", "rotation", "scale")))
        bounds = (frames.positions.min(axis=(0, 1)), frames.positions.max(axis=(0, 1)))   # viewers' culling
        from ..io.gltf_write import write_glb_with_clip
        clip = sampled_clip(name, times, keys, character.skeleton.rest_pose)
        write_glb_with_clip(args.character, args.output, character, clip, bounds, keep_animations=False)
    else:
        source = args.character if Path(args.character).suffix.lower() in (".glb", ".gltf") else None
        report = write_frames(args.output, frames, times, args.format, character, source, args.quantize, name,
                              args.backend)
        if report is not None:
            print(f"{args.output}: morph targets {report.bytes_per_frame_vertex:.2f} bytes per frame per vertex "
                  f"({report.quantized_frames} of {report.frames} frames quantized, {report.unique_frames} "
                  f"written; largest position error {report.max_error:.1e} of the bounding-box diagonal)")
    if args.png:
        from ..render.sheet import save_contact_sheet
        save_contact_sheet(args.png, frames.positions, frames.faces, times,
                           title=f"{Path(args.character).name}: {args.method}, {args.weights} weights")
    ms = frames.frame_ms
    print(f"{args.output}: {len(ms)} frame(s) × {poser.n} vertices, {args.method} ({args.weights} weights) on "
          f"{args.backend}: bind {poser.bind_ms:.0f} ms; per frame median {median(ms):.3f} ms, "
          f"min {ms.min():.3f}, max {ms.max():.3f}; {1e3 / median(ms):.0f} frames/s")


def pose_input(character, *, clip: str | Clip | None = None, motion: str | None = None, pose: str | None = None,
               rest: bool = False, time=None, frames: str | None = None, fps: float = 30.0,
               kind: str = "npz") -> tuple:
    """(local pose (F, J, ...) as ``Clip.sample`` gives it, times (F,) float64 seconds, name: the
    clip's, the pose file's stem or "rest") that ``nrpose pose`` poses for these options: the
    rest pose, a pose file, or a clip (a name of the character's, or a :class:`Clip`, e.g. a
    retargeted one) or ``motion`` (BVH, or a libigl DMAT animation at ``fps``) sampled at
    ``time`` (seconds), ``frames`` (``A:B[:STEP]``) or every frame at ``fps``.
    ``kind``: :func:`frames_output_kind` of the output ("glb" needs strictly increasing times)."""
    skel = character.skeleton
    if rest:
        return skel.rest_pose, np.zeros(1), "rest"
    if pose:
        from ..io.poses import load_pose
        return load_pose(pose, skel), np.zeros(1), Path(pose).stem
    if isinstance(clip, Clip):
        source = clip
    elif clip:
        source = character.clip(clip)
    elif Path(motion).suffix.lower() == ".dmat":
        from ..io.tgf import read_dmat_animation      # libigl DMAT motions only

        source = read_dmat_animation(motion, skel, fps)
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
    return source.sample(times), times, source.name


def posed_frames(poser: CharacterPoser, local, progress=None, stream: bool = False):
    """``poser.pose(local)``, refused (NrposeError) when a coordinate is not finite; with
    ``stream``, ``poser.stream(local)``, each of whose batches is refused as it is posed."""
    if stream:
        frames = poser.stream(local, progress=progress)
        return dataclasses.replace(frames, batches=finite_batches(frames.batches))
    frames = poser.pose(local, progress=progress)
    check_finite(frames.positions)
    return frames


def finite_batches(batches):
    """The batches of posed frames, each checked by :func:`check_finite` before it is passed on."""
    for batch in batches:
        check_finite(batch)
        yield batch


def check_finite(positions: np.ndarray) -> None:
    """NrposeError when a posed coordinate is not finite."""
    if not np.isfinite(positions).all():
        raise NrposeError("posing produced non-finite coordinates; please report this input")


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
