"""Baked morph-target animations written as .glb."""
import json
import re

import numpy as np
import pygltflib
import pytest

from nrpose.model.character import Mesh
from nrpose.errors import InputError
from nrpose.io.gltf_write import float32_times, json_float32, write_animated_glb


def accessor(gltf, blob, index):
    """Independent reading of a tightly packed accessor as float64 (count, width)."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5126: "<f4", 5125: "<u4"}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    a = np.frombuffer(blob, dtype, acc.count * width, start).reshape(acc.count, width)
    return a.astype(np.float64)


def two_meshes():
    rng = np.random.default_rng(3)
    tet = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    A = Mesh("a", rng.normal(size=(4, 3)), tet)
    B = Mesh("b", rng.normal(size=(5, 3)) + 3.0, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]]))
    return [A, B]


def test_round_trip(tmp_path):
    meshes = two_meshes()
    rest = np.concatenate([m.vertices for m in meshes])
    rng = np.random.default_rng(4)
    frames = 7
    P = rest[None] + 0.3 * rng.normal(size=(frames, len(rest), 3))
    T = np.linspace(0.0, 1.2, frames)
    out = tmp_path / "baked.glb"
    write_animated_glb(out, meshes, P.astype(np.float32), T, [0, 4])
    assert not [p for p in tmp_path.iterdir() if p.name != "baked.glb"]   # no temp left over
    gltf = pygltflib.GLTF2().load_binary(str(out))
    blob = gltf.binary_blob()
    assert len(gltf.meshes) == 2 and len(gltf.nodes) == 2 and len(gltf.animations) == 1
    for k, (m, start) in enumerate(zip(meshes, (0, 4))):
        prim = gltf.meshes[k].primitives[0]
        base = accessor(gltf, blob, prim.attributes.POSITION)
        acc = gltf.accessors[prim.attributes.POSITION]
        # the bounds read as float32 are the data's own, written in at most 9 significant digits
        assert np.array_equal(np.float32(acc.min), base.min(axis=0)) and np.array_equal(np.float32(acc.max),
                                                                                      base.max(axis=0))
        faces = accessor(gltf, blob, prim.indices).reshape(-1, 3)
        assert np.array_equal(faces, m.faces)
        assert len(prim.targets) == frames
        for f, target in enumerate(prim.targets):
            delta = accessor(gltf, blob, target["POSITION"])
            tacc = gltf.accessors[target["POSITION"]]
            assert tacc.min is not None and tacc.max is not None
            got = base + delta
            assert np.abs(got - P[f, start:start + len(m.vertices)].astype(np.float32)).max() < 1e-6
        assert gltf.meshes[k].weights == [1.0] + [0.0] * (frames - 1)
    anim = gltf.animations[0]
    assert {c.target.path for c in anim.channels} == {"weights"}
    assert sorted(c.target.node for c in anim.channels) == [0, 1]
    sampler = anim.samplers[anim.channels[0].sampler]
    assert sampler.interpolation == "LINEAR"
    times = accessor(gltf, blob, sampler.input)[:, 0]
    assert np.allclose(times, T) and gltf.accessors[sampler.input].min == [0.0]
    weights = accessor(gltf, blob, sampler.output).reshape(frames, frames)
    assert np.array_equal(weights, np.eye(frames))            # one-hot at each key time
    text = out.read_bytes()[20:20 + int.from_bytes(out.read_bytes()[12:16], "little")].decode()
    doc = json.loads(text)
    # glTF's defaults (LINEAR, an accessor at its view's start, not normalised) unwritten; no float64 digits
    assert '"LINEAR"' not in text and '"normalized":false' not in text
    assert all(a.get("byteOffset", 1) != 0 for a in doc["accessors"]), doc["accessors"]
    numbers = [float(x) for x in re.findall(r"-?\d+\.\d+(?:e[-+]?\d+)?", text)]
    assert numbers and json_float32(numbers) == numbers       # each the shortest float32 decimal
    with pytest.raises(InputError, match="NaN or infinite"):
        json_float32([1.0, np.nan])
    with pytest.raises(InputError, match="float32"):
        json_float32([1e39])


def test_humanoid_frames(tmp_path):
    from nrpose.rigs.humanoid import humanoid

    c = humanoid()
    m = c.meshes[0]
    clip = c.clip("walk")
    t = np.linspace(0.0, clip.duration, 4)
    K = c.skin_matrices(c.skeleton.forward_kinematics(clip.sample(t)))
    M = np.einsum("nk,fnkab->fnab", m.weights, K[:, m.joints])
    P = np.einsum("fnab,nb->fna", M, np.c_[m.vertices, np.ones(len(m.vertices))])[..., :3]
    out = tmp_path / "walk.glb"
    write_animated_glb(out, c, P, t)
    assert out.stat().st_size < 14 * 5 * len(m.vertices) * 3 + 400_000
    gltf = pygltflib.GLTF2().load_binary(str(out))
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    base = accessor(gltf, blob, prim.attributes.POSITION)
    last = base + accessor(gltf, blob, prim.targets[-1]["POSITION"])
    assert np.abs(last - P[-1]).max() < 1e-5


@pytest.mark.parametrize("change, message", [
    (lambda P, T: (P[:, :-1], T), "positions"),
    (lambda P, T: (P[..., :2], T), "positions"),
    (lambda P, T: (np.where(np.arange(3)[:, None, None] == 1, np.nan, P), T), "NaN"),
    (lambda P, T: (P, T[:-1]), "times"),
    (lambda P, T: (P, T[::-1]), "increasing"),
    (lambda P, T: (P, T - 1.0), "non-negative"),
])
def test_bad_input(tmp_path, change, message):
    meshes = two_meshes()
    rest = np.concatenate([m.vertices for m in meshes])
    P, T = np.repeat(rest[None], 3, axis=0), np.array([0.0, 0.5, 1.0])
    P, T = change(P, T)
    out = tmp_path / "bad.glb"
    with pytest.raises(InputError, match=message):
        write_animated_glb(out, meshes, P, T)
    assert not list(tmp_path.iterdir())


def test_bad_meshes_and_offsets(tmp_path):
    meshes = two_meshes()
    P, T = np.zeros((2, 9, 3)), np.array([0.0, 1.0])
    with pytest.raises(InputError, match="mesh_offsets"):
        write_animated_glb(tmp_path / "x.glb", meshes, P, T, [0, 3])
    with pytest.raises(InputError, match="meshes"):
        write_animated_glb(tmp_path / "x.glb", [], P, T)
    with pytest.raises(InputError, match=r"mesh 0 \(mesh0\) faces: 1 of 1 faces index vertices outside 0\.\.2"):
        write_animated_glb(tmp_path / "x.glb", [(np.zeros((3, 3)), [[0, 1, 5]])], P[:, :3], T)
    with pytest.raises(InputError, match=r"mesh 0 \(mesh0\) vertices: 1 of 3 rows have NaN"):
        write_animated_glb(tmp_path / "x.glb", [([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]])], P[:, :3], T)
    with pytest.raises(InputError, match="directory"):
        write_animated_glb(tmp_path / "missing" / "x.glb", meshes, P, T)


# --- posed copies of a glTF asset ----------------------------------------------------------

import gltf_asset  # noqa: E402  (tests/ is on sys.path under pytest's rootdir conftest-less mode)
from scipy.spatial.transform import Rotation  # noqa: E402

from nrpose.errors import FileFormatError  # noqa: E402
from nrpose.io import load_character  # noqa: E402
from nrpose.io.gltf_write import DIRECTION_BOUND, QUANTIZATION_BOUND  # noqa: E402


def decoded(gltf, blob, index):
    """Any VEC2/3/4 or SCALAR accessor as float64 (count, width): strides, normalised ints."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = np.dtype({5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}[acc.componentType])
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc.type]
    stride = view.byteStride or dtype.itemsize * width
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    rows = np.array([np.frombuffer(blob, dtype, width, start + i * stride) for i in range(acc.count)], np.float64)
    if acc.normalized:
        rows = np.maximum(rows / np.iinfo(dtype).max, -1.0)
    return rows


def knee_matrix(t):
    """The asset's knee rotation at time t (LINEAR slerp of 0 -> 90 degrees about z over 1 s)."""
    return Rotation.from_rotvec([0, 0, np.pi / 2 * t]).as_matrix()


def lbs_frames(character, times):
    """Posed vertices (F, V, 3) of the character's meshes by linear blend skinning (numpy)."""
    clip = character.clip("bend")
    K = character.skin_matrices(character.skeleton.forward_kinematics(clip.sample(times)))
    out = []
    for m in character.meshes:
        M = np.einsum("nk,fnkab->fnab", m.weights, K[:, m.joints])
        out.append(np.einsum("fnab,nb->fna", M, np.c_[m.vertices, np.ones(len(m.vertices))])[..., :3])
    return np.concatenate(out, axis=1)


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
@pytest.mark.parametrize("quantize", [False, True])
def test_posed_copy_keeps_the_asset(tmp_path, suffix, quantize):
    source = gltf_asset.build(tmp_path / f"asset{suffix}")
    character = load_character(source)
    assert [m.name for m in character.static_meshes] == ["pedestal"]
    T = np.linspace(0.0, 1.0, 5)
    P = lbs_frames(character, T)
    out = tmp_path / "posed.glb"
    report = write_animated_glb(out, character, P, T, source=source, quantize=quantize, animation_name="bend")
    src = pygltflib.GLTF2().load(str(source))
    gltf = pygltflib.GLTF2().load_binary(str(out))
    blob = gltf.binary_blob()
    # materials, textures, samplers, extras and unknown extensions as in the source; the image embedded
    for field in ("materials", "textures", "samplers", "skins"):
        assert [x.to_dict() for x in getattr(gltf, field)] == [x.to_dict() for x in getattr(src, field)]
    image = gltf.images[0]
    assert image.uri is None and image.mimeType == "image/png"
    view = gltf.bufferViews[image.bufferView]
    assert blob[view.byteOffset:view.byteOffset + view.byteLength] == gltf_asset.png_bytes()
    assert gltf.extras == {"scene_note": "kept"} and gltf.asset.copyright == "CC0"
    assert set(gltf.extensionsUsed) >= {"KHR_materials_emissive_strength", "EXT_tests_unknown"}
    assert (("KHR_mesh_quantization" in (gltf.extensionsRequired or [])) == quantize
            == (report.quantized_frames == len(T)))
    # the static pedestal: same node, same mesh, same data
    pedestal = gltf.nodes[4]
    assert pedestal.name == "pedestal" and pedestal.mesh == 1 and pedestal.translation == [2, 0, 0]
    assert pedestal.extensions == {"EXT_tests_unknown": {"note": "kept"}}
    src_blob = (tmp_path / "asset.bin").read_bytes() if suffix == ".gltf" else src.binary_blob()
    pid = src.meshes[1].primitives[0].attributes.POSITION
    assert np.array_equal(decoded(gltf, blob, pid), decoded(src, src_blob, pid))
    # the posed node: at the root, unskinned, named as before; the source node stays, emptied
    posed = [i for i, n in enumerate(gltf.nodes) if n.mesh is not None and i != 4]
    assert len(posed) == 1 and posed[0] in gltf.scenes[0].nodes
    node = gltf.nodes[posed[0]]
    assert node.name == "leg" and node.skin is None and gltf.nodes[3].mesh is None and gltf.nodes[3].skin is None
    assert gltf.nodes[3].name == "leg.bind" and gltf.nodes[3].extras == {"kind": "character"}
    scale = (node.scale or [1.0])[0]
    mesh = gltf.meshes[node.mesh]
    assert mesh.name == "leg" and mesh.extras["author"] == "tests" and len(mesh.extras["targetNames"]) == len(T)
    diagonal = np.linalg.norm(np.ptp(P[0], axis=0))
    bound = (QUANTIZATION_BOUND if quantize else 1e-6) * diagonal
    start = 0
    for k, (prim, sprim) in enumerate(zip(mesh.primitives, src.meshes[0].primitives)):
        assert prim.material == sprim.material == k and prim.indices == sprim.indices
        assert prim.extras == sprim.extras
        kept = {"TEXCOORD_0", "TEXCOORD_1", "COLOR_0", "_ID"}
        attrs = {a: v for a, v in vars(prim.attributes).items() if v is not None}
        assert set(attrs) == kept | {"POSITION", "NORMAL", "TANGENT"}
        assert all(attrs[a] == getattr(sprim.attributes, a) for a in kept)
        n = gltf.accessors[attrs["POSITION"]].count
        base = decoded(gltf, blob, attrs["POSITION"])
        src_normals = decoded(src, src_blob, sprim.attributes.NORMAL)
        src_tangents = decoded(src, src_blob, sprim.attributes.TANGENT)
        y = decoded(src, src_blob, sprim.attributes.POSITION)[:, 1]
        assert np.allclose(decoded(gltf, blob, attrs["NORMAL"]), src_normals, atol=1e-6)   # rest = source
        assert np.allclose(decoded(gltf, blob, attrs["TANGENT"]), src_tangents, atol=1e-6)
        assert len(prim.targets) == len(T)
        for f, target in enumerate(prim.targets):
            got = scale * (base + decoded(gltf, blob, target["POSITION"]))
            assert np.abs(got - P[f, start:start + n]).max() <= bound
            acc = gltf.accessors[target["POSITION"]]
            assert acc.min is not None and acc.max is not None
            # where every face around a vertex is rigid (the end rings), the authored (split)
            # normals and tangents turn with their bone
            R = np.where((y >= 1.5)[:, None, None], knee_matrix(T[f]), np.eye(3))
            for attr, vectors in (("NORMAL", src_normals), ("TANGENT", src_tangents[:, :3])):
                base_v = decoded(gltf, blob, attrs[attr])[:, :3]
                v = base_v + decoded(gltf, blob, target[attr])
                v /= np.linalg.norm(v, axis=1, keepdims=True)
                want = np.einsum("nab,nb->na", R, vectors)
                rigid = (y == 2.0) | (y == 0.0)
                angle = np.degrees(np.arccos(np.clip(np.einsum("na,na->n", v, want)[rigid], -1, 1)))
                assert angle.max() <= (DIRECTION_BOUND if quantize else 1e-3), (attr, f)
        start += n
    assert report.max_error <= bound / diagonal
    # float: 12 bytes each for POSITION, NORMAL, TANGENT; quantized: int16 positions (8 with
    # glTF's 4-byte alignment), int8 (4) or, for the 90-degree frame, int16 (8) directions
    assert report.bytes_per_frame_vertex == 36 if not quantize else 16 <= report.bytes_per_frame_vertex <= 24
    animation, = gltf.animations
    assert animation.name == "bend" and [c.target.node for c in animation.channels] == posed
    weights = decoded(gltf, blob, animation.samplers[0].output).reshape(len(T), len(T))
    assert np.array_equal(weights, np.eye(len(T)))


def test_split_normals_stay_split_and_smooth_normals_without_source(tmp_path):
    # a bent box from (vertices, faces) only: normals are the posed surface's smooth ones,
    # welded across the duplicated corners
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    V = np.concatenate([corners[q] for q in quads])            # 24 vertices: every side its own
    F = np.concatenate([[[4 * s, 4 * s + 1, 4 * s + 2], [4 * s, 4 * s + 2, 4 * s + 3]] for s in range(6)])
    R = Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix()
    P = np.stack([V, V @ R.T + [0.2, 0, 0]])
    out = tmp_path / "box.glb"
    write_animated_glb(out, [("box", V, F)], P, [0.0, 1.0])
    gltf = pygltflib.GLTF2().load_binary(str(out))
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    base = decoded(gltf, blob, prim.attributes.NORMAL)
    outward = np.zeros_like(V)   # area-weighted face normals summed over each corner's 3 copies
    for face in F:
        n = np.cross(V[face[1]] - V[face[0]], V[face[2]] - V[face[0]])
        for i in face:
            outward[(V == V[i]).all(axis=1)] += n
    outward /= np.linalg.norm(outward, axis=1, keepdims=True)
    assert np.allclose(base, outward, atol=1e-6)
    assert (np.einsum("na,na->n", base, V - V.mean(axis=0)) > 0).all()    # and point outwards
    posed = base + decoded(gltf, blob, prim.targets[1]["NORMAL"])
    assert np.allclose(posed, outward @ R.T, atol=1e-6)


def test_required_extension_is_refused_and_nothing_written(tmp_path):
    source = gltf_asset.build(tmp_path / "asset.glb", required=["EXT_tests_required"])
    character = load_character(source)
    T = np.array([0.0, 1.0])
    P = lbs_frames(character, T)
    with pytest.raises(FileFormatError, match="EXT_tests_required"):
        write_animated_glb(tmp_path / "out.glb", character, P, T, source=source)
    assert not (tmp_path / "out.glb").exists()
    carried = gltf_asset.build(tmp_path / "carried.glb", required=["KHR_texture_transform"])
    write_animated_glb(tmp_path / "ok.glb", load_character(carried), P, T, source=carried)
    assert "KHR_texture_transform" in pygltflib.GLTF2().load_binary(str(tmp_path / "ok.glb")).extensionsRequired


def test_quantized_clip_travelling_far_stays_float(tmp_path):
    # a clip moving 10 bounding-box diagonals: int16 steps would exceed the bound
    meshes = two_meshes()
    rest = np.concatenate([m.vertices for m in meshes])
    diagonal = np.linalg.norm(np.ptp(rest, axis=0))
    P = np.stack([rest, rest + [10 * diagonal, 0, 0]])
    report = write_animated_glb(tmp_path / "far.glb", meshes, P, [0.0, 1.0], quantize=True)
    assert report.quantized_frames == 0 and report.max_error < 1e-6
    near = write_animated_glb(tmp_path / "near.glb", meshes, P * [0.01, 1, 1], [0.0, 1.0], quantize=True)
    assert near.quantized_frames == 2 and near.max_error <= QUANTIZATION_BOUND


def test_nothing_is_written_that_nrpose_cannot_read_back():
    """A document with more animations (or accessors...) than the reader takes is refused by name."""
    import pygltflib
    from nrpose.errors import InputError
    from nrpose.io.gltf_schema import MAX_ITEMS
    from nrpose.io.gltf_write import check_readable_size
    gltf = pygltflib.GLTF2(animations=[pygltflib.Animation() for _ in range(MAX_ITEMS)])
    check_readable_size(gltf, "o.glb")
    gltf.animations.append(pygltflib.Animation())
    with pytest.raises(InputError, match="o.glb: would hold 10,001 animations"):
        check_readable_size(gltf, "o.glb")


@pytest.mark.parametrize("times, message", [
    ([0.0, 1e-320], "not strictly increasing as the file's float32"),    # distinct in float64 only
    ([0.0, 1.0, 1.0 + 1e-9], "not strictly increasing as the file's float32"),
    ([0.0, 1e39], "within float32's range"),
    ([-1.0, 0.0], "non-negative"),
    ([0.0, float("nan")], "finite"),
])
def test_key_times_must_stay_strictly_increasing_as_float32(times, message):
    with pytest.raises(InputError, match=message):
        float32_times(times, "clip 'x'")
    assert float32_times([0.0, 1 / 30, 2 / 30], "clip 'x'").dtype == np.float32


def test_a_bake_refuses_times_float32_cannot_tell_apart(tmp_path):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with pytest.raises(InputError, match="not strictly increasing as the file's float32"):
        write_animated_glb(tmp_path / "o.glb", [(V, np.array([[0, 1, 2]]))], np.stack([V, V]), [0.0, 1e-320])
    assert not (tmp_path / "o.glb").exists()
