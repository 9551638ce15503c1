"""The direct glTF reader: equal to the pygltflib path, and strict on every field class."""
import base64
import copy
import dataclasses
import json
import pickle
import random
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from nrpose.errors import FileFormatError
from nrpose.io import load_character
from nrpose.io.gltf_read import document_character, joint_nodes, load_gltf, read_document
from nrpose.io.gltf_write import write_glb_with_clip
from test_io_characters import raw_accessor, save, synthetic_gltf

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SHARED = ["Fox", "Mannequin", "Ely"]


def assert_same_character(a, b):
    """Bitwise equal skeletons, meshes, inverse binds and clips."""
    for key in ("names", "parents", "translation", "rotation", "scale", "pre"):
        np.testing.assert_array_equal(np.asarray(getattr(a.skeleton, key)), np.asarray(getattr(b.skeleton, key)))
    np.testing.assert_array_equal(a.inverse_bind, b.inverse_bind)
    assert len(a.meshes) == len(b.meshes)
    for m, n in zip(a.meshes, b.meshes):
        assert (m.name, m.rigid_joint) == (n.name, n.rigid_joint)
        for key in ("vertices", "faces", "joints", "weights", "bind_vertices", "inverse_bind"):
            x, y = getattr(m, key), getattr(n, key)
            assert (x is None) == (y is None), key
            if x is not None:
                assert x.dtype == y.dtype, key
                np.testing.assert_array_equal(x, y)
    assert [(c.name, c.duration) for c in a.clips] == [(c.name, c.duration) for c in b.clips]
    for c, d in zip(a.clips, b.clips):
        assert len(c.tracks) == len(d.tracks)
        for s, t in zip(c.tracks, d.tracks):
            assert (s.joint, s.path, s.interpolation) == (t.joint, t.path, t.interpolation)
            np.testing.assert_array_equal(s.times, t.times)
            np.testing.assert_array_equal(s.values, t.values)


def read_all(path: Path):
    """The character of a glTF file with every clip made (clips are decoded when first used)."""
    character = load_gltf(path)
    tuple(character.clips)
    return character


def pygltflib_character(path: Path):
    """The same file decoded by pygltflib's dataclasses, then read by the same stages."""
    gltf, buffers = read_document(path)
    return document_character(path, gltf, buffers)


@pytest.mark.parametrize("name", SHARED)
def test_shared_characters_equal_the_pygltflib_path(name):
    path = DATA / "gltf" / f"{name}.glb"
    if not path.is_file():
        pytest.skip(f"shared test data not found at {path}")
    assert_same_character(load_gltf(path), pygltflib_character(path))


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_generated_characters_equal_the_pygltflib_path(tmp_path, suffix):
    path = save(synthetic_gltf(), tmp_path / f"c{suffix}")
    char = load_gltf(path)
    assert_same_character(char, pygltflib_character(path))
    # a file written by nrpose (the character with its clip appended) reads back the same way
    out = tmp_path / "with_clip.glb"
    clip = char.clip("clip")
    tracks = tuple(t for t in clip.tracks if t.interpolation != "CUBICSPLINE")  # what the writer takes
    linear = dataclasses.replace(clip, name="linear", tracks=tracks)
    write_glb_with_clip(path, out, char, linear)
    again = load_gltf(out)
    assert_same_character(again, pygltflib_character(out))
    assert [c.name for c in again.clips] == ["clip", "linear"]


def test_external_buffer_file_inside_the_folder(tmp_path):
    embedded = save(synthetic_gltf(), tmp_path / "c.gltf")
    doc = json.loads(embedded.read_text())
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "body data.bin").write_bytes(base64.b64decode(doc["buffers"][0]["uri"].split(",")[1]))
    doc["buffers"][0]["uri"] = "bin/body%20data.bin"
    external = tmp_path / "external.gltf"
    external.write_text(json.dumps(doc))
    assert_same_character(load_gltf(external), load_gltf(embedded))


# --- clips: decoded when first used -----------------------------------------------------------------

@pytest.mark.parametrize("name", SHARED)
def test_clips_decoded_on_use_equal_the_files_keys(name):
    """Each clip, made on first use (here the last first), holds exactly the keys of its
    animation's accessors (read by the tests' own reader), as a load that makes them all."""
    path = DATA / "gltf" / f"{name}.glb"
    if not path.is_file():
        pytest.skip(f"shared test data not found at {path}")
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    joint_of = {int(node): j for j, node in enumerate(joint_nodes(path, *read_document(path))[1])}
    character = load_gltf(path)
    last_first = [character.clips[i] for i in reversed(range(len(character.clips)))][::-1]
    every = tuple(load_gltf(path).clips)
    assert [c.name for c in last_first] == [c.name for c in every] == [a.name for a in gltf.animations]
    for anim, clip, again in zip(gltf.animations, last_first, every):
        channels = [ch for ch in anim.channels if ch.target.node in joint_of
                    and ch.target.path in ("translation", "rotation", "scale")]
        assert len(clip.tracks) == len(again.tracks) == len(channels)
        for ch, track, other in zip(channels, clip.tracks, again.tracks):
            sampler = anim.samplers[ch.sampler]
            times = raw_accessor(gltf, blob, sampler.input)[:, 0]
            values = raw_accessor(gltf, blob, sampler.output)
            mode = sampler.interpolation or "LINEAR"
            values = values.reshape(len(times), 3, -1) if mode == "CUBICSPLINE" else values
            for t in (track, other):
                assert (t.joint, t.path, t.interpolation) == (joint_of[ch.target.node], ch.target.path, mode)
                np.testing.assert_array_equal(t.times, times)
                np.testing.assert_array_equal(t.values, values)
        assert clip.duration == again.duration == max(float(t.times[-1]) for t in clip.tracks)


def malformed_second_clip(path: Path) -> Path:
    """The synthetic character with a second animation, "broken", whose key times are a VEC3
    accessor (a fault only its data shows), saved at ``path``."""
    gltf = synthetic_gltf()
    gltf.animations.append(pygltflib.Animation(name="broken", samplers=[
        pygltflib.AnimationSampler(input=12, output=11, interpolation="LINEAR")], channels=[
        pygltflib.AnimationChannel(sampler=0, target=pygltflib.AnimationChannelTarget(node=1, path="rotation"))]))
    return save(gltf, path)


BROKEN = r"animations\[1\]\.samplers\[0\]\.input: key times must be a float SCALAR accessor"


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_a_malformed_clip_is_refused_when_it_is_used(tmp_path, suffix):
    path = malformed_second_clip(tmp_path / f"two{suffix}")
    character = load_character(path)                       # the second clip is not decoded
    assert character.clips.names == ("clip", "broken") and len(character.clips) == 2
    assert character.clip("clip").duration == 2.0
    for _ in range(2):                                      # refused each time it is asked for
        with pytest.raises(FileFormatError, match=BROKEN) as info:
            character.clip("broken")
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(FileFormatError, match=BROKEN):
        tuple(character.clips)
    # a file written with the character's animations kept must read back: they are decoded first
    clip = character.clip("clip")
    linear = dataclasses.replace(clip, tracks=tuple(t for t in clip.tracks if t.interpolation != "CUBICSPLINE"))
    out = tmp_path / "out.glb"
    with pytest.raises(FileFormatError, match=BROKEN):
        write_glb_with_clip(path, out, character, linear)
    assert not out.exists()
    write_glb_with_clip(path, out, character, linear, keep_animations=False)
    assert load_character(out).clips.names == ("clip",)


def test_clip_translations_are_range_checked_when_used(tmp_path):
    gltf = synthetic_gltf()
    blob = gltf.binary_blob()
    far = np.float32([[1, 0, 0], [3e30, 0, 0]]).tobytes()
    gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(far)))
    gltf.accessors.append(pygltflib.Accessor(bufferView=len(gltf.bufferViews) - 1, componentType=5126, count=2,
                                             type="VEC3"))
    gltf.buffers[0].byteLength = len(blob) + len(far)
    gltf.set_binary_blob(blob + far)
    gltf.animations.append(pygltflib.Animation(name="far", samplers=[
        pygltflib.AnimationSampler(input=8, output=len(gltf.accessors) - 1)], channels=[
        pygltflib.AnimationChannel(sampler=0, target=pygltflib.AnimationChannelTarget(node=2, path="translation"))]))
    character = load_character(save(gltf, tmp_path / "far.glb"))
    assert character.clip("clip").duration == 2.0
    with pytest.raises(FileFormatError, match=r"far\.glb: clip 'far': translations of joint 'mid'"):
        character.clip("far")


def test_undecoded_clips_are_picklable(tmp_path):
    """A loaded character ships (a Ray bake's load task) with its clips still to make; they are
    made where they are used."""
    path = malformed_second_clip(tmp_path / "two.glb")
    copy_ = pickle.loads(pickle.dumps(load_character(path)))
    assert copy_.clip("clip").duration == 2.0
    with pytest.raises(FileFormatError, match=BROKEN):
        copy_.clip("broken")


# --- malformed files: one FileFormatError naming the field ------------------------------------------

def document(tmp_path) -> dict:
    """The synthetic character as a JSON document with an embedded (data: URI) buffer."""
    return json.loads(save(synthetic_gltf(), tmp_path / "seed.gltf").read_text())


def set_floats(doc: dict, accessor: int, values) -> None:
    """Overwrite the float32 data of an accessor in the document's embedded buffer."""
    acc = doc["accessors"][accessor]
    view = doc["bufferViews"][acc["bufferView"]]
    header, payload = doc["buffers"][0]["uri"].split(",")
    blob = bytearray(base64.b64decode(payload))
    data = np.asarray(values, np.float32).tobytes()
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    blob[start: start + len(data)] = data
    doc["buffers"][0]["uri"] = header + "," + base64.b64encode(bytes(blob)).decode()


def cycle(doc):
    """Nodes 1 (root joint) and 2 (its child) made each other's child, off the tree of node 0."""
    doc["nodes"][0]["children"].remove(1)
    doc["nodes"][2]["children"].append(1)


# the synthetic accessors: 0 POSITION (strided), 1 indices, 2/3 JOINTS_0/WEIGHTS_0, 6 prop (sparse),
# 7 inverse binds, 8 times [0, 1], 10 times [0, 2], 11 rotation keys (LINEAR), 12 translation keys (STEP)
CASES = {
    # wrong JSON type
    "count true": (lambda d: d["accessors"][0].update(count=True),
                   r"accessors\[0\]\.count = true: expected an integer ≥ 1"),
    "count Infinity": (lambda d: d["accessors"][9].update(count=float("inf")),
                       r"accessors\[9\]\.count = inf: expected an integer"),
    "count 1e3 float": (lambda d: d["accessors"][0].update(count=1e3), r"accessors\[0\]\.count = 1000\.0"),
    "bufferView as a string": (lambda d: d["accessors"][0].update(bufferView="0"),
                               r"accessors\[0\]\.bufferView = '0': expected an index into bufferViews"),
    "POSITION as a string": (lambda d: d["meshes"][0]["primitives"][0]["attributes"].update(POSITION="0"),
                             r"meshes\[0\]\.primitives\[0\]\.attributes\.POSITION = '0'"),
    "WEIGHTS_0 x": (lambda d: d["meshes"][0]["primitives"][0]["attributes"].update(WEIGHTS_0="x"),
                    r"attributes\.WEIGHTS_0 = 'x': expected an index into accessors"),
    "buffer null": (lambda d: d["bufferViews"][5].update(buffer=None), r"bufferViews\[5\]\.buffer = null"),
    "buffer missing": (lambda d: d["bufferViews"][5].pop("buffer"), r"bufferViews\[5\]\.buffer is missing"),
    "sampler null": (lambda d: d["animations"][0]["channels"][0].update(sampler=None),
                     r"animations\[0\]\.channels\[0\]\.sampler = null: expected an index into samplers \(0\.\.4\)"),
    "channel emptied": (lambda d: d["animations"][0]["channels"].__setitem__(2, {}),
                        r"animations\[0\]\.channels\[2\]\.sampler is missing"),
    "target true": (lambda d: d["animations"][0]["channels"][0].update(target=True),
                    r"channels\[0\]\.target = true: expected an object"),
    "target node false": (lambda d: d["animations"][0]["channels"][2]["target"].update(node=False),
                          r"channels\[2\]\.target\.node = false: expected an index into nodes"),
    "child true": (lambda d: d["nodes"][1]["children"].__setitem__(0, True), r"nodes\[1\]\.children\[0\] = true"),
    "skin joint 1e30": (lambda d: d["skins"][0]["joints"].__setitem__(0, 1e30),
                        r"skins\[0\]\.joints\[0\] = 1e\+30: expected an index into nodes"),
    "skin joint 2^64": (lambda d: d["skins"][0]["joints"].__setitem__(1, 2 ** 64),
                        r"skins\[0\]\.joints\[1\] = 18446744073709551616: skin 0 lists node 18446744073709551616, "
                        r"which does not exist \(5 nodes\)"),
    # out of range / enums / shapes
    "bufferView 99": (lambda d: d["accessors"][0].update(bufferView=99),
                      r"accessors\[0\]\.bufferView = 99: expected an index into bufferViews \(0\.\.\d+\)"),
    "scene 5": (lambda d: d.update(scene=5), r"scene = 5: expected an index into scenes \(0\.\.0\)"),
    "mode 7": (lambda d: d["meshes"][0]["primitives"][0].update(mode=7),
               r"primitives\[0\]\.mode = 7: expected one of 0, 1"),
    "componentType 5124": (lambda d: d["accessors"][1].update(componentType=5124),
                           r"accessors\[1\]\.componentType = 5124: expected one of 5120"),
    "type VEC5": (lambda d: d["accessors"][0].update(type="VEC5"), r"accessors\[0\]\.type = 'VEC5'"),
    "interpolation CUBIC": (lambda d: d["animations"][0]["samplers"][0].update(interpolation="CUBIC"),
                            r"samplers\[0\]\.interpolation = 'CUBIC': expected one of LINEAR, STEP, CUBICSPLINE"),
    "path position": (lambda d: d["animations"][0]["channels"][0]["target"].update(path="position"),
                      r"target\.path = 'position'"),
    "normalized float": (lambda d: d["accessors"][0].update(normalized=True), r"accessors\[0\]\.normalized = true"),
    "min of 2": (lambda d: d["accessors"][0].update(min=[0, 0]),
                 r"accessors\[0\]\.min = list: expected an array of 3"),
    "max NaN": (lambda d: d["accessors"][0].update(max=[0, float("nan"), 0]), r"accessors\[0\]\.max\[1\] = nan"),
    "stride 6": (lambda d: d["bufferViews"][0].update(byteStride=6),
                 r"bufferViews\[0\]\.byteStride = 6: expected a multiple of 4"),
    "stride 256": (lambda d: d["bufferViews"][0].update(byteStride=256),
                   r"byteStride = 256: expected an integer in 4\.\.252"),
    "stride < element": (lambda d: d["bufferViews"][0].update(byteStride=8),
                         r"bufferViews\[0\]\.byteStride = 8 is shorter than one element \(12 bytes\)"),
    "negative byteOffset": (lambda d: d["accessors"][0].update(byteOffset=-4), r"accessors\[0\]\.byteOffset = -4"),
    "sparse count > count": (lambda d: d["accessors"][6]["sparse"].update(count=9),
                             r"accessors\[6\]\.sparse\.count = 9: expected an integer in 1\.\.3"),
    "sparse index past count": (lambda d: d["accessors"][6].update(count=2),
                                r"accessor 6: sparse index 2 is out of range \(count 2\)"),
    "sparse indices float": (lambda d: d["accessors"][6]["sparse"]["indices"].update(componentType=5126),
                             r"sparse\.indices\.componentType = 5126: expected one of 5121, 5123, 5125"),
    "rotation 1e308": (lambda d: d["nodes"][1].update(rotation=[1e308, 0, 0, 1]),
                       r"nodes\[1\]\.rotation\[0\] = 1e\+308: expected a finite number within float32's range"),
    "rotation zero": (lambda d: d["nodes"][1].update(rotation=[0, 0, 0, 0]),
                      r"nodes\[1\]\.rotation = list: expected a unit quaternion \(x, y, z, w\); its length is 0"),
    "translation of 2": (lambda d: d["nodes"][3].update(translation=[0, 1]),
                         r"nodes\[3\]\.translation = list: expected an array of 3 numbers"),
    "scale string": (lambda d: d["nodes"][3].update(scale=[1, "1", 1]),
                     r"nodes\[3\]\.scale\[1\] = '1': expected a finite number"),
    "matrix and TRS": (lambda d: d["nodes"][2].update(translation=[0, 0, 0]), r"nodes\[2\] has both a matrix and"),
    "duplicate joint": (lambda d: d["skins"][0].update(joints=[1, 1]),
                        r"skins\[0\]\.joints\[1\] = 1: expected distinct"),
    "duplicate child": (lambda d: d["nodes"][0]["children"].append(1),
                        r"nodes\[0\]\.children\[2\] = 1: expected distinct"),
    "no primitives": (lambda d: d["meshes"][0].update(primitives=[]),
                      r"meshes\[0\]\.primitives = list: expected a non-empty"),
    "asset 1.0": (lambda d: d["asset"].update(version="1.0"), r"asset\.version = '1\.0': expected 2\.0"),
    "draco": (lambda d: d.update(extensionsRequired=["KHR_draco_mesh_compression"]),
              r"extensionsRequired\[0\] = 'KHR_draco_mesh_compression': nrpose cannot decode compressed meshes"),
    # sizes derived from counts, checked against the bytes before anything is allocated
    "zeros 2^31": (lambda d: d["accessors"][6].pop("bufferView") and d["accessors"][6].update(count=2 ** 31),
                   r"accessors\[6\]\.count = 2147483648: 25769803776 bytes of zeros without a bufferView, more than"),
    "count 2^40 in a view": (lambda d: d["accessors"][0].update(count=2 ** 40),
                             r"accessor 0 is out of range: it reads up to byte 17592186044\d+ of bufferView 0"),
    "view past its buffer": (lambda d: d["bufferViews"][0].update(byteLength=2 ** 40),
                             r"bufferViews\[0\]: bytes 0\.\.1099511627776 run past buffer 0"),
    "byteLength past the data": (lambda d: d["buffers"][0].update(byteLength=d["buffers"][0]["byteLength"] + 4),
                                 r"buffer 0 holds \d+ bytes, byteLength says"),
    "accessors x10001": (lambda d: d.update(accessors=d["accessors"] * 626),
                         r"accessors has 10016 entries, more than a character file holds \(at most 10000\)"),
    # the node graph: a forest
    "cycle": (cycle, r"the node hierarchy contains a cycle"),
    "two parents": (lambda d: d["nodes"][3].update(children=[2]),
                    r"node 3 lists child 2, which does not exist or already has a parent"),
    "own child": (lambda d: d["nodes"][3].update(children=[3]), r"node 3 lists child 3"),
    # animation samplers
    "zero keys": (lambda d: d["accessors"][8].update(count=0), r"accessors\[8\]\.count = 0: expected an integer ≥ 1"),
    "times decrease": (lambda d: set_floats(d, 8, [1, 0]),
                       r"animation 0 channel 0: .*key times must increase strictly"),
    "times not scalar": (lambda d: d["animations"][0]["samplers"][0].update(input=12),
                         r"animations\[0\]\.samplers\[0\]\.input: key times must be a float SCALAR accessor"),
    "zero rotation keys": (lambda d: set_floats(d, 11, np.zeros((2, 4))),
                           r"animations\[0\]\.samplers\[0\]\.output: rotation key 0 has length 0"),
    "too few values": (lambda d: d["animations"][0]["samplers"][1].update(output=11),
                       r"animation 0 channel 1: .*shape"),
    # buffer URIs
    "uri %00": (lambda d: d["buffers"][0].update(uri="body%00.bin"),
                r"buffers\[0\]\.uri = 'body%00\.bin': expected a data: URI or a file name"),
    "uri ..": (lambda d: d["buffers"][0].update(uri="../body.bin"), r"buffers\[0\]\.uri = '\.\./body\.bin'"),
    "uri %2e%2e": (lambda d: d["buffers"][0].update(uri="%2e%2e/body.bin"),
                   r"buffers\[0\]\.uri = '%2e%2e/body\.bin'"),
    "uri absolute": (lambda d: d["buffers"][0].update(uri="/etc/passwd"), r"buffers\[0\]\.uri = '/etc/passwd'"),
    "uri http": (lambda d: d["buffers"][0].update(uri="http://example.com/b.bin"), r"buffers\[0\]\.uri = 'http:"),
    "uri not a string": (lambda d: d["buffers"][0].update(uri=7), r"buffers\[0\]\.uri = 7: expected a string"),
    "data uri not base64": (lambda d: d["buffers"][0].update(uri="data:application/octet-stream,AAAA"),
                            r"buffer 0 has a malformed data: URI"),
    "data uri bad base64": (lambda d: d["buffers"][0].update(uri="data:application/octet-stream;base64,A*A="),
                            r"buffer 0 has a malformed data: URI"),
    "missing file": (lambda d: d["buffers"][0].update(uri="nothere.bin"), r"nothere\.bin: no such file"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_malformed_field_is_named(tmp_path, case):
    edit, message = CASES[case]
    doc = document(tmp_path)
    edit(doc)
    path = tmp_path / "bad.gltf"
    path.write_text(json.dumps(doc))
    with pytest.raises(FileFormatError, match=message) as info:
        read_all(path)
    text = str(info.value)
    assert "\n" not in text and str(path) in text


def test_glb_json_chunk_is_checked_the_same(tmp_path):
    gltf = synthetic_gltf()
    gltf.accessors[0].count = True
    with pytest.raises(FileFormatError, match=r"bad\.glb: accessors\[0\]\.count = true"):
        load_gltf(save(gltf, tmp_path / "bad.glb"))


@pytest.mark.parametrize("root", ["[]", "7", '"glTF"', "null"])
def test_root_must_be_an_object(tmp_path, root):
    path = tmp_path / "r.gltf"
    path.write_text(root)
    with pytest.raises(FileFormatError, match="not an object"):
        load_gltf(path)


def test_deep_json_is_refused_by_depth(tmp_path):
    doc = document(tmp_path)
    path = tmp_path / "deep.gltf"
    path.write_text(json.dumps(doc)[:-1] + ', "extras": ' + "[" * 5000 + "]" * 5000 + "}")
    with pytest.raises(FileFormatError, match="nests arrays/objects 5001 deep"):
        load_gltf(path)


def leaves(value, prefix=()):
    """(path, value) of every scalar in a JSON document."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from leaves(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from leaves(v, prefix + (i,))
    else:
        yield prefix, value


def test_random_field_mutations_are_read_or_refused(tmp_path):
    """Every scalar of the document replaced by values of other JSON types or out of range:
    the file and its clips are read, or refused with a FileFormatError (never another exception)."""
    seed = document(tmp_path)
    spots = [p for p, v in leaves(seed) if not (p[0] == "buffers" and p[-1] == "uri")]
    bad = [None, True, False, -1, 0, 1, 3, 2 ** 31, 2 ** 64, 1e30, -1e308, float("inf"), float("nan"), 0.5,
           "0", "", "x", [], {}, [0], {"a": 1}]
    rng = random.Random(0)
    refused = 0
    for k in range(300):
        doc = copy.deepcopy(seed)
        for _ in range(1 + k % 2):
            where = rng.choice(spots)
            target = doc
            for step in where[:-1]:
                target = target[step]
            target[where[-1]] = rng.choice(bad)
        path = tmp_path / "m.gltf"
        path.write_text(json.dumps(doc))
        try:
            read_all(path)
        except FileFormatError as exc:
            assert "\n" not in str(exc)
            refused += 1
    assert refused > 150
