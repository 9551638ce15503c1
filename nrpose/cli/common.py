"""What several commands share: output checks before any work, frame writing, progress, timing."""
from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import NrposeError
from ..io import load_character
from ..io.files import atomic_path, check_writable, on_commit
from ..io.npz import Streamed, write_npz

__all__ = ["add_budget_options", "check_budget", "output_values", "median_ms", "median", "progress",
           "frames_output_kind", "check_outputs", "write_frames", "device_text", "character_with_weights"]


#: defaults of --max-frames and --max-output-values: a long clip of a large character fits
#: (10,000 frames = 5.5 min at 30 fps; 2e8 numbers = 0.8 GB as float32)
MAX_FRAMES = 10_000
MAX_OUTPUT_VALUES = 200_000_000


def add_budget_options(p) -> None:
    """--max-frames and --max-output-values: the work and output a run may ask for."""
    p.add_argument("--max-frames", type=int, default=MAX_FRAMES,
                   help=f"refuse runs of more frames (default {MAX_FRAMES:,}; each frame is posed, and is "
                        "a file for a directory output)")
    p.add_argument("--max-output-values", type=float, default=MAX_OUTPUT_VALUES,
                   help=f"refuse runs whose output holds more numbers (default {MAX_OUTPUT_VALUES:.0e}: "
                        "frames x vertices x 3, plus frames^2 morph weights in a .glb)")


def output_values(frames: int, vertices: int, kind: str) -> float:
    """The numbers a posed output holds (the estimate --max-output-values bounds): frames x
    vertices x 3, plus frames^2 morph weights in a .glb (``kind``: :func:`frames_output_kind`)."""
    return 3.0 * frames * vertices + (float(frames) ** 2 if kind == "glb" else 0.0)


def check_budget(args, frames: int, values: float, what: str) -> None:
    """NrposeError, before any work, when ``frames`` or the estimated output ``values`` exceed
    the run's --max-frames / --max-output-values (``what`` names the output)."""
    if args.max_frames < 1 or not args.max_output_values >= 1:
        raise NrposeError("--max-frames and --max-output-values must be at least 1")
    if frames > args.max_frames:
        raise NrposeError(f"{what}: {frames:,} frames, more than --max-frames {args.max_frames:,}; sample "
                          f"fewer (lower --fps, a shorter --frames range) or raise --max-frames")
    if values > args.max_output_values:
        raise NrposeError(f"{what}: the output would hold {values:.3g} numbers, more than --max-output-values "
                          f"{args.max_output_values:.3g}; sample fewer frames or raise --max-output-values")


def median_ms(fn, repeat: int) -> tuple[float, object]:
    """Median wall time (ms) of ``repeat`` calls of fn() and the last result."""
    times, result = [], None
    for _ in range(max(repeat, 1)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * median(times), result


def median(values) -> float:
    """The median of a non-empty sequence of numbers (np.median's value), without np.median's
    import of numpy.ma (~10 ms at the end of a run)."""
    s = np.sort(np.asarray(values, dtype=np.float64).reshape(-1))
    return float(0.5 * (s[(len(s) - 1) // 2] + s[len(s) // 2]))


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
    if not out:
        raise NrposeError("-o '': give an output name (OUT.npz, OUT.glb or a directory)")
    suffix = Path(out).suffix.lower()
    if suffix in (".npz", ".glb"):
        return suffix[1:]
    if suffix == "":
        return "dir"
    raise NrposeError(f"{out}: output must end in .npz or .glb, or be a directory")


def check_outputs(out: str | None, suffixes, png: str | None, out_is_dir: bool = False) -> None:
    """Refuse unusable output names before any work (nothing is written on failure): each
    output's directory must exist and take a new file. out_is_dir: OUT is a frame directory."""
    if out is not None:
        if suffixes is not None and Path(out).suffix.lower() not in suffixes:
            raise NrposeError(f"{out}: unknown output extension; use one of {', '.join(suffixes)}")
        check_writable(out, directory_ok=out_is_dir)
        if out_is_dir and os.path.lexists(out) and not Path(out).is_dir():
            raise NrposeError(f"{out}: exists and is not a directory; the frames need a directory (or a new name)")
    if png is not None:
        if Path(png).suffix.lower() != ".png":
            raise NrposeError(f"--png {png}: the preview must end in .png")
        check_writable(png)


def character_with_weights(path: str, skeleton: str | None, weights_file: str | None):
    """The character of ``path`` (a mesh with ``skeleton``: :func:`nrpose.io.load_character`),
    with ``weights_file``, libigl's per-vertex bone weights of a mesh + TGF character (rows =
    vertices, columns = bones in TGF order), as its skin weights when given."""
    character = load_character(path, skeleton)
    if not weights_file:
        return character
    if skeleton is None:
        raise NrposeError("--weights-file gives the weights of a mesh character (a mesh with --skeleton "
                          "SKELETON.tgf); a glTF file carries its own")
    # --weights-file only (a mesh + TGF character): libigl's DMAT reader, the bone weights' module
    from ..bind.bone_weights import with_skin_weights
    from ..io.tgf import read_dmat_weights

    W = read_dmat_weights(weights_file, character.skeleton, sum(len(m.vertices) for m in character.meshes))
    return with_skin_weights(character, W)


def write_frames(out: str, frames, times: np.ndarray, fmt: str, character, source=None, quantize: bool = False,
                 name: str = "baked", backend: str = "opencl"):
    """Posed frames to OUT.npz, OUT.glb or a directory of ``frame_NNNN.<fmt>`` files:
    :class:`nrpose.pose.poser.Frames`, or for OUT.npz and a directory a
    :class:`nrpose.pose.poser.FrameStream`, whose frames are written as they are posed.
    source, quantize, name (the animation's): for OUT.glb, see
    :func:`nrpose.io.gltf_write.write_animated_glb`, whose report is returned (else None);
    backend: "opencl" turns a large bake's normals on the device
    (:func:`nrpose.pose.surface_rotations.surface_rotations_for`)."""
    path = Path(out)
    kind = frames_output_kind(out)
    streamed = hasattr(frames, "batches")
    if kind == "npz":
        positions = (Streamed((frames.count, frames.vertices, 3), np.float32, frames.batches) if streamed
                     else frames.positions)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                write_npz(fh, {"positions": positions, "faces": frames.faces, "times": times,
                               "mesh_names": np.array(frames.mesh_names), "mesh_offsets": frames.mesh_offsets})
    elif kind == "glb":
        if streamed:
            raise NrposeError(f"{out}: a .glb is written from all the frames at once (CharacterPoser.pose)")
        from ..io.gltf_write import write_animated_glb      # pygltflib: imported for .glb outputs only
        from ..pose.surface_rotations import surface_rotations_for
        rotations = surface_rotations_for(frames.positions.shape[1], len(frames.positions), backend)
        return write_animated_glb(path, character, frames.positions, times, frames.mesh_offsets,
                                  source=source, quantize=quantize, animation_name=name, rotations=rotations)
    else:
        from ..io.meshes import write_geometry
        # all frames go to a temporary sibling directory first; only at commit is the
        # directory made, the previous run's frame files removed and the new ones moved in
        tmp = Path(tempfile.mkdtemp(prefix=".nrpose-", dir=path.parent))
        try:
            batches = frames.batches if streamed else [frames.positions]
            f = 0
            for batch in batches:
                for pos in batch:
                    write_geometry(tmp / f"frame_{f:04d}.{fmt}", pos, frames.faces)
                    f += 1
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

        def commit():
            try:
                path.mkdir(parents=True, exist_ok=True)
                for old in path.glob("frame_*"):
                    old.unlink()
                for new in sorted(tmp.iterdir()):
                    new.replace(path / new.name)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
        on_commit(commit, lambda: shutil.rmtree(tmp, ignore_errors=True))


def device_text() -> str:
    """The OpenCL device posing runs on, in one line."""
    from .. import device
    info = device.describe()
    return f"{info['device']} ({info['platform_version']}, {info['compute_units']} compute units)"
