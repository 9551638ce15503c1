"""Characters posed with nrmls, lbs and dqs: glTF skinning formula, references, rigid parts."""
from __future__ import annotations

import gc
import weakref
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from nrpose import device
from nrpose.io import load_character
from nrpose.model.character import Character, Mesh
from nrpose.pose.poser import CharacterPoser
from nrpose.model.skeleton import LocalPose, Skeleton

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared assets not found at {DATA}")

COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def read_accessor(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """Plain accessor read (tightly packed or strided views; no sparse) for the test's own formula."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype, width = np.dtype(COMPONENT[acc.componentType]), WIDTH[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    stride = view.byteStride or dtype.itemsize * width
    rows = [np.frombuffer(blob, dtype, width, start + i * stride) for i in range(acc.count)]
    out = np.array(rows, dtype=np.float64)
    if acc.normalized and dtype.kind == "u":
        out /= np.iinfo(dtype).max
    return out


def gltf_skinning(path: Path, joint_globals_by_name: dict[str, np.ndarray]) -> np.ndarray:
    """The glTF 2.0 skinning formula, v' = Σ_i w_i (G_{j_i} · IBM_{j_i}) v, for every skinned primitive."""
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    out = []
    for node in gltf.nodes:
        if node.mesh is None or node.skin is None:
            continue
        skin = gltf.skins[node.skin]
        ibm = read_accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
        joint_mats = np.array([joint_globals_by_name[gltf.nodes[j].name] for j in skin.joints]) @ ibm
        for prim in gltf.meshes[node.mesh].primitives:
            V = read_accessor(gltf, blob, prim.attributes.POSITION)
            J = read_accessor(gltf, blob, prim.attributes.JOINTS_0).astype(int)
            W = read_accessor(gltf, blob, prim.attributes.WEIGHTS_0)
            M = np.einsum("nk,nkab->nab", W / W.sum(axis=1, keepdims=True), joint_mats[J])
            out.append(np.einsum("nab,nb->na", M, np.c_[V, np.ones(len(V))])[:, :3])
    return np.concatenate(out)


def quat_matrix(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def file_node_globals(path: Path, animation: int, key: int) -> tuple[float, dict[str, np.ndarray]]:
    """Node global matrices straight from the file at the key-th key time of an animation
    (all its channels must share their key times): (time, {node name: 4x4})."""
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    anim = gltf.animations[animation]
    inputs = {anim.samplers[c.sampler].input for c in anim.channels}
    assert len(inputs) == 1, "the test needs channels sharing their key times"
    time = float(read_accessor(gltf, blob, inputs.pop())[key, 0])
    trs = {}
    for i, node in enumerate(gltf.nodes):
        trs[i] = {"translation": node.translation or [0, 0, 0], "rotation": node.rotation or [0, 0, 0, 1],
                  "scale": node.scale or [1, 1, 1]}
    for c in anim.channels:
        if c.target.path in ("translation", "rotation", "scale"):
            trs[c.target.node][c.target.path] = read_accessor(gltf, blob, anim.samplers[c.sampler].output)[key]
    local = {}
    for i, node in enumerate(gltf.nodes):
        if node.matrix:
            local[i] = np.array(node.matrix, dtype=np.float64).reshape(4, 4).T
        else:
            M = np.eye(4)
            M[:3, :3] = quat_matrix(trs[i]["rotation"]) * np.asarray(trs[i]["scale"], dtype=np.float64)
            M[:3, 3] = trs[i]["translation"]
            local[i] = M
    parent = {c: i for i, node in enumerate(gltf.nodes) for c in (node.children or [])}

    def world(i):
        return local[i] if i not in parent else world(parent[i]) @ local[i]

    return time, {node.name: world(i) for i, node in enumerate(gltf.nodes)}


@needs_data
@pytest.mark.parametrize("name", ["Fox", "Mannequin"])
def test_lbs_authored_reproduces_gltf_formula(name):
    """LBS with the file's weights equals the glTF formula computed here from the file alone
    (node TRS, animation keys, hierarchy, inverse bind matrices) at several key times."""
    path = DATA / "gltf" / f"{name}.glb"
    ch = load_character(path)
    gltf = pygltflib.GLTF2().load(str(path))
    animation = len(gltf.animations) - 1
    clip = next(c for c in ch.clips if c.name == gltf.animations[animation].name)
    n_keys = gltf.accessors[gltf.animations[animation].samplers[0].input].count
    keys = sorted({0, n_keys // 3, n_keys - 1})
    poser = CharacterPoser(ch, method="lbs", weights="authored")
    for key in keys:
        time, globals_ = file_node_globals(path, animation, key)
        frames = poser.pose(clip.sample(time))
        expect = gltf_skinning(path, globals_)
        size = np.ptp(expect, axis=0).max()
        assert np.abs(frames.positions[0] - expect).max() <= 1e-5 * size


@needs_data
@pytest.mark.parametrize("method", ["nrmls", "lbs", "dqs", "cor"])
@pytest.mark.parametrize("weights", ["authored", "euclidean"])
def test_methods_match_their_references_and_rest_is_identity(method, weights):
    ch = load_character(DATA / "gltf" / "Fox.glb")
    clip = ch.clip("Run")
    local = clip.sample(np.array([0.1, 0.5]))
    dev = CharacterPoser(ch, method=method, weights=weights)
    ref = CharacterPoser(ch, method=method, weights=weights, backend="numpy")
    rest = np.concatenate([m.vertices for m in ch.meshes])
    size = np.ptp(rest, axis=0).max()
    assert np.abs(dev.pose(ch.skeleton.rest_pose).positions[0] - rest).max() <= 1e-5 * size
    d = dev._deformer
    dev.pose(local)                          # the deformer's arrays grown to the clip's frames
    d._out.host[:] = np.nan                  # its own output
    out, expect = dev.pose(local).positions, ref.pose(local).positions
    if device.fine_grain_svm():          # written by the kernel itself: nothing copied
        found = device.frames_in(out, 3 * (d._npad if method == "nrmls" else 8 * d.n_groups))
        assert found is not None and found[1] == 0 and np.isnan(d._out.host).all()
        # and released once posed: the poser does not keep the caller's frames
        assert (d._handed is d._handoff.array) if method == "nrmls" else (d._out_bound[0] is d._out)
        memory = weakref.ref(found[0])
        del found
    assert np.isfinite(out).all()
    assert np.abs(out - expect).max() <= 1e-4 * size
    assert np.abs(out[0] - rest).max() > 1e-2 * size     # the clip does move the fox
    if device.fine_grain_svm():
        del out
        gc.collect()
        assert memory() is None


def two_bone_character() -> Character:
    """A chain root → elbow → tip along +x, a skinned bar around it and a rigid box on the elbow."""
    skel = Skeleton(("root", "elbow", "tip"), np.array([-1, 0, 1]),
                    np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]]),
                    np.tile([0.0, 0, 0, 1], (3, 1)), np.ones((3, 3)))
    x = np.linspace(0.05, 1.95, 20)
    bar = np.concatenate([np.c_[x, np.full(20, dy), np.full(20, dz)] for dy in (-0.1, 0.1) for dz in (-0.1, 0.1)])
    w_elbow = np.clip((bar[:, 0] - 0.8) / 0.4, 0, 1)
    joints = np.tile([0, 1], (len(bar), 1))
    weights = np.c_[1 - w_elbow, w_elbow]
    box = np.array([[1.5, 0.3, 0.0], [1.6, 0.3, 0.0], [1.5, 0.4, 0.0], [1.5, 0.3, 0.1]])
    meshes = (Mesh("bar", bar, np.zeros((0, 3), np.int64), joints, weights),
              Mesh("box", box, np.array([[0, 1, 2], [0, 1, 3]]), np.ones((4, 1), np.int64), np.ones((4, 1)), 1))
    return Character(skel, meshes)


@pytest.mark.parametrize("method", ["nrmls", "lbs", "dqs", "cor"])
def test_mesh_parented_to_a_joint_moves_rigidly(method):
    ch = two_bone_character()
    rot = np.array([0.0, 0.0, np.sin(np.pi / 6), np.cos(np.pi / 6)])     # 60° about z at the elbow
    pose = LocalPose(ch.skeleton.translation, np.array([[0, 0, 0, 1.0], rot, [0, 0, 0, 1.0]]),
                     ch.skeleton.scale)
    frames = CharacterPoser(ch, method=method).pose(pose)
    box_rest = ch.meshes[1].vertices
    box = frames.positions[0, frames.mesh_offsets[1]:]
    c, s = np.cos(np.pi / 3), np.sin(np.pi / 3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    expect = (box_rest - [1.0, 0, 0]) @ R.T + [1.0, 0, 0]
    assert np.abs(box - expect).max() <= 1e-5
    assert list(frames.mesh_names) == ["bar", "box"] and list(frames.mesh_offsets) == [0, 80]


@pytest.mark.parametrize("method", ["nrmls", "lbs", "dqs", "cor"])
def test_character_of_rigid_meshes_only(method):
    ch = two_bone_character()
    rigid_only = Character(ch.skeleton, (ch.meshes[1],))
    frames = CharacterPoser(rigid_only, method=method).pose(ch.skeleton.rest_pose)
    assert np.abs(frames.positions[0] - ch.meshes[1].vertices).max() <= 1e-6


@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_a_part_with_one_set_of_authored_weights_moves_rigidly(backend):
    """nrmls with authored weights: vertices sharing one weight row (a joint cap split 0.5/0.5)
    move rigidly (bind.bone_weights' group parameters), as under DQS and CoR; LBS bends them."""
    ch = two_bone_character()
    bar = ch.meshes[0]
    cap = np.abs(bar.vertices[:, 0] - 1.0) < 0.3
    w = bar.weights.copy()
    w[cap] = 0.5
    ch = Character(ch.skeleton, (Mesh("bar", bar.vertices, bar.faces, bar.joints, w),) + ch.meshes[1:])
    rot = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])     # 90° about z at the elbow
    pose = LocalPose(ch.skeleton.translation, np.array([[0, 0, 0, 1.0], rot, [0, 0, 0, 1.0]]), ch.skeleton.scale)
    X = bar.vertices[cap]
    d0 = np.linalg.norm(X[:, None] - X[None], axis=2)

    def cap_strain(method):
        if backend == "numpy" and method != "nrmls":
            pytest.skip("skinning's numpy path is covered by the reference tests")
        P = CharacterPoser(ch, method=method, backend=backend).pose(pose).positions[0, :len(bar.vertices)][cap]
        return np.abs(np.linalg.norm(P[:, None] - P[None], axis=2) - d0).max()

    assert cap_strain("nrmls") < 1e-5                  # float32 frames, either backend
    if backend == "opencl":
        assert cap_strain("dqs") < 1e-5 and cap_strain("cor") < 1e-5
        assert cap_strain("lbs") > 1e-2


def test_blend_option_reaches_nrmls_and_is_refused_elsewhere():
    from nrpose.errors import InputError

    ch = two_bone_character()
    rot = np.array([0.0, 0.0, np.sin(np.pi / 6), np.cos(np.pi / 6)])
    pose = LocalPose(ch.skeleton.translation, np.array([[0, 0, 0, 1.0], rot, [0, 0, 0, 1.0]]), ch.skeleton.scale)
    # the default (quaternion) and the relative blend, each on the device as in the reference
    for blend in ("quaternion", "relative"):
        q = CharacterPoser(ch, blend=blend).pose(pose).positions
        q_ref = CharacterPoser(ch, blend=blend, backend="numpy").pose(pose).positions
        assert np.abs(q - q_ref).max() <= 1e-5
    with pytest.raises(InputError, match="nrmls method only"):
        CharacterPoser(ch, method="lbs", blend="relative")
    with pytest.raises(InputError, match="blend must be one of"):
        CharacterPoser(ch, blend="slerp")


def test_skeleton_only_character_is_an_error():
    from nrpose.errors import InputError

    ch = two_bone_character()
    with pytest.raises(InputError, match="no mesh"):
        CharacterPoser(Character(ch.skeleton))
    bare = Character(ch.skeleton, (Mesh("m", ch.meshes[0].vertices, np.zeros((0, 3), np.int64)),))
    with pytest.raises(InputError, match="no skin weights"):
        CharacterPoser(bare, weights="authored")
    assert CharacterPoser(bare, weights="euclidean").pose(ch.skeleton.rest_pose).positions.shape == (1, 80, 3)


def two_skin_glb(path: Path) -> None:
    """Two meshes on one 2-joint chain, skinned by two skins whose inverse bind matrices
    differ (skin 1 binds its mesh 5 units lower: IBM_j = G_j⁻¹ · T(0, 5, 0))."""
    def tr(x, y, z):
        m = np.eye(4)
        m[:3, 3] = [x, y, z]
        return m

    x = np.linspace(0.1, 1.9, 10)
    world = np.concatenate([np.c_[x, np.full(10, dy), np.zeros(10)] for dy in (-0.1, 0.1)]).astype(np.float32)
    wa = np.clip((world[:, 0] - 0.8) / 0.4, 0, 1)
    joints = np.tile(np.array([0, 1, 0, 0], np.uint16), (len(world), 1))
    weights = np.c_[1 - wa, wa, np.zeros((len(world), 2))].astype(np.float32)
    rest_g = [np.eye(4), tr(1, 0, 0)]
    ibm0 = np.array([np.linalg.inv(g) for g in rest_g])
    ibm1 = np.array([np.linalg.inv(g) @ tr(0, 5, 0) for g in rest_g])
    pos_b = (world - np.float32([0, 5, 0])).astype(np.float32)          # T(0,5,0) · pos_b = world
    tris = np.array([[i, i + 1, 10 + i] for i in range(9)] + [[i + 1, 11 + i, 10 + i] for i in range(9)],
                    np.uint16).ravel()
    chunks = [world, pos_b, joints, weights, ibm0.transpose(0, 2, 1).astype(np.float32),
              ibm1.transpose(0, 2, 1).astype(np.float32), tris]
    blob, views = b"", []
    for c in chunks:
        views.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=c.nbytes))
        blob += c.tobytes()
    acc = [pygltflib.Accessor(bufferView=0, componentType=5126, count=len(world), type="VEC3",
                              min=world.min(0).tolist(), max=world.max(0).tolist()),
           pygltflib.Accessor(bufferView=1, componentType=5126, count=len(world), type="VEC3",
                              min=pos_b.min(0).tolist(), max=pos_b.max(0).tolist()),
           pygltflib.Accessor(bufferView=2, componentType=5123, count=len(world), type="VEC4"),
           pygltflib.Accessor(bufferView=3, componentType=5126, count=len(world), type="VEC4"),
           pygltflib.Accessor(bufferView=4, componentType=5126, count=2, type="MAT4"),
           pygltflib.Accessor(bufferView=5, componentType=5126, count=2, type="MAT4"),
           pygltflib.Accessor(bufferView=6, componentType=5123, count=len(tris), type="SCALAR")]
    prim = lambda p: pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=p, JOINTS_0=2, WEIGHTS_0=3),  # noqa: E731
                                         indices=6, mode=4)
    gltf = pygltflib.GLTF2(
        scene=0, scenes=[pygltflib.Scene(nodes=[0, 2, 3])],
        nodes=[pygltflib.Node(name="root", children=[1]), pygltflib.Node(name="elbow", translation=[1, 0, 0]),
               pygltflib.Node(name="A", mesh=0, skin=0), pygltflib.Node(name="B", mesh=1, skin=1)],
        meshes=[pygltflib.Mesh(name="A", primitives=[prim(0)]), pygltflib.Mesh(name="B", primitives=[prim(1)])],
        skins=[pygltflib.Skin(joints=[0, 1], inverseBindMatrices=4), pygltflib.Skin(joints=[0, 1], inverseBindMatrices=5)],
        accessors=acc, bufferViews=views, buffers=[pygltflib.Buffer(byteLength=len(blob))])
    gltf.set_binary_blob(blob)
    gltf.save_binary(str(path))


@pytest.mark.parametrize("method", ["lbs", "dqs", "nrmls", "cor"])
def test_skins_with_different_inverse_binds(tmp_path, method):
    path = tmp_path / "two_skins.glb"
    two_skin_glb(path)
    ch = load_character(path)
    assert np.abs(ch.meshes[0].vertices - ch.meshes[1].vertices).max() <= 1e-6   # same world bind shape
    rot = np.array([0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)])             # 45° at the elbow
    pose = LocalPose(ch.skeleton.translation, np.array([[0, 0, 0, 1.0], rot]), ch.skeleton.scale)
    out = CharacterPoser(ch, method=method).pose(pose).positions[0]
    G = ch.skeleton.forward_kinematics(pose)
    expect = gltf_skinning(path, dict(zip(ch.skeleton.names, G)))
    if method == "lbs":
        assert np.abs(out - expect).max() <= 1e-5
    # every method moves both meshes alike: they share the world bind shape and the skeleton
    assert np.abs(out[:20] - out[20:]).max() <= 1e-5
    assert np.abs(out[:20] - expect[:20]).max() <= 0.1                           # and near LBS
