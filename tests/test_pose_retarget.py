"""Retargeting (nrpose.pose.retarget, nrpose.cli.retarget, nrpose.io.bvh_write).

The CLI is exercised through ``nrpose.cli.main``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from nrpose import cli
from nrpose.io import load_character
from nrpose.model.character import Character
from nrpose.errors import InputError
from nrpose.io.bvh_read import read_bvh
from nrpose.io.bvh_write import write_bvh
from nrpose.pose.retarget import (RetargetPlan, joint_map, mapped_bones, normalize_name, retarget, retarget_pose,
                             sole_heights)
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import LocalPose, Skeleton, polar_rotation

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BVH = DATA / "bvh" / "131_03.bvh"
needs_data = pytest.mark.skipif(not BVH.is_file(), reason=f"shared assets not found at {DATA}")


# --------------------------------------------------------------------------- helpers

def run(args, capsys):
    """Exit code, stdout, stderr of ``nrpose retarget ...``."""
    code = cli.main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def angles(a, b):
    """Angles in degrees between rows of a and b (..., 3)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


def positions(skel, pose):
    return skel.forward_kinematics(pose)[..., :3, 3]


def bone_errors(source, clip, target, mapping, times, local):
    """Per mapped bone: (raw angles (F,), angles after rest alignment (F,)) in degrees.

    raw: target bone j → c against source bone m(j) → m(c), world directions.
    After rest alignment: the source bone carried by the constant rotation that
    takes its rest direction onto the target bone's direction in the target's
    aligned rest (the target posed from the source's rest pose), that rotation
    expressed in the source joint's frame: ``D_s(t) C D_s(t)^-1 u_s(t)``.
    """
    plan = RetargetPlan(source.skeleton, target.skeleton, mapping)
    Gs = source.skeleton.forward_kinematics(clip.sample(times))
    Gs0 = source.skeleton.rest_globals()
    pt, ps = positions(target.skeleton, local), Gs[..., :3, 3]
    aligned = positions(target.skeleton, plan.run(source.skeleton.rest_pose))[0]
    Rs, Rs0 = polar_rotation(Gs[..., :3, :3]), polar_rotation(Gs0[:, :3, :3])
    out = {}
    for b in mapped_bones(source.skeleton, target.skeleton, mapping):
        (j, c), (s, sc) = b.target, b.source
        ut, us = pt[:, c] - pt[:, j], ps[:, sc] - ps[:, s]
        a, us0 = aligned[c] - aligned[j], Gs0[sc, :3, 3] - Gs0[s, :3, 3]
        axis = np.cross(us0, a)
        ang = np.arctan2(np.linalg.norm(axis), us0 @ a)
        C = Rotation.from_rotvec(axis / max(np.linalg.norm(axis), 1e-300) * ang).as_matrix()
        D = Rs[:, s] @ Rs0[s].T
        expected = np.einsum("fab,bc,fdc,fd->fa", D, C, D, us)
        name = f"{target.skeleton.names[j]}->{target.skeleton.names[c]}"
        out[name] = (angles(ut, us), angles(ut, expected))
    return out


def copy_skeleton(skel: Skeleton, names, scale: float, seed: int = 0, armature: bool = True) -> Skeleton:
    """A copy of skel's rest posture: renamed, uniformly scaled, rest bone frames rotated at random,
    optionally under a Mixamo-like armature ``pre`` (a quarter turn and a 0.01 scale)."""
    G0 = skel.rest_globals()
    P = scale * G0[:, :3, 3]
    J = skel.num_joints
    Q = Rotation.random(J, random_state=seed).as_matrix()
    pre = np.tile(np.eye(4), (J, 1, 1))
    if armature:
        pre[0, :3, :3] = 0.01 * Rotation.from_euler("x", 90, degrees=True).as_matrix()
    t, q = np.zeros((J, 3)), np.zeros((J, 4))
    lin = np.zeros((J, 3, 3))
    for j in range(J):
        p = skel.parents[j]
        parent_lin = pre[j, :3, :3] if p < 0 else lin[p] @ pre[j, :3, :3]
        parent_pos = np.zeros(3) if p < 0 else P[p]
        t[j] = np.linalg.solve(parent_lin, P[j] - parent_pos)
        Rp = polar_rotation(parent_lin)
        q[j] = Rotation.from_matrix(Rp.T @ Q[j]).as_quat()
        lin[j] = parent_lin @ Rp.T @ Q[j]
    tip_world = np.einsum("jab,jb->ja", G0[:, :3, :3], skel.tips)
    tips = np.einsum("jab,jb->ja", np.linalg.inv(lin), scale * tip_world)
    return Skeleton(names=tuple(names), parents=skel.parents, translation=t, rotation=q, scale=np.ones((J, 3)),
                    pre=pre, tips=tips)


@pytest.fixture(scope="module")
def walker():
    from nrpose.rigs.humanoid import humanoid
    return humanoid()


@pytest.fixture(scope="module")
def cmu():
    if not BVH.is_file():
        pytest.skip(f"shared assets not found at {DATA}")
    return load_character(BVH)


@pytest.fixture(scope="module")
def gltf_targets():
    if not BVH.is_file():
        pytest.skip(f"shared assets not found at {DATA}")
    return {n: load_character(DATA / "gltf" / f"{n}.glb") for n in ("Mannequin", "Ely")}


# --------------------------------------------------------------------------- mapping

def test_names_are_normalised_case_prefix_and_separator_insensitively():
    assert normalize_name("mixamorig:LeftUpLeg") == normalize_name("left_up_leg") == "leftupleg"
    assert normalize_name("mixamorig_Hips") == normalize_name("HIPS") == "hips"
    assert normalize_name("Bip01 L Thigh") == "lthigh"


def _renamed(skel: Skeleton, table: dict) -> Skeleton:
    return Skeleton(names=tuple(table.get(n, n) for n in skel.names), parents=skel.parents,
                    translation=skel.translation, rotation=skel.rotation, scale=skel.scale)


HUMANOID_AS = {
    "mixamo": {"Hips": "mixamorig:Hips", "Spine": "mixamorig:Spine", "Chest": "mixamorig:Spine1",
               "Neck": "mixamorig:Neck", "Head": "mixamorig:Head",
               **{f"{s}{a}": f"mixamorig:{s}{b}" for s in ("Left", "Right") for a, b in
                  (("Shoulder", "Shoulder"), ("UpperArm", "Arm"), ("LowerArm", "ForeArm"), ("Hand", "Hand"),
                   ("UpLeg", "UpLeg"), ("Leg", "Leg"), ("Foot", "Foot"), ("Toe", "ToeBase"))}},
    "cmu_bvh11": {"Spine": "lowerback", "Chest": "Chest", "Neck": "lowerneck",
                  **{f"{s}{a}": f"{s}{b}" for s in ("Left", "Right") for a, b in
                     (("Shoulder", "Collar"), ("UpperArm", "Shoulder"), ("LowerArm", "Elbow"), ("Hand", "Wrist"),
                      ("UpLeg", "Hip"), ("Leg", "Knee"), ("Foot", "Ankle"), ("Toe", "Toe"))}},
    "cmu_cgspeed": {"Spine": "LowerBack", "Chest": "Spine",
                    **{f"{s}{a}": f"{s}{b}" for s in ("Left", "Right") for a, b in
                       (("Shoulder", "Shoulder"), ("UpperArm", "Arm"), ("LowerArm", "ForeArm"), ("Hand", "Hand"),
                        ("UpLeg", "UpLeg"), ("Leg", "Leg"), ("Foot", "Foot"), ("Toe", "ToeBase"))}},
    "unreal": {"Hips": "pelvis", "Spine": "spine_01", "Chest": "spine_02", "Neck": "neck_01", "Head": "head",
               **{f"{s}{a}": f"{b}_{s[0].lower()}" for s in ("Left", "Right") for a, b in
                  (("Shoulder", "clavicle"), ("UpperArm", "upperarm"), ("LowerArm", "lowerarm"), ("Hand", "hand"),
                   ("UpLeg", "thigh"), ("Leg", "calf"), ("Foot", "foot"), ("Toe", "ball"))}},
    "blender": {"Hips": "DEF-hips", **{f"{s}{a}": f"DEF-{b}.{s[0]}" for s in ("Left", "Right") for a, b in
                                       (("Shoulder", "collar"), ("UpperArm", "upper_arm"), ("LowerArm", "forearm"),
                                        ("Hand", "hand"), ("UpLeg", "thigh"), ("Leg", "shin"), ("Foot", "foot"),
                                        ("Toe", "toe"))}},
}


@pytest.mark.parametrize("a", sorted(HUMANOID_AS))
@pytest.mark.parametrize("b", sorted(HUMANOID_AS))
def test_automatic_mapping_across_naming_conventions(walker, a, b):
    skel = walker.skeleton
    src, tgt = _renamed(skel, HUMANOID_AS[a]), _renamed(skel, HUMANOID_AS[b])
    mapping = joint_map(src, tgt)
    expected = {tgt.names[j]: src.names[j] for j in range(skel.num_joints)}
    assert mapping == expected


def test_user_map_overrides_and_validates(walker):
    skel = walker.skeleton
    tgt = _renamed(skel, HUMANOID_AS["mixamo"])
    m = joint_map(skel, tgt, {"mixamorig:Head": "Neck", "mixamorig:Neck": None})
    assert m["mixamorig:Head"] == "Neck" and "mixamorig:Neck" not in m
    with pytest.raises(InputError, match="target joint 'mixamorig:Heda' does not exist.*mixamorig:Head"):
        joint_map(skel, tgt, {"mixamorig:Heda": "Head"})
    with pytest.raises(InputError, match="source joint 'Hed'"):
        joint_map(skel, tgt, {"mixamorig:Head": "Hed"})


@needs_data
def test_cmu_onto_mixamo_mapping(cmu, gltf_targets):
    m = joint_map(cmu.skeleton, gltf_targets["Mannequin"].skeleton)
    want = {"Hips": "Hips", "Spine": "lowerback", "Spine1": "Chest", "Spine2": "Chest2", "Neck": "lowerneck",
            "Head": "Head", "LeftShoulder": "LeftCollar", "LeftArm": "LeftShoulder", "LeftForeArm": "LeftElbow",
            "LeftHand": "LeftWrist", "RightUpLeg": "RightHip", "RightLeg": "RightKnee", "RightFoot": "RightAnkle",
            "RightToeBase": "RightToe", "LeftHandThumb1": "LThumb"}
    for t, s in want.items():
        assert m[f"mixamorig:{t}"] == s
    assert len(m) == 24 and "mixamorig:LeftHandIndex1" not in m


# --------------------------------------------------------------------------- transfer

def _self_case(character):
    clip = character.clips[0]
    mapping = joint_map(character.skeleton, character.skeleton)
    assert mapping == {n: n for n in character.skeleton.names}
    times, local, plan = retarget_pose(character, clip, character, mapping, root="keep", fps=30)
    assert plan.scale == pytest.approx(1.0, abs=1e-12)
    want = positions(character.skeleton, clip.sample(times))
    got = positions(character.skeleton, local)
    height = np.ptp(want[..., 1])
    return np.abs(got - want).max() / height


def test_onto_its_own_skeleton_reproduces_the_motion(walker):
    assert _self_case(walker) <= 1e-5


@needs_data
def test_cmu_onto_its_own_skeleton_reproduces_the_motion(cmu):
    assert _self_case(cmu) <= 1e-5


@pytest.mark.parametrize("case", ["walker", "cmu"])
def test_scaled_renamed_rotated_copy(case, request):
    source = request.getfixturevalue(case)
    skel = source.skeleton
    c = 1.7 if case == "walker" else 0.056
    names = [f"bone_{j:02d}" for j in range(skel.num_joints)]
    copy = copy_skeleton(skel, names, c, seed=3)
    target = Character(copy)
    assert joint_map(skel, copy) == {}                      # nothing in common by name
    user = dict(zip(names, skel.names))
    mapping = joint_map(skel, copy, user)
    times, local, plan = retarget_pose(source, source.clips[0], target, mapping, root="keep", fps=30)
    assert plan.scale == pytest.approx(c, rel=1e-9)
    errs = bone_errors(source, source.clips[0], target, mapping, times, local)
    raw = np.concatenate([e[0] for e in errs.values()])
    assert len(errs) >= 15 and raw.max() <= 0.5
    want = c * positions(skel, source.clips[0].sample(times))
    got = positions(copy, local)
    root = plan.root
    assert np.abs(got[:, root] - want[:, root]).max() <= 1e-6 * c * 20
    assert np.abs(got - want).max() <= 1e-5 * np.ptp(want[..., 1])   # the whole posture, scaled


def test_in_place_keeps_the_root_over_its_rest_position(walker):
    mapping = joint_map(walker.skeleton, walker.skeleton)
    times, local, plan = retarget_pose(walker, walker.clips[0], walker, mapping, root="in-place", fps=30)
    hips = positions(walker.skeleton, local)[:, plan.root]
    rest = walker.skeleton.rest_globals()[plan.root, :3, 3]
    assert np.abs(hips[:, [0, 2]] - rest[[0, 2]]).max() < 1e-12
    assert np.ptp(hips[:, 1]) > 0.01                        # vertical motion stays


@needs_data
@pytest.mark.parametrize("name", ["Mannequin", "Ely"])
def test_cmu_onto_gltf_characters(cmu, gltf_targets, name):
    target = gltf_targets[name]
    clip = cmu.clips[0]
    mapping = joint_map(cmu.skeleton, target.skeleton)
    times, local, plan = retarget_pose(cmu, clip, target, mapping, fps=30)
    assert np.isfinite(local.rotation).all() and np.isfinite(local.translation).all()
    errs = bone_errors(cmu, clip, target, mapping, times, local)
    assert len(errs) == 17
    aligned = np.stack([e[1] for e in errs.values()])      # (bones, frames)
    raw = {k: (float(v[0].mean()), float(v[0].max())) for k, v in errs.items()}
    print(f"\n{name}: {len(errs)} mapped bones, after rest alignment mean {aligned.mean():.4f} deg, "
          f"worst {aligned.max():.4f} deg; raw (mean, max) per bone: "
          + ", ".join(f"{k.replace('mixamorig:', '')} {a:.2f}/{b:.2f}" for k, (a, b) in raw.items()))
    assert aligned.mean() <= 2.0 and aligned.max() <= 10.0
    # chain bones (one bone from the joint) follow the source's raw world direction
    chain = [v[0] for k, v in errs.items() if "Hips->" not in k]
    assert np.concatenate(chain).max() <= 0.01
    # target bone lengths never change
    skel = target.skeleton
    pt = positions(skel, local)
    rest = skel.rest_globals()[:, :3, 3]
    child = np.flatnonzero(skel.parents >= 0)
    lengths = np.linalg.norm(pt[:, child] - pt[:, skel.parents[child]], axis=-1)
    rest_lengths = np.linalg.norm(rest[child] - rest[skel.parents[child]], axis=-1)
    assert np.abs(lengths - rest_lengths).max() <= 1e-6 * np.ptp(rest[:, 1])   # file scales are 1 ± 4e-7
    # feet: lowest point of each foot against the source's, scaled to the target
    Gs = cmu.skeleton.forward_kinematics(clip.sample(times))
    Gt = skel.forward_kinematics(local)
    report = []
    for fs, ft in plan.feet:
        err = sole_heights(skel, Gt, [ft]) - plan.scale * sole_heights(cmu.skeleton, Gs, [fs])
        report.append((skel.names[ft[0]], np.abs(err).mean(), np.abs(err).max()))
        assert np.abs(err).mean() <= 0.05 and np.abs(err).max() <= 0.15
    print(f"{name}: root scale {plan.scale:.4f}, lift {plan.lift:+.4f} m; sole height error "
          + ", ".join(f"{n.replace('mixamorig:', '')} mean {a * 100:.1f} cm max {b * 100:.1f} cm" for n, a, b in report))


# --------------------------------------------------------------------------- files and CLI

def test_bvh_writer_round_trip(walker, tmp_path):
    clip = walker.clips[0]
    copy = copy_skeleton(walker.skeleton, walker.skeleton.names, 1.0, seed=5)   # non-identity rest frames
    mapping = joint_map(walker.skeleton, copy)
    _, local, plan = retarget_pose(walker, clip, Character(copy), mapping, root="keep", fps=30)
    out = tmp_path / "copy.bvh"
    write_bvh(out, copy, local, 1 / 30, position_joints=[plan.root])
    skel, back = read_bvh(out)
    assert skel.names == copy.names
    T = np.arange(len(local.rotation)) / 30
    got, want = positions(skel, back.sample(T)), positions(copy, local)
    assert np.abs(got - want).max() <= 1e-5
    assert np.abs(got - positions(walker.skeleton, clip.sample(T))).max() <= 1e-5


@needs_data
def test_cli_glb_output_plays_the_clip_and_keeps_the_file(cmu, gltf_targets, tmp_path, capsys):
    target = DATA / "gltf" / "Ely.glb"
    out, png = tmp_path / "ely_131.glb", tmp_path / "sheet.png"
    code, stdout, err = run(["retarget", BVH, target, "-o", out, "--png", png, "--fps", 24], capsys)
    assert code == 0, err
    assert "animation '131_03'" in stdout and png.stat().st_size > 10_000
    ely = gltf_targets["Ely"]
    back = load_character(out)
    assert [c.name for c in back.clips] == [c.name for c in ely.clips] + ["131_03"]
    assert back.skeleton.names == ely.skeleton.names
    for m0, m1 in zip(ely.meshes, back.meshes):
        assert np.array_equal(m0.vertices, m1.vertices) and np.array_equal(m0.faces, m1.faces)
    clip = retarget(cmu, None, ely, joint_map(cmu.skeleton, ely.skeleton), fps=24)
    T = np.linspace(0, clip.duration, 40)
    got = positions(back.skeleton, back.clip("131_03").sample(T))
    want = positions(ely.skeleton, clip.sample(T))
    assert np.abs(got - want).max() <= 1e-5
    g0 = pygltflib.GLTF2().load(str(target))
    g1 = pygltflib.GLTF2().load(str(out))
    assert len(g1.images) == len(g0.images) and len(g1.materials) == len(g0.materials)
    assert len(g1.animations) == len(g0.animations) + 1


@needs_data
def test_cli_bvh_output_in_place_and_show_map(tmp_path, capsys):
    out = tmp_path / "mannequin.bvh"
    code, stdout, err = run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "--in-place", "--show-map",
                             "-o", out], capsys)
    assert code == 0, err
    assert "mixamorig:LeftArm" in stdout and "<-  LeftShoulder" in stdout
    assert "unmapped target joints (41" in stdout
    skel, clip = read_bvh(out)
    assert skel.names[0] == "mixamorig:Hips" and clip.duration == pytest.approx(275 / 30)
    hips = positions(skel, clip.sample(np.linspace(0, clip.duration, 50)))[:, 0]
    assert np.ptp(hips[:, 0]) < 1e-5 and np.ptp(hips[:, 2]) < 1e-5


@needs_data
def test_cli_show_map_alone(capsys):
    code, stdout, err = run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "--show-map"], capsys)
    assert code == 0 and "joint map (target <- source): 24 of 65" in stdout


def _assert_clean_failure(code, err, tmp_path, pattern):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nrpose: error:") and pattern in lines[0], err
    assert not [p for p in tmp_path.iterdir() if p.suffix in (".glb", ".bvh", ".png") or p.name.startswith(".")]


@needs_data
def test_bad_map_fails_cleanly(tmp_path, capsys):
    bad = tmp_path / "map.json"
    bad.write_text(json.dumps({"mixamorig:LeftArmm": "LeftShoulder"}))
    code, _, err = run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "--map", bad, "-o",
                        tmp_path / "o.glb", "--png", tmp_path / "o.png"], capsys)
    _assert_clean_failure(code, err, tmp_path, "'mixamorig:LeftArmm' does not exist")
    bad.write_text(json.dumps({"mixamorig:LeftArm": "LeftShoulderr"}))
    code, _, err = run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "--map", bad, "-o", tmp_path / "o.bvh"],
                       capsys)
    _assert_clean_failure(code, err, tmp_path, "source joint 'LeftShoulderr'")
    bad.write_text("[1, 2]")
    code, _, err = run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "--map", bad, "-o", tmp_path / "o.bvh"],
                       capsys)
    _assert_clean_failure(code, err, tmp_path, "joint map is a JSON object")


@needs_data
def test_source_without_motion_fails_cleanly(tmp_path, capsys):
    g = pygltflib.GLTF2().load(str(DATA / "gltf" / "Mannequin.glb"))
    g.animations = []
    still = tmp_path / "still.glb"
    g.save_binary(str(still))
    code, _, err = run(["retarget", still, DATA / "gltf" / "Ely.glb", "-o", tmp_path / "o.glb"], capsys)
    still.unlink()
    _assert_clean_failure(code, err, tmp_path, "no motion")


@needs_data
def test_rigs_without_mapped_joints_fail_cleanly(walker, tmp_path, capsys):
    skel = walker.skeleton
    odd = copy_skeleton(skel, [f"bone{j}" for j in range(skel.num_joints)], 1.0, armature=False)
    src = tmp_path / "odd.bvh"
    write_bvh(src, odd, LocalPose(*(np.repeat(a[None], 3, axis=0) for a in
                                    (odd.translation, odd.rotation, odd.scale))), 1 / 30)
    code, _, err = run(["retarget", src, DATA / "gltf" / "Ely.glb", "-o", tmp_path / "o.glb"], capsys)
    src.unlink()
    _assert_clean_failure(code, err, tmp_path, "no joint of")


def test_bad_options_fail_cleanly(tmp_path, capsys):
    code, _, err = run(["retarget", tmp_path / "a.bvh", tmp_path / "b.glb", "-o", tmp_path / "o.obj"], capsys)
    _assert_clean_failure(code, err, tmp_path, "the output must end in .glb, .bvh")
    code, _, err = run(["retarget", tmp_path / "a.bvh", tmp_path / "b.glb"], capsys)
    _assert_clean_failure(code, err, tmp_path, "give -o")
    code, _, err = run(["retarget", tmp_path / "a.bvh", tmp_path / "b.glb", "-o", tmp_path / "o.glb"], capsys)
    _assert_clean_failure(code, err, tmp_path, "no such file")


@needs_data
def test_gltf_source_clip_and_gltf_target_with_external_buffer(tmp_path, capsys):
    g = pygltflib.GLTF2().load(str(DATA / "gltf" / "Mannequin.glb"))
    (tmp_path / "mq.bin").write_bytes(g.binary_blob())
    g.buffers[0].uri = "mq.bin"
    g._glb_data = None
    g.save_json(str(tmp_path / "mq.gltf"))
    out = tmp_path / "out.glb"
    clip = "Armature|mixamo.com|Layer0"
    code, stdout, err = run(["retarget", DATA / "gltf" / "Ely.glb", tmp_path / "mq.gltf", "--source-clip", clip,
                             "-o", out], capsys)
    assert code == 0, err
    back = load_character(out)                              # self-contained: the .bin was copied in
    assert [c.name for c in back.clips] == [clip, f"{clip} (2)"]
    original = load_character(DATA / "gltf" / "Mannequin.glb")
    assert np.array_equal(back.meshes[0].vertices, original.meshes[0].vertices)
    code, _, err = run(["retarget", DATA / "gltf" / "Ely.glb", tmp_path / "mq.gltf", "--source-clip", "walk",
                        "-o", tmp_path / "o2.glb"], capsys)
    assert code == 2 and "no clip 'walk'" in err and not (tmp_path / "o2.glb").exists()


# --------------------------------------------------------------------------- complete clips for engines

FOX_MAP = {"b_Hip_01": "Hips", "b_Spine01_02": "lowerback", "b_Spine02_03": "Chest", "b_Neck_04": "Neck",
           "b_Head_05": "Head", "b_RightUpperArm_06": "RightShoulder", "b_RightForeArm_07": "RightElbow",
           "b_RightHand_08": "RightWrist", "b_LeftUpperArm_09": "LeftShoulder", "b_LeftForeArm_010": "LeftElbow",
           "b_LeftHand_011": "LeftWrist"}


def test_every_target_joint_is_keyed_unmapped_ones_at_rest(walker):
    skel = walker.skeleton
    mapping = {n: s for n, s in joint_map(skel, skel).items() if "Left" not in n}    # the left side unmapped
    clip = retarget(walker, None, walker, mapping, force=True)
    keyed = {(t.joint, t.path) for t in clip.tracks}
    assert keyed == {(j, p) for j in range(skel.num_joints) for p in ("translation", "rotation", "scale")}
    times = np.linspace(0, clip.duration, 7)
    pose = clip.sample(times)
    rest = skel.rest_pose
    for j, name in enumerate(skel.names):
        assert np.allclose(pose.scale[:, j], rest.scale[j], atol=0)
        if name not in mapping:
            assert np.allclose(pose.rotation[:, j], rest.rotation[j], atol=1e-15)
            assert np.allclose(pose.translation[:, j], rest.translation[j], atol=1e-15)
            track = next(t for t in clip.tracks if t.joint == j and t.path == "rotation")
            assert np.array_equal(track.times, [0.0, clip.duration])      # two keys: start and end
    moving = [t for t in clip.tracks if len(t.times) > 2]
    assert {t.joint for t in moving if t.path == "rotation"} == {skel.index(n) for n in mapping}


def test_root_modes(walker):
    mapping = joint_map(walker.skeleton, walker.skeleton)
    clip = walker.clips[0]
    out = {root: retarget_pose(walker, clip, walker, mapping, root=root) for root in ("origin", "keep", "in-place")}
    hips = {root: positions(walker.skeleton, local)[:, plan.root] for root, (_, local, plan) in out.items()}
    assert np.abs(hips["origin"][0, [0, 2]]).max() < 1e-12                 # starts above the origin
    shift = hips["keep"] - hips["origin"]
    assert np.abs(shift - shift[0]).max() < 1e-12 and abs(shift[0, 1]) < 1e-12   # a constant horizontal shift
    assert np.array_equal(out["origin"][1].rotation, out["keep"][1].rotation)    # heading kept
    assert np.ptp(hips["in-place"][:, [0, 2]], axis=0).max() < 1e-12
    with pytest.raises(InputError, match="root must be one of"):
        retarget_pose(walker, clip, walker, mapping, root="centre")


@needs_data
def test_coverage_accepts_humanoids_and_refuses_a_human_on_the_fox(cmu, gltf_targets):
    from nrpose.pose.retarget import MAX_PART_AT_REST, MIN_COVERAGE, check_coverage, coverage
    for name, target in gltf_targets.items():
        cov = check_coverage(target.skeleton, joint_map(cmu.skeleton, target.skeleton))
        print(f"\n{name}: {len(cov.mapped)} of {target.skeleton.num_joints} joints mapped, "
              f"{100 * cov.fraction:.1f}% of the bone length; largest part at rest {cov.missing[0]}")
        assert cov.fraction >= 0.8 and cov.missing[0][2] < 0.02
        assert all("Hand" in n or "_End" in n or "Eye" in n for n, _, _ in cov.missing)   # fingers, ends, eyes
    fox = load_character(DATA / "gltf" / "Fox.glb")
    mapping = joint_map(cmu.skeleton, fox.skeleton, FOX_MAP)
    cov = coverage(fox.skeleton, mapping)
    print(f"Fox: {len(cov.mapped)} mapped, {100 * cov.fraction:.1f}%, at rest {cov.missing}")
    assert len(cov.mapped) == 11 and cov.fraction < MIN_COVERAGE
    assert {n for n, _, _ in cov.missing} == {"b_LeftLeg01_015", "b_RightLeg01_019", "b_Tail01_012"}
    assert max(f for _, _, f in cov.missing) > MAX_PART_AT_REST
    with pytest.raises(InputError, match="covers too little"):
        retarget(cmu, None, fox, mapping)
    # with the hind legs mapped onto the human legs (tail still at rest) the fraction passes
    legs = {"b_LeftLeg01_015": "LeftHip", "b_LeftLeg02_016": "LeftKnee", "b_LeftFoot01_017": "LeftAnkle",
            "b_RightLeg01_019": "RightHip", "b_RightLeg02_020": "RightKnee", "b_RightFoot01_021": "RightAnkle"}
    fuller = coverage(fox.skeleton, joint_map(cmu.skeleton, fox.skeleton, {**FOX_MAP, **legs}))
    assert fuller.fraction > MIN_COVERAGE


@needs_data
def test_cli_refuses_a_poor_fit_unless_forced(tmp_path, capsys):
    fox_map = tmp_path / "fox.json"
    fox_map.write_text(json.dumps(FOX_MAP))
    args = ["retarget", BVH, DATA / "gltf" / "Fox.glb", "--map", fox_map, "-o", tmp_path / "fox.glb"]
    code, _, err = run(args, capsys)
    _assert_clean_failure(code, err, tmp_path, "covers too little of the target skeleton")
    assert "11 of 24 joints mapped (b_Hip_01," in err and "b_LeftLeg01_015 (4 joints" in err
    assert "b_Tail01_012 (3 joints" in err and "--force" in err and "--map MAP.json" in err
    code, stdout, err = run(args + ["--force"], capsys)
    assert code == 0 and "11 of 24 target joints mapped (61% of its bone length)" in stdout, err
    code, _, err = run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "--in-place", "--root", "keep",
                        "-o", tmp_path / "m.glb"], capsys)
    assert code == 2 and "--in-place and --root keep contradict" in err


@needs_data
def test_cli_glb_keys_every_joint_node_and_frames_the_motion(tmp_path, capsys):
    out = tmp_path / "mq.glb"
    code, stdout, err = run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "-o", out], capsys)
    assert code == 0, err
    g = pygltflib.GLTF2().load(str(out))
    anim = g.animations[-1]
    back = load_character(out)
    from nrpose.io.gltf_read import joint_nodes, read_document
    _, nodes = joint_nodes(out, *read_document(out))
    targets = {(c.target.node, c.target.path) for c in anim.channels}
    assert targets == {(int(n), p) for n in nodes for p in ("translation", "rotation", "scale")}
    # the clip ends on the source's last key
    clip = back.clip("131_03")
    assert clip.duration == pytest.approx(load_character(BVH).clips[0].duration, abs=1e-6)
    assert len(clip.tracks[0].times) in (2, 277) and max(len(t.times) for t in clip.tracks) == 277
    # the skinned mesh node's culling sphere (its POSITION bounds times its world matrix) holds every frame
    from nrpose.io.gltf_read import node_globals
    from nrpose.pose.poser import CharacterPoser
    _, world = node_globals(out, g)
    node = next(i for i, n in enumerate(g.nodes) if n.skin is not None)
    acc = g.accessors[g.meshes[g.nodes[node].mesh].primitives[0].attributes.POSITION]
    lo, hi = np.array(acc.min), np.array(acc.max)
    centre = world[node] @ np.r_[(lo + hi) / 2, 1.0]
    radius = np.linalg.norm(hi - lo) / 2 * np.linalg.norm(world[node][:3, 0])
    T = np.linspace(0, clip.duration, 24)
    posed = CharacterPoser(back, method="lbs", backend="numpy").pose(clip.sample(T)).positions
    assert np.linalg.norm(posed - centre[:3], axis=-1).max() <= radius
    # and that sphere is no more than needed: within 2x the sphere around the motion
    motion = posed.reshape(-1, 3)
    assert radius <= np.linalg.norm(np.ptp(motion, axis=0))


@needs_data
def test_retarget_then_pose_every_key(tmp_path, capsys):
    out = tmp_path / "mq.glb"
    assert run(["retarget", BVH, DATA / "gltf" / "Mannequin.glb", "-o", out], capsys)[0] == 0
    clip = load_character(out).clip("131_03")
    keys = np.unique(np.concatenate([t.times for t in clip.tracks]))
    frames = tmp_path / "all.npz"
    code, _, err = run(["pose", out, "--clip", "131_03", "--method", "lbs", "-o", frames], capsys)
    assert code == 0, err
    with np.load(frames) as z:
        # every key (the file's float32 times), the last one included exactly
        assert np.array_equal(z["times"].astype(np.float32), keys.astype(np.float32)) and z["times"][-1] == keys[-1]
        assert np.isfinite(z["positions"]).all() and len(z["positions"]) == len(keys) == 277
        last = z["positions"][-1]
    n = len(keys) - 2                                             # the last grid frame
    code, _, err = run(["pose", out, "--clip", "131_03", "--method", "lbs", "--frames", f"{n - 1}:{n}",
                        "-o", tmp_path / "grid.npz"], capsys)
    assert code == 0, err
    code, _, err = run(["pose", out, "--clip", "131_03", "--method", "lbs", "--time", repr(float(keys[-1])),
                        "-o", tmp_path / "end.npz"], capsys)
    assert code == 0, err
    with np.load(tmp_path / "end.npz") as z:
        assert np.abs(z["positions"][0] - last).max() == 0
    code, _, err = run(["pose", out, "--clip", "131_03", "--method", "lbs", "--frames", f"0:{n + 1}",
                        "-o", tmp_path / "past.npz"], capsys)
    assert code == 2 and "outside" in err


@pytest.mark.parametrize("parent_scale, moved", [([0.01, 0.01, 0.01], True), ([1.0, 2.0, 1.0], False)])
def test_fit_skinned_nodes_maps_the_culling_sphere_onto_the_bounds(parent_scale, moved):
    from nrpose.io.gltf_read import node_globals
    from nrpose.io.gltf_write import fit_skinned_nodes
    g = pygltflib.GLTF2(
        nodes=[pygltflib.Node(children=[1], rotation=[0.7071068, 0, 0, 0.7071068], scale=parent_scale,
                              translation=[0.5, 0, 0]),
               pygltflib.Node(mesh=0, skin=0), pygltflib.Node(mesh=0)],
        meshes=[pygltflib.Mesh(primitives=[pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=0))])],
        accessors=[pygltflib.Accessor(count=3, componentType=pygltflib.FLOAT, type="VEC3",
                                      min=[-1.0, 0.0, -0.2], max=[1.0, 1.8, 0.2])],
        skins=[pygltflib.Skin(joints=[0])])
    lo, hi = np.array([-2.0, -0.1, -3.0]), np.array([1.5, 1.9, 0.5])
    fit_skinned_nodes("doc.gltf", g, (lo, hi))
    assert g.nodes[2].translation is None and g.nodes[2].scale is None      # not skinned: untouched
    _, world = node_globals("doc.gltf", g)
    if not moved:                                                           # a sheared frame: left alone
        assert g.nodes[1].translation is None and g.nodes[1].scale is None
        return
    box_lo, box_hi = np.array([-1.0, 0.0, -0.2]), np.array([1.0, 1.8, 0.2])
    centre = world[1] @ np.r_[(box_lo + box_hi) / 2, 1.0]
    radius = np.linalg.norm(box_hi - box_lo) / 2 * np.linalg.norm(world[1][:3, 0])
    assert np.allclose(centre[:3], (lo + hi) / 2, atol=1e-9)
    assert radius == pytest.approx(np.linalg.norm(hi - lo) / 2, rel=1e-9)


@needs_data
def test_matrix_joint_nodes_become_trs_when_animated(tmp_path, capsys):
    g = pygltflib.GLTF2().load(str(DATA / "gltf" / "Mannequin.glb"))
    k = g.skins[0].joints[5]
    node = g.nodes[k]
    t = np.array(node.translation or [0, 0, 0])
    q = np.array(node.rotation or [0, 0, 0, 1])
    M = np.eye(4)
    M[:3, :3] = Rotation.from_quat(q).as_matrix()
    M[:3, 3] = t
    node.matrix, node.translation, node.rotation, node.scale = M.T.reshape(-1).tolist(), None, None, None
    src = tmp_path / "matrix.glb"
    g.save_binary(str(src))
    out = tmp_path / "out.glb"
    assert run(["retarget", BVH, src, "-o", out], capsys)[0] == 0
    back = pygltflib.GLTF2().load(str(out))
    assert back.nodes[k].matrix is None
    assert np.allclose(back.nodes[k].translation, t, atol=1e-6) and abs(np.dot(back.nodes[k].rotation, q)) > 1 - 1e-9
    assert any(c.target.node == k for c in back.animations[-1].channels)
