"""Device set-up: PoCL worker pinning (nrpose.device.pin_workers)."""
import os

import pytest

from nrpose import device


@pytest.fixture
def env(monkeypatch):
    """A clean POCL_AFFINITY for the test; the real environment is restored after."""
    monkeypatch.delenv("POCL_AFFINITY", raising=False)
    return monkeypatch


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="os.sched_getaffinity is Linux-only")
def test_pins_when_every_cpu_is_allowed(env):
    env.setattr(os, "sched_getaffinity", lambda pid: set(range(4)))
    env.setattr(os, "cpu_count", lambda: 4)
    assert device.pin_workers() is True
    assert os.environ["POCL_AFFINITY"] == "1"


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="os.sched_getaffinity is Linux-only")
def test_no_pinning_when_restricted_to_some_cpus(env):
    # PoCL pins worker i to CPU i: outside the allowed set that aborts the process
    env.setattr(os, "sched_getaffinity", lambda pid: {2, 3})
    env.setattr(os, "cpu_count", lambda: 4)
    assert device.pin_workers() is False
    assert "POCL_AFFINITY" not in os.environ


@pytest.mark.parametrize("value", ["0", "1"])
def test_user_setting_wins(env, value):
    env.setenv("POCL_AFFINITY", value)
    env.setattr(os, "sched_getaffinity", lambda pid: set(range(os.cpu_count() or 1)), raising=False)
    assert device.pin_workers() is False
    assert os.environ["POCL_AFFINITY"] == value


def test_not_linux(env):
    env.delattr(os, "sched_getaffinity", raising=False)
    assert device.pin_workers() is False
    assert "POCL_AFFINITY" not in os.environ
