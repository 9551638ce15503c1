"""Shared pieces of the benchmark suites: run metadata, timing statistics, output.

Reuses bench/table1.py's helpers (git, environment, statistics).
"""
from __future__ import annotations

import datetime as _dt
import os
import pathlib
import re
import resource
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
if str(HERE.parent) not in sys.path:
    sys.path.insert(0, str(HERE.parent))

import table1  # noqa: E402  (bench/table1.py: the colleague's Table-1 benchmark and helpers)

stats = table1.stats           # seconds -> {"median", "p10", "p90", "min", "max", "n"} in ms
git = table1.git


def quantiles(x) -> dict[str, float]:
    """{"median", "p10", "p90"}: the 50th, 10th and 90th percentiles (NumPy's linear
    interpolation) of the samples ``x`` (array-like of float, any shape, taken whole), in
    ``x``'s own units. For unitless samples such as paired time ratios; timings in seconds
    take :data:`stats`, which also converts to ms and adds min, max and n."""
    return {q: float(np.percentile(x, pc)) for q, pc in (("median", 50), ("p10", 10), ("p90", 90))}


def load() -> list[float]:
    """os.getloadavg() (1, 5, 15 min) as a list."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def cpu_times() -> list[int] | None:
    """The machine's cumulative CPU time counters in clock ticks, from the ``cpu`` line of
    /proc/stat (user, nice, system, idle, iowait, irq, softirq, steal); None where there
    is no /proc/stat."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    return [int(x) for x in fields[1:9]] if fields and fields[0] == "cpu" and len(fields) >= 9 else None


def steal_percent(before: list[int] | None, after: list[int] | None) -> float | None:
    """Share (%) of the CPU time between two :func:`cpu_times` readings that the
    hypervisor gave to other guests (steal): on a shared VM the measure of how
    contended the run was (timings taken at 30 % steal were ~2x slower at p90 on the
    2-core VM). None when unknown."""
    if before is None or after is None:
        return None
    d = [b - a for a, b in zip(before, after)]
    return round(100.0 * d[7] / sum(d), 1) if sum(d) > 0 else None


def peak_rss_gb() -> float:
    """Peak resident set size of this process so far, GB (Linux ru_maxrss is in KB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def environment() -> dict:
    """table1.environment() plus parsed PoCL / LLVM versions, CPU model and compute units."""
    env = table1.environment()
    dev = env["device"]
    pv = dev.get("platform_version", "")
    m = re.search(r"PoCL\s+(\S+)", pv)
    llvm = re.search(r"LLVM\s+([\d.]+)", pv)
    target = re.search(r"HSTR:\s*(\S+)", dev.get("device_version", ""))
    env.update({"pocl_version": m.group(1) if m else dev.get("driver_version"),
                "llvm_version": llvm.group(1) if llvm else None,
                "cpu": env.get("processor"), "compute_units": dev.get("threads", dev.get("compute_units")),
                "device_target": target.group(1) if target else None,
                "memory_gb": _mem_total_gb()})
    return env


def _mem_total_gb():
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemTotal"):
                return round(int(line.split()[1]) / 1e6, 2)
    except OSError:
        pass
    return None


def table1_row(model: str, kind: str, data: pathlib.Path, poses: int = 1, seed: int = 0,
               quick: bool = False) -> tuple:
    """A Table-1 row as table1.py builds it: (points (N, 3) float64, rest HandleSet, bounding-box
    diagonal, ``poses`` Pose objects of the row's kind drawn from ``seed``); quick: 500 points."""
    from nrpose.model.handles import Pose

    name, count, handles, _, rel = next(r for r in table1.TABLE1 if r[0] == model)
    v, _ = table1.load_model(name, count, rel, pathlib.Path(data), quick)
    rest = table1.chain_handles(v, handles) if kind == "segments" else table1.fps_handles(v, handles)
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    rng = np.random.default_rng(seed)
    make = (lambda: table1.chain_pose_args(rest, rng)) if kind == "segments" else (
        lambda: table1.point_pose_args(rest, rng, diag))
    return v, rest, diag, [Pose.make(rest, **make()) for _ in range(poses)]


def now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def add_rows_arguments(ap, rounds: int, poses: int, what: str) -> list[str]:
    """The options of the in-process A/B benchmarks over Table-1 rows (standby_ab.py,
    commit_ab.py) on the argparse parser ``ap``: --rows, --rounds, --poses (defaults
    ``rounds``, ``poses``; ``what`` names the two sides), --quick, --data, --json.
    Returns every row's name, "model/kind"."""
    every = [f"{m}/{k}" for m, *_ in table1.TABLE1 for k in table1.KINDS]
    ap.add_argument("--rows", default=",".join(every), help="comma-separated model/kind (default: all 8)")
    ap.add_argument("--rounds", type=int, default=rounds, help=f"rounds of the two {what} (default {rounds})")
    ap.add_argument("--poses", type=int, default=poses,
                    help=f"timed poses per {what[:-1]} per round (default {poses})")
    ap.add_argument("--quick", action="store_true", help="500 points per row (seconds; smoke test)")
    ap.add_argument("--data", default=str(table1.DEFAULT_DATA), help="shared data folder (meshes/...)")
    ap.add_argument("--json", help="write the record here")
    return every


def chosen_rows(a, every: list[str], prog: str) -> list[tuple[str, str]] | None:
    """The (model, kind) rows of parsed options ``a`` (:func:`add_rows_arguments`); None,
    after one line on stderr naming the problem, for an unknown row or a count below 1."""
    rows = [r.strip() for r in a.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in every]
    if bad or not rows:
        print(f"{prog}: unknown row {bad[0] if bad else '(none)'!r}; choose from {', '.join(every)}",
              file=sys.stderr)
        return None
    if a.rounds < 1 or a.poses < 1:
        print(f"{prog}: --rounds and --poses must be at least 1", file=sys.stderr)
        return None
    return [tuple(r.split("/")) for r in rows]


def write_record(doc: dict, path: str | None) -> None:
    """A benchmark's JSON record to ``path`` (atomically, table1.write_json), if given."""
    if path:
        table1.write_json(doc, pathlib.Path(path))
        print(f"wrote {path}")
