"""Smoke test of the e2e benchmark suite (bench/e2e.py) in its tiny mode, and its helpers.

The tiny run (Fox, NR-MLS, one round, no Blender; ~1 minute, most of it PoCL compiling in
the cold runs) checks the record's schema and that its figures are positive and finite.
No timing assertions.
"""
from __future__ import annotations

import json
import math
import pathlib
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(ROOT / "bench"))

e2e = pytest.importorskip("e2e")


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def test_import_times_parses_nesting_and_leaves_out_startup():
    text = "\n".join([
        "import time: self [us] | cumulative | imported package",
        "import time:       100 |        100 | encodings",
        "import time:        50 |         50 |   numpy.core",
        "import time:       200 |        250 | numpy",
        "import time:      1000 |       1000 |     matplotlib.pyplot",
        "import time:        10 |       1010 |   matplotlib",
        "import time:        30 |       1040 | nrpose",
    ])
    r = e2e.import_times(text, startup={"encodings"})
    assert r["total_s"] == pytest.approx((250 + 1040) * 1e-6)
    assert r["startup_s"] == pytest.approx(100e-6)
    assert r["modules"] == ["encodings", "numpy.core", "numpy", "matplotlib.pyplot", "matplotlib", "nrpose"]
    assert [t["module"] for t in r["top"]] == ["nrpose", "numpy"]
    assert r["heavy_imported"]["matplotlib"] and not r["heavy_imported"]["pygltflib"]


def test_agreement_matches_vertices_by_position(tmp_path):
    rng = np.random.default_rng(1)
    pos = rng.normal(size=(4, 50, 3)).astype(np.float32)
    perm = rng.permutation(50)
    np.savez(tmp_path / "ours.npz", positions=pos, mesh_names=np.array(["body"]), mesh_offsets=np.array([0]))
    np.savez(tmp_path / "same.npz", names=np.array(["body"]), positions_0=pos[:, perm])
    moved = pos[:, perm].copy()
    moved[2, 7] += np.float32([0.0, 0.01, 0.0])        # one vertex of frame 2 off by 0.01
    np.savez(tmp_path / "moved.npz", names=np.array(["body"]), positions_0=moved)
    np.savez(tmp_path / "other.npz", names=np.array(["hat"]), positions_0=pos)
    diag = float(np.linalg.norm(pos[0].max(axis=0) - pos[0].min(axis=0)))
    same = e2e.agreement(tmp_path / "ours.npz", tmp_path / "same.npz")
    assert same["max_rel"] == 0.0 and same["within_tolerance"]
    moved = e2e.agreement(tmp_path / "ours.npz", tmp_path / "moved.npz")
    assert moved["max_rel"] == pytest.approx(0.01 / diag, rel=1e-4)
    assert moved["worst_frame"] == 2 and moved["frame0_max_rel"] == 0.0
    assert "error" in e2e.agreement(tmp_path / "ours.npz", tmp_path / "other.npz")


def test_agreement_splits_meshes_at_their_offsets(tmp_path):
    rng = np.random.default_rng(2)
    pos = rng.normal(size=(3, 30, 3)).astype(np.float32)
    np.savez(tmp_path / "ours.npz", positions=pos, mesh_names=np.array(["a", "b"]), mesh_offsets=np.array([0, 10]))
    # Blender's meshes in another order; "b" (20 vertices) exactly, "a" shifted by 0.5 in frame 1
    a = pos[:, :10].copy()
    a[1] += 0.5
    np.savez(tmp_path / "theirs.npz", names=np.array(["b", "a"]), positions_0=pos[:, 10:], positions_1=a)
    diag = float(np.linalg.norm(pos[0].max(axis=0) - pos[0].min(axis=0)))
    r = e2e.agreement(tmp_path / "ours.npz", tmp_path / "theirs.npz")
    assert r["vertices"] == 30 and r["worst_frame"] == 1
    assert r["max_rel"] == pytest.approx(0.5 * np.sqrt(3) / diag, rel=1e-5)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    if not (DATA / "gltf" / "Fox.glb").exists():
        pytest.skip(f"shared data not found at {DATA}")
    pytest.importorskip("pyopencl")
    out = tmp_path_factory.mktemp("e2e") / "e2e.json"
    assert e2e.main(["--quick", "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_quick_record_schema(quick):
    assert quick["schema"] == "nrpose-bench-e2e/1"
    assert quick["options"]["quick"] and quick["options"]["characters"] == ["fox"]
    for key in ("timestamp", "git_commit", "environment", "load_start", "load_end", "modes", "measure", "targets"):
        assert key in quick
    assert set(quick["modes"]) == {"cold", "warm"}
    assert quick["blender"]["available"] is False and quick["blender"]["reason"]
    floor = [r for r in quick["rows"] if r["who"] == "floor"]      # the OpenCL floor, in both modes
    assert sorted(r["mode"] for r in floor) == ["cold", "warm"]
    assert all(r["output"] is None and _positive(r["wall_ms"]["median"]) for r in floor)
    rows = [r for r in quick["rows"] if r["who"] != "floor"]
    from nrpose.io import load_character
    from nrpose.model.timing import sample_times
    fox = load_character(DATA / "gltf" / "Fox.glb")
    frames = len(sample_times(fox.clip("Run").duration, 30))       # the whole clip at 30 fps
    vertices = sum(len(m.vertices) for m in fox.meshes)
    assert {(r["output"], r["mode"]) for r in rows} == {(o, m) for o in ("npz", "glb") for m in ("cold", "warm")}
    for r in rows:
        assert r["character"] == "fox" and r["who"] == "nrpose" and r["method"] == "nrmls"
        assert r["frames"] == frames and r["vertices"] == vertices
        assert all(_positive(r["wall_ms"][k]) for k in ("median", "p10", "p90", "min", "max"))
        assert r["wall_ms"]["n"] == 1 and _positive(r["peak_rss_mib"]["median"]) and _positive(r["cpu_ms"]["median"])
        assert r["vs_blender"] is None
        assert r["evicted_input"] in ((True, False) if r["mode"] == "cold" else (None,))


def test_quick_breakdown(quick):
    (b,) = quick["breakdown"]
    assert (b["character"], b["method"], b["output"]) == ("fox", "nrmls", "npz")
    assert _positive(b["imports_s"]) and _positive(b["job_s"]) and _positive(b["profiled_job_s"])
    assert set(b["stages_s"]) == {"load", "bind", "pose", "write"}
    assert all(_positive(v) for v in b["stages_s"].values()), b["stage_functions"]   # every rule matched
    assert sum(b["stages_s"].values()) <= b["job_s"]
    assert b["top_tottime"] and b["import_top"] and set(b["heavy_imported"]) == set(e2e.HEAVY_MODULES)


def test_quick_targets_not_meaningful(quick):
    assert quick["targets"] and all(not t["meaningful"] for t in quick["targets"])
    assert all(set(t) >= {"name", "target", "measured", "met"} for t in quick["targets"])
