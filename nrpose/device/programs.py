"""OpenCL programs: kernel sources as shipped (headers pasted) and their builds, once per
(context, kernel file, build options) for the life of the process, started ahead in a
background thread (:func:`prefetch`) with their kernels' compile for each device
(:func:`warm_up`; docs/device.md, "Cold start"). On PoCL, a program's binaries are kept in
the binding cache (:mod:`nrpose.bind.cache`) and later processes build it from them: PoCL's
own cache still runs the preprocessor over the source and its 1 MB of headers to find its
entry (~45 ms a program), a build from binaries takes ~3 ms."""
from __future__ import annotations

import concurrent.futures
import functools
import os
import re
import threading
from importlib import resources

import numpy as np

from ..errors import DeviceError
from .env import context, cpu_unknown_hint, host_cpu, plain_opencl, pocl_cpu_context, pyopencl, worker_device
from .policy import LAUNCH_LOCK, stop_standing

_INCLUDE = re.compile(r'\s*#include\s+"([\w.]+\.h)"')
_KERNEL = re.compile(r"__kernel\s+void\s+(\w+)\s*\(([^)]*)\)")
_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
#: bytes of the zeroed buffer every pointer argument of a warm-up launch gets
#: (:func:`warm_up`): more than any kernel reads of a header or mailbox
WARM_UP_BYTES = 4096


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


def program_options(options=()) -> tuple[str, ...]:
    """The build options of every nrpose program: ``options`` (strings), then
    ``-DPLAIN_OPENCL`` where the context's launches are plain OpenCL
    (:func:`nrpose.device.plain_opencl`, kernels/share.h)."""
    return tuple(options) + (("-DPLAIN_OPENCL",) if plain_opencl() else ())


#: builds started by :func:`prefetch`, by (context, name, options), until :func:`program` takes them
_PENDING: dict = {}
#: the (context, name, options) of the programs built
_BUILT: set = set()
_PENDING_LOCK = threading.Lock()
_BUILDER = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="nrpose-build")


def program(name: str, options: tuple[str, ...] = ()):
    """Build (once per context) and return the program for kernel file ``name``, with
    ``options`` (:func:`program_options`); a build :func:`prefetch` started is waited for."""
    key = (context()[0], name, program_options(options))
    with _PENDING_LOCK:
        started = _PENDING.pop(key, None)
    if started is not None:
        started.result()          # its DeviceError, if any, is raised here
    return _program(*key)


def prefetch(name: str, options: tuple[str, ...] = ()) -> None:
    """Start building the program :func:`program` will be asked for in a background thread,
    then compiling its kernels for each device there (:func:`warm_up`), so that both
    overlap the host work of a bind; pyopencl releases the GIL while PoCL compiles. For
    programs of kernels in share.h's protocol (:func:`warm_up` launches them). Nothing to do
    for a program built already (its kernels compiled at their first launch)."""
    key = (context()[0], name, program_options(options))
    with _PENDING_LOCK:
        if key not in _PENDING and key not in _BUILT:     # built: its kernels compiled at their first launch
            _PENDING[key] = _BUILDER.submit(_built_and_warm, *key)


def _built_and_warm(ctx, name: str, options: tuple[str, ...]):
    prg = _program(ctx, name, options)
    if not plain_opencl():      # plain launches take the implementation's local size: not known here
        warm_up(prg, kernel_source(name))
    return prg


def kernel_arguments(source: str) -> dict[str, tuple[bool, ...]]:
    """{kernel name: per argument, whether it is a pointer} of the ``__kernel void``
    functions declared in OpenCL ``source`` (#if-ed out ones too)."""
    return {m.group(1): tuple("*" in a for a in m.group(2).split(","))
            for m in _KERNEL.finditer(_COMMENT.sub(" ", source))}


def warm_up(prg, source: str) -> None:
    """Launch each kernel of the built program ``prg`` (built from ``source``) once on each
    device of the context, as :func:`nrpose.device.launch_shared` launches (local size 1),
    with an empty job: PoCL compiles a kernel's work-group function for each device at its
    first launch there (0.1-0.4 s each for nrpose's kernels), and this moves that compile
    from a deformer's first pose to the caller's thread. Only for kernels of share.h's
    protocol: every pointer argument is one zeroed buffer (a mailbox of zeros is a job with
    no blocks, whose header of zeros the kernel reads before it returns), every other
    argument an int 0. A standing worker is ended first (nothing else is enqueued on its
    device while it stands)."""
    cl = pyopencl()
    ctx = context()[0]
    zeros = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                      hostbuf=np.zeros(WARM_UP_BYTES, np.uint8))
    pointers = kernel_arguments(source)
    kernels = []
    for kernel in prg.all_kernels():
        for i, pointer in enumerate(pointers[kernel.function_name]):
            kernel.set_arg(i, zeros if pointer else np.int32(0))
        kernels.append(kernel)
    events = []
    for dev in sorted(ctx.devices, key=lambda d: d != worker_device()):
        q = cl.CommandQueue(ctx, dev)
        if dev == worker_device():
            with LAUNCH_LOCK:   # PoCL compiles for its worker device later, on the worker's thread
                stop_standing()
                events += [cl.enqueue_nd_range_kernel(q, k, (1,), (1,)) for k in kernels]
            q.flush()
        else:                   # the calling thread's device compiles inside the enqueue
            events += [cl.enqueue_nd_range_kernel(q, k, (1,), (1,)) for k in kernels]
    for e in events:
        e.wait()


@functools.lru_cache(maxsize=None)
def _program(ctx, name: str, options: tuple[str, ...]):
    source = kernel_source(name)
    parts = program_key_parts(ctx, source, options)
    if parts is None:
        prg = _source_build(ctx, name, source, options)
    else:
        from ..bind.cache import cache_dir, forget, lookup      # (numpy's, io's): when first built

        folder = cache_dir() / PROGRAM_CACHE_FOLDER
        binaries = lookup(parts, folder)
        prg = None if binaries is None else _binary_build(ctx, binaries, options)
        if prg is None:
            if binaries is not None:        # binaries PoCL refuses: replaced
                forget(parts, folder)
            prg = _source_build(ctx, name, source, options)
            # after the build's warm-up, beside the job: PoCL compiles each kernel's generic
            # work-group function for its binaries (0.13-0.21 s of CPU)
            _BUILDER.submit(_store_binaries, prg, parts, folder)
    _BUILT.add((ctx, name, options))
    return prg


def _store_binaries(prg, parts: dict, folder) -> None:
    from ..bind.cache import store

    binaries = program_binaries(prg)
    if binaries is not None:        # binaries only save time
        store(parts, {f"device{i}": np.frombuffer(b, np.uint8) for i, b in enumerate(binaries)}, folder, quiet=True)


#: clGetProgramInfo's parameters (CL/cl.h)
CL_PROGRAM_NUM_DEVICES, CL_PROGRAM_BINARY_SIZES, CL_PROGRAM_BINARIES = 0x1162, 0x1165, 0x1166


def program_binaries(prg) -> list[bytes] | None:
    """The binaries of the built program ``prg``, one per device, or None where the OpenCL
    implementation gives none. Asked through ctypes, which releases the GIL: PoCL compiles each
    kernel's generic work-group function into them (0.13-0.21 s), during which pyopencl's
    ``get_info`` would hold the GIL and stop the job's other threads."""
    import ctypes

    try:
        get = ctypes.CDLL(pyopencl()._cl.__file__).clGetProgramInfo    # its OpenCL loader's
    except (OSError, AttributeError):
        return None
    get.restype = ctypes.c_int32
    get.argtypes = (ctypes.c_void_p, ctypes.c_uint32, ctypes.c_size_t, ctypes.c_void_p, ctypes.c_void_p)
    handle, n = ctypes.c_void_p(prg.int_ptr), ctypes.c_uint32(0)
    if get(handle, CL_PROGRAM_NUM_DEVICES, ctypes.sizeof(n), ctypes.byref(n), None) != 0 or not n.value:
        return None
    sizes = (ctypes.c_size_t * n.value)()
    if get(handle, CL_PROGRAM_BINARY_SIZES, ctypes.sizeof(sizes), sizes, None) != 0 or not all(sizes):
        return None
    buffers = [ctypes.create_string_buffer(size) for size in sizes]
    pointers = (ctypes.c_char_p * n.value)(*[ctypes.cast(b, ctypes.c_char_p) for b in buffers])
    if get(handle, CL_PROGRAM_BINARIES, ctypes.sizeof(pointers), pointers, None) != 0:
        return None
    return [b.raw for b in buffers]


#: the binding cache's folder (:mod:`nrpose.bind.cache`) of program binaries
PROGRAM_CACHE_FOLDER = "programs"
#: environment variables that change what pyopencl and PoCL compile: a process with one set
#: builds from source (its binaries are not stored)
BUILD_VARIABLES = ("PYOPENCL_BUILD_OPTIONS", "POCL_EXTRA_BUILD_FLAGS")


def program_key_parts(ctx, source: str, options: tuple[str, ...]) -> dict | None:
    """Key parts (:func:`nrpose.bind.cache.cached`) of the binaries of the program built from
    ``source`` with ``options`` for the devices of ``ctx``: the source, the options, pyopencl's
    version, each device's platform, device and driver names and versions, and the host CPU's
    model and instruction-set flags (PoCL compiles for the CPU it runs on, and a cache directory
    may be shared by machines whose CPUs carry one model name). None where binaries are not
    kept: a context not all of PoCL's CPU devices, or one of :data:`BUILD_VARIABLES` set."""
    if not pocl_cpu_context(ctx) or any(os.environ.get(v) for v in BUILD_VARIABLES):
        return None
    return {"kind": "opencl program", "source": source, "options": list(options),
            "pyopencl": pyopencl().VERSION_TEXT,
            "devices": [[d.platform.name, d.platform.version, d.name, d.version, d.driver_version]
                        for d in ctx.devices], "cpu": host_cpu()}


def _source_build(ctx, name: str, source: str, options: tuple[str, ...]):
    cl = pyopencl()
    try:
        return cl.Program(ctx, source).build(options=list(options))
    except cl.RuntimeError as exc:  # build failure: a bug of ours (but say where) or a CPU PoCL does not know
        raise DeviceError(cpu_unknown_hint(ctx, str(exc)) or f"building kernels/{name} failed: {exc}") from None


def _binary_build(ctx, binaries: dict, options: tuple[str, ...]):
    """The program of PoCL binaries (one per device of ``ctx``, as stored by :func:`_program`),
    or None where PoCL refuses them."""
    cl = pyopencl()
    try:
        data = [binaries[f"device{i}"].tobytes() for i in range(len(ctx.devices))]
        return cl.Program(ctx, ctx.devices, data).build(options=list(options))
    except (KeyError, cl.Error):
        return None


def build_source(source: str, options: tuple[str, ...] = ()):
    """The program built from OpenCL ``source`` (``#include`` lines pasted,
    :func:`with_headers`) with ``options`` (:func:`program_options`), not cached (kernel
    variants of diagnostics, benchmark kernels). pyopencl's errors pass through."""
    cl = pyopencl()
    return cl.Program(context()[0], with_headers(source)).build(options=list(program_options(options)))
