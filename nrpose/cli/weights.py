"""``nrpose weights``: a character's bone weights to a file, and optionally a weight map.

    nrpose weights CHARACTER [--skeleton S] --method authored|euclidean|heat|exact|graph [--k K]
                   [--alpha A] -o WEIGHTS.npz [--png MAP.png --bone NAME]

The weights are the ones ``nrpose pose --method nrmls --weights METHOD`` binds
with: :func:`nrpose.bind.bone_weights.bone_weights` (its docstring gives the
methods and the rule for rigidly attached meshes). Surface distances are
cached on disk by content, so a later ``nrpose pose`` with the same weights
binds from the cache, and vice versa.

``--k K`` keeps the ``K`` most influential bones of each vertex (renormalised;
the others are stored as 0). Default: dense up to
:data:`nrpose.bind.bone_weights.SKELETON_K` bones, else ``K = SKELETON_K``
(what the poser uses); ``--k all`` keeps every bone.

Output (``.npz``, written under a temporary name and renamed): ``weights``
(V, B) float32; ``distances`` (V, B) float64; ``bones`` (B, 2, 3) rest
segments; ``bone_names`` (B,) str; ``bone_joints`` (B,) int64 driving joint;
``method`` str; ``k`` int (the number of bones kept per vertex; B when dense);
``alpha`` float; ``mesh_names`` (M,) str and ``mesh_offsets`` (M,) int64
(vertices of all meshes concatenated in file order, as ``nrpose pose``
writes them).

``--png MAP.png --bone NAME`` draws the weight of one bone on the mesh
(:mod:`nrpose.render.weightmap`, colour scale γ = 0.5 so that small leaked weights
show; a glTF character is drawn upright from the front and both sides, other
meshes with the weight map's default views). ``NAME`` is a bone name as listed by ``Skeleton.bones().names``
(``"joint->child"``) or a joint name, meaning that joint's first bone.
"""
from __future__ import annotations

import argparse
import difflib
import time
from pathlib import Path

import numpy as np

from ..bind.bone_weights import WEIGHTS, bone_weights
from ..errors import InputError
from ..io import load_character
from ..io.files import atomic_path, check_writable
from ..render.weightmap import save_weight_maps

#: library argument name -> the flag users type (the weights method is --method here)
FLAGS = {"weights": "--method", "k": "--k", "alpha": "--alpha", "skeleton": "--skeleton"}
GLTF_VIEWS = (("front", 0.0, -90.0), ("left side", 0.0, 0.0), ("right side", 0.0, 180.0))


def k_arg(text: str):
    """A --k value: a positive integer, or "all"."""
    if text.strip().lower() in ("all", "dense"):
        return "all"
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'all', got {text!r}") from None
    if k < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'all', got {text!r}")
    return k


def add_parser(sub) -> None:
    p = sub.add_parser(
        "weights", help="bone weights of a character (surface or Euclidean distances) to .npz, with a PNG map",
        description="Compute the nrmls bone weights of a character and write them to an .npz file.")
    p.add_argument("character", help=".glb/.gltf, or a mesh (OBJ, OFF, PLY, STL, .mesh) with --skeleton")
    p.add_argument("--skeleton", help="skeleton for a mesh character (.tgf or .bvh)")
    p.add_argument("--method", required=True, choices=WEIGHTS,
                   help="the file's skin weights (authored), or distances over the surface (heat, exact, "
                        "graph) or straight-line (euclidean)")
    p.add_argument("--k", type=k_arg, default=None,
                   help="bones kept per vertex (a positive integer, or 'all'); default: all up to 8 bones, else 8")
    p.add_argument("--alpha", type=float, default=1.0, help="weight exponent: w = 1/d^(2 alpha) (default 1)")
    p.add_argument("-o", "--output", required=True, help="WEIGHTS.npz")
    p.add_argument("--png", help="write a weight map of --bone to this PNG")
    p.add_argument("--bone", help="bone (as 'joint->child', or a joint name: its first bone) for --png")
    p.set_defaults(func=run, flags=FLAGS)


def resolve_bone(name: str, bones, skeleton) -> int:
    """Index of the bone called ``name`` (a bone name, or a joint name → its first bone)."""
    if name in bones.names:
        return bones.names.index(name)
    if name in skeleton.names:
        j = skeleton.names.index(name)
        own = np.flatnonzero(bones.joints == j)
        if len(own):
            return int(own[0])
        kids = [bones.names[b] for b in range(len(bones)) if skeleton.parents[bones.joints[b]] == j][:4]
        hint = f"; bones of its children: {', '.join(map(repr, kids))}" if kids else ""
        raise InputError(f"--bone {name!r}: this joint drives no bone (it sits where its child starts, or "
                         f"does not deform){hint}")
    pool = list(bones.names) + [n for n in skeleton.names if n not in bones.names]
    close = difflib.get_close_matches(name, pool, n=6, cutoff=0.5)
    if not close:  # substring matches help with long prefixed names (mixamorig:...)
        low = name.lower()
        close = [n for n in pool if low in n.lower()][:6]
    if close:
        hint = "did you mean " + ", ".join(map(repr, close)) + "?"
    else:
        hint = f"bones: {', '.join(map(repr, bones.names[:8]))}{', ...' if len(bones) > 8 else ''}"
    raise InputError(f"--bone {name!r}: no such bone or joint; {hint}")


def run(args) -> None:
    out = Path(args.output)
    if out.suffix.lower() != ".npz":
        raise InputError(f"{out}: the weights file must end in .npz")
    if bool(args.png) != bool(args.bone):
        raise InputError("--png and --bone go together: --png MAP.png --bone NAME")
    if args.png and Path(args.png).suffix.lower() != ".png":
        raise InputError(f"{args.png}: the weight map must end in .png")
    check_writable(out)
    if args.png:
        check_writable(args.png)
    character = load_character(args.character, args.skeleton)
    bones = character.skeleton.bones()
    b = resolve_bone(args.bone, bones, character.skeleton) if args.bone else None  # fail before the work
    t0 = time.perf_counter()
    res = bone_weights(character, args.method, args.k, args.alpha, parameters=False)
    bind_ms = 1e3 * (time.perf_counter() - t0)
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, weights=res.weights.astype(np.float32), distances=res.distances,
                     bones=bones.segments, bone_names=np.array(bones.names, dtype=str),
                     bone_joints=bones.joints.astype(np.int64), method=np.array(args.method),
                     k=np.array(res.k, np.int64), alpha=np.array(res.alpha),
                     mesh_names=np.array(res.meshes.names, dtype=str), mesh_offsets=res.meshes.offsets)
    msg = (f"{out}: {len(res.meshes.vertices)} vertices × {len(bones)} bones, {args.method} distances, "
           f"k={res.k}{' (dense)' if res.k == len(bones) else ''}, alpha {res.alpha:g}: {bind_ms:.0f} ms")
    if args.png:
        w = res.weights[:, b]
        label = f"{args.method}: max {w.max():.3f}"
        gltf = Path(args.character).suffix.lower() in (".glb", ".gltf")  # Y-up, facing +Z
        with atomic_path(args.png) as tmp:
            save_weight_maps(res.meshes.vertices, res.meshes.faces, {label: w}, tmp,
                             f"{Path(args.character).name}: weight of bone {bones.names[b]}",
                             vmax=1.0, gamma=0.5, views=GLTF_VIEWS if gltf else None, up="y" if gltf else "z")
        msg += f"; map of {bones.names[b]} → {args.png}"
    print(msg)
