"""Helper joints as plain animated joints (fit-skin --helper-tracks fitted): per-frame tracks,
the SSDR alternation of weights and tracks, and the file that plays them."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fit_skin_played import played_rms
from nrpose.cli import main
from nrpose.fit.character_skin import character_height, fit_character, fitted_positions, nrmls_targets
from nrpose.fit.helper_fit import add_helpers
from nrpose.fit.helper_tracks import fit_helper_tracks, refit_with_tracks
from nrpose.fit.rom import range_of_motion
from nrpose.io import load_character
from nrpose.model.rotation import Rotation
from nrpose.model.timing import sample_times
from nrpose.pose.poser import CharacterPoser

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOX = DATA / "gltf" / "Fox.glb"
pytestmark = pytest.mark.skipif(not FOX.is_file(), reason=f"shared assets not found at {DATA}")


@pytest.fixture(scope="module")
def fox_fit():
    """The Fox fitted (rule helpers) on a small range of motion, and NR-MLS of its Run."""
    fox = load_character(FOX)
    rom = range_of_motion(fox.skeleton, 45.0, pairs=1)
    poser = CharacterPoser(fox, method="nrmls")
    G, targets = nrmls_targets(poser, rom)
    fitted, _ = add_helpers(fox, fit_character(fox, G, targets, 4), G, rom, targets, 3, 4)
    run = fox.clip("Run").sample(sample_times(fox.clip("Run").duration, 30.0))
    Gr, Tr = nrmls_targets(poser, run)
    return fox, fitted, rom, G, targets, run, Gr, Tr


def test_tracks_recover_known_helper_motion(fox_fit):
    """Targets made by LBS of the fitted weights with helper transforms that no rule gives
    (the rule's, turned and shifted by a random rigid motion per frame): recovered."""
    fox, fitted, _, _, _, run, Gr, _ = fox_fit
    rule = np.stack([h.local(fox.skeleton, run) for h in fitted.helpers], axis=1)
    rng = np.random.default_rng(0)
    F, H = rule.shape[:2]
    kick = np.tile(np.eye(4), (F, H, 1, 1))
    kick[..., :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.3, size=(F * H, 3))).as_matrix().reshape(F, H, 3, 3)
    kick[..., :3, 3] = rng.normal(scale=0.05 * character_height(fox), size=(F, H, 3))
    truth = rule @ kick
    targets = fitted_positions(fox, fitted, Gr, run, truth)
    start = np.sqrt(((fitted_positions(fox, fitted, Gr, run) - targets) ** 2).sum(axis=2).max())
    tracks = fit_helper_tracks(fox, fitted, Gr, run, targets, sweeps=30)
    left = np.sqrt(((fitted_positions(fox, fitted, Gr, run, tracks) - targets) ** 2).sum(axis=2).max())
    assert start > 1e-2 * character_height(fox)
    assert left <= 1e-6 * character_height(fox), (start, left)
    np.testing.assert_allclose(tracks[..., :3, :3] @ np.swapaxes(tracks[..., :3, :3], -1, -2),
                               np.broadcast_to(np.eye(3), tracks[..., :3, :3].shape), atol=1e-9)


def test_each_sweep_lowers_the_error_on_a_held_out_clip(fox_fit):
    fox, fitted, _, _, _, run, Gr, Tr = fox_fit

    def sq(tracks):
        return ((fitted_positions(fox, fitted, Gr, run, tracks) - Tr) ** 2).sum()

    errors = [sq(None)] + [sq(fit_helper_tracks(fox, fitted, Gr, run, Tr, sweeps=s)) for s in (1, 2, 4)]
    assert all(b <= a * (1 + 1e-12) for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 0.95 * errors[0], errors


def test_alternation_keeps_a_partition_of_unity_and_lowers_the_training_error(fox_fit):
    fox, fitted, rom, G, targets, *_ = fox_fit
    refit = refit_with_tracks(fox, fitted, G, rom, targets, 4)
    before = ((fitted_positions(fox, fitted, G, rom, fit_helper_tracks(fox, fitted, G, rom, targets))
               - targets) ** 2).sum()
    after = ((fitted_positions(fox, refit, G, rom, fit_helper_tracks(fox, refit, G, rom, targets)) - targets) ** 2).sum()
    assert after < before
    w = refit.weights[0]
    assert (w >= 0).all() and np.allclose(w.sum(axis=1), 1) and w.shape[1] == 4
    assert refit.joints[0].max() < fox.skeleton.num_joints + len(fitted.helpers)
    assert [h.parent for h in refit.helpers] == [h.parent for h in fitted.helpers]
    # no helpers: nothing to alternate
    plain = fit_character(fox, G, targets, 4)
    assert refit_with_tracks(fox, plain, G, rom, targets, 4) is plain


def test_cli_fitted_tracks_file_plays_what_the_report_says(tmp_path, capsys):
    out, report = tmp_path / "fox.glb", tmp_path / "r.json"
    code = main(["fit-skin", str(FOX), "--train", "Walk", "--holdout", "Run", "--rom-degrees",
                 "30", "--helpers", "2", "--helper-tracks", "fitted", "-o", str(out), "--report", str(report)])
    assert code == 0, capsys.readouterr().err
    r = json.loads(report.read_text())
    assert r["helper_tracks"] == "fitted" and r["helpers"] >= 1
    assert played_rms(FOX, out, "Run") == pytest.approx(r["errors"]["Run"]["rms_fraction"], rel=1e-3)
    # the tracks beat the rule on the held-out clip (the same fit written with the rule)
    code = main(["fit-skin", str(FOX), "--train", "Walk", "--holdout", "Run", "--rom-degrees", "30", "--helpers", "2",
                 "-o", str(tmp_path / "rule.glb"), "--report", str(tmp_path / "rule.json")])
    assert code == 0
    assert r["errors"]["Run"]["rms"] < json.loads((tmp_path / "rule.json").read_text())["errors"]["Run"]["rms"]
