"""Timing launches: profiling queues, PoCL's event clock, and spans of launches."""
from __future__ import annotations

import functools
import time

from .env import context, pyopencl, worker_queue

#: the clock of PoCL's profiling timestamps on Linux (its pocl_gettimemono_ns), which
#: :meth:`nrpose.device.Jobs.publish` reads too, so that a launch's span can start at its
#: publication; None where Python has no such clock (then no span is given: published_span_s)
EVENT_CLOCK = getattr(time, "CLOCK_MONOTONIC_RAW", None)


def event_clock_ns() -> int:
    """Nanoseconds on :data:`EVENT_CLOCK` (0 where there is none)."""
    return time.clock_gettime_ns(EVENT_CLOCK) if EVENT_CLOCK is not None else 0


def timing_queue():
    """A profiling queue on the calling thread's device (:func:`nrpose.device.context`),
    made once: ``launch_shared(timed=True)`` runs the calling thread's share there."""
    return _timing_queue(*context())


@functools.lru_cache(maxsize=None)
def _timing_queue(ctx, host_queue):
    cl = pyopencl()
    return cl.CommandQueue(ctx, host_queue.device, properties=cl.command_queue_properties.PROFILING_ENABLE)


def profiling_queues() -> tuple:
    """``(worker queue or None, calling-thread queue)`` with profiling enabled, on the
    devices of the shared queues: :func:`nrpose.device.launch_shared`'s ``queues`` for
    timing launches with events (:func:`events_span_s`)."""
    cl = pyopencl()
    wq = worker_queue()
    return (None if wq is None else cl.CommandQueue(context()[0], wq.device,
                                                    properties=cl.command_queue_properties.PROFILING_ENABLE),
            timing_queue())


def published_span_s(jobs, event) -> float | None:
    """Seconds from ``jobs``' (a :class:`nrpose.device.Jobs`) last publication to the end
    of ``event``, the calling thread's kernel of a ``launch_shared(timed=True)`` (it
    returns once every block is done, whoever took it): the launch's kernel time as the
    devices ran it, a standing worker's share, which starts at the publication, included.
    None where the event's timestamps are not on :data:`EVENT_CLOCK` (its enqueue seen
    before the publication, or its end after now)."""
    now = event_clock_ns()
    if not 0 < jobs.published_ns <= event.profile.queued <= event.profile.end <= now:
        return None
    return (event.profile.end - jobs.published_ns) * 1e-9


def events_span_s(events) -> float:
    """Seconds from the first start to the last end of profiling events (a launch over
    several devices)."""
    return (max(e.profile.end for e in events) - min(e.profile.start for e in events)) * 1e-9
