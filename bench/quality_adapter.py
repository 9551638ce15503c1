"""The quality suites' only contact with nrpose: every import, and posing a shape or a
character by each method. After the package layout changes (pose/mls.py, pose/skinning.py,
pose/poser.py, bind/bone_weights.py, io/, model/) only the imports and :func:`joint_weights`
here change.

Methods (:data:`METHODS`): ``nrmls-<blend>`` (the OpenCL NR-MLS deformer, float32), ``lbs``
and ``dqs`` (the OpenCL skinning deformers, float32), ``cor`` (optimized centers of
rotation, :mod:`nrpose.cor`: float64 reference; no device kernel yet), and ``nrmls-proto``: the
float64 prototype of the proposed NR-MLS fixes (:mod:`nrpose.blend_variants`: tree-signed
quaternion blend, segment parameters (and, for authored weights, the joint-to-bone split) at
weight-group centroids).
"""
from __future__ import annotations

import numpy as np

# every nrpose import of the quality suites (bench/quality.py and bench/quality_fixes.py use these names)
from nrpose import Deformer, HandleSet, Pose, blend, blend_variants, cor, skinning
from nrpose import deformation_metrics, topological_fixes
from nrpose.character import Character, load_character
from nrpose.distances import distance_matrix, handle_sources, point_segment_distances
from nrpose.posing import CharacterPoser, concatenate_meshes, surface_distances
from nrpose.rigs import cylinder, sleeve, yjunction
from nrpose.rigs.fingers import fingers_shape
from nrpose.rigs.humanoid import humanoid
from nrpose.rotation import Rotation
from nrpose.weights import dense_weights, keep_top_k

__all__ = [  # the re-exported nrpose names the suites use, then this module's own
    "Deformer", "HandleSet", "Pose", "blend", "blend_variants", "cor", "skinning", "deformation_metrics",
    "topological_fixes", "Character", "load_character", "distance_matrix", "handle_sources",
    "point_segment_distances", "cylinder", "sleeve", "yjunction", "fingers_shape", "humanoid", "Rotation",
    "dense_weights", "METHODS", "bone_matrices", "compact", "pose_shape", "joint_weights", "pose_character",
    "character_geometry", "character_bones", "proto_frames"]

BLENDS = ("relative", "quaternion", "paper")
METHODS = tuple(f"nrmls-{b}" for b in BLENDS) + ("lbs", "dqs", "cor", "nrmls-proto")
SKELETON_K = 8          # as nrpose.posing: segment slots per vertex for NR-MLS on larger skeletons
SKIN_INFLUENCES = 4     # as nrpose.posing: bones kept per vertex for skinning with distance weights


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
    if method == "nrmls-proto":
        return proto_frames(V, rest, poses, blend.rest_terms(V, rest, weights=W), deformation_metrics.weight_groups(W))
    if method.startswith("nrmls-"):
        dev = Deformer(V, rest, weights=W, blend=method.split("-", 1)[1])
        return np.array(dev.pose_frames(poses), np.float64)
    joints, weights = compact(W, SKIN_INFLUENCES)
    mats = np.stack([bone_matrices(rest, p) for p in poses])
    if method == "cor":
        C = cor.centers(V, F, joints, weights)
        return np.stack([cor.cor_reference(V, joints, weights, m, C) for m in mats])
    dev = skinning.Deformer(V, joints, weights, method)
    return np.array(dev.pose_frames(mats), np.float64)


def proto_frames(V, rest: HandleSet, poses, T, labels) -> np.ndarray:
    """(frames, N, 3) float64 of the prototype fixes from rest terms T; labels (N,): the weight
    groups (:func:`nrpose.deformation_metrics.weight_groups`) that must move rigidly."""
    T = blend_variants.with_parameters(T, V, rest, blend.segment_parameters(
        blend_variants.group_centers(V, labels), rest.segments))
    tree = blend_variants.coinfluence_tree(T)
    return np.stack([blend_variants.pose_variant(T, rest, p, "tree", tree) for p in poses])


def joint_weights(character: Character, kind: str, alpha: float = 1.0) -> np.ndarray:
    """(V, J) joint weights of the character's concatenated meshes as nrpose.posing's skinning
    methods use them: ``authored`` (the files' skins) or a bone-distance kind (``heat``, ...),
    4 nearest bones summed per driving joint. Rigidly attached meshes: one-hot on their joint."""
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
        bones = skel.bones()
        D = surface_distances(geo.vertices, geo.faces, np.zeros((0, 3)), bones.segments, kind)
        bone_w = keep_top_k(dense_weights(D, alpha), SKIN_INFLUENCES)
        np.add.at(W.T, bones.joints, bone_w.T)
    rigid = geo.rigid >= 0
    W[rigid] = 0.0
    W[np.flatnonzero(rigid), geo.rigid[rigid]] = 1.0
    return W / W.sum(axis=1, keepdims=True)


def pose_character(method: str, character: Character, kind: str, local, W_joint: np.ndarray | None = None
                   ) -> np.ndarray:
    """(frames, V, 3) float64 posed vertices of the character for a batch local pose (F, J, ...).
    W_joint: :func:`joint_weights` (for ``cor``; computed when not given)."""
    if method == "nrmls-proto":
        geo = concatenate_meshes(character.meshes)
        bones = character.skeleton.bones()
        rest = HandleSet.make(segments=bones.segments)
        k = SKELETON_K if len(bones) > SKELETON_K else None
        if kind == "authored":
            Wj = joint_weights(character, kind) if W_joint is None else W_joint
            labels = deformation_metrics.weight_groups(Wj)
            Wb = blend_variants.joint_to_bone_weights(Wj, geo.vertices, bones.segments, bones.joints,
                                                      character.skeleton.parents, labels)
            T = blend.rest_terms(geo.vertices, rest, weights=Wb, k=k)
        else:
            D = surface_distances(geo.vertices, geo.faces, np.zeros((0, 3)), bones.segments, kind)
            T = blend.rest_terms(geo.vertices, rest, distances=D, k=k)
            labels = deformation_metrics.weight_groups(T.weights)
        segs, rots = bones.pose(character.skeleton.forward_kinematics(local))
        poses = [Pose(HandleSet(np.zeros((0, 3)), segs[f]), rots[f]) for f in range(len(segs))]
        return proto_frames(geo.vertices, rest, poses, T, labels)
    if method.startswith("nrmls-"):
        poser = CharacterPoser(character, "nrmls", kind, blend=method.split("-", 1)[1])
        return np.array(poser.pose(local).positions, np.float64)
    if method in ("lbs", "dqs"):
        return np.array(CharacterPoser(character, method, kind).pose(local).positions, np.float64)
    W = joint_weights(character, kind) if W_joint is None else W_joint
    geo = concatenate_meshes(character.meshes)
    joints, weights = compact(W, int(np.count_nonzero(W, axis=1).max()))
    C = cor.centers(geo.vertices, geo.faces, joints, weights)
    mats = character.skin_matrices(character.skeleton.forward_kinematics(local))
    return np.stack([cor.cor_reference(geo.vertices, joints, weights, m, C) for m in mats])


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
