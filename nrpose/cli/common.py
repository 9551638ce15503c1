"""What several commands share: output checks before any work, frame writing, progress, timing."""
from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import NrposeError
from ..io.files import atomic_path, check_writable
from ..io.gltf_write import write_animated_glb
from ..io.meshes import write_geometry
from ..io.npz import write_npz

__all__ = ["median_ms", "progress", "frames_output_kind", "check_outputs", "write_frames", "device_text"]


def median_ms(fn, repeat: int) -> tuple[float, object]:
    """Median wall time (ms) of ``repeat`` calls of fn() and the last result."""
    times, result = [], None
    for _ in range(max(repeat, 1)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)), result


def progress(done: int, total: int) -> None:
    """A progress bar on stderr when it is a terminal."""
    if total > 1 and sys.stderr.isatty():
        width = 30
        fill = width * done // total
        print(f"\r[{'#' * fill}{'.' * (width - fill)}] {done}/{total} frames", end="", file=sys.stderr)
        if done == total:
            print(file=sys.stderr)


def frames_output_kind(out: str) -> str:
    """"npz", "glb" or "dir" for ``nrpose pose -o OUT``; NrposeError for other extensions."""
    suffix = Path(out).suffix.lower()
    if suffix in (".npz", ".glb"):
        return suffix[1:]
    if suffix == "":
        return "dir"
    raise NrposeError(f"{out}: output must end in .npz or .glb, or be a directory")


def check_outputs(out: str | None, suffixes, png: str | None) -> None:
    """Refuse unusable output names before any work (nothing is written on failure)."""
    if out is not None:
        if suffixes is not None and Path(out).suffix.lower() not in suffixes:
            raise NrposeError(f"{out}: unknown output extension; use one of {', '.join(suffixes)}")
        check_writable(out)
    if png:
        if Path(png).suffix.lower() != ".png":
            raise NrposeError(f"--png {png}: the preview must end in .png")
        check_writable(png)


def write_frames(out: str, frames, times: np.ndarray, fmt: str, character, source=None, quantize: bool = False,
                 name: str = "baked"):
    """Posed frames (:class:`nrpose.pose.poser.Frames`) to OUT.npz, OUT.glb or a directory of
    ``frame_NNNN.<fmt>`` files. source, quantize, name (the animation's): for OUT.glb, see
    :func:`nrpose.io.gltf_write.write_animated_glb`, whose report is returned (else None)."""
    path = Path(out)
    kind = frames_output_kind(out)
    if kind == "npz":
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                write_npz(fh, {"positions": frames.positions, "faces": frames.faces, "times": times,
                               "mesh_names": np.array(frames.mesh_names), "mesh_offsets": frames.mesh_offsets})
    elif kind == "glb":
        return write_animated_glb(path, character, frames.positions, times, frames.mesh_offsets,
                                  source=source, quantize=quantize, animation_name=name)
    else:
        # all frames go to a temporary sibling directory first; only then are the
        # previous run's frame files removed and the new ones moved in
        path.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".nrpose-", dir=path.parent))
        try:
            for f, pos in enumerate(frames.positions):
                write_geometry(tmp / f"frame_{f:04d}.{fmt}", pos, frames.faces)
            for old in path.glob("frame_*"):
                old.unlink()
            for new in sorted(tmp.iterdir()):
                new.replace(path / new.name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def device_text() -> str:
    """The OpenCL device posing runs on, in one line."""
    from .. import device
    info = device.describe()
    return f"{info['device']} ({info['platform_version']}, {info['compute_units']} compute units)"
