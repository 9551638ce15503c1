"""The command line's contract under hostile use: empty values refused, a budget checked before
work, all outputs committed together, a closed stdout pipe ending quietly, one-line warnings."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_run import DATA, needs_data, run
from nrpose.cli import EXIT_PIPE
from nrpose.io.files import atomic_path, on_commit, output_transaction
from nrpose.io.meshes import write_geometry
from nrpose.model.handles import handles_document
from nrpose.rigs import cylinder

FOX = DATA / "gltf" / "Fox.glb"


@pytest.fixture()
def deform_case(tmp_path):
    V, F = cylinder.cylinder_mesh(rings=11, sectors=8)
    mesh = tmp_path / "cyl.obj"
    write_geometry(mesh, V, F)
    handles = tmp_path / "handles.json"
    handles.write_text(json.dumps(handles_document(cylinder.rest_handles(), cylinder.bend_pose(40), alpha=2.0)))
    return mesh, handles, V, F


@pytest.mark.parametrize("args, flag", [
    (["pose", "x.glb", "--clip", "", "-o", "o.npz"], "--clip"),
    (["pose", "x.glb", "--pose", "", "-o", "o.npz"], "--pose"),
    (["pose", "x.glb", "--rest", "-o", ""], "-o/--output"),
    (["pose", "x.glb", "--rest", "-o", "o.npz", "--png", " "], "--png"),
    (["info", ""], "character"),
    (["retarget", "a.bvh", "b.glb", "-o", "r.glb", "--map", ""], "--map"),
])
def test_empty_values_are_refused_by_name(tmp_path, capsys, monkeypatch, args, flag):
    monkeypatch.chdir(tmp_path)
    code, _, err = run(args, capsys)
    assert code == 2 and err == f"nrpose {args[0]}: {flag}: empty value; give a name\n"
    assert list(tmp_path.iterdir()) == []


@needs_data
def test_budget_is_checked_before_work_with_the_estimate(tmp_path, capsys):
    out = tmp_path / "o.glb"
    code, _, err = run(["pose", FOX, "--clip", "Run", "--fps", "1e4", "-o", out], capsys)
    assert code == 2 and err.count("\n") == 1 and "frames, more than --max-frames 10,000" in err
    # 4 frames x 1,728 vertices x 3 = 20,736 numbers (+ 16 morph weights in a .glb)
    code, _, err = run(["pose", FOX, "--clip", "Run", "--frames", "0:3", "--max-output-values", "20000",
                        "-o", out], capsys)
    assert code == 2 and "2.08e+04 numbers, more than --max-output-values 2e+04" in err, err
    code, _, err = run(["pose", FOX, "--clip", "Run", "--frames", "0:3", "--max-frames", "3", "-o", out], capsys)
    assert code == 2 and "4 frames, more than --max-frames 3" in err
    assert list(tmp_path.iterdir()) == []
    code, _, err = run(["pose", FOX, "--clip", "Run", "--frames", "0:3", "--max-frames", "4",
                        "--max-output-values", "20752", "-o", out], capsys)
    assert code == 0 and out.is_file()


def test_output_transaction_commits_all_or_nothing(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    with pytest.raises(RuntimeError):
        with output_transaction():
            with atomic_path(a) as tmp:
                tmp.write_text("a")
            assert not a.exists()            # written, not yet committed
            raise RuntimeError("the second output failed")
    assert list(tmp_path.iterdir()) == []
    with output_transaction():
        for p in (a, b):
            with atomic_path(p) as tmp:
                tmp.write_text(p.name)
    assert a.read_text() == "a.txt" and b.read_text() == "b.txt"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
    # a commit that fails (the first output's rename, say) leaves the later outputs' temporaries nowhere
    d = tmp_path / "d.txt"

    def failing_commit():
        raise OSError(17, "File exists", "first output")
    with pytest.raises(OSError):
        with output_transaction():
            on_commit(failing_commit, lambda: None)
            with atomic_path(d) as tmp:
                tmp.write_text("d")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


@needs_data
def test_frames_into_an_existing_non_directory_are_refused_first(tmp_path, capsys):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    code, _, err = run(["pose", FOX, "--clip", "Run", "--frames", "0:1", "-o", fifo, "--png", tmp_path / "s.png"],
                       capsys)
    assert code == 2 and "is not a directory" in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo"]


def test_too_many_segments_refused_before_weights(tmp_path, capsys):
    V = np.random.default_rng(0).normal(size=(30, 3))
    write_geometry(tmp_path / "m.xyz", V, np.zeros((0, 3), np.int64))
    seg = {"rest": [[0, 0, 0], [1, 0, 0]], "pose": [[0, 0, 0], [1, 0, 0]]}
    (tmp_path / "h.json").write_text(json.dumps({"segments": [seg] * 2049}))
    code, _, err = run(["deform", tmp_path / "m.xyz", "-H", tmp_path / "h.json", "-o", tmp_path / "o.xyz",
                        "--weights", "graph"], capsys)
    assert code == 2 and "2,049 segment handles: at most 2,048" in err


def test_a_failing_png_leaves_no_main_output(deform_case, tmp_path, capsys, monkeypatch):
    mesh, handles = deform_case[:2]

    def broken_preview(path, *args, **kw):
        raise OSError(28, "No space left on device", str(path))
    monkeypatch.setattr("nrpose.cli.deform.save_preview", broken_preview)
    before = sorted(tmp_path.iterdir())
    code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.ply", "--png", tmp_path / "p.png",
                        "--backend", "numpy"], capsys)
    assert code == 2 and err.count("\n") == 1 and "No space left" in err
    assert sorted(tmp_path.iterdir()) == before


def test_out_of_memory_is_one_line_and_leaves_no_output(deform_case, tmp_path, capsys, monkeypatch):
    mesh, handles = deform_case[:2]

    def exhausted(path, *args, **kw):
        raise MemoryError
    monkeypatch.setattr("nrpose.cli.deform.save_preview", exhausted)
    before = sorted(tmp_path.iterdir())
    code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.ply", "--png", tmp_path / "p.png",
                        "--backend", "numpy"], capsys)
    assert code == 2 and err.count("\n") == 1 and err.startswith("nrpose: error: out of memory")
    assert sorted(tmp_path.iterdir()) == before


@needs_data
def test_failing_frames_leave_no_directory(tmp_path, capsys, monkeypatch):
    import nrpose.io.meshes as meshes
    written = []

    def write_one_then_fail(path, *args):
        if written:
            raise OSError(27, "File too large", str(path))
        written.append(path)
        Path(path).write_text("frame")
    monkeypatch.setattr(meshes, "write_geometry", write_one_then_fail)
    code, _, err = run(["pose", FOX, "--clip", "Run", "--frames", "0:2", "-o", tmp_path / "frames"], capsys)
    assert code == 2 and err.count("\n") == 1 and written
    assert list(tmp_path.iterdir()) == []


def test_unwritable_directory_is_refused_before_work(deform_case, tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only directories")
    mesh, handles = deform_case[:2]
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o555)
    code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.ply", "--png", ro / "p.png"], capsys)
    assert code == 2 and "cannot write in" in err and not (tmp_path / "o.ply").exists()


@needs_data
def test_closed_stdout_pipe_ends_quietly():
    """`nrpose info X | head`: the reader has gone before nrpose writes (a real pipe)."""
    r, w = os.pipe()
    os.close(r)
    try:
        proc = subprocess.run([sys.executable, "-m", "nrpose", "info", str(FOX)], stdout=w,
                              stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(w)
    assert proc.returncode == EXIT_PIPE and proc.stderr == b""


def test_warnings_are_one_line(deform_case, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("NRPOSE_CACHE_DIR", str(tmp_path / "cache"))     # distances computed, not cached
    mesh, handles, V, F = deform_case
    V = V.copy()
    V[5] = [0, 5e7, 0]           # a stray vertex: heat geodesics fall back to graph distances
    write_geometry(mesh, V, F)
    code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.ply", "--weights", "heat",
                        "--backend", "numpy"], capsys)
    assert code == 0 and err.startswith("nrpose: warning: heat geodesics:") and err.count("\n") == 1
    # a run that fails after a warning prints its error line only

    def broken_preview(path, *args, **kw):
        raise OSError(27, "File too large", str(path))
    monkeypatch.setattr("nrpose.cli.deform.save_preview", broken_preview)
    monkeypatch.setenv("NRPOSE_CACHE_DIR", str(tmp_path / "cache2"))
    code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o2.ply", "--weights", "heat",
                        "--backend", "numpy", "--png", tmp_path / "p.png"], capsys)
    assert code == 2 and err.startswith("nrpose: error:") and "File too large" in err and err.count("\n") == 1


def test_values_beyond_the_kernels_range_are_refused(deform_case, tmp_path, capsys):
    mesh, handles, V, F = deform_case
    doc = json.loads(handles.read_text())
    doc["points"] = [{"rest": [0, 0, 0], "pose": [3.5e38, 0, 0]}]
    handles.write_text(json.dumps(doc))
    code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.ply"], capsys)
    assert code == 2 and "exceeds the largest" in err and err.count("\n") == 1
    write_geometry(mesh, V * 1e20, F)
    code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.ply", "--weights", "heat"], capsys)
    assert code == 2 and "exceeds the largest" in err and not (tmp_path / "o.ply").exists()


@needs_data
def test_pose_translation_beyond_range_is_refused(tmp_path, capsys):
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"translations": {"b_Root_00": [1e308, 0, 0]}}))
    code, _, err = run(["pose", FOX, "--pose", pose, "-o", tmp_path / "o.npz"], capsys)
    assert code == 2 and "exceeds the largest" in err and err.count("\n") == 1
    assert not np.any([p.suffix == ".npz" for p in tmp_path.iterdir()])
