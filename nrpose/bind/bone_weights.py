"""Bone weights of a character: the one place posing and ``nrpose weights`` get them from.

:func:`bone_weights` turns a character and a weights method into (V, B) weights
of all its vertices (meshes concatenated in file order,
:func:`nrpose.model.meshset.concatenate_meshes`) on the bones of
:meth:`nrpose.model.skeleton.Skeleton.bones`:

* ``authored``: the file's skin weights. A vertex's weight on joint j becomes
  weight on j's bones, shared between them by inverse squared distance (a
  joint's bones all move with its rigid transform, so any split keeps that
  motion exact); a weighted joint that drives no bone hands its weight to its
  nearest ancestor that does.
* ``euclidean``: straight-line distance ``d`` to the bone segments, then
  ``w = 1/d^(2α)`` normalised per vertex (:func:`nrpose.bind.weights.dense_weights`).
* ``heat``, ``exact``, ``graph``: the same with distances over the surface of
  the deforming meshes together (:func:`nrpose.bind.distances.distance_matrix`,
  cached on disk by content, :func:`nrpose.bind.distances.surface_distances`).

Then each vertex keeps its ``k`` most influential bones (renormalised; the
others are 0). Default: all bones up to :data:`SKELETON_K`, else ``SKELETON_K``.

With the weights come the segment parameters ``t`` the NR-MLS blend should take
(:func:`nrpose.pose.blend.rest_terms` ``t``; rest-only, so that equivariance and
rigid motions are kept):

* ``authored``: a part whose vertices all carry one set of skin weights (a weight
  group, :func:`nrpose.model.deformation_metrics.weight_groups`, at least 3 vertices)
  takes its parameters, and its split of each joint's weight among the joint's bones,
  at the group's centroid: the whole part then has one p* − R⁻¹q* and one rotation,
  and moves rigidly, as under DQS (elsewhere the closest points of the vertices).
* ``heat``, ``exact``, ``graph``: where each bone's surface path to the vertex starts
  (:func:`nrpose.bind.distances.arrival_parameters`), so that the handle point agrees
  with the weight (the other finger's tip no longer follows the bent finger's tip).
* ``euclidean``: the closest points (``t`` None).

A mesh attached rigidly to a joint does not deform: its vertices get weight 1
on the first bone of that joint (or of its nearest ancestor that drives a bone)
and their Euclidean bone distances.

:func:`with_skin_weights` gives a character skin weights from elsewhere (a
libigl weight DMAT, :func:`nrpose.io.tgf.read_dmat_weights`); ``authored``
then means those.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..model.handles import check_alpha
from ..model.deformation_metrics import weight_groups
from ..model.meshset import MeshSet, concatenate_meshes, submesh_faces
from ..model.skeleton import Bones
from ..options import WEIGHTS
from .distances import arrival_parameters, point_segment_distances, segment_parameters, surface_distances
from .weights import dense_weights, keep_top_k

__all__ = ["WEIGHTS", "SKELETON_K", "BoneWeights", "bone_weights", "authored_joint_weights", "authored_bone_weights",
           "skin_entries", "group_centers", "with_skin_weights", "joint_weights"]

SKELETON_K = 8        # bones kept per vertex by default on skeletons with more bones


@dataclass(frozen=True)
class BoneWeights:
    """weights (V, B) float64 rows summing to 1 (at most ``k`` non-zero); distances (V, B)
    float64 vertex-to-bone distances (over the surface for deforming vertices with heat,
    exact, graph; else straight-line), or None where not asked for; bones; k (bones kept per vertex, B when dense);
    alpha; meshes: the concatenated meshes the rows belong to; t: (V, B) float64 segment
    parameters in [0, 1] for the NR-MLS blend (module docstring), or None (closest points)."""

    weights: np.ndarray
    distances: np.ndarray | None
    bones: Bones
    k: int
    alpha: float
    meshes: MeshSet
    t: np.ndarray | None = None


def bone_weights(character, weights: str = "authored", k: int | str | None = None,
                 alpha: float = 1.0, parameters: bool = True, distances: bool = True) -> BoneWeights:
    """Weights of a character's vertices on its bones (see the module docstring).

    weights: one of :data:`WEIGHTS`; k: bones kept per vertex (a positive integer, "all",
    or None for the default); alpha: the exponent of distance weights; parameters: compute
    the blend's segment parameters ``t`` of topological weights (False: ``t`` None there,
    for callers that only want the weights); distances: False leaves ``distances`` None for
    authored weights, which do not use them (a pose's bind).
    """
    if weights not in WEIGHTS:
        raise InputError(f"weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
    alpha = check_alpha(alpha)
    if not character.meshes:
        raise InputError("the character has no mesh (a skeleton-only file); give a mesh and pass the "
                         "skeleton with skeleton=")
    skel = character.skeleton
    bones = skel.bones()
    B = len(bones)
    if B == 0:
        raise InputError("the skeleton has no bones to weight")
    if k is None:
        k_eff = SKELETON_K if B > SKELETON_K else B
    elif k == "all":
        k_eff = B
    else:
        if isinstance(k, bool) or int(k) != k or k < 1:
            raise InputError(f"k must be a positive integer or 'all', got {k!r}")
        k_eff = min(int(k), B)
    geo = concatenate_meshes(character.meshes)
    V, rigid = geo.vertices, geo.rigid
    deform = np.flatnonzero(rigid < 0)
    D = None if weights == "authored" and not distances else \
        point_segment_distances(V, bones.segments)[0] if len(V) else np.zeros((0, B))
    W = np.zeros((len(V), B))
    t = None
    if len(deform):
        if weights == "authored":
            joint_w = authored_joint_weights([m for m in character.meshes if m.rigid_joint is None],
                                             skel.num_joints)
            X = group_centers(V[deform], weight_groups(joint_w))
            dense = authored_bone_weights([m for m in character.meshes if m.rigid_joint is None], X, bones,
                                          skel.parents)
            t = np.empty((len(V), B))
            rigid_rows = np.flatnonzero(rigid >= 0)
            t[rigid_rows] = segment_parameters(V[rigid_rows], bones.segments)
            t[deform] = segment_parameters(X, bones.segments)
        else:
            if weights != "euclidean":
                faces = submesh_faces(geo.faces, deform, len(V))
                if len(faces) == 0:
                    raise InputError(f"the character's deforming meshes have no faces: {weights!r} distances "
                                     "run over a surface; use weights='euclidean'")
                D[deform] = surface_distances(V[deform], faces, np.zeros((0, 3)), bones.segments, weights)
                if parameters:
                    t = segment_parameters(V, bones.segments)
                    t[deform] = arrival_parameters(V[deform], faces, bones.segments)
            dense = dense_weights(D[deform], alpha)
        W[deform] = keep_top_k(dense, k_eff if k_eff < B else None)
    for j in np.unique(rigid[rigid >= 0]):
        W[rigid == j, _rigid_owner_bone(int(j), bones, skel.parents)] = 1.0
    return BoneWeights(W, D, bones, k_eff, alpha, geo, t)


def group_centers(points, labels) -> np.ndarray:
    """(N, 3): the centroid of each point's group (labels (N,) int, e.g.
    :func:`nrpose.model.deformation_metrics.weight_groups`), the point itself where the
    label is −1. points (N, 3)."""
    X = np.asarray(points, np.float64)
    lab = np.asarray(labels, np.int64)
    out = X.copy()
    g = lab >= 0
    if g.any():
        _, inv = np.unique(lab[g], return_inverse=True)
        inv = inv.reshape(-1)
        sums = np.zeros((inv.max() + 1, 3))
        np.add.at(sums, inv, X[g])
        out[g] = (sums / np.bincount(inv)[:, None])[inv]
    return out


def skin_entries(meshes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every authored skin weight of the meshes (concatenated) as (row (E,) int64, joint (E,)
    int64, weight (E,) float64), weights divided by their row's sum."""
    missing = [m.name for m in meshes if m.joints is None or m.weights is None]
    if missing:
        raise InputError(f"mesh {missing[0]!r} has no skin weights; use weights='euclidean' "
                         "(or heat, exact, graph)")
    rows, base = [], 0
    for m in meshes:
        rows.append(np.repeat(np.arange(base, base + len(m.vertices)), m.joints.shape[1]))
        base += len(m.vertices)
    r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    j = np.concatenate([np.asarray(m.joints, np.int64).ravel() for m in meshes]) if meshes else r
    w = np.concatenate([np.asarray(m.weights, np.float64).ravel() for m in meshes]) if meshes else np.zeros(0)
    return r, j, w / np.bincount(r, weights=w, minlength=base)[r]


def authored_joint_weights(meshes, n_joints: int) -> np.ndarray:
    """Dense (V, J) skin weights of the meshes (concatenated), rows summing to 1."""
    r, j, w = skin_entries(meshes)
    n = sum(len(m.vertices) for m in meshes)
    return np.bincount(r * n_joints + j, weights=w, minlength=n * n_joints).reshape(n, n_joints)


def with_skin_weights(character, joint_weights: np.ndarray):
    """The character with ``joint_weights`` (V, J) float64 (rows summing to 1; V = the
    vertices of all its meshes, concatenated in order) as its meshes' skin weights."""
    W = np.asarray(joint_weights, dtype=np.float64)
    sizes = [len(m.vertices) for m in character.meshes]
    if W.shape != (sum(sizes), character.skeleton.num_joints):
        raise InputError(f"skin weights: expected {sum(sizes)} vertices × {character.skeleton.num_joints} joints, "
                         f"got {W.shape}")
    J = W.shape[1]
    meshes, start = [], 0
    for m, n in zip(character.meshes, sizes):
        rows = W[start:start + n]
        meshes.append(replace(m, joints=np.tile(np.arange(J), (n, 1)), weights=rows))
        start += n
    return replace(character, meshes=tuple(meshes))


def joint_weights(bone_w: np.ndarray, bones: Bones, n_joints: int) -> np.ndarray:
    """(V, J) float64 weights on the joints from bone weights (V, B): each bone's weight goes to
    the joint that drives it (``bones.joints``); rows keep their sums."""
    bone_w = np.asarray(bone_w, np.float64)
    out = np.zeros((len(bone_w), n_joints))
    np.add.at(out.T, bones.joints, bone_w.T)
    return out


def authored_bone_weights(meshes, X: np.ndarray, bones: Bones, parents: np.ndarray) -> np.ndarray:
    """(V, B) bone weights of the meshes' vertices X (V, 3) (concatenated) from their authored
    skin weights (module docstring): a vertex's weight on a joint is shared between that
    joint's bones by inverse squared distance. Distances are taken only to the bones of the
    joints each vertex is weighted on."""
    n_joints = len(parents)
    owner = np.arange(n_joints)
    driven = np.zeros(n_joints, bool)
    driven[bones.joints] = True
    for j in range(n_joints):                        # parents come first: resolve in order
        if not driven[j]:
            p = parents[j]
            owner[j] = owner[p] if p >= 0 else -1
    r, j, w = skin_entries(meshes)
    lost = (owner[j] < 0) & (w > 0)
    if lost.any():
        raise InputError(f"joint {int(j[lost].min())} carries skin weight but neither it nor "
                         "an ancestor drives a bone")
    use = (w != 0) & (owner[j] >= 0)
    # one entry per (vertex, owning joint): weights of joints with the same owner add up
    key, inverse = np.unique(r[use] * n_joints + owner[j[use]], return_inverse=True)
    weight = np.bincount(inverse, weights=w[use], minlength=len(key))
    ev, ej = key // n_joints, key % n_joints
    # each entry expanded to its joint's bones
    order = np.argsort(bones.joints, kind="stable")
    count = np.bincount(bones.joints, minlength=n_joints)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    per = count[ej]
    entry = np.repeat(np.arange(len(key)), per)
    bone = order[first[ej][entry] + np.arange(len(entry)) - np.repeat(np.cumsum(per) - per, per)]
    A = bones.segments[bone, 0]
    AB = bones.segments[bone, 1] - A
    L2 = np.einsum("ij,ij->i", AB, AB)
    x = X[ev[entry]]
    t = np.clip(np.einsum("ij,ij->i", x - A, AB) * np.where(L2 > 0, 1.0 / np.where(L2 > 0, L2, 1.0), 0.0), 0.0, 1.0)
    d = np.linalg.norm(x - (A + t[:, None] * AB), axis=1)
    share = 1.0 / np.maximum(d ** 2, 1e-12)
    W = np.zeros((len(X), len(bones)))
    W[ev[entry], bone] = weight[entry] * share / np.bincount(entry, weights=share, minlength=len(key))[entry]
    return W


def _rigid_owner_bone(j: int, bones: Bones, parents: np.ndarray) -> int:
    """First bone of joint j or of its nearest ancestor that drives one."""
    a = j
    while a >= 0:
        own = np.flatnonzero(bones.joints == a)
        if len(own):
            return int(own[0])
        a = int(parents[a])
    raise InputError(f"rigid mesh on joint {j}: neither it nor an ancestor drives a bone")
