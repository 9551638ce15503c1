"""Smoke tests of the benchmark suites (bench/suites.py, ``python -m bench``) at tiny sizes.

One --quick run of every suite (seconds): the JSON document's fields are present
and its figures positive and finite, the PNG is written. No timing assertions.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib

import pytest

pytest.importorskip("pyopencl")
pytest.importorskip("matplotlib")

from nrpose.errors import InputError  # noqa: E402

DATA = pathlib.Path(__file__).resolve().parent.parent.parent / "shared" / "data"
BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench"


def _parser() -> argparse.ArgumentParser:
    return _bench_module("suites").parser("python -m bench")


def _finite_positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _stats_ok(s) -> bool:
    return all(_finite_positive(s[k]) for k in ("median", "p10", "p90", "min", "max")) and s["n"] >= 1


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("suites")
    args = _parser().parse_args(["--quick", "--repeat", "1", "--json", str(out / "s.json"),
                                 "--png", str(out / "s.png"), "--data", str(DATA)])
    assert args.func is _bench_module("suites").execute
    assert args.func(args) == 0
    return json.loads((out / "s.json").read_text()), out


def test_document(quick):
    doc, out = quick
    assert doc["schema"] == "nrpose-bench-suites/1"
    assert set(doc["suites"]) == {"table1", "roofline", "scaling", "clips"}
    env = doc["environment"]
    for key in ("pocl_version", "llvm_version", "cpu", "compute_units", "device", "python", "numpy"):
        assert env[key], key
    assert env["compute_units"] >= 1
    assert doc["options"]["quick"] is True and doc["options"]["repeat"] == 1
    assert len(doc["load_start"]) == 3 and len(doc["load_end"]) == 3
    for steal in [doc["cpu_steal_percent"]] + [s["cpu_steal_percent"] for s in doc["suites"].values()]:
        assert steal is None or 0.0 <= steal <= 100.0
    assert isinstance(doc["git_commit"], str) and isinstance(doc["git_dirty"], list)
    assert _finite_positive(doc["seconds"]) and _finite_positive(doc["peak_rss_gb"])
    assert (out / "s.png").stat().st_size > 10_000
    assert not [p for p in out.iterdir() if p.name.startswith(".")]     # no temporary left over
    for t in doc["targets"]:
        assert t["meaningful"] is False and {"name", "target", "measured", "met"} <= set(t)
        if t["measured"] is None:            # quick scaling has no 1M x 65 cell
            assert t["met"] is None
            continue
        # `met` agrees with `measured` and the target's direction; every-row targets judge the worst row
        at_most = "<=" in t["name"]
        assert t["met"] is (t["measured"] <= t["target"] if at_most else t["measured"] >= t["target"]), t
        if "per_row" in t:
            per_row = [v["fraction_arithmetic"] if isinstance(v, dict) else v for v in t["per_row"].values()]
            assert len(per_row) == 8 and all(_finite_positive(v) for v in per_row)
            assert t["measured"] == (max(per_row) if at_most else min(per_row)), t


def test_table1(quick):
    rows = quick[0]["suites"]["table1"]["rows"]
    assert len(rows) == 8
    for r in rows:
        assert _stats_ok(r["pocl_pose_ms"]) and _stats_ok(r["numpy_pose_ms"])
        assert _finite_positive(r["speedup_vs_numpy"]) and _finite_positive(r["paper_over_pocl"])


def test_roofline(quick):
    res = quick[0]["suites"]["roofline"]
    for k in ("gflops", "dram_gbs", "l3_gbs"):
        assert _finite_positive(res["roofs"][k]["median"])
    assert _finite_positive(res["roofs"]["launch"]["wall_ms"])
    assert res["method"]["timing"].endswith("; medians") and "pose kernels: " in res["method"]["timing"]
    assert res["flop_count"]["formula"].startswith("69 P + 18 K + 78 (+ 15 when P > 0")
    assert len(res["rows"]) == 8
    for r in res["rows"]:
        assert _stats_ok(r["kernel_ms"]) and _stats_ok(r["pose_ms"])
        for k in ("gflops", "gbs", "fraction_arithmetic", "fraction_bandwidth", "roofline_ceiling_gflops",
                  "fraction_arithmetic_best_round", "fraction_arithmetic_woken"):
            assert _finite_positive(r[k]), k
        # the kernel timed as a frame loop runs it and, beside it, with the worker woken per launch
        assert _stats_ok(r["kernel_woken_ms"]) and 0 <= r["kernel_stood_fraction"] <= 1
        assert math.isclose(r["fraction_arithmetic_woken"] * r["kernel_woken_ms"]["median"],
                            r["fraction_arithmetic"] * r["kernel_ms"]["median"])
        # the best round's median is no slower than the median over all rounds
        assert r["kernel_ms"]["min"] <= r["kernel_ms_best_round"] <= r["kernel_ms"]["median"]
        assert r["fraction_arithmetic_best_round"] >= r["fraction_arithmetic"]
        P, K = r["work"]["P"], r["work"]["K"]
        stored = 6 * P + 3 if K == 0 else 0      # point rigs read their levers (levers_stored)
        assert r["work"]["flops_per_point"] == 69 * P + 18 * K + 78 + (15 if P else 0) - stored
        assert 0 <= r["work"]["lanes"]["gathered_slot_fraction"] <= 1
        assert r["kernel_bound"] in ("arithmetic", "memory", "host phases", "launch", "instructions") and r["bound_by"]
        # net of an empty job's time the rate is higher (or 0 where nothing is left); a row under
        # 30 % of the roof that reaches it net of the empty job is launch bound (by that rule, or,
        # at --quick's sizes, within LAUNCH_BOUND_RATIO of the empty job)
        net = r["fraction_arithmetic_net_of_launch"]
        assert _finite_positive(r["launch_floor_ms"])
        assert net == 0.0 if r["kernel_ms"]["median"] <= r["launch_floor_ms"] else net > r["fraction_arithmetic"]
        if r["fraction_arithmetic"] < 0.3 <= net and r["kernel_bound"] != "host phases":
            assert r["kernel_bound"] == "launch"
            assert "holds it under 30 %" in r["bound_by"] or "is within" in r["bound_by"]
        # ablations: stores only where points are stored sorted (rigs with segments)
        assert set(r["ablation"]) == ({"memory", "stores"} if K else {"memory"})
        for a in r["ablation"].values():
            assert math.isfinite(a["share"]) and a["share"] < 1 and _finite_positive(a["variant_ms"])
            assert a["paired_ratio"]["p10"] <= a["paired_ratio"]["median"] <= a["paired_ratio"]["p90"]
        assert "measured by ablation" in r["bound_by"]


def test_scaling(quick):
    res = quick[0]["suites"]["scaling"]
    modes = {r["mode"] for r in res["rows"]}
    assert modes == {"dense", "sparse"}
    assert any(r["mode"] == "sparse" and r["slots"] < r["handles"] for r in res["rows"])
    for r in res["rows"]:
        assert _stats_ok(r["pose_ms"]) and _stats_ok(r["kernel_ms"]) and _finite_positive(r["bind_ms"])
    for m in ("dense", "sparse"):
        f = res["fits"][m]
        assert math.isfinite(f["power"]["b"]) and _finite_positive(f["power"]["a_ms"])
        assert math.isfinite(f["linear"]["c0_ms"])


def test_clips(quick):
    rows = quick[0]["suites"]["clips"]["rows"]
    if not DATA.exists():
        pytest.skip(f"{DATA} absent: no characters to pose")
    assert {r["method"] for r in rows} == {"nrmls", "lbs", "dqs"}
    assert {"fox", "bvh"} <= {r["character"] for r in rows}
    for r in rows:
        assert _finite_positive(r["fps"]) and _finite_positive(r["batch_fps"]) and _stats_ok(r["frame_ms"])


def test_bad_options(tmp_path):
    args = _parser().parse_args(["--repeat", "0", "--json", str(tmp_path / "x.json")])
    with pytest.raises(InputError):
        args.func(args)
    args = _parser().parse_args(["--json", str(tmp_path / "missing" / "x.json")])
    with pytest.raises(InputError):
        args.func(args)
    with pytest.raises(SystemExit):
        _parser().parse_args(["--suite", "nope"])


def _bench_module(name: str):
    """A module of bench/ (not a package: imported with bench/ on sys.path, as the suites run)."""
    import importlib
    import sys

    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    return importlib.import_module(name)


def test_report_renders_the_documents(quick, tmp_path):
    """bench/report.py puts every row and target of the documents between the README markers."""
    report = _bench_module("report")

    doc, _ = quick
    t1 = dict(doc["suites"]["table1"], timestamp=doc["timestamp"], git_commit=doc["git_commit"],
              environment=doc["environment"])
    readme = tmp_path / "README.md"
    readme.write_text("head\n<!-- results -->\nold\n<!-- /results -->\nmid\n"
                      "<!-- suites-results -->\nold\n<!-- /suites-results -->\ntail\n")
    (tmp_path / "t1.json").write_text(json.dumps(t1))
    (tmp_path / "s.json").write_text(json.dumps(doc))
    assert report.main(["--table1", str(tmp_path / "t1.json"), "--suites", str(tmp_path / "s.json"),
                        "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert text.startswith("head\n") and "\nmid\n" in text and text.endswith("tail\n") and "old" not in text
    for r in doc["suites"]["table1"]["rows"]:
        assert f"| {r['model']} | {r['kind']} |" in text and f"| {r['model']}/{r['kind']} |" in text
    for t in doc["targets"]:
        assert t["name"] in text
    assert "worker woken: kernel ms, % arith" in text and "Pose kernels timed " in text
    readme.write_text("no markers")
    assert report.main(["--table1", str(tmp_path / "t1.json"), "--suites", str(tmp_path / "s.json"),
                        "--readme", str(readme)]) == 2
    assert readme.read_text() == "no markers"


def test_report_fit_skin_line():
    """The manual's fit-skin sentence: each held-out row's RMS / max and file / bake, no training rows."""
    report = _bench_module("report")
    row = {"character": "Fox", "influences": 8, "helpers": 44, "tracks": "fitted", "rms_pct": 0.0912,
           "max_pct": 0.941, "file_bytes": 300_000, "bake_10s_bytes": 6_000_000}
    doc = {"created": "2026-11-29T05:00:00", "rows": [dict(row, set="training", rms_pct=0.5), dict(row, set="held-out")]}
    line = report.fit_skin_line(doc, "some/fit.json")
    assert "Fox 44 helpers (8 influences, fitted tracks) 0.091 / 0.94, 0.050" in line
    assert "0.500" not in line and "2026-11-29" in line and "`some/fit.json`" in line


def test_steal_percent_from_cpu_time_counters():
    common = _bench_module("common")

    before = [100, 0, 50, 800, 0, 0, 0, 50]
    after = [200, 0, 100, 950, 0, 0, 0, 150]          # 400 ticks, 100 of them stolen
    assert common.steal_percent(before, after) == 25.0
    assert common.steal_percent(None, after) is None and common.steal_percent(before, before) is None
    now = common.cpu_times()
    assert now is None or (len(now) == 8 and all(x >= 0 for x in now))


def test_kernel_ab(tmp_path, monkeypatch, capfd):
    """bench/kernel_ab.py on the box (project-generated, no shared data): the shipped
    kernel against itself (both outputs exactly the deformer's), a variant whose output
    differs (reported, not hidden), and bad input (a missing file, a variant with a
    syntax error, one without nrmls_pose, one whose nrmls_pose takes other arguments):
    exit 2 with one line on stderr (the compiler's own diagnostics included)."""
    import importlib

    monkeypatch.syspath_prepend(str(pathlib.Path(__file__).resolve().parent.parent / "bench"))
    kernel_ab = importlib.import_module("kernel_ab")
    shipped = kernel_ab.SHIPPED.read_text()
    changed = tmp_path / "changed.cl"
    changed.write_text(shipped.replace("1.4142135501f", "1.40f"))        # Rodrigues' sinc, off by 1 %
    for kind in ("points", "segments"):
        out = tmp_path / f"{kind}.json"
        assert kernel_ab.main([str(kernel_ab.SHIPPED), "--kind", kind, "--launches", "3", "--json", str(out)]) == 0
        doc = json.loads(out.read_text())
        assert doc["schema"] == "nrpose-bench-kernel-ab/1" and doc["row"]["points"] == 6006
        assert doc["row"]["kind"] == kind and doc["launches"] == 3
        assert _stats_ok(doc["base_ms"]) and _stats_ok(doc["variant_ms"]) and doc["variant_ms"]["n"] == 3
        assert _finite_positive(doc["base_over_variant"])
        assert doc["max_diff_rel_bbox"] == {"base": 0.0, "variant": 0.0}
        assert doc["files"]["base"]["sha256"] == doc["files"]["variant"]["sha256"]
        assert kernel_ab.main([str(changed), "--kind", kind, "--launches", "2", "--json", str(out)]) == 0
        assert json.loads(out.read_text())["max_diff_rel_bbox"]["variant"] > 1e-4
    capfd.readouterr()
    variants = {"renamed": shipped.replace("__kernel void nrmls_pose(", "__kernel void nrmls_pose_renamed("),
                "syntax": shipped.replace("const floatv ux = LOADV(0, u)", "const floatv ux = LOADV(0, u) +"),
                "arguments": shipped.replace("const int role)", "const int role, const int extra)")}
    cases = [([str(tmp_path / "missing.cl")], "no such file")]
    for name, text in variants.items():
        assert text != shipped, name
        (tmp_path / f"{name}.cl").write_text(text)
        cases.append(([str(tmp_path / f"{name}.cl")], "does not build"))
    for args, what in cases:
        assert kernel_ab.main(args + ["--launches", "2"]) == 2
        err = capfd.readouterr().err
        assert what in err and err.count("\n") == 1, err


def test_standby_ab(tmp_path, monkeypatch, capfd):
    """bench/standby_ab.py at 500 points on the box rows (project-generated data): the JSON
    fields, positive finite timings, equal outputs under both policies, the PNG, the
    standby setting restored; an unknown row or a bad count: exit 2, one line."""
    import importlib

    monkeypatch.syspath_prepend(str(pathlib.Path(__file__).resolve().parent.parent / "bench"))
    from nrpose import device

    if not device.standing_workers_possible():
        pytest.skip("standing workers only on x86 hosts")
    monkeypatch.setattr(device.policy, "_STANDBY", [750e-6])
    monkeypatch.setattr(device.mailbox, "STANDING_MIN_BLOCKS", 1)      # the quick rows have 2 blocks
    standby_ab = importlib.import_module("standby_ab")
    out, png = tmp_path / "ab.json", tmp_path / "ab.png"
    assert standby_ab.main(["--rows", "box/segments,box/points", "--rounds", "2", "--poses", "5", "--quick",
                            "--json", str(out), "--png", str(png)]) == 0
    assert device.standby_s() == 750e-6
    doc = json.loads(out.read_text())
    assert doc["schema"] == "nrpose-bench-standby-ab/1" and [r["kind"] for r in doc["rows"]] == ["segments", "points"]
    for r in doc["rows"]:
        assert r["model"] == "box" and r["points"] == 500
        assert _stats_ok(r["standing_ms"]) and _stats_ok(r["woken_ms"]) and r["standing_ms"]["n"] == 10
        assert _finite_positive(r["woken_over_standing"]["median"]) and r["woken_over_standing"]["rounds"] == 2
        assert r["max_diff_between_policies"] == 0.0 and _finite_positive(r["alone_ms"])
        if device.worker_queue() is not None:
            assert r["stood_fraction"] > 0.5                   # the standing policy did stand
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    capfd.readouterr()
    for argv in (["--rows", "box/nothing"], ["--rounds", "0"]):
        assert standby_ab.main(argv) == 2
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("standby_ab: ")


def test_commit_ab(tmp_path, monkeypatch, capfd):
    """bench/commit_ab.py against this checkout's own commit at 500 points on the box
    rows: the base package imports beside nrpose (its kernels from its own copy), both
    pose alike (same code: outputs equal), the JSON fields; an unknown commit or row, a
    bad count: exit 2, one line. Skipped outside a git checkout with history."""
    import importlib
    import subprocess

    root = pathlib.Path(__file__).resolve().parent.parent
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        pytest.skip("not a git checkout: commit_ab compares commits")
    monkeypatch.syspath_prepend(str(root / "bench"))
    commit_ab = importlib.import_module("commit_ab")
    monkeypatch.setattr("sys.path", list(__import__("sys").path))        # restored: the base's folder
    out = tmp_path / "ab.json"
    assert commit_ab.main(["HEAD", "--rows", "box/segments,box/points", "--rounds", "2", "--poses", "3",
                           "--quick", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["schema"] == "nrpose-bench-commit-ab/1" and doc["base_commit"] == head.stdout.strip()
    assert [r["kind"] for r in doc["rows"]] == ["segments", "points"]
    for r in doc["rows"]:
        assert r["model"] == "box" and r["points"] == 500 and r["max_diff_rel_bbox"] == 0.0
        assert _stats_ok(r["base_ms"]) and _stats_ok(r["this_ms"]) and r["this_ms"]["n"] == 6
        assert _finite_positive(r["base_over_this"]["median"]) and r["base_over_this"]["rounds"] == 2
    import nrpose_base
    assert nrpose_base.__name__ == "nrpose_base" and "nrpose_base" in str(nrpose_base.device.kernel_source.__module__)
    capfd.readouterr()
    for argv in (["no-such-commit", "--rows", "box/points"], ["HEAD", "--rows", "box/nothing"],
                 ["HEAD", "--rounds", "0"]):
        assert commit_ab.main(argv) == 2
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("commit_ab: ")


def test_pose_kernel_timing_falls_back_to_woken_events(monkeypatch):
    """roofline.Roofs.pose_kernel_once times a pose kernel as a frame loop runs it; where no
    span from the job's publication can be had (no CLOCK_MONOTONIC_RAW to read), it gives the
    woken-worker event span instead, says so in `timing`, and holds the kernels against the
    woken empty kernel's event time."""
    import numpy as np

    from nrpose import Deformer, HandleSet, Pose, device

    roofline = _bench_module("roofline")
    roofs = roofline.Roofs(quick=True)
    rest = HandleSet.make(segments=[[[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [2, 0, 0]]])
    d = Deformer(np.random.default_rng(5).uniform(-0.5, 2.5, (600, 3)), rest)
    d.pose(Pose.make(rest, segments=rest.segments + 0.1))
    t, stood = roofs.pose_kernel_once(d)
    assert math.isfinite(t) and t > 0 and roofs.timing == roofline.TIMING_STANDING
    ceilings = {"launch": {"event_ms": 0.04, "wall_ms": 0.1},
                "launch_standing": {"span_ms": 0.003, "wall_ms": 0.01}}
    assert roofs.launch_floor(ceilings)["event_ms"] == 0.003
    monkeypatch.setattr(device.timing, "EVENT_CLOCK", None)
    t, stood = roofs.pose_kernel_once(d)
    assert math.isfinite(t) and t > 0 and not stood and roofs.timing == roofline.TIMING_WOKEN
    assert roofs.launch_floor(ceilings)["event_ms"] == 0.04
    assert roofs.describe()["timing"].endswith(roofline.TIMING_WOKEN + "; medians")


def test_assess_names_the_bound():
    """roofline.assess on synthetic figures (1 GFLOP a pose, roof 100 GFLOP/s, an empty job
    of 5 us): at 40 % arithmetic; at 20 % with a best round at 40 % and the median 2x it, the
    host's slow phases; the same median with a best round at 25 % (or the median only 1.1x
    the best), launch (30 % net of the empty job) or instructions."""
    roofline = _bench_module("roofline")
    work = {"flops_per_pose": 1e9, "bytes_per_pose": 1e6, "arithmetic_intensity": 1000.0}
    roofs = {k: {roofline.ROOF_RULE: v} for k, v in (("gflops", 100.0), ("dram_gbs", 20.0), ("l3_gbs", 50.0))}
    launch = {"event_ms": 0.005, "wall_ms": 0.01, "what": "an empty job"}

    def bound(kernel_ms, best_ms=None):
        return roofline.assess(work, kernel_ms, kernel_ms, roofs, launch, best_round_ms=best_ms)

    assert bound(25.0)["kernel_bound"] == "arithmetic"                       # 40 %
    slow = bound(50.0, 25.0)                                                  # 20 %, best round 40 %
    assert slow["kernel_bound"] == "host phases" and "2.00x" in slow["bound_by"] and "40 %" in slow["bound_by"]
    assert bound(50.0, 40.0)["kernel_bound"] == "instructions"               # best round 25 %
    assert bound(50.0, 45.5)["kernel_bound"] == "instructions"               # 1.1x: no phase
    assert bound(50.0)["kernel_bound"] == "instructions"                     # no best round measured
    near = roofline.assess(work, 34.5, 34.5, roofs, {**launch, "event_ms": 8.0}, best_round_ms=33.0)
    assert near["kernel_bound"] == "launch"                                   # 29 %, 37 % net


def test_python_m_bench_from_the_checkout(tmp_path):
    """``python -m bench`` from the checkout's root runs bench/suites.py's command line: a bad
    option is one line on stderr and exit status 2."""
    import subprocess
    import sys

    root = BENCH.parent
    run = subprocess.run([sys.executable, "-m", "bench", "--repeat", "0", "--json", str(tmp_path / "x.json")],
                         cwd=root, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.strip().splitlines() == ["python -m bench: --repeat must be at least 1, got 0"]
    helped = subprocess.run([sys.executable, "-m", "bench", "--help"], cwd=root, capture_output=True,
                            text=True, timeout=120)
    assert helped.returncode == 0 and "--suite" in helped.stdout
