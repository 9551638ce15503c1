"""``nrpose pose -o OUT.glb``: the baked forms (--bake, --quantize), their refusals, and the
round trip through ``nrpose info``."""
from __future__ import annotations

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

import gltf_asset
from nrpose.cli import main


def run(args, capsys):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture()
def asset(tmp_path):
    return gltf_asset.build(tmp_path / "asset.gltf")


def accessor(gltf, blob, index):
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    assert acc.componentType == 5126 and not view.byteStride
    return np.frombuffer(blob, "<f4", acc.count * width, (view.byteOffset or 0) + (acc.byteOffset or 0)
                         ).reshape(acc.count, width).astype(np.float64)


def test_skin_bake_is_the_files_own_skinning(asset, tmp_path, capsys):
    out, npz = tmp_path / "skin.glb", tmp_path / "lbs.npz"
    code, _, err = run(["pose", asset, "--clip", "bend", "--method", "lbs", "--bake", "skin", "-o", out,
                        "--backend", "numpy", "--fps", "4"], capsys)
    assert code == 0, err
    assert run(["pose", asset, "--clip", "bend", "--method", "lbs", "-o", npz, "--backend", "numpy",
                "--fps", "4"], capsys)[0] == 0
    frames = np.load(npz)
    gltf = pygltflib.GLTF2().load_binary(str(out))
    blob = gltf.binary_blob()
    src = pygltflib.GLTF2().load(str(asset))
    assert [m.to_dict() for m in gltf.materials] == [m.to_dict() for m in src.materials]
    leg = gltf.nodes[3]
    assert leg.skin == 0 and leg.mesh == 0
    animation, = gltf.animations
    assert animation.name == "bend" and len(animation.channels) == 2 * 3     # every joint, T/R/S
    keys = {}
    for channel in animation.channels:
        sampler = animation.samplers[channel.sampler]
        times = accessor(gltf, blob, sampler.input)[:, 0]
        assert np.allclose(times, frames["times"]) and sampler.interpolation == "LINEAR"
        keys[(channel.target.node, channel.target.path)] = accessor(gltf, blob, sampler.output)
    # glTF skinning of the file as written (independently of nrpose), at every key
    ibm = accessor(gltf, blob, gltf.skins[0].inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    start = 0
    for prim in gltf.meshes[0].primitives:
        V = accessor(gltf, blob, prim.attributes.POSITION)
        W = accessor(gltf, blob, prim.attributes.WEIGHTS_0)
        J = np.frombuffer(blob, np.uint8, len(V) * 4,
                          gltf.bufferViews[gltf.accessors[prim.attributes.JOINTS_0].bufferView].byteOffset
                          ).reshape(-1, 4)
        for f in range(len(frames["times"])):
            G = []
            for node in (1, 2):
                M = np.eye(4)
                M[:3, :3] = Rotation.from_quat(keys[(node, "rotation")][f]).as_matrix() * keys[(node, "scale")][f]
                M[:3, 3] = keys[(node, "translation")][f]
                G.append(M if node == 1 else G[0] @ M)
            skin = np.array(G) @ ibm
            got = np.einsum("nk,nkab,nb->na", W, skin[J], np.c_[V, np.ones(len(V))])[:, :3]
            assert np.abs(got - frames["positions"][f, start:start + len(V)]).max() < 1e-6
        start += len(V)


@pytest.mark.parametrize("extra, message", [
    (["--bake", "skin"], "--method lbs --weights authored"),
    (["--bake", "skin", "--method", "lbs", "--quantize"], "--quantize"),
    (["--quantize", "-o", "{tmp}/x.npz"], "not .glb"),
])
def test_bake_refusals(asset, tmp_path, capsys, extra, message):
    extra = [e.format(tmp=tmp_path) for e in extra]
    out = [] if "-o" in extra else ["-o", tmp_path / "x.glb"]
    code, _, err = run(["pose", asset, "--clip", "bend", *out, *extra], capsys)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.glb").exists() and not (tmp_path / "x.npz").exists()


def test_required_extension_refused_before_work(tmp_path, capsys):
    source = gltf_asset.build(tmp_path / "asset.glb", required=["EXT_tests_required"])
    code, out, err = run(["pose", source, "--clip", "bend", "-o", tmp_path / "x.glb"], capsys)
    assert code == 2 and "EXT_tests_required" in err and len(err.strip().splitlines()) == 1
    assert not out and sorted(p.name for p in tmp_path.iterdir()) == ["asset.glb"]
    # the skin bake copies the document untouched: nothing is lost
    code, _, err = run(["pose", source, "--clip", "bend", "--method", "lbs", "--bake", "skin",
                        "-o", tmp_path / "skin.glb", "--backend", "numpy"], capsys)
    assert code == 0, err


@pytest.mark.parametrize("quantize", [[], ["--quantize"]])
def test_round_trip_through_info(asset, tmp_path, capsys, quantize):
    code, _, err = run(["info", asset], capsys)
    out = tmp_path / "posed.glb"
    code, text, err = run(["pose", asset, "--clip", "bend", "-o", out, "--backend", "numpy", *quantize], capsys)
    assert code == 0, err
    assert "bytes per frame per vertex" in text
    code, text, err = run(["info", out], capsys)
    assert code == 0, err
    lines = text.splitlines()
    assert "meshes: 0" in lines and "static meshes (the skeleton does not move them; kept as they are, " \
                                    "never posed): 3" in lines
    assert {"  pedestal: 16 vertices, 8 faces", "  leg.0: 24 vertices, 16 faces",
            "  leg.1: 24 vertices, 16 faces"} <= set(lines)
