"""Device set-up: PoCL worker pinning (nrpose.device.worker_pinning)."""
import os
import pathlib
import subprocess
import sys

import pytest

from nrpose import device

LINUX_ONLY = pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="os.sched_getaffinity is Linux-only")


@pytest.fixture
def env(monkeypatch):
    """POCL_AFFINITY unset for the test, whatever it was; monkeypatch restores it after
    (set first so that there is something to restore even when it was unset)."""
    monkeypatch.setenv("POCL_AFFINITY", "restored-after-the-test")
    monkeypatch.delenv("POCL_AFFINITY")
    return monkeypatch


@LINUX_ONLY
def test_pins_while_pocl_starts_when_every_cpu_is_allowed(env):
    env.setattr(os, "sched_getaffinity", lambda pid: set(range(4)))
    env.setattr(os, "cpu_count", lambda: 4)
    with device.worker_pinning() as pinned:
        assert pinned is True and os.environ["POCL_AFFINITY"] == "1"
    assert "POCL_AFFINITY" not in os.environ        # children decide for themselves


@LINUX_ONLY
def test_no_pinning_when_restricted_to_some_cpus(env):
    # PoCL pins worker i to CPU i: outside the allowed set
    env.setattr(os, "sched_getaffinity", lambda pid: {2, 3})
    env.setattr(os, "cpu_count", lambda: 4)
    with device.worker_pinning() as pinned:
        assert pinned is False and "POCL_AFFINITY" not in os.environ


@pytest.mark.parametrize("value", ["0", "1"])
def test_user_setting_wins_and_stays(env, value):
    env.setenv("POCL_AFFINITY", value)
    env.setattr(os, "sched_getaffinity", lambda pid: set(range(os.cpu_count() or 1)), raising=False)
    with device.worker_pinning() as pinned:
        assert pinned is False and os.environ["POCL_AFFINITY"] == value
    assert os.environ["POCL_AFFINITY"] == value


def test_not_linux(env):
    env.delattr(os, "sched_getaffinity", raising=False)
    with device.worker_pinning() as pinned:
        assert pinned is False and "POCL_AFFINITY" not in os.environ


@LINUX_ONLY
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2 if hasattr(os, "sched_getaffinity") else True,
                    reason="needs two CPUs")
def test_pocl_workers_pinned_and_environment_clean():
    """In a fresh process: after device.context(), PoCL's worker threads are each on one CPU
    and POCL_AFFINITY is not left in the environment."""
    pytest.importorskip("pyopencl")
    code = (
        "import os; from nrpose import device; device.context()\n"
        "print(os.environ.get('POCL_AFFINITY'))\n"
        "for t in os.listdir('/proc/self/task'):\n"
        "    line = [l for l in open(f'/proc/self/task/{t}/status') if l.startswith('Cpus_allowed_list')][0]\n"
        "    print(line.split(':')[1].strip())\n")
    clean = {k: v for k, v in os.environ.items() if k != "POCL_AFFINITY"}
    root = pathlib.Path(__file__).resolve().parent.parent
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean,
                         cwd=root, check=True).stdout.split()
    assert out[0] == "None"
    single = [c for c in out[1:] if c.isdigit()]
    assert len(single) >= 2 and len(set(single)) >= 2, out    # one worker thread per CPU
