"""LBS / DQS kernels against the float64 numpy references, plus properties and input errors."""
from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest
from launches import relaunch, splits, standing_workers_or_skip
from scipy.spatial.transform import Rotation

from nrpose import diagnostics
from nrpose.errors import InputError
from nrpose.model.rotation import quat_multiply
from nrpose.pose.skinning import (DqsSkinner, LbsSkinner, Skinner, dqs_reference,
                             dqs_reference_dq, dual_quaternions, lbs_reference)


# --------------------------------------------------------------------------- helpers

def make_rig(rng, n, j, k, pad=True):
    rest = rng.normal(size=(n, 3)) * np.array([0.3, 1.0, 0.2]) + np.array([0.1, 0.9, 0.0])
    joints = rng.integers(0, j, size=(n, k))
    weights = rng.random((n, k)) + 0.05
    if pad and k > 1:  # some padding entries: weight 0, joint -1 (ignored)
        drop = rng.random((n, k)) < 0.3
        drop[:, 0] = False
        weights[drop] = 0.0
        joints[drop] = -1
    return rest, joints, weights


def rigid(rng, j, scale=1.0):
    m = np.tile(np.eye(4), (j, 1, 1))
    m[:, :3, :3] = Rotation.random(j, random_state=rng).as_matrix()
    m[:, :3, 3] = rng.normal(size=(j, 3)) * scale
    return m


def affine(rng, j):
    m = rigid(rng, j)
    m[:, :3, :3] = m[:, :3, :3] @ (np.eye(3) + 0.3 * rng.normal(size=(j, 3, 3)))
    return m


def rotation_about(center, rotvec):
    m = np.eye(4)
    r = Rotation.from_rotvec(rotvec).as_matrix()
    m[:3, :3] = r
    m[:3, 3] = center - r @ center
    return m


def diag(x):
    return float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))


def assert_close(got, want, rel=1e-5):
    tol = rel * max(diag(want.reshape(-1, 3)), 1e-12)
    err = np.abs(got - want).max()
    assert err <= tol, f"max error {err:.3g} > {tol:.3g} (1e-5 of bbox diagonal)"


# --------------------------------------------------------------------------- kernel vs reference

@pytest.mark.parametrize("k", [1, 4, 8])
@pytest.mark.parametrize("n", [13, 1001])
def test_lbs_matches_reference(k, n):
    rng = np.random.default_rng(100 * k + n)
    rest, joints, weights = make_rig(rng, n, 17, k)
    d = LbsSkinner(rest, joints, weights)
    for mats in (rigid(rng, 17), affine(rng, 17)):
        got = d.pose(mats)
        assert got.shape == (n, 3) and got.dtype == np.float64
        assert_close(got, lbs_reference(rest, joints, weights, mats))


@pytest.mark.parametrize("k", [1, 4, 8])
@pytest.mark.parametrize("n", [13, 1001])
def test_dqs_matches_reference(k, n):
    rng = np.random.default_rng(200 * k + n)
    rest, joints, weights = make_rig(rng, n, 17, k)
    d = DqsSkinner(rest, joints, weights)
    for _ in range(2):
        mats = rigid(rng, 17)
        got = d.pose(mats)
        assert got.shape == (n, 3) and got.dtype == np.float64
        assert_close(got, dqs_reference(rest, joints, weights, mats))


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_pose_frames_matches_pose(method):
    rng = np.random.default_rng(5)
    rest, joints, weights = make_rig(rng, 203, 9, 4)
    d = Skinner(rest, joints, weights, method=method)
    frames = np.stack([rigid(rng, 9) for _ in range(5)])
    got = d.pose_frames(frames)
    assert got.shape == (5, 203, 3)
    ref = lbs_reference if method == "lbs" else dqs_reference
    for f in range(5):
        assert_close(got[f], ref(rest, joints, weights, frames[f]))
    # a smaller batch and a single pose after a larger batch reuse the buffers
    assert_close(d.pose_frames(frames[:2])[1], ref(rest, joints, weights, frames[1]))
    assert_close(d.pose(frames[3]), ref(rest, joints, weights, frames[3]))


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_out_takes_the_posed_vertices(method):
    """out= receives what the default path returns (float32: the device's values as they
    are; float64: the same converted) and is returned itself; a wrong shape or a non-float
    array is an InputError naming the expected shape."""
    rng = np.random.default_rng(6)
    rest, joints, weights = make_rig(rng, 150, 7, 4)
    d = Skinner(rest, joints, weights, method=method)
    frames = np.stack([rigid(rng, 7) for _ in range(3)])
    want = d.pose_frames(frames)
    for dtype in (np.float32, np.float64):
        out = np.full((3, 150, 3), np.nan, dtype)
        assert d.pose_frames(frames, out=out) is out
        assert np.array_equal(out, want.astype(dtype))
        one = np.full((150, 3), np.nan, dtype)
        assert d.pose(frames[1], out=one) is one and np.array_equal(one, want[1].astype(dtype))
    for bad in (np.zeros((2, 150, 3)), np.zeros((3, 150, 3), np.int32)):
        with pytest.raises(InputError, match=r"out: expected a float array of shape \(3, 150, 3\)"):
            d.pose_frames(frames, out=bad)
    with pytest.raises(InputError, match=r"out: expected a float array of shape \(150, 3\)"):
        d.pose(frames[0], out=np.zeros((3, 150)))


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_pose_frames_into_frames_array_directly(method):
    """pose_frames(out=) into a frames_array, or a run of its frames, is written by the
    kernel itself (its output bound at that frame): the same float32 values as a plain
    out, the frames around the run untouched; single poses and plain batches between
    such launches land where they should (the output bound back); a read-only view is
    refused; on the buffer path (no shared memory) a frames_array is a plain array."""
    from nrpose import device

    rng = np.random.default_rng(12)
    rest, joints, weights = make_rig(rng, 203, 9, 4)          # 203: a padded last group
    d = Skinner(rest, joints, weights, method=method)
    mats = np.stack([rigid(rng, 9) for _ in range(6)])
    want = np.empty((6, 203, 3), np.float32)
    d.pose_frames(mats, out=want)
    frames = d.frames_array(9)
    assert frames.shape == (9, 203, 3) and frames.dtype == np.float32
    assert device.fine_grain_svm() == (device.frames_in(frames, 3 * 8 * d.n_groups) is not None)
    frames[...] = -7.0
    run = frames[2:5]
    d._out.host[:] = np.nan                   # the deformer's own output: not written, nothing copied
    assert d.pose_frames(mats[:3], out=run) is run
    assert np.array_equal(frames[2:5], want[:3]) and (frames[:2] == -7).all() and (frames[5:] == -7).all()
    assert np.isnan(d._out.host).all() == device.fine_grain_svm()
    frames[2:5] = 0.0                         # relaunch writes its own output, not the caller's frames
    diagnostics.relaunch(d)
    assert (frames[2:5] == 0).all()
    d._out.download()
    assert np.array_equal(d._out.host[: 3 * 3 * 8 * d.n_groups].reshape(3, -1, 3)[:, :203], want[:3])
    frames[2:5] = want[:3]
    assert np.array_equal(d.pose(mats[4]).astype(np.float32), want[4])
    d.pose_frames(mats, out=frames[3:])
    assert np.array_equal(frames[3:], want) and (frames[:2] == -7).all() and np.array_equal(frames[2], want[0])
    d.pose_frames(mats[1:2], out=frames[1:2])                  # one frame, at frame 1
    assert np.array_equal(frames[1], want[1])
    plain = np.zeros((2, 203, 3), np.float32)
    assert d.pose_frames(mats[:2], out=plain) is plain and np.array_equal(plain, want[:2])
    assert np.array_equal(frames[3:], want)                    # not written by the plain launch
    frozen = frames[:2]
    frozen.flags.writeable = False
    with pytest.raises(InputError, match="not writable"):
        d.pose_frames(mats[:2], out=frozen)
    for bad in (-1, 2.5, "3", None):
        with pytest.raises(InputError, match="frames must be a whole number"):
            d.frames_array(bad)
    fewer = Skinner(rest[:-1], joints[:-1], weights[:-1], method=method)   # the same padding
    view = frames[:2, :-1]
    assert fewer.n_groups == d.n_groups and device.frames_in(view, 3 * 8 * fewer.n_groups) is None
    frames[...] = -7.0
    assert fewer.pose_frames(mats[:2], out=view) is view and (frames[:2, -1] == -7).all()
    d._svm = False                                             # the buffer path
    plain_frames = d.frames_array(2)
    assert device.frames_in(plain_frames, 3 * 8 * d.n_groups) is None
    assert d.pose_frames(mats[:2], out=plain_frames) is plain_frames
    assert np.array_equal(plain_frames, want[:2])


def test_standing_worker_follows_the_rebound_output(monkeypatch):
    """A standing worker runs a clone of the skinning kernel; when the output argument is
    rebound (runs of a frames_array, then single poses into the deformer's own output:
    Jobs.set_argument), the clone takes it too: every frame lands where it should (the
    jobs taken from both ends, device.ENDS_MAX_BOUND_BYTES)."""
    from nrpose import device
    from nrpose.pose.skinning import BLOCK, LANES

    standing_workers_or_skip()
    monkeypatch.setattr(device.policy, "_STANDBY", [None])           # restored after the test
    device.set_standby_s(0.5)
    rng = np.random.default_rng(5)
    n = (device.STANDING_MIN_BLOCKS + 2) * BLOCK * LANES - 5
    d = LbsSkinner(*make_rig(rng, n, 9, 4))
    mats = np.stack([rigid(rng, 9) for _ in range(4)])
    want = np.stack([d.pose(m) for m in mats]).astype(np.float32)
    assert d._jobs.ends               # its bound data fits two cores' L2: taken from both ends
    stood = []
    for _ in range(3):
        for m in mats:
            d.pose(m)
            stood.append(d._jobs.standing(d._kernel))
        frames = d.frames_array(6)
        frames[...] = -7.0
        d.pose_frames(mats[:2], out=frames[1:3])
        stood.append(d._jobs.standing(d._kernel))
        d.pose_frames(mats[2:], out=frames[4:6])
        singles = [d.pose(m).astype(np.float32) for m in mats]
        stood.append(d._jobs.standing(d._kernel))
        assert np.array_equal(frames[1:3], want[:2]) and np.array_equal(frames[4:6], want[2:])
        assert (frames[[0, 3]] == -7).all() and np.array_equal(np.stack(singles), want)
    assert any(stood)          # a standing worker served some of these poses


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_shared_and_mixed_joint_groups(method):
    """Vertices are stored sorted by their joints: a group's 8 lanes that share influence
    k's joint read its parameters once (broadcast), the others gather them lane by lane.
    Both kinds of group (read back from the bound joints) against the reference, the
    results in the caller's vertex order."""
    import pyopencl as cl

    rng = np.random.default_rng(21)
    n, j, k = 203, 5, 3
    rest, joints, weights = make_rig(rng, n, j, k, pad=False)
    mats = rigid(rng, j) if method == "dqs" else affine(rng, j)
    ref = lbs_reference if method == "lbs" else dqs_reference
    d = Skinner(rest, joints, weights, method=method)
    stored = np.empty(d.n_groups * k * 8, np.int32)
    cl.enqueue_copy(d._queue, stored, d._joints)
    groups = stored.reshape(d.n_groups, k, 8)
    shared = (groups == groups[:, :, :1]).all(axis=2)          # (groups, influences)
    assert shared[:, 0].sum() >= d.n_groups // 2 and (~shared).any()
    assert_close(d.pose(mats), ref(rest, joints, weights, mats))


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_groups_of_consecutive_rows_are_stored_whole(method):
    """Vertices given in runs of one joint (as exporters leave them) are stored in groups of
    consecutive rows, bound run-coded (the first row as ~row: device.run_coded_rows, read
    back here), which the kernel stores with vector stores from any row on; mixed with
    scattered groups, against the reference, in the caller's order."""
    import pyopencl as cl

    rng = np.random.default_rng(22)
    j, k = 12, 2
    sizes = rng.integers(8, 14, 40)
    joints = np.repeat(np.stack([rng.permutation(j)[:k] for _ in sizes]), sizes, axis=0)
    n = len(joints)
    joints[rng.random(n) < 0.1, 1] = j - 1        # some runs broken up
    rest = rng.normal(size=(n, 3))
    weights = np.stack([rng.uniform(0.6, 1.0, n), rng.uniform(0.0, 0.4, n)], 1)   # influence 0 dominant
    d = Skinner(rest, joints, weights, method=method)
    rows = np.empty(d.n_groups * 8, np.int32)
    cl.enqueue_copy(d._queue, rows, d._rows)
    first = rows[::8]
    assert (first < 0).sum() >= d.n_groups // 8 and (first >= 0).any()
    runs = first < 0
    assert (~first[runs] % 8 != 0).any()                   # runs that start anywhere
    decoded = rows.reshape(-1, 8).copy()
    decoded[runs, 0] = ~first[runs]
    assert (np.diff(decoded[runs], axis=1) == 1).all()
    assert np.array_equal(np.sort(decoded.ravel()), np.arange(d.n_groups * 8))
    mats = rigid(rng, j) if method == "dqs" else affine(rng, j)
    ref = lbs_reference if method == "lbs" else dqs_reference
    assert_close(d.pose(mats), ref(rest, joints, weights, mats))


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_padded_influences_and_buffer_fallback(method):
    """K = 8 with only 2 real influences (the kernel stops early), and the
    plain-buffer path used on devices without fine-grained SVM."""
    rng = np.random.default_rng(12)
    rest, joints, weights = make_rig(rng, 99, 7, 2, pad=False)
    joints8 = np.concatenate([np.full((99, 6), -1), joints], axis=1)   # padding first
    weights8 = np.concatenate([np.zeros((99, 6)), weights], axis=1)
    ref = lbs_reference if method == "lbs" else dqs_reference
    mats = rigid(rng, 7)
    want = ref(rest, joints, weights, mats)
    assert_close(Skinner(rest, joints8, weights8, method=method).pose(mats), want)
    d = Skinner(rest, joints8, weights8, method=method)
    replaced = weakref.ref(d._jobs)
    d._svm = False
    assert_close(d.pose(mats), want)
    assert_close(d.pose_frames(np.stack([mats, mats]))[1], want)
    gc.collect()
    assert replaced() is None      # the replaced mailbox (and what it kept) is not held by d's finalizer


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_shared_launch_any_split_same_vertices(method, monkeypatch):
    """The kernel's blocks (skinning.BLOCK groups of 8 vertices) may be taken by the
    calling thread alone, by PoCL's workers alone or by both, the workers standing or
    woken for the launch (device.launch_shared):
    bitwise the same result each way for a batch of frames, equal to the reference; a
    last block that is partly filled and a padded last group included."""
    from nrpose import device
    from nrpose.pose.skinning import BLOCK, LANES

    rng = np.random.default_rng(31)
    n, j, frames = 3 * BLOCK * LANES + 5, 11, 3
    rest, joints, weights = make_rig(rng, n, j, 4)
    d = Skinner(rest, joints, weights, method=method)
    assert 0 < d._jobs.alone_s < float("inf")
    mats = np.stack([rigid(rng, j) if method == "dqs" else affine(rng, j) for _ in range(frames)])
    shared = d.pose_frames(mats)
    ref = lbs_reference if method == "lbs" else dqs_reference
    for f in range(frames):
        assert_close(shared[f], ref(rest, joints, weights, mats[f]))
    npad = d.n_groups * LANES
    want = shared.astype(np.float32)
    for name, kw in splits().items():
        d._out.host[:] = np.nan
        relaunch(d, kw, monkeypatch)
        d._out.download()
        got = d._out.host[: frames * npad * 3].reshape(frames, npad, 3)[:, :n]
        assert np.array_equal(got, want), name


def test_small_launches_stay_on_the_calling_thread(monkeypatch):
    """A bind times one frame of the kernel on the calling thread alone; launches whose
    frames take less than device.SHARE_MIN_S together run there alone (when they do not
    follow the last one within the standby time); larger ones are shared."""
    import time

    from nrpose import device

    rng = np.random.default_rng(32)
    rest, joints, weights = make_rig(rng, 40, 5, 2)
    d = LbsSkinner(rest, joints, weights)
    decided = []
    real = device.Jobs.mode
    monkeypatch.setattr(device.Jobs, "mode", lambda self, *a: decided.append(real(self, *a)) or decided[-1])
    d._jobs.alone_s = device.SHARE_MIN_S / 4
    mats = rigid(rng, 5)
    for frames in (3, 4):
        d._jobs.stop()
        d._jobs._last = time.perf_counter() - 20.0
        d.pose_frames(np.stack([mats] * frames))
    assert decided == ["alone", "woken"]


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_joint_count_change_under_a_standing_worker(method, monkeypatch):
    """A standing worker runs the kernel with the arguments it stood with: a batch with
    more (or fewer) joints than the last one, within the standby time and fitting the
    same arrays, ends it first (else its frames would be read with the old stride)."""
    from nrpose import device
    from nrpose.pose.skinning import BLOCK, LANES

    standing_workers_or_skip()
    monkeypatch.setattr(device.policy, "_STANDBY", [10.0])
    rng = np.random.default_rng(33)
    n = 8 * BLOCK * LANES
    rest, joints, weights = make_rig(rng, n, 10, 4)
    d = Skinner(rest, joints, weights, method=method)
    ref = lbs_reference if method == "lbs" else dqs_reference
    make = rigid if method == "dqs" else affine
    for count, frames in ((10, 4), (12, 3), (11, 3), (10, 2)):
        mats = np.stack([make(rng, count) for _ in range(frames)])
        diagnostics.relaunch(d, workers=True)                       # a worker stands with the last arguments
        assert d._jobs.standing(d._kernel)
        got = d.pose_frames(mats)
        for f in range(frames):
            assert_close(got[f], ref(rest, joints, weights, mats[f]))
    device.stop_standing()


def test_lbs_scale_is_honoured_dqs_ignores_it():
    rng = np.random.default_rng(6)
    rest, joints, weights = make_rig(rng, 40, 3, 2)
    mats = rigid(rng, 3)
    scaled = mats.copy()
    scaled[:, :3, :3] *= 2.0
    assert_close(DqsSkinner(rest, joints, weights).pose(scaled),
                 dqs_reference(rest, joints, weights, mats))
    one = np.zeros((40, 1), int)
    assert_close(LbsSkinner(rest, one, np.ones((40, 1))).pose(scaled),
                 rest @ scaled[0, :3, :3].T + scaled[0, :3, 3])


# --------------------------------------------------------------------------- properties

@pytest.mark.parametrize("cls", [LbsSkinner, DqsSkinner])
def test_identity_gives_rest(cls):
    rng = np.random.default_rng(1)
    rest, joints, weights = make_rig(rng, 77, 6, 4)
    eye = np.tile(np.eye(4), (6, 1, 1))
    assert_close(cls(rest, joints, weights).pose(eye), rest)
    ref = lbs_reference if cls is LbsSkinner else dqs_reference
    np.testing.assert_allclose(ref(rest, joints, weights, eye), rest, atol=1e-12)


@pytest.mark.parametrize("cls", [LbsSkinner, DqsSkinner])
def test_common_rigid_motion(cls):
    rng = np.random.default_rng(2)
    rest, joints, weights = make_rig(rng, 77, 6, 8)
    m = rigid(rng, 1)[0]
    mats = np.tile(m, (6, 1, 1))
    want = rest @ m[:3, :3].T + m[:3, 3]
    assert_close(cls(rest, joints, weights).pose(mats), want)
    ref = lbs_reference if cls is LbsSkinner else dqs_reference
    np.testing.assert_allclose(ref(rest, joints, weights, mats), want, atol=1e-12)


def test_weight_rows_are_normalised():
    rng = np.random.default_rng(3)
    rest, joints, weights = make_rig(rng, 30, 5, 4)
    mats = affine(rng, 5)
    a = LbsSkinner(rest, joints, weights).pose(mats)
    b = LbsSkinner(rest, joints, 7.0 * weights).pose(mats)
    assert_close(a, b)
    np.testing.assert_allclose(lbs_reference(rest, joints, 7.0 * weights, mats),
                               lbs_reference(rest, joints, weights, mats), atol=1e-12)


def test_dqs_rigidity_about_a_shared_centre():
    """Joints rotating about one point c: DQS keeps every |x - c| (LBS shrinks)."""
    rng = np.random.default_rng(4)
    n = 50
    c = np.array([0.2, 1.0, -0.1])
    rest = c + rng.normal(size=(n, 3))
    mats = np.stack([np.eye(4), rotation_about(c, [0.0, 2.8, 0.0]),
                     rotation_about(c, rng.normal(size=3))])
    # single joint per vertex
    single = np.full((n, 1), 1)
    got = DqsSkinner(rest, single, np.ones((n, 1))).pose(mats)
    np.testing.assert_allclose(np.linalg.norm(got - c, axis=1),
                               np.linalg.norm(rest - c, axis=1), rtol=1e-5)
    # blended between the three joints (the candy-wrapper set-up)
    joints = np.tile([0, 1, 2], (n, 1))
    weights = rng.random((n, 3))
    r0 = np.linalg.norm(rest - c, axis=1)
    got = DqsSkinner(rest, joints, weights).pose(mats)
    np.testing.assert_allclose(np.linalg.norm(got - c, axis=1), r0, rtol=1e-5)
    ref = dqs_reference(rest, joints, weights, mats)
    np.testing.assert_allclose(np.linalg.norm(ref - c, axis=1), r0, rtol=1e-12)
    lbs = np.linalg.norm(lbs_reference(rest, joints, weights, mats) - c, axis=1)
    assert np.all(lbs <= r0 + 1e-12) and np.any(lbs < 0.9 * r0)


def test_dqs_antipodal_quaternions_agree():
    rng = np.random.default_rng(8)
    rest, joints, weights = make_rig(rng, 301, 11, 4)
    dq = dual_quaternions(rigid(rng, 11))
    flipped = dq * np.where(rng.random(11) < 0.5, -1.0, 1.0)[:, None]
    flipped[0] = -dq[0]
    d = DqsSkinner(rest, joints, weights)
    a = d.pose_dual_quaternions(dq)
    b = d.pose_dual_quaternions(flipped)
    assert_close(a, b)
    ref = dqs_reference_dq(rest, joints, weights, dq)
    np.testing.assert_allclose(dqs_reference_dq(rest, joints, weights, flipped), ref, atol=1e-12)
    assert_close(a, ref)


def test_dual_quaternions_encode_the_rigid_transform():
    rng = np.random.default_rng(9)
    mats = rigid(rng, 7)
    dq = dual_quaternions(mats)
    np.testing.assert_allclose(np.linalg.norm(dq[:, :4], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(dq[:, :4] * dq[:, 4:], axis=1), 0.0, atol=1e-12)
    p = rng.normal(size=(7, 1, 3))
    one = np.zeros((1, 1), int)
    for j in range(7):
        got = dqs_reference(p[j], one, np.ones((1, 1)), mats[j:j + 1])
        np.testing.assert_allclose(got, p[j] @ mats[j, :3, :3].T + mats[j, :3, 3], atol=1e-12)


@pytest.mark.parametrize("kind", ["uniform scale", "float32 noise", "axis scale and shear"])
def test_dual_quaternions_take_the_nearest_rotation(kind):
    """Scaled (taken as is, divided by the scale), float32-noisy and sheared blocks (polar
    factor): the rotation is the nearest one (from an SVD here); the translation is kept."""
    rng = np.random.default_rng(12)
    mats = rigid(rng, 40)
    rot = mats[:, :3, :3].copy()
    if kind == "uniform scale":
        mats[:, :3, :3] = rot * rng.uniform(0.5, 2.0, (40, 1, 1))
    elif kind == "float32 noise":
        mats[:, :3, :3] = (rot + rng.normal(scale=2e-6, size=rot.shape)).astype(np.float32)
    else:
        mats[:, :3, :3] = rot @ np.diag([1.0, 1.4, 0.6]) + rng.normal(scale=0.05, size=rot.shape)
    U, _, Vt = np.linalg.svd(mats[:, :3, :3])
    nearest = U @ Vt
    dq = dual_quaternions(mats)
    got = Rotation.from_quat(dq[:, :4]).as_matrix()
    np.testing.assert_allclose(got, nearest, atol=1e-9)
    t = 2.0 * quat_multiply(dq[:, 4:], dq[:, :4] * [-1, -1, -1, 1])[:, :3]     # t = 2 qd conj(qr)
    np.testing.assert_allclose(t, mats[:, :3, 3], atol=1e-12)


# --------------------------------------------------------------------------- errors

@pytest.fixture(scope="module")
def good():
    rng = np.random.default_rng(11)
    rest, joints, weights = make_rig(rng, 10, 4, 2, pad=False)
    return rest, joints, weights


def _raises(match, fn, *args, **kw):
    with pytest.raises(InputError, match=match):
        fn(*args, **kw)


@pytest.mark.parametrize("fn", [LbsSkinner, DqsSkinner,
                                lambda r, j, w: lbs_reference(r, j, w, np.tile(np.eye(4), (4, 1, 1)))])
def test_bad_bind_inputs(fn, good):
    rest, joints, weights = good
    _raises(r"shape \(N, 3\)", fn, rest[:, :2], joints, weights)
    _raises(r"empty", fn, rest[:0], joints[:0], weights[:0])
    _raises(r"\(N, K\) = \(10, K\)", fn, rest, joints[:5], weights[:5])
    _raises(r"integers", fn, rest, joints.astype(float), weights)
    _raises(r"shape of the joint indices", fn, rest, joints, weights[:, :1])
    bad = rest.copy()
    bad[3, 1] = np.nan
    _raises(r"rest vertices: 1 of 10 rows have NaN or infinite values \(first: row 3\)", fn, bad, joints, weights)
    w = weights.copy()
    w[2, 0] = np.inf
    _raises(r"weights: 1 of 10 rows have NaN or infinite values \(first: row 2\)", fn, rest, joints, w)
    w = weights.copy()
    w[4, 1] = -0.1
    _raises(r"non-negative.*vertex 4", fn, rest, joints, w)
    w = weights.copy()
    w[[1, 6]] = 0.0
    _raises(r"2 of 10 vertices have all-zero weights \(first: vertex 1\)", fn, rest, joints, w)
    j = joints.copy()
    j[5, 0] = -2
    _raises(r"joint indices must be >= 0.*vertex 5", fn, rest, j, weights)


@pytest.mark.parametrize("cls", [LbsSkinner, DqsSkinner])
def test_bad_pose_inputs(cls, good):
    rest, joints, weights = good
    d = cls(rest, joints, weights)
    eye = np.tile(np.eye(4), (4, 1, 1))
    _raises(r"joint index 3 is out of range for 3 skinning matrices", d.pose, eye[:3])
    _raises(r"shape \(J, 4, 4\)", d.pose, eye[:, :3])
    _raises(r"shape \(F, J, 4, 4\)", d.pose_frames, eye)
    m = eye.copy()
    m[1, 0, 0] = np.nan
    _raises(r"NaN or inf", d.pose, m)
    m = eye.copy()
    m[2, 3, 0] = 0.5
    _raises(r"affine", d.pose, m)
    # still usable afterwards
    assert_close(d.pose(eye), rest)


def test_dqs_rejects_reflections_and_bad_quaternions(good):
    rest, joints, weights = good
    d = DqsSkinner(rest, joints, weights)
    m = np.tile(np.eye(4), (4, 1, 1))
    m[1, 0, 0] = -1.0
    _raises(r"non-positive determinant", d.pose, m)
    dq = np.zeros((4, 8))
    dq[:, 3] = 2.0
    _raises(r"unit real parts", d.pose_dual_quaternions, dq)
    _raises(r"method='dqs'", LbsSkinner(rest, joints, weights).pose_dual_quaternions, dq)
    _raises(r"one of \('lbs', 'dqs', 'cor'\)", Skinner, rest, joints, weights, method="slerp")
