"""OpenCL device selection, program cache and shared launches.

Default: PoCL's CPU devices. ``PYOPENCL_CTX`` (pyopencl's own variable, e.g.
``PYOPENCL_CTX=0`` or ``0:0``) overrides the choice. Programs are built once
per (context, kernel file, build options) and kept for the life of the process;
callers keep their ``cl.Kernel`` objects and buffers alive.

How a launch uses the CPUs (see :func:`pocl_settings`): unless the
environment says otherwise, PoCL starts two devices, ``pthread`` with one
worker thread per CPU but one and ``basic``, which runs a kernel in the thread
that waits for it. The pose kernels are enqueued on both at once
(:func:`launch_shared`): the workers and the calling thread take blocks of
points of the job published in a mailbox (:class:`Jobs`, kernels/share.h)
until none are left, so the calling thread computes instead of sleeping until
a worker wakes it, and a worker that wakes late finds less to do. Measured on
the 2-core VM: an empty kernel's enqueue + wait takes 0.04-0.07 ms on the
pthread device and 2.6 us on the basic device; waking the worker costs the
calling thread 13-19 us and the worker starts 20-40 us later. So the worker
*stands*: after a job it polls the mailbox for the next one for
:func:`standby_s` (1 ms unless ``NRPOSE_STANDBY_US`` or :func:`set_standby_s`
says otherwise), and
frames posed in a loop cost no wake-up at all (as OpenMP runtimes spin
before they sleep); a launch too small to pay for a wake-up, not following
another within that time, runs on the calling thread alone
(:func:`time_alone`, :data:`SHARE_MIN_S`). The price is up to standby_s of
one CPU spent polling after the last pose: set ``NRPOSE_STANDBY_US=0`` where
processes outnumber CPUs.
"""
from __future__ import annotations

import atexit
import contextlib
import functools
import operator
import os
import re
import sys
import threading
import time
import weakref
from importlib import resources

import numpy as np

from .errors import DeviceError, InputError

_INCLUDE = re.compile(r'\s*#include\s+"([\w.]+\.h)"')

INSTALL_HINT = ("install one with `pip install pyopencl pocl-binary-distribution` "
                "(PoCL, a CPU OpenCL platform) or select one with PYOPENCL_CTX")

@functools.lru_cache(maxsize=None)
def _cl():
    """The pyopencl module, imported once (an import statement in every launch had cost
    ~0.25 us: 340-370 ns a call against 100-160 ns cached, in one process)."""
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - dependency is declared
        raise DeviceError(f"pyopencl is not importable ({exc}); {INSTALL_HINT}") from None
    return cl


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity set where the OS tells, else all)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):   # not Linux
        return os.cpu_count() or 1


def may_pin_workers() -> bool:
    """True when nrpose should ask PoCL to pin its worker threads: ``POCL_AFFINITY``
    is not set by the user, and this process may run on every CPU (PoCL pins worker
    i to CPU i, which may be outside a restricted set)."""
    if os.environ.get("POCL_AFFINITY"):     # empty counts as unset, as PYOPENCL_CTX's does
        return False
    try:
        allowed = os.sched_getaffinity(0)
    except (AttributeError, OSError):   # not Linux
        return False
    return allowed == set(range(os.cpu_count() or 0))


def pocl_settings() -> dict[str, str]:
    """The PoCL variables nrpose sets while PoCL starts; a variable the user has set
    (to anything but the empty string) is left alone.

    * ``POCL_DEVICES="pthread basic"`` (``"basic"`` on a single CPU): the worker-thread
      device and the device that runs kernels in the calling thread (:func:`launch_shared`).
    * ``POCL_MAX_PTHREAD_COUNT`` = usable CPUs - 1, with that device list: the calling
      thread is the last worker. The workers are left unpinned: pinned, the calling thread
      sometimes shared a worker's CPU for a whole process (woken on it by the worker it
      waited for) while the other CPU idled; 24 alternated processes on the 2-core VM,
      Table-1 dragon/bunny/armadillo segments and dragon points, medians 0.208 / 0.194 /
      0.206 / 0.618 ms unpinned vs 0.218 / 0.200 / 0.199 / 0.651 ms pinned, and the pinned
      worst process 0.32 ms against 0.25 ms.
    * ``POCL_AFFINITY=1`` only with a device list of the user's (PoCL's own workers on
      every CPU) and where :func:`may_pin_workers`: unpinned, PoCL's broadcast woke two
      workers onto one CPU and a sub-millisecond kernel ran on one thread (bench/README.md).
    """
    out = {}
    if not os.environ.get("POCL_DEVICES"):
        cpus = usable_cpus()
        out["POCL_DEVICES"] = "pthread basic" if cpus >= 2 else "basic"
        if cpus >= 2 and not os.environ.get("POCL_MAX_PTHREAD_COUNT"):
            out["POCL_MAX_PTHREAD_COUNT"] = str(cpus - 1)
    elif may_pin_workers():
        out["POCL_AFFINITY"] = "1"
    return out


@contextlib.contextmanager
def pocl_environment():
    """Inside the block (while PoCL starts) the environment holds :func:`pocl_settings`;
    after it, each variable is as it was, so that child processes, perhaps restricted to
    fewer CPUs, decide for themselves. Yields the settings made."""
    settings = pocl_settings()
    before = {k: os.environ.get(k) for k in settings}
    os.environ.update(settings)
    try:
        yield settings
    finally:
        for k, v in before.items():
            if v is None:
                del os.environ[k]
            else:                   # the empty value that counted as unset
                os.environ[k] = v


@functools.lru_cache(maxsize=None)
def context():
    """Return the shared ``(cl.Context, cl.CommandQueue)`` pair. The queue is the
    calling thread's: PoCL's ``basic`` device where the context has it (kernels run
    inside ``finish``), else the context's only device.

    Raises DeviceError with an installation hint when no platform exists.
    """
    cl = _cl()
    with pocl_environment():        # PoCL reads it when it starts, here
        ctx = _new_context(cl)
    host = [d for d in ctx.devices if _is_basic(d)]
    return ctx, cl.CommandQueue(ctx, (host or ctx.devices)[0])


def worker_queue():
    """Queue of PoCL's worker-thread device when the context also has the ``basic``
    device (:func:`launch_shared` uses both), else None."""
    return _worker_queue(*context())


@functools.lru_cache(maxsize=None)
def _worker_queue(ctx, host_queue):
    if len(ctx.devices) < 2:
        return None
    return _cl().CommandQueue(ctx, [d for d in ctx.devices if d != host_queue.device][0])


def _is_basic(dev) -> bool:
    return dev.name.startswith("basic")


def _new_context(cl):
    """The cl.Context of PYOPENCL_CTX's choice; else PoCL's pthread and basic devices
    together, when it offers both; else the first PoCL (or other) CPU device."""
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    if not platforms:
        raise DeviceError(f"no OpenCL platform found; {INSTALL_HINT}")
    if os.environ.get("PYOPENCL_CTX"):
        try:
            return cl.create_some_context(interactive=False)
        except (cl.Error, RuntimeError, ValueError, IndexError) as exc:
            raise DeviceError(f"PYOPENCL_CTX={os.environ['PYOPENCL_CTX']!r} selects no usable "
                              f"device ({exc}); unset it to use PoCL") from None
    ordered = sorted(platforms, key=lambda p: "Portable Computing Language" not in p.name)
    for plat in ordered:
        try:
            devs = plat.get_devices(device_type=cl.device_type.CPU)
        except cl.Error:
            devs = []
        if not devs:
            continue
        workers = [d for d in devs if d.name.startswith("pthread")]
        host = [d for d in devs if _is_basic(d)]
        if "Portable Computing Language" in plat.name and workers and host:
            return cl.Context(devices=[workers[0], host[0]])
        return cl.Context(devices=[(workers or devs)[0]])
    raise DeviceError(f"no OpenCL CPU device found; {INSTALL_HINT}")


def work_items(queues=None) -> tuple[tuple, ...]:
    """``((queue, work-items), ...)`` of a shared launch on ``queues`` (worker queue or
    None, calling-thread queue; default the shared ones): the worker device's queue
    with one work-item per worker thread, then the calling thread's queue with one; on
    a single device, its queue with 4 work-items per compute unit."""
    return _work_items(*(queues if queues is not None else (worker_queue(), context()[1])))


@functools.lru_cache(maxsize=16)
def _work_items(wq, q) -> tuple[tuple, ...]:
    if wq is None:
        return ((q, 4 * q.device.max_compute_units),)
    return ((wq, wq.device.max_compute_units), (q, 1))


#: below this time of a kernel on the calling thread alone, waking the workers costs more
#: than they save (2-core VM: a wake-up is 13-19 us of the calling thread's time and the
#: worker starts 20-40 us later). Measured on subsets of the dragon, pose kernel alone vs
#: shared (medians of 300 interleaved launches): 5 segments, 0.054 vs 0.063 ms at 9,000
#: points, 0.074 vs 0.070 at 13,000; 5 point handles, 0.092 vs 0.095 ms at 4,000 points,
#: 0.121 vs 0.110 at 6,000. At 60 us, the 6,006-point box's segment row (0.034-0.062 ms
#: alone, timed at bind) was shared in some processes and then took 0.08-0.18 ms, not 0.05.
SHARE_MIN_S = 90e-6


def worth_sharing(units: int, alone_s: float) -> bool:
    """True when a launch of ``units`` units (frames), each taking ``alone_s`` seconds on
    the calling thread alone (:func:`time_alone`), is worth waking the workers for."""
    return units * alone_s >= SHARE_MIN_S


def time_alone(run_alone, runs: int = 5) -> float:
    """Seconds that ``run_alone()`` (a kernel launched on the calling thread only, waited
    for) takes: the best of ``runs`` runs (the first ones after a bind run cold), stopping
    early once one is 10x :data:`SHARE_MIN_S` or longer. A launch of F such units is worth
    sharing with the workers when F times this reaches SHARE_MIN_S."""
    best = float("inf")
    for _ in range(runs):
        t = time.perf_counter()
        run_alone()
        best = min(best, time.perf_counter() - t)
        if best >= 10 * SHARE_MIN_S:     # shared in any case: spare the bind the other runs
            break
    return best


#: how long a standing worker waits for the next job after serving one (seconds;
#: ``NRPOSE_STANDBY_US`` overrides it, 0 turns standing workers off): posing in a loop
#: then costs no wake-up of PoCL's worker thread, for at most this much of one CPU spent
#: polling after the last pose (as OpenMP runtimes spin before they sleep)
STANDBY_S = 1e-3
#: the longest standby NRPOSE_STANDBY_US may ask for (seconds)
STANDBY_MAX_S = 10.0
#: a launch of fewer blocks than this never stands a worker (it may still wake one, when
#: its frames take SHARE_MIN_S alone): the box's segment row cut to 500 points (2 blocks)
#: was 0.90-1.08x as fast with a standing worker as alone, 1,000 points (4 blocks)
#: 1.12-1.16x, 3,000 1.22x (poses in a loop, one process)
STANDING_MIN_BLOCKS = 4
#: after another mailbox's launch ended its standing worker, a mailbox does not stand one
#: for this long (seconds): two deformers posed in turn, each ending the other's worker,
#: took 2.2-2.5x the time of woken workers (dragon and bunny segments, one process), and
#: 1.1-1.6x when each waited for the other's worker to return
STANDING_YIELD_S = 0.1
#: ... unless it has launched this many times in a row since another mailbox last did: a
#: deformer posed in blocks of frames between another's (two deformers, 50 poses each in
#: turn) had never stood again, its launches all within STANDING_YIELD_S of the other's
#: (the box's segment rig posed alone at 0.041 ms a frame, the other's standing at 0.025)
STANDING_RUN = 8

# the job mailbox's fields and roles (kernels/share.h)
JOB_NEXT, JOB_QUIT, JOB_STANDING = 0, 3, 4
JOB_DESC = 8                        # (blocks, frames, ends, -) of jobs with even tags, then odd ones
JOB_DESCS = (JOB_DESC, JOB_DESC + 4)  # the descriptor of tag t: JOB_DESCS[t & 1] (JOB_BLOCKS_OF)
JOB_END_BITS = 10                   # a job taken from both ends: blocks taken from its start, then its end
JOB_ENDS_MAX_BLOCKS = 1000          # its two counts then never read as JOB_PROLOGUE or JOB_IN_PROLOGUE
#: owners take their jobs from both ends (Jobs.ends) when the data their kernel binds is at
#: most this: the two cores' L2 caches (512 KB each here) then hold it between them, each core
#: the half it works on in every launch. Paired rounds of standing launches in one process,
#: ends off / on, four processes: box points (588 KB bound) span 1.02-1.42x, the gain large in
#: processes where it runs slow (48-51 us off, 36-37 on) and small in fast ones (31-32 us);
#: box segments (329 KB) 1.06x; skinning's bench rig (745 KB) pose wall LBS 1.02-1.33x, DQS
#: 1.14-1.69x; dragon and bunny segments (2.0-2.2 MB) 0.97-0.98x
ENDS_MAX_BOUND_BYTES = 1 << 20
JOB_DONE = 16                       # on a cache line of its own
JOB_INTS = 32
JOB_TAG_SHIFT = 20
JOB_CLOSED = (1 << JOB_TAG_SHIFT) - 1      # block index past every job's last: none to take
JOB_PROLOGUE = JOB_CLOSED - 1              # of a published job whose prologue comes first
JOB_IN_PROLOGUE = JOB_CLOSED - 2           # of a job whose prologue a work-item runs
ROLE_CALLER = 0

def standing_workers_possible() -> bool:
    """Standing workers need the host's stores to the mailbox to reach a running kernel in
    program order (x86's total store order; :meth:`Jobs.publish` relies on it): elsewhere
    launches wake their workers each time."""
    import platform
    return platform.machine().lower() in ("x86_64", "amd64", "i386", "i686", "x86")


def standby_s() -> float:
    """The standing workers' wait for the next job, seconds: as :func:`set_standby_s` last
    set it, else ``NRPOSE_STANDBY_US`` (microseconds, 0 to :data:`STANDBY_MAX_S`) as read
    at the first call, else :data:`STANDBY_S`; 0 where :func:`standing_workers_possible`
    is False. DeviceError naming the variable when it is not such a number."""
    if _STANDBY[0] is None:
        set_standby_s(None)
    return _STANDBY[0]


def set_standby_s(seconds: float | None) -> float:
    """Set the standing workers' wait (seconds, 0 to :data:`STANDBY_MAX_S`; 0: none stand)
    or, with None, read it again from ``NRPOSE_STANDBY_US``; returns it. A worker standing
    with a longer wait is ended. Launches read the setting each time (it is kept here, not
    looked up in the environment per pose). InputError for a value that is not a number of
    seconds in range."""
    if seconds is None:
        text = os.environ.get("NRPOSE_STANDBY_US", "").strip()
        try:
            value = float(text) * 1e-6 if text else STANDBY_S
        except ValueError:
            value = float("nan")
        if not 0 <= value <= STANDBY_MAX_S:
            raise DeviceError(f"NRPOSE_STANDBY_US must be a number of microseconds from 0 (no "
                              f"standing workers) to {STANDBY_MAX_S * 1e6:.0f}, got {text!r}")
    else:
        ok = isinstance(seconds, (int, float, np.integer, np.floating)) and not isinstance(seconds, bool)
        value = float(seconds) if ok else float("nan")
        if not 0 <= value <= STANDBY_MAX_S:
            raise InputError(f"standby must be a number of seconds from 0 to {STANDBY_MAX_S}, "
                             f"got {seconds!r}")
    before = _STANDBY[0]
    _STANDBY[0] = value if standing_workers_possible() else 0.0
    if before is not None and _STANDBY[0] < before:
        stop_standing()             # polling with a longer budget than now allowed
    return _STANDBY[0]


_STANDBY: list = [None]             # the setting: seconds, or None until first read


_POLLS_PER_S: list = [None]         # a standing worker's idle polls per second, once measured


def calibrate_standby(kernel) -> None:
    """Measure, once per process, how many idle polls a standing worker makes per second
    (share.h next_job), with a clone of ``kernel`` (a deformer's, after its first launches,
    which built it for PoCL's worker device) standing on a mailbox of its own with no job
    to serve: launched with 1 poll and with enough for 1 ms or more (doubling), each timed
    to its end; the difference cancels the launch. Owners call it at bind, so that no pose
    pays it (3-5 ms). No-op without a worker device, shared memory or standing workers."""
    wq = worker_queue()
    if _POLLS_PER_S[0] is not None or wq is None or not fine_grain_svm() or standby_s() <= 0:
        return
    cl = _cl()
    stop_standing()
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
    (:meth:`time_kernel`, called by the owner at bind; until then launches are shared).
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
    :data:`ENDS_MAX_BOUND_BYTES`.
    Not thread-safe: launch a deformer's kernels from one thread at a time.
    """

    def __init__(self, svm: bool | None = None, owner=None, bound_bytes: int | None = None):
        self.box = HostArray(JOB_INTS, svm=svm, dtype=np.int32, atomics=True)
        self.box.host[:] = 0
        self.box.upload()
        self.alone_s = float("inf")
        self.keep: tuple = ()
        self.ends = bound_bytes is not None and bound_bytes <= ENDS_MAX_BOUND_BYTES
        self._tag = 0
        self._last = float("-inf")      # perf_counter() at the end of the last launch
        self._standing = None           # (kernel, event, arrays kept, pid) of a standing worker
        self._clones: dict = {}         # kernel -> its standing clone (role: the poll budget)
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

    def time_kernel(self, kernel, blocks: int, prologue: bool = False) -> None:
        """At bind, after the kernel's first launches: time one frame of ``kernel`` (``blocks``
        blocks, a ``prologue`` or not) on the calling thread alone (``alone_s``,
        :func:`time_alone`: small launches are not shared) and calibrate the standby once
        per process (:func:`calibrate_standby`), so that no pose pays either."""
        self.alone_s = time_alone(lambda: launch_shared(kernel, self, blocks, prologue=prologue,
                                                        workers=False))
        calibrate_standby(kernel)

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
        return "woken" if worth_sharing(frames, self.alone_s) else "alone"

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
        global _standing
        stop_standing()
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
        event = _cl().enqueue_nd_range_kernel(wq, clone[0], (n,), (1,))
        self._standing = (kernel, event, self.keep, os.getpid())
        wq.flush()
        _standing = self

    def stop(self, displaced: bool = False) -> None:
        """End this mailbox's standing worker (if any) and wait until it has returned (in a
        process forked since it stood, only forget it: its thread is not there).
        displaced: another mailbox's launch needs the worker device; this mailbox then does
        not stand a worker again for :data:`STANDING_YIELD_S`, unless it launches
        :data:`STANDING_RUN` times in a row (:meth:`mode`)."""
        global _standing
        with _LAUNCHES:         # a finalizer may call this from any thread
            standing, self._standing = self._standing, None
            if _standing is self:
                _standing = None
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

    def arguments_changed(self) -> None:
        """Before an owner sets an argument of its kernel again (or frees an array it
        reads): end the standing worker and drop the clones, which hold the old ones."""
        self.stop()
        self._clones.clear()


_standing: Jobs | None = None      # the mailbox whose standing worker holds the worker device
#: launches and the standing worker's state (``_standing``, a mailbox's worker), one thread at
#: a time: deformers posed from several threads launch in turn (each deformer itself is posed
#: from one thread at a time; its per-frame arrays are its own)
_LAUNCHES = threading.RLock()
#: the mailbox of the last launch (Jobs.mode: STANDING_RUN), weakly: its owner's arrays
#: (Jobs.keep) are not kept alive by it
_last_mailbox: "weakref.ref[Jobs] | None" = None


def stop_standing(displaced: bool = False) -> None:
    """End the standing worker, if one holds PoCL's worker device, and wait until it has
    returned: before anything else is enqueued there, and at exit. displaced: as
    :meth:`Jobs.stop`'s."""
    with _LAUNCHES:
        if _standing is not None:
            _standing.stop(displaced)


atexit.register(stop_standing)


def launch_shared(kernel, jobs: Jobs, blocks: int, frames: int = 1, prologue: bool = False,
                  queues=None, workers: bool | None = None, timed: bool = False) -> list:
    """Run ``kernel`` on every device of the context at once, and wait for it.

    kernel: a ``cl.Kernel`` whose work-items take blocks of the job published in
    ``jobs`` (``FOR_EACH_JOB`` / ``FOR_EACH_BLOCK``, kernels/share.h) until none are
    left; its arguments set, the mailbox and :data:`ROLE_CALLER` the last two.
    blocks, frames: the job's size; prologue: the job starts with the kernel's
    prologue (share.h), which the first work-item to arrive runs (a kernel that does not
    claim it would wait for ever: only kernels written for it). queues: ``(worker queue or None, calling-thread queue)`` to use instead of
    the shared ones (profiling queues; workers are woken, never standing, then).

    workers: True shares the blocks with PoCL's worker threads (a standing worker where
    :func:`standby_s` > 0, else woken ones), False runs the kernel on the calling
    thread's queue alone, None (default) decides (:meth:`Jobs.mode`). A standing worker
    (share.h) serves this job, then polls for the next for up to standby_s. The calling
    thread waits in the kernel until every block is done, whoever took it. Without
    shared memory (``jobs.box.svm`` False) only the calling thread's queue runs the
    kernel. Returns the kernel's events (a standing worker's is not among them).
    timed: the launch as without it (a standing worker serves it where one stands), but
    the calling thread's share runs on a profiling queue (:func:`timing_queue`): its
    event, the last returned, ends when every block is done (:func:`published_span_s`).
    """
    with _LAUNCHES:
        return _launch_shared(kernel, jobs, blocks, frames, prologue, queues, workers, timed)


def _launch_shared(kernel, jobs: Jobs, blocks: int, frames: int, prologue: bool, queues, workers,
                   timed: bool = False) -> list:
    """:func:`launch_shared`, its lock held."""
    jobs.count_launch()
    cl = _cl()
    if queues is None and workers is None and jobs.standing(kernel):
        # frames in a loop: this kernel's standing worker polls (Jobs.mode "standing", and
        # nothing to stop or stand): publish, run the calling thread's share, wait
        host_q = timing_queue() if timed else context()[1]
        jobs.publish(blocks, frames, prologue, timed)
        events = [cl.enqueue_nd_range_kernel(host_q, kernel, (1,), (1,))]
        host_q.finish()
        jobs._last = time.perf_counter()
        return events
    plan = work_items(queues)
    host_q = timing_queue() if timed and queues is None else plan[-1][0]
    worker_q = plan[0][0] if len(plan) > 1 and jobs.box.svm else None
    standby = standby_s() if queues is None and worker_q is not None else 0.0
    if workers is None:
        mode = jobs.mode(kernel, frames, blocks, standby)
    else:
        mode = ("standing" if standby > 0 else "woken") if workers else "alone"
    if worker_q is None or mode == "alone":
        worker_q, mode = None, "alone"
        if len(plan) > 1:
            plan = [(host_q, 1)]
    if jobs._standing is not None and not (mode == "standing" and jobs.standing(kernel)):
        jobs.stop()                     # of another kernel, returned, or not wanted here
    if _standing is not None and _standing is not jobs and any(q.device == _standing_device()
                                                                for q, _ in plan):
        stop_standing(displaced=True)   # another mailbox's: it holds these queues' device
    jobs.publish(blocks, frames, prologue, timed)
    if not jobs.box.svm and host_q != jobs.box._queue:
        jobs.box._queue.finish()        # its upload and the owner's, on the context's queue
    events = []
    if mode == "standing" and not jobs.standing(kernel):
        jobs.stand(kernel, worker_q, standby)
    elif mode == "woken":
        events.append(cl.enqueue_nd_range_kernel(worker_q, kernel, (plan[0][1],), (1,)))
        worker_q.flush()
    events.append(cl.enqueue_nd_range_kernel(host_q, kernel, (plan[-1][1],), (1,)))
    host_q.finish()                     # the calling thread's blocks, then (in the kernel) the others'
    for e in events[:-1]:               # woken workers: done by now (the kernel waited for them)
        e.wait()
    jobs._last = time.perf_counter()
    return events


def _standing_device():
    """The device a standing worker runs on: PoCL's worker-thread device."""
    wq = worker_queue()
    return None if wq is None else wq.device


def profiling_queues() -> tuple:
    """``(worker queue or None, calling-thread queue)`` with profiling enabled, on the
    devices of the shared queues: :func:`launch_shared`'s ``queues`` for timing launches
    with events (:func:`events_span_s`)."""
    cl = _cl()
    wq = worker_queue()
    return (None if wq is None else cl.CommandQueue(context()[0], wq.device,
                                                    properties=cl.command_queue_properties.PROFILING_ENABLE),
            timing_queue())


#: the clock of PoCL's profiling timestamps on Linux (its pocl_gettimemono_ns), which
#: :meth:`Jobs.publish` reads too, so that a launch's span can start at its publication;
#: None where Python has no such clock (then no span is given: published_span_s)
EVENT_CLOCK = getattr(time, "CLOCK_MONOTONIC_RAW", None)


def event_clock_ns() -> int:
    """Nanoseconds on :data:`EVENT_CLOCK` (0 where there is none)."""
    return time.clock_gettime_ns(EVENT_CLOCK) if EVENT_CLOCK is not None else 0


def timing_queue():
    """A profiling queue on the calling thread's device (:func:`context`), made once:
    ``launch_shared(timed=True)`` runs the calling thread's share there."""
    return _timing_queue(*context())


@functools.lru_cache(maxsize=None)
def _timing_queue(ctx, host_queue):
    cl = _cl()
    return cl.CommandQueue(ctx, host_queue.device, properties=cl.command_queue_properties.PROFILING_ENABLE)


def published_span_s(jobs: Jobs, event) -> float | None:
    """Seconds from ``jobs``' last publication to the end of ``event``, the calling
    thread's kernel of a ``launch_shared(timed=True)`` (it returns once every block is
    done, whoever took it): the launch's kernel time as the devices ran it, a standing
    worker's share, which starts at the publication, included. None where the event's
    timestamps are not on :data:`EVENT_CLOCK` (its enqueue seen before the publication,
    or its end after now)."""
    now = event_clock_ns()
    if not 0 < jobs.published_ns <= event.profile.queued <= event.profile.end <= now:
        return None
    return (event.profile.end - jobs.published_ns) * 1e-9


def events_span_s(events) -> float:
    """Seconds from the first start to the last end of profiling events (a launch over
    several devices)."""
    return (max(e.profile.end for e in events) - min(e.profile.start for e in events)) * 1e-9


def describe() -> dict:
    """Device facts for benchmark records: platform, the first device's name, version and
    compute units, and how a shared launch uses the devices (``launch``: one entry per
    device, its name and work-items; ``threads``: worker threads + the calling thread;
    ``summary``: that in words, for plot titles)."""
    ctx, _ = context()
    dev = ctx.devices[0]
    plan = work_items()
    return {"platform": dev.platform.name, "platform_version": dev.platform.version,
            "device": dev.name, "device_version": dev.version,
            "driver_version": dev.driver_version, "compute_units": dev.max_compute_units,
            "launch": [{"device": q.device.name, "work_items": n} for q, n in plan],
            "threads": (plan[0][1] + 1) if len(plan) > 1 else dev.max_compute_units,
            "summary": (f"{plan[0][0].device.name} x {plan[0][1]} + calling thread ({plan[1][0].device.name})"
                        if len(plan) > 1 else f"{dev.name} ({dev.max_compute_units} CU)")}


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>`` as shipped in the installed package, headers pasted
    (:func:`with_headers`)."""
    return with_headers(resources.files("nrpose.kernels").joinpath(name).read_text())


def with_headers(source: str) -> str:
    """OpenCL ``source`` with each ``#include "x.h"`` line replaced by the text of
    ``kernels/x.h`` (pasted here rather than left to the compiler so that PoCL's kernel
    cache, keyed on the source, sees changes to the header)."""
    folder = resources.files("nrpose.kernels")
    return "".join(folder.joinpath(m.group(1)).read_text() if (m := _INCLUDE.match(line)) else line
                   for line in source.splitlines(keepends=True))


def program(name: str, options: tuple[str, ...] = ()):
    """Build (once per context) and return the program for kernel file ``name``."""
    return _program(context()[0], name, tuple(options))


@functools.lru_cache(maxsize=None)
def _program(ctx, name: str, options: tuple[str, ...]):
    cl = _cl()
    try:
        return cl.Program(ctx, kernel_source(name)).build(options=list(options))
    except cl.RuntimeError as exc:  # build failure: a bug of ours, but say where
        raise DeviceError(f"building kernels/{name} failed: {exc}") from None


def fine_grain_svm() -> bool:
    """True when the context's devices share fine-grained SVM buffers with the host (PoCL's do)."""
    cl = _cl()
    ctx, _ = context()
    try:
        return all(d.svm_capabilities & cl.device_svm_capabilities.FINE_GRAIN_BUFFER for d in ctx.devices)
    except (cl.Error, AttributeError):  # OpenCL 1.x device
        return False


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
        cl = _cl()
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
        cl = _cl()
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
            _cl().enqueue_copy(self._queue, self.host, self.arg, is_blocking=True)


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
    Posing a frame then costs no copy of the (N, 3) result: 5-35 us on the Table-1
    rows, half the rows written by the other core. A held result keeps ``array`` alive
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
