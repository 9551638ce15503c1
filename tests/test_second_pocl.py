"""A second PoCL build gives the same results bit for bit: every kernel of
tests/kernel_cases.py run on the PyPI PoCL (``pocl-binary-distribution``, the default) and
on Debian's (apt ``pocl-opencl-icd``), each in a process of its own that sees only that
PoCL (the ICD loader's ``OCL_ICD_VENDORS`` naming its .icd file: both call themselves
"Portable Computing Language", so PYOPENCL_CTX cannot tell them apart by name).

Debian's ICD file is looked for in ``NRPOSE_SECOND_POCL_ICD`` (a path), else where
.ci/run keeps it aside (/etc/OpenCL/second/pocl.icd: in /etc/OpenCL/vendors it would be
every process's default platform), else where Debian installs it; the test skips where
there is none.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nrpose.diagnostics import pypi_pocl_icd, pypi_pocl_refusal

CASES = Path(__file__).with_name("kernel_cases.py")
PYPI_ICD = pypi_pocl_icd()


def second_icd() -> Path | None:
    """The second PoCL's ICD file, when installed (and not the PyPI one)."""
    given = os.environ.get("NRPOSE_SECOND_POCL_ICD")
    for path in [Path(given)] if given else [Path("/etc/OpenCL/second/pocl.icd"), Path("/etc/OpenCL/vendors/pocl.icd")]:
        if path.is_file() and (PYPI_ICD is None or path.resolve() != PYPI_ICD.resolve()):
            return path
    return None


def run_cases(icd: Path, out: Path) -> tuple[dict, str]:
    """kernel_cases.py on the PoCL of ``icd`` alone: (errors / tolerance by case, platform version)."""
    env = {**os.environ, "OCL_ICD_VENDORS": str(icd)}
    env.pop("PYOPENCL_CTX", None)
    code = ("import runpy, sys, pyopencl as cl; print(cl.get_platforms()[0].version, file=sys.stderr); "
            f"sys.argv = [{str(CASES)!r}, '--save', {str(out)!r}]; runpy.run_path(sys.argv[0], run_name='__main__')")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    version = [line for line in proc.stderr.splitlines() if line.startswith("OpenCL")][0]
    return json.loads(proc.stdout.strip().splitlines()[-1]), version


@pytest.mark.skipif(second_icd() is None, reason="no second PoCL (apt install pocl-opencl-icd, or set "
                    "NRPOSE_SECOND_POCL_ICD to its .icd file)")
def test_second_pocl_bitwise(tmp_path):
    if refusal := pypi_pocl_refusal():
        pytest.skip(f"nothing to compare with: {refusal}")
    first, first_version = run_cases(PYPI_ICD, tmp_path / "pypi.npz")
    second, second_version = run_cases(second_icd(), tmp_path / "second.npz")
    assert first_version != second_version, "both runs used the same PoCL"
    assert all(v <= 1.0 for v in [*first.values(), *second.values()]), (first, second)
    a, b = np.load(tmp_path / "pypi.npz"), np.load(tmp_path / "second.npz")
    assert sorted(a.files) == sorted(b.files)
    differ = {k: int((a[k].view(np.uint32) != b[k].view(np.uint32)).sum()) if a[k].dtype == np.float32
              else int((a[k] != b[k]).sum()) for k in a.files}
    assert not any(differ.values()), {k: n for k, n in differ.items() if n}
