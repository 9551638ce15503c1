"""glTF 2.0 binaries (``.glb``): baked animations, and a character file with a clip added.

:func:`write_animated_glb` writes the rest geometry of each mesh with every
posed frame stored as a **morph target** (target f = posed frame f − rest,
float32 displacements) and one animation whose ``weights`` channel(s) switch
between the targets: at key time ``t_f`` the weight vector is one-hot at f,
with LINEAR interpolation in between (so playback blends consecutive frames
linearly, exactly reproducing every frame at its time). No skin is written:
the file shows the deformation that was computed (any deformer), not a
re-skinning of it.

Layout: one node per mesh (a single triangle primitive, ``POSITION`` with the
min/max the spec requires, uint32 indices, a grey PBR material); the mesh's
default ``weights`` select frame 0, so static viewers show the first frame;
``mesh.extras.targetNames`` are ``frame0 ...``. Coordinates are written as
given (no axis conversion; glTF is Y-up, metres). Size is about
``12 * F * V`` bytes; the caller limits the number of frames.
Written through :func:`nrpose.io.files.atomic_path`.

:func:`write_glb_with_clip` writes a glTF character file again with one more
animation: a :class:`~nrpose.model.character.Clip` of its skeleton, one
sampler per track on its joint's node (float32, the track's times and
interpolation; a joint node given as a ``matrix`` is rewritten as its TRS, as
animated nodes must be). The original content (meshes, skins, materials, textures,
other animations) is kept: every buffer is copied into the single GLB buffer
(a ``.gltf`` with external buffers or images becomes self-contained) and the
new data is appended after it.
"""
from __future__ import annotations

import mimetypes
import urllib.parse
from pathlib import Path
from typing import Sequence

import numpy as np
import pygltflib

from ..checks import real_rows, triangles, within_float32
from ..errors import InputError, NrposeError
from .files import atomic_path
from ..model.rotation import Rotation
from ..model.skeleton import polar_rotation
from .gltf_read import joint_nodes, node_globals, read_document

__all__ = ["write_animated_glb", "write_glb_with_clip", "fit_skinned_nodes", "Blob"]

_FLOAT, _UINT = pygltflib.FLOAT, pygltflib.UNSIGNED_INT


def _mesh_list(character_or_meshes) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, vertices (N, 3) float64, faces (M, 3) int64) per mesh."""
    meshes = getattr(character_or_meshes, "meshes", character_or_meshes)
    if meshes is None or isinstance(meshes, (str, bytes)) or len(meshes) == 0:
        raise InputError("write_animated_glb needs a character with meshes, or a list of meshes")
    out = []
    for i, m in enumerate(meshes):
        if hasattr(m, "vertices"):
            name, V, F = getattr(m, "name", None) or f"mesh{i}", m.vertices, m.faces
        elif isinstance(m, (tuple, list)) and len(m) in (2, 3):
            name, V, F = (f"mesh{i}", *m) if len(m) == 2 else m
        else:
            raise InputError(f"mesh {i}: expected a Mesh or a (vertices, faces) pair")
        V = real_rows(V, f"mesh {i} ({name}) vertices")
        out.append((str(name), V, triangles(F, len(V), f"mesh {i} ({name}) faces")))
    return out


def _offsets(mesh_offsets, sizes: list[int], total: int) -> np.ndarray:
    """Start index of each mesh in the concatenated vertices, plus the end: (n + 1,)."""
    n = len(sizes)
    natural = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    if mesh_offsets is None:
        starts = natural
    else:
        starts = np.asarray(mesh_offsets).reshape(-1)
        if not np.issubdtype(starts.dtype, np.integer):
            raise InputError(f"mesh_offsets must be integers, got {starts.dtype}")
        if len(starts) == n:
            starts = np.append(starts, total)
        if len(starts) != n + 1:
            raise InputError(f"mesh_offsets: expected {n} starts (or {n + 1} with the end), got {len(starts)}")
        starts = starts.astype(np.int64)
    if starts[0] < 0 or starts[-1] > total or not (np.diff(starts) == np.asarray(sizes)).all():
        raise InputError(f"mesh_offsets {starts.tolist()} do not match the mesh sizes {sizes} "
                         f"within {total} posed vertices")
    return starts


def _check(positions, times, total_needed: int) -> tuple[np.ndarray, np.ndarray]:
    P = np.asarray(positions, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[0] == 0:
        raise InputError(f"positions must have shape (frames, vertices, 3) with at least one frame, "
                         f"got {np.shape(positions)}")
    if P.shape[1] < total_needed:
        raise InputError(f"positions have {P.shape[1]} vertices per frame; the meshes need {total_needed}")
    if not np.isfinite(P).all():
        f = int(np.flatnonzero(~np.isfinite(P).all(axis=(1, 2)))[0])
        raise InputError(f"positions of frame {f} contain NaN or inf")
    T = np.asarray(times, dtype=np.float64).reshape(-1)
    if T.shape != (P.shape[0],):
        raise InputError(f"times: expected {P.shape[0]} values (one per frame), got {T.shape[0]}")
    if not np.isfinite(T).all() or (T < 0).any() or (np.diff(T) <= 0).any():
        raise InputError("times must be finite, non-negative seconds, strictly increasing")
    return P, T


class Blob:
    """The binary chunk of a GLB being written: 4-byte aligned buffer views and accessors.

    Appends to ``gltf.bufferViews`` / ``gltf.accessors`` (all views in buffer 0);
    :meth:`bytes` is the chunk's content.
    """

    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf, self.parts, self.size = gltf, [], 0

    def append(self, data: bytes) -> int:
        """Append raw bytes (then pad to 4); their byte offset."""
        start = self.size
        self.parts.append(data)
        self.size += len(data)
        pad = (-self.size) % 4
        if pad:
            self.parts.append(b"\0" * pad)
            self.size += pad
        return start

    def raw(self, data: bytes, target=None) -> int:
        """A buffer view of raw bytes; its index."""
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=self.append(data),
                                                          byteLength=len(data), target=target))
        return len(self.gltf.bufferViews) - 1

    def add(self, array: np.ndarray, kind: str, component: int = pygltflib.FLOAT, target=None,
            minmax: bool = False) -> int:
        """A buffer view and an accessor for ``array`` (already of the component's dtype); its index."""
        view = self.raw(np.ascontiguousarray(array).tobytes(), target)
        count = len(array)
        acc = pygltflib.Accessor(bufferView=view, componentType=component,
                                 count=count, type=kind)
        if minmax:
            flat = np.asarray(array).reshape(count, -1)
            acc.min = [float(x) for x in flat.min(axis=0)]
            acc.max = [float(x) for x in flat.max(axis=0)]
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def write_animated_glb(path, character_or_meshes, positions, times, mesh_offsets: Sequence[int] | None = None,
                       *, animation_name: str = "baked") -> None:
    """Write the meshes with the posed frames baked as morph targets and one animation.

    character_or_meshes: a :class:`~nrpose.model.character.Character` (its
    ``meshes``), or a sequence of :class:`~nrpose.model.character.Mesh` or
    ``(vertices, faces)`` / ``(name, vertices, faces)``; their vertices are
    the rest geometry. positions: (F, V, 3) posed vertices of all meshes
    concatenated; times: (F,) seconds, non-negative, strictly increasing;
    mesh_offsets: start of each mesh in V (n starts, or n + 1 with the end;
    None: the meshes back to back from 0). Raises InputError on bad input.
    """
    meshes = _mesh_list(character_or_meshes)
    sizes = [len(V) for _, V, _ in meshes]
    P, T = _check(positions, times, sum(sizes) if mesh_offsets is None else 0)
    within_float32(P, "positions")
    starts = _offsets(mesh_offsets, sizes, P.shape[1])
    n_frames = len(T)

    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator="nrpose gltf_export", version="2.0"))
    gltf.scene = 0
    gltf.scenes = [pygltflib.Scene(nodes=[])]
    gltf.materials = [pygltflib.Material(
        name="nrpose", doubleSided=True,
        pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(baseColorFactor=[0.62, 0.70, 0.86, 1.0],
                                                            metallicFactor=0.0, roughnessFactor=0.8))]
    blob = Blob(gltf)
    onehot = np.eye(n_frames, dtype=np.float32)
    input_acc = blob.add(T.astype(np.float32), "SCALAR", _FLOAT, minmax=True)
    output_acc = blob.add(onehot.reshape(-1), "SCALAR", _FLOAT)
    animation = pygltflib.Animation(name=str(animation_name), channels=[], samplers=[])
    for k, ((name, V, F), start) in enumerate(zip(meshes, starts[:-1])):
        rest = V.astype(np.float32)
        posed = P[:, start:start + len(V)]
        pos_acc = blob.add(rest, "VEC3", _FLOAT, pygltflib.ARRAY_BUFFER, minmax=True)
        idx_acc = blob.add(F.astype(np.uint32).reshape(-1), "SCALAR", _UINT, pygltflib.ELEMENT_ARRAY_BUFFER)
        targets = []
        for f in range(n_frames):
            delta = (posed[f] - rest.astype(np.float64)).astype(np.float32)
            targets.append({"POSITION": blob.add(delta, "VEC3", _FLOAT, pygltflib.ARRAY_BUFFER, minmax=True)})
        prim = pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=pos_acc), indices=idx_acc,
                                   material=0, mode=pygltflib.TRIANGLES, targets=targets)
        gltf.meshes.append(pygltflib.Mesh(name=name, primitives=[prim], weights=onehot[0].tolist(),
                                          extras={"targetNames": [f"frame{f}" for f in range(n_frames)]}))
        gltf.nodes.append(pygltflib.Node(name=name, mesh=k))
        gltf.scenes[0].nodes.append(k)
        animation.samplers.append(pygltflib.AnimationSampler(input=input_acc, output=output_acc,
                                                             interpolation="LINEAR"))
        animation.channels.append(pygltflib.AnimationChannel(
            sampler=k, target=pygltflib.AnimationChannelTarget(node=k, path="weights")))
    gltf.animations = [animation]
    data = blob.bytes()
    gltf.buffers = [pygltflib.Buffer(byteLength=len(data))]
    gltf.set_binary_blob(data)
    with atomic_path(Path(path)) as tmp:
        gltf.save_binary(str(tmp))


def write_glb_with_clip(target_path, out_path, target, clip, bounds=None) -> str:
    """Write the target glTF plus ``clip`` (a Clip of its skeleton) as a new animation, as a GLB.

    Returns the animation's name. Every track of the clip becomes a channel on
    its joint's node (float32, the track's times and interpolation; CUBICSPLINE
    is not written). bounds: optional world-space box (min (3,), max (3,)) the
    animated geometry stays in: each skinned mesh node is then placed
    (:func:`fit_skinned_nodes`) so that viewers' culling bounds hold it.
    """
    path = Path(target_path)
    gltf, buffers = read_document(path)
    skeleton, nodes = joint_nodes(path, gltf, buffers)
    if tuple(skeleton.names) != tuple(target.skeleton.names):
        raise NrposeError(f"{path}: its skeleton changed since it was loaded")
    if bounds is not None:
        fit_skinned_nodes(path, gltf, bounds)
    blob = Blob(gltf)
    starts = [blob.append(bytes(b)) for b in buffers]
    for view in gltf.bufferViews:
        view.byteOffset = (view.byteOffset or 0) + starts[view.buffer]
        view.buffer = 0
    for i, image in enumerate(gltf.images or []):
        if image.uri is not None and not image.uri.startswith("data:"):
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
    skel = target.skeleton
    for j in sorted({t.joint for t in clip.tracks}):
        node = gltf.nodes[int(nodes[j])]
        if node.matrix is not None:     # animated nodes must use TRS (glTF 2.0, 5.25)
            node.matrix = None
            node.translation, node.rotation, node.scale = (skel.translation[j].tolist(),
                                                           skel.rotation[j].tolist(), skel.scale[j].tolist())
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
            target=pygltflib.AnimationChannelTarget(node=int(nodes[track.joint]), path=track.path)))
    gltf.animations = list(gltf.animations or []) + [animation]
    data = blob.bytes()
    gltf.buffers = [pygltflib.Buffer(byteLength=len(data))]
    gltf.set_binary_blob(data)
    with atomic_path(Path(out_path)) as tmp:
        gltf.save_binary(str(tmp))
    return name


def fit_skinned_nodes(path, gltf: pygltflib.GLTF2, bounds) -> None:
    """Place each skinned mesh node so that its culling sphere holds the box ``bounds``.

    The glTF specification ignores a skinned mesh node's transform (its vertices follow the
    joints only), but viewers cull and frame it by its ``POSITION`` min/max times the node's
    world matrix: three.js culls a character whose root motion leaves the rest bounds (or
    whose mesh sits under a 0.01-scaled armature, as Mixamo exports do). The node gets the
    uniform scale and translation (in its parent's frame) that map the sphere around its
    rest box onto the sphere around ``bounds`` (min (3,), max (3,), world). Nodes whose
    parent's world matrix is not a rotation times a uniform scale are left as they are.
    """
    lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    parents, world = node_globals(Path(path), gltf)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    for i, node in enumerate(gltf.nodes):
        if node.mesh is None or node.skin is None:
            continue
        accessors = [gltf.accessors[p.attributes.POSITION] for p in gltf.meshes[node.mesh].primitives
                     if p.attributes.POSITION is not None]
        box = [(a.min, a.max) for a in accessors if a.min is not None and a.max is not None]
        if not box:
            continue
        mn = np.min([b[0] for b in box], axis=0)
        mx = np.max([b[1] for b in box], axis=0)
        r = np.linalg.norm(mx - mn) / 2
        if not (r > 0 and radius > 0):
            continue
        scale = radius / r
        desired = np.eye(4)
        desired[:3, :3] *= scale
        desired[:3, 3] = centre - scale * (mn + mx) / 2
        P = world[parents[i]] if parents[i] >= 0 else np.eye(4)
        local = np.linalg.inv(P) @ desired
        R = polar_rotation(local[:3, :3])
        s = np.linalg.norm(local[:3, :3], axis=0)
        if not np.allclose(local[:3, :3], R * s.mean(), rtol=0, atol=1e-6 * s.mean()):
            continue
        node.matrix = None
        node.translation = local[:3, 3].tolist()
        node.rotation = Rotation.from_matrix(R).as_quat().tolist()
        node.scale = [float(s.mean())] * 3
