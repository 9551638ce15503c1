"""When a launch shares its blocks with PoCL's worker threads, and how long a worker
stands after a job: the sharing threshold, the standby setting, and which mailbox's
standing worker holds the worker device (one at a time).

Waking PoCL's worker costs the calling thread tens of microseconds and the worker
starts later still. So the worker *stands*: after a job it polls the mailbox for the
next one for :func:`standby_s` (1 ms unless ``NRPOSE_STANDBY_US`` or
:func:`set_standby_s` says otherwise), and frames posed in a loop cost no wake-up (as
OpenMP runtimes spin before they sleep); a launch too small to pay for a wake-up, not
following another within that time, runs on the calling thread alone
(:func:`time_alone`, :data:`SHARE_MIN_S`). The price is up to standby_s of one CPU
spent polling after the last pose: set ``NRPOSE_STANDBY_US=0`` where processes
outnumber CPUs.
"""
from __future__ import annotations

import atexit
import os
import platform
import threading
import time

import numpy as np

from ..errors import DeviceError, InputError

#: below this time of a kernel on the calling thread alone, waking the workers costs more
#: than they save (a wake-up takes the calling thread's time and the worker starts late)
SHARE_MIN_S = 90e-6

#: how long a standing worker waits for the next job after serving one (seconds;
#: ``NRPOSE_STANDBY_US`` overrides it, 0 turns standing workers off)
STANDBY_S = 1e-3
#: the longest standby NRPOSE_STANDBY_US may ask for (seconds)
STANDBY_MAX_S = 10.0


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


def standing_workers_possible() -> bool:
    """Standing workers need the host's stores to the mailbox to reach a running kernel in
    program order (x86's total store order; :meth:`nrpose.device.Jobs.publish` relies on
    it): elsewhere launches wake their workers each time."""
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

#: launches and the standing worker's state (which mailbox's worker stands), one thread at
#: a time: deformers posed from several threads launch in turn (each deformer itself is
#: posed from one thread at a time; its per-frame arrays are its own)
LAUNCH_LOCK = threading.RLock()
_HOLDER: list = [None]              # the mailbox whose standing worker holds the worker device


def standing_mailbox():
    """The mailbox (:class:`nrpose.device.Jobs`) whose standing worker holds PoCL's worker
    device, or None."""
    return _HOLDER[0]


def hold_worker(jobs) -> None:
    """Record that ``jobs``' standing worker now holds the worker device (its caller holds
    :data:`LAUNCH_LOCK` and has ended any other)."""
    _HOLDER[0] = jobs


def release_worker(jobs) -> None:
    """Record that ``jobs``' standing worker, if it held the worker device, has ended."""
    if _HOLDER[0] is jobs:
        _HOLDER[0] = None


def stop_standing(displaced: bool = False) -> None:
    """End the standing worker, if one holds PoCL's worker device, and wait until it has
    returned: before anything else is enqueued there, and at exit. displaced: as
    :meth:`nrpose.device.Jobs.stop`'s."""
    with LAUNCH_LOCK:
        if _HOLDER[0] is not None:
            _HOLDER[0].stop(displaced)


atexit.register(stop_standing)
