"""Validation of array arguments given by users: vertices, handle coordinates, triangles.

Each check returns the array in the dtype the package computes with, or raises a typed
error (:mod:`nrpose.errors`) whose message names the argument, the problem and the fix.
"""
from __future__ import annotations

import numpy as np

from .errors import InputError


def _shape_text(tail: tuple[int, ...]) -> str:
    return "(N, " + ", ".join(map(str, tail)) + ")"


def real_rows(value, what: str, tail: tuple[int, ...] = (3,), error: type[InputError] = InputError,
              allow_empty: bool = False, fix: str = "give finite values") -> np.ndarray:
    """``value`` as a float64 array of shape (N, *tail) with every entry finite.

    value: anything numpy reads as real numbers (floats or integers; not bool, complex
    or text). what: the argument's name as the message should call it (e.g. "rest
    vertices"). error: the exception class raised. allow_empty: accept N = 0 (an empty
    input of any shape then becomes a (0, *tail) array). fix: the advice for non-finite rows.
    Returns (N, *tail) float64 (no copy when the input is already float64).
    """
    arr = _numeric(value, what, f"real numbers of shape {_shape_text(tail)}", error)
    if arr.dtype.kind not in "fiu":
        raise error(f"{what}: expected real numbers of shape {_shape_text(tail)}, got dtype {arr.dtype}")
    if arr.size == 0 and allow_empty:
        return np.zeros((0,) + tuple(tail))
    if arr.ndim != len(tail) + 1 or arr.shape[1:] != tuple(tail):
        raise error(f"{what}: expected shape {_shape_text(tail)}, got {arr.shape}")
    if len(arr) == 0:
        raise error(f"{what}: empty; expected shape {_shape_text(tail)} with N >= 1")
    arr = arr.astype(np.float64, copy=False)
    if not np.isfinite(arr).all():
        bad = np.flatnonzero(~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1))
        raise error(f"{what}: {len(bad)} of {len(arr)} rows have NaN or infinite values "
                    f"(first: row {int(bad[0])}); {fix}")
    return arr


#: the largest coordinate magnitude accepted anywhere coordinates enter (vertices, handles,
#: joint offsets, pose translations): squared distances, covariances and their sums then stay
#: far inside float32 (±3.4e38), which the OpenCL kernels compute in, and libigl's geometry
#: (winding numbers, geodesics) stays in the range it handles (a 10,000 km model in millimetres fits)
MAX_COORDINATE = 1e10


def coordinates(value, what: str, tail: tuple[int, ...] = (3,), error: type[InputError] = InputError,
                allow_empty: bool = False, fix: str = "give finite values") -> np.ndarray:
    """:func:`real_rows` whose every entry lies within ±:data:`MAX_COORDINATE`."""
    arr = real_rows(value, what, tail, error, allow_empty, fix)
    check_magnitude(arr, what, error)
    return arr


def check_magnitude(values: np.ndarray, what: str, error: type[InputError] = InputError,
                    limit: float = MAX_COORDINATE) -> None:
    """``error`` when a value of ``values`` (finite floats) exceeds ``limit`` in magnitude."""
    big = float(np.abs(values).max(initial=0.0))
    if big > limit:
        raise error(f"{what}: a value of magnitude {big:.3g} exceeds the largest nrpose accepts ({limit:.0e}; "
                    f"its kernels compute in float32); scale the data down")


def triangles(faces, n_vertices: int, what: str = "faces", error: type[InputError] = InputError,
              fix: str = "drop those faces or give the vertices they index") -> np.ndarray:
    """``faces`` as an (F, 3) int64 array of vertex indices in 0 .. n_vertices - 1.

    faces: integers, or floats holding whole numbers; F >= 1. what: the argument's name.
    error: the exception class raised. fix: the advice for faces out of range.
    """
    arr = _numeric(faces, what, "triangles of shape (F, 3)", error)
    if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0:
        raise error(f"{what}: expected triangles of shape (F, 3) with F >= 1, got {arr.shape}")
    if arr.dtype.kind == "f":
        broken = ~(arr == np.round(arr)).all(axis=1)          # NaN and fractions
        if broken.any():
            i = int(np.argmax(broken))
            raise error(f"{what}: {int(broken.sum())} of {len(arr)} faces hold vertex indices that are not "
                        f"whole numbers (first: face {i} = {arr[i].tolist()}); give integer indices")
    elif arr.dtype.kind not in "iu":
        raise error(f"{what}: expected integer vertex indices, got dtype {arr.dtype}")
    outside = ((arr < 0) | (arr >= n_vertices)).any(axis=1)
    if outside.any():
        i = int(np.argmax(outside))
        raise error(f"{what}: {int(outside.sum())} of {len(arr)} faces index vertices outside "
                    f"0..{n_vertices - 1} (first: face {i} = {arr[i].tolist()}); {fix}")
    return arr.astype(np.int64, copy=False)


def within_float32(values: np.ndarray, what: str) -> None:
    """InputError when a finite float64 value lies beyond float32's range (±3.4e38): a
    float32 file would hold it as infinity. values: any float array; what: its name."""
    big, largest = float(np.abs(values).max(initial=0.0)), float(np.finfo(np.float32).max)
    if big > largest:
        raise InputError(f"{what}: a value of magnitude {big:.3g} does not fit the file's float32 numbers "
                         f"(largest {largest:.3g}); scale the data down")


def _numeric(value, what: str, expected: str, error: type[InputError]) -> np.ndarray:
    """np.asarray(value), object arrays of numbers turned to float64; ``error`` if not an array."""
    try:
        arr = np.asarray(value)
        return arr.astype(np.float64) if arr.dtype.kind == "O" else arr
    except (TypeError, ValueError, OverflowError):
        raise error(f"{what}: expected {expected}; got {type(value).__name__} that is not a "
                    f"numeric array") from None
