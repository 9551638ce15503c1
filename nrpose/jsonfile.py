"""Reading the project's small JSON inputs (handle files, pose files, joint maps)."""
from __future__ import annotations

import json
from pathlib import Path

from .errors import FileFormatError, NrposeError


def read_json(path: str | Path, what: str, error: type[NrposeError] = FileFormatError):
    """The parsed JSON document at ``path``; ``error`` naming ``what`` (e.g. "pose file")
    when the file cannot be read or is not valid JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{path}: {what} is not valid JSON ({exc})") from None
