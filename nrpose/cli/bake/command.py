"""``nrpose bake JOBS.json -o OUTDIR [--workers N] [--ray [ADDRESS]] [--resume] [--summary S.json]
[--max-frames F] [--max-output-values V]`` (the budget of ``nrpose pose``, per job).

Exit status: 0 when every job is done, 1 when a job failed (each failure is
one line on stderr; the other jobs still run), 2 for a bad JOBS file or bad
options (nothing run), 130 when interrupted (the finished outputs stay in the
manifest: run again with ``--resume`` to do the rest). One bake at a time per
OUTDIR (a second one is refused: the driver holds a lock on OUTDIR).
"""
from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
import signal
import sys
import warnings
from dataclasses import replace
from pathlib import Path

from .jobs import load_jobs
from .manifest import Manifest, clear_scratch
from .progress import Progress, summary
from ...device import usable_cpus
from ...errors import InputError
from ...io.files import atomic_path, check_writable
from ..common import add_budget_options, check_budget


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``bake`` subcommand to an argparse subparsers object."""
    p = subparsers.add_parser("bake", help="pose a library of jobs (characters × clips × methods) in parallel, "
                                           "locally or on a Ray cluster")
    p.add_argument("jobs", help="JOBS.json (schema: docs/bake.md)")
    p.add_argument("-o", "--output", required=True, help="OUTDIR: outputs, manifest.json")
    p.add_argument("--workers", type=int, help="local worker processes (default: the CPUs)")
    p.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                   help="run on Ray: the cluster at ADDRESS, or a local Ray instance without one")
    p.add_argument("--resume", action="store_true",
                   help="skip jobs whose output is in the manifest and unchanged; redo the rest")
    p.add_argument("--summary", help="write every job's status, frames, seconds, worker and node as JSON")
    add_budget_options(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    """Run the bake; returns the exit status (0, 1 or 130). Raises NrposeError for bad input (status 2)."""
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers {args.workers}: expected at least 1")
    if args.ray is not None and args.workers is not None:
        raise InputError("--workers sets the local pool; on Ray the cluster's CPUs decide: drop one")
    if args.summary and Path(args.summary).suffix.lower() != ".json":
        raise InputError(f"--summary {args.summary}: the summary must end in .json")
    check_budget(args, 0, 0.0, args.jobs)
    budget = {"max_frames": args.max_frames, "max_output_values": args.max_output_values}
    jobs = [replace(job, **budget) for job in load_jobs(args.jobs)]
    outdir = Path(args.output)
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"{outdir}: is a file; OUTDIR must be a directory")
    if args.summary:
        check_writable(args.summary)
        _check_not_an_input(Path(args.summary), [args.jobs, *(f for job in jobs for f in job.inputs)])
    if args.ray is not None:
        from .ray_runner import check_ray
        check_ray()
    made = next((p for p in reversed([outdir, *outdir.parents]) if not p.exists()), None)
    outdir.mkdir(parents=True, exist_ok=True)
    try:
        return _locked(args, jobs, outdir.resolve())
    except BaseException:
        if made is not None:       # a failed run leaves no OUTDIR it made (its manifest could not be written...)
            shutil.rmtree(made, ignore_errors=True)
        raise


def _check_not_an_input(summary: Path, inputs: list) -> None:
    """InputError when --summary names the JOBS file or a file a job reads: the run would
    overwrite it."""
    for f in inputs:
        if Path(f).exists() and summary.exists() and os.path.samefile(summary, f):
            raise InputError(f"--summary {summary}: is {f}, an input of the bake; give another name")


def _locked(args, jobs, outdir: Path) -> int:
    lock = os.open(outdir, os.O_RDONLY)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(lock)
        raise InputError(f"{outdir}: another bake is writing there; wait for it or choose another OUTDIR") from None
    handler = signal.getsignal(signal.SIGINT)
    try:
        return _bake(args, jobs, outdir)
    finally:
        signal.signal(signal.SIGINT, handler)
        os.close(lock)


def _bake(args, jobs, outdir: Path) -> int:
    clear_scratch(outdir)              # a driver that died leaves its workers' scratch
    manifest = Manifest(outdir)
    if args.resume:
        skipped = {j.index for j in jobs if manifest.finished(j, outdir)}
    else:
        skipped = set()
        manifest.forget(jobs)
    todo = [j for j in jobs if j.index not in skipped]
    by_index = {j.index: j for j in jobs}
    records: dict[int, dict] = {}
    progress = Progress(len(todo))

    def on_result(record: dict) -> None:
        records[record["index"]] = record
        for message in record.get("warnings", ()):
            warnings.warn(message, RuntimeWarning, stacklevel=1)     # the command's one line of notes
        if record["status"] == "done":
            manifest.record(by_index[record["index"]], record["size"], record["sha256"], record["frames"])
        progress.update(record)

    workers = args.workers or usable_cpus()
    runner = "ray" if args.ray is not None else "local"
    interrupted = False
    try:
        if todo and args.ray is not None:
            from .ray_runner import run_ray
            run_ray(todo, outdir, None if args.ray == "local" else args.ray, on_result)
        elif todo:
            from .local import run_local
            run_local(todo, outdir, workers, on_result)
    except KeyboardInterrupt:
        interrupted = True
        signal.signal(signal.SIGINT, signal.SIG_IGN)    # a second Ctrl-C must not cut the clean-up short
    finally:
        try:
            manifest.save()
        finally:
            clear_scratch(outdir)
    # the summary before the failed jobs' lines: if it cannot be written, that is the run's one error line
    if args.summary:
        doc = summary(jobs, records, skipped, progress, runner, None if args.ray is not None else workers)
        with atomic_path(Path(args.summary)) as tmp:
            tmp.write_text(json.dumps(doc, indent=1) + "\n")
    if progress.tty and interrupted:
        print(file=sys.stderr)
    for job in jobs:
        r = records.get(job.index)
        if r is not None and r["status"] != "done":
            print(f"nrpose: bake: {job.label}: {r['error']}", file=sys.stderr)
    print(progress.final_line(len(skipped)))
    if interrupted:
        left = len(todo) - len(records)
        print(f"nrpose: bake: interrupted with {left} job(s) not run; run again with --resume to do them",
              file=sys.stderr)
        return 130
    return 1 if progress.failed else 0
