"""Smoke test of bench/cold_build.py: one round of one program, and its argument errors."""
from __future__ import annotations

import json
import pathlib
import subprocess
import sys

SCRIPT = pathlib.Path(__file__).resolve().parent.parent / "bench" / "cold_build.py"


def test_one_round_records_every_phase(tmp_path):
    out = tmp_path / "cold.json"
    subprocess.run([sys.executable, str(SCRIPT), "--rounds", "1", "--methods", "lbs", "--json", str(out)],
                   check=True, capture_output=True, text=True, timeout=600)
    doc = json.loads(out.read_text())
    row = doc["programs"]["lbs"]
    assert list(doc["programs"]) == ["lbs"] and row["program"] == "skinning.cl" and row["options"] == ["-DLBS_KERNEL"]
    for phase in ("context", "build", "warm_up"):
        assert row[f"{phase}_wall_ms"]["median"] > 0 and row[f"{phase}_cpu_ms"]["median"] > 0
    assert row["rss_mb_after"]["median"] >= row["rss_mb_before"]["median"] > 0


def test_bad_arguments_exit_2():
    for args in (["--rounds", "0"], ["--methods", "lbs,nope"]):
        got = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=60)
        assert got.returncode == 2 and got.stderr.count("\n") == 1 and "cold_build:" in got.stderr
