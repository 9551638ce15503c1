"""The seed paper's Figure 3: a box point cloud twisted and bent by line segments.

6,006 points (a solid 11 × 42 × 13 grid, the paper's "Box" row of Table 1)
filling a box 1.0 × 4.1 × 1.2 standing along +y (Y-up), and 4 line-segment
handles chained along its centre line, each 1/4 of the length.
"""
from __future__ import annotations

import numpy as np

from nrpose.model.handles import HandleSet, Pose
from nrpose.model.rotation import Rotation

SHAPE = (11, 42, 13)
SIZE = (1.0, 4.1, 1.2)
HANDLES = 4


def box_points() -> np.ndarray:
    """(6006, 3) float64 grid points (x slowest, z fastest)."""
    axes = [np.linspace(0.0, s, n) for s, n in zip(SIZE, SHAPE)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)


def rest_handles() -> HandleSet:
    """4 chained segments on the centre line (x, z) = (0.5, 0.6), y from 0 to 4.1."""
    y = np.linspace(0.0, SIZE[1], HANDLES + 1)
    joints = np.column_stack([np.full(HANDLES + 1, SIZE[0] / 2), y, np.full(HANDLES + 1, SIZE[2] / 2)])
    return HandleSet.make(segments=np.stack([joints[:-1], joints[1:]], axis=1))


def chain_pose(twist_deg: float = 0.0, bend_deg: float = 0.0) -> Pose:
    """Twist about the box axis (y) and bend about z, spread evenly along the chain.

    Segment k (0 at the base, which stays put) turns by k/(H-1) of the total
    twist about y and k/(H-1) of the total bend about z; the chain stays
    connected: each segment starts where the previous one ends.
    """
    rest = rest_handles()
    frac = np.arange(HANDLES) / (HANDLES - 1)
    rots = (Rotation.from_rotvec(np.outer(frac * np.radians(bend_deg), [0, 0, 1.0]))
            * Rotation.from_rotvec(np.outer(frac * np.radians(twist_deg), [0, 1.0, 0])))
    seg = rest.segments
    starts = [seg[0, 0]]
    for k in range(HANDLES):
        starts.append(starts[-1] + rots[k].apply(seg[k, 1] - seg[k, 0]))
    posed = np.stack([starts[:-1], starts[1:]], axis=1)
    return Pose.make(rest, segments=posed, rotations=rots.as_matrix())


#: the demo's named poses: (twist degrees, bend degrees)
POSES = {"twist": (180.0, 0.0), "bend": (0.0, 90.0), "twist_bend": (120.0, 75.0)}
