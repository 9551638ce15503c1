"""Character binds in the binding cache (NR-MLS; LBS, DQS and CoR): a cached bind equals a
fresh one bitwise; a changed vertex, skin weight or option, or another code version, is a new
bind."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from nrpose.bind import cache
from nrpose.model.character import Character
from nrpose.model.skeleton import LocalPose
from nrpose.pose import poser as poser_module
from nrpose.pose.poser import CharacterPoser

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOX = DATA / "gltf" / "Fox.glb"


pytestmark = pytest.mark.usefixtures("own_cache")   # fixtures fox and own_cache: tests/conftest.py


def some_poses(ch: Character) -> LocalPose:
    clip = ch.clips[0]
    return clip.sample(np.linspace(0.0, clip.duration, 7))


def bind_state(p: CharacterPoser) -> dict:
    """The bound deformer's rest terms (recomputed from the arrays it was bound with)."""
    t = p.deformer.terms
    return {n: np.asarray(getattr(t, n)) for n in ("weights", "t", "p_star", "u", "lever", "ref")}


def test_cached_bind_equals_fresh_bitwise(fox):
    fresh = CharacterPoser(fox, method="nrmls")
    assert fresh.bind_cache == "miss"
    again = CharacterPoser(fox, method="nrmls")
    assert again.bind_cache == "hit"
    a, b = bind_state(fresh), bind_state(again)
    for name in a:
        assert a[name].dtype == b[name].dtype and np.array_equal(a[name], b[name]), name
        assert a[name].tobytes() == b[name].tobytes(), name
    local = some_poses(fox)
    pa, pb = fresh.pose(local).positions, again.pose(local).positions
    assert pa.tobytes() == pb.tobytes()


def test_cached_layout_equals_fresh_bitwise(fox, monkeypatch):
    stored = {}
    real = poser_module.cached_status

    def spy(parts, compute, directory=None):
        stored["fresh"] = compute()
        got, status = real(parts, lambda: stored["fresh"], directory)
        return got, status

    monkeypatch.setattr(poser_module, "cached_status", spy)
    CharacterPoser(fox, method="nrmls")
    monkeypatch.setattr(poser_module, "cached_status", real)
    files = list((cache.cache_dir() / poser_module.BIND_CACHE_FOLDER).glob("*.npz"))   # the first bind's file: the same arrays, bit for bit
    assert len(files) == 1
    with np.load(files[0]) as z:
        for name, arr in stored["fresh"].items():
            assert z[name].dtype == arr.dtype and z[name].tobytes() == np.ascontiguousarray(arr).tobytes(), name


def changed_vertex(ch: Character) -> Character:
    m = ch.meshes[0]
    v = m.vertices.copy()
    v[5, 1] += 1e-9
    return dataclasses.replace(ch, meshes=(dataclasses.replace(m, vertices=v),) + tuple(ch.meshes[1:]))


def changed_weight(ch: Character) -> Character:
    m = ch.meshes[0]
    w = m.weights.copy()
    w[3] = w[3][::-1] if (w[3] != w[3][::-1]).any() else np.full_like(w[3], 1.0 / w.shape[1])
    return dataclasses.replace(ch, meshes=(dataclasses.replace(m, weights=w),) + tuple(ch.meshes[1:]))


@pytest.mark.parametrize("change", ["vertex", "weight", "k", "alpha", "blend", "weights", "code"])
def test_a_change_is_a_new_bind(fox, change, monkeypatch):
    assert CharacterPoser(fox, method="nrmls").bind_cache == "miss"
    assert CharacterPoser(fox, method="nrmls").bind_cache == "hit"
    ch, opts = fox, {}
    if change == "vertex":
        ch = changed_vertex(fox)
    elif change == "weight":
        ch = changed_weight(fox)
    elif change == "k":
        opts = {"k": 3}
    elif change == "alpha":
        opts = {"alpha": 2.0}
    elif change == "blend":
        opts = {"blend": "relative"}          # the default is the quaternion blend
    elif change == "weights":
        opts = {"weights": "euclidean"}
    else:
        monkeypatch.setattr(poser_module, "code_version", lambda modules: "another version")
    p = CharacterPoser(ch, method="nrmls", **opts)
    assert p.bind_cache == "miss"
    fresh = CharacterPoser(ch, method="nrmls", **opts)
    assert fresh.bind_cache == "hit"
    local = some_poses(fox)
    assert p.pose(local).positions.tobytes() == fresh.pose(local).positions.tobytes()


def test_code_version_follows_the_source(tmp_path, monkeypatch):
    mod = tmp_path / "bindmod_probe.py"
    mod.write_text("x = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    first = cache.code_version.__wrapped__(("bindmod_probe",))
    mod.write_text("x = 2\n")
    assert cache.code_version.__wrapped__(("bindmod_probe",)) != first
    assert len(first) == 64


# ---------------------------------------------------------------------- skinning binds
SKIN_METHODS = ("lbs", "dqs", "cor")


def skin_state(p: CharacterPoser) -> dict:
    """The host bind the skinning deformer is made from (source vertices, joints, weights[, centers])."""
    return {f"arg{i}": np.asarray(a) for i, a in enumerate(p._device_args)}


@pytest.mark.parametrize("method", SKIN_METHODS)
def test_cached_skin_bind_equals_fresh_bitwise(fox, method):
    fresh = CharacterPoser(fox, method=method)
    assert fresh.bind_cache == "miss"
    again = CharacterPoser(fox, method=method)
    assert again.bind_cache == "hit"
    a, b = skin_state(fresh), skin_state(again)
    assert len(a) == (4 if method == "cor" else 3)
    for name in a:
        assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
        assert a[name].tobytes() == b[name].tobytes(), name
    local = some_poses(fox)
    assert fresh.pose(local).positions.tobytes() == again.pose(local).positions.tobytes()


def test_lbs_and_dqs_share_a_bind_and_cor_has_its_own(fox):
    assert CharacterPoser(fox, method="lbs").bind_cache == "miss"
    assert CharacterPoser(fox, method="dqs").bind_cache == "hit"     # the same joints and weights
    assert CharacterPoser(fox, method="cor").bind_cache == "miss"    # and the centers of rotation


def test_cached_distance_weight_skin_bind_equals_fresh(fox):
    fresh = CharacterPoser(fox, method="lbs", weights="euclidean", alpha=1.5)
    again = CharacterPoser(fox, method="lbs", weights="euclidean", alpha=1.5)
    assert (fresh.bind_cache, again.bind_cache) == ("miss", "hit")
    a, b = skin_state(fresh), skin_state(again)
    assert all(a[n].tobytes() == b[n].tobytes() for n in a)


@pytest.mark.parametrize("change", ["vertex", "weight", "weights", "alpha", "code"])
@pytest.mark.parametrize("method", ["lbs", "cor"])
def test_a_change_is_a_new_skin_bind(fox, method, change, monkeypatch):
    base = {"weights": "euclidean"} if change == "alpha" else {}
    assert CharacterPoser(fox, method=method, **base).bind_cache == "miss"
    assert CharacterPoser(fox, method=method, **base).bind_cache == "hit"
    ch, opts = fox, dict(base)
    if change == "vertex":
        ch = changed_vertex(fox)
    elif change == "weight":
        ch = changed_weight(fox)
    elif change == "weights":
        opts = {"weights": "euclidean"}
    elif change == "alpha":
        opts["alpha"] = 2.0
    else:
        monkeypatch.setattr(poser_module, "code_version", lambda modules: "another version")
    p = CharacterPoser(ch, method=method, **opts)
    assert p.bind_cache == "miss"
    fresh = CharacterPoser(ch, method=method, **opts)
    assert fresh.bind_cache == "hit"
    a, b = skin_state(p), skin_state(fresh)
    assert all(a[n].tobytes() == b[n].tobytes() for n in a)


def test_a_damaged_skin_bind_file_is_rebuilt(fox):
    first = CharacterPoser(fox, method="lbs")
    files = list((cache.cache_dir() / poser_module.BIND_CACHE_FOLDER).glob("*.npz"))
    assert len(files) == 1
    raw = bytearray(files[0].read_bytes())
    raw[len(raw) // 2] ^= 0x01                     # inside a member's data: its CRC-32 no longer holds
    files[0].write_bytes(bytes(raw))
    again = CharacterPoser(fox, method="lbs")
    assert again.bind_cache == "rebuilt"
    a, b = skin_state(first), skin_state(again)
    assert all(a[n].tobytes() == b[n].tobytes() for n in a)


def test_segment_parameters_of_unweighted_bones_are_unused(fox):
    """The binding cache keeps a vertex's segment parameters t on its weighted bones (0 on
    most others): with t zeroed where the weight is 0, the rest terms other than t and the
    float64 reference poses are bitwise those of the full t (the character's bone weights)."""
    from test_mls import random_pose

    from nrpose import Deformer, HandleSet
    from nrpose.bind.bone_weights import SKELETON_K, bone_weights

    bw = bone_weights(fox, "authored", SKELETON_K, distances=False)
    deform = np.concatenate([np.full(len(m.vertices), m.rigid_joint is None) for m in fox.meshes])
    W, t = bw.weights[deform], bw.t[deform]
    zeroed = np.where(W != 0, t, 0.0)
    assert (zeroed != t).any()                      # else the test would be moot
    cached = CharacterPoser(fox, method="nrmls").deformer.terms.t      # what the cache gives the deformer
    assert np.array_equal(cached[W != 0], t[W != 0]) and set(np.unique(cached[cached != t])) == {0.0}
    rest = HandleSet.make(segments=fox.skeleton.bones().segments, what="skeleton bones")
    V = np.concatenate([m.vertices for m in fox.meshes])[deform]
    full, sparse = (Deformer(V, rest, weights=W, k=SKELETON_K, t=tt, backend="numpy") for tt in (t, zeroed))
    for name in ("weights", "p_star", "u", "lever", "ref", "phat"):
        assert getattr(full.terms, name).tobytes() == getattr(sparse.terms, name).tobytes(), name
    rng = np.random.default_rng(3)
    for _ in range(3):
        pose = random_pose(rng, rest)
        assert full.pose(pose).tobytes() == sparse.pose(pose).tobytes()
