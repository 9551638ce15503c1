"""Reading the project's small JSON inputs (handle files, pose files, joint maps)."""
from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, NrposeError
from .files import read_input_text


#: deepest nesting of arrays and objects accepted: far beyond any nrpose input (glTF needs < 10),
#: far below where Python's recursive JSON decoder overflows its stack
MAX_DEPTH = 100
#: longest JSON text accepted (characters): a glTF within the schema's 10,000 entries per array
#: stays far below; Python's objects for 64 MB of JSON take ~1 GB
MAX_JSON_CHARS = 64_000_000
#: largest JSON file read (bytes): MAX_JSON_CHARS characters of up to 4 bytes each
MAX_JSON_BYTES = 4 * MAX_JSON_CHARS
_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def nesting_depth(text: str) -> int:
    """Deepest nesting of JSON arrays/objects in ``text``, counted without recursion
    (brackets inside strings are ignored), in blocks of 4 MB (bounded memory)."""
    code = np.frombuffer(_STRING.sub('""', text).encode("utf-8", "surrogatepass"), dtype=np.uint8)
    depth = deepest = 0
    for start in range(0, len(code), 1 << 22):
        block = code[start:start + (1 << 22)]
        step = ((block == ord("[")) | (block == ord("{"))).astype(np.int32)
        step -= (block == ord("]")) | (block == ord("}"))
        levels = np.cumsum(step, dtype=np.int64) + depth
        deepest = max(deepest, int(levels.max(initial=depth)))
        depth = int(levels[-1]) if len(levels) else depth
    return deepest


def check_depth(text: str, where: str, what: str, error: type[NrposeError] = FileFormatError) -> None:
    """``error`` naming ``where`` and ``what`` when ``text`` nests deeper than :data:`MAX_DEPTH`:
    refused before Python's recursive JSON decoder can overflow its stack."""
    depth = nesting_depth(text)
    if depth > MAX_DEPTH:
        raise error(f"{where}: {what} nests arrays/objects {depth} deep (at most {MAX_DEPTH}); "
                    "is it the right file?")


def check_json_size(path: str | Path, what: str, error: type[NrposeError] = FileFormatError) -> None:
    """``error`` naming ``path`` and ``what`` when the file holds more bytes than a JSON input
    nrpose reads (:data:`MAX_JSON_BYTES`): refused before it is read into memory. A file that
    cannot be examined is left to its reader, which names the problem."""
    try:
        size = os.stat(path).st_size
    except OSError:
        return
    if size > MAX_JSON_BYTES:
        raise error(f"{path}: {what} is {size / 1e6:.0f} MB (at most {MAX_JSON_BYTES // 10**6} MB of JSON); "
                    "is it the right file?")


def parse_json(text: str, where: str, what: str, error: type[NrposeError] = FileFormatError,
               finite: bool = True):
    """``json.loads(text)``, with ``error`` naming ``where`` and ``what`` for invalid JSON, too
    deep nesting (more than :data:`MAX_DEPTH`) and, with ``finite``, ``NaN``/``Infinity`` (not
    JSON, though Python reads them) and numbers past float64's range (``1e999`` reads as
    infinity). ``finite=False`` leaves them to a reader that names the field (then
    :func:`check_finite`).

    The decoder runs first: it refuses nesting past the interpreter's recursion limit with a
    RecursionError, not a crash, and only then is the text scanned (:func:`check_depth`) for
    the depth the message names; a decoded document's depth is counted on its values, which is
    faster than scanning its text."""
    if len(text) > MAX_JSON_CHARS:
        raise error(f"{where}: {what} is {len(text) / 1e6:.0f} MB of JSON (at most {MAX_JSON_CHARS // 10**6} MB); "
                    "is it the right file?")
    hooks = {"parse_float": _finite_float, "parse_constant": _not_a_number} if finite else {}
    try:
        doc = json.loads(text, **hooks)
    except RecursionError:
        check_depth(text, where, what, error)
        raise error(f"{where}: {what} nests arrays/objects too deep to read; is it the right file?") from None
    except ValueError as exc:       # JSONDecodeError, and integers past Python's digit limit
        raise error(f"{where}: {what} is not valid JSON ({exc})") from None
    depth = document_depth(doc)
    if depth > MAX_DEPTH:
        raise error(f"{where}: {what} nests arrays/objects {depth} deep (at most {MAX_DEPTH}); "
                    "is it the right file?")
    return doc


def document_depth(value) -> int:
    """Deepest nesting of arrays/objects in parsed JSON ``value`` (0 for a number or string)."""
    return sum(containers for _, containers in _levels(value))


def _levels(value):
    """Parsed JSON ``value`` level by level, without recursion: (the level's values, whether
    any of them is an array or object), the first level ``[value]``."""
    level = [value]
    while level:
        inner, containers = [], False
        for v in level:
            if type(v) is dict:
                inner.extend(v.values())
                containers = True
            elif type(v) is list:
                inner.extend(v)
                containers = True
        yield level, containers
        level = inner


def check_finite(value, where: str, error: type[NrposeError] = FileFormatError) -> None:
    """``error`` naming the first NaN or infinite number in parsed JSON ``value`` by its path
    (depth already bounded by :func:`parse_json`)."""
    if _all_finite(value):      # the common case, without a path string for every value
        return
    stack = [("", value)]
    while stack:
        path, v = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            raise error(f"{where}: {path.lstrip('.') or 'the document'} = {v}: JSON has no such number")
        if isinstance(v, dict):
            stack.extend((f"{path}.{k}", x) for k, x in v.items())
        elif isinstance(v, list):
            stack.extend((f"{path}[{i}]", x) for i, x in enumerate(v))


def _all_finite(value) -> bool:
    """Whether parsed JSON ``value`` holds no NaN or infinite number."""
    return not any(type(v) is float and not math.isfinite(v) for level, _ in _levels(value) for v in level)


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"the number {text[:40]} is beyond float64's range")
    return value


def _not_a_number(name: str):
    raise ValueError(f"{name} is not a JSON number")


def read_json(path: str | Path, what: str, error: type[NrposeError] = FileFormatError):
    """The parsed JSON document at ``path``; ``error`` naming ``what`` (e.g. "pose file")
    when the file cannot be read, is too large or is not valid JSON."""
    check_json_size(path, what, error)
    return parse_json(read_input_text(path, what, error), str(path), what, error)
