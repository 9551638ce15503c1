"""The Ray runner: the same jobs as Ray tasks, on a cluster or a local Ray instance.

* Each character is loaded once, by a Ray task (:func:`load`), and each binding
  made once, by a Ray task (:func:`bind`) taking the loaded character: its
  result, the :class:`~nrpose.pose.poser.CharacterPoser`'s host binding (the
  character, weights, handles: numpy arrays and small objects; pickling drops
  the device objects), lives in the object store.
* A pose task (:func:`pose_chunk`) runs a few jobs of one binding
  (:func:`nrpose.cli.bake.worker.run_job`) and takes the binding's reference as
  an argument: Ray moves it to a node once, the node's workers read its arrays
  from shared memory. A Ray worker process builds the device part (rest terms,
  buffers, programs) of a binding it has not posed yet, and keeps it: later
  tasks of the binding in that process reuse it (unpickling builds nothing).
* Tasks are retried on worker or node loss (``max_retries``; a lost character
  or binding is made again from its task); outputs are written under a scratch name and
  renamed to their deterministic name, so a retry never leaves two files or a
  partial one. OUTDIR must be one directory on every node (a shared filesystem).
* A task returns small records (no arrays) to the driver.
* Each task takes one CPU and poses with one PoCL thread, so tasks × threads =
  the cluster's CPUs (set in the worker process before PoCL starts there, from
  that node's environment: a variable set on the node is kept).
"""
from __future__ import annotations

import importlib.util
import logging
import math
import os
import socket
import time
from pathlib import Path

from ...errors import InputError

#: task attempts after the first on worker or node loss
MAX_RETRIES = 3
#: pose tasks per cluster CPU (smaller chunks: finer balance, more task overhead)
CHUNKS_PER_CPU = 4

_CACHE = None       # the WorkerCache of this Ray worker process


class Made:
    """A load or bind task's result: the character or poser, or the one-line error that stopped it."""

    def __init__(self, value=None, error: str | None = None):
        self.value, self.error = value, error


def check_ray() -> None:
    """InputError with the install hint when Ray is not installed."""
    if importlib.util.find_spec("ray") is None:
        raise InputError("--ray needs Ray: pip install 'nrpose[ray]'")


def _threads() -> None:
    """One PoCL thread in this worker process (tasks × threads = CPUs), set before PoCL starts."""
    from .local import thread_settings

    for k, v in thread_settings(1, 1).items():
        os.environ.setdefault(k, v)


def _made(make) -> Made:
    from ...errors import NrposeError

    try:
        return Made(make())
    except NrposeError as exc:
        return Made(error=str(exc))
    except OSError as exc:
        return Made(error=f"{exc.filename or ''}: {exc.strerror or exc}")


def _cache():
    """The WorkerCache of this Ray worker process."""
    from .worker import WorkerCache

    global _CACHE
    if _CACHE is None:
        _CACHE = WorkerCache()
    return _CACHE


def load(job) -> Made:
    """Ray task: the character of ``job``."""
    _threads()
    from ...io import load_character

    return _made(lambda: load_character(job.character, job.skeleton))


def bind(loaded: Made, job) -> Made:
    """Ray task: the poser of ``job``'s binding (kept in this process's cache too)."""
    _threads()
    if loaded.error is not None:
        return loaded
    cache = _cache()
    cache.adopt(job, character=loaded.value)
    return _made(lambda: cache.poser(job, loaded.value)[0])


def pose_chunk(bound: Made, jobs: list, outdir: str) -> list[dict]:
    """Ray task: run jobs of one binding (``bound``: the :func:`bind` result); their records."""
    import ray

    _threads()
    from .worker import failed_record, run_job

    cache = _cache()
    node = f"{socket.gethostname()}/{ray.get_runtime_context().get_node_id()[:8]}"
    if bound.error is not None:
        return [failed_record(job, bound.error, None, node) for job in jobs]
    t0, adopted = time.perf_counter(), jobs[0].bind_key not in cache.posers
    if adopted:
        bound.value.deformer        # the device part, built in this process
        cache.adopt(jobs[0], poser=bound.value)
    seconds = time.perf_counter() - t0
    records = [run_job(job, Path(outdir), cache, node=node) for job in jobs]
    if adopted:     # the device build counts as the first job's binding
        records[0]["bind_seconds"] += seconds
    return records


def chunks(jobs: list, cpus: int) -> list[list]:
    """Jobs cut into chunks of one binding each, about CHUNKS_PER_CPU per CPU."""
    size = max(1, math.ceil(len(jobs) / (CHUNKS_PER_CPU * max(cpus, 1))))
    by_key: dict[tuple, list] = {}
    for job in jobs:
        by_key.setdefault(job.bind_key, []).append(job)
    return [group[i:i + size] for group in by_key.values() for i in range(0, len(group), size)]


def run_ray(jobs: list, outdir: Path, address: str | None, on_result) -> None:
    """Run ``jobs`` as Ray tasks on the cluster at ``address`` (None: start a local Ray instance);
    ``on_result(record)`` for each job. A KeyboardInterrupt cancels the tasks and propagates."""
    import ray

    from .worker import failed_record

    kwargs = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    ray.init(address=address or "local", **kwargs)    # "local": a new instance, not a running cluster
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        load_task = ray.remote(load).options(num_cpus=1, max_retries=MAX_RETRIES)
        bind_task = ray.remote(bind).options(num_cpus=1, max_retries=MAX_RETRIES)
        pose_task = ray.remote(pose_chunk).options(num_cpus=1, max_retries=MAX_RETRIES)
        characters, bindings, pending = {}, {}, {}

        def submit(chunk: list, attempt: int, reload: bool = False) -> None:
            job = chunk[0]
            if reload or job.load_key not in characters:
                characters[job.load_key] = load_task.remote(job)
            if reload or job.bind_key not in bindings:
                bindings[job.bind_key] = bind_task.remote(characters[job.load_key], job)
            pending[pose_task.remote(bindings[job.bind_key], chunk, str(outdir))] = (chunk, attempt)

        for chunk in chunks(jobs, cpus):
            submit(chunk, 1)
        try:
            while pending:
                # what finished within a moment, in one call: one call per result would cost
                # O(pending) each, quadratic in the chunks
                ready, _ = ray.wait(list(pending), num_returns=1)
                more, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0.05)
                ready = list(dict.fromkeys(ready + more))
                for ref in ready:
                    chunk, attempt = pending.pop(ref)
                    try:
                        records = ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        # Ray's own retries are spent, or an object was lost with its owner or node:
                        # submit again (with the character loaded and bound anew) a few times, then record
                        if attempt <= MAX_RETRIES:
                            submit(chunk, attempt + 1, reload=True)
                            continue
                        error = f"Ray could not run the job ({_cause(exc)}, {attempt} attempts)"
                        records = [failed_record(job, error) for job in chunk]
                    for record in records:
                        on_result(record)
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    finally:
        ray.shutdown()


def _cause(exc) -> str:
    """The name of the error behind a Ray error (task errors wrap it)."""
    cause = getattr(exc, "cause", None)
    return type(cause).__name__ if isinstance(cause, BaseException) else type(exc).__name__
