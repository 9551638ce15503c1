"""The local runner: a pool of worker processes on this machine.

Each worker is a fresh (spawned) process that runs one job at a time
(:func:`nrpose.cli.bake.worker.run_job`) and keeps what it loaded and bound. The
driver hands an idle worker a job of the binding it already holds, else of a
binding no other worker holds (of a character it has loaded, else of one no
other worker has loaded, else the one with the most jobs left), else of the
binding with the most jobs left: each character is loaded and bound once per
worker that poses it, characters tend to stay with one worker, and the workers
share the last bindings at the end.

PoCL threads: each worker gets ``CPUs // workers`` threads (the PoCL device
list and thread count of :func:`nrpose.device.pocl_settings`, for that many
CPUs, unpinned), so workers × threads = CPUs. Variables the user set are kept.

A worker that dies (killed, out of memory, a crash in a driver library) is
replaced and its job given to another worker, up to :data:`MAX_ATTEMPTS` times;
its partial output stays in its scratch directory, never under the output's name.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
from collections import deque
from multiprocessing.connection import wait
from pathlib import Path

from ...device import pocl_settings, usable_cpus

MAX_ATTEMPTS = 3


def thread_settings(workers: int, cpus: int | None = None) -> dict[str, str]:
    """PoCL variables for one of ``workers`` worker processes sharing ``cpus`` CPUs."""
    return pocl_settings(cpus=max(1, (cpus or usable_cpus()) // max(workers, 1)))


def _worker_main(conn, env: dict, outdir: str) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # the driver stops the workers
    os.environ.update(env)                           # before PoCL starts in this process
    from .. import map_large_blocks
    from .worker import WorkerCache, run_job

    map_large_blocks()                               # a whole-job process, as the nrpose program

    cache = WorkerCache()
    while True:
        try:
            job = conn.recv()
        except EOFError:
            return
        if job is None:
            return
        conn.send(run_job(job, Path(outdir), cache))


class _Slot:
    def __init__(self, ctx, env: dict, outdir: Path):
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(child, env, str(outdir)), daemon=True)
        self.process.start()
        child.close()
        self.job = None
        self.bound: list[tuple] = []       # bind keys this worker has posed, most recent last


class _Queue:
    """Jobs left, by bind key (insertion order: the JOBS file's)."""

    def __init__(self, jobs):
        self.by_key: dict[tuple, deque] = {}
        for job in jobs:
            self.by_key.setdefault(job.bind_key, deque()).append(job)

    def __bool__(self) -> bool:
        return any(self.by_key.values())

    def put_back(self, job) -> None:
        self.by_key.setdefault(job.bind_key, deque()).appendleft(job)

    def take(self, slot: _Slot, slots: list[_Slot]):
        left = {k: q for k, q in self.by_key.items() if q}
        if not left:
            return None
        mine = [k for k in reversed(slot.bound) if k in left]
        if mine:
            key = mine[0]
        else:
            others = [s for s in slots if s is not slot]
            held = {k for s in others for k in s.bound} | {s.job.bind_key for s in others if s.job}
            loaded = {k[:2] for k in slot.bound}
            free = [k for k in left if k not in held] or list(left)
            # its own characters first, then characters no other worker has loaded, then the most jobs
            key = max(free, key=lambda k: (k[:2] in loaded, k[:2] not in {h[:2] for h in held}, len(left[k])))
        return left[key].popleft()


def run_local(jobs, outdir: Path, workers: int, on_result) -> None:
    """Run ``jobs`` on ``workers`` processes; ``on_result(record)`` for each job, in completion order.

    A KeyboardInterrupt stops the workers and propagates.
    """
    ctx = multiprocessing.get_context("spawn")
    workers = max(1, min(workers, len(jobs)))
    env = thread_settings(workers)
    queue, attempts = _Queue(jobs), {job.index: 0 for job in jobs}
    slots = [_Slot(ctx, env, outdir) for _ in range(workers)]
    try:
        while True:
            for i, slot in enumerate(slots):
                if slot.job is None and queue:
                    if not slot.process.is_alive():       # died between jobs, or after losing one
                        slot.conn.close()
                        slots[i] = slot = _Slot(ctx, env, outdir)
                    slot.job = queue.take(slot, slots)
                    attempts[slot.job.index] += 1
                    try:
                        slot.conn.send(slot.job)
                    except OSError:                       # died just now: its sentinel says so below
                        pass
            busy = [s for s in slots if s.job is not None]
            if not busy:
                break
            ready = set(wait([s.conn for s in busy] + [s.process.sentinel for s in busy]))
            for i, slot in enumerate(slots):
                if slot.job is None:
                    continue
                record = None
                if slot.conn in ready or slot.process.sentinel in ready:
                    try:
                        if slot.conn.poll():
                            record = slot.conn.recv()
                    except (EOFError, OSError):
                        record = None
                if record is not None:
                    if slot.job.bind_key in slot.bound:
                        slot.bound.remove(slot.job.bind_key)
                    slot.bound.append(slot.job.bind_key)
                    record["attempts"] = attempts[slot.job.index]
                    slot.job = None
                    on_result(record)
                elif slot.process.sentinel in ready:      # died with the job
                    slot.process.join(5)
                    job, code = slot.job, slot.process.exitcode
                    slot.job = None
                    if attempts[job.index] < MAX_ATTEMPTS:
                        queue.put_back(job)           # a new worker takes this slot for it
                    else:
                        on_result(dict(_lost(job, code), attempts=attempts[job.index]))
    finally:
        for slot in slots:
            if slot.process.is_alive():
                slot.process.terminate()
        for slot in slots:
            slot.process.join(5)
            slot.conn.close()


def _lost(job, exitcode) -> dict:
    from .worker import failed_record

    how = f"signal {-exitcode}" if exitcode is not None and exitcode < 0 else f"exit status {exitcode}"
    return failed_record(job, f"the worker process died ({how}) on each of {MAX_ATTEMPTS} attempts")
