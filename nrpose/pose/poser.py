"""Characters posed on the device: bind once, then frames from joint rotations.

    poser = CharacterPoser(character, method="nrmls", weights="authored")
    frames = poser.pose(local_pose)           # LocalPose (J, ...) or (F, J, ...)
    frames.positions                          # (F, V, 3) float32, world space

Vertices of all the character's meshes are concatenated in file order
(``mesh_offsets`` tells where each mesh starts). Methods:

* ``nrmls``: the engine's near-rigid blend (:mod:`nrpose.pose.blend`) with the
  skeleton's bones (:meth:`nrpose.model.skeleton.Skeleton.bones`) as segment
  handles carrying their full rotation, weighted by
  :func:`nrpose.bind.bone_weights.bone_weights`.
  The blend takes the segment parameters that come with the weights
  (:class:`nrpose.bind.bone_weights.BoneWeights` ``t``): parts with one set of authored
  weights move rigidly; topological weights take their handle points where their paths start.
* ``lbs``/``dqs``/``cor``: linear / dual-quaternion skinning (:mod:`nrpose.pose.skinning`),
  and skinning with optimized centers of rotation (:mod:`nrpose.pose.cor`, the centers
  computed at bind from the deforming meshes' rest triangles and the weights).
  With authored weights a glTF mesh is skinned from its own bind-space
  POSITION data with ``G_j @ inverse_bind_j`` of its own skin: the glTF
  specification's formula.

Weights (:data:`nrpose.options.WEIGHTS`): ``authored`` (the file's
skin weights), ``euclidean`` (distance to the bone segments, ``1/d^(2α)``), or
a topological distance over the surface (``heat``, ``exact``, ``graph``). For
lbs/dqs the distance weights keep each vertex's 4 nearest bones, summed per
driving joint.

Meshes attached rigidly to a joint follow that joint's transform exactly,
whatever the method.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from . import skinning
from .cor import centers as cor_centers, cor_reference
from ..bind.cache import cache_dir, cached_status, code_version
from ..checks import check_magnitude
from ..errors import InputError
from ..model.character import Character
from ..model.handles import HandleSet, Pose, check_alpha
from ..model.meshset import concatenate_meshes, submesh_faces
from ..model.skeleton import LocalPose
from ..options import BLENDS, DEFAULT_BLEND, METHODS, WEIGHTS

__all__ = ["METHODS", "WEIGHTS", "CharacterPoser", "Frames", "FrameStream", "prefetch"]

SKIN_INFLUENCES = 4   # bones kept per vertex for lbs/dqs with distance weights
#: the modules whose code an NR-MLS bind runs: their source is part of the binding cache's key
BIND_MODULES = ("nrpose.pose.poser", "nrpose.pose.mls", "nrpose.pose.blend", "nrpose.bind.bone_weights",
                "nrpose.bind.weights", "nrpose.bind.distances", "nrpose.model.skeleton", "nrpose.model.meshset",
                "nrpose.model.rotation", "nrpose.model.handles", "nrpose.model.deformation_metrics")
#: the modules whose code an lbs/dqs/cor bind runs (joint weights, their compact form, the centers)
SKIN_BIND_MODULES = ("nrpose.pose.poser", "nrpose.pose.cor", "nrpose.pose.skinning", "nrpose.bind.bone_weights",
                     "nrpose.bind.weights", "nrpose.bind.distances", "nrpose.model.skeleton", "nrpose.model.meshset",
                     "nrpose.model.handles", "nrpose.model.deformation_metrics")
BIND_CACHE_FOLDER = "binds"   # character binds, beside the topological distances in the cache directory
BATCH = 16            # frames posed per kernel launch (bound data read once per batch)


@dataclass(frozen=True)
class Frames:
    """Posed frames: positions (F, V, 3) float32 (each frame C-contiguous; posed on
    OpenCL, a few padding points lie between frames, :meth:`nrpose.device.BoundKernel.frames_array`),
    faces (M, 3) int64 (indices into the concatenated vertices), mesh_names,
    mesh_offsets (len(meshes),) int64, and per-frame pose times in milliseconds (F,)."""

    positions: np.ndarray
    faces: np.ndarray
    mesh_names: tuple[str, ...]
    mesh_offsets: np.ndarray
    frame_ms: np.ndarray


@dataclass(frozen=True)
class FrameStream:
    """Posed frames as they come (:meth:`CharacterPoser.stream`): ``batches``, read once,
    poses the frames a batch at a time and yields each batch, (f, V, 3) float32 laid out as
    :attr:`Frames.positions`, valid until the next is taken; faces, mesh_names and
    mesh_offsets as :class:`Frames`; frame_ms (F,) filled in as the frames are posed;
    vertices: V."""

    batches: Iterator[np.ndarray]
    faces: np.ndarray
    mesh_names: tuple[str, ...]
    mesh_offsets: np.ndarray
    frame_ms: np.ndarray
    vertices: int

    @property
    def count(self) -> int:
        """F, the frames the stream yields in all."""
        return len(self.frame_ms)


class CharacterPoser:
    """A character bound for posing. See the module docstring for the options.

    k: segment slots per vertex for nrmls (default: all bones up to 8, else 8).
    blend: the nrmls rotation blend (:data:`nrpose.options.BLENDS`; the default
    "quaternion" is continuous at any spread of the bones' rotations, "relative" jumps
    where the dominant bone changes among three or more, at hips and shoulders).
    """

    def __init__(self, character: Character, method: str = "nrmls", weights: str = "authored",
                 alpha: float = 1.0, k: int | None = None, backend: str = "opencl", blend: str = DEFAULT_BLEND):
        if method not in METHODS:
            raise InputError(f"method must be one of {METHODS}, got {method!r}")
        if weights not in WEIGHTS:
            raise InputError(f"weights must be one of {WEIGHTS}, got {weights!r}")
        if blend not in BLENDS:
            raise InputError(f"blend must be one of {BLENDS}, got {blend!r}")
        if blend != DEFAULT_BLEND and method != "nrmls":
            raise InputError(f"blend {blend!r} applies to the nrmls method only; drop blend= or use method='nrmls'")
        alpha = check_alpha(alpha)      # checked for every method, used or not: a bad value is a mistake
        if not character.meshes:
            raise InputError("the character has no mesh to pose (a skeleton-only file); "
                             "give a mesh and pass the skeleton with skeleton=")
        t0 = time.perf_counter()
        self.character, self.method, self._backend = character, method, backend
        skel = character.skeleton
        meshes = character.meshes
        geo = concatenate_meshes(meshes)
        self.mesh_offsets, self.mesh_names, self.faces = geo.offsets, geo.names, geo.faces
        self.n = len(geo.vertices)
        self._rigid_idx = np.flatnonzero(geo.rigid >= 0)
        self._rigid_joint = geo.rigid[self._rigid_idx]
        self._deform_idx = np.flatnonzero(geo.rigid < 0)
        self._rest_world = geo.vertices
        self._rest_inv = np.linalg.inv(skel.rest_globals())
        self.bones = skel.bones()
        deform_meshes = [m for m in meshes if m.rigid_joint is None]
        self._deformer, self._bind_space, self._device_args, self.bind_cache = None, False, None, None
        if deform_meshes:
            V = self._rest_world[self._deform_idx]
            if method == "nrmls":
                # NR-MLS's modules (the blend, its deformer, bone weights): a skinning job never imports them
                from ..bind.bone_weights import SKELETON_K, bone_weights
                from .mls import prefetch_program

                rest = HandleSet.make(segments=self.bones.segments, what="skeleton bones")
                kk = k if k is not None else (SKELETON_K if len(self.bones) > SKELETON_K else None)
                if backend == "opencl":
                    prefetch_program(rest, kk, blend=blend)     # compiles while the host binds
                    W, t, layout = self._nrmls_bind(character, V, rest, weights, kk, alpha, blend)
                else:
                    bw = bone_weights(character, weights, kk, alpha, distances=False)
                    W, t, layout = bw.weights[self._deform_idx], bw.t[self._deform_idx] if bw.t is not None else None, None
                self._device_args = (V, rest, W, kk, blend, t, layout)
            else:
                prefetch(method, backend)
                offset = np.zeros(len(V), np.int64)
                self._bind_space = weights == "authored" and all(
                    m.bind_vertices is not None and m.inverse_bind is not None for m in deform_meshes)
                src = np.concatenate([m.bind_vertices for m in deform_meshes]) if self._bind_space else V
                if self._bind_space:
                    # each distinct skin's inverse binds get their own block of J matrices
                    self._ibms, group = _distinct([m.inverse_bind for m in deform_meshes])
                    offset = np.repeat(group * skel.num_joints, [len(m.vertices) for m in deform_meshes])
                faces = submesh_faces(geo.faces, self._deform_idx, self.n) if method == "cor" else None
                joints, wts, centers = self._skin_bind(character, V, src, offset, faces, weights, alpha)
                self._device_args = (src, joints, wts) + ((centers,) if method == "cor" else ())
            self._deformer = self._device_build()
        self.bind_ms = 1e3 * (time.perf_counter() - t0)

    def _device_build(self):
        """The deformer made from the host binding (``_device_args``): rest terms, buffers and
        programs on the device (nrmls on the numpy backend: the float64 reference)."""
        if self._device_args is None:
            return None
        if self.method == "nrmls":
            from .mls import Deformer     # NR-MLS only: a skinning job never imports it

            V, rest, W, k, blend, t, layout = self._device_args
            return Deformer(V, rest, weights=W, k=k, backend=self._backend, blend=blend, t=t, layout=layout)
        if self._backend != "opencl":
            return None
        if self.method == "cor":
            src, joints, wts, centers = self._device_args
            return skinning.Skinner(src, joints, wts, method="cor", centers=centers)
        cls = skinning.LbsSkinner if self.method == "lbs" else skinning.DqsSkinner
        return cls(*self._device_args)

    def __getstate__(self) -> dict:
        """The host binding alone (the character, weights, handles, vertices: numpy arrays and
        small objects), picklable: a binding made once can be shipped to other processes or nodes."""
        return dict(self.__dict__, _deformer=None)

    def __setstate__(self, state: dict) -> None:
        """A shipped binding: its device part is built in this process when first needed
        (:attr:`deformer`), so unpickling a binding that is not used costs no device work."""
        self.__dict__.update(state)

    def _nrmls_bind(self, character, V, rest, weights, k, alpha, blend) -> tuple[np.ndarray, np.ndarray | None, dict]:
        """(bone weights (V, B) of the deforming vertices, their segment parameters (V, B; 0
        where the weight is) or None, the Deformer's :func:`bind_layout`),
        from the binding cache (:mod:`nrpose.bind.cache`, its folder :data:`BIND_CACHE_FOLDER`)
        when the same character, options and code were bound before (``self.bind_cache``:
        "hit", "miss" or "rebuilt")."""
        deform = [m for m in character.meshes if m.rigid_joint is None]
        skinned = weights == "authored" and all(m.joints is not None and m.weights is not None for m in deform)
        parts = {"kind": "nrmls-character-bind", "code": code_version(BIND_MODULES),
                 **self._bind_key(character, V, rest.segments, skinned),
                 "options": {"weights": weights, "k": k, "alpha": float(alpha), "blend": blend,
                             "skin_shapes": [list(np.shape(m.joints)) for m in deform] if skinned else []}}

        def compute() -> dict:
            from ..bind.bone_weights import bone_weights    # NR-MLS only: a skinning job never imports it
            from .mls import bind_layout, kept_terms

            bw = bone_weights(character, weights, k, alpha, distances=False)
            W = bw.weights[self._deform_idx]
            t = bw.t[self._deform_idx] if bw.t is not None else None
            cols = np.argsort(W == 0, axis=1, kind="stable")[:, :max(int((W != 0).sum(axis=1).max(initial=0)), 1)]
            layout = bind_layout(kept_terms(V, rest, weights=W, k=k, t=t), rest, blend=blend)
            # W and t on each vertex's weighted bones only: a zero weight makes its t unused
            # (the rest terms and the kernel take w and w t), and the dense (V, B) t was 2/3 of
            # the entry that a warm job reads and checks
            return {**{f"layout_{n}": a for n, a in layout.items()},
                    **({} if t is None else {"t_values": np.take_along_axis(t, cols, axis=1)}),
                    "weight_bones": cols, "weight_values": np.take_along_axis(W, cols, axis=1)}

        got, self.bind_cache = cached_status(parts, compute, cache_dir() / BIND_CACHE_FOLDER)
        def dense(values: np.ndarray) -> np.ndarray:
            out = np.zeros((len(V), len(rest.segments)))
            np.put_along_axis(out, got["weight_bones"], values, axis=1)
            return out

        return (dense(got["weight_values"]), dense(got["t_values"]) if "t_values" in got else None,
                {n[7:]: a for n, a in got.items() if n.startswith("layout_")})

    def _bind_key(self, character, V, segments, with_skin: bool) -> dict:
        """The arrays a character bind depends on (binding-cache key parts): deforming
        vertices V (world rest), faces, bone segments and joints, parents, and the authored
        skin's joints and weights when ``with_skin``."""
        deform = [m for m in character.meshes if m.rigid_joint is None]
        return {"vertices": np.ascontiguousarray(V, np.float64), "faces": np.ascontiguousarray(self.faces, np.int64),
                "deform": self._deform_idx, "bones": np.ascontiguousarray(segments, np.float64),
                "bone_joints": np.asarray(self.bones.joints, np.int64),
                "parents": np.asarray(character.skeleton.parents, np.int64),
                "skin_joints": np.concatenate([np.asarray(m.joints, np.int64).ravel() for m in deform])
                if with_skin else np.zeros(0, np.int64),
                "skin_weights": np.concatenate([np.asarray(m.weights, np.float64).ravel() for m in deform])
                if with_skin else np.zeros(0)}

    def _skin_bind(self, character, V, src, offset, faces, weights, alpha) -> tuple:
        """(joints (V, K) int64, their weights (V, K) float64, centers of rotation (V, 3) or
        None without ``faces``) of the deforming vertices V (world rest) for lbs/dqs/cor:
        joint rows ``offset`` (V,) apart per distinct skin, centers computed from ``src``
        (the skinned rest vertices) and the deforming meshes' ``faces`` (cor only). From the
        binding cache when the same character, options and code were bound before
        (``self.bind_cache``: "hit", "miss" or "rebuilt")."""
        skel = character.skeleton
        deform = [m for m in character.meshes if m.rigid_joint is None]
        authored = weights == "authored"
        parts = {"kind": "skin-character-bind", "code": code_version(SKIN_BIND_MODULES),
                 **self._bind_key(character, V, self.bones.segments, authored),
                 "source": np.ascontiguousarray(src, np.float64), "offset": offset,
                 "options": {"weights": weights, "alpha": float(alpha), "influences": SKIN_INFLUENCES,
                             "centers": faces is not None,
                             "skin_shapes": [list(np.shape(m.joints)) for m in deform] if authored else []}}

        def compute() -> dict:
            # on a cache miss only: a cached skinning bind never imports the weights' module
            from ..bind.bone_weights import authored_joint_weights, bone_weights, joint_weights

            if authored:
                joint_w = authored_joint_weights(deform, skel.num_joints)
            else:
                bone_w = bone_weights(character, weights, SKIN_INFLUENCES, alpha).weights[self._deform_idx]
                joint_w = joint_weights(bone_w, self.bones, skel.num_joints)
            joints, wts = _compact(joint_w)
            joints = joints + offset[:, None]
            if faces is None:
                return {"joints": joints, "weights": wts}
            return {"joints": joints, "weights": wts,
                    "centers": cor_centers(src, faces if len(faces) else None, joints, wts)}

        got, self.bind_cache = cached_status(parts, compute, cache_dir() / BIND_CACHE_FOLDER)
        return got["joints"], got["weights"], got.get("centers")

    # ------------------------------------------------------------------ posing
    @property
    def deformer(self):
        """The bound deformer on the device (NR-MLS :class:`~nrpose.pose.mls.Deformer` or a
        :class:`~nrpose.pose.skinning.Skinner`), or None on the numpy backend."""
        if self._deformer is None and self._device_args is not None:
            self._deformer = self._device_build()
        return self._deformer

    def pose(self, local: LocalPose, progress=None) -> Frames:
        """Posed frames for a local pose (J, ...) or a batch (F, J, ...).

        progress: optional callable(done, total) called after each batch of frames.
        """
        G = self._joint_transforms(local)
        # on OpenCL: the frames in memory the deformer's kernel writes directly (no copy per frame)
        out = self._frames_memory(len(G))
        frame_ms = np.empty(len(G))
        for _ in self._posed_batches(G, out, frame_ms, progress):
            pass
        return Frames(out, self.faces, self.mesh_names, self.mesh_offsets, frame_ms)

    def stream(self, local: LocalPose, progress=None) -> FrameStream:
        """The frames of a local pose (J, ...) or a batch (F, J, ...), posed batch by batch
        as the returned stream's ``batches`` are taken (no array of every frame is made).
        The pose is checked now (InputError), the posing runs as the stream is read."""
        G = self._joint_transforms(local)
        frame_ms = np.empty(len(G))
        batches = self._posed_batches(G, self._frames_memory(min(len(G), BATCH)), frame_ms, progress)
        return FrameStream(batches, self.faces, self.mesh_names, self.mesh_offsets, frame_ms, self.n)

    def _joint_transforms(self, local: LocalPose) -> np.ndarray:
        """Global joint transforms (F, J, 4, 4) of a local pose (J, ...) or (F, J, ...),
        InputError where there is no frame or a transform is not finite or too large."""
        if np.ndim(local.rotation) == 3 and len(local.rotation) == 0:
            raise InputError("no frames to pose: give at least one time")
        G = self.character.skeleton.forward_kinematics(local)
        if not np.isfinite(G).all():
            raise InputError("the pose moves or scales joints to infinity; check its translations and scales")
        check_magnitude(G[..., :3, :], "posed joint transforms (translations, scaled rotations)")
        return G[None] if G.ndim == 3 else G

    def _frames_memory(self, frames: int) -> np.ndarray:
        """Uninitialised (frames, n, 3) float32 for posed frames: on OpenCL without rigid
        meshes the deformer's :meth:`~nrpose.device.BoundKernel.frames_array`, which its
        kernel writes into directly; else a plain array."""
        if len(self._deform_idx) == self.n and self._backend == "opencl":
            return self.deformer.frames_array(frames)
        return np.empty((frames, self.n, 3), np.float32)

    def _posed_batches(self, G: np.ndarray, out: np.ndarray, frame_ms: np.ndarray, progress) -> Iterator[np.ndarray]:
        """Pose the frames of G (F, J, 4, 4) BATCH at a time into ``out`` (from
        :meth:`_frames_memory`): frames a..b into ``out[a:b]`` where it holds all F, else into
        its first b - a (one batch's memory, reused); yield each batch's frames (a view of
        ``out``) when posed, its per-frame milliseconds in ``frame_ms[a:b]``, then
        ``progress(b, F)``. The deformer lets go of ``out`` when the generator ends."""
        deformer, F = self.deformer, len(G)
        whole = len(self._deform_idx) == self.n       # no rigid meshes: write in place
        # (F, J, 4, 4): skinning matrices, for rigidly attached meshes and for LBS/DQS of rest-space
        # vertices (bind-space vertices take their skins' own inverse binds instead)
        skin_rest = (G @ self._rest_inv
                     if self._rigid_idx.size or (self.method != "nrmls" and not self._bind_space) else None)
        # per-frame handle data for all frames at once (vectorised host work)
        if self.method == "nrmls":
            segs, rots = self.bones.pose(G)
            empty = np.zeros((0, 3))
        else:
            mats = (np.concatenate([G @ ibm for ibm in self._ibms], axis=1) if self._bind_space
                    else skin_rest)
        try:
            for a in range(0, F, BATCH):
                b = min(a + BATCH, F)
                t0 = time.perf_counter()
                batch = out[a:b] if len(out) == F else out[:b - a]
                if self._rigid_idx.size:
                    M = skin_rest[a:b, self._rigid_joint]                     # (f, n, 4, 4)
                    V = self._rest_world[self._rigid_idx]
                    batch[:, self._rigid_idx] = np.einsum("fnij,nj->fni", M[..., :3, :3], V) + M[..., :3, 3]
                if self._deform_idx.size:
                    dst = batch if whole else np.empty((b - a, len(self._deform_idx), 3), np.float32)
                    if self.method == "nrmls":
                        # FK output is consistent by construction: no Pose.make validation
                        deformer.pose_frames([Pose(HandleSet(empty, segs[f]), rots[f]) for f in range(a, b)],
                                             out=dst)
                    elif deformer is not None:
                        deformer.pose_frames(mats[a:b], out=dst)
                    else:
                        ref = {"lbs": skinning.lbs_reference, "dqs": skinning.dqs_reference,
                               "cor": cor_reference}[self.method]
                        dst[...] = [ref(*self._device_args[:3], m, *self._device_args[3:]) for m in mats[a:b]]
                    if not whole:
                        batch[:, self._deform_idx] = dst
                frame_ms[a:b] = 1e3 * (time.perf_counter() - t0) / (b - a)
                yield batch
                if progress:
                    progress(b, F)
        finally:
            if self._backend == "opencl" and deformer is not None:
                deformer.release_frames()             # the frames are the caller's: not kept by the poser


def prefetch(method: str, backend: str = "opencl") -> None:
    """Start building, in the background, the device program a poser of ``method`` on
    ``backend`` will use where it does not depend on the character (the skinning methods';
    an NR-MLS program depends on the rig and is started at bind), so that a caller can have
    it compile while the character loads (:func:`nrpose.pose.skinning.prefetch_program`; makes the OpenCL
    context now)."""
    if backend == "opencl" and method in skinning.PROGRAMS:
        skinning.prefetch_program(method)


# ---------------------------------------------------------------------- helpers
def _distinct(arrays: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """The distinct arrays of a list and, for each entry, the index of its distinct array."""
    distinct, index = [], []
    for a in arrays:
        k = next((i for i, d in enumerate(distinct) if np.array_equal(d, a)), None)
        if k is None:
            distinct.append(a)
            k = len(distinct) - 1
        index.append(k)
    return distinct, np.array(index, np.int64)


def _compact(W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense (V, J) weights → (joints (V, K), weights (V, K)), K = most non-zeros in a row."""
    K = max(int(np.count_nonzero(W, axis=1).max()), 1)
    joints = np.argsort(-W, axis=1, kind="stable")[:, :K]
    return joints, np.take_along_axis(W, joints, axis=1)
