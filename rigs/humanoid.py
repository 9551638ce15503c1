"""The embedded default character: a capsule humanoid with a skeleton, skin weights and a walk.

:func:`humanoid` builds a :class:`nrpose.model.character.Character` the same way a
glTF loader would describe one, from scratch and deterministically (no file,
no cache):

* **Mesh** ``body``: one closed, outward-oriented triangle mesh, the zero set
  of a signed distance function (a smooth union of tapered capsules: pelvis,
  abdomen, chest, shoulders, neck, head and nose, upper/lower arms, hands,
  upper/lower legs, feet, toes) meshed by ``igl.marching_cubes``. Y-up,
  metres, facing +Z (glTF's forward), the character's left on +X, about
  1.8 tall, soles on ``y = 0``, arms in an A-pose (45° below horizontal).
  About 11k vertices with the default ``resolution``.
* **Skeleton**: 21 joints, Mixamo-like names without prefix::

      Hips ─ Spine ─ Chest ─ Neck ─ Head
                     Chest ─ {Left,Right}Shoulder ─ …UpperArm ─ …LowerArm ─ …Hand
      Hips ─ {Left,Right}UpLeg ─ …Leg ─ …Foot ─ …Toe

  Joints lie on the capsule axes; every rest local rotation is the identity,
  so the rest globals are pure translations and ``inverse_bind`` is their
  inverse (``Character.skin_matrices(rest) = I``).
* **Skin weights**: up to 4 influences per vertex, rows summing to 1. Each
  vertex is labelled by the capsule it is nearest to; its candidate joints are
  that capsule's joint, its parent and its children (so the inside of one
  thigh never follows the other leg); among them the weights are inverse
  distances to the joints' bone segments, ``d^-4``, normalised.
* **Clip** ``walk``: 1 s gait cycle, 30 LINEAR keys (t = 0 … 1 s; the last
  pose equals the first up to the forward translation). Sagittal hip, knee,
  ankle and toe curves of a normal gait (periodic splines through textbook
  key angles, left and right half a cycle apart), arms swinging against the
  legs with some elbow bend, pelvis yaw and roll with counter-rotating chest,
  lateral sway. The ``Hips`` translation is solved on the skinned mesh (LBS
  of the sole vertices): the lowest vertex touches ``y = 0`` in every frame
  (bobbing, about 3.5 cm) and, over each key interval, the lowest sole
  vertex of the leg in the first half of its stance stays put (forward
  motion without foot sliding, about 1.47 m per cycle; the speed varies
  within the cycle, 0.9 to 2.1 m/s). The heel of the landing foot may float
  up to about 1.5 cm during the double support that follows.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from nrpose.model.character import Character, Clip, Mesh, Track
from nrpose.bind.distances import point_segment_distances
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import LocalPose, Skeleton

__all__ = ["humanoid", "JOINT_NAMES", "PARENTS", "REST_POSITIONS", "WALK_DURATION", "WALK_SAMPLES"]

WALK_DURATION = 1.0
WALK_SAMPLES = 30
_A_POSE = np.radians(45.0)        # arms below horizontal
_ARM_DIR = np.array([np.cos(_A_POSE), -np.sin(_A_POSE), 0.0])


def _joint_table():
    """Names, parents and world rest positions (J, 3) of the skeleton."""
    hip_x, leg_z = 0.095, 0.0
    sh = np.array([0.19, 1.415, -0.01])                    # left UpperArm joint (shoulder)
    elbow = sh + 0.28 * _ARM_DIR
    wrist = elbow + 0.25 * _ARM_DIR
    table = [
        ("Hips", None, (0.0, 0.95, 0.0)),
        ("Spine", "Hips", (0.0, 1.06, -0.005)),
        ("Chest", "Spine", (0.0, 1.25, -0.01)),
        ("Neck", "Chest", (0.0, 1.46, -0.015)),
        ("Head", "Neck", (0.0, 1.585, 0.0)),
    ]
    for side, s in (("Left", 1.0), ("Right", -1.0)):
        m = np.array([s, 1.0, 1.0])
        table += [
            (f"{side}Shoulder", "Chest", m * (0.035, 1.40, -0.01)),
            (f"{side}UpperArm", f"{side}Shoulder", m * sh),
            (f"{side}LowerArm", f"{side}UpperArm", m * elbow),
            (f"{side}Hand", f"{side}LowerArm", m * wrist),
        ]
    for side, s in (("Left", 1.0), ("Right", -1.0)):
        table += [
            (f"{side}UpLeg", "Hips", (s * hip_x, 0.92, leg_z)),
            (f"{side}Leg", f"{side}UpLeg", (s * hip_x, 0.505, 0.012)),
            (f"{side}Foot", f"{side}Leg", (s * hip_x, 0.085, -0.01)),
            (f"{side}Toe", f"{side}Foot", (s * hip_x, 0.028, 0.125)),
        ]
    names = tuple(t[0] for t in table)
    parents = np.array([-1 if p is None else names.index(p) for _, p, _ in table], np.int64)
    return names, parents, np.array([t[2] for t in table], dtype=np.float64)


JOINT_NAMES, PARENTS, REST_POSITIONS = _joint_table()
_J = {name: j for j, name in enumerate(JOINT_NAMES)}


def _primitives():
    """Tapered capsules ``(joint, a, b, ra, rb, depth_scale)`` of the body, world rest coordinates.

    ``depth_scale`` > 1 flattens the cross-section in z (torso is wider than deep).
    ``joint`` is the joint the capsule belongs to (used to label vertices).
    """
    P = REST_POSITIONS
    prims = [
        ("Hips", (-0.075, 0.955, -0.01), (0.075, 0.955, -0.01), 0.115, 0.115, 1.15),
        ("Spine", (0.0, 1.0, -0.01), (0.0, 1.2, -0.01), 0.125, 0.13, 1.3),
        ("Chest", (-0.065, 1.30, -0.01), (0.065, 1.30, -0.01), 0.135, 0.135, 1.25),
        ("Neck", (0.0, 1.44, -0.015), (0.0, 1.59, 0.0), 0.05, 0.047, 1.0),
        ("Head", (0.0, 1.645, 0.012), (0.0, 1.70, 0.0), 0.098, 0.098, 1.0),
        ("Head", (0.0, 1.655, 0.085), (0.0, 1.635, 0.105), 0.016, 0.012, 1.0),   # nose: shows the front
    ]
    for side, s in (("Left", 1.0), ("Right", -1.0)):
        m = np.array([s, 1.0, 1.0])
        sh, el, wr = P[_J[f"{side}UpperArm"]], P[_J[f"{side}LowerArm"]], P[_J[f"{side}Hand"]]
        hip, knee, ankle, toe = (P[_J[f"{side}{n}"]] for n in ("UpLeg", "Leg", "Foot", "Toe"))
        prims += [
            (f"{side}Shoulder", m * (0.03, 1.405, -0.012), sh, 0.065, 0.058, 1.25),
            (f"{side}UpperArm", sh, el, 0.052, 0.04, 1.0),
            (f"{side}LowerArm", el, wr, 0.04, 0.031, 1.0),
            (f"{side}Hand", wr + 0.02 * _ARM_DIR * m, wr + 0.12 * _ARM_DIR * m, 0.034, 0.028, 1.0),
            (f"{side}UpLeg", hip + (0, 0.02, 0), knee, 0.088, 0.058, 1.0),
            (f"{side}Leg", knee, ankle, 0.056, 0.038, 1.0),
            (f"{side}Foot", (s * 0.095, 0.042, -0.06), (s * 0.095, 0.034, 0.12), 0.042, 0.034, 1.0),
            (f"{side}Toe", (s * 0.095, 0.027, 0.13), (s * 0.095, 0.025, 0.18), 0.027, 0.025, 1.0),
        ]
    return [(_J[j], np.asarray(a, float), np.asarray(b, float), ra, rb, sz) for j, a, b, ra, rb, sz in prims]


def _sd_tapered_capsule(P, a, b, ra, rb, depth_scale):
    """Approximate signed distance to a capsule whose radius goes linearly from ra to rb."""
    scale = np.array([1.0, 1.0, depth_scale])
    Q, a, b = P * scale, a * scale, b * scale
    ab = b - a
    t = np.clip(((Q - a) @ ab) / (ab @ ab), 0.0, 1.0)
    d = Q - a - t[:, None] * ab
    return np.sqrt(np.einsum("ij,ij->i", d, d)) - (ra + t * (rb - ra))


def _smin(a, b, k):
    """Polynomial smooth minimum (smooth union of two distance fields)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


#: value given to a capsule's distance outside its bounding box grown by this margin:
#: larger than any blend radius plus the narrow band, so it never changes the union there
_FAR = 0.15


def _sdf(P, prims):
    """Body distance field (N,) and the per-capsule distances (C, N).

    Each capsule is evaluated only inside its bounding box grown by ``_FAR``;
    outside it its distance (at least ``_FAR``) is replaced by ``_FAR``, which
    leaves the sign of the union and its value where it is below ``_FAR - 0.04``
    unchanged.
    """
    D = np.full((len(prims), len(P)), _FAR)
    for i, (_, a, b, ra, rb, sz) in enumerate(prims):
        r = max(ra, rb) + _FAR
        inside = np.all((P >= np.minimum(a, b) - r) & (P <= np.maximum(a, b) + r), axis=1)
        D[i, inside] = np.minimum(_sd_tapered_capsule(P[inside], a, b, ra, rb, sz), _FAR)
    names = [JOINT_NAMES[p[0]] for p in prims]
    torso = [i for i, n in enumerate(names) if not n.startswith(("Left", "Right"))
             or n.endswith("Shoulder")]
    body = D[torso[0]]
    for i in torso[1:]:
        body = _smin(body, D[i], 0.04)
    for side in ("Left", "Right"):
        for chain in (("UpperArm", "LowerArm", "Hand"), ("UpLeg", "Leg", "Foot", "Toe")):
            idx = [i for i, n in enumerate(names) if n in {side + c for c in chain}]
            limb = D[idx[0]]
            for i in idx[1:]:
                limb = _smin(limb, D[i], 0.02)
            body = _smin(body, limb, 0.03)
    return body, D


def _grid_sdf(prims, lo, n, h):
    """Distance field on the grid ``lo + h * (i, j, k)``, (n[2], n[1], n[0]) C order (x fastest).

    Exact (as :func:`_sdf`) wherever it matters to marching cubes: first on a
    grid 3 times coarser, then on the fine nodes whose nearest coarse node is
    within a band of the surface; elsewhere the fine node takes the coarse
    node's value, whose sign is right because the field is 1.5-Lipschitz
    (depth-scaled capsules) and the nearest coarse node is at most sqrt(3) h
    away.
    """
    def points(ix, iy, iz):
        return np.column_stack([lo[0] + h * ix, lo[1] + h * iy, lo[2] + h * iz])

    coarse = [np.arange(0, n[k], 3) for k in range(3)]
    CZ, CY, CX = np.meshgrid(coarse[2], coarse[1], coarse[0], indexing="ij")
    Sc = _sdf(points(CX.ravel(), CY.ravel(), CZ.ravel()), prims)[0].reshape(CZ.shape)
    near = [np.minimum((np.arange(n[k]) + 1) // 3, len(coarse[k]) - 1) for k in range(3)]
    S = Sc[np.ix_(near[2], near[1], near[0])]
    band = np.abs(S) < 1.5 * 2.0 * np.sqrt(3.0) * h + 1e-9
    iz, iy, ix = np.nonzero(band)
    S[iz, iy, ix] = _sdf(points(ix, iy, iz), prims)[0]
    return S


def _mesh(resolution: float):
    """Marching-cubes mesh (V, F) and the capsule label of each vertex."""
    import igl  # local import: libigl is only needed to build the mesh

    prims = _primitives()
    h = resolution
    lo = np.array([-0.72, -0.03, -0.2])
    hi = np.array([0.72, 1.83, 0.24])
    n = np.ceil((hi - lo) / h).astype(int) + 1
    n += (1 - n) % 3                                       # last node on the coarse grid
    S = _grid_sdf(prims, lo, n, h)
    Z, Y, X = np.meshgrid(*(lo[k] + h * np.arange(n[k]) for k in (2, 1, 0)), indexing="ij")
    GV = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    V, F, _ = igl.marching_cubes(S.ravel(), GV, int(n[0]), int(n[1]), int(n[2]), 0.0)
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(int(used.sum()))
    V, F = V[used], remap[F]
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum()
    if vol < 0:
        F = np.ascontiguousarray(F[:, ::-1])
    V[:, 1] -= V[:, 1].min()                               # soles exactly on y = 0
    _, D = _sdf(V, prims)
    label = np.array([p[0] for p in prims])[np.argmin(D, axis=0)]
    return V, F, label


def _influence_segments():
    """One bone segment (J, 2, 3) per joint: the part of the body the joint carries."""
    P = REST_POSITIONS
    seg = np.zeros((len(JOINT_NAMES), 2, 3))
    for j, name in enumerate(JOINT_NAMES):
        kids = np.flatnonzero(PARENTS == j)
        if name == "Hips":
            seg[j] = [(0.0, 0.93, -0.01), P[_J["Spine"]]]
        elif name == "Chest":
            seg[j] = [P[j], P[_J["Neck"]]]
        elif name == "Head":
            seg[j] = [P[j], P[j] + (0, 0.17, 0)]
        elif name.endswith("Hand"):
            s = 1.0 if name.startswith("Left") else -1.0
            seg[j] = [P[j], P[j] + 0.13 * _ARM_DIR * (s, 1, 1)]
        elif name.endswith("Toe"):
            seg[j] = [P[j], P[j] + (0, -0.003, 0.055)]
        else:
            seg[j] = [P[j], P[kids[0]]]
    return seg


def _skin_weights(V, label, power: float = 4.0, influences: int = 4):
    """Joint indices (N, 4) int64 and weights (N, 4) float64 (see the module docstring)."""
    J = len(JOINT_NAMES)
    allowed = np.eye(J, dtype=bool)
    for j in range(J):
        if PARENTS[j] >= 0:
            allowed[j, PARENTS[j]] = allowed[PARENTS[j], j] = True
    D = point_segment_distances(V, _influence_segments())[0]
    D = np.where(allowed[label], np.maximum(D, 1e-4), np.inf)
    idx = np.argsort(D, axis=1, kind="stable")[:, :influences]
    d = np.take_along_axis(D, idx, axis=1)
    w = np.where(np.isfinite(d), d ** -power, 0.0)
    w /= w.sum(axis=1, keepdims=True)
    return idx.astype(np.int64), w


def _skeleton() -> Skeleton:
    J = len(JOINT_NAMES)
    local = REST_POSITIONS - np.where(PARENTS[:, None] >= 0, REST_POSITIONS[np.maximum(PARENTS, 0)], 0.0)
    return Skeleton(names=JOINT_NAMES, parents=PARENTS, translation=local,
                    rotation=np.tile([0.0, 0.0, 0.0, 1.0], (J, 1)), scale=np.ones((J, 3)))


def _periodic(keys):
    """Periodic cubic spline through (phase, degrees) keys; phase in [0, 1)."""
    p, v = np.array(keys, dtype=np.float64).T
    return CubicSpline(np.r_[p, p[0] + 1.0], np.r_[v, v[0]], bc_type="periodic")


# Sagittal gait angles (degrees) against the gait phase of one leg: 0 = heel
# strike, 0.6 = toe off, 0.6..1 = swing (after textbook normal-gait curves).
_HIP_FLEX = _periodic([(0.0, 24), (0.15, 14), (0.5, -14), (0.6, -6), (0.75, 16), (0.87, 27)])
_KNEE_FLEX = _periodic([(0.0, 4), (0.15, 16), (0.4, 5), (0.5, 22), (0.6, 38), (0.72, 60), (0.88, 22)])
_ANKLE_DORSI = _periodic([(0.0, 0), (0.08, -2), (0.4, 9), (0.5, 4), (0.62, -17), (0.75, 2), (0.9, 2)])
_TOE_EXT = _periodic([(0.0, 0), (0.4, 0), (0.5, 16), (0.58, 28), (0.66, 8), (0.8, 0)])


def _rx(deg):
    return Rotation.from_euler("x", np.radians(np.asarray(deg, dtype=np.float64))[..., None])


def _walk(skel: Skeleton, sole) -> Clip:
    """The procedural walk (see the module docstring); sole: (vertices, joints, weights) of the mesh."""
    t = np.linspace(0.0, WALK_DURATION, WALK_SAMPLES)
    phase = t / WALK_DURATION
    F = len(t)
    rot = {}
    for side, offset, s in (("Left", 0.0, 1.0), ("Right", 0.5, -1.0)):
        p = (phase + offset) % 1.0
        # hip flexion moves the leg forward (+z): rotation about -x; knee flexion backward: +x
        rot[f"{side}UpLeg"] = _rx(-_HIP_FLEX(p))
        rot[f"{side}Leg"] = _rx(_KNEE_FLEX(p))
        rot[f"{side}Foot"] = _rx(-_ANKLE_DORSI(p))
        rot[f"{side}Toe"] = _rx(-_TOE_EXT(p))
        # arms: hang near the sides, swing against the leg on the same side
        q = (phase + offset + 0.5) % 1.0
        swing = 0.75 * (_HIP_FLEX(q) - 8.0)
        drop = Rotation.from_euler("z", -s * 38.0, degrees=True)
        rot[f"{side}UpperArm"] = _rx(-swing) * drop
        hinge = np.cross(_ARM_DIR * (s, 1.0, 1.0), (0.0, 0.0, 1.0))   # forearm bends forward
        bend = np.radians(14.0 + 0.6 * np.maximum(swing, 0.0))
        rot[f"{side}LowerArm"] = Rotation.from_rotvec(bend[:, None] * hinge / np.linalg.norm(hinge))
        rot[f"{side}Shoulder"] = Rotation.from_euler("z", s * 3.0 * np.cos(2 * np.pi * (phase + offset))[:, None],
                                                        degrees=True)
    yaw = 6.0 * np.sin(2 * np.pi * (phase - 0.1))          # pelvis leads the swinging leg
    roll = 3.0 * np.sin(2 * np.pi * (phase - 0.05))         # swing side of the pelvis drops
    rot["Hips"] = Rotation.from_euler("yz", np.c_[-yaw, roll], degrees=True)
    rot["Spine"] = Rotation.from_euler("yx", np.c_[0.7 * yaw, np.full(F, 3.0)], degrees=True)
    rot["Chest"] = Rotation.from_euler("yz", np.c_[0.9 * yaw, -0.8 * roll], degrees=True)
    rot["Neck"] = Rotation.from_euler("y", -0.6 * yaw[:, None], degrees=True)
    rot["Head"] = Rotation.from_euler("yx", np.c_[-0.5 * yaw, np.full(F, -3.0)], degrees=True)

    pose = LocalPose(np.repeat(skel.translation[None], F, axis=0),
                     np.repeat(skel.rotation[None], F, axis=0), np.ones((F, skel.num_joints, 3)))
    for name, r in rot.items():
        pose.rotation[:, _J[name]] = r.as_quat()
    pose.translation[:, 0, 0] = 0.02 * np.cos(2 * np.pi * (phase - 0.3))   # sway over the stance leg

    # root height and forward motion from the skinned sole vertices of the mesh
    G = skel.forward_kinematics(pose)
    K = G @ np.linalg.inv(skel.rest_globals())
    soles = []
    for s in (1.0, -1.0):                                   # left (+x), right
        idx = np.flatnonzero((sole[0][:, 1] < 0.03) & (s * sole[0][:, 0] > 0))
        M = np.einsum("nk,fnkab->fnab", sole[2][idx], K[:, sole[1][idx]])
        soles.append(np.einsum("fnab,nb->fna", M, np.c_[sole[0][idx], np.ones(len(idx))])[..., :3])
    low = np.stack([S[..., 1].min(axis=1) for S in soles], axis=1)   # (F, side)
    pose.translation[:, 0, 1] -= low.min(axis=1)            # lowest skinned vertex on the ground
    # over each key interval the lowest sole vertex of the leg in the first half of
    # its stance stays put (rolling contact): that gives the forward motion
    step = np.zeros(F - 1)
    for k in range(F - 1):
        S = soles[0 if phase[k] < 0.5 else 1]
        m = np.argmin(S[k, :, 1])
        step[k] = S[k, m, 2] - S[k + 1, m, 2]
    pose.translation[:, 0, 2] = REST_POSITIONS[0, 2] + np.r_[0.0, np.cumsum(step)]

    tracks = [Track(0, "translation", t, pose.translation[:, 0])]
    for name in rot:
        tracks.append(Track(_J[name], "rotation", t, pose.rotation[:, _J[name]]))
    tracks.sort(key=lambda tr: (tr.joint, tr.path))
    return Clip("walk", WALK_DURATION, skel.rest_pose, tuple(tracks))


def humanoid(resolution: float = 0.015) -> Character:
    """The capsule humanoid character with its ``walk`` clip (see the module docstring).

    resolution: marching-cubes grid step in metres (0.0125 gives about 11k
    vertices). Deterministic: the same argument gives the same arrays.
    """
    skel = _skeleton()
    V, F, label = _mesh(float(resolution))
    joints, weights = _skin_weights(V, label)
    mesh = Mesh("body", V, F, joints, weights, None)
    return Character(skel, (mesh,), (_walk(skel, (V, joints, weights)),), np.linalg.inv(skel.rest_globals()))
