"""Topological weights end to end: the Figure-2 effect through the deformer, welding,
the binding cache through the character poser, and ``nrpose weights``.

Measured (this machine, PoCL, α = 1): finger A's bone bent 45° about its base,
largest displacement of finger B's tip as a fraction of the Euclidean-weight
result: heat 0.074, exact 0.075, graph 0.073; point cloud (kNN, k = 10) 0.074.
The issue's bound is 0.10.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

igl = pytest.importorskip("igl")

from nrpose import Deformer, HandleSet, Pose
from nrpose.bind import cache as bindcache  # noqa: E402
from nrpose.bind import distances as distances_mod  # noqa: E402
from nrpose.io import load_character  # noqa: E402
from nrpose.bind.distances import distance_matrix  # noqa: E402
from nrpose.io.meshes import write_geometry  # noqa: E402
from nrpose.pose.poser import BIND_CACHE_FOLDER, CharacterPoser  # noqa: E402
from nrpose.model.rotation import Rotation  # noqa: E402
from nrpose.rigs.fingers import fingers_shape  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
needs_data = pytest.mark.skipif(not (DATA / "gltf").is_dir(), reason=f"shared assets not found at {DATA}")
BOUND = 0.10


@pytest.fixture(scope="module")
def fingers():
    return fingers_shape()


def bend_finger_a(s, degrees=45.0):
    """Rest handles and a pose turning finger A's bone about its base (z axis)."""
    a = s.bone_names.index("finger_a")
    rest = HandleSet.make(segments=s.bones)
    R = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    segs = s.bones.copy()
    segs[a] = (segs[a] - segs[a, 0]) @ R.T + segs[a, 0]
    rots = np.stack([np.eye(3)] * len(s.bones))
    rots[a] = R
    return rest, Pose.make(rest, segments=segs, rotations=rots)


def tip_masks(s, V):
    """Vertices of finger A's and finger B's tip (the top 2 radii of each finger)."""
    top = V[:, 1] > s.finger_length - 2 * s.finger_radius
    return top & (V[:, 0] < -0.5 * s.finger_gap), top & (V[:, 0] > 0.5 * s.finger_gap)


def displacements(V, faces, s, method):
    rest, pose = bend_finger_a(s)
    D = distance_matrix(V, faces, None, s.bones, method=method)
    return np.linalg.norm(Deformer(V, rest, distances=D).pose(pose) - V, axis=1)


# ---------------------------------------------------------------------------
# Figure 2, measured through the deformer
# ---------------------------------------------------------------------------
def test_figure2_mesh_other_fingertip_stays(fingers):
    s = fingers
    V, F = s.vertices, s.faces
    assert s.finger_gap < s.finger_length  # the premise: spatially near, topologically far
    tip_a, tip_b = tip_masks(s, V)
    d_e = displacements(V, F, s, "euclidean")
    # the bent finger really moves, and Euclidean weights drag the other one along
    assert d_e[tip_a].max() > 1.0
    assert d_e[tip_b].max() > 0.1 * s.finger_length  # measured 0.293 (length 2.5)
    for method in ("heat", "graph"):
        d = displacements(V, F, s, method)
        assert d[tip_a].max() > 1.0, method
        ratio = d[tip_b].max() / d_e[tip_b].max()
        assert ratio <= BOUND, (method, ratio)  # measured heat 0.074, graph 0.073


def test_figure2_point_cloud_knn(fingers):
    s = fingers
    V = s.vertices  # vertices only: no faces
    tip_a, tip_b = tip_masks(s, V)
    d_e = displacements(V, None, s, "euclidean")
    d = displacements(V, None, s, "knn")
    assert d[tip_a].max() > 1.0
    ratio = d[tip_b].max() / d_e[tip_b].max()
    assert ratio <= BOUND, ratio  # measured 0.074


def test_triangle_soup_is_welded(fingers):
    """A glTF-style mesh split at every face (the Fox is one) gets the distances of
    the connected surface; without welding it falls back to near-Euclidean ones."""
    s = fingers
    Vs = s.vertices[s.faces].reshape(-1, 3)
    Fs = np.arange(len(Vs)).reshape(-1, 3)
    orig = s.faces.reshape(-1)
    for method in ("heat", "graph"):
        D = distance_matrix(s.vertices, s.faces, None, s.bones, method=method)
        Ds = distance_matrix(Vs, Fs, None, s.bones, method=method)
        np.testing.assert_allclose(Ds, D[orig], rtol=1e-6, atol=1e-9 * s.finger_length)
    # the same Figure-2 bound on the soup
    tip_a, tip_b = tip_masks(s, Vs)
    d_e = displacements(Vs, Fs, s, "euclidean")
    d_h = displacements(Vs, Fs, s, "heat")
    assert d_h[tip_b].max() <= BOUND * d_e[tip_b].max()
    # the soup's graph distances across the gap match the connected surface's:
    # finger B's tip is far from finger A's bone (without welding every triangle
    # would be its own component, reached only through the "air bridge")
    b = s.bone_names.index("finger_a")
    E = distance_matrix(Vs, Fs, None, s.bones, method="euclidean")
    welded = distance_matrix(Vs, Fs, None, s.bones, method="graph")
    assert np.median(welded[tip_b, b] / E[tip_b, b]) > 2.0


# ---------------------------------------------------------------------------
# a character made of the fingers shape (OBJ + TGF), for the poser and the CLI
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fingers_files(fingers, tmp_path_factory):
    d = tmp_path_factory.mktemp("fingers_character")
    write_geometry(d / "fingers.obj", fingers.vertices, fingers.faces)
    joints = fingers.bones.reshape(-1, 3)  # 6 joints: palm, finger A, finger B (start, end)
    lines = [f"{i + 1} {float(x)!r} {float(y)!r} {float(z)!r}" for i, (x, y, z) in enumerate(joints)]
    lines += ["#", "1 2", "3 4", "5 6", "#"]
    (d / "fingers.tgf").write_text("\n".join(lines) + "\n")
    return d / "fingers.obj", d / "fingers.tgf"


@pytest.fixture
def counted(monkeypatch, tmp_path):
    """A private cache directory and a counter of distance computations."""
    monkeypatch.setenv("NRPOSE_CACHE_DIR", str(tmp_path / "cache"))
    calls = []
    real = distances_mod.distance_matrix

    def counting(*args, **kwargs):
        calls.append(kwargs.get("method"))
        return real(*args, **kwargs)

    monkeypatch.setattr(distances_mod, "distance_matrix", counting)
    return calls


def test_posing_twice_with_heat_hits_the_cache(fingers_files, counted, tmp_path):
    ch = load_character(*fingers_files)
    assert len(ch.skeleton.bones()) == 3
    local = ch.skeleton.rest_pose
    first = CharacterPoser(ch, weights="heat").pose(local).positions
    assert counted == ["heat"]
    files = list((tmp_path / "cache").glob("*.npz"))
    assert len(files) == 1
    second = CharacterPoser(ch, weights="heat").pose(local).positions
    assert counted == ["heat"]  # the second bind read the cache
    np.testing.assert_array_equal(first, second)
    # a changed input is a miss; another method is another key
    moved = load_character(*fingers_files)
    moved.meshes[0].vertices[0] += 1e-3
    CharacterPoser(moved, weights="heat")
    CharacterPoser(ch, weights="graph")
    assert counted == ["heat", "heat", "graph"]
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 3


def test_cache_file_of_a_pose_run_is_rebuilt_when_corrupt(fingers_files, counted, tmp_path):
    ch = load_character(*fingers_files)
    CharacterPoser(ch, weights="heat")
    (path,) = (tmp_path / "cache").glob("*.npz")
    path.write_bytes(b"not an npz file")
    # the character's whole bind is cached too (its folder): without it the bind reads the distances again
    shutil.rmtree(tmp_path / "cache" / BIND_CACHE_FOLDER)
    CharacterPoser(ch, weights="heat")
    assert counted == ["heat", "heat"]
    with np.load(path) as z:
        assert "D" in z.files
    assert bindcache.FORMAT_VERSION >= 2  # welding changed the distances: old files are stale


# ---------------------------------------------------------------------------
# nrpose weights
# ---------------------------------------------------------------------------
@pytest.fixture
def nrpose_main():
    """``nrpose.cli.main``."""
    from nrpose import cli

    return cli.main


def test_weights_cli_writes_weights_and_map(fingers, fingers_files, counted, nrpose_main, tmp_path, capsys):
    obj, tgf = fingers_files
    out, png = tmp_path / "w.npz", tmp_path / "map.png"
    assert nrpose_main(["weights", str(obj), "--skeleton", str(tgf), "--method", "heat", "-o", str(out),
                        "--png", str(png), "--bone", "bone1"]) == 0
    line = capsys.readouterr().out
    assert "3 bones" in line and "heat" in line
    assert png.stat().st_size > 10_000
    with np.load(out) as z:
        W, D = z["weights"], z["distances"]
        assert W.dtype == np.float32 and W.shape == (len(fingers.vertices), 3)
        np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-6)
        assert z["bones"].shape == (3, 2, 3)
        np.testing.assert_allclose(z["bones"], fingers.bones, atol=1e-12)
        assert list(z["bone_names"]) == ["bone0->bone0_tip", "bone1->bone1_tip", "bone2->bone2_tip"]
        assert list(z["bone_joints"]) == [0, 1, 2]
        assert str(z["method"]) == "heat" and int(z["k"]) == 3  # 3 bones: dense by default
        np.testing.assert_array_equal(D, distance_matrix(fingers.vertices, fingers.faces, None, fingers.bones,
                                                         method="heat"))
    # Figure 2 in the file: finger A's bone barely reaches finger B
    on_b = (fingers.vertices[:, 0] > 0.5 * fingers.finger_gap) & (fingers.vertices[:, 1] > 0.3)
    assert W[on_b, 1].max() < 0.07
    # the weights command filled the cache: posing with heat weights binds from it
    n = len(counted)
    CharacterPoser(load_character(obj, tgf), weights="heat")
    assert len(counted) == n
    # top-k: one bone per vertex, weight 1
    assert nrpose_main(["weights", str(obj), "--skeleton", str(tgf), "--method", "euclidean", "--k", "1",
                        "-o", str(out)]) == 0
    with np.load(out) as z:
        W = z["weights"]
        assert int(z["k"]) == 1 and str(z["method"]) == "euclidean"
        assert ((W > 0).sum(axis=1) == 1).all() and np.allclose(W.max(axis=1), 1.0)


@pytest.mark.parametrize("argv, message", [
    (["--method", "heat", "--png", "m.png", "--bone", "bone7"], "did you mean"),
    (["--method", "heat", "--png", "m.png"], "--png and --bone go together"),
    (["--method", "heat", "--bone", "bone1"], "--png and --bone go together"),
    (["--method", "geodesic"], "invalid choice"),
    (["--method", "heat", "--k", "0"], "positive integer"),
    (["--method", "heat", "--alpha", "-1"], "alpha"),
])
def test_weights_cli_errors(fingers_files, nrpose_main, tmp_path, capsys, argv, message):
    obj, tgf = fingers_files
    out = tmp_path / "w.npz"
    assert nrpose_main(["weights", str(obj), "--skeleton", str(tgf), "-o", str(out)] + argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not out.exists() and not list(tmp_path.glob(".w.npz.*"))


def test_weights_cli_missing_inputs(fingers_files, nrpose_main, tmp_path, capsys):
    obj, tgf = fingers_files
    assert nrpose_main(["weights", str(obj), "--method", "heat", "-o", str(tmp_path / "w.npz")]) == 2
    assert "needs a skeleton" in capsys.readouterr().err
    assert nrpose_main(["weights", str(tmp_path / "none.glb"), "--method", "heat",
                        "-o", str(tmp_path / "w.npz")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert nrpose_main(["weights", str(obj), "--skeleton", str(tgf), "--method", "heat",
                        "-o", str(tmp_path / "w.txt")]) == 2
    assert ".npz" in capsys.readouterr().err


@needs_data
def test_weights_cli_fox_joint_name_and_default_k(nrpose_main, counted, tmp_path, capsys):
    out, png = tmp_path / "fox.npz", tmp_path / "fox.png"
    fox = DATA / "gltf" / "Fox.glb"
    assert nrpose_main(["weights", str(fox), "--method", "heat", "-o", str(out), "--png", str(png),
                        "--bone", "b_LeftForeArm_010"]) == 0
    assert "b_LeftForeArm_010->b_LeftHand_011" in capsys.readouterr().out
    with np.load(out) as z:
        W, names = z["weights"], list(z["bone_names"])
        assert W.shape == (1728, 29) and int(z["k"]) == 8  # 29 bones: sparse by default
        assert (np.count_nonzero(W, axis=1) <= 8).all()
        np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-5)
    assert png.stat().st_size > 10_000
    # the Fox is a triangle soup: welded, its heat distances keep the front legs apart
    ch = load_character(fox)
    skel, m = ch.skeleton, ch.meshes[0]
    b = names.index("b_LeftForeArm_010->b_LeftHand_011")
    dom = m.joints[np.arange(len(m.vertices)), np.argmax(m.weights, axis=1)]
    right_leg = np.isin(dom, [skel.index(n) for n in ("b_RightUpperArm_06", "b_RightForeArm_07", "b_RightHand_08")])
    assert nrpose_main(["weights", str(fox), "--method", "euclidean", "--k", "all", "-o", str(out)]) == 0
    with np.load(out) as z:
        w_e = z["weights"][:, b]
    assert nrpose_main(["weights", str(fox), "--method", "heat", "--k", "all", "-o", str(out)]) == 0
    with np.load(out) as z:
        w_h = z["weights"][:, b]
    assert w_h[right_leg].max() < 0.6 * w_e[right_leg].max()  # measured 0.050 vs 0.110
