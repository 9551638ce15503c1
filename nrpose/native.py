"""Calls into compiled libraries (libigl) with their own prints kept off the process's streams.

libigl reports problems by printing to stdout/stderr from C++ before (or instead of) raising;
the command line promises one line of error. :func:`quiet_native` points file descriptors 1
and 2 at a temporary file for the duration of a call and hands back what was printed.
"""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from typing import Iterator

__all__ = ["quiet_native"]


@contextlib.contextmanager
def quiet_native() -> Iterator[list[str]]:
    """Within the block, native writes to fd 1 and 2 go to a temporary file; the yielded list
    receives that text (one string) when the block ends, for an error message to quote."""
    captured: list[str] = []
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile() as sink:
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            yield captured
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            captured.append(sink.read(4096).decode("utf-8", "replace").strip())
