"""Benchmark: LBS / DQS skinning kernels vs the float64 numpy references.

Mannequin-size synthetic rig: N = 15,882 vertices, J = 65 joints, K = 4
influences per vertex (the 4 nearest joints, inverse-square-distance weights,
vertices ordered by dominant joint as mesh exporters tend to leave them).

Reports medians (ms) of:
  * ``pose``          -- the full ``Skinner.pose(mats)`` call: validation,
                         float32 upload, one kernel launch, read-back to float64;
  * ``pose_frames``   -- ``pose_frames`` of F frames in one launch, per frame;
  * ``kernel``        -- kernel execution alone for one frame, launched as ``pose``
                         launches it (OpenCL profiling events, first start to last
                         end over the devices that ran it);
  * ``reference``     -- the numpy float64 reference on the same inputs.

Writes bench/results/skinning.json. Usage: ``python bench/bench_skinning.py [--repeat R]``.
Not a test; keep runs short on the shared 2-core machine.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import time

import numpy as np
from scipy.spatial.transform import Rotation

from nrpose import device, diagnostics
from nrpose.pose.skinning import Skinner, dqs_reference, lbs_reference

N, J, K, FRAMES = 15_882, 65, 4, 16
ROOT = pathlib.Path(__file__).resolve().parent


def rig(seed: int = 0):
    rng = np.random.default_rng(seed)
    joint_pos = rng.normal(size=(J, 3)) * np.array([0.3, 0.8, 0.15]) + np.array([0, 0.9, 0])
    rest = rng.normal(size=(N, 3)) * np.array([0.3, 0.8, 0.15]) + np.array([0, 0.9, 0])
    d2 = ((rest[:, None, :] - joint_pos[None]) ** 2).sum(-1)
    joints = np.argsort(d2, axis=1)[:, :K]
    weights = 1.0 / (np.take_along_axis(d2, joints, 1) + 1e-4)
    order = np.lexsort((rest[:, 1], joints[:, 0]))
    mats = np.tile(np.eye(4), (FRAMES, J, 1, 1))
    mats[:, :, :3, :3] = Rotation.random(FRAMES * J, random_state=1).as_matrix().reshape(FRAMES, J, 3, 3)
    mats[:, :, :3, 3] = rng.normal(size=(FRAMES, J, 3)) * 0.1
    return rest[order], joints[order], weights[order], mats


def median_ms(fn, repeat: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e3)


def kernel_ms(deformer: Skinner, frame_mats, repeat: int) -> float:
    """Kernel execution time of one frame, launched as a pose launches it (shared with the
    workers or not, device.launch_shared), from profiling events on private queues: the
    first start to the last end over the devices that ran it."""
    deformer.pose(frame_mats)                 # a launch of one frame to repeat
    queues = device.profiling_queues()
    times = []
    for _ in range(repeat):
        events = diagnostics.relaunch(deformer, queues=queues)
        times.append(device.events_span_s(events) * 1e3)
    return float(np.median(times))


def git_commit() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                             text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "kernels/skinning.cl", "kernels/share.h",
                                "kernels/lanes.h", "nrpose/pose/skinning.py", "nrpose/device"], cwd=ROOT.parent, capture_output=True,
                               text=True).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=200, help="timed calls per device median")
    args = ap.parse_args()
    rest, joints, weights, mats = rig()
    results = {}
    for method, ref in (("lbs", lbs_reference), ("dqs", dqs_reference)):
        d = Skinner(rest, joints, weights, method=method)
        err = np.abs(d.pose(mats[0]) - ref(rest, joints, weights, mats[0])).max()
        frame = iter(range(10**9))
        results[method] = {
            "pose_ms": median_ms(lambda: d.pose(mats[next(frame) % FRAMES]), args.repeat),
            "pose_frames_ms_per_frame": median_ms(lambda: d.pose_frames(mats),
                                                  max(5, args.repeat // FRAMES)) / FRAMES,
            "kernel_ms": kernel_ms(d, mats[0], args.repeat),
            "reference_ms": median_ms(lambda: ref(rest, joints, weights, mats[0]),
                                      max(5, args.repeat // 20)),
            "max_abs_error_vs_reference": float(err),
        }
        r = results[method]
        r["speedup_pose_vs_reference"] = r["reference_ms"] / r["pose_ms"]
    record = {
        "benchmark": "skinning", "n_vertices": N, "n_joints": J, "n_influences": K,
        "frames_per_batch": FRAMES, "repeat": args.repeat,
        "device": device.describe(), "git_commit": git_commit(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "results": results,
    }
    out = ROOT / "results" / "skinning.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"skinning N={N} J={J} K={K} on {record['device']['device']} ({record['git_commit'][:12]})")
    print(f"{'method':6} {'pose':>8} {'batch/fr':>9} {'kernel':>8} {'numpy':>8} {'speedup':>8} {'max err':>9}")
    for m, r in results.items():
        print(f"{m:6} {r['pose_ms']:7.3f}m {r['pose_frames_ms_per_frame']:8.3f}m "
              f"{r['kernel_ms']:7.3f}m {r['reference_ms']:7.2f}m {r['speedup_pose_vs_reference']:7.1f}x "
              f"{r['max_abs_error_vs_reference']:9.2e}")
    print(f"(medians in ms; wrote {out.relative_to(ROOT.parent)})")


if __name__ == "__main__":
    main()
