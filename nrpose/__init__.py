"""nrpose: nearly rigid MLS deformation (Jeong & Kim) and skeletal posing on OpenCL.

Data flow: load (:mod:`nrpose.io`) → bind (:mod:`nrpose.bind`, rest-only work)
→ pose (:mod:`nrpose.pose`, per-frame handle data) → deform (kernel) → write
(:mod:`nrpose.io`). Data types: :mod:`nrpose.model`; conventions:
:mod:`nrpose.model.rotation`.

    from nrpose import Deformer, HandleSet, Pose
    rest = HandleSet.make(segments=[[[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [2, 0, 0]]])
    deformer = Deformer(points, rest, alpha=1.0)          # bind once
    posed = deformer.pose(Pose.make(rest, segments=posed_segments, rotations=rotations))
"""
import importlib

from .errors import DeviceError, FileFormatError, HandleError, InputError, NrposeError

__all__ = ["Deformer", "HandleSet", "Pose", "load_handles", "NrposeError", "InputError",
           "HandleError", "FileFormatError", "DeviceError"]

#: public name -> the module defining it, imported on first use (PEP 562): ``import nrpose``
#: (and so every ``nrpose`` command) then costs only what it uses
LAZY = {"Deformer": ".pose.mls", "load_handles": ".io.poses", "HandleSet": ".model.handles",
        "Pose": ".model.handles"}


def __getattr__(name: str):
    if name not in LAZY:
        raise AttributeError(f"module 'nrpose' has no attribute {name!r}")
    value = getattr(importlib.import_module(LAZY[name], __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(LAZY))
