"""Command line: ``nrpose deform | pose | info | weights | retarget | bake | demo | fit-skin``.

One module per command, each with ``add_parser(subparsers)`` and ``run(args)``.
Every user mistake (bad file, bad option, no OpenCL platform) ends with one
line on stderr and exit status 2; outputs are written to a temporary name
and renamed, so a failed run leaves no output behind. A command's ``run``
returns its exit status (None: 0); Ctrl-C ends a command with status 130.

Library errors name arguments as Python spells them (``weights='euclidean'``,
``skeleton=``, ``format_map()``); :func:`flag_text` rewrites them with the
flags of the command that ran (each command module's ``FLAGS``).
"""
from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import os
import re
import sys
import warnings

import numpy as np

from ..errors import NrposeError
from ..io.files import output_transaction

__all__ = ["main", "build_parser", "flag_text", "Parser", "UsageError"]

#: the commands, each a module of this package (imported when its parser is built)
COMMANDS = ("deform", "pose", "weights", "retarget", "bake", "info", "demo", "fit_skin")

# name='value' | name= (before a space, punctuation or the end) | name()
_ARGUMENT = re.compile(r"\b(\w+)(?:=(?:'([^']*)'|(?=[\s,;)]|$))|\(\))")


class UsageError(Exception):
    """A command line argparse refused (the message is already one line)."""


class Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, status 2 (argparse's default prints usage too)
        raise UsageError(f"{self.prog}: {message}")

    def parse_known_args(self, args=None, namespace=None):
        """argparse's, with empty values refused: an empty name is never a file, clip or choice."""
        namespace, extras = super().parse_known_args(args, namespace)
        for action in self._actions:
            value = getattr(namespace, action.dest, None)
            values = value if isinstance(value, list) else [value]
            if any(isinstance(v, str) and not v.strip() for v in values):
                name = "/".join(action.option_strings) or action.dest
                self.error(f"{name}: empty value; give a name")
        return namespace, extras


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command line parser; with ``only`` (a name in :data:`COMMANDS`) that command's
    alone, so that a run imports the modules of the command it runs and no other."""
    parser = Parser(prog="nrpose", description="Nearly rigid MLS deformation and skeletal posing on OpenCL.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for name in COMMANDS if only is None else (only,):
        importlib.import_module(f".{name}", __name__).add_parser(sub)
    return parser


def flag_text(message: str, flags: dict[str, str]) -> str:
    """``message`` with the library's argument names (``name='v'``, ``name=``, ``name()``)
    that ``flags`` knows replaced by the command's flags (``--flag v``, ``--flag``)."""
    def replace(m: re.Match) -> str:
        flag = flags.get(m.group(1))
        if flag is None:
            return m.group(0)
        return flag if m.group(2) is None else f"{flag} {m.group(2)}"
    return _ARGUMENT.sub(replace, message)


def command() -> int:
    """The ``nrpose`` program (console script, ``python -m nrpose``): :func:`main` in a process
    that runs one whole job, so its PoCL context is the worker device alone
    (``NRPOSE_WHOLE_JOB=1`` unless set: :func:`nrpose.device.env.whole_job`; its bake
    workers inherit it), its large blocks are returned when freed
    (:func:`map_large_blocks`) and its exit skips the interpreter's last garbage collections
    (:func:`skip_final_collections`)."""
    os.environ.setdefault("NRPOSE_WHOLE_JOB", "1")
    map_large_blocks()
    try:
        return main()
    finally:
        skip_final_collections()


def skip_final_collections() -> None:
    """Leave every object of a process about to exit out of the interpreter's garbage
    collections (``gc.freeze``): at exit those passes traverse every object of the ~370 modules a
    command imports (40-60 ms of a 400 ms job) to free memory the system takes back anyway.
    Exit handlers, thread joins and stream flushes still run; objects are still freed by their
    reference counts."""
    gc.disable()
    gc.freeze()


#: glibc's ``mallopt`` parameter M_MMAP_THRESHOLD, and the size set for it: a bind's arrays are
#: mapped, a frame's rows (190 KB on Mannequin) stay in the heap (at 128 KB, LBS jobs ran 7 % slower)
_M_MMAP_THRESHOLD, MMAP_THRESHOLD = -3, 1024 * 1024


def map_large_blocks() -> None:
    """Have glibc map every allocation of :data:`MMAP_THRESHOLD` bytes or more on its own, so
    it goes back to the system when freed. By default glibc raises that threshold to the largest
    block freed so far (up to 32 MB), after which a bind's temporary arrays come from the heap
    and stay resident: a cold NR-MLS job on Mannequin peaked ~60 MiB higher. Nothing to do
    where the C library is not glibc."""
    import ctypes     # imported by numpy already

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)


def main(argv=None) -> int:
    args, status = None, 0
    notes: list[str] = []
    try:
        argv = sys.argv[1:] if argv is None else list(argv)
        module = argv[0].replace("-", "_") if argv else None     # `fit-skin` is module fit_skin
        args = build_parser(module if module in COMMANDS else None).parse_args(argv)
        # the commands check their inputs and results for NaN and infinity themselves and say
        # so in one line; numpy's floating-point warnings on the way would add lines to stderr.
        # nrpose's own warnings (a binding cache not written...) show as one line each after a
        # run that succeeds; a failed run prints its error line only.
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.showwarning = lambda message, *rest, **kw: notes.append(warning_line(message))
            with output_transaction():
                try:
                    status = args.func(args) or 0
                    sys.stdout.flush()
                except BrokenPipeError:
                    # the reader of stdout has gone (`nrpose info X | head`): the outputs are
                    # complete, so they are kept; the command ends quietly as under SIGPIPE
                    quiet_stdout()
                    return EXIT_PIPE
    except UsageError as exc:
        return fail(str(exc))
    except NrposeError as exc:
        return fail(f"nrpose: error: {flag_text(str(exc), getattr(args, 'flags', {}))}")
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        return fail(f"nrpose: error: {where}{exc.strerror or exc}")
    except MemoryError:     # past the input bounds (a machine short of memory): one line, no output
        return fail("nrpose: error: out of memory: free memory or run fewer frames or a smaller "
                    "character per command (--max-frames, --max-output-values)")
    except KeyboardInterrupt:
        print("nrpose: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if notes:   # one line, as the contract promises (several warnings joined)
        print(" | ".join(dict.fromkeys(notes)), file=sys.stderr)
    return status


#: the exit status of a command whose stdout reader went away (128 + SIGPIPE, as a shell reports it)
EXIT_PIPE = 128 + 13
#: the exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it)
EXIT_INTERRUPTED = 128 + 2


def quiet_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush cannot fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def warning_line(message) -> str:
    """A warning as one line: ``nrpose: warning: MESSAGE``."""
    text = str(message).replace("\r", "\\r").replace("\n", "\\n")
    return f"nrpose: warning: {text}"


def fail(message: str) -> int:
    """The message on stderr as one line (a path may hold a newline), exit status 2."""
    print(message.replace("\r", "\\r").replace("\n", "\\n"), file=sys.stderr)
    return 2
