"""Distance fields, weights, the binding cache and the Figure-2 shape.

Measured (libigl 2.6.3, this machine), asserted with a little headroom:

* unit icosphere, 2562 vertices, 3 point handles on vertices, vs the analytic
  great-circle distance, where it is > 0.2: heat max rel 1.90 %, mean 0.83 %;
  exact max rel 0.074 %; graph (edge Dijkstra) max rel 17.6 %.
* fingers shape (2650 vertices, 3 bones + 1 point handle), heat vs exact
  (same source/offset rule): bones max rel 8.3 %, point handle max rel 13.0 %
  (0.189 vs 0.217, right next to the source), mean rel 0.82 %; kNN (k=10) on
  its vertices as a point cloud vs exact: mean |rel| 6.2 %.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

igl = pytest.importorskip("igl")

from nrpose.bind import cache as bindcache  # noqa: E402
from nrpose.bind.distances import distance_matrix, euclidean_distances, handle_sources  # noqa: E402
from nrpose.errors import HandleError, InputError  # noqa: E402
from nrpose.bind.weights import deviation, dense_weights, keep_top_k, relative_weights  # noqa: E402
from nrpose.rigs.fingers import fingers_shape  # noqa: E402


def icosphere(subdiv: int = 4):
    V, F = igl.icosahedron()
    V, F = igl.loop(V, F, subdiv)
    return V / np.linalg.norm(V, axis=1, keepdims=True), np.asarray(F, np.int64)


@pytest.fixture(scope="module")
def sphere():
    return icosphere(4)


@pytest.fixture(scope="module")
def fingers():
    return fingers_shape()


@pytest.fixture(scope="module")
def fingers_handles(fingers):
    P = np.array([[-0.5, 2.5, 0.0]]) * [1, 0.95, 1]  # just inside finger A's tip
    return P, fingers.bones


@pytest.fixture(scope="module")
def fingers_exact(fingers, fingers_handles):
    return distance_matrix(fingers.vertices, fingers.faces, *fingers_handles, method="exact")


# ---------------------------------------------------------------------------
# accuracy
# ---------------------------------------------------------------------------
def test_sphere_heat_and_exact_vs_analytic(sphere):
    V, F = sphere
    P = V[[0, 17, 100]]
    true = np.arccos(np.clip(V @ P.T, -1, 1))
    far = true > 0.2
    rel = {}
    for m in ("heat", "exact", "graph"):
        D = distance_matrix(V, F, P, None, method=m)
        assert D.shape == (len(V), 3) and D.dtype == np.float64
        rel[m] = np.abs(D - true)[far] / true[far]
    assert rel["exact"].max() < 0.002  # measured 0.00074
    assert rel["heat"].max() < 0.025  # measured 0.0190
    assert rel["heat"].mean() < 0.011  # measured 0.0083
    assert rel["graph"].max() < 0.25  # measured 0.176: edge paths zig-zag


def test_fingers_heat_vs_exact(fingers, fingers_handles, fingers_exact):
    D = distance_matrix(fingers.vertices, fingers.faces, *fingers_handles, method="heat")
    X = fingers_exact
    rel = np.abs(D - X) / X
    assert rel[:, 1:].max() < 0.095  # bones: measured 0.083
    assert rel[:, 0].max() < 0.15  # point handle: measured 0.130, next to the source
    assert rel.mean() < 0.01  # measured 0.0082


def test_graph_is_an_upper_bound_of_exact(fingers, fingers_handles, fingers_exact):
    G = distance_matrix(fingers.vertices, fingers.faces, *fingers_handles, method="graph")
    assert (G >= fingers_exact - 1e-9).all()
    assert np.median(G / fingers_exact) < 1.15


def test_knn_point_cloud_roughly_agrees(fingers, fingers_handles, fingers_exact):
    K = distance_matrix(fingers.vertices, None, *fingers_handles)  # default: knn
    K2 = distance_matrix(fingers.vertices, None, *fingers_handles, method="knn", k_neighbours=10)
    np.testing.assert_array_equal(K, K2)
    rel = (K - fingers_exact) / fingers_exact
    assert np.abs(rel).mean() < 0.08  # measured 0.062
    assert rel.min() > -0.1  # kNN shortcuts are short: barely below the geodesic


def test_all_methods_finite_nonnegative_and_above_euclidean(fingers, fingers_handles):
    V, F = fingers.vertices, fingers.faces
    E = euclidean_distances(V, *fingers_handles)
    assert np.allclose(distance_matrix(V, F, *fingers_handles, method="euclidean"), E)
    for m in ("heat", "graph"):
        D = distance_matrix(V, F, *fingers_handles, method=m)
        assert D.shape == (len(V), 4)
        assert np.isfinite(D).all() and (D >= E).all()


# ---------------------------------------------------------------------------
# Figure 2: spatially near, topologically far
# ---------------------------------------------------------------------------
def test_figure2_finger_a_is_far_from_finger_b_bone(fingers):
    s = fingers
    V, F = s.vertices, s.faces
    assert s.finger_gap < 0.25 * s.finger_length
    E = distance_matrix(V, F, None, s.bones, method="euclidean")
    b = s.bone_names.index("finger_b")
    upper_a = np.flatnonzero((V[:, 0] < -0.5 * s.finger_gap) & (V[:, 1] > 1.5))
    tip_a = upper_a[np.argmax(V[upper_a, 1])]
    for m in ("heat", "graph"):
        D = distance_matrix(V, F, None, s.bones, method=m)
        ratio = D[upper_a, b] / E[upper_a, b]
        assert ratio.min() > 1.8, m  # measured 1.90 (heat)
        assert D[tip_a, b] > 2.5 * E[tip_a, b], m
    # the sources of finger A's bone are on finger A only
    idx, off = handle_sources(V, F, None, s.bones)[s.bone_names.index("finger_a")]
    assert (V[idx, 0] < 0).all()
    assert np.allclose(off, euclidean_distances(V[idx], None, s.bones[1:2])[:, 0])


def test_figure2_weights(fingers):
    s = fingers
    V, F = s.vertices, s.faces
    a = s.bone_names.index("finger_a")
    on_b = (V[:, 0] > 0.5 * s.finger_gap) & (V[:, 1] > 0.3)
    w_e = dense_weights(distance_matrix(V, F, None, s.bones, method="euclidean"))[:, a]
    w_h = dense_weights(distance_matrix(V, F, None, s.bones, method="heat"))[:, a]
    assert w_e[on_b].max() > 0.14  # measured 0.152
    assert w_h[on_b].max() < 0.07  # measured 0.059


# ---------------------------------------------------------------------------
# several components, unreachable vertices, hidden bones
# ---------------------------------------------------------------------------
def _with_extras(s):
    """fingers + a small closed 'eye' shell outside finger A + one unreferenced vertex."""
    Ve, Fe = icosphere(2)
    Ve = 0.15 * Ve + [-1.1, 2.0, 0.0]  # beside finger A, outside the body
    V = np.vstack([s.vertices, Ve, [[3.0, 3.0, 3.0]]])
    F = np.vstack([s.faces, Fe + len(s.vertices)])
    eye = np.arange(len(s.vertices), len(s.vertices) + len(Ve))
    return V, F, eye, len(V) - 1


@pytest.mark.parametrize("method", ["heat", "graph", "exact"])
def test_components_and_unreachable_vertices(fingers, method):
    V, F, eye, lone = _with_extras(fingers)
    P = np.array([[0.5, -0.5, 0.0]])
    D1 = distance_matrix(V, F, P, fingers.bones, method=method)
    D2 = distance_matrix(V, F, P, fingers.bones, method=method)
    np.testing.assert_array_equal(D1, D2)  # deterministic, bit for bit
    assert np.isfinite(D1).all() and (D1 >= 0).all()
    E = euclidean_distances(V, P, fingers.bones)
    assert (D1 >= E - 1e-12).all()
    # no handle has a source on the eye or the lone vertex
    for idx, _ in handle_sources(V, F, P, fingers.bones):
        assert not np.isin(idx, np.r_[eye, lone]).any()
    # the eye sits by finger A: it inherits finger A's distances (air bridge)
    a, b = 1 + 1, 1 + 2
    assert D1[eye, a].max() < D1[eye, b].min()
    assert D1[lone].max() < 20.0


def test_knn_islands_are_finite(fingers):
    rng = np.random.default_rng(0)
    island = rng.normal(size=(30, 3)) * 0.05 + [4.0, 0.0, 0.0]
    V = np.vstack([fingers.vertices, island])
    D = distance_matrix(V, None, None, fingers.bones, method="knn", k_neighbours=6)
    assert np.isfinite(D).all()
    assert (D >= euclidean_distances(V, None, fingers.bones) - 1e-12).all()


def test_hidden_bone_still_gets_a_source(fingers):
    # a tiny bone inside finger A's bone region: nearest-bone never picks it
    bones = np.vstack([fingers.bones, [[[-0.5, 1.0, 0.0], [-0.5, 1.0001, 0.0]]]])
    src = handle_sources(fingers.vertices, fingers.faces, None, bones)
    assert all(len(i) >= 1 for i, _ in src)
    D = distance_matrix(fingers.vertices, fingers.faces, None, bones, method="heat")
    assert np.isfinite(D).all()


def test_visibility_blocks_sources_across_the_gap():
    # two separate boxes: bone 0 runs inside box L; box R has no bone of its own
    # nearer than bone 0 but cannot see it (the gap is outside the shape)
    V0, F0 = _box(-1.0, -0.2)
    V1, F1 = _box(0.2, 1.0)
    V = np.vstack([V0, V1])
    F = np.vstack([F0, F1 + len(V0)])
    bones = np.array([[[-0.6, -0.4, 0.0], [-0.6, 0.4, 0.0]], [[3.0, -0.4, 0.0], [3.0, 0.4, 0.0]]])
    idx, _ = handle_sources(V, F, None, bones)[0]
    assert (V[idx, 0] < 0).all()
    idx_nv, _ = handle_sources(V, F, None, bones, visibility=False)[0]
    assert (V[idx_nv, 0] > 0).any()


def test_scrambled_faces_skip_the_visibility_test_with_a_warning(fingers, monkeypatch):
    """A face list whose faces span the mesh (fuzzing found one: 25 s of winding numbers)
    picks bone sources without the visibility test, saying so; a sound mesh keeps it."""
    import warnings

    from nrpose.bind import distances

    V, F = fingers.vertices, np.asarray(fingers.faces)
    assert distances.visibility_work(V, F, len(V))[0] == 0
    scrambled = F.copy()
    scrambled[::3, 0] = np.argmax(V[:, 0])           # every third face fans out from one far vertex
    long, work = distances.visibility_work(V, scrambled, len(V))
    assert long > len(F) // 10
    monkeypatch.setattr(distances, "VISIBILITY_WORK", work / 2)     # this mesh is small: lower the budget
    with pytest.warns(RuntimeWarning, match=rf"without the visibility test: {long} faces span"):
        got = handle_sources(V, scrambled, None, fingers.bones)
    plain = handle_sources(V, scrambled, None, fingers.bones, visibility=False)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(got, plain))
    monkeypatch.setattr(distances, "VISIBILITY_WORK", work * 2)     # within the budget: tested, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        handle_sources(V, scrambled, None, fingers.bones)


def _box(x0, x1, n=6):
    """Closed triangulated box [x0,x1]×[-0.5,0.5]×[-0.5,0.5] via marching cubes."""
    g = np.linspace(-0.8, 0.8, 33)
    gx = np.linspace(x0 - 0.3, x1 + 0.3, 17)
    Z, Y, X = np.meshgrid(g, g, gx, indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    c = np.array([(x0 + x1) / 2, 0, 0])
    h = np.array([(x1 - x0) / 2, 0.5, 0.5])
    q = np.abs(P - c) - h
    S = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    V, F, _ = igl.marching_cubes(S, P, len(gx), len(g), len(g), 0.0)
    return np.asarray(V), np.asarray(F, np.int64)


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------
def test_bad_input(sphere):
    V, F = sphere
    P = V[:1]
    Vn = V.copy()
    Vn[5, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        distance_matrix(Vn, F, P)
    Fb = F.copy()
    Fb[0, 0] = len(V)
    with pytest.raises(InputError, match=rf"faces: 1 of {len(F)} faces index vertices outside 0\.\.{len(V) - 1} "
                                         r"\(first: face 0 = "):
        distance_matrix(V, Fb, P)
    with pytest.raises(InputError, match="outside"):
        distance_matrix(V, F - 1, P)
    with pytest.raises(InputError, match="empty"):
        distance_matrix(np.zeros((0, 3)), None, P)
    with pytest.raises(InputError, match="empty"):
        distance_matrix(V, np.zeros((0, 3), int), P)
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        distance_matrix(V[:, :2], None, P)
    with pytest.raises(InputError, match="triangles"):
        distance_matrix(V, F[:, :2], P)
    with pytest.raises(HandleError, match="no handles"):
        distance_matrix(V, F)
    with pytest.raises(HandleError, match="NaN"):
        distance_matrix(V, F, [[np.nan, 0, 0]])
    with pytest.raises(HandleError, match=r"segment_handles: expected shape \(N, 2, 3\)"):
        distance_matrix(V, F, None, np.zeros((2, 3)))
    with pytest.raises(InputError, match="unknown distance method"):
        distance_matrix(V, F, P, method="dijkstra")
    with pytest.raises(InputError, match="needs faces"):
        distance_matrix(V, None, P, method="heat")
    with pytest.raises(InputError, match="k_neighbours"):
        distance_matrix(V, None, P, method="knn", k_neighbours=0)


def test_columns_points_then_segments(sphere):
    V, F = sphere
    P = V[[3, 50]]
    S = np.array([[[0, 0, -0.5], [0, 0, 0.5]]])
    D = distance_matrix(V, F, P, S, method="graph")
    assert D.shape == (len(V), 3)
    assert D[3, 0] == 0 and D[50, 1] == 0
    np.testing.assert_allclose(D[:, 0], distance_matrix(V, F, P[:1], None, method="graph")[:, 0])
    np.testing.assert_allclose(D[:, 2], distance_matrix(V, F, None, S, method="graph")[:, 0])


def test_point_handle_offset(sphere):
    V, F = sphere
    P = 1.5 * V[[7]]  # outside the sphere: offset 0.5 from its nearest vertex
    D = distance_matrix(V, F, P, None, method="exact")
    true = np.arccos(np.clip(V @ V[7], -1, 1)) + 0.5
    assert D[7, 0] == pytest.approx(0.5)
    assert np.all(D[:, 0] <= true + 1e-3)
    assert np.all(D[:, 0] >= euclidean_distances(V, P)[:, 0] - 1e-12)


# ---------------------------------------------------------------------------
# weights
# ---------------------------------------------------------------------------
def test_relative_and_dense_weights():
    D = np.array([[1.0, 2.0, 4.0], [0.0, 1.0, 0.0], [1e-300, 1e300, 1.0]])
    W = relative_weights(D, alpha=1.0)
    np.testing.assert_allclose(W[0], [1.0, 0.25, 1 / 16])
    np.testing.assert_array_equal(W[1], [1.0, 0.0, 1.0])
    assert np.isfinite(W).all() and W[2, 0] == 1.0
    Wd = dense_weights(D, alpha=1.5)
    np.testing.assert_allclose(Wd.sum(axis=1), 1.0)
    np.testing.assert_allclose(Wd[1], [0.5, 0.0, 0.5])
    with pytest.raises(InputError):
        relative_weights(np.array([[np.nan, 1.0]]))
    with pytest.raises(InputError):
        relative_weights(np.array([[-1.0, 1.0]]))
    with pytest.raises(InputError):
        relative_weights(np.ones((2, 2)), alpha=0)


def test_keep_top_k():
    rng = np.random.default_rng(1)
    D = rng.uniform(0.1, 5.0, size=(50, 7))
    D[0, :] = 1.0  # ties: lowest indices win
    W = dense_weights(D, alpha=1.0)
    K = keep_top_k(W, 3)
    assert (np.count_nonzero(K, axis=1) == 3).all()
    np.testing.assert_allclose(K.sum(axis=1), 1.0)
    np.testing.assert_array_equal(np.flatnonzero(K[0]), [0, 1, 2])
    kept = np.sort(np.argsort(D, axis=1, kind="stable")[:, :3], axis=1)
    np.testing.assert_array_equal(np.sort(np.argsort(-K, axis=1, kind="stable")[:, :3], axis=1), kept)
    rows = np.arange(50)[:, None]
    np.testing.assert_allclose(K[rows, kept], W[rows, kept] / W[rows, kept].sum(axis=1, keepdims=True))
    assert keep_top_k(W, 10) is W and keep_top_k(W, None) is W     # k >= H: dense as is
    with pytest.raises(InputError):
        keep_top_k(W, 0)


def test_deviation_report():
    a = np.zeros((4, 3))
    b = np.zeros((4, 3))
    b[0] = [0.0, 3.0, 4.0]
    b[3] = [1.0, 0.0, 0.0]
    r = deviation(a, b)
    assert r["max"] == pytest.approx(5.0)
    assert r["rms"] == pytest.approx(np.sqrt(26 / 4))
    assert r["max_rel"] == pytest.approx(5.0 / np.linalg.norm([1.0, 3.0, 4.0]))
    with pytest.raises(InputError):
        deviation(a, b[:3])


# ---------------------------------------------------------------------------
# binding cache
# ---------------------------------------------------------------------------
def test_cache_hit_miss_and_rebuild(tmp_path, monkeypatch, sphere):
    monkeypatch.setenv("NRPOSE_CACHE_DIR", str(tmp_path / "cache"))
    V, F = sphere
    P = V[:2]
    calls = []

    def compute(V=V):
        calls.append(1)
        return {"D": distance_matrix(V, F, P, None, method="graph")}

    parts = bindcache.binding_key_parts(V, F, P, None, {"method": "graph", "alpha": 1.0})
    r1, st1 = bindcache.cached_status(parts, compute)
    r2, st2 = bindcache.cached_status(parts, compute)
    assert (st1, st2) == ("miss", "hit") and len(calls) == 1
    np.testing.assert_array_equal(r1["D"], r2["D"])
    path = bindcache.cache_path(parts)
    assert path.parent == tmp_path / "cache" and path.exists()
    assert not [p for p in path.parent.iterdir() if p.suffix == ".tmp"]

    # any change of content or options is a new key
    V2 = V.copy()
    V2[0, 0] += 1e-9
    parts2 = bindcache.binding_key_parts(V2, F, P, None, {"method": "graph", "alpha": 1.0})
    parts3 = bindcache.binding_key_parts(V, F, P, None, {"alpha": 1.0, "method": "heat"})
    assert len({bindcache.cache_key(p) for p in (parts, parts2, parts3)}) == 3
    assert bindcache.cache_key(bindcache.binding_key_parts(V, F, P, None, {"alpha": 1.0, "method": "graph"})) \
        == bindcache.cache_key(parts)  # option order does not matter
    _, st = bindcache.cached_status(parts2, lambda: compute(V2))
    assert st == "miss" and len(calls) == 2

    # a corrupt file is deleted and rebuilt, never trusted
    path.write_bytes(b"PK\x03\x04 definitely not a zip")
    r3, st3 = bindcache.cached_status(parts, compute)
    assert st3 == "rebuilt" and len(calls) == 3
    np.testing.assert_array_equal(r3["D"], r1["D"])
    _, st4 = bindcache.cached_status(parts, compute)
    assert st4 == "hit"
    # a valid npz stored under the wrong name is not trusted either
    other = bindcache.cache_path(parts2)
    os.replace(other, path)
    r5, st5 = bindcache.cached_status(parts, compute)
    assert st5 == "rebuilt"
    np.testing.assert_array_equal(r5["D"], r1["D"])
    assert bindcache.cached(parts, compute)["D"].shape == (len(V), 2)


def test_cache_default_location(monkeypatch, tmp_path):
    monkeypatch.delenv("NRPOSE_CACHE_DIR", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert bindcache.cache_dir() == tmp_path / ".cache" / "nrpose"


# ---------------------------------------------------------------------------
# weight map
# ---------------------------------------------------------------------------
def test_save_weight_map(tmp_path, sphere):
    from nrpose.render.weightmap import save_weight_map

    V, F = icosphere(1)
    w = dense_weights(distance_matrix(V, F, V[[0, 5]], None, method="graph"))[:, 0]
    out = save_weight_map(V, F, w, tmp_path / "w.png", "test")
    assert out.exists() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_heat_falls_back_to_graph_on_a_rejected_mesh():
    # zero-area (collinear) triangles: the cotangent Laplacian is undefined
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], float)
    F = np.array([[0, 1, 2], [1, 2, 3]])
    with pytest.warns(RuntimeWarning, match="graph"):
        D = distance_matrix(V, F, [[0.0, 0.0, 0.0]], method="heat")
    np.testing.assert_allclose(D[:, 0], [0, 1, 2, 3])
