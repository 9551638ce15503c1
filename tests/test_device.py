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


@LINUX_ONLY
def test_empty_setting_counts_as_unset_and_is_restored(env):
    env.setenv("POCL_AFFINITY", "")
    env.setattr(os, "sched_getaffinity", lambda pid: set(range(2)))
    env.setattr(os, "cpu_count", lambda: 2)
    with device.worker_pinning() as pinned:
        assert pinned is True and os.environ["POCL_AFFINITY"] == "1"
    assert os.environ["POCL_AFFINITY"] == ""


def test_not_linux(env):
    env.delattr(os, "sched_getaffinity", raising=False)
    with device.worker_pinning() as pinned:
        assert pinned is False and "POCL_AFFINITY" not in os.environ


def test_pocl_workers_pinned_and_environment_clean():
    """In a fresh process with PoCL's default settings: after device.context(), PoCL's
    worker threads are each on one CPU and POCL_AFFINITY is not left in the environment.
    Skipped where nrpose would not pin (restricted or single CPU, not Linux) or where the
    device has a single compute unit or is not PoCL's pthread device."""
    pytest.importorskip("pyopencl")
    clean = {k: v for k, v in os.environ.items()
             if k not in ("POCL_AFFINITY", "POCL_MAX_PTHREAD_COUNT", "POCL_DEVICES", "PYOPENCL_CTX")}
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("POCL_AFFINITY", raising=False)
        if not device.may_pin_workers() or (os.cpu_count() or 1) < 2:
            pytest.skip("nrpose does not pin PoCL's workers here (CPU set restricted, single CPU or not Linux)")
    code = (
        "import os\n"
        "from nrpose import device, errors\n"
        "try:\n"
        "    ctx, _ = device.context()\n"
        "except errors.DeviceError as e:\n"
        "    print('SKIP', e); raise SystemExit\n"
        "d = ctx.devices[0]\n"
        "print('pthread' in d.name and d.max_compute_units >= 2, os.environ.get('POCL_AFFINITY'))\n"
        "for t in os.listdir('/proc/self/task'):\n"
        "    line = [l for l in open(f'/proc/self/task/{t}/status') if l.startswith('Cpus_allowed_list')][0]\n"
        "    print(line.split(':')[1].strip())\n")
    root = pathlib.Path(__file__).resolve().parent.parent
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean,
                         cwd=root, check=True).stdout.split()
    if out[0] == "SKIP":
        pytest.skip("no OpenCL device: " + " ".join(out[1:]))
    if out[0] != "True":
        pytest.skip("not PoCL's pthread device with two or more compute units")
    assert out[1] == "None"                                  # POCL_AFFINITY not left behind
    single = [c for c in out[2:] if c.isdigit()]
    assert len(set(single)) >= 2, out                         # worker threads, one CPU each
