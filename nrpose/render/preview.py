"""PNG previews: side-by-side 3D views of meshes and point clouds, with handles.

``save_preview(path, panels, handles)`` draws one 3D view per panel with
matplotlib's Agg renderer (no screen, no pyplot state: safe in scripts and
threads) and writes the PNG through :func:`nrpose.io.files.atomic_path`.

* All panels share one bounding box and camera, with equal scale on the
  three axes, so "before" and "after" line up.
* Meshes are flat-shaded triangles (Lambert, one light over the camera's
  shoulder). Above ``MAX_FACES`` triangles the faces turned away from the
  camera are dropped first (hidden on a closed mesh), then, if still too
  many, an evenly spread subset is drawn (small holes may show).
* Point clouds are small dots coloured by height (the ``up`` axis), above
  ``MAX_POINTS`` an evenly spread subset.
* Handles are drawn on top: segments as thick lines, points as dots.
* A mesh whose triangles, projected, cover the view more than ``MAX_COVER``
  times over (spikes across the whole mesh: drawing time grows with it) is
  refused with InputError (:func:`check_cover`, also used by the contact sheets).
* ``up`` names the data axis drawn vertically: ``"y"`` (default, glTF, BVH
  and most OBJ) or ``"z"`` (or ``"x"``). The data are only relabelled
  (a proper rotation), never rescaled.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..checks import real_rows, triangles
from ..errors import InputError
from ..io.files import atomic_path

__all__ = ["save_preview", "render_figure", "spread", "check_cover", "MAX_FACES", "MAX_POINTS", "MAX_COVER", "LIGHT",
           "MESH_RGB", "UP"]

MAX_FACES = 60_000
MAX_POINTS = 60_000
#: projected triangle area a picture may draw, in views (the shared meshes and characters: 0.2-0.9)
MAX_COVER = 8
LIGHT = np.array([-0.4, -0.6, 0.7])       # in plot coordinates (x right, y depth, z up)
MESH_RGB = np.array([0.62, 0.70, 0.86])
# data axis -> plot axes (right-handed relabelling, the up axis becomes plot z)
UP = {"y": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
      "z": np.eye(3),
      "x": np.array([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])}


def spread(n: int, keep: int) -> np.ndarray:
    """Indices of an evenly spread subset of ``keep`` out of ``n``."""
    return np.unique(np.linspace(0, n - 1, keep).round().astype(np.int64))


def check_cover(projected_area: float, view_area: float) -> None:
    """Refuse (InputError) to draw triangles whose projected areas sum to more than
    ``MAX_COVER`` times the view's area (both in the same units): drawing time grows with it."""
    cover = float(projected_area) / max(float(view_area), 1e-300)
    if not cover <= MAX_COVER:
        raise InputError(f"cannot draw the picture: the mesh's triangles cover the view {cover:,.0f} times over (at "
                         f"most {MAX_COVER}; a surface seen whole covers it about once): are there spikes across the "
                         "mesh? check its coordinates, or leave the picture out")


def _eye(elev: float, azim: float) -> np.ndarray:
    """Unit direction (3,) towards the camera in plot coordinates."""
    el, az = np.radians(elev), np.radians(azim)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _front_faces(tri: np.ndarray, nrm: np.ndarray, elev: float, azim: float) -> np.ndarray:
    """Indices of the faces turned towards the camera (back faces of a closed mesh are hidden).

    The outward side is taken from the sign of the mesh's signed volume, so
    inward-oriented meshes are culled correctly too.
    """
    eye = _eye(elev, azim)
    volume = np.einsum("ij,ij->", tri[:, 0], nrm)         # 6 x signed volume (sum v0 . n)
    side = 1.0 if volume >= 0 else -1.0
    return np.flatnonzero(side * (nrm @ eye) >= 0)


def save_preview(path, panels: Sequence[tuple], handles: Sequence | None = None, *,
                 up: str = "y", elev: float = 15.0, azim: float = -60.0,
                 panel_inches: float = 4.0, dpi: int = 100) -> None:
    """Write a PNG with one 3D view per panel (atomically, see :func:`atomic_path`).

    panels: ``[(title, vertices (N, 3), faces (F, 3) or None), ...]``; faces
    ``None`` or empty draws a point cloud.
    handles: ``None`` or one entry per panel, each ``None`` or
    ``(points (P, 3) or None, segments (S, 2, 3) or None)``.
    up: data axis drawn vertically; elev, azim: camera angles in degrees
    (matplotlib's); the image is ``panel_inches * dpi`` pixels per panel.
    Raises InputError on malformed panels or handles (nothing is written).
    """
    fig = render_figure(panels, handles, up=up, elev=elev, azim=azim,
                        panel_inches=panel_inches, dpi=dpi)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)


def render_figure(panels: Sequence[tuple], handles: Sequence | None = None, *,
                  up: str = "y", elev: float = 15.0, azim: float = -60.0,
                  panel_inches: float = 4.0, dpi: int = 100):
    """The :class:`matplotlib.figure.Figure` that :func:`save_preview` saves."""
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    if up not in UP:
        raise InputError(f"up must be 'x', 'y' or 'z', got {up!r}")
    panels = list(panels)
    if not panels:
        raise InputError("save_preview needs at least one panel")
    if handles is not None and len(handles) != len(panels):
        raise InputError(f"handles must have one entry per panel ({len(panels)}), "
                         f"got {len(handles)}")
    to_plot = UP[up].T                      # rows: X_plot = X_data @ M.T

    prepared = []
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for k, panel in enumerate(panels):
        if len(panel) != 3:
            raise InputError(f"panel {k} must be (title, vertices, faces or None)")
        title, V, F = panel
        V = real_rows(V, f"panel {k} vertices") @ to_plot
        F = triangles(F, len(V), f"panel {k} faces") if F is not None and np.size(F) else None
        pts = segs = None
        if handles is not None and handles[k] is not None:
            if len(handles[k]) != 2:
                raise InputError(f"handles[{k}] must be (points, segments)")
            hp, hs = handles[k]
            if hp is not None and np.size(hp):
                pts = real_rows(hp, f"handles[{k}] points") @ to_plot
            if hs is not None and np.size(hs):
                segs = real_rows(hs, f"handles[{k}] segments", (2, 3)) @ to_plot
        for a in (V, pts, None if segs is None else segs.reshape(-1, 3)):
            if a is not None:
                lo, hi = np.minimum(lo, a.min(axis=0)), np.maximum(hi, a.max(axis=0))
        prepared.append((str(title), V, F, pts, segs))

    ext = hi - lo
    pad = 0.04 * max(ext.max(), 1e-12)
    lo, hi = lo - pad, hi + pad
    ext = np.maximum(hi - lo, 1e-3 * (hi - lo).max())
    hi = lo + ext
    up_lo, up_hi = lo[2], hi[2]

    eye = _eye(elev, azim)
    for _, V, F, _, _ in prepared:
        if F is not None:
            tri = V[F]
            check_cover(0.5 * np.abs(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) @ eye).sum(),
                        np.abs(eye) @ [ext[1] * ext[2], ext[0] * ext[2], ext[0] * ext[1]])

    n = len(prepared)
    fig = Figure(figsize=(panel_inches * n, panel_inches), dpi=dpi)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0.02)
    light = LIGHT / np.linalg.norm(LIGHT)
    for k, (title, V, F, pts, segs) in enumerate(prepared):
        ax = fig.add_subplot(1, n, k + 1, projection="3d", computed_zorder=False)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(ext), zoom=1.15)
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(title, fontsize=11)
        if F is not None:
            tri = V[F]
            nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            if len(F) > MAX_FACES:
                keep = _front_faces(tri, nrm, elev, azim)
                if len(keep) > MAX_FACES:
                    keep = keep[spread(len(keep), MAX_FACES)]
                tri, nrm = tri[keep], nrm[keep]
            length = np.linalg.norm(nrm, axis=1, keepdims=True)
            nrm = np.divide(nrm, length, out=np.zeros_like(nrm), where=length > 0)
            shade = 0.35 + 0.65 * np.abs(nrm @ light)       # two-sided Lambert
            colors = np.clip(shade[:, None] * MESH_RGB, 0, 1)
            coll = Poly3DCollection(tri, facecolors=colors, edgecolors="none",
                                    linewidths=0, antialiaseds=False, zorder=1)
            ax.add_collection3d(coll)
        else:
            P = V if len(V) <= MAX_POINTS else V[spread(len(V), MAX_POINTS)]
            size = float(np.clip(3000.0 / len(P), 0.3, 12.0))
            ax.scatter(P[:, 0], P[:, 1], P[:, 2], s=size, c=P[:, 2], cmap="viridis",
                       vmin=up_lo, vmax=up_hi, depthshade=False, linewidths=0, zorder=1)
        if segs is not None:
            ax.add_collection3d(Line3DCollection(segs, colors="#d62728", linewidths=3.0,
                                                 zorder=3))
        if pts is not None:
            ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=28, c="#111111",
                       edgecolors="white", linewidths=0.6, depthshade=False, zorder=4)
    return fig
