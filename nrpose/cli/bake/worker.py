"""One job, run in a worker process: load (cached), bind (cached), pose, write, publish.

A worker keeps the characters it loaded and the posers it bound (least recently
used dropped first), so jobs that share a character and binding options load
and bind it once per worker. The result of a job is a small record (no arrays):

    {"index", "output", "status": "done" | "failed", "error", "frames", "seconds",
     "load_seconds", "bind_seconds", "worker", "node", "size", "sha256"}
"""
from __future__ import annotations

import os
import shutil
import socket
import time
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ...errors import NrposeError
from ...io import load_character
from ...io.gltf_write import write_glb_with_clip
from ...io.poses import load_map
from ...pose.poser import CharacterPoser
from ...pose.retarget import joint_map, skinned_bounds
from ..common import check_budget, frames_output_kind, output_values, write_frames
from ..pose import pose_input, posed_frames
from ..retarget import retarget_clip
from .jobs import Job
from .manifest import digest, publish, scratch


class _Lru(OrderedDict):
    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def get_or_make(self, key, make):
        """(value, seconds spent making it: 0 when cached)."""
        if key in self:
            self.move_to_end(key)
            return self[key], 0.0
        t0 = time.perf_counter()
        value = make()
        self[key] = value
        while len(self) > self.size:
            self.popitem(last=False)
        return value, time.perf_counter() - t0


class WorkerCache:
    """Loaded characters, retargeted clips and bound posers of one worker process."""

    def __init__(self, characters: int = 4, posers: int = 8):
        self.characters = _Lru(characters)
        self.clips = _Lru(4 * characters)
        self.posers = _Lru(posers)

    def adopt(self, job: Job, character=None, poser=None) -> None:
        """Take the job's character loaded elsewhere, or its poser bound elsewhere (with its character)."""
        if poser is not None:
            character = poser.character
            self.posers.get_or_make(job.bind_key, lambda: poser)
        self.characters.get_or_make(job.load_key, lambda: character)

    def character(self, job: Job):
        return self.characters.get_or_make(job.load_key, lambda: load_character(job.character, job.skeleton))

    def clip(self, job: Job, character, outdir: Path):
        return self.clips.get_or_make(clip_key(job), lambda: retargeted(job, character, outdir))

    def poser(self, job: Job, character):
        return self.posers.get_or_make(job.bind_key, lambda: CharacterPoser(
            character, method=job.method, weights=job.weights, alpha=job.alpha, backend=job.backend,
            blend=job.blend))


def clip_key(job: Job) -> tuple:
    """Jobs with one clip key share one retargeted clip."""
    return job.load_key + (job.retarget, job.fps)


def retargeted(job: Job, character, outdir: Path):
    """The clip ``nrpose retarget SOURCE CHARACTER ... -o OUT.glb`` adds, as ``nrpose pose OUT.glb
    --clip NAME`` reads it back (the .glb holds float32 keys): written to a scratch .glb and read."""
    r = job.retarget
    source = load_character(r.source)
    mapping = joint_map(source.skeleton, character.skeleton, load_map(r.map) if r.map else None)
    local, made = retarget_clip(source, character, mapping, r.source, job.character, r.source_clip, r.root,
                                job.fps, r.force)[2::2]
    tmp = scratch(outdir)
    try:
        name = write_glb_with_clip(job.character, tmp / "retargeted.glb", character, made,
                                   skinned_bounds(character, local))
        return load_character(str(tmp / "retargeted.glb")).clip(name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def worker_name() -> str:
    return f"pid {os.getpid()}"


def node_name() -> str:
    return socket.gethostname()


def failed_record(job: Job, error: str | None, worker: str | None = None, node: str | None = None) -> dict:
    """The record of a job that did not finish (``error``: one line)."""
    return {"index": job.index, "output": job.output, "status": "failed", "error": error, "frames": 0,
            "seconds": 0.0, "load_seconds": 0.0, "bind_seconds": 0.0, "worker": worker, "node": node,
            "size": None, "sha256": None}


def run_job(job: Job, outdir: Path, cache: WorkerCache, node: str | None = None) -> dict:
    """Run one job (module docstring); never raises for a bad job: the record says what failed.
    Warnings raised on the way go into the record's ``warnings`` (messages), not to the worker's
    stderr: the driver reports them as the command's one line of notes."""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("default")
        record = _run_job(job, outdir, cache, node)
    record["warnings"] = list(dict.fromkeys(str(w.message) for w in seen))
    return record


def _run_job(job: Job, outdir: Path, cache: WorkerCache, node: str | None) -> dict:
    t0 = time.perf_counter()
    record = failed_record(job, None, worker_name(), node or node_name())
    tmp_dir = None
    try:
        with np.errstate(all="ignore"):    # as the pose command: its own checks speak for NaN and infinity
            character, record["load_seconds"] = cache.character(job)
            clip = job.clip
            if job.retarget is not None:
                clip, seconds = cache.clip(job, character, outdir)
                record["load_seconds"] += seconds
            kind = frames_output_kind(job.output)
            local, times, name = pose_input(character, clip=clip, motion=job.motion, pose=job.pose,
                                            rest=job.rest, time=list(job.time) if job.time else None,
                                            frames=job.frames, fps=job.fps, kind=kind)
            vertices = sum(len(m.vertices) for m in character.meshes)
            check_budget(job, len(times), output_values(len(times), vertices, kind), job.output)
            poser, record["bind_seconds"] = cache.poser(job, character)
            frames = posed_frames(poser, local, stream=kind != "glb")   # as `nrpose pose`: no whole-clip array
            tmp_dir = scratch(outdir)
            tmp = tmp_dir / Path(job.output).name
            source = job.character if Path(job.character).suffix.lower() in (".glb", ".gltf") else None
            write_frames(str(tmp), frames, times, job.format, character, source, job.quantize, name, job.backend)
            record["size"], record["sha256"] = digest(tmp)
            publish(tmp, outdir / job.output)
        record.update(status="done", frames=int(len(times)))
    except NrposeError as exc:
        record["error"] = str(exc)
    except OSError as exc:
        record["error"] = (f"{exc.filename}: " if exc.filename else "") + str(exc.strerror or exc)
    except Exception as exc:     # a bug must not stop the other jobs; the record names it
        record["error"] = f"internal error ({type(exc).__name__}: {exc}); please report this job"
    finally:
        if tmp_dir is not None:
            shutil.rmtree(tmp_dir, ignore_errors=True)
    record["error"] = record["error"] and record["error"].replace("\r", "\\r").replace("\n", "\\n")
    record["seconds"] = time.perf_counter() - t0
    return record
