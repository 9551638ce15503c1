"""Deformation-quality metrics on analytic cases: rigid motions, uniform scales, known bends."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrpose.model import deformation_metrics as dm
from nrpose.errors import InputError
from nrpose.rigs import cylinder


@pytest.fixture(scope="module")
def tube():
    V, F = cylinder.cylinder_mesh(rings=21, sectors=16)
    return V, F, dm.mesh_edges(F, len(V))


def rigid(rng, X):
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(size=3) * 5
    return X @ R.T + t, R, t


def test_rigid_motion_has_zero_strain_exact_volume_and_bounded_continuity(tube):
    V, F, E = tube
    rng = np.random.default_rng(1)
    P, R, t = rigid(rng, V)
    assert dm.edge_strain(V, P, E).max() < 1e-12
    assert dm.signed_volume(P, F) == pytest.approx(dm.signed_volume(V, F), rel=1e-12)
    # bone-apex cone volumes per region: exact when each apex moves with the mesh
    region = (V[F].mean(axis=1)[:, 0] > 1.0).astype(np.int64)
    apex = np.array([[0.5, 0, 0], [1.5, 0, 0]])
    ratio = dm.region_volume_ratios(V, P, F, region, apex, apex @ R.T + t)
    assert np.abs(ratio - 1).max() < 1e-12
    # a rigid displacement field differs between neighbours by (R - I) e: at most 2 |e|
    c = dm.continuity_ratio(V, P, E)
    assert c.max() <= 2 + 1e-12
    assert c.max() == pytest.approx(np.linalg.norm(R - np.eye(3), 2), rel=0.05)


def test_uniform_scale_gives_known_strain_and_volume(tube):
    V, F, E = tube
    s = 1.3
    summary = dm.strain_summary(dm.edge_strain(V, s * V, E))
    assert all(v == pytest.approx(s - 1) for v in summary.values())
    assert dm.signed_volume(s * V, F) == pytest.approx(s ** 3 * dm.signed_volume(V, F))
    apex = np.array([[1.0, 0, 0]])
    ratio = dm.region_volume_ratios(V, s * V, F, np.zeros(len(F), np.int64), apex, s * apex)
    assert ratio[0] == pytest.approx(s ** 3)


def test_cone_volumes_with_one_apex_sum_to_the_closed_volume(tube):
    V, F, _ = tube
    region = np.minimum((V[F].mean(axis=1)[:, 0] // 0.5).astype(np.int64), 3)
    apex = np.tile([[0.3, 0.05, -0.02]], (4, 1))
    assert dm.cone_volumes(V, F, region, apex).sum() == pytest.approx(dm.signed_volume(V, F))
    # with apexes on the bone, each slab's cone volume is about its share of the tube
    apex = np.array([[0.25 + 0.5 * k, 0, 0] for k in range(4)])
    vols = dm.cone_volumes(V, F, region, apex)
    assert np.allclose(vols, vols.mean(), rtol=0.2)


def test_frames_axis(tube):
    V, F, E = tube
    P = np.stack([V, 2 * V, V + 1])
    s = dm.edge_strain(V, P, E)
    assert s.shape == (3, len(E))
    assert np.allclose(s.max(axis=1), [0, 1, 0])
    assert np.allclose(dm.signed_volume(P, F), dm.signed_volume(V, F) * np.array([1, 8, 1]))


def test_continuity_sees_a_jump():
    x = np.linspace(0, 1, 1001)
    V = np.stack([x, 0 * x, 0 * x], 1)
    P = V.copy()
    P[x > 0.5, 1] += 0.01                       # a 0.01 step between points 0.001 apart
    pairs = np.stack([np.arange(1000), np.arange(1, 1001)], 1)
    assert dm.continuity_ratio(V, P, pairs).max() == pytest.approx(10.0)
    assert dm.continuity_ratio(V, V + [0, 0.01, 0], pairs).max() < 1e-12


def test_weight_groups_and_rigidity(tube):
    V, F, E = tube
    W = np.zeros((len(V), 2))
    W[:, 0] = np.clip(2 - V[:, 0] + 0.01 * np.random.default_rng(0).random(len(V)), 0, 1)
    W[:, 1] = 1 - W[:, 0]
    W[V[:, 0] > 1.5] = [0.3, 0.7]               # a part with one shared weight set
    labels = dm.weight_groups(W)
    part = V[:, 0] > 1.5
    assert len(np.unique(labels[part])) == 1 and labels[part][0] >= 0
    # the parts move rigidly, the blended middle bends: rigidity sees 0; then the part is stretched
    P = V.copy()
    blend = (V[:, 0] > 1.0) & ~part              # where the weights vary: no group
    P[blend] *= [1.0, 1.2, 1.2]
    assert dm.group_rigidity(V, P, E, labels) < 1e-12
    P[part, 0] = 1.5 + 1.1 * (V[part, 0] - 1.5)
    assert dm.group_rigidity(V, P, E, labels) == pytest.approx(0.1, rel=1e-6)
    # vertices with weights unlike any other get no group
    assert (dm.weight_groups(np.random.default_rng(0).random((50, 3))) == -1).all()


def test_bone_clearance_collapse_and_bulge(tube):
    V, F, _ = tube
    bones = cylinder.BONES
    # a rigid motion of mesh and bones: ratio 1 everywhere measured
    rng = np.random.default_rng(3)
    P, R, t = rigid(rng, V)
    r = dm.bone_clearance_ratios(V, P, bones, bones @ R.T + t)
    assert np.nanmax(np.abs(r - 1)) < 1e-9 and np.isfinite(r).mean() > 0.9
    # squeeze the tube radially by half around x in [0.9, 1.1] and puff it by 1.5 near 1.8
    P = V.copy()
    mid, end = np.abs(V[:, 0] - 1.0) < 0.1, np.abs(V[:, 0] - 1.8) < 0.05
    P[mid, 1:] *= 0.5
    P[end, 1:] *= 1.5
    r = dm.bone_clearance_ratios(V, P, bones, bones)
    assert np.nanmin(r) == pytest.approx(0.5)
    assert np.nanmax(r) - 1 == pytest.approx(0.5)


def test_bad_frames_raise(tube):
    V, F, E = tube
    with pytest.raises(InputError, match="shape"):
        dm.edge_strain(V, V[:-1], E)
    with pytest.raises(InputError, match="NaN"):
        dm.continuity_ratio(V, np.full_like(V, np.nan), E)


def test_measurable_edges_drop_slivers():
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1e-16, 0], [0, 1, 0]], float)
    E = np.array([[0, 1], [1, 2], [2, 3], [0, 3]])
    assert dm.measurable_edges(V, E).tolist() == [[0, 1], [2, 3], [0, 3]]
