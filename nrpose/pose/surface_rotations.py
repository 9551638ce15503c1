"""Neighbourhood rotations of posed frames on the device (kernels/surface.cl), for the normals
and tangents of baked ``.glb`` outputs.

:meth:`nrpose.model.normals.Surface.rotations` is the float64 reference: per welded position
the closest rotation to ``sum b^T B`` over the faces around it (b, B: their posed and bind edge
frames). :class:`SurfaceRotations` binds a :class:`~nrpose.model.normals.Surface` once and
computes the same for each frame in float32 on PoCL's threads (one shared launch, kernels/share.h);
the groups whose Newton iteration the kernel leaves unfinished (a determinant near zero or
negative: a folded or flattened neighbourhood) are finished on the host by
:func:`nrpose.model.normals.closest_rotations`, as the reference finishes them.
"""
from __future__ import annotations

import numpy as np

from .. import device
from ..model.bounds import column_bounds
from ..model.normals import Surface, closest_rotations

__all__ = ["SurfaceRotations", "PROGRAM", "DEVICE_MIN_VERTEX_FRAMES", "surface_rotations_for", "prefetch_program"]

#: the kernel file and build options
PROGRAM = ("surface.cl", ())
#: (starts, slots, faces, bind, rows, posed, out, stride, G, C, block, jobs, role): kernels/surface.cl
(ARG_STARTS, ARG_SLOTS, ARG_FACES, ARG_BIND, ARG_ROWS, ARG_POSED, ARG_OUT, ARG_STRIDE, ARG_G, ARG_C, ARG_BLOCK,
 ARG_JOBS, ARG_ROLE) = range(13)
LANES = 8          # groups per chunk (float8 lanes)
BLOCK = 32         # chunks per block of work taken from the job mailbox
FRAMES = 16        # frames per launch, at most
#: vertices x frames from which a bake's rotations go to the device: below, the reference's
#: ~1.5 us per vertex and frame costs less than a cold build of the kernel (~0.5 s)
DEVICE_MIN_VERTEX_FRAMES = 300_000


def prefetch_program() -> None:
    """Start building the kernel (:func:`nrpose.device.prefetch`), to overlap the posing."""
    device.prefetch(*PROGRAM)


def surface_rotations_for(vertices: int, frames: int, backend: str = "opencl"):
    """What a baked ``.glb`` of ``frames`` frames of ``vertices`` vertices computes its
    neighbourhood rotations with (``write_animated_glb``'s ``rotations``):
    :class:`SurfaceRotations` on the opencl backend from :data:`DEVICE_MIN_VERTEX_FRAMES`,
    else None (the float64 reference)."""
    return SurfaceRotations if backend == "opencl" and vertices * frames >= DEVICE_MIN_VERTEX_FRAMES else None


class SurfaceRotations:
    """:meth:`Surface.rotations` of posed frames, on the device.

    surface: the :class:`~nrpose.model.normals.Surface` of the N vertices posed. Calling the
    object with ``posed`` (N, 3) float positions of one frame returns the rotation of each
    vertex's neighbourhood, (N, 3, 3) float32 (frames (B, N, 3): (B, N, 3, 3)), within ~1e-5
    of the reference where the kernel's Newton iteration converges, the reference's own
    rounded where it does not.
    Not thread-safe (one job mailbox and one pair of arrays).
    """

    def __init__(self, surface: Surface):
        cl = device.pyopencl()
        self.surface = surface
        self.n, self.n_groups = len(surface.groups), surface.n_groups
        starts, slots, rows = lane_layout(surface)
        faces = np.vstack([surface.faces, np.zeros((1, 3), np.int64)])              # padding face M
        frames = surface.bind_frames.reshape(-1, 12)
        big = float(np.abs(frames).max(initial=0.0))
        bind = np.vstack([frames / (big if big > 0 else 1.0), np.zeros((1, 12))])   # a scale leaves R as it is
        ctx, _ = device.context()
        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        # (an element at least: a surface with no face has no slots, and OpenCL no empty buffers)
        self._bound = [cl.Buffer(ctx, ro, hostbuf=np.append(np.asarray(a, dtype).reshape(-1), dtype(0)))
                       for a, dtype in ((starts, np.int32), (slots, np.int32), (faces, np.int32),
                                        (bind, np.float32), (rows, np.int32))]
        self._posed = device.HostArray(FRAMES * 3 * self.n)
        self._out = device.HostArray(FRAMES * 10 * (self.n_groups + 1))
        self._jobs = device.Jobs(owner=self, bound_bytes=sum(b.size for b in self._bound))
        self._jobs.keep = (self._posed, self._out)
        self._kernel = cl.Kernel(device.program(*PROGRAM), "surface_rotations")
        chunks = len(rows)
        for arg, value in zip((ARG_STARTS, ARG_SLOTS, ARG_FACES, ARG_BIND, ARG_ROWS), self._bound):
            self._kernel.set_arg(arg, value)
        for arg, value in ((ARG_POSED, self._posed.arg), (ARG_OUT, self._out.arg), (ARG_STRIDE, np.int32(3 * self.n)),
                           (ARG_G, np.int32(self.n_groups)), (ARG_C, np.int32(chunks)), (ARG_BLOCK, np.int32(BLOCK)),
                           (ARG_JOBS, self._jobs.box.arg), (ARG_ROLE, np.int32(device.ROLE_CALLER))):
            self._kernel.set_arg(arg, value)
        self._blocks = -(-chunks // BLOCK)

    def __call__(self, posed: np.ndarray) -> np.ndarray:
        """Rotations (N, 3, 3) float32 of the neighbourhoods of ``posed`` (N, 3) from the bind;
        of frames (B, N, 3), (B, N, 3, 3), :data:`FRAMES` frames per launch."""
        posed = np.asarray(posed)
        if posed.ndim == 2:
            return self(posed[None])[0]
        if len(posed) <= FRAMES:
            return self._launch(posed)
        return np.concatenate([self._launch(posed[f:f + FRAMES]) for f in range(0, len(posed), FRAMES)])

    def _launch(self, posed: np.ndarray) -> np.ndarray:
        """Rotations (B, N, 3, 3) float32 of at most :data:`FRAMES` frames (B, N, 3), one launch."""
        frames = len(posed)
        # rotations do not change with a move or a scale: to the unit box, so that float32 keeps the
        # shape of a surface far from the origin and squared edge lengths (|e|^4) do not overflow
        low, high = column_bounds(posed) if posed.size else (0.0, 0.0)
        span = float(np.max(high - low))
        unit = self._posed.host[:posed.size].reshape(posed.shape)     # float32, written in place
        np.subtract(posed, low, out=unit, casting="same_kind")
        unit *= np.float32(1.0 / span) if span > 0 else np.float32(1.0)
        self._posed.upload()
        if self._blocks:
            device.launch_shared(self._kernel, self._jobs, self._blocks, frames)
        self._out.download()
        out = self._out.host[:frames * 10 * (self.n_groups + 1)].reshape(frames, self.n_groups + 1, 10)
        R = out[:, :self.n_groups, :9].reshape(frames, self.n_groups, 3, 3)
        unfinished = out[:, :self.n_groups, 9] == 0
        if unfinished.any():
            R = R.copy()
            R[unfinished] = closest_rotations(R[unfinished])
        return R[:, self.surface.groups]      # a copy: the next launch writes over the output


def lane_layout(surface: Surface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's chunks of :data:`LANES` groups (kernels/surface.cl): groups sorted by their
    face count, so that a chunk's lanes loop about as long. Returns ``starts`` (C + 1,) int64
    (chunk c's slots ``starts[c]:starts[c + 1]``), ``slots`` (S, 8) int64 (the face of each lane
    per slot; M, the padding face, past a lane's faces) and ``rows`` (C, 8) int64 (each lane's
    group; G for the padding lanes of the last chunk)."""
    G, M = surface.n_groups, len(surface.faces)
    counts = np.diff(surface.group_starts)
    order = np.argsort(counts, kind="stable")
    chunks = -(-G // LANES)
    rows = np.full(chunks * LANES, G, np.int64)
    rows[:G] = order
    lane_counts = np.zeros(chunks * LANES, np.int64)
    lane_counts[:G] = counts[order]
    starts = np.concatenate([[0], np.cumsum(lane_counts.reshape(chunks, LANES).max(axis=1))])
    slots = np.full((int(starts[-1]), LANES), M, np.int64)
    lane = np.repeat(np.arange(G), lane_counts[:G])                 # the lane of each corner, by lane
    j = np.arange(len(lane)) - np.repeat(np.cumsum(lane_counts[:G]) - lane_counts[:G], lane_counts[:G])
    first = np.repeat(surface.group_starts[order], lane_counts[:G])  # each corner's group's first corner
    slots[starts[lane // LANES] + j, lane % LANES] = surface.corner_faces[first + j]
    return starts, slots, rows.reshape(chunks, LANES)
