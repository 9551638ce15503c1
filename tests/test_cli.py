"""The command line: deform, pose, info, demo; one-line errors with exit status 2, no partial output."""
from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from nrpose import Deformer, DeviceError
from nrpose.io import load_character
from cli_run import DATA, needs_data, run
from nrpose.model.handles import handles_document
from nrpose.io.meshes import read_geometry, write_geometry
from nrpose.pose.blend import DEFAULT_BLEND
from nrpose.pose.poser import CharacterPoser
from nrpose.rigs import box, cylinder



@pytest.fixture()
def cylinder_case(tmp_path):
    V, F = cylinder.cylinder_mesh(rings=21, sectors=12)
    mesh = tmp_path / "cyl.obj"
    write_geometry(mesh, V, F)
    pose = cylinder.bend_pose(60)
    handles = tmp_path / "handles.json"
    handles.write_text(json.dumps(handles_document(cylinder.rest_handles(), pose, alpha=2.0)))
    return mesh, handles, V, F, pose


@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_deform_writes_mesh_matching_the_api(cylinder_case, tmp_path, capsys, backend):
    mesh, handles, V, F, pose = cylinder_case
    out = tmp_path / "out.ply"
    code, stdout, _ = run(["deform", mesh, "-H", handles, "-o", out, "--backend", backend, "--png",
                           tmp_path / "p.png"], capsys)
    assert code == 0 and "pose" in stdout
    g = read_geometry(out)
    expect = Deformer(V, cylinder.rest_handles(), alpha=2.0, backend=backend).pose(pose)
    assert np.array_equal(g.faces, F)
    assert np.abs(g.vertices - expect).max() <= 1e-5
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("blend", ["paper", "quaternion"])
def test_deform_point_cloud_and_alpha_override(tmp_path, capsys, blend):
    pts = box.box_points()
    src = tmp_path / "box.xyz"
    write_geometry(src, pts)
    pose = box.chain_pose(90, 45)
    handles = tmp_path / "h.json"
    handles.write_text(json.dumps(handles_document(box.rest_handles(), pose, alpha=1.0)))
    out = tmp_path / "posed.xyz"
    code, _, _ = run(["deform", src, "-H", handles, "-o", out, "--alpha", "2", "--blend", blend], capsys)
    assert code == 0
    expect = Deformer(pts, box.rest_handles(), alpha=2.0, blend=blend).pose(pose)
    assert np.abs(read_geometry(out).vertices - expect).max() <= 1e-4


BAD_HANDLES = {
    "malformed": "{not json",
    "no handles": json.dumps({"points": [], "segments": []}),
    "nan": '{"points": [{"rest": [0, 0, NaN], "pose": [0, 0, 0]}]}',
    "zero length": json.dumps({"segments": [{"rest": [[0, 0, 0], [0, 0, 0]], "pose": [[0, 0, 0], [1, 0, 0]]}]}),
    "shape": json.dumps({"points": [{"rest": [0, 0], "pose": [0, 0, 0]}]}),
    "bad rotation": json.dumps({"segments": [{"rest": [[0, 0, 0], [1, 0, 0]], "pose": [[0, 0, 0], [0, 1, 0]],
                                              "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}]}),
    # found by fuzzing the CLI: each was a traceback
    "ragged rotation": json.dumps({"segments": [{"rest": [[0, 0, 0], [1, 0, 0]], "pose": [[0, 0, 0], [0, 1, 0]],
                                                 "rotation": [[1, 0, 0], [0, 1], [0, 0, 1]]}]}),
    "400-digit number": '{"points": [{"rest": [' + "9" * 400 + ', 0, 0], "pose": [0, 0, 0]}]}',
    "alpha true": json.dumps({"alpha": True, "points": [{"rest": [0, 0, 0], "pose": [0, 0, 1]}]}),
    "5000-digit number": '{"points": [{"rest": [' + "9" * 5000 + ', 0, 0], "pose": [0, 0, 0]}]}',
}


@pytest.mark.parametrize("case", sorted(BAD_HANDLES))
def test_deform_bad_handles_exit_2_one_line_no_output(cylinder_case, tmp_path, capsys, case):
    mesh = cylinder_case[0]
    handles = tmp_path / "bad.json"
    handles.write_text(BAD_HANDLES[case])
    out = tmp_path / "out.obj"
    code, _, err = run(["deform", mesh, "-H", handles, "-o", out], capsys)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("nrpose")
    assert {p.name for p in tmp_path.iterdir()} == {"cyl.obj", "handles.json", "bad.json"}


def test_deform_bad_inputs_exit_2(cylinder_case, tmp_path, capsys):
    mesh, handles = cylinder_case[:2]
    empty = tmp_path / "empty.xyz"
    empty.write_text("")
    nan = tmp_path / "nan.xyz"
    nan.write_text("0 0 0\nnan 1 1\n")
    for args in (["deform", empty, "-H", handles, "-o", tmp_path / "o.obj"],
                 ["deform", nan, "-H", handles, "-o", tmp_path / "o.obj"],
                 ["deform", tmp_path / "missing.obj", "-H", handles, "-o", tmp_path / "o.obj"],
                 ["deform", mesh, "-H", handles, "-o", tmp_path / "o.obj", "--alpha", "-1"],
                 ["deform", mesh, "-H", handles, "-o", tmp_path / "o.obj", "--blend", "nope"],
                 ["deform", mesh, "-o", tmp_path / "o.obj"]):
        code, _, err = run(args, capsys)
        assert code == 2 and err.count("\n") == 1, (args, err)
        assert not (tmp_path / "o.obj").exists()


def test_deform_odd_inputs_and_outputs(cylinder_case, tmp_path, capsys):
    """Fuzzing finds: a FIFO as input (its read would wait for a
    writer), a PLY face index 1.5 or an OBJ one of 23 digits, a path with a newline, a
    twist of 1e300 (a rotation like any other), and an output name of 240 characters,
    legal, whose temporary name used to be too long."""
    import os
    mesh, handles = cylinder_case[:2]
    fifo = tmp_path / "h.json"
    os.mkfifo(fifo)
    frac = tmp_path / "frac.ply"
    frac.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n3 0 1.5 2\n")
    big = tmp_path / "big.obj"
    big.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n")
    odd = tmp_path / "a\nb.obj"
    for args, needle in ((["deform", mesh, "-H", fifo, "-o", tmp_path / "o.obj"], "not a regular file"),
                         (["deform", frac, "-H", handles, "-o", tmp_path / "o.obj"], "not a whole number"),
                         (["deform", big, "-H", handles, "-o", tmp_path / "o.obj"], "big.obj"),
                         (["deform", odd, "-H", handles, "-o", tmp_path / "o.obj"], "a\\nb.obj")):
        code, _, err = run(args, capsys)
        assert code == 2 and err.count("\n") == 1 and needle in err, (args, err)
        assert not (tmp_path / "o.obj").exists()
    twist = tmp_path / "twist.json"
    twist.write_text(json.dumps({"segments": [{"rest": [[0, 0, 0], [0, 0, 1]], "pose": [[0, 0, 0], [0, 0, 1]],
                                               "twist": 1e300}]}))
    long_name = tmp_path / ("a" * 236 + ".obj")
    code, _, err = run(["deform", mesh, "-H", twist, "-o", long_name], capsys)
    assert code == 0 and np.isfinite(read_geometry(long_name).vertices).all(), err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_console_script_runs_as_module(cylinder_case, tmp_path):
    mesh, handles = cylinder_case[:2]
    res = subprocess.run([sys.executable, "-m", "nrpose", "deform", str(mesh), "-H", str(handles), "-o",
                          str(tmp_path / "x.obj"), "--alpha", "0"], capture_output=True, text=True)
    assert res.returncode == 2 and "alpha" in res.stderr and "Traceback" not in res.stderr


@needs_data
def test_pose_clip_to_npz_and_directory(tmp_path, capsys):
    fox = DATA / "gltf" / "Fox.glb"
    code, stdout, _ = run(["pose", fox, "--clip", "Walk", "--frames", "0:6:2", "--fps", "24",
                           "-o", tmp_path / "walk.npz"], capsys)
    assert code == 0 and "per frame" in stdout
    z = np.load(tmp_path / "walk.npz")
    assert z["positions"].shape == (4, 1728, 3) and z["positions"].dtype == np.float32
    assert np.allclose(z["times"], [0, 2 / 24, 4 / 24, 6 / 24])
    assert list(z["mesh_offsets"]) == [0] and z["faces"].shape[1] == 3
    code, _, _ = run(["pose", fox, "--clip", "Run", "--time", "0.1", "0.2", "--method", "dqs",
                      "-o", tmp_path / "frames", "--format", "obj"], capsys)
    assert code == 0 and sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["frame_0000.obj",
                                                                                      "frame_0001.obj"]
    # --blend reaches the poser: the relative blend's frames (not the default's) are those of the API's
    code, _, _ = run(["pose", fox, "--clip", "Walk", "--frames", "0:6:2", "--fps", "24", "--blend", "relative",
                      "-o", tmp_path / "walk_q.npz"], capsys)
    assert code == 0
    character = load_character(fox)
    clip = next(c for c in character.clips if c.name == "Walk")
    expect = CharacterPoser(character, blend="relative").pose(clip.sample(np.arange(4) * 2 / 24)).positions
    got = np.load(tmp_path / "walk_q.npz")["positions"]
    assert np.abs(got - expect).max() <= 1e-5 and np.abs(got - z["positions"]).max() > 0


@needs_data
def test_pose_errors_exit_2_nothing_written(tmp_path, capsys):
    fox = DATA / "gltf" / "Fox.glb"
    bad = tmp_path / "pose.json"
    bad.write_text(json.dumps({"rotations": {"b_Hipp_01": [0, 0, 0, 1]}}))
    truncated = tmp_path / "fox.glb"
    truncated.write_bytes(fox.read_bytes()[:5000])
    cases = [(["pose", fox, "--clip", "Run", "--time", "99", "-o", tmp_path / "o.npz"], "outside"),
             (["pose", fox, "--clip", "Jump", "-o", tmp_path / "o.npz"], "Survey"),
             (["pose", fox, "--pose", bad, "-o", tmp_path / "o.npz"], "b_Hip_01"),
             (["pose", truncated, "--rest", "-o", tmp_path / "o.npz"], "fox.glb"),
             (["pose", fox, "--clip", "Run", "--frames", "5:2", "-o", tmp_path / "o.npz"], "frames"),
             (["pose", fox, "--clip", "Run", "--frames", "0:99999999999999999999", "-o", tmp_path / "o.npz"],
              "more than 1,000,000"),
             (["pose", fox, "--clip", "Run", "--fps", "1e9", "-o", tmp_path / "o.npz"], "more than 1,000,000"),
             (["pose", fox, "--rest", "--time", "1", "-o", tmp_path / "o.npz"], "--rest or --pose"),
             (["pose", fox, "--clip", "Run", "--frames", "0:" + "9" * 400, "-o", tmp_path / "o.npz"], "1e+300")]
    for args, needle in cases:
        code, _, err = run(args, capsys)
        assert code == 2 and err.count("\n") == 1 and needle in err, (args, err)
        assert not (tmp_path / "o.npz").exists()


@needs_data
def test_info_lists_meshes_joints_clips(capsys):
    code, stdout, _ = run(["info", DATA / "gltf" / "Fox.glb"], capsys)
    assert code == 0
    assert "1728 vertices" in stdout and "joints: 24" in stdout and "Run:" in stdout


def test_a_malformed_second_clip_fails_only_the_jobs_that_use_it(tmp_path, capsys):
    """Clips are decoded when used: the first clip poses; asking for the second names its fault in
    one line (exit 2, nothing written), as does ``info``, which lists every clip."""
    from test_io_gltf_read import BROKEN, malformed_second_clip

    path = malformed_second_clip(tmp_path / "two.glb")
    out = tmp_path / "o.npz"
    code, stdout, err = run(["pose", path, "--clip", "clip", "--method", "lbs", "--backend", "numpy",
                             "--time", "0", "1", "-o", out], capsys)
    assert code == 0 and np.load(out)["positions"].shape == (2, 7, 3), err
    out.unlink()
    for args in (["pose", path, "--clip", "broken", "--method", "lbs", "--backend", "numpy", "-o", out],
                 ["info", path]):
        code, stdout, err = run(args, capsys)
        assert code == 2 and err.count("\n") == 1 and re.search(BROKEN, err), (args, err)
        assert stdout == "" and not out.exists()


def test_demo_writes_pngs_and_prints_timing(tmp_path, capsys):
    code, stdout, _ = run(["demo", "--out", tmp_path, "--repeat", "3", "--frames", "4"], capsys)
    assert code == 0 and "pose" in stdout and "numpy reference" in stdout and "per frame" in stdout
    z = np.load(tmp_path / "walk.npz")
    assert z["positions"].shape[0] == 4 and np.isfinite(z["positions"]).all()
    for name in ("box_before.png", "box_after.png", "box_twist.ply", "walk.png", "walk.glb"):
        assert (tmp_path / name).stat().st_size > 0


def test_no_opencl_platform_is_one_line_with_install_hint(cylinder_case, tmp_path, capsys, monkeypatch):
    import pyopencl

    from nrpose import device

    mesh, handles = cylinder_case[:2]
    monkeypatch.setattr(pyopencl, "get_platforms", lambda: [])
    device.context.cache_clear()
    try:
        code, _, err = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.obj"], capsys)
    finally:
        device.context.cache_clear()
    assert code == 2 and err.count("\n") == 1
    assert "no OpenCL platform" in err and "pip install" in err
    assert not (tmp_path / "o.obj").exists()
    # the numpy reference needs no device
    code, _, _ = run(["deform", mesh, "-H", handles, "-o", tmp_path / "o.obj", "--backend", "numpy"], capsys)
    assert code == 0


def test_pyopencl_ctx_is_honoured(monkeypatch):
    from nrpose import device

    monkeypatch.setenv("PYOPENCL_CTX", "0")
    device.context.cache_clear()
    try:
        ctx, _ = device.context()
        assert ctx.devices
        monkeypatch.setenv("PYOPENCL_CTX", "99")
        device.context.cache_clear()
        with pytest.raises(DeviceError, match="PYOPENCL_CTX"):
            device.context()
    finally:
        monkeypatch.delenv("PYOPENCL_CTX")
        device.context.cache_clear()


def test_unwritable_png_or_output_fails_before_any_work(cylinder_case, tmp_path, capsys):
    mesh, handles = cylinder_case[:2]
    out = tmp_path / "out.ply"
    for args in (["deform", mesh, "-H", handles, "-o", out, "--png", tmp_path / "missing" / "p.png"],
                 ["deform", mesh, "-H", handles, "-o", tmp_path / "missing" / "o.ply"],
                 ["deform", mesh, "-H", handles, "-o", tmp_path / "out.abc"],
                 ["deform", mesh, "-H", handles, "-o", out, "--png", tmp_path / "p.jpg"]):
        code, _, err = run(args, capsys)
        assert code == 2 and err.count("\n") == 1, (args, err)
        assert not out.exists()


@needs_data
def test_pose_bad_fps_and_png_leave_nothing(tmp_path, capsys):
    fox = DATA / "gltf" / "Fox.glb"
    out = tmp_path / "o.npz"
    for args in (["pose", fox, "--clip", "Run", "--fps", "0", "-o", out],
                 ["pose", fox, "--clip", "Run", "--fps", "nan", "-o", out],
                 ["pose", fox, "--clip", "Run", "--fps", "-30", "-o", out],
                 ["pose", fox, "--clip", "Run", "-o", out, "--png", tmp_path / "no" / "s.png"],
                 ["pose", fox, "--clip", "Run", "--time", "0.5", "0.2", "-o", tmp_path / "o.glb"]):
        code, _, err = run(args, capsys)
        assert code == 2 and err.count("\n") == 1, (args, err)
        assert list(tmp_path.iterdir()) == []


@needs_data
def test_pose_directory_output_replaces_previous_frames(tmp_path, capsys):
    fox = DATA / "gltf" / "Fox.glb"
    frames = tmp_path / "frames"
    assert run(["pose", fox, "--clip", "Run", "--frames", "0:3", "-o", frames], capsys)[0] == 0
    assert run(["pose", fox, "--clip", "Run", "--frames", "0:1", "-o", frames], capsys)[0] == 0
    assert sorted(p.name for p in frames.iterdir()) == ["frame_0000.ply", "frame_0001.ply"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]      # no temporary left


def test_library_argument_names_become_the_commands_flags():
    """Library errors name arguments (``weights='euclidean'``, ``skeleton=``, ``format_map()``);
    the CLI prints the flags of the command that ran."""
    from nrpose.cli import flag_text
    from nrpose.cli import pose as pose_cmd, retarget as retarget_cmd, weights as weights_cmd

    msg = "mesh 'm' has no skin weights; use weights='euclidean' (or heat, exact, graph)"
    assert flag_text(msg, pose_cmd.FLAGS) == "mesh 'm' has no skin weights; use --weights euclidean (or heat, exact, graph)"
    assert flag_text(msg, weights_cmd.FLAGS) == "mesh 'm' has no skin weights; use --method euclidean (or heat, exact, graph)"
    assert (flag_text("drop blend= or use method='nrmls'", pose_cmd.FLAGS)
            == "drop --blend or use --method nrmls")
    assert flag_text("pass the skeleton with skeleton=", pose_cmd.FLAGS) == "pass the skeleton with --skeleton"
    assert (flag_text('give a joint map (user_map= {"T": "S"}); check it (see format_map())', retarget_cmd.FLAGS)
            == 'give a joint map (--map MAP.json, {"T": "S"}); check it (see --show-map)')
    # names a command does not know, and name=value pairs that are not arguments, stay as they are
    assert flag_text("blend= in x=1, f(), alpha=2", {"blend": "--blend"}) == "--blend in x=1, f(), alpha=2"


@needs_data
def test_pose_default_method_is_nrmls_with_the_default_blend(tmp_path, capsys):
    """Without --method: nrmls for every kind of weights, with the default (tree-signed
    quaternion) blend; the frames are that poser's."""
    fox = DATA / "gltf" / "Fox.glb"
    for extra in ([], ["--weights", "euclidean"]):
        out = tmp_path / f"default_{len(extra)}.npz"
        code, stdout, _ = run(["pose", fox, "--clip", "Run", "--time", "0.3", "-o", out, *extra], capsys)
        assert code == 0 and ", nrmls (" in stdout
    character = load_character(fox)
    expect = CharacterPoser(character, method="nrmls", blend=DEFAULT_BLEND).pose(
        character.clip("Run").sample(np.array([0.3]))).positions
    assert np.abs(np.load(tmp_path / "default_0.npz")["positions"] - expect).max() <= 1e-5
