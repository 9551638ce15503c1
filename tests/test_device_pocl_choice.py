"""Which PoCL nrpose runs on where a PoCL cannot compile for this CPU (PyPI's PoCL 3.0 with
LLVM 14 on AMD Zen 5: ``error: unknown target CPU 'generic'``): with several PoCLs, the one
that cannot is passed over; alone, its first build is refused with the fix in one line.

The choice is checked on stand-ins of pyopencl's platforms (whose builds succeed or fail as
told) and, where this machine has such a CPU, on the real drivers in a process of its own.
"""
from __future__ import annotations

import os
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

import gltf_asset

from nrpose.device import env
from nrpose.diagnostics import pypi_pocl_icd, pypi_pocl_refusal
from nrpose.errors import DeviceError

UNKNOWN_CPU = "clBuildProgram failed: BUILD_PROGRAM_FAILURE\nerror: unknown target CPU 'generic'"


class FakeCL(SimpleNamespace):
    """pyopencl's names that the context choice uses; ``builds[version]`` is None (the
    build succeeds) or the build log a failing build raises."""

    class Error(Exception):
        pass

    class RuntimeError(Error):
        pass

    device_type = SimpleNamespace(CPU=2)

    def __init__(self, builds: dict):
        super().__init__(builds=builds, built=[])
        self.platforms = [SimpleNamespace(name=name, version=version, devices=[])
                          for name, version in builds]
        for plat in self.platforms:
            plat.devices = [SimpleNamespace(name=f"{d}-CPU", platform=plat, type=2, driver_version="1")
                            for d in ("pthread", "basic")]
            plat.get_devices = (lambda p: lambda device_type=None: p.devices)(plat)
        self.Context = lambda devices: SimpleNamespace(devices=devices)
        self.Program = self._program

    def get_platforms(self):
        return self.platforms

    def _program(self, ctx, source):
        plat = ctx.devices[0].platform
        self.built.append(plat.version)

        def build(options=()):
            log = self.builds[(plat.name, plat.version)]
            if log is not None:
                raise FakeCL.RuntimeError(log)
            return SimpleNamespace(source=source)
        return SimpleNamespace(build=build)


@pytest.fixture
def fake(monkeypatch, tmp_path):
    def make(builds):
        cl = FakeCL(builds)
        monkeypatch.setattr(env, "pyopencl", lambda: cl)
        monkeypatch.delenv("PYOPENCL_CTX", raising=False)
        monkeypatch.setenv("NRPOSE_CACHE_DIR", str(tmp_path / "cache"))
        return cl
    return make


def test_a_pocl_that_cannot_compile_is_passed_over(fake):
    cl = fake({("Oclgrind", "1.2"): None, (env.POCL, "PoCL 3.0-rc2  LLVM 14"): UNKNOWN_CPU,
               (env.POCL, "PoCL 3.1+debian  LLVM 15"): None})
    ctx = env._new_context(cl)
    assert ctx.devices[0].platform.version == "PoCL 3.1+debian  LLVM 15"
    assert [d.name for d in ctx.devices] == ["pthread-CPU", "basic-CPU"]
    assert cl.built == ["PoCL 3.0-rc2  LLVM 14", "PoCL 3.1+debian  LLVM 15"]   # Oclgrind never tried


def test_the_verdicts_are_remembered(fake, tmp_path):
    builds = {(env.POCL, "PoCL 3.0-rc2  LLVM 14"): UNKNOWN_CPU, (env.POCL, "PoCL 3.1+debian  LLVM 15"): None}
    first = fake(builds)
    env._new_context(first)
    again = fake(builds)            # a later process: no probe build, the same choice
    assert env._new_context(again).devices[0].platform.version == "PoCL 3.1+debian  LLVM 15"
    assert len(first.built) == 2 and again.built == []
    verdicts = sorted(str(np.load(p)["refusal"]) for p in (tmp_path / "cache" / "opencl-compilers").iterdir())
    assert verdicts[0] == "" and "cannot compile for this CPU" in verdicts[1]


def test_an_unusable_cache_only_means_probing_again(fake, tmp_path, monkeypatch):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    builds = {(env.POCL, "PoCL A"): UNKNOWN_CPU, (env.POCL, "PoCL B"): None}
    for _ in range(2):
        cl = fake(builds)
        monkeypatch.setenv("NRPOSE_CACHE_DIR", str(blocker))
        assert env._new_context(cl).devices[0].platform.version == "PoCL B"
        assert cl.built == ["PoCL A", "PoCL B"]


def test_the_first_pocl_that_compiles_is_kept(fake):
    cl = fake({(env.POCL, "PoCL A"): None, (env.POCL, "PoCL B"): None})
    assert env._new_context(cl).devices[0].platform.version == "PoCL A"


def test_a_single_pocl_is_not_probed(fake):
    # its first real build says what is wrong: no probe build on every start
    cl = fake({(env.POCL, "PoCL 3.0-rc2  LLVM 14"): UNKNOWN_CPU, ("Oclgrind", "1.2"): None})
    assert env._new_context(cl).devices[0].platform.version == "PoCL 3.0-rc2  LLVM 14"
    assert cl.built == []


def test_no_pocl_that_compiles_is_refused_with_the_fix(fake):
    cl = fake({(env.POCL, "OpenCL 3.0 PoCL 3.0-rc2  Linux, LLVM 14"): UNKNOWN_CPU,
               (env.POCL, "OpenCL 3.0 PoCL 2.0  Linux, LLVM 13"): UNKNOWN_CPU})
    with pytest.raises(DeviceError) as exc:
        env._new_context(cl)
    message = str(exc.value)
    assert "OpenCL 3.0 PoCL 3.0-rc2 cannot compile for this CPU (pthread-CPU)" in message
    assert "apt install pocl-opencl-icd" in message and "\n" not in message


def test_other_build_failures_keep_their_log(fake):
    cl = fake({(env.POCL, "PoCL A"): "error: something else", (env.POCL, "PoCL B"): "error: something else"})
    with pytest.raises(DeviceError, match="the OpenCL compiler fails: error: something else"):
        env._new_context(cl)
    ctx = SimpleNamespace(devices=cl.platforms[0].devices)
    assert env.cpu_unknown_hint(ctx, "error: something else") is None


@pytest.mark.skipif(pypi_pocl_icd() is None, reason="pyopencl's wheel has no PoCL ICD file")
def test_cli_on_a_cpu_pypi_pocl_does_not_know(tmp_path):
    """The real drivers: PyPI's PoCL alone, on this CPU."""
    refusal = pypi_pocl_refusal()
    if refusal is None:
        pytest.skip("PyPI's PoCL compiles for this CPU: nothing is refused here")
    environment = {**os.environ, "OCL_ICD_VENDORS": str(pypi_pocl_icd())}
    environment.pop("PYOPENCL_CTX", None)
    asset, out = gltf_asset.build(tmp_path / "tube.glb"), tmp_path / "bent.npz"
    proc = subprocess.run([sys.executable, "-m", "nrpose", "pose", str(asset), "--clip", "bend", "-o", str(out)],
                          env=environment, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert lines[-1] == f"nrpose: error: {refusal}", lines
    assert "Traceback" not in proc.stderr
    assert not out.exists()
