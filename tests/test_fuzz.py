"""The CLI keeps its contract under a bounded mutation fuzz (tests/fuzzing).

1,200 deterministic cases (seed 0) over every command and input kind (24 more of bake,
fit-skin and demo, whose cases take seconds), 2 worker processes,
each case in a forked child with a 20 s CPU time and 3 GiB memory limit: every case must end
in exit 0 with a valid output or exit 2 with one stderr line and nothing left behind. The
long run is ``python bench/fuzz.py``. The harness's own parts (seeds valid, mutations
deterministic, the contract checks able to fail) are tested here too and always run.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from fuzzing.campaign import run
from fuzzing.cases import COMMANDS, Case, make_case
from fuzzing.known import MUST_REJECT, bake_files, known_cases
from fuzzing.runner import GOOD, Runner, classify
from fuzzing.seeds import BAKE_JOBS, make_seeds, shared_seeds

#: the known cases of issue 32 keep the contract (its fixes have landed)
FUZZ_ENABLED = True
#: the glTF reader's known cases, and the bounded run (whose glTF seeds reach the reader), wait for
#: the type-checked io/gltf_read.py (helper fuzzgltf): set True when it is merged
GLTF_READER_CHECKED = True
CASES = 1200
WORKERS = 2
#: the commands whose cases take seconds (a worker pool, a fit, the demo's two rigs): a run of
#: their own, of NEW_CASES cases, beside the CASES cases of the others
SLOW = ("bake", "fit-skin", "demo")
NEW_CASES = 24


def _warm_kernel_cache(seeds, folder) -> None:
    """Build the OpenCL kernels the seeds use once, without the per-case time limit (a cold
    PoCL cache takes longer than a case may), so that cases time their own work only."""
    for name, data in ((s.name, s.data) for s in seeds.values() if s.kind in ("obj", "handles", "glb")):
        (folder / name).write_bytes(data)
    for argv in (["deform", "body.obj", "-H", "handles.json", "-o", "o.ply"],
                 ["pose", "body.glb", "--clip", "bend", "--fps", "5", "-o", "o.npz", "--method", "nrmls"],
                 ["pose", "body.glb", "--clip", "bend", "--fps", "5", "-o", "o.npz", "--method", "lbs"],
                 ["pose", "body.glb", "--clip", "bend", "--fps", "5", "-o", "o.npz"]):
        subprocess.run([sys.executable, "-m", "nrpose", *argv], cwd=folder, capture_output=True, timeout=600)


@pytest.fixture(scope="module")
def runner(seeds, tmp_path_factory):
    _warm_kernel_cache(seeds, tmp_path_factory.mktemp("warm"))
    r = Runner()
    yield r
    r.close()


@pytest.fixture(scope="module")
def seeds():
    return make_seeds()


def _case(argv, files, **kw) -> Case:
    return Case(index=0, command=argv[0], template="unit", argv=argv, files=files, **kw)


SEED_RUNS = {
    "deform": ["deform", "in/m/body.obj", "-H", "in/h/handles.json", "-o", "out/o.ply", "--backend", "numpy"],
    "pose-glb": ["pose", "in/c/body.glb", "--clip", "bend", "--fps", "5", "-o", "out/o.npz", "--backend", "numpy"],
    "pose-tgf": ["pose", "in/m/body.obj", "--skeleton", "in/s/rig.tgf", "--pose", "in/p/pose.dmat",
                 "--weights", "euclidean", "-o", "out/frames", "--backend", "numpy"],
    "weights": ["weights", "in/c/body.gltf", "--method", "euclidean", "-o", "out/w.npz"],
    "retarget": ["retarget", "in/s/rig.bvh", "in/c/body.glb", "--fps", "5", "-o", "out/r.glb"],
    "info": ["info", "in/c/body.glb"],
    "fit-skin": ["fit-skin", "in/c/body.glb", "--train", "bend", "in/t/rig.bvh", "in/p/pose.json", "--holdout",
                 "bend", "--export", "in/t/rig.bvh", "--rom-degrees", "10", "--fps", "5", "-o", "out/f.glb",
                 "--report", "out/r.json"],
    "fit-skin-tgf": ["fit-skin", "in/m/body.obj", "--skeleton", "in/s/rig.tgf", "--train", "in/p/pose.dmat",
                     "--rom-degrees", "10", "-o", "out/f.glb", "--report", "out/r.json"],
    "demo": ["demo", "--out", "out/d", "--frames", "2", "--repeat", "1"],
    "bake": ["bake", "in/j/jobs.json", "-o", "out/bake", "--workers", "1", "--summary", "out/s.json"],
}


@pytest.mark.parametrize("name", sorted(SEED_RUNS))
def test_seeds_are_accepted_with_valid_outputs(runner, seeds, name):
    argv = SEED_RUNS[name]
    outcome, _ = runner.run(_case(argv, _seed_files(seeds, argv)))
    assert outcome.outcome == "accepted", outcome


def _seed_files(seeds, argv) -> dict:
    """The input files ``argv`` (a SEED_RUNS entry) names, from the seeds."""
    by_name = {s.name: s for s in seeds.values() if s.kind not in ("ply_ascii", "stl_ascii", "dmat_ascii",
                                                                   "gltf_external")}
    files = {}
    for a in argv:
        if a.startswith("in/j/"):          # every job of the bake seeds, in one JOBS file
            files.update(bake_files(seeds, {}, BAKE_JOBS))
        elif a.startswith("in/"):
            files[a] = by_name[a.rsplit("/", 1)[1]].data
    return files


def test_contract_checks_can_fail(runner, seeds):
    """A run that leaves a file, one that prints two error lines and one that crashes are caught."""
    ok = seeds["obj"].data
    # an output into a missing folder: rejected cleanly
    o, _ = runner.run(_case(["deform", "in/m/body.obj", "-H", "in/h/handles.json", "-o", "nodir/o.ply"],
                            {"in/m/body.obj": ok, "in/h/handles.json": seeds["handles"].data}))
    assert o.outcome == "rejected" and o.exit == 2
    # bad JSON nested 5,000 deep: a traceback today, a clean rejection after the fix
    deep = "[" * 5000 + "]" * 5000
    o, _ = runner.run(_case(["deform", "in/m/body.obj", "-H", "in/h/handles.json", "-o", "out/o.ply"],
                            {"in/m/body.obj": ok, "in/h/handles.json": deep.encode()}))
    assert o.outcome in ("traceback", "rejected")
    assert (o.outcome == "traceback") == ("RecursionError" in o.stderr)


def test_a_nan_word_is_a_bad_value_of_a_number_option_not_of_a_path():
    """`demo --out inf` writes a folder named inf (accepted rightly); `--frames inf` accepted is a defect."""
    def accepted(argv):
        case = Case(0, "demo", "demo", argv, input_kind="option", mutation="add")
        return classify(case, 0, "", "", "[]", False, {}, {}).classes
    assert "bad-option-accepted" not in accepted(["demo", "--out", "out/d", "--frames", "1", "--out", "inf"])
    assert "bad-option-accepted" in accepted(["demo", "--out", "out/d", "--frames", "inf"])


def test_a_hang_is_cpu_time_over_the_limit(runner, seeds):
    """A case is a hang when it spends more CPU than the limit (RLIMIT_CPU ends it), not when a
    loaded machine stretches its wall time: the fit-skin seed (~0.3 s of CPU) with a limit of 0.1 s."""
    fast = Runner(runner.root / "strict", time_limit=0.1)
    try:
        o, _ = fast.run(_case(SEED_RUNS["fit-skin"], _seed_files(seeds, SEED_RUNS["fit-skin"])))
    finally:
        fast.close()
    assert o.outcome == "hang", o


def test_cases_are_deterministic(seeds):
    a = [make_case(7, i, seeds) for i in range(400)]
    b = [make_case(7, i, seeds) for i in range(400)]
    assert [(c.argv, c.files, c.mutation) for c in a] == [(c.argv, c.files, c.mutation) for c in b]
    assert {c.command for c in a} == set(COMMANDS)


def test_bake_exit_1_is_checked_against_its_manifest(runner, seeds):
    """A bake with one failing job among good ones keeps the contract (exit 1, its line, the
    manifest listing the good one); the same run whose manifest lists the failed job does not."""
    jobs = [{"clip": "bend", "output": "a.npz"}, {"clip": "nope", "output": "b.npz"}]
    argv = ["bake", "in/j/jobs.json", "-o", "out/bake", "--workers", "1", "--summary", "out/s.json"]
    o, _ = runner.run(_case(argv, bake_files(seeds, {}, jobs)))
    assert (o.outcome, o.exit) == ("partial", 1), o
    assert "jobs[1] (b.npz)" in o.stderr and len(o.stderr.strip().splitlines()) == 1
    case = _case(argv + ["--max-frames", "0"], bake_files(seeds, {}, jobs))
    o, _ = runner.run(case)
    assert (o.outcome, o.exit) == ("rejected", 2), o     # a bad budget: nothing run
    from fuzzing.runner import validate
    problems = validate(["bake", "missing.json", "-o", "nodir"], 1, "", "nrpose: bake: jobs[0] (a.npz): x")
    assert problems     # no JOBS file, no manifest, no final line: the checks can fail


needs_fixes = pytest.mark.skipif(not FUZZ_ENABLED, reason="enabled after the fuzz fixes land (issue 32); "
                                "flip FUZZ_ENABLED in tests/test_fuzz.py")
needs_gltf_reader = pytest.mark.skipif(not GLTF_READER_CHECKED, reason="waits for the type-checked glTF reader "
                                       "(helper fuzzgltf); flip GLTF_READER_CHECKED in tests/test_fuzz.py")


def _reads_gltf_fields(name: str) -> bool:
    """Known cases whose fix is the glTF reader's (field types, sizes, views within buffers)."""
    return (name.startswith(("glTF ", "accessor without bufferView", "retarget: bufferView"))
            and not name.startswith("glTF nested"))


@pytest.fixture()
def fork_safe():
    """Cases fork from this process: one holding an OpenCL context already (an earlier test
    of this pytest run made one) gives children PoCL without its threads, and they hang."""
    from nrpose.device.env import context
    if context.cache_info().currsize:
        pytest.skip("an earlier test made an OpenCL context in this process; run tests/test_fuzz.py "
                    "in its own pytest process")


@needs_fixes
@pytest.mark.parametrize("name", sorted(known_cases()))
def test_issue_32_cases_keep_the_contract(runner, fork_safe, name):
    if _reads_gltf_fields(name) and not GLTF_READER_CHECKED:
        pytest.skip("waits for the type-checked glTF reader (helper fuzzgltf); flip GLTF_READER_CHECKED")
    outcome, _ = runner.run(known_cases()[name])
    allowed = ("rejected",) if name in MUST_REJECT else GOOD
    assert outcome.outcome in allowed, (outcome.outcome, outcome.stderr[-2000:], outcome.problems)


#: cases of campaigns run with --shared (seed, index), their defects fixed
FOUND = {"retarget: a clip past the reader's limit written (run K)": (2042, 4405)}


@pytest.mark.parametrize("name", sorted(FOUND))
def test_campaign_cases_keep_the_contract(runner, fork_safe, name):
    shared = shared_seeds()
    if not shared:
        pytest.skip("the campaign's cases use ../shared's assets, not found")
    outcome, _ = runner.run(make_case(*FOUND[name], make_seeds(), shared))
    assert outcome.outcome in GOOD, (outcome.outcome, outcome.stderr[-2000:], outcome.problems)


@needs_fixes
@needs_gltf_reader
@pytest.mark.parametrize("commands, count", [("fast", CASES), ("slow", NEW_CASES)])
def test_bounded_fuzz_run_breaks_no_contract(tmp_path, commands, count):
    shares = {c: p for c, p in COMMANDS.items() if (c in SLOW) == (commands == "slow")}
    summary = run(seed=0, count=count, workers=min(WORKERS, os.cpu_count() or 1), repro_dir=tmp_path / "repro",
                  commands=shares)
    assert summary["cases"] == count
    assert {c for c in summary["totals"]} == set(shares)
    defects = [{k: d[k] for k in ("class", "count", "where", "argv", "stderr_tail", "repro")}
               for d in summary["defects"]]
    assert summary["violations"] == 0, json.dumps(defects[:20], indent=1)
