"""Device set-up: the PoCL environment nrpose asks for (nrpose.device.pocl_settings /
pocl_environment) and the context it gets."""
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from nrpose import device

LINUX_ONLY = pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="os.sched_getaffinity is Linux-only")
VARS = ("POCL_DEVICES", "POCL_MAX_PTHREAD_COUNT", "POCL_AFFINITY", "NRPOSE_WHOLE_JOB")


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
        assert made == {"POCL_DEVICES": "pthread basic", "POCL_MAX_PTHREAD_COUNT": "3"}
        assert all(os.environ[k] == v for k, v in made.items())
    assert not any(k in os.environ for k in VARS)        # children decide for themselves


@LINUX_ONLY
def test_restricted_to_some_cpus(env):
    cpus(env, {2, 3}, 4)                 # workers = allowed CPUs - 1
    assert device.pocl_settings() == {"POCL_DEVICES": "pthread basic", "POCL_MAX_PTHREAD_COUNT": "1"}
    env.setenv("POCL_DEVICES", "pthread")
    assert device.pocl_settings() == {}  # PoCL pins worker i to CPU i: outside the allowed set


@LINUX_ONLY
def test_single_cpu_runs_on_the_calling_thread(env):
    cpus(env, {0}, 1)
    assert device.pocl_settings() == {"POCL_DEVICES": "basic"}
    cpus(env, {3}, 4)
    assert device.pocl_settings() == {"POCL_DEVICES": "basic"}


@LINUX_ONLY
def test_user_device_list_keeps_pocl_worker_count_and_pins(env):
    cpus(env, range(2), 2)
    env.setenv("POCL_DEVICES", "pthread")
    assert device.pocl_settings() == {"POCL_AFFINITY": "1"}
    env.delenv("POCL_DEVICES")
    env.setenv("POCL_MAX_PTHREAD_COUNT", "7")
    assert device.pocl_settings() == {"POCL_DEVICES": "pthread basic"}


@LINUX_ONLY
def test_whole_job_process_has_the_worker_device_alone_on_every_cpu(env):
    env.setenv("NRPOSE_WHOLE_JOB", "1")
    cpus(env, range(4), 4)
    assert device.pocl_settings() == {"POCL_DEVICES": "pthread", "POCL_MAX_PTHREAD_COUNT": "4", "POCL_AFFINITY": "1"}
    cpus(env, {2, 3}, 4)                 # not pinned: PoCL pins worker i to CPU i
    assert device.pocl_settings() == {"POCL_DEVICES": "pthread", "POCL_MAX_PTHREAD_COUNT": "2"}
    assert device.pocl_settings(cpus=1) == {"POCL_AFFINITY": "0", "POCL_DEVICES": "basic"}
    assert device.pocl_settings(cpus=2) == {"POCL_AFFINITY": "0", "POCL_DEVICES": "pthread",
                                            "POCL_MAX_PTHREAD_COUNT": "2"}
    env.setenv("POCL_DEVICES", "pthread basic")     # the user's list wins
    cpus(env, range(4), 4)
    assert device.pocl_settings() == {"POCL_AFFINITY": "1"}
    env.setenv("NRPOSE_WHOLE_JOB", "0")
    env.delenv("POCL_DEVICES")
    assert device.pocl_settings() == {"POCL_DEVICES": "pthread basic", "POCL_MAX_PTHREAD_COUNT": "3"}


def test_the_nrpose_program_runs_whole_jobs_unless_told_otherwise(env):
    import nrpose.cli as cli
    seen = []
    env.setattr(cli, "main", lambda: seen.append(os.environ.get("NRPOSE_WHOLE_JOB")) or 0)
    env.setattr(cli, "skip_final_collections", lambda: None)    # not in the test process
    assert cli.command() == 0 and seen == ["1"]
    env.setenv("NRPOSE_WHOLE_JOB", "0")
    assert cli.command() == 0 and seen == ["1", "0"]


@pytest.mark.parametrize("value", ["0", "1"])
def test_user_affinity_wins_and_stays(env, value):
    env.setenv("POCL_AFFINITY", value)
    env.setenv("POCL_DEVICES", "pthread")
    env.setattr(os, "sched_getaffinity", lambda pid: set(range(os.cpu_count() or 1)), raising=False)
    with device.pocl_environment() as made:
        assert "POCL_AFFINITY" not in made and os.environ["POCL_AFFINITY"] == value
    assert os.environ["POCL_AFFINITY"] == value


@LINUX_ONLY
def test_empty_settings_count_as_unset_and_are_restored(env):
    env.setenv("POCL_MAX_PTHREAD_COUNT", "")
    env.setenv("POCL_DEVICES", "")
    cpus(env, range(2), 2)
    with device.pocl_environment() as made:
        assert made == {"POCL_DEVICES": "pthread basic", "POCL_MAX_PTHREAD_COUNT": "1"}
    assert os.environ["POCL_MAX_PTHREAD_COUNT"] == "" and os.environ["POCL_DEVICES"] == ""
    assert "POCL_AFFINITY" not in os.environ


def test_not_linux(env):
    env.delattr(os, "sched_getaffinity", raising=False)
    env.setattr(os, "cpu_count", lambda: 2)
    env.setenv("POCL_DEVICES", "pthread")
    with device.pocl_environment() as made:
        assert made == {} and "POCL_AFFINITY" not in os.environ


def test_fresh_process_context():
    """In a fresh process with PoCL's default settings: device.context() holds PoCL's
    pthread and basic devices, the calling thread's queue is the basic one, there is one
    worker thread per CPU but one (PoCL's pthread device reports them as compute units),
    and no PoCL variable is left in the environment. Skipped on a single usable CPU or
    where the platform is not PoCL with both devices."""
    pytest.importorskip("pyopencl")
    if device.usable_cpus() < 2:
        pytest.skip("a single usable CPU: PoCL's basic device alone")
    clean = {k: v for k, v in os.environ.items() if k not in VARS + ("PYOPENCL_CTX",)}
    code = (
        "import os\n"
        "from nrpose import device, errors\n"
        "try:\n"
        "    ctx, q = device.context()\n"
        "except errors.DeviceError as e:\n"
        "    print('SKIP', e); raise SystemExit\n"
        "names = sorted(d.name.split('-')[0] for d in ctx.devices)\n"
        "wq = device.worker_queue()\n"
        "print(','.join(names), q.device.name.split('-')[0], wq.device.max_compute_units if wq else 0,\n"
        "      ','.join(sorted(k for k in os.environ if k in ('POCL_DEVICES', 'POCL_MAX_PTHREAD_COUNT',\n"
        "                                                     'POCL_AFFINITY'))) or '-')\n")
    root = pathlib.Path(__file__).resolve().parent.parent
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=clean,
                         cwd=root, check=True).stdout.split()
    if out[0] == "SKIP":
        pytest.skip("no OpenCL device: " + " ".join(out[1:]))
    if out[0] != "basic,pthread":
        pytest.skip(f"not PoCL with its pthread and basic devices: {out[0]}")
    assert out[1] == "basic"
    assert int(out[2]) == device.usable_cpus() - 1
    assert out[3] == "-"                                      # nothing left behind


def test_rsqrt8_against_float64():
    """kernels/lanes.h rsqrt8, both ways (x86's estimate + one Newton step, and the
    portable bit trick + three, forced by -DPORTABLE_RSQRT), against float64 1/sqrt:
    within 3e-7 relative from denormals to 1e30, and 0 * rsqrt8(0) = 0 (finite); its
    core rsqrt8_normal likewise on normal floats, and rsqrt8_normal_twice(x, h) as
    2h/sqrt(x) there (h of either sign, and 0). On x86-64 the two builds differ in
    some bits (the switch took effect)."""
    import platform

    import pyopencl as cl

    ctx, queue = device.context()
    src = device.with_headers('#include "lanes.h"\n'
                              "__kernel void rs(__global const float8 *x, __global float8 *y)\n"
                              "{ y[get_global_id(0)] = rsqrt8(x[get_global_id(0)]); }\n"
                              "__kernel void rs_normal(__global const float8 *x, __global float8 *y)\n"
                              "{ y[get_global_id(0)] = rsqrt8_normal(x[get_global_id(0)]); }\n"
                              "__kernel void rs_twice(__global const float8 *x, __global const float8 *h,\n"
                              "                       __global float8 *y)\n"
                              "{ const int i = get_global_id(0); y[i] = rsqrt8_normal_twice(x[i], h[i]); }\n")
    rng = np.random.default_rng(1)
    x = np.concatenate([[0.0, 1e-45, 3e-40, 1.1754942e-38, 1.2e-38, 1e-30, 1.0, 4.0, 1e30],
                        10.0 ** rng.uniform(-37, 30, 1000)]).astype(np.float32)
    x = np.concatenate([x, np.ones(-len(x) % 8, np.float32)])
    mf = cl.mem_flags
    xb = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    yb = cl.Buffer(ctx, mf.WRITE_ONLY, x.nbytes)
    results = []
    for options in ([], ["-DPORTABLE_RSQRT"]):
        prg = cl.Program(ctx, src).build(options=options)
        prg.rs(queue, (len(x) // 8,), None, xb, yb)
        y = np.empty_like(x)
        cl.enqueue_copy(queue, y, yb)
        assert np.isfinite(y).all() and y[0] > 1e18 and np.float32(0) * y[0] == 0, options
        pos = x > 0
        assert np.abs(y[pos] / (1.0 / np.sqrt(x[pos].astype(np.float64))) - 1).max() < 3e-7, options
        results.append(y)
        # rsqrt8_normal, for normal x only: the same to 3e-7 there
        normal = x >= np.float32(1.17549435e-38)
        prg.rs_normal(queue, (len(x) // 8,), None, xb, yb)
        yn = np.empty_like(x)
        cl.enqueue_copy(queue, yn, yb)
        assert np.abs(yn[normal] / (1.0 / np.sqrt(x[normal].astype(np.float64))) - 1).max() < 3e-7, options
        # rsqrt8_normal_twice(x, h) = 2h / sqrt(x), likewise
        h = rng.choice(np.float32([0.785398163, 1.57079633, -2.5, 0.0]), len(x)).astype(np.float32)
        hb = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=h)
        prg.rs_twice(queue, (len(x) // 8,), None, xb, hb, yb)
        yt = np.empty_like(x)
        cl.enqueue_copy(queue, yt, yb)
        want = 2.0 * h[normal] / np.sqrt(x[normal].astype(np.float64))
        assert (np.abs(yt[normal] - want) <= 3e-7 * np.abs(want)).all(), options
    if platform.machine() in ("x86_64", "AMD64"):
        assert not np.array_equal(*results)
