"""Retargeting: a motion recorded on one skeleton played on another.

    mapping = joint_map(source.skeleton, target.skeleton, user_map)   # {target joint: source joint}
    clip = retarget(source, source.clips[0], target, mapping, root="origin", fps=30)

The source and the target may differ in joint names, proportions, bone frames
(rest local rotations) and rest posture (T- against A-pose, splayed legs).
The result is a :class:`~nrpose.model.character.Clip` of the target that keys
every joint's translation, rotation and scale (so an engine switching from
another clip resets them all): rotations of the mapped joints and the
translation of the root-motion joint (the mapped joint nearest the root,
normally the hips) follow the source; every other local value is keyed at the
target's rest value (two keys, at the start and the end), so target bone
lengths never change.

Coverage (:func:`coverage`, :func:`check_coverage`)
--------------------------------------------------
A mapping that leaves large parts of the target at rest (a human motion on a
quadruped: its hind legs and tail would hang still) is refused unless forced.
The measure is the share of the target's bone length (:meth:`Skeleton.bones`,
zero-length bones and bones above the root-motion joint left out) whose
driving joint is mapped; at least :data:`MIN_COVERAGE` is needed, and no part
left at rest (a maximal subtree without a mapped joint) may hold more than
:data:`MAX_PART_AT_REST` of it. A Mixamo character driven by a CMU capture
without fingers reaches 0.84, its largest part at rest a finger (1.6%); the Fox
sample driven on hips, spine, neck, head and front legs reaches 0.61, a hind
leg at rest holding 14%.

Joint mapping (:func:`joint_map`)
---------------------------------
Names are compared case-, prefix- and separator-insensitively: a namespace
(``mixamorig:``) and rig prefixes (``mixamorig_``, ``Bip01``, ``DEF-``...)
are dropped, the rest is split into words at separators and camelCase
boundaries, a side word (``Left``/``L``/``l_``/``.R``/``_r``... or a glued
``l``/``r`` before a known part, as in ``LHipJoint`` or ``lhand``) is taken
out, and the remaining words are looked up in a table of body parts shared by
CMU BVH (both the ``LeftUpLeg``/``LowerBack`` and the ``LeftHip``/``lowerback``
/``LeftCollar`` variants), Mixamo, Unreal/Blender-style and generic humanoid
names. Rules, in order of precedence:

1. The user map ``{"TargetJoint": "SourceJoint"}`` overrides everything
   (``null`` unmaps a joint). Unknown names are an error.
2. The trunk is mapped by structure: the joints strictly between the hips and
   the neck (the lowest joint named ``*neck*`` on the way from the hips to the
   head) are paired in order when both rigs have as many, else by their
   relative arc-length position along the hips → neck path (one to one, in
   order, the extra joints of the longer chain unmapped). Likewise the joints
   between the neck and the head. So Mixamo ``Spine, Spine1, Spine2`` take
   CMU ``lowerback, Chest, Chest2`` (or ``LowerBack, Spine, Spine1``).
3. Body parts (slots): hips; neck; head; head top; eyes; jaw; per side
   clavicle, upper arm, forearm, hand, thumb/index/middle/ring/pinky 1..n,
   upper leg, lower leg, foot, toes, toe end. Aliases that depend on the rig:
   ``Shoulder`` is the clavicle (Mixamo, CMU ``LeftShoulder``/``LeftArm``)
   unless the same side has a ``Collar``/``Clavicle`` joint, when it is the
   upper arm (CMU ``LeftCollar``/``LeftShoulder``/``LeftElbow``); ``Hip``
   with a side is the upper leg (``LeftHip``), ``HipJoint`` is not a body part
   (a zero-length pelvis joint); ``Wrist`` and ``Hand`` (``Ankle``/``Foot``)
   are the same part, the one nearest the root wins.
4. Left-over target joints take a source joint of the same normalised name.

Each source joint is used at most once by the automatic rules.

Rest alignment
--------------
The rigs' rest postures differ, so every mapped target joint ``j`` (source
``s``) gets a fixed world rotation ``A_j`` that turns its rest bone(s) onto
the source's rest bone(s). A *bone pair* of ``j`` is (target ``j → c``, source
``s → m(c)``) for each nearest mapped descendant ``c`` of ``j``; where either
side has zero length (CMU ``LHipJoint``, ``lowerneck``, collars at the chest)
it looks through to the mapped descendants of ``c``. One pair (a chain joint:
limbs, spine, neck): ``A_j`` is the minimal rotation taking the target
direction onto the source direction, exactly. Several pairs (branch joints:
hips, upper chest): when two of them end at left/right counterparts (upper
legs, clavicles or upper arms), ``A_j`` matches the frames built from the
lateral direction (left end − right end, exactly; looking further down
both chains while the two ends coincide) and the remaining bones'
summed direction (spine, neck: as closely as the lateral constraint allows);
else it is the least-squares rotation of the unit directions. Pelvis and rib
cage shapes differ between rigs (CMU hip joints sit 19° in front of the
root), so a residual angle remains on those bones; it is the same in every
frame, and fitting it instead would tilt the target's pelvis. No pair (hands, head, toes): the
direction to the mean end of the joint's own bones (:meth:`Skeleton.bones`).

Transfer
--------
With source world rotations ``S_s(t)`` (polar parts of the global matrices,
so scaled frames such as Mixamo's 0.01 armature are fine) and target rest
world rotations ``T_j``::

    W_j(t) = S_s(t) · S_s(rest)⁻¹ · A_j · T_j

so a target bone turns exactly as its source bone turned from the source's
rest, twist included, starting from the source's rest posture. A chain joint
then gets the minimal extra rotation that puts its bone on the current source
bone direction (identity unless an unmapped source joint in between moved,
e.g. CMU's upper ``Neck`` under the mapped ``lowerneck``). Local rotations
follow from the target's hierarchy, parents first:
``L_j = polar(G_parent(t) · pre_j)⁻¹ · W_j``. Unmapped target joints keep
their rest local rotation (fingers without source fingers follow the hand).

Root motion
-----------
The root-motion joint's world position is the source's mapped joint's world
position times ``k = leg_target / leg_source``. Both rigs are taken to be
Y-up with the ground at y = 0 (glTF, BVH). Leg length: vertical drop from the
hips to the upper-leg joint + upper- and lower-leg lengths + ankle height
above the lowest point of the foot in the rest pose (a straightened leg; the
CMU rest pose has splayed legs), averaged over the sides found; without
mapped legs, the rest height of the hips above the lowest joint. The pelvis
and feet differ between rigs (CMU hip joints sit lower and further forward
under the root than Mixamo ones, CMU ankles lower above the sole), so the
root then gets one constant vertical offset, the median over the frames of
``k · sole_source(t) − sole_target(t)`` (sole: the lowest joint or bone tip of
the mapped feet): the target's feet touch down where the source's scaled feet
do (:attr:`RetargetPlan.lift`). The horizontal root motion (:data:`ROOT_MODES`):
``"origin"`` (default) shifts it so the first frame has the root above the
origin, heading kept (viewers frame and cull the character by its rest bounds,
so a capture that starts metres away would be culled); ``"keep"`` keeps the
capture's absolute positions; ``"in-place"`` holds the root over the target's
rest position (vertical motion stays).

Frames are sampled from the source clip at ``k / fps`` seconds before its end,
then at its end (:func:`nrpose.model.timing.sample_times`: the last key is kept,
loops close); the clip keys the target at those times (LINEAR). ``close=False``
samples the grid only (BVH output, fixed frame time).
"""
from __future__ import annotations

import itertools
import re
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..model.character import Character, Clip, Track
from ..model.rotation import Rotation, kabsch, minimal_rotvec
from ..model.skeleton import LocalPose, Skeleton, match_hint, polar_rotation
from ..model.timing import sample_times

__all__ = ["joint_map", "format_map", "normalize_name", "joint_slots", "mapped_bones", "leg_length",
           "sole_heights", "sample_times", "ROOT_MODES", "MIN_COVERAGE", "MAX_PART_AT_REST", "Coverage", "coverage",
           "check_coverage", "skinned_bounds", "RetargetPlan", "retarget", "retarget_pose", "make_clip"]

UP = 1  # +Y is up in both rigs (glTF; BVH as conventionally recorded)
ROOT_MODES = ("origin", "keep", "in-place")
MIN_COVERAGE = 0.7        # share of the target's bone length that mapped joints must drive
MAX_PART_AT_REST = 0.1    # largest share of it one unmapped part (a subtree) may hold

# --------------------------------------------------------------------------- names

_WORDS = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")
_PREFIXES = {"mixamorig", "bip", "biped", "def", "org", "mch", "jnt", "bn", "b", "j", "armature", "rig"}
_LEFT, _RIGHT = {"left", "l", "lt"}, {"right", "r", "rt"}

# body part words (joined, lower case) → part; "shoulder" and "hip" are resolved per rig
_SIDED = {
    "collar": "clavicle", "clavicle": "clavicle", "collarbone": "clavicle", "shoulder": "shoulder",
    "arm": "upperarm", "upperarm": "upperarm", "uparm": "upperarm", "humerus": "upperarm",
    "forearm": "forearm", "lowerarm": "forearm", "loarm": "forearm", "elbow": "forearm",
    "hand": "hand", "wrist": "hand", "palm": "hand",
    "upleg": "upperleg", "upperleg": "upperleg", "thigh": "upperleg", "femur": "upperleg", "hip": "upperleg",
    "leg": "lowerleg", "lowerleg": "lowerleg", "loleg": "lowerleg", "knee": "lowerleg", "calf": "lowerleg",
    "shin": "lowerleg", "foot": "foot", "ankle": "foot",
    "toe": "toes", "toes": "toes", "toebase": "toes", "ball": "toes",
    "toeend": "toeend", "toesend": "toeend", "toetip": "toeend", "toeendsite": "toeend",
    "eye": "eye", "fingers": "fingers", "fingerbase": "fingers", "handfingers": "fingers",
}
_CENTRAL = {"hips": "hips", "hip": "hips", "pelvis": "hips", "head": "head", "jaw": "jaw",
            "headtop": "headtop", "headtopend": "headtop", "headend": "headtop", "headnub": "headtop"}
_FINGER = re.compile(r"^(?:hand)?(thumb|index|middle|ring|pinky|pinkie|little)(?:finger)?(\d*)(end)?$")
_FINGER_NAMES = {"pinkie": "pinky", "little": "pinky"}


def _words(name: str) -> list[str]:
    base = str(name).rsplit(":", 1)[-1]
    words = []
    for chunk in re.split(r"[^A-Za-z0-9]+", base):
        words += [w.lower() for w in _WORDS.findall(chunk)]
    while len(words) > 1 and (words[0] in _PREFIXES or re.fullmatch(r"mixamorig\d*|bip\d*", words[0])):
        words = words[1:]
        while len(words) > 1 and words[0].isdigit():
            words = words[1:]
    return words


def normalize_name(name: str) -> str:
    """Case-, prefix- and separator-free form of a joint name (``mixamorig:Left_Arm`` → ``leftarm``)."""
    return "".join(_words(name))


def _split_side(name: str) -> tuple[str, str]:
    """(side ``"left"``/``"right"``/``""``, part words joined) of a joint name."""
    words = _words(name)
    for k, w in enumerate(words):
        if (w in _LEFT or w in _RIGHT) and len(words) > 1:
            return ("left" if w in _LEFT else "right"), "".join(words[:k] + words[k + 1:])
    joined = "".join(words)
    for side, pre in (("left", "left"), ("right", "right")):
        if joined.startswith(pre) and len(joined) > len(pre):
            return side, joined[len(pre):]
    if len(joined) > 1 and joined[0] in "lr":
        rest = joined[1:]
        if rest in _SIDED or rest == "hipjoint" or _FINGER.match(rest):
            return ("left" if joined[0] == "l" else "right"), rest
    return "", joined


def _part(side: str, part: str, has_collar: bool) -> str | None:
    if not side:
        return _CENTRAL.get(part)
    m = _FINGER.match(part)
    if m:
        finger = _FINGER_NAMES.get(m.group(1), m.group(1))
        return f"{side}_{finger}{m.group(3) and 'end' or int(m.group(2) or 1)}"
    kind = _SIDED.get(part)
    if kind == "shoulder":
        kind = "upperarm" if has_collar else "clavicle"
    return f"{side}_{kind}" if kind else None


def _depths(skel: Skeleton) -> np.ndarray:
    depth = np.zeros(skel.num_joints, np.int64)
    for j, p in enumerate(skel.parents):
        depth[j] = depth[p] + 1 if p >= 0 else 0
    return depth


def _path_up(skel: Skeleton, j: int, stop: int) -> list[int] | None:
    """Joints strictly between ``stop`` and ``j`` (from stop down), or None if stop is no ancestor."""
    out, a = [], int(skel.parents[j])
    while a >= 0 and a != stop:
        out.append(a)
        a = int(skel.parents[a])
    return out[::-1] if a == stop else None


def joint_slots(skel: Skeleton) -> dict[int, str]:
    """Body-part slot of each recognised joint (rule 3 of the module docstring), joint index → slot."""
    parts = [_split_side(n) for n in skel.names]
    collar = {side for side, p in parts if side and _SIDED.get(p) == "clavicle"}
    depth = _depths(skel)
    found: dict[str, int] = {}
    for j, (side, p) in enumerate(parts):
        slot = _part(side, p, side in collar)
        if slot is None:
            continue
        if slot not in found or depth[j] < depth[found[slot]]:
            found[slot] = j
    slots = {j: s for s, j in found.items()}
    # the neck: the lowest joint named *neck* between the hips and the head
    if "head" in found:
        hips = found.get("hips")
        chain = [a for a in _ancestors(skel, found["head"]) if hips is None or a != hips][::-1]
        neck = next((a for a in chain if "neck" in normalize_name(skel.names[a])), None)
        if neck is not None:
            slots[neck] = "neck"
    return slots


def _ancestors(skel: Skeleton, j: int) -> list[int]:
    out, a = [], int(skel.parents[j])
    while a >= 0:
        out.append(a)
        a = int(skel.parents[a])
    return out


def _arc(skel: Skeleton, pos: np.ndarray, start: int, chain: list[int], end: int) -> np.ndarray:
    """Relative arc-length positions (0..1) of the chain joints along start → chain → end."""
    pts = pos[[start, *chain, end]]
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    return cum[1:-1] / max(cum[-1], 1e-300)


def _pair_chains(ft: np.ndarray, fs: np.ndarray) -> list[tuple[int, int]]:
    """Order-preserving one-to-one pairs (target index, source index) of two chains."""
    if len(ft) == 0 or len(fs) == 0:
        return []
    if len(ft) == len(fs):
        return list(zip(range(len(ft)), range(len(fs))))
    best = None
    if len(ft) < len(fs):
        for pick in itertools.combinations(range(len(fs)), len(ft)):
            cost = float(np.abs(ft - fs[list(pick)]).sum())
            if best is None or cost < best[0]:
                best = (cost, list(zip(range(len(ft)), pick)))
    else:
        for pick in itertools.combinations(range(len(ft)), len(fs)):
            cost = float(np.abs(ft[list(pick)] - fs).sum())
            if best is None or cost < best[0]:
                best = (cost, list(zip(pick, range(len(fs)))))
    return best[1]


def _trunk_chains(skel: Skeleton, slots: dict[int, str]) -> list[tuple[list[int], np.ndarray]]:
    """[(hips → neck chain, arc positions), (neck → head chain, arc positions)]; empty lists if unknown."""
    by_slot = {s: j for j, s in slots.items()}
    pos = skel.rest_globals()[:, :3, 3]
    out = []
    for lo, hi in (("hips", "neck"), ("neck", "head")):
        a, b = by_slot.get(lo), by_slot.get(hi)
        chain = None if a is None or b is None else _path_up(skel, b, a)
        if chain is None:
            out.append(([], np.zeros(0)))
        else:
            out.append((chain, _arc(skel, pos, a, chain, b)))
    return out


def joint_map(source_skel: Skeleton, target_skel: Skeleton, user_map: dict | None = None) -> dict[str, str]:
    """Target joint name → source joint name (see the module docstring for the rules).

    user_map: {target name: source name or None}; unknown names raise InputError.
    """
    user_map = dict(user_map or {})
    for t, s in user_map.items():
        if t not in target_skel.names:
            raise InputError(f"joint map: target joint {t!r} does not exist; "
                             f"{match_hint(str(t), target_skel.names)}")
        if s is not None and s not in source_skel.names:
            raise InputError(f"joint map: source joint {s!r} (for {t!r}) does not exist; "
                             f"{match_hint(str(s), source_skel.names)}")
    ss, ts = joint_slots(source_skel), joint_slots(target_skel)
    mapping: dict[int, int] = {}
    used: set[int] = set()

    def put(t: int, s: int) -> None:
        if t not in mapping and s not in used:
            mapping[t] = s
            used.add(s)

    for (tc, tf), (sc, sf) in zip(_trunk_chains(target_skel, ts), _trunk_chains(source_skel, ss)):
        for a, b in _pair_chains(tf, sf):
            put(tc[a], sc[b])
    src_by_slot = {slot: j for j, slot in ss.items()}
    for t, slot in ts.items():
        if slot in src_by_slot:
            put(t, src_by_slot[slot])
    src_by_name = {}
    for j, n in enumerate(source_skel.names):
        src_by_name.setdefault(normalize_name(n), j)
    for t, n in enumerate(target_skel.names):
        s = src_by_name.get(normalize_name(n))
        if s is not None and t not in ts and s not in ss:
            put(t, s)
    out = {target_skel.names[t]: source_skel.names[s] for t, s in mapping.items()}
    for t, s in user_map.items():
        if s is None:
            out.pop(t, None)
        else:
            out[t] = s
    return {n: out[n] for n in target_skel.names if n in out}


def format_map(mapping: dict[str, str], source_skel: Skeleton, target_skel: Skeleton) -> str:
    """Human-readable mapping: pairs in target order, then unmapped target and source joints."""
    width = max((len(t) for t in mapping), default=0)
    lines = [f"joint map (target <- source): {len(mapping)} of {target_skel.num_joints} target joints"]
    lines += [f"  {t:<{width}}  <-  {s}" for t, s in mapping.items()]
    free_t = [n for n in target_skel.names if n not in mapping]
    used = set(mapping.values())
    free_s = [n for n in source_skel.names if n not in used]
    lines.append(f"unmapped target joints ({len(free_t)}, keep their rest rotation): {', '.join(free_t) or '-'}")
    lines.append(f"unused source joints ({len(free_s)}): {', '.join(free_s) or '-'}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- geometry helpers

def _align(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotation matrices (..., 3, 3) taking directions a onto b (a half turn about a
    perpendicular axis when they are opposite)."""
    rv = minimal_rotvec(a, b, opposite="half_turn")
    return Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(rv.shape[:-1] + (3, 3))


def _left_right(slots: list) -> tuple[int, int] | None:
    """Indices of the first left/right counterparts (``left_X``, ``right_X``) among slots, or None."""
    for a, sa in enumerate(slots):
        if sa and sa.startswith("left_"):
            for b, sb in enumerate(slots):
                if sb == "right_" + sa[5:]:
                    return a, b
    return None


def _frame(lateral: np.ndarray, primary: np.ndarray) -> np.ndarray | None:
    if not np.linalg.norm(lateral) > 0:
        return None
    x = lateral / np.linalg.norm(lateral)
    y = primary - (primary @ x) * x
    n = np.linalg.norm(y)
    if not np.isfinite(n) or n < 1e-9:
        return None
    y /= n
    return np.stack([x, y, np.cross(x, y)], axis=1)


def _frame_align(lat_t, pri_t, lat_s, pri_s) -> np.ndarray | None:
    """Rotation taking the target frame (lateral exact, primary in its plane) onto the source's."""
    Ft, Fs = _frame(lat_t, pri_t), _frame(lat_s, pri_s)
    return None if Ft is None or Fs is None else Fs @ Ft.T


def _lateral(ts: Skeleton, m: dict[int, int], pt, ps, a: int, b: int, eps_t: float, eps_s: float):
    """(target, source) vectors from the right counterpart b to the left one a, looking down both
    chains (first mapped descendants) while they coincide in either rig (CMU collars start at one
    point); None when they never separate."""
    mapped = set(m)
    while True:
        lt, ls = pt[a] - pt[b], ps[m[a]] - ps[m[b]]
        if np.linalg.norm(lt) > eps_t and np.linalg.norm(ls) > eps_s:
            return lt, ls
        da, db = _nearest_mapped(ts, a, mapped), _nearest_mapped(ts, b, mapped)
        if not da or not db:
            return None
        a, b = da[0], db[0]


def _rotations(G: np.ndarray) -> np.ndarray:
    return polar_rotation(G[..., :3, :3])


def _extent(pos: np.ndarray) -> float:
    return float(np.ptp(pos, axis=0).max(initial=0.0)) if len(pos) else 0.0


def _nearest_mapped(skel: Skeleton, j: int, mapped: set[int]) -> list[int]:
    out = []
    for c in skel.children(j):
        c = int(c)
        out.extend([c] if c in mapped else _nearest_mapped(skel, c, mapped))
    return out


def _bone_mean_dirs(skel: Skeleton) -> dict[int, np.ndarray]:
    """Direction from each joint to the mean end of the bones it drives (rest, world)."""
    bones = skel.bones()
    out = {}
    for j in np.unique(bones.joints):
        segs = bones.segments[bones.joints == j]
        d = segs[:, 1].mean(axis=0) - segs[0, 0]
        if np.linalg.norm(d) > 0:
            out[int(j)] = d
    return out


@dataclass(frozen=True)
class BonePair:
    """A mapped bone: target joints (joint, end) and source joints (joint, end)."""

    target: tuple[int, int]
    source: tuple[int, int]


def _pairs(ts: Skeleton, ss: Skeleton, m: dict[int, int], pt, ps, j: int, eps_t: float,
           eps_s: float, look_through: bool = True) -> list[BonePair]:
    s = m[j]
    mapped = set(m)
    out, todo = [], list(_nearest_mapped(ts, j, mapped))
    while todo:
        c = todo.pop(0)
        ok = np.linalg.norm(pt[c] - pt[j]) > eps_t and np.linalg.norm(ps[m[c]] - ps[s]) > eps_s
        if ok:
            out.append(BonePair((j, c), (s, m[c])))
        elif look_through:
            todo.extend(_nearest_mapped(ts, c, mapped))
    return out


def mapped_bones(source_skel: Skeleton, target_skel: Skeleton, mapping: dict[str, str]) -> list[BonePair]:
    """Bones whose both ends are mapped and have length in both rigs (no look-through).

    For each mapped target joint j and each nearest mapped descendant c: the
    target bone j → c and the source bone m(j) → m(c). These are the bones the
    tests measure.
    """
    m = _index_map(source_skel, target_skel, mapping)
    pt = target_skel.rest_globals()[:, :3, 3]
    ps = source_skel.rest_globals()[:, :3, 3]
    eps_t, eps_s = 1e-6 * max(_extent(pt), 1e-300), 1e-6 * max(_extent(ps), 1e-300)
    out = []
    for j in sorted(m):
        out += _pairs(target_skel, source_skel, m, pt, ps, j, eps_t, eps_s, look_through=False)
    return out


def _index_map(source_skel: Skeleton, target_skel: Skeleton, mapping: dict[str, str]) -> dict[int, int]:
    m = {}
    for t, s in mapping.items():
        if t not in target_skel.names:
            raise InputError(f"joint map: target joint {t!r} does not exist; {match_hint(t, target_skel.names)}")
        if s not in source_skel.names:
            raise InputError(f"joint map: source joint {s!r} does not exist; {match_hint(s, source_skel.names)}")
        m[target_skel.names.index(t)] = source_skel.names.index(s)
    return m


def _subtree(skel: Skeleton, j: int) -> list[int]:
    """Joint j and all its descendants."""
    out = [j]
    for d in range(j + 1, skel.num_joints):
        if skel.parents[d] in out:
            out.append(d)
    return out


def sole_heights(skel: Skeleton, G: np.ndarray, feet: list[list[int]]) -> np.ndarray:
    """Height (F,) of the lowest point (joint or bone tip) of the given foot subtrees."""
    sub = sorted({j for f in feet for j in f})
    Gf = np.take(G, sub, axis=-3)
    pos = Gf[..., :3, 3]
    tips = np.einsum("...jab,jb->...ja", Gf[..., :3, :3], skel.tips[sub]) + pos
    low = pos[..., UP].min(axis=-1)
    if np.isfinite(skel.tips[sub, 0]).any():
        low = np.minimum(low, np.nanmin(tips[..., UP], axis=-1))
    return low


def leg_length(skel: Skeleton, hips: int, legs: list[tuple[int, int, int]]) -> float:
    """Straightened leg length of a rig (module docstring, root motion) from the rest pose.

    hips: joint index; legs: (upper leg, lower leg, foot) joint indices per side.
    Without legs: the rest height of the hips above the lowest joint or bone tip.
    """
    G = skel.rest_globals()
    pos = G[:, :3, 3]
    tips = np.einsum("jab,jb->ja", G[:, :3, :3], skel.tips) + pos
    values = []
    for up, lo, foot in legs:
        sub = _subtree(skel, foot)
        low = min(pos[sub, UP].min(), np.nanmin(tips[sub, UP], initial=np.inf))
        values.append(pos[hips, UP] - pos[up, UP] + np.linalg.norm(pos[lo] - pos[up])
                      + np.linalg.norm(pos[foot] - pos[lo]) + pos[foot, UP] - low)
    if values:
        return float(np.mean(values))
    finite = tips[np.isfinite(tips[:, 0])]
    return float(pos[hips, UP] - min(pos[:, UP].min(), finite[:, UP].min(initial=np.inf)))


# --------------------------------------------------------------------------- transfer

class RetargetPlan:
    """Everything that depends on the two rest poses and the mapping (computed once).

    Attributes: ``mapping`` {target index: source index}; ``align`` {target
    index: A_j (3, 3)}; ``chain`` {target index: (source joint, source end,
    target rest bone (3,))} for joints aligned on a single bone; ``root``:
    target root-motion joint; ``scale``: root-motion scale k;
    ``leg_source``/``leg_target``: the leg lengths behind k; ``feet``: [(source
    foot subtree, target foot subtree)]; ``lift``: the vertical root offset of
    the last :meth:`run` (module docstring, root motion).
    """

    def __init__(self, source_skel: Skeleton, target_skel: Skeleton, mapping: dict[str, str]):
        self.source, self.target = source_skel, target_skel
        m = _index_map(source_skel, target_skel, mapping)
        if not m:
            raise InputError("no target joint is mapped to a source joint: the rigs share no known joint "
                             "names; give a joint map (user_map= {\"TargetJoint\": \"SourceJoint\"})")
        self.mapping = m
        Gs0, Gt0 = source_skel.rest_globals(), target_skel.rest_globals()
        ps, pt = Gs0[:, :3, 3], Gt0[:, :3, 3]
        self.source_rest_rot, self.target_rest_rot = _rotations(Gs0), _rotations(Gt0)
        eps_s, eps_t = 1e-6 * max(_extent(ps), 1e-300), 1e-6 * max(_extent(pt), 1e-300)
        lead_t, lead_s = _bone_mean_dirs(target_skel), _bone_mean_dirs(source_skel)
        slots_t, slots_s = joint_slots(target_skel), joint_slots(source_skel)
        self.align, self.chain, self.pairs = {}, {}, {}
        for j, s in m.items():
            pairs = _pairs(target_skel, source_skel, m, pt, ps, j, eps_t, eps_s)
            self.pairs[j] = pairs
            if len(pairs) == 1:
                (_, c), (_, sc) = pairs[0].target, pairs[0].source
                dt = pt[c] - pt[j]
                self.align[j] = _align(dt, ps[sc] - ps[s])
                self.chain[j] = (s, sc, dt)
            elif pairs:
                P = np.array([pt[p.target[1]] - pt[j] for p in pairs])
                Q = np.array([ps[p.source[1]] - ps[s] for p in pairs])
                P /= np.linalg.norm(P, axis=1, keepdims=True)
                Q /= np.linalg.norm(Q, axis=1, keepdims=True)
                sides = [slots_t.get(p.target[1]) or slots_s.get(p.source[1]) for p in pairs]
                lr = _left_right(sides)
                A = None
                if lr is not None:
                    lat = _lateral(target_skel, m, pt, ps, pairs[lr[0]].target[1], pairs[lr[1]].target[1],
                                   eps_t, eps_s)
                    rest = [k for k in range(len(pairs)) if k not in lr]
                    if lat is not None and rest:
                        A = _frame_align(lat[0], P[rest].sum(axis=0), lat[1], Q[rest].sum(axis=0))
                self.align[j] = kabsch(P, Q, centre=False) if A is None else A
            elif j in lead_t and s in lead_s:
                self.align[j] = _align(lead_t[j], lead_s[s])
            else:
                self.align[j] = np.eye(3)
        for j, A in self.align.items():
            if not np.isfinite(A).all():       # never expected: degenerate rest geometry
                self.align[j] = np.eye(3)
        depth = _depths(target_skel)
        self.root = min(m, key=lambda j: (depth[j], j))
        self.leg_source, self.leg_target, self.feet = self._legs()
        if not (self.leg_source > 0 and self.leg_target > 0):
            raise InputError(f"cannot scale the root motion: leg lengths {self.leg_source:g} (source) and "
                             f"{self.leg_target:g} (target) must be positive")
        self.scale = self.leg_target / self.leg_source
        self.lift = 0.0

    def _legs(self) -> tuple[float, float]:
        ss = {slot: j for j, slot in joint_slots(self.source).items()}
        inverse = {s: t for t, s in self.mapping.items()}
        legs_s, legs_t = [], []
        for side in ("left", "right"):
            chain = [ss.get(f"{side}_{p}") for p in ("upperleg", "lowerleg", "foot")]
            if None in chain or any(c not in inverse for c in chain):
                continue
            legs_s.append(tuple(chain))
            legs_t.append(tuple(inverse[c] for c in chain))
        feet = [(_subtree(self.source, s[2]), _subtree(self.target, t[2])) for s, t in zip(legs_s, legs_t)]
        return (leg_length(self.source, self.mapping[self.root], legs_s),
                leg_length(self.target, self.root, legs_t), feet)

    def run(self, source_pose: LocalPose, root: str = "origin") -> LocalPose:
        """Target local pose (F, J_t, ...) for a source local pose (F, J_s, ...).

        root: horizontal root motion, one of :data:`ROOT_MODES` (module docstring).
        """
        if root not in ROOT_MODES:
            raise InputError(f"root must be one of {', '.join(ROOT_MODES)}, got {root!r}")
        horizontal = [a for a in range(3) if a != UP]
        Gs = self.source.forward_kinematics(source_pose)
        if Gs.ndim == 3:
            Gs = Gs[None]
        F = len(Gs)
        Rs = _rotations(Gs)
        ps = Gs[..., :3, 3]
        delta = Rs @ np.swapaxes(self.source_rest_rot, -1, -2)[None]      # (F, Js, 3, 3)
        ts = self.target
        J = ts.num_joints
        rotation = np.repeat(ts.rotation[None], F, axis=0)
        translation = np.repeat(ts.translation[None], F, axis=0)
        G = np.empty((F, J, 4, 4))
        for j in range(J):
            p = ts.parents[j]
            base = ts.pre[j][None] if p < 0 else G[:, p] @ ts.pre[j]       # parent frame, (F, 4, 4)
            if j in self.mapping:
                s = self.mapping[j]
                W = delta[:, s] @ (self.align[j] @ self.target_rest_rot[j])
                if j in self.chain:
                    s0, s1, dt = self.chain[j]
                    u = np.einsum("fab,b->fa", W, self.target_rest_rot[j].T @ dt)
                    W = _align(u, ps[:, s1] - ps[:, s0]) @ W
                Rb = polar_rotation(base[:, :3, :3])
                rotation[:, j] = Rotation.from_matrix(np.swapaxes(Rb, -1, -2) @ W).as_quat()
                if j == self.root:
                    world = self.scale * ps[:, s]
                    if root == "in-place":
                        world[:, horizontal] = self.target.rest_globals()[j, horizontal, 3]
                    elif root == "origin":
                        world[:, horizontal] -= world[0, horizontal]
                    inv = np.linalg.inv(base)
                    translation[:, j] = np.einsum("fab,fb->fa", inv[:, :3, :3], world) + inv[:, :3, 3]
            rotation[:, j] = _continuous(rotation[:, j])
            L = np.zeros((F, 4, 4))
            L[:, :3, :3] = Rotation.from_quat(rotation[:, j]).as_matrix() * ts.scale[j][None, None, :]
            L[:, :3, 3] = translation[:, j]
            L[:, 3, 3] = 1.0
            G[:, j] = base @ L
        if self.feet:
            soles_s = sole_heights(self.source, Gs, [f[0] for f in self.feet])
            soles_t = sole_heights(ts, G, [f[1] for f in self.feet])
            lift = float(np.median(self.scale * soles_s - soles_t))
            r = self.root
            base = ts.pre[r][None] if ts.parents[r] < 0 else G[:, ts.parents[r]] @ ts.pre[r]
            up = np.zeros(3)
            up[UP] = lift
            translation[:, r] += np.einsum("fab,b->fa", np.linalg.inv(base)[:, :3, :3], up)
            self.lift = lift
        scale = np.repeat(ts.scale[None], F, axis=0)
        return LocalPose(translation, rotation, scale)


def _continuous(q: np.ndarray) -> np.ndarray:
    """Quaternions (F, 4) with signs flipped so consecutive ones lie in the same hemisphere."""
    q = q.copy()
    if len(q) > 1:
        flip = np.cumsum(np.r_[0, (np.sum(q[1:] * q[:-1], axis=1) < 0)]) % 2 == 1
        q[flip] *= -1
    return q


def _check_motion(source: Character, clip: Clip, m: dict[int, int]) -> None:
    moving = {t.joint for t in clip.tracks if t.path in ("rotation", "translation")}
    if not moving:
        raise InputError(f"source clip {clip.name!r} has no rotation or translation track: no motion to retarget")
    if not moving & set(m.values()):
        names = ", ".join(sorted(source.skeleton.names[j] for j in moving)[:6])
        raise InputError(f"source clip {clip.name!r} moves no mapped source joint (it moves {names}); "
                         "check the joint map (see format_map())")


def retarget_pose(source: Character, clip: Clip, target: Character, mapping: dict[str, str],
                  root: str = "origin", fps: float = 30.0, force: bool = False, close: bool = True):
    """(times (F,), target LocalPose (F, J, ...), plan) for the clip sampled at ``fps``.

    root: one of :data:`ROOT_MODES`; force: skip :func:`check_coverage`; close: end on the
    clip's last key (:func:`nrpose.model.timing.sample_times`).
    """
    plan = RetargetPlan(source.skeleton, target.skeleton, mapping)
    if not force:
        check_coverage(target.skeleton, mapping)
    _check_motion(source, clip, plan.mapping)
    times = sample_times(clip.duration, fps, close)
    local = plan.run(clip.sample(times), root)
    for what, arr in (("rotations", local.rotation), ("translations", local.translation)):
        if not np.isfinite(arr).all():
            raise InputError(f"retargeting produced non-finite {what}; please report this input")
    return times, local, plan


def retarget(source_character: Character, source_clip: Clip | str | None, target_character: Character,
             mapping: dict[str, str], root: str = "origin", fps: float = 30.0, name: str | None = None,
             force: bool = False) -> Clip:
    """The source clip played on the target: a Clip of the target skeleton (module docstring).

    source_clip: a Clip, a clip name, or None for the source's first clip; root: one of
    :data:`ROOT_MODES`; force: skip the coverage check (:func:`check_coverage`).
    """
    if not isinstance(source_clip, Clip):
        if not source_character.clips:
            raise InputError("the source has no animation clip: no motion to retarget")
        source_clip = (source_character.clips[0] if source_clip is None
                       else source_character.clip(source_clip))
    times, local, plan = retarget_pose(source_character, source_clip, target_character, mapping, root, fps, force)
    return make_clip(name or source_clip.name, times, local, plan, target_character.skeleton)


def make_clip(name: str, times: np.ndarray, local: LocalPose, plan: RetargetPlan, skeleton: Skeleton) -> Clip:
    """Clip of the target keying every joint's translation, rotation and scale (LINEAR).

    Mapped joints' rotations and the root-motion joint's translation at every time; the
    other values (constant: the target's rest values) at the first and last time only.
    """
    ends = times[[0, -1]] if len(times) > 1 else times[:1]
    tracks = []
    for j in range(skeleton.num_joints):
        for path in ("translation", "rotation", "scale"):
            values = getattr(local, path)[:, j]
            moving = (path == "rotation" and j in plan.mapping) or (path == "translation" and j == plan.root)
            tracks.append(Track(j, path, times, values) if moving else Track(j, path, ends, values[[0, -1]][:len(ends)]))
    return Clip(name, float(times[-1]), skeleton.rest_pose, tuple(tracks))


def skinned_bounds(character: Character, local: LocalPose) -> tuple[np.ndarray, np.ndarray] | None:
    """A world-space box (min (3,), max (3,)) holding the character's skinned meshes in every
    frame of ``local`` (F, J, ...), or None without skinned meshes.

    A skinned vertex is a convex combination of its joints' rigid motions, so it stays within
    ``reach_j`` (the farthest rest vertex weighted on joint j from j's rest position, times the
    largest stretch of j's skinning matrix) of some posed joint j: the box of the posed joints
    grown by their reaches holds it, without posing a vertex.
    """
    skinned = [m for m in character.meshes if m.joints is not None and m.weights is not None]
    if not skinned:
        return None
    skel = character.skeleton
    G0 = skel.rest_globals()
    reach = np.zeros(skel.num_joints)
    for m in skinned:
        for k in range(m.joints.shape[1]):
            on = m.weights[:, k] > 0
            d = np.linalg.norm(m.vertices[on] - G0[m.joints[on, k], :3, 3], axis=1)
            np.maximum.at(reach, m.joints[on, k], d)
    used = np.flatnonzero(reach > 0)
    G = skel.forward_kinematics(local)[..., used, :, :]
    stretch = np.linalg.norm((G @ np.linalg.inv(G0[used]))[..., :3, :3], ord=2, axis=(-2, -1))
    pos, r = G[..., :3, 3], (stretch * reach[used])[..., None]
    return (pos - r).reshape(-1, 3).min(axis=0), (pos + r).reshape(-1, 3).max(axis=0)


# --------------------------------------------------------------------------- coverage

@dataclass(frozen=True)
class Coverage:
    """How much of a target skeleton a mapping drives.

    fraction: share of the counted bone length whose joint is mapped (0..1); mapped: mapped
    target joint names (skeleton order); missing: (first joint name, joint count, share of
    the counted bone length) of each maximal unmapped subtree below the root-motion joint
    (a part left at rest), largest first.
    """

    fraction: float
    mapped: tuple[str, ...]
    missing: tuple[tuple[str, int, float], ...]


def coverage(target_skel: Skeleton, mapping: dict[str, str]) -> Coverage:
    """The share of the target's bone length driven by mapped joints (module docstring)."""
    mapped = {target_skel.names.index(t) for t in mapping if t in target_skel.names}
    if not mapped:
        return Coverage(0.0, (), ((target_skel.names[0], target_skel.num_joints, 1.0),))
    depth = _depths(target_skel)
    root = min(mapped, key=lambda j: (depth[j], j))
    above = set(_ancestors(target_skel, root))
    bones = target_skel.bones()
    length = np.linalg.norm(bones.segments[:, 1] - bones.segments[:, 0], axis=1)
    counted = np.array([int(j) not in above for j in bones.joints]) & (length > 0)
    driven = np.array([int(j) in mapped for j in bones.joints])
    total = float(length[counted].sum())
    fraction = float(length[counted & driven].sum()) / total if total > 0 else 1.0
    missing = []
    for j in _subtree(target_skel, root):
        p = int(target_skel.parents[j])
        if j not in mapped and (p in mapped or p in above or p < 0):
            sub = _subtree(target_skel, j)
            if not mapped & set(sub):
                size = float(length[counted & np.isin(bones.joints, sub)].sum())
                missing.append((target_skel.names[j], len(sub), size / total if total > 0 else 0.0))
    missing.sort(key=lambda m: -m[2])
    return Coverage(fraction, tuple(n for j, n in enumerate(target_skel.names) if j in mapped),
                    tuple(m for m in missing if m[2] > 0))


def check_coverage(target_skel: Skeleton, mapping: dict[str, str]) -> Coverage:
    """The :func:`coverage`; InputError (one line: what is mapped, what is missing) when the
    mapped joints drive less than :data:`MIN_COVERAGE` of the bone length or a part left at
    rest holds more than :data:`MAX_PART_AT_REST` of it (a limb, a tail)."""
    cov = coverage(target_skel, mapping)
    largest = cov.missing[0][2] if cov.missing else 0.0
    if cov.fraction < MIN_COVERAGE or largest > MAX_PART_AT_REST:
        listed = ", ".join(cov.mapped[:12]) + (", ..." if len(cov.mapped) > 12 else "")
        missing = ", ".join(f"{n} ({k} joint{'s' if k > 1 else ''}, {100 * f:.0f}%)" for n, k, f in cov.missing[:6])
        raise InputError(f"the joint map covers too little of the target skeleton to make sense: "
                         f"{len(cov.mapped)} of {target_skel.num_joints} joints mapped ({listed}), driving "
                         f"{100 * cov.fraction:.0f}% of its bone length (at least {100 * MIN_COVERAGE:.0f}% needed, "
                         f"no part at rest above {100 * MAX_PART_AT_REST:.0f}%); left at rest: {missing or '-'}; "
                         f"map more joints with user_map= or retarget anyway with force=")
    return cov
