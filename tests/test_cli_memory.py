"""The nrpose program's process: freed large blocks go back to the system
(nrpose.cli.map_large_blocks); its exit skips the last garbage collections, not its exit
handlers (nrpose.cli.skip_final_collections)."""
from __future__ import annotations

import ctypes
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or not hasattr(ctypes.CDLL(None), "mallopt"),
                                reason="glibc's mallopt: Linux with glibc only")

# a freed 16 MB array raises glibc's default mmap threshold to 16 MB; 2 MB arrays then come from
# the heap, and with the last one alive at its top none of them goes back to the system
SCRIPT = r"""
import sys
import numpy as np
from nrpose.cli import map_large_blocks

def rss_mb():
    with open("/proc/self/status") as f:
        return next(int(l.split()[1]) for l in f if l.startswith("VmRSS")) / 1024

if sys.argv[1] == "mapped":
    map_large_blocks()
base = rss_mb()
big = np.ones(2 * 1024 * 1024)
del big
blocks = [np.ones(256 * 1024) for _ in range(50)]
last = blocks[-1]
del blocks
print(rss_mb() - base)
"""


def resident_after(mode: str) -> float:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True, env=env)
    return float(out.stdout)


def test_freed_blocks_leave_the_process_with_map_large_blocks():
    assert resident_after("default") > 60      # glibc's default keeps the 100 MB resident
    assert resident_after("mapped") < 20


# the exit handler registered first runs last, after nrpose's and the interpreter's own
EXIT = r"""
import atexit, gc, sys
from nrpose import cli
atexit.register(lambda: print("at exit: collecting", gc.isenabled(), "frozen", gc.get_freeze_count() > 0, flush=True))
sys.argv = ["nrpose"] + sys.argv[1:]
sys.exit(cli.command())
"""


@pytest.mark.parametrize("argv, status", [(["--version-of-nothing"], 2), (["demo", "--help"], 0)])
def test_the_program_exits_with_its_status_and_handlers_and_no_final_collections(argv, status):
    out = subprocess.run([sys.executable, "-c", EXIT, *argv], capture_output=True, text=True)
    assert out.returncode == status, out.stderr
    assert out.stdout.endswith("at exit: collecting False frozen True\n")
