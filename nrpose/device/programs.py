"""OpenCL programs: kernel sources as shipped (headers pasted) and their builds, once per
(context, kernel file, build options) for the life of the process."""
from __future__ import annotations

import concurrent.futures
import functools
import re
import threading
from importlib import resources

from ..errors import DeviceError
from .env import context, plain_opencl, pyopencl

_INCLUDE = re.compile(r'\s*#include\s+"([\w.]+\.h)"')


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
    """Start building the program :func:`program` will be asked for, in a background thread,
    so that its compile (~1 s on PoCL without a cached binary: mostly a fixed cost per
    build) overlaps the host work of a bind; pyopencl releases the GIL while it builds."""
    key = (context()[0], name, program_options(options))
    with _PENDING_LOCK:
        if key not in _PENDING:
            _PENDING[key] = _BUILDER.submit(_program, *key)


@functools.lru_cache(maxsize=None)
def _program(ctx, name: str, options: tuple[str, ...]):
    cl = pyopencl()
    try:
        return cl.Program(ctx, kernel_source(name)).build(options=list(options))
    except cl.RuntimeError as exc:  # build failure: a bug of ours, but say where
        raise DeviceError(f"building kernels/{name} failed: {exc}") from None


def build_source(source: str, options: tuple[str, ...] = ()):
    """The program built from OpenCL ``source`` (``#include`` lines pasted,
    :func:`with_headers`) with ``options`` (:func:`program_options`), not cached (kernel
    variants of diagnostics, benchmark kernels). pyopencl's errors pass through."""
    cl = pyopencl()
    return cl.Program(context()[0], with_headers(source)).build(options=list(program_options(options)))
