"""Device set-up: the PoCL environment nrpose asks for (nrpose.device.pocl_settings /
pocl_environment) and the context it gets."""
import os
import pathlib
import subprocess
import sys

import pytest

from nrpose import device

LINUX_ONLY = pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="os.sched_getaffinity is Linux-only")
VARS = ("POCL_DEVICES", "POCL_MAX_PTHREAD_COUNT", "POCL_AFFINITY")


@pytest.fixture
def env(monkeypatch):
    """The PoCL variables unset for the test, whatever they were; monkeypatch restores
    them after (set first so that there is something to restore even when unset)."""
    for k in VARS:
        monkeypatch.setenv(k, "restored-after-the-test")
        monkeypatch.delenv(k)
    return monkeypatch


def cpus(env, allowed, count):
    env.setattr(os, "sched_getaffinity", lambda pid: set(allowed), raising=False)
    env.setattr(os, "cpu_count", lambda: count)


@LINUX_ONLY
def test_every_cpu_allowed(env):
    cpus(env, range(4), 4)
    with device.pocl_environment() as made:
        assert made == {"POCL_DEVICES": "pthread basic", "POCL_MAX_PTHREAD_COUNT": "3", "POCL_AFFINITY": "1"}
        assert all(os.environ[k] == v for k, v in made.items())
    assert not any(k in os.environ for k in VARS)        # children decide for themselves


@LINUX_ONLY
def test_restricted_to_some_cpus(env):
    # PoCL pins worker i to CPU i: outside the allowed set, so no pinning; workers = allowed - 1
    cpus(env, {2, 3}, 4)
    assert device.pocl_settings() == {"POCL_DEVICES": "pthread basic", "POCL_MAX_PTHREAD_COUNT": "1"}


@LINUX_ONLY
def test_single_cpu_runs_on_the_calling_thread(env):
    cpus(env, {0}, 1)
    assert device.pocl_settings() == {"POCL_DEVICES": "basic", "POCL_AFFINITY": "1"}
    cpus(env, {3}, 4)
    assert device.pocl_settings() == {"POCL_DEVICES": "basic"}


@LINUX_ONLY
def test_user_device_list_keeps_pocl_worker_count(env):
    cpus(env, range(2), 2)
    env.setenv("POCL_DEVICES", "pthread")
    assert device.pocl_settings() == {"POCL_AFFINITY": "1"}
    env.delenv("POCL_DEVICES")
    env.setenv("POCL_MAX_PTHREAD_COUNT", "7")
    assert device.pocl_settings() == {"POCL_DEVICES": "pthread basic", "POCL_AFFINITY": "1"}


@pytest.mark.parametrize("value", ["0", "1"])
def test_user_affinity_wins_and_stays(env, value):
    env.setenv("POCL_AFFINITY", value)
    env.setattr(os, "sched_getaffinity", lambda pid: set(range(os.cpu_count() or 1)), raising=False)
    with device.pocl_environment() as made:
        assert "POCL_AFFINITY" not in made and os.environ["POCL_AFFINITY"] == value
    assert os.environ["POCL_AFFINITY"] == value


@LINUX_ONLY
def test_empty_settings_count_as_unset_and_are_restored(env):
    env.setenv("POCL_AFFINITY", "")
    env.setenv("POCL_DEVICES", "")
    cpus(env, range(2), 2)
    with device.pocl_environment() as made:
        assert made["POCL_AFFINITY"] == "1" and made["POCL_DEVICES"] == "pthread basic"
    assert os.environ["POCL_AFFINITY"] == "" and os.environ["POCL_DEVICES"] == ""
    assert "POCL_MAX_PTHREAD_COUNT" not in os.environ


def test_not_linux(env):
    env.delattr(os, "sched_getaffinity", raising=False)
    env.setattr(os, "cpu_count", lambda: 2)
    with device.pocl_environment() as made:
        assert "POCL_AFFINITY" not in made and "POCL_AFFINITY" not in os.environ


def test_fresh_process_context():
    """In a fresh process with PoCL's default settings: device.context() holds PoCL's
    pthread and basic devices, the calling thread's queue is the basic one, the worker
    threads are pinned one per CPU, and no PoCL variable is left in the environment.
    Skipped where nrpose would not pin (restricted or single CPU, not Linux) or where
    the platform is not PoCL with both devices."""
    pytest.importorskip("pyopencl")
    clean = {k: v for k, v in os.environ.items() if k not in VARS + ("PYOPENCL_CTX",)}
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("POCL_AFFINITY", raising=False)
        if not device.may_pin_workers() or (os.cpu_count() or 1) < 2:
            pytest.skip("nrpose does not pin PoCL's workers here (CPU set restricted, single CPU or not Linux)")
    code = (
        "import os\n"
        "from nrpose import device, errors\n"
        "try:\n"
        "    ctx, q = device.context()\n"
        "except errors.DeviceError as e:\n"
        "    print('SKIP', e); raise SystemExit\n"
        "names = sorted(d.name.split('-')[0] for d in ctx.devices)\n"
        "print(','.join(names), q.device.name.split('-')[0], device.worker_queue() is not None,\n"
        "      ','.join(sorted(k for k in os.environ if k in ('POCL_DEVICES', 'POCL_MAX_PTHREAD_COUNT', 'POCL_AFFINITY'))) or '-')\n"
        "for t in os.listdir('/proc/self/task'):\n"
        "    line = [l for l in open(f'/proc/self/task/{t}/status') if l.startswith('Cpus_allowed_list')][0]\n"
        "    print(line.split(':')[1].strip())\n")
    root = pathlib.Path(__file__).resolve().parent.parent
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean,
                         cwd=root, check=True).stdout.split()
    if out[0] == "SKIP":
        pytest.skip("no OpenCL device: " + " ".join(out[1:]))
    if out[0] != "basic,pthread":
        pytest.skip(f"not PoCL with its pthread and basic devices: {out[0]}")
    assert out[1] == "basic" and out[2] == "True"
    assert out[3] == "-"                                      # nothing left behind
    single = [c for c in out[4:] if c.isdigit()]
    assert len(single) == (os.cpu_count() or 1) - 1, out      # worker threads, one CPU each
    assert len(set(single)) == len(single)
