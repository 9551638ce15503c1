"""Posing: the near-rigid MLS blend (reference and rest terms, :mod:`.blend`) and its
deformer (:mod:`.mls`), linear and dual-quaternion skinning (:mod:`.skinning`)."""
