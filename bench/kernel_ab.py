"""Kernel A/B: a variant of kernels/nrmls.cl against the shipped one, in one process.

    python bench/kernel_ab.py VARIANT.cl [--base BASE.cl] [--model box] [--kind points]
                              [--launches 400] [--json OUT.json]

Why: on a shared VM a single thread's speed differs between processes and drifts within
one, so comparing old and new code in alternated processes resolves only large changes. Here one deformer is bound for a Table-1 row
(bench/table1.py's model, handles and a pose of that row), both kernels are built with
its build options and bound to its arrays (:func:`nrpose.diagnostics.kernel_variant`),
each one's output is checked against the deformer's own, and they are launched
alternately, ``--launches`` times each, on the calling thread alone
(``diagnostics.relaunch(deformer, workers=False, kernel=...)``: the variant, its prologue
included; no worker wake-up), so that both see the same machine.

Reported (and written with ``--json``): for base and variant, the median, p10, p90 of
the launches in ms, the ratio of the medians base / variant (> 1: the variant is
faster) and the largest difference of each output from the deformer's own, relative
to the model's bounding-box diagonal; the device, the git commit, the files' SHA-256.
"""
from __future__ import annotations

import argparse
import contextlib
import hashlib
import os
import pathlib
import sys
import tempfile
import time
from importlib import resources

import numpy as np

import common
import table1
from nrpose import diagnostics
from nrpose.pose.mls import Deformer
from nrpose.errors import NrposeError

SHIPPED = pathlib.Path(str(resources.files("nrpose.kernels").joinpath("nrmls.cl")))


@contextlib.contextmanager
def compiler_quiet():
    """File descriptor 2 into a temporary file for the block: PoCL's compiler writes its
    diagnostics there directly; the build error reaches the user through DeviceError."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def row_deformer(model: str, kind: str, data: pathlib.Path) -> tuple[Deformer, np.ndarray, float]:
    """(deformer bound for the Table-1 row, its output for the row's first pose, bbox diagonal)."""
    v, rest, diag, (pose,) = common.table1_row(model, kind, data)
    deformer = Deformer(v, rest, alpha=table1.ALPHA, blend=table1.BLEND, lever=table1.LEVER)
    return deformer, deformer.pose(pose).copy(), diag


def paired_launches(deformer: Deformer, kernels: dict, launches: int) -> dict[str, list[float]]:
    """Seconds of each of ``launches`` rounds of ``kernels`` (name -> pose kernel variant,
    :func:`nrpose.diagnostics.kernel_variant`), launched in turn on the calling thread alone
    (``diagnostics.relaunch(deformer, workers=False, kernel=...)``, prologue and enqueue/wait
    included):
    round i's times of two kernels were taken side by side."""
    times: dict[str, list[float]] = {which: [] for which in kernels}
    for _ in range(launches):
        for which, kernel in kernels.items():
            t = time.perf_counter()
            diagnostics.relaunch(deformer, workers=False, kernel=kernel)
            times[which].append(time.perf_counter() - t)
    return times


def run(variant: pathlib.Path, base: pathlib.Path = SHIPPED, model: str = "box", kind: str = "points",
        launches: int = 400, data: pathlib.Path = table1.DEFAULT_DATA) -> dict:
    """The A/B record (see the module docstring)."""
    deformer, want, diag = row_deformer(model, kind, pathlib.Path(data))
    files = {"base": pathlib.Path(base), "variant": pathlib.Path(variant)}
    kernels, max_diff = {}, {}
    for which, path in files.items():
        with compiler_quiet():
            kernels[which] = diagnostics.kernel_variant(deformer, path.read_text())
        diagnostics.relaunch(deformer, workers=False, kernel=kernels[which])
        got = diagnostics.launch_output(deformer)[0]
        max_diff[which] = float(np.abs(got - want).max() / diag)
    times = paired_launches(deformer, kernels, launches)
    ms = {which: common.stats(t) for which, t in times.items()}
    paired = np.divide(times["base"], times["variant"])   # each launch against its neighbour: drift cancels
    return {
        "schema": "nrpose-bench-kernel-ab/1",
        "timestamp": common.now(), "git_commit": common.git("rev-parse", "HEAD"),
        "environment": common.environment(),
        "row": {"model": model, "kind": kind, "points": deformer.n,
                "handles": deformer.rest.count, "build_options": list(diagnostics.build_options(deformer))},
        "files": {which: {"path": str(p), "sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
                  for which, p in files.items()},
        "launches": launches,
        "timing": "diagnostics.relaunch(deformer, workers=False, kernel=...) on the calling thread, base and variant "
                  "alternated; ms per launch (pose kernel with its prologue + enqueue/wait)",
        "base_ms": ms["base"], "variant_ms": ms["variant"],
        "base_over_variant": ms["base"]["median"] / ms["variant"]["median"],
        "paired_base_over_variant": common.quantiles(paired),
        "max_diff_rel_bbox": max_diff,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("variant", help="the variant of kernels/nrmls.cl (a .cl file)")
    ap.add_argument("--base", default=str(SHIPPED), help="the kernel to compare against (default: shipped)")
    ap.add_argument("--model", default="box", choices=[r[0] for r in table1.TABLE1])
    ap.add_argument("--kind", default="points", choices=table1.KINDS)
    ap.add_argument("--launches", type=int, default=400, help="launches of each kernel (default 400)")
    ap.add_argument("--data", default=str(table1.DEFAULT_DATA), help="shared data folder (meshes/...)")
    ap.add_argument("--json", help="write the record here too")
    a = ap.parse_args(argv)
    for path in (a.variant, a.base):
        if not pathlib.Path(path).is_file():
            print(f"kernel_ab: {path}: no such file (give a .cl file)", file=sys.stderr)
            return 2
    if a.launches < 1:
        print("kernel_ab: --launches must be at least 1", file=sys.stderr)
        return 2
    try:
        doc = run(pathlib.Path(a.variant), pathlib.Path(a.base), a.model, a.kind, a.launches, pathlib.Path(a.data))
    except NrposeError as exc:
        print(f"kernel_ab: {exc}", file=sys.stderr)
        return 2
    b, v = doc["base_ms"], doc["variant_ms"]
    print(f"{a.model} {a.kind}: base {b['median']:.4f} ms (p10 {b['p10']:.4f}), variant {v['median']:.4f} ms "
          f"(p10 {v['p10']:.4f}); base/variant {doc['base_over_variant']:.3f}, paired median "
          f"{doc['paired_base_over_variant']['median']:.3f}; max |diff| / bbox "
          f"base {doc['max_diff_rel_bbox']['base']:.1e}, variant {doc['max_diff_rel_bbox']['variant']:.1e}")
    common.write_record(doc, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
