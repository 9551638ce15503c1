"""The NR-MLS deformer (nrpose.pose.mls): PoCL kernel against the float64 reference, and the blend's properties."""
from __future__ import annotations

import time
import weakref

import numpy as np
import pytest
from launches import relaunch, splits, standing_workers_or_skip

from nrpose import Deformer, HandleError, HandleSet, InputError, Pose, device, diagnostics
from nrpose.pose.blend import deform_reference, rest_terms
from nrpose.pose import blend as blend_mod
from nrpose.rigs import cylinder
from nrpose.model.rotation import Rotation

TOL = 1e-4  # of the bounding-box diagonal, kernel vs reference


def diag(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def random_rest(rng, n_points: int, n_segments: int) -> HandleSet:
    pts = rng.uniform(-1, 1, (n_points, 3))
    a = rng.uniform(-1, 1, (n_segments, 3))
    d = rng.normal(size=(n_segments, 3))
    d *= rng.uniform(0.3, 1.0, (n_segments, 1)) / np.linalg.norm(d, axis=1, keepdims=True)
    return HandleSet.make(pts, np.stack([a, a + d], axis=1))


def random_pose(rng, rest: HandleSet, max_angle: float = np.radians(120), stretch: bool = False) -> Pose:
    """Handles moved by noise; each segment turned by a random rotation up to max_angle."""
    s = len(rest.segments)
    axes = Rotation.random(s, random_state=rng).as_rotvec() if s else np.zeros((0, 3))
    axes = axes / np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
    rots = Rotation.from_rotvec(axes * rng.uniform(0, max_angle, (s, 1)))
    start = rest.segments[:, 0] + rng.normal(scale=0.3, size=(s, 3))
    scale = rng.uniform(0.8, 1.25, (s, 1)) if stretch else 1.0
    end = start + scale * rots.apply(rest.segments[:, 1] - rest.segments[:, 0]) if s else start
    pts = rest.points + rng.normal(scale=0.3, size=rest.points.shape)
    return Pose.make(rest, pts, np.stack([start, end], axis=1), rotations=rots.as_matrix() if s else None)


def moved(rest: HandleSet, rot: Rotation, shift=np.zeros(3)) -> Pose:
    """Every handle moved by one rigid motion x -> rot x + shift."""
    segs = rot.apply(rest.segments.reshape(-1, 3)).reshape(-1, 2, 3) + shift
    mats = np.repeat(rot.as_matrix()[None], len(rest.segments), axis=0)
    return Pose.make(rest, rot.apply(rest.points) + shift if len(rest.points) else (), segs, rotations=mats)


def turned(pose: Pose, rest: HandleSet, rot: Rotation) -> Pose:
    """The posed handles turned as a whole by rot about the origin."""
    h = pose.handles
    segs = rot.apply(h.segments.reshape(-1, 3)).reshape(-1, 2, 3)
    mats = np.einsum("ij,sjk->sik", rot.as_matrix(), pose.rotations)
    return Pose.make(rest, rot.apply(h.points) if len(h.points) else (), segs, rotations=mats)


def points_in_groups(rng, rest: HandleSet, total: int, sizes: tuple, span: tuple, noise: float) -> np.ndarray:
    """Points (at least ``total``, (n, 3)) in consecutive groups, each of ``sizes`` = [low, high)
    points near one segment of ``rest`` drawn at random: at parameters uniform in ``span`` along
    it, plus Gaussian noise of scale ``noise``."""
    a, b = rest.segments[:, 0], rest.segments[:, 1]
    groups = []
    while sum(len(g) for g in groups) < total:
        s, m = rng.integers(0, len(a)), rng.integers(*sizes)
        groups.append(a[s] + rng.uniform(*span, (m, 1)) * (b[s] - a[s]) + rng.normal(0, noise, (m, 3)))
    return np.concatenate(groups)


def both(points, rest, **kw):
    return Deformer(points, rest, **kw), Deformer(points, rest, backend="numpy", **kw)


# --------------------------------------------------------------------------- kernel vs reference
CONFIGS = [(4, 0), (0, 4), (3, 3), (1, 0), (0, 1), (2, 7), (10, 0)]   # (10, 0): 16 lanes, handle loop not unrolled


@pytest.mark.parametrize("n_pts,n_segs", CONFIGS)
@pytest.mark.parametrize("alpha", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("blend", ["relative", "paper", "quaternion"])
def test_kernel_matches_reference_random(n_pts, n_segs, alpha, blend):
    rng = np.random.default_rng(100 * n_pts + 10 * n_segs + int(4 * alpha))
    rest = random_rest(rng, n_pts, n_segs)
    points = rng.uniform(-1.5, 1.5, (1001, 3))  # not a multiple of 8
    dev, ref = both(points, rest, alpha=alpha, blend=blend)
    for _ in range(3):  # bind once, pose many: buffers and kernels are reused
        pose = random_pose(rng, rest, stretch=True)
        out, expect = dev.pose(pose), ref.pose(pose)
        assert out.shape == (1001, 3) and np.isfinite(out).all()
        assert np.abs(out - expect).max() <= TOL * diag(points)


@pytest.mark.parametrize("blend", ["relative", "paper", "quaternion"])
def test_point_handles_in_shared_and_mixed_reference_chunks(blend):
    """The kernel takes R_ref^T q_p from the per-pose table where a chunk's 8 points share
    their reference rotation and rotates q_p - q* per lane where they do not: both paths
    against the reference, on a layout that has both kinds of chunk."""
    from nrpose.pose.mls import device_layout, slot_terms

    rng = np.random.default_rng(7)
    rest = random_rest(rng, 3, 4)
    points = rng.uniform(-1.5, 1.5, (2001, 3))
    dev, ref = both(points, rest, blend=blend)
    arrays, _ = device_layout(slot_terms(dev.terms, None, dev.lever), rest, dev.lever, dev.lanes)
    chunks = arrays["ref"].reshape(-1, dev.lanes)
    shared = (chunks == chunks[:, :1]).all(axis=1)
    assert shared.any() and not shared.all()
    for _ in range(2):
        pose = random_pose(rng, rest)
        assert np.abs(dev.pose(pose) - ref.pose(pose)).max() <= TOL * diag(points)


@pytest.mark.parametrize("k,lever", [(None, "weight"), (3, "weight"), (3, "paper"), (None, "paper")])
def test_kept_terms_block_by_block_equal_the_whole(monkeypatch, k, lever):
    """The OpenCL bind keeps, block by block, what the kernel uses of the rest terms
    (rest_terms(per_block=slot_terms)): the same arrays as slot_terms of the whole
    dense terms, over several blocks computed on threads, with points on handles."""
    from nrpose.pose import blend
    from nrpose.pose.mls import slot_terms

    rng = np.random.default_rng(19)
    rest = random_rest(rng, 2, 6)
    points = rng.uniform(-1.2, 1.2, (1001, 3))
    points[:4] = rest.segments[1, 0]
    whole = slot_terms(rest_terms(points, rest, 1.5, lever, k=k), k, lever)
    monkeypatch.setattr(blend, "BLOCK", 96)
    blocks = rest_terms(points, rest, 1.5, lever, k=k, per_block=lambda T: slot_terms(T, k, lever))
    assert blocks.keys() == whole.keys() and ("slot" in blocks) == (k is not None)
    for key in whole:
        assert np.array_equal(blocks[key], whole[key]), key


def test_opencl_deformer_recomputes_its_dropped_rest_terms():
    """The OpenCL deformer does not hold its host copy of the rest terms after binding;
    ``terms`` recomputes them, equal to the numpy deformer's kept ones."""
    rng = np.random.default_rng(4)
    rest = random_rest(rng, 2, 5)
    points = rng.uniform(-1.2, 1.2, (300, 3))
    dev, ref = both(points, rest, k=3, alpha=2.0, lever="length")
    assert dev._terms is None and ref._terms is not None
    for name in ("weights", "t", "p_star", "u", "lever", "ref", "phat"):
        np.testing.assert_array_equal(getattr(dev.terms, name), getattr(ref.terms, name))
    # the indices the kernel sees, read back from the device, are the layout's
    (r_dev, s_dev), (r_ref, s_ref) = diagnostics.bound_indices(dev), diagnostics.bound_indices(ref)
    np.testing.assert_array_equal(r_dev, r_ref)
    np.testing.assert_array_equal(s_dev, s_ref)
    assert s_dev.shape == (3, len(r_dev)) and len(r_dev) % 8 == 0
    dense = both(points, rest)[0]
    assert diagnostics.bound_indices(dense)[1] is None


def test_sparse_slots_are_the_heaviest_segments():
    """The K slots per point (slot_terms, stored by device_layout) are its K heaviest
    segments (ties: lower index), listed by index, for rows with exactly K, fewer (points
    on a handle) and more (dense rest terms laid out sparse) non-zero segment weights."""
    from nrpose.pose.mls import device_layout, lanes_for, slot_terms

    rng = np.random.default_rng(8)
    rest = random_rest(rng, 2, 7)
    points = rng.uniform(-1.2, 1.2, (400, 3))
    points[:10] = rest.segments[2, 0]                        # one-hot weights
    seen = set()
    for k in (1, 3, 5):
        for terms in (rest_terms(points, rest, k=k), rest_terms(points, rest)):
            arrays, K = device_layout(slot_terms(terms, k, "weight"), rest, "weight", lanes_for(len(rest.segments)))
            ws = terms.weights[:, 2:]
            expect = np.sort(np.argsort(-ws, axis=1, kind="stable")[:, :K], axis=1)
            stored = arrays["slot"][:, :len(points)].T
            assert K == k and np.array_equal(stored, expect[arrays["row"][:len(points)]])
            seen |= set(np.sign(np.count_nonzero(ws, axis=1) - K))
    assert seen == {-1, 0, 1}                                # fewer, exactly and more than K


@pytest.mark.parametrize("k", [None, 2])
def test_chunks_of_consecutive_rows_are_stored_whole(k):
    """chunk_records binds the first row of a chunk whose lanes' rows are consecutive as
    ~row (the kernel then stores the chunk with three vector stores, anywhere in the
    output, not only at multiples of 8 rows) and every other row as it is; the kernel's
    output equals the reference whether a chunk is a run or not: points given in runs of
    one dominant segment (runs of 8 to 13, so that runs start at every offset), then in
    shuffled order, dense and sparse."""
    from nrpose.pose.mls import chunk_records, device_layout, lanes_for, slot_terms

    rng = np.random.default_rng(12)
    rest = random_rest(rng, 0, 4)
    ordered = points_in_groups(rng, rest, 700, (8, 14), (0.2, 0.8), 0.02)
    for points, want_runs in ((ordered, True), (ordered[rng.permutation(len(ordered))], False)):
        lanes = lanes_for(4)
        arrays, K = device_layout(slot_terms(rest_terms(points, rest, k=k), k, "weight"), rest, "weight", lanes)
        _, ints = chunk_records(arrays, 0, 4, K, lanes)
        rows = ints.reshape(len(arrays["row"]) // lanes, -1, lanes)[:, 1]
        plain = arrays["row"].reshape(-1, lanes)
        run = (np.diff(plain, axis=1) == 1).all(axis=1)
        assert np.array_equal(rows[:, 0], np.where(run, ~plain[:, 0], plain[:, 0]))
        assert np.array_equal(rows[:, 1:], plain[:, 1:])
        assert (run.mean() > 0.25) == want_runs and (plain[run, 0] % lanes != 0).any() == want_runs
        dev, ref = both(points, rest, k=k)
        for _ in range(2):
            pose = random_pose(rng, rest)
            assert np.abs(dev.pose(pose) - ref.pose(pose)).max() <= TOL * diag(points)


def chunk_kinds(deformer) -> list[str]:
    """How the pose kernel takes each chunk of ``deformer``'s stored points, block by block
    (kernels/nrmls.cl pair_ref): "pair" for two consecutive chunks of one block whose lanes all
    share one reference (counted once), else "single" (its lanes share it) or "mixed"."""
    ref, _ = diagnostics.bound_indices(deformer)
    chunks = ref.reshape(-1, deformer.lanes)
    block = deformer._block // deformer.lanes
    kinds = []
    for start in range(0, len(chunks), block):
        g, end = start, min(start + block, len(chunks))
        while g < end:
            if g + 1 < end and (chunks[g:g + 2] == chunks[g, 0]).all():
                kinds.append("pair")
                g += 2
            else:
                kinds.append("single" if (chunks[g] == chunks[g, 0]).all() else "mixed")
                g += 1
    return kinds


def variant_frames(dev, source: str, batch: list) -> np.ndarray:
    """The frames (F, n, 3) that the pose kernel built from ``source`` (a variant of
    kernels/nrmls.cl, diagnostics.kernel_variant) writes for ``batch``, relaunched into the
    deformer's own output slots after ``dev.pose_frames(batch)``."""
    dev.pose_frames(batch)
    variant = diagnostics.kernel_variant(dev, source)
    dev._out.host[: len(batch) * 3 * dev._npad] = np.nan
    diagnostics.relaunch(dev, kernel=variant)
    dev._out.download()
    return dev._out.host[: len(batch) * 3 * dev._npad].reshape(len(batch), dev._npad, 3)[:, : dev.n].copy()


@pytest.mark.parametrize("blend,lever", [("relative", "weight"), ("relative", "length"), ("paper", "weight")])
def test_chunk_pairs_match_the_reference(blend, lever):
    """On rigs of segments only the kernel poses two consecutive chunks whose lanes share one
    reference together (pose_pair: the slot loop's per-pose values broadcast once for both),
    the others one by one. Points are stored sorted by reference, so pairs form inside each
    reference's run of chunks. Two layouts: points in groups near one segment each (each
    reference's run starts and ends inside a chunk: chunks straddle two references, and
    blocks' ends leave uniform chunks unpaired), and points picked so that every reference
    has an odd number of whole chunks (each change of reference on a chunk boundary, after an
    unpaired uniform chunk: a pair must not take the next reference's first chunk). Single
    poses and a batch of three against the reference; the batch equals the single poses and
    the kernel built without pairs, bitwise; a kernel whose pair path is broken differs (the
    path is taken)."""
    from nrpose.pose.mls import lanes_for

    rng = np.random.default_rng(31)
    rest = random_rest(rng, 0, 4)
    lanes = lanes_for(len(rest.segments))
    grouped = points_in_groups(rng, rest, 1500, (3, 41), (0.1, 0.9), 0.05)
    cand = rng.uniform(-1.5, 1.5, (3000, 3))
    refs = Deformer(cand, rest, lever=lever, backend="numpy").terms.ref
    runs = [np.flatnonzero(refs == j)[: lanes * ((n // lanes - 1) | 1)]
            for j, n in enumerate(np.bincount(refs)) if n >= lanes]
    aligned = cand[np.sort(np.concatenate(runs))]
    source = device.kernel_source("nrmls.cl")
    unpaired = source.replace("#define CHUNK_PAIRS 1", "")
    broken = source.replace("rxb += wb * t[0];", "rxb += wa * t[0];")
    assert unpaired != source and broken != source
    for points in (grouped, aligned):
        dev, ref = both(points, rest, blend=blend, lever=lever)
        kinds = chunk_kinds(dev)
        assert {"pair", "single"} <= set(kinds) and kinds.count("pair") > len(kinds) / 3
        assert ("mixed" in kinds) == (points is grouped)
        poses = [random_pose(rng, rest) for _ in range(3)]
        singles = np.stack([dev.pose(p) for p in poses])
        for got, p in zip(singles, poses):
            assert np.abs(got - ref.pose(p)).max() <= TOL * diag(points)
        assert np.array_equal(dev.pose_frames(poses), singles)
        for batch in (poses[:1], poses):
            assert np.array_equal(variant_frames(dev, unpaired, batch), singles[: len(batch)])
            assert not np.array_equal(variant_frames(dev, broken, batch), singles[: len(batch)])
            assert np.array_equal(variant_frames(dev, "#define BATCHES_ONLY 1\n" + source, batch),
                                  singles[: len(batch)])


@pytest.mark.parametrize("n_pts, n_segs", [(4, 0), (3, 5), (0, 7)])
def test_batches_only_program_poses_one_frame_bitwise(n_pts, n_segs, monkeypatch):
    """Built for whole-job processes (-DBATCHES_ONLY, kernel_options in one), the pose kernel
    has no single-pose path: a job of one frame takes the batch path, with the same bits."""
    from nrpose.pose.mls import kernel_options
    rng = np.random.default_rng(7 + n_pts + n_segs)
    rest = random_rest(rng, n_pts, n_segs)
    dev = Deformer(rng.uniform(-1.5, 1.5, (517, 3)), rest)
    source = device.kernel_source("nrmls.cl")
    assert "#ifndef BATCHES_ONLY" in source
    pose = random_pose(rng, rest)
    single = dev.pose(pose)
    assert np.array_equal(variant_frames(dev, "#define BATCHES_ONLY 1\n" + source, [pose])[0], single)
    monkeypatch.setenv("NRPOSE_WHOLE_JOB", "1")
    assert "-DBATCHES_ONLY" in kernel_options(8, n_pts, n_segs, n_segs, "weight", True, False)
    monkeypatch.setenv("NRPOSE_WHOLE_JOB", "0")
    assert "-DBATCHES_ONLY" not in kernel_options(8, n_pts, n_segs, n_segs, "weight", True, False)


@pytest.mark.parametrize("angle", [45.0, 60.0, 90.0, 135.0, 170.0, 179.5])
def test_kernel_matches_reference_large_point_handle_angles(angle):
    """Point-handle minimal rotations of every size up to nearly pi, where the kernel's
    angle over sine (angle_per_sine, kernels/nrmls.cl) switches octant: the paper blend has no
    reference rotation, so a global turn reaches each handle's minimal rotation."""
    rng = np.random.default_rng(int(angle))
    rest = random_rest(rng, 6, 0)
    points = rng.uniform(-1.5, 1.5, (203, 3))
    axis = rng.normal(size=3)
    rot = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis))
    dev, ref = both(points, rest, blend="paper")
    for noise in (0.0, 0.05):
        pose = Pose.make(rest, rot.apply(rest.points) + rng.normal(scale=noise, size=(6, 3)))
        assert np.abs(dev.pose(pose) - ref.pose(pose)).max() <= TOL * diag(points)


@pytest.mark.parametrize("scale", [1e-12, 1e-9, 1e-6, 1e8])
@pytest.mark.parametrize("lever", ["weight", "paper"])
def test_kernel_matches_reference_tiny_and_huge_models(scale, lever):
    """Point handles on models 1e-12 to 1e8 across: |p̂ × ŷ|² and |p̂|² would be denormal
    on the tiny ones; the device binds p̂ scaled by a power of two (mls.device_layout),
    which keeps them normal floats (before, a model 1e-12 across was posed 10 % of its
    size off)."""
    rng = np.random.default_rng(int(-np.log10(scale)) + 40)
    rest = random_rest(rng, 5, 0)
    points = rng.uniform(-1.5, 1.5, (301, 3))
    pose = random_pose(rng, rest)
    dev, ref = both(points * scale, HandleSet.make(rest.points * scale), lever=lever)
    scaled = Pose.make(dev.rest, pose.handles.points * scale)
    assert np.abs(dev.pose(scaled) - ref.pose(scaled)).max() <= TOL * diag(points * scale)


@pytest.mark.parametrize("lever", ["weight", "length"])
def test_point_handle_at_every_centroid(lever):
    """Authored weights that put every point's p* on the point handle (up to rounding):
    p̂ is rounding residue (~1e-19) beside a 30-unit bone. The device's power-of-two
    scaling of p̂ (mls.device_layout) must not overflow the bone's lever in float32
    (it did: every point NaN); posed as the reference poses it."""
    rng = np.random.default_rng(1)
    a = np.array([1.1e-3, 0.0, 0.0])
    rest = HandleSet.make([a], [[a, a + [30.0, 0, 0]]])
    points = a - np.column_stack([rng.uniform(0.1, 2, 200), np.zeros((200, 2))])
    weights = rng.uniform(0.05, 1, (200, 2))
    R = Rotation.from_rotvec([0, 0, 0.5]).as_matrix()
    q = a + [0, 0.1, 0]
    pose = Pose.make(rest, [q], [[q, q + R @ [30.0, 0, 0]]], rotations=R[None])
    for blend in ("relative", "paper", "quaternion"):
        dev, ref = both(points, rest, lever=lever, blend=blend, weights=weights)
        out = dev.pose(pose)
        assert np.isfinite(out).all(), blend
        assert np.abs(out - ref.pose(pose)).max() <= TOL * 32.0, blend


@pytest.mark.parametrize("scale", [1e-4, 1e8])
@pytest.mark.parametrize("n_pts,n_segs", [(0, 4), (3, 0), (2, 5)])
@pytest.mark.parametrize("blend", ["relative", "quaternion"])
def test_kernel_matches_reference_at_any_scale(scale, n_pts, n_segs, blend):
    """Models 1e-4 and 1e8 across: the derived levers scale with length², so the kernel
    must normalise them before any absolute threshold (the quaternion blend's floor)."""
    rng = np.random.default_rng(n_pts * 10 + n_segs)
    rest = random_rest(rng, n_pts, n_segs)
    pose = random_pose(rng, rest)
    big = HandleSet.make(rest.points * scale, rest.segments * scale)
    points = rng.uniform(-1.5, 1.5, (301, 3)) * scale
    scaled = Pose.make(big, pose.handles.points * scale, pose.handles.segments * scale,
                       rotations=pose.rotations if n_segs else None)
    dev, ref = both(points, big, blend=blend)
    out = dev.pose(scaled)
    assert np.isfinite(out).all()
    assert np.abs(out - ref.pose(scaled)).max() <= TOL * diag(points)


@pytest.mark.parametrize("blend,lever,point", [("relative", "weight", False), ("relative", "length", False),
                                               ("relative", "weight", True), ("paper", "length", False),
                                               ("quaternion", "length", False)])
def test_rotation_table_against_float64(blend, lever, point):
    """The pose prologue's rotation table (kernels/nrmls.cl table_block, VW pairs at a
    time, read back from the device) against float64: relative log(R_j^-1 R_i) (on a rig
    of segments only turned into the world frame, R_j log(R_j^-1 R_i) = log(R_i R_j^-1);
    with a point handle, far from the points, in R_j's frame), paper
    log(R_i), quaternion Q_i in Q_j's hemisphere, each times segment i's lever factor
    len2 (rule "length": segments of different lengths); adversarial relative rotations
    of exactly pi and of 1e-4 rad; 10 x 10 pairs, so that the last block of 8 is part
    filled with pairs that are not trivial; the relative logs exactly antisymmetric
    (bitwise, where the lever factors are equal), so that blends seen from either handle agree."""
    rng = np.random.default_rng(11)
    S = 10
    a = np.stack([np.arange(S) * 2.0, np.zeros(S), np.zeros(S)], 1)
    length = np.linspace(0.6, 1.4, S)
    rest = HandleSet.make(segments=np.stack([a, a + length[:, None] * [0.0, 1.0, 0.0]], 1),
                          **({"points": [[9.0, 40.0, 0.0]]} if point else {}))
    points = a[rng.integers(0, S, 2000)] + rng.uniform(-0.4, 0.4, (2000, 3)) + [0.0, 0.5, 0.0]
    rots = Rotation.random(S, random_state=rng)
    axis = Rotation.random(random_state=rng).as_rotvec()
    rots = Rotation.concatenate([rots[0], rots[0] * Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis)),
                                 rots[0] * Rotation.from_rotvec([1e-4, 0.0, 0.0]), rots[3:]])
    R = rots.as_matrix()
    posed_start = a + rng.normal(size=(S, 3))
    pose = Pose.make(rest, segments=np.stack([posed_start, posed_start + length[:, None] * R[:, :, 1]], 1),
                     rotations=R, **({"points": [[9.0, 41.0, 0.0]]} if point else {}))
    dev = Deformer(points, rest, blend=blend, lever=lever)
    dev.pose(pose)
    refs = np.unique(diagnostics.bound_indices(dev)[0])
    assert list(refs) == list(range(S))       # every segment is some point's reference
    dev._frame_blocks.download()
    tw = 4 if blend == "quaternion" else 3
    at = dev._derived_at                      # frame 0's derived block follows its pose block
    block = dev._frame_blocks.host[dev._pose_stride: dev._pose_stride + at["stride"]]
    # j = S, R_g: unused here, its entries never written (whatever the memory held: cast only what is read)
    table = block[at["table"]: at["stride"]].reshape(S + 1, S, tw)[:S].astype(np.float64)
    len2 = diagnostics.bound_array(dev, "len2", np.float32)
    assert len2.shape == (S,)
    assert (len2 > 0).all() and (lever == "weight") == (np.ptp(len2) == 0)
    got = table / len2[None, :, None]
    if blend == "quaternion":
        q = rots.as_quat()                    # (x, y, z, w), up to sign
        qref = block[at["quats"]: at["quats"] + 4 * S].reshape(S, 4).astype(np.float64)   # the kernel's Q_j
        assert np.abs(np.abs(np.einsum("jc,jc->j", qref, q)) - 1).max() < 1e-6
        sign = np.sign(np.einsum("jic,ic->ji", got, q))
        assert np.abs(got - sign[..., None] * q[None]).max() < 1e-6
        # one sign per segment for every segment reference (the sign tree's: each signed
        # Q_s in its tree parent's hemisphere, up to the sign of the root), Q_j the signed one
        assert (sign == sign[:1]).all()
        assert np.abs(qref - got[0]).max() < 1e-6
        want = blend_mod.tree_signs(q, dev.tree)
        assert np.ptp(sign[0] * want) == 0
        child, parent = dev.tree[dev.tree[:, 1] >= 0].T
        assert (np.einsum("ic,ic->i", got[0, child], got[0, parent]) >= 0).all()
        return
    if blend == "paper":
        assert np.abs(got - rots.as_rotvec()[None]).max() < 1e-6
        return
    want = np.stack([(rots[j].inv() * rots).as_rotvec() for j in range(S)])
    world = R[0] if not point else np.eye(3)   # the pairs (0, 1) and (0, 2) are turned by R_0 (the lower index)
    if not point:
        want = np.einsum("jab,jib->jia", R, want)
    # float32: 1e-6 and (turned into the world frame: a few roundings more) 1e-6 of the angle
    err = np.linalg.norm(got - want, axis=2) / (1 + np.linalg.norm(want, axis=2))
    at_pi = np.zeros((S, S), bool)
    at_pi[0, 1] = at_pi[1, 0] = True           # +-pi about the axis: both logs are right
    assert err[~at_pi].max() < 1e-6
    for j, i in ((0, 1), (1, 0)):
        assert abs(np.linalg.norm(got[j, i]) - np.pi) < 1e-5
        assert np.linalg.norm(np.cross(got[j, i], world @ axis)) < 1e-5 * np.linalg.norm(axis)
    small = world @ [1e-4, 0, 0]
    assert np.abs(got[0, 2] - small).max() < 1e-6 and np.abs(got[2, 0] + small).max() < 1e-6
    if lever == "weight":
        assert np.array_equal(table, -table.transpose(1, 0, 2))     # bitwise

@pytest.mark.parametrize("lever", ["weight", "length", "paper"])
def test_kernel_matches_reference_levers(lever):
    rng = np.random.default_rng(7)
    rest = random_rest(rng, 2, 5)
    points = rng.uniform(-1, 1, (300, 3))
    dev, ref = both(points, rest, lever=lever)
    pose = random_pose(rng, rest, max_angle=np.radians(170))
    assert np.abs(dev.pose(pose) - ref.pose(pose)).max() <= TOL * diag(points)


def test_adversarial_nearly_coincident_handles_and_points_on_handles():
    rng = np.random.default_rng(3)
    base = random_rest(rng, 2, 3)
    pts = np.concatenate([base.points, base.points[:1] + 1e-7])            # two points 1e-7 apart
    segs = np.concatenate([base.segments, base.segments[:1] + 1e-7])       # near-duplicate segment
    rest = HandleSet.make(pts, segs)
    t = rng.uniform(0, 1, (5, 1))
    on_segments = rest.segments[0, 0] + t * (rest.segments[0, 1] - rest.segments[0, 0])
    points = np.concatenate([rng.uniform(-1, 1, (200, 3)), rest.points, rest.segments[:, 0],
                             rest.segments[:, 1], on_segments, np.full((3, 3), 50.0)])
    for alpha in (0.5, 1.0, 2.0):
        dev, ref = both(points, rest, alpha=alpha)
        pose = random_pose(rng, rest, max_angle=np.radians(90))
        out, expect = dev.pose(pose), ref.pose(pose)
        assert np.isfinite(out).all()
        assert np.abs(out - expect).max() <= TOL * diag(points)


# --------------------------------------------------------------------------- properties
@pytest.fixture(scope="module")
def mixed():
    rng = np.random.default_rng(11)
    rest = random_rest(rng, 3, 4)
    return rest, rng.uniform(-1.2, 1.2, (777, 3))


@pytest.mark.parametrize("blend", ["relative", "paper", "quaternion"])
def test_identity_pose_is_identity(mixed, blend):
    rest, points = mixed
    out = Deformer(points, rest, blend=blend).pose(Pose.make(rest, rest.points, rest.segments))
    assert np.abs(out - points).max() <= 1e-5 * diag(points)


@pytest.mark.parametrize("blend", ["relative", "paper", "quaternion"])
def test_pure_translation(mixed, blend):
    rest, points = mixed
    shift = np.array([0.3, -2.0, 5.0])
    out = Deformer(points, rest, blend=blend).pose(moved(rest, Rotation.identity(), shift))
    assert np.abs(out - (points + shift)).max() <= 1e-5 * diag(points + shift)


@pytest.mark.parametrize("angle", [30.0, 120.0, 179.0])
def test_rigid_motion_of_all_segments(angle):
    rng = np.random.default_rng(5)
    rest = random_rest(rng, 0, 5)
    points = rng.uniform(-1, 1, (500, 3))
    rot, shift = Rotation.from_rotvec(np.radians(angle) * np.array([0.36, 0.48, 0.8])), np.array([1.0, 2, 3])
    expect = rot.apply(points) + shift
    for blend in ("relative", "paper", "quaternion"):
        out = Deformer(points, rest, blend=blend).pose(moved(rest, rot, shift))
        assert np.abs(out - expect).max() <= 1e-5 * diag(points)


def test_rigid_motion_with_point_handles_relative_blend(mixed):
    """The relative and quaternion blends reproduce a rigid motion of point handles too
    (the paper's does not)."""
    rest, points = mixed
    rot, shift = Rotation.from_rotvec([2.0, -1.0, 0.5]), np.array([0.0, 1.0, -1.0])
    expect = rot.apply(points) + shift
    for blend in ("relative", "quaternion"):
        out = Deformer(points, rest, blend=blend).pose(moved(rest, rot, shift))
        assert np.abs(out - expect).max() <= 1e-5 * diag(points)
    paper = Deformer(points, rest, blend="paper").pose(moved(rest, rot, shift))
    assert np.abs(paper - expect).max() > 1e-2 * diag(points)


def test_points_on_handles_land_on_posed_handles():
    rng = np.random.default_rng(9)
    rest = random_rest(rng, 3, 3)
    t = np.array([0.0, 0.25, 0.5, 1.0])
    on_seg = [a + tt * (b - a) for a, b in rest.segments for tt in t]
    points = np.concatenate([rest.points, on_seg])
    pose = random_pose(rng, rest, stretch=True)
    expect = np.concatenate([pose.handles.points,
                             [a + tt * (b - a) for a, b in pose.handles.segments for tt in t]])
    for alpha in (0.5, 1.0, 2.0):
        out = Deformer(points, rest, alpha=alpha).pose(pose)
        assert np.abs(out - expect).max() <= 1e-5 * diag(expect)


@pytest.mark.parametrize("angle", [90.0, 179.9])
@pytest.mark.parametrize("blend", ["relative", "quaternion"])
def test_global_turn_commutes_with_deformation(mixed, angle, blend):
    rest, points = mixed
    rng = np.random.default_rng(1)
    pose = random_pose(rng, rest, max_angle=np.radians(150))
    G = Rotation.from_rotvec(np.radians(angle) * np.array([0.0, 0.6, 0.8]))
    size = diag(points)
    for backend, tol in (("opencl", 1e-5), ("numpy", 1e-8)):   # numpy: the Kabsch fit's 1e-9 regularisation
        dev = Deformer(points, rest, blend=blend, backend=backend)
        assert np.abs(dev.pose(turned(pose, rest, G)) - G.apply(dev.pose(pose))).max() <= tol * size
    # the paper's blend is not equivariant: the defect the default blend removes
    paper = Deformer(points, rest, blend="paper", backend="numpy")
    assert np.abs(paper.pose(turned(pose, rest, G)) - G.apply(paper.pose(pose))).max() > 1e-3 * size


def test_supplied_distances_and_weights():
    rng = np.random.default_rng(2)
    rest = random_rest(rng, 2, 2)
    points = rng.uniform(-1, 1, (200, 3))
    pose = random_pose(rng, rest)
    terms = rest_terms(points, rest)
    euclid = np.linalg.norm(points[:, None] - np.concatenate(
        [np.broadcast_to(rest.points, (200, 2, 3)),
         rest.segments[None, :, 0] + terms.t[..., None] * (rest.segments[None, :, 1] - rest.segments[None, :, 0])],
        axis=1), axis=2)
    base = Deformer(points, rest).pose(pose)
    assert np.abs(Deformer(points, rest, distances=euclid).pose(pose) - base).max() <= 1e-5
    custom = euclid * rng.uniform(1, 3, euclid.shape)
    out = Deformer(points, rest, distances=custom).pose(pose)
    assert np.abs(out - deform_reference(points, rest, pose, distances=custom)).max() <= TOL * diag(points)
    assert np.abs(out - base).max() > 1e-3  # the distances are actually used
    w = rng.uniform(0, 1, euclid.shape)
    out = Deformer(points, rest, weights=w).pose(pose)
    assert np.abs(out - deform_reference(points, rest, pose, weights=w)).max() <= TOL * diag(points)


# --------------------------------------------------------------------------- quality
def _cylinder(pose, alpha, lever="weight", blend="relative"):
    V, F = cylinder.cylinder_mesh()
    out = Deformer(V, cylinder.rest_handles(), alpha=alpha, lever=lever, blend=blend).pose(pose)
    return V, F, out.astype(np.float64)


@pytest.mark.parametrize("blend", ["relative", "quaternion"])
def test_twist_180_keeps_volume(blend):
    V, F, out = _cylinder(cylinder.twist_pose(180), alpha=1.0, blend=blend)
    assert cylinder.mesh_volume(out, F) >= 0.99 * cylinder.mesh_volume(V, F)


@pytest.mark.parametrize("blend", ["relative", "quaternion"])
def test_bend_90_keeps_volume_and_far_points_rigid(blend):
    pose = cylinder.bend_pose(90)
    V, F, out = _cylinder(pose, alpha=2.0, blend=blend)
    assert cylinder.mesh_volume(out, F) >= 0.97 * cylinder.mesh_volume(V, F)
    joint, R = cylinder.BONES[1, 0], pose.rotations[1]
    far2, far1 = V[:, 0] >= 1.5, V[:, 0] <= 0.5   # beyond half a bone length from the joint
    assert np.abs(out[far2] - ((V[far2] - joint) @ R.T + joint)).max() <= 0.01
    assert np.abs(out[far1] - V[far1]).max() <= 0.01
    # the literal lever w|p̂|² collapses the same bend: the defect the default removes
    V, F, literal = _cylinder(pose, alpha=2.0, lever="paper", blend=blend)
    assert cylinder.mesh_volume(literal, F) < 0.5 * cylinder.mesh_volume(V, F)


def _y_junction():
    """Three unit bones meeting at the origin (one down, two up-left / up-right), the
    upper two turned 90° about different axes, and a line of points crossing the
    region where the dominant upper bone changes (spacing 1e-4)."""
    segs = np.array([[[0, 0, 0], [0, -1, 0]], [[0, 0, 0], [-0.7, 0.7, 0]], [[0, 0, 0], [0.7, 0.7, 0]]], float)
    rest = HandleSet.make(segments=segs)
    turns = [Rotation.identity(), Rotation.from_rotvec([np.pi / 2, 0, 0]), Rotation.from_rotvec([0, 0, -np.pi / 2])]
    posed = np.stack([np.stack([r.apply(s[0]), r.apply(s[1])]) for r, s in zip(turns, segs)])
    pose = Pose.make(rest, segments=posed, rotations=np.stack([r.as_matrix() for r in turns]))
    x = np.linspace(-0.3, 0.3, 6001)
    return rest, pose, np.stack([x, np.full_like(x, 0.4), np.full_like(x, 0.15)], 1)


@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_quaternion_blend_is_continuous_where_the_dominant_bone_changes(backend):
    """The relative blend jumps (~1 % of a bone length between points 1e-4 apart) where
    its reference switches between two bones of different rotations; the quaternion
    blend moves neighbouring points by about their spacing."""
    rest, pose, line = _y_junction()
    step = {blend: np.linalg.norm(np.diff(Deformer(line, rest, blend=blend, backend=backend).pose(pose)
                                          .astype(np.float64), axis=0), axis=1).max()
            for blend in ("relative", "quaternion")}
    assert step["relative"] > 5e-3
    assert step["quaternion"] < 5e-4


# --------------------------------------------------------------------------- bad input
def test_bad_points_raise_typed_errors():
    rest = HandleSet.make(segments=[[[0, 0, 0], [1, 0, 0]]])
    with pytest.raises(InputError, match="NaN or infinite"):
        Deformer([[0, 0, 0], [np.nan, 0, 0]], rest)
    with pytest.raises(InputError, match="NaN or infinite"):
        Deformer([[0, 0, np.inf]], rest)
    with pytest.raises(InputError, match="shape"):
        Deformer(np.zeros((4, 2)), rest)
    with pytest.raises(InputError, match="empty"):
        Deformer(np.zeros((0, 3)), rest)
    with pytest.raises(InputError, match="distances"):
        Deformer(np.zeros((3, 3)), rest, distances=np.full((3, 1), -1.0))
    with pytest.raises(InputError, match="shape"):
        Deformer(np.zeros((3, 3)), rest, weights=np.ones((3, 2)))
    with pytest.raises(InputError, match="no positive weight"):
        Deformer(np.zeros((3, 3)), rest, weights=np.zeros((3, 1)))
    with pytest.raises(InputError, match="alpha"):
        Deformer(np.zeros((3, 3)), rest, alpha=-1)
    with pytest.raises(InputError, match="backend"):
        Deformer(np.zeros((3, 3)), rest, backend="cuda")


def test_bad_handles_raise_typed_errors():
    with pytest.raises(HandleError, match="no handles"):
        HandleSet.make()
    with pytest.raises(HandleError, match="zero length"):
        HandleSet.make(segments=[[[1, 1, 1], [1, 1, 1]]])
    with pytest.raises(HandleError, match="NaN"):
        HandleSet.make(points=[[0, np.nan, 0]])
    with pytest.raises(HandleError, match="shape"):
        HandleSet.make(points=[[0, 0]])
    rest = HandleSet.make(points=[[0, 0, 0]], segments=[[[0, 0, 0], [1, 0, 0]]])
    with pytest.raises(HandleError, match="posed handles"):
        Pose.make(rest, [[0, 0, 0]], [])
    with pytest.raises(HandleError, match="away from the posed direction"):
        Pose.make(rest, [[0, 0, 0]], [[[0, 0, 0], [0, 1, 0]]], rotations=[np.eye(3)])
    with pytest.raises(HandleError, match="not a rotation"):
        Pose.make(rest, [[0, 0, 0]], [[[0, 0, 0], [1, 0, 0]]], rotations=[2 * np.eye(3)])
    with pytest.raises(HandleError, match="either"):
        Pose.make(rest, [[0, 0, 0]], [[[0, 0, 0], [1, 0, 0]]], rotations=[np.eye(3)], twists=[1.0])
    dev = Deformer(np.zeros((2, 3)), rest)
    with pytest.raises(HandleError, match="binding has"):
        dev.pose(Pose.make(HandleSet.make(points=[[0, 0, 0]]), [[0, 0, 0]]))


@pytest.mark.parametrize("n_segs,k", [(16, None), (17, None), (16, 4)])
@pytest.mark.parametrize("blend", ["relative", "quaternion"])
def test_slot_loop_unrolled_or_not(n_segs, k, blend):
    """The slot loop unrolled (dense, up to 16 segments) or not (17; sparse), against the
    reference; a single chunk of lanes with eight different references (the gathered path)."""
    rng = np.random.default_rng(n_segs + (k or 0))
    rest = random_rest(rng, 0, n_segs)
    for points in (rng.uniform(-1.2, 1.2, (1201, 3)), rest.segments[:8, 0] + 0.01):
        dev, ref = both(points, rest, k=k, blend=blend)
        if len(points) == 8:
            assert len(np.unique(diagnostics.bound_indices(dev)[0][:8])) == 8
        for _ in range(2):
            pose = random_pose(rng, rest)
            assert np.abs(dev.pose(pose) - ref.pose(pose)).max() <= TOL * diag(points)


@pytest.mark.parametrize("k", [1, 2, 4])
@pytest.mark.parametrize("blend", ["relative", "quaternion"])
def test_sparse_top_k_matches_reference(k, blend):
    """k segment slots per point: kernel against the reference with the same top-k weights."""
    rng = np.random.default_rng(20 + k)
    rest = random_rest(rng, 2, 9)
    points = rng.uniform(-1.2, 1.2, (1500, 3))
    dev, ref = both(points, rest, k=k, alpha=1.0, blend=blend)
    assert dev.slots == k
    assert (np.count_nonzero(dev.terms.weights, axis=1) <= k).all()
    for _ in range(2):
        pose = random_pose(rng, rest)
        assert np.abs(dev.pose(pose) - ref.pose(pose)).max() <= TOL * diag(points)


def test_sparse_with_k_at_least_handles_is_dense(mixed):
    rest, points = mixed
    pose = random_pose(np.random.default_rng(4), rest)
    dense = Deformer(points, rest).pose(pose)
    assert np.array_equal(Deformer(points, rest, k=rest.count).pose(pose), dense)
    with pytest.raises(InputError, match="positive integer"):
        Deformer(points, rest, k=0)


def test_pose_frames_batch_matches_single_poses(mixed):
    rest, points = mixed
    rng = np.random.default_rng(8)
    poses = [random_pose(rng, rest) for _ in range(5)]
    dev, ref = both(points, rest)
    single = np.stack([dev.pose(p) for p in poses])
    batch = dev.pose_frames(poses)
    assert batch.shape == (5, len(points), 3)
    assert np.array_equal(batch, single)
    assert np.abs(batch - ref.pose_frames(poses)).max() <= TOL * diag(points)
    assert np.array_equal(dev.pose_frames(poses[:2]), single[:2])   # smaller batch after a larger one


@pytest.mark.parametrize("n_pts,n_segs", [(2, 3), (3, 0)])     # 8 and 16 lanes: row and vector stores
def test_pose_frames_into_frames_array_directly(n_pts, n_segs):
    """pose_frames(out=) into a frames_array (or a run of its frames) is written by the
    kernel itself: the same frames as a batch into a plain array, bitwise, and the frames
    around the run untouched; single poses between such batches (the kernel's handed
    argument bound back and forth) still hand over their frames; an out from another
    deformer's frames_array (other padding), a column slice or a plain array is copied
    into, as before. The numpy backend's frames_array is a plain float64 array."""

    rng = np.random.default_rng(31)
    rest = random_rest(rng, n_pts, n_segs)
    points = rng.uniform(-1, 1, (1010, 3))          # not a multiple of the lanes: padded frames
    dev, ref = both(points, rest)
    poses = [random_pose(rng, rest) for _ in range(6)]
    want = dev.pose_frames(poses)
    frames = dev.frames_array(9)
    assert frames.shape == (9, len(points), 3) and frames.dtype == np.float32
    assert device.fine_grain_svm() == (device.frames_in(frames, 3 * dev._npad) is not None)
    frames[...] = -7.0
    run = frames[2:5]
    dev._out.host[:] = np.nan                 # the launch's own slots: not written, nothing copied
    assert dev.pose_frames(poses[:3], out=run) is run
    assert np.array_equal(frames[2:5], want[:3])
    assert np.isnan(dev._out.host).all() == device.fine_grain_svm()
    frozen = frames[:2]
    frozen.flags.writeable = False            # read-only: refused, not written by the kernel
    with pytest.raises(InputError, match="not writable"):
        dev.pose_frames(poses[:2], out=frozen)
    assert (frames[:2] == -7).all() and (frames[5:] == -7).all()
    held = dev.pose(poses[4])
    assert np.array_equal(held, want[4])
    dev.pose_frames(poses, out=frames[3:])
    assert np.array_equal(frames[3:], want) and (frames[:2] == -7).all()
    assert np.array_equal(dev.pose(poses[5]), want[5]) and np.array_equal(held, want[4])
    assert np.abs(frames[3:] - ref.pose_frames(poses)).max() <= TOL * diag(points)
    # a frames_array of a deformer with the other lane count pads 1010 points otherwise
    other = Deformer(points, random_rest(rng, 2, 0 if n_segs else 2)).frames_array(2)
    assert device.frames_in(other, 3 * dev._npad) is None and device.frames_in(frames[:, 1:], 3 * dev._npad) is None
    assert dev.pose_frames(poses[:2], out=other) is other and np.array_equal(other, want[:2])
    # fewer points of a frames_array of more, the same padding: copied into, so that the
    # kernel's whole padded frames do not overwrite the points past the view
    fewer = Deformer(points[:-1], rest)
    assert fewer._npad == dev._npad
    frames[...] = -7.0
    view = frames[:2, :-1]
    assert device.frames_in(view, 3 * fewer._npad) is None
    assert fewer.pose_frames(poses[:2], out=view) is view and (frames[:2, -1] == -7).all()
    with pytest.raises(InputError, match="shape"):
        dev.pose_frames(poses[:2], out=frames[:2, :5])
    plain = np.zeros((2, len(points), 3), np.float32)
    assert dev.pose_frames(poses[:2], out=plain) is plain and np.array_equal(plain, want[:2])
    empty = dev.frames_array(0)
    assert dev.pose_frames([], out=empty).shape == (0, len(points), 3)
    for bad in (-1, 2.5, "3", None):
        with pytest.raises(InputError, match="frames must be a whole number"):
            dev.frames_array(bad)
    assert ref.frames_array(2).dtype == np.float64


@pytest.mark.parametrize("limit,ends", [(None, True), (0, False)])
def test_jobs_from_both_ends_where_the_bound_data_fits(monkeypatch, limit, ends):
    """A deformer whose bound block is at most device.ENDS_MAX_BOUND_BYTES has its jobs taken
    from both ends (Jobs.ends), a larger one not; either way, and with a standing worker
    taking blocks from the start while the calling thread takes them from the end, the
    poses equal the reference."""
    if limit is not None:
        monkeypatch.setattr(device.mailbox, "ENDS_MAX_BOUND_BYTES", limit)
    rng = np.random.default_rng(14)
    rest = random_rest(rng, 1, 3)
    points = rng.uniform(-1, 1, (3000, 3))
    dev, ref = both(points, rest)
    assert dev._bound.size <= 1 << 20 and dev._jobs.ends == ends
    for pose in [random_pose(rng, rest) for _ in range(4)]:
        want = ref.pose(pose)
        for workers in (True, None, None):            # the second finds the worker standing
            dev.pose(pose)
            diagnostics.relaunch(dev, workers=workers)
            dev._out.download()
            got = dev._out.host[: 3 * dev._npad].reshape(-1, 3)[: dev.n]
            assert np.abs(got - want).max() <= TOL * diag(points)


def test_standing_worker_follows_the_rebound_output(monkeypatch):
    """The standing worker runs a clone of the pose kernel; when the kernel's handed
    argument is rebound (a batch into a frames_array, then single poses handing frames
    over again: Jobs.set_argument), the clone takes the new argument too. Single poses
    served by a standing worker before and after such a batch land in their handed
    frames, and leave the batch's frames as they were."""
    from nrpose.pose.mls import BLOCK_POINTS

    standing_workers_or_skip()
    monkeypatch.setattr(device.policy, "_STANDBY", [None])           # restored after the test
    device.set_standby_s(0.5)
    rng = np.random.default_rng(37)
    rest = random_rest(rng, 2, 3)
    points = rng.uniform(-1, 1, ((device.STANDING_MIN_BLOCKS + 1) * BLOCK_POINTS, 3))
    dev = Deformer(points, rest)
    poses = [random_pose(rng, rest) for _ in range(4)]
    want = dev.pose_frames(poses).copy()
    stood = []
    for _ in range(2):
        held = [dev.pose(p) for p in poses[:2]]
        stood.append(dev._jobs.standing(dev._kernel))
        frames = dev.frames_array(4)
        dev.pose_frames(poses, out=frames)
        kept = frames.copy()
        after = [dev.pose(p) for p in poses[2:]]
        stood.append(dev._jobs.standing(dev._kernel))
        assert np.array_equal(np.stack(held + after), want) and np.array_equal(frames, kept)
        assert np.array_equal(frames, want)
    assert any(stood)          # a standing worker served some of these poses


@pytest.mark.parametrize("blocks", [1, 3])
@pytest.mark.parametrize("n_pts,n_segs", [(2, 3), (3, 0)])     # 8 and 16 lanes
def test_shared_launch_any_split_same_points(blocks, n_pts, n_segs, monkeypatch):
    """The pose kernel's blocks of points (mls.BLOCK_POINTS) may be taken by the
    calling thread alone, by PoCL's workers alone or by both, the workers standing or
    woken for the launch (device.launch_shared):
    bitwise the same result each way, equal to the reference; a last block that is
    partly filled and a padded last chunk included."""
    from nrpose.pose.mls import BLOCK_POINTS

    rng = np.random.default_rng(3)
    rest = random_rest(rng, n_pts, n_segs)
    points = rng.uniform(-1, 1, (blocks * BLOCK_POINTS + 5, 3))
    dev, ref = both(points, rest)
    pose = random_pose(rng, rest)
    expected = ref.pose(pose)
    shared = dev.pose(pose).copy()
    assert np.abs(shared - expected).max() <= TOL * diag(points)
    for name, kw in splits().items():
        dev._out.host[: 3 * dev._npad] = np.nan        # the launch's slot (relaunch writes there)
        relaunch(dev, kw, monkeypatch)
        dev._out.download()
        got = dev._out.host[: 3 * dev._npad].reshape(-1, 3)[: len(points)]
        assert np.array_equal(got, shared), name


def test_block_points_sizes():
    """Blocks of work (mls.block_points): whole chunks, about BLOCKS_PER_LAUNCH of them
    per launch, between BLOCK_POINTS and MAX_BLOCK_POINTS points each."""
    from nrpose.pose.mls import BLOCK_POINTS, BLOCKS_PER_LAUNCH, MAX_BLOCK_POINTS, block_points

    for lanes in (8, 16):
        for npad in (lanes, 256, 6_016, 8_192, 20_008, 35_824, 131_072, 1_000_000 // lanes * lanes):
            b = block_points(npad, lanes)
            assert b % lanes == 0 and BLOCK_POINTS <= b <= MAX_BLOCK_POINTS, (npad, lanes, b)
            blocks = -(-npad // b)
            assert blocks <= BLOCKS_PER_LAUNCH or b == MAX_BLOCK_POINTS, (npad, lanes, b)
            assert blocks >= BLOCKS_PER_LAUNCH - 1 or b == BLOCK_POINTS, (npad, lanes, b)
    assert block_points(35_824, 8) == 1_120 and block_points(6_016, 8) == BLOCK_POINTS


def test_bound_block_layout_is_the_kernels():
    """mls.bound_block, the pose kernel's one read-only argument: its header names the
    kernel's BOUND_* indices in kernels/nrmls.cl's order; each array at a multiple of
    BOUND_ALIGN bytes, its bytes as given (an empty one too), the header's ints the
    constants and offsets; a block past the int32 offsets (2 GiB) is a DeviceError naming
    the fix, raised before anything is allocated; a bound deformer's arrays read back
    (diagnostics.bound_array) are the ones it laid out."""
    import re

    from nrpose.pose.mls import BOUND_ALIGN, BOUND_ARRAYS, BOUND_CONSTANTS, GlobalFit, bound_block
    from nrpose.errors import DeviceError

    names = re.findall(r"^#define BOUND_([A-Z0-9_]+) (\d+)$", device.kernel_source("nrmls.cl"), re.M)
    assert [(n.lower(), int(i)) for n, i in names] == [(n, i) for i, n in enumerate(BOUND_CONSTANTS + BOUND_ARRAYS)]
    rng = np.random.default_rng(5)
    arrays = {"frec": rng.normal(size=77).astype(np.float32), "irec": np.arange(-5, 40, dtype=np.int32),
              "len2": np.float32([2.5]), "pairs": np.zeros(0, np.int32), "fit": rng.normal(size=(4, 3)),
              "tree": np.array([[1, -1], [0, 1]], np.int32)}
    constants = {n: 1000 + i for i, n in enumerate(BOUND_CONSTANTS)}
    block, where = bound_block(constants, arrays)
    assert block.dtype == np.uint8 and block.size % BOUND_ALIGN == 0
    head = block[: 4 * (len(BOUND_CONSTANTS) + len(BOUND_ARRAYS))].view(np.int32)
    assert list(head[: len(BOUND_CONSTANTS)]) == [constants[n] for n in BOUND_CONSTANTS]
    ends = [head.nbytes]
    for name, offset in zip(BOUND_ARRAYS, head[len(BOUND_CONSTANTS):]):
        a = arrays[name]
        assert where[name] == (offset, a.nbytes) and offset % BOUND_ALIGN == 0 and offset >= ends[-1]
        assert np.array_equal(block[offset: offset + a.nbytes].view(a.dtype).reshape(a.shape), a)
        ends.append(offset + a.nbytes)
    huge = dict(arrays, frec=np.broadcast_to(np.float32(0), (600_000_000,)))     # 2.4 GB, not allocated
    with pytest.raises(DeviceError, match="2 GiB.*fewer points"):
        bound_block(constants, huge)
    rest = HandleSet.make(points=[[0.0, 0.0, 3.0], [0.0, 3.0, 0.0]], segments=[[[0, 0, 0], [1, 0, 0]]])
    dev = Deformer(rng.uniform(-0.5, 0.5, (50, 3)) + [[0.0, 0.0, 3.0], [0.5, 0.0, 0.0]] * 25, rest, lever="length")
    assert dev._global is not None               # the points take R_g: the fit's data is bound
    assert np.array_equal(diagnostics.bound_array(dev, "fit", np.float64), GlobalFit(rest).values)   # 1 + 3 (P + 2S)
    ref, _ = diagnostics.bound_indices(dev)
    assert ref.shape == (dev._npad,) and set(ref) <= {0, 1}
    assert diagnostics.bound_array(dev, "len2", np.float32).shape == (1,)


@pytest.mark.parametrize("n_pts,n_segs", [(0, 3), (2, 0)])     # 8 and 16 lanes
def test_large_blocks_same_points(n_pts, n_segs, monkeypatch):
    """A deformer of 20,000 points takes its points in 32 blocks of 632 or 640 (mls.block_points,
    8 or 16 lanes), not 79 of 256: bitwise the same frames as with 256-point blocks, each way a launch may
    split the blocks, and equal to the reference."""
    from nrpose.pose import mls

    rng = np.random.default_rng(41)
    rest = random_rest(rng, n_pts, n_segs)
    points = rng.uniform(-1, 1, (20_000, 3))
    dev, ref = both(points, rest)
    assert dev._blocks == 32 and dev._block == (632 if dev.lanes == 8 else 640)
    monkeypatch.setattr(mls, "block_points", lambda npad, lanes: mls.BLOCK_POINTS)
    small = Deformer(points, rest)
    assert small._blocks == -(-small._npad // 256)
    poses = [random_pose(rng, rest) for _ in range(3)]
    want = small.pose_frames(poses)
    assert np.abs(want - ref.pose_frames(poses)).max() <= TOL * diag(points)
    assert np.array_equal(dev.pose_frames(poses), want)
    for name, kw in splits().items():
        dev._out.host[: 3 * 3 * dev._npad] = np.nan       # the launch's three slots
        relaunch(dev, kw, monkeypatch)
        dev._out.download()
        got = dev._out.host[: 3 * 3 * dev._npad].reshape(3, -1, 3)[:, : len(points)]
        assert np.array_equal(got, want), name


def test_time_launch_reruns_the_pose_as_a_frame_loop(monkeypatch):
    """diagnostics.time_launch: the last posing run again as a frame loop runs it (a
    standing worker serving it, after poses in a loop), its kernel time from the job's
    publication (finite, positive, at most the call's own time) and the same frames in
    the launch's slots, single poses and batches."""

    monkeypatch.setattr(device.policy, "_STANDBY", [None])           # restored after the test
    device.set_standby_s(0.2)
    rng = np.random.default_rng(43)
    rest = random_rest(rng, 2, 3)
    points = rng.uniform(-1, 1, (3_000, 3))
    dev = Deformer(points, rest)
    poses = [random_pose(rng, rest) for _ in range(2)]
    for frames in ([poses[0]], poses):
        want = dev.pose_frames(frames).copy()
        dev.pose_frames(frames)
        dev._out.host[: 3 * len(frames) * dev._npad] = np.nan
        t = time.perf_counter()
        span, stood = diagnostics.time_launch(dev)
        wall = time.perf_counter() - t
        assert span is not None and 0 < span <= wall
        assert stood == (device.worker_queue() is not None and device.fine_grain_svm()
                         and device.standing_workers_possible())
        dev._out.download()
        got = dev._out.host[: 3 * len(frames) * dev._npad].reshape(len(frames), -1, 3)[:, : len(points)]
        assert np.array_equal(got, want)
    device.stop_standing()


@pytest.mark.parametrize("blend", ["relative", "quaternion"])
@pytest.mark.parametrize("n_pts,n_segs", [(3, 2), (4, 0)])
def test_buffer_path_without_shared_memory(monkeypatch, blend, n_pts, n_segs):
    """Where the device has no fine-grained SVM, every per-pose array is an ordinary
    buffer that is copied to the device and back (device.HostArray) and the kernels run
    on the calling thread's queue alone: a mixed rig whose point-handle points take R_g
    (fitted on the device, into the uploaded pose buffer) and a rig of point handles
    only (its vector stores), single poses and batches that regrow the arrays, bitwise
    as with SVM (computed before SVM is switched off) and against the reference; R_g by
    GlobalFit.fit likewise."""
    from nrpose.pose.mls import GlobalFit

    rng = np.random.default_rng(23)
    rest = random_rest(rng, n_pts, n_segs)
    points = rng.uniform(-1.5, 1.5, (777, 3))
    svm, ref = both(points, rest, blend=blend)
    poses = [random_pose(rng, rest) for _ in range(3)]
    singles = [svm.pose(p) for p in poses]
    batches = [svm.pose_frames(poses), svm.pose_frames(poses[1:])]
    fits = GlobalFit.fit(rest, poses)
    monkeypatch.setattr(device.memory, "fine_grain_svm", lambda: False)
    dev = Deformer(points, rest, blend=blend)
    assert dev._global is not None and not dev._frame_blocks.svm and not dev._jobs.box.svm
    for pose, want in zip(poses, singles):
        got = dev.pose(pose)
        assert np.array_equal(got, want)
        assert np.abs(got - ref.pose(pose)).max() <= TOL * diag(points)
    assert not dev._out.svm
    got = dev.pose_frames(poses)                                  # 3 frames: the arrays regrow
    assert np.array_equal(got, batches[0])
    assert np.abs(got - ref.pose_frames(poses)).max() <= TOL * diag(points)
    assert np.array_equal(dev.pose_frames(poses[1:]), batches[1])
    frames = dev.frames_array(3)               # a plain array here: copied into
    assert device.frames_in(frames, 3 * dev._npad) is None
    assert dev.pose_frames(poses, out=frames) is frames and np.array_equal(frames, batches[0])
    assert np.array_equal(GlobalFit.fit(rest, poses), fits)


def test_pose_hands_its_result_over_without_a_copy():
    """pose() returns the frame in a slot of the deformer's output memory that is not
    written again while the result, or any view of it, lives (device.Handoff): results
    held across later poses, relaunches, a batch that regrows the arrays and the
    deformer's end keep their values; a third result held at once is a copy; a dropped
    result's slot is used again; a result may be written to."""

    rng = np.random.default_rng(43)
    rest = random_rest(rng, 3, 2)
    points = rng.uniform(-1, 1, (500, 3))
    dev, ref = both(points, rest)
    poses = [random_pose(rng, rest) for _ in range(8)]
    want = [ref.pose(p) for p in poses]

    def in_slots(a):                      # handed off: on the deformer's handoff slots
        return np.shares_memory(a, dev._handoff.array.host)

    held = [dev.pose(p) for p in poses[:3]]
    assert [in_slots(a) for a in held] == [True, True, False]   # two slots, then a copy
    del held[1]                          # its slot is free again
    column = dev.pose(poses[1])[:, 1]    # only a view kept: its slot stays taken
    assert in_slots(column)
    other = diagnostics.kernel_variant(dev, device.kernel_source("nrmls.cl").replace(
        "const floatv ux = LOADV(0, u)", "const floatv ux = 2.0f * LOADV(0, u)"))
    diagnostics.relaunch(dev, kernel=other)      # another result of the last pose: into the launch's slot
    assert not any(in_slots(dev.pose(p)) for p in poses[3:])    # every slot held: copies
    assert np.abs(held[0] - want[0]).max() <= TOL * diag(points)
    assert np.abs(held[1] - want[2]).max() <= TOL * diag(points)
    assert np.abs(column - want[1][:, 1]).max() <= TOL * diag(points)
    del held[0]
    again = dev.pose(poses[5])           # a slot was freed: handed off again
    assert in_slots(again) and np.abs(again - want[5]).max() <= TOL * diag(points)
    again[:] = 0.0                       # the caller's to write
    assert np.abs(dev.pose(poses[6]) - want[6]).max() <= TOL * diag(points)
    kept = (again.copy(), column.copy())
    launch_out = weakref.ref(dev._out)
    dev.pose_frames(poses)               # 8 frames: new per-frame arrays
    assert launch_out() is None          # held results keep only the handoff slots alive
    del dev
    assert np.array_equal(again, kept[0]) and np.array_equal(column, kept[1])


def test_no_handoff_where_reference_counts_are_not_exact(monkeypatch):
    """On a Python without the GIL (reference counts not exact) or without shared memory,
    pose() returns copies: equal results, none on deformer memory, all held at once."""
    import sys


    rng = np.random.default_rng(45)
    rest = random_rest(rng, 2, 1)
    points = rng.uniform(-1, 1, (200, 3))
    poses = [random_pose(rng, rest) for _ in range(3)]
    want = [Deformer(points, rest).pose(p).copy() for p in poses]
    monkeypatch.setattr(sys, "_is_gil_enabled", lambda: False, raising=False)
    dev = Deformer(points, rest)
    assert dev._handoff.array is None and dev._handoff.free() is None
    held = [dev.pose(p) for p in poses]
    for got, w in zip(held, want):
        assert np.array_equal(got, w) and not np.shares_memory(got, dev._out.host)



def test_frames_array_released_without_handoff_slots(monkeypatch):
    """Without handoff slots (a Python without the GIL), a batch posed straight into a
    frames_array and then release_frames() (as CharacterPoser does after each clip) bind the
    deformer's own output back: single poses and batches after it are right."""
    import sys


    if not device.fine_grain_svm():
        pytest.skip("frames_array is plain memory without shared memory: nothing is bound")
    rng = np.random.default_rng(46)
    rest = random_rest(rng, 2, 2)
    points = rng.uniform(-1, 1, (500, 3))
    poses = [random_pose(rng, rest) for _ in range(3)]
    want = Deformer(points, rest).pose_frames(poses).copy()
    monkeypatch.setattr(sys, "_is_gil_enabled", lambda: False, raising=False)
    dev = Deformer(points, rest)
    assert dev._handoff.array is None
    frames = dev.frames_array(3)
    assert np.array_equal(dev.pose_frames(poses, out=frames), want)
    dev.release_frames()
    assert dev._handed is None
    kept = frames.copy()
    assert np.array_equal(dev.pose(poses[1]), want[1]) and np.array_equal(dev.pose_frames(poses), want)
    assert np.array_equal(frames, kept)

def test_a_handed_off_result_changed_by_its_caller_changes_no_later_one():
    """pose_frames([p]) hands its frame over too: as a view, so that what the caller does
    to that array object (its shape, its writeable flag) stays with it."""

    rng = np.random.default_rng(44)
    rest = random_rest(rng, 2, 1)
    points = rng.uniform(-1, 1, (300, 3))
    dev, ref = both(points, rest)
    pose = random_pose(rng, rest)
    for _ in range(2 * device.HANDOFF_SLOTS):      # every slot, twice
        x = dev.pose_frames([pose])
        assert np.shares_memory(x, dev._handoff.array.host)
        x.shape = (-1,)
        x.flags.writeable = False
        del x
    y = dev.pose(pose)
    assert y.shape == (300, 3) and y.flags.writeable
    y[:] = 0.0
    assert np.abs(dev.pose(pose) - ref.pose(pose)).max() <= TOL * diag(points)
    assert device.HANDOFF_SLOTS == 2


def test_pose_kernel_variant_follows_the_deformers_arrays():
    """A kernel variant (diagnostics.kernel_variant, for bench/kernel_ab.py) run by
    relaunch(kernel=) uses the deformer's arrays and batch size as they are at the
    launch (bound again only after they change): after a single pose, a larger batch (new
    arrays), a batch into a frames_array (its memory bound) and a smaller batch, each
    relaunched twice, the shipped source as a variant gives the deformer's own results
    bitwise; a source that does not build is a
    DeviceError naming the compiler's error, one that does not run the job's prologue a
    DeviceError saying so (its launch would wait for ever)."""
    from nrpose import DeviceError, device

    rng = np.random.default_rng(41)
    rest = random_rest(rng, 2, 3)
    dev = Deformer(rng.uniform(-1, 1, (300, 3)), rest)
    source = device.kernel_source("nrmls.cl")
    variant = diagnostics.kernel_variant(dev, source)
    poses = [random_pose(rng, rest) for _ in range(3)]
    for batch, into in ((poses[:1], False), (poses, False), (poses[1:], True), (poses[:1], False)):
        want = dev.pose_frames(batch).copy()
        if into:                                         # the kernel's `handed` argument rebound
            dev.pose_frames(batch, out=dev.frames_array(len(batch)))
        for _ in range(2):
            dev._out.host[: len(batch) * 3 * dev._npad] = np.nan    # the launch's slots
            diagnostics.relaunch(dev, kernel=variant)
            dev._out.download()
            got = dev._out.host[: len(batch) * 3 * dev._npad].reshape(len(batch), dev._npad, 3)[:, :300]
            assert np.array_equal(got, want)
    with pytest.raises(DeviceError, match="does not build.*error:"):
        diagnostics.kernel_variant(dev, source.replace("const floatv ux = LOADV(0, u)", "const floatv ux = +"))
    with pytest.raises(DeviceError, match="does not run its job's prologue"):
        diagnostics.kernel_variant(dev, source.replace("claim_prologue(", "0 && (").replace(
            "open_job(jobs, job_tag_);", ""))


@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_pose_out_shape_is_checked(backend):
    """``out=`` of the wrong shape is an InputError naming the expected shape."""
    rng = np.random.default_rng(4)
    rest = random_rest(rng, 1, 2)
    dev = Deformer(rng.uniform(-1, 1, (13, 3)), rest, backend=backend)
    pose = random_pose(rng, rest)
    for bad in (np.zeros((13, 3), np.float32), np.zeros((1, 14, 3), np.float32)):
        with pytest.raises(InputError, match=r"out: expected an array of shape \(1, 13, 3\)"):
            dev.pose_frames([pose], out=bad)
    with pytest.raises(InputError, match=r"out: expected an array of shape \(13, 3\)"):
        dev.pose(pose, out=np.zeros((12, 3)))
    assert np.array_equal(dev.pose(pose, out=np.zeros((13, 3))), dev.pose(pose))


def test_small_launches_stay_on_the_calling_thread(monkeypatch):
    """A bind times one frame of the pose kernel on the calling thread alone (the job
    mailbox's alone_s). A launch whose frames take less than device.SHARE_MIN_S together
    runs there alone; larger ones wake the workers; a launch following the deformer's last
    one within the standby time (frames in a loop) and of device.STANDING_MIN_BLOCKS blocks
    or more stands a worker, and one that finds it standing uses it (without deciding
    again: launch_shared's path for frames in a loop)."""
    import time

    from nrpose.pose.mls import BLOCK_POINTS

    rng = np.random.default_rng(4)
    rest = random_rest(rng, 0, 2)
    dev = Deformer(rng.uniform(-1, 1, (device.STANDING_MIN_BLOCKS * BLOCK_POINTS, 3)), rest)
    jobs = dev._jobs
    assert 0 < jobs.alone_s < float("inf") and dev._blocks == device.STANDING_MIN_BLOCKS
    decided = []
    real = device.Jobs.mode
    monkeypatch.setattr(device.Jobs, "mode", lambda self, *a: decided.append(real(self, *a)) or decided[-1])
    jobs.alone_s = device.SHARE_MIN_S / 4
    if not device.standing_workers_possible():
        pytest.skip("standing workers only on x86 hosts")
    monkeypatch.setattr(device.policy, "_STANDBY", [10.0])
    for frames in (3, 4, 1):
        jobs.stop()
        jobs._last = time.perf_counter() - 20.0             # long since the last launch
        dev.pose_frames([random_pose(rng, rest)] * frames)
    dev.pose_frames([random_pose(rng, rest)])              # right after: in a loop
    assert jobs.standing(dev._kernel)
    before = jobs._last
    dev.pose_frames([random_pose(rng, rest)])              # finds it standing
    assert decided == ["alone", "woken", "alone", "standing"] and jobs._last > before
    assert jobs.mode(dev._kernel, 1, 1, 10.0) == "standing"           # it still stands
    jobs.stop()
    jobs._last = time.perf_counter()
    few = device.STANDING_MIN_BLOCKS - 1
    assert jobs.mode(dev._kernel, 1, few + 1, 10.0) == "standing"     # in a loop
    assert jobs.mode(dev._kernel, 1, few, 10.0) == "alone"            # too few blocks to share
    assert jobs.mode(dev._kernel, 1, few + 1, 0.0) == "alone"         # standing workers off


def test_minimal_rotation_conventions():
    from nrpose.model.rotation import minimal_rotvec

    a = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 1.0]])
    b = np.array([[0, 3.0, 0], [0, -1.0, 0], [0, 0, 5.0]])
    r = minimal_rotvec(a, b)
    assert np.allclose(r[0], [0, 0, np.pi / 2]) and np.allclose(r[1:], 0)   # opposite: zero (the blend)
    h = minimal_rotvec(a, b, opposite="half_turn")
    assert np.isclose(np.linalg.norm(h[1]), np.pi) and abs(h[1] @ a[1]) < 1e-12
    assert np.allclose(Rotation.from_rotvec(h).apply(a / np.linalg.norm(a, axis=1, keepdims=True)),
                       b / np.linalg.norm(b, axis=1, keepdims=True))


def _svd_fit(P: np.ndarray, Q: np.ndarray, mirrored: bool) -> tuple[np.ndarray, float]:
    """Oracle: the proper rotation maximising trace(Rᵀ C), C = Σ (q - q̄)(p - p̄)ᵀ, by SVD,
    and a tolerance: rounding amplified by the fit's conditioning (the gap that
    matters is σ1 + σ2, or σ1 - σ2 where the best rotation fits a reflection)."""
    C = (Q - Q.mean(0)).T @ (P - P.mean(0))
    U, sv, Vt = np.linalg.svd(C)
    gap = sv[1] - sv[2] if mirrored else sv[1] + sv[2]
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt, 1e-12 + 1e-9 * sv[0] / gap


def _fit_rest(rng, shape: str, offset_scale: float) -> tuple[HandleSet, np.ndarray]:
    """Rest handles for the R_g fit tests (flat for "coplanar"), moved off the origin by
    offset_scale, and their positions P (M, 3): point handles, then segment ends."""
    rest = random_rest(rng, int(rng.integers(1, 5)), int(rng.integers(1, 4)))
    offset = rng.normal(size=3) * offset_scale
    flat = [1, 1, 0] if shape == "coplanar" else [1, 1, 1]
    rest = HandleSet.make(points=rest.points * flat + offset, segments=rest.segments * flat + offset)
    return rest, np.concatenate([rest.points, rest.segments.reshape(-1, 3)])


def _fit_target(rng, shape: str, P: np.ndarray, shift_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, Q): a random rotation and the posed positions Q = R P (mirrored first for
    "mirrored", noisy for "noisy") shifted by a random vector times shift_scale."""
    R = Rotation.random(random_state=rng).as_matrix()
    Q = ((P * [-1, 1, 1]) if shape == "mirrored" else P) @ R.T + rng.normal(size=3) * shift_scale
    if shape == "noisy":
        Q = Q + rng.normal(scale=0.2, size=Q.shape)
    return R, Q


def _posed(rest: HandleSet, Q: np.ndarray) -> Pose:
    return Pose.make(rest, points=Q[: len(rest.points)], segments=Q[len(rest.points):].reshape(-1, 2, 3))


@pytest.mark.parametrize("shape", ["general", "noisy", "coplanar", "mirrored"])
def test_global_rotation_fit(shape):
    """R_g (kabsch, and GlobalRotation's centred-once form) against an SVD oracle:
    random rotations, noise, coplanar handles (rank-2 covariance), and a target
    that is the mirror image (the best proper rotation, not the reflection); rest
    and pose far from the origin too (GlobalRotation does not centre the posed side)."""
    from nrpose.pose.blend import GlobalRotation, global_rotation
    from nrpose.model.rotation import kabsch

    rng = np.random.default_rng(["general", "noisy", "coplanar", "mirrored"].index(shape))
    for trial in range(24):
        rest, P = _fit_rest(rng, shape, [1.0, 1e3, 1e6][trial % 3])
        R, Q = _fit_target(rng, shape, P, [1.0, 1e6][trial % 2])
        pose = _posed(rest, Q)
        want, tol = _svd_fit(P, Q, shape == "mirrored")
        fit = GlobalRotation(rest)
        for got in (kabsch(P, Q), global_rotation(rest, pose), fit(pose)):
            assert np.allclose(got @ got.T, np.eye(3), atol=1e-12) and np.linalg.det(got) > 0
            assert np.abs(got - want).max() < tol, (shape, trial)
        if shape in ("general", "coplanar"):    # exact rigid motions: R itself
            assert np.abs(fit(pose) - R).max() < tol


@pytest.mark.parametrize("shape", ["general", "noisy", "coplanar", "mirrored"])
def test_global_fit_on_device(shape):
    """The device's R_g fit (kernels/global_fit.h) against the SVD oracle and its
    float64 reference, several frames per launch. It reads float32 positions, so
    the tolerance is float32 rounding amplified by the fit's conditioning, with rest
    and pose up to 30 handle spans from the origin."""
    from nrpose.pose.blend import GlobalRotation
    from nrpose.pose.mls import GlobalFit

    rng = np.random.default_rng(10 + ["general", "noisy", "coplanar", "mirrored"].index(shape))
    for trial in range(12):
        rest, P = _fit_rest(rng, shape, [0.0, 1.0, 10.0][trial % 3])
        poses, wants = [], []
        for frame in range(3):
            _, Q = _fit_target(rng, shape, P, 10.0)
            poses.append(_posed(rest, Q))
            want, tol = _svd_fit(P, Q, shape == "mirrored")
            wants.append((want, 2e3 * tol + 1e-6))   # float32 positions: ~60x float64 rounding, offsets
        got = GlobalFit.fit(rest, poses)
        assert got.dtype == np.float32 and got.shape == (3, 3, 3)
        for g, pose, (want, tol) in zip(got, poses, wants):
            assert np.abs(g - want).max() < tol, (shape, trial)
            assert np.abs(g - GlobalRotation(rest)(pose)).max() < tol, (shape, trial)


def test_global_fit_on_device_ties():
    """Non-unique fits on the device as in the reference: collinear handles take the
    minimal rotation between the two lines, a single handle the identity, and handles
    posed on one line what the float64 reference takes."""
    from nrpose.pose.blend import GlobalRotation
    from nrpose.pose.mls import GlobalFit
    from nrpose.model.rotation import minimal_rotvec

    rng = np.random.default_rng(6)
    for trial in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        offset, move = rng.normal(size=(2, 3)) * [1.0, 10.0][trial % 2]
        s = rng.uniform(0.1, 3.0)
        line_p = np.array([[0.0, 0, 0], s * a]) + offset
        line_q = np.array([[0.0, 0, 0], s * b / np.linalg.norm(b) * np.linalg.norm(a)]) + move
        want = Rotation.from_rotvec(minimal_rotvec(a, b)).as_matrix()
        two_points = HandleSet.make(points=line_p)
        one_segment = HandleSet.make(segments=line_p[None])
        assert np.abs(GlobalFit.fit(two_points, [Pose.make(two_points, points=line_q)])[0] - want).max() < 2e-5
        assert np.abs(GlobalFit.fit(one_segment, [Pose.make(one_segment, segments=line_q[None])])[0]
                      - want).max() < 2e-5
        single = HandleSet.make(points=offset[None])
        assert np.array_equal(GlobalFit.fit(single, [Pose.make(single, points=(offset + move)[None])])[0],
                              np.eye(3, dtype=np.float32))
        # ties made by the pose: rest handles in general position, posed on one line
        # (rank-1 covariance); float32 rounding of the posed side must not break the tie
        spread = HandleSet.make(points=rng.normal(size=(4, 3)) + offset)
        on_line = move + rng.normal(size=(4, 1)) * b
        pose = Pose.make(spread, points=on_line)
        assert np.abs(GlobalFit.fit(spread, [pose])[0] - GlobalRotation(spread)(pose)).max() < 2e-5, trial


def test_global_rotation_ties():
    """Fits that are not unique take the optimal rotation nearest the identity: for
    collinear handles (two point handles, one segment) the minimal rotation between
    the two lines, for a single point handle the identity; also far from the origin."""
    from nrpose.pose.blend import GlobalRotation
    from nrpose.model.rotation import kabsch, minimal_rotvec

    rng = np.random.default_rng(5)
    for trial in range(30):
        a, b = rng.normal(size=3), rng.normal(size=3)
        offset = rng.normal(size=3) * [1.0, 1e4][trial % 2]
        move = rng.normal(size=3) * [1.0, 1e4][trial % 2]
        s = rng.uniform(0.1, 3.0, size=2)
        line_p = np.array([[0.0, 0, 0], s[0] * a]) + offset
        line_q = np.array([[0.0, 0, 0], s[0] * b / np.linalg.norm(b) * np.linalg.norm(a)]) + move
        want = Rotation.from_rotvec(minimal_rotvec(a, b)).as_matrix()
        two_points = HandleSet.make(points=line_p)
        one_segment = HandleSet.make(segments=line_p[None])
        for rest, pose in ((two_points, Pose.make(two_points, points=line_q)),
                           (one_segment, Pose.make(one_segment, segments=line_q[None]))):
            assert np.abs(GlobalRotation(rest)(pose) - want).max() < 1e-9, trial
        assert np.abs(kabsch(line_p, line_q) - want).max() < 1e-9
        single = HandleSet.make(points=offset[None])
        assert np.abs(GlobalRotation(single)(Pose.make(single, points=(offset + move)[None])) - np.eye(3)).max() < 1e-12


def test_global_fit_half_turn_ties():
    """When every optimal rotation is a half turn (collinear handles posed reversed: a
    circle of half turns about the axes perpendicular to the line), the reference and
    the device both take the one whose axis is nearest x, or y where the line is within
    30 degrees of x, also 1000 line lengths from the origin, where the device's float32
    positions leave a noise projection of the identity; a unique half turn (handles in
    general position turned by 180 degrees) is that turn on both."""
    from nrpose.pose.blend import GlobalRotation
    from nrpose.pose.mls import GlobalFit

    rng = np.random.default_rng(29)
    dirs = [rng.normal(size=3) for _ in range(6)] + [np.array([1.0, 0.1, -0.05]), np.array([1.0, 0, 0]),
                                                      np.array([0, 0, 1.0])]
    for trial, d in enumerate(dirs):
        d = d / np.linalg.norm(d)
        e = np.eye(3)[0 if abs(d[0]) <= np.sqrt(0.75) else 1]
        n = e - (e @ d) * d
        n /= np.linalg.norm(n)
        want = 2 * np.outer(n, n) - np.eye(3)
        far = [5.0, 100.0, 1000.0][trial % 3]     # up to ~1000 line lengths out
        offset, move = rng.normal(size=(2, 3)) * far
        tol = 2e-5 * max(1.0, far / 30)          # float32 positions: ulp(far) / line length
        line = offset + np.array([[0.0], [1.3]]) * d
        reversed_line = move + np.array([[1.3], [0.0]]) * d
        two_points, one_segment = HandleSet.make(points=line), HandleSet.make(segments=line[None])
        for rest, pose in ((two_points, Pose.make(two_points, points=reversed_line)),
                           (one_segment, Pose.make(one_segment, segments=reversed_line[None]))):
            assert np.abs(GlobalRotation(rest)(pose) - want).max() < 1e-9, trial
            assert np.abs(GlobalFit.fit(rest, [pose])[0] - want).max() < tol, trial
    for trial in range(5):
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis))
        rest = HandleSet.make(points=rng.normal(size=(5, 3)))
        pose = Pose.make(rest, points=turn.apply(rest.points) + rng.normal(size=3))
        assert np.abs(GlobalRotation(rest)(pose) - turn.as_matrix()).max() < 1e-9, trial
        assert np.abs(GlobalFit.fit(rest, [pose])[0] - turn.as_matrix()).max() < 2e-5, trial


def test_global_fit_needs_double_precision(monkeypatch):
    """A device without cl_khr_fp64 cannot fit R_g: a DeviceError that says so and what to do."""
    from nrpose import DeviceError, device
    from nrpose.pose.mls import GlobalFit

    class NoDoubles:
        extensions = "cl_khr_global_int32_base_atomics cl_khr_byte_addressable_store"

    monkeypatch.setattr(device, "context", lambda: (type("Ctx", (), {"devices": [NoDoubles()]})(), None))
    with pytest.raises(DeviceError, match="cl_khr_fp64.*PYOPENCL_CTX"):
        GlobalFit(HandleSet.make(points=np.eye(3)))



def kernel_angle_per_sine(s2: np.ndarray, c: np.ndarray, source: str | None = None) -> np.ndarray:
    """kernels/nrmls.cl angle_per_sine on float32 arrays s2, c (any length): float32 result."""
    import pyopencl as cl
    from importlib import resources

    ctx, queue = device.context()
    src = (source or resources.files("nrpose.kernels").joinpath("nrmls.cl").read_text()) + (
        "\n__kernel void aps(__global const float8 *s2, __global const float8 *c, __global float8 *y)\n"
        "{ const int i = get_global_id(0); y[i] = angle_per_sine(s2[i], c[i]); }\n")
    prg = cl.Program(ctx, device.with_headers(src)).build(options=["-DVW=8", "-DNPOINTS=1", "-DNSLOTS=0"])
    n, pad = len(s2), -len(s2) % 8
    args = [np.concatenate([a, np.ones(pad)]).astype(np.float32) for a in (s2, c)]
    mf = cl.mem_flags
    bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in args]
    yb = cl.Buffer(ctx, mf.WRITE_ONLY, args[0].nbytes)
    prg.aps(queue, (len(args[0]) // 8,), None, *bufs, yb)
    y = np.empty_like(args[0])
    cl.enqueue_copy(queue, y, yb)
    return y[:n]


def test_angle_per_sine_against_float64():
    """kernels/nrmls.cl angle_per_sine(s2, c) = atan2(sqrt(s2), c) / sqrt(s2), the point
    handles' and the rotation table's angle over sine, against float64: on random angles
    in [0, pi] with magnitudes 1e-9 to 1e9, near 0, pi/2 and pi, and at its octant switch
    (s2 = c^2: angles of exactly pi/4 and 3pi/4, and one float of s2 either side): within
    1e-6 relative, finite everywhere (its domain: normal s2)."""
    rng = np.random.default_rng(7)
    theta = np.concatenate([rng.uniform(0, np.pi, 4000), [1e-7, 1e-3, np.pi / 2, np.pi - 1e-3, np.pi - 1e-6]])
    size = 10.0 ** rng.uniform(-9, 9, len(theta))
    cb = np.float32([1.0, -1.0, 3.5e-4, -2.0e5, 7.25, -7.25])
    c2b = cb * cb
    s2 = np.concatenate([(size * np.sin(theta)) ** 2, c2b, np.nextafter(c2b, np.float32(np.inf)),
                         np.nextafter(c2b, np.float32(0))]).astype(np.float32)
    c = np.concatenate([size * np.cos(theta), cb, cb, cb]).astype(np.float32)
    assert (s2 >= np.float32(1.17549435e-38)).all()
    y = kernel_angle_per_sine(s2, c)
    s = np.sqrt(s2.astype(np.float64))
    assert np.isfinite(y).all()
    assert np.abs(y / (np.arctan2(s, c.astype(np.float64)) / s) - 1).max() < 1e-6
    # exactly pi/4 and 3pi/4 (s2 == c^2)
    exact = y[len(theta): len(theta) + len(cb)] * np.abs(cb)
    assert np.allclose(exact, np.where(cb > 0, np.pi / 4, 3 * np.pi / 4), rtol=1e-6, atol=0)
