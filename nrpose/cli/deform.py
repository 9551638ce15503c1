"""``nrpose deform``: a mesh or point cloud deformed by point and segment handles."""
from __future__ import annotations

import time

import numpy as np

from ..bind.distances import surface_distances
from ..pose.blend import BLENDS, LEVERS
from ..pose.mls import BACKENDS, Deformer, check_segment_count
from ..errors import NrposeError
from ..io.meshes import SUFFIXES, read_geometry, write_geometry
from ..io.poses import load_handles
from ..model.handles import check_alpha
from ..render.preview import save_preview
from .common import check_outputs, median_ms

#: library argument name -> the flag users type
FLAGS = {"alpha": "--alpha", "blend": "--blend", "lever": "--lever", "backend": "--backend"}


def add_parser(sub) -> None:
    p = sub.add_parser("deform", help="deform a mesh or point cloud with point / segment handles")
    p.add_argument("input", help="mesh (OBJ, PLY, OFF, STL) or point cloud (PLY, XYZ)")
    p.add_argument("-H", "--handles", required=True, help="handle file (JSON)")
    p.add_argument("-o", "--output", required=True, help="output mesh or point cloud")
    p.add_argument("--alpha", type=float, help="weight exponent: w = 1/d^(2 alpha) (overrides the file; default 1)")
    p.add_argument("--blend", choices=BLENDS, default=None,
                   help="rotation blend (default: quaternion with segment handles, relative with point "
                        "handles only; both continuous there)")
    p.add_argument("--lever", choices=LEVERS, default="weight", help="segment lever rule (default: weight)")
    p.add_argument("--backend", choices=BACKENDS, default="opencl", help="opencl (default) or numpy reference")
    p.add_argument("--weights", choices=("euclidean", "heat", "exact", "graph", "knn"), default="euclidean",
                   help="distances for the weights: euclidean (default) or over the surface (heat, exact, graph; "
                        "knn for point clouds)")
    p.add_argument("--png", help="write a before/after preview PNG")
    p.set_defaults(func=run, flags=FLAGS)


def run(args) -> None:
    check_outputs(args.output, SUFFIXES, args.png)
    geometry = read_geometry(args.input)
    rest, pose, file_alpha = load_handles(args.handles)
    check_segment_count(rest)          # before weights are computed for every handle
    alpha = check_alpha(args.alpha) if args.alpha is not None else (file_alpha or 1.0)
    t0 = time.perf_counter()
    distances = None
    if args.weights != "euclidean":
        distances = surface_distances(geometry.vertices, geometry.faces if len(geometry.faces) else None,
                                      rest.points, rest.segments, args.weights)
    deformer = Deformer(geometry.vertices, rest, alpha=alpha, blend=args.blend, lever=args.lever,
                        distances=distances, backend=args.backend)
    bind_ms = 1e3 * (time.perf_counter() - t0)
    pose_ms, posed = median_ms(lambda: deformer.pose(pose), 1)
    if not np.isfinite(posed).all():  # never expected: the blend is total; guard the contract
        raise NrposeError("deformation produced non-finite coordinates; please report this input")
    write_geometry(args.output, posed, geometry.faces)
    if args.png:
        save_preview(args.png, [("rest", geometry.vertices, geometry.faces),
                                ("posed", posed, geometry.faces)],
                     handles=[(rest.points, rest.segments), (pose.handles.points, pose.handles.segments)])
    print(f"{args.output}: {len(posed)} points, {rest.count} handles, alpha {alpha:g}, {deformer.blend} blend, "
          f"{args.backend}: bind {bind_ms:.1f} ms, pose {pose_ms:.2f} ms")
