"""Per-frame posing: characters posed by their skeletons (:mod:`.poser`) and motion
retargeted between rigs (:mod:`.retarget`)."""
