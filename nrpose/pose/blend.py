"""The near-rigid MLS blend (Jeong & Kim), split into rest-only terms and a pose.

For a point v and handles i (rest p_i, posed q_i), with normalised weights
ŵ_i = w_i / Σ w_i, ``w_i = 1 / d_i(v)^(2α)``::

    p* = Σ ŵ_i p_i          q* = Σ ŵ_i q_i          p̂_i = p_i − p*
    R  = blend of the handles' rotations r_i with levers λ_i
    v' = R (v − p*) + q*

A segment handle acts as the point of the rest segment closest to v (parameter
t), and as the point at the same t on the posed segment.

Levers (``lever=``): the paper weighs each rotation by ``w_i |p̂_i|²``, the squared
length of the vector whose direction change defines r_i. That is right for a
point handle, but for a segment the rotation is the segment's own and p̂_i is
the offset of its closest point from p*, which *vanishes for the bone nearest
to v*: the nearest bone loses its say and distant bones take over the rotation
(a cylinder bent 90° at a joint kept 26 % of its volume). A segment carries
its whole rotation whatever its offset, so nrpose gives it a lever that does
not vanish and does not grow with distance:

* ``"weight"`` (default): ``w_i L²``, with one length L for every segment (the
  mean rest segment length, so that point-handle levers ``w |p̂|²`` stay on the
  same scale). Among segments the rotation blend then follows the weights: a
  vertex weighted 70 % on a finger bone takes 70 % of its rotation from it.
* ``"length"``: ``w_i ℓ_i²``, each segment's own squared length. Equal to
  ``"weight"`` when all segments are equally long, but long bones outweigh
  short heavily weighted ones (on the Mannequin, a vertex 71 % on a 2.6 cm
  finger bone took 11 % of its rotation from it).
* ``"paper"``: the literal ``w_i |p̂_i|²`` for segments too.

Point handles always use ``w_i |p̂_i|²``.

Blends (``blend=``; the default, :func:`default_blend`: ``"quaternion"`` on rigs with
segments, ``"relative"`` on point handles only): ``"quaternion"`` is the normalised lever-weighted
sum of the handles' unit quaternions, ``R = Σ λ̃_i s_i Q_i / |Σ λ̃_i s_i Q_i|``, with
**one sign s_i per segment and pose for every point**: along a spanning tree of the
segments' co-influence (:func:`sign_tree`, rest only: a maximum spanning forest of
``A_ij = Σ_v ŵ_i ŵ_j``), each Q_i is put in the hemisphere of its tree parent's
(:func:`tree_signs`). The sum ``a(v) = Σ λ̃_i s_i Q_i`` is then as continuous as the
levers, and so is R wherever |a| > 0, at any spread of the rotations. Bound (points v,
v + δ, to first order): the displacement difference over the rest distance is at most

    2 + L_p* + L_q* + 2 |u| L_λ / |a|,

L_p*, L_q*, L_λ the Lipschitz constants of p*(v), q*(v) and the levers (1-norm), since a
rotation matrix moves at most twice as fast as its unit quaternion and
|d(a/|a|)| ≤ |da|/|a| ≤ |dλ̃|₁/|a|. Where the co-influencing segments' signed
quaternions have pairwise non-negative dot products, |a| ≥ |λ̃|₂ ≥ 1/√k (k segments with
a lever at v). A global rotation G multiplies every Q_i by one unit quaternion, which
keeps the dot products and so the signs: the blend is equivariant; equal rotations get
equal signs: a rigid motion is reproduced. It agrees with the relative blend to second
order in the spread of the rotations (the chordal mean) and costs less on the device (no
logarithms). A point handle contributes Q_ref ⊗ m_i, m_i the minimal rotation taking p̂_i
onto R_ref⁻¹ q̂_i, Q_ref the (tree-signed) quaternion of the point's reference rotation;
segments seen from the global reference R_g take the hemisphere of R_g's quaternion.
Where the levers all vanish, R = R_ref.

``"relative"`` averages in the tangent space of a per-point reference rotation R_ref:
``R = R_ref exp(Σ λ̃_i log(R_ref⁻¹ R_i))``. R_ref is the rotation of the handle
with the largest lever when that is a segment. A point handle has no rotation
of its own (only a direction pair), so points dominated by a point handle use
the global rotation R_g, the least-squares rotation of all handle positions
(rows: point handles, segment ends) from rest to pose. A point handle's relative
rotation is the minimal rotation taking p̂_i onto the direction of
``R_ref⁻¹ q̂_i``. Every term then turns with a global rotation G of the posed
handles (R_ref → G R_ref, q* → G q*), so G commutes with the deformation. Its
reference is discrete: where three or more handles with different rotations meet
with comparable levers it jumps where the dominant handle changes.
``"paper"`` averages rotation vectors, ``R = exp(Σ λ̃_i r_i)`` (the relative blend
with R_ref = I), which is not equivariant: a global turn of the posed handles by a
large angle does not commute with the deformation.

Segment parameters (``t=`` of :func:`rest_terms`): by default each point takes the
closest point of each rest segment; a binding may give other rest-only parameters
(the same for a part that must move rigidly, :func:`nrpose.bind.bone_weights.bone_weights`;
where surface paths arrive for topological weights, :func:`nrpose.bind.distances.arrival_parameters`).
Equivariance and rigid-motion reproduction hold for any rest-only t.

Everything here is float64 numpy. :func:`rest_terms` is computed once per
binding (the engine uploads it to the device); :func:`pose_reference` is the
float64 reference of the device's pose kernel.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import os
from dataclasses import dataclass

import numpy as np

from ..checks import coordinates
from ..errors import InputError
from ..options import BLENDS, DEFAULT_BLEND
from ..model.handles import HandleSet, Pose, check_alpha
from ..model.rotation import Rotation, covariance_rotation, minimal_quat, minimal_rotvec, quat_multiply, relative_rotvec_table
from ..bind.distances import segment_parameters
from ..bind.weights import dense_weights, keep_top_k


def default_blend(rest: HandleSet) -> str:
    """The default blend of a rig: :data:`DEFAULT_BLEND` with segment handles; ``"relative"``
    on point handles only, where every point's reference is R_g, one rotation for all points
    (the reference never switches: the blend is continuous), and whose tuned device path poses
    the Table-1 point rows 1.3-2x faster than the quaternion blend's."""
    return DEFAULT_BLEND if len(rest.segments) else "relative"
LEVERS = ("weight", "length", "paper")


@dataclass(frozen=True)
class RestTerms:
    """Rest-only quantities of a binding, per point (N points, P point handles,
    S segment handles, H = P + S; handle columns are points first).

    weights: (N, H) normalised blend weights ŵ (rows sum to 1).
    t:       (N, S) closest-point parameter on each rest segment, in [0, 1].
    p_star:  (N, 3) weighted rest centroid p*.
    u:       (N, 3) v − p*.
    lever:   (N, H) normalised levers λ̃ (rows sum to 1, or all 0 when every
             lever vanishes: then R = R_ref).
    ref:     (N,) int, reference rotation: segment index in [0, S), or S for
             the global rotation R_g.
    phat:    (N, P, 3) p̂_i = p_i − p* of the point handles.
    """

    weights: np.ndarray
    t: np.ndarray
    p_star: np.ndarray
    u: np.ndarray
    lever: np.ndarray
    ref: np.ndarray
    phat: np.ndarray


def segment_levers(rest: HandleSet, lever: str) -> np.ndarray:
    """Per-segment lever factor (S,): L² (mean rest length, rule "weight") or ℓ_i² ("length")."""
    lengths2 = np.sum((rest.segments[:, 1] - rest.segments[:, 0]) ** 2, axis=1)
    if lever == "weight" and len(lengths2):
        return np.full_like(lengths2, np.mean(np.sqrt(lengths2)) ** 2)
    return lengths2


def handle_points(handles: HandleSet, t: np.ndarray) -> np.ndarray:
    """Per-point handle positions (N, H, 3): point handles, then segments at parameters t (N, S)."""
    n = len(t)
    pts = np.broadcast_to(handles.points[None], (n,) + handles.points.shape)
    a = handles.segments[:, 0]
    seg = a[None] + t[..., None] * (handles.segments[:, 1] - a)[None]
    return np.concatenate([pts, seg], axis=1)


def _check_matrix(m, shape, what: str) -> np.ndarray:
    try:
        m = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected a numeric matrix of shape {shape}") from None
    if m.shape != shape:
        raise InputError(f"{what}: expected shape {shape} (points × handles), got {m.shape}")
    if not np.isfinite(m).all() or (m < 0).any():
        raise InputError(f"{what}: entries must be finite and non-negative")
    return m


def rest_terms(points, rest: HandleSet, alpha: float = 1.0, lever: str = "weight",
               distances=None, weights=None, k: int | None = None, per_block=None, t=None):
    """Rest-only terms of the blend for points (N, 3) and rest handles: RestTerms.

    distances: optional (N, H) distances replacing the Euclidean ones (e.g.
    geodesic). weights: optional (N, H) non-negative weights used as w_i
    directly (e.g. authored skin weights); excludes ``distances``. k: keep
    only the k most influential handles of each point (None: all).
    per_block: optional function of the RestTerms of a block of points returning
    a dict of per-point arrays (first axis: the block's points); then the result
    is that dict for all points, and the dense (N, H) terms never exist for all
    points at once (the OpenCL deformer's bind, :func:`nrpose.pose.mls.slot_terms`).
    t: optional (N, S) segment parameters in [0, 1] replacing the closest-point ones
    (rest-only; the module docstring).
    """
    v = coordinates(points, "points")
    alpha = check_alpha(alpha)
    if lever not in LEVERS:
        raise InputError(f"lever must be one of {LEVERS}, got {lever!r}")
    if distances is not None and weights is not None:
        raise InputError("give either distances or weights, not both")
    n, H = len(v), rest.count
    if weights is not None:
        w_all = _check_matrix(weights, (n, H), "weights")
        sums = w_all.sum(axis=1)
        if (sums <= 0).any():
            raise InputError(f"weights: {int((sums <= 0).sum())} point(s) have no positive weight; "
                             "every point needs at least one influencing handle")
    elif distances is not None:
        d_all = _check_matrix(distances, (n, H), "distances")
    if t is not None:
        if weights is None and distances is None:
            raise InputError("t (segment parameters) needs weights= or distances= (the Euclidean "
                             "weights are those of the closest points)")
        t_all = _check_matrix(t, (n, len(rest.segments)), "t")
        if (t_all > 1).any():
            raise InputError("t: segment parameters must lie in [0, 1]")

    def block(a: int) -> tuple[slice, dict]:
        b = slice(a, min(a + BLOCK, n))
        given = w_all[b] if weights is not None else None
        dist = d_all[b] if distances is not None else None
        T = _rest_block(v[b], rest, alpha, lever, dist, given, k, t_all[b] if t is not None else None)
        return b, (per_block(T) if per_block is not None
                   else {f: getattr(T, f) for f in RestTerms.__dataclass_fields__})

    # bounded memory: (block, H, 3) temporaries, results filled in place; blocks run on
    # the machine's cores (numpy releases the GIL in the array operations)
    out: dict[str, np.ndarray] = {}
    starts = range(0, n, BLOCK)
    workers = min(len(starts), os.cpu_count() or 1, MAX_WORKERS)
    with concurrent.futures.ThreadPoolExecutor(workers) if workers > 1 else contextlib.nullcontext() as pool:
        for b, blk in (pool.map(block, starts) if pool is not None else map(block, starts)):
            for f, part in blk.items():
                if f not in out:
                    out[f] = np.empty((n,) + part.shape[1:], part.dtype)
                out[f][b] = part
    return out if per_block is not None else RestTerms(**out)


#: points per block of rest_terms' computation (a character of 16k vertices in 4 blocks, so the
#: machine's cores share it and fewer temporaries are alive at once)
BLOCK = 4096
#: blocks computed at once (each holds ~12 H float64 values per point of temporaries:
#: ~25 MB per block in flight for 64 handles)
MAX_WORKERS = 4


def _rest_block(v, rest: HandleSet, alpha, lever, distances, weights, k, t) -> RestTerms:
    """rest_terms for one block of points (inputs already validated; t None: closest points)."""
    P, S = len(rest.points), len(rest.segments)
    if t is None:
        t = segment_parameters(v, rest.segments)
    p = handle_points(rest, t)
    if weights is not None:
        w = weights / weights.sum(axis=1, keepdims=True)
    else:
        if distances is None:
            diff = v[:, None, :] - p
            d = np.sqrt(np.einsum("nhk,nhk->nh", diff, diff))
        else:
            d = distances
        w = dense_weights(d, alpha)
    w = keep_top_k(w, k)
    p_star = np.einsum("nh,nhk->nk", w, p)
    phat = p - p_star[:, None, :]
    lev = w * np.einsum("nhk,nhk->nh", phat, phat)
    if lever != "paper":
        lev[:, P:] = w[:, P:] * segment_levers(rest, lever)[None]
    total = lev.sum(axis=1, keepdims=True)
    lev = np.where(total > 0, lev / np.where(total > 0, total, 1.0), 0.0)
    dominant = np.where(total[:, 0] > 0, lev.argmax(axis=1), w.argmax(axis=1))
    ref = np.where(dominant >= P, dominant - P, S).astype(np.int32)
    return RestTerms(weights=w, t=t, p_star=p_star, u=v - p_star, lever=lev, ref=ref,
                     phat=phat[:, :P].copy())


def reference_rotations(rest: HandleSet, pose: Pose, blend: str) -> Rotation:
    """The S + 1 reference rotations: each segment's, then the global one.

    ``"paper"``: all identity (the paper blends absolute rotation vectors).
    ``"relative"``: segment rotations, then R_g (Kabsch fit of all handle
    positions, point handles and segment ends, rest → pose).
    """
    if blend not in BLENDS:
        raise InputError(f"blend must be one of {BLENDS}, got {blend!r}")
    S = len(rest.segments)
    if blend == "paper":
        return Rotation.identity(S + 1)
    mats = np.concatenate([pose.rotations, global_rotation(rest, pose)[None]])
    return Rotation.from_matrix(mats)


def global_rotation(rest: HandleSet, pose: Pose) -> np.ndarray:
    """R_g (3, 3): least-squares rotation of all handle positions (point handles
    and segment ends, unweighted) from rest to pose; see :func:`nrpose.rotation.kabsch`.
    Posing many frames, keep a :class:`GlobalRotation`."""
    return GlobalRotation(rest)(pose)


class GlobalRotation:
    """:func:`global_rotation` of any pose of the rest handles, their rest side
    (centred positions) computed once.

    The posed positions need no centring: with the rest positions p_k centred,
    Σ (q_k − q̄) p_kᵀ = Σ (q_k − o) p_kᵀ for any o. They are taken relative to one
    posed handle o (not the origin: the rest side sums to zero only to rounding,
    and far from the origin that rounding times |q| would reach the fit).
    Per pose that leaves one (3, M) product and
    :func:`nrpose.rotation.covariance_rotation`. The OpenCL deformer runs the
    same fit on the device (kernels/global_fit.h, :class:`nrpose.pose.mls.GlobalFit`)
    from ``centred`` and ``scale2``; this is its float64 reference.

    centred: (M, 3) float64 rest positions (point handles, then segment ends) minus
    their mean; scale2: the largest |component|² of ``centred`` (the scale of the
    fit's tie tolerance, see covariance_rotation).
    """

    def __init__(self, rest: HandleSet):
        P0 = np.concatenate([rest.points, rest.segments.reshape(-1, 3)])
        self.centred = P0 - P0.mean(axis=0)
        self.scale2 = float(np.abs(self.centred).max() ** 2)

    def __call__(self, pose: Pose) -> np.ndarray:
        h = pose.handles
        q = np.concatenate([h.points, h.segments.reshape(-1, 3)])
        return covariance_rotation((q - q[0]).T @ self.centred, self.scale2)


def rotation_table(rest: HandleSet, pose: Pose, blend: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose rotation data for the kernel.

    Returns (refs (S+1, 3, 3) reference rotation matrices, table (S+1, S, 3))
    with table[j, i] = log(R_ref_j⁻¹ R_i), the rotation vector of segment i
    relative to reference j.
    """
    refs = reference_rotations(rest, pose, blend)
    S = len(rest.segments)
    if blend == "paper":
        logs = Rotation.from_matrix(pose.rotations).as_rotvec() if S else np.zeros((0, 3))
        table = np.broadcast_to(logs[None], (S + 1, S, 3)).copy()
    else:
        table = relative_rotvec_table(refs.as_quat())[:, :S]
    return refs.as_matrix(), table


def pose_reference(terms: RestTerms, rest: HandleSet, pose: Pose, blend: str | None = None,
                   tree: np.ndarray | None = None) -> np.ndarray:
    """Float64 reference of the pose kernel: posed points (N, 3).

    blend: one of :data:`BLENDS` (None: :func:`default_blend`); tree: the quaternion blend's
    :func:`sign_tree` (None: that of ``terms.weights``)."""
    rest.same_layout(pose.handles, "posed handles")
    blend = default_blend(rest) if blend is None else blend
    P = len(rest.points)
    q = handle_points(pose.handles, terms.t)
    q_star = np.einsum("nh,nhk->nk", terms.weights, q)
    if blend == "quaternion":
        if tree is None:
            tree = sign_tree(terms.weights[:, P:])
        return quaternion_rotations(terms, rest, pose, q, q_star, tree).apply(terms.u) + q_star
    refs, table = rotation_table(rest, pose, blend)
    R_ref = refs[terms.ref]                                         # (N, 3, 3)
    r = np.einsum("ns,nsk->nk", terms.lever[:, P:], table[terms.ref])
    if P:
        qhat = q[:, :P] - q_star[:, None, :]
        local = np.einsum("nji,npj->npi", R_ref, qhat)              # R_ref⁻¹ q̂_i
        r += np.einsum("np,npk->nk", terms.lever[:, :P], minimal_rotvec(terms.phat, local))
    rot = Rotation.from_matrix(R_ref) * Rotation.from_rotvec(r)
    return rot.apply(terms.u) + q_star


#: |Σ λ̃_i s_i Q_i| below this (the levers all vanish): R = R_ref
QUAT_FLOOR = 1e-6
#: co-influences equal to this relative precision are ties of the sign tree (broken by index),
#: so that summation order does not change the tree
TREE_DIGITS = 9


def sign_tree(segment_weights) -> np.ndarray:
    """The quaternion blend's sign tree: int64 (S, 2) rows (segment, parent), parents first,
    parent −1 at each root (rest only).

    segment_weights: (N, S) weights ŵ of the segments (dense, or scipy sparse). A maximum
    spanning forest of the co-influence ``A_ij = Σ_v ŵ_i ŵ_j`` (Kruskal, ties broken by
    index after rounding A to :data:`TREE_DIGITS` significant digits), each tree rooted at
    its segment of largest total weight, listed breadth first."""
    import scipy.sparse as sp

    W = sp.csr_matrix(segment_weights, dtype=np.float64)
    S = W.shape[1]
    A = (W.T @ W).toarray()
    total = np.asarray(W.sum(axis=0)).ravel()
    scale = max(float(A.max(initial=0.0)), 1e-300)
    A = np.round(A / scale, TREE_DIGITS)
    iu, ju = np.triu_indices(S, 1)
    keep = A[iu, ju] > 0
    iu, ju, aw = iu[keep], ju[keep], A[iu[keep], ju[keep]]
    root = np.arange(S)

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    adj: list[list[int]] = [[] for _ in range(S)]
    for e in np.lexsort((ju, iu, -aw)):                 # heaviest first, then by index
        a, b = find(int(iu[e])), find(int(ju[e]))
        if a != b:
            root[a] = b
            adj[iu[e]].append(int(ju[e]))
            adj[ju[e]].append(int(iu[e]))
    rows, seen = [], np.zeros(S, bool)
    for r in np.lexsort((np.arange(S), -np.round(total / max(total.max(initial=0.0), 1e-300), TREE_DIGITS))):
        if seen[r]:
            continue
        seen[r] = True
        queue = [(int(r), -1)]
        while queue:
            node, parent = queue.pop(0)
            rows.append((node, parent))
            for c in sorted(adj[node]):
                if not seen[c]:
                    seen[c] = True
                    queue.append((c, node))
    return np.array(rows, np.int64).reshape(S, 2)


def tree_signs(quats: np.ndarray, tree: np.ndarray) -> np.ndarray:
    """Signs (S,) putting each segment's unit quaternion (quats (S, 4)) in the hemisphere of
    its signed tree parent's (tree: :func:`sign_tree`)."""
    s = np.ones(len(quats))
    for i, p in tree:
        if p >= 0 and s[p] * (quats[i] @ quats[p]) < 0:
            s[i] = -1.0
    return s


def quaternion_rotations(terms: RestTerms, rest: HandleSet, pose: Pose, q: np.ndarray,
                         q_star: np.ndarray, tree: np.ndarray) -> Rotation:
    """Per-point rotations (N) of the ``"quaternion"`` blend (see the module docstring).

    q: (N, H, 3) posed handle points, q_star: (N, 3) posed centroids; tree: :func:`sign_tree`."""
    P, S = len(rest.points), len(rest.segments)
    Q = reference_rotations(rest, pose, "relative").as_quat()          # (S + 1, 4)
    Q[:S] *= tree_signs(Q[:S], tree)[:, None]
    Q_ref = Q[terms.ref]                                              # (N, 4)
    # segments keep their tree signs; seen from R_g (ref S) they take its hemisphere
    sign = np.where((terms.ref[:, None] == S) & (Q_ref @ Q[:S].T < 0), -1.0, 1.0)
    acc = np.einsum("ns,sk->nk", terms.lever[:, P:] * sign, Q[:S])
    if P:
        R_ref = Rotation.from_quat(Q_ref).as_matrix()
        local = np.einsum("nji,npj->npi", R_ref, q[:, :P] - q_star[:, None, :])   # R_ref⁻¹ q̂_i
        acc += np.einsum("np,npk->nk", terms.lever[:, :P], quat_multiply(Q_ref[:, None], minimal_quat(terms.phat, local)))
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return Rotation.from_quat(np.where(norm > QUAT_FLOOR, acc, Q_ref))


def deform_reference(points, rest: HandleSet, pose: Pose, alpha: float = 1.0, blend: str | None = None,
                     lever: str = "weight", distances=None, weights=None, k: int | None = None) -> np.ndarray:
    """One-shot float64 reference deformation: posed points (N, 3)."""
    terms = rest_terms(points, rest, alpha, lever, distances, weights, k)
    return pose_reference(terms, rest, pose, blend)
