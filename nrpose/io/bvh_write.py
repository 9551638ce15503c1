"""Writing BVH motion: any :class:`~nrpose.model.skeleton.Skeleton` and a batch of local poses.

BVH joints have identity rest rotations and offsets in their parent's frame,
so the skeleton is written in its rest pose *in world space*: a joint's
``OFFSET`` is its rest world position minus its parent's (a root's is its rest
world position), with every fixed ``pre`` matrix, rest rotation and scale
folded in (a Mixamo armature's 0.01 scale gives offsets in metres). Joints are
written depth first; a joint's BVH rotation at a frame is its world rotation
relative to its rest world rotation, ``B_j = W_j(t) · W_j(rest)⁻¹``, and the
channel values are the local ``B_parent⁻¹ · B_j`` as intrinsic ``Zrotation
Xrotation Yrotation`` degrees (``R = Rz @ Rx @ Ry``, as
:mod:`nrpose.io.bvh_read` reads them). Roots, and joints listed in
``position_joints``, also get ``Xposition Yposition Zposition``: their
position in the parent's BVH frame (a root's world position). Leaves get an
``End Site``: the skeleton's tip if it has one, else half the joint's distance
from its nearest ancestor at another position, along that direction.

Rotations are taken as polar parts of the global matrices: a rig with
non-uniform scales is written without them. Whitespace in joint names becomes
``_``. Written through :func:`nrpose.io.files.atomic_path`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..model.rotation import Rotation
from ..model.skeleton import LocalPose, Skeleton, polar_rotation
from .files import atomic_path

__all__ = ["write_bvh", "bvh_text"]


def _dfs(skel: Skeleton) -> list[int]:
    order, stack = [], [int(r) for r in np.flatnonzero(skel.parents < 0)][::-1]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(int(c) for c in skel.children(j)[::-1])
    return order


def _fmt(values) -> str:
    return " ".join(f"{v:.6f}" for v in values)


def bvh_text(skel: Skeleton, pose: LocalPose, frame_time: float, position_joints=()) -> str:
    """The BVH file contents for ``pose`` (F, J, ...) of ``skel`` (module docstring)."""
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise InputError(f"BVH frame time must be positive, got {frame_time}")
    G = skel.forward_kinematics(pose)
    if G.ndim == 3:
        G = G[None]
    if not np.isfinite(G).all():
        raise InputError("cannot write a BVH of non-finite poses")
    G0 = skel.rest_globals()
    P0, P = G0[:, :3, 3], G[..., :3, 3]
    W0, W = polar_rotation(G0[:, :3, :3]), polar_rotation(G[..., :3, :3])
    B = W @ np.swapaxes(W0, -1, -2)[None]                                  # (F, J, 3, 3)
    parents = skel.parents
    Bp = np.where((parents >= 0)[None, :, None, None], B[:, np.maximum(parents, 0)], np.eye(3))
    local = np.swapaxes(Bp, -1, -2) @ B
    euler = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_euler("ZXY", degrees=True).reshape(local.shape[:2] + (3,))
    Pp = np.where((parents >= 0)[None, :, None], P[:, np.maximum(parents, 0)], 0.0)
    rel = np.einsum("fjba,fjb->fja", Bp, P - Pp)                           # position in the parent's BVH frame
    moving = set(int(j) for j in np.flatnonzero(parents < 0)) | {int(j) for j in position_joints}
    names = [n.replace(" ", "_").replace("\t", "_") or f"joint{j}" for j, n in enumerate(skel.names)]
    tips = np.einsum("jab,jb->ja", G0[:, :3, :3], skel.tips)

    lines = ["HIERARCHY"]
    order = _dfs(skel)

    def end_site(j: int) -> np.ndarray:
        if np.isfinite(tips[j]).all():
            return tips[j]
        a = parents[j]
        while a >= 0 and np.linalg.norm(P0[j] - P0[a]) <= 1e-12:
            a = parents[a]
        return 0.5 * (P0[j] - P0[a]) if a >= 0 else np.zeros(3)

    def write(j: int, depth: int) -> None:
        pad = "\t" * depth
        kind = "ROOT" if parents[j] < 0 else "JOINT"
        offset = P0[j] if parents[j] < 0 else P0[j] - P0[parents[j]]
        lines.append(f"{pad}{kind} {names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {_fmt(offset)}")
        if j in moving:
            lines.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
        else:
            lines.append(f"{pad}\tCHANNELS 3 Zrotation Xrotation Yrotation")
        children = skel.children(j)
        for c in children:
            write(int(c), depth + 1)
        if len(children) == 0:
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {_fmt(end_site(j))}", f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    for r in np.flatnonzero(parents < 0):
        write(int(r), 0)
    F = len(G)
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {float(frame_time)!r}"]
    columns = []
    for j in order:
        if j in moving:
            columns.append(rel[:, j])
        columns.append(euler[:, j])
    data = np.concatenate(columns, axis=1)
    lines += [_fmt(row) for row in data]
    return "\n".join(lines) + "\n"


def write_bvh(path, skel: Skeleton, pose: LocalPose, frame_time: float, position_joints=()) -> None:
    """Write ``pose`` (F, J, ...) of ``skel`` as a BVH file (module docstring)."""
    text = bvh_text(skel, pose, frame_time, position_joints)
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_text(text)
