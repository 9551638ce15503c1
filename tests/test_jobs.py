"""The job mailbox of shared launches (kernels/share.h, nrpose.device.Jobs and
launch_shared): every block of every job is taken exactly once, by the calling thread
or a worker (standing or woken), with the job's own frame count; standing workers
serve jobs in a loop, return when idle or told to, and give way to other launches."""
import gc
import time

import numpy as np
import pytest
from launches import standing_workers_or_skip

from nrpose import device, diagnostics
from nrpose.errors import DeviceError, InputError

pytest.importorskip("pyopencl")

MARK = """#include "share.h"
/* who[b] = 2,000,000 (standing worker) or 1,000,000 (calling thread or a woken worker)
 * + BY + the job's frames, for each block b taken; `work` iterations of arithmetic per block */
__kernel void mark(__global int *who, const int work, volatile __global int *jobs, const int role)
{
    FOR_EACH_JOB(jobs, role) {
        FOR_EACH_BLOCK(b, jobs) {
            const int F = JOB_FRAMES_OF(jobs, job_tag_);
            float acc = 0.0f;
            for (int i = 0; i < work; ++i)
                acc = acc * 0.5f + (float)i;
            who[b] = (role > 0 ? 2000000 : 1000000) + BY + F + (acc < 0.0f);
        }
    }
}
"""
STANDING, CALLER = 2_000_000, 1_000_000


class Marker:
    """The `mark` kernel (marking blocks with `by` added) with its mailbox (or `jobs`, shared
    with another Marker) and a `who` array of `size` blocks."""

    def __init__(self, size: int = 4096, work: int = 200, jobs: device.Jobs | None = None, by: int = 0):
        import pyopencl as cl

        ctx, _ = device.context()
        self.kernel = cl.Kernel(cl.Program(ctx, device.with_headers(MARK)).build(options=[f"-DBY={by}"]),
                                "mark")
        self.jobs = jobs or device.Jobs()
        self.who = device.HostArray(size, dtype=np.int32)
        self.jobs.keep = (self.who,)
        self.kernel.set_args(self.who.arg, np.int32(work), self.jobs.box.arg, np.int32(0))

    def launch(self, blocks: int, frames: int = 1, **kw) -> np.ndarray:
        """who after one launch of `blocks` blocks (cleared first)."""
        self.who.host[:] = 0
        device.launch_shared(self.kernel, self.jobs, blocks, frames, **kw)
        return self.who.host.copy()


@pytest.fixture
def standby(monkeypatch):
    """Set the standby (microseconds) for the test; any standing worker is stopped after it."""
    monkeypatch.setattr(device.policy, "_STANDBY", [None])           # restored after the test
    yield lambda us: device.set_standby_s(us * 1e-6)
    device.stop_standing()


@pytest.mark.parametrize("ends", [False, True])
def test_every_block_once_with_its_frames_across_many_jobs(standby, ends):
    """2,100 shared launches (the 11-bit job tag wraps past 2,047) of 1-64 blocks and 1-5
    frames, one standing worker serving them in a loop: every block of every job taken
    once, with that job's frames, none beyond the job; the standing worker took some and
    the calling thread some. Taken from both ends (Jobs.ends), the standing worker's
    blocks of a job precede the calling thread's."""
    standing_workers_or_skip()
    standby(20_000)
    m = Marker()
    m.jobs.ends = ends
    takers = {STANDING: 0, CALLER: 0}
    for j in range(2100):
        blocks, frames = 1 + (j * 37) % 64, 1 + j % 5
        who = m.launch(blocks, frames, workers=True)
        assert np.all(who[:blocks] % 1000 == frames), j
        assert np.all(np.isin(who[:blocks] - frames, (STANDING, CALLER))), j
        assert not who[blocks:].any(), j
        if ends:
            by = who[:blocks] - frames
            assert not (np.flatnonzero(by == STANDING)[:, None] > np.flatnonzero(by == CALLER)).any(), (j, by)
        for k in takers:
            takers[k] += int(np.count_nonzero(who[:blocks] - frames == k))
    assert takers[STANDING] > 0 and takers[CALLER] > 0, takers


def test_idle_standing_worker_returns_and_a_later_launch_stands_again(standby):
    """With a 1 us standby the standing worker returns almost at once; the next job is
    then the calling thread's alone (none lost) and its launch stands a new worker."""
    standing_workers_or_skip()
    standby(1)
    m = Marker()
    m.launch(8, workers=True)
    deadline = time.perf_counter() + 5.0
    while m.jobs.box.host[device.JOB_STANDING] and time.perf_counter() < deadline:
        time.sleep(1e-3)
    assert not m.jobs.standing(m.kernel)
    standby(10_000_000)
    who = m.launch(40, 2, workers=True)
    assert np.all(np.isin(who[:40], (STANDING + 2, CALLER + 2))) and not who[40:].any()
    assert m.jobs.standing(m.kernel)


def test_timed_launch_spans_from_the_jobs_publication(standby, monkeypatch):
    """launch_shared(timed=True) with a standing worker serving: every block taken once
    (the calling thread's share on the profiling queue); published_span_s runs from the
    job's publication to the end of the calling thread's kernel: at least that kernel's
    own event time, at most the call's; an event older than the mailbox's last
    publication, or no clock to read, gives None."""
    standing_workers_or_skip()
    standby(200_000)
    m = Marker(work=20_000)
    m.launch(16, workers=True)              # stands the worker
    stood = []
    for _ in range(10):
        stood.append(m.jobs.standing(m.kernel))
        m.who.host[:] = 0
        t0 = device.event_clock_ns()
        events = device.launch_shared(m.kernel, m.jobs, 16, timed=True)
        t1 = device.event_clock_ns()
        span, ev = device.published_span_s(m.jobs, events[-1]), events[-1].profile
        assert span is not None and (ev.end - ev.start) * 1e-9 <= span <= (t1 - t0) * 1e-9
        assert np.all(np.isin(m.who.host[:16], (STANDING + 1, CALLER + 1))) and not m.who.host[16:].any()
    assert all(stood)
    m.jobs.publish(0, 1)                    # an empty job: the event is older now
    assert device.published_span_s(m.jobs, events[-1]) is None
    monkeypatch.setattr(device.timing, "EVENT_CLOCK", None)      # a Python without CLOCK_MONOTONIC_RAW
    events = device.launch_shared(m.kernel, m.jobs, 16, timed=True)
    assert device.published_span_s(m.jobs, events[-1]) is None


def test_a_standing_worker_serves_only_its_own_kernel(standby):
    """A mailbox's standing worker runs one kernel: a launch of another kernel on the same
    mailbox (a kernel variant) ends it before publishing, so every block is the new
    kernel's; so does a launch meant for the calling thread alone."""
    standing_workers_or_skip()
    standby(10_000_000)
    a = Marker()
    b = Marker(jobs=a.jobs, by=1000)
    b.who = a.who
    b.kernel.set_arg(0, a.who.arg)
    a.launch(64, workers=True)
    assert a.jobs.standing(a.kernel)
    who = b.launch(64, workers=True)
    assert np.all(np.isin(who[:64], (STANDING + 1001, CALLER + 1001)))
    assert b.jobs.standing(b.kernel) and not b.jobs.standing(a.kernel)
    for _ in range(20):
        who = a.launch(64, queues=(None, device.context()[1]))     # the calling thread's queue alone
        assert np.all(who[:64] == CALLER + 1)


def test_stop_ends_a_polling_worker_at_once(standby):
    """A standing worker that would poll for 10 s returns as soon as stop() asks."""
    standing_workers_or_skip()
    standby(10_000_000)
    m = Marker()
    m.launch(4, workers=True)
    assert m.jobs.standing(m.kernel) and device.standing_mailbox() is m.jobs
    t = time.perf_counter()
    m.jobs.stop()
    assert time.perf_counter() - t < 0.5
    assert m.jobs.box.host[device.JOB_STANDING] == 0 and device.standing_mailbox() is None


def test_standing_workers_give_way(standby):
    """One standing worker holds PoCL's worker device: another mailbox's shared launch
    ends it first; a launch on the calling thread alone leaves it standing; a launch on
    the workers' own queue (no calling thread) ends it too."""
    standing_workers_or_skip()
    standby(10_000_000)
    a, b = Marker(), Marker()
    a.launch(16, workers=True)
    assert a.jobs.standing(a.kernel)
    assert (b.launch(16, workers=True)[:16] >= CALLER).all()
    assert not a.jobs.standing(a.kernel) and b.jobs.standing(b.kernel)
    assert (a.launch(16, workers=False)[:16] == CALLER + 1).all()
    assert b.jobs.standing(b.kernel)
    who = a.launch(16, queues=(None, device.worker_queue()))
    assert (who[:16] == CALLER + 1).all() and device.standing_mailbox() is None


def test_alternating_mailboxes_do_not_hand_the_worker_back_and_forth(standby):
    """Two mailboxes launched in turn (two characters posed in turn): once each has had its
    standing worker ended by the other's launch, for device.STANDING_YIELD_S neither stands
    one (each would end the other's), and every block of every job is still taken once.
    Lowering the standby ends a worker standing longer."""
    standing_workers_or_skip()
    standby(10_000_000)
    a, b = Marker(), Marker(by=1000)
    stood = []
    for j in range(60):
        m, by = (a, 0) if j % 2 == 0 else (b, 1000)
        who = m.launch(48, 1 + j % 3)
        assert np.all(np.isin(who[:48] - by - (1 + j % 3), (STANDING, CALLER))) and not who[48:].any(), j
        stood.append(m.jobs.standing(m.kernel))
    # a's second launch stands a worker, b's second ends it and stands one; then, each
    # displaced by the other, neither stands
    assert stood[2] and stood[3] and not any(stood[4:]), stood
    device.stop_standing()
    a.jobs._displaced = float("-inf")
    a.launch(48)
    a.launch(48)                                      # in a loop again: stands
    assert a.jobs.standing(a.kernel)
    device.set_standby_s(1e-3)                        # lower than the 10 s it stands with
    assert device.standing_mailbox() is None and not a.jobs.standing(a.kernel)


def test_mailboxes_launched_in_blocks_in_turn_each_stand_again(standby):
    """Two mailboxes launched in blocks of launches in turn (two characters each posed for a
    few frames, then the other): within device.STANDING_YIELD_S of being displaced a mailbox
    stands a worker again once it has launched device.STANDING_RUN times in a row, so each
    block's later launches have one (before, the first mailbox never stood again); every
    block of every job is still taken once."""
    standing_workers_or_skip()
    standby(10_000_000)
    a, b = Marker(), Marker(by=1000)
    run = device.STANDING_RUN
    for block in range(6):
        m, by = (a, 0) if block % 2 == 0 else (b, 1000)
        stood = []
        for j in range(run + 6):
            who = m.launch(48)
            assert np.all(np.isin(who[:48] - by - 1, (STANDING, CALLER))) and not who[48:].any()
            stood.append(m.jobs.standing(m.kernel))
        if block >= 2:        # both have been displaced by now, within the yield window
            assert not any(stood[:run - 1]) and all(stood[run:]), (block, stood)


def test_standby_setting(standby, monkeypatch):
    """A standby of 0 wakes workers for each shared launch and leaves none standing.
    NRPOSE_STANDBY_US is read at the first launch (or set_standby_s(None)): a value that is
    not a number of microseconds from 0 to 10 s is a DeviceError naming the variable;
    set_standby_s takes seconds (InputError outside 0-10 s)."""
    standing_workers_or_skip()
    standby(0)
    m = Marker()
    who = m.launch(64, 3, workers=True)
    assert np.all(np.isin(who[:64], (CALLER + 3,))) and device.standing_mailbox() is None
    for bad in ("fast", "-5", "nan", "inf", "2e7"):
        monkeypatch.setenv("NRPOSE_STANDBY_US", bad)
        monkeypatch.setattr(device.policy, "_STANDBY", [None])          # not read yet
        with pytest.raises(DeviceError, match="NRPOSE_STANDBY_US must be a number of microseconds"):
            m.launch(4, workers=True)
    monkeypatch.setenv("NRPOSE_STANDBY_US", " 10000000 ")        # the longest: its polls fit an int
    assert device.set_standby_s(None) == 10.0
    assert (m.launch(4, workers=True)[:4] >= CALLER).all() and m.jobs.standing(m.kernel)
    monkeypatch.delenv("NRPOSE_STANDBY_US")
    assert device.set_standby_s(None) == device.STANDBY_S
    assert device.set_standby_s(0.25) == 0.25 and device.standby_s() == 0.25
    for bad in (-1e-6, 11.0, float("nan"), "0.5", True):
        with pytest.raises(InputError, match="standby must be a number of seconds from 0 to 10"):
            device.set_standby_s(bad)


def test_forked_child_forgets_the_standing_worker(standby):
    """A process forked while a worker stands has no such thread: stopping there (at exit,
    or a deformer's deletion) forgets it instead of waiting for ever."""
    standing_workers_or_skip()
    import os
    if not hasattr(os, "fork"):
        pytest.skip("no os.fork here")
    standby(10_000_000)
    m = Marker()
    m.launch(8, workers=True)
    assert m.jobs.standing(m.kernel)
    pid = os.fork()
    if pid == 0:                                           # the child: must not hang
        try:
            device.stop_standing()
            os._exit(0 if device.standing_mailbox() is None else 1)
        finally:
            os._exit(2)
    deadline = time.perf_counter() + 20
    while time.perf_counter() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        time.sleep(0.01)
    else:
        os.kill(pid, 9)
        os.waitpid(pid, 0)
        pytest.fail("the forked child hung stopping the parent's standing worker")
    assert os.waitstatus_to_exitcode(status) == 0
    assert m.jobs.standing(m.kernel)                       # the parent's still stands


def test_too_many_blocks_for_the_mailbox():
    m = Marker(size=8)
    with pytest.raises(DeviceError, match="exceeds the job mailbox"):
        m.jobs.publish(1 << device.JOB_TAG_SHIFT, 1)


@pytest.mark.parametrize("kind", ["nrmls", "lbs"])
def test_deleted_deformer_leaves_no_standing_worker(standby, kind):
    """A deformer's standing worker reads its arrays: deleting the deformer ends it
    (Jobs(owner=...)), for the NR-MLS and the skinning deformers."""
    standing_workers_or_skip()
    from nrpose.pose.mls import Deformer
    from nrpose.model.handles import HandleSet
    from nrpose.pose.skinning import LbsSkinner

    standby(10_000_000)
    rng = np.random.default_rng(5)
    points = rng.uniform(-1, 3, (5000, 3))
    if kind == "nrmls":
        rest = HandleSet.make(segments=np.array([[[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [2, 0, 0]]], float))
        dev = Deformer(points, rest)
    else:
        dev = LbsSkinner(points, rng.integers(0, 3, (5000, 2)), rng.uniform(0.1, 1, (5000, 2)))
        dev.pose(np.repeat(np.eye(4)[None], 3, axis=0))
    diagnostics.relaunch(dev, workers=True)
    assert dev._jobs.standing(dev._kernel)
    jobs = dev._jobs
    del dev
    gc.collect()
    assert device.standing_mailbox() is None and jobs.box.host[device.JOB_STANDING] == 0


CLAIM = """#include "share.h"
__kernel void claim(__global int *out, const int tag, volatile __global int *jobs, const int role)
{
    out[0] = take_block(jobs, tag, role);
}
"""
END = 1 << device.JOB_END_BITS      # a block taken from a job's end, in its counter


@pytest.mark.parametrize("next_tag,next_block,blocks,other,tag,taken,ends,role", [
    (5, 3, 10, 0, 5, 3, 0, 0),              # the job's own tag: block 3 taken
    (5, 3, 10, 0, 4, -1, 0, 0),             # the last job's tag: nothing, whatever the counts
    (5, 10, 10, 0, 5, -1, 0, 0),            # no block left
    (6, device.JOB_CLOSED, device.JOB_CLOSED - 1, 0, 6, -1, 0, 0),   # none to take
    # the last job (tag 4) all taken while the next one's descriptor is filled, not yet
    # opened: a work-item holding tag 4 reads its own job's count, not the new one's
    (4, 7, 7, 1000, 4, -1, 0, 0),
    # from both ends: 2 taken from the start, 3 from the end; a standing worker takes the
    # start's next (2), the calling thread the end's (10 - 1 - 3 = 6)
    (5, 2 + 3 * END, 10, 0, 5, 2, 1, 7),
    (5, 2 + 3 * END, 10, 0, 5, 6, 1, 0),
    (5, 4 + 6 * END, 10, 0, 5, -1, 1, 0),   # the ends met: nothing left for either
    (5, 4 + 6 * END, 10, 0, 5, -1, 1, 7),
    (5, 4 + 5 * END, 10, 0, 5, 4, 1, 0),    # the last block, from the end
    (5, 9, 10, 0, 5, 9, 0, 0),              # not from both ends: the calling thread takes the next
])
def test_a_block_is_taken_only_under_its_jobs_tag(next_tag, next_block, blocks, other, tag, taken, ends, role):
    """share.h take_block: a block is taken (the counter advanced) only when the job's tag
    matches the taker's and a block is left in the descriptor of that tag's parity (the
    other one, ``other`` blocks, may hold the next job's); in a job taken from both ends
    (its descriptor's third int), a standing worker (role > 0) takes the next block from
    its start, the calling thread (role 0) from its end, each counted in its own field."""
    import pyopencl as cl

    ctx, queue = device.context()
    kernel = cl.Kernel(cl.Program(ctx, device.with_headers(CLAIM)).build(), "claim")
    jobs, out = device.HostArray(device.JOB_INTS, dtype=np.int32, atomics=True), device.HostArray(1, dtype=np.int32)
    jobs.host[:] = 0
    jobs.host[device.JOB_NEXT] = next_tag << device.JOB_TAG_SHIFT | next_block
    jobs.host[device.JOB_DESCS[next_tag & 1]] = blocks
    jobs.host[device.JOB_DESCS[next_tag & 1] + 2] = ends
    jobs.host[device.JOB_DESCS[1 - (next_tag & 1)]] = other
    jobs.upload()
    kernel.set_args(out.arg, np.int32(tag), jobs.arg, np.int32(role))
    cl.enqueue_nd_range_kernel(queue, kernel, (1,), (1,))
    out.download()
    jobs.download()
    assert out.host[0] == taken
    step = (END if ends and role == 0 else 1) if taken >= 0 else 0
    assert jobs.host[device.JOB_NEXT] & ((1 << device.JOB_TAG_SHIFT) - 1) == next_block + step


def test_publish_opens_the_job_in_one_write_after_its_descriptor(monkeypatch):
    """Jobs.publish fills the descriptor of the new tag's parity (blocks, frames) and zeroes
    the done count, reads the clock (timed), then opens the job with its one write to the
    block counter: at block 0, or at the prologue; each job gets a new tag (1..2047,
    cycling), so that consecutive jobs use the two descriptors in turn."""
    jobs = device.Jobs()
    writes = []

    class Recorder(np.ndarray):
        def __setitem__(self, i, v):
            writes.append((i, int(v)))
            super().__setitem__(i, v)

    monkeypatch.setattr(device.mailbox, "event_clock_ns", lambda: writes.append("clock") or 1)
    jobs.box.host = jobs.box.host.view(Recorder)
    tags = []
    for blocks in (7, 3000):
        writes.clear()
        jobs.publish(blocks, 4, timed=True)
        tag = writes[-1][1] >> device.JOB_TAG_SHIFT
        tags.append(tag)
        desc = device.JOB_DESCS[tag & 1]
        assert sorted(writes[:4]) == sorted([(desc, blocks), (desc + 1, 4), (desc + 2, 0), (device.JOB_DONE, 0)])
        assert writes[4:] == ["clock", (device.JOB_NEXT, tag << device.JOB_TAG_SHIFT)]
    assert tags[1] == tags[0] + 1 and all(1 <= t <= 2047 for t in tags)
    writes.clear()
    jobs.publish(5, 2, prologue=True)           # opened at the prologue, not at block 0; no clock
    assert "clock" not in writes and [w for w in writes if w[0] == device.JOB_NEXT] == [writes[-1]]
    assert writes[-1] == (device.JOB_NEXT, (tags[1] + 1) << device.JOB_TAG_SHIFT | device.JOB_PROLOGUE)
    jobs._tag = 2047
    jobs.publish(1, 1)
    assert jobs.box.host[device.JOB_NEXT] >> device.JOB_TAG_SHIFT == 1
    jobs.ends = True                            # from both ends, up to JOB_ENDS_MAX_BLOCKS blocks
    for blocks in (device.JOB_ENDS_MAX_BLOCKS, device.JOB_ENDS_MAX_BLOCKS + 1):
        jobs.publish(blocks, 1)
        tag = jobs.box.host[device.JOB_NEXT] >> device.JOB_TAG_SHIFT
        assert jobs.box.host[device.JOB_DESCS[tag & 1] + 2] == (blocks <= device.JOB_ENDS_MAX_BLOCKS)


PROLOGUE = """#include "share.h"
/* A job with a prologue: the first work-item to arrive counts the run in state[1] (and in
 * state[2] if it is a standing worker), spins
 * `work` iterations, then writes the job's frames to state[0]; every block records
 * state[0] as it finds it (+ 2,000,000 standing worker, 1,000,000 otherwise). */
__kernel void staged(__global int *who, __global int *state, const int work, volatile __global int *jobs,
                     const int role)
{
    FOR_EACH_JOB(jobs, role) {
        if (claim_prologue(jobs, job_tag_)) {
            float acc = 0.0f;
            for (int i = 0; i < work; ++i)
                acc = acc * 0.5f + (float)i;
            state[1] += 1;
            state[2] += role > 0;
            state[0] = JOB_FRAMES_OF(jobs, job_tag_) + (acc < 0.0f);
            open_job(jobs, job_tag_);
        }
        FOR_EACH_BLOCK(b, jobs) {
            who[b] = (role > 0 ? 2000000 : 1000000) + state[0];
        }
    }
}
"""


@pytest.mark.parametrize("split", ["alone", "standing", "woken", "workers only"])
def test_a_jobs_prologue_runs_once_before_any_of_its_blocks(standby, split):
    """A job published with a prologue (launch_shared(prologue=True)): one work-item runs
    it, once per job, and no block of the job starts before it has finished (each block
    sees what it wrote), whoever runs it and the blocks: the calling thread alone, with
    a standing worker over 300 jobs in a loop (which then runs prologues, while the
    calling thread enters its kernel, and blocks too), with woken workers, on the
    workers alone."""
    import pyopencl as cl

    if split != "alone":
        standing_workers_or_skip()
    standby(20_000 if split == "standing" else 0)
    ctx, _ = device.context()
    kernel = cl.Kernel(cl.Program(ctx, device.with_headers(PROLOGUE)).build(), "staged")
    jobs = device.Jobs()
    who = device.HostArray(64, dtype=np.int32)
    state = device.HostArray(3, dtype=np.int32)
    jobs.keep = (who, state)
    kernel.set_args(who.arg, state.arg, np.int32(20_000), jobs.box.arg, np.int32(0))
    kw = {"alone": {"workers": False}, "standing": {"workers": True}, "woken": {"workers": True},
          "workers only": {"queues": (None, device.worker_queue())}}[split]
    takers = {STANDING: 0, CALLER: 0}
    state.host[1:] = 0
    launches = 300 if split == "standing" else 20
    for j in range(launches):
        blocks, frames = 1 + (j * 7) % 40, 1 + j % 5
        who.host[:] = 0
        state.host[0] = -1                   # stale, until the prologue writes the frames
        device.launch_shared(kernel, jobs, blocks, frames, prologue=True, **kw)
        assert state.host[1] == j + 1, j     # one prologue per job
        got = who.host.copy()
        assert np.all(got[:blocks] % 1_000_000 == frames), (j, got[:blocks])
        assert not got[blocks:].any(), j
        for k in takers:
            takers[k] += int(np.count_nonzero(got[:blocks] - frames == k))
    jobs.stop()
    if split == "standing":                  # the worker polls: it sees the job first
        assert takers[STANDING] > 0 and takers[CALLER] > 0, takers
        assert state.host[2] > 0, state.host[2]      # and runs prologues (143 of 300 in a CI run, over 150 here)


def test_plain_launches_run_the_prologue_once_before_the_blocks():
    """Plain OpenCL launches (Jobs.plain, share.h PLAIN_OPENCL, as on devices other than
    PoCL on x86): the prologue's own launch runs it once per job before any block, each
    block is taken once; the prologue's clone follows the kernel's arguments when the
    owner sets them through set_argument, and is made again after arguments_changed."""
    import pyopencl as cl

    ctx, _ = device.context()
    kernel = cl.Kernel(cl.Program(ctx, device.with_headers(PROLOGUE)).build(["-DPLAIN_OPENCL"]), "staged")
    jobs = device.Jobs()
    jobs.plain = True
    who = device.HostArray(64, dtype=np.int32)
    states = [device.HostArray(3, dtype=np.int32) for _ in range(3)]
    jobs.keep = (who, *states)
    kernel.set_args(who.arg, states[0].arg, np.int32(2_000), jobs.box.arg, np.int32(0))
    for j in range(24):
        state = states[min(j // 8, 2)]
        if j == 8:
            jobs.set_argument(kernel, 1, state.arg)
        elif j == 16:
            jobs.arguments_changed()
            kernel.set_arg(1, state.arg)
        blocks, frames = 1 + (j * 7) % 40, 1 + j % 5
        who.host[:] = 0
        state.host[:] = [-1, 0, 0]          # stale, until the prologue writes the frames
        device.launch_shared(kernel, jobs, blocks, frames, prologue=True)
        assert list(state.host[1:]) == [1, 0], j     # one prologue, the prologue launch's
        got = who.host.copy()
        assert np.all(got[:blocks] == CALLER + frames), (j, got[:blocks])
        assert not got[blocks:].any(), j


CLAIM_PROLOGUE = """#include "share.h"
__kernel void claim2(__global int *out, const int tag, volatile __global int *jobs)
{
    out[0] = claim_prologue(jobs, tag);
    out[1] = claim_prologue(jobs, tag);
}
"""


@pytest.mark.parametrize("state,tag,claimed", [
    (device.JOB_PROLOGUE, 5, 1),            # published with a prologue: the first claim wins
    (device.JOB_PROLOGUE, 4, 0),            # the last job's tag: no
    (device.JOB_IN_PROLOGUE, 5, 0),         # already claimed
    (0, 5, 0),                              # open (no prologue, or it is done)
])
def test_a_prologue_is_claimed_once_under_its_jobs_tag(state, tag, claimed):
    """share.h claim_prologue: only a job waiting for its prologue, under the claimer's tag,
    is claimed, and then only once (the state becomes JOB_IN_PROLOGUE)."""
    import pyopencl as cl

    ctx, queue = device.context()
    kernel = cl.Kernel(cl.Program(ctx, device.with_headers(CLAIM_PROLOGUE)).build(), "claim2")
    jobs, out = device.HostArray(device.JOB_INTS, dtype=np.int32, atomics=True), device.HostArray(2, dtype=np.int32)
    jobs.host[:] = 0
    jobs.host[device.JOB_NEXT] = 5 << device.JOB_TAG_SHIFT | state
    jobs.host[device.JOB_DESCS[5 & 1]] = 10
    jobs.upload()
    kernel.set_args(out.arg, np.int32(tag), jobs.arg)
    cl.enqueue_nd_range_kernel(queue, kernel, (1,), (1,))
    out.download()
    jobs.download()
    assert list(out.host) == [claimed, 0]
    assert jobs.host[device.JOB_NEXT] & ((1 << device.JOB_TAG_SHIFT) - 1) == (
        device.JOB_IN_PROLOGUE if claimed else state)


def test_deformers_posed_from_two_threads(standby, monkeypatch):
    """Launches and the standing worker's state are taken one thread at a time
    (device._LAUNCHES): two deformers posed from two threads at once, each many times,
    give each pose's single-threaded result, no launch waits for ever, and no standing
    worker is left polling once the standing one is stopped."""
    import threading

    from nrpose.pose.mls import Deformer
    from nrpose.model.handles import HandleSet, Pose

    standby(10_000_000)
    rng = np.random.default_rng(9)
    rest = HandleSet.make(segments=np.array([[[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [2, 0, 0]]], float))
    deformers = [Deformer(rng.uniform(-1, 3, (3000 + 500 * i, 3)), rest) for i in range(2)]
    poses = []
    for angle in np.linspace(0.1, 1.5, 6):
        c, s = np.cos(angle), np.sin(angle)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        poses.append(Pose.make(rest, segments=[[[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [1 + c, s, 0]]],
                               rotations=[np.eye(3), R]))
    want = [[d.pose(p).copy() for p in poses] for d in deformers]
    errors, spans = [], []
    inner = device.launch._launch_shared

    def timed(*args):          # each launch's span, widened by a sleep that releases the GIL
        start = time.perf_counter()
        time.sleep(1e-4)
        events = inner(*args)
        spans.append((start, time.perf_counter()))
        return events

    monkeypatch.setattr(device.launch, "_launch_shared", timed)

    def run(i):
        try:
            for r in range(60):
                j = (r + i) % len(poses)
                got = deformers[i].pose(poses[j])
                if not np.array_equal(got, want[i][j]):
                    errors.append((i, r))
        except Exception as exc:       # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not any(t.is_alive() for t in threads) and errors == []
    spans.sort()
    assert len(spans) == 120 and all(a[1] <= b[0] for a, b in zip(spans, spans[1:]))   # one at a time
    # every standing worker stood was tracked, and so is ended here (unlocked, two threads
    # standing workers at once lost track of one, which polled on for its whole standby)
    device.stop_standing()
    assert all(d._jobs.box.host[device.JOB_STANDING] == 0 for d in deformers)
