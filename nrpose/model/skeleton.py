"""Skeleton model: joints, forward kinematics, and bones as segment handles.

A :class:`Skeleton` has J joints in topological order (``parents[j] < j``,
``-1`` for a root). Each joint has a rest *local* transform: translation
(J, 3), rotation quaternion (J, 4) ``(x, y, z, w)`` and scale (J, 3), all
float64, plus a fixed ``pre`` matrix (J, 4, 4), identity unless a file puts
non-joint nodes between a joint and its parent joint (glTF: e.g. a Mixamo
``Armature`` node above the hips). Global transforms follow the column-vector
convention::

    G[j] = G[parents[j]] @ pre[j] @ T(translation[j]) @ R(rotation[j]) @ S(scale[j])

with ``G[parent] = I`` for roots. A :class:`LocalPose` holds local TRS for any
batch of frames, shape (..., J, 3|4|3); :meth:`Skeleton.forward_kinematics`
maps it to (..., J, 4, 4), level by level of the hierarchy (vectorised over
all joints of a level and over frames).

Bones (``Skeleton.bones()``) are the line-segment handles of the skeleton.
They are formed from the rest pose by these rules, in this order:

1. Targets of a joint j: every child c gives a segment from j to c, driven by
   j (a joint with several children gets one segment per child, all driven by
   j). A child at the same position as j (a zero-length bone, e.g. BVH
   ``LHipJoint`` with offset 0) is looked through: its own targets, computed
   recursively by this rule, become targets of j as well. A root with one child
   therefore gives the segment root → child.
2. An explicit tip (``tips[j]``: a BVH ``End Site`` or the far end of a leaf
   TGF bone, an offset in j's local frame) gives a segment from j to the tip.
3. A joint left without any segment by rules 1–2 (a glTF/TGF leaf, or a
   joint whose descendants all coincide with it) gets a short segment along
   the direction from its nearest ancestor at a different position to the
   joint, of length ``leaf_fraction`` (default 0.5) times that distance.
   A joint with no such ancestor drives no segment.
4. Segments shorter than ``1e-9`` times the skeleton's extent are dropped, as
   are repeated (driver, start, end) triples. Joints with ``deform[j] False``
   drive no segment.

A posed bone is its rest segment carried by its driving joint's transform
``M_j = G_j(pose) @ G_j(rest)^-1``; its rotation is
``R_pose_global @ R_rest_global^-1`` (polar rotation parts of the global
matrices), which carries the rest bone onto the posed bone, twist included.
A child translated by the pose (stretch) is therefore not followed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .rotation import quat_matrices, unit_quaternions

__all__ = ["LocalPose", "concat_poses", "Skeleton", "Bones", "local_matrices", "polar_rotation", "polar_components",
           "det_components"]

#: relative length below which a bone is considered degenerate
ZERO_LENGTH = 1e-9
#: smallest scale of a joint's rest frame (its largest is the inverse): the inverse bind stays
#: well inside float32 range
MIN_REST_SCALE = 1e-8


@dataclass(frozen=True, eq=False)
class LocalPose:
    """Local joint transforms for a batch of frames.

    translation: (..., J, 3), rotation: (..., J, 4) unit quaternions (x, y, z, w),
    scale: (..., J, 3); float64, in the file's units.
    """

    translation: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray


def concat_poses(poses) -> LocalPose:
    """The frames of LocalPoses (F_i, J, ...) one after another, a LocalPose (sum F_i, J, ...)."""
    return LocalPose(*(np.concatenate([getattr(p, k) for p in poses]) for k in ("translation", "rotation", "scale")))


def local_matrices(translation: np.ndarray, rotation: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``T @ R @ S`` as (..., 4, 4) float64 from (..., 3), (..., 4) xyzw, (..., 3)."""
    translation = np.asarray(translation, dtype=np.float64)
    rotation = np.asarray(rotation, dtype=np.float64)
    scale = np.asarray(scale, dtype=np.float64)
    batch = np.broadcast_shapes(translation.shape[:-1], rotation.shape[:-1], scale.shape[:-1])
    R = quat_matrices(np.broadcast_to(rotation, batch + (4,)).reshape(-1, 4))
    M = np.zeros(batch + (4, 4))
    M[..., :3, :3] = R.reshape(batch + (3, 3)) * np.broadcast_to(scale, batch + (3,))[..., None, :]
    M[..., :3, 3] = translation
    M[..., 3, 3] = 1.0
    return M


def polar_rotation(A: np.ndarray) -> np.ndarray:
    """Rotation part of (..., 3, 3) linear maps (polar decomposition), (..., 3, 3).

    For ``A = R @ S`` with S symmetric positive (uniform or axis scale) this is R.
    See :func:`polar_components` for the method; this is its row/column layout.
    """
    A = np.asarray(A, dtype=np.float64)
    if A.ndim < 2 or A.shape[-2:] != (3, 3):
        raise InputError(f"polar_rotation needs (..., 3, 3) matrices, got shape {A.shape}")
    flat = A.reshape(-1, 3, 3)
    out = polar_components(np.ascontiguousarray(np.moveaxis(flat, 0, -1)), flat)
    return np.ascontiguousarray(np.moveaxis(out, -1, 0)).reshape(A.shape)


def det_components(C: np.ndarray) -> np.ndarray:
    """Determinants (n,) of n 3x3 maps given component-major, C (3, 3, n)."""
    return (C[0, 0] * (C[1, 1] * C[2, 2] - C[1, 2] * C[2, 1]) - C[0, 1] * (C[1, 0] * C[2, 2] - C[1, 2] * C[2, 0])
            + C[0, 2] * (C[1, 0] * C[2, 1] - C[1, 1] * C[2, 0]))


#: the fast path's Newton–Schulz steps stop once max |σ² − 1| over the singular values σ is
#: at most this (a bound: 3 max |XᵀX − I| before the first step, δ² after a step from δ)
POLAR_TOLERANCE = 1e-14


def polar_components(C: np.ndarray, flat: np.ndarray | None = None) -> np.ndarray:
    """Polar rotation factors of n maps given component-major: C (3, 3, n) float64 with
    C[i, j] the (i, j) entries of all maps; returns (3, 3, n) float64, a new array.

    flat: the same maps as (n, 3, 3), if the caller has them (else a view of C).
    Maps within 1e-3 of a rotation times a uniform scale s (nearly every joint of a
    character, float32 data included) take a fast path: Newton–Schulz steps
    ``X ← X (3I − XᵀX) / 2`` from X = A / s, which take δ = max |σ² − 1| to ~(3/4) δ²
    (1e-3 → ~1e-6 → ~1e-12 → rounding), as many as :data:`POLAR_TOLERANCE` needs: float32
    data (δ ~1e-6) two, float64 rotations none. The others take an SVD (a batched SVD for
    every joint would dominate posing a clip). Component-major (3, 3, n) arrays because
    numpy's stacked 3x3 ``@`` and ``det`` cost far more than these element-wise products.
    """
    s2 = np.einsum("ijn,ijn->n", C, C) / 3.0                           # mean squared column norm
    X = C / np.sqrt(np.where(s2 > 0, s2, 1.0))
    D = np.einsum("kin,kjn->ijn", X, X)                                # XᵀX - I
    for i in range(3):
        D[i, i] -= 1.0
    off = np.abs(D.reshape(9, -1)).max(axis=0)
    near = (off <= 1e-3) & (det_components(X) > 0)
    every = bool(near.all())
    # only where it converges (elsewhere it may overflow); compress keeps (3, 3, m)
    # contiguous, X[..., near] would lay it out (m, 3, 3)
    Y, G = (X, D) if every else (np.compress(near, X, axis=2), np.compress(near, D, axis=2))
    delta = 3.0 * float(off[near].max(initial=0.0))     # |σ² − 1| ≤ the 3x3 spectral norm of G
    while delta > POLAR_TOLERANCE:
        G *= -0.5                                                      # (3I − YᵀY) / 2 = I − G / 2
        for i in range(3):
            G[i, i] += 1.0
        Y = np.einsum("ikn,kjn->ijn", Y, G)
        delta = delta * delta
        if delta > POLAR_TOLERANCE:
            G = np.einsum("kin,kjn->ijn", Y, Y)
            for i in range(3):
                G[i, i] -= 1.0
    if every:
        return Y
    X[..., near] = Y
    flat = np.moveaxis(C, -1, 0) if flat is None else flat
    U, _, Vt = np.linalg.svd(flat[~near])
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    X[..., ~near] = np.moveaxis(U @ Vt, 0, -1)
    return X


def match_hint(name: str, names) -> str:
    """"did you mean ...?" for an unknown joint name, else the first known joints."""
    import difflib      # error messages only

    close = difflib.get_close_matches(name, list(names), n=5, cutoff=0.5)
    if close:
        return "did you mean " + ", ".join(repr(c) for c in close) + "?"
    shown = ", ".join(repr(n) for n in list(names)[:12])
    return f"known joints: {shown}{', ...' if len(names) > 12 else ''}"


@dataclass(frozen=True, eq=False)
class Skeleton:
    """Joint hierarchy with rest local transforms (see the module docstring).

    names: J unique strings; parents: (J,) int64, ``parents[j] < j`` or -1;
    translation (J, 3), rotation (J, 4) xyzw, scale (J, 3): rest local TRS;
    pre: (J, 4, 4) fixed matrix between parent frame and local TRS (identity
    default); tips: (J, 3) explicit bone tips in the joint's local frame, NaN
    where none; deform: (J,) bool, joints that drive bones (all by default).
    """

    names: tuple[str, ...]
    parents: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    pre: np.ndarray = None
    tips: np.ndarray = None
    deform: np.ndarray = None
    _levels: tuple = field(init=False, repr=False, compare=False)
    _pre_at: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        names = tuple(str(n) for n in self.names)
        J = len(names)
        if J == 0:
            raise InputError("a skeleton needs at least one joint")
        if len(set(names)) != J:
            dup = sorted({n for n in names if names.count(n) > 1})
            raise InputError(f"duplicate joint names: {', '.join(dup)}")
        parents = np.asarray(self.parents, dtype=np.int64).reshape(-1)
        if parents.shape != (J,):
            raise InputError(f"parents: expected {J} entries, got {parents.size}")
        bad = np.flatnonzero((parents >= np.arange(J)) | (parents < -1))
        if bad.size:
            j = int(bad[0])
            raise InputError(f"joint {names[j]!r} (index {j}) has parent {parents[j]}: joints must "
                             "be in topological order (parent index < child index, -1 for roots)")
        eye = np.broadcast_to(np.eye(4), (J, 4, 4))
        arrays = {
            "translation": (self.translation, (J, 3), None),
            "rotation": (self.rotation, (J, 4), None),
            "scale": (self.scale, (J, 3), None),
            "pre": (self.pre, (J, 4, 4), eye),
            "tips": (self.tips, (J, 3), np.full((J, 3), np.nan)),
        }
        for key, (value, shape, default) in arrays.items():
            arr = np.array(default if value is None else value, dtype=np.float64)
            if arr.shape != shape:
                raise InputError(f"skeleton {key}: expected shape {shape}, got {arr.shape}")
            if key != "tips" and not np.isfinite(arr).all():
                raise InputError(f"skeleton {key}: contains NaN or infinite values")
            object.__setattr__(self, key, arr)
        self.rotation[:] = unit_quaternions(self.rotation, [f"skeleton rotation of joint {n!r}" for n in names])
        deform = np.ones(J, bool) if self.deform is None else np.asarray(self.deform, dtype=bool)
        if deform.shape != (J,):
            raise InputError(f"skeleton deform: expected shape ({J},), got {deform.shape}")
        depth = np.zeros(J, np.int64)
        for j in range(J):
            depth[j] = 0 if parents[j] < 0 else depth[parents[j]] + 1
        levels = tuple(np.flatnonzero(depth == d) for d in range(int(depth.max()) + 1))
        # joints whose pre is not the identity (glTF: the few nodes with a transform the
        # skeleton does not animate; none in BVH/TGF): forward_kinematics multiplies only those
        pre_at = np.flatnonzero((self.pre != np.eye(4)).any(axis=(1, 2)))
        for key, value in (("names", names), ("parents", parents), ("deform", deform), ("_levels", levels),
                           ("_pre_at", pre_at)):
            object.__setattr__(self, key, value)
        self._check_rest_scale()

    def _check_rest_scale(self) -> None:
        """Refuse rest frames the inverse bind cannot undo in float32 (a scale of 0 or 1e-320)."""
        with np.errstate(over="ignore", invalid="ignore"):
            sv = np.linalg.svd(self.rest_globals()[:, :3, :3], compute_uv=False)
        bad = np.flatnonzero(~np.isfinite(sv).all(axis=1) | (sv[:, -1] < MIN_REST_SCALE)
                             | (sv[:, 0] > 1 / MIN_REST_SCALE))
        if len(bad):
            j = int(bad[0])
            raise InputError(f"the rest transform of joint {self.names[j]!r} scales by "
                             f"{sv[j, -1]:.3g}..{sv[j, 0]:.3g}: joint scales (times their parents') must lie "
                             f"between {MIN_REST_SCALE:g} and {1 / MIN_REST_SCALE:g} for an inverse bind; "
                             "fix the joint's scale in the file")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def rest_pose(self) -> LocalPose:
        """The rest local transforms as a :class:`LocalPose` of shape (J, ...) (copies)."""
        return LocalPose(self.translation.copy(), self.rotation.copy(), self.scale.copy())

    def index(self, name: str) -> int:
        """Index of joint ``name``; InputError naming close matches if unknown."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(f"unknown joint {name!r}; {match_hint(name, self.names)}") from None

    def children(self, j: int) -> np.ndarray:
        """Indices (int64) of the children of joint j, ascending."""
        return np.flatnonzero(self.parents == j)

    def forward_kinematics(self, pose: LocalPose | None = None) -> np.ndarray:
        """Global matrices (..., J, 4, 4) float64 of ``pose`` (rest pose if None)."""
        pose = self.rest_pose if pose is None else pose
        shapes = [np.shape(a)[-2:] for a in (pose.translation, pose.rotation, pose.scale)]
        if shapes != [(self.num_joints, 3), (self.num_joints, 4), (self.num_joints, 3)]:
            raise InputError(f"pose arrays end in shapes {shapes}; this skeleton needs "
                             f"({self.num_joints}, 3), ({self.num_joints}, 4), ({self.num_joints}, 3)")
        L = local_matrices(pose.translation, pose.rotation, pose.scale)
        if len(self._pre_at):        # an identity pre changes nothing: skip its product
            L[..., self._pre_at, :, :] = self.pre[self._pre_at] @ L[..., self._pre_at, :, :]
        G = np.empty_like(L)
        G[..., self._levels[0], :, :] = L[..., self._levels[0], :, :]
        for level in self._levels[1:]:
            G[..., level, :, :] = G[..., self.parents[level], :, :] @ L[..., level, :, :]
        return G

    def rest_globals(self) -> np.ndarray:
        """Global rest matrices (J, 4, 4) float64."""
        return self.forward_kinematics()

    def bones(self, leaf_fraction: float = 0.5) -> "Bones":
        """Segment handles of the rest pose, formed by the module docstring's rules."""
        return Bones.from_skeleton(self, leaf_fraction)


@dataclass(frozen=True, eq=False)
class Bones:
    """Line-segment handles driven by joints.

    segments: (B, 2, 3) float64 rest (start, end); joints: (B,) int64 driving
    joint; names: B labels ``"joint->target"``; rest_globals: (J, 4, 4) global
    rest matrices of the skeleton they were made from.
    """

    segments: np.ndarray
    joints: np.ndarray
    names: tuple[str, ...]
    rest_globals: np.ndarray

    def __post_init__(self):
        # rest-only terms of pose(), computed once
        Gr = self.rest_globals[self.joints]
        inv = np.linalg.inv(Gr)
        # the segments' ends in their driving joints' rest frames (B, 2, 3)
        object.__setattr__(self, "_local_ends", np.einsum("bij,bkj->bki", inv[:, :3, :3], self.segments)
                           + inv[:, None, :3, 3])
        object.__setattr__(self, "_rest_rot_t", np.swapaxes(polar_rotation(Gr[:, :3, :3]), -1, -2))

    @classmethod
    def from_skeleton(cls, skel: Skeleton, leaf_fraction: float = 0.5) -> "Bones":
        G = skel.rest_globals()
        pos = G[:, :3, 3]
        tips = np.einsum("jab,jb->ja", G[:, :3, :3], skel.tips) + pos
        extent = float(np.ptp(np.vstack([pos, tips[np.isfinite(tips[:, 0])]]), axis=0).max(initial=0.0))
        eps = ZERO_LENGTH * max(extent, 1e-300)
        children = [skel.children(j) for j in range(skel.num_joints)]

        def targets(j: int, origin: np.ndarray) -> list[tuple[str, np.ndarray]]:
            found = []
            if np.isfinite(tips[j, 0]):
                found.append((f"{skel.names[j]}_tip", tips[j]))
            for c in children[j]:
                if np.linalg.norm(pos[c] - origin) > eps:
                    found.append((skel.names[c], pos[c]))
                else:
                    found.extend(targets(int(c), origin))
            return found

        segs, drivers, names = [], [], []
        for j in np.flatnonzero(skel.deform):
            seen = set()
            for label, end in targets(int(j), pos[j]):
                if np.linalg.norm(end - pos[j]) > eps and tuple(end) not in seen:
                    seen.add(tuple(end))
                    segs.append((pos[j], end))
                    drivers.append(j)
                    names.append(f"{skel.names[j]}->{label}")
            if not seen:
                a = skel.parents[j]
                while a >= 0 and np.linalg.norm(pos[j] - pos[a]) <= eps:
                    a = skel.parents[a]
                if a >= 0:
                    segs.append((pos[j], pos[j] + leaf_fraction * (pos[j] - pos[a])))
                    drivers.append(j)
                    names.append(f"{skel.names[j]}->(leaf)")
        return cls(np.asarray(segs, dtype=np.float64).reshape(-1, 2, 3),
                   np.asarray(drivers, dtype=np.int64), tuple(names), G)

    def __len__(self) -> int:
        return len(self.joints)

    def pose(self, globals_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Posed segments (..., B, 2, 3) and rotations relative to rest (..., B, 3, 3).

        globals_: (..., J, 4, 4) global joint matrices of the pose (from
        :meth:`Skeleton.forward_kinematics`).
        """
        Gp = np.asarray(globals_, dtype=np.float64)[..., self.joints, :3, :]
        batch = Gp.shape[:-2]
        # the posed joint frames applied to the ends in rest joint frames, and the rotations
        # times the rest ones' inverses, entry by entry on component-major copies C[i, j]
        # (..., B): numpy's einsum and stacked 3x3 matmul took 3 times as long on a clip's
        # (frames x bones) small matrices, and broadcasting over strided 4x4 entries twice
        C = np.ascontiguousarray(np.moveaxis(Gp, (-2, -1), (0, 1)))    # (3, 4, ..., B)
        L, Q = self._local_ends, self._rest_rot_t
        ends = np.empty(batch + (2, 3))
        for e in range(2):
            for i in range(3):
                ends[..., e, i] = C[i, 3] + C[i, 0] * L[:, e, 0] + C[i, 1] * L[:, e, 1] + C[i, 2] * L[:, e, 2]
        P = polar_components(C[:, :3].reshape(3, 3, -1)).reshape((3, 3) + batch)
        R = np.empty(batch + (3, 3))
        for i in range(3):
            for k in range(3):
                R[..., i, k] = P[i, 0] * Q[:, 0, k] + P[i, 1] * Q[:, 1, k] + P[i, 2] * Q[:, 2, k]
        return ends, R
