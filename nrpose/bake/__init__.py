"""Batch baking: many characters × clips × methods in one command, locally or on Ray.

``nrpose bake JOBS.json -o OUTDIR`` (:mod:`.command`) validates the JOBS file
(:mod:`.jobs`), skips finished outputs with ``--resume`` (:mod:`.manifest`),
and runs the rest on a pool of local processes (:mod:`.local`) or as Ray
tasks (:mod:`.ray_runner`). Each job (:mod:`.worker`) runs the pose command's
own load, bind, pose and write functions (:mod:`.work`), so its output is the
output of ``nrpose pose`` with the same options.
"""
