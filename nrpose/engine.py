"""Bind once, pose many: the near-rigid MLS deformer on OpenCL (or the numpy reference).

    deformer = Deformer(points, rest_handles, alpha=1.0)        # bind: rest-only work
    posed = deformer.pose(pose)                                   # per frame: (N, 3)

Binding computes :class:`nrpose.blend.RestTerms` in float64 on the host and
uploads them once (float32) to the device; the kernel objects and buffers
live as long as the deformer. A pose uploads one buffer of per-handle data
(posed handle positions, the S+1 reference rotations and the table of
relative rotation vectors, ~(P + 2S)·3 + (S+1)·(9 + 3S) floats) and runs one
kernel.

``backend="numpy"`` runs :func:`nrpose.blend.pose_reference` instead (float64);
nothing ever falls back to it silently.
"""
from __future__ import annotations

import numpy as np

from . import device
from .blend import BLENDS, RestTerms, global_rotation, pose_reference, rest_terms
from .errors import InputError
from .handles import HandleSet, Pose

BACKENDS = ("opencl", "numpy")
LANES = 8  # points per work-item (float8)


class Deformer:
    """A point set bound to rest handles.

    points: (N, 3) rest positions; rest: rest handles; alpha: weight exponent;
    blend: "relative" (default, equivariant) or "paper"; lever: "length"
    (default) or "paper" (see :mod:`nrpose.blend`); distances / weights:
    optional (N, H) matrices replacing Euclidean distances / giving the w_i.
    """

    def __init__(self, points, rest: HandleSet, alpha: float = 1.0, blend: str = "relative",
                 lever: str = "length", distances=None, weights=None, backend: str = "opencl"):
        if backend not in BACKENDS:
            raise InputError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if blend not in BLENDS:
            raise InputError(f"blend must be one of {BLENDS}, got {blend!r}")
        self.rest = rest
        self.blend = blend
        self.backend = backend
        self.terms: RestTerms = rest_terms(points, rest, alpha, lever, distances, weights)
        self.n = len(self.terms.u)
        if backend == "opencl":
            self._bind_device()

    # -- device ---------------------------------------------------------------
    def _bind_device(self) -> None:
        import pyopencl as cl

        ctx, self._queue = device.context()
        T, blend = self.terms, self.blend
        P, S = len(self.rest.points), len(self.rest.segments)
        n, npad = self.n, -(-self.n // LANES) * LANES
        self._npad = npad

        def soa(rows: np.ndarray) -> np.ndarray:  # (rows, N) -> (rows, Npad) float32
            out = np.zeros((rows.shape[0], npad), np.float32)
            out[:, :n] = rows
            return out

        # store points sorted by reference rotation so that a work-item's lanes
        # share it; `row` sends each stored point back to its caller's row
        order = np.argsort(T.ref, kind="stable")
        w, t = T.weights[order], T.t[order]
        coef = np.concatenate([w[:, :P].T, np.stack([w[:, P:] * (1 - t), w[:, P:] * t], 2).reshape(n, 2 * S).T])
        ref = np.full(npad, S, np.int32)
        ref[:n] = T.ref[order]
        row = np.arange(npad, dtype=np.int32)
        row[:n] = order
        arrays = {
            "u": soa(T.u[order].T), "ref": ref, "row": row, "coef": soa(coef), "lever": soa(T.lever[order].T),
            "phat": soa(T.phat[order].transpose(1, 2, 0).reshape(3 * P, n)) if P else np.zeros(1, np.float32),
        }
        mf = cl.mem_flags
        self._bufs = {k: cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))
                      for k, a in arrays.items()}
        self._bufs["derived"] = cl.Buffer(ctx, mf.READ_WRITE, 4 * (9 * (S + 1) + 3 * (S + 1) * S))
        self._npos = 3 * (P + 2 * S)
        self._pose = device.HostArray(self._npos + 9 * (S + 1))
        self._pose.host[self._npos + 9 * S:] = np.eye(3).ravel()   # R_g until a pose needs it
        self._needs_global = blend == "relative" and bool((T.ref == S).any())
        self._out = device.HostArray(3 * npad)
        prg = device.program("nrmls.cl")
        self._prepare = cl.Kernel(prg, "nrmls_prepare")
        self._prepare.set_args(np.int32(P), np.int32(S), np.int32(blend == "paper"), self._pose.arg,
                               self._bufs["derived"])
        self._kernel = cl.Kernel(prg, "nrmls_pose")
        b = self._bufs
        self._kernel.set_args(np.int32(npad), np.int32(P), np.int32(S), b["u"], b["ref"], b["row"], b["coef"],
                              b["lever"], b["phat"], self._pose.arg, b["derived"], self._out.arg, np.int32(1))

    def pose(self, pose: Pose) -> np.ndarray:
        """Posed points (N, 3): float32 on OpenCL, float64 on numpy."""
        self.rest.same_layout(pose.handles, "posed handles")
        if self.backend == "numpy":
            return pose_reference(self.terms, self.rest, pose, self.blend)
        import pyopencl as cl

        h, host, k = pose.handles, self._pose.host, self._npos
        host[: 3 * len(h.points)] = h.points.ravel()
        host[3 * len(h.points): k] = h.segments.ravel()
        host[k: k + pose.rotations.size] = pose.rotations.ravel()
        if self._needs_global:
            host[k + pose.rotations.size:] = global_rotation(self.rest, pose).ravel()
        self._pose.upload()
        S = len(self.rest.segments)
        q = self._queue
        cl.enqueue_nd_range_kernel(q, self._prepare, ((S + 1) * (S + 1),), None)
        cl.enqueue_nd_range_kernel(q, self._kernel, (self._npad // LANES,), None)
        self._out.download()
        return self._out.host[: 3 * self.n].reshape(self.n, 3).copy()
