"""``nrpose bake``: many characters × clips × methods in one command, locally or on Ray.

``nrpose bake JOBS.json -o OUTDIR`` (:mod:`.command`) validates the JOBS file
(:mod:`.jobs`), skips finished outputs with ``--resume`` (:mod:`.manifest`),
and runs the rest on a pool of local processes (:mod:`.local`) or as Ray
tasks (:mod:`.ray_runner`). Each job (:mod:`.worker`) runs the pose command's
own functions (:func:`nrpose.cli.pose.pose_input`, :func:`nrpose.cli.common.write_frames`;
for a ``retarget`` job :func:`nrpose.cli.retarget.retarget_clip` first), so its
output is the output of ``nrpose pose`` with the same options. Design: docs/bake.md.
"""
from .command import add_parser, run

__all__ = ["add_parser", "run"]
