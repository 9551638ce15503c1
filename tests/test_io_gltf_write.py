"""Baked morph-target animations written as .glb."""
import numpy as np
import pygltflib
import pytest

from nrpose.model.character import Mesh
from nrpose.errors import InputError
from nrpose.io.gltf_write import write_animated_glb


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
        assert np.allclose(acc.min, base.min(axis=0)) and np.allclose(acc.max, base.max(axis=0))
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
