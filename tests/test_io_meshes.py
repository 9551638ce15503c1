"""Geometry I/O: round trips keep vertex order and faces, point clouds, bad input, atomic writes."""
from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np
import pytest

from nrpose.io import meshes as meshio
from nrpose.errors import FileFormatError, InputError
from nrpose.io.files import atomic_path
from nrpose.io.meshes import Geometry, read_geometry, write_geometry

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BUNNY = DATA / "meshes" / "stanford-bunny.obj"
MESH_FORMATS = [".obj", ".ply", ".off"]          # lossless, any vertex order


# --------------------------------------------------------------------------- helpers

@pytest.fixture
def mesh():
    """Vertices out of spatial order, an unreferenced vertex (9), a duplicate
    position (7 == 2, must not be merged), a degenerate face, values that need
    17 significant digits."""
    rng = np.random.default_rng(0)
    V = rng.normal(size=(10, 3))
    V[7] = V[2]
    V[4] = [0.1, 1 / 3, -7.123456789012345e9]    # within checks.MAX_COORDINATE
    V[5] = [1e-300, 2.0000000000000004, -0.0]
    F = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 8], [1, 3, 5], [8, 8, 0]])
    return V, F


def files_in(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def write(path: Path, text) -> Path:
    if isinstance(text, str):
        text = text.encode()
    path.write_bytes(text)
    return path


def ply_header(fmt, nv, vprops=("float x", "float y", "float z"), nf=None,
               fprop="list uchar int vertex_indices"):
    lines = ["ply", f"format {fmt} 1.0", "comment test", f"element vertex {nv}"]
    lines += [f"property {p}" for p in vprops]
    if nf is not None:
        lines += [f"element face {nf}", f"property {fprop}"]
    return ("\n".join(lines) + "\nend_header\n").encode()


def one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


# --------------------------------------------------------------------------- round trips

@pytest.mark.parametrize("ext", MESH_FORMATS)
def test_mesh_round_trip_is_exact(tmp_path, mesh, ext):
    V, F = mesh
    p = tmp_path / f"m{ext}"
    write_geometry(p, V, F)
    g = read_geometry(p)
    assert isinstance(g, Geometry) and not g.is_point_cloud
    assert g.vertices.dtype == np.float64 and g.faces.dtype == np.int64
    np.testing.assert_array_equal(g.vertices, V)      # bit-exact, same order, nothing merged
    np.testing.assert_array_equal(g.faces, F)
    assert files_in(tmp_path) == [p.name]             # no temporary left behind
    V2, F2 = g                                        # unpacks like a tuple
    assert V2 is g.vertices and F2 is g.faces


@pytest.mark.parametrize("ext", [".ply", ".xyz", ".obj", ".off"])
def test_point_cloud_round_trip(tmp_path, mesh, ext):
    V, _ = mesh
    p = tmp_path / f"pc{ext}"
    write_geometry(p, V)
    g = read_geometry(p)
    assert g.is_point_cloud and g.faces.shape == (0, 3)
    np.testing.assert_array_equal(g.vertices, V)
    write_geometry(p, V, np.zeros((0, 3), int))       # empty faces = point cloud too
    assert read_geometry(p).is_point_cloud


def test_stl_round_trip_in_first_appearance_order(tmp_path):
    # float32-exact, distinct, all used, first used in index order: exact round trip
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.25, -2]], np.float64)
    F = np.array([[0, 1, 2], [0, 2, 3], [1, 3, 4], [4, 3, 2]])
    p = tmp_path / "m.stl"
    write_geometry(p, V, F)
    assert p.stat().st_size == 84 + 50 * len(F)      # binary STL
    g = read_geometry(p)
    np.testing.assert_array_equal(g.vertices, V)
    np.testing.assert_array_equal(g.faces, F)


def test_stl_general_mesh_keeps_geometry_not_order(tmp_path, mesh):
    V, F = mesh
    p = tmp_path / "m.stl"
    write_geometry(p, V, F)
    g = read_geometry(p)
    # same triangles (float32), corners merged by exact position, first appearance order
    np.testing.assert_array_equal(g.vertices[g.faces], V[F].astype(np.float32))
    used = V[F].astype(np.float32).reshape(-1, 3) + np.float32(0)
    _, first = np.unique(used, axis=0, return_index=True)
    np.testing.assert_array_equal(g.vertices, used[np.sort(first)])
    assert len(g.vertices) == 8       # vertex 9 unused, 7 merged into 2 (same position)


def test_ascii_stl_merges_corners_in_first_appearance_order(tmp_path):
    facets = [[(1, 1, 0), (1, 0, 0), (2, 0, 0)], [(0, 0, 0), (1, 0, 0), (1, 1, 0)],
              [(-0.0, 0, 0), (2, 0, 0), (1, 0, 0)]]
    text = "solid t\n" + "".join(
        "  facet normal 0 0 1\n    outer loop\n" + "".join(f"      vertex {x} {y} {z}\n" for x, y, z in f)
        + "    endloop\n  endfacet\n" for f in facets) + "endsolid t\n"
    g = read_geometry(write(tmp_path / "a.stl", text))
    np.testing.assert_array_equal(g.vertices, [[1, 1, 0], [1, 0, 0], [2, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(g.faces, [[0, 1, 2], [3, 1, 0], [3, 2, 1]])


def test_binary_stl_that_starts_with_solid(tmp_path):
    rec = np.zeros(1, meshio._STL_BINARY)
    rec["v"] = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    data = b"solid but binary".ljust(80) + struct.pack("<I", 1) + rec.tobytes()
    g = read_geometry(write(tmp_path / "b.stl", data))
    np.testing.assert_array_equal(g.faces, [[0, 1, 2]])


# --------------------------------------------------------------------------- OBJ / OFF / PLY details

def test_obj_corner_attributes_do_not_split_vertices(tmp_path, mesh):
    V, F = mesh
    lines = [f"v {x!r} {y!r} {z!r} 0.5 0.5 0.5" for x, y, z in V.tolist()]     # with vertex colours
    lines += [f"vt {u} 0.5" for u in np.linspace(0, 1, 3 * len(F))]
    lines += ["vn 0 0 1"] * (3 * len(F))
    lines += ["o thing", "g group", "usemtl m", "s 1"]
    k = 1
    for a, b, c in F + 1:
        lines.append(f"f {a}/{k}/{k} {b}/{k + 1}/{k + 1} {c}/{k + 2}/{k + 2}")
        k += 3
    lines.append("l 1 2")
    g = read_geometry(write(tmp_path / "a.obj", "\n".join(lines) + "\n"))
    np.testing.assert_array_equal(g.vertices, V)
    np.testing.assert_array_equal(g.faces, F)


def test_obj_polygons_relative_indices_comments(tmp_path):
    text = ("# header\nv 0 0 0\nv 1 0 0 # trailing comment\n  v 1 1 0\nv 0 1 0\n"
            "f 1 2 3 4\nv 2 0 0\n\tf -4 -1 -3   # relative to the 5 vertices so far\n"
            "f 1//1 3//1 4//1 \\\n 5//1\nv 9 9 9\n")
    g = read_geometry(write(tmp_path / "a.obj", text))
    np.testing.assert_array_equal(g.vertices[:5], [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]])
    assert len(g.vertices) == 6                        # the unreferenced last vertex is kept
    # quad and pentagon triangulated as fans (v0, vi, vi+1)
    np.testing.assert_array_equal(g.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2],
                                            [0, 2, 3], [0, 3, 4]])


def test_off_variants(tmp_path):
    text = ("NCOFF # normals and colours per vertex\n4 2 0\n"
            "0 0 0 0 0 1 255 0 0 255\n1 0 0 0 0 1 255 0 0 255\n"
            "1 1 0 0 0 1 255 0 0 255\n0 1 0 0 0 1 255 0 0 255\n"
            "4 0 1 2 3 10 20 30\n3 3 2 1\n")
    g = read_geometry(write(tmp_path / "a.off", text))
    np.testing.assert_array_equal(g.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    np.testing.assert_array_equal(g.faces, [[0, 1, 2], [0, 2, 3], [3, 2, 1]])
    g = read_geometry(write(tmp_path / "b.off", "OFF 3 0 0\n0 0 0\n1 0 0\n1 1 0\n"))
    assert g.is_point_cloud and len(g.vertices) == 3


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_point_cloud_with_extra_properties(tmp_path, fmt):
    V = np.random.default_rng(1).normal(size=(7, 3)).astype(np.float32)
    props = ("float x", "float y", "float z", "float nx", "float ny", "float nz",
             "uchar red", "uchar green", "uchar blue", "double quality")
    head = ply_header(fmt, len(V), props)
    if fmt == "ascii":
        body = "".join(f"{x!r} {y!r} {z!r} 0 0 1 10 20 30 0.5\n"
                       for x, y, z in V.astype(np.float64).tolist()).encode()
    else:
        e = "<" if fmt.endswith("little_endian") else ">"
        dt = np.dtype([("p", e + "f4", (6,)), ("c", "u1", (3,)), ("q", e + "f8")])
        rec = np.zeros(len(V), dt)
        rec["p"][:, :3] = V
        body = rec.tobytes()
    g = read_geometry(write(tmp_path / "pc.ply", head + body))
    assert g.is_point_cloud
    np.testing.assert_array_equal(g.vertices, V.astype(np.float64))


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("mixed", [False, True])
def test_ply_faces_quads_and_mixed_polygons(tmp_path, fmt, mixed):
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]], np.float32)
    polys = [[0, 1, 2, 3], [1, 4, 2, 0]] + ([[4, 2, 1]] if mixed else [])
    want = [[0, 1, 2], [0, 2, 3], [1, 4, 2], [1, 2, 0]] + ([[4, 2, 1]] if mixed else [])
    # extra elements before and after, an extra face property, a vertex list property
    head = ply_header(fmt, len(V), ("float x", "float y", "float z"), len(polys),
                      "list uchar int vertex_indices\nproperty uchar flags")
    head = head.replace(b"element vertex", b"element junk 2\nproperty short a\nelement vertex")
    head = head.replace(b"end_header", b"element edge 1\nproperty int v1\nproperty int v2\nend_header")
    if fmt == "ascii":
        body = "7\n8\n" + "".join(f"{x} {y} {z}\n" for x, y, z in V.tolist())
        body += "".join(f"{len(p)} {' '.join(map(str, p))} 1\n" for p in polys) + "0 1\n"
        body = body.encode()
    else:
        e = "<" if fmt.endswith("little_endian") else ">"
        body = np.array([7, 8], e + "i2").tobytes() + V.astype(e + "f4").tobytes()
        for p in polys:
            body += struct.pack("B", len(p)) + np.array(p, e + "i4").tobytes() + b"\x01"
        body += np.array([0, 1], e + "i4").tobytes()
    g = read_geometry(write(tmp_path / "q.ply", head + body))
    np.testing.assert_array_equal(g.vertices, V.astype(np.float64))
    np.testing.assert_array_equal(g.faces, want)


def test_xyz_comments_columns_commas(tmp_path):
    text = "# x y z r g b\n\n0 0 0 255 0 0\n1.5 -2 3e-3   # trailing\n  4,5,6\n7\t8\t9 1 2\n"
    g = read_geometry(write(tmp_path / "p.xyz", text))
    assert g.is_point_cloud
    np.testing.assert_array_equal(g.vertices, [[0, 0, 0], [1.5, -2, 3e-3], [4, 5, 6], [7, 8, 9]])


@pytest.mark.skipif(not BUNNY.is_file(), reason=f"shared data set not present ({BUNNY})")
def test_stanford_bunny():
    g = read_geometry(BUNNY)
    assert g.vertices.shape == (35947, 3)
    assert g.faces.shape == (69451, 3)
    # vertex order preserved: the file's first and last 'v' lines
    v_lines = [ln for ln in BUNNY.read_text().splitlines() if ln.startswith("v ")]
    np.testing.assert_array_equal(g.vertices[0], [float(t) for t in v_lines[0].split()[1:4]])
    np.testing.assert_array_equal(g.vertices[-1], [float(t) for t in v_lines[-1].split()[1:4]])
    assert g.faces.min() == 0 and g.faces.max() == 35946


# --------------------------------------------------------------------------- pymeshlab interop

@pytest.fixture
def clean_mesh(mesh):
    """``mesh`` without its degenerate face: pymeshlab deletes faces with a
    repeated vertex index on load (we keep them)."""
    V, F = mesh
    return V, F[:-1]


def _pml_load(path):
    pymeshlab = pytest.importorskip("pymeshlab")
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    m = ms.current_mesh()
    return m.vertex_matrix(), m.face_matrix()


@pytest.mark.parametrize("ext", MESH_FORMATS + [".stl"])
def test_pymeshlab_reads_what_we_write(tmp_path, clean_mesh, ext):
    V, F = clean_mesh
    p = tmp_path / f"m{ext}"
    write_geometry(p, V, F)
    ours = read_geometry(p)
    pv, pf = _pml_load(p)
    np.testing.assert_array_equal(pv, ours.vertices)
    np.testing.assert_array_equal(pf, ours.faces)


PML_SAVES = [(".obj", {}), (".off", {}), (".ply", {"binary": True}), (".ply", {"binary": False})]


@pytest.mark.parametrize("ext,kw,cloud", [(e, k, c) for e, k in PML_SAVES for c in (False, True)]
                         + [(".stl", {}, False)])
def test_we_read_what_pymeshlab_writes(tmp_path, clean_mesh, ext, kw, cloud):
    """pymeshlab's files carry normals, colours, quality (NCOFF, mixed-type PLY)."""
    pymeshlab = pytest.importorskip("pymeshlab")
    V, F = clean_mesh
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(V) if cloud else pymeshlab.Mesh(V, F))
    p = tmp_path / f"m{ext}"
    ms.save_current_mesh(str(p), **kw)
    g = read_geometry(p)
    pv, pf = _pml_load(p)
    np.testing.assert_array_equal(g.vertices, pv)
    np.testing.assert_array_equal(g.faces, pf.reshape(-1, 3))
    if ext != ".stl":
        np.testing.assert_allclose(g.vertices, V, rtol=1e-15, atol=1e-300)
        assert g.is_point_cloud == cloud


# --------------------------------------------------------------------------- bad input

def test_missing_unknown_empty(tmp_path):
    with pytest.raises(FileFormatError, match=r"nope\.obj: no such file") as e:
        read_geometry(tmp_path / "nope.obj")
    one_line(e)
    with pytest.raises(FileFormatError, match=r"unknown geometry extension '\.fbx'.*\.obj.*\.xyz"):
        read_geometry(write(tmp_path / "a.fbx", "x"))
    with pytest.raises(FileFormatError, match=r"extension '\(none\)'"):
        read_geometry(write(tmp_path / "noext", "x"))
    for ext in meshio.SUFFIXES:
        with pytest.raises(FileFormatError, match=rf"e{ext}: file is empty"):
            read_geometry(write(tmp_path / f"e{ext}", " \n"))
    with pytest.raises(FileFormatError, match="not a regular file"):
        read_geometry(tmp_path.joinpath("d.obj").mkdir() or tmp_path / "d.obj")
    with pytest.raises(FileFormatError, match="no vertices found"):
        read_geometry(write(tmp_path / "c.obj", "# only a comment\nvn 0 0 1\n"))
    with pytest.raises(FileFormatError, match="no vertices found"):
        read_geometry(write(tmp_path / "c.xyz", "# only a comment\n"))
    with pytest.raises(FileFormatError, match="no vertices found"):
        read_geometry(write(tmp_path / "z.ply", ply_header("ascii", 0)))


NAN_FILES = {
    "a.obj": "v 0 0 0\nv 1 nan 0\nv 1 1 0\nv inf 0 0\nf 1 2 3\n",
    "a.off": "OFF\n4 1 0\n0 0 0\n1 nan 0\n1 1 0\ninf 0 0\n3 0 1 2\n",
    "a.xyz": "0 0 0\n1 nan 0\n1 1 0\ninf 0 0\n",
    "a.ply": (ply_header("ascii", 4) + b"0 0 0\n1 nan 0\n1 1 0\ninf 0 0\n"),
    "b.ply": (ply_header("binary_little_endian", 4)
              + np.array([0, 0, 0, 1, np.nan, 0, 1, 1, 0, np.inf, 0, 0], "<f4").tobytes()),
}


@pytest.mark.parametrize("name", sorted(NAN_FILES))
def test_nan_and_inf_are_reported_with_count_and_first_index(tmp_path, name):
    with pytest.raises(FileFormatError, match=rf"{name}: vertices: 2 of 4 rows have NaN or infinite "
                                              r"values \(first: row 1\); fix or remove them") as e:
        read_geometry(write(tmp_path / name, NAN_FILES[name]))
    one_line(e)


def test_nan_in_stl_names_the_facet(tmp_path):
    rec = np.zeros(3, meshio._STL_BINARY)
    rec["v"] = np.arange(27).reshape(3, 3, 3)
    rec["v"][2, 1, 0] = np.nan
    data = b"x".ljust(80) + struct.pack("<I", 3) + rec.tobytes()
    with pytest.raises(FileFormatError, match=r"1 facet corners have NaN.*first: facet 2"):
        read_geometry(write(tmp_path / "n.stl", data))


OOR_FILES = {
    "a.obj": "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nf 1 2 9\nf 3 2 7\n",
    "r.obj": "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nf -1 -2 -4\nf -1 -2 -5\n",
    "a.off": "OFF\n3 3 0\n0 0 0\n1 0 0\n1 1 0\n3 0 1 2\n3 0 1 8\n3 -1 1 2\n",
    "a.ply": ply_header("ascii", 3, nf=3) + b"0 0 0\n1 0 0\n1 1 0\n3 0 1 2\n3 0 1 8\n3 0 1 3\n",
}


@pytest.mark.parametrize("name", sorted(OOR_FILES))
def test_faces_out_of_range(tmp_path, name):
    """pymeshlab drops such OBJ faces silently and aborts the process on such an OFF."""
    with pytest.raises(FileFormatError, match=rf"{name}: faces: 2 of 3 faces index vertices outside 0\.\.2 "
                                              r"\(first: face 1 = \[.*re-export it") as e:
        read_geometry(write(tmp_path / name, OOR_FILES[name]))
    one_line(e)


CORRUPT = {
    "g.obj": ("v 0 0 0\nv 1 zero 0\n", "vertex 1: 'zero' is not a number"),
    "h.obj": ("v 0 0\n", "line 1: a vertex needs 3 coordinates"),
    "i.obj": ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 x\n", "line 4: bad face index 'x'"),
    "j.obj": ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 0 1 2\n", "face index 0"),
    "k.obj": ("v 0 0 0\nv 1 0 0\nf 1 2\n", "at least 3 vertices"),
    "g.off": ("hello\n", "first word is 'hello', not OFF"),
    "h.off": ("OFF\n4 1 0\n0 0 0\n1 0 0\n", "truncated"),
    "i.off": ("OFF\nthree 1 0\n", "bad counts line"),
    "j.off": ("OFF BINARY\n", "binary OFF is not supported"),
    "k.off": ("4OFF\n1 0 0\n0 0 0 1\n", "only 3D"),
    "l.off": ("OFF\n3 1 0\n0 0 0\n1 0 0\n1 1 0\n2 0 1\n", "face 0: needs at least 3"),
    "g.ply": ("hello\n", "not a PLY file"),
    "h.ply": (ply_header("ascii", 5) + b"0 0 0\n1 0 0\n", "truncated"),
    "i.ply": (ply_header("binary_little_endian", 5) + bytes(20), "truncated.*more bytes"),
    "j.ply": (ply_header("binary_little_endian", 3, nf=2) + bytes(36) + b"\x03" + bytes(4),
              "truncated"),
    "k.ply": (ply_header("ascii", 1, ("float x", "float y")) + b"0 0\n", "no z property"),
    "l.ply": (ply_header("ascii", 1, ("float x", "float y", "quad z")) + b"0 0 0\n",
              "unknown PLY property type 'quad'"),
    "m.ply": (ply_header("ascii", 1).replace(b"ascii", b"binary_middle_endian") + b"0 0 0\n",
              "unknown PLY format"),
    "n.ply": (ply_header("ascii", 3, nf=1) + b"0 0 0\n1 0 0\n1 1 0\n2 0 1\n", "at least 3"),
    "o.ply": (ply_header("ascii", 2) + b"0 0 0\n1 x 0\n", "vertex 1: 'x' is not a number"),
    "j.stl": ("solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n"
              "vertex 1 1 a\nendloop\nendfacet\nendsolid\n", "corner 2: 'a' is not a number"),
    "g.stl": ("hello\n", "neither binary STL"),
    "h.stl": (b"x".ljust(80) + struct.pack("<I", 3) + bytes(60), "neither binary STL"),
    "i.stl": ("solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n",
              "not 3 per facet"),
    "g.xyz": ("0 0 0\n1 2\n", "line 2: a point needs 3 coordinates"),
    "h.xyz": ("0 0 0\n1 2 three\n", "point 1: 'three' is not a number"),
}


@pytest.mark.parametrize("name", sorted(CORRUPT))
def test_corrupt_files(tmp_path, name):
    text, match = CORRUPT[name]
    with pytest.raises(FileFormatError, match=rf"{name}: .*{match}") as e:
        read_geometry(write(tmp_path / name, text))
    one_line(e)


@pytest.mark.parametrize("args,match", [
    ((np.zeros((3, 2)),), r"shape \(N, 3\)"),
    ((np.zeros((0, 3)),), "vertices: empty"),
    ((np.array([[0, 0, 0], [np.nan, 0, 0], [1, np.inf, 0]]),),
     r"vertices: 2 of 3 rows have NaN or infinite values \(first: row 1\)"),
    ((np.eye(3), [[0, 1, 3]]), r"outside 0\.\.2 \(first: face 0"),
    ((np.eye(3), [[0, 1, 2, 0]]), r"triangles of shape \(F, 3\)"),
    ((np.eye(3), [[0.5, 1.0, 2.0]]), "not whole numbers .*; give integer indices; nothing written"),
    ((np.array([["a", "b", "c"]]),), "real numbers"),
])
@pytest.mark.parametrize("ext", [".obj", ".ply"])
def test_write_rejects_bad_arrays(tmp_path, args, match, ext):
    with pytest.raises(InputError, match=match):
        write_geometry(tmp_path / f"o{ext}", *args)
    assert files_in(tmp_path) == []


def test_write_refuses_lossy_or_unknown(tmp_path, mesh):
    V, F = mesh
    with pytest.raises(InputError, match=r"\.xyz stores points only and would drop the 6 faces"):
        write_geometry(tmp_path / "o.xyz", V, F)
    with pytest.raises(InputError, match="STL stores triangles only"):
        write_geometry(tmp_path / "o.stl", V)
    with pytest.raises(InputError, match=r"o\.stl: vertices: a value of magnitude 1e\+39 does not fit"):
        write_geometry(tmp_path / "o.stl", V * 0 + [[1e39, 0, 0]], F)     # float32 STL: inf
    with pytest.raises(FileFormatError, match=r"unknown geometry extension '\.fbx'"):
        write_geometry(tmp_path / "o.fbx", V, F)
    with pytest.raises(InputError, match="does not exist"):
        write_geometry(tmp_path / "missing" / "o.obj", V, F)
    assert files_in(tmp_path) == []


# --------------------------------------------------------------------------- atomic writes

def test_failed_write_leaves_no_file_and_keeps_the_old_one(tmp_path, mesh, monkeypatch):
    V, F = mesh

    def half_then_fail(fh, V, F):
        fh.write(b"v 0 0 0\n")
        raise OSError("disk full")

    monkeypatch.setitem(meshio.__dict__, "_write_obj", half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        write_geometry(tmp_path / "new.obj", V, F)
    assert files_in(tmp_path) == []                   # neither output nor temporary
    monkeypatch.undo()
    old = tmp_path / "old.obj"
    write_geometry(old, V, F)
    before = old.read_bytes()
    monkeypatch.setitem(meshio.__dict__, "_write_obj", half_then_fail)
    with pytest.raises(OSError):
        write_geometry(old, V[:3], F[:1])
    assert old.read_bytes() == before and files_in(tmp_path) == ["old.obj"]


def test_atomic_path(tmp_path):
    target = tmp_path / "out.npz"
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.endswith(".npz") and tmp != target
        assert not target.exists()
        np.savez(tmp, a=np.arange(3))
    np.testing.assert_array_equal(np.load(target)["a"], np.arange(3))
    assert files_in(tmp_path) == ["out.npz"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask
    # an exception inside the block: old content kept, temporary removed, error propagates
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise KeyboardInterrupt
    np.testing.assert_array_equal(np.load(target)["a"], np.arange(3))
    assert files_in(tmp_path) == ["out.npz"]
    # a writer that deletes its file: an error, nothing replaced
    with pytest.raises(InputError, match="produced no file"):
        with atomic_path(tmp_path / "x.json") as tmp:
            tmp.unlink()
    assert files_in(tmp_path) == ["out.npz"]
    with pytest.raises(InputError, match="is a directory"):
        with atomic_path(tmp_path):
            pass
