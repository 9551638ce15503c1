"""Helper joints as plain animated joints: per-frame transforms fitted to a clip's NR-MLS.

A helper's rule (:mod:`nrpose.fit.helper_joints`) is fitted once on the training poses and
plays any motion. For a clip that nrpose writes into the file, the helpers' animation can
instead be solved frame by frame against the clip's own NR-MLS positions, with the fitted
weights fixed (the transform step of SSDR / Dem Bones): :func:`fit_helper_tracks`. The
weights never see the clip; the helpers' channels do, so the clip plays closer to NR-MLS,
but a motion not written by nrpose gets no helper animation (the rule covers that case).

With tracks, the weights are fitted the same way (:func:`refit_with_tracks`, SSDR's
alternation over the training poses): tracks with the weights fixed, then every skinned
vertex's weights with the tracks fixed (its usual candidates plus the helpers under them),
``ALTERNATIONS`` times; the rules are then fitted again to the last training tracks (the
rest pose and players of motions nrpose did not write use them).

Solve: starting from the rule's transforms, ``SWEEPS`` rounds over the helpers; for helper h
with the others fixed, the vertices that use it (weight ``w_h > 0``, pooled over every mesh
whose skin holds it) want its skinning matrix to carry their source to
``(y - sum_{c != h} w_c M_c b) / w_h``, and the rigid local transform (in the parent's frame,
about the helper's centre) that does so best with weights ``w_h^2`` is exactly the minimiser of
the squared error over those vertices (weighted Procrustes): each step cannot raise the error.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..model.character import Character
from ..model.skeleton import LocalPose
from .character_skin import FittedSkin, mesh_space, skin_matrices
from .helper_joints import HelperJoint, driver_features, fit_rule, rigid_fit, rule_locals
from .skin_weights import MAX_CANDIDATES, candidate_joints, fit_weights, skin_positions

__all__ = ["fit_helper_tracks", "refit_with_tracks", "SWEEPS", "ALTERNATIONS"]

SWEEPS = 3          # rounds over the helpers per track fit
ALTERNATIONS = 3    # tracks / weights rounds of refit_with_tracks


def fit_helper_tracks(character: Character, fitted: FittedSkin, G: np.ndarray, pose: LocalPose,
                      targets: np.ndarray, sweeps: int = SWEEPS) -> np.ndarray:
    """Local transforms (F, H, 4, 4) float64 of the fitted skin's H helpers, in their parents'
    frames, for the frames of pose (F, J, ...) with global joint matrices G (F, J, 4, 4) and
    NR-MLS positions targets (F, V, 3) (all meshes in file order, model units)."""
    J = character.skeleton.num_joints
    tracks = rule_locals(fitted.helpers, character.skeleton, pose)
    starts = np.cumsum([0] + [len(m.vertices) for m in character.meshes])
    meshes = []     # (source, ibm, joints, weights, targets, skinning matrices) of each skinned mesh
    for i, m in enumerate(character.meshes):
        if fitted.joints[i] is not None and (fitted.joints[i] >= J).any():
            source, ibm = mesh_space(character, m)
            meshes.append((source, ibm, fitted.joints[i], fitted.weights[i], targets[:, starts[i]:starts[i + 1]],
                           skin_matrices(character, m, fitted, G, pose, tracks)))
    for _ in range(sweeps):
        for h, helper in enumerate(fitted.helpers):
            p = helper.parent
            Ginv = np.linalg.inv(G[:, p])
            z, u, a = [], [], []
            for source, ibm, j, w, y, mats in meshes:
                beta = np.where(j == J + h, w, 0).sum(axis=1)
                ok = beta > 0
                if not ok.any():
                    continue
                others = skin_positions(source[ok], mats, j[ok], np.where(j[ok] == J + h, 0, w[ok]))
                q = (y[:, ok] - others) / beta[ok][None, :, None]
                u.append(np.einsum("fij,fnj->fni", Ginv[:, :3, :3], q) + Ginv[:, None, :3, 3])
                z.append((np.c_[source[ok], np.ones(ok.sum())] @ ibm[p].T)[:, :3] - helper.centre)
                a.append(beta[ok] ** 2)
            if not z:
                continue
            tracks[:, h] = rigid_fit(np.concatenate(z), np.concatenate(u, axis=1), np.concatenate(a))
            for source, ibm, j, w, y, mats in meshes:
                mats[:, J + h] = G[:, p] @ tracks[:, h] @ helper.inverse_bind(ibm[p])
    return tracks


def refit_with_tracks(character: Character, fitted: FittedSkin, G: np.ndarray, pose: LocalPose,
                      targets: np.ndarray, influences: int, allowed=None,
                      rounds: int = ALTERNATIONS) -> FittedSkin:
    """``fitted`` (with helpers) with its weights fitted against per-frame helper tracks of the
    training poses (module docstring) and its helpers' rules fitted to the last tracks.

    G (F, J, 4, 4), pose (F, J, ...), targets (F, V, 3) as :func:`fit_helper_tracks`;
    allowed: per mesh (J,) bool joints its skin may use, or None.
    """
    if not fitted.helpers:
        return fitted
    t0 = time.perf_counter()
    skeleton = character.skeleton
    J = skeleton.num_joints
    parents = np.array([h.parent for h in fitted.helpers])
    starts = np.cumsum([0] + [len(m.vertices) for m in character.meshes])
    cands = []
    for i, m in enumerate(character.meshes):
        if fitted.joints[i] is None:
            cands.append(None)
            continue
        mask = None if allowed is None else allowed[i]
        base = candidate_joints(skeleton.parents, m.joints, m.weights, mask)
        cands.append(_with_helpers(base, parents, J, mask))
    joints, weights = list(fitted.joints), list(fitted.weights)
    tracks = None
    for _ in range(rounds):
        tracks = fit_helper_tracks(character, replace(fitted, joints=tuple(joints), weights=tuple(weights)),
                                   G, pose, targets)
        for i, m in enumerate(character.meshes):
            if cands[i] is None:
                continue
            source, _ = mesh_space(character, m)
            mats = skin_matrices(character, m, fitted, G, pose, tracks)
            joints[i], weights[i] = fit_weights(source, mats, targets[:, starts[i]:starts[i + 1]], cands[i], influences)
    out = replace(fitted, joints=tuple(joints), weights=tuple(weights))
    tracks = fit_helper_tracks(character, out, G, pose, targets)
    helpers = tuple(HelperJoint(h.parent, h.drivers, h.centre, fit_rule(driver_features(skeleton, pose, h.drivers),
                                                                        tracks[:, k]))
                    for k, h in enumerate(fitted.helpers))
    return replace(out, helpers=helpers, seconds=fitted.seconds + time.perf_counter() - t0)


def _with_helpers(base: np.ndarray, parents: np.ndarray, J: int, allowed) -> np.ndarray:
    """Candidates (N, C) int64, -1 padded: base's joints, then the helpers (index J + h) whose
    parent is among them and allowed, at most 2 * MAX_CANDIDATES."""
    rows, inverse = np.unique(base, axis=0, return_inverse=True)
    ok = np.ones(len(parents), bool) if allowed is None else np.asarray(allowed, bool)[parents]
    table = np.full((len(rows), 2 * MAX_CANDIDATES), -1, np.int64)
    for r, row in enumerate(rows):
        own = [int(c) for c in row if c >= 0]
        extra = [J + h for h in np.flatnonzero(np.isin(parents, own) & ok)]
        found = (own + extra)[:2 * MAX_CANDIDATES]
        table[r, :len(found)] = found
    width = max(int((table >= 0).sum(axis=1).max()), 1)
    return table[inverse.reshape(-1), :width]
