"""What benchmarks and tests need to see of a bound deformer: run its last launch again
(on other queues, with or without PoCL's workers, timed, or with a variant of its
kernel), read back what it bound, and how its launches share the work.

For bench/ and tests/, not a stable user API: these functions read the deformers'
internals (:class:`nrpose.device.BoundKernel`), so that nothing else has to, and change
with them. ``deformer``: an OpenCL :class:`nrpose.Deformer` (NR-MLS) or
:class:`nrpose.pose.skinning.Skinner` unless a function says otherwise.
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from . import device
from .errors import DeviceError, InputError
from .pose.mls import Deformer, device_layout, slot_terms


def relaunch(deformer, queues=None, workers: bool | None = None, kernel=None, timed: bool = False) -> list:
    """Run ``deformer``'s last posing's launch again (same inputs, same result) and return
    its events (:func:`nrpose.device.launch_shared`; for the NR-MLS deformer, its pose
    kernel, the prologue included, on each device that ran it). queues: as there, e.g.
    :func:`nrpose.device.profiling_queues`; workers: share the kernel with PoCL's worker
    threads (True), run it on the calling thread alone (False) or let launch_shared decide
    (None); kernel: a :func:`kernel_variant` to run instead of the deformer's own; timed:
    as launch_shared's (:func:`time_launch`). The frames are written into the launch's
    own output (:func:`launch_output`), never into a result handed to a caller."""
    return deformer._relaunch(queues, workers, kernel, timed)


def time_launch(deformer) -> tuple[float | None, bool]:
    """Run the last posing's launch again as a frame loop runs it (a standing worker serves
    it where one stands, :func:`nrpose.device.launch_shared` deciding) and time it:
    ``(seconds, stood)``, seconds from the job's publication to the end of the calling
    thread's kernel, which returns once every block is done
    (:func:`nrpose.device.published_span_s`; None where PoCL's event clock is not the
    host's), and whether a standing worker was there to serve it. Same inputs, same
    result, written into the launch's own output."""
    stood = worker_standing(deformer)
    events = relaunch(deformer, timed=True)
    return device.published_span_s(deformer._jobs, events[-1]), stood


def worker_standing(deformer) -> bool:
    """True while a standing worker of ``deformer``'s kernel polls its mailbox."""
    return deformer._jobs.standing(deformer._kernel)


def alone_s(deformer) -> float:
    """Seconds one frame of ``deformer``'s kernel takes on the calling thread alone, as
    timed at bind (launches of less than :data:`nrpose.device.SHARE_MIN_S` stay there)."""
    return deformer._jobs.alone_s


def launch_output(deformer, frames: int = 1) -> np.ndarray:
    """A copy of the first ``frames`` frames of ``deformer``'s own launch output (where
    :func:`relaunch` writes), float32 (frames, n, 3), read back from the device."""
    out = deformer._out
    out.download()
    npad = deformer._frame_floats // 3
    return out.host[: frames * 3 * npad].reshape(frames, npad, 3)[:, : deformer.n].copy()


def _mls(deformer) -> Deformer:
    if not isinstance(deformer, Deformer) or deformer.backend != "opencl":
        raise InputError("an OpenCL NR-MLS deformer (nrpose.Deformer, backend='opencl') is needed")
    return deformer


def build_options(deformer) -> tuple[str, ...]:
    """The build options of the NR-MLS ``deformer``'s pose kernel (its handle counts and
    variants, kernels/nrmls.cl)."""
    return tuple(_mls(deformer)._options)


def frame_bytes(deformer) -> int:
    """Bytes of per-frame data the NR-MLS ``deformer``'s pose kernel reads and its
    prologue writes for each frame (the frame's pose block and derived block)."""
    d = _mls(deformer)
    return 4 * (d._pose_stride + d._derived_at["stride"])


def kernel_variant(deformer, source: str):
    """``nrmls_pose`` built from ``source`` (the text of a variant of kernels/nrmls.cl, the
    shipped headers pasted) with the NR-MLS ``deformer``'s build options:
    ``relaunch(deformer, kernel=...)`` binds it to the deformer's current arguments and
    runs it in place of the deformer's own. DeviceError, naming the first compiler error,
    if it does not build or does not take nrmls_pose's arguments, or if it does not run
    the job's prologue (``claim_prologue``, kernels/share.h: the launch would wait for it
    for ever)."""
    d = _mls(deformer)
    cl = device.pyopencl()
    if "claim_prologue(" not in source:
        raise DeviceError("the nrmls_pose variant does not run its job's prologue (claim_prologue, "
                          "kernels/share.h): its launches would wait for it for ever")
    try:
        kernel = cl.Kernel(device.build_source(source, d._options), "nrmls_pose")
        args = d._pose_args()
        # typed scalars: relaunch rebinds the variant after the arguments change, and
        # pyopencl's untyped set_arg of an int is slow
        kernel.set_scalar_arg_dtypes([type(a) if isinstance(a, np.generic) else None for a in args])
        kernel.set_args(*args)
    except (cl.RuntimeError, cl.LogicError, TypeError) as exc:
        errors = [line.strip() for line in str(exc).splitlines() if "error:" in line]
        raise DeviceError("the nrmls_pose variant does not build or take nrmls_pose's arguments: "
                          + (errors[0] if errors else str(exc).splitlines()[0])) from None
    return kernel


def bound_array(deformer, name: str, dtype) -> np.ndarray:
    """Array ``name`` of :data:`nrpose.pose.mls.BOUND_ARRAYS` read back from the NR-MLS
    ``deformer``'s bound block on the device, as a flat array of ``dtype``."""
    d = _mls(deformer)
    cl = device.pyopencl()
    offset, nbytes = d._bound_at[name]
    out = np.empty(nbytes // np.dtype(dtype).itemsize, dtype)
    if out.size:
        cl.enqueue_copy(d._queue, out, d._bound, src_offset=offset)
    return out


def bound_indices(deformer) -> tuple[np.ndarray, np.ndarray | None]:
    """The NR-MLS ``deformer``'s per-point indices in stored order (points sorted by
    reference, padded to a multiple of its lanes): ref (Npad,) int32, each point's
    reference rotation (segment s, or S for the global one), and slots (K, Npad) int32,
    its segment slots (None when dense). On OpenCL they are read back from the bound
    device buffer; a numpy-backend deformer lays them out as the OpenCL one would."""
    if isinstance(deformer, Deformer) and deformer.backend == "numpy":
        kept = slot_terms(deformer._terms, deformer.k, deformer.lever)
        arrays, K = device_layout(kept, deformer.rest, deformer.lever, deformer.lanes)
        return arrays["ref"], (arrays["slot"] if K < len(deformer.rest.segments) else None)
    d = _mls(deformer)
    rec = bound_array(d, "irec", np.int32).reshape(d._npad // d.lanes, -1, d.lanes)   # ref, row, then slots
    slots = rec[:, 2:].transpose(1, 0, 2).reshape(rec.shape[1] - 2, d._npad) if rec.shape[1] > 2 else None
    return rec[:, 0].ravel(), slots


def pypi_pocl_icd() -> Path | None:
    """The ICD file of PyPI's PoCL (``pocl-binary-distribution``, registered in the pyopencl
    wheel's driver folder), or None where there is none."""
    spec = importlib.util.find_spec("pyopencl")
    icd = Path(spec.submodule_search_locations[0]) / ".libs" / "pocl.icd" if spec else None
    return icd if icd is not None and icd.is_file() else None


def pypi_pocl_refusal() -> str | None:
    """Why PyPI's PoCL cannot build a one-line kernel on this CPU (nrpose's message, from a
    child process that sees that PoCL alone: ``OCL_ICD_VENDORS`` names its ICD file), or
    None where it can or is not installed (e.g. its LLVM 14 does not know AMD Zen 5)."""
    icd = pypi_pocl_icd()
    if icd is None:
        return None
    code = ("import pyopencl as cl; from nrpose.device.env import compiler_refusal; "
            "print(compiler_refusal(cl.Context(cl.get_platforms()[0].get_devices())) or '')")
    env = {**os.environ, "OCL_ICD_VENDORS": str(icd)}
    env.pop("PYOPENCL_CTX", None)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    if proc.returncode != 0:
        last = proc.stderr.strip().splitlines()[-1:]
        return f"PyPI's PoCL does not start: {last[0] if last else f'exit status {proc.returncode}'}"
    return proc.stdout.strip() or None
