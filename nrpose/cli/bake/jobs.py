"""JOBS.json: the schema, the defaults merge, path resolution and whole-file validation.

A JOBS file is ``{"defaults": {...}, "jobs": [{...}, ...]}`` ("defaults" optional).
A job has the options of ``nrpose pose`` as keys (the table: docs/bake.md):
``character``, ``skeleton``; exactly one of ``clip``, ``motion``, ``pose``, ``rest``,
``retarget`` (``{"source", "map", "source_clip", "root", "in_place", "force"}``); at most one of
``time``, ``frames``; ``fps``, ``method``, ``weights``, ``alpha``, ``blend``,
``backend``, ``format``, ``quantize``; ``output`` (a relative name under OUTDIR).

``defaults`` takes every key but ``output``; a job's keys override them, and
the motion keys (clip, motion, pose, rest, retarget) and the sampling keys
(time, frames) are replaced as a group: a job with ``"rest": true`` drops a
default ``clip``. Relative paths resolve against the JOBS file's folder.

:func:`load_jobs` validates the whole file before any work and raises
:class:`~nrpose.errors.InputError` with one line naming the job (``jobs[3]
(walk.npz): ...``) for: unknown keys, wrong types or values, a missing motion
key or two of them, two jobs writing one output (or one inside another's
directory), an output outside OUTDIR, missing input files. Errors only a run
can find (a clip name the character lacks, a truncated file) fail that job alone.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path, PurePosixPath

from ...errors import InputError, NrposeError
from ...io.jsonfile import check_json_size, parse_json
from ...options import BACKENDS, BLENDS, DEFAULT_BLEND, METHODS, WEIGHTS
from ...pose.retarget import ROOT_MODES
from ..common import MAX_FRAMES, MAX_OUTPUT_VALUES, frames_output_kind
from ..pose import parse_frames
from ..retarget import SOURCE_SUFFIXES, TARGET_SUFFIXES

MOTION_KEYS = ("clip", "motion", "pose", "rest", "retarget")
SAMPLING_KEYS = ("time", "frames")
OPTION_KEYS = ("character", "skeleton") + MOTION_KEYS + SAMPLING_KEYS + (
    "fps", "method", "weights", "alpha", "blend", "backend", "format", "quantize")
JOB_KEYS = OPTION_KEYS + ("output",)
RETARGET_KEYS = ("source", "map", "source_clip", "root", "in_place", "force")
FORMATS = ("ply", "obj")
#: names in OUTDIR that belong to the bake itself
RESERVED = ("manifest.json", ".bake-tmp")


@dataclass(frozen=True)
class Retarget:
    """A ``retarget`` motion: absolute paths; ``root`` and ``force`` as ``nrpose retarget --root --force``."""

    source: str
    map: str | None = None
    source_clip: str | None = None
    root: str = "origin"
    force: bool = False


@dataclass(frozen=True)
class Job:
    """One validated job: absolute input paths, ``output`` relative to OUTDIR (POSIX form)."""

    index: int
    output: str
    character: str
    skeleton: str | None = None
    clip: str | None = None
    motion: str | None = None
    pose: str | None = None
    rest: bool = False
    retarget: Retarget | None = None
    time: tuple[float, ...] | None = None
    frames: str | None = None
    fps: float = 30.0
    method: str = "nrmls"
    weights: str = "authored"
    alpha: float = 1.0
    blend: str = DEFAULT_BLEND
    backend: str = "opencl"
    format: str = "ply"
    quantize: bool = False
    #: the bake's --max-frames / --max-output-values (checked per job before posing; not in ``spec``)
    max_frames: int = MAX_FRAMES
    max_output_values: float = MAX_OUTPUT_VALUES

    @property
    def inputs(self) -> list[str]:
        """The files the job reads."""
        files = [self.character, self.skeleton, self.motion, self.pose]
        if self.retarget is not None:
            files += [self.retarget.source, self.retarget.map]
        return [f for f in files if isinstance(f, str)]

    @property
    def label(self) -> str:
        return f"jobs[{self.index}] ({self.output})"

    @property
    def load_key(self) -> tuple:
        """Jobs with one load key share one loaded character."""
        return (self.character, self.skeleton)

    @property
    def bind_key(self) -> tuple:
        """Jobs with one bind key share one bound poser."""
        return self.load_key + (self.method, self.weights, self.alpha, self.blend, self.backend)

    @property
    def spec(self) -> str:
        """sha256 of the job's options (not its index): the manifest's record of what made an output."""
        options = {k: v for k, v in asdict(self).items() if k not in ("index", "max_frames", "max_output_values")}
        return hashlib.sha256(json.dumps(options, sort_keys=True).encode()).hexdigest()


def load_jobs(path: str | Path) -> list[Job]:
    """The validated jobs of a JOBS file (module docstring); InputError naming the job otherwise."""
    path = Path(path)
    if path.exists() and not path.is_file():     # a FIFO would block the read
        raise InputError(f"{path}: not a regular file; give the JOBS.json file")
    check_json_size(path, "the jobs file", InputError)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"{path}: cannot read the jobs file ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: the jobs file is not UTF-8 text") from None
    doc = parse_json(text, str(path), "the jobs file", InputError)
    if not isinstance(doc, dict) or set(doc) - {"defaults", "jobs"}:
        extra = sorted(set(doc) - {"defaults", "jobs"}) if isinstance(doc, dict) else []
        raise InputError(f"{path}: expected {{\"defaults\": {{...}}, \"jobs\": [...]}}"
                         + (f"; unknown key {extra[0]!r}" if extra else ""))
    defaults, entries = doc.get("defaults", {}), doc.get("jobs")
    if not isinstance(defaults, dict):
        raise InputError(f"{path}: \"defaults\" must be an object")
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{path}: \"jobs\" must be a non-empty list of job objects")
    _check_keys(path, "defaults", defaults, OPTION_KEYS)
    base = path.parent
    jobs = []
    for i, entry in enumerate(entries):
        label = f"jobs[{i}]" + (f" ({entry['output']})" if isinstance(entry, dict)
                                and isinstance(entry.get("output"), str) else "")
        if not isinstance(entry, dict):
            raise InputError(f"{path}: {label}: a job must be an object")
        _check_keys(path, label, entry, JOB_KEYS)
        try:
            jobs.append(_job(i, _merge(defaults, entry), base))
        except NrposeError as exc:
            raise InputError(f"{path}: {label}: {exc}") from None
    _check_outputs(path, jobs)
    return jobs


def _check_keys(path: Path, label: str, obj: dict, allowed: tuple[str, ...]) -> None:
    unknown = [k for k in obj if k not in allowed]
    if unknown:
        raise InputError(f"{path}: {label}: unknown key {unknown[0]!r}; keys are {', '.join(allowed)}")


def _merge(defaults: dict, job: dict) -> dict:
    merged = dict(defaults)
    for group in (MOTION_KEYS, SAMPLING_KEYS):
        if any(k in job for k in group):
            for k in group:
                merged.pop(k, None)
    merged.update(job)
    return merged


def _string(d: dict, key: str, required: bool = False) -> str | None:
    value = d.get(key)
    if value is None and not required:
        return None
    if not isinstance(value, str) or not value:
        raise InputError(f"{key!r} must be a non-empty string" + ("" if value is not None else " (required)"))
    if "\0" in value:
        raise InputError(f"{key!r} {value!r} holds a NUL character, which no file name or clip name can")
    return value


def _number(d: dict, key: str, default: float) -> float:
    value = d.get(key, default)
    if not _finite(value):
        raise InputError(f"{key!r} must be a finite number, got {value!r}")
    return float(value)


def _finite(value) -> bool:
    """A JSON number (not a boolean) that is a finite float (an integer of 400 digits is not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _choice(d: dict, key: str, choices: tuple[str, ...], default: str) -> str:
    value = d.get(key, default)
    if value not in choices:
        raise InputError(f"{key!r} must be one of {', '.join(choices)}, got {value!r}")
    return value


def _input_file(base: Path, value: str, key: str) -> str:
    p = (base / value).resolve()
    if not p.is_file():
        raise InputError(f"{key} {value}: no such file ({p})")
    return str(p)


def _job(index: int, d: dict, base: Path) -> Job:
    output = _output_name(_string(d, "output", required=True))
    character = _input_file(base, _string(d, "character", required=True), "character")
    skeleton = _string(d, "skeleton")
    motions = [k for k in MOTION_KEYS if d.get(k) is not None and d.get(k) is not False]
    if len(motions) != 1:
        raise InputError(f"give exactly one of {', '.join(MOTION_KEYS)}; got "
                         + (", ".join(motions) if motions else "none"))
    if "rest" in d and not isinstance(d["rest"], bool):
        raise InputError(f"'rest' must be true or false, got {d['rest']!r}")
    time, frames = d.get("time"), _string(d, "frames")
    if time is not None:
        values = time if isinstance(time, list) else [time]
        if not values or not all(_finite(t) for t in values):
            raise InputError(f"'time' must be a number or a non-empty list of numbers, got {time!r}")
        time = tuple(float(t) for t in values)
    if time is not None and frames is not None:
        raise InputError("give either 'time' or 'frames', not both")
    if motions[0] in ("rest", "pose") and (time is not None or frames is not None):
        raise InputError("'time' and 'frames' sample a clip; with 'rest' or 'pose' there is one frame: drop them")
    fps = _number(d, "fps", 30.0)
    if fps <= 0:
        raise InputError(f"'fps' must be positive, got {fps:g}")
    if frames is not None:
        parse_frames(frames, fps)
    retarget = None
    if motions[0] == "retarget":
        retarget = _retarget(d["retarget"], base)
        if Path(character).suffix.lower() not in TARGET_SUFFIXES:
            raise InputError(f"'retarget' drives a glTF character ({', '.join(TARGET_SUFFIXES)}), "
                             f"not {Path(character).name}")
        if frames_output_kind(output) == "glb":
            # `nrpose pose` of the retargeted .glb copies that file, retargeted animation and all
            raise InputError("a 'retarget' job writes .npz or a directory; for a .glb, run nrpose retarget "
                             "and bake the clip of its output")
    return Job(index=index, output=output, character=character,
               skeleton=_input_file(base, skeleton, "skeleton") if skeleton else None,
               clip=_string(d, "clip"),
               motion=_input_file(base, _string(d, "motion"), "motion") if d.get("motion") is not None else None,
               pose=_input_file(base, _string(d, "pose"), "pose") if d.get("pose") is not None else None,
               rest=d.get("rest") is True, retarget=retarget, time=time, frames=frames, fps=fps,
               method=_choice(d, "method", METHODS, "nrmls"),
               weights=_choice(d, "weights", WEIGHTS, "authored"),
               alpha=_number(d, "alpha", 1.0), blend=_choice(d, "blend", BLENDS, DEFAULT_BLEND),
               backend=_choice(d, "backend", BACKENDS, "opencl"),
               format=_choice(d, "format", FORMATS, "ply"), quantize=_quantize(d, output))


def _quantize(d: dict, output: str) -> bool:
    value = d.get("quantize", False)
    if not isinstance(value, bool):
        raise InputError(f"'quantize' must be true or false, got {value!r}")
    if value and frames_output_kind(output) != "glb":
        raise InputError("'quantize' compacts the morph targets of a .glb output; the output is not .glb")
    return value


def _retarget(spec, base: Path) -> Retarget:
    if not isinstance(spec, dict):
        raise InputError("'retarget' must be an object {\"source\": path, \"map\": path, ...}")
    unknown = [k for k in spec if k not in RETARGET_KEYS]
    if unknown:
        raise InputError(f"'retarget': unknown key {unknown[0]!r}; keys are {', '.join(RETARGET_KEYS)}")
    source = _string(spec, "source", required=True)
    if Path(source).suffix.lower() not in SOURCE_SUFFIXES:
        raise InputError(f"retarget source {source}: must end in {', '.join(SOURCE_SUFFIXES)}")
    for key in ("in_place", "force"):
        if not isinstance(spec.get(key, False), bool):
            raise InputError(f"'retarget': {key!r} must be true or false, got {spec[key]!r}")
    root = spec.get("root")
    if root is not None and root not in ROOT_MODES:
        raise InputError(f"'retarget': 'root' must be one of {', '.join(ROOT_MODES)}, got {root!r}")
    if spec.get("in_place") and root not in (None, "in-place"):
        raise InputError(f"'retarget': 'in_place' and 'root' {root!r} contradict each other; give one")
    mapping = _string(spec, "map")
    return Retarget(_input_file(base, source, "retarget source"),
                    _input_file(base, mapping, "retarget map") if mapping else None,
                    _string(spec, "source_clip"), "in-place" if spec.get("in_place") else root or "origin",
                    spec.get("force", False))


def _output_name(name: str) -> str:
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or ".." in p.parts or not p.parts or p.parts == (".",):
        raise InputError(f"'output' {name!r} must be a relative name under OUTDIR (no '..')")
    if p.parts[0] in RESERVED:
        raise InputError(f"'output' {name!r}: {p.parts[0]} is the bake's own")
    frames_output_kind(str(p))
    return str(p)


def _check_outputs(path: Path, jobs: list[Job]) -> None:
    """No two jobs write one output, and no output lies inside another job's output directory."""
    seen: dict[str, Job] = {}
    for job in jobs:
        key = job.output.casefold()      # one file on a case-insensitive filesystem
        if key in seen:
            raise InputError(f"{path}: {job.label}: writes the same output as {seen[key].label}")
        seen[key] = job
    for job in jobs:
        parents = PurePosixPath(job.output.casefold()).parents
        for parent in list(parents)[:-1]:
            if str(parent) in seen:
                raise InputError(f"{path}: {job.label}: lies inside the output of {seen[str(parent)].label}")
