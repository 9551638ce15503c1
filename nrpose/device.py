"""OpenCL device selection and program cache.

Default device: the first PoCL CPU device. ``PYOPENCL_CTX`` (pyopencl's own
variable, e.g. ``PYOPENCL_CTX=0`` or ``0:0``) overrides the choice. Programs are
built once per (context, kernel file, build options) and kept for the life of
the process; callers keep their ``cl.Kernel`` objects and buffers alive.

PoCL's worker threads are pinned one per CPU (``POCL_AFFINITY=1`` while PoCL
starts) unless the environment already says otherwise; see :func:`worker_pinning`.
"""
from __future__ import annotations

import contextlib
import functools
import os
import re
from importlib import resources

import numpy as np

from .errors import DeviceError

_INCLUDE = re.compile(r'\s*#include\s+"([\w.]+\.h)"')

INSTALL_HINT = ("install one with `pip install pyopencl pocl-binary-distribution` "
                "(PoCL, a CPU OpenCL platform) or select one with PYOPENCL_CTX")


def _cl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - dependency is declared
        raise DeviceError(f"pyopencl is not importable ({exc}); {INSTALL_HINT}") from None
    return cl


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


@contextlib.contextmanager
def worker_pinning():
    """While PoCL starts inside the block, ``POCL_AFFINITY=1`` (PoCL pins worker thread
    i to CPU i) where :func:`may_pin_workers`; the variable is removed after the block,
    so that child processes, perhaps restricted to fewer CPUs, decide for themselves.
    Yields whether it pinned.

    Why (measured on the 2-core VM, bench/README.md): unpinned, the kernel's
    broadcast wakes both workers onto the same idle CPU, and the second one
    waits there behind the first for the whole of a sub-millisecond kernel: a
    single Table-1 pose ran on one thread (its kernel took the same time with
    ``POCL_MAX_PTHREAD_COUNT=1``); pinned, both threads take part.
    """
    pin, before = may_pin_workers(), os.environ.get("POCL_AFFINITY")
    if pin:
        os.environ["POCL_AFFINITY"] = "1"
    try:
        yield pin
    finally:
        if pin and before is None:
            del os.environ["POCL_AFFINITY"]
        elif pin:                   # the empty value that counted as unset
            os.environ["POCL_AFFINITY"] = before


@functools.lru_cache(maxsize=None)
def context():
    """Return the shared ``(cl.Context, cl.CommandQueue)`` pair.

    Raises DeviceError with an installation hint when no platform exists.
    """
    cl = _cl()
    with worker_pinning():        # PoCL starts its worker threads in here
        ctx = _new_context(cl)
    return ctx, cl.CommandQueue(ctx)


def _new_context(cl):
    """The cl.Context of PYOPENCL_CTX's choice, else of the first PoCL (or other) CPU device."""
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    if not platforms:
        raise DeviceError(f"no OpenCL platform found; {INSTALL_HINT}")
    if os.environ.get("PYOPENCL_CTX"):
        try:
            ctx = cl.create_some_context(interactive=False)
        except (cl.Error, RuntimeError, ValueError, IndexError) as exc:
            raise DeviceError(f"PYOPENCL_CTX={os.environ['PYOPENCL_CTX']!r} selects no usable "
                              f"device ({exc}); unset it to use PoCL") from None
    else:
        ctx = None
        ordered = sorted(platforms, key=lambda p: "Portable Computing Language" not in p.name)
        for plat in ordered:
            try:
                devs = plat.get_devices(device_type=cl.device_type.CPU)
            except cl.Error:
                devs = []
            if devs:
                ctx = cl.Context(devices=[devs[0]])
                break
        if ctx is None:
            raise DeviceError(f"no OpenCL CPU device found; {INSTALL_HINT}")
    return ctx


def describe() -> dict:
    """Device facts for benchmark records: platform, device, version, compute units."""
    ctx, _ = context()
    dev = ctx.devices[0]
    return {"platform": dev.platform.name, "platform_version": dev.platform.version,
            "device": dev.name, "device_version": dev.version,
            "driver_version": dev.driver_version, "compute_units": dev.max_compute_units}


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>`` as shipped in the installed package, with each
    ``#include "x.h"`` line replaced by the text of ``kernels/x.h`` (pasted here
    rather than left to the compiler so that PoCL's kernel cache, keyed on the
    source, sees changes to the header)."""
    folder = resources.files("nrpose.kernels")
    lines = folder.joinpath(name).read_text().splitlines(keepends=True)
    return "".join(folder.joinpath(m.group(1)).read_text() if (m := _INCLUDE.match(line)) else line
                   for line in lines)


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
    """True when the device shares fine-grained SVM buffers with the host (PoCL CPU does)."""
    cl = _cl()
    ctx, _ = context()
    try:
        return bool(ctx.devices[0].svm_capabilities & cl.device_svm_capabilities.FINE_GRAIN_BUFFER)
    except (cl.Error, AttributeError):  # OpenCL 1.x device
        return False


class HostArray:
    """A float32 array that the host writes or reads and a kernel uses as an argument.

    On devices with fine-grained SVM the host array *is* the device memory:
    no copies, a pose is only kernel enqueues and a wait (:meth:`download`). Elsewhere a
    device buffer shadows it and :meth:`upload` / :meth:`download` copy.

    size: number of float32 elements; svm: force (True) or refuse (False)
    shared memory, default: whatever the device offers. ``host``: the
    (size,) numpy view; ``arg``: what to pass to ``Kernel.set_arg``.
    """

    def __init__(self, size: int, svm: bool | None = None):
        cl = _cl()
        ctx, self._queue = context()
        self.svm = fine_grain_svm() if svm is None else svm
        size = max(int(size), 1)
        if self.svm:
            flags = cl.svm_mem_flags.READ_WRITE | cl.svm_mem_flags.SVM_FINE_GRAIN_BUFFER
            self.host = cl.svm_empty(ctx, flags, (size,), np.float32)
            self.arg = cl.SVM(self.host)
        else:
            self.host = np.zeros(size, np.float32)
            self.arg = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, self.host.nbytes)

    def upload(self) -> None:
        """Make host writes visible to kernels enqueued next (no-op with SVM)."""
        if not self.svm:
            _cl().enqueue_copy(self._queue, self.arg, self.host, is_blocking=False)

    def download(self) -> None:
        """Wait for the queue and make kernel writes visible in ``host``.

        The host thread blocks (``finish``) rather than polling: PoCL's workers
        are pinned one per CPU (:func:`worker_pinning`), and a polling host thread
        takes a worker's CPU. Measured on the 2-core VM with pinned workers,
        polling for up to 0.3 ms before blocking was slower than blocking on
        every Table-1 row (box segments p25 0.14 vs 0.12 ms, box points median
        1.04-1.09 vs 0.80-0.94 ms); unpinned it had been 2x faster on the box.
        """
        if self.svm:
            self._queue.finish()
        else:
            _cl().enqueue_copy(self._queue, self.host, self.arg, is_blocking=True)
