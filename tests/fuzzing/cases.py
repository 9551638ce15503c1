"""Fuzz cases: a valid command line over seed files, then one or two mutations.

A :class:`Case` is everything a run needs: ``argv`` (relative to the case's directory;
``in/<slot>/<file>`` for inputs, ``out/...`` for outputs), the input files, the special
paths to build (:data:`tests.fuzzing.mutators.PATH_KINDS`), an optional file-size limit
(a full disk) or a closed stdout (a broken pipe), and labels for the summary: command,
template, input kind mutated and the mutation. :func:`make_case` is deterministic in
``(seed, index)``.
"""
from __future__ import annotations

import json
import random
from dataclasses import dataclass, field

from .mutators import BAD_VALUES, PATH_KINDS, mutate_file
from .seeds import BAKE_INPUTS, CLIP, Seed, jobs_document, manifest_document

__all__ = ["Case", "make_case", "COMMANDS"]

GLTF = ["glb", "gltf_embedded", "gltf_external"]
MESHES = ["obj", "off", "ply_ascii", "ply_binary", "stl_ascii", "stl_binary"]
MESH_OUT = [".obj", ".ply", ".off", ".stl", ".xyz"]
#: options whose value is a path (an input or an output)
PATH_FLAGS = {"-H", "-o", "--png", "--skeleton", "--motion", "--pose", "--map", "--summary", "--report", "--out"}
#: the share of cases of each command (bake, fit-skin and demo take seconds a case, the others well under one)
COMMANDS = {"deform": 0.23, "pose": 0.27, "weights": 0.13, "retarget": 0.18, "info": 0.09, "bake": 0.05,
            "fit-skin": 0.04, "demo": 0.01}
#: options a case may get added with a bad value, by command (and for every command)
ADDED_FLAGS = {"*": ["--fps", "--alpha", "--time", "--frames", "--k", "--bone", "--clip", "--source-clip", "--png",
                     "--method", "--weights", "--format"],
               "bake": ["--workers", "--summary", "--ray"],
               "fit-skin": ["--rom-degrees", "--influences", "--helpers", "--helper-tracks", "--train", "--holdout",
                            "--export", "--report"],
               "demo": ["--frames", "--repeat", "--out"]}
#: the kind of a file a seed refers to (mutated as that kind), by name
EXTRA_KINDS = dict(BAKE_INPUTS, **{"body.bin": "bin"})


@dataclass
class Case:
    """One fuzz case (see the module docstring)."""

    index: int
    command: str
    template: str
    argv: list
    files: dict = field(default_factory=dict)      # relative path -> bytes
    specials: dict = field(default_factory=dict)   # relative path -> path kind to build there
    input_kind: str = "none"                       # the kind of the mutated file, or "option"/"seed"
    mutation: str = "none"
    fsize: int | None = None                       # RLIMIT_FSIZE in bytes (a full disk)
    broken_pipe: bool = False                      # stdout closed before the run


class _Builder:
    def __init__(self, rng: random.Random, seeds: dict[str, Seed], shared: dict[str, Seed]):
        self.rng, self.seeds, self.shared = rng, seeds, shared
        self.slots: dict[str, tuple[str, Seed]] = {}   # slot -> (relative path, seed)

    def file(self, slot: str, kind: str, seed: Seed | None = None) -> str:
        """The path of a seed of ``kind`` (or ``seed`` itself) in the folder of ``slot``."""
        seed = seed or self.seeds[kind]
        if kind in self.shared and self.rng.random() < 0.1:
            seed = self.shared[kind]
        path = f"in/{slot}/{seed.name}"
        self.slots[slot] = (path, seed)
        return path

    def backend(self) -> list[str]:
        return ["--backend", "numpy" if self.rng.random() < 0.7 else "opencl"]

    def maybe(self, p: float, *tokens) -> list[str]:
        return list(tokens) if self.rng.random() < p else []


def _deform(b: _Builder) -> tuple[str, list]:
    r = b.rng
    kind = r.choice(MESHES + ["xyz"])
    weights = r.choice(["euclidean"] * 5 + ["graph", "heat", "exact"] + (["knn"] * 3 if kind == "xyz" else []))
    argv = ["deform", b.file("input", kind), "-H", b.file("handles", "handles"), "-o", f"out/o{r.choice(MESH_OUT)}",
            *b.backend(), "--weights", weights, *b.maybe(0.3, "--alpha", r.choice(["0.5", "2"])),
            *b.maybe(0.3, "--blend", r.choice(["relative", "paper", "quaternion"])),
            *b.maybe(0.2, "--lever", r.choice(["weight", "length", "paper"])), *b.maybe(0.15, "--png", "out/p.png")]
    return f"deform-{kind}", argv


def _pose_output(b: _Builder) -> list[str]:
    r = b.rng
    out = r.choice(["out/o.npz", "out/o.npz", "out/o.glb", "out/frames"])
    return ["-o", out] + (["--format", r.choice(["ply", "obj"])] if out == "out/frames" else [])


def _pose(b: _Builder) -> tuple[str, list]:
    r = b.rng
    variant = r.choice(["clip", "clip", "pose", "rest", "tgf-dmat", "bvh-motion", "bvh-clip"])
    if variant in ("clip", "pose", "rest"):
        argv = ["pose", b.file("character", r.choice(GLTF))]
        if variant == "clip":
            argv += ["--clip", CLIP] + r.choice([["--fps", "10"], ["--time", "0", "0.5"], ["--frames", "0:3"],
                                                 ["--fps", "5"]])
        elif variant == "pose":
            argv += ["--pose", b.file("pose", "pose_json")]
        else:
            argv += ["--rest"]
        argv += ["--weights", r.choice(["authored"] * 4 + ["euclidean", "graph", "heat"])]
    elif variant == "tgf-dmat":
        argv = ["pose", b.file("character", r.choice(MESHES)), "--skeleton", b.file("skeleton", "tgf"),
                "--pose", b.file("pose", r.choice(["dmat_ascii", "dmat_binary"])),
                "--weights", r.choice(["euclidean", "euclidean", "graph", "heat"])]
    else:
        argv = ["pose", b.file("character", r.choice(MESHES)), "--skeleton", b.file("skeleton", "bvh")]
        argv += (["--motion", b.file("motion", "bvh"), "--fps", "10"] if variant == "bvh-motion"
                 else ["--clip", "rig", "--fps", "10"])
        argv += ["--weights", r.choice(["euclidean", "graph"])]
    argv += [*_pose_output(b), *b.backend(), *b.maybe(0.3, "--method", r.choice(["nrmls", "lbs", "dqs"])),
             *b.maybe(0.2, "--alpha", "2"), *b.maybe(0.2, "--blend", r.choice(["paper", "quaternion"])),
             *b.maybe(0.1, "--png", "out/s.png")]
    return f"pose-{variant}", argv


def _weights(b: _Builder) -> tuple[str, list]:
    r = b.rng
    if r.random() < 0.6:
        argv, name = ["weights", b.file("character", r.choice(GLTF))], "weights-gltf"
    else:
        sk = r.choice(["tgf", "bvh"])
        argv = ["weights", b.file("character", r.choice(MESHES)), "--skeleton", b.file("skeleton", sk)]
        name = f"weights-mesh-{sk}"
    argv += ["--method", r.choice(["euclidean", "euclidean", "graph", "heat", "exact"]), "-o", "out/w.npz",
             *b.maybe(0.3, "--k", r.choice(["1", "2", "all"])), *b.maybe(0.2, "--alpha", "2"),
             *b.maybe(0.15, "--png", "out/w.png", "--bone", "Spine")]
    return name, argv


def _retarget(b: _Builder) -> tuple[str, list]:
    r = b.rng
    src = r.choice(["bvh", "bvh"] + GLTF)
    argv = ["retarget", b.file("source", src), b.file("target", r.choice(GLTF)), "--fps", r.choice(["10", "5"]),
            *b.maybe(0.4, "--map", b.file("map", "map_json")), *b.maybe(0.2, "--in-place"),
            *b.maybe(0.15, "--show-map"), "-o", r.choice(["out/r.glb", "out/r.glb", "out/r.bvh"]),
            *b.maybe(0.1, "--png", "out/r.png"), *(b.maybe(0.3, "--source-clip", CLIP) if src != "bvh" else [])]
    return f"retarget-{'bvh' if src == 'bvh' else 'gltf'}", argv


def _info(b: _Builder) -> tuple[str, list]:
    r = b.rng
    if r.random() < 0.7:
        kind = r.choice(GLTF + ["bvh", "tgf"])
        return f"info-{kind}", ["info", b.file("character", kind)]
    sk = r.choice(["tgf", "bvh"])
    return f"info-mesh-{sk}", ["info", b.file("character", r.choice(MESHES)), "--skeleton", b.file("skeleton", sk)]


def _bake(b: _Builder) -> tuple[str, list]:
    """A JOBS file of 1-4 seed jobs next to the files they read, one local worker; sometimes an
    OUTDIR with the manifest of an earlier run (``--resume``)."""
    r = b.rng
    doc = jobs_document(r)
    extra = {name: b.seeds[kind].data for name, kind in BAKE_INPUTS.items()}
    jobs = b.file("jobs", "jobs_json", Seed("jobs.json", "jobs_json", json.dumps(doc, indent=1).encode(), extra))
    out, name = "out/bake", "bake"
    if r.random() < 0.25:
        outputs = [j["output"] for j in doc["jobs"] if r.random() < 0.5] + ["gone.npz"]
        out = b.file("prev", "manifest", Seed("manifest.json", "manifest",
                                              json.dumps(manifest_document(outputs), indent=1).encode()))
        out, name = out.rsplit("/", 1)[0], "bake-resume"
    argv = ["bake", jobs, "-o", out, "--workers", "1", *b.maybe(0.4, "--summary", "out/summary.json"),
            *b.maybe(0.5 if name == "bake-resume" else 0.1, "--resume")]
    return name, argv


def _fit_skin(b: _Builder) -> tuple[str, list]:
    """The seed glTF (74 vertices, 7 joints), or a seed mesh with the TGF (trained on a DMAT pose)
    or BVH skeleton (on its clip), fitted to a few training motions at a low --fps."""
    r = b.rng
    if r.random() < 0.3:
        sk = r.choice(["tgf", "bvh"])
        train = [r.choice(["dmat_ascii", "dmat_binary"])] if sk == "tgf" else ["rig"]
        character = [b.file("character", r.choice(MESHES)), "--skeleton", b.file("skeleton", sk)]
    else:
        train = r.choice([[CLIP], [CLIP], ["bvh"], ["pose_json"], ["glb"], [CLIP, "bvh", "pose_json"]])
        character = [b.file("character", r.choice(GLTF))]
    specs = [t if t in (CLIP, "rig") else b.file(f"train{i}", t) for i, t in enumerate(train)]
    argv = ["fit-skin", *character, "--train", *specs, "-o", "out/f.glb",
            "--fps", r.choice(["5", "3"]), *b.maybe(0.7, "--rom-degrees", r.choice(["0", "10", "30", "90"])),
            *b.maybe(0.3, "--report", "out/r.json")]
    if r.random() < 0.2:
        argv += ["--holdout", CLIP if r.random() < 0.5 else b.file("holdout", "bvh")]
    if r.random() < 0.15:
        argv += ["--export", b.file("export", "bvh")]
    if r.random() < 0.2:
        argv += ["--helpers", r.choice(["1", "2"]), *b.maybe(0.5, "--helper-tracks", "fitted")]
    argv += [*b.maybe(0.2, "--influences", "8"),
             *b.maybe(0.2, "--weights", r.choice(["euclidean", "graph"])), *b.maybe(0.1, "--alpha", "2")]
    return f"fit-skin-{'+'.join(train)}", argv


def _demo(b: _Builder) -> tuple[str, list]:
    """Two walk frames and one timed pose of each box configuration (options only)."""
    r = b.rng
    return "demo", ["demo", "--out", r.choice(["out/d", "out/d/e"]), "--frames", r.choice(["1", "2", "3"]),
                    "--repeat", "1"]


TEMPLATES = {"deform": _deform, "pose": _pose, "weights": _weights, "retarget": _retarget, "info": _info,
             "bake": _bake, "fit-skin": _fit_skin, "demo": _demo}


def _mutate_option(case: Case, rng: random.Random) -> None:
    argv = case.argv
    flags = [i for i, a in enumerate(argv) if a.startswith("-") and i + 1 < len(argv)
             and not argv[i + 1].startswith("-")]
    positional = [i for i, a in enumerate(argv[1:], 1) if a.startswith("in/") and not argv[i - 1].startswith("-")]
    choice = rng.random()
    if choice < 0.15:   # an option added with a bad value
        flag = rng.choice(ADDED_FLAGS["*"] + ADDED_FLAGS.get(case.command, []))
        value = rng.choice(BAD_VALUES)
        argv += [flag, value]
        case.mutation = f"add {flag} {value[:20]!r}"
        return
    i = rng.choice(flags + positional) if flags or positional else None
    if i is None:
        return
    if i in positional or argv[i] in PATH_FLAGS:
        at = i if i in positional else i + 1
        kind = rng.choice(PATH_KINDS)
        old = argv[at]
        suffix = old[old.rfind("."):] if "." in old.rsplit("/", 1)[-1] else ""
        if rng.random() < 0.2:
            suffix = rng.choice(["", ".png", ".npz", ".txt", ".glb", ".PLY", ".json", ".bvh"])
        path = {"dir": f"out/adir{suffix}", "fifo": f"out/fifo{suffix}", "readonly": f"ro/x{suffix}",
                "missing_dir": f"nodir/x{suffix}", "empty": "", "long": "out/" + "a" * 300 + suffix,
                "newline": f"out/a\nb{suffix}", "under_file": f"{next(iter(case.files), 'in')}/x{suffix}",
                "existing_input": next(iter(case.files), "in"), "dotdot": f"out/../out/y{suffix}"}[kind]
        if kind in ("dir", "fifo", "readonly"):
            case.specials[path] = kind
        argv[at] = path
        case.mutation = f"{argv[i] if at != i else 'positional'} -> {kind} {path[:40]!r}"
    else:
        value = rng.choice(BAD_VALUES)
        argv[i + 1] = value
        case.mutation = f"{argv[i]} {value[:20]!r}"


def make_case(seed: int, index: int, seeds: dict[str, Seed], shared: dict[str, Seed] | None = None,
              commands: dict[str, float] | None = None) -> Case:
    """Case ``index`` of the run ``seed`` (deterministic); ``commands``: the share of each
    command (default :data:`COMMANDS`)."""
    rng = random.Random(f"{seed}:{index}")
    commands = commands or COMMANDS
    command = rng.choices(list(commands), weights=list(commands.values()))[0]
    b = _Builder(rng, seeds, shared or {})
    template, argv = TEMPLATES[command](b)
    case = Case(index, command, template, argv)
    for slot, (path, seed_) in b.slots.items():
        case.files[path] = seed_.data
        for name, data in seed_.extra.items():
            case.files[path.rsplit("/", 1)[0] + "/" + name] = data
    r = rng.random()
    if r < 0.04:
        case.input_kind, case.mutation = "seed", "none"
    elif r < 0.26 or not b.slots:
        case.input_kind = "option"
        _mutate_option(case, rng)
    elif r < 0.28:
        case.input_kind, case.mutation, case.fsize = "disk", "file size limit", rng.choice([0, 100, 3000])
    else:
        slot = rng.choice(sorted(b.slots))
        path, seed_ = b.slots[slot]
        targets = [(path, seed_.kind)] + [(path.rsplit("/", 1)[0] + "/" + n, EXTRA_KINDS.get(n, "bin"))
                                          for n in seed_.extra]
        target, kind = rng.choice(targets) if rng.random() < 0.3 else targets[0]
        data, what = mutate_file(case.files[target], kind, rng)
        if rng.random() < 0.15:
            data, more = mutate_file(data, kind, rng)
            what += "; " + more
        case.files[target] = data
        case.input_kind, case.mutation = kind, what
    if command == "info" and rng.random() < 0.05:
        case.broken_pipe = True
        case.mutation += "; stdout closed"
    return case
