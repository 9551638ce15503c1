"""What ``nrpose pose`` imports: only what the command uses.

A plain glTF pose (authored weights, every method) runs in a fresh interpreter and reports
``sys.modules`` after :func:`nrpose.cli.main`; plotting, mesh-processing and graph libraries
must not be among them, nor the glTF writer's library (pygltflib) for an ``.npz`` output, nor
the readers of other files (BVH, TGF and meshes, libigl's DMAT), nor, for the skinning methods,
NR-MLS's modules (its blend and deformer; with the bind cached, the bone weights too). The
rotation helpers that replaced scipy on the posing path are checked against scipy here too.
"""
from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
FOX = ROOT.parent / "shared" / "data" / "gltf" / "Fox.glb"
HEAVY = ("matplotlib", "pymeshlab", "igl", "scipy.spatial")
#: what an .npz output does not need: the glTF writer (and its library) and the contact sheet
NOT_FOR_NPZ = ("pygltflib", "nrpose.io.gltf_write", "nrpose.render")
#: what a glTF character with its own clip does not need: the readers of other files
NOT_FOR_GLTF_CLIP = ("nrpose.io.bvh_read", "nrpose.io.tgf")
#: what the skinning methods (lbs, dqs) do not need: NR-MLS's blend and deformer...
NOT_FOR_SKINNING = ("nrpose.pose.blend", "nrpose.pose.mls")
#: ... and, their bind cached, the bone weights (a cold authored bind takes its joint weights there)
NOT_FOR_CACHED_SKINNING = NOT_FOR_SKINNING + ("nrpose.bind.bone_weights", "nrpose.bind.distances",
                                              "nrpose.bind.weights", "nrpose.model.deformation_metrics")

PROBE = """
import json, sys
from nrpose.cli import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "modules": sorted(sys.modules)}))
"""


def among(mods, names) -> list:
    """The modules of ``mods`` that are one of ``names`` or inside one of them."""
    return sorted(m for m in mods if any(m == n or m.startswith(n + ".") for n in names))


def modules_after(args, tmp_path) -> set:
    env = {"NRPOSE_CACHE_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    r = subprocess.run([sys.executable, "-c", PROBE, *map(str, args)], capture_output=True, text=True,
                       cwd=ROOT, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads(r.stdout.strip().splitlines()[-1])
    assert doc["code"] == 0, r.stderr[-2000:]
    return set(doc["modules"])


@pytest.mark.parametrize("method", ["nrmls", "lbs", "dqs"])
def test_pose_imports_no_heavy_library(method, tmp_path):
    if not FOX.exists():
        pytest.skip(f"shared data not found at {FOX}")
    pytest.importorskip("pyopencl")
    args = ["pose", FOX, "--clip", "Run", "--time", "0", "0.4", "--method", method, "-o", tmp_path / "out.npz"]
    mods = modules_after(args, tmp_path)
    assert "nrpose.pose.poser" in mods and "pyopencl" in mods          # the probe saw the real job
    skinning = method != "nrmls"
    assert not among(mods, HEAVY + NOT_FOR_NPZ + NOT_FOR_GLTF_CLIP + (NOT_FOR_SKINNING if skinning else ()))
    assert skinning or "nrpose.pose.mls" in mods                        # the NR-MLS job does import it
    others = sorted(m for m in mods if m.startswith("nrpose.cli.") and m not in ("nrpose.cli.pose", "nrpose.cli.common"))
    assert not others, others                                           # no other command's module
    # the same job again, its bind cached: not even numpy.ma (np.median's import) on the way
    warm = modules_after(args, tmp_path)
    # nor difflib ("did you mean" hints; a cold NR-MLS bind's scipy imports it)
    assert "nrpose.pose.poser" in warm and not among(warm, ("numpy.ma", "difflib") + NOT_FOR_GLTF_CLIP)
    assert not skinning or not among(warm, NOT_FOR_CACHED_SKINNING)


def test_glb_output_imports_its_writer(tmp_path):
    """The probe sees the writer where the output needs it (the test above is not vacuous)."""
    if not FOX.exists():
        pytest.skip(f"shared data not found at {FOX}")
    pytest.importorskip("pyopencl")
    mods = modules_after(["pose", FOX, "--clip", "Run", "--time", "0", "0.4", "--method", "lbs",
                          "-o", tmp_path / "out.glb"], tmp_path)
    assert {"pygltflib", "nrpose.io.gltf_write"} <= mods
    assert not any(m == h or m.startswith(h + ".") for m in mods for h in HEAVY)


def test_import_nrpose_is_light():
    r = subprocess.run([sys.executable, "-c", "import json, sys, nrpose; print(json.dumps(sorted(sys.modules)))"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    mods = set(json.loads(r.stdout))
    assert not any(m.startswith(("scipy", "pyopencl", "nrpose.pose", "nrpose.io")) for m in mods)
    import nrpose
    from nrpose.pose.mls import Deformer
    assert nrpose.Deformer is Deformer and "Deformer" in dir(nrpose)
    with pytest.raises(AttributeError):
        nrpose.no_such_name


def test_quat_matrices_and_matrix_quats_equal_scipy():
    from scipy.spatial.transform import Rotation

    from nrpose.model.rotation import matrix_quats, quat_matrices
    rng = np.random.default_rng(3)
    q = rng.normal(size=(500, 4)) * rng.uniform(0.1, 10, size=(500, 1))     # any length: normalised first
    np.testing.assert_allclose(quat_matrices(q), Rotation.from_quat(q).as_matrix(), rtol=0, atol=1e-15)
    m = Rotation.random(500, random_state=4).as_matrix()
    # each branch of the largest-of-diagonal-and-trace choice, and half turns (trace -1)
    m = np.concatenate([m, np.eye(3)[None], np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None],
                        np.diag([-1.0, -1, 1])[None]])
    np.testing.assert_allclose(matrix_quats(m), Rotation.from_matrix(m, assume_valid=True).as_quat(),
                               rtol=0, atol=1e-15)


def test_quat_slerp_equals_scipy_composition():
    from scipy.spatial.transform import Rotation

    from nrpose.model.rotation import quat_slerp
    rng = np.random.default_rng(5)
    q0, q1 = rng.normal(size=(400, 4)), rng.normal(size=(400, 4))
    q1[:50] = q0[:50] * 3.0                 # the same rotation: a zero step
    q1[50:100] = -q0[50:100]                # the same rotation, other sign: the shorter arc is zero
    s = rng.uniform(size=(400, 1))
    s[:10] = 0.0
    s[10:20] = 1.0
    r0 = Rotation.from_quat(q0)
    ref = (r0 * Rotation.from_rotvec(s * (r0.inv() * Rotation.from_quat(q1)).as_rotvec())).as_quat()
    np.testing.assert_allclose(quat_slerp(q0, q1, s), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3, 10, 277])
def test_median_equals_numpy(n):
    from nrpose.cli.common import median
    values = np.random.default_rng(n).normal(size=n)
    assert median(values) == np.median(values)
    assert median(list(values)) == np.median(values)
