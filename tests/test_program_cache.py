"""Program binaries in the binding cache (nrpose.device.programs): a later process builds a
program from its PoCL binaries, not its source; a binary PoCL refuses is replaced by a build
from source; the poses are the same bits either way."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import FOX
from nrpose.device.programs import PROGRAM_CACHE_FOLDER

pytest.importorskip("pyopencl")

SCRIPT = r"""
import json, sys
import numpy as np
import pyopencl as cl
from nrpose import device
from nrpose.bind.cache import cache_dir, cache_path, cached
from nrpose.device.programs import PROGRAM_CACHE_FOLDER, program_key_parts

ctx, _ = device.context()
name, options = "skinning.cl", device.program_options(("-DLBS_KERNEL",))
folder = cache_dir() / PROGRAM_CACHE_FOLDER
parts = program_key_parts(ctx, device.kernel_source(name), options)
path = cache_path(parts or {}, folder)
if sys.argv[1] == "spoil":      # an entry under the right key whose binaries PoCL cannot use
    path.unlink()
    cached(parts, lambda: {f"device{i}": np.frombuffer(b"not a PoCL binary", np.uint8)
                           for i in range(len(ctx.devices))}, folder)
    print(json.dumps({}))
    sys.exit()
prg = device.program(name, options)
print(json.dumps({"source_chars": len(prg.get_info(cl.program_info.SOURCE)), "entry": str(path),
                  "kernels": sorted(k.function_name for k in prg.all_kernels())}))
"""


def run(tmp_path, mode: str, **extra) -> dict:
    env = dict(os.environ, NRPOSE_CACHE_DIR=str(tmp_path / "nrpose"), POCL_CACHE_DIR=str(tmp_path / "pocl"),
               **extra)
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, env=env, check=True)
    got = json.loads(out.stdout)
    if "entry" in got:      # stored beside the job, by the time the process has ended
        got["entry"] = os.path.exists(got["entry"])
    return got


def test_a_later_process_builds_the_program_from_its_binaries(tmp_path):
    first, second = run(tmp_path, "build"), run(tmp_path, "build")
    assert first["entry"] and first["source_chars"] > 1000          # built from source, binaries stored
    assert second["source_chars"] == 0                                # built from the stored binaries
    assert second["kernels"] == first["kernels"] and "lbs" in first["kernels"]


def test_binaries_pocl_refuses_are_replaced_by_a_build_from_source(tmp_path):
    run(tmp_path, "build")
    run(tmp_path, "spoil")
    mended = run(tmp_path, "build")
    assert mended["source_chars"] > 1000 and mended["entry"]           # from source, entry written again
    assert run(tmp_path, "build")["source_chars"] == 0                # and usable by the next process


def test_build_flags_of_the_environment_bypass_the_binaries(tmp_path):
    """pyopencl and PoCL add flags from the environment that the key does not see: such a
    process builds from source and stores nothing."""
    for variable in ("PYOPENCL_BUILD_OPTIONS", "POCL_EXTRA_BUILD_FLAGS"):
        got = run(tmp_path, "build", **{variable: "-w"})
        assert got["source_chars"] > 1000 and not got["entry"]
        assert not (tmp_path / "nrpose" / PROGRAM_CACHE_FOLDER).exists()


def test_an_unwritable_cache_costs_the_binaries_quietly(tmp_path):
    """Binaries only save time: a cache that cannot be written adds no warning of its own."""
    blocked = tmp_path / "a file"
    blocked.write_text("not a folder")
    env = dict(os.environ, NRPOSE_CACHE_DIR=str(blocked), POCL_CACHE_DIR=str(tmp_path / "pocl"))
    done = subprocess.run([sys.executable, "-c", SCRIPT, "build"], capture_output=True, text=True, env=env)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    assert json.loads(done.stdout)["source_chars"] > 1000


def test_forgetting_an_entry_the_folder_keeps_is_not_an_error(tmp_path, monkeypatch):
    from pathlib import Path
    from nrpose.bind.cache import cache_path, cached, forget

    parts = {"kind": "test"}
    cached(parts, lambda: {"a": np.zeros(3)}, tmp_path)

    def refuse(self, missing_ok=False):
        raise PermissionError(13, "read-only", str(self))

    monkeypatch.setattr(Path, "unlink", refuse)
    forget(parts, tmp_path)                                   # no exception
    monkeypatch.undo()
    assert cache_path(parts, tmp_path).exists()
    forget(parts, tmp_path)
    assert not cache_path(parts, tmp_path).exists()


@pytest.mark.skipif(not FOX.exists(), reason=f"shared assets not found at {FOX}")
@pytest.mark.parametrize("method", ["lbs", "nrmls"])
def test_poses_from_binaries_equal_poses_from_source(tmp_path, method):
    env = dict(os.environ, NRPOSE_CACHE_DIR=str(tmp_path / "nrpose"), POCL_CACHE_DIR=str(tmp_path / "pocl"))
    frames = []
    for k in range(2):                      # source build, then binaries (and the binding from the cache)
        out = tmp_path / f"run{k}.npz"
        done = subprocess.run([sys.executable, "-m", "nrpose", "pose", str(FOX), "--clip", "Survey", "--method",
                               method, "-o", str(out)], capture_output=True, text=True, env=env)
        assert done.returncode == 0, done.stderr
        with np.load(out) as z:
            frames.append(z["positions"])
    assert frames[0].tobytes() == frames[1].tobytes()


def test_the_key_names_the_host_cpu(monkeypatch):
    """Binaries are compiled for the CPU: a cache shared by machines whose CPUs differ only in
    their instruction-set flags must not hand one machine's binaries to the other."""
    from nrpose import device
    from nrpose.bind.cache import cache_path
    from nrpose.device import programs

    ctx, _ = device.context()
    parts = programs.program_key_parts(ctx, "kernel void k() {}", ())
    if sys.platform.startswith("linux"):
        assert "flags" in parts["cpu"]
    monkeypatch.setattr(programs, "host_cpu", lambda: parts["cpu"].replace("avx2", "") + " (no avx2)")
    assert cache_path(programs.program_key_parts(ctx, "kernel void k() {}", ())) != cache_path(parts)
