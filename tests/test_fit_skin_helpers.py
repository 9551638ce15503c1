"""Helper joints of nrpose fit-skin: the rule, the rigid fit, placement, and the written file."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from nrpose.cli import main
from nrpose.errors import InputError
from nrpose.fit.character_skin import character_height, error_table, fit_character, fitted_positions
from nrpose.fit.helper_fit import add_helpers, residuals
from nrpose.fit.helper_joints import driver_features, evaluate_rule, fit_rule, rigid_fit
from nrpose.fit.helper_keys import KEY_TOLERANCE
from nrpose.fit.rom import range_of_motion
from nrpose.fit.skin_file import write_fitted_glb
from nrpose.fit.skin_weights import skin_positions
from nrpose.io import load_character
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import LocalPose
from nrpose.model.timing import sample_times
from nrpose.pose.poser import CharacterPoser

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared assets not found at {DATA}")
FOX = DATA / "gltf" / "Fox.glb"


def rigid(rotations, translations):
    L = np.tile(np.eye(4), (len(rotations), 1, 1))
    L[:, :3, :3] = rotations
    L[:, :3, 3] = translations
    return L


@pytest.mark.parametrize("seed", [0, 1])
def test_rigid_fit_recovers_a_rigid_motion_and_weights_matter(seed):
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(40, 3))
    truth = rigid(Rotation.random(5, random_state=seed).as_matrix(), rng.normal(size=(5, 3)) * 3)
    u = np.einsum("fij,nj->fni", truth[:, :3, :3], z) + truth[:, None, :3, 3]
    assert np.abs(rigid_fit(z, u, rng.uniform(0.1, 1, 40)) - truth).max() < 1e-10
    # points with weight 0 do not pull the fit: corrupt them, the transform stays
    a = np.ones(40)
    a[:5] = 0
    u[:, :5] += 10
    assert np.abs(rigid_fit(z, u, a) - truth).max() < 1e-10
    assert np.abs(rigid_fit(z, u, np.ones(40)) - truth).max() > 1e-3
    with pytest.raises(InputError):
        rigid_fit(z, u, np.zeros(40))


@needs_data
def test_rule_reproduces_transforms_it_can_express_and_generalises():
    fox = load_character(FOX)
    skel = fox.skeleton
    # training poses: the two drivers turned together at random (every feature excited)
    F = 300
    rest = skel.rest_pose
    rotation = np.broadcast_to(rest.rotation, (F,) + rest.rotation.shape).copy()
    for j in (16, 17):
        rotation[:, j] = (Rotation.from_quat(skel.rotation[j])
                          * Rotation.from_rotvec(Rotation.random(F, random_state=j).as_rotvec() / 3)).as_quat()
    rom = LocalPose(np.broadcast_to(rest.translation, (F,) + rest.translation.shape).copy(), rotation,
                    np.broadcast_to(rest.scale, (F,) + rest.scale.shape).copy())
    drivers = (16, 17)
    phi = driver_features(skel, rom, drivers)
    assert phi.shape == (F, 1 + 4 * len(drivers))
    assert np.allclose(driver_features(skel, skel.rest_pose, drivers), np.r_[1.0, np.zeros(8)])
    # transforms a rule expresses exactly: a fixed rotation, a slide linear in the features
    rng = np.random.default_rng(3)
    coef = np.zeros(phi.shape[1:] + (12,))
    coef[0, :9] = Rotation.random(random_state=5).as_matrix().ravel()
    coef[:, 9:] = rng.normal(size=(phi.shape[1], 3))
    truth = evaluate_rule(phi, coef)
    assert np.abs(evaluate_rule(phi, fit_rule(phi, truth, ridge=0.0)) - truth).max() < 1e-9
    fitted = fit_rule(phi, truth)           # the default ridge: a small bias
    assert np.abs(evaluate_rule(phi, fitted) - truth).max() < 1e-2
    # a turn the rule approximates: the second driver's own rotation from rest
    delta = Rotation.from_quat(skel.rotation[17]).inv() * Rotation.from_quat(rom.rotation[:, 17])
    turn = np.tile(np.eye(4), (F, 1, 1))
    turn[:, :3, :3] = delta.as_matrix()
    approx = evaluate_rule(phi, fit_rule(phi, turn))
    assert np.abs(approx - turn).max() < 0.15        # turns up to 60 degrees, linear features
    # held-out poses (a clip never fitted): the same rule
    walk = fox.clip("Walk").sample(np.linspace(0, 0.7, 9))
    phi_walk = driver_features(skel, walk, drivers)
    assert np.abs(evaluate_rule(phi_walk, fitted) - evaluate_rule(phi_walk, coef)).max() < 3e-2


@needs_data
def test_helpers_fit_a_slide_driven_by_a_joint_that_lbs_cannot():
    """Targets: the Fox's authored LBS, plus a rigid slide of one region in its joint's frame
    driven by a child's rotation (no combination of the skeleton's transforms makes it)."""
    fox = load_character(FOX)
    skel, mesh = fox.skeleton, fox.meshes[0]
    rom = range_of_motion(skel, 45.0, pairs=2)
    G = skel.forward_kinematics(rom)
    p, child = 16, 17                         # b_LeftLeg01_015 and its child
    assert skel.parents[child] == p
    dominant = mesh.joints[np.arange(len(mesh.joints)), np.argmax(mesh.weights, axis=1)]
    region = dominant == p
    truth = skin_positions(mesh.bind_vertices, G @ mesh.inverse_bind, mesh.joints, mesh.weights)
    R_child = Rotation.from_quat(rom.rotation[:, child]).as_matrix()
    R_rest = Rotation.from_quat(skel.rotation[child]).as_matrix()
    slide_local = 0.5 * np.linalg.norm(skel.translation[child]) * (R_rest.T @ R_child)[:, :, 1]   # (F, 3)
    slide = np.einsum("fij,fj->fi", G[:, p, :3, :3], slide_local)
    targets = truth.copy()
    targets[:, region] += slide[:, None]
    plain = fit_character(fox, G, targets, 4)
    before = error_table(fox, fitted_positions(fox, plain, G), targets)
    with_helpers, log = add_helpers(fox, plain, G, rom, targets, 2, 4)
    after = error_table(fox, fitted_positions(fox, with_helpers, G, rom), targets)
    assert after["rms"] < 0.5 * before["rms"], (before["rms"], after["rms"], log)
    assert any(child in h.drivers for h in with_helpers.helpers), log
    with pytest.raises(InputError, match="local pose"):
        fitted_positions(fox, with_helpers, G)
    # the weights stay a partition of unity over the joints and helpers
    w = with_helpers.weights[0]
    assert (w >= 0).all() and np.allclose(w.sum(axis=1), 1)
    assert with_helpers.joints[0].max() == skel.num_joints + len(with_helpers.helpers) - 1
    # zero helpers asked: the fit unchanged
    same, _ = add_helpers(fox, plain, G, rom, targets, 0, 4)
    assert same.helpers == () and same.joints[0] is plain.joints[0]


def fox_lbs_case():
    """The Fox, a small range of motion, its authored LBS as targets, the vertices with at least
    half their weight on b_LeftLeg01_015 (16) and those whose dominant joint is b_Head_05 (6)."""
    fox = load_character(FOX)
    skel, mesh = fox.skeleton, fox.meshes[0]
    rom = range_of_motion(skel, 45.0, pairs=1)
    G = skel.forward_kinematics(rom)
    targets = skin_positions(mesh.bind_vertices, G @ mesh.inverse_bind, mesh.joints, mesh.weights)
    dominant = mesh.joints[np.arange(len(mesh.joints)), np.argmax(mesh.weights, axis=1)]
    leg = np.flatnonzero(np.where(mesh.joints == 16, mesh.weights, 0).sum(axis=1) >= 0.5)
    return fox, rom, G, targets, leg, np.flatnonzero(dominant == 6)


def test_residuals_are_the_peak_and_the_mean_square_over_the_poses():
    y = np.zeros((4, 2, 3))
    x = y.copy()
    x[2, 0, 0] = 3.0            # vertex 0: off by 3 in one pose of 4
    x[:, 1, 1] = 1.0            # vertex 1: off by 1 in every pose
    peak, meansq = residuals(x, y)
    assert np.allclose(peak, [3.0, 1.0]) and np.allclose(meansq, [9 / 4, 1.0])


@needs_data
def test_helpers_are_seeded_by_the_peak_residual():
    """A region off by a in every pose and another off by 3a in one pose only (a smaller RMS):
    the first helper goes to the second, where a motion reaching that pose fails."""
    fox, rom, G, targets, leg, head = fox_lbs_case()
    a = 0.01 * character_height(fox)
    sign = np.where(np.arange(len(targets)) % 2, 1.0, -1.0)
    targets[:, leg, 0] += a * sign[:, None]
    targets[7, head, 2] += 3 * a
    plain = fit_character(fox, G, targets, 4)
    _, log = add_helpers(fox, plain, G, rom, targets, 1, 4)
    assert log[0]["seed"] in head, log


@needs_data
def test_a_region_vertex_the_helper_does_not_serve_seeds_the_next():
    """A slide of one region driven by a child's rotation (a helper fits it) and, inside that
    region, two vertices off in one pose each (no rigid helper fits that): the first helper is
    seeded at the worse one and kept; the other, in its region and still off, seeds the next."""
    fox, rom, G, targets, leg, _ = fox_lbs_case()
    skel = fox.skeleton
    R_child = Rotation.from_quat(rom.rotation[:, 17]).as_matrix()
    R_rest = Rotation.from_quat(skel.rotation[17]).as_matrix()
    slide_local = 0.5 * np.linalg.norm(skel.translation[17]) * (R_rest.T @ R_child)[:, :, 1]
    targets[:, leg] += np.einsum("fij,fj->fi", G[:, 16, :3, :3], slide_local)[:, None]
    plain = fit_character(fox, G, targets, 4)
    slide_peak = residuals(fitted_positions(fox, plain, G)[:, leg], targets[:, leg])[0].max()
    rest = fox.meshes[0].vertices
    first = leg[0]
    distance = np.linalg.norm(rest[leg] - rest[first], axis=1)
    second = leg[np.argmin(np.where(distance > 1e-6, distance, np.inf))]
    targets[5, first, 0] += 3 * slide_peak
    targets[9, second, 0] += 2 * slide_peak
    plain = fit_character(fox, G, targets, 4)
    _, log = add_helpers(fox, plain, G, rom, targets, 2, 4)
    assert log[0]["seed"] == first and log[0]["kept"], log
    assert log[1]["seed"] == second, log


@needs_data
def test_per_frame_placement_serves_a_motion_no_rule_follows():
    """A region slid by a random offset per pose (no function of the joints' rotations): placed
    with per-frame transforms (``--helper-tracks fitted``) one helper takes most of it; placed
    with the rule the same helper cannot."""
    fox, rom, G, targets, leg, _ = fox_lbs_case()
    rng = np.random.default_rng(5)
    targets[:, leg] += 0.02 * character_height(fox) * rng.normal(size=(len(targets), 1, 3))
    plain = fit_character(fox, G, targets, 4)
    _, by_rule = add_helpers(fox, plain, G, rom, targets, 1, 4)
    fitted, per_frame = add_helpers(fox, plain, G, rom, targets, 1, 4, per_frame=True)
    assert by_rule[0]["seed"] == per_frame[0]["seed"] and per_frame[0]["kept"], (by_rule, per_frame)
    before = per_frame[0]["region_rms_before"]
    assert per_frame[0]["region_rms_after"] < 0.5 * before, per_frame
    assert by_rule[0]["region_rms_after"] > 0.8 * before, by_rule
    w = fitted.weights[0]
    assert (w >= 0).all() and np.allclose(w.sum(axis=1), 1)


@pytest.fixture(scope="module")
def helper_file(tmp_path_factory):
    """The Fox fitted with 3 helper joints on a small range of motion, written with Run: with the
    default key tolerance, and with a key at every frame (the second file)."""
    if not FOX.is_file():
        pytest.skip(f"shared assets not found at {DATA}")
    fox = load_character(FOX)
    rom = range_of_motion(fox.skeleton, 45.0, pairs=1)
    G = fox.skeleton.forward_kinematics(rom)
    poser = CharacterPoser(fox, method="nrmls")
    targets = poser.pose(rom).positions
    fitted, _ = add_helpers(fox, fit_character(fox, G, targets, 4), G, rom, targets, 3, 4)
    folder = tmp_path_factory.mktemp("helpers")
    out, every = folder / "fox_helpers.glb", folder / "fox_helpers_every_frame.glb"
    size = write_fitted_glb(FOX, out, fox, fitted, clips=[fox.clip("Run")], fps=30.0)
    write_fitted_glb(FOX, every, fox, fitted, clips=[fox.clip("Run")], fps=30.0, key_tolerance=0.0)
    return fox, fitted, out, size, every


@pytest.mark.parametrize("keys", ["every frame", "default tolerance"])
def test_file_with_helpers_plays_the_rule(helper_file, keys):
    """At a key per frame the file plays the rule (float32 round-off); with the default
    tolerance, between kept keys, within the tolerance (of the height) per helper a vertex uses:
    the keys bound each helper's share of a vertex's displacement."""
    fox, fitted, out, size, every = helper_file
    assert size == out.stat().st_size
    back = load_character(every if keys == "every frame" else out)
    J, H = fox.skeleton.num_joints, len(fitted.helpers)
    shares = ((fitted.joints[0] >= J) & (fitted.weights[0] > 0)).sum(axis=1).max()
    allowed = 0.0 if keys == "every frame" else shares * KEY_TOLERANCE * character_height(fox)
    assert back.skeleton.num_joints == J + H
    names = list(back.skeleton.names)
    for h, helper in enumerate(fitted.helpers):
        parent = back.skeleton.parents[names.index(f"nrpose_helper_{h}")]
        assert back.skeleton.names[parent] == fox.skeleton.names[helper.parent]
    assert [c.name for c in back.clips] == [c.name for c in fox.clips] + ["Run (2)"]
    for clip, back_clip in zip(fox.clips, back.clips):
        times = sample_times(clip.duration, 30.0)[::5]
        pose = clip.sample(times)
        G = fox.skeleton.forward_kinematics(pose)
        ours = fitted_positions(fox, fitted, G, pose)
        lbs = CharacterPoser(back, method="lbs", backend="numpy").pose(back_clip.sample(times)).positions
        bbox = np.ptp(ours.reshape(-1, 3), axis=0).max()
        assert np.abs(lbs - ours).max() <= allowed + 1e-5 * bbox, clip.name


@pytest.mark.skipif(shutil.which("gltfpack") is None, reason="gltfpack not installed (Debian package gltfpack)")
def test_gltfpack_parses_the_file_with_helpers(helper_file, tmp_path):
    out = helper_file[2]
    run = subprocess.run(["gltfpack", "-i", str(out), "-o", str(tmp_path / "packed.glb")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert not [line for line in (run.stdout + run.stderr).splitlines() if line.lower().startswith("error")]
    assert (tmp_path / "packed.glb").stat().st_size > 0


@needs_data
def test_cli_with_helpers_reports_them_and_writes_them(tmp_path, capsys):
    out, report = tmp_path / "fox.glb", tmp_path / "r.json"
    code = main(["fit-skin", str(FOX), "--train", "Walk", "--holdout", "Run", "--rom-degrees", "30",
                 "--helpers", "2", "-o", str(out), "--report", str(report)])
    assert code == 0, capsys.readouterr().err
    r = json.loads(report.read_text())
    assert 1 <= r["helpers"] <= 2 and r["helpers_requested"] == 2
    assert sum(p["kept"] for p in r["helper_placement"]) == r["helpers"]
    assert r["helpers_seconds"] > 0 and r["size"]["file_bytes"] == out.stat().st_size
    back = load_character(out)
    assert back.skeleton.num_joints == load_character(FOX).skeleton.num_joints + r["helpers"]
    # each of the file's animations drives the helpers
    helper_joints = {j for j, n in enumerate(back.skeleton.names) if n.startswith("nrpose_helper_")}
    assert all(helper_joints <= {t.joint for t in clip.tracks} for clip in back.clips)
