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
from .pose.mls import Deformer
from .errors import DeviceError, FileFormatError, HandleError, InputError, NrposeError
from .io.poses import load_handles
from .model.handles import HandleSet, Pose

__all__ = ["Deformer", "HandleSet", "Pose", "load_handles", "NrposeError", "InputError",
           "HandleError", "FileFormatError", "DeviceError"]
