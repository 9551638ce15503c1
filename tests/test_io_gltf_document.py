"""read_document builds the pygltflib document pygltflib's own decoder builds (the writers edit it)."""
from __future__ import annotations

import json
from pathlib import Path

import pygltflib

from fuzzing.seeds import glb_bytes, gltf_document
from nrpose.io.gltf_read import read_document

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "gltf"


def _same(a, b, where="gltf") -> None:
    """Equal types and values, attribute by attribute (pygltflib's dataclasses compare extras loosely)."""
    assert type(a) is type(b), where
    if hasattr(a, "__dict__"):
        assert set(vars(a)) == set(vars(b)), where
        for k in vars(a):
            _same(getattr(a, k), getattr(b, k), f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


def _documents(tmp_path):
    doc, blob = gltf_document(None)
    doc["extras"] = {"note": [1, 2]}
    doc["meshes"][0]["primitives"][0]["attributes"]["_CUSTOM"] = 0      # an attribute pygltflib does not name
    doc["accessors"][5]["min"] = [0]                                   # an integer where pygltflib keeps floats
    doc["animations"] *= 50
    (tmp_path / "seed.glb").write_bytes(glb_bytes(None, blob, json.dumps(doc)))
    yield tmp_path / "seed.glb"
    yield from sorted(SHARED.glob("*.glb"))


def test_read_document_matches_pygltflib(tmp_path):
    for path in _documents(tmp_path):   # the seed, and the shared characters when ../shared is there
        text = path.read_bytes()
        length = int.from_bytes(text[12:16], "little")
        expected = pygltflib.GLTF2.gltf_from_json(text[20:20 + length].decode())
        got, _ = read_document(path)
        _same(expected, got, path.name)
        assert got.gltf_to_json() == expected.gltf_to_json()
