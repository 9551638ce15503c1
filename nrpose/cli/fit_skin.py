"""``nrpose fit-skin``: NR-MLS exported as standard skinning (fitted LBS weights in a copy of the glTF)."""
from __future__ import annotations

import json
import time
from dataclasses import astuple
from pathlib import Path

import numpy as np

from ..errors import NrposeError
from ..fit.character_skin import (FittedSkin, character_height, error_table, fit_character, fitted_positions,
                                  nrmls_targets, with_computed_skin)
from ..fit.helper_fit import add_helpers
from ..fit.helper_joints import rule_locals
from ..fit.helper_keys import KEY_TOLERANCE, helper_keys
from ..fit.helper_tracks import fit_helper_tracks, refit_with_tracks
from ..fit.rom import ROM_DEGREES, range_of_motion
from ..fit.skin_file import skinned_primitives, stored_skin, write_fitted_glb
from ..io import load_character
from ..io.files import atomic_path
from ..io.gltf_write import float32_times
from ..io.poses import load_pose
from ..io.tgf import dmat_is_pose, read_dmat_animation
from ..model.character import Character
from ..model.skeleton import LocalPose, concat_poses
from ..model.timing import sample_times
from ..pose.poser import WEIGHTS, CharacterPoser
from .common import character_with_weights, check_outputs
from .pose import motion_clip

FLAGS = {"weights": "--weights", "alpha": "--alpha", "influences": "--influences", "skeleton": "--skeleton"}
INFLUENCES = (4, 8)
BAKE_BYTES = 12      # morph-target bake: one float32 xyz per vertex per frame
BAKE_SECONDS, BAKE_FPS = 10.0, 30.0
MAX_VERTEX_FRAMES = 40_000_000   # poses x vertices held at once (targets and fitted, ~1.5 GB)
MAX_POSES = 10_000   # poses of one set: the helper fit's time grows with them (Mannequin trains on 1,159)


def add_parser(sub) -> None:
    p = sub.add_parser("fit-skin", help="fit LBS weights that reproduce NR-MLS; write a skinned glTF any engine "
                                        "plays (a copy of a glTF character, or a new file for a mesh + skeleton)")
    p.add_argument("character", help=".glb/.gltf character (skinned; the output is a copy of it), or a mesh "
                                     "(OBJ, OFF, PLY, STL, .mesh) with --skeleton (the output is a new skinned glTF)")
    p.add_argument("--skeleton", help="skeleton of a mesh character (.tgf or .bvh, whose motion is its clip)")
    p.add_argument("--weights-file", help="libigl weight DMAT of a mesh + TGF character (rows = vertices, columns = "
                                          "bones in TGF order): its skin weights, whose joints the fit starts from")
    p.add_argument("--method", choices=("nrmls",), default="nrmls", help="deformer fitted (nrmls)")
    p.add_argument("--weights", choices=WEIGHTS, default=None,
                   help="NR-MLS weights (default: authored; heat for a mesh + skeleton without --weights-file)")
    p.add_argument("--alpha", type=float, default=1.0, help="weight exponent for distance weights (default 1)")
    p.add_argument("--train", nargs="+", default=[], metavar="CLIP|BVH|GLB|DMAT|POSE",
                   help="training motion: a clip of the character, a BVH or glTF (its last clip) on its "
                        "skeleton, a libigl animation or pose DMAT (TGF skeleton), or a pose JSON")
    p.add_argument("--holdout", nargs="+", default=[], metavar="CLIP|BVH|GLB|DMAT|POSE",
                   help="motions evaluated in the report but not trained on")
    p.add_argument("--export", nargs="+", default=[], metavar="BVH|GLB|DMAT",
                   help="BVH/glTF/DMAT animations added to the output as animations (the source's clips are kept)")
    p.add_argument("--rom-degrees", type=float, default=ROM_DEGREES,
                   help=f"range-of-motion sweep about each local axis, degrees (default {ROM_DEGREES:g}); a humanoid "
                        "also gets anatomical poses (0: no range of motion at all)")
    p.add_argument("--fps", type=float, default=30.0, help="clip sampling rate for training and evaluation, and the "
                                                                 "frame rate of a DMAT animation (default 30)")
    p.add_argument("--influences", type=int, default=4, help="joints per vertex: 4 or 8 (default 4)")
    p.add_argument("--helpers", type=int, default=0,
                   help="helper joints added where the residual is largest (default 0)")
    p.add_argument("--helper-tracks", choices=("rule", "fitted"), default="rule",
                   help="helper animation in the file: 'rule' (a fixed rule of the joints' rotations, fitted "
                        "on the training poses; default) or 'fitted' (solved per frame against each written "
                        "clip's NR-MLS, weights fitted the same way; motions not written by nrpose get the rule)")
    p.add_argument("--key-tolerance", type=float, default=KEY_TOLERANCE,
                   help=f"helper channels keep the keys a player needs for each helper's share of a vertex's "
                        f"position to stay within this fraction of the character's height at every frame "
                        f"(default {KEY_TOLERANCE:g}; 0: a key every frame)")
    p.add_argument("-o", "--output", required=True, help="OUT.glb")
    p.add_argument("--report", help="R.json: errors vs NR-MLS, sizes, times")
    p.set_defaults(func=run, flags=FLAGS)


def motion(character, spec: str, fps: float, pose_ok: bool = True):
    """(name, LocalPose (F, J, ...), clip or None) of a --train/--holdout/--export entry."""
    names = [c.name for c in character.clips]
    suffix = Path(spec).suffix.lower()
    if spec in names:
        clip = character.clip(spec)
    elif suffix == ".json" or (suffix == ".dmat" and dmat_is_pose(spec, character.skeleton)):
        if not pose_ok:
            raise NrposeError(f"{spec}: a pose (one frame); --export takes animations")
        return spec, LocalPose(*(a[None] for a in astuple(load_pose(spec, character.skeleton)))), None
    elif suffix == ".dmat":
        clip = read_dmat_animation(spec, character.skeleton, fps)
    elif Path(spec).suffix.lower() in (".bvh", ".glb", ".gltf"):
        # a glTF motion: its last clip (where `nrpose retarget` puts the retargeted one)
        loaded = load_character(spec)
        if not loaded.clips:
            raise NrposeError(f"{spec}: no animation in the file")
        clip = motion_clip(Character(loaded.skeleton, (), loaded.clips[-1:]), character.skeleton, spec)
    else:
        raise NrposeError(f"{spec!r}: not a clip of the character ({', '.join(map(repr, names)) or 'none'}), "
                          f"a .bvh, a .glb on its skeleton, a libigl .dmat{' or a pose .json' if pose_ok else ''}")
    return spec, clip.sample(sample_times(clip.duration, fps)), clip


def run(args) -> None:
    if args.influences not in INFLUENCES:
        raise NrposeError(f"--influences {args.influences}: expected 4 or 8")
    if args.helpers < 0:
        raise NrposeError(f"--helpers {args.helpers}: expected a count >= 0")
    if not args.train:
        raise NrposeError("no training motion: give --train CLIP|BVH|GLB|DMAT|POSE (the range of motion is added "
                          "to it)")
    if not (np.isfinite(args.fps) and args.fps > 0):
        raise NrposeError(f"--fps {args.fps}: expected a positive number")
    if not (np.isfinite(args.rom_degrees) and 0 <= args.rom_degrees <= 180):
        raise NrposeError(f"--rom-degrees {args.rom_degrees}: expected 0 to 180")
    if not (np.isfinite(args.key_tolerance) and 0 <= args.key_tolerance <= 0.1):
        raise NrposeError(f"--key-tolerance {args.key_tolerance}: expected a fraction of the height from 0 to 0.1")
    check_outputs(args.output, (".glb",), None)
    if args.report:
        check_outputs(args.report, (".json",), None)
    source = args.character if Path(args.character).suffix.lower() in (".glb", ".gltf") else None
    character = character_with_weights(args.character, args.skeleton, args.weights_file)
    weights = args.weights or ("heat" if source is None and not args.weights_file else "authored")
    allowed = [None] * len(character.meshes) if source is None else \
        [None if p is None else p[3] for p in skinned_primitives(source, character)]
    train = [motion(character, s, args.fps) for s in args.train]
    holdout = [motion(character, s, args.fps) for s in args.holdout]
    export = [motion(character, s, args.fps, pose_ok=False) for s in args.export]
    local = concat_poses([m[1] for m in train])
    rom_frames = 0
    if args.rom_degrees > 0:
        rom = range_of_motion(character.skeleton, args.rom_degrees)
        rom_frames = len(rom.rotation)
        local = concat_poses([local, rom])
    V = sum(len(m.vertices) for m in character.meshes)
    new_clips = [m[2] for m in export if m[2] is not None and m[2] not in character.clips]
    written = tuple(character.clips) + tuple(new_clips)     # the file's animations
    held = [("the training set", len(local.rotation))] + [(h[0], len(h[1].rotation)) for h in holdout]
    if args.helpers:     # each written clip sampled whole for its helpers' channels (and posed, for fitted tracks)
        held += [(f"clip {c.name!r}", len(sample_times(c.duration, args.fps))) for c in written]
    for clip in written:        # the file stores key times as float32: refused now, not after the fit
        for track in clip.tracks:
            float32_times(track.times, f"clip {clip.name!r}")
    for name, frames in held:
        if frames > MAX_POSES:
            raise NrposeError(f"{name}: {frames:,} poses, more than {MAX_POSES:,}; lower --fps or --rom-degrees, "
                              "or train on less")
        if frames * V > MAX_VERTEX_FRAMES:
            raise NrposeError(f"{name}: {frames} poses x {V} vertices is more than {MAX_VERTEX_FRAMES:,} at once; "
                              "lower --fps or --rom-degrees, or train on less")
    if args.helpers and not written:
        raise NrposeError(f"--helpers {args.helpers}: helper joints move only in the file's animations and it "
                          "has none; add one with --export MOTION, or use --helpers 0")
    if source is None:      # the skin the fit starts from: the weights file's, else the NR-MLS weights'
        character = with_computed_skin(character, weights, args.alpha)
    poser = CharacterPoser(character, method="nrmls", weights=weights, alpha=args.alpha)
    t0 = time.perf_counter()
    G, targets = nrmls_targets(poser, local)
    target_s = time.perf_counter() - t0
    fitted = fit_character(character, G, targets, args.influences, allowed)
    base_seconds = fitted.seconds
    fitted, helper_log = add_helpers(character, fitted, G, local, targets, args.helpers, args.influences, allowed,
                                     per_frame=args.helper_tracks == "fitted")
    fitted_tracks = args.helper_tracks == "fitted" and bool(fitted.helpers)
    if fitted_tracks:
        fitted = refit_with_tracks(character, fitted, G, local, targets, args.influences, allowed)
    fitted = stored_skin(fitted)        # the written clips' tracks and the report use the file's weights

    def tracks_of(pose, G_pose=None, positions=None):
        """Helper tracks (F, H, 4, 4) fitted to pose's NR-MLS (None in rule mode)."""
        if not fitted_tracks:
            return None
        if positions is None:
            G_pose, positions = nrmls_targets(poser, pose)
        return fit_helper_tracks(character, fitted, G_pose, pose, positions)

    tracks = [tracks_of(clip.sample(sample_times(clip.duration, args.fps))) for clip in written] \
        if fitted_tracks else None
    size = write_fitted_glb(source, args.output, character, fitted, new_clips, args.fps, tracks, args.key_tolerance)
    print(f"{args.output}: {V} vertices, {args.influences} influences, {len(fitted.helpers)} helper joints "
          f"fitted to {len(G)} poses ({rom_frames} range of motion) in {fitted.seconds:.1f} s "
          f"(NR-MLS targets {target_s:.1f} s)")
    if args.report:
        # the file's own weights, as a baseline: how far plain LBS of the source is from NR-MLS
        authored = FittedSkin(tuple(None if m.rigid_joint is not None else m.joints for m in character.meshes),
                              tuple(None if m.rigid_joint is not None else m.weights for m in character.meshes), 0.0)
        errors, baseline = {}, {}
        for name, pose, clip in [("training", local, None)] + holdout:
            Gh, Th = (G, targets) if pose is local else nrmls_targets(poser, pose)
            # fitted tracks where the file holds them: the training set's and the written clips'
            played = pose is local or (clip is not None and (clip in character.clips or name in args.export))
            helper_local = tracks_of(pose, Gh, Th) if played else None
            if helper_local is None and fitted.helpers:
                helper_local = rule_locals(fitted.helpers, character.skeleton, pose)
            if clip is not None and fitted.helpers:     # a clip's helpers as the file plays them: from its keys
                helper_local = helper_keys(character, fitted, Gh, helper_local, sample_times(clip.duration, args.fps),
                                           args.key_tolerance)[1]
            errors[name] = error_table(character, fitted_positions(character, fitted, Gh, pose, helper_local), Th)
            baseline[name] = {k: v for k, v in error_table(character, fitted_positions(character, authored, Gh),
                                                           Th).items() if k != "regions"}
        # the file's animations: the source's clips and the --export ones, at --fps
        frames = sum(len(sample_times(c.duration, args.fps)) for c in written)
        report = {
            "character": str(args.character), "skeleton": args.skeleton, "weights_file": args.weights_file,
            "weights": weights, "vertices": V, "height": character_height(character),
            "influences": args.influences, "helpers": len(fitted.helpers), "helpers_requested": args.helpers,
            "helper_tracks": args.helper_tracks, "key_tolerance": args.key_tolerance,
            "helper_placement": helper_log,
            "training": {"motions": list(args.train), "poses": int(len(G)), "range_of_motion_poses": rom_frames,
                         "range_of_motion_degrees": args.rom_degrees},
            "fit_seconds": fitted.seconds, "weights_seconds": base_seconds,
            "helpers_seconds": fitted.seconds - base_seconds, "targets_seconds": target_s, "errors": errors,
            "authored_lbs_errors": baseline,
            "size": {"file_bytes": size, "source_bytes": Path(args.character).stat().st_size,
                     "animations": len(character.clips) + len(new_clips), "animation_frames": frames,
                     "morph_bake_bytes_of_animations": BAKE_BYTES * frames * V,
                     "morph_bake_bytes_10s": int(BAKE_BYTES * BAKE_SECONDS * BAKE_FPS * V)},
        }
        with atomic_path(args.report) as tmp:
            Path(tmp).write_text(json.dumps(report, indent=1))
        for name, e in errors.items():
            b = baseline[name]
            print(f"  {name}: RMS {100 * e['rms_fraction']:.3f} % of height, max {100 * e['max_fraction']:.3f} %"
                  f" ({e['frames']} frames; LBS with the skin weights: RMS {100 * b['rms_fraction']:.3f} %, "
                  f"max {100 * b['max_fraction']:.3f} %)")
