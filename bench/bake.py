"""Benchmark: batch baking throughput, ``nrpose bake`` against separate ``nrpose pose`` processes.

The library (``--jobs`` ≥ 24, default 30): Fox (clips Survey, Walk, Run; methods
nrmls, nrmls with the quaternion blend, lbs, dqs: 12 jobs) and Mannequin and Ely
(their own clip, CMU 131_03 retargeted, 131_03 retargeted in place; nrmls, lbs,
dqs: 9 jobs each), all at 30 fps, the retargeted clips over frames 0:90:2 (46
frames), written as ``.npz``. Modes, each a fresh driver process timed from
start to exit (so process start, imports, PoCL start and kernel builds count
as they do for a user):

* ``separate``: each job as its own ``nrpose pose`` process, one after another;
  a retargeted job is ``nrpose retarget`` (to a .glb) then ``nrpose pose``.
* ``local1``, ``local2``: ``nrpose bake --workers 1`` / ``2``.
* ``ray_local``: ``nrpose bake --ray`` (starts a local Ray instance: its start is
  inside the time; ``ray_start_s`` is the start and stop of an empty instance).
* ``ray_cluster2``: ``nrpose bake --ray ADDRESS`` on a cluster simulated on
  this machine (``ray.cluster_utils.Cluster``: a head without CPUs and two
  one-CPU nodes), started before the timing as a real cluster would be.

Per mode: wall seconds, jobs/s, frames/s, wall per job, CPU seconds of the
driver's child processes (the driver and its workers; not a cluster's own
processes, which ``ray_cluster2`` uses); for the bakes, the sums
over jobs of their seconds, load and bind seconds (from ``--summary``). Ratios
to ``separate`` and to ``local2``. Load average and CPU steal before and after
each mode (the machine is shared). ``--rounds`` repeats every mode (median).
``--fps`` raises every job's frames (more posing and writing per job).

``overhead``: the bake machinery's cost per job, from ``--overhead`` one-frame
jobs (the Fox's rest pose, one binding) in each bake mode: wall time per job,
and the sum of the jobs' own seconds.

Usage: ``.venv/bin/python bench/bake.py [--rounds 1] [--modes ...] [--fps 30]
[--overhead 120] [--data DIR] [--json bench/results/bake.json]``.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import common  # noqa: E402

MODES = ("separate", "local1", "local2", "ray_local", "ray_cluster2")
BAKE = [sys.executable, "-m", "nrpose", "bake"]
NRPOSE = [sys.executable, "-m", "nrpose"]


def library(data: pathlib.Path, fps: int = 30) -> dict:
    """The JOBS document (module docstring); ``fps`` scales every job's frames (retargeted: 3 s, every 2nd)."""
    g, bvh = data / "gltf", str(data / "bvh" / "131_03.bvh")
    jobs = []
    for clip in ("Survey", "Walk", "Run"):
        for method, blend in (("nrmls", "relative"), ("nrmls", "quaternion"), ("lbs", None), ("dqs", None)):
            job = {"character": str(g / "Fox.glb"), "clip": clip, "method": method,
                   "output": f"fox/{clip}_{method}{'_' + blend if blend else ''}.npz"}
            jobs.append(dict(job, blend=blend) if blend else job)
    for name in ("Mannequin", "Ely"):
        for motion in ("own", "131", "131_in_place"):
            for method in ("nrmls", "lbs", "dqs"):
                job = {"character": str(g / f"{name}.glb"), "method": method,
                       "output": f"{name.lower()}/{motion}_{method}.npz"}
                if motion == "own":
                    job["clip"] = "Armature|mixamo.com|Layer0"
                else:
                    job.update(retarget={"source": bvh, "in_place": motion == "131_in_place"}, frames=f"0:{3 * fps}:2")
                jobs.append(job)
    return {"defaults": {"fps": fps}, "jobs": jobs}


def separate_commands(doc: dict, out: pathlib.Path) -> list[list[list[str]]]:
    """For each job, the command lines that make its output one process at a time."""
    runs = []
    for i, job in enumerate(doc["jobs"]):
        dest = out / job["output"]
        dest.parent.mkdir(parents=True, exist_ok=True)
        character, cmds = job["character"], []
        fps = str(doc["defaults"]["fps"])
        opts = ["--method", job["method"], "--fps", fps] + (["--blend", job["blend"]] if "blend" in job else [])
        if "retarget" in job:
            glb = out / f"retargeted_{i}.glb"
            cmds.append(NRPOSE + ["retarget", job["retarget"]["source"], character, "--fps", fps, "-o", str(glb)]
                        + (["--in-place"] if job["retarget"]["in_place"] else []))
            cmds.append(NRPOSE + ["pose", str(glb), "--clip", "131_03", "--frames", job["frames"]] + opts
                        + ["-o", str(dest)])
        else:
            cmds.append(NRPOSE + ["pose", character, "--clip", job["clip"]] + opts + ["-o", str(dest)])
        runs.append(cmds)
    return runs


def frames_of(out: pathlib.Path, doc: dict) -> int:
    return sum(len(np.load(out / j["output"])["times"]) for j in doc["jobs"])


def timed(cmds: list[list[str]]) -> float:
    t0 = time.perf_counter()
    for cmd in cmds:
        res = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd[:4])}...: exit {res.returncode}: {res.stderr.strip()[-300:]}")
    return time.perf_counter() - t0


def run_mode(mode: str, doc: dict, jobs_file: pathlib.Path, work: pathlib.Path, cluster_address: str | None):
    out = work / mode
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    summary = work / f"{mode}.summary.json"
    before = (common.load(), common.cpu_times())
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if mode == "separate":
        wall = timed([c for cmds in separate_commands(doc, out) for c in cmds])
        sums = None
    else:
        extra = {"local1": ["--workers", "1"], "local2": ["--workers", "2"], "ray_local": ["--ray"],
                 "ray_cluster2": ["--ray", cluster_address or ""]}[mode]
        wall = timed([BAKE + [str(jobs_file), "-o", str(out), "--summary", str(summary)] + extra])
        rows = json.loads(summary.read_text())["records"]
        assert all(r["status"] == "done" for r in rows), [r["error"] for r in rows if r["error"]]
        sums = {k: round(sum(r[k] for r in rows), 3) for k in ("seconds", "load_seconds", "bind_seconds")}
        sums["workers_or_nodes"] = len({(r["node"], r["worker"]) for r in rows})
    after = (common.load(), common.cpu_times())
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
    frames = frames_of(out, doc)
    return {"wall_s": wall, "cpu_s": round(cpu, 3), "jobs": len(doc["jobs"]), "frames": frames, "job_sums": sums,
            "load_before": before[0], "load_after": after[0], "steal_percent": common.steal_percent(before[1], after[1])}


def overhead(data: pathlib.Path, n: int, work: pathlib.Path, modes: list[str], address: str | None) -> dict:
    """Per-job cost of the bake machinery: ``n`` one-frame jobs (the Fox's rest pose, one binding):
    wall seconds per job, and per job minus the job's own seconds."""
    doc = {"defaults": {"character": str(data / "gltf" / "Fox.glb"), "rest": True},
           "jobs": [{"output": f"rest_{i:04d}.npz"} for i in range(n)]}
    jobs_file = work / "overhead.json"
    jobs_file.write_text(json.dumps(doc))
    out = {}
    for m in modes:
        r = run_mode(m, doc, jobs_file, work / "overhead", address)
        out[m] = {"jobs": n, "wall_s": round(r["wall_s"], 3), "wall_per_job_ms": round(1e3 * r["wall_s"] / n, 2),
                  "job_seconds_sum": r["job_sums"]["seconds"], "load_before": r["load_before"]}
        print(f"overhead {m}: {r['wall_s']:.1f} s for {n} jobs", flush=True)
    return out


def ray_start_seconds() -> float:
    code = ("import logging, ray; ray.init(address='local', include_dashboard=False, log_to_driver=False, "
            "logging_level=logging.ERROR); ray.shutdown()")
    return timed([[sys.executable, "-c", code]])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=1, help="times every mode runs (median; default 1)")
    ap.add_argument("--modes", default=",".join(MODES), help=f"comma-separated subset of {', '.join(MODES)}")
    ap.add_argument("--fps", type=int, default=30, help="frames per second of every job (default 30; more: "
                                                        "more posing and writing per job)")
    ap.add_argument("--overhead", type=int, default=120,
                    help="jobs of the per-job overhead library (the Fox's rest pose, one frame each; 0: skip)")
    ap.add_argument("--data", default=str(HERE.parent.parent / "shared" / "data"), help="asset folder")
    ap.add_argument("--json", default=str(HERE / "results" / "bake.json"), help="output record")
    a = ap.parse_args(argv)
    modes = [m.strip() for m in a.modes.split(",") if m.strip()]
    data = pathlib.Path(a.data)
    if set(modes) - set(MODES) or a.rounds < 1 or not data.is_dir():
        print(f"bench/bake.py: modes from {', '.join(MODES)}, --rounds >= 1, and the asset folder {data} (--data)",
              file=sys.stderr)
        return 2
    doc = library(data, a.fps)
    work = pathlib.Path(tempfile.mkdtemp(prefix="nrpose-bench-bake-"))
    cluster = None
    try:
        jobs_file = work / "jobs.json"
        jobs_file.write_text(json.dumps(doc, indent=1))
        if "ray_cluster2" in modes:
            from ray.cluster_utils import Cluster
            cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
            for _ in range(2):
                cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes()
        runs = {m: [] for m in modes}
        for r in range(a.rounds):           # modes alternate within a round: drifting load hits all
            for m in modes:
                runs[m].append(run_mode(m, doc, jobs_file, work, cluster.address if cluster else None))
                print(f"round {r + 1} {m}: {runs[m][-1]['wall_s']:.1f} s", flush=True)
        results = {}
        for m, rs in runs.items():
            wall = float(np.median([x["wall_s"] for x in rs]))
            results[m] = {"wall_s": [round(x["wall_s"], 3) for x in rs], "wall_s_median": round(wall, 3),
                          "jobs_per_s": round(rs[0]["jobs"] / wall, 3), "frames_per_s": round(rs[0]["frames"] / wall, 1),
                          "wall_per_job_s": round(wall / rs[0]["jobs"], 3), "jobs": rs[0]["jobs"],
                          "frames": rs[0]["frames"], "rounds": rs}
        ratios = {}
        for m in results:
            for base in ("separate", "local2"):
                if base in results and m != base:
                    ratios[f"{m}/{base} throughput"] = round(results[base]["wall_s_median"]
                                                             / results[m]["wall_s_median"], 2)
        record = {"benchmark": "bake (batch posing throughput)", "date": common.now(), "git": common.git(),
                  "environment": common.environment(), "library": doc, "results": results, "ratios": ratios}
        if a.overhead:
            record["overhead"] = overhead(data, a.overhead, work, [m for m in modes if m != "separate"],
                                          cluster.address if cluster else None)
        if "ray_local" in modes:
            record["ray_start_s"] = round(ray_start_seconds(), 2)
    finally:
        if cluster is not None:
            cluster.shutdown()
        shutil.rmtree(work, ignore_errors=True)
    common.write_record(record, a.json)
    for m, res in results.items():
        print(f"{m:>13}: {res['wall_s_median']:7.1f} s  {res['jobs_per_s']:6.2f} jobs/s  "
              f"{res['frames_per_s']:8.1f} frames/s")
    for k, v in ratios.items():
        print(f"{k}: {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
