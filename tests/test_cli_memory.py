"""The nrpose program returns freed large blocks to the system (nrpose.cli.map_large_blocks)."""
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
