"""glTF 2.0 JSON decoded into typed records, every field checked as the Khronos validator does.

:func:`decode` turns the parsed JSON of a glTF document into plain records whose attribute
names are pygltflib's (``gltf.nodes[i].children``, ``acc.sparse.indices.componentType``...),
absent optional fields being None (arrays: empty lists). Before a record exists, its fields
are checked: JSON type (an index is an int, never a bool, float or string), range (indices
inside their arrays, counts ≥ 1, offsets ≥ 0, byteStride a multiple of 4 in 4..252, at most
:data:`MAX_ITEMS` entries per array), enums (componentType, type, mode, interpolation, path),
shapes (node TRS and matrix, accessor min/max), finiteness and float32 range of node
transforms, unit rotation quaternions, unique skin joints and children. A violation raises
one FileFormatError naming the file and the field's JSON path, e.g.
``body.glb: accessors[3].count = true: expected an integer ≥ 1``.

Only the parts a character needs are decoded (asset, buffers, bufferViews, accessors, nodes,
meshes, skins, animations, scenes); cameras, materials and textures are passed over. Checks
that need the bytes of the buffers (accessors against their views) are the reader's.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from ..errors import FileFormatError

__all__ = ["COMPONENTS", "UNIT_TOLERANCE", "WIDTHS", "decode"]

COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
MODES = (0, 1, 2, 3, 4, 5, 6)
INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
#: animation target paths of the core spec, and KHR_animation_pointer's
PATHS = ("translation", "rotation", "scale", "weights", "pointer")
#: required extensions that change how mesh data is stored, which nrpose cannot decode
UNREADABLE = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")
#: most entries of one array of objects (accessors, nodes, channels...): a budget that keeps the
#: writers' pygltflib decoding of a document within seconds
MAX_ITEMS = 10_000
#: largest integer a glTF field may hold (JSON numbers are exact up to 2^53)
MAX_INT = 2 ** 53
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: a rotation quaternion's length may stray this far from 1 (it is normalised when read)
UNIT_TOLERANCE = 0.5


def _show(value) -> str:
    text = repr(value) if not isinstance(value, (dict, list)) else type(value).__name__
    return {"True": "true", "False": "false", "None": "null"}.get(text, text[:40])


class _Fields:
    """Typed reads of JSON fields; errors name the file and the field's JSON path."""

    def __init__(self, where: str, root: dict):
        self.where = where
        self.sizes = {key: len(root[key]) if isinstance(root.get(key), list) else 0
                      for key in ("accessors", "animations", "buffers", "bufferViews", "cameras",
                                  "meshes", "nodes", "scenes", "skins")}

    def error(self, field: str, value, expected: str) -> FileFormatError:
        return FileFormatError(f"{self.where}: {field} = {_show(value)}: expected {expected}")

    def missing(self, field: str, expected: str) -> FileFormatError:
        return FileFormatError(f"{self.where}: {field} is missing: it is required ({expected})")

    def objects(self, obj: dict, key: str, field: str, required: bool = False) -> list[dict]:
        """A list of JSON objects (empty if absent and not required)."""
        if key not in obj:
            if required:
                raise self.missing(field, "a non-empty array of objects")
            return []
        value = obj[key]
        if not isinstance(value, list) or (required and not value):
            raise self.error(field, value, "a non-empty array of objects" if required else "an array of objects")
        if len(value) > MAX_ITEMS:
            raise FileFormatError(f"{self.where}: {field} has {len(value)} entries, more than a character "
                                  f"file holds (at most {MAX_ITEMS}); is it the right file?")
        for i, item in enumerate(value):
            if not isinstance(item, dict):
                raise self.error(f"{field}[{i}]", item, "an object")
        return value

    def obj(self, obj: dict, key: str, field: str, required: bool = False) -> dict | None:
        if key not in obj:
            if required:
                raise self.missing(field, "an object")
            return None
        if not isinstance(obj[key], dict):
            raise self.error(field, obj[key], "an object")
        return obj[key]

    def integer(self, obj: dict, key: str, field: str, default=None, minimum: int = 0,
                required: bool = False, maximum: int = MAX_INT):
        if key not in obj:
            if required:
                raise self.missing(field, f"an integer ≥ {minimum}")
            return default
        value = obj[key]
        if type(value) is not int or not minimum <= value <= maximum:
            bound = f"in {minimum}..{maximum}" if maximum < MAX_INT else f"≥ {minimum}"
            raise self.error(field, value, f"an integer {bound}")
        return value

    def index(self, obj: dict, key: str, field: str, target: str, required: bool = False,
              size: int | None = None):
        """An index into the top-level array ``target`` (or into an array of ``size``)."""
        if key not in obj:
            if required:
                raise self.missing(field, f"an index into {target}")
            return None
        return self.check_index(obj[key], field, target, size)

    def check_index(self, value, field: str, target: str, size: int | None = None) -> int:
        n = self.sizes[target] if size is None else size
        if type(value) is not int or not 0 <= value < n:
            span = f"0..{n - 1}" if n else "there are none"
            raise self.error(field, value, f"an index into {target} ({span})")
        return value

    def indices(self, obj: dict, key: str, field: str, target: str, required: bool = False) -> list[int]:
        """A list of distinct indices into ``target`` (empty if absent and not required)."""
        if key not in obj:
            if required:
                raise self.missing(field, f"a non-empty array of indices into {target}")
            return []
        value = obj[key]
        if not isinstance(value, list) or (required and not value):
            raise self.error(field, value, f"an array of indices into {target}")
        out = [self.check_index(v, f"{field}[{i}]", target) for i, v in enumerate(value)]
        if len(set(out)) != len(out):
            first = next(i for i, v in enumerate(out) if out.index(v) != i)
            raise self.error(f"{field}[{first}]", out[first], "distinct indices (it is listed twice)")
        return out

    def enum(self, obj: dict, key: str, field: str, allowed, default=None, required: bool = False):
        if key not in obj:
            if required:
                raise self.missing(field, f"one of {', '.join(map(str, allowed))}")
            return default
        value = obj[key]
        if type(value) not in (int, str) or value not in allowed:
            raise self.error(field, value, f"one of {', '.join(map(str, allowed))}")
        return value

    def string(self, obj: dict, key: str, field: str):
        value = obj.get(key)
        if key in obj and not isinstance(value, str):
            raise self.error(field, value, "a string")
        return value

    def boolean(self, obj: dict, key: str, field: str, default: bool = False) -> bool:
        if key not in obj:
            return default
        if type(obj[key]) is not bool:
            raise self.error(field, obj[key], "true or false")
        return obj[key]

    def numbers(self, obj: dict, key: str, field: str, length: int | None = None) -> list | None:
        """A list of ``length`` finite JSON numbers within float32's range, or None if absent."""
        if key not in obj:
            return None
        value = obj[key]
        if not isinstance(value, list) or (length is not None and len(value) != length):
            raise self.error(field, value, f"an array of {length} numbers" if length else "an array of numbers")
        for i, v in enumerate(value):
            if type(v) not in (int, float) or not abs(v) <= FLOAT32_MAX:
                raise self.error(f"{field}[{i}]", v, "a finite number within float32's range (±3.4e38)")
        return value


def _asset(f: _Fields, root: dict) -> None:
    asset = f.obj(root, "asset", "asset")
    if asset is None:
        return
    version = f.string(asset, "version", "asset.version")
    if version is not None and version.split(".")[0] != "2":
        raise f.error("asset.version", version, "2.0 (only glTF 2.0 is supported)")
    required = root.get("extensionsRequired", [])
    if not isinstance(required, list) or not all(isinstance(e, str) for e in required):
        raise f.error("extensionsRequired", required, "an array of extension names")
    for i, name in enumerate(required):
        if name in UNREADABLE:
            raise FileFormatError(f"{f.where}: extensionsRequired[{i}] = {name!r}: nrpose cannot decode "
                                  "compressed meshes; export without mesh compression")


def _buffers(f: _Fields, root: dict) -> list:
    out = []
    for i, b in enumerate(f.objects(root, "buffers", "buffers")):
        field = f"buffers[{i}]"
        out.append(SimpleNamespace(uri=f.string(b, "uri", f"{field}.uri"),
                                   byteLength=f.integer(b, "byteLength", f"{field}.byteLength", minimum=1,
                                                        required=True)))
    return out


def _views(f: _Fields, root: dict, buffers: list) -> list:
    out = []
    for i, v in enumerate(f.objects(root, "bufferViews", "bufferViews")):
        field = f"bufferViews[{i}]"
        buffer = f.index(v, "buffer", f"{field}.buffer", "buffers", required=True)
        offset = f.integer(v, "byteOffset", f"{field}.byteOffset", default=0)
        length = f.integer(v, "byteLength", f"{field}.byteLength", minimum=1, required=True)
        stride = f.integer(v, "byteStride", f"{field}.byteStride", minimum=4, maximum=252)
        if stride is not None and stride % 4:
            raise f.error(f"{field}.byteStride", stride, "a multiple of 4 in 4..252")
        f.enum(v, "target", f"{field}.target", (34962, 34963))
        if offset + length > buffers[buffer].byteLength:
            raise FileFormatError(f"{f.where}: {field}: bytes {offset}..{offset + length} run past buffer "
                                  f"{buffer} ({buffers[buffer].byteLength} bytes by its byteLength)")
        out.append(SimpleNamespace(buffer=buffer, byteOffset=offset, byteLength=length, byteStride=stride))
    return out


def _sparse(f: _Fields, sparse: dict, field: str, count: int):
    n = f.integer(sparse, "count", f"{field}.count", minimum=1, maximum=count, required=True)
    idx = f.obj(sparse, "indices", f"{field}.indices", required=True)
    val = f.obj(sparse, "values", f"{field}.values", required=True)
    indices = SimpleNamespace(
        bufferView=f.index(idx, "bufferView", f"{field}.indices.bufferView", "bufferViews", required=True),
        byteOffset=f.integer(idx, "byteOffset", f"{field}.indices.byteOffset", default=0),
        componentType=f.enum(idx, "componentType", f"{field}.indices.componentType", (5121, 5123, 5125),
                             required=True))
    values = SimpleNamespace(
        bufferView=f.index(val, "bufferView", f"{field}.values.bufferView", "bufferViews", required=True),
        byteOffset=f.integer(val, "byteOffset", f"{field}.values.byteOffset", default=0))
    return SimpleNamespace(count=n, indices=indices, values=values)


def _accessors(f: _Fields, root: dict) -> list:
    out = []
    for i, a in enumerate(f.objects(root, "accessors", "accessors")):
        field = f"accessors[{i}]"
        ctype = f.enum(a, "componentType", f"{field}.componentType", tuple(COMPONENTS), required=True)
        kind = f.enum(a, "type", f"{field}.type", tuple(WIDTHS), required=True)
        count = f.integer(a, "count", f"{field}.count", minimum=1, required=True)
        normalized = f.boolean(a, "normalized", f"{field}.normalized")
        if normalized and ctype in (5125, 5126):
            raise f.error(f"{field}.normalized", True, "false for componentType 5125/5126 (only 8/16-bit "
                          "integers are normalised)")
        for key in ("min", "max"):
            f.numbers(a, key, f"{field}.{key}", WIDTHS[kind])
        sparse = f.obj(a, "sparse", f"{field}.sparse")
        out.append(SimpleNamespace(
            bufferView=f.index(a, "bufferView", f"{field}.bufferView", "bufferViews"),
            byteOffset=f.integer(a, "byteOffset", f"{field}.byteOffset", default=0),
            componentType=ctype, normalized=normalized, count=count, type=kind,
            sparse=None if sparse is None else _sparse(f, sparse, f"{field}.sparse", count)))
    return out


def _node(f: _Fields, n: dict, field: str):
    node = SimpleNamespace(
        name=f.string(n, "name", f"{field}.name"),
        children=f.indices(n, "children", f"{field}.children", "nodes"),
        mesh=f.index(n, "mesh", f"{field}.mesh", "meshes"),
        skin=f.index(n, "skin", f"{field}.skin", "skins"),
        camera=f.index(n, "camera", f"{field}.camera", "cameras"),
        matrix=f.numbers(n, "matrix", f"{field}.matrix", 16),
        translation=f.numbers(n, "translation", f"{field}.translation", 3),
        rotation=f.numbers(n, "rotation", f"{field}.rotation", 4),
        scale=f.numbers(n, "scale", f"{field}.scale", 3),
        weights=f.numbers(n, "weights", f"{field}.weights"))
    if node.matrix is not None and any(k in n for k in ("translation", "rotation", "scale")):
        raise FileFormatError(f"{f.where}: {field} has both a matrix and translation/rotation/scale; "
                              "a node holds one or the other")
    if node.rotation is not None:
        length = math.hypot(*node.rotation)
        if not abs(length - 1.0) <= UNIT_TOLERANCE:
            raise f.error(f"{field}.rotation", n["rotation"], f"a unit quaternion (x, y, z, w); its length "
                          f"is {length:.3g}")
    return node


def _meshes(f: _Fields, root: dict) -> list:
    out = []
    for m, mesh in enumerate(f.objects(root, "meshes", "meshes")):
        prims, seen = [], {}
        for p, prim in enumerate(f.objects(mesh, "primitives", f"meshes[{m}].primitives", required=True)):
            field = f"meshes[{m}].primitives[{p}]"
            attrs = f.obj(prim, "attributes", f"{field}.attributes", required=True)
            attributes = SimpleNamespace(**{name: f.check_index(v, f"{field}.attributes.{name}", "accessors")
                                            for name, v in attrs.items()})
            for t, target in enumerate(f.objects(prim, "targets", f"{field}.targets")):
                for name, v in target.items():
                    f.check_index(v, f"{field}.targets[{t}].{name}", "accessors")
            prims.append(SimpleNamespace(attributes=attributes,
                                         indices=f.index(prim, "indices", f"{field}.indices", "accessors"),
                                         mode=f.enum(prim, "mode", f"{field}.mode", MODES, default=4)))
            # the same geometry twice draws nothing new; 10,000 copies of it made a character
            # of 10,000 meshes from a few kilobytes
            key = (tuple(sorted(vars(attributes).items())), prims[-1].indices, prims[-1].mode)
            if key in seen:
                raise FileFormatError(f"{f.where}: {field} repeats meshes[{m}].primitives[{seen[key]}] (the "
                                      "same attributes, indices and mode)")
            seen[key] = p
        out.append(SimpleNamespace(name=f.string(mesh, "name", f"meshes[{m}].name"), primitives=prims))
    return out


def _skins(f: _Fields, root: dict) -> list:
    out = []
    for s, skin in enumerate(f.objects(root, "skins", "skins")):
        field = f"skins[{s}]"
        joints = skin.get("joints")
        for k, v in enumerate(joints if isinstance(joints, list) else []):   # f.indices names other types
            if type(v) is int and not 0 <= v < f.sizes["nodes"]:
                raise FileFormatError(f"{f.where}: {field}.joints[{k}] = {v}: skin {s} lists node {v}, "
                                      f"which does not exist ({f.sizes['nodes']} nodes)")
        out.append(SimpleNamespace(
            joints=f.indices(skin, "joints", f"{field}.joints", "nodes", required=True),
            inverseBindMatrices=f.index(skin, "inverseBindMatrices", f"{field}.inverseBindMatrices", "accessors"),
            skeleton=f.index(skin, "skeleton", f"{field}.skeleton", "nodes")))
    return out


def _animations(f: _Fields, root: dict) -> list:
    out = []
    for a, anim in enumerate(f.objects(root, "animations", "animations")):
        field = f"animations[{a}]"
        samplers = []
        for s, smp in enumerate(f.objects(anim, "samplers", f"{field}.samplers", required=True)):
            sf = f"{field}.samplers[{s}]"
            samplers.append(SimpleNamespace(
                input=f.index(smp, "input", f"{sf}.input", "accessors", required=True),
                output=f.index(smp, "output", f"{sf}.output", "accessors", required=True),
                interpolation=f.enum(smp, "interpolation", f"{sf}.interpolation", INTERPOLATIONS,
                                     default="LINEAR")))
        channels = []
        for c, ch in enumerate(f.objects(anim, "channels", f"{field}.channels", required=True)):
            cf = f"{field}.channels[{c}]"
            sampler = f.index(ch, "sampler", f"{cf}.sampler", "samplers", required=True, size=len(samplers))
            target = f.obj(ch, "target", f"{cf}.target", required=True)
            channels.append(SimpleNamespace(sampler=sampler, target=SimpleNamespace(
                node=f.index(target, "node", f"{cf}.target.node", "nodes"),
                path=f.enum(target, "path", f"{cf}.target.path", PATHS, required=True))))
        out.append(SimpleNamespace(name=f.string(anim, "name", f"{field}.name"), samplers=samplers,
                                   channels=channels))
    return out


def decode(where: str, root) -> SimpleNamespace:
    """Typed records of a parsed glTF JSON document (see the module docstring).

    where: the file's name for messages. Returns a record with ``buffers``, ``bufferViews``,
    ``accessors``, ``nodes``, ``meshes``, ``skins``, ``animations``, ``scenes`` (lists) and
    ``scene`` (int or None).
    """
    if not isinstance(root, dict):
        raise FileFormatError(f"{where}: the glTF JSON is {_show(root)}, not an object; is it a glTF file?")
    f = _Fields(where, root)
    _asset(f, root)
    buffers = _buffers(f, root)
    scenes = [SimpleNamespace(nodes=f.indices(s, "nodes", f"scenes[{i}].nodes", "nodes"))
              for i, s in enumerate(f.objects(root, "scenes", "scenes"))]
    return SimpleNamespace(
        buffers=buffers, bufferViews=_views(f, root, buffers), accessors=_accessors(f, root),
        nodes=[_node(f, n, f"nodes[{i}]") for i, n in enumerate(f.objects(root, "nodes", "nodes"))],
        meshes=_meshes(f, root), skins=_skins(f, root), animations=_animations(f, root),
        scenes=scenes, scene=f.index(root, "scene", "scene", "scenes"))
