"""Scaling suite: pose time against points x handles, dense blend and sparse skeleton posing.

Shape: a deterministic synthetic skeleton of H bones (a tree: bone i hangs off
the end of one of the 4 bones before it, unit length, random direction; seed
fixed) and N points sampled around it (a bone chosen uniformly, a uniform
parameter along it, Gaussian offset sigma 0.15). Poses: forward kinematics with
a random local rotation per bone (random axis, angle <= 30 deg), posed segments
and rotations passed to the engine as the skeleton posing does (no Pose.make
validation: built by FK, consistent).

* ``dense``: ``Deformer(points, bones)`` (k = None, every point sees every bone,
  as the paper's blend), run only where N*H <= DENSE_MAX (2e7 point-handles):
  binding builds several dense (N, H[, 3]) float64 arrays.
* ``sparse``: ``Deformer(points, bones, k=8)`` (what CharacterPoser does on
  skeletons of more than 8 bones), run where N*H <= SPARSE_MAX (6.5e7: the
  1M x 65 target; binding it takes ~9 s and ~2 GB peak RSS in the committed run).

Per size: bind wall time and the process's peak RSS after it, then rounds of
``posed = Deformer.pose(pose)`` back to back (wall; each result held until the next is made,
as Table 1 times them), then each pose again followed by
one timing of its pose kernel as the roofline suite times it (``Roofs.pose_kernel_once``: as a
frame loop runs it, from the job's publication; its prologue included); medians. Fits per mode, on the
pose medians: t = c0 + c1 N + c2 N H (least squares, ms) and t = a (N H)^b.
"""
from __future__ import annotations

import gc
import time

import numpy as np

import common
from nrpose.pose.mls import Deformer
from nrpose.model.handles import HandleSet, Pose
from nrpose.model.rotation import Rotation

POINTS = (10_000, 31_623, 100_000, 316_228, 1_000_000)
HANDLES = (4, 16, 65, 128)
K_SPARSE = 8
DENSE_MAX = 2e7
SPARSE_MAX = 6.5e7
QUICK_POINTS = (500, 2_000)
QUICK_HANDLES = (4, 12)
TARGET = {"points": 1_000_000, "handles": 65, "k": 8, "pose_ms_max": 25.0}


def skeleton(H: int, seed: int = 0):
    """(segments (H, 2, 3), parents (H,)) of the synthetic tree skeleton."""
    rng = np.random.default_rng(seed + 1000 * H)
    segs = np.zeros((H, 2, 3))
    parent = np.full(H, -1)
    for i in range(H):
        if i:
            parent[i] = rng.integers(max(0, i - 4), i)
            segs[i, 0] = segs[parent[i], 1]
        d = rng.normal(size=3)
        segs[i, 1] = segs[i, 0] + d / np.linalg.norm(d)
    return segs, parent


def cloud(segs: np.ndarray, N: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed + 7)
    b = rng.integers(0, len(segs), N)
    t = rng.random(N)[:, None]
    return segs[b, 0] + t * (segs[b, 1] - segs[b, 0]) + rng.normal(size=(N, 3)) * 0.15


def fk_poses(segs: np.ndarray, parent: np.ndarray, n: int, seed: int = 0) -> list[Pose]:
    """n FK poses: local rotations <= 30 deg about random axes, root start fixed."""
    rng = np.random.default_rng(seed + 99)
    H = len(segs)
    poses = []
    for _ in range(n):
        axis = rng.normal(size=(H, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        local = Rotation.from_rotvec(axis * rng.uniform(0, np.radians(30), (H, 1))).as_matrix()
        R = np.zeros((H, 3, 3))
        posed = np.zeros((H, 2, 3))
        for i in range(H):
            p = parent[i]
            R[i] = local[i] if p < 0 else R[p] @ local[i]
            start = segs[i, 0] if p < 0 else posed[p, 1]
            posed[i] = (start, start + R[i] @ (segs[i, 1] - segs[i, 0]))
        poses.append(Pose(HandleSet(np.zeros((0, 3)), posed), R))
    return poses


def grid(quick: bool) -> list[tuple[str, int, int]]:
    pts, hs = (QUICK_POINTS, QUICK_HANDLES) if quick else (POINTS, HANDLES)
    out = []
    for mode, cap in (("dense", DENSE_MAX), ("sparse", SPARSE_MAX)):
        for H in hs:
            for N in pts:
                if N * H <= cap or quick:
                    out.append((mode, N, H))
    return out


def measure(mode: str, N: int, H: int, repeat: int, roofs, quick: bool) -> dict:
    from roofline import lane_divergence, pose_work
    segs, parent = skeleton(H)
    pts = cloud(segs, N)
    rest = HandleSet.make(segments=segs)
    k = K_SPARSE if mode == "sparse" else None
    rss0 = common.peak_rss_gb()
    t0 = time.perf_counter()
    d = Deformer(pts, rest, k=k)
    bind_s = time.perf_counter() - t0
    rss1 = common.peak_rss_gb()
    del pts
    poses = fk_poses(segs, parent, 4 if quick else 8)
    for p in poses[:3]:
        out = d.pose(p)
    # small sizes are cheap: more rounds (up to 20) for steadier medians
    rounds = max(repeat, 1) if quick or N >= 300_000 else min(20, max(repeat, -(-3_000_000 // (N * min(H, 16)))))
    wall, kern = [], []
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for _ in range(rounds):
            # the poses back to back as frames are posed (a standing worker serves them; each
            # result held until the next is made, as Table 1 times them), then each again with
            # its kernel timed as a frame loop runs it (roofline.Roofs.pose_kernel_once)
            for p in poses:
                t = time.perf_counter()
                out = d.pose(p)
                wall.append(time.perf_counter() - t)
            for p in poses if roofs is not None else ():
                out = d.pose(p)
                kern.append(roofs.pose_kernel_once(d)[0])
    finally:
        if gc_was:
            gc.enable()
    if not np.isfinite(out).all():
        raise RuntimeError(f"scaling {mode} N={N} H={H}: non-finite posed points")
    row = {"mode": mode, "points": N, "handles": H, "k": k, "slots": d.slots,
           "point_handles": N * H, "bind_ms": bind_s * 1e3,
           "peak_rss_gb_after_bind": rss1, "peak_rss_gb_before_bind": rss0,
           "pose_ms": common.stats(wall), "load": common.load(), "work": dict(pose_work(d), lanes=lane_divergence(d))}
    if kern:
        row["kernel_ms"] = common.stats(kern)
    del d
    gc.collect()
    return row


def fit(rows: list[dict]) -> dict:
    """Least-squares fits of the median pose time (ms) of one mode."""
    N = np.array([r["points"] for r in rows], float)
    H = np.array([r["handles"] for r in rows], float)
    t = np.array([r["pose_ms"]["median"] for r in rows])
    out = {"n": len(rows)}
    if len(rows) >= 3:
        A = np.stack([np.ones_like(N), N, N * H], 1)
        c, *_ = np.linalg.lstsq(A, t, rcond=None)
        pred = A @ c
        out["linear"] = {"model": "t_ms = c0 + c1 * N + c2 * N * H", "c0_ms": float(c[0]),
                         "c1_ns_per_point": float(c[1] * 1e6), "c2_ns_per_point_handle": float(c[2] * 1e6),
                         "r2": float(1 - np.sum((t - pred) ** 2) / max(np.sum((t - t.mean()) ** 2), 1e-300)),
                         "max_rel_residual": float(np.max(np.abs(pred - t) / t))}
    if len(rows) >= 2:
        b, a = np.polyfit(np.log(N * H), np.log(t), 1)
        out["power"] = {"model": "t_ms = a * (N * H)^b", "a_ms": float(np.exp(a)), "b": float(b)}
    return out


def run(repeat: int = 5, quick: bool = False, roofs=None, log=None) -> dict:
    rows = []
    for mode, N, H in grid(quick):
        r = measure(mode, N, H, repeat, roofs, quick)
        rows.append(r)
        if log:
            log(f"scaling {mode:6s} N={N:8d} H={H:4d} bind {r['bind_ms'] / 1e3:7.2f} s  pose "
                f"{r['pose_ms']['median']:8.3f} ms" + (f"  kernel {r['kernel_ms']['median']:8.3f} ms"
                                                         if "kernel_ms" in r else "")
                + f"  rss {r['peak_rss_gb_after_bind']:.1f} GB  load {r['load'][:1]}")
    fits = {m: fit([r for r in rows if r["mode"] == m]) for m in ("dense", "sparse")}
    tgt = next((r for r in rows if r["mode"] == "sparse" and r["points"] == TARGET["points"]
                and r["handles"] == TARGET["handles"]), None)
    return {"grid": {"points": list(QUICK_POINTS if quick else POINTS),
                     "handles": list(QUICK_HANDLES if quick else HANDLES),
                     "dense_max_point_handles": DENSE_MAX, "sparse_max_point_handles": SPARSE_MAX,
                     "k_sparse": K_SPARSE,
                     "rule": "dense runs where N*H <= 2e7, sparse (k=8) where N*H <= 6.5e7 (the 1M x 65 "
                             "target; bind time grows with N*H); quick mode runs every cell of its tiny grid"},
            "shape": "synthetic tree skeleton of H unit bones, N points around it (see bench/scaling.py)",
            "rows": rows, "fits": fits,
            "target": dict(TARGET, measured=tgt["pose_ms"]["median"] if tgt else None,
                           met=(tgt["pose_ms"]["median"] <= TARGET["pose_ms_max"]) if tgt else None,
                           bind_ms=tgt["bind_ms"] if tgt else None,
                           peak_rss_gb=tgt["peak_rss_gb_after_bind"] if tgt else None)}
