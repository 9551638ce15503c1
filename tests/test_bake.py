"""nrpose bake: outputs equal to `nrpose pose` job by job, exactly once under faults, resumable."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from nrpose.cli import main as nrpose_main

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data (Fox, Ely, CMU BVH) is not present")

try:
    import ray
    from ray.cluster_utils import Cluster
except ImportError:
    ray = None
needs_ray = pytest.mark.skipif(ray is None, reason="Ray is not installed (pip install 'nrpose[ray]')")


def bake(argv, capsys=None) -> tuple[int, str]:
    """`nrpose bake ARGV` through nrpose.cli.main; (exit status, stderr)."""
    code = nrpose_main(["bake"] + [str(a) for a in argv])
    err = capsys.readouterr().err if capsys else ""
    return code, err


def start_bake(tmp_path: Path, argv) -> subprocess.Popen:
    """The bake in a separate driver process (for signals and killed workers)."""
    # Ctrl-C's default disposition in the driver, whatever this process inherited (a shell's
    # background job starts with SIGINT ignored, and Python then installs no handler)
    return subprocess.Popen([sys.executable, "-m", "nrpose", "bake"] + [str(a) for a in argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


# --------------------------------------------------------------------------- the job library

@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    """A tiny capsule humanoid (670 vertices) as OBJ + BVH skeleton with its walk, and a pose file."""
    from nrpose.io.bvh_write import write_bvh
    from nrpose.io.meshes import write_geometry
    from nrpose.rigs.humanoid import humanoid

    d = tmp_path_factory.mktemp("rig")
    h = humanoid(resolution=0.06)
    write_geometry(d / "human.obj", h.meshes[0].vertices, h.meshes[0].faces)
    walk = h.clip("walk")
    write_bvh(d / "walk.bvh", h.skeleton, walk.sample(np.arange(31) / 30), 1 / 30)
    (d / "bend.json").write_text(json.dumps({"rotations": {"LeftUpLeg": [0.38268343, 0, 0, 0.92387953]}}))
    return d


def library(rig: Path, fps: float = 30.0) -> dict:
    """Eight jobs: clip, motion, pose and rest; nrmls, lbs, dqs; .npz, .glb and frame directories; one bad."""
    return {"defaults": {"character": "human.obj", "skeleton": "walk.bvh", "weights": "euclidean", "clip": "walk",
                         "fps": fps},
            "jobs": [{"output": "a.npz"},
                     {"output": "b.glb", "method": "lbs"},
                     {"output": "c", "method": "dqs", "frames": "0:10:2", "format": "obj"},
                     {"output": "d.npz", "motion": "walk.bvh", "blend": "relative", "time": [0.1, 0.5]},
                     {"output": "e.npz", "rest": True},
                     {"output": "f.npz", "pose": "bend.json", "method": "lbs"},
                     {"output": "sub/g.npz", "alpha": 2.0, "fps": 60},
                     {"output": "bad.npz", "clip": "nope"}]}


def pose_argv(job: dict, defaults: dict, base: Path, out: Path) -> list[str]:
    """`nrpose pose` arguments for a job of :func:`library` (paths under ``base``)."""
    j = dict(defaults)
    if any(k in job for k in ("motion", "rest", "pose")):
        j.pop("clip")
    j.update(job)
    argv = ["pose", str(base / j["character"]), "--skeleton", str(base / j["skeleton"]), "-o", str(out)]
    for key in ("clip", "frames", "method", "weights", "blend", "format"):
        if key in j:
            argv += [f"--{key}", str(j[key])]
    for key in ("motion", "pose"):
        if key in j:
            argv += [f"--{key}", str(base / j[key])]
    argv += ["--fps", str(j["fps"])] + (["--alpha", str(j["alpha"])] if "alpha" in j else [])
    argv += (["--time"] + [str(t) for t in j["time"]] if "time" in j else []) + (["--rest"] if j.get("rest") else [])
    return argv


@pytest.fixture(scope="module")
def reference(rig, tmp_path_factory) -> Path:
    """The good jobs of the library, one by one through the pose command."""
    ref = tmp_path_factory.mktemp("reference")
    doc = library(rig)
    for job in doc["jobs"][:-1]:
        (ref / job["output"]).parent.mkdir(parents=True, exist_ok=True)
        assert nrpose_main(pose_argv(job, doc["defaults"], rig, ref / job["output"])) == 0, job
    return ref


def assert_same(out: Path, ref: Path, name: str) -> None:
    """Bitwise the same output (.npz: same arrays, bit for bit; the zip holds write times)."""
    a, b = out / name, ref / name
    if name.endswith(".npz"):
        za, zb = np.load(a), np.load(b)
        assert za.files == zb.files
        for k in za.files:
            assert za[k].dtype == zb[k].dtype and za[k].shape == zb[k].shape and za[k].tobytes() == zb[k].tobytes()
    elif a.is_dir():
        assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
        for p in b.iterdir():
            assert (a / p.name).read_bytes() == p.read_bytes(), p.name
    else:
        assert a.read_bytes() == b.read_bytes(), name


def assert_exactly_once(out: Path, outputs: list[str]) -> dict:
    """Every output present, nothing else (no scratch, no temporary), the manifest lists each once."""
    from nrpose.cli.bake.manifest import digest

    manifest = json.loads((out / "manifest.json").read_text())["outputs"]
    assert sorted(manifest) == sorted(outputs)
    expect = {"manifest.json"}
    for o in outputs:
        expect |= {f"{o}/{p.name}" for p in (out / o).iterdir()} if not Path(o).suffix else {o}
    found = {str(p.relative_to(out)) for p in out.rglob("*") if not p.is_dir()}
    assert found == expect, found ^ expect
    assert not (out / ".bake-tmp").exists()
    for name, entry in manifest.items():
        assert digest(out / name) == (entry["size"], entry["sha256"])
    return manifest


def write_jobs(path: Path, doc: dict) -> Path:
    path.write_text(json.dumps(doc))
    return path


GOOD = ["a.npz", "b.glb", "c", "d.npz", "e.npz", "f.npz", "sub/g.npz"]


# --------------------------------------------------------------------------- local pool

@pytest.mark.parametrize("workers", [1, 2])
def test_local_bake_equals_pose_command_and_bad_job_is_recorded(rig, reference, tmp_path, capsys, workers):
    jobs = write_jobs(rig / f"jobs{workers}.json", library(rig))
    out, summary = tmp_path / "out", tmp_path / "summary.json"
    code, err = bake([jobs, "-o", out, "--workers", workers, "--summary", summary], capsys)
    assert code == 1
    assert err.count("\n") == 1 and "jobs[7] (bad.npz)" in err and "no clip 'nope'" in err
    for name in GOOD:
        assert_same(out, reference, name)
    assert_exactly_once(out, GOOD)
    doc = json.loads(summary.read_text())
    rows = doc["records"]
    assert [r["status"] for r in rows] == ["done"] * 7 + ["failed"] and doc["failed"] == 1
    assert [r["frames"] for r in rows] == [31, 31, 6, 2, 1, 1, 61, 0]
    # each worker loads the character once and binds each binding once
    bindings = {("nrmls", 1.0, "quaternion"), ("lbs", 1.0, "quaternion"), ("dqs", 1.0, "quaternion"),
                ("nrmls", 1.0, "relative"), ("nrmls", 2.0, "quaternion")}
    per_worker = {}
    for r in rows[:-1]:
        per_worker.setdefault(r["worker"], []).append(r)
    assert 1 <= len(per_worker) <= workers
    for rs in per_worker.values():
        assert sum(r["load_seconds"] > 0 for r in rs) == 1
        assert sum(r["bind_seconds"] > 0 for r in rs) <= len(bindings)
    assert sum(r["bind_seconds"] > 0 for r in rows) >= len(bindings)
    if workers == 1:
        assert sum(r["bind_seconds"] > 0 for r in rows) == len(bindings)


BAD_JOBS = [
    ({"jobs": [{"output": "a.npz", "clip": "walk", "clipp": 1}]}, "jobs[0] (a.npz): unknown key 'clipp'"),
    ({"jobs": [{"output": "a.npz", "clip": "walk"}, {"output": "a.npz", "rest": True}]},
     "jobs[1] (a.npz): writes the same output as jobs[0]"),
    ({"jobs": [{"output": "a", "clip": "walk"}, {"output": "a/x.npz", "rest": True}]},
     "jobs[1] (a/x.npz): lies inside the output of jobs[0]"),
    ({"jobs": [{"output": "a.npz", "clip": "walk", "rest": True}]}, "jobs[0] (a.npz): give exactly one of"),
    ({"jobs": [{"output": "a.npz", "clip": "walk", "motion": "missing.bvh"}]}, "give exactly one of"),
    ({"jobs": [{"output": "a.npz", "motion": "missing.bvh"}]}, "jobs[0] (a.npz): motion missing.bvh: no such file"),
    ({"jobs": [{"output": "a.npz", "clip": "walk"}, {"output": "b.npz", "clip": "walk", "character": "x.glb"}]},
     "jobs[1] (b.npz): character x.glb: no such file"),
    ({"jobs": [{"output": "../a.npz", "clip": "walk"}]}, "must be a relative name under OUTDIR"),
    ({"jobs": [{"output": "a.obj", "clip": "walk"}]}, "must end in .npz or .glb"),
    ({"jobs": [{"output": "a.npz", "clip": "walk", "method": "fast"}]}, "'method' must be one of"),
    ({"jobs": [{"output": "a.npz", "clip": "walk", "time": 0.5, "frames": "0:3"}]}, "either 'time' or 'frames'"),
    ({"jobs": [{"output": "a.npz", "rest": True, "time": 0.5}]}, "with 'rest' or 'pose' there is one frame"),
    ({"jobs": [{"output": "a.npz", "clip": "walk", "frames": "3:1"}]}, "--frames '3:1'"),
    ({"jobs": [{"output": "a.npz", "clip": "walk", "fps": 0}]}, "'fps' must be positive"),
    ({"jobs": [{"output": "a.npz", "rest": 1}]}, "'rest' must be true or false"),
    ({"jobs": [{"output": "a.npz", "clip": 7}]}, "'clip' must be a non-empty string"),
    ({"jobs": [{"output": "a.npz", "retarget": {"source": "walk.bvh", "root": "Hips"}}]},
     "'root' must be one of origin, keep, in-place"),
    ({"jobs": [{"output": "a.npz", "retarget": {"source": "walk.bvh", "root": "keep", "in_place": True}}]},
     "contradict"),
    ({"jobs": [{"output": "a.npz", "retarget": {"source": "walk.bvh", "roots": "keep"}}]}, "unknown key 'roots'"),
    ({"jobs": [{"output": "a.npz", "clip": "walk", "quantize": True}]}, "the output is not .glb"),
    ({"jobs": [{"output": "a.npz", "retarget": {"source": "walk.bvh"}}]}, "'retarget' drives a glTF character"),
    ({"defaults": {"output": "a.npz"}, "jobs": [{"output": "a.npz", "clip": "walk"}]},
     "defaults: unknown key 'output'"),
    ({"jobs": []}, "non-empty list"),
    ({"jobs": [{"output": "manifest.json", "clip": "walk"}]}, "is the bake's own"),
    ({"job": []}, "unknown key 'job'"),
    ({"jobs": [{"output": "nul\0.npz", "clip": "walk"}]}, "holds a NUL character"),
    ({"jobs": [{"output": "a.npz", "clip": "wa\0lk"}]}, "holds a NUL character"),
]


@pytest.mark.parametrize("doc,needle", BAD_JOBS, ids=[n for _, n in BAD_JOBS])
def test_malformed_jobs_exit_2_nothing_run(rig, tmp_path, capsys, doc, needle):
    full = {"defaults": {"character": "human.obj", "skeleton": "walk.bvh", **doc.get("defaults", {})},
            **{k: v for k, v in doc.items() if k != "defaults"}}
    jobs = write_jobs(rig / "bad.json", full)
    code, err = bake([jobs, "-o", tmp_path / "out"], capsys)
    assert code == 2 and err.count("\n") == 1 and needle in err, err
    assert not (tmp_path / "out").exists()


def test_unreadable_jobs_file_and_bad_options_exit_2(rig, tmp_path, capsys):
    (tmp_path / "j.json").write_text("{not json")
    assert bake([tmp_path / "j.json", "-o", tmp_path / "o"], capsys)[0] == 2
    jobs = write_jobs(rig / "one.json", {"defaults": {"character": "human.obj", "skeleton": "walk.bvh"},
                                         "jobs": [{"output": "a.npz", "rest": True}]})
    code, err = bake([jobs, "-o", tmp_path / "o", "--workers", 0], capsys)
    assert code == 2 and "--workers" in err
    (tmp_path / "file").write_text("")
    code, err = bake([jobs, "-o", tmp_path / "file"], capsys)
    assert code == 2 and "is a file" in err and not (tmp_path / "o").exists()
    # a summary over the JOBS file (or a job's input) is refused
    jobs = write_jobs(rig / "two.json", {"defaults": {"character": "human.obj", "skeleton": "walk.bvh"},
                                         "jobs": [{"output": "a.npz", "rest": True},
                                                  {"output": "b.npz", "pose": "bend.json"}]})
    before = jobs.read_bytes(), (rig / "bend.json").read_bytes()
    for target in (jobs, rig / "bend.json"):
        code, err = bake([jobs, "-o", tmp_path / "o", "--summary", target], capsys)
        assert code == 2 and "an input of the bake" in err and err.count("\n") == 1, err
    assert (jobs.read_bytes(), (rig / "bend.json").read_bytes()) == before and not (tmp_path / "o").exists()


def test_a_jobs_file_too_large_is_refused_before_it_is_read(rig, tmp_path, capsys, monkeypatch):
    """Fuzzing made an 11 GB jobs file (its jobs repeated): read whole, it ran out of memory."""
    from nrpose.io import jsonfile

    jobs = write_jobs(rig / "big.json", {"defaults": {"character": "human.obj", "skeleton": "walk.bvh"},
                                         "jobs": [{"output": "a.npz", "rest": True}]})
    monkeypatch.setattr(jsonfile, "MAX_JSON_BYTES", jobs.stat().st_size - 1)
    monkeypatch.setattr(Path, "read_text", lambda *a, **k: pytest.fail("the file was read"))
    code, err = bake([jobs, "-o", tmp_path / "o"], capsys)
    assert code == 2 and "the jobs file is 0 MB (at most 0 MB of JSON)" in err and err.count("\n") == 1, err


def test_a_workers_warnings_are_the_drivers_one_line_of_notes(rig, tmp_path, capsys, monkeypatch):
    """A warning in a worker (here: the binding cache cannot be written) reaches stderr as the
    command's single line of notes after the run, not as the worker's own two-line warning."""
    cache = tmp_path / "cache"
    cache.write_text("a file where the cache folder should be")
    monkeypatch.setenv("NRPOSE_CACHE_DIR", str(cache))
    jobs = write_jobs(rig / "warn.json", {"defaults": {"character": "human.obj", "skeleton": "walk.bvh"},
                                          "jobs": [{"output": "a.npz", "clip": "walk", "frames": "0:2",
                                                    "weights": "euclidean"}]})
    code, err = bake([jobs, "-o", tmp_path / "o"], capsys)
    assert code == 0 and err.count("\n") == 1 and "cache" in err and "Warning" not in err, err


@needs_data
def test_fox_clips_and_retargeted_bvh_equal_the_commands(tmp_path, capsys):
    fox, ely, bvh = DATA / "gltf" / "Fox.glb", DATA / "gltf" / "Ely.glb", DATA / "bvh" / "131_03.bvh"
    doc = {"jobs": [{"character": str(fox), "clip": "Run", "frames": "0:8", "output": "run.glb"},
                    {"character": str(fox), "clip": "Walk", "method": "dqs", "frames": "0:8", "output": "walk.npz"},
                    {"character": str(ely), "retarget": {"source": str(bvh), "in_place": True}, "fps": 24,
                     "frames": "0:12", "output": "ely.npz"},
                    {"character": str(ely), "retarget": {"source": str(bvh), "root": "keep"}, "method": "lbs",
                     "frames": "0:6", "output": "ely_keep.npz"}]}
    code, _ = bake([write_jobs(tmp_path / "jobs.json", doc), "-o", tmp_path / "out", "--workers", 1], capsys)
    assert code == 0
    ref = tmp_path / "ref"
    ref.mkdir()
    assert nrpose_main(["pose", str(fox), "--clip", "Run", "--frames", "0:8", "-o", str(ref / "run.glb")]) == 0
    assert nrpose_main(["pose", str(fox), "--clip", "Walk", "--method", "dqs", "--frames", "0:8",
                        "-o", str(ref / "walk.npz")]) == 0
    assert nrpose_main(["retarget", str(bvh), str(ely), "--in-place", "--fps", "24", "-o", str(ref / "r.glb")]) == 0
    assert nrpose_main(["pose", str(ref / "r.glb"), "--clip", "131_03", "--fps", "24", "--frames", "0:12",
                        "-o", str(ref / "ely.npz")]) == 0
    assert nrpose_main(["retarget", str(bvh), str(ely), "--root", "keep", "-o", str(ref / "k.glb")]) == 0
    assert nrpose_main(["pose", str(ref / "k.glb"), "--clip", "131_03", "--method", "lbs", "--frames", "0:6",
                        "-o", str(ref / "ely_keep.npz")]) == 0
    for name in ("run.glb", "walk.npz", "ely.npz", "ely_keep.npz"):
        assert_same(tmp_path / "out", ref, name)


# --------------------------------------------------------------------------- faults

#: frames per second of the heavy jobs: 2,501 frames each
HEAVY_FPS = 2500


def heavy_library(rig: Path, n: int = 14) -> dict:
    """n jobs of 2,501 frames each (seconds in all: the driver is still running when a test signals it), for killing and interrupting."""
    methods = ("nrmls", "lbs", "dqs")
    return {"defaults": {"character": "human.obj", "skeleton": "walk.bvh", "weights": "euclidean", "clip": "walk",
                         "fps": HEAVY_FPS},
            "jobs": [{"output": f"j{i:02d}.npz", "method": methods[i % 3], "alpha": 1.0 + i // 3}
                     for i in range(n)]}


@pytest.fixture(scope="module")
def heavy_reference(rig, tmp_path_factory) -> Path:
    """The jobs of :func:`heavy_library`, one by one through the pose command."""
    ref = tmp_path_factory.mktemp("heavy")
    doc = heavy_library(rig)
    for job in doc["jobs"]:
        assert nrpose_main(pose_argv(job, doc["defaults"], rig, ref / job["output"])) == 0
    return ref


def wait_for(predicate, timeout: float = 120.0, what: str = "") -> None:
    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout, f"timed out waiting for {what}"
        time.sleep(0.02)


def manifest_count(out: Path) -> int:
    try:
        return len(json.loads((out / "manifest.json").read_text())["outputs"])
    except (OSError, ValueError):
        return 0


def children(pid: int) -> list[int]:
    return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def test_killed_worker_job_redone_every_output_once(rig, heavy_reference, tmp_path):
    doc = heavy_library(rig)
    jobs = write_jobs(rig / "heavy.json", doc)
    out, summary = tmp_path / "out", tmp_path / "s.json"
    proc = start_bake(tmp_path, [jobs, "-o", out, "--workers", 2, "--summary", summary])
    wait_for(lambda: manifest_count(out) >= 1, what="a first finished job")
    victims = [p for p in children(proc.pid) if "spawn_main" in Path(f"/proc/{p}/cmdline").read_text()]
    assert victims
    for victim in victims:      # every worker: at least one holds a job in flight
        os.kill(victim, signal.SIGKILL)
    _, err = proc.communicate(timeout=180)
    assert proc.returncode == 0, err
    names = [j["output"] for j in doc["jobs"]]
    assert_exactly_once(out, names)
    rows = json.loads(summary.read_text())["records"]
    assert all(r["status"] == "done" for r in rows)
    assert max(r["attempts"] for r in rows) == 2      # the killed worker's job, run again
    for name in names:
        assert_same(out, heavy_reference, name)


def test_sigint_then_resume_runs_only_unfinished_jobs(rig, heavy_reference, tmp_path):
    doc = heavy_library(rig)
    jobs = write_jobs(rig / "heavy2.json", doc)
    out, summary = tmp_path / "out", tmp_path / "s.json"
    proc = start_bake(tmp_path, [jobs, "-o", out, "--workers", 2])
    wait_for(lambda: manifest_count(out) >= 1, what="a finished job")
    proc.send_signal(signal.SIGINT)
    stdout, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "--resume" in err and "Traceback" not in err, err
    first = json.loads((out / "manifest.json").read_text())["outputs"]
    assert 1 <= len(first) < len(doc["jobs"])
    assert not (out / ".bake-tmp").exists()
    stamps = {name: (out / name).stat().st_mtime_ns for name in first}
    code, err = bake([jobs, "-o", out, "--resume", "--summary", summary])
    assert code == 0, err
    rows = json.loads(summary.read_text())["records"]
    assert {r["output"] for r in rows if r["status"] == "already done"} == set(first)
    assert {r["output"] for r in rows if r["status"] == "done"} == {j["output"] for j in doc["jobs"]} - set(first)
    assert all((out / name).stat().st_mtime_ns == t for name, t in stamps.items())
    names = [j["output"] for j in doc["jobs"]]
    manifest = assert_exactly_once(out, names)
    assert all(manifest[n] == first[n] for n in first)
    # a changed output on disk, or changed options, is not "already done"
    (out / names[-1]).write_bytes(b"truncated")
    code, _ = bake([jobs, "-o", out, "--resume", "--summary", summary])
    rows = json.loads(summary.read_text())["records"]
    assert code == 0 and [r["output"] for r in rows if r["status"] == "done"] == [names[-1]]
    for name in names:
        assert_same(out, heavy_reference, name)


# --------------------------------------------------------------------------- Ray

def ray_workers() -> list[int]:
    """PIDs of Ray worker processes running a pose task (Ray titles them ``ray::pose_chunk``)."""
    pids = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if (p / "cmdline").read_bytes().startswith(b"ray::pose_chunk"):
                    pids.append(int(p.name))
            except OSError:
                pass
    return pids


@needs_ray
def test_ray_local_equals_pose_command_and_survives_a_killed_worker(rig, reference, heavy_reference, tmp_path, capsys):
    doc = library(rig)
    doc["jobs"] += heavy_library(rig, 8)["jobs"]
    for j in doc["jobs"][8:]:
        j["fps"] = HEAVY_FPS
    jobs = write_jobs(rig / "ray.json", doc)
    out = tmp_path / "out"
    killed = []

    def kill_one():
        wait_for(lambda: manifest_count(out) >= 1 and ray_workers(), what="a running Ray pose task")
        killed.append(ray_workers()[0])
        os.kill(killed[0], signal.SIGKILL)

    killer = threading.Thread(target=kill_one, daemon=True)
    killer.start()
    code, err = bake([jobs, "-o", out, "--ray"], capsys)
    killer.join(5)
    assert killed and code == 1 and "jobs[7] (bad.npz)" in err
    names = GOOD + [j["output"] for j in doc["jobs"][8:]]
    assert_exactly_once(out, names)
    for name in GOOD:
        assert_same(out, reference, name)
    for name in names[len(GOOD):]:
        assert_same(out, heavy_reference, name)


@needs_ray
def test_ray_two_node_cluster_survives_a_removed_node(rig, reference, heavy_reference, tmp_path, capsys):
    doc = heavy_library(rig, 10)
    doc["jobs"] += library(rig)["jobs"][:-1]
    for j in doc["jobs"][10:]:
        j.setdefault("fps", 30)
    jobs = write_jobs(rig / "cluster.json", doc)
    out, summary = tmp_path / "out", tmp_path / "s.json"
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)
        doomed = cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()

        removed = []

        def remove_node():
            wait_for(lambda: manifest_count(out) >= 1, what="a first finished job")
            cluster.remove_node(doomed)
            removed.append(manifest_count(out))

        remover = threading.Thread(target=remove_node, daemon=True)
        remover.start()
        code, err = bake([jobs, "-o", out, "--ray", cluster.address, "--summary", summary], capsys)
        remover.join(60)
        assert code == 0, err
        assert removed and removed[0] < len(doc["jobs"])      # removed while jobs were left
    finally:
        cluster.shutdown()
    rows = json.loads(summary.read_text())["records"]
    assert all(r["status"] == "done" for r in rows)
    names = [j["output"] for j in doc["jobs"]]
    assert_exactly_once(out, names)
    for name in names[10:]:
        assert_same(out, reference, name)
    for name in names[:10]:
        assert_same(out, heavy_reference, name)


def test_second_bake_on_one_outdir_is_refused(rig, tmp_path, capsys):
    import fcntl

    jobs = write_jobs(rig / "lock.json", {"defaults": {"character": "human.obj", "skeleton": "walk.bvh"},
                                          "jobs": [{"output": "a.npz", "rest": True}]})
    out = tmp_path / "out"
    out.mkdir()
    fd = os.open(out, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)           # as a running bake's driver holds it
        code, err = bake([jobs, "-o", out], capsys)
    finally:
        os.close(fd)
    assert code == 2 and "another bake is writing there" in err and not list(out.iterdir())


def test_ray_missing_is_one_line_exit_2(rig, tmp_path, capsys, monkeypatch):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else find_spec(name, *a))
    jobs = write_jobs(rig / "noray.json", {"defaults": {"character": "human.obj", "skeleton": "walk.bvh"},
                                           "jobs": [{"output": "a.npz", "rest": True}]})
    code, err = bake([jobs, "-o", tmp_path / "out", "--ray"], capsys)
    assert code == 2 and "pip install 'nrpose[ray]'" in err and not (tmp_path / "out").exists()


def test_worker_thread_settings_share_the_cpus(monkeypatch):
    """workers × PoCL threads = CPUs, never pinned (each worker's thread i would share CPU i);
    a variable the user set is kept."""
    from nrpose.cli.bake.local import thread_settings

    for k in ("POCL_DEVICES", "POCL_MAX_PTHREAD_COUNT", "POCL_AFFINITY"):
        monkeypatch.delenv(k, raising=False)
    assert thread_settings(2, cpus=2) == {"POCL_DEVICES": "basic", "POCL_AFFINITY": "0"}
    assert thread_settings(2, cpus=8) == {"POCL_DEVICES": "pthread basic", "POCL_MAX_PTHREAD_COUNT": "3",
                                          "POCL_AFFINITY": "0"}
    assert thread_settings(3, cpus=2) == {"POCL_DEVICES": "basic", "POCL_AFFINITY": "0"}
    monkeypatch.setenv("POCL_DEVICES", "pthread")
    monkeypatch.setenv("POCL_AFFINITY", "1")
    assert thread_settings(1, cpus=4) == {}


@pytest.mark.parametrize("method", ["nrmls", "lbs"])
def test_poser_binding_ships_without_its_device_part(rig, method, monkeypatch):
    """A pickled CharacterPoser (what a Ray bind task ships) holds the host binding; unpickled it
    builds its device part without computing weights again and poses bitwise the same frames."""
    import pickle

    import nrpose.bind.bone_weights as bone_weights_module
    from nrpose.io import load_character
    from nrpose.pose.poser import CharacterPoser

    character = load_character(str(rig / "human.obj"), str(rig / "walk.bvh"))
    poser = CharacterPoser(character, method=method, weights="euclidean")
    local = character.clips[0].sample(np.arange(5) / 30.0)
    expected = poser.pose(local).positions.copy()
    shipped = pickle.dumps(poser)
    assert poser.deformer is not None       # pickling leaves the original working
    monkeypatch.setattr(bone_weights_module, "bone_weights", lambda *a, **k: pytest.fail("weights made again"))
    copy = pickle.loads(shipped)
    assert copy.deformer is not None and copy.deformer is not poser.deformer
    assert np.array_equal(copy.pose(local).positions, expected)


def test_ctrl_c_before_the_jobs_run_is_status_130(rig, tmp_path, capsys, monkeypatch):
    """Ctrl-C while the JOBS file is read (outside the runner's own handling): nrpose.cli.main
    returns 130 with one line, nothing written."""
    import nrpose.cli.bake.command as command

    def interrupted(path):
        raise KeyboardInterrupt

    monkeypatch.setattr(command, "load_jobs", interrupted)
    code, err = bake([write_jobs(rig / "ctrl_c.json", library(rig)), "-o", tmp_path / "out"], capsys)
    assert code == 130 and err == "nrpose: interrupted\n"
    assert not (tmp_path / "out").exists()
