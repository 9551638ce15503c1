"""Per-handle topological distance fields: the ``D`` of the blend weights.

``distance_matrix(V, F, point_handles, segment_handles, method)`` returns
``D`` of shape ``(N, P + S)`` float64, finite and ``>= 0``: column ``j`` is the
distance from every vertex to handle ``j``, point handles first, then segment
handles (bones). The seed paper (Jeong & Kim, section 3) weights handle ``i``
at a point by ``1 / d_i^(2α)`` and recommends the shortest distance *over the
surface* instead of the straight-line distance, so that a handle does not
pull points that are spatially near but topologically far (Figure 2: a
finger's bone must not move the neighbouring finger).

Methods
-------
``heat``      (default with faces) libigl heat geodesics [Crane et al. 2013],
              one factorisation per connected component, one solve per handle.
              Time step ``t = heat_t_factor · h²`` with ``h`` the mean edge
              length of the component (libigl's default; factor 1). The
              intrinsic-Delaunay Laplacian is used (robust to the slivers of
              marching-cubes and scanned meshes).
``exact``     ``igl.exact_geodesic`` (MMP); slow, for small meshes / validation.
``graph``     Dijkstra over the mesh edges (``scipy.sparse.csgraph``); paths
              follow edges so it over-estimates the geodesic by a few percent.
              Also the fallback for a component on which the heat method fails.
``knn``       (default without faces) Dijkstra over the symmetrised
              k-nearest-neighbour graph of a point cloud.
``euclidean`` straight-line distance to the point / closest point of the
              segment (the paper's "spatial" weights; for comparison).

Sources and offsets (where a handle's distance starts)
------------------------------------------------------
A handle usually lies *inside* the body, the surface distance starts on the
surface: each handle ``h`` gets a set of source vertices ``s`` with offsets
``o_s = |s - h|`` (Euclidean, to the point or the closest point of the
segment), and the exact quantity we approximate is::

    D[v, h] = min_s ( g(s, v) + o_s )          g: distance over the surface

* Point handle: a single source, the nearest surface vertex (lowest index on
  ties).
* Segment handle (bone): the vertices whose nearest bone (Euclidean, among
  the segment handles only) is this bone, that can *see* it: the straight
  segment from the vertex to its closest point on the bone must stay inside
  the shape, tested by sampling the generalised winding number
  (``igl.fast_winding_number``) at 7 interior points of that segment
  (all > 0.5). Point clouds skip the visibility test, and so does (with a
  warning) a mesh on which it would cost more than :data:`VISIBILITY_WORK`
  (:func:`visibility_work`: faces spanning a quarter of the mesh, which the fast
  winding number cannot lump with others, times the samples; a scrambled face
  list makes thousands of them, and minutes of work). A bone that ends up
  with no source (hidden by other bones) falls back to its single nearest
  visible vertex, or its nearest vertex if none is visible.
* ``graph`` / ``knn`` evaluate the formula exactly (for their graph metric):
  a super-source joined to every source by an edge of length ``o_s``.
* ``heat`` / ``exact`` solve once from the whole source set (multi-source
  distance ``g(S, v)``) and use::

      D[v, h] = max( g(S, v) + min_s o_s ,  |v - h| )

  Both terms are lower bounds of the exact formula (triangle inequality), so
  the max is the tighter lower bound; it is exact on the sources themselves
  (``D = o_s``) and near the joints where a bone's end sits deep inside the
  body. ``exact`` uses the same rule, so heat-vs-exact measures only the heat
  approximation.
* Heat from a *region*: a bone's sources cover a patch of surface (a whole
  finger). The heat method is poor there (inside the patch the normalised
  heat gradient is noise: about 57 % mean relative error on the fingers shape). Outside a patch the distance to it is the distance to its border,
  so heat is solved from the *front*: the sources that have a non-source
  neighbour; the sources themselves get 0. libigl's normalisation (minus the
  mean over the front) is kept and negatives are clipped to 0. Heat against
  exact on the fingers shape (2.6k vertices): bones max 8.3 %, a
  point handle max 13 % (right next to it), mean 0.8 % relative error; unit
  icosphere (2.6k vertices, point sources) vs great circles: max 1.9 %.
* Time step: ``t = m·h²``. Max relative error for ``m`` = 0.25,
  0.5, 1, 2, 4: icosphere point sources 3.4, 2.5, 1.9, 1.6, 1.4 %; fingers
  bones 7.7, 4.7, 8.3, 15.8, 25.2 % (mean 0.88, 0.43, 0.84, 1.7, 2.8 %:
  a large t blurs a region's front). m = 1 (libigl's and
  Crane et al.'s default) is kept: ``heat_t_factor``.

Coincident vertices are welded first
------------------------------------
Real assets split vertices along UV seams and hard edges (a glTF vertex
carries one normal and one texture coordinate): the Fox sample is a
triangle soup (1,728 vertices, 576 components, 290 distinct positions), the
Mannequin is cut into 61 pieces (15,882 vertices, 14,442 positions).
Over such a mesh no surface path crosses a seam, and every piece would get
its distances from the "air bridge" below, i.e. nearly Euclidean ones. All
surface methods (and ``knn``) therefore merge vertices with *bit-identical*
positions (after ``+ 0.0``, so ``-0.0 == 0.0``), drop the faces that become
degenerate, solve on the welded mesh, and give every input vertex the row of
its welded vertex (``weld=False`` turns this off). The Fox and the Mannequin
are then one connected surface each.

Every method ends with ``D = max(D, Euclidean)`` (a surface path can never be
shorter than the straight line), and negative heat values are clipped to 0.

Unreachable vertices (other shells, isolated vertices, kNN islands)
-------------------------------------------------------------------
A vertex in a connected component that holds none of handle ``h``'s sources
(eyes, teeth, separate shells, unreferenced vertices) gets the "air bridge"
rule: among its ``K = 8`` nearest vertices that *are* reached by ``h``,
``D[v, h] = min_u ( D[u, h] + |u - v| )``. The component thus inherits the
distances of the surface it sits closest to (an eye follows the head), the
value is finite, ``>= |v - h|``, and deterministic (the same input gives the
same bits). Every handle has at least one source, so the reached set is never
empty.

Validation: non-finite or wrongly shaped coordinates, faces out of range,
empty inputs, no handles, unknown method → :class:`~nrpose.errors.InputError`
(handle problems → :class:`~nrpose.errors.HandleError`).
"""
from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numpy as np

from ..checks import coordinates, real_rows, triangles
from ..errors import HandleError, InputError
from ..native import quiet_native
from .cache import binding_key_parts, cached

if TYPE_CHECKING:     # scipy is imported where a graph is built (not on the posing path)
    import scipy.sparse as sp

__all__ = [
    "surface_distances",
    "METHODS",
    "distance_matrix",
    "euclidean_distances",
    "handle_sources",
    "visibility_work",
    "point_segment_distances",
    "mesh_components",
    "weld_vertices",
]

METHODS = ("heat", "exact", "graph", "knn", "euclidean")
_BRIDGE_K = 8
#: the largest longest-edge / median-edge ratio given to libigl's geodesics
MAX_EDGE_SPREAD = 1e6
_VIS_SAMPLES = np.linspace(0.125, 0.875, 7)  # along bone point -> vertex
#: a face whose longest edge spans this share of the mesh's bounding-box diagonal is "long"
LONG_FACE = 0.25
#: most winding-number samples times long faces given to the visibility test (~4 s on the
#: 2-core VM; the shared test meshes and characters have no long face at all)
VISIBILITY_WORK = 1e8


# ----------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------
def _validate(vertices, faces, point_handles, segment_handles):
    V = coordinates(vertices, "vertices")
    F = None
    if faces is not None:
        if np.size(faces) == 0:
            raise InputError("faces: empty; pass faces=None for a point cloud")
        F = triangles(faces, len(V))
    P = coordinates(() if point_handles is None else point_handles, "point_handles", error=HandleError,
                  allow_empty=True)
    S = coordinates(() if segment_handles is None else segment_handles, "segment_handles", (2, 3),
                  error=HandleError, allow_empty=True)
    if len(P) + len(S) == 0:
        raise HandleError("no handles: give at least one point or segment handle")
    return V, F, P, S


# ----------------------------------------------------------------------------
# Euclidean geometry
# ----------------------------------------------------------------------------
def segment_parameters(points: np.ndarray, segments: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Closest-point parameters t (N, S) of points (N, 3) on segments (S, 2, 3), clamped to [0, 1]
    (computed ``chunk`` rows at a time: the (rows, S, 3) temporaries stay a few MB)."""
    a = segments[:, 0]
    ab = segments[:, 1] - a
    length2 = np.einsum("sk,sk->s", ab, ab)
    t = np.empty((len(points), len(segments)))
    for r in range(0, len(points), chunk):
        rel = points[r:r + chunk, None, :] - a[None]
        t[r:r + chunk] = np.einsum("nsk,sk->ns", rel, ab) / length2
    return np.clip(t, 0.0, 1.0, out=t)


def point_segment_distances(X: np.ndarray, segments: np.ndarray, chunk: int = 2048):
    """Distances (N, S) from points X (N, 3) to segments (S, 2, 3), and for
    each point the index (N,) of its nearest segment (lowest index on ties)
    and the closest point (N, 3) on that segment. A zero-length segment acts
    as a point. Works in chunks of rows to bound memory."""
    X = np.asarray(X, dtype=np.float64)
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 3)
    A = segments[:, 0]  # (S,3)
    AB = segments[:, 1] - A
    L2 = np.einsum("ij,ij->i", AB, AB)
    inv = np.where(L2 > 0, 1.0 / np.where(L2 > 0, L2, 1.0), 0.0)
    n = len(X)
    D = np.empty((n, len(segments)))
    nearest = np.zeros(n, np.int64)
    Cn = np.empty((n, 3))
    for a in range(0, n, chunk):
        Xc = X[a:a + chunk]
        t = np.clip(np.einsum("nsk,sk->ns", Xc[:, None, :] - A[None], AB) * inv, 0.0, 1.0)
        C = A[None] + t[..., None] * AB[None]
        d = np.linalg.norm(Xc[:, None, :] - C, axis=2)
        D[a:a + chunk] = d
        if len(segments):
            j = np.argmin(d, axis=1)
            nearest[a:a + chunk] = j
            Cn[a:a + chunk] = C[np.arange(len(Xc)), j]
    return D, nearest, Cn


def euclidean_distances(X, point_handles=None, segment_handles=None) -> np.ndarray:
    """Straight-line distances (N, P+S) from rows of X to the handles."""
    X = np.asarray(X, dtype=np.float64)
    P = np.zeros((0, 3)) if point_handles is None else np.asarray(point_handles, np.float64).reshape(-1, 3)
    S = np.zeros((0, 2, 3)) if segment_handles is None else np.asarray(segment_handles, np.float64).reshape(-1, 2, 3)
    Dp = np.empty((len(X), len(P)))
    for a in range(0, len(X), 8192):
        Dp[a:a + 8192] = np.linalg.norm(X[a:a + 8192, None, :] - P[None], axis=2)
    Ds = point_segment_distances(X, S)[0] if len(S) else np.zeros((len(X), 0))
    return np.hstack([Dp, Ds])


# ----------------------------------------------------------------------------
# graphs and components
# ----------------------------------------------------------------------------
def _edge_graph(V: np.ndarray, F: np.ndarray) -> sp.csr_matrix:
    import scipy.sparse as sp
    E = np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    E = np.sort(E, axis=1)
    E = E[E[:, 0] != E[:, 1]]
    E = np.unique(E, axis=0)
    return _symmetric_graph(V, E)


def _knn_graph(V: np.ndarray, k: int) -> sp.csr_matrix:
    import scipy.sparse as sp
    from scipy.spatial import cKDTree
    n = len(V)
    k = int(min(k, n - 1))
    if k < 1:
        return sp.csr_matrix((n, n))
    _, idx = cKDTree(V).query(V, k=k + 1)
    rows = np.repeat(np.arange(n), k)
    cols = idx[:, 1:].ravel()
    E = np.sort(np.column_stack([rows, cols]), axis=1)
    E = E[E[:, 0] != E[:, 1]]
    E = np.unique(E, axis=0)
    return _symmetric_graph(V, E)


def _symmetric_graph(V: np.ndarray, E: np.ndarray) -> sp.csr_matrix:
    import scipy.sparse as sp
    n = len(V)
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    # csgraph drops explicit zeros: coincident vertices stay joined by a tiny edge
    scale = max(float(np.ptp(V, axis=0).max()), 1.0)
    w = np.maximum(w, 1e-12 * scale)
    G = sp.coo_matrix((np.r_[w, w], (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])),
                      shape=(n, n))
    return G.tocsr()


def mesh_components(n_vertices: int, faces: np.ndarray | None) -> np.ndarray:
    """Connected-component label (N,) int64 of every vertex; vertices used by
    no face are singleton components. Labels are deterministic."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    if faces is None or len(faces) == 0:
        return np.arange(n_vertices, dtype=np.int64)
    F = np.asarray(faces, dtype=np.int64)
    E = np.vstack([F[:, [0, 1]], F[:, [1, 2]]])
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(A, directed=False)[1].astype(np.int64)


def weld_vertices(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct positions ``W`` (M, 3), in order of first occurrence, and
    ``inv`` (N,) int64 with ``V == W[inv]`` (bit-identical after ``+ 0.0``)."""
    V = np.ascontiguousarray(np.asarray(V, dtype=np.float64) + 0.0)
    _, first, inv = np.unique(V, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    if len(first) == len(V):
        return V, np.arange(len(V), dtype=np.int64)
    order = np.argsort(first, kind="stable")       # unique rows -> first-occurrence order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return V[first[order]], rank[inv].astype(np.int64)


# ----------------------------------------------------------------------------
# sources
# ----------------------------------------------------------------------------
def _visible(V, F, vidx, C) -> np.ndarray:
    """For each pair (vertex V[vidx[i]], bone point C[i]): does the straight
    segment between them stay inside the closed shape (winding number > 0.5
    at interior samples)?"""
    import igl

    if len(vidx) == 0:
        return np.zeros(0, bool)
    X = V[vidx]
    Q = C[None, :, :] + _VIS_SAMPLES[:, None, None] * (X - C)[None]  # (m, n, 3)
    with quiet_native():
        W = igl.fast_winding_number(V, F, np.ascontiguousarray(Q.reshape(-1, 3)))
    W = np.abs(np.asarray(W).reshape(len(_VIS_SAMPLES), len(vidx)))
    return np.all(W > 0.5, axis=0)


def visibility_work(V, F, vertices: int) -> tuple[int, float]:
    """(long faces, samples x long faces) of a visibility test of ``vertices`` surface vertices
    on the mesh V (n, 3), F (m, 3): the fast winding number evaluates a face that spans a good
    part of the mesh (:data:`LONG_FACE`) exactly at every sample near it, so these products
    bound its cost."""
    P = V[F]
    longest = np.sqrt(np.max(np.sum((P - np.roll(P, 1, axis=1)) ** 2, axis=2), axis=1))
    long = int((longest > LONG_FACE * np.linalg.norm(V.max(axis=0) - V.min(axis=0))).sum())
    return long, float(long) * vertices * len(_VIS_SAMPLES)


def handle_sources(V, F, point_handles, segment_handles, *, visibility: bool = True,
                   E: np.ndarray | None = None):
    """Source vertices and offsets of every handle (see the module docstring).

    Returns a list (P+S) of ``(indices int64 (k,), offsets float64 (k,))``.
    ``F`` None means a point cloud (no visibility test).
    """
    V, F, P, S = _validate(V, F, point_handles, segment_handles)
    if E is None:
        E = euclidean_distances(V, P, S)
    n = len(V)
    if F is not None:
        surf = np.zeros(n, bool)
        surf[F.ravel()] = True
    else:
        surf = np.ones(n, bool)
    surf_idx = np.flatnonzero(surf)
    out = []
    for j in range(len(P)):
        i = int(surf_idx[np.argmin(E[surf_idx, j])])
        out.append((np.array([i], np.int64), np.array([E[i, j]])))
    if len(S) == 0:
        return out
    Es = E[:, len(P):]
    # nearest bone of each surface vertex from E (no second distance pass), and
    # the closest point on that bone
    nearest = np.argmin(Es[surf_idx], axis=1) if len(surf_idx) else np.zeros(0, np.int64)
    A = S[nearest, 0]
    AB = S[nearest, 1] - A
    L2 = np.einsum("ij,ij->i", AB, AB)
    t = np.einsum("ij,ij->i", V[surf_idx] - A, AB) / np.where(L2 > 0, L2, 1.0)
    Cn = A + np.clip(np.where(L2 > 0, t, 0.0), 0.0, 1.0)[:, None] * AB
    if F is not None and visibility:
        long, work = visibility_work(V, F, len(surf_idx))
        if work > VISIBILITY_WORK:
            warnings.warn(f"bone sources chosen without the visibility test: {long} faces span more than "
                          f"{LONG_FACE:.0%} of the mesh (a scrambled face list?)", RuntimeWarning, stacklevel=2)
            visibility = False
    if F is not None and visibility:
        vis = _visible(V, F, surf_idx, Cn)
    else:
        vis = np.ones(len(surf_idx), bool)
    sel_of = [surf_idx[(nearest == s) & vis] for s in range(len(S))]
    hidden = [s for s in range(len(S)) if len(sel_of[s]) == 0]
    if hidden and F is not None and visibility:
        # nearest vertex that sees the bone, else the nearest vertex; one
        # winding-number evaluation for all hidden bones (its set-up dominates)
        orders = [surf_idx[np.argsort(Es[surf_idx, s], kind="stable")][:256] for s in hidden]
        Cs = np.concatenate([point_segment_distances(V[o], S[s:s + 1])[2] for s, o in zip(hidden, orders)])
        v_all = _visible(V, F, np.concatenate(orders), Cs)
        at = 0
        for s, order in zip(hidden, orders):
            v = v_all[at:at + len(order)]
            at += len(order)
            sel_of[s] = order[[int(np.argmax(v))]] if v.any() else order[:1]
    else:
        for s in hidden:
            sel_of[s] = surf_idx[[int(np.argmin(Es[surf_idx, s]))]]
    for s in range(len(S)):
        sel = sel_of[s]
        out.append((sel.astype(np.int64), Es[sel, s].copy()))
    return out


# ----------------------------------------------------------------------------
# solvers: each fills G[:, h] for the reached vertices, inf elsewhere
# ----------------------------------------------------------------------------
def _dijkstra_offsets(G: sp.csr_matrix, sources) -> np.ndarray:
    """Exact min_s (graph(s, v) + o_s) per handle via a super-source node."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra
    n = G.shape[0]
    out = np.full((n, len(sources)), np.inf)
    Gc = G.tocoo()
    for h, (idx, off) in enumerate(sources):
        shift = 1.0 + float(off.max(initial=0.0))  # keeps zero offsets as edges
        rows = np.r_[Gc.row, np.full(len(idx), n)]
        cols = np.r_[Gc.col, idx]
        data = np.r_[Gc.data, off + shift]
        A = sp.csr_matrix((data, (rows, cols)), shape=(n + 1, n + 1))
        d = dijkstra(A, directed=True, indices=n)[:n]
        out[:, h] = d - shift
    return out


def _per_component(V, F, comp, sources, solve_component):
    """Run ``solve_component(Vc, Fc, [(h, local_idx, offsets)]) -> (nc, k)`` on
    each face component that holds sources; returns (N, H) with inf where a
    handle has no source in the vertex's component."""
    n, H = len(V), len(sources)
    out = np.full((n, H), np.inf)
    src_comp = {}
    for h, (idx, off) in enumerate(sources):
        for c in np.unique(comp[idx]):
            m = comp[idx] == c
            src_comp.setdefault(int(c), []).append((h, idx[m], off[m]))
    fcomp = comp[F[:, 0]]
    order = np.argsort(fcomp, kind="stable")
    bounds = np.searchsorted(fcomp[order], np.arange(comp.max() + 2))
    for c in sorted(src_comp):
        Fc_glob = F[order[bounds[c]:bounds[c + 1]]]
        verts = np.flatnonzero(comp == c)
        if len(Fc_glob) == 0:  # isolated vertex holding a source
            for h, idx, off in src_comp[c]:
                out[verts, h] = off.min()
            continue
        local = -np.ones(n, np.int64)
        local[verts] = np.arange(len(verts))
        Vc = np.ascontiguousarray(V[verts])
        Fc = np.ascontiguousarray(local[Fc_glob])
        jobs = [(h, local[idx], off) for h, idx, off in src_comp[c]]
        res = solve_component(Vc, Fc, jobs)
        for col, (h, _, _) in enumerate(jobs):
            out[verts, h] = res[:, col]
    return out


def _heat_component(t_factor: float):
    def solve(Vc, Fc, jobs):
        import igl

        res = np.empty((len(Vc), len(jobs)))
        ok = len(Fc) > 0
        if ok:
            try:
                data = igl.HeatGeodesicsData()
                data.use_intrinsic_delaunay = True
                h = igl.avg_edge_length(Vc, Fc)
                with quiet_native():
                    ok = bool(h > 0) and igl.heat_geodesics_precompute(
                        Vc, Fc, float(t_factor * h * h), data) is not False
            except Exception:  # libigl rejects the mesh: use the graph fallback
                ok = False
        if ok:
            E = np.vstack([Fc[:, [0, 1]], Fc[:, [1, 2]], Fc[:, [2, 0]]])
            for col, (_, idx, off) in enumerate(jobs):
                ins = np.zeros(len(Vc), bool)
                ins[idx] = True
                cut = ins[E[:, 0]] != ins[E[:, 1]]
                front = np.unique(E[cut].ravel())
                front = front[ins[front]]  # sources with a non-source neighbour
                if len(front) == 0:  # the whole component is a source
                    res[:, col] = off.min()
                    continue
                with quiet_native():
                    d = np.asarray(igl.heat_geodesics_solve(data, front), dtype=np.float64)
                if not np.isfinite(d).all():
                    ok = False
                    break
                d = np.maximum(d, 0.0)
                d[ins] = 0.0
                res[:, col] = d + off.min()
        if not ok:
            warnings.warn("heat geodesics failed on a component; using graph distances there",
                          RuntimeWarning, stacklevel=4)
            return _graph_component(Vc, Fc, jobs)
        return res
    return solve


def exact_component(Vc, Fc, jobs):
    """Exact geodesic distances (libigl) on one connected component: Vc (n, 3) float64,
    Fc (m, 3) int64, jobs a list of (handle, source vertex indices, source offsets (s,)) ->
    (n, len(jobs)) float64, each column offset by its sources' smallest offset."""
    import igl

    # at unit size: libigl's tolerances are absolute (a mesh of 1e-30 units never finishes)
    scale = float(np.linalg.norm(np.ptp(Vc, axis=0))) or 1.0
    Vn = np.ascontiguousarray(Vc / scale)
    check_exact_ready(Vn, Fc)
    res = np.empty((len(Vc), len(jobs)))
    empty = np.zeros(0, np.int64)
    targets = np.arange(len(Vc), dtype=np.int64)
    for col, (_, idx, off) in enumerate(jobs):
        with quiet_native():
            d = igl.exact_geodesic(Vn, Fc, np.ascontiguousarray(idx), empty, targets, empty)
        res[:, col] = scale * np.asarray(d, np.float64) + off.min()
    return res


#: the thinnest triangle (twice its area over its longest edge squared) given to libigl's
#: exact geodesics
MIN_EXACT_QUALITY = 1e-10


def check_exact_ready(Vc, Fc) -> None:
    """InputError unless the component (Vc (n, 3), Fc (m, 3) int64) is what libigl's exact
    geodesics survive: every edge in at most two faces, consistently oriented, no sliver
    triangle (:data:`MIN_EXACT_QUALITY`); it crashes, hangs or exhausts memory otherwise."""
    directed = np.vstack([Fc[:, [0, 1]], Fc[:, [1, 2]], Fc[:, [2, 0]]])
    _, uses = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    _, same_way = np.unique(directed, axis=0, return_counts=True)
    P = Vc[Fc]
    e2 = np.max(np.sum((P - np.roll(P, 1, axis=1)) ** 2, axis=2), axis=1)
    quality = np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1) / np.where(e2 > 0, e2, 1)
    problems = [f"{n} {what}" for n, what in (((uses > 2).sum(), "edges in more than two faces"),
                                              ((same_way > 1).sum(), "edges with faces of opposite orientation"),
                                              ((quality < MIN_EXACT_QUALITY).sum(), "sliver triangles")) if n]
    if problems:
        raise InputError(f"method 'exact' needs a manifold, consistently oriented mesh without slivers; this one "
                         f"has {', '.join(problems)}: fix the mesh or use method 'heat' or 'graph'")


def clean_faces(F: np.ndarray) -> np.ndarray:
    """Faces (M, 3) without those that repeat a vertex or repeat another face's vertices
    (libigl's exact geodesics crash on both); the first of a repeated face is kept."""
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    _, first = np.unique(np.sort(F, axis=1), axis=0, return_index=True)
    return F[np.sort(first)]


def edge_spread(V: np.ndarray, F: np.ndarray) -> float:
    """Longest over median edge length of the mesh (inf when the median is 0)."""
    E = np.linalg.norm(V[F] - V[np.roll(F, 1, axis=1)], axis=2).ravel()
    median = float(np.median(E))
    return float(E.max()) / median if median > 0 else np.inf


def _graph_component(Vc, Fc, jobs):
    G = _edge_graph(Vc, Fc)
    return _dijkstra_offsets(G, [(idx, off) for _, idx, off in jobs])


# ----------------------------------------------------------------------------
# unreachable vertices
# ----------------------------------------------------------------------------
def _bridge_unreached(V: np.ndarray, D: np.ndarray) -> None:
    """In place: D[v, h] = min over the K nearest reached u of D[u, h] + |u - v|.

    Handles with the same unreached set share one k-d tree and one query
    (run on all cores: per-query results do not depend on the split)."""
    from scipy.spatial import cKDTree
    bad = ~np.isfinite(D)
    if not bad.any():
        return
    groups: dict[bytes, list[int]] = {}
    for h in np.flatnonzero(bad.any(axis=0)):
        groups.setdefault(np.packbits(bad[:, h]).tobytes(), []).append(int(h))
    for hs in groups.values():
        miss = bad[:, hs[0]]
        reached = np.flatnonzero(~miss)
        qi = np.flatnonzero(miss)
        k = min(_BRIDGE_K, len(reached))
        dist, nb = cKDTree(V[reached]).query(V[qi], k=k, workers=-1)
        dist = dist.reshape(len(qi), k)
        nb = reached[nb.reshape(len(qi), k)]
        Dh = np.ascontiguousarray(D[:, hs])               # (N, g): row gathers stay local
        D[np.ix_(qi, hs)] = np.min(Dh[nb] + dist[:, :, None], axis=1)


# ----------------------------------------------------------------------------
# public entry point
# ----------------------------------------------------------------------------
def distance_matrix(
    vertices,
    faces=None,
    point_handles=None,
    segment_handles=None,
    method: str | None = None,
    k_neighbours: int = 10,
    *,
    heat_t_factor: float = 1.0,
    visibility: bool = True,
    weld: bool = True,
) -> np.ndarray:
    """Distance from every vertex to every handle, ``(N, P+S)`` float64.

    vertices (N, 3); faces (F, 3) int or None (point cloud); point_handles
    (P, 3) or None; segment_handles (S, 2, 3) or None. Columns: points first,
    then segments. ``method`` None picks ``'heat'`` for a mesh and ``'knn'``
    for a point cloud. ``k_neighbours`` is the kNN graph's k. Result is
    finite, ``>= 0`` and ``>=`` the Euclidean distance. See the module
    docstring for the source, offset and unreachable-vertex rules; ``weld``
    merges coincident vertices first (see "Coincident vertices are welded").
    """
    V, F, P, S = _validate(vertices, faces, point_handles, segment_handles)
    if method is None:
        method = "heat" if F is not None else "knn"
    if method not in METHODS:
        raise InputError(f"unknown distance method {method!r}; choose one of {', '.join(METHODS)}")
    if method in ("heat", "exact", "graph") and F is None:
        raise InputError(f"method {method!r} needs faces; use 'knn' or 'euclidean' for a point cloud")
    if method == "knn" and (int(k_neighbours) != k_neighbours or k_neighbours < 1):
        raise InputError(f"k_neighbours must be a positive integer, got {k_neighbours!r}")
    if not (np.isfinite(heat_t_factor) and heat_t_factor > 0):
        raise InputError(f"heat_t_factor must be > 0, got {heat_t_factor!r}")
    if F is not None:
        F = clean_faces(F)
        if len(F) == 0:
            raise InputError("faces: every face repeats a vertex (the mesh has no area); use a point-cloud method")

    if weld and method != "euclidean":
        Vw, inv = weld_vertices(V)
        if len(Vw) < len(V):
            Fw = None
            if F is not None:
                Fw = inv[F]
                Fw = Fw[(Fw[:, 0] != Fw[:, 1]) & (Fw[:, 1] != Fw[:, 2]) & (Fw[:, 0] != Fw[:, 2])]
                if len(Fw) == 0:
                    raise InputError("every face is degenerate once coincident vertices are merged "
                                     "(the mesh has no area); use weld=False or a point-cloud method")
            D = distance_matrix(Vw, Fw, P, S, method, k_neighbours, heat_t_factor=heat_t_factor,
                                visibility=visibility, weld=False)
            return D[inv]

    E = euclidean_distances(V, P, S)
    if method == "euclidean":
        return E
    if method == "knn":
        sources = handle_sources(V, None, P, S, E=E)
        G = _knn_graph(V, int(k_neighbours))
        D = _dijkstra_offsets(G, sources)
    else:
        sources = handle_sources(V, F, P, S, visibility=visibility, E=E)
        comp = mesh_components(len(V), F)
        # libigl's geodesics run for hours (or exhaust memory) on a mesh with a stray far vertex
        spread = edge_spread(V, F) if method in ("heat", "exact") else 0.0
        if spread > MAX_EDGE_SPREAD and method == "exact":
            raise InputError(f"method 'exact': the longest edge is {spread:.3g} times the median edge (at most "
                             f"{MAX_EDGE_SPREAD:.0e}; a stray vertex?); fix the mesh or use method 'graph'")
        if spread > MAX_EDGE_SPREAD:
            warnings.warn(f"heat geodesics: the longest edge is {spread:.3g} times the median edge; using "
                          "graph distances", RuntimeWarning, stacklevel=2)
            method = "graph"
        solver = {"heat": _heat_component(heat_t_factor), "exact": exact_component,
                  "graph": _graph_component}[method]
        D = _per_component(V, F, comp, sources, solver)
    reached = np.isfinite(D)
    D[reached] = np.maximum(D[reached], E[reached])
    _bridge_unreached(V, D)
    D = np.maximum(D, E)
    if not np.isfinite(D).all():  # cannot happen: every handle has a source
        raise RuntimeError("internal error: non-finite distance left")
    return D


def arrival_parameters(V, faces, segments) -> np.ndarray:
    """(N, S) float64: for each vertex and bone, the parameter in [0, 1] on the bone of the
    source (:func:`handle_sources`) that the vertex's shortest path over the surface starts
    from: where a topological distance, and so the weight, "arrives" from.

    With surface distances the weight of bone i at v measures the path from the bone's
    nearest source, but the blend's handle point p_i(t) is otherwise the bone's Euclidean
    closest point to v: on a palm with two fingers, for the other finger's tip, the point
    beside the bent finger's tip (which moves most) instead of its base, where the path to
    the tip starts. Taking t where the path starts makes the handle point agree with the
    weight (:func:`nrpose.pose.blend.rest_terms` ``t``). V (N, 3); faces (M, 3) (graph: mesh
    edges, coincident vertices welded first) or None (graph: the symmetrised 10 nearest
    neighbours); segments (S, 2, 3). Dijkstra from a super-source joined to each source by
    its offset, each vertex's source found by pointer jumping on the predecessors; a vertex
    no path reaches keeps its closest-point parameter."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra
    X = np.asarray(V, np.float64)
    segs = np.asarray(segments, np.float64).reshape(-1, 2, 3)
    F = None if faces is None else np.asarray(faces, np.int64)
    Xw, inv = weld_vertices(X)
    if F is not None:
        F = inv[F]
        F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    n = len(Xw)
    G = (_edge_graph(Xw, F) if F is not None else _knn_graph(Xw, 10)).tocoo()
    t = segment_parameters(Xw, segs)
    for h, (idx, off) in enumerate(handle_sources(Xw, F, None, segs)[: len(segs)]):
        shift = 1.0 + float(np.max(off, initial=0.0))     # keeps every source edge positive
        A = sp.csr_matrix((np.r_[G.data, off + shift], (np.r_[G.row, np.full(len(idx), n)], np.r_[G.col, idx])),
                          shape=(n + 1, n + 1))
        d, pred = dijkstra(A, directed=True, indices=n, return_predecessors=True)
        reached = np.isfinite(d[:n])
        pred = pred[:n].copy()
        stop = (pred == n) | ~reached
        pred[stop] = np.flatnonzero(stop)
        while True:                                       # pointer jumping to the chain's source
            nxt = pred[pred]
            if np.array_equal(nxt, pred):
                break
            pred = nxt
        t[reached, h] = segment_parameters(Xw[pred[reached]], segs[h:h + 1])[:, 0]
    return t[inv]


def surface_distances(V: np.ndarray, faces, points: np.ndarray, segments: np.ndarray, method: str) -> np.ndarray:
    """(V, P + S) handle distances over the surface (or a kNN graph of a point cloud),
    :func:`distance_matrix`, cached on disk by content (:mod:`nrpose.bind.cache`)."""
    parts = binding_key_parts(V, faces, points, segments, {"distances": method})
    return cached(parts, lambda: {"D": distance_matrix(V, faces, points, segments, method=method)})["D"]
