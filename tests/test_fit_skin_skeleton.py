"""nrpose fit-skin on a mesh with a TGF or BVH skeleton: the fit written as a new skinned glTF.

Oracles: NR-MLS of the mesh + skeleton character itself (the report's errors must be what
the written file plays), exactness on a rigid motion, and three.js and Blender playing
the file as nrpose's LBS of it.
"""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from nrpose.cli import main
from nrpose.fit.character_skin import nrmls_targets
from nrpose.io import load_character
from nrpose.io.bvh_write import write_bvh
from nrpose.io.meshes import write_geometry
from nrpose.io.tgf import read_dmat_animation
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import LocalPose
from nrpose.model.timing import sample_times
from nrpose.pose.poser import CharacterPoser
from nrpose.rigs.cylinder import cylinder_mesh
from nrpose.rigs.humanoid import humanoid

from dmat_files import motion_matrix, write_dmat
from fit_skin_played import blender_errors, three_js_errors

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LIBIGL = DATA / "libigl"
needs_data = pytest.mark.skipif(not LIBIGL.is_dir(), reason=f"shared assets not found at {DATA}")
TGF = "1 0 0 0\n2 1 0 0\n3 2 0 0\n#\n1 2\n2 3\n#\n"      # two unit bones along +x
FRAMES = 12


def quat(axis, degrees):
    return Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, float)).as_quat()


def run(args, capsys):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def tube(tmp_path_factory):
    """A closed tube (OBJ) around two bones (TGF); a bend-and-twist animation DMAT of 12 frames, a
    training pose JSON and a rigid-turn pose JSON beside them."""
    d = tmp_path_factory.mktemp("tube")
    V, F = cylinder_mesh(rings=31, sectors=16)
    write_geometry(d / "tube.obj", V, F)
    (d / "tube.tgf").write_text(TGF)
    character = load_character(d / "tube.obj", d / "tube.tgf")
    skeleton = character.skeleton
    s = np.linspace(0.0, 1.0, FRAMES)
    rotation = np.tile(skeleton.rest_pose.rotation, (FRAMES, 1, 1))
    rotation[:, 0] = Rotation.from_rotvec(np.outer(np.radians(30) * s, [1, 0, 0])).as_quat()
    rotation[:, 1] = Rotation.from_rotvec(np.outer(np.radians(100) * s, [0, 0, 1])).as_quat()
    pose = LocalPose(np.tile(skeleton.translation, (FRAMES, 1, 1)), rotation, np.ones((FRAMES, 2, 3)))
    write_dmat(d / "bend.dmat", motion_matrix(skeleton, skeleton.forward_kinematics(pose)))
    (d / "pose.json").write_text(json.dumps({"rotations": {"bone1": quat([0, 1, 0], 60).tolist()}}))
    (d / "rigid.json").write_text(json.dumps({"rotations": {"bone0": quat([1, 1, 0], 70).tolist()}}))
    return d, character


@pytest.fixture(scope="module")
def fitted_tube(tube, tmp_path_factory):
    """The tube fitted with its default (heat) weights, 4 influences and 2 helpers, the bend held out
    and exported: (output, report, the output loaded back)."""
    d, _ = tube
    out = tmp_path_factory.mktemp("fit") / "tube.glb"
    report = out.with_suffix(".json")
    code = main([str(a) for a in ["fit-skin", d / "tube.obj", "--skeleton", d / "tube.tgf", "--train", d / "pose.json",
                                  "--holdout", d / "bend.dmat", "--export", d / "bend.dmat", "--helpers", 2,
                                  "-o", out, "--report", report]])
    assert code == 0
    return out, json.loads(report.read_text()), load_character(out)


def test_the_file_is_the_skeleton_and_mesh_with_the_exported_clip(tube, fitted_tube):
    _, character = tube
    out, r, back = fitted_tube
    assert r["weights"] == "heat" and r["helpers"] == 2 and r["height"] == pytest.approx(2.0)
    assert back.skeleton.names[:2] == ("bone0", "bone1")
    assert sorted(back.skeleton.names[2:]) == ["bone1_end", "nrpose_helper_0", "nrpose_helper_1"]
    assert np.array_equal(back.skeleton.parents[:2], character.skeleton.parents)
    assert np.allclose(back.skeleton.rest_globals()[:2], character.skeleton.rest_globals(), atol=1e-6)
    m = back.meshes[0]
    assert np.array_equal(m.faces, character.meshes[0].faces)
    assert np.abs(m.bind_vertices - character.meshes[0].vertices).max() < 1e-6      # POSITION: the bind shape
    assert m.joints.shape[1] == 4 and np.allclose(m.weights.sum(axis=1), 1.0) and (m.weights >= 0).all()
    # the TGF's last tip is an end joint, so nrpose reads the file back with the TGF's bones
    end = back.skeleton.index("bone1_end")
    assert back.skeleton.parents[end] == 1 and np.allclose(back.skeleton.rest_globals()[end, :3, 3], [2, 0, 0])
    assert not m.weights[m.joints == end].any()
    assert [c.name for c in back.clips] == ["bend"]


def test_the_report_is_what_the_file_plays_and_beats_lbs_of_the_weights(tube, fitted_tube):
    d, character = tube
    out, r, back = fitted_tube
    held = r["errors"][str(d / "bend.dmat")]
    assert held["frames"] == FRAMES
    # the exported clip played by nrpose's LBS of the file, against NR-MLS of the mesh + TGF
    clip = back.clip("bend")
    times = sample_times(clip.duration, 30.0)
    played = CharacterPoser(back, method="lbs", backend="numpy").pose(clip.sample(times)).positions
    motion = read_dmat_animation(d / "bend.dmat", character.skeleton, 30.0)
    _, targets = nrmls_targets(CharacterPoser(character, weights="heat"), motion.sample(times))
    d2 = ((played - targets) ** 2).sum(axis=2)
    assert np.sqrt(d2.mean()) / r["height"] == pytest.approx(held["rms_fraction"], rel=1e-3, abs=1e-7)
    assert np.sqrt(d2.max()) / r["height"] == pytest.approx(held["max_fraction"], rel=1e-3, abs=1e-7)
    # fitted LBS is closer to NR-MLS than LBS of the weights NR-MLS is bound with
    for name, e in r["errors"].items():
        assert e["rms"] < r["authored_lbs_errors"][name]["rms"], name
    assert held["max_fraction"] < 0.05


def test_a_rigid_motion_is_fitted_exactly(tube, tmp_path, capsys):
    d, _ = tube
    report = tmp_path / "r.json"
    code, _, err = run(["fit-skin", d / "tube.obj", "--skeleton", d / "tube.tgf", "--train", d / "rigid.json",
                        "--rom-degrees", 0, "-o", tmp_path / "o.glb", "--report", report], capsys)
    assert code == 0, err
    assert json.loads(report.read_text())["errors"]["training"]["max_fraction"] < 1e-6


def test_a_mesh_with_a_bvh_skeleton_keeps_its_motion(tmp_path, capsys):
    body = humanoid(resolution=0.03)
    walk = body.clip("walk")
    times = sample_times(walk.duration, 30.0)
    write_geometry(tmp_path / "body.obj", body.meshes[0].vertices, body.meshes[0].faces)
    write_bvh(tmp_path / "walk.bvh", body.skeleton, walk.sample(times), 1 / 30)
    out, report = tmp_path / "body.glb", tmp_path / "r.json"
    code, _, err = run(["fit-skin", tmp_path / "body.obj", "--skeleton", tmp_path / "walk.bvh", "--weights",
                        "euclidean", "--train", "walk", "--rom-degrees", 0, "-o", out, "--report", report], capsys)
    assert code == 0, err
    r = json.loads(report.read_text())
    assert r["weights"] == "euclidean" and r["errors"]["training"]["frames"] == len(times)
    assert r["errors"]["training"]["rms"] < r["authored_lbs_errors"]["training"]["rms"]
    character = load_character(tmp_path / "body.obj", tmp_path / "walk.bvh")
    back = load_character(out)
    skeleton = character.skeleton
    leaves = [n for j, n in enumerate(skeleton.names) if not len(skeleton.children(j))]
    assert set(back.skeleton.names) == set(skeleton.names) | {f"{n}_end" for n in leaves}     # the end sites
    index = [back.skeleton.index(n) for n in skeleton.names]
    assert [c.name for c in back.clips] == ["walk"]
    want = skeleton.forward_kinematics(character.clip("walk").sample(times))
    assert np.abs(back.skeleton.forward_kinematics(back.clip("walk").sample(times))[:, index] - want).max() < 1e-4


def test_several_roots_get_a_common_root_and_every_bone_reads_back(tmp_path, capsys):
    """Two separate TGF chains (two roots, one a single bone): the skin's joints share the root node
    glTF requires, and nrpose poses the file it wrote with NR-MLS."""
    V, F = cylinder_mesh(rings=21, sectors=12)
    write_geometry(tmp_path / "two.obj", V, F)
    (tmp_path / "two.tgf").write_text("1 0 0 0\n2 1 0 0\n3 1 0 0\n4 2 0 0\n#\n1 2\n3 4\n#\n")
    (tmp_path / "pose.json").write_text(json.dumps({"rotations": {"bone1": quat([0, 0, 1], 50).tolist()}}))
    out = tmp_path / "two.glb"
    code, _, err = run(["fit-skin", tmp_path / "two.obj", "--skeleton", tmp_path / "two.tgf", "--weights",
                        "euclidean", "--train", tmp_path / "pose.json", "-o", out], capsys)
    assert code == 0, err
    import pygltflib
    gltf = pygltflib.GLTF2.load(str(out))
    root = gltf.skins[0].skeleton
    assert gltf.nodes[root].name == "nrpose_root" and root not in gltf.skins[0].joints
    assert sorted(gltf.nodes[root].children) == [0, 1] and gltf.scenes[0].nodes[0] == root
    assert {"bone0_end", "bone1_end"} <= {n.name for n in gltf.nodes}
    code, _, err = run(["pose", out, "--rest", "-o", tmp_path / "rest.npz"], capsys)
    assert code == 0, err


@needs_data
def test_libigl_arm_with_its_weights_file(tmp_path, capsys):
    arm = load_character(LIBIGL / "arm.obj", LIBIGL / "arm.tgf")
    (tmp_path / "pose.json").write_text(json.dumps({"rotations": {"bone1": quat([0, 0, 1], 45).tolist(),
                                                                  "bone2": quat([1, 0, 0], 30).tolist()}}))
    pose = arm.skeleton.rest_pose
    pose.rotation[arm.skeleton.index("bone2")] = quat([0, 1, 0], 40)
    lift = LocalPose(*(np.stack([getattr(arm.skeleton.rest_pose, f), getattr(pose, f)])
                       for f in ("translation", "rotation", "scale")))
    write_dmat(tmp_path / "lift.dmat", motion_matrix(arm.skeleton, arm.skeleton.forward_kinematics(lift)))
    out, report = tmp_path / "arm.glb", tmp_path / "r.json"
    code, _, err = run(["fit-skin", LIBIGL / "arm.obj", "--skeleton", LIBIGL / "arm.tgf", "--weights-file",
                        LIBIGL / "arm-weights.dmat", "--train", tmp_path / "pose.json", "--influences", 8,
                        "--helpers", 4, "--export", tmp_path / "lift.dmat", "-o", out, "--report", report], capsys)
    assert code == 0, err
    r = json.loads(report.read_text())
    assert r["weights"] == "authored" and r["vertices"] == 8311
    assert r["errors"]["training"]["rms"] < 0.6 * r["authored_lbs_errors"]["training"]["rms"]
    m = load_character(out).meshes[0]
    assert m.joints.shape[1] == 8 and np.allclose(m.weights.sum(axis=1), 1.0)


@pytest.mark.parametrize("extra, message", [
    (["--skeleton", None], "needs a skeleton"),
    (["--weights", "authored"], "no skin weights"),
    (["--export", "pose.dmat"], "--export takes animations"),
    (["--skeleton", "tube.obj"], "a mesh needs a skeleton, a .tgf or .bvh"),
    (["--helpers", "2"], "helper joints move only in the file's animations"),
    (["--weights-file", "pose.dmat"], "expected"),
    (["--train", "bones.dmat"], "do not divide into frames"),
])
def test_cli_bad_mesh_inputs_exit_2_one_line_no_output(tube, tmp_path, capsys, extra, message):
    d, character = tube
    write_dmat(d / "pose.dmat", np.tile([0.0, 0, 0, 1], 2)[:, None])
    write_dmat(d / "bones.dmat", np.ones((5, 1)))
    skeleton = [] if extra == ["--skeleton", None] else ["--skeleton", d / "tube.tgf"]
    if extra[0] == "--skeleton":
        skeleton, extra = ([] if extra[1] is None else ["--skeleton", d / extra[1]]), []
    args = ["fit-skin", d / "tube.obj", *skeleton, "--train", d / "pose.json"]
    if extra:
        args += [extra[0], d / extra[1] if extra[1].endswith(".dmat") else extra[1]]
    out = tmp_path / "o.glb"
    code, _, err = run(args + ["-o", out], capsys)
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert not out.exists()


@pytest.mark.parametrize("frame_time, extra, message", [
    (1e-320, [], "not strictly increasing as the file's float32 seconds"),      # keys collapse in float32
    (1 / 30, ["--helpers", "1", "--fps", "1e6"], "poses, more than 10,000"),   # a written clip sampled whole
])
def test_cli_written_clips_are_checked_before_the_fit(tube, tmp_path, capsys, frame_time, extra, message):
    d, character = tube
    pose = character.skeleton.rest_pose
    poses = LocalPose(*(np.repeat(getattr(pose, f)[None], 12, axis=0) for f in ("translation", "rotation", "scale")))
    poses.rotation[:, 1] = Rotation.from_rotvec(np.outer(np.linspace(0, 1, 12), [0, 0, 1])).as_quat()
    write_bvh(tmp_path / "swing.bvh", character.skeleton, poses, frame_time)
    out = tmp_path / "o.glb"
    code, _, err = run(["fit-skin", d / "tube.obj", "--skeleton", d / "tube.tgf", "--train", d / "pose.json",
                        "--export", tmp_path / "swing.bvh", *extra, "-o", out], capsys)
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert not out.exists()


@needs_data
def test_cli_glb_refuses_a_skeleton_or_weights_file(tube, tmp_path, capsys):
    d, _ = tube
    fox = DATA / "gltf" / "Fox.glb"
    for extra, message in ((["--skeleton", d / "tube.tgf"], "carries its own skeleton"),
                           (["--weights-file", LIBIGL / "arm-weights.dmat"], "a glTF file carries its own")):
        code, _, err = run(["fit-skin", fox, "--train", "Walk", *extra, "-o", tmp_path / "o.glb"], capsys)
        assert code == 2 and err.count("\n") == 1 and message in err, err
        assert not (tmp_path / "o.glb").exists()


def test_three_js_plays_the_new_file_as_nrpose_skins_it(fitted_tube):
    out, _, back = fitted_tube
    errors = three_js_errors(out, back, back.clip("bend"))
    assert max(errors) <= 1e-5, errors


def test_blender_plays_the_new_file_as_nrpose_skins_it(fitted_tube):
    out, _, back = fitted_tube
    errors = blender_errors(out, back, back.clip("bend"))
    assert max(errors) <= 1e-5, errors


@pytest.mark.skipif(shutil.which("gltfpack") is None, reason="gltfpack not installed (Debian package gltfpack)")
def test_gltfpack_parses_the_new_file(fitted_tube, tmp_path):
    run_ = subprocess.run(["gltfpack", "-i", str(fitted_tube[0]), "-o", str(tmp_path / "packed.glb")],
                          capture_output=True, text=True, timeout=300)
    assert run_.returncode == 0, run_.stderr
    assert not [line for line in (run_.stdout + run_.stderr).splitlines() if line.lower().startswith("error")]
