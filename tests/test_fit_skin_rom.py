"""The range of motion of ``nrpose fit-skin``: axis sweeps alone for a skeleton without humanoid
limbs, plus anatomical bends (knees, elbows, shoulders, hips, wrists, thumbs) for a recognised humanoid."""
from collections import Counter

import numpy as np
import pytest

from nrpose.fit.anatomy import (ARM_ELEVATIONS, FLEXION, HIP_ABDUCTION, HIP_FLEXION, MAX_ARM_SWING, THUMB_SWING,
                                THUMB_WRIST, WRIST_SWING, WRIST_SWING_TWIST, WRIST_TWIST,
                                anatomical_poses, body_axes, humanoid_limbs)
from nrpose.fit.rom import axis_sweeps, range_of_motion
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import Skeleton
from nrpose.rigs.humanoid import humanoid

# body-frame positions (cm): left +x, up +y, forward +z; Mixamo names, T-pose, straight limbs
BODY = {"Hips": (None, (0, 100, 0)), "Spine": ("Hips", (0, 120, 0)), "Neck": ("Spine", (0, 150, 0)),
        "Head": ("Neck", (0, 165, 0))}
for _side, _x in (("Left", 1.0), ("Right", -1.0)):
    _chains = (("Spine", "Shoulder", 5, 145, 0), ("Shoulder", "Arm", 18, 145, 0), ("Arm", "ForeArm", 45, 145, 0),
               ("ForeArm", "Hand", 70, 145, 0), ("Hips", "UpLeg", 10, 95, 0), ("UpLeg", "Leg", 10, 52, 0),
               ("Leg", "Foot", 10, 9, 0), ("Foot", "ToeBase", 10, 2, 12),
               ("Hand", "HandThumb1", 72, 143, 3), ("HandThumb1", "HandThumb2", 75, 140, 6))
    for _parent, _part, _x0, _y, _z in _chains:
        BODY[_side + _part] = (_parent if _parent in ("Spine", "Hips") else _side + _parent, (_x0 * _x, _y, _z))


def mixamo_skeleton(facing: Rotation, seed: int = 1) -> Skeleton:
    """A Mixamo-named skeleton under an ``Armature`` root turned by ``facing`` and scaled by 0.01
    (as Mixamo exports), every bone with a random rest frame (its rest globals are ``facing``
    applied to BODY, in metres)."""
    rng = np.random.default_rng(seed)
    names = ["Armature"] + [f"mixamorig:{n}" for n in BODY]
    parents = [-1] + [0 if p is None else 1 + list(BODY).index(p) for p, _ in BODY.values()]
    P = np.vstack([[0, 0, 0], facing.apply(np.array([b for _, b in BODY.values()], float)) * 0.01])
    R = [facing] + [Rotation.from_rotvec(rng.normal(size=3)) for _ in BODY]
    rot, trans = [facing.as_quat()], [np.zeros(3)]
    for j in range(1, len(names)):
        p = parents[j]
        rot.append((R[p].inv() * R[j]).as_quat())
        trans.append(R[p].inv().apply(P[j] - P[p]) / (0.01 if p >= 0 else 1.0))
    scale = np.ones((len(names), 3))
    scale[0] = 0.01
    return Skeleton(names, parents, np.array(trans), np.array(rot), scale)


def cases():
    facing = Rotation.from_euler("y", 70, degrees=True)     # faces +z turned 70° about up
    return [("mixamo", mixamo_skeleton(facing), facing.apply([1.0, 0, 0]), facing.apply([0, 0, 1.0])),
            ("humanoid", humanoid(resolution=0.05).skeleton, np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))]


CASES = cases()


def moved(skeleton, pose):
    """(F, J) bool: joints whose rotation differs from rest."""
    return ~np.isclose(np.abs((pose.rotation * skeleton.rotation).sum(-1)), 1.0, atol=1e-12, rtol=0)


def positions(skeleton, pose):
    return skeleton.forward_kinematics(pose)[..., :3, 3]


def only(skeleton, pose, name):
    """Indices of the poses that move joint ``name`` alone."""
    m = moved(skeleton, pose)
    j = next(i for i, n in enumerate(skeleton.names) if n.rsplit(":", 1)[-1] == name)
    return np.flatnonzero(m[:, j] & (m.sum(axis=1) == 1))


def index(skeleton, name):
    return next(i for i, n in enumerate(skeleton.names) if n.rsplit(":", 1)[-1] == name)


def test_a_skeleton_without_humanoid_limbs_gets_exactly_the_axis_sweeps():
    # a quadruped-like rig named as the Fox is: nothing recognised
    names = ["b_Root_00", "b_Hip_01", "b_Spine01_02", "b_LeftLeg01_015", "b_LeftLeg02_016", "b_Tail01_012"]
    parents = [-1, 0, 1, 1, 3, 1]
    rng = np.random.default_rng(3)
    skel = Skeleton(names, parents, rng.normal(size=(6, 3)), Rotation.from_rotvec(rng.normal(size=(6, 3))).as_quat(),
                    np.ones((6, 3)))
    assert humanoid_limbs(skel) == {} and body_axes(skel) is None
    assert len(anatomical_poses(skel).rotation) == 0
    rom, sweeps = range_of_motion(skel, 60.0, pairs=2), axis_sweeps(skel, 60.0, pairs=2)
    assert rom.rotation.shape == (12 * 6 + 2 * 5, 6, 4)
    for key in ("translation", "rotation", "scale"):
        assert getattr(rom, key).tobytes() == getattr(sweeps, key).tobytes()


@pytest.mark.parametrize("name,skel,left,forward", CASES, ids=[c[0] for c in CASES])
def test_humanoid_gets_the_sweeps_then_anatomical_poses(name, skel, left, forward):
    assert len(humanoid_limbs(skel)) == (6 if name == "mixamo" else 4)      # nrpose's humanoid rig has no thumbs
    axes = body_axes(skel)
    assert np.allclose(axes[0], left, atol=1e-9) and axes[2] @ forward > 0.99
    rom, sweeps, anatomy = range_of_motion(skel), axis_sweeps(skel), anatomical_poses(skel)
    F = len(sweeps.rotation)
    assert len(rom.rotation) == F + len(anatomy.rotation) and len(anatomy.rotation) > 100
    assert rom.rotation[:F].tobytes() == sweeps.rotation.tobytes()
    assert rom.rotation[F:].tobytes() == anatomy.rotation.tobytes()
    q = anatomy.rotation
    assert np.isfinite(q).all() and np.allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.array_equal(anatomy.translation, np.broadcast_to(skel.translation, anatomy.translation.shape))
    assert np.array_equal(anatomy.scale, np.broadcast_to(skel.scale, anatomy.scale.shape))
    again = anatomical_poses(skel)
    assert again.rotation.tobytes() == q.tobytes()
    # one joint moves, or a limb's upper and middle joint together (a thumb's: the hand and thumb1); no pose twice
    m = moved(skel, anatomy)
    assert ((m.sum(axis=1) == 1) | (m.sum(axis=1) == 2)).all()
    pairs = {tuple(np.flatnonzero(row)) for row in m if row.sum() == 2}
    limbs = humanoid_limbs(skel).values()
    assert pairs == {(u, l) for u, l, _ in limbs}
    flat = np.round(q.reshape(len(q), -1) * np.sign(q[..., 3:]).reshape(len(q), -1).repeat(4, axis=1), 9)
    assert len(np.unique(flat, axis=0)) == len(q)


@pytest.mark.parametrize("name,skel,left,forward", CASES, ids=[c[0] for c in CASES])
def test_knee_flexion_moves_the_ankle_behind_the_knee(name, skel, left, forward):
    pose = anatomical_poses(skel)
    P, P0 = positions(skel, pose), skel.rest_globals()[:, :3, 3]
    for side in ("Left", "Right"):
        hip, knee, ankle = (index(skel, side + n) for n in ("UpLeg", "Leg", "Foot"))
        f = only(skel, pose, side + "Leg")
        assert len(f) == len(FLEXION)
        shin = P[f, ankle] - P[f, knee]
        assert (shin @ forward < 0).all() and ((P[f, ankle] - P0[ankle]) @ forward < 0).all()
        shin0 = P0[ankle] - P0[knee]
        cos = shin @ shin0 / np.linalg.norm(shin, axis=1) / np.linalg.norm(shin0)
        bend = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        assert np.allclose(bend, FLEXION, atol=1e-6)        # a hinge perpendicular to the shin
        assert np.allclose(P[f, hip], P0[hip]) and np.allclose(P[f, knee], P0[knee])


@pytest.mark.parametrize("name,skel,left,forward", CASES, ids=[c[0] for c in CASES])
def test_elbow_flexion_moves_the_wrist_forward_toward_the_shoulder(name, skel, left, forward):
    pose = anatomical_poses(skel)
    P, P0 = positions(skel, pose), skel.rest_globals()[:, :3, 3]
    upper = "Arm" if name == "mixamo" else "UpperArm"
    lower = "ForeArm" if name == "mixamo" else "LowerArm"
    for side in ("Left", "Right"):
        shoulder, elbow, wrist = (index(skel, side + n) for n in (upper, lower, "Hand"))
        f = only(skel, pose, side + lower)
        assert len(f) == len(FLEXION)
        reach = np.linalg.norm(P[f, wrist] - P0[shoulder], axis=1)
        rest = np.linalg.norm(P0[wrist] - P0[shoulder])
        assert (np.diff(reach) < 0).all() and reach[0] < rest and reach[-1] < 0.5 * rest
        assert ((P[f, wrist] - P0[wrist]) @ forward > 0).all()


@pytest.mark.parametrize("name,skel,left,forward", CASES, ids=[c[0] for c in CASES])
def test_hip_flexion_moves_the_knee_forward_and_abduction_stays_distinct_when_flexed(name, skel, left, forward):
    pose = anatomical_poses(skel)
    P, P0 = positions(skel, pose), skel.rest_globals()[:, :3, 3]
    left, up, forward = body_axes(skel)      # checked against the built facing above
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        hip, knee = index(skel, side + "UpLeg"), index(skel, side + "Leg")
        f = only(skel, pose, side + "UpLeg")
        thigh0 = P0[knee] - P0[hip]
        thigh = (P[f, knee] - P[f, hip]) / np.linalg.norm(thigh0)
        d0 = thigh0 / np.linalg.norm(thigh0)
        flexed = {}
        for flexion in HIP_FLEXION:
            for abduction in HIP_ABDUCTION:
                if not (flexion or abduction):
                    continue
                # a thigh hanging down: outward about ±forward, then knee forward about -left
                want = (Rotation.from_rotvec(-np.radians(flexion) * left)
                        * Rotation.from_rotvec(np.radians(abduction) * sign * forward)).apply(d0)
                hits = np.flatnonzero(np.linalg.norm(thigh - want, axis=1) < 1e-6)
                assert len(hits), (side, flexion, abduction)
                if flexion > 0 and abduction == 0:
                    assert want @ forward > 0 and ((P[f[hits], knee] - P0[knee]) @ forward > 0).all()
                if flexion == 90:
                    flexed[abduction] = want
        # at 90° flexion (thigh forward) adduction, none and abduction point the knee apart
        dirs = np.array(list(flexed.values()))
        gaps = np.linalg.norm(dirs[:, None] - dirs[None], axis=2)[np.triu_indices(len(dirs), 1)]
        assert len(dirs) == len(HIP_ABDUCTION) and gaps.min() > 0.3
        lateral = {a: d @ (sign * left) for a, d in flexed.items()}
        assert lateral[min(HIP_ABDUCTION)] < 0 < lateral[max(HIP_ABDUCTION)]
        assert all(abs(d @ up) < 0.2 for d in dirs)


@pytest.mark.parametrize("name,skel,left,forward", CASES, ids=[c[0] for c in CASES])
def test_shoulder_poses_lower_raise_and_twist_the_arm_within_the_limit(name, skel, left, forward):
    pose = anatomical_poses(skel)
    P, P0 = positions(skel, pose), skel.rest_globals()[:, :3, 3]
    up = np.cross(forward, left)
    upper, lower = ("Arm", "ForeArm") if name == "mixamo" else ("UpperArm", "LowerArm")
    for side in ("Left", "Right"):
        shoulder, elbow = index(skel, side + upper), index(skel, side + lower)
        f = only(skel, pose, side + upper)
        arm0 = P0[elbow] - P0[shoulder]
        arm = P[f, elbow] - P[f, shoulder]
        cos = arm @ arm0 / np.linalg.norm(arm, axis=1) / np.linalg.norm(arm0)
        swing = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        assert swing.max() <= MAX_ARM_SWING + 1e-6 and swing.max() > 120
        along_up = arm @ up / np.linalg.norm(arm, axis=1)
        assert along_up.min() < -0.999 and along_up.max() > np.cos(np.radians(180 - max(ARM_ELEVATIONS))) - 1e-6
        # twisted poses: same arm direction as another pose, different rotation
        _, counts = np.unique(np.round(arm / np.linalg.norm(arm, axis=1, keepdims=True), 6), axis=0,
                              return_counts=True)
        assert counts.max() >= 5


@pytest.mark.parametrize("name,skel,left,forward", CASES, ids=[c[0] for c in CASES])
def test_wrist_poses_swing_about_four_axes_across_the_forearm_twist_and_combine(name, skel, left, forward):
    """Hand-only poses per side: ±WRIST_SWING about 4 axes across the forearm (the main two and
    their diagonals), the main two after a ±WRIST_SWING_TWIST twist, ±WRIST_TWIST about the
    forearm; the hand turns in the world as stated (its rest global rotation to the posed one)."""
    pose = anatomical_poses(skel)
    G, G0 = skel.forward_kinematics(pose), skel.rest_globals()
    lower = "ForeArm" if name == "mixamo" else "LowerArm"
    for side in ("Left", "Right"):
        hand, elbow = index(skel, side + "Hand"), index(skel, side + lower)
        f = only(skel, pose, side + "Hand")
        assert len(f) == 8 + 8 + 2
        fore = (G0[hand, :3, 3] - G0[elbow, :3, 3]) / np.linalg.norm(G0[hand, :3, 3] - G0[elbow, :3, 3])
        turns = Rotation.from_matrix(G[f, hand, :3, :3] / np.linalg.norm(G[f, hand, :3, 0], axis=-1)[:, None, None]
                                     ) * Rotation.from_matrix(G0[hand, :3, :3] / np.linalg.norm(G0[hand, :3, 0])).inv()
        vec = turns.as_rotvec()
        angle, axis = np.degrees(np.linalg.norm(vec, axis=1)), vec / np.linalg.norm(vec, axis=1)[:, None]
        swings = np.isclose(angle, WRIST_SWING, atol=1e-6) & (np.abs(axis @ fore) < 1e-6)
        assert swings.sum() == 8
        directions = {tuple(np.round(a * np.sign(a[np.argmax(np.abs(a))]), 6)) for a in axis[swings]}
        assert len(directions) == 4                       # 4 axes, each both ways
        twists = np.isclose(angle, WRIST_TWIST, atol=1e-6) & np.isclose(np.abs(axis @ fore), 1, atol=1e-6)
        assert twists.sum() == 2
        combined = 2 * np.degrees(np.arccos(np.cos(np.radians(WRIST_SWING / 2)) *
                                            np.cos(np.radians(WRIST_SWING_TWIST / 2))))
        assert np.isclose(angle[~swings & ~twists], combined, atol=1e-6).all()


def world_turns(G, G0, frames, joint):
    """Rotation vectors (n, 3) of joint's world rotation from rest in frames, and their angles in degrees."""
    unit = np.linalg.norm(G0[joint, :3, 0])
    turns = Rotation.from_matrix(G[frames, joint, :3, :3] / unit) * Rotation.from_matrix(G0[joint, :3, :3] / unit).inv()
    vec = turns.as_rotvec()
    return vec, np.degrees(np.linalg.norm(vec, axis=1))


def test_thumb_poses_turn_the_thumb_across_itself_alone_and_with_the_hand():
    """Per side: the thumb turned ±THUMB_SWING about 4 axes across its bone (8 poses), each alone
    and with the hand turned ±THUMB_WRIST about the wrist's 2 swing axes (the 4 x 8 pairs once
    each); a skeleton without thumbs has none of these poses."""
    name, skel, left, forward = CASES[0]
    pose = anatomical_poses(skel)
    G, G0 = skel.forward_kinematics(pose), skel.rest_globals()
    m = moved(skel, pose)
    for side in ("Left", "Right"):
        hand, first, second = (index(skel, side + n) for n in ("Hand", "HandThumb1", "HandThumb2"))
        alone = only(skel, pose, side + "HandThumb1")
        assert len(alone) == 8
        bone = G0[second, :3, 3] - G0[first, :3, 3]
        vec, angle = world_turns(G, G0, alone, first)
        assert np.allclose(angle, THUMB_SWING, atol=1e-6)
        assert np.allclose(vec @ bone, 0, atol=1e-9)                    # across the thumb
        assert len({key(v) for v in vec}) == 4                          # 4 axes, each both ways
        assert (np.linalg.norm(G[alone, second, :3, 3] - G0[second, :3, 3], axis=1) > 0.01).all()
        both = np.flatnonzero(m[:, hand] & m[:, first])
        assert len(both) == 32 and (m[both].sum(axis=1) == 2).all()
        hand_vec, hand_angle = world_turns(G, G0, both, hand)
        fore = G0[hand, :3, 3] - G0[index(skel, side + "ForeArm"), :3, 3]
        across = np.cross(fore, forward) / np.linalg.norm(np.cross(fore, forward))
        side_axis = np.cross(fore, across) / np.linalg.norm(fore)
        assert np.allclose(hand_angle, THUMB_WRIST, atol=1e-6)
        axes = hand_vec / np.linalg.norm(hand_vec, axis=1)[:, None]
        assert np.allclose(np.abs(axes @ across) + np.abs(axes @ side_axis), 1, atol=1e-9)   # the two main axes
        assert sorted(Counter(tuple(np.round(h, 6)) for h in hand_vec).values()) == [8] * 4    # each turn with 8 thumbs
        # the thumb's own turn (its world turn with the hand's taken off) is one of the 8 alone
        unit = np.linalg.norm(G0[first, :3, 0])
        own = (Rotation.from_rotvec(hand_vec).inv() * Rotation.from_matrix(G[both, first, :3, :3] / unit)
               * Rotation.from_matrix(G0[first, :3, :3] / unit).inv()).as_rotvec()
        alone_turns = {tuple(np.round(v, 6)) for v in vec}
        pairs = [(tuple(np.round(o, 6)), tuple(np.round(h, 6))) for o, h in zip(own, hand_vec)]
        assert {p[0] for p in pairs} == alone_turns and len(set(pairs)) == 32
    assert not any(k[1] == "thumb" for k in humanoid_limbs(CASES[1][1]))


def test_a_thumb_along_forward_or_of_no_length_gets_no_nan():
    """A thumb bone along forward takes its axes across it from up; a thumb of zero length is not a limb."""
    name, skel, left, forward = CASES[0]
    first = index(skel, "LeftHandThumb1")
    second = index(skel, "LeftHandThumb2")
    for offset, limb in ((np.array([0.0, 0.0, 5.0]), True), (np.zeros(3), False)):
        t = skel.translation.copy()
        # thumb2's offset in thumb1's frame that puts it `offset` cm (body frame) from thumb1
        R1 = Rotation.from_matrix(skel.rest_globals()[first, :3, :3] / np.linalg.norm(skel.rest_globals()[first, :3, 0]))
        t[second] = R1.inv().apply(Rotation.from_euler("y", 70, degrees=True).apply(offset) * 0.01) / 0.01
        bent = Skeleton(skel.names, skel.parents, t, skel.rotation, skel.scale)
        assert (("left", "thumb") in humanoid_limbs(bent)) == limb
        q = anatomical_poses(bent).rotation
        assert np.isfinite(q).all() and np.allclose(np.linalg.norm(q, axis=-1), 1, atol=1e-12)
        assert len(q) == len(anatomical_poses(skel).rotation) - (0 if limb else 40)


def key(v):
    """A rotation vector's axis line, rounded (v and -v give the same key)."""
    return tuple(np.round(v * np.sign(v[np.argmax(np.abs(v))]) / np.linalg.norm(v), 6))
