"""Helper joints placed where the fitted LBS is furthest from NR-MLS, SSDR-style.

:func:`add_helpers` adds helpers one at a time to a fitted skin (:mod:`nrpose.fit.character_skin`):

1. **Where**: the vertex with the largest peak residual (its largest distance from NR-MLS in
   any training pose, as the fit stands with the helpers so far) seeds a region, unless it
   seeded one before or lies in a dropped helper's region (step 4): the vertices within
   ``REGION_RADIUS`` of the character's height of it (rest positions), with a peak residual at
   least ``REGION_RESIDUAL`` of the seed's, that have the seed's dominant joint p among their
   candidates. The peak, not the RMS over the poses: a joint bent far in a few range-of-motion
   poses (a knee at the sweep's limit) has a small RMS residual but is where a motion that
   bends it as far fails. A vertex in an earlier kept helper's region seeds again if it is
   still the worst (the helper did not serve it: a seam between two joints next to the
   seed's). The helper is
   a child of p; its drivers (:mod:`nrpose.fit.helper_joints`)
   are p (unless p is the root or its parent carries no skin weight: its rotation then only
   turns the whole body) and p's children in the mesh's skin.
2. **Start**: per training frame, the rigid transform (in p's frame) that best carries the
   region's rest vertices to their NR-MLS positions; the rule is fitted to those transforms.
3. **Alternate** ``ROUNDS`` times: the region's weights are fitted again with the helper as an
   extra candidate (NNLS, :func:`nrpose.fit.skin_weights.fit_weights`); per frame the helper's
   rigid transform is fitted to what the vertices using it still miss (weighted Procrustes on
   ``(y - sum_{c != h} w_c M_c b) / w_h``, weights ``w_h^2``, as SSDR does); the rule is fitted to
   those transforms and **evaluated** (the weights are always fitted against the rule's
   transforms, the ones the file plays).
4. A helper that no region vertex uses (all its weights 0) or that does not lower the region's
   RMS residual is dropped; its region's vertices do not seed again.

With ``per_frame`` (``--helper-tracks fitted``, where the file plays per-frame helper tracks,
:mod:`nrpose.fit.helper_tracks`) the helpers move in steps 2 to 4, and in the residuals that
seed the next one, by their per-frame rigid transforms instead of the rule: a region the rule
cannot serve but tracks can (an upper arm's swing) then takes one helper, not many, and the
next helpers go where the played file is still furthest from NR-MLS (the knees, the wrists).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..model.character import Character
from ..model.skeleton import LocalPose
from .character_skin import FittedSkin, character_height, mesh_space, skin_matrices
from .helper_joints import HelperJoint, driver_features, fit_rule, rigid_fit, rule_locals
from .skin_weights import candidate_joints, fit_weights, skin_positions

__all__ = ["add_helpers", "residuals", "REGION_RADIUS", "REGION_RESIDUAL", "ROUNDS"]

REGION_RADIUS = 0.25  # of the character's height
REGION_RESIDUAL = 0.25   # region vertices: peak residual at least this fraction of the seed's
ROUNDS = 3
MIN_WEIGHT = 1e-3     # helper weights below this do not enter its transform fit


def residuals(positions: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex of positions (F, N, 3) vs targets (F, N, 3): the peak residual (N,) float64,
    its largest distance over the poses (model units), and the mean squared distance (N,)."""
    d2 = ((np.asarray(positions, np.float64) - targets) ** 2).sum(axis=2)
    return np.sqrt(d2.max(axis=0)), d2.mean(axis=0)


def drivers_of(character: Character, p: int, allowed: np.ndarray) -> tuple:
    """Joints whose local rotations drive a helper under joint p (see the module docstring)."""
    parents = character.skeleton.parents
    weighted = np.zeros(character.skeleton.num_joints, bool)
    for m in character.meshes:
        if m.joints is not None:
            weighted[m.joints[m.weights > 0]] = True
    own = [p] if parents[p] >= 0 and weighted[parents[p]] else []
    return tuple(own + [int(c) for c in np.flatnonzero(parents == p) if allowed[c]])


def add_helpers(character: Character, fitted: FittedSkin, G: np.ndarray, pose: LocalPose, targets: np.ndarray,
                count: int, influences: int, allowed=None, per_frame: bool = False) -> tuple[FittedSkin, list]:
    """``fitted`` with up to ``count`` helper joints; and per helper tried a dict (parent, drivers,
    mesh, seed vertex, region vertices, region RMS before/after, kept).

    G (F, J, 4, 4) global matrices of the training poses pose (F, J, ...); targets (F, V, 3)
    their NR-MLS positions (all meshes in file order); allowed: per mesh (J,) bool or None;
    per_frame: the helpers move by per-frame transforms, not their rules (module docstring).
    """
    if count < 0:
        raise InputError(f"helper count must be >= 0, got {count}")
    t0 = time.perf_counter()
    skeleton = character.skeleton
    J = skeleton.num_joints
    height = character_height(character)
    starts = np.cumsum([0] + [len(m.vertices) for m in character.meshes])
    joints, weights = list(fitted.joints), list(fitted.weights)
    helpers = list(fitted.helpers)
    cands = []
    for i, m in enumerate(character.meshes):
        cands.append(None if joints[i] is None else
                     candidate_joints(skeleton.parents, m.joints, m.weights, None if allowed is None else allowed[i]))
    used = [np.zeros(len(m.vertices), bool) for m in character.meshes]    # seeds and dropped regions
    peak, meansq = [], []    # per mesh, per vertex (updated in each new region): see residuals()
    current = FittedSkin(tuple(joints), tuple(weights), 0.0, tuple(helpers))
    # per_frame: helpers move by per-frame transforms (their tracks), as --helper-tracks fitted plays them
    moves = list(rule_locals(helpers, skeleton, pose).transpose(1, 0, 2, 3)) if per_frame else []

    def tracks_with(extra=()):
        return np.stack(moves + list(extra), axis=1) if per_frame and (moves or extra) else None
    for i, m in enumerate(character.meshes):
        if joints[i] is None:
            peak.append(None)
            meansq.append(None)
            continue
        source, _ = mesh_space(character, m)
        mats = skin_matrices(character, m, current, G, pose, tracks_with())
        pos = skin_positions(source, mats, joints[i], weights[i])
        r, ms = residuals(pos, targets[:, starts[i]:starts[i + 1]])
        peak.append(r)
        meansq.append(ms)
    log = []
    while len(helpers) - len(fitted.helpers) < count:
        best = None
        for i, r in enumerate(peak):
            if r is None:
                continue
            r = np.where(used[i], -1.0, r)
            n = int(np.argmax(r))
            if r[n] > 0 and (best is None or r[n] > best[2]):
                best = (i, n, r[n])
        if best is None:
            break
        i, seed, _ = best
        r = peak[i]
        m = character.meshes[i]
        source, ibm = mesh_space(character, m)
        p = int(joints[i][seed, 0])
        p = p if p < J else helpers[p - J].parent
        near = np.linalg.norm(m.vertices - m.vertices[seed], axis=1) <= REGION_RADIUS * height
        region = np.flatnonzero(near & (cands[i] == p).any(axis=1) & (r >= REGION_RESIDUAL * r[seed]))
        region = region if len(region) else np.array([seed])
        used[i][seed] = True
        y = targets[:, starts[i] + region]                                   # (F, n, 3)
        local_rest = (np.c_[source[region], np.ones(len(region))] @ ibm[p].T)[:, :3]
        centre = local_rest.mean(axis=0)
        z = local_rest - centre
        Ginv = np.linalg.inv(G[:, p])
        u = np.einsum("fij,fnj->fni", Ginv[:, :3, :3], y) + Ginv[:, None, :3, 3]
        drivers = drivers_of(character, p, np.ones(J, bool) if allowed is None or allowed[i] is None else allowed[i])
        phi = driver_features(skeleton, pose, drivers)
        L = rigid_fit(z, u, np.ones(len(region)))
        h = len(helpers)
        trial_j, trial_w = joints[i].copy(), weights[i].copy()
        before = float(np.sqrt(meansq[i][region].mean()))
        helper = None
        # candidates: the joints', this helper, earlier helpers the vertex uses
        rows = [list(dict.fromkeys([int(c) for c in base if c >= 0] + [J + h] + [int(c) for c in held if c >= J]))
                for base, held in zip(cands[i][region], trial_j[region])]
        cand = np.full((len(rows), max(map(len, rows))), -1, np.int64)
        for k, row in enumerate(rows):
            cand[k, :len(row)] = row
        for _ in range(ROUNDS):
            coef = fit_rule(phi, L)
            helper = HelperJoint(p, drivers, centre, coef)
            trial = FittedSkin(tuple(joints), tuple(weights), 0.0, tuple(helpers) + (helper,))
            used_L = L      # per_frame: the transforms these weights are fitted against
            mats = skin_matrices(character, m, trial, G, pose, tracks_with([L]))
            rj, rw = fit_weights(source[region], mats, y, cand, influences)
            trial_j[region], trial_w[region] = rj, rw
            beta = np.where(rj == J + h, rw, 0).sum(axis=1)
            ok = beta > MIN_WEIGHT
            if not ok.any():
                break
            others = skin_positions(source[region][ok], mats, rj[ok], np.where(rj[ok] == J + h, 0, rw[ok]))
            q = (y[:, ok] - others) / beta[ok][None, :, None]
            u = np.einsum("fij,fnj->fni", Ginv[:, :3, :3], q) + Ginv[:, None, :3, 3]
            L = rigid_fit(z[ok], u, beta[ok] ** 2)
        # the weights were fitted against the last rule (per_frame: transforms) evaluated: keep that pair
        after_pos = skin_positions(source[region], mats, trial_j[region], trial_w[region])
        after = float(np.sqrt(((after_pos - y) ** 2).sum(axis=2).mean()))
        kept = helper is not None and (trial_j[region] == J + h).any() and after < before
        log.append({"parent": skeleton.names[p], "drivers": [skeleton.names[d] for d in drivers],
                    "mesh": i, "seed": int(seed), "region_vertices": int(len(region)), "region_rms_before": before,
                    "region_rms_after": after, "kept": bool(kept)})
        if kept:
            helpers.append(helper)
            moves.append(used_L)
            joints[i], weights[i] = trial_j, trial_w
            peak[i][region], meansq[i][region] = residuals(after_pos, y)
        else:
            used[i][region] = True
    return replace(fitted, joints=tuple(joints), weights=tuple(weights), helpers=tuple(helpers),
                   seconds=fitted.seconds + time.perf_counter() - t0), log
