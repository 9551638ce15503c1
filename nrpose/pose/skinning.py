"""Linear blend skinning (LBS) and dual quaternion skinning (DQS) on the device.

Inputs (conventions of :mod:`nrpose.rotation`: rows are points, matrices act
on column vectors, quaternions are ``(x, y, z, w)``):

* ``rest`` (N, 3): rest-pose vertices.
* ``joints`` (N, K) integers and ``weights`` (N, K) non-negative floats: the
  K influences of each vertex (K is free: 1, 4, 8, ...). Entries with weight
  0 are padding; their joint index is ignored (it may be anything, e.g. -1).
  **Each weight row is normalised to sum 1 at bind**; a row whose weights are
  all zero is an error.
* ``mats`` (J, 4, 4): skinning matrices ``M_j = G_j @ IBM_j`` (global joint
  transform times inverse bind matrix). They must be affine (bottom row
  ``0 0 0 1``); J must exceed every joint index that carries weight.

LBS: ``x' = (sum_k w_k M_{j_k}) x``; scale and shear in ``M_j`` are honoured.

DQS (Kavan et al. 2007): each ``M_j`` is reduced to its rigid part -- the
nearest rotation to the 3x3 block (its polar factor; exact for a rotation
times a uniform scale) and the translation column -- and converted to a unit
dual quaternion. **Scale and
shear in M_j are ignored by DQS.** Per vertex, each joint's dual quaternion
is sign-flipped to lie in the hemisphere of the vertex's dominant (largest
weight, first on ties) joint's rotation quaternion, the weighted sum is
divided by the norm of its real part, and the resulting rigid transform is
applied.

Device side: float32, groups of 8 vertices in float8 lanes, bound data
(rest vertices, influences) uploaded once in a structure-of-arrays layout,
see ``kernels/skinning.cl``; each vertex's influences are sorted by
decreasing weight at bind (influence 0 is the dominant joint), and the vertices
by their joints, so that the 8 vertices of a group mostly share each influence's
joint and read its parameters once (the kernel writes each vertex to its own row). A launch
(:func:`nrpose.device.launch_shared`) runs the kernel on PoCL's worker
threads and the calling thread at once: each takes blocks of :data:`BLOCK`
groups of the job published in the deformer's mailbox (:class:`nrpose.device.Jobs`)
until none are left and poses every frame of the launch for them (frames
innermost); the device module decides whether to share a launch (small ones
stay on the calling thread unless a standing worker polls or frames come in
a loop). Per-pose parameters, results and the mailbox live in
fine-grained SVM when the device offers it (PoCL does): one pose is then a
kernel enqueue plus ``finish`` per device; other devices get write + launch +
read on one queue. :meth:`Skinner.pose_frames` poses F frames in one
launch. DQS converts matrices to dual quaternions on the host;
:meth:`Skinner.pose_dual_quaternions` skips that.

The numpy references :func:`lbs_reference` and :func:`dqs_reference` compute
the same in float64 and apply the same validation and weight normalisation.

CoR (``method="cor"``, kernels/cor.cl): skinning with optimized centers of rotation, bound
through the same class with the vertices' centers (:class:`nrpose.pose.cor.CorSkinner`
computes them; :func:`nrpose.pose.cor.cor_reference` is its float64 reference).
"""
from __future__ import annotations

import numpy as np

from .. import device
from ..checks import coordinates, real_rows
from ..errors import InputError
from ..model.rotation import matrix_quats
from ..model.skeleton import det_components, polar_components

__all__ = ["LbsSkinner", "DqsSkinner", "Skinner", "lbs_reference", "dqs_reference",
           "dqs_reference_dq", "dual_quaternions", "prepare_influences", "prefetch_program"]

LANES = 8          # vertices per group (float8 lanes)
# the kernels' arguments (kernels/skinning.cl lbs, dqs): bound data, per-pose parameters
# and output, sizes, then the job mailbox and the role (share.h)
# (kernels/cor.cl cor: the same, its `rest` rows the offsets v - c, then the centers c)
(ARG_REST, ARG_JOINTS, ARG_WEIGHTS, ARG_ROWS, ARG_PARAMS, ARG_OUT, ARG_K, ARG_J, ARG_G, ARG_BLOCK,
 ARG_JOBS, ARG_ROLE) = range(12)
#: methods and their kernels' programs: (kernel file, build options), one kernel each
PROGRAMS = {"lbs": ("skinning.cl", ("-DLBS_KERNEL",)), "dqs": ("skinning.cl", ("-DDQS_KERNEL",)),
            "cor": ("cor.cl", ())}
BLOCK = 32         # groups (of 8 vertices) per block of work taken from the job mailbox (share.h)


def prefetch_program(method: str) -> None:
    """Start compiling the program a :class:`Skinner` of ``method`` ("lbs", "dqs" or "cor")
    launches (:func:`nrpose.device.prefetch`), to overlap the host work before it is bound.
    InputError for another method."""
    if method not in PROGRAMS:
        raise InputError(f"skinning method must be one of {tuple(PROGRAMS)}, got {method!r}")
    device.prefetch(*PROGRAMS[method])


# --------------------------------------------------------------------------- validation

def prepare_influences(rest, joints, weights):
    """Validate bind inputs; return (rest (N,3) f64, joints (N,K) int64, weights (N,K) f64).

    Weights rows are normalised to sum 1; padding entries (weight 0) get joint 0.
    Also returns the largest joint index that carries weight, as a 4th item.
    """
    rest = coordinates(rest, "rest vertices")
    n = rest.shape[0]

    joints = np.asarray(joints)
    if joints.ndim == 1:
        joints = joints[:, None]
    if joints.ndim != 2 or joints.shape[0] != n or joints.shape[1] == 0:
        raise InputError(f"joint indices must have shape (N, K) = ({n}, K) with K >= 1, "
                         f"got {np.shape(joints)}")
    if not np.issubdtype(joints.dtype, np.integer):
        raise InputError(f"joint indices must be integers, got dtype {joints.dtype}")
    weights = np.asarray(weights)
    if weights.ndim == 1:
        weights = weights[:, None]
    if weights.shape != joints.shape:
        raise InputError(f"weights must have the shape of the joint indices {joints.shape}, "
                         f"got {weights.shape}")
    weights = real_rows(weights, "weights", weights.shape[1:])
    if np.any(weights < 0):
        rows = np.flatnonzero((weights < 0).any(axis=1))
        raise InputError(f"weights must be non-negative: {len(rows)} of {n} vertices have "
                         f"negative weights (first: vertex {rows[0]})")
    sums = weights.sum(axis=1)
    if np.any(sums <= 0):
        rows = np.flatnonzero(sums <= 0)
        raise InputError(f"{len(rows)} of {n} vertices have all-zero weights (first: vertex "
                         f"{rows[0]}); every vertex needs at least one positive weight")
    used = weights > 0
    joints = joints.astype(np.int64)
    if np.any(joints[used] < 0):
        rows = np.flatnonzero((used & (joints < 0)).any(axis=1))
        raise InputError(f"joint indices must be >= 0: {len(rows)} of {n} vertices have a "
                         f"negative index with positive weight (first: vertex {rows[0]})")
    joints = np.where(used, joints, 0)
    weights = weights / sums[:, None]
    max_joint = int(joints.max())
    return rest, joints, weights, max_joint


def _check_mats(mats, max_joint: int, *, frames: bool = False) -> np.ndarray:
    mats = np.asarray(mats, dtype=np.float64)
    want = "(F, J, 4, 4)" if frames else "(J, 4, 4)"
    nd = 4 if frames else 3
    if mats.ndim != nd or mats.shape[-2:] != (4, 4) or mats.shape[-3] == 0 \
            or (frames and mats.shape[0] == 0):
        raise InputError(f"skinning matrices must have shape {want}, got {mats.shape}")
    largest = float(np.abs(mats).max())          # NaN or inf if any entry is (one pass for both)
    if not np.isfinite(largest):
        raise InputError("skinning matrices contain NaN or inf; give finite values")
    j = mats.shape[-3]
    if max_joint >= j:
        raise InputError(f"joint index {max_joint} is out of range for {j} skinning matrices "
                         f"(valid: 0..{j - 1})")
    if np.abs(mats[..., 3, :] - _AFFINE_BOTTOM).max() > 1e-6 * max(1.0, largest):
        raise InputError("skinning matrices must be affine: bottom row 0 0 0 1")
    return mats


_AFFINE_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- dual quaternions

def dual_quaternions(mats) -> np.ndarray:
    """Unit dual quaternions (..., 8) = (qr.xyzw, qd.xyzw) of the rigid parts of mats (..., 4, 4).

    The rotation is the nearest rotation to the 3x3 block, scale and shear dropped: its
    polar factor (:func:`nrpose.skeleton.polar_components`; a few Newton–Schulz steps for
    the near-conformal float32 matrices of glTF characters, cheaper than scipy's
    orthogonalising from_matrix). ``qd = 0.5 (t, 0) qr`` with t the
    translation column. Reflections (det <= 0) are rejected.
    """
    mats = np.asarray(mats, dtype=np.float64)
    lead = mats.shape[:-2]
    flat = mats.reshape(-1, 4, 4)
    lin = flat[:, :3, :3]
    C = np.ascontiguousarray(np.moveaxis(lin, 0, -1))                 # (3, 3, n) component-major
    det = det_components(C)
    if np.any(det <= 0):
        raise InputError(f"{int(np.count_nonzero(det <= 0))} skinning matrices have a "
                         f"non-positive determinant (reflection or collapse); DQS needs rotations")
    rot = np.moveaxis(polar_components(C, lin), -1, 0)
    qr = matrix_quats(rot)
    t = flat[:, :3, 3]
    out = np.empty((len(flat), 8))
    out[:, :4] = qr                                   # (x, y, z, w)
    v, w = qr[:, :3], qr[:, 3:]
    out[:, 4:7] = 0.5 * (w * t + _cross(t, v))        # qd = 0.5 (t, 0) qr
    out[:, 7] = -0.5 * np.einsum("ni,ni->n", t, v)
    return out.reshape(lead + (8,))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (M, 3) arrays (np.cross is slow on small arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


# --------------------------------------------------------------------------- references

def lbs_reference(rest, joints, weights, mats) -> np.ndarray:
    """Linear blend skinning in float64 numpy: (N, 3) posed vertices."""
    rest, joints, weights, max_joint = prepare_influences(rest, joints, weights)
    mats = _check_mats(mats, max_joint)
    blend = np.einsum("nk,nkij->nij", weights, mats[joints, :3, :])   # (N, 3, 4)
    return np.einsum("nij,nj->ni", blend[:, :, :3], rest) + blend[:, :, 3]


def dqs_reference(rest, joints, weights, mats) -> np.ndarray:
    """Dual quaternion skinning in float64 numpy of the rigid parts of mats: (N, 3)."""
    rest, joints, weights, max_joint = prepare_influences(rest, joints, weights)
    mats = _check_mats(mats, max_joint)
    return _dqs(rest, joints, weights, dual_quaternions(mats))


def dqs_reference_dq(rest, joints, weights, dq) -> np.ndarray:
    """Dual quaternion skinning from per-joint unit dual quaternions dq (J, 8) directly."""
    rest, joints, weights, max_joint = prepare_influences(rest, joints, weights)
    dq = _check_dq(dq, max_joint)
    return _dqs(rest, joints, weights, dq)


def _check_dq(dq, max_joint: int, *, frames: bool = False) -> np.ndarray:
    dq = np.asarray(dq, dtype=np.float64)
    nd = 3 if frames else 2
    if dq.ndim != nd or dq.shape[-1] != 8 or dq.shape[-2] == 0:
        raise InputError(f"dual quaternions must have shape {'(F, J, 8)' if frames else '(J, 8)'}"
                         f", got {dq.shape}")
    if not np.all(np.isfinite(dq)):
        raise InputError("dual quaternions contain NaN or inf; give finite values")
    if max_joint >= dq.shape[-2]:
        raise InputError(f"joint index {max_joint} is out of range for {dq.shape[-2]} dual "
                         f"quaternions (valid: 0..{dq.shape[-2] - 1})")
    if np.any(np.abs(np.linalg.norm(dq[..., :4], axis=-1) - 1.0) > 1e-3):
        raise InputError("dual quaternions must have unit real parts (|qr| = 1)")
    return dq


def _dqs(rest, joints, weights, dq) -> np.ndarray:
    n = len(rest)
    dominant = joints[np.arange(n), np.argmax(weights, axis=1)]     # first max on ties
    q = dq[joints]                                                  # (N, K, 8)
    dot = np.einsum("nki,ni->nk", q[..., :4], dq[dominant, :4])
    s = np.where(dot < 0, -weights, weights)
    b = np.einsum("nk,nki->ni", s, q)
    b = b / np.linalg.norm(b[:, :4], axis=1, keepdims=True)
    r, rw, d, dw = b[:, :3], b[:, 3:4], b[:, 4:7], b[:, 7:8]
    c = np.cross(r, rest) + rw * rest
    t = rw * d - dw * r + np.cross(r, d)
    return rest + 2.0 * (np.cross(r, c) + t)


# --------------------------------------------------------------------------- device

class Skinner(device.BoundKernel):
    """Skinning deformer bound once to a mesh's rest vertices and influences (a
    :class:`nrpose.device.BoundKernel`).

    ``method`` is ``"lbs"``, ``"dqs"`` or ``"cor"`` (skinning with optimized centers of
    rotation, :mod:`nrpose.pose.cor`, whose :class:`~nrpose.pose.cor.CorSkinner` computes
    ``centers`` (N, 3), the vertices' centers of rotation, at bind). Construction validates the inputs,
    normalises weights, sorts each vertex's influences by decreasing weight,
    uploads everything once, poses the identity once (PoCL compiles the kernel
    for each device at its first launch) and times one frame of the kernel on
    the calling thread alone; :meth:`pose` and :meth:`pose_frames` then cost one
    (shared) kernel launch each. Not thread-safe: pose one deformer from one thread at
    a time (its launches share per-pose arrays and a job mailbox).
    """

    def __init__(self, rest, joints, weights, method: str = "lbs", centers=None):
        if method not in PROGRAMS:
            raise InputError(f"skinning method must be one of {tuple(PROGRAMS)}, got {method!r}")
        if (centers is None) != (method != "cor"):
            raise InputError("centers: give them with method 'cor' (only)")
        import pyopencl as cl
        self.method = method
        rest, joints, weights, self.max_joint = prepare_influences(rest, joints, weights)
        if centers is not None:
            centers = np.asarray(centers, np.float64)
            if centers.shape != rest.shape or not np.isfinite(centers).all():
                raise InputError(f"centers: expected finite values of shape {rest.shape}, got {np.shape(centers)}")
            # the kernel's bound rows (its `rest`): v - c, then c
            rest = np.concatenate([rest - centers, centers], axis=1)
        n, k = joints.shape
        self.n_vertices, self.n_influences = n, k
        self.n = n              # points per frame (BoundKernel)
        order = np.argsort(-weights, axis=1, kind="stable")         # dominant first
        joints = np.take_along_axis(joints, order, axis=1)
        weights = np.take_along_axis(weights, order, axis=1)
        # vertices stored sorted by their joints (influence 0, then 1, ...), so that a
        # group's 8 lanes nearly always share influence k's joint (kernels/skinning.cl:
        # its parameters are then read once for the 8); `rows` sends each to its row
        stored = np.lexsort(joints.T[::-1])
        rest, joints, weights = rest[stored], joints[stored], weights[stored]

        g = -(-n // LANES)
        npad = g * LANES
        self.n_groups = g       # groups of 8 vertices (the last one padded)
        self._frame_floats = 3 * npad
        r = np.zeros((npad, rest.shape[1]), np.float32)
        r[:n] = rest
        jj = np.zeros((npad, k), np.int32)
        jj[:n] = joints
        ww = np.zeros((npad, k), np.float32)
        ww[:n] = weights
        ww[n:, 0] = 1.0                                              # padding: joint 0, weight 1
        rows = np.arange(npad, dtype=np.int32)                      # padding: rows n.. of the slab
        rows[:n] = stored
        # (G, 8, C) -> (G, C, 8): SoA per group of 8 vertices
        soa = lambda a: np.ascontiguousarray(a.reshape(g, LANES, -1).transpose(0, 2, 1))
        ctx, self._queue = device.context()
        self._ctx = ctx
        mf = cl.mem_flags
        ro = mf.READ_ONLY | mf.COPY_HOST_PTR
        self._rest = cl.Buffer(ctx, ro, hostbuf=soa(r))
        self._joints = cl.Buffer(ctx, ro, hostbuf=soa(jj))
        self._weights = cl.Buffer(ctx, ro, hostbuf=soa(ww))
        self._rows = cl.Buffer(ctx, ro, hostbuf=device.run_coded_rows(rows, LANES))
        self._bound_bytes = sum(b.size for b in (self._rest, self._joints, self._weights, self._rows))
        self._kernel = cl.Kernel(device.program(*PROGRAMS[method]), method)
        for arg, value in ((ARG_REST, self._rest), (ARG_JOINTS, self._joints), (ARG_WEIGHTS, self._weights),
                           (ARG_ROWS, self._rows), (ARG_K, np.int32(k)), (ARG_G, np.int32(g)),
                           (ARG_BLOCK, np.int32(BLOCK)), (ARG_ROLE, np.int32(device.ROLE_CALLER))):
            self._kernel.set_arg(arg, value)
        self._blocks = -(-g // BLOCK)
        # Per-pose parameters, posed vertices and the job mailbox:
        # device.HostArray (fine-grained SVM when the device has it). Setting
        # ``_svm = False`` forces the copying buffer path (tests use it on PoCL):
        # the next pose replaces the arrays, and launches run on one queue.
        self._svm = device.fine_grain_svm()
        self._in: device.HostArray | None = None     # per-pose parameters
        self._out: device.HostArray | None = None    # posed vertices
        self._jobs: device.Jobs | None = None       # the kernel's job mailbox (share.h)
        self._joints_bound = -1
        # what the kernel's output argument is bound to: (HostArray, first frame), the
        # deformer's own slab (_out, 0) or a frames_array's memory (frames_in)
        self._out_bound: tuple | None = None
        self._batch = 0       # frames of the last launch
        self._warm_up(lambda: self.pose(np.tile(np.eye(4), (self.max_joint + 1, 1, 1))))

    # -- per pose -------------------------------------------------------------
    def pose(self, mats, out: np.ndarray | None = None) -> np.ndarray:
        """Posed vertices (N, 3) float64 for skinning matrices (J, 4, 4); out: optional
        (N, 3) float array to write them into instead (and return)."""
        mats = _check_mats(mats, self.max_joint)
        self._check_out(out, (self.n_vertices, 3))
        result = self._posed(self._params(mats[None]), 1, None if out is None else out[None])
        return result[0] if out is None else out

    def pose_frames(self, mats, out: np.ndarray | None = None) -> np.ndarray:
        """Posed vertices (F, N, 3) float64 for F frames of matrices (F, J, 4, 4), one launch;
        out: optional (F, N, 3) float array to write them into instead (and return): a
        float32 one takes the device's values without the float64 array between (a
        clip's frames, `nrpose.pose.poser`), one from :meth:`frames_array` without a copy."""
        mats = _check_mats(mats, self.max_joint, frames=True)
        self._check_out(out, (len(mats), self.n_vertices, 3))
        return self._posed(self._params(mats), len(mats), out)

    def _direct_frames(self) -> bool:
        return self._svm

    @staticmethod
    def _check_out(out, shape: tuple) -> None:
        if out is not None and (np.shape(out) != shape or not np.issubdtype(np.asarray(out).dtype, np.floating)):
            raise InputError(f"out: expected a float array of shape {shape}, got "
                             f"{np.shape(out)} {getattr(out, 'dtype', type(out).__name__)}")
        device.check_out_writable(out)

    def _params(self, mats: np.ndarray) -> np.ndarray:
        """Per-pose kernel parameters (F, J, W) of matrices (F, J, 4, 4): lbs, the rows 0..2
        (12); dqs, unit dual quaternions (8); cor, the 12 rows and the rotation quaternion (16)."""
        rows = mats[:, :, :3, :].reshape(mats.shape[0], mats.shape[1], 12)
        if self.method == "lbs":
            return rows
        dq = dual_quaternions(mats)
        return dq if self.method == "dqs" else np.concatenate([rows, dq[..., :4]], axis=-1)

    def _array(self, which: str, n: int, arg: int, **kw) -> device.HostArray:
        """HostArray `which` with >= n elements, bound to kernel argument `arg`
        (``kw``: dtype, atomics, as HostArray's).

        HostArrays have a fixed size: a larger batch allocates a larger one
        (and rebinds it); smaller batches reuse the current one. One whose
        memory kind (SVM or not) is not ``_svm``'s is replaced too.
        """
        cur = getattr(self, which)
        if cur is None or cur.host.size < n or cur.svm != self._svm:
            if self._jobs is not None:
                self._jobs.arguments_changed()    # a standing worker reads the array replaced here
            cur = device.HostArray(n, svm=self._svm, **kw)
            self._kernel.set_arg(arg, cur.arg)
            setattr(self, which, cur)
        return cur

    def _run(self, params: np.ndarray, owned: bool, direct: tuple | None) -> np.ndarray | None:
        """params (F, J, W) -> posed (F, N, 3): a new float64 array (owned), else a view of
        the output; None where ``direct``, (memory, first frame) of a :meth:`frames_array`,
        received the frames. One launch (SVM) or write+launch+read."""
        f, j, width = params.shape
        npad = self.n_groups * LANES
        arr_in = self._array("_in", f * j * width, ARG_PARAMS)
        arr_out = self._array("_out", f * npad * 3, ARG_OUT) if direct is None else None
        if self._jobs is None or self._jobs.box.svm != self._svm:
            alone_s = float("inf") if self._jobs is None else self._jobs.alone_s
            if self._jobs is not None:
                self._jobs.retire()
            self._jobs = device.Jobs(svm=self._svm, owner=self, bound_bytes=self._bound_bytes)
            self._jobs.alone_s = alone_s
            self._kernel.set_arg(ARG_JOBS, self._jobs.box.arg)
        self._bind_out(*(direct or (arr_out, 0)))
        if j != self._joints_bound:
            self._jobs.arguments_changed()        # a standing worker's clone has the old J
            self._kernel.set_arg(ARG_J, np.int32(j))
            self._joints_bound = j
        self._batch = f
        arr_in.host[: f * j * width].reshape(params.shape)[...] = params   # float64 -> float32
        arr_in.upload()
        self._launch()
        if direct is not None:        # shared memory: launch_shared has waited for the frames
            return None
        arr_out.download()
        posed = arr_out.host[: f * npad * 3].reshape(f, npad, 3)[:, : self.n_vertices]
        return posed.astype(np.float64) if owned else posed

    def _unbind_frames(self) -> None:
        """The kernel's output bound back to the deformer's own."""
        if self._out is not None and self._out_bound is not None and self._out_bound[0] is not self._out:
            self._bind_out(self._out, 0)

    def _bind_out(self, memory: device.HostArray, first: int) -> None:
        """Bind the kernel's output to frame ``first`` of ``memory``, if it is not bound there,
        and keep it and the parameters alive while a standing worker may use them."""
        bound = self._out_bound
        if bound is None or bound[0] is not memory or bound[1] != first:
            import pyopencl as cl
            arg = memory.arg if first == 0 else cl.SVM(memory.host[3 * self.n_groups * LANES * first:])
            self._jobs.set_argument(self._kernel, ARG_OUT, arg)
            self._out_bound = (memory, first)
        self._jobs.keep = (self._in, memory)

    def _own_output(self) -> None:
        """The next launch writes into the deformer's own output (not a caller's frames)."""
        self._bind_out(self._array("_out", self._batch * self.n_groups * LANES * 3, ARG_OUT), 0)

    def pose_dual_quaternions(self, dq) -> np.ndarray:
        """DQS only: posed vertices (N, 3) from per-joint unit dual quaternions dq (J, 8)."""
        if self.method != "dqs":
            raise InputError("pose_dual_quaternions needs a deformer built with method='dqs'")
        dq = _check_dq(dq, self.max_joint)
        return self._run(dq[None], True, None)[0]


class LbsSkinner(Skinner):
    """Linear blend skinning deformer: ``LbsSkinner(rest, joints, weights).pose(mats)``."""

    def __init__(self, rest, joints, weights):
        super().__init__(rest, joints, weights, method="lbs")


class DqsSkinner(Skinner):
    """Dual quaternion skinning deformer: ``DqsSkinner(rest, joints, weights).pose(mats)``."""

    def __init__(self, rest, joints, weights):
        super().__init__(rest, joints, weights, method="dqs")
