"""PoCL started, and its compiler's kernel library loaded, on a background thread at the start
of the ``nrpose`` program, while the main thread imports numpy and pyopencl
(docs/device.md, "Cold start").

A process's first PoCL build parses PoCL's 7 MB kernel library (~0.5 s on the 2-core VM,
whatever the program); that is most of a cold job's compile and, started by the job's own
build, it waits for the imports, the context and (NR-MLS) the character's load. Here a
one-line program is built as soon as the process starts, through the OpenCL loader that
pyopencl's extension module links (loaded with ctypes, without importing pyopencl or numpy),
so the job's own build finds the library loaded. Where PoCL's disk cache already holds the
one-line program, the thread costs its platform start-up and a cache lookup (~20-60 ms on
the other CPU).

Nothing here is needed for correctness: where the extension or PoCL cannot be found the
thread ends without effect, and :func:`nrpose.device.context` starts PoCL itself.
"""
from __future__ import annotations

import ctypes
import importlib.machinery
import importlib.util
import os
import threading
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Callable

#: the program built: it has to be compiled, and anything compiled loads the kernel library
SOURCE = b"kernel void nrpose_startup(global int *out) { out[0] = 0; }\n"
#: OpenCL constants (CL/cl.h)
CL_PLATFORM_NAME, CL_DEVICE_TYPE_CPU = 0x0902, 1 << 1
POCL_PLATFORM = b"Portable Computing Language"

#: set once the thread has started PoCL, or given up (never cleared: a process starts PoCL once)
_STARTED = threading.Event()
_STARTED.set()                  # until start_pocl() runs, nobody is starting PoCL here
_state = {"thread": None, "pocl": False}


def start_pocl(settings: Callable[[], AbstractContextManager]) -> bool:
    """Start PoCL and build a one-line program on a daemon thread, once per process. Call
    before numpy's import, with the environment PoCL should see (``NRPOSE_WHOLE_JOB``):
    PoCL starts inside ``settings()`` (:func:`nrpose.device.pocl_environment`, as the
    context would start it). Not started (False) when ``PYOPENCL_CTX`` chooses the platform, when pyopencl's extension
    module is not found, or when a thread was started already."""
    if _state["thread"] is not None or os.environ.get("PYOPENCL_CTX"):
        return False
    extension = _pyopencl_extension()
    if extension is None:
        return False
    # what pyopencl's import sets (the OpenCL loader of its wheels looks for its drivers there):
    # set first, so that PoCL starts with the environment it would have
    os.environ["PYOPENCL_HOME"] = str(extension.parent)
    _STARTED.clear()
    thread = threading.Thread(target=_run, args=(extension, settings), name="nrpose-pocl-startup", daemon=True)
    _state["thread"] = thread
    thread.start()
    return True


def pocl_started() -> bool:
    """Wait until the startup thread, if any, has started PoCL (or given up); True if PoCL
    was started there (its settings applied then)."""
    _STARTED.wait()
    return _state["pocl"]


def join() -> None:
    """Wait for the startup thread to end (a process exiting with PoCL's compiler running on
    another thread could crash in the compiler's static destructors)."""
    thread = _state["thread"]
    if thread is not None:
        thread.join()


def _pyopencl_extension() -> Path | None:
    """Path of pyopencl's compiled module ``_cl``, found without importing pyopencl; None
    where there is none."""
    try:
        spec = importlib.util.find_spec("pyopencl")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    folder = Path(os.path.abspath(next(iter(spec.submodule_search_locations))))
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        if (folder / f"_cl{suffix}").is_file():
            return folder / f"_cl{suffix}"
    return None


def _run(extension: Path, settings: Callable[[], AbstractContextManager]) -> None:
    try:
        cl = _opencl(extension)
        with settings():
            platforms = _platforms(cl)
        _state["pocl"] = True
        _STARTED.set()
        _build(cl, platforms)
    except (OSError, AttributeError, ValueError):   # no loader, no symbol: the context starts PoCL
        pass
    finally:
        _STARTED.set()


def _opencl(extension: Path) -> ctypes.CDLL:
    """The OpenCL API as pyopencl's extension links it: dlsym on the extension's handle
    searches its dependencies, the OpenCL loader among them (loaded from the extension's own
    search path, as the import of pyopencl loads it)."""
    cl = ctypes.CDLL(str(extension))
    handle, uint, size = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_size_t
    for name, restype, argtypes in (
            ("clGetPlatformIDs", ctypes.c_int32, (uint, handle, ctypes.POINTER(uint))),
            ("clGetPlatformInfo", ctypes.c_int32, (handle, uint, size, handle, handle)),
            ("clGetDeviceIDs", ctypes.c_int32, (handle, ctypes.c_uint64, uint, handle, ctypes.POINTER(uint))),
            ("clCreateContext", handle, (handle, uint, handle, handle, handle, ctypes.POINTER(ctypes.c_int32))),
            ("clCreateProgramWithSource", handle,
             (handle, uint, ctypes.POINTER(ctypes.c_char_p), handle, ctypes.POINTER(ctypes.c_int32))),
            ("clBuildProgram", ctypes.c_int32, (handle, uint, handle, ctypes.c_char_p, handle, handle)),
            ("clReleaseProgram", ctypes.c_int32, (handle,)),
            ("clReleaseContext", ctypes.c_int32, (handle,))):
        fn = getattr(cl, name)
        fn.restype, fn.argtypes = restype, argtypes
    return cl


def _platforms(cl) -> list[int]:
    """The platforms' handles (PoCL starts here)."""
    n = ctypes.c_uint32(0)
    if cl.clGetPlatformIDs(0, None, ctypes.byref(n)) != 0 or n.value == 0:
        return []
    ids = (ctypes.c_void_p * n.value)()
    if cl.clGetPlatformIDs(n.value, ids, None) != 0:
        return []
    return list(ids)


def _build(cl, platforms: list[int]) -> None:
    """Build :data:`SOURCE` for PoCL's CPU devices in a context of their own."""
    for platform in platforms:
        name = ctypes.create_string_buffer(256)
        if cl.clGetPlatformInfo(platform, CL_PLATFORM_NAME, 256, name, None) != 0 or POCL_PLATFORM not in name.value:
            continue
        count = ctypes.c_uint32(0)
        devices = (ctypes.c_void_p * 8)()
        if cl.clGetDeviceIDs(platform, CL_DEVICE_TYPE_CPU, 8, devices, ctypes.byref(count)) != 0 or not count.value:
            continue
        n = min(count.value, 8)
        err = ctypes.c_int32(0)
        ctx = cl.clCreateContext(None, n, devices, None, None, ctypes.byref(err))
        if not ctx or err.value != 0:
            continue
        source = ctypes.c_char_p(SOURCE)
        prg = cl.clCreateProgramWithSource(ctx, 1, ctypes.byref(source), None, ctypes.byref(err))
        if prg and err.value == 0:
            cl.clBuildProgram(prg, n, devices, b"", None, None)
            cl.clReleaseProgram(prg)
        cl.clReleaseContext(ctx)
        return
