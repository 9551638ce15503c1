"""Every kernel of nrpose on tiny inputs against its float64 reference, for a run on
another OpenCL device (tests/test_oclgrind.py runs it under Oclgrind, in a process of its
own: the device is chosen once per process, by PYOPENCL_CTX).

    python tests/kernel_cases.py [--save OUT.npz] [--fill BITS]

prints one JSON object, case -> max error / tolerance, and with --save writes every
case's device output (float32 as the device gave it, for bitwise comparisons between
devices: tests/test_second_pocl.py). Each case is posed with several blocks of work (so
that launches have more than one work-group) and, for the pose kernels, as one frame, as
a batch of frames and as a batch into a frames_array (the kernel writing the caller's
memory). An error above 1 means the kernel is off its reference by more than the tests'
tolerance.

--fill BITS (a 32-bit pattern, e.g. 0x7fc0dead) is the canary of tests/test_canary.py:
every device array nrpose makes (:class:`nrpose.device.HostArray`: outputs, frame
blocks, scratch, handoff slots, frames_array memory, on the host and on the device) and
every output array given to a kernel here starts filled with BITS instead of whatever
memory held, and --save also writes each such array as it ends ("memory NNN", uint32
bits, in the order they were made; "mailbox NNN" for the job mailboxes), so that runs
with different BITS show which lanes nothing wrote (BITS in each run), which were written
with defined values (the same in every run) and which were written from memory nothing
had written (neither).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from test_mls import random_pose, random_rest  # noqa: E402  (tests' own helpers)
from test_skinning import affine, make_rig, rigid  # noqa: E402
from test_model_normals import sphere  # noqa: E402
from test_surface_rotations import TOL as SURFACE_TOL, bent  # noqa: E402

from nrpose import Deformer  # noqa: E402
from nrpose.device import HostArray  # noqa: E402
from nrpose.pose.mls import GlobalFit  # noqa: E402
from nrpose.pose.blend import GlobalRotation  # noqa: E402
from nrpose.pose.cor import CorSkinner, cor_reference  # noqa: E402
from nrpose.pose.skinning import DqsSkinner, LbsSkinner, dqs_reference, lbs_reference  # noqa: E402
from nrpose.model.normals import Surface, weld  # noqa: E402
from nrpose.pose.surface_rotations import SurfaceRotations  # noqa: E402

POINTS = 300        # a few blocks of work at 8 or 16 lanes
FRAMES = 3
#: of the bounding-box diagonal: tests/test_mls.py's for NR-MLS, test_skinning.py's for skinning
NRMLS_TOL, SKIN_TOL = 1e-4, 1e-5

#: the --fill pattern (None: outputs given to kernels start as np.empty leaves them)
FILL: list = [None]


def fill_device_arrays(bits: int) -> list:
    """From now on, every HostArray made starts filled with the 32-bit pattern ``bits``
    (its host memory and, without shared memory, its device buffer); returns the list
    each is appended to, in the order they are made (kept alive: read at the end)."""
    made = []
    init = HostArray.__init__

    def filled(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.host.view(np.uint32)[:] = bits
        self.upload()
        made.append(self)

    HostArray.__init__ = filled
    FILL[0] = bits
    return made


def blank(shape) -> np.ndarray:
    """A float32 output array for a kernel: the --fill pattern where one is given."""
    out = np.empty(shape, np.float32)
    if FILL[0] is not None:
        out.view(np.uint32)[...] = FILL[0]
    return out


#: (name, point handles, segments, Deformer keywords): the kernel's build variants (point
#: handles only at 16 lanes, segments only with chunk pairs, both, sparse slots, the blends
#: and a lever rule with stored levers)
NRMLS = [("points", 3, 0, {}), ("segments", 0, 3, {}), ("mixed", 2, 2, {}),
         ("sparse", 1, 4, {"k": 3}), ("quaternion", 2, 2, {"blend": "quaternion"}),
         ("paper", 2, 2, {"blend": "paper", "lever": "paper"}), ("length", 0, 3, {"lever": "length"})]


def diag(x: np.ndarray) -> float:
    x = x.reshape(-1, 3)
    return float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))


def nrmls_cases(rng) -> dict:
    """NR-MLS pose kernel (kernels/nrmls.cl), one frame and a batch, and the numpy backend's:
    {case: (device output, reference, tolerance)}."""
    out = {}
    for name, p, s, kw in NRMLS:
        rest = random_rest(rng, p, s)
        pts = rng.uniform(-1, 1, (POINTS, 3))
        dev, ref = Deformer(pts, rest, **kw), Deformer(pts, rest, backend="numpy", **kw)
        poses = [random_pose(rng, rest) for _ in range(FRAMES)]
        want = np.stack([ref.pose(q) for q in poses])
        tol = NRMLS_TOL * diag(want)
        out[f"nrmls {name}"] = (dev.pose(poses[0]).copy(), want[0], tol)
        out[f"nrmls {name} batch"] = (dev.pose_frames(poses), want, tol)
        if name == "mixed":
            out[f"nrmls {name} frames_array"] = (dev.pose_frames(poses, out=dev.frames_array(FRAMES)), want, tol)
    return out


def skinning_cases(rng) -> dict:
    """LBS and DQS kernels (kernels/skinning.cl) and CoR's (kernels/cor.cl), one frame and a
    batch, and their references (float32 outputs: into float32 arrays, as the device wrote them)."""
    rest, joints, weights = make_rig(rng, POINTS, 5, 3)
    cor = CorSkinner(rest, joints, weights, None)
    out = {}
    for name, make, reference, mats in (
            ("lbs", lambda: LbsSkinner(rest, joints, weights), lbs_reference, [affine(rng, 5) for _ in range(FRAMES)]),
            ("dqs", lambda: DqsSkinner(rest, joints, weights), dqs_reference, [rigid(rng, 5) for _ in range(FRAMES)]),
            ("cor", lambda: cor, lambda *a: cor_reference(*a, cor.centers), [rigid(rng, 5) for _ in range(FRAMES)])):
        dev = make()
        want = np.stack([reference(rest, joints, weights, m) for m in mats])
        tol = SKIN_TOL * diag(want)
        out[name] = (dev.pose(mats[0], out=blank((POINTS, 3))), want[0], tol)
        out[f"{name} batch"] = (dev.pose_frames(np.stack(mats), out=blank((FRAMES, POINTS, 3))), want, tol)
        out[f"{name} frames_array"] = (dev.pose_frames(np.stack(mats), out=dev.frames_array(FRAMES)), want, tol)
    return out


def global_fit_cases(rng) -> dict:
    """R_g on its own (kernels/global_fit.cl) against nrpose.pose.blend.GlobalRotation."""
    rest = random_rest(rng, 3, 2)
    poses = [random_pose(rng, rest) for _ in range(FRAMES)]
    got = GlobalFit.fit(rest, poses)
    fit = GlobalRotation(rest)
    want = np.stack([fit(q) for q in poses])
    return {"global fit": (got, want, 1e-4)}


def surface_cases(rng) -> dict:
    """Neighbourhood rotations (kernels/surface.cl) of a bent sphere with several chunks of
    work, against Surface.rotations."""
    V, F = sphere(9)
    surface = Surface(V, F, weld(V))
    posed = bent(V, rng)
    return {"surface rotations": (SurfaceRotations(surface)(posed), surface.rotations(posed), SURFACE_TOL)}


def main() -> None:
    rng = np.random.default_rng(32)
    made = fill_device_arrays(int(sys.argv[sys.argv.index("--fill") + 1], 0)) if "--fill" in sys.argv else []
    cases = {**nrmls_cases(rng), **skinning_cases(rng), **global_fit_cases(rng), **surface_cases(rng)}
    memory = {}
    for i, a in enumerate(made):
        a.download()
        # int32 arrays are job mailboxes: protocol words (job tags count launches), not data
        memory[f"{'mailbox' if a.host.dtype == np.int32 else 'memory'} {i:03d}"] = a.host.view(np.uint32).copy()
    if "--save" in sys.argv:
        np.savez(sys.argv[sys.argv.index("--save") + 1], **{k: got for k, (got, _, _) in cases.items()}, **memory)
    print(json.dumps({k: float(np.abs(got - want).max() / tol) for k, (got, want, tol) in cases.items()}))


if __name__ == "__main__":
    main()
