"""Input files read with the caller's error, output paths checked early, atomic writes."""
from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from pathlib import Path
from typing import Iterator

from ..errors import FileFormatError, InputError, NrposeError

__all__ = ["read_input", "read_input_text", "check_writable", "atomic_path", "output_transaction", "on_commit"]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _umask()


def read_input(path, what: str, error: type[NrposeError] = FileFormatError) -> bytes:
    """The bytes of the input file ``path``, a ``what`` (e.g. "BVH file"); ``error`` naming
    the problem when it does not exist, is not a regular file (a directory, or a FIFO, whose
    read would wait for a writer) or cannot be read."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        raise error(f"{path}: no such file; check the path to the {what}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror}); check the path") from None
    if not stat.S_ISREG(mode):
        raise error(f"{path}: not a regular file; give a {what}")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror}); check its permissions") from None


def read_input_text(path, what: str, error: type[NrposeError] = FileFormatError) -> str:
    """:func:`read_input` decoded as UTF-8 text (a byte-order mark dropped)."""
    data = read_input(path, what, error)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: the {what} is not UTF-8 text ({exc.reason} at byte {exc.start}); "
                    f"re-save it as UTF-8") from None


def check_writable(path, directory_ok: bool = False) -> Path:
    """The directory of output ``path``; InputError if the name is empty, path is a directory
    (unless ``directory_ok``: an output directory whose parent receives the temporary files),
    its directory is missing, or a file cannot be created there (a probe file is made and removed).

    Lets a command refuse a bad output name before doing any work."""
    if not str(path):
        raise InputError("an output name is empty; give a file name to write")
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    if path.is_dir() and not directory_ok:
        raise InputError(f"{path}: is a directory; give a file name to write")
    if not directory.is_dir():
        raise InputError(f"{path}: directory {directory} does not exist; create it first")
    try:
        fd, probe = tempfile.mkstemp(prefix=".nrpose-", dir=directory)
    except OSError as exc:
        raise InputError(f"{path}: cannot write in {directory} ({exc.strerror}); "
                         f"choose a writable directory") from None
    os.close(fd)
    os.unlink(probe)
    return directory


#: the open output transaction's (commit, abort) actions, or None outside one
_pending: list[tuple] | None = None


@contextlib.contextmanager
def output_transaction() -> Iterator[None]:
    """Outputs written inside the block (through :func:`atomic_path` or :func:`on_commit`) are
    put in place together when it ends normally, and all removed when it raises: a command
    that fails leaves none of its outputs behind."""
    global _pending
    outer, _pending = _pending, []
    actions = _pending
    try:
        yield
    except BaseException:
        _pending = outer
        for _, abort in reversed(actions):
            with contextlib.suppress(OSError):
                abort()
        raise
    _pending = outer
    for k, (commit, _) in enumerate(actions):
        try:
            commit()
        except BaseException:       # the outputs not yet put in place are removed, not left as temporaries
            for _, abort in reversed(actions[k:]):
                with contextlib.suppress(OSError):
                    abort()
            raise


def on_commit(commit, abort) -> None:
    """Run ``commit()`` when the open :func:`output_transaction` ends normally (``abort()``
    when it raises); outside a transaction, ``commit()`` now."""
    if _pending is None:
        commit()
    else:
        _pending.append((commit, abort))


@contextlib.contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same directory, same extension).

    Write the file there; when the ``with`` block ends normally the temporary
    file is flushed to disk and renamed over ``path`` (``os.replace``, atomic
    on one filesystem; inside an :func:`output_transaction`, when it ends) with
    the permissions a new file would get (umask). If
    the block raises, the temporary file is removed, ``path`` is left as it
    was, and the exception propagates. Usable by any writer that takes a file
    name (numpy ``.npz``, glTF, JSON, matplotlib PNG...)::

        with atomic_path("out.npz") as tmp:
            np.savez(tmp, a=a)

    Raises InputError when the directory does not exist or is not writable.
    """
    path = Path(path)
    directory = check_writable(path)
    # suffix: the full extension, so writers that infer the format from it work
    suffix = "".join(path.suffixes[-2:]) if path.name.endswith(".tar.gz") else path.suffix
    try:
        # a short name: any name legal for `path` (up to 255 bytes) leaves room for it
        fd, tmp_name = tempfile.mkstemp(prefix=".nrpose-", suffix=f".tmp{suffix}", dir=directory)
    except OSError as exc:
        raise InputError(f"{path}: cannot write in {directory} ({exc.strerror}); "
                         f"choose a writable directory") from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if not tmp.exists():
            raise InputError(f"{path}: the writer produced no file; nothing was written")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        on_commit(lambda: os.replace(tmp, path), tmp.unlink)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
