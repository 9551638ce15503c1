"""The source glTF written again with fitted skin weights (JOINTS_n / WEIGHTS_n).

Everything else is kept (nodes, materials, UVs, normals, textures, the source's
animations); all buffers are copied into the single GLB buffer and the new
weights appended after them (uint16 joints and float32 weights, 4 per set, so
8 influences use ``JOINTS_0/1`` and ``WEIGHTS_0/1``; each set's weights are
stored as fitted, the file's rows summing to 1 within float32).
Requested clips are then added as ordinary animations by
:func:`nrpose.io.gltf_write.write_glb_with_clip`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib

from ..errors import InputError
from ..io.files import atomic_path
from ..io.gltf_read import joint_nodes, node_globals, read_document
from ..io.gltf_write import Blob, check_copyable, write_glb_with_clip
from ..model.character import Character
from .character_skin import FittedSkin

__all__ = ["skinned_primitives", "write_fitted_glb"]


def skinned_primitives(path, character: Character) -> list:
    """Per character mesh: (gltf mesh index, primitive index, skin index, allowed (J,) bool
    joints of that skin), or None for a rigidly attached mesh — matched in the loader's order
    (default scene, depth-first nodes, primitives in order)."""
    path = Path(path)
    gltf, buffers = read_document(path)
    skeleton, nodes = joint_nodes(path, gltf, buffers)
    if tuple(skeleton.names) != tuple(character.skeleton.names):
        raise InputError(f"{path}: not the file the character was loaded from (skeletons differ)")
    node_joint = {int(n): j for j, n in enumerate(nodes)}
    parents, _ = node_globals(path, gltf)
    scene_roots = set(gltf.scenes[gltf.scene or 0].nodes or []) if gltf.scenes else None
    order, stack = [], [int(i) for i in np.flatnonzero(parents < 0)[::-1]]
    while stack:
        i = stack.pop()
        order.append(i)
        stack.extend(reversed(gltf.nodes[i].children or []))

    def lineage(i):
        while i >= 0:
            yield i
            i = int(parents[i])

    found = []
    for i in order:
        node = gltf.nodes[i]
        if node.mesh is None or (scene_roots is not None and not scene_roots.intersection(lineage(i))):
            continue
        attached = any(a in node_joint for a in lineage(i))
        if node.skin is None and not attached:
            continue
        for p in range(len(gltf.meshes[node.mesh].primitives)):
            if node.skin is None:
                found.append(None)
            else:
                allowed = np.zeros(skeleton.num_joints, bool)
                allowed[[node_joint[n] for n in gltf.skins[node.skin].joints]] = True
                found.append((node.mesh, p, node.skin, allowed))
    if len(found) != len(character.meshes) or any(
            (f is None) != (m.rigid_joint is not None) for f, m in zip(found, character.meshes)):
        raise InputError(f"{path}: its meshes do not match the loaded character's")
    return found


def write_fitted_glb(source_path, out_path, character: Character, fitted: FittedSkin, clips=()) -> int:
    """Write source_path (.glb/.gltf of ``character``) to out_path (.glb) with the fitted weights
    on its skinned primitives, plus ``clips`` (Clips of its skeleton) as new animations; returns
    the file's size in bytes (the file itself is in place when the command's outputs commit)."""
    path = Path(source_path)
    check_copyable(path)
    places = skinned_primitives(path, character)
    gltf, buffers = read_document(path)
    _, nodes = joint_nodes(path, gltf, buffers)
    if any(im.uri is not None and not im.uri.startswith("data:") for im in gltf.images or []):
        raise InputError(f"{path}: images in separate files are not copied; give the .glb of the character")
    blob = Blob(gltf)
    starts = [blob.append(bytes(b)) for b in buffers]
    for view in gltf.bufferViews:
        view.byteOffset = (view.byteOffset or 0) + starts[view.buffer]
        view.buffer = 0
    for place, j, w in zip(places, fitted.joints, fitted.weights):
        if place is None:
            continue
        mesh, p, skin, _ = place
        local = {int(n): k for k, n in enumerate(gltf.skins[skin].joints)}
        try:
            skin_joints = np.vectorize(lambda x: local[int(nodes[x])], otypes=[np.int64])(j)
        except KeyError:
            raise InputError(f"mesh {mesh}: a fitted joint is not in skin {skin}") from None
        sets = -(-j.shape[1] // 4)
        pad = 4 * sets - j.shape[1]
        J = np.pad(skin_joints, ((0, 0), (0, pad)), mode="edge").astype(np.uint16)
        W = np.pad(w, ((0, 0), (0, pad))).astype(np.float32)
        attrs = gltf.meshes[mesh].primitives[p].attributes
        for s in range(sets):
            setattr(attrs, f"JOINTS_{s}", blob.add(J[:, 4 * s:4 * s + 4], "VEC4", pygltflib.UNSIGNED_SHORT,
                                                   pygltflib.ARRAY_BUFFER))
            setattr(attrs, f"WEIGHTS_{s}", blob.add(W[:, 4 * s:4 * s + 4], "VEC4", pygltflib.FLOAT,
                                                    pygltflib.ARRAY_BUFFER))
        s = sets
        while getattr(attrs, f"JOINTS_{s}", None) is not None:   # older sets beyond the fitted ones
            setattr(attrs, f"JOINTS_{s}", None)
            setattr(attrs, f"WEIGHTS_{s}", None)
            s += 1
    data = blob.bytes()
    gltf.buffers = [pygltflib.Buffer(byteLength=len(data))]
    gltf.set_binary_blob(data)
    with atomic_path(Path(out_path)) as tmp:
        gltf.save_binary(str(tmp))
        for clip in clips:
            write_glb_with_clip(tmp, tmp, character, clip)
        return tmp.stat().st_size
