"""Anatomical range of motion of a humanoid: the bends a motion makes past the axis sweeps.

The axis sweeps of :mod:`nrpose.fit.rom` turn a joint at most ±60° from rest; a captured
motion bends knees and elbows to 130°, swings an upper arm 130° from its T-pose rest with a
90° twist. :func:`anatomical_poses` adds those bends for the limbs it recognises by their
joint names (:func:`nrpose.pose.retarget.joint_slots`: Mixamo ``mixamorig:LeftArm``,
``LeftForeArm``, ``LeftHand``, ``LeftHandThumb1``, ``LeftHandThumb2``, ``LeftUpLeg``,
``LeftLeg``, ``LeftFoot``, with or without a ``prefix:``, any case, and the other conventions
it knows). A skeleton without such limbs
(the Fox's ``b_...`` names) gets none.

Directions come from the rest joint positions (world frame, :meth:`Skeleton.rest_globals`):
*left* from the right to the left upper leg (else upper arm), *up* from the hips to the neck
(else head) made perpendicular to left, *forward* = left × up. Per recognised side
(*lateral* = ±left, outward), in degrees:

* **shoulder** (the upper-arm joint): the arm pointed at elevation e from hanging down
  (``ARM_ELEVATIONS``) in the plane at angle h from lateral towards forward
  (``ARM_PLANES``, negative: backward), direction ``cos e·(−up) + sin e·(cos h·lateral +
  sin h·forward)``, those at most ``MAX_ARM_SWING`` from the rest arm; at or below
  horizontal each also twisted about the arm by ``ARM_TWISTS``;
* **elbow** and **knee**: flexion by ``FLEXION`` about the hinge perpendicular to the lower
  limb and to forward, in the sense that moves the hand forward (the forearm folds towards
  the shoulder) and the foot backward;
* **wrist** (the hand joint): the hand turned ±``WRIST_SWING`` about the axis perpendicular to
  the forearm and forward, about the axis perpendicular to both and about their two
  diagonals; about each of the first two also after a twist of ±``WRIST_SWING_TWIST`` about
  the forearm (a captured hand turns about a skew axis: 131_03 turns one 113°); and twisted
  about the forearm alone by ±``WRIST_TWIST``;
* **thumb** (the first thumb joint, below a recognised arm's hand, with the second thumb joint
  below it): the thumb turned ±``THUMB_SWING`` about the axis perpendicular to the thumb and
  forward, about the axis perpendicular to both and about their two diagonals, each alone and
  with the hand turned
  ±``THUMB_WRIST`` about each of the wrist's two swing axes (131_03 holds the right thumb
  90° from rest with the hand turned 65°, where LBS of thumb and hand weights alone misses
  NR-MLS by 1 % of the height: these poses make that residual show in training);
* **hip** (the upper-leg joint): the rest thigh direction turned by abduction a about
  forward (positive: outward), then by flexion f about left (positive: knee forward), for
  ``HIP_FLEXION`` × ``HIP_ABDUCTION`` (f = −30: extension; a = −30: adduction), so that at
  90° flexion each abduction is a distinct pose; at f = 0 and 90 (a = 0) also twisted about
  the thigh by ``HIP_TWISTS``;
* **combinations**: hip flexion with knee flexion (``HIP_KNEE``), an arm direction with
  elbow flexion (``ARM_ELBOW``) and the thumb with the hand (above).

Each moved joint gets a world rotation W: a *swing* (the shortest arc carrying its child's
rest direction to the target direction, then the twist about the target) or a turn about a
hinge. Its local rotation becomes ``q_rest ⊗ g⁻¹ W g`` with g the rotation of its rest global
transform, so in a combination the child's turn is carried by the parent's. An axis across a
bone is perpendicular to the bone and forward (to the bone and up for a bone along forward). Every
other joint, translation and scale stays at rest.
"""
from __future__ import annotations

import numpy as np

from ..model.rotation import Rotation, minimal_quat
from ..model.skeleton import LocalPose, Skeleton, polar_rotation
from ..pose.retarget import joint_slots

__all__ = ["anatomical_poses", "body_axes", "humanoid_limbs", "LIMB_PARTS", "FLEXION", "ARM_ELEVATIONS",
           "ARM_PLANES", "ARM_TWISTS", "MAX_ARM_SWING", "WRIST_SWING", "WRIST_TWIST", "WRIST_SWING_TWIST",
           "THUMB_SWING", "THUMB_WRIST", "HIP_FLEXION",
           "HIP_ABDUCTION", "HIP_TWISTS", "HIP_KNEE", "ARM_ELBOW"]

LIMB_PARTS = {"arm": ("upperarm", "forearm", "hand"), "leg": ("upperleg", "lowerleg", "foot")}
FLEXION = (30.0, 60.0, 90.0, 120.0, 150.0)              # elbow and knee
ARM_ELEVATIONS = (0.0, 45.0, 90.0, 135.0, 165.0)        # from hanging down
ARM_PLANES = (-90.0, -45.0, 0.0, 45.0, 90.0, 135.0)     # from lateral towards forward
ARM_TWISTS = (-90.0, -45.0, 45.0, 90.0)                 # arm at or below horizontal
MAX_ARM_SWING = 150.0                                   # from the rest arm direction
WRIST_SWING, WRIST_TWIST = 100.0, 90.0
WRIST_SWING_TWIST = 45.0                                # twist before a swing about a main axis
THUMB_SWING, THUMB_WRIST = 90.0, 60.0                   # thumb alone; the hand with it
HIP_FLEXION = (-30.0, 0.0, 30.0, 60.0, 90.0, 120.0)
HIP_ABDUCTION = (-30.0, 0.0, 45.0)
HIP_TWISTS = (-45.0, 45.0)                              # at flexion 0 and 90
HIP_KNEE = ((45.0, 60.0), (45.0, 120.0), (90.0, 60.0), (90.0, 120.0))    # (hip flexion, knee flexion)
ARM_ELBOW = ((0.0, 0.0, 60.0), (0.0, 0.0, 120.0), (90.0, 90.0, 60.0), (90.0, 90.0, 120.0),
             (135.0, 90.0, 60.0), (135.0, 90.0, 120.0))                  # (elevation, plane, elbow)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _turn(axis: np.ndarray, degrees: float) -> Rotation:
    """Rotation by ``degrees`` about the direction ``axis`` (3,)."""
    return Rotation.from_rotvec(_unit(axis) * np.radians(degrees))


def _toward(axis: np.ndarray, bone: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Unit ``axis`` or its opposite: the one about which a positive turn moves ``bone``'s tip along ``wanted``."""
    axis = _unit(axis)
    return axis if np.cross(axis, bone) @ wanted >= 0 else -axis


def _swing(bone: np.ndarray, target: np.ndarray, twist: float = 0.0) -> Rotation:
    """The shortest arc carrying direction ``bone`` onto ``target``, then ``twist`` degrees about ``target``."""
    return _turn(target, twist) * Rotation.from_quat(minimal_quat(bone, target))


def humanoid_limbs(skeleton: Skeleton) -> dict[tuple[str, str], tuple[int, int, int]]:
    """{(side 'left'/'right', 'arm'/'leg'/'thumb'): (upper, lower, end joint indices)} of the limbs whose
    three joints are recognised by name, each below the one before and apart from it at rest; a thumb
    is (hand, thumb1, thumb2) below a recognised arm's hand."""
    index = {slot: j for j, slot in joint_slots(skeleton).items()}
    P = skeleton.rest_globals()[:, :3, 3]

    def below(j: int, a: int) -> bool:
        """j is a descendant of a, apart from it at rest (a bone with a direction)."""
        if np.allclose(P[j], P[a], rtol=0, atol=1e-9 * max(1.0, float(np.abs(P).max()))):
            return False
        while j >= 0 and j != a:
            j = int(skeleton.parents[j])
        return j == a

    limbs = {}
    for side in ("left", "right"):
        for kind, parts in LIMB_PARTS.items():
            joints = tuple(index.get(f"{side}_{p}") for p in parts)
            if None not in joints and below(joints[1], joints[0]) and below(joints[2], joints[1]):
                limbs[side, kind] = joints
        thumb = (limbs.get((side, "arm"), (None,) * 3)[2], index.get(f"{side}_thumb1"), index.get(f"{side}_thumb2"))
        if None not in thumb and below(thumb[1], thumb[0]) and below(thumb[2], thumb[1]):
            limbs[side, "thumb"] = thumb
    return limbs


def body_axes(skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(left, up, forward) unit vectors (3,) float64 in the world frame of the rest pose, from the
    recognised upper legs (else upper arms), hips and neck (else head); None without them."""
    index = {slot: j for j, slot in joint_slots(skeleton).items()}
    P = skeleton.rest_globals()[:, :3, 3]
    pair = next((p for p in ("upperleg", "upperarm") if f"left_{p}" in index and f"right_{p}" in index), None)
    top = index.get("neck", index.get("head"))
    if pair is None or top is None or "hips" not in index:
        return None
    left = P[index[f"left_{pair}"]] - P[index[f"right_{pair}"]]
    up = P[top] - P[index["hips"]]
    if not (np.linalg.norm(left) > 0 and np.linalg.norm(np.cross(left, up)) > 0):
        return None
    left = _unit(left)
    up = _unit(up - (up @ left) * left)
    return left, up, np.cross(left, up)


def _across(bone: np.ndarray, forward: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes (3,) perpendicular to ``bone`` and each other: across (⟂ forward, or ⟂ up for a
    bone along forward) and side."""
    across = np.cross(bone, forward)
    if np.linalg.norm(across) <= 1e-6 * np.linalg.norm(bone):
        across = np.cross(bone, up)
    across = _unit(across)
    return across, _unit(np.cross(bone, across))


def _turns_across(across: np.ndarray, side: np.ndarray, degrees: float) -> list[Rotation]:
    """Turns by ±degrees about across, side and their two diagonals (8)."""
    return [_turn(s * axis, degrees) for axis in (across, side, across + side, across - side) for s in (1, -1)]


def _thumb_poses(P: np.ndarray, arm, thumb, up, forward) -> list[dict[int, Rotation]]:
    hand, first, second = thumb
    across, side = _across(P[second] - P[first], forward, up)
    wrist_across, wrist_side = _across(P[arm[2]] - P[arm[1]], forward, up)
    turns = _turns_across(across, side, THUMB_SWING)
    return [{first: t} for t in turns] + [{first: t, hand: _turn(s * axis, THUMB_WRIST)} for t in turns
                                         for axis in (wrist_across, wrist_side) for s in (1, -1)]


def _arm_poses(P: np.ndarray, joints, lateral, up, forward) -> list[dict[int, Rotation]]:
    upper, lower, hand = joints
    arm, fore = P[lower] - P[upper], P[hand] - P[lower]
    across, side = _across(fore, forward, up)

    def pointing(e: float, h: float) -> np.ndarray:
        e, h = np.radians(e), np.radians(h)
        return -np.cos(e) * up + np.sin(e) * (np.cos(h) * lateral + np.sin(h) * forward)

    def swing_angle(target) -> float:
        return np.degrees(np.arccos(np.clip(_unit(arm) @ target, -1.0, 1.0)))

    poses = []
    for e in ARM_ELEVATIONS:
        for h in ARM_PLANES if e > 0 else (0.0,):
            target = pointing(e, h)
            if swing_angle(target) > MAX_ARM_SWING:
                continue
            for twist in (0.0,) + (ARM_TWISTS if e <= 90 else ()):
                if twist or swing_angle(target) > 1e-6:
                    poses.append({upper: _swing(arm, target, twist)})
    elbow = _toward(across, fore, forward)
    poses += [{lower: _turn(elbow, f)} for f in FLEXION]
    poses += [{hand: t} for t in _turns_across(across, side, WRIST_SWING)]
    poses += [{hand: _turn(s * axis, WRIST_SWING) * _turn(fore, t * WRIST_SWING_TWIST)}
              for axis in (across, side) for s in (1, -1) for t in (1, -1)]
    poses += [{hand: _turn(fore, s * WRIST_TWIST)} for s in (1, -1)]
    poses += [{upper: _swing(arm, pointing(e, h)), lower: _turn(elbow, f)} for e, h, f in ARM_ELBOW]
    return poses


def _leg_poses(P: np.ndarray, joints, lateral, left, forward) -> list[dict[int, Rotation]]:
    upper, lower, foot = joints
    thigh, shin = P[lower] - P[upper], P[foot] - P[lower]
    flex_axis = _toward(left, thigh, forward)
    abduction_axis = _toward(forward, thigh, lateral)
    knee = _toward(np.cross(shin, forward), shin, -forward)

    def pointing(f: float, a: float) -> np.ndarray:
        return (_turn(flex_axis, f) * _turn(abduction_axis, a)).apply(thigh)

    poses = [{upper: _swing(thigh, pointing(f, a))} for f in HIP_FLEXION for a in HIP_ABDUCTION if f or a]
    poses += [{upper: _swing(thigh, pointing(f, 0.0), t)} for f in (0.0, 90.0) for t in HIP_TWISTS]
    poses += [{lower: _turn(knee, f)} for f in FLEXION]
    poses += [{upper: _swing(thigh, pointing(f, 0.0)), lower: _turn(knee, k)} for f, k in HIP_KNEE]
    return poses


def anatomical_poses(skeleton: Skeleton) -> LocalPose:
    """The poses of the module docstring as a LocalPose (F, J, ...) float64; F = 0 for a skeleton
    without recognised humanoid limbs. Left side first, per side arm, thumb, then leg poses."""
    limbs, axes = humanoid_limbs(skeleton), body_axes(skeleton)
    poses: list[dict[int, Rotation]] = []
    if limbs and axes is not None:
        left, up, forward = axes
        P = skeleton.rest_globals()[:, :3, 3]
        for side, sign in (("left", 1.0), ("right", -1.0)):
            if (side, "arm") in limbs:
                poses += _arm_poses(P, limbs[side, "arm"], sign * left, up, forward)
            if (side, "thumb") in limbs:
                poses += _thumb_poses(P, limbs[side, "arm"], limbs[side, "thumb"], up, forward)
            if (side, "leg") in limbs:
                poses += _leg_poses(P, limbs[side, "leg"], sign * left, left, forward)
    rest = skeleton.rest_pose
    F, J = len(poses), skeleton.num_joints
    rotation = np.broadcast_to(rest.rotation, (F, J, 4)).copy()
    g = Rotation.from_matrix(polar_rotation(skeleton.rest_globals()[:, :3, :3]))
    for f, moves in enumerate(poses):
        for j, world in moves.items():
            rotation[f, j] = (Rotation.from_quat(rest.rotation[j]) * g[j].inv() * world * g[j]).as_quat()
    return LocalPose(np.broadcast_to(rest.translation, (F, J, 3)).copy(), rotation,
                     np.broadcast_to(rest.scale, (F, J, 3)).copy())
