"""``nrpose retarget``: a motion from one rig onto another, written as glTF or BVH.

    nrpose retarget SOURCE (.bvh|.glb|.gltf) TARGET (.glb|.gltf) [--source-clip NAME]
                    [--map MAP.json] [--in-place] [--fps F] [--show-map]
                    -o OUT (.glb|.bvh) [--png SHEET.png]

The retargeting itself is :mod:`nrpose.retarget`. Outputs:

* ``OUT.glb``: the target file with the retargeted clip appended as a new
  animation (named after the source clip; `` (2)``... if that name is taken):
  one sampler per mapped joint's node rotation (float32 quaternions) and one
  for the root-motion node's translation, LINEAR, keyed at ``k / fps``. The
  original content (meshes, skins, materials, textures, other animations) is
  kept: every buffer of the target is copied into the single GLB buffer (a
  ``.gltf`` with external buffers or images becomes self-contained) and the
  new data is appended after it. Pose it with ``nrpose pose OUT.glb --clip
  NAME``.
* ``OUT.bvh``: the target skeleton and the clip as BVH
  (:mod:`nrpose.formats.bvh_write`), frame time ``1 / fps``.
* ``--png``: a contact sheet of the retargeted character (linear blend
  skinning of its meshes in numpy) with the source skeleton, scaled by the
  root-motion scale, drawn beside it; every panel is centred horizontally on
  the hips.
* ``--show-map``: prints the joint mapping and the joints left unmapped
  (alone, or with ``-o``).

Bad input (unknown joints in the map, no motion, no mapped joint, wrong
extensions) raises :class:`~nrpose.errors.NrposeError` before anything is
written; files are written through :func:`nrpose.meshio.atomic_path`.
"""
from __future__ import annotations

import argparse
import mimetypes
from pathlib import Path

import numpy as np
import pygltflib

from .checks import within_float32
from .errors import InputError, NrposeError
from .meshio import check_writable

__all__ = ["add_retarget_parser", "cmd_retarget", "write_glb_with_clip", "save_retarget_sheet"]

SOURCE_SUFFIXES = (".bvh", ".glb", ".gltf")
TARGET_SUFFIXES = (".glb", ".gltf")
OUTPUT_SUFFIXES = (".glb", ".bvh")


def add_retarget_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``retarget`` subcommand to an argparse subparsers object."""
    p = subparsers.add_parser("retarget", help="play a motion (BVH or glTF clip) on another rig (glTF)")
    p.add_argument("source", help="motion: .bvh, or a .glb/.gltf with an animation")
    p.add_argument("target", help="character to drive: .glb or .gltf")
    p.add_argument("--source-clip", help="animation of a glTF source, by name (default: its first)")
    p.add_argument("--map", help='joint map JSON {"TargetJoint": "SourceJoint"}, overrides the automatic one')
    p.add_argument("--in-place", action="store_true", help="no horizontal root motion")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second of the output (default 30)")
    p.add_argument("--show-map", action="store_true", help="print the joint mapping and the unmapped joints")
    p.add_argument("-o", "--output", help="OUT.glb (target + new animation) or OUT.bvh (target skeleton)")
    p.add_argument("--png", help="write a contact sheet PNG (retargeted character beside the source skeleton)")
    p.set_defaults(func=cmd_retarget)
    return p


def _suffix(path: str, allowed: tuple[str, ...], what: str) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise InputError(f"{path}: {what} must end in {', '.join(allowed)}")
    return suffix


def cmd_retarget(args) -> None:
    from .character import load_character
    from .retarget import format_map, joint_map, load_map, make_clip, retarget_pose

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
    if not mapping:
        raise InputError(f"no joint of {args.target} maps to a joint of {args.source}: the rigs share no known "
                         "joint names; give a joint map (--map MAP.json, {\"TargetJoint\": \"SourceJoint\"})")
    if not source.clips:
        raise InputError(f"{args.source}: has no animation: no motion to retarget")
    clip = source.clip(args.source_clip) if args.source_clip else source.clips[0]
    times, local, plan = retarget_pose(source, clip, target, mapping, args.in_place, args.fps)
    result = make_clip(clip.name, times, local, plan, target.skeleton)

    out = Path(args.output)
    if out.suffix.lower() == ".glb":
        name = write_glb_with_clip(args.target, out, target, result)
    else:
        from .formats.bvh_write import write_bvh
        write_bvh(out, target.skeleton, local, 1.0 / args.fps, position_joints=[plan.root])
        name = result.name
    if args.png:
        save_retarget_sheet(args.png, source, clip, target, times, local, plan,
                            title=f"{Path(args.target).name} <- {Path(args.source).name} ({clip.name})")
    print(f"{out}: animation {name!r}, {len(times)} frames at {args.fps:g} fps ({times[-1]:.2f} s), "
          f"{len(plan.mapping)} of {target.skeleton.num_joints} target joints mapped, root motion x{plan.scale:.4g}"
          f"{' in place' if args.in_place else ''}, lift {plan.lift:+.3g}")


# --------------------------------------------------------------------------- glTF

def _joint_nodes(path: Path, gltf: pygltflib.GLTF2, buffers: list[bytes], names) -> np.ndarray:
    """Node index of each skeleton joint, as :func:`nrpose.formats.gltf.load_gltf` orders them."""
    from .formats import gltf as gltf_format

    acc = gltf_format._Accessors(path, gltf, buffers)
    binds = gltf_format._skin_binds(path, gltf, acc)
    nodes = gltf_format._Nodes(path, gltf)
    skeleton, node_to_joint, _ = gltf_format._skeleton(gltf, nodes, binds)
    if tuple(skeleton.names) != tuple(names):
        raise NrposeError(f"{path}: its skeleton changed since it was loaded")
    joint_nodes = np.empty(skeleton.num_joints, np.int64)
    joint_nodes[node_to_joint[node_to_joint >= 0]] = np.flatnonzero(node_to_joint >= 0)
    return joint_nodes


def write_glb_with_clip(target_path, out_path, target, clip) -> str:
    """Write the target glTF plus ``clip`` (a Clip of its skeleton) as a new animation, as a GLB.

    Returns the animation's name. Every track of the clip becomes a channel on
    its joint's node (float32, the track's times and interpolation; CUBICSPLINE
    is not written).
    """
    from .formats import gltf as gltf_format
    from .gltf_export import Blob
    from .meshio import atomic_path

    path = Path(target_path)
    gltf, buffers = gltf_format._read_document(path)
    joint_nodes = _joint_nodes(path, gltf, buffers, target.skeleton.names)
    blob = Blob(gltf)
    starts = [blob.append(bytes(b)) for b in buffers]
    for view in gltf.bufferViews:
        view.byteOffset = (view.byteOffset or 0) + starts[view.buffer]
        view.buffer = 0
    for i, image in enumerate(gltf.images or []):
        if image.uri is not None and not image.uri.startswith("data:"):
            import urllib.parse
            try:
                data = (path.parent / urllib.parse.unquote(image.uri)).read_bytes()
            except OSError as exc:
                raise InputError(f"{path}: image {i}: cannot read {image.uri!r} ({exc.strerror})") from None
            image.mimeType = image.mimeType or mimetypes.guess_type(image.uri)[0] or "image/png"
            image.bufferView, image.uri = blob.raw(data), None
    taken = {a.name for a in gltf.animations or []}
    name, k = clip.name, 2
    while name in taken:
        name, k = f"{clip.name} ({k})", k + 1
    animation = pygltflib.Animation(name=name, channels=[], samplers=[])
    inputs = {}
    for track in clip.tracks:
        if track.interpolation == "CUBICSPLINE":
            raise InputError("write_glb_with_clip writes LINEAR and STEP tracks only")
        within_float32(track.values, f"retargeted {track.path} track of joint {track.joint}")
        key = track.times.tobytes()
        if key not in inputs:
            inputs[key] = blob.add(track.times.astype(np.float32), "SCALAR", minmax=True)
        output = blob.add(track.values.astype(np.float32),
                          {"rotation": "VEC4", "translation": "VEC3", "scale": "VEC3"}[track.path])
        animation.samplers.append(pygltflib.AnimationSampler(input=inputs[key], output=output,
                                                             interpolation=track.interpolation))
        animation.channels.append(pygltflib.AnimationChannel(
            sampler=len(animation.samplers) - 1,
            target=pygltflib.AnimationChannelTarget(node=int(joint_nodes[track.joint]), path=track.path)))
    gltf.animations = list(gltf.animations or []) + [animation]
    data = blob.bytes()
    gltf.buffers = [pygltflib.Buffer(byteLength=len(data))]
    gltf.set_binary_blob(data)
    with atomic_path(Path(out_path)) as tmp:
        gltf.save_binary(str(tmp))
    return name


# --------------------------------------------------------------------------- contact sheet

def _skinned_frames(character, G: np.ndarray):
    """Posed vertices (F, V, 3) of all meshes by linear blend skinning, and the faces."""
    from .pose.skinning import lbs_reference

    mats = character.skin_matrices(G)
    verts, faces, offset = [], [], 0
    for mesh in character.meshes:
        if mesh.joints is None:
            continue
        verts.append(np.stack([lbs_reference(mesh.vertices, mesh.joints, mesh.weights, M) for M in mats]))
        faces.append(mesh.faces + offset)
        offset += len(mesh.vertices)
    if not verts:
        return None, None
    return np.concatenate(verts, axis=1), np.concatenate(faces)


def save_retarget_sheet(path, source, clip, target, times, local, plan, title: str = "",
                        max_panels: int = 8) -> list[int]:
    """Contact sheet: retargeted target (mesh, or bones without one) with the source skeleton beside it."""
    from .preview import _spread
    from .sheet import save_contact_sheet, view_matrix

    F = len(times)
    pick = np.arange(F) if F <= max_panels else _spread(F, max_panels)
    Gt = target.skeleton.forward_kinematics(_take(local, pick))
    Gs = source.skeleton.forward_kinematics(clip.sample(times[pick]))
    hips_t = Gt[:, plan.root, :3, 3].copy()
    hips_s = Gs[:, plan.mapping[plan.root], :3, 3].copy()
    hips_t[:, 1] = 0.0
    hips_s[:, 1] = 0.0
    V, faces = _skinned_frames(target, Gt)
    tb = target.skeleton.bones()
    t_ends, _ = tb.pose(Gt)
    if V is None:
        V = t_ends.reshape(len(pick), -1, 3)
    V = V - hips_t[:, None]
    height = float(np.ptp(target.skeleton.rest_globals()[:, 1, 3])) or 1.0
    right = view_matrix()[0].copy()
    right[1] = 0.0
    right /= np.linalg.norm(right) or 1.0
    sb = source.skeleton.bones()
    s_ends, _ = sb.pose(Gs)
    s_ends = plan.scale * (s_ends - hips_s[:, None, None]) + 0.75 * height * right
    return save_contact_sheet(path, V, faces, times[pick], title=title, max_panels=max_panels,
                              handles_per_frame=list(s_ends))


def _take(local, index):
    from .skeleton import LocalPose

    return LocalPose(local.translation[index], local.rotation[index], local.scale[index])
