"""Benchmark suites: the paper's Table 1 on PoCL, roofline, scaling, character clips, and the
deformation quality suite (bench/quality.py; its close-up and table PNGs in bench/results/quality/).

    python -m bench [--suite table1|scaling|clips|roofline|quality|all] [--repeat N]
                    [--quick] [--json OUT.json] [--png PLOT.png] [--data DIR]

(from the checkout's root; ``python bench/suites.py`` and ``make bench`` run the same.)
Bad options: one line on stderr, exit status 2. One JSON document
(schema ``nrpose-bench-suites/1``, bench/README.md) with the device, the git commit,
the options, the load average, every suite's figures and the targets; one PNG with a
panel per suite run. Not a test: no assertions.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import common  # noqa: E402
from common import table1  # noqa: E402
from nrpose.errors import InputError, NrposeError  # noqa: E402

SCHEMA = "nrpose-bench-suites/1"
SUITES = ("table1", "roofline", "scaling", "clips", "quality")
#: what ``--suite all`` runs: the timing suites (the quality suite, minutes of posing and
#: measuring that no timing depends on, runs when named)
ALL = ("table1", "roofline", "scaling", "clips")
#: the quality suite's pictures (bench/quality.py)
QUALITY_PNG_DIR = HERE / "results" / "quality"
DEFAULT_JSON = HERE / "results" / "suites.json"
DEFAULT_PNG = HERE / "results" / "suites.png"
TARGETS = {"paper_over_pocl_min": 100.0, "speedup_vs_numpy_min": 300.0, "fraction_arithmetic_min": 0.30,
           "skeleton_1m_pose_ms_max": 25.0}


def run(suites=("all",), repeat: int = 5, quick: bool = False, data=None, log=None) -> dict:
    """Run the suites; return the result document (see bench/README.md)."""
    chosen = list(ALL) if "all" in suites else [s for s in SUITES if s in suites]
    unknown = [s for s in suites if s != "all" and s not in SUITES]
    if unknown or not chosen:
        raise ValueError(f"unknown suite(s) {unknown}; choose from {SUITES + ('all',)}")
    data = pathlib.Path(data) if data is not None else table1.DEFAULT_DATA
    repeat = max(int(repeat), 1)
    doc = {"schema": SCHEMA, "timestamp": common.now(),
           "git_commit": common.git("rev-parse", "HEAD"),
           "options": {"suites": chosen, "repeat": repeat, "quick": quick, "data": str(data)},
           "environment": common.environment(), "load_start": common.load(), "suites": {}}
    t_all, cpu_all = time.perf_counter(), common.cpu_times()
    roofs = None
    if "roofline" in chosen or "scaling" in chosen:
        import roofline
        roofs = roofline.Roofs(quick)
    for name in chosen:
        t0, cpu0 = time.perf_counter(), common.cpu_times()
        if name == "table1":
            t = table1.run(repeat, quick, data, log=log)
            res = {k: t[k] for k in ("rows", "targets", "options", "source", "device_setup_ms")}
            res["table1_schema"] = t["schema"]
        elif name == "roofline":
            res = roofline.run(repeat, quick, data, roofs=roofs, log=log)
        elif name == "scaling":
            import scaling
            res = scaling.run(repeat, quick, roofs=roofs, log=log)
            if roofs is not None:
                ceil = (doc["suites"].get("roofline") or {}).get("roofs") or roofline.merge_roofs(
                    *(roofs.measure(2 if quick else 3) for _ in range(2)))
                res["roofs"] = ceil
                floor = roofs.launch_floor(ceil)
                for r in res["rows"]:
                    if "kernel_ms" in r:
                        r.update(roofline.assess(r["work"], r["kernel_ms"]["median"], r["pose_ms"]["median"],
                                                 ceil, floor))
        elif name == "quality":
            import quality
            res = quality.run(quick=quick, frames=2 if quick else 6, png_dir=QUALITY_PNG_DIR, data=data, log=log)
        else:
            import clips
            res = clips.run(repeat, quick, data, log=log)
        res["seconds"] = time.perf_counter() - t0
        res["load_end"] = common.load()
        res["cpu_steal_percent"] = common.steal_percent(cpu0, common.cpu_times())
        if log:
            log(f"{name}: {res['seconds']:.0f} s, CPU steal {res['cpu_steal_percent']} %")
        doc["suites"][name] = res
    doc["seconds"] = time.perf_counter() - t_all
    doc["load_end"] = common.load()
    doc["cpu_steal_percent"] = common.steal_percent(cpu_all, common.cpu_times())
    doc["git_commit_end"] = common.git("rev-parse", "HEAD")
    doc["git_dirty"] = common.git("diff", "--name-only", "HEAD", "--", "nrpose", "kernels", "rigs").splitlines()
    doc["peak_rss_gb"] = common.peak_rss_gb()
    doc["targets"] = targets(doc)
    return doc


def targets(doc: dict) -> list[dict]:
    """The issue's targets against this run's medians (``meaningful`` false in quick mode)."""
    s, out, q = doc["suites"], [], doc["options"]["quick"]
    for t in s.get("quality", {}).get("targets", []):
        # quality figures do not depend on timing: meaningful in quick mode too
        out.append({"name": f"quality {t['case']}: {t['target']}", "target": t["target"], "measured": t["measured"],
                    "where": t["case"], "met": t["met"], "meaningful": True,
                    **({"why": t["why"]} if "why" in t else {})})
    if "table1" in s:
        rows = s["table1"]["rows"]
        worst = min(rows, key=lambda r: r["paper_over_pocl"])
        out.append({"name": "table1 pose >= 100x below the paper (every row)", "target": TARGETS["paper_over_pocl_min"],
                    "measured": worst["paper_over_pocl"], "where": f"{worst['model']}/{worst['kind']} (worst row)",
                    "per_row": {f"{r['model']}/{r['kind']}": r["paper_over_pocl"] for r in rows},
                    "met": worst["paper_over_pocl"] >= TARGETS["paper_over_pocl_min"], "meaningful": not q})
        worst = min(rows, key=lambda r: r["speedup_vs_numpy"])
        out.append({"name": "table1 pose >= 300x faster than the numpy reference, same run (every row)",
                    "target": TARGETS["speedup_vs_numpy_min"], "measured": worst["speedup_vs_numpy"],
                    "where": f"{worst['model']}/{worst['kind']} (worst row)",
                    "per_row": {f"{r['model']}/{r['kind']}": r["speedup_vs_numpy"] for r in rows},
                    "met": worst["speedup_vs_numpy"] >= TARGETS["speedup_vs_numpy_min"], "meaningful": not q})
    if "roofline" in s:
        rows = s["roofline"]["rows"]
        best = max(rows, key=lambda r: r["fraction_arithmetic"])
        worst = min(rows, key=lambda r: r["fraction_arithmetic"])
        out.append({"name": "NR-MLS pose kernel >= 30 % of the measured arithmetic roof at Table-1 sizes (every row)",
                    "target": TARGETS["fraction_arithmetic_min"], "measured": worst["fraction_arithmetic"],
                    "where": f"{worst['model']}/{worst['kind']} (worst row; best {best['model']}/{best['kind']} "
                             f"{best['fraction_arithmetic']:.3f})",
                    "best_row": {"where": f"{best['model']}/{best['kind']}", "measured": best["fraction_arithmetic"]},
                    "per_row": {f"{r['model']}/{r['kind']}": {"fraction_arithmetic": r["fraction_arithmetic"],
                                                              "fraction_arithmetic_best_round":
                                                                  r["fraction_arithmetic_best_round"],
                                                              "batched_fraction_arithmetic":
                                                                  r["batched"]["fraction_arithmetic"],
                                                              "bound_by": r["bound_by"]} for r in rows},
                    "batched": {"measured": s["roofline"]["best_batched_fraction_arithmetic"],
                                "where": s["roofline"]["best_batched_row"] + " (best row, one launch of "
                                         f"{rows[0]['batch_frames']} frames, kernel time per frame)"},
                    "met": worst["fraction_arithmetic"] >= TARGETS["fraction_arithmetic_min"],
                    "meaningful": not q})
    if "scaling" in s:
        t = s["scaling"]["target"]
        out.append({"name": "1,000,000 points x 65 bones (sparse, k = 8) posed in <= 25 ms",
                    "target": TARGETS["skeleton_1m_pose_ms_max"], "measured": t["measured"],
                    "where": "scaling sparse N=1e6 H=65", "met": t["met"], "meaningful": not q and t["measured"] is not None,
                    "bind_ms": t["bind_ms"], "peak_rss_gb": t["peak_rss_gb"]})
    return out


# --------------------------------------------------------------------------- output

def write_json(doc: dict, path) -> None:
    import json

    from nrpose.io.files import atomic_path
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n")


def write_png(doc: dict, path) -> None:
    """One figure, a panel per suite run."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from nrpose.io.files import atomic_path
    s = doc["suites"]
    names = [n for n in SUITES if n in s]
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 4.6 * len(names)), squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        globals()[f"_plot_{name}"](ax, s[name])
    env = doc["environment"]
    fig.suptitle(f"nrpose benchmark suites: {env['device'].get('summary', env['device']['device'])}, PoCL "
                 f"{env['pocl_version']}, LLVM {env['llvm_version']}\ncommit {doc['git_commit'][:8]}"
                 f"{' + changes' if doc['git_dirty'] else ''}; {doc['timestamp']}; load {doc['load_start'][:1]}"
                 f"{' (quick: timings mean nothing)' if doc['options']['quick'] else ''}", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def _plot_table1(ax, res):
    rows = res["rows"]
    x = np.arange(len(rows))
    series = [("paper (2009)", [r["paper_ms"] for r in rows], "#999999"),
              ("PoCL", [r["pocl_pose_ms"]["median"] for r in rows], "#1f77b4"),
              ("numpy float64", [r["numpy_pose_ms"]["median"] for r in rows], "#ff7f0e")]
    for k, (label, vals, col) in enumerate(series):
        bars = ax.bar(x + (k - 1) * 0.27, vals, 0.27, label=label, color=col)
        for b, v in zip(bars, vals):
            ax.annotate(f"{v:.3g}", (b.get_x() + b.get_width() / 2, v), ha="center", va="bottom", fontsize=6)
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{r['model']}\n{r['kind']}\n{r['points']:,}×{r['handles']}" for r in rows], fontsize=7)
    ax.set_ylabel("pose time (ms, median)")
    ax.set_title("Table 1: pose time per frame (paper/PoCL ×{:.0f}–{:.0f}, numpy/PoCL ×{:.0f}–{:.0f})".format(
        min(r["paper_over_pocl"] for r in rows), max(r["paper_over_pocl"] for r in rows),
        min(r["speedup_vs_numpy"] for r in rows), max(r["speedup_vs_numpy"] for r in rows)), fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(axis="y", which="both", alpha=0.3)


def _plot_roofline(ax, res):
    import roofline
    roofs = res["roofs"]
    peak, dram, l3 = (roofs[k][roofline.ROOF_RULE] for k in ("gflops", "dram_gbs", "l3_gbs"))
    ai = np.logspace(-1, 2, 200)
    ax.loglog(ai, np.minimum(peak, ai * dram), "k-", lw=1.5, label=f"DRAM roof ({dram:.0f} GB/s, {peak:.0f} GFLOP/s)")
    ax.loglog(ai, np.minimum(peak, ai * l3), "k--", lw=1, label=f"L3 roof ({l3:.0f} GB/s)")
    ax.axhline(0.3 * peak, color="r", lw=0.8, ls=":", label="30 % of arithmetic roof")
    for r in res["rows"]:
        mk = "o" if r["kind"] == "segments" else "s"
        line, = ax.loglog(r["work"]["arithmetic_intensity"], r["gflops"], mk, ms=7,
                          label=f"{r['model']}/{r['kind']}: {100 * r['fraction_arithmetic']:.0f} % "
                                f"({r['kernel_bound']}); batched {100 * r['batched']['fraction_arithmetic']:.0f} %")
        # the same poses in one launch (hollow marker, same colour), per frame
        ax.loglog(r["work"]["arithmetic_intensity"], r["batched"]["gflops"], mk, ms=9, mfc="none",
                  mec=line.get_color())
    ax.set_xlabel("arithmetic intensity (counted flop / byte)")
    ax.set_ylabel("GFLOP/s (pose kernel as a frame loop runs it)")
    ax.set_title("Roofline: nrmls_pose at Table-1 sizes against this device's measured ceilings "
                 "(filled: single pose; hollow: batched launch, per frame)", fontsize=9)
    ax.legend(fontsize=6, ncol=2, loc="lower right")
    ax.grid(which="both", alpha=0.3)


def _plot_scaling(ax, res):
    cmap = {h: c for h, c in zip(sorted({r["handles"] for r in res["rows"]}), ["C0", "C1", "C2", "C3", "C4", "C5"])}
    for mode, mk, ls in (("dense", "o", "-"), ("sparse", "^", "--")):
        rows = [r for r in res["rows"] if r["mode"] == mode]
        for h in sorted({r["handles"] for r in rows}):
            rr = sorted((r for r in rows if r["handles"] == h), key=lambda r: r["points"])
            ax.loglog([r["point_handles"] for r in rr], [r["pose_ms"]["median"] for r in rr], mk + ls,
                      color=cmap[h], label=f"{mode} H={h}")
        f = res["fits"][mode].get("power")
        if f:
            x = np.logspace(np.log10(min(r["point_handles"] for r in rows)),
                            np.log10(max(r["point_handles"] for r in rows)), 50)
            ax.loglog(x, f["a_ms"] * x ** f["b"], ls, color="gray", lw=0.8,
                      label=f"{mode} fit t ∝ (N·H)^{f['b']:.2f}")
    t = res["target"]
    if t.get("measured"):
        ax.axhline(t["pose_ms_max"], color="r", lw=0.8, ls=":", label="25 ms target (1M × 65, k=8)")
    ax.set_xlabel("points × handles (N·H)")
    ax.set_ylabel("pose time (ms, median)")
    ax.set_title("Scaling: Deformer.pose time vs size (dense blend and sparse k=8 skeletons)", fontsize=9)
    ax.legend(fontsize=6, ncol=3)
    ax.grid(which="both", alpha=0.3)


def _plot_quality(ax, res):
    cases = [c["case"] for c in res["cases"]]
    methods = res["methods"]
    x = np.arange(len(cases))
    w = 0.8 / max(len(methods), 1)
    for k, m in enumerate(methods):
        ax.bar(x + (k - len(methods) / 2) * w, [c["methods"][m]["p99.9"] for c in res["cases"]], w, label=m)
    ax.set_xticks(x, cases, fontsize=6, rotation=60, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("p99.9 edge strain")
    ax.set_title("Quality: p99.9 edge strain per case and method (full table: bench/results/quality/table.png)",
                 fontsize=9)
    ax.legend(fontsize=6, ncol=4)
    ax.grid(axis="y", which="both", alpha=0.3)


def _plot_clips(ax, res):
    rows = res["rows"]
    chars = list(dict.fromkeys(r["character"] for r in rows))
    x = np.arange(len(chars))
    for k, m in enumerate(res["methods"]):
        row = [next((r for r in rows if r["character"] == c and r["method"] == m), None) for c in chars]
        vals = [r["fps"] if r else 0 for r in row]
        bars = ax.bar(x + (k - 1) * 0.27, vals, 0.27, label=m)
        for b, v in zip(bars, vals):
            ax.annotate(f"{v:.0f}", (b.get_x() + b.get_width() / 2, v), ha="center", va="bottom", fontsize=6)
        # the whole pose(clip) call: forward kinematics, bone poses and the output array on top
        ax.scatter(x + (k - 1) * 0.27, [r["batch_fps"] if r else np.nan for r in row], marker="_", s=120,
                   color="black", zorder=3, label="whole pose(clip) call" if k == 0 else None)
    lab = {r["character"]: f"{r['character']}\n{r['vertices']:,} v, {r['joints']} j" for r in rows}
    ax.set_xticks(x, [lab[c] for c in chars], fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("frames per second\n(bars: 1000 / median frame ms)")
    ax.set_title("Clips: posing characters through their clips", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(axis="y", which="both", alpha=0.3)


def summary(doc: dict) -> list[str]:
    lines = []
    for t in doc["targets"]:
        m = t["measured"]
        lines.append(f"target {t['name']}: {m:.4g} ({t['where']}) -> "
                     f"{'met' if t['met'] else 'NOT met'}{'' if t['meaningful'] else ' (not meaningful: quick)'}"
                     if m is not None else f"target {t['name']}: not measured")
    return lines


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--suite", action="append", choices=SUITES + ("all",),
                    help="suite to run (repeatable; default all)")
    ap.add_argument("--repeat", type=int, default=5, help="timing rounds (default 5)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes, seconds (smoke tests; timings mean nothing)")
    ap.add_argument("--json", default=str(DEFAULT_JSON), help="output JSON (default bench/results/suites.json)")
    ap.add_argument("--png", default=str(DEFAULT_PNG), help="output PNG ('' to skip)")
    ap.add_argument("--data", default=str(table1.DEFAULT_DATA), help="shared data folder")


def parser(prog: str | None = None) -> argparse.ArgumentParser:
    """The suites' command line (options as in bench/README.md); ``func``: :func:`execute`."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    add_arguments(ap)
    ap.set_defaults(func=execute)
    return ap


def main(argv=None, prog: str | None = None) -> int:
    """Parse ``argv`` and run the chosen suites; exit status (2 with one line on stderr for
    bad options)."""
    a = parser(prog).parse_args(argv)
    try:
        return a.func(a)
    except NrposeError as exc:
        print(f"{prog or 'suites'}: {exc}", file=sys.stderr)
        return 2


def execute(a) -> int:
    """Run the suites ``a`` (from :func:`parser`) names; write a.json (atomically) and
    a.png. Returns 0; InputError for a repeat below 1 or an output folder that does not
    exist."""
    if a.repeat < 1:
        raise InputError(f"--repeat must be at least 1, got {a.repeat}")
    for opt in ("json", "png"):
        path = getattr(a, opt)
        if path and not pathlib.Path(path).parent.is_dir():
            raise InputError(f"--{opt} {path}: directory {pathlib.Path(path).parent} does not exist")
    doc = run(a.suite or ["all"], a.repeat, a.quick, a.data, log=lambda s: print(s, flush=True))
    write_json(doc, a.json)
    if a.png:
        write_png(doc, a.png)
    for line in summary(doc):
        print(line)
    print(f"wrote {a.json}" + (f" and {a.png}" if a.png else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
