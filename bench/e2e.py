"""e2e suite: the whole job, file to file, as a user runs it, against Blender 5 doing the same.

    .venv/bin/python -m bench --suite e2e [--repeat 5] [--quick] [--no-blender] [--json OUT.json]
                                             [--characters fox,mannequin,ely] [--outputs npz,glb] [--data DIR]

(``.venv/bin/python bench/e2e.py`` takes the same options.)

Every timed job is a whole process: ``nrpose pose CHARACTER --clip CLIP --method M -o OUT``
(the console script next to the interpreter running this file, as a user starts it), for
each method (nrmls, lbs, dqs; authored weights, 30 fps, the whole clip) into ``.npz`` and
into ``.glb``, on Fox (clip Run), Mannequin and Ely (each with CMU 131_03 retargeted onto
it by ``nrpose retarget`` into a temporary folder at the start). The anchor: Blender 5
(``bpy`` in the project's .venv-blender, made by ``make blender``, which this
benchmark runs when it is missing) importing the same .glb,
playing the same clip at the same frames, reading back every frame's deformed vertices
and writing them with ``np.savez`` (bench/blender_bake.py). Its positions are checked
against ``nrpose pose --method lbs`` (the same job, linear blend skinning of the authored
weights): ``agreement`` in the record.

Modes: ``cold`` -- a fresh empty nrpose binding cache (NRPOSE_CACHE_DIR) and PoCL kernel
cache (POCL_CACHE_DIR) per run, and the input .glb dropped from the OS page cache
(posix_fadvise DONTNEED on that file only: no root-wide drop_caches); the interpreter's
and the libraries' files stay cached. ``warm`` -- caches filled by an untimed run of the
same job, input file read just before. Runs are alternated: per round every contestant
runs once per mode, the order rotated by round. nrpose runs with the OpenCL drivers of a
user's install, PoCL's alone (:func:`user_icds`; the test extra adds Oclgrind's). Reported per contestant: wall time of the
process (start to reaped), peak RSS (the job's ru_maxrss, seen from a small launcher process), CPU time;
medians with p10/p90 over ``--repeat`` rounds; the ratio Blender / nrpose of the medians
and per round (paired).

The OpenCL floor (:data:`FLOOR`), alternated with the jobs in both modes: a process that
imports numpy and pyopencl and builds and runs a one-line kernel on the device the jobs
use. Beside the cold target the record puts the cold floor's median and the budget the
target leaves a job (Blender's median / the ratio): where the budget is below the floor, no
job that runs its kernels on PoCL can meet it. (Warm, nrpose builds its programs from the
binaries in its binding cache, which the floor does not: its warm figure is no floor.)

Breakdown: per character and method (into .npz, warm caches), instrumented runs of the
same job, :data:`BREAKDOWN_RUNS` of each kind (medians): ``-X importtime`` (module import
time, the modules imported); then, with every one of those modules imported beforehand (so
no import time falls in a stage), the functions of :data:`STAGE_RULES` (load / bind / pose
/ write) timed by wrappers; and one run under cProfile for the functions that bound each
stage.

Not a test: no assertions; the machine is shared, so the record keeps load averages and
CPU steal beside the figures.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import pstats
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from nrpose import diagnostics

HERE = pathlib.Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import common  # noqa: E402

SCHEMA = "nrpose-bench-e2e/1"
DEFAULT_JSON = HERE / "results" / "e2e.json"
DEFAULT_DATA = HERE.parent.parent / "shared" / "data"
METHODS = ("nrmls", "lbs", "dqs")
OUTPUTS = ("npz", "glb")
MODES = ("cold", "warm")
FPS = 30
MOTION = "bvh/131_03.bvh"
# name, file under the data folder, clip (None: retarget MOTION onto it)
CHARACTERS = (("fox", "gltf/Fox.glb", "Run"), ("mannequin", "gltf/Mannequin.glb", None),
              ("ely", "gltf/Ely.glb", None))
ROOT = HERE.parent
BLENDER_ENV = ROOT / ".venv-blender"      # the Makefile's `blender` target makes it
BPY_PYTHON = (3, 11)            # the only CPython the bpy 5 wheels are built for
# Blender vs nrpose lbs, max distance / rest bounding-box diagonal: float32 round-off where
# the frames fall on the clip's keys (measured ~1e-5)
AGREEMENT_TOLERANCE = 1e-4
# (stage, module path regex, qualified function name regex): the functions timed as the
# stages of a job. Stage times are exclusive: a stage's function called inside another
# stage's (frames posed as the writer takes them) counts for its own stage only; nested
# calls within a stage count once; a generator function is timed while it runs (each
# step). Update the paths when the package moves.
STAGE_RULES = (
    ("load", r"nrpose/io/__init__\.py$", r"load_character"),
    ("load", r"nrpose/model/character\.py$", r"Clips\.__getitem__"),   # a clip decoded when first used
    ("bind", r"nrpose/pose/poser\.py$", r"CharacterPoser\.__init__"),
    ("pose", r"nrpose/pose/poser\.py$", r"CharacterPoser\.(pose|stream|_posed_batches)"),
    ("pose", r"nrpose/model/character\.py$", r"(Clip|Track)\.sample"),   # the clip's local poses
    ("write", r"nrpose/cli/(pose|common)\.py$", r"write_frames"),       # the pose command's writer
)
STAGES = ("load", "bind", "pose", "write")
BREAKDOWN_RUNS = 5      # instrumented runs of each kind per job: the breakdown's figures are their medians
HEAVY_MODULES = ("matplotlib", "pymeshlab", "igl", "scipy.spatial", "pygltflib")
TARGETS = {"nrmls_warm_vs_blender_min": 3.0, "lbs_warm_vs_blender_min": 4.0, "cold_vs_blender_min": 1.5,
           "imports_s_max": 0.25, "gltf_load_mannequin_s_max": 0.030}

# Runs in the job's interpreter: python -c PROBE MODULES.json RULES.json OUT MODE nrpose-args...
# Imports every module in MODULES.json first (the job then imports nothing), then runs
# `nrpose` with MODE "timers" (the functions of RULES.json wrapped in timers; OUT gets
# {stage: seconds}) or "profile" (cProfile; OUT gets its stats). Last stdout line: JSON
# {"job_s"}: the job's wall time after the imports.
PROBE = r"""
import cProfile, functools, importlib, inspect, json, os, re, runpy, sys, time
mods, rules, out, mode = json.load(open(sys.argv[1])), json.load(open(sys.argv[2])), sys.argv[3], sys.argv[4]
for m in mods:
    try:
        importlib.import_module(m)
    except Exception:
        pass
spent, running, wrapped = {}, [], {}   # running: [stage, since] of the stages entered, innermost last

def enter(stage):
    now = time.perf_counter()
    if running:                      # the enclosing stage pauses
        outer = running[-1]
        spent[outer[0]] = spent.get(outer[0], 0.0) + now - outer[1]
    running.append([stage, now])

def leave():
    now = time.perf_counter()
    stage, since = running.pop()
    spent[stage] = spent.get(stage, 0.0) + now - since
    if running:
        running[-1][1] = now

def timer(f, stage):
    def inside():
        return running and running[-1][0] == stage
    if inspect.isgeneratorfunction(f):
        @functools.wraps(f)
        def timed_steps(*a, **k):
            it = f(*a, **k)
            while True:
                nested = inside()
                if not nested:
                    enter(stage)
                try:
                    item = next(it)
                except StopIteration as stop:
                    return stop.value
                finally:
                    if not nested:
                        leave()
                yield item
        return timed_steps

    @functools.wraps(f)
    def timed(*a, **k):
        if inside():
            return f(*a, **k)
        enter(stage)
        try:
            return f(*a, **k)
        finally:
            leave()
    return timed

if mode == "timers":
    for mod in list(sys.modules.values()):
        path = (getattr(mod, "__file__", None) or "").replace(os.sep, "/")
        for stage, mod_re, fn_re in rules:
            if not re.search(mod_re, path):
                continue
            for name, obj in list(vars(mod).items()):
                if getattr(obj, "__module__", None) != mod.__name__:
                    continue
                owners = [(mod, name, obj)] if inspect.isfunction(obj) else [
                    (obj, n, v) for n, v in vars(obj).items() if inspect.isfunction(v)] if inspect.isclass(obj) else []
                for owner, n, f in owners:
                    if f not in wrapped and re.fullmatch(fn_re, f.__qualname__):
                        wrapped[f] = timer(f, stage)
                        setattr(owner, n, wrapped[f])
    for mod in list(sys.modules.values()):    # names imported elsewhere at module level
        if getattr(mod, "__name__", "").startswith("nrpose"):
            for name, obj in list(vars(mod).items()):
                if inspect.isfunction(obj) and obj in wrapped:
                    setattr(mod, name, wrapped[obj])
sys.argv = ["nrpose"] + sys.argv[5:]
prof, code, t = cProfile.Profile(), 0, time.perf_counter()
if mode == "profile":
    prof.enable()
try:
    runpy.run_module("nrpose", run_name="__main__", alter_sys=True)
except SystemExit as e:
    code = e.code or 0
prof.disable()
job = time.perf_counter() - t
if mode == "profile":
    prof.dump_stats(out)
else:
    json.dump({"stages": spent, "wrapped": sorted(f"{f.__module__}.{f.__qualname__}" for f in wrapped)},
              open(out, "w"))
print(json.dumps({"job_s": job}))
sys.exit(code)
"""


# --------------------------------------------------------------------------- processes

def nrpose_script() -> pathlib.Path:
    """The ``nrpose`` console script beside this interpreter (a venv's bin/), else on PATH."""
    here = pathlib.Path(sys.executable).parent / "nrpose"
    found = here if here.exists() else shutil.which("nrpose")
    if not found:
        raise RuntimeError("no nrpose console script beside this Python or on PATH: run from the venv "
                           "(make venv; .venv/bin/python bench/e2e.py)")
    return pathlib.Path(found)


def script_python(script: pathlib.Path) -> str:
    """The interpreter a console script runs under (its #! line)."""
    first = script.read_text(errors="replace").splitlines()[0]
    return first[2:].strip().split()[0] if first.startswith("#!") else sys.executable


#: a small Python that runs the job and writes its wall time, peak RSS and CPU time
#: (argv: OUT.json job...): see :func:`run_process`
LAUNCHER = r"""
import json, resource, subprocess, sys, time
t = time.perf_counter()
code = subprocess.call(sys.argv[2:])
wall = time.perf_counter() - t
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
with open(sys.argv[1], "w") as f:
    json.dump({"wall_s": wall, "peak_rss_kib": ru.ru_maxrss, "cpu_s": ru.ru_utime + ru.ru_stime}, f)
sys.exit(code)
"""


#: the OpenCL floor (argv: none): what any PoCL job pays before its own work -- numpy and
#: pyopencl imported, a context on PoCL's worker-thread CPU device (the device a whole
#: ``nrpose`` job runs on), a one-line kernel built and run once. Cold (an empty
#: POCL_CACHE_DIR), PoCL parses its kernel library and compiles; no nrpose job can be faster.
FLOOR = r"""
import os
os.environ["POCL_DEVICES"] = "pthread"
import numpy as np
import pyopencl as cl
device = next(d for p in cl.get_platforms() if "Portable Computing Language" in p.name
              for d in p.get_devices(device_type=cl.device_type.CPU))
ctx = cl.Context([device])
queue = cl.CommandQueue(ctx)
program = cl.Program(ctx, "__kernel void twice(__global float *a) { a[get_global_id(0)] *= 2.0f; }").build()
a = np.ones(16, np.float32)
buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
program.twice(queue, a.shape, None, buf)
cl.enqueue_copy(queue, a, buf)
assert (a == 2).all()
"""


def run_process(cmd: list, env: dict, log_path: pathlib.Path) -> dict:
    """Run ``cmd`` to completion, stdout and stderr to ``log_path``. Returns
    {"wall_s", "peak_rss_mib", "cpu_s", "stdout"}; RuntimeError with the output's tail on
    a non-zero exit.

    The job is started and timed by :data:`LAUNCHER` in a small interpreter (``-I -S``):
    Linux counts the memory of the process that forks a job into the job's peak RSS
    (ru_maxrss covers the forked copy before exec), so forked from this benchmark every
    job would show at least the benchmark's own size."""
    stats = log_path.with_suffix(".rusage.json")
    with open(log_path, "wb") as log:
        code = subprocess.call([sys.executable, "-I", "-S", "-c", LAUNCHER, str(stats), *map(str, cmd)],
                               stdout=log, stderr=subprocess.STDOUT, env=env)
    text = log_path.read_text(errors="replace")
    if code != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} exited {code}: {text[-2000:]}")
    r = json.loads(stats.read_text())
    return {"wall_s": r["wall_s"], "peak_rss_mib": r["peak_rss_kib"] / 1024, "cpu_s": r["cpu_s"], "stdout": text}


def evict(path: pathlib.Path) -> bool:
    """Drop ``path``'s pages from the OS page cache (this file only); False if refused."""
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)
        return True
    except (OSError, AttributeError):
        return False


def read_through(path: pathlib.Path) -> None:
    """Read ``path`` whole so that its pages are in the OS page cache."""
    with open(path, "rb") as f:
        while f.read(1 << 20):
            pass


# --------------------------------------------------------------------------- Blender

def blender_python(log=None) -> tuple[str | None, dict]:
    """The interpreter of the project's ``bpy`` environment (.venv-blender), made by ``make
    blender`` on first use; (None, info with "reason") where it cannot be had."""
    info = {"env": str(BLENDER_ENV), "made_by": "make blender"}
    py = BLENDER_ENV / "bin" / "python"
    if not py.exists():
        base = next((c for c in (shutil.which(f"python{BPY_PYTHON[0]}.{BPY_PYTHON[1]}"),
                                 getattr(sys, "_base_executable", None), shutil.which("python3")) if c), None)
        version = subprocess.run([base, "-c", "import sys; print(*sys.version_info[:2])"], capture_output=True,
                                 text=True).stdout.split() if base else []
        if tuple(map(int, version)) != BPY_PYTHON:
            info["reason"] = (f"bpy 5 needs CPython {BPY_PYTHON[0]}.{BPY_PYTHON[1]}; found "
                              f"{'.'.join(version) or 'no python3'} ({base})")
            return None, info
        if shutil.which("make") is None:
            info["reason"] = f"no bpy environment at {BLENDER_ENV} and no make to run `make blender`"
            return None, info
        if log:
            log(f"e2e: make blender (bpy into {BLENDER_ENV}; once, a few minutes)")
        r = subprocess.run(["make", "-C", str(ROOT), "blender", f"PYTHON={base}"], capture_output=True, text=True)
        if r.returncode != 0:
            tail = (r.stderr or r.stdout).strip().splitlines()
            info["reason"] = f"make blender failed: {tail[-1] if tail else r.returncode}"
            return None, info
    r = subprocess.run([str(py), "-c", "import sys, bpy; print(bpy.app.version_string); print(sys.version.split()[0])"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        tail = r.stderr.strip().splitlines()
        info["reason"] = f"import bpy failed in {BLENDER_ENV}: {tail[-1] if tail else r.returncode}"
        return None, info
    info["bpy_version"], info["python"] = r.stdout.split()[:2]
    return str(py), info


def agreement(nrpose_npz: pathlib.Path, blender_npz: pathlib.Path) -> dict:
    """Distances between nrpose's and Blender's positions of the same frames, per vertex
    matched by nearest neighbour in frame 0 within the mesh of the same name; max, p99 and
    frame 0's max, as fractions of the rest bounding-box diagonal."""
    from scipy.spatial import cKDTree

    a, b = np.load(nrpose_npz), np.load(blender_npz)
    pos, names = a["positions"], [str(n) for n in a["mesh_names"]]
    edges = np.append(a["mesh_offsets"][:len(names)], pos.shape[1])     # mesh_offsets: each mesh's first vertex
    theirs = {str(n): b[f"positions_{i}"] for i, n in enumerate(b["names"])}
    diag = float(np.linalg.norm(pos[0].max(axis=0) - pos[0].min(axis=0)))
    errs = []
    for i, name in enumerate(names):
        ours = pos[:, edges[i]:edges[i + 1]]
        other = theirs.get(name)
        if other is None or other.shape[0] != ours.shape[0]:
            return {"error": f"mesh {name!r}: Blender has {None if other is None else other.shape}, "
                             f"nrpose {ours.shape}"}
        _, idx = cKDTree(other[0]).query(ours[0])
        errs.append(np.linalg.norm(ours - other[:, idx], axis=2))
    err = np.concatenate(errs, axis=1) / diag
    per_frame = err.max(axis=1)
    return {"max_rel": float(err.max()), "p99_rel": float(np.percentile(err, 99)),
            "frame0_max_rel": float(per_frame[0]), "worst_frame": int(per_frame.argmax()),
            "per_frame_max_rel": [float(f"{x:.3g}") for x in per_frame],
            "frames": int(err.shape[0]), "vertices": int(err.shape[1]), "diagonal": diag,
            "tolerance_rel": AGREEMENT_TOLERANCE, "within_tolerance": bool(err.max() <= AGREEMENT_TOLERANCE),
            "note": "between a clip's keys Blender interpolates quaternion components linearly (then "
                    "normalises) where nrpose slerps: frames off the keys may differ by more than the tolerance"}


# --------------------------------------------------------------------------- breakdown

def import_times(stderr: str, startup=()) -> dict:
    """``-X importtime`` lines -> {"total_s": the top-level imports' cumulative times,
    those of the interpreter's own start (``startup``: module names) left out;
    "startup_s": those; "modules": every module in import order; "top": the 12 slowest
    top-level imports; "heavy_imported": {module: imported?} for :data:`HEAVY_MODULES`}."""
    rows = []
    for line in stderr.splitlines():
        m = re.match(r"import time:\s+(\d+)\s+\|\s+(\d+)\s+\|( *)(\S+)", line)
        if m:
            rows.append((m.group(4), int(m.group(2)) * 1e-6, len(m.group(3)) - 1))
    top = [(name, cum) for name, cum, depth in rows if depth == 0]
    mods = [name for name, _, _ in rows]
    job = [(n, c) for n, c in top if n not in startup]
    return {"total_s": sum(c for _, c in job), "startup_s": sum(c for n, c in top if n in startup),
            "modules": mods, "top": [{"module": n, "cumulative_s": c} for n, c in sorted(job, key=lambda r: -r[1])[:12]],
            "heavy_imported": {h: any(m == h or m.startswith(h + ".") for m in mods) for h in HEAVY_MODULES}}


def _probe(py: str, mode: str, args: list, env: dict, tmp: pathlib.Path) -> float:
    r = subprocess.run([py, "-c", PROBE, str(tmp / "modules.json"), str(tmp / "rules.json"), str(tmp / mode), mode,
                        *args], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"instrumented run ({mode}) failed: {r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])["job_s"]


def breakdown(py: str, args: list, env: dict, tmp: pathlib.Path, runs: int = BREAKDOWN_RUNS) -> dict:
    """Imports and stages of one job (``args`` after ``nrpose``), medians of ``runs`` runs of
    each kind: ``-X importtime``; with every module it imports imported beforehand and the
    :data:`STAGE_RULES` functions timed; then one run under cProfile (its 15 functions of
    most own time)."""
    r = subprocess.run([py, "-X", "importtime", "-c", "pass"], env=env, capture_output=True, text=True)
    startup = set(import_times(r.stderr)["modules"])
    runs_of_imports = []
    for _ in range(runs):
        r = subprocess.run([py, "-X", "importtime", "-m", "nrpose", *args], env=env, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"importtime run failed: {r.stderr[-2000:]}")
        runs_of_imports.append(import_times(r.stderr, startup))
    imports = runs_of_imports[0]
    (tmp / "modules.json").write_text(json.dumps([m for m in imports["modules"] if not m.endswith("__main__")]))
    (tmp / "rules.json").write_text(json.dumps(STAGE_RULES))
    jobs, stage_runs = [], []
    for _ in range(runs):
        jobs.append(_probe(py, "timers", args, env, tmp))
        timed = json.loads((tmp / "timers").read_text())
        stage_runs.append({s: timed["stages"].get(s, 0.0) for s in STAGES})
    secs = {s: float(np.median([r[s] for r in stage_runs])) for s in STAGES}
    job = float(np.median(jobs))
    profiled = _probe(py, "profile", args, env, tmp)
    st = pstats.Stats(str(tmp / "profile"))
    top = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:15]
    return {"runs": runs, "imports_s": float(np.median([i["total_s"] for i in runs_of_imports])),
            "imports_s_runs": [i["total_s"] for i in runs_of_imports],
            "interpreter_start_imports_s": imports["startup_s"],
            "stages_s": secs, "stages_s_runs": stage_runs, "job_s": job, "other_s": job - sum(secs.values()),
            "stage_functions": timed["wrapped"], "import_top": imports["top"],
            "heavy_imported": imports["heavy_imported"], "modules_imported": len(imports["modules"]),
            "profiled_job_s": profiled,
            "top_tottime": [{"function": f"{pathlib.Path(k[0]).name}:{k[1]}({k[2]})", "tottime_s": v[2],
                             "cumtime_s": v[3], "calls": v[1]} for k, v in top]}


# --------------------------------------------------------------------------- the suite

def user_icds() -> dict:
    """The environment that gives the timed processes the OpenCL drivers of a user's install
    (``pip install nrpose``: PoCL's alone): ``{"OCL_ICD_VENDORS": <PoCL's .icd>}`` where the
    pyopencl wheel's driver folder also holds others (the test extra's Oclgrind, whose
    loading at platform enumeration costs ~15 ms per process), else {}; {} too where that
    PoCL cannot compile for this CPU (the machine's own PoCL is then the user's)."""
    icd = diagnostics.pypi_pocl_icd()
    if icd is None or not (set(icd.parent.glob("*.icd")) - {icd}) or diagnostics.pypi_pocl_refusal():
        return {}
    return {"OCL_ICD_VENDORS": str(icd)}


def prepare(data: pathlib.Path, names, script: pathlib.Path, tmp: pathlib.Path, env: dict, log=None) -> tuple:
    """[{name, path, clip, source}] of the characters present, and [{name, reason}] skipped."""
    out, skipped = [], []
    for name, rel, clip in CHARACTERS:
        if name not in names:
            continue
        path = data / rel
        if not path.exists():
            skipped.append({"character": name, "reason": f"{path} not found"})
            continue
        if clip is None:
            motion = data / MOTION
            if not motion.exists():
                skipped.append({"character": name, "reason": f"{motion} not found"})
                continue
            target = tmp / f"{path.stem}-{motion.stem}.glb"
            r = run_process([script, "retarget", motion, path, "-o", target], env, tmp / "retarget.log")
            m = re.search(r"animation '([^']+)'", r["stdout"])
            out.append({"character": name, "path": target, "clip": m.group(1) if m else motion.stem,
                        "source": f"{rel} + {MOTION} (nrpose retarget)"})
            if log:
                log(f"e2e: {r['stdout'].strip()}")
        else:
            out.append({"character": name, "path": path, "clip": clip, "source": f"{rel} (clip {clip})"})
    return out, skipped


def contestants(methods, outputs, blender: bool) -> list[tuple]:
    """(who, method, output) in the order of round 0: nrpose's jobs, the OpenCL floor
    (:data:`FLOOR`, no output), Blender's job."""
    out = [("nrpose", m, o) for m in methods for o in outputs] + [("floor", None, None)]
    return out + ([("blender", None, "npz")] if blender else [])


def run(repeat: int = 5, quick: bool = False, data=None, names=None, blender: bool = True, log=None,
        outputs=OUTPUTS) -> dict:
    """Run the suite; return the record (module docstring; bench/README.md). outputs: the
    output kinds timed (a subset of :data:`OUTPUTS`)."""
    data = pathlib.Path(data) if data is not None else DEFAULT_DATA
    names = tuple(names or ([CHARACTERS[0][0]] if quick else [c[0] for c in CHARACTERS]))
    methods = METHODS[:1] if quick else METHODS
    rounds = 1 if quick else max(int(repeat), 1)
    blender = blender and not quick
    script = nrpose_script()
    py = script_python(script)
    doc = {"schema": SCHEMA, "timestamp": common.now(), "git_commit": common.git("rev-parse", "HEAD"),
           "options": {"repeat": rounds, "quick": quick, "data": str(data), "characters": list(names),
                       "methods": list(methods), "outputs": list(outputs), "modes": list(MODES), "fps": FPS,
                       "weights": "authored", "nrpose": str(script), "python": py},
           "environment": common.environment(), "load_start": common.load(),
           "modes": {"cold": "each run: fresh empty NRPOSE_CACHE_DIR and POCL_CACHE_DIR, the input .glb dropped "
                             "from the OS page cache (posix_fadvise DONTNEED on that file; no system-wide "
                             "drop_caches); interpreter and library files stay in the page cache. pyopencl keeps no "
                             "binary cache of its own on PoCL (it leaves caching to PoCL)",
                     "warm": "binding and PoCL caches filled by an untimed run of the same job; the input "
                             "file read just before the run"},
           "measure": "wall: process start to reaped (perf_counter around subprocess.call in a small launcher "
                      "process); peak_rss: the job's ru_maxrss (RUSAGE_CHILDREN of the launcher); cpu: its user + "
                      "system time; medians, p10, p90 over rounds; "
                      "vs_blender: Blender's median wall / this row's (same mode, same character; > 1: nrpose "
                      "faster), paired: the same ratio per round",
           "opencl_icds": user_icds(),
           "rows": [], "agreement": {}, "breakdown": [], "skipped": []}
    t_all, cpu_all = time.perf_counter(), common.cpu_times()
    bpy_python, doc["blender"] = blender_python(log) if blender else (None, {"reason": "not requested"})
    doc["blender"]["available"] = bpy_python is not None
    if blender and bpy_python is None and log:
        log(f"e2e: Blender anchor skipped: {doc['blender']['reason']}")
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="nrpose-e2e-"))
    try:
        base = dict(os.environ, **doc["opencl_icds"])
        warm = {"NRPOSE_CACHE_DIR": str(tmp / "warm" / "nrpose"), "POCL_CACHE_DIR": str(tmp / "warm" / "pocl")}
        base_env = dict(base, **warm)
        chars, doc["skipped"] = prepare(data, names, script, tmp, base_env, log)
        for s in doc["skipped"]:
            if log:
                log(f"e2e: {s['character']} skipped: {s['reason']}")
        for ch in chars:
            doc["rows"].extend(_character(ch, methods, outputs, rounds, script, py, bpy_python, tmp, base, warm,
                                          doc, log))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    _ratios(doc["rows"])
    doc["seconds"] = time.perf_counter() - t_all
    doc["load_end"] = common.load()
    doc["cpu_steal_percent"] = common.steal_percent(cpu_all, common.cpu_times())
    doc["targets"] = targets(doc)
    return doc


def _character(ch, methods, outputs, rounds, script, py, bpy_python, tmp, base, warm, doc, log) -> list[dict]:
    name, glb, clip = ch["character"], ch["path"], ch["clip"]
    work = tmp / name
    work.mkdir()
    cpu0, load0 = common.cpu_times(), common.load()
    # the reference job (also the warm-up of lbs -> npz): frames and vertices, and the agreement's nrpose side
    ref = work / "reference-lbs.npz"
    warm_env = dict(base, **warm)
    run_process([script, "pose", glb, "--clip", clip, "--method", "lbs", "-o", ref], warm_env, work / "log")
    with np.load(ref) as z:
        frames, vertices = z["positions"].shape[:2]
    ch.update(frames=int(frames), vertices=int(vertices))
    blender_stages = None

    def command(who, method, output, out):
        if who == "blender":
            return [bpy_python, HERE / "blender_bake.py", glb, clip, FPS, frames, out]
        if who == "floor":
            return [py, "-c", FLOOR]
        return [script, "pose", glb, "--clip", clip, "--method", method, "-o", out]

    players = contestants(methods, outputs, bpy_python is not None)
    for who, method, output in players:           # warm-up: fills the warm caches
        out = work / f"warmup-{who}-{method}.{output}"
        r = run_process(command(who, method, output, out), warm_env, work / "log")
        if who == "blender":
            blender_stages = json.loads(r["stdout"].strip().splitlines()[-1])
            doc["agreement"][name] = agreement(ref, out)
            if log:
                a = doc["agreement"][name]
                log(f"e2e {name}: Blender vs nrpose lbs: max {a.get('max_rel', float('nan')):.2e} of the diagonal "
                    f"(frame 0 {a.get('frame0_max_rel', float('nan')):.2e})")
    samples = {(p, mode): [] for p in players for mode in MODES}
    for r_i in range(rounds):
        order = players[r_i % len(players):] + players[:r_i % len(players)]
        for mode in (MODES if r_i % 2 == 0 else MODES[::-1]):
            for p in order:
                who, method, output = p
                out = work / f"run.{output}"
                if mode == "cold":
                    fresh = work / f"cold-{r_i}"
                    env = dict(base, NRPOSE_CACHE_DIR=str(fresh / "nrpose"), POCL_CACHE_DIR=str(fresh / "pocl"))
                    evicted = evict(glb)
                else:
                    env, evicted = warm_env, None
                    read_through(glb)
                r = run_process(command(who, method, output, out), env, work / "log")
                r["evicted"] = evicted
                samples[(p, mode)].append(r)
                if mode == "cold":
                    shutil.rmtree(work / f"cold-{r_i}", ignore_errors=True)
                out.unlink(missing_ok=True)
    rows = []
    for (p, mode), rs in samples.items():
        who, method, output = p
        rss = [r["peak_rss_mib"] for r in rs]
        rows.append({"character": name, "source": ch["source"], "clip": clip, "frames": ch["frames"],
                     "vertices": ch["vertices"], "who": who, "method": method, "output": output, "mode": mode,
                     "wall_ms": common.stats([r["wall_s"] for r in rs]), "wall_s_rounds": [r["wall_s"] for r in rs],
                     "cpu_ms": common.stats([r["cpu_s"] for r in rs]),
                     "peak_rss_mib": {"median": float(np.median(rss)), "max": float(max(rss))},
                     "evicted_input": all(r["evicted"] for r in rs) if mode == "cold" else None})
        if who == "blender" and blender_stages:
            rows[-1]["blender_stages_s"] = blender_stages
    steal, load1 = common.steal_percent(cpu0, common.cpu_times()), common.load()
    for row in rows:
        row.update(cpu_steal_percent=steal, load_start=load0, load_end=load1)
    for method in methods:
        args = ["pose", str(glb), "--clip", clip, "--method", method, "-o", str(work / "probe.npz")]
        b = breakdown(py, args, warm_env, work, BREAKDOWN_RUNS if rounds > 1 else 1)
        b.update(character=name, method=method, output="npz", mode="warm")
        doc["breakdown"].append(b)
        if log:
            log(f"e2e {name} {method} stages: imports {b['imports_s']:.3f} s; " + ", ".join(
                f"{s} {v:.3f}" for s, v in b["stages_s"].items()) + f"; other {b['other_s']:.3f}")
    if log:
        for row in rows:
            log(f"e2e {name:9s} {row['who']:7s} {row['method'] or '':5s} {row['output']} {row['mode']}: "
                f"{row['wall_ms']['median']:7.0f} ms (p10 {row['wall_ms']['p10']:.0f}, p90 {row['wall_ms']['p90']:.0f}), "
                f"peak RSS {row['peak_rss_mib']['median']:.0f} MiB")
    return rows


def _ratios(rows: list[dict]) -> None:
    """vs_blender on every nrpose row of Blender's job (into .npz): Blender's median wall / the
    row's, and per round (None on the .glb rows: Blender writes no such file here)."""
    for row in rows:
        bl = next((r for r in rows if r["who"] == "blender" and r["character"] == row["character"]
                   and r["mode"] == row["mode"] and r["output"] == row["output"]), None)
        if row["who"] != "nrpose" or bl is None:
            row["vs_blender"] = None
            continue
        paired = np.array(bl["wall_s_rounds"]) / np.array(row["wall_s_rounds"])
        row["vs_blender"] = {"ratio": bl["wall_ms"]["median"] / row["wall_ms"]["median"],
                             "paired": common.quantiles(paired),
                             "rss_ratio": row["peak_rss_mib"]["median"] / bl["peak_rss_mib"]["median"]}


def floors(rows: list[dict], mode: str, target: float) -> dict:
    """Per character (Mannequin, Ely): the OpenCL floor's median wall in ``mode`` (:data:`FLOOR`)
    beside the budget the target leaves a whole job (Blender's median / ``target``), ms."""
    out = {}
    for name in ("mannequin", "ely"):
        row = {r["who"]: r for r in rows if r["character"] == name and r["mode"] == mode}
        if "floor" in row and "blender" in row:
            out[name] = {"floor_ms": row["floor"]["wall_ms"]["median"],
                         "budget_ms": row["blender"]["wall_ms"]["median"] / target}
    return out


def targets(doc: dict) -> list[dict]:
    """The issue's targets against this run's figures (``meaningful`` false in quick mode)."""
    q, rows, out = doc["options"]["quick"], doc["rows"], []

    def pick(method, mode):
        return [r for r in rows if r["who"] == "nrpose" and r["method"] == method and r["mode"] == mode
                and r["output"] == "npz" and r["character"] in ("mannequin", "ely") and r["vs_blender"]]

    for label, method, mode, key in (("NR-MLS warm", "nrmls", "warm", "nrmls_warm_vs_blender_min"),
                                     ("LBS warm", "lbs", "warm", "lbs_warm_vs_blender_min"),
                                     ("NR-MLS cold", "nrmls", "cold", "cold_vs_blender_min")):
        rs = pick(method, mode)
        worst = min(rs, key=lambda r: r["vs_blender"]["ratio"]) if rs else None
        out.append({"name": f"{label} whole process -> .npz >= {TARGETS[key]:g}x faster than Blender "
                            "(Mannequin, Ely)", "target": TARGETS[key],
                    "measured": worst["vs_blender"]["ratio"] if worst else None,
                    "where": worst["character"] if worst else None,
                    "met": bool(worst and worst["vs_blender"]["ratio"] >= TARGETS[key]), "meaningful": not q,
                    "floor": floors(rows, mode, TARGETS[key]) if mode == "cold" else {}})
    b = doc["breakdown"]
    worst = max(b, key=lambda r: r["imports_s"]) if b else None
    out.append({"name": "imports of nrpose pose <= 0.25 s", "target": TARGETS["imports_s_max"],
                "measured": worst["imports_s"] if worst else None,
                "where": f"{worst['character']}/{worst['method']} (worst)" if worst else None,
                "met": bool(worst and worst["imports_s"] <= TARGETS["imports_s_max"]), "meaningful": not q})
    man = [r for r in b if r["character"] == "mannequin"]
    load = min(r["stages_s"]["load"] for r in man) if man else None
    out.append({"name": "glTF load of Mannequin <= 30 ms (timed load stage, best of the methods' runs)",
                "target": TARGETS["gltf_load_mannequin_s_max"], "measured": load, "where": "mannequin",
                "met": bool(load is not None and load <= TARGETS["gltf_load_mannequin_s_max"]), "meaningful": not q})
    rs = [r for r in rows if r["vs_blender"]]
    worst = max(rs, key=lambda r: r["vs_blender"]["rss_ratio"]) if rs else None
    out.append({"name": "peak RSS <= Blender's on the same job (every row)", "target": 1.0,
                "measured": worst["vs_blender"]["rss_ratio"] if worst else None,
                "where": f"{worst['character']}/{worst['method']}/{worst['output']}/{worst['mode']} (worst)"
                         if worst else None,
                "met": bool(worst and worst["vs_blender"]["rss_ratio"] <= 1.0), "meaningful": not q})
    return out


# --------------------------------------------------------------------------- output

def table(doc: dict) -> list[str]:
    """The record as text: per character, mode and contestant the wall median, ratio, RSS."""
    lines = [f"{'character':10s} {'mode':4s} {'job':14s} {'wall ms':>8s} {'p10':>6s} {'p90':>6s} "
             f"{'x Blender':>9s} {'RSS MiB':>8s}"]
    for r in sorted(doc["rows"], key=lambda r: (r["character"], r["mode"], r["who"] != "blender",
                                                METHODS.index(r["method"]) if r["method"] else -1,
                                                r["output"] or "")):
        job = r["who"] if r["who"] != "nrpose" else f"{r['method']}->{r['output']}"
        vs = f"{r['vs_blender']['ratio']:9.2f}" if r.get("vs_blender") else f"{'':9s}"
        lines.append(f"{r['character']:10s} {r['mode']:4s} {job:14s} {r['wall_ms']['median']:8.0f} "
                     f"{r['wall_ms']['p10']:6.0f} {r['wall_ms']['p90']:6.0f} {vs} {r['peak_rss_mib']['median']:8.0f}")
    for t in doc["targets"]:
        m = t["measured"]
        lines.append(f"target {t['name']}: " + (f"{m:.4g} ({t['where']}) -> {'met' if t['met'] else 'NOT met'}"
                                                 f"{'' if t['meaningful'] else ' (quick: not meaningful)'}"
                                                 if m is not None else "not measured"))
        for name, f in t.get("floor", {}).items():
            lines.append(f"  {name}: the OpenCL floor {f['floor_ms']:.0f} ms against a budget of "
                         f"{f['budget_ms']:.0f} ms for the whole job")
    return lines


def write_json(doc: dict, path) -> None:
    """``doc`` to ``path`` atomically (a sibling temporary file, then rename)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=1, default=str) + "\n")
    os.replace(tmp, path)


def main(argv=None, prog: str | None = None) -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5, help="rounds (default 5)")
    ap.add_argument("--quick", action="store_true",
                    help="Fox, nrmls, one round, no Blender (smoke test: timings mean nothing)")
    ap.add_argument("--no-blender", action="store_true", help="skip the Blender anchor")
    ap.add_argument("--characters", default=",".join(c[0] for c in CHARACTERS),
                    help="comma-separated subset of " + ", ".join(c[0] for c in CHARACTERS))
    ap.add_argument("--outputs", default=",".join(OUTPUTS),
                    help="comma-separated output kinds to time (default npz,glb; the targets are on npz)")
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="shared data folder (default ../shared/data)")
    ap.add_argument("--json", default=str(DEFAULT_JSON), help="output JSON (default bench/results/e2e.json)")
    a = ap.parse_args(argv)
    names = [n.strip() for n in a.characters.split(",") if n.strip()]
    outputs = tuple(o.strip() for o in a.outputs.split(",") if o.strip())
    bad = [n for n in names if n not in [c[0] for c in CHARACTERS]] + [o for o in outputs if o not in OUTPUTS]
    if bad or not names or not outputs or a.repeat < 1:
        print(f"e2e: unknown character or output {bad[0]!r}" if bad else
              "e2e: need a character, an output and --repeat >= 1", file=sys.stderr)
        return 2
    doc = run(a.repeat, a.quick, a.data, None if a.quick else names, not a.no_blender,
              log=lambda s: print(s, flush=True), outputs=outputs)
    write_json(doc, a.json)
    for line in table(doc):
        print(line)
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
