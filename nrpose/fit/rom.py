"""Range-of-motion training poses: every joint swept about its local axes, parent-child pairs, and
a humanoid's anatomical bends.

The axis sweeps (:func:`axis_sweeps`), for a skeleton of J joints, hold

* per joint and per local axis x, y, z: the joint alone rotated by ``±degrees`` and
  ``±degrees / 2`` on top of its rest rotation (12 poses per joint);
* per joint with a parent: ``pairs`` poses with the joint and its parent each rotated
  about a random axis by a random angle in ``[-degrees, degrees]`` (seeded, reproducible).

Translations and scales stay at rest. So ``12 J + pairs * (joints with a parent)`` poses.
:func:`range_of_motion` is the axis sweeps followed by the anatomical poses of
:mod:`nrpose.fit.anatomy` (knees and elbows bent to 150°, arms raised, lowered and twisted, hips
flexed and spread; none for a skeleton without humanoid limbs recognised by name, whose set is
the axis sweeps alone).
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..model.rotation import Rotation
from ..model.skeleton import LocalPose, Skeleton, concat_poses
from .anatomy import anatomical_poses

__all__ = ["range_of_motion", "axis_sweeps", "ROM_DEGREES", "ROM_PAIRS"]

ROM_DEGREES = 60.0   # sweep limit about each local axis
ROM_PAIRS = 2        # random parent-child combinations per joint


def range_of_motion(skeleton: Skeleton, degrees: float = ROM_DEGREES, pairs: int = ROM_PAIRS,
                    seed: int = 0) -> LocalPose:
    """:func:`axis_sweeps` then :func:`nrpose.fit.anatomy.anatomical_poses`, a LocalPose (F, J, ...) float64
    (the axis sweeps themselves for a skeleton without recognised humanoid limbs)."""
    sweeps, anatomical = axis_sweeps(skeleton, degrees, pairs, seed), anatomical_poses(skeleton)
    return concat_poses([sweeps, anatomical]) if len(anatomical.rotation) else sweeps


def axis_sweeps(skeleton: Skeleton, degrees: float = ROM_DEGREES, pairs: int = ROM_PAIRS,
                seed: int = 0) -> LocalPose:
    """The single-joint sweeps and parent-child pairs of the module docstring as a LocalPose (F, J, ...)
    float64."""
    if not (np.isfinite(degrees) and 0 < degrees <= 180):
        raise InputError(f"degrees must be in (0, 180], got {degrees}")
    if pairs < 0:
        raise InputError(f"pairs must be >= 0, got {pairs}")
    J = skeleton.num_joints
    limit = np.radians(degrees)
    angles = np.array([-1.0, -0.5, 0.5, 1.0]) * limit
    # single-joint sweeps: (J, 3 axes, 4 angles) rotation vectors
    rotvec = np.zeros((J, 3, len(angles), 3))
    for axis in range(3):
        rotvec[:, axis, :, axis] = angles
    single_joint = np.repeat(np.arange(J), 3 * len(angles))
    single = rotvec.reshape(-1, 3)
    rng = np.random.default_rng(seed)
    child = np.repeat(np.flatnonzero(skeleton.parents >= 0), pairs)
    F1, F2 = len(single), len(child)
    delta = np.zeros((F1 + F2, J, 3))
    delta[np.arange(F1), single_joint] = single
    for joints in (child, skeleton.parents[child]):
        axis = rng.normal(size=(F2, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        delta[F1 + np.arange(F2), joints] = axis * rng.uniform(-limit, limit, size=(F2, 1))
    rest = skeleton.rest_pose
    F = len(delta)
    rotation = (Rotation.from_quat(np.broadcast_to(rest.rotation, (F, J, 4)).reshape(-1, 4))
                * Rotation.from_rotvec(delta.reshape(-1, 3))).as_quat().reshape(F, J, 4)
    return LocalPose(np.broadcast_to(rest.translation, (F, J, 3)).copy(), rotation,
                     np.broadcast_to(rest.scale, (F, J, 3)).copy())
