"""Bind once, pose many: the near-rigid MLS deformer on OpenCL (or the numpy reference).

    deformer = Deformer(points, rest_handles, alpha=1.0)        # bind: rest-only work
    posed = deformer.pose(pose)                                   # per frame: (N, 3)

Binding computes :class:`nrpose.pose.blend.RestTerms` in float64 on the host, block
by block, keeps what the kernel uses (:func:`slot_terms`) and uploads it once
(float32) to the device; the kernel objects and buffers
live as long as the deformer. A pose writes (P + 2S)·3 + 9S + 1 floats of
per-handle data (posed positions, the segments' rotations, the output slot) into memory
shared with the device and launches ``nrmls_pose`` once. Its job's prologue,
run by whichever work-item arrives first (kernels/share.h), fits the global
rotation R_g when some point takes it as its reference (:class:`GlobalFit`,
kernels/global_fit.h) and turns the rotations into the table the points use
(relative rotation vectors, or sign-aligned quaternions for the quaternion
blend); then the calling thread takes blocks of points alongside PoCL's worker
threads (:func:`nrpose.device.launch_shared`; in a loop of poses a standing
worker, which polls for the next pose and runs the prologue while the calling
thread enters the kernel), or alone when the launch is too small to be worth
waking them (timed at bind). ``pose_frames`` does the same for F poses in one
launch. ``pose`` hands its result over without a copy (:class:`nrpose.device.Handoff`).

``backend="numpy"`` runs :func:`nrpose.pose.blend.pose_reference` instead (float64);
nothing ever falls back to it silently.
"""
from __future__ import annotations

import numpy as np

from .. import device
from ..errors import DeviceError, InputError
from ..model.handles import HandleSet, Pose
from ..options import BACKENDS
from .blend import BLENDS, GlobalRotation, RestTerms, pose_reference, rest_terms, segment_levers, sign_tree, default_blend

#: points per block of work taken from the job mailbox (share.h): at least BLOCK_POINTS,
#: about BLOCKS_PER_LAUNCH blocks per launch, at most MAX_BLOCK_POINTS (block_points)
BLOCK_POINTS = 256
BLOCKS_PER_LAUNCH = 32
MAX_BLOCK_POINTS = 4096
#: the pose kernel's bound block (kernels/nrmls.cl BOUND_*, :func:`bound_block`): its header's
#: ints, the deformer's constants, then the byte offsets of the rest-only arrays, in this order
BOUND_CONSTANTS = ("np", "nsegs", "block", "pose_stride", "frame_stride", "paper", "npairs")
BOUND_ARRAYS = ("frec", "irec", "len2", "pairs", "fit", "tree")
BOUND_ALIGN = 128       # bytes: each array's offset a multiple (float8 rows are read 32-byte aligned)
#: most segment handles a deformer binds: the quaternion blend's sign tree and the OpenCL
#: kernel's per-frame rotation tables grow as segments² (2,048: 67 MB a frame)
MAX_SEGMENTS = 2048


def check_segment_count(handles: HandleSet) -> None:
    """InputError when ``handles`` has more than :data:`MAX_SEGMENTS` segments (a caller can
    check before it computes weights for them)."""
    if len(handles.segments) > MAX_SEGMENTS:
        raise InputError(f"{len(handles.segments):,} segment handles: at most {MAX_SEGMENTS:,} (the per-frame "
                         "rotation tables grow as segments squared)")
#: index of ``nrmls_pose``'s ``handed`` argument (Deformer._pose_args)
ARG_HANDED = 3


def lanes_for(segments: int) -> int:
    """Points per chunk, the pose kernel's lanes per work-item (-DVW, kernels/lanes.h) for a
    rig with ``segments`` segment handles: 16 without segments, else 8.

    A rig of point handles spends its kernel in chains of ~90 cycles per handle (cross
    product, inverse square root, atan2) that leave the FMA pipes half idle; with 16 lanes
    every operation is two independent 8-lane instructions. Segment rigs, whose slot loop
    reads the rotation table (no such chains) and gathers where lanes disagree, gain
    nothing from 16 and keep 8."""
    return 8 if segments else 16


def block_points(npad: int, lanes: int) -> int:
    """Points per block of work of a launch over ``npad`` points (a multiple of ``lanes``):
    about :data:`BLOCKS_PER_LAUNCH` blocks, each a whole number of chunks of ``lanes`` points,
    from :data:`BLOCK_POINTS` to :data:`MAX_BLOCK_POINTS` points.

    Every block taken is a compare-and-swap on the mailbox's counter, whose cache line then
    moves between the cores; a few dozen blocks still share the work
    evenly between a calling thread and a worker that starts late."""
    chunks = -(-npad // BLOCKS_PER_LAUNCH // lanes)
    return lanes * min(max(chunks, BLOCK_POINTS // lanes), MAX_BLOCK_POINTS // lanes)


class Deformer(device.BoundKernel):
    """A point set bound to rest handles (a :class:`nrpose.device.BoundKernel`).

    points: (N, 3) rest positions; rest: rest handles; alpha: weight exponent;
    blend: "quaternion" (equivariant, continuous at any spread of the rotations), "relative"
    (equivariant; jumps where the dominant segment changes among three or more with different
    rotations) or "paper"; None: :func:`nrpose.pose.blend.default_blend` (quaternion with
    segments, relative on point handles only); lever: "weight"
    (default), "length" or "paper" (see :mod:`nrpose.pose.blend`); distances / weights:
    optional (N, H) matrices replacing Euclidean distances / giving the w_i;
    k: keep the k most influential handles of each point (None: all, dense); t: optional
    (N, S) rest-only segment parameters (:func:`nrpose.pose.blend.rest_terms`).
    ``tree``: the quaternion blend's sign tree (:func:`nrpose.pose.blend.sign_tree` of the
    bound segment weights; None for the other blends).
    With k < S the kernel stores, per point, k segment slots (which segment,
    its coefficients) instead of all S segments. layout: on OpenCL, :func:`bind_layout`
    of these same arguments from an earlier bind (the binding cache), used instead of
    computing it.

    ``terms``: the :class:`nrpose.pose.blend.RestTerms` (float64, dense (N, H)). The
    numpy backend keeps them. The OpenCL deformer never holds them for all points:
    it computes them block by block and keeps of each block only what the kernel
    uses (:func:`slot_terms`), then uploads that; ``terms`` recomputes them from
    the arrays given at bind, which it keeps by reference. Binding a 1M-point,
    65-bone cloud with k = 8 peaks at 0.9 GB of host memory (2.5 GB while the
    dense terms were built first) and holds 0.5 GB once bound. ``lanes``: points per
    chunk of the kernel's bound records (:func:`lanes_for`).

    Not thread-safe: pose one deformer from one thread at a time (its launches share
    per-frame arrays and a job mailbox); deformers posed from different threads each
    take PoCL's worker in turn (:mod:`nrpose.device`).
    """

    PROLOGUE = True

    def __init__(self, points, rest: HandleSet, alpha: float = 1.0, blend: str | None = None,
                 lever: str = "weight", distances=None, weights=None, k: int | None = None,
                 backend: str = "opencl", t=None, layout: dict | None = None):
        self.lever = lever
        check_segment_count(rest)
        if backend not in BACKENDS:
            raise InputError(f"backend must be one of {BACKENDS}, got {backend!r}")
        blend = default_blend(rest) if blend is None else blend
        if blend not in BLENDS:
            raise InputError(f"blend must be one of {BLENDS}, got {blend!r}")
        self.rest = rest
        self.blend = blend
        self.backend = backend
        self.k = k
        self.lanes = lanes_for(len(rest.segments))
        self._bind_inputs = (points, alpha, lever, distances, weights, k, t)
        P = len(rest.points)
        if backend == "opencl":
            # block by block, only what the kernel keeps (slot_terms): the dense (N, H)
            # rest terms of a 1M-point, 65-bone cloud would take 1.6 GB at once
            prefetch_program(rest, k, lever, blend)
            if layout is None:
                layout = bind_layout(kept_terms(points, rest, alpha, lever, distances, weights, k, t), rest, lever,
                                     blend)
            self._terms: RestTerms | None = None
            self.n = int(layout["points"])
            self.tree = layout["tree"].astype(np.int64) if blend == "quaternion" else None
            self._bind_device(layout)
        else:
            self._terms = rest_terms(points, rest, alpha, lever, distances, weights, k, t=t)
            self.n = len(self._terms.u)
            self.tree = sign_tree(self._terms.weights[:, P:]) if blend == "quaternion" else None
            self._frame_floats = None

    @property
    def terms(self) -> RestTerms:
        """The rest terms (kept by the numpy backend, recomputed for the OpenCL one)."""
        if self._terms is not None:
            return self._terms
        points, alpha, lever, distances, weights, k, t = self._bind_inputs
        return rest_terms(points, self.rest, alpha, lever, distances, weights, k, t=t)

    # -- device ---------------------------------------------------------------
    def _bind_device(self, layout: dict) -> None:
        """Upload the per-point terms the kernel keeps (:func:`bind_layout`, all points)."""
        import pyopencl as cl

        ctx, self._queue = device.context()
        blend = self.blend
        P, S = len(self.rest.points), len(self.rest.segments)
        refs_global, K = bool(layout["refs_global"]), int(layout["slots"])
        quat = blend == "quaternion"
        arrays = {name: a for name, a in layout.items() if name not in BIND_SCALARS}
        del layout
        npad = len(arrays["ref"])
        self._npad, self.slots = npad, K
        self._frame_floats = 3 * npad
        self._npairs = len(arrays["pairs"]) // 2 if S else 0   # S = 0: a placeholder pair
        self._npos = 3 * (P + 2 * S)
        # floats per frame: positions, rotations, then the frame's output slot (int32 bits)
        self._pose_stride = self._npos + 9 * (S + 1) + 1
        self._derived_at = derived_layout(P, S, quat)
        # a frame's pose block, then its derived block, on cache lines of their own
        self._frame_stride = -(-(self._pose_stride + self._derived_at["stride"]) // 32) * 32
        # R_g per pose on the device (the pose kernel's prologue), when some point takes the
        # global rotation as its reference
        self._global = GlobalFit(self.rest) if blend != "paper" and refs_global else None
        self._block = block_points(npad, self.lanes)
        self._blocks = -(-npad // self._block)
        frec, irec = chunk_records(arrays, P, S, K, self.lanes)
        block, self._bound_at = bound_block(
            {"np": npad, "nsegs": S, "block": self._block // self.lanes, "pose_stride": self._pose_stride,
             "frame_stride": self._frame_stride, "paper": int(blend == "paper"), "npairs": self._npairs},
            {"frec": frec, "irec": irec, "len2": arrays["len2"], "pairs": arrays["pairs"],
             "fit": self._global.values if self._global is not None else np.zeros(0),
             "tree": (self.tree if self.tree is not None else np.zeros((0, 2))).astype(np.int32)})
        del frec, irec, arrays
        self._bound = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=block)
        del block
        # handle counts are build-time constants of the kernels (nrmls.cl says why): one
        # program per (P, K, dense or sparse, blend, lever), built (~1-1.5 s, PoCL caches
        # it on disk) at the first bind of that configuration in a process
        options = kernel_options(self.lanes, P, S, K, self.lever, quat, self._global is not None)
        self._options = options
        self._kernel = cl.Kernel(device.program("nrmls.cl", options), "nrmls_pose")
        # the pose kernel's job mailbox (kernels/share.h)
        self._jobs = device.Jobs(owner=self, bound_bytes=self._bound.size)
        self._frames = 0      # capacity of the per-frame arrays (grown by _reserve)
        # the pose kernel's arguments change with _reserve and _bind_handed: a variant
        # (nrpose.diagnostics.kernel_variant) is bound again only after such a change
        self._args_version = 0
        self._variants: dict = {}   # variant -> the _args_version it is bound at
        # which parts of a frame's pose block a pose fills (empty views cost ~0.3 us each)
        self._fill_points, self._fill_segments = P > 0, S > 0
        self._batch = 1       # frames of the last launch
        # frames handed to callers without a copy (pose()): slots of their own, so that a
        # held result keeps only them alive (twice its size), not the per-frame arrays
        self._handoff = device.Handoff(device.HANDOFF_SLOTS, 3 * npad, (1, self.n, 3))
        # the memory bound as the kernel's `handed` argument: the handoff slots, or the
        # memory of the frames_array of the last launch into one (pose_frames), bound back
        # only when a pose hands a frame over: binding stops a standing worker, and binding
        # back after every batch made a loop of the box's batches 1.6x slower
        self._handed = self._handoff.array
        self._reserve(1)
        # the identity pose, into the launch's own slot
        identity = Pose(self.rest, np.repeat(np.eye(3)[None], S, axis=0))
        self._warm_up(lambda: self._run([identity], False, None))

    def _pose_args(self) -> list:
        """The arguments of ``nrmls_pose`` as they are now (kernels/nrmls.cl): the bound
        block, the frame blocks, the output slots, the handed slots (:data:`ARG_HANDED`),
        the job mailbox and the role."""
        return [self._bound, self._frame_blocks.arg, self._out.arg,
                (self._out if self._handed is None else self._handed).arg, self._jobs.box.arg,
                np.int32(device.ROLE_CALLER)]

    def _reserve(self, frames: int) -> None:
        """Per-frame arrays (poses in, rotation tables, posed points out) for ``frames`` frames.

        The frame blocks hold each frame's pose block (written here) and then its derived
        block (written by the kernel's prologue), ``_frame_stride`` floats apart. The output
        array holds ``frames`` slots of 3 Npad floats; each frame's pose block names the
        slot it is written into: one of these (codes 0..frames-1) or one of the bind's
        :class:`nrpose.device.Handoff` slots, whose frames are handed to the caller. Nothing
        to do where ``frames`` are reserved already."""
        if frames <= self._frames:
            return
        self._jobs.arguments_changed()      # a standing worker reads the arrays replaced here
        self._frame_blocks = device.HostArray(frames * self._frame_stride)
        blocks = self._frame_blocks.host.reshape(frames, self._frame_stride)[:, : self._pose_stride]
        S = len(self.rest.segments)
        blocks[:, self._npos + 9 * S: self._npos + 9 * S + 9] = np.eye(3).ravel()   # R_g, unless GlobalFit writes it
        self._slots = self._frame_blocks.host.view(np.int32).reshape(frames, self._frame_stride)[
            :, self._pose_stride - 1]
        self._own_slots = np.arange(frames, dtype=np.int32)
        self._out = device.HostArray(frames * 3 * self._npad)
        self._kernel.set_args(*self._pose_args())
        self._args_version += 1
        self._jobs.keep = (self._frame_blocks, self._out, self._handed)
        self._frames = frames
        # each frame's posed point handles (P, 3), segments (S, 2, 3) and rotations (S, 3, 3)
        # as views into its pose block: filling shaped views costs ~0.6 us a pose, slicing
        # and ravelling ~2.6 us
        P, k = len(self.rest.points), 3 * len(self.rest.points)
        self._frame_rows = [(b[:k].reshape(P, 3), b[k:self._npos].reshape(S, 2, 3),
                             b[self._npos:self._npos + 9 * S].reshape(S, 3, 3)) for b in blocks]
        self._results = {}    # frames -> view of the output array, (F, N, 3)

    def pose(self, pose: Pose, out: np.ndarray | None = None) -> np.ndarray:
        """Posed points (N, 3): float32 on OpenCL, float64 on numpy.

        out: optional (N, 3) array to write the result into (and return). Without it, on
        OpenCL, the result is a view of one of the deformer's two handoff slots
        (:class:`nrpose.device.Handoff`), no copy: yours to keep and write, never written
        by the deformer while it or a view of it lives (keeping it keeps both slots, twice
        its size, alive); while both slots are held, a pose returns a copy.
        """
        if out is None and self.backend == "opencl":    # a frame loop's call: the shortest way
            self.rest.same_layout(pose.handles, "posed handles")
            return self._run([pose], True, None)[0]
        if out is not None and np.shape(out) != (self.n, 3):
            raise InputError(f"out: expected an array of shape {(self.n, 3)} (points, 3), got {np.shape(out)}")
        result = self.pose_frames([pose], None if out is None else out[None])[0]
        return result if out is None else out

    def pose_frames(self, poses, out: np.ndarray | None = None) -> np.ndarray:
        """Posed points (F, N, 3) of F poses in one launch (float32; float64 on numpy).

        Each chunk of points (:attr:`lanes`) reads its bound data once for all F frames.
        out: optional (F, N, 3) array to write into (and return): from
        :meth:`frames_array`, the kernel writes into it directly, else the frames are
        copied into it; without it, a new array (one frame: handed over as :meth:`pose`
        hands it).
        """
        poses = list(poses)
        for p in poses:
            self.rest.same_layout(p.handles, "posed handles")
        F = len(poses)
        if out is not None and np.shape(out) != (F, self.n, 3):
            raise InputError(f"out: expected an array of shape {(F, self.n, 3)} (frames, points, 3), "
                             f"got {np.shape(out)}")
        device.check_out_writable(out)
        return self._posed(poses, F, out)

    def _reference(self, poses: list) -> np.ndarray:
        """The numpy backend's frames (F, N, 3) float64: :func:`nrpose.pose.blend.pose_reference`
        of each pose."""
        if not poses:
            return np.zeros((0, self.n, 3))
        return np.stack([pose_reference(self._terms, self.rest, p, self.blend, self.tree) for p in poses])

    def _own_output(self) -> None:
        """The next launch writes into its own output slots (not into a caller's frames)."""
        self._slots[: self._batch] = self._own_slots[: self._batch]

    def _unbind_frames(self) -> None:
        """The kernel's ``handed`` argument bound back to the deformer's own slots."""
        self._bind_handed(self._handoff.array)

    def _bind_variant(self, kernel):
        """``kernel`` (a variant of ``nrmls_pose``, :func:`nrpose.diagnostics.kernel_variant`)
        with the deformer's current arguments, set again only after they changed."""
        if self._variants.get(kernel) != self._args_version:
            self._jobs.arguments_changed(kernel)    # its clones hold the old arguments
            kernel.set_args(*self._pose_args())
            self._variants[kernel] = self._args_version
        return kernel

    def _bind_handed(self, memory) -> None:
        """Bind ``memory`` (a HostArray, or None where there are no handoff slots: the
        deformer's own output, as :meth:`_pose_args` binds it) as the kernel's ``handed``
        argument, if it is not."""
        if memory is not self._handed:
            self._handed = memory
            self._args_version += 1
            self._jobs.set_argument(self._kernel, ARG_HANDED, (self._out if memory is None else memory).arg)
            self._jobs.keep = (self._frame_blocks, self._out, memory)

    def _run(self, poses: list, owned: bool, direct: tuple | None) -> np.ndarray | None:
        """Launch the pose kernel for the poses: the posed points (F, N, 3),
        the caller's own (owned: a single frame is written into a free handed-off slot,
        :class:`nrpose.device.Handoff`, else copied) or a view of the launch's slots;
        direct: (memory, first frame) of a :func:`nrpose.device.frame_array` the frames
        are written into instead (:func:`nrpose.device.frames_in`; returns None)."""
        F = len(poses)
        if F > self._frames:            # (a pose's path: no call where they are reserved)
            self._reserve(F)
        for (points, segments, rotations), pose in zip(self._frame_rows, poses):
            if self._fill_points:
                points[...] = pose.handles.points
            if self._fill_segments:
                segments[...] = pose.handles.segments
                rotations[...] = pose.rotations
        slot = self._handoff.free() if owned and F == 1 and direct is None else None
        if direct is not None:
            self._bind_handed(direct[0])
            self._slots[:F] = -1 - (direct[1] + self._own_slots[:F])
        elif slot is None:
            self._slots[:F] = self._own_slots[:F]
        else:
            self._bind_handed(self._handoff.array)
            self._slots[0] = slot
        # after the slots, which are part of the pose blocks; not the derived blocks (the
        # kernel's prologue writes them); with shared memory there is nothing to upload (the
        # call alone took ~0.3 us of a box pose's ~5 us of host work)
        if not self._frame_blocks.svm:
            self._frame_blocks.upload(rows=(F, self._pose_stride, self._frame_stride))
        self._batch = F
        self._launch()
        if direct is not None:        # shared memory: launch_shared has waited for the frames
            return None
        if slot is not None:
            return self._handoff.take(slot)
        self._out.download()
        result = self._results.get(F)
        if result is None:
            result = self._results[F] = self._out.host[: F * 3 * self._npad].reshape(F, self._npad, 3)[:, : self.n]
        return result.copy() if owned else result


class GlobalFit:
    """R_g, the global rotation (:class:`nrpose.pose.blend.GlobalRotation`, its float64
    reference), fitted on the device (kernels/global_fit.h) for each frame of a block
    of poses by the pose kernel's prologue, where the points read it: no host work per
    pose (the fit on the host would cost each point-handle pose far more than its kernel).

    rest: the rest handles. ``values``: what the fit reads (float64 (1 + 3M,): the
    tie tolerance's scale, then the M = P + 2S centred rest positions (M, 3), point
    handles, then segment ends), bound once (the deformer's bound block).
    """

    def __init__(self, rest: HandleSet):
        fit = GlobalRotation(rest)
        ctx, _ = device.context()
        if not all("cl_khr_fp64" in d.extensions for d in ctx.devices):
            raise DeviceError("point-handle rigs fit their global rotation in double precision: the "
                              "OpenCL device needs cl_khr_fp64 (PoCL's CPU devices have it); choose "
                              "another device with PYOPENCL_CTX or use backend='numpy'")
        self.values = np.concatenate([[fit.scale2], np.ravel(fit.centred)]).astype(np.float64)

    @classmethod
    def fit(cls, rest: HandleSet, poses) -> np.ndarray:
        """R_g (F, 3, 3) float32 of poses of ``rest`` fitted on the device on their own by
        the same code (kernels/global_fit.cl, global_fit.h; for tests and diagnostics)."""
        import pyopencl as cl

        poses = list(poses)
        M = len(rest.points) + 2 * len(rest.segments)
        block = device.HostArray(max(len(poses), 1) * (3 * M + 9))
        rows = block.host.reshape(-1, 3 * M + 9)
        for f, p in enumerate(poses):
            rest.same_layout(p.handles, "posed handles")
            rows[f, : 3 * M] = np.concatenate([p.handles.points.ravel(), p.handles.segments.ravel()])
        ctx, queue = device.context()
        data = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=cls(rest).values)
        kernel = cl.Kernel(device.program("global_fit.cl"), "global_rotation")
        kernel.set_args(block.arg, data, np.int32(M), np.int32(3 * M + 9), np.int32(3 * M))
        block.upload()
        if poses:
            cl.enqueue_nd_range_kernel(queue, kernel, (len(poses),), None)
        block.download()
        return rows[: len(poses), 3 * M:].reshape(-1, 3, 3).copy()


def kernel_options(lanes: int, P: int, S: int, K: int, lever: str, quat: bool, global_fit: bool) -> tuple[str, ...]:
    """Build options of kernels/nrmls.cl for a bind: lanes per work-item, P point handles,
    S segments, K slots per point, the lever rule, the quaternion blend, R_g on the device;
    in a whole-job process (:func:`nrpose.device.whole_job`: it poses clips in batches),
    without the single-pose path (-DBATCHES_ONLY: ~0.15 s less compile on a cold start)."""
    return ((f"-DVW={lanes}", f"-DNPOINTS={P}", f"-DNSLOTS={K}") + (("-DSPARSE",) if K < S else ())
            + (() if levers_stored(lever, S) else ("-DDERIVED_LEVER",)) + (("-DQUAT_BLEND",) if quat else ())
            + (("-DGLOBAL_FIT",) if global_fit else ()) + (("-DBATCHES_ONLY",) if device.whole_job() else ()))


def prefetch_program(rest: HandleSet, k: int | None = None, lever: str = "weight", blend: str | None = None) -> None:
    """Start compiling the pose kernel an OpenCL :class:`Deformer` of these arguments will
    use (:func:`nrpose.device.prefetch`), where its options are known before the rest
    terms: without point handles (or with the paper blend) no point takes the global
    rotation as reference, so R_g is not fitted on the device."""
    P, S = len(rest.points), len(rest.segments)
    blend = default_blend(rest) if blend is None else blend
    if P and blend != "paper":
        return
    K = S if k is None or k >= S else int(k)
    device.prefetch("nrmls.cl", kernel_options(lanes_for(S), P, S, K, lever, blend == "quaternion", False))


#: the entries of :func:`bind_layout` besides :func:`device_layout`'s arrays
BIND_SCALARS = ("points", "slots", "refs_global", "tree")


def bind_layout(kept: dict, rest: HandleSet, lever: str = "weight", blend: str | None = None) -> dict:
    """What an OpenCL :class:`Deformer` uploads of the kept terms (:func:`kept_terms`):
    :func:`device_layout`'s arrays, ``tree`` (the quaternion blend's sign tree, (0, 2) for
    the other blends), and (0-d arrays) ``points`` (n), ``slots`` (K) and ``refs_global``
    (whether some point takes R_g as reference). A Deformer of the same arguments can be
    given it (``layout=``) instead of computing it: the binding cache stores it."""
    P, S = len(rest.points), len(rest.segments)
    blend = default_blend(rest) if blend is None else blend
    arrays, K = device_layout(kept, rest, lever, lanes_for(S), blend == "quaternion")
    tree = sign_tree(segment_weights(kept, P, S)) if blend == "quaternion" else np.zeros((0, 2), np.int64)
    return {**arrays, "tree": tree, "points": np.array(len(kept["u"])), "slots": np.array(K),
            "refs_global": np.array(bool((kept["ref"] == S).any()))}


def kept_terms(points, rest: HandleSet, alpha: float = 1.0, lever: str = "weight", distances=None,
               weights=None, k: int | None = None, t=None) -> dict:
    """What an OpenCL :class:`Deformer` of these arguments keeps of its rest terms
    (:func:`slot_terms`, all points), computed block by block (:func:`bind_layout` takes them)."""
    return rest_terms(points, rest, alpha, lever, distances, weights, k,
                      per_block=lambda T: slot_terms(T, k, lever), t=t)


def slot_terms(T: RestTerms, k: int | None, lever: str) -> dict:
    """What the pose kernel keeps of the rest terms T of some points, in their order
    (float64, per point): ``u`` (n, 3); ``ref`` (n,); ``slot`` (n, K) int64, the K
    segment slots, only with top-k sparsity (k < S: the point's K = k heaviest segments,
    ties to the lower index, listed by index; dense, slot k is segment k); ``coef`` (n, P + 2K), the q*
    coefficients: point handles' w, then per slot w on the segment's posed start a and w t
    on its posed direction b - a (w is the slot's lever coefficient too); ``phat`` (n, P, 3);
    where :func:`levers_stored` (the "paper" rule, rigs without segments) ``lever``
    (n, P + K), the normalised levers (elsewhere the kernel derives them: w |phat|^2 per
    point handle, per slot w times the lever factor folded into its per-pose table, and
    normalises them by 1 / their sum, bound by :func:`device_layout`). Computed block by block
    at bind (:func:`nrpose.pose.blend.rest_terms` ``per_block``), so that the dense (n, H)
    terms never exist for all points at once."""
    n, P, S = len(T.u), T.phat.shape[1], T.t.shape[1]
    ws, t = T.weights[:, P:], T.t
    K = S if k is None or k >= S else int(k)
    if K < S:
        # rest_terms keeps at most k = K non-zero weights per point, so nearly every row's
        # slots are its non-zero segments: taken from the non-zero pattern; rows with fewer
        # (filled with their lowest-index zero ones) or more are sorted
        nz = ws != 0
        full = nz.sum(axis=1) == K
        slot = np.empty((n, K), np.int64)
        slot[full] = np.nonzero(nz[full])[1].reshape(-1, K)
        if not full.all():
            slot[~full] = np.sort(np.argsort(-ws[~full], axis=1, kind="stable")[:, :K], axis=1)
    take = (lambda a: np.take_along_axis(a, slot, axis=1)) if K < S else (lambda a: a)  # noqa: E731
    wk, tk = take(ws), take(t)
    kept = {"u": T.u, "ref": T.ref, "phat": T.phat,
            "coef": np.concatenate([T.weights[:, :P], np.stack([wk, wk * tk], 2).reshape(n, 2 * K)], 1)}
    if K < S:
        kept["slot"] = slot
    if levers_stored(lever, S):
        kept["lever"] = np.concatenate([T.lever[:, :P], take(T.lever[:, P:])], 1)
    return kept


def segment_weights(kept: dict, P: int, S: int):
    """(n, S) scipy sparse matrix of the segment weights ŵ kept by :func:`slot_terms`
    (the slots' w, on their segments): what :func:`nrpose.pose.blend.sign_tree` reads."""
    import scipy.sparse as sp

    w = kept["coef"][:, P::2]
    n, K = w.shape
    cols = kept["slot"] if "slot" in kept else np.broadcast_to(np.arange(K), (n, K))
    return sp.csr_matrix((w.ravel(), (np.repeat(np.arange(n), K), np.ravel(cols))), shape=(n, S))


def levers_stored(lever: str, segments: int) -> bool:
    """Whether the pose kernel reads each point's normalised levers from its bound record
    (``lever`` rows, kernels/nrmls.cl) instead of deriving them per pose (-DDERIVED_LEVER):
    with the "paper" rule, and on rigs without segments, whose point-handle levers
    w |phat|^2 (the same under every rule) the kernel would derive from three more
    products per handle and normalise per point (stored, they pose faster). Segment rigs derive
    theirs: a slot's lever w times its segment's factor, folded into the per-pose table,
    and one bound 1 / lever sum per point, rather than P + K more floats per point."""
    return lever == "paper" or segments == 0


def device_layout(kept: dict, rest: HandleSet, lever: str, lanes: int, quat: bool = False) -> tuple[dict, int]:
    """The per-point arrays that kernels/nrmls.cl binds, as rows of all points
    (:func:`chunk_records` packs them into its chunk-major records; its header
    states the rows), and the number K of segment slots per point (S when
    dense, k < S with top-k sparsity). kept: :func:`slot_terms` of all points.

    Points are stored sorted by reference rotation, then by their slots, so
    that a work-item's ``lanes`` lanes (:func:`lanes_for`) share them; ``row`` sends each
    back to the caller's row. The levers (stored, or 1 / their sum) are bound halved, so
    that the kernel sums half the blended rotation vector (its Rodrigues step then saves
    two multiplies), except for the quaternion blend (``quat``), whose quaternion sum is
    normalised and held against a floor relative to the levers. Returns float32/int32
    arrays padded to a multiple of ``lanes`` points.
    """
    n, P, S = len(kept["u"]), len(rest.points), len(rest.segments)
    refs = kept["ref"]
    slots = kept.get("slot")
    K = S if slots is None else slots.shape[1]
    npad = -(-n // lanes) * lanes

    def soa(rows: np.ndarray) -> np.ndarray:  # (rows, N) -> (rows, Npad) float32
        out = np.zeros((rows.shape[0], npad), np.float32)
        out[:, :n] = rows
        return out

    order = np.lexsort(tuple(slots.T[::-1]) + (refs,)) if K < S else np.argsort(refs, kind="stable")
    # the padding points (coefficients 0) take the last point's reference and slots: they
    # read only rotation-table entries that the prologue writes (the pairs used, below)
    ref = np.full(npad, refs[order[-1]] if n else S, np.int32)
    ref[:n] = refs[order]
    row = np.arange(npad, dtype=np.int32)
    row[:n] = order
    slot = np.zeros((K, npad) if K < S else 1, np.int32)     # stored only when sparse
    if K < S and n:
        slot[:, :n] = slots[order].T
        slot[:, n:] = slot[:, n - 1: n]
    # the (reference, segment) pairs of the rotation table that some point uses
    if not S:
        used = np.zeros(0, np.int64)
    elif K == S:
        used = (np.unique(refs).astype(np.int64)[:, None] * (S + 1) + np.arange(S)).ravel()
    else:
        used = np.unique(refs[:, None].astype(np.int64) * (S + 1) + slots)
    # phat and len2 scaled by 2^-e and 2^-2e, e the binary exponent of phat's largest
    # |component|: exact, the kernel's blend does not change (it uses phat's direction and
    # levers normalised per point), and |phat x y|^2 stays a normal float32 on tiny models
    # (kernels/nrmls.cl, the point-handle loop)
    # (without point handles, the longest segment lever's exponent: the table' entries
    # len2 log(...) and the levers' sum stay normal floats on tiny models too)
    big = float(np.abs(kept["phat"]).max()) if P and n else 0.0
    len2 = segment_levers(rest, lever) if S else np.zeros(0)
    longest = float(np.sqrt(len2.max())) if len2.size else 0.0
    scale = 2.0 ** -np.frexp(big or longest)[1] if big or longest else 1.0
    if longest > 0:
        # at most 2^50 / the longest lever: where every p* sits on a point handle, phat is
        # rounding residue (~1e-19) and its scale would overflow len2 * scale^2 in float32
        scale = min(scale, 2.0 ** (50 - np.frexp(longest)[1]))
    none = np.zeros(1, np.float32)
    stored = levers_stored(lever, S)
    len2_bound = (len2 * scale ** 2).astype(np.float32)
    phat32 = (scale * kept["phat"]).astype(np.float32)      # (n, P, 3), as the kernel reads it
    if not stored:
        # 1 / each point's lever sum (rest-only): point handles' w |phat|^2, the slots'
        # w len2, from the float32 values the kernel reads (a lever factor that rounds to 0
        # there drops out of the sum too)
        w = kept["coef"].astype(np.float32).astype(np.float64)
        lsum = np.zeros(n)
        if P:
            lsum += np.einsum("np,npc,npc->n", w[:, :P], phat32.astype(np.float64), phat32.astype(np.float64))
        if K:
            factor = len2_bound.astype(np.float64)
            lsum += w[:, P::2] @ factor if K == S else np.einsum("nk,nk->n", w[:, P::2], factor[slots])
        inv = np.divide(1.0, lsum, out=np.zeros(n), where=lsum > 0)
        inv = np.minimum(inv, np.finfo(np.float32).max)
    half = 1.0 if quat else 0.5         # exact: the blend sums r / 2 (kernels/nrmls.cl, Rodrigues)
    arrays = {
        "u": soa(kept["u"][order].T), "ref": ref, "row": row, "slot": slot,
        "coef": soa(kept["coef"][order].T),
        # the rows after phat: the stored normalised levers (P + K rows), or 1 / the lever sum
        # of levers derived in the kernel from coef, phat and len2 (1 row)
        "lever": soa(half * kept["lever"][order].T) if stored else soa(half * inv[order][None]),
        "len2": len2_bound if S else none,
        "phat": soa(phat32[order].transpose(1, 2, 0).reshape(3 * P, n)) if P else none,
        "pairs": (np.stack([used // (S + 1), used % (S + 1)], 1).astype(np.int32).ravel() if S
                  else np.zeros(2, np.int32)),
    }
    return arrays, K


def bound_block(constants: dict, arrays: dict) -> tuple[np.ndarray, dict]:
    """The pose kernel's bound block (kernels/nrmls.cl BOUND_*): one read-only argument for
    the deformer's constants and rest-only arrays, since PoCL's enqueue costs the calling
    thread ~0.1 us per argument.

    constants: {name: int} for each of :data:`BOUND_CONSTANTS`; arrays: {name: numpy array}
    for each of :data:`BOUND_ARRAYS` (any dtype, copied as its C-order bytes). Returns (the
    block, uint8 (nbytes,): the header's int32s, then each array at a multiple of
    :data:`BOUND_ALIGN` bytes; {name: (byte offset, nbytes)} of the arrays). DeviceError
    when the block outgrows the header's int32 offsets (2 GiB)."""
    header = 4 * (len(BOUND_CONSTANTS) + len(BOUND_ARRAYS))
    at, where = -(-header // BOUND_ALIGN) * BOUND_ALIGN, {}
    for name in BOUND_ARRAYS:
        where[name] = (at, arrays[name].nbytes)
        at += -(-arrays[name].nbytes // BOUND_ALIGN) * BOUND_ALIGN
    if at > np.iinfo(np.int32).max:
        raise DeviceError(f"the deformer's bound data takes {at / 2**30:.1f} GiB, more than the pose "
                          f"kernel's 2 GiB; bind fewer points per deformer (or use sparse weights, k)")
    block = np.zeros(at, np.uint8)
    block[:header].view(np.int32)[:] = ([int(constants[n]) for n in BOUND_CONSTANTS]
                                        + [where[n][0] for n in BOUND_ARRAYS])
    for name in BOUND_ARRAYS:
        offset, nbytes = where[name]
        block[offset: offset + nbytes] = np.ascontiguousarray(arrays[name]).reshape(-1).view(np.uint8)
    return block, where


def derived_layout(P: int, S: int, quat: bool) -> dict:
    """Offsets (floats) of the parts of a frame's derived block, which the pose kernel's
    prologue writes (kernels/nrmls.cl, its header), and ``stride``, the block's size:
    refs (S+1, 3, 3), quats (S+1, 4), ploc (S+1, P, 3), segv (S, 6), table (S+1, S, TW)
    with TW = 4 for the quaternion blend (quat), else 3."""
    quats = 9 * (S + 1)
    ploc = quats + 4 * (S + 1)
    segv = ploc + 3 * P * (S + 1)
    table = segv + 6 * S
    return {"refs": 0, "quats": quats, "ploc": ploc, "segv": segv, "table": table,
            "stride": table + (4 if quat else 3) * (S + 1) * S}


def chunk_records(arrays: dict, P: int, S: int, K: int, lanes: int) -> tuple[np.ndarray, np.ndarray]:
    """The per-point arrays of :func:`device_layout` packed chunk-major, as
    kernels/nrmls.cl reads them: (float32 records, int32 records), one record
    of rows of ``lanes`` lanes per chunk of ``lanes`` stored points (rows in the kernel's order;
    the output rows run-coded, :func:`nrpose.device.run_coded_rows`). P point handles, S
    segments, K segment slots (K < S: sparse, slots stored)."""
    floats = [arrays["u"], arrays["coef"]] + ([arrays["phat"]] if P else []) + [arrays["lever"]]
    row = device.run_coded_rows(arrays["row"], lanes)
    ints = [arrays["ref"][None], row[None]] + ([arrays["slot"]] if K < S else [])

    def pack(rows: list[np.ndarray]) -> np.ndarray:  # (R, Npad) blocks -> (Npad/lanes, R, lanes)
        a = np.concatenate(rows)
        return np.ascontiguousarray(a.reshape(len(a), -1, lanes).transpose(1, 0, 2)).ravel()

    return pack(floats), pack(ints)
