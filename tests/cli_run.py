"""What the CLI tests share: the shared assets' folder and running ``nrpose`` in-process."""
from pathlib import Path

import pytest

from nrpose.cli import main

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared assets not found at {DATA}")


def run(args, capsys):
    """``nrpose ARGS`` in this process: (exit status, stdout, stderr)."""
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err
