"""Reading the project's small JSON inputs (handle files, pose files, joint maps)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, NrposeError
from .files import read_input_text


#: deepest nesting of arrays and objects accepted: far beyond any nrpose input (glTF needs < 10),
#: far below where Python's recursive JSON decoder overflows its stack
MAX_DEPTH = 100
_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def nesting_depth(text: str) -> int:
    """Deepest nesting of JSON arrays/objects in ``text``, counted without recursion
    (brackets inside strings are ignored)."""
    code = np.frombuffer(_STRING.sub('""', text).encode("utf-8", "surrogatepass"), dtype=np.uint8)
    step = (np.isin(code, (ord("["), ord("{"))).astype(np.int64)
            - np.isin(code, (ord("]"), ord("}"))).astype(np.int64))
    return int(np.cumsum(step).max(initial=0))


def check_depth(text: str, where: str, what: str, error: type[NrposeError] = FileFormatError) -> None:
    """``error`` naming ``where`` and ``what`` when ``text`` nests deeper than :data:`MAX_DEPTH`:
    refused before Python's recursive JSON decoder can overflow its stack."""
    depth = nesting_depth(text)
    if depth > MAX_DEPTH:
        raise error(f"{where}: {what} nests arrays/objects {depth} deep (at most {MAX_DEPTH}); "
                    "is it the right file?")


def parse_json(text: str, where: str, what: str, error: type[NrposeError] = FileFormatError):
    """``json.loads(text)``, with ``error`` naming ``where`` and ``what`` for invalid JSON or
    too deep nesting (:func:`check_depth`)."""
    check_depth(text, where, what, error)
    try:
        return json.loads(text)
    except ValueError as exc:       # JSONDecodeError, and integers past Python's digit limit
        raise error(f"{where}: {what} is not valid JSON ({exc})") from None


def read_json(path: str | Path, what: str, error: type[NrposeError] = FileFormatError):
    """The parsed JSON document at ``path``; ``error`` naming ``what`` (e.g. "pose file")
    when the file cannot be read or is not valid JSON."""
    return parse_json(read_input_text(path, what, error), str(path), what, error)
