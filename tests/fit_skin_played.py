"""What a fitted file plays: shared by the fit-skin tests."""
from __future__ import annotations

import numpy as np
import pytest

from nrpose.fit.character_skin import character_height, nrmls_targets
from nrpose.io import load_character
from nrpose.model.timing import sample_times
from nrpose.pose.poser import CharacterPoser


def played_rms(source, out, clip: str, fps: float = 30.0) -> float:
    """RMS distance, as a fraction of the height, between the file ``out``'s clip ``clip``
    played by nrpose's LBS at ``fps`` and NR-MLS of the character ``source`` on the same clip."""
    character, back = load_character(source), load_character(out)
    played = [c for c in back.clips if c.name == clip][0]
    times = sample_times(played.duration, fps)
    lbs = CharacterPoser(back, method="lbs", backend="numpy").pose(played.sample(times)).positions
    _, targets = nrmls_targets(CharacterPoser(character, method="nrmls"), character.clip(clip).sample(times))
    return float(np.sqrt(((lbs - targets) ** 2).sum(axis=2).mean()) / character_height(character))


def client_errors(positions, character, clip, times) -> list[float]:
    """Per time, the largest distance, as a fraction of the bounding box, between a client's
    vertex positions (one (V, 3) array per time) and nrpose's LBS of ``character`` (the file
    loaded back) on ``clip`` at ``times``."""
    want = CharacterPoser(character, method="lbs", backend="numpy").pose(clip.sample(times)).positions
    size = np.ptp(want.reshape(-1, 3), axis=0).max()
    return [np.abs(np.asarray(p, float) - w).max() / size for p, w in zip(positions, want)]


def three_js_errors(out, back, clip) -> list[float]:
    """:func:`client_errors` of three.js (headless Chromium) playing the file ``out``, loaded back
    by nrpose as ``back``, at the start, middle and end of ``clip``; skips without Chromium."""
    from clients import browser
    reason = browser.available()
    if reason:
        pytest.skip(reason)
    times = np.array([0.0, 0.49 * clip.duration, clip.duration - 1e-3])   # three.js loops at the end
    report = browser.probe(out, times, clip=clip.name)
    assert not report.get("errors") and report.get("warnings", []) == [], report
    return client_errors([s["meshes"][0]["positions"] for s in report["samples"]], back, clip, times)


def blender_errors(out, back, clip) -> list[float]:
    """:func:`client_errors` of Blender importing and playing the file ``out`` at the first,
    middle and last keys of ``clip`` (Blender interpolates quaternion components between keys);
    skips without a Python with bpy."""
    from clients import blender
    reason = blender.available()
    if reason:
        pytest.skip(reason)
    keys = max(clip.tracks, key=lambda t: len(t.times)).times
    times = keys[[0, len(keys) // 2, -1]]
    report = blender.probe(out, times, clip.name)
    assert "ERROR" not in report["log"], report["log"]
    return client_errors([report["positions"][i][0] for i in range(len(times))], back, clip, times)
