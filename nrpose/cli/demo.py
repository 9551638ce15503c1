"""``nrpose demo``: the embedded default, a walking capsule humanoid and the paper's Figure 3 box."""
from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np

from ..pose.mls import Deformer
from ..errors import NrposeError
from ..io.meshes import write_geometry
from ..pose.poser import CharacterPoser
from ..render.preview import save_preview
from ..render.sheet import save_contact_sheet
from ..rigs import box
from ..rigs.humanoid import humanoid
from .common import add_budget_options, check_budget, device_text, median_ms, output_values, progress, write_frames

#: library argument name -> the flag users type
FLAGS: dict[str, str] = {}


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="embedded default: a walking capsule humanoid and the paper's Figure 3 box")
    p.add_argument("--out", default="out", help="output directory (default: out)")
    p.add_argument("--frames", type=int, default=60, help="walk frames (default 60)")
    p.add_argument("--repeat", type=int, default=50,
                   help=f"box poses timed per configuration (default 50, at most {MAX_REPEAT:,})")
    add_budget_options(p)
    p.set_defaults(func=run, flags=FLAGS)


#: most timed box poses per configuration (a run of the default takes well under a second)
MAX_REPEAT = 10_000


def run(args) -> None:
    """NR-MLS on PoCL: the humanoid's frames, animated .glb and contact sheet; the box's
    before/after PNGs."""
    if args.frames < 1 or args.repeat < 1:
        raise NrposeError("--frames and --repeat must be at least 1")
    if args.repeat > MAX_REPEAT:
        raise NrposeError(f"--repeat {args.repeat:,}: at most {MAX_REPEAT:,} timed poses per configuration")
    out = Path(args.out)
    check_budget(args, args.frames, 0.0, str(out / "walk.glb"))     # the frames, before their numbers
    made = next((p for p in reversed([out, *out.parents]) if not p.exists()), None)
    out.mkdir(parents=True, exist_ok=True)
    try:
        print(f"device: {device_text()}")
        walk(out, args.frames, args)
        figure3_box(out, args.repeat)
    except BaseException:
        if made is not None:       # a failed run leaves no folder it made
            shutil.rmtree(made, ignore_errors=True)
        raise


def walk(out: Path, n_frames: int, budget) -> None:
    """The capsule humanoid's walk clip posed with NR-MLS and authored weights (``budget``: the
    run's --max-frames / --max-output-values, checked before posing)."""
    t0 = time.perf_counter()
    character = humanoid()
    build_ms = 1e3 * (time.perf_counter() - t0)
    vertices = sum(len(m.vertices) for m in character.meshes)
    check_budget(budget, n_frames, output_values(n_frames, vertices, "glb"), str(out / "walk.glb"))
    clip = character.clip("walk")
    times = np.linspace(0.0, clip.duration, n_frames)
    poser = CharacterPoser(character, method="nrmls", weights="authored")
    frames = poser.pose(clip.sample(times), progress=progress)
    write_frames(str(out / "walk.npz"), frames, times, "ply", character)
    write_frames(str(out / "walk.glb"), frames, times, "ply", character)
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


def figure3_box(out: Path, repeat: int) -> None:
    """The paper's Figure 3: a 6,006-point box twisted and bent by 4 segments, on PoCL."""
    points, rest = box.box_points(), box.rest_handles()
    bind_ms, deformer = median_ms(lambda: Deformer(points, rest, backend="opencl"), 1)
    reference = Deformer(points, rest, backend="numpy")
    print(f"Figure 3 box: {len(points)} points, {rest.count} segment handles; bind {bind_ms:.1f} ms")
    panels, handles = [("rest", points, None)], [(rest.points, rest.segments)]
    for name, (twist, bend) in box.POSES.items():
        pose = box.chain_pose(twist, bend)
        pose_ms, posed = median_ms(lambda: deformer.pose(pose), repeat)
        ref_ms, ref = median_ms(lambda: reference.pose(pose), 3)
        err = float(np.abs(posed - ref).max())
        write_geometry(out / f"box_{name}.ply", posed)
        panels.append((f"{name} (twist {twist:g}°, bend {bend:g}°)", posed, None))
        handles.append((pose.handles.points, pose.handles.segments))
        print(f"  {name:<10} pose {pose_ms:7.3f} ms (median of {repeat}) | numpy reference "
              f"{ref_ms:7.2f} ms ({ref_ms / pose_ms:5.0f}x) | max |PoCL - reference| {err:.1e}")
    save_preview(out / "box_before.png", panels[:1], handles=handles[:1])
    save_preview(out / "box_after.png", panels, handles=handles)
    print(f"  wrote {out / 'box_before.png'}, {out / 'box_after.png'} and box_*.ply")
