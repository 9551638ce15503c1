"""Character file readers: glTF 2.0 (:mod:`.gltf`), BVH (:mod:`.bvh`) and libigl
TGF/DMAT with OBJ/OFF/PLY/STL/.mesh meshes (:mod:`.tgf`).

Each reader returns plain arrays or :class:`~nrpose.skeleton.Skeleton` objects;
:func:`nrpose.character.load_character` picks one by file extension.
"""
