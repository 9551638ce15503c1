"""The quality suites' only contact with nrpose: every import, and posing a shape or a
character by each method.

Methods (:data:`METHODS`), all on the device (float32): ``nrmls-<blend>`` (the NR-MLS
deformer with each blend, :data:`nrpose.pose.blend.BLENDS`; ``nrmls-quaternion`` is the
default, tree-signed blend), with the segment parameters that come with the weights
(:func:`nrpose.bind.bone_weights.bone_weights` ``t``: weight-group centroids for authored
weights, arrival parameters for topological ones); ``nrmls-closest``: the default blend with
the closest-point parameters (fixes for rigid parts and topological weights off: what they
change); ``lbs``, ``dqs`` and ``cor`` (:mod:`nrpose.pose.skinning`, :mod:`nrpose.pose.cor`).
Shapes take their weights as authored ones (one weight set for every method; groups of
equal rows get one parameter, as the poser does for authored weights).
"""
from __future__ import annotations

import numpy as np

# every nrpose import of the quality suites (bench/quality.py and bench/quality_fixes.py use these names)
from nrpose import Deformer, HandleSet, Pose
from nrpose.bind.bone_weights import bone_weights, group_centers
from nrpose.bind.distances import (arrival_parameters, distance_matrix, point_segment_distances,
                                   segment_parameters)
from nrpose.bind.weights import dense_weights
from nrpose.io import load_character
from nrpose.model import deformation_metrics
from nrpose.model.character import Character
from nrpose.model.meshset import concatenate_meshes
from nrpose.model.rotation import Rotation
from nrpose.pose import blend, cor, skinning
from nrpose.pose.poser import CharacterPoser
from nrpose.rigs import cylinder, sleeve, yjunction
from nrpose.rigs.fingers import fingers_shape
from nrpose.rigs.humanoid import humanoid

__all__ = [  # the re-exported nrpose names the suites use, then this module's own
    "Deformer", "HandleSet", "Pose", "blend", "cor", "skinning", "deformation_metrics", "Character",
    "load_character", "distance_matrix", "arrival_parameters", "segment_parameters", "group_centers",
    "point_segment_distances", "cylinder", "sleeve", "yjunction", "fingers_shape", "humanoid", "Rotation",
    "dense_weights", "METHODS", "DEFAULT_METHOD", "bone_matrices", "compact", "pose_shape", "joint_weights",
    "pose_character", "character_geometry", "character_bones", "continuity_bound"]

METHODS = tuple(f"nrmls-{b}" for b in blend.BLENDS) + ("nrmls-closest", "lbs", "dqs", "cor")
DEFAULT_METHOD = f"nrmls-{blend.DEFAULT_BLEND}"
SKIN_INFLUENCES = 4     # as nrpose.pose.poser: bones kept per vertex for skinning with distance weights


def bone_matrices(rest: HandleSet, pose: Pose) -> np.ndarray:
    """(B, 4, 4) rigid transforms taking each rest segment onto its posed one with its rotation:
    x ↦ R_b (x − a_b) + a'_b (a: the segment's start)."""
    R = pose.rotations
    a0, a1 = rest.segments[:, 0], pose.handles.segments[:, 0]
    M = np.tile(np.eye(4), (len(R), 1, 1))
    M[:, :3, :3] = R
    M[:, :3, 3] = a1 - np.einsum("bij,bj->bi", R, a0)
    return M


def compact(W: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Dense (N, J) weights → the k largest per row: (joints (N, k) int64, weights (N, k))."""
    k = min(k, W.shape[1])
    joints = np.argsort(-W, axis=1, kind="stable")[:, :k]
    return joints, np.take_along_axis(W, joints, axis=1)


def pose_shape(method: str, V, F, rest: HandleSet, poses: list[Pose], W: np.ndarray) -> np.ndarray:
    """(frames, N, 3) float64: points V (N, 3) (triangles F) bound to segment handles ``rest``
    with bone weights W (N, B), posed by ``method`` (a rigid transform per bone for skinning)."""
    if method.startswith("nrmls-"):
        blend_name = method.split("-", 1)[1]
        t = None
        if blend_name != "closest":
            t = segment_parameters(group_centers(V, deformation_metrics.weight_groups(W)), rest.segments)
        dev = Deformer(V, rest, weights=W, t=t, blend=blend.DEFAULT_BLEND if blend_name == "closest" else blend_name)
        return np.array(dev.pose_frames(poses), np.float64)
    joints, weights = compact(W, SKIN_INFLUENCES)
    mats = np.stack([bone_matrices(rest, p) for p in poses])
    if method == "cor":
        dev = cor.CorSkinner(V, joints, weights, F if F is not None and len(F) else None)
    else:
        dev = skinning.Skinner(V, joints, weights, method)
    return np.array(dev.pose_frames(mats), np.float64)


def joint_weights(character: Character, kind: str, alpha: float = 1.0) -> np.ndarray:
    """(V, J) joint weights of the character's concatenated meshes as nrpose.pose.poser's skinning
    methods use them: ``authored`` (the files' skins) or a bone-distance kind (``heat``, ...),
    4 nearest bones summed per driving joint. Rigidly attached meshes: one-hot on their joint.
    (The weight groups of the rigidity metric.)"""
    skel, meshes = character.skeleton, character.meshes
    geo = concatenate_meshes(meshes)
    W = np.zeros((len(geo.vertices), skel.num_joints))
    if kind == "authored":
        at = 0
        for m in meshes:
            n = len(m.vertices)
            if m.joints is not None:
                np.add.at(W[at:at + n], (np.repeat(np.arange(n), m.joints.shape[1]), m.joints.ravel()), m.weights.ravel())
            at += n
    else:
        bones = character.skeleton.bones()
        np.add.at(W.T, bones.joints, bone_weights(character, kind, SKIN_INFLUENCES, alpha, parameters=False).weights.T)
    rigid = geo.rigid >= 0
    W[rigid] = 0.0
    W[np.flatnonzero(rigid), geo.rigid[rigid]] = 1.0
    return W / W.sum(axis=1, keepdims=True)


def pose_character(method: str, character: Character, kind: str, local) -> np.ndarray:
    """(frames, V, 3) float64 posed vertices of the character for a batch local pose (F, J, ...)."""
    if method == "nrmls-closest":
        bones = character.skeleton.bones()
        bw = bone_weights(character, kind, parameters=False)
        geo = concatenate_meshes(character.meshes)
        k = bw.k if bw.k < len(bones) else None
        dev = Deformer(geo.vertices, HandleSet.make(segments=bones.segments), weights=bw.weights, k=k)
        segs, rots = bones.pose(character.skeleton.forward_kinematics(local))
        return np.array(dev.pose_frames([Pose(HandleSet(np.zeros((0, 3)), segs[f]), rots[f])
                                         for f in range(len(segs))]), np.float64)
    if method.startswith("nrmls-"):
        poser = CharacterPoser(character, "nrmls", kind, blend=method.split("-", 1)[1])
    else:
        poser = CharacterPoser(character, method, kind)
    return np.array(poser.pose(local).positions, np.float64)


def character_geometry(character: Character):
    """(rest vertices (V, 3) float64 world space, faces (M, 3) int64) of the concatenated meshes."""
    geo = concatenate_meshes(character.meshes)
    return geo.vertices, geo.faces


def character_bones(character: Character, local=None):
    """Rest bone segments (B, 2, 3), and posed ones (F, B, 2, 3) for a batch local pose."""
    bones = character.skeleton.bones()
    if local is None:
        return bones.segments
    return bones.pose(character.skeleton.forward_kinematics(local))[0]


def continuity_bound(pts, rest: HandleSet, pose: Pose, pairs, W=None) -> tuple[np.ndarray, np.ndarray]:
    """The default blend's derived continuity bound per pair of points (nrpose/pose/blend.py's
    docstring, 2 + L_p* + L_q* + 2 |u| L_λ / |a|, in finite-difference form over each pair:
    differences over the rest distance, the larger |u| and the smaller |a| of the two), and
    |a| (N,), for points pts (N, 3) bound to segment handles ``rest`` (weights W, default
    Euclidean) posed by ``pose``; pairs (E, 2)."""
    T = blend.rest_terms(pts, rest) if W is None else blend.rest_terms(pts, rest, weights=W)
    S = len(rest.segments)
    Q = blend.reference_rotations(rest, pose, "relative").as_quat()[:S]
    signs = blend.tree_signs(Q, blend.sign_tree(T.weights))
    q_star = np.einsum("nh,nhk->nk", T.weights, blend.handle_points(pose.handles, T.t))
    a = np.linalg.norm(T.lever @ (signs[:, None] * Q), axis=1)
    i, j = np.asarray(pairs).T
    delta = np.linalg.norm(pts[i] - pts[j], axis=1)
    u = np.maximum(np.linalg.norm(T.u[i], axis=1), np.linalg.norm(T.u[j], axis=1))
    return 2 + (np.linalg.norm(T.p_star[i] - T.p_star[j], axis=1) + np.linalg.norm(q_star[i] - q_star[j], axis=1)
                + 2 * u * np.abs(T.lever[i] - T.lever[j]).sum(axis=1) / np.minimum(a[i], a[j])) / delta, a
