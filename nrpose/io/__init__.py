"""Every reader and writer of nrpose's files; :func:`load_character` picks a reader by suffix.

Characters: glTF 2.0 (:mod:`.gltf_read`, written by :mod:`.gltf_write`), BVH
(:mod:`.bvh_read`, :mod:`.bvh_write`), libigl TGF skeletons and OBJ/OFF/PLY/STL/.mesh
meshes (:mod:`.tgf`). Deformable geometry: :mod:`.meshes`. Pose, handle and
joint-map JSON: :mod:`.poses`. Input checks and atomic writes: :mod:`.files`.
"""
from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

from ..checks import check_magnitude
from ..errors import FileFormatError, InputError
from ..model.character import Character, Clip, Mesh

__all__ = ["load_character", "READERS", "MESH_SUFFIXES"]

#: mesh file suffixes (read by :func:`.tgf.read_mesh`)
MESH_SUFFIXES = (".obj", ".off", ".ply", ".stl", ".mesh")

# Each reader below imports its module when called: a job imports the readers of its own files only.


def _gltf_character(path: Path) -> Character:
    from .gltf_read import load_gltf

    return load_gltf(path)


def _bvh_character(path: Path) -> Character:
    from .bvh_read import read_bvh

    skeleton, clip = read_bvh(path)
    return Character(skeleton, clips=(clip,))


def _tgf_character(path: Path) -> Character:
    from .tgf import read_tgf

    return Character(read_tgf(path))


def _mesh(path: Path) -> Mesh:
    from .tgf import read_mesh

    vertices, faces = read_mesh(path)
    return Mesh(path.stem, vertices, faces)


#: suffix -> (reader of a Path, what it gives: "character" with its own skeleton, "skeleton"
#: (a Character without meshes), or "mesh" (a Mesh, needing a skeleton file beside it))
READERS = {".glb": (_gltf_character, "character"), ".gltf": (_gltf_character, "character"),
           ".bvh": (_bvh_character, "skeleton"), ".tgf": (_tgf_character, "skeleton"),
           **{suffix: (_mesh, "mesh") for suffix in MESH_SUFFIXES}}


def load_character(path: str | Path, skeleton: str | Path | None = None) -> Character:
    """Load a character by extension (:data:`READERS`).

    ``.glb``/``.gltf``: meshes, skin, clips. ``.bvh``: skeleton and its motion
    clip, no mesh. ``.tgf``: skeleton only. A mesh (``.obj .off .ply .stl
    .mesh``) needs ``skeleton`` (a ``.tgf`` or ``.bvh``); it gets no skin weights.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in READERS:
        raise FileFormatError(f"{path}: unknown character extension {suffix!r}; use .glb, .gltf, .bvh, "
                              f".tgf or a mesh ({', '.join(MESH_SUFFIXES)}) with a skeleton")
    reader, kind = READERS[suffix]
    if kind == "mesh":
        if skeleton is None or READERS.get(Path(skeleton).suffix.lower(), (None, None))[1] != "skeleton":
            raise InputError(f"{path}: a mesh needs a skeleton, a .tgf or .bvh file"
                             + ("" if skeleton is None else f" (got {skeleton})"))
        base = load_character(skeleton)
        return Character(base.skeleton, (reader(path),), base.clips)
    if skeleton is not None:
        raise InputError(f"{path}: a glTF file carries its own skeleton; do not pass one" if kind == "character"
                         else f"{path}: is already a skeleton; pass a mesh with it instead")
    return _check_ranges(reader(path), path)


def _check_ranges(character: Character, path: Path) -> Character:
    """The character, after FileFormatError if a coordinate it carries (vertices, joint
    offsets) exceeds :data:`nrpose.checks.MAX_COORDINATE`; its clips' translations are
    checked likewise as each clip is made (:func:`_check_clip`)."""
    skel = character.skeleton
    check_magnitude(skel.translation, f"{path}: joint translations", FileFormatError)
    for mesh in character.meshes:
        for values in (mesh.vertices, mesh.bind_vertices):
            if values is not None:
                check_magnitude(values, f"{path}: vertices of mesh {mesh.name!r}", FileFormatError)
    return dataclasses.replace(character, clips=character.clips.then(functools.partial(_check_clip, path,
                                                                                       skel.names)))


def _check_clip(path: Path, joints: tuple[str, ...], clip: Clip) -> Clip:
    """The clip of the file ``path`` (on joints named ``joints``), after FileFormatError if a
    translation key exceeds :data:`nrpose.checks.MAX_COORDINATE`."""
    for track in clip.tracks:
        if track.path == "translation":
            check_magnitude(track.values, f"{path}: clip {clip.name!r}: translations of joint "
                                          f"{joints[track.joint]!r}", FileFormatError)
    return clip
