"""Smoke test of bench/quality.py on one small case: it runs end to end, writes the JSON
document with every metric finite for every method, and the table and close-up PNGs. No quality
thresholds here beyond the candy wrapper
(tests/test_deformation_metrics.py, test_cor.py and test_quality_fixes.py hold those); and the
suite runs through ``python -m bench --suite quality`` (bench/suites.py)."""
from __future__ import annotations

import importlib.util
import json
import math
import pathlib
import sys

import pytest

pytest.importorskip("pyopencl")

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench"
METRICS = {"p50", "p99", "p99.9", "max", "volume", "region_volume_min", "region_volume_max", "continuity",
           "rigidity", "collapse", "bulge"}


@pytest.fixture(scope="module")
def quality():
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_quality", BENCH / "quality.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_quality_suite_runs_on_a_cylinder(quality, tmp_path):
    methods = ["nrmls-quaternion", "nrmls-relative", "nrmls-closest", "lbs", "dqs", "cor"]
    code = quality.main(["--cases", "cylinder twist 90", "--methods", *methods, "--json", str(tmp_path / "q.json"),
                         "--png-dir", str(tmp_path), "--closeups", "all"])
    assert code == 0
    doc = json.loads((tmp_path / "q.json").read_text())
    assert doc["schema"] == "nrpose-bench-quality/1" and [c["case"] for c in doc["cases"]] == ["cylinder twist 90"]
    res = doc["cases"][0]["methods"]
    assert set(res) == set(methods)
    for m in methods:
        assert METRICS <= set(res[m]) and all(math.isfinite(res[m][k]) for k in METRICS), m
    # a twist keeps the tube's volume except under LBS (the candy wrapper)
    assert res["lbs"]["volume"] < 0.9 < res["dqs"]["volume"]
    assert (tmp_path / "table.png").stat().st_size > 0
    assert (tmp_path / "closeup_cylinder_twist_90.png").stat().st_size > 0
    # the default blend's targets on this case: volume judged, p99.9 against LBS/DQS/CoR
    targets = {t["target"].split(" ")[0]: t for t in doc["targets"]}
    assert set(targets) == {"p99.9", "volume"}
    assert targets["volume"]["measured"] == res["nrmls-quaternion"]["volume"]


def test_quality_is_a_bench_suite(tmp_path, monkeypatch):
    sys.path.insert(0, str(BENCH))
    import quality
    import suites

    seen = {}

    def fake_run(quick=False, **kw):
        seen.update(quick=quick, **kw)
        return {"schema": quality.SCHEMA, "methods": ["nrmls-quaternion"], "cases": [],
                "targets": [{"case": "c", "target": "volume >= 0.97", "measured": 0.99, "met": True}]}

    monkeypatch.setattr(quality, "run", fake_run)
    monkeypatch.setattr(suites, "QUALITY_PNG_DIR", tmp_path)
    doc = suites.run(["quality"], quick=True)
    assert seen["quick"] and seen["png_dir"] == tmp_path
    assert doc["suites"]["quality"]["schema"] == quality.SCHEMA
    assert [t["name"] for t in doc["targets"]] == ["quality c: volume >= 0.97"]
