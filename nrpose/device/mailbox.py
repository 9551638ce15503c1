"""The job mailbox of a kernel's shared launches (kernels/share.h): the launch protocol
between the host and the work-items that take blocks of a job, as methods of
:class:`Jobs`, and the standing worker that polls a mailbox for its next job."""
from __future__ import annotations

import os
import time
import weakref

import numpy as np

from ..errors import DeviceError
from . import policy
from .env import fine_grain_svm, plain_opencl, pyopencl, worker_queue
from .memory import HostArray
from .timing import event_clock_ns

# the job mailbox's fields and roles (kernels/share.h)
JOB_NEXT, JOB_QUIT, JOB_STANDING = 0, 3, 4
JOB_DESC = 8                        # (blocks, frames, ends, -) of jobs with even tags, then odd ones
JOB_DESCS = (JOB_DESC, JOB_DESC + 4)  # the descriptor of tag t: JOB_DESCS[t & 1] (JOB_BLOCKS_OF)
JOB_END_BITS = 10                   # a job taken from both ends: blocks taken from its start, then its end
JOB_ENDS_MAX_BLOCKS = 1000          # its two counts then never read as JOB_PROLOGUE or JOB_IN_PROLOGUE
#: owners take their jobs from both ends (Jobs.ends) when the data their kernel binds is at
#: most this: two cores' L2 caches then hold it between them, each core the half it works on
#: in every launch
ENDS_MAX_BOUND_BYTES = 1 << 20
JOB_DONE = 16                       # on a cache line of its own
JOB_INTS = 32
JOB_TAG_SHIFT = 20
JOB_CLOSED = (1 << JOB_TAG_SHIFT) - 1      # block index past every job's last: none to take
JOB_PROLOGUE = JOB_CLOSED - 1              # of a published job whose prologue comes first
JOB_IN_PROLOGUE = JOB_CLOSED - 2           # of a job whose prologue a work-item runs
ROLE_CALLER = 0
ROLE_PROLOGUE = -1                  # plain launches: the launch of the job's prologue (share.h)

#: a launch of fewer blocks than this never stands a worker (it may still wake one, when
#: its frames take SHARE_MIN_S alone): too little work to share with a standing worker
STANDING_MIN_BLOCKS = 4
#: after another mailbox's launch ended its standing worker, a mailbox does not stand one
#: for this long (seconds): two deformers posed in turn would otherwise hand the worker
#: back and forth, each ending the other's
STANDING_YIELD_S = 0.1
#: ... unless it has launched this many times in a row since another mailbox last did
#: (deformers posed in blocks of frames in turn)
STANDING_RUN = 8


_POLLS_PER_S: list = [None]         # a standing worker's idle polls per second, once measured


def calibrate_standby(kernel) -> None:
    """Measure, once per process, how many idle polls a standing worker makes per second
    (share.h next_job), with a clone of ``kernel`` (a deformer's, after its first launches,
    which built it for PoCL's worker device) standing on a mailbox of its own with no job
    to serve: launched with 1 poll and with enough for 1 ms or more (doubling), each timed
    to its end; the difference cancels the launch. Owners call it at bind, so that no pose
    pays it (3-5 ms). No-op without a worker device, shared memory or standing workers, and
    where launches are plain OpenCL (:func:`nrpose.device.plain_opencl`)."""
    wq = worker_queue()
    if (_POLLS_PER_S[0] is not None or wq is None or not fine_grain_svm() or policy.standby_s() <= 0
            or plain_opencl()):
        return
    cl = pyopencl()
    policy.stop_standing()
    probe = kernel.clone()
    box = HostArray(JOB_INTS, dtype=np.int32, atomics=True)
    box.host[:] = 0
    box.host[JOB_NEXT] = JOB_CLOSED                # no block to take: the worker only polls
    probe.set_arg(probe.num_args - 2, box.arg)

    def run(polls: int) -> float:
        probe.set_arg(probe.num_args - 1, np.int32(polls))
        t = time.perf_counter()
        cl.enqueue_nd_range_kernel(wq, probe, (1,), (1,)).wait()
        return time.perf_counter() - t

    base, polls = min(run(1) for _ in range(2)), 8192
    while True:
        span = run(polls) - base
        if span >= 1e-3 or polls >= 1 << 28:
            _POLLS_PER_S[0] = polls / max(span, 1e-6)
            return
        polls *= 2


class Jobs:
    """The job mailbox of a kernel's shared launches (kernels/share.h): a small
    int32 :class:`HostArray` (``box``) that a kernel takes as its last-but-one argument,
    its ``role`` (:data:`ROLE_CALLER`) being the last; the owner sets both with the
    kernel's other arguments. One per deformer.

    ``alone_s``: seconds one frame of the kernel takes on the calling thread alone
    (timed by the owner at bind, :class:`nrpose.device.BoundKernel`; until then launches
    are shared).
    ``keep``: the arrays the kernel's launches use (set by the owner, kept alive while
    a standing worker may still read them). A standing worker runs a clone of the
    kernel made when it first stood, with the arguments of then: owners call
    :meth:`arguments_changed` before they set any argument again (or free an array
    the kernel reads), :meth:`stop` to end the standing worker; ``owner``: the
    deformer whose arrays the kernel reads, when it is collected the standing worker
    is ended (:meth:`stop`). ``ends``: publish jobs of at most :data:`JOB_ENDS_MAX_BLOCKS`
    blocks to be taken from both ends, standing workers from the start and the calling
    thread (and woken workers, whose role is the caller's) from the end (share.h): where
    ``bound_bytes``, the size of the data the owner's kernel binds, is given and at most
    :data:`ENDS_MAX_BOUND_BYTES`. ``plain``: launches are plain OpenCL
    (:func:`nrpose.device.plain_opencl`; share.h PLAIN_OPENCL): the job's prologue runs as
    a launch of its own, of the kernel's clone with role :data:`ROLE_PROLOGUE`
    (:meth:`prologue_kernel`).
    Not thread-safe: launch a deformer's kernels from one thread at a time.
    """

    def __init__(self, svm: bool | None = None, owner=None, bound_bytes: int | None = None):
        self.box = HostArray(JOB_INTS, svm=svm, dtype=np.int32, atomics=True)
        self.box.host[:] = 0
        self.box.upload()
        self.alone_s = float("inf")
        self.keep: tuple = ()
        self.ends = bound_bytes is not None and bound_bytes <= ENDS_MAX_BOUND_BYTES
        self.plain = plain_opencl()
        self._tag = 0
        self._last = float("-inf")      # perf_counter() at the end of the last launch
        self._standing = None           # (kernel, event, arrays kept, pid) of a standing worker
        self._clones: dict = {}         # kernel -> its standing clone (role: the poll budget)
        self._prologues: dict = {}      # kernel -> its clone of role ROLE_PROLOGUE (plain launches)
        self._displaced = float("-inf")  # when another mailbox's launch last ended its worker
        self._run = 0                   # launches in a row with no other mailbox's between
        self.published_ns = 0           # EVENT_CLOCK at the last publish() (published_span_s)
        # a standing worker reads the owner's arrays: end it when the owner is collected
        # (retire() detaches this, when the owner replaces its mailbox)
        self._finalizer = weakref.finalize(owner, self.stop) if owner is not None else None

    def publish(self, blocks: int, frames: int, prologue: bool = False, timed: bool = False) -> None:
        """Make a job of ``blocks`` blocks and ``frames`` frames the one kernels take
        blocks of (share.h: the descriptor of the new tag's parity filled, taken from both
        ends where :attr:`ends` and it has at most :data:`JOB_ENDS_MAX_BLOCKS` blocks, and the
        done count zeroed, then the counter opened at block 0 in one write, or, with a
        ``prologue``, at the prologue, which the first work-item to arrive runs before
        opening the blocks); timed: record when (``published_ns``, :func:`published_span_s`;
        0 otherwise), just before that write. The mailbox is uploaded (no-op with shared
        memory) on the context's queue."""
        if not 0 <= blocks < JOB_IN_PROLOGUE:
            raise DeviceError(f"a launch of {blocks} blocks exceeds the job mailbox's "
                              f"{JOB_IN_PROLOGUE - 1}; pose fewer points per deformer")
        self._tag = tag = self._tag % 2047 + 1
        b = self.box.host
        # the last job is done (its launch waited for it) and its work-items have counted;
        # one still holding its tag reads the other descriptor
        desc = JOB_DESCS[tag & 1]
        b[desc] = blocks
        b[desc + 1] = frames
        b[desc + 2] = self.ends and blocks <= JOB_ENDS_MAX_BLOCKS
        b[JOB_DONE] = 0
        self.published_ns = event_clock_ns() if timed else 0   # only timed launches read the clock
        # open: block 0 is next, or first the prologue, which its runner opens
        b[JOB_NEXT] = tag << JOB_TAG_SHIFT | (JOB_PROLOGUE if prologue else 0)
        self.box.upload()

    def mode(self, kernel, frames: int, blocks: int, standby: float) -> str:
        """How a launch of ``kernel`` (``frames`` frames, ``blocks`` blocks) uses PoCL's
        workers when the caller leaves it to :func:`launch_shared` (``workers=None``):

        * ``"standing"``: a standing worker of this kernel polls this mailbox (it costs
          nothing), or, with standing workers on (``standby`` > 0 seconds), this
          mailbox's last launch ended less than ``standby`` ago and the job has
          :data:`STANDING_MIN_BLOCKS` blocks or more: frames posed in a loop, where the
          worker woken now stands for the next ones; but not within
          :data:`STANDING_YIELD_S` of another mailbox's launch ending this one's worker
          (deformers posed in turn would hand the worker back and forth) unless this
          mailbox has launched :data:`STANDING_RUN` times in a row since (deformers posed
          in blocks of frames in turn);
        * ``"woken"``: the frames take at least :data:`SHARE_MIN_S` on the calling thread
          alone (:func:`worth_sharing`): workers woken for this launch only (launches
          spaced further apart than ``standby``, e.g. one frame per display refresh,
          spend no CPU polling between frames);
        * ``"alone"``: otherwise, the calling thread alone.
        """
        now = time.perf_counter()
        if standby > 0 and (self.standing(kernel) or (
                blocks >= STANDING_MIN_BLOCKS and now - self._last < standby
                and (now - self._displaced >= STANDING_YIELD_S or self._run >= STANDING_RUN))):
            return "standing"
        return "woken" if policy.worth_sharing(frames, self.alone_s) else "alone"

    def standing(self, kernel) -> bool:
        """True while a standing worker of ``kernel`` polls this mailbox."""
        return (self._standing is not None and self._standing[0] is kernel
                and bool(self.box.host[JOB_STANDING]))

    def stand(self, kernel, wq, seconds: float) -> None:
        """Enqueue a standing worker of ``kernel`` on the workers' queue ``wq`` (ending any
        other first), taking the published job's blocks and then polling for the next
        for about ``seconds``. It runs the kernel's clone (made at its first standing,
        its arguments as they were then, the role set to the poll budget), so that
        ``kernel`` keeps ROLE_CALLER and no argument is set per launch (pyopencl's
        set_arg of an int takes ~15 us)."""
        policy.stop_standing()
        if _POLLS_PER_S[0] is None:
            calibrate_standby(kernel)
        polls = min(max(1, int(seconds * _POLLS_PER_S[0])), 2**31 - 1)
        clone = self._clones.get(kernel)
        if clone is None or clone[1] != polls:
            worker = kernel.clone()
            worker.set_arg(worker.num_args - 1, np.int32(polls))
            self._clones[kernel] = clone = (worker, polls)
        self.box.host[JOB_QUIT] = 0
        self.box.host[JOB_STANDING] = 1
        n = wq.device.max_compute_units
        event = pyopencl().enqueue_nd_range_kernel(wq, clone[0], (n,), (1,))
        self._standing = (kernel, event, self.keep, os.getpid())
        wq.flush()
        policy.hold_worker(self)

    def stop(self, displaced: bool = False) -> None:
        """End this mailbox's standing worker (if any) and wait until it has returned (in a
        process forked since it stood, only forget it: its thread is not there).
        displaced: another mailbox's launch needs the worker device; this mailbox then does
        not stand a worker again for :data:`STANDING_YIELD_S`, unless it launches
        :data:`STANDING_RUN` times in a row (:meth:`mode`)."""
        with policy.LAUNCH_LOCK:         # a finalizer may call this from any thread
            standing, self._standing = self._standing, None
            policy.release_worker(self)
            if standing is not None and standing[3] == os.getpid():
                self.box.host[JOB_QUIT] = 1
                standing[1].wait()
                if displaced:
                    self._displaced = time.perf_counter()

    def count_launch(self) -> None:
        """Count a launch of this mailbox: ``_run``, its launches in a row with no other
        mailbox's between (:meth:`mode`, :data:`STANDING_RUN`)."""
        global _last_mailbox
        if _last_mailbox is None or _last_mailbox() is not self:
            _last_mailbox, self._run = weakref.ref(self), 0
        self._run += 1

    def retire(self) -> None:
        """End the standing worker of a mailbox its owner replaces, and forget the owner."""
        self.stop()
        if self._finalizer is not None:
            self._finalizer.detach()

    def set_argument(self, kernel, index: int, value) -> None:
        """Set argument ``index`` of ``kernel`` and of its standing clone, ending a standing
        worker (it runs with the old one): cloning again after :meth:`arguments_changed`
        made the next launch ~0.4 ms slower."""
        self.stop()
        kernel.set_arg(index, value)
        clone = self._clones.get(kernel)
        if clone is not None:
            clone[0].set_arg(index, value)
        prologue = self._prologues.get(kernel)
        if prologue is not None:
            prologue.set_arg(index, value)

    def arguments_changed(self, kernel=None) -> None:
        """Before an owner sets an argument of its kernel again (or frees an array it
        reads): end the standing worker and drop the clones, which hold the old ones
        (only ``kernel``'s where given: a variant of the kernel bound again)."""
        self.stop()
        if kernel is None:
            self._clones.clear()
            self._prologues.clear()
        else:
            self._clones.pop(kernel, None)
            self._prologues.pop(kernel, None)

    def prologue_kernel(self, kernel):
        """``kernel``'s clone of role :data:`ROLE_PROLOGUE`, which runs the job's prologue
        in a plain launch of its own (share.h PLAIN_OPENCL): made at its first use, with
        ``kernel``'s arguments of then (:meth:`set_argument` sets them in both,
        :meth:`arguments_changed` drops it)."""
        clone = self._prologues.get(kernel)
        if clone is None:
            clone = self._prologues[kernel] = kernel.clone()
            clone.set_arg(clone.num_args - 1, np.int32(ROLE_PROLOGUE))
        return clone

    def keep_standing(self, kernel, mode: str) -> None:
        """Before a launch of ``kernel`` that uses PoCL's workers as ``mode`` says
        (:meth:`mode`): end this mailbox's standing worker unless it stands for ``kernel``
        and the launch is to be served by it (``"standing"``); one that has returned, or
        runs another kernel, is ended too."""
        if self._standing is not None and not (mode == "standing" and self.standing(kernel)):
            self.stop()

    def launched(self) -> None:
        """After a launch has waited for its job: record when (:meth:`mode`, frames posed
        in a loop)."""
        self._last = time.perf_counter()



#: the mailbox of the last launch (Jobs.mode: STANDING_RUN), weakly: its owner's arrays
#: (Jobs.keep) are not kept alive by it
_last_mailbox: "weakref.ref[Jobs] | None" = None
