"""Standing workers against workers woken per pose, in one process (Table-1 rows).

    python bench/standby_ab.py [--rows dragon/segments,box/points] [--rounds 12]
                               [--poses 100] [--quick] [--json OUT.json] [--png OUT.png]

Why in one process: on the shared 2-core VM a single thread's speed differs by up to
~1.4x between processes, so alternated processes resolve only large changes. For each
Table-1 row (bench/table1.py's model and handles, 20 poses of its kind drawn with seed 1)
one deformer is bound; then rounds alternate the two launch policies of
nrpose.device.launch_shared, each round posing ``--poses`` poses back to back
(``Deformer.pose(p, out=)`` into one array, warm after the first round; Table 1's
``pocl_pose_into_ms`` writes 20 different ones) after 10 untimed ones:

* ``standing``: the default standby (device.STANDBY_S, 1 ms): from the second pose of
  a loop on, PoCL's worker stands between poses, polling for the next;
* ``woken``: standby 0 (``NRPOSE_STANDBY_US=0``): each pose wakes the worker when the launch is
  worth it (frames taking >= device.SHARE_MIN_S on the calling thread alone), else runs
  on the calling thread alone: the behaviour before standing workers.

The order of the two alternates between rounds. Reported per row (and written with
``--json``; ``--png``: a bar chart): each policy's median, p10 and p90 over all its
poses (ms), the per-round ratio woken / standing (median, min, max; > 1: standing is
faster), the share of the standing policy's poses after which a worker stood, the
kernel's time alone on the calling thread as timed at bind, and the largest difference
between the two policies' outputs (they must be equal: same blocks, same arithmetic).
Errors: one line on stderr, exit status 2.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

import numpy as np

import common
import table1
from nrpose import device, diagnostics
from nrpose.pose.mls import Deformer
from nrpose.errors import NrposeError

POLICIES = {"standing": device.STANDBY_S, "woken": 0.0}     # standby, seconds
WARMUP = 10


def measure_row(model: str, kind: str, data: pathlib.Path, rounds: int, poses: int, quick: bool) -> dict:
    """One row's record (see the module docstring)."""
    v, rest, _, row_poses = common.table1_row(model, kind, data, poses=20, seed=1, quick=quick)
    d = Deformer(v, rest, alpha=table1.ALPHA, blend=table1.BLEND, lever=table1.LEVER)
    out = np.empty((len(v), 3), np.float32)
    times = {name: [] for name in POLICIES}
    ratios, last, stood = [], {}, 0
    for r in range(rounds):
        order = list(POLICIES) if r % 2 == 0 else list(POLICIES)[::-1]
        medians = {}
        for name in order:
            device.set_standby_s(POLICIES[name])
            for i in range(WARMUP):
                d.pose(row_poses[i % len(row_poses)], out=out)
            ts = []
            for i in range(poses):
                t = time.perf_counter()
                d.pose(row_poses[i % len(row_poses)], out=out)
                ts.append(time.perf_counter() - t)
                stood += name == "standing" and diagnostics.worker_standing(d)
            medians[name] = float(np.median(ts))
            times[name] += ts
            last[name] = d.pose(row_poses[0]).copy()
        ratios.append(medians["woken"] / medians["standing"])
    ms = {name: common.stats(t) for name, t in times.items()}
    return {"model": model, "kind": kind, "points": int(len(v)), "handles": rest.count,
            "alone_ms": diagnostics.alone_s(d) * 1e3, **{f"{name}_ms": ms[name] for name in POLICIES},
            "woken_over_standing": {"median": float(np.median(ratios)), "min": float(min(ratios)),
                                    "max": float(max(ratios)), "rounds": len(ratios)},
            "stood_fraction": stood / (rounds * poses),
            "max_diff_between_policies": float(np.abs(last["standing"] - last["woken"]).max())}


def run(rows: list[tuple[str, str]], rounds: int = 12, poses: int = 100, quick: bool = False,
        data: pathlib.Path = table1.DEFAULT_DATA, log=print) -> dict:
    before = device.standby_s()
    cpu0, load0 = common.cpu_times(), common.load()
    records = []
    try:
        for model, kind in rows:
            records.append(measure_row(model, kind, pathlib.Path(data), rounds, poses, quick))
            r = records[-1]
            if log:
                log(f"{model:9s} {kind:8s} standing {r['standing_ms']['median']:.3f} ms, woken "
                    f"{r['woken_ms']['median']:.3f} ms, woken/standing per round {r['woken_over_standing']['median']:.2f} "
                    f"[{r['woken_over_standing']['min']:.2f}, {r['woken_over_standing']['max']:.2f}]")
    finally:
        device.set_standby_s(before)
    return {"schema": "nrpose-bench-standby-ab/1", "timestamp": common.now(),
            "git_commit": common.git("rev-parse", "HEAD"), "environment": common.environment(),
            "options": {"rounds": rounds, "poses_per_round": poses, "warmup": WARMUP, "quick": quick},
            "standing_workers_possible": device.standing_workers_possible(),
            "policies": {"standing": f"standby {device.STANDBY_S * 1e3:g} ms (the default)",
                         "woken": "standby 0 (NRPOSE_STANDBY_US=0)"},
            "timing": "Deformer.pose(p, out=) back to back, ms per pose, the two policies alternated "
                      "in rounds",
            "load_start": load0, "load_end": common.load(),
            "cpu_steal_percent": common.steal_percent(cpu0, common.cpu_times()), "rows": records}


def write_png(doc: dict, path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = doc["rows"]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(9, 4.2))
    for k, (name, colour) in enumerate((("woken", "#999999"), ("standing", "#1f77b4"))):
        med = [r[f"{name}_ms"]["median"] for r in rows]
        lo = [r[f"{name}_ms"]["median"] - r[f"{name}_ms"]["p10"] for r in rows]
        hi = [r[f"{name}_ms"]["p90"] - r[f"{name}_ms"]["median"] for r in rows]
        ax.bar(x + (k - 0.5) * 0.38, med, 0.38, yerr=[lo, hi], capsize=3, color=colour,
               label=f"{name} workers" + (" (NRPOSE_STANDBY_US=0)" if name == "woken" else " (default)"))
    tops = [max(r["woken_ms"]["p90"], r["standing_ms"]["p90"]) for r in rows]
    for i, r in enumerate(rows):
        ax.text(i, tops[i] * 1.03, f"{r['woken_over_standing']['median']:.2f}×", ha="center", fontsize=8)
    ax.set_ylim(0, max(tops) * 1.3)              # room for the legend above the bars
    ax.set_xticks(x, [f"{r['model']}\n{r['kind']}" for r in rows], fontsize=8)
    ax.set_ylabel("pose, ms (median, p10-p90)")
    ax.set_title(f"Pose in a loop: standing vs woken workers, one process "
                 f"({doc['git_commit'][:7]}; label: woken / standing per round)", fontsize=9)
    ax.legend(fontsize=8, loc="upper center", ncol=2)
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    every = common.add_rows_arguments(ap, rounds=12, poses=100, what="policies")
    ap.add_argument("--png", help="write a bar chart here")
    a = ap.parse_args(argv)
    rows = common.chosen_rows(a, every, "standby_ab")
    if rows is None:
        return 2
    try:
        doc = run(rows, a.rounds, a.poses, a.quick, pathlib.Path(a.data))
    except NrposeError as exc:
        print(f"standby_ab: {exc}", file=sys.stderr)
        return 2
    common.write_record(doc, a.json)
    if a.png:
        write_png(doc, pathlib.Path(a.png))
        print(f"wrote {a.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
