"""A character's meshes as one vertex set: what posing and weighting work on."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MeshSet", "concatenate_meshes", "submesh_faces"]


@dataclass(frozen=True)
class MeshSet:
    """A character's meshes concatenated in file order: vertices (V, 3) float64,
    faces (M, 3) int64 (into the concatenation), offsets (meshes,) int64 where
    each mesh starts, names, rigid (V,) int64: the joint a rigidly attached
    vertex follows, or -1 for skinned/deforming vertices."""

    vertices: np.ndarray
    faces: np.ndarray
    offsets: np.ndarray
    names: tuple[str, ...]
    rigid: np.ndarray


def concatenate_meshes(meshes) -> MeshSet:
    """:class:`MeshSet` of a character's meshes (:class:`nrpose.model.character.Mesh`)."""
    sizes = np.array([len(m.vertices) for m in meshes], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    return MeshSet(
        vertices=np.concatenate([m.vertices for m in meshes]).astype(np.float64),
        faces=np.concatenate([np.asarray(m.faces, np.int64).reshape(-1, 3) + o
                              for m, o in zip(meshes, offsets)]).astype(np.int64),
        offsets=offsets, names=tuple(m.name for m in meshes),
        rigid=np.concatenate([np.full(len(m.vertices), -1 if m.rigid_joint is None else m.rigid_joint)
                              for m in meshes]).astype(np.int64))


def submesh_faces(faces: np.ndarray, keep: np.ndarray, n: int) -> np.ndarray:
    """Faces (M', 3) among the vertices ``keep`` (renumbered 0..len(keep)-1) of n vertices,
    dropping faces that leave them."""
    new = np.full(n, -1)
    new[keep] = np.arange(len(keep))
    f = new[faces]
    return f[(f >= 0).all(axis=1)]
