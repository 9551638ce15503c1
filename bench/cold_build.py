"""Cold build of each program `nrpose pose` compiles: every round a fresh process with an
empty PoCL cache and binding cache (which keeps program binaries) per program, the programs
in turn.

    python bench/cold_build.py [--rounds 5] [--methods nrmls,lbs,dqs,cor] [--json bench/results/cold_build.json]

Why: a process whose PoCL cache does not hold a program pays its whole compile (the first
run after an install or a kernel change, a fresh container); that compile, not the pose,
bounds a cold `nrpose pose`. Per program (the NR-MLS pose kernel as every skeleton of more
than SKELETON_K bones builds it, LBS, DQS, CoR), one process each round measures, in
order: importing nrpose.device and creating the OpenCL context; the build (`nrpose.device.program`'s: every device of
the context, from source); compiling the kernel for each device (`nrpose.device.warm_up`,
which `nrpose.device.prefetch` runs after the build: PoCL compiles a kernel's work-group
function at its first launch on each device); and the peak RSS before and after. Each
phase's wall time and the process's CPU time (the worker device compiles on PoCL's
worker thread) in ms, medians over the rounds, with p10 / p90. A bad argument: one line on
stderr, exit status 2.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import common

#: the `nrpose pose` methods whose programs are measured (program_of)
METHODS = ("nrmls", "lbs", "dqs", "cor")
#: what each process times, in order: importing nrpose.device and creating the context, the
#: build, the compile of its kernels for each device
PHASES = ("context", "build", "warm_up")


def program_of(method: str) -> tuple[str, tuple[str, ...]]:
    """(kernel file, build options) of the program `nrpose pose --method` compiles; for
    nrmls, the pose kernel of a skeleton of more than SKELETON_K bones (sparse, k slots)."""
    from nrpose.bind.bone_weights import SKELETON_K
    from nrpose.pose import mls, skinning

    if method == "nrmls":
        S = SKELETON_K + 1
        return "nrmls.cl", mls.kernel_options(mls.lanes_for(S), 0, S, SKELETON_K, "weight", True, False)
    return skinning.PROGRAMS[method]


def child(method: str) -> dict:
    """One cold build of ``method``'s program in this process (its PoCL cache empty):
    {phase: {"wall_ms", "cpu_ms"}}, "rss_mb_before", "rss_mb_after", "program", "options"."""
    def mark():
        return time.perf_counter(), time.process_time()

    out = {}
    t = mark()
    from nrpose import device
    name, options = program_of(method)
    device.context()
    for phase in PHASES:
        if phase == "build":
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            prg = device.program(name, options)
        elif phase == "warm_up":
            device.warm_up(prg, device.kernel_source(name))
        u = mark()
        out[phase] = {"wall_ms": 1e3 * (u[0] - t[0]), "cpu_ms": 1e3 * (u[1] - t[1])}
        t = u
    return {**out, "rss_mb_before": rss, "rss_mb_after": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "program": name, "options": list(options)}


def run(rounds: int, methods=METHODS) -> dict:
    """``rounds`` rounds of a fresh process per method of ``methods`` (:func:`child`), the
    methods in turn."""
    samples = {m: [] for m in methods}
    load0, cpu0 = common.load(), common.cpu_times()
    for r in range(rounds):
        for m in (methods if r % 2 == 0 else methods[::-1]):
            with tempfile.TemporaryDirectory() as cache:
                # both caches empty: PoCL's, and nrpose's of program binaries (the binding cache)
                env = dict(os.environ, POCL_CACHE_DIR=os.path.join(cache, "pocl"),
                           NRPOSE_CACHE_DIR=os.path.join(cache, "nrpose"))
                got = subprocess.run([sys.executable, __file__, "--child", m], env=env, capture_output=True,
                                     text=True, check=True)
                samples[m].append(json.loads(got.stdout.splitlines()[-1]))
    programs = {}
    for m, runs in samples.items():
        row = {"program": runs[0]["program"], "options": runs[0]["options"]}
        for phase in PHASES:
            for what in ("wall_ms", "cpu_ms"):
                row[f"{phase}_{what}"] = common.quantiles([s[phase][what] for s in runs])
        for what in ("rss_mb_before", "rss_mb_after"):
            row[what] = common.quantiles([s[what] for s in runs])
        programs[m] = row
    return {"benchmark": "cold_build", "date": common.now(), "rounds": rounds,
            "environment": common.environment(), "load_before": load0, "load_after": common.load(),
            "cpu_steal_percent": common.steal_percent(cpu0, common.cpu_times()), "programs": programs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5, help="processes per program (default 5)")
    ap.add_argument("--json", default=str(common.HERE / "results" / "cold_build.json"), help="write the record here")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated (default: all four)")
    ap.add_argument("--child", choices=METHODS, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child)))
        return 0
    methods = tuple(m.strip() for m in a.methods.split(",") if m.strip())
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods or a.rounds < 1:
        print(f"cold_build: unknown method {bad[0] if bad else '(none)'!r}; choose from {', '.join(METHODS)}"
              if bad or not methods else "cold_build: --rounds must be at least 1", file=sys.stderr)
        return 2
    doc = run(a.rounds, methods)
    for m, row in doc["programs"].items():
        print(f"{m:6s} " + "  ".join(f"{p} {row[f'{p}_wall_ms']['median']:.0f} ms (cpu {row[f'{p}_cpu_ms']['median']:.0f})"
                                     for p in PHASES) + f"  rss {row['rss_mb_after']['median']:.0f} MB")
    common.write_record(doc, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
