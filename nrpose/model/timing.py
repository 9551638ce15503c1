"""Clip sampling times and the bound on how many frames one call may ask for.

Clip times are compared to within one float32 step, the precision glTF stores key
times in (:func:`same_time`): a time that close to the clip's duration *is* the last key (a clip
of 248 frames at 30 fps read from glTF lasts 8.26666641 s, below 248 / 30 in
float64, and its last key must not be lost to that rounding).
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["MAX_FRAMES", "check_frame_count", "sample_times", "clip_times", "same_time"]

#: the most frames one call samples (an hour at 30 fps is 108,000 frames)
MAX_FRAMES = 1_000_000


def check_frame_count(count: float, what: str) -> None:
    """InputError when ``count`` frames (``what`` asked for them) exceed :data:`MAX_FRAMES`."""
    if count > MAX_FRAMES:
        raise InputError(f"{what} asks for {float(min(count, 1e300)):.3g} frames, more than {MAX_FRAMES:,}; "
                         f"sample fewer (a shorter range, a larger step or a lower frame rate) or pose the "
                         f"clip in parts")


def same_time(a, b) -> np.ndarray:
    """Whether times a and b (seconds, broadcast) agree to within one float32 step (of the larger
    of them, at least of 1 s): equal in the precision clips store key times in."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    return np.abs(a - b) <= np.spacing(scale.astype(np.float32)).astype(np.float64)


def clip_times(times, duration: float) -> np.ndarray:
    """Times (float64) inside [0, duration] within the clip's float32 precision, clamped to it.

    Raises InputError for a time that is not finite or lies outside the clip.
    """
    t = np.asarray(times, dtype=np.float64)
    inside = np.isfinite(t) & ((t >= 0) | same_time(t, 0.0)) & ((t <= duration) | same_time(t, duration))
    if not inside.all():
        bad = t[~inside].reshape(-1)[0]
        raise InputError(f"time {bad} is outside [0, {duration:g}] seconds")
    return np.clip(t, 0.0, duration)


def sample_times(duration: float, fps: float, close: bool = True) -> np.ndarray:
    """Times (F,) float64 seconds sampling a whole clip at ``fps``.

    The frames ``k / fps`` before the end of the clip (compared to within a float32
    step, :func:`same_time`), then, with ``close``, the last key itself (``duration``),
    so a clip keeps its last key and a loop closes without a seam; when the end
    lies on the grid it is that grid frame. Without ``close`` only grid frames
    (for formats with a fixed frame time such as BVH): the end is included when
    it lies on the grid. At least the time 0.
    """
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")
    if not (np.isfinite(duration) and duration >= 0):
        raise InputError(f"clip duration must be a non-negative number of seconds, got {duration}")
    count = np.floor(duration * fps) + 2          # grid frames up to just past the end
    check_frame_count(count, f"{duration:g} s at {fps:g} fps")
    grid = np.arange(int(count)) / fps
    on_grid = same_time(grid, duration)
    before = grid[(grid < duration) & ~on_grid]
    if close or on_grid.any():
        return np.append(before, duration)
    return before if len(before) else np.zeros(1)
