"""A retargeted character in real clients: three.js (headless Chromium) and Blender 5.

CMU 131_03 on the Mannequin (a Mixamo export: its skinned mesh sits under a 0.01-scaled armature,
so three.js culls and frames it by a 1.8 cm sphere at the origin unless the writer places the node,
:func:`nrpose.io.gltf_write.fit_skinned_nodes`). Positions through each client's own animation and
skin state must equal nrpose's linear blend skinning of the clip (the glTF skinning formula).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nrpose import cli
from nrpose.io import load_character
from nrpose.pose.poser import CharacterPoser

from clients import blender, browser

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BVH = DATA / "bvh" / "131_03.bvh"
pytestmark = pytest.mark.skipif(not BVH.is_file(), reason=f"shared assets not found at {DATA}")


@pytest.fixture(scope="module")
def retargeted(tmp_path_factory):
    out = tmp_path_factory.mktemp("retarget") / "mannequin_131_03.glb"
    assert cli.main(["retarget", str(BVH), str(DATA / "gltf" / "Mannequin.glb"), "-o", str(out)]) == 0
    character = load_character(out)
    return out, character, character.clip("131_03")


def expected(character, clip, times) -> np.ndarray:
    return CharacterPoser(character, method="lbs", backend="numpy").pose(clip.sample(times)).positions.astype(float)


def test_three_js_plays_it_and_shows_it(retargeted, tmp_path):
    reason = browser.available()
    if reason:
        pytest.skip(reason)
    out, character, clip = retargeted
    # three.js loops the action: at exactly the duration it is back at time 0, so the last sample
    # is taken just before the end (between keys: three.js slerps as nrpose does)
    times = np.array([0.0, 0.49 * clip.duration, clip.duration - 1e-3])
    want = expected(character, clip, times)
    report = browser.probe(out, times, clip="131_03")
    assert not report.get("errors") and report.get("warnings", []) == [], report
    size = np.ptp(want.reshape(-1, 3), axis=0).max()
    errors = [np.abs(s["meshes"][0]["positions"] - w).max() / size for s, w in zip(report["samples"], want)]
    print(f"\nthree.js positions vs nrpose LBS, relative to the motion's extent: {errors}")
    assert max(errors) <= 1e-5
    from PIL import Image
    for t in (0.0, times[1]):
        png = browser.screenshot(out, tmp_path / f"mannequin_{t:.2f}.png", time=float(t), clip="131_03")
        image = np.asarray(Image.open(png).convert("RGB")).astype(int)
        background = np.median(image.reshape(-1, 3), axis=0)
        covered = (np.abs(image - background).sum(axis=-1) > 30).mean()
        print(f"screenshot at {t:.2f} s: {100 * covered:.2f}% of the pixels show the character ({png})")
        assert covered > 0.002            # visible: neither culled nor out of the framed view


def test_blender_imports_it_and_plays_it(retargeted):
    reason = blender.available()
    if reason:
        pytest.skip(reason)
    out, character, clip = retargeted
    # at keys: between them Blender interpolates quaternion components, not along the arc
    keys = max(clip.tracks, key=lambda t: len(t.times)).times
    times = keys[[0, len(keys) // 2, -1]]
    assert times[-1] == clip.duration
    want = expected(character, clip, times)
    report = blender.probe(out, times, "131_03")
    assert "WARNING" not in report["log"] and "ERROR" not in report["log"], report["log"]
    size = np.ptp(want.reshape(-1, 3), axis=0).max()
    errors = [np.abs(report["positions"][i][0] - w).max() / size for i, w in enumerate(want)]
    print(f"\nBlender positions vs nrpose LBS, relative to the motion's extent: {errors}")
    assert max(errors) <= 1e-5
