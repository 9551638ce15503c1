"""Weight maps as PNG: a mesh coloured by one handle's blend weight.

``save_weight_map(V, F, w, path, title)`` draws two views (front and
oblique) of the mesh with every face coloured by the mean weight of its
vertices (viridis, 0..1). ``save_weight_maps`` stacks several labelled
weight columns (e.g. Euclidean vs heat) as rows. Matplotlib's Agg backend:
no display needed.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from ..checks import real_rows, triangles
from ..errors import InputError

__all__ = ["save_weight_map", "save_weight_maps"]

_VIEWS = (("front", 90.0, -90.0), ("oblique", 28.0, -62.0))


def _check(vertices, faces, w):
    V = real_rows(vertices, "vertices")
    F = triangles(faces, len(V))
    w = np.asarray(w, dtype=np.float64).reshape(-1)
    if len(w) != len(V) or not np.isfinite(w).all():
        raise InputError(f"weights must be {len(V)} finite values, got {w.shape}")
    return V, F, w


def save_weight_maps(vertices, faces, columns: Mapping[str, np.ndarray], path, title: str = "",
                     vmax: float | None = None, gamma: float = 1.0, views=None, up: str = "z",
                     scale_label: str = "weight") -> Path:
    """One row per labelled weight column, one panel per view; returns the path.

    ``gamma`` < 1 stretches the colour scale near 0 (``PowerNorm``) so that
    small leaked weights show. ``views``: ``(name, elevation, azimuth)``
    triples in degrees (default: front and oblique, for a shape lying in the
    xy plane). ``up="y"`` draws Y-up data (glTF) upright: the drawing frame is
    ``(x, -z, y)``, so azimuth -90 at elevation 0 faces a character that looks
    along +z and azimuth 0 shows its left side. ``scale_label`` names the colour bar's quantity."""
    if up not in ("z", "y"):
        raise InputError(f"up must be 'z' or 'y', got {up!r}")
    views = tuple(_VIEWS if views is None else views)
    if not views:
        raise InputError("no views to draw")
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    cols = list(columns.items())
    if not cols:
        raise InputError("no weight columns to draw")
    checked = [(label, *_check(vertices, faces, w)) for label, w in cols]
    if up == "y":
        checked = [(label, V[:, [0, 2, 1]] * [1.0, -1.0, 1.0], F, w) for label, V, F, w in checked]
    V = checked[0][1]
    lo, hi = V.min(axis=0), V.max(axis=0)
    half = (hi - lo).max() / 2
    top = vmax if vmax is not None else max(1e-12, max(float(c[3].max()) for c in checked))
    norm = (matplotlib.colors.Normalize(0.0, top) if gamma == 1.0
            else matplotlib.colors.PowerNorm(gamma, 0.0, top))
    cmap = matplotlib.colormaps["viridis"]

    height = 3.6 * len(cols) + 0.7
    fig = plt.figure(figsize=(4.5 * len(views), height), dpi=110)
    for r, (label, V, F, w) in enumerate(checked):
        fw = w[F].mean(axis=1)
        # a little Lambert shading so the shape reads in the oblique view
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        for c, (vname, elev, azim) in enumerate(views):
            ax = fig.add_subplot(len(cols), len(views), len(views) * r + c + 1, projection="3d")
            e, a = np.radians(elev), np.radians(azim)
            eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            shade = 0.55 + 0.45 * np.abs(n @ eye)
            rgba = cmap(norm(fw))
            rgba[:, :3] *= shade[:, None]
            poly = Poly3DCollection(V[F], facecolors=rgba, edgecolors="none", linewidths=0)
            ax.add_collection3d(poly)
            ext = np.maximum(hi - lo, 1e-3 * half)
            ax.set_xlim(lo[0], lo[0] + ext[0])
            ax.set_ylim(lo[1], lo[1] + ext[1])
            ax.set_zlim(lo[2], lo[2] + ext[2])
            ax.set_box_aspect(tuple(ext), zoom=1.0)
            ax.view_init(elev=elev, azim=azim)
            ax.set_axis_off()
            ax.set_title(f"{label} — {vname}", fontsize=10)
    fig.suptitle(title, fontsize=12)
    sm = matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.subplots_adjust(left=0.0, right=1.0 - 1.26 / (4.5 * len(views)), bottom=0.02, top=1.0 - 0.75 / height, wspace=0.0, hspace=0.08)
    cax = fig.add_axes((1.0 - 1.0 / (4.5 * len(views)), 0.2, 0.18 / (4.5 * len(views)), 0.6))
    fig.colorbar(sm, cax=cax, label=scale_label + (f" (colour scale γ={gamma:g})" if gamma != 1.0 else ""))
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def save_weight_map(vertices, faces, weights_column, path, title: str = "") -> Path:
    """Two views of the mesh coloured by one handle's weights; returns the path."""
    return save_weight_maps(vertices, faces, {"weight": weights_column}, path, title)
