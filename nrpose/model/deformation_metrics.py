"""Quality of a deformation: a rest mesh against posed frames, whatever method posed them.

Every function takes the rest vertices ``rest`` (N, 3) float64 and the posed vertices
``posed`` (N, 3) or a batch of frames (F, N, 3) (any real dtype; computed in float64)
and returns a value per frame (a leading F axis when frames were given). Lengths are in
the mesh's units; every metric below is dimensionless.

* :func:`edge_strain`: |ℓ/ℓ₀ − 1| of every mesh edge (0 under any rigid motion;
  |s − 1| under a uniform scale s). :func:`strain_summary` gives p50/p99/p99.9/max.
* :func:`signed_volume`: the closed-mesh volume (divergence theorem).
* :func:`region_volume_ratios`: volume kept per region of an open or closed surface, by
  the **bone-apex cone** rule: a region's volume is the signed volume of the cone from
  an apex (a point that moves rigidly with the region's bone, e.g. the bone's midpoint)
  to the region's triangles, ``Σ (a − o)·((b − o) × (c − o)) / 6``. It is exact under
  any rigid motion of the region with its bone, needs no capping of open limbs, and the
  regions of a closed mesh sharing one apex sum to :func:`signed_volume`.
* :func:`continuity_ratio`: the largest |Δ displacement| between neighbours (mesh edges,
  or any pairs) divided by their rest distance: ≤ 2 for any rigid motion, ≤ the local
  Lipschitz constant of (deformation − identity) for a smooth deformation, and ≈ jump /
  spacing (large) across a discontinuity.
* :func:`weight_groups` and :func:`group_rigidity`: parts whose vertices share one set
  of weights, and their largest in-group edge strain (0 when the part moves rigidly).
* :func:`bone_clearance_ratios`: per-vertex distance to the local posed skeleton over the
  rest one; its minimum is the **joint collapse** (1: none, 0: the surface reaches the
  bone) and its maximum minus 1 the **bulge** (largest outward offset beyond the rest
  radius, relative to that radius).
"""
from __future__ import annotations

import numpy as np

from ..checks import real_rows, triangles
from ..errors import InputError

PERCENTILES = {"p50": 50.0, "p99": 99.0, "p99.9": 99.9, "max": 100.0}


def mesh_edges(faces, n_vertices: int) -> np.ndarray:
    """Unique undirected edges (E, 2) int64 (smaller index first) of triangles (M, 3)."""
    F = triangles(faces, n_vertices)
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    return np.unique(E[E[:, 0] != E[:, 1]], axis=0)


def measurable_edges(vertices, edges, fraction: float = 0.1) -> np.ndarray:
    """The edges (E', 2) at least ``fraction`` × the median rest edge length long.

    Meshes from marching cubes or scans hold near-coincident vertices (edges of 1e-16 m):
    their relative strain and continuity ratio measure rounding, not the deformation."""
    V = np.asarray(vertices, np.float64)
    E = np.asarray(edges, np.int64).reshape(-1, 2)
    l0 = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    return E[l0 >= fraction * np.median(l0)] if len(E) else E


def frames_of(rest: np.ndarray, posed) -> tuple[np.ndarray, bool]:
    """posed as float64 (F, N, 3) and whether a single frame (N, 3) was given."""
    P = np.asarray(posed, dtype=np.float64)
    single = P.ndim == 2
    P = P[None] if single else P
    if P.ndim != 3 or P.shape[1:] != rest.shape:
        raise InputError(f"posed vertices: expected shape {rest.shape} or (F,) + {rest.shape}, got {np.shape(posed)}")
    if not np.isfinite(P).all():
        raise InputError("posed vertices contain NaN or infinite values")
    return P, single


def _pairs_of(rest, posed, pairs):
    """Checked rest (N, 3) and posed (F, N, 3) float64, whether one frame was given, and the
    vertex pairs (E, 2) int64 of non-zero rest length with those lengths (E,)."""
    V = real_rows(rest, "rest vertices")
    P, single = frames_of(V, posed)
    E = np.asarray(pairs, np.int64).reshape(-1, 2)
    l0 = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    return V, P, single, E[l0 > 0], l0[l0 > 0]


def edge_strain(rest, posed, edges) -> np.ndarray:
    """|ℓ/ℓ₀ − 1| per edge: (E,) for one frame or (F, E). Edges of zero rest length are dropped."""
    _, P, single, E, l0 = _pairs_of(rest, posed, edges)
    s = np.abs(np.linalg.norm(P[:, E[:, 0]] - P[:, E[:, 1]], axis=2) / l0 - 1.0)
    return s[0] if single else s


def strain_summary(strain) -> dict:
    """p50, p99, p99.9 and max (float) of strains (any shape, pooled)."""
    s = np.asarray(strain, np.float64).ravel()
    if s.size == 0:
        return {k: 0.0 for k in PERCENTILES}
    return {k: float(np.percentile(s, q)) for k, q in PERCENTILES.items()}


def signed_volume(vertices, faces) -> np.ndarray | float:
    """Signed volume of a closed triangle mesh: float for (N, 3) vertices, (F,) for frames (F, N, 3)."""
    X = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    a, b, c = X[..., F[:, 0], :], X[..., F[:, 1], :], X[..., F[:, 2], :]
    vol = np.einsum("...ij,...ij->...i", a, np.cross(b, c)).sum(axis=-1) / 6.0
    return float(vol) if np.ndim(vol) == 0 else vol


def cone_volumes(vertices, faces, face_region, apex) -> np.ndarray:
    """Signed cone volumes (..., R): apex[..., r] (R, 3) to the faces of region r.

    vertices (..., N, 3); faces (M, 3); face_region (M,) int in [0, R) (−1: no region)."""
    X = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    reg = np.asarray(face_region, np.int64)
    apex = np.asarray(apex, np.float64)
    keep = reg >= 0
    F, reg = F[keep], reg[keep]
    o = apex[..., reg, :]
    a, b, c = (X[..., F[:, k], :] - o for k in range(3))
    tet = np.einsum("...ij,...ij->...i", a, np.cross(b, c)) / 6.0
    out = np.zeros(tet.shape[:-1] + (apex.shape[-2],))
    np.add.at(np.moveaxis(out, -1, 0), reg, np.moveaxis(tet, -1, 0))
    return out


def region_volume_ratios(rest, posed, faces, face_region, apex_rest, apex_posed) -> np.ndarray:
    """Posed over rest bone-apex cone volume per region: (R,) or (F, R) (see the module docstring).

    face_region: (M,) region of each face (−1: none); apex_rest (R, 3); apex_posed (R, 3)
    or (F, R, 3): the apex moved with its region's bone. A region of zero rest volume gets NaN."""
    V = real_rows(rest, "rest vertices")
    P, single = frames_of(V, posed)
    v0 = cone_volumes(V, faces, face_region, apex_rest)
    ap = np.asarray(apex_posed, np.float64)
    v1 = cone_volumes(P, faces, face_region, ap if ap.ndim == 3 else ap[None])
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(np.abs(v0) > 0, v1 / np.where(v0 != 0, v0, 1.0), np.nan)
    return r[0] if single else r


def continuity_ratio(rest, posed, pairs) -> np.ndarray:
    """Per pair |Δ(posed − rest)| / |Δ rest|: (E,) or (F, E). Pairs of zero rest distance are dropped."""
    V, P, single, E, l0 = _pairs_of(rest, posed, pairs)
    D = P - V[None]
    r = np.linalg.norm(D[:, E[:, 0]] - D[:, E[:, 1]], axis=2) / l0
    return r[0] if single else r


def weight_groups(weights, min_size: int = 3, decimals: int = 6) -> np.ndarray:
    """Label (N,) int64 of each vertex's weight set: vertices whose weight rows (N, H) agree to
    ``decimals`` places share a label; sets held by fewer than ``min_size`` vertices get −1.
    Rows are normalised to sum 1 first (zero rows get −1)."""
    W = np.asarray(weights, np.float64)
    s = W.sum(axis=1, keepdims=True)
    key = np.round(W / np.where(s > 0, s, 1.0), decimals) + 0.0
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    labels = np.where((counts[inv] >= min_size) & (s[:, 0] > 0), inv, -1)
    return labels.astype(np.int64)


def group_rigidity(rest, posed, edges, labels) -> np.ndarray:
    """Largest edge strain among edges whose two ends carry the same group label (≥ 0):
    float per frame ((), or (F,)); 0 when no edge lies inside a group."""
    lab = np.asarray(labels, np.int64)
    E = np.asarray(edges, np.int64).reshape(-1, 2)
    inside = E[(lab[E[:, 0]] == lab[E[:, 1]]) & (lab[E[:, 0]] >= 0)]
    V = real_rows(rest, "rest vertices")
    P, single = frames_of(V, posed)
    if len(inside) == 0:
        out = np.zeros(len(P))
    else:
        out = edge_strain(V, P, inside).max(axis=1)
    return out[0] if single else out


def segment_distances(X: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distances (..., N, S) from points X (..., N, 3) to segments (..., S, 2, 3)."""
    a = segments[..., 0, :]
    ab = segments[..., 1, :] - a
    rel = X[..., :, None, :] - a[..., None, :, :]
    L2 = np.einsum("...sk,...sk->...s", ab, ab)
    t = np.einsum("...nsk,...sk->...ns", rel, ab) / np.where(L2 > 0, L2, 1.0)[..., None, :]
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * ab[..., None, :, :], axis=-1)


def bone_neighbours(segments, tol: float = 1e-6) -> np.ndarray:
    """(S, S) bool: bones sharing an end point (within tol × the skeleton's size), and each bone itself."""
    S = np.asarray(segments, np.float64)
    ends = S.reshape(-1, 3)
    size = max(float(np.ptp(ends, axis=0).max()), 1e-12)
    d = np.linalg.norm(ends[:, None] - ends[None], axis=2) <= tol * size
    n = len(S)
    return d.reshape(n, 2, n, 2).any(axis=(1, 3)) | np.eye(n, dtype=bool)


def bone_clearance_ratios(rest, posed, bones_rest, bones_posed, floor: float = 0.25,
                          chunk: int = 4096) -> np.ndarray:
    """Per-vertex clearance ratio d_posed / d_rest: (N,) or (F, N); NaN where not measured.

    d is the distance from a vertex to its *local skeleton*: the bone nearest to it at rest
    and the bones sharing an end with that bone, the same bones at rest and posed.
    bones_rest (S, 2, 3); bones_posed (S, 2, 3) or (F, S, 2, 3). Vertices closer to their
    local skeleton than ``floor`` × the median rest distance are not measured (the ratio of
    two tiny distances says nothing about collapse). min → joint collapse, max − 1 → bulge.
    """
    V = real_rows(rest, "rest vertices")
    P, single = frames_of(V, posed)
    B0 = np.asarray(bones_rest, np.float64)
    B1 = np.asarray(bones_posed, np.float64)
    B1 = B1 if B1.ndim == 4 else np.broadcast_to(B1, (len(P),) + B1.shape)
    nb = bone_neighbours(B0)
    out = np.full((len(P), len(V)), np.nan)
    d0_all = np.empty(len(V))
    local_all = np.empty((len(V), len(B0)), bool)
    for a in range(0, len(V), chunk):
        D0 = segment_distances(V[a:a + chunk], B0)
        local = nb[np.argmin(D0, axis=1)]
        local_all[a:a + chunk] = local
        d0_all[a:a + chunk] = np.where(local, D0, np.inf).min(axis=1)
    keep = d0_all >= floor * np.median(d0_all)
    for a in range(0, len(V), chunk):
        sl = slice(a, min(a + chunk, len(V)))
        D1 = segment_distances(P[:, sl], B1)
        d1 = np.where(local_all[sl][None], D1, np.inf).min(axis=2)
        out[:, sl] = np.where(keep[sl][None], d1 / np.where(keep[sl], d0_all[sl], 1.0)[None], np.nan)
    return out[0] if single else out
