"""glTF 2.0 binaries (``.glb``): baked animations, and a character file with a clip added.

:func:`write_animated_glb` bakes posed frames as **morph targets** (target f =
posed frame f − base, for ``POSITION``, ``NORMAL`` and, where the source has
it, ``TANGENT``) and one animation whose ``weights`` channel(s) switch between
the targets: at key time ``t_f`` the weight vector is zero except at f, with
LINEAR interpolation in between (so playback blends consecutive frames
linearly, exactly reproducing every frame at its time). No skin is written: the
file shows the deformation that was computed (any deformer).

With ``source`` (the glTF the character was loaded from) the output is a
**copy of that document**: materials, textures, images (external and
``data:`` images are embedded in the binary chunk), samplers, every attribute
of the posed primitives but their geometry (all ``TEXCOORD_n``, ``COLOR_n``,
custom ``_X``), other nodes and meshes (static meshes stay as they are), the
scene tree, skins, ``extras`` and extensions nrpose does not know. Each posed
node (one per source node; one primitive per source primitive, same indices,
mode and material) moves to a new **root-level node** with the source node's
name, so that its vertices are nrpose's world-space positions whatever the
ancestors' (possibly animated) transforms; the source node stays in the tree
without its mesh and skin, and the posed primitives lose ``JOINTS_n``/
``WEIGHTS_n`` and their own morph targets. The source's animations are
replaced by the bake (they moved the skeleton, which now deforms nothing); their
data stays in the buffer, unreferenced, so that nothing is renumbered.

Normals: per vertex, the file's ``NORMAL`` (and ``TANGENT``) is turned by the
rotation of the vertex's welded neighbourhood from the source geometry to the
frame (:func:`nrpose.model.normals.local_rotations`; on the device for large bakes,
``rotations=``): custom normals, seams and hard edges keep their shape. Without ``NORMAL``
in the source, the
smooth normals of the posed surface are written (positions welded across seams).

A source that *requires* an extension nrpose cannot carry faithfully
(:data:`CARRIED` lists what it can) raises FileFormatError before anything is
written.

Compact bakes (``quantize=True``, ``KHR_mesh_quantization``): position deltas
are normalised int16 (8 bytes per vertex: glTF aligns every vertex attribute
element to 4 bytes), normal and tangent deltas normalised int8 (4 bytes each),
or int16 (8) for a primitive's frame that int8 cannot hold within
:data:`DIRECTION_BOUND` degrees, else float (:func:`_direction_delta`: the target
direction is scaled per vertex to keep its delta within [-1, 1], as clients
normalise morphed normals).
The dequantisation scale is the posed node's uniform scale ``S``, the largest
position delta of the clip (base positions are stored divided by S; normals
are unaffected by a uniform scale), so a position's error is at most
``S / 65534``; when that exceeds :data:`QUANTIZATION_BOUND` of the rest
bounding-box diagonal (clips travelling several body lengths) the node stays
float. Morph weights stay 0 and 1 (Blender clamps larger shape-key values).
Identical frames and primitives' arrays are written once (targets share
accessors). The mesh's
default ``weights`` select frame 0; ``mesh.extras.targetNames`` are
``frame0 ...``. Coordinates are written as given (glTF is Y-up, metres).
Written through :func:`nrpose.io.files.atomic_path`.

:func:`write_glb_with_clip` writes a glTF character file again with one more
animation: a :class:`~nrpose.model.character.Clip` of its skeleton, one
sampler per track on its joint's node (float32, the track's times and
interpolation; a joint node given as a ``matrix`` is rewritten as its TRS, as
animated nodes must be). The original content (meshes, skins, materials, textures,
other animations unless ``keep_animations=False``) is kept: every buffer is
copied into the single GLB buffer (a ``.gltf`` with external buffers or images
becomes self-contained) and the new data is appended after it.
"""
from __future__ import annotations

import base64
import hashlib
import mimetypes
import struct
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pygltflib

from ..checks import check_magnitude, real_rows, triangles, within_float32
from ..errors import FileFormatError, InputError, NrposeError
from ..model.bounds import column_bounds
from ..model.normals import Surface, weld
from ..model.rotation import Rotation
from ..model.skeleton import polar_rotation
from .files import atomic_path
from .gltf_read import joint_nodes, node_globals, read_accessor, read_document
from .gltf_schema import MAX_ITEMS

__all__ = ["write_animated_glb", "write_glb_with_clip", "fit_skinned_nodes", "check_copyable", "copy_document",
           "save_glb", "add_clip", "add_channel", "json_float32", "float32_times", "new_document", "unique_name",
           "BakeReport", "Blob", "CARRIED", "QUANTIZATION_BOUND", "DIRECTION_BOUND"]

_FLOAT, _UINT, _SHORT, _BYTE = pygltflib.FLOAT, pygltflib.UNSIGNED_INT, pygltflib.SHORT, pygltflib.BYTE
QUANTIZATION = "KHR_mesh_quantization"
#: largest position error of a quantized frame, as a fraction of the rest bounding-box diagonal
QUANTIZATION_BOUND = 1e-4
#: largest angle (degrees) between a quantized frame's normal or tangent and the exact one
DIRECTION_BOUND = 1.0
#: frames whose normals' rotations are computed together (one launch on the device)
FRAME_BATCH = 16
#: required extensions a posed copy keeps faithfully (materials, textures, lights, quantized attributes)
CARRIED = frozenset({
    QUANTIZATION, "KHR_texture_transform", "KHR_texture_basisu", "EXT_texture_webp", "EXT_texture_avif",
    "KHR_lights_punctual", "KHR_materials_unlit", "KHR_materials_emissive_strength", "KHR_materials_ior",
    "KHR_materials_specular", "KHR_materials_volume", "KHR_materials_transmission", "KHR_materials_clearcoat",
    "KHR_materials_sheen", "KHR_materials_iridescence", "KHR_materials_anisotropy", "KHR_materials_dispersion",
    "KHR_materials_variants", "KHR_materials_pbrSpecularGlossiness"})
#: primitive extensions that define the geometry the bake replaces
_GEOMETRY_EXTENSIONS = ("KHR_draco_mesh_compression",)


def _mesh_list(character_or_meshes) -> list[tuple[str, np.ndarray, np.ndarray, tuple | None]]:
    """(name, vertices (N, 3) float64, faces (M, 3) int64, source indices or None) per mesh."""
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
        out.append((str(name), V, triangles(F, len(V), f"mesh {i} ({name}) faces"), getattr(m, "source", None)))
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
    P = np.asarray(positions)
    if P.dtype.kind != "f":
        P = P.astype(np.float64)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[0] == 0:
        raise InputError(f"positions must have shape (frames, vertices, 3) with at least one frame, "
                         f"got {np.shape(positions)}")
    if P.shape[1] < total_needed:
        raise InputError(f"positions have {P.shape[1]} vertices per frame; the meshes need {total_needed}")
    for f in range(len(P)):
        if not np.isfinite(P[f]).all():
            raise InputError(f"positions of frame {f} contain NaN or inf")
    T = np.asarray(times, dtype=np.float64).reshape(-1)
    if T.shape != (P.shape[0],):
        raise InputError(f"times: expected {P.shape[0]} values (one per frame), got {T.shape[0]}")
    float32_times(T, "times")
    return P, T


def float32_times(times, what: str) -> np.ndarray:
    """Key times (K,) as the float32 seconds a glTF file stores them; InputError naming ``what``
    unless they are finite, non-negative, within float32's range and strictly increasing once
    stored (frames closer than float32 tells apart at their time would share a key time)."""
    T = np.asarray(times, dtype=np.float64).reshape(-1)
    if not np.isfinite(T).all() or (T < 0).any() or T.max(initial=0.0) > np.finfo(np.float32).max:
        raise InputError(f"{what}: key times must be finite, non-negative seconds within float32's range")
    stored = T.astype(np.float32)
    if (np.diff(stored) <= 0).any():
        k = int(np.argmax(np.diff(stored) <= 0))
        raise InputError(f"{what}: key times {T[k]:.9g} s and {T[k + 1]:.9g} s are not strictly increasing as the "
                         "file's float32 seconds; frames must be further apart (check the frame time or --fps)")
    return stored


class Blob:
    """The binary chunk of a GLB being written: aligned buffer views (4 bytes; 8 where the document
    needs it) and accessors.

    Appends to ``gltf.bufferViews`` / ``gltf.accessors`` (all views in buffer 0); ``parts``
    (bytes each) make the chunk's content, ``size`` bytes (:func:`save_glb` writes them).
    """

    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf, self.parts, self.size = gltf, [], 0
        self.align = max(4, gltf.required_alignment())     # 8 for documents that use EXT_structural_metadata
        self.replaced: dict[int, bytes] = {}       # view -> its new bytes (:meth:`replace`)

    def append(self, data: bytes) -> int:
        """Append raw bytes (then pad to the document's alignment, 4 or 8); their byte offset."""
        start = self.size
        self.parts.append(data)
        self.size += len(data)
        pad = (-self.size) % self.align
        if pad:
            self.parts.append(b"\0" * pad)
            self.size += pad
        return start

    def raw(self, data: bytes, target=None, stride: int | None = None) -> int:
        """A buffer view of raw bytes; its index."""
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=self.append(data),
                                                          byteLength=len(data), target=target, byteStride=stride))
        return len(self.gltf.bufferViews) - 1

    def add(self, array: np.ndarray, kind: str, component: int = pygltflib.FLOAT, target=None,
            minmax: bool = False, normalized: bool = False) -> int:
        """A buffer view and an accessor for ``array`` (already of the component's dtype; integers
        read as fractions of the type's maximum where ``normalized``); its index."""
        return self._accessor(self.raw(np.ascontiguousarray(array).tobytes(), target), 0, array, kind,
                              component, normalized, minmax)

    def add_together(self, items) -> list[int]:
        """Accessors for several arrays in one buffer view (fewer views in the JSON than
        :meth:`add`, one each): items (array already of the component's dtype, kind,
        component, normalized, minmax) as :meth:`add`; each starts 4-byte aligned. Not for
        vertex attributes (no stride). Their accessor indices."""
        chunks, offsets, at = [], [], 0
        for array, *_ in items:
            data = np.ascontiguousarray(array).tobytes()
            offsets.append(at)
            chunks += [data, b"\0" * (-len(data) % 4)]
            at += len(data) + (-len(data) % 4)
        view = self.raw(b"".join(chunks))
        return [self._accessor(view, offset, *item) for item, offset in zip(items, offsets)]

    def _accessor(self, view: int, offset: int, array, kind: str, component: int, normalized: bool,
                  minmax: bool) -> int:
        """Append the accessor of ``array`` at ``offset`` in buffer view ``view``; its index."""
        acc = pygltflib.Accessor(bufferView=view, byteOffset=offset or None, componentType=component,
                                 count=len(array), type=kind, normalized=normalized or None)
        if minmax:
            low, high = column_bounds(np.asarray(array).reshape(len(array), -1))
            acc.min, acc.max = (json_float32(low), json_float32(high)) if component == _FLOAT else \
                ([float(x) for x in low], [float(x) for x in high])
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def replace(self, accessor: int, array: np.ndarray, kind: str, component: int, target=None,
                normalized: bool = False) -> int:
        """Like :meth:`add`, but where the document lets it, accessor ``accessor`` (read by one
        reference only, the one the caller is replacing) takes the new data in place: its buffer
        view, read by no other accessor or image, gets the new bytes and the old ones leave the
        chunk (:func:`save_glb` packs the views again), so a rewritten attribute leaves no dead
        data. Elsewhere (a shared view, sparse data, an extension nrpose does not know, which
        might read views) a new accessor is added. Returns the accessor's index."""
        acc = self.gltf.accessors[accessor] if 0 <= accessor < len(self.gltf.accessors) else None
        if acc is None or acc.sparse is not None or acc.bufferView is None:
            return self.add(array, kind, component, target, normalized=normalized)
        accessors, views = _references(self.gltf)
        if accessors[accessor] != 1 or views[acc.bufferView] != 1:
            return self.add(array, kind, component, target, normalized=normalized)
        data = np.ascontiguousarray(array)
        view = self.gltf.bufferViews[acc.bufferView]
        view.byteStride, view.target, view.byteLength = None, target, data.nbytes
        self.replaced[acc.bufferView] = data.tobytes()
        self.gltf.accessors[accessor] = pygltflib.Accessor(bufferView=acc.bufferView, byteOffset=None,
                                                           componentType=component,
                                                           count=len(data), type=kind, normalized=normalized or None,
                                                           name=acc.name, extras=acc.extras,
                                                           extensions=acc.extensions)
        return accessor

    def pack(self) -> None:
        """Lay the chunk out again from the buffer views (the replaced ones' new bytes), leaving out
        bytes no view reads; nothing to do without :meth:`replace` d views."""
        if not self.replaced:
            return
        starts = np.cumsum([0] + [len(p) for p in self.parts])
        parts = self.parts
        self.parts, self.size = [], 0
        for i, view in enumerate(self.gltf.bufferViews):
            data = self.replaced.get(i)
            if data is None:       # a slice of the part the view lies in (views never span two)
                start = view.byteOffset or 0
                k = int(np.searchsorted(starts, start, side="right")) - 1
                data = memoryview(parts[k])[start - starts[k]:start - starts[k] + view.byteLength]
                if len(data) != view.byteLength:
                    raise FileFormatError(f"bufferView {i} runs past the end of its buffer")
            view.byteOffset = self.append(data)
        self.replaced = {}

    def normalized_vec3(self, values: np.ndarray, dtype, minmax: bool = False) -> int:
        """A normalised integer VEC3 vertex attribute of ``values`` (N, 3) (already integers of
        ``dtype``), padded to a 4-byte stride as glTF requires; its accessor index."""
        n, size = len(values), np.dtype(dtype).itemsize
        padded = np.zeros((n, 4), dtype)
        padded[:, :3] = values
        view = self.raw(padded.tobytes(), pygltflib.ARRAY_BUFFER, 4 * size)
        acc = pygltflib.Accessor(bufferView=view, byteOffset=None, componentType=_SHORT if size == 2 else _BYTE,
                                 normalized=True, count=n, type="VEC3")
        if minmax:   # normalised accessors keep min/max in the stored integers
            low, high = column_bounds(values)
            acc.min, acc.max = [int(x) for x in low], [int(x) for x in high]
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


def json_float32(values) -> list[float]:
    """values (any shape, reals) as a flat list of the shortest decimals that read back as the same
    float32: glTF readers take JSON numbers as float32, and float64's 17 digits would double the
    text of accessor bounds and node transforms. InputError where a value is not a finite float32."""
    values = np.asarray(values, np.float64)
    if not np.isfinite(values).all():
        raise InputError("a number for the glTF's JSON is NaN or infinite; check the data it comes from")
    within_float32(values, "a number for the glTF's JSON")
    return [float(str(x)) for x in values.astype(np.float32).reshape(-1)]


def add_channel(animation: pygltflib.Animation, node: int, path: str, input: int, output: int,
                interpolation: str = "LINEAR") -> None:
    """Append a sampler (accessors ``input``, ``output``) and the channel driving ``path`` of node
    ``node`` with it; LINEAR, glTF's default interpolation, is left unwritten."""
    animation.samplers.append(pygltflib.AnimationSampler(
        input=input, output=output, interpolation=None if interpolation == "LINEAR" else interpolation))
    animation.channels.append(pygltflib.AnimationChannel(
        sampler=len(animation.samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path=path)))


def _references(gltf: pygltflib.GLTF2) -> tuple[np.ndarray, np.ndarray]:
    """How many times each accessor and each buffer view is referenced: (accessors,) and (views,)
    int64 counts; every count is a large number in a document using an extension outside
    :data:`CARRIED` (one might reference them)."""
    acc = np.zeros(len(gltf.accessors), np.int64)
    views = np.zeros(len(gltf.bufferViews), np.int64)
    if set(gltf.extensionsUsed or []) - CARRIED:
        return acc + 2 ** 40, views + 2 ** 40
    for mesh in gltf.meshes:
        for prim in mesh.primitives:
            refs = [v for v in vars(prim.attributes).values() if isinstance(v, int)] + \
                [v for t in prim.targets or [] for v in (t if isinstance(t, dict) else vars(t)).values()
                 if isinstance(v, int)] + ([prim.indices] if prim.indices is not None else [])
            np.add.at(acc, [r for r in refs if 0 <= r < len(acc)], 1)
    refs = [s.inverseBindMatrices for s in gltf.skins if s.inverseBindMatrices is not None] + \
        [i for a in gltf.animations for s in a.samplers for i in (s.input, s.output)]
    np.add.at(acc, [r for r in refs if isinstance(r, int) and 0 <= r < len(acc)], 1)
    refs = [a.bufferView for a in gltf.accessors] + [im.bufferView for im in gltf.images or []] + \
        [v for a in gltf.accessors if a.sparse is not None for v in (a.sparse.indices.bufferView,
                                                                     a.sparse.values.bufferView)]
    np.add.at(views, [r for r in refs if isinstance(r, int) and 0 <= r < len(views)], 1)
    return acc, views


def check_copyable(source) -> None:
    """FileFormatError when the glTF file ``source`` requires an extension a posed copy cannot carry
    (checked again by :func:`write_animated_glb`; call it before the work to fail early)."""
    _check_required(read_document(Path(source))[0], source)


def _check_required(gltf: pygltflib.GLTF2, path) -> None:
    for name in gltf.extensionsRequired or []:
        if name not in CARRIED:
            raise FileFormatError(f"{path}: requires the glTF extension {name!r}, which nrpose cannot carry "
                                  "into a posed copy faithfully; write .npz, or use a file without it")


def copy_document(path: Path) -> tuple[pygltflib.GLTF2, Blob, list[bytes]]:
    """The document at ``path`` with every buffer and image copied into one binary chunk;
    FileFormatError (the reader's) for an accessor that cannot be read, as the copy carries
    accessors the job never reads (clips not played, unused data)."""
    gltf, buffers = read_document(path)
    for i in range(len(gltf.accessors or [])):
        read_accessor(path, gltf, buffers, i)
    blob = Blob(gltf)
    starts = [blob.append(bytes(b)) for b in buffers]
    for view in gltf.bufferViews:
        view.byteOffset = (view.byteOffset or 0) + starts[view.buffer]
        view.buffer = 0
    for i, image in enumerate(gltf.images or []):
        if image.uri is None:
            continue
        if image.uri.startswith("data:"):
            header, _, payload = image.uri.partition(",")
            try:
                data = base64.b64decode(payload, validate=True) if header.endswith(";base64") \
                    else urllib.parse.unquote_to_bytes(payload)
            except ValueError:
                raise FileFormatError(f"{path}: image {i} has a malformed data: URI") from None
            mime = header[5:].split(";")[0] or None
        else:
            try:
                data = (path.parent / urllib.parse.unquote(image.uri)).read_bytes()
            except OSError as exc:
                raise InputError(f"{path}: image {i}: cannot read {image.uri!r} ({exc.strerror})") from None
            mime = mimetypes.guess_type(image.uri)[0]
        image.mimeType = image.mimeType or mime or "image/png"
        image.bufferView, image.uri = blob.raw(data), None
    return gltf, blob, buffers


def check_readable_size(gltf: pygltflib.GLTF2, out) -> None:
    """InputError when the document has an array longer than a glTF nrpose reads holds
    (:data:`nrpose.io.gltf_schema.MAX_ITEMS`): nrpose writes nothing it cannot read back."""
    arrays = [(key, getattr(gltf, key)) for key in ("accessors", "animations", "bufferViews", "meshes", "nodes",
                                                   "materials", "images", "textures", "skins")]
    for a in gltf.animations or []:
        arrays += [("channels of an animation", a.channels), ("samplers of an animation", a.samplers)]
    for key, value in arrays:
        if value is not None and len(value) > MAX_ITEMS:
            raise InputError(f"{out}: would hold {len(value):,} {key}, more than a glTF file nrpose reads "
                             f"(at most {MAX_ITEMS:,}): write fewer frames or clips, or thin the source's")


def save_glb(gltf: pygltflib.GLTF2, blob: Blob, out: Path) -> int:
    """Write the document with ``blob`` as its binary chunk to ``out`` (atomically); its size in
    bytes. Written chunk by chunk: the blob's parts go to the file as they are, never joined into
    one copy (pygltflib's ``save_binary`` would join them, then copy every view again)."""
    check_readable_size(gltf, out)
    blob.pack()
    align = max(blob.align, gltf.required_alignment())
    tail = -blob.size % align
    gltf.buffers = [pygltflib.Buffer(byteLength=blob.size + tail)]
    text = gltf.gltf_to_json(separators=(",", ":"), indent=None).encode("utf-8")
    text += b" " * (-(12 + len(text)) % align)     # the binary chunk's data start aligned in the file
    size = 12 + 8 + len(text) + 8 + blob.size + tail
    with atomic_path(out) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<4sII", b"glTF", 2, size))
        f.write(struct.pack("<I4s", len(text), b"JSON"))
        f.write(text)
        f.write(struct.pack("<I4s", blob.size + tail, b"BIN\0"))
        for part in blob.parts:
            f.write(part)
        f.write(b"\0" * tail)
    return size


@dataclass
class BakeReport:
    """What :func:`write_animated_glb` wrote. target_bytes: bytes of all morph-target
    accessors; frames x vertices: the baked grid; quantized_frames: frames stored as
    normalised integers; unique_frames: frames with their own data (the rest reuse an
    identical frame's); max_error: largest position error after dequantisation, as a
    fraction of the rest bounding-box diagonal (float32 rounding for float frames)."""

    frames: int
    vertices: int
    target_bytes: int
    quantized_frames: int
    unique_frames: int
    max_error: float

    @property
    def bytes_per_frame_vertex(self) -> float:
        return self.target_bytes / (self.frames * self.vertices)


@dataclass
class _Primitive:
    """One posed primitive: its slice of the posed vertices and the source's data for it."""

    start: int
    rest: np.ndarray               # (N, 3) world rest positions
    faces: np.ndarray              # (M, 3) triangles
    bind: np.ndarray               # (N, 3) the source's own positions (its normals' space)
    normals: np.ndarray | None     # (N, 3) the source's NORMAL, or None
    tangents: np.ndarray | None    # (N, 4) the source's TANGENT, or None
    template: pygltflib.Primitive  # the primitive to copy (attributes other than geometry kept)


class _Node:
    """A posed node: its primitives, welded as one surface."""

    def __init__(self, name: str, prims: list[_Primitive], rotations=None):
        """rotations: as :func:`write_animated_glb`'s."""
        self.name, self.prims = name, prims
        sizes = [len(p.rest) for p in prims]
        self.cuts = np.cumsum([0] + sizes)
        faces = np.concatenate([p.faces + c for p, c in zip(prims, self.cuts)])
        bind = np.concatenate([p.bind for p in prims])
        self.surface = Surface(bind, faces, weld(bind))
        self.rotations = self.surface.rotations if rotations is None else rotations(self.surface)
        self.authored = np.concatenate([np.full(len(p.rest), p.normals is not None) for p in prims])
        self.source_normals = np.concatenate([p.normals if p.normals is not None else np.zeros((len(p.rest), 3))
                                              for p in prims])
        self.has_tangents = all(p.tangents is not None for p in prims)
        self.source_tangents = np.concatenate([p.tangents for p in prims]) if self.has_tangents else None

    def frames(self, batch: np.ndarray) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """Per frame of ``batch`` (B, N, 3) float64 positions of the node's vertices, normals (N, 3)
        and tangent directions (N, 3) or None: the source's own normals and tangents turned
        with their neighbourhood (the batch's rotations at once), smooth normals where the
        source has none."""
        turns = self.authored.any() or self.has_tangents
        normals = tangents = [None] * len(batch)
        if turns:
            R = self.rotations(batch)                   # (B, N, 3, 3): float32 from the device
            normals = _turn(R, self.source_normals)
            if self.has_tangents:
                tangents = _turn(R, self.source_tangents[:, :3])
        if turns and self.authored.all():               # every normal is the source's, turned
            return list(zip(normals, tangents))
        out = []
        for positions, turned, turned_tangents in zip(batch, normals, tangents):
            smooth = self.surface.smooth_normals(positions)
            if turns:
                smooth[self.authored] = turned[self.authored]
            out.append((smooth, turned_tangents))
        return out


def _turn(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R @ v`` per frame and row: R (B, N, 3, 3), v (N, 3); (B, N, 3) of R's dtype (one
    einsum over the batch: 1.7x faster than three whole-array products per frame, and numpy's
    batched 3 x 3 matmul costs several times more)."""
    return np.einsum("fnij,nj->fni", R, v.astype(R.dtype, copy=False))


def _posed_nodes(meshes, starts, source: Path | None, gltf, buffers, rotations=None) -> list[tuple[int | None, _Node]]:
    """(source node index or None, posed node) per node to write; rotations: as
    :func:`write_animated_glb`'s."""
    groups: dict = {}
    for k, ((name, V, F, src), start) in enumerate(zip(meshes, starts[:-1])):
        if source is None:
            groups[("mesh", k)] = (None, name, [_Primitive(int(start), V, F, V, None, None, None)])
            continue
        node, mesh, p = src
        template = gltf.meshes[mesh].primitives[p]
        attrs = template.attributes
        bind = read_accessor(source, gltf, buffers, attrs.POSITION)
        if len(bind) != len(V):
            raise NrposeError(f"{source}: mesh {mesh} primitive {p} changed since it was loaded")
        normals = read_accessor(source, gltf, buffers, attrs.NORMAL) if attrs.NORMAL is not None else None
        tangents = read_accessor(source, gltf, buffers, attrs.TANGENT) if attrs.TANGENT is not None else None
        if (normals is not None and normals.shape != (len(V), 3)) or \
                (tangents is not None and tangents.shape != (len(V), 4)):
            raise FileFormatError(f"{source}: mesh {mesh} primitive {p}: NORMAL must be VEC3 and TANGENT VEC4")
        entry = groups.setdefault(("node", node), (node, gltf.nodes[node].name or name, []))
        entry[2].append(_Primitive(int(start), V, F, bind, normals, tangents, template))
    return [(node, _Node(name, prims, rotations)) for node, name, prims in groups.values()]


class _TargetWriter:
    """Morph-target accessors of one posed node, frame by frame (see the module docstring)."""

    def __init__(self, blob: Blob, node: _Node, scale: float, quantize: bool):
        """scale: the node's uniform scale (quantized: the largest position delta, so that
        deltas / scale lie in [-1, 1]; else 1)."""
        self.blob, self.node, self.scale, self.quantize = blob, node, scale, quantize
        rest = np.concatenate([p.rest for p in node.prims])
        self.base_positions = (rest / scale).astype(np.float32)
        self._base = self.base_positions.astype(np.float64)     # what a player adds the deltas to
        self.base_normals, self.base_tangents = node.frames(rest[None])[0]
        self.seen: dict = {}
        self.target_bytes = self.quantized = self.unique = 0
        self.max_error = 0.0

    def _accessor(self, values: np.ndarray, dtype, minmax: bool) -> int:
        index = (self.blob.normalized_vec3(values, dtype, minmax) if dtype != np.float32 else
                 self.blob.add(values.astype(np.float32), "VEC3", _FLOAT, pygltflib.ARRAY_BUFFER, minmax=minmax))
        view = self.blob.gltf.bufferViews[self.blob.gltf.accessors[index].bufferView]
        self.target_bytes += view.byteLength
        return index

    def frames(self, batch: np.ndarray) -> list[list[dict]]:
        """Targets (one dict per primitive) of each posed frame of ``batch`` (B, N, 3) of the node."""
        return [self._frame(positions, normals, tangents)
                for positions, (normals, tangents) in zip(batch, self.node.frames(batch))]

    def _frame(self, positions: np.ndarray, normals: np.ndarray, tangents: np.ndarray | None) -> list[dict]:
        base = self._base
        d_pos = positions / self.scale - base
        if self.quantize:
            enc_pos = np.clip(np.round(d_pos * 32767), -32767, 32767).astype(np.int16)
            got = self.scale * (base + enc_pos / 32767.0)
            self.quantized += 1
        else:
            enc_pos = d_pos.astype(np.float32)
            got = self.scale * (base + enc_pos)
        self.max_error = max(self.max_error, float(np.abs(got - positions).max()))
        enc = {"POSITION": (enc_pos, None), "NORMAL": (normals, self.base_normals)}
        if tangents is not None:
            enc["TANGENT"] = (tangents, self.base_tangents)
        targets, fresh = [{} for _ in self.node.prims], False
        for k, (a, b) in enumerate(zip(self.node.cuts[:-1], self.node.cuts[1:])):
            for attr, (values, base) in enc.items():
                part = values[a:b] if base is None else _direction_delta(values[a:b], base[a:b], self.quantize)
                part = np.ascontiguousarray(part)      # hashed as it is, without a copy of its bytes
                key = (k, attr, part.dtype.str, hashlib.blake2b(part, digest_size=32).digest())
                if key not in self.seen:
                    fresh = True
                    self.seen[key] = self._accessor(part, part.dtype, attr == "POSITION")
                targets[k][attr] = self.seen[key]
        self.unique += fresh
        return targets


def _direction_delta(posed: np.ndarray, base: np.ndarray, quantize: bool) -> np.ndarray:
    """Morph delta (N, 3) of unit directions (normals, tangents): float32 ``posed - base``; or,
    quantized, normalised int8 (else int16) of ``a posed - base`` with the largest per-vertex
    ``a`` in (0, 1] that keeps it in [-1, 1] (clients normalise morphed directions, so only the
    direction of ``a posed`` counts), the first whose decoded directions are all within
    :data:`DIRECTION_BOUND` degrees (a direction turned past 90 degrees may need a small ``a``,
    which int8 resolves too coarsely); float32 if neither is."""
    if quantize:
        # slack of half an int8 step: np.clip absorbs it (and rounding noise near +-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(posed > 0, (1.004 + base) / posed, np.where(posed < 0, (base - 1.004) / posed, np.inf))
        target = np.minimum(room.min(axis=1), 1.0)[:, None] * posed
        moving = np.linalg.norm(posed, axis=1) > 0.5
        for dtype in (np.int8, np.int16):
            top = np.iinfo(dtype).max
            q = np.clip(np.round((target - base) * top), -top, top).astype(dtype)
            decoded = base + q / top
            cosine = np.einsum("ij,ij->i", decoded, posed) / np.maximum(np.linalg.norm(decoded, axis=1), 1e-30)
            if (cosine[moving] >= np.cos(np.radians(DIRECTION_BOUND))).all():
                return q
    return (posed - base).astype(np.float32)


def _primitive(blob: Blob, template, base_positions, base_normals, base_tangents, targets,
               indices=None, material=None) -> pygltflib.Primitive:
    """A copy of ``template`` (None: a new triangle primitive) with the baked geometry."""
    attrs = {k: v for k, v in vars(template.attributes).items() if v is not None} if template else {}
    for k in list(attrs):
        if k.startswith(("JOINTS_", "WEIGHTS_")):
            del attrs[k]
    attrs["POSITION"] = blob.add(base_positions, "VEC3", _FLOAT, pygltflib.ARRAY_BUFFER, minmax=True)
    attrs["NORMAL"] = blob.add(base_normals.astype(np.float32), "VEC3", _FLOAT, pygltflib.ARRAY_BUFFER)
    if base_tangents is not None:
        attrs["TANGENT"] = blob.add(base_tangents.astype(np.float32), "VEC4", _FLOAT, pygltflib.ARRAY_BUFFER)
    if template is None:
        return pygltflib.Primitive(attributes=pygltflib.Attributes(**attrs), indices=indices, material=material,
                                   mode=pygltflib.TRIANGLES, targets=targets)
    extensions = {k: v for k, v in (template.extensions or {}).items() if k not in _GEOMETRY_EXTENSIONS}
    return pygltflib.Primitive(attributes=pygltflib.Attributes(**attrs), indices=template.indices,
                               material=template.material, mode=template.mode, targets=targets,
                               extensions=extensions, extras=template.extras)


def unique_name(name: str, taken: set) -> str:
    """``name``, or ``name.2``, ``name.3`` ... : the first not in ``taken`` (node names), which
    it joins."""
    candidate, k = name, 2
    while candidate in taken:
        candidate, k = f"{name}.{k}", k + 1
    taken.add(candidate)
    return candidate


def new_document() -> pygltflib.GLTF2:
    """An empty glTF document written by nrpose: one empty scene and material 0, a grey one."""
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator="nrpose", version="2.0"))
    gltf.scene, gltf.scenes = 0, [pygltflib.Scene(nodes=[])]
    gltf.materials = [pygltflib.Material(
        name="nrpose", doubleSided=True,
        pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(baseColorFactor=[0.62, 0.70, 0.86, 1.0],
                                                            metallicFactor=0.0, roughnessFactor=0.8))]
    return gltf


def write_animated_glb(path, character_or_meshes, positions, times, mesh_offsets: Sequence[int] | None = None,
                       *, animation_name: str = "baked", source=None, quantize: bool = False,
                       rotations=None) -> BakeReport:
    """Write the meshes with the posed frames baked as morph targets and one animation.

    character_or_meshes: a :class:`~nrpose.model.character.Character` (its
    ``meshes``), or a sequence of :class:`~nrpose.model.character.Mesh` or
    ``(vertices, faces)`` / ``(name, vertices, faces)``; their vertices are
    the rest geometry. positions: (F, V, 3) posed vertices of all meshes
    concatenated; times: (F,) seconds, non-negative, strictly increasing;
    mesh_offsets: start of each mesh in V (n starts, or n + 1 with the end;
    None: the meshes back to back from 0). source: the glTF file the meshes
    were loaded from (each Mesh's ``source`` indices refer to it): the output
    is a copy of it (module docstring); None: a new document, one node per
    mesh with a grey material. quantize: compact targets (module docstring).
    rotations: what turns the normals and tangents (module docstring), given a node's
    :class:`~nrpose.model.normals.Surface`, a callable posed (B, N, 3) -> rotations
    (B, N, 3, 3) (:class:`nrpose.pose.surface_rotations.SurfaceRotations` on the device);
    None: the float64 :meth:`Surface.rotations <nrpose.model.normals.Surface.rotations>`.
    Raises InputError on bad input, FileFormatError for a source that cannot
    be copied. Returns a :class:`BakeReport`.
    """
    meshes = _mesh_list(character_or_meshes)
    sizes = [len(m[1]) for m in meshes]
    P, T = _check(positions, times, sum(sizes) if mesh_offsets is None else 0)
    within_float32(P, "positions")
    starts = _offsets(mesh_offsets, sizes, P.shape[1])
    n_frames = len(T)
    if source is not None:
        source = Path(source)
        if any(m[3] is None for m in meshes):
            raise InputError("write_animated_glb: with source=, every mesh needs its source indices "
                             "(a Mesh loaded from that file)")
        gltf, blob, buffers = copy_document(source)
        _check_required(gltf, source)
        gltf.animations = []
    else:
        gltf, buffers = new_document(), []
        blob = Blob(gltf)
    rest_all = np.concatenate([m[1] for m in meshes])
    diagonal = float(np.linalg.norm(rest_all.max(axis=0) - rest_all.min(axis=0))) or 1.0

    input_acc = blob.add(T.astype(np.float32), "SCALAR", _FLOAT, minmax=True)
    animation = pygltflib.Animation(name=str(animation_name), channels=[], samplers=[])
    outputs: dict = {}
    report = BakeReport(n_frames, int(sum(sizes)), 0, 0, 0, 0.0)
    if not gltf.scenes:
        gltf.scenes, gltf.scene = [pygltflib.Scene(nodes=[])], 0
    scene = gltf.scenes[gltf.scene or 0]
    joints = {j for skin in gltf.skins or [] for j in skin.joints or []}
    for source_node, node in _posed_nodes(meshes, starts, source, gltf, buffers, rotations):
        def batches():
            for f in range(0, n_frames, FRAME_BATCH):
                yield np.concatenate([P[f:f + FRAME_BATCH, p.start:p.start + len(p.rest)] for p in node.prims],
                                     axis=1).astype(np.float64)
        reach = max(float(np.abs(P[f:f + FRAME_BATCH, p.start:p.start + len(p.rest)] - p.rest).max(initial=0.0))
                    for p in node.prims for f in range(0, n_frames, FRAME_BATCH))
        # int16 steps of reach / 32767 keep the error within the bound, or the positions stay float
        quantized = quantize and reach / 65534 <= 0.9 * QUANTIZATION_BOUND * diagonal
        scale = max(reach, 1e-30) if quantized else 1.0
        writer = _TargetWriter(blob, node, scale, quantized)
        targets = [[] for _ in node.prims]
        for batch in batches():
            for frame in writer.frames(batch):
                for k, t in enumerate(frame):
                    targets[k].append(t)
        report.target_bytes += writer.target_bytes
        report.quantized_frames = max(report.quantized_frames, writer.quantized)
        report.unique_frames = max(report.unique_frames, writer.unique)
        report.max_error = max(report.max_error, writer.max_error / diagonal)
        prims = []
        for k, (p, a, b) in enumerate(zip(node.prims, node.cuts[:-1], node.cuts[1:])):
            tangents = None
            if writer.base_tangents is not None:
                tangents = np.c_[writer.base_tangents[a:b], p.tangents[:, 3]]
            if p.template is None:
                idx = blob.add(p.faces.astype(np.uint32).reshape(-1), "SCALAR", _UINT, pygltflib.ELEMENT_ARRAY_BUFFER)
                prims.append(_primitive(blob, None, writer.base_positions[a:b], writer.base_normals[a:b], None,
                                        targets[k], idx, 0))
            else:
                prims.append(_primitive(blob, p.template, writer.base_positions[a:b], writer.base_normals[a:b],
                                        tangents, targets[k]))
        keys = np.eye(n_frames, dtype=np.float32)
        old = gltf.meshes[gltf.nodes[source_node].mesh] if source_node is not None else None
        gltf.meshes.append(pygltflib.Mesh(
            name=(old.name if old is not None else node.name), primitives=prims, weights=keys[0].tolist(),
            extras={**(old.extras or {} if old is not None else {}),
                    "targetNames": [f"frame{f}" for f in range(n_frames)]}))
        name = node.name
        if source_node is not None:
            kept = gltf.nodes[source_node]
            kept.mesh = kept.skin = None
            if source_node in joints:
                name = unique_name(f"{node.name}.posed", {n.name for n in gltf.nodes})
            else:
                kept.name = unique_name(f"{node.name}.bind", {n.name for n in gltf.nodes})
        gltf.nodes.append(pygltflib.Node(name=name, mesh=len(gltf.meshes) - 1,
                                         scale=[scale] * 3 if scale != 1.0 else None))
        scene.nodes = list(scene.nodes or []) + [len(gltf.nodes) - 1]
        key = keys.tobytes()
        if key not in outputs:
            outputs[key] = blob.add(keys.reshape(-1), "SCALAR", _FLOAT)
        add_channel(animation, len(gltf.nodes) - 1, "weights", input_acc, outputs[key])
    if report.quantized_frames:
        for field in ("extensionsUsed", "extensionsRequired"):
            names = list(getattr(gltf, field) or [])
            if QUANTIZATION not in names:
                setattr(gltf, field, names + [QUANTIZATION])
    gltf.animations = [animation]
    save_glb(gltf, blob, Path(path))
    return report


def write_glb_with_clip(target_path, out_path, target, clip, bounds=None, *, keep_animations: bool = True) -> str:
    """Write the target glTF plus ``clip`` (a Clip of its skeleton) as a new animation, as a GLB.

    Returns the animation's name. Every track of the clip becomes a channel on
    its joint's node (float32, the track's times and interpolation; CUBICSPLINE
    is not written). bounds: optional world-space box (min (3,), max (3,)) the
    animated geometry stays in: each skinned mesh node is then placed
    (:func:`fit_skinned_nodes`) so that viewers' culling bounds hold it.
    keep_animations=False: the clip is the file's only animation; else the target's clips are
    made first (FileFormatError for a malformed one, which the output would carry).
    """
    if keep_animations:
        tuple(target.clips)     # clips are decoded on first use: the kept ones must read back
    path = Path(target_path)
    gltf, blob, buffers = copy_document(path)
    skeleton, nodes = joint_nodes(path, gltf, buffers)
    if tuple(skeleton.names) != tuple(target.skeleton.names):
        raise NrposeError(f"{path}: its skeleton changed since it was loaded")
    if bounds is not None:
        fit_skinned_nodes(path, gltf, bounds)
    if not keep_animations:
        gltf.animations = []
    name = add_clip(gltf, blob, nodes, target.skeleton, clip)
    save_glb(gltf, blob, Path(out_path))
    return name


def add_clip(gltf: pygltflib.GLTF2, blob: Blob, nodes, skeleton, clip) -> str:
    """Append ``clip`` (a Clip of ``skeleton``, whose joint j is node ``nodes[j]``) to the document
    as a new animation (data in ``blob``); its name (made unique among the document's)."""
    taken = {a.name for a in gltf.animations or []}
    name, k = clip.name, 2
    while name in taken:
        name, k = f"{clip.name} ({k})", k + 1
    animation = pygltflib.Animation(name=name, channels=[], samplers=[])
    inputs = {}
    for j in sorted({t.joint for t in clip.tracks}):
        node = gltf.nodes[int(nodes[j])]
        if node.matrix is not None:     # animated nodes must use TRS (glTF 2.0, 5.25)
            node.matrix = None
            node.translation, node.rotation, node.scale = (skeleton.translation[j].tolist(),
                                                           skeleton.rotation[j].tolist(),
                                                           skeleton.scale[j].tolist())
    for track in clip.tracks:
        if track.interpolation == "CUBICSPLINE":
            raise InputError("write_glb_with_clip writes LINEAR and STEP tracks only")
        within_float32(track.values, f"retargeted {track.path} track of joint {track.joint}")
        if track.path == "translation":     # what nrpose's reader takes back (nrpose.io's clip check)
            check_magnitude(track.values,
                            f"clip {clip.name!r}: translations of joint {skeleton.names[track.joint]!r}")
        key = track.times.tobytes()
        if key not in inputs:
            inputs[key] = blob.add(float32_times(track.times, f"clip {clip.name!r}"), "SCALAR", minmax=True)
        output = blob.add(track.values.astype(np.float32),
                          {"rotation": "VEC4", "translation": "VEC3", "scale": "VEC3"}[track.path])
        add_channel(animation, int(nodes[track.joint]), track.path, inputs[key], output, track.interpolation)
    gltf.animations = list(gltf.animations or []) + [animation]
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
        box = [(a.min, a.max) for a in accessors if a.min and a.max]      # pygltflib's default is []
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
