"""glTF 2.0 characters (``.glb`` and ``.gltf``): JSON and binary chunk read directly.

The JSON is parsed with :mod:`json` and checked field by field (:mod:`.gltf_schema`: types,
indices, enums, shapes); accessors are numpy views on the buffers' bytes, their sizes checked
against the bytes that exist before any array is made. pygltflib is used only by
:func:`read_document`, for the writers that edit a document.

What is read:

* Skeleton: the union of all skins' joints, in depth-first order of the node
  forest. A joint's parent is its nearest ancestor node that is a joint; the
  local transforms of non-joint nodes in between (or above a root joint, e.g.
  a Mixamo ``Armature`` with its rotation and 0.01 scale) go into the fixed
  ``Skeleton.pre`` matrix. Node ``matrix`` transforms are decomposed into TRS
  (FileFormatError if they shear). Unnamed nodes are called ``node<i>``;
  a repeated name gets ``.<i>`` appended.
* Inverse bind matrices: (J, 4, 4) per skeleton joint, from the first skin
  that lists the joint (identity when a skin has none, as the spec says).
* Meshes, one :class:`~nrpose.model.character.Mesh` per primitive (triangles,
  strips and fans) of the nodes of the default scene. Skinned primitives
  take every ``JOINTS_n``/``WEIGHTS_n`` set (n = 0, 1, ...), remapped to
  skeleton joints, rows normalised to sum 1; their rest vertices are the bind
  shape in world space, ``v_w = sum_i w_i (G[j_i] @ IBM[j_i]) @ v`` with the
  nodes' default transforms (the skinned mesh node's own transform is ignored,
  per the spec). A non-skinned mesh whose node is a joint or lies below one is
  rigid: world vertices ``G[node] @ v``, one influence of weight 1 on that
  joint. Meshes attached to no joint are scenery: kept as
  ``Character.static_meshes`` (world vertices ``G[node] @ v``, no weights),
  never posed. Each mesh records its ``source`` (node, mesh, primitive)
  indices. Morph targets, normals and texture coordinates are not read.
* Clips: every animation, channels on joints only (channels on other nodes
  and morph ``weights`` are ignored), samplers LINEAR / STEP / CUBICSPLINE. The
  animations' structure is checked at load; a clip's key times and values are read and
  checked when the clip is first used (:class:`~nrpose.model.character.Clips`), so a
  malformed clip raises its FileFormatError then, and a clip never used is never decoded.

Accessors honour ``byteStride``, normalised integers and sparse storage.
Every inconsistency raises FileFormatError naming the object at fault.
"""
from __future__ import annotations

import base64
import binascii
import dataclasses
import functools
import json
import struct
import typing
import urllib.parse
from pathlib import Path, PurePosixPath
from types import SimpleNamespace

import numpy as np

from ..errors import FileFormatError, InputError
from ..model.character import Character, Clip, Clips, Mesh, Track
from ..model.rotation import Rotation
from ..model.skeleton import LocalPose, Skeleton, local_matrices, polar_rotation
from .files import read_input
from .gltf_schema import COMPONENTS, UNIT_TOLERANCE, WIDTHS, decode
from .jsonfile import check_finite, parse_json

__all__ = ["load_gltf", "read_document", "read_accessor", "joint_nodes", "node_globals", "document_character"]

GLB_JSON, GLB_BIN = 0x4E4F534A, 0x004E4942
#: bytes an accessor without a bufferView (all zeros) may span beyond those of the buffers
ZERO_ACCESSOR_SLACK = 1 << 16


def _read_glb(path: Path, data: bytes) -> tuple[str, bytes | None]:
    """JSON text and BIN chunk of a binary glTF, validating the container."""
    if len(data) < 12:
        raise FileFormatError(f"{path}: truncated GLB ({len(data)} bytes, header needs 12)")
    magic, version, length = struct.unpack_from("<4sII", data)
    if magic != b"glTF":
        raise FileFormatError(f"{path}: not a binary glTF (magic {magic!r}, expected b'glTF')")
    if version != 2:
        raise FileFormatError(f"{path}: GLB version {version}; only glTF 2.0 is supported")
    if length != len(data):
        raise FileFormatError(f"{path}: {'truncated' if length > len(data) else 'corrupt'} GLB: "
                              f"header says {length} bytes, file has {len(data)}")
    chunks, offset = {}, 12
    while offset < length:
        if offset + 8 > length:
            raise FileFormatError(f"{path}: corrupt GLB: chunk header at byte {offset} runs past the end")
        size, kind = struct.unpack_from("<II", data, offset)
        if offset + 8 + size > length:
            raise FileFormatError(f"{path}: corrupt GLB: chunk at byte {offset} ({size} bytes) runs past the end")
        chunks.setdefault(kind, data[offset + 8: offset + 8 + size])
        offset += 8 + size
    if GLB_JSON not in chunks:
        raise FileFormatError(f"{path}: corrupt GLB: no JSON chunk")
    try:
        return chunks[GLB_JSON].decode("utf-8"), chunks.get(GLB_BIN)
    except UnicodeDecodeError:
        raise FileFormatError(f"{path}: corrupt GLB: JSON chunk is not UTF-8") from None


def _buffer_file(path: Path, i: int, uri: str) -> Path:
    """The file a buffer's relative URI names, inside the glTF's folder."""
    name = urllib.parse.unquote(uri)
    parts = urllib.parse.urlsplit(uri)
    pure = PurePosixPath(name)
    if parts.scheme or parts.netloc or not name or any(ord(ch) < 32 for ch in name) or "\\" in name \
            or pure.is_absolute() or ".." in pure.parts:
        raise FileFormatError(f"{path}: buffers[{i}].uri = {uri[:60]!r}: expected a data: URI or a file name "
                              "relative to the glTF's folder (no scheme, no '..', no control characters)")
    return path.parent.joinpath(*pure.parts)


def _buffer_bytes(path: Path, doc, blob: bytes | None) -> list[bytes]:
    """The bytes of each buffer of a decoded document, at least byteLength of them."""
    buffers = []
    for i, buf in enumerate(doc.buffers):
        if buf.uri is None:
            if blob is None:
                raise FileFormatError(f"{path}: buffer {i} has no uri and there is no GLB BIN chunk")
            content = blob
        elif buf.uri.startswith("data:"):
            header, comma, payload = buf.uri.partition(",")
            try:
                if not comma or not header.endswith(";base64"):
                    raise ValueError(header)
                content = base64.b64decode(payload, validate=True)
            except (ValueError, binascii.Error):
                raise FileFormatError(f"{path}: buffer {i} has a malformed data: URI (buffers[{i}].uri must be "
                                      "'data:<type>;base64,<base64 bytes>')") from None
        else:
            content = read_input(_buffer_file(path, i, buf.uri), f"buffer {i} of {path}")
        if len(content) < buf.byteLength:
            raise FileFormatError(f"{path}: buffer {i} holds {len(content)} bytes, "
                                  f"byteLength says {buf.byteLength}")
        buffers.append(content)
    return buffers


def _load(path: Path) -> tuple[str, SimpleNamespace, list[bytes]]:
    """JSON text, typed records (:func:`.gltf_schema.decode`) and buffer bytes of a glTF file."""
    data = read_input(path, f"{path.suffix} file")
    if path.suffix.lower() == ".glb":
        text, blob = _read_glb(path, data)
    else:
        try:
            text, blob = data.decode("utf-8"), None
        except UnicodeDecodeError:
            raise FileFormatError(f"{path}: a .gltf file must be UTF-8 JSON") from None
    root = parse_json(text, str(path), "the glTF JSON", finite=False)
    doc = decode(str(path), root)     # names a bad number in a field it reads; then any other
    check_finite(root, str(path))
    return text, doc, _buffer_bytes(path, doc, blob)


def read_document(path: Path):
    """The parsed glTF as a ``pygltflib.GLTF2`` (for writers that edit it) and the bytes of each
    of its buffers; the document passes every check of :func:`load_gltf`'s reading first."""
    import pygltflib  # writers only: the load path does not need it

    text, _, buffers = _load(path)
    try:
        gltf = _typed(json.loads(text), pygltflib.GLTF2)
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise FileFormatError(f"{path}: invalid glTF JSON ({exc})") from None
    return gltf, buffers


def _typed(value, hint):
    """``value`` (parsed JSON) as pygltflib's type ``hint`` builds it, without its per-object
    decoder (pygltflib.GLTF2.gltf_from_json spends ~0.4 ms an object: a minute for a document
    of 10,000 animations); keys a dataclass does not declare become attributes, as there."""
    kind, cls, arg = _plan(hint)
    if kind == "list":
        return [_typed(v, arg) for v in value] if isinstance(value, list) else value
    if kind == "dataclass" and isinstance(value, dict):
        fields = arg
        obj = cls(**{k: _typed(v, fields[k]) for k, v in value.items() if k in fields})
        for k, v in value.items():
            if k not in fields:
                setattr(obj, k, v)
        return obj
    if kind == "attributes" and isinstance(value, dict):
        return cls(**value)                          # pygltflib's own class for any attribute name
    if kind == "float" and type(value) is int:
        return float(value)
    return value


@functools.lru_cache(maxsize=None)
def _plan(hint) -> tuple:
    """How :func:`_typed` builds a value of type ``hint``: (kind, class, argument), Optional[X] as X."""
    if typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return _plan(args[0]) if len(args) == 1 else ("any", None, None)
    if typing.get_origin(hint) is list:
        return "list", None, typing.get_args(hint)[0]
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return "dataclass", hint, typing.get_type_hints(hint)
    if isinstance(hint, type) and hint.__name__ == "Attributes":
        return "attributes", hint, None
    return ("float" if hint is float else "any"), None, None


class _Accessors:
    """Reads accessors as (count, width) arrays: float64 if float or normalised, else int64.

    gltf: records from :func:`.gltf_schema.decode` (or a pygltflib document with the same
    names). Every size is checked against the bytes of the buffers before an array is made;
    each accessor is read once (results are shared, read-only).
    """

    def __init__(self, path: Path, gltf, buffers: list[bytes]):
        self.path, self.gltf, self.buffers = path, gltf, buffers
        self.read_so_far: dict[int, np.ndarray] = {}

    def _error(self, message: str) -> FileFormatError:
        return FileFormatError(f"{self.path}: {message}")

    def _view(self, index, offset, count, dtype, width, what):
        """Raw (count, width) array of ``dtype`` viewing buffer view ``index`` (no copy)."""
        views = self.gltf.bufferViews
        if type(index) is not int or not 0 <= index < len(views):
            raise self._error(f"{what}: bufferView {index} does not exist")
        view = views[index]
        if type(view.buffer) is not int or not 0 <= view.buffer < len(self.buffers):
            raise self._error(f"bufferView {index}: buffer {view.buffer} does not exist")
        start, length, offset = view.byteOffset or 0, view.byteLength, offset or 0
        if length is None:
            raise self._error(f"bufferView {index} has no byteLength (it is required)")
        if start < 0 or length < 0 or offset < 0 or count < 0 or (view.byteStride or 0) < 0:
            raise self._error(f"{what}: negative count, offset, length or stride in bufferView {index}")
        if start + length > len(self.buffers[view.buffer]):
            raise self._error(f"bufferView {index}: bytes {start}..{start + length} are beyond "
                              f"buffer {view.buffer} ({len(self.buffers[view.buffer])} bytes)")
        item = np.dtype(dtype).itemsize
        stride = view.byteStride or item * width
        if stride < item * width:
            raise self._error(f"{what}: bufferViews[{index}].byteStride = {stride} is shorter than one "
                              f"element ({item * width} bytes); the stride must hold a whole element")
        end = offset + stride * (count - 1) + item * width if count else 0
        if end > length:
            raise self._error(f"{what} is out of range: it reads up to byte {end} of bufferView "
                              f"{index}, which has {length} bytes")
        return np.ndarray((count, width), dtype=np.dtype(dtype).newbyteorder("<"),
                          buffer=self.buffers[view.buffer], offset=start + offset, strides=(stride, item))

    def read(self, index: int) -> np.ndarray:
        if index not in self.read_so_far:
            out = self._read(index)
            out.flags.writeable = False
            self.read_so_far[index] = out
        return self.read_so_far[index]

    def _read(self, index: int) -> np.ndarray:
        accessors = self.gltf.accessors
        if type(index) is not int or not 0 <= index < len(accessors):
            raise self._error(f"accessor {index} does not exist")
        acc = accessors[index]
        what = f"accessor {index}"
        if type(acc.count) is not int or acc.count < 0:
            raise self._error(f"{what}: count {acc.count} is not a non-negative integer")
        if acc.componentType not in COMPONENTS or acc.type not in WIDTHS:
            raise self._error(f"{what}: unsupported componentType {acc.componentType} / type {acc.type}")
        dtype, width = COMPONENTS[acc.componentType], WIDTHS[acc.type]
        if acc.type in ("MAT2", "MAT3") and np.dtype(dtype).itemsize < 4:
            raise self._error(f"{what}: padded {acc.type} of 8/16-bit components is not supported")
        if acc.bufferView is None:
            size, held = acc.count * width * np.dtype(dtype).itemsize, sum(len(b) for b in self.buffers)
            if size > held + ZERO_ACCESSOR_SLACK:
                raise self._error(f"accessors[{index}].count = {acc.count}: {size} bytes of zeros without a "
                                  f"bufferView, more than the file's buffers hold ({held} bytes); "
                                  "give the accessor a bufferView or a true count")
            out = np.zeros((acc.count, width), dtype=dtype)
        else:
            out = self._view(acc.bufferView, acc.byteOffset, acc.count, dtype, width, what)
        if acc.sparse is not None and acc.sparse.count:
            sp = acc.sparse
            if sp.indices.componentType not in (5121, 5123, 5125):
                raise self._error(f"{what}: sparse indices componentType {sp.indices.componentType} is invalid")
            idx = self._view(sp.indices.bufferView, sp.indices.byteOffset, sp.count,
                             COMPONENTS[sp.indices.componentType], 1, f"{what} sparse indices")[:, 0]
            if idx.size and idx.max() >= acc.count:
                raise self._error(f"{what}: sparse index {idx.max()} is out of range (count {acc.count})")
            if (np.diff(idx.astype(np.int64)) <= 0).any():
                raise self._error(f"accessors[{index}].sparse.indices: must increase strictly (each "
                                  "element is overridden once, in order)")
            out = out if out.flags.writeable else out.copy()
            out[idx.astype(np.int64)] = self._view(sp.values.bufferView, sp.values.byteOffset, sp.count,
                                                   dtype, width, f"{what} sparse values")
        if dtype == np.float32:
            out = out.astype(np.float64)
            if not np.isfinite(out).all():
                raise self._error(f"{what}: contains NaN or infinite values")
            return out
        if acc.normalized:
            info = np.iinfo(dtype)
            return np.maximum(out.astype(np.float64) / info.max, -1.0)
        return out.astype(np.int64)


def _trs(path: Path, index: int, node) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local translation (3,), rotation (4,) xyzw and scale (3,) of a node."""
    if node.matrix is not None:
        try:
            M = np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T
        except (TypeError, ValueError, OverflowError):
            M = None
        if M is None or not np.isfinite(M).all():
            raise FileFormatError(f"{path}: node {index} matrix: expected 16 finite numbers")
        R = polar_rotation(M[:3, :3])
        S = np.diag(R.T @ M[:3, :3])
        if not np.allclose(R * S, M[:3, :3], atol=1e-6 * max(np.abs(M[:3, :3]).max(), 1e-12)) \
                or not np.allclose(M[3], [0, 0, 0, 1]):
            raise FileFormatError(f"{path}: node {index} matrix is not a translation-rotation-scale")
        return M[:3, 3], Rotation.from_matrix(R).as_quat(), S
    t = np.asarray(node.translation if node.translation is not None else [0, 0, 0], dtype=np.float64)
    q = np.asarray(node.rotation if node.rotation is not None else [0, 0, 0, 1], dtype=np.float64)
    s = np.asarray(node.scale if node.scale is not None else [1, 1, 1], dtype=np.float64)
    if t.shape != (3,) or q.shape != (4,) or s.shape != (3,) or not np.isfinite(np.r_[t, q, s]).all() \
            or np.linalg.norm(q) < 1e-12:
        raise FileFormatError(f"{path}: node {index} has a malformed translation/rotation/scale")
    return t, q / np.linalg.norm(q), s


class _Nodes:
    """Node forest: parents (N,), depth-first order, local TRS and rest globals (N, 4, 4)."""

    def __init__(self, path: Path, gltf):
        n = len(gltf.nodes)
        self.parents = np.full(n, -1, np.int64)
        for i, node in enumerate(gltf.nodes):
            for c in node.children or []:
                if not 0 <= c < n or self.parents[c] >= 0 or c == i:
                    raise FileFormatError(f"{path}: node {i} lists child {c}, which does not exist "
                                          "or already has a parent")
                self.parents[c] = i
        order, stack = [], [int(i) for i in np.flatnonzero(self.parents < 0)[::-1]]
        while stack:
            i = stack.pop()
            order.append(i)
            stack.extend(reversed(gltf.nodes[i].children or []))
        if len(order) != n:
            raise FileFormatError(f"{path}: the node hierarchy contains a cycle")
        self.order = order
        trs = [_trs(path, i, node) for i, node in enumerate(gltf.nodes)]
        self.translation, self.rotation, self.scale = (np.array([x[k] for x in trs]) for k in range(3))
        self.local = local_matrices(self.translation, self.rotation, self.scale)
        self.globals = self.local.copy()
        for i in order:
            if self.parents[i] >= 0:
                self.globals[i] = self.globals[self.parents[i]] @ self.local[i]

    def ancestors(self, i: int):
        """Ancestors of node i, nearest first."""
        while self.parents[i] >= 0:
            i = int(self.parents[i])
            yield i


def _skin_binds(path: Path, gltf, acc: _Accessors) -> list[np.ndarray]:
    """Inverse bind matrices (Js, 4, 4) float64 of each skin, checked against its joints."""
    if not gltf.skins:
        raise FileFormatError(f"{path}: the glTF has no skin; a character needs a skinned skeleton")
    binds = []
    for s, skin in enumerate(gltf.skins):
        joints = np.asarray(skin.joints or [], dtype=np.int64)
        if joints.size == 0 or joints.min() < 0 or joints.max() >= len(gltf.nodes):
            raise FileFormatError(f"{path}: skin {s} has no joints or lists nodes that do not exist")
        if skin.inverseBindMatrices is None:
            binds.append(np.tile(np.eye(4), (len(joints), 1, 1)))
            continue
        raw = acc.read(skin.inverseBindMatrices)
        if raw.shape != (len(joints), 16) or raw.dtype.kind != "f":
            raise FileFormatError(f"{path}: skin {s} needs {len(joints)} float MAT4 inverse bind matrices, "
                                  f"accessor {skin.inverseBindMatrices} has {raw.shape[0]} of width {raw.shape[1]}")
        binds.append(raw.reshape(-1, 4, 4).transpose(0, 2, 1))
    return binds


def _skeleton(gltf, nodes: _Nodes, binds: list[np.ndarray]) -> tuple[Skeleton, np.ndarray, np.ndarray]:
    """Skeleton, node → joint map (N,) (-1 for non-joints) and inverse binds (J, 4, 4)."""
    is_joint = np.zeros(len(gltf.nodes), bool)
    ibm_of_node = {}
    for skin, ibms in zip(gltf.skins, binds):
        for node, ibm in zip(skin.joints, ibms):
            ibm_of_node.setdefault(node, ibm)
        is_joint[skin.joints] = True
    joint_nodes = [i for i in nodes.order if is_joint[i]]
    node_to_joint = np.full(len(gltf.nodes), -1, np.int64)
    node_to_joint[joint_nodes] = np.arange(len(joint_nodes))
    parents, pre = [], []
    for i in joint_nodes:
        between = []
        for a in nodes.ancestors(i):
            if is_joint[a]:
                break
            between.append(a)
        else:
            a = -1
        parents.append(int(node_to_joint[a]) if a >= 0 else -1)
        M = np.eye(4)
        for b in reversed(between):
            M = M @ nodes.local[b]
        pre.append(M)
    names, seen = [], set()
    for i in joint_nodes:
        name = gltf.nodes[i].name or f"node{i}"
        name = f"{name}.{i}" if name in seen else name
        seen.add(name)
        names.append(name)
    skeleton = Skeleton(names=tuple(names), parents=parents, translation=nodes.translation[joint_nodes],
                        rotation=nodes.rotation[joint_nodes], scale=nodes.scale[joint_nodes], pre=np.array(pre))
    return skeleton, node_to_joint, np.array([ibm_of_node[i] for i in joint_nodes])


def _triangles(path: Path, what: str, mode: int, idx: np.ndarray) -> np.ndarray:
    """(M, 3) int64 triangles from an index list of a TRIANGLES / STRIP / FAN primitive."""
    if mode == 4:
        if len(idx) % 3:
            raise FileFormatError(f"{path}: {what}: {len(idx)} indices is not a multiple of 3")
        return idx.reshape(-1, 3)
    if mode not in (5, 6):
        raise FileFormatError(f"{path}: {what}: primitive mode {mode} (points/lines) is not a surface")
    if len(idx) < 3:
        raise FileFormatError(f"{path}: {what}: a strip or fan needs at least 3 indices")
    k = np.arange(len(idx) - 2)
    if mode == 5:
        tri = np.stack([idx[k], idx[k + 1 + k % 2], idx[k + 2 - k % 2]], axis=1)
    else:
        tri = np.stack([np.full_like(k, idx[0]), idx[k + 1], idx[k + 2]], axis=1)
    return tri


def _influences(path, what, attrs, acc: _Accessors, n: int):
    """Skin-local joint indices (n, K) int64 and weights (n, K) float64 of all sets."""
    joints, weights, k = [], [], 0
    while getattr(attrs, f"JOINTS_{k}", None) is not None:
        j = acc.read(getattr(attrs, f"JOINTS_{k}"))
        if getattr(attrs, f"WEIGHTS_{k}", None) is None:
            raise FileFormatError(f"{path}: {what} has JOINTS_{k} without WEIGHTS_{k}")
        w = acc.read(getattr(attrs, f"WEIGHTS_{k}"))
        if j.dtype.kind == "f" or j.shape != (n, 4) or w.shape != (n, 4):
            raise FileFormatError(f"{path}: {what}: JOINTS_{k}/WEIGHTS_{k} must be {n} integer and {n} "
                                  f"numeric VEC4, got {j.shape} and {w.shape}")
        if w.dtype.kind != "f":  # integer weights without the normalized flag
            w = w / np.iinfo(COMPONENTS[acc.gltf.accessors[getattr(attrs, f'WEIGHTS_{k}')].componentType]).max
        joints.append(j)
        weights.append(w)
        k += 1
    if not joints:
        raise FileFormatError(f"{path}: {what} is skinned but has no JOINTS_0/WEIGHTS_0")
    return np.hstack(joints), np.hstack(weights)


def _meshes(path: Path, gltf, nodes: _Nodes, acc: _Accessors, binds: list[np.ndarray],
            node_to_joint: np.ndarray) -> tuple[list[Mesh], list[Mesh]]:
    """Posable and static meshes of the default scene (see the module docstring)."""
    if gltf.scenes:
        if not 0 <= (gltf.scene or 0) < len(gltf.scenes):
            raise FileFormatError(f"{path}: default scene {gltf.scene} does not exist")
        roots = set(gltf.scenes[gltf.scene or 0].nodes or [])
    else:
        roots = set(nodes.order)
    # per node, in depth-first order (parents first): in the scene, and the nearest joint at or above it
    parents, joint_of = nodes.parents.tolist(), node_to_joint.tolist()
    inside, nearest = [False] * len(parents), [-1] * len(parents)
    for i in nodes.order:
        p = parents[i]
        inside[i] = i in roots or (p >= 0 and inside[p])
        nearest[i] = joint_of[i] if joint_of[i] >= 0 else nearest[p] if p >= 0 else -1
    meshes, static = [], []
    for i in (i for i in nodes.order if inside[i]):
        node = gltf.nodes[i]
        if node.mesh is None:
            continue
        if not 0 <= node.mesh < len(gltf.meshes):
            raise FileFormatError(f"{path}: node {i} refers to mesh {node.mesh}, which does not exist")
        attach = nearest[i]
        gmesh = gltf.meshes[node.mesh]
        base = gmesh.name or node.name or f"mesh{node.mesh}"
        for p, prim in enumerate(gmesh.primitives):
            name = base if len(gmesh.primitives) == 1 else f"{base}.{p}"
            what = f"mesh {node.mesh} primitive {p}"
            if getattr(prim.attributes, "POSITION", None) is None:
                raise FileFormatError(f"{path}: {what} has no POSITION")
            V = acc.read(prim.attributes.POSITION)
            if V.shape[1] != 3 or V.dtype.kind != "f":
                raise FileFormatError(f"{path}: {what}: POSITION must be VEC3 numbers")
            idx = np.arange(len(V)) if prim.indices is None else acc.read(prim.indices)[:, 0]
            if idx.dtype.kind != "i":
                raise FileFormatError(f"{path}: {what}: indices must be unsigned integers")
            if idx.size and (idx.min() < 0 or idx.max() >= len(V)):
                raise FileFormatError(f"{path}: {what}: index {idx.max()} is out of range ({len(V)} vertices)")
            F = _triangles(path, what, 4 if prim.mode is None else prim.mode, idx.astype(np.int64))
            Vh = np.c_[V, np.ones(len(V))]
            source = (i, node.mesh, p)
            if node.skin is None:
                W = (Vh @ nodes.globals[i].T)[:, :3]
                if attach < 0:
                    static.append(Mesh(name, W, F, source=source))
                else:
                    meshes.append(Mesh(name, W, F, np.full((len(V), 1), attach), np.ones((len(V), 1)), attach,
                                       source=source))
                continue
            if not 0 <= node.skin < len(gltf.skins):
                raise FileFormatError(f"{path}: node {i} refers to skin {node.skin}, which does not exist")
            skin = gltf.skins[node.skin]
            local, weights = _influences(path, what, prim.attributes, acc, len(V))
            if local.min() < 0 or local.max() >= len(skin.joints):
                raise FileFormatError(f"{path}: {what}: joint index {local.max()} is out of range "
                                      f"(skin {node.skin} has {len(skin.joints)} joints)")
            sums = weights.sum(axis=1)
            if (weights < 0).any() or (sums <= 0).any():
                raise FileFormatError(f"{path}: {what}: vertex {int(np.argmin(sums))} has negative or all-zero weights")
            weights = weights / sums[:, None]
            bind = nodes.globals[skin.joints] @ binds[node.skin]  # (Js, 4, 4)
            blended = np.einsum("nk,nkab->nab", weights, bind[local])
            W = np.einsum("nab,nb->na", blended, Vh)[:, :3]
            joints = node_to_joint[np.asarray(skin.joints)][local]
            # this skin's inverse bind matrices, by skeleton joint (identity for joints it lacks)
            ibm = np.tile(np.eye(4), (int(node_to_joint.max()) + 1, 1, 1))
            ibm[node_to_joint[np.asarray(skin.joints)]] = binds[node.skin]
            meshes.append(Mesh(name, W, F, joints, weights, None, V.astype(np.float64), ibm, source))
    return meshes, static


def _clip_channels(path: Path, gltf, node_to_joint: np.ndarray) -> list[tuple[int, str, list[tuple]]]:
    """(animation index, clip name, channels) of each animation with a channel on a joint's
    translation / rotation / scale, each channel ``(c, joint, target path, sampler index)``:
    the structural checks of the animations, no accessor read."""
    clips = []
    for a, anim in enumerate(gltf.animations):
        channels = []
        for c, channel in enumerate(anim.channels):
            node, target = channel.target.node, channel.target.path
            if node is None or target not in ("translation", "rotation", "scale"):
                continue
            if not 0 <= node < len(node_to_joint):
                raise FileFormatError(f"{path}: animation {a} channel {c} targets node {node}, which does not exist")
            if node_to_joint[node] < 0:
                continue
            if not 0 <= channel.sampler < len(anim.samplers):
                raise FileFormatError(f"{path}: animation {a} channel {c}: sampler {channel.sampler} does not exist")
            channels.append((c, int(node_to_joint[node]), target, channel.sampler))
        if channels:
            clips.append((a, anim.name or f"animation{a}", channels))
    return clips


class _ClipReader:
    """Makes clip i of a document (``Clips``' ``make``): reads and checks the accessors of its
    channels (from :func:`_clip_channels`), tracks on joints only. Holds the document and its
    buffers' bytes until every clip is made."""

    def __init__(self, path: Path, gltf, buffers: list[bytes], clips: list[tuple], rest: LocalPose):
        self.path, self.gltf, self.buffers, self.clips, self.rest = path, gltf, buffers, clips, rest

    def __call__(self, i: int) -> Clip:
        path, (a, name, channels) = self.path, self.clips[i]
        acc, anim = _Accessors(path, self.gltf, self.buffers), self.gltf.animations[a]
        tracks = []
        for c, joint, target, s in channels:
            sampler = anim.samplers[s]
            mode = sampler.interpolation or "LINEAR"
            field = f"animations[{a}].samplers[{s}]"
            times = acc.read(sampler.input)
            if times.shape[1] != 1 or times.dtype.kind != "f":
                raise FileFormatError(f"{path}: {field}.input: key times must be a float SCALAR accessor, "
                                      f"accessor {sampler.input} is not")
            times = times[:, 0].astype(np.float64)
            values = acc.read(sampler.output).astype(np.float64)
            if mode == "CUBICSPLINE" and len(values) == 3 * len(times):
                values = values.reshape(len(times), 3, -1)
            if target == "rotation" and values.shape[-1] == 4:
                keys = values[:, 1] if values.ndim == 3 else values
                length = np.linalg.norm(keys / 2.0, axis=-1) * 2.0
                bad = np.flatnonzero(~(np.abs(length - 1.0) <= UNIT_TOLERANCE))
                if bad.size:
                    raise FileFormatError(f"{path}: {field}.output: rotation key {bad[0]} has length "
                                          f"{length[bad[0]]:.3g}; rotation keys must be unit quaternions")
            try:
                tracks.append(Track(joint, target, times, values, mode))
            except InputError as exc:
                raise FileFormatError(f"{path}: animation {a} channel {c}: {exc}") from None
        return Clip(name, max(float(t.times[-1]) for t in tracks), self.rest, tuple(tracks))


def read_accessor(path: Path, gltf, buffers: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index`` of a document from :func:`read_document` as (count, width): float64
    if float or normalised, else int64 (FileFormatError naming ``path`` when malformed)."""
    return _Accessors(path, gltf, buffers).read(index)


def joint_nodes(path: Path, gltf, buffers: list[bytes]) -> tuple[Skeleton, np.ndarray]:
    """The skeleton of a document from :func:`read_document` and the node index (J,) int64 of
    each of its joints, in :func:`load_gltf`'s joint order."""
    acc = _Accessors(path, gltf, buffers)
    skeleton, node_to_joint, _ = _skeleton(gltf, _Nodes(path, gltf), _skin_binds(path, gltf, acc))
    nodes = np.empty(skeleton.num_joints, np.int64)
    nodes[node_to_joint[node_to_joint >= 0]] = np.flatnonzero(node_to_joint >= 0)
    return skeleton, nodes


def clip_animations(path: Path, gltf, nodes: np.ndarray) -> list[int]:
    """The document's animation index of each clip :func:`load_gltf` makes from it, in order
    (animations without a channel on a joint make none); nodes: :func:`joint_nodes`' second value."""
    node_to_joint = np.full(len(gltf.nodes), -1, np.int64)
    node_to_joint[nodes] = np.arange(len(nodes))
    return [a for a, _, _ in _clip_channels(path, gltf, node_to_joint)]


def node_globals(path: Path, gltf) -> tuple[np.ndarray, np.ndarray]:
    """Parent (N,) int64 (-1 for roots) and rest world matrix (N, 4, 4) float64 of every node of a
    document from :func:`read_document`."""
    nodes = _Nodes(Path(path), gltf)
    return nodes.parents, nodes.globals


def load_gltf(path: str | Path) -> Character:
    """Character from a ``.glb`` or ``.gltf`` file (see the module docstring)."""
    path = Path(path)
    _, gltf, buffers = _load(path)
    return document_character(path, gltf, buffers)


def document_character(path: Path, gltf, buffers: list[bytes]) -> Character:
    """Character of a document: typed records of :func:`.gltf_schema.decode` (what
    :func:`load_gltf` reads) or a pygltflib document from :func:`read_document`; ``path``
    names the file in errors. The animations' structure is checked now; each clip's keys are
    read and checked when the clip is first asked for (:class:`~nrpose.model.character.Clips`),
    from the document and buffers given, which must not change afterwards."""
    acc = _Accessors(path, gltf, buffers)
    binds = _skin_binds(path, gltf, acc)
    nodes = _Nodes(path, gltf)
    skeleton, node_to_joint, inverse_bind = _skeleton(gltf, nodes, binds)
    meshes, static = _meshes(path, gltf, nodes, acc, binds, node_to_joint)
    plan = _clip_channels(path, gltf, node_to_joint)
    clips = Clips([name for _, name, _ in plan], _ClipReader(path, gltf, buffers, plan, skeleton.rest_pose))
    return Character(skeleton, tuple(meshes), clips, inverse_bind, tuple(static))
