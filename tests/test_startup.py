"""The nrpose program starts PoCL and its compiler on a thread before it imports numpy
(nrpose.device.startup): PoCL then has the settings the context would have given it, the
environment is left as it was, a compiled program is in PoCL's cache, and nothing of it shows
in what a command does or prints."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import threading

import pytest

from conftest import FOX

pytest.importorskip("pyopencl")

POCL_VARIABLES = ("POCL_DEVICES", "POCL_MAX_PTHREAD_COUNT", "POCL_AFFINITY")

SCRIPT = r"""
import json, os, sys
from nrpose.device import pocl_environment, startup
started = startup.start_pocl(pocl_environment) if sys.argv[1] == "start" else False
numpy_then = "numpy" in sys.modules
pocl_here = startup.pocl_started()
from nrpose import device
ctx, _ = device.context()
startup.join()
print(json.dumps({"started": started, "numpy_then": numpy_then, "pocl_here": pocl_here,
                  "devices": sorted(d.name for d in ctx.devices),
                  "env": {k: os.environ.get(k) for k in %r}}))
""" % (POCL_VARIABLES,)


def clean_env(tmp_path, **extra) -> dict:
    """The test's environment without PoCL's and pyopencl's choices, PoCL's cache in tmp_path."""
    env = {k: v for k, v in os.environ.items() if k not in POCL_VARIABLES + ("PYOPENCL_CTX",)}
    return dict(env, POCL_CACHE_DIR=str(tmp_path / "pocl"), **extra)


def programs_cached(tmp_path) -> int:
    return sum(1 for _ in (tmp_path / "pocl").rglob("program.bc"))


def run_script(tmp_path, mode: str, whole_job: str) -> dict:
    out = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True,
                         env=clean_env(tmp_path, NRPOSE_WHOLE_JOB=whole_job))
    return json.loads(out.stdout)


@pytest.mark.parametrize("whole_job", ["1", "0"])
def test_startup_gives_pocl_the_context_settings_before_numpy(tmp_path, whole_job):
    plain = run_script(tmp_path / "plain", "none", whole_job)
    early = run_script(tmp_path / "early", "start", whole_job)
    assert early["started"] and early["pocl_here"] and not early["numpy_then"]
    assert not plain["pocl_here"]
    # the same devices (PoCL read nrpose's settings), and the environment left as it was
    assert early["devices"] == plain["devices"]
    assert len(early["devices"]) == (1 if whole_job == "1" else 2) or os.cpu_count() == 1
    assert early["env"] == plain["env"] == {k: None for k in POCL_VARIABLES}
    # the thread compiled a program for each device (PoCL loaded its kernel library for it); the
    # context alone none
    assert programs_cached(tmp_path / "early") == len(early["devices"]) and programs_cached(tmp_path / "plain") == 0


def test_startup_is_not_started_where_it_cannot_help(monkeypatch):
    from nrpose.device import pocl_environment, startup

    def threads():
        return [t for t in threading.enumerate() if t.name == "nrpose-pocl-startup"]

    before = threads()
    monkeypatch.setenv("PYOPENCL_CTX", "0")          # the user chooses the platform
    assert not startup.start_pocl(pocl_environment)
    monkeypatch.delenv("PYOPENCL_CTX")
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)     # no pyopencl
    assert not startup.start_pocl(pocl_environment)
    assert threads() == before


@pytest.mark.skipif(not FOX.exists(), reason=f"shared assets not found at {FOX}")
def test_program_poses_cold_and_fails_cleanly_with_the_startup_thread(tmp_path):
    env = clean_env(tmp_path, NRPOSE_CACHE_DIR=str(tmp_path / "nrpose"))
    env.pop("NRPOSE_WHOLE_JOB", None)
    out = tmp_path / "run.npz"
    ok = subprocess.run([sys.executable, "-m", "nrpose", "pose", str(FOX), "--clip", "Run", "--method", "lbs",
                         "-o", str(out)], capture_output=True, text=True, env=env)
    assert ok.returncode == 0, ok.stderr
    assert out.exists() and ok.stderr == ""
    assert programs_cached(tmp_path) == 2            # the startup's program and the skinning program
    # a mistake found while the startup thread compiles: one line, status 2, no output
    bad = subprocess.run([sys.executable, "-m", "nrpose", "pose", str(tmp_path / "missing.glb"), "--clip", "Run", "-o",
                          str(tmp_path / "bad.npz")], capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and len(bad.stderr.splitlines()) == 1 and "missing.glb" in bad.stderr
    assert not (tmp_path / "bad.npz").exists()


@pytest.mark.parametrize("argv, builds", [
    (["pose", "x.glb", "--clip", "Run"], True), (["fit-skin", "x.glb"], True), (["deform", "m.obj"], True),
    (["pose", "x.glb", "--backend", "numpy"], False), (["deform", "--backend=numpy", "m.obj"], False),
    (["info", "x.glb"], False), (["retarget", "a.bvh", "x.glb"], False), ([], False)])
def test_the_program_starts_pocl_for_commands_that_build_programs(argv, builds):
    from nrpose.cli import builds_programs

    assert builds_programs(argv) == builds
