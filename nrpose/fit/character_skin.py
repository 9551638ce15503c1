"""A character's NR-MLS deformation fitted as linear blend skinning on its own skeleton.

Each skinned mesh keeps its own source positions and inverse bind matrices (glTF bind
space: ``G_j @ inverse_bind_j`` applied to its POSITION data; meshes without them use
their rest vertices and the skeleton's inverse rest globals), so the fitted weights are
the ones a glTF file stores. Rigidly attached meshes follow their joint exactly under
both deformers and are not fitted.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..bind.bone_weights import bone_weights, joint_weights, with_skin_weights
from ..errors import InputError
from ..model.character import Character, Mesh
from ..model.skeleton import LocalPose
from ..pose.poser import CharacterPoser
from .helper_joints import helper_skin_matrices
from .skin_weights import candidate_joints, fit_weights, skin_positions

__all__ = ["FittedSkin", "with_computed_skin", "nrmls_targets", "fit_character", "fitted_positions", "mesh_space",
           "error_table", "character_height", "skin_matrices"]


@dataclass(frozen=True)
class FittedSkin:
    """Per character mesh: joints (N, k) int64 and weights (N, k) float64, or None for a rigidly
    attached mesh; seconds: the time the fit took; helpers: HelperJoints
    (:mod:`nrpose.fit.helper_joints`), joint index ``J + h`` in ``joints`` for J skeleton joints."""

    joints: tuple
    weights: tuple
    seconds: float
    helpers: tuple = ()


def skin_matrices(character: Character, mesh: Mesh, fitted: FittedSkin, G: np.ndarray,
                  pose: LocalPose | None, tracks: np.ndarray | None = None) -> np.ndarray:
    """Skinning matrices (F, J + H, 4, 4) float64 of a skinned mesh: joints, then the helpers
    (their local transforms: tracks (F, H, 4, 4) if given, else their rules evaluated on pose,
    the local pose G was computed from)."""
    _, ibm = mesh_space(character, mesh)
    mats = G @ ibm
    if not fitted.helpers:
        return mats
    if pose is None and tracks is None:
        raise InputError("a fit with helper joints needs the local pose to evaluate their rules")
    return np.concatenate([mats, helper_skin_matrices(fitted.helpers, character.skeleton, G, pose, ibm, tracks)],
                          axis=1)


def mesh_space(character: Character, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Source positions (N, 3) and inverse binds (J, 4, 4) the mesh is skinned from."""
    if mesh.bind_vertices is not None and mesh.inverse_bind is not None:
        return mesh.bind_vertices, mesh.inverse_bind
    return mesh.vertices, np.linalg.inv(character.skeleton.rest_globals())


def with_computed_skin(character: Character, weights: str, alpha: float = 1.0) -> Character:
    """A character whose meshes lack skin weights (a mesh + TGF/BVH skeleton) with the joint
    weights of its ``weights`` bone weights (:func:`nrpose.bind.bone_weights.bone_weights`,
    default k; :func:`~nrpose.bind.bone_weights.joint_weights`) as its skin: the joints a fit
    starts from (:func:`nrpose.fit.skin_weights.candidate_joints`). A character with skin
    weights is returned as it is; InputError for ``authored`` without them."""
    if all(m.joints is not None for m in character.meshes):
        return character
    if weights == "authored":
        raise InputError("the mesh has no skin weights to start the fit from: give --weights-file W.dmat, or "
                         "--weights heat|exact|graph|euclidean to compute them")
    bw = bone_weights(character, weights, None, alpha, parameters=False)
    return with_skin_weights(character, joint_weights(bw.weights, bw.bones, character.skeleton.num_joints))


def nrmls_targets(poser: CharacterPoser, local: LocalPose) -> tuple[np.ndarray, np.ndarray]:
    """Global joint matrices (F, J, 4, 4) float64 and NR-MLS positions (F, V, 3) float32."""
    G = poser.character.skeleton.forward_kinematics(local)
    G = G[None] if G.ndim == 3 else G
    positions = np.array(poser.pose(local).positions, copy=True)
    if not np.isfinite(positions).all():
        raise InputError("NR-MLS posing produced non-finite coordinates for a training pose")
    return G, positions


def fit_character(character: Character, G: np.ndarray, targets: np.ndarray, influences: int,
                  allowed=None) -> FittedSkin:
    """Fitted weights of every non-rigid mesh (see :mod:`nrpose.fit.skin_weights`).

    G: (F, J, 4, 4) global joint matrices of the training poses; targets: (F, V, 3) positions
    of all meshes concatenated in file order; allowed: per mesh a (J,) bool mask of joints
    its skin may use, or None (all joints).
    """
    if influences < 1:
        raise InputError(f"influences must be >= 1, got {influences}")
    t0 = time.perf_counter()
    joints, weights, start = [], [], 0
    parents = character.skeleton.parents
    for i, mesh in enumerate(character.meshes):
        n = len(mesh.vertices)
        if mesh.rigid_joint is not None:
            joints.append(None)
            weights.append(None)
        else:
            if mesh.joints is None:
                raise InputError(f"mesh {mesh.name!r} has no skin weights to choose candidate joints from")
            source, ibm = mesh_space(character, mesh)
            cand = candidate_joints(parents, mesh.joints, mesh.weights, None if allowed is None else allowed[i])
            j, w = fit_weights(source, G @ ibm, targets[:, start:start + n], cand, influences)
            joints.append(j)
            weights.append(w)
        start += n
    return FittedSkin(tuple(joints), tuple(weights), time.perf_counter() - t0)


def fitted_positions(character: Character, fitted: FittedSkin, G: np.ndarray,
                     pose: LocalPose | None = None, tracks: np.ndarray | None = None) -> np.ndarray:
    """LBS of the fitted weights: (F, V, 3) float64 for global joint matrices G (F, J, 4, 4) of
    pose (the local pose, needed when the fit has helper joints); tracks: the helpers' local
    transforms (F, H, 4, 4) (:mod:`nrpose.fit.helper_tracks`) instead of their rules."""
    rest_inv = np.linalg.inv(character.skeleton.rest_globals())
    parts = []
    for mesh, j, w in zip(character.meshes, fitted.joints, fitted.weights):
        if j is None:
            M = G[:, mesh.rigid_joint] @ rest_inv[mesh.rigid_joint]
            parts.append(np.einsum("fij,nj->fni", M[:, :3, :3], mesh.vertices) + M[:, None, :3, 3])
        else:
            source, _ = mesh_space(character, mesh)
            parts.append(skin_positions(source, skin_matrices(character, mesh, fitted, G, pose, tracks), j, w))
    return np.concatenate(parts, axis=1)


def character_height(character: Character) -> float:
    """The character's height, model units: the vertical (Y, glTF's up) extent of the rest
    vertices of a character read from glTF (its meshes have a ``source``); a mesh with a TGF or
    BVH skeleton has no up axis, so the largest extent of its rest bounding box."""
    V = np.concatenate([m.vertices for m in character.meshes])
    extent = V.max(axis=0) - V.min(axis=0)
    return float(extent[1] if all(m.source is not None for m in character.meshes) else extent.max())


def error_table(character: Character, fitted: np.ndarray, targets: np.ndarray) -> dict:
    """RMS and max vertex distance of fitted (F, V, 3) vs targets (F, V, 3): overall (model units
    and fraction of :func:`character_height`) and per region (vertices by dominant authored joint)."""
    height = character_height(character)
    d2 = ((np.asarray(fitted, np.float64) - targets) ** 2).sum(axis=2)     # (F, V)
    dominant = np.concatenate([m.joints[np.arange(len(m.joints)), np.argmax(m.weights, axis=1)]
                               if m.joints is not None else np.full(len(m.vertices), -1)
                               for m in character.meshes])

    def stats(d):
        rms, mx = float(np.sqrt(d.mean())), float(np.sqrt(d.max()))
        return {"rms": rms, "max": mx, "rms_fraction": rms / height, "max_fraction": mx / height}

    regions = {}
    for j in np.unique(dominant):
        name = character.skeleton.names[j] if j >= 0 else "(no skin)"
        sel = d2[:, dominant == j]
        regions[name] = {**stats(sel), "vertices": int(sel.shape[1])}
    return {**stats(d2), "frames": int(len(d2)), "regions": regions}
