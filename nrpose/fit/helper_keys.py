"""Helper channels with fewer keys: the keys a LINEAR glTF player needs to stay within a tolerance.

A helper's transform is known at every frame of a clip (its rule, or its fitted track), but
most of those keys are redundant: between two keys a player interpolates, glTF's LINEAR
(the translation lerped, the rotation slerped: three.js, nrpose's reader) or, in Blender,
the quaternion's components lerped and normalised (nlerp). :func:`reduce_keys` keeps
the first and last frames and refines greedily (each round, in every stretch between kept
keys, the frame furthest off) until at every frame *both* interpolations are within the
tolerance of the helper's transform, measured as the most it displaces a vertex it moves:

    e_f = s_f (w |dt_f| + m * 2 sin(theta_f / 2))

with s_f the largest singular value of the helper's parent's global matrix at frame f, w the
largest weight a vertex gives the helper, m the largest product of a vertex's weight on it
and its distance from the helper's centre (in the parent's bind frame), dt_f the
translation error and theta_f the angle between the interpolated and exact rotations: a
bound on the helper's share ``w_n |dR z_n + dt|`` of every vertex's error (a vertex with a
small weight on a helper is moved little by its keys). Interpolating two keys whose
quaternions lie in opposite hemispheres, nlerp turns the long way round, so such a gap is
refined like any other. Rotations are stored as normalised int16 (:func:`stored_quats`,
glTF's core format; each component within 1/65534): the interpolation starts from the
stored keys, so their rounding is inside the check (a key itself is off by its rounding
only, under 6.1e-5 m).
"""
from __future__ import annotations

import numpy as np

from ..model.character import Character
from ..model.rotation import matrix_quats, quat_matrices, quat_multiply, quat_slerp
from .character_skin import FittedSkin, character_height, mesh_space

__all__ = ["KEY_TOLERANCE", "helper_trs", "stored_quats", "reduce_keys", "helper_keys"]

QUAT_SCALE = 32767      # rotations stored as normalised int16: k means k / 32767

#: default key tolerance, a fraction of the character's height (4x under the fit's held-out RMS
#: target of 0.2 %, 20x under its max target of 1 %)
KEY_TOLERANCE = 5e-4


def helper_trs(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translations (F, 3) and unit quaternions (F, 4) (x, y, z, w; consecutive ones in the same
    hemisphere, so that players' slerp takes the short way) of a helper's local transforms L (F, 4, 4)."""
    q = matrix_quats(L[:, :3, :3])
    flip = np.cumprod(np.r_[1.0, np.sign(np.einsum("fi,fi->f", q[1:], q[:-1]) + 1e-300)])
    return L[:, :3, 3], q * flip[:, None]


def stored_quats(q: np.ndarray) -> np.ndarray:
    """Unit quaternions q (K, 4) as the file stores them: (K, 4) int16, normalised (k / 32767)."""
    return np.rint(np.asarray(q) * QUAT_SCALE).astype(np.int16)


def _reach(character: Character, fitted: FittedSkin) -> tuple[np.ndarray, np.ndarray]:
    """Per helper of ``fitted``: the largest weight a vertex gives it, and the largest product of
    a vertex's weight on it and its distance from the helper's centre in the parent's bind frame
    ((H,) float64 each; 0 for a helper no vertex uses)."""
    J = character.skeleton.num_joints
    weight, reach = np.zeros(len(fitted.helpers)), np.zeros(len(fitted.helpers))
    for mesh, joints, weights in zip(character.meshes, fitted.joints, fitted.weights):
        if joints is None:
            continue
        source, ibm = mesh_space(character, mesh)
        b = np.c_[source, np.ones(len(source))]
        for h, helper in enumerate(fitted.helpers):
            w = np.where(joints == J + h, weights, 0.0).sum(axis=1)
            used = w > 0
            if used.any():
                z = (b[used] @ ibm[helper.parent].T)[:, :3] - helper.centre
                weight[h] = max(weight[h], float(w[used].max()))
                reach[h] = max(reach[h], float((w[used] * np.linalg.norm(z, axis=1)).max()))
    return weight, reach


def _parent_scales(G: np.ndarray, fitted: FittedSkin) -> np.ndarray:
    """(F, H) float64: the largest singular value of each helper's parent's global matrix in
    frames G (F, J, 4, 4)."""
    parents = [h.parent for h in fitted.helpers]
    return np.linalg.svd(G[:, parents, :3, :3], compute_uv=False)[..., 0]


def reduce_keys(times: np.ndarray, t: np.ndarray, q: np.ndarray, scale: np.ndarray, radius: float,
                tolerance: float) -> np.ndarray:
    """Frames kept (K,) int64, increasing, the first and last among them, of one helper's
    channels: times (F,) seconds, translations t (F, 3), unit quaternions q (F, 4) as
    :func:`helper_trs`; scale (F,) the parent's scale times w and radius m / w (model units of
    the parent's bind frame; w, m of :func:`_reach`), so that the error is
    ``scale (|dt| + radius * chord)``; tolerance in model units (module docstring; <= 0 keeps
    every frame)."""
    F = len(times)
    if tolerance <= 0 or F <= 2:
        return np.arange(F)
    keep = np.zeros(F, bool)
    keep[[0, F - 1]] = True
    while True:
        lerp, slerp, nlerp = _played(times, t, q, np.flatnonzero(keep))
        chord = np.maximum(_chord(slerp, q), _chord(nlerp, q))
        err = scale * (np.linalg.norm(lerp - t, axis=1) + radius * chord)
        err[keep] = 0.0           # a key's own error is the int16 rounding, which no key can lower
        if not (err > tolerance).any():
            return np.flatnonzero(keep)
        stretch = np.cumsum(keep) - 1                        # the stretch each frame starts or lies in
        order = np.lexsort((err, stretch))
        worst = order[np.r_[stretch[order][1:] != stretch[order][:-1], True]]
        keep[worst[err[worst] > tolerance]] = True


def _played(times, t, q, keys) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At every frame, from ``keys`` (K >= 2,) as stored (:func:`stored_quats`): the lerped
    translation (F, 3), the slerped and the nlerped (Blender's) unit quaternion (F, 4)."""
    k = np.clip(np.searchsorted(keys, np.arange(len(times)), side="right") - 1, 0, len(keys) - 2)
    a, b = keys[k], keys[k + 1]
    s = ((times - times[a]) / (times[b] - times[a]))[:, None]
    stored = stored_quats(q) / QUAT_SCALE
    nlerp = (1 - s) * stored[a] + s * stored[b]
    nlerp /= np.maximum(np.linalg.norm(nlerp, axis=1, keepdims=True), 1e-300)
    return (1 - s) * t[a] + s * t[b], quat_slerp(stored[a], stored[b], s), nlerp


def _chord(r: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(F,) 2 sin(theta / 2) of the angle theta between unit quaternions r and q (F, 4): twice the
    length of the vector part of r^-1 q (no cancellation for small angles)."""
    return 2 * np.linalg.norm(quat_multiply(r * [-1.0, -1.0, -1.0, 1.0], q)[:, :3], axis=1)


def helper_keys(character: Character, fitted: FittedSkin, G: np.ndarray, local: np.ndarray, times: np.ndarray,
                tolerance: float = KEY_TOLERANCE) -> tuple[list, np.ndarray]:
    """Keys of every helper's channels in a clip and what a glTF LINEAR player makes of them.

    G (F, J, 4, 4): the skeleton's global matrices at times (F,) seconds; local (F, H, 4, 4): the
    helpers' local transforms there (rules or fitted tracks); tolerance: a fraction of the
    character's height (module docstring). Returns the kept frames per helper (H arrays (K_h,)
    int64, :func:`reduce_keys`) and the transforms (F, H, 4, 4) float64 played from those keys
    at ``times`` (lerp, slerp).
    """
    played = np.array(local, dtype=np.float64, copy=True)
    weight, reach = _reach(character, fitted)
    scales = _parent_scales(G, fitted) * weight
    absolute = tolerance * character_height(character)
    kept = []
    for h in range(local.shape[1]):
        t, q = helper_trs(local[:, h])
        keys = reduce_keys(times, t, q, scales[:, h], float(reach[h] / max(weight[h], 1e-300)), absolute)
        kept.append(keys)
        if len(times) >= 2:
            lerp, slerp, _ = _played(times, t, q, keys)
            played[:, h, :3, 3] = lerp
            played[:, h, :3, :3] = quat_matrices(slerp)
        else:
            played[:, h, :3, :3] = quat_matrices(stored_quats(q) / QUAT_SCALE)
    return kept, played
