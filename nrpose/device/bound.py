"""A kernel bound to a deformer's data: the base class of the deformers that pose frames
with one shared launch (:class:`BoundKernel`), and the layout of their output rows."""
from __future__ import annotations

import numpy as np

from ..errors import DeviceError
from .launch import launch_shared
from .mailbox import calibrate_standby
from .memory import frame_array, frame_count, frames_in
from .policy import time_alone


def run_coded_rows(rows: np.ndarray, lanes: int) -> np.ndarray:
    """Output rows (Npad,) int32 of points stored in chunks of ``lanes``, as kernels read
    them (lanes.h STORE_CHUNKV): the first row of each chunk whose rows are consecutive
    (a run of the caller's points that stays together in the stored order) as ~row, so that
    the chunk is stored by vector stores; every other row as it is. A new array."""
    coded = np.array(rows, np.int32)
    first = coded[::lanes]
    runs = (np.diff(coded.reshape(-1, lanes), axis=1) == 1).all(axis=1)
    first[runs] = ~first[runs]
    return coded


class BoundKernel:
    """A kernel bound once to a deformer's rest data that poses F frames per launch
    (:func:`nrpose.device.launch_shared`), writing (F, n, 3) float32 frames on the device.

    The user API it gives its subclasses: :meth:`frames_array` (frames the kernel writes
    into directly), :meth:`release_frames`; each subclass validates its own inputs in
    ``pose`` / ``pose_frames`` and hands them to :meth:`_posed`.

    What a subclass sets at bind: ``n`` (points per frame); ``_kernel`` (its
    ``cl.Kernel``, the mailbox and role its last two arguments); ``_jobs`` (its
    :class:`nrpose.device.Jobs`); ``_blocks`` (blocks of a launch's job); ``_frame_floats``
    (floats from one output frame to the next, 3 Npad; None: no device, frames are plain
    arrays); ``_batch`` (frames of the last launch, set by ``_run``). What it implements:
    ``_run(inputs, owned, direct)`` (write the inputs, launch (:meth:`_launch`), return the
    frames: the caller's own array where ``owned``, else a view of the launch's output;
    None where ``direct``, (memory, first frame) of a :meth:`frames_array`, received them),
    ``_own_output()`` (the next launch writes into the deformer's own output) and
    ``_unbind_frames()`` (:meth:`release_frames`); ``_reference(inputs)`` where it may have
    no device; :meth:`_direct_frames` where launches
    may not write into frame arrays. :mod:`nrpose.diagnostics` runs launches again through
    :meth:`_relaunch`.

    Not thread-safe: pose one deformer from one thread at a time (its launches share
    per-frame arrays and a job mailbox).
    """

    #: the kernel's jobs start with its prologue (kernels/share.h), run by the first
    #: work-item to arrive
    PROLOGUE = False
    _frame_floats: int | None = None

    def frames_array(self, frames: int) -> np.ndarray:
        """An uninitialised (frames, n, 3) array for ``pose_frames``' ``out``: with shared
        memory (PoCL) in memory the kernel writes into directly, so that posing into it, or
        into a run of its frames (``out=a[i:j]``), costs no copy; its frames are each (n, 3)
        C-contiguous but 3 Npad floats apart (Npad: n padded to the kernel's lanes), so the
        whole is not C-contiguous. Float32; float64 where the deformer has no device
        (a numpy backend); elsewhere a plain array. After a launch into it the deformer
        keeps its memory (as the kernel's argument) until a launch into another array,
        its next single pose where that hands its frame over, or :meth:`release_frames`.
        InputError unless ``frames`` is a whole number >= 0."""
        if self._frame_floats is None:
            return np.empty((frame_count(frames), self.n, 3))
        return frame_array(frames, self._frame_floats, self.n, shared=self._direct_frames())

    def release_frames(self) -> None:
        """Stop keeping the memory of the last :meth:`frames_array` posed into (the kernel's
        output bound back to the deformer's own; ~2 us, or ~0.05 ms where a standing
        worker holds it)."""
        if self._frame_floats is not None:
            self._unbind_frames()

    def _direct_frames(self) -> bool:
        """Whether launches may write into a :meth:`frames_array`'s memory."""
        return True

    def _posed(self, inputs, count: int, out: np.ndarray | None) -> np.ndarray:
        """Frames (count, n, 3) of validated ``inputs`` (what ``_run`` takes), in one launch:
        written into ``out`` (shape checked by the caller) and returned, directly where it
        lies in a :meth:`frames_array`, else copied; without it, a new array. Without a
        device (``_frame_floats`` None), ``_reference(inputs)`` computes them."""
        if self._frame_floats is None:
            result = self._reference(inputs)
        else:
            direct = frames_in(out, self._frame_floats) if out is not None and count and self._direct_frames() else None
            result = self._run(inputs, out is None, direct)
            if direct is not None:    # shared memory: launch_shared has waited for the frames
                return out
        if out is None:
            return result
        out[...] = result
        return out

    def _launch(self, queues=None, workers: bool | None = None, kernel=None, timed: bool = False) -> list:
        """Launch the bound kernel (or ``kernel``, a variant taking its arguments,
        :meth:`_bind_variant`) for the last ``_run``'s frames, into the output it is bound
        to; the arguments as :func:`nrpose.device.launch_shared`'s. Returns its events."""
        if kernel is None and queues is None and workers is None and not timed:
            # a pose's launch, positional (keyword arguments cost a small pose ~0.5 us)
            return launch_shared(self._kernel, self._jobs, self._blocks, self._batch, self.PROLOGUE)
        return launch_shared(self._kernel if kernel is None else self._bind_variant(kernel), self._jobs,
                             self._blocks, self._batch, prologue=self.PROLOGUE, queues=queues,
                             workers=workers, timed=timed)

    def _relaunch(self, queues=None, workers: bool | None = None, kernel=None, timed: bool = False) -> list:
        """Run the last posing's launch again (same inputs, same result) into the deformer's
        own output (never into a caller's frames); arguments as :meth:`_launch`'s."""
        self._own_output()
        return self._launch(queues, workers, kernel, timed)

    def _bind_variant(self, kernel):
        """``kernel`` (a variant of the bound kernel) with the bound kernel's current
        arguments; DeviceError where the deformer runs no variants."""
        raise DeviceError(f"{type(self).__name__} runs no kernel variants")

    def _warm_up(self, first_launch) -> None:
        """At bind: ``first_launch()`` poses once (PoCL compiles a kernel's work-group
        function at its first launch on each device, 0.1-0.35 s each, unless
        :func:`nrpose.device.prefetch` compiled it: paid at bind, not in the first
        frame; shared, as launches are until the kernel is timed), then one frame of the
        kernel is timed on the calling thread alone (``alone_s``: small launches are not
        shared) and the standby calibrated once per process, so that no pose pays either."""
        first_launch()
        self._jobs.alone_s = time_alone(lambda: launch_shared(self._kernel, self._jobs, self._blocks,
                                                              prologue=self.PROLOGUE, workers=False))
        calibrate_standby(self._kernel)
