"""A new skinned glTF document for a character with no glTF to copy (a mesh + TGF/BVH skeleton).

:func:`skinned_document` makes:

* one node per joint, node j for joint j, named as the joint, with its rest local
  translation, rotation and scale, children as in the skeleton; a joint with an explicit tip
  (a TGF bone's far end, a BVH ``End Site``) where no child joint sits gets a child node
  ``<joint>_end`` there, a joint of the skin that no vertex uses (glTF has no tips: Mixamo and
  Blender files keep a leaf bone's length the same way, and nrpose reads the file back with
  every bone, plus a short one beyond each end node); the roots are scene nodes, under one
  ``nrpose_root`` node (identity) when there are several, as glTF wants a skin's joints to
  have a common root;
* one node per mesh (after the joints, at the scene's root: glTF ignores a skinned mesh
  node's own transform) holding one triangle primitive: ``POSITION`` the rest vertices
  (world space, which is also bind space here), ``NORMAL`` their area-weighted smooth
  normals (positions welded across seams; +Y for a vertex no face uses), uint32 indices and
  the grey material of :func:`nrpose.io.gltf_write.new_document`;
* one skin over every joint, in joint order, then the end nodes, whose inverse bind matrices
  are the inverses of their rest globals;
* the character's clips as animations (:func:`nrpose.io.gltf_write.add_clip`).

The primitives get no ``JOINTS_n``/``WEIGHTS_n``: the caller adds the weights it has
(:func:`nrpose.fit.skin_file.write_fitted_glb`).
"""
from __future__ import annotations

import numpy as np
import pygltflib

from ..errors import InputError
from ..model.character import Character
from ..model.normals import smooth_normals, weld
from .gltf_write import Blob, add_clip, json_float32, new_document, unique_name

__all__ = ["skinned_document"]


def skinned_document(character: Character) -> tuple[pygltflib.GLTF2, Blob, list[int], list[tuple]]:
    """(document, its binary chunk, node index of each joint (J,), and per character mesh its
    (gltf mesh, primitive, skin, None) place) for ``character`` (see the module docstring).
    InputError for a skeleton with nodes between its joints (``pre``, glTF only: copy that file
    instead), a rigidly attached mesh or a mesh without faces."""
    skeleton = character.skeleton
    J = skeleton.num_joints
    if not np.allclose(skeleton.pre, np.eye(4)):
        raise InputError("the skeleton has nodes between its joints (a glTF skeleton): write a copy of its file")
    gltf = new_document()
    blob = Blob(gltf)
    for j in range(J):
        gltf.nodes.append(pygltflib.Node(
            name=skeleton.names[j], translation=json_float32(skeleton.translation[j]),
            rotation=json_float32(skeleton.rotation[j]), scale=json_float32(skeleton.scale[j]),
            children=[int(c) for c in skeleton.children(j)]))
    rest = skeleton.rest_globals()
    binds = list(rest)
    names = set(skeleton.names)
    for j in np.flatnonzero(np.isfinite(skeleton.tips[:, 0])):
        near = 1e-9 * (1 + np.abs(skeleton.tips[j]).max())
        if any(np.abs(skeleton.translation[c] - skeleton.tips[j]).max() <= near for c in skeleton.children(j)):
            continue        # a child joint's bone already ends there (every TGF bone has a tip)
        name = unique_name(f"{skeleton.names[j]}_end", names)
        gltf.nodes.append(pygltflib.Node(name=name, translation=json_float32(skeleton.tips[j])))
        gltf.nodes[j].children.append(len(gltf.nodes) - 1)
        binds.append(rest[j] @ np.block([[np.eye(3), skeleton.tips[j][:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    for node in gltf.nodes:
        node.children = node.children or None
    inverse_bind = np.linalg.inv(np.array(binds))
    gltf.skins = [pygltflib.Skin(
        name="nrpose", joints=list(range(len(gltf.nodes))),
        inverseBindMatrices=blob.add(np.transpose(inverse_bind, (0, 2, 1)).astype(np.float32).reshape(-1, 16),
                                     "MAT4"))]
    roots = [int(j) for j in np.flatnonzero(skeleton.parents < 0)]
    if len(roots) > 1:
        gltf.nodes.append(pygltflib.Node(name=unique_name("nrpose_root", names), children=roots))
        roots = [len(gltf.nodes) - 1]
    gltf.skins[0].skeleton = roots[0]
    places = []
    for mesh in character.meshes:
        if mesh.rigid_joint is not None or len(mesh.faces) == 0:
            raise InputError(f"mesh {mesh.name!r}: a skinned glTF is written for triangle meshes that deform "
                             "(this one is rigidly attached or has no faces)")
        V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
        normals = smooth_normals(V, F, weld(V))
        normals[~(np.linalg.norm(normals, axis=1) > 0.5)] = (0.0, 1.0, 0.0)     # a vertex no face uses
        attributes = pygltflib.Attributes(
            POSITION=blob.add(V.astype(np.float32), "VEC3", pygltflib.FLOAT, pygltflib.ARRAY_BUFFER, minmax=True),
            NORMAL=blob.add(normals.astype(np.float32), "VEC3", pygltflib.FLOAT, pygltflib.ARRAY_BUFFER))
        indices = blob.add(F.astype(np.uint32).reshape(-1), "SCALAR", pygltflib.UNSIGNED_INT,
                           pygltflib.ELEMENT_ARRAY_BUFFER)
        places.append((len(gltf.meshes), 0, 0, None))
        gltf.meshes.append(pygltflib.Mesh(name=mesh.name, primitives=[pygltflib.Primitive(
            attributes=attributes, indices=indices, material=0, mode=pygltflib.TRIANGLES)]))
        gltf.nodes.append(pygltflib.Node(name=unique_name(mesh.name, names), mesh=places[-1][0], skin=0))
        roots.append(len(gltf.nodes) - 1)
    gltf.scenes[0].nodes = roots
    for clip in character.clips:
        add_clip(gltf, blob, list(range(J)), skeleton, clip)
    return gltf, blob, list(range(J)), places

