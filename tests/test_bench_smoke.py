"""Smoke test of bench/table1.py at tiny sizes (--quick: 500 points, 3 poses per row).

Checks that the benchmark runs end to end and writes a complete JSON document
with positive, finite figures. No timing assertions: this is not a benchmark.
"""
from __future__ import annotations

import importlib.util
import json
import math
import pathlib

import pytest

pytest.importorskip("pyopencl")
pytest.importorskip("pymeshlab")

BENCH = pathlib.Path(__file__).resolve().parent.parent / "bench" / "table1.py"

ROW_FIELDS = {"model", "kind", "points", "handles", "paper_points", "paper_ms", "paper_ms_per_point_handle",
              "source", "bbox_diagonal", "bind_ms", "bind_first_ms", "bind_numpy_ms", "pose_make_ms", "pocl_pose_ms",
              "pocl_pose_into_ms", "pocl_pose_after_pause_ms", "pocl_pose_warmup_ms", "numpy_pose_ms", "speedup_vs_numpy",
              "pocl_batched_per_frame_ms", "batch_frames", "batched_speedup_vs_numpy",
              "pocl_ms_per_point_handle", "numpy_ms_per_point_handle",
              "paper_over_pocl", "max_error_rel_bbox", "handles_rest"}
STATS = {"median", "p10", "p90", "min", "max", "n"}


@pytest.fixture(scope="module")
def table1():
    spec = importlib.util.spec_from_file_location("bench_table1", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def quick_run(table1, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    code = table1.main(["--quick", "--repeat", "1", "--json", str(out / "t.json"), "--png", str(out / "t.png")])
    assert code == 0
    return json.loads((out / "t.json").read_text()), out


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def test_document_fields(quick_run):
    doc, out = quick_run
    assert doc["schema"] == "nrpose-bench-table1/1"
    for key in ("timestamp", "git_commit", "git_commit_end", "git_dirty", "nrpose_path", "options", "environment",
                "device_setup_ms", "source", "rows", "targets"):
        assert key in doc, key
    assert doc["options"]["quick"] is True
    assert doc["source"] in ("meshes", "synthetic", "mixed")
    env = doc["environment"]
    for key in ("python", "numpy", "pyopencl", "device"):
        assert env[key], key
    assert env["device"]["compute_units"] >= 1
    t = doc["targets"]
    assert t["meaningful"] is False and t["row"] == "dragon/segments"
    dragon = next(r for r in doc["rows"] if (r["model"], r["kind"]) == ("dragon", "segments"))
    assert t["pose_ms"] == dragon["pocl_pose_ms"]["median"] and t["speedup"] == dragon["speedup_vs_numpy"]
    assert t["pose_ms_met"] is (t["pose_ms"] <= t["pose_ms_max"])
    assert t["speedup_met"] is (t["speedup"] >= t["speedup_min"])
    assert t["speedup_met_all_rows"] is all(r["speedup_vs_numpy"] >= t["speedup_min"] for r in doc["rows"])
    assert t["batched_per_frame_ms"] == dragon["pocl_batched_per_frame_ms"]["median"]
    assert _positive(t["batched_speedup"])
    assert (out / "t.png").stat().st_size > 1000


def test_rows(quick_run):
    doc, _ = quick_run
    rows = doc["rows"]
    assert [(r["model"], r["kind"]) for r in rows] == [
        (m, k) for m in ("dragon", "bunny", "armadillo", "box") for k in ("segments", "points")]
    for r in rows:
        assert ROW_FIELDS <= set(r), ROW_FIELDS - set(r)
        assert r["points"] == 500
        for key in ("bind_ms", "bind_numpy_ms", "pose_make_ms", "pocl_pose_ms", "pocl_pose_into_ms",
                    "pocl_pose_after_pause_ms", "pocl_batched_per_frame_ms",
                    "numpy_pose_ms"):
            assert set(r[key]) == STATS
            assert r[key]["n"] >= 1
            assert all(_positive(r[key][s]) for s in STATS - {"n"}), (r["model"], key, r[key])
        assert _positive(r["bind_first_ms"]), r["bind_first_ms"]
        assert r["pocl_pose_ms"]["n"] == 3 * 3 and r["pocl_pose_ms"]["p10"] <= r["pocl_pose_ms"]["p90"]
        assert r["pocl_pose_after_pause_ms"]["n"] == 1 and r["pocl_pose_into_ms"]["n"] == 3
        warm = r["pocl_pose_warmup_ms"]       # by elapsed time in the block; bins hold every pose
        assert sum(warm["n"]) == r["pocl_pose_ms"]["n"] and warm["from_ms"][0] == 0.0
        assert all(_positive(m) for m in warm["median_ms"]) and warm["from_ms"] == sorted(warm["from_ms"])
        assert r["batch_frames"] == 3
        for key in ("paper_ms", "bbox_diagonal", "speedup_vs_numpy", "batched_speedup_vs_numpy",
                    "pocl_ms_per_point_handle",
                    "numpy_ms_per_point_handle", "paper_over_pocl", "paper_ms_per_point_handle"):
            assert _positive(r[key]), (r["model"], key, r[key])
        # PoCL (float32) agrees with the float64 reference; 0 only if exact
        assert math.isfinite(r["max_error_rel_bbox"]) and 0 <= r["max_error_rel_bbox"] < 1e-4
        n_seg = len(r["handles_rest"]["segments"])
        n_pts = len(r["handles_rest"]["points"])
        assert (n_seg, n_pts) == ((r["handles"], 0) if r["kind"] == "segments" else (0, r["handles"]))


def test_synthetic_fallback(table1, tmp_path):
    doc = table1.run(repeat=1, quick=True, data=tmp_path / "absent")
    assert doc["source"] == "synthetic"
    kinds = {r["model"]: r["source"]["kind"] for r in doc["rows"]}
    assert kinds["dragon"] == kinds["bunny"] == kinds["armadillo"] == "synthetic"
    assert all(_positive(r["pocl_pose_ms"]["median"]) for r in doc["rows"])


def test_handles_deterministic(table1):
    import numpy as np
    v = table1.synthetic_points(2000, 7)
    a, b = table1.chain_handles(v, 5), table1.chain_handles(v.copy(), 5)
    assert np.array_equal(a.segments, b.segments)
    # a connected chain spanning the extent along the first principal axis
    assert np.allclose(a.segments[1:, 0], a.segments[:-1, 1])
    p, q = table1.fps_handles(v, 6), table1.fps_handles(v, 6)
    assert np.array_equal(p.points, q.points) and len(np.unique(p.points, axis=0)) == 6
    rest = a
    pose = table1.chain_pose_args(rest, np.random.default_rng(3))
    assert np.allclose(pose["segments"][1:, 0], pose["segments"][:-1, 1])  # FK keeps it connected
    assert np.allclose(pose["segments"][0, 0], rest.segments[0, 0])
