"""Character loaders: glTF, BVH, TGF/DMAT, meshes, pose files."""
import base64
import json
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

from nrpose.io import load_character
from nrpose.io.poses import load_pose
from nrpose.model.character import Character
from nrpose.errors import FileFormatError, InputError
from nrpose.io.bvh_read import read_bvh
from nrpose.io.gltf_read import load_gltf
from nrpose.io.tgf import read_dmat_pose, read_mesh, read_tgf

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")


@pytest.fixture(scope="module")
def characters():
    """Real glTF characters, loaded once."""
    if not DATA.is_dir():
        pytest.skip(f"shared test data not found at {DATA}")
    return {name: load_gltf(DATA / "gltf" / f"{name}.glb") for name in ("Fox", "Mannequin", "Ely")}


# --- an independent reading of glTF for the bind-shape test ------------------------------

def raw_accessor(gltf, blob, index):
    """Accessor as float64 (count, width), honouring byteStride and normalisation."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = np.dtype({5121: "<u1", 5123: "<u2", 5125: "<u4", 5126: "<f4"}[acc.componentType])
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    stride = view.byteStride or dtype.itemsize * width
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    rows = [np.frombuffer(blob, dtype, width, start + i * stride) for i in range(acc.count)]
    out = np.array(rows, dtype=np.float64)
    return out / np.iinfo(dtype).max if acc.normalized else out


def node_globals(gltf):
    """Default global matrix of every node, (N, 4, 4)."""
    n = len(gltf.nodes)
    local = np.empty((n, 4, 4))
    for i, node in enumerate(gltf.nodes):
        if node.matrix:
            local[i] = np.array(node.matrix).reshape(4, 4).T
            continue
        M = np.eye(4)
        M[:3, :3] = Rotation.from_quat(node.rotation or [0, 0, 0, 1]).as_matrix() * (node.scale or [1, 1, 1])
        M[:3, 3] = node.translation or [0, 0, 0]
        local[i] = M
    parent = {c: i for i, node in enumerate(gltf.nodes) for c in node.children or []}
    G = {}

    def glob(i):
        if i not in G:
            G[i] = (glob(parent[i]) if i in parent else np.eye(4)) @ local[i]
        return G[i]

    return np.array([glob(i) for i in range(n)])


@needs_data
@pytest.mark.parametrize("name", ["Fox", "Mannequin", "Ely"])
def test_rest_pose_reproduces_bind_shape(characters, name):
    gltf = pygltflib.GLTF2().load(str(DATA / "gltf" / f"{name}.glb"))
    blob = gltf.binary_blob()
    G = node_globals(gltf)
    mesh_node = next(i for i, n in enumerate(gltf.nodes) if n.skin is not None)
    skin = gltf.skins[gltf.nodes[mesh_node].skin]
    prim = gltf.meshes[gltf.nodes[mesh_node].mesh].primitives[0]
    v = raw_accessor(gltf, blob, prim.attributes.POSITION)
    joints = raw_accessor(gltf, blob, prim.attributes.JOINTS_0).astype(int)
    weights = raw_accessor(gltf, blob, prim.attributes.WEIGHTS_0)
    weights /= weights.sum(axis=1, keepdims=True)
    ibm = raw_accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    joint_mats = np.linalg.inv(G[mesh_node]) @ G[skin.joints] @ ibm
    vh = np.c_[v, np.ones(len(v))]
    local = np.einsum("nk,nkab,nb->na", weights, joint_mats[joints], vh)
    world = (local @ G[mesh_node].T)[:, :3]
    mesh = characters[name].meshes[0]
    scale = np.ptp(world, axis=0).max()
    np.testing.assert_allclose(mesh.vertices, world, atol=1e-9 * scale)
    # these files bind at their default pose: every G_j @ IBM_j is the same matrix (identity for
    # the Mixamo exports, whose positions are already in world space under a scaled Armature)
    bind = G[skin.joints] @ ibm
    np.testing.assert_allclose(bind, np.broadcast_to(bind[0], bind.shape), atol=1e-4)
    # skinning with the character's own matrices at rest gives the rest vertices back
    char = characters[name]
    M = char.skin_matrices(char.skeleton.rest_globals())
    posed = np.einsum("nk,nkab,nb->na", mesh.weights, M[mesh.joints], np.c_[mesh.vertices, np.ones(len(v))])
    np.testing.assert_allclose(posed[:, :3], mesh.vertices, atol=1e-9 * scale)


@needs_data
def test_real_character_counts(characters):
    fox, man, ely = characters["Fox"], characters["Mannequin"], characters["Ely"]
    assert [c.name for c in fox.clips] == ["Survey", "Walk", "Run"]
    assert fox.skeleton.num_joints == 24 and sum(len(m.vertices) for m in fox.meshes) == 1728
    assert man.skeleton.num_joints == 65 and sum(len(m.vertices) for m in man.meshes) == 15882
    assert ely.skeleton.num_joints == 67 and sum(len(m.vertices) for m in ely.meshes) == 5040
    for char in (fox, man, ely):
        mesh = char.meshes[0]
        assert mesh.faces.dtype == np.int64 and mesh.faces.max() < len(mesh.vertices)
        np.testing.assert_allclose(mesh.weights.sum(axis=1), 1.0, atol=1e-12)
        assert mesh.joints.max() < char.skeleton.num_joints
        bones = char.skeleton.bones()
        assert set(np.unique(bones.joints)) == set(range(char.skeleton.num_joints))
    assert "mixamorig:Hips" in man.skeleton.names
    assert not np.allclose(man.skeleton.pre[man.skeleton.index("mixamorig:Hips")], np.eye(4))  # Armature
    walk = fox.clip("Walk")
    pose = walk.sample(np.linspace(0, walk.duration, 4))
    assert pose.rotation.shape == (4, 24, 4)
    np.testing.assert_allclose(np.linalg.norm(pose.rotation, axis=-1), 1.0, atol=1e-12)
    with pytest.raises(InputError, match="Survey"):
        fox.clip("walk")


# --- a synthetic glTF --------------------------------------------------------------------

def hermite(t, t0, t1, v0, b0, a1, v1):
    """glTF CUBICSPLINE between two keys (spec appendix C)."""
    s, td = (t - t0) / (t1 - t0), t1 - t0
    return ((2 * s**3 - 3 * s**2 + 1) * v0 + td * (s**3 - 2 * s**2 + s) * b0
            + (-2 * s**3 + 3 * s**2) * v1 + td * (s**3 - s**2) * a1)


CUBIC_SCALE = np.array([[0, 0, 0], [1, 1, 1], [1, 0, 0],  # key 0: in, value, out
                        [0, 2, 0], [2, 1, 3], [0, 0, 0]], dtype=np.float32)  # key 1
CUBIC_ROT = np.array([[0, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0],
                      [0, 0, 1, 0], [0, 0, 0.7071068, 0.7071068], [0, 0, 0, 0]], dtype=np.float32)


def synthetic_gltf(skin=True):
    """Armature (non-joint) > root joint > mid joint (matrix) > prop (rigid mesh); skinned quad.

    Node 4 holds the skinned mesh with a transform that must be ignored.
    """
    blob = bytearray()
    views, accessors = [], []

    def view(data: bytes, stride=None):
        while len(blob) % 4:
            blob.append(0)
        views.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), byteStride=stride))
        blob.extend(data)
        return len(views) - 1

    def accessor(array, ctype, kind, normalized=False, stride=None):
        a = np.ascontiguousarray(array)
        if stride:  # pad each element to `stride` bytes
            rows = a.reshape(len(a), -1).view(np.uint8)
            padded = np.zeros((len(a), stride), np.uint8)
            padded[:, :rows.shape[1]] = rows
            data = padded.tobytes()
        else:
            data = a.tobytes()
        accessors.append(pygltflib.Accessor(bufferView=view(data, stride), componentType=ctype, count=len(a),
                                            type=kind, normalized=normalized or None))
        return len(accessors) - 1

    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    mid_matrix = np.eye(4)
    mid_matrix[:3, :3] = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()
    mid_matrix[:3, 3] = [1, 0, 0]
    rest = {0: np.eye(4), 1: np.eye(4)}
    rest[0][:3, 3] = [0, 0, 1]  # Armature translation; root joint at identity local
    rest[1] = rest[0] @ mid_matrix
    ibm = np.stack([np.linalg.inv(rest[0]), np.linalg.inv(rest[1])]).transpose(0, 2, 1).astype(np.float32)
    pos = accessor(quad, 5126, "VEC3", stride=16)
    idx = accessor(np.array([0, 1, 2, 0, 2, 3], np.uint16), 5123, "SCALAR")
    j0 = accessor(np.array([[0, 1, 0, 0]] * 4, np.uint8), 5121, "VEC4")
    w0 = accessor(np.array([[255, 0, 0, 0], [128, 0, 0, 0], [0, 0, 0, 0], [0, 255, 0, 0]], np.uint8),
                  5121, "VEC4", normalized=True)
    j1 = accessor(np.array([[1, 0, 0, 0]] * 4, np.uint16), 5123, "VEC4")
    w1 = accessor(np.array([[0, 0, 0, 0], [0.5, 0, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]], np.float32), 5126, "VEC4")
    prop = accessor(quad[:3], 5126, "VEC3")
    accessors[prop].sparse = pygltflib.Sparse(  # vertex 2 overridden to (2, 2, 0)
        count=1, indices=pygltflib.AccessorSparseIndices(bufferView=view(np.uint8([2]).tobytes()), componentType=5121),
        values=pygltflib.AccessorSparseValues(bufferView=view(np.float32([2, 2, 0]).tobytes())))
    ibm_acc = accessor(ibm.reshape(2, 16), 5126, "MAT4")
    t01 = accessor(np.array([0, 1], np.float32), 5126, "SCALAR")
    t3 = accessor(np.array([0, 0.5, 1], np.float32), 5126, "SCALAR")
    t02 = accessor(np.array([0, 2], np.float32), 5126, "SCALAR")
    rot_lin = accessor(np.array([[0, 0, 0, 1], [0, np.sin(np.pi / 4), 0, np.cos(np.pi / 4)]], np.float32),
                       5126, "VEC4")
    tr_step = accessor(np.array([[1, 0, 0], [2, 0, 0], [3, 0, 0]], np.float32), 5126, "VEC3")
    sc_cub = accessor(CUBIC_SCALE, 5126, "VEC3")
    rot_cub = accessor(CUBIC_ROT, 5126, "VEC4")
    tr_arm = accessor(np.array([[0, 0, 1], [0, 0, 7]], np.float32), 5126, "VEC3")

    attrs = pygltflib.Attributes(POSITION=pos, JOINTS_0=j0, WEIGHTS_0=w0)
    attrs.JOINTS_1, attrs.WEIGHTS_1 = j1, w1
    gltf = pygltflib.GLTF2(
        scene=0, scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(name="Armature", translation=[0, 0, 1], children=[1, 4]),
               pygltflib.Node(name="root", children=[2]),
               pygltflib.Node(name="mid", matrix=mid_matrix.T.reshape(-1).tolist(), children=[3]),
               pygltflib.Node(name="prop", translation=[0, 0.5, 0], mesh=1),
               pygltflib.Node(name="body", translation=[9, 9, 9], mesh=0, skin=0 if skin else None)],
        meshes=[pygltflib.Mesh(name="body", primitives=[pygltflib.Primitive(attributes=attrs, indices=idx)]),
                pygltflib.Mesh(name="prop", primitives=[pygltflib.Primitive(
                    attributes=pygltflib.Attributes(POSITION=prop))])],
        skins=[pygltflib.Skin(joints=[1, 2], inverseBindMatrices=ibm_acc)] if skin else [],
        animations=[pygltflib.Animation(name="clip", samplers=[
            pygltflib.AnimationSampler(input=t01, output=rot_lin, interpolation="LINEAR"),
            pygltflib.AnimationSampler(input=t3, output=tr_step, interpolation="STEP"),
            pygltflib.AnimationSampler(input=t02, output=sc_cub, interpolation="CUBICSPLINE"),
            pygltflib.AnimationSampler(input=t02, output=rot_cub, interpolation="CUBICSPLINE"),
            pygltflib.AnimationSampler(input=t01, output=tr_arm, interpolation="LINEAR")], channels=[
            pygltflib.AnimationChannel(sampler=0, target=pygltflib.AnimationChannelTarget(node=1, path="rotation")),
            pygltflib.AnimationChannel(sampler=1, target=pygltflib.AnimationChannelTarget(node=2, path="translation")),
            pygltflib.AnimationChannel(sampler=2, target=pygltflib.AnimationChannelTarget(node=2, path="scale")),
            pygltflib.AnimationChannel(sampler=3, target=pygltflib.AnimationChannelTarget(node=2, path="rotation")),
            pygltflib.AnimationChannel(sampler=4, target=pygltflib.AnimationChannelTarget(node=0, path="translation")),
        ])],
        accessors=accessors, bufferViews=views, buffers=[pygltflib.Buffer(byteLength=len(blob))])
    gltf.set_binary_blob(bytes(blob))
    return gltf


def save(gltf, path: Path) -> Path:
    if path.suffix == ".glb":
        gltf.save_binary(str(path))
    else:
        blob = gltf.binary_blob()
        gltf.buffers[0].uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        path.write_text(gltf.to_json())
    return path


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_synthetic_gltf_structure(tmp_path, suffix):
    char = load_character(save(synthetic_gltf(), tmp_path / f"c{suffix}"))
    skel = char.skeleton
    assert skel.names == ("root", "mid") and list(skel.parents) == [-1, 0]
    np.testing.assert_allclose(skel.pre[0][:3, 3], [0, 0, 1])  # the Armature node
    np.testing.assert_allclose(Rotation.from_quat(skel.rotation[1]).as_rotvec(), [0, 0, np.pi / 2], atol=1e-7)
    G = skel.rest_globals()
    np.testing.assert_allclose(G[1][:3, 3], [1, 0, 1], atol=1e-7)
    body, prop = sorted(char.meshes, key=lambda m: m.name)
    # bind = rest, so the bind shape is the raw positions (node "body"'s own transform ignored)
    np.testing.assert_allclose(body.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], atol=1e-6)
    assert body.faces.tolist() == [[0, 1, 2], [0, 2, 3]] and body.rigid_joint is None
    assert body.joints.shape == (4, 8)
    w = np.zeros((4, 2))
    np.add.at(w, (np.repeat(np.arange(4), 8), body.joints.ravel()), body.weights.ravel())
    np.testing.assert_allclose(w, [[1, 0], [128 / 255 / (128 / 255 + 0.5), 0.5 / (128 / 255 + 0.5)], [0, 1], [0, 1]])
    # rigid prop below joint "mid": world = G_mid @ T(0, 0.5, 0) @ v, v with its sparse override
    assert prop.rigid_joint == 1 and prop.joints.tolist() == [[1]] * 3
    expected = (np.c_[[[0, 0.5, 0], [1, 0.5, 0], [2, 2.5, 0]], np.ones(3)] @ G[1].T)[:, :3]
    np.testing.assert_allclose(prop.vertices, expected, atol=1e-6)


def test_synthetic_clip_sampling(tmp_path):
    char = load_character(save(synthetic_gltf(), tmp_path / "c.glb"))
    clip = char.clip("clip")
    assert clip.duration == 2.0 and len(clip.tracks) == 4  # the Armature channel is not a joint
    t = np.array([0, 0.25, 0.49, 0.5, 0.75, 1.0, 1.5, 2.0])
    pose = clip.sample(t)
    assert pose.translation.shape == (8, 2, 3)
    angles = Rotation.from_quat(pose.rotation[:, 0]).as_rotvec()[:, 1]  # LINEAR slerp, 0 -> 90 deg about y
    np.testing.assert_allclose(angles, np.radians(90) * np.clip(t, 0, 1), atol=1e-6)
    np.testing.assert_allclose(pose.translation[:, 1, 0], [1, 1, 1, 2, 2, 3, 3, 3])  # STEP
    k = CUBIC_SCALE.astype(float)
    np.testing.assert_allclose(pose.scale[:, 1], hermite(t[:, None], 0, 2, k[1], k[2], k[3], k[4]), atol=1e-6)
    q = hermite(t[:, None], 0, 2, *CUBIC_ROT.astype(float)[[1, 2, 3, 4]])
    np.testing.assert_allclose(pose.rotation[:, 1], q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(pose.scale[:, 0], 1.0)  # untouched channels keep rest values
    single = clip.sample(0.5)
    assert single.rotation.shape == (2, 4)
    with pytest.raises(InputError, match="outside"):
        clip.sample(2.5)
    with pytest.raises(InputError, match="outside"):
        clip.sample([-0.1, 0.0])


def test_gltf_bad_input(tmp_path):
    glb = save(synthetic_gltf(), tmp_path / "ok.glb")
    data = glb.read_bytes()
    (tmp_path / "cut.glb").write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match="truncated"):
        load_gltf(tmp_path / "cut.glb")
    (tmp_path / "tiny.glb").write_bytes(data[:5])
    with pytest.raises(FileFormatError, match="truncated"):
        load_gltf(tmp_path / "tiny.glb")
    (tmp_path / "magic.glb").write_bytes(b"GLTF" + data[4:])
    with pytest.raises(FileFormatError, match="magic"):
        load_gltf(tmp_path / "magic.glb")
    with pytest.raises(FileFormatError, match="no skin"):
        load_gltf(save(synthetic_gltf(skin=False), tmp_path / "noskin.glb"))
    broken = synthetic_gltf()
    broken.accessors[0].count = 1000
    with pytest.raises(FileFormatError, match="accessor 0 is out of range"):
        load_gltf(save(broken, tmp_path / "range.glb"))
    broken = synthetic_gltf()
    broken.skins[0].joints = [1, 2, 99]
    with pytest.raises(FileFormatError, match="skin 0"):
        load_gltf(save(broken, tmp_path / "joints.glb"))
    (tmp_path / "bad.gltf").write_text("{not json")
    with pytest.raises(FileFormatError, match="glTF JSON is not valid JSON"):
        load_gltf(tmp_path / "bad.gltf")
    for number in ("1e999", "NaN", "-Infinity"):      # Python's json reads them; JSON has no such numbers
        (tmp_path / "inf.gltf").write_text('{"asset": {"version": "2.0"}, "extras": {"x": %s}}' % number)
        with pytest.raises(FileFormatError, match=r"extras\.x = -?(inf|nan): JSON has no such number"):
            load_gltf(tmp_path / "inf.gltf")


# --- BVH ---------------------------------------------------------------------------------

BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 1 2 3
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 1 0
    CHANNELS 4 Yrotation Xrotation Zrotation Yposition
    End Site
    {
      OFFSET 0 2 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.5
10 20 30 30 40 50 0 0 0 7
0 0 0 0 0 0 90 0 0 1
"""


def test_bvh_channels_euler_order_and_end_site(tmp_path):
    path = tmp_path / "m.bvh"
    path.write_text(BVH)
    skel, clip = read_bvh(path)
    assert skel.names == ("Hips", "Spine") and list(skel.parents) == [-1, 0]
    np.testing.assert_allclose(skel.translation, [[1, 2, 3], [0, 1, 0]])
    np.testing.assert_allclose(skel.tips[1], [0, 2, 0])
    assert clip.duration == 0.5
    pose = clip.sample(0.0)
    Rz, Rx, Ry = (Rotation.from_euler(a, d, degrees=True).as_matrix() for a, d in (("z", 30), ("x", 40), ("y", 50)))
    np.testing.assert_allclose(Rotation.from_quat(pose.rotation[0]).as_matrix(), Rz @ Rx @ Ry, atol=1e-12)
    np.testing.assert_allclose(pose.translation, [[10, 20, 30], [0, 7, 0]])  # positions replace offsets
    half = clip.sample(0.25)
    np.testing.assert_allclose(Rotation.from_quat(half.rotation[1]).as_rotvec(), [0, np.radians(45), 0], atol=1e-12)
    bones = skel.bones()
    assert set(bones.names) == {"Hips->Spine", "Spine->Spine_tip"}


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace("90 0 0 1", "90 0 0"), r"m\.bvh:20: frame line has 9 values"),
    (lambda s: s.replace("90 0 0 1", "90 nan 0 1"), r"m\.bvh:20: .*NaN"),
    (lambda s: s.split("MOTION")[0], "no MOTION"),
    (lambda s: s.replace("Frames: 2", "Frames: 3"), "'Frames: 3' but 2 frame lines"),
    (lambda s: s.replace("Yrotation Xrotation Zrotation", "Yrotation Wrotation Zrotation"), r"m\.bvh:9: .*Wrotation"),
    (lambda s: s.replace("OFFSET 0 1 0", "OFFSET 0 1"), r"m\.bvh:8: OFFSET of Spine"),
])
def test_bvh_errors_name_lines(tmp_path, edit, message):
    path = tmp_path / "m.bvh"
    path.write_text(edit(BVH))
    with pytest.raises(FileFormatError, match=message):
        read_bvh(path)


@needs_data
def test_cmu_bvh():
    char = load_character(DATA / "bvh" / "131_03.bvh")
    assert char.skeleton.num_joints == 31 and char.meshes == ()
    clip = char.clips[0]
    assert clip.duration == pytest.approx(1101 * 0.0083333)
    G = char.skeleton.forward_kinematics(clip.sample(np.linspace(0, clip.duration, 5)))
    assert G.shape == (5, 31, 4, 4) and np.isfinite(G).all()
    bones = char.skeleton.bones()
    lengths = np.linalg.norm(bones.segments[:, 1] - bones.segments[:, 0], axis=1)
    assert (lengths > 0).all() and set(np.unique(bones.joints)) == set(range(31))


# --- TGF / DMAT / meshes -----------------------------------------------------------------

def libigl_forward_kinematics(C, BE, dQ):
    """igl::forward_kinematics: per-bone rotations vQ (B, 3, 3) and translations vT (B, 3)."""
    parent = {int(b): e for e, b in enumerate(BE[:, 1])}
    P = [parent.get(int(a), -1) for a in BE[:, 0]]
    vQ, vT = {}, {}

    def fk(b):
        if b in vQ:
            return
        r = C[BE[b, 0]]
        R = Rotation.from_quat(dQ[b]).as_matrix()
        if P[b] < 0:
            vQ[b], vT[b] = R, r - R @ r
        else:
            fk(P[b])
            vQ[b] = vQ[P[b]] @ R
            vT[b] = vT[P[b]] - vQ[b] @ r + vQ[P[b]] @ r
    for b in range(len(BE)):
        fk(b)
    return np.array([vQ[b] for b in range(len(BE))]), np.array([vT[b] for b in range(len(BE))])


def parse_tgf(path):
    lines = [line.split() for line in Path(path).read_text().splitlines() if line.strip()]
    sep = [i for i, f in enumerate(lines) if f[0] == "#"]
    C = np.array([[float(v) for v in f[1:4]] for f in lines[:sep[0]]])
    BE = np.array([[int(f[0]) - 1, int(f[1]) - 1] for f in lines[sep[0] + 1:sep[1]]])
    return C, BE


@needs_data
def test_tgf_hand_pose_matches_libigl_forward_kinematics():
    import igl

    skel = read_tgf(DATA / "libigl" / "hand.tgf")
    C, BE = parse_tgf(DATA / "libigl" / "hand.tgf")
    assert skel.num_joints == len(BE) == 20
    bones = skel.bones()
    assert len(bones) == 20
    by_name = {n.split("->")[0]: seg for n, seg in zip(bones.names, bones.segments)}
    for e, (a, b) in enumerate(BE):
        np.testing.assert_allclose(by_name[f"bone{e}"], [C[a], C[b]], atol=1e-12)
    dQ = igl.readDMAT(str(DATA / "libigl" / "hand-pose.dmat")).reshape(-1, 4)
    vQ, vT = libigl_forward_kinematics(C, BE, dQ)
    pose = load_pose(DATA / "libigl" / "hand-pose.dmat", skel)
    M = Character(skel).skin_matrices(skel.forward_kinematics(pose))
    order = [int(n[4:]) for n in skel.names]
    np.testing.assert_allclose(M[:, :3, :3], vQ[order], atol=1e-12)
    np.testing.assert_allclose(M[:, :3, 3], vT[order], atol=1e-12)


def test_tgf_errors(tmp_path):
    path = tmp_path / "s.tgf"
    path.write_text("1 0 0 0\n2 1 0 0\n#\n1 3\n#\n")
    with pytest.raises(FileFormatError, match=r"s\.tgf:4: bone 1 3"):
        read_tgf(path)
    path.write_text("1 0 0 0\n2 1 0 0\n")
    with pytest.raises(FileFormatError, match="no '#'"):
        read_tgf(path)
    path.write_text("1 0 0 0\n2 1 0 0\n#\n1 2\n2 1\n#\n")
    with pytest.raises(FileFormatError, match="several bones|cycle"):
        read_tgf(path)
    path.write_text("1 0 0 0\n2 1 0 0\n3 1 1 0\n#\n2 3\n1 2\n#\n")
    skel = read_tgf(path)
    assert skel.names == ("bone1", "bone0") and list(skel.parents) == [-1, 0]
    (tmp_path / "p.dmat").write_text("1 4\n0\n0\n0\n1\n")
    with pytest.raises(FileFormatError, match="expected 2 quaternions"):
        read_dmat_pose(tmp_path / "p.dmat", skel)


@needs_data
def test_tet_mesh_surface_and_mesh_with_skeleton():
    import igl

    V, F = read_mesh(DATA / "libigl" / "hand.mesh")
    Vall, _, _ = igl.readMESH(str(DATA / "libigl" / "hand.mesh"))
    assert len(np.unique(F)) == len(V) < len(Vall)
    # kept vertices are a subsequence of the file's, in order
    match = [int(np.flatnonzero((Vall == v).all(axis=1))[0]) for v in V[:: max(len(V) // 50, 1)]]
    assert match == sorted(match)
    volume = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6
    assert volume > 0  # outward-facing boundary
    arm = load_character(DATA / "libigl" / "arm.obj", skeleton=DATA / "libigl" / "arm.tgf")
    weights = igl.readDMAT(str(DATA / "libigl" / "arm-weights.dmat"))
    assert arm.skeleton.num_joints == weights.shape[1] == 4
    assert len(arm.meshes[0].vertices) == len(weights) == 8311 and arm.meshes[0].joints is None


def test_load_character_dispatch_errors(tmp_path):
    with pytest.raises(FileFormatError, match="unknown character extension"):
        load_character(tmp_path / "x.fbx")
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(InputError, match="needs a skeleton"):
        load_character(tmp_path / "m.obj")
    (tmp_path / "s.tgf").write_text("1 0 0 0\n2 1 0 0\n#\n1 2\n#\n")
    char = load_character(tmp_path / "m.obj", skeleton=tmp_path / "s.tgf")
    assert char.meshes[0].faces.tolist() == [[0, 1, 2]] and char.skeleton.names == ("bone0",)
    with pytest.raises(FileFormatError, match="no such mesh"):
        load_character(tmp_path / "missing.obj", skeleton=tmp_path / "s.tgf")


def test_pose_file(tmp_path):
    path = tmp_path / "m.bvh"
    path.write_text(BVH)
    skel, _ = read_bvh(path)
    pose_path = tmp_path / "pose.json"
    pose_path.write_text(json.dumps({"rotations": {"Spine": [0, 0, 2, 0]}, "translations": {"Hips": [4, 5, 6]}}))
    pose = load_pose(pose_path, skel)
    np.testing.assert_allclose(pose.rotation, [[0, 0, 0, 1], [0, 0, 1, 0]])
    np.testing.assert_allclose(pose.translation, [[4, 5, 6], [0, 1, 0]])
    pose_path.write_text(json.dumps({"rotations": {"Spin": [0, 0, 0, 1]}}))
    with pytest.raises(InputError, match="unknown joint 'Spin'; did you mean 'Spine'"):
        load_pose(pose_path, skel)
    pose_path.write_text(json.dumps({"rotations": {"Spine": [0, 0, 1]}}))
    with pytest.raises(InputError, match="expected 4 finite numbers"):
        load_pose(pose_path, skel)
    pose_path.write_text(json.dumps({"rotation": {}}))
    with pytest.raises(InputError, match="'rotation'"):
        load_pose(pose_path, skel)
    pose_path.write_text("{")
    with pytest.raises(FileFormatError, match="not valid JSON"):
        load_pose(pose_path, skel)
