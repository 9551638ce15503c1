"""A fuzz campaign: cases ``0..N-1`` of a seed over ``W`` worker processes.

Workers are forked from this process; each runs its share of the cases (index ``i`` with
``i % W == w``) one at a time through a :class:`~tests.fuzzing.runner.Runner` and sends
the outcomes back. Cases are deterministic in ``(seed, index)``, so the parent rebuilds
a case to save its reproducer. :func:`run` returns the summary of
:meth:`~tests.fuzzing.runner.Collector.summary` plus timing; with ``out`` it also writes
it as JSON (every 30 s while running, and at the end).
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import queue
import shutil
import sys
import time
from pathlib import Path

from .cases import make_case
from .runner import GOOD, Collector, Outcome, Runner
from .seeds import make_seeds, shared_seeds

__all__ = ["run"]


def _worker(seed: int, start: int, step: int, count: int, deadline: float, use_shared: bool, commands, q) -> None:
    seeds, shared = make_seeds(), (shared_seeds() if use_shared else {})
    runner = Runner()
    try:
        for i in range(start, count, step):
            if time.time() > deadline:
                break
            try:
                case = make_case(seed, i, seeds, shared, commands)
            except Exception as exc:     # a mutator's own bug must not end the worker's share of cases
                print(f"fuzz: case {i}: the harness could not build it ({type(exc).__name__}: {exc})",
                      file=sys.stderr, flush=True)
                continue
            outcome, casedir = runner.run(case)
            q.put(outcome)
            if casedir.exists():
                shutil.rmtree(casedir, ignore_errors=True)
    finally:
        runner.close()
        q.put(None)


def run(seed: int = 0, count: int = 1000, workers: int = 1, minutes: float | None = None,
        repro_dir: str | Path | None = None, out: str | Path | None = None, use_shared: bool = False,
        progress=None, commands: dict[str, float] | None = None) -> dict:
    """Run up to ``count`` cases (or until ``minutes`` pass); the summary dict. ``commands``:
    the share of each command (default :data:`tests.fuzzing.cases.COMMANDS`)."""
    deadline = time.time() + 60 * minutes if minutes else float("inf")
    seeds, shared = make_seeds(), (shared_seeds() if use_shared else {})
    collector = Collector(repro_dir)
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    # not daemons: a case's child (forked from a worker) may start processes of its own (bake's pool)
    procs = [ctx.Process(target=_worker, args=(seed, w, workers, count, deadline, use_shared, commands, q))
             for w in range(workers)]
    t0 = time.time()
    for p in procs:
        p.start()
    alive, last_write = workers, time.time()
    while alive:
        try:
            o: Outcome | None = q.get(timeout=120)
        except queue.Empty:
            if not any(p.is_alive() for p in procs):
                break
            continue
        if o is None:
            alive -= 1
            continue
        case = make_case(seed, o.index, seeds, shared, commands) if o.outcome not in GOOD else None
        collector.add(o, case)
        if progress:
            progress(collector, o)
        if out and time.time() - last_write > 30:
            _write(out, collector, seed, t0, workers)
            last_write = time.time()
    for p in procs:
        p.join(timeout=60)
    summary = _write(out, collector, seed, t0, workers) if out else _summary(collector, seed, t0, workers)
    return summary


def _summary(collector: Collector, seed: int, t0: float, workers: int) -> dict:
    s = collector.summary()
    elapsed = time.time() - t0
    by_class: dict = {}
    for cmd in s["totals"].values():
        for kinds in cmd.values():
            for outcome, n in kinds.items():
                by_class[outcome] = by_class.get(outcome, 0) + n
    head = {"seed": seed, "workers": workers, "elapsed_s": round(elapsed, 1),
            "cases_per_s": round(s["cases"] / elapsed, 2) if elapsed else 0.0, "by_outcome": by_class,
            "pid": os.getpid()}
    return {**head, **s}


def _write(out, collector: Collector, seed: int, t0: float, workers: int) -> dict:
    summary = _summary(collector, seed, t0, workers)
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(summary, indent=1))
    tmp.replace(path)
    return summary
