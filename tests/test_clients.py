"""nrpose's glTF outputs in real clients: three.js (GLTFLoader in headless Chromium), Blender 5's
importer, and gltfpack as a strict parser. Each client skips with its reason when absent.

Outputs: Fox's Run and Mannequin's clip baked as float morph targets, Fox quantized, Mannequin's
skin bake (``--method lbs --bake skin``), and the test asset (two materials, a texture, tangents,
a static pedestal). Positions sampled through each client's own morph/skin state at three key
times must equal the ``.npz`` of the same command: within 1e-5 of the bounding-box diagonal for
float bakes and skins, within :data:`nrpose.io.gltf_write.QUANTIZATION_BOUND` for quantized ones.
Screenshots are written to ``$NRPOSE_SHOTS`` (a directory) when set, else to pytest's temporary
directory; their paths are printed.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import gltf_asset
from clients import blender, browser
from nrpose.cli import main
from nrpose.io.gltf_write import QUANTIZATION_BOUND

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MANNEQUIN_CLIP = "Armature|mixamo.com|Layer0"

#: case -> (character, clip, extra pose options, tolerance as a fraction of the bounding-box diagonal)
CASES = {
    "fox-morph": ("Fox", "Run", [], 1e-5),
    "fox-quantized": ("Fox", "Run", ["--quantize"], QUANTIZATION_BOUND),
    "mannequin-morph": ("Mannequin", MANNEQUIN_CLIP, [], 1e-5),
    "mannequin-skin": ("Mannequin", MANNEQUIN_CLIP, ["--method", "lbs", "--bake", "skin"], 1e-5),
    "asset-morph": ("asset", "bend", [], 1e-5),
}


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """case -> (OUT.glb, positions (F, V, 3), times (F,), diagonal) from ``nrpose pose``."""
    if not DATA.is_dir():
        pytest.skip(f"shared test data not found at {DATA}")
    folder = tmp_path_factory.mktemp("clients")
    sources = {"Fox": DATA / "gltf" / "Fox.glb", "Mannequin": DATA / "gltf" / "Mannequin.glb",
               "asset": gltf_asset.build(folder / "asset.gltf")}
    made = {}
    for case, (name, clip, extra, _) in CASES.items():
        method = extra[extra.index("--method") + 1] if "--method" in extra else "nrmls"
        npz, glb = folder / f"{case}.npz", folder / f"{case}.glb"
        common = ["pose", str(sources[name]), "--clip", clip, "--method", method]
        assert main([*common, "-o", str(npz)]) == 0
        assert main([*common, *[e for e in extra if e not in ("--method", method)], "-o", str(glb)]) == 0
        with np.load(npz) as z:
            P, T = z["positions"].astype(np.float64), z["times"]
        made[case] = (glb, P, T, float(np.linalg.norm(np.ptp(P[0], axis=0))))
    return made


def key_times(T):
    """Three key times: first, middle, last but one (players wrap a looping clip's last key to 0)."""
    return sorted({0, len(T) // 2, max(len(T) - 2, 0)})


def posed(meshes, keep):
    """Concatenated positions of the client's meshes that nrpose posed."""
    return np.concatenate([m for m, k in zip(meshes, keep) if k])


@pytest.mark.skipif(browser.available() is not None, reason=str(browser.available()))
@pytest.mark.parametrize("case", list(CASES))
def test_threejs_plays_the_output(outputs, case):
    glb, P, T, diagonal = outputs[case]
    clip, tolerance = CASES[case][1], CASES[case][3]
    idx = key_times(T)
    report = browser.probe(glb, T[idx], clip)
    assert report.get("error") is None and report["errors"] == [], report
    assert [a["name"] for a in report["animations"]] == [clip]
    skin = "--bake" in CASES[case][2]
    keep = [m["skinned"] if skin else m["morphTargets"] > 0 for m in report["meshes"]]
    for mesh, k in zip(report["meshes"], keep):
        assert mesh["normal"] and mesh["uv"] or not k          # nothing of the asset lost
        if k and not skin:
            assert mesh["morphTargets"] == mesh["morphNormals"] == len(T)
    if case.startswith("fox"):
        assert report["meshes"][0]["materials"][0]["map"]      # the texture
    if case == "asset-morph":
        assert [m["name"] for m in report["meshes"]] == ["pedestal", "leg_0", "leg_1"]
        assert [m["tangent"] and m["color"] for m in report["meshes"]] == [False, True, True]
        assert [m["materials"][0]["name"] for m in report["meshes"]] == ["stone", "skin", "stone"]
    errors = []
    for i, sample in zip(idx, report["samples"]):
        got = posed([m["positions"] for m in sample["meshes"]], keep)
        errors.append(np.abs(got - P[i]).max() / diagonal)
    print(f"three.js {case}: largest error at times {T[idx]}: {max(errors):.2e} of the diagonal")
    assert max(errors) <= tolerance


def shot_folder(tmp_path) -> Path:
    folder = Path(os.environ.get("NRPOSE_SHOTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@pytest.mark.skipif(browser.available() is not None, reason=str(browser.available()))
@pytest.mark.parametrize("case, time", [("fox-morph", 0.3), ("fox-quantized", 0.3), ("mannequin-morph", 0.03),
                                        ("asset-morph", 0.8)])
def test_threejs_screenshot(outputs, case, time, tmp_path):
    glb = outputs[case][0]
    png = browser.screenshot(glb, shot_folder(tmp_path) / f"{case}.png", time, CASES[case][1])
    print(f"screenshot: {png}")
    pixels = np.asarray(Image.open(png).convert("RGB")).astype(int)
    background = pixels[0, 0]
    drawn = np.abs(pixels - background).sum(axis=2) > 30
    assert 0.02 < drawn.mean() < 0.9                           # the character is in the picture
    if case.startswith("fox"):                                 # textured: the fox's orange fur
        r, g, b = pixels[drawn].T
        assert ((r > 150) & (g > 40) & (g < 140) & (b < 60)).mean() > 0.3


@pytest.mark.skipif(blender.available() is not None, reason=str(blender.available()))
@pytest.mark.parametrize("case", list(CASES))
def test_blender_imports_the_output(outputs, case):
    glb, P, T, diagonal = outputs[case]
    idx = key_times(T)
    report = blender.probe(glb, T[idx], CASES[case][1])
    assert report["result"] == ["FINISHED"]
    assert "WARNING" not in report["log"] and "ERROR" not in report["log"], report["log"]
    keep = [m["name"] != "pedestal" for m in report["meshes"]]
    for mesh in report["meshes"]:
        assert mesh["materials"] and mesh["uv_layers"] >= (0 if mesh["name"] == "pedestal" else 1)
        assert mesh["custom_normals"] or mesh["name"] == "pedestal"
    errors = [np.abs(posed(report["positions"][k], keep) - P[i]).max() / diagonal for k, i in enumerate(idx)]
    print(f"Blender {case}: largest error at times {T[idx]}: {max(errors):.2e} of the diagonal")
    assert max(errors) <= CASES[case][3]


@pytest.mark.skipif(shutil.which("gltfpack") is None, reason="gltfpack not installed (Debian package gltfpack)")
@pytest.mark.parametrize("case", list(CASES))
def test_gltfpack_parses_the_output(outputs, case, tmp_path):
    run = subprocess.run(["gltfpack", "-i", str(outputs[case][0]), "-o", str(tmp_path / "packed.glb")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert not [line for line in (run.stdout + run.stderr).splitlines() if line.lower().startswith("error")]
    assert (tmp_path / "packed.glb").stat().st_size > 0
