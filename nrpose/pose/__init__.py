"""Posing: the near-rigid MLS blend (float64 reference and rest terms, :mod:`.blend`) and its
deformer on the device (:mod:`.mls`), linear and dual-quaternion skinning (:mod:`.skinning`),
characters posed by their skeletons (:mod:`.poser`) and motion retargeted between rigs
(:mod:`.retarget`)."""
