"""Reading the project's small JSON inputs (handle files, pose files, joint maps)."""
from __future__ import annotations

import json
from pathlib import Path

from ..errors import FileFormatError, NrposeError
from .files import read_input_text


def read_json(path: str | Path, what: str, error: type[NrposeError] = FileFormatError):
    """The parsed JSON document at ``path``; ``error`` naming ``what`` (e.g. "pose file")
    when the file cannot be read or is not valid JSON."""
    text = read_input_text(path, what, error)
    try:
        return json.loads(text)
    except ValueError as exc:       # JSONDecodeError, and integers past Python's digit limit
        raise error(f"{path}: {what} is not valid JSON ({exc})") from None
