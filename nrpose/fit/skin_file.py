"""The source glTF written again with fitted skin weights (JOINTS_n / WEIGHTS_n), or, for a
character with no glTF to copy (a mesh + TGF/BVH skeleton), a new skinned glTF of it
(:mod:`nrpose.io.gltf_skinned`) with them.

Everything else is kept (nodes, materials, UVs, normals, textures, the source's
animations); all buffers are copied into the single GLB buffer and the new weights
take the place of the source's where nothing else reads those (else they are
appended: :meth:`nrpose.io.gltf_write.Blob.replace`), 4 per set, so 8 influences use
``JOINTS_0/1`` and ``WEIGHTS_0/1``: joints as unsigned bytes (unsigned shorts in a
skin of more than 256 joints), weights as normalised unsigned shorts (glTF's core
formats for them) whose rows sum to exactly 65535 (:func:`stored_weights`: the fit's
weights rounded by largest remainders, less than 1/65535 each from the fit's). A
source's sets beyond the fitted ones leave the primitive; their data stays.
Requested clips are added as ordinary animations (:func:`nrpose.io.gltf_write.add_clip`);
helper joints as nodes with their rules written as animation channels (:func:`write_fitted_glb`).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pygltflib

from ..checks import within_float32
from ..errors import InputError
from ..io.gltf_read import clip_animations, joint_nodes, node_globals, read_document
from ..io.gltf_skinned import skinned_document
from ..io.gltf_write import Blob, add_channel, add_clip, check_copyable, copy_document, json_float32, save_glb
from ..model.character import Character
from ..model.timing import sample_times
from .character_skin import FittedSkin, mesh_space
from .helper_joints import rule_locals
from .helper_keys import KEY_TOLERANCE, helper_keys, helper_trs, stored_quats

__all__ = ["skinned_primitives", "stored_weights", "stored_skin", "write_fitted_glb", "add_helper_nodes",
           "add_helper_channels"]

WEIGHT_SCALE = 65535     # a normalised unsigned short weight k means k / 65535


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


def stored_weights(w: np.ndarray) -> np.ndarray:
    """Weights (N, k) >= 0 with rows summing to 1 as the file stores them: (N, k) uint16, each row
    summing to exactly 65535 (rounded down, then the largest remainders rounded up); InputError
    for a row without a positive finite sum or with a negative weight."""
    w = np.asarray(w, np.float64)
    sums = w.sum(axis=1, keepdims=True)
    if not (np.isfinite(sums).all() and (sums > 0).all() and (w >= 0).all()):
        raise InputError("skin weights: a vertex's weights are negative, not finite or all zero")
    scaled = w * (WEIGHT_SCALE / sums)
    out = np.floor(scaled)
    short = (WEIGHT_SCALE - out.sum(axis=1)).astype(np.int64)       # 0 <= short < k
    rank = np.argsort(np.argsort(out - scaled, axis=1, kind="stable"), axis=1)   # largest remainder first
    out += rank < short[:, None]
    return out.astype(np.uint16)


def stored_skin(fitted: FittedSkin) -> FittedSkin:
    """``fitted`` with the weights the file stores (:func:`stored_weights`, as float64 fractions),
    so that what is computed from it is what players of the file compute."""
    return replace(fitted, weights=tuple(None if w is None else stored_weights(w) / WEIGHT_SCALE
                                         for w in fitted.weights))


def write_fitted_glb(source_path, out_path, character: Character, fitted: FittedSkin, clips=(),
                     fps: float = 30.0, tracks=None, key_tolerance: float = KEY_TOLERANCE) -> int:
    """Write source_path (.glb/.gltf of ``character``) to out_path (.glb) with the fitted weights
    on its skinned primitives, plus ``clips`` (Clips of its skeleton) as new animations; returns
    the file's size in bytes (the file itself is in place when the command's outputs commit).
    source_path None: a character with no glTF to copy (a mesh + TGF/BVH skeleton) is written as
    a new skinned document (:func:`nrpose.io.gltf_skinned.skinned_document`).

    Helper joints (``fitted.helpers``) become nodes, children of their parent joint's node, in
    every skin holding that joint (inverse bind appended); their rules are evaluated at ``fps``
    over every animation of the file (the source's and ``clips``) and written as translation and
    rotation channels of those animations, keeping the keys a player needs to stay within
    ``key_tolerance`` (a fraction of the character's height; 0 keeps every frame:
    :func:`nrpose.fit.helper_keys.helper_keys`); their rest TRS is the rule at the rest pose.
    tracks: instead of the rules, per animation (the source's, then ``clips``) the helpers'
    local transforms (F, H, 4, 4) at ``fps`` (:func:`nrpose.fit.helper_tracks.fit_helper_tracks`).
    """
    skeleton = character.skeleton
    if source_path is None:
        gltf, blob, nodes, places = skinned_document(character)
    else:
        path = Path(source_path)
        check_copyable(path)
        places = skinned_primitives(path, character)
        gltf, blob, buffers = copy_document(path)
        _, nodes = joint_nodes(path, gltf, buffers)
    for clip in clips:
        add_clip(gltf, blob, nodes, skeleton, clip)
    node_of = [int(n) for n in nodes] + add_helper_nodes(gltf, blob, character, places, fitted.helpers, nodes)
    for place, j, w in zip(places, fitted.joints, fitted.weights):
        if place is None:
            continue
        mesh, p, skin, _ = place
        local = {int(n): k for k, n in enumerate(gltf.skins[skin].joints)}
        try:
            skin_joints = np.vectorize(lambda x: local[node_of[x]], otypes=[np.int64])(j)
        except KeyError:
            raise InputError(f"mesh {mesh}: a fitted joint is not in skin {skin}") from None
        sets = -(-j.shape[1] // 4)
        pad = 4 * sets - j.shape[1]
        small = len(gltf.skins[skin].joints) <= 256
        J = np.pad(skin_joints, ((0, 0), (0, pad)), mode="edge").astype(np.uint8 if small else np.uint16)
        W = np.pad(stored_weights(w), ((0, 0), (0, pad)))
        attrs = gltf.meshes[mesh].primitives[p].attributes
        for s in range(sets):     # in the source's JOINTS_s / WEIGHTS_s accessors where it has them
            for name, data, component, normalized in (
                    (f"JOINTS_{s}", J, pygltflib.UNSIGNED_BYTE if small else pygltflib.UNSIGNED_SHORT, False),
                    (f"WEIGHTS_{s}", W, pygltflib.UNSIGNED_SHORT, True)):
                old = getattr(attrs, name, None)
                setattr(attrs, name, blob.replace(-1 if old is None else old, data[:, 4 * s:4 * s + 4], "VEC4",
                                                  component, pygltflib.ARRAY_BUFFER, normalized))
        s = sets
        while getattr(attrs, f"JOINTS_{s}", None) is not None:   # older sets beyond the fitted ones
            setattr(attrs, f"JOINTS_{s}", None)
            setattr(attrs, f"WEIGHTS_{s}", None)
            s += 1
    if fitted.helpers:
        helper_nodes = node_of[skeleton.num_joints:]
        every = tuple(character.clips) + tuple(clips)
        animations = gltf.animations
        if source_path is not None:
            animations = [gltf.animations[a] for a in clip_animations(path, gltf, nodes)]    # the clips' own
            if len(animations) != len(every):
                raise InputError(f"{path}: its animations do not match the loaded character's clips")
        for k, (animation, clip) in enumerate(zip(animations, every)):
            times = sample_times(clip.duration, fps)
            pose = clip.sample(times)
            local = rule_locals(fitted.helpers, skeleton, pose) if tracks is None else tracks[k]
            keys, _ = helper_keys(character, fitted, skeleton.forward_kinematics(pose), local, times, key_tolerance)
            add_helper_channels(blob, animation, local, helper_nodes, times, keys)
    return save_glb(gltf, blob, Path(out_path))


def add_helper_nodes(gltf, blob: Blob, character: Character, places, helpers, nodes) -> list:
    """Add the helper nodes (see :func:`write_fitted_glb`) to the document; their node indices."""
    skeleton = character.skeleton
    added = []
    names = {n.name for n in gltf.nodes}
    for h, helper in enumerate(helpers):
        t, q = helper_trs(helper.local(skeleton, skeleton.rest_pose))
        name, k = f"nrpose_helper_{h}", 2
        while name in names:
            name, k = f"nrpose_helper_{h}_{k}", k + 1
        names.add(name)
        gltf.nodes.append(pygltflib.Node(name=name, translation=json_float32(t[0]), rotation=json_float32(q[0])))
        parent = gltf.nodes[int(nodes[helper.parent])]
        parent.children = list(parent.children or []) + [len(gltf.nodes) - 1]
        added.append(len(gltf.nodes) - 1)
    if not helpers:
        return added
    done, world = set(), None
    joint_of = {int(n): j for j, n in enumerate(nodes)}
    for place, mesh in zip(places, character.meshes):
        if place is None or place[2] in done:
            continue
        done.add(place[2])
        skin = gltf.skins[place[2]]
        _, ibm = mesh_space(character, mesh)
        if world is None and any(int(n) not in joint_of for n in skin.joints):
            # a skin's node that is no joint of the character (a new document's end node): bound at rest
            world = node_globals("the document", gltf)[1]
        mats = [ibm[joint_of[int(n)]] if int(n) in joint_of else np.linalg.inv(world[int(n)]) for n in skin.joints]
        for helper, node in zip(helpers, added):
            if int(nodes[helper.parent]) in skin.joints:
                skin.joints.append(node)
                mats.append(helper.inverse_bind(ibm[helper.parent]))
        old = -1 if skin.inverseBindMatrices is None else skin.inverseBindMatrices
        skin.inverseBindMatrices = blob.replace(old, np.transpose(mats, (0, 2, 1)).astype(np.float32).reshape(-1, 16),
                                                "MAT4", pygltflib.FLOAT)
    return added


def add_helper_channels(blob: Blob, animation, local: np.ndarray, helper_nodes, times: np.ndarray, keys) -> None:
    """Append to ``animation`` the helpers' translation and rotation channels (LINEAR): local
    (F, H, 4, 4) their local transforms at times (F,) seconds, of which helper h keeps the frames
    keys[h] (int array). One buffer view holds them all; rotations are normalised int16
    (:func:`nrpose.fit.helper_keys.stored_quats`, glTF's core format for them), translations
    float32; helpers keeping the same frames share their times."""
    items, times_item, slots = [], {}, []
    for h in range(len(helper_nodes)):
        kept = np.asarray(keys[h])
        if kept.tobytes() not in times_item:
            times_item[kept.tobytes()] = len(items)
            items.append((times[kept].astype(np.float32), "SCALAR", pygltflib.FLOAT, False, True))
        t, q = helper_trs(local[:, h])
        within_float32(t[kept], "helper joint translation")
        slots.append((times_item[kept.tobytes()], len(items), len(items) + 1))
        items += [(t[kept].astype(np.float32), "VEC3", pygltflib.FLOAT, False, False),
                  (stored_quats(q[kept]), "VEC4", pygltflib.SHORT, True, False)]
    index = blob.add_together(items)
    for node, (k, t, r) in zip(helper_nodes, slots):
        for path, output in (("translation", index[t]), ("rotation", index[r])):
            add_channel(animation, node, path, index[k], output)
