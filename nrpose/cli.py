"""Command line: ``nrpose deform`` and ``nrpose demo``.

Every user mistake (bad file, bad option, no OpenCL platform) ends with one
line on stderr and exit status 2; outputs are written to a temporary name
and renamed, so a failed run leaves no output behind.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from .blend import BLENDS, LEVERS
from .engine import BACKENDS, Deformer
from .errors import NrposeError


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, status 2 (argparse's default prints usage too)
        raise _UsageError(f"{self.prog}: {message}")


class _UsageError(Exception):
    pass


def _median_ms(fn, repeat: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(max(repeat, 1)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)), result


def cmd_deform(args) -> None:
    from .handles import check_alpha, load_handles
    from .meshio import read_geometry, write_geometry

    geometry = read_geometry(args.input)
    rest, pose, file_alpha = load_handles(args.handles)
    alpha = check_alpha(args.alpha) if args.alpha is not None else (file_alpha or 1.0)
    t0 = time.perf_counter()
    deformer = Deformer(geometry.vertices, rest, alpha=alpha, blend=args.blend, lever=args.lever,
                        backend=args.backend)
    bind_ms = 1e3 * (time.perf_counter() - t0)
    pose_ms, posed = _median_ms(lambda: deformer.pose(pose), 1)
    if not np.isfinite(posed).all():  # never expected: the blend is total; guard the contract
        raise NrposeError("deformation produced non-finite coordinates; please report this input")
    write_geometry(args.output, posed, geometry.faces)
    if args.png:
        from .preview import save_preview
        save_preview(args.png, [("rest", geometry.vertices, geometry.faces),
                                ("posed", posed, geometry.faces)],
                     handles=[(rest.points, rest.segments), (pose.handles.points, pose.handles.segments)])
    print(f"{args.output}: {len(posed)} points, {rest.count} handles, alpha {alpha:g}, {args.blend} blend, "
          f"{args.backend}: bind {bind_ms:.1f} ms, pose {pose_ms:.2f} ms")


def cmd_demo(args) -> None:
    """The paper's Figure 3: a 6,006-point box twisted and bent by 4 segments, on PoCL."""
    from .meshio import write_geometry
    from .preview import save_preview
    from .rigs import box

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    points, rest = box.box_points(), box.rest_handles()
    bind_ms, deformer = _median_ms(lambda: Deformer(points, rest, backend="opencl"), 1)
    reference = Deformer(points, rest, backend="numpy")
    print(f"Figure 3 box: {len(points)} points, {rest.count} segment handles; bind {bind_ms:.1f} ms on "
          f"{deformer_device()}")
    panels, handles = [("rest", points, None)], [(rest.points, rest.segments)]
    for name, (twist, bend) in box.POSES.items():
        pose = box.chain_pose(twist, bend)
        pose_ms, posed = _median_ms(lambda: deformer.pose(pose), args.repeat)
        ref_ms, ref = _median_ms(lambda: reference.pose(pose), 3)
        err = float(np.abs(posed - ref).max())
        write_geometry(out / f"box_{name}.ply", posed)
        panels.append((f"{name} (twist {twist:g}°, bend {bend:g}°)", posed, None))
        handles.append((pose.handles.points, pose.handles.segments))
        print(f"  {name:<10} pose {pose_ms:7.3f} ms (median of {args.repeat}) | numpy reference "
              f"{ref_ms:7.2f} ms ({ref_ms / pose_ms:5.0f}x) | max |PoCL - reference| {err:.1e}")
    save_preview(out / "box_before.png", panels[:1], handles=handles[:1])
    save_preview(out / "box_after.png", panels, handles=handles)
    print(f"wrote {out / 'box_before.png'}, {out / 'box_after.png'} and box_*.ply in {out}")


def deformer_device() -> str:
    from . import device
    info = device.describe()
    return f"{info['device']} ({info['platform_version']}, {info['compute_units']} compute units)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="nrpose", description="Nearly rigid MLS deformation and skeletal posing on OpenCL.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("deform", help="deform a mesh or point cloud with point / segment handles")
    p.add_argument("input", help="mesh (OBJ, PLY, OFF, STL) or point cloud (PLY, XYZ)")
    p.add_argument("-H", "--handles", required=True, help="handle file (JSON)")
    p.add_argument("-o", "--output", required=True, help="output mesh or point cloud")
    p.add_argument("--alpha", type=float, help="weight exponent: w = 1/d^(2 alpha) (overrides the file; default 1)")
    p.add_argument("--blend", choices=BLENDS, default="relative", help="rotation blend (default: relative)")
    p.add_argument("--lever", choices=LEVERS, default="length", help="segment lever rule (default: length)")
    p.add_argument("--backend", choices=BACKENDS, default="opencl", help="opencl (default) or numpy reference")
    p.add_argument("--png", help="write a before/after preview PNG")
    p.set_defaults(func=cmd_deform)

    p = sub.add_parser("demo", help="the paper's Figure 3 box on PoCL, with PNGs and timings")
    p.add_argument("--out", default="out", help="output directory (default: out)")
    p.add_argument("--repeat", type=int, default=50, help="poses timed per configuration (default 50)")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
        args.func(args)
    except _UsageError as exc:
        print(exc, file=sys.stderr)
        return 2
    except NrposeError as exc:
        print(f"nrpose: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"nrpose: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
