"""Frames streamed as they are posed (CharacterPoser.stream, ``nrpose pose -o OUT.npz``): the
same frames as CharacterPoser.pose, bit for bit, in one batch's memory; an .npz written from
them equals one written from all the frames; a run that fails half-way leaves no output."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nrpose.cli import main
from nrpose.pose.poser import BATCH, CharacterPoser, FrameStream

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOX = DATA / "gltf" / "Fox.glb"


pytestmark = pytest.mark.usefixtures("own_cache")   # fixtures fox and own_cache: tests/conftest.py


def clip_poses(ch, frames: int):
    clip = ch.clips[0]
    return clip.sample(np.linspace(0.0, clip.duration, frames))


@pytest.mark.parametrize("method, backend", [("nrmls", "opencl"), ("lbs", "opencl"), ("dqs", "opencl"),
                                             ("lbs", "numpy")])
def test_stream_equals_pose_bitwise(fox, method, backend):
    frames = 2 * BATCH + 3                       # two whole batches and a part
    local = clip_poses(fox, frames)
    poser = CharacterPoser(fox, method=method, backend=backend)
    whole = poser.pose(local)
    stream = poser.stream(local)
    assert isinstance(stream, FrameStream) and stream.count == frames and stream.vertices == poser.n
    got, memory = [], set()
    for batch in stream.batches:
        assert batch.dtype == np.float32 and batch.shape[1:] == (poser.n, 3) and len(batch) <= BATCH
        memory.add(batch.__array_interface__["data"][0])
        got.append(batch.copy())
    assert [len(b) for b in got] == [BATCH, BATCH, 3]
    assert len(memory) == 1                           # one batch's memory, reused
    assert np.concatenate(got).tobytes() == np.ascontiguousarray(whole.positions).tobytes()
    assert (stream.frame_ms > 0).all()
    assert stream.faces is poser.faces and stream.mesh_names == whole.mesh_names


@pytest.mark.parametrize("method", ["nrmls", "lbs"])
def test_stream_with_a_rigid_mesh_equals_pose(method):
    from test_pose_poser import two_bone_character
    ch = two_bone_character()
    rot = np.array([0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)])
    angles = np.linspace(0, 1, BATCH + 5)[:, None]
    q = np.zeros((len(angles), 3, 4))
    q[:, :, 3] = 1.0
    q[:, 1] = rot * angles + [0, 0, 0, 1.0] * (1 - angles)
    q /= np.linalg.norm(q, axis=2, keepdims=True)
    skel = ch.skeleton
    from nrpose.model.skeleton import LocalPose
    local = LocalPose(np.broadcast_to(skel.translation, (len(q), 3, 3)), q, np.broadcast_to(skel.scale, (len(q), 3, 3)))
    poser = CharacterPoser(ch, method=method)
    whole = poser.pose(local).positions
    streamed = np.concatenate([b.copy() for b in poser.stream(local).batches])
    assert streamed.tobytes() == np.ascontiguousarray(whole).tobytes()


def test_stream_checks_the_pose_before_any_frame(fox):
    from nrpose.errors import InputError
    local = clip_poses(fox, 3)
    bad = type(local)(local.translation + np.inf, local.rotation, local.scale)
    with np.errstate(all="ignore"), pytest.raises(InputError, match="infinity"):
        CharacterPoser(fox, method="lbs").stream(bad)


@pytest.mark.parametrize("process", ["in-process", "nrpose program"])
@pytest.mark.parametrize("method", ["nrmls", "lbs"])
def test_cli_npz_equals_the_posed_frames(fox, method, tmp_path, process):
    """The command's frames are the library's bitwise, also from the ``nrpose`` program, whose
    context is PoCL's worker device alone (whole-job launches) where this process shares launches."""
    out = tmp_path / "o.npz"
    argv = ["pose", str(FOX), "--clip", "Survey", "--method", method, "-o", str(out)]
    if process == "in-process":
        assert main(argv) == 0
    else:
        env = {k: v for k, v in os.environ.items() if k not in ("NRPOSE_WHOLE_JOB", "POCL_DEVICES")}
        done = subprocess.run([sys.executable, "-m", "nrpose", *argv], env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    clip = fox.clip("Survey")
    from nrpose.model.timing import sample_times
    times = sample_times(clip.duration, 30.0)
    frames = CharacterPoser(fox, method=method).pose(clip.sample(times))
    with np.load(out) as z:
        assert z.files == ["positions", "faces", "times", "mesh_names", "mesh_offsets"]
        assert z["positions"].shape == (len(times), frames.positions.shape[1], 3)
        assert z["positions"].tobytes() == np.ascontiguousarray(frames.positions).tobytes()
        assert np.array_equal(z["times"], times) and np.array_equal(z["faces"], frames.faces)


@pytest.mark.parametrize("output", ["o.npz", "frames"])
def test_a_failure_half_way_through_the_stream_leaves_the_old_output(fox, tmp_path, monkeypatch, capsys, output):
    """The writer has taken the first batches when the next is refused: the temporary file is
    removed and the previous output stays as it was."""
    import nrpose.cli.pose as cli_pose
    work = tmp_path / "work"
    work.mkdir()
    out = work / output
    if output.endswith(".npz"):
        out.write_bytes(b"the previous run's output")
    else:
        out.mkdir()
        (out / "frame_0000.ply").write_text("previous")
    before = {p.name: p.read_bytes() for p in work.rglob("*") if p.is_file()}
    checked = []
    real = cli_pose.check_finite

    def fail_on_the_third(positions):
        checked.append(len(positions))
        if len(checked) == 3:
            positions = positions.copy()
            positions[0, 0, 0] = np.nan
        real(positions)
    monkeypatch.setattr(cli_pose, "check_finite", fail_on_the_third)
    code = main(["pose", str(FOX), "--clip", "Survey", "--method", "lbs", "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "non-finite" in err and err.count("\n") == 1
    assert len(checked) == 3                                   # it failed after two batches were written
    after = {p.name: p.read_bytes() for p in work.rglob("*") if p.is_file()}
    assert after == before
    assert not [p for p in os.listdir(work) if p.startswith(".nrpose-")]
