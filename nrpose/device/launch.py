"""Shared launches: a kernel run on PoCL's worker threads and the calling thread at once.

Unless the environment says otherwise, PoCL starts two devices (:func:`nrpose.device.
pocl_settings`), ``pthread`` with one worker thread per CPU but one and ``basic``, which
runs a kernel in the thread that waits for it. The pose kernels are enqueued on both at
once: the workers and the calling thread take blocks of points of the job published in a
mailbox (:class:`nrpose.device.Jobs`, kernels/share.h) until none are left, so the calling
thread computes instead of sleeping until a worker wakes it, and a worker that wakes late
finds less to do. Whether the workers are woken, stand or are left alone is decided per
launch (:meth:`nrpose.device.Jobs.mode`, :mod:`nrpose.device.policy`).

That protocol holds on PoCL's CPU devices on x86 alone (kernels/share.h says why).
Elsewhere (:func:`nrpose.device.plain_opencl`) a launch is plain OpenCL 1.2
(:func:`launch_plain`): the job's prologue, then its blocks, as two launches on one
in-order queue.
"""
from __future__ import annotations

from . import policy
from .policy import LAUNCH_LOCK
from .env import context, pyopencl, work_items, worker_device
from .mailbox import Jobs
from .timing import timing_queue


def launch_shared(kernel, jobs: Jobs, blocks: int, frames: int = 1, prologue: bool = False,
                  queues=None, workers: bool | None = None, timed: bool = False) -> list:
    """Run ``kernel`` on every device of the context at once, and wait for it.

    kernel: a ``cl.Kernel`` whose work-items take blocks of the job published in
    ``jobs`` (``FOR_EACH_JOB`` / ``FOR_EACH_BLOCK``, kernels/share.h) until none are
    left; its arguments set, the mailbox and :data:`nrpose.device.ROLE_CALLER` the last
    two. blocks, frames: the job's size; prologue: the job starts with the kernel's
    prologue (share.h), which the first work-item to arrive runs (a kernel that does not
    claim it would wait for ever: only kernels written for it). queues: ``(worker queue
    or None, calling-thread queue)`` to use instead of the shared ones (profiling queues;
    workers are woken, never standing, then).

    workers: True shares the blocks with PoCL's worker threads (a standing worker where
    :func:`nrpose.device.standby_s` > 0, else woken ones), False runs the kernel on the
    calling thread's queue alone, None (default) decides (:meth:`Jobs.mode`). A standing
    worker (share.h) serves this job, then polls for the next for up to standby_s. The
    calling thread waits in the kernel until every block is done, whoever took it.
    Without shared memory (``jobs.box.svm`` False) only the calling thread's queue runs
    the kernel. Returns the kernel's events (a standing worker's is not among them).
    timed: the launch as without it (a standing worker serves it where one stands), but
    the calling thread's share runs on a profiling queue
    (:func:`nrpose.device.timing_queue`): its event, the last returned, ends when every
    block is done (:func:`nrpose.device.published_span_s`).
    Where ``jobs.plain``, the launch is :func:`launch_plain` (``workers`` unused).
    """
    with LAUNCH_LOCK:
        return _launch_shared(kernel, jobs, blocks, frames, prologue, queues, workers, timed)


def _launch_shared(kernel, jobs: Jobs, blocks: int, frames: int, prologue: bool, queues, workers,
                   timed: bool = False) -> list:
    """:func:`launch_shared`, its lock held."""
    if jobs.plain:
        return launch_plain(kernel, jobs, blocks, frames, prologue, queues, timed)
    jobs.count_launch()
    cl = pyopencl()
    if queues is None and workers is None and jobs.standing(kernel):
        # frames in a loop: this kernel's standing worker polls (Jobs.mode "standing", and
        # nothing to stop or stand): publish, run the calling thread's share, wait
        host_q = timing_queue() if timed else context()[1]
        jobs.publish(blocks, frames, prologue, timed)
        events = [cl.enqueue_nd_range_kernel(host_q, kernel, (1,), (1,))]
        host_q.finish()
        jobs.launched()
        return events
    plan = work_items(queues)
    host_q = timing_queue() if timed and queues is None else plan[-1][0]
    worker_q = plan[0][0] if len(plan) > 1 and jobs.box.svm else None
    standby = policy.standby_s() if queues is None and worker_q is not None else 0.0
    if workers is None:
        mode = jobs.mode(kernel, frames, blocks, standby)
    else:
        mode = ("standing" if standby > 0 else "woken") if workers else "alone"
    if worker_q is None or mode == "alone":
        worker_q, mode = None, "alone"
        if len(plan) > 1:
            plan = [(host_q, 1)]
    jobs.keep_standing(kernel, mode)
    holder = policy.standing_mailbox()
    if holder is not None and holder is not jobs and any(q.device == worker_device() for q, _ in plan):
        policy.stop_standing(displaced=True)   # another mailbox's: it holds these queues' device
    jobs.publish(blocks, frames, prologue, timed)
    jobs.box.settle(host_q)             # its upload and the owner's, on the context's queue
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
    jobs.launched()
    return events


def launch_plain(kernel, jobs: Jobs, blocks: int, frames: int = 1, prologue: bool = False,
                 queues=None, timed: bool = False) -> list:
    """:func:`launch_shared` as plain OpenCL 1.2 (kernels/share.h PLAIN_OPENCL; programs
    built with ``-DPLAIN_OPENCL``), and wait for it: the job published in ``jobs``, then
    on one in-order queue its prologue (where ``prologue``) as a launch of one work-item of
    ``kernel``'s clone of role :data:`nrpose.device.ROLE_PROLOGUE`
    (:meth:`Jobs.prologue_kernel`), then ``blocks`` work-items of ``kernel``, work-item i
    taking block i. The queue orders the prologue's writes before the blocks' reads, and
    the wait for it the blocks' writes before the host's reads. The queue: the worker
    device's where the context has one (its threads share the work-groups), else the
    calling thread's; with ``queues``, their first; ``timed``,
    :func:`nrpose.device.timing_queue` (its events end when the job is done:
    :func:`nrpose.device.published_span_s`). Returns the launches' events."""
    cl = pyopencl()
    if timed and queues is None:
        q = timing_queue()
    else:
        q = work_items(queues)[0][0]
    jobs.publish(blocks, frames, prologue, timed)
    jobs.box.settle(q)                  # its upload and the owner's, on the context's queue
    events = []
    if prologue:
        events.append(cl.enqueue_nd_range_kernel(q, jobs.prologue_kernel(kernel), (1,), None))
    if blocks:
        events.append(cl.enqueue_nd_range_kernel(q, kernel, (blocks,), None))
    q.finish()
    jobs.launched()
    return events
