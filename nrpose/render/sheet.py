"""Contact sheets: a PNG grid of the frames of an animation.

``save_contact_sheet(path, positions, faces, times, title)`` draws up to
``max_panels`` frames (evenly spread over the sequence, first and last
included) side by side, each titled with its time, under one camera and one
shared, equal-scale bounding box, so motion between panels is real motion.

Drawing is a small orthographic software renderer in numpy on matplotlib's
Agg backend (no screen, no pyplot state) instead of ``mplot3d``: each frame's
mesh is projected once, faces turned away from the camera are dropped
(closed meshes, either orientation), a mesh whose front faces cover the
panel more than ``MAX_COVER`` times over is refused (:func:`nrpose.render.preview.check_cover`),
and the rest are rasterised with a
per-pixel nearest-face test at twice the panel resolution, Lambert-shaded,
then shown with ``imshow`` (smoothed down: anti-aliased). Cost grows with
pixels, not with triangles drawn through matplotlib: 12 panels of 16k
vertices take about 2 s (plus matplotlib's import on first use). Without
faces the vertices are drawn as dots coloured by height.
Skeleton segments (``handles_per_frame``) are drawn on top.

The camera, light and colours are those of :mod:`nrpose.render.preview` (same
``up``/``elev``/``azim`` meaning, same constants), so the two kinds of
picture look alike. The helpers :func:`view_matrix`, :func:`rasterize`,
:func:`draw_mesh`, :func:`draw_points` and :func:`draw_segments` work on any 2D matplotlib axis
and can be reused by other pictures. The PNG is written through
:func:`nrpose.io.files.atomic_path`.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..checks import real_rows, triangles
from ..errors import InputError
from ..io.files import atomic_path
from .preview import LIGHT, MESH_RGB, UP, check_cover, spread

__all__ = ["save_contact_sheet", "view_matrix", "rasterize", "draw_mesh", "draw_points",
           "draw_segments"]

_SEGMENT_RGB = "#d62728"


def view_matrix(up: str = "y", elev: float = 15.0, azim: float = -60.0) -> np.ndarray:
    """Rotation (3, 3) taking data points (rows: ``X @ M.T``) to (screen x, screen y, depth).

    Same camera as matplotlib's 3D axes in :mod:`nrpose.render.preview`: ``up`` is
    the data axis drawn vertically, ``elev``/``azim`` in degrees; depth grows
    towards the viewer.
    """
    if up not in UP:
        raise InputError(f"up must be 'x', 'y' or 'z', got {up!r}")
    el, az = math.radians(float(elev)), math.radians(float(azim))
    right = [-math.sin(az), math.cos(az), 0.0]
    screen_up = [-math.sin(el) * math.cos(az), -math.sin(el) * math.sin(az), math.cos(el)]
    eye = [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
    return np.array([right, screen_up, eye]) @ UP[up]


def _light(up: str, elev: float, azim: float) -> np.ndarray:
    """Preview's light direction (given in plot coordinates) in screen coordinates."""
    cam = view_matrix(up, elev, azim) @ UP[up].T          # plot -> screen
    light = cam @ LIGHT
    return light / np.linalg.norm(light)


def rasterize(screen: np.ndarray, faces: np.ndarray, light: np.ndarray, bounds, size, *,
              color=MESH_RGB) -> tuple[np.ndarray, int]:
    """Flat-shaded RGBA image (H, W, 4) float of a mesh in screen coordinates, and faces drawn.

    screen: (N, 3) (x, y, depth towards the viewer); faces: (M, 3) int;
    light: unit (3,) direction in screen coordinates; bounds: (x0, x1, y0,
    y1) screen rectangle shown; size: (W, H) pixels. Back faces are culled
    (the outward side is found from the sign of the signed volume); each
    pixel centre shows the nearest front face covering it (depth order of
    face centroids); uncovered pixels are transparent.
    """
    W, H = int(size[0]), int(size[1])
    x0, x1, y0, y1 = (float(b) for b in bounds)
    tri = screen[faces]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    side = 1.0 if np.einsum("ij,ij->", tri[:, 0], nrm) >= 0 else -1.0
    keep = np.flatnonzero(side * nrm[:, 2] > 0)
    tri, nrm = tri[keep], side * nrm[keep]
    order = np.argsort(tri[:, :, 2].mean(axis=1), kind="stable")     # far to near
    tri, nrm = tri[order], nrm[order]
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.divide(nrm, length, out=np.zeros_like(nrm), where=length > 0)
    shade = 0.35 + 0.65 * np.clip(nrm @ light, 0.0, 1.0)
    colors = np.clip(shade[:, None] * np.asarray(color, dtype=np.float64), 0.0, 1.0)
    # pixel coordinates: x right, y down, pixel (i, j) centred at (i + 0.5, j + 0.5)
    px = (tri[:, :, 0] - x0) * (W / max(x1 - x0, 1e-300))
    py = (y1 - tri[:, :, 1]) * (H / max(y1 - y0, 1e-300))
    lo_x = np.clip(np.ceil(px.min(axis=1) - 0.5), 0, W).astype(np.int64)
    hi_x = np.clip(np.floor(px.max(axis=1) - 0.5), -1, W - 1).astype(np.int64)
    lo_y = np.clip(np.ceil(py.min(axis=1) - 0.5), 0, H).astype(np.int64)
    hi_y = np.clip(np.floor(py.max(axis=1) - 0.5), -1, H - 1).astype(np.int64)
    bw, bh = np.maximum(hi_x - lo_x + 1, 0), np.maximum(hi_y - lo_y + 1, 0)
    area = (px[:, 1] - px[:, 0]) * (py[:, 2] - py[:, 0]) - (px[:, 2] - px[:, 0]) * (py[:, 1] - py[:, 0])
    check_cover(0.5 * np.abs(area).sum(), W * H)
    sgn = np.where(area >= 0, 1.0, -1.0)
    top = np.full(W * H, -1, np.int64)                   # nearest face per pixel (rank)
    counts = bw * bh
    starts = np.concatenate([[0], np.cumsum(counts)])
    chunk, first = 4_000_000, 0
    while first < len(tri):                              # bounded memory for huge faces
        last = int(np.searchsorted(starts, starts[first] + chunk, side="right")) - 1
        last = min(max(last, first + 1), len(tri))
        ids = np.arange(first, last)
        c = counts[ids]
        t = np.repeat(ids, c)
        local = np.arange(int(c.sum())) - np.repeat(starts[ids] - starts[first], c)
        i = lo_x[t] + local % bw[t]
        j = lo_y[t] + local // bw[t]
        cx, cy = i + 0.5, j + 0.5
        inside = np.ones(len(t), bool)
        for a, b in ((0, 1), (1, 2), (2, 0)):
            e = (px[t, b] - px[t, a]) * (cy - py[t, a]) - (py[t, b] - py[t, a]) * (cx - px[t, a])
            inside &= sgn[t] * e >= 0
        np.maximum.at(top, (j * W + i)[inside], t[inside])
        first = last
    image = np.zeros((H * W, 4))
    hit = top >= 0
    image[hit, :3] = colors[top[hit]]
    image[hit, 3] = 1.0
    return image.reshape(H, W, 4), len(tri)


def draw_mesh(ax, screen: np.ndarray, faces: np.ndarray, light: np.ndarray, bounds, size, *,
              color=MESH_RGB, zorder: float = 1) -> int:
    """Draw :func:`rasterize`'s image on a 2D axis over ``bounds`` (x0, x1, y0, y1); returns faces drawn.

    ``size`` (W, H) should be about twice the axis' size in pixels: the image
    is smoothed down to it (anti-aliasing).
    """
    image, drawn = rasterize(screen, faces, light, bounds, size, color=color)
    x0, x1, y0, y1 = bounds
    ax.imshow(image, extent=(x0, x1, y0, y1), origin="upper", interpolation="antialiased",
              zorder=zorder, aspect="auto")
    return drawn


def draw_points(ax, screen: np.ndarray, heights: np.ndarray, vmin: float, vmax: float, *,
                max_points: int = 60_000, zorder: float = 1) -> None:
    """Dots (far to near) coloured by ``heights`` (viridis between vmin and vmax)."""
    idx = np.arange(len(screen)) if len(screen) <= max_points else spread(len(screen), max_points)
    idx = idx[np.argsort(screen[idx, 2], kind="stable")]
    size = float(np.clip(1500.0 / len(idx), 0.2, 10.0))
    ax.scatter(screen[idx, 0], screen[idx, 1], s=size, c=heights[idx], cmap="viridis",
               vmin=vmin, vmax=vmax, linewidths=0, zorder=zorder)


def draw_segments(ax, segments: np.ndarray, *, zorder: float = 3) -> None:
    """Segments (S, 2, 3) in screen coordinates as red lines with dark joint dots."""
    from matplotlib.collections import LineCollection

    if len(segments) == 0:
        return
    ax.add_collection(LineCollection(segments[:, :, :2], colors=_SEGMENT_RGB, linewidths=1.8,
                                     zorder=zorder), autolim=False)
    ends = segments.reshape(-1, 2, 3)[:, :, :2].reshape(-1, 2)
    ax.scatter(ends[:, 0], ends[:, 1], s=6, c="#111111", linewidths=0, zorder=zorder + 0.1)


def _check(positions, faces, times, handles_per_frame, max_panels):
    P = np.asarray(positions, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[0] == 0 or P.shape[1] == 0:
        raise InputError(f"positions must have shape (frames, vertices, 3) with at least one "
                         f"frame and vertex, got {np.shape(positions)}")
    if not np.isfinite(P).all():
        f = int(np.flatnonzero(~np.isfinite(P).all(axis=(1, 2)))[0])
        raise InputError(f"positions of frame {f} contain NaN or inf; cannot draw them")
    F = None
    if faces is not None and np.size(faces):
        F = triangles(faces, P.shape[1])
    if times is None:
        T = np.arange(P.shape[0], dtype=np.float64)
    else:
        T = np.asarray(times, dtype=np.float64).reshape(-1)
        if T.shape != (P.shape[0],) or not np.isfinite(T).all():
            raise InputError(f"times must be {P.shape[0]} finite numbers (one per frame), "
                             f"got shape {np.shape(times)}")
    if handles_per_frame is not None and len(handles_per_frame) != P.shape[0]:
        raise InputError(f"handles_per_frame must have one entry per frame ({P.shape[0]}), "
                         f"got {len(handles_per_frame)}")
    if isinstance(max_panels, bool) or not isinstance(max_panels, (int, np.integer)) or max_panels < 1:
        raise InputError(f"max_panels must be a positive integer, got {max_panels!r}")
    return P, F, T


def _segments(h, k: int) -> np.ndarray | None:
    if h is None or np.size(h) == 0:
        return None
    return real_rows(h, f"handles_per_frame[{k}] segments", (2, 3))


def _grid(n: int, panel_aspect: float) -> tuple[int, int]:
    """Columns and rows whose whole picture is closest to a 16:9 landscape."""
    best = None
    for cols in range(1, n + 1):
        rows = math.ceil(n / cols)
        if (cols - 1) * rows >= n:      # an empty column
            continue
        score = abs(math.log(cols * panel_aspect / rows / (16 / 9)))
        if best is None or score < best[0]:
            best = (score, cols, rows)
    return best[1], best[2]


def save_contact_sheet(path, positions, faces=None, times=None, title: str = "",
                       max_panels: int = 12, handles_per_frame: Sequence | None = None, *,
                       up: str = "y", elev: float = 15.0, azim: float = -60.0,
                       panel_inches: float = 3.0, dpi: int = 100) -> list[int]:
    """Write a PNG grid of frames; returns the indices of the frames drawn.

    positions: (F, V, 3) posed vertices per frame; faces: (M, 3) int
    triangles, or None for points; times: (F,) seconds (None: frame
    numbers); title: line over the grid; max_panels: at most this many
    frames, evenly spread (first and last included); handles_per_frame: None
    or one entry per frame, None or segments (S, 2, 3) drawn on top.
    up / elev / azim: camera as in :func:`nrpose.render.preview.save_preview`;
    panel_inches: panel height.
    """
    from matplotlib.figure import Figure

    P, F, T = _check(positions, faces, times, handles_per_frame, max_panels)
    M = view_matrix(up, elev, azim)
    light = _light(up, elev, azim)
    frames = [int(f) for f in (np.arange(len(P)) if len(P) <= max_panels else spread(len(P), max_panels))]
    screens, segs = [], []
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for f in frames:
        S = P[f] @ M.T
        H = _segments(None if handles_per_frame is None else handles_per_frame[f], f)
        H = None if H is None else H @ M.T
        for a in (S, None if H is None else H.reshape(-1, 3)):
            if a is not None:
                lo, hi = np.minimum(lo, a[:, :2].min(axis=0)), np.maximum(hi, a[:, :2].max(axis=0))
        screens.append(S)
        segs.append(H)
    ext = hi - lo
    pad = 0.04 * max(ext.max(), 1e-12)
    lo, hi = lo - pad, hi + pad
    ext = np.maximum(hi - lo, 0.05 * (hi - lo).max())
    centre = 0.5 * (lo + hi)
    lo, hi = centre - ext / 2, centre + ext / 2
    aspect = float(np.clip(ext[0] / ext[1], 0.35, 3.0))

    n = len(frames)
    cols, rows = _grid(n, aspect)
    pw, ph = panel_inches * aspect, panel_inches
    head = 0.45 if title else 0.1
    fig = Figure(figsize=(cols * pw, rows * (ph + 0.25) + head), dpi=dpi)
    fig.subplots_adjust(left=0.005, right=0.995, bottom=0.005, top=1 - head / fig.get_figheight(),
                        wspace=0.02, hspace=0.12)
    if title:
        fig.suptitle(str(title), fontsize=13, y=1 - 0.08 / fig.get_figheight(), va="top")
    up_index = {"x": 0, "y": 1, "z": 2}[up]
    vmin, vmax = float(P[frames][..., up_index].min()), float(P[frames][..., up_index].max())
    raster = (max(int(2 * pw * dpi), 8), max(int(2 * ph * dpi), 8))
    for k, (f, S, H) in enumerate(zip(frames, screens, segs)):
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal", adjustable="box")
        ax.set_axis_off()
        label = f"t = {T[f]:.3g} s" if times is not None else f"frame {f}"
        ax.set_title(label, fontsize=9, pad=2)
        if F is not None:
            draw_mesh(ax, S, F, light, (lo[0], hi[0], lo[1], hi[1]), raster)
        else:
            draw_points(ax, S, P[f][:, up_index], vmin, vmax)
        if H is not None:
            draw_segments(ax, H)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return frames
