"""libigl weight and animation DMATs (nrpose.io.tgf, ``nrpose pose --weights-file / --motion X.dmat``).

Oracle: libigl's own linear blend skinning, ``igl.lbs_matrix(V, W) @ Tf``, with each frame's
column read as libigl tutorial 408_DirectDeltaMush reads it (a column-major (4·B) × 3 matrix).
"""
from __future__ import annotations

from pathlib import Path

import igl
import numpy as np
import pytest

from nrpose import cli
from nrpose.bind.bone_weights import with_skin_weights
from nrpose.errors import FileFormatError, InputError
from nrpose.io import load_character
from nrpose.io.tgf import bone_joints, read_dmat_animation, read_dmat_weights
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import LocalPose
from nrpose.pose.poser import CharacterPoser

from dmat_files import motion_matrix, transforms_matrix, write_dmat

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "libigl"
ARM = (DATA / "arm.obj", DATA / "arm.tgf", DATA / "arm-weights.dmat")
needs_data = pytest.mark.skipif(not ARM[0].is_file(), reason=f"shared assets not found at {DATA}")


@pytest.fixture(scope="module")
def arm():
    if not ARM[0].is_file():
        pytest.skip(f"shared assets not found at {DATA}")
    return load_character(ARM[0], ARM[1])


def animation(skeleton, frames: int, seed: int, hierarchy: bool) -> np.ndarray:
    """A (12·B) × frames libigl animation matrix of rigid per-bone transforms.

    hierarchy: transforms from forward kinematics (each bone rotates about its start, children
    follow); else independent random rigid motions per bone (LBS still defines the result).
    """
    rng = np.random.default_rng(seed)
    if hierarchy:
        pose = skeleton.rest_pose
        pose = LocalPose(np.tile(pose.translation, (frames, 1, 1)),
                         Rotation.from_rotvec(rng.normal(scale=0.6, size=(frames * skeleton.num_joints, 3)))
                         .as_quat().reshape(frames, -1, 4), np.tile(pose.scale, (frames, 1, 1)))
        return motion_matrix(skeleton, skeleton.forward_kinematics(pose))
    B = len(bone_joints(skeleton, "test"))
    A = np.tile(np.eye(4), (frames, B, 1, 1))
    A[..., :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.8, size=(frames * B, 3))).as_matrix().reshape(frames, B, 3, 3)
    A[..., :3, 3] = rng.normal(scale=0.3, size=(frames, B, 3))
    return transforms_matrix(A)


def libigl_lbs(V, W, T) -> np.ndarray:
    M = igl.lbs_matrix(V, W)
    B = W.shape[1]
    return np.stack([M @ T[:, f].reshape(3, 4 * B).T for f in range(T.shape[1])])


@needs_data
def test_weights_file_rows_and_columns(arm):
    W = read_dmat_weights(ARM[2], arm.skeleton, len(arm.meshes[0].vertices))
    raw = igl.readDMAT(str(ARM[2]))
    joints = bone_joints(arm.skeleton, "test")
    assert W.shape == (8311, arm.skeleton.num_joints)
    assert np.allclose(W[:, joints], raw / raw.sum(axis=1, keepdims=True), rtol=0, atol=1e-15)
    assert np.allclose(W.sum(axis=1), 1.0)


@needs_data
@pytest.mark.parametrize("backend", ["numpy", "opencl"])
@pytest.mark.parametrize("hierarchy", [True, False])
def test_animation_lbs_equals_libigl(arm, tmp_path, backend, hierarchy):
    raw = igl.readDMAT(str(ARM[2]))
    V = arm.meshes[0].vertices
    T = animation(arm.skeleton, 6, seed=int(hierarchy), hierarchy=hierarchy)
    clip = read_dmat_animation(write_dmat(tmp_path / "anim.dmat", T), arm.skeleton, fps=24)
    assert clip.duration == pytest.approx(5 / 24)
    character = with_skin_weights(arm, read_dmat_weights(ARM[2], arm.skeleton, len(V)))
    frames = CharacterPoser(character, method="lbs", weights="authored", backend=backend).pose(
        clip.sample(np.arange(6) / 24))
    want = libigl_lbs(V, raw, T)
    err = np.abs(frames.positions - want).max() / np.ptp(V, axis=0).max()
    assert err <= 2e-6, err
    # between frames the clip interpolates; the per-bone transforms are the file's exactly at frames
    joints = bone_joints(arm.skeleton, "test")
    G = arm.skeleton.forward_kinematics(clip.sample(3 / 24))[joints] @ np.linalg.inv(
        arm.skeleton.rest_globals()[joints])
    Tf = T[:, 3].reshape(3, -1).T
    assert np.abs(G[:, :3, :] - np.stack([Tf[4 * e:4 * e + 4].T for e in range(len(joints))])).max() < 1e-12


@needs_data
def test_one_column_layout_is_the_same_animation(arm, tmp_path):
    T = animation(arm.skeleton, 4, seed=7, hierarchy=True)
    a = read_dmat_animation(write_dmat(tmp_path / "a.dmat", T), arm.skeleton)
    b = read_dmat_animation(write_dmat(tmp_path / "b.dmat", T.ravel(order="F")[:, None]), arm.skeleton)
    t = np.linspace(0, a.duration, 9)
    assert np.array_equal(a.sample(t).rotation, b.sample(t).rotation)


@needs_data
def test_bad_dmats_raise_typed_errors(arm, tmp_path):
    skel, n = arm.skeleton, len(arm.meshes[0].vertices)
    raw = igl.readDMAT(str(ARM[2]))
    cases = [(raw[:-1], "expected 8311 rows"), (raw.T, "transposed"), (raw[:, :3], "4 columns")]
    neg = raw.copy()
    neg[10, 2] = -0.25
    zero = raw.copy()
    zero[17] = 0
    nan = raw.copy()
    nan[3, 1] = np.nan
    cases += [(neg, "vertex 10 on bone 2 is negative"), (zero, "vertex 17 has no weight"), (nan, "NaN")]
    for k, (matrix, message) in enumerate(cases):
        with pytest.raises(FileFormatError, match=message):
            read_dmat_weights(write_dmat(tmp_path / f"w{k}.dmat", matrix), skel, n)
    T = animation(skel, 3, seed=1, hierarchy=True)
    with pytest.raises(FileFormatError, match="do not divide into frames of 4 bones"):
        read_dmat_animation(write_dmat(tmp_path / "short.dmat", T[:-1]), skel)
    scaled = T.copy()
    scaled[:, 1] *= 1.5
    with pytest.raises(FileFormatError, match="frame 1, bone 0: the 3×3 part is not a rotation"):
        read_dmat_animation(write_dmat(tmp_path / "scaled.dmat", scaled), skel)
    with pytest.raises(FileFormatError, match="no such DMAT"):
        read_dmat_animation(tmp_path / "missing.dmat", skel)
    from nrpose.rigs.humanoid import humanoid
    with pytest.raises(InputError, match="needs a skeleton read from TGF"):
        read_dmat_animation(write_dmat(tmp_path / "h.dmat", T), humanoid().skeleton)


def run(args, capsys):
    code = cli.main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@needs_data
def test_cli_weights_file_and_dmat_motion(arm, tmp_path, capsys):
    T = animation(arm.skeleton, 5, seed=3, hierarchy=True)
    anim = write_dmat(tmp_path / "anim.dmat", T)
    out = tmp_path / "arm.npz"
    code, stdout, err = run(["pose", ARM[0], "--skeleton", ARM[1], "--weights-file", ARM[2], "--motion", anim,
                             "--method", "lbs", "-o", out], capsys)
    assert code == 0, err
    with np.load(out) as z:
        assert z["positions"].shape == (5, 8311, 3) and np.allclose(z["times"], np.arange(5) / 30)
        want = libigl_lbs(arm.meshes[0].vertices, igl.readDMAT(str(ARM[2])), T)
        assert np.abs(z["positions"] - want).max() <= 2e-6 * np.ptp(want[0], axis=0).max()
    out.unlink()
    bad_w = write_dmat(tmp_path / "w.dmat", np.ones((5, 4)))
    bad_a = write_dmat(tmp_path / "a.dmat", T[:-5])
    for args, message in [
            (["--weights-file", bad_w, "--rest"], "expected 8311 rows"),
            (["--weights-file", ARM[2], "--motion", bad_a], "do not divide into frames"),
            (["--weights-file", ARM[2], "--weights", "euclidean", "--rest"], "drop --weights euclidean")]:
        code, _, err = run(["pose", ARM[0], "--skeleton", ARM[1], *args, "-o", tmp_path / "o.npz"], capsys)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and message in lines[0], err
    assert not list(tmp_path.glob("o.*")) and not list(tmp_path.glob(".*"))
