"""nrpose fit-skin: LBS weights fitted to example poses (nrpose.fit) and the fitted glTF copy."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nrpose.cli import main
from nrpose.errors import InputError
from nrpose.fit.character_skin import (FittedSkin, error_table, fit_character, fitted_positions, mesh_space,
                                       nrmls_targets)
from nrpose.fit.helper_fit import add_helpers
from nrpose.fit.rom import range_of_motion
from nrpose.fit.skin_file import write_fitted_glb
from nrpose.fit.skin_weights import candidate_joints, fit_weights, skin_positions
from nrpose.io import load_character
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import LocalPose
from nrpose.pose.poser import CharacterPoser

from fit_skin_played import blender_errors, three_js_errors

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared assets not found at {DATA}")
FOX = DATA / "gltf" / "Fox.glb"


def random_case(seed, J=7, N=300, F=30, true_k=3):
    """Random skinning matrices (F, J, 4, 4), sources (N, 3) and true influences (N, true_k)."""
    rng = np.random.default_rng(seed)
    parents = np.array([-1] + [int(rng.integers(0, j)) for j in range(1, J)])
    mats = np.tile(np.eye(4), (F, J, 1, 1))
    mats[:, :, :3, :3] = Rotation.random(F * J, random_state=seed).as_matrix().reshape(F, J, 3, 3)
    mats[:, :, :3, 3] = rng.normal(size=(F, J, 3))
    source = rng.normal(size=(N, 3)) * 2 + 5      # off the origin: exercises the centring
    joints = np.stack([rng.choice(J, true_k, replace=False) for _ in range(N)])
    weights = rng.dirichlet(np.ones(true_k), size=N)
    return parents, mats, source, joints, weights


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lbs_output_is_recovered_to_float32_precision(seed):
    parents, mats, source, joints, weights = random_case(seed)
    targets = skin_positions(source, mats, joints, weights)
    cand = candidate_joints(parents, joints, weights)
    assert all(set(joints[n]) <= set(cand[n]) for n in range(len(joints)))
    j, w = fit_weights(source, mats, targets, cand, 4)
    fitted = skin_positions(source, mats, j, w)
    extent = np.ptp(targets.reshape(-1, 3), axis=0).max()
    assert np.abs(fitted - targets).max() <= 1e-6 * extent
    # the weights themselves are the true ones (the poses determine them)
    dense = np.zeros((len(source), len(parents)))
    np.add.at(dense, (np.arange(len(source))[:, None], j), w)
    truth = np.zeros_like(dense)
    np.add.at(truth, (np.arange(len(source))[:, None], joints), weights)
    assert np.abs(dense - truth).max() < 1e-5


@pytest.mark.parametrize("k", [1, 2, 4, 8])
def test_weights_are_nonnegative_sum_to_one_and_respect_the_influence_count(k):
    parents, mats, source, joints, weights = random_case(5, true_k=6)
    targets = skin_positions(source, mats, joints, weights) + np.random.default_rng(0).normal(
        scale=0.05, size=(len(mats), len(source), 3))
    j, w = fit_weights(source, mats, targets, candidate_joints(parents, joints, weights), k)
    assert j.shape == w.shape == (len(source), k)
    assert (w >= 0).all() and np.allclose(w.sum(axis=1), 1, atol=1e-12)
    assert (np.count_nonzero(w, axis=1) <= k).all()
    assert (np.diff(w, axis=1) <= 0).all()            # largest first
    assert j.min() >= 0 and j.max() < len(parents)


def test_top_k_refit_is_no_worse_than_truncating():
    parents, mats, source, joints, weights = random_case(7, true_k=6)
    targets = skin_positions(source, mats, joints, weights)
    j, w = fit_weights(source, mats, targets, candidate_joints(parents, joints, weights), 3)
    order = np.argsort(-weights, axis=1)[:, :3]
    tj, tw = np.take_along_axis(joints, order, 1), np.take_along_axis(weights, order, 1)
    tw = tw / tw.sum(axis=1, keepdims=True)
    err = lambda jj, ww: ((skin_positions(source, mats, jj, ww) - targets) ** 2).sum()  # noqa: E731
    assert err(j, w) <= err(tj, tw) * (1 + 1e-9)


def test_candidates_are_authored_then_parents_then_children_within_allowed():
    parents = np.array([-1, 0, 1, 1, 3])
    cand = candidate_joints(parents, np.array([[3, 1], [0, 0]]), np.array([[0.3, 0.7], [1.0, 0.0]]))
    assert list(cand[0][cand[0] >= 0]) == [1, 3, 0, 2, 4]
    assert list(cand[1][cand[1] >= 0]) == [0, 1]
    allowed = np.array([True, True, False, True, True])
    cand = candidate_joints(parents, np.array([[3, 1]]), np.array([[0.3, 0.7]]), allowed, limit=3)
    assert list(cand[0]) == [1, 3, 0]


def test_bad_fit_inputs_raise():
    parents, mats, source, joints, weights = random_case(3)
    targets = skin_positions(source, mats, joints, weights)
    cand = candidate_joints(parents, joints, weights)
    with pytest.raises(InputError, match="influences"):
        fit_weights(source, mats, targets, cand, 0)
    with pytest.raises(InputError, match="training pose"):
        fit_weights(source, mats[:0], targets[:0], cand, 4)
    bad = targets.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        fit_weights(source, mats, bad, cand, 4)
    with pytest.raises(InputError, match="candidates"):
        fit_weights(source, mats, targets, np.full_like(cand, -1), 4)


def test_range_of_motion_sweeps_each_joint_within_the_limit():
    fox = load_character(FOX) if FOX.is_file() else None
    if fox is None:
        pytest.skip(f"shared assets not found at {DATA}")
    skel = fox.skeleton
    J = skel.num_joints
    rom = range_of_motion(skel, 60.0, pairs=2)
    with_parent = int((skel.parents >= 0).sum())
    assert rom.rotation.shape == (12 * J + 2 * with_parent, J, 4)
    rest = Rotation.from_quat(np.broadcast_to(skel.rotation, rom.rotation.shape).reshape(-1, 4))
    delta = (rest.inv() * Rotation.from_quat(rom.rotation.reshape(-1, 4))).magnitude().reshape(len(rom.rotation), J)
    assert delta.max() <= np.radians(60) + 1e-9
    moved = (delta[:12 * J] > 1e-9).sum(axis=1)
    assert (moved == 1).all()
    assert np.allclose(np.sort(delta[:12 * J].max(axis=1))[[0, -1]], np.radians([30, 60]))
    assert ((delta[12 * J:] > 1e-9).sum(axis=1) <= 2).all()
    assert np.array_equal(rom.translation[0], skel.translation)


@needs_data
def test_fox_authored_lbs_is_recovered_and_a_rigid_motion_fit_is_exact():
    fox = load_character(FOX)
    rom = range_of_motion(fox.skeleton, 45.0, pairs=1)
    G = fox.skeleton.forward_kinematics(rom)
    mesh = fox.meshes[0]
    source, ibm = mesh_space(fox, mesh)
    truth = skin_positions(source, G @ ibm, mesh.joints, mesh.weights)
    fitted = fit_character(fox, G, truth, 4)
    out = fitted_positions(fox, fitted, G)
    assert np.abs(out - truth).max() <= 1e-6 * np.ptp(mesh.vertices, axis=0).max()
    # rigid motion: the whole character turned and moved, NR-MLS targets
    poser = CharacterPoser(fox, method="nrmls")
    rest = fox.skeleton.rest_pose
    F = 6
    rot = (Rotation.random(F, random_state=4) * Rotation.from_quat(rest.rotation[0])).as_quat()
    local = LocalPose(np.broadcast_to(rest.translation, (F,) + rest.translation.shape).copy(),
                      np.broadcast_to(rest.rotation, (F,) + rest.rotation.shape).copy(),
                      np.broadcast_to(rest.scale, (F,) + rest.scale.shape).copy())
    local.rotation[:, 0] = rot
    local.translation[:, 0] += np.random.default_rng(0).normal(size=(F, 3)) * 50
    G, targets = nrmls_targets(poser, local)
    fitted = fit_character(fox, G, targets, 4)
    table = error_table(fox, fitted_positions(fox, fitted, G), targets)
    assert table["max_fraction"] < 1e-6


@needs_data
def test_written_glb_loads_with_the_fitted_weights(tmp_path):
    fox = load_character(FOX)
    local = fox.clip("Walk").sample(np.linspace(0, 0.6, 8))
    poser = CharacterPoser(fox, method="nrmls")
    G, targets = nrmls_targets(poser, local)
    for k in (4, 8):
        fitted = fit_character(fox, G, targets, k)
        out = tmp_path / f"fox{k}.glb"
        write_fitted_glb(FOX, out, fox, fitted, clips=[fox.clip("Run")])
        back = load_character(out)
        assert [c.name for c in back.clips] == [c.name for c in fox.clips] + ["Run (2)"]
        m = back.meshes[0]
        assert np.array_equal(m.bind_vertices, fox.meshes[0].bind_vertices)
        assert m.joints.shape[1] == k
        again = FittedSkin((m.joints,), (m.weights,), 0.0)
        ours = fitted_positions(fox, fitted, G)
        bbox = np.ptp(ours.reshape(-1, 3), axis=0).max()
        assert np.abs(fitted_positions(back, again, G) - ours).max() <= 1e-5 * bbox
        # nrpose's own LBS of the file equals the fit
        lbs = CharacterPoser(back, method="lbs", backend="numpy").pose(local).positions
        assert np.abs(lbs - ours).max() <= 1e-5 * bbox


def run(args, capsys):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@needs_data
@pytest.mark.parametrize("extra, message", [
    (["--train", "Walk", "--influences", "0"], "--influences 0"),
    (["--train", "Walk", "--influences", "5"], "--influences 5"),
    (["--train", "Walk", "--helpers", "-1"], "--helpers -1"),
    ([], "no training motion"),
    (["--train", "Jump"], "not a clip"),
    (["--train", "Walk", "--rom-degrees", "-5"], "--rom-degrees"),
    (["--train", "Walk", "--fps", "100000"], "poses, more than 10,000"),
    (["--train", "Walk", "--key-tolerance", "-1e-4"], "--key-tolerance"),
    (["--train", "Walk", "--key-tolerance", "nan"], "--key-tolerance"),
    (["--train", "Walk", "--key-tolerance", "0.5"], "--key-tolerance"),
])
def test_cli_bad_options_exit_2_one_line_no_output(tmp_path, capsys, extra, message):
    out = tmp_path / "o.glb"
    code, _, err = run(["fit-skin", FOX, *extra, "-o", out], capsys)
    assert code == 2 and err.count("\n") == 1 and message in err
    assert not out.exists()


@needs_data
def test_cli_writes_the_file_and_report(tmp_path, capsys):
    out, report = tmp_path / "fox.glb", tmp_path / "r.json"
    code, text, err = run(["fit-skin", FOX, "--train", "Walk", "--holdout", "Run", "--rom-degrees", "30",
                           "-o", out, "--report", report], capsys)
    assert code == 0, err
    r = json.loads(report.read_text())
    assert set(r["errors"]) == {"training", "Run"}
    for e in r["errors"].values():
        assert 0 < e["rms"] <= e["max"] and np.isclose(e["rms_fraction"], e["rms"] / r["height"])
        assert sum(g["vertices"] for g in e["regions"].values()) == r["vertices"] == 1728
    assert r["errors"]["training"]["rms_fraction"] < 0.01
    assert r["size"]["file_bytes"] == out.stat().st_size
    assert r["size"]["morph_bake_bytes_10s"] == 12 * 300 * 1728
    assert len(load_character(out).clips) == 3


@pytest.fixture(scope="module", params=[(4, 0), (8, 0), (4, 3), (8, 3)], ids=["k4", "k8", "k4-helpers3", "k8-helpers3"])
def fitted_fox(tmp_path_factory, request):
    """Fox fitted with 4 or 8 influences (JOINTS_0/1, WEIGHTS_0/1), without and with 3 helper joints, from
    Walk poses and a small range of motion."""
    if not FOX.is_file():
        pytest.skip(f"shared assets not found at {DATA}")
    k, helpers = request.param
    fox = load_character(FOX)
    local = fox.clip("Walk").sample(np.linspace(0, 0.6, 6))
    if helpers:
        rom = range_of_motion(fox.skeleton, 45.0, pairs=0)
        local = LocalPose(*(np.concatenate([getattr(local, f), getattr(rom, f)])
                            for f in ("translation", "rotation", "scale")))
    G, targets = nrmls_targets(CharacterPoser(fox, method="nrmls"), local)
    fitted = fit_character(fox, G, targets, k)
    fitted, _ = add_helpers(fox, fitted, G, local, targets, helpers, k)
    assert len(fitted.helpers) == helpers
    out = tmp_path_factory.mktemp("fit") / f"fox{k}_{helpers}.glb"
    write_fitted_glb(FOX, out, fox, fitted)
    back = load_character(out)
    return out, back, back.clip("Survey")


def test_three_js_plays_the_fitted_file_as_nrpose_skins_it(fitted_fox):
    out, back, clip = fitted_fox
    if back.meshes[0].joints.shape[1] > 4:
        pytest.skip("three.js r111 skins with JOINTS_0/WEIGHTS_0 only (4 influences)")
    errors = three_js_errors(out, back, clip)
    assert max(errors) <= 1e-5, errors


def test_blender_plays_the_fitted_file_as_nrpose_skins_it(fitted_fox):
    errors = blender_errors(*fitted_fox)
    assert max(errors) <= 1e-5, errors
