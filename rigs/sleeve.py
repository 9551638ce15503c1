"""The two-bone cylinder (rigs/cylinder.py) with a rigid joint cap: a separate closed sleeve
around the joint whose vertices all carry one weight set split between the two bones, as the
joint caps of a robot character. Bone weights: the tube's Euclidean ``1/d²`` (α = 1), the
sleeve's ``split``.
"""
from __future__ import annotations

import numpy as np

from nrpose.bind.distances import point_segment_distances
from nrpose.rigs import cylinder
from nrpose.bind.weights import dense_weights


def sleeve_rig(split=(0.4, 0.6), rings: int = 41, sectors: int = 24):
    """(vertices (N, 3), faces (M, 3) int64, bone weights (N, 2), index of the first sleeve vertex)."""
    V, F = cylinder.cylinder_mesh(rings=rings, sectors=sectors)
    C, CF = cylinder.cylinder_mesh(radius=0.3, length=0.4, rings=9, sectors=sectors)
    W = dense_weights(point_segment_distances(V, cylinder.BONES)[0], 1.0)
    return (np.concatenate([V, C + [0.8, 0, 0]]), np.concatenate([F, CF + len(V)]),
            np.concatenate([W, np.tile(np.asarray(split, float), (len(C), 1))]), len(V))
