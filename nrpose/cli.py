"""Command line: ``nrpose deform`` and ``nrpose demo``.

Every user mistake (bad file, bad option, no OpenCL platform) ends with one
line on stderr and exit status 2; outputs are written to a temporary name
and renamed, so a failed run leaves no output behind.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from .pose.blend import BLENDS, LEVERS
from .pose.mls import BACKENDS, Deformer
from .character import check_frame_count
from .errors import NrposeError


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, status 2 (argparse's default prints usage too)
        raise _UsageError(f"{self.prog}: {message}")


class _UsageError(Exception):
    pass


def _median_ms(fn, repeat: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(max(repeat, 1)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)), result


def cmd_deform(args) -> None:
    from .handles import check_alpha, load_handles
    from .meshio import SUFFIXES, check_writable, read_geometry, write_geometry

    _check_outputs(args.output, SUFFIXES, args.png)
    geometry = read_geometry(args.input)
    rest, pose, file_alpha = load_handles(args.handles)
    alpha = check_alpha(args.alpha) if args.alpha is not None else (file_alpha or 1.0)
    t0 = time.perf_counter()
    distances = None
    if args.weights != "euclidean":
        from .posing import surface_distances
        distances = surface_distances(geometry.vertices, geometry.faces if len(geometry.faces) else None,
                                      rest.points, rest.segments, args.weights)
    deformer = Deformer(geometry.vertices, rest, alpha=alpha, blend=args.blend, lever=args.lever,
                        distances=distances, backend=args.backend)
    bind_ms = 1e3 * (time.perf_counter() - t0)
    pose_ms, posed = _median_ms(lambda: deformer.pose(pose), 1)
    if not np.isfinite(posed).all():  # never expected: the blend is total; guard the contract
        raise NrposeError("deformation produced non-finite coordinates; please report this input")
    write_geometry(args.output, posed, geometry.faces)
    if args.png:
        from .preview import save_preview
        save_preview(args.png, [("rest", geometry.vertices, geometry.faces),
                                ("posed", posed, geometry.faces)],
                     handles=[(rest.points, rest.segments), (pose.handles.points, pose.handles.segments)])
    print(f"{args.output}: {len(posed)} points, {rest.count} handles, alpha {alpha:g}, {args.blend} blend, "
          f"{args.backend}: bind {bind_ms:.1f} ms, pose {pose_ms:.2f} ms")


def cmd_demo(args) -> None:
    """Embedded default: the project's capsule humanoid walking (NR-MLS on PoCL: frames,
    animated .glb, contact sheet) and the paper's Figure 3 box (before/after PNGs)."""
    if args.frames < 1 or args.repeat < 1:
        raise NrposeError("--frames and --repeat must be at least 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"device: {deformer_device()}")
    _demo_humanoid(out, args.frames)
    _demo_box(out, args.repeat)


def _demo_humanoid(out: Path, n_frames: int) -> None:
    from .posing import CharacterPoser
    from .rigs.humanoid import humanoid
    from .sheet import save_contact_sheet

    t0 = time.perf_counter()
    character = humanoid()
    build_ms = 1e3 * (time.perf_counter() - t0)
    clip = character.clip("walk")
    times = np.linspace(0.0, clip.duration, n_frames)
    poser = CharacterPoser(character, method="nrmls", weights="authored")
    frames = poser.pose(clip.sample(times), progress=_progress)
    _write_frames(str(out / "walk.npz"), frames, times, "ply", character)
    _write_frames(str(out / "walk.glb"), frames, times, "ply", character)
    segs = poser.bones.pose(character.skeleton.forward_kinematics(clip.sample(times)))[0]
    save_contact_sheet(out / "walk.png", frames.positions, frames.faces, times, max_panels=8,
                       handles_per_frame=list(segs),
                       title=f"capsule humanoid, NR-MLS on PoCL ({poser.n} vertices, {len(poser.bones)} bones)")
    ms = frames.frame_ms
    print(f"humanoid walk: {poser.n} vertices, {character.skeleton.num_joints} joints ({len(poser.bones)} bone "
          f"handles), built in {build_ms:.0f} ms, bound in {poser.bind_ms:.0f} ms")
    print(f"  {len(ms)} frames: per frame median {np.median(ms):.3f} ms, min {ms.min():.3f}, max {ms.max():.3f} "
          f"({1e3 / np.median(ms):.0f} frames/s)")
    print(f"  wrote {out / 'walk.npz'}, {out / 'walk.glb'} (morph-target animation), {out / 'walk.png'}")


def _demo_box(out: Path, repeat: int) -> None:
    """The paper's Figure 3: a 6,006-point box twisted and bent by 4 segments, on PoCL."""
    from .meshio import write_geometry
    from .preview import save_preview
    from .rigs import box

    points, rest = box.box_points(), box.rest_handles()
    bind_ms, deformer = _median_ms(lambda: Deformer(points, rest, backend="opencl"), 1)
    reference = Deformer(points, rest, backend="numpy")
    print(f"Figure 3 box: {len(points)} points, {rest.count} segment handles; bind {bind_ms:.1f} ms")
    panels, handles = [("rest", points, None)], [(rest.points, rest.segments)]
    for name, (twist, bend) in box.POSES.items():
        pose = box.chain_pose(twist, bend)
        pose_ms, posed = _median_ms(lambda: deformer.pose(pose), repeat)
        ref_ms, ref = _median_ms(lambda: reference.pose(pose), 3)
        err = float(np.abs(posed - ref).max())
        write_geometry(out / f"box_{name}.ply", posed)
        panels.append((f"{name} (twist {twist:g}°, bend {bend:g}°)", posed, None))
        handles.append((pose.handles.points, pose.handles.segments))
        print(f"  {name:<10} pose {pose_ms:7.3f} ms (median of {repeat}) | numpy reference "
              f"{ref_ms:7.2f} ms ({ref_ms / pose_ms:5.0f}x) | max |PoCL - reference| {err:.1e}")
    save_preview(out / "box_before.png", panels[:1], handles=handles[:1])
    save_preview(out / "box_after.png", panels, handles=handles)
    print(f"  wrote {out / 'box_before.png'}, {out / 'box_after.png'} and box_*.ply")


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


def _progress(done: int, total: int) -> None:
    if total > 1 and sys.stderr.isatty():
        width = 30
        fill = width * done // total
        print(f"\r[{'#' * fill}{'.' * (width - fill)}] {done}/{total} frames", end="", file=sys.stderr)
        if done == total:
            print(file=sys.stderr)


def cmd_pose(args) -> None:
    from .character import load_character, load_pose, sample_times
    from .posing import CharacterPoser

    kind = _frames_output_kind(args.output)
    if kind == "dir":   # created if needed: its parent must exist
        parent = Path(args.output).resolve().parent
        if not parent.is_dir() or Path(args.output).is_file():
            raise NrposeError(f"{args.output}: cannot make a frame directory there (is {parent} a directory?)")
    _check_outputs(args.output if kind != "dir" else None, None, args.png)
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
            clip = _motion_clip(motion, skel, args.motion)
        if args.time and args.frames:
            raise NrposeError("give either --time or --frames, not both")
        times = (np.asarray(args.time, dtype=np.float64) if args.time
                 else parse_frames(args.frames, args.fps) if args.frames
                 else sample_times(clip.duration, args.fps))
        if kind == "glb" and (np.diff(times) <= 0).any():
            raise NrposeError("--time: an animated .glb needs strictly increasing times; sort them or "
                              "write .npz or a directory")
        local = clip.sample(times)
    poser = CharacterPoser(character, method=args.method, weights=args.weights, alpha=args.alpha,
                           backend=args.backend, blend=args.blend)
    frames = poser.pose(local, progress=_progress)
    if not np.isfinite(frames.positions).all():
        raise NrposeError("posing produced non-finite coordinates; please report this input")
    _write_frames(args.output, frames, times, args.format, character)
    if args.png:
        from .sheet import save_contact_sheet
        save_contact_sheet(args.png, frames.positions, frames.faces, times,
                           title=f"{Path(args.character).name}: {args.method}, {args.weights} weights")
    ms = frames.frame_ms
    print(f"{args.output}: {len(ms)} frame(s) × {poser.n} vertices, {args.method} ({args.weights} weights) on "
          f"{args.backend}: bind {poser.bind_ms:.0f} ms; per frame median {np.median(ms):.3f} ms, "
          f"min {ms.min():.3f}, max {ms.max():.3f}; {1e3 / np.median(ms):.0f} frames/s")


def _motion_clip(motion, skel, path):
    """The motion file's clip, on a character whose skeleton has the motion's joint names."""
    from .character import Clip, Track

    missing = [n for n in motion.skeleton.names if n not in skel.names]
    if missing:
        raise NrposeError(f"{path}: joint {missing[0]!r} (and {len(missing) - 1} more) not in the character's "
                          "skeleton; --motion drives the skeleton it was recorded on "
                          "(retarget other rigs first)")
    clip = motion.clips[0]
    index = [skel.index(n) for n in motion.skeleton.names]
    tracks = tuple(Track(index[t.joint], t.path, t.times, t.values, t.interpolation) for t in clip.tracks)
    return Clip(clip.name, clip.duration, skel.rest_pose, tracks)


def _frames_output_kind(out: str) -> str:
    """"npz", "glb" or "dir" for ``nrpose pose -o OUT``; NrposeError for other extensions."""
    suffix = Path(out).suffix.lower()
    if suffix in (".npz", ".glb"):
        return suffix[1:]
    if suffix == "":
        return "dir"
    raise NrposeError(f"{out}: output must end in .npz or .glb, or be a directory")


def _check_outputs(out: str, suffixes, png: str | None) -> None:
    """Refuse unusable output names before any work (nothing is written on failure)."""
    from .meshio import check_writable

    if out is not None:
        if suffixes is not None and Path(out).suffix.lower() not in suffixes:
            raise NrposeError(f"{out}: unknown output extension; use one of {', '.join(suffixes)}")
        check_writable(out)
    if png:
        if Path(png).suffix.lower() != ".png":
            raise NrposeError(f"--png {png}: the preview must end in .png")
        check_writable(png)


def _write_frames(out: str, frames, times: np.ndarray, fmt: str, character) -> None:
    from .meshio import atomic_path, write_geometry

    path = Path(out)
    kind = _frames_output_kind(out)
    if kind == "npz":
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, positions=frames.positions, faces=frames.faces, times=times,
                         mesh_names=np.array(frames.mesh_names), mesh_offsets=frames.mesh_offsets)
    elif kind == "glb":
        from .gltf_export import write_animated_glb
        write_animated_glb(path, character, frames.positions, times, frames.mesh_offsets)
    else:
        # all frames go to a temporary sibling directory first; only then are the
        # previous run's frame files removed and the new ones moved in
        import shutil
        import tempfile

        path.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".nrpose-", dir=path.parent))
        try:
            for f, pos in enumerate(frames.positions):
                write_geometry(tmp / f"frame_{f:04d}.{fmt}", pos, frames.faces)
            for old in path.glob("frame_*"):
                old.unlink()
            for new in sorted(tmp.iterdir()):
                new.replace(path / new.name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def cmd_info(args) -> None:
    from .character import load_character

    ch = load_character(args.character, args.skeleton)
    skel = ch.skeleton
    print(f"{args.character}")
    print(f"meshes: {len(ch.meshes)}")
    for m in ch.meshes:
        kind = (f"rigid on {skel.names[m.rigid_joint]!r}" if m.rigid_joint is not None
                else f"skinned, {m.joints.shape[1]} influences" if m.joints is not None else "no skin weights")
        print(f"  {m.name}: {len(m.vertices)} vertices, {len(m.faces)} faces, {kind}")
    print(f"joints: {skel.num_joints} ({len(skel.bones())} bones)")
    depth = np.zeros(skel.num_joints, int)
    for j, p in enumerate(skel.parents):
        depth[j] = depth[p] + 1 if p >= 0 else 0
        print(f"  {'  ' * depth[j]}{skel.names[j]}")
    print(f"clips: {len(ch.clips)}")
    for c in ch.clips:
        print(f"  {c.name}: {c.duration:.3f} s")


def deformer_device() -> str:
    from . import device
    info = device.describe()
    return f"{info['device']} ({info['platform_version']}, {info['compute_units']} compute units)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="nrpose", description="Nearly rigid MLS deformation and skeletal posing on OpenCL.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("deform", help="deform a mesh or point cloud with point / segment handles")
    p.add_argument("input", help="mesh (OBJ, PLY, OFF, STL) or point cloud (PLY, XYZ)")
    p.add_argument("-H", "--handles", required=True, help="handle file (JSON)")
    p.add_argument("-o", "--output", required=True, help="output mesh or point cloud")
    p.add_argument("--alpha", type=float, help="weight exponent: w = 1/d^(2 alpha) (overrides the file; default 1)")
    p.add_argument("--blend", choices=BLENDS, default="relative", help="rotation blend (default: relative)")
    p.add_argument("--lever", choices=LEVERS, default="weight", help="segment lever rule (default: weight)")
    p.add_argument("--backend", choices=BACKENDS, default="opencl", help="opencl (default) or numpy reference")
    p.add_argument("--weights", choices=("euclidean", "heat", "exact", "graph", "knn"), default="euclidean",
                   help="distances for the weights: euclidean (default) or over the surface (heat, exact, graph; "
                        "knn for point clouds)")
    p.add_argument("--png", help="write a before/after preview PNG")
    p.set_defaults(func=cmd_deform)

    from .posing import METHODS, WEIGHTS

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
    p.set_defaults(func=cmd_pose)

    from .benchcli import add_bench_parser
    from .retargetcli import add_retarget_parser
    from .weightcli import add_weights_parser
    add_weights_parser(sub)
    add_retarget_parser(sub)
    add_bench_parser(sub)

    p = sub.add_parser("info", help="meshes, joints and clips of a character")
    p.add_argument("character")
    p.add_argument("--skeleton")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("demo", help="embedded default: a walking capsule humanoid and the paper's Figure 3 box")
    p.add_argument("--out", default="out", help="output directory (default: out)")
    p.add_argument("--frames", type=int, default=60, help="walk frames (default 60)")
    p.add_argument("--repeat", type=int, default=50, help="box poses timed per configuration (default 50)")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
        # the commands check their inputs and results for NaN and infinity themselves and say
        # so in one line; numpy's floating-point warnings on the way would add lines to stderr
        # (nrpose's own warnings, e.g. a binding cache not written, still show)
        with np.errstate(all="ignore"):
            args.func(args)
    except _UsageError as exc:
        return _fail(str(exc))
    except NrposeError as exc:
        return _fail(f"nrpose: error: {exc}")
    except OSError as exc:
        return _fail(f"nrpose: error: {exc.filename or ''}: {exc.strerror or exc}")
    return 0


def _fail(message: str) -> int:
    """The message on stderr as one line (a path may hold a newline), exit status 2."""
    print(message.replace("\r", "\\r").replace("\n", "\\n"), file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
