"""The choices of nrpose's options, as plain tuples: command lines and job files offer and
check them without importing the modules that implement them (and their numpy, device and
binding code). Those modules take them from here."""
from __future__ import annotations

__all__ = ["METHODS", "WEIGHTS", "BLENDS", "DEFAULT_BLEND", "BACKENDS"]

#: posing methods of :class:`nrpose.pose.poser.CharacterPoser`
METHODS = ("nrmls", "lbs", "dqs", "cor")
#: weights of a character (:func:`nrpose.bind.bone_weights.bone_weights`)
WEIGHTS = ("authored", "euclidean", "heat", "exact", "graph")
#: rotation blends of the near-rigid MLS (:mod:`nrpose.pose.blend`)
BLENDS = ("quaternion", "relative", "paper")
#: the default blend of rigs with segments (skeletons): continuous at any spread, equivariant
DEFAULT_BLEND = "quaternion"
#: where a deformer runs (:class:`nrpose.pose.mls.Deformer`)
BACKENDS = ("opencl", "numpy")
