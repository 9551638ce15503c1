"""The OpenCL context nrpose launches on: PoCL's settings while it starts, the devices,
their queues and how a shared launch spreads over them.

Default: PoCL's CPU devices. ``PYOPENCL_CTX`` (pyopencl's own variable, e.g.
``PYOPENCL_CTX=0`` or ``0:0``) overrides the choice.
"""
from __future__ import annotations

import contextlib
import functools
import os
import platform

from ..errors import DeviceError
from .policy import standing_workers_possible

POCL = "Portable Computing Language"
INSTALL_HINT = ("install one with `pip install pyopencl pocl-binary-distribution` "
                "(PoCL, a CPU OpenCL platform) or select one with PYOPENCL_CTX")


@functools.lru_cache(maxsize=None)
def pyopencl():
    """The pyopencl module, imported once (an import statement per launch costs ~0.25 us)."""
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


#: environment variable: "1" makes the context PoCL's worker-thread device alone (see
#: :func:`pocl_settings`); the ``nrpose`` command sets it for itself and its workers
WHOLE_JOB_VARIABLE = "NRPOSE_WHOLE_JOB"


def whole_job() -> bool:
    """True when this process runs whole jobs (``NRPOSE_WHOLE_JOB=1``; the ``nrpose`` command
    sets it unless the user has): its context is then PoCL's worker-thread device alone, a
    worker per CPU, instead of the worker device plus the calling thread's ``basic`` device.
    PoCL builds every program once per device, so a cold start compiles half as much
    (Mannequin's cold LBS job ~1.1 s of CPU instead of ~1.7 s), while a clip's 16-frame
    launches lose nothing measurable to waking the workers. A process that poses frame by
    frame (the library's default) keeps the shared launch (:func:`nrpose.device.launch_shared`)."""
    return os.environ.get(WHOLE_JOB_VARIABLE) == "1"


def pocl_settings(cpus: int | None = None) -> dict[str, str]:
    """The PoCL variables nrpose sets while PoCL starts; a variable the user has set
    (to anything but the empty string) is left alone.

    ``cpus``: this process's share of the CPUs when several processes pose side by side
    (default: :func:`usable_cpus`, all of them). With a share, ``POCL_AFFINITY=0``:
    pinned, every process's worker i would run on CPU i.

    * ``POCL_DEVICES="pthread basic"`` (``"basic"`` on a single CPU): the worker-thread
      device and the device that runs kernels in the calling thread
      (:func:`nrpose.device.launch_shared`).
    * ``POCL_MAX_PTHREAD_COUNT`` = usable CPUs - 1, with that device list: the calling
      thread is the last worker. The workers are left unpinned: pinned, the calling thread
      sometimes shared a worker's CPU for a whole process (woken on it by the worker it
      waited for) while another CPU idled.
    * Where :func:`whole_job`: ``POCL_DEVICES="pthread"`` (``"basic"`` on a single
      CPU) with ``POCL_MAX_PTHREAD_COUNT`` = the CPUs.
    * ``POCL_AFFINITY=1`` only where PoCL's own workers run on every CPU (a device list of
      the user's, or whole-job launches) and where :func:`may_pin_workers`: unpinned,
      PoCL's broadcast may wake two workers onto one CPU, and a sub-millisecond kernel
      then runs on one thread.
    """
    out = {}
    share = cpus is not None
    cpus = max(1, cpus) if share else usable_cpus()
    if share and not os.environ.get("POCL_AFFINITY"):
        out["POCL_AFFINITY"] = "0"
    workers_everywhere, whole = bool(os.environ.get("POCL_DEVICES")), whole_job()
    if not workers_everywhere:
        if cpus < 2:
            out["POCL_DEVICES"] = "basic"
        elif whole:
            out["POCL_DEVICES"] = "pthread"
            workers_everywhere = True
        else:
            out["POCL_DEVICES"] = "pthread basic"
        if cpus >= 2 and not os.environ.get("POCL_MAX_PTHREAD_COUNT"):
            out["POCL_MAX_PTHREAD_COUNT"] = str(cpus if whole else cpus - 1)
    if workers_everywhere and not share and may_pin_workers():
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
    cl = pyopencl()
    with pocl_environment():        # PoCL reads it when it starts, here
        ctx = _new_context(cl)
    host = [d for d in ctx.devices if _is_basic(d)]
    return ctx, cl.CommandQueue(ctx, (host or ctx.devices)[0])


def plain_opencl() -> bool:
    """True where launches are plain OpenCL 1.2 (kernels/share.h PLAIN_OPENCL: programs
    built with ``-DPLAIN_OPENCL``, :func:`nrpose.device.launch_shared` launching the job's
    prologue and blocks in turn on one in-order queue): every context but one whose
    devices are all PoCL's CPU devices, on an x86 host
    (:func:`nrpose.device.standing_workers_possible`), the only place where the
    shared-launch protocol's ordering and concurrent work-groups are known to hold
    (docs/device.md, "Memory model")."""
    return _plain_opencl(context()[0])


@functools.lru_cache(maxsize=None)
def _plain_opencl(ctx) -> bool:
    return not (pocl_cpu_context(ctx) and standing_workers_possible())


def pocl_cpu_context(ctx) -> bool:
    """True when every device of the cl.Context ``ctx`` is one of PoCL's CPU devices."""
    cl = pyopencl()
    return all(POCL in d.platform.name and d.type & cl.device_type.CPU
               for d in ctx.devices)


def worker_queue():
    """Queue of PoCL's worker-thread device when the context also has the ``basic``
    device (:func:`nrpose.device.launch_shared` uses both), else None."""
    return _worker_queue(*context())


@functools.lru_cache(maxsize=None)
def _worker_queue(ctx, host_queue):
    if len(ctx.devices) < 2:
        return None
    return pyopencl().CommandQueue(ctx, [d for d in ctx.devices if d != host_queue.device][0])


def worker_device():
    """PoCL's worker-thread device, where a standing worker runs (None without one)."""
    wq = worker_queue()
    return None if wq is None else wq.device


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
    ordered = sorted(platforms, key=lambda p: POCL not in p.name)
    several_pocls = sum(POCL in p.name for p in ordered) > 1
    refused = []
    for plat in ordered:
        try:
            devs = plat.get_devices(device_type=cl.device_type.CPU)
        except cl.Error:
            devs = []
        if not devs:
            continue
        workers = [d for d in devs if d.name.startswith("pthread")]
        host = [d for d in devs if _is_basic(d)]
        if POCL in plat.name and workers and host:
            ctx = cl.Context(devices=[workers[0], host[0]])
        else:
            ctx = cl.Context(devices=[(workers or devs)[0]])
        # with a choice of PoCLs, one whose LLVM does not know this CPU is passed over
        if several_pocls and POCL in plat.name and (reason := remembered_refusal(ctx)):
            refused.append(reason)
            continue
        return ctx
    if refused:
        raise DeviceError(refused[0])
    raise DeviceError(f"no OpenCL CPU device found; {INSTALL_HINT}")


def compiler_refusal(ctx) -> str | None:
    """Why the OpenCL compiler of the cl.Context ``ctx`` cannot build a one-line kernel
    (:func:`cpu_unknown_hint`'s message or the build log), or None when it can."""
    cl = pyopencl()
    try:
        cl.Program(ctx, "__kernel void probe(__global int *x) { x[0] = 0; }").build()
    except cl.RuntimeError as exc:
        return cpu_unknown_hint(ctx, str(exc)) or f"the OpenCL compiler fails: {exc}"
    return None


def remembered_refusal(ctx) -> str | None:
    """:func:`compiler_refusal` of the cl.Context ``ctx``, probed once per platform, device
    and CPU and remembered in the binding cache (:mod:`nrpose.bind.cache`, folder
    ``opencl-compilers/``; ``refusal`` empty where the compiler builds): the probe costs
    20-40 ms a process with Debian's PoCL. An unwritable cache only means probing again."""
    import numpy as np

    from ..bind.cache import cache_dir, lookup, store

    dev = ctx.devices[0]
    parts = {"kind": "opencl compiler verdict", "cpu": host_cpu(),
             "device": [dev.platform.name, dev.platform.version, dev.name, dev.driver_version]}
    folder = cache_dir() / "opencl-compilers"
    known = lookup(parts, folder)
    if known is not None:
        return str(known["refusal"]) or None
    reason = compiler_refusal(ctx)
    store(parts, {"refusal": np.array(reason or "")}, folder, quiet=True)
    return reason


@functools.lru_cache(maxsize=None)
def host_cpu() -> str:
    """The first CPU's ``model name`` and ``flags`` lines of /proc/cpuinfo (Linux), else the
    platform module's machine and processor names."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            first = f.read(1 << 16).split("\n\n", 1)[0]
        lines = [line for line in first.splitlines() if line.split(":")[0].strip() in ("model name", "flags")]
        if lines:
            return "\n".join(lines)
    except OSError:
        pass
    return f"{platform.machine()} {platform.processor()}"


def cpu_unknown_hint(ctx, build_log: str) -> str | None:
    """The error message for a program build of the cl.Context ``ctx`` that failed with
    ``build_log`` because the platform's LLVM does not know this CPU (PyPI's PoCL 3.0,
    LLVM 14, on AMD Zen 5 and other processors newer than it), or None for other failures."""
    if "unknown target CPU" not in build_log:
        return None
    dev = ctx.devices[0]
    return (f"{dev.platform.version.split('  ')[0]} cannot compile for this CPU ({dev.name}): its LLVM "
            "does not know the processor; install a PoCL built with a newer LLVM (Debian, Ubuntu: "
            "`apt install pocl-opencl-icd`), which nrpose then prefers, or select another device with PYOPENCL_CTX")


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


def fine_grain_svm() -> bool:
    """True when the context's devices share fine-grained SVM buffers with the host (PoCL's do)."""
    cl = pyopencl()
    ctx, _ = context()
    try:
        return all(d.svm_capabilities & cl.device_svm_capabilities.FINE_GRAIN_BUFFER for d in ctx.devices)
    except (cl.Error, AttributeError):  # OpenCL 1.x device
        return False


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
