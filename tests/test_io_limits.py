"""Readers bounded before work: BVH nesting without recursion, DMAT sizes checked against the
file (no libigl allocation or print), libigl's geodesics kept from faces and meshes it cannot take,
coordinates bounded where they enter."""
from __future__ import annotations

import json

import igl
import numpy as np
import pytest

from nrpose.bind.distances import MAX_EDGE_SPREAD, clean_faces, distance_matrix, edge_spread
from nrpose.checks import MAX_COORDINATE, coordinates
from nrpose.errors import FileFormatError, HandleError, InputError
from nrpose.io import load_character
from nrpose.io.bvh_read import MAX_DEPTH, read_bvh
from nrpose.io.poses import load_handles
from nrpose.io.tgf import read_dmat_pose, read_tgf
from nrpose.native import quiet_native
from nrpose.rigs import cylinder


def _chain_bvh(depth: int, offset: str = "0 1 0", motion: str = "0 0 0") -> str:
    lines = ["HIERARCHY", "ROOT j0", "{", "OFFSET 0 0 0", "CHANNELS 3 Xposition Yposition Zposition"]
    for k in range(1, depth):
        lines += [f"JOINT j{k}", "{", f"OFFSET {offset}"]
    lines += ["End Site", "{", "OFFSET 0 1 0", "}"] + ["}"] * depth
    return "\n".join(lines + ["MOTION", "Frames: 1", "Frame Time: 0.1", motion]) + "\n"


def test_bvh_nesting_is_parsed_without_recursion(tmp_path):
    path = tmp_path / "chain.bvh"
    path.write_text(_chain_bvh(MAX_DEPTH))
    skeleton, _ = read_bvh(path)
    assert list(skeleton.parents) == [-1] + list(range(MAX_DEPTH - 1))
    assert np.allclose(skeleton.translation[1:], [0, 1, 0])
    for depth in (MAX_DEPTH + 1, 5000):          # 5,000: past Python's recursion limit
        path.write_text(_chain_bvh(depth))
        with pytest.raises(FileFormatError, match=f"nested more than {MAX_DEPTH} deep"):
            read_bvh(path)


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace("OFFSET 0 1 0", "OFFSET 0 1e300 0", 1), "exceeds the largest"),
    (lambda s: s.replace("\n0 0 0\n", "\n0 -1e308 0\n"), "Yposition of joint j0"),
    (lambda s: s.replace("}\nMOTION", "MOTION"), "unexpected end of file, expected '}'"),
])
def test_bvh_values_beyond_the_kernels_range_are_refused(tmp_path, edit, message):
    path = tmp_path / "chain.bvh"
    path.write_text(edit(_chain_bvh(4)))
    with pytest.raises(FileFormatError, match=message):
        read_bvh(path)


def _tgf(tmp_path, bones: int):
    lines = [f"{k + 1} {k} 0 0" for k in range(bones + 1)] + ["#"]
    lines += [f"{k + 1} {k + 2}" for k in range(bones)]
    path = tmp_path / "chain.tgf"
    path.write_text("\n".join(lines) + "\n")
    return read_tgf(path)


@pytest.mark.parametrize("ascii_", [True, False])
def test_dmat_reads_as_libigl_writes(tmp_path, ascii_):
    skeleton = _tgf(tmp_path, 3)
    rng = np.random.default_rng(3)
    q = rng.normal(size=(3, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    path = tmp_path / "pose.dmat"
    igl.writeDMAT(str(path), q.reshape(-1, 1), ascii_)
    pose = read_dmat_pose(path, skeleton)
    got = pose.rotation[[skeleton.index(f"bone{e}") for e in range(3)]]
    assert np.allclose(np.abs(np.sum(got * q, axis=1)), 1.0)


@pytest.mark.parametrize("data, message", [
    (b"2147483648 4\n1 2 3\n", "2147483648"),             # libigl: std::bad_alloc, abort
    (b"1 -3\n1 2 3\n", "not 'COLUMNS ROWS'"),             # libigl: prints, then aborts
    (b"0 0\n1 2147483648\n" + b"\0" * 16, "bytes"),       # binary: sizes vs bytes
    (b"1 12\n1 2 x 4\n", "12 x 1 values, the file holds 4"),
    (b"1 3\n1 2 \xc3\xa9\n", "not a number"),
    (b"", "not 'COLUMNS ROWS'"),
])
def test_dmat_headers_are_checked_before_allocation_and_print_nothing(tmp_path, capfd, data, message):
    skeleton = _tgf(tmp_path, 3)
    path = tmp_path / "pose.dmat"
    path.write_bytes(data)
    with pytest.raises(FileFormatError, match=message):
        read_dmat_pose(path, skeleton)
    assert capfd.readouterr() == ("", "")


def test_quiet_native_keeps_prints_off_the_streams(capfd):
    import os
    with quiet_native() as printed:
        os.write(1, b"native out\n")
        os.write(2, b"native err\n")
    assert capfd.readouterr() == ("", "") and printed == ["native out\nnative err"]


def _mesh():
    V, F = cylinder.cylinder_mesh(rings=6, sectors=8)
    return V, F, V[[0, len(V) // 2]] + [0.01, 0, 0]


def test_faces_libigl_crashes_on_are_dropped_before_it():
    V, F, P = _mesh()
    bad = np.vstack([F, F[:3], [[0, 0, 1]], F[5][::-1][None]])   # repeated, degenerate, flipped repeat
    assert np.array_equal(clean_faces(bad), F)
    for method in ("exact", "heat", "graph"):
        np.testing.assert_allclose(distance_matrix(V, bad, P, method=method),
                                   distance_matrix(V, F, P, method=method), rtol=1e-12, atol=1e-12)
    with pytest.raises(InputError, match="every face repeats a vertex"):
        distance_matrix(V, [[0, 0, 1], [2, 2, 2]], P, method="exact")


def test_stray_vertex_keeps_geodesics_from_libigl():
    V, F, P = _mesh()
    V = V.copy()
    V[3] = [0, 1e8, 0]
    assert edge_spread(V, F) > MAX_EDGE_SPREAD > edge_spread(*_mesh()[:2])
    with pytest.raises(InputError, match="the longest edge is"):
        distance_matrix(V, F, P, method="exact")
    with pytest.warns(RuntimeWarning, match="using graph distances"):
        D = distance_matrix(V, F, P, method="heat")
    np.testing.assert_allclose(D, distance_matrix(V, F, P, method="graph"))


def test_coordinates_are_bounded_where_they_enter(tmp_path):
    assert coordinates([[MAX_COORDINATE, 0, -MAX_COORDINATE]], "v").shape == (1, 3)
    with pytest.raises(InputError, match="exceeds the largest"):
        coordinates([[0, 0, 1.0001 * MAX_COORDINATE]], "v")
    h = tmp_path / "h.json"
    h.write_text(json.dumps({"points": [{"rest": [0, 0, 0], "pose": [1e20, 0, 0]}]}))
    with pytest.raises(HandleError, match="exceeds the largest"):
        load_handles(h)
    V, F, P = _mesh()
    with pytest.raises(InputError, match="exceeds the largest"):
        distance_matrix(V * 1e20, F, P, method="graph")
    path = tmp_path / "c.bvh"
    path.write_text(_chain_bvh(3, offset="0 1e11 0"))
    with pytest.raises(FileFormatError, match="exceeds the largest"):
        load_character(path)
