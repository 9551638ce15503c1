"""A new skinned glTF document for a character with no glTF to copy (a mesh + TGF/BVH skeleton).

:func:`skinned_document` makes:

* one node per joint, node j for joint j, named as the joint, with its rest local
  translation, rotation and scale, children as in the skeleton; the roots are scene nodes;
* one node per mesh (after the joints, at the scene's root: glTF ignores a skinned mesh
  node's own transform) holding one triangle primitive: ``POSITION`` the rest vertices
  (world space, which is also bind space here), ``NORMAL`` their area-weighted smooth
  normals (positions welded across seams), uint32 indices and the grey material of
  :func:`nrpose.io.gltf_write.new_document`;
* one skin over every joint, in joint order, whose inverse bind matrices are the
  inverses of the rest globals;
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
from .gltf_write import Blob, add_clip, json_float32, new_document

__all__ = ["skinned_document"]


def skinned_document(character: Character) -> tuple[pygltflib.GLTF2, Blob, list[int]]:
    """(document, its binary chunk, node index of each joint (J,)) for ``character`` (see the
    module docstring). InputError for a skeleton with nodes between its joints (``pre``, glTF
    only: copy that file instead), a rigidly attached mesh or a mesh without faces."""
    skeleton = character.skeleton
    J = skeleton.num_joints
    if not np.allclose(skeleton.pre, np.eye(4)):
        raise InputError("the skeleton has nodes between its joints (a glTF skeleton): write a copy of its file")
    gltf = new_document()
    blob = Blob(gltf)
    nodes = list(range(J))
    for j in range(J):
        gltf.nodes.append(pygltflib.Node(
            name=skeleton.names[j], translation=json_float32(skeleton.translation[j]),
            rotation=json_float32(skeleton.rotation[j]), scale=json_float32(skeleton.scale[j]),
            children=[int(c) for c in skeleton.children(j)] or None))
    inverse_bind = np.linalg.inv(skeleton.rest_globals())
    gltf.skins = [pygltflib.Skin(
        name="nrpose", joints=nodes,
        inverseBindMatrices=blob.add(np.transpose(inverse_bind, (0, 2, 1)).astype(np.float32).reshape(-1, 16),
                                     "MAT4"))]
    roots = [int(j) for j in np.flatnonzero(skeleton.parents < 0)]
    if len(roots) == 1:
        gltf.skins[0].skeleton = roots[0]
    mesh_nodes = []
    for mesh in character.meshes:
        if mesh.rigid_joint is not None or len(mesh.faces) == 0:
            raise InputError(f"mesh {mesh.name!r}: a skinned glTF is written for triangle meshes that deform "
                             "(this one is rigidly attached or has no faces)")
        V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
        attributes = pygltflib.Attributes(
            POSITION=blob.add(V.astype(np.float32), "VEC3", pygltflib.FLOAT, pygltflib.ARRAY_BUFFER, minmax=True),
            NORMAL=blob.add(smooth_normals(V, F, weld(V)).astype(np.float32), "VEC3", pygltflib.FLOAT,
                            pygltflib.ARRAY_BUFFER))
        indices = blob.add(F.astype(np.uint32).reshape(-1), "SCALAR", pygltflib.UNSIGNED_INT,
                           pygltflib.ELEMENT_ARRAY_BUFFER)
        gltf.meshes.append(pygltflib.Mesh(name=mesh.name, primitives=[pygltflib.Primitive(
            attributes=attributes, indices=indices, material=0, mode=pygltflib.TRIANGLES)]))
        gltf.nodes.append(pygltflib.Node(name=mesh.name, mesh=len(gltf.meshes) - 1, skin=0))
        mesh_nodes.append(len(gltf.nodes) - 1)
    gltf.scenes[0].nodes = roots + mesh_nodes
    for clip in character.clips:
        add_clip(gltf, blob, nodes, skeleton, clip)
    return gltf, blob, nodes
