"""Per-column bounds of point and attribute arrays."""
from __future__ import annotations

import numpy as np


def column_bounds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)``, each (C,) of ``values``' dtype: the minimum and maximum of ``values``
    (..., C), not empty, over every axis but the last. One strided reduction per column:
    numpy's reduction over the leading axes of an array with a short last axis is ~20x slower
    (16 Mannequin frames (16, 15882, 3) float32: 6.6 ms against 0.3 ms)."""
    columns = range(values.shape[-1])
    return (np.array([values[..., c].min() for c in columns], values.dtype),
            np.array([values[..., c].max() for c in columns], values.dtype))
