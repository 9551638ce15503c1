"""Whole-clip sampling and clip time checks (nrpose.model.timing, Clip.sample, ``--frames``/``--time``).

Durations read from glTF are float32 values: a clip of n frames at fps lasts float32(n / fps),
which is below n / fps in float64 about half of the time. Its last key must still be sampled.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nrpose.cli.pose import parse_frames
from nrpose.errors import InputError
from nrpose.model.character import Clip, Track
from nrpose.model.skeleton import Skeleton
from nrpose.model.timing import clip_times, sample_times, same_time

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOX = DATA / "gltf" / "Fox.glb"


def float32_clip(n: int, fps: float) -> Clip:
    """A one-joint clip keyed at float32(k / fps), k = 0..n, as a glTF file stores it."""
    skel = Skeleton(names=("root",), parents=np.array([-1]), translation=np.zeros((1, 3)),
                    rotation=np.array([[0.0, 0.0, 0.0, 1.0]]), scale=np.ones((1, 3)))
    times = (np.arange(n + 1) / fps).astype(np.float32).astype(np.float64)
    values = np.c_[times, np.zeros((n + 1, 2))]
    return Clip("c", float(times[-1]), skel.rest_pose, (Track(0, "translation", times, values),))


def test_float32_durations_keep_their_last_key():
    below = 0
    for fps in (24.0, 25.0, 30.0, 60.0):
        for n in range(1, 400):
            clip = float32_clip(n, fps)
            below += clip.duration < n / fps
            t = sample_times(clip.duration, fps)
            assert len(t) == n + 1, (n, fps)
            assert t[-1] == clip.duration                       # exactly the last key
            assert np.allclose(t[:-1], np.arange(n) / fps, rtol=0, atol=1e-12)
            assert np.array_equal(sample_times(clip.duration, fps, close=False), t)   # the end is on the grid
    assert below > 100          # the case the float64 comparison lost is common, not hypothetical


def test_the_issue_case_8_2667_s_at_30_fps():
    duration = float(np.float32(248 / 30))
    assert duration < 248 / 30 and np.floor(duration * 30 + 1e-6) + 1 == 248       # what the old rule gave
    t = sample_times(duration, 30)
    assert len(t) == 249 and t[-1] == duration


def test_off_grid_end_is_appended_unless_grid_only():
    t = sample_times(1.01, 30)
    assert len(t) == 32 and t[-2] == pytest.approx(1.0) and t[-1] == 1.01
    g = sample_times(1.01, 30, close=False)
    assert len(g) == 31 and g[-1] == pytest.approx(1.0)
    assert np.array_equal(sample_times(0.0, 30), [0.0])
    assert np.array_equal(sample_times(0.0, 30, close=False), [0.0])
    assert (np.diff(sample_times(9.1749633, 30)) > 0).all()
    with pytest.raises(InputError, match="fps"):
        sample_times(1.0, 0.0)
    with pytest.raises(InputError, match="duration"):
        sample_times(float("nan"), 30)


def test_frames_and_times_reach_the_last_key():
    clip = float32_clip(248, 30)
    times = parse_frames("0:248", 30.0)                    # A:B includes B
    assert len(times) == 249 and times[-1] == 248 / 30 > clip.duration
    pose = clip.sample(times)                               # accepted: equal in float32
    assert pose.translation[-1, 0, 0] == pytest.approx(clip.duration, abs=0)
    assert clip.sample(248 / 30).translation[0, 0] == clip.duration
    with pytest.raises(InputError, match="outside"):
        clip.sample(parse_frames("0:249", 30.0))
    with pytest.raises(InputError, match="outside"):
        clip.sample(clip.duration * (1 + 1e-6))
    assert same_time(248 / 30, clip.duration) and not same_time(clip.duration + 2e-6, clip.duration)
    assert clip_times([-1e-9, 0.5], 1.0)[0] == 0.0
    with pytest.raises(InputError):
        clip_times([np.nan], 1.0)


@pytest.mark.skipif(not FOX.is_file(), reason=f"shared assets not found at {DATA}")
@pytest.mark.parametrize("fps", [24.0, 30.0])
def test_fox_run_loop_closes(fps):
    from nrpose.io import load_character
    clip = load_character(FOX).clip("Run")
    last_key = max(t.times[-1] for t in clip.tracks)
    t = sample_times(clip.duration, fps)
    assert t[-1] == last_key == clip.duration
    first, last = clip.sample(t[[0, -1]]).rotation
    # a loop: the last frame is the last key, which equals the first one (no seam of a partial step)
    assert np.abs(np.abs(np.sum(first * last, axis=-1)) - 1).max() < 1e-6


@pytest.mark.parametrize("interpolation", ["LINEAR", "STEP", "CUBICSPLINE"])
def test_a_clip_samples_its_tracks_together_as_each_alone(interpolation):
    """Clip.sample interpolates tracks that share key times in one pass; each joint gets what
    its track gives alone, the last of two tracks of one target wins, and a track of equal
    keys holds its key."""
    rng = np.random.default_rng(7)
    J = 9
    skel = Skeleton(names=tuple(f"j{j}" for j in range(J)), parents=np.arange(J) - 1,
                    translation=rng.normal(size=(J, 3)), rotation=np.tile([0.0, 0, 0, 1], (J, 1)),
                    scale=np.ones((J, 3)))
    shared = np.sort(rng.uniform(0, 2, 6))
    tracks = []
    for path, width in (("translation", 3), ("rotation", 4), ("scale", 3)):
        def keys(times):
            return rng.normal(size=(len(times), 3, width) if interpolation == "CUBICSPLINE" else (len(times), width))
        tracks += [Track(j, path, shared, keys(shared), interpolation) for j in range(5)]
        tracks.append(Track(6, path, shared * 1.3, keys(shared), interpolation))     # other key times
        tracks.append(Track(2, path, shared, keys(shared), interpolation))           # 2 again: wins
        tracks.append(Track(6, path, shared, keys(shared), interpolation))           # 6 again, other times
        constant = np.repeat(keys(shared[:1]), len(shared), axis=0)
        tracks.append(Track(7, path, shared, constant, interpolation))
    clip = Clip("c", float(shared[-1] * 1.3), skel.rest_pose, tuple(tracks))
    t = np.concatenate([np.linspace(0, clip.duration, 41), shared])
    pose = clip.sample(t)
    for track in tracks:
        winner = [x for x in tracks if (x.joint, x.path) == (track.joint, track.path)][-1]
        got = getattr(pose, track.path)[:, track.joint]
        np.testing.assert_allclose(got, winner.sample(t), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(pose.translation[:, 8], np.broadcast_to(skel.translation[8], (len(t), 3)))  # rest
    if interpolation != "CUBICSPLINE":    # equal keys: the key itself (a slerp's rotation: unit)
        held = tracks[-1].values[0]
        np.testing.assert_array_equal(pose.scale[:, 7], np.broadcast_to(held, (len(t), 3)))
        rotation = [x for x in tracks if (x.joint, x.path) == (7, "rotation")][0].values[0]
        if interpolation == "LINEAR":
            rotation = rotation / np.linalg.norm(rotation)
        np.testing.assert_allclose(pose.rotation[:, 7], np.broadcast_to(rotation, (len(t), 4)), rtol=0, atol=1e-15)
