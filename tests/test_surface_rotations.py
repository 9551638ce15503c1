"""Neighbourhood rotations on the device (kernels/surface.cl, nrpose.pose.surface_rotations)
against their float64 reference (nrpose.model.normals.Surface.rotations), and the baked .glb's
normals made with them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrpose.model.normals import Surface, weld
from nrpose.pose.surface_rotations import FRAMES, LANES, SurfaceRotations, lane_layout, surface_rotations_for
from test_model_normals import sphere

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: float32 sums and Newton steps against float64: entries of R
TOL = 2e-5


def bent(V: np.ndarray, rng) -> np.ndarray:
    """V twisted about y, bent and moved: a smooth, non-rigid pose (N, 3)."""
    twist = Rotation.from_rotvec((0.9 * V[:, 1])[:, None] * [0, 1, 0]).as_matrix()
    W = np.einsum("nij,nj->ni", twist, V) * [1.0, 1.3, 0.8]
    return W @ Rotation.from_rotvec(rng.normal(size=3)).as_matrix().T + rng.normal(size=3)


def device_and_reference(V, F, posed):
    surface = Surface(V, F, weld(V))
    return SurfaceRotations(surface)(posed), surface.rotations(posed)


@pytest.mark.parametrize("n", [5, 12, 31])
def test_device_rotations_equal_the_reference(n):
    rng = np.random.default_rng(n)
    V, F = sphere(n)
    for posed in (bent(V, rng), V @ Rotation.random(random_state=n).as_matrix().T * 3.0):
        got, want = device_and_reference(V, F, posed)
        assert np.abs(got - want).max() < TOL
        np.testing.assert_allclose(np.linalg.det(got), 1.0, atol=1e-5)


def test_frames_in_batches_equal_the_reference():
    """More frames than one launch takes (FRAMES): each as the reference gives it."""
    rng = np.random.default_rng(5)
    V, F = sphere(10)
    surface = Surface(V, F, weld(V))
    batch = np.stack([bent(V, rng) for _ in range(FRAMES + 5)])
    got = SurfaceRotations(surface)(batch)
    assert got.shape == (len(batch), len(V), 3, 3)
    assert np.abs(got - surface.rotations(batch)).max() < TOL


def test_rigid_motion_gives_its_rotation_at_any_scale_and_place():
    V, F = sphere(9)
    R = Rotation.from_rotvec([0.4, -1.9, 0.7]).as_matrix()
    for scale, offset in ((1e-3, 5.0), (1.0, 5.0), (1e3, 5.0), (1e12, 1.0), (1e-12, 1.0), (1.0, 1e6)):
        got, _ = device_and_reference(V * scale, F, (V * scale) @ R.T + offset * scale)
        assert np.abs(got - R).max() < TOL
    rng = np.random.default_rng(9)
    got, want = device_and_reference(V * 1e15, F, bent(V, rng) * 1e15)
    assert np.abs(got - want).max() < TOL


def test_adversarial_neighbourhoods_match_the_reference():
    """Zero-area faces, a vertex in no face, a collapsed frame, a mirrored (det < 0) and a
    flattened neighbourhood: the kernel leaves what it cannot finish to the host, which
    finishes it as the reference does."""
    rng = np.random.default_rng(3)
    V, F = sphere(8)
    V = np.vstack([V, [[5.0, 5.0, 5.0]]])                    # in no face
    F = np.vstack([F, [[0, 0, 1]], [[2, 2, 2]]])               # zero-area faces
    surface = Surface(V, F, weld(V))
    dev = SurfaceRotations(surface)
    mirrored = V * [-1.0, 1.0, 1.0]
    flat = V * [1.0, 1e-7, 1.0]
    for posed in (bent(V, rng), mirrored, flat, np.zeros_like(V), V + rng.normal(scale=0.3, size=V.shape)):
        got, want = dev(posed), surface.rotations(posed)
        assert np.isfinite(got).all()
        np.testing.assert_allclose(np.linalg.det(got), 1.0, atol=1e-5)
        assert np.abs(got - want).max() < 1e-3
        well = np.linalg.svd(_sums(surface, posed), compute_uv=False)
        conditioned = (well[:, 2] > 1e-2 * well[:, 0])[surface.groups]
        assert np.abs(got - want)[conditioned].max(initial=0.0) < TOL
    assert np.abs(dev(np.zeros_like(V)) - np.eye(3)).max() == 0.0        # a zero sum: the identity
    assert np.abs(dev(V)[-1] - np.eye(3)).max() == 0.0                   # in no face: the identity


def _sums(surface: Surface, posed: np.ndarray) -> np.ndarray:
    """Each group's sum matrix (G, 3, 3) of b^T B over its faces' edge frames (e1, e2, e2 - e1,
    n / sqrt|n|), formed here as Surface.rotations describes it."""
    V = posed[surface.faces]
    e1, e2 = V[:, 1] - V[:, 0], V[:, 2] - V[:, 0]
    n = np.cross(e1, e2)
    n = n / np.sqrt(np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300))
    b = np.stack([e1, e2, e2 - e1, n], axis=1)
    per_face = np.matmul(b.transpose(0, 2, 1), surface.bind_frames).reshape(-1, 9)
    sums = np.zeros((surface.n_groups, 9))
    np.add.at(sums, np.repeat(np.arange(surface.n_groups), np.diff(surface.group_starts)), per_face[surface.corner_faces])
    return sums.reshape(-1, 3, 3)


def test_a_surface_without_faces_turns_nothing():
    V = np.random.default_rng(2).normal(size=(11, 3))
    for F in (np.zeros((0, 3), np.int64), np.array([[0, 1, 2]])):
        got, want = device_and_reference(V, F, V * 2.0 + 1.0)
        assert np.abs(got - want).max() < TOL
        assert (got[3:] == np.eye(3)).all()


def test_lane_layout_gives_each_group_its_faces():
    V, F = sphere(7)
    surface = Surface(V, F, weld(V))
    starts, slots, rows = lane_layout(surface)
    assert rows.shape[1] == LANES and (np.sort(rows.reshape(-1))[:surface.n_groups] == np.arange(surface.n_groups)).all()
    for c, chunk in enumerate(rows):
        for lane, g in enumerate(chunk):
            faces = slots[starts[c]:starts[c + 1], lane]
            if g == surface.n_groups:
                assert (faces == len(F)).all()
            else:
                want = surface.corner_faces[surface.group_starts[g]:surface.group_starts[g + 1]]
                assert sorted(faces[faces < len(F)]) == sorted(want) and (faces[len(want):] == len(F)).all()


def test_large_bakes_go_to_the_device():
    assert surface_rotations_for(15882, 277) is SurfaceRotations
    assert surface_rotations_for(1728, 36) is None
    assert surface_rotations_for(15882, 277, "numpy") is None


@pytest.mark.skipif(not (DATA / "gltf" / "Fox.glb").exists(), reason="needs ../shared/data (Fox.glb)")
def test_baked_glb_normals_on_the_device_equal_the_reference(tmp_path):
    from nrpose.io import load_character
    from nrpose.io.gltf_read import read_accessor
    from nrpose.io.gltf_write import write_animated_glb
    from nrpose.pose.poser import CharacterPoser
    import pygltflib

    fox = DATA / "gltf" / "Fox.glb"
    character = load_character(fox)
    clip = character.clip("Run")
    times = np.linspace(0, clip.duration, 6)
    frames = CharacterPoser(character, method="lbs").pose(clip.sample(times))
    written = {}
    for name, rotations in (("device", SurfaceRotations), ("reference", None)):
        out = tmp_path / f"{name}.glb"
        write_animated_glb(out, character, frames.positions, times, frames.mesh_offsets, source=fox,
                           rotations=rotations)
        gltf = pygltflib.GLTF2().load(str(out))
        buffers = [gltf.binary_blob()]
        written[name] = [read_accessor(out, gltf, buffers, t["NORMAL"])
                         for p in gltf.meshes[-1].primitives for t in p.targets]
    assert len(written["device"]) == len(times)
    for a, b in zip(written["device"], written["reference"]):
        assert np.abs(a - b).max() < 1e-4
