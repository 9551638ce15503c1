"""Clip sampling times and the bound on how many frames one call may ask for."""
from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["MAX_FRAMES", "check_frame_count", "sample_times"]

#: the most frames one call samples (an hour at 30 fps is 108,000 frames)
MAX_FRAMES = 1_000_000


def check_frame_count(count: float, what: str) -> None:
    """InputError when ``count`` frames (``what`` asked for them) exceed :data:`MAX_FRAMES`."""
    if count > MAX_FRAMES:
        raise InputError(f"{what} asks for {float(min(count, 1e300)):.3g} frames, more than {MAX_FRAMES:,}; "
                         f"sample fewer (a shorter range, a larger step or a lower frame rate) or pose the "
                         f"clip in parts")


def sample_times(duration: float, fps: float) -> np.ndarray:
    """Times k / fps (seconds, float64) for 0 <= k / fps <= duration (at least the time 0)."""
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")
    count = np.floor(duration * fps + 1e-6) + 1
    check_frame_count(count, f"{duration:g} s at {fps:g} fps")
    return np.minimum(np.arange(int(count)) / fps, duration)
