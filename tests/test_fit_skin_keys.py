"""The fitted file's compact encodings: helper channels with only the keys a player needs
(nrpose.fit.helper_keys), weights stored as normalised unsigned shorts (nrpose.fit.skin_file)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from fit_skin_played import played_rms
from nrpose.cli import main
from nrpose.fit.helper_keys import helper_trs, reduce_keys, stored_quats
from nrpose.fit.skin_file import stored_weights
from nrpose.model.rotation import Rotation, quat_matrices
from nrpose.model.timing import sample_times

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOX = DATA / "gltf" / "Fox.glb"


def transforms(rotvecs: np.ndarray, t: np.ndarray) -> np.ndarray:
    L = np.tile(np.eye(4), (len(t), 1, 1))
    L[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    L[:, :3, 3] = t
    return L


def played_points(times, t, q, keys, points, nlerp: bool) -> np.ndarray:
    """(F, n, 3): points moved by the transforms a player interpolates from keys (slerp, or
    Blender's normalised component lerp), independently of the module's own interpolation."""
    q = stored_quats(q) / 32767
    out = []
    for f, time in enumerate(times):
        k = min(max(np.searchsorted(keys, f, side="right") - 1, 0), len(keys) - 2)
        a, b = keys[k], keys[k + 1]
        s = (time - times[a]) / (times[b] - times[a])
        if nlerp:
            r = (1 - s) * q[a] + s * q[b]
            R = quat_matrices(r[None])[0]
        else:
            rel = Rotation.from_quat(q[a]).inv() * Rotation.from_quat(q[b])
            R = (Rotation.from_quat(q[a]) * Rotation.from_rotvec(s * rel.as_rotvec())).as_matrix()
        out.append(points @ R.T + (1 - s) * t[a] + s * t[b])
    return np.array(out)


@pytest.mark.parametrize("seed", range(4))
def test_kept_keys_play_every_frame_within_the_tolerance(seed):
    """Every point within the radius, moved by either player's interpolation of the kept keys,
    stays within the tolerance (times the parent's scale) of where the exact transforms put it."""
    rng = np.random.default_rng(seed)
    F = 120
    times = np.sort(rng.random(F)).cumsum() / 10
    # a uniform spin of 143 degrees (slerp alone would need two keys for it, nlerp not), then a
    # smooth motion with a jerk (the rotation vector's z jumps by 1.5 between two frames)
    phase = np.linspace(0, 3, F)[:, None]
    rot = np.sin(phase * rng.uniform(0.3, 1, 3)) * rng.uniform(0.2, 1, 3)
    axis = rng.normal(size=3)
    rot[:40] = np.outer(2.5 * (times[:40] - times[0]) / (times[39] - times[0]), axis / np.linalg.norm(axis))
    rot[40:] += rot[39] - rot[40]
    rot[F // 2:] += [0, 0, 1.5]
    L = transforms(rot, np.cos(phase * rng.uniform(0.3, 1, 3)) * 0.3 * (np.arange(F) >= 40)[:, None])
    t, q = helper_trs(L)
    scale = np.full(F, rng.uniform(0.5, 2))
    radius, tolerance = 0.8, 2e-3
    keys = reduce_keys(times, t, q, scale, radius, tolerance)
    assert keys[0] == 0 and keys[-1] == F - 1 and (np.diff(keys) > 0).all()
    assert len(keys) < F / 2          # smooth stretches need few keys
    points = rng.normal(size=(200, 3))
    points *= radius / np.linalg.norm(points, axis=1, keepdims=True)
    exact = np.einsum("fij,nj->fni", L[:, :3, :3], points) + L[:, None, :3, 3]
    for nlerp in (False, True):
        err = np.linalg.norm(played_points(times, t, q, keys, points, nlerp) - exact, axis=2).max(axis=1)
        assert (err * scale <= tolerance * (1 + 1e-9)).all(), nlerp


def test_a_uniform_motion_needs_two_keys_and_no_tolerance_keeps_every_frame():
    F = 50
    times = np.arange(F) / 30
    L = transforms(np.outer(np.linspace(0, 1, F), [0, 0, 0.1]), np.outer(np.linspace(0, 1, F), [1, 2, 3]))
    t, q = helper_trs(L)
    assert list(reduce_keys(times, t, q, np.ones(F), 1.0, 1e-4)) == [0, F - 1]
    assert list(reduce_keys(times, t, q, np.ones(F), 1.0, 0.0)) == list(range(F))
    # under the int16 rounding of the rotations: every frame a key, and the refinement ends
    assert list(reduce_keys(times, t, q, np.ones(F), 1.0, 1e-9)) == list(range(F))


def test_stored_weights_sum_to_65535_and_stay_within_a_step():
    rng = np.random.default_rng(3)
    w = rng.random((5000, 8)) ** 4
    w[:, 6:] = 0
    w /= w.sum(axis=1, keepdims=True)
    s = stored_weights(w)
    assert s.dtype == np.uint16 and (s.sum(axis=1, dtype=np.int64) == 65535).all()
    assert np.abs(s / 65535 - w).max() < 1 / 65535
    assert (s[:, 6:] == 0).all()


def referenced_accessors(g: pygltflib.GLTF2) -> set:
    """Accessors the document's meshes, skins and animations read."""
    used = {i for m in g.meshes for p in m.primitives for i in vars(p.attributes).values() if isinstance(i, int)}
    used |= {p.indices for m in g.meshes for p in m.primitives if p.indices is not None}
    used |= {s.inverseBindMatrices for s in g.skins if s.inverseBindMatrices is not None}
    return used | {i for a in g.animations for s in a.samplers for i in (s.input, s.output)}


def test_replace_takes_an_accessor_in_place_only_where_nothing_else_reads_it():
    from nrpose.io.gltf_write import Blob
    g = pygltflib.GLTF2()
    blob = Blob(g)
    a = blob.add(np.zeros((4, 4), np.float32), "VEC4")
    b = blob.add(np.ones((4, 4), np.float32), "VEC4")
    g.meshes = [pygltflib.Mesh(primitives=[pygltflib.Primitive(attributes=pygltflib.Attributes(WEIGHTS_0=a)),
                                           pygltflib.Primitive(attributes=pygltflib.Attributes(WEIGHTS_0=b)),
                                           pygltflib.Primitive(attributes=pygltflib.Attributes(WEIGHTS_0=b))])]
    new = np.full((4, 4), 7, np.uint16)
    assert blob.replace(a, new, "VEC4", pygltflib.UNSIGNED_SHORT, normalized=True) == a
    assert blob.replace(b, new, "VEC4", pygltflib.UNSIGNED_SHORT) == 2        # read twice: a new accessor
    blob.pack()
    data = b"".join(blob.parts)
    view = g.bufferViews[g.accessors[a].bufferView]
    assert data[view.byteOffset:view.byteOffset + view.byteLength] == new.tobytes()
    assert g.accessors[a].normalized and g.accessors[a].componentType == pygltflib.UNSIGNED_SHORT
    assert blob.size == 32 + 64 + 32     # the old 64 bytes of accessor a are gone
    g.extensionsUsed = ["EXT_meshopt_compression"]       # might read views: nothing replaced in place
    assert blob.replace(a, new, "VEC4", pygltflib.UNSIGNED_SHORT) == 3


@pytest.mark.skipif(not FOX.is_file(), reason=f"shared assets not found at {DATA}")
def test_cli_file_is_compact_and_plays_what_the_report_says(tmp_path, capsys):
    """The written Fox with helpers: helper channels of the slow clip (Survey) thinned, every
    skin weight set a normalised unsigned short, joints unsigned bytes; the report's held-out
    figures are those of the file as nrpose plays it (test_fit_skin_tracks checks the latter
    with fitted tracks; here with rules)."""
    from nrpose.io import load_character

    out, report = tmp_path / "fox.glb", tmp_path / "r.json"
    code = main(["fit-skin", str(FOX), "--train", "Walk", "--holdout", "Run", "--rom-degrees", "30",
                 "--helpers", "2", "--key-tolerance", "1e-3", "-o", str(out), "--report", str(report)])
    assert code == 0, capsys.readouterr().err
    r = json.loads(report.read_text())
    g = pygltflib.GLTF2().load(str(out))
    helpers = {i for i, n in enumerate(g.nodes) if (n.name or "").startswith("nrpose_helper")}
    assert len(helpers) == r["helpers"] >= 1
    survey = [a for a in g.animations if a.name == "Survey"][0]
    frames = len(sample_times(load_character(FOX).clip("Survey").duration, 30.0))
    counts = [g.accessors[survey.samplers[c.sampler].input].count for c in survey.channels if c.target.node in helpers]
    assert max(counts) < frames and min(counts) >= 2
    for prim in (p for m in g.meshes for p in m.primitives if p.attributes.WEIGHTS_0 is not None):
        weights, joints = g.accessors[prim.attributes.WEIGHTS_0], g.accessors[prim.attributes.JOINTS_0]
        assert weights.componentType == pygltflib.UNSIGNED_SHORT and weights.normalized
        assert joints.componentType == pygltflib.UNSIGNED_BYTE
    # the source's weights and inverse binds were replaced in place: no buffer view left unread
    read = {g.accessors[i].bufferView for i in referenced_accessors(g)} | {im.bufferView for im in g.images}
    assert all(i in read for i in range(len(g.bufferViews)))
    assert sum(v.byteLength for v in g.bufferViews) <= g.buffers[0].byteLength < \
        sum(v.byteLength for v in g.bufferViews) + 4 * len(g.bufferViews)
    assert played_rms(FOX, out, "Run") == pytest.approx(r["errors"]["Run"]["rms_fraction"], rel=1e-3)


@pytest.mark.skipif(not FOX.is_file(), reason=f"shared assets not found at {DATA}")
def test_helper_channels_go_to_the_clips_animations(tmp_path):
    """A source whose first animation moves no joint (it makes no clip): each clip's helper
    channels still land in that clip's own animation."""
    from nrpose.fit.character_skin import fit_character, nrmls_targets
    from nrpose.fit.helper_fit import add_helpers
    from nrpose.fit.rom import range_of_motion
    from nrpose.fit.skin_file import write_fitted_glb
    from nrpose.io import load_character
    from nrpose.pose.poser import CharacterPoser

    g = pygltflib.GLTF2().load(str(FOX))
    walk = [a for a in g.animations if a.name == "Walk"][0]
    sampler = walk.samplers[walk.channels[0].sampler]
    g.animations.insert(0, pygltflib.Animation(name="mesh node only", samplers=[pygltflib.AnimationSampler(
        input=sampler.input, output=sampler.output)], channels=[pygltflib.AnimationChannel(
            sampler=0, target=pygltflib.AnimationChannelTarget(node=1, path="rotation"))]))
    source = tmp_path / "fox_extra_animation.glb"
    g.save_binary(str(source))
    fox = load_character(source)
    assert [c.name for c in fox.clips] == ["Survey", "Walk", "Run"]
    rom = range_of_motion(fox.skeleton, 30.0, pairs=1)
    G, targets = nrmls_targets(CharacterPoser(fox, method="nrmls"), rom)
    fitted, _ = add_helpers(fox, fit_character(fox, G, targets, 4), G, rom, targets, 1, 4)
    out = tmp_path / "fitted.glb"
    write_fitted_glb(source, out, fox, fitted)
    back = pygltflib.GLTF2().load(str(out))
    helper = next(i for i, n in enumerate(back.nodes) if (n.name or "").startswith("nrpose_helper"))
    moves_helper = [any(c.target.node == helper for c in a.channels) for a in back.animations]
    assert [a.name for a in back.animations] == ["mesh node only", "Survey", "Walk", "Run"]
    assert moves_helper == [False, True, True, True]
