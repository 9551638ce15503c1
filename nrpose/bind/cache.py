"""On-disk cache of binding results (distance matrices, weights, character binds) and of
other results that are pure functions of their inputs (OpenCL program binaries).

A binding is a pure function of its inputs, so its arrays are stored in
``<cache dir>/<key>.npz`` where ``key`` is a sha256 over the *content* of the
inputs: every entry of ``key_parts`` in sorted-name order, arrays by dtype,
shape and C-order bytes, everything else as sorted JSON, plus
:data:`FORMAT_VERSION` (bump it when a binding's meaning changes and old
files become unusable). The same data in another dtype (float32 vs float64
vertices) is a different key on purpose.

* Location: ``$NRPOSE_CACHE_DIR`` if set, else ``~/.cache/nrpose``.
* Writes are atomic: a temporary file in the same directory, fsync, then
  ``os.replace``; a reader never sees half a file.
* A file that cannot be read, lacks the stored key or version, or holds a
  different key is deleted and rebuilt: it is never trusted.
* A cache directory that cannot be written is not an error: the result is
  computed and returned, uncached (with a warning).

API: ``cached(key_parts, compute) -> dict[str, np.ndarray]`` (and
:func:`cached_status`, which also says ``"hit"``, ``"miss"`` or
``"rebuilt"``); :func:`lookup` and :func:`store` read and write one entry,
:func:`forget` deletes an entry its user cannot use.
"""
from __future__ import annotations

import functools
import hashlib
import importlib.util
import json
import os
import tempfile
import warnings
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from ..errors import InputError
from ..io.npz import read_npz, write_npz

__all__ = ["FORMAT_VERSION", "cache_dir", "cache_key", "cache_path", "cached", "cached_status", "forget",
           "lookup", "store", "binding_key_parts", "code_version"]

FORMAT_VERSION = 3  # 3: surface distances skip the visibility test past its work budget (2: weld)
_META = "__nrpose_cache_key__"


def cache_dir() -> Path:
    """``$NRPOSE_CACHE_DIR`` or ``~/.cache/nrpose`` (not created here)."""
    env = os.environ.get("NRPOSE_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "nrpose"


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, (set, frozenset)):
        return sorted(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot hash a {type(o).__name__} in cache key options")


def cache_key(key_parts: Mapping[str, object]) -> str:
    """sha256 hex digest over the content of ``key_parts`` (see module doc)."""
    if not isinstance(key_parts, Mapping):
        raise InputError(f"key_parts must be a dict, got {type(key_parts).__name__}")
    h = hashlib.sha256()
    h.update(f"nrpose-bindcache v{FORMAT_VERSION}\0".encode())
    for name in sorted(key_parts):
        if not isinstance(name, str):
            raise InputError(f"key_parts names must be strings, got {name!r}")
        value = key_parts[name]
        h.update(b"\0name\0" + name.encode())
        if isinstance(value, np.ndarray) or (isinstance(value, (list, tuple)) and value
                                             and isinstance(value[0], np.ndarray)):
            arr = np.ascontiguousarray(np.asarray(value))
            if arr.dtype == object:
                raise InputError(f"key part {name!r}: object arrays cannot be hashed")
            h.update(f"\0array\0{arr.dtype.str}\0{arr.shape}\0".encode())
            h.update(arr.tobytes())
        elif isinstance(value, (bytes, bytearray)):
            h.update(b"\0bytes\0" + bytes(value))
        else:
            try:
                text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=_json_default,
                                  allow_nan=True)
            except (TypeError, ValueError) as exc:
                raise InputError(f"key part {name!r} cannot be hashed: {exc}") from None
            h.update(b"\0json\0" + text.encode())
    return h.hexdigest()


@functools.lru_cache(maxsize=None)
def code_version(modules: tuple[str, ...]) -> str:
    """sha256 hex digest over the source files of ``modules`` (imported module names): a key
    part that makes a cached result stale when the code that computed it changes."""
    h = hashlib.sha256()
    for name in modules:
        # the file, found without running the module: a job does not import code it does not run
        h.update(name.encode() + b"\0" + Path(importlib.util.find_spec(name).origin).read_bytes() + b"\0")
    return h.hexdigest()


def cache_path(key_parts: Mapping[str, object], directory: str | os.PathLike | None = None) -> Path:
    return Path(directory if directory is not None else cache_dir()) / f"{cache_key(key_parts)}.npz"


def binding_key_parts(vertices, faces, point_handles, segment_handles, options: Mapping | None = None,
                      kind: str = "binding") -> dict:
    """The usual key parts of a binding (arrays as float64 / int64, options dict)."""
    def arr(a, dtype, shape_tail):
        if a is None:
            return np.zeros((0,) + shape_tail, dtype)
        return np.ascontiguousarray(np.asarray(a, dtype=dtype).reshape((-1,) + shape_tail))
    return {
        "kind": kind,
        "vertices": arr(vertices, np.float64, (3,)),
        "faces": arr(faces, np.int64, (3,)),
        "point_handles": arr(point_handles, np.float64, (3,)),
        "segment_handles": arr(segment_handles, np.float64, (2, 3)),
        "options": dict(options or {}),
    }


def _load(path: Path, key: str) -> dict[str, np.ndarray] | None:
    """Arrays of a valid cache file, or None (and the file deleted) if not."""
    try:
        arrays = read_npz(path)
        meta = arrays.pop(_META, None)
        if meta is None or str(meta[()]) != f"{FORMAT_VERSION}:{key}":
            raise ValueError("key or version mismatch")
        return arrays
    except Exception:  # corrupt, truncated, foreign: never trusted
        try:
            path.unlink()
        except OSError:
            pass
        return None


def _store(path: Path, key: str, arrays: Mapping[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem[:16]}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write_npz(f, {_META: np.array(f"{FORMAT_VERSION}:{key}"), **arrays})
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _check_result(result) -> dict[str, np.ndarray]:
    if not isinstance(result, Mapping):
        raise InputError(f"compute() must return a dict of arrays, got {type(result).__name__}")
    out = {}
    for name, value in result.items():
        if not isinstance(name, str) or not name.isidentifier() or name == _META:
            raise InputError(f"result names must be identifiers (not {_META}), got {name!r}")
        arr = np.asarray(value)
        if arr.dtype == object:
            raise InputError(f"result {name!r} is not a numeric/string array")
        out[name] = arr
    return out


def cached_status(key_parts: Mapping[str, object], compute: Callable[[], Mapping[str, np.ndarray]],
                  directory: str | os.PathLike | None = None) -> tuple[dict[str, np.ndarray], str]:
    """Like :func:`cached`, also returning ``"hit"``, ``"miss"`` or ``"rebuilt"``
    (a file existed but was unreadable or did not match)."""
    path = cache_path(key_parts, directory)     # the key hashed once (it may hold large arrays)
    existed = path.exists()
    arrays = _load(path, path.stem) if existed else None
    if arrays is not None:
        return arrays, "hit"
    result = _check_result(compute())
    _write(path, result, quiet=False)
    return result, ("rebuilt" if existed else "miss")


def lookup(key_parts: Mapping[str, object], directory: str | os.PathLike | None = None) -> dict[str, np.ndarray] | None:
    """The arrays stored for ``key_parts``, or None (a file that cannot be used is deleted)."""
    path = cache_path(key_parts, directory)
    return _load(path, path.stem) if path.exists() else None


def store(key_parts: Mapping[str, object], arrays: Mapping[str, np.ndarray],
          directory: str | os.PathLike | None = None, *, quiet: bool = False) -> None:
    """Store ``arrays`` (name → array) for ``key_parts``, atomically; a file that cannot be
    written warns (RuntimeWarning), unless ``quiet`` (results that only save time)."""
    _write(cache_path(key_parts, directory), _check_result(arrays), quiet)


def _write(path: Path, arrays: dict[str, np.ndarray], quiet: bool) -> None:
    try:
        _store(path, path.stem, arrays)
    except OSError as exc:
        if not quiet:
            warnings.warn(f"binding cache not written ({path.parent}): {exc}", RuntimeWarning, stacklevel=3)


def cached(key_parts: Mapping[str, object], compute: Callable[[], Mapping[str, np.ndarray]],
           directory: str | os.PathLike | None = None) -> dict[str, np.ndarray]:
    """Return the arrays stored for ``key_parts``, computing and storing them
    (``compute()`` → dict name → array) on a miss or an unusable file; a file that cannot be
    written warns (RuntimeWarning)."""
    return cached_status(key_parts, compute, directory)[0]


def forget(key_parts: Mapping[str, object], directory: str | os.PathLike | None = None) -> None:
    """Delete the file stored for ``key_parts`` (a result its user found unusable), if any and
    if the directory lets it."""
    try:
        cache_path(key_parts, directory).unlink(missing_ok=True)
    except OSError:
        pass
