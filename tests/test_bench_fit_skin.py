"""Smoke test of bench/fit_skin.py on libigl's arm (a mesh + TGF case, its weight file): the
benchmark runs end to end from random poses written as a BVH on the TGF's joints, and records
a training and a held-out row. No timing assertions: this is not a benchmark."""
from __future__ import annotations

import importlib.util
import json
import pathlib

import pytest

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench"
DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.mark.skipif(not (DATA / "libigl").is_dir(), reason=f"shared assets not found at {DATA}")
def test_arm_case_runs_and_fits_better_than_its_weights(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_fit_skin", BENCH / "fit_skin.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "fit.json"
    code = mod.main(["--data", str(DATA), "--only", "arm", "--helpers", "2", "--json", str(out),
                     "--curve", str(tmp_path / "curve.png")])
    assert code == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["set"] for r in rows] == ["training", "held-out"]
    held = rows[1]
    assert held["report"]["errors"][next(k for k in held["report"]["errors"] if k != "training")]["frames"] == \
        mod.RANDOM_POSES
    assert 0 < held["rms_pct"] < held["authored_rms_pct"]
    assert (tmp_path / "curve.png").stat().st_size > 0
