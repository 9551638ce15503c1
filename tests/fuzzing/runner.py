"""Run fuzz cases against ``nrpose.cli.main`` and check the CLI's contract.

Each case runs in a child forked from a process that has imported nrpose (no OpenCL
context is made before the fork; a child that asks for the opencl backend makes its
own). The child gets a directory of its own (``in/`` inputs, ``out/`` outputs, special
paths), an address-space limit (:data:`MEMORY_LIMIT`, ``RLIMIT_AS``), optionally a
file-size limit (a full disk) or a closed stdout, and when the fuzzer runs as root it
drops the capability to override file permissions so that read-only folders are read-only. Its stdout and stderr
are captured through pipes. A hang is a child that uses more than :data:`TIME_LIMIT` seconds
of CPU (``RLIMIT_CPU``: SIGXCPU) or is still running after :data:`WALL_LIMIT` seconds (the
parent kills it: a deadlock uses no CPU); CPU time, not wall time, so that a slow but finite
case does not count as a hang on a loaded machine.

The contract (``CLASSES`` are the ways to break it):

* exit 0 and every output valid: readable by the project's own readers (meshes, BVH,
  glTF), finite (``.npz``), a PNG signature; at most one line on stderr;
  no temporary file left. An option given as nan/inf is never valid: exit 0 with one is
  ``bad-option-accepted``;
* or exit 2 with exactly one line on stderr and the case's directory exactly as before
  (no new, removed or changed file or folder);
* ``bake`` also may exit 1 (some jobs failed, the others done): then its stderr is one
  ``nrpose: bake: jobs[I] (OUTPUT): ...`` line per failed job, and the manifest, the
  ``--summary`` and the final stdout line agree with them (done outputs listed and valid,
  failed ones not listed). A job that fails with the worker's "internal error" is a
  ``traceback``, one whose error says "please report" is ``nonfinite``.

:func:`run_case` returns an :class:`Outcome`; :class:`Collector` counts outcomes,
de-duplicates violations by (command, class, where) and saves one reproducer per
distinct defect (``case.json`` + the input files; replay it with
``python -m tests.fuzzing.runner REPRO_DIR``).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import math
import os
import pkgutil
import re
import resource
import select
import shutil
import signal
import stat
import sys
import tempfile
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

from nrpose.cli import EXIT_PIPE

from .cases import PATH_FLAGS, Case

__all__ = ["Outcome", "Runner", "Collector", "run_case", "CLASSES", "TIME_LIMIT", "WALL_LIMIT", "MEMORY_LIMIT"]

TIME_LIMIT = 20.0
#: seconds of wall time after which a child is killed as hung whatever its CPU time
WALL_LIMIT = 60.0
MEMORY_LIMIT = 3 << 30
CAPTURE_LIMIT = 1 << 20

#: contract violations, in the order a case's primary class is chosen
CLASSES = ("crash", "hang", "memory", "traceback", "invalid-output", "bad-option-accepted", "leftover",
           "broken-pipe", "nonfinite", "multiline-stderr", "bad-exit")
#: outcomes that keep the contract (``partial``: a bake's exit 1, some jobs failed, accounted for)
GOOD = ("accepted", "rejected", "partial")


@dataclass
class Outcome:
    index: int
    command: str
    template: str
    input_kind: str
    mutation: str
    outcome: str                       # a CLASSES entry or a GOOD one
    classes: list = field(default_factory=list)
    exit: int | None = None            # exit status, or -signal
    seconds: float = 0.0
    stderr: str = ""
    where: str = ""                    # last traceback frame / signal / message head
    nrpose_frame: str = ""             # last traceback frame inside nrpose
    problems: list = field(default_factory=list)

    @property
    def key(self) -> str:
        return f"{self.command}|{self.outcome}|{self.where}"


def preload() -> None:
    """Import every nrpose module (and matplotlib's Agg) so that forked children start warm."""
    import matplotlib
    matplotlib.use("Agg")
    import nrpose
    for mod in pkgutil.walk_packages(nrpose.__path__, "nrpose."):
        if mod.name.endswith("__main__"):
            continue
        importlib.import_module(mod.name)


# --------------------------------------------------------------------------- case set-up

def _snapshot(root: Path) -> dict:
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            kind = stat.S_IFMT(st.st_mode)
            # a folder's own size and time change when a temporary file comes and goes
            out[str(p.relative_to(root))] = (kind, 0, 0) if kind == stat.S_IFDIR else (kind, st.st_size, st.st_mtime_ns)
    return out


def prepare(case, root: Path) -> Path:
    """The case's directory under ``root``: inputs, ``out/``, special paths."""
    d = root / f"c{case.index}"
    if d.exists():
        _rmtree(d)
    (d / "out").mkdir(parents=True)
    for rel, data in case.files.items():
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    for rel, kind in case.specials.items():
        p = d / rel
        if kind == "readonly":
            p.parent.mkdir(parents=True, exist_ok=True)
            continue
        if p.exists() or p.is_symlink():
            continue
        p.parent.mkdir(parents=True, exist_ok=True)
        if kind == "dir":
            p.mkdir()
        elif kind == "fifo":
            os.mkfifo(p)
    for rel, kind in case.specials.items():
        if kind == "readonly":
            (d / rel).parent.chmod(0o555)
    return d


def drop_dac_override() -> None:
    """Clear CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH (root then obeys permission bits, so a
    read-only folder is read-only) from this process's capabilities (Linux capset)."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    header = (ctypes.c_uint32 * 2)(0x20080522, 0)   # _LINUX_CAPABILITY_VERSION_3, this process
    data = (ctypes.c_uint32 * 6)()                   # 2 x (effective, permitted, inheritable)
    if libc.syscall(125, header, data) != 0:         # capget
        raise OSError(ctypes.get_errno(), "capget")
    mask = ~((1 << 1) | (1 << 2)) & 0xFFFFFFFF
    data[0] &= mask
    data[1] &= mask
    if libc.syscall(126, header, data) != 0:         # capset
        raise OSError(ctypes.get_errno(), "capset")


def can_drop() -> bool:
    """True when running as root on x86-64 Linux, where :func:`drop_dac_override` applies."""
    return os.geteuid() == 0 and sys.platform == "linux" and os.uname().machine == "x86_64"


def _rmtree(path: Path) -> None:
    for dirpath, dirnames, _ in os.walk(path):
        for n in dirnames:
            _writable(Path(dirpath) / n)
    shutil.rmtree(path, ignore_errors=True)


def _writable(p: Path) -> None:
    try:
        if not p.is_symlink():
            p.chmod(0o755)
    except OSError:
        pass


# --------------------------------------------------------------------------- output validation

def _value(argv, flag):
    """The value of ``flag``'s last occurrence (the one argparse keeps), None without one."""
    at = [i for i, a in enumerate(argv[:-1]) if a == flag]
    return argv[at[-1] + 1] if at else None


def _check_glb(path: Path, problems: list) -> None:
    """Structural check of a written .glb: container lengths, views inside buffers, accessors inside views."""
    import struct
    data = path.read_bytes()
    if len(data) < 20 or data[:4] != b"glTF" or struct.unpack_from("<I", data, 8)[0] != len(data):
        problems.append(f"{path.name}: bad GLB container")
        return
    size = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + size])
    blob_len = struct.unpack_from("<I", data, 20 + size)[0] if len(data) >= 28 + size else 0
    buffers = doc.get("buffers", [])
    for i, b in enumerate(buffers):
        if "uri" not in b and b.get("byteLength", 0) > blob_len:
            problems.append(f"{path.name}: buffer {i} byteLength {b.get('byteLength')} > BIN {blob_len}")
    for i, v in enumerate(doc.get("bufferViews", [])):
        b = buffers[v["buffer"]] if 0 <= v.get("buffer", -1) < len(buffers) else None
        if b is None or v.get("byteOffset", 0) + v["byteLength"] > b.get("byteLength", 0):
            problems.append(f"{path.name}: bufferView {i} runs past its buffer")
    sizes = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
    widths = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
    views = doc.get("bufferViews", [])
    for i, a in enumerate(doc.get("accessors", [])):
        if "bufferView" not in a:
            continue
        v = views[a["bufferView"]] if 0 <= a["bufferView"] < len(views) else None
        item = sizes.get(a.get("componentType"), 0) * widths.get(a.get("type"), 0)
        if v is None or not item:
            problems.append(f"{path.name}: accessor {i} has a bad view or type")
            continue
        stride = v.get("byteStride") or item
        if a["count"] and a.get("byteOffset", 0) + stride * (a["count"] - 1) + item > v["byteLength"]:
            problems.append(f"{path.name}: accessor {i} runs past its bufferView")


def _report_json(path, problems: list) -> None:
    """A JSON report (fit-skin --report, bake --summary): parses with finite numbers only."""
    def constant(name):
        raise ValueError(f"non-finite number {name}")
    try:
        json.loads(Path(path).read_text(), parse_constant=constant)
    except (OSError, ValueError) as exc:
        problems.append(f"{path}: not a valid report ({type(exc).__name__}: {str(exc)[:200]})")


def _validate_bake(argv: list, code: int, stdout: str, stderr: str, problems: list, read_output) -> None:
    """The outputs of a bake that exited 0 or 1 (module docstring)."""
    from nrpose.cli.bake.jobs import load_jobs
    from nrpose.cli.bake.manifest import digest
    from nrpose.errors import NrposeError

    outdir = Path(_value(argv, "-o") or _value(argv, "--output"))
    try:
        jobs = load_jobs(argv[1])
    except NrposeError as exc:
        problems.append(f"the JOBS file of a run that exited {code} does not load ({exc})")
        return
    failed = [ln for ln in stderr.splitlines() if ln.startswith("nrpose: bake: jobs[")]
    others = [ln for ln in stderr.splitlines() if ln.strip() and ln not in failed]
    if code == 0 and (failed or len(others) > 1):
        problems.append(f"exit 0 with {len(failed)} failed-job line(s) and {len(others)} other line(s) on stderr")
    if code == 1 and (not failed or others):
        problems.append(f"exit 1 with {len(failed)} failed-job line(s) and other stderr lines {others[:2]}")
    failed_names = {ln.split("(", 1)[1].split("):", 1)[0] for ln in failed if "(" in ln}
    m = re.search(r"^bake: (\d+) jobs \((\d+) done, (\d+) failed, (\d+) already done\)", stdout, re.M)
    if not m:
        problems.append("no final 'bake: N jobs (...)' line on stdout")
    elif (int(m[1]), int(m[3])) != (len(jobs), len(failed)):
        problems.append(f"final line {m[0]!r}: {len(jobs)} jobs and {len(failed)} failed-job lines expected")
    try:
        listed = json.loads((outdir / "manifest.json").read_text())["outputs"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        problems.append(f"{outdir}/manifest.json unreadable ({type(exc).__name__})")
        return
    for leftover in (".bake-tmp",):
        if (outdir / leftover).exists():
            problems.append(f"{outdir}/{leftover} left behind")
    for job in jobs:
        entry, out = listed.get(job.output), outdir / job.output
        if job.output in failed_names:
            if entry is not None and entry.get("spec") == job.spec:
                problems.append(f"{job.output}: failed but in the manifest for these options")
            continue
        if not isinstance(entry, dict) or entry.get("spec") != job.spec:
            problems.append(f"{job.output}: done but not in the manifest for these options")
        elif not out.exists() or digest(out) != (entry["size"], entry["sha256"]):
            problems.append(f"{job.output}: the file does not match its manifest entry")
        else:
            read_output(str(out), frames_output_kind(job.output))
    summary = _value(argv, "--summary")
    if summary:
        try:
            doc = json.loads(Path(summary).read_text())
            statuses = {r["output"]: r["status"] for r in doc["records"]}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            problems.append(f"{summary}: unreadable summary ({type(exc).__name__})")
            return
        bad = [o for o, st in statuses.items() if (st == "failed") != (o in failed_names)]
        if bad or doc.get("failed") != len(failed):
            problems.append(f"{summary}: statuses disagree with stderr on {bad[:3]} (failed {doc.get('failed')})")


def frames_output_kind(name: str) -> str:
    suffix = Path(name).suffix.lower()
    return suffix[1:] if suffix in (".npz", ".glb") else "dir"


def validate(argv: list, code: int = 0, stdout: str = "", stderr: str = "") -> list[str]:
    """Problems with the outputs of a run that exited 0 (or a bake that exited 1; its
    ``stdout`` and ``stderr`` so far are checked against its manifest); empty when all are valid."""
    import numpy as np

    problems: list[str] = []
    command = argv[0]
    out, png = _value(argv, "-o") or _value(argv, "--output"), _value(argv, "--png")

    def read(fn, p):
        try:
            fn(p)
        except Exception as exc:  # noqa: BLE001 - any failure to read back is the finding
            problems.append(f"{p}: not readable back ({type(exc).__name__}: {str(exc)[:200]})")

    from nrpose.io import load_character
    from nrpose.io.bvh_read import read_bvh
    from nrpose.io.meshes import read_geometry

    def read_mesh(p):
        g = read_geometry(p)
        if not len(g.vertices) or not np.isfinite(g.vertices).all():
            raise ValueError("empty or non-finite vertices")

    def read_npz(p):
        with np.load(p, allow_pickle=False) as z:
            for k in z.files:
                a = z[k]
                if a.dtype.kind == "f" and not np.isfinite(a).all():
                    raise ValueError(f"array {k} not finite")

    def read_bvh_file(p):
        read_bvh(p)

    def read_glb(p):
        _check_glb(Path(p), problems)
        if command in ("retarget", "fit-skin"):
            tuple(load_character(p).clips)      # clips are decoded when used: read them all

    def read_png(p):
        if Path(p).read_bytes()[:8] != b"\x89PNG\r\n\x1a\n":
            raise ValueError("not a PNG")

    def read_dir(p):
        frames = sorted(Path(p).glob("frame_*"))
        if not frames:
            raise ValueError("no frame files")
        for f in frames:
            read_mesh(f)

    if command == "info":   # its stdout is checked by the parent
        return problems
    if command == "bake":
        readers = {"npz": read_npz, "glb": read_glb, "dir": read_dir}
        _validate_bake(argv, code, stdout, stderr, problems, lambda p, kind: read(readers[kind], p))
        return problems
    if command == "demo":
        d = Path(_value(argv, "--out") or "out")
        for name, fn in (("walk.npz", read_npz), ("walk.glb", read_glb), ("walk.png", read_png),
                         ("box_before.png", read_png), ("box_after.png", read_png), ("box_twist.ply", read_mesh)):
            read(fn, str(d / name))
        return problems
    if command == "fit-skin" and _value(argv, "--report"):
        _report_json(_value(argv, "--report"), problems)
    if out is not None:
        suffix = Path(out).suffix.lower()
        if command == "deform":
            read(read_mesh, out)
        elif suffix == ".npz":
            read(read_npz, out)
        elif suffix == ".glb":
            read(read_glb, out)
        elif suffix == ".bvh":
            read(read_bvh_file, out)
        elif command == "pose" and suffix == "":
            read(read_dir, out)
        else:
            problems.append(f"{out}: exit 0 with an output of unknown kind")
    elif command != "retarget" or "--show-map" not in argv:
        problems.append("exit 0 without an output")
    if png:
        read(read_png, png)
    return problems


# --------------------------------------------------------------------------- one case

class _Recorder:
    """A text stream that keeps what is written to it (the first :data:`CAPTURE_LIMIT`
    characters) and passes it on to ``stream``."""

    def __init__(self, stream):
        self.stream, self.parts, self.size = stream, [], 0

    def write(self, text):
        if self.size < CAPTURE_LIMIT:
            self.parts.append(text)
            self.size += len(text)
        return self.stream.write(text)

    def text(self) -> str:
        return "".join(self.parts)

    def __getattr__(self, name):
        return getattr(self.stream, name)


def _child(case, casedir: Path, env: dict, drop: bool, w_out: int, w_err: int, w_res: int,
           time_limit: float) -> None:
    code = 1
    try:
        os.setpgid(0, 0)
        os.chdir(casedir)
        if case.broken_pipe:
            r, w = os.pipe()
            os.close(r)
            os.dup2(w, 1)
        else:
            os.dup2(w_out, 1)
        os.dup2(w_err, 2)
        # the parent's sys.stdout/stderr may be a test runner's capture objects
        sys.stdout = _Recorder(open(1, "w", encoding="utf-8", errors="backslashreplace", closefd=False))
        sys.stderr = _Recorder(open(2, "w", encoding="utf-8", errors="backslashreplace", buffering=1,
                                    closefd=False))
        os.environ.update(env)
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        cpu = int(math.ceil(time_limit))
        resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))
        if case.fsize is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (case.fsize, case.fsize))
        if drop:
            drop_dac_override()
        from nrpose.cli import main
        code = main(list(case.argv))
        try:
            sys.stdout.flush()
        except BrokenPipeError:   # what the interpreter does when stdout fails at exit
            print("Exception ignored while flushing sys.stdout:\nBrokenPipeError: [Errno 32] Broken pipe",
                  file=sys.stderr)
            code = 120
        if code == 0 or (case.command == "bake" and code == 1):
            problems = validate(list(case.argv), code, sys.stdout.text(), sys.stderr.text())
            os.write(w_res, json.dumps(problems).encode())
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException:  # noqa: BLE001 - what Python would print for an uncaught exception
        try:
            traceback.print_exc()
        except BaseException:  # noqa: BLE001
            pass
        code = 1
    finally:
        for s in (sys.stdout, sys.stderr):
            try:
                s.flush()
            except BaseException:  # noqa: BLE001 - a closed stdout
                pass
        os._exit(code if isinstance(code, int) else 1)


def _read_all(fds: dict, deadline: float) -> tuple[dict, bool]:
    """Drain the pipes until all close or ``deadline``; True when the deadline passed."""
    bufs = {fd: bytearray() for fd in fds}
    open_fds = set(fds)
    while open_fds:
        left = deadline - time.monotonic()
        if left <= 0:
            return bufs, True
        ready, _, _ = select.select(list(open_fds), [], [], min(left, 1.0))
        for fd in ready:
            chunk = os.read(fd, 65536)
            if not chunk:
                open_fds.discard(fd)
            elif len(bufs[fd]) < CAPTURE_LIMIT:
                bufs[fd] += chunk
    return bufs, False


def run_case(case, root: Path, env: dict, drop: bool, time_limit: float = TIME_LIMIT) -> tuple[Outcome, Path]:
    """Run one case; returns its outcome and its directory (the caller removes it)."""
    casedir = prepare(case, root)
    before = _snapshot(casedir)
    pipes = [os.pipe() for _ in range(3)]
    sys.stdout.flush()
    sys.stderr.flush()
    t0 = time.monotonic()
    pid = os.fork()
    if pid == 0:
        for r, _ in pipes:
            os.close(r)
        _child(case, casedir, env, drop, pipes[0][1], pipes[1][1], pipes[2][1], time_limit)
    for _, w in pipes:
        os.close(w)
    fds = {pipes[0][0]: "out", pipes[1][0]: "err", pipes[2][0]: "res"}
    bufs, timed_out = _read_all(fds, t0 + max(WALL_LIMIT, 3 * time_limit))
    if timed_out:
        try:
            os.killpg(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    _, status, usage = os.wait4(pid, 0)
    # RLIMIT_CPU ended it (SIGXCPU at the soft limit, SIGKILL at the hard one)
    timed_out = (timed_out or os.waitstatus_to_exitcode(status) == -signal.SIGXCPU
                 or usage.ru_utime + usage.ru_stime >= time_limit)
    seconds = time.monotonic() - t0
    for fd in fds:
        os.close(fd)
    out = bytes(bufs[pipes[0][0]]).decode("utf-8", "replace")
    err = bytes(bufs[pipes[1][0]]).decode("utf-8", "replace")
    res = bytes(bufs[pipes[2][0]]).decode("utf-8", "replace")
    code = os.waitstatus_to_exitcode(status)
    after = _snapshot(casedir)
    o = classify(case, code, out, err, res, timed_out, before, after)
    o.seconds = round(seconds, 3)
    return o, casedir


NAN_VALUES = {"nan", "NaN", "inf", "-inf"}
FRAME = re.compile(r'File "([^"]+)", line (\d+), in (\S+)')


def _short(path: str) -> str:
    i = path.rfind("nrpose/")
    return path[i:] if i >= 0 else path.rsplit("/", 2)[-1] if "site-packages" in path else path


def _message_head(err: str) -> str:
    line = err.strip().splitlines()[0] if err.strip() else ""
    line = re.sub(r"(?:in|out|ro|nodir)/\S*", "P", line)
    line = re.sub(r"\d+(\.\d+)?(e[-+]?\d+)?", "#", line)
    line = re.sub(r"'[^']*'", "'S'", line)
    return line[:70]


def classify(case, code, out, err, res, timed_out, before, after) -> Outcome:
    o = Outcome(case.index, case.command, case.template, case.input_kind, case.mutation, "", exit=code,
                stderr=err[-4000:])
    lines = err.splitlines()
    changed = sorted(set(after) ^ set(before)) + sorted(k for k in before if k in after and after[k] != before[k])
    frames = FRAME.findall(err)
    if frames:
        f = frames[-1]
        o.where = f"{_short(f[0])}:{f[2]}"
        nr = [x for x in frames if "nrpose" in x[0] and "tests/fuzzing" not in x[0]]
        if nr:
            o.nrpose_frame = f"{_short(nr[-1][0])}:{nr[-1][1]}:{nr[-1][2]}"
        exc = lines[-1].split(":")[0] if lines else ""
        o.where = f"{exc} @ {o.nrpose_frame.rsplit(':', 2)[0] + ':' + nr[-1][2] if nr else o.where}"
    classes = []
    if timed_out:
        classes.append("hang")
        o.where = o.where or case.template
    elif code < 0:
        memory = "bad_alloc" in err or "MemoryError" in err
        classes.append("memory" if memory else "crash")
        o.where = o.where or f"signal {signal.Signals(-code).name} {case.template}"
    elif "Broken pipe" in err:
        classes.append("broken-pipe")
        o.where = o.where or _message_head(err)
    elif code == 1 and case.command == "bake" and "Traceback" not in err:
        # some jobs failed: each a line of its own, the manifest and summary saying so
        o.problems = json.loads(res) if res else ["no validation result"]
        if "internal error" in err:
            classes.append("traceback")
        elif "please report" in err:
            classes.append("nonfinite")
        if o.problems:
            classes.append("invalid-output")
        line = next((ln for ln in lines if "internal error" in ln or "please report" in ln),
                    o.problems[0] if o.problems else "")
        o.where = _message_head(re.sub(r"^nrpose: bake: jobs\[\d+\] \(.*?\): ", "bake job: ", line))
    elif code == 1 and "Traceback" in err:
        exc_line = lines[-1] if lines else ""
        classes.append("memory" if "MemoryError" in exc_line.split(":")[0] else "traceback")
    elif code == 0:
        try:
            o.problems = json.loads(res) if res else ["no validation result"]
        except ValueError:
            o.problems = ["validation result unreadable"]
        if case.command == "info" and not case.broken_pipe and not out.strip():
            o.problems.append("info printed nothing")
        if o.problems:
            classes.append("invalid-output")
            o.where = o.where or _message_head(o.problems[0])
        # a NaN word as the value of a number or name option (a path may be named "inf")
        if case.input_kind == "option" and any(v in NAN_VALUES and flag not in PATH_FLAGS
                                               for flag, v in zip(case.argv, case.argv[1:])):
            classes.append("bad-option-accepted")
            o.where = o.where or case.mutation.split(" ")[0]
        temps = [k for k in set(after) - set(before) if Path(k).name.startswith(".nrpose-")]
        if temps:
            classes.append("leftover")
            o.problems.append(f"temporary files left: {temps[:3]}")
    elif code == EXIT_PIPE and case.broken_pipe and not err.strip():
        pass    # the quiet end of a command whose stdout reader went away
    elif code == 2:
        if "bad_alloc" in err or "MemoryError" in err:
            classes.append("memory")
        if changed:
            classes.append("leftover")
            o.problems.append(f"left behind / changed: {changed[:5]}")
        if "please report" in err:
            classes.append("nonfinite")
        o.where = o.where or _message_head(err)
    else:
        classes.append("bad-exit")
    # exit 2: exactly one line; exit 0: at most one (a warning)
    if code in (0, 2) and "Traceback" not in err and (len(lines) > 1 or (code == 2 and not lines)):
        classes.append("multiline-stderr")
        o.where = (o.where if code == 0 else "") or _message_head(err) or "empty stderr"
    if code not in (0, 2) and changed and "leftover" not in classes and case.command != "bake":
        o.problems.append(f"left behind / changed: {changed[:5]}")
    classes = sorted(set(classes), key=CLASSES.index)
    o.classes = classes
    o.outcome = classes[0] if classes else ("accepted" if code in (0, EXIT_PIPE) else
                                            "partial" if code == 1 and case.command == "bake" else "rejected")
    if o.outcome in ("leftover", "invalid-output", "bad-option-accepted", "broken-pipe", "nonfinite"):
        o.where = f"{case.template}: {o.where or _message_head(err)}"
    return o


# --------------------------------------------------------------------------- a whole run

class Runner:
    """Runs cases one at a time under a private temporary root (see the module docstring)."""

    def __init__(self, root: Path | None = None, time_limit: float = TIME_LIMIT):
        preload()
        self.root = Path(root or tempfile.mkdtemp(prefix="nrpose-fuzz-"))
        self.root.mkdir(parents=True, exist_ok=True)
        self.drop = can_drop()
        self.time_limit = time_limit
        home = self.root / "home"
        for sub in ("cache", "mpl"):
            (home / sub).mkdir(parents=True, exist_ok=True)
        # PoCL keeps its kernel cache where it is (a fresh one would recompile per run)
        self.env = {"NRPOSE_CACHE_DIR": str(home / "cache"), "MPLCONFIGDIR": str(home / "mpl")}
        self.cases = self.root / "cases"
        self.cases.mkdir(exist_ok=True)

    def run(self, case) -> tuple[Outcome, Path]:
        return run_case(case, self.cases, self.env, self.drop, self.time_limit)

    def close(self) -> None:
        _rmtree(self.root)


class Collector:
    """Totals by command × input kind × outcome, distinct defects, one reproducer each."""

    def __init__(self, repro_dir: Path | None = None):
        self.repro_dir = Path(repro_dir) if repro_dir else None
        self.totals: dict = {}
        self.defects: dict = {}
        self.count = 0
        self.violations = 0

    def add(self, o: Outcome, case=None) -> None:
        self.count += 1
        t = self.totals.setdefault(o.command, {}).setdefault(o.input_kind, {})
        t[o.outcome] = t.get(o.outcome, 0) + 1
        if o.outcome in GOOD:
            return
        self.violations += 1
        d = self.defects.get(o.key)
        if d is not None:
            d["count"] += 1
            return
        d = {"key": o.key, "count": 1, "command": o.command, "class": o.outcome, "classes": o.classes,
             "where": o.where, "nrpose_frame": o.nrpose_frame, "template": o.template,
             "input_kind": o.input_kind, "mutation": o.mutation, "exit": o.exit, "argv": case.argv if case else [],
             "stderr_tail": o.stderr.strip().splitlines()[-3:] if o.stderr.strip() else [], "problems": o.problems}
        if self.repro_dir and case is not None:
            d["repro"] = str(save_repro(self.repro_dir, case, o))
        self.defects[o.key] = d

    def summary(self) -> dict:
        return {"cases": self.count, "violations": self.violations, "distinct": len(self.defects),
                "totals": self.totals,
                "defects": sorted(self.defects.values(), key=lambda d: (CLASSES.index(d["class"]), -d["count"]))}


def save_repro(repro_dir: Path, case, o: Outcome) -> Path:
    h = hashlib.sha1(o.key.encode()).hexdigest()[:8]
    d = repro_dir / f"{o.outcome}-{case.command}-{h}"
    try:
        d.mkdir(parents=True)
    except FileExistsError:   # this defect's reproducer is saved already
        return d
    for rel, data in case.files.items():
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    meta = {k: v for k, v in asdict(case).items() if k != "files"}
    meta["files"] = sorted(case.files)
    meta["outcome"] = asdict(o)
    (d / "case.json").write_text(json.dumps(meta, indent=1))
    return d


def replay(repro: Path) -> Outcome:
    """Run a saved reproducer again; prints and returns its outcome."""
    meta = json.loads((repro / "case.json").read_text())
    files = {rel: (repro / rel).read_bytes() for rel in meta["files"]}
    case = Case(meta["index"], meta["command"], meta["template"], meta["argv"], files, meta["specials"],
                meta["input_kind"], meta["mutation"], meta["fsize"], meta["broken_pipe"])
    runner = Runner()
    try:
        o, casedir = runner.run(case)
    finally:
        runner.close()
    print(json.dumps(asdict(o), indent=1))
    return o


if __name__ == "__main__":
    replay(Path(sys.argv[1]))
