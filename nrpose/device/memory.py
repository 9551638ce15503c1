"""Host memory that kernels use: arrays shared with the device (or shadowed by a device
buffer), frame arrays kernels write into directly, and the slots through which a
deformer hands its frames over without a copy."""
from __future__ import annotations

import operator
import sys

import numpy as np

from ..errors import InputError
from .env import context, fine_grain_svm, pyopencl


class HostArray:
    """An array that the host writes or reads and a kernel uses as an argument.

    On devices with fine-grained SVM the host array *is* the device memory:
    no copies, a pose is only kernel enqueues and a wait. Elsewhere a device
    buffer shadows it and :meth:`upload` / :meth:`download` copy.

    size: number of elements; svm: force (True) or refuse (False) shared
    memory, default: whatever the device offers; dtype: float32 (default) or
    int32; atomics: kernels on several devices update it atomically at once
    (the job mailbox of :func:`launch_shared`). ``host``: the (size,) numpy view;
    ``arg``: what to pass to ``Kernel.set_arg``.
    """

    def __init__(self, size: int, svm: bool | None = None, dtype=np.float32, atomics: bool = False):
        cl = pyopencl()
        ctx, self._queue = context()
        self.svm = fine_grain_svm() if svm is None else svm
        size = max(int(size), 1)
        if self.svm:
            flags = cl.svm_mem_flags.READ_WRITE | cl.svm_mem_flags.SVM_FINE_GRAIN_BUFFER
            if atomics:
                flags |= cl.svm_mem_flags.SVM_ATOMICS
            # 128-byte aligned (pyopencl asks only for the element size): kernels read and
            # write rows of 8 or 16 floats at multiples of 32 bytes from the start, each on
            # as few cache lines as can be
            self.host = cl.svm_empty(ctx, flags, (size,), dtype, alignment=128)
            self.arg = cl.SVM(self.host)
        else:
            self.host = np.zeros(size, dtype)
            self.arg = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, self.host.nbytes)

    def upload(self, rows: tuple[int, int, int] | None = None) -> None:
        """Make host writes visible to kernels enqueued next (no-op with SVM). rows:
        (count, width, stride) in elements, to copy only the first ``width`` elements of
        each of ``count`` rows ``stride`` apart (one rectangular copy; the rest of the
        device's copy stays as it is), e.g. the pose blocks of a deformer's frame blocks
        without the derived blocks that its kernel writes; None: the whole array."""
        if self.svm:
            return
        cl = pyopencl()
        if rows is None:
            cl.enqueue_copy(self._queue, self.arg, self.host, is_blocking=False)
            return
        count, width, stride = rows
        item = self.host.itemsize
        cl.enqueue_copy(self._queue, self.arg, self.host, buffer_origin=(0, 0), host_origin=(0, 0),
                        region=(width * item, count), buffer_pitches=(stride * item,),
                        host_pitches=(stride * item,), is_blocking=False)

    def download(self) -> None:
        """Wait for the calling thread's queue and make kernel writes visible in ``host``
        (after :func:`launch_shared`, which has waited for every device, only the copy
        where there is no SVM)."""
        if self.svm:
            self._queue.finish()
        else:
            pyopencl().enqueue_copy(self._queue, self.host, self.arg, is_blocking=True)

    def settle(self, queue) -> None:
        """Wait for this array's uploads unless ``queue`` runs after them (they were
        enqueued on the context's queue, :func:`nrpose.device.context`; no-op with SVM)."""
        if not self.svm and queue != self._queue:
            self._queue.finish()



#: output slots a deformer hands to its callers without a copy (:class:`Handoff`): two, so
#: that a frame loop may hold the last result while the next pose runs
HANDOFF_SLOTS = 2


class _Owner:
    """The base of a handed-off slot's array: numpy views of that array keep the array
    itself (views collapse their bases only through arrays), and ``memory`` keeps the
    slots' device memory alive (the deformer may go)."""
    __slots__ = ("__array_interface__", "memory")


def _owned_array(owner: _Owner, address: int, shape: tuple, strides: tuple | None = None) -> np.ndarray:
    """A float32 array of ``shape`` (byte ``strides``; None: C order) on the memory at
    ``address``, with ``owner`` (whose ``memory`` keeps that memory alive) as its base."""
    owner.__array_interface__ = {"data": (address, False), "shape": shape, "strides": strides,
                                 "typestr": "<f4", "version": 3}
    return np.asarray(owner)


class _FrameOwner(_Owner):
    """The base of a :func:`frame_array`: ``memory`` is its :class:`HostArray`, ``stride``
    the floats from one frame to the next, ``n`` the points of a frame."""
    __slots__ = ("stride", "n")


def frame_count(frames) -> int:
    """``frames`` as a number of frames (a whole number >= 0), else InputError."""
    try:
        count = operator.index(frames)
    except TypeError:
        count = -1
    if count < 0:
        raise InputError(f"frames must be a whole number >= 0, got {frames!r}")
    return count


def check_out_writable(out) -> None:
    """InputError unless ``out`` is None or a writable numpy array (a deformer's ``out=``)."""
    if out is not None and not getattr(getattr(out, "flags", None), "writeable", False):
        raise InputError("out: the array is not writable; give a writable numpy array "
                         "(e.g. deformer.frames_array(F))")


def frame_array(frames: int, stride: int, n: int, shared: bool = True) -> np.ndarray:
    """An uninitialised float32 array of shape (frames, n, 3): with ``shared`` and
    fine-grained shared memory, in memory a deformer's kernel writes into directly
    (:func:`frames_in`), its frames ``stride`` floats apart (a deformer's padded frame,
    3 Npad >= 3 n), each (n, 3) C-contiguous; else a plain array. InputError unless
    ``frames`` is a whole number >= 0."""
    frames = frame_count(frames)
    if not (shared and fine_grain_svm()):
        return np.empty((frames, n, 3), np.float32)
    owner = _FrameOwner()
    owner.memory, owner.stride, owner.n = HostArray(max(frames, 1) * stride), stride, n
    return _owned_array(owner, owner.memory.host.ctypes.data, (frames, n, 3), (4 * stride, 12, 4))


def frames_in(out: np.ndarray, stride: int) -> tuple[HostArray, int] | None:
    """Where ``out`` lies in a :func:`frame_array` of frames ``stride`` floats apart: (that
    array's memory, the index of out's first frame in it); None if it does not (another
    array, other strides, a view that is not a run of whole frames, e.g. fewer points of a
    frame_array of more, whose other points a launch would overwrite, or is read-only)."""
    base = out
    while isinstance(base, np.ndarray) and isinstance(base.base, np.ndarray):
        base = base.base
    owner = base.base if isinstance(base, np.ndarray) else None
    if not isinstance(owner, _FrameOwner) or owner.stride != stride or out.dtype != np.float32 \
            or not out.flags.writeable or out.ndim != 3 or out.shape[1:] != (owner.n, 3) \
            or out.strides[1:] != (12, 4) or (len(out) > 1 and out.strides[0] != 4 * stride):
        return None
    offset = out.ctypes.data - owner.memory.host.ctypes.data
    if offset % (4 * stride):
        return None
    return owner.memory, offset // (4 * stride)


class Handoff:
    """Frames that launches write and callers receive without a copy.

    ``array``: a :class:`HostArray` of ``count`` slots of ``stride`` floats (shared memory
    only; None elsewhere), apart from a deformer's launch outputs: its kernel takes it as
    an argument beside them and writes a frame into slot i where the frame's pose block
    names slot code ``-1 - i`` (:meth:`free`; codes >= 0 are the launch's own slots).
    Each slot has one float32 array of ``shape`` (C order, at most ``stride`` floats) on
    its memory, made once and never given out itself: after a launch wrote slot i,
    :meth:`take` returns a view of it, and the slot is free again once nothing but this
    object references that array, i.e. once every view of it is gone (a view holds the
    array it was made from; CPython's reference counts, as the GIL build keeps them).
    Posing a frame then costs no copy of the (N, 3) result. A held result keeps ``array`` alive
    (``count`` times its size), not the deformer's other arrays. Without shared memory
    launches download their outputs, so nothing is handed off (:meth:`free` is None);
    nor on a Python built without the GIL, whose reference counts are not exact.
    """

    def __init__(self, count: int, stride: int, shape: tuple):
        # reference counts tell who holds a slot only where the GIL keeps them exact
        gil = getattr(sys, "_is_gil_enabled", lambda: True)()
        self.array = HostArray(count * stride) if fine_grain_svm() and gil else None
        self._arrays = [self._array_at(4 * i * stride, shape) for i in range(count)] if self.array else []

    def _array_at(self, offset: int, shape: tuple) -> np.ndarray:
        owner = _Owner()
        owner.memory = self.array.host
        return _owned_array(owner, self.array.host.ctypes.data + offset, shape)

    def free(self) -> int | None:
        """The slot code (-1 - i) of a slot i whose array nobody holds; None when every
        one is held (or there are none)."""
        for i in range(len(self._arrays)):
            if sys.getrefcount(self._arrays[i]) <= 2:      # this list's reference and the call's
                return -1 - i
        return None

    def take(self, code: int) -> np.ndarray:
        """A view of the array of the slot with code ``code`` (from :meth:`free`, written by
        a launch that has completed), handed to the caller: the slot is not written again
        while it or a view of it lives."""
        return self._arrays[-1 - code].view()
