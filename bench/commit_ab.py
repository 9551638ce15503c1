"""This checkout's nrpose against an earlier commit's, posing Table-1 rows in one process.

    python bench/commit_ab.py BASE [--rows dragon/segments,box/points] [--rounds 30]
                              [--poses 40] [--blend B] [--quick] [--json OUT.json]

Why: on the shared 2-core VM a single thread's speed differs by up to ~1.4x between
processes and drifts within one, so alternated processes resolve only large changes
(kernel_ab.py compares kernel sources, standby_ab.py launch policies; this compares
whole packages: host code, kernels and launches together). The package and kernels of
commit BASE (``git archive``) are imported beside this checkout's under the name
``nrpose_base`` (every ``nrpose`` module path in its Python files renamed; it builds its
kernels from its own copy and has its own OpenCL context and standing workers). For each
Table-1 row (bench/table1.py's model and handles, 20 poses of its kind drawn with seed 1)
both deformers are bound; then rounds alternate them (the order alternates too), each
round posing ``--poses`` poses back to back after 10 untimed ones, as a frame loop does
(``posed = deformer.pose(p)``), with a pause of twice the standby between them so that
the other's standing worker has returned.

Reported per row (and written with ``--json``): each side's median over all its poses
(ms), the per-round ratio base / this (median, min, max; > 1: this checkout is faster)
and the largest difference between the two outputs of one pose relative to the bounding
box diagonal (0 when the arithmetic is unchanged). The base must pose through the same
API (``nrpose.Deformer(points, rest)``, ``nrpose.HandleSet.make``, ``nrpose.Pose.make(rest,
points, segments, rotations=)``); ``--blend`` gives both deformers that blend (default: each
package's default). Errors (unknown commit, not a git checkout, unknown row): one line on
stderr, exit status 2.
"""
from __future__ import annotations

import argparse
import gc
import importlib
import io
import pathlib
import re
import subprocess
import sys
import tarfile
import tempfile
import time

import numpy as np

import common
import table1
from nrpose import device
from nrpose import Deformer
from nrpose.errors import NrposeError

ROOT = pathlib.Path(__file__).resolve().parent.parent
BASE_NAME = "nrpose_base"
WARMUP = 10
_MODULE_PATH = re.compile(r"\bnrpose(?=[.\s\"'])")


class BaseError(Exception):
    """The base commit cannot be imported (message for the user)."""


def import_base(commit: str, folder: pathlib.Path):
    """Commit ``commit``'s nrpose package, with its kernels, importable as ``nrpose_base``
    from ``folder`` (which this puts on sys.path); the imported package."""
    try:
        tar = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "nrpose", "kernels"],
                             capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        err = getattr(exc, "stderr", b"") or b""
        raise BaseError(f"cannot read commit {commit!r} of {ROOT} with git archive: "
                        f"{err.decode(errors='replace').strip() or exc}") from None
    with tarfile.open(fileobj=io.BytesIO(tar)) as t:
        t.extractall(folder, filter="data")
    pkg = folder / BASE_NAME
    (folder / "nrpose").rename(pkg)
    (folder / "kernels").rename(pkg / "kernels")
    for py in pkg.rglob("*.py"):
        py.write_text(_MODULE_PATH.sub(BASE_NAME, py.read_text()))
    sys.path.insert(0, str(folder))
    return importlib.import_module(BASE_NAME)


def measure_row(base, model: str, kind: str, data: pathlib.Path, rounds: int, poses: int,
                quick: bool, blend: str | None = None) -> dict:
    """One row's record (see the module docstring); base: the imported base package."""
    v, rest, diag, row_poses = common.table1_row(model, kind, data, poses=20, seed=1, quick=quick)
    # the package's public names, whatever its module layout
    rest_b = base.HandleSet.make(rest.points, rest.segments)
    poses_b = [base.Pose.make(rest_b, p.handles.points, p.handles.segments,
                              rotations=p.rotations if len(rest.segments) else None) for p in row_poses]
    kw = {} if blend is None else {"blend": blend}
    sides = {"base": (base.Deformer(v, rest_b, **kw), poses_b),
             "this": (Deformer(v, rest, **kw), row_poses)}
    diff = float(np.abs(sides["base"][0].pose(poses_b[3]) - sides["this"][0].pose(row_poses[3])).max()) / diag
    pause = 2 * device.standby_s() + 1e-3
    times = {k: [] for k in sides}
    medians = {k: [] for k in sides}
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for r in range(rounds):
            for name in (("base", "this") if r % 2 else ("this", "base")):
                deformer, ps = sides[name]
                time.sleep(pause)
                posed = None
                for i in range(WARMUP):
                    posed = deformer.pose(ps[i % len(ps)])
                ts = []
                for i in range(poses):
                    t = time.perf_counter()
                    posed = deformer.pose(ps[i % len(ps)])
                    ts.append(time.perf_counter() - t)
                del posed
                times[name] += ts
                medians[name].append(float(np.median(ts)))
    finally:
        if gc_was:
            gc.enable()
    ratios = np.array(medians["base"]) / np.array(medians["this"])
    return {"model": model, "kind": kind, "points": int(len(v)), "handles": rest.count,
            **{f"{name}_ms": common.stats(t) for name, t in times.items()},
            "base_over_this": {"median": float(np.median(ratios)), "min": float(ratios.min()),
                               "max": float(ratios.max()), "rounds": len(ratios)},
            "max_diff_rel_bbox": diff}


def run(commit: str, rows: list[tuple[str, str]], rounds: int = 30, poses: int = 40, quick: bool = False,
        data: pathlib.Path = table1.DEFAULT_DATA, blend: str | None = None, log=print) -> dict:
    with tempfile.TemporaryDirectory(prefix="nrpose-commit-ab-") as tmp:
        base = import_base(commit, pathlib.Path(tmp))
        cpu0, load0 = common.cpu_times(), common.load()
        records = []
        for model, kind in rows:
            records.append(measure_row(base, model, kind, pathlib.Path(data), rounds, poses, quick, blend))
            r = records[-1]
            if log:
                log(f"{model:9s} {kind:8s} base {r['base_ms']['median']:.3f} ms, this {r['this_ms']['median']:.3f} ms, "
                    f"base/this per round {r['base_over_this']['median']:.2f} "
                    f"[{r['base_over_this']['min']:.2f}, {r['base_over_this']['max']:.2f}], "
                    f"max diff {r['max_diff_rel_bbox']:.1e}")
    base_commit = common.git("rev-parse", commit)
    return {"schema": "nrpose-bench-commit-ab/1", "timestamp": common.now(),
            "git_commit": common.git("rev-parse", "HEAD"), "base_commit": base_commit or commit,
            "environment": common.environment(),
            "options": {"rounds": rounds, "poses_per_round": poses, "warmup": WARMUP, "quick": quick,
                        "blend": blend or "each package's default"},
            "timing": "posed = Deformer.pose(p) back to back, ms per pose; the two packages alternated "
                      "in rounds, one process",
            "load_start": load0, "load_end": common.load(),
            "cpu_steal_percent": common.steal_percent(cpu0, common.cpu_times()), "rows": records}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base", help="the commit to compare against (anything git understands: a hash, HEAD~3, a tag)")
    every = common.add_rows_arguments(ap, rounds=30, poses=40, what="packages")
    ap.add_argument("--blend", default=None, help="the blend of both deformers (default: each package's default)")
    a = ap.parse_args(argv)
    rows = common.chosen_rows(a, every, "commit_ab")
    if rows is None:
        return 2
    try:
        doc = run(a.base, rows, a.rounds, a.poses, a.quick, pathlib.Path(a.data), a.blend)
    except (BaseError, NrposeError) as exc:
        print(f"commit_ab: {exc}", file=sys.stderr)
        return 2
    common.write_record(doc, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
