"""Geometry files: meshes (OBJ, PLY, OFF, STL) and point clouds (PLY without faces, XYZ).

Contract (the CLI's INPUT / OUTPUT):

* :func:`read_geometry` returns a :class:`Geometry`: ``vertices`` (N, 3)
  float64 in **file order** (every vertex is kept, referenced or not, and no
  two are merged), ``faces`` (F, 3) int64, ``(0, 3)`` for a point cloud.
* Polygons (quads, n-gons) are **triangulated as fans** ``(v0, vi, vi+1)`` in
  file order, which adds no vertex (exact for convex polygons). Degenerate
  faces (a repeated index) are kept as they are.
* :func:`write_geometry` writes exactly the given vertices in the given order
  and the given triangles, through :func:`nrpose.io.files.atomic_path` (a temporary file in the
  target directory, then ``os.replace``: a failed write leaves no output and
  never a half-written one).

Formats, and what a round trip keeps:

========  =================================================================
``.obj``  ``v``/``f`` lines; ``vt``/``vn``/``l``/groups/materials ignored,
          ``f 1/2/3`` and negative (relative) indices understood. Written
          with shortest round-trip decimals: lossless.
``.ply``  ASCII and binary (both endiannesses), any property types, extra
          properties and elements skipped; ``vertex_indices`` (or
          ``vertex_index``) lists give the faces, no face element (or zero
          faces) gives a point cloud. Written binary little-endian with double
          coordinates: lossless.
``.off``  ASCII ``OFF`` with the optional ``ST``/``C``/``N`` prefixes; extra
          per-vertex and per-face values ignored. Written lossless.
``.stl``  ASCII or binary. STL has no vertex indices: each facet stores its
          three corners. Reading merges corners with bit-identical
          coordinates (``-0.0`` equals ``0.0``), numbering vertices in order
          of first appearance (facet order, then corner order); nothing else
          is merged. Written binary, float32 coordinates. A mesh round-trips
          exactly only if its vertices are float32 values, pairwise distinct,
          all used by a face and first used in index order; otherwise the
          read-back vertices are a reordering/subset: **STL cannot preserve
          vertex order**, use another format when order matters.
          A point cloud cannot be written as STL.
``.xyz``  Text, one point per line, whitespace (or comma) separated, first
          3 columns used, ``#`` starts a comment. Points only: writing a mesh
          with faces as ``.xyz`` is refused (it would drop the faces).
========  =================================================================

Why not pymeshlab / libigl for reading: on clean files pymeshlab keeps OBJ/PLY/OFF vertex order (and
merges STL corners in first-appearance order), but it silently **deletes
vertices with NaN/inf coordinates and renumbers the rest** (OBJ, PLY, OFF),
silently drops OBJ faces whose index is out of range and faces with a
repeated vertex index (all formats), and **aborts the
process** (heap corruption, SIGABRT at exit) after loading an OFF file with an
out-of-range face index. ``igl.read_triangle_mesh`` aborts (double free) on a
PLY whose vertex properties have mixed types (e.g. the point-cloud PLYs
pymeshlab writes), rejects ``NCOFF`` headers and does not merge STL corners.
So every format is parsed here with numpy, which makes the validation below
possible; pymeshlab is used by the tests to cross-check files both ways.

Every problem raises :class:`~nrpose.errors.FileFormatError` (reading, unknown
extension) or :class:`~nrpose.errors.InputError` (arrays given to the writer)
with a one-line message naming the file and the fix.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..checks import coordinates, real_rows, triangles, within_float32
from ..errors import FileFormatError, InputError
from .files import atomic_path, read_input

__all__ = ["Geometry", "read_geometry", "write_geometry", "SUFFIXES"]

SUFFIXES = (".obj", ".ply", ".off", ".stl", ".xyz")
_SUPPORTED = "use .obj, .ply, .off, .stl (meshes) or .ply, .xyz (point clouds)"


@dataclass(frozen=True)
class Geometry:
    """Vertices (N, 3) float64 in file order and triangles (F, 3) int64 ((0, 3): point cloud)."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def is_point_cloud(self) -> bool:
        return len(self.faces) == 0

    def __iter__(self):  # allows ``V, F = read_geometry(path)``
        return iter((self.vertices, self.faces))


# --------------------------------------------------------------------------- public API

def read_geometry(path) -> Geometry:
    """Read a mesh or point cloud; see the module docstring for formats and rules."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise FileFormatError(f"{path}: unknown geometry extension {suffix or '(none)'!r}; "
                              f"{_SUPPORTED}")
    data = read_input(path, f"{suffix} file")
    if not data.strip():
        raise FileFormatError(f"{path}: file is empty; give a {suffix} file with vertices")
    reader = {".obj": _read_obj, ".ply": _read_ply, ".off": _read_off,
              ".stl": _read_stl, ".xyz": _read_xyz}[suffix]
    try:
        V, F = reader(data)
    except _Bad as exc:
        raise FileFormatError(f"{path}: {exc}") from None
    except (ValueError, IndexError, OverflowError, struct.error, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{path}: corrupt or not a {suffix} file ({exc}); "
                              f"re-export it") from None
    return _check_read(path, V, F)


def write_geometry(path, vertices, faces=None) -> None:
    """Write vertices (N, 3) and optional triangles (F, 3) to ``path`` (format by extension).

    Vertices and faces are written exactly in the given order (STL: see the
    module docstring). The write is atomic (:func:`atomic_path`).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise FileFormatError(f"{path}: unknown geometry extension {suffix or '(none)'!r}; "
                              f"{_SUPPORTED}")
    V, F = _check_arrays(path, vertices, faces)
    if suffix == ".xyz" and len(F):
        raise InputError(f"{path}: .xyz stores points only and would drop the {len(F)} faces; "
                         f"write .ply, .obj or .off to keep them")
    if suffix == ".stl" and not len(F):
        raise InputError(f"{path}: STL stores triangles only, not a point cloud; "
                         f"write .ply or .xyz")
    if suffix == ".stl":
        within_float32(V, f"{path}: vertices")
    writer = {".obj": _write_obj, ".ply": _write_ply, ".off": _write_off,
              ".stl": _write_stl, ".xyz": _write_xyz}[suffix]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            writer(fh, V, F)


# --------------------------------------------------------------------------- validation

class _Bad(Exception):
    """A parse problem; read_geometry prefixes the file name."""


def _check_read(path: Path, V: np.ndarray, F: np.ndarray) -> Geometry:
    V = np.array(V, dtype=np.float64).reshape(-1, 3)
    F = np.array(F, dtype=np.int64).reshape(-1, 3)
    if len(V) == 0:
        raise FileFormatError(f"{path}: no vertices found; give a file with geometry")
    V = coordinates(V, f"{path}: vertices", error=FileFormatError, fix="fix or remove them")
    if len(F):
        F = triangles(F, len(V), f"{path}: faces", FileFormatError, "the file is inconsistent, re-export it")
    return Geometry(V, F)


def _check_arrays(path: Path, vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    try:
        V = real_rows(vertices, f"{path}: vertices")
        if faces is None or np.size(faces) == 0:
            return V, np.zeros((0, 3), np.int64)
        return V, triangles(faces, len(V), f"{path}: faces")
    except InputError as e:
        raise InputError(f"{e}; nothing written") from None


def _fan(polys: list[list[int]]) -> np.ndarray:
    """Triangulate polygons (lists of >= 3 indices) as fans; triangles pass through."""
    if all(len(p) == 3 for p in polys):
        return np.array(polys, dtype=np.int64).reshape(-1, 3)
    tris = []
    for p in polys:
        for i in range(1, len(p) - 1):
            tris.append((p[0], p[i], p[i + 1]))
    return np.array(tris, dtype=np.int64).reshape(-1, 3)


def _fan_block(block: np.ndarray) -> np.ndarray:
    """(M, k) polygons of one size k >= 3 -> (M (k-2), 3) fan triangles, polygon-major."""
    m, k = block.shape
    idx = np.arange(1, k - 1)
    tris = np.empty((m, k - 2, 3), np.int64)
    tris[:, :, 0] = block[:, :1]
    tris[:, :, 1] = block[:, idx]
    tris[:, :, 2] = block[:, idx + 1]
    return tris.reshape(-1, 3)


def _floats(tokens, what: str, per_row: int = 1) -> np.ndarray:
    """float64 array of text tokens (str or bytes; a flat list or rows of tokens).

    A bad token raises _Bad naming the row: ``{what} {i}`` where i counts
    rows, or flat tokens // per_row.
    """
    try:
        return np.array(tokens, dtype=np.float64)
    except ValueError:
        pass
    for i, row in enumerate(tokens):
        for t in (row if isinstance(row, (list, tuple)) else (row,)):
            t = t.decode("utf-8", "replace") if isinstance(t, bytes) else str(t)
            try:
                float(t)
            except ValueError:
                raise _Bad(f"{what} {i // per_row}: {t!r} is not a number; the file is "
                           f"corrupt") from None
    raise _Bad(f"{what} values are not numbers; the file is corrupt")


def _text(data: bytes) -> str:
    return data.decode("utf-8", errors="replace")


# --------------------------------------------------------------------------- OBJ

def _read_obj(data: bytes):
    text = _text(data).replace("\\\r\n", " ").replace("\\\n", " ")
    lines = text.splitlines()
    # Fast path (plain 'v x y z' and 'f a b c' lines, the common case): vectorised.
    vlines = [ln for ln in lines if ln[:2] in ("v ", "v\t")]
    flines = [ln for ln in lines if ln[:2] in ("f ", "f\t")]
    vtok = " ".join(vlines).split()
    ftext = " ".join(flines)
    if "/" in ftext:
        ftext = re.sub(r"/\S*", "", ftext)
    ftok = ftext.split()
    indented = any(ln[:1] in (" ", "\t") and ln.lstrip()[:1] in ("v", "f") for ln in lines)
    if (not indented and len(vtok) == 4 * len(vlines) and len(ftok) == 4 * len(flines) and "#" not in ftext
            and not any("#" in t for t in vtok[::4])):
        V = _floats(np.array(vtok, dtype=object).reshape(-1, 4)[:, 1:].tolist(), "vertex") \
            if vlines else np.zeros((0, 3))
        try:
            F = np.array(ftok, dtype=object).reshape(-1, 4)[:, 1:].astype(np.int64) \
                if flines else np.zeros((0, 3), np.int64)
        except ValueError:
            F = None
        if F is not None and np.all(F > 0):
            return V, F - 1
    return _read_obj_lines(lines)


def _read_obj_lines(lines: list[str]):
    """General OBJ parse, line by line (polygons, relative indices, comments)."""
    verts: list[list[str]] = []
    polys: list[list[int]] = []
    for lineno, line in enumerate(lines, 1):
        head = line.lstrip()[:1]
        if not head or head not in "vf":
            continue
        toks = line.split("#", 1)[0].split()
        if not toks:
            continue
        key = toks[0]
        if key == "v":
            if len(toks) < 4:
                raise _Bad(f"line {lineno}: a vertex needs 3 coordinates ({line.strip()!r})")
            verts.append(toks[1:4])
        elif key == "f":
            if len(toks) < 4:
                raise _Bad(f"line {lineno}: a face needs at least 3 vertices ({line.strip()!r})")
            n = len(verts)
            poly = []
            for t in toks[1:]:
                try:
                    i = int(t.split("/", 1)[0])
                except ValueError:
                    raise _Bad(f"line {lineno}: bad face index {t!r}") from None
                if i == 0:
                    raise _Bad(f"line {lineno}: face index 0 (OBJ indices start at 1)")
                poly.append(i - 1 if i > 0 else n + i)
            polys.append(poly)
    V = _floats(verts, "vertex") if verts else np.zeros((0, 3))
    return V, _fan(polys)


def _write_obj(fh, V, F):
    lines = ["# nrpose\n"]
    lines += [f"v {x!r} {y!r} {z!r}\n" for x, y, z in V.tolist()]
    lines += [f"f {a} {b} {c}\n" for a, b, c in (F + 1).tolist()]
    fh.write("".join(lines).encode())


# --------------------------------------------------------------------------- OFF

def _read_off(data: bytes):
    lines = []
    for line in _text(data).splitlines():
        toks = line.split("#", 1)[0].split()
        if toks:
            lines.append(toks)
    if not lines:
        raise _Bad("no OFF header")
    head = lines[0][0]
    m = re.fullmatch(r"(?:ST|C|N|4|n)*OFF", head)
    if not m:
        raise _Bad(f"first word is {head!r}, not OFF; give an OFF file or fix the extension")
    if "4" in head or "n" in head:
        raise _Bad(f"{head}: only 3D OFF files are supported")
    rest = lines[0][1:]
    pos = 1
    if rest and rest[0].upper() == "BINARY":
        raise _Bad("binary OFF is not supported; save it as ASCII OFF or PLY")
    if not rest:
        if len(lines) < 2:
            raise _Bad("missing the vertex/face counts line after the header")
        rest, pos = lines[1], 2
    try:
        nv, nf = int(rest[0]), int(rest[1])
    except (ValueError, IndexError):
        raise _Bad(f"bad counts line {' '.join(rest)!r}; expected 'vertices faces edges'") from None
    if nv < 0 or nf < 0:
        raise _Bad("negative vertex or face count")
    if len(lines) < pos + nv + nf:
        raise _Bad(f"truncated: header announces {nv} vertices and {nf} faces, the file has "
                   f"{len(lines) - pos} data lines")
    vlines = lines[pos:pos + nv]
    if nv and all(len(t) == 3 for t in vlines):              # plain 'x y z' lines
        V = _floats(vlines, "vertex")
        flines = lines[pos + nv:pos + nv + nf]
        if all(len(t) == 4 and t[0] == "3" for t in flines):  # plain triangles
            try:
                F = np.array(flines, dtype=np.int64).reshape(-1, 4)[:, 1:]
            except ValueError:
                F = None
            if F is not None:
                return V, F
    short = [i for i, t in enumerate(vlines) if len(t) < 3]
    if short:
        raise _Bad(f"vertex {short[0]} has fewer than 3 coordinates")
    V = _floats([t[:3] for t in vlines], "vertex") if nv else np.zeros((0, 3))
    polys = []
    for j, t in enumerate(lines[pos + nv:pos + nv + nf]):
        try:
            k = int(t[0])
            idx = [int(x) for x in t[1:1 + k]]
        except ValueError:
            raise _Bad(f"face {j}: bad line {' '.join(t)!r}") from None
        if k < 3 or len(idx) < k:
            raise _Bad(f"face {j}: needs at least 3 vertex indices ({' '.join(t)!r})")
        polys.append(idx)
    return V, _fan(polys)


def _write_off(fh, V, F):
    lines = [f"OFF\n{len(V)} {len(F)} 0\n"]
    lines += [f"{x!r} {y!r} {z!r}\n" for x, y, z in V.tolist()]
    lines += [f"3 {a} {b} {c}\n" for a, b, c in F.tolist()]
    fh.write("".join(lines).encode())


# --------------------------------------------------------------------------- PLY

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
              "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
              "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _ply_type(name: str) -> str:
    try:
        return _PLY_TYPES[name]
    except KeyError:
        raise _Bad(f"unknown PLY property type {name!r}") from None


def _read_ply(data: bytes):
    end = re.search(rb"end_header[ \t]*\r?\n", data)
    if not data.startswith(b"ply") or end is None:
        raise _Bad("not a PLY file (no 'ply' magic or no 'end_header'); re-export it")
    header = data[:end.start()].decode("ascii", errors="replace").splitlines()
    body_start = end.end()
    fmt = None
    elements: list[tuple[str, int, list]] = []   # (name, count, [(name, type) | (name, ctype, itype)])
    for line in header[1:]:
        toks = line.split()
        if not toks or toks[0] in ("comment", "obj_info"):
            continue
        if toks[0] == "format" and len(toks) >= 2:
            fmt = toks[1]
        elif toks[0] == "element" and len(toks) == 3:
            try:
                elements.append((toks[1], int(toks[2]), []))
            except ValueError:
                raise _Bad(f"bad header line {line!r}") from None
        elif toks[0] == "property" and elements:
            if len(toks) == 5 and toks[1] == "list":
                elements[-1][2].append((toks[4], _ply_type(toks[2]), _ply_type(toks[3])))
            elif len(toks) == 3:
                elements[-1][2].append((toks[2], _ply_type(toks[1])))
            else:
                raise _Bad(f"bad header line {line!r}")
        else:
            raise _Bad(f"bad header line {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise _Bad(f"unknown PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise _Bad("no 'vertex' element in the header")
    if any(e[0] == "tristrips" and e[1] > 0 for e in elements) and "face" not in names:
        raise _Bad("triangle strips are not supported; save the faces as a 'face' element")
    if fmt == "ascii":
        parse = _PlyAscii(data[body_start:])
    else:
        parse = _PlyBinary(data, body_start, "<" if fmt == "binary_little_endian" else ">")
    V = F = None
    for name, count, props in elements:
        if name == "vertex" and count == 0:
            V = np.zeros((0, 3))
        elif name == "vertex":
            cols = parse.element(name, count, props, want=("x", "y", "z"))
            missing = [c for c in "xyz" if c not in cols]
            if missing:
                raise _Bad(f"the vertex element has no {', '.join(missing)} property")
            V = np.column_stack([cols["x"], cols["y"], cols["z"]]).astype(np.float64)
        elif name == "face":
            key = next((p[0] for p in props if len(p) == 3
                        and p[0] in ("vertex_indices", "vertex_index")), None)
            if key is None and count:
                raise _Bad("the face element has no vertex_indices list")
            cols = parse.element(name, count, props, want=(key,))
            F = cols.get(key, np.zeros((0, 3), np.int64))
        else:
            parse.element(name, count, props, want=())
        if V is not None and F is not None:
            break   # later elements (edges, materials...) are not needed
    return V, (F if F is not None else np.zeros((0, 3), np.int64))


class _PlyAscii:
    def __init__(self, body: bytes):
        self.tok = body.split()
        self.pos = 0

    def _take(self, n: int, what: str):
        if self.pos + n > len(self.tok):
            raise _Bad(f"truncated: the {what} element needs more values than the file has")
        out = self.tok[self.pos:self.pos + n]
        self.pos += n
        return out

    def element(self, name, count, props, want):
        if count == 0:
            return {}
        lists = [i for i, p in enumerate(props) if len(p) == 3]
        if not lists:
            vals = _floats(self._take(count * len(props), name), name,
                           len(props)).reshape(count, len(props))
            return {p[0]: vals[:, i] for i, p in enumerate(props) if p[0] in want}
        # Uniform fast path: every list as long as in the first row.
        start = self.pos
        widths, lens, off = [], [], 0
        for p in props:
            if len(p) == 3:
                k = int(self.tok[start + off]) if start + off < len(self.tok) else 0
                lens.append(k)
                widths.append(1 + k)
                off += 1 + k
            else:
                widths.append(1)
                off += 1
        row = off
        if start + row * count <= len(self.tok):
            block = _floats(self.tok[start:start + row * count], name, row).reshape(count, row)
            edges = np.concatenate([[0], np.cumsum(widths)])
            ok = all(np.all(block[:, edges[i]] == lens[j]) for j, i in enumerate(lists))
            if ok:
                self.pos = start + row * count
                out = {}
                for i, p in enumerate(props):
                    if p[0] not in want:
                        continue
                    if len(p) == 3:
                        out[p[0]] = _poly_block(block[:, edges[i] + 1:edges[i + 1]], name)
                    else:
                        out[p[0]] = block[:, edges[i]]
                return out
        # General path: row by row.
        gathered = {p[0]: [] for p in props if p[0] in want}
        for _ in range(count):
            for p in props:
                if len(p) == 3:
                    k = _whole(self._take(1, name)[0], f"{name} list length")
                    vals = self._take(k, name)
                    if p[0] in gathered:
                        gathered[p[0]].append([_whole(v, f"{name} vertex index") for v in vals])
                else:
                    v = self._take(1, name)[0]
                    if p[0] in gathered:
                        gathered[p[0]].append(float(v))
        return {k: (_polys(v, name) if props_is_list(props, k) else np.array(v))
                for k, v in gathered.items()}


def props_is_list(props, key) -> bool:
    return any(p[0] == key and len(p) == 3 for p in props)


def _whole(token, what: str) -> int:
    """An ASCII PLY integer (written as 3 or 3.0); _Bad for 4.5."""
    value = float(token)
    if value != int(value):
        raise _Bad(f"{what} {token!r} is not a whole number")
    return int(value)


def _poly_block(block: np.ndarray, name: str) -> np.ndarray:
    if block.shape[1] < 3:
        raise _Bad(f"{name} lists need at least 3 vertex indices, found {block.shape[1]}")
    broken = np.flatnonzero(~(block == np.round(block)).all(axis=1))
    if len(broken):
        raise _Bad(f"{name} {int(broken[0])} has a vertex index that is not a whole number")
    return _fan_block(block.astype(np.int64))


def _polys(polys: list[list[int]], name: str) -> np.ndarray:
    short = [i for i, p in enumerate(polys) if len(p) < 3]
    if short:
        raise _Bad(f"{name} {short[0]} has fewer than 3 vertex indices")
    return _fan(polys)


class _PlyBinary:
    def __init__(self, data: bytes, pos: int, endian: str):
        self.data, self.pos, self.e = data, pos, endian

    def _need(self, n: int, name: str):
        if self.pos + n > len(self.data):
            raise _Bad(f"truncated: the {name} element needs {self.pos + n - len(self.data)} "
                       f"more bytes than the file has")

    def element(self, name, count, props, want):
        e = self.e
        if count == 0:
            return {}
        if not any(len(p) == 3 for p in props):
            dt = np.dtype([(f"p{i}", e + p[1]) for i, p in enumerate(props)])
            self._need(dt.itemsize * count, name)
            rec = np.frombuffer(self.data, dt, count, self.pos)
            self.pos += dt.itemsize * count
            return {p[0]: rec[f"p{i}"] for i, p in enumerate(props) if p[0] in want}
        # Uniform fast path: lists as long as in the first row.
        fields, off = [], self.pos
        for i, p in enumerate(props):
            if len(p) == 3:
                ct = np.dtype(e + p[1])
                self._need(off - self.pos + ct.itemsize, name)
                k = int(np.frombuffer(self.data, ct, 1, off)[0])
                fields.append((f"n{i}", ct))
                fields.append((f"p{i}", np.dtype(e + p[2]), (k,)))
                off += ct.itemsize + k * np.dtype(p[2]).itemsize
            else:
                fields.append((f"p{i}", np.dtype(e + p[1])))
                off += np.dtype(p[1]).itemsize
        dt = np.dtype(fields)
        if self.pos + dt.itemsize * count <= len(self.data):
            rec = np.frombuffer(self.data, dt, count, self.pos)
            ok = all(np.all(rec[f"n{i}"] == rec.dtype[f"p{i}"].shape[0])
                     for i, p in enumerate(props) if len(p) == 3)
            if ok:
                self.pos += dt.itemsize * count
                out = {}
                for i, p in enumerate(props):
                    if p[0] in want:
                        col = rec[f"p{i}"]
                        out[p[0]] = _poly_block(col.reshape(count, -1), name) if len(p) == 3 else col
                return out
        # General path: row by row.
        gathered = {p[0]: [] for p in props if p[0] in want}
        for _ in range(count):
            for p in props:
                if len(p) == 3:
                    ct, it = np.dtype(e + p[1]), np.dtype(e + p[2])
                    self._need(ct.itemsize, name)
                    k = int(np.frombuffer(self.data, ct, 1, self.pos)[0])
                    self.pos += ct.itemsize
                    self._need(k * it.itemsize, name)
                    vals = np.frombuffer(self.data, it, k, self.pos)
                    self.pos += k * it.itemsize
                    if p[0] in gathered:
                        gathered[p[0]].append(vals.astype(np.int64).tolist())
                else:
                    t = np.dtype(e + p[1])
                    self._need(t.itemsize, name)
                    v = np.frombuffer(self.data, t, 1, self.pos)[0]
                    self.pos += t.itemsize
                    if p[0] in gathered:
                        gathered[p[0]].append(float(v))
        return {k: (_polys(v, name) if props_is_list(props, k) else np.array(v))
                for k, v in gathered.items()}


def _write_ply(fh, V, F):
    head = ["ply", "format binary_little_endian 1.0", "comment nrpose",
            f"element vertex {len(V)}", "property double x", "property double y",
            "property double z"]
    if len(F):
        head += [f"element face {len(F)}", "property list uchar int vertex_indices"]
    head.append("end_header\n")
    fh.write("\n".join(head).encode("ascii"))
    fh.write(V.astype("<f8").tobytes())
    if len(F):
        if F.max() > np.iinfo(np.int32).max:
            raise InputError("more than 2^31 vertices cannot be indexed in PLY")
        rec = np.empty(len(F), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
        rec["n"] = 3
        rec["i"] = F
        fh.write(rec.tobytes())


# --------------------------------------------------------------------------- STL

_STL_BINARY = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def _read_stl(data: bytes):
    corners = None
    if len(data) >= 84:
        n = struct.unpack_from("<I", data, 80)[0]
        if len(data) == 84 + 50 * n:
            corners = np.frombuffer(data, _STL_BINARY, n, 84)["v"].reshape(-1, 3)
    if corners is None:
        if not data.lstrip()[:5].lower() == b"solid":
            raise _Bad("neither binary STL (size does not match the facet count) nor ASCII "
                       "STL (no 'solid'); re-export it")
        tok = np.array(data.lower().split())
        at = np.flatnonzero(tok == b"vertex")
        if len(at) == 0:
            raise _Bad("ASCII STL without any 'vertex' line")
        if len(at) % 3 or at[-1] + 3 >= len(tok):
            raise _Bad(f"ASCII STL has {len(at)} vertex lines, not 3 per facet; the file is "
                       f"truncated or corrupt")
        corners = _floats(tok[at[:, None] + np.arange(1, 4)].astype(str).tolist(), "corner")
    if len(corners) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    corners = corners.astype(np.float64)
    bad = ~np.isfinite(corners).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise _Bad(f"{int(bad.sum())} facet corners have NaN or infinite coordinates (first: "
                   f"facet {first // 3}); fix or remove them")
    corners = corners + 0.0                                   # -0.0 -> 0.0
    # Merge equal rows: a stable lexicographic sort puts equal corners next to
    # each other, the first of each run being the earliest in the file.
    order = np.lexsort(corners.T[::-1])
    srt = corners[order]
    starts = np.ones(len(srt), bool)
    starts[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    group = np.empty(len(srt), np.int64)
    group[order] = np.cumsum(starts) - 1                      # corner -> group
    first = order[starts]                                     # group -> earliest corner
    by_first = np.argsort(first, kind="stable")               # groups in first-appearance order
    rank = np.empty_like(by_first)
    rank[by_first] = np.arange(len(by_first))
    return corners[first[by_first]], rank[group].reshape(-1, 3)


def _write_stl(fh, V, F):
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    rec = np.zeros(len(F), _STL_BINARY)
    rec["normal"] = n
    rec["v"] = tri
    fh.write(b"nrpose binary STL".ljust(80, b" "))
    fh.write(struct.pack("<I", len(F)))
    fh.write(rec.tobytes())


# --------------------------------------------------------------------------- XYZ

def _read_xyz(data: bytes):
    rows = []
    for lineno, line in enumerate(_text(data).splitlines(), 1):
        toks = line.split("#", 1)[0].replace(",", " ").split()
        if not toks:
            continue
        if len(toks) < 3:
            raise _Bad(f"line {lineno}: a point needs 3 coordinates ({line.strip()!r})")
        rows.append(toks[:3])
    return (_floats(rows, "point") if rows else np.zeros((0, 3))), np.zeros((0, 3), np.int64)


def _write_xyz(fh, V, F):
    fh.write("".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in V.tolist()).encode())
