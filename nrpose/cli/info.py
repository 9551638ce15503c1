"""``nrpose info``: meshes (posable and static), joints and clips of a character."""
from __future__ import annotations

import numpy as np

from ..io import load_character

#: library argument name -> the flag users type
FLAGS = {"skeleton": "--skeleton"}


def add_parser(sub) -> None:
    p = sub.add_parser("info", help="meshes, joints and clips of a character")
    p.add_argument("character")
    p.add_argument("--skeleton")
    p.set_defaults(func=run, flags=FLAGS)


def run(args) -> None:
    ch = load_character(args.character, args.skeleton)
    clips = tuple(ch.clips)     # decoded on first use: a malformed one fails the command before any line
    skel = ch.skeleton
    print(f"{args.character}")
    print(f"meshes: {len(ch.meshes)}")
    for m in ch.meshes:
        kind = (f"rigid on {skel.names[m.rigid_joint]!r}" if m.rigid_joint is not None
                else f"skinned, {m.joints.shape[1]} influences" if m.joints is not None else "no skin weights")
        print(f"  {m.name}: {len(m.vertices)} vertices, {len(m.faces)} faces, {kind}")
    if ch.static_meshes:
        print(f"static meshes (the skeleton does not move them; kept as they are, never posed): "
              f"{len(ch.static_meshes)}")
        for m in ch.static_meshes:
            print(f"  {m.name}: {len(m.vertices)} vertices, {len(m.faces)} faces")
    print(f"joints: {skel.num_joints} ({len(skel.bones())} bones)")
    depth = np.zeros(skel.num_joints, int)
    for j, p in enumerate(skel.parents):
        depth[j] = depth[p] + 1 if p >= 0 else 0
        print(f"  {'  ' * depth[j]}{skel.names[j]}")
    print(f"clips: {len(clips)}")
    for c in clips:
        print(f"  {c.name}: {c.duration:.3f} s")
